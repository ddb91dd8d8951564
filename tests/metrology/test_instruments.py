"""Analytic checks of the tests' three profilometer simulators (``tests/metrology/instruments``).

Each simulator is checked against closed forms computed here by other means: the erf profile
of a blurred step (point samples), its mean over a turned pixel footprint by Gauss-Legendre
quadrature (pixel integration), and for the interferometer the chinese-hat MTF on gratings and
its edge response as a 1-D frequency integral (scipy.integrate.quad).
"""

import ast
import inspect

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import ndtr

import filegen
from instruments import boxcar, csi, point

QUIET = dict(tilt_rad=np.zeros(2), piston_m=0.0, noise_m=0.0, n_spikes=0, invalid_fraction=0.0)
CSI_QUIET = dict(QUIET, batwing=0.0, dropout_probability=0.0)
MODULES = (point, boxcar, csi)


def _quiet(mod):
    return CSI_QUIET if mod is csi else QUIET


def _design_points(inst, out_shape):
    """Design (row, col) of every camera pixel centre, from the instrument's matrix/offset."""
    r, c = np.indices(out_shape, dtype=float)
    m, o = inst["matrix"], inst["offset"]
    return m[0, 0] * r + m[0, 1] * c + o[0], m[1, 0] * r + m[1, 1] * c + o[1]


def _step(design_shape, fine, col_edge, depth_m):
    """Fine-grid surface etched by ``depth_m`` right of design column coordinate ``col_edge``
    (a cell boundary), 0 left of it."""
    _, cols = filegen.fine_grid(design_shape, fine)
    return np.broadcast_to(np.where(cols > col_edge, -depth_m, 0.0)[None, :],
                           (design_shape[0] * fine, design_shape[1] * fine)).copy()


@pytest.mark.parametrize("mod", MODULES, ids=lambda m: m.__name__)
def test_flat_surface_gives_the_plane_of_tilt_and_piston_only(mod):
    shape, fine, out = (12, 12), 40, (40, 40)
    tilt = np.array([1.5e-4, -0.8e-4])
    h, inst = mod.measure(np.zeros((shape[0] * fine, shape[1] * fine)), fine, shape, out, np.random.default_rng(3),
                          **dict(_quiet(mod), tilt_rad=tilt, piston_m=0.2e-6, rotation_deg=0.8, flip_rows=True))
    r, c = np.indices(out)
    x = (c - (out[1] - 1) / 2) * inst["pixel_m"]
    y = ((out[0] - 1) / 2 - r) * inst["pixel_m"]
    np.testing.assert_allclose(h, tilt[0] * x + tilt[1] * y + 0.2e-6, rtol=0, atol=1e-15)


@pytest.mark.parametrize("mod", (point, boxcar), ids=lambda m: m.__name__)
def test_uniformly_etched_design_reads_flat_away_from_its_border(mod):
    shape, fine, out = (12, 12), 40, (30, 30)
    h, _ = mod.measure(np.full((shape[0] * fine, shape[1] * fine), -300e-9), fine, shape, out,
                       np.random.default_rng(4), **dict(_quiet(mod), pixel_m=1e-6))
    np.testing.assert_allclose(h, -300e-9, rtol=0, atol=1e-15)


def test_csi_flat_etched_design_is_flat_but_for_the_airy_tail_of_its_border():
    # The incoherent Airy PSF's tail carries the unetched surround's 0 some way in (~1/x^2);
    # 100 um from the border that is well under a percent of the depth.
    shape, fine, out = (44, 44), 20, (20, 20)
    h, _ = csi.measure(np.full((shape[0] * fine, shape[1] * fine), -300e-9), fine, shape, out,
                       np.random.default_rng(4), **dict(CSI_QUIET, pixel_m=1e-6, na=0.4))
    assert np.abs(h + 300e-9).max() < 1e-9
    assert np.ptp(h) < 0.1e-9


