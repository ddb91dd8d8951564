"""``doe map``: tiles of a whole element, maps and models, against an independent generator."""

import json

import numpy as np
import pytest

from doedesign.cli import main
from doedesign.design import Design
from metrology.diagnosis.map_models import fit_depth_model, fit_overlay_model
from metrology.diagnosis.map_report import assemble
from metrology.diagnosis.tiles_map import map_tiles, run_map

from elementgen import DEPTHS_M, PITCH_M, element_levels, measure

EFFECTS = ["etch_depth", "mask_overlay", "linewidth_bias", "etch_loading", "mask_rotation"]
T = 40


def _design(levels, path):
    masks = np.stack([(levels >> j) & 1 for j in range(4)])
    height = -np.tensordot(np.array(DEPTHS_M), masks, 1)
    Design(height_m=height, pitch_m=PITCH_M, levels=levels.astype(np.int16)).save(path)


def test_models_recover_known_fields():
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-4e-3, 4e-3, (2, 30))
    s = np.full(30, 1e-9)
    # 7 ppm magnification, 5 urad rotation, a 20 nm shift, with 1 nm noise.
    dx = 20e-9 + 7e-6 * x - 5e-6 * y + 1e-9 * rng.standard_normal(30)
    dy = 7e-6 * y + 5e-6 * x + 1e-9 * rng.standard_normal(30)
    t = fit_overlay_model(x, y, dx, dy, s, s)["terms"]
    assert t["magnification_ppm"]["value"] == pytest.approx(7, rel=0.05)
    assert t["rotation_urad"]["value"] == pytest.approx(5, rel=0.05)
    assert t["translation_x_m"]["value"] == pytest.approx(20e-9, rel=0.05)
    assert not t["translation_y_m"]["named"] and not t["orthogonality_urad"]["named"]
    e = 0.01 + 0.03 * (x ** 2 + y ** 2) / 4.3e-3 ** 2 + 1e-4 * rng.standard_normal(30)
    d = fit_depth_model(x, y, e, np.full(30, 1e-4), 4.3e-3)["terms"]
    assert d["radial_centre_to_edge"]["value"] == pytest.approx(0.03, rel=0.02)
    assert not d["gradient_x_per_mm"]["named"]


def test_tile_grid_covers_the_design_with_overlap():
    tiles = map_tiles((100, 130), 40, 8)
    rows = sorted({t["region"][0] for t in tiles})
    cols = sorted({t["region"][2] for t in tiles})
    assert rows == [0, 32, 60] and cols == [0, 32, 64, 90]
    assert all(t["region"][1] - t["region"][0] == 40 for t in tiles)


