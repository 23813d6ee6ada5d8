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

Uncertainty: the formal ``Σ = σ² (JᵀJ)⁻¹`` at the solution with ``σ² = ‖r‖² / (m − n)`` treats
every corner's error as independent; on real boards a view's corners share their errors (print,
detector, the model's misfit), and the formal σ was 2–3× below the spread of the solution over
views on OpenCV's chessboards. From :data:`JACKKNIFE_MIN_VIEWS` views the covariance is
therefore scaled, parameter by parameter, up to the jackknife over views (each view left out by
one Gauss–Newton step from the solution, :func:`~._calib_jac.leave_out_steps`: no re-solve):
``sigma_method`` and ``sigma_inflation`` of the result say what was done. The projection
uncertainty follows mrcal (Kogan): a pixel's ray at a working distance is fixed in the frame of
the boards (mean over the views of ``T_board_cam · p``), the whole parameter covariance
(intrinsics and poses) is pushed through to the pixel, and ``sqrt(trace Σ_q)`` is the RMS of its
2-D error.

Speed (one thread, OpenCV's stereo chessboards, 13 views × 54 corners, best of 7 interleaved
with ``cv2.calibrateCamera`` of the same model on the same float32 corners; shared 2-core
machine, 2026-12-02): 0.4–1.1× OpenCV's time for every model (pinhole, k1, k1k2, 5-term,
rational), ``model="auto"`` 4.1–4.9× one 5-term OpenCV calibration (before: 1.1–2.5× and
44–73×). What it took: per-view Gram blocks by one batched product (:class:`~._calib_jac.
GroupLayout`), the predicted decrease from the blocks, the Jacobian evaluated with each trial
step, no re-evaluation at convergence; in ``auto``, warm starts along the candidates, 30
iterations per candidate, and leave-one-out by downdating instead of re-solving.
``facegeo bench calibration.real`` measures it again.

References
----------
.. [1] Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000.
.. [2] B. Efron, C. Stein, "The jackknife estimate of variance", Ann. Statist. 9(3), 1981.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from facegeo.checks import as_array, check_choice
from facegeo.errors import InputError
from facegeo.frames import Pose, nearest_rotation
from facegeo.geometry._calib_jac import (
    BlockJacobian,
    GroupLayout,
    block_lm,
    held_out_residual,
    leave_out_steps,
    project_with_jac,
    reduced_blocks,
    rodrigues_batch,
)
from facegeo.geometry._calib_model import (  # noqa: F401 (re-exported)
    _LOSSES,
    MODEL_FREE,
    MODELS,
    _Model,
    model_of_dist,
    project_points,
    rotate_rvec,
)
from facegeo.geometry.camera import Camera

log = logging.getLogger(__name__)

__all__ = [
    "JACKKNIFE_MIN_VIEWS",
    "MODELS",
    "MODEL_FREE",
    "CameraCalibration",
    "calibrate_camera",
    "fit_model",
    "model_of_dist",
    "project_points",
    "rotate_rvec",
    "zhang_start",
]

# The model (MODELS, MODEL_FREE, model_of_dist, the θ layout _Model) and the projection kernels
# (rotate_rvec, project_points) live in ._calib_model; imported above and re-exported here.


# ------------------------------------------------------------------------------ result

#: Fewest views in the final solve for the jackknife over views (``sigma_method="jackknife"``);
#: with fewer the formal covariance is reported as it is (``sigma_method="formal"``).
JACKKNIFE_MIN_VIEWS = 6