def test_point_instrument_reads_the_blurred_step_at_each_pixel_centre():
    shape, fine, out, depth = (12, 12), 80, (40, 40), 300e-9
    edge = 5.5  # a cell boundary (and a design pixel edge)
    h, inst = point.measure(_step(shape, fine, edge, depth), fine, shape, out, np.random.default_rng(5),
                            **dict(QUIET, rotation_deg=0.7, flip_cols=True, flip_rows=False, pixel_m=1.1e-6))
    _, cols = _design_points(inst, out)
    cell = filegen.PITCH_M / fine
    # A step sampled at cell centres, blurred discretely: the continuous step under a Gaussian of
    # variance sigma^2 - cell^2 / 12 (the midpoint rule's end correction).
    sigma = np.sqrt(inst["blur_sigma_m"] ** 2 - cell ** 2 / 12)
    want = -depth * ndtr((cols - edge) * filegen.PITCH_M / sigma)
    np.testing.assert_allclose(h, want, rtol=0, atol=1e-4 * depth)
    assert np.ptp(h) > 0.99 * depth  # the step is in the field


def _box_mean(fun, inst, out, side_px=1.0, n=24):
    """Mean of ``fun(design_row, design_col)`` over each camera pixel's square footprint of side
    ``side_px`` camera pixels, by Gauss-Legendre quadrature."""
    x, w = np.polynomial.legendre.leggauss(n)
    total = np.zeros(out)
    r0, c0 = np.indices(out, dtype=float)
    m, o = inst["matrix"], inst["offset"]
    for a, wa in zip(x * side_px / 2, w):
        for b, wb in zip(x * side_px / 2, w):
            rr, cc = r0 + a, c0 + b
            total += wa * wb / 4 * fun(m[0, 0] * rr + m[0, 1] * cc + o[0], m[1, 0] * rr + m[1, 1] * cc + o[1])
    return total


def test_boxcar_instrument_reads_the_blurred_step_averaged_over_each_turned_pixel():
    shape, fine, out, depth = (12, 12), 80, (40, 40), 300e-9
    edge = 5.5
    h, inst = boxcar.measure(_step(shape, fine, edge, depth), fine, shape, out, np.random.default_rng(6),
                             **dict(QUIET, rotation_deg=-0.9, flip_rows=True, pixel_m=1.2e-6))
    cell = filegen.PITCH_M / fine
    sigma = np.sqrt(inst["blur_sigma_m"] ** 2 - cell ** 2 / 12)
    want = _box_mean(lambda r, c: -depth * ndtr((c - edge) * filegen.PITCH_M / sigma), inst, out)
    np.testing.assert_allclose(h, want, rtol=0, atol=1e-4 * depth)
    # Pixel integration is not point sampling: at the edge they differ by a few % of the step.
    _, cols = _design_points(inst, out)
    point_read = -depth * ndtr((cols - edge) * filegen.PITCH_M / sigma)
    assert np.abs(h - point_read).max() > 0.02 * depth


def _grating(shape, fine, period_m, amp_m, angle_deg=0.0):
    """A cosine grating (fine grid), wave vector at ``angle_deg`` from +x toward +y."""
    rows, cols = filegen.fine_grid(shape, fine)
    t = np.radians(angle_deg)
    x = cols[None, :] * filegen.PITCH_M
    y = -rows[:, None] * filegen.PITCH_M
    return amp_m * np.cos(2 * np.pi * (np.cos(t) * x + np.sin(t) * y) / period_m)


def _amplitude(h, inst, out, period_m, angle_deg=0.0):
    """Least-squares amplitude of the grating frequency in the image (plus a plane)."""
    rows, cols = _design_points(inst, out)
    t = np.radians(angle_deg)
    ph = 2 * np.pi * (np.cos(t) * cols * filegen.PITCH_M - np.sin(t) * rows * filegen.PITCH_M) / period_m
    a = np.column_stack([np.cos(ph).ravel(), np.sin(ph).ravel(), np.ones(h.size), rows.ravel(), cols.ravel()])
    coef = np.linalg.lstsq(a, h.ravel(), rcond=None)[0]
    return np.hypot(coef[0], coef[1])


