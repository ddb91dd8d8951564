"""Hidden-effect generator: synthetic measurements with effects the diagnosis is not told about.

Every size, direction, affected mask and noise level is drawn at random from a seed, so the
diagnosis cannot be tuned to one case. Height cases are produced directly on the fine model
grid (already registered); PSF cases on the sensor window. Arrays are row-major, row 0 at the
top.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import scipy.ndimage as ndi

from metrology.diagnosis.effects import get_effect

if TYPE_CHECKING:
    from doedesign.camera import Camera
    from doedesign.design import Design
    from metrology.diagnosis.engine import Diagnosis
    from metrology.diagnosis.psf import PsfRenderer

__all__ = ["HEIGHT_EFFECTS", "HiddenCase", "PSF_EFFECTS", "correlated_noise", "make_height_case",
           "make_psf_case", "parameter_errors", "psf_test_setup", "random_levels"]

HEIGHT_EFFECTS = ("etch_depth", "mask_overlay", "linewidth_bias", "proximity_blur", "sidewall_slope",
                  "etch_loading", "instrument_blur", "batwing")
PSF_EFFECTS = ("dual_pixel_crosstalk", "source_bandwidth", "defocus", "depth_scale", "background")


@dataclass
class HiddenCase:
    """A synthetic measurement and the truth behind it.

    Attributes
    ----------
    truth : dict
        Effect name -> parameter values in the registry's order and units.
    main : dict
        Effect name -> indices of the parameters that were set (the others are at null);
        parameter errors are judged on these.
    noise_rms : float
        Rms of the added noise (measurement units).
    """

    truth: dict
    main: dict
    noise_rms: float
    data: dict = field(default_factory=dict)


def random_levels(shape: tuple[int, int], rng: np.random.Generator, n_levels: int = 16,
                  feature_px: float = 4.0) -> np.ndarray:
    """A DOE-like level map: a smooth random phase wrapped into ``n_levels`` levels, with an
    unetched (level 0) patch so the local pattern density varies across the field."""
    field_ = ndi.gaussian_filter(rng.standard_normal(shape), feature_px, mode="wrap")
    field_ *= 3.0 * n_levels / (field_.std() * 2 * np.pi)
    ramp = rng.uniform(0.5, 2.0) * (np.arange(shape[1]) / shape[1])[None, :] * n_levels
    levels = np.floor(np.mod(field_ * 2 * np.pi + ramp, n_levels)).astype(np.int16)
    rows, cols = np.mgrid[:shape[0], :shape[1]]
    cy, cx = rng.uniform(0.2, 0.8) * shape[0], rng.uniform(0.0, 1.0) * shape[1]
    radius = rng.uniform(0.25, 0.4) * min(shape)
    levels[np.hypot(rows - cy, cx - cols) < radius] = 0
    return levels


def _height_truth(name, rng):
    """Realistic random values of one height-domain effect and the indices that matter."""
    if name == "etch_depth":
        v = np.zeros(4)
        j = int(rng.integers(0, 4))
        v[j] = rng.choice([-1, 1]) * rng.uniform(0.04, 0.08)
        return v, [j]
    if name == "mask_overlay":
        v = np.zeros(6)
        j = int(rng.integers(1, 4))
        mag, ang = rng.uniform(0.3e-6, 0.6e-6), rng.uniform(0, 2 * np.pi)
        v[2 * (j - 1):2 * j] = mag * np.cos(ang), mag * np.sin(ang)
        return v, [2 * (j - 1), 2 * j - 1]
    if name == "linewidth_bias":
        return np.full(4, rng.choice([-1, 1]) * rng.uniform(0.2e-6, 0.4e-6)), [0, 1, 2, 3]
    if name == "proximity_blur":
        return np.array([rng.uniform(1.0e-6, 1.8e-6)]), [0]
    if name == "sidewall_slope":
        # Wider than two fine steps: narrower ramps are a 3-tap kernel on the 1.08 um grid,
        # indistinguishable from instrument blur (the diagnosis reports them as ambiguous).
        return np.array([rng.uniform(2.2e-6, 3.0e-6)]), [0]
    if name == "etch_loading":
        return np.array([rng.uniform(0.05, 0.12)]), [0]
    if name == "instrument_blur":
        return np.array([rng.uniform(0.35e-6, 0.7e-6)]), [0]
    if name == "batwing":
        return np.array([rng.uniform(0.1, 0.25), rng.uniform(0.5e-6, 1.0e-6)]), [0, 1]
    raise KeyError(name)


def correlated_noise(shape: tuple[int, ...], rms: float, corr_px: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian noise of rms ``rms`` smoothed by a Gaussian of ``corr_px`` pixels."""
    n = rng.standard_normal(shape)
    if corr_px > 0:
        n = ndi.gaussian_filter(n, corr_px, mode="wrap")
    return n * (rms / n.std())


