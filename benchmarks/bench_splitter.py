"""A peer's test: the invrs-gym ``diffractive_splitter`` challenge, designed here, scored there.

The challenge (invrs-gym, MIT): a 7 x 7 spot array from one 7.2 um period of a fused-silica relief
(n = 1.46) 0.692 um deep, at 632.8 nm, lit from the air side, scored by its own Fourier modal
evaluation (fmmax, 793 terms) as ``total efficiency x (1 - uniformity error)`` in TE. Public
leaderboard: designs from a commercial tool 0.136-0.435, best entry 0.561.

This tool's design: the thin-element model of the period (``doedesign.rigorous.thin_element_efficiencies``,
18 x 18 pixels of 0.4 um, the challenge's minimum feature) optimized with the tool's nlopt driver
(:func:`doedesign.optimizer.nlopt_driver.minimize`, L-BFGS, gradients by JAX) and its annealing finish
(:func:`doedesign.optimizer.anneal.anneal`), then rounded by the level rule
(:func:`doedesign.levels.quantize`) and polished pixel by pixel on the thin-element metric
(:func:`_polish`, a direct binary search; the tool has none, and annealed two-level heights round
to a poor binary element). The binary design is scored by the challenge's own code; the 2-,
4-, 8- and 16-level designs (steps of 2 pi / N at 632.8 nm) by :func:`doedesign.rigorous.rigorous_efficiencies`
on the same grid as a stack of binary layers (its binary score beside the challenge's checks the two).

invrs-gym imports ``refractiveindex2``, which downloads a database at import; the diffractive
splitter uses none of its materials, so offline a stand-in module is installed first
(:func:`_offline_refractiveindex`).

Measured (2-core CPU, shared; 2026-12-02): the binary design's thin-element metric 0.335, the
challenge's score 0.0154 (``doe rigorous`` on the same settings: 0.0154, 58 s CPU against the
challenge's 136 s, both with JAX compilation); 4, 8 and 16 levels at 401 terms: 0.0033, 0.0019,
0.0025 (thin-element 0.278, 0.544, 0.532). 0.4 um cells are 0.63 wavelengths: far outside the
thin-element limits, and a thin-element design fails the rigorous score.

    python -m benchmarks.bench_splitter [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
import types

import numpy as np

from doedesign.levels import quantize
from doedesign.optimizer.anneal import anneal
from doedesign.optimizer.nlopt_driver import minimize
from doedesign.rigorous import rigorous_efficiencies

WL_UM = 0.6328
N_GLASS = 1.46
PERIOD_UM = 7.2
CELLS = 18  # 0.4 um pixels: the challenge's minimum width
GRID = 180  # the challenge's 0.04 um grid
SPLIT = 3  # orders -3..3 in x and y
BINARY_DEPTH_UM = 0.692
LEADERBOARD = {"commercial tool, lowest": 0.136, "commercial tool, highest": 0.435, "best entry": 0.561}


def _orders():
    o = np.arange(-SPLIT, SPLIT + 1)
    return np.array([(p, q) for p in o for q in o])


def metric(eta: np.ndarray) -> float:
    """The challenge's eval metric: total x (1 - (max - min) / (max + min))."""
    return float(eta.sum() * (1 - (eta.max() - eta.min()) / (eta.max() + eta.min())))


def _thin_loss(levels_n):
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    o = _orders()
    env = jnp.asarray(np.sinc(o[:, 0] / CELLS) ** 2 * np.sinc(o[:, 1] / CELLS) ** 2)
    k = 2 * np.pi * (N_GLASS - 1) / WL_UM

    def loss(h_um):
        c = jnp.fft.fft2(jnp.exp(1j * k * h_um)) / h_um.size
        eta = jnp.abs(c[o[:, 1] % CELLS, o[:, 0] % CELLS]) ** 2 * env
        mean = jnp.mean(eta)
        return -jnp.sum(eta) + 1.0 * jnp.sqrt(jnp.mean((eta / mean - 1) ** 2))

    vg = jax.jit(jax.value_and_grad(loss))

    def fun(x):
        v, g = vg(jnp.asarray(x.reshape(CELLS, CELLS)))
        return float(v), np.asarray(g).reshape(x.shape)

    return fun


def thin_metric(h_um: np.ndarray) -> float:
    o = _orders()
    c = np.fft.fft2(np.exp(2j * np.pi * (N_GLASS - 1) * h_um / WL_UM)) / h_um.size
    eta = np.abs(c[o[:, 1] % CELLS, o[:, 0] % CELLS]) ** 2 * np.sinc(o[:, 0] / CELLS) ** 2 * np.sinc(o[:, 1] / CELLS) ** 2
    return metric(eta)


