"""One process sample as a differentiable map of the continuous heights (robust design).

The optimizer's heights ``h`` are continuous; the masks are binary. Rounding ``h`` to levels
inside the objective makes it piecewise constant in ``h`` (no gradient), so robust design
instead extends each mask's bit to continuous depths: at ``d = -h / step`` steps, bit ``j``
is the linear interpolation of the bits of the two neighbouring levels (level ``N`` wraps to
level 0). On every level the soft bits are the masks themselves; between levels they are
continuous and piecewise linear, so the fabricated height is differentiable almost
everywhere and the same map applies in the continuous stage, the annealing and on the final
levels. Quantization happens only at the end of the design, as without ``--robust``.

Effects that act smoothly on the soft masks ``B_j`` (one sample per design pixel, area
coverage, as :func:`masks.fabricated.fabricated_height` at ``oversample = 1``):

- etch depth per mask: the etch of mask ``j`` is ``D_j (1 + eps_j)`` deep;
- etch gradient: every depth times ``1 + g . r`` (``r`` from the design centre, y up);
- linewidth bias ``b_j`` (smooth edge model): a pixel next to an opening gains ``b_j / pitch``
  of coverage per open neighbour, ``B + (b / p) sum_n relu(B_n - B)`` for growth (the mirror
  image for shrinkage), exact to first order in ``b`` on Manhattan edges;
- overlay and rotation of mask ``j``: ``B_j`` moved by bilinear interpolation, the exact
  area coverage of a sub-pixel translation.

The perturbed height is ``h + e(h)`` with ``e`` the fabricated minus the ideal height of the
soft masks, so ``e = 0`` for the ideal process at any ``h``. Not modelled here (they act in
``doe tolerance`` through the full process model only): proximity blur, sidewall slope, etch
loading, roughness and microtrenching.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse

from doedesign.errors import DoeError

from ..process import ProcessParams

__all__ = ["SmoothProcess", "soft_bits"]

# Neighbour offsets (row, col) of the edge model: the four pixels sharing an edge.
_NEIGHBOURS = ((-1, 0), (1, 0), (0, -1), (0, 1))


def soft_bits(height_m: np.ndarray, step_m: float, n_levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Bits of every mask at continuous heights, and their derivative in the height.

    Parameters
    ----------
    height_m : ndarray
        Heights (m), 0 = top, negative where etched; taken modulo the ``n_levels`` step height.
    step_m : float
    n_levels : int
        A power of two (``log2(n_levels)`` masks).

    Returns
    -------
    bits, dbits_dh : ndarray, shape (n_masks,) + height_m.shape
        ``bits[j]`` in [0, 1], equal to bit ``j`` of the level on every level.
    """
    n_masks = int(round(math.log2(n_levels)))
    if 2 ** n_masks != n_levels:
        raise DoeError(f"soft bits need a power-of-two number of levels, got {n_levels}")
    depth = -np.asarray(height_m, float) / step_m
    # On-level heights (k * step to rounding) give exactly the level's bits.
    whole = np.round(depth)
    depth = np.mod(np.where(np.abs(depth - whole) < 1e-9, whole, depth), n_levels)
    k = np.minimum(np.floor(depth).astype(np.int64), n_levels - 1)
    t = depth - k
    table = (np.arange(n_levels + 1)[:, None] % n_levels >> np.arange(n_masks)) & 1
    lo, hi = table[k], table[k + 1]                       # (..., n_masks)
    bits = np.moveaxis(lo + t[..., None] * (hi - lo), -1, 0)
    slope = np.moveaxis((hi - lo) * (-1.0 / step_m), -1, 0)
    return bits, slope


def _neighbour(a, dr, dc):
    """``a`` at (row + dr, col + dc), zero (unetched) outside."""
    out = np.zeros_like(a)
    rows, cols = a.shape
    out[max(-dr, 0):rows - max(dr, 0), max(-dc, 0):cols - max(dc, 0)] = \
        a[max(dr, 0):rows - max(-dr, 0), max(dc, 0):cols - max(-dc, 0)]
    return out


