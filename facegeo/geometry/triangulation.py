"""Triangulation of structured-light decodes: camera rays against the projector, fused over cameras.

A camera pixel ``q`` that decoded the projector coordinate ``(x, y)`` lies on the camera ray
``p(t) = o + t·d`` (``o`` the camera centre, ``d`` the unit ray through the pixel centre, ``t``
metres). Every solver here finds ``t`` by weighted least squares on the **projector's
reprojection residual** along that ray,

    r_i(t) = (π_i(o + t·d) − x_i) / σ_i,     i ∈ {x, y} (y only where it was decoded),

where ``π`` is the projector's projection (:meth:`facegeo.geometry.camera.Camera.project`,
distortion included) and ``σ_i`` the decode's 1-σ noise in projector pixels. With ``x`` only this
is the camera ray against the projector's column *plane* (a curved sheet when the projector has
distortion); with ``x`` and ``y`` it is the ray against the projector *ray*, weighted by the
decode's noise (the camera pixel is taken as exact: its centre is where the measurement was made,
so all the error sits in the decoded code). A linear (algebraic) solution starts three
Gauss–Newton steps in float64.

Uncertainty comes from the intersection geometry: with ``J_i = ∂r_i/∂t`` at the solution,
``σ_t = (Σ J_i²)^(-1/2)`` metres along the ray. ``J`` shrinks as the camera ray turns parallel to
the projector's column plane (the projector code stops changing along the ray), so ``σ_t`` grows
without bound there and :func:`triangulate_maps` rejects the point by threshold rather than
placing it anywhere. The decode noise ``σ_i`` is widened by the pixel's **footprint** in the
projector: a camera pixel spanning ``g`` projector pixels (``g`` the largest code step to a
neighbouring pixel) integrates a box of that width. On a smooth surface the code is sampled at
the pixel centre and that box adds no error, so only the excess over ``footprint_ratio`` times
the map's median footprint counts, as a uniform box of variance ``excess²/12``: grazing
surfaces (strongly foreshortened in the camera) and depth discontinuities (a code jump between
neighbours) carry large σ instead of wild points. (An assumption of this module, not of the
paper: a decoder's own σ should grow there too, but a plain Gray decode reports none.) With ``x`` and ``y`` both decoded,
the normalised residual ``χ = sqrt(Σ r_i²)`` (one degree of freedom) is the camera–projector
reprojection consistency test.

:func:`fuse_cameras` checks every camera's points against the other cameras' point maps
(free-space violations are rejected, agreeing points are averaged with inverse-variance weights)
and :func:`triangulate_camera_pair` triangulates two cameras through matching projector codes,
for rigs whose projector is not calibrated (:func:`triangulate_camera_pairs`: every camera
against every other, merged per camera, ready for :func:`fuse_cameras`). There the match's 2-D
covariance in the other camera is used whole (generalised least squares), and the maps carry
how each depth follows each camera's code noise (:class:`CodeGains`), because two cameras'
points are then made from the same code maps and :func:`fuse_cameras` must not count them as
independent.

References
----------
.. [1] Debevec et al., "Acquiring the Reflectance Field of a Human Face", SIGGRAPH 2000, §2
   (geometry from structured light projected by a video projector, seen by the two cameras).
.. [2] Hartley & Zisserman, *Multiple View Geometry*, 2nd ed., §12 (triangulation: minimise the
   reprojection error, not an algebraic distance).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facegeo.checks import as_array, check_positive
from facegeo.errors import InputError, ShapeError
from facegeo.geometry.camera import Camera

__all__ = [
    "BEHIND",
    "INCONSISTENT",
    "NO_CODE",
    "OCCLUDED_VIEW",
    "OK",
    "OUTLIER",
    "REASONS",
    "UNCERTAIN",
    "CodeGains",
    "FusedPoints",
    "PointMap",
    "RayFit",
    "code_footprint",
    "fuse_cameras",
    "match_projector_codes",
    "neighbour_spacing",
    "solve_along_rays",
    "triangulate_camera_pair",
    "triangulate_camera_pairs",
    "triangulate_maps",
]

#: Reason codes of :attr:`PointMap.reason` (``uint8``).
OK, NO_CODE, BEHIND, UNCERTAIN, INCONSISTENT, OUTLIER, OCCLUDED_VIEW = range(7)
#: Names of the reason codes, indexed by code.
REASONS = ("ok", "no_code", "behind", "uncertain", "inconsistent", "outlier",
           "free_space_violation")

#: Gauss–Newton steps after the linear start (the residual is nearly linear in t; 3 reach
#: float64 rounding on the test rigs).
_GN_STEPS = 3
#: Smallest ``det Σ / (tr Σ)²`` (≈ smallest / largest eigenvalue) of a camera–camera match's
#: 2 × 2 covariance: below it the match is degenerate (B's neighbouring pixels all on one row or
#: column, so the fit sees no change of that axis with the code and claims zero variance along
#: it; such a point came out with σ ≈ 1e-17 m).
_MIN_COV_RATIO = 1e-6


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
        use = np.isfinite(q) & np.isfinite(s) & (s > 0)
        wh = np.zeros((n, 2, 2))
        wh[:, [0, 1], [0, 1]] = np.where(use, 1.0 / np.where(use, s, 1.0), 0.0)
    else:
        cov = as_array(cov_other, "cov_other", shape=(n, 2, 2), finite=False)
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


@dataclass
class CodeGains:
    """How a camera–camera point map's depths follow the decode noise they were made from.

    Camera A's pixel ``q`` matched into B through the codes (:func:`triangulate_camera_pair`)
    has, to first order, the depth error

        δt = dt_dcodeᵀ·n_A(q) − Σ_j h_j·dt_dcodeᵀ·n_B(j),

    ``n_A(q)`` A's code noise at ``q``, ``n_B(j)`` B's at the ``k`` pixels of the local affine
    fit, ``h_j`` their weights in the fitted location (``Σ h_j = 1``, ``Σ h_j² = (G⁻¹)₃₃``):
    both codes enter through the same ``∂q_B/∂code``. B's pixel ``q_B`` at the match is one of
    those ``j``, with ``h ≈ (G⁻¹)₃₃`` (exact when A's code sits at the neighbours' mean code), and
    ``q_B``'s own point (B against A) is made from ``n_B(q_B)`` and, through *its* fit, from
    ``n_A(q)``: the two cameras' points of one surface point share code noise.
    :func:`fuse_cameras` uses these gains for that covariance (``Σ`` the diagonal code
    covariances ``sigma_code²``),

        Cov(δt_A, δt_B) = dt_dcode_Aᵀ·Σ_A·partner_dt_dcode_B[A]
                          + partner_dt_dcode_A[B]ᵀ·Σ_B·dt_dcode_B.

    Attributes
    ----------
    sigma_code : (H, W, 2) float64, projector pixels
        The camera's own decode noise (x, y), 1 σ.
    dt_dcode : (H, W, 2) float64, metres per projector pixel
        Depth along the ray per unit error of the camera's own code at the pixel; NaN without a
        point.
    partner_dt_dcode : dict of str to (H, W, 2) float64, metres per projector pixel
        Per partner camera: depth per unit error of that camera's code at the pixel its match
        landed on (``−h·dt_dcode`` of the pair, merged over partners like the depths); 0 where
        that partner did not contribute.
    partner_weight : dict of str to (H, W) float64
        Per partner camera: ``h = (G⁻¹)₃₃`` of the fit into it (``Σ_j h_j²``, ≈ 1/k). Two
        cameras' points fitted into the same third camera near the same code share its
        neighbours' noise, ``Cov ≈ partner_dt_dcode_Aᵀ·Σ·partner_dt_dcode_B / sqrt(h_A·h_B)``.
    """

    sigma_code: np.ndarray
    dt_dcode: np.ndarray
    partner_dt_dcode: dict
    partner_weight: dict


@dataclass
class PointMap:
    """One camera's triangulated points on its pixel grid.

    Attributes
    ----------
    camera : str
        Camera name.
    p_world : (H, W, 3) float64, metres, world frame
        Surface point per pixel; NaN where ``reason != OK``.
    sigma : (H, W) float64, metres
        1-σ along the camera ray (intersection geometry, module docstring).
    chi : (H, W) float64
        Camera–projector reprojection residual in σ (NaN with one coordinate).
    confidence : (H, W) float32, 0..1
        The decode's confidence.
    reason : (H, W) uint8
        :data:`OK` or why the pixel has no point (:data:`REASONS`).
    center_world : (3,) float64, metres
        The camera centre (points' normals are oriented toward it).
    code_gains : CodeGains or None
        Camera–camera maps only: how the depths follow each camera's code noise, for the
        covariance of two cameras' points made from the same code maps (:func:`fuse_cameras`).
        ``None`` (camera–projector maps): the cameras' points are independent.
    """

    camera: str
    p_world: np.ndarray
    sigma: np.ndarray
    chi: np.ndarray
    confidence: np.ndarray
    reason: np.ndarray
    center_world: np.ndarray
    code_gains: CodeGains | None = None

    @property
    def valid(self) -> np.ndarray:
        """``(H, W)`` bool: the pixel has a point."""
        return self.reason == OK

    @property
    def depth(self) -> np.ndarray:
        """Distance from the camera centre, ``(H, W)`` float64, metres (NaN without a point)."""
        return np.linalg.norm(self.p_world - self.center_world, axis=-1)

    def reason_counts(self) -> dict:
        """``{reason name: pixel count}`` over the whole map."""
        counts = np.bincount(self.reason.ravel(), minlength=len(REASONS))
        return {REASONS[i]: int(counts[i]) for i in range(len(REASONS))}

    def reject(self, mask: np.ndarray, code: int) -> None:
        """Mark valid pixels in ``mask`` as rejected with ``code`` (in place)."""
        m = mask & (self.reason == OK)
        self.reason[m] = code
        self.p_world[m] = np.nan


def code_footprint(code: np.ndarray) -> np.ndarray:
    """Projector pixels spanned by each camera pixel: the largest code step to a 4-neighbour.

    Parameters
    ----------
    code : (H, W) float, projector pixels (NaN invalid)

    Returns
    -------
    (H, W) float64, projector pixels; 0 where no neighbour is decoded.
    """
    c = np.asarray(code, np.float64)
    g = np.zeros(c.shape)
    with np.errstate(invalid="ignore"):
        dx = np.abs(np.diff(c, axis=1))
        dy = np.abs(np.diff(c, axis=0))
    dx = np.nan_to_num(dx, nan=0.0)
    dy = np.nan_to_num(dy, nan=0.0)
    g[:, 1:] = np.maximum(g[:, 1:], dx)
    g[:, :-1] = np.maximum(g[:, :-1], dx)
    g[1:] = np.maximum(g[1:], dy)
    g[:-1] = np.maximum(g[:-1], dy)
    return g


def _excess_footprint(code: np.ndarray, ok: np.ndarray, ratio: float) -> np.ndarray:
    g = code_footprint(code)
    sel = ok & (g > 0)
    if not sel.any():
        return np.zeros(code.shape)
    return np.maximum(g - ratio * float(np.median(g[sel])), 0.0)


def _map(a, name, shape, dtype=np.float64):
    a = as_array(a, name, dtype=dtype, finite=False)
    if a.shape != shape:
        raise ShapeError(f"{name}: expected shape {shape} (the decode's x map), got {a.shape}")
    return a


def triangulate_maps(camera: Camera, projector: Camera, x, y=None, *, valid=None,
                     confidence=None, sigma_x=None, sigma_y=None, min_confidence: float = 0.2,
                     default_sigma_px: float = 0.3, footprint_ratio: float | None = 2.0,
                     max_sigma_ratio: float = 5.0, max_sigma: float | None = None,
                     min_angle_deg: float | None = None, max_chi: float = 4.0, spike_sigmas: float = 6.0,
                     spike_floor: float = 1e-3) -> PointMap:
    """Triangulate one camera's decode maps against the projector.

    Parameters
    ----------
    camera : Camera
        The camera that saw the patterns; its size must equal the maps'.
    projector : Camera
        The projector (an inverse camera).
    x, y : (H, W) float, projector pixels (pixel-centre convention, NaN invalid)
        Decoded projector column and row; ``y`` ``None`` or all-NaN triangulates against
        column planes only.
    valid : (H, W) bool, optional
        The decoder's validity mask (default: finite ``x``).
    confidence : (H, W) float, 0..1, optional
        Pixels below ``min_confidence`` get no point (reason :data:`NO_CODE`).
    sigma_x, sigma_y : (H, W) float, projector pixels, optional
        Decode noise (1 σ); NaN or missing → ``default_sigma_px``.
    footprint_ratio : float or None
        Widen σ by the pixel's footprint in the projector beyond this multiple of the map's
        median footprint (module docstring); ``None`` disables it.
    max_sigma_ratio : float
        Reject points whose σ exceeds this multiple of the map's median σ (reason
        :data:`UNCERTAIN`): near-parallel ray/plane, grazing surfaces, silhouettes.
    max_sigma : float, metres, optional
        Absolute σ limit as well.
    min_angle_deg : float, degrees, optional
        Reject points whose effective triangulation angle (:attr:`RayFit.sin_angle`) is below
        this (reason :data:`UNCERTAIN`): a camera ray nearly parallel to the projector's plane.
        Default from the rig: :func:`rig_min_angle_deg` of the solved rays (at most 3°).
    max_chi : float
        Reject points whose camera–projector residual exceeds this many σ (reason
        :data:`INCONSISTENT`; only where ``y`` was decoded).
    spike_sigmas, spike_floor : float, metres
        Reject points farther along their ray from the 3 × 3 median depth than
        ``spike_sigmas·σ_min + spike_floor`` (``σ_min`` the smallest σ in the 3 × 3 window) (reason :data:`OUTLIER`; isolated wrong codes).

    Returns
    -------
    PointMap

    Notes
    -----
    Implements the ray/plane and ray/ray triangulation of the module docstring. Deviation from
    a plain midpoint: the projector's reprojection error is minimised, because the decoded code
    carries the noise and the camera pixel centre does not.
    """
    if not isinstance(camera, Camera) or not isinstance(projector, Camera):
        uncal = ("; an uncalibrated projector (a rig.Projector: resolution only) must be "
                 "calibrated first" if getattr(projector, "calibrated", True) is False else "")
        raise InputError("camera, projector: expected facegeo.geometry.camera.Camera objects, "
                         f"got {type(camera).__name__}, {type(projector).__name__}{uncal}")
    x = as_array(x, "x", shape=(None, None), finite=False)
    shape = x.shape
    if shape != (camera.height, camera.width):
        raise ShapeError(f"x: expected the camera {camera.name!r}'s image shape "
                         f"{(camera.height, camera.width)}, got {shape}")
    y = np.full(shape, np.nan) if y is None else _map(y, "y", shape)
    ok = np.isfinite(x) if valid is None else _map(valid, "valid", shape, bool) & np.isfinite(x)
    conf = (np.ones(shape, np.float32) if confidence is None
            else _map(confidence, "confidence", shape, np.float32))
    with np.errstate(invalid="ignore"):
        ok &= ~(conf < min_confidence)
    d0 = check_positive(default_sigma_px, "default_sigma_px")
    sx = np.full(shape, d0) if sigma_x is None else _map(sigma_x, "sigma_x", shape)
    sy = np.full(shape, d0) if sigma_y is None else _map(sigma_y, "sigma_y", shape)
    sx = np.where(np.isfinite(sx) & (sx > 0), sx, d0)
    sy = np.where(np.isfinite(sy) & (sy > 0), sy, d0)
    xm = np.where(ok, x, np.nan)
    ym = np.where(ok, y, np.nan)
    if footprint_ratio is not None:
        sx = np.sqrt(sx**2 + _excess_footprint(xm, ok, footprint_ratio) ** 2 / 12.0)
        sy = np.sqrt(sy**2 + _excess_footprint(ym, ok, footprint_ratio) ** 2 / 12.0)
    reason = np.where(ok, OK, NO_CODE).astype(np.uint8)
    idx = np.flatnonzero(ok)
    o, dirs = camera.pixel_rays(camera.pixel_grid().reshape(-1, 2)[idx])
    fit = solve_along_rays(o, dirs, projector,
                           np.stack([x.ravel()[idx], y.ravel()[idx]], 1),
                           np.stack([sx.ravel()[idx], sy.ravel()[idx]], 1))
    fit.chi = np.where(fit.n_constraints == 2, fit.chi, np.nan)
    p, sig, chi, r = _classify(reason.ravel(), idx, fit, o, dirs, max_sigma_ratio=max_sigma_ratio,
                               max_sigma=max_sigma, min_angle_deg=min_angle_deg,
                               max_chi=max_chi)
    pm = PointMap(camera.name, p.reshape(shape + (3,)), sig.reshape(shape), chi.reshape(shape),
                  conf.astype(np.float32), r.reshape(shape), camera.center_world.copy())
    _reject_spikes(pm, spike_sigmas, spike_floor)
    return pm


def _classify(reason, idx, fit: RayFit, o, d, *, max_sigma_ratio, max_sigma, min_angle_deg,
              max_chi):
    """Points and rejection reasons of solved rays (shared by both triangulations).

    ``reason`` (flat, OK where a ray was solved) is updated in place; ``idx`` are the flat
    pixels of the rays ``o + t·d`` in ``fit``. Returns flat ``p, sigma, chi, reason``.
    """
    n = reason.size
    sig = np.full(n, np.nan)
    chi = np.full(n, np.nan)
    sig[idx], chi[idx] = fit.sigma_t, fit.chi
    reason[idx[~(np.isfinite(fit.t) & (fit.t > 0))]] = BEHIND
    live = reason == OK
    with np.errstate(invalid="ignore"):
        narrow = np.zeros(n, bool)
        narrow[idx] = fit.sin_angle < np.sin(np.radians(
            rig_min_angle_deg(fit.sin_angle[live[idx]]) if min_angle_deg is None
            else min_angle_deg))
        reason[live & (~np.isfinite(sig) | narrow)] = UNCERTAIN
        live = reason == OK
        if live.any():
            limit = max_sigma_ratio * float(np.median(sig[live]))
            if max_sigma is not None:
                limit = min(limit, check_positive(max_sigma, "max_sigma"))
            reason[live & (sig > limit)] = UNCERTAIN
        reason[(reason == OK) & (chi > max_chi)] = INCONSISTENT
    p = np.full((n, 3), np.nan)
    good = reason[idx] == OK
    p[idx[good]] = o[good] + fit.t[good, None] * d[good]
    return p, sig, chi, reason


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


def _median3(a: np.ndarray) -> np.ndarray:
    """3 × 3 NaN-ignoring median (NaN where the window holds fewer than 3 values)."""
    H, W = a.shape
    pad = np.pad(a, 1, constant_values=np.nan)
    win = np.sort(np.stack([pad[i:i + H, j:j + W] for i in range(3) for j in range(3)], -1),
                  axis=-1)  # NaN sort last
    cnt = np.isfinite(win).sum(-1)
    lo = np.take_along_axis(win, np.maximum(cnt - 1, 0)[..., None] // 2, -1)[..., 0]
    hi = np.take_along_axis(win, (cnt // 2)[..., None], -1)[..., 0]
    return np.where(cnt >= 3, 0.5 * (lo + hi), np.nan)


def _min3(a: np.ndarray) -> np.ndarray:
    """3 × 3 NaN-ignoring minimum."""
    H, W = a.shape
    pad = np.pad(np.where(np.isfinite(a), a, np.inf), 1, constant_values=np.inf)
    m = np.min(np.stack([pad[i:i + H, j:j + W] for i in range(3) for j in range(3)]), axis=0)
    return np.where(np.isfinite(m), m, np.nan)


def _reject_spikes(pm: PointMap, k: float, floor: float) -> None:
    # tolerance from the smallest σ around the pixel: a wrong code inflates its own σ (and its
    # 4-neighbours') through the footprint term, which must not hide it from this test
    depth = pm.depth
    med = _median3(depth)
    with np.errstate(invalid="ignore"):
        spike = np.abs(depth - med) > k * _min3(np.where(pm.valid, pm.sigma, np.nan)) + floor
        lonely = pm.valid & ~np.isfinite(med)  # fewer than 3 points in the 3 × 3 window
    pm.reject(spike | lonely, OUTLIER)


# ------------------------------------------------------------------------- fusion


@dataclass
class FusedPoints:
    """Points of several cameras after the cross-camera check.

    Attributes
    ----------
    p_world : (N, 3) float64, metres, world frame
    sigma : (N,) float64, metres (1 σ, after averaging with agreeing cameras)
    confidence : (N,) float32, 0..1
    camera : (N,) int, index of the observing camera (into ``camera_names``)
    pixel : (N, 2) int, (column, row) in that camera
    confirmed : (N,) bool, another camera saw the same surface within tolerance
    camera_names : list of str
    centers_world : (C, 3) float64, metres, camera centres
    """

    p_world: np.ndarray
    sigma: np.ndarray
    confidence: np.ndarray
    camera: np.ndarray
    pixel: np.ndarray
    confirmed: np.ndarray
    camera_names: list
    centers_world: np.ndarray

    def __len__(self) -> int:
        return int(self.p_world.shape[0])

    @property
    def view_dirs(self) -> np.ndarray:
        """Unit vectors from each point toward its camera, ``(N, 3)`` float64, world frame."""
        v = self.centers_world[self.camera] - self.p_world
        return v / np.linalg.norm(v, axis=1, keepdims=True)


def _pixel_of(cam: Camera, p) -> tuple[np.ndarray, np.ndarray]:
    """The pixel of ``cam`` each world point ``p`` (N, 3) falls in, (N, 2) int64 (column, row),
    clipped to the image, and whether it is in front and inside the image (N,) bool: the
    partner pixel :func:`fuse_cameras` compares a point with."""
    q, front = cam.project(p)
    ok = front & cam.in_image(q)
    qi = np.rint(np.where(ok[:, None], q, 0)).astype(np.int64)
    qi[:, 0] = qi[:, 0].clip(0, cam.width - 1)
    qi[:, 1] = qi[:, 1].clip(0, cam.height - 1)
    return qi, ok


def fuse_cameras(maps: list[PointMap], cameras: list[Camera], *, tol_sigmas: float = 4.0,
                 tol_floor: float = 1e-3, average: bool = True,
                 cluster_spacings: float | None = 2.0,
                 min_cluster_fraction: float = 0.1) -> FusedPoints:
    """Check every camera's points against the others' and merge them into one cloud.

    For a point ``p`` of camera A seen at pixel ``q_B`` of camera B, let ``d = |p − c_B|`` and
    ``D`` the 3 × 3 median depth of B's own points around ``q_B``, with tolerance
    ``τ = tol_sigmas·sqrt(σ_A² + σ_B²) + tol_floor``:

    * ``d < D − τ``: B looked through the place where ``p`` should be — a free-space violation;
      the point is rejected (reason :data:`OCCLUDED_VIEW` in A's map).
    * ``|d − D| ≤ τ``: confirmed; with ``average`` the point becomes the inverse-variance mean of
      ``p`` and B's point at the nearest pixel (σ shrinks accordingly; when A's and B's points
      are each other's nearest, both average to the same point and one copy is kept).
    * ``d > D + τ`` or B has no point there: no evidence (occluded in B, or unseen).

    The fused σ is that of the weighted mean ``Σ w_i p_i / Σ w_i`` (``w_i = 1/σ_i²``):
    ``σ² = (Σ w_i + 2 Σ_{i<j} w_i w_j C_ij (v_i·v_j)) / (Σ w_i)²``, ``v`` the rays, ``C_ij``
    the covariance of the two depths. Camera–projector points are independent (``C = 0``,
    ``σ² = 1 / Σ w_i``). Camera–camera points are not: A's and B's points of one surface point
    are made from the same two code maps — A's code at A's pixel is among the neighbours of B's
    local fit into A, and B's code at B's pixel among A's — so ``C_ij`` comes from the maps'
    :class:`CodeGains` (and from a third camera both were fitted into). Counted as independent,
    as until this version, that σ was optimistic (plane, two cameras, 0.1 px codes: RMS z
    1.118, 1.10 of the per-camera maps'; now 1.024; the synthetic small face: 1.156, now
    1.071). The weights stay ``1/σ_i²``, so the positions are unchanged: with correlations of
    0.1–0.25 between estimates of similar σ a generalised (correlation-aware) mean would move
    them little.

    Then the fused cloud is split into clusters (points closer than ``cluster_spacings`` times
    the median distance to the 6th-nearest neighbour are linked) and clusters smaller than
    ``min_cluster_fraction`` of the largest are dropped (reason :data:`OUTLIER`): a patch of
    consistently wrong codes (a flipped coarse Gray bit) floats off the surface, and when no
    other camera sees through it the free-space test cannot catch it. Limitation: a wrong patch
    that lands behind the visible surface, attached to it, and hidden from every other camera
    survives with ``x``-only decodes (with ``y`` the camera–projector residual rejects it).

    Parameters
    ----------
    maps : list of PointMap
        One per camera (modified in place: rejected points get a reason).
    cameras : list of Camera
        The same cameras, in the same order.
    tol_sigmas, tol_floor : float, tol_floor in metres
        Agreement tolerance.
    average : bool
        Average confirmed points with the other camera's.
    cluster_spacings : float, optional
        Link distance of the cluster filter in median 6th-neighbour distances (``None``: no
        filter).
    min_cluster_fraction : float, 0..1
        Smallest cluster kept, as a fraction of the largest.

    Returns
    -------
    FusedPoints
    """
    if len(maps) != len(cameras) or not maps:
        raise InputError(f"maps, cameras: expected one point map per camera (>= 1), got "
                         f"{len(maps)} maps and {len(cameras)} cameras")
    depth_med = [_median3(m.depth) for m in maps]
    # check against the maps as triangulated (rejections below must not change the evidence)
    masks = [m.valid.copy() for m in maps]
    points = [m.p_world.copy() for m in maps]
    out = []
    for a, (ma, ca) in enumerate(zip(maps, cameras)):
        rows, cols = np.nonzero(masks[a])
        p = ma.p_world[rows, cols]
        s = ma.sigma[rows, cols]
        num = p / s[:, None] ** 2
        den = 1.0 / s**2
        confirmed = np.zeros(p.shape[0], bool)
        violated = np.zeros(p.shape[0], bool)
        # the averaged estimates: (camera, its pixels' rows, cols, weight) per point of A
        terms = [(a, rows, cols, den.copy())]
        pix = {a: (rows, cols)}  # each camera's pixel at A's points (for third-camera terms)
        for b, (mb, cb) in enumerate(zip(maps, cameras)):
            if b == a:
                continue
            qi, ok = _pixel_of(cb, p)
            pix[b] = (qi[:, 1], qi[:, 0])
            D = np.where(ok, depth_med[b][qi[:, 1], qi[:, 0]], np.nan)
            sb = mb.sigma[qi[:, 1], qi[:, 0]]
            sb = np.where(np.isfinite(sb), sb, s)
            d = np.linalg.norm(p - cb.center_world, axis=1)
            tau = tol_sigmas * np.sqrt(s**2 + sb**2) + tol_floor
            with np.errstate(invalid="ignore"):
                violated |= d < D - tau
                agree = np.abs(d - D) <= tau
            have = agree & masks[b][qi[:, 1], qi[:, 0]]
            confirmed |= have
            if average and have.any():
                pb = points[b][qi[have, 1], qi[have, 0]]
                wb = 1.0 / sb[have] ** 2
                num[have] += pb * wb[:, None]
                den[have] += wb
                terms.append((b, qi[:, 1], qi[:, 0], np.where(have, 1.0 / sb**2, 0.0)))
        bad = np.zeros(ma.reason.shape, bool)
        bad[rows[violated], cols[violated]] = True
        ma.reject(bad, OCCLUDED_VIEW)
        keep = ~violated
        pf = num[keep] / den[keep, None]
        # Var of the weighted mean Σ w_i·p_i / Σ w_i: Σ w_i²σ_i² = Σ w_i, plus the covariance of
        # estimates made from the same code maps (camera–camera)
        var_num = den + _shared_code_covariance(terms, pix, maps, points, cameras)
        sig_f = np.sqrt(np.maximum(var_num, 0.0)) / den
        out.append((pf, sig_f[keep], ma.confidence[rows[keep], cols[keep]],
                    np.full(int(keep.sum()), a), np.stack([cols[keep], rows[keep]], 1),
                    confirmed[keep]))
    cat = [np.concatenate([o[i] for o in out]) for i in range(6)]
    # two cameras' mutually nearest confirmed points average to the same point: keep one
    _, first = np.unique(cat[0], axis=0, return_index=True)
    first.sort()
    cat = [a[first] for a in cat]
    if cluster_spacings is not None and len(cat[0]) > 1:
        keep = _large_clusters(cat[0], cluster_spacings, min_cluster_fraction)
        for c in np.unique(cat[3][~keep]):
            sel = ~keep & (cat[3] == c)
            bad = np.zeros(maps[c].reason.shape, bool)
            bad[cat[4][sel, 1], cat[4][sel, 0]] = True
            maps[c].reject(bad, OUTLIER)
        cat = [a[keep] for a in cat]
    return FusedPoints(cat[0], cat[1], cat[2].astype(np.float32), cat[3].astype(np.int64),
                       cat[4].astype(np.int64), cat[5], [c.name for c in cameras],
                       np.stack([c.center_world for c in cameras]))


def _shared_code_covariance(terms, pix, maps, points, cameras) -> np.ndarray:
    """``2·Σ_{i<j} w_i·w_j·Cov(δt_i, δt_j)·(v_i·v_j)`` over the estimates one fused point
    averages (:func:`fuse_cameras`), ``(N,)`` metres² times weight²: the covariance of
    camera–camera points made from the same code maps (:class:`CodeGains`), along their rays
    ``v``. 0 for maps without gains (independent, as camera–projector points are).

    ``terms`` holds per averaged estimate ``(camera index, rows, cols, weight)`` (``(N,)``
    each, weight 0 where that camera's point was not averaged in); ``pix`` every camera's
    ``(rows, cols)`` at the points (the third camera's code noise is read there)."""
    n = terms[0][3].shape[0]
    total = np.zeros(n)
    names = [m.camera for m in maps]
    zero = np.zeros((n, 2))
    var_code = {c: maps[c].code_gains.sigma_code[r, q] ** 2 for c, (r, q) in pix.items()
                if maps[c].code_gains is not None}
    looked = []
    for c, r, q, w in terms:
        g = maps[c].code_gains
        if g is None:
            continue
        v = points[c][r, q] - cameras[c].center_world
        with np.errstate(invalid="ignore", divide="ignore"):
            v = v / np.linalg.norm(v, axis=-1, keepdims=True)
        looked.append((c, w, v, np.nan_to_num(g.dt_dcode[r, q]),
                       {k: np.nan_to_num(pg[r, q]) for k, pg in g.partner_dt_dcode.items()},
                       {k: h[r, q] for k, h in g.partner_weight.items()}))
    for i in range(len(looked)):
        for j in range(i + 1, len(looked)):
            ci, wi, vi, si, pi, hi = looked[i]
            cj, wj, vj, sj, pj, hj = looked[j]
            # i's own code in j's fit, and j's own code in i's fit
            cov = ((si * var_code[ci] * pj.get(names[ci], zero)).sum(-1)
                   + (pi.get(names[cj], zero) * var_code[cj] * sj).sum(-1))
            # both fitted into a third camera m near the same code: its neighbours' noise
            for m, name in enumerate(names):
                if m in (ci, cj) or name not in pi or name not in pj or m not in var_code:
                    continue
                with np.errstate(invalid="ignore", divide="ignore"):
                    t = (pi[name] * var_code[m] * pj[name]).sum(-1) / np.sqrt(hi[name] * hj[name])
                cov += np.where(np.isfinite(t), t, 0.0)
            both = (wi > 0) & (wj > 0)
            term = 2.0 * wi * wj * cov * np.einsum("ij,ij->i", vi, vj)
            total += np.where(both & np.isfinite(term), term, 0.0)
    return total


def neighbour_spacing(points, k: int = 6) -> float:
    """Median distance of a point to its ``k``-th nearest neighbour, metres.

    The sampling scale of a point cloud (≈ 1.5–2 point spacings for ``k = 6`` on a surface),
    used for the link distance of the cluster filter and the mesh's trim / observed radius.
    """
    from scipy.spatial import cKDTree

    p = as_array(points, "points", shape=(None, 3))
    if len(p) < 2:
        raise InputError(f"points: need at least 2 points for a spacing, got {len(p)}")
    return float(np.median(cKDTree(p).query(p, k=min(k + 1, len(p)))[0][:, -1]))


def _large_clusters(p: np.ndarray, spacings: float, min_fraction: float) -> np.ndarray:
    """Points in clusters (linked within ``spacings`` × the median 6th-neighbour distance) of
    ≥ ``min_fraction`` of the largest cluster's size."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    tree = cKDTree(p)
    r = spacings * neighbour_spacing(p)
    pairs = tree.query_pairs(r, output_type="ndarray")
    n = len(p)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    counts = np.bincount(lab)
    return counts[lab] >= min_fraction * counts.max()


# ------------------------------------------------------------------------- camera–camera


def match_projector_codes(x_a, y_a, x_b, y_b, *, k: int = 8,
                          max_code_dist: float | None = None):
    """Sub-pixel location in camera B of each camera-A pixel's projector code.

    B's decode maps pixel → code; the inverse near A's code is fitted as a local affine map
    ``q_B ≈ M·(x, y) + m`` over B's ``k`` pixels nearest in code space (a k-d tree over B's
    codes), so no projector calibration is needed. A's pixels are matched in blocks of
    65,536, so the fit's temporaries stay bounded (≈ 30 MB) whatever the image size.

    Parameters
    ----------
    x_a, y_a : (H_a, W_a) float, projector pixels, NaN invalid
    x_b, y_b : (H_b, W_b) float, projector pixels, NaN invalid
    k : int
        Neighbours of the local affine fit (>= 3).
    max_code_dist : float, projector pixels, optional
        No match when B's nearest code is farther than this from A's. Default twice the median
        code-space spacing of B's pixels, at least :data:`MIN_CODE_DIST`.

    Returns
    -------
    q_b : (H_a, W_a, 2) float64, pixels of B (NaN where unmatched)
    jac : (H_a, W_a, 2, 2) float64, ``∂q_B/∂(x, y)`` (pixels of B per projector pixel), for
        propagating the decode noise.
    """
    q_b, jac, _, _ = _match_codes(x_a, y_a, x_b, y_b, k=k, max_code_dist=max_code_dist)
    return q_b, jac


#: Floor of the default code-distance limit of :func:`match_projector_codes`, projector pixels.
MIN_CODE_DIST = 0.5
#: A pixels per block of :func:`match_projector_codes` (its temporaries are ≈ 0.5 kB a pixel).
_MATCH_CHUNK = 1 << 16


def _match_codes(x_a, y_a, x_b, y_b, *, k: int = 8, max_code_dist: float | None = None):
    """:func:`match_projector_codes`, plus the variance of each fitted B location from the local
    fit's misfit, ``(H_a, W_a, 2)`` pixels² of B, and the fit's normalised leverage at A's code,
    ``(H_a, W_a)`` (:func:`_affine_inverse`)."""
    from scipy.spatial import cKDTree

    xa, ya = (as_array(v, n, finite=False) for v, n in ((x_a, "x_a"), (y_a, "y_a")))
    xb, yb = (as_array(v, n, finite=False) for v, n in ((x_b, "x_b"), (y_b, "y_b")))
    if xa.shape != ya.shape or xb.shape != yb.shape or xa.ndim != 2 or xb.ndim != 2:
        raise ShapeError(f"x_a/y_a and x_b/y_b: expected two pairs of equal 2-D maps, got "
                         f"{xa.shape}/{ya.shape} and {xb.shape}/{yb.shape}")
    if k < 3:
        raise InputError(f"k: expected >= 3 neighbours for an affine fit, got {k}")
    q_b = np.full(xa.shape + (2,), np.nan)
    jac = np.full(xa.shape + (2, 2), np.nan)
    var_fit = np.full(xa.shape + (2,), np.nan)
    lev = np.full(xa.shape, np.nan)
    okb = np.isfinite(xb) & np.isfinite(yb)
    oka = np.isfinite(xa) & np.isfinite(ya)
    if okb.sum() < k or not oka.any():
        return q_b, jac, var_fit, lev
    rb, cb_ = np.nonzero(okb)
    codes_b = np.stack([xb[okb], yb[okb]], 1)
    tree = cKDTree(codes_b)
    ca = np.stack([xa[oka], ya[oka]], 1)
    if max_code_dist is None:
        # never 0: where the cameras out-resolve the projector most of B's pixels share
        # their code with a neighbour and the median spacing is 0
        spacing = tree.query(codes_b, k=2)[0][:, 1]
        max_code_dist = max(2.0 * float(np.median(spacing)), MIN_CODE_DIST)
    out = [np.full((ca.shape[0], 2), np.nan), np.full((ca.shape[0], 2, 2), np.nan),
           np.full((ca.shape[0], 2), np.nan), np.full(ca.shape[0], np.nan)]
    for lo in range(0, ca.shape[0], _MATCH_CHUNK):  # bounded memory: (chunk, k, 3) at a time
        sl = slice(lo, lo + _MATCH_CHUNK)
        for o, v in zip(out, _affine_inverse(tree, codes_b, rb, cb_, ca[sl], k, max_code_dist)):
            o[sl] = v
    q_b[oka], jac[oka], var_fit[oka], lev[oka] = out
    return q_b, jac, var_fit, lev


def _affine_inverse(tree, codes_b, rb, cb_, ca, k: int, max_code_dist: float):
    """B pixel, ``∂q_B/∂code``, the fit's variance and leverage at each code of ``ca``
    ``(M, 2)``, from B's ``k`` nearest codes; NaN where unmatched.

    The variance of the fitted location is the regression's: the residual scatter of B's
    pixels about the local affine map, per axis ``Σ res² / (k − 3)`` (0 for ``k = 3``), times
    the intercept's leverage ``(G⁻¹)₃₃``. The leverage is returned normalised, ``k·(G⁻¹)₃₃``:
    ≈ 1 when A's code sits among the neighbours' codes, large when the fit extrapolates
    (A's code outside them, e.g. at the border of B's decoded region).
    """
    dist, nn = tree.query(ca, k=k)
    X = codes_b[nn] - ca[:, None, :]  # (M, k, 2) centred on A's code
    Xh = np.concatenate([X, np.ones(X.shape[:2] + (1,))], -1)  # (M, k, 3)
    Y = np.stack([cb_[nn], rb[nn]], -1).astype(np.float64)  # (M, k, 2) B pixels
    G = np.einsum("mki,mkj->mij", Xh, Xh)
    rhs = np.einsum("mki,mkj->mij", Xh, Y)
    det = np.linalg.det(G)
    scale = np.einsum("mki,mki->m", X, X) / k
    good = (dist[:, 0] <= max_code_dist) & (np.abs(det) > 1e-9 * np.maximum(scale, 1e-12) ** 2)
    sol = np.full((ca.shape[0], 3, 2), np.nan)
    lev = np.full(ca.shape[0], np.nan)
    if good.any():
        sol[good] = np.linalg.solve(G[good], rhs[good])
        lev[good] = np.linalg.inv(G[good])[:, 2, 2]
    qa = sol[:, 2, :]  # value at A's code (X = 0)
    J = np.swapaxes(sol[:, :2, :], 1, 2)  # (M, 2 [q], 2 [code])
    res = Y - np.einsum("mki,mij->mkj", Xh, sol)
    v_fit = (res**2).sum(1) / max(k - 3, 1) * lev[:, None]  # (M, 2), pixels² of B
    # the fitted location must stay among the neighbours (no extrapolation across holes)
    span = np.linalg.norm(Y - Y.mean(1, keepdims=True), axis=-1).max(1)
    far = np.linalg.norm(qa - Y.mean(1), axis=1) > span + 1.0
    qa[far] = np.nan
    return qa, J, v_fit, lev * k


def triangulate_camera_pair(cam_a: Camera, cam_b: Camera, x_a, y_a, x_b, y_b, *,
                            sigma_px: float = 0.3, sigma_x=None, sigma_y=None, k: int = 8,
                            max_sigma_ratio: float = 5.0, min_angle_deg: float | None = None,
                            max_chi: float = 4.0,
                            max_leverage: float | None = 3.0) -> PointMap:
    """Triangulate camera A's pixels against camera B through matching projector codes.

    For rigs with an uncalibrated projector: each A pixel is matched to the sub-pixel location in
    B that decoded the same projector code (:func:`match_projector_codes`), then the A ray is
    intersected with B's ray by minimising B's reprojection error (:func:`solve_along_rays`
    with B as the "other" view); the B-epipolar residual is the consistency check
    (``max_chi``).

    The matching noise in B is a 2 × 2 covariance with two parts: A's decode noise
    (``sigma_x``, ``sigma_y``, else ``sigma_px``) mapped through the local ``∂q_B/∂code``,
    ``J·diag(σ_x², σ_y²)·Jᵀ``, and the variance of the local fit itself per pixel axis (its
    residual scatter times the intercept's leverage), which carries B's own decode noise —
    averaged over the ``k`` neighbours — and the misfit of a locally affine code → B-pixel map.
    A's ray is intersected with B's by generalised least squares on that covariance
    (:func:`solve_along_rays` with ``cov_other``). Deviation from the per-axis σ used until
    this version: ``J`` mixes the code axes into both of B's pixel axes whenever B's image is
    turned against the projector's, and with a coarse row code beside a fine column code
    (Gray ``y`` 0.3 px, phase ``x`` 0.08 px) the two pixel errors are strongly correlated;
    weighted per axis the points were worse and σ misstated (plane, camera B rolled 30°:
    depth RMS 0.239 → 0.181 mm, RMS z 0.92 → 0.96; the synthetic small face, 0.1 px codes:
    0.229 → 0.206 mm; its real decode: 0.177 → 0.106 mm). The fit's part stays per axis
    (not its 2 × 2 scatter): its cross term rests on ``k − 3`` = 5 residual degrees of
    freedom, and weighting by it made σ 10–15 % optimistic (RMS z 1.14 against 1.01 on the
    small face with 0.08 / 0.29 px codes) and kept ≈ 1 % more, worse points (0.184 against
    0.171 mm). (Before the previous version ``sigma_px`` was taken as A's and B's noise added
    in quadrature, which over-stated σ by √2.) A match the fit extrapolates (normalised
    leverage ``k·(G⁻¹)₃₃`` above ``max_leverage``: A's code lies
    outside B's neighbouring codes, as at the border of B's decoded region) gets no point
    (reason :data:`UNCERTAIN`): on the tiny synthetic scan those ≈ 7 % of the matches carried
    2.2 mm RMS depth error against 0.6 mm for the rest, and made the mesh's 95th-percentile
    error 1.3 mm instead of 0.7. So does a degenerate match (the covariance's
    ``det / trace²`` below ``1e-6``: B's neighbours all on one pixel row, the fit sees no change
    of that axis with the code and claimed zero variance across it — σ ≈ 1e-17 m, which then
    outweighed every other estimate in a merge or fusion).

    Not modelled: at grazing incidence the affine match's misfit exceeds what the residual
    scatter shows (on the sphere's limb RMS z is 1.2–1.5, against 1.00–1.05 elsewhere).

    The point map carries :class:`CodeGains` (how each depth follows A's and B's code noise)
    for :func:`fuse_cameras`.

    Parameters
    ----------
    cam_a, cam_b : Camera
    x_a, y_a : (H_a, W_a) float, projector pixels (NaN invalid); both coordinates are needed
    x_b, y_b : (H_b, W_b) float
    sigma_px : float, projector pixels
        A's decode noise (1 σ) where ``sigma_x`` / ``sigma_y`` give none.
    sigma_x, sigma_y : (H_a, W_a) float, projector pixels, optional
        A's decode noise per pixel and axis (NaN → ``sigma_px``), as in
        :func:`triangulate_maps`: e.g. a phase-shift column with a Gray-code row, σ 0.08 and
        0.29 px.
    k, max_sigma_ratio, min_angle_deg, max_chi
        See :func:`match_projector_codes` and :func:`triangulate_maps`.
    max_leverage : float or None
        Largest normalised leverage of the code match (≈ 1 inside B's codes); ``None`` keeps
        every match.

    Returns
    -------
    PointMap
        On A's pixel grid.
    """
    return _camera_pair(cam_a, cam_b, x_a, y_a, x_b, y_b, sigma_px=sigma_px, sigma_x=sigma_x,
                        sigma_y=sigma_y, k=k, max_sigma_ratio=max_sigma_ratio,
                        min_angle_deg=min_angle_deg, max_chi=max_chi,
                        max_leverage=max_leverage)[0]


def _camera_pair(cam_a, cam_b, x_a, y_a, x_b, y_b, *, sigma_px, sigma_x, sigma_y, k,
                 max_sigma_ratio, min_angle_deg, max_chi,
                 max_leverage) -> tuple[PointMap, np.ndarray]:
    """:func:`triangulate_camera_pair`, plus the local fit's share of each point's variance
    (B's codes and the affine misfit, independent of A's code), ``(H_a, W_a)`` metres² (NaN
    without a point)."""
    xa = as_array(x_a, "x_a", shape=(cam_a.height, cam_a.width), finite=False)
    if max_leverage is not None:
        check_positive(max_leverage, "max_leverage")  # also refuses NaN (no silent 'off')
    shape = xa.shape
    d0 = check_positive(sigma_px, "sigma_px")
    s = np.stack([np.full(shape, d0) if m is None else _map(m, n, shape)
                  for m, n in ((sigma_x, "sigma_x"), (sigma_y, "sigma_y"))], -1)
    s = np.where(np.isfinite(s) & (s > 0), s, d0)  # (H, W, 2 [code]), projector pixels
    q_b, jac, var_fit, lev = _match_codes(xa, y_a, x_b, y_b, k=k)
    # covariance of q_B: A's code noise through ∂q_B/∂code, J·diag(s²)·Jᵀ, with the correlation
    # of the two pixel axes; plus the local fit's variance per axis (B's codes and the affine
    # misfit, estimated from 5 residual degrees of freedom for k = 8: too few for a cross term
    # worth weighting by; see the docstring)
    cov_a = np.einsum("...ik,...k,...jk->...ij", jac, s**2, jac)  # (H, W, 2, 2), pixels² of B
    cov_fit = var_fit[..., None] * np.eye(2)
    cov = cov_a + cov_fit
    ok = np.isfinite(q_b).all(-1) & np.isfinite(cov).all((-2, -1))
    with np.errstate(invalid="ignore"):
        extrapolated = ok & (lev > max_leverage) if max_leverage is not None else ok & False
        # B's neighbours on one pixel row (or column): the fit sees no change of that axis
        # with the code, and the location claims zero variance along it
        det = cov[..., 0, 0] * cov[..., 1, 1] - cov[..., 0, 1] * cov[..., 1, 0]
        tr2 = (cov[..., 0, 0] + cov[..., 1, 1]) ** 2
        degenerate = ok & ~(det > _MIN_COV_RATIO * tr2)
    ok &= ~extrapolated & ~degenerate
    idx = np.flatnonzero(ok)
    o, d = cam_a.pixel_rays(cam_a.pixel_grid().reshape(-1, 2)[idx])
    fit = solve_along_rays(o, d, cam_b, q_b.reshape(-1, 2)[idx],
                           cov_other=cov.reshape(-1, 2, 2)[idx])
    # the depth's gains on the code noise (CodeGains): δt = gᵀ·δq_B, δq_B = J·(n_A − Σ h_j n_B(j))
    g = fit.dt_dq  # (n, 2), metres per pixel of B
    dt_dcode = np.full((xa.size, 2), np.nan)
    dt_dcode[idx] = np.einsum("nij,ni->nj", jac.reshape(-1, 2, 2)[idx], g)
    var_fit_t = np.full(xa.size, np.nan)  # the fit's share of σ², metres² (B's codes, misfit)
    var_fit_t[idx] = np.einsum("ni,ni->n", g * g, var_fit.reshape(-1, 2)[idx])
    h = lev.reshape(-1, 1) / k  # (G⁻¹)₃₃: weight of B's pixel at the match in the fit
    reason = np.full(xa.size, NO_CODE, np.uint8)
    reason[idx] = OK
    p, sig, chi, reason = _classify(reason, idx, fit, o, d, max_sigma_ratio=max_sigma_ratio,
                                    max_sigma=None, min_angle_deg=min_angle_deg,
                                    max_chi=max_chi)
    reason[(extrapolated | degenerate).ravel()] = UNCERTAIN
    live = reason == OK
    dt_dcode[~live] = np.nan
    var_fit_t[~live] = np.nan
    partner = np.where(live[:, None], -h * dt_dcode, 0.0).reshape(shape + (2,))
    gains = CodeGains(s, dt_dcode.reshape(shape + (2,)), {cam_b.name: partner},
                      {cam_b.name: np.where(live, h[:, 0], np.nan).reshape(shape)})
    pm = PointMap(cam_a.name, p.reshape(shape + (3,)), sig.reshape(shape), chi.reshape(shape),
                  np.ones(shape, np.float32), reason.reshape(shape), cam_a.center_world.copy(),
                  gains)
    return pm, var_fit_t.reshape(shape)


def triangulate_camera_pairs(cameras: list[Camera], x: list, y: list, *, confidence=None,
                             sigma_px=0.3, sigma_x=None, sigma_y=None, k: int = 8,
                             max_sigma_ratio: float = 5.0, min_angle_deg: float | None = None,
                             max_chi: float = 4.0, max_leverage: float | None = 3.0,
                             tol_sigmas: float = 4.0, tol_floor: float = 1e-3,
                             spike_sigmas: float = 6.0,
                             spike_floor: float = 1e-3) -> tuple[list[PointMap], dict]:
    """Every camera's points against every other camera, through matching projector codes.

    The camera–camera counterpart of calling :func:`triangulate_maps` once per camera, for rigs
    whose projector is uncalibrated: camera A's pixels are triangulated against each other
    camera B in turn (:func:`triangulate_camera_pair`, all ordered pairs), and the estimates of
    one A pixel — all on A's ray — are merged: the inverse-variance mean of the depths that
    agree with the most certain one within ``tol_sigmas·sqrt(σ_i² + σ_best²) + tol_floor``
    (the others are dropped). A's own code noise is common to all of A's pairs, so it is not
    averaged down but propagated once: with normalised weights ``ŵ_i``, ``s_i`` pair i's depth
    gain on A's code (:attr:`CodeGains.dt_dcode`) and ``f_i`` its fit's variance (B's codes,
    independent between partners), ``σ² = (Σ ŵ_i s_i)ᵀ·Σ_A·(Σ ŵ_i s_i) + Σ ŵ_i² f_i``. The
    gains are vectors over the code axes: a horizontal partner reads mostly A's column code, a
    vertical one its row code, so the pairs' own-code errors are not perfectly correlated, as
    the previous version's ``(Σ ŵ_i σ_i √a_i)²`` took them (plane, three cameras: RMS z 0.88,
    now 1.01). Isolated wrong depths are then
    rejected as in :func:`triangulate_maps` (reason :data:`OUTLIER`). The result, one map per
    camera on its own pixel grid, goes to :func:`fuse_cameras` like the camera–projector maps,
    with the merged :class:`CodeGains`.
    Memory: besides the inputs and the finished maps (one per camera, as the camera–projector
    route keeps), only camera A's maps against its partners are held at a time (one
    :class:`PointMap` and one fit-variance map per partner) while they are merged.

    Parameters
    ----------
    cameras : list of Camera
        At least two; the maps' sizes are the cameras'.
    x, y : list of (H_c, W_c) float, projector pixels (NaN invalid)
        Each camera's decoded projector column and row; mask invalid or low-confidence codes as
        NaN first (they are neither triangulated nor matched against).
    confidence : list of (H_c, W_c) float, 0..1, optional
        Stored in the maps (default 1).
    sigma_px : float or sequence of float, projector pixels
        Each camera's decode noise (1 σ) where ``sigma_x`` / ``sigma_y`` give none.
    sigma_x, sigma_y : list of (H_c, W_c) float (or None), projector pixels, optional
        Each camera's decode noise per pixel and axis (:func:`triangulate_camera_pair`).
    k, max_sigma_ratio, min_angle_deg, max_chi, max_leverage
        :func:`triangulate_camera_pair`.
    tol_sigmas, tol_floor : float, tol_floor in metres
        Agreement of one pixel's estimates from different partners.
    spike_sigmas, spike_floor : float, spike_floor in metres
        :func:`triangulate_maps`.

    Returns
    -------
    maps : list of PointMap
        One per camera, in order; ``reason`` where no partner gave a point is the furthest any
        partner got (e.g. :data:`INCONSISTENT` over :data:`NO_CODE`).
    partners : dict
        ``{camera A: {camera B: points of A triangulated against B}}``.
    """
    cams = list(cameras)
    if len(cams) < 2 or len(x) != len(cams) or len(y) != len(cams):
        raise InputError(f"cameras, x, y: expected two or more cameras with one x and one y map "
                         f"each, got {len(cams)} cameras, {len(x)} x and {len(y)} y maps")
    sp = np.asarray(sigma_px, np.float64)
    if sp.ndim > 1 or (sp.ndim == 1 and sp.size not in (1, len(cams))):
        raise InputError(f"sigma_px: expected one number or one per camera ({len(cams)}), got "
                         f"shape {sp.shape}")
    s = np.broadcast_to(sp.reshape(-1) if sp.ndim else sp, (len(cams),))
    for c, v in zip(cams, s):
        check_positive(float(v), f"sigma_px ({c.name})")
    for name, maps_ in (("sigma_x", sigma_x), ("sigma_y", sigma_y), ("confidence", confidence)):
        if maps_ is not None and len(maps_) != len(cams):
            raise InputError(f"{name}: expected one map (or None) per camera ({len(cams)}), got "
                             f"{len(maps_)}")
    maps, partners = [], {}
    for a, ca in enumerate(cams):
        pair_maps, shares = [], []
        partners[ca.name] = {}
        for b, cb in enumerate(cams):
            if b == a:
                continue
            pm, share = _camera_pair(
                ca, cb, x[a], y[a], x[b], y[b], sigma_px=float(s[a]),
                sigma_x=None if sigma_x is None else sigma_x[a],
                sigma_y=None if sigma_y is None else sigma_y[a], k=k,
                max_sigma_ratio=max_sigma_ratio, min_angle_deg=min_angle_deg, max_chi=max_chi,
                max_leverage=max_leverage)
            partners[ca.name][cb.name] = int(pm.valid.sum())
            pair_maps.append(pm)
            shares.append(share)
        pm = _merge_along_rays(pair_maps, shares, tol_sigmas, tol_floor)
        del pair_maps, shares
        if confidence is not None and confidence[a] is not None:
            pm.confidence = _map(confidence[a], "confidence", pm.reason.shape, np.float32)
        _reject_spikes(pm, spike_sigmas, spike_floor)
        maps.append(pm)
    return maps, partners


def _merge_along_rays(maps: list[PointMap], var_fit: list[np.ndarray], tol_sigmas: float,
                      tol_floor: float) -> PointMap:
    """One camera's point maps against several partners, merged into one
    (:func:`triangulate_camera_pairs`); ``var_fit`` the fit's share of each map's variance."""
    if len(maps) == 1:
        return maps[0]
    D = np.stack([m.depth for m in maps])  # (J, H, W), NaN without a point
    S = np.stack([np.where(m.valid, m.sigma, np.nan) for m in maps])
    ok = np.isfinite(D) & np.isfinite(S)
    best = np.argmin(np.where(ok, S, np.inf), axis=0)[None]
    d0 = np.take_along_axis(D, best, 0)
    s0 = np.take_along_axis(S, best, 0)
    with np.errstate(invalid="ignore"):
        agree = ok & (np.abs(D - d0) <= tol_sigmas * np.sqrt(S**2 + s0**2) + tol_floor)
    S1 = np.where(agree, S, 1.0)
    w = np.where(agree, 1.0 / S1**2, 0.0)
    wsum = w.sum(0)
    have = wsum > 0
    wn = w / np.where(have, wsum, 1.0)
    depth = (wn * np.where(agree, D, 0.0)).sum(0)
    # A's own code enters every pair through its gain: propagate it once, the fits apart
    gains = [m.code_gains for m in maps]
    sig_code = gains[0].sigma_code
    dt_dcode = (wn[..., None] * np.nan_to_num(np.stack([g.dt_dcode for g in gains]))).sum(0)
    var = ((dt_dcode * sig_code) ** 2).sum(-1)
    var += (wn**2 * np.nan_to_num(np.stack(var_fit))).sum(0)
    partner, weight = {}, {}
    for wj, aj, g in zip(wn, agree, gains):
        for name, pg in g.partner_dt_dcode.items():
            partner[name] = partner.get(name, 0.0) + wj[..., None] * pg
            weight[name] = np.where(aj, g.partner_weight[name], np.nan)
    p_best = np.take_along_axis(np.stack([m.p_world for m in maps]), best[..., None], 0)[0]
    c = maps[0].center_world
    with np.errstate(invalid="ignore", divide="ignore"):
        ray = (p_best - c) / d0[0][..., None]
    p = np.where(have[..., None], c + depth[..., None] * ray, np.nan)
    chi = np.take_along_axis(np.stack([m.chi for m in maps]), best, 0)[0]
    reason = np.where(have, OK, np.stack([m.reason for m in maps]).max(0)).astype(np.uint8)
    code_gains = CodeGains(sig_code, np.where(have[..., None], dt_dcode, np.nan), partner,
                           weight)
    return PointMap(maps[0].camera, p, np.where(have, np.sqrt(var), np.nan),
                    np.where(have, chi, np.nan), maps[0].confidence, reason, c.copy(),
                    code_gains)
