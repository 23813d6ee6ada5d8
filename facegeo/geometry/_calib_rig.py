"""Rig extrinsics by bundle adjustment, and cross-validation of a camera calibration.

Rig: every camera ``c`` has a pose ``T_c_ref`` relative to a reference camera (identity for the
reference) and every board view ``v`` a pose ``T_ref_board_v``; the residual of a corner seen by
camera c in view v is ``project_c(T_c_ref · T_ref_board_v · p_board) − q``. All poses (and, if
asked, every camera's intrinsics) are refined jointly by the block Levenberg–Marquardt of
:mod:`._calib_jac` (analytic Jacobian; intrinsics and camera poses dense, board poses in 6-column
blocks; ``scipy.optimize.least_squares`` for a robust loss), so N cameras with different view
counts and views seen by only some cameras work alike. Initial poses come from ``solvePnP`` per
observation (the better of the iterative and the planar IPPE poses), chained through views seen
by two cameras, each chosen by agreement among the views and cameras (:func:`_initial_rig`).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import cv2
import numpy as np

from facegeo.checks import check_choice, check_positive, fmt_value
from facegeo.errors import InputError
from facegeo.frames import Pose, nearest_rotation
from facegeo.geometry._calib_jac import (
    BlockJacobian,
    group_indicator,
    project_with_jac,
    rodrigues_batch,
    rotate_with_jac,
)
from facegeo.geometry._calib_camera import calibrate_camera
from facegeo.geometry._calib_solve import (
    _Model,
    inside_hull,
    minimise,
    model_of_dist,
    project_points,
    rotate_rvec,
)
from facegeo.geometry.camera import Camera

__all__ = ["RigCalibration", "calibrate_rig", "cross_validate"]


@dataclass
class RigCalibration:
    """The result of :func:`calibrate_rig`.

    Attributes
    ----------
    cameras : list of Camera
        Refined cameras; ``T_cam_world`` in the chosen world frame.
    T_world_board : dict
        View id → board pose ``T_world_board`` (metres).
    rms_px : dict
        Camera name → RMS corner residual ``sqrt(mean ‖r‖²)``, pixels.
    views_used : dict
        Camera name → number of board views it contributed.
    residuals : dict
        Camera name → ``(N, 2)`` float64 residuals (pixels) and ``(N, 2)`` observed pixels, as
        ``(r, q)``.
    reference : str
        The reference camera.
    """

    cameras: list
    T_world_board: dict
    rms_px: dict
    views_used: dict
    residuals: dict
    reference: str

    def camera(self, name: str) -> Camera:
        """The refined camera called ``name``."""
        for c in self.cameras:
            if c.name == name:
                return c
        raise InputError(f"camera: no camera named {fmt_value(name)}")


def _pose6(T: Pose) -> np.ndarray:
    return np.concatenate([T.rvec, T.t])


def _pose(x6) -> Pose:
    return Pose.from_rvec_tvec(x6[:3], x6[3:])


def _rig_problem(names, cameras, observations, vpos, refine_intrinsics, models=None):
    """Residuals and block Jacobian of the rig bundle adjustment.

    Parameters: ``x = (θ of every camera whose intrinsics are refined, T_c_ref of cameras
    1…C−1, T_ref_board of every view)`` as 6-vectors (rvec, tvec); the residual of a corner seen by
    camera c in view v is ``project_c(T_c_ref · T_ref_board_v · p) − q``. Returns a namespace
    with ``fun_jac(x, jac)``, ``unpack_intr(x)``, ``theta0``, ``mdls``, ``cam_idx``, ``q_all``,
    ``n_intr``, ``n_cam``.
    """
    C, Vn = len(names), len(vpos)
    models = models or {}
    mdls = [_Model(models.get(n) or model_of_dist(cameras[n].dist), None) for n in names]
    if isinstance(refine_intrinsics, (bool, np.bool_)):
        refine = [bool(refine_intrinsics)] * C
    else:
        refine = [n in refine_intrinsics for n in names]
    off_i = np.cumsum([0] + [m.n if rf else 0 for m, rf in zip(mdls, refine)])
    n_intr = int(off_i[-1])
    # observation arrays
    cam_idx, view_idx, Pl, Ql = [], [], [], []
    for ci, n in enumerate(names):
        for v, (p, q) in observations[n].items():
            p = np.asarray(p, np.float64)
            cam_idx.append(np.full(len(p), ci))
            view_idx.append(np.full(len(p), vpos[v]))
            Pl.append(p)
            Ql.append(np.asarray(q, np.float64))
    cam_idx = np.concatenate(cam_idx)
    view_idx = np.concatenate(view_idx)
    p_all = np.concatenate(Pl)
    q_all = np.concatenate(Ql)
    theta0 = [m.pack(cameras[n].K, cameras[n].dist) for m, n, rf in zip(mdls, names, refine)
              if rf]
    fixed = [
        (cameras[n].fx, cameras[n].fy, cameras[n].cx, cameras[n].cy,
         np.pad(cameras[n].dist, (0, 8 - cameras[n].dist.size))) for n in names
    ]
    n_cam = 6 * (C - 1)

    def unpack_intr(x):
        fx = np.empty(C)
        fy, cx, cy = np.empty(C), np.empty(C), np.empty(C)
        d8 = np.empty((C, 8))
        for ci, m in enumerate(mdls):
            if refine[ci]:
                fx[ci], fy[ci], cx[ci], cy[ci], d8[ci] = m.unpack(x[off_i[ci]: off_i[ci + 1]])
            else:
                fx[ci], fy[ci], cx[ci], cy[ci], d8[ci] = fixed[ci]
        return fx, fy, cx, cy, d8

    rows_v = np.repeat(view_idx, 2)
    S = group_indicator(rows_v, Vn)
    cam_rows = [np.flatnonzero(cam_idx == ci) for ci in range(C)]

    def fun_jac(x, jac: bool):
        fx, fy, cx, cy, d8 = unpack_intr(x)
        cp = np.zeros((C, 6))
        cp[1:] = x[n_intr: n_intr + n_cam].reshape(C - 1, 6)
        bp = x[n_intr + n_cam:].reshape(Vn, 6)
        if not jac:
            b = bp[view_idx]
            p_ref = rotate_rvec(b[:, :3], p_all) + b[:, 3:]
            c = cp[cam_idx]
            p_cam = rotate_rvec(c[:, :3], p_ref) + c[:, 3:]
            q = project_points(p_cam, fx[cam_idx], fy[cam_idx], cx[cam_idx], cy[cam_idx],
                               d8[cam_idx])
            return (q - q_all).ravel(), None
        Rb, dRb = rodrigues_batch(bp[:, :3])
        Rc, dRc = rodrigues_batch(cp[:, :3])
        Rbp, dRbp = rotate_with_jac(Rb[view_idx], dRb[view_idx], p_all)
        p_ref = Rbp + bp[view_idx, 3:]
        Rcp, dRcp = rotate_with_jac(Rc[cam_idx], dRc[cam_idx], p_ref)
        p_cam = Rcp + cp[cam_idx, 3:]
        q, dq_dp, dq_dk = project_with_jac(p_cam, fx[cam_idx], fy[cam_idx], cx[cam_idx],
                                           cy[cam_idx], d8[cam_idx])
        N = p_all.shape[0]
        Ja = np.zeros((N, 2, n_intr + n_cam))
        for ci in range(C):  # cameras: a handful
            sel = cam_rows[ci]
            if refine[ci]:
                Ja[sel, :, off_i[ci]: off_i[ci + 1]] = mdls[ci].intr_jac(dq_dk[sel])
            if ci:
                o = n_intr + 6 * (ci - 1)
                Ja[sel, :, o: o + 3] = dq_dp[sel] @ dRcp[sel]
                Ja[sel, :, o + 3: o + 6] = dq_dp[sel]
        dq_dref = dq_dp @ Rc[cam_idx]
        Jb = np.concatenate([dq_dref @ dRbp, dq_dref], axis=-1).reshape(-1, 6)
        return (q - q_all).ravel(), BlockJacobian(Ja.reshape(2 * N, -1), Jb, rows_v, Vn, S)

    return SimpleNamespace(fun_jac=fun_jac, unpack_intr=unpack_intr, theta0=theta0, mdls=mdls,
                           cam_idx=cam_idx, q_all=q_all, n_intr=n_intr, n_cam=n_cam)


def _view_rms(cam: Camera, p, q, T: Pose) -> float:
    """RMS reprojection error (px) of board points ``p`` at pose ``T`` (T_cam_board) against ``q``."""
    pr, _ = cv2.projectPoints(p, T.rvec, T.tvec, cam.K, cam.dist)
    return float(np.sqrt(np.mean(np.sum((pr[:, 0] - q) ** 2, axis=1))))


def _view_pose(cam: Camera, p, q) -> Pose | None:
    """A board view's pose in ``cam``: the iterative ``solvePnP`` and, for a planar board, both
    poses of ``SOLVEPNP_IPPE`` (a planar target's two-fold ambiguity), the one with the lowest
    reprojection error. A partial view (a few corners) can leave the iterative solve in the
    wrong branch: on the small preset's seed 3 one such view (7 corners, 1.27 px against a
    0.09 px median) dragged the rig adjustment to focal lengths 19–27 % off."""
    cands = []
    ok, rv, tv = cv2.solvePnP(p, q, cam.K, cam.dist)
    if ok:
        cands.append(Pose.from_rvec_tvec(rv, tv))
    if len(p) >= 4 and np.ptp(p[:, 2]) == 0.0 and p[0, 2] == 0.0:
        try:
            n_sol, rvs, tvs, _ = cv2.solvePnPGeneric(p, q, cam.K, cam.dist, flags=cv2.SOLVEPNP_IPPE)
        except cv2.error:
            n_sol = 0
        for k in range(int(n_sol)):
            cands.append(Pose.from_rvec_tvec(rvs[k], tvs[k]))
    if not cands:
        return None
    return min(cands, key=lambda T: _view_rms(cam, p, q, T))


def _initial_rig(names, cameras, observations, T_cb):
    """Initial ``T_c_ref`` per camera and ``T_ref_board`` per view, chained from the reference
    (``names[0]``) through shared views, each chosen by agreement rather than taken from the
    first view found.

    A camera joins through the cameras already placed: of the candidates its shared views give
    (``T_c_b · T_ref_b⁻¹``), the one whose prediction of the camera's own observations of those
    views has the smallest median RMS. A view's board pose, once cameras that saw it are
    placed, is the candidate (``T_c_ref⁻¹ · T_c_b`` of each such camera) with the smallest sum of
    squared reprojection errors over all of them — so a camera that saw only a few corners of
    a view does not set its pose for the others. Returns ``(T_c_ref, T_ref_b)``; a camera left
    out shares no view with the placed ones."""
    obs = {n: {v: (np.asarray(p, np.float64), np.asarray(q, np.float64))
               for v, (p, q) in observations[n].items()} for n in names}
    T_c_ref = {names[0]: Pose.identity()}

    def place_views() -> dict:
        seen: dict = {}
        for n in T_c_ref:
            for v in obs[n]:
                seen.setdefault(v, []).append(n)
        out = {}
        for v, cams in seen.items():
            cands = [T_c_ref[n].inverse() @ T_cb[(n, v)] for n in cams]
            if len(cands) == 1:
                out[v] = cands[0]
                continue
            cost = [sum(_view_rms(cameras[m], *obs[m][v], T_c_ref[m] @ T) ** 2 * len(obs[m][v][0])
                        for m in cams) for T in cands]
            out[v] = cands[int(np.argmin(cost))]
        return out

    T_ref_b = place_views()
    while True:
        joined = False
        for n in names:
            if n in T_c_ref:
                continue
            shared = [v for v in obs[n] if v in T_ref_b]
            if not shared:
                continue
            cands = [T_cb[(n, v)] @ T_ref_b[v].inverse() for v in shared]
            if len(cands) > 1:
                score = [np.median([_view_rms(cameras[n], *obs[n][w], T @ T_ref_b[w])
                                    for w in shared]) for T in cands]
                T_c_ref[n] = cands[int(np.argmin(score))]
            else:
                T_c_ref[n] = cands[0]
            joined = True
        if not joined:
            return T_c_ref, T_ref_b
        T_ref_b = place_views()


def calibrate_rig(observations: dict, cameras: dict, *, reference: str | None = None,
                  refine_intrinsics=True, models: dict | None = None, loss: str = "linear",
                  f_scale: float = 1.0, world: str | tuple = "reference") -> RigCalibration:
    """Bundle-adjust a multi-camera rig over camera and board poses jointly.

    Parameters
    ----------
    observations : dict
        ``{camera_name: {view_id: (p_board (N, 3) metres, q (N, 2) pixels)}}``; a view id names
        one physical board pose shared by every camera that saw it.
    cameras : dict
        ``{camera_name: Camera}`` initial intrinsics (each keeps its distortion length:
        0, 4, 5 or 8 coefficients), e.g. from :func:`calibrate_camera`.
    reference : str, optional
        The camera whose frame is the rig frame (default: the first camera).
    refine_intrinsics : bool or collection of str
        Refine every camera's intrinsics with the poses (True), none (False), or only those of
        the cameras named (the others keep ``cameras``' intrinsics; only their poses are solved,
        e.g. a camera with too few views to calibrate alone).
    models : dict, optional
        ``{camera_name: model}`` (keys of :data:`~._calib_solve.MODELS`): which distortion
        coefficients are refined (e.g. ``"k1"`` keeps k2, p1, p2 at 0). Default: every
        coefficient of the camera's distortion vector (:func:`~._calib_solve.model_of_dist`).
    loss, f_scale
        Robust loss of ``scipy.optimize.least_squares`` (see :func:`calibrate_camera`).
    world : "reference", ("board", view_id) or Pose
        The world frame: the reference camera's frame, the board frame of one view, or an
        explicit ``T_ref_world`` (an alignment transform).

    Returns
    -------
    RigCalibration

    Raises
    ------
    InputError
        A camera without observations or intrinsics, a camera sharing no view (directly or
        through other cameras) with the reference, an unknown world view.
    """
    check_choice(loss, "loss", ("linear", "soft_l1", "huber", "cauchy", "arctan"))
    check_positive(f_scale, "f_scale")
    names = list(cameras)
    if not names:
        raise InputError("cameras: at least one camera is needed")
    for n in names:
        if n not in observations or not observations[n]:
            raise InputError(f"observations: camera {fmt_value(n)} has no board views")
    ref = names[0] if reference is None else reference
    if ref not in cameras:
        raise InputError(f"reference: no camera {fmt_value(ref)}; cameras: {', '.join(names)}")
    names = [ref] + [n for n in names if n != ref]
    # ---- per-observation PnP (the better of the iterative solve and both planar IPPE poses)
    T_cb = {}
    for n in names:
        cam = cameras[n]
        for v, (p, q) in observations[n].items():
            T = _view_pose(cam, np.asarray(p, np.float64), np.asarray(q, np.float64))
            if T is None:
                raise InputError(f"observations[{fmt_value(n)}][{fmt_value(v)}]: no pose for this view")
            T_cb[(n, v)] = T
    T_c_ref, T_ref_b = _initial_rig(names, cameras, observations, T_cb)
    missing = [n for n in names if n not in T_c_ref]
    if missing:
        raise InputError(
            f"observations: camera(s) {', '.join(missing)} share no board view with {fmt_value(ref)} "
            "(directly or through other cameras); the rig cannot be connected"
        )
    views = sorted(T_ref_b, key=str)
    vpos = {v: i for i, v in enumerate(views)}
    pb = _rig_problem(names, cameras, observations, vpos, refine_intrinsics, models)
    mdls, cam_idx, q_all, n_intr, n_cam = pb.mdls, pb.cam_idx, pb.q_all, pb.n_intr, pb.n_cam
    C, Vn = len(names), len(views)
    parts = list(pb.theta0)
    parts += [_pose6(T_c_ref[n]) for n in names[1:]]
    parts += [_pose6(T_ref_b[v]) for v in views]
    x0 = np.concatenate(parts)
    # dense columns: intrinsics and camera poses (few); blocks: board poses
    x, r, _ = minimise(pb.fun_jac, x0, loss, f_scale)
    r = r.reshape(-1, 2)
    fx, fy, cx, cy, d8 = pb.unpack_intr(x)
    cp = np.zeros((C, 6))
    cp[1:] = x[n_intr: n_intr + n_cam].reshape(C - 1, 6)
    bp = x[n_intr + n_cam:].reshape(Vn, 6)
    # world frame
    if isinstance(world, Pose):
        T_ref_world = world
    elif world == "reference":
        T_ref_world = Pose.identity()
    elif isinstance(world, tuple) and len(world) == 2 and world[0] == "board":
        if world[1] not in vpos:
            raise InputError(f"world: no board view {fmt_value(world[1])}; views: {views}")
        T_ref_world = _pose(bp[vpos[world[1]]])  # T_ref_board with board := world
    else:
        raise InputError(f"world: expected 'reference', ('board', view_id) or a Pose, got "
                         f"{fmt_value(world)}")
    T_world_ref = T_ref_world.inverse()
    out_cams, rms, used, resid = [], {}, {}, {}
    for ci, n in enumerate(names):
        K = np.array([[fx[ci], 0, cx[ci]], [0, fy[ci], cy[ci]], [0, 0, 1.0]])
        nd = mdls[ci].nd
        T_cw = _pose(cp[ci]) @ T_ref_world
        out_cams.append(Camera(n, cameras[n].width, cameras[n].height, K, d8[ci][:nd].copy(),
                               T_cw))
        sel = cam_idx == ci
        rms[n] = float(np.sqrt(np.mean((r[sel] ** 2).sum(-1))))
        used[n] = len(observations[n])
        resid[n] = (r[sel], q_all[sel])
    T_wb = {v: T_world_ref @ _pose(bp[i]) for v, i in vpos.items()}
    # keep the caller's camera order
    order = list(cameras)
    out_cams.sort(key=lambda c: order.index(c.name))
    return RigCalibration(out_cams, T_wb, rms, used, resid, ref)


#: Where :func:`cross_validate` compares the two halves' projections.
CV_REGIONS = ("covered", "image")


def cross_validate(object_points, image_points, image_size, *, grid=(16, 12), seed=0,
                   region: str = "covered", splits: int = 1, **kwargs) -> dict:
    """mrcal-style cross-validation: two solves on disjoint halves of the views.

    The views are shuffled (``seed``) and split in two halves; each half is calibrated with
    :func:`calibrate_camera` (``kwargs`` passed on). On a grid of pixels, the ray of solve A is
    projected by solve B after the best rotation between the two camera frames (Kabsch on the
    rays: a rotation of the whole camera is not an intrinsic difference, mrcal's "implied
    transform" restricted to rotation); the difference is compared with the predicted
    ``sqrt(σ_A² + σ_B²)`` from the two solves' projection uncertainties.

    ``region="covered"`` (default) compares only the grid pixels inside the convex hull of the
    corners of *both* halves — the region each solve was fitted on. Outside it each solve
    extrapolates its distortion polynomial, and two fits that agree on their data can differ
    there by any amount: on OpenCV's left camera (13 views of a 9 × 6 chessboard reaching r ≈ 0.6
    of the image's corners, ``opencv5``) the whole image gives 26.6 px RMS / 214 px worst
    between the halves (seed 0; 7.8 px with seed 1), the covered region 0.47 / 0.80 px (0.64 /
    1.17 px). Both figures are returned; ``region="image"`` makes the whole grid the headline
    (the comparison before issue 35). The rotation is fitted on the compared pixels.

    With ``splits`` > 1 the comparison is repeated on that many splits (seeds ``seed`` …
    ``seed + splits − 1``) and the figures combine them: RMS of the splits' RMS, the worst
    pixel, the smallest ``n_pixels``. One split of 13 views is one draw of which 6 views face
    which 7: on OpenCV's right camera (facegeo's corners, ``k1k2``) seeds 0–7 give 1.08, 0.44,
    1.03, 0.63, 0.05, 0.06, 0.29, 0.25 px against predictions of 0.34–0.90 px, and OpenCV's
    own corners 0.60, 1.07, 0.39, 0.92, 0.84, 0.42, 0.55, 0.99 px — the spread between splits
    is larger than the difference between corner detectors (issue 35, docs/calibration.md).

    Parameters
    ----------
    object_points, image_points, image_size
        As for :func:`calibrate_camera`.
    grid : (int, int)
        Pixels (columns × rows) over the image.
    seed : int
        Shuffles the views before the split.
    region : {"covered", "image"}
        The pixels of ``diff_rms_px`` / ``diff_max_px`` / ``predicted_rms_px``.
    splits : int
        Random splits compared (≥ 1); with more than one, ``split_diff_rms_px`` and
        ``split_predicted_rms_px`` list each split's figures.

    Returns
    -------
    dict
        ``diff_rms_px``, ``diff_max_px`` (over the region's grid pixels), ``predicted_rms_px``,
        ``region``, ``n_pixels`` (grid pixels compared), ``image_diff_rms_px``,
        ``image_diff_max_px`` (the whole grid, for reference) and the two
        :class:`CameraCalibration` results as ``a`` and ``b``.

    Raises
    ------
    InputError
        Fewer than 2 × ``min_views`` views; fewer than 3 grid pixels in the compared region.
    """
    from facegeo.checks import check_positive_int
    from facegeo.geometry._calib_detect import as_corner_lists

    check_choice(region, "region", CV_REGIONS)
    splits = check_positive_int(splits, "splits")
    if splits > 1:
        runs = [cross_validate(object_points, image_points, image_size, grid=grid,
                               seed=seed + k, region=region, **kwargs) for k in range(splits)]

        def rms(key):
            return float(np.sqrt(np.mean([r[key] ** 2 for r in runs])))

        return {"diff_rms_px": rms("diff_rms_px"),
                "diff_max_px": max(r["diff_max_px"] for r in runs),
                "predicted_rms_px": rms("predicted_rms_px"), "region": region,
                "n_pixels": min(r["n_pixels"] for r in runs),
                "image_diff_rms_px": rms("image_diff_rms_px"),
                "image_diff_max_px": max(r["image_diff_max_px"] for r in runs),
                "splits": splits,
                "split_diff_rms_px": [r["diff_rms_px"] for r in runs],
                "split_predicted_rms_px": [r["predicted_rms_px"] for r in runs],
                "a": runs[0]["a"], "b": runs[0]["b"]}
    P, Q = as_corner_lists(object_points, image_points)
    min_views = int(kwargs.get("min_views", 3))
    if len(P) < 2 * min_views:
        raise InputError(f"cross_validate: {len(P)} views; need at least {2 * min_views} "
                         "(two disjoint halves)")
    perm = np.random.default_rng(seed).permutation(len(P))
    ia, ib = np.sort(perm[: len(P) // 2]), np.sort(perm[len(P) // 2:])
    a = calibrate_camera([P[i] for i in ia], [Q[i] for i in ia], image_size, **kwargs)
    b = calibrate_camera([P[i] for i in ib], [Q[i] for i in ib], image_size, **kwargs)
    cam = a.camera
    xs = np.linspace(0, cam.width - 1, int(grid[0]))
    ys = np.linspace(0, cam.height - 1, int(grid[1]))
    q = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    va, ok_a = a.camera.unproject(q, return_valid=True)
    vb, ok_b = b.camera.unproject(q, return_valid=True)
    ok = ok_a & ok_b  # pixels whose ray exists in both solves
    # the region both solves were fitted on: inside the hull of each half's used corners
    ua_used = [i for j, i in enumerate(ia) if a.views_used[j]]
    ub_used = [i for j, i in enumerate(ib) if b.views_used[j]]
    covered = (inside_hull(np.concatenate([Q[i] for i in ua_used]), q)
               & inside_hull(np.concatenate([Q[i] for i in ub_used]), q))

    def compare(sel):
        if sel.sum() < 3:
            return None
        qs = q[sel]
        A = va[sel] / np.linalg.norm(va[sel], axis=-1, keepdims=True)
        B = vb[sel] / np.linalg.norm(vb[sel], axis=-1, keepdims=True)
        R_ba = nearest_rotation(B.T @ A)
        qb, _ = b.camera.project_cam(A @ R_ba.T)
        return qs, np.linalg.norm(qb - qs, axis=-1)

    whole = compare(ok)
    if whole is None:
        raise InputError("cross_validate: the two solves share fewer than 3 valid grid pixels")
    main = whole if region == "image" else compare(ok & covered)
    if main is None:
        raise InputError(f"cross_validate: fewer than 3 of the {q.shape[0]} grid pixels lie "
                         "inside the corners of both halves (region 'covered'); give a finer "
                         "grid or region='image'")
    qs, d = main
    ua = a.projection_uncertainty(q=qs)
    ub = b.projection_uncertainty(q=qs)
    pred = np.sqrt(ua["sigma_px"] ** 2 + ub["sigma_px"] ** 2)
    return {"diff_rms_px": float(np.sqrt(np.mean(d**2))), "diff_max_px": float(d.max()),
            "predicted_rms_px": float(np.sqrt(np.mean(pred**2))), "region": region,
            "n_pixels": int(qs.shape[0]),
            "image_diff_rms_px": float(np.sqrt(np.mean(whole[1] ** 2))),
            "image_diff_max_px": float(whole[1].max()), "splits": 1, "a": a, "b": b}
