"""Camera calibrations in OpenCV FileStorage files (XML or YAML): read, write, rescale.

Calibration tools built on OpenCV save their results with ``cv2.FileStorage``; this module turns
those files into :class:`facegeo.geometry.camera.Camera` objects and writes cameras back so that
OpenCV tools read them. Every file goes through ``cv2.FileStorage`` (XML, YAML, JSON alike).

Key spellings read
------------------

* **One camera, OpenCV's spelling** (the ``calibration`` sample, ``calibrate_camera_charuco``,
  ``facegeo calibrate``, :func:`write_opencv_camera`): ``camera_matrix``,
  ``distortion_coefficients``, ``image_width``, ``image_height``; ``R``, ``T`` (world → camera)
  when present, else the camera sits at the world origin.
* **One camera, 3DUNDERWORLD-SLS** (``calib/output/calib.xml``): a ``Camera`` map with
  ``Matrix``, ``Distortion``, ``Rotation``, ``Translation`` (world → camera, millimetres),
  ``Height``, ``Width``, all required (and ``Calibrated``: 0 is refused).
* **A camera pair, ``stereo_calib``**: ``intrinsics.yml`` with ``M1``, ``D1``, ``M2``, ``D2``
  (or ``cameraMatrix1``, ``distCoeffs1``, … as ``cv2.stereoCalibrate`` names them) and
  ``extrinsics.yml`` with ``R``, ``T`` (camera 1 → camera 2); the image size from
  ``image_width`` / ``image_height`` when a file has them, else given by the caller
  (``stereo_calib`` does not write it).

Conventions (``docs/conventions.md``): ``X_cam = R X_world + T``; pixel centres at integers;
distortion in OpenCV's order. Lengths in a file are in the file's own unit (millimetres for
3DUNDERWORLD, board-square units for ``stereo_calib``'s default): ``units`` is that unit in
metres (``1e-3`` for millimetres) and facegeo works in metres.

**Distortion lengths.** OpenCV uses 4, 5, 8, 12 (+ thin prism s1…s4) or 14 (+ tilt τx, τy)
coefficients; :class:`~facegeo.geometry.camera.Camera` models 0, 4, 5 or 8. A 12 or 14 vector
whose extra terms are all exactly zero is read as its first 8 (the same lens); non-zero thin
prism or tilt terms are refused with :class:`~facegeo.errors.InputError` naming the file, the key
and the terms (facegeo cannot model that lens; recalibrate with ``CALIB_RATIONAL_MODEL`` or
fewer terms).

**Image size changes.** :func:`rescale_camera` maps a calibration to images resized by a
uniform factor ``s``: ``f' = f·s``, ``c' = (c + ½)·s − ½`` (the pixel-centre rule: an image
reduced by box means of ``1/s × 1/s`` blocks, e.g. OpenCV's ``IMREAD_REDUCED_*`` or
``cv2.resize(..., INTER_AREA)`` on exact multiples, maps pixel centre c to that c').
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.checks import check_positive, fmt_value
from facegeo.errors import InputError

__all__ = ["read_matrices", "read_opencv_camera", "read_opencv_stereo", "write_opencv_camera",
           "write_opencv_stereo", "rescale_camera", "stereo_extrinsics"]

log = logging.getLogger(__name__)

#: Key spellings of a single-camera file: ``(label, map the keys sit under or None,
#: {role: key})``, tried in order; the first whose camera-matrix key exists is used.
_CAMERA_SPELLINGS = (
    ("OpenCV calibration output", None,
     {"K": "camera_matrix", "dist": "distortion_coefficients", "width": "image_width",
      "height": "image_height", "R": "R", "T": "T"}),
    ("3DUNDERWORLD calib.xml", "Camera",
     {"K": "Matrix", "dist": "Distortion", "width": "Width", "height": "Height",
      "R": "Rotation", "T": "Translation"}),
)

#: Key spellings of a camera pair's intrinsics: stereo_calib's, then cv2.stereoCalibrate's names.
_PAIR_SPELLINGS = ({"K1": "M1", "D1": "D1", "K2": "M2", "D2": "D2"},
                   {"K1": "cameraMatrix1", "D1": "distCoeffs1", "K2": "cameraMatrix2",
                    "D2": "distCoeffs2"})

#: Keys :func:`write_opencv_stereo` adds for the world pose of camera 1 (no OpenCV tool uses
#: them; :func:`read_opencv_stereo` places camera 1 at the world origin without them).
_PAIR_WORLD_KEYS = ("R_cam1_world", "T_cam1_world")


#: What a pair's R, T map between.
_PAIR_FRAMES = "camera 1 → camera 2"


def _where(path: Path, key: str | None) -> str:
    return f"{path} [{key}]" if key else str(path)


def _node_kind(node) -> str:
    if node.isInt() or node.isReal():
        return f"the number {fmt_value(node.real())}"
    if node.isString():
        return f"the string {node.string()!r}"
    if node.isMap():
        return f"a map of {', '.join(node.keys()) or 'nothing'}"
    return "a sequence that is not all numbers" if node.isSeq() else "an unknown node"


class _Storage:
    """An open ``cv2.FileStorage`` for reading, with keys as ``"map/key"`` paths and errors that
    name the file and the key."""

    def __init__(self, path: str | os.PathLike):
        import cv2

        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"{self.path}: calibration file not found")
        try:
            fs = cv2.FileStorage(str(self.path), cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError) as exc:  # OpenCV raises SystemError wrapping cv2.error
            cause = exc.__cause__ if isinstance(exc, SystemError) and exc.__cause__ else exc
            text = " ".join(str(cause).split())
            m = re.search(r"\((\d+)\): (.*?)'?$", text)  # "...file.yml(3): Invalid syntax'"
            msg = f"line {m.group(1)}: {m.group(2)}" if m else text or type(cause).__name__
            raise InputError(f"{self.path}: not an OpenCV FileStorage file (XML, YAML or JSON); "
                             f"{msg}") from None
        if not fs.isOpened():
            raise InputError(f"{self.path}: cannot open as an OpenCV FileStorage file")
        self.fs = fs

    def __enter__(self) -> _Storage:
        return self

    def __exit__(self, *exc) -> None:
        self.fs.release()

    def top_keys(self) -> list[str]:
        root = self.fs.root()
        return list(root.keys()) if root.isMap() else []

    def node(self, key: str):
        """The node at ``key`` (``"Camera/Matrix"``), or None when absent."""
        node = None
        for part in key.split("/"):
            if node is None:
                node = self.fs.getNode(part)
            elif node.isMap():
                node = node.getNode(part)
            else:
                return None
            if node.empty() or node.isNone():
                return None
        return node

    def has(self, key: str) -> bool:
        return self.node(key) is not None

    def require(self, key: str, what: str):
        node = self.node(key)
        if node is None:
            raise InputError(f"{_where(self.path, key)}: missing; expected {what}")
        return node

    def matrix(self, key: str, what: str = "a matrix") -> np.ndarray:
        """A matrix (``!!opencv-matrix``), a sequence of numbers (1-D) or a number (1 × 1), as
        float64."""
        node = self.require(key, what)
        m = None
        if node.isSeq():
            vals = [node.at(i) for i in range(node.size())]
            if all(v.isReal() or v.isInt() for v in vals):
                m = np.array([v.real() for v in vals], dtype=np.float64)
        elif node.isInt() or node.isReal():
            m = np.array([[node.real()]])
        elif node.isMap() and "data" in node.keys():  # opencv-matrix or opencv-nd-matrix
            import cv2

            try:
                m = node.mat()
            except cv2.error as exc:
                said = re.search(r"error: \(.*?\) (.*)", " ".join(str(exc).split()))
                raise InputError(f"{_where(self.path, key)}: a malformed matrix (rows, cols, "
                                 f"data disagree; OpenCV: {said.group(1) if said else exc})"
                                 ) from None
            if m is not None:
                m = np.asarray(m, dtype=np.float64)
            elif node.getNode("rows").isInt() and node.getNode("cols").isInt():
                # an empty opencv-matrix (rows or cols 0) reads as None
                m = np.zeros((int(node.getNode("rows").real()),
                              int(node.getNode("cols").real())))
        if m is None:
            raise InputError(f"{_where(self.path, key)}: expected {what}, got {_node_kind(node)}")
        if not np.isfinite(m).all():
            raise InputError(f"{_where(self.path, key)}: non-finite values in {what}")
        return m

    def integer(self, key: str, what: str) -> int:
        node = self.require(key, what)
        if not (node.isInt() or node.isReal()) or node.real() != int(node.real()) \
                or node.real() < 1:
            raise InputError(f"{_where(self.path, key)}: expected {what} (a positive integer)")
        return int(node.real())


def read_matrices(path: str | os.PathLike, keys: Sequence[str]) -> dict[str, np.ndarray]:
    """Read named matrices from an OpenCV FileStorage file.

    Parameters
    ----------
    path : path-like
        XML, YAML or JSON written by ``cv2.FileStorage``.
    keys : sequence of str
        Top-level keys, or ``"map/key"`` paths into nested maps (``"Camera/Matrix"``).

    Returns
    -------
    dict
        ``{key: (rows, cols) float64}`` (a sequence of numbers gives a 1-D array).

    Raises
    ------
    InputError
        The file is missing or not FileStorage, or a key is absent or not a matrix; the message
        names the file and the key.
    """
    with _Storage(path) as st:
        return {k: st.matrix(k) for k in keys}


def _distortion(d: np.ndarray, path: Path, key: str) -> np.ndarray:
    """OpenCV's distortion vector as :class:`Camera` takes it (module docstring)."""
    from facegeo.geometry.camera import DIST_LENGTHS

    if d.ndim > 2 or (d.ndim == 2 and 1 not in d.shape):
        raise InputError(f"{_where(path, key)}: expected a distortion vector (1 × n or n × 1), "
                         f"got a {d.shape[0]} × {d.shape[1]} matrix")
    d = d.ravel()
    n = d.shape[0]
    if n in (12, 14):
        extra = d[8:]
        if np.any(extra != 0.0):
            names = ["s1", "s2", "s3", "s4", "tau_x", "tau_y"][: n - 8]
            terms = ", ".join(f"{a} = {fmt_value(float(v))}" for a, v in zip(names, extra)
                              if v != 0.0)
            raise InputError(
                f"{_where(path, key)}: {n} distortion coefficients with non-zero thin-prism / "
                f"tilt terms ({terms}); facegeo's Camera models {', '.join(map(str, DIST_LENGTHS))}"
                " coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]): recalibrate without "
                "CALIB_THIN_PRISM_MODEL / CALIB_TILTED_MODEL")
        log.debug("%s [%s]: %d distortion coefficients, the terms beyond 8 are zero; using 8",
                  path, key, n)
        d = d[:8]
    elif n not in DIST_LENGTHS:
        raise InputError(f"{_where(path, key)}: {n} distortion coefficients; OpenCV uses 4, 5, "
                         "8, 12 or 14 (facegeo's Camera 0, 4, 5 or 8)")
    return d


