"""Place the repository's notebooks inside the documentation's source tree.

Sphinx reads pages only under ``docs/``; the notebooks live in ``notebooks/`` at the root,
where the test suite runs them. At the start of a build each one is copied to
``docs/notebooks/`` (an ignored folder) when it is newer than the copy, so the site always
shows the notebooks as they are in the repository and none is kept twice in git.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from sphinx.application import Sphinx

__all__ = ["copy_notebooks", "setup"]


def copy_notebooks(app: Sphinx) -> None:
    """Copy ``notebooks/*.ipynb`` next to the pages, dropping copies of removed notebooks."""
    source = Path(app.srcdir).parent / "notebooks"
    target = Path(app.srcdir) / "notebooks"
    target.mkdir(exist_ok=True)
    wanted = {p.name for p in source.glob("*.ipynb")}
    for stale in target.glob("*.ipynb"):
        if stale.name not in wanted:
            stale.unlink()
    for name in sorted(wanted):
        src, dst = source / name, target / name
        if not dst.exists() or dst.read_bytes() != src.read_bytes():
            shutil.copyfile(src, dst)


def setup(app: Sphinx) -> dict[str, object]:
    app.connect("builder-inited", copy_notebooks)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
