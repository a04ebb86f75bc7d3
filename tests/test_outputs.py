"""Files a run writes: only the documented arrays, and error messages in plain words."""

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays


def test_written_skins_hold_only_documented_arrays(tmp_path):
    """predicted_skin.vtp, skin_pre.vtp and deformed_mesh.vtu carry no VTK-internal arrays
    (``vtkOriginalPointIds`` / ``vtkOriginalCellIds`` index meshes the run does not write);
    the skins hold the displacement and the modelled flag of pvcmf.arrays; the result in
    memory keeps its arrays."""
    import pvcmf
    from pvcmf.pipeline import simulate

    case = pvcmf.datasets.phantom(patient=1, spacing=3.0)
    res = simulate(case.ct, case.plan, tmp_path / "run", bones=case.truth, n_tets=3000,
                   muscles=False, figures=False)
    for name in ("predicted_skin.vtp", "skin_pre.vtp"):
        skin = pv.read(tmp_path / "run" / name)
        assert set(skin.point_data.keys()) <= {arrays.DISPLACEMENT, arrays.SKIN_MODELLED,
                                               arrays.NORMALS}, name
        assert arrays.DISPLACEMENT in skin.point_data and not skin.cell_data.keys(), name
    mesh = pv.read(tmp_path / "run" / "deformed_mesh.vtu")
    for data in (mesh.point_data, mesh.cell_data):
        assert not [k for k in data.keys() if k.startswith("vtk")]
    written = pv.read(tmp_path / "run" / "predicted_skin.vtp")
    np.testing.assert_array_equal(written[arrays.DISPLACEMENT], res.skin_post[arrays.DISPLACEMENT])
    assert arrays.ORIGINAL_POINT_IDS in res.skin_post.point_data  # the input is untouched


@pytest.mark.parametrize("n, words", [(1, "1 entry but"), (2, "2 entries but")])
def test_out_refusal_counts_entries_in_plain_words(tmp_path, n, words):
    """A folder that holds no earlier run is refused; the count reads '1 entry', '2 entries'."""
    from pvcmf.outputs import check_output_dir

    for i in range(n):
        (tmp_path / f"f{i}.txt").write_text("x")
    with pytest.raises(ValueError, match=words):
        check_output_dir(tmp_path)
