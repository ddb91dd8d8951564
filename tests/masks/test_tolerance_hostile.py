"""`doe tolerance` against what a hostile user tries (issue 26): bad specs, outputs and scheduler
addresses are refused as one line (exit 2, no traceback, nothing written); servers that are not
dask schedulers are refused within a bounded time; a million samples start at once."""

from __future__ import annotations

import json
import logging
import math
import resource
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from doedesign import budget, cli
from doedesign.camera import Camera
from doedesign.design import Design
from doedesign.errors import DoeError
from doedesign.fileio import INCOMPLETE_MARKER
from doedesign.levels import level_step_m
from masks.tolerance import analysis, scheduler
from masks.tolerance.runner import make_client, n_workers
from masks.tolerance.analysis import nominal_depths
from masks.tolerance.spec import build_spec, default_spec

STEP = level_step_m("fused_silica", 550e-9, 16)


def _design(path, n=16, kind="bayer"):
    levels = np.random.default_rng(3).integers(0, 16, (n, n)).astype(np.int16)
    cam = Camera(aperture_diameter_m=n * 5.4e-6, focus_distance_m=math.inf, window_shape=(16, 16),
                 axis_pixel=(8, 8))
    meta = {"camera": cam.to_dict(), "target": {"kind": kind, "wavelengths_nm": [620.0, 550.0, 450.0], "rggb": True}}
    Design(-levels * STEP, 5.4e-6, levels=levels, metadata=meta).save(path)
    return path


def _run(capsys, *argv):
    code = cli.main(["tolerance", *map(str, argv)])
    return code, capsys.readouterr().err


def _refused(code, err):
    lines = err.strip().splitlines()
    assert code == 2 and "Traceback" not in err and lines[-1].startswith("doe tolerance"), err
    assert len(lines) == 1 or lines[0].startswith("usage:"), err


QUICK = ("--samples", "2", "--sobol-base", "0", "--no-oat", "--scheduler", "inline")


def test_spec_nested_50000_deep(tmp_path, capsys):
    spec = tmp_path / "deep.toml"
    spec.write_text("x = " + "[" * 50000 + "]" * 50000 + "\n")
    code, err = _run(capsys, _design(tmp_path / "d.npz"), "--spec", spec, "--out", tmp_path / "t", *QUICK)
    _refused(code, err)
    assert "nested too deeply" in err and not (tmp_path / "t").exists()
    deep_json = tmp_path / "deep.json"
    deep_json.write_text("[" * 50000 + "]" * 50000)
    code, err = _run(capsys, tmp_path / "d.npz", "--spec", deep_json, "--out", tmp_path / "t", *QUICK)
    _refused(code, err)


def test_sparse_2_gib_spec_refused_from_its_size(tmp_path, capsys):
    spec = tmp_path / "huge.toml"
    with open(spec, "wb") as fh:
        fh.truncate(2 * 1024 ** 3)
    t0 = time.process_time()
    code, err = _run(capsys, _design(tmp_path / "d.npz"), "--spec", spec, "--out", tmp_path / "t", *QUICK)
    _refused(code, err)
    assert "too large" in err and time.process_time() - t0 < 5


def test_absurd_sigma_refused(tmp_path, capsys):
    depths = nominal_depths(Design(np.zeros((2, 2)), 5.4e-6))
    for table, what in (({"mask_overlay": {"sigma_um": 1e6}}, "sigma"), ({"etch_depth": {"mean_nm": 1e9}}, "mean"),
                        ({"roughness": {"dist": "uniform", "low_nm": 0, "high_nm": 1e4}}, "high")):
        with pytest.raises(DoeError, match=f"{what} .* beyond the process model's plausible range"):
            build_spec(table, depths)
    build_spec({"mask_overlay": {"sigma_um": 2}, "etch_depth": {"sigma_rel": 0.5}}, depths)  # plausible
    spec = tmp_path / "s.toml"
    spec.write_text("[mask_overlay]\nsigma_um = 1e6\n")
    code, err = _run(capsys, _design(tmp_path / "d.npz"), "--spec", spec, "--out", tmp_path / "t", *QUICK)
    _refused(code, err)
    assert "sigma 1e+06 um" in err


