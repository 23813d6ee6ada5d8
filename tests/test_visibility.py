"""Tests of facegeo.surface.visibility: closest hit, occlusion and segment visibility.

The independent reference is trimesh's pure-numpy ray–triangle test
(``trimesh.ray.ray_triangle``, no Embree, float64). Its ``RayMeshIntersector`` wants an ``rtree``
index for the broad phase; rtree is not a facegeo dependency, so a brute-force AABB broad phase
stands in for it (the narrow phase, which decides the hits, is trimesh's own).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from trimesh.ray.ray_triangle import ray_triangle_id

from facegeo.errors import InputError, ShapeError
from facegeo.surface.visibility import EPS_RELATIVE, Hits, RayScene

# --------------------------------------------------------------------------- tolerances
#: Relative distance agreement with the float64 reference (ours is float64-refined).
T_REL_TOL = 1e-9
#: Fraction of rays allowed a different face id than the reference (edge ties).
FACE_MISMATCH_MAX = 1e-3
#: Where face ids differ (a tie on a shared edge), hit points agree within this, in scene scales.
TIE_POINT_TOL = 1e-6
#: Barycentric weights: non-negative, sum to 1 within this.
BARY_SUM_TOL = 1e-12
#: A hit point lies on its face's plane (and on its ray) within this, relative to the scene
#: scale (float64 rounding of a few operations).
PLANE_TOL = 1e-11
#: Reported normals are unit winding normals within this (dimensionless).
NORMAL_TOL = 1e-12
#: A tangent ray's hit counts as an edge contact when its smallest weight is below this.
EDGE_CONTACT_BARY = 1e-9
#: Minimum fraction of vertex-aimed rays that must hit at the vertex (float32 Embree is not
#: watertight at vertices: measured 2 of 642 slip through on an icosphere).
VERTEX_HIT_MIN = 0.99


# --------------------------------------------------------------------------- fixtures


def _icosphere(subdivisions=3, radius=1.0, centre=(0.0, 0.0, 0.0)):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices) + np.asarray(centre), np.asarray(m.faces)


def _two_spheres():
    """Two overlapping spheres (not merged): rays cross up to four surfaces."""
    v1, f1 = _icosphere(3, 1.0, (0.05, -0.02, 0.01))
    v2, f2 = _icosphere(3, 0.6, (0.9, 0.2, -0.1))
    return np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)])


def _dented_sphere():
    """A sphere with radial dents (concave regions), asymmetric in x, y, z."""
    v, f = _icosphere(4)
    r = 1.0 + 0.25 * np.sin(3.0 * v[:, 0] + 0.3) * np.sin(2.0 * v[:, 1]) * np.cos(2.5 * v[:, 2])
    return v * r[:, None], f


class _BruteTree:
    """Duck-typed stand-in for an rtree index: AABB overlap test over all triangles."""

    def __init__(self, tris):
        self.lo = tris.min(axis=1)
        self.hi = tris.max(axis=1)
        self.bounds = np.concatenate([self.lo.min(axis=0), self.hi.max(axis=0)])

    def intersection(self, box):
        box = np.asarray(box)
        return np.flatnonzero(((self.lo <= box[3:]) & (self.hi >= box[:3])).all(axis=1))


def _reference_closest(vertices, faces, o, d):
    """Closest hits by trimesh's float64 numpy ray–triangle test: (face, t), -1 / NaN on miss."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    tris = np.asarray(mesh.triangles)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    tri, ray, loc = ray_triangle_id(
        tris, o, d, tree=_BruteTree(tris), multiple_hits=False,
        triangles_normal=np.asarray(mesh.face_normals),
    )
    face = np.full(len(o), -1, dtype=np.int64)
    t = np.full(len(o), np.nan)
    face[ray] = tri
    t[ray] = np.einsum("ni,ni->n", loc - o[ray], d[ray])
    return face, t, loc, ray


def _rays_at(rng, n, bounds, radius):
    """Rays from a sphere of ``radius`` around the bounds' centre toward points in the bounds."""
    c = bounds.mean(axis=0)
    o = rng.normal(size=(n, 3))
    o = c + radius * o / np.linalg.norm(o, axis=1, keepdims=True)
    target = rng.uniform(bounds[0], bounds[1], size=(n, 3))
    return o, target - o


