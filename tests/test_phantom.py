"""Virtual patients (pvcmf.datasets.phantom) and the template head (atlas head + warps).

Expected values come from published anatomy and CT physics (anatomy: soft-tissue thickness forehead ~5 mm,
cheeks 15-25 mm, lips ~12 mm, chin ~11 mm; CT: air -1000, fat ~-100, muscle ~40, bone
> 1000, teeth ~2500 HU) and from paper 000's Table II (class II / III jaw relations), not
from numbers the code printed.
"""

from __future__ import annotations

import dataclasses
import importlib

import numpy as np
import pytest
import pyvista as pv
from scipy import ndimage

import pvcmf
from pvcmf import arrays
from pvcmf.datasets import template

SPACING = 2.0
SOFT = (arrays.FAT, arrays.MUSCLE_TISSUE)
HARD = (arrays.BONE_TISSUE, arrays.TEETH)


@pytest.fixture(scope="module")
def cases():
    return {p: pvcmf.datasets.phantom(patient=p, spacing=SPACING) for p in (1, 2, 3, 4)}


def _volume(image, name):
    return np.asarray(image[name]).reshape(image.dimensions[::-1])


def _ray(case, start, direction):
    """Labels sampled every voxel along a ray (nearest voxel), air outside the image."""
    t = case.truth
    n = int(400 / case.spacing)
    pts = np.asarray(start, float) + np.arange(n)[:, None] * case.spacing * np.asarray(direction)
    ijk = np.round((pts - np.asarray(t.origin)) / case.spacing).astype(int)
    dims = np.asarray(t.dimensions)
    ok = np.all((ijk >= 0) & (ijk < dims), axis=1)
    labels = np.full(n, arrays.AIR)
    labels[ok] = np.asarray(t[arrays.TISSUE])[ijk[ok, 0] + dims[0] * (ijk[ok, 1] + dims[1] * ijk[ok, 2])]
    return labels


def _thickness(case, start, direction):
    """Soft tissue (mm) between the skin and the first bone or tooth along a ray."""
    labels = _ray(case, start, direction)
    skin = int(np.argmax(labels != arrays.AIR))
    hard = int(np.argmax(np.isin(labels, HARD)))
    assert hard > skin, "ray must meet skin before hard tissue"
    assert np.isin(labels[skin:hard], SOFT + (arrays.AIR,)).all()
    return (hard - skin) * case.spacing


def _sites(case):
    """Measurement rays from the landmarks: forehead, left cheek, upper lip, chin."""
    lm = case.landmarks
    b = np.asarray(case.truth.bounds)
    return {
        "forehead": ((0.0, b[3], lm["soft_tissue_glabella"][2] + 15.0), (0, -1, 0)),
        "cheek": ((b[1], lm["cheek_left"][1] - 18.0, lm["cheek_left"][2]), (-1, 0, 0)),
        "lips": ((0.0, b[3], lm["labrale_superius"][2] - 4.0), (0, -1, 0)),
        "chin": ((0.0, b[3], lm["pogonion"][2]), (0, -1, 0)),
    }


def _overjet(case):
    """Sagittal incisor overjet: most anterior upper minus lower tooth voxel near the midline."""
    t = case.truth
    tissue, bone = np.asarray(t[arrays.TISSUE]), np.asarray(t[arrays.BONE])
    pts = t.points
    front = {}
    for jaw in (arrays.MAXILLA, arrays.MANDIBLE):
        m = (tissue == arrays.TEETH) & (bone == jaw) & (np.abs(pts[:, 0]) < 5.0)
        front[jaw] = pts[m, 1].max()
    return front[arrays.MAXILLA] - front[arrays.MANDIBLE]


# ----------------------------------------------------------------------------- the Case
def test_case_fields_and_dtypes(cases):
    case = cases[1]
    assert isinstance(case, pvcmf.datasets.Case)
    assert case.name == "patient 1" and case.patient == 1 and case.spacing == SPACING
    assert isinstance(case.ct, pv.ImageData) and isinstance(case.truth, pv.ImageData)
    assert case.ct[arrays.CT].dtype == np.float32
    for name in (arrays.TISSUE, arrays.MUSCLE, arrays.BONE):
        assert case.truth[name].dtype == np.uint8
    assert case.ct.dimensions == case.truth.dimensions
    assert np.allclose(case.ct.origin, case.truth.origin)
    assert np.allclose(case.ct.spacing, SPACING)
    for p, c in cases.items():
        assert c.plan is pvcmf.plan.TABLE_II[p]
    assert len(case.landmarks) >= 20
    # every tissue but metal, which the virtual patients do not have
    assert (set(np.unique(case.truth[arrays.TISSUE]))
            == set(arrays.TISSUE_LABELS.values()) - {arrays.METAL})
    assert set(np.unique(case.truth[arrays.BONE])) == set(arrays.BONE_LABELS.values())


