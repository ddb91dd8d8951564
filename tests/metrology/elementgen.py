"""Independent generator of a whole-element height map with spatially varying process errors.

Written from a physics description, apart from the model code (no :mod:`masks` or diagnosis
import): each mask j (open where bit j of the level is set) is printed displaced by a field
``u_j(x, y)`` (translation, rotation and magnification about the design centre; mask 0 is the
reference), and etched to ``D_j (1 + e_j) (1 + a (r / R)^2)``: ``a`` the centre-to-edge radial
non-uniformity, ``R`` the element's half-width. Each map pixel (``pitch / u`` square, on the design
grid) reports the exact area mean of the surface over it: within a pixel the displacement is a
translation (a rotation of 1e-5 rad moves a 2.7 um pixel's corners by 0.03 nm), so a mask's
coverage of the pixel is the overlap of the pixel, moved back by ``u_j``, with the drawn
Manhattan openings, computed from the overlaps along rows and columns separately. Then white
noise. Only ``patches`` (design-pixel regions) are measured; the rest is NaN (not measured).

Positions: x toward increasing column, y up; arrays row-major, row 0 at the top.
"""

from __future__ import annotations

import numpy as np

PITCH_M = 5.4e-6
DEPTHS_M = (75e-9, 150e-9, 300e-9, 600e-9)


def element_levels(n_px, seed=0, feature_px=3):
    """A 16-level element: random levels in blocks of ``feature_px`` design pixels."""
    rng = np.random.default_rng(seed)
    k = -(-n_px // feature_px)
    return np.kron(rng.integers(0, 16, (k, k)), np.ones((feature_px, feature_px), int))[:n_px, :n_px]


def _overlap_1d(lo, hi, n):
    """Overlap (design pixels) of intervals [lo, hi) (arrays, design-pixel edges) with pixels 0..n-1,
    as (first pixel index, overlap with it, overlap with the next)."""
    i0 = np.floor(lo).astype(int)
    first = np.minimum(i0 + 1, hi) - lo
    second = np.clip(hi - (i0 + 1), 0, None)
    return i0, first, second


def measure(levels, u, patches, truth, noise_m=0.5e-9, seed=1):
    """The map (m, NaN outside ``patches``), ``u`` pixels per design pixel.

    ``truth``: ``radial`` (centre-to-edge fraction), ``depth_error`` (4 fractions),
    ``shift_m`` {mask: (dx, dy)}, ``rotation_rad`` {mask: a}, ``magnification`` {mask: m}.
    """
    rng = np.random.default_rng(seed)
    n = levels.shape[0]
    out = np.full((n * u, n * u), np.nan, dtype=np.float64)
    centre = (n - 1) / 2
    half = 0.5 * n
    for r0, r1, c0, c1 in patches:
        a = np.arange(r0 * u, r1 * u)
        b = np.arange(c0 * u, c1 * u)
        # Pixel edges in design-pixel coordinates (design pixel i spans [i - 0.5, i + 0.5)).
        top, left = a[:, None] / u - 0.5, b[None, :] / u - 0.5
        rc, cc = top + 0.5 / u, left + 0.5 / u
        x, y = (cc - centre) * PITCH_M, -(rc - centre) * PITCH_M
        rho2 = (x ** 2 + y ** 2) / (half * PITCH_M) ** 2
        height = np.zeros((a.size, b.size))
        for j in range(4):
            dx, dy = truth.get("shift_m", {}).get(j, (0.0, 0.0))
            rot = truth.get("rotation_rad", {}).get(j, 0.0)
            mag = truth.get("magnification", {}).get(j, 0.0)
            ux = dx + mag * x - rot * y
            uy = dy + mag * y + rot * x
            # Moved back onto the drawn mask: rows go down as y goes up.
            sr, sc = top + uy / PITCH_M, left - ux / PITCH_M
            sr, sc = np.broadcast_to(sr, height.shape), np.broadcast_to(sc, height.shape)
            i0, fr1, fr2 = _overlap_1d(sr + 0.5, sr + 0.5 + 1 / u, n)
            k0, fc1, fc2 = _overlap_1d(sc + 0.5, sc + 0.5 + 1 / u, n)
            open_ = ((levels >> j) & 1).astype(float)
            pad = np.pad(open_, 1)
            g = lambda i, k: pad[np.clip(i + 1, 0, n + 1), np.clip(k + 1, 0, n + 1)]  # noqa: E731
            cover = (fr1 * fc1 * g(i0, k0) + fr1 * fc2 * g(i0, k0 + 1) + fr2 * fc1 * g(i0 + 1, k0)
                     + fr2 * fc2 * g(i0 + 1, k0 + 1)) * u * u
            e = truth.get("depth_error", np.zeros(4))[j]
            depth = DEPTHS_M[j] * (1 + e) * (1 + truth.get("radial", 0.0) * rho2)
            height -= cover * depth
        out[r0 * u:r1 * u, c0 * u:c1 * u] = height + noise_m * rng.standard_normal(height.shape)
    return out
