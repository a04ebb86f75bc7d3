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


def _default_map():
    """(offset, scale) that put the skin and bone iso-values on segment's HU thresholds."""
    from ..filters.segmentation import BONE_THRESHOLD, SKIN_THRESHOLD

    scale = (BONE_THRESHOLD - SKIN_THRESHOLD) / (HEADSQ_BONE_ISO - HEADSQ_SKIN_ISO)
    return SKIN_THRESHOLD - scale * HEADSQ_SKIN_ISO, scale


def headsq(*, offset=None, scale=None):
    """VTK's real head CT (64 x 64 x 93 voxels, 3.2 x 3.2 x 1.5 mm) as ImageData.

    The scan is stored in scanner units, not HU: ``ct = scale * value + offset``. The
    defaults map the scan's skin iso-value (500) to :func:`pvcmf.filters.segment`'s default
    ``skin_threshold`` (-500 HU) and its bone iso-value (1150) to the default
    ``bone_threshold`` (250 HU), i.e. ``scale = 750 / 650 ~ 1.154`` and
    ``offset ~ -1076.9``, so that ``headsq().cmf.segment()`` works with its defaults.
    With them air is about -1080 HU and the soft-tissue peak of the scan (~1030 units) about
    110 HU: fine for the skin and bone masks, but not calibrated HU for fat/muscle
    classification. Pass ``offset=-1000.0, scale=1.0`` for values closer to HU in the soft
    tissue (then use ``bone_threshold=150``).

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
    from ..io import read_ct

    d_offset, d_scale = _default_map()
    offset = d_offset if offset is None else offset
    scale = d_scale if scale is None else scale
    local = data_path("headsq", "quarter.nhdr", required=False)
    if local is not None and local.is_file():
        header = local
    else:
        header = _download_headsq()
    image = read_ct(header, offset=offset, scale=scale)
    # The scan runs from the skull top down (index z inferior) with the face toward index
    # y = 0: reverse y and z (a 180-degree turn about x, no mirroring) for the pvcmf patient
    # frame, y anterior and z superior.
    from .. import arrays

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
