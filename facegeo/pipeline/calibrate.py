"""The calibrate stage: cameras, rig and projector from a scan's board views (issues 9, 35).

``run_calibrate(scan_dir, out_dir)`` (``facegeo calibrate``) reads every camera's
``calib/<camera>/`` views, detects the board
(:func:`facegeo.geometry.calibration.detect_boards`; a plain chessboard's corners refined on
the stored values or in linear light through ``[calib] response``, whichever fits the board's
local homographies better per camera — ``metrics["cameras"][name]["corner_refinement"]``),
calibrates each camera
(:func:`~facegeo.geometry.calibration.calibrate_camera`; by default its distortion model is
chosen by k-fold cross-validation over its views, ``model="auto"``), cross-validates it,
bundle-adjusts the rig (:func:`~facegeo.geometry.calibration.calibrate_rig`; a camera with
fewer than :data:`MIN_VIEWS_ALONE` views keeps its nominal intrinsics and is only posed, with a
warning) and writes

* ``rig.json`` — the scan's rig with the calibrated cameras (``Rig`` serialisation); the world
  frame is ``scan.world`` when declared, else the board of view 0 of the first camera (a
  synthetic scan, or lights on a θ × φ grid: the nominal ``rig.json``'s frame, the calibrated
  rig placed on it by a working-volume fit; :func:`_world_frame`); the projector is the jointly calibrated one when the scan
  has projector views that calibrate, else ``rig.json``'s own (a nominal projector camera
  placed in the world frame, an uncalibrated resolution-only entry copied unchanged: it has no
  pose), the lights are copied;
* ``<camera>.yml`` — OpenCV FileStorage: ``camera_matrix``, ``distortion_coefficients``,
  ``image_width``, ``image_height``, ``avg_reprojection_error``, ``per_view_reprojection_errors``,
  ``distortion_model`` (the model chosen: which coefficients were solved for);
* ``stereo_<reference>_<camera>.yml`` — with two or more cameras, the rig's extrinsics for
  OpenCV's tools, one file per camera beside the reference camera (``M1, D1, M2, D2, R, T, E,
  F`` as ``cv2.stereoCalibrate`` / ``stereo_calib`` name them, ``T`` in metres:
  :func:`~facegeo.pipeline._calibrate_products.write_stereo_pairs`); ``metrics["opencv_stereo"]`` lists them;
* ``residuals_<camera>.png`` — residual vectors over the image (×``RESIDUAL_GAIN``) and a
  histogram of their lengths, drawn with OpenCV (matplotlib is not a dependency);
* ``detections.json`` — the per-image detection report;
* with ``[calib.projector]`` views: the projector — the board (any kind the cameras accept)
  found in each view's white frame, the view's patterns decoded (its own frames and
  patterns, or ``[structured_light]``'s), Moreno & Taubin local homographies
  (:mod:`facegeo.pipeline._calibrate_projector`), a separate solve from the Zhang start — no
  nominal intrinsics needed; its distortion model chosen as a camera's, ``model="auto"`` with
  the rig file's model — :data:`PROJECTOR_MODEL` for an uncalibrated entry — as fallback; σ,
  projection uncertainty and cross-validation as a camera's — then the rig's bundle adjustment
  with the projector refined jointly or kept at its separate solve, whichever predicts
  held-out projector corners better: :func:`~facegeo.pipeline._calibrate_projector.
  projector_rig`), its YAML and residual plot; otherwise ``metrics["projector"]`` says that it was not calibrated, why,
  and what ``rig.json`` keeps instead (also logged as a warning, its record marked with
  :data:`SUMMARY_RECORD`: ``facegeo calibrate`` prints the line itself and drops the record);
* ``metrics.json`` — ``{"calibrate": metrics}`` (the dict returned), by ``run_calibrate`` only.

``calibrate_products(scan, dest, **settings) -> (metrics, settings)`` is the same work as a
cached stage (the shape of ``facegeo.pipeline.project.project_products``): it writes the products
above except ``metrics.json`` and returns the metrics for the stage cache to record.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError
from facegeo.frames import Pose
from facegeo.fsutil import atomic_write_text
from facegeo.pipeline._calibrate_products import (  # noqa: F401 (re-exported)
    CV_HALVES_MIN_VIEWS,
    LOO_MIN_VIEWS,
    RESIDUAL_GAIN,
    residual_plot,
    solve_metrics,
    write_stereo_pairs,
    write_yaml,
)
from facegeo.pipeline._calibrate_projector import (  # noqa: F401 (SUMMARY_RECORD re-exported)
    SUMMARY_RECORD,
    projector_observations as _projector_observations,
    projector_rig as _projector_rig,
    projector_spec,
    view_label,
    view_rejections,
)

log = logging.getLogger(__name__)

__all__ = ["CALIBRATE_DEFAULTS", "run_calibrate", "calibrate_products", "calibrate_inputs",
           "RESIDUAL_GAIN"]

# RESIDUAL_GAIN (residual vectors' drawing scale): defined with the plots, re-exported.

# SUMMARY_RECORD (the log-record attribute of a line the metrics repeat) is defined beside the
# projector's observations, which log one too, and re-exported here.


#: Fewest usable board views a camera is calibrated from on its own; a rig camera with fewer
#: keeps its nominal intrinsics and only its pose is solved (with a warning).
MIN_VIEWS_ALONE = 3

#: Pixels per image side whose rays place a calibrated rig on a reference rig (:func:`_align`).
ALIGN_GRID = 7

#: Fallback lens model of a projector calibrated from an uncalibrated ``rig.json`` entry
#: (resolution only: no distortion vector to take the model from, as a nominal projector camera
#: gives). The projector goes through the cameras' model selection (``model="auto"``: issue 35 —
#: on a real procam capture the selection preferred ``k1``, held-out 0.219 vs 0.260 px, and
#: forcing pinhole moved the projector's cy by ≈ 125 px); this model is used only when its views
#: are too few to hold one out (3), and when the stage's ``model`` is not ``auto``.
PROJECTOR_MODEL = "pinhole"


def _working_point(cameras) -> np.ndarray:
    """The point nearest every camera's optical axis (least squares): where the rig looks."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cameras:
        d = c.T_cam_world.R[2]  # optical axis in the world frame
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center_world
    if len(cameras) < 2 or np.linalg.cond(A) > 1e8:  # one camera, or parallel axes
        c = cameras[0]
        return c.center_world + c.T_cam_world.R[2] * np.linalg.norm(c.center_world)
    return np.linalg.solve(A, b)


