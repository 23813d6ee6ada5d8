"""Code regions matched by their centroids (facegeo.geometry.code_regions).

Analytic case: two cameras 12° apart and a projector between them see a plane 0.5 m away; each
camera pixel's projector code is the projector pixel its plane point falls in (a Gray code names
the block's centre), the projector coarse enough that each code covers ≈ 3 × 3 camera pixels.
"""

from __future__ import annotations

import numpy as np
import pytest

from facegeo.errors import InputError
from facegeo.frames import look_at
from facegeo.geometry.camera import Camera
from facegeo.geometry.code_regions import code_region_centroids, triangulate_region_centroids

#: Centroid points to the plane, RMS, millimetres (measured 2.27 mm with 4-row blocks, 2.36 with
#: 1-row ones: 0.5 m away, 240-px-wide cameras 0.105 m apart, 7.9 mm of depth per pixel of
#: disparity — a centroid error of ≈ 0.2 px).
PLANE_RMS_MM = 3.5
#: std(error / σ) along the camera ray, at most (measured 1.86: the centroid covariance, the
#: region's scatter over its count, does not hold the boundary's quantisation, which is
#: correlated along the region's edge — σ is about half the error).
SIGMA_STD_MAX = 2.5
#: Regions of one camera matched in the other, at least (measured 0.93: the border regions one
#: camera sees cut are the rest).
MATCHED_FRACTION = 0.8

Z_PLANE = 0.5


def _cam(name, eye, w=240, h=180, f=300.0):
    K = np.array([[f, 0, (w - 1) / 2 + 3.0], [0, f * 1.01, (h - 1) / 2 - 2.0], [0, 0, 1]])
    return Camera(name, w, h, K, np.zeros(5), look_at(eye, (0.0, 0.0, Z_PLANE)))


def _codes(cam, proj, block=(1.0, 1.0)):
    q = cam.pixel_grid().reshape(-1, 2)
    o, d = cam.pixel_rays(q)
    t = (Z_PLANE - o[:, 2]) / d[:, 2]
    p = o + t[:, None] * d
    qp, front = proj.project(p)
    inside = front & (qp[:, 0] >= -0.5) & (qp[:, 0] < proj.width - 0.5) & \
        (qp[:, 1] >= -0.5) & (qp[:, 1] < proj.height - 0.5)
    out = []
    for i, b in enumerate(block):
        c = np.floor((qp[:, i] + 0.5) / b) * b + (b - 1) / 2.0  # the block's centre
        out.append(np.where(inside, c, np.nan).reshape(cam.height, cam.width))
    return out


@pytest.fixture(scope="module")
def rig():
    a = _cam("a", (-0.05, 0.01, 0.0))
    b = _cam("b", (0.055, -0.01, 0.0))
    proj = _cam("p", (0.0, 0.0, 0.0), w=80, h=60, f=100.0)
    return a, b, proj


def test_centroids_average_each_code_region():
    x = np.array([[0.0, 0.0, 1.0], [0.0, np.nan, 1.0]])
    y = np.zeros_like(x)
    c = code_region_centroids(x, y, block_x=1, block_y=1)
    assert c.key.size == 2
    np.testing.assert_allclose(c.q[0], [1 / 3, 1 / 3])  # (0,0), (1,0), (0,1): col, row
    np.testing.assert_allclose(c.q[1], [2.0, 0.5])
    assert list(c.count) == [3, 2]
    # coarser keys merge regions
    assert code_region_centroids(x, y, block_x=2, block_y=1).key.size == 1


def test_centroid_points_lie_on_the_plane(rig):
    a, b, proj = rig
    xa, ya = _codes(a, proj)
    xb, yb = _codes(b, proj, block=(1.0, 4.0))  # b resolves fewer row bits
    # match at the coarser camera's blocks
    ca = code_region_centroids(xa, ya, block_x=1, block_y=4)
    cb = code_region_centroids(xb, yb, block_x=1, block_y=4)
    r = triangulate_region_centroids(a, b, ca, cb)
    assert r.counts["points"] >= MATCHED_FRACTION * min(ca.key.size, cb.key.size)
    err_mm = (r.p_world[:, 2] - Z_PLANE) * 1e3
    assert np.sqrt(np.mean(err_mm**2)) < PLANE_RMS_MM
    # the plane faces the cameras: the error along the ray is ≈ the error in z
    assert np.std(err_mm * 1e-3 / r.sigma) < SIGMA_STD_MAX
    assert np.all(np.isfinite(r.sigma)) and np.all(r.sigma > 0)
    assert r.pixel.min() >= 0 and (r.pixel < [a.width, a.height]).all()


