"""Size grading of :func:`pvcmf.filters.tetrahedralize` (``grading=g``): coarser deep inside.

The element size is ``s`` (the mean surface edge) within ``0.5 s`` of any region
interface (skin, muscle surfaces, bone, the cut of a region of interest) and grows
linearly to ``g s`` at ``2 g s`` from it, so that the tetrahedra are fine where the face
is seen and at the muscles and coarse deep in the fat. The distance to the interfaces
is computed once per call on the label image (``scipy.ndimage.distance_transform_edt``
on a grid of about half the working spacing; the surfaces are snapped onto the
image interfaces, so this is their distance to within that grid); gmsh reads the sizes
as a ``Structured`` background field (trilinear interpolation of a regular grid written
to a temporary binary file), which is cheaper for gmsh to evaluate than a ``Distance``
field over every surface triangle. :func:`graded_share` gives the count calibration the
reduction in elements that the grading brings at a given spacing.

Delegates to scipy.ndimage (distance transform) and the gmsh Python API (``Structured``
and background mesh fields).
"""

from __future__ import annotations

import logging
import numbers
import os
import tempfile

import numpy as np
from scipy import ndimage

log = logging.getLogger(__name__)

#: the size is the surface size up to this many surface sizes from an interface (a
#: ramp starting at the surface would make the elements on the surface taller than
#: their triangles) ...
DIST_MIN = 0.5
#: ... and grows linearly to ``g s`` at ``RAMP * g s`` away (a gentler ramp than
#: ``g s`` at ``g s`` leaves HXT's optimiser less to do)
RAMP = 2.0
#: the distance grid's step, in working spacings (the distance is then accurate to
#: about a quarter of an element)
GRID_STEP = 0.5
#: largest accepted growth factor
MAX_GRADING = 8.0


def check_grading(grading):
    """``None`` for uniform meshes (``None`` or 0), else the growth factor as a float > 1.

    Examples
    --------
    >>> from pvcmf.filters.meshing.grading import check_grading
    >>> check_grading(None), check_grading(0), check_grading(2)
    (None, None, 2.0)
    """
    if grading is None:
        return None
    if isinstance(grading, bool) or not isinstance(grading, numbers.Real):
        raise TypeError(
            f"grading must be None, 0 or a number in (1, {MAX_GRADING:g}], "
            f"got {type(grading).__name__} {grading!r}"
        )
    g = float(grading)
    if g == 0.0:
        return None
    if not (1.0 < g <= MAX_GRADING):
        raise ValueError(
            f"grading must be None, 0 or a number in (1, {MAX_GRADING:g}] (the size growth "
            f"deep inside), got {grading!r}"
        )
    return g


def size_ratio(distance, s, grading):
    """Element size over the surface size ``s`` at ``distance`` (mm) from an interface.

    1 up to ``DIST_MIN * s``, ``grading`` from ``RAMP * grading * s`` on, linear in between.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters.meshing.grading import size_ratio
    >>> size_ratio(np.array([0.0, 0.5, 2.25, 4.0, 9.0]), 1.0, 2.0).tolist()
    [1.0, 1.0, 1.5, 2.0, 2.0]
    """
    d0, d1 = DIST_MIN * s, RAMP * grading * s
    t = np.clip((np.asarray(distance, float) - d0) / (d1 - d0), 0.0, 1.0)
    return 1.0 + (grading - 1.0) * t


