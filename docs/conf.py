"""Sphinx configuration of the doe-toolkit documentation (``make docs``).

The pages are Markdown (MyST); the API reference comes from the docstrings (autodoc,
autosummary, numpydoc), the CLI reference from the real ``doe`` parser (``_ext/doe_cli.py``), and
the notebooks of ``notebooks/`` are rendered by myst-nb without running them: the test suite
runs them (tests/cli/test_notebooks.py) and leaves executed copies in ``build/notebooks/``, which
``_ext/notebook_pages.py`` shows when they match the stored notebooks.
"""

from __future__ import annotations

import os
import sys
import types
from datetime import date
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE / "_ext"))
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")

project = "doe-toolkit"
author = "the doe-toolkit contributors"
copyright = f"2026-{date.today().year}, {author}"
release = "0.1.0"

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx.ext.intersphinx",
    "numpydoc",
    "myst_nb",
    "doe_cli",
    "notebook_pages",
]

# autosummary writes its pages with the first suffix: reStructuredText.
source_suffix = {".rst": "restructuredtext", ".md": "myst-nb", ".ipynb": "myst-nb"}
exclude_patterns = ["_build", "**.ipynb_checkpoints", "README.md"]
root_doc = "index"

# MyST: $...$ and $$...$$ maths, heading anchors for links between pages.
myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3
# The notebooks are run by the test suite, never here; the site shows its executed copies (with
# outputs) when current, else the notebooks as stored (docs/_ext/notebook_pages.py).
nb_execution_mode = "off"

autosummary_generate = True
autosummary_imported_members = False
autodoc_default_options = {"members": True, "show-inheritance": False}
autodoc_typehints = "none"  # numpydoc lists the types; the signatures keep their hints
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False

intersphinx_mapping = {}

html_theme = "pydata_sphinx_theme"
html_title = "doe-toolkit"
html_theme_options = {
    "navigation_depth": 3,
    "show_toc_level": 2,
    "footer_start": ["copyright"],
    "footer_end": [],
}
html_static_path: list[str] = []

# Every broken reference fails the build (with -W), except references in the docstrings'
# generated API pages to names the reference does not document (module constants, private
# helpers, unqualified names): `DOE_DOCS_STRICT_API=1 make docs` lists those too.
nitpicky = True
STRICT_API_REFERENCES = os.environ.get("DOE_DOCS_STRICT_API") == "1"


def _api_page_reference(app, domain, node) -> bool:
    """Silence a missing reference made from a generated API page (unless strict)."""
    return not STRICT_API_REFERENCES and str(node.get("refdoc", "")).startswith("api/generated/")


_documented_module: list[str] = [""]


def _note_module(app, what, name, obj, options, lines) -> None:
    if what == "module":
        _documented_module[0] = name


def _skip_reexport(app, what, name, obj, skip, options):
    """A package's re-exports are documented once, in the module that defines them."""
    module = getattr(obj, "__module__", None)
    if what == "module" and module and isinstance(obj, type | types.FunctionType) and module != _documented_module[0]:
        return True
    return None


def setup(app) -> None:
    app.connect("warn-missing-reference", _api_page_reference)
    app.connect("autodoc-process-docstring", _note_module)
    app.connect("autodoc-skip-member", _skip_reexport)
