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
  The cell's G is the mean of its two green pixels, (1, 0) and (0, 1), weighted by the light
  the green PSF carries from the top-left scene point to each (:func:`green_weights`, the
  matched filter): (1, 0) alone for Eq. (1), both for the RGGB target and balanced designs
  that put green on either of them.
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

from . import targets
from .camera import Camera
from .design import Design
from .errors import DoeError

__all__ = ["IMAGES", "Method", "NOISE_SIGMA", "PAPER_TABLE1", "TARGET_OFFSETS", "apply_psf",
           "bilinear_demosaic", "delta_kernels", "design_psf", "design_target", "evaluate", "figure", "green_weights", "load_images", "mosaic",
           "nearest_neighbour", "psf_kernels", "psnr_scores", "rggb_masks", "rggb_target_kernels",
           "standard_methods"]

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


def rggb_target_kernels() -> np.ndarray:
    """Kernels (3, 3, 3) of the RGGB target (:func:`doedesign.targets.builtin.bayer` with ``rggb=True``):
    green split evenly between (1, 0) and (0, 1)."""
    return targets.bayer(Camera(window_shape=(3, 3), axis_pixel=(1, 1)), rggb=True).intensity[0]


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


def green_weights(kernel_g: np.ndarray) -> tuple[float, float]:
    """Weights of a cell's green pixels (1, 0) and (0, 1) for the nearest-neighbour reconstruction.

    Each weight is the light the green kernel (centred, odd size) carries from the cell's
    top-left scene point to that pixel, normalized to a sum of 1: the matched filter of the two
    samples, so a flat field keeps its level. A kernel with no light on either gives (1, 0).
    """
    k = np.asarray(kernel_g, dtype=float)
    m = k.shape[0] // 2
    if k.shape[0] < 3 or k.shape[1] < 3:
        return 1.0, 0.0
    a, b = max(float(k[m + 1, m]), 0.0), max(float(k[m, m + 1]), 0.0)
    return (a / (a + b), b / (a + b)) if a + b > 0 else (1.0, 0.0)


def nearest_neighbour(raw: np.ndarray, green: tuple[float, float] = (1.0, 0.0)) -> np.ndarray:
    """Cell-wise reconstruction: R from (0, 0), G from (1, 0) and (0, 1) weighted by ``green``
    (see :func:`green_weights`), B from (1, 1) of each 2 x 2 cell."""
    rows, cols = raw.shape
    if rows % 2 or cols % 2:
        raise DoeError(f"mosaic of {rows} x {cols} pixels: nearest-neighbour needs even sizes")
    cells = [raw[0::2, 0::2], green[0] * raw[1::2, 0::2] + green[1] * raw[0::2, 1::2], raw[1::2, 1::2]]
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


def _rgb2luv(rgb: np.ndarray) -> np.ndarray:
    """:func:`skimage.color.rgb2luv` (CIE LUV, D65), imported when first needed."""
    from skimage.color import rgb2luv  # type: ignore[attr-defined]  # public, but missing from skimage's __init__.pyi __all__

    return rgb2luv(rgb)


def _luv_peaks():
    """Extent of L, U and V over the sRGB gamut (sampled finely on the cube's surface)."""
    t = np.linspace(0, 1, 33)
    a, b = np.meshgrid(t, t, indexing="ij")
    faces = []
    for fixed in (0.0, 1.0):
        f = np.full_like(a, fixed)
        faces += [np.stack([f, a, b], -1), np.stack([a, f, b], -1), np.stack([a, b, f], -1)]
    luv = _rgb2luv(np.concatenate(faces, axis=0))
    return luv.reshape(-1, 3).max(axis=0) - luv.reshape(-1, 3).min(axis=0)


def psnr_scores(reference: np.ndarray, estimate: np.ndarray, margin: int = 4) -> _Scores:
    """PSNR (dB) in RGB and per LUV channel on the interior (``margin`` px dropped at each edge)."""
    sl = (slice(margin, -margin or None), slice(margin, -margin or None))
    ref, est = reference[sl], np.clip(estimate[sl], 0.0, 1.0)

    def psnr(a, b, peak):
        mse = np.mean((a - b) ** 2)
        return float(10 * np.log10(peak ** 2 / mse)) if mse > 0 else float("inf")

    luv_ref, luv_est = _rgb2luv(ref), _rgb2luv(est)
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
        rec = (nearest_neighbour(raw, green_weights(self.kernels[1])) if self.reconstruct == "nearest"
               else bilinear_demosaic(raw))
        # Undo the channel's light loss (white balance); noise is amplified with it.
        return rec / gain


