"""segment and find_jaws on the real head CTs of PVCMF_DATA_DIR (Visible Human female and
male); skipped without the data.

At the scans' 1 mm, cropped in-slice to the head: a 2 mm copy cannot represent the
temporomandibular joint space, the sinus mucosa or the metal streaks. The female is
segmented whole (the intracranial volume); find_jaws runs on the jaw region of its labels;
the male on a crop from below the mandible to above the nose."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pytest
import pyvista as pv
from scipy import ndimage

import pvcmf
from pvcmf import arrays
from pvcmf.filters.bone_segments import occlusal_normal
from pvcmf.filters.face_axes import occlusal_axes
from pvcmf.filters.metal import streak_zone
from pvcmf.plan import Osteotomy, Plan

from ct_helpers import turned_labels


def _read(name):
    root = Path(os.environ.get("PVCMF_DATA_DIR", Path(__file__).parents[1] / ".." / "shared"
                               / "data"))
    folder = root / name
    if not folder.is_dir():
        pytest.skip(f"{folder} not found (set PVCMF_DATA_DIR to the real-data folder)")
    return pvcmf.read_ct(folder, frame="patient")


def _crop(name, z_mm):
    """The scan at full resolution, cropped in-slice to the head (10 voxels of margin) and
    axially to ``z_mm`` (mm above the first slice)."""
    ct = _read(name)
    v = np.asarray(ct[arrays.CT]).reshape(ct.dimensions, order="F")
    body = (v > -500.0).any(axis=2)
    box = []
    for axis in (0, 1):
        hit = np.flatnonzero(body.any(axis=1 - axis))
        box.append(slice(max(int(hit[0]) - 10, 0), min(int(hit[-1]) + 11, v.shape[axis])))
    dz = float(ct.spacing[2])
    box.append(slice(int(z_mm[0] / dz), min(int(z_mm[1] / dz) + 1, v.shape[2])))
    sub = v[tuple(box)]
    origin = np.asarray(ct.origin) + np.asarray(ct.spacing) * [b.start for b in box]
    img = pv.ImageData(dimensions=sub.shape, spacing=ct.spacing, origin=origin)
    img[arrays.CT] = np.ascontiguousarray(sub).ravel(order="F")
    return img


def _vol(img, name=arrays.TISSUE):
    return np.asarray(img[name]).reshape(img.dimensions, order="F")


@pytest.fixture(scope="module")
def female():
    """The whole head at 1 mm."""
    ct = _crop("vhp_female_head", (0.0, 1000.0))
    return ct, pvcmf.filters.segment(ct)


@pytest.fixture(scope="module")
def female_jaws(female):
    """The labels from the neck to above the skull base (both condyles, the nasal floor)."""
    ct, lab = female
    n = int(140.0 / lab.spacing[2])
    return ct, lab.extract_subset((0, lab.dimensions[0] - 1, 0, lab.dimensions[1] - 1, 0, n))


@pytest.fixture(scope="module")
def male():
    """1 mm, from below the mandible to above the nose (the amalgam fillings and the face
    cut flat by the field of view)."""
    ct = _crop("vhp_male_head", (40.0, 200.0))
    return ct, pvcmf.filters.segment(ct)


def test_female_intracranial_volume(female):
    _, lab = female
    litres = pvcmf.filters.segmentation.tissue_volumes(lab)["intracranial"] / 1000.0
    assert 1.1 <= litres <= 1.7


def test_female_no_soft_tissue_deep_inside_the_vault(female):
    """Inside the cranial ring of the vault slices, soft tissue lies only along the bone and
    the air (the sinus mucosa): a brain or CSF shell left outside the intracranial volume
    would be soft tissue away from both. (The scalp and temporalis outside the ring are
    thicker than that and are not counted.)"""
    _, lab = female
    t = _vol(lab)
    ic = t == arrays.INTRACRANIAL
    area = ic.sum(axis=(0, 1))
    vault = np.flatnonzero(area >= 0.5 * area.max())  # slices of the cranial vault
    soft = np.isin(t, arrays.SOFT_LABELS)
    hard = np.isin(t, arrays.HARD_LABELS)
    ring = np.zeros_like(hard)
    for k in vault:  # the few vault slices of a 2 mm copy
        ring[:, :, k] = ndimage.binary_fill_holes(hard[:, :, k] | ic[:, :, k])
    depth = ndimage.distance_transform_edt(soft | ic, sampling=lab.spacing)
    deep = soft & ring & (depth > 3.0)
    assert np.count_nonzero(deep) * np.prod(lab.spacing) < 100.0  # mm^3
    assert np.count_nonzero(ic & ring) > 0.9 * np.count_nonzero(ic[:, :, vault])


def test_male_metal_and_clipped_face(male):
    _, lab = male
    t = _vol(lab)
    assert np.count_nonzero(t == arrays.METAL) > 0
    warnings = " ".join(lab.field_data["warnings"])
    assert "anterior" in warnings and "field of view" in warnings
    assert "round field of view" not in warnings and arrays.SCAN_FOV not in lab.field_data


def test_female_nose_cut_by_the_round_field_of_view(female):
    """The female scan's reconstruction circle (125 mm across its face slices) clips the tip
    of the nose over a few centimetres of height; the male's head lies inside its circles."""
    ct, lab = female
    assert "round field of view" in " ".join(lab.field_data["warnings"])
    rows = np.asarray(lab.field_data[arrays.SCAN_FOV]).reshape(-1, 4)
    nose = rows[np.abs(rows[:, 3] - 125.0) < 2.0]
    assert len(nose) >= 15  # slices (1 mm)
    # the circle's front: the tip of the nose, the face's most anterior skin
    v = _vol(lab)
    face = np.argwhere(v != arrays.AIR)
    front = ct.origin[1] + ct.spacing[1] * face[:, 1].max()
    assert np.all(np.abs(nose[:, 2] + nose[:, 3] - front) < 3.0)


