"""Virtual patients: the embedded default data set of pvcmf.

``phantom(patient, spacing)`` builds a deterministic virtual patient from the analytic
atlas head (:mod:`pvcmf.atlas`) through a patient warp
(:mod:`pvcmf.datasets.template`): truth labels (tissue, facial muscles, bone
segments), a CT with realistic Hounsfield units, partial-volume edges and noise, landmarks
and the patient's surgical plan (paper 000, Table II).

Delegates to :mod:`pvcmf.atlas.raster` (label rasterisation), :mod:`pvcmf.datasets.template`
(patient warps), numpy (CT synthesis, vectorised on grid sub-boxes) and
:func:`scipy.ndimage.gaussian_filter` (partial-volume blur).
"""

from __future__ import annotations

import functools
import logging
import time
from dataclasses import dataclass, field

import numpy as np
import pyvista as pv
from scipy import ndimage

from .. import arrays
from ..atlas.landmarks import landmark_segments, landmarks
from ..atlas.raster import SPACING_RANGE, head_grid, rasterize  # noqa: F401 (re-export)
from ..atlas.raster import check_spacing as _check_spacing
from ..plan import TABLE_II
from ..progress import Progress
from . import template

log = logging.getLogger(__name__)

#: Hounsfield units of the phantom's tissues (medians before blur and noise)
HU = {
    "air": -1000.0,
    "fat": -100.0,
    "muscle": 40.0,
    "brain": 35.0,
    "eye": 15.0,
    "cortical": 1700.0,
    "cancellous": 700.0,
    "teeth": 2500.0,
    "table": -150.0,
}
#: standard deviation (HU) of the CT noise
NOISE_HU = 18.0
#: standard deviation (voxels) of the partial-volume blur
BLUR_VOXELS = 0.6
#: thickness (mm) of the cortical layer of the bones
CORTEX_MM = 1.8
#: air gap (mm) between the head and the patient table, and the table's thickness
TABLE_GAP = 10.0
TABLE_THICKNESS = 12.0


@dataclass
class Case:
    """A virtual patient.

    Attributes
    ----------
    name : str
        Human-readable name, e.g. ``"patient 1"``.
    patient : int
        Patient number 1-4.
    spacing : float
        Voxel size in mm.
    ct : pyvista.ImageData
        Point array ``ct`` (float32, HU).
    truth : pyvista.ImageData
        Same geometry; point arrays ``tissue``, ``muscle``, ``bone`` (uint8).
    landmarks : dict
        name -> float ndarray (3,), mm, patient frame.
    plan : pvcmf.plan.Plan
        The patient's row of Table II.
    parameters : pvcmf.datasets.template.PatientParameters
        Size, soft-tissue thickness and jaw relation of the patient.
    """

    name: str
    patient: int
    spacing: float
    ct: pv.ImageData
    truth: pv.ImageData
    landmarks: dict
    plan: object
    parameters: object = None
    build_seconds: float = field(default=0.0, compare=False)

    def copy(self):
        """Deep copy (images, landmarks); the plan is immutable and shared."""
        return Case(self.name, self.patient, self.spacing, self.ct.copy(deep=True),
                    self.truth.copy(deep=True), {k: v.copy() for k, v in self.landmarks.items()},
                    self.plan, self.parameters, self.build_seconds)


def _grid_for(warp, spacing, table=True):
    """Image grid holding the patient's head, a margin and (optionally) the table."""
    pad = TABLE_GAP + TABLE_THICKNESS + spacing if table else 0.0
    return head_grid(warp, spacing, pad_back=pad)


def _table_mask(grid, tissue):
    """A carbon-fibre table slab behind the head, never touching it."""
    ax = grid.axes()
    head_y = np.flatnonzero((tissue != arrays.AIR).any(axis=(0, 2)))
    y_back = ax[1][head_y[0]] if len(head_y) else ax[1][0] + TABLE_GAP + TABLE_THICKNESS
    y1 = y_back - TABLE_GAP
    y0 = y1 - TABLE_THICKNESS
    in_y = (ax[1] >= y0) & (ax[1] <= y1)
    in_x = np.abs(ax[0]) <= 0.45 * (ax[0][-1] - ax[0][0])
    mask = np.zeros(tissue.shape, bool)
    mask[:, in_y[:, None] & in_x[None, :]] = True
    mask[:2] = False
    mask[-2:] = False
    return mask


