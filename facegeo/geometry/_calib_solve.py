"""Single-camera calibration from corner lists: facegeo's own least-squares solver.

The model is OpenCV's (``facegeo.geometry.camera``): pinhole ``K`` with zero skew and the
radial-tangential (optionally rational) distortion. The solve follows Zhang (2000) as OpenCV
does: ``cv2.initCameraMatrix2D`` (homographies of the planar board) starts ``K``, ``solvePnP``
starts each view's pose ``T_cam_board``, and a Levenberg–Marquardt solve refines
intrinsics + distortion + every pose jointly, minimising

    Σ_views Σ_corners ‖ project(K, d, T_cam_board_v · p_board) − q ‖²

(the course notes' calibration objective, `siggraph2000-course` §"camera calibration"). The
Jacobian is analytic (:mod:`._calib_jac`: the OpenCV projection's derivatives by hand, OpenCV's
Rodrigues derivative) and block-sparse (each residual depends on the intrinsics and on one view's
six pose parameters); the normal equations are solved by the Schur complement on the intrinsics
(:func:`~._calib_jac.block_lm`, the bundle-adjustment trick), as OpenCV's own solver does
densely. A robust loss goes through ``scipy.optimize.least_squares`` (trust-region reflective)
with the same Jacobian.

Uncertainty: ``Σ = σ² (JᵀJ)⁻¹`` at the solution with ``σ² = ‖r‖² / (m − n)``; the projection
uncertainty follows mrcal (Kogan): a pixel's ray at a working distance is fixed in the frame of
the boards (mean over the views of ``T_board_cam · p``), the whole parameter covariance (intrinsics
and poses) is pushed through to the pixel, and ``sqrt(trace Σ_q)`` is the RMS of its 2-D error.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from facegeo.checks import as_array, check_choice, check_positive
from facegeo.errors import InputError
from facegeo.frames import Pose
from facegeo.geometry._calib_jac import (
    BlockJacobian,
    block_lm,
    group_indicator,
    project_with_jac,
    rodrigues_batch,
    rotate_with_jac,
)
from facegeo.geometry.camera import Camera

log = logging.getLogger(__name__)

__all__ = [
    "MODELS",
    "MODEL_FREE",
    "CameraCalibration",
    "calibrate_camera",
    "model_of_dist",
    "project_points",
    "rotate_rvec",
]

#: Distortion models by name → length of the camera's OpenCV coefficient vector
#: ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``; :data:`MODEL_FREE` says which of them are solved for
#: (the others stay 0): ``k1`` and ``k1k2`` are the radial-only models of narrow lenses, stored
#: as OpenCV's 4-vector.
MODELS = {"pinhole": 0, "k1": 4, "k1k2": 4, "opencv4": 4, "opencv5": 5, "rational8": 8}

#: Indices (OpenCV order) of the distortion coefficients each model solves for.
MODEL_FREE = {"pinhole": (), "k1": (0,), "k1k2": (0, 1), "opencv4": (0, 1, 2, 3),
              "opencv5": (0, 1, 2, 3, 4), "rational8": tuple(range(8))}

#: The full model of each distortion-vector length (a camera read from a rig file).
_MODEL_OF_LENGTH = {0: "pinhole", 4: "opencv4", 5: "opencv5", 8: "rational8"}


def model_of_dist(dist) -> str:
    """The model that solves every coefficient of an OpenCV distortion vector of this length.

    Parameters
    ----------
    dist : (n,) float64, n ∈ {0, 4, 5, 8}

    Returns
    -------
    str
        A key of :data:`MODELS`.
    """
    return _MODEL_OF_LENGTH[np.asarray(dist).size]


_LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")


# ------------------------------------------------------------------------------ kernels


def rotate_rvec(rvec: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Rotate points by axis-angle vectors (Rodrigues), row by row.

    Parameters
    ----------
    rvec : (N, 3) or (3,) float64, radians
    p : (N, 3) float64

    Returns
    -------
    (N, 3) float64
    """
    theta = np.linalg.norm(rvec, axis=-1, keepdims=True)
    small = theta < 1e-12
    th = np.where(small, 1.0, theta)
    k = rvec / th
    c = np.cos(theta)
    s = np.sin(theta)
    kxp = np.cross(np.broadcast_to(k, p.shape), p)
    kdp = np.sum(k * p, axis=-1, keepdims=True)
    rot = p * c + kxp * s + k * kdp * (1.0 - c)
    # first order for tiny angles: p + r × p
    lin = p + np.cross(np.broadcast_to(rvec, p.shape), p)
    return np.where(small, lin, rot)


