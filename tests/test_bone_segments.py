"""find_jaws / cut_bones without cut planes: the anatomy's mandible and Le Fort I maxilla
against the virtual patients' true segments."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv
from scipy import ndimage

import pvcmf
from pvcmf import arrays
from pvcmf.filters.bone_segments import find_jaws, segment_volumes
from pvcmf.filters.face_axes import occlusal_axes
from pvcmf.plan import Osteotomy, Plan


def dice(a, b):
    return 2.0 * np.count_nonzero(a & b) / max(np.count_nonzero(a) + np.count_nonzero(b), 1)


@pytest.fixture(scope="module")
def patient1():
    case = pvcmf.datasets.phantom(patient=1, spacing=2.0)
    return case, pvcmf.filters.segment(case.ct)


def test_jaws_match_phantom_truth(patient1):
    case, lab = patient1
    bone = np.asarray(find_jaws(lab)[arrays.BONE])
    truth = np.asarray(case.truth[arrays.BONE])
    assert dice(bone == arrays.MANDIBLE, truth == arrays.MANDIBLE) >= 0.95
    assert dice(bone == arrays.MAXILLA, truth == arrays.MAXILLA) >= 0.95
    hard = np.isin(np.asarray(lab[arrays.TISSUE]), arrays.HARD_LABELS)
    assert np.array_equal(bone > 0, hard)


def test_cut_bones_without_planes_finds_segments(patient1):
    _, lab = patient1
    plan = Plan((Osteotomy("maxilla", (0, 0, 2.0)), Osteotomy("mandible", (0, 0, 1.0))))
    cut = pvcmf.filters.cut_bones(lab, plan)
    vols = segment_volumes(cut)
    assert vols["maxilla"] > 5 and vols["mandible"] > 5 and vols["cranium"] > vols["mandible"]
    # a cut plane still overrides the anatomy
    plane = Plan((Osteotomy("maxilla", cut=(((0, 0, 1e4), (0, 0, -1)),)),))
    over = np.asarray(pvcmf.filters.cut_bones(lab, plane)[arrays.BONE])
    assert np.array_equal(over == arrays.MAXILLA, np.asarray(lab[arrays.BONE]) > 0)


def test_no_teeth_is_an_error(patient1):
    _, lab = patient1
    noteeth = lab.copy()
    t = np.asarray(noteeth[arrays.TISSUE]).copy()
    t[np.isin(t, (arrays.TEETH, arrays.METAL))] = arrays.BONE_TISSUE
    noteeth[arrays.TISSUE] = t
    with pytest.raises(ValueError, match="cut planes"):
        find_jaws(noteeth)
    with pytest.raises(ValueError, match="occlusal_normal: fewer than 10 tooth voxels"):
        occlusal_axes(noteeth)  # a plan in the occlusal axes needs teeth too


@pytest.mark.parametrize("patient", [1, 2, 3, 4])
def test_jaws_of_every_virtual_patient(segmented_patients, patient):
    """The mandible and the Le Fort I maxilla found from the anatomy against each virtual
    patient's true segments (2 mm): the maxilla reaches back to the end of the hard palate
    and up to its Le Fort I level."""
    case, lab = segmented_patients[patient]
    bone = np.asarray(find_jaws(lab)[arrays.BONE])
    truth = np.asarray(case.truth[arrays.BONE])
    for segment in (arrays.MANDIBLE, arrays.MAXILLA):
        score = dice(bone == segment, truth == segment)
        assert score >= 0.95, f"{arrays.BONE_NAMES[segment]} Dice {score:.3f}"


def test_jaws_of_a_closed_bite(patient1):
    """The virtual patient with the teeth in occlusion: the slices between the arches
    removed and the upper crowns' lowest slice laid onto the lower crowns' top (no slice free
    of teeth between them). Both segments keep a Dice >= 0.95 against the truth shifted the
    same way."""
    case, lab = patient1
    d = tuple(lab.dimensions)
    t = np.asarray(lab[arrays.TISSUE]).reshape(d, order="F")
    truth = np.asarray(case.truth[arrays.BONE]).reshape(d, order="F")
    profile = np.isin(t, (arrays.TEETH, arrays.METAL)).sum(axis=(0, 1))
    z = np.flatnonzero(profile)
    gap = [k for k in range(z[0], z[-1]) if profile[k] == 0]
    assert gap, "the virtual patient's arches are apart"
    keep = np.setdiff1d(np.arange(d[2]), gap + [gap[-1] + 1])
    closed, bone = t[:, :, keep], truth[:, :, keep]
    contact = t[:, :, gap[-1] + 1] == arrays.TEETH
    closed[:, :, gap[0] - 1][contact] = arrays.TEETH
    assert np.all(np.isin(closed, (arrays.TEETH, arrays.METAL)).sum(axis=(0, 1))[
        z[0]:z[-1] - len(gap)])
    img = pv.ImageData(dimensions=closed.shape, spacing=lab.spacing, origin=lab.origin)
    img[arrays.TISSUE] = closed.ravel(order="F")
    found = np.asarray(find_jaws(img)[arrays.BONE]).reshape(closed.shape, order="F")
    for segment in (arrays.MANDIBLE, arrays.MAXILLA):
        score = dice(found == segment, bone == segment)
        assert score >= 0.95, f"{arrays.BONE_NAMES[segment]} Dice {score:.3f}"


def test_jaws_of_thin_bone_joined_at_the_joints(patient1):
    """The virtual patient with the joint spaces filled with bone (a joint lost to thick
    slices or partial volume) and only a 4 mm cortex left of every bone (the marrow made soft
    tissue): one erosion would break such bone into pieces. The mandible is split from the
    skull at the joints: both segments keep a Dice >= 0.95 against the truth."""
    case, lab = patient1
    d = tuple(lab.dimensions)
    t = np.asarray(lab[arrays.TISSUE]).reshape(d, order="F").copy()
    truth = np.asarray(case.truth[arrays.BONE]).reshape(d, order="F")
    mand, cranium = truth == arrays.MANDIBLE, truth == arrays.CRANIUM
    joint = (ndimage.binary_dilation(mand, iterations=2)
             & ndimage.binary_dilation(cranium, iterations=2) & ~np.isin(t, arrays.HARD_LABELS))
    joint[:, :, :np.nonzero(mand)[2].max() - 4] = False  # the condyles' tops only
    t[joint] = arrays.BONE_TISSUE
    marrow = ndimage.binary_erosion(np.isin(t, arrays.HARD_LABELS), iterations=2)
    t[marrow & (t == arrays.BONE_TISSUE)] = arrays.FAT
    hard = np.isin(t, arrays.HARD_LABELS)
    pieces, _ = ndimage.label(hard)
    assert np.intersect1d(pieces[mand & hard], pieces[cranium & hard]).size  # joined
    img = lab.copy()
    img[arrays.TISSUE] = t.ravel(order="F")
    found = np.asarray(find_jaws(img)[arrays.BONE]).reshape(d, order="F")
    for segment in (arrays.MANDIBLE, arrays.MAXILLA):
        score = dice(found == segment, (truth == segment) & hard)
        assert score >= 0.95, f"{arrays.BONE_NAMES[segment]} Dice {score:.3f}"


def _pitched(volume, spacing, degrees, cval):
    """``volume`` turned ``degrees`` about the x axis through its centre (nearest voxel):
    a head scanned with the chin down (negative) or up."""
    a = np.radians(degrees)
    turn = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    s = np.asarray(spacing, float)
    c = (np.asarray(volume.shape) - 1) / 2
    matrix = (turn.T * s[None, :]) / s[:, None]
    return ndimage.affine_transform(volume, matrix, offset=c - matrix @ c, order=0, cval=cval)


def _upright_pitch(patient1):
    return float(find_jaws(patient1[1]).field_data[arrays.ARCH_PITCH][0])


@pytest.mark.parametrize("degrees", [-20.0, 15.0])
def test_jaws_of_a_head_scanned_tilted(patient1, degrees):
    """The virtual patient scanned with the chin 20 degrees down, or 15 up: the segments are
    found on the image turned level with the dental arches. Against the truth turned the
    same way: the mandible keeps a Dice >= 0.95, the maxilla >= 0.94 (the image and the
    truth are each turned nearest-voxel, and the labels found turned back: 2 mm voxels
    moved up to a voxel at the Le Fort I cut)."""
    case, lab = patient1
    d = tuple(lab.dimensions)
    t = _pitched(np.asarray(lab[arrays.TISSUE]).reshape(d, order="F"), lab.spacing, degrees,
                 arrays.AIR)
    truth = _pitched(np.asarray(case.truth[arrays.BONE]).reshape(d, order="F"), lab.spacing,
                     degrees, arrays.BONE_NONE)
    img = pv.ImageData(dimensions=d, spacing=lab.spacing, origin=lab.origin)
    img[arrays.TISSUE] = t.ravel(order="F")
    jaws = find_jaws(img)
    found = np.asarray(jaws[arrays.BONE]).reshape(d, order="F")
    hard = np.isin(t, arrays.HARD_LABELS)
    # the arch's pitch turns with the head (chin down raises it)
    assert float(jaws.field_data[arrays.ARCH_PITCH][0]) == pytest.approx(
        _upright_pitch(patient1) - degrees, abs=2.0)
    for segment, least in ((arrays.MANDIBLE, 0.95), (arrays.MAXILLA, 0.94)):
        score = dice(found == segment, (truth == segment) & hard)
        assert score >= least, f"{arrays.BONE_NAMES[segment]} Dice {score:.3f}"
