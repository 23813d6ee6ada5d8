"""Benchmark of camera calibration against ``cv2.calibrateCamera`` on the same corners (same
model, one thread each): solve time, RMS, and the parameter differences to OpenCV's solution.

* ``calibration.camera`` — 5, 10 and 20 views of synthetic corners (asymmetric camera, 5-term
  distortion, 0.2 px noise) with ground-truth errors, and 20 views placed by
  :func:`facegeo.synth.boards.calibration_board_poses` (tilts 45–60°, image-filling);
* ``calibration.real`` — OpenCV's own stereo chessboards (``left*.jpg``, ``right*.jpg``,
  9 × 6 inner corners, classic detector) from ``../shared/data/calibration/
  opencv_stereo_chessboards`` (``FACEGEO_SHARED_DATA`` overrides; no rows when absent): one
  row per distortion model against ``cv2.calibrateCamera`` with that model's flags
  (:data:`CV2_FLAGS`), and ``model="auto"`` (every candidate solved, degenerate lenses refused,
  leave-one-view-out held-out error, jackknife σ) against one 5-term OpenCV calibration;
* ``calibration.projector`` — projector focal error with and without the joint refinement;
* ``calibration.hdr`` — Debevec–Malik response recovery and merge (``capture.hdr``) against
  ``cv2.createCalibrateDebevec`` / ``createMergeDebevec`` on one bracket: time beside the
  error to the true curve and radiance (why facegeo keeps its own: ``capture/hdr.py``);
* ``calibration.model`` — the distortion model chosen per camera (``model="auto"``) against
  the fixed 5-term model on the `small` preset's narrow camera (12° × 19°, 240 × 360 px): solve
  time against the principal-point error, and ``auto``'s time against one OpenCV calibration.

Times are the best of ``repeat`` runs of each solver, the two solvers' runs interleaved (the
machine is shared: interleaving exposes both to the same load).
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from facegeo.bench import BenchRow, one_blas_thread, register, repeats, shared_data_dir

log = logging.getLogger(__name__)

#: Injected corner noise, pixels (per axis).
NOISE_PX = 0.2

#: What the rows compare with.
_VS = "vs cv2.calibrateCamera (1 thread)"

#: ``model="auto"`` against one OpenCV calibration (5-term model) of the same corners.
_VS_ONE = "vs one cv2.calibrateCamera, 5-term (1 thread)"


def _cv2_flags(model: str, fix_aspect_ratio=None) -> int:
    """``cv2.calibrateCamera`` flags solving the same model as facegeo's ``model``."""
    import cv2

    zero = cv2.CALIB_ZERO_TANGENT_DIST
    flags = {"pinhole": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | zero,
             "k1": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | zero,
             "k1k2": cv2.CALIB_FIX_K3 | zero, "opencv4": cv2.CALIB_FIX_K3, "opencv5": 0,
             "rational8": cv2.CALIB_RATIONAL_MODEL}[model]
    return flags | (cv2.CALIB_FIX_ASPECT_RATIO if fix_aspect_ratio is not None else 0)


def _interleaved(fns, repeat: int):
    """Best wall time of each function over ``repeat`` interleaved rounds, and its last result."""
    best = [float("inf")] * len(fns)
    out = [None] * len(fns)
    for _ in range(repeats(repeat)):
        for k, fn in enumerate(fns):
            t0 = time.perf_counter()
            out[k] = fn()
            best[k] = min(best[k], time.perf_counter() - t0)
    return best, out


def _versus_opencv(P, Q, size, *, repeat: int = 3, model: str = "opencv5", **kwargs):
    """Time facegeo's ``calibrate_camera`` and ``cv2.calibrateCamera`` (the same model's flags;
    the 5-term model for ``model="auto"``) on the same float32 corners; return both times,
    both RMS and facegeo's result, OpenCV's K and distortion."""
    import cv2

    from facegeo.geometry.calibration import calibrate_camera

    P32 = [p.astype(np.float32) for p in P]
    Q32 = [q.astype(np.float32) for q in Q]
    Pd = [p.astype(np.float64) for p in P32]
    Qd = [q.astype(np.float64) for q in Q32]
    fa = kwargs.get("fix_aspect_ratio")
    flags = _cv2_flags("opencv5" if model == "auto" else model, fa)
    K0 = np.eye(3) if fa is not None else None
    prev = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        (t_ours, t_cv), (c, (rms_cv, K_cv, d_cv, _, _)) = _interleaved(
            [lambda: calibrate_camera(Pd, Qd, size, model=model, reject_views=False, **kwargs),
             lambda: cv2.calibrateCamera(P32, Q32, size, K0, None, flags=flags)], repeat)
    finally:
        cv2.setNumThreads(prev)
    return t_ours, t_cv, c, float(rms_cv), K_cv, np.ravel(d_cv)
