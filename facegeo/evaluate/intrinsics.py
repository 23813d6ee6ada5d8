"""A calibrated rig against reference cameras: published intrinsics, or the generator's rig.

Reads ``out/calibrate/rig.json`` (the calibrated rig, world frame). References:

* ``[reference] intrinsics`` of a real scan (:func:`facegeo.capture.references.reference_intrinsics`):
  per camera ``reference_focal_rel_error`` = ``max(|fx / fx_ref − 1|, |fy / fy_ref − 1|)`` and
  ``reference_principal_point_error_px`` = ``|c − c_ref|``;
* the generator's true rig (``ground_truth/rig.json``, synthetic scans): per camera
  ``focal_rel_error``, ``principal_point_error_px`` and, after the rigid alignment of the whole
  rig onto the true one (the calibrated world frame is a gauge; the alignment is the
  ``calibrate`` stage's own, ``facegeo.pipeline.calibrate._align``), ``rotation_error_deg`` and
  ``translation_error_mm`` (camera centres); ``nominal_focal_rel_error`` /
  ``nominal_principal_point_error_px`` of the scan's nominal ``rig.json`` beside them; the
  projector's under ``projector`` when the stage calibrated it (its metrics say
  ``projector.calibrated``) and the true rig has one. On the scan of
  ``tests/test_evaluate.py`` these equal the stage's own figures to 1e-12.

Headlines: ``<figure>_max`` over the cameras.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["evaluate_calibration", "intrinsics_errors"]


def intrinsics_errors(camera, K_ref) -> dict:
    """``focal_rel_error`` and ``principal_point_error_px`` of ``camera`` against the 3 × 3
    matrix ``K_ref``."""
    K_ref = np.asarray(K_ref, np.float64)
    return {"focal_rel_error": float(max(abs(camera.fx / K_ref[0, 0] - 1),
                                         abs(camera.fy / K_ref[1, 1] - 1))),
            "principal_point_error_px": float(np.hypot(camera.cx - K_ref[0, 2],
                                                       camera.cy - K_ref[1, 2]))}


def _rot_deg(Ra, Rb) -> float:
    from facegeo.frames import rvec_from_rotation

    return float(np.degrees(np.linalg.norm(rvec_from_rotation(Ra @ Rb.T))))


def _pose_errors(est, T_gt, true) -> dict:
    T_est = est.T_cam_world @ T_gt
    return {"rotation_error_deg": _rot_deg(T_est.R, true.T_cam_world.R),
            "translation_error_mm": float(
                np.linalg.norm(T_est.origin_of_a_in_b - true.center_world) * 1e3)}


def _projector_was_calibrated(out) -> bool:
    """Whether the calibrate stage calibrated the projector (its metrics say so; an
    uncalibrated one keeps ``rig.json``'s nominal projector, which is not a measurement)."""
    for name in ("stage.json", "metrics.json"):
        path = Path(out) / "calibrate" / name
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        m = doc.get("metrics", doc) if isinstance(doc, dict) else {}
        proj = m.get("projector") if isinstance(m, dict) else None
        return bool(isinstance(proj, dict) and proj.get("calibrated"))
    return False


def evaluate_calibration(scan, out) -> dict:
    """The calibrated rig in ``out/calibrate/`` against the scan's references (module
    docstring); ``{}`` when there is no calibrated rig or no reference."""
    from facegeo.capture.references import reference_intrinsics
    from facegeo.geometry.rig import Rig

    path = Path(out) / "calibrate" / "rig.json"
    if not path.is_file():
        return {}
    rig = Rig.load(path)
    cams: dict[str, dict] = {}
    for name, K in reference_intrinsics(scan).items():
        if name in rig.camera_names:
            e = intrinsics_errors(rig.camera(name), K)
            cams.setdefault(name, {}).update({f"reference_{k}": v for k, v in e.items()})
    metrics: dict = {}
    if scan.synthetic and "rig" in scan.ground_truth_keys:
        from facegeo.pipeline.calibrate import _align

        truth = Rig.load(scan.ground_truth_path("rig"))
        mine = [c for c in rig.cameras if c.name in truth.camera_names]
        if mine:
            T_gt = _align(mine, truth.cameras)
            for c in mine:
                t = truth.camera(c.name)
                m = cams.setdefault(c.name, {})
                K_t = np.array([[t.fx, 0, t.cx], [0, t.fy, t.cy], [0, 0, 1]])
                m.update(intrinsics_errors(c, K_t))
                m.update(_pose_errors(c, T_gt, t))
                if c.name in scan.rig.camera_names:
                    n = scan.rig.camera(c.name)
                    m["nominal_focal_rel_error"] = float(abs(n.fx / t.fx - 1))
                    m["nominal_principal_point_error_px"] = float(np.hypot(n.cx - t.cx,
                                                                           n.cy - t.cy))
            pr, pt = rig.projector, truth.projector
            if _projector_was_calibrated(out) and truth.projector_calibrated:
                K_t = np.array([[pt.fx, 0, pt.cx], [0, pt.fy, pt.cy], [0, 0, 1]])
                metrics["projector"] = {**intrinsics_errors(pr, K_t),
                                        **_pose_errors(pr, T_gt, pt)}
    if not cams and not metrics:
        return {}
    metrics["cameras"] = cams
    for key in ("focal_rel_error", "principal_point_error_px", "rotation_error_deg",
                "translation_error_mm", "reference_focal_rel_error",
                "reference_principal_point_error_px"):
        vals = [c[key] for c in cams.values() if key in c]
        if vals:
            metrics[f"{key}_max"] = float(max(vals))
    return metrics
