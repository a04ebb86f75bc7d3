"""What the pipeline says it did: the reason given for a skipped step names what happened."""

import numpy as np
import pyvista as pv

from pvcmf import arrays
from pvcmf.plan import Osteotomy, Plan


def _labels(*segments):
    img = pv.ImageData(dimensions=(4, 4, 4))
    bone = np.full(img.n_points, arrays.CRANIUM, dtype=np.uint8)
    for i, seg in enumerate(segments):
        bone[i] = seg
    img[arrays.BONE] = bone
    return img


def test_skipped_bone_segments_names_where_each_segment_comes_from():
    """Without a bone-segment image each planned segment comes from its cut planes, the
    labels or the anatomy (find_jaws): the message names the one that applies, per segment."""
    from pvcmf.pipeline import _segment_sources

    cut = (((0.0, 0.0, 1.5), (0.0, 0.0, -1.0)),)
    plan = Plan((Osteotomy("maxilla", cut=cut), Osteotomy("mandible")))
    anatomy = _segment_sources(_labels(), plan)
    assert "maxilla from the plan's cut planes" in anatomy
    assert "mandible from the anatomy (find_jaws)" in anatomy
    labelled = _segment_sources(_labels(arrays.MANDIBLE), plan)
    assert "mandible from the labels" in labelled and "anatomy" not in labelled
    assert "cut planes" not in _segment_sources(_labels(arrays.MANDIBLE),
                                                Plan((Osteotomy("mandible"),)))


def test_simulate_reports_segments_found_from_the_labels():
    """A virtual patient's labels carry the planned segments: the skipped step says so (and
    not that the segments came from cut planes the plan does not have)."""
    import pvcmf
    from pvcmf.pipeline import simulate

    case = pvcmf.datasets.phantom(patient=1, spacing=3.0)
    assert not any(o.cut for o in case.plan.osteotomies)
    res = simulate(case.ct, case.plan, labels=case.truth, predict=False, figures=False,
                   out=None)
    why = res.skipped["bone segments"]
    assert "from the labels" in why and "cut planes" not in why