def standard_methods(doe_psf: np.ndarray | None = None, axis_pixel: tuple[int, int] = (256, 256),
                     rggb: bool = False) -> list[Method]:
    """The rows of Table 1; ``doe_psf`` (3, rows, cols) R, G, B adds ``proposed_doe``.

    ``rggb`` adds ``proposed_target_rggb``, the target PSF of a design made for the RGGB
    geometry (green on either Bayer pixel), beside the seed's Eq. (1) ``proposed_target``.
    """
    ideal = delta_kernels(((0, 0),) * 3)
    target = delta_kernels(TARGET_OFFSETS)
    methods = [Method("ideal_demosaic", ideal, "bilinear"), Method("ideal_nearest", ideal),
               Method("proposed_target", target)]
    if rggb:
        methods.append(Method("proposed_target_rggb", rggb_target_kernels()))
    if doe_psf is not None:
        methods.append(Method("proposed_doe", psf_kernels(doe_psf, axis_pixel)))
    return methods


def design_target(design: Design, camera: Camera | None = None) -> targets.Target:
    """The Bayer target a design was made for: its R, G, B wavelengths (656/589/486 nm when the
    metadata has none) and its geometry (Eq. (1), or RGGB when the metadata says ``rggb``)."""
    meta = design.metadata.get("target")
    meta = meta if isinstance(meta, dict) else {}
    wls = meta.get("wavelengths_nm")
    wls = np.asarray(wls, dtype=float) * 1e-9 if wls and len(wls) == 3 else targets.RGB_WAVELENGTHS_M
    return targets.bayer(camera or design.camera(), wls, rggb=bool(meta.get("rggb", False)))


def design_psf(design: Design, source: str = "design") -> tuple[np.ndarray, Camera, dict]:
    """Coded-view R, G, B PSFs (3, rows, cols) of a Bayer design in its camera, and its figures.

    The figures (``info``) are the light on each colour's target pixels of :func:`design_target`
    (summed over both green pixels for RGGB) beside the single-colour bound, the green split
    between (1, 0) and (0, 1) and the reconstruction's :func:`green_weights`.
    """
    from .bounds import bound_report, spot_bound
    from .engine.psf import compute_psf

    camera = design.camera()
    target = design_target(design, camera)
    res = compute_psf(design, camera, wavelengths_m=target.wavelengths_m, depths_m=[np.inf], views=("coded",))
    psf, (r0, c0) = res.psf[0, 0], camera.axis_pixel
    energy = np.sum(psf * target.mask[0], axis=(-2, -1)).tolist()
    bound = spot_bound(camera, design.pitch_m, design.shape, target, design.material)[0]
    info = {"source": source, "geometry": "rggb" if target.meta["rggb"] else "eq1",
            "energy_in_window": res.energy_in_window[0, 0].tolist(), "energy_on_target_pixel": energy,
            "green_on_10_01": [float(psf[1, r0 + 1, c0]), float(psf[1, r0, c0 + 1])],
            "green_weights": list(green_weights(psf_kernels(psf, camera.axis_pixel, 1)[1])),
            "quantized": design.levels is not None,
            "objective": design.metadata.get("optimizer", {}).get("objective", "loss"),
            "bound": bound_report([energy], [bound])}
    return psf, camera, info


def evaluate(images: dict[str, np.ndarray], methods: Sequence[Method], seed: int = 0
             ) -> tuple[dict[str, _Scores], dict[str, dict[str, _Scores]], dict[str, dict[str, np.ndarray]]]:
    """Mean PSNR per method over the images (each image with its own noise draw, seeded).

    Returns
    -------
    table : dict  method -> {"rgb_db", "l_db", "u_db", "v_db"} (means over images)
    per_image : dict  method -> image -> scores
    reconstructions : dict  method -> image -> reconstructed array (for figures)
    """
    per_image: dict[str, dict[str, _Scores]] = {}
    recs: dict[str, dict[str, np.ndarray]] = {}
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
    """Fig. 2-like panel: reconstructions (top) and mean ``|dU| + |dV|`` error maps (bottom)."""
    import matplotlib.pyplot as plt

    from .fileio import save_figure

    name = image_name or next(iter(images))
    ref = images[name]
    methods = [m for m in ("ideal_nearest", "proposed_target", "proposed_target_rggb", "proposed_doe") if m in recs]
    fig, axes = plt.subplots(2, len(methods) + 1, figsize=(3.2 * (len(methods) + 1), 6.4))
    axes[0, 0].imshow(ref)
    axes[0, 0].set_title("scene")
    axes[1, 0].axis("off")
    luv_ref = _rgb2luv(ref)
    errs = {m: np.abs(_rgb2luv(np.clip(recs[m][name], 0, 1))[..., 1:] - luv_ref[..., 1:]).mean(-1) for m in methods}
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
