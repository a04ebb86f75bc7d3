"""The data model and the accessor contract."""

import numpy as np
import pytest
import pyvista as pv

import pvcmf
from pvcmf import arrays


def test_labels_are_distinct():
    assert len(set(arrays.TISSUE_LABELS.values())) == len(arrays.TISSUE_LABELS)
    assert len(set(arrays.BC_CODES.values())) == len(arrays.BC_CODES)
    assert arrays.MUSCLE_IDS[arrays.MUSCLES[0]] == 1
    assert len(arrays.MUSCLES) == 12 and max(arrays.MUSCLE_IDS.values()) < 256


def test_require_array_messages():
    img = pv.ImageData(dimensions=(2, 2, 2))
    img[arrays.CT] = np.zeros(8, dtype=np.float32)
    assert arrays.require_array(img, arrays.CT, "point", dtype="f", ncomp=1).shape == (8,)
    with pytest.raises(ValueError, match="no point array 'tissue'.*segment"):
        arrays.require_array(img, arrays.TISSUE, producer="segment")
    with pytest.raises(ValueError, match="dtype unsigned int"):
        arrays.require_array(img, arrays.CT, dtype="u")
    with pytest.raises(ValueError, match="3 component"):
        arrays.require_array(img, arrays.CT, ncomp=3)
    with pytest.raises(ValueError, match="association"):
        arrays.require_array(img, arrays.CT, "vertex")


@pytest.mark.parametrize("cls", [pv.ImageData, pv.UnstructuredGrid, pv.PolyData])
def test_accessor_registered(cls):
    ds = cls()
    for name in ("segment", "tetrahedralize", "solve", "apply_plan", "distance_to"):
        assert callable(getattr(ds.cmf, name))


def test_accessor_methods_carry_their_filters_signature_and_docstring():
    """``inspect.signature(ds.cmf.<m>)`` is the filter's, less the dataset, for every method."""
    import importlib
    import inspect

    from pvcmf.accessor import METHODS

    ds = pv.Sphere()
    for name, (module, function) in METHODS.items():
        func = getattr(importlib.import_module(module), function)
        params = list(inspect.signature(func).parameters.values())[1:]
        assert inspect.signature(getattr(ds.cmf, name)) == inspect.Signature(params), name
        assert getattr(ds.cmf, name).__doc__ == func.__doc__, name
        assert getattr(pvcmf.CMFAccessor, name).__name__ == name


def test_accessor_passes_the_dataset_first():
    img = pv.ImageData(dimensions=(4, 4, 4))
    img[arrays.TISSUE] = np.full(64, arrays.FAT, dtype=np.uint8)
    img[arrays.BONE] = np.zeros(64, dtype=np.uint8)
    from pvcmf.plan import Osteotomy, Plan

    plan = Plan((Osteotomy("mandible", (0.0, 0.0, 1.0), cut=[((0, 0, 0), (0, 0, 1))]),))
    with pytest.raises(ValueError, match="no bone"):
        img.cmf.cut_bones(plan)


def test_filters_registry_names_exist():
    assert set(pvcmf.filters.__all__) <= set(dir(pvcmf.filters))
    with pytest.raises(AttributeError):
        pvcmf.filters.not_a_filter


def test_plan_table_ii_and_matrix():
    from pvcmf.plan import TABLE_II, Osteotomy

    o = TABLE_II[1].osteotomies[0]
    assert o.segment == "maxilla" and o.translation == (6.0, 5.0, -4.0)
    m = Osteotomy("mandible", (1.0, 2.0, 3.0)).matrix()
    # (horizontal, vertical, AP) -> (x, z, y)
    np.testing.assert_allclose(m[:3, 3], [1.0, 3.0, 2.0])
    r = Osteotomy("maxilla", rotation=(0, 0, 30)).matrix(centroid=(1, 2, 3))
    np.testing.assert_allclose(r[:3, :3] @ r[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(r[:3, :3] @ [1, 2, 3] + r[:3, 3], [1, 2, 3], atol=1e-12)
    with pytest.raises(ValueError, match="segment"):
        Osteotomy("cranium")
    with pytest.raises(ValueError, match="translation"):
        Osteotomy("maxilla", (np.nan, 0, 0))
