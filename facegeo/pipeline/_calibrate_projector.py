"""The calibrate stage's projector views: board corners in projector pixels, any board kind.

Each ``[calib.projector]`` view is one board pose seen by the cameras under every pattern of
the group (its own ``frames`` / ``patterns``, or ``[structured_light]``'s when it declares
none: :meth:`facegeo.capture.scan.Scan.pattern_spec`). Per view and camera:

1. **the board** is found in the view's ``white`` frame — the board under the projector's full
   light, which is all a plain chessboard or circle grid in a dark room shows — with the
   detector of the scan's board kind (:func:`facegeo.geometry._calib_detect.detect_board`;
   a plain chessboard's corners refined in linear light where the camera's own views chose
   that, :func:`facegeo.geometry._calib_detect.detect_boards`).
   Without a ``white`` frame the pixelwise maximum over the view's frames stands in for it
   (each pixel is lit in one frame of a pattern / inverse pair). Where the board is not found
   there and the camera's ``[calib]`` views include a file of this projector view (a
   ``[calib]`` template pointing at the projector captures: the same pose), that view's
   detection is used;
2. **the patterns** are decoded (:func:`facegeo.geometry.structured_light.decode_stream`:
   Gray code and, where the spec has it, phase shift, which makes the codes sub-pixel);
3. **each corner's projector position** is the local homography of the decoded pixels around
   it applied to the corner (:func:`facegeo.geometry._calib_projector.projector_corners`,
   Moreno & Taubin 2012).

A corner's projector position is averaged over the cameras that decoded it. A view is used
when at least :data:`MIN_PROJECTOR_CORNERS` of its corners decoded; the projector needs
:data:`MIN_PROJECTOR_VIEWS` such views. A view a camera could not use is skipped with its
reason (view, camera and file named), never silently.

The rig's bundle adjustment then refines the projector jointly with the cameras or keeps its
separate solve, whichever predicts held-out projector corners better
(:func:`projector_rig`).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from facegeo.errors import InputError

log = logging.getLogger(__name__)

#: Attribute of a log record that repeats a line of the metrics (``"projector"``: the warning
#: of ``metrics["projector"]["summary"]``; ``"projector_skipped"``: the skipped views), for a
#: caller that prints that line itself (``facegeo calibrate``).
SUMMARY_RECORD = "facegeo_summary"

__all__ = ["CHOICE_MIN_VIEWS", "MIN_PROJECTOR_CORNERS", "MIN_PROJECTOR_VIEWS", "POSE_CHECK_FACTOR",
           "POSE_CHECK_FLOOR_PX", "SOLVES", "projector_rig", "projector_spec",
           "projector_observations", "view_label", "view_rejections"]

#: Fewest decoded corners a projector view needs (over its cameras).
MIN_PROJECTOR_CORNERS = 6
#: Fewest usable projector views the projector is calibrated from.
MIN_PROJECTOR_VIEWS = 3


def projector_spec(scan):
    """The pattern spec of ``[calib.projector]``, checked against its frames before any image
    is read.

    Returns
    -------
    PatternSpec

    Raises
    ------
    InputError
        The group declares no patterns and the scan has no ``[structured_light.patterns]`` to
        take them from, or its frames lack some the spec's decoding needs (named).
    """
    from facegeo.geometry.structured_light import pattern_names

    spec = scan.pattern_spec("calib.projector")
    if spec is None:
        raise InputError(
            "projector: [calib.projector] declares no patterns (calib.projector.patterns) and "
            "the scan has no [structured_light.patterns] to take them from; give "
            "calib.projector.frames and calib.projector.patterns (docs/scan-format.md)")
    have = set(scan.projector_frames)
    lacking = [n for n in pattern_names(spec) if n not in have]
    if lacking:
        raise InputError(
            f"projector: calib.projector frames lack {', '.join(lacking[:6])}"
            + (f" and {len(lacking) - 6} more" if len(lacking) > 6 else "")
            + " of the pattern spec; the projector views cannot be decoded")
    return spec


def _rel(scan, path: Path) -> str:
    try:
        return Path(path).relative_to(scan.root).as_posix()
    except ValueError:
        return str(path)


def view_label(scan, view: int, path) -> str:
    """A board view's label in reports and messages: ``"view 3 (calib/cam/graycode_40.png)"``
    (its index and its file relative to the scan; the base name alone need not be unique)."""
    return f"view {int(view)} ({_rel(scan, path)})"


def _calib_files(scan, camera: str) -> dict:
    """``{resolved path: view}`` of ``camera``'s ``[calib]`` image files (empty without)."""
    if not scan.has("calib") or not scan.calib_images:
        return {}
    return {Path(p).resolve(): int(w)
            for w, p in zip(scan.calib_views(camera), scan.calib_view_paths(camera))}