def _synthesize_ct(labels, grid, seed):
    tissue = labels[arrays.TISSUE]
    hu = np.full(tissue.shape, HU["air"], np.float32)
    hu[tissue == arrays.FAT] = HU["fat"]
    hu[labels[arrays.EYE]] = HU["eye"]
    hu[tissue == arrays.MUSCLE_TISSUE] = HU["muscle"]
    hu[tissue == arrays.INTRACRANIAL] = HU["brain"]
    bone = tissue == arrays.BONE_TISSUE
    depth = labels[arrays.BONE_DEPTH][bone]
    hu[bone] = HU["cancellous"] + (HU["cortical"] - HU["cancellous"]) * np.exp(
        -np.maximum(depth - CORTEX_MM, 0.0) / 1.0)
    hu[tissue == arrays.TEETH] = HU["teeth"]
    hu[_table_mask(grid, tissue)] = HU["table"]
    hu = ndimage.gaussian_filter(hu, BLUR_VOXELS, mode="nearest", truncate=3.0)
    rng = np.random.default_rng(seed)
    hu += rng.standard_normal(hu.shape, dtype=np.float32) * np.float32(NOISE_HU)
    return hu


def _image(grid, data):
    img = pv.ImageData(dimensions=grid.dims, spacing=(grid.spacing,) * 3, origin=grid.origin)
    for name, values in data.items():
        img.point_data[name] = values.ravel()
    return img


def _patient_landmarks(warp):
    lm = landmarks()
    seg = landmark_segments()
    out = {}
    for name, p in lm.items():
        if seg[name] is None:
            out[name] = warp.forward(p[None])[0]
        else:
            out[name] = warp.forward_bone(p[None], seg[name])[0]
    return out


@functools.lru_cache(maxsize=8)
def _build(patient, spacing):
    t0 = time.perf_counter()
    params = template.patient_parameters(patient)
    warp = template.PatientWarp(params)
    grid = _grid_for(warp, spacing)
    log.info("phantom %d: grid %s at %.2f mm", patient, grid.dims, spacing)
    labels = rasterize(grid, warp)
    hu = _synthesize_ct(labels, grid, params.seed)
    ct = _image(grid, {arrays.CT: hu})
    truth = _image(grid, {k: labels[k] for k in (arrays.TISSUE, arrays.MUSCLE, arrays.BONE)})
    case = Case(name=f"patient {patient}", patient=patient, spacing=spacing, ct=ct, truth=truth,
                landmarks=_patient_landmarks(warp), plan=TABLE_II[patient], parameters=params)
    case.build_seconds = time.perf_counter() - t0
    log.info("phantom %d built in %.1f s", patient, case.build_seconds)
    return case


def phantom(patient=1, spacing=1.0, progress_bar=False):
    """Build virtual patient ``patient`` (1-4): CT, truth labels, landmarks and plan.

    The patients are the template head (:mod:`pvcmf.datasets.template`) through a smooth
    invertible warp and differ in size, soft-tissue thickness and jaw relation: 1 class II
    (maxilla 4 mm forward), 2 class III (maxilla 5 mm back), 3 class II (mandible 5.5 mm
    back), 4 class III (mandible 3.2 mm forward); each one's plan (Table II) corrects it.
    Built cases are cached in memory; every call returns an independent copy.

    Parameters
    ----------
    patient : int
        1, 2, 3 or 4.
    spacing : float
        Isotropic voxel size in mm, 0.5 .. 4.
    progress_bar : bool
        Show the build as a progress bar (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    Case
        ``ct`` (HU, see :data:`HU`), ``truth`` (``tissue``, ``muscle``, ``bone``),
        ``landmarks``, ``plan``, ``name``.

    Raises
    ------
    ValueError
        For a patient outside 1-4 or a spacing outside 0.5-4 mm.

    Examples
    --------
    >>> import pvcmf
    >>> case = pvcmf.datasets.phantom(patient=1, spacing=3.0)
    >>> case.ct["ct"].dtype
    dtype('float32')
    """
    template._check_patient(patient)
    spacing = _check_spacing(spacing)
    with Progress(total=1, desc=f"phantom {int(patient)}", enabled=progress_bar) as bar:
        case = _build(int(patient), spacing).copy()
        bar.step(f"{spacing:g} mm")
    return case


class _CallableModule(type(functools)):
    """Lets ``pvcmf.datasets.phantom`` be both this module and the builder function.

    Importing the submodule ``pvcmf.datasets.phantom`` rebinds the package attribute
    ``phantom`` to the module, so the module itself forwards calls to :func:`phantom`
    (``pvcmf.datasets.phantom(1)`` and ``pvcmf.datasets.phantom.HU`` both work).
    """

    def __call__(self, *args, **kwargs):
        return phantom(*args, **kwargs)


import sys as _sys  # noqa: E402

_sys.modules[__name__].__class__ = _CallableModule