def test_null_element_with_gaps_and_tiles_off_the_map(tmp_path):
    """A null element: flat maps, no model term; a half-measured tile is still diagnosed, a stitch gap
    and the tiles beyond a map smaller than the element say why; nothing is refused."""
    n, u = 400, 2
    levels = element_levels(n)
    starts = [0, 200, 320]
    patches = [(r, r + T, c, c + T) for r in starts for c in starts if (r, c) != (200, 200)]
    m = measure(levels, u, patches, {})
    m[0:T * u // 2, 200 * u:(200 + T) * u] = np.nan  # half of one tile unmeasured
    np.save(tmp_path / "map.npy", m[:, :(n - 60) * u])  # the last 60 design columns were not measured
    _design(levels, tmp_path / "d.npz")
    out = tmp_path / "out"
    assert main(["map", "--design", str(tmp_path / "d.npz"), "--measured", str(tmp_path / "map.npy"),
                 "--upsample", "2", "--out", str(out), "--tile-px", "40", "--overlap-px", "0",
                 "--effects", ",".join(EFFECTS), "--scheduler", "inline"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["n_diagnosed"] == 8  # every patch, those at column 320 cut by the map's edge to half
    assert report["named_terms"] == []
    why = {t["id"]: t["status"] for t in report["not_diagnosed"]}
    assert why["r00200c00200"] == "not measured (gap)"
    assert why["r00000c00360"] == "off the measured area"
    assert len(why) == report["n_tiles"] - 8
    for j in (1, 2, 3):
        assert np.max(np.abs(report["maps"][f"overlay_mask{j}_m"]["dx"])) < 3e-9
    assert (out / "overlay.png").is_file() and (out / "report.md").is_file()
    # A rerun resumes: nothing is diagnosed again.
    lines = (out / "tiles.jsonl").read_text().count("\n")
    run_map(levels, PITCH_M, tmp_path / "map.npy", u, out, tile_px=T, overlap_px=0, candidates=EFFECTS,
            scheduler="inline")
    assert (out / "tiles.jsonl").read_text().count("\n") == lines
    # A run killed while writing leaves half a line: that tile alone is diagnosed again.
    text = (out / "tiles.jsonl").read_text().splitlines()
    ok_line = next(i for i, t in enumerate(text) if '"status": "ok"' in t)
    (out / "tiles.jsonl").write_text("\n".join(text[:ok_line] + text[ok_line + 1:] + [text[ok_line][:40]]) + "\n")
    cli_depths = [v * 1e-9 for v in (75, 150, 300, 600)]  # as doe map reads --depths-nm (75 * 1e-9 != 75e-9)
    again = run_map(levels, PITCH_M, tmp_path / "map.npy", u, out, tile_px=T, overlap_px=0, candidates=EFFECTS,
                    scheduler="inline", depths_m=cli_depths)
    first = json.loads(text[ok_line])
    redo = next(r for r in again if r["id"] == first["id"])
    # On one BLAS thread (as in a Dask worker) the tile repeats bit for bit in the same warm process.
    assert redo == first


@pytest.mark.slow
def test_whole_element_recovers_radial_depth_magnification_rotation(tmp_path):
    """The 1600 px element (5.4 um pixels; the map at 2.7 um, 9 tiles measured): 3 % radial depth,
    10 ppm magnification of mask 2, a shift and a 10 urad rotation of mask 3, each within 20 %."""
    n, u = 1600, 2
    levels = element_levels(n)
    starts = [0, 800, 1560]
    patches = [(r, r + T, c, c + T) for r in starts for c in starts]
    truth = {"radial": 0.03, "magnification": {2: 10e-6}, "shift_m": {3: (50e-9, -30e-9)},
             "rotation_rad": {3: 10e-6}}
    np.save(tmp_path / "map.npy", measure(levels, u, patches, truth))
    tiles = run_map(levels, PITCH_M, tmp_path / "map.npy", u, tmp_path / "out", tile_px=T, overlap_px=0,
                    candidates=EFFECTS, scheduler="inline")
    res = assemble(tiles, levels.shape, PITCH_M)
    m = res["models"]
    assert m["overlay_mask2"]["terms"]["magnification_ppm"]["value"] == pytest.approx(10, rel=0.2)
    assert m["overlay_mask3"]["terms"]["rotation_urad"]["value"] == pytest.approx(10, rel=0.2)
    assert m["overlay_mask3"]["terms"]["translation_x_m"]["value"] == pytest.approx(50e-9, rel=0.2)
    assert m["overlay_mask3"]["terms"]["translation_y_m"]["value"] == pytest.approx(-30e-9, rel=0.2)
    assert m["depth_all"]["terms"]["radial_centre_to_edge"]["value"] == pytest.approx(0.03, rel=0.2)
    assert set(res["named_terms"]) >= {"overlay_mask2.magnification_ppm", "overlay_mask3.rotation_urad",
                                      "overlay_mask3.translation_x_m", "overlay_mask3.translation_y_m",
                                      "depth_all.radial_centre_to_edge"}
    assert not any(t.startswith("overlay_mask1") for t in res["named_terms"])


# Depth errors and an overlay on two tiles of a 120 px element: before tiles ran on one BLAS
# thread, inline results differed from the workers' in the last bits of these tiles' overlays.
SCALE_TRUTH = {"depth_error": [0.02, 0.02, 0.02, 0.02], "shift_m": {2: (40e-9, 0.0)}}


def _scale_map(tmp_path):
    levels = element_levels(120)
    np.save(tmp_path / "map.npy", measure(levels, 2, [(40, 80, 40, 80), (0, 40, 80, 120)], SCALE_TRUTH))
    return levels


def _run(levels, tmp_path, scheduler, workers=None):
    out = tmp_path / f"{scheduler}{workers}"
    run_map(levels, PITCH_M, tmp_path / "map.npy", 2, out, tile_px=T, overlap_px=0, candidates=EFFECTS,
            scheduler=scheduler, workers=workers, tiles_per_task=1)
    return (out / "tiles.jsonl").read_text().splitlines()


def _by_id(lines):
    return sorted(lines, key=lambda line: json.loads(line)["id"])


def test_inline_and_two_workers_write_the_same_tiles(tmp_path, monkeypatch, capsys):
    """Same input, same answer: tiles.jsonl inline and on two Dask workers, byte for byte (the
    lines in tile order: workers finish in their own order). With bars on, the map draws its own
    bar and no tile draws the bars of its diagnosis's steps."""
    levels = _scale_map(tmp_path)
    monkeypatch.setenv("DOE_PROGRESS", "1")
    inline = _run(levels, tmp_path, "inline")
    bars = capsys.readouterr().err
    assert "map tiles" in bars and "diagnosis step" not in bars
    monkeypatch.delenv("DOE_PROGRESS")
    assert sum('"status": "ok"' in line for line in inline) == 2
    assert _by_id(_run(levels, tmp_path, "processes", 2)) == _by_id(inline)


@pytest.mark.slow
def test_same_map_with_one_two_and_four_workers(tmp_path):
    levels = _scale_map(tmp_path)
    runs = [_by_id(_run(levels, tmp_path, "processes", w)) for w in (1, 2, 4)]
    assert runs[0] == runs[1] == runs[2] == _by_id(_run(levels, tmp_path, "threads", 2))


def test_map_corrections_name_aligner_scale_and_radial_warning(tmp_path):
    from metrology.diagnosis.map_correction import map_corrections, read_map_report

    rng = np.random.default_rng(5)
    x, y = rng.uniform(-4e-3, 4e-3, (2, 25))
    s = np.full(25, 1e-9)
    noise = lambda: 0.5e-9 * rng.standard_normal(25)  # noqa: E731
    zero = fit_overlay_model(x, y, noise(), noise(), s, s)
    mag = fit_overlay_model(x, y, 10e-6 * x + noise(), 10e-6 * y + noise(), s, s)
    moved = fit_overlay_model(x, y, 50e-9 - 10e-6 * y + noise(), 10e-6 * x + noise(), s, s)
    e = -0.03 * (x ** 2 + y ** 2) / 4.3e-3 ** 2 + 1e-4 * rng.standard_normal(25)
    report = {"n_tiles": 25, "models": {"overlay_mask1": zero, "overlay_mask2": mag, "overlay_mask3": moved,
                                        "depth_all": fit_depth_model(x, y, e, np.full(25, 1e-4), 4.3e-3)}}
    (tmp_path / "r.json").write_text(json.dumps(report))
    out = map_corrections(read_map_report(tmp_path / "r.json"))
    by_mask = {m["mask"]: m for m in out["masks"]}
    assert by_mask[1] == {"mask": 1, "aligner_offset_m": [0.0, 0.0], "aligner_rotation_rad": 0.0, "mask_scale": 1.0}
    assert by_mask[2]["mask_scale"] == pytest.approx(1 - 10e-6, abs=0.3e-6)
    assert by_mask[3]["aligner_offset_m"][0] == pytest.approx(-50e-9, rel=0.05)
    assert by_mask[3]["aligner_rotation_rad"] == pytest.approx(-10e-6, rel=0.05)
    assert any("mask 2" in w and "ppm" in w for w in out["warnings"])
    assert any("etch depth -3.0" in w for w in out["warnings"])
    (tmp_path / "bad.json").write_text("[1]")
    with pytest.raises(Exception, match="not a doe map report"):
        read_map_report(tmp_path / "bad.json")


def test_hdf5_map_is_read_by_tile(tmp_path):
    import h5py

    from metrology.diagnosis.tiles_map import diagnose_tile, open_map

    levels = element_levels(120)
    m = measure(levels, 2, [(40, 80, 40, 80)], {"shift_m": {1: (60e-9, 0.0)}})
    with h5py.File(tmp_path / "map.h5", "w") as f:
        f.create_dataset("height_m", data=m, chunks=(40, 40), compression="gzip")
    arr = open_map(tmp_path / "map.h5")
    assert isinstance(arr, h5py.Dataset)  # not read into memory
    rec = diagnose_tile(levels, PITCH_M, str(tmp_path / "map.h5"), 2, {"id": "t", "region": [40, 80, 40, 80]},
                        list(DEPTHS_M), EFFECTS, 10.0)
    dx, err = rec["params"]["dx_mask1_m"]
    assert rec["status"] == "ok" and abs(dx - 60e-9) < max(3 * err, 6e-9)
    (tmp_path / "map.txt").write_text("1 2 3")
    with pytest.raises(Exception, match="must be .npy or .h5"):
        open_map(tmp_path / "map.txt")


def test_a_tiles_model_surface_is_simulate_surface_bit_for_bit_on_random_models():
    """The tile's model evaluations (masks' etches kept between them, the design checked once)
    give simulate_surface's region bit for bit, on a design larger than the tile, for random
    values of the map's effects, etch loading and the registration, in a fit-like sequence (one
    effect moved at a time, moves taken back)."""
    from masks.process import ProcessParams, simulate_surface
    from metrology.diagnosis.effects import apply_process, effects_for
    from metrology.diagnosis.heights import HeightProblem

    levels = element_levels(160)
    region, u = (60, 100, 40, 80), 2
    meas = measure(levels, u, [region], {})[region[0] * u:region[1] * u, region[2] * u:region[3] * u]
    problem = HeightProblem(levels, PITCH_M, meas, PITCH_M / u, region, ProcessParams.ideal(depths_m=list(DEPTHS_M)),
                            effects_for("height", ["etch_depth", "mask_overlay", "linewidth_bias", "etch_loading"]))
    rng = np.random.default_rng(7)
    model = {n: np.zeros(len(e.params)) for n, e in problem.effects.items()}
    names = list(model)
    for i in range(60):
        name = names[rng.integers(len(names))]
        if name == "etch_loading" and i % 3:
            model[name] = np.zeros(1)  # mostly off: the etches at unit depth are reused
        else:
            scales = problem.effects[name].scales()
            model[name] = rng.uniform(-1, 1, scales.size) * scales * (rng.integers(1, 4))
            lo, hi = problem.effects[name].bounds()
            model[name] = np.clip(model[name], lo, hi)
        chosen = sorted((problem.effects[n] for n in model), key=lambda e: e.order)
        params = apply_process(problem.base, chosen, model)
        np.testing.assert_array_equal(problem.process_surface(params),
                                      simulate_surface(levels, PITCH_M, params, step_m=PITCH_M / u,
                                                       region=region).height_m)