def _size(st: _Storage, prefix: str, keys: Mapping[str, str], size) -> tuple[int, int]:
    w_key, h_key = prefix + keys["width"], prefix + keys["height"]
    if st.has(w_key) or st.has(h_key) or size is None:
        return (st.integer(w_key, "the image width in pixels (or give size=(width, height))"),
                st.integer(h_key, "the image height in pixels (or give size=(width, height))"))
    w, h = size
    return int(w), int(h)


def _pose(st: _Storage, r_key: str, t_key: str, units: float, *, required: bool,
          frames: str = "world → camera"):
    """``Pose`` from a rotation matrix (or rvec) and a translation in file units."""
    from facegeo.frames import Pose, rotation_from_rvec

    has_r, has_t = st.has(r_key), st.has(t_key)
    if not (has_r or has_t) and not required:
        return Pose.identity()
    R = st.matrix(r_key, f"a 3 × 3 rotation ({frames})")
    t = st.matrix(t_key, f"a translation of 3 elements ({frames})")
    if R.size == 3:  # an rvec, as some tools write it
        R = rotation_from_rvec(R.ravel())
    if R.shape != (3, 3):
        raise InputError(f"{_where(st.path, r_key)}: expected a 3 × 3 rotation, got shape "
                         f"{R.shape}")
    if t.size != 3:
        raise InputError(f"{_where(st.path, t_key)}: expected 3 elements, got {t.size}")
    try:
        return Pose(R, t.ravel() * units)
    except InputError as exc:
        raise InputError(f"{_where(st.path, r_key)}: {exc}") from None


