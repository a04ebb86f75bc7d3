"""jaw_pose: the plane of the dental arches and label grids turned level with it and back,
against arches built at known angles."""

from __future__ import annotations

import numpy as np
import pytest

from pvcmf.filters.jaw_pose import MIN_TILT_DEG, Level, occlusal_tilt


def _rotation(pitch, roll):
    """Rotation by ``pitch`` degrees about x, then ``roll`` about y."""
    a, b = np.radians(pitch), np.radians(roll)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    return ry @ rx


def _arch(turn, spacing=(1.0, 1.0, 1.0), shape=(80, 80, 60)):
    """A horseshoe of teeth (a half ring, 50 mm across, 8 mm high) turned by ``turn``."""
    spacing = np.asarray(spacing)
    centre = (np.asarray(shape) - 1) * spacing / 2
    p = np.indices(shape).reshape(3, -1).T * spacing - centre
    q = p @ turn  # the arch's own frame: turn.T @ p per point
    r = np.hypot(q[:, 0], q[:, 1])
    inside = (np.abs(r - 22.0) < 4.0) & (q[:, 1] > -5.0) & (np.abs(q[:, 2]) < 4.0)
    return inside.reshape(shape)


@pytest.mark.parametrize("pitch, roll", [(-20.0, 0.0), (12.0, 5.0), (0.0, -8.0), (25.0, 10.0)])
def test_tilt_of_an_arch_built_at_known_angles(pitch, roll):
    turn = _rotation(pitch, roll)
    rotation, deg = occlusal_tilt(_arch(turn), (1.0, 1.0, 1.0))
    expect = np.degrees(np.arccos(turn[2, 2]))
    assert deg == pytest.approx(expect, abs=1.0)
    # the rotation found levels the arch's normal
    normal = turn[:, 2]
    assert rotation @ normal == pytest.approx([0.0, 0.0, 1.0], abs=0.02)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    assert rotation @ rotation.T == pytest.approx(np.eye(3), abs=1e-12)


def test_anisotropic_voxels_give_the_tilt_in_millimetres():
    turn = _rotation(-18.0, 0.0)
    teeth = _arch(turn, spacing=(1.0, 1.0, 2.0), shape=(80, 80, 30))
    _, deg = occlusal_tilt(teeth, (1.0, 1.0, 2.0))
    assert deg == pytest.approx(18.0, abs=1.5)


def test_a_level_arch_a_row_of_teeth_and_too_few_voxels_are_left_alone():
    rotation, deg = occlusal_tilt(_arch(np.eye(3)), (1.0, 1.0, 1.0))
    assert rotation is None and deg < MIN_TILT_DEG
    row = np.zeros((40, 40, 40), bool)  # a short row of front teeth, upright
    row[15:25, 20:23, 10:20] = True
    rotation, deg = occlusal_tilt(row, (1.0, 1.0, 1.0))
    assert rotation is None and deg == pytest.approx(90.0)
    blob = np.zeros((40, 40, 40), bool)  # as wide as deep as high: no plane
    blob[10:20, 10:20, 10:20] = True
    assert occlusal_tilt(blob, (1.0, 1.0, 1.0)) == (None, 0.0)
    few = np.zeros((10, 10, 10), bool)
    few[2, 2, :5] = True
    assert occlusal_tilt(few, (1.0, 1.0, 1.0)) == (None, 0.0)


def test_level_turns_the_arch_flat_and_back_keeps_every_label():
    turn = _rotation(-20.0, 6.0)
    spacing = (1.0, 1.0, 1.5)
    teeth = _arch(turn, spacing, shape=(80, 80, 40))
    rotation, _ = occlusal_tilt(teeth, spacing)
    level = Level(teeth.shape, spacing, rotation)
    flat = level.forward(teeth.view(np.uint8)) > 0
    height = np.flatnonzero(flat.any(axis=(0, 1)))
    assert (height[-1] - height[0] + 1) * spacing[2] <= 8.0 + 2 * spacing[2]
    labels = np.where(teeth, 2, 0).astype(np.uint8)
    labels[teeth & (np.indices(teeth.shape)[0] < 40)] = 3
    back = level.back(level.forward(labels), teeth)
    assert np.all(back[teeth] > 0) and not back[~teeth].any()
    assert np.mean(back[teeth] == labels[teeth]) > 0.97
    assert not np.shares_memory(back, labels)


def test_pitch_sign_and_the_warning_for_a_tilted_head(caplog):
    """A plane descending anteriorly (+y) has a positive pitch; labels whose upper arch
    pitches beyond the occlusal plane's usual cant are warned about, others not."""
    import logging

    import pyvista as pv

    from pvcmf import arrays
    from pvcmf.filters.jaw_pose import OCCLUSAL_CANT, OCCLUSAL_CANT_SD, check_pose, pitch

    a = np.radians(20.0)
    assert pitch(np.array([0.0, np.sin(a), np.cos(a)])) == pytest.approx(20.0)
    assert pitch(np.array([0.0, -np.sin(a), np.cos(a)])) == pytest.approx(-20.0)
    img = pv.ImageData(dimensions=(2, 2, 2))
    assert check_pose(img) is None
    limit = 3.0 * OCCLUSAL_CANT_SD
    for angle, warned in ((OCCLUSAL_CANT, False), (OCCLUSAL_CANT + 0.9 * limit, False),
                          (OCCLUSAL_CANT + 1.1 * limit, True), (OCCLUSAL_CANT - 1.1 * limit, True)):
        img.field_data[arrays.ARCH_PITCH] = np.array([angle])
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="pvcmf"):
            message = check_pose(img)
        assert (message is not None) is warned
        assert ("head lies tilted" in caplog.text) is warned
        if warned:
            assert ("chin down" if angle > OCCLUSAL_CANT else "chin up") in message
