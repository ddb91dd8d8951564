"""A peer's test: the invrs-gym ``diffractive_splitter`` challenge, designed here, scored there.

The challenge (invrs-gym, MIT): a 7 x 7 spot array from one 7.2 um period of a fused-silica relief
(n = 1.46) 0.692 um deep, at 632.8 nm, lit from the air side, scored by its own Fourier modal
evaluation (fmmax, 793 terms) as ``total efficiency x (1 - uniformity error)`` in TE. Public
leaderboard: designs from a commercial tool 0.136-0.435, best entry 0.561.

This tool's design, rigorous in the loop: the challenge's metric computed by the Fourier modal
method (:class:`doedesign.optimizer.rigorous_objective.SpotArrayObjective`, fmmax through
:func:`doedesign.rigorous.stack_efficiency`, JAX gradients) on 18 x 18 cells of 0.4 um (the
challenge's minimum width and spacing, so every design respects it), driven by the tool's nlopt
driver (:func:`doedesign.optimizer.nlopt_driver.minimize`, L-BFGS) through a continuation
(:func:`doedesign.optimizer.rigorous_objective.continuation`: tanh projection sharpness 2, 8, 32,
128 and power-mean order 8, 16, 32, 64 for the max and min, fixed evaluation counts), from the
challenge's own start (half-filled, 10 % noise, a fixed seed), then rounded by the level rule
(:func:`doedesign.levels.quantize`). The 8- and 16-level designs start instead from the design
with half their levels, its relief in their finer steps (:func:`warm_start`: level ``k`` becomes
``2k``, the same heights), through a shorter continuation (:func:`warm_stages`: sharpness 4, 16,
64, 256, fixed evaluation counts); the rounded result is kept only if the design model scores it
above its start. The loop runs at 121 Fourier terms (one evaluation with its gradient: about 0.45 s
CPU for one layer, against 1.2-1.4 s at 193 terms and 9.5 s at 401); the binary design is scored by
the challenge's own code at its 793 terms, and the 4-, 8- and 16-level designs (steps of 2 pi / N at
632.8 nm, N - 1 binary layers) by :func:`doedesign.rigorous.rigorous_efficiencies` at 401 terms.

invrs-gym imports ``refractiveindex2``, which downloads a database at import; the diffractive
splitter uses none of its materials, so offline a stand-in module is installed first
(:func:`_offline_refractiveindex`).

Measured (2-core CPU, shared; 2026-12-02): the binary design scores 0.1748 by the challenge's own
code (793 terms; 83.6 s CPU with compilation), inside the commercial tool's 0.136-0.435 and short
of the best entry's 0.561; the design took 149 s CPU (349 evaluations: L-BFGS stopped on a failed
line search in stages 2-4, the gradient of fmmax's jones_direct_fourier field being about 5 % off,
see :mod:`doedesign.optimizer.rigorous_objective`) and its design-model (121-term) metric is 0.245.
The thin-element design this replaces scored 0.0154. At 401 terms (the multi-level scores'
setting) the binary design scores 0.209. Rerun 2026-12-03 with ``--levels 4 8`` (121-term design,
401-term score; 2-core CPU shared, load 4-8): 4 levels 0.326 (220 evaluations, 264 s CPU; the
2026-12-02 run of the same stages gave 0.301, not reproduced, cause not found), 8 levels 0.363 (40 evaluations from the 4-level
design, 133 s CPU with compilation; design model 0.518 -> 0.597). The 401-term figures are not
converged against the challenge's 793 (0.209 against 0.175 on the same binary element), so they
compare levels with each other, not with the leaderboard. 16 levels (2026-12-03, the chain
``--levels 4 8 16`` in one run, single-threaded XLA, which reproduced 0.326 and 0.3628 for 4 and 8):
0.3628, the 8-level design itself: from it, the continuation stopped after 12 of its 20
evaluations (113 s CPU) with a rounded result no better. One 16-level evaluation with its gradient
costs 5.63 s CPU at 121 terms (15 layers; compilation and the first evaluation 43.8 s CPU).
Batching the layers' eigensolves (``batch_layers``) gives the same numbers but did not pay here:
3 batched layers had not finished their first evaluation in 600 s (one layer: 9 s with
compilation), so the design traces one eigensolve per layer (7 layers: compiled and 40
evaluations in 133 s CPU).

    python -m benchmarks.bench_splitter [--quick] [--levels 4 8 16] [--save DIR] [--start DIR/splitter_8_levels.npz]
"""