class InterfaceDistance:
    """Distance (mm) of the meshed voxels to the nearest region interface.

    Parameters
    ----------
    code : (nz, ny, nx) uint8 array
        Working-grid codes of the image (``>= first_meshed`` are meshed regions, one
        code per region).
    origin, spacing : 3 floats
        Of ``code``'s first voxel and its voxel size (x, y, z), mm.
    step : float
        Wanted grid step in mm (the image is sampled every ``round(step / voxel)``
        voxels, at least every voxel).
    first_meshed : int
        The smallest code that is meshed.

    Attributes
    ----------
    distance : (mz, my, mx) float array
        0 outside the meshed regions and at the voxels next to another code.
    origin, step : (3,) float arrays
        Of the sampled grid (x, y, z).
    inside : 1-d float array
        ``distance`` at the meshed voxels (for :func:`graded_share`).

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters.meshing.grading import InterfaceDistance
    >>> code = np.zeros((9, 9, 9), np.uint8)
    >>> code[1:-1, 1:-1, 1:-1] = 2
    >>> d = InterfaceDistance(code, (0, 0, 0), (1, 1, 1), 1.0, 2)
    >>> float(d.distance[4, 4, 4])
    3.0
    """

    def __init__(self, code, origin, spacing, step, first_meshed):
        spacing = np.asarray(spacing, float)
        k = max(1, int(round(step / float(spacing.min()))))
        c = np.ascontiguousarray(code[::k, ::k, ::k])
        meshed = c >= first_meshed
        interior = meshed.copy()
        for ax in range(3):  # a voxel with a different 6-neighbour lies at an interface
            diff = np.diff(c, axis=ax) != 0
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[ax], hi[ax] = slice(0, -1), slice(1, None)
            interior[tuple(lo)] &= ~diff
            interior[tuple(hi)] &= ~diff
        self.step = spacing * k
        self.origin = np.asarray(origin, float)
        if interior.any():
            self.distance = ndimage.distance_transform_edt(interior, sampling=self.step[::-1])
        else:
            self.distance = np.zeros(c.shape)
        self.inside = self.distance[meshed]

    def sizes(self, s, grading):
        """Element sizes (mm) on the sampled grid for surface size ``s``."""
        return s * size_ratio(self.distance, s, grading)

    def write_structured(self, path, s, grading):
        """Write the sizes in gmsh's binary ``Structured`` field format to ``path``.

        3 doubles origin, 3 doubles step, 3 int32 counts (x, y, z), then the values with
        x the slowest and z the fastest index.
        """
        values = np.ascontiguousarray(self.sizes(s, grading).transpose(2, 1, 0), dtype="<f8")
        with open(path, "wb") as fh:
            fh.write(self.origin.astype("<f8").tobytes())
            fh.write(self.step.astype("<f8").tobytes())
            fh.write(np.asarray(values.shape, "<i4").tobytes())
            fh.write(values.tobytes())


def graded_share(distance, s, grading):
    """Mean of ``(s / size)**3`` over the meshed voxels: graded count / uniform count.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters.meshing.grading import graded_share
    >>> graded_share(np.array([0.0, 100.0]), 1.0, 2.0)
    0.5625
    """
    if distance.size == 0:
        return 1.0
    return float(np.mean(size_ratio(distance, s, grading) ** -3.0))


def add_background_field(distance, s, grading):
    """Set the graded sizes as the background mesh field of the current gmsh model.

    Returns the temporary file and the previous values of the global gmsh options
    changed here; hand both to :func:`restore` after meshing.
    """
    import gmsh

    fd, path = tempfile.mkstemp(prefix="pvcmf_grading_", suffix=".bin")
    os.close(fd)
    names = ("Mesh.MeshSizeExtendFromBoundary", "Mesh.MeshSizeFromPoints")
    saved = {}
    try:
        distance.write_structured(path, s, grading)
        field = gmsh.model.mesh.field.add("Structured")
        gmsh.model.mesh.field.setString(field, "FileName", path)
        gmsh.model.mesh.field.setNumber(field, "TextFormat", 0)
        gmsh.model.mesh.field.setAsBackgroundMesh(field)
        # the sizes come from the field alone (not interpolated from the surface nodes)
        for name in names:
            saved[name] = gmsh.option.getNumber(name)
            gmsh.option.setNumber(name, 0)
    except BaseException:
        restore(path, saved)  # nothing half-set is left behind
        raise
    log.debug("grading: background field from %s (s %.3g mm, g %.3g)", path, s, grading)
    return path, saved


def restore(path, saved):
    """Undo :func:`add_background_field`'s global options and remove its file."""
    import gmsh

    for name, value in saved.items():
        gmsh.option.setNumber(name, value)
    try:
        os.remove(path)
    except OSError:
        pass