def _assert_consistent(scene: RayScene, h: Hits, o, d, *, on_surface=False):
    """Per-ray invariants: NaN/-1 exactly on misses; hits lie on their face and on the ray.

    ``on_surface``: the rays start on the surface, so some may be lifted ``eps`` off their
    starting plane; their hit point is then within ``eps`` of ``origin + t * direction``.
    """
    assert h.hit.dtype == bool, "metric: hit mask dtype"
    miss = ~h.hit
    assert np.all(np.isnan(h.t[miss])) and np.all(h.face[miss] == -1), "metric: miss sentinels"
    assert np.all(np.isnan(h.bary[miss])) and np.all(np.isnan(h.point[miss])), "metric: miss NaNs"
    assert np.all(np.isnan(h.normal[miss])), "metric: miss normals NaN"
    if not h.hit.any():
        return
    assert np.all(np.isfinite(h.t[h.hit])) and np.all(h.face[h.hit] >= 0), "metric: hit finite"
    b = h.bary[h.hit]
    assert b.min() >= 0.0, "metric: barycentric weights non-negative"
    assert np.max(np.abs(b.sum(axis=1) - 1.0)) <= BARY_SUM_TOL, "metric: weights sum to 1"
    assert not scene.degenerate[h.face[h.hit]].any(), "metric: degenerate faces never hit"
    tri = scene.vertices[scene.faces[h.face[h.hit]]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    assert np.max(np.abs(np.einsum("ni,ni->n", h.normal[h.hit], n) - 1.0)) <= NORMAL_TOL, (
        "metric: normal is the unit winding normal of the hit face"
    )
    off_plane = np.abs(np.einsum("ni,ni->n", h.point[h.hit] - tri[:, 0], n))
    assert off_plane.max() <= PLANE_TOL * scene.scale, "metric: hit point on face plane"
    o = np.broadcast_to(o, h.point.shape)[h.hit]
    d = np.broadcast_to(d, h.point.shape)[h.hit]
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    along = o + h.t[h.hit][:, None] * d
    gap = np.linalg.norm(along - h.point[h.hit], axis=1).max()
    bound = scene.eps * (1 + 1e-9) if on_surface else PLANE_TOL * scene.scale
    assert gap <= bound, f"metric: |origin + t * direction - point| = {gap:.3g} m"


# --------------------------------------------------------------------------- reference


@pytest.mark.parametrize("make", [_icosphere, _two_spheres, _dented_sphere])
def test_closest_hit_matches_trimesh_reference(make):
    rng = np.random.default_rng(11)
    v, f = make()
    scene = RayScene(v, f)
    o, d = _rays_at(rng, 2500, scene.bounds, 3.0 * scene.scale)
    h = scene.closest_hit(o, d)
    ref_face, ref_t, ref_loc, ref_ray = _reference_closest(v, f, o, d)
    _assert_consistent(scene, h, o, d)

    assert np.mean(h.hit != (ref_face >= 0)) <= FACE_MISMATCH_MAX, "metric: hit-mask agreement"
    same = h.face == ref_face
    assert np.mean(~same) <= FACE_MISMATCH_MAX, "metric: fraction of rays with a different face"
    both = h.hit & (ref_face >= 0)
    rel = np.abs(h.t[both] - ref_t[both]) / ref_t[both]
    assert rel.max() <= T_REL_TOL, f"metric: max relative |Δt| = {rel.max():.3g}"
    ties = both & ~same
    if ties.any():
        ref_point = np.full_like(h.point, np.nan)
        ref_point[ref_ray] = ref_loc
        gap = np.linalg.norm(h.point[ties] - ref_point[ties], axis=1).max()
        assert gap <= TIE_POINT_TOL * scene.scale, "metric: tie hit points agree"
    assert h.hit.mean() > 0.3, "metric: the ray set actually hits the mesh"


def test_concave_mesh_has_rays_with_several_hits_and_returns_nearest():
    rng = np.random.default_rng(12)
    v, f = _two_spheres()
    scene = RayScene(v, f)
    o, d = _rays_at(rng, 800, scene.bounds, 3.0 * scene.scale)
    mesh = trimesh.Trimesh(v, f, process=False)
    tris = np.asarray(mesh.triangles)
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    _, ray, loc = ray_triangle_id(tris, o, dn, tree=_BruteTree(tris), multiple_hits=True,
                                  triangles_normal=np.asarray(mesh.face_normals))
    counts = np.bincount(ray, minlength=len(o))
    assert (counts >= 3).sum() > 20, "metric: enough rays cross three or more surfaces"
    t_all = np.einsum("ni,ni->n", loc - o[ray], dn[ray])
    nearest = np.full(len(o), np.inf)
    np.minimum.at(nearest, ray, t_all)
    h = scene.closest_hit(o, d)
    multi = counts >= 3
    rel = np.abs(h.t[multi] - nearest[multi]) / nearest[multi]
    assert rel.max() <= T_REL_TOL, "metric: closest t equals the nearest of all hits"


# --------------------------------------------------------------------------- hard cases


def test_rays_starting_on_the_surface_do_not_self_intersect():
    rng = np.random.default_rng(13)
    v, f = _icosphere(3)
    scene = RayScene(v, f)
    o, d = _rays_at(rng, 2000, scene.bounds, 3.0)
    first = scene.closest_hit(o, d)
    p, n, own = first.point[first.hit], first.normal[first.hit], first.face[first.hit]

    out = scene.closest_hit(p, n)
    assert not out.hit.any(), "metric: outward rays from a convex surface hit nothing"
    tangent = np.cross(n, rng.normal(size=n.shape))
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    tilted = scene.closest_hit(p, tangent + 0.02 * n)
    assert not tilted.hit.any(), "metric: rays 1.1° above the tangent plane hit nothing"

    inward = scene.closest_hit(p, -n)
    assert inward.hit.all(), "metric: inward rays hit the far side"
    assert inward.t.min() > 1.5, "metric: inward hits are across the sphere (t > 1.5 radii)"
    assert not np.any(inward.face == own), "metric: inward rays never report their own face"

    along = scene.closest_hit(p, tangent)
    _assert_consistent(scene, along, p, tangent, on_surface=True)
    assert not np.any(along.face == own), "metric: tangent rays never report their own face"
    # A tangent ray leaves its face through an edge, touching the neighbours there.
    if along.hit.any():
        assert along.bary[along.hit].min(axis=1).max() <= EDGE_CONTACT_BARY, (
            "metric: tangent-ray hits are edge contacts"
        )
        height = np.einsum("ni,ni->n", along.point[along.hit] - p[along.hit], n[along.hit])
        assert np.abs(height).max() <= PLANE_TOL * scene.scale, (
            "metric: edge contacts lie in the starting face's plane"
        )
    # The shadow-ray form offsets along the normal: tangent segments are then free.
    vis = scene.segment_visible(p, p + 0.5 * tangent, normals=n)
    assert vis.mean() >= 0.999, "metric: fraction of tangent segments visible with normals"


def test_rays_from_surface_points_in_a_concave_mesh():
    rng = np.random.default_rng(14)
    v, f = _dented_sphere()
    scene = RayScene(v, f)
    o, d = _rays_at(rng, 1500, scene.bounds, 3.0 * scene.scale)
    first = scene.closest_hit(o, d)
    p, n, own = first.point[first.hit], first.normal[first.hit], first.face[first.hit]
    dirs = rng.normal(size=p.shape)
    dirs *= np.where(np.einsum("ni,ni->n", dirs, n) < 0, -1.0, 1.0)[:, None]  # upper hemisphere
    h = scene.closest_hit(p, dirs)
    _assert_consistent(scene, h, p, dirs, on_surface=True)
    assert not np.any(h.face == own), "metric: no ray reports the face it starts on"
    assert np.all(h.t[h.hit] >= scene.eps), "metric: every hit is beyond eps"
    assert h.hit.any(), "metric: concavities shadow some upper-hemisphere rays"
    ref_face, _, _, _ = _reference_closest(v, f, p + scene.eps * dirs / np.linalg.norm(
        dirs, axis=1, keepdims=True), dirs)
    assert np.mean(h.hit != (ref_face >= 0)) <= FACE_MISMATCH_MAX, (
        "metric: hit-mask agreement with the reference from origins moved eps"
    )


def test_edge_and_vertex_aimed_rays_are_watertight_and_consistent():
    rng = np.random.default_rng(15)
    mesh = trimesh.creation.icosphere(subdivisions=3)
    scene = RayScene.from_trimesh(mesh)
    edges = np.asarray(mesh.edges_unique)
    s = rng.uniform(size=(len(edges), 1))
    target = (1 - s) * mesh.vertices[edges[:, 0]] + s * mesh.vertices[edges[:, 1]]
    o = 3.0 * target + 0.5 * rng.normal(size=target.shape)
    h = scene.closest_hit(o, target - o)
    _assert_consistent(scene, h, o, target - o)
    dist = np.linalg.norm(target - o, axis=1)
    assert h.hit.all(), "metric: every edge-aimed ray hits (no leak through edges)"
    assert np.max(np.abs(h.t - dist) / dist) <= T_REL_TOL, "metric: edge hits at the edge"
    has_edge = (mesh.faces[h.face] == edges[:, :1]).any(axis=1) & (
        mesh.faces[h.face] == edges[:, 1:]).any(axis=1)
    assert has_edge.all(), "metric: the hit face is one of the edge's two faces"

    vt = np.asarray(mesh.vertices)
    ov = 3.0 * vt + 0.5 * rng.normal(size=vt.shape)
    hv = scene.closest_hit(ov, vt - ov)
    _assert_consistent(scene, hv, ov, vt - ov)
    dist = np.linalg.norm(vt - ov, axis=1)
    at_vertex = np.abs(hv.t - dist) <= T_REL_TOL * dist
    assert at_vertex.mean() >= VERTEX_HIT_MIN, "metric: fraction of vertex-aimed rays at vertex"


def test_rays_grazing_a_single_triangle_are_finite_and_consistent():
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.2, 0.9, 0.0]])
    scene = RayScene(v, [[0, 1, 2]])
    # In-plane rays toward the interior, rays exactly along each edge, rays through a vertex.
    o = np.array([[-1.0, 0.3, 0.0], [-1.0, -0.1, 0.0], [2.0, 0.2, 0.0], [0.1, 0.45, 0.0]])
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.1, 0.0], [-0.8, 0.7, 0.0], [0.0, 0.0, 1.0]])
    h = scene.closest_hit(o, d)
    _assert_consistent(scene, h, o, d)
    # Rays crossing the plane exactly through an edge point, from both sides.
    e = 0.5 * (v[1] + v[2])
    o2 = np.array([e + [0.3, 0.2, 1.0], e + [-0.2, 0.1, -1.0]])
    h2 = scene.closest_hit(o2, e - o2)
    _assert_consistent(scene, h2, o2, e - o2)
    assert h2.hit.all(), "metric: edge crossings hit the closed triangle"
    assert np.max(np.abs(h2.point - e)) <= 1e-12, "metric: edge crossing point, metres"
    assert h2.bary[:, 0].max() <= 1e-12, "metric: edge crossing has no weight on v0"