from __future__ import annotations

import argparse
import sys
import time
import types
from collections.abc import Callable

import numpy as np

from doedesign.levels import quantize
from doedesign.optimizer.rigorous_objective import SpotArrayObjective, continuation, spot_array_metric
from doedesign.rigorous import rigorous_efficiencies

WL_UM = 0.6328
N_GLASS = 1.46
PERIOD_UM = 7.2
CELLS = 18  # 0.4 um pixels: the challenge's minimum width
GRID = 180  # the challenge's 0.04 um grid
SPLIT = 3  # orders -3..3 in x and y
BINARY_DEPTH_UM = 0.692
DESIGN_TERMS = 121  # Fourier terms inside the optimization loop (the score: the challenge's 793)
QUICK_TERMS = 69  # the quick mode: the smallest circular expansion holding the 7 x 7 orders
# Evaluations per stage of the warm-started continuation (:func:`warm_stages`), fixed counts.
WARM_EVALUATIONS = {8: 10, 16: 5}
LEADERBOARD = {"commercial tool, lowest": 0.136, "commercial tool, highest": 0.435, "best entry": 0.561}


def _orders():
    o = np.arange(-SPLIT, SPLIT + 1)
    return np.array([(p, q) for p in o for q in o])


def metric(eta: np.ndarray) -> float:
    """The challenge's eval metric: total x (1 - (max - min) / (max + min))."""
    return spot_array_metric(eta)


def step_um(n_levels: int) -> float:
    """The level step: 2 pi / N at 632.8 nm; the binary element keeps the challenge's 0.692 um."""
    return BINARY_DEPTH_UM if n_levels == 2 else WL_UM / (N_GLASS - 1) / n_levels


