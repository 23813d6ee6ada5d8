"""A calibration-only witness camera (issue 37): the generator writes it and its reference
images; the stages skip it for frames and calibration places it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from facegeo.capture import imageio
from facegeo.capture.scan import load_scan
from facegeo.geometry.rig import Rig
from facegeo.synth import capture as C

#: Angle between the witness's and each capture camera's direction from the head (degrees):
#: issue 37 asks for 35–45°; measured 40.0 / 40.0 on the default rig.
WITNESS_ANGLE_RANGE_DEG = (35.0, 45.0)
#: Reference pixels inside the witness's true head mask that are lit (> 0): measured 1.000
#: (axis_lobes lights every direction).
REFERENCE_LIT_FRACTION = 0.99
#: Calibrated witness pose against the true one, relative to the reference camera (cam_left;
#: gauge-free), on a 240 × 360 witness scan with 12 shared board views (measured 0.204° and
#: 5.60 mm; the nominal rig.json is 0.463° and 9.15 mm off). The calibration must also beat
#: the nominal rig on both.
WITNESS_ROT_TOL_DEG = 0.4
WITNESS_CENTRE_TOL_MM = 8.0


@pytest.fixture(scope="module")
def witness_scan(tmp_path_factory):
    root = tmp_path_factory.mktemp("witness") / "scan"
    C.generate_scan(root, "tiny", witness=True)
    return root


def _relative_pose(rig, ref: str, name: str):
    """``name``'s rotation and centre in ``ref``'s camera frame (independent of the world
    frame, which calibration chooses for itself)."""
    A, B = rig.camera(ref).T_cam_world, rig.camera(name).T_cam_world
    R = B.R @ A.R.T
    t = B.t - R @ A.t
    return R, -R.T @ t


def _pose_error(rig, truth, ref: str, name: str):
    Rc, cc = _relative_pose(rig, ref, name)
    Rt, ct = _relative_pose(truth, ref, name)
    ang = np.degrees(np.arccos(np.clip((np.trace(Rc @ Rt.T) - 1.0) / 2.0, -1.0, 1.0)))
    return float(ang), float(1000.0 * np.linalg.norm(cc - ct))


def test_manifest_declares_the_witness_calibration_only(witness_scan):
    scan = load_scan(witness_scan)
    assert scan.camera_names == ["cam_left", "cam_right", C.WITNESS_NAME]
    assert scan.cameras_with_frames("calib") == scan.camera_names
    for group in ("calib.projector", "structured_light", "olat"):
        assert scan.cameras_with_frames(group) == ["cam_left", "cam_right"], group
        assert scan.camera_frames(group, C.WITNESS_NAME) == [], group
    key = "images.witness.axis_lobes"
    assert key in scan.reference_keys
    from facegeo.evaluate.views import reference_image_key

    assert reference_image_key(C.WITNESS_NAME, "axis_lobes") == key


def test_witness_viewpoint_and_perturbation(witness_scan):
    nominal = Rig.load(witness_scan / "rig.json")
    truth = Rig.load(witness_scan / "ground_truth" / "rig.json")
    w = nominal.camera(C.WITNESS_NAME)
    for cam in nominal.cameras[:2]:
        cos = float(np.dot(w.center_world, cam.center_world)
                    / np.linalg.norm(w.center_world) / np.linalg.norm(cam.center_world))
        ang = np.degrees(np.arccos(cos))
        assert WITNESS_ANGLE_RANGE_DEG[0] <= ang <= WITNESS_ANGLE_RANGE_DEG[1], (cam.name, ang)
    # faces the head: its optical axis passes within 5 cm of the head centre
    z = w.T_cam_world.R[2]
    c = w.center_world
    assert np.linalg.norm(-c - np.dot(-c, z) * z) < 0.05
    # perturbed like the others, and the capture cameras' errors are those of the scan without it
    assert not np.allclose(truth.camera(C.WITNESS_NAME).K, w.K)
    plain = C.perturbed_rig(Rig(cameras=nominal.cameras[:2], projector=nominal.projector,
                                lights=nominal.lights), 0)
    for cam in plain.cameras:
        np.testing.assert_array_equal(truth.camera(cam.name).K, cam.K)
        np.testing.assert_array_equal(truth.camera(cam.name).T_cam_world.R, cam.T_cam_world.R)


def test_reference_lighting_is_the_render_stages(witness_scan):
    """Same environment, weights and pixel footprint as ``facegeo render``'s default."""
    from facegeo.lighting import envmap as E
    from facegeo.pipeline.reconstruct import RENDER_SUPERSAMPLE
    from facegeo.pipeline.render import builtin_env

    truth = Rig.load(witness_scan / "ground_truth" / "rig.json")
    stage = truth.lights
    w_render = E.field_weights(E.light_weights(builtin_env("axis_lobes"), stage,
                                               solid_angle="paper"), stage)
    np.testing.assert_array_equal(C.witness_weights(stage), w_render)
    assert C.WITNESS_SUPERSAMPLE == RENDER_SUPERSAMPLE
    scan = load_scan(witness_scan)
    ref = np.asarray(imageio.read_image(scan.reference_path("images.witness.axis_lobes")))
    w = truth.camera(C.WITNESS_NAME)
    assert ref.shape == (w.height, w.width, 3) and ref.dtype == np.float32
    mask = np.load(witness_scan / "ground_truth" / "geometry_witness.npz")["mask"]
    lit = (ref.max(axis=2) > 0)[mask].mean()
    assert lit >= REFERENCE_LIT_FRACTION, lit
    assert np.isfinite(ref).all() and not (ref[~mask] != 0).all()


