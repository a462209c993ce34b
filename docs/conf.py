"""Sphinx configuration of sb3_cgac's documentation (the API reference from the reST docstrings, and docs/*.md)."""

import os
import sys

sys.path.insert(0, os.path.abspath(".."))

with open(os.path.join(os.path.dirname(__file__), "..", "sb3_cgac", "version.txt")) as file_handler:
    release = file_handler.read().strip()
version = release

project = "sb3_cgac"
author = "sb3_cgac contributors"
copyright = "2026, sb3_cgac contributors"

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",
    "myst_parser",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
master_doc = "index"
# The results folders hold the comparisons' own summary.md files and figures: data, not pages
exclude_patterns = ["_build", "results", "figures"]
myst_heading_anchors = 3
# docs/*.md link to the results folders and scripts of the repository, which are not pages of this site
suppress_warnings = ["myst.xref_missing"]

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": True}
# Optional dependencies of some modules: documented without being installed
autodoc_mock_imports = ["envpool", "mujoco_playground", "brax", "etils", "jax", "mjlab", "rsl_rl", "myosuite", "onnx"]

html_theme = "sphinx_rtd_theme"
html_title = f"sb3_cgac {release}"
