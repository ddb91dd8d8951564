"""Lithography on a fine grid: how one binary mask turns into printed area coverage.

Every function here works on *coverage* images: a float in 0..1 per fine pixel, the
fraction of that (square) pixel covered by the printed opening. Working with area
coverage instead of a binary image is what makes the simulated surface vary
continuously with sub-pixel overlay, bias and blur, so that least-squares fits of those
parameters see smooth residuals. Arrays are row-major, row 0 at the top.

The image functions take a ``backend`` (:mod:`doedesign.engine.backend`, default the CPU's
NumPy) and work on its arrays with the array API standard and the backend's ``ndimage``, so
the same formulas run on a GPU (``doe tolerance --device gpu``). Small 1-D index and weight
vectors are made on the host and copied over. The one exception is the microtrench's
chessboard distance transform (:func:`edge_foot`): no GPU library has one, so the distance
is found by SciPy on a host copy of the coverage and copied back.
"""

from __future__ import annotations

import hashlib

import numpy as np

from doedesign.engine.backend import Array, Backend, select_backend

__all__ = ["FOOT_DISTANCES_KEPT", "block_coverage", "blurred", "box_kernel", "edge_foot", "expose", "grow", "grown_mask",
           "interpolate_separable",
           "inverse_motion", "move", "threshold_coverage", "upsample_mask"]

# Trench-foot distance maps kept between calls (one per mask of a model; on a whole 512 px
# camera field some 75 MB each).
FOOT_DISTANCES_KEPT = 4
_FOOT_DISTANCES: dict = {}


def backend_of(backend: str | Backend | None) -> Backend:
    """The backend the image functions compute on (None: the CPU's NumPy)."""
    return select_backend("cpu" if backend is None else backend)


def upsample_mask(mask: Array, upsample: int, backend: Backend | None = None) -> Array:
    """Nearest-neighbour upsampling of a binary design mask to float32 coverage.

    Parameters
    ----------
    mask : ndarray of bool, shape (rows, cols)
    upsample : int
        Fine pixels per design pixel along each axis.

    Returns
    -------
    ndarray of float32, shape (rows * upsample, cols * upsample)
        1 inside openings, 0 elsewhere; opening edges fall on fine-pixel boundaries.
    """
    be = backend_of(backend)
    xp = be.xp
    mask = xp.astype(be.asarray(mask), xp.float32)
    rows, cols = mask.shape
    fine = xp.broadcast_to(mask[:, None, :, None], (rows, upsample, cols, upsample))
    return xp.reshape(fine, (rows * upsample, cols * upsample))


def grow(coverage: Array, bias_px: float, backend: Backend | None = None) -> Array:
    """Grow (bias > 0) or shrink (bias < 0) openings by ``bias_px`` fine pixels on every edge.

    The growth uses a square structuring element, so a square opening of side L becomes a
    square of side L + 2 b (area change b * perimeter + 4 b**2), as a uniform
    over/under-exposure of a Manhattan layout does. Whole pixels are added with a
    maximum filter; the fractional remainder adds that fraction of the next pixel, which
    is the exact area coverage when the edges lie on pixel boundaries (call this before
    any sub-pixel shift) and keeps the result continuous in ``bias_px``.

    Parameters
    ----------
    coverage : ndarray of float, shape (rows, cols)
    bias_px : float
        Edge displacement in fine pixels (positive = wider openings).

    Returns
    -------
    ndarray of float32
    """
    if bias_px == 0:
        return coverage
    if bias_px < 0:
        return 1.0 - grow(1.0 - coverage, -bias_px, backend)
    be = backend_of(backend)
    xp = be.xp
    whole = int(np.floor(bias_px))
    frac = float(np.float32(bias_px - whole))
    out = xp.astype(coverage, xp.float32, copy=False)
    for axis in (0, 1):
        if whole:
            out = be.ndimage.maximum_filter1d(out, 2 * whole + 1, axis=axis, mode="constant", cval=0.0)
        if frac > 0:
            outer = _max3(out, axis, be)
            outer *= frac
            _elementwise_at(be, "maximum", outer, (...,), out)
            out = outer
    return out