def test_male_no_hard_tissue_from_metal_streaks(male):
    """Near the amalgam fillings (the streak zone: in-plane within 30 mm, in the metal's
    slices) every hard voxel belongs to the skeleton or the dentition (hard components of
    at least 0.5 mL) or lies within 3 mm of it: bright streaks are not bone. (Away from the
    metal, small free bones are real: the hyoid, the turbinates, calcified cartilage.)"""
    _, lab = male
    t = _vol(lab)
    hard = np.isin(t, arrays.HARD_LABELS)
    comp, _ = ndimage.label(hard, np.ones((3, 3, 3), bool))
    sizes = np.bincount(comp.ravel()) * np.prod(lab.spacing)
    big = (sizes >= 500.0)[comp] & hard
    dist = ndimage.distance_transform_edt(~big, sampling=lab.spacing)
    box, zone = streak_zone(t == arrays.METAL, lab.spacing)
    assert zone.sum() > 0
    assert np.all(dist[box][hard[box] & zone] <= 3.0)


def test_female_jaws(female_jaws):
    """The female's maxilla is edentulous and her mouth open: one dental arch (the lower
    incisors and canines); the mandible is one piece with both condyles, and the maxilla is
    seeded by the alveolar ridge. At 1 mm: the joint space is thinner than 2 mm. Her few
    teeth are a row, not an arch: they give no occlusal plane to plan in (refused)."""
    _, lab = female_jaws
    jaws = pvcmf.filters.find_jaws(lab)
    with pytest.raises(ValueError, match="across their row"):
        occlusal_axes(jaws)
    bone = _vol(jaws, arrays.BONE)
    mand = bone == arrays.MANDIBLE
    _, n = ndimage.label(mand, np.ones((3, 3, 3), bool))
    assert n == 1
    vox = np.prod(lab.spacing) / 1000.0
    assert 25.0 < np.count_nonzero(mand) * vox < 60.0  # mL: an adult mandible
    teeth = _vol(lab) == arrays.TEETH
    assert np.all(mand[teeth])  # every (lower) tooth in the mandible
    # both condyles: mandible on each side of the midline up to the skull base, at least
    # 40 mm above the incisal edges
    i = np.nonzero(mand)
    xc = np.median(np.nonzero(teeth)[0])
    z_teeth = np.nonzero(teeth)[2].max()
    for side in (i[0] < xc - 20.0 / lab.spacing[0], i[0] > xc + 20.0 / lab.spacing[0]):
        assert (i[2][side].max() - z_teeth) * lab.spacing[2] > 40.0
    maxilla = bone == arrays.MAXILLA
    assert 2.0 < np.count_nonzero(maxilla) * vox < 30.0
    assert np.all(i[2].min() < np.nonzero(maxilla)[2].min())
    # a Le Fort I piece without teeth: one piece (up to crumbs of the thin sinus walls) with
    # the alveolar ridge on both sides, the hard palate back to its end and the walls above
    # it up to the cut over the nasal floor
    comp, _ = ndimage.label(maxilla, np.ones((3, 3, 3), bool))
    sizes = np.bincount(comp.ravel())[1:]
    assert sizes.max() > 0.95 * sizes.sum()
    extent = np.ptp(np.argwhere(maxilla), axis=0) * lab.spacing
    assert extent[0] > 45.0  # mm across: the ridge's both sides
    assert extent[1] > 40.0  # mm front to back: the palate to the posterior nasal spine
    # mm: the ridge of this resorbed maxilla lies about 10 mm under the nasal floor and the
    # Le Fort I cut 6 mm over it: the piece is 10-22 mm high (not up the sinus walls)
    assert 10.0 < extent[2] < 22.0