def test_bad_input_raises():
    with pytest.raises(ValueError, match="patient"):
        pvcmf.datasets.phantom(patient=5)
    with pytest.raises(ValueError, match="patient"):
        pvcmf.datasets.phantom(patient=0)
    with pytest.raises(ValueError, match="spacing"):
        pvcmf.datasets.phantom(patient=1, spacing=0.1)
    with pytest.raises(ValueError, match="spacing"):
        pvcmf.datasets.phantom(patient=1, spacing=float("nan"))
    with pytest.raises(TypeError, match="patient"):
        pvcmf.datasets.phantom(patient="1")
    with pytest.raises(TypeError, match="spacing"):
        pvcmf.datasets.phantom(patient=1, spacing="2")


def test_deterministic_and_cache_returns_copies(cases):
    again = pvcmf.datasets.phantom(patient=1, spacing=SPACING)
    assert again.ct is not cases[1].ct
    np.testing.assert_array_equal(again.ct[arrays.CT], cases[1].ct[arrays.CT])
    again.ct[arrays.CT][:] = 0.0
    again.truth[arrays.TISSUE][:] = 0
    again.landmarks["nasion"][:] = 0.0
    third = pvcmf.datasets.phantom(patient=1, spacing=SPACING)
    np.testing.assert_array_equal(third.ct[arrays.CT], cases[1].ct[arrays.CT])
    np.testing.assert_array_equal(third.truth[arrays.TISSUE], cases[1].truth[arrays.TISSUE])
    assert np.all(third.landmarks["nasion"] == cases[1].landmarks["nasion"])


def test_banded_rasterisation_is_exact():
    """Coarse-to-fine label evaluation equals evaluating every voxel."""
    for patient in (2, 3):
        warp = template.patient_warp(patient)
        grid = importlib.import_module("pvcmf.datasets.phantom")._grid_for(warp, 2.5, table=False)
        banded = template.rasterize(grid, warp, factor=2)
        full = template.rasterize(grid, warp, factor=1)
        for name in (arrays.TISSUE, arrays.MUSCLE, arrays.BONE):
            np.testing.assert_array_equal(banded[name], full[name])


# ----------------------------------------------------------------------------- anatomy
def test_patients_differ_in_size_thickness_and_jaw_relation(cases):
    volume = {p: (np.asarray(c.truth[arrays.TISSUE]) != arrays.AIR).sum() * SPACING ** 3
              for p, c in cases.items()}
    assert volume[3] > 1.15 * volume[2]
    cheek = {p: _thickness(c, *_sites(c)["cheek"]) for p, c in cases.items()}
    assert cheek[3] > cheek[2] + 3.0
    overjet = {p: _overjet(c) for p, c in cases.items()}
    # Table II corrects: P1 maxilla back 4 mm and P3 mandible forward 5.5 mm (class II,
    # large overjet); P2 maxilla forward 5 mm and P4 mandible back 3.2 mm (class III).
    assert overjet[1] > 3.0 and overjet[3] > 3.0, overjet
    assert overjet[2] < 0.0 and overjet[4] < 0.0, overjet


# real adult ranges; the upper lip (vermilion to incisor) is 11-17 mm, up to 18 in a large face
@pytest.mark.parametrize("site, lo, hi", [("forehead", 3.0, 8.0), ("cheek", 15.0, 25.0),
                                          ("lips", 9.0, 18.0), ("chin", 8.0, 15.0)])
def test_soft_tissue_thickness(cases, site, lo, hi):
    for p, case in cases.items():
        mm = _thickness(case, *_sites(case)[site])
        assert lo <= mm <= hi, f"patient {p} {site}: {mm} mm"


