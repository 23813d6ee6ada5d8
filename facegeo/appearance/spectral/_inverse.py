"""Inverse spectral skin model: (C_m, β_m, C_h) per texel from linear-RGB albedo, and per
spectrum from measured reflectance; and edits of fitted parameters.

Albedo (:func:`fit_albedo`)
    1. **Lookup stage.** Each texel's log-RGB picks its nearest table entry through the
       lookup table's 64³ voxel index (:meth:`SkinLUT.nearest`, one gather per texel).
    2. **Refinement.** A few damped Gauss–Newton (Levenberg–Marquardt) steps, vectorised over
       all texels, minimise the log-RGB residual ``r = ln rgb_model(x) − ln rgb_target`` over
       the table coordinates x = (∛C_m, β_m, ∛C_h), with the model the table's trilinear
       interpolant (``refine="lut"``, default) or the exact spectral model with forward
       differences (``refine="exact"``, ~100× slower, for small maps). Log residuals weigh
       every channel by its relative error, so dark skin is fitted as well as light skin.
    3. **Diagnosis.** The residual says whether the colour is in the model's gamut; the
       Gauss–Newton covariance ``σ² (JᵀJ)⁻¹`` under a relative RGB noise σ (default 1 %)
       says whether each parameter is identifiable: C_m and C_h need a predicted relative
       1-σ error below ``identifiability_tol`` (10 %), β_m an absolute one below it.

Spectra (:func:`fit_spectra`)
    Least squares on the reflectance itself (the RMSE metric), seeded from a coarse table of
    spectra, refined by vectorised Levenberg–Marquardt on the exact model.

References
----------
Donner, C., Jensen, H. W. (2006). A Spectral BSSRDF for Shading Human Skin. EGSR 2006 — lists
the inverse problem (physiological parameters from measured skin) as future work.
Marquardt, D. W. (1963). An algorithm for least-squares estimation of nonlinear parameters.
SIAM J. Appl. Math. 11(2).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from facegeo.checks import as_array, fmt_value
from facegeo.errors import InputError
from facegeo.appearance.spectral._absorption import DEFAULT_EUMELANIN, check_wavelengths
from facegeo.appearance.spectral._lut import LOG_FLOOR, SkinLUT, layered_spectra_grid, skin_lut
from facegeo.appearance.spectral._model import (
    PARAMETER_RANGES,
    SkinParameters,
    check_skin_parameters,
    skin_rgb,
    skin_spectrum,
)

log = logging.getLogger(__name__)

__all__ = [
    "FLAG_OUT_OF_GAMUT",
    "FLAG_C_M_UNIDENTIFIABLE",
    "FLAG_BETA_M_UNIDENTIFIABLE",
    "FLAG_C_H_UNIDENTIFIABLE",
    "FLAG_AT_BOUND",
    "FLAG_DARK",
    "FLAG_SKIPPED_STEPS",
    "AlbedoFit",
    "SpectrumFit",
    "fit_albedo",
    "fit_spectra",
    "edit_parameters",
    "edit",
]

FLAG_OUT_OF_GAMUT = 1  #: log-RGB residual above ``gamut_tol``: no skin in the model has this colour
FLAG_C_M_UNIDENTIFIABLE = 2  #: predicted relative error of C_m above the tolerance
FLAG_BETA_M_UNIDENTIFIABLE = 4  #: predicted absolute error of β_m above the tolerance
FLAG_C_H_UNIDENTIFIABLE = 8  #: predicted relative error of C_h above the tolerance
FLAG_AT_BOUND = 16  #: a parameter sits on the edge of its range
FLAG_DARK = 32  #: a target channel is below 1e-4 (log residual floored)
#: Levenberg–Marquardt skipped a step: singular normal matrix or non-finite residual/cost
#: (counted in ``AlbedoFit.skipped_steps``; the parameters are the last good iterate)
FLAG_SKIPPED_STEPS = 64


@dataclass
class AlbedoFit:
    """Per-texel result of :func:`fit_albedo`; every array has the input's leading shape (...).

    Attributes
    ----------
    C_m, beta_m, C_h : (...) float64
        Fitted parameters (always inside :data:`PARAMETER_RANGES`; check the flags before
        trusting them).
    rgb_model : (...,3) float64
        Linear-sRGB albedo of the fitted parameters (the refinement's model).
    target : (...,3) float64
        The albedo that was fitted.
    residual : (...) float64
        ‖rgb_model − target‖₂, linear RGB.
    residual_log : (...) float64
        RMS over channels of ln(rgb_model / target) (≈ relative error).
    sigma : (...,3) float64
        Uncertainty: the larger of the local Gauss–Newton 1-σ error under the noise model and
        the spread of the equally good solutions of the global check; relative for C_m and
        C_h, absolute for β_m (inf where the Jacobian is singular).
    in_gamut : (...) bool
    identifiable : (...,3) bool
        Per parameter (C_m, β_m, C_h).
    flags : (...) uint8
        Bitwise OR of the ``FLAG_*`` constants; 0 means fully trusted.
    x_lut : (...,3) float64
        Table coordinates of the lookup stage (its nearest entry).
    skipped_steps : (...) int64
        Levenberg–Marquardt steps skipped because the damped normal matrix was singular or
        the residual at the trial point was not finite, summed over every start of the texel
        (sets :data:`FLAG_SKIPPED_STEPS`). 0 for ``refine="none"``.
    """

    C_m: np.ndarray
    beta_m: np.ndarray
    C_h: np.ndarray
    rgb_model: np.ndarray
    target: np.ndarray
    residual: np.ndarray
    residual_log: np.ndarray
    sigma: np.ndarray
    in_gamut: np.ndarray
    identifiable: np.ndarray
    flags: np.ndarray
    x_lut: np.ndarray
    skipped_steps: np.ndarray

    @property
    def parameters(self) -> SkinParameters:
        return SkinParameters(self.C_m, self.beta_m, self.C_h)

    @property
    def ok(self) -> np.ndarray:
        """In gamut with C_m and C_h identifiable, (...) bool."""
        return self.in_gamut & self.identifiable[..., 0] & self.identifiable[..., 2]


@dataclass
class SpectrumFit:
    """Result of :func:`fit_spectra` for spectra of leading shape (...).

    Attributes
    ----------
    C_m, beta_m, C_h : (...) float64
    model : (..., L) float64
        Model reflectance at the fitted parameters.
    rmse : (...) float64
        Root-mean-square reflectance error over the wavelengths.
    wavelengths : (L,) float64, nm
    skipped_steps : (...) int64
        Levenberg–Marquardt steps skipped (singular normal matrix or non-finite residual);
        a spectrum with skipped steps may not be at a minimum — check before trusting it.
    """

    C_m: np.ndarray
    beta_m: np.ndarray
    C_h: np.ndarray
    model: np.ndarray
    rmse: np.ndarray
    wavelengths: np.ndarray
    skipped_steps: np.ndarray

    @property
    def parameters(self) -> SkinParameters:
        return SkinParameters(self.C_m, self.beta_m, self.C_h)


# --------------------------------------------------------------------------- linear algebra


def _det3(A: np.ndarray) -> np.ndarray:
    return (
        A[:, 0, 0] * (A[:, 1, 1] * A[:, 2, 2] - A[:, 1, 2] * A[:, 2, 1])
        - A[:, 0, 1] * (A[:, 1, 0] * A[:, 2, 2] - A[:, 1, 2] * A[:, 2, 0])
        + A[:, 0, 2] * (A[:, 1, 0] * A[:, 2, 1] - A[:, 1, 1] * A[:, 2, 0])
    )


def _inv3(A: np.ndarray) -> np.ndarray:
    """Batched 3×3 inverse by the adjugate; rows with a (near-)singular A become inf."""
    adj = np.empty_like(A)
    adj[:, 0, 0] = A[:, 1, 1] * A[:, 2, 2] - A[:, 1, 2] * A[:, 2, 1]
    adj[:, 0, 1] = A[:, 0, 2] * A[:, 2, 1] - A[:, 0, 1] * A[:, 2, 2]
    adj[:, 0, 2] = A[:, 0, 1] * A[:, 1, 2] - A[:, 0, 2] * A[:, 1, 1]
    adj[:, 1, 0] = A[:, 1, 2] * A[:, 2, 0] - A[:, 1, 0] * A[:, 2, 2]
    adj[:, 1, 1] = A[:, 0, 0] * A[:, 2, 2] - A[:, 0, 2] * A[:, 2, 0]
    adj[:, 1, 2] = A[:, 0, 2] * A[:, 1, 0] - A[:, 0, 0] * A[:, 1, 2]
    adj[:, 2, 0] = A[:, 1, 0] * A[:, 2, 1] - A[:, 1, 1] * A[:, 2, 0]
    adj[:, 2, 1] = A[:, 0, 1] * A[:, 2, 0] - A[:, 0, 0] * A[:, 2, 1]
    adj[:, 2, 2] = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    det = _det3(A)
    scale = np.abs(A).reshape(len(A), -1).max(axis=1) ** 3
    singular = ~(np.abs(det) > 1e-14 * scale)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = adj / np.where(singular, 1.0, det)[:, None, None]
    inv[singular] = np.inf
    return inv


def _lm(
    x: np.ndarray,
    residual_fn: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    lo: np.ndarray,
    hi: np.ndarray,
    iterations: int,
    free: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised Levenberg–Marquardt with box constraints (projected steps).

    ``residual_fn(x) -> (r (N, M), J (N, M, 3))``; ``free`` (3,) bool masks the parameters
    that move. Returns the improved ``x`` (N, 3) and ``skipped`` (N,) int64: per row, the
    iterations whose step could not be taken — the damped normal matrix was singular (the
    step is not finite) or the residual at the trial point (or at the start) is not finite.
    Such a step is rejected like a step that does not lower the cost (λ grows), but it is
    counted, never silently dropped; the caller reports it.
    """
    x = x.copy()
    lam = np.full(len(x), 1e-3)
    r, J = residual_fn(x)
    J = J * free
    cost = np.einsum("nm,nm->n", r, r)
    skipped = np.zeros(len(x), np.int64)
    eye = np.eye(3)
    for _ in range(int(iterations)):
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite rows: counted below
            H = np.einsum("nmi,nmj->nij", J, J)
            g = np.einsum("nmi,nm->ni", J, r)
            d = np.einsum("nii->ni", H)
            A = H + (lam[:, None] * d + 1e-12 + (~free) * 1.0)[:, :, None] * eye
            step = -np.einsum("nij,nj->ni", _inv3(A), g)
        finite_step = np.all(np.isfinite(step), axis=1)
        step = np.where(finite_step[:, None], step, 0.0) * free
        x_new = np.clip(x + step, lo, hi)
        r_new, J_new = residual_fn(x_new)
        J_new = J_new * free
        cost_new = np.einsum("nm,nm->n", r_new, r_new)
        finite_cost = np.isfinite(cost_new) & np.all(np.isfinite(J_new), axis=(1, 2))
        skipped += ~(finite_step & finite_cost & np.isfinite(cost))
        better = finite_step & finite_cost & (cost_new < cost)
        x[better] = x_new[better]
        r[better] = r_new[better]
        J[better] = J_new[better]
        cost[better] = cost_new[better]
        lam = np.where(better, lam / 3.0, lam * 4.0)
    n_bad = int(np.count_nonzero(skipped))
    if n_bad:
        log.debug("Levenberg–Marquardt: %d of %d rows skipped %d step(s) (singular system or "
                  "non-finite residual)", n_bad, len(x), int(skipped.sum()))
    return x, skipped


# --------------------------------------------------------------------------- albedo


def _rgb_exact_x(x: np.ndarray, convention: str) -> np.ndarray:
    C_m, beta_m, C_h = SkinLUT.from_x(x)
    return skin_rgb(C_m, beta_m, C_h, convention=convention)


def _local_sigma(
    Jl: np.ndarray, r: np.ndarray, x: np.ndarray, free: np.ndarray, noise: float
) -> np.ndarray:
    """Local uncertainty (relative for C_m, C_h; absolute for β_m) at x.

    The 1-σ error under relative noise σ, from σ² (JᵀJ)⁻¹, plus the size of the Gauss–Newton
    step ``(JᵀJ)⁻¹Jᵀr`` still to go (≈ 0 after refinement; the quantisation error of the
    lookup stage when there was none).
    """
    Jl = Jl * free
    H_inv = _inv3(np.einsum("nmi,nmj->nij", Jl, Jl) + np.diag((~free) * 1.0))
    sx = noise * np.sqrt(np.abs(np.einsum("nii->ni", H_inv)))
    with np.errstate(invalid="ignore"):
        step = np.abs(np.einsum("nij,nj->ni", H_inv, np.einsum("nmi,nm->ni", Jl, r)))
    dx = sx + np.where(np.isfinite(step), step, np.inf)
    sigma = np.stack([3.0 * dx[:, 0] / x[:, 0], dx[:, 1], 3.0 * dx[:, 2] / x[:, 2]], axis=1)
    sigma[:, ~free] = 0.0
    return sigma


def fit_albedo(
    rgb,
    *,
    lut: SkinLUT | None = None,
    refine: str = "lut",
    iterations: int = 8,
    beta_m: float | None = None,
    beta_profile: int = 6,
    noise: float = 0.002,
    gamut_tol: float = 0.02,
    identifiability_tol: float = 0.1,
    chunk: int = 1 << 15,
) -> AlbedoFit:
    """Per-texel (C_m, β_m, C_h) from a linear-sRGB albedo map.

    Three parameters for three channels: the solution can be locally ill-conditioned (C_h
    barely changes the colour of dark skin) and it can be non-unique (pheomelanin and blood
    both redden: two (β_m, C_h) pairs can give one colour). Both are detected:

    * **local** — the Gauss–Newton covariance ``σ² (JᵀJ)⁻¹`` at the solution, σ = ``noise``,
      plus the Gauss–Newton step still to go (≈ 0 after refinement; the table's
      quantisation error with ``refine="none"``);
    * **global** — besides the free refinement from the lookup seed, (C_m, C_h) are fitted
      with β_m held at ``beta_profile`` blends evenly spaced over [0, 1] (a profile of the
      residual along β_m, which maps the valley of near-solutions), and each profile point
      is then released (which finds every isolated solution). Every candidate whose RMS
      log residual is within ``noise`` of the best explains the colour as well, and a
      parameter is identifiable only if all of them agree on it within
      ``identifiability_tol`` (and its local 1-σ error is within it too).

    Parameters
    ----------
    rgb : (..., 3) array_like float, linear sRGB
        Albedo under the white-reflector-is-(1, 1, 1) normalisation of
        :func:`facegeo.appearance.spectral.skin_rgb`. Finite; channels ≤ 1e-4 are floored and flagged.
    lut : SkinLUT, optional
        Default :func:`facegeo.appearance.spectral.skin_lut` ().
    refine : {"lut", "exact", "none"}
        Model inside the refinement: the table's interpolant (fast); the spectral model
        (after the table refinement, 3 more steps on the exact model, ~100× slower, for small
        maps); or none (lookup stage only: quantised to the table, no global check).
    iterations : int
        Free Levenberg–Marquardt steps per start.
    beta_m : float, optional
        Fix the melanin blend instead of fitting it (2 unknowns for 3 channels: one start,
        usually identifiable).
    beta_profile : int
        Melanin blends of the global check (0 disables it: local check only, ~10× faster;
        the cost grows as 1 + 2 · beta_profile refinements).
    noise : float
        Relative RGB noise σ (default 0.2 %, about a 10-bit albedo; the table's interpolation
        error is ≤ 0.12 %). Pass the noise of your albedo.
    gamut_tol : float
        Largest RMS log-RGB residual (≈ relative error) counted as in gamut (default 2 %).
    identifiability_tol : float
        Largest relative error of C_m, C_h (absolute for β_m) counted as identifiable (0.1).
    chunk : int
        Texels per vectorised block.

    Returns
    -------
    AlbedoFit
    """
    if refine not in ("lut", "exact", "none"):
        raise InputError(
            f"refine: unknown value {fmt_value(refine)}; expected one of 'lut', 'exact', 'none'"
        )
    target = as_array(rgb, "rgb", shape=(..., 3))
    lut = skin_lut() if lut is None else lut
    if beta_m is not None:
        lo_b, hi_b = lut.ranges["beta_m"]
        if not (np.isfinite(beta_m) and lo_b <= beta_m <= hi_b):
            raise InputError(f"beta_m: expected a value in [{lo_b:g}, {hi_b:g}], got {fmt_value(beta_m)}")
    tolerances = {"noise": noise, "gamut_tol": gamut_tol, "identifiability_tol": identifiability_tol}
    for name, v in tolerances.items():
        if not (np.isfinite(v) and v > 0):
            raise InputError(f"{name}: expected a finite number > 0, got {fmt_value(v)}")
    if int(beta_profile) < 0 or int(iterations) < 0:
        raise InputError(
            f"beta_profile, iterations: expected >= 0, got {fmt_value(beta_profile)}, {fmt_value(iterations)}"
        )
    shape = target.shape[:-1]
    t = target.reshape(-1, 3)
    n = t.shape[0]
    free = np.array([True, beta_m is None, True])
    held = np.array([True, False, True])
    seeds_b = (
        np.linspace(lut.lo[1], lut.hi[1], max(2, int(beta_profile)))
        if (beta_m is None and refine != "none" and int(beta_profile) > 0)
        else np.empty(0)
    )
    out_x = np.empty((n, 3))
    out_x0 = np.empty((n, 3))
    out_m = np.empty((n, 3))
    out_sigma = np.empty((n, 3))
    out_spread = np.zeros((n, 3))
    out_skipped = np.zeros(n, np.int64)
    for s in range(0, n, max(1, int(chunk))):
        e = min(n, s + int(chunk))
        tc = t[s:e]
        nc = e - s
        tlog = np.log(np.maximum(tc, LOG_FLOOR))
        idx0 = lut.nearest(tc)
        x0 = lut.x_of_index(idx0)
        if beta_m is not None:
            x0[:, 1] = beta_m
        P = len(seeds_b)
        X = np.tile(x0, (1 + 2 * P, 1))  # the free start, then the β profile, then its polish
        X[nc : (1 + P) * nc, 1] = np.repeat(seeds_b, nc)
        S = 1 + 2 * P
        tl = np.tile(tlog, (S, 1))

        def res_lut(x, tl=tl):
            m, J = lut.interpolate_x(x, jacobian=True)
            mc = np.maximum(m, LOG_FLOOR)
            return np.log(mc) - tl[: len(x)], J / mc[:, :, None]

        if refine != "none":
            X[:nc], sk = _lm(X[:nc], lambda x: res_lut(x, tlog), lut.lo, lut.hi, iterations,
                             free)
            out_skipped[s:e] += sk
            if P:
                # Profile over β_m: (C_m, C_h) fitted with β_m held at each blend ...
                prof = slice(nc, (1 + P) * nc)
                X[prof], sk = _lm(
                    X[prof], lambda x: res_lut(x, tl[prof]), lut.lo, lut.hi, iterations, held
                )
                out_skipped[s:e] += sk.reshape(P, nc).sum(axis=0)
                # ... then each profile point released (finds every isolated solution).
                pol = slice((1 + P) * nc, S * nc)
                X[pol], sk = _lm(
                    X[prof], lambda x: res_lut(x, tl[pol]), lut.lo, lut.hi, iterations, free
                )
                out_skipped[s:e] += sk.reshape(P, nc).sum(axis=0)
        if refine == "none":
            m = lut.rgb_flat[idx0]
            mc = np.maximum(m, LOG_FLOOR)
            Jl = lut.node_jacobian[idx0] / mc[:, :, None]
            out_x[s:e], out_x0[s:e], out_m[s:e] = x0, x0, m
            out_sigma[s:e] = _local_sigma(Jl, np.log(mc) - tlog, x0, free, noise)
            continue
        r = np.log(np.maximum(lut.interpolate_x(X), LOG_FLOOR)) - tl
        cost = np.sqrt(np.mean(r**2, axis=1)).reshape(S, nc)
        Xs = X.reshape(S, nc, 3)
        best = np.argmin(cost, axis=0)
        x = Xs[best, np.arange(nc)]
        if S > 1:
            cb_cost = cost[best, np.arange(nc)]
            # Every start (free or profiled) within `noise` of the best explains the colour as
            # well: the parameters are known only to within their spread.
            consistent = cost <= cb_cost + noise  # (S, nc)
            C = np.stack([Xs[..., 0] ** 3, Xs[..., 1], Xs[..., 2] ** 3], axis=-1)  # (S, nc, 3)
            cb = np.stack([x[:, 0] ** 3, x[:, 1], x[:, 2] ** 3], axis=-1)
            dev = np.abs(C - cb)  # β_m: absolute; C_m, C_h: symmetric relative e^|ln C/C_b| - 1
            dev[..., 0] = np.expm1(np.abs(np.log(C[..., 0] / cb[:, 0])))
            dev[..., 2] = np.expm1(np.abs(np.log(C[..., 2] / cb[:, 2])))
            out_spread[s:e] = np.max(np.where(consistent[..., None], dev, 0.0), axis=0)
        if refine == "exact":

            def res_exact(x, tlog=tlog):
                m = _rgb_exact_x(x, lut.convention)
                mc = np.maximum(m, LOG_FLOOR)
                J = np.empty(m.shape + (3,))
                for k in range(3):
                    h = np.where(x[:, k] + 1e-4 <= lut.hi[k], 1e-4, -1e-4)
                    xk = x.copy()
                    xk[:, k] += h
                    J[:, :, k] = (_rgb_exact_x(xk, lut.convention) - m) / h[:, None]
                return np.log(mc) - tlog, J / mc[:, :, None]

            x, sk = _lm(x, res_exact, lut.lo, lut.hi, 3, free)
            out_skipped[s:e] += sk
            m = _rgb_exact_x(x, lut.convention)
            _, Jl = res_lut(x, tlog)
        else:
            m, J = lut.interpolate_x(x, jacobian=True)
            Jl = J / np.maximum(m, LOG_FLOOR)[:, :, None]
        r_final = np.log(np.maximum(m, LOG_FLOOR)) - tlog
        out_x[s:e], out_x0[s:e], out_m[s:e] = x, x0, m
        out_sigma[s:e] = _local_sigma(Jl, r_final, x, free, noise)
    C_m, b_m, C_h = SkinLUT.from_x(out_x)
    residual = np.linalg.norm(out_m - t, axis=1)
    residual_log = np.sqrt(
        np.mean((np.log(np.maximum(out_m, LOG_FLOOR) / np.maximum(t, LOG_FLOOR))) ** 2, axis=1)
    )
    in_gamut = residual_log <= gamut_tol
    uncertainty = out_sigma + out_spread
    identifiable = np.isfinite(uncertainty) & (uncertainty <= identifiability_tol)
    identifiable[:, ~free] = True
    span = lut.hi - lut.lo
    on_edge = (out_x <= lut.lo + 1e-9 * span) | (out_x >= lut.hi - 1e-9 * span)
    at_bound = np.any(free & on_edge, axis=1)
    flags = (
        (~in_gamut) * FLAG_OUT_OF_GAMUT
        | (~identifiable[:, 0]) * FLAG_C_M_UNIDENTIFIABLE
        | (~identifiable[:, 1]) * FLAG_BETA_M_UNIDENTIFIABLE
        | (~identifiable[:, 2]) * FLAG_C_H_UNIDENTIFIABLE
        | at_bound * FLAG_AT_BOUND
        | np.any(t <= LOG_FLOOR, axis=1) * FLAG_DARK
        | (out_skipped > 0) * FLAG_SKIPPED_STEPS
    ).astype(np.uint8)
    if np.any(out_skipped):
        log.info("fit_albedo: %d of %d texels had skipped Levenberg–Marquardt steps "
                 "(flag FLAG_SKIPPED_STEPS)", int(np.count_nonzero(out_skipped)), n)
    if n:
        log.debug(
            "fit_albedo: %d texels, %.1f %% in gamut, %.1f %% with C_m and C_h identifiable",
            n, 100.0 * in_gamut.mean(), 100.0 * (identifiable[:, 0] & identifiable[:, 2]).mean(),
        )
    return AlbedoFit(
        C_m=C_m.reshape(shape),
        beta_m=b_m.reshape(shape),
        C_h=C_h.reshape(shape),
        rgb_model=out_m.reshape(shape + (3,)),
        target=t.reshape(shape + (3,)),
        residual=residual.reshape(shape),
        residual_log=residual_log.reshape(shape),
        sigma=uncertainty.reshape(shape + (3,)),
        in_gamut=in_gamut.reshape(shape),
        identifiable=identifiable.reshape(shape + (3,)),
        flags=flags.reshape(shape),
        x_lut=out_x0.reshape(shape + (3,)),
        skipped_steps=out_skipped.reshape(shape),
    )


# --------------------------------------------------------------------------- spectra


def fit_spectra(
    reflectance,
    wavelengths,
    *,
    iterations: int = 15,
    seed_grid: tuple[int, int, int] = (16, 6, 16),
    convention: str = DEFAULT_EUMELANIN,
    ranges: dict[str, tuple[float, float]] | None = None,
) -> SpectrumFit:
    """Least-squares (C_m, β_m, C_h) for measured reflectance spectra.

    Parameters
    ----------
    reflectance : (..., L) array_like float
        Diffuse reflectance, unitless, finite.
    wavelengths : (L,) array_like float, nm, inside 380–780 nm
    iterations : int
        Levenberg–Marquardt steps on the exact model (forward-difference Jacobian).
    seed_grid : (3,) int
        Coarse table of spectra (cube-root axes) whose best entry seeds each fit.
    convention : str
        Eumelanin constant.
    ranges : dict, optional
        Parameter box (default :data:`PARAMETER_RANGES`).

    Returns
    -------
    SpectrumFit
    """
    wl = check_wavelengths(wavelengths)
    R = as_array(reflectance, "reflectance", shape=(..., wl.size))
    rng = dict(PARAMETER_RANGES)
    rng.update(ranges or {})
    lo = np.array([np.cbrt(rng["C_m"][0]), rng["beta_m"][0], np.cbrt(rng["C_h"][0])])
    hi = np.array([np.cbrt(rng["C_m"][1]), rng["beta_m"][1], np.cbrt(rng["C_h"][1])])
    shape = R.shape[:-1]
    y = R.reshape(-1, wl.size)
    axes = [np.linspace(lo[k], hi[k], int(seed_grid[k])) for k in range(3)]
    table = layered_spectra_grid(axes[0] ** 3, axes[1], axes[2] ** 3, wl, convention=convention)
    table = table.reshape(-1, wl.size)
    # argmin_k |y - t_k|^2 = argmin_k (|t_k|^2 - 2 y·t_k)
    score = np.sum(table**2, axis=1)[None, :] - 2.0 * y @ table.T
    best = np.argmin(score, axis=1)
    i, j, k = np.unravel_index(best, tuple(int(s) for s in seed_grid))
    x0 = np.stack([axes[0][i], axes[1][j], axes[2][k]], axis=1)

    def spectra(x):
        return skin_spectrum(x[:, 0] ** 3, x[:, 1], x[:, 2] ** 3, wl, convention=convention)

    def res(x):
        m = spectra(x)
        J = np.empty(m.shape + (3,))
        for kk in range(3):
            h = np.where(x[:, kk] + 1e-5 <= hi[kk], 1e-5, -1e-5)
            xk = x.copy()
            xk[:, kk] += h
            J[:, :, kk] = (spectra(xk) - m) / h[:, None]
        return m - y, J

    x, skipped = _lm(x0, res, lo, hi, iterations, np.array([True, True, True]))
    if np.any(skipped):
        log.info("fit_spectra: %d of %d spectra had skipped Levenberg–Marquardt steps",
                 int(np.count_nonzero(skipped)), len(x))
    model = spectra(x)
    rmse = np.sqrt(np.mean((model - y) ** 2, axis=1))
    C_m, b_m, C_h = SkinLUT.from_x(x)
    return SpectrumFit(
        C_m=C_m.reshape(shape),
        beta_m=b_m.reshape(shape),
        C_h=C_h.reshape(shape),
        model=model.reshape(shape + (wl.size,)),
        rmse=rmse.reshape(shape),
        wavelengths=wl,
        skipped_steps=skipped.reshape(shape),
    )


# --------------------------------------------------------------------------- edits

_Modifier = float | Callable[[np.ndarray], np.ndarray] | None


def _apply(mod: _Modifier, value: np.ndarray, name: str) -> np.ndarray:
    if mod is None:
        return value
    if callable(mod):
        new = mod(value.copy())
    else:
        new = np.broadcast_to(np.asarray(mod, float), value.shape)
    new = np.asarray(new, dtype=np.float64)
    if new.shape != value.shape:
        try:
            new = np.broadcast_to(new, value.shape)
        except ValueError as exc:
            raise InputError(
                f"{name}: the edit returned shape {new.shape}, expected {value.shape}"
            ) from exc
    if not np.all(np.isfinite(new)):
        raise InputError(f"{name}: the edit produced non-finite values")
    return np.array(new, dtype=np.float64)


def edit_parameters(
    params: SkinParameters | AlbedoFit,
    *,
    C_m: _Modifier = None,
    beta_m: _Modifier = None,
    C_h: _Modifier = None,
    rho_s: _Modifier = None,
) -> SkinParameters:
    """New parameter maps: each modifier is None (keep), a number (set) or a callable (map).

    Results are clipped to :data:`PARAMETER_RANGES` (the count of clipped texels is logged).

    Examples
    --------
    >>> more_blood = edit_parameters(fit, C_h=lambda c: 1.5 * c)      # doctest: +SKIP
    """
    p = params.parameters if isinstance(params, AlbedoFit) else params
    out = {}
    for name, mod in (("C_m", C_m), ("beta_m", beta_m), ("C_h", C_h), ("rho_s", rho_s)):
        value = getattr(p, name)
        if value is None:
            if mod is not None and not callable(mod):
                value = np.zeros(p.shape)
            elif mod is not None:
                raise InputError(f"{name}: cannot map a parameter the input does not have")
            else:
                out[name] = None
                continue
        new = _apply(mod, np.asarray(value, float), name)
        lo, hi = PARAMETER_RANGES[name]
        clipped = (new < lo) | (new > hi)
        if clipped.any():
            log.warning(
                "edit: %d %s value(s) clipped to [%g, %g]", int(clipped.sum()), name, lo, hi
            )
        out[name] = np.clip(new, lo, hi)
    return SkinParameters(**out)


def edit(
    params: SkinParameters | AlbedoFit,
    *,
    C_m: _Modifier = None,
    beta_m: _Modifier = None,
    C_h: _Modifier = None,
    lut: SkinLUT | None = None,
    exact: bool = False,
) -> np.ndarray:
    """Albedo after editing the physiological parameters, for relighting.

    Parameters
    ----------
    params : SkinParameters or AlbedoFit
        Parameter maps, or a fit. With a fit the edit is applied as a ratio to the fitted
        albedo, ``target · rgb(new)/rgb(old)``, so texture the model does not explain
        (residual, out-of-gamut texels) is kept; an edit that changes nothing returns the
        original albedo.
    C_m, beta_m, C_h : None, float or callable
        As :func:`edit_parameters` (e.g. ``C_h=lambda c: 1.5 * c`` for a flush).
    lut : SkinLUT, optional
        Table used when ``exact`` is False.
    exact : bool
        Evaluate the spectral model instead of the table's interpolant.

    Returns
    -------
    (..., 3) float32, linear sRGB
    """
    new = edit_parameters(params, C_m=C_m, beta_m=beta_m, C_h=C_h)
    lut = skin_lut() if lut is None else lut

    def rgb_of(p: SkinParameters) -> np.ndarray:
        if exact:
            return skin_rgb(p.C_m, p.beta_m, p.C_h)
        c_m, b_m, c_h = check_skin_parameters(p.C_m, p.beta_m, p.C_h, ranges=lut.ranges)
        return lut.interpolate(c_m, b_m, c_h)

    rgb_new = rgb_of(new)
    if isinstance(params, AlbedoFit):
        rgb_old = rgb_of(params.parameters)  # same evaluator: a no-op edit is exact
        ratio = rgb_new / np.maximum(rgb_old, LOG_FLOOR)
        return (params.target * ratio).astype(np.float32)
    return rgb_new.astype(np.float32)