def _align(cameras, reference_cameras) -> Pose:
    """``T_rig_world``: the rigid transform placing a calibrated rig (its own frame, ``rig``) on
    ``reference_cameras`` (same names, world frame) so that both see the same working volume.

    Each camera contributes its centre and a ``ALIGN_GRID²`` grid of pixels whose rays are cut at
    the depth where the reference camera sees the rig's working point (:func:`_working_point`);
    the transform is the least-squares rigid fit of these points (Kabsch, via
    :func:`facegeo.frames.nearest_rotation`). Fitting camera poses instead would pivot the
    working volume about the cameras: on narrow cameras a principal-point error is nearly a
    camera rotation, and 0.35° of it swings the head 1.1 m away by ≈ 7 mm.

    Each side's rays go through its own intrinsics, so the calibrated rig's pixels see the points
    the reference rig's pixels see. Small preset placed on its nominal ``rig.json``: the
    structured-light mesh lands 0.41° / 6.5 mm from the true surface; 0.79° / 14.2 mm with the
    average of the camera poses, 0.95° / 17 mm with the calibrated intrinsics on both sides (the
    poses alone placing the rig).
    """
    from facegeo.frames import nearest_rotation

    ref = {c.name: c for c in reference_cameras}
    pairs = [(c, ref[c.name]) for c in cameras if c.name in ref]
    target = _working_point([r for _, r in pairs])
    src, dst = [], []
    for c, r in pairs:
        depth = float(r.T_cam_world.apply(target)[2])
        xs = np.linspace(0, r.width - 1, ALIGN_GRID)
        ys = np.linspace(0, r.height - 1, ALIGN_GRID)
        q = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
        vc, ok_c = c.unproject(q, return_valid=True)
        vr, ok_r = r.unproject(q, return_valid=True)
        ok = ok_c & ok_r
        src += [c.center_world, *c.T_cam_world.inverse().apply(vc[ok] * depth)]
        dst += [r.center_world, *r.T_cam_world.inverse().apply(vr[ok] * depth)]
    src, dst = np.asarray(src), np.asarray(dst)
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    R = nearest_rotation((dst - cd).T @ (src - cs))
    T_world_rig = Pose(R, cd - R @ cs)
    return T_world_rig.inverse()