def stages(quick: bool, n_levels: int) -> list[tuple[float, float, int]]:
    """(beta, p, evaluations) of the continuation from the challenge's start (2 and 4 levels)."""
    if quick:
        return [(2.0, 8.0, 4), (64.0, 32.0, 4)]
    per = {2: 150, 4: 60}[n_levels]
    return [(2.0, 8.0, per), (8.0, 16.0, per), (32.0, 32.0, per), (128.0, 64.0, per * 2 // 3)]


def warm_stages(quick: bool, n_levels: int) -> list[tuple[float, float, int]]:
    """(beta, p, evaluations) of the continuation from the coarser design (8 and 16 levels).

    The start is already a sharp relief (every layer filled 0 or 1, which any ``beta`` keeps), so
    no stage at ``beta`` 2 washes it out; ``beta`` 4 first, where a layer's projection still has
    slope at 0 and 1 for the driver to move it.
    """
    if quick:
        return [(4.0, 16.0, 3), (64.0, 32.0, 3)]
    per = WARM_EVALUATIONS[n_levels]
    return [(4.0, 16.0, per), (16.0, 32.0, per), (64.0, 64.0, per), (256.0, 64.0, per)]


def warm_start(levels: np.ndarray, n_from: int, n_levels: int) -> np.ndarray:
    """A coarser design's relief in the finer level steps: level ``k`` of ``n_from`` is ``k n_levels / n_from``."""
    if n_levels % n_from or n_from < 4:
        raise ValueError(f"a {n_levels}-level design starts from a design of a divisor of {n_levels} levels, "
                         f"4 or more (2 levels have their own depth), got {n_from}")
    return np.asarray(levels, dtype=float) * (n_levels // n_from)


def design_splitter(n_levels: int, quick: bool = False, start: np.ndarray | None = None) -> dict:
    """Rigorous design of the period, from the challenge's start or from ``start`` (depths in steps).

    Returns ``levels``, ``heights_um``, ``metric`` (the design model's, rounded levels),
    ``start_metric`` (the start's, when given), ``cpu_s``, ``evaluations`` and ``kept_start``
    (True where the rounded design scored below its start and the start was kept: a fixed rule,
    the same answer on any machine).
    """
    t0 = time.process_time()
    terms = QUICK_TERMS if quick else DESIGN_TERMS
    obj = SpotArrayObjective((CELLS, CELLS), PERIOD_UM, WL_UM, N_GLASS, step_um(n_levels), n_levels, _orders(),
                             n_terms=terms, grid=36 if quick else GRID, incidence="air", polarization="te")
    if start is None:
        rng = np.random.default_rng([53, n_levels])
        # the challenge's own start: half-filled with 10 % noise (here in depth steps)
        x0 = np.clip((n_levels - 1) * (0.5 + 0.1 * rng.standard_normal((CELLS, CELLS))), 0, n_levels - 1)
        plan, start_metric = stages(quick, n_levels), None
    else:
        x0 = np.asarray(start, dtype=float)
        plan, start_metric = warm_stages(quick, n_levels), obj.metric(x0)
    d, hist = continuation(obj, x0, plan, desc=f"splitter {n_levels} levels")
    step = step_um(n_levels)
    levels = quantize(-d * step * 1e-6, step * 1e-6, n_levels).levels
    m = obj.metric(levels.astype(float))
    kept = start_metric is not None and start_metric > m
    if kept:
        levels, m = np.rint(x0).astype(levels.dtype), start_metric
    return dict(levels=levels, heights_um=-levels * step, metric=m, start_metric=start_metric,
                cpu_s=time.process_time() - t0, evaluations=len(hist), kept_start=kept)


def upsample(a: np.ndarray) -> np.ndarray:
    f = GRID // a.shape[0]
    return np.repeat(np.repeat(a, f, axis=0), f, axis=1)


def _offline_refractiveindex():
    if "refractiveindex2" in sys.modules:
        return
    try:
        import refractiveindex2  # noqa: F401
        return
    except Exception:
        pass
    ri = types.ModuleType("refractiveindex2")

    class RefractiveIndexMaterial:
        def __init__(self, **kw):
            self.kw = kw

    class NoExtinctionCoefficient(Exception):
        pass

    ri.RefractiveIndexMaterial = RefractiveIndexMaterial
    ri.refractiveindex = types.SimpleNamespace(NoExtinctionCoefficient=NoExtinctionCoefficient)
    sys.modules["refractiveindex2"] = ri


def gym_score(levels_binary: np.ndarray) -> tuple[float, float]:
    """The challenge's own evaluation of a binary design: (eval metric, CPU seconds)."""
    _offline_refractiveindex()
    import dataclasses

    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    from invrs_gym.challenges.diffract import splitter_challenge

    ch = splitter_challenge.diffractive_splitter()
    params = ch.component.init(jax.random.PRNGKey(0))
    # density 1 is glass: the unetched level 0; the array's first axis is x (columns here)
    dens = upsample((levels_binary == 0).astype(float)).T
    params["density"] = dataclasses.replace(params["density"], array=jnp.asarray(dens))
    params["thickness_grating"] = dataclasses.replace(params["thickness_grating"], array=jnp.asarray(BINARY_DEPTH_UM))
    t0 = time.process_time()
    resp, _ = ch.component.response(params)
    value = float(ch.eval_metric(resp))
    return value, time.process_time() - t0


def own_score(h_um: np.ndarray, n_terms: int) -> tuple[float, float, int]:
    """This tool's rigorous score of the period (same settings as the challenge): (metric, CPU s, terms)."""
    t0 = time.process_time()
    r = rigorous_efficiencies(upsample(h_um) * 1e-6, PERIOD_UM / GRID * 1e-6, [WL_UM * 1e-6], N_GLASS,
                              n_terms=n_terms, incidence="air")
    te = r.polarized("te")[0]
    eta = np.array([te[r.order_index(p, q)] for p, q in _orders()])
    return metric(eta), time.process_time() - t0, r.n_terms


def run(quick: bool = False, levels: tuple[int, ...] | None = None,
        on_rows: Callable[[list[dict]], None] | None = None, save_dir: str | None = None,
        start_file: str | None = None) -> list[dict]:
    """Design and score each level count; 8 and 16 levels start from the design with half their levels.

    ``on_rows(rows)``, if given, is called with the rows so far after each level count. Each
    design's levels go to ``save_dir/splitter_<N>_levels.npz`` if given; ``start_file`` (such a
    file) supplies a design to start from, so that ``--levels 16 --start splitter_8_levels.npz``
    continues a chain without designing 4 and 8 levels again.
    """
    rows = []
    terms_ml = QUICK_TERMS if quick else 401
    levels = levels or ((2,) if quick else (2, 4, 8, 16))
    designs: dict[int, np.ndarray] = {}
    if start_file:
        with np.load(start_file) as f:
            designs[int(f["n_levels"])] = np.asarray(f["levels"])
    for n in levels:
        start_from = n // 2 if n >= 8 and n // 2 in designs else None
        start = warm_start(designs[start_from], start_from, n) if start_from else None
        des = design_splitter(n, quick, start)
        lev, design_m, design_cpu, evals = des["levels"], des["metric"], des["cpu_s"], des["evaluations"]
        designs[n] = lev
        if save_dir:
            from pathlib import Path

            Path(save_dir).mkdir(parents=True, exist_ok=True)
            np.savez(Path(save_dir) / f"splitter_{n}_levels.npz", levels=lev, n_levels=n, quick=quick)
        if n == 2 and not quick:
            g, g_cpu = gym_score(lev)
            rows.append(dict(benchmark="splitter", figure="invrs-gym diffractive_splitter: binary design from doe's "
                                                          "optimizer (rigorous loop), challenge's own score",
                             value=round(g, 4), unit="eval metric", peer="leaderboard best / commercial tool range",
                             peer_value=LEADERBOARD["best entry"], ratio=round(g / LEADERBOARD["best entry"], 3),
                             limit=None,
                             notes=f"design model ({DESIGN_TERMS} terms) metric {design_m:.3f}; design {design_cpu:.0f} s "
                                   f"CPU, {evals} evaluations; commercial-tool entries "
                                   f"{LEADERBOARD['commercial tool, lowest']}-{LEADERBOARD['commercial tool, highest']}; "
                                   f"18 x 18 cells of 0.4 um, depth 0.692 um"))
            rows.append(dict(benchmark="splitter", figure="one period of the splitter: challenge's evaluation CPU time",
                             value=round(g_cpu, 1), unit="s CPU", peer=None, peer_value=None, ratio=None, limit=60.0,
                             notes="invrs-gym response + eval metric, 793 terms, includes JAX compilation"))
            own, own_cpu, own_terms = own_score(np.where(lev == 0, 0.0, -BINARY_DEPTH_UM), 800)
            rows.append(dict(benchmark="splitter", figure="one period of the splitter: doe rigorous CPU time (same "
                                                          "settings)", value=round(own_cpu, 1), unit="s CPU",
                             peer="challenge's evaluation", peer_value=round(g_cpu, 1),
                             ratio=round(own_cpu / g_cpu, 3), limit=60.0,
                             notes=f"{own_terms} terms; its score {own:.4f} beside the challenge's {g:.4f}"))
        s, cpu, terms = own_score(des["heights_um"], terms_ml)
        if start_from:
            origin = (f"from the {start_from}-level design (its relief in {n}-level steps, design-model metric "
                      f"{des['start_metric']:.3f})" + ("; the rounded result scored below it, so the start was kept"
                                                        if des["kept_start"] else ""))
        else:
            origin = "from the challenge's start"
        rows.append(dict(benchmark="splitter", figure=f"splitter at {n} levels (steps of 2 pi / {n}), rigorous score",
                         value=round(s, 4), unit="eval metric", peer="leaderboard best", peer_value=LEADERBOARD["best entry"],
                         ratio=round(s / LEADERBOARD["best entry"], 3), limit=None,
                         notes=f"designed in the rigorous loop ({QUICK_TERMS if quick else DESIGN_TERMS} terms, {evals} "
                               f"evaluations, {design_cpu:.0f} s CPU, design-model metric {design_m:.3f}) {origin}; "
                               f"scored by doe rigorous, {terms} terms, {n - 1} binary layers, {cpu:.0f} s CPU"))
        if on_rows:
            on_rows(rows)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--rows")
    ap.add_argument("--levels", type=int, nargs="*", help="level counts to design (default 2 4 8 16)")
    ap.add_argument("--save", help="folder for each design's levels (splitter_<N>_levels.npz)")
    ap.add_argument("--start", help="a saved design (splitter_<N>_levels.npz) to start 2N levels from")
    args = ap.parse_args(argv)
    from doedesign.fileio import write_json

    rows = run(args.quick, tuple(args.levels) if args.levels else None,
               (lambda r: write_json(args.rows, r)) if args.rows else None, args.save, args.start)
    for r in rows:
        sys.stdout.write(f"{r['figure']}: {r['value']} {r['unit']} ({r['notes']})\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
