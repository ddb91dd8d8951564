"""Where the thin-element model stops holding: a 16-level blazed grating, rigorous against scalar.

A 1-D 16-level blazed grating in fused silica (16 pixels per period, levels of 2 pi / 16 at
550 nm, light through the substrate at normal incidence) is scored by the Fourier modal method
(:mod:`doedesign.rigorous`, fmmax) for periods of 2 to 50 wavelengths. The thin-element first
order is sinc^2(1/16) = 0.9872 at every period; the rigorous first order over the transmitted
total (so the 3.4 % interface reflection is not counted) falls below it as the period
shrinks. Rows: that error for TE and TM at each period, and the CPU time of the run. Writes
``benchmarks/results/rigorous_blazed.csv`` and ``.png`` (``--out`` to change the folder).

    python -m benchmarks.bench_rigorous [--quick] [--out DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from doedesign.materials import get_material
from doedesign.rigorous import rigorous_efficiencies

WL_M = 550e-9
LEVELS = 16
PERIODS_WL = (2, 3, 4, 6, 8, 12, 16, 20, 30, 40, 50)
QUICK_PERIODS_WL = (2, 4, 8, 16)


def blazed_table(periods_wl=PERIODS_WL) -> list[dict]:
    """First-order efficiency of the 16-level blazed grating per period (rigorous and thin element)."""
    mat = get_material("fused_silica")
    step = mat.height_2pi_m(WL_M) / LEVELS
    h = (-(LEVELS - 1 - np.arange(LEVELS)) * step)[None, :]  # phase rising to the right: order +1
    thin = float(np.sinc(1 / LEVELS) ** 2)
    out = []
    for p in periods_wl:
        n_glass = float(mat.n(WL_M))
        # every order propagating in the glass, and as many again evanescent
        terms = 2 * int(2 * p * n_glass) + 21
        t0 = time.process_time()
        r = rigorous_efficiencies(h, p * WL_M / LEVELS, [WL_M], mat.n, n_terms=terms)
        cpu = time.process_time() - t0
        k = r.order_index(1)
        row = dict(period_wl=p, feature_wl=p / LEVELS, depth_over_feature=15 * step / (p * WL_M / LEVELS),
                   terms=r.n_terms, thin=thin, cpu_s=cpu)
        for pol in ("te", "tm"):
            e = r.polarized(pol)[0]
            row[f"{pol}_abs"] = float(e[k])
            row[f"{pol}_rel"] = float(e[k] / e.sum())
            row[f"{pol}_error"] = float(e[k] / e.sum() - thin)
        out.append(row)
    return out


def plot(table, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from doedesign.fileio import save_figure

    fig, ax = plt.subplots(figsize=(6, 4))
    p = [r["period_wl"] for r in table]
    ax.plot(p, [r["te_rel"] for r in table], "o-", label="rigorous TE (relative)")
    ax.plot(p, [r["tm_rel"] for r in table], "s-", label="rigorous TM (relative)")
    ax.axhline(table[0]["thin"], color="k", ls="--", label="thin element sinc$^2$(1/16)")
    ax.set_xscale("log")
    ax.set_xticks(p, [str(v) for v in p])
    ax.minorticks_off()
    ax.set_xlabel("period (wavelengths)")
    ax.set_ylabel("first-order efficiency")
    ax.set_title("16-level blazed grating, fused silica, 550 nm")
    ax.legend()
    ax.grid(alpha=0.3)
    save_figure(fig, path)
    plt.close(fig)


def write_csv(table, path):
    from doedesign.fileio import atomic_path

    keys = list(table[0])
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join([",".join(keys)] + [",".join(f"{r[k]:.6g}" for k in keys) for r in table]) + "\n")


def run(quick: bool = False, out: str | Path | None = None) -> list[dict]:
    table = blazed_table(QUICK_PERIODS_WL if quick else PERIODS_WL)
    folder = Path(out) if out else Path(__file__).resolve().parent / "results"
    folder.mkdir(parents=True, exist_ok=True)
    write_csv(table, folder / "rigorous_blazed.csv")
    plot(table, folder / "rigorous_blazed.png")
    rows = []
    for r in table:
        for pol in ("te", "tm"):
            rows.append(dict(benchmark="rigorous", figure=f"16-level blazed, period {r['period_wl']} wavelengths: "
                                                          f"{pol.upper()} first order minus thin element",
                             value=round(r[f"{pol}_error"], 4), unit="efficiency", peer="thin element sinc^2(1/16)",
                             peer_value=round(r["thin"], 4), ratio=round(r[f"{pol}_rel"] / r["thin"], 4), limit=None,
                             notes=f"fmmax {r['terms']} terms, 15 layers, relative to transmitted; absolute "
                                   f"{r[f'{pol}_abs']:.4f}; feature {r['feature_wl']:.3g} wavelengths; "
                                   f"{r['cpu_s']:.1f} s CPU"))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out")
    ap.add_argument("--rows", help="also write the rows as JSON here")
    args = ap.parse_args(argv)
    rows = run(args.quick, args.out)
    if args.rows:
        from doedesign.fileio import write_json

        write_json(args.rows, rows)
    for r in rows:
        sys.stdout.write(f"{r['figure']}: {r['value']} ({r['notes']})\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
