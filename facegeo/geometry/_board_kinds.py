"""Every board kind a scan may declare, as a printed sheet: extent, outline, points, texture,
file form (``docs/scan-format.md``, board kinds).

The kinds: :class:`facegeo.geometry.board.CharucoBoard`, and the detection specs
:class:`~facegeo.geometry._calib_detect.ChessboardSpec` /
:class:`~facegeo.geometry._calib_detect.CircleGridSpec`. A ChArUco sheet is exactly its
squares; a plain chessboard's has a white border of :data:`CHESSBOARD_MARGIN_SQUARES` around its
outer squares (the quiet zone the detectors need), a circle grid's one spacing around the
outermost centres. :func:`facegeo.geometry.board.render_board` renders any of them; these are
re-exported there.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError
from facegeo.fsutil import atomic_write_text

__all__ = ["CHESSBOARD_MARGIN_SQUARES", "CIRCLE_RADIUS_FRACTION", "board_extent",
           "board_outline", "board_pitch", "board_points", "board_texture", "board_to_dict",
           "save_board"]

#: White border around a plain chessboard's outer squares, squares.
CHESSBOARD_MARGIN_SQUARES = 1.0
#: Radius of a printed circle of a circle grid, fraction of the distance between nearest
#: circles (the spacing of a symmetric grid, spacing/√2 of an asymmetric one).
CIRCLE_RADIUS_FRACTION = 0.3


#: Diffuse reflectance of the board's white paper (linear, unitless).
WHITE_REFLECTANCE = 0.85
#: Diffuse reflectance of the board's black ink (linear, unitless).
BLACK_REFLECTANCE = 0.04


def _kind(board) -> str:
    """``"charuco"``, ``"chessboard"`` or ``"circles"``: the board's own ``board_kind`` (a class
    attribute of :class:`~facegeo.geometry.board.CharucoBoard` and the detection specs; read
    here without importing them, which import this module)."""
    kind = getattr(type(board), "board_kind", None)
    if kind in ("charuco", "chessboard", "circles"):
        return kind
    raise InputError(f"board: expected a CharucoBoard, ChessboardSpec or CircleGridSpec, got "
                     f"{type(board).__name__}")


def board_pitch(board) -> float:
    """Metres between neighbouring features: the square (ChArUco, chessboard) or the circle
    grid's ``spacing``."""
    k = _kind(board)
    if k == "charuco":
        return float(board.square_length)
    return float(board.square_size if k == "chessboard" else board.spacing)


def board_points(board) -> np.ndarray:
    """Every detectable point of the board, in its detector's id order.

    Returns
    -------
    (N, 3) float64, metres, board frame
        ChArUco inner corners (:meth:`CharucoBoard.chessboard_corners`), a chessboard's inner
        corners or a circle grid's centres (``object_points()``).
    """
    return board.chessboard_corners() if _kind(board) == "charuco" else board.object_points()


def board_extent(board) -> tuple[float, float, float, float]:
    """The printed sheet in the board frame: ``(x0, y0, x1, y1)``, metres.

    ChArUco: ``(0, 0, squares_x·L, squares_y·L)``. Chessboard (origin at the first inner
    corner): its ``(cols + 1) × (rows + 1)`` squares from ``(−s, −s)`` plus the white border
    :data:`CHESSBOARD_MARGIN_SQUARES`. Circle grid: the centres' bounding box plus one spacing.
    """
    k = _kind(board)
    if k == "charuco":
        W, H = board.size
        return 0.0, 0.0, float(W), float(H)
    if k == "chessboard":
        s = float(board.square_size)
        e = (1.0 + CHESSBOARD_MARGIN_SQUARES) * s
        return -e, -e, (board.cols - 1) * s + e, (board.rows - 1) * s + e
    p = board.object_points()
    s = float(board.spacing)
    return (float(p[:, 0].min()) - s, float(p[:, 1].min()) - s, float(p[:, 0].max()) + s,
            float(p[:, 1].max()) + s)


def board_outline(board, n_per_edge: int = 16) -> np.ndarray:
    """Points along the printed sheet's edge (:func:`board_extent`).

    Returns
    -------
    (4·n_per_edge, 3) float64, metres, board frame
        Clockwise from ``(x0, y0)``; a ChArUco board's equals :meth:`CharucoBoard.outline`.
    """
    if _kind(board) == "charuco":
        return board.outline(n_per_edge)
    x0, y0, x1, y1 = board_extent(board)
    W, H = x1 - x0, y1 - y0
    s = np.linspace(0.0, 1.0, n_per_edge, endpoint=False)
    z = np.zeros_like(s)
    return np.concatenate([
        np.stack([x0 + s * W, y0 + z, z], -1),
        np.stack([x1 + z, y0 + s * H, z], -1),
        np.stack([x1 - s * W, y1 + z, z], -1),
        np.stack([x0 + z, y1 - s * H, z], -1),
    ])


