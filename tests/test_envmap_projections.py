"""Environment-map projections added for issue 37: cube maps (horizontal cross and strip),
the ``mirror-ball`` spelling, and lat-long conventions other than facegeo's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from facegeo.errors import InputError, ShapeError
from facegeo.geometry.lights import LightList
from facegeo.geometry.rig import LightStage
from facegeo.lighting import envmap as E
from facegeo.lighting._cubemap import cube_texel_solid_angles

#: Cube round trip direction → pixel → direction, max |Δ| in pixels.
ROUNDTRIP_PX = 1e-9
#: Σ of a cube's exact texel solid angles against 4π, absolute (steradians).
CUBE_SPHERE_ABS = 1e-6
#: A uniform cube map's integral against 4π·L, relative.
UNIFORM_INTEGRAL_REL = 1e-6
#: Bilinear lookup of a cube map of a linear function across faces and seams, max |Δ| (the
#: function's range is [0, 2]; measured 0.011 with 16-pixel faces, largest at cube corners).
CUBE_BILINEAR_ABS = 0.02
#: The axis-lobe map as a 96-row lat-long and a 96-row cube cross (32-pixel faces): Eq. (4)
#: weights, max |Δw| / max w (measured 0.4 % on the 32 × 16 grid, 0.6 % on 40 random lights).
CUBE_VS_LATLONG_WEIGHTS_REL = 0.01
#: The same environment rasterised in another lat-long convention and read with the flag:
#: the weights agree to rounding (max |Δw| / max w; the sub-pixel sets are the same).
CONVENTION_WEIGHTS_REL = 1e-9
#: Read without the flag, the front–back mirror moves the +Z lobe's energy to −Z: the weights
#: differ by at least this share of max w.
MIRRORED_WEIGHTS_MIN = 0.5

SIZES = {"cross": (24, 32), "strip": (8, 48)}
AXES = {"+X": (1, 0, 0), "-X": (-1, 0, 0), "+Y": (0, 1, 0), "-Y": (0, -1, 0),
        "+Z": (0, 0, 1), "-Z": (0, 0, -1)}


@pytest.mark.parametrize("layout", ["cross", "strip"])
def test_cube_round_trip_and_exact_solid_angles(layout):
    h, w = SIZES[layout]
    assert E.cube_layout(h, w) == layout
    d, valid = E.pixel_directions("cube", h, w)
    assert valid.sum() == 6 * (h // (3 if layout == "cross" else 1)) ** 2
    assert np.all(np.isnan(d[~valid]))
    q = E.directions_to_pixels("cube", d[valid], h, w)
    yy, xx = np.nonzero(valid)
    assert np.abs(q - np.stack([xx, yy], -1)).max() <= ROUNDTRIP_PX
    for s in (1, 3):
        om = E.pixel_solid_angles("cube", h, w, supersample=s)
        assert abs(om.sum() - 4 * np.pi) <= CUBE_SPHERE_ABS
        assert np.all(om[~np.repeat(np.repeat(valid, s, 0), s, 1)] == 0)
    # the corner texel of a face sees less solid angle than the centre texel (not a flat rule)
    om = E.pixel_solid_angles("cube", h, w)
    assert om[valid].min() < 0.5 * om[valid].max()


def test_cube_solid_angle_matches_the_face_integral():
    # one face split 1 × 1: 4π/6; split 2 × 2: four equal quarters
    a1 = cube_texel_solid_angles(1)
    a2 = cube_texel_solid_angles(2)
    assert abs(a1[0, 0] - 4 * np.pi / 6) <= CUBE_SPHERE_ABS
    assert np.allclose(a2, np.pi / 6, atol=CUBE_SPHERE_ABS)


def test_cube_faces_sit_where_documented():
    # horizontal cross: [+X][+Z][−X][−Z] in the middle row (facegeo axes, the faces OpenGL
    # names −X, +Z, +X, −Z), +Y above +Z, −Y below; the strip in OpenGL's order
    # +X −X +Y −Y +Z −Z, i.e. facegeo's −X, +X, +Y, −Y, +Z, −Z.
    h, w = 24, 32
    a = 8
    cells = {"+X": (0, 1), "+Z": (1, 1), "-X": (2, 1), "-Z": (3, 1), "+Y": (1, 0), "-Y": (1, 2)}
    for name, (c, r) in cells.items():
        q = E.directions_to_pixels("cube", AXES[name], h, w)
        assert np.allclose(q, [c * a + a / 2 - 0.5, r * a + a / 2 - 0.5]), name
    order = ["-X", "+X", "+Y", "-Y", "+Z", "-Z"]
    for c, name in enumerate(order):
        q = E.directions_to_pixels("cube", AXES[name], 8, 48)
        assert np.allclose(q, [c * 8 + 3.5, 3.5]), name
    # unmirrored views from the centre: on the +Z face, +X is to the left and +Y at the top
    q = E.directions_to_pixels("cube", [[0.3, 0.2, 1.0]], h, w)[0]
    assert q[0] < 11.5 and q[1] < 11.5


@pytest.mark.parametrize("layout", ["cross", "strip"])
def test_uniform_cube_map_integrates_to_4pi_L(layout):
    L = np.array([0.5, 2.0, 3.0])
    env = E.analytic_map(lambda v: np.broadcast_to(L, v.shape[:-1] + (3,)), 24 if layout ==
                         "cross" else 8, projection="cube", layout=layout)
    assert np.allclose(env.integral(), 4 * np.pi * L, rtol=UNIFORM_INTEGRAL_REL)


def test_cube_bilinear_is_continuous_across_seams():
    def lin(v):
        return 1.0 + v

    env = E.analytic_map(lin, 48, projection="cube")
    rng = np.random.default_rng(7)
    v = rng.normal(size=(20000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    assert np.abs(env.radiance(v) - lin(v)).max() <= CUBE_BILINEAR_ABS
    # directions straddling the +Z/+X seam (x = z) read from both faces
    t = np.linspace(-0.02, 0.02, 41)
    seam = np.stack([1.0 + t, 0.1 * np.ones_like(t), 1.0 - t], -1)
    seam /= np.linalg.norm(seam, axis=1, keepdims=True)
    assert np.abs(env.radiance(seam) - lin(seam)).max() <= CUBE_BILINEAR_ABS


def test_cube_and_latlong_give_the_same_light_weights():
    ll = E.axis_lobe_map(96)
    cube = E.axis_lobe_map(96, projection="cube")
    rng = np.random.default_rng(3)
    v = rng.normal(size=(40, 3))
    for lights in (LightStage(n_theta=32, n_phi=16), LightList(directions=v)):
        a, b = E.light_weights(ll, lights), E.light_weights(cube, lights)
        assert np.abs(a - b).max() / a.max() <= CUBE_VS_LATLONG_WEIGHTS_REL, type(lights)


def test_cube_shape_errors():
    with pytest.raises(ShapeError, match="horizontal cross"):
        E.EnvironmentMap(np.ones((16, 32, 3), np.float32), "cube")
    with pytest.raises(ShapeError, match="horizontal cross"):
        E.EnvironmentMap(np.ones((10, 13, 3), np.float32), "cube")  # 4:3 but not whole faces
    with pytest.raises(InputError, match="multiple of 3"):
        E.analytic_map(lambda v: np.ones(v.shape[:-1] + (3,)), 32, projection="cube")


def test_mirror_ball_spelling_and_alias():
    img = np.ones((16, 16, 3), np.float32)
    assert E.EnvironmentMap(img, "mirrorball").projection == "mirror-ball"
    assert E.EnvironmentMap(img, "mirror-ball").projection == "mirror-ball"
    assert E.canonical_projection("mirrorball") == "mirror-ball"
    d1, _ = E.pixel_directions("mirrorball", 16, 16)
    d2, _ = E.pixel_directions("mirror-ball", 16, 16)
    assert np.array_equal(d1, d2, equal_nan=True)
    with pytest.raises(InputError, match="mirror-ball"):
        E.canonical_projection("mirror_ball")


@pytest.mark.parametrize("convention", ["u0_at_plus_z", "blender"])
def test_other_latlong_convention_read_with_the_flag(convention, tmp_path):
    from facegeo.capture import imageio

    stage = LightStage(n_theta=32, n_phi=16)
    ref = E.light_weights(E.axis_lobe_map(48), stage)
    other = E.axis_lobe_map(48, convention=convention)  # the same environment, other layout
    path = imageio.write_image(tmp_path / f"{convention}.exr", other.image)
    flagged = E.read_envmap(path, convention=convention)
    assert flagged.convention == convention
    w = E.light_weights(flagged, stage)
    assert np.abs(w - ref).max() / ref.max() <= CONVENTION_WEIGHTS_REL
    assert np.allclose(flagged.radiance([0, 0, 1.0]), E.AXIS_LOBE_COLORS[(0, 0, 1)], atol=0.05)
    # without the flag the map is misread: the +Z (blue) lobe lands elsewhere
    plain = E.read_envmap(path)
    w_plain = E.light_weights(plain, stage)
    assert np.abs(w_plain - ref).max() / ref.max() >= MIRRORED_WEIGHTS_MIN
    assert not np.allclose(plain.radiance([0, 0, 1.0]), E.AXIS_LOBE_COLORS[(0, 0, 1)], atol=0.3)


def test_u0_at_plus_z_is_the_front_back_mirror():
    # columns follow the light grid's azimuth θ: +Z at the left edge, +X the left quarter,
    # −Z the centre; read as facegeo's map, +Z and −Z swap and ±X stay (a mirror, z → −z)
    h, w = 8, 16
    q = E.directions_to_pixels("latlong", [[0, 0, 1.0], [1.0, 0, 0], [0, 0, -1.0], [-1.0, 0, 0]],
                               h, w, convention="u0_at_plus_z")
    assert np.isclose(q[0, 0] % w, w - 0.5) or np.isclose(q[0, 0], -0.5)  # +Z at the seam
    assert np.allclose(q[1:, 0], [w / 4 - 0.5, w / 2 - 0.5, 3 * w / 4 - 0.5])
    img = E.axis_lobe_map(32, convention="u0_at_plus_z").image
    plain = E.EnvironmentMap(img)
    assert np.allclose(plain.radiance([0, 0, -1.0]), E.AXIS_LOBE_COLORS[(0, 0, 1)], atol=0.05)
    assert np.allclose(plain.radiance([1.0, 0, 0]), E.AXIS_LOBE_COLORS[(1, 0, 0)], atol=0.05)


def test_convention_errors():
    with pytest.raises(InputError, match="convention.*facegeo"):
        E.EnvironmentMap(np.ones((8, 16, 3), np.float32), convention="mitsuba2")
    with pytest.raises(InputError, match="lat-long convention"):
        E.EnvironmentMap(np.ones((16, 16, 3), np.float32), "angular", convention="u0_at_plus_z")
    # the rotation keeps the convention
    env = E.axis_lobe_map(16, convention="u0_at_plus_z").rotated(0.3)
    assert env.convention == "u0_at_plus_z"


# --------------------------------------------------------------------------- threading to the CLI


def test_cli_relight_and_render_take_projection_and_convention():
    from facegeo.cli import build_parser

    p = build_parser()
    for cmd in (["relight", "S", "--env", "m.exr"], ["render", "S", "--camera", "front"]):
        a = p.parse_args(cmd + ["--projection", "cube", "--envmap-convention", "u0_at_plus_z"])
        assert (a.projection, a.envmap_convention) == ("cube", "u0_at_plus_z")
        a = p.parse_args(cmd + ["--projection", "mirrorball"])
        assert E.canonical_projection(a.projection) == "mirror-ball"
        assert p.parse_args(cmd).envmap_convention == "facegeo"
        with pytest.raises(SystemExit):
            p.parse_args(cmd + ["--envmap-convention", "mitsuba"])


def test_render_env_loader_threads_projection_and_convention(tmp_path):
    from facegeo.capture import imageio
    from facegeo.pipeline.render import _load_env

    path = imageio.write_image(tmp_path / "u0.exr",
                               E.axis_lobe_map(32, convention="u0_at_plus_z").image)
    env = _load_env(str(path), "latlong", 0.0, "u0_at_plus_z")
    assert env.convention == "u0_at_plus_z"
    assert np.allclose(env.radiance([0, 0, 1.0]), E.AXIS_LOBE_COLORS[(0, 0, 1)], atol=0.05)
    cube = imageio.write_image(tmp_path / "c.exr", E.axis_lobe_map(24, projection="cube").image)
    assert _load_env(str(cube), "cube", 0.0).projection == "cube"
    with pytest.raises(InputError, match="apply to map files"):
        _load_env("sky", "cube", 0.0)
    with pytest.raises(InputError, match="apply to map files"):
        _load_env("axis_lobes", "latlong", 0.0, "blender")


@pytest.fixture(scope="module")
def tiny_scan(tmp_path_factory):
    from facegeo.capture.scan import load_scan
    from facegeo.synth.capture import generate_scan

    root = tmp_path_factory.mktemp("envmap") / "tiny"
    generate_scan(root, "tiny", seed=5)
    return load_scan(root)


@pytest.mark.slow
def test_run_relight_with_the_convention_flag_equals_the_facegeo_map(tiny_scan, tmp_path):
    from facegeo.capture import imageio
    from facegeo.pipeline.relight import run_relight

    scan = tiny_scan
    view = scan.camera_names[0]
    ref_file = imageio.write_image(tmp_path / "ref.exr", E.axis_lobe_map(32).image)
    u0_file = imageio.write_image(tmp_path / "u0.exr",
                                  E.axis_lobe_map(32, convention="u0_at_plus_z").image)
    ref = run_relight(scan.root, ref_file, view=view, out_dir=tmp_path / "a")
    flagged = run_relight(scan.root, u0_file, view=view, out_dir=tmp_path / "b",
                          convention="u0_at_plus_z")
    plain = run_relight(scan.root, u0_file, view=view, out_dir=tmp_path / "c")
    img_ref = imageio.read_image(ref["files"]["exr"])
    img_flag = imageio.read_image(flagged["files"]["exr"])
    img_plain = imageio.read_image(plain["files"]["exr"])
    scale = float(np.abs(img_ref).max())
    assert np.abs(img_flag - img_ref).max() <= CONVENTION_WEIGHTS_REL * scale + 1e-6
    assert np.abs(img_plain - img_ref).max() >= 0.05 * scale  # misread: mirrored front–back
    assert flagged["envmap_convention"] == "u0_at_plus_z" and ref["envmap_convention"] == "facegeo"
    # the flagged and the plain reading of one file write two images, not one over the other
    assert Path(flagged["files"]["exr"]).name != Path(plain["files"]["exr"]).name
    with pytest.raises(InputError, match="shipped map 'sky'"):
        run_relight(scan.root, "sky", view=view, out_dir=tmp_path / "d", convention="blender")
