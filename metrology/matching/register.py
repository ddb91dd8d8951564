"""Registration of a measured height map to the design it was made from.

The measured field shows part of the element, at an unknown lateral scale (the file's
pixel size is what is being checked), rotated by a small angle and possibly flipped or
transposed by the reader or the way the part sat under the objective.

Method (each step uses the fact that a DOE is a grid of square pixels):

1. Rotation modulo 90 deg: the step edges are Manhattan, so the gradient angles cluster
   at theta + k 90 deg; the energy-weighted mean of ``exp(4 i phi)`` gives theta.
2. Lattice: projected on the rotated axes u and v, the edge energy is a comb with the
   DOE pitch as period. Its periodogram peak gives the period in measurement pixels
   (the lateral scale, per axis) and its phase the sub-pixel position of the edges.
   Rotation and period are refined together by maximizing the comb's peak, whose
   height drops as soon as the edges across the field stop lining up.
3. Read-out: the measurement sampled at the centre of every DOE pixel of that lattice is
   a small image of design heights; normalized cross-correlation (FFT) against the design
   for each of the 8 flips / transposes gives the orientation and the integer offset.
4. Scale scan: a nominal pixel size (the file's, or ``--pixel-size-um``) is a starting value.
   When no lattice within ``scale_tolerance`` of it reads out a good match, the comb peaks of
   the whole band from 1/2 to 2 times it (:data:`SCALE_SEARCH_FACTOR`, widened by the
   tolerance) are tried, strongest first; the read-out's correlation with the design picks
   the pitch among them (the comb's harmonics and the sidebands of block designs read out
   the design badly), and only a good match (:data:`GOOD_MATCH_NCC`) moves the scale away
   from the starting one. The scan costs a few more lattice fits only when the narrow one failed.
   A failure then says whether the scale did not match (the strongest lattice lies outside
   the nominal band: its pixel size is given) or the pattern did not.

The result is an affine map from measurement pixel (row, col) to design pixel
(row, col), both with pixel centres at integer coordinates and row 0 at the top.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
import scipy.fft as sfft
from scipy import ndimage, optimize

from doedesign.errors import DoeError

__all__ = ["GOOD_MATCH_NCC", "MIN_MATCH_NCC", "ORIENTATIONS", "Registration", "SCALE_CANDIDATES",
           "SCALE_SEARCH_FACTOR", "WIDE_SCALE_CANDIDATES", "design_on_measurement", "orient", "register",
           "resample_to_design"]

log = logging.getLogger(__name__)

# Bin (measurement pixels) of the 1-D edge-energy projections; far below the ~5 px period.
_PROJ_BIN_PX = 0.05
# Edge pixels used for the lattice fit (strongest gradients first); plenty for 1e-4 scale.
_MAX_EDGE_POINTS = 600_000
# A correct read-out correlates with the design near 1; below this nothing matched.
MIN_MATCH_NCC = 0.5
#: A match this good ends the search over candidate lattice periods.
GOOD_MATCH_NCC = 0.9
# Comb peaks tried as the DOE pitch (the strongest first).
SCALE_CANDIDATES = 4
#: A nominal pixel size may be off by this factor either way: the scale scan's band.
SCALE_SEARCH_FACTOR = 2.0
# Comb peaks of that wider band tried (strongest first) once the narrow band found no good match.
WIDE_SCALE_CANDIDATES = 8
# Shortest lattice period (measurement pixels) the scan tries: below it a DOE pixel holds too
# few samples to read out.
_MIN_PERIOD_PX = 2.0

# An array orientation (transpose, flip_rows, flip_cols), applied in that order; all 8 of them.
Orientation = tuple[bool, bool, bool]
ORIENTATIONS = tuple((t, fr, fc) for t in (False, True) for fr in (False, True) for fc in (False, True))


def orient(array: np.ndarray, orientation: Orientation) -> np.ndarray:
    """Apply ``(transpose, flip_rows, flip_cols)`` to a 2-D array, in that order."""
    t, fr, fc = orientation
    out = array.T if t else array
    if fr:
        out = out[::-1]
    if fc:
        out = out[:, ::-1]
    return out


def _orientation_matrix(orientation):
    """Linear part of :func:`orient` on (row, col) index vectors."""
    t, fr, fc = orientation
    m = np.array([[0.0, 1.0], [1.0, 0.0]]) if t else np.eye(2)
    return np.diag([-1.0 if fr else 1.0, -1.0 if fc else 1.0]) @ m


@dataclass
class Registration:
    """Affine map from measurement pixels to design pixels.

    ``[R, C] = matrix @ [row, col] + offset``: measurement pixel centre (row, col) lies at
    design-pixel coordinates (R, C) (design pixel (i, j) centred at (i, j)).

    Attributes
    ----------
    matrix : ndarray (2, 2)
    offset : ndarray (2,)
    pitch_m : float
        Design pixel pitch.
    design_shape : (int, int)
    measurement_shape : (int, int)
    match_ncc : float
        Normalized cross-correlation of the read-out with the design (1 = identical).
    """

    matrix: np.ndarray
    offset: np.ndarray
    pitch_m: float
    design_shape: tuple[int, int]
    measurement_shape: tuple[int, int]
    match_ncc: float = float("nan")

    def to_design(self, rows: ArrayLike, cols: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Design coordinates (R, C) of measurement coordinates (rows, cols)."""
        rows, cols = np.asarray(rows, float), np.asarray(cols, float)
        m, t = self.matrix, self.offset
        return m[0, 0] * rows + m[0, 1] * cols + t[0], m[1, 0] * rows + m[1, 1] * cols + t[1]

    def to_measurement(self, r_design: ArrayLike, c_design: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Measurement coordinates (rows, cols) of design coordinates (R, C)."""
        inv = np.linalg.inv(self.matrix)
        dr = np.asarray(r_design, float) - self.offset[0]
        dc = np.asarray(c_design, float) - self.offset[1]
        return inv[0, 0] * dr + inv[0, 1] * dc, inv[1, 0] * dr + inv[1, 1] * dc

    def decompose(self) -> dict:
        """Orientation, rotation and per-axis scale.

        Returns
        -------
        dict
            ``orientation`` (transpose, flip_rows, flip_cols) that brings the measurement
            array to the design's orientation, ``rotation_deg`` (the remaining
            counter-clockwise rotation, y up, within +-45 deg), ``scale`` (design pixels
            per measurement pixel, mean of both axes) and ``scale_xy``.
        """
        for o in ORIENTATIONS:
            rest = self.matrix @ np.linalg.inv(_orientation_matrix(o))
            if np.linalg.det(rest) <= 0:
                continue
            # In (row, col) index space a counter-clockwise turn on screen (y up) is
            # [[cos, -sin], [sin, cos]] acting on (row, col).
            angle = np.arctan2(rest[1, 0] - rest[0, 1], rest[0, 0] + rest[1, 1])
            if abs(angle) <= np.pi / 4 + 1e-9:
                scale_xy = np.array([np.hypot(*rest[:, 1]), np.hypot(*rest[:, 0])])
                return {"orientation": o, "rotation_deg": float(np.degrees(angle)),
                        "scale": float(np.sqrt(abs(np.linalg.det(self.matrix)))),
                        "scale_xy": scale_xy}
        raise DoeError("registration matrix has no valid decomposition")  # unreachable for a similarity

    @classmethod
    def from_parameters(cls, scale: float, rotation_deg: float, orientation: Sequence[bool],
                        centre_design_rc: Sequence[float], pitch_m: float, design_shape: Sequence[int],
                        measurement_shape: Sequence[int]) -> Registration:
        """The map that orients, turns and scales the measurement onto the design.

        ``matrix = scale * rotation @ orientation``; the measurement's centre pixel lands at
        design coordinates ``centre_design_rc``. The inverse of :meth:`decompose`.
        """
        a = np.radians(rotation_deg)
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        matrix = float(scale) * rot @ _orientation_matrix(tuple(orientation))
        centre = np.array([(measurement_shape[0] - 1) / 2, (measurement_shape[1] - 1) / 2])
        offset = np.asarray(centre_design_rc, float) - matrix @ centre
        return cls(matrix, offset, float(pitch_m), (int(design_shape[0]), int(design_shape[1])),
                   (int(measurement_shape[0]), int(measurement_shape[1])))

    @property
    def pixel_size_m(self) -> float:
        """Effective measurement pixel size (m) implied by the DOE pitch."""
        return self.pitch_m * self.decompose()["scale"]

    def centre_offset_m(self) -> tuple[float, float]:
        """Position (x right, y up; m) of the measurement's centre from the design centre."""
        rc = (self.measurement_shape[0] - 1) / 2, (self.measurement_shape[1] - 1) / 2
        r, c = self.to_design(*rc)
        return (float((c - (self.design_shape[1] - 1) / 2) * self.pitch_m),
                float(-(r - (self.design_shape[0] - 1) / 2) * self.pitch_m))

    def to_dict(self) -> dict:
        """Plain JSON summary (units in the key names)."""
        d = self.decompose()
        x, y = self.centre_offset_m()
        t, fr, fc = d["orientation"]
        return {
            "scale": d["scale"],
            "scale_xy": [float(v) for v in d["scale_xy"]],
            "pixel_size_um": self.pitch_m * d["scale"] * 1e6,
            "pixel_size_xy_um": [float(v) * self.pitch_m * 1e6 for v in d["scale_xy"]],
            "rotation_deg": d["rotation_deg"],
            "shift_um": [x * 1e6, y * 1e6],
            "flip": bool(fr or fc),
            "transpose": bool(t),
            "flip_rows": bool(fr),
            "flip_cols": bool(fc),
            "match_ncc": float(self.match_ncc),
            "matrix": self.matrix.tolist(),
            "offset": self.offset.tolist(),
            "convention": ("[R, C] = matrix @ [row, col] + offset, measurement pixel (row, col) to "
                           "design pixel (R, C), pixel centres at integers, row 0 at the top; "
                           "shift_um = centre of the measured field from the design centre, x right, y up; "
                           "the measurement is transposed, then rows flipped, then columns flipped, "
                           "then turned rotation_deg counter-clockwise (y up) onto the design"),
        }


