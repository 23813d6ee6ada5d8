"""The calibrate stage's products for OpenCV's tools (issue 35): the rig's extrinsics as one
``stereo_<reference>_<camera>.yml`` per camera pair, read back with ``cv2.FileStorage``."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from facegeo.frames import Pose, look_at
from facegeo.geometry.camera import Camera

#: max |R| / |t| difference (rad-ish / m) of a camera pose composed back from the file's
#: ``R_cam1_world``, ``T_cam1_world``, ``R``, ``T`` (float64 rounding of two products)
POSE_MAX = 1e-12

W, H = 640, 480


def _rig_cameras():
    """Three asymmetric cameras (fx ≠ fy, cx ≠ cy, poses off every axis), one of another size."""
    K = [np.array([[812.3, 0.0, 331.7], [0.0, 809.1, 236.2], [0.0, 0.0, 1.0]]),
         np.array([[790.4, 0.0, 318.2], [0.0, 793.9, 244.6], [0.0, 0.0, 1.0]]),
         np.array([[401.0, 0.0, 158.3], [0.0, 399.2, 121.9], [0.0, 0.0, 1.0]])]
    dist = [np.array([-0.12, 0.08, 4e-4, -3e-4, -0.01]), np.array([-0.09, 0.0, 0.0, 0.0]),
            np.zeros(0)]
    poses = [look_at([-0.06, 0.02, 0.9], [0.0, 0.0, 0.05]),
             look_at([0.08, -0.01, 0.85], [0.01, 0.0, 0.0]),
             look_at([0.01, 0.12, 0.8], [0.0, -0.01, 0.0])]
    sizes = [(W, H), (W, H), (320, 240)]
    return [Camera(n, s[0], s[1], k, d, p)
            for n, s, k, d, p in zip(("cam_b", "cam_a", "cam_small"), sizes, K, dist, poses)]


def _read(path, key):
    """Node ``key`` of an OpenCV file: a matrix, or a number for a scalar node."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        node = fs.getNode(key)
        return node.real() if node.isReal() or node.isInt() else node.mat()
    finally:
        fs.release()


def test_stereo_pairs_read_back_by_opencv_reproduce_intrinsics_and_poses(tmp_path):
    """Each pair file, read by ``cv2.FileStorage`` alone, gives K and dist of both cameras bit
    for bit and both world poses to rounding (camera 2's composed as ``[R | T] ∘ T_cam1_world``:
    ``X_cam2 = R X_cam1 + T``, cv2.stereoCalibrate's convention); the camera of another image
    size is skipped with its reason, not written as a pair OpenCV cannot take."""
    from facegeo.pipeline._calibrate_products import write_stereo_pairs

    cams = _rig_cameras()
    info = write_stereo_pairs(tmp_path, cams, "cam_a")
    assert info["reference"] == "cam_a"
    assert info["files"] == {"cam_b": "stereo_cam_a_cam_b.yml"}
    assert "image size" in info["skipped"]["cam_small"]
    ref, other = cams[1], cams[0]
    path = tmp_path / info["files"]["cam_b"]
    for key, cam in (("1", ref), ("2", other)):
        assert np.array_equal(_read(path, f"M{key}"), cam.K)
        assert np.array_equal(_read(path, f"D{key}").ravel(), cam.dist)
    T1 = Pose(_read(path, "R_cam1_world"), _read(path, "T_cam1_world").ravel())
    T21 = Pose(_read(path, "R"), _read(path, "T").ravel())
    T2 = T21 @ T1
    for T, cam in ((T1, ref), (T2, other)):
        assert np.abs(T.R - cam.T_cam_world.R).max() < POSE_MAX
        assert np.abs(T.t - cam.T_cam_world.t).max() < POSE_MAX
    # E and F as cv2.stereoCalibrate defines them: E = [T]x R, F = K2^-T E K1^-1 (F[2,2] = 1)
    t = _read(path, "T").ravel()
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    E = tx @ _read(path, "R")
    assert np.array_equal(_read(path, "E"), E)
    F = np.linalg.inv(other.K).T @ E @ np.linalg.inv(ref.K)
    assert np.allclose(_read(path, "F"), F / F[2, 2], rtol=0, atol=1e-15 * np.abs(F).max()
                       / abs(F[2, 2]))
    assert _read(path, "image_width") == W and _read(path, "image_height") == H


