"""Calibration of cameras and rigs from board images or corner lists (issue 9).

The public namespace of three private modules:

* :mod:`._calib_detect` — board detection with a per-image report: ChArUco (OpenCV ≥ 4.7
  ``CharucoDetector``, legacy pattern option), plain chessboards (``findChessboardCornersSB``),
  circle grids; :func:`usable_detections` lists every skipped image with its reason.
* :mod:`._calib_solve` (:func:`calibrate_camera` in :mod:`._calib_camera`): facegeo's own solver (Zhang start, joint
  least squares over intrinsics, distortion and per-view poses; robust loss; outlier-view
  rejection; parameter standard deviations from ``σ² (JᵀJ)⁻¹`` raised to the jackknife over
  views from 6 views on (``sigma_method``); leave-one-view-out cross-validation;
  mrcal-style projection uncertainty over the image).
* :mod:`._calib_model` — the distortion models (:data:`MODELS`), the intrinsic parameter
  vector and the projection kernels the solvers share.
* :mod:`._calib_select` — :func:`select_model` (``model="auto"``): the distortion model per
  camera — degenerate lenses refused (:func:`lens_degeneracy`), a more complex model only when
  its leave-one-view-out held-out gain exceeds the noise.
* :mod:`._calib_projector` — :func:`projector_corners`: board corners in projector pixels by
  Moreno & Taubin's local homographies over the decoded structured light.
* :mod:`._calib_rig` — :func:`calibrate_rig` (bundle adjustment of N cameras and the board
  poses, world frame from a camera, a board view or an alignment transform) and
  :func:`cross_validate` (two solves on disjoint halves, mrcal's check).

Conventions: ``docs/conventions.md`` (poses ``T_cam_world``/``T_cam_board``, OpenCV camera frame,
integer pixel coordinates are pixel centres); metres and pixels. See ``docs/calibration.md``.

References
----------
.. [1] Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000.
.. [2] P. Debevec et al., SIGGRAPH 2000 course notes, image-based modeling, rendering and
   lighting: camera calibration.
.. [3] mrcal (D. Kogan): projection uncertainty and cross-validation,
   https://mrcal.secretsauce.net/uncertainty.html
"""

from __future__ import annotations

from facegeo.geometry._calib_detect import (
    MIN_CORNERS_PER_VIEW, BoardDetection, ChessboardSpec, CircleGridSpec, as_corner_lists,
    charuco_reading, detect_boards, detect_charuco, detect_chessboard, detect_circle_grid,
    detection_report,
    usable_detections,
)
from facegeo.geometry._calib_projector import (
    PROJECTOR_MIN_PIXELS, PROJECTOR_WINDOW_PX, projector_corners,
)
from facegeo.geometry._calib_rig import RigCalibration, calibrate_rig, cross_validate
from facegeo.geometry._calib_select import AUTO_CANDIDATES, lens_degeneracy, select_model
from facegeo.geometry._calib_camera import calibrate_camera
from facegeo.geometry._calib_solve import (
    JACKKNIFE_MIN_VIEWS, MODEL_FREE, MODELS, CameraCalibration, model_of_dist, project_points,
    rotate_rvec,
)

__all__ = [
    "AUTO_CANDIDATES", "JACKKNIFE_MIN_VIEWS", "MIN_CORNERS_PER_VIEW", "MODEL_FREE", "MODELS",
    "BoardDetection", "ChessboardSpec", "CircleGridSpec", "CameraCalibration", "RigCalibration",
    "as_corner_lists", "charuco_reading", "detect_boards", "detect_charuco", "detect_chessboard",
    "detect_circle_grid", "detection_report", "usable_detections",
    "PROJECTOR_MIN_PIXELS", "PROJECTOR_WINDOW_PX", "projector_corners",
    "calibrate_camera", "calibrate_rig", "cross_validate", "lens_degeneracy", "model_of_dist",
    "project_points", "rotate_rvec", "select_model",
]

