"""The pvcmf data model: array names, label ids, boundary-condition codes and units.

Every filter takes its array names, label ids and bc codes from here and nowhere else,
and validates its inputs with :func:`require_array`.

Units
-----
Lengths in millimetres, stresses and Young's moduli in MPa, time in seconds.
User-facing angles (plans) are in degrees; radians are used internally.

Coordinates (patient frame)
---------------------------
x horizontal (patient's left +), y anterior +, z superior +.
A surgical plan's (horizontal, vertical, anterior-posterior) triple maps to (x, z, y):
see :data:`PLAN_AXES`.
"""

from __future__ import annotations

import numpy as np

# --------------------------------------------------------------------------- units
LENGTH_UNIT = "mm"
STRESS_UNIT = "MPa"
TIME_UNIT = "s"
ANGLE_UNIT = "deg"

#: index of the (x, y, z) axis for the plan's (horizontal, vertical, anterior-posterior) triple
PLAN_AXES = (0, 2, 1)

# --------------------------------------------------------------------------- image arrays
CT = "ct"  #: point, float32, Hounsfield units (or scanner units rescaled to HU)
#: field (labels of ``segment``), float64, 4 values: the image's own skin, bone, teeth and
#: metal levels (HU) the segmentation used
THRESHOLDS = "thresholds"
TISSUE = "tissue"  #: point (image) / cell (grid), uint8, tissue label, see TISSUE_LABELS
MUSCLE = "muscle"  #: point (image) / cell (grid), uint8, 0 none, 1.. index into MUSCLES + 1
BONE = "bone"  #: point (image), uint8, bone segment id, see BONE_LABELS

# --------------------------------------------------------------------------- tissue labels
AIR = 0
FAT = 1  #: fat / generic soft tissue
SOFT_TISSUE = FAT
MUSCLE_TISSUE = 2
BONE_TISSUE = 3
TEETH = 4
INTRACRANIAL = 5  #: what lies inside the skull (brain, CSF): not part of the face model
#: metal (fillings, crowns, plates): hard tissue that moves rigidly with its bone segment
METAL = 6

TISSUE_LABELS = {
    "air": AIR,
    "fat": FAT,
    "muscle": MUSCLE_TISSUE,
    "bone": BONE_TISSUE,
    "teeth": TEETH,
    "intracranial": INTRACRANIAL,
    "metal": METAL,
}
#: labels that make up the facial soft-tissue model (meshed)
SOFT_LABELS = (FAT, MUSCLE_TISSUE)
#: labels that are hard tissue (move rigidly with their segment)
HARD_LABELS = (BONE_TISSUE, TEETH, METAL)

# --------------------------------------------------------------------------- bone segments
BONE_NONE = 0
CRANIUM = 1
MAXILLA = 2
MANDIBLE = 3
BONE_LABELS = {"none": BONE_NONE, "cranium": CRANIUM, "maxilla": MAXILLA, "mandible": MANDIBLE}
BONE_NAMES = {v: k for k, v in BONE_LABELS.items()}

# --------------------------------------------------------------------------- muscles
#: the six muscles of paper 000 Fig. 2a
MUSCLE_KINDS = (
    "orbicularis_oculi",
    "levator_labii_superioris_alaeque_nasi",
    "levator_labii_superioris",
    "masseter",
    "zygomaticus_major",
    "zygomaticus_minor",
)
SIDES = ("left", "right")
#: muscle names; the label id of MUSCLES[i] is i + 1 (0 = no muscle)
MUSCLES = tuple(f"{kind}_{side}" for side in SIDES for kind in MUSCLE_KINDS)
MUSCLE_IDS = {name: i + 1 for i, name in enumerate(MUSCLES)}
MUSCLE_NONE = 0

# --------------------------------------------------------------------------- grid arrays
MUSCLE_FRACTION = "muscle_fraction"  #: cell, float64 in [0, 1]
E_FIBER = "E_fiber"  #: cell, float64, MPa, Young's modulus along the fibre
E_CROSS = "E_cross"  #: cell, float64, MPa, Young's modulus across the fibre
NU = "nu"  #: cell, float64, Poisson ratio
FIBER = "fiber"  #: cell (grid) / point (image), float64 (n, 3), unit vector, zero where isotropic
BC = "bc"  #: point, int8, see BC_* codes
BC_DISPLACEMENT = "bc_displacement"  #: point, float64 (n, 3), mm
BC_NORMAL = "bc_normal"  #: point, float64 (n, 3), unit sliding normal
DISPLACEMENT = "displacement"  #: point, float64 (n, 3), mm
DISTANCE = "distance"  #: point, float64, mm, + anterior / - posterior of the truth
REGION = "region"  #: point (skin), uint8, face region id, see FACE_REGIONS