def _camera(path: Path, name: str, K: np.ndarray, dist: np.ndarray, size, pose, k_key: str):
    """A :class:`Camera`; its complaints (skew, a non-positive focal length) name the file."""
    from facegeo.geometry.camera import Camera

    if K.shape != (3, 3):
        raise InputError(f"{_where(path, k_key)}: expected a 3 × 3 camera matrix, got shape "
                         f"{K.shape}")
    try:
        return Camera(name, size[0], size[1], K, dist, pose)
    except InputError as exc:
        raise InputError(f"{_where(path, k_key)}: {exc}") from None


def read_opencv_camera(path: str | os.PathLike, name: str = "camera", *, units: float = 1.0,
                       size: tuple[int, int] | None = None):
    """One camera from an OpenCV FileStorage calibration file (module docstring for the keys).

    Parameters
    ----------
    path : path-like
        XML or YAML: OpenCV's calibration output (``camera_matrix``, ...), a 3DUNDERWORLD
        ``calib.xml`` (``Camera/Matrix``, ...) or :func:`write_opencv_camera`'s file.
    name : str
        The camera's name in facegeo.
    units : float > 0, metres per file unit
        The unit of the file's translation: ``1.0`` metres (facegeo's files), ``1e-3``
        millimetres (3DUNDERWORLD).
    size : (width, height) int, pixels, optional
        The image size, for files that do not state it (``tutorial_camera_params.yml``); the
        file's own size wins when it has one.

    Returns
    -------
    facegeo.geometry.camera.Camera
        ``K`` and ``dist`` as stored (pixels of the image size the file states), pose
        ``T_cam_world`` from ``R``, ``T`` × ``units`` (metres), or the identity when a file of
        OpenCV's spelling has no pose.

    Raises
    ------
    InputError
        Not a FileStorage file; no known camera-matrix key (the message lists the keys found);
        a required key missing (``camera_matrix`` / ``distortion_coefficients`` / the size, and
        for 3DUNDERWORLD also ``Rotation`` / ``Translation``) or malformed; a distortion Camera
        cannot model; a ``stereo_calib`` pair file (use :func:`read_opencv_stereo`). The message
        names the file and the key.
    """
    units = check_positive(units, "units")
    with _Storage(path) as st:
        for label, root, keys in _CAMERA_SPELLINGS:
            prefix = f"{root}/" if root else ""
            if root and not st.has(root):
                continue
            if root is None and not st.has(keys["K"]):
                continue
            log.debug("%s: reading a camera of the %s spelling", st.path, label)
            if root and st.has(prefix + "Calibrated"):
                flag = st.node(prefix + "Calibrated")
                if (flag.isInt() or flag.isReal()) and flag.real() == 0:
                    raise InputError(f"{_where(st.path, prefix + 'Calibrated')}: 0 — this "
                                     "camera was not calibrated by the scanner")
            K = st.matrix(prefix + keys["K"], "a 3 × 3 camera matrix")
            dist = _distortion(st.matrix(prefix + keys["dist"], "the distortion coefficients"),
                               st.path, prefix + keys["dist"])
            wh = _size(st, prefix, keys, size)
            pose = _pose(st, prefix + keys["R"], prefix + keys["T"], units,
                         required=root is not None)
            return _camera(st.path, name, K, dist, wh, pose, prefix + keys["K"])
        top = st.top_keys()
        if any(all(k in top for k in (s["K1"], s["K2"])) for s in _PAIR_SPELLINGS):
            raise InputError(f"{st.path}: a camera pair's intrinsics ({', '.join(top[:6])}); read "
                             "it with read_opencv_stereo")
        raise InputError(
            f"{st.path} [camera_matrix]: missing; not a camera calibration of a known spelling "
            "(camera_matrix + distortion_coefficients, or a 3DUNDERWORLD Camera map with "
            f"Matrix, Distortion, ...); its top-level keys are {', '.join(top) or 'none'}")


