"""Geometric shadow maps and shadow-consistent bilinear taps (facegeo.surface.shadows).

The scene is analytic: a tessellated ground plane z = 0 under a square occluder at height
``H_OCC``; a light at a known position casts the square's shadow, whose outline on the plane is
the square projected from the light — so which plane points are lit is known exactly, and a
camera looking down at the plane sees a frame whose values are known at every pixel centre.
"""

from __future__ import annotations

import numpy as np
import pytest

from facegeo.errors import InputError, ShapeError
from facegeo.frames import look_at
from facegeo.geometry.camera import Camera
from facegeo.geometry.lights import LightList
from facegeo.surface.atlas import vertex_normals
from facegeo.surface.reflectance import bilinear_taps, frame_sampler, sample_frame, sample_taps
from facegeo.surface.shadows import ShadowRays, lifted_origins, shadow_taps
from facegeo.surface.visibility import RayScene

#: Height (m) of the occluding square over the plane, its half-size (m) and centre.
H_OCC, HALF, CENTRE = 0.05, 0.03, np.array([0.01, -0.005])
#: Light positions (m): one steep and oblique, one lower (a longer shadow).
LIGHTS = np.array([[0.21, 0.13, 0.6], [-0.3, 0.12, 0.45]])
#: A distant light's direction (toward it).
DISTANT = np.array([0.3, -0.2, 0.8]) / np.linalg.norm([0.3, -0.2, 0.8])
#: A light between the plane and the square (under its centre): the square is beyond it.
UNDER = np.array([0.01, -0.005, 0.03])
#: A grazing light: n·l ≈ 0.1 on the plane, below SHADOW_TAPS_MIN_COS, with a long shadow.
GRAZING = np.array([-1.0, 0.05, 0.11])
#: Each side of a shadow outline holds at least this many of the compared points / samples.
MIN_PER_SIDE, MIN_EDGE_SAMPLES = 100, 20
#: Plain bilinear's mean error at the straddling samples of a 0/1 edge (≈ 0.17 measured; 0.25
#: for edges uniformly placed between pixel centres): what the taps remove.
BILINEAR_EDGE_ERR_MIN = 0.1
#: Points within this distance (m) of the analytic shadow outline are not compared (the ray
#: origins are lifted eps = 1e-5 × scene size off the plane; float32 rays).
EDGE_MARGIN = 2e-4
#: Renormalised float32 bilinear weights sum to 1 within this (a lit sample reads 1 − 6e-8).
WEIGHT_SUM_TOL = 1e-6
#: Linearity for one light: max |S(a + b) − S(a) − S(b)| relative to max |S(a + b)|.
LINEARITY_REL_TOL = 1e-6


def _plane_and_square(n: int = 24, size: float = 0.3):
    """Plane z = 0 over [-size, size]² as an n × n grid (normals +z), and the occluder square
    at z = H_OCC (normals −z toward the plane, two triangles), in one mesh."""
    xs = np.linspace(-size, size, n + 1)
    X, Y = np.meshgrid(xs, xs)
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    sx, sy = CENTRE
    sq = np.array([[sx - HALF, sy - HALF, H_OCC], [sx + HALF, sy - HALF, H_OCC],
                   [sx + HALF, sy + HALF, H_OCC], [sx - HALF, sy + HALF, H_OCC]])
    k = len(V)
    Fs = np.array([[k, k + 2, k + 1], [k, k + 3, k + 2]])  # wound to face −z
    return np.concatenate([V, sq]), np.concatenate([F, Fs])


