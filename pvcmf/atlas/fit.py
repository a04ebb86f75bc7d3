"""The facial muscle atlas (:class:`Atlas`) and its fitting to a patient (paper 000, sec. II).

Fitting to a patient is a 3-D thin-plate spline (:mod:`pvcmf.tps`, scipy
``RBFInterpolator``) from the atlas landmarks to the patient's (:meth:`Atlas.warp`, the
paper's method). :meth:`Atlas.register` refines it with the patient's label image: the
spline keeps the landmarks exact and also carries atlas skin and skull points onto the
patient's surfaces (regularised, point-to-plane closest points), so the soft-tissue
thickness between landmarks follows the patient. Without patient landmarks,
:meth:`Atlas.fit` finds them: a similarity ICP (scale, rotation, translation; Umeyama
and point-to-plane steps on ``scipy.spatial.cKDTree`` closest points) of the atlas skin
and skull to the patient's (see :mod:`pvcmf.atlas.surfaces`), a non-rigid ICP with
regularised thin-plate splines of decreasing smoothing, then the atlas landmarks carried
over and snapped onto the patient's skin or bone.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from .. import arrays
from ..tps import ThinPlateSpline, landmark_arrays
from .surfaces import (FIT_SPACING, _downsample, _PatientSurfaces, _plane_step, _symmetric_goal,
                       _umeyama, _unique_rows)

log = logging.getLogger("pvcmf.atlas")


@dataclass
class FitInfo:
    """Diagnostics of :meth:`Atlas.fit` / :meth:`Atlas.register` (distances in mm).

    ``rms_*`` are RMS point-to-plane distances of the atlas skin/skull control points to
    the patient's after the similarity, the non-rigid fit, the landmark spline and the
    refinement."""

    scale: float = 1.0
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rms_similarity: float = np.nan
    rms_nonrigid: float = np.nan
    rms_landmarks: float = np.nan
    rms_refined: float = np.nan
    n_control: int = 0
    seconds: float = 0.0


# --------------------------------------------------------------------------- atlas
@dataclass
class Atlas:
    """A facial muscle atlas: landmarks, muscle surfaces and template skin/skull.

    Parameters
    ----------
    landmarks : dict[str, numpy.ndarray]
        Landmark name -> (3,) position in the atlas frame (mm).
    muscles : dict[str, pyvista.PolyData]
        Muscle name (:data:`pvcmf.arrays.MUSCLES`) -> closed triangulated surface.
    skin, skull : pyvista.PolyData, optional
        Template surfaces used by :meth:`fit` (automatic fitting needs them).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.atlas import Atlas
    >>> lm = {"a": (0, 0, 0), "b": (50, 0, 0), "c": (0, 50, 0), "d": (0, 0, 50), "e": (20, 20, 20)}
    >>> at = Atlas(lm, {"masseter_left": pv.Sphere(center=(10, 10, 10), radius=3)})
    >>> moved = at.warp({k: np.add(v, 5.0) for k, v in lm.items()})
    >>> np.round(moved.muscles["masseter_left"].center, 6).tolist()
    [15.0, 15.0, 15.0]
    """

    landmarks: dict
    muscles: dict
    skin: pv.PolyData | None = None
    skull: pv.PolyData | None = None

    def __post_init__(self):
        self.landmarks = {k: np.asarray(v, dtype=float).reshape(3) for k, v in self.landmarks.items()}
        unknown = [m for m in self.muscles if m not in arrays.MUSCLE_IDS]
        if unknown:
            raise ValueError(
                f"muscles: unknown names {unknown}; expected names of arrays.MUSCLES"
            )
        for name, surf in self.muscles.items():
            if not isinstance(surf, pv.PolyData):
                raise TypeError(f"muscles[{name!r}] must be a PolyData, got {type(surf).__name__}")
            if not surf.is_all_triangles:  # keep the triangles only (drop stray lines/verts)
                tri = surf.triangulate()
                self.muscles[name] = pv.PolyData(tri.points, faces=tri.faces)

    # ------------------------------------------------------------------ basics
    @property
    def names(self):
        """Landmark names, in order."""
        return list(self.landmarks)

    def copy(self):
        """Deep copy (surfaces copied)."""
        return Atlas(
            {k: v.copy() for k, v in self.landmarks.items()},
            {k: v.copy() for k, v in self.muscles.items()},
            None if self.skin is None else self.skin.copy(),
            None if self.skull is None else self.skull.copy(),
        )

    def transform_to(self, landmarks, *, smoothing=0.0):
        """Thin-plate spline from the atlas landmarks to ``landmarks`` (patient frame).

        ``landmarks`` must hold every atlas landmark name (extra names are ignored); a
        missing name, a NaN or coincident points raise ``ValueError`` naming them.
        """
        if not isinstance(landmarks, dict):
            raise TypeError(
                f"landmarks must be a dict name -> (x, y, z), got {type(landmarks).__name__}"
            )
        return ThinPlateSpline(self.landmarks, landmarks, smoothing=smoothing)

    def warp(self, landmarks):
        """The atlas carried to the patient: a new Atlas in the patient frame.

        Parameters
        ----------
        landmarks : dict[str, array_like]
            Patient landmarks with every atlas name.
        """
        t = self.transform_to(landmarks)
        return Atlas(
            {k: np.asarray(landmarks[k], dtype=float) for k in self.landmarks},
            {k: t.warp(v) for k, v in self.muscles.items()},
            None if self.skin is None else t.warp(self.skin),
            None if self.skull is None else t.warp(self.skull),
        )

    def landmark_kinds(self, tol=3.0):
        """``{name: 'skin' | 'bone' | 'inner'}``: the template surface a landmark lies on."""
        out = {}
        pts = np.array(list(self.landmarks.values()))
        ds = cKDTree(self.skin.points).query(pts)[0] if self.skin is not None else np.full(len(pts), np.inf)
        db = cKDTree(self.skull.points).query(pts)[0] if self.skull is not None else np.full(len(pts), np.inf)
        for name, a, b in zip(self.landmarks, ds, db):
            out[name] = "inner" if min(a, b) > tol else ("skin" if a <= b else "bone")
        return out

    def apply(self, transform, *, surfaces=True):
        """A new Atlas with every point mapped by ``transform`` ((n, 3) -> (n, 3)).

        ``surfaces=False`` maps the landmarks and muscles only (skin/skull dropped)."""

        def move(ds):
            out = ds.copy()
            out.points = transform(np.asarray(ds.points))
            return out

        names = self.names
        pts = transform(np.array([self.landmarks[n] for n in names]))
        return Atlas(
            dict(zip(names, pts)),
            {k: move(v) for k, v in self.muscles.items()},
            None if self.skin is None or not surfaces else move(self.skin),
            None if self.skull is None or not surfaces else move(self.skull),
        )

    # ------------------------------------------------------------------ registration
    def _controls(self, n):
        """About ``n`` atlas skin and skull points, evenly spread, and their class (0/1)."""
        key = (int(n), self.skin.n_points, self.skull.n_points)
        cache = self.__dict__.setdefault("_control_cache", {})
        if key not in cache:
            cache.clear()
            cache[key] = self._make_controls(n)
        pts, classes = cache[key]
        return pts.copy(), classes.copy()

    def _make_controls(self, n, margin=20.0, coarse=2.5):
        """Control points: ``coarse`` times sparser away from the muscles (``margin`` mm
        around their bounding box) than near them, about ``n`` in all."""
        lo = np.min([m.bounds[::2] for m in self.muscles.values()], axis=0) - margin
        hi = np.max([m.bounds[1::2] for m in self.muscles.values()], axis=0) + margin
        surfs = [np.asarray(self.skin.points), np.asarray(self.skull.points)]
        near = [((p >= lo) & (p <= hi)).all(axis=1) for p in surfs]
        area = self.skin.area + self.skull.area
        frac = sum(m.sum() for m in near) / sum(len(p) for p in surfs)
        cell = float(np.sqrt(area * (frac + (1 - frac) / coarse**2) / max(int(n), 10)))
        pts = [
            np.vstack([_downsample(p[m], cell), _downsample(p[~m], coarse * cell)])
            for p, m in zip(surfs, near)
        ]
        classes = np.concatenate([np.zeros(len(pts[0]), int), np.ones(len(pts[1]), int)])
        # where bone reaches the skin both surfaces hold the same points: keep one
        return _unique_rows(np.vstack(pts), classes, 0.25 * cell)

    def register(
        self,
        labels,
        landmarks=None,
        *,
        spacing=FIT_SPACING,
        n_control=1200,
        smoothing=(1000.0, 300.0, 100.0),
        iterations=3,
        max_distance=8.0,
        progress_bar=False,
    ):
        """Thin-plate spline from the atlas to a patient's label image.

        With ``landmarks`` the spline passes exactly through them and is refined so that
        the atlas skin and skull land on the patient's (point-to-plane closest points of
        about ``n_control`` atlas surface points, regularised by ``smoothing``):
        the soft-tissue thickness between landmarks then follows the patient, which
        landmarks alone cannot tell. Without ``landmarks`` they are found first
        (:meth:`fit`).

        Parameters
        ----------
        labels : pyvista.ImageData
            Patient label image with point array ``tissue``.
        landmarks : dict, optional
            Patient landmarks with every atlas name.
        spacing : float
            Spacing (mm) the patient surfaces are contoured at.
        n_control : int
            About how many atlas skin/skull control points drive the refinement.
        smoothing : sequence of float
            Smoothing (mm) of the control points, one refinement round per value; empty
            for the landmark spline alone.
        iterations : int
            Closest-point updates per round.
        max_distance : float
            Control points farther than this (mm) from the patient surface are ignored.
        progress_bar : bool
            Log the steps at INFO level.

        Returns
        -------
        transform : pvcmf.tps.ThinPlateSpline
            Atlas frame -> patient frame (``transform.warp(dataset)``).
        landmarks : dict
            The patient landmarks used (given or found).
        info : FitInfo
            Residuals (mm) and timing.
        """
        say = log.info if progress_bar else log.debug
        t0 = time.perf_counter()
        if self.skin is None or self.skull is None:
            raise ValueError("atlas registration needs an atlas with skin and skull surfaces")
        target = _PatientSurfaces(labels, spacing)
        if landmarks is None:
            landmarks, info = self._fit(target, progress_bar=progress_bar)
        else:
            info = FitInfo()
        lm_names, lm_src, lm_dst = landmark_arrays(self.landmarks, landmarks, name="landmarks")
        ctrl, classes = self._controls(n_control)
        # drop control points next to a landmark: the landmark rules there
        far = cKDTree(lm_src).query(ctrl)[0] > 2.0
        ctrl, classes = ctrl[far], classes[far]
        warp = ThinPlateSpline(lm_src, lm_dst)
        cur = warp(ctrl)
        info.rms_landmarks = target.rms(cur, classes, max_distance)
        for lam in smoothing:
            for _ in range(iterations):
                q, n, dist = target.closest(cur, classes)
                keep = dist <= max_distance
                goal = cur[keep] + (((q - cur) * n).sum(1)[:, None] * n)[keep]
                warp = ThinPlateSpline(
                    np.vstack([lm_src, ctrl[keep]]),
                    np.vstack([lm_dst, goal]),
                    smoothing=np.concatenate([np.zeros(len(lm_src)), np.full(keep.sum(), lam)]),
                    check_target=False,
                )
                cur = warp(ctrl)
            say("atlas refine: smoothing %g, rms %.2f mm", lam, target.rms(cur, classes, max_distance))
        info.rms_refined = target.rms(cur, classes, max_distance)
        info.n_control = len(ctrl)
        info.seconds = time.perf_counter() - t0
        say("atlas registration: %.2f s", info.seconds)
        return warp, {k: np.asarray(landmarks[k], dtype=float) for k in lm_names}, info

    def fit(self, labels, *, spacing=FIT_SPACING, return_info=False, progress_bar=False, **options):
        """Find the patient's landmarks automatically from a tissue label image.

        1. skin and skull of the patient (:func:`label_surfaces`);
        2. similarity ICP (scale, rotation, translation) of the atlas skin and skull onto
           them: point-to-point then point-to-plane steps from a centroid/size start;
        3. non-rigid ICP: regularised thin-plate splines through atlas surface points
           moved to their symmetric closest points, for decreasing smoothing;
        4. the atlas landmarks carried through, and skin and bone landmarks snapped onto
           the patient's skin and bone along the surface normal.

        Parameters
        ----------
        labels : pyvista.ImageData
            Patient label image with point array ``tissue`` (air, soft tissue, bone).
        spacing : float
            Spacing (mm) the surfaces are extracted at.
        return_info : bool
            Also return a :class:`FitInfo`.
        progress_bar : bool
            Log the steps at INFO level.
        **options
            ``n_control`` (1000), ``smoothing`` (schedule, mm; default (1000, 300):
            stiffer fits found the landmarks better on the virtual patients than ones
            that follow the surfaces closely), ``iterations`` per value (3), ``project``
            (bool, True).

        Returns
        -------
        dict[str, numpy.ndarray] (and FitInfo)
            Patient landmarks for :meth:`warp` / ``embed_muscles``.
        """
        if self.skin is None or self.skull is None:
            raise ValueError("automatic fitting needs an atlas with skin and skull surfaces")
        out, info = self._fit(_PatientSurfaces(labels, spacing), progress_bar=progress_bar, **options)
        return (out, info) if return_info else out

    def _fit(
        self,
        target,
        *,
        n_control=1000,
        smoothing=(1000.0, 300.0),
        iterations=3,
        project=True,
        progress_bar=False,
    ):
        say = log.info if progress_bar else log.debug
        t0 = time.perf_counter()
        src, classes = self._controls(n_control)

        # ---- similarity from a centroid / RMS-size start: point-to-point, then point-to-plane
        mov_all = np.vstack([self.skin.points, self.skull.points])
        pat_all = np.vstack(target.points)
        # heads differ by ~10 % in size: start at scale 1 (an RMS-size ratio is biased when
        # the scan crops the head); atlas points mapped outside the scan are ignored
        s, rot = 1.0, np.eye(3)
        tr = pat_all.mean(0) - mov_all.mean(0)
        for _ in range(10):
            moved = s * src @ rot.T + tr
            q, _, dist = target.closest(moved, classes)
            keep = target.inside(moved)
            keep &= dist <= np.quantile(dist[keep], 0.9)
            s, rot, tr = _umeyama(src[keep], q[keep])
        for it in range(50):
            moved = s * src @ rot.T + tr
            q, n, dist = target.closest(moved, classes)
            keep = target.inside(moved)
            keep &= dist <= np.quantile(dist[keep], 0.9)
            ds, drot, dtr = _plane_step(moved[keep], q[keep], n[keep])
            s, rot, tr = ds * s, drot @ rot, ds * drot @ tr + dtr
            if np.linalg.norm(dtr) < 1e-3 and abs(ds - 1) < 1e-5:
                break
        cur = s * src @ rot.T + tr
        info = FitInfo(scale=s, rotation=rot, translation=tr)
        info.rms_similarity = target.rms(cur, classes)
        say("atlas fit: similarity s=%.3f, rms %.2f mm (%d its)", s, info.rms_similarity, it + 1)

        # ---- non-rigid: regularised thin-plate splines through symmetric closest points
        warp = None
        for lam in smoothing:
            for _ in range(iterations):
                goal = _symmetric_goal(cur, classes, target.trees, target.sparse)
                ok = np.isfinite(goal[:, 0])
                warp = ThinPlateSpline(src[ok], goal[ok], smoothing=lam, check_target=False)
                cur = warp(src)
            say("atlas fit: smoothing %g, rms %.2f mm", lam, target.rms(cur, classes))
        info.rms_nonrigid = target.rms(cur, classes)

        names = self.names
        pts = np.array([self.landmarks[n] for n in names])
        pts = warp(pts) if warp is not None else s * pts @ rot.T + tr
        if project:
            kinds = self.landmark_kinds()
            for c, kind in enumerate(("skin", "bone")):
                sel = np.array([kinds[n] == kind for n in names])
                if sel.any():
                    cls = np.full(sel.sum(), c)
                    q, n, d = target.closest(pts[sel], cls)
                    near = (d <= 6.0)[:, None]
                    # move along the surface normal only: no sliding on the surface
                    pts[sel] = np.where(near, pts[sel] + ((q - pts[sel]) * n).sum(1)[:, None] * n, pts[sel])
        info.seconds = time.perf_counter() - t0
        say("atlas fit: %.2f s", info.seconds)
        return dict(zip(names, pts)), info