def read_opencv_stereo(intrinsics: str | os.PathLike,
                       extrinsics: str | os.PathLike | None = None, *,
                       names: tuple[str, str] = ("left", "right"), units: float = 1.0,
                       size: tuple[int, int] | None = None):
    """A camera pair from ``stereo_calib``'s ``intrinsics.yml`` / ``extrinsics.yml``.

    Camera 1 is placed at the world origin (``X_world = X_cam1``) unless the file has
    ``R_cam1_world`` / ``T_cam1_world`` (:func:`write_opencv_stereo` writes them); camera 2 is
    ``R``, ``T`` from camera 1 (``X_cam2 = R X_cam1 + T``, OpenCV's ``stereoCalibrate``).

    Parameters
    ----------
    intrinsics : path-like
        ``M1``, ``D1``, ``M2``, ``D2`` (or ``cameraMatrix1``, ``distCoeffs1``, ...); may also hold
        ``R``, ``T`` and the image size (:func:`write_opencv_stereo`'s single file).
    extrinsics : path-like, optional
        ``R``, ``T`` (``stereo_calib``'s ``extrinsics.yml``); default: read them from
        ``intrinsics``.
    names : (str, str)
        The cameras' names.
    units : float > 0, metres per file unit
        The unit of ``T`` (``stereo_calib`` writes board units: its ``square_size``).
    size : (width, height) int, pixels, optional
        The image size when neither file states it (``stereo_calib`` does not).

    Returns
    -------
    (Camera, Camera)

    Raises
    ------
    InputError
        A missing key (``R`` / ``T`` when neither file has them, ``image_width`` without
        ``size``, an intrinsics key), a malformed matrix, a distortion Camera cannot model;
        the message names the file and the key.
    """
    from facegeo.frames import Pose

    units = check_positive(units, "units")
    with _Storage(intrinsics) as st:
        top = st.top_keys()
        keys = next((s for s in _PAIR_SPELLINGS if s["K1"] in top), _PAIR_SPELLINGS[0])
        Ks = [st.matrix(keys[k], "a 3 × 3 camera matrix") for k in ("K1", "K2")]
        ds = [_distortion(st.matrix(keys[k], "the distortion coefficients"), st.path, keys[k])
              for k in ("D1", "D2")]
        wh = _size(st, "", {"width": "image_width", "height": "image_height"}, size)
        T1 = (_pose(st, *_PAIR_WORLD_KEYS, units, required=True)
              if any(st.has(k) for k in _PAIR_WORLD_KEYS) else Pose.identity())
        T21 = None
        if extrinsics is None:
            if not st.has("R"):
                raise InputError(f"{_where(st.path, 'R')}: missing; this file has no extrinsics "
                                 "(R, T: camera 1 → camera 2): pass stereo_calib's "
                                 "extrinsics.yml as extrinsics=")
            T21 = _pose(st, "R", "T", units, required=True, frames=_PAIR_FRAMES)
    if T21 is None:
        with _Storage(extrinsics) as se:
            T21 = _pose(se, "R", "T", units, required=True, frames=_PAIR_FRAMES)
    path = Path(intrinsics)
    return (_camera(path, names[0], Ks[0], ds[0], wh, T1, keys["K1"]),
            _camera(path, names[1], Ks[1], ds[1], wh, T21 @ T1, keys["K2"]))