def grown_mask(mask: Array, upsample: int, bias_px: float, backend: Backend | None = None) -> Array:
    """``grow(upsample_mask(mask, upsample), bias_px)``, the same numbers, built from the design
    pixels.

    An upsampled mask is constant on each design pixel's block of fine pixels, so a growth that
    reaches less than half a block only changes the fine rows (columns) next to a block's edge,
    and only to the value of the neighbouring design pixel (or that value times the fractional
    part). Each axis's pass is then a choice among five design-resolution arrays per fine
    row (column): the maximum filters of :func:`grow` on the fine grid cost 50 ms a mask on a
    diagnosis crop of 1150 x 1150 fine pixels, a quarter of a CSI diagnosis that fits a bias.
    Growths that reach half a block or more go through :func:`grow`.

    Parameters
    ----------
    mask : ndarray of bool, shape (rows, cols)
        The binary design mask.
    upsample : int
        Fine pixels per design pixel along each axis.
    bias_px : float
        Edge displacement in fine pixels (positive = wider openings).

    Returns
    -------
    ndarray of float32, shape (rows * upsample, cols * upsample)
    """
    be = backend_of(backend)
    xp = be.xp
    b = abs(float(bias_px))
    whole = int(np.floor(b))
    if b == 0 or 2 * (whole + 1) > upsample:
        return grow(upsample_mask(mask, upsample, be), bias_px, be)
    frac = float(np.float32(b - whole))
    m = xp.astype(be.asarray(mask), xp.float32)
    if bias_px < 0:
        m = 1.0 - m
    rows = _grow_axis(m, 0, whole, frac, upsample, xp)
    cols = _grow_axis(rows, 1, whole, frac, upsample, xp)
    return 1.0 - cols if bias_px < 0 else cols


def _grow_axis(a, axis, whole, frac, u, xp):
    """One axis's pass of :func:`grow` on the upsample, along ``axis``, of ``a`` (design
    resolution along that axis, constant over each block), for ``2 (whole + 1) <= u``: fine
    pixel k of a block is the block's value, its maximum with the previous block's (k < whole)
    or the next's (k >= u - whole), or with ``frac`` times it (k = whole, k = u - 1 - whole);
    zero beyond the edges, as :func:`grow`'s filters have it."""
    a = xp.moveaxis(a, axis, -1)
    zero = xp.zeros(a.shape[:-1] + (1,), dtype=a.dtype)
    before = xp.concat([zero, a[..., :-1]], axis=-1)
    after = xp.concat([a[..., 1:], zero], axis=-1)
    out = xp.empty(a.shape + (u,), dtype=a.dtype)
    out[...] = a[..., None]
    if whole:
        out[..., :whole] = xp.maximum(a, before)[..., None]
        out[..., u - whole:] = xp.maximum(a, after)[..., None]
    if frac > 0:
        out[..., whole] = xp.maximum(a, before * frac)
        out[..., u - 1 - whole] = xp.maximum(a, after * frac)
    out = xp.reshape(out, a.shape[:-1] + (a.shape[-1] * u,))
    return xp.moveaxis(out, -1, axis)


def _max3(image, axis, be):
    """Maximum over each pixel and its two neighbours along ``axis``, for values >= 0 (zero
    beyond the edges): ``maximum_filter1d(size=3, mode="constant")`` from shifted slices, 4-8x
    faster on a large image than the filter's line buffers."""
    out = be.xp.asarray(image, copy=True)
    ahead = (slice(None),) * axis + (slice(1, None), ...)
    behind = (slice(None),) * axis + (slice(None, -1), ...)
    _elementwise_at(be, "maximum", out, ahead, image[behind])
    _elementwise_at(be, "maximum", out, behind, image[ahead])
    return out


def _elementwise_at(be, name, out, index, other):
    """``out[index] = f(out[index], other)`` for the standard's two-argument function ``name``
    (``maximum``, ``minimum``): in place where the namespace's ufuncs take ``out=`` (NumPy,
    CuPy; no temporary image), else through a temporary (the standard's way)."""
    f = getattr(be.xp, name)
    if be.name in ("numpy", "cupy"):
        view = out[index]
        f(view, other, out=view)
    else:
        out[index] = f(out[index], other)