def test_stereo_pairs_fall_back_to_the_first_camera_when_the_reference_is_not_one(tmp_path):
    """The bundle adjustment's reference may be the projector: the pairs then hang off the
    first camera."""
    from facegeo.pipeline._calibrate_products import write_stereo_pairs

    cams = _rig_cameras()[:2]
    info = write_stereo_pairs(tmp_path, cams, "projector")
    assert info == {"reference": "cam_b", "files": {"cam_a": "stereo_cam_b_cam_a.yml"}}
    assert (tmp_path / "stereo_cam_b_cam_a.yml").is_file()


@pytest.mark.parametrize("suffix", ["M1", "D2", "R", "T", "E", "F"])
def test_stereo_pair_keys_are_the_ones_opencv_samples_read(tmp_path, suffix):
    """stereo_calib.cpp's keys: every one present and non-empty."""
    from facegeo.pipeline._calibrate_products import write_stereo_pairs

    write_stereo_pairs(tmp_path, _rig_cameras()[:2], "cam_a")
    m = _read(tmp_path / "stereo_cam_a_cam_b.yml", suffix)
    assert m is not None and m.size > 0


# ------------------------------------------------------------------ the stage cache


def _counting_stage(runs: list):
    from facegeo.pipeline.cache import StageSpec

    def run(ctx):
        runs.append(dict(ctx.settings))
        (ctx.out_dir / "rig.json").write_text(json.dumps(ctx.settings))
        return {"settings_seen": dict(ctx.settings)}

    return StageSpec("calibrate", run, settings={"model": "auto", "cross_validation": True})


def test_a_commands_stage_products_are_kept_by_the_pipeline(tmp_path):
    """Products made by the stage's own command (``settings_by``) with settings the pipeline's
    defaults lack are reused by a later default pipeline run (not rerun, not replaced); a
    forced rerun keeps the command's settings; a run asking other settings explicitly is
    refused, naming each differing setting with both values, and leaves the products as
    they were."""
    from facegeo.errors import InputError
    from facegeo.pipeline.cache import MANIFEST_NAME, Pipeline

    runs: list = []
    pipe = Pipeline([_counting_stage(runs)])
    mine = {"model": "k1k2", "legacy": True, "loss": "huber", "reference": None,
            "cross_validation": True}
    [r] = pipe.run(tmp_path, settings={"calibrate": mine}, settings_by="facegeo calibrate")
    assert r.ran and runs == [mine]
    manifest = json.loads((tmp_path / "out" / "calibrate" / MANIFEST_NAME).read_text())
    assert manifest["settings_by"] == "facegeo calibrate" and manifest["settings"] == mine
    [r2] = pipe.run(tmp_path)  # facegeo reconstruct / mesh: default settings
    assert not r2.ran and r2.key == r.key and len(runs) == 1
    [r3] = pipe.run(tmp_path, from_stage="calibrate")  # forced: with the command's settings
    assert r3.ran and runs[-1] == mine and r3.key == r.key
    assert json.loads((tmp_path / "out" / "calibrate" / MANIFEST_NAME).read_text())[
        "settings_by"] == "facegeo calibrate"
    [r4] = pipe.run(tmp_path, settings={"calibrate": {"model": "k1k2"}})  # agrees: fine
    assert not r4.ran
    with pytest.raises(InputError, match=r"made by 'facegeo calibrate' with other settings "
                                         r"\(model: 'k1k2' there, 'opencv5' asked\)"):
        pipe.run(tmp_path, settings={"calibrate": {"model": "opencv5"}})
    assert json.loads((tmp_path / "out" / "calibrate" / "rig.json").read_text()) == mine
    # the command itself may change its settings: a new calibration, still the user's
    other = {**mine, "legacy": None}
    [r5] = pipe.run(tmp_path, settings={"calibrate": other}, settings_by="facegeo calibrate")
    assert r5.ran and r5.key != r.key and runs[-1] == other


def test_pipeline_products_without_a_command_follow_the_pipelines_settings(tmp_path):
    """Products the pipeline made itself carry no ``settings_by``: explicit settings rerun the
    stage as before (nothing kept, nothing refused)."""
    from facegeo.pipeline.cache import Pipeline

    runs: list = []
    pipe = Pipeline([_counting_stage(runs)])
    pipe.run(tmp_path)
    [r] = pipe.run(tmp_path, settings={"calibrate": {"model": "opencv5"}})
    assert r.ran and runs[-1]["model"] == "opencv5"