def _analytic_lit(xy: np.ndarray, light: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For plane points ``xy`` ``(P, 2)``: lit by the point light (not in the square's
    shadow), and the distance (m, on the plane) to the shadow's outline."""
    # the segment from (x, y, 0) to the light crosses z = H_OCC at s = H_OCC / light_z
    s = H_OCC / light[2]
    cross = xy + s * (light[None, :2] - xy)
    off = np.abs(cross - CENTRE[None, :]) - HALF  # inside the square where both < 0
    inside = (off < 0).all(axis=1)
    # distance to the outline in the crossing plane, scaled back to the plane (1 / (1 − s))
    d_out = np.where(inside, -off.max(axis=1), np.linalg.norm(np.maximum(off, 0), axis=1))
    return ~inside, d_out / (1 - s)


@pytest.fixture(scope="module")
def scene():
    V, F = _plane_and_square()
    return V, F, ShadowRays(RayScene(V, F), vertex_normals(V, F))


def _on_plane(rays: ShadowRays, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Face and barycentrics of the plane at positions ``xy`` ``(P, 2)`` (traced from below,
    so the occluder does not get in the way)."""
    o = np.concatenate([xy, np.full((len(xy), 1), -0.2)], axis=1)
    h = rays.scene.closest_hit(o, np.broadcast_to([0.0, 0.0, 1.0], o.shape),
                               fields=("face", "bary"))
    assert h.hit.all() and (h.face < len(rays.scene.faces) - 2).all()
    return h.face, h.bary


def _points_on_plane(rays: ShadowRays, xy: np.ndarray):
    return rays.points(*_on_plane(rays, xy))


def test_lifted_origins_flat_and_convex():
    V, F = _plane_and_square()
    rng = np.random.default_rng(0)
    face = rng.integers(0, len(F) - 2, 500)
    bary = rng.dirichlet(np.ones(3), 500)
    p = np.einsum("pk,pkc->pc", bary, V[F[face]])
    # flat: every vertex tangent plane holds the point, nothing moves
    np.testing.assert_array_equal(lifted_origins(V, F, vertex_normals(V, F), p, face), p)
    # convex: a coarse sphere's face points move out toward the sphere, never inward
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    Vs, Fs = np.asarray(ico.vertices), np.asarray(ico.faces)
    fs = rng.integers(0, len(Fs), 500)
    bs = rng.dirichlet(np.ones(3), 500)
    ps = np.einsum("pk,pkc->pc", bs, Vs[Fs[fs]])
    lifted = lifted_origins(Vs, Fs, Vs / 0.1, ps, fs)
    r0, r1 = np.linalg.norm(ps, axis=1), np.linalg.norm(lifted, axis=1)
    assert (r1 >= r0 - 1e-15).all() and (r1 > r0).mean() > 0.9


@pytest.mark.parametrize("k", [0, 1])
def test_lit_matches_the_analytic_shadow(scene, k):
    V, F, rays = scene
    rng = np.random.default_rng(k)
    xy = rng.uniform(-0.1, 0.1, (4000, 2))
    pts = _points_on_plane(rays, xy)
    truth, dist = _analytic_lit(xy, LIGHTS[k])
    got = rays.lit(pts, position=LIGHTS[k])
    far = dist > EDGE_MARGIN
    assert min((~truth[far]).sum(), truth[far].sum()) > MIN_PER_SIDE  # both sides sampled
    np.testing.assert_array_equal(got[far], truth[far])
    # a subset of rows gives the same answers
    rows = np.flatnonzero(far)[::7]
    np.testing.assert_array_equal(rays.lit(pts, rows, position=LIGHTS[k]), got[rows])


def test_lit_distant_light_facing_and_segment_end(scene):
    V, F, rays = scene
    rng = np.random.default_rng(5)
    xy = rng.uniform(-0.1, 0.1, (3000, 2))
    pts = _points_on_plane(rays, xy)
    truth, dist = _analytic_lit(xy, DISTANT * 1e4)  # a distant light: a far point light's limit
    got = rays.lit(pts, direction=DISTANT)
    keep = dist > EDGE_MARGIN
    assert min((~truth[keep]).sum(), truth[keep].sum()) > MIN_PER_SIDE
    np.testing.assert_array_equal(got[keep], truth[keep])
    # a light below the plane: every plane point faces away (attached shadow)
    assert not rays.lit(pts, direction=-DISTANT).any()
    # the segment ends at the light: the square beyond a light under it casts nothing
    assert rays.lit(pts, position=UNDER).all()
    with pytest.raises(InputError, match="position or its direction"):
        rays.lit(pts)
    with pytest.raises(InputError, match="integer row indices"):
        rays.lit(pts, np.ones(len(xy), bool), direction=DISTANT)


@pytest.fixture(scope="module")
def sphere():
    """A coarse icosphere (radius 0.1 m, 320 faces) with radial shading normals, and 20,000
    random points on its faces."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    V, F = np.asarray(ico.vertices), np.asarray(ico.faces)
    rays = ShadowRays(RayScene(V, F), V / 0.1)
    rng = np.random.default_rng(2)
    face = rng.integers(0, len(F), 20000)
    return V, F, rays, face, rays.points(face, rng.dirichlet(np.ones(3), 20000))


#: A light over the sphere (m).
SPHERE_LIGHT = np.array([0.4, 0.9, 0.2])


def test_terminator_one_ring_counts_as_lit(sphere):
    """A coarse convex sphere casts no shadow on itself: every point whose shading normal faces
    the light is lit, although a ray from the faceted surface meets a neighbouring facet."""
    V, F, rays, face, pts = sphere
    light = SPHERE_LIGHT
    to_l = light[None, :] - pts.origin
    facing = np.einsum("pc,pc->p", pts.n, to_l) > 0
    got = rays.lit(pts, position=light)
    np.testing.assert_array_equal(got, facing)
    # the same through rows (how ShadowTaps asks for its texels)
    rows = np.flatnonzero(facing)[::3]
    np.testing.assert_array_equal(rays.lit(pts, rows, position=light), facing[rows])
    # the origins are lifted (Hanika): from the faceted point the same segments self-shadow
    np.testing.assert_array_equal(pts.origin, lifted_origins(V, F, V / 0.1, pts.p, face))
    geo = np.cross(V[F[face, 1]] - V[F[face, 0]], V[F[face, 2]] - V[F[face, 0]])
    plain = rays.scene.segment_visible(pts.p, light, normals=geo)
    assert (facing & ~plain).sum() > MIN_EDGE_SAMPLES


def test_one_ring_rule_without_the_lift(sphere):
    """From the faceted points themselves (origins not lifted) a convex sphere's segments meet
    neighbouring facets; every such hit is on the point's 1-ring, and counts as lit."""
    from facegeo.surface.shadows import SurfacePoints

    V, F, rays, face, pts = sphere
    flat = SurfacePoints(p=pts.p, origin=pts.p, n=pts.n, face=pts.face, ok=pts.ok,
                         start=pts.p + rays.scene.eps * pts.n)
    light = SPHERE_LIGHT
    facing = np.einsum("pc,pc->p", flat.n, light[None, :] - flat.origin) > 0
    blocked = ~rays.scene.segment_visible(flat.start, light)
    assert (facing & blocked).sum() > MIN_EDGE_SAMPLES  # what the rule has to resolve
    np.testing.assert_array_equal(rays.lit(flat, position=light), facing)
    rows = np.flatnonzero(facing & blocked)
    assert rays.lit(flat, rows, position=light).all()


def _near():
    """The near-field LIGHTS as a light list (δA weights unused here)."""
    return LightList(positions=LIGHTS, solid_angles=np.ones(len(LIGHTS)))


def _camera():
    K = np.array([[460.0, 0.0, 61.3], [0.0, 455.0, 52.8], [0.0, 0.0, 1.0]])  # fx ≠ fy, off-centre
    return Camera("top", 124, 106, K, np.zeros(5), look_at([0.02, -0.03, 0.5], [0.0, 0.0, 0.0]))


def _behind_square(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Whether the segments ``p0 → p1`` ``(P, 3)`` cross the occluding square."""
    s = (H_OCC - p0[:, 2]) / (p1[:, 2] - p0[:, 2])
    x = p0 + s[:, None] * (p1 - p0)
    inside = (np.abs(x[:, :2] - CENTRE[None, :]) < HALF).all(axis=1)
    return inside & (s > 0) & (s < 1)


def _frame(camera, light):
    """The analytic OLAT frame — a white plane at unit irradiance where lit, sampled at pixel
    centres — and each pixel's distance (m) to the shadow outline, ``(H·W,)``."""
    q = camera.pixel_grid().reshape(-1, 2)
    o, d = camera.pixel_rays(q)
    t = -o[:, 2] / d[:, 2]
    on_plane = o + t[:, None] * d
    lit, dist = _analytic_lit(on_plane[:, :2], light)
    # pixels that see the square's (unlit) back instead: 0, and never "sure" of anything
    hidden = _behind_square(on_plane, o)
    lit &= ~hidden
    dist[hidden] = 0.0
    frame = np.repeat(lit.astype(np.float32)[:, None], 3, 1)
    return frame.reshape(camera.height, camera.width, 3), dist


def _samples(rays, cam, seed, n):
    """Plane positions ``xy`` whose bilinear taps lie inside the camera, their pixel positions
    ``q`` and (face, bary)."""
    xy = np.random.default_rng(seed).uniform(-0.07, 0.07, (n, 2))
    p = np.concatenate([xy, np.zeros((n, 1))], axis=1)
    q = cam.project(p)[0]
    ok = ((q[:, 0] > 0.5) & (q[:, 0] < cam.width - 1.5)
          & (q[:, 1] > 0.5) & (q[:, 1] < cam.height - 1.5))
    ok &= ~_behind_square(p, np.broadcast_to(cam.center_world, p.shape))  # seen by the camera
    xy, q = xy[ok], q[ok]
    return xy, q, *_on_plane(rays, xy)


def test_shadow_taps_recover_hard_edges(scene):
    V, F, rays = scene
    cam = _camera()
    xy, q, face, bary = _samples(rays, cam, 3, 40000)
    near = _near()
    distant = LightList(directions=[DISTANT], solid_angles=[1.0])
    rng = np.random.default_rng(3)
    for lights, where in ((near, LIGHTS), (distant, [DISTANT * 1e4])):
        _check_edges(rays, cam, xy, q, face, bary, lights, where, rng)


def _check_edges(rays, cam, xy, q, face, bary, lights, where, rng):
    st = shadow_taps(rays, cam, q, face, bary, lights)
    for k in range(len(where)):
        frame, pix_dist = _frame(cam, where[k])
        truth, dist = _analytic_lit(xy, where[k])
        plain = sample_taps(frame, st.index, st.weight)
        s = plain.copy()
        changed = st.apply(k, frame, s)
        straddle = np.ptp(frame.reshape(-1, 3)[st.index][..., 0], axis=1) > 0
        sure = (dist > EDGE_MARGIN) & (pix_dist[st.index] > EDGE_MARGIN).all(axis=1)
        assert (straddle & sure).sum() > MIN_EDGE_SAMPLES and changed <= straddle.sum()
        # where the taps straddle the edge, the texel's own value comes back exactly
        np.testing.assert_allclose(s[straddle & sure, 0], truth[straddle & sure], rtol=0,
                                   atol=WEIGHT_SUM_TOL)
        # bilinear mixed them: the error the taps remove
        err = np.abs(plain[straddle & sure, 0] - truth[straddle & sure]).mean()
        assert err > BILINEAR_EDGE_ERR_MIN
        # elsewhere nothing changes
        np.testing.assert_array_equal(s[~straddle], plain[~straddle])
        # linear in the frame for a given light: the taps depend on the geometry only
        a = frame * 0.3
        b = frame * 0.7 + 0.1 * rng.random(frame.shape).astype(np.float32)
        sa, sb, sab = (sample_taps(x, st.index, st.weight) for x in (a, b, a + b))
        for x, y in ((a, sa), (b, sb), (a + b, sab)):
            st.apply(k, x, y)
        assert np.abs(sab - (sa + sb)).max() <= LINEARITY_REL_TOL * np.abs(sab).max()
    assert st.samples == 4 * len(where) * len(q) and st.changed > 0 and st.seconds > 0


def test_shadow_taps_leave_grazing_light_alone(scene):
    """Below SHADOW_TAPS_MIN_COS the taps stay bilinear: near the terminator the shading fades
    by itself."""
    V, F, rays = scene
    cam = _camera()
    xy, q, face, bary = _samples(rays, cam, 6, 15000)
    frame, _ = _frame(cam, GRAZING)
    lights = LightList(positions=[GRAZING], solid_angles=[1.0])
    plain = sample_taps(frame, *bilinear_taps(q, cam.width, cam.height))
    s = plain.copy()
    assert shadow_taps(rays, cam, q, face, bary, lights).apply(0, frame, s) == 0
    np.testing.assert_array_equal(s, plain)
    assert shadow_taps(rays, cam, q, face, bary, lights, min_cos=0.0).apply(0, frame, s) > 0


def test_shadow_taps_honour_masks_and_check_input(scene):
    V, F, rays = scene
    cam = _camera()
    xy, q, face, bary = _samples(rays, cam, 4, 3000)
    st = shadow_taps(rays, cam, q, face, bary, _near())
    frame, pix_dist = _frame(cam, LIGHTS[0])
    truth, dist = _analytic_lit(xy, LIGHTS[0])
    flat = frame.reshape(-1, 3)[:, 0]
    sure = (dist > EDGE_MARGIN) & (pix_dist[st.index] > EDGE_MARGIN).all(axis=1)
    i = np.flatnonzero((np.ptp(flat[st.index], axis=1) > 0) & sure)[0]
    taps = st.index[i]
    mine = taps[flat[taps] == float(truth[i])]  # the taps on the texel's side of the edge
    other = taps[flat[taps] != float(truth[i])]
    sampler = frame_sampler(q, cam.width, cam.height)
    for masked, expect_nan in ((other[0], False), (mine[0], True)):
        valid = np.ones((cam.height, cam.width), bool)
        valid.reshape(-1)[masked] = False
        frame = frame.copy()
        frame.reshape(-1, 3)[masked] = np.nan  # a non-finite pixel, masked as the stage does
        s = sample_frame(frame, sampler, valid)
        assert np.isnan(s[i]).all()  # plain bilinear touched the masked pixel
        st.apply(0, frame, s, valid)
        assert np.isnan(s[i]).all() == expect_nan
        if not expect_nan:
            assert abs(s[i, 0] - truth[i]) <= WEIGHT_SUM_TOL
    s0 = sample_taps(frame, st.index, st.weight)
    with pytest.raises(ShapeError, match="samples"):
        st.apply(0, frame, s0[:-1])
    with pytest.raises(InputError, match="out of range"):
        st.apply(len(LIGHTS), frame, s0)
    with pytest.raises(ShapeError, match="frame"):
        st.apply(0, frame.transpose(1, 0, 2), s0)
    with pytest.raises(ShapeError, match="one row per sample"):
        shadow_taps(rays, cam, q, face[:-1], bary, _near())
    with pytest.raises(InputError, match="min_cos"):
        shadow_taps(rays, cam, q, face, bary, _near(), min_cos=1.5)
