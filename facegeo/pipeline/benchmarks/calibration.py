"""Benchmark of camera calibration: solve time against reprojection and ground-truth error for
5, 10 and 20 views of synthetic corners (asymmetric camera, 0.2 px noise), beside
``cv2.calibrateCamera`` on the same corners (same model, one thread each)."""

from __future__ import annotations

import time

import numpy as np

from facegeo.pipeline.bench import BenchRow, register

#: Injected corner noise, pixels (per axis).
NOISE_PX = 0.2


@register("calibration.camera")
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
                extra={"seconds": round(t_ours, 3), "rms_px": round(c.rms_px, 4),
                       "cv2_rms_px": round(float(rms_cv), 4), "principal_point_error_px":
                       round(pp, 3), "cv2_focal_rel_error": float(max(
                           abs(K_cv[0, 0] / K[0, 0] - 1), abs(K_cv[1, 1] / K[1, 1] - 1))),
                       "std_fx_px": round(c.std["fx"], 3), "noise_px": NOISE_PX}))
    finally:
        cv2.setNumThreads(prev)
    return rows
