"""Sphinx configuration: API pages from the docstrings (autodoc + napoleon), the markdown pages
through myst-parser, the furo theme, the gallery (sphinx-gallery: ``examples/gallery/plot_*.py`` run
into ``docs/gallery/``, generated, not committed) and the command-line reference from the parser
(sphinx-argparse). Build with ``make docs`` (warnings are errors)."""
import os
import sys

sys.path.insert(0, os.path.abspath(".."))
sys.path.insert(0, os.path.abspath("."))  # _cli_parser (the parser of docs/cli_reference.md)
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
    "sphinx_gallery.gen_gallery",
    "sphinxarg.ext",
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

# The gallery: every examples/gallery/plot_*.py runs at each build (a few seconds each, CPU, float64
# scenes) and its matplotlib figures become the pictures of docs/gallery/ (generated; .gitignore).
os.environ.setdefault("MPLBACKEND", "Agg")
sphinx_gallery_conf = {
    "examples_dirs": ["../examples/gallery"],
    "gallery_dirs": ["gallery"],
    "filename_pattern": r"/plot_",
    "ignore_pattern": r"__init__\.py",
    "within_subsection_order": "FileNameSortKey",
    "image_scrapers": ("matplotlib",),
    "download_all_examples": False,
    "remove_config_comments": True,
    "abort_on_example_error": True,
    "only_warn_on_example_error": False,
    "show_memory": False,
    "plot_gallery": "True",
}
