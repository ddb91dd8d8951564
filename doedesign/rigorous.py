"""Rigorous diffraction efficiencies of a periodic patch, beside the thin-element ones.

The thin-element (scalar) model, which every other part of the tool uses, treats the element as
a phase screen ``exp(i 2 pi (n - 1) h / lambda)``. It fails where features approach the
wavelength or the etch depth approaches the feature width. This module scores one period of a
design with the Fourier modal method (rigorous coupled-wave analysis) and puts both answers
side by side, with the thin-element validity figures.

Solver choice (all four are the field's own libraries; compared on 2026-12-02, Python 3.11, CPU)

========== ============== ================================================ ==========================
library    licence        install from wheels (fresh venv)                 notes
========== ============== ================================================ ==========================
fmmax      MIT            jax + jaxlib (Apache-2.0): ~390 MB, 13 s         Fourier modal method in
                                                                           JAX, vector formulations
                                                                           for 2-D patterns; the
                                                                           solver of invrs-gym
grcwa      GPL-3.0        autograd, small                                  excluded: GPL
inkstone   AGPL-3.0       numpy, scipy                                     excluded: AGPL
torcwa     LGPL           torch (~2 GB with CUDA wheels)                   excluded: LGPL and size
========== ============== ================================================ ==========================

fmmax is the only permissive one, and it is what the invrs-gym challenges score with, so a
design scored here and there is scored by the same method. It is an optional extra
(``pip install "doe-toolkit[rigorous]"``) and imported lazily: without it,
:func:`rigorous_efficiencies` raises one line saying how to install it. JAX runs on the CPU in
double precision (``JAX_PLATFORMS=cpu`` unless the user set it).

Model
-----
The height map (z up, 0 at the unetched top, negative where etched; row 0 at the top,
column 0 at the left) is one period of a periodic element. It becomes a stack of binary
layers, one per step between distinct heights: in the slice between two consecutive heights,
glass fills the pixels whose surface is at or above the slice's top. The light arrives at
normal incidence either through the substrate (``incidence="substrate"``: glass, relief, air,
the usual DOE in front of a lens) or from the air side (``"air"``: air, relief, glass, as the
invrs-gym diffractive splitter is posed). Transmitted efficiencies are the Poynting flux in each
propagating order over the incident flux. ``te``: the electric field along y (up the columns),
which for a 1-D grating along x (one row) is along its lines (checked against the
effective-medium film in the tests); ``tm``: along x; ``unpolarised``: their mean. The relief is
repeated pixel by pixel onto the finer grid fmmax needs for the chosen terms (the same geometry).

Hand-written here: only the slicing of a height map into layers and the order bookkeeping;
the eigenmodes, scattering matrices and fluxes are fmmax's.

The thin-element model (:func:`thin_element_efficiencies`) is the PSF engine's pixel model
(:mod:`doedesign.engine.psf`): each pixel a flat phase step, so order ``(p, q)`` carries
``|DFT[p, q] / N|^2 sinc^2(p / cols) sinc^2(q / rows)``, no Fresnel loss. The comparison uses the
rigorous efficiencies renormalized to the transmitted total (:func:`compare`), so that the
interface reflection of a few percent, which no phase screen models, does not count as
disagreement; the absolute figures are reported too.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .budget import check_memory
from .errors import DoeError

__all__ = ["DEFAULT_TERMS", "DEFAULT_TOLERANCE", "score_design", "FEATURE_MIN_WAVELENGTHS", "DEPTH_MAX_FEATURES", "INCIDENCES", "POLARIZATIONS",
           "RigorousResult", "compare", "relief_layers", "rigorous_efficiencies", "smallest_feature_m",
           "stack_efficiency", "thin_element_efficiencies", "validity"]

log = logging.getLogger(__name__)

# A refractive index, or a function of the wavelength (m) giving one.
IndexLike = complex | float | Callable[[float], complex | np.ndarray]

DEFAULT_TERMS = 200
INCIDENCES = ("substrate", "air")
POLARIZATIONS = ("te", "tm", "unpolarised")
MAX_LAYERS = 64
# Largest difference (absolute efficiency, rigorous over its transmitted total against thin
# element) that passes without a warning.
DEFAULT_TOLERANCE = 0.02
# Thin-element validity limits: smallest feature at least this many wavelengths, and etch depth at
# most this many smallest features. Measured on the 16-level blazed grating in fused silica at
# 550 nm (benchmarks/bench_rigorous.py, 1.12 um deep): its first order (over the transmitted
# total) falls short of the thin element's 0.987 by 0.013-0.014 at a feature of 3.1 wavelengths,
# 0.017-0.018 at 2.5, 0.021-0.023 at 1.9, 0.038 at 1.25 and 0.095-0.10 at 0.5. Two wavelengths is
# where the shortfall passes 2 points; there the depth is 1.0 feature. The two limits come from one
# family of gratings, so they are not separately measured.
FEATURE_MIN_WAVELENGTHS = 2.0
DEPTH_MAX_FEATURES = 1.0
INSTALL_HINT = 'the rigorous solver is an optional extra: pip install "doe-toolkit[rigorous]" (fmmax, JAX)'


def _solver():
    """Import fmmax lazily, on the CPU in double precision; one line if it is missing."""
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    try:
        import jax
        import fmmax
    except ImportError:
        raise DoeError(INSTALL_HINT) from None
    jax.config.update("jax_enable_x64", True)
    return jax, fmmax


@dataclass
class RigorousResult:
    """Transmitted efficiencies of one period.

    Attributes
    ----------
    orders : ndarray (k, 2) int
        ``(p, q)``: order along the columns (x) and along the rows (y, positive toward row 0).
    wavelengths_m : ndarray (w,)
    efficiency : ndarray (w, 2, k)
        Transmitted efficiency per wavelength, polarization (te, tm) and order (propagating
        orders only; the rest are 0).
    n_terms : int
        Fourier terms used.
    """

    orders: np.ndarray
    wavelengths_m: np.ndarray
    efficiency: np.ndarray
    n_terms: int
    settings: dict = field(default_factory=dict)

    def polarized(self, polarization: str) -> np.ndarray:
        """Efficiency (w, k) for ``te``, ``tm`` or ``unpolarised`` (their mean)."""
        if polarization not in POLARIZATIONS:
            raise DoeError(f"polarization must be one of {', '.join(POLARIZATIONS)}, got {polarization!r}")
        if polarization == "unpolarised":
            return self.efficiency.mean(axis=1)
        return self.efficiency[:, POLARIZATIONS.index(polarization)]

    def order_index(self, p: int, q: int = 0) -> int:
        hit = np.flatnonzero((self.orders[:, 0] == p) & (self.orders[:, 1] == q))
        if hit.size == 0:
            raise DoeError(f"order ({p}, {q}) is not in the expansion")
        return int(hit[0])


def relief_layers(height_m: np.ndarray, max_layers: int = MAX_LAYERS,
                  resolution_m: float = 1e-12) -> tuple[list[np.ndarray], list[float]]:
    """Slice a height map into binary layers, top first.

    Returns
    -------
    patterns : list of bool (rows, cols)
        True where glass fills the slice.
    thicknesses_m : list of float
        Slice thicknesses, top slice first; they add up to the relief depth.
    """
    h = np.round(np.asarray(height_m, dtype=np.float64) / resolution_m) * resolution_m
    levels = np.unique(h)[::-1]
    if levels.size - 1 > max_layers:
        raise DoeError(f"the relief has {levels.size} distinct heights; the rigorous model slices at most "
                       f"{max_layers + 1}: quantize the design to levels first")
    patterns = [h >= top for top in levels[:-1]]
    return patterns, [float(a - b) for a, b in zip(levels[:-1], levels[1:])]


def _expansion(fmmax, shape, n_terms):
    rows, cols = shape
    if rows == 1:
        half = max(1, (n_terms - 1) // 2)
        m = sorted(range(-half, half + 1), key=lambda v: (abs(v), v))
        return fmmax.Expansion(basis_coefficients=np.array([(v, 0) for v in m], dtype=int))
    if cols == 1:
        half = max(1, (n_terms - 1) // 2)
        m = sorted(range(-half, half + 1), key=lambda v: (abs(v), v))
        return fmmax.Expansion(basis_coefficients=np.array([(0, v) for v in m], dtype=int))
    lattice = fmmax.LatticeVectors(u=cols * fmmax.X, v=rows * fmmax.Y)
    return fmmax.generate_expansion(primitive_lattice_vectors=lattice, approximate_num_terms=int(n_terms),
                                    truncation=fmmax.Truncation.CIRCULAR)


def rigorous_efficiencies(height_m: np.ndarray, pitch_m: float, wavelengths_m: ArrayLike, index: IndexLike,
                          n_terms: int = DEFAULT_TERMS, incidence: str = "substrate", formulation: str = "jones_direct_fourier",
                          index_gap: complex = 1.0) -> RigorousResult:
    """Transmitted efficiencies of one period of a surface relief, by the Fourier modal method.

    Parameters
    ----------
    height_m : ndarray (rows, cols)
        One period (z up, 0 at the top, negative etched; row 0 at the top). One row makes a
        1-D grating along x.
    pitch_m : float
        Pixel pitch; the period is ``cols * pitch_m`` by ``rows * pitch_m``.
    wavelengths_m : sequence of float
    index : float, complex or callable
        Refractive index of the relief and substrate, or ``index(wavelength_m)``.
    n_terms : int
        Fourier terms (approximate for 2-D, circular truncation); more converge better.
    incidence : {"substrate", "air"}
        The side the plane wave comes from (module docstring).
    formulation : str
        An ``fmmax.Formulation`` name (``fft``, ``jones_direct_fourier``, ...).
    index_gap : complex
        Index outside the glass (air, 1).

    Returns
    -------
    RigorousResult
    """
    if incidence not in INCIDENCES:
        raise DoeError(f"incidence must be one of {', '.join(INCIDENCES)}, got {incidence!r}")
    height_m = np.asarray(height_m, dtype=np.float64)
    if height_m.ndim != 2 or height_m.size == 0:
        raise DoeError(f"the rigorous model needs a 2-D height map, got shape {height_m.shape}")
    n_terms = int(n_terms)
    if n_terms < 1:
        raise DoeError(f"n_terms must be at least 1, got {n_terms}")
    patterns, thick_m = relief_layers(height_m)
    # Each layer's eigenproblem is a dense complex matrix of 2 n_terms squared, several held at once.
    check_memory(16 * (2 * n_terms) ** 2 * 8 * (len(patterns) + 2) + 64 * height_m.size * (len(patterns) + 2),
                 f"rigorous model of a {height_m.shape[0]} x {height_m.shape[1]} px period with {n_terms} terms "
                 f"and {len(patterns)} layers")
    jax, fmmax = _solver()
    import jax.numpy as jnp

    try:
        form = fmmax.Formulation[formulation.upper()]
    except KeyError:
        raise DoeError(f"unknown formulation {formulation!r}; one of "
                       f"{', '.join(f.name.lower() for f in fmmax.Formulation)}") from None
    rows, cols = height_m.shape
    um = 1e6  # lengths in micrometres inside the solver, numbers near 1
    lattice = fmmax.LatticeVectors(u=cols * pitch_m * um * fmmax.X, v=rows * pitch_m * um * fmmax.Y)
    expansion = _expansion(fmmax, (rows, cols), n_terms)
    n = expansion.num_terms
    # fmmax needs at least 2 max|order| + 1 samples per axis: repeat pixels by whole factors
    # (the same geometry, finer sampling).
    need_x, need_y = fmmax.min_array_shape_for_expansion(expansion)
    rep_x, rep_y = -(-need_x // cols), -(-need_y // rows)
    patterns = [np.repeat(np.repeat(p, rep_y, axis=0), rep_x, axis=1) for p in patterns]
    wls = np.atleast_1d(np.asarray(wavelengths_m, dtype=np.float64))
    eff = np.zeros((wls.size, 2, n))

    # One compiled eigensolve per array shape: the layers of a relief share one, which saves
    # JAX's per-operation dispatch on every layer.
    @jax.jit
    def solve(perm, wl_um, k_in):
        return fmmax.eigensolve_isotropic_media(wavelength=wl_um, in_plane_wavevector=k_in,
                                                primitive_lattice_vectors=lattice, permittivity=perm,
                                                expansion=expansion, formulation=form)

    for wi, wl in enumerate(wls):
        n_glass = complex(index(float(wl)) if callable(index) else index)
        eps_glass, eps_gap = n_glass ** 2, complex(index_gap) ** 2
        # fmmax arrays are (x, y): columns first, so the pattern is transposed.
        slabs = [jnp.asarray(np.where(p.T, eps_glass, eps_gap)) for p in patterns]
        # A uniform slice (every pixel glass or none) solves as a uniform layer.
        slabs = [s[:1, :1] if bool(jnp.all(s == s[0, 0])) else s for s in slabs]
        if incidence == "substrate":
            perms = [jnp.full((1, 1), eps_glass)] + slabs[::-1] + [jnp.full((1, 1), eps_gap)]
            thick = [0.0] + thick_m[::-1] + [0.0]
        else:
            perms = [jnp.full((1, 1), eps_gap)] + slabs + [jnp.full((1, 1), eps_glass)]
            thick = [0.0] + thick_m + [0.0]
        t = stack_efficiency(perms, [d * um for d in thick], wl * um, lattice, expansion, form, solve)
        t = np.asarray(t)
        eff[wi] = t.T
    orders = np.asarray(expansion.basis_coefficients, dtype=int).copy()
    # fmmax's second coordinate runs with the array's second axis: rows downward; report q upward.
    orders[:, 1] = -orders[:, 1]
    return RigorousResult(orders, wls, eff, n,
                          dict(incidence=incidence, formulation=form.name.lower(), layers=len(patterns)))


def stack_efficiency(permittivities: list, thicknesses_um: list, wavelength_um: float, lattice: Any, expansion: Any,
                     formulation: Any, solve: Callable | None = None, batch_layers: bool = False) -> Any:
    """Transmitted efficiency of a layer stack at normal incidence, per order and polarization.

    The one place where this tool calls fmmax's eigensolves, scattering matrix and fluxes:
    :func:`rigorous_efficiencies` calls it on a sliced height map, and the rigorous design
    objective (:mod:`doedesign.optimizer.rigorous_objective`) on continuous densities. It is
    traceable by JAX, so ``jax.grad`` of anything computed from it is the adjoint gradient.

    Parameters
    ----------
    permittivities : list of arrays (x, y)
        Incident medium first, exit medium last; a ``(1, 1)`` array is a uniform layer. fmmax's
        arrays are (x, y): columns first.
    thicknesses_um : list of float
        One per layer (the first and last are not used: half-spaces).
    wavelength_um : float
    lattice : fmmax.LatticeVectors
        The period, in micrometres.
    expansion : fmmax.Expansion
    formulation : fmmax.Formulation
    solve : callable, optional
        ``solve(permittivity, wavelength_um, in_plane_wavevector)``, e.g. a jitted eigensolve
        shared by the layers of one shape; fmmax's ``eigensolve_isotropic_media`` if None.
    batch_layers : bool
        Solve the layers of one array shape in one call (their permittivities stacked on a
        leading axis, ``_layer_solves``) instead of one call per layer: inside ``jax.jit``
        one eigensolve is traced and compiled whatever the layer count. The same numbers.

    Returns
    -------
    jax array (n_terms, 2)
        Transmitted Poynting flux per order (the two exit polarizations summed) over the
        incident flux, for the te (column 0) and tm (column 1) incident wave.
    """
    _, fmmax = _solver()
    import jax.numpy as jnp

    if solve is None:
        def solve(perm, wl, k):
            return fmmax.eigensolve_isotropic_media(wavelength=wl, in_plane_wavevector=k,
                                                    primitive_lattice_vectors=lattice, permittivity=perm,
                                                    expansion=expansion, formulation=formulation)
    n = expansion.num_terms
    wl_um = jnp.asarray(wavelength_um)
    k_in = fmmax.plane_wave_in_plane_wavevector(wavelength=wl_um, polar_angle=jnp.asarray(0.0),
                                                azimuthal_angle=jnp.asarray(0.0),
                                                permittivity=jnp.asarray(permittivities[0]).reshape(-1)[0])
    solves = _layer_solves(permittivities, solve, wl_um, k_in) if batch_layers else \
        [solve(p, wl_um, k_in) for p in permittivities]
    s = fmmax.stack_s_matrix(layer_solve_results=solves, layer_thicknesses=[jnp.asarray(t) for t in thicknesses_um])
    a_in = jnp.zeros((2 * n, 2), dtype=complex).at[0, 0].set(1.0).at[n, 1].set(1.0)
    inc_fwd, _ = fmmax.amplitude_poynting_flux(forward_amplitude=a_in, backward_amplitude=s.s21 @ a_in,
                                               layer_solve_result=solves[0])
    out, _ = fmmax.amplitude_poynting_flux(forward_amplitude=s.s11 @ a_in, backward_amplitude=jnp.zeros_like(a_in),
                                           layer_solve_result=solves[-1])
    return (out[:n] + out[n:]).real / jnp.sum(inc_fwd, axis=0).real


def _layer_solves(permittivities: list, solve: Callable, wavelength_um: Any, k_in: Any) -> list:
    """One eigensolve per array shape: the layers of that shape stacked on a leading batch axis.

    fmmax's eigensolves take leading batch dimensions; the batched result is split back into
    one ``LayerSolveResult`` per layer (without its tangent vector field, which the scattering
    matrix does not use) in the order of ``permittivities``.
    """
    import dataclasses

    import jax
    import jax.numpy as jnp

    _, fmmax = _solver()
    groups: dict[tuple, list[int]] = {}
    for i, p in enumerate(permittivities):
        groups.setdefault(tuple(jnp.shape(p)), []).append(i)
    solves: list = [None] * len(permittivities)
    for idx in groups.values():
        if len(idx) == 1:
            solves[idx[0]] = solve(permittivities[idx[0]], wavelength_um, k_in)
            continue
        res = solve(jnp.stack([jnp.asarray(permittivities[i]) for i in idx]), wavelength_um, k_in)
        res = fmmax.broadcast_result(dataclasses.replace(res, tangent_vector_field=None), (len(idx),))
        for b, i in enumerate(idx):
            solves[i] = jax.tree_util.tree_map(lambda x, b=b: x[b], res)
    return solves


def thin_element_efficiencies(height_m: np.ndarray, wavelengths_m: ArrayLike, index: IndexLike,
                              orders: np.ndarray) -> np.ndarray:
    """Thin-element efficiencies ``(w, k)`` of one period at the given ``orders`` (p, q).

    Each pixel a flat phase ``2 pi (n - 1) h / lambda`` (the PSF engine's pixel model): order
    ``(p, q)`` carries ``|DFT / N|^2 sinc^2(p / cols) sinc^2(q / rows)``; propagation cut-off is
    not applied (the caller compares propagating orders).
    """
    h = np.asarray(height_m, dtype=np.float64)
    rows, cols = h.shape
    orders = np.asarray(orders, dtype=int)
    wls = np.atleast_1d(np.asarray(wavelengths_m, dtype=np.float64))
    out = np.zeros((wls.size, orders.shape[0]))
    for wi, wl in enumerate(wls):
        n_glass = complex(index(float(wl)) if callable(index) else index).real
        field_ = np.exp(2j * np.pi * (n_glass - 1.0) * h / wl)
        # Row 0 is the top: order q (toward the top) is DFT index -q along the rows.
        coeff = np.fft.fft2(field_) / h.size
        p, q = orders[:, 0], orders[:, 1]
        c = coeff[(-q) % rows, p % cols]
        out[wi] = np.abs(c) ** 2 * np.sinc(p / cols) ** 2 * np.sinc(q / rows) ** 2
    return out


def compare(result: RigorousResult, thin: np.ndarray, polarization: str = "unpolarised",
            min_efficiency: float = 1e-3) -> dict:
    """Rigorous beside thin-element efficiencies, per wavelength.

    Returns per wavelength: the orders where either model has at least ``min_efficiency``, the
    absolute rigorous efficiencies, the rigorous efficiencies over the transmitted total
    (``rigorous_relative``), the thin-element ones and the largest absolute difference between
    the relative and the thin-element values (``max_difference``).
    """
    eff = result.polarized(polarization)
    rows = []
    for wi, wl in enumerate(result.wavelengths_m):
        total = float(eff[wi].sum())
        rel = eff[wi] / total if total > 0 else eff[wi]
        keep = np.flatnonzero((eff[wi] >= min_efficiency) | (thin[wi] >= min_efficiency))
        keep = keep[np.argsort(-np.maximum(rel[keep], thin[wi][keep]))]
        diff = np.abs(rel - thin[wi])
        rows.append(dict(
            wavelength_nm=float(wl * 1e9), transmitted=total,
            max_difference=float(diff[keep].max()) if keep.size else 0.0,
            orders=[dict(order=[int(result.orders[k, 0]), int(result.orders[k, 1])], rigorous=float(eff[wi, k]),
                         rigorous_relative=float(rel[k]), thin_element=float(thin[wi, k])) for k in keep]))
    return dict(polarization=polarization, wavelengths=rows)


def smallest_feature_m(height_m: np.ndarray, pitch_m: float, periodic: bool = True) -> float:
    """The narrowest run of equal heights along rows or columns, in metres (pitch if none)."""
    h = np.asarray(height_m)
    best = None
    for arr in (h, h.T):
        if arr.shape[1] < 2:
            continue
        for row in arr:
            edges = np.flatnonzero(row != np.roll(row, -1)) if periodic else np.flatnonzero(np.diff(row) != 0)
            if edges.size >= 2:
                runs = np.diff(np.concatenate([edges, [edges[0] + row.size]])) if periodic else np.diff(edges)
                if runs.size:
                    best = int(runs.min()) if best is None else min(best, int(runs.min()))
    return float((best or 1) * pitch_m)


def validity(smallest_feature: float, depth_m: float, wavelengths_m: ArrayLike) -> dict:
    """Where the thin-element model holds: feature over wavelength and depth over feature.

    Parameters
    ----------
    smallest_feature : float
        Smallest lateral feature (m): the pixel pitch, or :func:`smallest_feature_m`.
    depth_m : float
        Deepest etch (m).
    wavelengths_m : sequence of float

    Returns
    -------
    dict
        ``feature_over_wavelength`` (at the longest wavelength), ``depth_over_feature``, the limits
        and ``holds`` (True where both are within the limits), with a sentence.
    """
    wl = float(np.max(np.atleast_1d(wavelengths_m)))
    fw = smallest_feature / wl
    df = abs(depth_m) / smallest_feature
    holds = bool(fw >= FEATURE_MIN_WAVELENGTHS and df <= DEPTH_MAX_FEATURES)
    text = (f"smallest feature {smallest_feature * 1e6:.3g} um = {fw:.3g} wavelengths at {wl * 1e9:.0f} nm, "
            f"depth {abs(depth_m) * 1e9:.0f} nm = {df:.3g} features: the thin-element model "
            + ("holds (limits: feature >= {:g} wavelengths, depth <= {:g} features)" if holds else
               "is outside its limits (feature >= {:g} wavelengths, depth <= {:g} features); check with doe rigorous")
            .format(FEATURE_MIN_WAVELENGTHS, DEPTH_MAX_FEATURES))
    return dict(feature_over_wavelength=fw, depth_over_feature=df, feature_min_wavelengths=FEATURE_MIN_WAVELENGTHS,
                depth_max_features=DEPTH_MAX_FEATURES, holds=holds, statement=text)


def score_design(height_m: np.ndarray, pitch_m: float, material: str, wavelengths_m: ArrayLike, n_terms: int = DEFAULT_TERMS,
                 polarization: str = "unpolarised", incidence: str = "substrate",
                 tolerance: float = DEFAULT_TOLERANCE, formulation: str = "jones_direct_fourier") -> dict:
    """Rigorous and thin-element efficiencies of one period of a design, with the verdict.

    Parameters
    ----------
    height_m : ndarray (rows, cols)
        One period of the element (row 0 at the top).
    pitch_m : float
    material : str
        Registry name (:mod:`doedesign.materials`): the relief's and substrate's index.
    wavelengths_m : sequence of float
    n_terms, polarization, incidence, formulation
        See :func:`rigorous_efficiencies` and :func:`compare`.
    tolerance : float
        Largest difference in any order's efficiency that passes without a warning.

    Returns
    -------
    dict
        ``validity`` (:func:`validity`), ``comparison`` (:func:`compare`), ``warnings`` (one line per
        wavelength where the two models disagree by more than ``tolerance``) and the settings.
    """
    from .materials import get_material

    mat = get_material(material)
    wls = np.atleast_1d(np.asarray(wavelengths_m, dtype=np.float64))
    result = rigorous_efficiencies(height_m, pitch_m, wls, mat.n, n_terms, incidence, formulation)
    thin = thin_element_efficiencies(height_m, wls, mat.n, result.orders)
    comp = compare(result, thin, polarization)
    depth = float(np.max(height_m) - np.min(height_m))
    feature = smallest_feature_m(height_m, pitch_m)
    warnings = [f"at {w['wavelength_nm']:.1f} nm the rigorous and thin-element efficiencies differ by "
                f"{w['max_difference']:.3f} (more than {tolerance:g}) in some order"
                for w in comp["wavelengths"] if w["max_difference"] > tolerance]
    return dict(period_px=list(np.shape(height_m)), pitch_m=float(pitch_m), material=material,
                n_terms=result.n_terms, incidence=incidence, formulation=result.settings["formulation"],
                layers=result.settings["layers"], tolerance=float(tolerance), depth_m=depth,
                validity=validity(feature, depth, wls), comparison=comp, warnings=warnings)
