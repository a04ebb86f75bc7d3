"""Pre-operative CT next to the virtual post-operative CT, one slice each.

The virtual post-operative CT (:func:`pvcmf.postop.postop_ct`) is the pre-operative CT
warped by the truth's displacement and the plan's bone moves, with its own noise and
pose. A sagittal (or any axis-aligned) slice of each, side by side in the same grey
window, shows the moved jaw and the soft tissue that followed it. Delegates to
matplotlib (``imshow`` of the slice, extracted with numpy from the image's point array).
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from .. import arrays

__all__ = ["ct_slice", "postop_ct_slices"]

_AXES = {"x": 0, "y": 1, "z": 2}
_NAMES = {"x": ("y (anterior) [mm]", "z (superior) [mm]"),
          "y": ("x (left) [mm]", "z (superior) [mm]"),
          "z": ("x (left) [mm]", "y (anterior) [mm]")}


def ct_slice(image, axis="x", position=0.0):
    """The slice of a CT nearest to ``position`` along ``axis``.

    Parameters
    ----------
    image : pyvista.ImageData
        CT with point array ``arrays.CT``.
    axis : {'x', 'y', 'z'}, default 'x'
        Normal of the slice ('x': sagittal, 'y': coronal, 'z': axial).
    position : float, default 0.0
        Coordinate (mm) of the slice along ``axis``; clamped to the image.

    Returns
    -------
    tuple
        ``(values (n_u, n_v) array, extent (u0, u1, v0, v1) in mm)`` with ``u``, ``v`` the
        two other axes in order.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.figures.postop_ct import ct_slice
    >>> img = pv.ImageData(dimensions=(3, 4, 5))
    >>> img[arrays.CT] = np.arange(60, dtype=np.float32)
    >>> ct_slice(img, "x", 1.0)[0].shape
    (4, 5)
    """
    if axis not in _AXES:
        raise ValueError(f"axis must be 'x', 'y' or 'z', got {axis!r}")
    values = np.asarray(arrays.require_array(image, arrays.CT, "point", dtype="f", ncomp=1,
                                             producer="read_ct / postop_ct"))
    dims = tuple(int(d) for d in image.dimensions)
    vol = values.reshape(dims, order="F")
    k = _AXES[axis]
    origin, spacing = np.asarray(image.origin, float), np.asarray(image.spacing, float)
    index = int(np.clip(np.rint((position - origin[k]) / spacing[k]), 0, dims[k] - 1))
    sl = np.take(vol, index, axis=k)
    others = [a for a in range(3) if a != k]
    extent = []
    for a in others:
        extent += [origin[a], origin[a] + spacing[a] * (dims[a] - 1)]
    return sl, tuple(extent)


def postop_ct_slices(pre_ct, post_ct, *, axis="x", position=0.0, window=(-1000.0, 1500.0),
                     titles=("pre-operative CT", "virtual post-operative CT"), zoom=None,
                     difference=True):
    """Side-by-side slices of the pre-operative and the virtual post-operative CT.

    Parameters
    ----------
    pre_ct, post_ct : pyvista.ImageData
        CTs with point array ``arrays.CT`` (HU).
    axis : {'x', 'y', 'z'}, default 'x'
        Slice normal ('x': sagittal, the profile of the face).
    position : float, default 0.0
        Slice coordinate (mm), the midline by default.
    window : (float, float), default (-1000, 1500)
        Grey window (HU).
    titles : (str, str)
        Panel titles.
    zoom : (u0, u1, v0, v1), optional
        Axis limits (mm) of both panels, e.g. the face.
    difference : bool, default True
        A third panel, post minus pre (HU, blue-white-red over +-1000): what moved.
        Meaningful when both CTs share one grid and pose.

    Returns
    -------
    matplotlib.figure.Figure

    Examples
    --------
    >>> import pvcmf
    >>> from pvcmf.figures.postop_ct import postop_ct_slices
    >>> case = pvcmf.datasets.phantom(1, spacing=4.0)
    >>> fig = postop_ct_slices(case.ct, case.ct)
    >>> len(fig.axes)  # three panels and two colour bars
    5
    """
    n = 3 if difference else 2
    # fixed layout (a constrained layout settles differently on a second draw)
    fig = Figure(figsize=(4.2 * n + 1.0, 5.4))
    axes = fig.subplots(1, n, sharex=True, sharey=True)
    fig.subplots_adjust(left=0.07, right=0.98, top=0.94, bottom=0.08, wspace=0.12)
    slices = []
    grey = None
    for ax, ct, title in zip(axes, (pre_ct, post_ct), titles):
        sl, extent = ct_slice(ct, axis, position)
        slices.append(sl)
        grey = ax.imshow(sl.T, origin="lower", extent=extent, cmap="gray", vmin=window[0],
                         vmax=window[1], interpolation="nearest")
        ax.set_title(title)
    fig.colorbar(grey, ax=list(axes[:2]), shrink=0.8, label="HU", location="bottom",
                 pad=0.12)
    if difference:
        if slices[0].shape != slices[1].shape:
            raise ValueError("difference=True needs both CTs on one grid, got slices of shapes "
                             f"{slices[0].shape} and {slices[1].shape}")
        diff = axes[2].imshow((slices[1] - slices[0]).T, origin="lower", extent=extent,
                              cmap="RdBu_r", vmin=-1000, vmax=1000, interpolation="nearest")
        axes[2].set_title("post - pre")
        fig.colorbar(diff, ax=axes[2], shrink=0.8, label="HU", location="bottom", pad=0.12)
    for ax in axes:
        ax.set_xlabel(_NAMES[axis][0])
        ax.set_aspect("equal")
        if zoom is not None:
            ax.set_xlim(zoom[0], zoom[1])
            ax.set_ylim(zoom[2], zoom[3])
    axes[0].set_ylabel(_NAMES[axis][1])
    return fig
