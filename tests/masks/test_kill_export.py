"""A killed ``doe masks`` leaves no file that looks like a result, marks its folder incomplete,
and the next run cleans up after it and leaves complete outputs."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np

from doedesign.design import Design
from doedesign.fileio import INCOMPLETE_MARKER, TEMP_SUFFIX


def _design(tmp_path, n=360):
    rng = np.random.default_rng(5)
    levels = rng.integers(0, 16, (n, n)).astype(np.int16)
    step = Design(np.zeros((2, 2)), 5.4e-6).height_2pi_m() / 16
    return Design(-levels * step, 5.4e-6, levels=levels, metadata={"name": "kill"}).save(tmp_path / "kill.npz")


def _masks(design, out):
    return subprocess.Popen([sys.executable, "-c", "import sys; from doedesign.cli import main; "
                             "sys.exit(main(sys.argv[1:]))", "masks", str(design), "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def test_kill_mid_write_then_rerun(tmp_path):
    design = _design(tmp_path)
    out = tmp_path / "out"
    proc = _masks(design, out)
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        temps = [p for p in out.glob(f".*{TEMP_SUFFIX}")] if out.exists() else []
        # the marker is in place and a temporary is open: the GDS (or its skeleton) is being written
        if temps and (out / INCOMPLETE_MARKER).exists():
            break
        time.sleep(0.005)
    assert proc.poll() is None, "the export finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    names = sorted(p.name for p in out.iterdir())
    # What a kill leaves: the marker and perhaps a temporary, nothing with a result's name.
    assert INCOMPLETE_MARKER in names
    assert "report.json" not in names and "kill.gds" not in names
    assert all(n == INCOMPLETE_MARKER or n.endswith(TEMP_SUFFIX) for n in names), names

    rerun = _masks(design, out)
    assert rerun.wait(timeout=300) == 0, rerun.stderr.read().decode()
    names = sorted(p.name for p in out.iterdir())
    assert names == ["kill.gds", "kill.lyp", "masks.png", "report.json"], names
    report = json.loads((out / "report.json").read_text())
    assert report["verification"]["passed"]