def move(coverage: Array, shift_rc: tuple[float, float], rotation_rad: float,
         centre_rc: tuple[float, float], backend: Backend | None = None, order: int = 1) -> Array:
    """Move a coverage image by a translation and a counter-clockwise rotation.

    Linear interpolation of a box-sampled image is its exact area coverage after a
    sub-pixel translation, and a close one after the small rotations of mask overlay.
    It is not exact in the pixels' first moments: a pixel an edge now crosses holds its area at
    one side. ``order=3`` (cubic Lagrange taps for a translation, a cubic spline for a
    rotation) moves an image of :func:`masks.moments.moment_corrected` pixels keeping their
    moments to third order, at the price of values beyond 0..1 beside the edges.

    Parameters
    ----------
    coverage : ndarray of float, shape (rows, cols)
    shift_rc : (float, float)
        Translation in fine pixels along (row, column); row grows downward.
    rotation_rad : float
        Counter-clockwise rotation (x right, y up), about ``centre_rc``.
    centre_rc : (float, float)
        Rotation centre in fine-pixel index coordinates (row, column).

    Returns
    -------
    ndarray of float32
    """
    be = backend_of(backend)
    shift = np.asarray(shift_rc, dtype=float)
    if rotation_rad == 0:
        out = coverage
        for axis in (0, 1):
            out = _translate_axis(out, float(shift[axis]), axis, be.xp, order)
        return out
    inverse, offset = inverse_motion(shift_rc, rotation_rad, centre_rc)
    return be.ndimage.affine_transform(coverage, be.asarray(inverse), offset=tuple(float(v) for v in offset),
                                       order=order, mode="grid-constant", cval=0.0, prefilter=order > 1)