def test_head_structures(cases):
    for case in cases.values():
        tissue = _volume(case.truth, arrays.TISSUE)
        bone = _volume(case.truth, arrays.BONE)
        # the vault is closed: filling the bone's holes finds the braincase
        filled = ndimage.binary_fill_holes(bone > 0)
        brain = tissue == arrays.INTRACRANIAL
        assert filled[brain].mean() > 0.99
        # air cavities inside the head (sinuses, nasal cavity, airway)
        head = ndimage.binary_fill_holes(tissue != arrays.AIR)
        assert (head & (tissue == arrays.AIR)).sum() * SPACING ** 3 > 20_000
        # teeth belong to the jaws; maxilla and mandible never touch
        teeth = tissue == arrays.TEETH
        assert set(np.unique(bone[teeth])) == {arrays.MAXILLA, arrays.MANDIBLE}
        assert not (ndimage.binary_dilation(bone == arrays.MAXILLA) & (bone == arrays.MANDIBLE)).any()
        # head and table are separate components of the thresholded CT
        ct = _volume(case.ct, arrays.CT)
        comps, n = ndimage.label(ct > -400)
        head_comp = np.bincount(comps[tissue != arrays.AIR]).argmax()
        table = (ct > -400) & (tissue == arrays.AIR) & (comps != head_comp)
        assert n >= 2 and table.sum() > 1000
        # a few voxels of air margin on every side except the table's
        assert (tissue[:3] == arrays.AIR).all() and (tissue[-3:] == arrays.AIR).all()
        assert (tissue[:, :, :3] == arrays.AIR).all() and (tissue[:, :, -3:] == arrays.AIR).all()
        assert (tissue[:, -3:] == arrays.AIR).all()


def test_hounsfield_units(cases):
    documented = {arrays.AIR: (-1000, 30), arrays.FAT: (-100, 20), arrays.MUSCLE_TISSUE: (40, 15),
                  arrays.INTRACRANIAL: (35, 15)}
    for case in cases.values():
        ct = np.asarray(case.ct[arrays.CT])
        tissue = np.asarray(case.truth[arrays.TISSUE])
        for label, (hu, tol) in documented.items():
            assert abs(np.median(ct[tissue == label]) - hu) < tol, label
        bone = ct[tissue == arrays.BONE_TISSUE]
        assert np.median(bone) > 1000 and np.percentile(bone, 2) > 400
        assert np.median(ct[tissue == arrays.TEETH]) > 1800
        air = ct[(tissue == arrays.AIR) & (np.abs(ct) > 0)]
        assert 10 < np.std(air[air < -900]) < 30  # noise


def test_muscles_in_soft_tissue(cases):
    for case in cases.values():
        muscle = np.asarray(case.truth[arrays.MUSCLE])
        tissue = np.asarray(case.truth[arrays.TISSUE])
        assert set(np.unique(muscle)) == {0, *arrays.MUSCLE_IDS.values()}
        assert (tissue[muscle > 0] == arrays.MUSCLE_TISSUE).all()
    # the analytic template muscles lie (>= 95 % of their volume) in soft tissue
    img = template.label_image(spacing=1.5)
    tissue = np.asarray(img[arrays.TISSUE])
    pts = img.points
    for name, sdf in template.muscle_sdfs().items():
        lo, hi = sdf.bounds
        box = np.flatnonzero(np.all((pts >= lo) & (pts <= hi), axis=1))
        inside = box[template.muscle_sdf(name, pts[box]) < 0]
        assert len(inside) * 1.5 ** 3 > 300, name
        share = np.isin(tissue[inside], SOFT).mean()
        assert share >= 0.95, f"{name}: {share:.3f} in soft tissue"


def test_landmarks(cases):
    tmpl = template.landmarks()
    segments = template.landmark_segments()
    for name in ("nasion", "orbitale_left", "zygion_right", "gonion_left", "menton", "pogonion",
                 "subnasale", "pronasale", "labrale_superius", "labrale_inferius",
                 "cheilion_left", "soft_tissue_nasion", "A_point", "B_point"):
        assert name in tmpl
    # left/right pairs mirror each other in the template
    for name, p in tmpl.items():
        if name.endswith("_left"):
            q = tmpl[name[:-5] + "_right"]
            np.testing.assert_allclose(p * (-1, 1, 1), q, atol=1e-3)
    assert tmpl["pronasale"][1] > tmpl["subnasale"][1] > tmpl["A_point"][1]
    assert tmpl["nasion"][2] > tmpl["A_point"][2] > tmpl["B_point"][2] > tmpl["menton"][2]
    for case in cases.values():
        b = np.asarray(case.truth.bounds).reshape(3, 2)
        tissue = _volume(case.truth, arrays.TISSUE)
        head = ndimage.binary_fill_holes(tissue != arrays.AIR)
        hard = np.isin(tissue, HARD)
        for name, p in case.landmarks.items():
            assert p.shape == (3,) and np.isfinite(p).all()
            assert np.all(p > b[:, 0]) and np.all(p < b[:, 1]), name
            k, j, i = np.round((p - case.truth.origin) / SPACING).astype(int)[::-1]
            near = (slice(k - 1, k + 2), slice(j - 1, j + 2), slice(i - 1, i + 2))
            if segments[name] is None:  # on the skin: head and outside air within a voxel
                assert head[near].any() and not head[near].all(), name
            elif name != "sella":  # on bone or teeth
                assert hard[near].any(), name


