"""An analytic head-shell label image for examples, tests and benchmarks."""

from __future__ import annotations

import numpy as np
import pyvista as pv

from ... import arrays


def shell_labels(spacing=1.0, radii=(60.0, 75.0, 85.0), soft=14.0, bone=5.0, tube_radius=4.0):
    """A small analytic head-shell label image: soft tissue over a bone shell, 4 muscle tubes.

    An ellipsoid of radii ``radii`` (mm): the outer ``soft`` mm are fat on the front
    (``y > -0.3 radii[1]``, a face) and air at the back, the next ``bone`` mm bone, the
    inside intracranial. Four muscle tubes of radius ``tube_radius`` run
    horizontally (along x) at mid-depth of the soft tissue in the anterior half (y > 0),
    with muscle ids 1-4. The bone below ``z = -0.3 radii[2]`` is the mandible, the rest the
    cranium (point array ``arrays.BONE``). For examples, tests and benchmarks.

    Parameters
    ----------
    spacing : float
        Voxel size in mm.
    radii : 3 floats
        Ellipsoid semi-axes in mm.
    soft, bone : float
        Thickness (mm, measured along the smallest semi-axis) of the soft tissue and bone.
    tube_radius : float
        Radius of the muscle tubes in mm.

    Returns
    -------
    pyvista.ImageData
        With uint8 point arrays ``arrays.TISSUE``, ``arrays.MUSCLE`` and ``arrays.BONE``.

    Examples
    --------
    >>> from pvcmf import arrays
    >>> from pvcmf.filters.meshing import shell_labels
    >>> img = shell_labels(spacing=3.0)
    >>> sorted(set(img[arrays.MUSCLE].tolist()))
    [0, 1, 2, 3, 4]
    """
    r = np.asarray(radii, float)
    pad = 3 * spacing
    dims = np.ceil(2 * (r + pad) / spacing).astype(int) + 1
    origin = -(dims - 1) * spacing / 2.0
    img = pv.ImageData(dimensions=dims, spacing=(spacing,) * 3, origin=origin)
    x, y, z = (origin[k] + spacing * np.arange(dims[k]) for k in range(3))
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    depth = (1.0 - np.sqrt((X / r[0]) ** 2 + (Y / r[1]) ** 2 + (Z / r[2]) ** 2)) * r.min()
    tissue = np.zeros(X.shape, np.uint8)
    tissue[(depth >= 0) & (Y > -0.3 * r[1])] = arrays.FAT
    tissue[depth >= soft] = arrays.BONE_TISSUE
    tissue[depth >= soft + bone] = arrays.INTRACRANIAL
    bone_seg = np.where(Z < -0.3 * r[2], arrays.MANDIBLE, arrays.CRANIUM).astype(np.uint8)
    bone_seg[tissue != arrays.BONE_TISSUE] = arrays.BONE_NONE
    muscle = np.zeros(X.shape, np.uint8)
    for k, z0 in enumerate(np.linspace(-0.5, 0.5, 4) * r[2]):
        tube = (np.hypot(depth - soft / 2.0, Z - z0) <= tube_radius) & (Y > 0) & (np.abs(X) < 0.6 * r[0])
        muscle[tube] = k + 1
        tissue[tube] = arrays.MUSCLE_TISSUE
    img.point_data[arrays.TISSUE] = tissue.ravel(order="F")
    img.point_data[arrays.MUSCLE] = muscle.ravel(order="F")
    img.point_data[arrays.BONE] = bone_seg.ravel(order="F")
    return img