def test_out_onto_a_file_or_unwritable(tmp_path, capsys):
    design = _design(tmp_path / "d.npz")
    (tmp_path / "f").write_text("keep")
    for out in (tmp_path / "f", tmp_path / "f" / "sub"):
        code, err = _run(capsys, design, "--out", out, *QUICK)
        _refused(code, err)
    assert (tmp_path / "f").read_text() == "keep"


@pytest.mark.skipif(hasattr(__import__("os"), "geteuid") and __import__("os").geteuid() == 0,
                    reason="root writes into read-only folders")
def test_out_in_read_only_folder(tmp_path, capsys):
    design = _design(tmp_path / "d.npz")
    (tmp_path / "ro").mkdir(mode=0o555)
    code, err = _run(capsys, design, "--out", tmp_path / "ro" / "t", *QUICK)
    _refused(code, err)
    assert "not writable" in err


def test_full_disk_keeps_samples_under_the_marker(tmp_path):
    _design(tmp_path / "d.npz")

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (4000, 4000))  # samples (about 1 kB) fit, the report not

    res = subprocess.run([sys.executable, "-c", "import sys; from doedesign.cli import main; sys.exit(main())",
                          "tolerance", "d.npz", "--out", "t", *QUICK], cwd=tmp_path, preexec_fn=limit,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert "File too large" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    out = tmp_path / "t"
    assert (out / INCOMPLETE_MARKER).is_file() and not (out / "report.json").exists()
    assert len(list((out / "samples").glob("mc-*.json"))) == 2  # kept: a rerun resumes from them


@pytest.mark.parametrize("address", ["tcp://", "tcp://host", "tcp://host:99999", "tcp://ho st:80", "tcp://:80",
                                     "tcp://host:port", "tcp://[::1:80", "udp://host:80"])
def test_malformed_scheduler_address(tmp_path, capsys, address):
    code, err = _run(capsys, tmp_path / "missing.npz", "--out", tmp_path / "t", "--scheduler", address)
    _refused(code, err)
    assert "--scheduler" in err and not (tmp_path / "t").exists()


class _Server:
    """A TCP server on 127.0.0.1 that accepts and then answers HTTP, or never answers."""

    def __init__(self, http):
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.sock.settimeout(30)
        self.address = f"tcp://127.0.0.1:{self.sock.getsockname()[1]}"
        self.http, self.conns = http, []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        try:
            while True:
                conn, _ = self.sock.accept()
                self.conns.append(conn)
                if self.http:  # what a web server answers dask's handshake: 8 bytes that read as 3 EiB
                    conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")
        except OSError:
            return

    def close(self):
        self.sock.close()
        for conn in self.conns:
            conn.close()


@pytest.mark.parametrize("http", [True, False], ids=["http", "silent"])
def test_server_that_is_not_a_scheduler_is_refused_in_bounded_time(tmp_path, capsys, monkeypatch, http):
    monkeypatch.setattr(scheduler, "PROBE_TIMEOUT_S", 1.0)
    design = _design(tmp_path / "d.npz")
    server = _Server(http)
    try:
        t0 = time.monotonic()
        code, err = _run(capsys, design, "--out", tmp_path / "t", "--samples", "2", "--scheduler", server.address)
        elapsed = time.monotonic() - t0
    finally:
        server.close()
    _refused(code, err)
    assert ("not a dask scheduler" if http else "sent no dask handshake") in err and elapsed < 15
    assert not (tmp_path / "t").exists()  # connected first: no run.json, no folder


def test_real_scheduler_passes_the_probe():
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://",
                      dashboard_address=None, silence_logs=logging.CRITICAL) as cluster:
        scheduler.probe_scheduler(cluster.scheduler_address, timeout_s=10)
        with make_client(cluster.scheduler_address) as client:
            assert n_workers(client) == 1


