"""Reading and writing: CT images in the patient frame, plans, landmarks and model exports.

``read_ct`` (in :mod:`pvcmf.io.ct`) is the entry point for images.
"""

from .ct import read_ct

__all__ = ["read_ct"]
