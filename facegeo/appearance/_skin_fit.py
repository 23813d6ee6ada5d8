"""Fitting the paper's skin model to measured reflectance functions (Debevec et al. 2000, §4.2, §4.4).

Private module behind :mod:`facegeo.appearance.skin`. Everything is vectorised over chunks of
reflectance functions: the coarse-to-fine direct searches evaluate every candidate of every
function of a chunk in one numpy expression.
"""

from __future__ import annotations

import functools
import logging
import warnings
from dataclasses import dataclass

import numpy as np

from facegeo.appearance._skin_model import (
    S_WHITE,
    SINGULAR_SIN2,
    LightSet,
    normalize,
    ramp_f_from_x,
)
from facegeo.appearance.brdf import fresnel_dielectric, torrance_sparrow_geometry
from facegeo.checks import as_array, check_unit_vectors, fmt_value
from facegeo.errors import InputError, ShapeError

log = logging.getLogger(__name__)

# flags (bit mask per reflectance function)
FLAG_BLACK = 1  #: no light reaches the camera: parameters are fallbacks (normal = view)
FLAG_SINGULAR = 2  #: diffuse colour ≈ light colour: separation fell back to diffuse only
FLAG_SHADOWED = 4  #: fewer than MIN_SAMPLES unshadowed samples: normal is the fallback
FLAG_SATURATED = 8  #: some samples were saturated and masked out
FLAG_SINGLE_CHANNEL = 16  #: single-channel input: diffuse lobe only, no colour separation
FLAG_GRAZING_VIEW = 32  #: n·v below GRAZING_COS: the view grazes the surface
FLAG_SPECULAR_IN_SHADOW = 64  #: resynthesis: some specular samples came from shadowed lights
FLAG_SPECULAR_SKIPPED = 128  #: resynthesis: negligible specular energy, specular not modelled
FLAG_BACKFACING = 256  #: resynthesis: the novel view is at or below the surface's horizon
#: some samples were masked by the caller (untrusted pixels: black-clipped, saturated or
#: non-finite, e.g. the projected field's NaN samples) and left out
FLAG_MASKED = 512
#: the fitted chromaticity ramp left Eq. 6's physical range (:func:`physical_ramp`): refitted
#: without it (α_0 = α_1 = 0, the representative chromaticity d_0 at every angle)
FLAG_RAMP_REJECTED = 1024

FLAG_NAMES = {
    FLAG_BLACK: "black", FLAG_SINGULAR: "singular", FLAG_SHADOWED: "shadowed",
    FLAG_SATURATED: "saturated", FLAG_SINGLE_CHANNEL: "single_channel",
    FLAG_GRAZING_VIEW: "grazing_view", FLAG_SPECULAR_IN_SHADOW: "specular_in_shadow",
    FLAG_SPECULAR_SKIPPED: "specular_skipped", FLAG_BACKFACING: "backfacing",
    FLAG_MASKED: "masked", FLAG_RAMP_REJECTED: "ramp_rejected",
}

#: Minimum number of unshadowed, unsaturated samples for a lobe fit.
MIN_SAMPLES = 3
#: Cosine below which a view counts as grazing (85°).
GRAZING_COS = np.cos(np.radians(85.0))
#: Brightness range, as fractions of the function's 90th-percentile brightness, whose samples
#: give the initial diffuse chromaticity d_0 (§4.2: "values falling in a certain brightness range").
D0_BRIGHTNESS_RANGE = (0.25, 1.0)
#: Shadow map threshold (§4.4): a sample darker than this fraction of the function's
#: 99th-percentile brightness is shadowed.
SHADOW_THRESHOLD = 0.02
#: Angular scale of the mirror down-weighting in the ramp fit: weight 1 − exp(−(1 − l·r)/σ),
#: σ = 1 − cos(15°).
MIRROR_SIGMA = 1.0 - np.cos(np.radians(15.0))
#: Chromaticity rows of the ramp's second polish (``fit_ramp``): weights
#: ``(1 − exp(−(1 − l·r)/σ_c))^p`` with σ_c = 1 − cos 60°, p = 4 — samples within ≈ 45° of the
#: mirror direction barely count, where the mirror weight above (15°) still lets specular
#: tails through (measured on the small preset: 15°, p = 1 gave normals 0.63°, albedo 2.8 %,
#: resynthesis 5.6× / 4.8× better than naive; 60°, p = 4: 0.08°, 2.3 %, 7.0× / 6.3×).
CHROMA_SIGMA = 1.0 - np.cos(np.radians(60.0))
#: The second polish runs only where its weight λ = chroma × (lobe misfit after the first
#: polish) exceeds this: below it the chromaticity rows cannot move the minimum measurably
#: (paper-mode data: λ ≈ 1e-12 with d_0 known, ≲ 1e-7 estimated; the generator: 1e-4–1e-2).
CHROMA_MIN_WEIGHT = 1e-6


def chroma_weights(cos_lr):
    """Weights of the ramp's chromaticity rows (:func:`fit_ramp`):
    ``(1 − exp(−(1 − l·r)/σ_c))⁴`` for ``cos_lr = l·r`` (r the mirror direction), any shape;
    σ_c = :data:`CHROMA_SIGMA`."""
    t = 1.0 - np.exp(-(1.0 - cos_lr) / CHROMA_SIGMA)
    t *= t
    t *= t
    return t


def ramp_mu_s(p, xcos, A, B):
    """μ_s of §4.2 under candidate ramps, in closed form (as :func:`ramp_mu_d`).

    With e ⊥ s, ``R·s = μ_d (c·s) + μ_s``; with μ_d of :func:`ramp_mu_d` and
    ``c·s = (g d_0·s − f)/|u|`` this is ``μ_s = B + A f/g``, ``B = R·s − A (d_0·s)``,
    ``g = 1 + f``. 0 where ``|g| ≤ 1e-6`` (the chromaticity reaches s: singular, no row).

    Parameters
    ----------
    p : (n, K, ≥2) float64, candidates (α_0, α_1, ...)
    xcos : (n, K or 1, L) float64, ``clip(n·l) clip(n·v)``
    A, B : (n, L) float64

    Returns
    -------
    (n, K, L) float64
    """
    f = ramp_f_from_x(xcos, p[..., 0:1], p[..., 1:2])
    g = 1.0 + f
    ok = np.abs(g) > 1e-6
    return np.where(ok, B[:, None, :] + A[:, None, :] * f / np.where(ok, g, 1.0), 0.0)


