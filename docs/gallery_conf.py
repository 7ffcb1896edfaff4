"""sphinx-gallery settings for the gallery of demos/ (imported by conf.py).

The demos save their figures under ``out/<demo>/`` and close them, so the matplotlib scraper finds nothing;
:func:`out_png_scraper` copies the PNG files a code block wrote into the gallery instead.  Each demo runs with
``--quick``, in the folder sphinx-gallery runs it in (demos/), so its files land in demos/out/ (ignored by git).
"""
import ast
import re
import shutil
import time
from pathlib import Path

from sphinx_gallery.scrapers import figure_rst

DEMOS = Path(__file__).resolve().parents[1] / "demos"
#: Demos shown without running: their quick mode takes minutes (the paper's study); every other demo runs in its
#: quick mode while the docs build (3-35 s each from an empty data cache on 2 shared cores).
LONG = ("06_study",)

_since = [0.0]  # files written after this time belong to the current code block


def mark_start(gallery_conf, fname, when=None):
    """reset_modules hook: remember when an example starts."""
    _since[0] = time.time()


def quick_argv(gallery_conf, script_vars):
    """Command-line arguments of every executed demo: its quick mode.  Also gives the demo its ``__file__`` and
    ``__doc__`` as when it runs as a script (sphinx-gallery leaves them out): the demos find this checkout and the
    in vivo data from ``__file__`` and take their --help text from ``__doc__``."""
    src = Path(script_vars["src_file"])
    script_vars["example_globals"]["__file__"] = str(src)
    script_vars["example_globals"]["__doc__"] = ast.get_docstring(ast.parse(src.read_text()), clean=False)
    return ["--quick"]


def out_png_scraper(block, block_vars, gallery_conf):
    """rST for the PNG files under demos/out/ written since the previous code block (sorted by name)."""
    out = DEMOS / "out"
    new = sorted(p for p in out.rglob("*.png") if p.stat().st_mtime >= _since[0]) if out.is_dir() else []
    _since[0] = time.time()
    paths = []
    for png, dest in zip(new, block_vars["image_path_iterator"]):
        shutil.copyfile(png, dest)
        paths.append(dest)
    return figure_rst(paths, gallery_conf["src_dir"])


sphinx_gallery_conf = {
    "examples_dirs": str(DEMOS),
    "gallery_dirs": "gallery",
    "filename_pattern": "/(?!" + "|".join(re.escape(n) for n in LONG) + r")\d\d_\w+\.py$",
    "ignore_pattern": r"run_all\.py",
    # functions by name, so that Sphinx can cache the configuration
    "within_subsection_order": "sphinx_gallery.sorting.FileNameSortKey",
    "reset_argv": "gallery_conf.quick_argv",
    "image_scrapers": ("matplotlib", "gallery_conf.out_png_scraper"),
    "reset_modules": ("matplotlib", "gallery_conf.mark_start"),
    "abort_on_example_error": True,
    "download_all_examples": False,
    "remove_config_comments": True,
    "show_memory": False,
    "min_reported_time": 1,
}