def test_warp_round_trip():
    rng = np.random.default_rng(0)
    pts = rng.uniform((-60, -60, -100), (60, 110, 80), size=(200, 3))
    for p in (1, 2, 3, 4):
        warp = template.patient_warp(p)
        np.testing.assert_allclose(warp.inverse(warp.forward(pts)), pts, atol=1e-3)
        assert not np.allclose(warp.forward(pts), pts, atol=1.0)
    np.testing.assert_allclose(template.identity_warp().forward(pts), pts, atol=1e-9)


# ----------------------------------------------------------------------------- face shape
def test_face_proportions_match_real_face(cases):
    """Nose, lips, forehead, neck, face height/width, lower face and vault breadth of every
    patient lie within the real face's ranges (``REAL_FACE``); the atlas head's do not."""
    from pvcmf.datasets.phantom_face import REAL_FACE, face_proportions, outside_real

    assert set(REAL_FACE) == {"nose", "upper_lip", "lower_lip", "forehead", "neck",
                              "height_width", "lower_face", "vault_width"}
    for p, case in cases.items():
        assert outside_real(face_proportions(case)) == {}, p
    from pvcmf.study.cohort import virtual_patient

    atlas = dataclasses.replace(template.patient_parameters(1), face=0.0)
    plain = face_proportions(virtual_patient(atlas, cases[1].plan, spacing=SPACING))
    assert {"upper_lip", "lower_lip"} <= set(outside_real(plain)), plain
    assert plain["neck"] < face_proportions(cases[1])["neck"] - 10.0


def _artisynth_face_profile(folder):
    """Outer midline profile (z -> most anterior y, patient frame, mm, 3 mm bins) of the
    ArtiSynth face mesh (hexahedra in metres, face toward -x)."""
    nodes = {}
    for line in (folder / "face.node").read_text().splitlines():
        try:
            nodes[int(line[0:8])] = [float(line[a:a + 20]) for a in (8, 28, 48)]
        except ValueError:
            continue
    ids = np.array(list(nodes))
    xyz = np.array(list(nodes.values())) * 1000.0
    index = {k: i for i, k in enumerate(ids)}
    hexes = []
    for line in (folder / "face.elem").read_text().splitlines():
        try:
            hexes.append([index[int(line[6 * i:6 * i + 6])] for i in range(8)])
        except (ValueError, KeyError):
            continue
    points = np.column_stack([xyz[:, 1], -xyz[:, 0], xyz[:, 2]])
    grid = pv.UnstructuredGrid({pv.CellType.HEXAHEDRON: np.array(hexes)}, points)
    cut = grid.extract_surface(algorithm="dataset_surface").slice(normal="x",
                                                                  origin=(0.7, 0, 0)).points
    z = np.round(cut[:, 2] / 3.0) * 3.0
    return {float(v): float(cut[z == v, 1].max()) for v in np.unique(z)}


def test_real_face_ranges_hold_the_artisynth_face(data_dir):
    """The nose and upper-lip ranges of ``REAL_FACE`` hold the real (ArtiSynth) face's
    values measured on its mesh: pronasale ahead of subnasale, labrale superius ahead of
    subnasale."""
    from pvcmf.datasets.phantom_face import REAL_FACE

    folder = data_dir / "artisynth_badinface"
    if not (folder / "face.node").exists():
        pytest.skip("artisynth_badinface not in the data folder")
    profile = _artisynth_face_profile(folder)
    z = np.array(list(profile))
    y = np.array(list(profile.values()))
    tip = int(np.argmax(y))
    below = (z <= z[tip] - 15.0) & (z >= z[tip] - 40.0)
    subnasale = float(y[below].min())
    lip = (z <= z[tip] - 30.0) & (z >= z[tip] - 45.0)
    nose, upper_lip = float(y[tip]) - subnasale, float(y[lip].max()) - subnasale
    assert REAL_FACE["nose"][0] <= nose <= REAL_FACE["nose"][1], nose
    assert REAL_FACE["upper_lip"][0] <= upper_lip <= REAL_FACE["upper_lip"][1], upper_lip
    # the atlas head's upper lip barely projects: outside the real range
    atlas = template.landmarks()
    assert atlas["labrale_superius"][1] - atlas["subnasale"][1] < REAL_FACE["upper_lip"][0]