BC_FREE = 0
BC_FIXED = 1
BC_JOINT = 2
BC_SLIDING = 3
BC_CODES = {"free": BC_FREE, "fixed": BC_FIXED, "joint": BC_JOINT, "sliding": BC_SLIDING}

FACE_REGIONS = {
    "other": 0,
    "upper_lip": 1,
    "lower_lip": 2,
    "chin": 3,
    "nose": 4,
    "cheek_left": 5,
    "cheek_right": 6,
}

# --------------------------------------------------------------------------- validation
_ASSOC = {"point": "point_data", "cell": "cell_data", "field": "field_data"}


def require_array(dataset, name, association="point", dtype=None, ncomp=None, producer=None):
    """Return ``dataset``'s array ``name`` after checking it exists with the right kind.

    Parameters
    ----------
    dataset : pyvista.DataSet
        Dataset holding the array.
    name : str
        Array name, one of the constants of this module.
    association : {'point', 'cell', 'field'}
        Where the array must live.
    dtype : numpy dtype kind string or type, optional
        ``'f'`` float, ``'i'`` signed int, ``'u'`` unsigned int, ``'iu'`` any integer, or a
        numpy type that the array's dtype must equal.
    ncomp : int, optional
        Number of components (1 for scalars, 3 for vectors).
    producer : str, optional
        Name of the filter that produces the array, quoted in the error message.

    Returns
    -------
    numpy.ndarray
        The array (a view; do not modify it in place).

    Raises
    ------
    ValueError
        If the array is missing or has the wrong dtype or number of components.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> img = pv.ImageData(dimensions=(2, 2, 2))
    >>> img[arrays.CT] = np.zeros(8, dtype=np.float32)
    >>> arrays.require_array(img, arrays.CT, "point", dtype="f").shape
    (8,)
    """
    if association not in _ASSOC:
        raise ValueError(
            f"association must be one of {sorted(_ASSOC)}, got {association!r}"
        )
    hint = f" (it is produced by {producer})" if producer else ""
    data = getattr(dataset, _ASSOC[association])
    if name not in data.keys():
        raise ValueError(
            f"{type(dataset).__name__} has no {association} array {name!r}{hint}; "
            f"it has {sorted(data.keys())}"
        )
    arr = np.asarray(data[name])
    if dtype is not None:
        if isinstance(dtype, str):
            ok = arr.dtype.kind in dtype
            want = {"f": "float", "i": "signed int", "u": "unsigned int", "iu": "integer"}.get(
                dtype, dtype
            )
        else:
            ok = arr.dtype == np.dtype(dtype)
            want = np.dtype(dtype).name
        if not ok:
            raise ValueError(
                f"{association} array {name!r} must have dtype {want}, got {arr.dtype}{hint}"
            )
    if ncomp is not None:
        have = 1 if arr.ndim == 1 else arr.shape[1]
        if have != ncomp or arr.ndim > 2:
            raise ValueError(
                f"{association} array {name!r} must have {ncomp} component(s), "
                f"got shape {arr.shape}{hint}"
            )
    return arr