def test_misses_are_nan_and_flagged():
    v, f = _icosphere(2)
    scene = RayScene(v, f)
    o = np.array([[0.0, 0.0, 3.0], [2.0, 2.0, 2.0], [0.0, 1.2, 0.0]])
    d = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    h = scene.closest_hit(o, d)
    _assert_consistent(scene, h, o, d)
    assert not h.hit.any(), "metric: all three rays miss"
    assert np.all(h.face == -1) and np.all(np.isnan(h.t)), "metric: miss sentinels"
    assert not scene.occluded(o, d, np.inf).any(), "metric: misses are not occluded"
    assert scene.segment_visible(o, o + 10 * d).all(), "metric: miss segments visible"


def test_occluder_in_front_of_a_point_shadows_it_and_not_when_behind():
    # A ground quad at y = 0 (normal +Y) and a small occluder quad at y = 0.5 above x, z in
    # [0.2, 0.4] x [0.1, 0.3] (asymmetric on purpose).
    ground = np.array([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], float)
    occ = np.array([[0.2, 0.5, 0.1], [0.4, 0.5, 0.1], [0.4, 0.5, 0.3], [0.2, 0.5, 0.3]])
    v = np.vstack([ground, occ])
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 6, 5], [4, 7, 6]])
    scene = RayScene(v, f)
    p = np.array([[0.3, 0.0, 0.2], [0.7, 0.0, -0.6], [0.25, 0.0, 0.15]])
    n = np.tile([0.0, 1.0, 0.0], (3, 1))
    light_above = np.array([0.3, 2.0, 0.2])
    vis = scene.segment_visible(p, light_above, normals=n)
    assert vis.tolist() == [False, True, False], "metric: shadow under the occluder only"
    light_between = np.array([0.3, 0.25, 0.2])  # below the occluder: it is behind the light
    assert scene.segment_visible(p, light_between, normals=n).all(), (
        "metric: an occluder beyond the light does not shadow"
    )
    # Without normals the same answers (origins exactly on the ground plane).
    assert scene.segment_visible(p, light_above).tolist() == [False, True, False], (
        "metric: shadow test without normals"
    )
    # Swapped ends: the segment is the same set of points.
    assert scene.segment_visible(light_above, p).tolist() == [False, True, False], (
        "metric: visibility is symmetric in the segment's ends"
    )
    h = scene.closest_hit(light_above, p - light_above)
    assert h.face.tolist()[0] in (2, 3) and h.face.tolist()[1] in (0, 1), (
        "metric: from the light, the occluder is hit first"
    )