def _tongue(lab, jaws):
    """The tongue from the anatomy: soft tissue inside the dental arch (the convex hull of
    the teeth seen from above, 5 mm inside it), from 10 mm below the teeth's lowest voxel (the
    floor of the mouth lies below the roots) to the middle of the teeth's height, farther
    than 5 mm from the skeleton and the dentition (the hard components of at least 0.5 mL)."""
    from scipy.spatial import Delaunay

    t = _vol(lab)
    sp = np.asarray(lab.spacing)
    teeth = np.isin(t, (arrays.TEETH, arrays.METAL))
    ij = np.argwhere(teeth.any(axis=2))
    hull = Delaunay(ij)
    grid = np.indices(teeth.shape[:2]).reshape(2, -1).T
    inside = (hull.find_simplex(grid) >= 0).reshape(teeth.shape[:2])
    inside = ndimage.distance_transform_edt(inside, sampling=sp[:2]) > 5.0
    z = np.flatnonzero(teeth.any(axis=(0, 1)))
    z0 = max(int(z[0] - 10.0 / sp[2]), 0)
    z1 = int(0.5 * (z[0] + z[-1]))
    region = np.zeros(t.shape, dtype=bool)
    region[:, :, z0:z1 + 1] = inside[:, :, None]
    hard = np.isin(t, arrays.HARD_LABELS)
    comp, _ = ndimage.label(hard, np.ones((3, 3, 3), bool))
    big = (np.bincount(comp.ravel()) * np.prod(sp) >= 500.0)[comp] & hard
    return region & (ndimage.distance_transform_edt(~big, sampling=sp) > 5.0)


def _soft_tissue_grid(lab, step):
    """Hexahedral grid of the soft-tissue voxels of ``lab`` taken every ``step`` voxels
    (cells centred on the voxel centres), with the matching label image."""
    sub = tuple(slice(0, None, step) for _ in range(3))
    t = _vol(lab)[sub]
    bone = _vol(lab, arrays.BONE)[sub]
    sp = np.asarray(lab.spacing) * step
    labels = pv.ImageData(dimensions=t.shape, spacing=sp, origin=lab.origin)
    labels[arrays.TISSUE] = t.ravel(order="F")
    labels[arrays.BONE] = bone.ravel(order="F")
    cells = pv.ImageData(dimensions=np.array(t.shape) + 1, spacing=sp,
                         origin=np.asarray(lab.origin) - 0.5 * sp)
    cells.cell_data["soft"] = np.isin(t, arrays.SOFT_LABELS).ravel(order="F").astype(np.uint8)
    return cells.threshold(0.5, scalars="soft"), labels


def test_male_no_bone_and_no_joint_node_in_the_tongue(male):
    """Metal streaks in the tongue must not become bone: no hard label in the tongue, and
    with the mandible moved, no soft-tissue node there is glued to a moving bone."""
    _, lab = male
    t = _vol(lab)
    teeth = np.isin(t, (arrays.TEETH, arrays.METAL))
    ij = np.argwhere(teeth)
    lo = np.maximum(ij.min(axis=0) - [25, 40, 40], 0)
    hi = np.minimum(ij.max(axis=0) + [26, 11, 31], t.shape)
    jaw = lab.extract_subset((lo[0], hi[0] - 1, lo[1], hi[1] - 1, lo[2], hi[2] - 1))
    jaw = pvcmf.filters.find_jaws(jaw)
    tongue = _tongue(jaw, jaw)
    assert tongue.sum() * np.prod(jaw.spacing) > 5000.0  # mm^3: a tongue's body is 40-60 mL
    assert not np.any(np.isin(_vol(jaw)[tongue], arrays.HARD_LABELS))
    grid, labels = _soft_tissue_grid(jaw, 2)
    plan = Plan((Osteotomy("mandible", (0.0, 4.0, 0.0)),))
    bc = pvcmf.filters.apply_plan(grid, plan, labels, fixed_posterior=False)
    joint = np.asarray(bc.points)[np.asarray(bc[arrays.BC]) == arrays.BC_JOINT]
    assert len(joint) > 100
    idx = np.rint((joint - np.asarray(jaw.origin)) / np.asarray(jaw.spacing)).astype(int)
    idx = np.clip(idx, 0, np.array(tongue.shape) - 1)
    assert not np.any(tongue[tuple(idx.T)])


