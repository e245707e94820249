"""Sphinx configuration of the prsa-ctrl documentation.

Build (warnings are errors; the output goes outside the checkout):

    pip install ".[docs]"
    sphinx-build -W --keep-going -b html docs /tmp/prsa-docs-html

Pages are MyST Markdown; the tutorials are the notebooks of ``notebooks/`` (linked into
``docs/tutorials/``), shown as stored, never executed; the API reference is generated from the
docstrings (numpydoc) of each subpackage's ``__all__`` by ``docs/_ext/prsa_docs.py``. The build
reads no network resource.
"""

import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "_ext"))
os.environ.setdefault("MPLBACKEND", "Agg")

import prsa_ctrl  # noqa: E402  (the installed package; an editable install is this checkout)

project = "prsa-ctrl"
author = "prsa-ctrl contributors"
copyright = "prsa-ctrl contributors, MIT licence"
release = version = prsa_ctrl.__version__

extensions = [
    "myst_nb",                 # MyST Markdown pages and the notebooks
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "numpydoc",
    "sphinx.ext.mathjax",
    "prsa_docs",               # docs/_ext: API pages and the plant-key table from the code
]

exclude_patterns = ["_build", "**/.ipynb_checkpoints"]
source_suffix = {".rst": "restructuredtext", ".md": "myst-nb", ".ipynb": "myst-nb"}
root_doc = "index"

# Notebooks are rendered as stored (outputs stripped in the repository): never executed here.
nb_execution_mode = "off"
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 4
suppress_warnings = ["myst.header"]

# API reference: numpydoc renders the docstrings; autosummary only draws the summary tables
# (no stub files are generated into the source tree).
autosummary_generate = False
autodoc_member_order = "bysource"
autodoc_typehints = "none"
autodoc_default_options = {"show-inheritance": False}
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

html_theme = "furo"
html_title = f"prsa-ctrl {release}"
html_static_path = []
# No intersphinx: the build must not fetch anything.