def _warp_matrix(shape, shift_rc, rotation_rad):
    """Sparse bilinear warp: ``out[o] = in[R^-1 (o - c - t) + c]``, zero outside (as litho.move)."""
    rows, cols = shape
    centre = np.array([(rows - 1) / 2.0, (cols - 1) / 2.0])
    cos, sin = math.cos(rotation_rad), math.sin(rotation_rad)
    inverse = np.array([[cos, sin], [-sin, cos]])
    r, c = np.meshgrid(np.arange(rows, dtype=float), np.arange(cols, dtype=float), indexing="ij")
    o = np.stack([r.ravel(), c.ravel()]) - (centre + np.asarray(shift_rc, float))[:, None]
    src = inverse @ o + centre[:, None]
    r0, c0 = np.floor(src).astype(np.int64)
    fr, fc = src[0] - r0, src[1] - c0
    out_idx = np.arange(rows * cols)
    data, ii, jj = [], [], []
    for dr, dc, w in ((0, 0, (1 - fr) * (1 - fc)), (1, 0, fr * (1 - fc)), (0, 1, (1 - fr) * fc), (1, 1, fr * fc)):
        rr, cc = r0 + dr, c0 + dc
        ok = (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols) & (w > 0)
        data.append(w[ok])
        ii.append(out_idx[ok])
        jj.append(rr[ok] * cols + cc[ok])
    return sparse.csr_matrix((np.concatenate(data), (np.concatenate(ii), np.concatenate(jj))),
                             shape=(rows * cols, rows * cols))


@dataclass
class SmoothProcess:
    """A process sample acting on continuous heights: ``h -> (h + e(h), vjp)``.

    Parameters
    ----------
    params : masks.process.ProcessParams
        The sample (only its depth, gradient, bias, overlay and rotation are used).
    depths_m : sequence of float
        Nominal depth of each mask's etch (the design's binary depths).
    step_m, pitch_m : float
    n_levels : int
    """

    params: ProcessParams
    depths_m: np.ndarray
    step_m: float
    pitch_m: float
    n_levels: int = 16
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        self.depths_m = np.asarray(self.depths_m, float)
        if self.depths_m.size != self.params.n_masks or 2 ** self.depths_m.size != self.n_levels:
            raise DoeError(f"{self.depths_m.size} mask depths, {self.params.n_masks} masks in the process and "
                           f"{self.n_levels} levels do not match")
        self.scale = self.params.etch_depth / self.depths_m
        self.bias_px = self.params.linewidth_bias / self.pitch_m

    def _geometry(self, shape):
        """Per shape: the etch-gradient map and each mask's warp matrix (None when it does not move)."""
        if shape not in self._cache:
            p = self.params
            rows, cols = shape
            grad = None
            if np.any(p.etch_gradient):
                x = (np.arange(cols) - (cols - 1) / 2.0) * self.pitch_m
                y = ((rows - 1) / 2.0 - np.arange(rows)) * self.pitch_m
                grad = 1.0 + p.etch_gradient[1] * y[:, None] + p.etch_gradient[0] * x[None, :]
            warps = []
            for j in range(p.n_masks):
                dx, dy, rot = p.mask_overlay[j]
                rot += math.radians(p.mask_rotation[j])
                moves = dx != 0 or dy != 0 or rot != 0
                warps.append(_warp_matrix(shape, (-dy / self.pitch_m, dx / self.pitch_m), rot) if moves else None)
            self._cache[shape] = (grad, warps)
        return self._cache[shape]

    def __call__(self, height_m):
        h = np.asarray(height_m, float)
        grad_map, warps = self._geometry(h.shape)
        bits, slope = soft_bits(h, self.step_m, self.n_levels)
        error = np.zeros_like(h)
        saved = []
        for j, b in enumerate(bits):
            c = self.bias_px[j]
            # Edge model: which neighbour differences move this pixel (fixed for the vjp).
            diffs = [_neighbour(b, dr, dc) - b for dr, dc in _NEIGHBOURS] if c else []
            masks = [d * np.sign(c) > 0 for d in diffs]
            printed = b + abs(c) * sum(m * d for m, d in zip(masks, diffs)) if c else b
            if warps[j] is not None:
                printed = (warps[j] @ printed.ravel()).reshape(h.shape)
            depth = self.depths_m[j] * self.scale[j] * (grad_map if grad_map is not None else 1.0)
            error -= depth * printed - self.depths_m[j] * b
            saved.append((c, masks, depth))

        def vjp(g):
            g = np.asarray(g, float)
            out = g.copy()
            for j, (c, masks, depth) in enumerate(saved):
                u = -depth * g
                if warps[j] is not None:
                    u = (warps[j].T @ u.ravel()).reshape(g.shape)
                if c:
                    # Transpose of b + |c| sum_n m_n (N_n b - b): N_n^T is the opposite neighbour.
                    u = u + abs(c) * sum(_neighbour(m * u, -dr, -dc) - m * u
                                    for m, (dr, dc) in zip(masks, _NEIGHBOURS))
                out += (u + self.depths_m[j] * g) * slope[j]
            return out

        return h + error, vjp
