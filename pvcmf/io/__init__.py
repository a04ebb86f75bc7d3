"""Reading and writing: CT images in the patient frame, plans, landmarks and model exports.

``read_ct`` (in :mod:`pvcmf.io.ct`) is the entry point for images; :func:`export`
(:mod:`pvcmf.io.exporters`) writes a model for CalculiX/Abaqus, FEBio or any meshio format;
:mod:`pvcmf.io.transforms` and :mod:`pvcmf.io.landmarks` read plans and landmarks from
planning tools (ITK/3D Slicer files); :func:`write_surface` (:mod:`pvcmf.io.surfaces`)
writes a skin as STL, OBJ or PLY for planning software.
"""

from .ct import read_ct
from .exporters import (
    calculix_available,
    check_export,
    export,
    read_calculix_dat,
    run_calculix,
    write_feb,
    write_inp,
    write_mesh,
)
from .landmarks import read_landmarks, write_landmarks
from .surfaces import read_surface, write_surface
from .transforms import read_itk_transform, read_plan_file, read_transform, write_itk_transform

__all__ = ["read_ct", "export", "check_export", "write_mesh", "write_inp", "write_feb", "run_calculix",
           "read_calculix_dat", "calculix_available", "read_landmarks", "write_landmarks",
           "read_transform", "read_itk_transform", "write_itk_transform", "read_plan_file",
           "write_surface", "read_surface"]
