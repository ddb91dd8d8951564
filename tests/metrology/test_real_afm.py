"""Real etched relief end to end (issue 52, must 3): `doe compare` of the two real Nanosurf AFM
scans (tests/data/realdata/afm-nanosurf-binary-arrays/, NSFopen's example data, MIT licence
beside the files) against binary designs of their lattices.

The test finds each lattice from the file by its own means, independent of the tool's Fourier
registration: the features at mid-height (connected regions), their centroids fitted by
least squares to a lattice (origin + i a + j b) give the periods and the turn; the features'
mean area gives the feature size (disc diameter, square side). It writes a 2-level design of
one cell (surround "repeat"), its feature rounded to whole design pixels, so that the tool must
measure the edge position itself. Independent estimates: the step from the two modes of the
height histogram after the test's own levelling (rows aligned by the median of their
differences, Gwyddion's "median of differences", then the x slope by the median step), the
duty cycle from the share of pixels above mid-height.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage, signal

from doedesign.cli import main
from doedesign.design import Design
from metrology.formats.readers import read_measurement

AFM = Path(__file__).resolve().parents[1] / "data" / "realdata" / "afm-nanosurf-binary-arrays"
CELL_PX = 40  # design pixels per lattice period (0.25 um pixels on the 10 um lattice)

# file, whether the features are raised (unetched top = the features) or holes (top = the field)
SCANS = {"circles.nid": "raised discs", "squares_holes.nid": "square holes"}


def _level_rows(h):
    """The test's own levelling: each row moved by the median of its differences to the row
    above (tilt along y and the scanner's line offsets), then the median step along x out."""
    d = np.nanmedian(np.diff(h, axis=0), axis=1)
    h = h - np.concatenate([[0.0], np.cumsum(d)])[:, None]
    return h - np.nanmedian(np.diff(h, axis=1)) * np.arange(h.shape[1])[None, :]


def _two_modes(h):
    """Heights (m) of the two strongest modes of the height histogram, low first."""
    counts, edges = np.histogram(h[np.isfinite(h)], bins=400)
    smooth = ndimage.gaussian_filter1d(counts.astype(float), 2.0)
    peaks, _ = signal.find_peaks(smooth, distance=40)
    top2 = np.sort(peaks[np.argsort(smooth[peaks])[-2:]])
    centres = 0.5 * (edges[:-1] + edges[1:])
    return centres[top2]


def _lattice_from_features(h, raised):
    """Periods (px along x and y), turn (deg, y up) and mean feature area (px^2) from the
    centroids of the whole features at mid-height."""
    lo, hi = _two_modes(h)
    feature = h > 0.5 * (lo + hi) if raised else h < 0.5 * (lo + hi)
    lab, n = ndimage.label(feature)
    idx = np.arange(1, n + 1)
    area = ndimage.sum(feature, lab, idx)
    cent = np.array(ndimage.center_of_mass(feature, lab, idx))
    slices = ndimage.find_objects(lab)
    whole = np.array([s[0].start > 0 and s[1].start > 0 and s[0].stop < h.shape[0] and s[1].stop < h.shape[1]
                      for s in slices]) & (area > 0.2 * np.median(area))
    cent, area = cent[whole], area[whole]
    # Integer lattice indices from a rough period, then least squares: centre = o + i a + j b.
    period0 = np.sqrt(h.size / whole.sum())
    ij = np.rint((cent - cent[0]) / period0)
    for _ in range(3):
        basis = np.column_stack([np.ones(len(cent)), ij])
        coef, *_ = np.linalg.lstsq(basis, cent, rcond=None)
        ij = np.rint(np.linalg.solve(coef[1:].T, (cent - coef[0]).T).T)
    a_y, a_x = coef[1], coef[2]  # row step of i, col step of j; each (row, col)
    turn = np.degrees(np.arctan2(-a_x[0], a_x[1]))
    return np.hypot(*a_x), np.hypot(*a_y), turn, float(np.mean(area)), feature


def _design_for(h, pixel_m, raised, tmp_path):
    """A one-cell 2-level design of the scan's lattice; returns (path, figures)."""
    levelled = _level_rows(h)
    lo, hi = _two_modes(levelled)
    px, py, turn, area_px, feature = _lattice_from_features(levelled, raised)
    pitch_m = np.sqrt(px * py) * pixel_m / CELL_PX
    scale = pixel_m / pitch_m  # design pixels per measurement pixel
    c = (np.arange(CELL_PX) - (CELL_PX - 1) / 2)
    rr, cc = np.meshgrid(c, c, indexing="ij")
    if raised:
        diameter = 2 * np.sqrt(area_px / np.pi) * scale
        size = np.round(diameter)  # whole design pixels: the tool must find the edges itself
        inside = rr ** 2 + cc ** 2 <= (size / 2) ** 2
        levels = np.where(inside, 0, 1)
    else:
        side = np.sqrt(area_px) * scale
        size = np.round(side)
        k = int(size)
        inside = np.zeros((CELL_PX, CELL_PX), bool)
        s0 = (CELL_PX - k) // 2
        inside[s0:s0 + k, s0:s0 + k] = True
        levels = np.where(inside, 1, 0)
    step = round((hi - lo) * 1e8) * 1e-8  # nominal etch depth, rounded to 10 nm
    design = Design(height_m=-step * levels.astype(float), pitch_m=pitch_m, levels=levels.astype(np.int16),
                    metadata={"name": "afm lattice cell", "n_levels": 2, "mask_depths_m": [step],
                              "surround": "repeat"})
    path = design.save(tmp_path / "cell.npz")
    figures = {"period_x_px": px, "period_y_px": py, "turn_deg": turn, "step_m": hi - lo,
               "unetched_fraction": float(np.mean(feature if raised else ~feature)),
               "feature_px": size, "feature_from_file_px": (diameter if raised else side), "area_px": area_px}
    return path, figures


def _profile_widths(h, raised):
    """Mean width (px) of the whole features along the lattice's two axes, between the mid-height
    crossings of profiles through each feature's centroid: the edge position, independent of
    the corners' rounding that an area measure includes."""
    lo, hi = _two_modes(h)
    mid = 0.5 * (lo + hi)
    px, _, turn, _, feature = _lattice_from_features(h, raised)
    lab, _ = ndimage.label(feature)
    t = np.radians(turn)
    s = np.arange(-0.45 * px, 0.45 * px, 0.05)
    widths = []
    for i, sl in enumerate(ndimage.find_objects(lab)):
        if sl[0].start == 0 or sl[1].start == 0 or sl[0].stop == h.shape[0] or sl[1].stop == h.shape[1]:
            continue
        centre = np.array(ndimage.center_of_mass(lab == i + 1))
        for u in (np.array([-np.sin(t), np.cos(t)]), np.array([np.cos(t), np.sin(t)])):
            prof = ndimage.map_coordinates(h, centre[:, None] + u[:, None] * s[None, :], order=1)
            inside = prof > mid if raised else prof < mid
            k = s.size // 2
            right = k + int(np.argmin(inside[k:])) - 1
            left = k - int(np.argmin(inside[k::-1])) + 1
            if not inside[k] or right + 1 >= s.size or left < 1:
                continue

            def cross(a, b, prof=prof):
                return s[a] + (mid - prof[a]) / (prof[b] - prof[a]) * (s[b] - s[a])

            widths.append(cross(right, right + 1) - cross(left - 1, left))
    return float(np.mean(widths)), len(widths)


@pytest.mark.parametrize("name", sorted(SCANS))
def test_real_afm_lattice_and_step_fast(name, tmp_path):
    """The fast variant of the slow end-to-end tests below: the library stages `doe compare` runs
    first (levelling, the lattice's registration, the joint levelling with one offset per scan
    line, the level heights), without the edge and camera-frame fits."""
    from metrology.matching.depths import interior_mask, level_heights
    from metrology.matching.lattice import register_lattice
    from metrology.matching.level import level_joint, level_on_top, remove_spikes
    from metrology.matching.register import design_on_measurement

    raised = SCANS[name] == "raised discs"
    m = read_measurement(AFM / name)
    assert m.metadata["raster_scan"] is True
    path, ref = _design_for(m.height_m, m.pixel_size_m, raised, tmp_path)
    design = Design.load(path)
    h, _ = remove_spikes(m.height_m)
    reg, levels, printed, lattice = register_lattice(level_on_top(h).height_m, design.levels, design.height_m,
                                                     design.pitch_m, m.pixel_size_m)
    assert lattice.period_px[0] == pytest.approx(ref["period_x_px"], rel=0.005)
    assert lattice.period_px[1] == pytest.approx(ref["period_y_px"], rel=0.005)
    assert lattice.turn_deg == pytest.approx(ref["turn_deg"], abs=0.2)
    assert reg.match_ncc > 0.9
    labels = design_on_measurement(levels, reg)
    interior = interior_mask(labels, 1.0 / reg.decompose()["scale"])
    joint = level_joint(h, np.where(interior, labels, -1), line_offsets=True)
    stats = level_heights(joint.height_m, labels, interior, 2)
    assert stats.mean_m[0] == pytest.approx(0, abs=0.005 * ref["step_m"])  # levelled on the unetched top
    assert stats.mean_m[0] - stats.mean_m[1] == pytest.approx(ref["step_m"], rel=0.02)


@pytest.fixture(scope="module", params=sorted(SCANS))
def compared(request, tmp_path_factory):
    """`doe compare` of one real scan against the design the test writes; (name, report, figures)."""
    name = request.param
    tmp = tmp_path_factory.mktemp(name.split(".")[0])
    m = read_measurement(AFM / name)
    design, ref = _design_for(m.height_m, m.pixel_size_m, SCANS[name] == "raised discs", tmp)
    out = tmp / "out"
    # No --force: nothing is refused.
    assert main(["compare", str(AFM / name), "--design", str(design), "--out", str(out), "--no-psf",
                 "--no-render", "--x3p"]) == 0
    ref["design"] = Design.load(design)
    return name, json.loads((out / "report.json").read_text()), ref, out


@pytest.mark.slow
def test_real_afm_step_height_against_histogram_modes(compared):
    """The step height (camera-frame fit, level means, per-cell medians) agrees within 2 % with the
    two modes of the height histogram after the test's own levelling; its uncertainty is the
    standard error over the lattice's cells."""
    name, rep, ref, _ = compared
    step_nm = ref["step_m"] * 1e9
    depth = rep["etch_depths_nm"][0]
    cell = rep["lattice"]["depth_per_cell"]
    for value in (depth, rep["etch_depths_levels_nm"][0], cell["depth_nm"]):
        assert value == pytest.approx(step_nm, rel=0.02), name
    assert cell["cells"] >= 20 and 0 < cell["err_nm"] < 0.01 * step_nm
    assert rep["etch_depths_err_nm"][0] > 0
    # The camera-frame fit sees one window of a few cells: it lies within the scatter of one cell
    # about the field's mean (its formal error, a tenth of a nanometre, leaves that scatter out).
    assert abs(depth - cell["depth_nm"]) < 2 * cell["std_nm"]


@pytest.mark.slow
def test_real_afm_lattice_registered_turned_and_not_square(compared):
    """The turned lattice registers (modulo its period) with the test's centroid lattice's periods
    and turn; the x and y scales, 2.3-2.6 % apart on this scanner, are measured and not refused."""
    name, rep, ref, _ = compared
    lat = rep["lattice"]
    assert lat["period_px_xy"][0] == pytest.approx(ref["period_x_px"], rel=0.005), name
    assert lat["period_px_xy"][1] == pytest.approx(ref["period_y_px"], rel=0.005), name
    assert lat["turn_deg"] == pytest.approx(ref["turn_deg"], abs=0.2), name
    assert 3 < lat["turn_deg"] < 7
    match = rep["match"]
    assert match["confidence"] == "high" and not match["forced"] and match["problem"] is None
    assert match["pixel_aspect"] > 0.02 and match["pixel_aspect_judged"] is False
    sx, sy = rep["registration"]["pixel_size_xy_um"]
    # Against the design's lattice the file's 195.3 nm pixel is short along x, long along y.
    assert sx < 0.1953 < sy
    assert (sy - sx) / sx == pytest.approx(ref["period_x_px"] / ref["period_y_px"] - 1, abs=0.005)


@pytest.mark.slow
def test_real_afm_duty_cycle_and_edges(compared):
    """The duty cycle agrees within 2 % with the share of pixels above mid-height; the feature's
    size (the design's, rounded to whole design pixels, with the fitted edge shift) within 2 % of
    the mid-height crossings of the test's profiles (discs: the area's diameter)."""
    name, rep, ref, out = compared
    raised = SCANS[name] == "raised discs"
    duty = rep["duty_cycle"]
    assert duty["unetched_fraction"] == pytest.approx(ref["unetched_fraction"], rel=0.02), name
    if raised:
        assert duty["etched_fraction"] == pytest.approx(1 - ref["unetched_fraction"], rel=0.02)
    design = ref["design"]
    pitch_px = design.pitch_m / read_measurement(AFM / name).pixel_size_m  # file px per design px
    # Openings grow by the shift: a hole widens by twice it, a raised disc narrows by twice it.
    size_px = (ref["feature_px"] + (-2 if raised else 2) * duty["edge_shift_um"] * 1e-6 / design.pitch_m) * pitch_px
    h = _level_rows(read_measurement(AFM / name).height_m)
    independent = 2 * np.sqrt(ref["area_px"] / np.pi) if raised else _profile_widths(h, raised)[0]
    assert size_px == pytest.approx(independent, rel=0.02), name
    # The design was off by its rounding: the measured edge moved it toward the file's.
    assert abs(size_px - independent) < abs(ref["feature_px"] * pitch_px - independent) + 0.05


@pytest.mark.slow
def test_real_afm_levelled_on_unetched_surface_and_artefacts_named(compared):
    """levelled.x3p is flat and at 0 on the unetched surface (no tilt, no scan-line offsets left);
    the report names the tilt and the scan-line noise as the instrument's, near the test's own
    estimates (median steps along x, rows aligned by the median of their differences)."""
    from metrology.formats.x3p import read_x3p

    name, rep, ref, out = compared
    raised = SCANS[name] == "raised discs"
    levelled = read_x3p(out / "levelled.x3p").height_m
    lo, hi = _two_modes(levelled)
    top = levelled > 0.5 * (lo + hi)  # the unetched surface is the top: disc tops, the field around holes
    top = ndimage.binary_erosion(top, iterations=4) & np.isfinite(levelled)
    # At 0 within 1 % of the step (the disc tops are slightly domed: their eroded median is 3 nm up).
    assert abs(np.median(levelled[top])) < 0.01 * ref["step_m"], name
    rows, cols = np.nonzero(top)
    a = np.column_stack([np.ones(rows.size), cols - cols.mean(), rows - rows.mean()])
    coef, *_ = np.linalg.lstsq(a, levelled[top], rcond=None)
    assert np.all(np.abs(coef[1:]) * 255 < 5e-9)  # under 5 nm across the field
    art = rep["instrument_artefacts"]
    assert art["raster_scan"] is True and "instrument" in art["attributed_to"]
    assert "scan" in art["attributed_to"] and "tilt" in art["attributed_to"]
    # The scan lines' offsets (on these scans mostly the slow axis's z drift; the jumps between
    # neighbouring lines are about 1 nm) are gone: on the level covering most of the field (the
    # etched field around discs, the top around holes) the lines' medians scatter under half as much
    # as the raw scan's after a plane.
    raw = read_measurement(AFM / name).height_m
    raised = SCANS[name] == "raised discs"
    wide = levelled < 0.5 * (lo + hi) if raised else levelled > 0.5 * (lo + hi)
    wide = ndimage.binary_erosion(wide, iterations=4) & np.isfinite(levelled)
    rows, cols = np.nonzero(wide)
    a = np.column_stack([np.ones(rows.size), cols - cols.mean(), rows - rows.mean()])
    plane, *_ = np.linalg.lstsq(a, raw[wide], rcond=None)
    raw_flat = raw.copy()
    raw_flat[wide] -= a @ plane

    def line_scatter(h):
        med = [np.median(h[r][wide[r]]) for r in range(h.shape[0]) if wide[r].sum() > 30]
        return np.std(med)

    assert line_scatter(levelled) < line_scatter(raw_flat) / 2, name
    x_slope = np.median(np.diff(raw, axis=1))
    assert art["tilt_x_nm_per_px"] == pytest.approx(x_slope * 1e9, rel=0.15)
    d = np.median(np.diff(raw, axis=0), axis=1)
    drift = np.concatenate([[0.0], np.cumsum(d)])
    assert art["tilt_y_nm_per_px"] == pytest.approx(np.polyfit(np.arange(drift.size), drift, 1)[0] * 1e9, abs=0.15)
    assert 2 < art["scan_line_offsets_rms_nm"] < 20
    page = (out / "report.md").read_text()
    assert "scan-line offsets" in page and "Duty cycle" in page and "Lattice" in page