def _condyles_reached(mand, teeth, spacing, height=40.0):
    """Whether the mandible rises ``height`` mm above the teeth's top on both sides of the
    dentition's midline (20 mm lateral to it): both rami up to the condyles."""
    i = np.nonzero(mand)
    xc = np.median(np.nonzero(teeth)[0])
    z_teeth = np.nonzero(teeth)[2].max()
    return all(len(i[2][side]) and (i[2][side].max() - z_teeth) * spacing[2] > height
               for side in (i[0] < xc - 20.0 / spacing[0], i[0] > xc + 20.0 / spacing[0]))


def test_male_jaws_in_occlusion(male):
    """The male's teeth are in occlusion (no slice free of teeth between the arches): the
    upper teeth go to a Le Fort I maxilla, the lower ones to a mandible that is one piece
    with both condyles. In every column through the dentition the maxilla's tooth voxels
    lie above the mandible's; both arches are dentate, so each holds a good share of the
    tooth voxels."""
    _, lab = male
    bone = _vol(pvcmf.filters.find_jaws(lab), arrays.BONE)
    t = _vol(lab)
    teeth = np.isin(t, (arrays.TEETH, arrays.METAL))
    mand, maxilla = bone == arrays.MANDIBLE, bone == arrays.MAXILLA
    vox = np.prod(lab.spacing) / 1000.0
    _, n = ndimage.label(mand, np.ones((3, 3, 3), bool))
    assert n == 1
    assert _condyles_reached(mand, teeth & mand, lab.spacing, height=30.0)
    assert 25.0 < np.count_nonzero(mand) * vox < 70.0  # mL: an adult mandible
    assert 10.0 < np.count_nonzero(maxilla) * vox < 40.0  # mL: Le Fort I bone and teeth
    up, low = teeth & maxilla, teeth & mand
    assert np.count_nonzero(up | low) > 0.98 * np.count_nonzero(teeth)
    for part in (up, low):
        assert np.count_nonzero(part) > 0.3 * np.count_nonzero(teeth)
    z = np.arange(t.shape[2])[None, None, :]
    up_low = np.where(up, z, t.shape[2]).min(axis=2)  # lowest maxillary tooth voxel
    low_top = np.where(low, z, -1).max(axis=2)  # highest mandibular tooth voxel
    both = up.any(axis=2) & low.any(axis=2)
    assert both.sum() > 50
    assert np.all(up_low[both] > low_top[both])
    # the maxilla holds the hard palate: it reaches 30 mm behind the front of the upper teeth
    yi = np.nonzero(maxilla)[1]
    assert (np.nonzero(up)[1].max() - yi.min()) * lab.spacing[1] > 30.0


def _thick(ct, step):
    """The scan with every ``step``-th slice kept: a CT reconstructed in thick slices."""
    v = np.asarray(ct[arrays.CT]).reshape(ct.dimensions, order="F")[:, :, ::step]
    img = pv.ImageData(dimensions=v.shape, origin=ct.origin,
                       spacing=(ct.spacing[0], ct.spacing[1], ct.spacing[2] * step))
    img[arrays.CT] = np.ascontiguousarray(v).ravel(order="F")
    return img


@pytest.mark.parametrize("name", ["female_jaws", "male"])
def test_thick_slices_keep_the_jaws(name, request):
    """Every third slice kept (1 x 1 x 3 mm): partial volume fills the joint spaces, so the
    lower teeth's bone touches the skull. The mandible and the Le Fort I maxilla found on the
    thick slices match those of the 1 mm scan on the slices both hold: Dice >= 0.95 for the
    mandible, >= 0.9 for the maxilla (its Le Fort I level is a slice, 3 mm: a slab of about
    a tenth of its bone)."""
    ct, lab = request.getfixturevalue(name)
    fine = _vol(pvcmf.filters.find_jaws(lab), arrays.BONE)[:, :, ::3]
    coarse_lab = pvcmf.filters.segment(_thick(ct, 3))
    coarse = _vol(pvcmf.filters.find_jaws(coarse_lab), arrays.BONE)[:, :, :fine.shape[2]]
    hard = np.isin(_vol(coarse_lab), arrays.HARD_LABELS)[:, :, :fine.shape[2]]
    pieces, _ = ndimage.label(hard)
    joined = np.intersect1d(pieces[coarse == arrays.MANDIBLE], pieces[coarse == arrays.CRANIUM])
    assert joined.size, "the thick slices' mandible is not joined to the skull"
    for segment, least in ((arrays.MANDIBLE, 0.95), (arrays.MAXILLA, 0.9)):
        a, b = fine == segment, coarse == segment
        score = 2.0 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b))
        assert score >= least, f"{arrays.BONE_NAMES[segment]} Dice {score:.3f}"


