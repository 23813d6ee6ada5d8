"""Calibration boards: the ChArUco board's geometry, printed texture and exact synthetic views,
and the same for every board kind a scan may declare (plain chessboards and circle grids:
:func:`render_board`, :func:`board_texture`, :func:`board_extent`).

Board frame (OpenCV's ``CharucoBoard`` object frame): origin at the board's top-left corner, x
along the ``squares_x`` direction, y along ``squares_y`` (down the printed image), z = 0 on the
board; the printed face looks toward board −z, so a camera with ``R_cam_board ≈ I`` sees it. A
texel ``(col, row)`` of :meth:`CharucoBoard.texture` covers board points
``[col·m, (col+1)·m] × [row·m, (row+1)·m]`` (``m`` metres per texel).

:meth:`CharucoBoard.render` makes a camera image of the board by exact ray–plane intersection of
every (supersampled) pixel ray, so lens distortion is honoured exactly, and a bilinear lookup into
the texture; :func:`random_board_poses` draws well-conditioned calibration views.

``calib/charuco_board.json`` is ``CharucoBoard()`` saved; regenerate it with
``python -m facegeo.geometry.rig`` (see :mod:`facegeo.geometry.rig`).
"""

from __future__ import annotations

import json
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np

from facegeo.geometry._board_kinds import (  # noqa: F401 (re-exported)
    BLACK_REFLECTANCE,
    CHESSBOARD_MARGIN_SQUARES,
    CIRCLE_RADIUS_FRACTION,
    WHITE_REFLECTANCE,
    board_extent,
    board_outline,
    board_pitch,
    board_points,
    board_texture,
    board_to_dict,
    save_board,
)
from facegeo.geometry.camera import Camera
from facegeo.checks import as_array, check_positive, fmt_value
from facegeo.errors import InputError
from facegeo.frames import Pose, rotation_from_rvec
from facegeo.fsutil import atomic_write_text, load_json_file

__all__ = [
    "CharucoBoard",
    "BoardView",
    "board_extent",
    "board_outline",
    "board_pitch",
    "board_points",
    "board_texture",
    "board_to_dict",
    "render_board",
    "save_board",
    "CHESSBOARD_MARGIN_SQUARES",
    "CIRCLE_RADIUS_FRACTION",
    "random_board_poses",
    "aruco_dictionary_names",
    "WHITE_REFLECTANCE",
    "BLACK_REFLECTANCE",
    "BOARD_FORMAT",
    "BOARD_VERSION",
]

# WHITE_REFLECTANCE, BLACK_REFLECTANCE: the paper's and the ink's diffuse reflectance (linear),
# defined with the board kinds (facegeo.geometry._board_kinds) and re-exported here.
#: ``"format"`` tag of a board file.
BOARD_FORMAT = "facegeo-charuco-board"
#: Version of the board file layout.
BOARD_VERSION = 1

_BOARD_KEYS = ("squares_x", "squares_y", "square_length", "marker_length", "dictionary")

# Undistorted rays of the last few cameras rendered (the undistortion is the costly part of a
# render, and calibration renders many views through each camera). Key: intrinsics + supersample.
# Sub-pixel rays are kept in float32 (≈ 1e-5 px, far below the box filter's effect) to halve the
# memory; pixel-centre rays, which give p_world, stay float64.
_RAY_CACHE: OrderedDict = OrderedDict()
_RAY_CACHE_SIZE = 4
_RAY_CACHE_LOCK = threading.Lock()  # renders may run on several threads (synth calibration)


def aruco_dictionary_names() -> list[str]:
    """Names of OpenCV's predefined ArUco dictionaries (``"DICT_5X5_100"``, ...)."""
    return sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))


