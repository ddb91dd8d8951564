"""Diagnosis of files measured by three independent instrument simulators, through the CLI.

The wafer comes from ``tests/metrology/filegen.py`` (16-level design of 48 pixels, hidden
fabrication effects: nulls, single effects and pairs, the mix of ``filegen.random_cases``);
the camera image from one of the tests' own instruments (``tests/metrology/instruments``):

- ``point``: Gaussian blur, point samples at the pixel centres (no pixel integration);
- ``boxcar``: Gaussian blur, mean over each pixel's footprint;
- ``csi``: chinese-hat OTF of an NA-limited objective, camera fill factor, batwing, dropouts.

None of them is the diagnosis's own instrument model, so the table measures how the diagnosis
copes with cameras it does not describe exactly. Every case goes through what a user runs,
``doe diagnose --design design.npz --measured measured.datx --out DIR``, as a subprocess with
a time limit, and is scored from ``DIR/report.json``: hidden effects named, false fabrication
names (measurement artefacts may be named), relative parameter errors (limits: 0.1 for
overlay and etch depth, 0.2 for the rest), final residual over the noise floor (limit 1.3),
wall and CPU seconds, and crashes, refusals and time-outs.

With ``--calibrated`` every case is diagnosed as a metrologist with a calibrated instrument
would: an artefact (a random 16-level field of the same pitch) is measured by the same
instrument (its pixel and lateral transfer, :data:`TRANSFER_KEYS`; its mounting, noise and
spikes drawn afresh), ``doe calibrate instrument`` fits it, and ``doe diagnose --instrument``
holds the result (``calibration_cpu_s`` in the row).

Resumable: each finished case is one JSON line of ``OUT/cases.jsonl``; a rerun skips those.
With ``--alone`` the diagnoses run one at a time while ``--workers`` other processes make the
next cases' files ahead of them (the instruments of one seed in one process, which makes their
wafer once; ``OUT/work/INSTRUMENT_SEED/case.json`` marks a case made): each diagnosis shares the
two cores with one file maker, as a user's with one other job, where two cases side by side
(``--workers 2`` without ``--alone``) inflate the CPU seconds as well as the wall (a CSI null: 68
CPU s beside another case, 32 alone). ``--files-only`` makes the files and stops; a run with
``--alone`` after it diagnoses on the idle machine.
``OUT/summary.md`` and ``OUT/summary.json`` hold the table per instrument.

    python -m benchmarks.bench_instruments --n 30 --workers 2 --out benchmarks/results/instruments

``--design-px 130 --field-px 512`` gives the largest fields the speed limit names (512 x 512 camera
pixels, any drawn pixel size and rotation inside the design). ``--design-px 108 --field-px 400-800``
gives each case a field drawn from its seed (:func:`draw_field`): a side of 400-800 camera pixels
and a pixel of 0.7-1.3 um that keeps the field inside the design (at most 0.71 um at 800 px, up
to 1.3 um below 437 px), the size a 20x objective gives over a 0.5 mm design.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np

from benchmarks.bench_diagnose_files import parameter_error
from doedesign.fileio import atomic_path, json_ready, write_json

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "metrology"))
import filegen  # noqa: E402  (the tests' independent wafer generator)
from instruments import boxcar, csi, point  # noqa: E402  (the tests' own instruments)

log = logging.getLogger(__name__)
INSTRUMENTS = {"point": point, "boxcar": boxcar, "csi": csi}
DESIGN_PX = 48
N_CASES = 30
# A safety limit on each diagnosis's wall time, far above any case's (the diagnosis has no clock
# of its own); a case it cuts is a time-out, a failure in the table.
TIME_LIMIT_S = 1800.0
# Largest camera pixel and rotation the simulators draw, and the centre's largest offset (design px).
MAX_PIXEL_M, MAX_ROTATION_DEG, MAX_CENTRE_PX = 1.3e-6, 1.0, 0.5
FINAL_LIMIT = 1.3


MIN_PIXEL_M = 0.7e-6


def _room_m(design_px):
    """Side (m) a square camera field may span, turned by the largest rotation, inside the design."""
    t = math.radians(MAX_ROTATION_DEG)
    return (design_px - 2 * MAX_CENTRE_PX) * filegen.PITCH_M / (math.cos(t) + math.sin(t))


def field_px(design_px=DESIGN_PX):
    """Camera pixels per side of the largest square field that lies inside the design for any
    drawn pixel size, rotation and centre offset."""
    return int(_room_m(design_px) / MAX_PIXEL_M)


def parse_field(text):
    """``--field-px``: ``"512"`` -> 512, ``"400-800"`` -> (400, 800) (a range drawn per case)."""
    lo, _, hi = str(text).partition("-")
    if not lo.strip().isdigit() or (hi and not hi.strip().isdigit()):
        raise ValueError(f"field {text!r}: give camera pixels per side, N or LOW-HIGH")
    if not hi:
        return int(lo)
    lo, hi = int(lo), int(hi)
    if not 0 < lo <= hi:
        raise ValueError(f"field {text!r}: LOW-HIGH with 0 < LOW <= HIGH")
    return lo, hi


def design_for(side_m):
    """Smallest design (px) that holds a square field of side ``side_m`` under any drawn placement."""
    return math.ceil(side_m / (_room_m(2) - _room_m(1)) + 2 * MAX_CENTRE_PX)


def check_field(field, design_px):
    """Raise ``ValueError`` when ``field`` (a range) cannot lie inside the design at the smallest pixel."""
    if isinstance(field, tuple) and field[1] * MIN_PIXEL_M > _room_m(design_px):
        raise ValueError(f"a field of {field[1]} camera pixels of {MIN_PIXEL_M * 1e6:.1f} um does not fit a "
                         f"{design_px} px design; give --design-px {design_for(field[1] * MIN_PIXEL_M)}"
                         " or more")


def draw_field(field, seed, design_px=DESIGN_PX):
    """A case's camera field from its seed: ``(side px, pixel m, header pixel m)``.

    ``field``: a side (the pixel left to the instrument: ``None`` for both pixels) or a range
    ``(lo, hi)``: the side uniform in it, the pixel uniform in 0.7-1.3 um or up to the largest
    that keeps the field inside the design, the header within 0.5 % of it (as the simulators
    draw it). The same for every instrument, from a stream of its own."""
    if not isinstance(field, tuple):
        return (field or field_px(design_px)), None, None
    check_field(field, design_px)
    rng = np.random.default_rng([seed, 400])
    side = int(rng.integers(field[0], field[1] + 1))
    pixel = rng.uniform(MIN_PIXEL_M, min(MAX_PIXEL_M, _room_m(design_px) / side))
    return side, pixel, pixel * (1 + rng.uniform(-0.005, 0.005))


def planned_cases(n, seed=2024):
    """``n`` (effects, seed) pairs in ``filegen.random_cases``' mix: null, single, single, pair."""
    return filegen.planned_cases(n, seed)


