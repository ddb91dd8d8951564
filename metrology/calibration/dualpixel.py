"""Dual-pixel raw frames to the two aperture views: splitting, crosstalk, demosaicing, white balance.

A dual-pixel sensor (Canon EOS 5D Mark IV in the seed) stores two raw frames per capture: the
sum of both photodiodes of every pixel and one photodiode alone (the "stored" view). The other
view is the difference. Each photodiode sees one half of the lens aperture, so with the DOE on
one half the two views are the coded and the uncoded image -- up to crosstalk: a fraction of
the light meant for one photodiode lands in the other. The fraction differs per Bayer colour
channel (the microlenses are slightly chromatic) and varies slowly across the sensor columns.

Crosstalk model, per pixel with colour channel ``ch`` and column ``col``::

    measured_stored = (1 - c_s) S + c_o O
    measured_other  = c_s S + (1 - c_o) O

with ``S, O`` the light meant for each photodiode and ``c_s = c_stored[ch, col]``,
``c_o = c_other[ch, col]`` the fractions each one leaks to the other. The sum is conserved.
Calibration uses two white-wall captures with one half of the aperture blocked: with only the
stored view lit, ``c_s`` is the other view's share of the total, and vice versa.

Arrays are row-major with row 0 at the top of the sensor, column 0 at the left; the Bayer
pattern string names the 2x2 cell starting at (row 0, column 0) in row-major order.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage
from scipy.interpolate import make_smoothing_spline

from doedesign.errors import DoeError
from doedesign.fileio import dumps_json, parse_json, write_npz

__all__ = ["CFA_PATTERNS", "CHANNELS", "CrosstalkCalibration", "MAX_NEGATIVE_FRACTION", "MIN_CLIPPED_PIXELS",
           "RAW_SUFFIXES", "VIEW_NAMES", "apply_channel_gains", "calibrate_crosstalk", "cfa_channels",
           "coded_view_name", "column_ratios", "compensate_crosstalk", "demosaic_bilinear",
           "grey_world_gains", "load_frame", "mosaic_channel_gains", "saturation_from_data",
           "smooth_columns", "split_views", "white_balance"]

log = logging.getLogger(__name__)

#: Colour channels of a 2 x 2 colour filter array cell, in the order results list them.
CHANNELS = ("R", "G1", "G2", "B")
CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
RAW_SUFFIXES = (".cr2", ".cr3", ".dng", ".nef", ".arw", ".raf", ".orf", ".rw2")
VIEW_NAMES = ("stored", "other")
# A capture is rejected as "stored view brighter than the sum" when more than this share of its
# unsaturated pixels has view > sum: read noise flips a few dark pixels, swapped frames flip most.
MAX_NEGATIVE_FRACTION = 0.05
# A data-derived saturation level needs at least this many pixels piled up at the frame maximum;
# clipping stacks many pixels on one value, a bright but unclipped peak does not.
MIN_CLIPPED_PIXELS = 4


# -- reading -----------------------------------------------------------------------------------
def load_frame(path: str | Path) -> np.ndarray:
    """Read one raw frame as a float64 2-D array (row 0 at the top).

    Parameters
    ----------
    path : str or Path
        ``.npy``, ``.tif``/``.tiff`` (one 2-D page), or a camera raw file (``.cr2``, ``.dng``, ...)
        read with rawpy (its visible raw mosaic; install rawpy to use this).

    Raises
    ------
    DoeError
        Missing file, unreadable content, not a single 2-D frame, or non-finite values.
    """
    from doedesign.fileio import check_input_file, load_npy

    path = check_input_file(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            data = load_npy(path)
        elif suffix in (".tif", ".tiff"):
            import tifffile

            data = tifffile.imread(path)
        elif suffix in RAW_SUFFIXES:
            data = _read_raw(path)
        else:
            raise DoeError(f"{path}: unknown frame format {suffix!r}; use .tif, .npy or a camera raw file")
    except DoeError:
        raise
    except Exception as exc:  # readers raise many types for a broken file; report it as one line
        raise DoeError(f"{path}: cannot read frame: {exc}") from None
    data = np.squeeze(np.asarray(data))
    if data.dtype.kind not in "biuf":
        raise DoeError(f"{path}: frame values must be numbers, got dtype {data.dtype}")
    if data.ndim != 2:
        raise DoeError(f"{path}: expected one 2-D raw frame, got an array of shape {data.shape}")
    data = data.astype(float)
    if not np.all(np.isfinite(data)):
        raise DoeError(f"{path}: frame holds {np.count_nonzero(~np.isfinite(data))} NaN or infinite values")
    return data


def _read_raw(path):
    try:
        import rawpy
    except ImportError:
        raise DoeError(f"{path}: reading camera raw files needs rawpy; install it (pip install rawpy) "
                       "or export the frames to TIFF") from None
    with rawpy.imread(str(path)) as raw:
        return np.array(raw.raw_image_visible, dtype=float)


# -- splitting -----------------------------------------------------------------------------------
def saturation_from_data(sum_frame: np.ndarray) -> float | None:
    """Saturation level of a frame read from the data, or None when nothing is clipped.

    Clipped pixels pile up on the frame maximum; when at least ``MIN_CLIPPED_PIXELS`` pixels
    share that maximum it is taken as the saturation level.
    """
    top = float(np.max(sum_frame))
    return top if np.count_nonzero(sum_frame >= top) >= MIN_CLIPPED_PIXELS else None


def split_views(sum_frame: np.ndarray, view_frame: np.ndarray, saturation: float | None = None,
                black_level: float = 0.0, name: str = "capture") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The two photodiode views from the stored frames.

    Parameters
    ----------
    sum_frame, view_frame : ndarray (rows, cols)
        Sum of both photodiodes and the stored single photodiode, same shape.
    saturation : float, optional
        Raw level (before black-level subtraction) at or above which a pixel of the sum frame
        is saturated. Default: read from the data (:func:`saturation_from_data`).
    black_level : float
        Offset present in each stored frame, subtracted from both before splitting.
    name : str
        Name of the capture for error messages (e.g. the file name).

    Returns
    -------
    stored, other : ndarray
        The stored view and ``sum - stored``. Saturated pixels carry half the sum in both views:
        the split is unknown there, so both views get the same value and still add up to the sum.
    saturated : ndarray of bool
    """
    s = np.asarray(sum_frame, dtype=float)
    v = np.asarray(view_frame, dtype=float)
    if s.shape != v.shape:
        raise DoeError(f"{name}: sum frame is {s.shape[0]} x {s.shape[1]} but the view frame is "
                       f"{v.shape[0]} x {v.shape[1]}; both frames of a capture must have the same size")
    if saturation is None:
        saturation = saturation_from_data(s)
    saturated = np.zeros(s.shape, bool) if saturation is None else s >= saturation
    s = s - black_level
    v = v - black_level
    brighter = (v > s) & ~saturated
    clear = max(int(np.count_nonzero(~saturated)), 1)
    if np.count_nonzero(brighter) > MAX_NEGATIVE_FRACTION * clear:
        raise DoeError(f"{name}: the stored view is brighter than the sum in {np.count_nonzero(brighter) / clear:.0%} "
                       "of the pixels; the frames are swapped or the black level is wrong")
    stored = np.where(saturated, s / 2, v)
    other = np.where(saturated, s / 2, s - v)
    return stored, other, saturated


