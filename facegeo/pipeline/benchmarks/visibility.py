"""Benchmarks of :mod:`facegeo.surface.visibility` against raw embreex and ``trimesh.ray``.

``visibility.closest_hit``: camera-coherent rays (a pinhole grid) against a displaced sphere of
~1.3 M triangles (quick: ~82 k), head-sized (radius 0.1 m) and seen from 0.5 m.
``visibility.occluded``: incoherent shadow rays from random surface points toward random
directions (the worst case for memory locality; :class:`~facegeo.surface.visibility.RayScene` sorts such
batches in Z-order on large meshes, and a row shows raw embreex on pre-sorted rays).

Each row carries the ratio to raw embreex (one ``EmbreeScene.run`` call on the same float32
arrays and the same BVH, so only facegeo's overhead and threading differ) and to trimesh's
``mesh.ray`` measured in the same run. Timings on the shared 2-core machines are noisy: compare
ratios, not absolute speeds, and rerun when another job was using the second core.
"""

from __future__ import annotations

import numpy as np

from facegeo.pipeline.bench import BenchRow, best_of, register

_RADIUS = 0.1  # metres, a head
_CAMERA_DISTANCE = 0.5  # metres


def _mesh(quick: bool):
    """A displaced icosphere (concavities, so some rays meet several layers of surface)."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=6 if quick else 8)
    v = np.asarray(sphere.vertices)
    bump = 1.0 + 0.2 * np.sin(9 * v[:, 0]) * np.sin(7 * v[:, 1] + 1.0) * np.sin(8 * v[:, 2] + 0.5)
    v = _RADIUS * v * bump[:, None]
    return trimesh.Trimesh(v, np.asarray(sphere.faces), process=False)


def _pinhole_rays(n_side: int):
    """Origins (3,) and unit directions (n_side², 3) of a pinhole camera on +Z looking at 0."""
    c = np.array([0.013, -0.007, _CAMERA_DISTANCE])
    half = 1.15 * _RADIUS / _CAMERA_DISTANCE  # tan of the half field of view
    x, y = np.meshgrid(np.linspace(-half, half, n_side), np.linspace(-half, half, n_side))
    d = np.stack([x, -y, -np.ones_like(x)], axis=-1).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return c, d


def _trimesh_closest(mesh, o, d):
    """trimesh.ray closest hits as (face, t) arrays, -1 / NaN on miss."""
    tri, ray, loc = mesh.ray.intersects_id(o, d, multiple_hits=False, return_locations=True)
    face = np.full(len(o), -1, dtype=np.int64)
    t = np.full(len(o), np.nan)
    face[ray] = tri
    t[ray] = np.linalg.norm(loc - o[ray], axis=1)
    return face, t


@register("visibility.closest_hit")
def bench_closest_hit(quick: bool) -> list[BenchRow]:
    from facegeo.surface.visibility import RayScene

    mesh = _mesh(quick)
    n_side = 448 if quick else 1000
    repeat = 2 if quick else 3
    scene = RayScene.from_trimesh(mesh)
    t_build, _ = best_of(scene.build, repeat=1)
    c, d = _pinhole_rays(n_side)
    n = len(d)
    o = np.broadcast_to(c, d.shape)

    t_ours, hits = best_of(lambda: scene.closest_hit(o, d), repeat)
    threads = scene.n_threads
    scene.n_threads = 1
    t_one, _ = best_of(lambda: scene.closest_hit(o, d), repeat)
    scene.n_threads = threads

    # Raw embreex on the same BVH and float32 arrays, one call.
    emb, prim_to_face = scene._scene()
    o32 = np.ascontiguousarray(o - scene._centre, dtype=np.float32)
    d32 = np.ascontiguousarray(d, dtype=np.float32)
    t_raw, raw = best_of(lambda: emb.run(o32, d32, output=1), repeat)
    raw_hit = raw["primID"] >= 0
    raw_prim = np.maximum(raw["primID"], 0).astype(np.int64)
    raw_face = np.where(raw_hit, raw_prim if prim_to_face is None else prim_to_face[raw_prim], -1)
    raw_t = np.where(raw_hit, raw["tfar"].astype(np.float64), np.nan)
    both = hits.hit & raw_hit
    err_t = float(np.max(np.abs(hits.t[both] - raw_t[both]) / raw_t[both])) if both.any() else 0.0
    diff_face = float(np.mean(hits.face != raw_face))

    # trimesh's mesh.ray (embreex-backed when embreex is installed), on a subset.
    n_tm = min(n, 200_000)
    sub = np.linspace(0, n - 1, n_tm).astype(np.int64)
    o_tm, d_tm = np.ascontiguousarray(o[sub]), np.ascontiguousarray(d[sub])
    _trimesh_closest(mesh, o_tm[:10], d_tm[:10])  # build trimesh's scene outside the timing
    t_tm, (tm_face, tm_t) = best_of(lambda: _trimesh_closest(mesh, o_tm, d_tm), repeat)
    ok = hits.hit[sub] & (tm_face >= 0)
    t_sub = hits.t[sub]
    err_tm = float(np.max(np.abs(tm_t[ok] - t_sub[ok]) / t_sub[ok])) if ok.any() else 0.0
    diff_tm = float(np.mean(tm_face != hits.face[sub]))

    ours = n / t_ours / 1e6
    raw_speed = n / t_raw / 1e6
    tm_speed = n_tm / t_tm / 1e6
    sizes = {"faces": scene.n_faces, "rays": n, "hit fraction": float(hits.hit.mean())}
    return [
        BenchRow("visibility.closest_hit", f"RayScene.closest_hit ({threads} threads)",
                 ours, "Mrays/s", err_t, "max |Δt|/t vs raw embreex",
                 {"vs embreex": ours / raw_speed, "vs trimesh.ray": ours / tm_speed},
                 {**sizes, "face ids differing vs embreex": diff_face, "BVH build s": t_build}),
        BenchRow("visibility.closest_hit", "RayScene.closest_hit (1 thread)",
                 n / t_one / 1e6, "Mrays/s", None, None,
                 {"vs embreex": (n / t_one / 1e6) / raw_speed}, {}),
        BenchRow("visibility.closest_hit", "raw embreex run(output=1), 1 call, robust BVH",
                 raw_speed, "Mrays/s", None, None, {}, sizes),
        BenchRow("visibility.closest_hit", "trimesh mesh.ray.intersects_id",
                 tm_speed, "Mrays/s", err_tm, "max |Δt|/t vs RayScene",
                 {}, {"rays": n_tm, "face ids differing vs RayScene": diff_tm}),
    ]


def _surface_points(mesh, n: int, rng: np.random.Generator):
    """Uniform random points on the mesh and their face normals."""
    area = np.asarray(mesh.area_faces)
    f = rng.choice(len(area), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)[f]]
    p = np.einsum("ni,nij->nj", w, tri)
    return p, np.asarray(mesh.face_normals)[f]


@register("visibility.occluded")
def bench_occluded(quick: bool) -> list[BenchRow]:
    from facegeo.surface.visibility import RayScene

    rng = np.random.default_rng(20000)
    mesh = _mesh(quick)
    n = 200_000 if quick else 1_000_000
    repeat = 2 if quick else 3
    scene = RayScene.from_trimesh(mesh).build()
    p, nrm = _surface_points(mesh, n, rng)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # Shadow rays toward the hemisphere above the surface, as toward lights that can reach it.
    d *= np.where(np.einsum("ni,ni->n", d, nrm) < 0, -1.0, 1.0)[:, None]

    t_ours, occ = best_of(lambda: scene.occluded(p, d, np.inf), repeat)
    threads = scene.n_threads
    scene.n_threads = 1
    t_one, _ = best_of(lambda: scene.occluded(p, d, np.inf), repeat)
    scene.n_threads = threads

    emb, _ = scene._scene()
    o32 = np.ascontiguousarray(p + scene.eps * d - scene._centre, dtype=np.float32)
    d32 = np.ascontiguousarray(d, dtype=np.float32)
    far = np.full(n, np.finfo(np.float32).max, dtype=np.float32)
    t_raw, raw = best_of(lambda: emb.run(o32, d32, query="OCCLUDED", dists=far), repeat)
    diff_raw = float(np.mean(occ != (raw == 0)))
    # The ceiling for incoherent rays: raw embreex on the same rays in Z-order (sort untimed).
    from facegeo.surface.visibility import _morton_order

    z = _morton_order(p, scene.bounds[0], scene.bounds[1])
    o32z, d32z = np.ascontiguousarray(o32[z]), np.ascontiguousarray(d32[z])
    t_rawz, _ = best_of(lambda: emb.run(o32z, d32z, query="OCCLUDED", dists=far), repeat)
    sorted_auto = scene._ray_order(p, d, np.ones(n), None) is not None

    # Consistency with closest_hit on a subset (occluded iff a hit exists).
    sub = np.linspace(0, n - 1, min(n, 100_000)).astype(np.int64)
    diff_closest = float(np.mean(scene.closest_hit(p[sub], d[sub]).hit != occ[sub]))

    n_tm = min(n, 200_000)
    o_tm = np.ascontiguousarray(p[:n_tm] + scene.eps * d[:n_tm])
    d_tm = np.ascontiguousarray(d[:n_tm])
    mesh.ray.intersects_any(o_tm[:10], d_tm[:10])
    t_tm, tm_any = best_of(lambda: mesh.ray.intersects_any(o_tm, d_tm), repeat)
    diff_tm = float(np.mean(np.asarray(tm_any) != occ[:n_tm]))

    ours = n / t_ours / 1e6
    raw_speed = n / t_raw / 1e6
    tm_speed = n_tm / t_tm / 1e6
    sizes = {"faces": scene.n_faces, "rays": n, "occluded fraction": float(occ.mean())}
    return [
        BenchRow("visibility.occluded", f"RayScene.occluded ({threads} threads)",
                 ours, "Mrays/s", diff_raw, "fraction differing vs raw embreex",
                 {"vs embreex": ours / raw_speed, "vs trimesh.ray": ours / tm_speed},
                 {**sizes, "differing vs closest_hit": diff_closest,
                  "Z-order sorting (auto)": sorted_auto}),
        BenchRow("visibility.occluded", "RayScene.occluded (1 thread)",
                 n / t_one / 1e6, "Mrays/s", None, None,
                 {"vs embreex": (n / t_one / 1e6) / raw_speed}, {}),
        BenchRow("visibility.occluded", "raw embreex run(query='OCCLUDED'), 1 call, robust BVH",
                 raw_speed, "Mrays/s", None, None, {}, sizes),
        BenchRow("visibility.occluded", "raw embreex, same rays pre-sorted in Z-order (untimed)",
                 n / t_rawz / 1e6, "Mrays/s", None, None,
                 {"RayScene.occluded vs this": ours / (n / t_rawz / 1e6)}, {}),
        BenchRow("visibility.occluded", "trimesh mesh.ray.intersects_any (origin moved eps)",
                 tm_speed, "Mrays/s", diff_tm, "fraction differing vs RayScene",
                 {}, {"rays": n_tm}),
    ]
