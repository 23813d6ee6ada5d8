"""Pull–push hole filling (Gortler et al. 1996, *The Lumigraph*, §3.4), in texture space and
over points in space.

Texels no camera sees are *flagged*, never measured; :func:`pull_push` fills them from their
neighbours on the atlas image across a pyramid, for the atlas previews;
:func:`pull_push_points` fills values carried by points from their neighbours in space, for the
novel-view renderer's inferred texels (:func:`facegeo.render.novel.infer_texel_colours`:
surface no camera saw, marked as inferred and never counted as measured). The image's rules:

* **pull**: each coarser level holds the weighted mean of 2 × 2 finer texels, with weight the
  sum of the (clamped) finer weights, clamped to 1;
* **push**: each finer texel keeps its own value in proportion to its clamped weight ``w`` and
  takes ``1 − w`` from the coarser level (nearest-neighbour upsampled).

Texels with weight ≥ 1 are returned unchanged, so measured data is never altered; the filled
values are inferences, kept apart from measured ones by the caller's mask.
"""

from __future__ import annotations

import numpy as np

from facegeo.checks import as_array
from facegeo.errors import InputError, ShapeError

__all__ = ["pull_push", "pull_push_points"]


def _pull(v: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    h, wd = w.shape
    H2, W2 = (h + 1) // 2, (wd + 1) // 2
    wp = np.zeros((2 * H2, 2 * W2), np.float64)
    vp = np.zeros((2 * H2, 2 * W2) + v.shape[2:], np.float64)
    wp[:h, :wd] = w
    vp[:h, :wd] = v * w[..., None]
    ws = wp.reshape(H2, 2, W2, 2).sum(axis=(1, 3))
    vs = vp.reshape(H2, 2, W2, 2, -1).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        vc = np.where(ws[..., None] > 0, vs / ws[..., None], 0.0)
    return vc, np.minimum(ws, 1.0)


def pull_push(values, weights, *, levels: int | None = None) -> np.ndarray:
    """Fill low-weight texels of an image from a weighted pyramid.

    Parameters
    ----------
    values : (H, W) or (H, W, C) float
        Image; values where ``weights == 0`` are ignored (may be NaN).
    weights : (H, W) float, ≥ 0
        Confidence per texel; 0 = unknown, ≥ 1 = fully trusted (kept as is).
    levels : int, optional
        Pyramid depth; default until the coarsest level is 1 × 1.

    Returns
    -------
    (H, W) or (H, W, C) float32
        Filled image; texels are NaN only when every weight is 0.
    """
    v = as_array(values, "values", dtype=np.float64, finite=False)
    if v.ndim not in (2, 3):
        raise ShapeError(f"values: expected shape (H, W) or (H, W, C), got {v.shape}")
    w = as_array(weights, "weights", shape=v.shape[:2])
    if np.any(w < 0):
        raise InputError("weights: expected weights >= 0")
    squeeze = v.ndim == 2
    if squeeze:
        v = v[..., None]
    w = np.minimum(w, 1.0)
    v = np.where(w[..., None] > 0, v, 0.0)
    if not np.all(np.isfinite(v)):
        raise InputError("values: non-finite values where the weight is > 0")
    pyr = [(v, w)]
    n = 0
    while max(pyr[-1][1].shape) > 1 and (levels is None or n < levels):
        pyr.append(_pull(*pyr[-1]))
        n += 1
    cur, cw = pyr[-1]
    out = np.where(cw[..., None] > 0, cur, np.nan)
    for vf, wf in reversed(pyr[:-1]):
        h, wd = wf.shape
        up = np.repeat(np.repeat(out, 2, axis=0), 2, axis=1)[:h, :wd]
        with np.errstate(invalid="ignore"):
            out = np.where(wf[..., None] >= 1, vf,
                           wf[..., None] * vf + (1 - wf[..., None]) * up)
        out = np.where((wf[..., None] > 0) & ~np.isfinite(up), vf, out)
    out = out.astype(np.float32)
    return out[..., 0] if squeeze else out


def _cell_keys(q: np.ndarray) -> np.ndarray:
    """Pack (N, 3) non-negative int64 cell coordinates (< 2**21 each) into one int64 key."""
    return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]


def _lookup(keys: np.ndarray, table_keys: np.ndarray) -> np.ndarray:
    """Index of each key in the sorted ``table_keys``, −1 where absent."""
    i = np.searchsorted(table_keys, keys)
    i = np.minimum(i, table_keys.size - 1)
    return np.where(table_keys[i] == keys, i, -1)


