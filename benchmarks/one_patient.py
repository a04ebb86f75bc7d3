"""The pipeline on one virtual patient against its post-operative truth.

Run: ``python benchmarks/one_patient.py [--patient 1] [--spacing 2] [--n-tets 30000]
[--truth-tets 16000]`` (not run by CI; the truth needs the ``reference`` extra and is
read from the cache when it was solved before). Runs :func:`pvcmf.pipeline.simulate` on
virtual patient ``--patient`` with its true bone labels and landmarks, solves (or reads)
its post-operative truth (:func:`pvcmf.truth.grid.postop_skin`) and prints the |error|
p50 / p90 / p95 (mm) of the predicted skin against the truth's skin:

* on the face regions of :func:`pvcmf.study.statistics.label_face_regions` (every region
  but ``other``);
* over the whole dense skin;
* over the solved grid's free boundary instead of the dense skin (it also holds the walls
  of the mouth and airway and the neck's cut, which no skin scan shows).

These are the numbers of the "pipeline on one patient" paragraph of
``docs/benchmarks/study.md``.
"""

from __future__ import annotations

import argparse

import numpy as np

import pvcmf
from pvcmf import arrays
from pvcmf.pipeline import simulate
from pvcmf.study.statistics import label_face_regions
from pvcmf.truth.grid import postop_skin


def percentiles(values):
    """p50 / p90 / p95 of ``|values|`` (mm) as a string."""
    q = np.percentile(np.abs(values), [50, 90, 95])
    return " / ".join(f"{v:.2f}" for v in q)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patient", type=int, default=1)
    ap.add_argument("--spacing", type=float, default=2.0)
    ap.add_argument("--n-tets", type=int, default=30_000)
    ap.add_argument("--truth-tets", type=int, default=16_000)
    args = ap.parse_args(argv)

    case = pvcmf.datasets.phantom(patient=args.patient, spacing=args.spacing)
    res = simulate(case.ct, case.plan, bones=case.truth, landmarks=case.landmarks,
                   n_tets=args.n_tets, figures=False)
    truth = postop_skin(case, n_tets=args.truth_tets)
    err = res.skin_post.cmf.distance_to(truth)
    d = np.asarray(err[arrays.DISTANCE])
    face = np.asarray(label_face_regions(res.skin_post, landmarks=case.landmarks)[arrays.REGION])
    boundary = res.post.extract_surface(algorithm=None).warp_by_vector(arrays.DISPLACEMENT)
    d_boundary = np.asarray(boundary.cmf.distance_to(truth)[arrays.DISTANCE])
    print(f"patient {args.patient}, {args.spacing:g} mm, {res.mesh.n_cells} tetrahedra, "
          f"truth of {args.truth_tets} tetrahedra; |error| p50 / p90 / p95 mm:")
    print(f"  face regions ({int((face > 0).sum())} skin points): {percentiles(d[face > 0])}")
    print(f"  whole skin ({len(d)} points): {percentiles(d)}")
    print(f"  grid's free boundary ({len(d_boundary)} points): {percentiles(d_boundary)}")


if __name__ == "__main__":
    main()