def _param_diff(cam, K_cv, d_cv) -> dict:
    e = cam
    d = np.zeros(max(np.size(e.dist), d_cv.size))
    d[: np.size(e.dist)] = np.ravel(e.dist)
    return {"max_abs_diff_fx_fy_cx_cy_px": float(max(
        abs(e.fx - K_cv[0, 0]), abs(e.fy - K_cv[1, 1]), abs(e.cx - K_cv[0, 2]),
        abs(e.cy - K_cv[1, 2]))),
        "max_abs_diff_dist": float(np.abs(d[: d_cv.size] - d_cv).max())}


@register("calibration.camera")
@one_blas_thread
def bench_camera(quick: bool) -> list[BenchRow]:
    from facegeo.frames import Pose
    from facegeo.geometry.board import CharucoBoard, random_board_poses
    from facegeo.geometry.camera import Camera

    K = np.array([[1210.0, 0.0, 655.3], [0.0, 1190.0, 371.8], [0.0, 0.0, 1.0]])
    dist = np.array([-0.21, 0.09, 0.0012, -0.0007, -0.02])
    cam = Camera("bench", 1280, 720, K, dist, Pose.identity())
    board = CharucoBoard(10, 7, 0.03, 0.022)
    P0 = board.chessboard_corners()
    rows = []
    cases = [(f"{n} views (random_board_poses)", random_board_poses(cam, n, n, board=board), n)
             for n in ((5, 10) if quick else (5, 10, 20))]
    if not quick:
        from facegeo.synth.boards import calibration_board_poses

        cases.append(("20 views (synth.boards.calibration_board_poses)",
                      calibration_board_poses(board, [cam], 20, 20), 20))
    for label, poses, n in cases:
        rng = np.random.default_rng(n)
        Q = [cam.project_cam(T.apply(P0))[0] + rng.normal(0, NOISE_PX, (len(P0), 2))
             for T in poses]
        t_ours, t_cv, c, rms_cv, K_cv, d_cv = _versus_opencv([P0] * n, Q, cam.size)
        e = c.camera
        focal = max(abs(e.fx / K[0, 0] - 1), abs(e.fy / K[1, 1] - 1))
        pp = float(np.hypot(e.cx - K[0, 2], e.cy - K[1, 2]))
        rows.append(BenchRow(
            "calibration.camera", f"facegeo calibrate_camera, {label}", n / t_ours,
            "views/s", error=focal, error_unit="max |Δf|/f vs truth",
            ratios={_VS: t_cv / t_ours}, threads=1, baseline_threads={_VS: 1},
            extra={"seconds": round(t_ours, 4), "cv2_seconds": round(t_cv, 4),
                   "rms_px": c.rms_px, "cv2_rms_px": rms_cv,
                   "principal_point_error_px": round(pp, 3),
                   "cv2_focal_rel_error": float(max(abs(K_cv[0, 0] / K[0, 0] - 1),
                                                    abs(K_cv[1, 1] / K[1, 1] - 1))),
                   "std_fx_px": round(c.std["fx"], 3), "std_cx_px": round(c.std["cx"], 3),
                   "noise_px": NOISE_PX, **_param_diff(e, K_cv, d_cv)}))
    return rows


#: Models of the ``calibration.real`` rows (quick: the 5-term model and ``auto``).
REAL_MODELS = ("pinhole", "k1", "k1k2", "opencv5", "rational8", "auto")


