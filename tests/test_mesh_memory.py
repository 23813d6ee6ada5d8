"""The camera–camera route in bounded memory (issue 34): compressed point maps, block-wise steps.

Every step now works on the decoded pixels only, in blocks; these tests hold it to giving the
same numbers as the full-grid computations it replaced (bit for bit where stated: the blocks
change no arithmetic), and to memory that follows the decoded pixels rather than the image:

* the 3 × 3 window tests at chosen pixels against the ``(H, W)`` ones;
* the duplicate search against ``np.unique``; the slab-wise clusters against the components
  of every pair within the link distance; the blocked spacing and solver against one block;
* camera–camera triangulation and fusion with tiny blocks against the default blocks;
* the plane fit at chosen pixels against the ``(H, W)`` one; the compressed code set and noise
  against the maps they came from;
* traced allocations (numpy reports them to ``tracemalloc``) of triangulating and fusing two
  4-Mpx cameras that decoded a 1 % window: under one float64 ``(H, W)`` grid (the full-grid
  version allocated dozens).

Measured figures at 16 Mpx are the benchmark's (``facegeo bench mesh.full_resolution``,
docs/mesh.md).
"""

from __future__ import annotations

import numpy as np
import pytest

from facegeo.geometry import _camera_pairs, _fusion, _point_maps, _rays
from facegeo.geometry import triangulation as tr
from facegeo.geometry.code_maps import (CodeNoise, CodeSet, interpolate_code_map,
                                        interpolate_code_values)

#: Traced peak of triangulating + fusing two cameras that decoded ~1 % of their pixels, in
#: float64 (H, W) grids per camera (the full-grid version: ≈ 40; now a uint8 reason grid and,
#: while fusing, an int32 lookup grid per camera — 0.63 — and the decoded pixels' arrays).
MAX_PEAK_IN_FLOAT64_GRIDS = 1.0


def _sparse_map(rng, H=37, W=53, frac=0.6):
    """A PointMap with random points on a random subset of pixels (some rejected), and the
    camera centre at the origin."""
    index = np.flatnonzero(rng.random(H * W) < frac)
    n = index.size
    pts = rng.normal(0.0, 0.01, (n, 3)) + [0.0, 0.0, 0.5]
    reason = np.full(H * W, tr.NO_CODE, np.uint8)
    reason[index] = np.where(rng.random(n) < 0.85, tr.OK, tr.UNCERTAIN)
    pts[reason[index] != tr.OK] = np.nan
    sig = rng.uniform(1e-4, 1e-3, n)
    return tr.PointMap("cam", (H, W), index, pts, sig, np.full(n, np.nan),
                       np.ones(n, np.float32), reason.reshape(H, W), np.zeros(3))


def test_window_tests_at_pixels_equal_the_grid_ones():
    rng = np.random.default_rng(0)
    pm = _sparse_map(rng)
    lut = pm.lookup()
    flat = np.arange(pm.shape[0] * pm.shape[1])  # every pixel, borders and holes included
    grid = pm.depth
    np.testing.assert_array_equal(_point_maps._median3_at(lut, pm.depth_at, flat),
                                  tr._median3(grid).ravel())
    s = np.where(pm.valid_at, pm.point_sigma, np.nan)
    sgrid = np.where(pm.valid, pm.sigma, np.nan)
    np.testing.assert_array_equal(_point_maps._min3_at(lut, s, flat), tr._min3(sgrid).ravel())


def test_point_map_views_and_rejection():
    rng = np.random.default_rng(1)
    pm = _sparse_map(rng)
    v = pm.valid
    assert v.sum() == pm.valid_at.sum()
    np.testing.assert_array_equal(pm.p_world[v], pm.points[pm.valid_at])
    assert np.isnan(pm.p_world[~v]).all() and np.isnan(pm.sigma.ravel()[
        np.setdiff1d(np.arange(v.size), pm.index)]).all()
    np.testing.assert_array_equal(pm.positions(pm.index), np.arange(len(pm)))
    assert (pm.positions([-5 + 0 * pm.index[0]]) == -1).all() or pm.index[0] == 0
    # reject three valid pixels and one pixel without a point: only the valid ones change
    flat = np.concatenate([pm.index[pm.valid_at][:3], np.setdiff1d(np.arange(v.size),
                                                                   pm.index)[:1]])
    before = pm.reason_counts()
    pm.reject_at(flat, tr.OUTLIER)
    after = pm.reason_counts()
    assert after["outlier"] == before["outlier"] + 3 and after["ok"] == before["ok"] - 3
    assert np.isnan(pm.p_world.reshape(-1, 3)[flat[:3]]).all()


