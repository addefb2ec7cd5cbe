"""Sphinx configuration of the so_transients documentation.

Build: ``make docs``, or ``sphinx-build -W -b html docs docs/_build/html`` (warnings are
errors). Pages are Markdown (MyST) or reStructuredText; ``_ext/step_docs.py`` generates the
steps' config tables and the candidate columns from the code.
"""
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "_ext"))
sys.path.insert(0, str(HERE.parent))

import so_transients  # noqa: E402  (registers the steps the pages document)

project = "so_transients"
author = "the so_transients developers"
copyright = "2025-2026, " + author
release = version = so_transients.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "step_docs",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "_ext", "Thumbs.db", ".DS_Store"]
root_doc = "index"

myst_enable_extensions = ["colon_fence", "deflist"]
myst_heading_anchors = 3

autodoc_typehints = "none"
autodoc_member_order = "bysource"
napoleon_google_docstring = False
napoleon_numpy_docstring = True

html_theme = "alabaster"
html_title = f"so_transients {release}"
html_static_path = []
html_theme_options = {
    "description": "Rapid transients in SO LAT time-ordered data",
    "fixed_sidebar": False,
}
