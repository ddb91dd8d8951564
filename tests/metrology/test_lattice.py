"""Registration of a periodic design (one cell, surround "repeat") modulo its lattice, on a
field drawn analytically: discs on a lattice with unequal x and y periods (a scanner's two piezo
calibrations), turned 5 degrees, edges blurred."""

import numpy as np
import pytest
from scipy.special import erfc

from doedesign.errors import DoeError
from metrology.matching.lattice import cell_depths, edge_span, fundamental_peaks, register_lattice
from metrology.matching.match import assess_match
from metrology.matching.register import Registration, design_on_measurement

PIXEL = 0.2e-6
STEP = 490e-9
CELL = 40
PITCH = 0.25e-6  # 40 design pixels: a 10 um cell


def _disc_field(px_um=10.12, py_um=9.88, turn_deg=5.0, origin=(101.3, 87.6), shape=(256, 256), radius_um=2.8):
    t = np.radians(turn_deg)
    ax = px_um / (PIXEL * 1e6) * np.array([-np.sin(t), np.cos(t)])  # (row, col): y up is row down
    ay = py_um / (PIXEL * 1e6) * np.array([np.cos(t), np.sin(t)])
    rr, cc = np.mgrid[:shape[0], :shape[1]].astype(float)
    d = np.stack([rr - origin[0], cc - origin[1]])
    f = np.tensordot(np.linalg.inv(np.column_stack([ax, ay])), d, axes=1)
    f -= np.rint(f)
    off = f[0][None] * ax[:, None, None] + f[1][None] * ay[:, None, None]
    dist_um = np.hypot(off[0], off[1]) * PIXEL * 1e6
    h = STEP * 0.5 * erfc((dist_um - radius_um) / (np.sqrt(2) * 0.3)) - STEP
    return h, ax, ay, np.array(origin)


def _disc_cell(diameter_px=22):
    c = np.arange(CELL) - (CELL - 1) / 2
    rr, cc = np.meshgrid(c, c, indexing="ij")
    levels = np.where(rr ** 2 + cc ** 2 <= (diameter_px / 2) ** 2, 0, 1).astype(np.int16)
    return levels, -STEP * levels


def test_fundamental_peaks_give_each_axis_period_turn_and_shear():
    h, ax, ay, _ = _disc_field()
    lat = fundamental_peaks(h, (CELL * PITCH / PIXEL, CELL * PITCH / PIXEL))
    assert lat.period_px[0] == pytest.approx(np.hypot(*ax), rel=1e-3)
    assert lat.period_px[1] == pytest.approx(np.hypot(*ay), rel=1e-3)
    assert lat.turn_deg == pytest.approx(5.0, abs=0.05)
    assert abs(lat.shear_deg) < 0.1
    report = lat.report(PIXEL)
    assert report["period_um_xy"][0] == pytest.approx(10.12, rel=1e-3)
    assert "modulo" in report["modulo"]


def test_lattice_registration_maps_every_disc_onto_the_cells_disc():
    h, ax, ay, origin = _disc_field()
    levels, printed = _disc_cell()
    reg, tiled, tiled_printed, _ = register_lattice(h, levels, printed, PITCH, PIXEL)
    assert tiled.shape[0] % CELL == 0 and tiled.shape == tiled_printed.shape
    for i, j in ((0, 0), (1, 0), (0, 1), (-1, 2)):
        r, c = origin + i * ax + j * ay
        if not (0 <= r < 256 and 0 <= c < 256):
            continue
        dr, dc = reg.to_design(r, c)
        # The disc centre lands on the cell's centre (19.5, 19.5) modulo the cell.
        assert (dr - 19.5 + CELL / 2) % CELL - CELL / 2 == pytest.approx(0, abs=0.3)
        assert (dc - 19.5 + CELL / 2) % CELL - CELL / 2 == pytest.approx(0, abs=0.3)
    sx, sy = reg.decompose()["scale_xy"]
    assert sx == pytest.approx(CELL / np.hypot(*ax), rel=2e-3) and sy == pytest.approx(CELL / np.hypot(*ay), rel=2e-3)
    # The whole field lies on the tiled design, and reads it out: a raster scan's 2.4 % aspect passes.
    labels = design_on_measurement(tiled, reg)
    assert (labels >= 0).all()
    check = assess_match(h, tiled_printed, STEP, reg, scanned=True, edge_span=edge_span(levels))
    assert check.ok and check.pixel_aspect == pytest.approx(10.12 / 9.88 - 1, abs=3e-3)
    assert not check.aspect_judged


def test_lattice_of_another_cell_is_refused():
    h, *_ = _disc_field()
    stripes = np.zeros((CELL, CELL), np.int16)
    stripes[:, :5] = 1
    stripes[:5, :] = 1
    with pytest.raises(DoeError, match="another lattice"):
        register_lattice(h, stripes, -STEP * stripes, PITCH, PIXEL)


def test_camera_pixels_of_unequal_axes_refused_raster_scan_not():
    rng = np.random.default_rng(2)
    design_levels = np.kron(rng.integers(0, 2, (12, 12)), np.ones((5, 5), int))
    printed = -STEP * design_levels
    reg = Registration(matrix=np.diag([1.0, 1.03]), offset=np.array([4.0, 4.0]), pitch_m=PITCH,
                       design_shape=printed.shape, measurement_shape=(50, 48))
    h = design_on_measurement(printed, reg, fill=0.0).astype(float)
    camera = assess_match(h, printed, STEP, reg)
    assert not camera.ok and "longer along one axis" in camera.problem
    raster = assess_match(h, printed, STEP, reg, scanned=True)
    assert raster.ok and raster.pixel_aspect == pytest.approx(0.03, abs=1e-3)


def test_edge_span_is_a_third_of_the_shortest_run():
    stripes = np.zeros((CELL, CELL), np.int16)
    stripes[:, 10:22] = 1  # runs of 12 and 28 along the rows, none across
    assert edge_span(stripes) == 4
    assert edge_span(np.zeros((CELL, CELL), np.int16)) == CELL // 3


def test_cell_depths_scatter_is_the_cells_own():
    """Cells of known steps: the mean and the scatter over the cells come back."""
    levels, _ = _disc_cell()
    tiled = np.tile(levels, (4, 4))
    steps = 480e-9 + 10e-9 * np.arange(16).reshape(4, 4)
    h = -np.kron(steps, np.ones((CELL, CELL))) * tiled
    reg = Registration(matrix=np.eye(2), offset=np.zeros(2), pitch_m=PITCH, design_shape=tiled.shape,
                       measurement_shape=tiled.shape)
    out = cell_depths(h, tiled, np.ones(tiled.shape, bool), reg, (CELL, CELL))
    assert out["cells"] == 16
    assert out["depth_nm"] == pytest.approx(steps.mean() * 1e9, abs=1e-6)
    assert out["std_nm"] == pytest.approx(np.std(steps, ddof=1) * 1e9, rel=1e-9)