def board_texture(board, px_per_square: int = 64) -> tuple[np.ndarray, float]:
    """The printed sheet as a reflectance image.

    Parameters
    ----------
    board : CharucoBoard, ChessboardSpec or CircleGridSpec
    px_per_square : int
        Texels per :func:`board_pitch` (rounded up to even for a chessboard or a circle grid,
        so the sheet is a whole number of texels).

    Returns
    -------
    texture : (rows, cols) float32, linear reflectance
        :data:`WHITE_REFLECTANCE` paper, :data:`BLACK_REFLECTANCE` ink. A chessboard's square
        ``[a·s, (a+1)·s] × [b·s, (b+1)·s]`` is white when ``a + b`` is even, so its first inner
        square (between corners 0, 1, ``cols``, ``cols + 1``) is light, as
        ``findChessboardCornersSB`` numbers a board whose ``cols + rows`` is odd. Circles are
        black discs of radius :data:`CIRCLE_RADIUS_FRACTION` × the nearest-centre distance,
        edge texels by their covered fraction (a one-texel ramp).
    metres_per_texel : float, metres
        ``m``: texel ``(col, row)`` has its centre at board point ``(x0 + (col + ½)·m,
        y0 + (row + ½)·m)``, ``(x0, y0)`` from :func:`board_extent`.
    """
    BLACK, WHITE = BLACK_REFLECTANCE, WHITE_REFLECTANCE

    k = _kind(board)
    if k == "charuco":
        return board.texture(px_per_square)
    pps = px_per_square
    if isinstance(pps, bool) or not isinstance(pps, (int, np.integer)) or pps < 4:
        raise InputError(f"px_per_square: expected an integer >= 4, got {fmt_value(pps)}")
    pps = int(pps) + int(pps) % 2
    pitch = board_pitch(board)
    m = pitch / pps
    x0, y0, x1, y1 = board_extent(board)
    nx, ny = int(round((x1 - x0) / m)), int(round((y1 - y0) / m))
    # texel centres in units of the pitch, relative to the board origin
    u = (x0 / pitch + (np.arange(nx) + 0.5) / pps)
    v = (y0 / pitch + (np.arange(ny) + 0.5) / pps)
    if k == "chessboard":
        a = np.floor(u).astype(np.int64)
        b = np.floor(v).astype(np.int64)
        in_x = (a >= -1) & (a < board.cols)
        in_y = (b >= -1) & (b < board.rows)
        black = ((a[None, :] + b[:, None]) % 2 == 1) & in_x[None, :] & in_y[:, None]
        ink = black.astype(np.float32)
    else:
        ink = np.zeros((ny, nx), np.float32)
        nn = pitch / math.sqrt(2.0) if board.asymmetric else pitch
        r = CIRCLE_RADIUS_FRACTION * nn / m  # texels
        for cx, cy, _ in board.object_points():
            ci, cj = (cx - x0) / m - 0.5, (cy - y0) / m - 0.5  # centre, texel coordinates
            i0, i1 = max(int(ci - r - 2), 0), min(int(ci + r + 3), nx)
            j0, j1 = max(int(cj - r - 2), 0), min(int(cj + r + 3), ny)
            d = np.hypot(np.arange(i0, i1)[None, :] - ci, np.arange(j0, j1)[:, None] - cj)
            cover = np.clip(r - d + 0.5, 0.0, 1.0).astype(np.float32)
            np.maximum(ink[j0:j1, i0:i1], cover, out=ink[j0:j1, i0:i1])
    tex = np.float32(WHITE) - np.float32(WHITE - BLACK) * ink
    return tex.astype(np.float32), m


def board_to_dict(board) -> dict:
    """A board as ``board.json`` holds it (``docs/scan-format.md``, board kinds): a ChArUco
    board's :meth:`CharucoBoard.to_dict` (the version-1 file, no ``kind``); ``{"kind":
    "chessboard", "cols", "rows", "square_size"}`` or ``{"kind": "circles", "cols", "rows",
    "spacing", "asymmetric"}`` (lengths in metres). The scan loader reads each back."""
    k = _kind(board)
    if k == "charuco":
        return board.to_dict()
    if k == "chessboard":
        return {"kind": k, "cols": int(board.cols), "rows": int(board.rows),
                "square_size": float(board.square_size)}
    return {"kind": k, "cols": int(board.cols), "rows": int(board.rows),
            "spacing": float(board.spacing), "asymmetric": bool(board.asymmetric)}


def save_board(board, path) -> Path:
    """Write :func:`board_to_dict` to ``path`` as JSON, atomically. Returns the path."""
    path = Path(path)
    atomic_write_text(path, json.dumps(board_to_dict(board), indent=2, allow_nan=False) + "\n")
    return path