def project_points(p_cam: np.ndarray, fx, fy, cx, cy, dist8) -> np.ndarray:
    """OpenCV projection of camera-frame points (no z ≤ 0 check; the solver keeps z > 0).

    Parameters
    ----------
    p_cam : (N, 3) float64, metres, camera frame
    fx, fy, cx, cy : float or (N,) float64, pixels
    dist8 : (8,) or (N, 8) float64, ``(k1, k2, p1, p2, k3, k4, k5, k6)``

    Returns
    -------
    q : (N, 2) float64, pixels
    """
    d = np.asarray(dist8)
    k1, k2, p1, p2, k3, k4, k5, k6 = (d[..., i] for i in range(8))
    x = p_cam[:, 0] / p_cam[:, 2]
    y = p_cam[:, 1] / p_cam[:, 2]
    x2, y2, xy = x * x, y * y, x * y
    r2 = x2 + y2
    g = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * g + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
    yd = y * g + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
    return np.stack([fx * xd + cx, fy * yd + cy], axis=-1)


class _Model:
    """Layout of the intrinsic parameter vector θ for one camera."""

    def __init__(self, model: str, fix_aspect_ratio: float | None):
        check_choice(model, "model", tuple(MODELS))
        self.model = model
        self.nd = MODELS[model]  # length of the camera's distortion vector
        self.free = np.array(MODEL_FREE[model], int)  # solved coefficients (OpenCV order)
        self.aspect = None if fix_aspect_ratio is None else float(fix_aspect_ratio)
        self.names = (["f"] if self.aspect is not None else ["fx", "fy"]) + ["cx", "cy"] + [
            ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")[i] for i in self.free]
        self.n = len(self.names)

    def pack(self, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
        d8 = np.zeros(8)
        d = np.ravel(dist)[:8]
        d8[: d.size] = d
        f = [K[1, 1]] if self.aspect is not None else [K[0, 0], K[1, 1]]
        return np.concatenate([f, [K[0, 2], K[1, 2]], d8[self.free]])

    def unpack(self, theta: np.ndarray):
        """θ (..., n) → fx, fy, cx, cy, dist8 (..., 8)."""
        if self.aspect is not None:
            fy = theta[..., 0]
            fx = self.aspect * fy
            o = 1
        else:
            fx, fy = theta[..., 0], theta[..., 1]
            o = 2
        cx, cy = theta[..., o], theta[..., o + 1]
        d8 = np.zeros(theta.shape[:-1] + (8,))
        d8[..., self.free] = theta[..., o + 2: o + 2 + self.free.size]
        return fx, fy, cx, cy, d8

    def intr_jac(self, dq_dk: np.ndarray) -> np.ndarray:
        """Derivatives in :data:`~._calib_jac.INTRINSIC_ORDER` (…, 2, 12) → θ's (…, 2, n)."""
        if self.aspect is not None:
            f = (self.aspect * dq_dk[..., 0] + dq_dk[..., 1])[..., None]
        else:
            f = dq_dk[..., 0:2]
        return np.concatenate([f, dq_dk[..., 2:4], dq_dk[..., 4 + self.free]], axis=-1)

    def camera(self, theta: np.ndarray, name: str, size) -> Camera:
        fx, fy, cx, cy, d8 = self.unpack(theta)
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return Camera(name, size[0], size[1], K, d8[: self.nd].copy(), Pose.identity())


# ------------------------------------------------------------------------------ result


@dataclass
class CameraCalibration:
    """The result of :func:`calibrate_camera`.

    Attributes
    ----------
    camera : Camera
        The calibrated camera; its pose is the identity (the camera frame is its own world).
    model : str
        Distortion model name (:data:`MODELS`).
    rms_px : float
        OpenCV's figure: ``sqrt(mean over used corners of ‖q_pred − q‖²)``, pixels.
    views_used : (V,) bool
        Per input view: kept (True) or rejected as an outlier / unusable (False).
    per_view_rms_px : (V,) float64
        RMS of each view's corner residuals (NaN for views never solved).
    residuals : list of (N_i, 2) float64, pixels
        Per view, per corner ``q_pred − q`` at the final solution (all views, used or not).
    T_cam_board : list of Pose or None
        Per view, the board pose (None for views without one).
    param_names : list of str
        Names of the intrinsic parameters, in :attr:`std` order.
    std : dict
        Standard deviation of each intrinsic parameter (pixels for fx, fy, cx, cy), from
        ``σ² (JᵀJ)⁻¹``; ``fx`` and ``fy`` are both present when the aspect ratio is fixed.
    sigma_px : float
        Residual standard deviation per coordinate, ``sqrt(‖r‖² / (m − n))``, pixels.
    covariance : (n, n) float64
        Covariance of the whole parameter vector (intrinsics, then 6 per used view: rvec, tvec).
    rejected : list of str
        Why views were dropped.
    model_selection : dict or None
        With ``model="auto"``: how the model was chosen (:func:`~._calib_select.select_model`:
        ``model``, ``reason``, per-model held-out ``scores``).
    """

    camera: Camera
    model: str
    rms_px: float
    views_used: np.ndarray
    per_view_rms_px: np.ndarray
    residuals: list
    T_cam_board: list
    param_names: list
    std: dict
    sigma_px: float
    covariance: np.ndarray
    rejected: list = field(default_factory=list)
    model_selection: dict | None = None
    _theta: np.ndarray = None
    _poses: np.ndarray = None
    _mdl: _Model = None
    _object_points: list = None

    @property
    def n_views_used(self) -> int:
        """Number of views in the final solve."""
        return int(self.views_used.sum())

    def projection_uncertainty(self, *, grid=(16, 12), distance: float | None = None,
                               q=None) -> dict:
        """mrcal-style projection uncertainty over the image.

        For each pixel of a ``grid`` (columns × rows) spanning the image, the point at
        ``distance`` along its ray is fixed in each used board's frame; a perturbation of the
        parameters moves the boards and the intrinsics, the point's camera-frame position is the
        mean over the boards, and its projection moves. First-order propagation of
        :attr:`covariance` gives a 2×2 covariance per pixel.

        Parameters
        ----------
        grid : (int, int), optional
        distance : float, metres, optional
            Working distance; default the median distance of the board centres.
        q : (G, 2) float64, pixels, optional
            Evaluate at these pixels instead of the grid.

        Returns
        -------
        dict
            ``q`` (G, 2) grid pixels; ``sigma_px`` (G,) ``sqrt(trace Σ_q)`` (RMS 2-D error of the
            projection, pixels); ``rms_px``, ``max_px``; ``distance_m``.
        """
        cam = self.camera
        if q is None:
            gx, gy = int(grid[0]), int(grid[1])
            xs = np.linspace(0, cam.width - 1, gx)
            ys = np.linspace(0, cam.height - 1, gy)
            q = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
        else:
            q = as_array(q, "q", shape=(None, 2))
        v, ok = cam.unproject(q, return_valid=True)
        q, v = q[ok], v[ok]  # pixels whose ray exists (a fold of the distortion has none)
        poses = self._poses
        if distance is None:
            centres = [np.mean(p, axis=0) for p, u in zip(self._object_points, self.views_used)
                       if u]
            p_c = rotate_rvec(poses[:, :3], np.array(centres)) + poses[:, 3:]
            distance = float(np.median(p_c[:, 2]))
        p_cam0 = v / np.linalg.norm(v, axis=-1, keepdims=True) * distance
        # the point in each board's frame: R^T (p − t)
        G, V = p_cam0.shape[0], poses.shape[0]
        p_b = np.empty((V, G, 3))
        for i in range(V):
            p_b[i] = rotate_rvec(-poses[i, :3], p_cam0 - poses[i, 3:])

        # analytic first-order propagation: p_cam = mean_v (R_v p_b[v] + t_v), q = project(p_cam)
        R, dR = rodrigues_batch(poses[:, :3])
        pc = np.einsum("vij,vgj->gi", R, p_b) / V + poses[:, 3:].mean(axis=0)
        fx, fy, cx, cy, d8 = self._mdl.unpack(self._theta)
        _, dq_dp, dq_dk = project_with_jac(pc, fx, fy, cx, cy, d8)
        dpc_dr = np.einsum("vkij,vgj->vgik", dR, p_b) / V  # (V, G, 3, 3): ∂p_cam/∂r_v
        J_r = np.einsum("gai,vgik->gavk", dq_dp, dpc_dr)  # (G, 2, V, 3)
        J_t = np.broadcast_to((dq_dp / V)[:, :, None, :], (G, 2, V, 3))
        J = np.concatenate([self._mdl.intr_jac(dq_dk),
                            np.concatenate([J_r, J_t], axis=-1).reshape(G, 2, 6 * V)], axis=-1)
        S = np.einsum("gin,nm,gjm->gij", J, self.covariance, J)
        sig = np.sqrt(np.clip(np.trace(S, axis1=1, axis2=2), 0, None))
        return {"q": q, "sigma_px": sig, "rms_px": float(np.sqrt(np.mean(sig**2))),
                "max_px": float(sig.max()), "distance_m": distance}


# ------------------------------------------------------------------------------ solver


def _check_views(P, Q, size, min_views):
    """Reject views that cannot constrain a pose; raise when too few remain."""
    usable = np.zeros(len(P), bool)
    reasons = []
    for i, (p, q) in enumerate(zip(P, Q)):
        if p.shape[0] < 6:
            reasons.append(f"view {i}: {p.shape[0]} corners, need at least 6")
            continue
        c = p - p.mean(axis=0)
        sv = np.linalg.svd(c, compute_uv=False)
        if sv[1] <= 1e-9 * max(sv[0], 1e-300):
            reasons.append(f"view {i}: all {p.shape[0]} board points are collinear")
            continue
        if np.abs(p[:, 2]).max() > 1e-9 * max(sv[0], 1e-300):
            reasons.append(f"view {i}: board points are not planar (z ≠ 0)")
            continue
        qc = q - q.mean(axis=0)
        sq = np.linalg.svd(qc, compute_uv=False)
        if sq[1] <= 1e-6 * max(sq[0], 1e-300):
            reasons.append(f"view {i}: all image points are collinear")
            continue
        if (q[:, 0] < -0.5).any() or (q[:, 1] < -0.5).any() or (
                q[:, 0] > size[0] - 0.5).any() or (q[:, 1] > size[1] - 0.5).any():
            reasons.append(f"view {i}: image points outside the {size[0]}×{size[1]} image "
                           "(wrong image size?)")
            continue
        usable[i] = True
    if usable.sum() < min_views:
        raise InputError(
            f"calibrate_camera: only {int(usable.sum())} of {len(P)} views are usable, need at "
            f"least {min_views}" + (f" ({'; '.join(reasons)})" if reasons else "")
        )
    return usable, reasons


def _single_problem(P, Q, mdl: _Model):
    """Residuals and block Jacobian of one camera's calibration over ``(θ, poses)``."""
    V = len(P)
    ni = mdl.n
    counts = np.array([p.shape[0] for p in P])
    vidx = np.repeat(np.arange(V), counts)
    p_all = np.concatenate(P)
    q_all = np.concatenate(Q)
    rows_v = np.repeat(vidx, 2)
    S = group_indicator(rows_v, V)

    def fun_jac(x, jac: bool):
        th = x[:ni]
        ps = x[ni:].reshape(V, 6)
        fx, fy, cx, cy, d8 = mdl.unpack(th)
        R, dR = rodrigues_batch(ps[:, :3])
        if not jac:
            pc = np.einsum("nij,nj->ni", R[vidx], p_all) + ps[vidx, 3:]
            return (project_points(pc, fx, fy, cx, cy, d8) - q_all).ravel(), None
        Rp, dRp = rotate_with_jac(R[vidx], dR[vidx], p_all)
        pc = Rp + ps[vidx, 3:]
        q, dq_dp, dq_dk = project_with_jac(pc, fx, fy, cx, cy, d8)
        Ja = mdl.intr_jac(dq_dk).reshape(-1, ni)
        Jb = np.concatenate([dq_dp @ dRp, dq_dp], axis=-1).reshape(-1, 6)
        return (q - q_all).ravel(), BlockJacobian(Ja, Jb, rows_v, V, S)

    return fun_jac, vidx


def _solve(P, Q, theta0, poses0, mdl: _Model, loss: str, f_scale: float):
    """Joint solve of intrinsics and poses; returns ``x, r (N, 2), vidx, BlockJacobian``."""
    fun_jac, vidx = _single_problem(P, Q, mdl)
    x0 = np.concatenate([theta0, poses0.ravel()])
    x, r, J = minimise(fun_jac, x0, loss, f_scale)
    return x, r.reshape(-1, 2), vidx, J


def minimise(fun_jac, x0, loss: str, f_scale: float):
    """Least squares over a block-sparse calibration problem.

    The plain loss uses facegeo's block Levenberg–Marquardt (:func:`~._calib_jac.block_lm`,
    analytic Jacobian, Schur complement on the dense parameters). A robust loss uses
    ``scipy.optimize.least_squares`` (trust-region reflective) with the same analytic Jacobian
    (dense, exact trust-region solver).

    Returns
    -------
    x, r, J : the solution, its residuals and its :class:`~._calib_jac.BlockJacobian`.
    """
    if loss == "linear":
        x, r, J, _ = block_lm(fun_jac, x0)
        return x, r, J
    res = least_squares(lambda x: fun_jac(x, False)[0], x0,
                        jac=lambda x: fun_jac(x, True)[1].dense(), method="trf",
                        tr_solver="exact", loss=loss, f_scale=f_scale, x_scale="jac",
                        ftol=1e-14, xtol=1e-14, gtol=1e-14, max_nfev=100 * (x0.size + 1))
    r, J = fun_jac(res.x, True)
    return res.x, r, J


def _init(P, Q, size, mdl: _Model, K0):
    if K0 is None:
        obj = [p.astype(np.float32) for p in P]
        img = [q.astype(np.float32).reshape(-1, 1, 2) for q in Q]
        K0 = cv2.initCameraMatrix2D(obj, img, tuple(int(s) for s in size),
                                    aspectRatio=mdl.aspect if mdl.aspect else 0.0)
        if mdl.aspect is not None:
            K0[0, 0] = mdl.aspect * K0[1, 1]
    poses = np.zeros((len(P), 6))
    for i, (p, q) in enumerate(zip(P, Q)):
        ok, rv, tv = cv2.solvePnP(p, q, K0, None, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            ok, rv, tv = cv2.solvePnP(p, q, K0, None, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            raise InputError(f"calibrate_camera: no initial pose for view {i}")
        poses[i, :3] = rv.ravel()
        poses[i, 3:] = tv.ravel()
    return np.asarray(K0, np.float64), poses


def calibrate_camera(object_points, image_points, image_size, *, model: str = "opencv5",
                     fix_aspect_ratio: float | None = None, K_init=None,
                     loss: str = "linear", f_scale: float = 1.0,
                     reject_views: bool = True, reject_factor: float = 3.0,
                     reject_floor_px: float = 0.5, min_views: int = 3,
                     auto_fallback: str = "opencv5", name: str = "camera") -> CameraCalibration:
    """Calibrate one camera from corner lists (Zhang 2000 start, joint least squares).

    Parameters
    ----------
    object_points : sequence of (N_i, 3) float64, metres, board frame
        Per view, the board points (planar: z = 0).
    image_points : sequence of (N_i, 2) float64, pixels
        Per view, their detected positions (integers are pixel centres).
    image_size : (int, int)
        ``(width, height)``, pixels.
    model : {"pinhole", "k1", "k1k2", "opencv4", "opencv5", "rational8", "auto"}
        Distortion model (:data:`MODELS`); ``"auto"`` chooses among
        :data:`~._calib_select.AUTO_CANDIDATES` by k-fold cross-validation over the usable
        views (:func:`~._calib_select.select_model`: held-out reprojection error, the simplest
        model within one standard error of the best) and records the choice in
        :attr:`CameraCalibration.model_selection`.
    fix_aspect_ratio : float, optional
        Fix ``fx / fy`` to this value (OpenCV's ``CALIB_FIX_ASPECT_RATIO``).
    K_init : (3, 3) float64, optional
        Initial camera matrix (default ``cv2.initCameraMatrix2D``).
    loss : {"linear", "soft_l1", "huber", "cauchy", "arctan"}
        Robust loss of ``scipy.optimize.least_squares``; ``f_scale`` (pixels) is its inlier
        scale. With a robust loss the covariance uses the loss-weighted Jacobian.
    reject_views : bool
        Drop views whose RMS exceeds ``max(reject_factor · median, reject_floor_px)`` and
        re-solve (repeated until none is dropped, keeping at least ``min_views``).
    min_views : int
        Fewest usable views.
    auto_fallback : str
        With ``model="auto"``, the model used when the views are too few to hold any out
        (fewer than ``min_views + 1``).
    name : str
        Name of the returned camera.

    Returns
    -------
    CameraCalibration

    Raises
    ------
    InputError
        Fewer than ``min_views`` usable views (too few corners, collinear or non-planar board
        points, image points outside the image), mismatched lists, unknown model or loss.
    """
    from facegeo.geometry._calib_detect import as_corner_lists

    P, Q = as_corner_lists(object_points, image_points)
    size = tuple(int(s) for s in as_array(image_size, "image_size", shape=(2,)))
    if min(size) <= 0:
        raise InputError(f"image_size: expected positive (width, height), got {size}")
    check_choice(loss, "loss", _LOSSES)
    check_positive(f_scale, "f_scale")
    if fix_aspect_ratio is not None:
        check_positive(fix_aspect_ratio, "fix_aspect_ratio")
    if model != "auto":
        check_choice(model, "model", tuple(MODELS) + ("auto",))
    usable, reasons = _check_views(P, Q, size, min_views)
    selection = None
    if model == "auto":
        from facegeo.geometry._calib_select import select_model

        u = np.flatnonzero(usable)
        selection = select_model(
            [P[i] for i in u], [Q[i] for i in u], size, solve=calibrate_camera, models=MODELS,
            min_views=min_views,
            fix_aspect_ratio=fix_aspect_ratio, K_init=K_init, loss=loss, f_scale=f_scale,
            reject_views=reject_views, reject_factor=reject_factor,
            reject_floor_px=reject_floor_px, fallback=auto_fallback, name=name)
        model = selection["model"]
    mdl = _Model(model, fix_aspect_ratio)
    rejected = list(reasons)
    V = len(P)
    n_corners = int(sum(p.shape[0] for p, u in zip(P, usable) if u))
    if 2 * n_corners <= mdl.n + 6 * int(usable.sum()):
        raise InputError(
            f"calibrate_camera: {n_corners} corners in {int(usable.sum())} views give fewer "
            f"equations than the {mdl.n + 6 * int(usable.sum())} unknowns; add views or corners"
        )
    idx = np.flatnonzero(usable)
    K0, poses_init = _init([P[i] for i in idx], [Q[i] for i in idx], size, mdl, K_init)
    theta = mdl.pack(K0, np.zeros(8))
    poses = np.zeros((V, 6))
    poses[idx] = poses_init
    used = usable.copy()
    while True:
        idx = np.flatnonzero(used)
        x, r, vidx, J = _solve([P[i] for i in idx], [Q[i] for i in idx], theta, poses[idx], mdl,
                               loss, f_scale)
        theta = x[: mdl.n]
        poses[idx] = x[mdl.n:].reshape(-1, 6)
        per_view = np.sqrt(np.bincount(vidx, (r**2).sum(-1)) / np.bincount(vidx))
        if not reject_views or len(idx) <= min_views:
            break
        med = float(np.median(per_view))
        thr = max(reject_factor * med, reject_floor_px)
        bad = per_view > thr
        n_drop = min(int(bad.sum()), len(idx) - min_views)
        if n_drop == 0:
            break
        worst = idx[np.argsort(-per_view)[:n_drop]]
        for i in worst:
            used[i] = False
            rejected.append(f"view {i}: RMS {per_view[list(idx).index(i)]:.3g} px > "
                            f"{thr:.3g} px (outlier)")
        log.info("calibrate_camera(%s): rejected %d outlier view(s)", name, n_drop)
    cam = mdl.camera(theta, name, size)
    # residuals and poses of every usable view at the final intrinsics (rejected views: re-posed)
    fx, fy, cx, cy, d8 = mdl.unpack(theta)
    residuals, T_list = [], []
    per_view_all = np.full(V, np.nan)
    for i in range(V):
        if not usable[i]:
            residuals.append(np.full(Q[i].shape, np.nan))
            T_list.append(None)
            continue
        if not used[i]:
            ok, rv, tv = cv2.solvePnP(P[i], Q[i], cam.K, cam.dist)
            poses[i] = np.concatenate([rv.ravel(), tv.ravel()])
        pc = rotate_rvec(np.broadcast_to(poses[i, :3], P[i].shape), P[i]) + poses[i, 3:]
        ri = project_points(pc, fx, fy, cx, cy, d8) - Q[i]
        residuals.append(ri)
        per_view_all[i] = float(np.sqrt(np.mean((ri**2).sum(-1))))
        T_list.append(Pose.from_rvec_tvec(poses[i, :3], poses[i, 3:]))
    m, n = r.size, x.size
    ssr = float((r**2).sum())
    sigma2 = ssr / max(m - n, 1)
    JtJ = J.jtj()
    try:
        cov = sigma2 * np.linalg.inv(JtJ)
    except np.linalg.LinAlgError:
        cov = np.full((n, n), np.nan)
    sd = np.sqrt(np.clip(np.diag(cov)[: mdl.n], 0, None))
    std = dict(zip(mdl.names, sd.tolist()))
    if mdl.aspect is not None:
        std["fy"] = std["f"]
        std["fx"] = mdl.aspect * std["f"]
    rms = float(np.sqrt(ssr / (m / 2)))
    return CameraCalibration(
        camera=cam, model=model, rms_px=rms, views_used=used, per_view_rms_px=per_view_all,
        residuals=residuals, T_cam_board=T_list, param_names=mdl.names, std=std,
        sigma_px=float(np.sqrt(sigma2)), covariance=cov, rejected=rejected, _theta=theta,
        _poses=poses[np.flatnonzero(used)], _mdl=mdl,
        _object_points=[P[i] for i in range(V)], model_selection=selection,
    )
