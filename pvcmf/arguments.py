"""Command-line options shared by ``pvcmf simulate`` and ``pvcmf plan``: the units and the
axes of a CT, parsed by :mod:`argparse` into what :func:`pvcmf.filters.standardize` takes.
"""

from __future__ import annotations

import argparse

import numpy as np

from .io.orientation import orientation_code

__all__ = ["add_ct_checks", "units_argument", "orient_argument"]


def units_argument(text):
    """``--units``: 'auto', 'hu', 'rescale' or a number (the offset to add to reach HU)."""
    if text.strip().lower() in ("auto", "hu", "rescale"):
        return text.strip().lower()
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected 'auto', 'hu', 'rescale' or a number (the offset to add), got "
            f"{text!r}") from None
    if not np.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite offset, got {text!r}")
    return value


def orient_argument(text):
    """``--orient``: 'auto', 'none' or a 3-letter code such as 'LPI'."""
    if text.strip().lower() in ("auto", "none"):
        return text.strip().lower()
    try:
        code = orientation_code(text.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            "expected 'auto', 'none' or a 3-letter code, one letter per image axis from L/R, "
            f"A/P, S/I, each pair once (e.g. 'LPI'), got {text!r}") from None
    return code


def add_ct_checks(parser, units_note=""):
    """Add ``--units``, ``--orient`` and ``--shading`` (the units and axes check of the CT
    and the cone-beam shading step, 'auto' by default) to ``parser``; ``units_note``: a
    sentence appended to ``--units``'s help."""
    parser.add_argument("--units", type=units_argument, default="auto",
                        help="'auto' (detect scanner units from the histogram; default), "
                             "'hu', 'rescale' (a cone-beam CT's grey values: air and soft "
                             "tissue mapped to -1000 and +40 HU), or the offset to add to "
                             "reach HU" + units_note)
    parser.add_argument("--orient", type=orient_argument, default="auto",
                        help="'auto' (face +y and vertex +z checked from the anatomy; "
                             "default), 'none' (trust the file), or where the image axes "
                             "point, e.g. 'LPI'")
    parser.add_argument("--shading", choices=("auto", "n4", "none"), default="auto",
                        help="the slow shading of a cone-beam scan's field divided out (N4): "
                             "'auto' for grey values rescaled to HU (default), 'n4' for any "
                             "scan, 'none'")