@register("calibration.real")
@one_blas_thread
def bench_real(quick: bool) -> list[BenchRow]:
    """OpenCV's stereo chessboards: facegeo vs ``cv2.calibrateCamera`` on the same corners, per
    model; ``auto`` against one 5-term OpenCV calibration."""
    import cv2

    from facegeo.geometry.calibration import ChessboardSpec, detect_boards, usable_detections

    d = shared_data_dir() / "calibration" / "opencv_stereo_chessboards"
    if not d.is_dir():
        log.warning("calibration.real: %s is absent; no rows", d)
        return []
    rows = []
    for side in ("left",) if quick else ("left", "right"):
        files = sorted(d.glob(f"{side}*.jpg"))
        imgs = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
        dets = usable_detections(detect_boards(imgs, ChessboardSpec(9, 6, 0.025),
                                               names=[f.name for f in files],
                                               method="classic"))
        size = dets[0].image_size
        for model in ("opencv5", "auto") if quick else REAL_MODELS:
            t_ours, t_cv, c, rms_cv, K_cv, d_cv = _versus_opencv(
                [x.p_board for x in dets], [x.q for x in dets], size, model=model,
                repeat=3 if quick else 7)
            vs = _VS_ONE if model == "auto" else _VS
            extra = {"seconds": round(t_ours, 4), "cv2_seconds": round(t_cv, 4),
                     "rms_px": c.rms_px, "cv2_rms_px": rms_cv, "model": c.model,
                     "sigma_method": c.sigma_method,
                     "sigma_inflation": round(c.sigma_inflation, 3),
                     "std_fx_cx_cy_px": [round(c.std[k], 3) for k in ("fx", "cx", "cy")]}
            if model != "auto":
                extra.update(_param_diff(c.camera, K_cv, d_cv))
            rows.append(BenchRow(
                "calibration.real", f"facegeo calibrate_camera(model={model!r}), OpenCV "
                f"{side}*.jpg ({len(dets)} views, 54 corners)", len(dets) / t_ours, "views/s",
                error=c.rms_px - rms_cv, error_unit="RMS − cv2 RMS, px",
                ratios={vs: t_cv / t_ours}, threads=1, baseline_threads={vs: 1}, extra=extra))
    return rows


#: What the stereo rows compare with.
_VS_STEREO = "vs cv2.stereoCalibrate (1 thread)"


@register("calibration.stereo")
@one_blas_thread
def bench_stereo(quick: bool) -> list[BenchRow]:
    """OpenCV's stereo chessboards: facegeo's rig bundle adjustment
    (:func:`~facegeo.geometry.calibration.calibrate_rig`, both cameras' 5-term intrinsics
    refined with the relative pose and the board poses) against ``cv2.stereoCalibrate``
    (``CALIB_USE_INTRINSIC_GUESS``: the same unknowns) on the same corners of the views both
    cameras found, both started from the same per-camera calibrations (facegeo's
    ``calibrate_camera``, 5-term). Error: the two solutions' RMS and how far apart they land
    (focal, relative rotation, baseline)."""
    import cv2

    from facegeo.geometry.calibration import (
        ChessboardSpec,
        calibrate_camera,
        calibrate_rig,
        detect_boards,
    )

    d = shared_data_dir() / "calibration" / "opencv_stereo_chessboards"
    if not d.is_dir():
        log.warning("calibration.stereo: %s is absent; no rows", d)
        return []
    spec = ChessboardSpec(9, 6, 0.025)
    dets = {}
    for side in ("left", "right"):
        files = sorted(d.glob(f"{side}*.jpg"))
        imgs = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
        found = detect_boards(imgs, spec, names=[f.name for f in files], method="classic")
        dets[side] = {f.name[len(side):]: x for f, x in zip(files, found) if x.found}
    both = sorted(set(dets["left"]) & set(dets["right"]))
    size = dets["left"][both[0]].image_size
    P = [dets["left"][v].p_board.astype(np.float64) for v in both]
    Q = {s: [dets[s][v].q.astype(np.float64) for v in both] for s in ("left", "right")}
    cams = {s: calibrate_camera(P, Q[s], size, model="opencv5", reject_views=False).camera
            for s in ("left", "right")}
    cams = {s: replace(c, name=s) for s, c in cams.items()}
    obs = {s: {v: (p, q) for v, p, q in zip(both, P, Q[s])} for s in ("left", "right")}
    P32 = [p.astype(np.float32) for p in P]
    Q32 = {s: [q.astype(np.float32) for q in Q[s]] for s in Q}
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-6)
    prev = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        (t_ours, t_cv), (rig, cv) = _interleaved(
            [lambda: calibrate_rig(obs, cams, reference="left", models={"left": "opencv5",
                                                                          "right": "opencv5"}),
             lambda: cv2.stereoCalibrate(
                 P32, Q32["left"], Q32["right"], cams["left"].K.copy(), cams["left"].dist.copy(),
                 cams["right"].K.copy(), cams["right"].dist.copy(), size,
                 flags=cv2.CALIB_USE_INTRINSIC_GUESS, criteria=crit)],
            3 if quick else 7)
    finally:
        cv2.setNumThreads(prev)
    rms_cv, K1, _, K2, _, R_cv, T_cv = cv[:7]
    L, R = rig.camera("left"), rig.camera("right")
    T_rl = R.T_cam_world @ L.T_cam_world.inverse()  # right from left, as OpenCV's R, T
    dR = T_rl.R @ np.asarray(R_cv).T
    angle = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0))))
    n = sum(len(q) for q in Q["left"]) + sum(len(q) for q in Q["right"])
    rms_ours = float(np.sqrt(sum(rig.rms_px[s] ** 2 * sum(len(q) for q in Q[s])
                                 for s in ("left", "right")) / n))
    extra = {"seconds": round(t_ours, 4), "cv2_seconds": round(t_cv, 4), "views": len(both),
             "rms_px": round(rms_ours, 5), "cv2_rms_px": round(float(rms_cv), 5),
             "max_abs_diff_focal_px": round(float(max(
                 abs(L.fx - K1[0, 0]), abs(L.fy - K1[1, 1]), abs(R.fx - K2[0, 0]),
                 abs(R.fy - K2[1, 1]))), 4),
             "relative_rotation_diff_deg": round(angle, 5),
             "baseline_diff_mm": round(float(np.linalg.norm(T_rl.t - np.ravel(T_cv))) * 1e3, 4)}
    return [BenchRow(
        "calibration.stereo", f"facegeo calibrate_rig (5-term, intrinsics refined), OpenCV "
        f"left/right*.jpg ({len(both)} views both found, 54 corners)", len(both) / t_ours,
        "views/s", error=rms_ours - float(rms_cv), error_unit="RMS − cv2 RMS, px",
        ratios={_VS_STEREO: t_cv / t_ours}, threads=1, baseline_threads={_VS_STEREO: 1},
        extra=extra)]


