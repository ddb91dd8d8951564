"""Tile results assembled into maps, the models fitted to them, and the report page.

Writes ``report.json`` (strict JSON: per-tile values with uncertainties, the fitted models and
their residuals, the tiles not diagnosed and why), ``report.md``, ``overlay.png`` (a quiver plot
per mask) and ``depth_bias.png`` (colour maps of the depth error and the linewidth bias, and the
depth model's residual). Positions: metres from the design centre, x right, y up.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from metrology.diagnosis.map_models import fit_depth_model, fit_overlay_model

__all__ = ["assemble", "write_report"]


def _xy(rec, shape, pitch_m):
    r, c = rec["centre_design_px"]
    return (c - (shape[1] - 1) / 2) * pitch_m, -(r - (shape[0] - 1) / 2) * pitch_m


def assemble(tiles: list[dict], design_shape: tuple[int, int], pitch_m: float) -> dict:
    """Maps and models of the tiles that were diagnosed (``status`` ok)."""
    ok = [t for t in tiles if t.get("status") == "ok"]
    missing = [{"id": t["id"], "region": t["region"], "status": t.get("status")} for t in tiles
               if t.get("status") != "ok"]
    out: dict[str, Any] = {"n_tiles": len(tiles), "n_diagnosed": len(ok), "not_diagnosed": missing, "models": {}}
    if len(ok) < 3:
        out["models_note"] = "fewer than 3 tiles diagnosed: no model fitted"
        return out
    xy = np.array([_xy(t, design_shape, pitch_m) for t in ok])
    par = lambda name: np.array([t["params"][name] for t in ok])  # noqa: E731  (value, error) per tile
    half = 0.5 * min(design_shape) * pitch_m
    maps: dict[str, Any] = {"x_m": xy[:, 0].tolist(), "y_m": xy[:, 1].tolist(), "tile_ids": [t["id"] for t in ok],
            "loading": [t.get("loading") for t in ok]}
    for j in (1, 2, 3):
        dx, dy = par(f"dx_mask{j}_m"), par(f"dy_mask{j}_m")
        maps[f"overlay_mask{j}_m"] = {"dx": dx[:, 0].tolist(), "dy": dy[:, 0].tolist(),
                                      "dx_error": dx[:, 1].tolist(), "dy_error": dy[:, 1].tolist()}
        out["models"][f"overlay_mask{j}"] = fit_overlay_model(xy[:, 0], xy[:, 1], dx[:, 0], dy[:, 0],
                                                              dx[:, 1], dy[:, 1])
    for j in range(4):
        d, b = par(f"depth_error_mask{j}"), par(f"bias_mask{j}_m")
        maps[f"depth_error_mask{j}"] = {"value": d[:, 0].tolist(), "error": d[:, 1].tolist()}
        maps[f"bias_mask{j}_m"] = {"value": b[:, 0].tolist(), "error": b[:, 1].tolist()}
        out["models"][f"depth_mask{j}"] = fit_depth_model(xy[:, 0], xy[:, 1], d[:, 0], d[:, 1], half)
    # All masks' depth errors together (their weighted mean per tile): the etch's own non-uniformity.
    d = np.stack([par(f"depth_error_mask{j}") for j in range(4)])
    w = 1 / d[:, :, 1] ** 2
    mean, err = (w * d[:, :, 0]).sum(0) / w.sum(0), 1 / np.sqrt(w.sum(0))
    maps["depth_error_all"] = {"value": mean.tolist(), "error": err.tolist()}
    out["models"]["depth_all"] = fit_depth_model(xy[:, 0], xy[:, 1], mean, err, half)
    out["maps"] = maps
    out["named_terms"] = sorted(f"{m}.{k}" for m, fit in out["models"].items() for k, t in fit["terms"].items()
                                if t["named"] and k != "offset")
    return out


def _plots(result, folder):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from doedesign.fileio import save_figure

    maps = result["maps"]
    x, y = np.array(maps["x_m"]) * 1e3, np.array(maps["y_m"]) * 1e3
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.3))
    for ax, j in zip(axes, (1, 2, 3)):
        ov = maps[f"overlay_mask{j}_m"]
        dx, dy = np.array(ov["dx"]) * 1e9, np.array(ov["dy"]) * 1e9
        q = ax.quiver(x, y, dx, dy, np.hypot(dx, dy), cmap="viridis")
        fig.colorbar(q, ax=ax, label="overlay (nm)")
        ax.set(title=f"mask {j} overlay (vs mask 0)", xlabel="x (mm)", ylabel="y (mm)", aspect="equal")
    save_figure(fig, Path(folder) / "overlay.png")
    plt.close(fig)
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.3))
    panels = [(np.array(maps["depth_error_all"]["value"]) * 100, "depth error, all masks (%)"),
              (np.array(result["models"]["depth_all"]["residual"]) * 100, "depth model residual (%)"),
              (np.array(maps["bias_mask3_m"]["value"]) * 1e9, "linewidth bias mask 3 (nm)")]
    for ax, (v, title) in zip(axes, panels):
        s = ax.scatter(x, y, c=v, s=40, marker="s", cmap="coolwarm")
        fig.colorbar(s, ax=ax)
        ax.set(title=title, xlabel="x (mm)", ylabel="y (mm)", aspect="equal")
    save_figure(fig, Path(folder) / "depth_bias.png")
    plt.close(fig)


def write_report(result: dict, folder: str | Path, inputs: dict) -> dict:
    """Write report.json, report.md and the figures into ``folder``; return the report."""
    from doedesign import report_md as md
    from doedesign.fileio import write_json

    folder = Path(folder)
    report = {"inputs": inputs, **result}
    if "maps" in result:
        _plots(result, folder)
    write_json(folder / "report.json", report)
    rows = []
    for m, fit in result.get("models", {}).items():
        for k, t in fit["terms"].items():
            rows.append([m, k, md.fmt_pm(t["value"], t["error"]), "yes" if t["named"] else ""])
    parts = ["# Map of the element", f"{result['n_diagnosed']} of {result['n_tiles']} tiles diagnosed.",
             md.figure(folder, "overlay.png", "overlay of masks 1-3 against mask 0 per tile"),
             md.figure(folder, "depth_bias.png", "depth error, its model's residual and linewidth bias"),
             "## Models (weighted least squares over the tiles)",
             md.table(rows, ["model", "term", "value +- error", "named"]) if rows else result.get("models_note"),
             "## Not diagnosed",
             md.table([[t["id"], t["region"], t["status"]] for t in result["not_diagnosed"][:50]],
                      ["tile", "region (design px)", "why"]) if result["not_diagnosed"] else "Every tile was diagnosed.",
             md.json_link()]
    md.write_markdown(folder / "report.md", parts)
    return report
