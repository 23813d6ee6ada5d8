"""Code maps shared by many pixels (facegeo.geometry.code_maps) and the mesh stage's camera-camera
route on cameras that out-resolve the projector (issue 34).

Library tests on analytic staircases; a stage test on the generator's condition of the real
bust: a tiny scan whose projector pixel covers ≈ 4 × 4 camera pixels, Gray code only, once
intact and once with the right camera's frames lost as the real capture lost them
(``sl_missing="issue34"``), both meshed camera against camera (the true rig with the projector
uncalibrated).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from facegeo.errors import InputError
from facegeo.geometry import triangulation as tr
from facegeo.geometry.code_maps import (code_region_size, interpolate_code_map,
                                        shared_code_fraction)

#: Interpolated code of a 4-px staircase over a linear ramp against the ramp, RMS, projector
#: px (measured 0.43 with a 9-px window, 0.41–0.48 for windows 5–13; the staircase itself
#: 1.22, about 4/√12).
STAIRCASE_INTERP_RMS_PX = 0.6

# Stage, tiny preset seed 3, projector_scale 4, Gray only, depth 6. Measured: intact 3,896
# points, area 32,216 mm², mesh p95 3.17 mm; lost frames 3,789 points, 31,101 mm² (0.965 of
# the intact), p95 4.16 mm; without interpolation 319 points (intact) and none (lost frames).
#: Mesh area of the lost-frame scan over the intact one's, at least.
LOST_OVER_INTACT_AREA = 0.9
#: Points with interpolated codes over points without, at least (intact scan).
INTERP_OVER_RAW_POINTS = 5.0
#: Mesh samples in the observed region to the true surface, 95th percentile, mm (80 × 120 px
#: cameras, 4 camera px per projector px: a coarse scan).
TINY_COARSE_MESH_P95_MM = 6.0


def _ramp(H=40, W=60, block=4):
    u = np.broadcast_to(np.arange(W, dtype=np.float64), (H, W))
    v = np.broadcast_to(np.arange(H, dtype=np.float64)[:, None], (H, W))
    true_x = 0.6 * u + 0.2 * v + 3.0  # projector px: the camera out-resolves the projector
    stair = np.floor(true_x / block) * block + (block - 1) / 2.0
    return true_x, stair


def test_shared_code_fraction_and_region_size():
    true_x, stair = _ramp()
    cont = true_x + 0.0
    assert shared_code_fraction(cont, cont) < 0.05  # continuous (phase): nothing shared
    assert shared_code_fraction(stair, np.zeros_like(stair)) > 0.9
    assert code_region_size(stair, np.zeros_like(stair)) > 10
    nan = np.full((5, 5), np.nan)
    assert shared_code_fraction(nan, nan) == 0.0
    assert code_region_size(nan, nan) == 1.0


def test_interpolation_recovers_the_ramp_under_a_staircase():
    true_x, stair = _ramp()
    r = interpolate_code_map(stair, window=9)
    inner = np.s_[5:-5, 5:-5]
    err = r.code[inner] - true_x[inner]
    assert np.isfinite(err).all()
    rms_interp = float(np.sqrt(np.mean(err**2)))
    rms_stair = float(np.sqrt(np.mean((stair[inner] - true_x[inner]) ** 2)))
    assert rms_interp < STAIRCASE_INTERP_RMS_PX < rms_stair
    # σ: the window's scatter about its plane, about the staircase's block / √12
    assert 0.5 * 4 / math.sqrt(12) < float(np.nanmedian(r.sigma)) < 1.5 * 4 / math.sqrt(12)


def test_interpolation_leaves_invalid_and_sparse_pixels_nan():
    true_x, stair = _ramp()
    stair = stair.copy()
    stair[:, 30:] = np.nan
    stair[20, 10] = np.nan
    stair[0:3, 0:3] = np.nan
    r = interpolate_code_map(stair, window=5, min_count=8)
    assert np.isnan(r.code[:, 30:]).all()
    assert np.isnan(r.code[20, 10])
    # an isolated valid pixel (too few neighbours) gets no plane
    lone = np.full((9, 9), np.nan)
    lone[4, 4] = 3.0
    assert np.isnan(interpolate_code_map(lone, window=5).code).all()


def test_interpolation_drops_a_pixel_far_from_its_plane():
    true_x, stair = _ramp()
    stair = stair.copy()
    stair[20, 20] += 40.0  # a wrong code: 10 blocks off
    r = interpolate_code_map(stair, window=9)
    assert np.isnan(r.code[20, 20])
    assert np.isfinite(r.code[20, 22])


@pytest.mark.parametrize("kw, msg", [({"window": 4}, "window"), ({"window": 1}, "window"),
                                     ({"window": 5, "min_count": 2}, "min_count")])
def test_bad_settings_name_the_argument(kw, msg):
    with pytest.raises(InputError, match=msg):
        interpolate_code_map(np.zeros((10, 10)), **kw)


def test_rig_min_angle_follows_a_narrow_rig_and_keeps_a_floor():
    s = np.sin(np.radians(np.full(100, 2.3)))  # 40 mm baseline at 1 m
    assert tr.rig_min_angle_deg(s) == pytest.approx(0.25 * 2.3)
    s = np.sin(np.radians(np.full(100, 30.0)))  # a wide rig: the fixed limit as before
    assert tr.rig_min_angle_deg(s) == tr.MIN_ANGLE_CAP_DEG
    s = np.sin(np.radians(np.full(100, 0.2)))  # edge-on: still rejected
    assert tr.rig_min_angle_deg(s) == tr.MIN_ANGLE_FLOOR_DEG
    assert tr.rig_min_angle_deg(np.array([np.nan])) == tr.MIN_ANGLE_CAP_DEG


@pytest.fixture(scope="module")
def coarse_scans(tmp_path_factory):
    from facegeo.capture.scan import load_scan
    from facegeo.geometry.rig import Projector, Rig
    from facegeo.pipeline.decode import run_decode
    from facegeo.synth.capture import PRESETS, generate_scan

    base = tmp_path_factory.mktemp("coarse")
    fast = replace(PRESETS["tiny"], n_theta=4, n_phi=2, calib_views=1, projector_views=1)
    out = {}
    for name, lost in (("intact", None), ("lost", {"cam_right": "issue34"})):
        generate_scan(base / name, fast, seed=3, projector_scale=4.0, sl_phase_steps=0,
                      sl_missing=lost)
        scan = load_scan(base / name)
        run_decode(scan)
        out[name] = scan
    true_rig = Rig.load(out["intact"].ground_truth_path("rig"))
    p = true_rig.projector
    rig = Rig(true_rig.cameras, Projector(p.name, p.width, p.height), true_rig.lights)
    return out, str(rig.save(base / "rig_uncalibrated.json"))


def _mesh(scan, rig, tmp_path, name, **kw):
    """The mesh stage's metrics, with the evaluation of its products against the generator's
    surface under ``["evaluate"]["mesh"]`` (the stage reads no truth, issue 37)."""
    from facegeo.evaluate.cloud import evaluate_mesh_against_reference
    from facegeo.pipeline.mesh import mesh_products

    dest = tmp_path / name / "mesh"
    dest.mkdir(parents=True)
    m = mesh_products(scan, scan.out_dir / "decode", dest, rig=rig, depth=6, **kw)[0]
    m["evaluate"] = {"mesh": evaluate_mesh_against_reference(scan, dest.parent)}
    return m


def test_out_resolving_cameras_with_lost_frames_mesh_like_intact_ones(coarse_scans, tmp_path):
    scans, rig = coarse_scans
    intact = _mesh(scans["intact"], rig, tmp_path, "intact")
    lost = _mesh(scans["lost"], rig, tmp_path, "lost")
    for m in (intact, lost):
        assert m["triangulation"] == "camera-camera"
        assert all(c["interpolated"] for c in m["code_interpolation"].values())
        assert m["evaluate"]["mesh"]["mesh_p95_error_mm"] < TINY_COARSE_MESH_P95_MM
    assert lost["area_mm2"] >= LOST_OVER_INTACT_AREA * intact["area_mm2"]
    raw = _mesh(scans["intact"], rig, tmp_path, "raw", code_interpolation="off")
    assert intact["points"] >= INTERP_OVER_RAW_POINTS * raw["points"]
    # the camera that lost its row bits decodes coarser blocks: a wider window
    w = lost["code_interpolation"]
    assert w["cam_right"]["window"] > w["cam_left"]["window"]


def test_code_interpolation_setting_is_checked(coarse_scans, tmp_path):
    scans, rig = coarse_scans
    with pytest.raises(InputError, match="code_interpolation"):
        _mesh(scans["intact"], rig, tmp_path, "bad", code_interpolation="sometimes")
    with pytest.raises(InputError, match="min_angle_deg"):
        _mesh(scans["intact"], rig, tmp_path, "bad2", min_angle_deg=95.0)
