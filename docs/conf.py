"""Sphinx configuration of the lrm-cvx documentation (``sphinx-build -W docs docs/_build``)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

import lrm_cvx  # noqa: E402

project = "lrm-cvx"
author = "lrm-cvx developers"
copyright = "lrm-cvx developers, BSD-3-Clause"  # noqa: A001
release = version = lrm_cvx.__version__

extensions = [
    "myst_nb",
    "numpydoc",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.intersphinx",
    "sphinx.ext.mathjax",
]
source_suffix = {".rst": "restructuredtext", ".md": "myst-nb", ".ipynb": "myst-nb"}
exclude_patterns = ["_build", "**.ipynb_checkpoints", "README.md"]
root_doc = "index"

# MyST: headings become link targets, ``$...$`` maths, fenced directives
myst_heading_anchors = 3
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
suppress_warnings: list[str] = []

# Notebooks: rendered as committed (without outputs) unless LRM_CVX_DOCS_EXECUTE=1
nb_execution_mode = "force" if os.environ.get("LRM_CVX_DOCS_EXECUTE") == "1" else "off"
nb_execution_timeout = 600

# API reference from the numpydoc docstrings
autosummary_generate = True
autodoc_default_options = {"members": False}
autodoc_typehints = "none"
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

intersphinx_mapping = {
    "python": ("https://docs.python.org/3", None),
    "numpy": ("https://numpy.org/doc/stable", None),
    "xarray": ("https://docs.xarray.dev/en/stable", None),
}
intersphinx_disabled_reftypes = ["*"]
intersphinx_timeout = 5
if os.environ.get("LRM_CVX_DOCS_OFFLINE", "1") == "1":  # CI and field machines have no network
    intersphinx_mapping = {}

html_theme = "pydata_sphinx_theme"
html_title = f"lrm-cvx {release}"
html_theme_options = {
    "navigation_depth": 2,
    "show_toc_level": 2,
    "secondary_sidebar_items": ["page-toc"],
}
html_static_path: list[str] = []