def test_duplicate_search_equals_numpy_unique():
    rng = np.random.default_rng(2)
    p = rng.normal(size=(5000, 3)).round(1)  # many exact duplicates
    p[::7] = p[::7] * 0.0  # -0.0 and 0.0 compare equal, as in np.unique
    p[1::7] = -p[1::7] * 0.0
    want = np.sort(np.unique(p, axis=0, return_index=True)[1])
    np.testing.assert_array_equal(_fusion._first_of_each_point(p), want)
    assert _fusion._first_of_each_point(np.zeros((0, 3))).size == 0


def test_slab_clusters_equal_the_components_of_all_pairs(monkeypatch):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    centres = rng.uniform(-1, 1, (40, 3))
    p = (centres[rng.integers(0, 40, 6000)] + rng.normal(0, 0.03, (6000, 3)))
    r = 0.05
    pairs = cKDTree(p).query_pairs(r, output_type="ndarray")
    n = len(p)
    _, want = connected_components(coo_matrix((np.ones(len(pairs)), tuple(pairs.T)),
                                              shape=(n, n)), directed=False)
    monkeypatch.setattr(_fusion, "_SLAB_POINTS", 97)  # many slabs, each narrower than r
    got = _fusion._components_within(p, r)
    # the same partition: a bijection between the labels
    pair_labels = np.unique(np.stack([want, got], 1), axis=0)
    assert len(pair_labels) == len(np.unique(want)) == len(np.unique(got))


def test_blocked_spacing_and_solver_equal_one_block(monkeypatch):
    rng = np.random.default_rng(4)
    p = rng.normal(size=(3001, 3))
    whole = tr.neighbour_spacing(p)
    monkeypatch.setattr(_fusion, "_QUERY_CHUNK", 100)
    assert tr.neighbour_spacing(p) == whole
    cams, proj = _rig()
    x, y, _ = _decode(cams[0], proj)
    pm = tr.triangulate_maps(cams[0], proj, x, y)
    monkeypatch.setattr(_rays, "_SOLVE_CHUNK", 333)  # blocks of 333 rays, none of one ray
    pm2 = tr.triangulate_maps(cams[0], proj, x, y)
    np.testing.assert_array_equal(pm2.points, pm.points)
    np.testing.assert_array_equal(pm2.point_sigma, pm.point_sigma)
    np.testing.assert_array_equal(pm2.reason, pm.reason)


def _rig():
    from facegeo.geometry.rig import default_rig

    rig = default_rig().scaled(1 / 3)
    return list(rig.cameras), rig.projector.scaled(0.5)


SPHERE_C = np.array([0.004, -0.003, 0.01])
SPHERE_R = 0.09


def _decode(cam, proj, noise=0.1, seed=0):
    o, d = cam.pixel_rays()
    oc = o - SPHERE_C
    b = np.einsum("...i,...i->...", oc, d)
    disc = b * b - (np.einsum("...i,...i->...", oc, oc) - SPHERE_R**2)
    hit = disc > 0
    with np.errstate(invalid="ignore"):
        p = o + (-b - np.sqrt(disc))[..., None] * d
        q, front = proj.project(np.where(hit[..., None], p, 0.0))
        lit = hit & front & proj.in_image(q) & (
            np.einsum("...i,...i->...", p - SPHERE_C, proj.center_world - p) > 0)
    q = q + np.random.default_rng(seed).normal(0, noise, q.shape)
    return np.where(lit, q[..., 0], np.nan), np.where(lit, q[..., 1], np.nan), lit


def test_camera_pairs_and_fusion_do_not_depend_on_the_blocks(monkeypatch):
    """Tiny blocks (odd sizes, so every block boundary falls somewhere else) give the same
    maps and fused points, bit for bit, as the default blocks."""
    cams, proj = _rig()
    dec = [_decode(c, proj, seed=i) for i, c in enumerate(cams)]
    xs, ys = [d[0] for d in dec], [d[1] for d in dec]
    sig = {"sigma_x": [np.full(x.shape, 0.1) for x in xs],
           "sigma_y": [np.full(x.shape, 0.2) for x in xs]}

    def run():
        maps, _ = tr.triangulate_camera_pairs(cams, xs, ys, **sig)
        views = [(m.p_world, m.sigma, m.reason.copy(), m.code_gains.dt_dcode.copy())
                 for m in maps]
        return views, tr.fuse_cameras(maps, cams)

    views, fused = run()
    monkeypatch.setattr(_camera_pairs, "_MATCH_CHUNK", 1237)
    monkeypatch.setattr(_fusion, "_FUSE_CHUNK", 911)
    monkeypatch.setattr(_point_maps, "_WINDOW_CHUNK", 777)
    views2, fused2 = run()
    for a, b in zip(views, views2):
        for u, v in zip(a, b):
            np.testing.assert_array_equal(u, v)
    assert len(fused) > 10_000
    for k in ("p_world", "sigma", "confidence", "camera", "pixel", "confirmed"):
        np.testing.assert_array_equal(getattr(fused2, k), getattr(fused, k))


