"""Sphinx configuration of the doe-toolkit documentation (``make docs``).

The pages are Markdown (MyST); the API reference comes from the docstrings (autodoc,
autosummary, numpydoc), the CLI reference from the real ``doe`` parser (``_ext/doe_cli.py``), and
the notebooks of ``notebooks/`` are rendered by myst-nb without running them: the test suite
runs them (tests/cli/test_notebooks.py) and leaves executed copies in ``build/notebooks/``, which
``_ext/notebook_pages.py`` shows when they match the stored notebooks.
"""

from __future__ import annotations

import ast
import functools
import importlib.util
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

# Every broken reference fails the build (with -W), the docstrings' references in the generated
# API pages included. The build runs offline (no intersphinx inventories are fetched), so the few
# references to other projects' objects have no inventory to resolve against: they are listed here.
nitpicky = True
nitpick_ignore = [
    ("py:mod", "logging"),
    ("py:func", "json.loads"),
    ("py:mod", "skimage.data"),
    ("py:func", "skimage.color.rgb2luv"),
    ("py:func", "scipy.interpolate.make_smoothing_spline"),
    ("py:func", "x3pio.info"),
    ("py:class", "io.BufferedReader"),
]


_documented_module: list[str] = [""]


def _note_module(app, what, name, obj, options, lines) -> None:
    if what == "module":
        _documented_module[0] = name


@functools.cache
def _assigned_names(module: str) -> frozenset[str]:
    """Names a module assigns at its top level (its own constants, not imported ones)."""
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        return frozenset()
    names: set[str] = set()
    for node in ast.parse(Path(spec.origin).read_text(encoding="utf-8")).body:
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
        names.update(t.id for t in targets if isinstance(t, ast.Name))
    return frozenset(names)


def _skip_unexported(obj, name: str) -> bool | None:
    """Keep a module's autosummary tables to its ``__all__``, the members automodule documents.

    autosummary lists every public function and class a module defines; a top-level one that
    its module's ``__all__`` leaves out has no entry on the page, so its row would be a broken link.
    """
    if not isinstance(obj, type | types.FunctionType) or getattr(obj, "__qualname__", None) != name:
        return None
    exported = getattr(sys.modules.get(getattr(obj, "__module__", ""), None), "__all__", None)
    return True if exported is not None and name not in exported else None


def _skip_reexport(app, what, name, obj, skip, options):
    """A package's re-exports are documented once, in the module that defines them."""
    if what != "module":
        return _skip_unexported(obj, name)
    module = getattr(obj, "__module__", None)
    if isinstance(obj, type | types.FunctionType):
        if getattr(obj, "__name__", name) != name and name in _assigned_names(_documented_module[0]):
            return False  # an alias the module defines (``Array = Any``)
        return True if module and module != _documented_module[0] else None
    return None


def setup(app) -> None:
    app.connect("autodoc-process-docstring", _note_module)
    app.connect("autodoc-skip-member", _skip_reexport)