def test_degenerate_triangles_are_never_hit():
    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    front = np.array([[-0.5, 0.1, 1.0], [0.5, 0.1, 1.0], [0.0, 0.1, 1.0],  # collinear
                      [0.2, 0.3, 1.0]])  # repeated-vertex (zero area) with vertex 7 twice
    v = np.vstack([quad, front])
    f = np.array([[4, 5, 6], [0, 1, 2], [7, 7, 5], [0, 2, 3], [6, 6, 6]])
    scene = RayScene(v, f)
    assert scene.degenerate.tolist() == [True, False, True, False, True], (
        "metric: degenerate mask"
    )
    o = np.array([[0.0, 0.1, 3.0], [0.3, 0.2, 3.0], [0.2, 0.3, 3.0], [-0.5, 0.1, 3.0]])
    h = scene.closest_hit(o, [0.0, 0.0, -1.0])
    _assert_consistent(scene, h, o, [0.0, 0.0, -1.0])
    assert h.hit.all() and np.all(np.isin(h.face, [1, 3])), "metric: rays pass to the quad"
    assert np.allclose(h.t, 3.0, rtol=T_REL_TOL, atol=0), "metric: t of the quad, metres"
    assert not scene.occluded(o, [0.0, 0.0, -1.0], 2.5).any(), (
        "metric: degenerate faces do not occlude"
    )
    only_degenerate = RayScene(v, f[[0, 2, 4]])
    assert not only_degenerate.closest_hit(o, [0.0, 0.0, -1.0]).hit.any(), (
        "metric: an all-degenerate mesh is never hit"
    )
    assert not only_degenerate.occluded(o, [0.0, 0.0, -1.0], np.inf).any(), (
        "metric: an all-degenerate mesh never occludes"
    )