def _world_frame(scan, rig_cal, obs, proj_name, nominal) -> tuple[Pose, Pose, str]:
    """Where the calibrated rig goes: ``(T_rig_world, T_world_nominal, what)``.

    ``T_rig_world`` maps world points into the bundle adjustment's frame (the reference
    camera's); ``T_world_nominal`` maps points of the scan's nominal ``rig.json`` frame (where
    its lights and an uncalibrated projector live) into the world frame. ``scan.world``
    (format v2) decides: ``{camera, board_view}`` — the board's frame in that view (the bundle
    adjustment's pose of that board); ``{transform}`` — ``p_world = T · p_nominal``, the
    calibrated rig placed on the nominal one by the working-volume fit (:func:`_align`).

    Without it (issues 35, 37) the world is the board of view 0 of the scan's first camera
    (:func:`_default_board_view`: the lowest view that camera used when view 0 is not one of
    them): a measured frame, where the nominal ``rig.json``'s frame is a guess (15 mm and 0.43°
    from the board on a real capture). Two cases keep the nominal frame instead, placed by the
    working-volume fit: a synthetic scan (its ``rig.json`` frame is the generator's world, where
    its truth, lights and novel cameras are given — the generator declares no ``world``), and a
    rig whose lights are the θ × φ grid (its axes are the rig frame's: it cannot turn with a
    board; :func:`_lights_to_world`). ``what`` says which frame was taken and why.
    """
    cams = [c for c in rig_cal.cameras if c.name != proj_name]
    T_rig_nom = _align(cams, nominal.cameras)
    w = scan.world
    if w is None:
        from facegeo.geometry.lights import LightList

        if scan.synthetic:
            return (T_rig_nom, Pose.identity(), "the nominal rig.json frame (working-volume "
                    "fit): a synthetic scan's rig.json frame is the generator's world")
        if nominal.lights is not None and not isinstance(nominal.lights, LightList):
            return (T_rig_nom, Pose.identity(), "the nominal rig.json frame (working-volume "
                    "fit): the rig's lights are a θ × φ grid, whose axes cannot turn with "
                    "a board (declare scan.world to choose)")
        cam, view = _default_board_view(scan, obs)
        T_rig_world = rig_cal.T_world_board[f"v{view}"]
        why = "" if view == 0 else f"; view 0 not used by {cam}"
        return (T_rig_world, T_rig_world.inverse() @ T_rig_nom,
                f"board of view {view} (camera {cam}): no scan.world declared, the board of "
                f"view 0 of the first camera{why}")
    if "T_world_rig" in w:
        T_world_nom = Pose.from_matrix(w["T_world_rig"])
        return T_rig_nom @ T_world_nom.inverse(), T_world_nom, "scan.world.transform"
    key = f"v{int(w['board_view'])}"
    if key not in obs.get(w["camera"], {}):
        used = ", ".join(sorted(k[1:] for k in obs.get(w["camera"], {}) if k.startswith("v")))
        raise InputError(f"scan.world: camera {fmt_value(w['camera'])} has no usable board in view "
                         f"{w['board_view']} (the world frame's board pose); views it used: "
                         f"{used or 'none'}")
    # p_rig = T_rig_board · p_board and the world is the board: T_rig_world = T_rig_board
    T_rig_world = rig_cal.T_world_board[key]
    return (T_rig_world, T_rig_world.inverse() @ T_rig_nom,
            f"board of view {w['board_view']} (camera {w['camera']})")


def _default_board_view(scan, obs) -> tuple[str, int]:
    """The board pose that holds the world frame when the scan declares none: view 0 of the
    scan's first camera, else the lowest ``[calib]`` view that camera used (its board views
    are keyed ``v<view>``; a camera with none passes to the next)."""
    for cam in scan.camera_names:
        views = sorted(int(k[1:]) for k in obs.get(cam, {}) if k[:1] == "v" and k[1:].isdigit())
        if views:
            return cam, views[0]
    raise InputError(f"{scan.root}: no camera has a usable board view to hold the world frame")


def _projector_not_calibrated(projector, attempt: dict | None) -> dict:
    """``metrics["projector"]`` of a projector the stage did not calibrate: ``calibrated``
    (False), ``reason``, ``rig_json`` (what the calibrated ``rig.json`` holds instead:
    ``"nominal"`` — the scan's projector camera as given; ``"uncalibrated"`` — resolution only)
    and ``summary`` (one line for the CLI), beside ``attempt``'s keys (a failed attempt:
    ``error``, ``views_detected`` ...). ``attempt`` is None when the scan has no projector
    board views."""
    from facegeo.geometry.camera import Camera

    m = dict(attempt or {})
    if attempt is None:
        why = "no [calib.projector] board views"
    else:
        err = str(attempt.get("error", "no usable view"))
        err = err[len("projector: "):] if err.startswith("projector: ") else err
        why = f"its [calib.projector] board views did not calibrate it: {err}"
    if isinstance(projector, Camera):
        kept, what = "nominal", ("rig.json's nominal projector (its intrinsics and pose as "
                                 "given, not measured)")
    else:
        kept, what = "uncalibrated", ("rig.json's uncalibrated projector (resolution only: no "
                                      "intrinsics, no pose)")
    m.update({"calibrated": False, "reason": why, "rig_json": kept,
              "summary": f"projector: not calibrated ({why}); the calibrated "
                         f"rig.json keeps {what}"
                         + ("; board views under [calib.projector] calibrate it"
                            if attempt is None else "")})
    return m


def _lights_to_world(lights, T_world_nom: Pose):
    """The nominal rig's lights in the world frame (``T_world_nom``: nominal → world).

    A light list moves with the frame (directions rotated, positions and centre mapped); the
    θ × φ grid's axes are fixed to the rig frame, so only a translation (its centre) can follow.
    """
    from dataclasses import replace

    from facegeo.geometry.lights import LightList

    if lights is None or T_world_nom == Pose.identity():
        return lights
    if isinstance(lights, LightList):
        return replace(
            lights, center=T_world_nom.apply(np.asarray(lights.center, np.float64)),
            directions=(None if lights.positions is not None
                        else T_world_nom.apply_direction(lights.directions)),
            positions=None if lights.positions is None else T_world_nom.apply(lights.positions),
            horizon_axis=(None if lights.horizon_axis is None
                          else T_world_nom.apply_direction(lights.horizon_axis)))
    if np.degrees(np.linalg.norm(T_world_nom.rvec)) > 1e-9:
        raise InputError("scan.world rotates the world against the rig frame, but the rig's "
                         "lights are the θ × φ grid, whose axes are the rig frame's: give the "
                         "lights as a list (directions), or a world frame without rotation")
    return replace(lights, center=tuple(T_world_nom.apply(np.asarray(lights.center, float))))


def _rot_deg(Ra, Rb) -> float:
    from facegeo.frames import rvec_from_rotation

    return float(np.degrees(np.linalg.norm(rvec_from_rotation(Ra @ Rb.T))))


