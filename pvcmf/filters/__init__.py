"""Pipeline steps as pure filters: ``f(dataset, *, options) -> new dataset``.

One module per step of the papers, named after what it does:

========================  ==========================  =====================================
filter                    module                      paper step
========================  ==========================  =====================================
segment                   ``segmentation``            000 sec. II: skin/skull/soft tissue
classify_tissue           ``classify``                001 Fig. 1: per-slice GMM + EM, median
embed_muscles             ``muscles``                 000 sec. II: atlas + TPS, Fig. 2b
fiber_directions          ``fibers``                  000 Fig. 3: OBB fibre directions
tetrahedralize            ``meshing``                 000 Fig. 2c: labelled tetrahedral mesh
fit_to_skin               ``meshing.skin_fit``        mesh skin pushed out around the dense skin
sample_muscle_fraction    ``fractions``               000 Fig. 1: random-point sampling
average_voxels            ``fractions``               001: per-tetrahedron voxel average
assign_materials          ``materials``               000 Table I / 001 materials
cut_bones, move_bones     ``osteotomy``               000 Fig. 5: bone segments and plan
apply_plan                ``boundary_conditions``     000 Fig. 4: sliding / joint / fixed
plan_axes                 ``face_axes``               a plan's moves in the face's axes
mirror_plane              ``symmetry``                the head's left-right direction
extract_skin              ``skin``                    skin surface of a label image or mesh
register                  ``registration``            000 sec. V: ICP (point-to-plane)
distance_to               ``distance``                000 Fig. 6: signed distance maps
map_to_surface            ``surface_mapping``         001: tet -> dense skin, Gaussian
standardize               ``orientation``             CT in HU, face +y, vertex +z
working_grid              ``resolution``              a very fine scan averaged in blocks
flatten_shading           ``shading``                 a cone-beam scan's shading divided out
========================  ==========================  =====================================

Modules are imported lazily, so ``import pvcmf`` stays fast and a heavy dependency
(gmsh, ...) is loaded only by the step that needs it.
"""

from __future__ import annotations

import importlib

_REGISTRY = {
    "segment": "segmentation",  # not "segment": importing a submodule named like
    # its filter would shadow the filter with the module on the package
    "classify_tissue": "classify",
    "embed_muscles": "muscles",
    "fiber_directions": "fibers",
    "oriented_bounding_box": "fibers",
    "tetrahedralize": "meshing",  # not "tetrahedralize": same shadowing as segment
    "fit_to_skin": "meshing",
    "sample_muscle_fraction": "fractions",
    "average_voxels": "fractions",
    "assign_materials": "materials",
    "cut_bones": "osteotomy",
    "move_bones": "osteotomy",
    "find_jaws": "bone_segments",
    "apply_plan": "boundary_conditions",
    "plan_axes": "face_axes",
    "mirror_plane": "symmetry",  # not "mirror_plane": same shadowing as segment
    "extract_skin": "skin",
    "register": "registration",
    "distance_to": "distance",
    "map_to_surface": "surface_mapping",
    "transfer_operator": "surface_mapping",
    "crumple_metric": "surface_mapping",
    "working_grid": "resolution",
    "flatten_shading": "shading",
    "standardize": "orientation",  # check_units, orient_head: pvcmf.filters.orientation
}

__all__ = sorted(_REGISTRY)


def __getattr__(name):
    try:
        module = _REGISTRY[name]
    except KeyError:
        raise AttributeError(f"module 'pvcmf.filters' has no attribute {name!r}") from None
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)


def __dir__():
    return sorted(set(globals()) | set(_REGISTRY))
