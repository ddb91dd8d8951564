"""Every notebook in notebooks/ runs top to bottom (the workflows a user follows) and shows
the figures it draws.

Each notebook that runs cleanly is also written, with its outputs, to ``build/notebooks/``
(git-ignored): the documentation build shows those copies when they are present and still match
the stored notebook (``docs/_ext/notebook_pages.py``), so ``make test`` runs each notebook once
and the site shows its figures without running it a second time.
"""

import hashlib
import shutil
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
# Where the executed notebooks go; docs/_ext/notebook_pages.py reads them (same folder, same key).
EXECUTED = ROOT / "build" / "notebooks"
SOURCE_KEY = "doe_source_sha256"


def _figure_cells(nb):
    """Code cells that draw a figure (matplotlib or the package's figure helpers)."""
    drawing = ("plt.subplots", "plt.figure", "_figure(", ".imshow(", "plt.plot(")
    return [i for i, c in enumerate(nb.cells) if c.cell_type == "code" and any(d in c.source for d in drawing)]


def _keep_executed(nb, path):
    """Write the executed notebook for the docs, tagged with the hash of the stored file it ran."""
    nb.metadata[SOURCE_KEY] = hashlib.sha256(path.read_bytes()).hexdigest()
    EXECUTED.mkdir(parents=True, exist_ok=True)
    partial = EXECUTED / f".{path.stem}.partial"
    nbformat.write(nb, partial)
    partial.replace(EXECUTED / path.name)


# Notebooks that run a long workflow end to end (the fab loop diagnoses six fields): `make test-all`.
SLOW = {"08_fab_loop"}


@pytest.mark.parametrize("path", [pytest.param(p, marks=pytest.mark.slow) if p.stem in SLOW else p for p in NOTEBOOKS],
                         ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path, monkeypatch):
    # Run in a scratch copy of the folder so outputs never land in the repository.
    work = tmp_path / "nb"
    shutil.copytree(path.parent, work)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.setenv("PYVISTA_OFF_SCREEN", "true")
    monkeypatch.setenv("DOE_PROGRESS", "0")
    (EXECUTED / path.name).unlink(missing_ok=True)
    nb = nbformat.read(work / path.name, as_version=4)
    client = NotebookClient(nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(work)}})
    client.execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert not errors
    # Every cell that draws a figure shows it: an image output in that cell or a later one.
    shown = [i for i, c in enumerate(nb.cells) if c.cell_type == "code"
             for o in c.get("outputs", []) if "image/png" in o.get("data", {})]
    drawn = _figure_cells(nb)
    assert drawn, f"{path.name} draws no figure"
    assert shown and max(drawn) <= max(shown), f"{path.name}: figures drawn in cells {drawn}, shown in {shown}"
    assert len(set(shown)) >= len(drawn) / 2, f"{path.name}: figures drawn in cells {drawn}, shown in {shown}"
    _keep_executed(nb, path)