def make_height_case(effects: Sequence[str], seed: int, shape: tuple[int, int] = (48, 48), pitch_m: float = 5.4e-6,
                     upsample: int = 5) -> HiddenCase:
    """A measured height map of a random design with hidden ``effects``.

    Parameters
    ----------
    effects : sequence of str
        Height-domain effect names to hide (empty for the null case).
    seed : int
    shape : (int, int)
        Design pixels.
    pitch_m : float
    upsample : int
        Fine samples per design pixel (the measurement grid).

    Returns
    -------
    HiddenCase
        ``data`` holds ``levels``, ``pitch_m``, ``step_m``, ``measured_height_m``.
    """
    from masks.process import ProcessParams, simulate_surface

    rng = np.random.default_rng(seed)
    levels = random_levels(shape, rng)
    truth, main = {}, {}
    for name in effects:
        truth[name], main[name] = _height_truth(name, rng)
    step = pitch_m / upsample
    params = ProcessParams.ideal()
    ordered = sorted(truth, key=lambda n: (get_effect(n).stage != "process", get_effect(n).order))
    for name in ordered:
        e = get_effect(name)
        if e.stage == "process":
            params = e.apply(params, truth[name])
    h = simulate_surface(levels, pitch_m, params, step_m=step).height_m
    for name in ordered:
        e = get_effect(name)
        if e.stage == "surface":
            h = e.apply(h, truth[name], step)
    noise_rms = rng.uniform(0.5e-9, 2.0e-9)
    h = h + correlated_noise(h.shape, noise_rms, rng.uniform(0.0, 1.0), rng) + rng.uniform(-50e-9, 50e-9)
    return HiddenCase(truth=truth, main=main, noise_rms=noise_rms,
                      data={"levels": levels, "pitch_m": pitch_m, "step_m": step, "measured_height_m": h})


def parameter_errors(case: HiddenCase, diagnosis: Diagnosis) -> dict[str, float]:
    """Relative error of each hidden effect's main parameters (``|fit - truth| / |truth|``).

    Returns a dict effect -> max relative error over its main parameters (inf when the effect
    was not named). For effects whose main parameters form a vector (an overlay shift), the
    error is the norm of the difference over the norm of the truth.
    """
    out = {}
    for name, values in case.truth.items():
        if name not in diagnosis.model:
            out[name] = float("inf")
            continue
        idx = case.main[name]
        fit = np.asarray(diagnosis.model[name], dtype=float)[idx]
        true = np.asarray(values, dtype=float)[idx]
        if name == "mask_overlay":
            out[name] = float(np.linalg.norm(fit - true) / np.linalg.norm(true))
        else:
            out[name] = float(np.max(np.abs(fit - true) / np.abs(true)))
    return out


def _psf_truth(name, rng, n_channels):
    if name == "dual_pixel_crosstalk":
        return np.array([rng.uniform(0.06, 0.16)]), [0]
    if name == "source_bandwidth":
        return np.array([rng.uniform(10e-9, 20e-9)]), [0]
    if name == "defocus":
        return np.array([rng.uniform(1.0, 2.5)]), [0]
    if name == "depth_scale":
        return np.array([rng.choice([-1, 1]) * rng.uniform(0.04, 0.08)]), [0]
    if name == "background":
        return rng.uniform(2e-5, 6e-5, n_channels), list(range(n_channels))
    raise KeyError(name)


def psf_test_setup(n_wavelengths: int = 3, size_px: int = 96, pitch_m: float = 14.4e-6,
                   window: tuple[int, int] = (40, 72),
                   axis: tuple[float, float] = (20, 16)) -> tuple[Design, Camera, np.ndarray]:
    """A small split-aperture configuration for fast PSF diagnoses.

    A 16-level blazed staircase of period 12 pixels (172.8 um) over a 1.38 mm square pupil
    filling the design; its first order lands about 30 sensor pixels right of the axis at
    550 nm (x = lambda z / period).

    Returns
    -------
    design : Design
    camera : Camera
    wavelengths_m : ndarray
    """
    from doedesign.camera import Camera
    from doedesign.design import Design
    from doedesign.levels import level_step_m

    step = level_step_m("fused_silica", 550e-9)
    levels = np.tile((np.arange(size_px) % 12) * 16 // 12, (size_px, 1)).astype(np.int16)
    design = Design(height_m=-levels * step, pitch_m=pitch_m, levels=levels)
    camera = Camera(aperture_diameter_m=None, window_shape=window, axis_pixel=axis, doe_side="left")
    wavelengths = np.linspace(480e-9, 620e-9, n_wavelengths) if n_wavelengths > 1 else np.array([550e-9])
    return design, camera, wavelengths


def make_psf_case(effects: Sequence[str], seed: int, n_wavelengths: int = 3,
                  views: Sequence[str] = ("coded", "uncoded"),
                  setup: tuple[Design, Camera, np.ndarray] | None = None,
                  renderer: PsfRenderer | None = None) -> HiddenCase:
    """A measured PSF stack with hidden PSF-domain ``effects`` and Gaussian read noise.

    Returns
    -------
    HiddenCase
        ``data`` holds ``design``, ``camera``, ``wavelengths_m``, ``views``, ``measured_psf``
        (views, wavelengths, rows, cols) and ``renderer`` (reusable by the diagnosis).
    """
    from metrology.diagnosis.psf import PsfRenderer, psf_forward

    rng = np.random.default_rng(seed)
    design, camera, wavelengths = setup or psf_test_setup(n_wavelengths)
    channels = [f"{v}_{wl * 1e9:.0f}nm" for v in views for wl in wavelengths]
    truth, main = {}, {}
    for name in effects:
        truth[name], main[name] = _psf_truth(name, rng, len(channels))
    render = renderer or PsfRenderer(camera, design.pitch_m, design.shape, design.material)
    table = {n: get_effect(n).for_channels(channels) for n in truth}
    stack = psf_forward(truth, table, render, design.height_m, wavelengths, camera.focus_distance_m, views)
    peak = stack.max(axis=(-2, -1), keepdims=True)
    noise_rel = rng.uniform(3e-4, 1e-3)
    # Read noise of one rms in normalized units for every channel (homoscedastic).
    noise = noise_rel * peak.mean() * rng.standard_normal(stack.shape)
    measured = (stack + noise) * rng.uniform(1e3, 1e5)  # arbitrary camera units
    return HiddenCase(truth=truth, main=main, noise_rms=float(noise_rel * peak.mean()),
                      data={"design": design, "camera": camera, "wavelengths_m": wavelengths, "views": views,
                            "measured_psf": measured, "renderer": render})
