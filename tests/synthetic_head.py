"""A small synthetic head CT with known labels, for the segmentation / classification tests.

Nested ellipsoids: fat shell with two muscle slabs, skull shell, brain, an air sinus inside
the face, a tooth block, and a table below the head that does not touch it. HU values are
blurred (partial volume) and noised; truth labels are the voxel-centre labels.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
from scipy import ndimage

from pvcmf import arrays

HU = {"air": -1000.0, "fat": -100.0, "muscle": 40.0, "bone": 1400.0, "teeth": 2600.0,
      "brain": 35.0, "table": 300.0}


def synthetic_head(spacing=2.0, noise=12.0, blur=0.6, seed=0):
    """Return ``(ct, truth)`` ImageData: ``ct`` float32 HU, ``truth`` with ``tissue``."""
    n = (np.array([200.0, 220.0, 200.0]) / spacing).astype(int)
    img = pv.ImageData(dimensions=n, spacing=(spacing,) * 3, origin=(-100.0, -110.0, -100.0))
    x, y, z = (img.points[:, i].reshape(n, order="F") for i in range(3))

    def ell(a, b, c, cx=0.0, cy=0.0, cz=0.0):
        return ((x - cx) / a) ** 2 + ((y - cy) / b) ** 2 + ((z - cz) / c) ** 2 <= 1.0

    skin = ell(80, 95, 85)
    outer_bone = ell(68, 83, 73)
    inner_bone = ell(62, 77, 67)
    brain = inner_bone & (z > -30)
    skull = outer_bone & ~brain
    # the face block below the brain is bone with an air sinus and the teeth
    sinus = ell(14, 10, 10, cx=25, cy=50, cz=-45)
    teeth = ell(30, 8, 6, cy=55, cz=-55) & skull
    # skull below z=-30 is solid bone except the sinus; make the lower part soft tissue
    lower_soft = outer_bone & (z < -30) & ~ell(58, 80, 64, cz=-30)
    skull = skull & ~lower_soft
    muscle = skin & ~outer_bone & (((np.abs(x) > 60) & (np.abs(z) < 30)) | ell(20, 20, 15, cy=88, cz=-20))
    table = (z < -95) & (z > -99) & (np.abs(x) < 90)

    tissue = np.zeros(n, dtype=np.uint8)
    hu = np.full(n, HU["air"])
    layers = [  # later layers overwrite earlier ones
        (skin, arrays.FAT, "fat"), (muscle, arrays.MUSCLE_TISSUE, "muscle"),
        (lower_soft, arrays.FAT, "fat"), (skull, arrays.BONE_TISSUE, "bone"),
        (teeth, arrays.TEETH, "teeth"), (brain, arrays.INTRACRANIAL, "brain"),
        (sinus, arrays.AIR, "air"), (table, arrays.AIR, "table"),
    ]
    for mask, label, name in layers:
        tissue[mask] = label
        hu[mask] = HU[name]

    rng = np.random.default_rng(seed)
    ct_vals = ndimage.gaussian_filter(hu, blur / 1.0) + rng.normal(0.0, noise, n)
    ct = img.copy()
    ct.point_data[arrays.CT] = ct_vals.astype(np.float32).ravel(order="F")
    truth = img.copy()
    truth.point_data[arrays.TISSUE] = tissue.ravel(order="F")
    return ct, truth


def dice(a, b):
    """Dice coefficient of two boolean arrays."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    return 2.0 * np.count_nonzero(a & b) / max(np.count_nonzero(a) + np.count_nonzero(b), 1)
