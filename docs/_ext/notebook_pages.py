"""Place the repository's notebooks inside the documentation's source tree.

Sphinx reads pages only under ``docs/``; the notebooks live in ``notebooks/`` at the root,
where the test suite runs them, stored without outputs. At the start of a build each one is
copied to ``docs/notebooks/`` (an ignored folder), so none is kept twice in git:

- the executed copy that ``tests/cli/test_notebooks.py`` wrote to ``build/notebooks/`` (with
  its outputs, figures included) when there is one and it was run from the notebook as it is
  stored now (the copy carries the SHA-256 of the stored file in its metadata);
- the stored notebook otherwise (its page shows code and text, no outputs).

myst-nb never runs a notebook (``nb_execution_mode = "off"``), so the docs build costs no
notebook run; ``make test`` runs the tests before the docs, so its site shows the figures.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from sphinx.application import Sphinx
from sphinx.util import logging

__all__ = ["EXECUTED_DIR", "SOURCE_KEY", "copy_notebooks", "executed_copy", "setup"]

logger = logging.getLogger(__name__)

#: Where the test suite leaves the executed notebooks, relative to the repository root.
EXECUTED_DIR = Path("build") / "notebooks"
#: Metadata key of an executed notebook: the SHA-256 of the stored notebook it was run from.
SOURCE_KEY = "doe_source_sha256"


def executed_copy(stored: Path, executed_dir: Path) -> bytes | None:
    """The executed notebook for ``stored`` if it is current, else None.

    Parameters
    ----------
    stored : Path
        The notebook as stored in ``notebooks/`` (without outputs).
    executed_dir : Path
        The folder the test suite writes the executed notebooks to.

    Returns
    -------
    bytes or None
        The executed file's bytes when it exists, parses and was run from ``stored`` as it is
        now; None otherwise (missing, unreadable, or run from an older version).
    """
    candidate = executed_dir / stored.name
    if not candidate.is_file():
        return None
    data = candidate.read_bytes()
    try:
        source = json.loads(data).get("metadata", {}).get(SOURCE_KEY)
    except (ValueError, AttributeError):
        return None
    return data if source == hashlib.sha256(stored.read_bytes()).hexdigest() else None


def copy_notebooks(app: Sphinx) -> None:
    """Copy each notebook (executed when current, else as stored) next to the pages.

    Copies of removed notebooks are deleted; a copy is rewritten only when its content changes,
    so Sphinx rereads only the pages that changed.
    """
    root = Path(app.srcdir).parent
    source = root / "notebooks"
    target = Path(app.srcdir) / "notebooks"
    target.mkdir(exist_ok=True)
    wanted = {p.name for p in source.glob("*.ipynb")}
    for stale in target.glob("*.ipynb"):
        if stale.name not in wanted:
            stale.unlink()
    shown = 0
    for name in sorted(wanted):
        src, dst = source / name, target / name
        executed = executed_copy(src, root / EXECUTED_DIR)
        shown += executed is not None
        data = src.read_bytes() if executed is None else executed
        if not dst.exists() or dst.read_bytes() != data:
            dst.write_bytes(data)
    logger.info("notebook pages: %d of %d with outputs (from %s)", shown, len(wanted), EXECUTED_DIR)


def setup(app: Sphinx) -> dict[str, object]:
    """Register the copy step at the start of every build."""
    app.connect("builder-inited", copy_notebooks)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
