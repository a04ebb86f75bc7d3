"""Old import path of the virtual post-operative CT and of the validation from a CT: see
:mod:`pvcmf.truth.postop` and :mod:`pvcmf.study.from_ct`."""

from .study.from_ct import refine_skin, skin_from_ct, upper_face_region, validate_from_ct  # noqa: F401
from .truth.postop import AIR_HU, GAP_HU, postop_ct, random_pose, reference_grid  # noqa: F401

__all__ = ["postop_ct", "random_pose", "reference_grid", "refine_skin", "skin_from_ct",
           "upper_face_region", "validate_from_ct"]