# ------------------------------------------------------------------------------- writing

def _write_storage(path: Path, entries: Sequence[tuple[str, Any]], comments: Sequence[str]):
    """Write ``(key, value)`` pairs with ``cv2.FileStorage`` atomically (format by suffix)."""
    import cv2

    from facegeo.fsutil import atomic_path

    path = Path(path)
    if path.suffix.lower() not in (".yml", ".yaml", ".xml", ".json"):
        raise InputError(f"{path}: an OpenCV FileStorage file needs the suffix .yml, .yaml, .xml "
                         "or .json (it picks the format)")
    with atomic_path(path) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        if not fs.isOpened():
            raise OSError(f"OpenCV cannot write {path}")
        try:
            for key, value in entries:
                if isinstance(value, np.ndarray):
                    fs.write(key, np.ascontiguousarray(value, dtype=np.float64))
                elif isinstance(value, (bool, np.bool_)):
                    fs.write(key, int(value))
                elif isinstance(value, (int, np.integer)):
                    fs.write(key, int(value))
                elif isinstance(value, (float, np.floating)):
                    fs.write(key, float(value))
                else:
                    fs.write(key, str(value))
            for c in comments:
                fs.writeComment(c)
        finally:
            fs.release()
    return path


def _extra_entries(extra: Mapping[str, Any] | None, taken: set[str]) -> list[tuple[str, Any]]:
    out = []
    for k, v in (extra or {}).items():
        if k in taken:
            raise InputError(f"extra: key {k!r} is written by the camera itself")
        out.append((k, np.asarray(v, np.float64) if isinstance(v, (list, tuple, np.ndarray))
                    else v))
    return out


