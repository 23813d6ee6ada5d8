"""Camera specifications for novel views: a camera, a named camera, or an orbit.

Private module behind :mod:`facegeo.render`.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError
from facegeo.frames import Pose
from facegeo.geometry.camera import Camera

#: ``orbit:<camera>:<degrees>`` (e.g. ``orbit:cam_left:-30``); the angle is checked by
#: :func:`_orbit_degrees`.
_ORBIT = re.compile(r"^orbit:(?P<cam>[^:]+):(?P<deg>[^:]*)$")
#: Largest |angle| of an orbit in a camera spec, degrees: a full turn. A larger angle is a
#: typo (and 1e308 would reach the rotation as garbage).
MAX_ORBIT_DEG = 360.0


def _orbit_degrees(value: Any, spec: Any) -> float:
    """The orbit angle of ``spec`` as a float: finite, |angle| <= :data:`MAX_ORBIT_DEG`."""
    try:
        deg = float(value)
    except (TypeError, ValueError):
        deg = math.nan
    if not (math.isfinite(deg) and abs(deg) <= MAX_ORBIT_DEG):
        raise InputError(f"camera spec {fmt_value(spec)}: expected an orbit angle in degrees "
                         f"with |angle| <= {MAX_ORBIT_DEG:g}, got {fmt_value(value)}")
    return deg


def _rotation_y(angle: float) -> np.ndarray:
    # same convention as facegeo.lighting.envmap.rotation_y (+Z turns toward +X)
    from facegeo.lighting.envmap import rotation_y

    return rotation_y(angle)


def orbit_camera(camera: Camera, degrees: float, *, center=(0.0, 0.0, 0.0),
                 name: str | None = None) -> Camera:
    """``camera`` orbited by ``degrees`` about the vertical (+Y) axis through ``center``.

    The camera keeps its intrinsics and distortion and its pose relative to the rotated world:
    its centre moves to ``R_y(θ) (c − center) + center`` and it turns with it, so a camera
    aimed at ``center`` stays aimed at it. Positive angles follow the right-hand rule about +Y
    (+Z turns toward +X), as :func:`facegeo.lighting.envmap.rotation_y`.

    Parameters
    ----------
    camera : Camera
    degrees : float, degrees
    center : (3,) float, metres, world frame
        A point on the rotation axis (the head centre, the rig's target: the origin).
    name : str, optional
        Default ``"<camera>_orbit<degrees>"``.

    Returns
    -------
    Camera
    """
    deg = float(degrees)
    if not math.isfinite(deg):
        raise InputError(f"degrees: expected a finite angle, got {fmt_value(degrees)}")
    c0 = np.asarray(center, np.float64).reshape(3)
    Ry = _rotation_y(math.radians(deg))
    # T_rot maps the old world to the rotated one: p' = Ry (p - c0) + c0
    T_rot = Pose(Ry, c0 - Ry @ c0)
    T_new = camera.T_cam_world @ T_rot.inverse()
    return camera.replace(name=name or f"{camera.name}_orbit{deg:g}", T_cam_world=T_new)


#: The name of the rig's virtual frontal camera in camera specs (:func:`front_camera`).
FRONT = "front"
#: The novel views of the ``render`` stage and of the fit's default views: the frontal camera
#: orbited by these angles (degrees) — views no source camera saw (on the two-camera presets,
#: 15° and 45° beyond the outermost camera).
NOVEL_ORBITS = (30.0, -30.0, 60.0, -60.0)


def front_camera(cameras: Mapping[str, Camera], *, center=(0.0, 0.0, 0.0)) -> Camera:
    """The rig's frontal camera: the source cameras' mean view of ``center``.

    Its rotation is the chordal mean of the cameras' rotations
    (:func:`facegeo.frames.nearest_rotation` of Σ R_c), it looks through ``center`` from the
    cameras' mean distance to ``center``; intrinsics and distortion are the first camera's. For a rig of cameras at ±15°
    about the head it is the camera at 0°, so orbits of it by ±30° and ±60° are views that
    no source camera saw (15° and 45° beyond the outermost one), where orbits of a source
    camera by 30° can land on the other source camera.

    Parameters
    ----------
    cameras : mapping of str -> Camera — the source cameras (at least one)
    center : (3,) float, metres, world frame — the point the rig looks at (the head centre)

    Returns
    -------
    Camera named ``"front"``
    """
    from facegeo.frames import nearest_rotation

    cams = list(cameras.values())
    if not cams:
        raise InputError("camera spec: 'front' needs at least one source camera")
    c0 = np.asarray(center, np.float64).reshape(3)
    R = nearest_rotation(sum(c.T_cam_world.R for c in cams))
    dist = float(np.mean([np.linalg.norm(c.center_world - c0) for c in cams]))
    eye = c0 - dist * R[2]  # R[2]: the optical axis in the world frame
    return cams[0].replace(name=FRONT, T_cam_world=Pose(R, -R @ eye))


def parse_camera_spec(spec: Any, cameras: Mapping[str, Camera], *,
                      center=(0.0, 0.0, 0.0)) -> Camera:
    """The camera a spec names.

    Parameters
    ----------
    spec : Camera, dict, or str
        A :class:`Camera`; a dict ``{"orbit": degrees, "from": name}`` or a camera dict
        (``Camera.to_dict``); a string ``"orbit:<name>:<degrees>"``, the name of one of
        ``cameras``, or a path to a JSON file holding a camera dict. An orbit's angle is a
        finite number of degrees with |angle| <= :data:`MAX_ORBIT_DEG` (360).
    cameras : mapping of str -> Camera
        The cameras a spec may name (the scan's cameras, the generator's novel ones).
    center : (3,) float, metres
        The orbit axis passes through this point.

    Returns
    -------
    Camera

    Raises
    ------
    InputError
        An unknown camera name, an orbit angle that is not a number or beyond ±360°, a
        ``.json`` spec naming no file (or invalid JSON), any other unrecognised spec.
    """
    def named(name: str) -> Camera:
        if name == FRONT and name not in cameras:
            return front_camera(cameras, center=center)
        if name not in cameras:
            front = "" if FRONT in cameras else f" (and '{FRONT}', the rig's frontal view)"
            raise InputError(f"camera spec: unknown camera {fmt_value(name)}; known cameras are "
                             f"{', '.join(cameras)}{front}")
        return cameras[name]

    if isinstance(spec, Camera):
        return spec
    if isinstance(spec, Mapping):
        if "orbit" in spec:
            if "from" not in spec:
                raise InputError("camera spec: an orbit needs 'from': <camera name>")
            return orbit_camera(named(str(spec["from"])), _orbit_degrees(spec["orbit"], spec),
                                center=center, name=spec.get("name"))
        return Camera.from_dict(spec, where="camera spec")
    if isinstance(spec, str):
        m = _ORBIT.match(spec.strip())
        if m:
            return orbit_camera(named(m["cam"]), _orbit_degrees(m["deg"], spec), center=center)
        if spec in cameras or spec == FRONT:
            return named(spec)
        path = Path(spec)
        if path.suffix.lower() == ".json":
            if not path.is_file():
                raise InputError(f"camera spec: camera JSON file {path} "
                                 f"{'is not a file' if path.exists() else 'does not exist'}")
            try:
                d = json.loads(path.read_text(encoding="utf-8"))
            except ValueError as exc:
                raise InputError(f"camera spec {path}: not valid JSON ({exc})") from exc
            return Camera.from_dict(d, where=str(path))
        if path.suffix.lower() in OPENCV_SUFFIXES:
            return opencv_camera_file(path)
    raise InputError(f"camera spec {fmt_value(spec)}: expected 'orbit:<camera>:<degrees>', a camera "
                     f"name ({', '.join(cameras)}), a camera JSON file, an OpenCV "
                     "FileStorage file (.yml, .yaml, .xml), or a camera dict")


#: Suffixes of a camera spec read as an OpenCV FileStorage file (:func:`opencv_camera_file`).
OPENCV_SUFFIXES = (".yml", ".yaml", ".xml")


def opencv_camera_file(path) -> Camera:
    """A camera from an OpenCV FileStorage file (YAML or XML), named after the file's stem.

    ``camera_matrix``, ``distortion_coefficients``, ``image_width`` / ``image_height`` and the
    world → camera pose ``R`` (3 × 3 or a Rodrigues vector), ``T`` in metres
    (:func:`facegeo.capture.opencv_storage.read_opencv_camera`; a 3DUNDERWORLD ``calib.xml``
    too), or, where the file has no ``R``/``T``, ``rvec``/``tvec`` (``cv2.solvePnP``'s names,
    the same convention ``X_cam = R(rvec) X_world + tvec``). The world is the rig's frame the
    render uses (docs/render.md); a file with no pose at all is refused.
    """
    from facegeo.capture.opencv_storage import read_matrices, read_opencv_camera
    from facegeo.frames import Pose, rotation_from_rvec

    path = Path(path)
    if not path.is_file():
        raise InputError(f"camera spec: OpenCV camera file {path} "
                         f"{'is not a file' if path.exists() else 'does not exist'}")
    cam = read_opencv_camera(path, name=path.stem)
    try:
        rt = read_matrices(path, ["R", "T"])
    except InputError:
        rt = None
    if rt is None:
        try:
            m = read_matrices(path, ["rvec", "tvec"])
        except InputError:
            if "Camera" in _top_keys(path):  # 3DUNDERWORLD: its pose is required and read
                return cam
            raise InputError(f"{path}: no camera pose (R and T, or rvec and tvec: world → "
                             "camera, metres, in the rig's world frame)") from None
        r, t = m["rvec"].ravel(), m["tvec"].ravel()
        if r.size != 3 or t.size != 3:
            raise InputError(f"{path} [rvec, tvec]: expected 3 elements each, got {r.size} and "
                             f"{t.size}")
        cam = cam.replace(T_cam_world=Pose(rotation_from_rvec(r), t))
    return cam


def _top_keys(path: Path) -> list[str]:
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        return list(fs.root().keys())
    finally:
        fs.release()
