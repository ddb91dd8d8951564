"""The colour-sorting Bayer study of the seed supplement (section 2, Table 1, Fig. 2).

Image formation per method: each colour channel of a natural image (values 0-1, row 0 at
the top) is convolved with that channel's PSF, sampled by an RGGB mosaic with 0/1
transmittance (R at even row / even column, G at (even, odd) and (odd, even), B at
(odd, odd)), Gaussian noise of sigma 1/255 is added (sigma = 1 on a 0-255 scale), and the
mosaic is clipped to [0, 1] like a sensor. Reconstruction:

- ``nearest``: each 2 x 2 cell's R (its (0, 0) pixel), G (its (1, 0) pixel) and B (its
  (1, 1) pixel) are given to all four pixels of the cell. With the proposed PSF (R to the
  axis pixel, G one row down, B one row down and one column right) these three samples come
  from the SAME scene point -- the cell's top-left pixel -- which is why chroma improves.
- ``bilinear``: the standard bilinear demosaicing (normalized convolution of each channel's
  samples), used for the ideal-PSF baseline.

Scores: PSNR in RGB (peak 1) and in CIE L, U, V (:func:`skimage.color.rgb2luv`, D65) with
peaks equal to each channel's extent over the sRGB gamut (L: 100, U: about 259, V: about
242); a common peak per channel, so differences in dB do not depend on this choice. PSF
light is not renormalized: a DOE channel that puts a fraction e of its light in the window
records e times the signal plus the same noise, and the reconstruction divides by e (a gain),
so lost light shows up as noise, as it would in a camera.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage, signal

from .errors import DoeError

__all__ = ["IMAGES", "Method", "NOISE_SIGMA", "PAPER_TABLE1", "TARGET_OFFSETS", "apply_psf",
           "bilinear_demosaic", "delta_kernels", "evaluate", "figure", "load_images", "mosaic",
           "nearest_neighbour", "psf_kernels", "psnr_scores", "rggb_masks", "standard_methods"]

log = logging.getLogger(__name__)

# Natural colour images shipped inside scikit-image (load offline).
IMAGES = ("astronaut", "coffee", "chelsea", "rocket")
NOISE_SIGMA = 1.0 / 255.0
PAPER_TABLE1 = {
    "ideal_demosaic": {"rgb_db": 28.9, "l_db": 35.5, "u_db": 37.6, "v_db": 35.7},
    "ideal_nearest": {"rgb_db": 28.9, "l_db": 35.5, "u_db": 37.7, "v_db": 35.7},
    "proposed_target": {"rgb_db": 28.9, "l_db": 35.4, "u_db": 39.5, "v_db": 35.7 + 2.1},
}
# Offsets (rows, cols) from the axis of the Bayer target's R, G, B spots (supplement Eq. 1).
TARGET_OFFSETS = ((0, 0), (1, 0), (1, 1))
# PSNR (dB) per colour space channel: "rgb_db", "l_db", "u_db", "v_db".
_Scores = dict[str, float]


def load_images(names: Sequence[str] = IMAGES, crop: int | None = None) -> dict[str, np.ndarray]:
    """Natural colour test images from :mod:`skimage.data` as float arrays in [0, 1].

    ``crop`` (int) keeps a centred ``crop x crop`` region for speed; sizes are cut to even
    numbers so the mosaic holds whole 2 x 2 cells.
    """
    import skimage.data

    out = {}
    for name in names:
        try:
            img = getattr(skimage.data, name)()
        except (AttributeError, OSError, ValueError) as exc:
            raise DoeError(f"test image {name!r} is not available offline in skimage.data: {exc}") from None
        img = np.asarray(img[..., :3], dtype=float) / 255.0
        if crop:
            c = int(crop) // 2 * 2
            r0 = (img.shape[0] - c) // 4 * 2
            c0 = (img.shape[1] - c) // 4 * 2
            img = img[max(r0, 0):max(r0, 0) + c, max(c0, 0):max(c0, 0) + c]
        # Whole 2 x 2 Bayer cells only.
        out[name] = img[:img.shape[0] // 2 * 2, :img.shape[1] // 2 * 2]
    return out


def delta_kernels(offsets: Sequence[tuple[int, int]]) -> np.ndarray:
    """One small kernel per channel with all its light on ``offsets[c]`` = (drow, dcol) from the centre."""
    m = max(max(abs(r), abs(c)) for r, c in offsets)
    size = 2 * m + 1
    k = np.zeros((len(offsets), size, size))
    for ch, (r, c) in enumerate(offsets):
        k[ch, m + r, m + c] = 1.0
    return k


def psf_kernels(psf: ArrayLike, axis_pixel: tuple[int, int], radius_px: int | None = None) -> np.ndarray:
    """Per-channel convolution kernels (3, 2r+1, 2r+1) centred on the axis from PSFs (3, rows, cols).

    ``radius_px`` (default: as far as the window reaches on every side) crops the PSF; the
    light outside is lost, as it would be outside a camera's field.
    """
    psf = np.asarray(psf, dtype=float)
    r0, c0 = axis_pixel
    rows, cols = psf.shape[-2:]
    reach = min(r0, c0, rows - 1 - r0, cols - 1 - c0)
    r = reach if radius_px is None else min(int(radius_px), reach)
    return psf[:, r0 - r:r0 + r + 1, c0 - r:c0 + r + 1].copy()


def apply_psf(img: np.ndarray, kernels: np.ndarray) -> np.ndarray:
    """Sensor image per channel: the scene convolved with its kernel (light outside the frame is dark)."""
    out = np.empty_like(img)
    for ch in range(3):
        k = kernels[ch]
        if np.count_nonzero(k) == 1:
            # A shifted delta: an exact shift, no FFT round-off.
            (i, j), = np.argwhere(k)
            out[..., ch] = ndimage.shift(img[..., ch], (i - k.shape[0] // 2, j - k.shape[1] // 2), order=0,
                                         mode="constant", cval=0.0) * k[i, j]
        else:
            out[..., ch] = signal.fftconvolve(img[..., ch], k, mode="same")
    return out


def rggb_masks(shape: tuple[int, int]) -> np.ndarray:
    """Boolean (3, rows, cols) masks of the R, G and B sites of an RGGB mosaic."""
    rr, cc = np.meshgrid(np.arange(shape[0]) % 2, np.arange(shape[1]) % 2, indexing="ij")
    return np.stack([(rr == 0) & (cc == 0), rr != cc, (rr == 1) & (cc == 1)])


def mosaic(sensor_rgb: np.ndarray, rng: np.random.Generator, sigma: float = NOISE_SIGMA) -> np.ndarray:
    """RGGB samples with 0/1 transmittance, Gaussian noise and clipping to [0, 1]."""
    masks = rggb_masks(sensor_rgb.shape[:2])
    raw = np.sum(np.moveaxis(sensor_rgb, -1, 0) * masks, axis=0)
    return np.clip(raw + rng.normal(0.0, sigma, raw.shape), 0.0, 1.0)


def nearest_neighbour(raw: np.ndarray) -> np.ndarray:
    """Cell-wise reconstruction: R from (0, 0), G from (1, 0), B from (1, 1) of each 2 x 2 cell."""
    rows, cols = raw.shape
    if rows % 2 or cols % 2:
        raise DoeError(f"mosaic of {rows} x {cols} pixels: nearest-neighbour needs even sizes")
    cells = [raw[0::2, 0::2], raw[1::2, 0::2], raw[1::2, 1::2]]
    return np.stack([np.repeat(np.repeat(c, 2, axis=0), 2, axis=1) for c in cells], axis=-1)


def bilinear_demosaic(raw: np.ndarray) -> np.ndarray:
    """Standard bilinear demosaicing: normalized convolution of each channel's samples."""
    masks = rggb_masks(raw.shape)
    kern_rb = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], float) / 4
    kern_g = np.array([[0, 1, 0], [1, 4, 1], [0, 1, 0]], float) / 4
    out = np.empty(raw.shape + (3,))
    for ch, k in enumerate((kern_rb, kern_g, kern_rb)):
        num = ndimage.convolve(raw * masks[ch], k, mode="mirror")
        den = ndimage.convolve(masks[ch].astype(float), k, mode="mirror")
        out[..., ch] = num / den
    return out


