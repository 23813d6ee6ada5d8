"""Pull–push over space (:func:`facegeo.surface.pullpush.pull_push_points`) and the renderer's
inference of texels no camera measured over the surface rather than the atlas
(:func:`facegeo.render.novel.infer_texel_colours`, issue 37)."""

from __future__ import annotations

import numpy as np
import pytest

from facegeo.errors import InputError, ShapeError
from facegeo.surface.pullpush import pull_push_points

#: On a 90 mm sphere sampled at ≈ 1 mm, a linear field is filled within this (absolute, the
#: field spans 1) over unknown points within 6 mm of the known cap (measured 0.006–0.02).
LINEAR_NEAR_TOL = 0.05
#: Two unknown points a tenth of a cell apart differ by at most this (the field spans 1;
#: measured ≤ 0.004): the trilinear push makes the fill continuous in position.
CONTINUITY_TOL = 0.02


def _sphere(n, seed=0, r=0.09):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    return d * r, d


def test_known_rows_unchanged_and_a_constant_filled_exactly():
    p, d = _sphere(20000)
    vals = np.stack([d[:, 0], np.full(len(d), 0.25)], axis=1)
    known = d[:, 2] > 0.3
    given = vals.copy()
    given[~known] = np.nan
    out = pull_push_points(p, given, known)
    assert out.dtype == np.float32 and out.shape == vals.shape
    assert np.array_equal(out[known], vals[known].astype(np.float32))
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out[~known, 1], 0.25, rtol=1e-6)
    # one column in, one column out
    one = pull_push_points(p, given[:, 1], known)
    assert one.shape == (len(p),)
    np.testing.assert_allclose(one, 0.25, rtol=1e-6)


def test_a_smooth_field_is_continued_across_the_boundary_and_continuously():
    p, d = _sphere(60000)
    field = 0.5 + 0.5 * d[:, 0]  # linear in position, spans [0, 1]
    known = d[:, 2] > 0.2
    out = pull_push_points(p, np.where(known, field, np.nan), known)
    near = ~known & (d[:, 2] > 0.2 - 6e-3 / 0.09)  # within ≈ 6 mm of the known cap
    assert near.sum() > 500
    assert np.abs(out[near] - field[near]).mean() <= LINEAR_NEAR_TOL
    # continuity: the fill at points a tenth of a cell (≈ 0.1 mm) from the unknown ones
    q = p[~known][:2000]
    step = np.array([1e-4, 0.0, 0.0])
    both = np.vstack([p, q, q + step])
    k2 = np.concatenate([known, np.zeros(2 * len(q), bool)])
    v2 = np.concatenate([np.where(known, field, np.nan), np.full(2 * len(q), np.nan)])
    f = pull_push_points(both, v2, k2, cell=1e-3)
    a, b = f[len(p):len(p) + len(q)], f[len(p) + len(q):]
    assert np.abs(a - b).max() <= CONTINUITY_TOL


def test_bad_input_is_refused_with_what_was_wrong():
    p, d = _sphere(100)
    known = d[:, 2] > 0
    with pytest.raises(ShapeError, match="points"):
        pull_push_points(p[:, :2], d[:, 0], known)
    with pytest.raises(ShapeError, match="values"):
        pull_push_points(p, d[:-1, 0], known)
    with pytest.raises(ShapeError, match="known"):
        pull_push_points(p, d[:, 0], known[:-1])
    with pytest.raises(InputError, match="non-finite"):
        pull_push_points(p, np.where(known, np.nan, 1.0), known)
    with pytest.raises(InputError, match="cell"):
        pull_push_points(p, d[:, 0], known, cell=-1.0)
    with pytest.raises(InputError, match="too fine"):
        pull_push_points(p, d[:, 0], known, cell=1e-12)
    # nothing known: NaN rows, no error; nothing missing: the values back
    none = pull_push_points(p, d[:, 0], np.zeros(len(p), bool))
    assert np.isnan(none).all()
    np.testing.assert_array_equal(pull_push_points(p, d[:, 0], np.ones(len(p), bool)),
                                  d[:, 0].astype(np.float32))


def _two_charts():
    """A flat 40 × 20 mm strip of texels at 1 mm (red for x < 28 mm, blue beyond), cut at
    x = 20 mm into two charts laid out in the atlas so that the left chart's right edge sits
    beside the blue end of the right chart (mirrored), while in space it meets red texels."""
    from facegeo.surface.atlas import Texels

    ys, xs = np.mgrid[0:20, 0:40]
    x, y = xs.ravel(), ys.ravel()
    p = np.stack([x * 1e-3, y * 1e-3, np.zeros(x.size)], axis=1)
    n = np.tile([0.0, 0.0, 1.0], (x.size, 1))
    # atlas: the left chart (x < 20) at columns 0–19; the right chart (x ≥ 20) placed at
    # columns 21–40 but mirrored (x = 39 beside the left chart's x = 19 across one gutter)
    col = np.where(x < 20, x, 21 + (39 - x))
    tex = Texels(row=y.astype(np.int64), col=col.astype(np.int64),
                 face=np.zeros(x.size, np.int64), bary=np.zeros((x.size, 3)), p_world=p,
                 n_world=n, n_geom=n, index_map=None)
    colour = np.where((x < 28)[:, None], [0.8, 0.1, 0.1], [0.1, 0.1, 0.8]).astype(np.float32)
    return tex, x, colour


def test_inference_over_the_surface_takes_the_neighbours_in_space_not_on_the_atlas():
    """The left chart's last 6 columns unmeasured: over the surface they take the red of the
    texels on both sides of them in space; pull–push on the atlas (``space="texture"``) pulls
    in the blue of the chart beside them in the atlas (the patches issue 37's renders showed)."""
    from facegeo.render.novel import infer_texel_colours

    tex, x, colour = _two_charts()
    hole = (x >= 14) & (x < 20)
    given = colour[None].copy()
    given[:, hole] = np.nan
    need = np.arange(x.size)
    surf, miss = infer_texel_colours(tex, need, given)
    assert np.array_equal(miss, hole)
    assert np.array_equal(surf[:, ~hole], colour[None, ~hole])
    red = np.array([0.8, 0.1, 0.1])
    # (the blue 8 mm away reaches the hole through the pyramid's coarse levels, a little)
    err = np.abs(surf[0, hole] - red).max(axis=1)
    assert err.mean() < 0.05 and err.max() < 0.1, (err.mean(), err.max())
    flat, _ = infer_texel_colours(tex, need, given, space="texture")
    old = np.abs(flat[0, hole] - red).max(axis=1)
    assert old.mean() > 0.2 and old.max() > 0.5, (old.mean(), old.max())  # blue bleeds in
    with pytest.raises(InputError, match="space"):
        infer_texel_colours(tex, need, given, space="uv")
