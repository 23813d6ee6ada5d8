"""Board detection for calibration: ChArUco, plain chessboards and circle grids.

Every detector returns a :class:`BoardDetection` per image — found or not, with the reason when
not — so images without a board are listed, never silently dropped. Corners are sub-pixel:
ChArUco corners are refined by OpenCV's ``CharucoDetector`` (``cornerSubPix`` on the chessboard
saddle points), chessboards by ``findChessboardCornersSB`` (sub-pixel by construction), where
it finds none (``method="auto"``) or with ``method="classic"`` by ``findChessboardCorners`` +
``cornerSubPix`` (11 × 11 window, as OpenCV's calibration sample does), circle centres by
``findCirclesGrid``'s blob centroids.

Pixel convention: OpenCV's and facegeo's — integer coordinates are pixel centres.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import cv2
from typing import ClassVar

import numpy as np

from facegeo.checks import as_array, check_choice, check_positive, fmt_value
from facegeo.errors import InputError

log = logging.getLogger(__name__)

__all__ = [
    "BoardDetection",
    "ChessboardSpec",
    "CircleGridSpec",
    "detect_charuco",
    "detect_chessboard",
    "detect_circle_grid",
    "detect_board",
    "detect_boards",
    "charuco_reading",
    "usable_detections",
    "detection_report",
]

#: Fewest corners a view needs to constrain a pose and contribute to intrinsics.
MIN_CORNERS_PER_VIEW = 6


@dataclass(frozen=True)
class ChessboardSpec:
    """A plain chessboard: ``cols × rows`` inner corners, ``square_size`` metres apart.

    Board frame: origin at the first detected corner, x along a row (``cols`` direction), y along
    the columns, z = 0 on the board (OpenCV's calibration sample convention).
    """

    board_kind: ClassVar[str] = "chessboard"

    cols: int
    rows: int
    square_size: float

    def __post_init__(self):
        for name in ("cols", "rows"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 2:
                raise InputError(f"{name}: expected an integer >= 2 inner corners, got {fmt_value(v)}")
        check_positive(self.square_size, "square_size")

    def object_points(self) -> np.ndarray:
        """``(cols·rows, 3)`` float64, metres, board frame, x fastest (OpenCV's corner order)."""
        k = np.arange(self.cols * self.rows)
        s = float(self.square_size)
        return np.stack([(k % self.cols) * s, (k // self.cols) * s, np.zeros(k.size)], -1)


@dataclass(frozen=True)
class CircleGridSpec:
    """A circle grid of ``cols × rows`` circles, centres ``spacing`` metres apart.

    ``asymmetric=True`` is OpenCV's asymmetric grid (odd rows shifted by half a spacing; the
    object points follow OpenCV's sample: ``((2 j + i % 2)·s, i·s, 0)`` with ``spacing = 2 s``
    between circles of one row).
    """

    board_kind: ClassVar[str] = "circles"

    cols: int
    rows: int
    spacing: float
    asymmetric: bool = False

    def __post_init__(self):
        for name in ("cols", "rows"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 2:
                raise InputError(f"{name}: expected an integer >= 2 circles, got {fmt_value(v)}")
        check_positive(self.spacing, "spacing")

    def object_points(self) -> np.ndarray:
        """``(cols·rows, 3)`` float64, metres, board frame, in ``findCirclesGrid``'s order."""
        i, j = np.divmod(np.arange(self.cols * self.rows), self.cols)  # i row, j column
        s = float(self.spacing)
        if self.asymmetric:
            x = (2 * j + i % 2) * (s / 2.0)
            y = i * (s / 2.0)
        else:
            x, y = j * s, i * s
        return np.stack([x, y, np.zeros(x.size)], -1).astype(np.float64)


@dataclass
class BoardDetection:
    """What one image showed of a board.

    Attributes
    ----------
    name : str
        The image's label (file name or index).
    image_size : (int, int)
        ``(width, height)``, pixels.
    found : bool
        Enough corners were found to use the view (≥ :data:`MIN_CORNERS_PER_VIEW`).
    reason : str
        Empty when found; otherwise why the view is skipped.
    ids : (N,) int64
        Corner ids on the board (ChArUco ids; running index for chessboards and grids).
    p_board : (N, 3) float64, metres, board frame
        Object points of the detected corners.
    q : (N, 2) float64, pixels
        Sub-pixel image positions (x = column, y = row; integers are pixel centres).
    legacy : bool or None
        ChArUco: the pattern reading used (OpenCV's legacy pattern or not); None for the
        other kinds.
    refinement : {"encoded", "linear"} or None
        Chessboard: the values its corners were refined on (:func:`detect_chessboard`'s
        ``linearize``) — the stored pixel values or linear light; None for the other kinds.
    """

    name: str
    image_size: tuple[int, int]
    found: bool
    reason: str = ""
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    p_board: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    q: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    legacy: bool | None = None
    refinement: str | None = None

    @property
    def n_corners(self) -> int:
        """Number of corners detected."""
        return int(self.q.shape[0])


def _gray8(image, name: str) -> np.ndarray:
    """An 8-bit single-channel view of ``image`` (uint8/uint16/float in [0, 1]; RGB → luma)."""
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = a[..., :3]
        if a.dtype == np.uint8:
            a = cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2GRAY)
        else:
            a = a.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    elif a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim != 2:
        raise InputError(f"{name}: expected an (H, W) or (H, W, 3) image, got shape {a.shape}")
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a)
    if a.dtype == np.uint16:
        return (a >> 8).astype(np.uint8)
    if a.dtype.kind == "f":
        f = np.nan_to_num(a.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0)
        return np.clip(np.rint(f * 255.0), 0, 255).astype(np.uint8)
    raise InputError(f"{name}: unsupported image dtype {a.dtype} (use uint8, uint16 or float)")


def _result(name, size, ids, p_board, q, *, min_corners: int, what: str) -> BoardDetection:
    n = 0 if q is None else len(q)
    if n < min_corners:
        return BoardDetection(
            name, size, False, f"{what}: {n} corner(s) found, need at least {min_corners}"
        )
    return BoardDetection(
        name, size, True, "", np.asarray(ids, np.int64), np.asarray(p_board, np.float64),
        np.asarray(q, np.float64).reshape(-1, 2),
    )


def detect_charuco(image, board, *, name: str = "image", legacy: bool | None = None,
                   min_corners: int = MIN_CORNERS_PER_VIEW) -> BoardDetection:
    """Detect a ChArUco board with OpenCV ≥ 4.7's ``cv2.aruco.CharucoDetector``.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array, uint8, uint16 or float in [0, 1]
        RGB channel order for colour images.
    board : facegeo.geometry.board.CharucoBoard
    name : str, optional
        Label used in the report.
    legacy : bool or None, optional
        ``CharucoBoard.setLegacyPattern(True)``: boards printed by OpenCV < 4.6 with an even
        number of rows start with a white square. None (default): the board's own
        :attr:`~facegeo.geometry.board.CharucoBoard.legacy` (the new pattern when the board
        does not declare it; :func:`detect_boards` reads an undeclared set both ways).
    min_corners : int, optional

    Returns
    -------
    BoardDetection
        ``p_board`` from ``board.chessboard_corners()[ids]`` (float64, exact, not OpenCV's
        float32 copy).
    """
    g = _gray8(image, name)
    size = (g.shape[1], g.shape[0])
    use = bool(board.legacy if legacy is None else legacy)
    cvb = board.to_cv2()
    cvb.setLegacyPattern(use)
    det = cv2.aruco.CharucoDetector(cvb)
    corners, ids, marker_corners, marker_ids = det.detectBoard(g)
    if marker_ids is None or len(marker_ids) == 0:
        return BoardDetection(
            name, size, False,
            f"no ArUco markers of {board.dictionary} found (wrong dictionary or board, or no "
            "board in view)",
        )
    if ids is None or corners is None or len(ids) == 0:  # OpenCV 5.1: empty arrays, not None
        return BoardDetection(
            name, size, False,
            f"{len(marker_ids)} marker(s) found but no ChArUco corners interpolated (check "
            "squares_x/squares_y and legacy pattern)",
        )
    ids = ids.ravel().astype(np.int64)
    if ids.max() >= board.n_corners:
        return BoardDetection(name, size, False, "corner ids exceed the board definition")
    p_board = board.chessboard_corners()[ids]
    return replace(_result(name, size, ids, p_board, corners.reshape(-1, 2),
                           min_corners=min_corners, what="ChArUco"), legacy=use)


def detect_chessboard(image, spec: ChessboardSpec, *, name: str = "image",
                      method: str = "auto", linearize=None) -> BoardDetection:
    """Detect a plain chessboard (all corners or none).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
    spec : ChessboardSpec
    method : {"auto", "sb", "classic"}
        ``"sb"``: ``cv2.findChessboardCornersSB`` (sector-based, sub-pixel accurate, with
        ``CALIB_CB_EXHAUSTIVE | CALIB_CB_ACCURACY``); ``"classic"``: ``findChessboardCorners``
        then ``cornerSubPix`` with an 11 × 11 window (OpenCV's calibration sample);
        ``"auto"`` (default): ``"sb"``, its corners refined by ``cornerSubPix`` (the window
        below; against the true corners of the generator's 240 × 360 px projector views,
        34 images: median 0.05 px RMS, worst 0.14, where the sector detector's own were at
        0.08–0.09, worst 0.23; kept unrefined if the refinement fails the check below), and
        where it finds no board the classic detector's
        corners **in the sector detector's order**: the first inner square light
        (:func:`_light_square_first`). The two detectors number a board from opposite ends
        (on all 26 of OpenCV's 9 × 6 stereo images both detect, the classic order is the sector
        one reversed, to ≤ 4 px; the sector detector's first square is the light one on all
        26, the classic's the dark one), and one view whose corners run the other way breaks a
        rig calibration (OpenCV's ``left05.jpg``, which only the classic detector finds: the
        stereo RMS went from 0.26 to 15.9 px with it unreordered, 0.25 px reordered). A board
        whose two ends look alike (an even number of inner squares along its diagonal) cannot
        be ordered that way: there the fallback is not used. ``"auto"`` also checks each
        result's corners against their board neighbours (:func:`_grid_deviation`): a corner
        farther than ``max(GRID_CHECK_PX, GRID_CHECK_FRACTION · spacing)`` from where the
        local homography of its neighbours puts it makes the result inconsistent, and the next
        detector is tried (or the view is reported not found). On small, strongly tilted
        squares (the generator's 240 × 360 px views, squares 9–25 px, tilts 45–60°) the
        sector
        detector put 5 of 32 views 0.18–2.3 px RMS from the truth (one corner 9.7 px off),
        where the classic one with its adapted window was within 0.04–0.10 px on all.

        The classic detector's ``cornerSubPix`` window is OpenCV's sample's 11-pixel
        half-size, capped at 0.6 × the smallest corner spacing so it never reaches the next
        corner (an 11-pixel half-window over 10-pixel squares pulled the corners 2–6 px RMS;
        capped: 0.04–0.08 px). OpenCV's own 9 × 6 sample boards, ≥ 18.9 px apart, keep 11.

    linearize : callable, optional
        Stored pixel values → linear light (the capture's response, e.g.
        :meth:`facegeo.capture.response.Response.linearize`). Given, the sub-pixel refinement
        (``cornerSubPix``, both paths) runs on the image's linear luminance; the board is still
        found on the 8-bit image. A corner's gradient-orthogonality condition holds for any
        monotonic encoding of an ideal step, but not of a blurred one: the pixels across an
        edge average light (the lens, the sensor's area), and the sRGB curve bends that ramp
        asymmetrically, pulling the saddle point. On the generator's procam chessboards
        (8-bit sRGB, 240 × 360 px, squares 9–25 px, ``tests/test_projector_plain_board.py``
        seeds 0–2) the corners' RMS about the true camera's best pose drops from 0.071 / 0.064
        / 0.061 px to 0.055 / 0.057 / 0.057 px (camera views). On OpenCV's stereo JPEGs
        (declared sRGB) it raises the calibration RMS by 10 %: :func:`detect_boards` decides
        per camera. None (default): refined on the 8-bit values, as before.

    Returns
    -------
    BoardDetection
        ``refinement`` is ``"linear"`` with ``linearize``, else ``"encoded"``.
    """
    return _chessboard_readings(image, spec, name, method, [linearize])[0]


def _linear_gray(image, linearize, name: str) -> np.ndarray:
    """``(H, W)`` float32 linear luminance of ``image`` through ``linearize`` (the weights of
    :func:`_gray8`)."""
    a = np.asarray(linearize(image), np.float32)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = a[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32)
    elif a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim != 2:
        raise InputError(f"{name}: expected an (H, W) or (H, W, 3) image, got shape {a.shape}")
    return np.ascontiguousarray(np.nan_to_num(a, nan=0.0, posinf=1.0, neginf=0.0))


def _find_chessboard(g: np.ndarray, spec: ChessboardSpec, name: str,
                     method: str) -> BoardDetection:
    """The chessboard's corners as ``method`` finds them on the 8-bit image ``g``: the sector
    detector's own (``"sb"``), the classic detector's before ``cornerSubPix``
    (``"classic"``)."""
    size = (g.shape[1], g.shape[0])
    pattern = (int(spec.cols), int(spec.rows))
    if method == "sb":
        ok, corners = cv2.findChessboardCornersSB(
            g, pattern, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        )
    else:
        ok, corners = cv2.findChessboardCorners(
            g, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        )
    if not ok or corners is None:
        return BoardDetection(
            name, size, False,
            f"no {spec.cols}×{spec.rows} chessboard found (check the inner-corner counts)",
        )
    n = spec.cols * spec.rows
    return _result(name, size, np.arange(n), spec.object_points(), corners.reshape(-1, 2),
                   min_corners=1, what="chessboard")


def _chessboard_readings(image, spec: ChessboardSpec, name: str, method: str,
                         linearizers) -> list[BoardDetection]:
    """:func:`detect_chessboard` once per entry of ``linearizers`` (None: refined on the
    8-bit values; a callable: on the linear luminance), the board found once."""
    check_choice(method, "method", ("auto", "sb", "classic"))
    g = _gray8(image, name)
    size = (g.shape[1], g.shape[0])
    subs = [(g, "encoded") if f is None else (_linear_gray(image, f, name), "linear")
            for f in linearizers]
    if method != "auto":
        raw = _find_chessboard(g, spec, name, method)
        if not raw.found or method == "sb":
            return [replace(raw, refinement=how) for _, how in subs]
        return [replace(raw, q=_corner_subpix(sub, raw.q, spec).reshape(-1, 2)
                        .astype(np.float64), refinement=how) for sub, how in subs]
    what = f"{spec.cols}×{spec.rows} chessboard"
    got = _find_chessboard(g, spec, name, "sb")
    classic = []  # the classic detector's corners, found once if needed

    def auto(sub, how) -> BoardDetection:
        if got.found:
            ref = _refined(sub, got, spec)
            if not _inconsistent(ref, what):
                return replace(ref, refinement=how)
        why_got = _inconsistent(got, what)
        if got.found and not why_got:
            return replace(got, refinement=how)
        if (spec.cols + spec.rows) % 2 == 0 or spec.cols < 3:
            # ends alike / too narrow to tell the order: no fallback
            return got if not got.found else BoardDetection(name, size, False, why_got)
        if not classic:
            classic.append(_find_chessboard(g, spec, name, "classic"))
        alt, why = classic[0], why_got
        if alt.found:
            q = _corner_subpix(sub, alt.q, spec).reshape(-1, 2).astype(np.float64)
            q = _light_square_first(g, q, int(spec.cols))
            alt = _result(name, size, alt.ids, alt.p_board, q, min_corners=1,
                          what="chessboard")
            why_alt = _inconsistent(alt, what)
            if not why_alt:
                return replace(alt, refinement=how)
            why = why or why_alt
        if got.found or alt.found:
            return BoardDetection(name, size, False, why)
        return got

    return [auto(sub, how) for sub, how in subs]


#: A chessboard corner this far (pixels) from where its grid neighbours put it is an error
#: of the detector (:func:`_grid_deviation`) ...
GRID_CHECK_PX = 1.0
#: ... or this fraction of the corner spacing, whichever is larger. (OpenCV's 640 × 480 sample
#: chessboards, squares 19–37 px: correct corners up to 1.6 px off; the detector errors this
#: catches on the generator's small squares: 1.5–6.5 px.)
GRID_CHECK_FRACTION = 0.1


def _corner_subpix(g: np.ndarray, corners: np.ndarray, spec: ChessboardSpec,
                   fraction: float = 0.6) -> np.ndarray:
    """``cv2.cornerSubPix`` (30 iterations or 0.01 px) in OpenCV's sample's 11-pixel
    half-window, capped at ``fraction`` × the smallest corner spacing, on ``g`` (8-bit, or
    float32 linear luminance). Returns (N, 1, 2) float32."""
    c = np.ascontiguousarray(np.asarray(corners, np.float32).reshape(-1, 1, 2))
    sp = _corner_spacing(c.reshape(-1, 2), int(spec.cols), int(spec.rows))
    w = int(max(2, min(11, fraction * sp)))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    return cv2.cornerSubPix(g, c, (w, w), (-1, -1), crit)


#: Half-window of the refinement of the sector detector's corners, fraction of the smallest
#: corner spacing (capped at 11 px). 0.45 let one corner of OpenCV's ``right01.jpg`` jump
#: 4–5 px to a neighbouring edge; at 0.35 they move ≤ 1.6 px on all 25 images, as far as the
#: two detectors disagree there.
REFINE_FRACTION = 0.35


def _refined(g: np.ndarray, det: BoardDetection, spec: ChessboardSpec) -> BoardDetection:
    """``det`` with its corners refined by :func:`_corner_subpix` (:data:`REFINE_FRACTION`)."""
    q = _corner_subpix(g, det.q, spec, REFINE_FRACTION).reshape(-1, 2).astype(np.float64)
    return BoardDetection(det.name, det.image_size, True, "", det.ids, det.p_board, q)


def _corner_spacing(q: np.ndarray, cols: int, rows: int) -> float:
    """Smallest distance between neighbouring corners of a row-major ``cols × rows`` grid."""
    G = q.reshape(rows, cols, 2)
    d = [np.linalg.norm(np.diff(G, axis=a), axis=-1).min() for a in (0, 1) if G.shape[a] > 1]
    return float(min(d))


def _grid_deviation(q: np.ndarray, p_board: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per detected point, pixels between it and where the homography fitted to its board
    neighbours puts it, and the image distance to its nearest neighbour.

    Neighbours: the points within 2.9 nearest-neighbour distances on the board (two grid
    steps of a chessboard, diagonals included), the point itself left out. A plane's points
    map by a homography locally even through lens distortion, so a correct detection deviates
    by its noise only; a corner on the wrong saddle point, or a circle whose centroid the image
    border cut, by much more.

    Returns
    -------
    dev : (N,) float64, pixels
    spacing : (N,) float64, pixels
    """
    xy = np.asarray(p_board, np.float64)[:, :2]
    d = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    nn = float(d.min())
    dq = np.linalg.norm(q[:, None] - q[None], axis=-1)
    np.fill_diagonal(dq, np.inf)
    spacing = dq.min(axis=1)
    dev = np.zeros(len(q))
    for i in range(len(q)):  # one small fit per point (≤ a few hundred)
        near = np.flatnonzero(d[i] <= 2.9 * nn)
        if near.size < 4:
            continue
        H, _ = cv2.findHomography(xy[near], q[near], 0)
        if H is None:
            dev[i] = np.inf
            continue
        p = H @ np.array([xy[i, 0], xy[i, 1], 1.0])
        dev[i] = np.hypot(p[0] / p[2] - q[i, 0], p[1] / p[2] - q[i, 1])
    return dev, spacing


def _inconsistent(det: BoardDetection, what: str) -> str:
    """Why a found board's points are not a plane's grid (:func:`_grid_deviation`; empty when
    they are, or when nothing was found)."""
    if not det.found:
        return ""
    dev, spacing = _grid_deviation(det.q, det.p_board)
    lim = np.maximum(GRID_CHECK_PX, GRID_CHECK_FRACTION * spacing)
    k = int(np.argmax(dev / lim))
    if dev[k] <= lim[k]:
        return ""
    return (f"{what} found but point {k} is {dev[k]:.2g} px from where its neighbours put it "
            f"(limit {lim[k]:.2g} px): a detector error")


def _at_border(det: BoardDetection) -> str:
    """Why a found circle grid touches the image border (empty when it does not): a centre
    closer to it than 0.4 × its nearest neighbour's distance may be a cut circle's centroid."""
    if not det.found:
        return ""
    q = det.q
    dq = np.linalg.norm(q[:, None] - q[None], axis=-1)
    np.fill_diagonal(dq, np.inf)
    W, H = det.image_size
    gap = np.minimum(np.minimum(q[:, 0] + 0.5, W - 0.5 - q[:, 0]),
                     np.minimum(q[:, 1] + 0.5, H - 0.5 - q[:, 1]))
    bad = gap < 0.4 * dq.min(axis=1)
    if not bad.any():
        return ""
    return (f"circle {int(np.flatnonzero(bad)[0])} is {gap[bad][0]:.2g} px from the image "
            "border: it may be cut")


def _light_square_first(g: np.ndarray, q: np.ndarray, cols: int) -> np.ndarray:
    """Chessboard corners ``q`` (row-major, ``cols`` per row) in the order whose first inner
    square — between corners 0, 1, ``cols``, ``cols + 1`` — is the light one (the sector
    detector's order): reversed when it is darker than its neighbour along the row. For a
    board with an odd number of inner squares along the diagonal (``cols + rows`` odd) the two
    ends differ in colour, so this tells the two orders apart."""
    def square(k: int) -> float:  # mean grey over a 3 × 3 patch at inner square k's centre
        c = (q[k] + q[k + 1] + q[cols + k] + q[cols + k + 1]) / 4.0
        x, y = (int(round(v)) for v in c)
        return float(g[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2].mean())

    return q[::-1].copy() if square(0) < square(1) else q


def _relaxed_blob_detector(size):
    """``cv2.SimpleBlobDetector`` for small or strongly foreshortened circles: OpenCV's
    defaults need ≥ 25 px² blobs, 10 px apart, circularity ≥ 0.8 (a circle seen at more than
    ≈ 55° from its normal falls below it)."""
    p = cv2.SimpleBlobDetector_Params()
    p.minArea = 4.0
    p.maxArea = float(size[0] * size[1]) / 4.0
    p.minDistBetweenBlobs = 2.0
    p.minCircularity = 0.5
    return cv2.SimpleBlobDetector_create(p)


def detect_circle_grid(image, spec: CircleGridSpec, *, name: str = "image") -> BoardDetection:
    """Detect a circle grid with ``cv2.findCirclesGrid`` (dark circles on a light board).

    OpenCV's defaults first; where they find no grid, ``CALIB_CB_CLUSTERING`` (its grid search
    for strong perspective), then both again with a blob detector that accepts blobs of
    ≥ 4 px², 2 px apart and circularity ≥ 0.5 (small circles, circles seen obliquely). On the
    generator's 240 × 360 px camera views of a 4 × 11 grid tilted 45–60° (circles 6–14 px
    across), the defaults found 19 of the 32 images with a whole grid, the fallbacks 12 more;
    every grid found is numbered as the object points (PnP with the true camera: 0.009–0.19 px
    RMS). A grid with a centre nearer the image border than 0.4 × its spacing (a circle the
    border may cut: its centroid is not its centre) or off the local homography of its
    neighbours (as for chessboards, :func:`detect_chessboard`) is not accepted, and the next
    search is tried.

    Returns
    -------
    BoardDetection
    """
    g = _gray8(image, name)
    size = (g.shape[1], g.shape[0])
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if spec.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    pattern = (int(spec.cols), int(spec.rows))
    kind = "asymmetric" if spec.asymmetric else "symmetric"
    n = spec.cols * spec.rows
    why = ""
    for extra, relaxed in ((0, False), (cv2.CALIB_CB_CLUSTERING, False),
                           (cv2.CALIB_CB_CLUSTERING, True), (0, True)):
        kw = {"blobDetector": _relaxed_blob_detector(size)} if relaxed else {}
        ok, centres = cv2.findCirclesGrid(g, pattern, flags=flags | extra, **kw)
        if not ok or centres is None:
            continue
        det = _result(name, size, np.arange(n), spec.object_points(), centres.reshape(-1, 2),
                      min_corners=1, what="circle grid")
        bad = _at_border(det) or _inconsistent(det, f"{spec.cols}×{spec.rows} {kind} circle grid")
        if not bad:
            return det
        why = why or bad
    return BoardDetection(name, size, False,
                          why or f"no {spec.cols}×{spec.rows} {kind} circle grid found")


def charuco_reading(board, legacy: bool | None = None) -> bool | None:
    """The ChArUco pattern to read ``board`` with: ``legacy`` when given, else the board's
    declaration; None when neither says and the two patterns differ (an even row count:
    :attr:`~facegeo.geometry.board.CharucoBoard.legacy_matters`) — read both ways
    (:func:`detect_boards`); False for an odd row count (the same board either way)."""
    if legacy is not None:
        return bool(legacy)
    if board.legacy is not None:
        return board.legacy
    return None if board.legacy_matters else False


def detect_boards(images, board, *, names=None, legacy: bool | None = None,
                  method: str = "auto", linearize=None) -> list[BoardDetection]:
    """Detect a board in every image of one camera.

    A ChArUco board with an even row count whose pattern is declared neither by ``legacy`` nor
    by the board (:func:`charuco_reading` None) is read both ways — OpenCV's new pattern and
    its legacy one (OpenCV < 4.6) — and the reading that finds more corners over the images is
    kept (the new pattern on a tie); each detection's ``legacy`` says which. A wrong reading
    finds the markers but interpolates few or no corners (the squares' colours are swapped),
    so the counts are far apart on a real set.

    Parameters
    ----------
    images : sequence of arrays
        One camera's views, all the same size.
    board : CharucoBoard, ChessboardSpec or CircleGridSpec
    names : sequence of str, optional
        Labels for the report (default ``"view_000"``…).
    legacy : bool or None
        ChArUco pattern (:func:`detect_charuco`); None: the board's, else both readings.
    method
        Passed to :func:`detect_chessboard`.
    linearize : callable, optional
        A chessboard's images → linear light (the capture's response). Given, every image's
        corners are refined both on the stored values and in linear light
        (:func:`detect_chessboard`), and the refinement whose corners fit the local homography
        of their board neighbours better over the camera's views (RMS of
        :func:`_grid_deviation` over the views found both ways; the stored values on a tie) is
        kept for all of them: each detection's ``refinement`` says which. A wrong tone curve
        (a JPEG sharpened after its curve, a response that is not the declared one) bends the
        edges the other way, and the check sees it: on the generator's 8-bit sRGB chessboards
        the linear corners deviate 0.059–0.077 px RMS against 0.080–0.094 px on the stored
        values (procam seeds 0–2, each camera's own views), on OpenCV's stereo JPEGs 0.525 /
        0.651 px against 0.508 / 0.634 px (left / right; mostly their lens distortion, alike
        both ways), and the cameras' calibration RMS moves the same way (synthetic 0.061–0.074
        → 0.049–0.060 px; OpenCV's 0.177 / 0.187 → 0.197 / 0.209 px). Other board kinds
        ignore it.

    Returns
    -------
    list of BoardDetection
        One per image, in order (found or not).

    Raises
    ------
    InputError
        Images of different sizes (the message names the first odd one).
    """
    images = list(images)
    names = [f"view_{i:03d}" for i in range(len(images))] if names is None else list(names)
    if len(names) != len(images):
        raise InputError(f"names: {len(names)} labels for {len(images)} images")
    size0 = None
    for img, nm in zip(images, names):
        shape = np.shape(img)
        size = (shape[1], shape[0]) if len(shape) >= 2 else None
        if size0 is None:
            size0 = size
        elif size != size0:
            raise InputError(
                f"images: {nm} is {size[0]}×{size[1]} px but {names[0]} is {size0[0]}×"
                f"{size0[1]} px; one camera's calibration views must share one image size"
            )
    reading = (charuco_reading(board, legacy) if getattr(board, "board_kind", None) == "charuco"
               else False)
    readings = (False, True) if reading is None else (reading,)
    if isinstance(board, ChessboardSpec) and linearize is not None:
        return _better_refinement(images, board, names, method, linearize)
    out: dict = {r: [] for r in readings}
    for img, nm in zip(images, names):
        for r in readings:
            out[r].append(detect_board(img, board, name=nm, legacy=r, method=method))
    if len(readings) == 1:
        return out[readings[0]]
    n = {r: sum(d.n_corners for d in out[r] if d.found) for r in readings}
    best = True if n[True] > n[False] else False
    log.info("ChArUco %d×%d board, pattern not declared: read as %s (%d corners; the other "
             "pattern %d)", board.squares_x, board.squares_y,
             "OpenCV's legacy pattern" if best else "the new pattern", n[best], n[not best])
    return out[best]


def _better_refinement(images, board, names, method, linearize) -> list[BoardDetection]:
    """:func:`detect_boards` of a chessboard with ``linearize``: both refinements of every
    image, the one whose corners fit their neighbours better over the views found both ways
    (RMS of :func:`_grid_deviation`; the stored values on a tie)."""
    both = [_chessboard_readings(img, board, nm, method, [None, linearize])
            for img, nm in zip(images, names)]
    dev = [[], []]
    for pair in both:
        if pair[0].found and pair[1].found:
            for k in (0, 1):
                dev[k].append(_grid_deviation(pair[k].q, pair[k].p_board)[0])
    rms = [float(np.sqrt(np.mean(np.concatenate(d) ** 2))) if d else np.inf for d in dev]
    k = 1 if rms[1] < rms[0] else 0
    log.info("chessboard corners refined on %s (their board neighbours' local homographies: "
             "%.4g px RMS, %s %.4g px)", ("the stored values", "linear light")[k], rms[k],
             ("linear light", "the stored values")[k], rms[1 - k])
    return [pair[k] for pair in both]


def detect_board(image, board, *, name: str = "image", legacy: bool | None = None,
                 method: str = "auto", linearize=None) -> BoardDetection:
    """Detect a board of any kind in one image: :func:`detect_charuco`,
    :func:`detect_chessboard` or :func:`detect_circle_grid` by the type of ``board``.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array, uint8, uint16 or float in [0, 1]
    board : CharucoBoard, ChessboardSpec or CircleGridSpec
    name : str
        Label of the image in the detection's ``reason`` and report.
    legacy, method
        Passed to :func:`detect_charuco` / :func:`detect_chessboard`.
    linearize : callable, optional
        Passed to :func:`detect_chessboard` (other kinds ignore it).

    Returns
    -------
    BoardDetection

    Raises
    ------
    InputError
        ``board`` is none of the three kinds.
    """
    if isinstance(board, ChessboardSpec):
        return detect_chessboard(image, board, name=name, method=method, linearize=linearize)
    if isinstance(board, CircleGridSpec):
        return detect_circle_grid(image, board, name=name)
    if hasattr(board, "to_cv2") and hasattr(board, "chessboard_corners"):
        return detect_charuco(image, board, name=name, legacy=legacy)
    raise InputError(
        "board: expected a CharucoBoard, ChessboardSpec or CircleGridSpec, got "
        f"{type(board).__name__}"
    )


def detection_report(detections) -> list[dict]:
    """The per-image report: ``[{"name", "found", "corners", "reason"}, ...]`` (JSON-ready)."""
    return [
        {"name": d.name, "found": bool(d.found), "corners": d.n_corners, "reason": d.reason}
        for d in detections
    ]


def usable_detections(detections, *, min_views: int = 3, what: str = "camera"):
    """The found views, or an error listing why each image was skipped.

    Returns
    -------
    list of BoardDetection
        Only the found ones, in order.

    Raises
    ------
    InputError
        Fewer than ``min_views`` views have a board; the message lists every skipped image and
        its reason.
    """
    found = [d for d in detections if d.found]
    if len(found) < min_views:
        skipped = "; ".join(f"{d.name}: {d.reason}" for d in detections if not d.found)
        raise InputError(
            f"{what}: only {len(found)} of {len(detections)} images have a usable board, need "
            f"at least {min_views}" + (f" (skipped — {skipped})" if skipped else "")
        )
    return found


def as_corner_lists(p_board_list, q_list):
    """Validate corner lists: per view ``(N_i, 3)`` object points and ``(N_i, 2)`` pixels."""
    if len(p_board_list) != len(q_list):
        raise InputError(
            f"object_points/image_points: {len(p_board_list)} views of object points but "
            f"{len(q_list)} of image points"
        )
    P, Q = [], []
    for i, (p, q) in enumerate(zip(p_board_list, q_list)):
        p = as_array(p, f"object_points[{i}]", shape=(None, 3))
        q = as_array(q, f"image_points[{i}]", shape=(None, 2))
        if p.shape[0] != q.shape[0]:
            raise InputError(
                f"view {i}: {p.shape[0]} object points but {q.shape[0]} image points"
            )
        P.append(p)
        Q.append(q)
    return P, Q