@dataclass(frozen=True)
class SearchDepth:
    """Depth of the coarse-to-fine direct searches.

    Attributes
    ----------
    levels : int
        Step halvings (the search's depth); precision ≈ initial step / 2**levels.
    moves : int
        Compass moves per level.
    normal_step : float, radians
        Initial step of the normal search (tangent-plane offset).
    alpha_step : float
        Initial step of α_0, α_1 (and of the d_0 shift along the d_0–s line).
    alpha_levels : int
        Step halvings of the (α_0, α_1) search, which only has to land in the polish's basin.
    polish : int
        Levenberg–Marquardt iterations after the ramp search (0: search only).
    polish_normal : bool
        Polish the normal together with α_0, α_1 (exact recovery on paper-mode data); off,
        the ramp is polished at the searched normal. Deviation from the
        paper's pure direct search: the ramp's three coordinates form a long shallow valley
        that a pattern search crawls along; a few Gauss–Newton steps reach the bottom.
    chroma : float
        κ of the ramp's chromaticity rows (:func:`fit_ramp`): after the polish, functions whose
        lobe misfit M stays above ``CHROMA_MIN_WEIGHT / κ`` are polished again from the
        search's result with ``κ M Σ w_c μ_s² / Σ w_c |R|²`` added — the paper's fit to the
        observed chromaticities, weighted by how much the lobe criterion leaves undecided.
        0: the lobe criterion alone (the behaviour before issue 13's fix).
    sample_lights : int
        With more than twice this many lights, the fit's starts (initial separation, moment
        normal, first lobe fit), the ramp's search and both polishes use an even subsample of
        at least this many (:func:`light_subsample`); then ``finish`` iterations on all lights
        take the subsample's minimum to all lights' (a one-step estimator: from inside the
        basin one Gauss–Newton step lands where the all-lights fit does, to a small fraction
        of its noise error; tested), and the final separation and lobe fit use all lights.
        0: all lights throughout. Deviation for speed (issue 13's 200 k functions a minute):
        five parameters need far fewer than 2048 samples to reach their minimum's basin.
    finish : int
        Levenberg–Marquardt iterations on all lights after the subsample's polishes (a
        function stops earlier once its step is below ``POLISH_XTOL``).
    """

    levels: int = 10
    moves: int = 3
    normal_step: float = 0.1
    alpha_step: float = 0.25
    polish: int = 10
    alpha_levels: int = 4
    polish_normal: bool = True
    chroma: float = 300.0
    sample_lights: int = 512
    finish: int = 1