# What an instrument's calibration carries over to the fields it measures: its pixel and its
# lateral transfer (draw names of each simulator).
TRANSFER_KEYS = {"point": ("pixel_m", "header_pixel_m", "blur_sigma_m"),
                 "boxcar": ("pixel_m", "header_pixel_m", "blur_sigma_m"),
                 "csi": ("pixel_m", "header_pixel_m", "na", "wavelength_m", "fill", "batwing", "batwing_width_m")}
ARTEFACT_DESIGN_PX, ARTEFACT_FIELD_PX = 40, 130


def calibrate(instrument, case, directory, time_limit_s=TIME_LIMIT_S):
    """Measure an artefact with ``case``'s instrument (its :data:`TRANSFER_KEYS`) and run
    ``doe calibrate instrument`` on it; return (calibration file or None, CPU s, stderr tail)."""
    rng = np.random.default_rng([case.seed, 99])
    levels = filegen.random_levels((ARTEFACT_DESIGN_PX, ARTEFACT_DESIGN_PX), rng)
    held = {k: case.instrument[k] for k in TRANSFER_KEYS[instrument]}
    height, inst = INSTRUMENTS[instrument].measure(filegen.wafer_surface(levels, {}), filegen.FINE_PER_PX,
                                                   levels.shape, (ARTEFACT_FIELD_PX,) * 2, rng, **held)
    design, measured = filegen.FileCase(levels=levels, truth={}, instrument=inst, height_m=height,
                                        seed=case.seed).write(Path(directory))
    out = Path(directory) / "instrument.json"
    code, _, _, cpu, err = _run_doe(["calibrate", "instrument", str(measured), "--design", str(design),
                                     "--out", str(out)], time_limit_s)
    return (out if code == 0 else None), cpu, err