def _same_pose(calib_files: dict, paths: dict) -> int | None:
    """The ``[calib]`` view whose file is one of this projector view's frames (a ``[calib]``
    template pointing at the projector captures), else None."""
    for p in paths.values():
        w = calib_files.get(Path(p).resolve())
        if w is not None:
            return w
    return None


def _lit_image(raw: dict):
    """The board under full projector light: the ``white`` frame, else the pixelwise maximum
    over the frames."""
    if "white" in raw:
        return raw["white"], "white"
    it = iter(raw.values())
    lit = np.array(next(it), copy=True)
    for a in it:
        np.maximum(lit, a, out=lit)
    return lit, "max over frames"


#: A projector view's board, as a camera found it, is not used when its pose fits the camera's
#: own calibration worse than this many times the camera's reprojection RMS ...
POSE_CHECK_FACTOR = 3.0
#: ... and than this, pixels (the camera solve's outlier rule, ``calibrate_camera``).
POSE_CHECK_FLOOR_PX = 0.5


def _pose_rms(camera, p_board, q) -> float:
    """RMS (pixels) of the board's corners about their best pose in ``camera``."""
    import cv2

    ok, rv, tv = cv2.solvePnP(p_board, q, camera.K, camera.dist)
    if not ok:
        return float("inf")
    ok, rv, tv = cv2.solvePnP(p_board, q, camera.K, camera.dist, rv, tv, True,
                              cv2.SOLVEPNP_ITERATIVE)
    pr, _ = cv2.projectPoints(p_board, rv, tv, camera.K, camera.dist)
    return float(np.sqrt(np.mean(np.sum((pr.reshape(-1, 2) - q) ** 2, axis=1))))


