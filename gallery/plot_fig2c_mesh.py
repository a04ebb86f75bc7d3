"""Paper 000 Fig. 2c: the muscle-embedded volumetric mesh, cut open
==================================================================

One step from the tissue + muscle label image of virtual patient 1 to a tetrahedral mesh
in which every tetrahedron lies in fat (yellow) or in one muscle (red), with element faces
on the muscle surfaces (``pvcmf.filters.tetrahedralize``: SurfaceNets multi-label
surfaces, then gmsh per region). The mesh is cut horizontally through the masseters; the
tetrahedra below the cut are drawn whole, the rest as a translucent skin.
"""

import os
import warnings
from pathlib import Path

import pyvista as pv

import pvcmf
from pvcmf import arrays
from pvcmf.figures.mesh import mesh_figure

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)

labels = pvcmf.datasets.phantom(1, spacing=2.0).truth
with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # muscles thinner than the mesh would be named here
    mesh = labels.cmf.tetrahedralize(n_tets=60_000)
masseter = mesh.extract_cells(mesh.cell_data[arrays.MUSCLE] == arrays.MUSCLE_IDS["masseter_left"])
plotter = mesh_figure(mesh, normal=(0.0, 0.0, 1.0), origin=masseter.center)
plotter.screenshot(OUT / "fig2c_mesh.png")