@dataclass(frozen=True)
class BoardView:
    """A synthetic camera image of a board (:meth:`CharucoBoard.render`).

    Attributes
    ----------
    reflectance : (H, W) float32, linear reflectance
        Supersampled (box-filtered) board reflectance seen by each pixel; 0 off the board.
    mask : (H, W) bool
        The ray through the pixel centre hits the board's printed face.
    p_world : (H, W, 3) float64, metres, world frame
        Board point hit by each pixel-centre ray; NaN where ``mask`` is False.
    """

    reflectance: np.ndarray
    mask: np.ndarray
    p_world: np.ndarray

    def to_uint8(self) -> np.ndarray:
        """The reflectance as an 8-bit image (``round(255·reflectance)``), e.g. for detectors."""
        return np.clip(np.rint(self.reflectance * 255.0), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class CharucoBoard:
    """A ChArUco board.

    Parameters
    ----------
    squares_x, squares_y : int
        Chessboard squares along board x and y (≥ 2 each).
    square_length : float, metres
    marker_length : float, metres
        ArUco marker side, ``< square_length``.
    dictionary : str
        Name of an OpenCV predefined dictionary (:func:`aruco_dictionary_names`) with at least
        ``squares_x·squares_y // 2`` markers.
    legacy : bool or None
        OpenCV's legacy pattern (``cv2.aruco.CharucoBoard.setLegacyPattern``: boards made by
        OpenCV < 4.6 — and by many printed-board generators since — whose even row count
        starts with a white square). ``True`` / ``False``: that pattern; ``None`` (default,
        ``"auto"`` in a board file): not declared — the new pattern when drawn, and a set of
        views is read both ways and the reading with more corners taken
        (:func:`facegeo.geometry.calibration.detect_boards`). With an odd ``squares_y`` the
        two patterns are the same board (:attr:`legacy_matters` is False) and the key is
        moot.
    """

    board_kind: ClassVar[str] = "charuco"
    squares_x: int = 7
    squares_y: int = 5
    square_length: float = 0.04
    marker_length: float = 0.03
    dictionary: str = "DICT_5X5_100"
    legacy: bool | None = None

    def __post_init__(self):
        if self.legacy is not None and not isinstance(self.legacy, (bool, np.bool_)):
            raise InputError(f"legacy: expected true, false or \"auto\" (not declared), got "
                             f"{fmt_value(self.legacy)}")
        object.__setattr__(self, "legacy", None if self.legacy is None else bool(self.legacy))
        for name in ("squares_x", "squares_y"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 2:
                raise InputError(f"{name}: expected an integer >= 2, got {fmt_value(v)}")
            object.__setattr__(self, name, int(v))
        sq = check_positive(self.square_length, "square_length")
        mk = check_positive(self.marker_length, "marker_length")
        if not mk < sq:
            raise InputError(
                f"marker_length: must be smaller than square_length ({fmt_value(sq)} m), got {fmt_value(mk)} m"
            )
        object.__setattr__(self, "square_length", sq)
        object.__setattr__(self, "marker_length", mk)
        names = aruco_dictionary_names()
        if not isinstance(self.dictionary, str) or self.dictionary not in names:
            raise InputError(
                f"dictionary: unknown ArUco dictionary {fmt_value(self.dictionary)}; expected one of "
                f"{', '.join(names)}"
            )
        have = self._cv2_dictionary().bytesList.shape[0]
        need = self.n_markers
        if need > have:
            raise InputError(
                f"dictionary: {self.dictionary} has {have} markers but a {self.squares_x}×"
                f"{self.squares_y} board needs {need}; choose a larger dictionary"
            )

    # ------------------------------------------------------------------ geometry

    def _cv2_dictionary(self):
        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))

    @property
    def n_markers(self) -> int:
        """Number of ArUco markers on the board."""
        return (self.squares_x * self.squares_y) // 2

    @property
    def n_corners(self) -> int:
        """Number of inner chessboard corners ``(squares_x − 1)(squares_y − 1)``."""
        return (self.squares_x - 1) * (self.squares_y - 1)

    @property
    def size(self) -> tuple[float, float]:
        """``(width_m, height_m)``: board extent along board x and y, metres."""
        return (self.squares_x * self.square_length, self.squares_y * self.square_length)

    @property
    def legacy_matters(self) -> bool:
        """Whether OpenCV's legacy and new patterns differ for this board (an even
        ``squares_y``: the legacy pattern then starts with a white square)."""
        return self.squares_y % 2 == 0

    def with_legacy(self, legacy: bool | None) -> CharucoBoard:
        """This board with :attr:`legacy` set (``dataclasses.replace``)."""
        from dataclasses import replace

        return replace(self, legacy=legacy)

    def to_cv2(self):
        """The equivalent ``cv2.aruco.CharucoBoard`` (legacy pattern set when :attr:`legacy`)."""
        b = cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y),
            self.square_length,
            self.marker_length,
            self._cv2_dictionary(),
        )
        if self.legacy:
            b.setLegacyPattern(True)
        return b

    def chessboard_corners(self) -> np.ndarray:
        """Inner chessboard corners in OpenCV's ChArUco id order (x fastest).

        Returns
        -------
        (N, 3) float64, metres, board frame
            Row k is ChArUco corner id k; equals ``to_cv2().getChessboardCorners()`` (which is
            float32) to float32 precision.
        """
        nx = self.squares_x - 1
        k = np.arange(self.n_corners)
        L = self.square_length
        return np.stack(
            [(k % nx + 1) * L, (k // nx + 1) * L, np.zeros(k.shape[0])], axis=-1
        ).astype(np.float64)

    def outline(self, n_per_edge: int = 16) -> np.ndarray:
        """Points along the board's outer edge.

        Returns
        -------
        (4·n_per_edge, 3) float64, metres, board frame
            Clockwise from the origin corner, ``n_per_edge`` evenly spaced points per edge.
        """
        W, H = self.size
        s = np.linspace(0.0, 1.0, n_per_edge, endpoint=False)
        z = np.zeros_like(s)
        return np.concatenate(
            [
                np.stack([s * W, z, z], -1),
                np.stack([np.full_like(s, W), s * H, z], -1),
                np.stack([W - s * W, np.full_like(s, H), z], -1),
                np.stack([z, H - s * H, z], -1),
            ]
        )

    def texture(self, px_per_square: int = 64) -> tuple[np.ndarray, float]:
        """The printed board as a reflectance image.

        Parameters
        ----------
        px_per_square : int, optional
            Texels per chessboard square.

        Returns
        -------
        texture : (squares_y·px_per_square, squares_x·px_per_square) float32, linear reflectance
            :data:`WHITE_REFLECTANCE` / :data:`BLACK_REFLECTANCE`, drawn by OpenCV's
            ``CharucoBoard.generateImage`` (no margin, 1-bit marker border).
        metres_per_texel : float, metres
            ``m``: texel ``(col, row)`` has its centre at board point
            ``((col + ½)·m, (row + ½)·m)``.
        """
        pps = px_per_square
        if isinstance(pps, bool) or not isinstance(pps, (int, np.integer)) or pps < 4:
            raise InputError(f"px_per_square: expected an integer >= 4, got {fmt_value(pps)}")
        pps = int(pps)
        board = self.to_cv2()
        # OpenCV's generateImage fails an ROI assertion for a few resolutions where the marker's
        # rounded pixel size overruns its square (e.g. 62 px/square for a 0.029/0.0218 board);
        # the next resolution up is always fine, and the returned scale follows it.
        for attempt in range(8):
            try:
                img = board.generateImage(
                    (self.squares_x * pps, self.squares_y * pps), marginSize=0, borderBits=1
                )
                break
            except cv2.error:
                if attempt == 7:
                    raise
                pps += 1
        white = (img.astype(np.float32) / np.float32(255.0))
        tex = np.float32(BLACK_REFLECTANCE) + np.float32(
            WHITE_REFLECTANCE - BLACK_REFLECTANCE
        ) * white
        return tex.astype(np.float32), self.square_length / pps

    # ------------------------------------------------------------------ rendering

    def render(
        self,
        camera: Camera,
        T_cam_board: Pose,
        *,
        supersample: int = 3,
        px_per_square: int | None = None,
    ) -> BoardView:
        """Render the camera's view of the board's reflectance (:func:`render_board`).

        Parameters
        ----------
        camera : Camera
        T_cam_board : Pose
            Board frame to camera frame.
        supersample : int, optional
            Samples per pixel along each axis.
        px_per_square : int, optional
            Texture resolution; default: about two texels per camera pixel at the board's nearest
            corner (at least 32, at most 512).

        Returns
        -------
        BoardView
        """
        return render_board(self, camera, T_cam_board, supersample=supersample,
                            px_per_square=px_per_square)

    # ------------------------------------------------------------------ JSON

    def to_dict(self) -> dict:
        """JSON-ready mapping (lengths in metres); ``legacy`` only when declared (a board
        without it reads as ``"auto"``, and version-1 files stay as they were)."""
        d = {
            "format": BOARD_FORMAT,
            "version": BOARD_VERSION,
            "squares_x": self.squares_x,
            "squares_y": self.squares_y,
            "square_length": self.square_length,
            "marker_length": self.marker_length,
            "dictionary": self.dictionary,
        }
        if self.legacy is not None:
            d["legacy"] = self.legacy
        return d

    @classmethod
    def from_dict(cls, d: Any) -> CharucoBoard:
        """Inverse of :meth:`to_dict`; errors name the field. ``legacy`` is optional:
        ``true``, ``false`` or ``"auto"`` (the same as leaving it out)."""
        allowed = ("format", "version") + _BOARD_KEYS + ("legacy",)
        if not isinstance(d, dict):
            raise InputError(f"board: expected a mapping, got {type(d).__name__}")
        for k in _BOARD_KEYS:
            if k not in d:
                raise InputError(f"{k}: missing field (expected {', '.join(allowed)})")
        unknown = sorted(set(d) - set(allowed))
        if unknown:
            raise InputError(f"{unknown[0]}: unknown field (expected only {', '.join(allowed)})")
        if d.get("format", BOARD_FORMAT) != BOARD_FORMAT:
            raise InputError(f"format: expected {fmt_value(BOARD_FORMAT)}, got {fmt_value(d['format'])}")
        if d.get("version", BOARD_VERSION) != BOARD_VERSION:
            raise InputError(
                f"version: this facegeo reads board version {BOARD_VERSION}, got {fmt_value(d['version'])}"
            )
        legacy = d.get("legacy", "auto")
        if legacy == "auto":
            legacy = None
        elif not isinstance(legacy, bool):
            raise InputError(f"legacy: expected true, false or \"auto\", got {fmt_value(legacy)}")
        return cls(**{k: d[k] for k in _BOARD_KEYS}, legacy=legacy)

    def to_json(self) -> str:
        """Pretty, strict JSON text, newline-terminated."""
        return json.dumps(self.to_dict(), indent=2, allow_nan=False) + "\n"

    def save(self, path) -> Path:
        """Write the board to ``path`` as JSON, atomically. Returns the path."""
        path = Path(path)
        atomic_write_text(path, self.to_json())
        return path

    @classmethod
    def load(cls, path) -> CharucoBoard:
        """Read a board file.

        Raises
        ------
        facegeo.errors.ScanFormatError
            Unreadable file, invalid JSON, or a missing / unknown / bad field (named).
        """
        return load_json_file(path, "board", cls.from_dict)


# --------------------------------------------------------------------------- any board kind
# Extent, outline, points and texture of every kind: facegeo.geometry._board_kinds.


def render_board(board, camera: Camera, T_cam_board: Pose, *, supersample: int = 3,
                 px_per_square: int | None = None) -> BoardView:
    """Render a camera's view of a printed board's reflectance, any board kind.

    Each pixel is sampled by ``supersample × supersample`` rays through a regular sub-pixel
    grid; each ray is undistorted exactly (:meth:`Camera.unproject`), intersected with the
    board plane, and the texture (:func:`board_texture`) is sampled bilinearly at the hit point.
    Pixels average their samples (box filter); samples that miss the sheet
    (:func:`board_extent`), or hit its back, contribute 0.

    Parameters
    ----------
    board : CharucoBoard, ChessboardSpec or CircleGridSpec
    camera : Camera
    T_cam_board : Pose
        Board frame to camera frame.
    supersample : int, optional
        Samples per pixel along each axis.
    px_per_square : int, optional
        Texels per :func:`board_pitch`; default: about two texels per camera pixel at the
        sheet's nearest corner (at least 32, at most 512).

    Returns
    -------
    BoardView
    """
    if not isinstance(camera, Camera):
        raise InputError(f"camera: expected a Camera, got {type(camera).__name__}")
    if not isinstance(T_cam_board, Pose):
        raise InputError(f"T_cam_board: expected a Pose, got {type(T_cam_board).__name__}")
    ss = supersample
    if isinstance(ss, bool) or not isinstance(ss, (int, np.integer)) or ss < 1:
        raise InputError(f"supersample: expected an integer >= 1, got {fmt_value(ss)}")
    ss = int(ss)
    R = T_cam_board.R
    t = T_cam_board.t
    if px_per_square is None:
        z = T_cam_board.apply(board_outline(board, 4))[:, 2]
        z_min = float(z.min()) if np.all(z > 0) else 0.0
        f = max(camera.fx, camera.fy)
        want = 2.0 * f * board_pitch(board) / z_min if z_min > 0 else 512
        px_per_square = int(min(512, max(32, math.ceil(want))))
    tex, m = board_texture(board, px_per_square)
    centre_rays, sub_rays = _camera_rays(camera, ss)

    n_cam = R[:, 2]  # board z axis in the camera frame
    d0 = float(n_cam @ t)  # > 0 ⇔ the camera is on the printed (−z) side
    x0, y0, x1, y1 = board_extent(board)

    R_xy = np.ascontiguousarray(R[:, :2])  # board x, y axes in the camera frame

    def hit(x_n):
        """Where rays ``x_n`` (…, 2) meet the board: (ok, p_cam, xb, yb), metres."""
        den = n_cam[0] * x_n[..., 0] + n_cam[1] * x_n[..., 1] + n_cam[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = d0 / den
        ok = (den > 0) & np.isfinite(s) & (d0 > 0)
        p_cam = np.empty(x_n.shape[:-1] + (3,))
        p_cam[..., 0] = s * x_n[..., 0]
        p_cam[..., 1] = s * x_n[..., 1]
        p_cam[..., 2] = s
        # p_board = R_board_cam @ (p − t), x and y only; one (N, 3) @ (3, 2) product (the
        # same float64 values as the full per-row (…, 3) @ (3, 3) product, 1.5× faster)
        d = (p_cam - t).reshape(-1, 3)
        p_xy = (d @ R_xy).reshape(x_n.shape[:-1] + (2,))
        xb = p_xy[..., 0]
        yb = p_xy[..., 1]
        with np.errstate(invalid="ignore"):
            ok &= (xb >= x0) & (xb <= x1) & (yb >= y0) & (yb <= y1)
        return ok, p_cam, xb, yb

    acc = np.zeros((camera.height, camera.width), dtype=np.float64)
    for x_n in sub_rays:
        ok, _, xb, yb = hit(x_n)
        # texel coordinates (float64, then float32 in the lookup); 0 where the ray misses
        # (x0 = 0 for a ChArUco board: xb − 0.0 is xb exactly, its renders are unchanged)
        u = xb - x0
        u /= m
        u -= 0.5
        u[~ok] = 0.0
        v = yb - y0
        v /= m
        v -= 0.5
        v[~ok] = 0.0
        val = _bilinear(tex, u, v)
        val[~ok] = 0.0
        acc += val
    reflectance = (acc / (ss * ss)).astype(np.float32)

    mask, p_cam, _, _ = hit(centre_rays)
    p_world = camera.T_cam_world.inverse().apply(p_cam)
    p_world[~mask] = np.nan
    return BoardView(reflectance, mask, p_world)


# --------------------------------------------------------------------------- helpers


def _camera_rays(camera: Camera, ss: int):
    """Normalised (z = 1) undistorted rays: pixel centres ``(H, W, 2)`` float64 and the ``ss²``
    sub-pixel grids ``[(H, W, 2) float32, ...]``; cached for the last few intrinsics used."""
    key = (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(), ss)
    with _RAY_CACHE_LOCK:
        hit = _RAY_CACHE.get(key)
        if hit is not None:
            _RAY_CACHE.move_to_end(key)
            return hit
    grid = camera.pixel_grid()
    centre = camera.unproject(grid)[..., :2]
    offsets = (np.arange(ss) + 0.5) / ss - 0.5
    subs = []
    for oy in offsets:
        for ox in offsets:
            if ox == 0.0 and oy == 0.0:
                x_n = centre
            else:
                x_n = camera.unproject(grid + np.array([ox, oy]))[..., :2]
            subs.append(x_n.astype(np.float32))
    for a in subs + [centre]:
        a.setflags(write=False)
    value = (centre, subs)
    with _RAY_CACHE_LOCK:  # two threads may have computed the same rays: either will do
        _RAY_CACHE[key] = value
        while len(_RAY_CACHE) > _RAY_CACHE_SIZE:
            _RAY_CACHE.popitem(last=False)
    return value


_REMAP_MAX = 32767  # cv2.remap needs source and map sides below SHRT_MAX


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup of ``img`` (H, W) at texel coordinates ``(u, v)`` = (col, row), texel
    centres at integers; coordinates are clamped to the image (edge texels extend to the border).

    ``cv2.remap`` (``INTER_LINEAR``, ``BORDER_REPLICATE``, float32 maps) on a float32 image: OpenCV
    interpolates float32 images in floating point (its 1/32-texel fixed-point weights apply only
    to integer and float64 images, which is why ``img`` is cast to float32 here). The maps are
    float32, so coordinates carry float32 round-off (2.4e-4 texel at 4000 texels): against the
    former float64 numpy lookup, board renders differ by at most 1.2e-4 relative per pixel (mean
    absolute 5e-8); at the same float32 coordinates the two agree to < 1e-5 of the texture's range
    (``tests/test_board.py::test_bilinear_matches_numpy_reference``). Renders ~1.5× faster.

    Parameters
    ----------
    img : (H, W) float array
    u, v : (...) float arrays of the same shape, texel coordinates

    Returns
    -------
    (...) float32
    """
    img = np.ascontiguousarray(img, dtype=np.float32)
    H, W = img.shape
    if H >= _REMAP_MAX or W >= _REMAP_MAX:
        raise InputError(
            f"board texture: {W}×{H} texels; cv2.remap takes images below {_REMAP_MAX} texels a "
            "side (lower px_per_square)"
        )
    u = np.asarray(u)
    shape = u.shape
    mu = np.asarray(u, dtype=np.float32).reshape(-1)
    mv = np.asarray(v, dtype=np.float32).reshape(-1)
    n = mu.size
    if n == 0:
        return np.zeros(shape, dtype=np.float32)
    cols = min(n, _REMAP_MAX - 1)
    rows = -(-n // cols)
    pad = rows * cols - n
    if pad:
        mu = np.concatenate([mu, np.zeros(pad, np.float32)])
        mv = np.concatenate([mv, np.zeros(pad, np.float32)])
    out = cv2.remap(img, mu.reshape(rows, cols), mv.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1)[:n].reshape(shape)


def random_board_poses(
    camera: Camera,
    n: int,
    rng,
    *,
    board: CharucoBoard | None = None,
    tilt_deg: tuple[float, float] = (15.0, 45.0),
    fill: tuple[float, float] = (0.3, 0.7),
    roll_deg: tuple[float, float] = (-30.0, 30.0),
    max_view_angle_deg: float = 70.0,
    margin_px: float = 8.0,
    max_tries: int = 500,
) -> list[Pose]:
    """Varied, well-conditioned calibration views of a board: poses ``T_cam_board``.

    View k tilts the board by an angle drawn from ``tilt_deg`` about an in-plane axis at
    azimuth ``2π(k + u)/n`` (u uniform), so the tilt axes cover every direction; a roll about
    the board normal is drawn from ``roll_deg``. Its distance is solved so the board's projected
    bounding box fills a fraction drawn from ``fill`` of the image (the larger of its width / W
    and height / H), and its centre lies at a random pixel. A draw is kept only when the whole
    board outline projects inside the image with ``margin_px`` to spare, every corner is in front
    of the camera, and the printed face is seen at less than ``max_view_angle_deg`` from its
    normal everywhere.

    Parameters
    ----------
    camera : Camera
    n : int
        Number of poses.
    rng : numpy.random.Generator or int
        Randomness (a seed is accepted).
    board : CharucoBoard, optional
        Default ``CharucoBoard()``.

    Returns
    -------
    list of Pose
        ``T_cam_board`` (board frame to camera frame).

    Raises
    ------
    InputError
        Bad ranges, or no acceptable pose found in ``max_tries`` draws (the message says which
        constraint to relax).
    """
    if not isinstance(camera, Camera):
        raise InputError(f"camera: expected a Camera, got {type(camera).__name__}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise InputError(f"n: expected a positive integer, got {fmt_value(n)}")
    rng = np.random.default_rng(rng)
    board = CharucoBoard() if board is None else board
    t_lo, t_hi = _check_range(tilt_deg, "tilt_deg", 0.0, 89.0)
    f_lo, f_hi = _check_range(fill, "fill", 1e-3, 1.0)
    r_lo, r_hi = _check_range(roll_deg, "roll_deg", -180.0, 180.0)
    cos_max = math.cos(math.radians(check_positive(max_view_angle_deg, "max_view_angle_deg")))
    W_img, H_img = camera.width, camera.height
    W_m, H_m = board.size
    c_board = np.array([W_m / 2.0, H_m / 2.0, 0.0])
    outline = board.outline(16)
    lo = np.array([-0.5 + margin_px, -0.5 + margin_px])
    hi = np.array([W_img - 0.5 - margin_px, H_img - 0.5 - margin_px])

    poses: list[Pose] = []
    for k in range(int(n)):
        for _ in range(max_tries):
            tilt = math.radians(rng.uniform(t_lo, t_hi))
            az = 2.0 * math.pi * (k + rng.uniform()) / n
            roll = math.radians(rng.uniform(r_lo, r_hi))
            axis = np.array([math.cos(az), math.sin(az), 0.0])
            R = rotation_from_rvec(axis * tilt) @ rotation_from_rvec(np.array([0.0, 0.0, roll]))
            f_target = rng.uniform(f_lo, f_hi)
            q_c = np.array(
                [
                    camera.cx + rng.uniform(-0.5, 0.5) * (1.0 - f_target) * W_img,
                    camera.cy + rng.uniform(-0.5, 0.5) * (1.0 - f_target) * H_img,
                ]
            )
            v_c = camera.unproject(q_c)
            if not np.all(np.isfinite(v_c)):
                continue
            z = max(camera.fx * W_m / (f_target * W_img), camera.fy * H_m / (f_target * H_img))
            ok = False
            for _it in range(8):
                t = z * v_c - R @ c_board
                p_cam = outline @ R.T + t
                q, front = camera.project_cam(p_cam)
                if not front.all():
                    break
                span = q.max(axis=0) - q.min(axis=0)
                f_now = max(span[0] / W_img, span[1] / H_img)
                if abs(f_now - f_target) < 2e-3:
                    ok = True
                    break
                z *= f_now / f_target
            if not ok:
                continue
            if np.any(q < lo) or np.any(q > hi):
                continue
            cos_view = (p_cam @ R[:, 2]) / np.linalg.norm(p_cam, axis=-1)
            if np.any(cos_view < cos_max):
                continue
            poses.append(Pose(R, t))
            break
        else:
            raise InputError(
                f"random_board_poses: no acceptable view {k} of the {board.squares_x}×"
                f"{board.squares_y} board in camera {fmt_value(camera.name)} after {max_tries} draws; "
                "lower 'fill' or 'tilt_deg', or reduce 'margin_px'"
            )
    return poses


def _check_range(r: Any, name: str, lo: float, hi: float) -> tuple[float, float]:
    a = as_array(r, name, shape=(2,))
    if not (lo <= a[0] <= a[1] <= hi):
        raise InputError(
            f"{name}: expected (low, high) with {lo} <= low <= high <= {hi}, got {fmt_value(r)}"
        )
    return float(a[0]), float(a[1])