def test_layers_t_min_and_t_max_select_the_nearest_in_range():
    # Five parallel squares at z = 0 .. 4, listed in shuffled order.
    zs = np.array([3.0, 0.0, 4.0, 1.0, 2.0])
    v = np.concatenate([[[-1, -1, z], [1, -1, z], [1, 1, z], [-1, 1, z]] for z in zs])
    f = np.concatenate([[[4 * i, 4 * i + 1, 4 * i + 2], [4 * i, 4 * i + 2, 4 * i + 3]]
                        for i in range(len(zs))])
    scene = RayScene(v, f)
    o = np.array([0.13, -0.21, 10.0])
    d = np.array([0.01, 0.02, -1.0])
    unit = d / np.linalg.norm(d)
    t_layer = (o[2] - np.sort(zs)[::-1]) / -unit[2]  # distances to z = 4, 3, 2, 1, 0
    h = scene.closest_hit(o, d)
    assert h.t == pytest.approx(t_layer[0], rel=T_REL_TOL), "metric: nearest layer first"
    t_min = np.array([t_layer[0] + 0.1, t_layer[2] + 0.1, 0.0])
    t_max = np.array([np.inf, np.inf, t_layer[0] - 0.1])
    h2 = scene.closest_hit(o, np.tile(d, (3, 1)), t_min=t_min, t_max=t_max)
    assert h2.hit.tolist() == [True, True, False], "metric: t range selects layers"
    assert h2.t[:2] == pytest.approx(t_layer[[1, 3]], rel=T_REL_TOL), "metric: t of layers"
    assert zs[h2.face[:2] // 2].tolist() == [3.0, 1.0], "metric: face ids of the layers"
    at_max = scene.closest_hit(o, d, t_max=t_layer[0] * (1 + 1e-12))
    assert at_max.hit, "metric: a hit at t_max is inside [t_min, t_max]"
    assert scene.occluded(o, d, t_layer[0] + 0.1), "metric: occluded within t_max"
    assert not scene.occluded(o, d, t_layer[0] - 0.1), "metric: not occluded before the layer"
    assert not scene.occluded(o, d, np.inf, t_min=t_layer[4] + 0.1), (
        "metric: nothing beyond the last layer"
    )


def test_grazing_rays_on_a_flat_plane_skip_self_hits_but_find_a_wall():
    # A flat square of 8 coplanar triangles at z = 0 and a wall x = 1.5 beyond it.
    g = trimesh.creation.box(extents=[2.0, 2.0, 0.0])
    flat = trimesh.Trimesh(*trimesh.remesh.subdivide(g.vertices, g.faces), process=False)
    wall_v = np.array([[1.5, -3, -1], [1.5, 3, -1], [1.5, 3, 1], [1.5, -3, 1]], float)
    v = np.vstack([flat.vertices, wall_v])
    n0 = len(flat.vertices)
    f = np.vstack([flat.faces, [[n0, n0 + 1, n0 + 2], [n0, n0 + 2, n0 + 3]]])
    # Rotate and move off the axes so float32 rounds the plane (z = 0 is exact in float32).
    R = trimesh.transformations.rotation_matrix(0.7, [0.3, -0.5, 0.8])[:3, :3]
    shift = np.array([0.31, -0.17, 0.23])
    scene = RayScene(v @ R.T + shift, f)
    wall = {len(f) - 2, len(f) - 1}
    rng = np.random.default_rng(16)
    n = 400
    p_local = np.column_stack([rng.uniform(-0.9, 0.9, (n, 2)), np.zeros(n)])
    p = p_local @ R.T + shift
    az = rng.uniform(-0.5, 0.5, n)  # toward +x, so every ray meets the wall
    for elev in (0.0, 1e-7, 1e-5, 1e-3):
        d_local = np.column_stack([np.cos(az), np.sin(az), np.full(n, np.tan(elev))])
        d = d_local @ R.T
        h = scene.closest_hit(p, d)
        _assert_consistent(scene, h, p, d, on_surface=True)
        assert h.hit.all() and set(h.face.tolist()) <= wall, (
            f"metric: at elevation {elev} rad every ray passes its own plane and hits the wall"
        )
        t_wall = (1.5 - p_local[:, 0]) / np.cos(az) * np.sqrt(1 + np.tan(elev) ** 2)
        # Rays starting on their own plane may be lifted eps off it: t within eps, metres.
        assert np.max(np.abs(h.t - t_wall)) <= scene.eps, "metric: |Δt| to the wall, metres"
        assert scene.occluded(p, d, np.inf).all(), "metric: the wall occludes"


def test_far_from_origin_scene_keeps_float64_accuracy():
    rng = np.random.default_rng(17)
    v, f = _dented_sphere()
    v = 0.1 * v  # head-sized
    offset = np.array([1000.0, -2000.0, 500.0])  # kilometres from the world origin
    near = RayScene(v, f)
    far = RayScene(v + offset, f)
    o, d = _rays_at(rng, 2000, near.bounds, 0.5)
    h0 = near.closest_hit(o, d)
    h1 = far.closest_hit(o + offset, d)
    assert np.mean(h0.face != h1.face) <= FACE_MISMATCH_MAX, "metric: same faces when shifted"
    both = h0.hit & h1.hit
    assert np.max(np.abs(h0.t[both] - h1.t[both])) <= 1e-9, "metric: |Δt| in metres"


def test_occluded_and_segment_visible_agree_with_closest_hit():
    rng = np.random.default_rng(18)
    v, f = _two_spheres()
    scene = RayScene(v, f)
    o, d = _rays_at(rng, 3000, scene.bounds, 2.0 * scene.scale)
    h = scene.closest_hit(o, d)
    t_max = rng.uniform(0.0, 4.0 * scene.scale, len(o))
    clear = ~(np.abs(h.t - t_max) <= 1e-6 * scene.scale)  # away from float32 rounding of t_max
    occ = scene.occluded(o, d, t_max)
    expect = h.hit & (h.t <= t_max)
    assert np.array_equal(occ[clear], expect[clear]), "metric: occluded iff closest t <= t_max"
    assert expect[clear].any() and (~expect[clear]).any(), "metric: both outcomes present"

    unit = d / np.linalg.norm(d, axis=1, keepdims=True)
    p_to = o + t_max[:, None] * unit
    vis = scene.segment_visible(o, p_to)
    blocked = h.hit & (h.t < t_max - scene.eps)
    clear &= ~(np.abs(h.t - (t_max - scene.eps)) <= 1e-6 * scene.scale)
    assert np.array_equal(vis[clear], ~blocked[clear]), "metric: visible iff no hit inside"

    # From surface points (shadow rays), upper hemisphere, toward lights 5 scales away.
    p, n = h.point[h.hit], h.normal[h.hit]
    w = rng.normal(size=p.shape)
    w *= np.where(np.einsum("ni,ni->n", w, n) < 0, -1.0, 1.0)[:, None]
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    light = p + 5.0 * scene.scale * w
    hs = scene.closest_hit(p, w)
    occ_s = scene.occluded(p, w, np.inf)
    assert np.mean(occ_s != hs.hit) <= FACE_MISMATCH_MAX, "metric: shadow rays agree"
    assert np.mean(scene.segment_visible(p, light, normals=n) == hs.hit) <= FACE_MISMATCH_MAX, (
        "metric: segment visibility from surface points agrees with closest_hit"
    )


# --------------------------------------------------------------------------- API


def test_shapes_broadcast_and_threads_do_not_change_results():
    rng = np.random.default_rng(19)
    v, f = _dented_sphere()
    one = RayScene(v, f, n_threads=1)
    many = RayScene(v, f, n_threads=2, chunk_size=97)
    c = np.array([0.3, -0.2, 4.0])
    d = rng.normal(size=(7, 11, 3)) * 0.2 + [0.0, 0.0, -1.0]
    h1 = one.closest_hit(c, d)
    h2 = many.closest_hit(np.broadcast_to(c, d.shape), d)
    assert h1.shape == (7, 11) and h1.bary.shape == (7, 11, 3), "metric: leading shape kept"
    for name in ("hit", "face"):
        assert np.array_equal(getattr(h1, name), getattr(h2, name)), f"metric: {name} identical"
    for name in ("t", "bary", "point", "normal"):
        assert np.array_equal(getattr(h1, name), getattr(h2, name), equal_nan=True), (
            f"metric: {name} identical across threads and chunk sizes"
        )
    occ = many.occluded(c, d, np.full((7, 11), 10.0))
    assert occ.shape == (7, 11) and np.array_equal(occ, h1.hit), "metric: occluded shape/value"
    vis = one.segment_visible(np.zeros((5, 3)), c)
    assert vis.shape == (5,), "metric: segment_visible shape with (3,) end point"
    empty = one.closest_hit(np.zeros((0, 3)), np.ones((0, 3)))
    assert empty.hit.shape == (0,) and empty.point.shape == (0, 3), "metric: empty batch"


def test_sorting_rays_does_not_change_results():
    rng = np.random.default_rng(20)
    v, f = _two_spheres()
    scene = RayScene(v, f, n_threads=2, chunk_size=256)
    o, d = _rays_at(rng, 3000, scene.bounds, 2.0 * scene.scale)
    t_max = rng.uniform(0.0, 4.0 * scene.scale, len(o))
    plain = scene.closest_hit(o, d, t_max=t_max, sort_rays=False)
    z = scene.closest_hit(o, d, t_max=t_max, sort_rays=True)
    for name in ("hit", "face"):
        assert np.array_equal(getattr(plain, name), getattr(z, name)), f"metric: {name} equal"
    for name in ("t", "bary", "point", "normal"):
        assert np.array_equal(getattr(plain, name), getattr(z, name), equal_nan=True), (
            f"metric: {name} identical in input order after Z-order tracing"
        )
    assert np.array_equal(scene.occluded(o, d, t_max, sort_rays=True),
                          scene.occluded(o, d, t_max, sort_rays=False)), (
        "metric: occluded identical with and without sorting"
    )


def test_normals_follow_the_winding():
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    o, d = np.array([0.2, 0.3, 1.0]), np.array([0.0, 0.0, -1.0])
    up = RayScene(v, [[0, 1, 2]]).closest_hit(o, d)
    down = RayScene(v, [[0, 2, 1]]).closest_hit(o, d)
    assert up.normal.tolist() == [0.0, 0.0, 1.0], "metric: counter-clockwise winding → +Z"
    assert down.normal.tolist() == [0.0, 0.0, -1.0], "metric: swapped winding → -Z"
    assert up.bary == pytest.approx([0.5, 0.2, 0.3], abs=1e-15), "metric: weights of v0, v1, v2"
    assert down.bary == pytest.approx([0.5, 0.3, 0.2], abs=1e-15), "metric: swapped weights"


def test_properties_and_from_trimesh():
    mesh = trimesh.creation.box(extents=[0.2, 0.3, 0.4])
    scene = RayScene.from_trimesh(mesh)
    assert scene.n_faces == 12, "metric: face count"
    expected = np.array([[-0.1, -0.15, -0.2], [0.1, 0.15, 0.2]])
    assert scene.bounds == pytest.approx(expected), "metric: bounds, metres"
    assert scene.scale == pytest.approx(np.sqrt(0.2**2 + 0.3**2 + 0.4**2)), "metric: diagonal"
    assert scene.eps == pytest.approx(EPS_RELATIVE * scene.scale), "metric: default eps"
    # eps is far above float32 rounding at the scene's extent (centred: half the diagonal).
    assert scene.eps > 100 * np.finfo(np.float32).eps * scene.scale / 2, "metric: eps vs ulp"
    assert RayScene.from_trimesh(mesh, eps=1e-3).eps == 1e-3, "metric: eps override"
    scene.n_threads = 1
    assert scene.n_threads == 1, "metric: n_threads is settable"
    with pytest.raises(InputError, match="n_threads"):
        scene.n_threads = 0
    with pytest.raises(InputError, match="mesh"):
        RayScene.from_trimesh(np.zeros((3, 3)))
    v = np.array(mesh.vertices)
    scene2 = RayScene(v, mesh.faces)
    v[:] = 0.0
    assert scene2.closest_hit([0, 0, 1.0], [0, 0, -1.0]).hit, "metric: the scene copies its input"


@pytest.mark.parametrize(
    ("kwargs", "err", "needle"),
    [
        ({"vertices": [[0, 0, np.nan], [1, 0, 0], [0, 1, 0]]}, InputError, "vertices"),
        ({"vertices": [[0, 0], [1, 0], [0, 1]]}, ShapeError, "vertices"),
        ({"faces": [[0, 1, 3]]}, InputError, "faces"),
        ({"faces": [[0, 1, -1]]}, InputError, "faces"),
        ({"faces": [[0.5, 1, 2]]}, ShapeError, "faces"),
        ({"faces": np.zeros((0, 3), int)}, InputError, "faces"),
        ({"eps": -1.0}, InputError, "eps"),
    ],
)
def test_construction_errors_name_the_argument(kwargs, err, needle):
    args = {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, 2]]}
    args.update(kwargs)
    eps = args.pop("eps", None)
    with pytest.raises(err, match=needle):
        RayScene(args["vertices"], args["faces"], eps=eps)


