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
               "feature_px": size, "feature_from_file_px": (diameter if raised else side)}
    return path, figures


@pytest.mark.parametrize("name", sorted(SCANS))
def test_real_afm_scan_compared_end_to_end(name, tmp_path):
    raised = SCANS[name] == "raised discs"
    m = read_measurement(AFM / name)
    design, ref = _design_for(m.height_m, m.pixel_size_m, raised, tmp_path)
    out = tmp_path / "out"
    assert main(["compare", str(AFM / name), "--design", str(design), "--out", str(out), "--no-psf",
                 "--no-render"]) == 0
    rep = json.loads((out / "report.json").read_text())
    print(json.dumps({k: rep[k] for k in ("etch_depths_nm", "etch_depths_err_nm", "etch_depths_levels_nm",
                                          "registration", "match", "instrument_artefacts", "lattice",
                                          "duty_cycle", "linewidth_bias_um")}, indent=1))
    print(ref)
