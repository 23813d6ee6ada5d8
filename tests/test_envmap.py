"""Environment maps: projections, orientation, rotation, energy of the light-basis projection,
bad input."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from facegeo.errors import InputError, ShapeError
from facegeo.frames import light_directions, light_solid_angles
from facegeo.lighting import envmap as E

from conftest import shared_file

#: Pixel round trip directions → pixels → directions, max |Δ| in pixels.
ROUNDTRIP_PX = 1e-9
#: Σ pixel solid angles vs 4π, relative (lat-long exact; disc maps lose a sliver at the rim).
SPHERE_AREA_REL = {"latlong": 1e-12, "mirror-ball": 2e-3, "angular": 2e-3, "cube": 1e-12}

#: Map size (height, width) per projection in the projection tests (a cube: the 4:3 cross).
SIZES = {"latlong": (24, 48), "mirror-ball": (24, 24), "angular": (24, 24), "cube": (24, 32)}
#: Energy Σ_l w_l vs the map's integral, relative, per channel (issue 12).
ENERGY_PAPER_REL = 5e-3
ENERGY_EXACT_REL = 1e-3
#: Same analytic map in two projections: mean radiance per cell, max relative difference.
CROSS_PROJECTION_REL = 0.03


def _const(v):
    return np.ones(v.shape[:-1] + (3,))


def _smooth(v):
    # asymmetric in every axis, strictly positive
    return np.stack([1.0 + 0.5 * v[..., 0], 1.2 + 0.8 * v[..., 1] + 0.1 * v[..., 2],
                     0.7 + 0.3 * v[..., 2] ** 2], axis=-1)


@pytest.mark.parametrize("projection", E.PROJECTIONS)
def test_pixel_directions_round_trip(projection):
    h, w = SIZES[projection]
    d, valid = E.pixel_directions(projection, h, w)
    assert np.allclose(np.linalg.norm(d[valid], axis=-1), 1.0, atol=1e-12)
    q = E.directions_to_pixels(projection, d[valid], h, w)
    yy, xx = np.nonzero(valid)
    assert np.abs(q - np.stack([xx, yy], -1)).max() <= ROUNDTRIP_PX


@pytest.mark.parametrize("projection", E.PROJECTIONS)
def test_pixel_solid_angles_cover_the_sphere(projection):
    h, w = (12 * s for s in SIZES[projection])
    total = E.pixel_solid_angles(projection, h, w).sum()
    assert abs(total / (4 * np.pi) - 1) <= SPHERE_AREA_REL[projection]


def test_latlong_follows_openexr_orientation():
    # Imf::LatLongMap: centre column +Z, left quarter +X, right quarter -X, edges -Z, top +Y.
    h, w = 8, 16
    d, _ = E.pixel_directions("latlong", h, w)
    v = E.directions_to_pixels("latlong", np.eye(3), h, w)
    assert np.allclose(v[0], [w / 4 - 0.5, h / 2 - 0.5])      # +X: left quarter
    assert np.allclose(v[2], [w / 2 - 0.5, h / 2 - 0.5])      # +Z: centre
    q = E.directions_to_pixels("latlong", [[-1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]], h, w)
    assert np.allclose(q[0], [3 * w / 4 - 0.5, h / 2 - 0.5])  # -X: right quarter
    assert np.isclose(q[1, 0] % w, w - 0.5) or np.isclose(q[1, 0], -0.5)  # -Z: the seam
    assert q[2, 1] < 0                                         # +Y above row 0's centre
    assert d[0, 0, 1] > 0.9 and d[-1, 0, 1] < -0.9            # top row up, bottom row down


@pytest.mark.parametrize("projection", ["mirror-ball", "mirrorball", "angular"])
def test_disc_maps_centre_is_plus_z_right_is_plus_x(projection):
    q = E.directions_to_pixels(projection, [[0, 0, 1.0], [1.0, 0, 0], [0, 1.0, 0]], 101, 101)
    assert np.allclose(q[0], [50, 50])
    assert q[1, 0] > 50 and np.isclose(q[1, 1], 50)  # +X on the right
    assert q[2, 1] < 50 and np.isclose(q[2, 0], 50)  # +Y at the top
    # the rim is -Z
    d, valid = E.pixel_directions(projection, 101, 101)
    assert d[50, 0, 2] < -0.95 and d[50, 100, 2] < -0.95  # edge pixel centres, r = 0.99


@pytest.mark.parametrize("projection", E.PROJECTIONS)
def test_axis_lobe_map_colours_per_axis(projection):
    env = E.axis_lobe_map(96, projection=projection)
    for axis, colour in E.AXIS_LOBE_COLORS.items():
        if projection in ("mirror-ball", "angular") and axis == (0, 0, -1):
            continue  # -Z is the disc's rim: a lookup there is a ring of pixels
        got = env.radiance(np.asarray(axis, float))
        assert np.allclose(got, colour, atol=0.05), (axis, got)


def test_rotation_turns_plus_z_toward_plus_x():
    env = E.axis_lobe_map(64).rotated(np.pi / 2)
    assert np.allclose(env.radiance([1.0, 0, 0]), E.AXIS_LOBE_COLORS[(0, 0, 1)], atol=0.05)
    assert np.allclose(env.radiance([0, 0, -1.0]), E.AXIS_LOBE_COLORS[(1, 0, 0)], atol=0.05)
    # the light-basis projection sees the rotation too
    w = E.light_stage_radiance(env, 32, 16)
    l = np.argmax(light_directions(32, 16) @ np.array([1.0, 0, 0]))
    assert w[l, 2] > 5 * max(w[l, 0], w[l, 1])


@pytest.mark.parametrize("projection", ["mirror-ball", "angular", "cube"])
def test_projections_agree_on_the_light_basis(projection):
    ll = E.light_stage_radiance(E.analytic_map(_smooth, 64), 16, 8)
    other = E.light_stage_radiance(E.analytic_map(_smooth, 96 if projection == "cube" else 128,
                                                   projection=projection), 16, 8)
    assert np.max(np.abs(other / ll - 1)) <= CROSS_PROJECTION_REL


@pytest.mark.parametrize("grid", [(32, 16), (64, 32)])
@pytest.mark.parametrize("fn", [_const, _smooth])
def test_energy_analytic(grid, fn):
    env = E.analytic_map(fn, 64)
    integral = env.integral()
    if fn is _const:
        assert np.allclose(integral, 4 * np.pi, rtol=1e-12)
    for sa, tol in (("paper", ENERGY_PAPER_REL), ("exact", ENERGY_EXACT_REL)):
        w = E.light_stage_weights(env, *grid, solid_angle=sa)
        assert np.max(np.abs(w.sum(0) / integral - 1)) <= tol, sa


def test_energy_exact_is_exact_and_paper_reads_high_by_the_midpoint_error():
    env = E.analytic_map(_const, 32)
    w = E.light_stage_weights(env, 16, 8, solid_angle="exact")
    assert np.allclose(w.sum(0), 4 * np.pi, rtol=1e-12)
    w = E.light_stage_weights(env, 16, 8, solid_angle="paper")
    h = np.pi / 16  # half the cell's φ extent: midpoint rule over-reads by h/sin h − 1
    assert np.allclose(w.sum(0) / (4 * np.pi) - 1, h / np.sin(h) - 1, rtol=1e-6)


def test_projection_is_a_cell_integral_not_a_point_sample():
    # A lobe narrower than a cell, off the cell centres: a point sample at the cell centres
    # would miss most of it; the cell integral keeps its energy.
    axis = np.array([0.3, 0.2, 0.93])
    axis /= np.linalg.norm(axis)
    env = E.analytic_map(lambda v: np.maximum(v @ axis, 0)[..., None] ** 1000 * np.ones(3), 128)
    w = E.light_stage_weights(env, 16, 8, solid_angle="exact")
    assert np.allclose(w.sum(0), env.integral(), rtol=1e-9)
    point = env.radiance(light_directions(16, 8)) * light_solid_angles(16, 8, exact=True)[:, None]
    assert abs(point.sum(0)[0] / env.integral()[0] - 1) > 0.2  # the point sample is far off


@pytest.mark.parametrize("name", ["sunset.exr", "studio.exr"])
def test_energy_shared_maps(shared_data, name, caplog):
    path = shared_file(shared_data, f"envmaps/{name}")
    with caplog.at_level(logging.INFO, logger="facegeo.lighting.envmap"):
        env = E.read_envmap(path)
    assert env.image.min() >= 0
    integral = env.integral()
    for grid in ((32, 16), (64, 32)):
        for sa, tol in (("paper", ENERGY_PAPER_REL), ("exact", ENERGY_EXACT_REL)):
            w = E.light_stage_weights(env, *grid, solid_angle=sa)
            assert np.max(np.abs(w.sum(0) / integral - 1)) <= tol, (grid, sa)


def test_direction_weights_voronoi():
    rng = np.random.default_rng(3)
    v = rng.normal(size=(60, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    env = E.analytic_map(_smooth, 64)
    w, areas = E.direction_weights(env, v)
    assert np.isclose(areas.sum(), 4 * np.pi, rtol=1e-9)
    assert np.max(np.abs(w.sum(0) / env.integral() - 1)) <= ENERGY_EXACT_REL
    # a constant environment: each weight is its Voronoi cell's area
    wc, _ = E.direction_weights(E.analytic_map(_const, 64), v)
    assert np.max(np.abs(wc[:, 0] / areas - 1)) <= 0.05  # pixel-level assignment of the cells


def test_light_weights_take_a_grid_or_a_list_of_lights():
    """One entry point for a rig's lights: the grid gets light_stage_weights (either δA rule);
    a full-sphere list with its Voronoi solid angles gets direction_weights' weights; a dome
    (horizon axis) integrates the map above the horizon only, over the list's clipped cells."""
    from facegeo.geometry.lights import LightList
    from facegeo.geometry.rig import LightStage

    env = E.analytic_map(_smooth, 64)
    for sa in ("paper", "exact"):
        np.testing.assert_array_equal(E.light_weights(env, LightStage(n_theta=16, n_phi=8),
                                                      solid_angle=sa),
                                      E.light_stage_weights(env, 16, 8, solid_angle=sa))
    rng = np.random.default_rng(3)
    v = rng.normal(size=(60, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    w_ref, areas = E.direction_weights(env, v)
    full = LightList(directions=v)  # default δA: the Voronoi areas
    np.testing.assert_allclose(full.solid_angles, areas, rtol=1e-9)
    np.testing.assert_allclose(E.light_weights(env, full), w_ref, rtol=1e-12)
    up = v[v[:, 1] > 0.05]
    dome = LightList(directions=up, horizon_axis=(0.0, 1.0, 0.0))
    w = E.light_weights(E.analytic_map(_const, 64), dome)
    # a constant map: each weight is its (clipped) cell's area; together the upper hemisphere
    np.testing.assert_allclose(w[:, 0], dome.solid_angles, rtol=1e-12)
    assert abs(w[:, 0].sum() / (2 * np.pi) - 1) < 1e-6
    lit_below = E.analytic_map(lambda d: np.where(d[..., 1:2] < 0, 1.0, 0.0) * np.ones(3), 64)
    assert np.abs(E.light_weights(lit_below, dome)).max() < 1e-12  # below the horizon: unseen


def test_direction_weights_bad_input():
    env = E.analytic_map(_const, 16)
    with pytest.raises(ShapeError, match="at least 4"):
        E.direction_weights(env, np.eye(3))
    with pytest.raises(InputError, match="unit vectors"):
        E.direction_weights(env, 2 * np.vstack([np.eye(3), -np.eye(3)]))


# --------------------------------------------------------------------------- bad input


def _img(h=16, w=32):
    return np.ones((h, w, 3), np.float32)


def test_nan_inf_rejected():
    for bad in (np.nan, np.inf):
        img = _img()
        img[3, 5, 1] = bad
        with pytest.raises(InputError, match=r"NaN/inf.*row 3, column 5"):
            E.EnvironmentMap(img)


def test_large_negative_rejected_small_negative_clipped(caplog):
    img = _img()
    img[2, 4, 0] = -0.5
    with pytest.raises(InputError, match="negative radiance"):
        E.EnvironmentMap(img)
    img[2, 4, 0] = -0.004
    with caplog.at_level(logging.INFO, logger="facegeo.lighting.envmap"):
        env = E.EnvironmentMap(img)
    assert env.image[2, 4, 0] == 0 and "clipped 1 small negative" in caplog.text


def test_unknown_projection_and_wrong_aspect():
    with pytest.raises(InputError, match="projection.*latlong"):
        E.EnvironmentMap(_img(), "cubemap")
    with pytest.raises(ShapeError, match="2:1"):
        E.EnvironmentMap(_img(16, 16), "latlong")
    with pytest.raises(ShapeError, match="1:1"):
        E.EnvironmentMap(_img(16, 32), "mirrorball")
    with pytest.raises(ShapeError, match=r"\(H, W, 3\)"):
        E.EnvironmentMap(np.ones((4, 8, 3, 2)))


def test_read_envmap_files(tmp_path):
    from facegeo.capture import imageio

    img = E.axis_lobe_map(16).image
    p = imageio.write_image(tmp_path / "lobes.exr", img)
    env = E.read_envmap(p, rotate_deg=90)
    assert np.isclose(env.rotation, np.pi / 2)
    assert np.allclose(env.image, img, rtol=1e-6)
    bad = img.copy()
    bad[1, 1] = np.nan
    p = imageio.write_image(tmp_path / "nan.exr", bad)
    with pytest.raises(InputError, match="nan.exr.*NaN"):
        E.read_envmap(p)
    p8 = imageio.write_image(tmp_path / "ldr.png", (np.clip(img, 0, 1) * 255).astype(np.uint8))
    with pytest.raises(InputError, match="needs a response"):
        E.read_envmap(p8)
    env8 = E.read_envmap(p8, response="srgb")
    assert env8.image.dtype == np.float32 and env8.image.max() <= 1.0


# --------------------------------------------------------------------------- shipped maps

#: Shipped half-float file vs the procedural map it was written from: max |Δ| / max, per map
#: (float16 keeps 11 significant bits: ≤ 2^-11 relative per pixel).
SHIPPED_HALF_REL = 2.0 ** -11


@pytest.mark.parametrize("name", E.SHIPPED_MAPS)
def test_shipped_map_files_are_the_documented_procedural_maps(name):
    # The files in facegeo/data/envmaps must be what procedural_map(name) produces (stored as
    # half floats): a hand-edited or stale file fails here.
    path = E.shipped_map_path(name)
    assert path.is_file(), f"{path} missing: run facegeo.lighting.envmap.write_shipped_maps()"
    assert path.stat().st_size < 64 << 10  # small: the package carries them
    got = E.shipped_map(name)
    want = E.procedural_map(name)
    assert got.image.shape == want.image.shape == (E.SHIPPED_HEIGHT, 2 * E.SHIPPED_HEIGHT, 3)
    assert np.all(np.abs(got.image - want.image) <= SHIPPED_HALF_REL * np.abs(want.image) + 1e-7)


def test_sky_sun_is_where_documented_and_carries_most_energy():
    # Orientation of the sky's sun: the brightest pixel is the one the documented direction
    # maps to (lat-long convention of this module), and the light grid cell nearest the sun
    # direction gets the largest Eq. (4) weight. Its energy (pixels brighter than 100) is
    # > 40 % of the map's integral: a sun-like, all-frequency map.
    from facegeo.frames import nearest_light_index

    env = E.procedural_map("sky")
    sun = np.asarray(E.SKY_SUN["direction"], float)
    sun /= np.linalg.norm(sun)
    q = E.directions_to_pixels("latlong", sun[None], env.height, env.width)[0]
    lum = env.image.sum(-1)
    iy, ix = np.unravel_index(np.argmax(lum), lum.shape)
    assert abs(iy - q[1]) <= 1.0 and abs(ix - q[0]) <= 1.0  # pixel centres are integers
    om = E.pixel_solid_angles("latlong", env.height, env.width)
    assert (om * lum * (lum > 300)).sum() > 0.4 * (om * lum).sum()
    w = E.light_stage_weights(env, 32, 16, solid_angle="exact")
    assert np.argmax(w.sum(1)) == nearest_light_index(sun[None], 32, 16)[0]


def test_studio_key_light_is_front_left_and_above():
    # The key light (brightest, warm) lies toward +X (the subject's left), +Y and +Z: the
    # Eq. (4) weights of lights in that octant carry more than those of the mirrored one.
    env = E.procedural_map("studio")
    d = light_directions(32, 16)
    w = E.light_stage_weights(env, 32, 16, solid_angle="exact").sum(1)
    key = (d[:, 0] > 0) & (d[:, 1] > 0) & (d[:, 2] > 0)
    mirrored = (d[:, 0] < 0) & (d[:, 1] > 0) & (d[:, 2] > 0)
    assert w[key].sum() > 2 * w[mirrored].sum()
    with pytest.raises(InputError, match="name"):
        E.procedural_map("moon")
