"""facegeo.capture.opencv_storage: OpenCV FileStorage calibrations read, written and rescaled."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest

from conftest import shared_file
from facegeo.capture.opencv_storage import (read_matrices, read_opencv_camera,
                                            read_opencv_stereo, rescale_camera,
                                            stereo_extrinsics, write_opencv_camera,
                                            write_opencv_stereo)
from facegeo.errors import InputError
from facegeo.frames import Pose
from facegeo.geometry.camera import Camera

# Tolerances (named, with units).
PAIR_POSE_MAX = 1e-12  # max |R| / |t| (rad-ish / m) difference after composing R, T back
UNITS_T_MAX_M = 1e-15  # max |T| difference after writing in mm and reading back, metres
EPIPOLAR_MAX_PX = 1e-6  # max |q2ᵀ F q1| / |F q1|₂ (distance to the epipolar line), pixels
F_VS_OPENCV_MAX = 1e-6  # max |F − F_cv2| after both are scaled to F[2, 2] = 1
RULE_MAX_PX = 1e-12  # max |c' − (c + ½)s + ½| of a rescaled principal point, pixels
BOX_MEAN_MAX = 1e-4  # max |reduced ramp − predicted centre coordinate|, pixels (float32 image)

W, H = 640, 480
K_ASYM = np.array([[812.3, 0.0, 331.7], [0.0, 809.1, 236.2], [0.0, 0.0, 1.0]])
POSE = Pose.from_rvec_tvec([0.21, -0.37, 0.13], [0.05, -0.08, 1.2])
DISTS = {0: np.zeros(0), 4: np.array([-0.09, 0.05, -2e-4, 5e-4]),
         5: np.array([-0.12, 0.08, 4e-4, -3e-4, -0.01]),
         8: np.array([-0.12, 0.08, 4e-4, -3e-4, -0.01, 0.03, -0.02, 0.006])}

UNDERWORLD_XML = "structured_light/alexander_quarter/{cam}/calib/output/calib.xml"


def _camera(name="cam_a", dist=DISTS[5], pose=POSE, K=K_ASYM, size=(W, H)) -> Camera:
    return Camera(name, size[0], size[1], K, dist, pose)


def _write_yml(path, **entries):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in entries.items():
        fs.write(k, v)
    fs.release()
    return path


# ------------------------------------------------------------------ round trips


@pytest.mark.parametrize("n_dist", sorted(DISTS))
@pytest.mark.parametrize("suffix", [".yml", ".xml"])
def test_camera_round_trips_through_opencv_exactly(tmp_path, n_dist, suffix):
    """Camera → file → cv2.FileStorage gives the same K, dist, R, T bit for bit (17 digits),
    and read_opencv_camera gives back an equal Camera."""
    cam = _camera(dist=DISTS[n_dist])
    path = write_opencv_camera(tmp_path / f"cam{suffix}", cam)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        assert int(fs.getNode("image_width").real()) == W
        assert int(fs.getNode("image_height").real()) == H
        assert np.array_equal(fs.getNode("camera_matrix").mat(), cam.K)
        d = fs.getNode("distortion_coefficients").mat()
        assert np.array_equal(np.zeros(0) if d is None else d.ravel(), cam.dist)
        assert np.array_equal(fs.getNode("R").mat(), cam.T_cam_world.R)
        assert np.array_equal(fs.getNode("T").mat().ravel(), cam.T_cam_world.t)
    finally:
        fs.release()
    assert read_opencv_camera(path, "cam_a") == cam


def test_writer_is_atomic_and_writes_units_and_extras(tmp_path):
    cam = _camera()
    path = write_opencv_camera(tmp_path / "cam_mm.yml", cam, units=1e-3,
                               extra={"avg_reprojection_error": 0.25,
                                      "per_view_reprojection_errors": [0.2, 0.3]})
    assert [p.name for p in tmp_path.iterdir()] == ["cam_mm.yml"]  # no temporary left behind
    m = read_matrices(path, ["T", "per_view_reprojection_errors"])
    assert m["T"].ravel() == pytest.approx(cam.T_cam_world.t * 1e3, rel=1e-15)
    assert m["per_view_reprojection_errors"].shape == (2, 1)
    back = read_opencv_camera(path, "cam_a", units=1e-3)
    assert np.abs(back.T_cam_world.t - cam.T_cam_world.t).max() < UNITS_T_MAX_M
    no_pose = write_opencv_camera(tmp_path / "intr.yml", cam, pose=False)
    assert read_opencv_camera(no_pose, "c").T_cam_world == Pose.identity()
    with pytest.raises(InputError, match="suffix"):
        write_opencv_camera(tmp_path / "cam.txt", cam)


def test_calibrate_stage_yaml_is_the_same_writer(tmp_path):
    """facegeo calibrate's <camera>.yml comes from write_opencv_camera (no pose)."""
    from facegeo.pipeline._calibrate_products import write_yaml

    cam = _camera()
    write_yaml(tmp_path / "cam.yml", cam, 0.25, [0.2, 0.3])
    back = read_opencv_camera(tmp_path / "cam.yml", "cam_a")
    assert np.array_equal(back.K, cam.K) and np.array_equal(back.dist, cam.dist)
    assert read_matrices(tmp_path / "cam.yml", ["avg_reprojection_error"])[
        "avg_reprojection_error"].ravel().tolist() == [0.25]


