"""A calibrated rig against reference cameras: published intrinsics, or the generator's rig.

Reads the ``calibrate`` stage's ``rig.json`` (the calibrated rig, world frame; by default
``out/calibrate/rig.json``). The stage itself never reads a reference (issue 35: the
comparisons moved here); ``facegeo calibrate`` shows these figures beside the stage's
(:func:`with_calibration_errors`). References:

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
  ``projector.calibrated``) and the true rig has one, with
  ``focal_rel_error_without_joint`` — the projector's separate solve, before the joint bundle
  adjustment (the stage's ``projector.separate_intrinsics``). These are the figures the stage
  computed itself before the move, equal to 1e-9 (the alignment is fitted from the rig's
  world frame instead of the bundle adjustment's; a rigid change of frame leaves it as it is).

Headlines: ``<figure>_max`` over the cameras.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["evaluate_calibration", "intrinsics_errors", "with_calibration_errors"]


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


def _stage_metrics(folder: Path) -> dict:
    """The ``calibrate`` stage's metrics recorded in its folder: ``stage.json``'s (the stage
    cache's manifest) or ``metrics.json``'s (``facegeo calibrate --out``: ``{"calibrate": …}``);
    ``{}`` when neither reads."""
    for name in ("stage.json", "metrics.json"):
        try:
            doc = json.loads((folder / name).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        m = doc.get("metrics", doc) if isinstance(doc, dict) else {}
        m = m.get("calibrate", m) if isinstance(m, dict) else {}
        if isinstance(m, dict):
            return m
    return {}


def evaluate_calibration(scan, out, *, calibrate_dir=None, stage_metrics: dict | None = None
                         ) -> dict:
    """The calibrated rig against the scan's references (module docstring); ``{}`` when there
    is no calibrated rig or no reference.

    Parameters
    ----------
    scan : facegeo.capture.scan.Scan
    out : path-like
        The scan's ``out/``; the rig is read from ``out/calibrate/`` unless ``calibrate_dir``.
    calibrate_dir : path-like, optional
        The ``calibrate`` products' folder (``facegeo calibrate --out DIR``).
    stage_metrics : dict, optional
        The stage's metrics (``calibrate_products``' first return); default: those recorded in
        the folder. They say whether the projector was calibrated (an uncalibrated one keeps
        ``rig.json``'s nominal projector, which is not a measurement) and give its separate
        solve.
    """
    from facegeo.capture.references import reference_intrinsics
    from facegeo.geometry.rig import Rig

    folder = Path(calibrate_dir) if calibrate_dir is not None else Path(out) / "calibrate"
    path = folder / "rig.json"
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
                m.update(intrinsics_errors(c, t.K))
                m.update(_pose_errors(c, T_gt, t))
                if c.name in scan.rig.camera_names:
                    n = scan.rig.camera(c.name)
                    m["nominal_focal_rel_error"] = float(abs(n.fx / t.fx - 1))
                    m["nominal_principal_point_error_px"] = float(np.hypot(n.cx - t.cx,
                                                                           n.cy - t.cy))
            pr, pt = rig.projector, truth.projector
            proj = (stage_metrics if stage_metrics is not None
                    else _stage_metrics(folder)).get("projector")
            if isinstance(proj, dict) and proj.get("calibrated") and truth.projector_calibrated:
                metrics["projector"] = {**intrinsics_errors(pr, pt.K),
                                        **_pose_errors(pr, T_gt, pt)}
                sep = proj.get("separate_intrinsics")
                if isinstance(sep, dict):  # the separate solve, before the joint adjustment
                    metrics["projector"]["focal_rel_error_without_joint"] = float(
                        max(abs(sep["fx"] / pt.fx - 1), abs(sep["fy"] / pt.fy - 1)))
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


def with_calibration_errors(scan, stage_metrics: dict, calibrate_dir) -> dict:
    """The ``calibrate`` stage's metrics with :func:`evaluate_calibration`'s figures merged in:
    each camera's and the projector's errors beside the stage's own figures, and the
    ``<figure>_max`` headlines — the table ``facegeo calibrate`` prints (the stage computed
    these itself before issue 35 moved them here). ``stage_metrics`` is not modified."""
    ev = evaluate_calibration(scan, None, calibrate_dir=calibrate_dir,
                              stage_metrics=stage_metrics)
    merged = dict(stage_metrics)
    merged["cameras"] = {name: {**cm, **ev.get("cameras", {}).get(name, {})}
                         for name, cm in stage_metrics.get("cameras", {}).items()}
    if isinstance(stage_metrics.get("projector"), dict) and "projector" in ev:
        merged["projector"] = {**stage_metrics["projector"], **ev["projector"]}
    merged.update({k: v for k, v in ev.items() if k.endswith("_max")})
    return merged
