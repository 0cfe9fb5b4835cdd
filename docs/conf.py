"""Sphinx configuration: API pages from the docstrings (autodoc + napoleon), the markdown pages
through myst-parser, the furo theme. Build with ``make docs`` (warnings are errors)."""
import os
import sys

sys.path.insert(0, os.path.abspath(".."))
import torch_hsh  # noqa: E402

project = "torch_hsh"
author = "torch_hsh maintainers"
copyright = "2026, torch_hsh maintainers"
release = torch_hsh.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "myst_parser",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "tables", "Thumbs.db", ".DS_Store"]

myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3

autodoc_default_options = {"members": True, "undoc-members": False, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
napoleon_use_ivar = True  # dataclass "Attributes:" as fields, not duplicate attribute entries

html_theme = "furo"
html_title = f"torch_hsh {release}"
