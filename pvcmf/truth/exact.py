"""The virtual patient's exact soft tissue: its boundary level sets and its muscle fractions.

Shared by the truth's meshers (:mod:`pvcmf.truth.independent`, :mod:`pvcmf.truth.conform`)
and its refinement measure (:mod:`pvcmf.truth.refinement`):

* :func:`_fields` / :func:`_region` - the boundary level sets of the soft tissue (skin,
  bone, teeth, air cavities with the tongue, brain case) at patient points and the signed
  region function (negative inside the soft tissue) with its active component;
* :func:`_project` - Newton projection onto the zero set of the region function;
* :func:`_materials` - each tetrahedron's muscle fraction from the exact muscle level sets;
* :func:`_volumes` - signed tetrahedron volumes.

Delegates to the analytic atlas (:mod:`pvcmf.atlas`) through the patient warp, and numpy.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

from .. import arrays
from ..atlas.muscles import _muscle_models
from ..atlas.shapes import F32
from ..atlas.skull import (braincase_sdf, cranium_vault_sdf, face_bone_sdf,
                           face_cavities_sdf, lower_teeth_sdf, mandible_sdf, spine_sdf,
                           upper_teeth_sdf)
from ..atlas.soft_tissue import (airway_sdf, eyes_sdf, neck_muscles_sdf, oral_air_sdf,
                                 skin_sdf, temporalis_sdf, tongue_sdf)


#: boundary components of the soft tissue: (name, sign): the region is where every
#: ``sign * f < 0``
_BOUNDARY = ("skin", "bone", "teeth", "air", "brain")

def _fields(warp, x):
    """The boundary level sets (mm, atlas frame; negative inside the structure) at patient
    points ``x`` (n, 3): dict name -> (n,)."""
    X = tuple(x[:, i].astype(F32) for i in range(3))
    base = warp.base_inverse(X)
    soft, face, mand = warp.soft(base), warp.face(base), warp.mandible(base)

    def f(fn, s):
        return np.asarray(fn(s), dtype=float)

    bone = np.minimum.reduce([f(cranium_vault_sdf, base), f(spine_sdf, base),
                              f(face_bone_sdf, face), f(mandible_sdf, mand)])
    teeth = np.minimum(f(upper_teeth_sdf, face), f(lower_teeth_sdf, mand))
    # the tongue is not meshed: with the oral air it is the oral cavity, a free surface
    air = np.minimum.reduce([f(face_cavities_sdf, face), f(oral_air_sdf, face),
                             f(airway_sdf, soft), f(tongue_sdf, soft)])
    return {"skin": f(skin_sdf, soft), "bone": bone, "teeth": teeth, "air": air,
            "brain": f(braincase_sdf, base)}



def _region(fields):
    """Signed region function (< 0 in the soft tissue) and the active component index."""
    parts = np.stack([fields["skin"], -fields["bone"], -fields["teeth"], -fields["air"],
                      -fields["brain"]])
    return parts.max(axis=0), parts.argmax(axis=0)



def _volumes(x, tets):
    q = x[tets]
    return np.einsum("ij,ij->i", np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]),
                     q[:, 3] - q[:, 0]) / 6



def _project(warp, p, steps=3, dh=0.2):
    """Newton projection of points ``p`` (n, 3) onto the zero set of the soft tissue's
    region function (gradient by central differences of ``dh`` mm)."""
    p = np.array(p, dtype=float)
    for _ in range(steps):  # a few Newton steps, each vectorised over the points
        r, _ = _region(_fields(warp, p))
        grad = np.column_stack([(_region(_fields(warp, p + dh * e))[0]
                                 - _region(_fields(warp, p - dh * e))[0]) / (2 * dh)
                                for e in np.eye(3)])
        p = p - (r / np.maximum(np.einsum("ij,ij->i", grad, grad), 1e-12))[:, None] * grad
    return p



def _materials(grid, warp, n=3):
    """Cell arrays tissue / muscle / muscle_fraction from the exact muscle level sets.

    ``muscle_fraction``: the share of ``(n + 1)(n + 2)(n + 3) / 6`` sample points of each
    tetrahedron (a barycentric lattice, shrunk towards the centroid) inside a muscle; the
    materials mix by it (:func:`pvcmf.filters.assign_materials`, rule of mixtures), so a
    muscle sheet thinner than the elements keeps its share of the stiffness on every mesh
    instead of being all or nothing by where a centroid falls. ``muscle``: the facial
    muscle at the centroid (0 elsewhere); ``tissue``: muscle where the fraction is at least
    one half."""
    x = np.asarray(grid.points, dtype=float)
    tets = np.asarray(grid.cells_dict[pv.CellType.TETRA])
    bary = np.array([(i, j, k, n - i - j - k) for i in range(n + 1) for j in range(n + 1 - i)
                     for k in range(n + 1 - i - j)], dtype=float) / n
    bary = np.vstack([np.full(4, 0.25), 0.7 * bary + 0.3 * 0.25])  # centroid first
    c = np.einsum("qv,evd->eqd", bary, x[tets]).reshape(-1, 3)
    X = tuple(c[:, i].astype(F32) for i in range(3))
    s = warp.soft(warp.base_inverse(X))
    muscle = np.zeros(len(c), dtype=np.uint8)
    for name, model in _muscle_models().items():  # twelve muscles, vectorised inside
        muscle[(muscle == 0) & (np.asarray(model(s)) < 0)] = arrays.MUSCLE_IDS[name]
    generic = np.minimum.reduce([np.asarray(fn(s), float)
                                 for fn in (tongue_sdf, temporalis_sdf, neck_muscles_sdf)])
    eye = np.asarray(eyes_sdf(s), float) < 0
    muscle[eye] = 0
    inside = (((muscle > 0) | (generic < 0)) & ~eye).reshape(len(tets), -1)
    fraction = inside[:, 1:].mean(axis=1)
    grid.cell_data[arrays.TISSUE] = np.where(fraction >= 0.5, arrays.MUSCLE_TISSUE,
                                             arrays.FAT).astype(np.uint8)
    grid.cell_data[arrays.MUSCLE] = muscle.reshape(len(tets), -1)[:, 0]
    grid.cell_data[arrays.MUSCLE_FRACTION] = fraction


def _labelled_grid(x, tets, free, plane, warp):
    """The truth's tetrahedral grid: point array ``boundary`` (0 inside; 1 + the index in
    :data:`_BOUNDARY` of the exact surface a free boundary node lies on; ``len(_BOUNDARY)
    + 1`` on the posterior plane) and the cell materials of :func:`_materials`."""
    boundary = np.zeros(len(x), dtype=np.uint8)
    _, active = _region(_fields(warp, x[free]))
    boundary[free] = active + 1
    boundary[plane] = len(_BOUNDARY) + 1
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: tets}, x)
    grid.point_data["boundary"] = boundary
    _materials(grid, warp)
    return grid

