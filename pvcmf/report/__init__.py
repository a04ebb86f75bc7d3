"""The per-case HTML report: one self-contained offline page per prediction or validation.

* :func:`write_report` -> ``report.html`` of a case folder (:mod:`pvcmf.report.case`);
* :func:`validation_figures` -> paper 000 Figs. 6-8 of one validated case;
* :func:`disabled` -> a block in which no report is written (``--no-report``);
* :mod:`pvcmf.report.scene` -> the 3D view (vtk.js, vendored) and how skins are packed;
* :mod:`pvcmf.report.browser` -> checks a page in a headless Chromium (tests).
"""

from .case import write_report
from .figures import validation_figures
from .html import REPORT_NAME, disabled, region_rows, report_html

__all__ = ["REPORT_NAME", "disabled", "region_rows", "report_html", "validation_figures",
           "write_report"]