def pull_push_points(points, values, known, *, cell: float | None = None,
                     chunk: int = 65536) -> np.ndarray:
    """Fill the unknown rows of values carried by points on a surface, from a pull–push pyramid
    of cubic cells in 3-D (Gortler et al. 1996 §3.4's rules, over space instead of an image).

    :func:`pull_push` fills an atlas image, where the texels beside a hole are the ones beside
    it on the atlas: across a chart's edge they belong to another part of the surface, and a
    chart nobody measured takes the colour of whatever chart lies next to it in the atlas
    (patches). Here a point's neighbours are its neighbours in space, so the fill is continuous
    over the surface whatever the parameterisation.

    * **pull**: level 0 holds the mean of the known points in each cell of side ``cell``, weight
      their count clamped to 1; each coarser level (cells twice the side) the weighted mean of
      its 2 × 2 × 2 children, weight the sum of theirs clamped to 1 — as :func:`pull_push`;
    * **push**, evaluated at each unknown point ``p``: ``f_K(p)`` at the coarsest level, then
      ``f_k(p) = a·Ŝ_k(p)/Ŵ_k(p) + (1 − a)·f_{k+1}(p)`` with ``a = min(1, Ŵ_k(p))``, where
      ``Ŵ_k`` and ``Ŝ_k`` are the level's weights and weighted means interpolated trilinearly
      between cell centres (an absent cell counts 0). Pull–push pushes a coarse value to its
      children unchanged (blocks of ``2^k`` texels); the trilinear push makes the fill a
      continuous function of position.

    Parameters
    ----------
    points : (N, 3) float — positions (any unit; ``cell`` in the same)
    values : (N,) or (N, C) float — values; rows where ``known`` is False are ignored (may be NaN)
    known : (N,) bool
    cell : float, optional — level 0's cell side; default the median distance from a known
        point to its nearest known neighbour (the texel pitch on an atlas's texels)
    chunk : int — unknown points evaluated per block (bounded memory)

    Returns
    -------
    (N,) or (N, C) float32 — known rows unchanged, unknown rows filled (NaN only when no row is
    known)
    """
    p = as_array(points, "points", dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ShapeError(f"points: expected shape (N, 3), got {p.shape}")
    v = as_array(values, "values", dtype=np.float64, finite=False)
    if v.ndim not in (1, 2) or v.shape[0] != p.shape[0]:
        raise ShapeError(f"values: expected shape ({p.shape[0]},) or ({p.shape[0]}, C), "
                         f"got {v.shape}")
    k = np.asarray(known, bool)
    if k.shape != (p.shape[0],):
        raise ShapeError(f"known: expected shape ({p.shape[0]},), got {k.shape}")
    squeeze = v.ndim == 1
    v2 = v.reshape(p.shape[0], -1)
    if not np.all(np.isfinite(v2[k])):
        raise InputError("values: non-finite values where known is True")
    out = v2.astype(np.float32)
    miss = np.flatnonzero(~k)
    if miss.size == 0 or not k.any():
        out[miss] = np.nan
        return out[:, 0] if squeeze else out
    pk, vk = p[k], v2[k]
    if cell is None:
        from scipy.spatial import cKDTree
        sub = pk[:: max(1, pk.shape[0] // 20000)]
        d = cKDTree(pk).query(sub, k=2)[0][:, 1] if pk.shape[0] > 1 else np.ones(1)
        cell = float(np.median(d[d > 0])) if np.any(d > 0) else 1.0
    cell = float(cell)
    if not (np.isfinite(cell) and cell > 0):
        raise InputError(f"cell: expected a finite number > 0, got {cell!r}")
    lo = np.minimum(p.min(axis=0), pk.min(axis=0)) - 2 * cell
    extent = float(np.max(p.max(axis=0) - lo)) + 2 * cell
    n_levels = max(1, int(np.ceil(np.log2(extent / cell))) + 1)
    if extent / cell >= 2 ** 20:
        raise InputError(f"cell: {cell!r} is too fine for points spanning {extent!r} "
                         "(more than 2**20 cells a side)")
    # pull: per level the sorted cell keys, clamped weights and weighted sums
    q = np.floor((pk - lo) / cell).astype(np.int64)
    keys, inv = np.unique(_cell_keys(q), return_inverse=True)
    cnt = np.bincount(inv, minlength=keys.size).astype(np.float64)
    sums = np.zeros((keys.size, vk.shape[1]))
    np.add.at(sums, inv, vk)
    mean = sums / cnt[:, None]
    coords = q[np.unique(inv, return_index=True)[1]]
    w = np.minimum(cnt, 1.0)
    levels = [(keys, w, mean)]
    for _ in range(1, n_levels):
        _, w_f, mean_f = levels[-1]
        cq = coords >> 1
        ck, cinv = np.unique(_cell_keys(cq), return_inverse=True)
        ws = np.bincount(cinv, weights=w_f, minlength=ck.size)
        vs = np.zeros((ck.size, mean_f.shape[1]))
        np.add.at(vs, cinv, mean_f * w_f[:, None])
        coords = cq[np.unique(cinv, return_index=True)[1]]
        levels.append((ck, np.minimum(ws, 1.0), vs / ws[:, None]))
        if ck.size == 1:
            break
    glob = vk.mean(axis=0)
    corners = np.array([[i, j, l] for i in (0, 1) for j in (0, 1) for l in (0, 1)], np.int64)
    for s in range(0, miss.size, chunk):
        rows = miss[s:s + chunk]
        f = np.broadcast_to(glob, (rows.size, vk.shape[1])).copy()
        for lev in range(len(levels) - 1, -1, -1):
            keys_l, w_l, mean_l = levels[lev]
            h = cell * (1 << lev)
            u = (p[rows] - lo) / h - 0.5
            base = np.floor(u).astype(np.int64)
            t = u - base
            W = np.zeros(rows.size)
            S = np.zeros((rows.size, vk.shape[1]))
            for c in corners:
                qq = base + c
                ok = (qq >= 0).all(axis=1)
                idx = np.full(rows.size, -1, np.int64)
                idx[ok] = _lookup(_cell_keys(qq[ok]), keys_l)
                tw = np.prod(np.where(c == 1, t, 1.0 - t), axis=1)
                hit = idx >= 0
                ww = tw[hit] * w_l[idx[hit]]
                W[hit] += ww
                S[hit] += ww[:, None] * mean_l[idx[hit]]
            a = np.minimum(W, 1.0)
            with np.errstate(invalid="ignore", divide="ignore"):
                m = np.where(W[:, None] > 0, S / np.where(W > 0, W, 1.0)[:, None], 0.0)
            f = a[:, None] * m + (1.0 - a[:, None]) * f
        out[rows] = f
    return out[:, 0] if squeeze else out
