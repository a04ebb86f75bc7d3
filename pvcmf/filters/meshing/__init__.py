"""Labelled tetrahedral meshing of the facial soft tissue (paper 000, sec. II, Fig. 2c).

One step from the tissue + muscle label image to a tetrahedral mesh in which every
tetrahedron lies in exactly one region (fat or one muscle) and the element faces follow
the muscle surfaces. The package is split by responsibility:

========================  ==============================================================
module                    what it does
========================  ==============================================================
``inputs``                checks of the label image and the count; the region of interest
``grid``                  region codes of the image, the working grid (muscles claim
                          voxels up to their volume), topology repair, connected regions
``surfaces``              conforming SurfaceNets surfaces snapped onto the image
                          interfaces, constrained smoothing, closedness check, patches
``subvoxel``              optional sub-voxel muscle interfaces: the muscle sheets on the
                          half level of the smoothed label indicators
``volume``                gmsh volume meshing (one at a time per process), sliver
                          removal, the count model of the working spacing
``grading``               optional size grading (gmsh background field from a distance
                          transform)
``quality``               element quality, sliver-node relocation, field-data names
``mesher``                :func:`tetrahedralize`: calibration, fallbacks, output grid
``shell``                 :func:`shell_labels`, an analytic label image for examples
``skin_fit``              :func:`fit_to_skin`: the skin nodes pushed out around a dense skin
========================  ==============================================================

The steps:

1. the soft tissue (``arrays.SOFT_LABELS``, optionally cropped to a region of interest) is
   resampled on an isotropic working grid whose spacing is calibrated from the requested
   number of tetrahedra (the surface triangles are about that size);
2. every connected region of the working grid gets its own label and VTK's SurfaceNets
   builds conforming multi-label surfaces: an interface between two regions is one set
   of triangles shared by both, snapped onto the full-resolution image interfaces and
   lightly smoothed; with ``subvoxel=True`` the named muscles' sheets are then moved
   onto the half level of their smoothed label indicators (between the voxel centres);
3. the surfaces are checked (every region's boundary must be closed) and a volume per
   region is meshed by gmsh (HXT); when gmsh rejects the surfaces, a slightly different
   grid, then weaker smoothing and placement, finally the plain working-grid surfaces are
   tried, with a warning when the surfaces were weakened;
4. the region label is written on every element (``arrays.TISSUE``, ``arrays.MUSCLE``) and
   the element quality and the timings to the field data (names in
   :data:`QUALITY_FIELDS`).

``conforming=False`` meshes the soft tissue as one homogeneous region (muscles ignored):
the paper's state of the art, completed by :func:`pvcmf.filters.sample_muscle_fraction`
or :func:`pvcmf.filters.average_voxels`. Measured accuracy, quality and speed:
``docs/benchmarks/meshing.md`` (``benchmarks/meshing.py``).

Delegates to PyVista/VTK (``contour_labels`` = ``vtkSurfaceNets3D``,
``vtkConstrainedSmoothingFilter``), scipy.ndimage (connected components, box averages of
the muscles, distance transforms), scipy.spatial (KD-trees of the image interfaces),
scipy.sparse (surface patches, surface relaxation) and the gmsh Python API.
"""

from __future__ import annotations

from .grid import SurfaceError
from .inputs import N_TETS_RANGE
from .mesher import tetrahedralize
from .quality import (
    GRADING,
    MIN_DIHEDRAL,
    MIN_RADIUS_RATIO,
    N_TETS_REQUESTED,
    P1_DIHEDRAL,
    P1_RADIUS_RATIO,
    QUALITY_FIELDS,
    SMOOTHING_SCALE,
    SURFACE_SPACING,
    TIME_SURFACE,
    TIME_TOTAL,
    TIME_VOLUME,
    tet_quality,
)
from .shell import shell_labels
from .skin_fit import fit_to_skin

__all__ = [
    "GRADING",
    "MIN_DIHEDRAL",
    "MIN_RADIUS_RATIO",
    "N_TETS_RANGE",
    "N_TETS_REQUESTED",
    "P1_DIHEDRAL",
    "P1_RADIUS_RATIO",
    "QUALITY_FIELDS",
    "SMOOTHING_SCALE",
    "SURFACE_SPACING",
    "SurfaceError",
    "TIME_SURFACE",
    "TIME_TOTAL",
    "TIME_VOLUME",
    "fit_to_skin",
    "shell_labels",
    "tet_quality",
    "tetrahedralize",
]
