"""Benchmark of camera calibration: solve time against reprojection and ground-truth error for
5, 10 and 20 views of synthetic corners (asymmetric camera, 0.2 px noise), beside
``cv2.calibrateCamera`` on the same corners (same model, one thread each)."""

from __future__ import annotations

import time

import numpy as np

from facegeo.pipeline.bench import BenchRow, one_blas_thread, register

#: Injected corner noise, pixels (per axis).
NOISE_PX = 0.2


@register("calibration.camera")
@one_blas_thread
def bench_camera(quick: bool) -> list[BenchRow]:
    import cv2

    from facegeo.frames import Pose
    from facegeo.geometry.board import CharucoBoard, random_board_poses
    from facegeo.geometry.calibration import calibrate_camera
    from facegeo.geometry.camera import Camera

    K = np.array([[1210.0, 0.0, 655.3], [0.0, 1190.0, 371.8], [0.0, 0.0, 1.0]])
    dist = np.array([-0.21, 0.09, 0.0012, -0.0007, -0.02])
    cam = Camera("bench", 1280, 720, K, dist, Pose.identity())
    board = CharucoBoard(10, 7, 0.03, 0.022)
    P0 = board.chessboard_corners()
    rows = []
    prev = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        for n in (5, 10) if quick else (5, 10, 20):
            poses = random_board_poses(cam, n, n, board=board)
            rng = np.random.default_rng(n)
            Q = [(cam.project_cam(T.apply(P0))[0] + rng.normal(0, NOISE_PX, (len(P0), 2)))
                 .astype(np.float32).astype(np.float64) for T in poses]
            P = [P0] * n
            t0 = time.perf_counter()
            c = calibrate_camera(P, Q, cam.size, reject_views=False)
            t_ours = time.perf_counter() - t0
            t0 = time.perf_counter()
            rms_cv, K_cv, _, _, _ = cv2.calibrateCamera(
                [p.astype(np.float32) for p in P], [q.astype(np.float32) for q in Q], cam.size,
                None, None)
            t_cv = time.perf_counter() - t0
            e = c.camera
            focal = max(abs(e.fx / K[0, 0] - 1), abs(e.fy / K[1, 1] - 1))
            pp = float(np.hypot(e.cx - K[0, 2], e.cy - K[1, 2]))
            rows.append(BenchRow(
                "calibration.camera", f"facegeo calibrate_camera, {n} views", n / t_ours,
                "views/s", error=focal, error_unit="max |Δf|/f vs truth",
                ratios={"vs cv2.calibrateCamera (1 thread)": t_cv / t_ours},
                threads=1, baseline_threads={"vs cv2.calibrateCamera (1 thread)": 1},
                extra={"seconds": round(t_ours, 3), "rms_px": round(c.rms_px, 4),
                       "cv2_rms_px": round(float(rms_cv), 4), "principal_point_error_px":
                       round(pp, 3), "cv2_focal_rel_error": float(max(
                           abs(K_cv[0, 0] / K[0, 0] - 1), abs(K_cv[1, 1] / K[1, 1] - 1))),
                       "std_fx_px": round(c.std["fx"], 3), "noise_px": NOISE_PX}))
    finally:
        cv2.setNumThreads(prev)
    return rows


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
