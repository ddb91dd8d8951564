"""A whole-element height map diagnosed tile by tile, on Dask, resumably.

The map is on the design grid (``pitch_m / upsample`` per pixel, measurement pixel (0, 0) on the
first fine sample of design pixel (0, 0), row 0 at the top), as a stitcher writes it; a small
residual misregistration is the diagnosis's ``registration_shift`` nuisance in every tile. Each
tile (``tile_px`` design pixels per side, ``overlap_px`` shared with its neighbours) is cut from
the file inside the worker (a memory-mapped ``.npy`` or an HDF5 dataset, read lazily), diagnosed
by :func:`metrology.diagnosis.heights.diagnose_heights` (the same model and vocabulary as
``doe diagnose --frame design``) and refitted with the map's parameters free
(:data:`MAP_EFFECTS`: every tile gets a value and an uncertainty of each, named or not).
Each finished tile is appended to ``OUT/tiles.jsonl`` as it comes; a rerun skips those there.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from doedesign.errors import DoeError

__all__ = ["MAP_EFFECTS", "MIN_VALID_SHARE", "diagnose_tile", "load_jsonl", "map_tiles", "open_map", "run_map"]

log = logging.getLogger(__name__)

#: Effects whose parameters every tile reports (etch loading is degenerate with the depths on a tile
#: of near-uniform density: its value comes from the selection where it names it).
MAP_EFFECTS = ("etch_depth", "mask_overlay", "linewidth_bias")
# A tile with less of its pixels measured is reported as not diagnosed (stitch gap, off the field).
MIN_VALID_SHARE = 0.25


def open_map(path: str | Path) -> Any:
    """The height map (m) of ``path`` as a lazily read array: ``.npy`` memory-mapped, ``.h5`` /
    ``.hdf5`` the dataset ``height_m`` (its chunks read on slicing). Only the header is read."""
    from doedesign.fileio import check_input_file

    path = check_input_file(path, DoeError)
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            arr = np.load(path, mmap_mode="r", allow_pickle=False)
        elif suffix in (".h5", ".hdf5"):
            import h5py

            arr = h5py.File(path, "r")["height_m"]
        else:
            raise DoeError(f"{path}: a map must be .npy or .h5 (dataset height_m)")
    except (OSError, KeyError, ValueError) as exc:
        raise DoeError(f"{path}: cannot read the map ({exc})") from None
    if arr.ndim != 2:
        raise DoeError(f"{path}: the map must be 2-D, got shape {arr.shape}")
    return arr


def map_tiles(design_shape: tuple[int, int], tile_px: int, overlap_px: int) -> list[dict]:
    """Tiles over the design: ``id``, ``region`` (row0, row1, col0, col1; half-open design pixels),
    the last of each row and column ending at the design's edge."""
    if not 0 <= overlap_px < tile_px:
        raise DoeError(f"--overlap-px {overlap_px} must be at least 0 and below --tile-px {tile_px}")
    stride = tile_px - overlap_px

    def starts(n):
        if n <= tile_px:
            return [0]
        s = list(range(0, n - tile_px + 1, stride))
        return s if s[-1] == n - tile_px else s + [n - tile_px]

    return [{"id": f"r{r:05d}c{c:05d}", "region": [r, min(r + tile_px, design_shape[0]), c,
                                                      min(c + tile_px, design_shape[1])]}
            for r in starts(design_shape[0]) for c in starts(design_shape[1])]


def diagnose_tile(levels: np.ndarray, pitch_m: float, map_path: str, upsample: int, tile: dict,
                  depths_m: list[float], candidates: list[str] | None, threshold: float) -> dict:
    """One tile's result: where it lies, what the selection named, and each map parameter's value
    and standard error (the refit); ``status`` says why a tile could not be diagnosed.

    Computed on one BLAS thread (:func:`~metrology.diagnosis.parallel.one_thread`) wherever it
    runs, so a tile's result is the same inline, in threads and in any Dask worker, bit for bit.
    Its diagnosis draws no bars of its own: the map's bar counts the tiles.
    """
    from doedesign.progress import silenced
    from metrology.diagnosis.parallel import one_thread

    with one_thread(), silenced():
        return _diagnose_tile(levels, pitch_m, map_path, upsample, tile, depths_m, candidates, threshold)


