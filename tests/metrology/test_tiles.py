"""A large camera window fitted on tiles: the tiles are the whole window's pixels."""

import numpy as np
import pytest

from masks.process import ProcessParams
from metrology.diagnosis.camera import CAMERA, CameraHeightProblem
from metrology.diagnosis.effects import effects_for
from metrology.diagnosis.tiles import TiledCameraProblem, tile_origins
from metrology.matching.instrument import Placement

import filegen


def test_tile_origins_spread_from_edge_to_edge():
    assert tile_origins(512, 48, 4) == [0, 155, 309, 464]
    assert tile_origins(40, 48, 4) == [0]
    assert tile_origins(100, 50, 2) == [0, 50]


def _problem(effects, seed=5, field_px=120):
    case = filegen.make_case(effects, seed, design_px=40, field_px=field_px)
    inst = case.instrument
    pl = Placement(np.array(inst["matrix"]), np.array(inst["offset"]))
    return case, CameraHeightProblem(case.levels, filegen.PITCH_M, case.height_m, pl, ProcessParams.ideal(),
                                     effects_for("height", ["mask_overlay", "linewidth_bias", "mask_rotation"]))


def test_each_tile_renders_the_whole_windows_pixels_with_its_small_margin():
    # Under a refined placement (shift, rotation, scale, blur) and process effects that move
    # edges, a tile's own fine grid, two design pixels wide around it, gives the pixels the
    # whole window's grid gives: the margin holds the kernel and the refinement.
    _, whole = _problem(["mask_overlay"])
    tiled = TiledCameraProblem(whole, tile_px=40, per_side=3)
    model = {CAMERA.name: np.array([0.4, -0.3, 2e-3, 1.5e-3, -2e-3, 0.45e-6]),
             "mask_overlay": np.array([0, 0, 0.3e-6, -0.1e-6, 0, -0.2e-6]),
             "linewidth_bias": np.full(4, 0.2e-6), "mask_rotation": np.array([0, 0.03, 0])}
    full = whole.render(model)
    assert len(tiled.tiles) == 9
    for sl, tile in zip(tiled.slices, tiled.tiles):
        np.testing.assert_allclose(tile.render(model), full[sl], rtol=0, atol=1e-12)


def test_tiled_residual_is_the_whole_fields_levelling_on_the_tiles():
    # One piston and tilt for the field: a plane added to the data is removed from the tiles'
    # residual as from the whole window's, and the residual is the measured minus the model
    # on the tiles' valid pixels.
    case, whole = _problem([])
    tiled = TiledCameraProblem(whole, tile_px=40, per_side=2)
    model = {CAMERA.name: CAMERA.start_values()}
    r = tiled.residual(model)
    assert r.size == int(tiled.compared.sum()) < whole.keep.sum()
    rows, cols = whole.measured.shape
    rr, cc = np.mgrid[:rows, :cols]
    whole.measured = whole.measured + 3e-9 + 2e-11 * rr - 1e-11 * cc
    for tile, sl in zip(tiled.tiles, tiled.slices):
        tile.measured = whole.measured[sl]
    np.testing.assert_allclose(tiled.residual(model), r, rtol=0, atol=1e-15)


@pytest.mark.slow
def test_a_300_px_window_fitted_on_tiles_names_the_hidden_overlay():
    from metrology.diagnosis.camera_diagnosis import diagnose_camera

    case = filegen.make_case(["mask_overlay"], 11, design_px=70, field_px=300)
    inst = case.instrument
    pl = Placement(np.array(inst["matrix"]), np.array(inst["offset"]))
    diag = diagnose_camera(case.levels, filegen.PITCH_M, case.height_m, pl, window_px=300)
    fab = [s for s in diag.steps if s.kind != "artefact"]
    assert [s.effect for s in fab] == ["mask_overlay"]
    j = case.truth["mask_overlay"]["mask"]
    fit = np.array([fab[0].params[f"dx_mask{j}_m"], fab[0].params[f"dy_mask{j}_m"]])
    truth = case.truth["mask_overlay"]["shift_m"]
    assert np.hypot(*(fit - truth)) < 0.1 * np.hypot(*truth)
    assert diag.final_residual_rms < 1.3 * diag.noise_floor
