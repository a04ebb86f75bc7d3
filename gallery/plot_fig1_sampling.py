"""Paper 000 Fig. 1: random-point sampling of a tetrahedron's muscle share
=========================================================================

The state of the art meshes the soft tissue homogeneously and finds the share of muscle in
each tetrahedron by sampling: random points are drawn uniformly inside the tetrahedron and
tested against the muscle (black outside, red inside). The share converges only as
``1 / sqrt(n)``; the title compares it with the exact share (the tetrahedron clipped by the
muscle). ``pvcmf.filters.sample_muscle_fraction`` does this for every tetrahedron at once.
"""

import os
from pathlib import Path

import pyvista as pv

from pvcmf.figures.sampling import sampling_figure

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)

plotter = sampling_figure(n_points=150, seed=0)
plotter.screenshot(OUT / "fig1_sampling.png")