def write_opencv_camera(path: str | os.PathLike, camera, *, units: float = 1.0,
                        pose: bool = True, extra: Mapping[str, Any] | None = None) -> Path:
    """Write one camera as an OpenCV FileStorage file (atomically), as OpenCV's calibration
    sample does.

    Keys: ``image_width``, ``image_height`` (int), ``camera_matrix`` (3 × 3),
    ``distortion_coefficients`` (n × 1, n ∈ {0, 4, 5, 8}); with ``pose`` also ``R`` (3 × 3) and
    ``T`` (3 × 1) world → camera, ``X_cam = R X_world + T``, ``T`` in ``units``. Then ``extra``,
    in order. Doubles are written with 17 significant digits, so :func:`read_opencv_camera`
    (or ``cv2.FileStorage``) gives back the same float64 values.

    Parameters
    ----------
    path : path-like
        ``.yml`` / ``.yaml`` (YAML), ``.xml`` or ``.json``: the suffix picks the format.
    camera : facegeo.geometry.camera.Camera
    units : float > 0, metres per file unit
        The unit ``T`` is written in (``1e-3``: millimetres).
    pose : bool
        Write ``R`` and ``T``.
    extra : mapping, optional
        More entries (``{"avg_reprojection_error": 0.2}``); sequences become ``n × 1`` matrices
        unless already 2-D arrays.

    Returns
    -------
    Path
    """
    from facegeo.geometry.camera import Camera

    if not isinstance(camera, Camera):
        raise InputError(f"camera: expected a facegeo Camera, got {type(camera).__name__}")
    units = check_positive(units, "units")
    entries: list[tuple[str, Any]] = [
        ("image_width", camera.width), ("image_height", camera.height),
        ("camera_matrix", camera.K), ("distortion_coefficients", camera.dist.reshape(-1, 1))]
    comments = []
    if pose:
        entries += [("R", camera.T_cam_world.R),
                    ("T", (camera.T_cam_world.t / units).reshape(3, 1))]
        comments.append(f"R, T: world -> camera {camera.name} (X_cam = R X_world + T); "
                        f"T in units of {fmt_value(units)} m")
    extras = []
    for k, v in _extra_entries(extra, {k for k, _ in entries}):
        if isinstance(v, np.ndarray) and v.ndim < 2:
            v = v.reshape(-1, 1)
        extras.append((k, v))
    return _write_storage(Path(path), entries + extras, comments)


def stereo_extrinsics(camera_1, camera_2, *, units: float = 1.0) -> dict[str, np.ndarray]:
    """``R``, ``T``, ``E``, ``F`` of a camera pair, as ``cv2.stereoCalibrate`` returns them.

    ``X_cam2 = R X_cam1 + T`` (``T`` in ``units``); ``E = [T]ₓ R``;
    ``F = K2⁻ᵀ E K1⁻¹`` scaled to ``F[2, 2] = 1`` (when non-zero), so that
    ``q2ᵀ F q1 = 0`` for the undistorted pixels ``q1``, ``q2`` (homogeneous) of a point.

    Returns
    -------
    dict
        ``R (3, 3)``, ``T (3, 1)``, ``E (3, 3)``, ``F (3, 3)``, float64.
    """
    units = check_positive(units, "units")
    T21 = camera_2.T_cam_world @ camera_1.T_cam_world.inverse()
    R, t = T21.R, T21.t / units
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    E = tx @ R
    F = np.linalg.inv(camera_2.K).T @ E @ np.linalg.inv(camera_1.K)
    if F[2, 2] != 0.0:
        F = F / F[2, 2]
    return {"R": np.array(R), "T": t.reshape(3, 1), "E": E, "F": F}