@register("calibration.projector")
@one_blas_thread
def bench_projector(quick: bool) -> list[BenchRow]:
    """Projector focal error with and without the joint refinement: a pinhole projector seen in
    4 board views (0.2 px noise on its corners) beside two cameras with 12 views each."""
    import cv2

    from facegeo.frames import Pose, look_at
    from facegeo.geometry.board import CharucoBoard
    from facegeo.geometry.calibration import calibrate_camera, calibrate_rig
    from facegeo.geometry.camera import Camera

    rng = np.random.default_rng(21)
    K = np.array([[1210.0, 0.0, 655.3], [0.0, 1190.0, 371.8], [0.0, 0.0, 1.0]])
    dist = np.array([-0.21, 0.09, 0.0012, -0.0007, -0.02])
    cams = [Camera("a", 1280, 720, K, dist, look_at([0.0, 0.0, -0.5], [0, 0, 0.3])),
            Camera("b", 1280, 720, K, dist, look_at([0.12, 0.02, -0.48], [0, 0, 0.3]))]
    K_p = np.array([[997.0, 0.0, 257.1], [0.0, 989.5, 202.5], [0.0, 0.0, 1.0]])
    proj = Camera("projector", 512, 384, K_p, None, look_at([0.02, -0.08, -0.55], [0, 0, 0.3]))
    board = CharucoBoard(10, 7, 0.03, 0.022)
    P0 = board.chessboard_corners()
    obs = {"a": {}, "b": {}, "projector": {}}
    n_cam_views = 8 if quick else 12
    for v in range(n_cam_views):
        T_wb = Pose(cv2.Rodrigues(rng.uniform(-0.4, 0.4, 3))[0],
                    np.array([-0.13, -0.09, 0.3]) + rng.uniform(-0.03, 0.03, 3))
        for c in cams + ([proj] if v < 4 else []):
            q, front = c.project(T_wb.apply(P0))
            if front.all() and c.in_image(q).all():
                noise = 0.2 if c is proj else 0.1
                obs[c.name][v] = (P0, q + rng.normal(0, noise, q.shape))
    t0 = time.perf_counter()
    init = {}
    for c in cams:
        vs = list(obs[c.name].values())
        init[c.name] = calibrate_camera([p for p, _ in vs], [q for _, q in vs], c.size,
                                        name=c.name, reject_views=False).camera
    vs = list(obs["projector"].values())
    sep = calibrate_camera([p for p, _ in vs], [q for _, q in vs], proj.size, model="pinhole",
                           name="projector", reject_views=False).camera
    t_sep = time.perf_counter() - t0
    init["projector"] = sep
    t0 = time.perf_counter()
    rig = calibrate_rig(obs, init, reference="a")
    t_joint = time.perf_counter() - t0
    est = rig.camera("projector")

    def ferr(c):
        return float(max(abs(c.fx / K_p[0, 0] - 1), abs(c.fy / K_p[1, 1] - 1)))

    views = len(obs["projector"])
    return [
        BenchRow("calibration.projector",
                 "separate (projector as inverse camera; time includes both cameras' solves)",
                 views / t_sep, "views/s", error=ferr(sep), error_unit="max |Δf|/f vs truth",
                 threads=1, extra={"projector_views": views, "seconds": round(t_sep, 3)}),
        BenchRow("calibration.projector", "joint bundle adjustment with the cameras",
                 views / t_joint, "views/s", error=ferr(est), error_unit="max |Δf|/f vs truth",
                 threads=1, extra={"projector_views": views, "seconds": round(t_joint, 3),
                        "projector_rms_px": round(rig.rms_px["projector"], 4)}),
    ]


