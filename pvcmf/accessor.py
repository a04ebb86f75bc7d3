"""The ``cmf`` dataset accessor: ``dataset.cmf.<step>(...)`` chains the pipeline.

Every method only delegates to the pure filter of the same name in :mod:`pvcmf.filters`
(or :func:`pvcmf.mtm.solve`), passing the dataset as first argument, so that::

    mesh = case.ct.cmf.segment().cmf.embed_muscles(landmarks=case.landmarks)

reads as the paper's pipeline. Registered on :class:`pyvista.DataSet`, so it exists on
ImageData, UnstructuredGrid and PolyData alike. Delegates to
``pyvista.register_dataset_accessor``.
"""

from __future__ import annotations

import pyvista as pv

from . import filters


def _delegate(name, module=None):
    def method(self, *args, **kwargs):
        func = getattr(module() if module else filters, name)
        return func(self._dataset, *args, **kwargs)

    method.__name__ = name
    method.__doc__ = f"Delegate to :func:`pvcmf.filters.{name}` with this dataset first."
    return method


def _mtm():
    from . import mtm

    return mtm


@pv.register_dataset_accessor("cmf", pv.DataSet)
class CMFAccessor:
    """Pipeline steps of pvcmf on any PyVista dataset (see :mod:`pvcmf.filters`)."""

    def __init__(self, dataset):
        self._dataset = dataset

    segment = _delegate("segment")
    classify_tissue = _delegate("classify_tissue")
    embed_muscles = _delegate("embed_muscles")
    fiber_directions = _delegate("fiber_directions")
    tetrahedralize = _delegate("tetrahedralize")
    sample_muscle_fraction = _delegate("sample_muscle_fraction")
    average_voxels = _delegate("average_voxels")
    assign_materials = _delegate("assign_materials")
    cut_bones = _delegate("cut_bones")
    move_bones = _delegate("move_bones")
    apply_plan = _delegate("apply_plan")
    skin = _delegate("extract_skin")
    register = _delegate("register")
    distance_to = _delegate("distance_to")
    map_to_surface = _delegate("map_to_surface")
    solve = _delegate("solve", _mtm)
    stiffness = _delegate("stiffness", _mtm)
