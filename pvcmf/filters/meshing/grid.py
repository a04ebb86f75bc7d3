"""The working grid: the label image as region codes, resampled at the meshing spacing.

The soft tissue is resampled by nearest neighbour on an isotropic grid; a named muscle
also claims, fullest cells first (box average, ``scipy.ndimage.uniform_filter``), working
voxels until they hold its volume, so that muscles thinner than the spacing keep a layer
of working voxels. Configurations that would make the surfaces non-manifold (a label
touching itself or another only along an edge or at a corner) are repaired, muscles never
losing voxels, and muscle fragments the coarse grid adds are given to the fat. Every
connected region then gets its own label (``scipy.ndimage.label``).
"""

from __future__ import annotations

import logging
import warnings

import numpy as np
from scipy import ndimage

from ... import arrays

log = logging.getLogger(__name__)

# working-grid codes: 0 air (SurfaceNets background), 1 not meshed (bone, teeth, brain...),
# 2 fat, 3 + m muscle m (m = 0 for muscle tissue without a muscle id)
_AIR, _OTHER, _FAT, _MUSCLE0 = 0, 1, 2, 3
_N_CODES = _MUSCLE0 + len(arrays.MUSCLES) + 1
#: named muscles claim working voxels up to their volume (False: nearest neighbour only)
_CLAIM_MUSCLES = True


class SurfaceError(RuntimeError):
    """The multi-label surfaces are not a valid input for the volume mesher."""


def _code_name(code):
    if code == _FAT:
        return "fat"
    if code == _MUSCLE0:
        return "muscle tissue without id"
    return arrays.MUSCLES[code - _MUSCLE0 - 1]


def _codes(tissue, muscle, conforming):
    """Working-grid code per image point (see the ``_AIR`` ... ``_MUSCLE0`` codes)."""
    code = np.full(tissue.shape, _OTHER, dtype=np.uint8)
    code[tissue == arrays.AIR] = _AIR
    code[tissue == arrays.FAT] = _FAT
    is_muscle = tissue == arrays.MUSCLE_TISSUE
    if not conforming:
        code[is_muscle] = _FAT
    else:
        m = muscle[is_muscle].astype(np.int64) if muscle is not None else 0
        if np.any(np.asarray(m) > len(arrays.MUSCLES)):
            raise ValueError(
                f"labels: point array {arrays.MUSCLE!r} holds ids up to {int(np.max(m))}, "
                f"expected 0..{len(arrays.MUSCLES)}"
            )
        code[is_muscle] = _MUSCLE0 + m
    return code


def _check_muscles(code, voxel_volume, stacklevel=3):
    """Warn about muscles that are too small to be meshed (a voxel or two).

    ``stacklevel``: of the warning, to point at the caller of the filter.
    """
    named = code[code > _MUSCLE0].astype(np.intp) - (_MUSCLE0 + 1)
    counts = np.bincount(named, minlength=_N_CODES - _MUSCLE0 - 1)
    tiny = np.flatnonzero((counts > 0) & (counts < 8))
    if tiny.size:
        names = ", ".join(f"{arrays.MUSCLES[i]} ({counts[i]} voxel(s))" for i in tiny)
        warnings.warn(
            f"muscle(s) {names} are too small to be meshed as their own region "
            f"(< 8 voxels, {8 * voxel_volume:.3g} mm^3); they are merged into the fat",
            stacklevel=stacklevel,
        )
        for i in tiny:
            code[code == _MUSCLE0 + 1 + i] = _FAT


def _crop_fine(code_zyx, labels, offset=(0, 0, 0)):
    """The code volume cropped to the soft-tissue box plus one voxel: (code, origin, spacing).

    ``offset``: the image index (x, y, z) of ``code_zyx[0, 0, 0]`` (a cropped image).
    """
    sp = np.asarray(labels.spacing, float)
    soft = code_zyx >= _FAT
    box = []
    for ax in range(3):  # array axes z, y, x
        idx = np.flatnonzero(soft.any(axis=tuple(a for a in range(3) if a != ax)))
        box.append(slice(max(idx[0] - 1, 0), min(idx[-1] + 2, code_zyx.shape[ax])))
    lo = np.array([box[2].start, box[1].start, box[0].start]) + np.asarray(offset, np.int64)
    return np.ascontiguousarray(code_zyx[tuple(box)]), np.asarray(labels.origin, float) + lo * sp, sp