@pytest.mark.parametrize("na, q", [(0.3, 0.25), (0.45, 0.5), (0.55, 0.8)])
def test_csi_passes_a_grating_by_the_chinese_hat_mtf(na, q):
    shape, fine, out, amp, wl = (24, 24), 40, (60, 60), 50e-9, 0.58e-6
    cutoff = 2 * na / wl
    period = 1 / (q * cutoff)
    # A near-point pixel (fill 1e-6): only the optics filter.
    h, inst = csi.measure(_grating(shape, fine, period, amp, 30.0), fine, shape, out, np.random.default_rng(7),
                          **dict(CSI_QUIET, na=na, wavelength_m=wl, fill=1e-6, rotation_deg=0.5))
    want = (2 / np.pi) * (np.arccos(q) - q * np.sqrt(1 - q * q))
    assert _amplitude(h, inst, out, period, 30.0) / amp == pytest.approx(want, rel=0.02)


def test_csi_passes_nothing_beyond_the_cutoff():
    shape, fine, out, amp, na, wl = (24, 24), 40, (60, 60), 50e-9, 0.35, 0.58e-6
    period = 1 / (1.15 * 2 * na / wl)
    h, inst = csi.measure(_grating(shape, fine, period, amp, -20.0), fine, shape, out, np.random.default_rng(8),
                          **dict(CSI_QUIET, na=na, wavelength_m=wl, fill=1e-6))
    assert _amplitude(h, inst, out, period, -20.0) < 1e-3 * amp
    # The same grating at 0.85 of the cut-off is seen (MTF 0.034): the fit can see it.
    period = 1 / (0.85 * 2 * na / wl)
    h, inst = csi.measure(_grating(shape, fine, period, amp, -20.0), fine, shape, out, np.random.default_rng(8),
                          **dict(CSI_QUIET, na=na, wavelength_m=wl, fill=1e-6))
    assert _amplitude(h, inst, out, period, -20.0) > 0.02 * amp


def _csi_edge(x_m, na, wl, side_m, cell_m):
    """Edge response of the chinese-hat MTF (unit step up at x = 0, x across the edge), averaged
    over a box of ``side_m`` across it: 1/2 + int_0^fc MTF(f) sinc(f a) sin(2 pi f x) / (pi f) df.
    The grid holds the step as samples at cell centres, which a discrete filter reads as a step
    whose spectrum is (pi f c) / sin(pi f c) times the continuous one."""
    fc = 2 * na / wl

    def integrand(f, x):
        mtf = csi.chinese_hat(f, fc)
        return mtf * np.sinc(f * side_m) * np.pi * f * cell_m / np.sin(np.pi * f * cell_m) \
            * np.sin(2 * np.pi * f * x) / (np.pi * f)
    return np.array([0.5 + quad(integrand, 0, fc, args=(x,), limit=400)[0] for x in np.ravel(x_m)])


@pytest.mark.parametrize("fill", [1e-6, 0.25, 1.0])
def test_csi_step_profile_is_the_mtf_edge_averaged_over_the_active_square(fill):
    shape, fine, out, depth, na, wl, pix = (16, 16), 40, (40, 40), 200e-9, 0.3, 0.58e-6, 1.1e-6
    edge = 7.5
    h, inst = csi.measure(_step(shape, fine, edge, depth), fine, shape, out, np.random.default_rng(9),
                          **dict(CSI_QUIET, na=na, wavelength_m=wl, fill=fill, pixel_m=pix, rotation_deg=0.0))
    _, cols = _design_points(inst, out)
    x = (cols[0] - edge) * filegen.PITCH_M           # unrotated: every row holds the profile
    # The etched strip ends at the design's right border (unetched beyond): a second edge,
    # whose Airy tail reaches the field.
    far = (shape[1] - 0.5 - edge) * filegen.PITCH_M
    side, cell = np.sqrt(fill) * pix, filegen.PITCH_M / fine
    want = -depth * (_csi_edge(x, na, wl, side, cell) - _csi_edge(x - far, na, wl, side, cell))
    np.testing.assert_allclose(h, np.broadcast_to(want, out), rtol=0, atol=2e-3 * depth)
    assert np.ptp(h) > 0.95 * depth


