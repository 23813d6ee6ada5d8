"""facegeo.geometry.rig: the light stage, rig files, the default rig and its shipped JSON."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from facegeo import frames
from facegeo.geometry.camera import Camera
from facegeo.errors import InputError, ScanFormatError
from facegeo.frames import Pose
from facegeo.geometry.rig import LightStage, Rig, default_rig, main

REPO = Path(__file__).resolve().parents[1]
DEFAULT_RIG_FILE = REPO / "calib" / "default_rig.json"

# Tolerances (named, with units).
SHIPPED_FILE_MAX = 1e-12  # max |file value − default_rig() value| (m, px or unitless)
ORIGIN_NEAR_CENTRE_PX = 15.0  # max distance of the projected head centre from the image centre, px
POSITION_MAX_M = 1e-12  # max |position − (center + radius·ω)|, metres


def _flatten(d, prefix=""):
    """Leaves of a nested JSON value as {path: value}."""
    out = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else k))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            out.update(_flatten(v, f"{prefix}[{i}]"))
    else:
        out[prefix] = d
    return out


# --------------------------------------------------------------------------- light stage


def test_light_stage_matches_frames():
    ls = LightStage()
    assert (ls.n_theta, ls.n_phi, ls.radius, ls.n_lights) == (64, 32, 1.5, 2048)
    assert ls.light_order == "theta-fastest"
    assert np.array_equal(ls.directions, frames.light_directions(64, 32))
    assert np.array_equal(ls.solid_angles, frames.light_solid_angles(64, 32))
    # Theta fastest: consecutive lights share φ and step θ.
    theta, phi = frames.direction_angles(ls.directions[:3])
    assert np.allclose(phi, phi[0]) and np.all(np.diff(theta) > 0)


def test_light_positions_are_centre_plus_radius_omega():
    ls = LightStage(n_theta=8, n_phi=4, radius=1.2, center=(0.01, -0.02, 0.03))
    p = ls.positions
    err = np.abs(p - (np.array([0.01, -0.02, 0.03]) + 1.2 * ls.directions)).max()
    assert err <= POSITION_MAX_M, f"max |position - (c + r·ω)| = {err:.3g} m"
    dist_err = np.abs(np.linalg.norm(p - ls.center, axis=-1) - 1.2).max()
    assert dist_err <= POSITION_MAX_M, f"max | |p - c| - r | = {dist_err:.3g} m"


def test_distant_lights_have_no_positions_and_round_trip():
    ls = LightStage(n_theta=8, n_phi=4, radius=math.inf)
    assert ls.is_distant
    with pytest.raises(InputError, match="distant"):
        _ = ls.positions
    d = json.loads(json.dumps(ls.to_dict(), allow_nan=False))
    assert d["radius"] == "inf"
    assert LightStage.from_dict(d) == ls


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"n_theta": 0}, "n_theta"),
        ({"radius": -1.0}, "radius"),
        ({"radius": float("nan")}, "radius"),
        ({"color": (1.0, -0.1, 1.0)}, "color"),
        ({"center": (0.0, 0.0)}, "center"),
    ],
)
def test_bad_light_stage_names_the_field(kwargs, field):
    with pytest.raises(InputError) as info:
        LightStage(**kwargs)
    assert str(info.value).startswith(field)


# --------------------------------------------------------------------------- rig files


def test_save_load_round_trip_is_identical(tmp_path):
    rig = default_rig()
    path = rig.save(tmp_path / "sub" / "rig.json")
    back = Rig.load(path)
    assert back == rig
    assert back.to_dict() == rig.to_dict()
    assert path.read_text() == back.to_json(), "save(load(f)) reproduces the file byte for byte"
    assert not list((tmp_path / "sub").glob(".rig.json.*")), "no temporary files left behind"


def test_rig_without_projector_round_trips(tmp_path):
    rig = Rig(default_rig().cameras[:1], None, LightStage(n_theta=4, n_phi=2, radius=math.inf))
    assert Rig.load(rig.save(tmp_path / "r.json")) == rig


def test_shipped_default_rig_file_equals_default_rig():
    """calib/default_rig.json is what `python -m facegeo.geometry.rig` writes; it must not drift."""
    shipped = _flatten(json.loads(DEFAULT_RIG_FILE.read_text()))
    code = _flatten(default_rig().to_dict())
    assert shipped.keys() == code.keys(), "same fields (regenerate with `python -m facegeo.geometry.rig`)"
    worst = 0.0
    for k, v in code.items():
        if isinstance(v, float):
            worst = max(worst, abs(shipped[k] - v))
        else:
            assert shipped[k] == v, f"{k}: file has {shipped[k]!r}, code has {v!r}"
    assert worst <= SHIPPED_FILE_MAX, f"max |file - code| over numeric fields = {worst:.3g}"
    assert Rig.load(DEFAULT_RIG_FILE).camera_names == ["cam_left", "cam_right"]


def test_main_writes_calib_files(tmp_path):
    assert main([str(tmp_path)]) == 0
    assert Rig.load(tmp_path / "default_rig.json") == default_rig()
    assert (tmp_path / "charuco_board.json").is_file()


def _write(tmp_path, d) -> Path:
    p = tmp_path / "bad_rig.json"
    p.write_text(json.dumps(d))
    return p


def test_malformed_json_names_the_file(tmp_path):
    p = tmp_path / "broken.json"
    p.write_text('{"cameras": [')
    with pytest.raises(ScanFormatError) as info:
        Rig.load(p)
    assert "broken.json" in str(info.value) and "not valid JSON" in str(info.value)
    with pytest.raises(ScanFormatError, match="missing.json"):
        Rig.load(tmp_path / "missing.json")


@pytest.mark.parametrize(
    "edit, key, words",
    [
        (lambda d: d["cameras"][1].pop("K"), "cameras[1].K", "missing field"),
        (lambda d: d["cameras"][0].__setitem__("K", [[1, 0], [0, 1]]), "cameras[0].K", "shape"),
        (lambda d: d["cameras"][0].__setitem__("dist", [0.1, 0.2, 0.3]), "cameras[0].dist",
         "0, 4, 5 or 8"),
        (lambda d: d["cameras"][1].__setitem__("width", -5), "cameras[1].width",
         "positive integer"),
        (lambda d: d["cameras"][0]["T_cam_world"].__setitem__("R", np.eye(3)[::-1].tolist()),
         "cameras[0].T_cam_world", "not a rotation"),
        (lambda d: d["projector"].pop("height"), "projector.height", "missing field"),
        (lambda d: d["lights"].__setitem__("n_phi", "32"), "lights.n_phi", "expected a JSON number"),
        (lambda d: d["lights"].__setitem__("light_order", "phi-fastest"), "lights.light_order",
         "theta-fastest"),
        (lambda d: d.__setitem__("camras", []), "camras", "unknown field"),
        (lambda d: d.pop("cameras"), "cameras", "missing field"),
        (lambda d: d["cameras"][1].__setitem__("name", "cam_left"), "cameras", "unique"),
        # JSON strings and booleans where numbers belong: numpy / int() would accept them
        (lambda d: d["cameras"][0]["K"][0].__setitem__(0, "366"), "cameras[0].K[0][0]",
         "expected a JSON number, got the string '366'"),
        (lambda d: d["cameras"][1].__setitem__("width", "80"), "cameras[1].width",
         "expected a JSON number, got the string '80'"),
        (lambda d: d["cameras"][0].__setitem__("height", True), "cameras[0].height",
         "expected a JSON number, got bool"),
        (lambda d: d["cameras"][0]["dist"].__setitem__(1, None), "cameras[0].dist[1]",
         "expected a JSON number, got null"),
        (lambda d: d["cameras"][1]["T_cam_world"]["t"].__setitem__(2, "1.1"),
         "cameras[1].T_cam_world.t[2]", "got the string '1.1'"),
        (lambda d: d["projector"]["K"][1].__setitem__(1, "1983.5"), "projector.K[1][1]",
         "got the string '1983.5'"),
        (lambda d: d["lights"]["center"].__setitem__(0, "0"), "lights.center[0]",
         "got the string '0'"),
    ],
)
def test_malformed_rig_errors_name_file_and_field(tmp_path, edit, key, words):
    d = default_rig().to_dict()
    edit(d)
    p = _write(tmp_path, d)
    with pytest.raises(ScanFormatError) as info:
        Rig.load(p)
    msg = str(info.value)
    assert "bad_rig.json" in msg, msg
    assert f"[{key}]" in msg, msg
    assert words in msg, msg
    assert info.value.key == key


def test_camera_lookup_lists_valid_names():
    rig = default_rig()
    assert rig.camera("cam_right") is rig.cameras[1]
    with pytest.raises(InputError, match="cam_left, cam_right"):
        rig.camera("cam_centre")


def test_rig_validation():
    cams = default_rig().cameras
    with pytest.raises(InputError, match="at least one"):
        Rig([])
    with pytest.raises(InputError, match="unique"):
        Rig([cams[0], cams[0]])
    with pytest.raises(InputError, match="projector"):
        Rig(cams, projector="proj")


def test_scaled_rig_scales_cameras_not_projector():
    rig = default_rig()
    half = rig.scaled(0.5)
    assert [(c.width, c.height) for c in half.cameras] == [(240, 360), (240, 360)]
    assert half.projector == rig.projector
    assert half.lights == rig.lights
    assert half.cameras[0].fx == rig.cameras[0].fx * 0.5


# --------------------------------------------------------------------------- default rig


def test_default_rig_is_shaped_like_the_paper():
    rig = default_rig()
    left, right = rig.cameras
    assert (left.width, left.height) == (480, 720), "portrait: width 480, height 720"
    for cam in rig.cameras:
        c = cam.center_world
        assert 1.0 <= np.linalg.norm(c) <= 1.2
        assert c[2] > 0, "cameras face the subject, who looks along +Z"
        yaw = math.degrees(math.atan2(c[0], c[2]))
        assert 10.0 <= abs(yaw) <= 20.0
        assert abs(cam.fx / cam.fy - 1.0) > 1e-3, "fx != fy (asymmetric fixture)"
        assert cam.has_distortion
    assert left.center_world[0] < 0 < right.center_world[0]
    assert left.center_world[1] != right.center_world[1], "slightly different heights"
    proj = rig.projector
    assert (proj.width, proj.height) == (1024, 768) and not proj.has_distortion
    assert left.center_world[0] < proj.center_world[0] < right.center_world[0]
    assert proj.center_world[1] > 0, "projector slightly above the cameras' axis"
    assert rig.lights == LightStage(64, 32, 1.5)


def _origin_offset_px(cam: Camera) -> float:
    """Distance of the projected head centre from the image centre (inf if not in front)."""
    q, in_front = cam.project(np.zeros(3))
    if not in_front:
        return math.inf
    return float(np.hypot(q[0] - (cam.width - 1) / 2, q[1] - (cam.height - 1) / 2))


def test_default_cameras_see_the_head_centred_and_whole():
    rig = default_rig()
    for cam in rig.cameras + [rig.projector]:
        off = _origin_offset_px(cam)
        assert off <= ORIGIN_NEAR_CENTRE_PX, f"{cam.name}: head centre {off:.1f} px off centre"
        # A 0.30 m head (±0.15 m in Y, ±0.09 m in X) is inside the image.
        head = np.array([[0, 0.15, 0.05], [0, -0.15, 0.05], [0.09, 0, 0], [-0.09, 0, 0]])
        q, in_front = cam.project(head)
        assert in_front.all() and cam.in_image(q).all(), f"{cam.name}: head leaves the image"
        # Image up is world +Y: the top of the head has the smaller row.
        assert q[0, 1] < q[1, 1]


# Design of the default rig: name -> (yaw about +Y from +Z in degrees, distance m, height m).
DESIGN = {"cam_left": (-15.0, 1.10, 0.035), "cam_right": (15.0, 1.12, -0.020)}
CENTRE_DESIGN_MAX_M = 1e-9  # max |center_world − designed eye|, metres


def _centre_design_error(cam: Camera) -> float:
    yaw, dist, height = DESIGN[cam.name]
    eye = np.array([dist * math.sin(math.radians(yaw)), height, dist * math.cos(math.radians(yaw))])
    return float(np.abs(cam.center_world - eye).max())


def test_default_cameras_sit_at_their_designed_eyes():
    for cam in default_rig().cameras:
        err = _centre_design_error(cam)
        assert err <= CENTRE_DESIGN_MAX_M, f"{cam.name}: max |centre - eye| = {err:.3g} m"


def test_swapped_axes_fail():
    """The checks above are not passed by symmetry: each swapped convention fails one of them."""
    cam = default_rig().cameras[0]
    assert _origin_offset_px(cam) <= ORIGIN_NEAR_CENTRE_PX
    # World/camera pose confusion (T_world_cam used as T_cam_world): the head leaves the centre.
    confused = cam.replace(T_cam_world=cam.T_cam_world.inverse())
    assert _origin_offset_px(confused) > 10 * ORIGIN_NEAR_CENTRE_PX
    # Transposed rotation. A look-at rotation is nearly a half-turn, hence nearly symmetric, so
    # the head stays centred; the camera centre -Rᵀt moves off the designed eye instead.
    R_T = cam.replace(T_cam_world=Pose(cam.T_cam_world.R.T, cam.T_cam_world.t))
    err = _centre_design_error(R_T)
    assert err > 1e-2, f"transposed R: max |centre - eye| = {err:.3g} m should be large"
    # Transposed K is not a valid intrinsic matrix at all.
    with pytest.raises(InputError, match="K"):
        cam.replace(K=cam.K.T)
    # Swapped fx/fy moves a point near the top of the head by more than half a pixel
    # (fx and fy differ by 0.3 %).
    K_sw = cam.K.copy()
    K_sw[0, 0], K_sw[1, 1] = cam.K[1, 1], cam.K[0, 0]
    p = np.array([0.05, 0.14, 0.05])
    d = np.abs(cam.replace(K=K_sw).project(p)[0] - cam.project(p)[0]).max()
    assert d > 0.5, f"max pixel shift from swapping fx and fy = {d:.3f} px"


# --------------------------------------------------------------------------- v2: light lists,
# rigs without lights, uncalibrated projectors

from facegeo.geometry.lights import LightList, LightSet, voronoi_solid_angles
from facegeo.geometry.rig import Projector

#: Absolute tolerance (sr) on Voronoi areas that are exact by symmetry (float64 round-off).
VORONOI_EXACT_SR = 1e-9
#: Worst relative difference between the Voronoi cell and the grid's δA cell of the same
#: light, exact cell areas (the bisector of two rings is a tilted great circle, not the
#: parallel between them): measured 1.16 % at 16 × 8 and 0.080 % at 64 × 32.
VORONOI_VS_GRID_REL = {(16, 8): 0.013, (64, 32): 0.001}


def _cube():
    return np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)


def test_voronoi_solid_angles_of_a_cube_are_an_eighth_of_the_sphere():
    w = voronoi_solid_angles(_cube())
    assert np.abs(w - 4 * math.pi / 8).max() < VORONOI_EXACT_SR


def test_dome_cells_are_clipped_at_the_horizon():
    """The upper four cube vertices as a dome (up = +Y): each cell is the cube's cell clipped at
    the horizon, π/2 sr (exact by symmetry), and the cells sum to 2π. Without the horizon the
    same four lights would split the whole sphere (π each), the bug this guards against."""
    up = _cube()[_cube()[:, 1] > 0]
    w = voronoi_solid_angles(up, [0, 1, 0])
    assert np.abs(w - math.pi / 2).max() < VORONOI_EXACT_SR
    with pytest.raises(InputError, match="below the horizon"):
        voronoi_solid_angles(_cube(), [0, 1, 0])


def test_light_on_the_horizon_gets_half_its_symmetric_cell():
    """Octahedron vertices, dome up = +Y: four lights lie on the horizon. Each octahedron cell is
    4π/6; the zenith keeps all of it, horizon lights keep half: total 2π."""
    d = np.array([[0, 1, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, 0, -1]], float)
    w = voronoi_solid_angles(d, [0, 1, 0])
    assert abs(w[0] - 4 * math.pi / 6) < VORONOI_EXACT_SR
    assert np.abs(w[1:] - 4 * math.pi / 12).max() < VORONOI_EXACT_SR
    assert abs(w.sum() - 2 * math.pi) < VORONOI_EXACT_SR


@pytest.mark.parametrize("n_theta, n_phi", sorted(VORONOI_VS_GRID_REL))
def test_voronoi_weights_match_the_grid_delta_a_on_the_upper_hemisphere(n_theta, n_phi):
    """The light stage grid's upper half as a dome: Voronoi weights against the known δA
    (frames.light_solid_angles, exact cell areas), worst relative difference; the sum is
    exactly 2π."""
    d = frames.light_directions(n_theta, n_phi)
    dA = frames.light_solid_angles(n_theta, n_phi, exact=True)
    upper = d[:, 1] > 0
    w = voronoi_solid_angles(d[upper], [0, 1, 0])
    assert abs(w.sum() - 2 * math.pi) < 1e-9
    assert np.abs(w / dA[upper] - 1).max() < VORONOI_VS_GRID_REL[(n_theta, n_phi)]
    unclipped = voronoi_solid_angles(d[upper])  # the lowest ring would absorb the lower half
    assert np.abs(unclipped / dA[upper] - 1).max() > 1.0


def test_light_list_near_field_positions_and_round_trip(tmp_path):
    center = np.array([0.0, 0.1, 0.0])
    pos = center + 2.0 * _cube() / math.sqrt(3)
    ll = LightList(positions=pos, center=center, intensities=np.linspace(0.5, 1, 8),
                   names=[f"flash{k}" for k in range(8)])
    assert np.abs(np.linalg.norm(ll.directions, axis=1) - 1).max() < 1e-12
    assert np.abs(ll.directions - _cube() / math.sqrt(3)).max() < 1e-12
    assert ll.intensities.shape == (8, 3) and not ll.is_distant and ll.index("flash3") == 3
    rig = Rig([default_rig().cameras[0]], None, ll)
    rig.save(tmp_path / "rig.json")
    back = Rig.load(tmp_path / "rig.json")
    assert back == rig and isinstance(back.lights, LightList)


def test_both_light_kinds_satisfy_the_light_set_protocol():
    for lights in (LightStage(4, 2), LightList(directions=_cube())):
        assert isinstance(lights, LightSet)
        assert lights.directions.shape == (lights.n_lights, 3)
        assert lights.solid_angles.shape == (lights.n_lights,)


@pytest.mark.parametrize("kwargs, words", [
    ({"directions": np.eye(3)[:2].tolist() + [[0, 0, 0]]}, "zero-length"),
    ({"directions": _cube(), "names": ["a"] * 8}, "repeated: a"),
    ({"directions": _cube(), "names": [f"a/{k}" for k in range(8)]}, "not a valid light name"),
    ({"directions": _cube(), "intensities": -np.ones(8)}, "intensities"),
    ({"directions": np.vstack([_cube(), _cube()[:1]])}, "are the same direction"),
    ({}, "exactly one of them"),
])
def test_bad_light_lists_name_the_field(kwargs, words):
    with pytest.raises(InputError, match=words):
        LightList(**kwargs)


def test_rig_without_lights_and_with_an_uncalibrated_projector_round_trips(tmp_path):
    rig = Rig(default_rig().cameras, Projector("proj", 1024, 768), None)
    assert not rig.projector_calibrated and default_rig().projector_calibrated
    rig.save(tmp_path / "rig.json")
    d = json.loads((tmp_path / "rig.json").read_text())
    assert d["lights"] is None and d["projector"] == {"name": "proj", "width": 1024,
                                                      "height": 768, "calibrated": False}
    assert Rig.load(tmp_path / "rig.json") == rig
    d["projector"]["calibrated"] = True
    (tmp_path / "rig.json").write_text(json.dumps(d))
    with pytest.raises(ScanFormatError, match=r"projector.calibrated"):
        Rig.load(tmp_path / "rig.json")


def test_azimuth_elevation_directions_follow_the_grid_convention():
    """Azimuth a and elevation e equal the grid's θ and 90° − φ: the directions agree with
    frames.light_directions on a 8 × 4 grid (max abs difference, unit vectors)."""
    from facegeo.geometry.lights import directions_from_azimuth_elevation

    n_theta, n_phi = 8, 4
    i, j = np.meshgrid(np.arange(n_theta), np.arange(n_phi))
    theta = 360.0 * (i.ravel() + 0.5) / n_theta
    phi = 180.0 * (j.ravel() + 0.5) / n_phi
    d = directions_from_azimuth_elevation(theta, 90.0 - phi)
    assert np.abs(d - frames.light_directions(n_theta, n_phi)).max() < 1e-12
    assert np.allclose(directions_from_azimuth_elevation(90.0, 0.0), [[1.0, 0.0, 0.0]])
    with pytest.raises(InputError, match="elevation_deg"):
        directions_from_azimuth_elevation(0.0, 95.0)