def make_files(instrument, names, seed, directory, design_px=DESIGN_PX, field=None, **overrides):
    """Draw the wafer and the instrument for one case and write its two files; return the case.

    ``overrides``: instrument parameters held instead of drawn (``pixel_m=0.7e-6``); ``field``: a
    side, or a range whose side and pixel are drawn from ``seed`` (:func:`draw_field`)."""
    levels, truth, surface, surface_cpu = _wafer(seed, tuple(names), design_px)
    # The camera draws from its own stream, so every instrument sees the same wafer.
    cam_rng = np.random.default_rng([seed, list(INSTRUMENTS).index(instrument)])
    field, pixel, header = draw_field(field, seed, design_px)
    if pixel is not None:
        overrides = {"pixel_m": pixel, "header_pixel_m": header, **overrides}
    height, inst = INSTRUMENTS[instrument].measure(surface, filegen.FINE_PER_PX, levels.shape, (field, field), cam_rng,
                                                 **overrides)
    case = filegen.FileCase(levels=levels, truth=truth, instrument=inst, height_m=height, seed=seed,
                            extra={"surface_cpu_s": surface_cpu})
    case.write(directory)
    return case


@functools.lru_cache(maxsize=1)
def _wafer(seed, names, design_px):
    """A case's design, hidden effects and fine-grid surface (the same for every instrument, so the
    last one is kept: the instruments of one case in turn share it); and its CPU s when made."""
    t = time.process_time()
    rng = np.random.default_rng(seed)
    levels = filegen.random_levels((design_px, design_px), rng)
    truth = {name: filegen.draw_effect(name, rng) for name in names}
    surface = filegen.wafer_surface(levels, truth)
    surface.flags.writeable = False
    return levels, truth, surface, time.process_time() - t


def _doe():
    here = Path(sys.executable).parent / "doe"
    return [str(here)] if here.exists() else [shutil.which("doe") or "doe"]


def _cpu_limit(seconds):
    def limit():
        resource.setrlimit(resource.RLIMIT_CPU, (int(seconds), int(seconds) + 5))
    return limit


def diagnose(directory, extra=(), time_limit_s=TIME_LIMIT_S, cpu_limit_s=None):
    """Run ``doe diagnose`` on ``directory``'s files; return (exit status or None on time-out,
    report or None, wall s, CPU s, last lines of stderr).

    ``time_limit_s`` bounds the wall time; ``cpu_limit_s`` (optional) the CPU time of each of
    its processes (``RLIMIT_CPU``), the fairer limit on a shared machine. Either ends the run as
    a time-out."""
    out = Path(directory) / "diag"
    code, _, wall, cpu, err = _run_doe(["diagnose", "--design", str(Path(directory) / "design.npz"),
                                        "--measured", str(Path(directory) / "measured.datx"), "--out", str(out),
                                        *extra], time_limit_s, cpu_limit_s)
    report = None
    if code == 0 and (out / "report.json").exists():
        report = json.loads((out / "report.json").read_text())
    return code, report, wall, cpu, err


def _run_doe(args, time_limit_s, cpu_limit_s=None):
    """Run ``doe ARGS`` as a subprocess; return (exit status or None on time-out, None, wall s,
    CPU s, last lines of stderr)."""
    cmd = [*_doe(), *args]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    # Its own session, so that a time-out stops the diagnosis's worker processes too.
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=None if cpu_limit_s is None else _cpu_limit(cpu_limit_s))
    try:
        _, err = proc.communicate(timeout=time_limit_s)
        code = proc.returncode
        if code in (-signal.SIGXCPU, -signal.SIGKILL):  # over the CPU limit
            code = None
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
        code = None
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return code, None, wall, cpu, "\n".join(err.strip().splitlines()[-3:])


