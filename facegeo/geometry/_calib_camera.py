"""Calibrating one camera: :func:`calibrate_camera`, the public entry of the solver
(:mod:`._calib_solve`) and of the model selection (:mod:`._calib_select`) — kept apart from both
so that neither imports the other's user (no import cycle).
"""

from __future__ import annotations

from facegeo.checks import as_array, check_choice, check_positive
from facegeo.errors import InputError
from facegeo.geometry._calib_select import _select
from facegeo.geometry._calib_solve import (
    _LOSSES,
    MODELS,
    CameraCalibration,
    _check_views,
    fit_model,
    zhang_start,
)

__all__ = ["calibrate_camera"]


def calibrate_camera(object_points, image_points, image_size, *, model: str = "opencv5",
                     fix_aspect_ratio: float | None = None, K_init=None,
                     loss: str = "linear", f_scale: float = 1.0,
                     reject_views: bool = True, reject_factor: float = 3.0,
                     reject_floor_px: float = 0.5, min_views: int = 3,
                     auto_fallback: str = "opencv5", name: str = "camera") -> CameraCalibration:
    """Calibrate one camera from corner lists (Zhang 2000 start, joint least squares).

    Speed: 0.4–1.1× ``cv2.calibrateCamera``'s time on the same corners and model, ``auto``
    4–5× one OpenCV calibration (module docstring; ``docs/calibration.md`` § "Model selection
    without degenerate lenses, honest σ, speed").

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
        :data:`~._calib_select.AUTO_CANDIDATES` (:func:`~._calib_select.select_model`: every
        candidate solved on all views, warm-started from the previous one; degenerate lenses
        refused; a more complex model only when its leave-one-view-out held-out error beats
        the simpler one's by more than the noise) and records the choice in
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
        With ``sigma_method`` / ``sigma_inflation`` saying how :attr:`~CameraCalibration.std`
        was made honest (the jackknife over views from :data:`JACKKNIFE_MIN_VIEWS` views).

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
    check_choice(model, "model", tuple(MODELS) + ("auto",))
    usable, reasons = _check_views(P, Q, size, min_views)
    opts = dict(fix_aspect_ratio=fix_aspect_ratio, loss=loss, f_scale=f_scale,
                reject_views=reject_views, reject_factor=reject_factor,
                reject_floor_px=reject_floor_px, min_views=min_views, name=name)
    if model == "auto":
        selection, c = _select(P, Q, size, usable, reasons, fallback=auto_fallback,
                               K_init=K_init, **opts)
        c.model_selection = selection
        return c
    start = zhang_start(P, Q, size, usable, fix_aspect_ratio=fix_aspect_ratio, K_init=K_init)
    return fit_model(P, Q, size, usable, model, start, rejected=reasons, **opts)
