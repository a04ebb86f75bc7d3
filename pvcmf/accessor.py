"""The ``cmf`` dataset accessor: ``dataset.cmf.<step>(...)`` chains the pipeline.

Every method is the pure filter of the same name in :mod:`pvcmf.filters` (or
:func:`pvcmf.mtm.solve` / :func:`pvcmf.mtm.stiffness`) with this dataset as its first
argument, so that::

    mesh = case.ct.cmf.segment().cmf.embed_muscles(landmarks=case.landmarks)

reads as the paper's pipeline. Each method carries its filter's docstring and signature
(less the dataset): ``help(grid.cmf.solve)`` and ``inspect.signature(grid.cmf.solve)``
show the filter's parameters. A method is built on first use, so ``import pvcmf`` does not
import the filters' modules. Registered on :class:`pyvista.DataSet`, so it exists on
ImageData, UnstructuredGrid and PolyData alike. Delegates to
``pyvista.register_dataset_accessor`` and :func:`functools.wraps`.
"""

from __future__ import annotations

import functools
import importlib

import pyvista as pv

__all__ = ["CMFAccessor", "METHODS"]

#: accessor method -> (module, function) it delegates to
METHODS = {
    "standardize": ("pvcmf.filters", "standardize"),
    "working_grid": ("pvcmf.filters", "working_grid"),
    "flatten_shading": ("pvcmf.filters", "flatten_shading"),
    "segment": ("pvcmf.filters", "segment"),
    "find_jaws": ("pvcmf.filters", "find_jaws"),
    "classify_tissue": ("pvcmf.filters", "classify_tissue"),
    "embed_muscles": ("pvcmf.filters", "embed_muscles"),
    "fiber_directions": ("pvcmf.filters", "fiber_directions"),
    "tetrahedralize": ("pvcmf.filters", "tetrahedralize"),
    "sample_muscle_fraction": ("pvcmf.filters", "sample_muscle_fraction"),
    "average_voxels": ("pvcmf.filters", "average_voxels"),
    "assign_materials": ("pvcmf.filters", "assign_materials"),
    "cut_bones": ("pvcmf.filters", "cut_bones"),
    "move_bones": ("pvcmf.filters", "move_bones"),
    "apply_plan": ("pvcmf.filters", "apply_plan"),
    "skin": ("pvcmf.filters", "extract_skin"),
    "register": ("pvcmf.filters", "register"),
    "distance_to": ("pvcmf.filters", "distance_to"),
    "map_to_surface": ("pvcmf.filters", "map_to_surface"),
    "transfer_operator": ("pvcmf.filters", "transfer_operator"),
    "fit_to_skin": ("pvcmf.filters", "fit_to_skin"),
    "dense_skin": ("pvcmf.filters.meshing.skin_fit", "dense_skin"),
    "head_skin": ("pvcmf.filters.skin", "head_skin"),
    "unavoidable_crumples": ("pvcmf.filters.crumple_bound", "unavoidable_crumples"),
    "plan_response": ("pvcmf.mtm.response", "plan_response"),
    "solve": ("pvcmf.mtm", "solve"),
    "stiffness": ("pvcmf.mtm", "stiffness"),
    "export": ("pvcmf.io", "export"),
}


def _method(name, func):
    """``func`` as a method passing the accessor's dataset first (docstring and signature
    of ``func``: ``inspect.signature`` of the bound method drops the dataset)."""

    @functools.wraps(func)
    def method(self, *args, **kwargs):
        return func(self._dataset, *args, **kwargs)

    method.__name__ = name
    method.__qualname__ = f"CMFAccessor.{name}"
    return method


class _Delegate:
    """Class attribute that builds its method from the filter on first access."""

    def __init__(self, name, module, function):
        self.name, self.module, self.function = name, module, function

    def __get__(self, instance, owner):
        func = getattr(importlib.import_module(self.module), self.function)
        method = _method(self.name, func)
        setattr(owner, self.name, method)  # replace the descriptor: built once
        return method if instance is None else method.__get__(instance, owner)


@pv.register_dataset_accessor("cmf", pv.DataSet)
class CMFAccessor:
    """Pipeline steps of pvcmf on any PyVista dataset (see :mod:`pvcmf.filters`)."""

    def __init__(self, dataset):
        self._dataset = dataset


for _name, (_module, _function) in METHODS.items():
    setattr(CMFAccessor, _name, _Delegate(_name, _module, _function))
del _name, _module, _function