def test_a_million_samples_are_drawn_lazily(tmp_path, monkeypatch):
    design = Design.load(_design(tmp_path / "d.npz"))
    spec = default_spec(nominal_depths(design))
    seen = {}

    class Stop(Exception):
        pass

    def fake_run_jobs(ev, jobs, samples_dir, client, seconds_per_job, total):
        seen["total"] = total
        seen["first"] = [next(jobs) for _ in range(3)]
        raise Stop

    monkeypatch.setattr(analysis, "run_jobs", fake_run_jobs)
    t0 = time.process_time()
    with pytest.raises(Stop):
        analysis.tolerance_analysis(design, spec, 1_000_000, tmp_path / "t", scheduler="inline", sobol_base=0,
                                    one_at_a_time=False)
    assert time.process_time() - t0 < 10  # drawing 1e6 parameter sets first took minutes
    assert seen["total"] == 1_000_000
    for k, job in enumerate(seen["first"]):  # the values sample k always had: SeedSequence([seed, k])
        values, seed = spec.draw(0, k)
        assert job["id"] == f"mc-{k:05d}" and job["values"] == values and job["seed"] == seed


def test_unknown_target_kind_is_warned_in_log_and_report(tmp_path, capsys, caplog):
    design = _design(tmp_path / "d.npz", kind="bayr")
    with caplog.at_level(logging.WARNING):
        code, err = _run(capsys, design, "--out", tmp_path / "t", *QUICK)
    assert code == 0, err
    assert any("'bayr' is unknown" in r.getMessage() for r in caplog.records)
    report = json.loads((tmp_path / "t" / "report.json").read_text())
    assert report["primary_metric"] == "efficiency" and "'bayr' is unknown" in report["metric_note"]
    assert "**Warning:** target kind 'bayr' is unknown" in (tmp_path / "t" / "report.md").read_text()
    known = json.loads(json.dumps(analysis.tolerance_analysis(
        Design.load(_design(tmp_path / "k.npz")), default_spec(nominal_depths(Design.load(tmp_path / "k.npz"))),
        1, tmp_path / "k", scheduler="inline", sobol_base=0, one_at_a_time=False)))
    assert known["metric_note"] is None


def test_bayer_design_at_one_wavelength_refused(tmp_path, capsys):
    code, err = _run(capsys, _design(tmp_path / "d.npz"), "--out", tmp_path / "t", "--wavelengths", "550", *QUICK)
    _refused(code, err)
    assert "3 wavelengths" in err and not (tmp_path / "t").exists()


def test_local_workers_checked_against_memory(tmp_path, capsys, monkeypatch):
    design = _design(tmp_path / "d.npz")
    d = Design.load(design)
    ev = analysis.build_evaluator(d, default_spec(nominal_depths(d)))[0]
    # one sample fits, nine (8 workers and this process) do not
    monkeypatch.setenv(budget.LIMIT_ENV, str(3 * analysis.evaluation_bytes(ev)))
    code, err = _run(capsys, design, "--out", tmp_path / "t", "--samples", "2", "--workers", "8")
    _refused(code, err)
    assert "8 local tolerance worker(s)" in err and not (tmp_path / "t").exists()


@pytest.mark.slow
def test_eight_process_workers_shut_down_quietly(tmp_path):
    """8 process workers on a small machine: their shutdown used to print heartbeat tracebacks."""
    _design(tmp_path / "d.npz")
    res = subprocess.run([sys.executable, "-c", "import sys; from doedesign.cli import main; sys.exit(main())",
                          "tolerance", "d.npz", "--out", "t", "--samples", "4", "--sobol-base", "0", "--no-oat",
                          "--workers", "8"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and res.stderr == "", res.stderr
