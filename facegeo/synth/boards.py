"""Board poses a rig can be calibrated from: strong tilts, image-filling views, shared views.

A narrow-field camera (the default rig's: ≈ 12° × 19°) calibrated from boards tilted ≤ 35° and
centred in the image cannot separate its principal point from the pose and the decentering
distortion: the small scan's ``cam_left`` came out 48 px off with a reported σ(cx) of 11 px.
What constrains the model (Zhang 2000 §5; mrcal's "how to calibrate": tilted boards, close,
covering the image) is

* **tilt**: each view tilts the board 45–60° from the target camera's optical axis, about an
  in-plane axis whose direction is stratified over the views (so the tilt axes cover every
  direction, and both focal lengths and both principal-point coordinates are seen through
  perspective);
* **coverage**: each view's board fills a large fraction of the image and is pushed toward one
  of the image corners in turn (and the centre), so the union of the views reaches every corner
  of the image, where the distortion terms are largest;
* **shared views**: a camera-targeted view need not be seen by the other cameras; every
  ``shared_every``-th view (and every view when ``shared_every=1``, as for the projector views,
  which must be seen by the cameras and the projector at once) keeps the whole board inside
  every camera, so the rig's bundle adjustment connects the cameras.

Measured on the default rig's narrow cameras (exact corners + 0.15 px noise, pinhole model,
30 views): what pins the principal point is how much of the image each view covers — σ(c)
falls ≈ 1/fill² (σ(cx) 47 / 11 / 4.4 px at fill 0.3 / 0.6 / 0.95) — and the corners per view
(√N), not the tilt (30–82° give the same σ(c) at equal fill). Shared views cannot be close (the
cameras' fields overlap only near the head), so :func:`rig_calibration_views` (the synthetic
capture's camera views) adds close views per camera (:data:`CLOSE_VIEWS`) to the shared ones,
and :func:`board_for_cameras` makes the board as tall as a portrait image allows.

:func:`calibration_board_poses` returns world poses ``T_world_board`` (board frame →
world), the convention of ``facegeo.synth.capture``'s ``_board_poses``; render a view with
``board.render(cam, cam.T_cam_world @ T_world_board)``.
"""

from __future__ import annotations

import math

import numpy as np

from facegeo.checks import check_positive, fmt_value
from facegeo.errors import InputError
from facegeo.frames import Pose, rotation_from_rvec
from facegeo.geometry.camera import Camera

__all__ = ["BOARD_KINDS", "CLOSE_VIEWS", "CORNER_CELL", "CORNER_TRIES", "CORNER_VIEWS",
           "board_coverage",
           "board_for_cameras",
           "calibration_board_poses", "rig_calibration_views"]

#: Image anchors cycled through by the views of one camera: the four corners, then the centre
#: (fractions of the free image span: −1 / +1 push the board's box against that side).
_ANCHORS = ((-1.0, -1.0), (1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (0.0, 0.0))


#: A corner view puts a board corner within this fraction of the image size (per axis) from
#: the image corner, when it can within :data:`CORNER_TRIES` draws.
CORNER_CELL = 0.3
CORNER_TRIES = 300

#: Settings of the close views :func:`rig_calibration_views` adds per camera: boards close
#: enough to fill 85–95 % of that camera's image (≈ 0.6–0.8 m for the default rig's board),
#: tilted 30–50°. On a narrow camera (12° × 19°) a principal-point error is almost a per-view
#: rotation of the board; what separates the two is image coverage (module docstring). Fill
#: 0.9–0.98 pins c no better (σ(c) within 10 %) and takes 5–25× the time to place.
CLOSE_VIEWS = {"fill": (0.85, 0.95), "tilt_deg": (30.0, 50.0)}

#: Settings of the corner views :func:`rig_calibration_views` adds per camera with
#: ``corner_per_camera``: boards spanning 30–50 % of the image, tilted 20–45°, each pushed into
#: one image corner in turn until a board corner lies within ``corner_cell`` (10 %) of the image
#: size from it (within 3000 draws: 300 left one corner of four at 14–20 %; ≈ 0.4 s per view). A board that fills the image keeps its inner corners a square away from the
#: image's edges; these reach the image's corners, where the radial terms are largest.
#: Measured on the test rig (240 × 360 px cameras, 12 shared views, seeds 0/1): inner corners
#: in 36–45 % of a 16 × 16 grid of the image without them, 56–63 % with 4 per camera, 60–70 %
#: with 8 (``tests/test_calib_views.py``).
CORNER_VIEWS = {"fill": (0.3, 0.5), "tilt_deg": (20.0, 45.0), "corner_cell": 0.1,
                "corner_tries": 3000}

#: The image corners, the anchors of the corner views.
_CORNER_ANCHORS = _ANCHORS[:4]


def _range(r, name, lo, hi):
    try:
        a, b = (float(v) for v in r)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected (low, high), got {fmt_value(r)}") from None
    if not (lo <= a <= b <= hi):
        raise InputError(f"{name}: expected (low, high) with {lo} <= low <= high <= {hi}, got "
                         f"{fmt_value(r)}")
    return a, b


def _inside(cam: Camera, p_cam: np.ndarray, margin_px: float, cos_max: float, normal_cam):
    """Whole outline in front, inside the image with ``margin_px``, printed face seen at less
    than the maximum view angle everywhere."""
    q, front = cam.project_cam(p_cam)
    if not front.all() or not np.all(np.isfinite(q)):
        return False, q
    lo = -0.5 + margin_px
    if (q < lo).any() or (q[:, 0] > cam.width - 0.5 - margin_px).any() or (
            q[:, 1] > cam.height - 0.5 - margin_px).any():
        return False, q
    # printed face looks toward board −z: the view direction p/|p| must be along +normal
    cos_view = (p_cam @ normal_cam) / np.linalg.norm(p_cam, axis=-1)
    return bool(np.all(cos_view >= cos_max)), q


def calibration_board_poses(board, cameras, n: int, rng, *, shared_every: int = 3,
                            tilt_deg=(45.0, 60.0), fill=(0.6, 0.85), roll_deg=(-30.0, 30.0),
                            margin_px: float = 2.0, max_view_angle_deg: float = 75.0,
                            max_tries: int = 4000, also_seen_by=(),
                            corner_cell: float = CORNER_CELL, corner_tries: int = CORNER_TRIES,
                            anchors=None) -> list[Pose]:
    """World poses of a calibration board that constrain every camera's intrinsics.

    View k targets camera ``cameras[k mod C]`` (C cameras): the board is tilted by an angle drawn
    from ``tilt_deg`` about an in-plane axis at azimuth ``2π(j + u)/m`` in that camera's image
    (j: the view's index among the camera's m views, u uniform), rolled by ``roll_deg``, and
    placed at the distance where its projected box spans a fraction drawn from ``fill`` of the
    image (the larger of width and height fractions), pushed toward image anchor
    ``j mod 5`` (the four corners — where a board corner must land within :data:`CORNER_CELL`
    of the image size from the image corner — then the centre; shared views of several cameras: near the
    centre, where the cameras' views overlap, and targeting only the cameras whose field of
    view is within 1.5× the narrowest, so a projector's wide field does not set the size). A
    draw is kept when the whole board is
    inside the target camera's image with ``margin_px`` to spare, in front of it, and its printed
    face is seen at less than ``max_view_angle_deg`` everywhere; a *shared* view (every
    ``shared_every``-th, starting with view 0; ``shared_every=1``: all; 0: none) must satisfy
    this in every camera. Where a shared view cannot be placed in half of ``max_tries`` draws, its tilt
    and fill are scaled down gradually over the remaining draws (to half the drawn values at
    most). Every view must also satisfy it in each of ``also_seen_by`` (a projector whose
    calibration views need not be shared by every camera: one camera and the projector).

    ``corner_cell`` (default :data:`CORNER_CELL`) sets how close to its image corner a corner
    view's nearest board corner must come, in its first ``corner_tries`` draws (default
    :data:`CORNER_TRIES`; then anywhere); ``anchors`` (default: the four image corners, then
    the centre) the image anchors the views of one camera cycle through, ``(ax, ay)`` in
    ``[−1, 1]``.

    Parameters
    ----------
    board : CharucoBoard, ChessboardSpec or CircleGridSpec
    cameras : sequence of Camera
        Cameras (a projector too: it is an inverse camera) in the world frame.
    n : int
        Number of views.
    rng : numpy.random.Generator or int
    shared_every : int
        Every this many views is seen whole by every camera (1: every view; 0: none).
    tilt_deg, fill, roll_deg : (float, float)
        Ranges, degrees / fraction of the image.
    margin_px : float
        Pixels kept between the board's outline and the image border.
    max_view_angle_deg : float
        Largest angle between a viewing ray and the board normal.
    max_tries : int
        Draws per view before relaxing (shared views) or giving up.
    also_seen_by : sequence of Camera
        Cameras (a projector) that must see every view whole too, never targeted.

    Returns
    -------
    list of Pose
        ``T_world_board`` per view.

    Raises
    ------
    InputError
        Bad arguments, or a view that cannot be placed (the message names the camera and the
        constraint to relax).
    """
    cams = list(cameras)
    if not cams or not all(isinstance(c, Camera) for c in cams):
        raise InputError("cameras: expected a non-empty sequence of Camera")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise InputError(f"n: expected a positive integer, got {fmt_value(n)}")
    if isinstance(shared_every, bool) or not isinstance(shared_every, (int, np.integer)) or \
            shared_every < 0:
        raise InputError(f"shared_every: expected an integer >= 0, got {fmt_value(shared_every)}")
    t_lo, t_hi = _range(tilt_deg, "tilt_deg", 0.0, 85.0)
    f_lo, f_hi = _range(fill, "fill", 1e-3, 1.0)
    r_lo, r_hi = _range(roll_deg, "roll_deg", -180.0, 180.0)
    check_positive(max_tries, "max_tries")
    cos_max = math.cos(math.radians(check_positive(max_view_angle_deg, "max_view_angle_deg")))
    # the board's edges are seen up to a few degrees more obliquely than its centre
    cos_pre = math.cos(math.radians(max_view_angle_deg - 3.0))
    rng = np.random.default_rng(rng)
    C = len(cams)
    check_positive(corner_cell, "corner_cell")
    anchors = _ANCHORS if anchors is None else tuple(tuple(float(x) for x in a) for a in anchors)
    from facegeo.geometry.board import board_extent, board_outline, board_points

    x0, y0, x1, y1 = board_extent(board)
    W_m, H_m = x1 - x0, y1 - y0
    c_board = np.array([(x0 + x1) / 2.0, (y0 + y1) / 2.0, 0.0])
    outline = board_outline(board, 8)
    inner = board_points(board)
    per_cam = [len(range(ci, n, C)) for ci in range(C)]
    # shared views target the narrow cameras (field of view within 1.5× the narrowest): a board
    # filling a wide camera (a projector) would overflow a narrow one
    fov = np.array([min(c.width / c.fx, c.height / c.fy) for c in cams])
    narrow = [i for i in range(C) if fov[i] <= 1.5 * fov.min()]
    # where the narrow cameras' optical axes come closest (least squares): shared views go there
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for i in narrow:
        d = cams[i].T_cam_world.R[2]  # optical axis in the world
        P_perp = np.eye(3) - np.outer(d, d)
        A += P_perp
        b += P_perp @ cams[i].center_world
    x_conv = np.linalg.lstsq(A, b, rcond=None)[0]
    board_scale = float(np.hypot(W_m, H_m))
    poses: list[Pose] = []
    for k in range(n):
        shared = shared_every > 0 and k % shared_every == 0
        ci = k % C
        if shared and ci not in narrow:
            ci = narrow[(k // shared_every) % len(narrow)]
        cam = cams[ci]
        j = k // C
        m = per_cam[ci]
        others = [c for c in cams if c is not cam] if shared else []
        must = others + [c for c in also_seen_by if all(c is not o for o in others)]
        ax, ay = anchors[j % len(anchors)] if not shared or C == 1 else (0.0, 0.0)
        T_wc = cam.T_cam_world.inverse()
        corner = None if (ax == 0.0 or others) else np.array(
            [-0.5 if ax < 0 else cam.width - 0.5, -0.5 if ay < 0 else cam.height - 0.5])
        placed = None
        for attempt in range(int(max_tries)):
            # shared views: after half the draws, scale tilt and fill down (to half at most)
            shrink = 1.0 - 0.5 * min(1.0, max(0.0, 2.0 * attempt / max_tries - 1.0)) \
                if shared else 1.0
            tilt = math.radians(shrink * rng.uniform(t_lo, t_hi))
            # stratified tilt directions; shared views: any direction all the cameras accept
            az = 2.0 * math.pi * ((j + rng.uniform()) / m if not others else rng.uniform())
            roll = math.radians(rng.uniform(r_lo, r_hi))
            axis = np.array([math.cos(az), math.sin(az), 0.0])
            R = rotation_from_rvec(axis * tilt) @ rotation_from_rvec(np.array([0.0, 0.0, roll]))
            f_target = shrink * rng.uniform(f_lo, f_hi)
            jitter = rng.uniform(0.8, 1.0, 2) if (ax or ay) else rng.uniform(-0.3, 0.3, 2)
            # where the board's projected box is centred: toward the anchor, in the free span
            # less the margin (else a small image's corner views never keep their margin)
            free = np.maximum(0.5 * (1.0 - f_target) * np.array(cam.size, float) - margin_px,
                              0.0)
            q_c = np.array([(cam.width - 1) / 2.0 + (ax or 1.0) * jitter[0] * free[0],
                            (cam.height - 1) / 2.0 + (ay or 1.0) * jitter[1] * free[1]])
            v_c = cam.unproject(q_c)
            if not np.all(np.isfinite(v_c)):
                continue
            v_c = v_c / v_c[2]
            z = max(cam.fx * W_m / (f_target * cam.width), cam.fy * H_m / (f_target * cam.height))
            if others:  # cheap pre-check: the board centre's view angle from every other camera
                c_w = x_conv
                n_w = T_wc.R @ R[:, 2]
                if any(np.dot(n_w, c_w - o.center_world) < cos_pre * np.linalg.norm(
                        c_w - o.center_world) for o in others):
                    continue
            ok = False
            if others:  # centre the board where the cameras' axes meet, jittered
                p_c = cam.T_cam_world.apply(x_conv + 0.1 * board_scale * rng.uniform(-1, 1, 3))
                t = p_c - R @ c_board
                p_cam = outline @ R.T + t
                ok = True
            q_aim = q_c.copy()
            for _ in range(0 if others else 12):
                # distance for the fill; aim so the box (not the board centre) sits at q_c
                t = z * v_c - R @ c_board
                p_cam = outline @ R.T + t
                q, front = cam.project_cam(p_cam)
                if not front.all():
                    break
                span = q.max(axis=0) - q.min(axis=0)
                off = q_c - 0.5 * (q.max(axis=0) + q.min(axis=0))
                f_now = max(span[0] / cam.width, span[1] / cam.height)
                if abs(f_now - f_target) < 2e-3 and np.abs(off).max() < 0.5:
                    ok = True
                    break
                z *= f_now / f_target
                q_aim = q_aim + off
                v_c = cam.unproject(q_aim)
                if not np.all(np.isfinite(v_c)):
                    break
                v_c = v_c / v_c[2]
            if not ok:
                continue
            inside, q = _inside(cam, p_cam, margin_px, cos_max, R[:, 2])
            if not inside:
                continue
            if corner is not None and attempt < corner_tries:
                # a corner view must put a board corner near that image corner
                qi, _ = cam.project_cam(inner @ R.T + t)
                d = np.maximum(np.abs(qi[:, 0] - corner[0]) / cam.width,
                               np.abs(qi[:, 1] - corner[1]) / cam.height)
                if d.min() > corner_cell:
                    continue
            T_world_board = T_wc @ Pose(R, t)
            good = True
            for o in must:
                T_ob = o.T_cam_world @ T_world_board
                if not _inside(o, T_ob.apply(outline), margin_px, cos_max, T_ob.R[:, 2])[0]:
                    good = False
                    break
            if good:
                placed = T_world_board
                break
        if placed is None:
            raise InputError(
                f"calibration_board_poses: could not place view {k} ({'shared by every camera' if shared else 'for ' + fmt_value(cam.name)}) "
                f"in {max_tries} draws; lower tilt_deg or fill, raise shared_every, or reduce "
                "margin_px")
        poses.append(placed)
    return poses


def rig_calibration_views(board, cameras, n: int, rng, *, close_per_camera: int | None = None,
                          close=CLOSE_VIEWS, corner_per_camera: int = 0,
                          corner=CORNER_VIEWS) -> list[Pose]:
    """A rig's camera calibration views: ``n`` views seen whole by every camera, then close
    views of each camera alone, then (``corner_per_camera``) corner views of each camera.

    The shared views (:func:`calibration_board_poses` with ``shared_every=1``) connect the
    cameras in the rig's bundle adjustment but sit where the cameras' axes meet, at the head's
    distance, where the board covers about half of a narrow camera's image. The close views
    (``close_per_camera`` per camera, default ``⌈n / 3⌉``; :data:`CLOSE_VIEWS`) fill most of one
    camera's image, which is what pins a narrow camera's principal point (Zhang 2000's
    intrinsic constraints need the perspective of image-wide views; at 12° a principal-point
    shift is otherwise traded for a rotation of each view's board).

    Parameters
    ----------
    board : CharucoBoard, ChessboardSpec or CircleGridSpec
    cameras : sequence of Camera
        The rig's cameras (not the projector), world frame.
    n : int
        Shared views.
    rng : numpy.random.Generator or int
    close_per_camera : int, optional
        Close views per camera (0: none).
    close : dict
        Keyword arguments of :func:`calibration_board_poses` for the close views.
    corner_per_camera : int
        Corner views per camera (default 0: none; :data:`CORNER_VIEWS`), cycling through the
        four image corners: what brings board corners to the image's corners.
    corner : dict
        Keyword arguments of :func:`calibration_board_poses` for the corner views.

    Returns
    -------
    list of Pose
        ``T_world_board``: the ``n`` shared views, then the close views (camera ``k mod C``
        for the k-th), then the corner views (likewise). The draws of the shared and close
        views do not depend on ``corner_per_camera``.
    """
    cams = list(cameras)
    m = close_per_camera
    if m is not None and (isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 0):
        raise InputError(f"close_per_camera: expected an integer >= 0, got {fmt_value(m)}")
    rng = np.random.default_rng(rng)
    poses = calibration_board_poses(board, cams, n, rng, shared_every=1)  # validates n
    m = -(-int(n) // 3) if m is None else int(m)
    if m and cams:
        poses += calibration_board_poses(board, cams, m * len(cams), rng,
                                         **{"shared_every": 0, **close})
    mc = corner_per_camera
    if isinstance(mc, bool) or not isinstance(mc, (int, np.integer)) or mc < 0:
        raise InputError(f"corner_per_camera: expected an integer >= 0, got {fmt_value(mc)}")
    if mc and cams:
        poses += calibration_board_poses(board, cams, int(mc) * len(cams), rng,
                                         **{"shared_every": 0, "anchors": _CORNER_ANCHORS,
                                            **corner})
    return poses


#: Board kinds :func:`board_for_cameras` makes (the scan format's ``calib.board`` kinds).
BOARD_KINDS = ("charuco", "chessboard", "circles")


def board_for_cameras(cameras, *, fill: float = 0.6, squares: int = 5, dictionary="DICT_4X4_50",
                      kind: str = "charuco"):
    """A calibration board for a rig's calibration views, shaped like the narrowest camera's
    image.

    The ChArUco square is a multiple of 4 mm (marker ¾ of it) such that ``squares`` squares
    span ``fill`` of the narrowest camera's image width at its distance from the world origin
    (the head); the other side has as many squares as the image's aspect ratio allows (at least
    4), so the board covers a portrait image's height too. Covering the image is what pins a
    narrow camera's principal point (:func:`rig_calibration_views`), and the taller board
    doubles the corners per view (default rig: 5 × 7 squares, 24 corners, against 5 × 4 and 12
    before).

    The other kinds print on that ChArUco board's sheet (about the same size, so the same
    poses fit the images): a plain chessboard of squares ⅝ of the ChArUco square (rounded to
    1 mm) with as many inner corners as the sheet holds inside its white border
    (``facegeo.geometry.board.CHESSBOARD_MARGIN_SQUARES``), ``cols + rows`` odd so its two ends
    differ (the detector's numbering is then unambiguous; default rig: 4 × 7 corners, 18 mm);
    or an asymmetric circle grid (OpenCV's kind) of 4 circles per row, as many rows as fit, an odd
    number of them (a grid with an even number of rows looks the same turned half round;
    default rig: 4 × 11, spacing 25 mm).

    Parameters
    ----------
    cameras : sequence of Camera
        World frame with the head at the origin.
    fill : float
        Fraction of the narrowest image width the ``squares`` squares span at the head.
    squares : int
        Squares along the image's x axis (board x) of the ChArUco board.
    dictionary : str
        ArUco dictionary (must hold ``⌊squares_x · squares_y / 2⌋`` markers).
    kind : {"charuco", "chessboard", "circles"}

    Returns
    -------
    CharucoBoard, ChessboardSpec or CircleGridSpec
    """
    from facegeo.checks import check_choice
    from facegeo.geometry.board import CharucoBoard  # local import: board needs cv2

    check_choice(kind, "kind", BOARD_KINDS)
    cams = list(cameras)
    if not cams or not all(isinstance(c, Camera) for c in cams):
        raise InputError("cameras: expected a non-empty sequence of Camera")
    check_positive(fill, "fill")
    if isinstance(squares, bool) or not isinstance(squares, (int, np.integer)) or squares < 3:
        raise InputError(f"squares: expected an integer >= 3, got {fmt_value(squares)}")
    widths = [c.width * float(np.linalg.norm(c.center_world)) / c.fx for c in cams]
    i = int(np.argmin(widths))
    square = max(round(fill * widths[i] / squares / 0.004), 1) * 0.004  # marker = ¾ exactly
    squares_y = max(4, int(squares * cams[i].height / cams[i].width))
    charuco = CharucoBoard(squares_x=int(squares), squares_y=squares_y, square_length=square,
                           marker_length=square * 0.75, dictionary=dictionary)
    if kind == "charuco":
        return charuco
    from facegeo.geometry._calib_detect import ChessboardSpec, CircleGridSpec
    from facegeo.geometry.board import CHESSBOARD_MARGIN_SQUARES

    W, H = charuco.size
    if kind == "chessboard":
        s = round(max(round(square * 0.625 / 0.001), 1) * 0.001, 6)
        border = 2.0 * (1.0 + CHESSBOARD_MARGIN_SQUARES)  # outer squares and white border
        cols = max(int(W / s - border + 1e-9) + 1, 3)
        rows = max(int(H / s - border + 1e-9) + 1, 2)
        if (cols + rows) % 2 == 0:
            rows -= 1
        return ChessboardSpec(cols=cols, rows=rows, square_size=s)
    # asymmetric grid: a row spans 3.5 spacings, plus one spacing of border on each side
    s = round(max(round(W / 5.5 / 0.001), 1) * 0.001, 6)
    rows = max(int((H - 2.0 * s) / (s / 2.0) + 1e-9) + 1, 3)
    if rows % 2 == 0:
        rows -= 1
    return CircleGridSpec(cols=4, rows=rows, spacing=s, asymmetric=True)


def board_coverage(board, camera: Camera, T_cam_boards, grid=(8, 8)) -> float:
    """Fraction of an image grid's cells that contain at least one board corner of the views.

    Parameters
    ----------
    board : CharucoBoard, ChessboardSpec or CircleGridSpec
    camera : Camera
    T_cam_boards : sequence of Pose
        Views in the camera's frame.
    grid : (int, int)
        Cells across × down.

    Returns
    -------
    float in [0, 1]
    """
    from facegeo.geometry.board import board_points

    gx, gy = int(grid[0]), int(grid[1])
    hit = np.zeros((gy, gx), bool)
    P = board_points(board)
    for T in T_cam_boards:
        q, front = camera.project_cam(T.apply(P))
        ok = front & camera.in_image(q)
        ix = np.clip((q[ok, 0] + 0.5) / camera.width * gx, 0, gx - 1).astype(int)
        iy = np.clip((q[ok, 1] + 0.5) / camera.height * gy, 0, gy - 1).astype(int)
        hit[iy, ix] = True
    return float(hit.mean())