# --------------------------------------------------------------------------- image geometry
def voxel_points(image, ids):
    """Coordinates (mm) of the voxels ``ids`` (flat point ids) of an ImageData.

    Computed from origin, spacing and dimensions, without materialising every point of
    the image (``image.points`` builds an (n, 3) array for the whole volume).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.arrays import voxel_points
    >>> img = pv.ImageData(dimensions=(3, 4, 5), spacing=(1, 2, 3), origin=(10, 0, 0))
    >>> bool(np.allclose(voxel_points(img, [0, 7, 59]), img.points[[0, 7, 59]]))
    True
    """
    ids = np.asarray(ids, dtype=np.int64)
    nx, ny, _ = image.dimensions
    ijk = np.stack([ids % nx, (ids // nx) % ny, ids // (nx * ny)], axis=1)
    return np.asarray(image.origin, dtype=float) + ijk * np.asarray(image.spacing, dtype=float)


# --------------------------------------------------------------------------- atlas, virtual patients, pipeline (core)
BONE_DEPTH = "bone_depth"  #: rasterised head, float32, mm inside bone (cortical/cancellous HU)
EYE = "eye"  #: rasterised head, bool, inside an eye
SDF = "sdf"  #: point, float32, mm, a signed distance being contoured
MASK = "mask"  #: point, float32 0/1, a binary mask being contoured
NORMALS = "Normals"  #: point, float (n, 3), VTK's surface normals (``compute_normals``)
MUSCLE_ID = "muscle_id"  #: field, int, the muscle id (``MUSCLE_IDS``) of a muscle surface
VALID_POINT_MASK = "vtkValidPointMask"  #: point, VTK probe's flag: inside the probed mesh
ORIGINAL_IDS = ("vtkOriginalPointIds", "vtkOriginalCellIds")  #: VTK's extraction ids
DISPLACEMENT_MAGNITUDE = "|displacement| (mm)"  #: point, float, mm, |displacement| in figures


# --------------------------------------------------------------------------- truth and study
REFERENCE_SOLVER = "reference_solver"  #: field, float64 (4,): dofs, Newton its, factorisations, s
REFERENCE_RELEASED = "reference_released"  #: field, int64: prescribed point ids left free
REFERENCE_FOLDED = "reference_folded"  #: field, int64: cells the vertex displacements invert
MAPPING_SUPPORT = "mapping_support"  #: point (skin), float64, weight sum of map_to_surface
ORIGINAL_POINT_IDS = "vtkOriginalPointIds"  #: point, VTK extraction: source point ids
#: columns of the error-statistics table (pvcmf.study.statistics), in order
STAT_COLUMNS = ("n", "median", "mean_abs", "rms", "p50", "p90", "p95", "within_1mm",
                "within_2mm")
#: metric columns of a sweep row (|distance| statistics, mm and %)
SWEEP_METRICS = ("p50", "p90", "p95", "median", "mean_abs", "rms", "within_1mm", "within_2mm",
                 "n_skin")
#: timing columns of a sweep row (s)
SWEEP_TIMES = ("t_prepare", "t_eval", "cpu_prepare", "cpu_eval")
SWEEP_CASE = "case"  #: sweep table column: the case label (``P1`` for virtual patient 1)
SWEEP_CACHED = "cached"  #: sweep table column, bool: the row was read from the cache
SWEEP_ERROR = "error"  #: sweep table column: why a skipped task failed (``on_error='skip'``)
SWEEP_N_CELLS = "n_cells"  #: sweep result: tetrahedra of the mesh
SWEEP_DISTANCE = "distance"  #: sweep result array: signed error per skin point, mm
SWEEP_SKIN_POINTS = "skin_points"  #: sweep result array (n, 3): the skin's points, mm
SWEEP_SKIN_FACES = "skin_faces"  #: sweep result array: the skin's VTK face connectivity

# --------------------------------------------------------------------------- meshing
# field data of the tetrahedral meshes (pvcmf.filters.meshing.tetrahedralize)
MESH_MIN_DIHEDRAL = "min_dihedral_deg"  #: field, float, smallest dihedral angle (deg)
MESH_P1_DIHEDRAL = "p1_dihedral_deg"  #: field, float, 1st percentile of the per-cell minimum
MESH_MIN_RADIUS_RATIO = "min_radius_ratio"  #: field, float, smallest 3 r_in / R_circ
MESH_P1_RADIUS_RATIO = "p1_radius_ratio"  #: field, float, its 1st percentile
MESH_N_TETS_REQUESTED = "n_tets_requested"  #: field, int, the requested count
MESH_SURFACE_SPACING = "surface_spacing_mm"  #: field, float, working-grid spacing (mm)
MESH_SMOOTHING_SCALE = "smoothing_scale"  #: field, float, surface smoothing used
MESH_TIME_SURFACE = "time_surface_s"  #: field, float, s spent on the surfaces
MESH_TIME_VOLUME = "time_volume_s"  #: field, float, s spent on the volume mesh
MESH_TIME_TOTAL = "time_total_s"  #: field, float, s in all
MESH_GRADING = "grading"  #: field, float, size growth deep inside (1.0: uniform)
#: point array of the region ids on the working grid handed to SurfaceNets
MESH_COMPONENT = "comp"

# --------------------------------------------------------------------------- muscle embedding
# field data of the label images written by pvcmf.filters.embed_muscles
LANDMARK_NAMES = "landmark_names"  #: field, str, names of the warped landmarks used
LANDMARK_POINTS = "landmark_points"  #: field, float64 (n, 3), mm, their positions

# --------------------------------------------------------------------------- registration
# field data of the surfaces registered by pvcmf.filters.register
ICP_MATRIX = "icp_matrix"  #: field, float64 (4, 4), source -> target
ICP_RMS = "icp_rms"  #: field, float64, mm, point-to-plane RMS at the end
ICP_ITERATIONS = "icp_iterations"  #: field, int, iterations run
ICP_CONVERGED = "icp_converged"  #: field, int, 1 when converged
ICP_OVERLAP = "icp_overlap"  #: field, float64, share of the samples near the target

# --------------------------------------------------------------------------- filter arrays
# scratch arrays of intermediate datasets inside the filters (never in their output)
SCRATCH_CELL_ID = "cell_id"  #: cell, int64, index of the cell in the input grid
SCRATCH_HEAD = "head"  #: point, float, smoothed head indicator contoured for the skin


# --------------------------------------------------------------------------- skin transfer and plan response
TRANSFER_INSIDE = "transfer_inside"  #: point (skin), uint8, 1 where inside a tetrahedron
#: summary / field data: skin edges stretched beyond the steepest tetrahedron around them
#: (+10 %) by the mesh -> skin transfer (:func:`pvcmf.filters.surface_mapping.crumple_metric`)
CRUMPLE_VIOLATIONS = "crumple_violations"
#: summary / field data: largest ratio of an edge's stretch to that bound (<= 1.1 passes)
CRUMPLE_MAX_RATIO = "crumple_max_ratio"
CRUMPLE_EDGES = "crumple_edges"  #: summary / field data: number of skin edges checked
#: point (skin), uint8, 1 where the mesh models the skin (inside it or within the transfer's
#: band); 0 where the skin is not modelled (e.g. behind a face model's posterior cut) and its
#: displacement is the extension decayed to the fixed plane's zero
SKIN_MODELLED = "skin_modelled"
#: summary / field data: skin points the mesh models (:data:`SKIN_MODELLED`)
SKIN_MODELLED_POINTS = "skin_modelled_points"
#: field (labels of ``segment``), float64, 8 per plane where the scan cut the head flat (the
#: field of view's edge, the scan's end): axis, sign, coordinate (mm), the cut's extent (mm)
#: along the two other axes, 1 for the field of view's edge or 0 for the image's end
#: (:func:`pvcmf.filters.field_of_view.cuts_array`)
SCAN_CUTS = "scan_cuts"
#: field (labels of ``segment``), float64, 4 per axial slice where the round field of view
#: cuts the head: z, the circle's centre x and y, its radius (mm)
#: (:func:`pvcmf.filters.field_of_view.fov_cuts`)
SCAN_FOV = "scan_fov"
#: field (the CT of :func:`pvcmf.filters.working_grid`), int64, 3 values: the blocks of scan
#: voxels averaged into one working voxel along x, y and z (1, 1, 1: the scan's own grid)
WORKING_FACTORS = "working_factors"
#: field (the CT of :func:`pvcmf.filters.working_grid`), float64, 3 values: the scan's own
#: voxel spacing (mm) before the blocks
SCAN_SPACING = "scan_spacing"
#: field (the CT of :func:`pvcmf.filters.flatten_shading`), float64, 2 values: the 5th and
#: 95th percentiles over the tissue of the shading field divided out (median 1; 1, 1: none)
SHADING = "shading"
#: field (the CT of :func:`pvcmf.read_ct` from a DICOM series), string, 1 value: the series'
#: DICOM Modality (``"CT"`` for CT and most cone-beam CT; absent where the file does not
#: say): :func:`pvcmf.io.units.check_units` refuses another imaging modality and maps a CT's
#: grey values that are not HU
MODALITY = "modality"
#: field (the CT of :func:`pvcmf.read_ct`), string, 1 value: the file or folder it was read
#: from; :func:`pvcmf.pipeline.simulate` checks the units and axes of a CT given in memory
#: as read_ct returned it, as it does for a path (:func:`pvcmf.filters.standardize`'s
#: new image has no such field)
SOURCE_PATH = "source_path"
#: point (skin), uint8, 1 where the skin lies on such a cut, the scan's edge and not the
#: patient's skin (present when the labels have ``SCAN_CUTS`` or ``SCAN_FOV``)
SKIN_CUT = "skin_cut"
#: summary / field data: skin points on a cut of the scan (:data:`SKIN_CUT`)
SKIN_CUT_POINTS = "skin_cut_points"
#: field (labels of ``find_jaws``), float64, 1 value where the teeth form a flat arch: the
#: pitch (degrees) of the upper dental arch's plane from the image's axial plane, positive
#: where it descends anteriorly (as the occlusal plane does against the Frankfort
#: horizontal) (:func:`pvcmf.filters.jaw_pose.check_pose`)
ARCH_PITCH = "arch_pitch"
#: field (labels of ``find_jaws``), float64, 3 values where the teeth form a flat arch: the
#: unit normal (superior) of the upper dental arch's plane, in the image's axes (a plan's
#: ``axes = "occlusal"``, :func:`pvcmf.filters.plan_axes`)
ARCH_NORMAL = "arch_normal"
#: field (labels of ``find_jaws``), float64, 1 value with ``ARCH_NORMAL``: the teeth's spread
#: (mm, standard deviation) across their row in that plane, an arch's depth as opposed to
#: a row of front teeth (:data:`pvcmf.filters.jaw_pose.MIN_ARCH_SPAN_MM`)
ARCH_SPAN = "arch_span"
#: field, float64, 3 values: the unit normal of the head's mirror (midsagittal) plane, the
#: head's left-right direction in the image's axes, from its hard tissue's symmetry
#: (:func:`pvcmf.filters.mirror_plane`; a plan's ``axes = "occlusal"`` takes its horizontal)
MIRROR_NORMAL = "mirror_normal"


# --------------------------------------------------------------------------- solution checks
# field data of pvcmf.mtm.solve: what a linear solution does that tissue cannot
MTM_INVERTED = "mtm_inverted_cells"  #: field, int64, tetrahedra the displacement turns inside out
#: field, float64, largest |displacement| of a free (or sliding) node over the largest
#: prescribed |bc_displacement| (NaN when nothing moves)
MTM_FREE_RATIO = "mtm_free_over_prescribed"


# --------------------------------------------------------------------------- validation study
#: point (judged skin), int64, index of the point in the skin every method was mapped to
#: (pairs the skin points of two methods: :mod:`pvcmf.study.inference`)
SKIN_POINT_ID = "skin_point_id"
#: field (judged skin), int64 (1,): points of the judged face left out because the
#: post-operative CT shows no skin where the truth puts it
#: (:data:`pvcmf.study.validation.JUDGE_LIMIT`)
STUDY_EXCLUDED = "study_excluded"


# --------------------------------------------------------------------------- mesh fitted to the dense skin
# pvcmf.filters.meshing.fit_to_skin: the mesh's skin nodes pushed out around the dense skin
SKIN_FIT_PUSH = "skin_fit_push"  #: point (grid), float64 (n, 3), mm each node was moved
SKIN_FIT_MAX_PUSH = "skin_fit_max_push_mm"  #: field / summary, float, largest node move (mm)
SKIN_FIT_NODES = "skin_fit_nodes_moved"  #: field / summary, int, nodes moved
#: field / summary, int, dense skin points outside the mesh (within the fit's reach) before
SKIN_FIT_OUTSIDE_BEFORE = "skin_fit_outside_before"
#: field / summary, int, dense skin points outside the mesh (within the fit's reach) after
SKIN_FIT_OUTSIDE_AFTER = "skin_fit_outside_after"
SKIN_FIT_SECONDS = "skin_fit_seconds"  #: field / summary, float, seconds the fit took
#: the field data of fit_to_skin, in the order summary.json lists them
SKIN_FIT_FIELDS = (SKIN_FIT_MAX_PUSH, SKIN_FIT_NODES, SKIN_FIT_OUTSIDE_BEFORE,
                   SKIN_FIT_OUTSIDE_AFTER, SKIN_FIT_SECONDS)

# --- crumple metric (surface mapping) ---
#: summary / field data: a lower bound on the crumple violations of any mesh -> skin
#: transfer that interpolates inside the mesh (:func:`pvcmf.filters.crumple_bound.unavoidable_crumples`)
CRUMPLE_UNAVOIDABLE = "crumple_unavoidable"

# --------------------------------------------------------------------------- truth's P2 field
# pvcmf.truth.solver.solve_reference: the quadratic solution at the edge midpoints, so that
# the truth can be evaluated as the quadratic field it is (pvcmf.truth.refinement)
REFERENCE_EDGES = "reference_edges"  #: field, int64 (m, 2): point ids of each mesh edge
#: field, float64 (m, 3), mm: the solution at the midpoint of each of REFERENCE_EDGES
REFERENCE_MIDPOINT_DISPLACEMENT = "reference_midpoint_displacement"