def _luv_peaks():
    """Extent of L, U and V over the sRGB gamut (sampled finely on the cube's surface)."""
    from skimage.color import rgb2luv

    t = np.linspace(0, 1, 33)
    a, b = np.meshgrid(t, t, indexing="ij")
    faces = []
    for fixed in (0.0, 1.0):
        f = np.full_like(a, fixed)
        faces += [np.stack([f, a, b], -1), np.stack([a, f, b], -1), np.stack([a, b, f], -1)]
    luv = rgb2luv(np.concatenate(faces, axis=0))
    return luv.reshape(-1, 3).max(axis=0) - luv.reshape(-1, 3).min(axis=0)


def psnr_scores(reference: np.ndarray, estimate: np.ndarray, margin: int = 4) -> _Scores:
    """PSNR (dB) in RGB and per LUV channel on the interior (``margin`` px dropped at each edge)."""
    from skimage.color import rgb2luv

    sl = (slice(margin, -margin or None), slice(margin, -margin or None))
    ref, est = reference[sl], np.clip(estimate[sl], 0.0, 1.0)

    def psnr(a, b, peak):
        mse = np.mean((a - b) ** 2)
        return float(10 * np.log10(peak ** 2 / mse)) if mse > 0 else float("inf")

    luv_ref, luv_est = rgb2luv(ref), rgb2luv(est)
    peaks = _luv_peaks()
    return {"rgb_db": psnr(ref, est, 1.0),
            **{f"{c}_db": psnr(luv_ref[..., i], luv_est[..., i], peaks[i]) for i, c in enumerate("luv")}}