#: The ``calibrate`` stage's settings by default: ``facegeo calibrate``'s defaults, so that its
#: run into the scan's ``out/calibrate`` and ``facegeo reconstruct``'s stage compute one key.
CALIBRATE_DEFAULTS = {"model": "auto", "legacy": None, "loss": "linear", "reference": None,
                      "cross_validation": True}


def run_calibrate(scan_dir, out_dir=None, *, model: str = "auto", legacy: bool | None = None,
                  loss: str = "linear", reference: str | None = None,
                  cross_validation: bool = True, progress=None) -> dict:
    """Calibrate a scan's cameras and rig from its ``calib/`` board views (``facegeo
    calibrate``): :func:`calibrate_products` into ``out_dir``, plus ``out_dir/metrics.json``
    (``{"calibrate": metrics}``).

    Parameters
    ----------
    scan_dir : path-like or Scan
        A scan directory (:func:`facegeo.capture.scan.load_scan`) or a loaded scan.
    out_dir : path-like, optional
        Where to write the products. Default ``<scan>/out/calibrate``: the ``calibrate`` stage
        of the stage cache, with these settings recorded as the user's (:func:`_run_as_stage`:
        ``facegeo reconstruct`` / ``mesh`` reuse it; a current stage is not redone), written
        into a staging folder swapped in when complete (a failed run leaves the previous
        calibration as it was; the same when that folder is given by name); another folder
        you give is written into, and removed again when this run created it and failed
        before writing anything into it.
    model, legacy, loss, reference, cross_validation, progress
        See :func:`calibrate_products`.

    Returns
    -------
    dict
        The metrics of :func:`calibrate_products`.
    """
    scan = _scan(scan_dir)
    _check_request(scan, reference)  # before any folder is made
    kw = dict(model=model, legacy=legacy, loss=loss, reference=reference,
              cross_validation=cross_validation, progress=progress)
    own = scan.root / "out" / "calibrate"
    if out_dir is None or Path(out_dir).resolve() == own.resolve():
        # the scan's own out/calibrate: the calibrate stage of the cache (given by name too:
        # written directly, a previous stage manifest would go on describing other products)
        return _run_as_stage(scan, kw)
    out = Path(out_dir)  # a folder of the user's: written into; removed again if created empty
    created = not out.exists()
    try:
        metrics, _ = calibrate_products(scan, out, **kw)
    except BaseException:
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise
    atomic_write_text(out / "metrics.json", json.dumps({"calibrate": metrics}, indent=1) + "\n")
    return metrics


#: The command named in the stage manifest of a ``run_calibrate`` into ``out/calibrate``.
COMMAND = "facegeo calibrate"


def calibrate_inputs(scan) -> list[Path]:
    """The scan files the ``calibrate`` stage reads, in the stage key's order: the manifest,
    the rig file, a board file and every camera's ``[calib]`` files (no ground truth nor
    ``[reference]``: the errors against them are the evaluation's,
    :mod:`facegeo.evaluate.intrinsics`) — the inputs of ``facegeo reconstruct``'s
    ``calibrate`` stage, so that a ``facegeo calibrate`` run and the pipeline compute one key
    (``tests/test_calib_products.py`` checks that they agree)."""
    files = [scan.manifest_path, scan.root / scan.manifest["scan"]["rig"]]
    board = scan.manifest.get("calib", {}).get("board")
    if isinstance(board, str) and (scan.root / board).is_file():  # a board file, not a table
        files.append(scan.root / board)
    for cam in scan.camera_names:
        files += [p for _, p in scan.expected_files("calib", cam)]
        if "projector" in scan.manifest.get("calib", {}):
            files += [p for _, p in scan.expected_files("calib.projector", cam)]
    return files


def _run_as_stage(scan, kw: dict) -> dict:
    """``run_calibrate`` into the scan's ``out/calibrate``: the ``calibrate`` stage of the stage
    cache (:class:`facegeo.pipeline.cache.Pipeline`; its key made of the same inputs as
    ``facegeo reconstruct``'s stage), with this command's settings recorded as the user's
    (``settings_by``): ``facegeo reconstruct`` and ``facegeo mesh`` reuse the products, or rerun
    the stage with these settings, and never replace them with a calibration made otherwise.
    Products are written into a staging folder swapped in when complete (a failed run leaves
    the previous calibration as it was); when they are current (same settings, inputs and code)
    nothing is redone and their metrics are returned."""
    from facegeo.pipeline.cache import Pipeline, StageSpec

    progress = kw.pop("progress")
    settings = {"model": kw["model"], "legacy": None if kw["legacy"] is None
                else bool(kw["legacy"]), "loss": kw["loss"], "reference": kw["reference"],
                "cross_validation": bool(kw["cross_validation"])}

    def run(ctx) -> dict:
        metrics, _ = calibrate_products(scan, ctx.out_dir, progress=progress, **ctx.settings)
        atomic_write_text(ctx.out_dir / "metrics.json",
                          json.dumps({"calibrate": metrics}, indent=1) + "\n")
        return metrics

    spec = StageSpec("calibrate", run, inputs=lambda d: calibrate_inputs(scan),
                     settings=settings)
    [result] = Pipeline([spec]).run(scan.root, settings={"calibrate": settings},
                                    settings_by=COMMAND)
    if not result.ran:
        log.info("calibrate: %s is current (same settings, inputs and code): reused",
                 result.out_dir)
    return result.metrics