def test_stereo_pair_round_trip_and_fundamental_matrix_against_opencv(tmp_path):
    """write_opencv_stereo → read_opencv_stereo gives both cameras back in the same world frame;
    F satisfies the epipolar constraint and equals cv2.findFundamentalMat's (8-point, exact
    correspondences) after normalisation."""
    from facegeo.frames import look_at

    a = _camera("left", dist=np.zeros(0), pose=look_at([-0.06, 0.02, 0.9], [0.0, 0.0, 0.05]))
    K_b = np.array([[790.4, 0.0, 318.2], [0.0, 793.9, 244.6], [0.0, 0.0, 1.0]])
    b = _camera("right", dist=np.zeros(0), K=K_b,
                pose=look_at([0.08, -0.01, 0.85], [0.01, 0.0, 0.0]))
    path = write_opencv_stereo(tmp_path / "stereo.yml", a, b, units=1e-3)
    a2, b2 = read_opencv_stereo(path, units=1e-3)
    for c, c2 in ((a, a2), (b, b2)):
        assert c2.name == c.name and np.array_equal(c2.K, c.K) and c2.size == c.size
        assert np.abs(c2.T_cam_world.R - c.T_cam_world.R).max() < PAIR_POSE_MAX
        assert np.abs(c2.T_cam_world.t - c.T_cam_world.t).max() < PAIR_POSE_MAX
    m = read_matrices(path, ["R", "T", "E", "F"])
    ext = stereo_extrinsics(a, b, units=1e-3)
    assert np.array_equal(m["F"], ext["F"]) and np.array_equal(m["E"], ext["E"])
    rng = np.random.default_rng(3)
    p = rng.uniform([-0.08, -0.08, -0.05], [0.08, 0.08, 0.08], (40, 3))
    q1, _ = a.project(p)
    q2, _ = b.project(p)
    h1 = np.c_[q1, np.ones(len(q1))]
    h2 = np.c_[q2, np.ones(len(q2))]
    lines = h1 @ m["F"].T
    dist_px = np.abs(np.einsum("ij,ij->i", h2, lines)) / np.linalg.norm(lines[:, :2], axis=1)
    assert dist_px.max() < EPIPOLAR_MAX_PX
    F_cv, _ = cv2.findFundamentalMat(q1, q2, cv2.FM_8POINT)
    assert np.abs(F_cv / F_cv[2, 2] - m["F"]).max() < F_VS_OPENCV_MAX * np.abs(m["F"]).max()


def test_stereo_writer_refuses_two_image_sizes(tmp_path):
    with pytest.raises(InputError, match="one image size"):
        write_opencv_stereo(tmp_path / "s.yml", _camera("a"), _camera("b", size=(320, 240)))


# ------------------------------------------------------------------ real files


def _xml_matrix(path, tag):
    """An opencv-matrix of a calib.xml read with ElementTree (an independent reader)."""
    node = ET.parse(path).getroot().find(f"Camera/{tag}")
    rows, cols = int(node.find("rows").text), int(node.find("cols").text)
    return np.array(node.find("data").text.split(), float).reshape(rows, cols)


@pytest.mark.parametrize("cam", ["leftCam", "rightCam"])
def test_3dunderworld_calib_xml_reads(shared_data, cam):
    """The scanner's calib.xml: K, the 5 distortion terms, R and T (mm → m) and the image size
    equal the file's numbers (read again with ElementTree)."""
    path = shared_file(shared_data, UNDERWORLD_XML.format(cam=cam))
    c = read_opencv_camera(path, cam, units=1e-3)
    assert c.size == (4896, 3264)
    assert np.array_equal(c.K, _xml_matrix(path, "Matrix"))
    assert np.array_equal(c.dist, _xml_matrix(path, "Distortion").ravel())
    assert np.array_equal(c.T_cam_world.R, _xml_matrix(path, "Rotation"))
    assert np.array_equal(c.T_cam_world.t, _xml_matrix(path, "Translation").ravel() * 1e-3)
    # the bust stands about a metre in front of each camera (world origin on the extr board)
    assert 0.8 < np.linalg.norm(c.center_world) < 1.2


