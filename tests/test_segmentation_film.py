"""segment removes a plastic wrap film lying on the skin across a thin air gap (touching
it along a line) and keeps the skin, an ear flap and the nose; on the real Visible Human
female head the film wrapped over the back of the head and neck leaves no sheet over an
air gap on the skin. The real-scan test skips without the data."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv
from scipy import ndimage

import pvcmf
from pvcmf import arrays
from pvcmf.filters.surface_objects import drop_film

SOFT, AIR, FILM, BONE, BRAIN = 20.0, -1000.0, -150.0, 1400.0, 35.0


def _vol(img, name=arrays.TISSUE):
    return np.asarray(img[name]).reshape(img.dimensions, order="F")


def _head(gap, post=False):
    """A head-like ellipsoid at 1 mm (skin, skull, brain, an ear flap 4 mm thick on the
    -x side, a nose) with a film one voxel thick over its +x side, ``gap`` voxels of air
    under it, touching the skin along one horizontal line (``post``: held by a tissue post
    7 mm across instead, which no opening cuts). Returns the CT and the head, ear and film
    masks."""
    n = (96, 104, 100)
    img = pv.ImageData(dimensions=n, spacing=(1.0, 1.0, 1.0), origin=(-48.0, -52.0, -50.0))
    x, y, z = (img.points[:, i].reshape(n, order="F") for i in range(3))
    r = np.sqrt((x / 38.0) ** 2 + (y / 44.0) ** 2 + (z / 42.0) ** 2)
    skin = r <= 1.0
    skull = (r <= 0.85) & (r > 0.72)
    brain = r <= 0.72
    ear = (x < -30) & (x > -46) & (abs(y) <= 2) & (abs(z - 5) < 14)
    nose = (abs(x) <= 6) & (y > 38) & (y < 50) & (abs(z) < 12) & (y - 38 < 12 - abs(z))
    head = skin | ear | nose
    # the film: a shell (gap + 1) voxels outside the skin over the +x side, 60 x 60 mm
    depth = ndimage.distance_transform_edt(~skin)
    film = (depth > gap) & (depth <= gap + 1) & (x > 10) & (abs(y) < 30) & (abs(z) < 30)
    touch = (depth > 0) & (depth <= gap) & (abs(z) <= 0.5) & (x > 10) & (abs(y) < 30)
    if post:
        touch = (depth > 0) & (depth <= gap + 1) & (abs(z) <= 3) & (abs(y) <= 3) & (x > 10)
    v = np.full(n, AIR)
    v[head] = SOFT
    v[skull] = BONE
    v[brain] = BRAIN
    v[film | touch] = FILM
    v += np.random.default_rng(0).normal(0.0, 15.0, n)
    img[arrays.CT] = v.astype(np.float32).ravel(order="F")
    return img, head, ear, film


@pytest.mark.parametrize("gap", [1, 2, 3])
def test_film_over_an_air_gap_is_removed(gap):
    """The film (one voxel, ``gap`` voxels of air under it, touching the skin along a
    line) is no soft tissue; the skin, the ear flap and the nose are."""
    ct, head, ear, film = _head(gap)
    t = _vol(pvcmf.filters.segment(ct, check=False))
    tissue = t != arrays.AIR
    assert np.count_nonzero(tissue & film) < 0.02 * film.sum(), "film left on the skin"
    assert np.count_nonzero(head & ~tissue) < 0.002 * head.sum(), "skin removed"
    assert np.count_nonzero(tissue & ear) > 0.97 * ear.sum(), "ear removed"


def test_film_stays_without_object_opening():
    """The test head is valid: with ``object_opening=0`` (nothing on the skin dropped) the
    film is soft tissue."""
    ct, head, ear, film = _head(1)
    t = _vol(pvcmf.filters.segment(ct, check=False, object_opening=0.0))
    assert np.count_nonzero((t != arrays.AIR) & film) > 0.9 * film.sum()


def test_drop_film_keeps_small_pieces_and_dense_voxels():
    """A film piece under ``min_area`` stays, and so do voxels denser than ``dense`` (thin
    bone); coarse voxels (over ``FILM_VOXEL_MM``) are not tested; the input is kept."""
    ct, head, ear, film = _head(1)
    v = _vol(ct, arrays.CT)
    mask = head | film | (v > -500)
    before = mask.copy()
    out, ml = drop_film(mask, v, (1.0, 1.0, 1.0), 240.0)
    assert ml > 2.0 and np.count_nonzero(out & film) < 0.02 * film.sum()
    np.testing.assert_array_equal(mask, before)
    out, ml = drop_film(mask, v, (1.0, 1.0, 1.0), 240.0, min_area=1e5)
    assert ml == 0.0 and np.array_equal(out, mask)
    out, ml = drop_film(mask, np.where(film, 500.0, v), (1.0, 1.0, 1.0), 240.0)
    assert np.count_nonzero(out & film) > 0.9 * film.sum()
    out, ml = drop_film(mask, v, (1.0, 1.0, 2.0), 240.0)
    assert ml == 0.0


def test_film_held_by_a_post_is_removed_around_it():
    """A film 3 voxels above the skin, held by a post no opening cuts (it stays joined to
    the head): its voxels reach the head only around the air gap, through the post (the
    geodesic test); the film goes except a few millimetres around the post."""
    ct, head, ear, film = _head(3, post=True)
    v = _vol(ct, arrays.CT)
    mask = ndimage.binary_fill_holes(v > -500)
    out, ml = drop_film(mask, v, (1.0, 1.0, 1.0), 240.0)
    assert np.count_nonzero(out & film) < 0.1 * film.sum(), "film left on the skin"
    assert np.count_nonzero(head & ~out) < 0.002 * head.sum(), "skin removed"


# --------------------------------------------------------------------------- real CT
def _female_back_of_neck(female_ct, crop_ct):
    """The Visible Human female's back of the head and neck, 1 mm, 20 to 140 mm above its
    first slice: its wrap film lies there over the skin across an air gap."""
    ct, v = female_ct
    head = (v[:, :, 20:140] > -500.0).any(axis=2)
    xs, ys = np.flatnonzero(head.any(axis=1)), np.flatnonzero(head.any(axis=0))
    # the back half of the head (the patient frame: y anterior)
    box = (slice(int(xs[0]) - 8, int(xs[-1]) + 9),
           slice(int(ys[0]) - 8, (int(ys[0]) + int(ys[-1])) // 2), slice(20, 140))
    return crop_ct(ct, v, box)


def _sheet_over_gap(tissue):
    """Voxels of air under a sheet: air in an axial slice that the slice's own hole filling
    of the tissue closes, within 4 mm of the outside (the gap between a film and the skin;
    not the airway, deeper)."""
    filled = np.stack([ndimage.binary_fill_holes(tissue[:, :, k])
                       for k in range(tissue.shape[2])], axis=2)
    holes = filled & ~tissue
    depth = np.stack([ndimage.distance_transform_edt(filled[:, :, k])
                      for k in range(tissue.shape[2])], axis=2)
    return holes & (depth <= 4.0)


def test_female_film_leaves_no_sheet_over_an_air_gap(female_ct, crop_ct):
    """Segmenting the back of the real head leaves few air pockets under a sheet near the
    skin (the film's gap), a fraction of those the film makes when not removed."""
    ct = _female_back_of_neck(female_ct, crop_ct)
    t = _vol(pvcmf.filters.segment(ct, check=False)) != arrays.AIR
    t0 = _vol(pvcmf.filters.segment(ct, check=False, object_opening=0.0)) != arrays.AIR
    after, before = _sheet_over_gap(t).sum(), _sheet_over_gap(t0).sum()
    assert before > 500, f"the crop shows no film ({before} gap voxels)"
    assert after < 0.2 * before, f"{after} gap voxels under a sheet left of {before}"