def score(names, truth, report):
    """The accuracy part of a case's row from its report."""
    fab = {s["effect"]: s["params"] for s in report["steps"] if not s["measurement_artefact"]}
    errs = {}
    for n in names:
        if n in fab:
            try:
                errs[n] = parameter_error(n, truth[n], fab[n])
            except KeyError:  # a renamed parameter: say so rather than guess
                errs[n] = float("nan")
    floor = report.get("noise_floor")
    final = report.get("final_residual_rms")
    ratio = final / floor if final is not None and floor else float("nan")
    within = all(e <= (0.1 if n in ("mask_overlay", "etch_depth") else 0.2) for n, e in errs.items())
    named_right = sorted(set(fab) & set(names))
    return {"named": sorted(fab), "artefacts": report.get("measurement_artefacts"), "named_right": named_right,
            "false_names": sorted(set(fab) - set(names)), "parameter_error": errs,
            "final_residual_rms": final, "noise_floor": floor, "final_over_floor": ratio,
            "unexplained": report.get("unexplained"),
            "all_right": (len(named_right) == len(names) and not set(fab) - set(names) and within
                          and ratio <= FINAL_LIMIT)}


def prepare_case(instrument, names, seed, work, design_px=DESIGN_PX, field=None):
    """Make one case's files in ``work/INSTRUMENT_SEED`` (:func:`make_files`) and its journal
    row's first part, kept beside them as ``case.json``; a folder that holds one is reused."""
    directory = Path(work) / f"{instrument}_{seed}"
    made = directory / "case.json"
    if made.exists():
        return json.loads(made.read_text())
    if directory.exists():
        shutil.rmtree(directory)
    t = time.process_time()
    case = make_files(instrument, names, seed, directory, design_px, field)
    inst = {k: v for k, v in case.instrument.items() if k != "spikes"}
    row = json_ready({"instrument": instrument, "hidden": list(names), "seed": seed, "truth": case.truth,
                      "camera": inst, "field_px": int(case.height_m.shape[0]), "make_cpu_s": time.process_time() - t,
                      "surface_cpu_s": case.extra["surface_cpu_s"]})
    write_json(made, row)
    return row


def _prepare_one(args):
    instruments, names, seed, *rest = args
    return [prepare_case(i, names, seed, *rest) for i in instruments]


def run_case(instrument, names, seed, work, extra=(), keep=False, time_limit_s=TIME_LIMIT_S, cpu_limit_s=None,
             calibrated=False, design_px=DESIGN_PX, field=None):
    """Make (or reuse, :func:`prepare_case`), diagnose and score one case (``calibrated``: through
    a calibration of its instrument, :func:`calibrate`; ``design_px``, ``field``: as
    :func:`make_files`); return its journal row."""
    directory = Path(work) / f"{instrument}_{seed}"
    row = prepare_case(instrument, names, seed, work, design_px, field)
    case = types.SimpleNamespace(truth=row["truth"], seed=seed, instrument=row["camera"])
    cal = None
    if calibrated:
        cal, row["calibration_cpu_s"], err = calibrate(instrument, case, directory / "artefact", time_limit_s)
        if cal is None:
            row.update(outcome="crash", exit_status=None, wall_s=0.0, cpu_s=0.0, stderr_tail=f"calibration failed: {err}")
            return json_ready(row)
        extra = (*extra, "--instrument", str(cal))
    code, report, wall, cpu, err = diagnose(directory, extra, time_limit_s, cpu_limit_s)
    outcome = ("timeout" if code is None else "ok" if report is not None else "refused" if code == 2 else "crash")
    row.update(outcome=outcome, exit_status=code, wall_s=wall, cpu_s=cpu, stderr_tail=None if code == 0 else err)
    if report is not None:
        row.update(score(names, case.truth, report))
    log.info("%s %s seed %d: %s %s", instrument, "+".join(names) or "null", seed, outcome,
             {k: row.get(k) for k in ("named", "false_names", "parameter_error", "final_over_floor")})
    if row.get("all_right") and not keep:  # a wrong answer keeps its files for analysis
        shutil.rmtree(directory)
    return json_ready(row)


