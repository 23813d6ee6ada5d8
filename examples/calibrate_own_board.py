"""Calibrate a camera from your own board images, and compare with OpenCV on the same corners.

Run:  python examples/calibrate_own_board.py IMAGES... --chessboard 9x6 --square 0.025
      python examples/calibrate_own_board.py --synthetic [--views 15]
                (renders ChArUco views of the package's board with a known camera first)

Steps, in library calls (``facegeo calibrate SCAN`` does this for every camera of a scan, with
the rig, the projector, plots and cross-validation):

1. ``detect_boards`` finds the board in every image and says why an image was skipped;
2. ``calibrate_camera`` solves intrinsics, distortion and per-view poses (Zhang start, joint
   least squares, outlier-view rejection) and gives each parameter's standard deviation;
3. ``cv2.calibrateCamera`` on the same corners, as the independent reference;
4. with ``--synthetic`` the true camera is known, so the error of both is printed too.

Inner corners are counted, as OpenCV counts them: a board of 10 × 7 squares has 9 × 6.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from facegeo.geometry.calibration import (
    ChessboardSpec, calibrate_camera, detect_boards, usable_detections,
)


def _synthetic_views(n_views: int, seed: int = 0):
    """ChArUco views of the package's board seen by the default rig's first camera."""
    from facegeo.geometry.board import CharucoBoard, random_board_poses
    from facegeo.geometry.rig import default_rig

    board = CharucoBoard()
    cam = default_rig().cameras[0]
    poses = random_board_poses(cam, n_views, np.random.default_rng(seed), board=board,
                               tilt_deg=(30.0, 55.0))
    images = []
    for T in poses:
        view = board.render(cam, T)
        images.append(np.clip(255 * (0.1 + view.reflectance), 0, 255).astype(np.uint8))
    return images, board, cam


def load_gray(paths) -> list[np.ndarray]:
    """8-bit greyscale images, as the board detectors want them."""
    from facegeo.capture.imageio import read_image

    out = []
    for p in paths:
        img = np.asarray(read_image(p))
        if img.dtype.kind == "f":
            img = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
        elif img.dtype == np.uint16:
            img = (img >> 8).astype(np.uint8)
        out.append(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img)
    return out


def _report(name: str, K, dist, rms: float) -> None:
    print(f"{name:>8}: fx {K[0, 0]:9.3f}  fy {K[1, 1]:9.3f}  cx {K[0, 2]:8.3f}  cy {K[1, 2]:8.3f}"
          f"  k1 {dist[0]:+.4f}  k2 {dist[1]:+.4f}  RMS {rms:.4f} px")


def calibrate(images, board, names=None, truth=None) -> dict:
    detections = detect_boards(images, board, names=names)
    for d in detections:
        if not d.found:
            print(f"skipped {d.name}: {d.reason}")
    found = usable_detections(detections)
    P = [d.p_board for d in found]
    Q = [d.q for d in found]
    h, w = np.shape(images[0])[:2]
    ours = calibrate_camera(P, Q, (w, h), model="opencv5")
    K = ours.camera.K
    dist = np.asarray(ours.camera.dist, float)
    _report("facegeo", K, dist, ours.rms_px)
    print("          σ: " + "  ".join(f"{k} {v:.3g}" for k, v in ours.std.items()
                                     if k in ("fx", "fy", "cx", "cy")))
    rms_cv, K_cv, dist_cv, _, _ = cv2.calibrateCamera(
        [p.astype(np.float32) for p in P], [q.astype(np.float32).reshape(-1, 1, 2) for q in Q],
        (w, h), None, None)
    _report("OpenCV", K_cv, dist_cv.ravel(), rms_cv)
    out = {"rms_px": ours.rms_px, "rms_px_opencv": float(rms_cv), "K": K, "K_opencv": K_cv,
           "views_used": int(ours.n_views_used)}
    if truth is not None:
        for label, KK in (("facegeo", K), ("OpenCV", K_cv)):
            print(f"{label:>8} error: fx {KK[0, 0] - truth.K[0, 0]:+.3f} px, cx "
                  f"{KK[0, 2] - truth.K[0, 2]:+.3f} px, cy {KK[1, 2] - truth.K[1, 2]:+.3f} px")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("images", nargs="*", type=Path)
    ap.add_argument("--chessboard", help="inner corners COLSxROWS, e.g. 9x6")
    ap.add_argument("--square", type=float, help="square size in metres")
    ap.add_argument("--synthetic", action="store_true")
    ap.add_argument("--views", type=int, default=15)
    a = ap.parse_args(argv)
    if a.synthetic:
        images, board, cam = _synthetic_views(a.views)
        calibrate(images, board, truth=cam)
        return 0
    if not a.images or not a.chessboard or not a.square:
        ap.error("give IMAGES, --chessboard COLSxROWS and --square METRES (or --synthetic)")
    try:
        cols, rows = (int(x) for x in a.chessboard.lower().split("x"))
    except ValueError:
        ap.error(f"--chessboard: expected COLSxROWS such as 9x6, got {a.chessboard!r}")
    images = load_gray(sorted(a.images))
    calibrate(images, ChessboardSpec(cols, rows, a.square), names=[p.name for p in sorted(a.images)])
    return 0


if __name__ == "__main__":
    from facegeo.cli import run_script  # one-line errors and exit statuses, as the CLI

    run_script(main)