@register("calibration.model")
@one_blas_thread
def bench_model(quick: bool) -> list[BenchRow]:
    """``model="auto"`` vs ``"opencv5"`` on the `small` preset's narrow camera, 16 views of
    :func:`facegeo.synth.boards.rig_calibration_views` with 0.15 px corner noise."""
    from facegeo.geometry.rig import default_rig
    from facegeo.synth.boards import board_for_cameras, rig_calibration_views

    cam = default_rig().scaled(0.5).cameras[0]
    board = board_for_cameras([cam])
    P0 = board.chessboard_corners()
    rows = []
    for seed in (0,) if quick else (0, 1):
        rng = np.random.default_rng(seed)
        P, Q = [], []
        for T in rig_calibration_views(board, [cam], 12, seed):
            q, front = cam.project_cam((cam.T_cam_world @ T).apply(P0))
            ok = front & cam.in_image(q)
            if ok.sum() >= 6:
                P.append(P0[ok])
                Q.append(q[ok] + rng.normal(0.0, 0.15, q[ok].shape))
        for model in ("opencv5", "auto"):
            t_ours, t_cv, c, _, _, _ = _versus_opencv(P, Q, cam.size, model=model,
                                                      repeat=1 if quick else 3)
            e = c.camera
            pp = float(np.hypot(e.cx - cam.cx, e.cy - cam.cy))
            vs = _VS_ONE if model == "auto" else _VS
            rows.append(BenchRow(
                "calibration.model", f"model={model}, narrow camera, {len(P)} views, seed {seed}",
                len(P) / t_ours, "views/s", error=pp, error_unit="‖c − c_true‖, px", threads=1,
                ratios={vs: t_cv / t_ours}, baseline_threads={vs: 1},
                extra={"seconds": round(t_ours, 3), "chosen": c.model,
                       "focal_rel_error": float(max(abs(e.fx / cam.fx - 1),
                                                    abs(e.fy / cam.fy - 1))),
                       "std_c_px": round(float(np.hypot(c.std["cx"], c.std["cy"])), 3),
                       "sigma_method": c.sigma_method,
                       "rms_px": round(c.rms_px, 4), "noise_px": 0.15}))
    return rows


#: The camera curve of the ``calibration.hdr`` bracket: exposure x ∈ [0, 1] → code
#: ``255 · x^0.45 (1.1 − 0.1 x)`` (not a gamma: a recovery that assumes one is visibly off).
def _hdr_code(x):
    x = np.clip(x, 0.0, 1.0)
    return np.round(255 * (x ** 0.45 * (1.1 - 0.1 * x))).astype(np.uint8)