class _Ahead:
    """Cases' files made ahead of their diagnoses in other processes (:func:`_prepare_ahead`)."""

    def __init__(self, pool, futures):
        self.pool, self.futures = pool, futures

    def wait(self, seed):
        """Block until the files of ``seed``'s cases are made (True; a maker's error is raised)."""
        if seed in self.futures:
            made = self.futures.pop(seed).result()
            log.info("files made: seed %d (%s)", seed, ", ".join(r["instrument"] for r in made))
        return True

    def close(self):
        self.pool.shutdown(cancel_futures=True)


def _prepare_ahead(cases, workers):
    """Start making every case's files, in order, in ``workers`` processes (at least one) beside
    the diagnoses; a case whose ``case.json`` exists is reused at once."""
    from concurrent.futures import ProcessPoolExecutor

    by_seed = {}
    for i, names, seed, *rest in cases:
        by_seed.setdefault(seed, [[], names, seed, *rest])[0].append(i)
    # One process per worker, each making one seed's cases at a time (a 800 px point field's
    # surface holds 12 GB while it is made: two makers and a diagnosis fill a 23 GB machine).
    pool = ProcessPoolExecutor(max(1, workers))
    return _Ahead(pool, {seed: pool.submit(_prepare_one, task) for seed, task in by_seed.items()})


def _run_one(args):
    return run_case(*args)


def summary(rows, instruments):
    """Per-instrument totals (a list of dicts, one per instrument)."""
    table = []
    for name in instruments:
        mine = [r for r in rows if r["instrument"] == name]
        ok = [r for r in mine if r["outcome"] == "ok"]
        errs = [e for r in ok for e in r["parameter_error"].values() if e is not None]
        key_errs = [e for r in ok for n, e in r["parameter_error"].items()
                    if e is not None and n in ("mask_overlay", "etch_depth")]
        ratios = [r["final_over_floor"] for r in ok if r["final_over_floor"] is not None]
        table.append({
            "instrument": name, "cases": len(mine), "ran": len(ok),
            "crashed": sum(r["outcome"] == "crash" for r in mine),
            "refused": sum(r["outcome"] == "refused" for r in mine),
            "timed_out": sum(r["outcome"] == "timeout" for r in mine),
            "all_right": sum(bool(r.get("all_right")) for r in mine),
            "hidden": sum(len(r["hidden"]) for r in mine),
            "hidden_named": sum(len(r["named_right"]) for r in ok),
            "false_names": sum(len(r["false_names"]) for r in ok),
            "largest_parameter_error": max(errs, default=None),
            "largest_overlay_or_depth_error": max(key_errs, default=None),
            "within_final_limit": sum(x <= FINAL_LIMIT for x in ratios),
            "median_final_over_floor": float(np.median(ratios)) if ratios else None,
            "largest_final_over_floor": max(ratios, default=None),
            "median_wall_s": float(np.median([r["wall_s"] for r in mine])) if mine else None,
            "median_cpu_s": float(np.median([r["cpu_s"] for r in mine])) if mine else None,
            "max_cpu_s": max((r["cpu_s"] for r in mine), default=None),
            "total_cpu_s": float(sum(r["cpu_s"] for r in mine)),
        })
        cal = [r["calibration_cpu_s"] for r in mine if r.get("calibration_cpu_s") is not None]
        if cal:
            table[-1]["median_calibration_cpu_s"] = float(np.median(cal))
    return table


