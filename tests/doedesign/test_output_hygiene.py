"""Output hygiene: temporaries, stale temporaries, incomplete markers, unwritable targets."""

import os
import subprocess
import sys

import numpy as np
import pytest

from doedesign import fileio
from doedesign.errors import DoeError


def test_temporary_has_no_final_extension_and_is_renamed(tmp_path):
    target = tmp_path / "masks.gds"
    with fileio.atomic_path(target) as tmp:
        assert not tmp.name.endswith(".gds") and tmp.name.endswith(fileio.TEMP_SUFFIX)
        tmp.write_bytes(b"data")
    assert target.read_bytes() == b"data"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["masks.gds"]


def test_stale_temporary_of_dead_process_is_removed_live_one_kept(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    stale = tmp_path / f".a.gds.{dead}-xyz{fileio.TEMP_SUFFIX}"
    live = tmp_path / f".a.gds.{os.getpid()}-abc{fileio.TEMP_SUFFIX}"
    stale.write_bytes(b"old")
    live.write_bytes(b"writing")
    fileio.write_json(tmp_path / "r.json", {"a": 1})
    assert not stale.exists() and live.exists()


def test_result_path_taken_by_folder_or_out_is_file(tmp_path, monkeypatch):
    (tmp_path / "report.json").mkdir()
    with pytest.raises(DoeError, match="taken by a folder"):
        fileio.write_json(tmp_path / "report.json", {})
    (tmp_path / "f").write_text("x")
    with pytest.raises(DoeError, match="existing file"):
        fileio.ensure_output_dir(tmp_path / "f")
    with pytest.raises(DoeError, match="existing folder"):
        fileio.ensure_output_file(tmp_path / "report.json")
    with pytest.raises(DoeError, match="cannot create"):
        fileio.ensure_output_dir(tmp_path / "f" / "sub")
    assert fileio.ensure_output_dir(tmp_path / "new" / "sub") == tmp_path / "new" / "sub"
    assert not (tmp_path / "new").exists()
    monkeypatch.setattr(fileio.os, "access", lambda *a: False)  # a read-only folder (tests run as root)
    with pytest.raises(DoeError, match="not writable"):
        fileio.ensure_output_dir(tmp_path)


def test_output_run_marks_incomplete_until_done(tmp_path):
    with fileio.output_run(tmp_path / "o", "doe test") as folder:
        assert (folder / fileio.INCOMPLETE_MARKER).exists()
    assert not (tmp_path / "o" / fileio.INCOMPLETE_MARKER).exists()
    with pytest.raises(KeyboardInterrupt):
        with fileio.output_run(tmp_path / "o", "doe test") as folder:
            fileio.write_json(folder / "first.json", {})
            raise KeyboardInterrupt
    assert (tmp_path / "o" / fileio.INCOMPLETE_MARKER).exists() and (tmp_path / "o" / "first.json").exists()
    # an error (a full disk, a refused input) takes back what the run wrote: no partial output
    with pytest.raises(RuntimeError):
        with fileio.output_run(tmp_path / "e", "doe test") as folder:
            fileio.write_json(folder / "first.json", {})
            raise RuntimeError("disk full")
    assert not (tmp_path / "e").exists()
    with pytest.raises(RuntimeError):  # a failure before any output leaves nothing
        with fileio.output_run(tmp_path / "p", "doe test"):
            raise RuntimeError("refused")
    assert not (tmp_path / "p").exists()


def test_npz_claimed_size_and_objects_refused(tmp_path):
    path = tmp_path / "obj.npz"
    np.savez(path, a=np.array([{"x": 1}], dtype=object))
    with pytest.raises(DoeError) as exc:
        fileio.read_npz(path, ["a"], "thing")
    assert "allow_pickle" not in str(exc.value) and "objects" in str(exc.value)
    with pytest.raises(DoeError, match="no such file"):
        fileio.read_npz(tmp_path / "missing.npz", [], "thing")
    fifo = tmp_path / "pipe.npz"
    os.mkfifo(fifo)
    with pytest.raises(DoeError, match="not a regular file"):
        fileio.read_npz(fifo, [], "thing")