def projector_observations(scan, board, legacy: bool | None = None, camera_detections=None,
                           cameras=None):
    """Board corners in projector pixels for every projector view, and the cameras' corners
    of those views.

    Parameters
    ----------
    scan : Scan
        With ``[calib.projector]``.
    board : CharucoBoard, ChessboardSpec or CircleGridSpec
        ``scan.board``.
    legacy : bool or None
        The ChArUco pattern the cameras' views were read with (:func:`~facegeo.geometry.
        calibration.detect_boards`); None: the board's own declaration.
    camera_detections : dict, optional
        ``{camera: {calib view: BoardDetection}}`` of the camera path, for views whose file is
        also a frame of a projector view (same pose).
    cameras : dict, optional
        ``{camera: (Camera, reprojection RMS px)}``, the cameras as calibrated from their own
        views: a board whose pose fits one worse than ``max(POSE_CHECK_FACTOR · RMS,
        POSE_CHECK_FLOOR_PX)`` is a detector error, and that camera's view is skipped.

    Returns
    -------
    proj_obs : dict
        ``{pose key: ((N, 3) float64 board points, metres; (N, 2) float64 projector pixels)}``;
        the key is ``"p<view>"``, or ``"v<w>"`` when projector view ``view`` is ``[calib]``
        view ``w`` of the cameras (the same pose: the rig's bundle adjustment ties them).
    cam_obs : dict
        ``{camera: {pose key: (board points, camera pixels)}}``: the cameras' own corners of
        these poses (for a ``"v<w>"`` pose the caller keeps the camera path's where it has
        them).
    metrics : dict
        ``views_detected`` (usable views), ``corners`` (their total), ``skipped`` (one line per
        view and camera not used: ``"projector view 3, camera cam_left (FILE): reason"``),
        ``decoded`` (the codes decoded: ``"gray"``, ``"gray+phase(x)"``, ...).

    Raises
    ------
    InputError
        No pattern spec or frames it needs (:func:`projector_spec`), or fewer than
        :data:`MIN_PROJECTOR_VIEWS` usable views (every skipped view listed with its reason).
    """
    from facegeo.capture.imageio import read_image
    from facegeo.geometry._calib_detect import detect_board
    from facegeo.geometry._calib_projector import projector_corners
    from facegeo.geometry.structured_light import decode_stream

    spec = projector_spec(scan)
    resp = scan.response("calib.projector")
    n_views = int(scan.manifest["calib"]["projector"]["views"])
    has_view = {n: {v for v, _ in scan.camera_frames("calib.projector", n)}
                for n in scan.camera_names}
    camera_detections = camera_detections or {}
    calib_files = {n: _calib_files(scan, n) for n in scan.camera_names}
    lin_refine = {n: any(d.refinement == "linear" for d in camera_detections.get(n, {}).values())
                  for n in scan.camera_names}
    proj_obs, cam_obs = {}, {n: {} for n in scan.camera_names}
    skipped, n_corners = [], 0
    for v in range(n_views):
        acc: dict[int, list] = {}
        p_of: dict[int, np.ndarray] = {}
        poses, view_cams = set(), {}
        for name in scan.camera_names:
            if v not in has_view[name]:
                continue  # declared missing (calib.projector.cameras)
            paths = scan.projector_view_paths(name, v)
            raw = {k: read_image(p) for k, p in paths.items()}
            lit, what = _lit_image(raw)
            src = paths["white"] if "white" in paths else paths[next(iter(paths))]
            label = (f"projector view {v}, camera {name} ("
                     + (_rel(scan, src) if what == "white" else
                        f"{what}, {_rel(scan, Path(src).parent)}") + ")")
            # the refinement the camera's own views chose (detect_boards), in this group's
            # response: a plain chessboard's corners in linear light or on the stored values
            det = detect_board(lit, board, name=label, legacy=legacy,
                               linearize=resp.linearize if lin_refine.get(name) else None)
            w = _same_pose(calib_files[name], paths)
            poses.add(w)
            if not det.found and w is not None:
                own = camera_detections.get(name, {}).get(w)
                if own is not None and own.found:
                    log.info("%s: %s; using the board of its [calib] view %d", label,
                             det.reason, w)
                    det = own
            if not det.found:
                skipped.append(f"{label}: {det.reason}")
                continue
            if name in (cameras or {}):
                cam, rms = cameras[name]
                lim = max(POSE_CHECK_FACTOR * rms, POSE_CHECK_FLOOR_PX)
                r = _pose_rms(cam, det.p_board, det.q)
                if not r <= lim:
                    skipped.append(f"{label}: the board's pose fits camera {name}'s calibration "
                                   f"to {r:.3g} px RMS (limit {lim:.3g} px): a detector error")
                    continue
            lin = {k: resp.linearize(a) for k, a in raw.items()}
            dec = decode_stream(lin, spec)
            q_map = np.stack([dec.x, dec.y], -1).astype(np.float64)
            qp, ok, _ = projector_corners(det.q, q_map, dec.valid)
            if ok.sum() < MIN_PROJECTOR_CORNERS:
                skipped.append(f"{label}: only {int(ok.sum())} of {det.n_corners} corners "
                               f"decodable (need {MIN_PROJECTOR_CORNERS}; "
                               f"{100 * dec.valid.mean():.0f} % of the pixels decoded)")
                continue
            view_cams[name] = det
            for i, p, q in zip(det.ids[ok], det.p_board[ok], qp[ok]):
                acc.setdefault(int(i), []).append(q)
                p_of[int(i)] = p
        # the same pose as a [calib] view when every camera says so
        key = f"v{poses.pop()}" if len(poses) == 1 and None not in poses else f"p{v}"
        if len(acc) < MIN_PROJECTOR_CORNERS:
            if view_cams:
                skipped.append(f"projector view {v}: {len(acc)} corners decoded over its "
                               f"cameras (need {MIN_PROJECTOR_CORNERS})")
            continue
        for name, det in view_cams.items():
            cam_obs[name][key] = (det.p_board, det.q)
        ids = np.array(sorted(acc))
        proj_obs[key] = (np.array([p_of[i] for i in ids]),
                         np.array([np.mean(acc[i], axis=0) for i in ids]))
        n_corners += len(ids)
    if skipped:  # marked like the stage's summary: `facegeo calibrate` prints each line itself
        log.warning("projector: skipped %d view image(s): %s", len(skipped), "; ".join(skipped),
                    extra={SUMMARY_RECORD: "projector_skipped"})
    if len(proj_obs) < MIN_PROJECTOR_VIEWS:
        raise InputError(
            f"projector: {len(proj_obs)} of {n_views} projector views have ≥ "
            f"{MIN_PROJECTOR_CORNERS} decodable corners, need {MIN_PROJECTOR_VIEWS}"
            + (f" (skipped — {'; '.join(skipped)})" if skipped else ""))
    decoded = "+".join(spec.codes) + (f"+phase({','.join(spec.phase_axes)})"
                                      if spec.phase_steps and spec.phase_axes else "")
    return proj_obs, cam_obs, {"views_detected": len(proj_obs), "corners": n_corners,
                               "skipped": skipped, "decoded": decoded}


