"""Shared pytest set-up: offscreen rendering, the real-data folder, small cached inputs."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import pyvista as pv

from pvcmf.figures.offscreen import prefer_egl

pv.OFF_SCREEN = True
prefer_egl()  # headless: EGL straight away, without VTK's failed X attempt
ROOT = Path(__file__).resolve().parents[1]

# Tests find the shared real data through PVCMF_DATA_DIR, defaulting to ../shared/data.
os.environ.setdefault("PVCMF_DATA_DIR", str(ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def data_dir():
    """The shared real-data folder; skip cleanly when it is absent."""
    path = Path(os.environ["PVCMF_DATA_DIR"])
    if not path.is_dir():
        pytest.skip(f"real data folder {path} not found (set PVCMF_DATA_DIR)")
    return path


@pytest.fixture(scope="session")
def female_ct(data_dir):
    """The Visible Human female head CT in the patient frame, read once per run, with its
    values as an (x, y, z) array: ``(image, values)``. Tests crop it (:func:`crop_ct`) and
    never write into it."""
    import numpy as np

    import pvcmf
    from pvcmf import arrays

    root = data_dir / "vhp_female_head"
    if not root.is_dir():
        pytest.skip(f"{root} not found (set PVCMF_DATA_DIR to the real-data folder)")
    ct = pvcmf.read_ct(root, frame="patient")
    return ct, np.asarray(ct[arrays.CT]).reshape(ct.dimensions, order="F")


def _crop_ct(ct, values, box):
    import numpy as np

    from pvcmf import arrays

    sub = values[tuple(box)]
    origin = np.asarray(ct.origin) + np.asarray(ct.spacing) * [b.start for b in box]
    img = pv.ImageData(dimensions=sub.shape, spacing=ct.spacing, origin=origin)
    img[arrays.CT] = np.ascontiguousarray(sub).ravel(order="F")
    return img


@pytest.fixture()
def verify_image_cache(verify_image_cache):
    """pytest-pyvista image comparison with baselines in tests/image_cache."""
    verify_image_cache.high_variance_test = False
    return verify_image_cache


CHART_DIR = ROOT / "tests" / "image_cache" / "charts"


@pytest.fixture()
def verify_chart(request):
    """Compare a matplotlib figure with its baseline PNG in ``tests/image_cache/charts``.

    Call ``verify_chart(fig)`` (optionally ``verify_chart(fig, "suffix", tol=...)``).
    A missing baseline fails the test unless ``PVCMF_UPDATE_BASELINES=1`` is set, which
    writes it (then inspect it and commit it). ``tol`` is matplotlib's RMS tolerance.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.testing.compare import compare_images

    def check(fig, suffix="", tol=10.0, dpi=80):
        name = request.node.name.replace("[", "_").replace("]", "") + (f"_{suffix}" if suffix else "")
        baseline = CHART_DIR / f"{name}.png"
        out_dir = ROOT / "tests" / "_image_failures"
        out_dir.mkdir(parents=True, exist_ok=True)
        actual = out_dir / f"{name}.png"
        fig.savefig(actual, dpi=dpi)
        if not baseline.exists():
            if os.environ.get("PVCMF_UPDATE_BASELINES") == "1":
                CHART_DIR.mkdir(parents=True, exist_ok=True)
                fig.savefig(baseline, dpi=dpi)
                return
            pytest.fail(f"no chart baseline {baseline}; run with PVCMF_UPDATE_BASELINES=1 to create it")
        result = compare_images(str(baseline), str(actual), tol=tol)
        assert result is None, result

    return check


@pytest.fixture(scope="session")
def segmented_patients():
    """The four virtual patients at 2 mm with their ``segment()`` output, built once.

    ``{patient: (case, labels)}``; shared by test_segment.py and test_classify.py.
    """
    import pvcmf

    out = {}
    for p in (1, 2, 3, 4):
        case = pvcmf.datasets.phantom(patient=p, spacing=2.0)
        out[p] = (case, case.ct.cmf.segment())
    return out


@pytest.fixture(scope="session")
def crop_ct():
    """``crop_ct(ct, values, box)``: a new image of ``values[box]`` (three slices) with
    ``ct``'s spacing, placed where the box lies in ``ct``."""
    return _crop_ct
