"""Paper 001 Fig. 1: fat and muscle by a per-slice Gaussian mixture and EM
=========================================================================

A real head CT (the Visible Human female head, ``$PVCMF_DATA_DIR/vhp_female_head``, read in
the patient frame and copied at 2 mm) is segmented (:func:`pvcmf.filters.segment`: skin,
bone, teeth, intracranial volume, air cavities); the soft tissue is then split into fat and
muscle by :func:`pvcmf.filters.classify_tissue`: per axial slice, a mixture of five
Gaussians is fitted by EM to the histogram of the soft-tissue HU, the threshold is where
the fat and muscle posteriors are equal, and a 5x5 median filter per slice removes
isolated voxels. The slice shown is the one through the most teeth (the masseters and the
tongue lie in it). (a) histogram, the five initial Gaussians (grey dots) and their sum
(dark grey dashes), (b) after EM, (c) the slice after the threshold (fat orange, muscle
white, bone blue), (d) after the median filter. Without the real data the virtual patient
is used.
"""

import os
from pathlib import Path

import numpy as np
import pyvista as pv

import pvcmf
from pvcmf import arrays
from pvcmf.figures.gmm import fig1_gmm

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)

folder = Path(os.environ.get("PVCMF_DATA_DIR", "")) / "vhp_female_head"
if folder.is_dir():
    ct = pvcmf.read_ct(folder, frame="patient")
    v = np.asarray(ct[arrays.CT]).reshape(ct.dimensions, order="F")[::2, ::2, ::2]
    ct2 = pv.ImageData(dimensions=v.shape, spacing=tuple(2 * np.asarray(ct.spacing)),
                       origin=ct.origin)
    ct2[arrays.CT] = np.ascontiguousarray(v).ravel(order="F")
else:
    ct2 = pvcmf.datasets.phantom(patient=1, spacing=2.0).ct
labels = pvcmf.filters.segment(ct2)
tissue = np.asarray(labels[arrays.TISSUE]).reshape(labels.dimensions, order="F")
k = int(np.argmax((tissue == arrays.TEETH).sum(axis=(0, 1))))
fig = fig1_gmm(labels, slice_index=k, n_components=5)
fig.savefig(OUT / "fig1_gmm_classification.png", dpi=100)
