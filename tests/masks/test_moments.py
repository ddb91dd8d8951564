"""First moments of partly covered fine pixels (masks.moments), against the exact moments of the
continuous openings and ramps."""

import numpy as np
import pytest

from masks import litho
from masks.moments import box_moment_taps, moment_corrected

U = 8  # fine pixels per design pixel


def _half_plane(cols=20, rows=6, open_from=10):
    """A design mask open from column ``open_from`` on (design pixels)."""
    mask = np.zeros((rows, cols), bool)
    mask[:, open_from:] = True
    return mask


@pytest.mark.parametrize("bias_px", [0.3, 0.5, 0.85, 2.4, -0.3, -1.7])
def test_a_biased_edge_keeps_the_opening_s_exact_first_moment(bias_px):
    # The opening is x >= 80 - bias (fine pixel widths, pixel i spans [i, i + 1]) to the image's
    # right end at 160: its area and first moment per row are exact integrals.
    coverage = litho.grown_mask(_half_plane(), U, bias_px)
    x0, width = 10 * U - bias_px, 20 * U
    area, moment = width - x0, (width ** 2 - x0 ** 2) / 2
    centres = np.arange(width) + 0.5
    corrected = moment_corrected(coverage)
    row = corrected[3].astype(float)
    assert row.sum() == pytest.approx(area, abs=1e-5)
    assert row @ centres == pytest.approx(moment, abs=1e-3)
    # The area coverage alone has the area but not the moment: the partial pixel's f (1 - f) / 2.
    f = x0 - np.floor(x0)
    plain = coverage[3].astype(float) @ centres
    assert abs(plain - moment) == pytest.approx(f * (1 - f) / 2, abs=1e-3)
    # Rows are untouched by the column edge (no moment along them).
    np.testing.assert_allclose(corrected[:, 70:], np.broadcast_to(corrected[3, 70:], (48, 90)), atol=1e-6)


@pytest.mark.parametrize("bias_px, shift_rc", [(0.0, (2.35, -1.6)), (0.4, (2.35, -1.6)), (-0.7, (0.5, 3.2))])
def test_a_biased_and_shifted_square_keeps_each_edge_s_first_moment(bias_px, shift_rc):
    # The camera model's print (masks.process with ``moments``): the grown edges' moments, then
    # a move that keeps them. Each edge's own moment is checked in a window holding that edge
    # alone, where the square is cut by it only (a band away from the corners); a linear move
    # of the area coverage misses it by f (1 - f) / 2 per pixel row.
    mask = np.zeros((12, 12), bool)
    mask[3:8, 4:9] = True
    grown = litho.grown_mask(mask, U, bias_px)
    corrected = litho.move(moment_corrected(grown), shift_rc, 0.0, (48.0, 48.0), order=3)
    plain = litho.move(grown, shift_rc, 0.0, (48.0, 48.0))
    r0, r1 = 24 - bias_px + shift_rc[0], 64 + bias_px + shift_rc[0]
    c0, c1 = 32 - bias_px + shift_rc[1], 72 + bias_px + shift_rc[1]
    # Area is kept (grown_mask's convex corners of a shrunk square are not exact areas: compare sums).
    assert corrected.sum() == pytest.approx(plain.sum(), rel=1e-6)
    x = np.arange(96) + 0.5
    for lo, hi, band_axis, edges in ((16, 44, 1, (r0, None)), (44, 76, 1, (None, r1)),
                                     (24, 52, 0, (c0, None)), (52, 84, 0, (None, c1))):
        # Rows (band_axis 1: columns 45..54) or columns (band_axis 0: rows 40..49) of the band.
        band = slice(45, 55) if band_axis == 1 else slice(40, 50)
        pick = (slice(lo, hi), band) if band_axis == 1 else (band, slice(lo, hi))
        axis = 0 if band_axis == 1 else 1
        a, b = (edges[0], hi) if edges[0] is not None else (lo, edges[1])
        exact = 10 * (b ** 2 - a ** 2) / 2
        moment = (np.moveaxis(corrected[pick].astype(float), axis, 0) * x[lo:hi, None]).sum()
        assert moment == pytest.approx(exact, abs=2e-3), (lo, hi, band_axis)
        f = a - np.floor(a) if edges[0] is not None else b - np.floor(b)
        if f * (1 - f) > 0.05:
            linear = (np.moveaxis(plain[pick].astype(float), axis, 0) * x[lo:hi, None]).sum()
            assert abs(linear - exact) > 0.2


def test_whole_pixel_edges_and_smooth_images_are_left_alone():
    coverage = litho.upsample_mask(_half_plane(), U)
    np.testing.assert_array_equal(moment_corrected(coverage), coverage)
    ramp = np.tile(np.linspace(0.0, 1.0, 50, dtype=np.float32), (4, 1))
    np.testing.assert_array_equal(moment_corrected(ramp), ramp)


@pytest.mark.parametrize("width_px", [0.6, 1.5, 2.4, 4.0, 7.3])
def test_the_moment_sidewall_kernel_has_the_ramp_s_second_moment(width_px):
    # A uniform pixel spread by a box of width w is a trapezoid of second moment (1 + w^2) / 12;
    # uniform pixels weighted by taps k_t have sum(k t^2) + 1/12. The taps carry the pixels'
    # first moments, so sum(k t^2) = w^2 / 12 (exact where the trapezoid is linear in each pixel).
    taps = box_moment_taps(width_px)
    np.testing.assert_array_equal(litho.box_kernel(width_px, moments=True), taps)
    t = np.arange(taps.size) - taps.size // 2
    assert taps.sum() == pytest.approx(1.0, abs=1e-9)
    assert taps @ t == pytest.approx(0.0, abs=1e-9)
    assert taps @ t ** 2 == pytest.approx(width_px ** 2 / 12, abs=0.01)
    # The point-value taps give the ramp at the pixel centres, not its pixels' second moment.
    plain = litho.box_kernel(width_px)
    tp = np.arange(plain.size) - plain.size // 2
    assert abs(plain @ tp ** 2 - width_px ** 2 / 12) > 0.02