def design_splitter(n_levels: int, starts: int = 6, iterations: int = 300) -> tuple[np.ndarray, np.ndarray, float]:
    """Thin-element design of the period: (levels, heights in um, thin-element metric)."""
    step = WL_UM / (N_GLASS - 1) / n_levels
    fun = _thin_loss(n_levels)
    best = None
    for seed in range(starts):
        rng = np.random.default_rng([53, n_levels, seed])
        x0 = -rng.uniform(0, (n_levels - 1) * step, (CELLS, CELLS))
        lo, hi = -(n_levels - 1) * step, 0.0  # the process range: every height has a fabricable level
        h, _ = minimize(fun, x0, lo, hi, max_iter=iterations, desc=f"splitter {n_levels} start {seed}")
        scale = abs(fun(h.ravel())[0])

        def stage(h0, max_iter, max_time_s, desc, penalty):
            def pen(x):
                v, g = fun(x)
                pv, pg = penalty(x)
                return v + pv, g + pg
            return minimize(pen, h0, lo, hi, max_iter=max_iter, max_time_s=max_time_s, desc=desc)

        h, _ = anneal(stage, h.reshape(CELLS, CELLS), step, scale, iterations // 3)
        levels = _polish(quantize(h * 1e-6, step * 1e-6, n_levels).levels, n_levels, step)
        hq = -levels * step
        m = thin_metric(hq)
        if best is None or m > best[2]:
            best = (levels, hq, m)
    return best


def _polish(levels: np.ndarray, n_levels: int, step: float, passes: int = 20) -> np.ndarray:
    """Pixel-by-pixel level changes that raise the thin-element metric (a direct binary search),
    after the rounding: the annealed heights of a two-level element round to a poor binary one,
    which the nlopt stages, on continuous heights, cannot fix."""
    lev = levels.copy()
    best = thin_metric(-lev * step)
    for _ in range(passes):
        improved = False
        for r in range(lev.shape[0]):
            for c in range(lev.shape[1]):
                keep = lev[r, c]
                for k in range(n_levels):
                    if k == keep:
                        continue
                    lev[r, c] = k
                    m = thin_metric(-lev * step)
                    if m > best + 1e-12:
                        best, keep, improved = m, k, True
                lev[r, c] = keep
        if not improved:
            break
    return lev


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


def run(quick: bool = False) -> list[dict]:
    rows = []
    terms_ml = 200 if quick else 400
    designs = {n: design_splitter(n, starts=2 if quick else 6, iterations=100 if quick else 300)
               for n in ((2, 4) if quick else (2, 4, 8, 16))}
    lev2, h2, thin2 = designs[2]
    h2_gym = np.where(lev2 == 0, 0.0, -BINARY_DEPTH_UM)
    g, g_cpu = gym_score(lev2)
    rows.append(dict(benchmark="splitter", figure="invrs-gym diffractive_splitter: binary design from doe's optimizer, "
                                                  "challenge's own score", value=round(g, 4), unit="eval metric",
                     peer="leaderboard best / commercial tool range", peer_value=LEADERBOARD["best entry"],
                     ratio=round(g / LEADERBOARD["best entry"], 3), limit=None,
                     notes=f"thin-element metric of the same design {thin2:.3f}; commercial-tool entries "
                           f"{LEADERBOARD['commercial tool, lowest']}-{LEADERBOARD['commercial tool, highest']}; "
                           f"18 x 18 cells of 0.4 um, depth 0.692 um"))
    own, own_cpu, own_terms = own_score(h2_gym, 800)
    rows.append(dict(benchmark="splitter", figure="one period of the splitter: challenge's evaluation CPU time",
                     value=round(g_cpu, 1), unit="s CPU", peer=None, peer_value=None, ratio=None, limit=60.0,
                     notes="invrs-gym response + eval metric, 793 terms, includes JAX compilation"))
    rows.append(dict(benchmark="splitter", figure="one period of the splitter: doe rigorous CPU time (same settings)",
                     value=round(own_cpu, 1), unit="s CPU", peer="challenge's evaluation", peer_value=round(g_cpu, 1),
                     ratio=round(own_cpu / g_cpu, 3), limit=60.0,
                     notes=f"{own_terms} terms; its score {own:.4f} beside the challenge's {g:.4f}"))
    for n, (lev, h, thin) in designs.items():
        s, cpu, terms = own_score(h, terms_ml)
        rows.append(dict(benchmark="splitter", figure=f"splitter at {n} levels (steps of 2 pi / {n}), rigorous score",
                         value=round(s, 4), unit="eval metric", peer="leaderboard best", peer_value=LEADERBOARD["best entry"],
                         ratio=round(s / LEADERBOARD["best entry"], 3), limit=None,
                         notes=f"doe rigorous, {terms} terms, {n - 1} binary layers, {cpu:.0f} s CPU; thin-element "
                               f"metric {thin:.3f}"))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--rows")
    args = ap.parse_args(argv)
    rows = run(args.quick)
    if args.rows:
        from doedesign.fileio import write_json

        write_json(args.rows, rows)
    for r in rows:
        sys.stdout.write(f"{r['figure']}: {r['value']} {r['unit']} ({r['notes']})\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