def test_teeth_in_occlusion_on_slices_too_thick_are_warned(male, caplog):
    """Every fourth slice of the male (1 x 1 x 4 mm): his teeth in occlusion show no gap
    between the crowns, so the arches cannot be told apart; find_jaws says so (and takes one
    arch) instead of passing a wrong split off as a found one."""
    ct, _ = male
    lab = pvcmf.filters.segment(_thick(ct, 4))
    with caplog.at_level(logging.WARNING, logger="pvcmf"):
        pvcmf.filters.find_jaws(lab)
    assert any("no occlusal surface shows between them" in r.getMessage()
               for r in caplog.records), [r.getMessage() for r in caplog.records]


def _turned(volume, spacing, degrees, order, cval):
    """``volume`` turned ``degrees`` about the x axis through its centre (chin down for a
    negative angle)."""
    a = np.radians(degrees)
    turn = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    s = np.asarray(spacing, float)
    c = (np.asarray(volume.shape) - 1) / 2
    matrix = (turn.T * s[None, :]) / s[:, None]
    return ndimage.affine_transform(volume, matrix, offset=c - matrix @ c, order=order,
                                    cval=cval)


def test_male_scanned_chin_down(male):
    """The male's scan turned 15 degrees chin down (his arches then tilt about 30 degrees
    from the axial slices, where an axial occlusal slice or Le Fort I level cuts through
    the teeth and the palate), on a grid 40 mm wider front and back, above and below so
    that nothing leaves it: the jaws found match those of the scan as it is, turned the same
    way (Dice >= 0.9; both images are resampled), and the occlusal plane found is the
    upright one turned (within 2 degrees)."""
    ct, lab = male
    pad = ((0, 0), (40, 40), (40, 40))
    v = np.pad(_vol(ct, arrays.CT).astype(np.float32), pad, constant_values=-1024.0)
    img = pv.ImageData(dimensions=v.shape, spacing=ct.spacing, origin=ct.origin)
    img[arrays.CT] = _turned(v, ct.spacing, -15.0, 1, -1024.0).ravel(order="F")
    jaws = pvcmf.filters.find_jaws(pvcmf.filters.segment(img))
    level = pvcmf.filters.find_jaws(lab)
    # the occlusal plane (a plan's axes = "occlusal") turns with the head
    a = np.radians(-15.0)
    turn = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    normals = [occlusal_normal(jaws), turn @ occlusal_normal(level)]
    assert np.degrees(np.arccos(min(normals[0] @ normals[1], 1.0))) < 2.0, normals
    found = _vol(jaws, arrays.BONE)
    upright = np.pad(_vol(level, arrays.BONE), pad)
    upright = _turned(upright, ct.spacing, -15.0, 0, 0)
    for segment in (arrays.MANDIBLE, arrays.MAXILLA):
        a, b = found == segment, upright == segment
        score = 2.0 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b))
        assert score >= 0.9, f"{arrays.BONE_NAMES[segment]} Dice {score:.3f}"


def test_male_turned_about_his_vertical(male):
    """The male's labels (amalgam streaks, a face cut by the field of view) turned 10
    degrees about the upper arch's normal, nearest voxel: the head's mirror plane found on
    them is the upright one turned (within 1 degree), so a plan in his occlusal axes moves
    forward as his face points, not as the scanner's y axis."""
    from scipy.spatial.transform import Rotation

    _, lab = male
    normal = occlusal_normal(pvcmf.filters.find_jaws(lab))
    level = pvcmf.filters.mirror_plane(lab, normal)
    R = Rotation.from_rotvec(np.radians(10.0) * normal).as_matrix()
    turned = turned_labels(lab, R, pad=30)
    found = pvcmf.filters.mirror_plane(turned, R @ normal)
    angle = np.degrees(np.arccos(min(abs(found.direction @ (R @ level.direction)), 1.0)))
    assert angle < 1.0, angle
    assert found.overlap > 0.6 and abs(found.turn - level.turn - 10.0) < 1.5, found