def test_face_shape_is_invertible():
    from pvcmf.datasets.template.face import FaceShape

    rng = np.random.default_rng(1)
    pts = rng.uniform((-110, -120, -200), (110, 150, 140), size=(50_000, 3))
    for nose in (0.85, 1.0, 1.15):
        shape = FaceShape(1.0, nose)
        assert shape.jacobian_determinant(pts).min() > 0.25
        np.testing.assert_allclose(shape.inverse(shape.forward(pts)), pts, atol=1e-4)
    np.testing.assert_array_equal(FaceShape(0.0).forward(pts), pts)
    # the face moves: lips forward, neck longer
    moved = FaceShape(1.0).forward([[0.0, 104.6, -52.0], [0.0, 0.0, -145.0]])
    assert moved[0, 1] > 108.0 and moved[1, 2] < -160.0


def test_soft_tissue_covers_skeleton(cases):
    """Positive soft-tissue thickness everywhere: no bone or tooth voxel within a voxel of
    the air outside the head."""
    for p, case in cases.items():
        tissue = _volume(case.truth, arrays.TISSUE)
        lab, _ = ndimage.label(tissue == arrays.AIR)
        outside = lab == lab[0, 0, 0]
        depth = ndimage.distance_transform_edt(~outside, sampling=SPACING)
        assert depth[np.isin(tissue, HARD)].min() >= SPACING, p


def test_cohort_faces_vary_with_the_seed():
    from pvcmf.study.cohort import cohort_parameters

    noses = {round(template.PatientWarp(p).shape.nose, 6) for p, _ in cohort_parameters(6, 2)}
    assert len(noses) == 6 and all(0.85 <= v <= 1.15 for v in noses)
    assert template.identity_warp().shape.strength == 0.0


# ----------------------------------------------------------------------------- template
def test_template_muscle_surfaces_closed_and_oriented():
    surfaces = template.muscle_surfaces(spacing=0.75)
    assert list(surfaces) == list(arrays.MUSCLES)
    for name, surf in surfaces.items():
        assert surf.n_cells > 100, name
        assert surf.is_all_triangles
        assert surf.n_open_edges == 0, name
        assert surf.is_manifold, name
        # outward orientation: the divergence-theorem volume of the triangles is positive
        tri = surf.points[surf.regular_faces]
        signed = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
        assert signed > 0 and abs(signed - surf.volume) < 0.01 * surf.volume, name
        assert 300 < surf.volume < 40_000, (name, surf.volume)
    with pytest.raises(ValueError, match="spacing"):
        template.muscle_surfaces(spacing=5.0)
    with pytest.raises(ValueError, match="name"):
        template.muscle_sdf("buccinator_left", np.zeros((1, 3)))


def test_template_label_image_matches_patient_layout():
    img = template.label_image(spacing=4.0)
    assert sorted(img.point_data.keys()) == sorted([arrays.TISSUE, arrays.MUSCLE, arrays.BONE])
    for name in img.point_data.keys():
        assert img[name].dtype == np.uint8


# ----------------------------------------------------------------------------- figure
def test_virtual_patient_render(cases, verify_image_cache):
    """Skin translucent, skull segments and the 12 muscles of patient 1 (front, right)."""
    from pvcmf.figures.patient import virtual_patient

    pl = virtual_patient(cases[1], window_size=(800, 420))
    pl.show()
    with pytest.raises(ValueError, match="views"):
        virtual_patient(cases[1], views=("top",))


def test_virtual_patient_right_view_is_a_photograph(cases):
    """The 'right' view shows the patient's right side as a photograph does: the face
    toward the viewer's right, so the (green) mandible lies in the right part of the head."""
    from pvcmf.figures.patient import virtual_patient

    pl = virtual_patient(cases[1], views=("right",), window_size=(400, 400))
    img = np.asarray(pl.screenshot(return_img=True), dtype=int)[..., :3]
    pl.close()
    drawn = np.nonzero(np.abs(img - 255).sum(axis=-1) > 30)[1]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    green = np.nonzero((g > r + 40) & (g > b + 40))[1]  # palegreen, under the skin's tint
    assert green.size > 200
    # the mandible's front, under the face, is on the right; mirrored it sat near the middle
    assert green.mean() > drawn.min() + 0.6 * (drawn.max() - drawn.min()), (
        green.mean(), drawn.min(), drawn.max())