def _board_reading(board, legacy: bool | None) -> tuple[bool | None, dict]:
    """The ChArUco pattern to read ``board`` with, and ``metrics["board"]``: ``kind``,
    ``legacy`` (None while undecided: the first camera's views decide) and ``legacy_from``
    (the setting, the board description, an odd row count, or — filled in once read —
    detection)."""
    from facegeo.geometry.calibration import charuco_reading

    kind = getattr(type(board), "board_kind", None)
    if kind != "charuco":
        return False, {"kind": kind}
    use = charuco_reading(board, legacy)
    why = ("the legacy setting (--legacy-board)" if legacy is not None else
           "the board description" if board.legacy is not None else
           "an odd row count: both patterns are the same board" if use is not None else
           "to be detected")
    return use, {"kind": kind, "legacy": use, "legacy_from": why}


def _check_request(scan, reference) -> None:
    """What a calibration needs from the scan, checked before any board is detected (seconds
    to minutes): board views, and ``reference`` naming one of its cameras (or its projector
    when the scan has projector board views)."""
    if not scan.has("calib"):
        raise InputError(f"{scan.root}: the scan has no [calib] section (no board views)")
    if reference is not None:
        names = list(scan.camera_names)
        if scan.rig.projector is not None and scan.has("calib.projector"):
            names.append(scan.rig.projector.name)
        proj = scan.rig.projector
        if reference not in names and proj is not None and reference == proj.name:
            raise InputError(f"reference: the projector {fmt_value(reference)} can hold the "
                             "rig's frame only when it is calibrated, from [calib.projector] "
                             f"board views, which the scan has not; give a camera: "
                             f"{', '.join(names)}")
        if reference not in names:
            raise InputError(f"reference: no camera {fmt_value(reference)}; cameras: "
                             f"{', '.join(names)}")


def _linearizer(scan, group: str):
    """The ``group``'s stored values → linear light, for the chessboard corners' sub-pixel
    refinement (:func:`facegeo.geometry.calibration.detect_boards` decides per camera whether
    to refine there); None for a linear response (the two are one)."""
    resp = scan.response(group)
    return None if resp.kind == "linear" else resp.linearize


def _scan(scan):
    from facegeo.capture.scan import Scan, load_scan

    return scan if isinstance(scan, Scan) else load_scan(scan)