def light_subsample(lights: LightSet, at_least: int) -> np.ndarray | None:
    """An even subsample of ``lights`` with at least ``at_least`` lights, as an ``(L,)`` bool
    mask; None when the set has at most twice that many (or ``at_least`` ≤ 0).

    On the light-stage grid every s-th azimuth of every s-th inclination (docs/conventions.md
    light index ``l = j·n_theta + i``), s the largest stride that keeps ``at_least`` lights:
    2048 lights (64 × 32) → 512 (32 × 16). A free list keeps every s-th light in its order.
    """
    k = int(at_least)
    L = lights.n_lights
    if k <= 0 or L <= 2 * k:
        return None
    if lights.grid is not None:
        n_theta, n_phi = lights.grid
        s = 1
        while -(-n_theta // (s + 1)) * -(-n_phi // (s + 1)) >= k:
            s += 1
        if s < 2:
            return None
        idx = np.arange(L)
        return (idx % n_theta % s == 0) & (idx // n_theta % s == 0)
    return np.arange(L) % (L // k) == 0


def direct_search(objective, x0: np.ndarray, step0, levels: int, moves: int, *,
                  pattern: str = "grid", subset: bool = False):
    """Coarse-to-fine compass search, vectorised over N problems.

    Pattern search: each iteration evaluates the candidates of the pattern around the centre
    (``"grid"``: every point of {−1, 0, 1}^P × step, 3^P candidates, which follows diagonal
    valleys; ``"compass"``: the centre and ±step along each axis, 2P + 1 candidates), move to
    the best (one call of ``objective`` per iteration); a problem whose centre stays best
    halves its step. Runs until every problem has halved ``levels`` times or after
    ``levels · moves`` iterations. Ties keep the centre.

    With ``subset=True`` a problem stops as soon as its centre stays best at the finest step
    ``step0 / 2**levels`` (it is converged to the requested precision) and
    ``objective(cand, rows)`` is called with only the problems still searching (``rows``: their
    indices into the N problems, ``cand`` ``(len(rows), K, P)``); without it, finished problems
    keep taking finest-step moves until all have finished, and every problem is evaluated
    every iteration (the same minimum to within the finest step, at more cost).

    Parameters
    ----------
    objective : callable ``(N, K, P) -> (N, K)`` (``subset``: ``(cand, rows) -> (n, K)``)
        Non-finite values count as +inf.
    x0 : (N, P) float64
    step0 : (P,) float64
    levels, moves : int

    Returns
    -------
    x : (N, P) float64
    value : (N,) float64
        Objective at x.
    """
    x = np.array(x0, dtype=np.float64)
    N, P = x.shape
    step = np.broadcast_to(np.asarray(step0, np.float64), (P,))
    step = np.tile(step, (N, 1))
    if pattern == "compass":
        offs = np.concatenate([np.zeros((1, P)), np.eye(P), -np.eye(P)])
    elif pattern == "grid":
        offs = np.stack(np.meshgrid(*([[0.0, -1.0, 1.0]] * P), indexing="ij"), -1).reshape(-1, P)
    else:
        raise ValueError(f"pattern: expected 'grid' or 'compass', got {fmt_value(pattern)}")
    val = np.full(N, np.inf)
    halvings = np.zeros(N, np.int64)
    for _ in range(levels * moves):
        act = np.flatnonzero(halvings <= levels) if subset else np.arange(N)
        if act.size == 0 or (not subset and np.all(halvings >= levels)):
            break
        cand = x[act, None, :] + offs[None] * step[act, None, :]
        f = np.asarray(objective(cand, act) if subset else objective(cand), np.float64)
        f = np.where(np.isfinite(f), f, np.inf)
        best = np.argmin(f, axis=1)
        k = np.arange(act.size)
        x[act] = cand[k, best]
        val[act] = f[k, best]
        stay = (best == 0) & (halvings[act] < levels + int(subset))
        step[act[stay]] *= 0.5
        halvings[act[stay]] += 1
    return x, val


def _tangent_basis(n):
    """Two unit vectors ``(N, 3)`` orthogonal to ``n`` and to each other."""
    if KERNELS:
        from facegeo.appearance._skin_kernels_samples import tangent_basis

        return tangent_basis(np.ascontiguousarray(n, np.float64))
    a = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = normalize(np.cross(n, a))
    t2 = np.cross(n, t1)
    return t1, t2


def _lobe_misfit(y, w, x):
    """Relative weighted misfit of ``y ≈ k x`` with the best k ≥ 0: ``1 − <y,x>²/(|y|²|x|²)``.

    ``y`` ``(N, [K,] L)``, ``w`` ``(N, L)``, ``x`` broadcastable; sums over the last axis.
    """
    if y.ndim == 3:
        w = w[:, None, :]
    syy = np.sum(w * y * y, axis=-1)
    sxy = np.sum(w * y * x, axis=-1)
    sxx = np.sum(w * x * x, axis=-1)
    ok = (sxx > 1e-300) & (syy > 1e-300) & (sxy > 0)
    den = np.where(ok, sxx * syy, 1.0)
    return np.where(ok, 1.0 - sxy * sxy / den, 1.0)


def _misfit_from_sums(syy, sxy, sxx):
    """:func:`_lobe_misfit` from its three weighted sums (any broadcastable shapes)."""
    ok = (sxx > 1e-300) & (syy > 1e-300) & (sxy > 0)
    den = np.where(ok, sxx * syy, 1.0)
    return np.where(ok, 1.0 - sxy * sxy / den, 1.0)


def _lobe_residuals(y, w, x):
    """Residual vector whose squared sum is :func:`_lobe_misfit`: ``√w (y − k x)/√(Σ w y²)``."""
    if y.ndim == 3:
        w = w[:, None, :]
    syy = np.sum(w * y * y, axis=-1, keepdims=True)
    sxy = np.sum(w * y * x, axis=-1, keepdims=True)
    sxx = np.sum(w * x * x, axis=-1, keepdims=True)
    ok = (sxx > 1e-300) & (syy > 1e-300) & (sxy > 0)
    k = np.where(ok, sxy / np.where(ok, sxx, 1.0), 0.0)
    return np.sqrt(w) * (y - k * x) / np.sqrt(np.where(syy > 1e-300, syy, 1.0))


def _lobe_residuals_sqrtw(y, sqw, x):
    """:func:`_lobe_residuals` for ``y`` ``(N, K, L)``, ``x`` ``(N, K or 1, L)`` with ``√w``
    ``(N, L)`` given. ``y`` is overwritten (callers pass a fresh array)."""
    yw = np.multiply(y, sqw[:, None, :], out=y)
    xw = x * sqw[:, None, :]
    syy = np.einsum("nkl,nkl->nk", yw, yw)[..., None]
    sxy = np.einsum("nkl,nkl->nk", yw, np.broadcast_to(xw, yw.shape))[..., None]
    sxx = np.einsum("nkl,nkl->nk", xw, xw)[..., None]
    ok = (sxx > 1e-300) & (syy > 1e-300) & (sxy > 0)
    k = np.where(ok, sxy / np.where(ok, sxx, 1.0), 0.0)
    yw -= k * xw
    yw /= np.sqrt(np.where(syy > 1e-300, syy, 1.0))
    return yw


#: Run the searches and the polish in the compiled kernels of ``_skin_kernels`` (numba; serial
#: loops over a chunk's functions, chunks spread over Python threads). False: the numpy reference below, which the kernels are
#: tested against.
KERNELS = True

#: Jacobian of the ramp's Levenberg–Marquardt polish by forward differences (P + 1 residual
#: evaluations per step, the centre's reused) instead of central ones (2P): measured ≈ 1.2–1.3×
#: faster fit with α's within 1e-5 and ρ_s within 2e-4 relative of the central-difference
#: polish, normals identical (128 paper-mode functions; docs/skin.md).
POLISH_FORWARD = True


#: The compiled polish (``_skin_kernels.ramp_polish``) stops a function once a proposed step
#: moves no parameter (α_0, α_1, tangent offsets of the normal) by more than this and was
#: rejected or taken undamped: converged, further steps only move it by rounding. Measured
#: (2048 lights, 512 functions): paper mode converges in 4–5 of the 10 iterations, the second
#: (chromaticity) polish on generator data in 6–8; results within 1e-8 of all 10 iterations
#: (docs/skin.md). 0 keeps every iteration (the numpy reference always does).
POLISH_XTOL = 1e-9


def gauss_newton_polish(residuals, x0, *, iterations: int = 8, h: float = 1e-5,
                        forward: bool = False):
    """Levenberg–Marquardt polish of N small least-squares problems at once.

    ``residuals(cand (N, K, P)) -> (N, K, M)``; the Jacobian is taken by central differences
    (the 2P offsets in one call), or with ``forward=True`` by forward differences (P offsets;
    O(h) less accurate, which moves the converged point only by ~h × the residual); the
    centre's residuals are kept from the previous step. A
    step is kept only where it lowers the sum of squares, so the polish never makes a search
    result worse. The P × P normal equations of all problems are one batched
    ``np.linalg.solve`` on ``(n, P, P)``.

    Every problem takes all ``iterations`` steps: stopping problems whose sum of squares no
    longer falls (tried) changed α's by up to 0.3 along the ramp's flat valley when d_0 is
    estimated, for ≈ 10 % speed. (The compiled polish stops a problem only once its steps are
    below :data:`POLISH_XTOL`, which moves α's by < 1e-8.)

    Returns ``(x (N, P), value (N,))``.
    """
    x = np.array(x0, dtype=np.float64)
    N, P = x.shape
    offs = h * np.eye(P) if forward else np.concatenate([h * np.eye(P), -h * np.eye(P)])
    lam = np.full(N, 1e-8)
    r = residuals(x[:, None, :])[:, 0]
    val = np.sum(r * r, axis=-1)
    for _ in range(iterations):
        rr = residuals(x[:, None, :] + offs[None])
        if forward:
            J = (rr - r[:, None, :]) / h  # (n, P, M)
        else:
            J = (rr[:, :P] - rr[:, P:]) / (2.0 * h)
        JtJ = J @ np.swapaxes(J, 1, 2)
        g = (J @ r[..., None])[..., 0]
        A = JtJ + lam[:, None, None] * (np.eye(P) * np.maximum(
            np.einsum("npp->np", JtJ), 1e-30)[:, None, :])
        try:
            dx = -np.linalg.solve(A, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        dx = np.where(np.isfinite(dx), dx, 0.0)
        xn = x + dx
        rn = residuals(xn[:, None, :])[:, 0]
        vn = np.sum(rn * rn, axis=-1)
        better = np.isfinite(vn) & (vn < val)
        x = np.where(better[:, None], xn, x)
        r = np.where(better[:, None], rn, r)
        val = np.where(better, vn, val)
        lam = np.where(better, lam * 0.1, lam * 10.0)
    return x, val


def moment_normal(y, w, lights: LightSet, fallback):
    """Closed-form normal from the first moment ``Σ_l D(ω_l) ω_l δA_l`` (Ma et al. 2007).

    What spherical gradient illumination measures: for a clamped Lambertian lobe over the full
    sphere the moment is parallel to n. Light sets covering part of the sphere, or masked
    (shadowed) samples, bias it — the lobe search corrects that.

    Parameters
    ----------
    y : (N, L) float64, diffuse brightness
    w : (N, L) float64, 0/1 mask of usable samples
    lights : LightSet
    fallback : (N, 3) float64, unit, used where the moment vanishes

    Returns
    -------
    (N, 3) float64, unit
    """
    if KERNELS:
        from facegeo.appearance._skin_kernels_samples import moment_normal as kernel

        c = np.ascontiguousarray
        return kernel(c(y, np.float64), c(w, np.float64), c(lights.solid_angles),
                      c(lights.directions), c(np.broadcast_to(fallback, y.shape[:1] + (3,)),
                                              np.float64))
    m = (y * w * lights.solid_angles) @ lights.directions
    nrm = np.linalg.norm(m, axis=1, keepdims=True)
    ok = nrm > 1e-300
    return np.where(ok, m / np.where(ok, nrm, 1.0), fallback)


def fit_lambertian_lobe(y, w, lights: LightSet, n_start, depth: SearchDepth):
    """Lambertian-lobe fit ``y_l ≈ k max(0, n·l)`` by coarse-to-fine direct search (§4.2).

    Minimises the relative weighted misfit (weights ``w δA``) over n, with the best k ≥ 0 in
    closed form for each candidate; the search moves n in its tangent plane around
    ``n_start`` (Debevec et al. 2000 §4.2: "fit a Lambertian lobe to the diffuse component,
    using a coarse-to-fine direct search").

    Returns
    -------
    n : (N, 3) float64, unit
    k : (N,) float64, the lobe's scale (= albedo / π for a Lambertian surface)
    misfit_start, misfit : (N,) float64
        Relative misfit at ``n_start`` and at the result.
    """
    if KERNELS:
        return _fit_lobe_compiled(y, w, lights, n_start, depth)
    # Precomputed once per call, not per candidate: only lights some function of the chunk
    # can use (w = 0 samples add nothing to any sum), the weighted data w δA y and its norm.
    n_all = lights.directions
    used = np.flatnonzero(w.any(axis=0))
    l = n_all[used] if used.size < n_all.shape[0] else n_all
    wd = (w * lights.solid_angles)[:, used] if used.size < n_all.shape[0] else w * lights.solid_angles
    yu = y[:, used] if used.size < n_all.shape[0] else y
    t1, t2 = _tangent_basis(n_start)
    lt = np.ascontiguousarray(l.T)
    wy = (wd * yu)[:, :, None]  # (N, L', 1)
    wdc = wd[:, :, None]
    syy = np.sum(wd * yu * yu, axis=1)[:, None]  # (N, 1)

    def normals(u):
        return normalize(n_start[:, None, :] + u[..., :1] * t1[:, None, :]
                         + u[..., 1:2] * t2[:, None, :])

    def objective(u, rows=None):
        # 1 − <y,x>²/(|y|²|x|²) (weights w δA) as batched matrix products; rows: the
        # problems still searching (direct_search's subset)
        sel = slice(None) if rows is None else rows
        nk = n_start[sel][:, None, :] + u[..., :1] * t1[sel][:, None, :] \
            + u[..., 1:2] * t2[sel][:, None, :]
        nk = normalize(nk)
        x = nk @ lt  # (n, K, L')
        np.maximum(x, 0.0, out=x)
        sxy = (x @ wy[sel])[..., 0]
        sxx = (np.square(x, out=x) @ wdc[sel])[..., 0]
        return _misfit_from_sums(syy[sel], sxy, sxx)

    u0 = np.zeros((n_start.shape[0], 2))
    misfit_start = objective(u0[:, None, :])[:, 0]
    u, misfit = direct_search(objective, u0, depth.normal_step, depth.levels, depth.moves,
                              subset=True)
    n = normals(u[:, None, :])[:, 0]
    l = n_all
    wd = w * lights.solid_angles
    x = np.maximum(n @ l.T, 0.0)
    sxx = np.sum(wd * x * x, axis=1)
    k = np.where(sxx > 0, np.sum(wd * y * x, axis=1) / np.where(sxx > 0, sxx, 1.0), 0.0)
    return n, np.maximum(k, 0.0), misfit_start, misfit


def _fit_lobe_compiled(y, w, lights: LightSet, n_start, depth: SearchDepth):
    """:func:`fit_lambertian_lobe` in the compiled kernel ``_skin_kernels.lobe_search``."""
    from facegeo.appearance._skin_kernels import lobe_search

    c = np.ascontiguousarray
    n_start = c(n_start, np.float64)
    t1, t2 = _tangent_basis(n_start)
    u, k, misfit_start, misfit = lobe_search(
        c(y, np.float64), c(w, np.float64), c(lights.directions), c(lights.solid_angles),
        n_start, t1, t2, float(depth.normal_step), int(depth.levels), int(depth.moves))
    n = normalize(n_start + u[:, :1] * t1 + u[:, 1:2] * t2)
    return n, k, misfit_start, misfit


def _row_nanquantile(a, q):
    """``np.nanquantile(a, q, axis=1)`` (linear interpolation) for ``a`` ``(N, L)`` without
    numpy's per-row Python loop: one sort (NaNs last), then the two neighbours of the virtual
    index ``q (k − 1)`` of each row's k finite values. NaN where a row has none."""
    srt = np.sort(a, axis=1)
    k = np.sum(~np.isnan(a), axis=1)
    pos = q * np.maximum(k - 1, 0)
    i0 = np.floor(pos).astype(np.int64)
    i1 = np.minimum(i0 + 1, np.maximum(k - 1, 0))
    t = pos - i0
    rows = np.arange(a.shape[0])
    lo, hi = srt[rows, i0], srt[rows, i1]
    out = np.where(t >= 0.5, hi - (hi - lo) * (1.0 - t), lo + (hi - lo) * t)
    return np.where(k > 0, out, np.nan)


def initial_diffuse_chromaticity(R, valid):
    """Initial uniform diffuse chromaticity d_0 (§4.2).

    The median of the red/green and of the green/blue ratios over the samples whose brightness
    lies in :data:`D0_BRIGHTNESS_RANGE` times the function's 90th-percentile brightness;
    ``d_0 = normalize(r/g, 1, 1/(g/b))``.

    Parameters
    ----------
    R : (N, L, 3) float64, white balanced
    valid : (N, L) bool, unshadowed and unsaturated

    Returns
    -------
    d_0 : (N, 3) float64, unit; the light colour where no sample qualifies.
    found : (N,) bool
    """
    if KERNELS:
        from facegeo.appearance._skin_kernels_samples import median_ratios

        lo, hi = D0_BRIGHTNESS_RANGE
        mrg, mgb = median_ratios(np.ascontiguousarray(R, np.float64),
                                 np.ascontiguousarray(valid, bool), float(lo), float(hi))
    else:
        mrg, mgb = _median_ratios(R, valid)
    return _d0_from_ratios(R, valid, mrg, mgb)


def _median_ratios(R, valid):
    """The two medians of :func:`initial_diffuse_chromaticity` (numpy reference)."""
    b = R.sum(axis=2)
    bv = np.where(valid, b, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        p90 = np.nan_to_num(_row_nanquantile(bv, 0.9), nan=0.0)
        lo, hi = D0_BRIGHTNESS_RANGE
        sel = valid & (b >= lo * p90[:, None]) & (b <= hi * p90[:, None])
        sel &= (R[..., 1] > 0) & (R[..., 2] > 0) & (R[..., 0] >= 0)
        G = np.where(sel, R[..., 1], 1.0)
        rg = np.where(sel, R[..., 0] / G, np.nan)
        gb = np.where(sel, R[..., 1] / np.where(sel, R[..., 2], 1.0), np.nan)
        mrg = _row_nanquantile(rg, 0.5)
        mgb = _row_nanquantile(gb, 0.5)
    return mrg, mgb


@functools.cache
def _colour_plane_basis():
    """Two orthonormal vectors ⊥ s (the plane of :func:`_d0_from_ratios`'s scatter)."""
    b1 = normalize(np.cross(S_WHITE, [1.0, 0.0, 0.0]))
    b2 = np.cross(S_WHITE, b1)
    return b1, b2


def _d0_from_ratios(R, valid, mrg, mgb):
    """d_0 from the two medians, projected onto the colours' plane through s
    (:func:`initial_diffuse_chromaticity`)."""
    b1, b2 = _colour_plane_basis()
    if KERNELS:
        from facegeo.appearance._skin_kernels_samples import colour_scatter, d0_from_ratios

        a, b, c = colour_scatter(np.ascontiguousarray(R, np.float64),
                                 np.ascontiguousarray(valid, bool), b1, b2)
        return d0_from_ratios(np.ascontiguousarray(mrg, np.float64),
                              np.ascontiguousarray(mgb, np.float64), a, b, c, b1, b2)
    found = np.isfinite(mrg) & np.isfinite(mgb) & (mgb > 0)
    d = np.stack([np.where(found, mrg, 1.0), np.ones_like(mrg),
                  np.where(found, 1.0 / np.where(found, mgb, 1.0), 1.0)], axis=1)
    d = normalize(d, fallback=S_WHITE)
    # Project onto the plane through s that the function's colours span (the plane of
    # diffuse chromaticities and light colour, §4.1): the two medians come from different
    # samples, so (r/g, 1, b/g) can sit slightly off it, and then no ramp of Eq. 6 reaches
    # the data. The plane's normal e ⊥ s is the least-scatter direction of R in s's complement.
    w = valid.astype(np.float64)
    u1, u2 = R @ b1, R @ b2
    a, b, c = (np.sum(w * u1 * u1, 1), np.sum(w * u1 * u2, 1), np.sum(w * u2 * u2, 1))
    # smallest-eigenvalue eigenvector of [[a, b], [b, c]]
    lam = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)
    ex = np.where(np.abs(b) > 1e-300, b, np.where(a <= c, 1.0, 0.0))
    ey = np.where(np.abs(b) > 1e-300, lam - a, np.where(a <= c, 0.0, 1.0))
    e = normalize(ex[:, None] * b1 + ey[:, None] * b2, fallback=b1)
    spread = (a + c) > 0
    dp = normalize(d - np.sum(d * e, 1, keepdims=True) * e, fallback=S_WHITE)
    d = np.where((found & spread)[:, None], dp, d)
    return d, found


def ramp_mu_d(p, xcos, A, Rd, Rdms, ds):
    """The separated diffuse coefficient μ_d of §4.2 under candidate ramps, in closed form.

    For each candidate ``(α_0, α_1)`` and sample, Eq. 7 gives f from ``x = cos θ_i cos θ_r``,
    Eq. 6 the chromaticity ``c = u/|u|`` with ``u = g d_0 − f s``, ``g = 1 + f``, and §4.2
    separates ``R = μ_d c + μ_s s + μ_e (c × s)``. Without forming 3-vectors (d_0, s unit):

        |u|² = 1 + 2 (1 − d_0·s) f g,    |u × s|² = g² |d_0 × s|²,
        R·u − (R·s)(u·s) = g (R·d_0 − (R·s)(d_0·s)),

    so ``μ_d = (|u|/g) A`` with ``A = (R·d_0 − (R·s)(d_0·s))/|d_0 × s|²`` (one number per
    sample, independent of the candidate); where the matrix is singular
    (``|u × s|² < SINGULAR_SIN2 |u|²``, as in :func:`separate_colour`) ``μ_d = R·c =
    (R·d_0 + f (R·d_0 − R·s))/|u|``. Equals ``separate_colour(R, ramp_chromaticity(d_0, f))``'s
    μ_d to rounding (tested), at a fraction of the cost.

    Parameters
    ----------
    p : (n, K, ≥2) float64, candidates; ``p[..., 0]`` α_0, ``p[..., 1]`` α_1
    xcos : (n, K or 1, L) float64 in [0, 1], ``clip(n·l) clip(n·v)``
    A, Rd, Rdms : (n, L) float64
        ``A`` as above (0 where d_0 ∥ s), ``R·d_0`` and ``R·d_0 − R·s`` (white balanced).
    ds : (n,) float64, ``d_0·s``

    Returns
    -------
    (n, K, L) float64
    """
    two_1mds = (2.0 * (1.0 - ds))[:, None, None]
    ds2k = (1.0 - ds * ds)[:, None, None]
    # in place where possible: three (n, K, L) allocations per call instead of ten
    f = ramp_f_from_x(xcos, p[..., 0:1], p[..., 1:2])
    g = f + 1.0
    uu = f * g
    uu *= two_1mds
    uu += 1.0
    np.maximum(uu, 1e-300, out=uu)  # ≥ (1 + d_0·s)/2 but for rounding
    # f is linear in x ∈ [0, 1]: bound |g| from below and |u|² (convex in f) from above per
    # candidate from the ramp's ends; test samples only where the bound allows a singular one
    g0, g1 = 1.0 + p[..., 0:1], 1.0 + p[..., 1:2]
    gmin = np.where(g0 * g1 > 0, np.minimum(np.abs(g0), np.abs(g1)), 0.0)
    uumax = 1.0 + two_1mds * np.maximum((g0 - 1) * g0, (g1 - 1) * g1)
    maybe = gmin * gmin * ds2k < SINGULAR_SIN2 * uumax
    sing = (g * g * ds2k < SINGULAR_SIN2 * uu) if np.any(maybe) else None
    su = np.sqrt(uu, out=uu)
    if sing is not None and np.any(sing):
        gs = np.where(sing, 1.0, g)
        return np.where(sing, (Rd[:, None, :] + f * Rdms[:, None, :]) / su,
                        A[:, None, :] * su / gs)
    su /= g
    su *= A[:, None, :]
    return su


#: Smallest ramp weight f of Eq. 7 a fitted ramp may reach over x = cos θ_i cos θ_r ∈ [0, 1]:
#: at f = −1 Eq. 6's chromaticity ``d_0 + f (d_0 − s)`` is the light's own colour s, below it
#: the diffuse colour would pass through white to the complementary hue (and at the crossing
#: the separation is singular).
RAMP_F_MIN = -1.0


def physical_ramp(alpha_0, alpha_1, normal_ramp, normal):
    """Reject fitted ramps outside Eq. 6's physical range: where ``min(α_0, α_1)`` (f's
    minimum over x ∈ [0, 1], f being linear in x) is at or below :data:`RAMP_F_MIN`, or
    either α is not finite, α_0 = α_1 = 0 and the ramp's normal is replaced by ``normal``
    (the lobe's, before the ramp's polish).

    Deviation from the paper, which leaves α free: on a near-grey function (d_0 a few degrees
    from s) the separation is ill-conditioned and the ramp's polish can slide to huge
    opposite coefficients (seen: α_0 = 164, α_1 = −166 on 2 % colour noise, the normal moved
    50°, 84 % of the function called specular) — and whether it does depends on the last bits
    of the arithmetic (one CPU's vector width against another's). A degenerate ramp is refused
    the way a degenerate lens is (issue 35).

    Returns ``(alpha_0, alpha_1, normal_ramp, rejected)`` with ``rejected`` (N,) bool.
    """
    a0 = np.asarray(alpha_0, np.float64)
    a1 = np.asarray(alpha_1, np.float64)
    bad = ~(np.isfinite(a0) & np.isfinite(a1)) | (np.minimum(a0, a1) <= RAMP_F_MIN)
    if not bad.any():
        return a0, a1, normal_ramp, bad
    return (np.where(bad, 0.0, a0), np.where(bad, 0.0, a1),
            np.where(bad[:, None], normal, normal_ramp), bad)


def fit_ramp(R, w, lights: LightSet, n, v, d_0, depth: SearchDepth):
    """α_0, α_1 of Eq. 7 by coarse-to-fine direct search (Debevec et al. 2000, §4.2).

    d_0 stays fixed (the paper's representative chromaticity). For each candidate (α_0, α_1)
    the function is separated with the ramp's per-sample chromaticity (Eq. 6 + §4.2) and the
    candidate scored by how far the separated diffuse coefficient μ_d is from a Lambertian
    lobe ``k max(0, n·l)`` (relative weighted misfit), with samples near the mirror direction
    ``r = 2(n·v)n − v`` down-weighted by ``1 − exp(−(1 − l·r)/σ)``.

    Deviation from the paper: the paper fits "the observed chromaticities in the original
    unseparated reflectance function". Observed chromaticities include the specular lobe's
    tails, which carry the light's colour and move along the very d_0–s line the ramp moves
    along, so that fit is biased wherever the lobe is not negligible. Scoring the separation
    the ramp implies uses the same chromaticities but is exact on data the model made (when
    d_0 is the model's). Note that (d_0, α_0, α_1) are only weakly identifiable together:
    shifting d_0 along the d_0–s line and α_1 by about the same amount changes the predicted
    chromaticities at the 1e-5 level, so α's are only comparable for the same d_0.

    Parameters
    ----------
    R : (N, L, 3) float64, white balanced
    w : (N, L) float64, 0/1 usable samples
    n, v : (N, 3) float64, unit
    d_0 : (N, 3) float64, unit

    The direct search runs at the given normal; the Levenberg–Marquardt polish
    (``depth.polish`` iterations) refines α_0, α_1 and the normal together, since the ramp
    and the lobe are coupled through cos θ_i (a normal error biases the ramp and vice versa).

    **Chromaticity rows (the paper's criterion, where the lobe cannot decide).** The lobe
    criterion is blind to a uniform scale of μ_d: as α_0, α_1 grow together the ramp
    chromaticity tends to ``normalize(d_0 − s)`` and μ_d to ``A √(2(1 − d_0·s))`` — the same
    lobe shape for every large ramp, with ``μ_s = B + A f/(1 + f)`` (``B = R·s − A d_0·s``)
    moving a growing share of every sample into S. On data the model made, the misfit has its
    exact minimum at the truth; on anything else (the generator's Fresnel-weighted colour
    blend, real skin) the polish slides along that direction and lets the ramp absorb the
    non-Lambertian brightness: 60 % of a 92 %-diffuse small-preset function set went to S.
    So, per function, after the polish: ``λ = depth.chroma × M`` (M the lobe misfit the
    polish left); where ``λ > CHROMA_MIN_WEIGHT`` the polish is rerun from the search's
    result on the lobe residuals plus the rows ``√λ √w_c μ_s / √Σ w_c |R|²`` — the paper's
    "best fit to the observed chromaticities" (a diffuse sample has μ_s = 0), with samples
    within ≈ 45° of the mirror direction left out (:func:`chroma_weights`). On paper-mode
    data M ≈ 1e-15 (d_0 known) to 1e-10 (estimated): the rows do not run and exact recovery
    is kept; on mismatched data they pin the scale (small preset: S 7.5 % of the energy
    against the generator's 7.7 %, was 60 %).

    Returns
    -------
    alpha_0, alpha_1 : (N,) float64
    normal : (N, 3) float64, unit (the input normal when ``depth.polish`` is 0)
    misfit : (N,) float64
    """
    if KERNELS:
        return _fit_ramp_compiled(R, w, lights, n, v, d_0, depth)
    sub = light_subsample(lights, depth.sample_lights)
    # only lights some function of the chunk uses (the shadowed half of the sphere drops out)
    used = np.flatnonzero(w.any(axis=0))
    if used.size < lights.n_lights:
        lights = lights.subset(used)
        R, w = R[:, used], w[:, used]
        sub = None if sub is None else sub[used]
    l = lights.directions
    lt = np.ascontiguousarray(l.T)
    s = S_WHITE
    nv0 = np.einsum("ni,ni->n", n, v)
    r = 2.0 * nv0[:, None] * n - v
    wm = 1.0 - np.exp(-(1.0 - r @ lt) / MIRROR_SIGMA)
    wd = w * lights.solid_angles * wm
    Rs = R @ s  # (N, L)
    Rd = np.einsum("nlc,nc->nl", R, d_0)
    ds = d_0 @ s
    t1, t2 = _tangent_basis(n)
    # Per function, independent of the candidate (precomputed once, not per evaluation):
    # the sums ramp_mu_d needs (Eq. 6 without 3-vectors).
    ds2 = 1.0 - ds * ds  # |d_0 × s|²
    A = (Rd - Rs * ds[:, None]) / np.where(ds2 > 0, ds2, 1.0)[:, None]
    A = np.where((ds2 > 0)[:, None], A, 0.0)
    Rdms = Rd - Rs
    B, cw1 = _chroma_rows(R, w, lights, n, v, A, ds)
    cw = np.zeros_like(cw1)  # the chromaticity rows' weights: off in the first polish

    def mu_s(p, xcos, rows):
        return ramp_mu_s(p, xcos, A[rows], B[rows])
    # fixed normal (the search, and the polish without the normal): n·l, cos θ_i cos θ_r
    nl_fix = np.maximum(n @ lt, 0.0)  # (N, L)
    x_fix = np.clip(nl_fix, 0.0, 1.0) * np.clip(nv0, 0.0, 1.0)[:, None]

    def mu_d(p, xcos, sel):
        return ramp_mu_d(p, xcos, A[sel], Rd[sel], Rdms[sel], ds[sel])

    def problem(wd, keep=None):
        """The residuals and the search's objective for the sample weights ``wd``; ``keep``
        (L,) bool: the lights the chromaticity rows use (all when None)."""
        sqw = np.sqrt(wd)
        sxx_fix = np.sum(wd * nl_fix * nl_fix, axis=1)  # (N,)
        wnl_fix = (wd * nl_fix)[:, :, None]
        wdc = wd[:, :, None]

        def residuals(p, rows=slice(None)):
            # p = (α_0, α_1[, u, w]): optional tangent-plane offsets of the normal
            if p.shape[-1] == 4:
                nk = normalize(n[rows][:, None, :] + p[..., 2:3] * t1[rows][:, None, :]
                               + p[..., 3:4] * t2[rows][:, None, :])
                nl = np.maximum(nk @ lt, 0.0)  # (n, K, L)
                nv = np.einsum("nkc,nc->nk", nk, v[rows])[..., None]
                xcos = np.clip(nl, 0.0, 1.0) * np.clip(nv, 0.0, 1.0)
            else:
                nl = nl_fix[rows][:, None, :]
                xcos = x_fix[rows][:, None, :]
            res = _lobe_residuals_sqrtw(mu_d(p, xcos, rows), sqw[rows], nl)
            c = cw[rows] if keep is None else cw[rows] * keep
            return np.concatenate([res, mu_s(p, xcos, rows) * c[:, None, :]], axis=-1)

        def objective(p, rows):
            # Σ residuals² of the fixed-normal ramp in closed form from the three weighted sums
            m = mu_d(p, x_fix[rows][:, None, :], rows)
            syy = ((m * m) @ wdc[rows])[..., 0]
            sxy = (m @ wnl_fix[rows])[..., 0]
            sxx = sxx_fix[rows][:, None]
            ok = (sxx > 1e-300) & (syy > 1e-300) & (sxy > 0)
            fit = 1.0 - sxy * sxy / np.where(ok, sxx * syy, 1.0)
            return np.where(ok, fit, np.where(syy > 1e-300, 1.0, syy))

        return residuals, objective

    # the search and the polishes on the light subsample (all lights when it is None), the
    # finishing iterations on all lights
    residuals, objective = problem(wd, None) if sub is None else problem(wd * sub, sub)
    n_out = n
    x0 = np.zeros((n.shape[0], 2))
    p, misfit = direct_search(objective, x0, depth.alpha_step, depth.alpha_levels, depth.moves,
                              subset=True)
    if depth.polish:
        ps = p if not depth.polish_normal else np.concatenate([p, np.zeros_like(p)], axis=1)
        p, misfit = gauss_newton_polish(residuals, ps, iterations=depth.polish,
                                        forward=POLISH_FORWARD)
        lam = depth.chroma * np.maximum(misfit, 0.0)
        sel = np.flatnonzero(lam > CHROMA_MIN_WEIGHT)
        if sel.size:
            # second polish from the search's result with the chromaticity rows weighted by
            # the lobe misfit the first polish left (chroma_weights)
            cw[sel] = np.sqrt(lam[sel])[:, None] * cw1[sel]
            p[sel], misfit[sel] = gauss_newton_polish(
                lambda q: residuals(q, sel), ps[sel], iterations=depth.polish,
                forward=POLISH_FORWARD)
        if sub is not None and depth.finish:
            # from the subsample's minimum to all lights' (the same rows, cw 0 where unused)
            p, misfit = gauss_newton_polish(problem(wd)[0], p, iterations=depth.finish,
                                            forward=POLISH_FORWARD)
        if depth.polish_normal:
            n_out = normalize(n + p[:, 2:3] * t1 + p[:, 3:4] * t2)
            p = p[:, :2]
    return p[:, 0], p[:, 1], n_out, misfit


def gate_specular(D, mu_s, w, gate: float):
    """Keep μ_s only where it exceeds the noise: the final separation's optional specular gate.

    §4.2 takes ``S = max(μ_s, 0) s``, which turns every positive noise excursion into S: on
    the small preset with 2 % Gaussian noise S held 21 % of the energy where the generator
    puts 7.5 %. A white specular term only adds to a sample, so negative μ_s is noise (or
    ramp error); its RMS estimates the noise, ``σ² = 2 Σ_w min(μ_s, 0)² / Σ w`` per function
    (half the noise is negative), and a sample keeps ``μ_s`` only where ``μ_s > gate · σ``
    (the rest goes back to D). Deviation from the paper (which clamps at 0), hence off by
    default (``fit_reflectance(specular_gate=0)``): where σ comes from model mismatch rather
    than noise it also cuts real specular tails (noise-free small preset, gate 3: ρ_s error
    3.2 → 4.5 %; the fit stage's projected functions: ρ_s error 17 → 42 %).

    Parameters
    ----------
    D : (N, L, 3) float64, ``R − max(μ_s, 0) s`` (white balanced)
    mu_s : (N, L) float64, signed
    w : (N, L) float64, 0/1 usable samples (the noise estimate's)
    gate : float, ≥ 0; 0 returns the inputs unchanged

    Returns
    -------
    D : (N, L, 3) float64, ``R − S`` with the gated S
    mu_s : (N, L) float64, 0 where gated
    y : (N, L) float64 or None, ``|D|`` (None when nothing was gated: the caller's holds)
    """
    if not gate > 0.0:
        return D, mu_s, None
    neg = np.minimum(mu_s, 0.0)
    sigma = np.sqrt(2.0 * np.sum(w * neg * neg, axis=1) / np.maximum(np.sum(w, axis=1), 1.0))
    gated = (mu_s > 0.0) & (mu_s <= gate * sigma[:, None])
    if not np.any(gated):
        return D, mu_s, None
    back = np.where(gated, mu_s, 0.0) / np.sqrt(3.0)  # per channel: μ_s s = μ_s/√3
    D = D + back[..., None]
    return D, np.where(gated, 0.0, mu_s), np.linalg.norm(D, axis=2)


#: :func:`gate_chromaticity` leaves a function alone when its threshold is below this fraction
#: of its brightest sample: noise-free and synthetic functions keep the paper's separation
#: exactly.
GATE_FLOOR = 1e-3


def chroma_noise(R, w, d_0):
    """The noise the colour separation turns into μ_s, per function, measured where the model
    says there is no light.

    §4.2 separates a sample R into μ_d d + μ_s s + μ_e e (e = d × s) by inverting [d, s, e].
    Diffuse and specular light both lie in the (d, s) plane, so μ_e holds only noise (and
    colour the model does not have), and for isotropic colour noise of σ per channel μ_e and
    μ_s carry the same noise, σ / sin θ, θ the angle between the diffuse colour d_0 and the
    light's colour s: on a coloured object (skin: θ ≈ 10–25°) small, on a near-grey one
    (DiLiGenT's cat: θ ≈ 4°) fifteen times the sample noise — which the paper's
    ``S = max(μ_s, 0) s`` keeps as specular energy (18 % of the cat's). Unlike the negative
    μ_s of :func:`gate_specular`, μ_e does not see the ramp's in-plane model error.

    Parameters
    ----------
    R : (N, L, 3) float64, white balanced; w : (N, L) float64 0/1 usable samples
    d_0 : (N, 3) float64, unit

    Returns
    -------
    sigma : (N,) float64 — RMS of μ_e over the usable samples (inf where d_0 = s: no
        separation possible)
    top : (N,) float64 — the largest usable |R| (the scale of :data:`GATE_FLOOR`)
    """
    e = np.cross(d_0, S_WHITE)
    sin2 = np.einsum("ni,ni->n", e, e)
    mu_e = np.einsum("nlc,nc->nl", R, e) / np.where(sin2 > 0, sin2, 1.0)[:, None]
    sigma = np.sqrt(np.sum(w * mu_e * mu_e, axis=1) / np.maximum(np.sum(w, axis=1), 1.0))
    top = np.max(w * np.linalg.norm(R, axis=2), axis=1)
    return np.where(sin2 > 0, sigma, np.inf), top


def chroma_gate_active(sigma, top, gate: float):
    """(N,) bool: the functions :func:`gate_chromaticity` may change (threshold ≥ GATE_FLOOR
    of the brightest sample)."""
    return (gate > 0.0) & (gate * np.asarray(sigma) >= GATE_FLOOR * np.asarray(top))


def gate_chromaticity(D, mu_s, sigma, top, gate: float):
    """Keep μ_s only where the light's colour is told apart from the albedo's: the check of the
    light's chromaticity against the object's before moving energy into S (issue 36).

    A sample keeps ``μ_s`` only where ``μ_s > gate · σ``, σ the function's colour noise as the
    separation sees it (:func:`chroma_noise`: large where the diffuse colour is close to the
    light's); the rest goes back to D. Deviation from the paper (which clamps μ_s at 0): on a
    near-grey object the paper's separation turns colour noise into specular energy.
    Functions whose threshold is below :data:`GATE_FLOOR` of their brightest sample are
    unchanged.

    Parameters
    ----------
    D : (N, L, 3) float64, white balanced; mu_s : (N, L) float64, signed
    sigma, top : (N,) float64 — :func:`chroma_noise`; gate : float ≥ 0 (0: unchanged)

    Returns
    -------
    D, mu_s, y : as :func:`gate_specular`
    """
    if not gate > 0.0:
        return D, mu_s, None
    act = chroma_gate_active(sigma, top, gate)
    if not act.any():
        return D, mu_s, None
    thr = np.where(act, gate * np.where(np.isfinite(sigma), sigma, np.inf), 0.0)
    gated = (mu_s > 0.0) & (mu_s <= thr[:, None])
    if not np.any(gated):
        return D, mu_s, None
    D = D + (np.where(gated, mu_s, 0.0) / np.sqrt(3.0))[..., None]
    return D, np.where(gated, 0.0, mu_s), np.linalg.norm(D, axis=2)


def _chroma_rows(R, w, lights: LightSet, n, v, A, ds):
    """The chromaticity rows of :func:`fit_ramp`'s second polish: ``B = R·s − A (d_0·s)`` of
    :func:`ramp_mu_s` and the unit row weights ``√w_c / √Σ w_c |R|²`` with
    ``w_c = w δA`` × :func:`chroma_weights` (each ``(N, L)``)."""
    nv = np.einsum("ni,ni->n", n, v)
    r = 2.0 * nv[:, None] * n - v
    wc = w * lights.solid_angles * chroma_weights(r @ lights.directions.T)
    RR = np.einsum("nlc,nlc->nl", R, R)
    nR = np.sqrt(np.maximum(np.sum(wc * RR, axis=1), 1e-300))
    B = R @ S_WHITE - A * ds[:, None]
    return np.ascontiguousarray(B), np.ascontiguousarray(np.sqrt(wc) / nR[:, None])


def _fit_ramp_compiled(R, w, lights: LightSet, n, v, d_0, depth: SearchDepth):
    """:func:`fit_ramp` in the compiled kernels (``_skin_kernels``): the same inputs, search
    and Levenberg–Marquardt steps, the polish with the analytic Jacobian."""
    from facegeo.appearance._skin_kernels import ramp_polish, ramp_search
    from facegeo.appearance._skin_kernels_samples import chroma_rows, ramp_inputs

    c = np.ascontiguousarray
    n, v, d_0 = c(n, np.float64), c(v, np.float64), c(d_0, np.float64)
    t1, t2 = _tangent_basis(n)
    wd, x_fix, nl_fix, A, Rd, Rdms, ds = ramp_inputs(
        c(R, np.float64), c(w, np.float64), c(lights.solid_angles), c(lights.directions), n, v,
        d_0, float(MIRROR_SIGMA))
    # the search and the polishes on the light subsample (the kernels use the samples of
    # nonzero weight), the finishing iterations on all lights
    sub = light_subsample(lights, depth.sample_lights)
    ws = wd if sub is None else wd * sub
    p, misfit = ramp_search(x_fix, nl_fix, ws, A, Rd, Rdms, ds, float(depth.alpha_step),
                            int(depth.alpha_levels), int(depth.moves), SINGULAR_SIN2)
    n_out = n
    if depth.polish:
        p0 = c(p if not depth.polish_normal else np.concatenate([p, np.zeros_like(p)], axis=1))
        dirs = c(lights.directions)

        P = p0.shape[1]
        # the lobe rows' JᵀJ, Jᵀr, Σ r² at p0, recorded by the first polish for the second
        start = np.empty((p0.shape[0], P * P + P + 1))

        def polish(rows, B, cw, chroma, mode, x0, wgt, iterations):
            # per-function arguments of the functions ``rows`` (None: all)
            f = (lambda a: a) if rows is None else (lambda a: c(a[rows]))
            return ramp_polish(f(x0), f(n), f(t1), f(t2), f(v), dirs, f(x_fix), f(nl_fix),
                               f(wgt), f(A), f(Rd), f(Rdms), f(ds), int(iterations),
                               SINGULAR_SIN2, B, cw, chroma, float(POLISH_XTOL), f(start), mode)

        zero = np.zeros_like(wd)  # no chromaticity rows in the first polish
        p, misfit = polish(None, zero, zero, False, 1, p0, ws, depth.polish)
        lam = depth.chroma * np.maximum(misfit, 0.0)
        sel = np.flatnonzero(lam > CHROMA_MIN_WEIGHT)
        rows = None if sel.size == p.shape[0] else sel
        if sel.size:
            # second polish from the search's result with the chromaticity rows weighted by
            # the lobe misfit the first polish left (see fit_ramp); their inputs only for
            # the functions that need them
            B, cw1 = chroma_rows(c(R, np.float64), c(w, np.float64), c(lights.solid_angles),
                                 dirs, c(n[sel]), c(v[sel]), c(A[sel]), c(ds[sel]),
                                 sel.astype(np.int64), float(CHROMA_SIGMA))
            cw = c(np.sqrt(lam[sel])[:, None] * cw1)
            p[sel], misfit[sel] = polish(rows, B, cw, True, 2, p0, ws, depth.polish)
        if sub is not None and depth.finish:
            # from the subsample's minimum to all lights': without and with the rows
            p1 = c(p)
            rest = np.setdiff1d(np.arange(p.shape[0]), sel, assume_unique=True)
            if rest.size:
                q = None if rest.size == p.shape[0] else rest
                p[rest], misfit[rest] = polish(q, zero[:rest.size], zero[:rest.size], False, 0,
                                               p1, wd, depth.finish)
            if sel.size:
                p[sel], misfit[sel] = polish(rows, B, cw, True, 0, p1, wd, depth.finish)
        if depth.polish_normal:
            n_out = normalize(n + p[:, 2:3] * t1 + p[:, 3:4] * t2)
    return p[:, 0], p[:, 1], n_out, misfit


def specular_energy(S, shadow, lights: LightSet, n, v, eta):
    """Total specular energy ρ_s (Fig. 14 d): the integral of the measured microfacet distribution.

    Inverting Eq. 8 per sample, ``ρ_s P(h_l) = S_l · 4 (n·v)/(F G)``; with ``dω_l = 4 (v·h) dω_h``
    the normalisation ``∫ P cos θ_h dω_h = 1`` gives

        ρ_s = Σ_l S_l (n·v)(n·h_l) / (F G (v·h_l)) δA_l

    over unshadowed lights with ``F G (v·h) > 1e-6`` (a lobe hidden in shadow is not counted).

    Parameters
    ----------
    S : (N, L) float64, the specular sample per colour channel (μ_s⁺/√3)
    shadow : (N, L) bool
    n, v : (N, 3) float64, unit

    Returns
    -------
    (N,) float64, ≥ 0
    """
    if KERNELS:
        from facegeo.appearance._skin_kernels_samples import specular_energy as kernel

        c = np.ascontiguousarray
        return kernel(c(S, np.float64), c(shadow, bool), c(lights.directions),
                      c(lights.solid_angles), c(n, np.float64), c(v, np.float64), float(eta))
    nl = n @ lights.directions.T
    nv = np.einsum("ni,ni->n", n, v)
    # only the samples that can contribute (S > 0, unshadowed, both cosines positive): the
    # specular lobe is a small part of the sphere, so this skips most of the work
    rows, cols = np.nonzero((S > 0) & ~shadow & (nl > 0) & (nv > 0)[:, None])
    l = lights.directions[cols]
    h = normalize(l + v[rows], fallback=n[rows])
    nh = np.einsum("kc,kc->k", h, n[rows])
    vh = np.einsum("kc,kc->k", h, v[rows])
    nvk = nv[rows]
    F = fresnel_dielectric(vh, eta)
    G = torrance_sparrow_geometry(nl[rows, cols], nvk, nh, vh)
    den = F * G * vh
    ok = den > 1e-6
    val = np.where(ok, S[rows, cols] * nvk * np.maximum(nh, 0.0) / np.where(ok, den, 1.0), 0.0)
    out = np.bincount(rows, weights=val * lights.solid_angles[cols], minlength=S.shape[0])
    return np.maximum(out, 0.0)


def check_reflectance(R, lights: LightSet, masked=None):
    """Validate reflectance functions: ``(N, L, 3)``, ``(N, L, 1)`` or ``(N, L)``, finite, ≥ 0
    — except at the samples ``masked`` ``(N, L)`` bool marks, whose values are not checked.

    Returns ``(R (N, L, C) in its own dtype, single_channel)``: callers convert per chunk.
    """
    R = as_array(R, "R", dtype=None, finite=masked is None)
    if R.ndim == 2:
        R = R[..., None]
    if R.ndim != 3 or R.shape[2] not in (1, 3):
        raise ShapeError(f"R: expected shape (N, L, 3), (N, L, 1) or (N, L), got {R.shape}")
    if R.shape[1] != lights.n_lights:
        raise ShapeError(f"R: expected {lights.n_lights} lights on axis 1 (the light set's), "
                         f"got shape {R.shape}")
    if not (np.issubdtype(R.dtype, np.floating) or np.issubdtype(R.dtype, np.integer)):
        raise InputError(f"R: expected real numbers, got dtype {R.dtype}")
    keep = None
    if masked is not None:
        keep = ~check_mask(masked, "masked", R.shape[0], R.shape[1])[..., None]
        if np.issubdtype(R.dtype, np.floating):
            bad = ~np.isfinite(R) & keep
            if bad.any():
                raise InputError(f"R: {int(bad.sum())} non-finite value(s) (NaN or inf) outside "
                                 f"the masked samples; first at index "
                                 f"{tuple(int(i) for i in np.argwhere(bad)[0])}")
    neg = R < 0 if keep is None else (R < 0) & keep
    if np.any(neg):
        raise InputError("R: reflectance must be >= 0 (subtract the ambient frame and clip)")
    return R, R.shape[2] == 1


def check_views(v, N):
    v = as_array(v, "v")
    if v.shape == (3,):
        v = np.broadcast_to(v, (N, 3))
    if v.shape != (N, 3):
        raise ShapeError(f"v: expected shape (3,) or ({N}, 3), got {v.shape}")
    return check_unit_vectors(v, "v")


def check_mask(mask, name, N, L):
    if mask is None:
        return np.zeros((N, L), bool)
    m = np.asarray(mask)
    if m.dtype != bool:
        raise InputError(f"{name}: expected a bool array, got dtype {m.dtype}")
    if m.shape != (N, L):
        raise ShapeError(f"{name}: expected shape ({N}, {L}), got {m.shape}")
    return m
