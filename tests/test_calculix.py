"""CalculiX (ccx) solves the exported .inp to the MTM's displacements.

An independent finite-element code on the same linear tetrahedra: its C3D4 element with the
engineering constants, orientation distribution and sliding *EQUATIONs of the export must
give pvcmf's MTM displacements to ccx's printed precision (7 significant digits). Skips
without ``ccx`` (Debian/Ubuntu: ``apt-get install calculix-ccx``).
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from test_export import mixed_box

import pvcmf
from pvcmf import arrays
from pvcmf.io import calculix_available, run_calculix

pytestmark = pytest.mark.skipif(calculix_available() is None,
                                reason="CalculiX 'ccx' not installed (apt-get install calculix-ccx)")


def _rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def test_mixed_box_matches_mtm(tmp_path):
    grid = mixed_box()
    u_mtm = np.asarray(pvcmf.mtm.solve(grid)[arrays.DISPLACEMENT])
    u_ccx, _ = run_calculix(grid, tmp_path)
    assert _rel(u_ccx, u_mtm) < 1e-6
    again, _ = run_calculix(tmp_path / "model.inp", tmp_path / "rerun")  # a deck on disk
    assert np.array_equal(again, u_ccx)
    # prescribed values hold in ccx's answer: joint, fixed, and the sliding normal part
    bc = grid[arrays.BC]
    joint = bc == arrays.BC_JOINT
    assert np.allclose(u_ccx[joint], grid[arrays.BC_DISPLACEMENT][joint], atol=1e-6)
    assert np.all(u_ccx[bc == arrays.BC_FIXED] == 0)
    s = bc == arrays.BC_SLIDING
    n = grid[arrays.BC_NORMAL][s] / np.linalg.norm(grid[arrays.BC_NORMAL][s], axis=1)[:, None]
    assert np.allclose(np.einsum("ij,ij->i", u_ccx[s], n),
                       np.einsum("ij,ij->i", grid[arrays.BC_DISPLACEMENT][s], n), atol=1e-6)


def test_fibres_matter():
    """The comparison can fail: other fibres (or none) give a clearly different field."""
    grid, other = mixed_box(), mixed_box(fiber_tilt=-2.0)
    u = np.asarray(pvcmf.mtm.solve(grid)[arrays.DISPLACEMENT])
    u_other = np.asarray(pvcmf.mtm.solve(other)[arrays.DISPLACEMENT])
    u_ccx, _ = run_calculix(grid)
    assert _rel(u_other, u) > 1e-3 and _rel(u_ccx, u_other) > 1e-3


@pytest.mark.slow
def test_phantom_pipeline_matches_mtm(tmp_path):
    """The demo model (virtual patient 1, 2 mm voxels, a few thousand tetrahedra)."""
    from pvcmf import datasets
    from pvcmf.pipeline import simulate

    case = datasets.phantom(patient=1, spacing=2.0)
    result = simulate(case.ct, case.plan, None, bones=case.truth,
                      landmarks=getattr(case, "landmarks", None), n_tets=3000, figures=False)
    if result.post is None:
        pytest.skip(f"the pipeline made no prediction: {result.skipped}")
    post = result.post
    start = time.perf_counter()
    u_ccx, seconds = run_calculix(post, tmp_path)
    total = time.perf_counter() - start
    u = np.asarray(post[arrays.DISPLACEMENT])
    err = _rel(u_ccx, u)
    print(f"phantom: {post.n_cells} tets, {post.n_points} nodes, ccx {seconds:.2f} s "
          f"(with export {total:.2f} s), relative difference {err:.2e}")
    assert err < 1e-6