def test_opencv_sample_calibrations_read(shared_data):
    """OpenCV's sample outputs: calibration's left_intrinsics.yml (with image size), the
    tutorial's yml without a size (given instead), stereo_calib's intrinsics.yml (a pair whose
    extrinsics are not shipped: the error says so)."""
    root = "calibration/opencv_stereo_chessboards/"
    left = read_opencv_camera(shared_file(shared_data, root + "left_intrinsics.yml"), "left")
    assert left.size == (640, 480) and left.fx == pytest.approx(535.9157, abs=1e-4)
    tut = shared_file(shared_data, root + "tutorial_camera_params.yml")
    with pytest.raises(InputError, match=r"tutorial_camera_params\.yml \[image_width\]"):
        read_opencv_camera(tut)
    assert read_opencv_camera(tut, size=(640, 480)).cx == pytest.approx(324.099)
    intr = shared_file(shared_data, root + "intrinsics.yml")
    with pytest.raises(InputError, match="read_opencv_stereo"):
        read_opencv_camera(intr)
    with pytest.raises(InputError, match=r"intrinsics\.yml \[R\]: missing.*extrinsics"):
        read_opencv_stereo(intr, size=(640, 480))


def test_stereo_calib_pair_with_extrinsics_file(tmp_path):
    """stereo_calib's two files: intrinsics.yml (M1, D1, M2, D2) and extrinsics.yml (R, T, R1,
    ...); camera 1 is the world frame, camera 2 is R, T from it."""
    R = cv2.Rodrigues(np.array([0.02, -0.15, 0.01]))[0]
    T = np.array([[-3.1], [0.05], [0.12]])  # board units (squares of 25 mm)
    K2 = K_ASYM + np.diag([3.0, -2.0, 0.0])
    intr = _write_yml(tmp_path / "intrinsics.yml", M1=K_ASYM, D1=DISTS[5].reshape(1, 5),
                      M2=K2, D2=DISTS[4].reshape(1, 4))
    extr = _write_yml(tmp_path / "extrinsics.yml", R=R, T=T, R1=np.eye(3), R2=np.eye(3))
    a, b = read_opencv_stereo(intr, extr, size=(W, H), units=0.025)
    assert a.T_cam_world == Pose.identity()
    assert np.array_equal(b.K, K2) and np.array_equal(b.dist, DISTS[4])
    assert np.abs(b.T_cam_world.t - T.ravel() * 0.025).max() < 1e-15
    assert np.array_equal(b.T_cam_world.R, R)


# ------------------------------------------------------------------ distortion lengths


def test_distortion_lengths_12_and_14(tmp_path):
    d12 = np.r_[DISTS[8], np.zeros(4)]
    p = _write_yml(tmp_path / "c12.yml", camera_matrix=K_ASYM, distortion_coefficients=d12,
                   image_width=W, image_height=H)
    assert np.array_equal(read_opencv_camera(p).dist, DISTS[8])  # zero thin prism: same lens
    d12[9] = 1e-3
    p = _write_yml(tmp_path / "c12b.yml", camera_matrix=K_ASYM, distortion_coefficients=d12,
                   image_width=W, image_height=H)
    with pytest.raises(InputError, match=r"c12b\.yml \[distortion_coefficients\]: 12 .*s2 = "):
        read_opencv_camera(p)
    d14 = np.r_[DISTS[8], np.zeros(4), [0.01, 0.0]]
    p = _write_yml(tmp_path / "c14.yml", camera_matrix=K_ASYM, distortion_coefficients=d14,
                   image_width=W, image_height=H)
    with pytest.raises(InputError, match="tau_x = 0.01"):
        read_opencv_camera(p)
    p = _write_yml(tmp_path / "c6.yml", camera_matrix=K_ASYM,
                   distortion_coefficients=np.zeros(6), image_width=W, image_height=H)
    with pytest.raises(InputError, match="6 distortion coefficients"):
        read_opencv_camera(p)


# ------------------------------------------------------------------ bad input


