"""Sphinx configuration of the pvcmf documentation.

Build offline with warnings as errors::

    python -m sphinx -W -b html docs docs/_build/html

The gallery (``gallery/``) is run by sphinx-gallery; PyVista renders offscreen and its scraper
collects the open plotters, matplotlib's collects the open figures. Scripts whose study takes
minutes (parameter sweeps, the validation study, the virtual post-operative truth) are shown
with their code only; set ``PVCMF_DOCS_GALLERY=all`` to run every script, or
``PVCMF_DOCS_GALLERY=none`` to run none (a quick build of the text and the API reference).
"""

import os
import sys
from pathlib import Path

import pyvista

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pvcmf  # noqa: E402  (after the path: the documented package is this checkout's)
import pvcmf.figures.offscreen  # noqa: E402

pyvista.OFF_SCREEN = True
pvcmf.figures.offscreen.prefer_egl()  # headless: EGL without a failed X attempt
pyvista.BUILDING_GALLERY = True
os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
# gallery scripts write their PNG/CSV files next to the build, not into the source tree
os.environ.setdefault("PVCMF_GALLERY_OUT", str(ROOT / "docs" / "_build" / "gallery_out"))

project = "pvcmf"
author = "The pvcmf authors"
copyright = "2026, The pvcmf authors"
release = pvcmf.__version__ if hasattr(pvcmf, "__version__") else "0.1.0"
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "gallery/*.ipynb", "gallery/*.py", "gallery/*.zip",
                    "gallery/*.json", "gallery/*.md5", "gallery/*.codeobj.json"]
templates_path = ["_templates"]
# the gallery configuration holds functions (scrapers): Sphinx cannot pickle it, which only
# means a full re-read when it changes
suppress_warnings = ["config.cache"]
html_static_path = ["_static"]
html_theme = "alabaster"
html_theme_options = {"description": "Face prediction after jaw surgery", "fixed_sidebar": True}

# Markdown pages: $...$ maths, ::: fences, heading anchors for links like page.md#section
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

# API reference from the numpydoc docstrings
autosummary_generate = True
autosummary_imported_members = False
autodoc_default_options = {"members": True, "undoc-members": False, "ignore-module-all": True,
                           "show-inheritance": True}
autodoc_typehints = "description"
autodoc_mock_imports = ["ngsolve", "cupy", "cupyx", "pypardiso", "sksparse", "trame"]
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False
napoleon_use_ivar = True  # "Attributes" as fields: dataclass members are documented once
# absolute values written |x| in docstrings read as substitutions: define them as themselves
rst_epilog = "\n".join(f".. |{name}| replace:: \\|{name}\\|"
                        for name in ("distance", "x - x_tip", "error", "d", "u", "displacement",
                                     "bc_displacement"))

# no network: no intersphinx, no remote images
intersphinx_mapping = {}

_FAST = [
    "plot_virtual_patient", "plot_fig1_sampling", "plot_fig1_gmm_classification",
    "plot_fig2a_muscles", "plot_fig2b_label_slice", "plot_fig2c_mesh", "plot_fig3_obb",
    "plot_fig4_boundary_conditions", "plot_fig5_osteotomy", "plot_tables", "plot_plan_axes",
]
_which = os.environ.get("PVCMF_DOCS_GALLERY", "fast")
_pattern = {"all": r"plot_", "none": r"^$"}.get(_which, "(" + "|".join(_FAST) + r")\.py$")

_seen = {}


def _saved_figures(block, block_vars, gallery_conf):
    """Scrape the PNGs a gallery script saved itself (matplotlib ``Figure.savefig``).

    The figure modules build :class:`matplotlib.figure.Figure` objects without pyplot, which
    matplotlib's scraper cannot see; their scripts save them into ``PVCMF_GALLERY_OUT``. A PNG
    that is new or rewritten since the previous code block is shown. Blocks that leave
    PyVista plotters open are left to PyVista's scraper (it renders the plotters itself).
    """
    import shutil

    from sphinx_gallery.scrapers import figure_rst

    out = Path(os.environ["PVCMF_GALLERY_OUT"])
    fresh = []
    for path in sorted(out.glob("*.png")):
        stamp = path.stat().st_mtime_ns
        if _seen.get(path) != stamp:
            _seen[path] = stamp
            fresh.append(path)
    if any(not p._closed for p in pyvista.plotting.plotter._ALL_PLOTTERS.values()):
        return ""
    names = []
    for path in fresh:
        name = next(block_vars["image_path_iterator"])
        shutil.copyfile(path, name)
        names.append(name)
    return figure_rst(names, gallery_conf["src_dir"])


sphinx_gallery_conf = {
    "examples_dirs": str(ROOT / "gallery"),
    "gallery_dirs": "gallery",
    "filename_pattern": _pattern,
    "plot_gallery": "False" if _which == "none" else "True",
    "image_scrapers": ("matplotlib", _saved_figures, pyvista.Scraper()),
    "download_all_examples": False,
    "remove_config_comments": True,
    "within_subsection_order": "FileNameSortKey",
    "min_reported_time": 5,
    "reset_modules": ("matplotlib",),
    "show_memory": False,
}
