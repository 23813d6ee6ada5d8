"""Fitted normals against a reference normal map (``[reference] normals``).

A photometric-stereo data set publishes the object's true normals per pixel (DiLiGenT's
``Normal_gt``; ``facegeo import --dataset diligent`` writes ``reference/normals.npy``: ``(H, W,
3)`` float64, unit, camera frame). The image-space ``fit`` stage writes its models in
``out/fit/photometric.npz`` (normals in the lights' — world — frame, the rows the pixels
``r·W + c``); the reference is turned into the world frame by the camera's rotation
(``n_world = R_cam_world^T n_cam``) and compared where both are finite:

* ``normal_mean_error_deg``, ``normal_median_error_deg``, ``normals_compared``.

On the fit's own pixels and rows this is the figure the stage's scoring reports (the same
angles, :func:`facegeo.appearance.lambertian.angular_error_deg`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facegeo.errors import InputError

__all__ = ["evaluate_normals", "normal_errors"]


def normal_errors(normal, ref) -> dict:
    """Mean and median angle (degrees, rounded to 4 digits) of ``normal`` against ``ref``
    (both ``(N, 3)``, the same frame) over the rows where both are finite."""
    from facegeo.appearance.lambertian import angular_error_deg

    err = angular_error_deg(np.asarray(normal, np.float64), np.asarray(ref, np.float64))
    err = err[np.isfinite(err)]
    if not err.size:
        return {"normal_mean_error_deg": None, "normal_median_error_deg": None,
                "normals_compared": 0}
    return {"normal_mean_error_deg": round(float(err.mean()), 4),
            "normal_median_error_deg": round(float(np.median(err)), 4),
            "normals_compared": int(err.size)}


def evaluate_normals(scan, out) -> dict:
    """``out/fit/photometric.npz`` against ``[reference] normals`` (module docstring); ``{}``
    when either is missing."""
    from facegeo.appearance.photometric import load_photometric

    path = Path(out) / "fit" / "photometric.npz"
    if "normals" not in scan.reference_keys or not path.is_file():
        return {}
    model = load_photometric(path)
    with np.load(path) as z:
        rows = z["rows"].astype(np.int64)
        W, H = (int(v) for v in z["image_size"])
    ref_path = scan.reference_path("normals")
    n_cam = np.load(ref_path)
    if n_cam.size != H * W * 3:
        raise InputError(f"[reference] normals: {ref_path} holds {n_cam.shape}, the fitted "
                         f"image is {H} x {W} (expected ({H}, {W}, 3))")
    cam = scan.camera_names[0]
    ref = n_cam.reshape(-1, 3)[rows] @ scan.rig.camera(cam).T_cam_world.R
    return {"reference": f"reference normals ({ref_path.name})", "camera": cam,
            **normal_errors(model.normal, ref)}
