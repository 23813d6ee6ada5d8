"""Depths along camera rays against a second view (:mod:`facegeo.geometry.triangulation`).

:func:`solve_along_rays` (the reprojection solver, module docstring of
:mod:`facegeo.geometry.triangulation`) and :func:`_classify`, the rejection of its solutions
shared by the camera–projector and camera–camera routes. Rows are independent: the solver
works through long inputs in blocks of :data:`_SOLVE_CHUNK` rays, bounding its temporaries
(≈ 1 kB a ray) whatever the image size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facegeo.checks import as_array, check_positive
from facegeo.errors import InputError, ShapeError
from facegeo.geometry._point_maps import BEHIND, INCONSISTENT, OK, UNCERTAIN
from facegeo.geometry.camera import Camera

#: Gauss–Newton steps after the linear start (the residual is nearly linear in t; 3 reach
#: float64 rounding on the test rigs).
_GN_STEPS = 3
#: Rays per block of :func:`solve_along_rays`.
_SOLVE_CHUNK = 1 << 16


@dataclass
class RayFit:
    """Depths along camera rays from :func:`solve_along_rays`.

    Attributes
    ----------
    t : (N,) float64, metres
        Distance along the unit ray; NaN where unsolved.
    sigma_t : (N,) float64, metres
        1-σ of ``t`` from the intersection geometry (``inf`` where the ray runs along the
        constraint, NaN where unsolved).
    chi : (N,) float64
        Normalised reprojection residual ``sqrt(Σ r_i²)``; only meaningful where two
        coordinates constrain the point (it is ≈ 0 with one).
    n_constraints : (N,) int
        Coordinates used (0, 1 or 2).
    sin_angle : (N,) float64
        Effective sine of the triangulation angle: the lateral 1-σ of the constraint at the
        point (``σ_px · z_other / f_other`` metres) over ``sigma_t``. 1 for a ray crossing the
        projector's ray/plane at right angles, → 0 as the ray runs along it.
    dt_dq : (N, 2) float64, metres per pixel of the other view
        ``∂t/∂q_other`` at the solution: how the depth follows an error of the target (the
        weighted least-squares gain). Propagates a target's error sources one by one, e.g. the
        camera–camera route's share of each camera's code noise (:func:`fuse_cameras`).
    """

    t: np.ndarray
    sigma_t: np.ndarray
    chi: np.ndarray
    n_constraints: np.ndarray
    sin_angle: np.ndarray
    dt_dq: np.ndarray | None = None


def _project_along(other: Camera, o, d, t):
    q, ok = other.project(o + t[:, None] * d)
    return q, ok


def _whitening(cov, use):
    """Inverse Cholesky factors ``L⁻¹`` of ``(N, 2, 2)`` covariances (``Σ = L·Lᵀ``), so that
    ``L⁻¹·r`` has unit covariance. A row constrained in one coordinate only (``use``) gets
    ``1/sqrt(Σ_ii)`` on that coordinate; a row whose used block is not positive definite gets
    zeros (unconstrained). Returns ``(N, 2, 2)`` and the updated ``use``."""
    wh = np.zeros(cov.shape)
    both = use.all(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.sqrt(cov[:, 0, 0])
        b = cov[:, 1, 0] / a
        c2 = cov[:, 1, 1] - b * b
        # positive definite, and not so ill-conditioned that the inverse is rounding noise
        pd = both & (a > 0) & (c2 > 1e-12 * cov[:, 1, 1]) & np.isfinite(c2)
        c = np.sqrt(np.where(pd, c2, 1.0))
        wh[pd, 0, 0] = 1.0 / a[pd]
        wh[pd, 1, 0] = -b[pd] / (a[pd] * c[pd])
        wh[pd, 1, 1] = 1.0 / c[pd]
        for i in (0, 1):
            one = use[:, i] & ~use[:, 1 - i] & (cov[:, i, i] > 0) & np.isfinite(cov[:, i, i])
            wh[one, i, i] = 1.0 / np.sqrt(cov[one, i, i])
            use[~both & ~one, i] = False
    use[both & ~pd] = False
    return wh, use


def solve_along_rays(o_world, d_world, other: Camera, q_other, sigma_other=None, *,
                     cov_other=None) -> RayFit:
    """Depth along each camera ray that best reprojects into ``other`` at ``q_other``.

    Minimises ``Σ_i ((π_i(o + t·d) − q_i) / σ_i)²`` over ``t`` (module docstring), the
    triangulation of the camera ray against the projector ray (both coordinates) or the
    projector's column plane (``q_other[:, 1]`` NaN). With ``cov_other`` the residual is
    weighted by the full 2 × 2 covariance instead, ``rᵀ·Σ⁻¹·r`` with ``r = π(o + t·d) − q``
    (generalised least squares, solved on ``L⁻¹·r`` with ``Σ = L·Lᵀ``): a target located
    through a map that mixes its axes (the camera–camera route's code match, where ``∂q/∂code``
    turns a coarse row code's noise into both pixel axes) has correlated coordinate errors,
    and per-axis σ would weigh them wrongly and misstate ``σ_t``.

    Parameters
    ----------
    o_world : (N, 3) float64, metres, world frame
        Ray origins (camera centre).
    d_world : (N, 3) float64, unit vectors, world frame
        Ray directions.
    other : Camera
        The projector (or a second camera).
    q_other : (N, 2) float64, pixels of ``other``
        Target coordinates; NaN marks a coordinate that is not constrained.
    sigma_other : (N, 2) float64, pixels of ``other``
        1-σ noise of each coordinate, > 0 (independent coordinates). Not needed with
        ``cov_other``.
    cov_other : (N, 2, 2) float64, pixels² of ``other``, optional
        Covariance of the target instead of ``sigma_other``; a row whose block over the
        constrained coordinates is not positive definite is left unsolved (NaN).

    Returns
    -------
    RayFit
    """
    o = as_array(o_world, "o_world", shape=(None, 3), finite=False)
    n = o.shape[0]
    d = as_array(d_world, "d_world", shape=(n, 3), finite=False)
    q = as_array(q_other, "q_other", shape=(n, 2), finite=False)
    if cov_other is None:
        if sigma_other is None:
            raise InputError("sigma_other, cov_other: expected one of them, got neither")
        s = as_array(sigma_other, "sigma_other", shape=(n, 2), finite=False)
        cov = None
    else:
        s = None
        cov = as_array(cov_other, "cov_other", shape=(n, 2, 2), finite=False)
    if n <= _SOLVE_CHUNK:
        return _solve_block(o, d, other, q, s, cov)
    # no block of one ray: numpy multiplies a single row by a matrix on another path, which
    # can round the last bit differently
    edges = list(range(0, n, _SOLVE_CHUNK)) + [n]
    if edges[-1] - edges[-2] == 1:
        del edges[-2]
    parts = [_solve_block(o[a:b], d[a:b], other, q[a:b], None if s is None else s[a:b],
                          None if cov is None else cov[a:b]) for a, b in zip(edges, edges[1:])]
    return RayFit(*(np.concatenate([getattr(f, k) for f in parts])
                    for k in ("t", "sigma_t", "chi", "n_constraints", "sin_angle", "dt_dq")))


def _solve_block(o, d, other: Camera, q, s, cov) -> RayFit:
    """:func:`solve_along_rays` on checked arrays (``s`` or ``cov`` None), all rows at once."""
    n = o.shape[0]
    if cov is None:
        use = np.isfinite(q) & np.isfinite(s) & (s > 0)
        wh = np.zeros((n, 2, 2))
        wh[:, [0, 1], [0, 1]] = np.where(use, 1.0 / np.where(use, s, 1.0), 0.0)
    else:
        wh, use = _whitening(cov, np.isfinite(q))
    use &= np.isfinite(o).all(1)[:, None] & np.isfinite(d).all(1)[:, None]
    wh[~use.any(1)] = 0.0
    # Linear start in the other's normalised (undistorted) coordinates: with P(t) = A + t·B in
    # its frame, u·P_z = P_x is linear in t (times f: pixels). Distortion is ignored here (GN
    # handles it).
    R, T = other.T_cam_world.R, other.T_cam_world.t
    A = o @ R.T + T
    B = d @ R.T
    f = np.array([other.fx, other.fy])
    c = np.array([other.cx, other.cy])
    u = (np.where(use, q, 0.0) - c) / f
    a = np.einsum("nij,nj->ni", wh, f * (B[:, :2] - u * B[:, 2:3]))
    b = np.einsum("nij,nj->ni", wh, f * (u * A[:, 2:3] - A[:, :2]))
    den = (a * a).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(den > 0, (a * b).sum(1) / den, np.nan)
    t[~use.any(1)] = np.nan
    # Gauss–Newton on the true (distorted) projection, central differences along the ray.
    sig_t = np.full(n, np.nan)
    chi = np.full(n, np.nan)
    dt_dq = np.full((n, 2), np.nan)
    qs = np.where(use, q, 0.0)
    for step in range(_GN_STEPS + 1):
        live = np.isfinite(t) & (t > 0)
        if not live.any():
            break
        idx = np.flatnonzero(live)
        ti = t[idx]
        h = 1e-6 * np.maximum(ti, 1e-3)
        oi, di, whi = o[idx], d[idx], wh[idx]
        q0, ok0 = _project_along(other, oi, di, ti)
        qp, okp = _project_along(other, oi, di, ti + h)
        qm, okm = _project_along(other, oi, di, ti - h)
        ok = ok0 & okp & okm
        r = np.einsum("nij,nj->ni", whi, np.where(use[idx], q0 - qs[idx], 0.0))
        J = np.einsum("nij,nj->ni", whi, np.where(use[idx], (qp - qm) / (2 * h[:, None]), 0.0))
        jj = (J * J).sum(1)
        good = ok & (jj > 0) & np.isfinite(jj)
        with np.errstate(divide="ignore", invalid="ignore"):
            sig_t[idx] = np.where(good, 1.0 / np.sqrt(jj), np.where(ok & (jj == 0), np.inf, np.nan))
            chi[idx] = np.where(ok, np.sqrt((r * r).sum(1)), np.nan)
            # ∂t/∂q: δt = −Jᵀ·δr / JᵀJ with δr = −L⁻¹·δq
            dt_dq[idx] = np.where(good[:, None],
                                  np.einsum("nji,nj->ni", whi, J) / jj[:, None], np.nan)
        bad = idx[~ok]
        t[bad] = np.nan
        if step == _GN_STEPS:
            break
        upd = np.where(good, -(J * r).sum(1) / np.where(good, jj, 1.0), 0.0)
        # keep a step from crossing behind the camera
        t[idx] = np.where(good, np.maximum(ti + upd, 0.5 * ti), ti)
    z = ((o + np.nan_to_num(t)[:, None] * d) @ R.T + T)[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        # lateral σ of the constraint: (trace Σ⁻¹)^(-1/2), (Σ 1/σ_i²)^(-1/2) for diagonal Σ
        s_eff = 1.0 / np.sqrt((wh * wh).sum((1, 2)))
        sin_angle = np.clip(s_eff * z / np.sqrt(other.fx * other.fy) / sig_t, 0.0, 1.0)
    sin_angle[~np.isfinite(t)] = np.nan
    dt_dq[~np.isfinite(t)] = np.nan
    return RayFit(t, sig_t, chi, use.sum(1), sin_angle, dt_dq)


# ------------------------------------------------------------------------- point maps


#: Upper bound of the rig-derived smallest ray angle, degrees (the fixed limit of earlier
#: versions: wide rigs are judged as before).
MIN_ANGLE_CAP_DEG = 3.0
#: The rig-derived smallest ray angle as a fraction of the rig's median ray angle.
MIN_ANGLE_FRACTION = 0.25
#: Lower bound of the rig-derived smallest ray angle, degrees: rays that meet at less are
#: rejected however narrow the whole rig is (a camera that sees the projector's planes
#: edge-on).
MIN_ANGLE_FLOOR_DEG = 0.5


def rig_min_angle_deg(sin_angle) -> float:
    """Smallest accepted angle between the two rays of a point, from the rig itself, degrees.

    ``MIN_ANGLE_FRACTION × median ray angle`` over the solved rays, clipped to
    ``[MIN_ANGLE_FLOOR_DEG, MIN_ANGLE_CAP_DEG]``: a stereo pair 40 mm apart at 1 m meets at
    ≈ 2.3° everywhere, and a fixed 3° limit rejected every one of its points; a point whose
    rays meet at a quarter of the rig's usual angle is the grazing, ill-conditioned case the
    limit is for. The depth's σ carries the rest (``max_sigma_ratio``).

    Parameters
    ----------
    sin_angle : (N,) float
        Sine of each solved point's ray angle (NaN ignored).

    Returns
    -------
    float, degrees (the cap when no angle is finite)
    """
    a = np.degrees(np.arcsin(np.clip(np.asarray(sin_angle, np.float64), 0.0, 1.0)))
    a = a[np.isfinite(a)]
    if a.size == 0:
        return MIN_ANGLE_CAP_DEG
    return float(np.clip(MIN_ANGLE_FRACTION * np.median(a), MIN_ANGLE_FLOOR_DEG,
                         MIN_ANGLE_CAP_DEG))


def _map(a, name, shape, dtype=np.float64):
    a = as_array(a, name, dtype=dtype, finite=False)
    if a.shape != shape:
        raise ShapeError(f"{name}: expected shape {shape} (the decode's x map), got {a.shape}")
    return a


def _classify(fit: RayFit, p, *, max_sigma_ratio, max_sigma, min_angle_deg, max_chi):
    """Rejection reasons of solved rays (shared by both triangulations).

    ``fit`` holds the solutions of ``n`` rays, ``p`` ``(n, 3)`` their points ``o + t·d`` (set
    to NaN here where the reason is not :data:`OK`, in place). Returns the ``(n,)`` uint8
    reasons: :data:`BEHIND`, :data:`UNCERTAIN` (angle below ``min_angle_deg`` — from the rig,
    :func:`rig_min_angle_deg`, when None — infinite σ, or σ above ``max_sigma_ratio`` × the
    median σ of the points left, or above ``max_sigma``), :data:`INCONSISTENT` (``χ >
    max_chi``), else :data:`OK`.
    """
    sig, chi = fit.sigma_t, fit.chi
    reason = np.full(sig.size, OK, np.uint8)
    reason[~(np.isfinite(fit.t) & (fit.t > 0))] = BEHIND
    live = reason == OK
    with np.errstate(invalid="ignore"):
        narrow = fit.sin_angle < np.sin(np.radians(
            rig_min_angle_deg(fit.sin_angle[live]) if min_angle_deg is None
            else min_angle_deg))
        reason[live & (~np.isfinite(sig) | narrow)] = UNCERTAIN
        live = reason == OK
        if live.any():
            limit = max_sigma_ratio * float(np.median(sig[live]))
            if max_sigma is not None:
                limit = min(limit, check_positive(max_sigma, "max_sigma"))
            reason[live & (sig > limit)] = UNCERTAIN
        reason[(reason == OK) & (chi > max_chi)] = INCONSISTENT
    p[reason != OK] = np.nan
    return reason