def _edge_points(height_m):
    """Coordinates, gradient components and weights of the strongest edge pixels."""
    h = np.asarray(height_m, float)
    valid = np.isfinite(h)
    if valid.sum() < 100:
        raise DoeError("registration: fewer than 100 valid pixels")
    filled = np.where(valid, h, np.median(h[valid]))
    gy = ndimage.sobel(filled, axis=0)
    gx = ndimage.sobel(filled, axis=1)
    # Gradients next to invalid pixels are artefacts of the filling.
    near_invalid = ndimage.binary_dilation(~valid, iterations=2)
    w = gx * gx + gy * gy
    w[near_invalid] = 0
    thresh = max(np.percentile(w, 99.5) * 0.02, np.finfo(float).tiny)
    sel = np.flatnonzero(w > thresh)
    if sel.size < 50:
        raise DoeError("registration: no step edges found in the measurement")
    if sel.size > _MAX_EDGE_POINTS:
        sel = sel[np.argsort(w.ravel()[sel])[-_MAX_EDGE_POINTS:]]
    rows, cols = np.unravel_index(sel, h.shape)
    return rows.astype(float), cols.astype(float), gy.ravel()[sel], gx.ravel()[sel], w.ravel()[sel]


class _Comb:
    """Periodogram of the edge energy projected on one rotated axis."""

    def __init__(self, coord, weight):
        self.lo = coord.min()
        idx = np.floor((coord - self.lo) / _PROJ_BIN_PX).astype(int)
        self.hist = np.bincount(idx, weight)
        self.pos = self.lo + (np.arange(self.hist.size) + 0.5) * _PROJ_BIN_PX
        self.extent = self.hist.size * _PROJ_BIN_PX

    def amplitude(self, f):
        return np.abs(np.dot(self.hist, np.exp(-2j * np.pi * f * self.pos)))

    def phase_position(self, f):
        """Position (px) of one comb tooth: the edges lie at this + k / f."""
        s = np.dot(self.hist, np.exp(-2j * np.pi * f * self.pos))
        return -np.angle(s) / (2 * np.pi * f)

    def candidates(self, f_lo, f_hi, count):
        """Up to ``count`` local maxima of the comb spectrum in [f_lo, f_hi], strongest first."""
        n = sfft.next_fast_len(4 * self.hist.size)
        spec = np.abs(sfft.rfft(self.hist, n))
        freqs = np.arange(spec.size) / (n * _PROJ_BIN_PX)
        band = np.flatnonzero((freqs >= f_lo) & (freqs <= f_hi))
        if band.size == 0:
            raise DoeError("registration: scale search range is empty")
        inner = band[(band > 0) & (band < spec.size - 1)]
        maxima = inner[(spec[inner] >= spec[inner - 1]) & (spec[inner] >= spec[inner + 1])]
        if maxima.size == 0:
            maxima = band[[np.argmax(spec[band])]]
        order = maxima[np.argsort(spec[maxima])[::-1]]
        picked = []
        for i in order:
            if all(abs(freqs[i] - f) > 2 / self.extent for f in picked):
                picked.append(freqs[i])
            if len(picked) == count:
                break
        return picked

    def peak(self, f_lo, f_hi):
        """Frequency (cycles per px) of the strongest peak in [f_lo, f_hi], refined."""
        n = sfft.next_fast_len(4 * self.hist.size)
        f0 = self.candidates(f_lo, f_hi, 1)[0]
        half = 1.0 / (n * _PROJ_BIN_PX)
        res = optimize.minimize_scalar(lambda f: -self.amplitude(f), bounds=(f0 - half, f0 + half),
                                       method="bounded", options={"xatol": 1e-9})
        return float(res.x), float(-res.fun)