def _json_safe(obj):
    """Non-finite floats → None (metrics go through ``json.dumps(allow_nan=False)``)."""
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def calibrate_products(scan, dest, *, model: str = "auto", legacy: bool | None = None,
                       loss: str = "linear", reference: str | None = None,
                       cross_validation: bool = True, progress=None) -> tuple[dict, dict]:
    """Write the ``calibrate`` products of ``scan`` into ``dest``; return ``(metrics, settings)``.

    The stage form of the calibration (the shape of
    :func:`facegeo.pipeline.project.project_products`): products ``rig.json`` (the calibrated
    rig, the scan's world frame), ``<camera>.yml``, ``residuals_<camera>.png``,
    ``detections.json`` and, with a calibrated projector, its YAML and plot. The metrics are
    returned (the stage cache records them in ``out/metrics.json``), not written here.

    Parameters
    ----------
    scan : path-like or Scan
        A scan directory or a loaded scan with a ``[calib]`` section.
    dest : path-like
        The folder to write into (created).
    model : {"auto", "pinhole", "k1", "k1k2", "opencv4", "opencv5", "rational8"}
        Distortion model of every camera; ``"auto"`` (default) chooses per camera by
        leave-one-view-out cross-validation over its views, refusing degenerate lenses
        (:func:`facegeo.geometry.calibration.select_model`; the choice, every candidate's
        held-out score and why each other one was not taken go to the metrics). The projector
        goes through the same selection with ``"auto"``; with a named model it keeps its rig
        file's (:data:`PROJECTOR_MODEL` for an uncalibrated entry).
    legacy : bool or None
        A ChArUco board's pattern: OpenCV's legacy one (boards made by OpenCV < 4.6,
        ``setLegacyPattern``) or not. None (default): the board description's ``legacy``
        key; where it declares none and the two patterns differ (an even row count), the first
        camera's views are read both ways and the reading with more corners is used for every
        camera and the projector (:func:`facegeo.geometry.calibration.detect_boards`;
        ``metrics["board"]`` says which and why).
    loss : str
        Robust loss of the solves (``"linear"``, ``"soft_l1"``, ``"huber"``, ``"cauchy"``).
    reference : str, optional
        The camera the bundle adjustment holds fixed (default: the rig's first camera).
    cross_validation : bool
        Run the two-halves check per camera (needs ≥ 6 usable views).
    progress : callable(str), optional
        Called with a short message per step (not a setting); warnings are logged, not sent
        here.

    Returns
    -------
    metrics : dict
        ``{"cameras": {name: {model, [model_selection: {reason, best, folds, scores},]
        [intrinsics: "nominal", warning (a camera posed only),] reprojection_rms_px,
        views_used, views_detected, rejected
        (why each dropped view was dropped, named ``"view 3 (FILE)"``), per_view_rms_px (view
        index → RMS at the camera's own solution; dropped views re-posed), corner_refinement
        ("encoded" or "linear": a plain chessboard's; None for other boards and corner lists),
        cross_validation_px, cross_validation_predicted_px, projection_uncertainty_rms_px
        (where the views have corners), projection_uncertainty_image_rms_px (whole image),
        std_px: {fx, fy, cx, cy}, std_formal_px, sigma_method, sigma_inflation,
        [leave_one_out_held_out_rms_px, leave_one_out_projection_rms_px,
        leave_one_out_predicted_rms_px,] cross_validation_method (:func:`~facegeo.pipeline._calibrate_products.solve_metrics`)
        }}, "projector": {calibrated: true,
        views_detected, corners, skipped (one line per view and camera not used, naming the
        file and why), decoded (the codes: "gray", "gray+phase(x)" ...), views_used, model
        (chosen as a camera's), model_fallback, the statistics of a camera's solve
        (:func:`~facegeo.pipeline._calibrate_products.solve_metrics`: σ, model_selection, projection uncertainty, cross-validation),
        start ("nominal" or "uncalibrated": the rig.json entry it started
        from), reprojection_rms_px, separate_rms_px, separate_intrinsics ({fx, fy, cx,
        cy} of the separate solve, before the rig's adjustment), joint_intrinsics (the joint
        solve's), solve ("joint" or "separate": the one in rig.json), solve_reason,
        solve_held_out_rms_px ({joint, separate}: leave-one-projector-pose-out RMS, px; None
        unscored), solve_held_out_poses, solve_gain_px2 / solve_gain_se_px2 (the separate
        solve's held-out gain per pose and its standard error)} or {calibrated: false, reason, rig_json
        ("nominal" or "uncalibrated": what the calibrated rig.json holds), summary (one line)[,
        error (the failed attempt's)]} or None (no projector), "opencv_stereo": {reference,
        files: {camera: file name}[, skipped: {camera: why}]} (two or more cameras),
        reprojection_rms_px_max, "seconds"}`` (non-finite numbers as None). View k of every
        camera is taken to be the same board pose (the scan format's ``calib`` views are
        simultaneous). The stage reads no reference: the errors against the generator's rig
        or a real scan's ``[reference]`` intrinsics are
        :func:`facegeo.evaluate.intrinsics.evaluate_calibration`'s (``facegeo calibrate``
        prints them beside these, :func:`~facegeo.evaluate.intrinsics.with_calibration_errors`).
    settings : dict
        The settings used (JSON-serialisable; the stage cache keys on them).

    Raises
    ------
    InputError, ScanFormatError
        No calibration views in the scan; a camera without a usable view, or (single-camera
        scan) with fewer than :data:`MIN_VIEWS_ALONE` (the message lists every skipped image
        and why); no camera with :data:`MIN_VIEWS_ALONE` views.
    """
    from facegeo.capture.imageio import read_image
    from facegeo.geometry.calibration import (
        BoardDetection, calibrate_camera, calibrate_rig, cross_validate, detect_boards,
        detection_report, model_of_dist, usable_detections,
    )
    from facegeo.geometry.camera import Camera
    from facegeo.geometry.rig import Rig

    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    scan = _scan(scan)
    settings = {"model": model, "legacy": None if legacy is None else bool(legacy),
                "loss": loss, "reference": reference, "cross_validation": bool(cross_validation)}
    _check_request(scan, reference)
    out = Path(dest)
    out.mkdir(parents=True, exist_ok=True)
    board = scan.board
    nominal = scan.rig
    corner_lists = scan.manifest["calib"].get("corners") is not None
    metrics: dict = {"cameras": {}, "model": model}
    legacy, metrics["board"] = _board_reading(board, legacy)
    # the projector's patterns, checked before minutes of camera work (not fatal: the
    # projector is then reported not calibrated, with this error)
    proj_error = None
    if nominal.projector is not None and scan.has("calib.projector"):
        try:
            projector_spec(scan)
        except InputError as exc:
            proj_error = str(exc)
            pj = nominal.projector
            if reference is not None and reference == pj.name:
                raise InputError(f"reference: the projector {pj.name!r} cannot hold the rig's "
                                 f"frame: it cannot be calibrated ({proj_error}); give a "
                                 "camera as --reference") from exc
    report, obs, calibs, cam_dets = {}, {}, {}, {}
    for name in scan.camera_names:
        cam0 = nominal.camera(name)
        if corner_lists:  # published detections: straight to the solver (scan format v2)
            say(f"corner lists {name}")
            views = sorted(scan.calib_corners(name))
            dets = [BoardDetection(f"view {v}", cam0.size, True, "", cv.ids,
                                   cv.object_points, cv.image_points)
                    for v, cv in sorted(scan.calib_corners(name).items())]
        else:
            say(f"detect {name}")
            paths = scan.calib_view_paths(name)
            views = scan.calib_views(name)
            # named by view index and file: the base name alone need not be unique
            dets = detect_boards([read_image(p) for p in paths], board,
                                 names=[view_label(scan, v, p) for v, p in zip(views, paths)],
                                 legacy=legacy, linearize=_linearizer(scan, "calib"))
            cam_dets[name] = dict(zip(views, dets))
            if legacy is None and any(d.found for d in dets):  # read both ways: now fixed
                legacy = next(d.legacy for d in dets if d.found)
                metrics["board"].update(legacy=legacy, legacy_from=(
                    f"detected: camera {name}'s views read both ways, "
                    f"{'the legacy' if legacy else 'the new'} pattern found more corners"))
        report[name] = detection_report(dets)
        # the bundle adjustment ties a board pose across cameras by view index, not file name
        view_of = {id(d): v for d, v in zip(dets, views)}
        view_key = {i: f"v{v}" for i, v in view_of.items()}
        # in a rig, a camera with 1-2 views is posed with its nominal intrinsics (below)
        rig_scan = len(scan.camera_names) > 1
        found = usable_detections(
            dets, min_views=1 if rig_scan else MIN_VIEWS_ALONE,
            what=f"camera {name}" + (f" ({MIN_VIEWS_ALONE} views calibrate it; 1-2 pose it with "
                                     "its nominal intrinsics)" if rig_scan else ""))
        if dets and dets[0].image_size != cam0.size:
            raise InputError(f"camera {name}: views are {dets[0].image_size} px but rig.json says "
                             f"{cam0.size}")
        if len(found) < MIN_VIEWS_ALONE:
            why = (f"camera {name}: {len(found)} usable board view(s), fewer than "
                   f"{MIN_VIEWS_ALONE} to calibrate it alone; its intrinsics are the nominal "
                   "rig.json's and only its pose is solved, jointly with the rig")
            # logged only, not said as a step too: `facegeo calibrate` shows both on stderr
            log.warning(why)
            obs[name] = {view_key[id(d)]: (d.p_board, d.q) for d in found}
            metrics["cameras"][name] = {
                "model": "nominal", "intrinsics": "nominal", "warning": why,
                "views_detected": len(found), "views_used": len(found), "rejected": [],
                "cross_validation_px": None}
            continue
        say(f"calibrate {name}")
        c = calibrate_camera([d.p_board for d in found], [d.q for d in found], cam0.size,
                             model=model, loss=loss, name=name,
                             auto_fallback=model_of_dist(cam0.dist))
        calibs[name] = c
        if c.model_selection is not None:
            log.info("camera %s: distortion model %s", name, c.model_selection["reason"])
        obs[name] = {view_key[id(d)]: (d.p_board, d.q) for d, u in zip(found, c.views_used)
                     if u}
        m = {"model": c.model, "views_detected": len(found), "views_used": c.n_views_used,
             "corner_refinement": found[0].refinement,
             "rejected": view_rejections(c.rejected, [d.name for d in found]),
             "camera_rms_px": c.rms_px,
             "per_view_rms_px": {str(view_of[id(d)]): float(r)
                                 for d, r in zip(found, c.per_view_rms_px)}}
        if cross_validation:
            say(f"cross-validate {name}")
        m.update(solve_metrics(c, [d.p_board for d in found], [d.q for d in found],
                                loss=loss, cross_validation=cross_validation))
        metrics["cameras"][name] = m
    proj_obs, proj_metrics = {}, None
    if proj_error is not None:
        proj_metrics = {"error": proj_error}
    elif nominal.projector is not None and scan.has("calib.projector"):
        say("projector corners")
        try:
            proj_obs, cam_extra, proj_metrics = _projector_observations(
                scan, board, legacy, cam_dets,
                {n: (c.camera, c.rms_px) for n, c in calibs.items()})
            for n, o in cam_extra.items():  # a [calib] view's pose: the camera path's own
                for k, val in o.items():
                    obs.setdefault(n, {}).setdefault(k, val)
        except InputError as exc:
            proj_metrics = {"error": str(exc)}
    if not calibs:
        raise InputError(
            f"{scan.root}: no camera has the {MIN_VIEWS_ALONE} usable board views needed to "
            "calibrate it alone (" + "; ".join(m["warning"] for m in metrics["cameras"].values())
            + ")")
    init = {n: c.camera for n, c in calibs.items()}
    init.update({n: nominal.camera(n) for n in obs if n not in calibs})  # posed only
    proj_name = None
    if proj_obs:
        pj = nominal.projector
        # an uncalibrated projector (resolution only) starts from no intrinsics: the separate
        # solve's Zhang start needs none, its model is PROJECTOR_MODEL
        nominal_k = isinstance(pj, Camera)
        pmodel = model_of_dist(pj.dist) if nominal_k else PROJECTOR_MODEL
        pP, pQ = [p for p, _ in proj_obs.values()], [q for _, q in proj_obs.values()]
        try:
            # the cameras' selection (model="auto"), the rig file's model its fallback; a
            # model the user forces on the cameras is not forced on the projector
            pc = calibrate_camera(pP, pQ, (pj.width, pj.height),
                                  model="auto" if model == "auto" else pmodel,
                                  auto_fallback=pmodel, name=pj.name, loss=loss,
                                  reject_views=False)
            proj_name = pj.name
            init[proj_name] = pc.camera
            obs[proj_name] = proj_obs
            proj_models = {proj_name: pc.model}
            if cross_validation:
                say("cross-validate the projector")
            proj_metrics.update({"views_used": pc.n_views_used, "separate_rms_px": pc.rms_px,
                                 "separate_intrinsics": {k: float(getattr(pc.camera, k))
                                                         for k in ("fx", "fy", "cx", "cy")},
                                 "model": pc.model, "model_fallback": pmodel,
                                 "start": "nominal" if nominal_k else "uncalibrated",
                                 **solve_metrics(pc, pP, pQ, loss=loss,
                                                  cross_validation=cross_validation)})
            if pc.model_selection is not None:
                log.info("projector %s: distortion model %s", proj_name,
                         pc.model_selection["reason"])
        except InputError as exc:
            proj_metrics["error"] = str(exc)
    say("bundle-adjust the rig")
    models = {n: c.model for n, c in calibs.items()}
    if proj_name is not None:  # "k1" keeps k2, p1, p2 at 0 in the joint solve too
        models.update(proj_models)
    refine = set(calibs) | ({proj_name} if proj_name else set())
    if reference is None and scan.camera_names[0] not in calibs:
        reference = next(iter(calibs))  # the rig frame: a camera calibrated from its own views
    pj = nominal.projector
    if reference is not None and pj is not None and reference == pj.name and proj_name is None:
        why = (proj_metrics or {}).get("error", "the scan has no [calib.projector] board views")
        raise InputError(f"reference: the projector {pj.name!r} cannot hold the rig's frame: "
                         f"it was not calibrated ({why}); give a camera as --reference")
    if proj_name is not None:  # joint or separate projector: held-out projector corners
        say("choose the projector's solve")
        rig_cal, choice = _projector_rig(obs, init, proj_name, proj_models[proj_name],
                                         reference=reference, loss=loss, models=models,
                                         refine=refine)
        proj_metrics.update(choice)
        log.info("projector %s: %s", proj_name, choice["solve_reason"])
    else:
        rig_cal = calibrate_rig(obs, init, reference=reference, loss=loss, models=models,
                                refine_intrinsics=refine)
    T_rig_world, T_world_nom, metrics["world"] = _world_frame(scan, rig_cal, obs, proj_name,
                                                              nominal)
    cams = [c.replace(T_cam_world=c.T_cam_world @ T_rig_world) for c in rig_cal.cameras
            if c.name != proj_name]
    projector = nominal.projector
    if proj_name is not None:
        pr = rig_cal.camera(proj_name)
        projector = pr.replace(T_cam_world=pr.T_cam_world @ T_rig_world)
    elif projector is not None:
        proj_metrics = _projector_not_calibrated(projector, proj_metrics)
        # marked, so a caller that shows the summary itself (facegeo calibrate) can drop it
        log.warning("%s", proj_metrics["summary"], extra={SUMMARY_RECORD: "projector"})
        if isinstance(projector, Camera):  # nominal numbers: where the nominal rig puts it
            projector = projector.replace(
                T_cam_world=projector.T_cam_world @ T_world_nom.inverse())
        # else a Projector (resolution only) has no pose to move: written unchanged
    rig = Rig(cams, projector, _lights_to_world(nominal.lights, T_world_nom))
    rig.save(out / "rig.json")
    if len(cams) > 1:
        metrics["opencv_stereo"] = write_stereo_pairs(out, cams, rig_cal.reference)
    for c in rig_cal.cameras:
        if c.name == proj_name:
            continue
        m = metrics["cameras"][c.name]
        m["reprojection_rms_px"] = rig_cal.rms_px[c.name]
        r, q = rig_cal.residuals[c.name]
        per_view = (calibs[c.name].per_view_rms_px if c.name in calibs
                    else np.full(0, np.nan))
        write_yaml(out / f"{c.name}.yml", c, rig_cal.rms_px[c.name],
                    per_view[np.isfinite(per_view)], m["model"])
        residual_plot(out / f"residuals_{c.name}.png", c.size, r, q, c.name)
    metrics["rig_reference"] = rig_cal.reference
    if proj_name is not None:
        pr = rig_cal.camera(proj_name)
        proj_metrics["calibrated"] = True
        proj_metrics["reprojection_rms_px"] = rig_cal.rms_px[proj_name]
        r, q = rig_cal.residuals[proj_name]
        residual_plot(out / f"residuals_{proj_name}.png", pr.size, r, q, proj_name)
        write_yaml(out / f"{proj_name}.yml", pr, rig_cal.rms_px[proj_name], [],
                    proj_metrics["model"])
    metrics["projector"] = proj_metrics
    # the headline over the cameras (the worst one), for the summary table and the report;
    # the errors against references are the evaluation's (facegeo.evaluate.intrinsics)
    vals = [c["reprojection_rms_px"] for c in metrics["cameras"].values()
            if isinstance(c.get("reprojection_rms_px"), float)]
    if vals:
        metrics["reprojection_rms_px_max"] = float(max(vals))
    if proj_metrics and isinstance(proj_metrics.get("reprojection_rms_px"), float):
        metrics["projector_reprojection_rms_px"] = proj_metrics["reprojection_rms_px"]
    metrics["seconds"] = time.perf_counter() - t0
    atomic_write_text(out / "detections.json", json.dumps(report, indent=1) + "\n")
    return _json_safe(metrics), settings