def _hdr_bracket(n_stops: int = 18, shape=(60, 80), seed: int = 1):
    """A scene of log-uniform radiance over four decades, independent per channel (channels
    clip in different exposures), bracketed one stop apart; and the true inverse curve at
    each code."""
    rng = np.random.default_rng(seed)
    e = np.exp(rng.uniform(np.log(1e-3), np.log(10.0), size=shape + (3,)))
    times = 2.0 ** np.arange(-(n_stops // 2), n_stops - n_stops // 2)
    x = np.linspace(0, 1, 200001)
    inverse = np.interp(np.arange(256), 255 * (x ** 0.45 * (1.1 - 0.1 * x)), x)
    return e, times, np.stack([_hdr_code(e * t) for t in times]), inverse


@register("calibration.hdr")
@one_blas_thread
def bench_hdr(quick: bool) -> list[BenchRow]:
    """Debevec–Malik response recovery and merge (``facegeo.capture.hdr``) against OpenCV's
    ``cv2.createCalibrateDebevec`` / ``createMergeDebevec`` on the same 18-exposure bracket
    (60 × 80 px), one thread each: time against the error to the true curve (codes 8–247,
    normalised at code 128) and the merged radiance's error to the true radiance (pixels well
    exposed — code 64–191 — in some exposure; median-normalised), both with the true curve."""
    import cv2

    from facegeo.capture import hdr

    e, times, stack, inverse = _hdr_bracket()
    bgr = [np.ascontiguousarray(s[..., ::-1]) for s in stack]
    t32 = times.astype(np.float32)
    ref = inverse / inverse[128]
    rows = []
    prev = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        for n in (70,) if quick else (70, 1000):
            (t_ours, t_cv), (rec, resp) = _interleaved(
                [lambda: hdr.recover_response(stack, times, lam=10.0, n_samples=n),
                 lambda: cv2.createCalibrateDebevec(n, 10.0, False).process(bgr, t32)],
                1 if n > 200 else 3)
            curves = {"ours": np.exp(rec.g),
                      "cv2": resp.reshape(256, 3)[:, ::-1].astype(np.float64)}
            err = {k: float(np.abs((c / c[128])[8:248] / ref[8:248, None] - 1).max())
                   for k, c in curves.items()}
            vs = "vs cv2.createCalibrateDebevec (1 thread)"
            rows.append(BenchRow(
                "calibration.hdr", f"facegeo recover_response, {n} samples, λ = 10, "
                f"{len(times)} exposures", 1.0 / t_ours, "solves/s", error=err["ours"],
                error_unit="max |Δg|/g vs the true curve", ratios={vs: t_cv / t_ours},
                threads=1, baseline_threads={vs: 1},
                extra={"seconds": round(t_ours, 4), "cv2_seconds": round(t_cv, 4),
                       "cv2_error": err["cv2"]}))
        resp_true = np.maximum(inverse, inverse[1])
        resp_cv = np.repeat(resp_true[:, None], 3, 1).astype(np.float32).reshape(256, 1, 3)
        merge_cv = cv2.createMergeDebevec()
        (t_ours, t_cv), (ours, theirs) = _interleaved(
            [lambda: hdr.merge_exposures(stack, times, np.log(resp_true))[0],
             lambda: merge_cv.process(bgr, t32, resp_cv)[..., ::-1]], 3)
    finally:
        cv2.setNumThreads(prev)
    good = np.any((stack >= 64) & (stack <= 191), axis=0)
    merr = {}
    for k, rad in (("ours", ours), ("cv2", theirs)):
        r = rad[good] / e[good]
        merr[k] = float(np.abs(r / np.median(r) - 1).max())
    vs = "vs cv2.createMergeDebevec (1 thread)"
    mpx = stack.shape[1] * stack.shape[2] * len(times) / 1e6
    rows.append(BenchRow(
        "calibration.hdr", f"facegeo merge_exposures, {len(times)} exposures, the true curve",
        mpx / t_ours, "Mpx/s (input)", error=merr["ours"],
        error_unit="max |ΔE|/E, well-exposed pixels", ratios={vs: t_cv / t_ours}, threads=1,
        baseline_threads={vs: 1},
        extra={"seconds": round(t_ours, 5), "cv2_seconds": round(t_cv, 5),
               "cv2_error": merr["cv2"],
               "why_ours": "OpenCV weights a pixel's channels by their mean hat weight: a "
                           "channel clipped in one exposure still counts"}))
    return rows