def test_csi_batwing_is_the_signed_band_pass_overshoot_at_a_step():
    shape, fine, out, depth, w, amp = (12, 12), 80, (30, 30), 300e-9, 0.3e-6, 0.12
    edge = 5.5
    surf = _step(shape, fine, edge, depth)
    kw = dict(CSI_QUIET, fill=1e-6, pixel_m=0.8e-6, batwing_width_m=w, rotation_deg=0.9)
    h0, inst = csi.measure(surf, fine, shape, out, np.random.default_rng(10), **kw)
    h1, _ = csi.measure(surf, fine, shape, out, np.random.default_rng(10), **dict(kw, batwing=amp))
    _, cols = _design_points(inst, out)
    # Depth grows to the right: the high side is x < 0, where the overshoot is +amp * depth.
    u = -(cols - edge) * filegen.PITCH_M / w
    phi = np.exp(-u ** 2 / 2) / np.sqrt(2 * np.pi)
    want = amp * depth * u * phi / (np.exp(-0.5) / np.sqrt(2 * np.pi))
    np.testing.assert_allclose(h1 - h0, want, rtol=0, atol=0.03 * amp * depth)
    # The pixels read both wings near their peaks (+-amp * depth at x = -+w).
    assert (h1 - h0).max() > 0.7 * amp * depth and (h1 - h0).min() < -0.7 * amp * depth


def test_csi_drops_pixels_at_steep_edges_only():
    shape, fine, out = (16, 16), 40, (50, 50)
    _, cols = filegen.fine_grid(shape, fine)
    # A 600 nm step (steeper than asin(NA) can collect once imaged) and a 20 nm one.
    surf = np.broadcast_to(np.where(cols > 5.5, -600e-9, 0.0) + np.where(cols > 10.5, -20e-9, 0.0),
                           (shape[0] * fine, shape[1] * fine))
    h, inst = csi.measure(surf, fine, shape, out, np.random.default_rng(11),
                          **dict(CSI_QUIET, dropout_probability=1.0, na=0.3, pixel_m=1e-6))
    _, c = _design_points(inst, out)
    dist_um = np.minimum(np.abs(c - 5.5), np.abs(c - 10.5)) * filegen.PITCH_M * 1e6
    near_tall = np.abs(c - 5.5) * filegen.PITCH_M < 0.3e-6
    assert np.isnan(h[near_tall]).all()
    assert not np.isnan(h[np.abs(c - 10.5) * filegen.PITCH_M < 3e-6]).any()
    assert not np.isnan(h[dist_um > 3]).any()
    assert inst["n_dropouts"] == np.isnan(h).sum()
    h, inst = csi.measure(surf, fine, shape, out, np.random.default_rng(11),
                          **dict(CSI_QUIET, dropout_probability=0.0, na=0.3, pixel_m=1e-6))
    assert not np.isnan(h).any()


@pytest.mark.parametrize("mod", MODULES, ids=lambda m: m.__name__)
@pytest.mark.parametrize("flip", ["none", "rows", "cols"])
def test_a_known_feature_lands_where_the_matrix_says(mod, flip):
    shape, fine, out = (12, 12), 40, (40, 40)
    rows, cols = filegen.fine_grid(shape, fine)
    at = np.array([4.3, 7.1])                      # design pixel coordinates of a small dot
    dot = -100e-9 * np.exp(-((rows[:, None] - at[0]) ** 2 + (cols[None, :] - at[1]) ** 2) / (2 * 0.25 ** 2))
    h, inst = mod.measure(dot, fine, shape, out, np.random.default_rng(12),
                          **dict(_quiet(mod), rotation_deg=0.9, flip_rows=flip == "rows", flip_cols=flip == "cols",
                                 centre_px=np.array([5.8, 5.3])))
    r, c = np.indices(out, dtype=float)
    wgt = -h / -h.sum()
    cam = np.array([(wgt * r).sum(), (wgt * c).sum()])     # the dot's centroid in the camera
    np.testing.assert_allclose(inst["matrix"] @ cam + inst["offset"], at, atol=0.01)


