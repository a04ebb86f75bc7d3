"""Paper 000 Fig. 2c: the muscle-embedded volumetric mesh, cut open
==================================================================

One step from the tissue + muscle label image of virtual patient 1 to a tetrahedral mesh
in which every tetrahedron lies in fat (yellow) or in one muscle (red), with element faces
on the muscle surfaces (``pvcmf.filters.tetrahedralize``: SurfaceNets multi-label
surfaces, then gmsh per region). The mesh is cut horizontally 28 mm below the origin,
through the masseters, the zygomatici and the levatores labii; the tetrahedra crossing the
cut are drawn whole and seen from above (anterior at the top, the patient's left on the
right), the mesh below as a translucent skin. The muscle volumes are the red patches of
the section, as in the paper.
"""

import os
import warnings
from pathlib import Path

import pyvista as pv

import pvcmf
from pvcmf.figures.mesh import mesh_figure

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)

labels = pvcmf.datasets.phantom(1, spacing=2.0).truth
with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # muscles thinner than the mesh would be named here
    mesh = labels.cmf.tetrahedralize(n_tets=60_000)
plotter = mesh_figure(mesh, normal=(0.0, 0.0, 1.0), origin=(0.0, 0.0, -28.0),
                      window_size=(900, 700))
plotter.screenshot(OUT / "fig2c_mesh.png")
