"""Real CT data: VTK's classic head CT ``headsq`` (quarter resolution).

The files are looked up in ``$PVCMF_DATA_DIR/headsq/`` (see :func:`pvcmf.datasets.data_path`);
if they are not there they are downloaded once from their public origin, the VTK data
repository mirrored by PyVista (``pyvista/vtk-data``, ``Data/headsq``), into pooch's cache
folder for pvcmf (``pooch.os_cache("pvcmf")``, override with ``$PVCMF_CACHE_DIR``), exactly as
``pyvista.examples.download_*`` do; the 94 files are checked against one SHA-256 digest.
Reading delegates to :func:`pvcmf.read_ct` (NRRD).
"""

from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path

from ..io import read_ct
from ..io.orientation import standardize
from ._paths import data_path

log = logging.getLogger(__name__)

#: public origin of the headsq files
HEADSQ_URL = "https://github.com/pyvista/vtk-data/raw/master/Data/headsq/"
#: header plus the 93 raw slices
HEADSQ_FILES = ("quarter.nhdr", *(f"quarter.{i}" for i in range(1, 94)))
#: SHA-256 of the files' bytes concatenated in HEADSQ_FILES order
HEADSQ_SHA256 = "00464eb712c0f191bc05667ca3df70c9efcd25ec43351959fcd5b6b4b18ed772"

#: iso-values of this scan in its scanner units (VTK's examples use them for skin and bone)
HEADSQ_SKIN_ISO = 500.0
HEADSQ_BONE_ISO = 1150.0
#: default map to HU: HU = HEADSQ_SCALE * value + HEADSQ_OFFSET
HEADSQ_OFFSET = -1000.0
HEADSQ_SCALE = 1.0


def headsq(*, offset=None, scale=None):
    """VTK's real head CT (64 x 64 x 93 voxels, 3.2 x 3.2 x 1.5 mm) as ImageData, in HU.

    The scan is stored in scanner units, with the face toward -y and the vertex toward -z, and
    its header names no anatomical frame. :func:`pvcmf.filters.standardize` finds both from
    the image (air and soft-tissue peaks give the offset to HU; the anatomy gives the axes),
    so no hand-made offset or flip is needed. ``offset``/``scale`` override the units:
    ``ct = scale * value + offset`` (``HEADSQ_OFFSET`` is the classic ``-1000``).

    Parameters
    ----------
    offset, scale : float, optional
        Linear map from scanner units to HU; ``None`` for both detects it.

    Returns
    -------
    pyvista.ImageData
        Point array ``ct`` (float32, HU), spacing as in the file, origin 0, face toward +y
        and vertex toward +z (a 180-degree turn about x of the file's voxels, no mirroring).

    Raises
    ------
    ValueError
        If a downloaded copy does not match the expected checksum.

    Examples
    --------
    >>> import pvcmf
    >>> ct = pvcmf.datasets.headsq()  # doctest: +SKIP
    >>> ct.dimensions  # doctest: +SKIP
    (64, 64, 93)
    """
    local = data_path("headsq", "quarter.nhdr", required=False)
    if local is not None and local.is_file():
        header = local
    else:
        header = _download_headsq()
    if offset is None and scale is None:
        image, report = standardize(read_ct(header))
    else:
        offset = HEADSQ_OFFSET if offset is None else offset
        scale = HEADSQ_SCALE if scale is None else scale
        image, report = standardize(read_ct(header, offset=offset, scale=scale), units="hu")
    log.info("headsq: %s; axes %s", report["units"]["how"], report["orientation"]["code"])
    return image


def _download_headsq():
    """Fetch the headsq files with pooch into the cache; return the header's path."""
    import pooch

    cache = Path(os.environ.get("PVCMF_CACHE_DIR") or pooch.os_cache("pvcmf")) / "headsq"
    log.info("headsq: not in $PVCMF_DATA_DIR; downloading from %s into %s", HEADSQ_URL, cache)
    paths = [
        Path(pooch.retrieve(HEADSQ_URL + name, known_hash=None, fname=name, path=cache,
                            progressbar=False))
        for name in HEADSQ_FILES  # 94 files, not voxels
    ]
    digest = hashlib.sha256()
    for path in paths:
        digest.update(path.read_bytes())
    if digest.hexdigest() != HEADSQ_SHA256:
        raise ValueError(
            f"headsq: the files downloaded into {cache} do not match the expected SHA-256 "
            f"{HEADSQ_SHA256}; delete that folder and try again"
        )
    return paths[0]
