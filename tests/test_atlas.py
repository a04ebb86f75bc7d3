"""The facial muscle atlas and the thin-plate spline that carries it to a patient."""

from __future__ import annotations

import re

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.atlas import Atlas, default
from pvcmf.filters import oriented_bounding_box
from pvcmf.tps import ThinPlateSpline, landmark_arrays, vtk_transform

RNG = np.random.default_rng(7)
SRC = RNG.uniform(-80, 80, (15, 3))
DST = SRC * [1.05, 0.97, 1.02] + RNG.normal(0, 3.0, SRC.shape) + [2, -1, 4]


# --------------------------------------------------------------------------- TPS
def test_tps_interpolates_landmarks_exactly():
    t = ThinPlateSpline(SRC, DST)
    np.testing.assert_allclose(t(SRC), DST, atol=1e-9)


def test_tps_is_identity_for_identical_sets():
    t = ThinPlateSpline(SRC, SRC)
    q = RNG.uniform(-150, 150, (500, 3))
    np.testing.assert_allclose(t(q), q, atol=1e-9)


def test_tps_reproduces_affine_maps_and_matches_vtk():
    a = np.array([[1.1, 0.1, 0.0], [-0.05, 0.9, 0.2], [0.0, 0.1, 1.2]])
    t = ThinPlateSpline(SRC, SRC @ a.T + [5, 6, 7])
    q = RNG.uniform(-150, 150, (300, 3))
    np.testing.assert_allclose(t(q), q @ a.T + [5, 6, 7], atol=1e-8)
    # an independent implementation: VTK's vtkThinPlateSplineTransform, basis R
    t, v = ThinPlateSpline(SRC, DST), vtk_transform(SRC, DST)
    theirs = np.array([v.TransformPoint(*p) for p in q])
    np.testing.assert_allclose(t(q), theirs, atol=1e-8)


def test_tps_warp_copies_datasets():
    sphere = pv.Sphere(radius=10)
    before = sphere.points.copy()
    moved = ThinPlateSpline(SRC, SRC + [1, 2, 3]).warp(sphere)
    np.testing.assert_allclose(moved.points, before + [1, 2, 3], atol=1e-9)
    np.testing.assert_array_equal(sphere.points, before)


def test_bad_landmarks_are_named():
    src = {f"p{i}": p for i, p in enumerate(SRC)}
    with pytest.raises(ValueError, match=r"missing 1 landmark.*'p3'"):
        landmark_arrays(src, {k: v for k, v in src.items() if k != "p3"})
    with pytest.raises(ValueError, match="p4.*NaN"):
        landmark_arrays(src, dict(src, p4=(np.nan, 0, 0)))
    with pytest.raises(ValueError, match=r"coincide.*\('p1', 'p2'\)"):
        landmark_arrays(src, dict(src, p2=src["p1"]))
    flat = {k: (v[0], v[1], 0.0) for k, v in src.items()}
    with pytest.raises(ValueError, match="coplanar"):
        landmark_arrays(flat, flat)
    with pytest.raises(ValueError, match="at least 4"):
        landmark_arrays(SRC[:3], DST[:3])
    with pytest.raises(ValueError, match="smoothing"):
        ThinPlateSpline(SRC, DST, smoothing=-1)


# --------------------------------------------------------------------------- default atlas
@pytest.fixture(scope="module")
def atlas():
    return default()


def test_default_atlas_content(atlas):
    assert isinstance(atlas, Atlas)
    assert sorted(atlas.muscles) == sorted(arrays.MUSCLES)
    assert len(atlas.landmarks) >= 20
    for name, surf in atlas.muscles.items():
        assert surf.n_open_edges == 0, name
        assert surf.is_all_triangles, name
        assert 300 < surf.volume < 40_000, name  # mm^3: thin straps up to the masseter
        side = 1 if name.endswith("_left") else -1
        assert side * surf.center[0] > 0, name  # left muscles on the patient's left (+x)
        assert surf.center[1] > 0, name  # all in the front half of the head
    for kind in arrays.MUSCLE_KINDS:  # bilateral symmetry about x = 0
        left, right = atlas.muscles[f"{kind}_left"], atlas.muscles[f"{kind}_right"]
        np.testing.assert_allclose(np.multiply(left.center, [-1, 1, 1]), right.center, atol=1.0)
    assert atlas.skin.n_points > 1000 and atlas.skull.n_points > 1000
    kinds = atlas.landmark_kinds()
    assert kinds["pronasale"] == "skin" and kinds["nasion"] == "bone"


def test_default_is_cached_but_independent(atlas):
    other = default()
    other.muscles["masseter_left"].points[:] += 100.0
    other.landmarks["nasion"][:] = 0.0
    fresh = default()
    np.testing.assert_allclose(fresh.muscles["masseter_left"].center, atlas.muscles["masseter_left"].center)
    assert np.any(fresh.landmarks["nasion"] != 0)


def test_atlas_warp_with_own_landmarks_is_identity(atlas):
    same = atlas.warp(atlas.landmarks)
    for name in ("masseter_left", "zygomaticus_major_right"):
        np.testing.assert_allclose(same.muscles[name].points, atlas.muscles[name].points, atol=1e-8)


# --------------------------------------------------------------------------- plausibility
def _badin_fibres(folder):
    """Fibre polylines of the ArtiSynth 'Badin' face, in pvcmf's frame and mm.

    The face model looks toward -x with z up (metres), so pvcmf (x left, y anterior, z up)
    = (y_badin, -x_badin, z_badin) * 1000; its fibres lie on the patient's right."""
    nodes = {}
    for line in (folder / "face_muscles_CH_with_LLS.node").read_text().splitlines():
        parts = line.split()
        if len(parts) == 4:
            nodes[int(parts[0])] = np.array([float(v) for v in parts[1:]])
    fibres = {}
    pat = re.compile(r"^\s*FIBER\((\d+),(\d+),(\d+)\)\s*=\s*(\d+)")
    for line in (folder / "face_muscles_topology_flynn.mac").read_text().splitlines():
        m = pat.match(line)
        if m:
            mus, fib, k, nid = map(int, m.groups())
            fibres.setdefault((mus, fib), []).append((k, nid))
    out = {}
    for (mus, fib), pts in fibres.items():
        ids = [nid for _, nid in sorted(pts)]
        if all(i in nodes for i in ids):
            xyz = np.array([nodes[i] for i in ids]) * 1000.0
            out.setdefault(mus, []).append(np.column_stack([xyz[:, 1], -xyz[:, 0], xyz[:, 2]]))
    return out


#: Badin muscle index (topology file) -> atlas muscle kind, and the angle allowed (deg)
BADIN = {11: ("zygomaticus_major", 35.0), 12: ("levator_labii_superioris", 30.0),
         8: ("levator_labii_superioris_alaeque_nasi", 30.0)}


def _axis_angle(u, v):
    return np.degrees(np.arccos(min(1.0, abs(float(np.dot(u, v))))))


def test_atlas_fibres_agree_with_real_face_model(atlas, data_dir):
    folder = data_dir / "artisynth_badinface"
    if not folder.is_dir():
        pytest.skip("artisynth_badinface not in the data folder")
    fibres = _badin_fibres(folder)
    angles = {}
    for mus, (kind, limit) in BADIN.items():
        # real: mean unit direction of the fibres (origin -> insertion)
        dirs = [f[-1] - f[0] for f in fibres[mus]]
        dirs = [d / np.linalg.norm(d) for d in dirs]
        real = np.mean([d * np.sign(d[2]) for d in dirs], axis=0)
        real /= np.linalg.norm(real)
        # right side, pointing up: from the mouth up and out to the patient's right (-x)
        assert real[0] < 0 or kind.endswith("nasi")
        _, axes, _ = oriented_bounding_box(atlas.muscles[f"{kind}_right"].points)
        angles[kind] = _axis_angle(axes[0], real)
        print(f"{kind}: atlas vs Badin fibre direction {angles[kind]:.1f} deg")
        assert angles[kind] < limit, (kind, angles[kind])
    # the atlas is no better than chance if its directions were random: check one pair
    # of distinct muscles differs from the real ones more than the matching pair does
    _, mass_axes, _ = oriented_bounding_box(atlas.muscles["masseter_right"].points)
    zyg = np.mean([(f[-1] - f[0]) / np.linalg.norm(f[-1] - f[0]) for f in fibres[11]], axis=0)
    assert _axis_angle(mass_axes[0], zyg / np.linalg.norm(zyg)) > angles["zygomaticus_major"]