def _lattice(rows, cols, gy, gx, w, f_range, theta0, f_start=None):
    """Rotation, periods and tooth positions of the edge lattice along u and v.

    ``f_start`` (cycles per px) restricts both combs to the peak nearest that frequency.
    """

    def combs(theta):
        c, s = np.cos(theta), np.sin(theta)
        u = cols * c + rows * s
        v = -cols * s + rows * c
        return _Comb(u, (gx * c + gy * s) ** 2), _Comb(v, (-gx * s + gy * c) ** 2)

    cu, cv = combs(theta0)
    if f_start is not None:
        f_range = (f_start - 2 / min(cu.extent, cv.extent), f_start + 2 / min(cu.extent, cv.extent))
    fu, _ = cu.peak(*f_range)
    fv, _ = cv.peak(*f_range)

    def score(theta):
        a, b = combs(theta)
        best = 0.0
        for comb, f in ((a, fu), (b, fv)):
            width = 1.0 / comb.extent
            r = optimize.minimize_scalar(lambda q: -comb.amplitude(q), bounds=(f - width, f + width),
                                         method="bounded", options={"xatol": 1e-9})
            best += -r.fun
        return -best

    # The comb fades once edges across the field drift by a period: search well inside that.
    extent = max(cu.extent, cv.extent)
    span = min(np.radians(1.0), 2.0 / (fu * extent))
    res = optimize.minimize_scalar(score, bounds=(theta0 - span, theta0 + span), method="bounded",
                                   options={"xatol": 1e-7})
    theta = float(res.x)
    cu, cv = combs(theta)
    fu, _ = cu.peak(fu - 2 / cu.extent, fu + 2 / cu.extent)
    fv, _ = cv.peak(fv - 2 / cv.extent, fv + 2 / cv.extent)
    return theta, (fu, cu.phase_position(fu)), (fv, cv.phase_position(fv))