def view_rejections(rejected, names) -> list[str]:
    """``calibrate_camera``'s rejection reasons (``"view i: ..."``, ``i`` the position among
    the views it was given) with each view's own label (``names[i]``: the scan's view index
    and file)."""
    def sub(m):
        i = int(m.group(1))
        return f"{names[i]}:" if 0 <= i < len(names) else m.group(0)

    return [re.sub(r"^view (\d+):", sub, r) for r in rejected]


#: Fewest projector poses for the joint / separate choice (:func:`projector_rig`): each held
#: out in turn leaves the separate solve its :data:`MIN_PROJECTOR_VIEWS`.
CHOICE_MIN_VIEWS = MIN_PROJECTOR_VIEWS + 1

#: The two projector solves :func:`projector_rig` chooses between.
SOLVES = ("joint", "separate")


def _held_out(rig_cal, name: str, key, p, q) -> np.ndarray:
    """Squared residuals (px²) of pose ``key``'s projector corners ``q`` predicted by
    ``rig_cal``: the board where the cameras put it (``T_world_board[key]``: the projector did
    not see it in this solve), through the projector's solved pose and intrinsics."""
    c = rig_cal.camera(name)
    pr, _ = c.project_cam(c.T_cam_world.apply(rig_cal.T_world_board[key].apply(p)))
    return np.sum((pr - q) ** 2, axis=1)