def _diagnose_tile(levels, pitch_m, map_path, upsample, tile, depths_m, candidates, threshold):
    from masks.process import ProcessParams
    from metrology.diagnosis.effects import effects_for
    from metrology.diagnosis.fitting import fit_effects
    from metrology.diagnosis.heights import HeightProblem, diagnose_heights

    r0, r1, c0, c1 = tile["region"]
    u = int(upsample)
    arr = open_map(map_path)
    rows, cols = arr.shape
    out = {"id": tile["id"], "region": tile["region"],
           "centre_design_px": [(r0 + r1 - 1) / 2, (c0 + c1 - 1) / 2]}
    fine = np.full(((r1 - r0) * u, (c1 - c0) * u), np.nan)
    a0, a1, b0, b1 = r0 * u, min(r1 * u, rows), c0 * u, min(c1 * u, cols)
    if a1 > a0 and b1 > b0:
        fine[:a1 - a0, :b1 - b0] = np.asarray(arr[a0:a1, b0:b1], dtype=float)
    share = float(np.isfinite(fine).mean())
    out["valid_share"] = share
    if share < MIN_VALID_SHARE:
        out["status"] = "off the measured area" if a1 <= a0 or b1 <= b0 else "not measured (gap)"
        return out
    step = pitch_m / u
    region = (r0, r1, c0, c1)
    try:
        diag = diagnose_heights(levels, pitch_m, fine, step, region=region, region_px=max(r1 - r0, c1 - c0),
                                depths_m=depths_m, candidates=candidates, threshold=threshold)
        problem = HeightProblem(levels, pitch_m, fine, step, region, ProcessParams.ideal(depths_m=depths_m),
                                effects_for("height", list(MAP_EFFECTS)))
    except DoeError as exc:
        out["status"] = f"not diagnosed: {exc}"
        return out
    free = list(MAP_EFFECTS) + ["registration_shift"]
    start = {n: np.asarray(diag.model.get(n, np.zeros(len(problem.effects[n].params))), float) for n in free}
    model, _, errors = fit_effects(problem, start, free, precise=True)
    out["status"] = "ok"
    out["named"] = diag.named
    out["unexplained"] = bool(diag.unexplained)
    out["noise_floor_m"] = float(diag.noise_floor)
    out["final_residual_rms_m"] = float(diag.final_residual_rms)
    out["loading"] = float(diag.model["etch_loading"][0]) if "etch_loading" in diag.model else None
    out["params"] = {}
    for name in free:
        for p, v, e in zip(problem.effects[name].params, model[name], errors[name]):
            out["params"][p.name] = [float(v), float(e)]
    return out


def _batch(levels, pitch_m, map_path, upsample, tiles, depths_m, candidates, threshold):
    return [diagnose_tile(levels, pitch_m, map_path, upsample, t, depths_m, candidates, threshold) for t in tiles]


def load_jsonl(path: Path) -> dict[str, dict]:
    """Tile results already in ``path`` (a line cut short by a killed run is dropped)."""
    done = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            done[rec["id"]] = rec
    return done


def run_map(levels: np.ndarray, pitch_m: float, map_path: str | Path, upsample: int, out_dir: str | Path,
            tile_px: int = 40, overlap_px: int = 8, depths_m: list[float] | None = None,
            candidates: list[str] | None = None, threshold: float = 10.0, scheduler: str = "processes",
            workers: int | None = None, tiles_per_task: int = 4) -> list[dict]:
    """Diagnose every tile of a map; results in tile order (the same whatever the workers).

    Parameters
    ----------
    levels : ndarray of int
        Design levels, row 0 at the top.
    pitch_m : float
    map_path : path
        The map (:func:`open_map`), ``pitch_m / upsample`` per pixel.
    upsample : int
        Map pixels per design pixel per axis.
    out_dir : path
        ``tiles.jsonl`` grows there as tiles finish; a rerun resumes.
    tile_px, overlap_px : int
        Design pixels per tile side, and shared by neighbouring tiles.
    scheduler, workers
        As for ``doe tolerance`` (:func:`masks.tolerance.runner.make_client`).
    """
    from doedesign.fileio import dumps_json
    from doedesign.progress import Progress
    from masks.process import ProcessParams
    from masks.tolerance.runner import make_client

    arr = open_map(map_path)
    u = int(upsample)
    need = (levels.shape[0] * u, levels.shape[1] * u)
    if arr.shape != need:
        log.warning("%s: map of %s pixels, the design at %d per pixel needs %s: tiles beyond it are reported "
                    "as off the measured area", map_path, arr.shape, u, need)
    depths = [float(v) for v in (ProcessParams.ideal().etch_depth if depths_m is None else depths_m)]
    tiles = map_tiles(levels.shape, tile_px, overlap_px)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    jsonl = out / "tiles.jsonl"
    done = load_jsonl(jsonl)
    todo = [t for t in tiles if t["id"] not in done]
    batches = [todo[i:i + tiles_per_task] for i in range(0, len(todo), tiles_per_task)]
    args = (np.asarray(levels), float(pitch_m), str(map_path), u)
    with open(jsonl, "a") as fh, Progress(len(tiles), desc="map tiles") as bar:
        bar.update(len(tiles) - len(todo), status="resumed")

        def keep(results):
            for rec in results:
                fh.write(dumps_json(rec, indent=None) + "\n")
                done[rec["id"]] = rec
            fh.flush()
            bar.update(len(results), status=results[-1]["id"] if results else "")

        with make_client(scheduler, workers) as client:
            if client is None:
                for b in batches:
                    keep(_batch(*args, b, depths, candidates, threshold))
            else:
                from distributed import as_completed

                remote = client.scatter(args[0], broadcast=True)
                futures = [client.submit(_batch, remote, *args[1:], b, depths, candidates, threshold, pure=False)
                           for b in batches]
                for future in as_completed(futures):
                    keep(future.result())
    return [done[t["id"]] for t in tiles]