@pytest.mark.parametrize("mod", MODULES, ids=lambda m: m.__name__)
def test_drawn_placement_and_artefacts_are_in_their_ranges(mod):
    shape, fine, out = (16, 16), 10, (50, 50)
    surf = np.zeros((shape[0] * fine, shape[1] * fine))
    for seed in range(12):
        h, inst = mod.measure(surf, fine, shape, out, np.random.default_rng(seed))
        assert 0.7e-6 <= inst["pixel_m"] <= 1.3e-6
        assert abs(inst["header_pixel_m"] / inst["pixel_m"] - 1) <= 0.005
        assert abs(inst["rotation_deg"]) <= 1 and not (inst["flip_rows"] and inst["flip_cols"])
        centre = inst["matrix"] @ ((np.array(out) - 1) / 2) + inst["offset"]
        assert np.all(np.abs(centre - (np.array(shape) - 1) / 2) <= 0.5)
        scale = np.sqrt(abs(np.linalg.det(inst["matrix"])))
        assert scale == pytest.approx(inst["pixel_m"] / filegen.PITCH_M, rel=1e-12)
        assert np.all(np.abs(inst["tilt_rad"]) <= 2e-4) and 0.5e-9 <= inst["noise_m"] <= 1.5e-9
        assert 0 <= len(inst["spikes"]) <= 12
        assert all(0.1e-6 <= abs(s) <= 1e-6 for _, _, s in inst["spikes"])
        assert inst["n_invalid"] <= 0.01 * h.size
        if mod is csi:
            assert 0.25 <= inst["na"] <= 0.55 and 0.5 <= inst["fill"] <= 1 and 0 <= inst["batwing"] <= 0.15


@pytest.mark.parametrize("mod", MODULES, ids=lambda m: m.__name__)
def test_a_field_outside_the_design_is_refused(mod):
    shape, fine = (12, 12), 10
    with pytest.raises(ValueError, match="design"):
        mod.measure(np.zeros((120, 120)), fine, shape, (70, 70), np.random.default_rng(0), pixel_m=1.0e-6)
    with pytest.raises(KeyError):
        mod.measure(np.zeros((120, 120)), fine, shape, (20, 20), np.random.default_rng(0), pixel_size=1.0e-6)


@pytest.mark.parametrize("mod", MODULES, ids=lambda m: m.__name__)
def test_simulators_import_neither_the_model_nor_each_other(mod):
    tree = ast.parse(inspect.getsource(mod))
    names = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    names |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert not any(m.startswith(("masks", "metrology", "instruments", "doedesign")) for m in names)
    assert names <= {"__future__", "numpy", "scipy.fft", "scipy.ndimage", "filegen"}


def test_boxcar_instrument_agrees_with_the_generators_own_camera():
    # Two implementations of the same pixel-integrating camera, written apart: filegen's
    # (8 x 8 sub-samples per pixel) and boxcar's (exact footprint mean by FFT), on the same
    # wafer and placement (filegen's drawn geometry; only its artefacts are turned off).
    quiet = dict(tilt_rad=np.zeros(2), noise_m=0.0, n_spikes=0, invalid_fraction=0.0, batwing=0.0)
    case = filegen.make_case(["mask_overlay"], 5, design_px=16, field_px=50, instrument=quiet)
    fi, out = case.instrument, case.height_m.shape
    scale = fi["pixel_m"] / filegen.PITCH_M
    mirror = np.diag([-1.0 if fi["flip_rows"] else 1.0, -1.0 if fi["flip_cols"] else 1.0])
    turn = fi["matrix"] / scale @ mirror
    h, inst = boxcar.measure(filegen.wafer_surface(case.levels, case.truth), filegen.FINE_PER_PX, case.levels.shape,
                             out, np.random.default_rng(0),
                             **dict(QUIET, pixel_m=fi["pixel_m"], flip_rows=fi["flip_rows"], flip_cols=fi["flip_cols"],
                                    rotation_deg=np.degrees(np.arctan2(turn[1, 0], turn[0, 0])),
                                    centre_px=fi["matrix"] @ ((np.array(out) - 1) / 2) + fi["offset"],
                                    blur_sigma_m=fi["blur_sigma_m"]))
    np.testing.assert_allclose(inst["matrix"], fi["matrix"], atol=1e-12)
    diff = h - case.height_m
    diff -= np.mean(diff)                                    # filegen's piston
    assert np.ptp(h) > 500e-9
    assert np.sqrt(np.mean(diff ** 2)) < 0.3e-9