# ------------------------------------------------------------------ OpenCV's stereo chessboards

#: leave-one-view-out held-out RMS of each camera in the stage, px (measured 0.183 / 0.192)
REAL_HELD_OUT_MAX_PX = 0.3
#: σ of the projection where the boards have corners, px ("unc px" of facegeo calibrate;
#: measured 0.297 / 0.154 left / right; over the whole image 3.83 / 0.31)
REAL_COVERED_SIGMA_MAX_PX = 0.5


@pytest.fixture(scope="module")
def opencv_stage(shared_data, tmp_path_factory):
    """OpenCV's stereo chessboards imported as a scan and calibrated by ``run_calibrate`` into
    the scan's own ``out/calibrate`` (the ``facegeo calibrate`` path, ≈ 8 s)."""
    from conftest import shared_file
    from facegeo.capture.datasets import import_dataset
    from facegeo.pipeline.calibrate import run_calibrate

    src = shared_file(shared_data, "calibration/opencv_stereo_chessboards")
    root = tmp_path_factory.mktemp("opencv_stage") / "scan"
    import_dataset("opencv-stereo", src, root)
    return root, run_calibrate(root)


def test_real_stage_reports_model_choice_sigma_and_cross_validation(opencv_stage):
    """Per camera: why each other model was not taken (the rational model refused as a
    degenerate lens), how σ was made honest (the jackknife over 13 views, inflated over the
    formal σ), the leave-one-view-out held-out RMS and the two-halves check; the stereo pair
    file beside the cameras' YAML."""
    root, m = opencv_stage
    for name in ("left", "right"):
        cm = m["cameras"][name]
        assert "degenerate" in cm["model_selection"]["rejected"]["rational8"]
        assert cm["sigma_method"] == "jackknife" and cm["sigma_inflation"] > 1.0
        assert all(cm["std_px"][k] > cm["std_formal_px"][k] for k in ("fx", "cx", "cy"))
        assert cm["reprojection_rms_px"] <= cm["leave_one_out_held_out_rms_px"] * 1.2
        assert cm["leave_one_out_held_out_rms_px"] < REAL_HELD_OUT_MAX_PX
        assert np.isfinite(cm["cross_validation_px"])
        # JPEGs whose corners fit their neighbours better on the stored values than through
        # the declared sRGB curve: refined there, as before (calibration RMS 0.177 / 0.187 px;
        # 0.197 / 0.209 px in linear light)
        assert cm["corner_refinement"] == "encoded"
        # σ of the projection where the boards are (the region of cross_validation_px), the
        # whole image's beside it: the left camera's opencv5 lens extrapolates to its corners
        # (measured covered 0.30 / 0.15 px, image 3.83 / 0.31 px, left / right)
        assert cm["projection_uncertainty_region"] == "covered"
        assert cm["projection_uncertainty_rms_px"] < REAL_COVERED_SIGMA_MAX_PX
        assert cm["projection_uncertainty_rms_px"] < cm["projection_uncertainty_image_rms_px"]
    assert m["opencv_stereo"]["files"] == {"right": "stereo_left_right.yml"}
    assert (root / "out" / "calibrate" / "stereo_left_right.yml").is_file()


def test_a_calibrate_run_is_the_stage_reconstruct_reuses(opencv_stage):
    """``facegeo calibrate``'s products are the pipeline's ``calibrate`` stage: the same
    inputs, and ``facegeo reconstruct`` (here until the stage) takes them as they are."""
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.cache import MANIFEST_NAME
    from facegeo.pipeline.calibrate import COMMAND, calibrate_inputs
    from facegeo.pipeline.reconstruct import reconstruct_pipeline

    root, _ = opencv_stage
    scan = load_scan(root)
    pipe = reconstruct_pipeline(scan)
    spec = next(s for s in pipe.stages if s.name == "calibrate")
    assert [str(p) for p in spec.inputs(root)] == [str(p) for p in calibrate_inputs(scan)]
    manifest = json.loads((root / "out" / "calibrate" / MANIFEST_NAME).read_text())
    assert manifest["settings_by"] == COMMAND
    [r] = pipe.run(root, until="calibrate")
    assert not r.ran and r.key == manifest["key"]