def write_opencv_stereo(path: str | os.PathLike, camera_1, camera_2, *,
                        units: float = 1.0) -> Path:
    """Write a camera pair as one OpenCV FileStorage file (atomically).

    Keys: ``image_width``, ``image_height``; ``M1``, ``D1``, ``M2``, ``D2`` (the intrinsics as
    ``stereo_calib``'s ``intrinsics.yml`` names them); ``R``, ``T``, ``E``, ``F`` as
    ``cv2.stereoCalibrate`` returns them (:func:`stereo_extrinsics`; ``T`` in ``units``); and
    ``R_cam1_world``, ``T_cam1_world`` (camera 1's world pose, which OpenCV tools ignore) so that
    :func:`read_opencv_stereo` gives back both cameras in the same world frame.

    Raises
    ------
    InputError
        The cameras' image sizes differ (``stereoCalibrate`` and ``stereoRectify`` take one
        ``imageSize``).
    """
    from facegeo.geometry.camera import Camera

    for i, c in enumerate((camera_1, camera_2), 1):
        if not isinstance(c, Camera):
            raise InputError(f"camera_{i}: expected a facegeo Camera, got {type(c).__name__}")
    if camera_1.size != camera_2.size:
        raise InputError(f"camera_2: image size {camera_2.size} differs from camera_1's "
                         f"{camera_1.size}; an OpenCV stereo pair has one image size")
    units = check_positive(units, "units")
    ext = stereo_extrinsics(camera_1, camera_2, units=units)
    entries = [("image_width", camera_1.width), ("image_height", camera_1.height),
               ("M1", camera_1.K), ("D1", camera_1.dist.reshape(-1, 1)),
               ("M2", camera_2.K), ("D2", camera_2.dist.reshape(-1, 1)),
               ("R", ext["R"]), ("T", ext["T"]), ("E", ext["E"]), ("F", ext["F"]),
               ("R_cam1_world", camera_1.T_cam_world.R),
               ("T_cam1_world", (camera_1.T_cam_world.t / units).reshape(3, 1))]
    comments = [f"camera 1 = {camera_1.name}, camera 2 = {camera_2.name}; X_cam2 = R X_cam1 + T; "
                f"lengths in units of {fmt_value(units)} m"]
    return _write_storage(Path(path), entries, comments)


# ------------------------------------------------------------------------------- rescaling

def rescale_camera(camera, width: int, height: int):
    """The camera for its images resized to ``width × height`` by one uniform factor.

    Implements the pixel-centre rule: with ``s = width / camera.width = height / camera.height``,
    ``fx' = fx·s``, ``fy' = fy·s``, ``cx' = (cx + ½)·s − ½``, ``cy' = (cy + ½)·s − ½``
    (:meth:`facegeo.geometry.camera.Camera.scaled`); distortion (normalised coordinates) and
    pose are unchanged.

    Parameters
    ----------
    camera : facegeo.geometry.camera.Camera
    width, height : int, pixels
        The new image size.

    Returns
    -------
    facegeo.geometry.camera.Camera

    Raises
    ------
    InputError
        The two axes scale differently (``width · H ≠ height · W``, compared exactly): the
        images were cropped or squeezed, not scaled, and no single factor maps the calibration.
    """
    from facegeo.checks import check_positive_int

    width = check_positive_int(width, "width")
    height = check_positive_int(height, "height")
    if width * camera.height != height * camera.width:
        raise InputError(
            f"rescale {camera.name}: {camera.width} × {camera.height} → {width} × {height} "
            f"scales x by {fmt_value(width / camera.width)} but y by "
            f"{fmt_value(height / camera.height)}; only a uniform scale maps a calibration "
            "(crop or pad the images to the calibrated aspect first)")
    if (width, height) == camera.size:
        return camera
    return camera.scaled(width / camera.width)