def inverse_motion(shift_rc: tuple[float, float], rotation_rad: float,
                   centre_rc: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Where a point of the moved image was before :func:`move` moved it.

    A point ``o`` of the image after the motion (translation ``t``, then a counter-clockwise
    rotation about ``c``) shows what stood at ``R^-1 (o - c - t) + c``, returned as the affine
    map ``(matrix, offset)``: ``matrix @ o + offset``. Any length unit, as long as ``shift_rc``
    and ``centre_rc`` share it (fine pixels here, design pixels for a camera sampling a moved
    mask, :meth:`metrology.matching.placement.Placement.in_frame_of`).
    """
    cos, sin = np.cos(rotation_rad), np.sin(rotation_rad)
    # With row pointing down, a counter-clockwise rotation in (x, y-up) is
    # [[cos, -sin], [sin, cos]] on (row, col); its inverse is the transpose.
    inverse = np.array([[cos, sin], [-sin, cos]])
    centre = np.asarray(centre_rc, dtype=float)
    return inverse, centre - inverse @ (centre + np.asarray(shift_rc, dtype=float))


def _translate_axis(image, shift, axis, xp, order=1):
    """Linear-interpolation translation by ``shift`` pixels along ``axis``, zero fill.

    ``out[o] = (1 - f) image[o - k] + f image[o - k - 1]`` with ``shift = k + f``; the same
    as ``scipy.ndimage.shift(order=1)`` for one axis, several times faster on big images.
    ``order=3``: the cubic Lagrange taps on ``image[o - k + 1 .. o - k - 2]``, whose first three
    moments are the shift's (``sum w_j j^n = f^n``).
    """
    if shift == 0:
        return image
    k = int(np.floor(shift))
    f = float(np.float32(shift - k))
    if order == 3:
        nodes = (-1, 0, 1, 2)
        taps = [(k + j, float(np.prod([(f - i) / (j - i) for i in nodes if i != j]))) for j in nodes]
    else:
        taps = [(k, 1.0 - f), (k + 1, f)]
    out = xp.zeros_like(image, dtype=xp.float32)
    for offset, weight in taps:
        if weight == 0 or abs(offset) >= image.shape[axis]:
            continue
        dst = [slice(None), slice(None)]
        src = [slice(None), slice(None)]
        if offset >= 0:
            dst[axis], src[axis] = slice(offset, None), slice(0, image.shape[axis] - offset)
        else:
            dst[axis], src[axis] = slice(0, offset), slice(-offset, None)
        out[tuple(dst)] += weight * image[tuple(src)]
    return out


def expose(coverage: Array, blur_px: float, threshold: float, upsample: int = 1,
           backend: Backend | None = None) -> Array:
    """Print a mask through a Gaussian aerial-image blur and a resist threshold.

    The aerial image is the coverage blurred by a Gaussian of ``blur_px`` fine pixels; the
    resist clears where it exceeds ``threshold``. The printed coverage of a pixel is
    ``0.5 + (aerial - threshold) / |grad aerial|``, clipped to 0..1: the fraction of the
    pixel on the cleared side of a locally straight contour, so the printed edge moves
    continuously with the blur and the threshold. Isolated openings, whose aerial image
    peaks lower, shrink more than clusters, and corners round.

    Parameters
    ----------
    coverage : ndarray of float, shape (rows, cols)
    blur_px : float
        Gaussian sigma in fine pixels (0 = sharp image: returned unchanged).
    threshold : float
        Aerial-image level at which the resist clears, in (0, 1).
    upsample : int
        Fine pixels per design pixel; the image must start on a design-pixel boundary.
        A wide blur is computed on blocks whose size divides it, so that the result
        does not depend on where the simulated window starts.

    Returns
    -------
    ndarray of float32
    """
    if blur_px == 0:
        return coverage
    # Even block sizes up to sigma / 2 keep the aerial image within ~4e-3 of the exact blur
    # (edges within ~0.01 sigma); odd ones were measured several times worse.
    blocks = [k for k in range(2, upsample + 1, 2) if upsample % k == 0 and k <= blur_px / 2]
    be = backend_of(backend)
    return threshold_coverage(blurred(coverage, blur_px, max(blocks, default=1), be), threshold, 0.0, be)


def threshold_coverage(aerial: Array, threshold: float, grow_px: float = 0.0,
                       backend: Backend | None = None) -> Array:
    """Printed coverage of a resist that clears where ``aerial`` exceeds ``threshold``.

    ``0.5 + grow_px + (aerial - threshold) / |grad aerial|``, clipped to 0..1: the fraction of
    each pixel on the cleared side of the locally straight contour (its signed distance in
    pixels), with the contour moved outward along its normal by ``grow_px`` pixels (an isotropic
    undercut: convex corners round). Exact for a straight edge when ``grow_px`` is within the
    image's linear range. The one threshold rule of :func:`expose` and
    :func:`masks.proximity.print_coverage`; ``aerial`` is overwritten.

    Returns
    -------
    ndarray of float32
    """
    be = backend_of(backend)
    xp = be.xp
    aerial = xp.astype(aerial, xp.float32, copy=False)
    slope = xp.hypot(_gradient(aerial, 0, xp), _gradient(aerial, 1, xp))
    # A flat aerial image far from the threshold prints as 0 or 1 whatever the guard.
    _elementwise_at(be, "maximum", slope, (...,), float(np.float32(1e-6)))
    aerial -= float(np.float32(threshold))
    aerial /= slope
    aerial += float(np.float32(0.5 + grow_px))
    # Clipped to 0..1 (array_api_compat's clip masks element by element: slow on a large image).
    _elementwise_at(be, "maximum", aerial, (...,), 0.0)
    _elementwise_at(be, "minimum", aerial, (...,), 1.0)
    return aerial


def _gradient(image, axis, xp):
    """``numpy.gradient`` along one axis of a 2-D image (unit spacing; central differences
    inside, one-sided at the two ends), in the image's dtype."""
    n = image.shape[axis]
    out = xp.empty_like(image)

    def part(sl):
        return (slice(None), sl) if axis else (sl, slice(None))

    out[part(slice(1, n - 1))] = (image[part(slice(2, None))] - image[part(slice(None, n - 2))]) / 2.0
    out[part(slice(0, 1))] = image[part(slice(1, 2))] - image[part(slice(0, 1))]
    out[part(slice(n - 1, n))] = image[part(slice(n - 1, n))] - image[part(slice(n - 2, n - 1))]
    return out


def blurred(image: Array, sigma_px: float, block: int = 1, backend: Backend | None = None) -> Array:
    """Gaussian blur with zero outside the array, cheap for wide kernels.

    With ``block = k > 1`` the image is first block-averaged by a factor ``k``, blurred
    with ``sqrt(sigma**2 - (k**2 - 1) / 12)`` (the block average itself adds the variance of
    a box), and linearly interpolated back; for an even ``k <= sigma / 2`` the result is
    within ~4e-3 of the exact blur (image range 1).

    Parameters
    ----------
    image : ndarray of float, shape (rows, cols)
    sigma_px : float
    block : int
        Block size ``k`` (1 = blur at full resolution).

    Returns
    -------
    ndarray of float32
    """
    be = backend_of(backend)
    xp = be.xp
    k = int(block)
    rows, cols = image.shape
    image = xp.astype(image, xp.float32, copy=False)
    if k < 2 or rows < 4 * k or cols < 4 * k:
        return be.ndimage.gaussian_filter(image, sigma_px, mode="constant", cval=0.0)
    # Two zero blocks on every side give the interpolation samples beyond the edges.
    pr, pc = -rows % k, -cols % k
    padded = xp.zeros((rows + pr + 4 * k, cols + pc + 4 * k), dtype=xp.float32)
    padded[2 * k:2 * k + rows, 2 * k:2 * k + cols] = image
    # Block sum from k * k strided views: much faster than a 4-D reshape().mean().
    coarse = xp.zeros((padded.shape[0] // k, padded.shape[1] // k), dtype=xp.float32)
    for a in range(k):
        for b in range(k):
            coarse += padded[a::k, b::k]
    coarse *= float(np.float32(1.0 / k ** 2))
    sigma_c = np.sqrt(max(sigma_px ** 2 - (k ** 2 - 1) / 12.0, 0.0)) / k
    coarse = be.ndimage.gaussian_filter(coarse, sigma_c, mode="constant", cval=0.0)
    # Coarse sample i is the mean of fine pixels (i - 2) k .. (i - 2) k + k - 1 of the image.
    return interpolate_separable(coarse, (np.arange(rows) - (k - 1) / 2) / k + 2,
                                 (np.arange(cols) - (k - 1) / 2) / k + 2, be)


def interpolate_separable(coarse: Array, row_coords: np.ndarray, col_coords: np.ndarray,
                          backend: Backend | None = None, order: int = 1) -> Array:
    """Bilinear (``order`` 1) or cubic B-spline (``order`` 3) interpolation of ``coarse`` at the
    grid ``row_coords x col_coords``.

    Coordinates (host arrays) are in coarse-sample index units; outside the array the edge
    value is held (the callers keep their windows wide enough that this never matters). The
    cubic spline passes through the samples (``ndimage.spline_filter1d``'s prefilter, then the
    four-tap B-spline basis per axis) and is exact for cubics: where a bilinear interpolant of a
    curved image is off by ``h^2 f'' / 8`` (its chords lie on one side of the curve), the
    spline's error falls as ``h^4``.

    Returns
    -------
    ndarray of float32, shape (len(row_coords), len(col_coords))
    """
    if order not in (1, 3):
        raise ValueError(f"interpolation order must be 1 or 3, got {order}")
    be = backend_of(backend)
    xp = be.xp
    out = xp.astype(be.asarray(coarse), xp.float32, copy=False)
    cubic = order == 3 and min(out.shape) >= 4
    if cubic:
        # The prefilter of both axes on the coarse samples (it commutes with the other axis' taps).
        for axis in (0, 1):
            out = be.ndimage.spline_filter1d(out, order=3, axis=axis, output=xp.float32, mode="nearest")
    # The spline's columns first: its larger pass then gathers whole rows.
    for axis, coords in ((1, col_coords), (0, row_coords)) if cubic else ((0, row_coords), (1, col_coords)):
        n = out.shape[axis]
        coords = np.clip(np.asarray(coords, dtype=float), 0, n - 1)
        shape = [1, 1]
        shape[axis] = -1
        if cubic:
            out = _cubic_taps(be, out, coords, axis, shape)
            continue
        i0 = np.minimum(np.floor(coords).astype(np.int64), max(n - 2, 0))
        i1 = np.minimum(i0 + 1, n - 1)
        w = be.asarray((coords - i0).astype(np.float32).reshape(shape))
        low = xp.take(out, be.asarray(i0), axis=axis)
        high = xp.take(out, be.asarray(i1), axis=axis)
        high -= low
        high *= w
        high += low
        out = high
    return out


def _cubic_taps(be, coef, coords, axis, shape):
    """The cubic B-spline of coefficients ``coef`` along ``axis``, at ``coords`` (in range)."""
    xp = be.xp
    n = coef.shape[axis]
    i = np.floor(coords).astype(np.int64)
    t = coords - i
    basis = ((1 - t) ** 3 / 6, (3 * t ** 3 - 6 * t ** 2 + 4) / 6, (-3 * t ** 3 + 3 * t ** 2 + 3 * t + 1) / 6, t ** 3 / 6)
    out = None
    for k, b in enumerate(basis):
        # Taps beyond the ends are clipped to them (the callers keep their windows wide enough).
        taken = xp.take(coef, be.asarray(np.clip(i - 1 + k, 0, n - 1)), axis=axis)
        taken *= be.asarray(b.astype(np.float32).reshape(shape))
        if out is None:
            out = taken
        else:
            out += taken
    return out


def edge_foot(coverage: Array, width_px: float, backend: Backend | None = None) -> Array:
    """Profile of a microtrench: ``exp(-s / w)`` at distance ``s`` from the nearest sidewall.

    ``s`` is the chessboard (L-infinity) distance from a pixel centre to the nearest closed
    pixel, corrected by that pixel's closed fraction ``c`` (its edge sits ``0.5 - c`` pixels
    before its far side), so a straight edge gives the exact profile at the pixel centres and
    the profile moves continuously with the edge: when a pixel starts to close, the distance
    falls from ``n + 0.5`` (the fully closed pixel beyond) to ``n + 0.5 - c``. Trenches of two
    nearby sidewalls do not add: the nearest one sets the depth, at an opening's corner as
    along its edges (ions reflected from the nearer wall dominate). SciPy's chessboard distance
    transform finds the nearest closed pixel, on the host whatever the backend (GPU libraries
    have only Euclidean ones, whose nearest pixel differs); outside the array is closed.

    Parameters
    ----------
    coverage : ndarray of float, shape (rows, cols)
        Printed opening coverage 0..1.
    width_px : float
        Decay length ``w`` in fine pixels, > 0.

    Returns
    -------
    array of float64
        0 deep inside wide openings, 1 at the foot of a straight edge (capped at 1);
        meaningful where the coverage is non-zero (the caller multiplies by it).
    """
    be = backend_of(backend)
    s = _foot_distance(coverage) if be.is_numpy else be.asarray(_foot_distance(be.to_host(coverage)))
    return be.xp.minimum(be.xp.exp(-be.xp.astype(s, be.xp.float64) / float(width_px)), 1.0)


def _foot_distance(coverage):
    """The distance ``s`` of :func:`edge_foot` (fine pixels, float32), kept for the last few
    coverages: a fit of the trenches' depth and width changes neither the coverage nor ``s``,
    and the distance transform is most of the trench's cost."""
    from scipy.ndimage import distance_transform_cdt  # on host arrays only (see edge_foot)

    coverage = np.ascontiguousarray(coverage)
    key = (coverage.shape, coverage.dtype.str, hashlib.sha1(memoryview(coverage).cast("B")).digest())
    s = _FOOT_DISTANCES.pop(key, None)
    if s is None:
        closed = 1.0 - np.asarray(coverage, dtype=np.float64)
        padded = np.pad(closed, 1, constant_values=1.0)
        dist, (ri, ci) = distance_transform_cdt(padded <= 0.0, metric="chessboard", return_indices=True)
        s = (dist + 0.5 - padded[ri, ci])[1:-1, 1:-1].astype(np.float32)
    _FOOT_DISTANCES[key] = s
    while len(_FOOT_DISTANCES) > FOOT_DISTANCES_KEPT:
        _FOOT_DISTANCES.pop(next(iter(_FOOT_DISTANCES)))
    return s


def box_kernel(width_px: float, moments: bool = False) -> np.ndarray:
    """1-D box of a continuous width ``width_px`` (fine pixels), normalized to sum 1.

    Tap t is the overlap of pixel ``[t - 0.5, t + 0.5]`` with ``[-width/2, width/2]``
    divided by the width, so a sharp step between pixels, filtered by it, takes exactly
    the values of a linear ramp of that width at the pixel centres, and the kernel changes
    continuously with the width.

    With ``moments`` the taps are :func:`masks.moments.box_moment_taps`: the ramp's slopes
    inside the pixels carried as their first moments, for a model that treats each pixel as
    uniform (the camera render).
    """
    if moments:
        from masks.moments import box_moment_taps

        return box_moment_taps(width_px)
    half = width_px / 2.0
    n = int(np.ceil(half + 0.5))
    taps = np.arange(-n, n + 1, dtype=float)
    weights = np.clip(np.minimum(taps + 0.5, half) - np.maximum(taps - 0.5, -half), 0.0, None)
    return weights / weights.sum()


def block_coverage(mask: np.ndarray, subgrid: int) -> np.ndarray:
    """Area coverage (float32) of the print grid's cells from a mask-grid array (block means)."""
    m = np.asarray(mask, dtype=np.float32)
    s = int(subgrid)
    if s == 1:
        return m
    rows, cols = m.shape[0] // s, m.shape[1] // s
    return m[:rows * s, :cols * s].reshape(rows, s, cols, s).mean(axis=(1, 3))
