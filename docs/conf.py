"""Sphinx configuration of the femreg documentation (``make docs`` -> docs/_build/html)."""
import os
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's femreg and forward
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")

import femreg  # noqa: E402

project = "femreg"
author = "femreg developers"
copyright = "femreg developers"
version = release = femreg.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "numpydoc",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build"]
templates_path = ["_templates"]

# --- API reference
autosummary_generate = True
autosummary_imported_members = False
autodoc_default_options = {"members": True, "show-inheritance": False}
autodoc_typehints = "none"  # numpydoc's Parameters sections say the types
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

# --- MyST (the README's sections and the reports in docs/*.md)
myst_enable_extensions = ["dollarmath", "amsmath"]
myst_heading_anchors = 3


def _drop_missing_figures(app, docname, source):
    """The study report lists its figures, which `femreg study` writes next to the report in out/ and which are
    not in the repository: drop the image lines whose file is absent (the list of figures stays)."""
    if not docname.endswith("study_report"):
        return
    here = Path(app.srcdir) / Path(docname).parent

    def missing(line):
        m = re.fullmatch(r"!\[[^\]]*\]\(([^)]+\.png)\)\s*", line)
        return m is not None and not (here / m.group(1)).exists()

    source[0] = "".join(ln for ln in source[0].splitlines(keepends=True) if not missing(ln))


def setup(app):
    app.connect("source-read", _drop_missing_figures)


# --- Gallery of demos/: the quick demos run, the long ones are shown without running
sys.path.insert(0, str(Path(__file__).resolve().parent))
from gallery_conf import sphinx_gallery_conf  # noqa: E402,F401

# --- HTML
html_theme = "pydata_sphinx_theme"
html_title = f"femreg {release}"
html_theme_options = {"navigation_with_keys": False, "show_toc_level": 2}
html_static_path = []