#: Intrinsics whose inflations, RMS, are ``sigma_inflation`` (and the board poses' scale).
#: Each parameter's jackknife-to-formal variance ratio is pulled this far (in log) toward their
#: geometric mean over these parameters.
_POOL = 0.5
_INFLATION_PARAMS = ("f", "fx", "fy", "cx", "cy")


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
    param_names : list of str
        Names of the intrinsic parameters, in :attr:`std` order.
    std : dict
        Standard deviation of each intrinsic parameter (pixels for fx, fy, cx, cy): the formal
        one (``σ² (JᵀJ)⁻¹``, :attr:`std_formal`), with ``sigma_method="jackknife"`` scaled by
        ``sqrt(max(1, R_j^½ R̄^½))`` — ``R_j`` the parameter's jackknife-to-formal variance
        ratio, ``R̄`` their geometric mean over fx, fy, cx, cy (half its own, half pooled: one
        parameter's ratio from 6–15 views is noisy); ``fx`` and ``fy`` are both present when
        the aspect ratio is fixed.
    sigma_px : float
        Residual standard deviation per coordinate, ``sqrt(‖r‖² / (m − n))``, pixels.
    covariance : (n, n) float64
        Covariance of the whole parameter vector (intrinsics, then 6 per used view: rvec,
        tvec): the formal one scaled per parameter, ``D Σ D`` with ``D = std / std_formal``
        for the intrinsics and ``sqrt(max(1, R̄))`` for the board poses.
    rejected : list of str
        Why views were dropped.
    model_selection : dict or None
        With ``model="auto"``: how the model was chosen (:func:`~._calib_select.select_model`:
        ``model``, ``reason``, per-model held-out ``scores`` and why each other candidate was
        rejected).
    sigma_method : {"jackknife", "formal"}
        ``"jackknife"``: with at least :data:`JACKKNIFE_MIN_VIEWS` views the standard deviations
        are raised to the jackknife over views (:attr:`std`; corner errors are correlated
        within a view: the formal covariance, which treats every corner as independent, was
        2–3× too small on OpenCV's chessboards); the jackknife is conservative (Efron & Stein
        1981): on independent synthetic noise σ comes out 0–40 % above the spread.
        ``"formal"``: fewer views, the formal covariance as it is.
    sigma_inflation : float
        RMS over fx, fy, cx, cy of ``std / std_formal`` (≥ 1; 1 with ``"formal"``).
    std_formal : dict
        The formal standard deviations, ``sqrt(diag σ² (JᵀJ)⁻¹)``.
    std_jackknife : dict or None
        The jackknife standard deviations per parameter (from 3 used views on), else None.
    converged : bool
        Whether the solve converged (relative decrease of ``‖r‖²`` below 1e-12) within its
        iteration limit.
    """

    camera: Camera
    model: str
    rms_px: float
    views_used: np.ndarray
    per_view_rms_px: np.ndarray
    residuals: list
    param_names: list
    std: dict
    sigma_px: float
    covariance: np.ndarray
    rejected: list = field(default_factory=list)
    model_selection: dict | None = None
    sigma_method: str = "formal"
    sigma_inflation: float = 1.0
    std_formal: dict = field(default_factory=dict)
    std_jackknife: dict | None = None
    converged: bool = True
    _theta: np.ndarray = None
    _poses: np.ndarray = None  # (V_used, 6): the used views' poses, covariance order
    _mdl: _Model = None
    _object_points: list = None
    _image_points: list = None
    _poses_all: np.ndarray = None  # (V, 6), NaN for unusable views
    _loo: np.ndarray = None  # (V_used, n): θ step with each used view left out
    _reduced: tuple = None  # (S (V_used, n, n), s (V_used, n)): reduced normal blocks
    _grams: np.ndarray = None  # (V_used, k, k): per used view, Gram of [Ja | Jb | r]

    @property
    def n_views_used(self) -> int:
        """Number of views in the final solve."""
        return int(self.views_used.sum())

    @functools.cached_property
    def T_cam_board(self) -> list:
        """Per view, the board pose ``T_cam_board`` (:class:`~facegeo.frames.Pose`; None for
        views without one)."""
        return [None if not np.all(np.isfinite(p)) else Pose.from_rvec_tvec(p[:3], p[3:])
                for p in self._poses_all]

    def projection_uncertainty(self, *, grid=(16, 12), distance: float | None = None,
                               q=None, region: str = "image") -> dict:
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
        region : {"image", "covered"}
            ``"covered"``: only the grid pixels inside the convex hull of the used views'
            corners — where the solve has data, the region of
            :func:`~._calib_rig.cross_validate`'s headline. Outside it the projection is the
            distortion polynomial's extrapolation, and its σ grows with the free terms: on
            OpenCV's left camera (``opencv5``, boards out to r ≈ 0.6 of the image's corners)
            3.8 px RMS over the whole 16 × 12 grid, 0.30 px on the 75 covered pixels, 4.9 px on
            the others, 26 px at the corner (0, 479) — and the leave-one-view-out spread of the
            projection agrees (3.7 px over the grid): the whole-image figure is right, but
            says how far the lens model extrapolates, not how well the covered image is
            calibrated. ``"image"`` (default): the whole grid.

        Returns
        -------
        dict
            ``q`` (G, 2) grid pixels; ``sigma_px`` (G,) ``sqrt(trace Σ_q)`` (RMS 2-D error of the
            projection, pixels); ``rms_px``, ``max_px``; ``distance_m``.
        """
        check_choice(region, "region", ("image", "covered"))
        cam = self.camera
        q = _grid_pixels(cam, grid) if q is None else as_array(q, "q", shape=(None, 2))
        if region == "covered":
            used = [qi for qi, u in zip(self._image_points, self.views_used) if u]
            q = q[inside_hull(np.concatenate(used), q)]
            if q.shape[0] == 0:
                raise InputError("projection_uncertainty: no grid pixel lies inside the used "
                                 "corners (region 'covered'); give a finer grid or "
                                 "region='image'")
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

    def held_out_mse(self, thetas=None) -> np.ndarray:
        """Each view's mean squared corner residual (px²) with its board pose re-solved at given
        intrinsics: the held-out error of a view at intrinsics solved without it.

        For a used view, to second order in the change of intrinsics ``δ``: with the view's
        blocks of the normal equations at this solution (``U, W, V, a = Jaᵀr, b = Jbᵀr``,
        :meth:`~._calib_jac.BlockJacobian.grams`), its residual after the best pose change is
        ``‖r‖² + 2aᵀδ + δᵀUδ − (b + Wᵀδ)ᵀ V⁻¹ (b + Wᵀδ)`` — the PRESS identity of linear least
        squares (no solve per view; ``tests/test_calib_selection.py`` checks it against full
        re-solves; with a robust loss, of the loss-weighted residuals). A view not used in the
        solve (an outlier) keeps its residual at these intrinsics.

        Parameters
        ----------
        thetas : (V, n) float64, optional
            Intrinsic parameter vectors per view (:attr:`param_names` order); default the
            leave-one-view-out solutions (:meth:`leave_one_out_thetas`).

        Returns
        -------
        (V,) float64, px²
            NaN for views without a pose (unusable).
        """
        if thetas is None:
            thetas = self.leave_one_out_thetas()
        out = self.per_view_rms_px ** 2  # views not used: their residual here
        used = np.flatnonzero(self.views_used)
        delta = np.asarray(thetas)[used] - self._theta
        n_cor = np.array([self._object_points[i].shape[0] for i in used])
        out[used] = held_out_residual(self._grams, self._mdl.n, delta) / n_cor
        return out

    def leave_one_out_thetas(self) -> np.ndarray:
        """``(V, n)``: per view, the intrinsics solved without it (one Gauss–Newton step from this
        solution, :func:`~._calib_jac.leave_out_steps`); this solution for views not used."""
        thetas = np.tile(self._theta, (self.views_used.size, 1))
        thetas[np.flatnonzero(self.views_used)] += self._loo
        return thetas

    def leave_one_out(self, *, grid=(16, 12)) -> dict:
        """Leave-one-view-out cross-validation: from 4 views on (3 left to solve each time).

        Each used view is left out in turn: the intrinsics solved without it (one Gauss–Newton
        step from the full solution: :func:`~._calib_jac.leave_out_steps`; it agrees with a full
        re-solve to ≈ 0.03 px on fx, cx, cy on OpenCV's stereo chessboards) predict its corners
        with its board pose re-solved (six parameters: what a pose absorbs is not scored;
        :meth:`held_out_mse`), and
        project a grid of the full solution's rays after the best rotation between the two
        camera frames (mrcal's implied transform, rotation only, as
        :func:`~._calib_rig.cross_validate`).

        Parameters
        ----------
        grid : (int, int)
            Pixels (columns × rows) over the image for the projection comparison.

        Returns
        -------
        dict
            ``held_out_rms_px`` (RMS over every used corner of its held-out residual, pixels),
            ``in_sample_rms_px`` (:attr:`rms_px`), ``per_view_held_out_rms_px`` ((V,) NaN for
            unusable views), ``projection_jackknife_rms_px`` (the jackknife spread of the
            projection over the grid, RMS: what a solve from a different set of views moves a
            pixel by) beside ``predicted_rms_px`` (:meth:`projection_uncertainty` RMS on the same
            pixels: honest when the two agree), ``views``, ``method``.

        Raises
        ------
        InputError
            Fewer than 4 used views.
        """
        used = np.flatnonzero(self.views_used)
        Vu = used.size
        if Vu < 4:
            raise InputError(f"leave_one_out: {Vu} used views; need at least 4 (3 to solve "
                             "each time)")
        mse = self.held_out_mse()
        n_cor = np.array([p.shape[0] for p in self._object_points])
        ok = np.isfinite(mse) & self.views_used
        held = float(np.sqrt(np.sum(mse[ok] * n_cor[ok]) / np.sum(n_cor[ok])))
        cam = self.camera
        q = _grid_pixels(cam, grid)
        v, ok_q = cam.unproject(q, return_valid=True)
        q, v = q[ok_q], v[ok_q]
        v = v / np.linalg.norm(v, axis=-1, keepdims=True)
        d = np.full((Vu, q.shape[0], 2), np.nan)
        for j, th in enumerate(self._theta + self._loo):
            if not np.all(np.isfinite(th)):
                continue
            c_j = self._mdl.camera(th, cam.name, cam.size)
            v_j, ok_j = c_j.unproject(q, return_valid=True)
            if not ok_j.all():
                continue
            v_j = v_j / np.linalg.norm(v_j, axis=-1, keepdims=True)
            R = nearest_rotation(v_j.T @ v)
            q_j, _ = c_j.project_cam(v @ R.T)
            d[j] = q_j - q
        good = np.all(np.isfinite(d), axis=(1, 2))
        dd = d[good]
        n = dd.shape[0]
        jk = (np.sqrt((n - 1) / n * np.mean(np.sum((dd - dd.mean(0)) ** 2, axis=(0, 2))))
              if n >= 2 else float("nan"))
        pred = self.projection_uncertainty(q=q)["rms_px"]
        return {"held_out_rms_px": held, "in_sample_rms_px": self.rms_px,
                "per_view_held_out_rms_px": np.sqrt(mse), "projection_jackknife_rms_px": jk,
                "predicted_rms_px": pred, "views": int(Vu),
                "method": "leave-one-view-out (one Gauss-Newton step from the full solution)"}


def inside_hull(points: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``(G,)`` bool: which pixels ``q`` lie inside (or on) the convex hull of ``points``."""
    hull = cv2.convexHull(np.asarray(points, np.float32)).reshape(-1, 2)
    return np.array([cv2.pointPolygonTest(hull, (float(x), float(y)), False) >= 0
                     for x, y in q], bool)


def _grid_pixels(cam, grid) -> np.ndarray:
    xs = np.linspace(0, cam.width - 1, int(grid[0]))
    ys = np.linspace(0, cam.height - 1, int(grid[1]))
    return np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)


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
    """Residuals and block Jacobian of one camera's calibration over ``(θ, poses)``.

    The views' board points are held padded, ``(V, L, 3)``, so a view's rotation (and its
    derivative) meets its points in one batched product rather than one gathered 3 × 3 (and
    3 × 3 × 3) matrix per point.
    """
    V = len(P)
    ni = mdl.n
    counts = np.array([p.shape[0] for p in P])
    L = int(counts.max())
    vidx = np.repeat(np.arange(V), counts)
    valid = np.arange(L)[None, :] < counts[:, None]
    Pp = np.zeros((V, L, 3))
    Pp[valid] = np.concatenate(P)
    PpT = Pp.transpose(0, 2, 1)  # (V, 3, L)
    sel = None if valid.all() else np.flatnonzero(valid.ravel())
    q_all = np.concatenate(Q)
    rows_v = np.repeat(vidx, 2)
    layout = GroupLayout(rows_v, V)

    def fun_jac(x, jac: bool):
        th = x[:ni]
        ps = x[ni:].reshape(V, 6)
        fx, fy, cx, cy, d8 = mdl.unpack(th)
        R = rodrigues_batch(ps[:, :3], jac=jac)
        R, dR = R if jac else (R, None)
        pc = ((R @ PpT).transpose(0, 2, 1) + ps[:, None, 3:]).reshape(-1, 3)
        if sel is not None:
            pc = pc[sel]
        if not jac:
            return (project_points(pc, fx, fy, cx, cy, d8) - q_all).ravel(), None
        q, dq_dp, dq_dk = project_with_jac(pc, fx, fy, cx, cy, d8)
        # ∂(R p)_i/∂r_k = Σ_j dR[k, i, j] p_j, per view: (V, 9, 3) @ (V, 3, L) → (V, L, i, k)
        dRp = (dR.reshape(V, 9, 3) @ PpT).reshape(V, 3, 3, L).transpose(0, 3, 2, 1)
        dRp = dRp.reshape(-1, 3, 3)
        if sel is not None:
            dRp = dRp[sel]
        Jr = np.einsum("nai,nik->nak", dq_dp, dRp)
        Ja = mdl.intr_jac(dq_dk).reshape(-1, ni)
        Jb = np.concatenate([Jr, dq_dp], axis=-1).reshape(-1, 6)
        return (q - q_all).ravel(), BlockJacobian(Ja, Jb, rows_v, V, layout=layout)

    return fun_jac, vidx


def _solve(P, Q, theta0, poses0, mdl: _Model, loss: str, f_scale: float,
           max_iter: int = 100):
    """Joint solve of intrinsics and poses; returns ``x, r (N, 2), vidx, BlockJacobian,
    converged``."""
    fun_jac, vidx = _single_problem(P, Q, mdl)
    x0 = np.concatenate([theta0, poses0.ravel()])
    x, r, J, converged = minimise(fun_jac, x0, loss, f_scale, max_iter=max_iter,
                                  report=True)
    return x, r.reshape(-1, 2), vidx, J, converged


def minimise(fun_jac, x0, loss: str, f_scale: float, *, max_iter: int = 100,
             report: bool = False):
    """Least squares over a block-sparse calibration problem.

    The plain loss uses facegeo's block Levenberg–Marquardt (:func:`~._calib_jac.block_lm`,
    analytic Jacobian, Schur complement on the dense parameters). A robust loss uses
    ``scipy.optimize.least_squares`` (trust-region reflective) with the same analytic Jacobian
    (dense, exact trust-region solver).

    Returns
    -------
    x, r, J : the solution, its residuals and its :class:`~._calib_jac.BlockJacobian`
        (and, with ``report``, whether it converged within ``max_iter`` Jacobian evaluations
        — scipy's evaluations ``max_iter × (n + 1)`` for a robust loss).
    """
    if loss == "linear":
        x, r, J, it = block_lm(fun_jac, x0, max_iter=max_iter)
        return (x, r, J, it < max_iter) if report else (x, r, J)
    res = least_squares(lambda x: fun_jac(x, False)[0], x0,
                        jac=lambda x: fun_jac(x, True)[1].dense(), method="trf",
                        tr_solver="exact", loss=loss, f_scale=f_scale, x_scale="jac",
                        ftol=1e-14, xtol=1e-14, gtol=1e-14, max_nfev=max_iter * (x0.size + 1))
    r, J = fun_jac(res.x, True)
    return (res.x, r, J, res.status > 0) if report else (res.x, r, J)


def _loss_weights(r: np.ndarray, loss: str, f_scale: float) -> np.ndarray:
    """IRLS weights ``ρ′(z)``, ``z = (r / f_scale)²``, of scipy's robust losses (1 for linear):
    at a robust solution the weighted normal equations are those of the robust problem."""
    if loss == "linear":
        return np.ones_like(r)
    z = (r / f_scale) ** 2
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + z)
    if loss == "huber":
        return np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1.0)))
    if loss == "cauchy":
        return 1.0 / (1.0 + z)
    return 1.0 / (1.0 + z * z)  # arctan


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


def zhang_start(P, Q, size, usable, *, fix_aspect_ratio=None, K_init=None):
    """The Zhang (2000) start of a calibration: ``K`` (``cv2.initCameraMatrix2D`` or
    ``K_init``), zero distortion and a ``solvePnP`` pose per usable view.

    Returns
    -------
    K : (3, 3) float64
    dist8 : (8,) float64 (zeros)
    poses : (V, 6) float64
        rvec, tvec per view; NaN for views not usable.
    """
    mdl = _Model("pinhole", fix_aspect_ratio)
    idx = np.flatnonzero(usable)
    K0, poses_u = _init([P[i] for i in idx], [Q[i] for i in idx], size, mdl, K_init)
    poses = np.full((len(P), 6), np.nan)
    poses[idx] = poses_u
    return K0, np.zeros(8), poses


def fit_model(P, Q, size, usable, model: str, start, *, fix_aspect_ratio=None,
              loss: str = "linear", f_scale: float = 1.0, reject_views: bool = True,
              reject_factor: float = 3.0, reject_floor_px: float = 0.5, min_views: int = 3,
              name: str = "camera", rejected=(), max_iter: int = 100) -> CameraCalibration:
    """Solve one model from a start (the work of :func:`calibrate_camera` after its checks).

    Parameters
    ----------
    P, Q : lists of (N_i, 3) and (N_i, 2) float64
        Every view (checked by :func:`calibrate_camera`'s view checks).
    size : (int, int)
    usable : (V,) bool
        Views that passed the checks.
    model : str
        A key of :data:`MODELS`.
    start : (K (3, 3), dist8 (8,), poses (V, 6))
        :func:`zhang_start`, or another solution (a warm start: model selection starts each
        candidate from the previous one's solution, the coefficients the new model adds at 0).
    rejected : sequence of str
        Reasons of views already dropped (carried into the result).
    max_iter : int
        Jacobian evaluations per solve at most (:func:`~._calib_jac.block_lm`); the result's
        ``converged`` says whether the last solve stopped before.

    Other parameters are those of :func:`calibrate_camera`.
    """
    mdl = _Model(model, fix_aspect_ratio)
    V = len(P)
    n_used = int(usable.sum())
    n_corners = int(sum(p.shape[0] for p, u in zip(P, usable) if u))
    if 2 * n_corners <= mdl.n + 6 * n_used:
        raise InputError(
            f"calibrate_camera: {n_corners} corners in {n_used} views give fewer "
            f"equations than the {mdl.n + 6 * n_used} unknowns; add views or corners"
        )
    K0, d0, poses0 = start
    theta = mdl.pack(K0, d0)
    poses = np.array(poses0, np.float64, copy=True)
    rejected = list(rejected)
    used = usable.copy()
    while True:
        idx = np.flatnonzero(used)
        x, r, vidx, J, converged = _solve([P[i] for i in idx], [Q[i] for i in idx], theta,
                                          poses[idx], mdl, loss, f_scale, max_iter)
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
    c = _result(P, Q, size, usable, used, mdl, x, r, J, poses, loss, f_scale, name, rejected)
    c.converged = bool(converged)
    return c


def _result(P, Q, size, usable, used, mdl, x, r, J, poses, loss, f_scale, name, rejected):
    """Assemble the :class:`CameraCalibration` of a solution: residuals of every usable view,
    the formal covariance, the leave-one-view-out steps and the jackknife inflation."""
    theta = x[: mdl.n]
    cam = mdl.camera(theta, name, size)
    V = len(P)
    poses = poses.copy()
    poses[~usable] = np.nan
    for i in np.flatnonzero(usable & ~used):  # outliers: posed at the final intrinsics
        ok, rv, tv = cv2.solvePnP(P[i], Q[i], cam.K, cam.dist)
        poses[i] = np.concatenate([rv.ravel(), tv.ravel()]) if ok else np.nan
    ui = np.flatnonzero(usable & np.all(np.isfinite(poses), axis=1))
    if np.array_equal(ui, np.flatnonzero(used)):
        r_all = r  # every usable view in the solve: its residuals
    else:
        fun_all, _ = _single_problem([P[i] for i in ui], [Q[i] for i in ui], mdl)
        r_all = fun_all(np.concatenate([theta, poses[ui].ravel()]), False)[0].reshape(-1, 2)
    counts = np.array([P[i].shape[0] for i in ui])
    parts = np.split(r_all, np.cumsum(counts)[:-1])
    residuals = [np.full(q.shape, np.nan) for q in Q]
    per_view_all = np.full(V, np.nan)
    for j, i in enumerate(ui):
        residuals[i] = parts[j]
        per_view_all[i] = float(np.sqrt(np.mean((parts[j] ** 2).sum(-1))))

    m, n = r.size, x.size
    ssr = float((r**2).sum())
    sigma2 = ssr / max(m - n, 1)
    try:
        cov = sigma2 * np.linalg.inv(J.jtj())
    except np.linalg.LinAlgError:
        cov = np.full((n, n), np.nan)
    var_f = np.clip(np.diag(cov)[: mdl.n], 0, None)

    # leave-one-view-out: one Gauss–Newton step per used view from this solution (IRLS
    # weights of a robust loss); the jackknife over views from the same steps
    w = np.sqrt(_loss_weights(r.ravel(), loss, f_scale))
    Jw = BlockJacobian(J.Ja * w[:, None], J.Jb * w[:, None], J.group, J.n_groups,
                       layout=J.layout)
    Gm = Jw.grams(r.ravel() * w)
    S, s = reduced_blocks(Gm, mdl.n)
    Vu = int(used.sum())
    loo = leave_out_steps(S, s, [[g] for g in range(Vu)])
    std_jk, method = None, "formal"
    scale = np.ones(x.size)  # per parameter: σ over the formal σ
    k = [j for j, nm in enumerate(mdl.names) if nm in _INFLATION_PARAMS]
    if Vu >= 3 and np.all(np.isfinite(loo)):
        var_jk = (Vu - 1) / Vu * np.sum((loo - loo.mean(0)) ** 2, axis=0)
        std_jk = _std_dict(mdl, np.sqrt(var_jk))
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = var_jk / var_f
        ok = np.isfinite(ratio) & (ratio > 0)
        if Vu >= JACKKNIFE_MIN_VIEWS and ok[k].all():
            method = "jackknife"
            pooled = float(np.exp(np.mean(np.log(ratio[k]))))
            ratio = np.where(ok, ratio, pooled)
            scale[: mdl.n] = np.sqrt(np.maximum(1.0, ratio ** (1 - _POOL) * pooled ** _POOL))
            # the board poses: the pooled inflation (no jackknife of a view's own pose)
            scale[mdl.n:] = np.sqrt(max(1.0, pooled))
    inflation = float(np.sqrt(np.mean(scale[k] ** 2)))
    std_formal = _std_dict(mdl, np.sqrt(var_f))
    return CameraCalibration(
        camera=cam, model=mdl.model, rms_px=float(np.sqrt(ssr / (m / 2))), views_used=used,
        per_view_rms_px=per_view_all, residuals=residuals, param_names=mdl.names,
        std=_std_dict(mdl, scale[: mdl.n] * np.sqrt(var_f)), sigma_px=float(np.sqrt(sigma2)),
        covariance=cov * np.outer(scale, scale), rejected=rejected, sigma_method=method,
        sigma_inflation=inflation, std_formal=std_formal, std_jackknife=std_jk, _theta=theta,
        _poses=poses[np.flatnonzero(used)], _mdl=mdl, _object_points=list(P),
        _image_points=list(Q), _poses_all=poses, _loo=loo, _reduced=(S, s), _grams=Gm,
    )


def _std_dict(mdl: _Model, sd: np.ndarray) -> dict:
    std = dict(zip(mdl.names, np.asarray(sd, float).tolist()))
    if mdl.aspect is not None:
        std["fy"] = std["f"]
        std["fx"] = mdl.aspect * std["f"]
    return std