def _working_grid(fine, s):
    """Resample the (cropped) code volume on a grid of spacing ``s``.

    Nearest neighbour, except that a named muscle also claims the fat of the working-grid
    voxels it reaches within ``s / 2`` (so a muscle thinner than ``s`` keeps a layer of
    working voxels; its surfaces are then placed on the fine interfaces by
    :func:`_fine_targets`).
    """
    code_zyx, origin0, sp = fine[:3]
    soft = code_zyx >= _FAT
    lo, hi = [], []
    for axis in range(3):  # x, y, z -> array axes 2, 1, 0
        any_ = soft.any(axis=tuple(a for a in range(3) if a != 2 - axis))
        idx = np.flatnonzero(any_)
        lo.append(idx[0])
        hi.append(idx[-1])
    lo, hi = np.array(lo), np.array(hi)
    extent = (hi - lo) * sp
    n = np.floor(extent / s + 1e-9).astype(int) + 1
    # centre the working grid on the soft-tissue box
    start = lo * sp + 0.5 * (extent - (n - 1) * s)
    idx = [
        np.clip(np.rint((start[k] + np.arange(n[k]) * s) / sp[k]).astype(int), 0, code_zyx.shape[2 - k] - 1)
        for k in range(3)
    ]
    sub = code_zyx[np.ix_(idx[2], idx[1], idx[0])]
    half = np.floor(0.5 * s / sp[::-1] + 1e-9).astype(int)  # array axes z, y, x
    if _CLAIM_MUSCLES and np.any(half >= 1):
        _claim_muscles(sub, code_zyx, idx[::-1], half, float(np.prod(sp)) / s**3)
    origin = origin0 + start
    return sub, origin


def _claim_muscles(sub, code_zyx, idx_zyx, half, cell_ratio):
    """Give every named muscle about as many working voxels as its volume.

    Nearest-neighbour resampling loses a muscle thinner than the working spacing where it
    passes between the samples (and keeps it where it hits one). Here the share of muscle
    ``m`` in the box of the working spacing around every working voxel
    (``scipy.ndimage.uniform_filter`` on the muscle's bounding box) ranks the fat and
    unnamed-muscle voxels, and the fullest ones are given to ``m`` until its working
    voxels hold its image volume (``cell_ratio`` = image voxel / working voxel volume), so
    a thin muscle keeps a layer of working voxels; its surfaces are then placed on the
    fine interfaces by :func:`_fine_targets`.
    """
    named = np.where(code_zyx > _MUSCLE0, code_zyx, 0)
    size = tuple(2 * half + 1)
    for c0, box in enumerate(ndimage.find_objects(named)):
        if box is None:
            continue
        c = c0 + 1
        sl = tuple(
            slice(max(b.start - h, 0), min(b.stop + h, n))
            for b, h, n in zip(box, half, code_zyx.shape)
        )
        sel = [np.flatnonzero((ix >= q.start) & (ix < q.stop)) for ix, q in zip(idx_zyx, sl)]
        if any(len(x) == 0 for x in sel):
            continue
        share = ndimage.uniform_filter((code_zyx[sl] == c).astype(np.float32), size=size, mode="constant")
        share = share[np.ix_(*[ix[x] - q.start for ix, x, q in zip(idx_zyx, sel, sl)])]
        block = sub[np.ix_(*sel)]
        free = (block == _FAT) | (block == _MUSCLE0)
        # as many working voxels as the muscle's volume, the fullest cells first
        want = int(round(np.count_nonzero(code_zyx[sl] == c) * cell_ratio))
        have = int(np.count_nonzero(block == c))
        cand = np.flatnonzero(free.ravel() & (share.ravel() > 0))
        claim = np.zeros(block.shape, bool)
        if want > have and len(cand):
            top = cand[np.argsort(-share.ravel()[cand], kind="stable")[: want - have]]
            claim.ravel()[top] = True
        if claim.any():
            block[claim] = c
            sub[np.ix_(*sel)] = block


