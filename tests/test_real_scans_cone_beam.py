"""The real heads as a cone-beam scanner holds a face (a field around the jaws that reaches
the ears, no cranial cavity, grey values that are not HU; ``ct_helpers.cone_beam_field``):
labelled and cut into jaws as the whole scan is.

The female's field holds her otic capsules, as dense as teeth and, without the brain in the
scan, not told from teeth by their distance to it: they must not become an upper arch.
Skipped where the data folder lacks the scans.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pvcmf import arrays
from pvcmf.filters import find_jaws
from pvcmf.filters.orientation import standardize

from ct_helpers import cone_beam_field


@pytest.fixture(scope="module", params=["vhp_female_head", "vhp_male_head"])
def field_labels(request, data_dir):
    ct, report = standardize(cone_beam_field(data_dir, request.param), units="rescale")
    assert report["orientation"]["code"] == "LAS"
    return request.param, ct.cmf.segment()


def test_the_teeth_are_one_dentition(field_labels):
    """Every tooth voxel lies within a dental arch's reach of the others: no otic capsule
    several centimetres behind and above them."""
    _, labels = field_labels
    teeth = np.asarray(labels.points)[np.asarray(labels[arrays.TISSUE]) == arrays.TEETH]
    assert len(teeth) > 100
    extent = np.ptp(teeth, axis=0)
    assert extent[1] < 60.0 and extent[2] < 60.0, extent


def test_the_jaws_are_found_as_in_the_whole_scan(field_labels, caplog):
    name, labels = field_labels
    with caplog.at_level(logging.WARNING, logger="pvcmf"):
        jaws = find_jaws(labels)
    messages = [r.getMessage() for r in caplog.records]
    assert not any("no nasal floor" in m for m in messages), messages
    bone = np.asarray(jaws[arrays.BONE])
    ml = {k: np.count_nonzero(bone == arrays.BONE_LABELS[k]) * np.prod(jaws.spacing) / 1e3
          for k in ("maxilla", "mandible")}
    assert ml["mandible"] > 20.0 and ml["maxilla"] > 3.0, ml


def test_a_noisy_field_keeps_the_jaws(data_dir):
    """The male's field with noise of about 33 HU (20 grey values; cone-beam scans are
    noisy): the tooth voxels scatter, the occlusal gaps sampled in part of the arch fit a
    sharply folded surface, which must not cut the mandible's front off nor set the
    occlusal level below the teeth. Both jaws keep a Dice of 0.75 against the clean
    field's."""
    jaws = {}
    for noise in (0.0, 20.0):
        ct, _ = standardize(cone_beam_field(data_dir, "vhp_male_head", noise=noise),
                            units="rescale")
        jaws[noise] = np.asarray(find_jaws(ct.cmf.segment())[arrays.BONE])
    for k in ("maxilla", "mandible"):
        a, b = (jaws[n] == arrays.BONE_LABELS[k] for n in (20.0, 0.0))
        score = 2 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b))
        assert score > 0.75, (k, score)


@pytest.fixture(scope="module")
def female_fields(data_dir):
    """The female's field as scanned (no shading) and with strong cupping (the attenuation
    20 % darker on the field's axis), in HU."""
    clean = cone_beam_field(data_dir, "vhp_female_head")
    cupped = cone_beam_field(data_dir, "vhp_female_head", cupping=0.2)
    return (standardize(clean, units="rescale")[0], standardize(cupped, units="rescale")[0])


def _jaw_volumes(ct):
    labels = ct.cmf.segment()
    bone = np.asarray(find_jaws(labels)[arrays.BONE])
    hard = np.isin(np.asarray(labels[arrays.TISSUE]), arrays.HARD_LABELS)
    ml = {k: np.count_nonzero(bone == arrays.BONE_LABELS[k]) * np.prod(ct.spacing) / 1e3
          for k in ("maxilla", "mandible")}
    return ml, hard


def test_cupping_flattened_gives_the_jaws_of_the_unshaded_field(female_fields):
    """Cupping moves the bone level the histogram gives off the bone in the field's middle
    or at its edge; flatten_shading brings the hard tissue and the jaws back."""
    clean, cupped = female_fields
    ref, ref_hard = _jaw_volumes(clean)
    raw, raw_hard = _jaw_volumes(cupped)
    flat_ct = cupped.cmf.flatten_shading()
    flat, flat_hard = _jaw_volumes(flat_ct)

    def dice(a):
        return 2 * np.count_nonzero(a & ref_hard) / (np.count_nonzero(a) + np.count_nonzero(ref_hard))

    assert dice(flat_hard) > 0.96 and dice(flat_hard) > dice(raw_hard) + 0.05
    for k in ref:
        assert abs(flat[k] - ref[k]) < 0.15 * ref[k], (k, ref, raw, flat)
    assert abs(raw["maxilla"] - ref["maxilla"]) > 0.5 * ref["maxilla"], (ref, raw)
    low, high = flat_ct.field_data[arrays.SHADING]
    assert high / low > 1.15


@pytest.mark.parametrize("value", [0.0, 1500.0])
def test_a_field_filled_outside_with_a_constant_reads_as_air(data_dir, value):
    """The male's field with its outside written as one grey value, not the lowest: read as
    air, his head comes out as with the outside at air."""
    field = cone_beam_field(data_dir, "vhp_male_head")
    ref, _ = standardize(field, units="rescale")
    grey = np.asarray(field[arrays.CT])
    filled = field.copy()
    filled[arrays.CT] = np.where(grey == grey.min(), value, grey).astype(np.float32)
    out, report = standardize(filled, units="rescale")
    assert report["units"]["fill"]["value"] == value
    assert report["orientation"]["code"] == "LAS"
    teeth = [np.count_nonzero(np.asarray(ct.cmf.segment()[arrays.TISSUE]) == arrays.TEETH)
             for ct in (ref, out)]
    assert abs(teeth[1] - teeth[0]) < 0.05 * teeth[0], teeth