def _normalized_xcorr(image, template, valid):
    """NCC of ``template`` (with validity mask) at every offset inside ``image`` (FFT based).

    Returns an array (H - h + 1, W - w + 1); entry (i, j) compares image[i:i+h, j:j+w].
    """
    H, W = image.shape
    h, w = template.shape
    m = valid.astype(float)
    n = m.sum()
    t = np.where(valid, template - template[valid].mean(), 0.0)
    t_norm = np.sqrt(np.sum(t * t))
    shape = (sfft.next_fast_len(H + h - 1), sfft.next_fast_len(W + w - 1))
    f_img = sfft.rfft2(image, shape)
    f_img2 = sfft.rfft2(image * image, shape)

    def corr(f_a, b):
        # Cross-correlation sum_k a[i + k] b[k] via the flipped kernel.
        full = sfft.irfft2(f_a * sfft.rfft2(b[::-1, ::-1], shape), shape)
        return full[h - 1:H, w - 1:W]

    num = corr(f_img, t)
    s1 = corr(f_img, m)
    s2 = corr(f_img2, m)
    var = np.maximum(s2 - s1 * s1 / n, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        ncc = num / (np.sqrt(var) * t_norm)
    ncc[~np.isfinite(ncc) | (var < 1e-6 * var.max())] = -1.0
    return ncc


def register(height_m: np.ndarray, design_height_m: np.ndarray, pitch_m: float, pixel_size_m: float | None = None,
             scale_tolerance: float = 0.15, scale_search: float = SCALE_SEARCH_FACTOR) -> Registration:
    """Find the affine map from the measurement's pixels to the design's pixels.

    Parameters
    ----------
    height_m : ndarray
        Measured heights (m), levelled or not (only edges and relative heights matter);
        NaN where invalid. Row 0 at the top (camera order).
    design_height_m : ndarray
        Design heights (m), row 0 at the top.
    pitch_m : float
        Design pixel pitch (m).
    pixel_size_m : float, optional
        Nominal measurement pixel size (from the file): a starting value. The period search
        starts within ``scale_tolerance`` of it, then scans ``1 / scale_search`` to
        ``scale_search`` times it; without it any period of 2.2 to 40 px is tried.
    scale_tolerance : float
        Relative range of the first period search around the nominal pixel size. Keep it
        below 0.25: a design made of n-pixel blocks also has comb peaks at (n +- 1) / n of
        the pitch frequency; the wider scan tells them apart by the read-out's match only.
    scale_search : float
        Factor either way of the nominal pixel size the scale scan covers (1: no scan).

    Returns
    -------
    Registration

    Raises
    ------
    DoeError
        No edges, no lattice, or no orientation whose read-out matches the design; where the
        strongest lattice lies outside the nominal band, the message says that the scale did
        not match and gives the pixel size the lattice measures.
    """
    h = np.asarray(height_m, float)
    design = np.asarray(design_height_m, float)
    rows, cols, gy, gx, w = _edge_points(h)
    theta0 = float(np.angle(np.sum(w * np.exp(4j * np.arctan2(gy, gx)))) / 4)
    c0, s0 = np.cos(theta0), np.sin(theta0)
    comb = _Comb(cols * c0 + rows * s0, (gx * c0 + gy * s0) ** 2)
    tried: list[float] = []

    def search(f_range, count):
        # A design built of zones also has comb sidebands near the pitch: try the strongest
        # peaks and keep the lattice whose read-out matches the design best.
        best = (-np.inf, None, None)
        for f_start in comb.candidates(*f_range, count):
            if any(abs(f_start - f) <= 2 / comb.extent for f in tried):
                continue
            tried.append(f_start)
            lattice = _lattice(rows, cols, gy, gx, w, f_range, theta0, f_start)
            found = _match(h, design, pitch_m, *lattice)
            if best[1] is None or found[0] > best[0]:
                best = found
            if best[0] >= GOOD_MATCH_NCC:
                break
        return best

    if not pixel_size_m:
        best = search((1 / 40, 1 / 2.2), SCALE_CANDIDATES)
        score, reg, period_px = best
        if reg is None:
            raise DoeError(f"registration: the measured pattern does not match the design anywhere: the field "
                           f"shows another design or a region outside this one (best normalized correlation "
                           f"{score:.2f}, need {MIN_MATCH_NCC}; lattice period {period_px:.3f} px)")
        return reg
    f_nom = pixel_size_m / pitch_m
    narrow = (f_nom * (1 - scale_tolerance), f_nom * (1 + scale_tolerance))
    wide = (f_nom / (scale_search * (1 + scale_tolerance)),
            min(f_nom * scale_search * (1 + scale_tolerance), 1 / _MIN_PERIOD_PX))
    scan = scale_search > 1 and wide[0] < wide[1]
    best = search(narrow, SCALE_CANDIDATES)
    if best[0] < GOOD_MATCH_NCC and scan:
        # A scale away from the starting one needs a good match: a poor one there is a
        # sideband's or another design's chance correlation.
        found = search(wide, WIDE_SCALE_CANDIDATES)
        if found[0] >= GOOD_MATCH_NCC:
            best = found
    score, reg, period_px = best
    if reg is not None:
        ratio = reg.pixel_size_m / pixel_size_m
        if abs(ratio - 1) > scale_tolerance:
            log.warning("registration: the measured pixel size is %.4g um, %.3gx the starting %.4g um",
                        reg.pixel_size_m * 1e6, ratio, pixel_size_m * 1e6)
        return reg
    # The strongest lattice of the scale band: the pixel size the field itself shows.
    f_peak = comb.candidates(*wide, 1)[0] if scan else 1 / period_px
    measured_m = f_peak * pitch_m
    if abs(measured_m / pixel_size_m - 1) > scale_tolerance:
        raise DoeError(f"registration: the scale did not match: the field's edge lattice measures a pixel size "
                       f"of {measured_m * 1e6:.4g} um (a period of {1 / f_peak:.3f} px of the "
                       f"{pitch_m * 1e6:.4g} um DOE pitch), {measured_m / pixel_size_m:.3g}x the starting "
                       f"{pixel_size_m * 1e6:.4g} um, and at no scale from {1 / scale_search:.2g}x to "
                       f"{scale_search:.2g}x the starting one does the read-out match the design (best "
                       f"normalized correlation {score:.2f}, need {MIN_MATCH_NCC}): give the right pixel size, "
                       f"or the field shows another design")
    raise DoeError(f"registration: the measured pattern does not match the design anywhere: the field shows "
                   f"another design or a region outside this one (best normalized correlation {score:.2f}, "
                   f"need {MIN_MATCH_NCC}; lattice period {1 / f_peak:.3f} px, a pixel size of "
                   f"{measured_m * 1e6:.4g} um, within {scale_tolerance:.0%} of the starting one; scales from "
                   f"{1 / scale_search:.2g}x to {scale_search:.2g}x it were tried)")


def _match(h, design, pitch_m, theta, u_lattice, v_lattice):
    """Read the measurement at every DOE-pixel centre of a lattice and match it to the design.

    Returns (score, Registration or None when the score is too low, lattice period in px).
    """
    (fu, u0), (fv, v0) = u_lattice, v_lattice
    log.info("lattice: rotation %.4f deg, period %.4f x %.4f px", np.degrees(theta), 1 / fu, 1 / fv)

    # Read the design heights at the centre of every DOE pixel inside the field.
    c, s = np.cos(theta), np.sin(theta)
    corners_r = np.array([0, 0, h.shape[0] - 1, h.shape[0] - 1], float)
    corners_c = np.array([0, h.shape[1] - 1, 0, h.shape[1] - 1], float)
    cu = corners_c * c + corners_r * s
    cv = -corners_c * s + corners_r * c
    kb = np.arange(np.floor((cu.min() - u0) * fu), np.ceil((cu.max() - u0) * fu))
    ka = np.arange(np.floor((cv.min() - v0) * fv), np.ceil((cv.max() - v0) * fv))
    uu = u0 + (kb + 0.5) / fu
    vv = v0 + (ka + 0.5) / fv
    pr = uu[None, :] * s + vv[:, None] * c
    pc = uu[None, :] * c - vv[:, None] * s
    valid = np.isfinite(h)
    # Average over the central part of each DOE pixel: less noise, edges barely touched.
    sigma = 0.12 / max(fu, fv)
    smooth = ndimage.gaussian_filter(np.where(valid, h, 0.0), sigma)
    weight = ndimage.gaussian_filter(valid.astype(float), sigma)
    inside = (pr >= 0) & (pr <= h.shape[0] - 1) & (pc >= 0) & (pc <= h.shape[1] - 1)
    num = ndimage.map_coordinates(smooth, [pr, pc], order=1, mode="nearest")
    den = ndimage.map_coordinates(weight, [pr, pc], order=1, mode="nearest")
    readout_valid = inside & (den > 0.99)
    readout = np.where(readout_valid, num / np.maximum(den, 1e-12), 0.0)
    if readout_valid.sum() < 16:
        return -np.inf, None, 1 / fu
    # Crop to the rows/cols that hold data.
    keep_r = np.flatnonzero(readout_valid.any(axis=1))
    keep_c = np.flatnonzero(readout_valid.any(axis=0))
    readout = readout[keep_r[0]:keep_r[-1] + 1, keep_c[0]:keep_c[-1] + 1]
    readout_valid = readout_valid[keep_r[0]:keep_r[-1] + 1, keep_c[0]:keep_c[-1] + 1]
    ka, kb = ka[keep_r[0]:keep_r[-1] + 1], kb[keep_c[0]:keep_c[-1] + 1]

    # Outside the design the wafer is unetched: pad with zeros so a field that runs off
    # the element still matches.
    pad = max(readout.shape)
    padded = np.pad(design, pad)
    best = (-np.inf, None, None)
    for o in ORIENTATIONS:
        tmpl, tval = orient(readout, o), orient(readout_valid, o)
        if tmpl.shape[0] > padded.shape[0] or tmpl.shape[1] > padded.shape[1]:
            continue
        ncc = _normalized_xcorr(padded, tmpl, tval)
        idx = np.unravel_index(np.argmax(ncc), ncc.shape)
        if ncc[idx] > best[0]:
            best = (float(ncc[idx]), o, idx)
    score, o, (i0, j0) = best
    log.info("registration: orientation %s, offset (%d, %d), NCC %.3f", o, i0 - pad, j0 - pad, score)
    if not score >= MIN_MATCH_NCC:
        return score, None, 1 / fu

    # Three read-out pixels give the exact affine map: read-out index (a, b) sits at the
    # measurement point (pr, pc) and, after orientation o, at design (a' + i0, b' + j0).
    ia = orient(np.broadcast_to(np.arange(readout.shape[0])[:, None], readout.shape), o)
    ib = orient(np.broadcast_to(np.arange(readout.shape[1])[None, :], readout.shape), o)
    src, dst = [], []
    for ap, bp in ((0, 0), (1, 0), (0, 1)):
        a, b = ia[ap, bp], ib[ap, bp]
        u = u0 + (kb[b] + 0.5) / fu
        v = v0 + (ka[a] + 0.5) / fv
        src.append([u * s + v * c, u * c - v * s, 1.0])
        dst.append([ap + i0 - pad, bp + j0 - pad])
    sol = np.linalg.solve(np.array(src), np.array(dst, float))
    return score, Registration(matrix=sol[:2].T.copy(), offset=sol[2].copy(), pitch_m=float(pitch_m),
                               design_shape=tuple(design.shape), measurement_shape=tuple(h.shape),
                               match_ncc=score), 1 / fu


def resample_to_design(height_m: np.ndarray, registration: Registration, upsample: int = 1,
                       region: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Measured heights on the design grid (or a finer grid aligned with it).

    Parameters
    ----------
    height_m : ndarray
        Measurement (NaN where invalid).
    registration : Registration
    upsample : int
        Samples per design pixel per axis; sample (a, b) is centred at design coordinates
        ``(row0 + (a + 0.5) / upsample - 0.5, col0 + (b + 0.5) / upsample - 0.5)``, the
        same fine grid as :func:`masks.process.simulate_surface`.
    region : (row0, row1, col0, col1), optional
        Half-open design-pixel window; default the whole design.

    Returns
    -------
    ndarray
        Bilinear samples; NaN outside the measured field or next to invalid pixels.
    """
    h = np.asarray(height_m, float)
    row0, row1, col0, col1 = region if region is not None else (0, registration.design_shape[0], 0,
                                                                registration.design_shape[1])
    u = int(upsample)
    rr = row0 + (np.arange((row1 - row0) * u) + 0.5) / u - 0.5
    cc = col0 + (np.arange((col1 - col0) * u) + 0.5) / u - 0.5
    mr, mc = registration.to_measurement(rr[:, None], cc[None, :])
    valid = np.isfinite(h)
    vals = ndimage.map_coordinates(np.where(valid, h, 0.0), [mr, mc], order=1, mode="constant", cval=0.0)
    ok = ndimage.map_coordinates(valid.astype(float), [mr, mc], order=1, mode="constant", cval=0.0)
    inside = (mr >= 0) & (mr <= h.shape[0] - 1) & (mc >= 0) & (mc <= h.shape[1] - 1)
    return np.where(inside & (ok > 0.999), vals, np.nan)


def design_on_measurement(values: np.ndarray, registration: Registration,
                          measurement_shape: tuple[int, int] | None = None, fill: float = -1) -> np.ndarray:
    """Design-pixel values (e.g. levels) at each measurement pixel, nearest design pixel.

    Returns an array shaped like the measurement; ``fill`` where the pixel maps outside
    the design.
    """
    shape = measurement_shape or registration.measurement_shape
    r, c = registration.to_design(np.arange(shape[0])[:, None], np.arange(shape[1])[None, :])
    ri, ci = np.rint(r).astype(int), np.rint(c).astype(int)
    values = np.asarray(values)
    inside = (ri >= 0) & (ri < values.shape[0]) & (ci >= 0) & (ci < values.shape[1])
    out = np.full(shape, fill, dtype=np.result_type(values.dtype, np.min_scalar_type(fill)))
    out[inside] = values[ri[inside], ci[inside]]
    return out
