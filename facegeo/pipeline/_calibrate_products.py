"""What the calibrate stage reports and writes per solve (private; :mod:`facegeo.pipeline.
calibrate` is the stage): a solve's statistics for the metrics (:func:`solve_metrics`, the same
for a camera and the projector), each camera's OpenCV FileStorage file, the rig's stereo pairs
for OpenCV's tools and the residual plots.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from facegeo.errors import InputError

__all__ = ["CV_HALVES_MIN_VIEWS", "CV_SPLITS", "LOO_MIN_VIEWS", "RESIDUAL_GAIN",
           "residual_plot", "solve_metrics", "write_stereo_pairs", "write_yaml"]

#: Residual vectors are drawn this many times longer than they are.
RESIDUAL_GAIN = 100.0


#: Fewest board views of the two-halves cross-validation (:func:`~facegeo.geometry.calibration.
#: cross_validate`: three views per half). From :data:`LOO_MIN_VIEWS` used views on, a solve is
#: also cross-validated by leaving one view out at a time (the only check below 6 views).
CV_HALVES_MIN_VIEWS = 6

#: Fewest used views of the leave-one-view-out check (three left to solve each time).
LOO_MIN_VIEWS = 4

#: Random splits of the two-halves cross-validation, combined as the RMS of their figures
#: (``cross_validate(splits=...)``). One split is one draw: on OpenCV's right camera seed 0 read
#: 1.08 px where seeds 1-3 read 0.44-1.03 (facegeo's corners; OpenCV's 0.39-1.07); over 4
#: splits 0.84 px (OpenCV's corners 0.79), the left camera 0.15 (1.03). 4 splits cost 8 solves
#: of half the views.
CV_SPLITS = 4

_INTRINSICS = ("fx", "fy", "cx", "cy")


def solve_metrics(c, P, Q, *, loss: str, cross_validation: bool) -> dict:
    """What one solve (a camera's or the projector's: the same statistics) tells the metrics.

    ``model_selection`` (with ``model="auto"``: ``reason``, ``best``, ``folds``, ``scores``
    and ``rejected`` — why each other candidate, a degenerate lens among them, was not taken);
    ``std_px`` (σ of fx, fy, cx, cy as reported), ``std_formal_px`` (``σ² (JᵀJ)⁻¹``),
    ``sigma_method`` (``"jackknife"`` from
    :data:`~facegeo.geometry.calibration.JACKKNIFE_MIN_VIEWS` views, else ``"formal"``) and
    ``sigma_inflation`` (RMS of ``std / std_formal``); the projection uncertainty
    ``projection_uncertainty_rms_px`` / ``_max_px`` where the views have corners
    (``projection_uncertainty_region`` ``"covered"``: the grid pixels inside their convex hull,
    the region ``cross_validation_px`` compares; ``"image"`` when no grid pixel is) and over the
    whole image, ``projection_uncertainty_image_rms_px`` / ``_image_max_px`` (the lens model's
    extrapolation to the image's corners included); and, with ``cross_validation``,
    ``leave_one_out_held_out_rms_px`` (RMS over the used
    corners of each view's residual at the intrinsics solved without it, its pose re-solved:
    :meth:`~facegeo.geometry.calibration.CameraCalibration.leave_one_out`; from
    :data:`LOO_MIN_VIEWS` used views), ``leave_one_out_projection_rms_px`` (the jackknife
    spread of the projection over the image) beside ``leave_one_out_predicted_rms_px`` (the
    projection uncertainty on the same pixels), and ``cross_validation_px`` /
    ``_max_px`` / ``_predicted_px`` (two solves on disjoint halves of the ``P``, ``Q`` views,
    compared where both halves have corners, from :data:`CV_HALVES_MIN_VIEWS`; None below;
    the RMS over :data:`CV_SPLITS` random splits, each split's in ``cross_validation_splits_px``),
    ``cross_validation_image_px`` (the same over the whole image: extrapolation included) or
    ``cross_validation_error`` (why it could not be made). ``cross_validation_method`` names
    the checks made.
    """
    from facegeo.geometry.calibration import cross_validate

    m = {"std_px": {k: c.std[k] for k in _INTRINSICS},
         "std_formal_px": {k: c.std_formal[k] for k in _INTRINSICS if k in c.std_formal},
         "sigma_method": c.sigma_method, "sigma_inflation": c.sigma_inflation}
    if c.model_selection is not None:
        m["model_selection"] = {k: c.model_selection[k]
                                for k in ("reason", "best", "folds", "scores", "rejected")}
    # σ of the projection where the views have corners (beside cross_validation_px, which
    # compares there too), and over the whole image: the lens model's extrapolation
    # (CameraCalibration.projection_uncertainty: OpenCV's left camera 0.30 px against 3.8 px)
    u = c.projection_uncertainty()
    m["projection_uncertainty_image_rms_px"] = u["rms_px"]
    m["projection_uncertainty_image_max_px"] = u["max_px"]
    try:
        u = c.projection_uncertainty(region="covered")
        m["projection_uncertainty_region"] = "covered"
    except InputError:  # no grid pixel inside the corners: the whole image's figure
        m["projection_uncertainty_region"] = "image"
    m["projection_uncertainty_rms_px"] = u["rms_px"]
    m["projection_uncertainty_max_px"] = u["max_px"]
    m["cross_validation_px"] = None
    checks = []
    if cross_validation and c.n_views_used >= LOO_MIN_VIEWS:
        loo = c.leave_one_out()
        m["leave_one_out_held_out_rms_px"] = loo["held_out_rms_px"]
        m["leave_one_out_projection_rms_px"] = loo["projection_jackknife_rms_px"]
        m["leave_one_out_predicted_rms_px"] = loo["predicted_rms_px"]
        checks.append(f"leave-one-view-out over {loo['views']} views")
    if cross_validation and len(P) >= CV_HALVES_MIN_VIEWS:
        try:
            cv = cross_validate(P, Q, c.camera.size, model=c.model, loss=loss,
                                reject_views=False, splits=CV_SPLITS)
        except InputError as exc:  # e.g. the halves' corners share too few grid pixels
            m["cross_validation_error"] = str(exc)
        else:
            m["cross_validation_px"] = cv["diff_rms_px"]
            m["cross_validation_max_px"] = cv["diff_max_px"]
            m["cross_validation_predicted_px"] = cv["predicted_rms_px"]
            m["cross_validation_image_px"] = cv["image_diff_rms_px"]
            m["cross_validation_splits_px"] = cv["split_diff_rms_px"]
            checks.append(f"two halves of {len(P)} views, {CV_SPLITS} random splits, where "
                          f"both have corners (≥ {cv['n_pixels']} grid pixels)")
    m["cross_validation_method"] = "; ".join(checks) or None
    return m


def write_yaml(path: Path, cam, rms: float, per_view, model: str | None = None) -> None:
    """``<camera>.yml`` as OpenCV's calibration sample writes it (no pose), atomically; with
    ``model``, the distortion model chosen (``distortion_model``: which of the coefficients
    were solved for, e.g. ``k1`` of a 4-vector; OpenCV's tools ignore the key)."""
    from facegeo.capture.opencv_storage import write_opencv_camera

    extra = {"avg_reprojection_error": float(rms),
             "per_view_reprojection_errors": np.asarray(per_view, np.float64).reshape(-1, 1)}
    if model is not None:
        extra["distortion_model"] = model
    write_opencv_camera(path, cam, pose=False, extra=extra)


def write_stereo_pairs(out: Path, cameras, reference: str) -> dict:
    """The rig's extrinsics for OpenCV's tools: one ``stereo_<reference>_<camera>.yml`` per
    camera beside the reference (:func:`facegeo.capture.opencv_storage.write_opencv_stereo`:
    ``M1, D1, M2, D2`` and ``R, T, E, F`` as ``cv2.stereoCalibrate`` names them, camera 1 the
    reference; ``T`` in metres; ``R_cam1_world``, ``T_cam1_world`` place the pair in the rig's
    world frame). ``cameras``: the calibrated cameras in the world frame; ``reference``: the
    camera of the pairs' camera 1 (the bundle adjustment's, or the first camera when that was
    the projector). Returns ``{camera: file name}`` and, for a camera whose image size differs
    from the reference's (an OpenCV stereo pair has one image size), ``{camera: why}`` under
    ``"skipped"``."""
    from facegeo.capture.opencv_storage import write_opencv_stereo

    by_name = {c.name: c for c in cameras}
    ref = by_name.get(reference, cameras[0])
    written, skipped = {}, {}
    for c in cameras:
        if c.name == ref.name:
            continue
        if c.size != ref.size:
            skipped[c.name] = (f"image size {c.size} differs from the reference {ref.name}'s "
                               f"{ref.size}: an OpenCV stereo pair has one image size")
            continue
        name = f"stereo_{ref.name}_{c.name}.yml"
        write_opencv_stereo(out / name, ref, c)
        written[c.name] = name
    return {"reference": ref.name, "files": written, **({"skipped": skipped} if skipped else {})}


def residual_plot(path: Path, size, r: np.ndarray, q: np.ndarray, title: str) -> None:
    """Residual vectors over the image (left) and a histogram of ‖r‖ (right), as a PNG."""
    W, H = size
    s = min(1.0, 640.0 / max(W, H))
    w, h = max(int(W * s), 1), max(int(H * s), 1)
    img = np.full((h + 40, w + 320, 3), 255, np.uint8)
    cv2.rectangle(img, (0, 40), (w - 1, h + 39), (0, 0, 0), 1)
    for (x, y), (dx, dy) in zip(q, r):
        p0 = (int(round(x * s)), int(round(y * s)) + 40)
        p1 = (int(round((x + RESIDUAL_GAIN * dx) * s)), int(round((y + RESIDUAL_GAIN * dy) * s))
              + 40)
        cv2.line(img, p0, p1, (200, 0, 0), 1, cv2.LINE_AA)
        cv2.circle(img, p0, 1, (0, 0, 0), -1)
    mag = np.linalg.norm(r, axis=-1)
    hist, edges = np.histogram(mag, bins=30, range=(0.0, max(float(mag.max()), 1e-9)))
    x0, y0, bw, bh = w + 20, 60, 280, h - 40
    top = max(int(hist.max()), 1)
    for i, c in enumerate(hist):
        x = x0 + int(i * bw / len(hist))
        cv2.rectangle(img, (x, y0 + bh - int(bh * c / top)), (x + int(bw / len(hist)) - 1,
                                                                 y0 + bh), (0, 0, 200), -1)
    cv2.line(img, (x0, y0 + bh), (x0 + bw, y0 + bh), (0, 0, 0), 1)
    cv2.putText(img, f"|r| px: 0 .. {edges[-1]:.3g}", (x0, y0 + bh + 18),
                cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, f"{title}  RMS {np.sqrt(np.mean(mag ** 2)):.3f} px  (vectors x"
                f"{RESIDUAL_GAIN:g})", (5, 25), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1,
                cv2.LINE_AA)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img[..., ::-1]):
        raise InputError(f"{path}: could not write the residual plot")