def _repair_topology(sub, max_iter=20):
    """Remove the label configurations that make SurfaceNets surfaces non-manifold.

    A label occupying only one diagonal of a 2x2 square (regions touching along an
    edge) or only two opposite corners of a 2x2x2 cube (touching at a vertex) is made
    face-connected by giving one neighbouring voxel its label, or cut by taking the
    neighbour's label, whichever raises the code (air < other < fat < muscle, so muscles
    are never cut); two different labels alone at opposite corners of a cube are
    separated by relabelling the lower one. Vectorised over the grid,
    repeated until clean; returns the number of voxels changed.
    """
    v = sub
    changed = 0
    history = []  # the grids after the last two passes
    for it in range(max_iter):
        n_fix = 0
        for ax1, ax2 in ((0, 1), (0, 2), (1, 2)):
            w = np.moveaxis(v, (ax1, ax2), (0, 1))  # a view: writes go to v
            a, b = w[:-1, :-1], w[1:, 1:]
            c, d = w[1:, :-1], w[:-1, 1:]
            for p, q, o1, o2 in ((a, b, c, d), (c, d, a, b)):
                bad = (p == q) & (o1 != p) & (o2 != p)
                if bad.any():
                    # labels only grow in code order (air < other < fat < muscle), so
                    # a muscle is never cut by the repair and the loop terminates
                    up1 = bad & (p > o1)
                    up2 = bad & ~up1 & (p > o2)
                    down = bad & ~up1 & ~up2
                    o1[up1] = p[up1]
                    o2[up2] = p[up2]
                    p[down] = np.maximum(o1[down], o2[down])
                    n_fix += int(bad.sum())
        corners = [(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)]
        views = {q: v[q[0] : v.shape[0] - 1 + q[0], q[1] : v.shape[1] - 1 + q[1], q[2] : v.shape[2] - 1 + q[2]] for q in corners}
        for p in corners[:4]:
            q = tuple(1 - x for x in p)
            bad = views[p] == views[q]
            for o in corners:
                if o not in (p, q):
                    bad &= views[o] != views[p]
            if bad.any():
                o = (q[0], p[1], p[2])
                up = bad & (views[p] > views[o])
                down = bad & ~up
                views[o][up] = views[p][up]
                views[p][down] = views[o][down]
                n_fix += int(bad.sum())
            # two different labels alone at opposite corners: SurfaceNets gives their
            # sheets one vertex each at the same place; the lower code (air < other <
            # fat < muscle) takes the label of a neighbouring corner
            bad = views[p] != views[q]
            for o in corners:
                if o not in (p, q):
                    bad &= (views[o] != views[p]) & (views[o] != views[q])
            if bad.any():
                low_p = bad & (views[p] < views[q])
                low_q = bad & ~low_p
                op, oq = (q[0], p[1], p[2]), (p[0], q[1], q[2])
                views[p][low_p] = views[op][low_p]
                views[q][low_q] = views[oq][low_q]
                n_fix += int(bad.sum())
        changed += n_fix
        if n_fix == 0:
            break
        # a few voxels can flip back and forth for ever (a 2-cycle): the grid after
        # ``max_iter`` passes is then known without running them
        if len(history) == 2 and np.array_equal(history[0], v):
            if (max_iter - 1 - it) % 2:
                v[...] = history[1]
            log.debug("tetrahedralize: topology repair cycles after %d passes", it + 1)
            break
        history = history[-1:] + [v.copy()]
    return changed


def _image_pieces(code):
    """Number of 6-connected pieces of every muscle code in the full-resolution image."""
    pieces = {}
    for c, box in enumerate(ndimage.find_objects(np.where(code > _MUSCLE0, code, 0)), start=0):
        if box is not None and c + 1 > _MUSCLE0:
            pieces[c + 1] = ndimage.label(code[box] == c + 1)[1]
    return pieces


def _drop_fragments(sub, pieces):
    """Give to the fat the muscle fragments the coarse grid adds to the image's pieces."""
    dropped = 0
    for c, n_image in pieces.items():
        lab, n = ndimage.label(sub == c)
        if n > n_image:
            sizes = np.bincount(lab.ravel())[1:]
            keep = np.argsort(sizes)[::-1][:n_image] + 1
            frag = (lab > 0) & ~np.isin(lab, keep)
            sub[frag] = _FAT
            dropped += int(frag.sum())
    return dropped


def _components(sub):
    """Label each connected region of every meshed code; returns (comp_zyx, comp -> code)."""
    comp = np.where(sub == _OTHER, 1, 0).astype(np.int32)
    comp_code = [_AIR, _OTHER]
    nxt = 2
    for c in np.unique(sub):
        if c < _FAT:
            continue
        lab, n = ndimage.label(sub == c)
        m = lab > 0
        comp[m] = lab[m] + (nxt - 1)
        comp_code.extend([int(c)] * n)
        nxt += n
    return comp, np.asarray(comp_code, dtype=np.int64)