def test_query_errors_name_the_argument_and_index():
    scene = RayScene([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    o = np.zeros((4, 3))
    d = np.tile([0.0, 0.0, 1.0], (4, 1))
    bad = o.copy()
    bad[2, 1] = np.nan
    with pytest.raises(InputError, match=r"origins.*\(2, 1\)"):
        scene.closest_hit(bad, d)
    badd = d.copy()
    badd[3, 0] = np.inf
    with pytest.raises(InputError, match=r"directions.*\(3, 0\)"):
        scene.occluded(o, badd, 1.0)
    zero = d.copy()
    zero[1] = 0.0
    with pytest.raises(InputError, match=r"directions.*zero-length.*\(1,\)"):
        scene.closest_hit(o, zero)
    with pytest.raises(ShapeError, match="origins"):
        scene.closest_hit(np.zeros((4, 2)), d)
    with pytest.raises(ShapeError, match="broadcast"):
        scene.closest_hit(np.zeros((4, 3)), np.ones((5, 3)))
    with pytest.raises(InputError, match="t_min"):
        scene.closest_hit(o, d, t_min=-1.0)
    with pytest.raises(InputError, match="t_max"):
        scene.occluded(o, d, np.nan)
    with pytest.raises(ShapeError, match="t_max"):
        scene.occluded(o, d, np.ones(3))
    with pytest.raises(InputError, match="p_to"):
        scene.segment_visible(o, [0.0, np.nan, 1.0])
    with pytest.raises(InputError, match="normals"):
        scene.segment_visible(o, [0.0, 0.0, 1.0], normals=np.zeros((4, 3)))


def test_fields_subset_is_identical_to_the_full_result_and_omits_the_rest():
    # A subset of fields skips only writing the others: every field computed must equal the
    # default call's bit for bit, on rays that include surface-start rays (re-casts) and
    # misses, in chunks and on two threads, in input order and Z-order.
    rng = np.random.default_rng(23)
    v, f = _dented_sphere()
    scene = RayScene(v, f, n_threads=2, chunk_size=211)
    o, d = _rays_at(rng, 1500, scene.bounds, 2.0 * scene.scale)
    tri = v[f[rng.integers(0, len(f), 500)]]
    p = np.einsum("ni,nij->nj", rng.dirichlet([1, 1, 1], 500), tri)
    o, d = np.vstack([o, p]), np.vstack([d, rng.normal(size=(500, 3))])
    for sort in (False, True):
        full = scene.closest_hit(o, d, sort_rays=sort)
        for fields in (("t", "face", "bary"), ["point"], "normal", ("face", "t")):
            sub = scene.closest_hit(o, d, sort_rays=sort, fields=fields)
            wanted = {fields} if isinstance(fields, str) else set(fields)
            assert np.array_equal(sub.hit, full.hit), "metric: hit identical"
            for name in ("t", "face", "bary", "point", "normal"):
                got = getattr(sub, name)
                if name in wanted:
                    assert np.array_equal(got, getattr(full, name), equal_nan=True), (
                        f"metric: {name} identical with fields={fields}"
                    )
                else:
                    assert got is None, f"metric: {name} not computed with fields={fields}"
    none = scene.closest_hit(o, d, fields=())
    assert np.array_equal(none.hit, full.hit) and none.t is None, "metric: hit alone"
    with pytest.raises(InputError, match=r"fields.*'depth'.*expected some of"):
        scene.closest_hit(o, d, fields=("t", "depth"))


def test_prepare_rays_matches_numpy_and_reads_shared_rows_in_place():
    # The compiled preparation pass against its numpy formulation, with per-ray inputs given
    # one row per ray and one row shared by all (broadcast origins, scalar t_min / t_max), and
    # its validation flag on each kind of bad ray. Each layout runs its own loop (per-ray
    # origins with scalar distances and a shared origin have branch-free fast paths).
    from facegeo.surface import _vis_kernels as k
    from facegeo.surface._vis_util import _dot

    rng = np.random.default_rng(29)
    m = 257
    o = rng.normal(size=(m, 3))
    D = rng.normal(size=(m, 3)) * rng.uniform(0.1, 10.0, (m, 1))
    ts = rng.uniform(0.0, 1e-3, m)
    tmax = np.where(rng.random(m) < 0.3, np.inf, rng.uniform(0.0, 5.0, m))
    centre = np.array([0.3, -0.7, 1.1])

    def run(o, D, ts, tmax, round_down):
        out = (np.empty((m, 3), np.float32), np.empty((m, 3), np.float32), np.empty((m, 3)),
               np.empty(m, np.float32))
        ok = k.prepare_rays(o, D, False, ts, tmax, centre, round_down, *out)
        return ok, out

    def strided(a):  # the same values in a non-contiguous view (the general loop reads it)
        wide = np.empty((len(a), 4))
        wide[:, :3] = a
        return wide[:, :3]

    layouts = ((o, ts, tmax), (o, ts[:1], tmax[:1]), (o[:1], ts[:1], tmax[:1]),
               (o[:1], ts, tmax[:1]), (strided(o), ts[:1], tmax[:1]))
    for (oo, tt, xx), DD in [(lay, D) for lay in layouts] + [(layouts[2], strided(D))]:
        ob, tb, xb = (np.broadcast_to(a, (m,) + a.shape[1:]) for a in (oo, tt, xx))
        d = D / np.sqrt(_dot(D, D))[:, None]
        far = np.minimum(xb - tb, np.finfo(np.float32).max)
        for round_down in (False, True):
            ok, (org32, d32, d64, far32) = run(oo, DD, tt, xx, round_down)
            assert ok, "metric: valid rays pass"
            assert np.array_equal(d64, d), "metric: unit directions bit-identical to numpy"
            assert np.array_equal(d32, d.astype(np.float32)), "metric: float32 directions"
            expect = (ob + d * tb[:, None] - centre).astype(np.float32)
            assert np.array_equal(org32, expect), "metric: moved, centred float32 origins"
            if round_down:  # never past t_max: the float32 distance is at most the float64 one
                assert np.all(far32.astype(np.float64) <= far), "metric: rounded toward zero"
                fin = far32 < np.finfo(np.float32).max
                assert np.all(far[fin] - far32[fin] <= np.spacing(far32[fin])), (
                    "metric: by under one float32 ulp"
                )
            else:
                assert np.array_equal(far32, far.astype(np.float32)), "metric: to nearest"
    for bad in ("nan origin", "inf direction", "zero direction"):
        for oo, tt, xx in layouts:
            ob, Db = oo.copy(), D.copy()  # (copies are contiguous: the fast loops)
            if bad == "nan origin":
                ob[min(100, len(ob) - 1), 2] = np.nan
            elif bad == "inf direction":
                Db[5, 0] = np.inf
            else:
                Db[200] = 0.0
            assert not run(ob, Db, tt, xx, False)[0], (
                f"metric: {bad} reported ({len(oo)} origin rows, {len(tt)} t_min rows)")


def test_rays_no_query_reads_are_still_validated():
    # Validation runs inside the compiled preparation pass; rays that never reach it (a scene
    # of degenerate faces only, rays with t_max < t_min) must still be checked and named.
    flat = RayScene([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]])
    o = np.zeros((3, 3))
    d = np.tile([0.0, 0.0, 1.0], (3, 1))
    assert not flat.closest_hit(o, d).hit.any(), "metric: degenerate-only scene never hits"
    bad = o.copy()
    bad[1, 0] = np.nan
    with pytest.raises(InputError, match=r"origins.*\(1, 0\)"):
        flat.closest_hit(bad, d)
    with pytest.raises(InputError, match=r"origins.*\(1, 0\)"):
        flat.occluded(bad, d, 1.0)
    scene = RayScene([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    zero = d.copy()
    zero[2] = 0.0
    with pytest.raises(InputError, match=r"directions.*zero-length.*\(2,\)"):
        scene.occluded(o, zero, [1.0, 1.0, 0.0], t_min=0.5)  # ray 2 skipped: t_max < t_min
    with pytest.raises(InputError, match=r"directions.*zero-length.*\(2,\)"):
        scene.closest_hit(o, zero, t_max=[1.0, 1.0, 0.0], t_min=0.5)


@pytest.mark.slow
def test_bench_loads_a_previous_checkout_beside_this_one(tmp_path):
    # FACEGEO_BENCH_PREVIOUS: the closest_hit benchmark times another checkout's RayScene in
    # the same process. Loading this checkout as the "previous" one must give a separate class
    # (its own copied modules, not this one under another name) with bit-identical hits, and
    # the comparison must notice a single changed value.
    from pathlib import Path

    import facegeo
    from facegeo.bench.visibility import _load_previous, _same_hits

    root = Path(facegeo.__file__).parent.parent
    Prev = _load_previous(str(root))
    assert Prev is not RayScene and Prev.__module__ != RayScene.__module__, (
        "metric: a separately loaded class")
    kern = __import__(Prev.__module__.rsplit(".", 1)[0] + "._vis_kernels", fromlist=["x"])
    assert kern.__name__ != "facegeo.surface._vis_kernels", "metric: its own kernels module"
    rng = np.random.default_rng(31)
    v, f = _dented_sphere()
    ours, prev = RayScene(v, f, n_threads=1), Prev(v, f, n_threads=1)
    o, d = _rays_at(rng, 400, ours.bounds, 2.0 * ours.scale)
    a, b = ours.closest_hit(o, d), prev.closest_hit(o, d)
    assert _same_hits(a, b), "metric: bit-identical hits from the same code"
    t = b.t.copy()
    i = int(np.flatnonzero(b.hit)[0])
    t[i] = np.nextafter(t[i], np.inf)
    changed = Hits(b.hit, t, b.face, b.bary, b.point, b.normal)
    assert not _same_hits(a, changed), "metric: one ulp in one t is a difference"