def test_reconstruct_runs_with_a_calibration_only_camera(witness_scan, caplog):
    """``reconstruct`` with default choices to the end; decode, mesh and project skip the
    witness with a log line each. (The tiny preset's 80 × 120 boards cannot be calibrated:
    that stage's recorded error is the known one, docs/synth.md, and the chain falls back.)"""
    import logging

    from facegeo.pipeline.reconstruct import run_reconstruct

    with caplog.at_level(logging.INFO):
        results = {r.name: r for r in run_reconstruct(witness_scan, until="project")}
    for name in ("decode", "mesh", "atlas", "project"):
        assert "error" not in results[name].metrics, (name, results[name].metrics.get("error"))
    assert "no ArUco markers" in str(results["calibrate"].metrics.get("error", ""))
    for stage in ("decode", "mesh", "project"):
        lines = [r.getMessage() for r in caplog.records
                 if r.getMessage().startswith(f"{stage} witness: skipped")]
        assert len(lines) == 1, (stage, lines)
    assert "witness" not in results["project"].metrics.get("cameras", {})


def test_calibration_places_the_witness(tmp_path):
    """A 240 × 360 witness scan (the tiny rig at half the default size: its boards are
    detectable) calibrates, and the calibrated rig holds the witness near its true pose."""
    from facegeo.pipeline.calibrate import run_calibrate

    preset = replace(C.PRESETS["tiny"], name="tiny_calib", camera_scale=1 / 2, calib_views=12,
                     n_theta=4, n_phi=2, sl_supersample=1)
    root = tmp_path / "scan"
    C.generate_scan(root, preset, witness=True)
    run_calibrate(root)
    cal = Rig.load(root / "out" / "calibrate" / "rig.json")
    truth = Rig.load(root / "ground_truth" / "rig.json")
    nominal = Rig.load(root / "rig.json")
    rot, centre = _pose_error(cal, truth, "cam_left", C.WITNESS_NAME)
    rot_nom, centre_nom = _pose_error(nominal, truth, "cam_left", C.WITNESS_NAME)
    assert rot <= WITNESS_ROT_TOL_DEG and centre <= WITNESS_CENTRE_TOL_MM, (rot, centre)
    assert rot < rot_nom and centre < centre_nom, (rot, centre, rot_nom, centre_nom)
