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

import numpy as np

from .. import arrays
from ..io import read_ct
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
    """VTK's real head CT (64 x 64 x 93 voxels, 3.2 x 3.2 x 1.5 mm) as ImageData.

    The scan is stored in scanner units, not HU: ``ct = scale * value + offset``. The
    defaults (``offset=-1000``, ``scale=1``) put air at -1000 HU, the scan's fat peak (~900
    units) at about -100 HU, its soft-tissue peak (~1030) at about 30 HU, and its skin
    iso-value (500) at -500 HU, :func:`pvcmf.filters.segment`'s default ``skin_threshold``.
    VTK's bone iso-value (1150) lands at 150 HU: a rendering choice for this blurred
    quarter-resolution scan that also takes dense soft tissue; ``segment``'s default
    ``bone_threshold`` (500 HU = 1500 units) keeps skull, jaws and spine, so
    ``headsq().cmf.segment()`` works with its defaults (one skin component with the bone
    inside it, tested). Pass ``bone_threshold=150`` to segment at VTK's bone iso-value.

    Parameters
    ----------
    offset, scale : float, optional
        Linear map from scanner units to HU; ``None`` takes the defaults above.

    Returns
    -------
    pyvista.ImageData
        Point array ``ct`` (float32), spacing as in the file, origin 0. The voxel order of
        the file (skull top first, face toward y = 0) is turned 180 degrees about x (y and z
        reversed, no mirroring) so that y points anterior and z superior, as in the pvcmf
        patient frame; left/right is as stored.

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
    offset = HEADSQ_OFFSET if offset is None else offset
    scale = HEADSQ_SCALE if scale is None else scale
    local = data_path("headsq", "quarter.nhdr", required=False)
    if local is not None and local.is_file():
        header = local
    else:
        header = _download_headsq()
    image = read_ct(header, offset=offset, scale=scale)
    # The scan runs from the skull top down (index z inferior) with the face toward index
    # y = 0: reverse y and z (a 180-degree turn about x, no mirroring) for the pvcmf patient
    # frame, y anterior and z superior.
    vol = image.point_data[arrays.CT].reshape(image.dimensions, order="F")
    image.point_data[arrays.CT] = np.ascontiguousarray(vol[:, ::-1, ::-1]).ravel(order="F")
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
