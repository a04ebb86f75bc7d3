"""Units and orientation of a head CT, checked from the image itself.

:func:`standardize` (``check_units`` then ``orient_head``) takes the image that
:func:`pvcmf.read_ct` returns (patient frame as the file says, identity direction) and gives
it back in Hounsfield units with the face toward +y and the vertex toward +z, plus a report
of what it found and did.

Units (:func:`check_units`, :mod:`pvcmf.io.units`)
    The air and soft-tissue peaks of the histogram and the bone tail far above them make a
    CT; scanner units differ from HU by a storage offset, found from the peaks
    (``units='auto'``); a cone-beam CT's grey values by a scale too, mapped by the line
    through the peaks (``units='rescale'``).
Orientation (:func:`orient_head`)
    Decided on a copy pooled to about 3 mm voxels (block mean for the body, block maximum for
    thin bone). Three anatomical facts, none fitted to a scan:

    * the head is mirror-symmetric about its mid-sagittal plane: the left-right axis is the
      one whose mirror image of the bone mask overlaps it best;
    * a head scan is cut by the scan range along the body axis (neck, or both ends for a
      face scan) while the in-plane field of view holds the whole head; where the skull vault
      is in the scan, the cranial cavity (soft tissue enclosed by bone in slices of at least
      two orientations) lies superior to the rest of the body;
    * the skeleton's share of the body grows toward the vertex (skull) and toward the face
      (jaws, teeth), and the air inside the head (sinuses, nasal cavity, pharynx) lies in
      front of the cranial cavity;
    * the dental arch is a U open toward the back (:func:`~pvcmf.io.head_check.arch_trend`).

    A face-only scan (a cone-beam field around the jaws) holds no cranial cavity, and its
    skull base and spine make the bone share grow backward: there the arch alone tells the
    face side, the vertex side comes from a strong bone-share trend along the body axis, and
    a weak trend that does not contradict the file keeps the file's vertex side (reported).

    Left and right cannot be told from anatomy (the head is symmetric): the left-right sign
    is taken from the file, so the re-orientation is a proper rotation, never a mirroring.
    When the cues are weak and the file's axes are not confirmed, the image is refused with
    a message naming ``orient='none'`` (trust the file) and ``orient='<code>'``.

Orientation codes are three letters, one per image axis (x, y, z), saying toward which side of
the patient that axis points: ``'LAS'`` is the pvcmf patient frame (x left, y anterior, z
superior); a scan stored face toward -y and vertex toward -z is ``'LPI'``.

Delegates to numpy and :mod:`scipy.ndimage` (labelling, morphology).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import ndimage as ndi

from .head_check import (TEETH_STEPS, _teeth_blocks, _teeth_ml,  # noqa: F401 (re-export)
                         arch_trend, check_head)
from .units import (AIR_HU, HU_OFFSETS, SOFT_HU, _peaks, _volume,  # noqa: F401 (re-export)
                    _with_volume, check_units)

log = logging.getLogger(__name__)

__all__ = ["check_head", "check_units", "orient_head", "orientation_code", "reorient", "standardize",
           "HU_OFFSETS"]

#: voxel size (mm) of the pooled copy the orientation is decided on
DECISION_VOXEL = 3.0
_LETTERS = {"L": (0, 1), "R": (0, -1), "A": (1, 1), "P": (1, -1), "S": (2, 1), "I": (2, -1)}
#: the mirror plane is sought within this distance (mm) of the bone's centre plane: a
#: cone-beam field centred beside the midline cuts one side's bone more than the other's
MIRROR_REACH_MM = 15.0
#: least correlation (absolute) of a bone-share trend that counts as a cue
TREND = 0.3
#: least correlation (absolute) of the dental arch's trend that counts as a cue: teeth lie
#: farther back the farther they lie from the midline, so a whole arch is near -1
ARCH_TREND = 0.5
#: least correlation (absolute) of the bone-share trend along the body axis that tells the
#: vertex side without a cranial cavity (the orbits and skull base weigh against the jaws
#: there); a weaker trend that does not contradict the file leaves the file's vertex side
TREND_NO_CAVITY = 0.5
_NAMES = {(0, 1): "L", (0, -1): "R", (1, 1): "A", (1, -1): "P", (2, 1): "S", (2, -1): "I"}


# --------------------------------------------------------------------------- orientation
def _parse_code(code):
    code = str(code).upper()
    picks = [_LETTERS.get(c) for c in code]
    if len(code) != 3 or None in picks or sorted(p[0] for p in picks) != [0, 1, 2]:
        raise ValueError(
            f"orient must be 'auto', 'none' or a 3-letter code with one of L/R, A/P, S/I per "
            f"image axis (e.g. 'LAS' for the patient frame, 'LPI'), got {code!r}")
    return code, picks


def orientation_code(code):
    """The upper-case 3-letter orientation code ``code`` names, or a ValueError.

    One letter per image axis from L/R, A/P, S/I, each pair once (see :func:`reorient`).

    Examples
    --------
    >>> orientation_code("lpi")
    'LPI'
    """
    return _parse_code(code)[0]


def reorient(image, code):
    """Turn an image whose axes point as ``code`` says into the patient frame (``'LAS'``).

    Parameters
    ----------
    image : pyvista.ImageData
        Point array ``ct``; identity direction.
    code : str
        One letter per image axis (x, y, z): the side of the patient it points to, one of
        L/R, A/P, S/I each, e.g. ``'LPI'`` for face toward -y and vertex toward -z.

    Returns
    -------
    pyvista.ImageData
        A new image with voxel axes reordered and reversed (spacing reordered, origin kept).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.filters.orientation import reorient
    >>> img = pv.ImageData(dimensions=(2, 3, 4))
    >>> img["ct"] = img.points[:, 2].astype(np.float32)
    >>> out = reorient(img, "LSP")  # image y is superior, image z posterior
    >>> out.dimensions, float(out["ct"].reshape(out.dimensions, order="F")[0, 0, 2])
    ((2, 4, 3), 3.0)
    """
    vol = _volume(image)
    code, picks = _parse_code(code)
    order = [0, 0, 0]
    for i, (axis, sign) in enumerate(picks):
        if sign < 0:
            vol = np.flip(vol, i)
        order[axis] = i
    out = np.transpose(vol, order)
    return _with_volume(image, out, spacing=np.asarray(image.spacing)[order])


def _pool(vol, spacing, body_level, bone_level, dense_levels=None):
    """Body and bone masks of ``vol`` pooled to about DECISION_VOXEL mm voxels.

    Body: the voxel at each block's corner above ``body_level``; bone: any voxel of the block
    above ``bone_level`` (thin skull survives the pooling). With ``dense_levels`` (lo, hi),
    also the blocks whose maximum lies in [lo, hi) (tooth-dense, not metal) and those whose
    maximum is ``hi`` or more (metal).
    """
    f = [min(max(1, int(round(DECISION_VOXEL / s))), n) for s, n in zip(spacing, vol.shape)]
    shape = [n // k * k for n, k in zip(vol.shape, f)]
    v = vol[: shape[0], : shape[1], : shape[2]]
    body = v[:: f[0], :: f[1], :: f[2]] > body_level
    # one code per block: 1 bone, 2 tooth-dense, 3 metal. The code rises with the value, so
    # the block's code is the code of the block's maximum (pooled first: the comparisons
    # run on the pooled copy only; NaN voxels are ignored)
    peak = _block_max(v, f)
    top = (peak > bone_level).view(np.uint8)
    if dense_levels is not None:
        top = top + (peak >= dense_levels[0]).view(np.uint8) + (peak >= dense_levels[1]).view(
            np.uint8)
    ds = np.asarray(spacing) * f
    # C order: labelling and morphology of Fortran-ordered masks run several times slower
    body, top = np.ascontiguousarray(body), np.ascontiguousarray(top)
    if dense_levels is None:
        return body, top > 0, ds
    return body, top > 0, ds, top == 2, top == 3


def _block_max(a, f):
    """Maximum over blocks of ``f`` voxels (``a``'s shape a multiple of ``f``; NaN ignored):
    one axis at a time, in-place maxima of strided views; the axis of the largest memory
    stride first (its views are whole contiguous slabs, and the others then run on a
    smaller array)."""
    for axis in sorted(range(3), key=lambda ax: -abs(a.strides[ax])):
        k = f[axis]
        if k > 1:
            index = [slice(None)] * 3
            index[axis] = slice(0, None, k)
            out = a[tuple(index)].copy(order="K")  # the memory order of `a`
            for offset in range(1, k):
                index[axis] = slice(offset, None, k)
                np.fmax(out, a[tuple(index)], out=out)
            a = out
    return a


def _largest(mask):
    lab, n = ndi.label(mask)
    if n == 0:
        return mask
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    return lab == np.argmax(sizes)


def _enclosed(mask, axis=None):
    """Voxels not in ``mask`` that no path outside ``mask`` joins to the border.

    With ``axis`` the paths stay in the slices across that axis (a 2-D hole fill per slice).
    """
    struct = ndi.generate_binary_structure(3, 1)
    free = ~mask
    if axis is not None:
        index = [slice(None)] * 3
        index[axis] = [0, 2]
        struct[tuple(index)] = False
    lab, _ = ndi.label(free, structure=struct)
    border = set()
    for ax in range(3):
        if ax == axis:
            continue
        border.update(np.unique(lab.take(0, axis=ax)))
        border.update(np.unique(lab.take(-1, axis=ax)))
    return free & ~np.isin(lab, list(border))


def _mirror_overlap(mask, axis, reach=0):
    """``(share, plane)``: the share of ``mask`` that its mirror image overlaps about the
    best of the planes across ``axis`` within ``reach`` voxels of its own centre plane
    (half-voxel steps; a field of view off the head's midline leaves the bone's centre off
    it), and that plane (index along ``axis``). Mirrored voxels beyond the array count as
    missed."""
    idx = np.nonzero(mask)
    c = idx[axis].mean()
    best = (0.0, c)
    for plane in c + 0.5 * np.arange(-2 * int(reach), 2 * int(reach) + 1):
        mirrored = np.rint(2 * plane - idx[axis]).astype(int)
        inside = (mirrored >= 0) & (mirrored < mask.shape[axis])
        pts = [i[inside] for i in idx]
        pts[axis] = mirrored[inside]
        best = max(best, (float(mask[tuple(pts)].sum() / max(len(idx[0]), 1)), plane))
    return best


def _cues(vol, spacing, air, soft):
    """Anatomical measurements on the pooled copy (see the module notes)."""
    step = soft - air
    body, bone, ds, dense, metal = _pool(
        vol, spacing, 0.5 * (air + soft), soft + 0.35 * step,
        (soft + TEETH_STEPS[0] * step, soft + TEETH_STEPS[1] * step))
    if body.any():  # crop to the body plus a margin; faces the body touches stay faces
        nz = np.nonzero(body)
        box = tuple(slice(max(int(i.min()) - 3, 0), int(i.max()) + 4) for i in nz)
        body, bone, dense, metal = body[box], bone[box], dense[box], metal[box]
    body = _largest(ndi.binary_opening(body, iterations=2))
    head = body | _enclosed(body)
    bone &= head
    voxel_ml = float(np.prod(ds)) / 1e3
    cues = {"voxel_mm": [round(float(d), 2) for d in ds], "body_ml": round(head.sum() * voxel_ml)}
    cues["teeth_ml"] = round(_teeth_ml(dense & head, ds), 2)
    votes = sum(_enclosed(body, a).astype(np.uint8) for a in range(3))
    cues["inner_air_ml"] = round(float(np.count_nonzero((votes >= 1) & ~body)) * voxel_ml)
    if bone.sum() < 10 or head.sum() < 100:
        cues["cavity_ml"] = 0
        return cues, None
    votes = sum(_enclosed(ndi.binary_closing(bone), a).astype(np.uint8) for a in range(3))
    cavity = _largest((votes >= 2) & head & ~bone)
    extent = [float(np.ptp(np.nonzero(cavity)[a]) * ds[a]) if cavity.any() else 0.0
              for a in range(3)]
    has_cavity = bool(cavity.sum() >= 0.05 * head.sum() and min(extent) >= 50.0)
    cues["cavity_ml"] = round(float(cavity.sum()) * voxel_ml) if has_cavity else 0
    centre = np.array(ndi.center_of_mass(head)) * ds
    mirrors = [_mirror_overlap(bone, a, round(MIRROR_REACH_MM / ds[a])) for a in range(3)]
    cues["mirror"] = [round(m[0], 3) for m in mirrors]
    lr = int(np.argmax(cues["mirror"]))  # fillings and crowns lie on the arch too
    trend = arch_trend(_teeth_blocks((dense | metal) & head, ds), ds, lr, mirrors[lr][1])
    cues["arch_trend"] = None if trend is None else [round(c, 3) for c in trend]
    face_area = [float(head.take(0, a).sum() + head.take(-1, a).sum())
                 * float(np.prod(np.delete(ds, a))) for a in range(3)]
    cues["cut_area_mm2"] = [round(x) for x in face_area]
    corr = []
    for a in range(3):
        other = tuple(i for i in range(3) if i != a)
        area = head.sum(axis=other).astype(float)
        ok = area > 0.2 * area.max()
        frac = bone.sum(axis=other)[ok] / area[ok]
        x = np.nonzero(ok)[0]
        corr.append(float(np.corrcoef(x, frac)[0, 1]) if ok.sum() > 2 and np.ptp(frac) > 0 else 0.0)
    cues["bone_share_trend"] = [round(c, 3) for c in corr]
    inner_air = head & ~body
    ref = np.array(ndi.center_of_mass(cavity)) * ds if has_cavity else centre
    if inner_air.sum() * voxel_ml >= 5.0:
        cues["inner_air_offset_mm"] = [round(float(v), 1) for v in
                                       np.array(ndi.center_of_mass(inner_air)) * ds - ref]
    if has_cavity:
        cues["body_below_cavity_mm"] = [round(float(v), 1) for v in centre - ref]
    return cues, True


def _face_votes(cues, ap, cavity):
    """Which way the face points along image axis ``ap`` (+1, -1), one vote per cue that
    speaks: the bone share, the inner air and the dental arch (:func:`arch_trend`). Without a
    cranial cavity the arch alone where it speaks: the bone share of a face-only scan grows
    toward its skull base and spine, and its inner air has no cavity to lie in front of."""
    arch = cues.get("arch_trend")
    arch_vote = ([-int(np.sign(arch[ap]))] if arch is not None and abs(arch[ap]) >= ARCH_TREND
                 else [])
    if arch_vote and not cavity:
        return arch_vote
    votes = []
    trend = cues["bone_share_trend"]
    if abs(trend[ap]) >= TREND:
        votes.append(int(np.sign(trend[ap])))
    if "inner_air_offset_mm" in cues and abs(cues["inner_air_offset_mm"][ap]) >= 10.0:
        votes.append(int(np.sign(cues["inner_air_offset_mm"][ap])))
    return votes + arch_vote


def _decide(cues):
    """``(code, from_file, why)``: the orientation code from the cues (None where they do
    not settle it, and why), and whether the vertex side is the file's."""
    mirror = np.asarray(cues["mirror"])
    lr = int(np.argmax(mirror))
    rest = [a for a in range(3) if a != lr]
    if mirror[lr] - max(mirror[rest]) < 0.15:
        return None, False, (f"no single plane of mirror symmetry (bone overlap {cues['mirror']} "
                      "for the x, y, z mirrors): not a head, or a head cut too much")
    trend = np.asarray(cues["bone_share_trend"])
    cut = np.asarray(cues["cut_area_mm2"], dtype=float)
    si, from_file = None, False
    if "body_below_cavity_mm" in cues:
        d = np.asarray(cues["body_below_cavity_mm"])
        k = rest[int(np.argmax(np.abs(d[rest])))]
        other = rest[0] if k == rest[1] else rest[1]
        if abs(d[k]) >= 15.0 and abs(d[k]) >= 2 * abs(d[other]):
            si, si_sign = k, -int(np.sign(d[k]))
    if si is None:  # no cranial cavity: a face-only scan, or a head cut below the vault
        k = rest[int(np.argmax(cut[rest]))]
        other = rest[0] if k == rest[1] else rest[1]
        if cut[k] < 1000.0 or cut[k] < 2 * cut[other]:
            return None, False, ("no cranial cavity, and the scan range does not show which axis is "
                          f"the body axis (cut areas {cues['cut_area_mm2']} mm2)")
        if abs(trend[k]) >= TREND_NO_CAVITY:
            si, si_sign = k, int(np.sign(trend[k]))
        elif k == 2 and trend[k] > -TREND:  # not contradicted: the file's
            si, si_sign, from_file = 2, 1, True
        else:
            return None, False, ("no cranial cavity, and neither the bone-share trend along the body "
                          "axis nor the file's axes show the vertex side (the scan range cuts "
                          f"the body along image axis {'xyz'[k]}: cut areas "
                          f"{cues['cut_area_mm2']} mm2; bone-share trends "
                          f"{cues['bone_share_trend']})")
    ap = rest[0] if si == rest[1] else rest[1]
    votes = _face_votes(cues, ap, cavity="body_below_cavity_mm" in cues)
    if not votes or len(set(votes)) > 1:
        return None, False, ("the face side is not clear (bone-share trend "
                      f"{cues['bone_share_trend']}, inner-air offset "
                      f"{cues.get('inner_air_offset_mm')}, dental-arch trend "
                      f"{cues.get('arch_trend')})")
    picks = {si: (2, si_sign), ap: (1, votes[0])}
    m = np.zeros((3, 3))
    for i, (axis, sign) in picks.items():
        m[axis, i] = sign
    m[0, lr] = 1
    if np.linalg.det(m) < 0:  # left/right from the file: a rotation, never a mirroring
        m[0, lr] = -1
    picks[lr] = (0, int(m[0, lr]))
    return "".join(_NAMES[picks[i]] for i in range(3)), from_file, None


def orient_head(image, orient="auto", *, air=None, soft=None):
    """Check from the anatomy that the face points +y and the vertex +z; re-orient if not.

    Parameters
    ----------
    image : pyvista.ImageData
        Point array ``ct`` (HU or scanner units), in the patient frame as the file says
        (what :func:`pvcmf.read_ct` returns).
    orient : str
        ``'auto'`` decides from the anatomy (module notes) and refuses when unsure;
        ``'none'`` keeps the file's axes; a code such as ``'LPI'`` says where each image
        axis points and is applied without looking at the anatomy.
    air, soft : float, optional
        Air and soft-tissue peaks; found from the histogram when not given.

    Returns
    -------
    image : pyvista.ImageData
        A new image, face toward +y and vertex toward +z.
    report : dict
        ``mode``, ``code`` (where the input's axes pointed), ``reoriented`` (bool),
        ``left_right`` (always taken from the file), and for ``'auto'`` the ``cues``.

    Raises
    ------
    ValueError
        For a bad ``orient``, or with ``'auto'`` when the anatomy does not settle the
        orientation (not a head CT, or too little of one).
    """
    code, report = _orientation(image, orient, air, soft)
    if code == "LAS":
        return _with_volume(image, np.array(_volume(image), dtype=np.float32, order="F")), report
    return reorient(image, code), report


def _orientation(image, orient, air, soft, cues=None):
    """Where the image axes point (a code) and the report of :func:`orient_head`; ``cues``
    measured already (:func:`standardize`) are not measured again."""
    vol = _volume(image)
    lr_note = ("left/right taken from the file: a head's two sides cannot be told apart "
               "from the image")
    if not isinstance(orient, str):
        raise TypeError(f"orient must be a string, got {type(orient).__name__}")
    if orient.lower() == "none":
        return "LAS", {"mode": "none", "code": "LAS", "reoriented": False,
                       "left_right": lr_note}
    if orient.lower() != "auto":
        code, _ = _parse_code(orient)
        log.info("orient_head: axes %s given; turned into the patient frame (LAS)", code)
        return code, {"mode": "given", "code": code, "reoriented": code != "LAS",
                      "left_right": lr_note}
    if air is None or soft is None:
        found = _peaks(vol)
        if found is None:
            raise ValueError("orient_head: no air and tissue peaks: not a CT")
        air, soft = found[0], found[1]
    if cues is None:
        cues, ok = _cues(vol, np.asarray(image.spacing, dtype=float), float(air), float(soft))
    else:
        cues, ok = cues
    code, from_file, why = _decide(cues) if ok else (None, False, "no body with bone found")
    if code is None:
        raise ValueError(
            f"orient_head: cannot tell the head's orientation from the image: {why}. Pass "
            "orient='none' to trust the file's axes, or a code such as orient='LPI' (one of "
            "L/R, A/P, S/I per image axis)")
    report = {"mode": "auto", "code": code, "reoriented": code != "LAS", "left_right": lr_note}
    if from_file:
        report["vertex"] = ("vertex side taken from the file: the scan holds no cranial "
                            "cavity (a face-only scan), and its bone share does not show it")
        log.info("orient_head: %s", report["vertex"])
    if code == "LAS":
        log.info("orient_head: the anatomy confirms the file's axes (face +y, vertex +z)")
    else:
        log.warning("orient_head: the anatomy says the image axes point %s, not LAS: "
                    "re-oriented (face +y, vertex +z); %s", code, lr_note)
    return code, {**report, "cues": cues}


def standardize(image, *, units="auto", orient="auto"):
    """A CT in HU with the face toward +y and the vertex toward +z, and what was done.

    :func:`check_units` then :func:`orient_head`.

    Parameters
    ----------
    image : pyvista.ImageData
        Point array ``ct``, as :func:`pvcmf.read_ct` returns it.
    units : {'auto', 'hu', 'rescale'} or float
        See :func:`check_units`.
    orient : str
        ``'auto'``, ``'none'`` or a code; see :func:`orient_head`.

    Returns
    -------
    image : pyvista.ImageData
        A new image.
    report : dict
        ``{"units": {...}, "orientation": {...}}``, JSON-serialisable.

    Raises
    ------
    ValueError
        If the image is not a CT (:func:`check_units`), shows no head (neither a cranial
        cavity nor teeth, :func:`check_head`: a chest, a limb), or its orientation cannot be
        told (see above).
    """
    out, units_report = check_units(image, units)
    slope, offset = units_report["slope"], units_report["offset"]
    air, soft = (slope * units_report[k] + offset for k in ("air_peak", "soft_peak"))
    cues = _cues(_volume(out), np.asarray(out.spacing, dtype=float), air, soft)
    check_head(cues[0])
    code, orient_report = _orientation(out, orient, air, soft, cues)
    orient_report.setdefault("cues", cues[0])
    if code != "LAS":  # ``out`` is already a new image: no second copy when nothing turns
        out = reorient(out, code)
    return out, _plain({"units": units_report, "orientation": orient_report})


def _plain(obj):
    """The report with numpy scalars turned into Python ones (JSON-serialisable)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj
