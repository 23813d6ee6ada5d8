"""Distortion model selection that refuses degenerate lenses, and σ that predicts the spread
(issue 35): ``calibrate_camera(model="auto")``, :func:`lens_degeneracy`, the jackknife over
views (``sigma_method``), leave-one-view-out cross-validation.

Real data: OpenCV's stereo chessboards under ``../shared/data`` (skipped with a reason when
absent). Their corners are found here as OpenCV's calibration sample finds them
(``findChessboardCorners`` + 11 × 11 ``cornerSubPix``), the corners ``left_intrinsics.yml``
was solved from — so the comparison with it is about the model and σ, not the detector.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from facegeo.frames import Pose
from facegeo.geometry.board import CharucoBoard, random_board_poses
from facegeo.geometry.calibration import (
    AUTO_CANDIDATES, calibrate_camera, cross_validate, lens_degeneracy, select_model,
)
from facegeo.geometry.camera import Camera

TRUE_K = np.array([[1210.0, 0.0, 655.3], [0.0, 1190.0, 371.8], [0.0, 0.0, 1.0]])
TRUE_DIST = np.array([-0.21, 0.09, 0.0012, -0.0007, -0.02])
SIZE = (1280, 720)
BOARD = CharucoBoard(10, 7, 0.03, 0.022)

#: reported σ against the spread it should predict: within this factor both ways
SIGMA_RATIO_TOL = 1.5
#: the left camera's fx, fy, cx, cy against left_intrinsics.yml: within this many reported σ
YML_N_SIGMA = 2.0
#: leave-one-view-out held-out reprojection RMS, pixels (the issue's cross-validation bound)
CV_HELD_OUT_PX = 1.0
#: two solves on disjoint halves (``cross_validate``): their projection difference within this
#: factor of the difference their σ predict (measured 0.34–0.86 here; before the jackknife σ,
#: the right camera's was 3.7× its prediction)
CV_PREDICTED_FACTOR = 2.0
#: fewest grid pixels (of 16 × 12) inside both halves' corners on OpenCV's chessboards
#: (measured 42-67 over seeds 0-3)
CV_MIN_PIXELS = 30
#: a lens's radial terms may add up to at most this many times their net effect (the test's own
#: check; the degenerate rational fits of OpenCV's cameras: 37–3200, real lenses 1.0–2.9)
CANCEL_TOL = 10.0
#: linearised leave-one-out (one Gauss–Newton step) against full re-solves: fx, fy, cx, cy
#: within this fraction of their formal σ
LOO_LINEAR_SIGMA = 0.1
#: and each view's held-out mean squared residual within this relative difference
LOO_HELD_OUT_REL = 0.05


def _camera(K=TRUE_K, dist=TRUE_DIST):
    return Camera("cam", SIZE[0], SIZE[1], K, dist, Pose.identity())


def _views(n, seed, noise_px, rng):
    cam = _camera()
    P0 = BOARD.chessboard_corners()
    poses = random_board_poses(cam, n, seed, board=BOARD)
    Q = [cam.project_cam(T.apply(P0))[0] + rng.normal(0, noise_px, (len(P0), 2)) for T in poses]
    return [P0] * n, Q, poses


def _radial_check(cam) -> dict:
    """The test's own check of a lens over its image: every image corner has a ray
    (``Camera.unproject``), and along r ∈ [0, r_max of those rays] the radial factor stays
    positive, the distorted radius increases and the terms do not cancel."""
    w, h = cam.size
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    v, ok = cam.unproject(corners, return_valid=True)
    d = np.zeros(8)
    d[: cam.dist.size] = cam.dist
    k1, k2, _, _, k3, k4, k5, k6 = d
    r_max = float(np.max(np.hypot(v[:, 0], v[:, 1]) / v[:, 2])) if ok.all() else np.nan
    r = np.linspace(0.0, r_max if ok.all() else 1.0, 2000)
    s = r * r
    num, den = 1 + k1 * s + k2 * s**2 + k3 * s**3, 1 + k4 * s + k5 * s**2 + k6 * s**3
    g = num / den
    gross = (abs(k1) + abs(k4)) * s + (abs(k2) + abs(k5)) * s**2 + (abs(k3) + abs(k6)) * s**3
    net = np.abs(g - 1).max()
    return {"corners_have_rays": bool(ok.all()), "positive": bool(np.all((num > 0) & (den > 0))),
            "monotonic": bool(np.all(np.diff(r * g) > 0)),
            "cancellation": float(gross.max() / net) if net > 0 else 1.0}


def _is_a_lens(cam) -> bool:
    c = _radial_check(cam)
    return (c["corners_have_rays"] and c["positive"] and c["monotonic"]
            and c["cancellation"] <= CANCEL_TOL)


def _jackknife_spread(P, Q, size, model, **kw):
    """Leave-one-view-out by full re-solves: the jackknife standard error of fx, fy, cx, cy,
    ``sqrt((V − 1)/V Σ (θ_i − θ̄)²)``."""
    est = []
    for i in range(len(P)):
        c = calibrate_camera(P[:i] + P[i + 1:], Q[:i] + Q[i + 1:], size, model=model,
                             reject_views=False, **kw)
        est.append([c.camera.fx, c.camera.fy, c.camera.cx, c.camera.cy])
    est = np.array(est)
    V = len(est)
    return np.sqrt((V - 1) / V * np.sum((est - est.mean(0)) ** 2, axis=0))


# ------------------------------------------------------------------ lens degeneracy


def test_lens_degeneracy_refuses_folds_poles_shared_roots_and_cancellation():
    """A real lens passes; each way a fitted distortion stops being a lens over the image is
    refused with its reason: a k1 so strong the distorted radius folds before the image
    corners, numerator and denominator sharing a root inside the image, and the issue's
    rational fit (coefficients 10–100 cancelling). A pole beyond the image's corners is not
    refused."""
    K = np.array([[536.0, 0, 342.0], [0, 536.0, 235.0], [0, 0, 1]])

    def cam(dist, size=(640, 480)):
        return Camera("c", size[0], size[1], K, np.asarray(dist, float), Pose.identity())

    assert not lens_degeneracy(_camera())["degenerate"]
    assert not lens_degeneracy(cam([-0.28, 0.09, 0.0, 0.0]))["degenerate"]  # OpenCV's right
    # k1 alone of OpenCV's left camera: r(1 + k1 r²) peaks at 0.749 < the corner's 0.80
    out = lens_degeneracy(cam([-0.264, 0.0, 0.0, 0.0]))
    assert out["degenerate"] and "folds back" in out["reason"] and "no ray" in out["reason"]
    # a strong pincushion 1 / (1 − 4 r²) reaches the image's corners (r = 0.37) before its
    # pole (r = 0.5): a lens over this image
    assert not lens_degeneracy(cam([0.0, 0.0, 0.0, 0.0, 0.0, -4.0, 0.0, 0.0]))["degenerate"]
    # (1 − s/0.09)(1 + 0.1 s) / ((1 − s/0.09)(1 + 0.2 s)): both vanish at r = 0.3
    n = np.polynomial.polynomial.polymul([1, -1 / 0.09], [1, 0.1])
    d = np.polynomial.polynomial.polymul([1, -1 / 0.09], [1, 0.2])
    out = lens_degeneracy(cam([n[1], n[2], 0, 0, 0, d[1], d[2], 0]))
    assert out["degenerate"] and "share a root" in out["reason"], out
    # ... and 0.5 % apart: the factor swings through 0 between them
    d = np.polynomial.polynomial.polymul([1, -1 / 0.0905], [1, 0.2])
    assert lens_degeneracy(cam([n[1], n[2], 0, 0, 0, d[1], d[2], 0]))["degenerate"]
    issue = [-18.97, 106.058, 0.001, 0.0, 15.445, -18.682, 100.528, 47.222]
    out = lens_degeneracy(cam(issue))
    assert out["degenerate"] and "cancel" in out["reason"] and out["cancellation"] > 100
    # the test's own check agrees on every case
    for dist, lens in (([-0.28, 0.09, 0.0, 0.0], True), ([-0.264, 0, 0, 0], False),
                       (issue, False)):
        assert _is_a_lens(cam(dist)) == lens, dist


# ------------------------------------------------------------------ leave-one-out, jackknife


def test_linearised_leave_one_out_matches_full_resolves():
    """The one-Gauss–Newton-step leave-one-view-out solutions and held-out errors (what the
    selection and the jackknife use) against full re-solves without each view and a
    ``solvePnP`` of the held-out view at those intrinsics."""
    rng = np.random.default_rng(7)
    P, Q, _ = _views(8, 21, 0.2, rng)
    c = calibrate_camera(P, Q, SIZE, reject_views=False)
    lin = c.leave_one_out_thetas()
    ho = c.held_out_mse()
    sd = np.array([c.std_formal[k] for k in ("fx", "fy", "cx", "cy")])
    for i in range(len(P)):
        ci = calibrate_camera(P[:i] + P[i + 1:], Q[:i] + Q[i + 1:], SIZE, reject_views=False)
        e = ci.camera
        exact = np.array([e.fx, e.fy, e.cx, e.cy])
        assert np.all(np.abs(lin[i, :4] - exact) <= LOO_LINEAR_SIGMA * sd), (i, lin[i], exact)
        ok, rv, tv = cv2.solvePnP(P[i], Q[i], e.K, e.dist)
        rv, tv = cv2.solvePnPRefineLM(P[i], Q[i], e.K, e.dist, rv, tv)
        q, _ = cv2.projectPoints(P[i], rv, tv, e.K, e.dist)
        mse = np.mean(np.sum((q.reshape(-1, 2) - Q[i]) ** 2, axis=-1))
        assert abs(ho[i] / mse - 1) <= LOO_HELD_OUT_REL, (i, ho[i], mse)


def test_independent_noise_is_not_inflated_correlated_view_errors_are():
    """Independent corner noise: the jackknife finds the formal σ about right (inflation
    1.0–1.6 per draw, mean 1.2: the jackknife is conservative) and the reported σ predicts the
    spread over 40 draws. Corner errors shared within a view (each view's corners off by its own
    smooth field, as a warped print or a detector's bias give): the formal σ is 3–5× too small,
    the jackknife's predicts the spread — fx, cx, cy within ``SIGMA_RATIO_TOL``."""
    P0 = BOARD.chessboard_corners()
    cam = _camera()
    poses = random_board_poses(cam, 10, 5, board=BOARD)
    clean = [cam.project_cam(T.apply(P0))[0] for T in poses]
    rng = np.random.default_rng(3)
    u = (P0[:, :2] - P0[:, :2].mean(0)) / np.ptp(P0[:, :2], axis=0)  # board coords in ±0.5
    for correlated in (False, True):
        est, rep, formal, infl = [], [], [], []
        for _ in range(40):
            Q = []
            for q in clean:
                e = rng.normal(0, 0.05, q.shape)
                if correlated:  # a smooth per-view field: affine + one quadratic term, ≈ 0.5 px
                    A = rng.normal(0, 0.5, (2, 3))
                    e += A[:, 0] + u @ A[:, 1:].T + rng.normal(0, 0.5, 2) * (u**2).sum(1)[:, None]
                Q.append(q + e)
            c = calibrate_camera([P0] * len(Q), Q, SIZE, K_init=TRUE_K, reject_views=False)
            est.append([c.camera.fx, c.camera.cx, c.camera.cy])
            rep.append([c.std[k] for k in ("fx", "cx", "cy")])
            formal.append([c.std_formal[k] for k in ("fx", "cx", "cy")])
            infl.append(c.sigma_inflation)
            assert c.sigma_method == "jackknife"
        spread = np.std(est, axis=0, ddof=1)
        ratio = spread / np.mean(rep, axis=0)
        assert np.all(ratio <= SIGMA_RATIO_TOL) and np.all(ratio >= 1 / SIGMA_RATIO_TOL), (
            correlated, ratio)
        if correlated:
            assert np.mean(infl) > 2.0
            assert np.any(spread / np.mean(formal, axis=0) > 2 * SIGMA_RATIO_TOL)
        else:
            assert np.mean(infl) < 1.3


def test_five_views_cross_validate_and_report_formal_sigma():
    """Five views: leave-one-out cross-validation works (4 left to solve each time) and gives a
    held-out error near the injected noise; too few views for the jackknife, σ is the formal
    one and says so. Six views: the jackknife."""
    rng = np.random.default_rng(11)
    P, Q, _ = _views(6, 4, 0.1, rng)
    c = calibrate_camera(P[:5], Q[:5], SIZE, model="auto")
    sel = c.model_selection
    assert sel["folds"] == 5 and c.model not in sel["rejected"]
    loo = c.leave_one_out()
    assert loo["views"] == 5
    assert 0.1 * np.sqrt(2) <= loo["held_out_rms_px"] <= 2 * 0.1 * np.sqrt(2)
    assert c.sigma_method == "formal" and c.sigma_inflation == 1.0
    assert c.std["fx"] == c.std_formal["fx"]
    c6 = calibrate_camera(P, Q, SIZE, model=c.model)
    assert c6.sigma_method == "jackknife" and c6.sigma_inflation >= 1.0


def test_selection_reuses_its_solve_and_records_every_reason():
    """``auto`` returns the chosen candidate's own solve (warm-started, not solved twice) — the
    same optimum as solving that model directly; every candidate not taken has its reason."""
    rng = np.random.default_rng(2)
    P, Q, _ = _views(10, 8, 0.2, rng)
    c = calibrate_camera(P, Q, SIZE, model="auto")
    d = calibrate_camera(P, Q, SIZE, model=c.model)
    for a, b in ((c.camera.fx, d.camera.fx), (c.camera.cx, d.camera.cx),
                 (c.camera.cy, d.camera.cy)):
        assert abs(a - b) <= 1e-3  # px: both converged (relative ‖r‖² decrease 1e-12)
    sel = select_model(P, Q, SIZE)
    assert sel["model"] == c.model and set(sel["scores"]) == set(AUTO_CANDIDATES)
    assert set(sel["rejected"]) == set(AUTO_CANDIDATES) - {c.model}  # superseded ones too
    assert all(isinstance(sel["scores"][m]["rejected"], str) for m in sel["rejected"])
    assert c.model in sel["reason"] and "not taken" in sel["reason"]


# ------------------------------------------------------------------ OpenCV's chessboards


def _sample_corners(shared_data, side):
    """OpenCV's calibration sample's corners of ``{side}*.jpg``: ``findChessboardCorners``
    (adaptive threshold, normalise, fast check) then ``cornerSubPix`` 11 × 11, 30 iterations /
    0.01 px; the board 9 × 6 corners of 25 mm, row-major."""
    from conftest import shared_file

    d = shared_file(shared_data, "calibration/opencv_stereo_chessboards")
    obj = np.zeros((54, 3))
    obj[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 0.025
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_FAST_CHECK | cv2.CALIB_CB_NORMALIZE_IMAGE
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    P, Q = [], []
    for f in sorted(d.glob(f"{side}*.jpg")):
        g = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        ok, c = cv2.findChessboardCorners(g, (9, 6), flags=flags)
        assert ok, f.name
        c = cv2.cornerSubPix(g, c, (11, 11), (-1, -1), crit)
        P.append(obj.copy())
        Q.append(c.reshape(-1, 2).astype(np.float64))
    return d, P, Q


@pytest.fixture(scope="module")
def opencv_auto(shared_data):
    """``model="auto"`` (default options) on both cameras of OpenCV's stereo chessboards."""
    out = {}
    for side in ("left", "right"):
        d, P, Q = _sample_corners(shared_data, side)
        out[side] = (d, P, Q, calibrate_camera(P, Q, (640, 480), model="auto", name=side))
    return out


@pytest.mark.parametrize("side", ["left", "right"])
def test_real_auto_model_is_a_lens_and_cross_validates(opencv_auto, side):
    """The chosen model is a lens over the whole image (the test's own check: every image
    corner has a ray, the distortion positive, monotonic and un-cancelled out to there); the
    rational model — the issue's degenerate choice — is refused as degenerate; leave-one-view-
    out cross-validation ≤ 1 px (held-out reprojection RMS over every used view)."""
    _, P, Q, c = opencv_auto[side]
    sel = c.model_selection
    assert _is_a_lens(c.camera), (c.model, c.camera.dist, _radial_check(c.camera))
    assert c.model in ("k1k2", "opencv5"), sel["reason"]
    assert "degenerate" in sel["rejected"]["rational8"], sel["rejected"]
    loo = c.leave_one_out()
    assert loo["held_out_rms_px"] <= CV_HELD_OUT_PX, loo
    assert loo["held_out_rms_px"] <= 1.2 * c.rms_px  # close to in-sample: no overfit
    assert sel["scores"][c.model]["held_out_rms_px"] == pytest.approx(loo["held_out_rms_px"])
    # mrcal's check on two halves of 6-7 views, compared where both halves have corners (the
    # convex hull of each half's corners: region "covered", the default) — ≤ 1 px, and within
    # what the halves' σ predict. Over the whole image the boards (reaching r ≈ 0.6 of the
    # corners' 0.95) leave each half to extrapolate: the left camera's halves differ there by
    # 26.6 px RMS (seed 0; measured covered 0.46 / 0.34 px left / right, seeds 0-3 ≤ 0.62 /
    # 0.89)
    cv = cross_validate(P, Q, (640, 480), model=c.model)
    assert cv["region"] == "covered" and cv["n_pixels"] >= CV_MIN_PIXELS, cv
    assert cv["diff_rms_px"] <= CV_HELD_OUT_PX, cv
    assert cv["diff_rms_px"] <= CV_PREDICTED_FACTOR * cv["predicted_rms_px"], cv
    assert cv["image_diff_rms_px"] >= cv["diff_rms_px"]
    if side == "left":  # the whole image extrapolates: the figure the restriction removes
        assert cv["image_diff_rms_px"] > 10 * CV_HELD_OUT_PX, cv


def test_real_left_matches_opencv_yml_within_two_sigma(opencv_auto):
    """The left camera's fx, fy, cx, cy within 2 reported σ of ``left_intrinsics.yml``
    (OpenCV's own calibration of the same corners: 5-term model, fixed aspect ratio)."""
    d, _, _, c = opencv_auto["left"]
    fs = cv2.FileStorage(str(d / "left_intrinsics.yml"), cv2.FILE_STORAGE_READ)
    K = fs.getNode("camera_matrix").mat()
    fs.release()
    e = c.camera
    for k, ours, ref in (("fx", e.fx, K[0, 0]), ("fy", e.fy, K[1, 1]), ("cx", e.cx, K[0, 2]),
                         ("cy", e.cy, K[1, 2])):
        assert abs(ours - ref) <= YML_N_SIGMA * c.std[k], (k, ours, ref, c.std[k])


@pytest.mark.parametrize("side", ["left", "right"])
def test_real_sigma_predicts_leave_one_view_out_spread(opencv_auto, side):
    """Reported σ of fx, fy, cx, cy within ×1.5 of the jackknife spread the test computes from
    full re-solves without each used view (the chosen model); the formal σ (``std_formal``,
    what was reported before) is more than 1.5× too small on at least one of them."""
    _, P, Q, c = opencv_auto[side]
    used = np.flatnonzero(c.views_used)
    spread = _jackknife_spread([P[i] for i in used], [Q[i] for i in used], (640, 480), c.model)
    keys = ("fx", "fy", "cx", "cy")
    ratio = np.array([c.std[k] for k in keys]) / spread
    assert c.sigma_method == "jackknife" and c.sigma_inflation > 1.0
    assert np.all(ratio <= SIGMA_RATIO_TOL) and np.all(ratio >= 1 / SIGMA_RATIO_TOL), ratio
    formal = np.array([c.std_formal[k] for k in keys]) / spread
    assert formal.min() < 1 / SIGMA_RATIO_TOL, formal


#: facegeo's corners (sector detector + refinement, ``detect_boards``) against OpenCV's sample's
#: corners on OpenCV's stereo chessboards, ``model="auto"``: leave-one-view-out held-out RMS
#: not worse than this factor of OpenCV's corners' (measured left 0.183 vs 0.241, right 0.192
#: vs 0.332 px: 0.76 / 0.58)
CORNERS_HELD_OUT_FACTOR = 1.0


@pytest.mark.parametrize("side", ["left", "right"])
def test_real_facegeo_corners_cross_validate_within_a_pixel(shared_data, opencv_auto, side):
    """The stage's cross-validation of facegeo's own corners ≤ 1 px on both cameras (issue 35),
    side by side with OpenCV's corners. One two-halves split is one draw: the right camera read
    1.08 px at seed 0 (OpenCV's corners 0.60) and 0.44 / 1.03 / 0.63 at seeds 1-3 (OpenCV's
    1.07 / 0.39 / 0.92), so the stage combines ``CV_SPLITS`` splits: measured facegeo's corners
    left 0.14 / right 0.84 px, OpenCV's 1.03 / 0.79 px. Corner windows were no remedy (a
    refinement half-window of 0.5 × the spacing: right 0.24-0.53 px but the left camera worse
    and views rejected; docs/calibration.md)."""
    from facegeo.geometry.calibration import ChessboardSpec, detect_boards
    from facegeo.pipeline._calibrate_products import CV_SPLITS

    d, _, _, c_cv = opencv_auto[side]
    files = sorted(d.glob(f"{side}*.jpg"))
    dets = [x for x in detect_boards([cv2.imread(str(f)) for f in files],
                                     ChessboardSpec(9, 6, 0.025)) if x.found]
    assert len(dets) == len(files)
    P, Q = [x.p_board for x in dets], [x.q for x in dets]
    c = calibrate_camera(P, Q, (640, 480), model="auto", name=side)
    cv = cross_validate(P, Q, (640, 480), model=c.model, reject_views=False, splits=CV_SPLITS)
    assert cv["splits"] == CV_SPLITS and len(cv["split_diff_rms_px"]) == CV_SPLITS
    assert cv["diff_rms_px"] <= CV_HELD_OUT_PX, cv["split_diff_rms_px"]
    assert cv["diff_rms_px"] <= CV_PREDICTED_FACTOR * cv["predicted_rms_px"], cv
    # the combination is the RMS of the splits, the first split the seed-0 check
    assert cv["diff_rms_px"] == pytest.approx(np.sqrt(np.mean(np.square(
        cv["split_diff_rms_px"]))), rel=1e-12)
    one = cross_validate(P, Q, (640, 480), model=c.model, reject_views=False)
    assert one["diff_rms_px"] == pytest.approx(cv["split_diff_rms_px"][0], rel=1e-12)
    held = c.leave_one_out()["held_out_rms_px"]
    held_cv = c_cv.leave_one_out()["held_out_rms_px"]
    assert held <= CORNERS_HELD_OUT_FACTOR * held_cv, (held, held_cv)