# -- colour filter array -----------------------------------------------------------------------
def cfa_channels(shape: tuple[int, int], pattern: str = "RGGB", origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Index into :data:`CHANNELS` (R, G1, G2, B) of every pixel of a mosaic.

    ``pattern`` lists the colours of the 2x2 cell at the sensor's (0, 0) in row-major order;
    G1 is its first green, G2 its second. ``origin`` is the (row, col) of the array's first
    pixel on the full sensor, for crops.
    """
    pattern = str(pattern).upper()
    if pattern not in CFA_PATTERNS:
        raise DoeError(f"unknown CFA pattern {pattern!r}; use one of {', '.join(CFA_PATTERNS)}")
    cell = []
    greens = 0
    for letter in pattern:
        if letter == "G":
            greens += 1
            cell.append(CHANNELS.index(f"G{greens}"))
        else:
            cell.append(CHANNELS.index(letter))
    grid = np.array(cell).reshape(2, 2)
    rows = (np.arange(shape[0]) + origin[0]) % 2
    cols = (np.arange(shape[1]) + origin[1]) % 2
    return grid[rows[:, None], cols[None, :]]


# -- crosstalk -------------------------------------------------------------------------------------
@dataclass
class CrosstalkCalibration:
    """Per-channel, per-column crosstalk ratios of a dual-pixel sensor.

    Attributes
    ----------
    ratio : ndarray (2, 4, cols)
        ``ratio[0]``: share of the stored view's light leaking to the other view (``c_stored``);
        ``ratio[1]``: share of the other view's light leaking to the stored view (``c_other``);
        per channel R, G1, G2, B (axis 1) and sensor column (axis 2), smoothed.
    raw_ratio : ndarray (2, 4, cols)
        The column averages before smoothing (NaN in columns without that channel).
    cfa_pattern : str
    stored_view_half : {"left", "right"}
        The aperture half the stored photodiode sees (lit when the *other* half was blocked).
    metadata : dict
    """

    ratio: np.ndarray
    raw_ratio: np.ndarray
    cfa_pattern: str = "RGGB"
    stored_view_half: str = "right"
    metadata: dict = field(default_factory=dict)

    @property
    def width(self) -> int:
        return self.ratio.shape[-1]

    def summary(self) -> dict[str, dict[str, float]]:
        """Mean ratio per view and channel (over the columns holding that channel)."""
        out = {}
        for vi, view in enumerate(VIEW_NAMES):
            out[view] = {ch: float(np.nanmean(self.raw_ratio[vi, ci])) for ci, ch in enumerate(CHANNELS)}
        return out

    def save(self, path: str | Path) -> Path:
        """Write the calibration ``.npz`` (ratios + a JSON metadata string)."""
        meta = dict(self.metadata, cfa_pattern=self.cfa_pattern, stored_view_half=self.stored_view_half,
                    channels=list(CHANNELS), views=list(VIEW_NAMES),
                    layout="ratio[view, channel, column]; column 0 at the sensor's left edge")
        return write_npz(path, ratio=self.ratio, raw_ratio=self.raw_ratio, metadata=np.str_(dumps_json(meta, indent=None)))

    @classmethod
    def load(cls, path: str | Path) -> CrosstalkCalibration:
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as npz:
                ratio, raw, text = npz["ratio"], npz["raw_ratio"], str(npz["metadata"])
        except (OSError, ValueError, KeyError, EOFError) as exc:
            raise DoeError(f"{path}: not a crosstalk calibration file: {exc}") from None
        meta = parse_json(text, f"{path}: metadata")
        if not isinstance(meta, dict):
            raise DoeError(f"{path}: metadata must be a JSON object")
        if ratio.ndim != 3 or ratio.shape[:2] != (2, 4):
            raise DoeError(f"{path}: ratio must be (2 views, 4 channels, columns), got {ratio.shape}")
        return cls(ratio=ratio, raw_ratio=raw, cfa_pattern=meta.get("cfa_pattern", "RGGB"),
                   stored_view_half=meta.get("stored_view_half", "right"), metadata=meta)


def column_ratios(leak: np.ndarray, total: np.ndarray, channels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Leaked-to-total ratio per channel and column: sum of leak over sum of total down each column.

    The ratio of sums is the total-weighted mean of the per-pixel ratios, so dim pixels (whose
    ratio is mostly noise) count less. Returns (ratio (4, cols), weight (4, cols)), NaN and 0
    where a column holds no pixel of a channel.
    """
    ratio = np.full((4, leak.shape[1]), np.nan)
    weight = np.zeros((4, leak.shape[1]))
    for ci in range(4):
        mask = channels == ci
        tot = np.where(mask, total, 0.0).sum(axis=0)
        lk = np.where(mask, leak, 0.0).sum(axis=0)
        has = mask.any(axis=0) & (tot > 0)
        ratio[ci, has] = lk[has] / tot[has]
        weight[ci, has] = tot[has]
    return ratio, weight


def smooth_columns(ratio: np.ndarray, weight: np.ndarray, lam: float | None = None) -> np.ndarray:
    """Smoothing spline across columns of each channel's ratios, evaluated at every column.

    ``lam`` is the penalty of :func:`scipy.interpolate.make_smoothing_spline` (None: chosen by
    generalized cross-validation). Weights are the light totals (shot noise ~ 1 / total).
    """
    cols = np.arange(ratio.shape[-1], dtype=float)
    out = np.empty_like(ratio)
    for ci in range(ratio.shape[0]):
        ok = np.isfinite(ratio[ci]) & (weight[ci] > 0)
        if np.count_nonzero(ok) < 5:
            raise DoeError(f"crosstalk calibration: channel {CHANNELS[ci]} has only {np.count_nonzero(ok)} "
                           "lit columns; the white-wall captures are too small or dark")
        w = weight[ci, ok] / weight[ci, ok].mean()
        spline = make_smoothing_spline(cols[ok], ratio[ci, ok], w=w, lam=lam)
        out[ci] = spline(cols)
    return out


def calibrate_crosstalk(left_blocked: tuple[np.ndarray, np.ndarray], right_blocked: tuple[np.ndarray, np.ndarray],
                        pattern: str = "RGGB", lam: float | None = None, saturation: float | None = None,
                        black_level: float = 0.0,
                        names: tuple[str, str] = ("left-blocked capture", "right-blocked capture")) -> CrosstalkCalibration:
    """Crosstalk ratios from white-wall captures with the left, then the right aperture half blocked.

    Parameters
    ----------
    left_blocked, right_blocked : (sum_frame, view_frame)
        Raw frame pairs of each capture, same size.
    pattern : str
        Bayer pattern (:func:`cfa_channels`).
    lam : float, optional
        Spline smoothing penalty (None: generalized cross-validation).
    saturation, black_level : see :func:`split_views`. Saturated pixels are left out.

    Returns
    -------
    CrosstalkCalibration
    """
    shapes = {np.shape(f) for pair in (left_blocked, right_blocked) for f in pair}
    if len(shapes) != 1:
        raise DoeError(f"crosstalk calibration: {names[0]} and {names[1]} frames differ in size "
                       f"({sorted(shapes)}); all four frames must have the same size")
    lit = []
    ratios, weights = [], []
    for (s, v), name in zip((left_blocked, right_blocked), names):
        stored, other, sat = split_views(s, v, saturation, black_level, name)
        # The photodiode that receives the unblocked half is the brighter one.
        stored_lit = stored[~sat].sum() > other[~sat].sum()
        lit.append(0 if stored_lit else 1)
        leak = np.where(sat, 0.0, other if stored_lit else stored)
        total = np.where(sat, 0.0, stored + other)
        channels = cfa_channels(total.shape, pattern)
        r, w = column_ratios(leak, total, channels)
        ratios.append(r)
        weights.append(w)
    if lit[0] == lit[1]:
        raise DoeError(f"crosstalk calibration: the {VIEW_NAMES[lit[0]]} view is the brighter one in both "
                       f"{names[0]} and {names[1]}; one half of the aperture must be blocked in each")
    order = np.argsort(lit)  # capture lighting the stored view first
    raw = np.stack([ratios[i] for i in order])
    smooth = np.stack([smooth_columns(ratios[i], weights[i], lam) for i in order])
    if np.any(smooth.sum(axis=0) >= 0.9):
        raise DoeError("crosstalk calibration: leaked shares add up to 90 % or more in some columns; the two views "
                       "cannot be separated (were the aperture halves really blocked?)")
    # With the left half blocked only the right half is lit: that capture's lit view sees the right half.
    stored_half = "right" if lit[0] == 0 else "left"
    meta = {"lam": lam, "saturation": saturation, "black_level": black_level,
            "frame_shape": list(np.shape(left_blocked[0]))}
    log.info("crosstalk calibration: stored view sees the %s half; mean ratios %s", stored_half,
             np.nanmean(raw, axis=-1).round(4).tolist())
    return CrosstalkCalibration(ratio=smooth, raw_ratio=raw, cfa_pattern=pattern.upper(),
                                stored_view_half=stored_half, metadata=meta)


def compensate_crosstalk(stored: np.ndarray, other: np.ndarray, calibration: CrosstalkCalibration,
                         origin: tuple[int, int] = (0, 0), saturated: np.ndarray | None = None,
                         name: str = "capture") -> tuple[np.ndarray, np.ndarray]:
    """Undo the crosstalk: invert the 2x2 mixing of each pixel.

    Parameters
    ----------
    stored, other : ndarray (rows, cols)
        Views from :func:`split_views`.
    calibration : CrosstalkCalibration
    origin : (int, int)
        (row, col) of the frames' first pixel on the calibrated sensor, for crops.
    saturated : ndarray of bool, optional
        Pixels left as they are (their split is unknown).

    Returns
    -------
    stored, other : ndarray
        The light meant for each photodiode.
    """
    rows, cols = np.shape(stored)
    if origin[1] < 0 or origin[1] + cols > calibration.width:
        raise DoeError(f"{name}: frame columns {origin[1]}..{origin[1] + cols - 1} lie outside the "
                       f"{calibration.width} calibrated columns")
    channels = cfa_channels((rows, cols), calibration.cfa_pattern, origin)
    col_idx = np.arange(cols) + origin[1]
    c_s = calibration.ratio[0][channels, col_idx[None, :]]
    c_o = calibration.ratio[1][channels, col_idx[None, :]]
    det = 1.0 - c_s - c_o
    s = ((1.0 - c_o) * stored - c_o * other) / det
    o = ((1.0 - c_s) * other - c_s * stored) / det
    if saturated is not None:
        s = np.where(saturated, stored, s)
        o = np.where(saturated, other, o)
    return s, o


def coded_view_name(stored_view_half: str, doe_side: str) -> str:
    """'stored' or 'other': which photodiode view carries the DOE on ``doe_side`` of the aperture."""
    if doe_side not in ("left", "right"):
        raise DoeError(f"doe_side must be 'left' or 'right' for a split-aperture capture, got {doe_side!r}")
    return "stored" if stored_view_half == doe_side else "other"


# -- demosaicing and white balance -------------------------------------------------------------------
_BILINEAR = np.array([[0.25, 0.5, 0.25], [0.5, 1.0, 0.5], [0.25, 0.5, 0.25]])


def demosaic_bilinear(mosaic: np.ndarray, pattern: str = "RGGB", origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Bilinear demosaicing to (rows, cols, 3) RGB.

    Each colour plane is the normalized convolution of its samples with the bilinear tent
    (a missing value is the mean of its 2 or 4 nearest samples of that colour); at the border
    the same rule uses the samples that exist. Both greens form the G plane.
    """
    mosaic = np.asarray(mosaic, dtype=float)
    channels = cfa_channels(mosaic.shape, pattern, origin)
    out = np.empty(mosaic.shape + (3,))
    for k, members in enumerate(((0,), (1, 2), (3,))):
        mask = np.isin(channels, members).astype(float)
        num = ndimage.convolve(mosaic * mask, _BILINEAR, mode="constant")
        den = ndimage.convolve(mask, _BILINEAR, mode="constant")
        out[..., k] = np.where(mask > 0, mosaic, num / den)
    return out


def grey_world_gains(rgb_reference: np.ndarray) -> np.ndarray:
    """Per-channel gains making the reference's channel means equal (green gain 1)."""
    means = np.asarray(rgb_reference, dtype=float).reshape(-1, 3).mean(axis=0)
    if np.any(means <= 0):
        raise DoeError(f"grey-world white balance: a colour channel of the reference has mean {means.min():.3g} <= 0")
    return means[1] / means


def white_balance(coded_rgb: np.ndarray, uncoded_rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grey-world white balance from the uncoded view, applied to both views (seed section 4).

    Returns (coded, uncoded, gains).
    """
    gains = grey_world_gains(uncoded_rgb)
    return coded_rgb * gains, uncoded_rgb * gains, gains


def mosaic_channel_gains(mosaic: np.ndarray, pattern: str = "RGGB", origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Gains equalizing the four CFA channels' totals of a mosaic (grey world on the raw data).

    For a narrowband capture every channel sees the same irradiance times its response at that
    wavelength; dividing by the relative response (these gains) gives one full-resolution
    monochrome image.
    """
    mosaic = np.asarray(mosaic, dtype=float)
    channels = cfa_channels(mosaic.shape, pattern, origin)
    totals = np.array([mosaic[channels == c].mean() for c in range(4)])
    if np.any(totals <= 0):
        raise DoeError(f"channel gains: CFA channel {CHANNELS[int(np.argmin(totals))]} has no signal")
    return totals.mean() / totals


def apply_channel_gains(mosaic: np.ndarray, gains: ArrayLike, pattern: str = "RGGB",
                        origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Multiply each CFA channel of a mosaic by its gain."""
    mosaic = np.asarray(mosaic, dtype=float)
    return mosaic * np.asarray(gains)[cfa_channels(mosaic.shape, pattern, origin)]