def test_missing_keys_name_the_file_and_the_key(tmp_path):
    p = _write_yml(tmp_path / "no_dist.yml", camera_matrix=K_ASYM, image_width=W,
                   image_height=H)
    with pytest.raises(InputError, match=r"no_dist\.yml \[distortion_coefficients\]: missing"):
        read_opencv_camera(p)
    # the 3DUNDERWORLD spelling requires the pose
    fs = cv2.FileStorage(str(tmp_path / "calib.xml"), cv2.FILE_STORAGE_WRITE)
    fs.startWriteStruct("Camera", cv2.FileNode_MAP)
    fs.write("Calibrated", 1)
    fs.write("Matrix", K_ASYM)
    fs.write("Distortion", DISTS[5].reshape(1, 5))
    fs.write("Rotation", np.eye(3))
    fs.write("Height", H)
    fs.write("Width", W)
    fs.endWriteStruct()
    fs.release()
    with pytest.raises(InputError, match=r"calib\.xml \[Camera/Translation\]: missing"):
        read_opencv_camera(tmp_path / "calib.xml", units=1e-3)
    # only one of R, T in OpenCV's spelling
    p = _write_yml(tmp_path / "half_pose.yml", camera_matrix=K_ASYM,
                   distortion_coefficients=DISTS[5], image_width=W, image_height=H, R=np.eye(3))
    with pytest.raises(InputError, match=r"half_pose\.yml \[T\]: missing"):
        read_opencv_camera(p)


def test_files_that_are_not_calibrations(tmp_path):
    png = tmp_path / "board.png"
    cv2.imwrite(str(png), np.zeros((8, 8), np.uint8))
    with pytest.raises(InputError, match=r"board\.png: not an OpenCV FileStorage file"):
        read_opencv_camera(png)
    other = _write_yml(tmp_path / "imagelist.yml", images="left01.jpg", nframes=13)
    with pytest.raises(InputError, match=r"imagelist\.yml \[camera_matrix\]: missing.*"
                                         r"top-level keys are images, nframes"):
        read_opencv_camera(other)
    with pytest.raises(InputError, match="not found"):
        read_opencv_camera(tmp_path / "absent.yml")
    skew = K_ASYM.copy()
    skew[0, 1] = 0.5
    p = _write_yml(tmp_path / "skew.yml", camera_matrix=skew, distortion_coefficients=DISTS[5],
                   image_width=W, image_height=H)
    with pytest.raises(InputError, match=r"skew\.yml \[camera_matrix\]: K: .*zero skew"):
        read_opencv_camera(p)
    p = _write_yml(tmp_path / "words.yml", camera_matrix="K", distortion_coefficients=DISTS[5],
                   image_width=W, image_height=H)
    with pytest.raises(InputError, match=r"words\.yml \[camera_matrix\]: expected a 3 × 3 "
                                         r"camera matrix, got the string 'K'"):
        read_opencv_camera(p)


# ------------------------------------------------------------------ rescaling


def test_rescale_camera_follows_the_pixel_centre_rule():
    cam = _camera(size=(4896, 3264), K=np.array([[12217.4, 0.0, 2301.66],
                                                 [0.0, 12215.6, 1689.80], [0.0, 0.0, 1.0]]))
    q = rescale_camera(cam, 1224, 816)
    s = 0.25
    assert q.size == (1224, 816)
    assert (q.fx, q.fy) == (cam.fx * s, cam.fy * s)
    assert abs(q.cx - ((cam.cx + 0.5) * s - 0.5)) < RULE_MAX_PX
    assert abs(q.cy - ((cam.cy + 0.5) * s - 0.5)) < RULE_MAX_PX
    assert np.array_equal(q.dist, cam.dist) and q.T_cam_world == cam.T_cam_world
    back = rescale_camera(q, 4896, 3264)
    assert np.abs(back.K - cam.K).max() < 1e-9
    assert rescale_camera(cam, 4896, 3264) is cam
    with pytest.raises(InputError, match=r"scales x by 0.25 but y by 0.5"):
        rescale_camera(cam, 1224, 1632)


@pytest.mark.parametrize("n", [2, 4])
def test_pixel_centre_rule_is_what_an_area_reduction_does(n):
    """A ramp whose value is each pixel's x (resp. y) coordinate, reduced by cv2.resize
    INTER_AREA by n, holds at reduced pixel c' the full-resolution coordinate
    c = (c' + ½)·n − ½ — the inverse of the rule rescale_camera applies."""
    h, w = 12 * n, 16 * n
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    for ramp, axis in ((xs, 1), (ys, 0)):
        small = cv2.resize(ramp, (w // n, h // n), interpolation=cv2.INTER_AREA)
        c_small = np.arange(small.shape[axis], dtype=np.float64)
        expected = (c_small + 0.5) * n - 0.5
        got = small.mean(axis=1 - axis)
        assert np.abs(got - expected).max() < BOX_MEAN_MAX