def test_wrong_correspondences_are_inconsistent(rig):
    import dataclasses

    a, b, proj = rig
    xa, ya = _codes(a, proj)
    xb, yb = _codes(b, proj)
    ca = code_region_centroids(xa, ya, block_x=1, block_y=1)
    cb = code_region_centroids(xb, yb, block_x=1, block_y=1)
    right = triangulate_region_centroids(a, b, ca, cb)
    # b's centroids 5 px off the epipolar lines (down the rows): no ray pair meets
    moved = dataclasses.replace(cb, q=cb.q + [0.0, 5.0])
    wrong = triangulate_region_centroids(a, b, ca, moved)
    assert wrong.counts["points"] < 0.1 * right.counts["points"]
    assert wrong.counts["inconsistent"] > 0.8 * wrong.counts["common"]


def test_no_common_code_gives_no_point(rig):
    a, b, _ = rig
    x = np.full((a.height, a.width), np.nan)
    x[0, 0] = 3.0
    c1 = code_region_centroids(x, x, block_x=1, block_y=1)
    c2 = code_region_centroids(x + 10, x + 10, block_x=1, block_y=1)
    r = triangulate_region_centroids(a, b, c1, c2)
    assert r.p_world.shape == (0, 3) and r.counts["points"] == 0


@pytest.mark.parametrize("kw", [{"block_x": 0.5, "block_y": 1}, {"block_x": 1, "block_y": np.nan}])
def test_bad_blocks_are_refused(kw):
    with pytest.raises(InputError, match="block"):
        code_region_centroids(np.zeros((2, 2)), np.zeros((2, 2)), **kw)


def test_code_block_reads_the_gray_block_from_sigma():
    from facegeo.geometry.code_regions import code_block

    assert code_block(np.full((3, 3), 4 / np.sqrt(12))) == 4.0
    assert code_block(np.full((3, 3), 1 / np.sqrt(12))) == 1.0
    assert code_block(np.full((3, 3), 0.05)) == 1.0  # a phase decode: finer than a pixel
    assert code_block(np.full((3, 3), np.nan)) == 1.0


def test_hole_fill_adds_points_only_in_the_holes(rig):
    from facegeo.geometry.code_regions import hole_fill_points

    a, b, proj = rig
    xa, ya = _codes(a, proj)
    xb, yb = _codes(b, proj)
    full = hole_fill_points([a, b], [xa, xb], [ya, yb], [(1, 1), (1, 1)], np.zeros((0, 3)),
                            min_gap=1e-3)
    p = full["p_world"]
    assert len(p) > 1000 and (full["camera"] == 0).all()
    # existing points everywhere but a 4 cm disc: the fill lands in the disc only
    hole = np.linalg.norm(p[:, :2], axis=1) < 0.02
    fill = hole_fill_points([a, b], [xa, xb], [ya, yb], [(1, 1), (1, 1)], p[~hole],
                            min_gap=3e-3)
    got = np.linalg.norm(fill["p_world"][:, :2], axis=1)
    assert len(got) > 0.5 * hole.sum()
    assert (got < 0.02 + 3e-3).all()
    with pytest.raises(InputError, match="min_gap"):
        hole_fill_points([a, b], [xa, xb], [ya, yb], [(1, 1), (1, 1)], p, min_gap=0.0)


def test_coarsened_centroids_equal_the_coarse_reduction(rig, monkeypatch):
    """Merging fine regions' moments gives what reducing the maps at the coarse block gives,
    and the banded reduction equals one band over the whole image."""
    import facegeo.geometry.code_regions as cr

    a, _, proj = rig
    x, y = _codes(a, proj)
    monkeypatch.setattr(cr, "CENTROID_ROWS", 7)  # many bands, regions across them
    fine = code_region_centroids(x, y, block_x=1, block_y=2)
    coarse = code_region_centroids(x, y, block_x=4, block_y=8)
    merged = cr.coarsen_centroids(fine, 4, 4)
    np.testing.assert_array_equal(merged.key, coarse.key)
    np.testing.assert_array_equal(merged.count, coarse.count)
    np.testing.assert_allclose(merged.q, coarse.q, rtol=0, atol=1e-9)
    np.testing.assert_allclose(merged.cov, coarse.cov, rtol=1e-6, atol=1e-12)
    monkeypatch.setattr(cr, "CENTROID_ROWS", 10**6)  # one band
    whole = code_region_centroids(x, y, block_x=1, block_y=2)
    np.testing.assert_array_equal(whole.key, fine.key)
    np.testing.assert_allclose(whole.q, fine.q, rtol=0, atol=1e-9)
    np.testing.assert_allclose(whole.cov, fine.cov, rtol=1e-6, atol=1e-12)
    assert cr.coarsen_centroids(fine, 1, 1) is fine
    with pytest.raises(InputError, match="factor"):
        cr.coarsen_centroids(fine, 1.5, 1)
