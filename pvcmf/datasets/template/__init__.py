"""The template head of the virtual patients: the atlas head and the patient warps.

The anatomy (signed distance functions of bones, teeth, soft tissue and the twelve facial
muscles, the landmarks and the rasteriser) is library data owned by :mod:`pvcmf.atlas`;
this package gathers it under one name with the perturbations that make each virtual
patient (:mod:`pvcmf.datasets.template.warp`) and the face shaping that gives the head a real
face's proportions (:mod:`pvcmf.datasets.template.face`). Virtual patients are built from the atlas,
never the reverse.

Frame: x = patient's left +, y = anterior +, z = superior +, mm; the origin lies between
the ear canals (porion) on the Frankfort horizontal plane (z = 0).
"""

from __future__ import annotations

from ...atlas.landmarks import landmark_segments, landmarks
from ...atlas.muscles import muscle_sdf, muscle_sdfs, muscle_surfaces
from ...atlas.raster import _Grid, head_grid, head_points, label_image, rasterize
from ...atlas.shapes import F32
from ...atlas.skull import (CRANIUM_CENTER, CRANIUM_INNER, CRANIUM_OUTER, Z_LEFORT,
                            Z_LOWER_EDGE, Z_UPPER_EDGE, braincase_sdf, cranium_vault_sdf,
                            face_bone_sdf, face_cavities_sdf, lower_teeth_sdf, mandible_sdf,
                            orbits_sdf, spine_sdf, upper_teeth_sdf)
from ...atlas.soft_tissue import (airway_sdf, eyes_sdf, neck_muscles_sdf, oral_air_sdf, skin_sdf,
                                  temporalis_sdf, thickness_field, tongue_sdf)
from .face import REAL_FACE, FaceShape
from .warp import (CENTER, INNER_AXES, PatientParameters, PatientWarp, _check_patient,
                   identity_warp, patient_parameters, patient_warp)

__all__ = [
    "CENTER", "CRANIUM_CENTER", "CRANIUM_INNER", "CRANIUM_OUTER", "F32", "FaceShape",
    "INNER_AXES", "REAL_FACE",
    "PatientParameters", "PatientWarp", "Z_LEFORT", "Z_LOWER_EDGE", "Z_UPPER_EDGE",
    "_Grid", "_check_patient", "airway_sdf", "braincase_sdf", "cranium_vault_sdf",
    "eyes_sdf", "face_bone_sdf", "face_cavities_sdf", "head_grid", "head_points",
    "identity_warp", "label_image", "landmark_segments", "landmarks", "lower_teeth_sdf",
    "mandible_sdf", "muscle_sdf", "muscle_sdfs", "muscle_surfaces", "neck_muscles_sdf",
    "oral_air_sdf", "orbits_sdf", "patient_parameters", "patient_warp", "rasterize",
    "skin_sdf", "spine_sdf", "temporalis_sdf", "thickness_field", "tongue_sdf",
    "upper_teeth_sdf",
]