def projector_rig(obs: dict, init: dict, name: str, model: str, *, reference, loss: str,
                  models: dict, refine: set):
    """The rig's bundle adjustment with the projector solved jointly with the cameras or kept
    at its separate solve (its pose only solved), whichever predicts held-out projector corners
    better; no truth read.

    Moreno & Taubin (2012) refine the projector jointly with the camera (their stereo
    calibration after each device's own): its intrinsics then also answer to the board poses
    the cameras measure, which helps when its own views leave focal and distance traded (4
    views on the ``small`` preset) and hurts when the cameras' poses of the board are biased. The score of either solve is a
    **leave-one-projector-pose-out** prediction: for each projector pose ``k`` the projector is
    solved without its corners of ``k`` (separately, ``calibrate_camera`` with ``model``; for
    the joint candidate also refined in the rig), the rig places board ``k`` from the cameras'
    corners, and the projector's corners of ``k`` are predicted through the projector's pose and
    intrinsics — the camera-to-projector correspondence structured light triangulates. The
    separate solve is taken when its held-out mean squared error per pose is lower than the
    joint's by more than the noise — the rule of the model selection
    (:data:`~facegeo.geometry._calib_select.AUTO_GAIN_NOISE` standard errors of the per-pose
    paired differences) — else the joint solve is kept (Moreno & Taubin's, and the stage's
    before). With fewer than :data:`CHOICE_MIN_VIEWS` poses the joint solve is kept unscored.

    Parameters
    ----------
    obs, init : dict
        :func:`~facegeo.geometry.calibration.calibrate_rig`'s observations and initial
        cameras, the projector ``name`` among them (``init[name]``: its separate solve).
    name : str
        The projector.
    model : str
        The projector's distortion model (its separate solve's).
    reference, loss, models
        As :func:`~facegeo.geometry.calibration.calibrate_rig`'s.
    refine : set of str
        The cameras whose intrinsics the bundle adjustment refines (the projector's own entry
        is decided here).

    Returns
    -------
    rig_cal : RigCalibration
        The chosen solve's bundle adjustment.
    choice : dict
        ``solve`` (``"joint"`` or ``"separate"``), ``solve_reason``,
        ``solve_held_out_rms_px`` (``{joint, separate}``, None when not scored),
        ``solve_held_out_poses``, ``solve_gain_px2`` / ``solve_gain_se_px2`` (the separate
        solve's mean held-out gain per pose over the joint one and its standard error; when
        scored) and ``joint_intrinsics`` (``{fx, fy, cx, cy}`` of the joint
        solve).
    """
    from facegeo.geometry._calib_select import AUTO_GAIN_NOISE, AUTO_TIE_PX2
    from facegeo.geometry.calibration import calibrate_camera, calibrate_rig

    proj = obs[name]
    size = init[name].size
    base = set(refine) - {name}
    refines = {"joint": base | {name}, "separate": base}

    def rig(o, i, which):
        return calibrate_rig(o, i, reference=reference, loss=loss, models=models,
                             refine_intrinsics=refines[which])

    full = {"joint": rig(obs, init, "joint")}
    joint_k = full["joint"].camera(name)
    choice = {"joint_intrinsics": {k: float(getattr(joint_k, k)) for k in ("fx", "fy", "cx",
                                                                            "cy")},
              "solve_held_out_rms_px": {s: None for s in SOLVES}, "solve_held_out_poses": 0}
    if len(proj) < CHOICE_MIN_VIEWS:
        choice.update(solve="joint", solve_reason=(
            f"joint: {len(proj)} projector poses, fewer than {CHOICE_MIN_VIEWS} to hold one "
            "out; not scored"))
        return full["joint"], choice
    sq = {s: [] for s in SOLVES}  # per held-out pose: its corners' squared residuals
    for k in proj:
        sub = {kk: v for kk, v in proj.items() if kk != k}
        try:
            pc = calibrate_camera([p for p, _ in sub.values()], [q for _, q in sub.values()],
                                  size, model=model, loss=loss, reject_views=False, name=name)
            o, i = {**obs, name: sub}, {**init, name: pc.camera}
            r = {s: rig(o, i, s) for s in SOLVES}
        except InputError as exc:  # a subset that does not solve: this pose is not scored
            log.info("projector %s: pose %s not held out: %s", name, k, exc)
            continue
        if all(k in r[s].T_world_board for s in SOLVES):  # the cameras saw it (the stage's
            for s in SOLVES:                               # projector poses always are)
                sq[s].append(_held_out(r[s], name, k, *proj[k]))
    n = len(sq["joint"])
    if n < 2:
        choice.update(solve="joint", solve_reason=(
            f"joint: only {n} projector pose(s) could be held out (solved without it, its "
            "board placed by a camera); not scored"))
        return full["joint"], choice
    score = {s: float(np.sqrt(np.mean(np.concatenate(sq[s])))) for s in SOLVES}
    # paired per pose, as the model selection's gain (AUTO_GAIN_NOISE standard errors)
    d = np.array([np.mean(a) - np.mean(b) for a, b in zip(sq["joint"], sq["separate"])])
    gain, se = float(d.mean()), float(d.std(ddof=1) / np.sqrt(n))
    best = "separate" if gain > AUTO_GAIN_NOISE * se + AUTO_TIE_PX2 else "joint"
    choice.update(solve=best, solve_held_out_rms_px=score, solve_held_out_poses=n,
                  solve_gain_px2=gain, solve_gain_se_px2=se, solve_reason=(
                      f"{best}: held-out projector corners {score['joint']:.4g} px RMS joint, "
                      f"{score['separate']:.4g} px separate (leave one of {n} projector poses "
                      f"out, its board placed by the cameras); the separate solve gains "
                      f"{gain:.3g} ± {se:.3g} px² per pose"
                      + ("" if best == "separate" else
                         f", not above the noise ({AUTO_GAIN_NOISE:g} standard error)")))
    if best == "separate":
        full["separate"] = rig(obs, init, "separate")
    return full[best], choice