def summary_markdown(table, rows, info=None, design_px=DESIGN_PX, field=None):
    cols = ["instrument", "cases", "all_right", "ran", "crashed", "refused", "timed_out", "hidden_named", "hidden",
            "false_names", "largest_overlay_or_depth_error", "largest_parameter_error", "within_final_limit",
            "median_final_over_floor", "largest_final_over_floor", "median_wall_s", "median_cpu_s", "max_cpu_s"]
    cols += ["median_calibration_cpu_s"] if all("median_calibration_cpu_s" in t for t in table) else []

    def fmt(v):
        return "" if v is None else f"{v:.3g}" if isinstance(v, float) else str(v)
    lines = []
    if info:
        lines += [f"Machine: {info['cpus']} CPUs, {info.get('memory_gib', '?')} GiB, Python {info['python']} "
                  "(shared: wall times are swamped by other work; CPU seconds are the diagnosis subprocess's).", ""]
    side = (f"{field[0]}-{field[1]} px square (side and pixel drawn per case)" if isinstance(field, tuple)
            else f"{field or field_px(design_px)} px square")
    lines += [f"Design {design_px} x {design_px} px; camera field {side}.", ""]
    lines += ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(t[c]) for c in cols) + " |" for t in table]
    lines += ["", "all_right: every hidden effect named, no false fabrication name, parameter errors within "
              "0.1 (overlay, etch depth) / 0.2 (others), final residual <= 1.3 x the noise floor.", "",
              "| instrument | hidden | seed | field px | pixel um | outcome | named | false | parameter error "
              "| final/floor | wall s | CPU s |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        errs = ", ".join(f"{k} {fmt(v)}" for k, v in (r.get("parameter_error") or {}).items())
        note = r.get("named") if r["outcome"] == "ok" else (r.get("stderr_tail") or "").splitlines()[-1:] or ""
        pixel = r["camera"].get("pixel_m")
        lines.append(f"| {r['instrument']} | {'+'.join(r['hidden']) or 'null'} | {r['seed']} | "
                     f"{r.get('field_px', field or '')} | {'' if pixel is None else f'{pixel * 1e6:.3f}'} | {r['outcome']} | "
                     f"{note} | {r.get('false_names', '')} | {errs} | {fmt(r.get('final_over_floor'))} | "
                     f"{r['wall_s']:.0f} | {r['cpu_s']:.0f} |")
    return "\n".join(lines) + "\n"


def run(quick=False, n=None, workers=1, out=None, instruments=tuple(INSTRUMENTS), extra=(), keep=False,
        time_limit_s=TIME_LIMIT_S, cpu_limit_s=None, calibrated=False, design_px=DESIGN_PX, field=None,
        alone=False, files_only=False):
    """Run (or resume) the cases; return ``benchmarks.run`` rows (one per instrument and figure).

    ``quick``: one null case per instrument. ``out`` (a folder) keeps ``cases.jsonl`` and the
    summaries; without it the cases run in a temporary folder and nothing resumes.
    ``alone``: the diagnoses one at a time, the files made ahead by ``workers`` processes beside
    them. ``files_only``: make the files and stop (a later ``alone`` run diagnoses them).
    """
    import tempfile

    n = 1 if quick else (n or N_CASES)
    tmp = None
    if out is None:
        tmp = tempfile.TemporaryDirectory()
        out = tmp.name
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    journal = out / "cases.jsonl"
    done = [json.loads(line) for line in journal.read_text().splitlines() if line.strip()] if journal.exists() else []
    seen = {(r["instrument"], r["seed"]) for r in done}
    planned = planned_cases(n)
    # Case by case, every instrument in turn: a run stopped early still compares the instruments.
    todo = [(i, names, seed, out / "work", tuple(extra), keep, time_limit_s, cpu_limit_s, calibrated, design_px, field)
            for names, seed in planned
            for i in instruments if (i, seed) not in seen]
    made = None
    if alone or files_only:
        made = _prepare_ahead([(i, names, seed, out / "work", design_px, field) for i, names, seed, *_ in todo],
                              workers)
    if files_only:
        for seed in list(made.futures):
            made.wait(seed)
        made.close()
        return []
    if alone:
        results = (_run_one(args) for args in todo if made.wait(args[2]))
        pool = None
    elif workers > 1:
        from concurrent.futures import ProcessPoolExecutor

        pool = ProcessPoolExecutor(workers)
        results = pool.map(_run_one, todo)
    else:
        pool, results = None, map(_run_one, todo)
    try:
        for row in results:
            done.append(row)
            with open(journal, "a") as f:
                f.write(json.dumps(row) + "\n")
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        if made is not None:
            made.close()
    keys = {(i, s): k for k, (i, s) in enumerate((i, s) for i in instruments for _, s in planned)}
    rows = sorted((r for r in done if (r["instrument"], r["seed"]) in keys),
                  key=lambda r: keys[(r["instrument"], r["seed"])])
    table = summary(rows, instruments)
    from benchmarks.run import machine

    info = machine()
    write_json(out / "summary.json", {"machine": info, "design_px": design_px,
                                      "field_px": list(field) if isinstance(field, tuple) else field or field_px(design_px),
                                      "time_limit_s": time_limit_s, "cpu_limit_s": cpu_limit_s,
                                      "extra_options": list(extra), "calibrated": calibrated,
                                      "instruments": table, "cases": rows})
    with atomic_path(out / "summary.md") as path:
        path.write_text(summary_markdown(table, rows, info, design_px, field))
    if tmp is not None:
        tmp.cleanup()
    return table_rows(table, design_px, field)


def table_rows(table, design_px=DESIGN_PX, field=None):
    """The benchmark table's rows (``benchmarks.run``'s columns) of :func:`summary`'s ``table``."""
    where = (f", design {design_px} px, fields {field[0]}-{field[1]} px" if isinstance(field, tuple)
             else f", design {design_px} px, field {field} px" if field else "")
    return [dict(benchmark="instruments", figure=f"{t['instrument']}{where}: cases all right", value=t["all_right"],
                 unit="count", peer=None, peer_value=None, ratio=None, limit=t["cases"],
                 notes=f"{t['hidden_named']}/{t['hidden']} hidden named, {t['false_names']} false names, "
                       f"{t['crashed']} crashed, {t['refused']} refused, {t['timed_out']} timed out; largest "
                       f"overlay/depth error {_fmt(t['largest_overlay_or_depth_error'])}; {t['within_final_limit']}/"
                       f"{t['ran']} within 1.3x the floor; diagnosis median {_fmt(t['median_cpu_s'])}, max "
                       f"{_fmt(t['max_cpu_s'])} CPU s per case (median wall {_fmt(t['median_wall_s'])} s)")
            for t in table]


def _fmt(v):
    return "none" if v is None else f"{v:.3g}"


def main(argv=None):
    import argparse

    parser = argparse.ArgumentParser(description="diagnosis accuracy on files from three independent instruments")
    parser.add_argument("--n", type=int, default=N_CASES, help="cases per instrument (default 30)")
    parser.add_argument("--out", default="benchmarks/results/instruments", help="output folder (resumes)")
    parser.add_argument("--workers", type=int, default=1, help="cases run side by side")
    parser.add_argument("--instruments", default=",".join(INSTRUMENTS), help="comma-separated subset")
    parser.add_argument("--time-limit", type=float, default=TIME_LIMIT_S, help="wall seconds per diagnosis")
    parser.add_argument("--cpu-limit", type=float, default=None,
                        help="CPU seconds per diagnosis process (RLIMIT_CPU; fairer than wall on a shared machine)")
    parser.add_argument("--keep", action="store_true", help="keep every case's files (those not all right are kept)")
    parser.add_argument("--diagnose-option", action="append", default=[],
                        help="extra option passed to doe diagnose (repeatable, e.g. --diagnose-option=--window-px=96)")
    parser.add_argument("--design-px", type=int, default=DESIGN_PX, help=f"design pixels per side (default {DESIGN_PX})")
    parser.add_argument("--field-px", type=parse_field, default=None,
                        help="camera pixels per side, N or a range LOW-HIGH drawn per case with its pixel "
                             "(default: the largest field inside the design)")
    parser.add_argument("--calibrated", action="store_true",
                        help="diagnose through a calibration of each case's instrument on an artefact it measured")
    parser.add_argument("--alone", action="store_true",
                        help="diagnose the cases one at a time, their files made ahead by --workers other processes "
                             "(none once --files-only has made them: the diagnoses then run on the idle machine)")
    parser.add_argument("--files-only", action="store_true", help="make every case's files and stop")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    names = [s.strip() for s in args.instruments.split(",") if s.strip()]
    unknown = set(names) - set(INSTRUMENTS)
    if unknown:
        parser.error(f"unknown instruments {sorted(unknown)}; choose from {list(INSTRUMENTS)}")
    try:
        check_field(args.field_px, args.design_px)
    except ValueError as exc:
        parser.error(str(exc))
    run(n=args.n, workers=args.workers, out=args.out, instruments=names, extra=args.diagnose_option,
        keep=args.keep, time_limit_s=args.time_limit, cpu_limit_s=args.cpu_limit, calibrated=args.calibrated,
        design_px=args.design_px, field=args.field_px, alone=args.alone,
        files_only=args.files_only)
    log.info("summary: %s", Path(args.out, "summary.md"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
