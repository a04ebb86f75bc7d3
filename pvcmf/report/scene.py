"""The report's interactive 3D view: skins packed into the page and a vtk.js viewer.

Which viewer
------------
The page must work offline, from one file, years later. Three maintained ways to put a
VTK scene into a web page were weighed:

* PyVista's ``Plotter.export_html`` is deprecated (0.49) in favour of trame;
* trame-vtk's standalone export (``export_vtksz`` + ``trame_vtk/tools/static_viewer.html``,
  1.0 MB of viewer) replays a render window as a fixed scene in vtk.js's
  ``OfflineLocalView``: rotate and zoom work, but the page's own script cannot reach its
  actors, so skins cannot be toggled nor the colouring switched from the page;
* VTK-WASM runs VTK's C++ renderer in WebAssembly: a larger download per page and a
  young JavaScript interface;
* vtk.js itself (Kitware, BSD-3-Clause, released on npm every few weeks; the same library
  trame-vtk's viewer is built from): its UMD build (``vtk.js`` of the npm package
  ``vtk.js``, 2.5 MB minified, 0.6 MB gzipped) is vendored gzipped in
  ``pvcmf/report/vendor/`` with its licence and inlined into each page.

vtk.js is used: it is the maintained renderer underneath the other two options, and the
page's script drives it directly (one actor per skin, visibility toggles, colour map and
colour bar, camera reset).

Packing
-------
Points are quantised to 16 bits per axis over the skin's bounding box (0.005 mm steps on
a 300 mm head, far below a CT voxel), triangles are 32-bit indices, scalars float32;
each array is gzip-compressed and base64-encoded and inflated in the browser with the
standard ``DecompressionStream``. A skin of more than ``max_points`` points is decimated
first (:meth:`pyvista.PolyData.decimate`), point arrays resampled from the nearest
original point. Delegates to numpy, :mod:`gzip` and :mod:`base64`.
"""

from __future__ import annotations

import base64
import gzip
import json
from pathlib import Path

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

__all__ = ["DEFAULT_MAX_POINTS", "VTKJS_VERSION", "colormap_stops", "pack_skin", "vtkjs_source",
           "VIEWER_JS"]

#: skins with more points are decimated before packing (keeps a report under ~10 MB)
DEFAULT_MAX_POINTS = 150_000
#: the vendored vtk.js release
VTKJS_VERSION = "37.3.1"
_VENDOR = Path(__file__).with_name("vendor")


def vtkjs_source():
    """The vendored vtk.js UMD build (text) to inline into a page."""
    return gzip.decompress((_VENDOR / "vtk.js.gz").read_bytes()).decode("utf-8")


def _b64gz(array):
    raw = np.ascontiguousarray(array).tobytes()
    return base64.b64encode(gzip.compress(raw, compresslevel=6, mtime=0)).decode("ascii")


def _triangles(skin):
    tri = skin if skin.is_all_triangles else skin.triangulate()
    if tri.n_verts or tri.n_lines or tri.n_strips:  # the view shows the triangles only
        tri = pv.PolyData(np.asarray(tri.points), faces=tri.faces)
    return tri, np.asarray(tri.regular_faces if tri.n_cells else np.empty((0, 3)), np.uint32)


