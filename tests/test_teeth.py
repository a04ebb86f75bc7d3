"""Which tooth-dense bone is teeth (pvcmf.filters.teeth): the dentition, not the otic
capsules of the skull base, which are as dense."""

from __future__ import annotations

import numpy as np
import pytest

from pvcmf.filters.teeth import DENTITION_LINK_MM, teeth_of_the_dentition

SPACING = np.array([1.0, 1.0, 1.0])
FACTOR = (2, 2, 2)


def _grid():
    return np.zeros((140, 160, 120), dtype=bool)


def _arch(mask, z, gap=0):
    """Teeth (4 mm cubes) along a U in x-y at height ``z``, the front toward +y; ``gap``:
    teeth left out of the right side (missing teeth)."""
    for k, t in enumerate(np.linspace(-1.0, 1.0, 14)):
        if gap and 0 < k - 8 <= gap:
            continue
        x, y = int(70 + 25 * t), int(110 - 30 * t * t)
        mask[x - 2:x + 2, y - 2:y + 2, z - 2:z + 2] = True
    return mask


def _capsules(mask, z):
    """The two otic capsules: small dense blobs far behind, beside and above the arch."""
    for x in (30, 110):
        mask[x - 2:x + 2, 20:24, z - 2:z + 2] = True
    return mask


def test_the_capsules_are_not_teeth_without_a_brain():
    teeth = _capsules(_arch(_grid(), 40), 95)
    out = teeth_of_the_dentition(teeth, np.zeros_like(teeth), SPACING, FACTOR)
    np.testing.assert_array_equal(out, _arch(_grid(), 40))
    assert teeth[30, 21, 95] and not out[30, 21, 95]  # the input is left alone


def test_an_open_mouth_and_missing_teeth_stay_teeth():
    teeth = _arch(_arch(_grid(), 40, gap=2), 70)  # arches 30 mm apart, two teeth missing
    out = teeth_of_the_dentition(teeth, np.zeros_like(teeth), SPACING, FACTOR)
    np.testing.assert_array_equal(out, teeth)


def test_the_capsules_near_the_brain_are_not_teeth():
    teeth = _capsules(_arch(_grid(), 40), 95)
    brain = _grid()
    brain[20:120, 20:60, 100:120] = True
    out = teeth_of_the_dentition(teeth, brain, SPACING, FACTOR)
    np.testing.assert_array_equal(out, _arch(_grid(), 40))


@pytest.mark.parametrize("apart", [DENTITION_LINK_MM + 8, DENTITION_LINK_MM - 8])
def test_the_link_is_the_gap_between_teeth(apart):
    """Two teeth ``apart`` mm apart (gap): one group below the link, two above it (the
    larger kept)."""
    teeth = _grid()
    teeth[20:30, 50:60, 40:50] = True  # the larger
    x = 30 + int(apart)
    teeth[x:x + 4, 50:54, 40:44] = True
    out = teeth_of_the_dentition(teeth, np.zeros_like(teeth), SPACING, FACTOR)
    assert out[20:30, 50:60, 40:50].all()
    assert out[x:x + 4, 50:54, 40:44].all() == (apart < DENTITION_LINK_MM)
