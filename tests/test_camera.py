"""facegeo.geometry.camera: projection against OpenCV, inverse pairs, rays, NaN handling, validation."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from facegeo.geometry.camera import Camera
from facegeo.errors import InputError, ShapeError
from facegeo.frames import Pose

# Tolerances (named, with units).
PROJECT_VS_OPENCV_MAX_PX = 1e-9  # max |q − cv2.projectPoints|, pixels
ROUND_TRIP_MAX_PX = 1e-6  # max |project(unproject(q)) − q| over the whole image, pixels
UNDISTORT_VS_OPENCV_MAX_PX = 1e-8  # max |undistort − cv2.undistortPoints (iterated)|, pixels
JACOBIAN_FD_MAX = 1e-7  # max |analytic − central-difference Jacobian|, unitless
RAY_REPROJECT_MAX_PX = 1e-6  # max pixel error of a ray point projected back, pixels
UNIT_NORM_MAX = 1e-12  # max | |d| − 1 | of ray directions
SCALED_MAX_PX = 1e-9  # max error of the scaled camera's pixel mapping, pixels

W, H = 640, 480
K_ASYM = np.array([[812.3, 0.0, 331.7], [0.0, 809.1, 236.2], [0.0, 0.0, 1.0]])
DIST5 = np.array([-0.12, 0.08, 4e-4, -3e-4, -0.01])
DIST8 = np.array([-0.12, 0.08, 4e-4, -3e-4, -0.01, 0.03, -0.02, 0.006])
DIST4 = np.array([-0.09, 0.05, -2e-4, 5e-4])
# A pose off every axis: rotation about a skew axis, translation with three unequal components.
POSE = Pose.from_rvec_tvec([0.21, -0.37, 0.13], [0.05, -0.08, 1.2])


def make_camera(dist=DIST5, pose=POSE, K=K_ASYM) -> Camera:
    return Camera("cam_test", W, H, K, dist, pose)


def points_in_view(cam: Camera, n: int, rng, *, margin: float = 0.0) -> np.ndarray:
    """World points in front of ``cam`` whose pixels lie over the image (± margin·size)."""
    q = np.stack(
        [
            rng.uniform(-margin * W, (1 + margin) * W, n) - 0.5,
            rng.uniform(-margin * H, (1 + margin) * H, n) - 0.5,
        ],
        axis=-1,
    )
    depth = rng.uniform(0.3, 3.0, n)
    v_cam = cam.unproject(q)
    p_cam = v_cam * depth[:, None]
    return cam.T_cam_world.inverse().apply(p_cam)


@pytest.mark.parametrize("dist", [np.zeros(0), DIST4, DIST5, DIST8], ids=["n0", "n4", "n5", "n8"])
def test_project_matches_opencv(dist):
    rng = np.random.default_rng(1)
    cam = make_camera(dist)
    p_world = points_in_view(cam, 2000, rng, margin=0.05)
    q, in_front = cam.project(p_world)
    assert in_front.all()
    K, d, rvec, tvec = cam.to_opencv()
    q_cv, _ = cv2.projectPoints(p_world, rvec, tvec, K, d)
    err = np.abs(q - q_cv.reshape(-1, 2)).max()
    assert err <= PROJECT_VS_OPENCV_MAX_PX, f"max |q - cv2.projectPoints| = {err:.3g} px"


def test_project_vectorises_over_leading_axes():
    rng = np.random.default_rng(2)
    cam = make_camera()
    p = points_in_view(cam, 24, rng).reshape(2, 3, 4, 3)
    q, in_front = cam.project(p)
    assert q.shape == (2, 3, 4, 2) and in_front.shape == (2, 3, 4)
    q_flat, _ = cam.project(p.reshape(-1, 3))
    assert np.array_equal(q.reshape(-1, 2), q_flat), "max |q(batched) - q(flat)| must be 0"


def test_unproject_project_round_trip_whole_image():
    cam = make_camera()
    q = cam.pixel_grid()
    # Include the exact image border, where distortion is largest.
    edges = np.array([[-0.5, -0.5], [W - 0.5, -0.5], [-0.5, H - 0.5], [W - 0.5, H - 0.5]])
    v, valid = cam.unproject(q, return_valid=True)
    assert valid.all(), "undistortion converged for every pixel"
    assert np.all(v[..., 2] == 1.0)
    q2, in_front = cam.project_cam(v)
    assert in_front.all()
    err = np.abs(q2 - q).max()
    assert err <= ROUND_TRIP_MAX_PX, f"max round-trip error over {W}x{H} pixels = {err:.3g} px"
    q3, _ = cam.project_cam(cam.unproject(edges))
    err_edges = np.abs(q3 - edges).max()
    assert err_edges <= ROUND_TRIP_MAX_PX, f"max round-trip error at corners = {err_edges:.3g} px"


def test_undistort_matches_opencv_iterated():
    cam = make_camera()
    q = cam.pixel_grid()[::5, ::5].reshape(-1, 2)
    v = cam.unproject(q)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    x_cv = cv2.undistortPoints(q.reshape(-1, 1, 2), cam.K, cam.dist, None, None, None, crit)
    err_px = (np.abs(x_cv.reshape(-1, 2) - v[:, :2]) * [cam.fx, cam.fy]).max()
    assert err_px <= UNDISTORT_VS_OPENCV_MAX_PX, (
        f"max |undistort - cv2.undistortPoints| = {err_px:.3g} px"
    )


def test_distortion_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    cam = make_camera(DIST8)
    x = rng.uniform(-0.5, 0.5, (200, 2))
    _, J = cam._distort(x, jacobian=True)
    h = 1e-6
    J_fd = np.empty_like(J)
    for k in range(2):
        e = np.zeros(2)
        e[k] = h
        J_fd[..., :, k] = (cam.distort(x + e) - cam.distort(x - e)) / (2 * h)
    err = np.abs(J - J_fd).max()
    assert err <= JACOBIAN_FD_MAX, f"max |J - J_fd| = {err:.3g}"


def test_undistort_flags_fold_of_the_model_as_nan():
    # k1 = -0.5: x_d = x(1 - 0.5 r²) peaks at r = sqrt(2/3) with r_d ≈ 0.544; beyond it there is
    # no inverse on the principal branch.
    cam = make_camera(np.array([-0.5, 0.0, 0.0, 0.0]))
    x_d = np.array([[0.2, 0.1], [0.7, 0.0], [0.0, -0.8], [np.nan, 0.0]])
    x_n, ok = cam.undistort(x_d, return_converged=True)
    assert ok.tolist() == [True, False, False, False]
    assert np.isnan(x_n[~ok]).all() and np.isfinite(x_n[ok]).all()
    err = np.abs(cam.distort(x_n[ok]) - x_d[ok]).max()
    assert err <= 1e-13, f"max |distort(undistort(x)) - x| = {err:.3g} (normalised)"


def test_pixel_rays_pass_through_pixel_centres():
    rng = np.random.default_rng(4)
    cam = make_camera()
    q = np.stack([rng.uniform(-0.5, W - 0.5, 500), rng.uniform(-0.5, H - 0.5, 500)], -1)
    o, d = cam.pixel_rays(q)
    assert o.shape == d.shape == (500, 3)
    norm_err = np.abs(np.linalg.norm(d, axis=-1) - 1).max()
    assert norm_err <= UNIT_NORM_MAX, f"max | |d| - 1 | = {norm_err:.3g}"
    assert np.allclose(o, cam.center_world, atol=0, rtol=0)
    s = rng.uniform(0.2, 5.0, (500, 1))
    q2, in_front = cam.project(o + s * d)
    assert in_front.all()
    err = np.abs(q2 - q).max()
    assert err <= RAY_REPROJECT_MAX_PX, f"max reprojection error of ray points = {err:.3g} px"


def test_pixel_rays_default_is_every_pixel_centre():
    cam = make_camera()
    o, d = cam.pixel_rays()
    assert o.shape == d.shape == (H, W, 3)
    q, _ = cam.project(o[::37, ::41] + 1.7 * d[::37, ::41])
    err = np.abs(q - cam.pixel_grid()[::37, ::41]).max()
    assert err <= RAY_REPROJECT_MAX_PX, f"max reprojection error of pixel rays = {err:.3g} px"
    # Pixel (col 5, row 3) is grid[3, 5] = (5, 3): x is the column.
    assert cam.pixel_grid()[3, 5].tolist() == [5.0, 3.0]


def test_points_behind_camera_are_nan_and_flagged():
    cam = make_camera()
    p_cam = np.array([[0.1, -0.2, 1.0], [0.1, -0.2, -1.0], [0.3, 0.1, 0.0], [0.0, 0.0, -1e-9]])
    q, in_front = cam.project_cam(p_cam)
    assert in_front.tolist() == [True, False, False, False]
    assert np.isfinite(q[0]).all() and np.isnan(q[1:]).all()
    # The same through the world frame.
    q_w, in_front_w = cam.project(cam.T_cam_world.inverse().apply(p_cam))
    assert in_front_w.tolist() == [True, False, False, False]
    assert np.isnan(q_w[1:]).all()
    # Not in the image either.
    assert cam.in_image(q).tolist() == [True, False, False, False]
    # Non-finite input is flagged the same way, not raised.
    q_nan, in_front_nan = cam.project(np.array([[np.nan, 0.0, 1.0], [0.0, np.inf, 1.0]]))
    assert not in_front_nan.any() and np.isnan(q_nan).all()


def test_in_image_half_open_pixel_bounds():
    cam = make_camera()
    q = np.array(
        [[-0.5, -0.5], [W - 0.5, 10.0], [10.0, H - 0.5], [W - 0.5 - 1e-9, H - 0.5 - 1e-9],
         [-0.5 - 1e-9, 3.0], [np.nan, 3.0]]
    )
    assert cam.in_image(q).tolist() == [True, False, False, True, False, False]


def test_to_dict_round_trip_through_json():
    cam = make_camera(DIST8)
    back = Camera.from_dict(json.loads(json.dumps(cam.to_dict())))
    assert back == cam
    assert np.array_equal(back.K, cam.K) and np.array_equal(back.dist, cam.dist)


def test_opencv_round_trip():
    cam = make_camera()
    K, d, rvec, tvec = cam.to_opencv()
    back = Camera.from_opencv(cam.name, W, H, K, d.reshape(1, -1), rvec.reshape(3, 1), tvec)
    assert np.array_equal(back.K, cam.K) and np.array_equal(back.dist, cam.dist)
    err_R = np.abs(back.T_cam_world.R - cam.T_cam_world.R).max()
    assert err_R <= 1e-14, f"max |R - R(rvec(R))| = {err_R:.3g}"


def test_properties_and_center():
    cam = make_camera()
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (812.3, 809.1, 331.7, 236.2)
    c = cam.center_world
    err = np.abs(cam.T_cam_world.apply(c)).max()
    assert err <= 1e-15, f"max |T_cam_world(center_world)| = {err:.3g} m"


def test_camera_is_immutable_copy():
    K = K_ASYM.copy()
    cam = make_camera(K=K)
    K[0, 0] = 1.0
    assert cam.fx == 812.3, "the camera keeps a copy of K"
    with pytest.raises(ValueError):
        cam.K[0, 0] = 5.0


def test_scaled_camera_maps_pixel_centres():
    rng = np.random.default_rng(5)
    cam = make_camera()
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    p = points_in_view(cam, 300, rng)
    q, _ = cam.project(p)
    q_half, _ = half.project(p)
    err = np.abs(q_half - ((q + 0.5) * 0.5 - 0.5)).max()
    assert err <= SCALED_MAX_PX, f"max |q_half - ((q + 0.5)/2 - 0.5)| = {err:.3g} px"
    with pytest.raises(InputError, match="width"):
        cam.scaled(0.37)
    with pytest.raises(InputError, match="factor"):
        cam.scaled(-1.0)


@pytest.mark.parametrize(
    "kwargs, exc, field",
    [
        ({"K": np.eye(3)[:, :2]}, ShapeError, "K"),
        ({"K": K_ASYM.T}, InputError, "K"),  # a transposed K is caught by its structure
        ({"K": np.diag([800.0, -700.0, 1.0])}, InputError, "K"),
        ({"width": -640}, InputError, "width"),
        ({"height": 480.5}, InputError, "height"),
        ({"dist": np.zeros(3)}, ShapeError, "dist"),
        ({"dist": np.array([0.1, np.nan, 0.0, 0.0])}, InputError, "dist"),
        ({"name": ""}, InputError, "name"),
        ({"T_cam_world": np.eye(4)}, InputError, "T_cam_world"),
    ],
)
def test_bad_camera_input_names_the_field(kwargs, exc, field):
    args = dict(name="cam", width=W, height=H, K=K_ASYM, dist=DIST5, T_cam_world=POSE)
    args.update(kwargs)
    with pytest.raises(exc) as info:
        Camera(**args)
    assert str(info.value).startswith(field), f"message {info.value!s:.80} names {field!r}"


def test_from_dict_errors_name_the_field():
    d = make_camera().to_dict()
    del d["K"]
    with pytest.raises(InputError, match=r"cameras\[2\]\.K: missing"):
        Camera.from_dict(d, where="cameras[2]")
    d = make_camera().to_dict()
    d["dist"] = [0.1, 0.2, 0.3]
    with pytest.raises(ShapeError, match=r"camera\.dist:"):
        Camera.from_dict(d)
    d = make_camera().to_dict()
    d["focal"] = 3
    with pytest.raises(InputError, match=r"camera\.focal: unknown field"):
        Camera.from_dict(d)


# --------------------------------------------------------------------------- distortion fold

FOLD_REL_STEP = 1e-6  # relative step either side of the fold radius, dimensionless


def _radial_rd(dist, r):
    """Distorted radius r·P(r²)/Q(r²) of the radial(+rational) model, by direct evaluation."""
    d = np.zeros(8)
    d[: len(dist)] = dist
    k1, k2, _, _, k3, k4, k5, k6 = d
    s = r * r
    return r * (1 + k1 * s + k2 * s**2 + k3 * s**3) / (1 + k4 * s + k5 * s**2 + k6 * s**3)


@pytest.mark.parametrize("dist", [np.array([-0.5, 0.0, 0.0, 0.0]), DIST5, DIST8],
                         ids=["k1", "n5", "n8"])
def test_fold_radius_is_where_the_radial_model_turns(dist):
    cam = make_camera(dist)
    r_f = cam.fold_radius()
    assert np.isfinite(r_f) and r_f > 0
    if dist.size == 4:
        assert r_f == pytest.approx(np.sqrt(2 / 3), rel=1e-12), "k1 = -0.5: r_f = sqrt(2/3), rel"
    # r_d increases up to r_f and decreases right after it (a maximum, not a plateau).
    r = r_f * np.array([0.5, 1 - FOLD_REL_STEP, 1.0, 1 + FOLD_REL_STEP])
    rd = _radial_rd(dist, r)
    assert rd[0] < rd[1] < rd[2], "r_d increasing inside the fold"
    assert rd[3] < rd[2], "r_d decreasing beyond the fold"
    assert make_camera(np.zeros(0)).fold_radius() == np.inf
    assert make_camera(np.array([0.1, 0.0, 0.0, 0.0])).fold_radius() == np.inf, "k1 > 0 never folds"


def test_points_beyond_the_fold_are_invalid_not_inside_the_image():
    """DESIGN §7: with DIST5 the model folds at ≈ 66° off-axis; points beyond it used to project
    back inside the image. Now they are invalid (mask False, q NaN); points just inside stay
    valid and finite."""
    cam = make_camera(DIST5)
    r_f = cam.fold_radius()
    assert 60 < np.degrees(np.arctan(r_f)) < 70, "DIST5 folds ≈ 66° off-axis"
    az = np.radians([10.0, 100.0, 200.0, 290.0])
    # beyond the fold the raw model's radius falls back through 0 (the image centre) at r0
    r_scan = r_f * np.linspace(1.01, 3.0, 4000)
    r0 = r_scan[np.argmin(np.abs(_radial_rd(DIST5, r_scan)))]
    scale = np.array([0.999, 1.0 + 1e-9, 1.0 + FOLD_REL_STEP, r0 / r_f, 2.0, 5.0])
    R, A = np.meshgrid(r_f * scale, az, indexing="ij")
    x_n = np.stack([R * np.cos(A), R * np.sin(A)], -1)
    p_cam = np.concatenate([x_n, np.ones(x_n.shape[:-1] + (1,))], -1) * 0.7
    q, ok = cam.project_cam(p_cam)
    assert ok[0].all() and np.isfinite(q[0]).all(), "just inside the fold: valid"
    assert not ok[1:].any() and np.isnan(q[1:]).all(), "at and beyond the fold: invalid, NaN"
    # the bug this guards: the raw model puts some of those far-off-axis points in the image
    q_raw = cam.distort(x_n[3]) * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    assert cam.in_image(q_raw).all(), "without the check points beyond the fold land inside"
    # the same through project (world frame)
    p_world = cam.T_cam_world.inverse().apply(p_cam)
    q_w, ok_w = cam.project(p_world)
    assert np.array_equal(ok_w, ok), "project and project_cam agree on validity"


def test_unproject_is_consistent_with_the_fold():
    """Pixels whose undistortion lands beyond the fold are invalid; every valid pixel's ray
    projects back to the pixel (round trip ≤ ROUND_TRIP_MAX_PX) and is inside the fold."""
    cam = make_camera(np.array([-0.5, 0.0, 0.0, 0.0]))
    r_f = cam.fold_radius()
    xs = np.linspace(-1.5 * W, 2.5 * W, 161)
    ys = np.linspace(-1.5 * H, 2.5 * H, 121)
    q = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    v, ok = cam.unproject(q, return_valid=True)
    assert ok.any() and (~ok).any(), "the grid spans both sides of the fold"
    assert np.isnan(v[~ok]).all(), "invalid rays are NaN"
    assert np.all(np.hypot(v[ok, 0], v[ok, 1]) < r_f), "valid rays inside the fold"
    q2, ok2 = cam.project_cam(v[ok])
    assert ok2.all(), "a valid ray projects validly"
    err = np.abs(q2 - q[ok]).max()
    assert err <= ROUND_TRIP_MAX_PX, f"max |project(unproject(q)) − q| = {err:.3g} px"