@dataclass
class Method:
    """One row of the table: per-channel kernels, their light fraction, and the reconstruction."""

    name: str
    kernels: np.ndarray
    reconstruct: str = "nearest"

    def simulate(self, img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The reconstructed image (rows, cols, 3) of ``img`` seen through this method."""
        gain = self.kernels.sum(axis=(-2, -1))
        if np.any(gain <= 0):
            raise DoeError(f"{self.name}: a channel's PSF holds no light")
        raw = mosaic(apply_psf(img, self.kernels), rng)
        rec = nearest_neighbour(raw) if self.reconstruct == "nearest" else bilinear_demosaic(raw)
        # Undo the channel's light loss (white balance); noise is amplified with it.
        return rec / gain


def standard_methods(doe_psf: np.ndarray | None = None, axis_pixel: tuple[int, int] = (256, 256),
                     rggb: bool = False) -> list[Method]:
    """The rows of Table 1; ``doe_psf`` (3, rows, cols) R, G, B adds ``proposed_doe``."""
    ideal = delta_kernels(((0, 0),) * 3)
    target = delta_kernels(TARGET_OFFSETS)
    methods = [Method("ideal_demosaic", ideal, "bilinear"), Method("ideal_nearest", ideal),
               Method("proposed_target", target)]
    if doe_psf is not None:
        methods.append(Method("proposed_doe", psf_kernels(doe_psf, axis_pixel)))
    return methods


def evaluate(images: dict[str, np.ndarray], methods: Sequence[Method], seed: int = 0
             ) -> tuple[dict[str, _Scores], dict[str, dict[str, _Scores]], dict[str, dict[str, np.ndarray]]]:
    """Mean PSNR per method over the images (each image with its own noise draw, seeded).

    Returns
    -------
    table : dict  method -> {"rgb_db", "l_db", "u_db", "v_db"} (means over images)
    per_image : dict  method -> image -> scores
    reconstructions : dict  method -> image -> reconstructed array (for figures)
    """
    per_image, recs = {}, {}
    for m in methods:
        per_image[m.name], recs[m.name] = {}, {}
        for i, (name, img) in enumerate(images.items()):
            rng = np.random.default_rng([seed, i])
            rec = m.simulate(img, rng)
            recs[m.name][name] = rec
            per_image[m.name][name] = psnr_scores(img, rec)
    table = {m: {k: float(np.mean([s[k] for s in scores.values()])) for k in ("rgb_db", "l_db", "u_db", "v_db")}
             for m, scores in per_image.items()}
    return table, per_image, recs


def figure(images: dict[str, np.ndarray], recs: dict[str, dict[str, np.ndarray]], path: str | Path,
           image_name: str | None = None) -> Path:
    """Fig. 2-like panel: reconstructions (top) and mean |dU|+|dV| error maps (bottom)."""
    import matplotlib.pyplot as plt
    from skimage.color import rgb2luv

    from .fileio import save_figure

    name = image_name or next(iter(images))
    ref = images[name]
    methods = [m for m in ("ideal_nearest", "proposed_target", "proposed_doe") if m in recs]
    fig, axes = plt.subplots(2, len(methods) + 1, figsize=(3.2 * (len(methods) + 1), 6.4))
    axes[0, 0].imshow(ref)
    axes[0, 0].set_title("scene")
    axes[1, 0].axis("off")
    luv_ref = rgb2luv(ref)
    errs = {m: np.abs(rgb2luv(np.clip(recs[m][name], 0, 1))[..., 1:] - luv_ref[..., 1:]).mean(-1) for m in methods}
    vmax = max(float(np.percentile(e, 99)) for e in errs.values())
    for j, m in enumerate(methods, start=1):
        axes[0, j].imshow(np.clip(recs[m][name], 0, 1))
        axes[0, j].set_title(m.replace("_", " "))
        im = axes[1, j].imshow(errs[m], cmap="magma", vmin=0, vmax=vmax)
        axes[1, j].set_title(f"mean |dU|,|dV| = {errs[m].mean():.2f}")
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(im, ax=axes[1, 1:].tolist(), shrink=0.8, label="LUV chroma error")
    fig.suptitle(f"Bayer colour sorting, nearest-neighbour reconstruction ({name}); row 0 at the top")
    return save_figure(fig, path)
