"""Sphinx configuration of mfnormal's documentation.

Build: ``.venv/bin/python -m sphinx -W -b html docs docs/_build/html`` (from the repository root).
The pages are MyST markdown; the plugin reference (plugins.rst) is generated from the
plugins' docstrings by ``_ext/plugin_reference.py``.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent / "_ext"))

project = "mfnormal"
author = "the mfnormal authors"
copyright = "the mfnormal authors, MIT license"

extensions = ["myst_parser", "plugin_reference"]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]

myst_enable_extensions = []
myst_heading_anchors = 3

html_theme = "alabaster"
html_title = "mfnormal"
html_static_path = ["_static"]
html_css_files = ["plugin_reference.css"]
html_theme_options = {"page_width": "1100px", "sidebar_width": "230px"}
html_show_sourcelink = False
