"""Where a ``doe diagnose`` of a large field spends its CPU time (issue 50's must 2), with no limit.

One case per row set: a wafer drawn by the tests' independent generator (``tests/metrology/filegen``)
and measured by one of the tests' own instrument simulators (``tests/metrology/instruments``) over a
field of 400-800 camera pixels, diagnosed through the command line in this process under
``cProfile`` with the process CPU clock as its timer (every thread's CPU charged to the main thread's
call stack). The rows: CPU seconds of the whole command, of the comparison (registration, levelling
and the instrument's fit on the whole field, before any candidate), of the instrument stage (every
call of :func:`~metrology.diagnosis.camera_nuisance.choose_transfer`, a rerun inside the selection
included) and of the selection (:func:`~metrology.diagnosis.engine.run_diagnosis`, every pass); what
was named and the final residual over the floor. No clock decides the diagnosis: the same case gives
the same answer on any machine, only its time changes.

``python -m benchmarks.bench_large_field [--instrument point --effects mask_overlay --seed 11
--design-px 110 --field 434]``.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import tempfile
import time
from pathlib import Path

__all__ = ["profile_case", "run"]

# Cases like those the instruments missed at the old 60 s default, on fields of 434-500
# camera pixels over a design of 110 px of 5.4 um (the first is the quick run's), and two of the
# largest fields the goal names: 740 and 800 camera pixels of 0.7 um (``pixel_m`` held, not drawn).
CASES = [{"instrument": "point", "effects": ["mask_overlay"], "seed": 11, "design_px": 110, "field": 434},
         {"instrument": "point", "effects": ["etch_depth"], "seed": 12, "design_px": 110, "field": 500},
         {"instrument": "csi", "effects": ["mask_overlay"], "seed": 13, "design_px": 110, "field": 440},
         {"instrument": "boxcar", "effects": ["mask_rotation"], "seed": 14, "design_px": 110, "field": 500},
         {"instrument": "csi", "effects": ["etch_depth"], "seed": 15, "design_px": 110, "field": 740,
          "pixel_m": 0.7e-6},
         {"instrument": "boxcar", "effects": ["linewidth_bias"], "seed": 16, "design_px": 110, "field": 800,
          "pixel_m": 0.7e-6}]
CASE = CASES[0]
# Stage -> (module path suffix, function): the outermost calls' cumulative CPU.
STAGES = {"comparison": ("matching/compare.py", "compare_measurement"),
          "instrument stage": ("diagnosis/camera_nuisance.py", "choose_transfer"),
          "selection": ("diagnosis/engine.py", "run_diagnosis"),
          "report files and plots": ("diagnosis/result.py", "save")}
STAGE_NOTES = {"comparison": " (registration, levelling, edge fit and the instrument's fit on the whole field)",
               "instrument stage": " (every call; its rerun inside the selection is in the selection's row too)",
               "selection": " (every pass, on the busiest window of --window-px 160 camera px, not the whole field)",
               "report files and plots": " (report.json, the maps and the figures)"}


def profile_case(instrument: str, effects: list[str], seed: int, design_px: int, field: int,
                 directory: Path, pstats_path: Path | None = None, pixel_m: float | None = None) -> dict:
    """Make the case's files in ``directory``, diagnose them under the CPU-clock profiler; the figures.

    ``pstats_path``: where to keep the profile too (``pstats`` format), for the top functions;
    ``pixel_m``: the camera pixel held, its header 0.3 % larger (default: both drawn by the instrument)."""
    from benchmarks import bench_instruments as bi
    from doedesign.cli import main

    # The file's header a little off the true pixel, as the simulators draw it (within 0.5 %).
    held = {} if pixel_m is None else {"pixel_m": pixel_m, "header_pixel_m": pixel_m * 1.003}
    case = bi.make_files(instrument, effects, seed, directory, design_px=design_px, field=field, **held)
    prof = cProfile.Profile(time.process_time)
    cpu0 = time.process_time()
    prof.enable()
    code = main(["diagnose", "--design", str(directory / "design.npz"), "--measured",
                 str(directory / "measured.datx"), "--out", str(directory / "diag")])
    prof.disable()
    total = time.process_time() - cpu0
    if pstats_path is not None:
        prof.dump_stats(str(pstats_path))
    stats = pstats.Stats(prof).stats
    stage = {}
    for label, (path, func) in STAGES.items():
        # The outermost call's cumulative time (ct of the entries not called from themselves).
        stage[label] = sum(ct for (file, _, name), (_, _, _, ct, callers) in stats.items()
                           if name == func and file.replace("\\", "/").endswith(path)
                           and not any(c[2] == func for c in callers))
    report = json.loads((directory / "diag" / "report.json").read_text())
    score = bi.score(effects, case.truth, report)
    return {"exit": code, "cpu_s": total, "stages_cpu_s": stage, "named": report["effects_found"],
            "final_over_floor": report["final_residual_rms"] / report["noise_floor"],
            "summary": report["summary"], "all_right": score.get("all_right"), "score": score,
            "field_px": field, "pixel_um": case.instrument.get("pixel_m", float("nan")) * 1e6}


def run(quick: bool = False, case: dict | None = None, pstats_path: Path | None = None,
        keep: Path | None = None) -> list[dict]:
    """Rows of every case of :data:`CASES` (``quick``: the first), or of ``case`` alone (its profile
    kept in ``pstats_path``, its files and diagnosis in the folder ``keep``, if given)."""
    if case is None:
        return [row for c in (CASES[:1] if quick else CASES) for row in run(case=c)]
    case = dict(CASE, **case)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) if keep is None else Path(keep)
        folder.mkdir(parents=True, exist_ok=True)
        got = profile_case(case["instrument"], case["effects"], case["seed"], case["design_px"], case["field"],
                           folder, pstats_path, case.get("pixel_m"))
    name = (f"diagnose {case['instrument']} {'+'.join(case['effects']) or 'null'} seed {case['seed']}, "
            f"{case['field']} x {case['field']} camera px of {got['pixel_um']:.2f} um")
    notes = (f"named {', '.join(got['named']) or 'nothing'}; final {got['final_over_floor']:.2f}x the floor; "
             f"all right: {got['all_right']}; no time limit (same answer on any machine); CPU s on this machine, "
             "every thread")
    rows = [{"benchmark": "large_field", "figure": f"{name}: whole command", "value": round(got["cpu_s"], 1),
             "unit": "CPU s", "peer": None, "peer_value": None, "ratio": None, "limit": 90.0, "notes": notes}]
    for label, value in got["stages_cpu_s"].items():
        rows.append({"benchmark": "large_field", "figure": f"{name}: {label}", "value": round(value, 1),
                     "unit": "CPU s", "peer": None, "peer_value": None, "ratio": None, "limit": None,
                     "notes": f"{100 * value / got['cpu_s']:.0f} % of the command" + STAGE_NOTES.get(label, "")})
    return rows


def _main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--instrument", default=CASE["instrument"])
    parser.add_argument("--effects", default=",".join(CASE["effects"]))
    parser.add_argument("--seed", type=int, default=CASE["seed"])
    parser.add_argument("--design-px", type=int, default=CASE["design_px"])
    parser.add_argument("--field", type=int, default=CASE["field"])
    parser.add_argument("--pixel-m", type=float, help="camera pixel held (default: drawn)")
    parser.add_argument("--case", type=int, help="the case of CASES at this index (the case options ignored)")
    parser.add_argument("--keep", help="keep the case's files and diagnosis in this folder")
    parser.add_argument("--all", action="store_true", help="every case of CASES (the other options ignored)")
    parser.add_argument("--rows", help="write the rows here (JSON)")
    parser.add_argument("--pstats", help="keep the case's cProfile here (pstats format; one case only)")
    args = parser.parse_args(argv)
    case = CASES[args.case] if args.case is not None else {
        "instrument": args.instrument, "effects": [e for e in args.effects.split(",") if e], "seed": args.seed,
        "design_px": args.design_px, "field": args.field, "pixel_m": args.pixel_m}
    rows = run() if args.all else run(case=case, pstats_path=Path(args.pstats) if args.pstats else None,
                                      keep=Path(args.keep) if args.keep else None)
    text = json.dumps(rows, indent=1)
    if args.rows:
        Path(args.rows).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(_main())