def pack_skin(skin, scalars=None, *, max_points=DEFAULT_MAX_POINTS):
    """Pack a skin (and named point scalars) for the viewer.

    Parameters
    ----------
    skin : pyvista.PolyData
        Surface (triangulated here if needed).
    scalars : dict, optional
        Name -> point values (one per point of ``skin``).
    max_points : int, default DEFAULT_MAX_POINTS
        Decimate above this many points.

    Returns
    -------
    dict
        JSON-ready: ``origin``, ``step`` (dequantisation), ``points`` (uint16 x 3, in the
        display frame of :mod:`pvcmf.figures.face_views`: x -> -x, so the viewer shows the
        patient as a photograph does), ``triangles`` (uint32 x 3, wound for the reflected
        points), ``scalars`` (name -> float32, with ``range``), and ``n_points``,
        ``n_triangles``.

    Examples
    --------
    >>> import pyvista as pv
    >>> from pvcmf.report.scene import pack_skin
    >>> packed = pack_skin(pv.Sphere(), {"z": pv.Sphere().points[:, 2]})
    >>> packed["n_points"], sorted(packed["scalars"])
    (842, ['z'])
    """
    if not isinstance(skin, pv.PolyData) or skin.n_points == 0:
        raise ValueError("skin must be a non-empty pyvista.PolyData")
    scalars = {k: np.asarray(v, dtype=float).ravel() for k, v in (scalars or {}).items()}
    for name, values in scalars.items():
        if values.shape != (skin.n_points,):
            raise ValueError(f"scalars[{name!r}] must have one value per point "
                             f"({skin.n_points}), got {values.shape[0]}")
    tri, faces = _triangles(skin)
    points = np.asarray(tri.points, dtype=float)
    if tri.n_points > max_points:
        small = tri.decimate(1.0 - max_points / tri.n_points)
        _, nearest = cKDTree(points).query(small.points)
        scalars = {k: v[nearest] for k, v in scalars.items()}
        tri, faces = _triangles(small)
        points = np.asarray(tri.points, dtype=float)
    # the display frame (x -> -x): the patient frame is left-handed (x left, y anterior, z
    # superior), so drawn as it is every view is a mirror image; reflected, the front view
    # shows the patient's right on the viewer's left as a photograph does, and the
    # triangles are wound the other way so that their normals still point outward
    points = points * np.array([-1.0, 1.0, 1.0])
    faces = np.ascontiguousarray(faces[:, [0, 2, 1]])
    lo, hi = points.min(axis=0), points.max(axis=0)
    step = np.maximum(hi - lo, 1e-9) / 65535.0
    q = np.rint((points - lo) / step).astype(np.uint16)
    packed = {"n_points": int(len(points)), "n_triangles": int(len(faces)),
              "origin": lo.tolist(), "step": step.tolist(), "points": _b64gz(q),
              "triangles": _b64gz(faces), "scalars": {}}
    for name, values in scalars.items():
        finite = values[np.isfinite(values)]
        packed["scalars"][name] = {
            "values": _b64gz(values.astype(np.float32)),
            "range": [float(finite.min()), float(finite.max())] if finite.size else [0, 1]}
    return packed


def colormap_stops(cmap, n=9):
    """``n`` evenly spaced (position 0-1, r, g, b) stops of a matplotlib colour map."""
    import matplotlib

    cmap = matplotlib.colormaps[cmap] if isinstance(cmap, str) else cmap
    t = np.linspace(0.0, 1.0, n)
    return [[float(x), *map(float, cmap(x)[:3])] for x in t]


def scene_json(skins, colourings):
    """The page's scene: packed skins and colourings (name -> skin, scalar, stops, range)."""
    return json.dumps({"skins": skins, "colourings": colourings}, separators=(",", ":"))