def test_plane_fit_at_pixels_and_code_set_equal_the_maps():
    rng = np.random.default_rng(5)
    H, W = 60, 90
    u = np.arange(W)[None, :] * np.ones((H, 1))
    v = np.arange(H)[:, None] * np.ones((1, W))
    code = np.floor((0.3 * u + 0.1 * v + 2) / 2) * 2 + 0.5
    code[rng.random((H, W)) < 0.2] = np.nan
    code = code.astype(np.float32)
    r = interpolate_code_map(code, window=7)
    index = np.flatnonzero(np.isfinite(code))
    c, s = interpolate_code_values(code, index, window=7)
    np.testing.assert_array_equal(c, r.code.ravel()[index])
    np.testing.assert_array_equal(s, r.sigma.ravel()[index])
    # the code set keeps exactly the pixels with both codes; the noise is read anywhere
    y = np.where(rng.random((H, W)) < 0.1, np.nan, v + 0.25)
    sx = np.where(rng.random((H, W)) < 0.3, np.nan, rng.uniform(-0.1, 0.5, (H, W)))
    cs = CodeSet.from_maps(code, y, sigma_x=sx, sigma_y=None)
    gx, gy = cs.grids()
    both = np.isfinite(code) & np.isfinite(y)
    np.testing.assert_array_equal(np.isfinite(gx), both)
    np.testing.assert_array_equal(gx[both], code[both].astype(np.float64))
    want = np.stack([np.where(np.isfinite(sx) & (sx > 0), sx, 0.3), np.full((H, W), 0.3)], -1)
    np.testing.assert_array_equal(cs.noise.grid(0.3), want)
    with pytest.raises(Exception, match="sigma"):
        CodeNoise((H, W), np.arange(3), np.zeros((2, 2)))


def test_memory_follows_the_decoded_pixels_not_the_image(monkeypatch):
    """Two 2448 × 1632 cameras of the full-resolution benchmark's rig that decoded a central
    window of ≈ 1 % of their pixels: the traced peak of triangulating and fusing them stays
    under one float64 (H, W) grid per camera (2 × 30 MB), with blocks of 4096 pixels (the blocks' own
    temporaries, ≈ 1.3 kB a pixel in the code match, are bounded by the block size, not by
    the image)."""
    import tracemalloc

    for mod, name in ((_camera_pairs, "_MATCH_CHUNK"), (_fusion, "_FUSE_CHUNK"),
                      (_point_maps, "_WINDOW_CHUNK"), (_rays, "_SOLVE_CHUNK")):
        monkeypatch.setattr(mod, name, 4096)

    from facegeo.bench.mesh import _ellipsoid_hits, _ellipsoid_rig

    rig = _ellipsoid_rig(0.5)
    xs, ys = [], []
    for cam in rig.cameras:
        H, W = cam.height, cam.width
        r0, c0 = H // 2 - 80, W // 2 - 120
        q, lit = _ellipsoid_hits(cam, rig.projector, r0, r0 + 160)
        x = np.full((H, W), np.nan, np.float32)
        y = np.full((H, W), np.nan, np.float32)
        sl = (slice(r0, r0 + 160), slice(c0, c0 + 240))
        x[sl] = np.where(lit, q[..., 0], np.nan)[:, c0:c0 + 240]
        y[sl] = np.where(lit, q[..., 1], np.nan)[:, c0:c0 + 240]
        xs.append(x)
        ys.append(y)
    grid_bytes = 8 * sum(x.size for x in xs)
    import scipy.sparse.csgraph  # noqa: F401  (imports are not the steps' memory)
    import scipy.spatial  # noqa: F401

    tracemalloc.start()
    try:
        codes = [CodeSet.from_maps(x, y) for x, y in zip(xs, ys)]
        maps, _ = tr.triangulate_code_sets(rig.cameras, codes)
        fused = tr.fuse_cameras(maps, rig.cameras)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(fused) > 5_000  # the windows overlap on the surface in part
    assert peak < MAX_PEAK_IN_FLOAT64_GRIDS * grid_bytes, (peak / 2**20, grid_bytes / 2**20)
