"""The optical proximity correction (masks.opc, masks.opc_density): the contact limit, what it gains
through a 30 um gap, the print it reports against the print model's own tiled path, the minimum
feature, the density stage against the level set alone, and determinism.

The correction images its masks through :func:`masks.proximity.aerial_image_vjp` (one transform
of the whole padded mask, with its adjoint); the check of its reported print goes through
:func:`masks.proximity.print_coverage` (the tiled angular-spectrum sum the process model uses),
a second implementation of the same image.
"""

import numpy as np
import pytest

from doedesign.errors import DoeError
from masks import litho
from masks.grid import narrowest_runs_px
from masks.litho import block_coverage
from masks.opc import OpcSettings, correct_mask
from masks.proximity import ProximityOptics, print_coverage

PITCH = 5.4e-6
UPSAMPLE = 12  # 0.45 um print cells
STEP = PITCH / UPSAMPLE
GAP = 30e-6


def _fine_pattern(seed=5, n=6):
    """A binary mask with about one edge per design pixel (the issue's fine element), on the print grid."""
    design = np.random.default_rng(seed).random((n, n)) < 0.5
    return litho.upsample_mask(design, UPSAMPLE) > 0.5


def test_contact_gap_keeps_the_drawn_mask():
    drawn = _fine_pattern()
    result = correct_mask(drawn, STEP, ProximityOptics(0.0, resist_blur_m=0.0), 0.5, settings=OpcSettings(iterations=3))
    assert result.best_iteration == 0
    assert result.area_error_m2[0] == 0.0
    np.testing.assert_array_equal(block_coverage(result.mask, 2), drawn.astype(np.float32))


def test_correction_through_30um_prints_closer_to_the_design_and_reports_its_real_print():
    drawn = _fine_pattern()
    optics = ProximityOptics(GAP)
    settings = OpcSettings(iterations=12)
    result = correct_mask(drawn, STEP, optics, 0.5, settings=settings)
    errors = np.array(result.area_error_m2)
    # Measured 207 -> 102 um^2 (51 % less) on this pattern; the kept iterate is the best one.
    assert errors[result.best_iteration] == errors.min()
    assert errors.min() < 0.75 * errors[0]
    # The reported print, through the tiled image path of the process model (chrome around it).
    pad = 60
    printed = np.asarray(print_coverage(np.pad(block_coverage(result.mask, settings.subgrid), pad), STEP, optics, 0.5))
    printed = printed[pad:-pad, pad:-pad]
    area_gap = float(np.abs(printed - result.printed).sum()) * STEP ** 2
    assert area_gap < 0.01 * errors[result.best_iteration]
    assert float(np.abs(printed - drawn).sum()) * STEP ** 2 == pytest.approx(errors[result.best_iteration], rel=0.01)


def test_corrected_openings_keep_the_minimum_feature_and_the_run_repeats():
    drawn = _fine_pattern(seed=8)
    settings = OpcSettings(iterations=6, min_feature_cells=4)
    first = correct_mask(drawn, STEP, ProximityOptics(GAP), 0.5, settings=settings)
    narrowest_open, _ = narrowest_runs_px(first.mask)
    assert narrowest_open >= settings.min_feature_cells
    again = correct_mask(drawn, STEP, ProximityOptics(GAP), 0.5, settings=settings)
    np.testing.assert_array_equal(first.mask, again.mask)
    assert first.area_error_m2 == again.area_error_m2


def test_the_density_stage_prints_closer_than_the_level_set_alone_and_repeats():
    drawn = _fine_pattern()
    optics = ProximityOptics(GAP)
    alone = correct_mask(drawn, STEP, optics, 0.5, settings=OpcSettings(iterations=4))
    settings = OpcSettings(iterations=4, method="density", density_iterations=10, step_cells=0.5)
    first = correct_mask(drawn, STEP, optics, 0.5, settings=settings)
    # Iterate 1 is the density stage's own mask (made manufacturable), iterate 0 the drawn mask.
    # Measured 207 -> 92 um^2 at iterate 1 (88 after the polish); the level set alone 138 in 4 steps.
    assert len(first.area_error_m2) == settings.iterations + 2
    assert first.area_error_m2[1] < 0.7 * first.area_error_m2[0]
    assert min(first.area_error_m2) < min(alone.area_error_m2)
    assert narrowest_runs_px(first.mask)[0] >= settings.min_feature_cells
    again = correct_mask(drawn, STEP, optics, 0.5, settings=settings)
    np.testing.assert_array_equal(first.mask, again.mask)
    assert first.area_error_m2 == again.area_error_m2


@pytest.mark.parametrize("kwargs", [{"iterations": 0}, {"subgrid": 9}, {"min_feature_cells": 0},
                                    {"step_cells": 0.0}, {"steepness": float("nan")},
                                    {"level_set_steepness": 0.5}, {"method": "ilt"}, {"density_iterations": 0}])
def test_settings_out_of_range_are_refused(kwargs):
    with pytest.raises(DoeError, match="OPC"):
        OpcSettings(**kwargs)


def test_a_mask_that_is_not_2d_is_refused():
    with pytest.raises(DoeError, match="2-D"):
        correct_mask(np.zeros((2, 3, 4), bool), STEP, ProximityOptics(GAP), 0.5)