#: the page's viewer: builds one vtk.js actor per skin; reads the scene from the JSON
#: element ``#pvcmf-scene``; sets ``data-viewer`` on <body> to "ready" or "error: ..."
VIEWER_JS = r"""
(function () {
  'use strict';
  const body = document.body;
  function fail(err) {
    body.dataset.viewer = 'error: ' + err;
    console.error('pvcmf viewer: ' + err);
  }
  async function inflate(b64) {
    const bin = atob(b64);
    const bytes = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream('gzip'));
    return new Response(stream).arrayBuffer();
  }
  async function polydata(skin) {
    const q = new Uint16Array(await inflate(skin.points));
    const pts = new Float32Array(q.length);
    for (let i = 0; i < q.length; i++) pts[i] = skin.origin[i % 3] + q[i] * skin.step[i % 3];
    const tri = new Uint32Array(await inflate(skin.triangles));
    const cells = new Uint32Array(tri.length / 3 * 4);
    for (let c = 0, j = 0; c < tri.length; c += 3) {
      cells[j++] = 3; cells[j++] = tri[c]; cells[j++] = tri[c + 1]; cells[j++] = tri[c + 2];
    }
    const pd = vtk.Common.DataModel.vtkPolyData.newInstance();
    pd.getPoints().setData(pts, 3);
    pd.getPolys().setData(cells);
    const arrays = {};
    for (const [name, s] of Object.entries(skin.scalars)) {
      arrays[name] = vtk.Common.Core.vtkDataArray.newInstance({
        name: name, numberOfComponents: 1, values: new Float32Array(await inflate(s.values))});
    }
    const normals = vtk.Filters.Core.vtkPolyDataNormals.newInstance({computeCellNormals: false});
    normals.setInputData(pd);
    const out = normals.getOutputData();
    return {pd: out, arrays: arrays};
  }
  async function main() {
    const scene = JSON.parse(document.getElementById('pvcmf-scene').textContent);
    const container = document.getElementById('viewer');
    const grw = vtk.Rendering.Misc.vtkGenericRenderWindow.newInstance({background: [1, 1, 1]});
    grw.setContainer(container);
    grw.resize();
    const renderer = grw.getRenderer();
    const rw = grw.getRenderWindow();
    const actors = {};
    for (const [name, skin] of Object.entries(scene.skins)) {
      const {pd, arrays} = await polydata(skin);
      const mapper = vtk.Rendering.Core.vtkMapper.newInstance({scalarVisibility: false});
      mapper.setInputData(pd);
      const actor = vtk.Rendering.Core.vtkActor.newInstance();
      actor.setMapper(mapper);
      actor.getProperty().setColor(...skin.color);
      actor.getProperty().setOpacity(skin.opacity);
      actor.getProperty().setSpecular(0.15);
      actor.setVisibility(skin.visible);
      renderer.addActor(actor);
      actors[name] = {actor: actor, mapper: mapper, pd: pd, arrays: arrays};
    }
    function colour(key) {
      for (const a of Object.values(actors)) a.mapper.setScalarVisibility(false);
      document.querySelectorAll('.colourbar').forEach(function (el) {
        el.hidden = el.dataset.colouring !== key; });
      const c = scene.colourings[key];
      if (c && actors[c.skin] && actors[c.skin].arrays[c.scalar]) {
        const a = actors[c.skin];
        a.pd.getPointData().setScalars(a.arrays[c.scalar]);
        const lut = vtk.Rendering.Core.vtkColorTransferFunction.newInstance();
        for (const s of c.stops) lut.addRGBPoint(c.range[0] + s[0] * (c.range[1] - c.range[0]), s[1], s[2], s[3]);
        if (c.nan) lut.setNanColor(c.nan[0], c.nan[1], c.nan[2], 1.0);
        a.mapper.setLookupTable(lut);
        a.mapper.setScalarRange(c.range[0], c.range[1]);
        a.mapper.setScalarVisibility(true);
        a.pd.modified();
      }
      rw.render();
    }
    function frontView() {
      const cam = renderer.getActiveCamera();
      renderer.resetCamera();
      const fp = cam.getFocalPoint();
      const d = cam.getDistance();
      cam.setPosition(fp[0], fp[1] + d, fp[2]);
      cam.setViewUp(0, 0, 1);
      renderer.resetCamera();
      cam.zoom(1.25);
      rw.render();
    }
    document.querySelectorAll('input[data-skin]').forEach(function (box) {
      box.addEventListener('change', function () {
        actors[box.dataset.skin].actor.setVisibility(box.checked); rw.render(); });
    });
    const select = document.getElementById('colouring');
    if (select) select.addEventListener('change', function () { colour(select.value); });
    document.getElementById('reset-view').addEventListener('click', frontView);
    window.addEventListener('resize', function () { grw.resize(); rw.render(); });
    colour(select ? select.value : '');
    frontView();
    window.pvcmfViewer = {actors: actors, renderer: renderer, renderWindow: rw, colour: colour};
    body.dataset.viewer = 'ready';
  }
  window.addEventListener('load', function () {
    if (typeof vtk === 'undefined') { fail('vtk.js did not load'); return; }
    main().catch(function (err) { fail(err && err.stack ? err.stack : err); });
  });
})();
"""
