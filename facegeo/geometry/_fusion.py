"""Fusion of several cameras' point maps (:mod:`facegeo.geometry.triangulation`).

:func:`fuse_cameras` checks every camera's points against the other cameras' maps (free-space
violations rejected, agreeing points averaged, with the covariance of camera–camera points made
from the same code maps), drops duplicates and small clusters. It works through the points in
blocks and finds clusters slab by slab, so that its working set stays a few hundred MB for
millions of points (issue 34: 8 M points of two 16-Mpx cameras).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facegeo.checks import as_array
from facegeo.errors import InputError
from facegeo.geometry._point_maps import OCCLUDED_VIEW, OUTLIER, PointMap, _median3_at, _take
from facegeo.geometry.camera import Camera

#: Points per block of :func:`fuse_cameras` (≈ 0.6 kB of temporaries a point with two cameras).
_FUSE_CHUNK = 1 << 16
#: Query points per block of :func:`neighbour_spacing`.
_QUERY_CHUNK = 1 << 18
#: Points per slab of :func:`_large_clusters` (its pairs within the link distance, ≈ 12 a
#: point on a surface: ≈ 50 MB a slab).
_SLAB_POINTS = 1 << 18


@dataclass
class FusedPoints:
    """Points of several cameras after the cross-camera check.

    Attributes
    ----------
    p_world : (N, 3) float64, metres, world frame
    sigma : (N,) float64, metres (1 σ, after averaging with agreeing cameras)
    confidence : (N,) float32, 0..1
    camera : (N,) int32, index of the observing camera (into ``camera_names``)
    pixel : (N, 2) int32, (column, row) in that camera
    confirmed : (N,) bool, another camera saw the same surface within tolerance
    camera_names : list of str
    centers_world : (C, 3) float64, metres, camera centres
    """

    p_world: np.ndarray
    sigma: np.ndarray
    confidence: np.ndarray
    camera: np.ndarray
    pixel: np.ndarray
    confirmed: np.ndarray
    camera_names: list
    centers_world: np.ndarray

    def __len__(self) -> int:
        return int(self.p_world.shape[0])

    @property
    def view_dirs(self) -> np.ndarray:
        """Unit vectors from each point toward its camera, ``(N, 3)`` float64, world frame."""
        v = self.centers_world[self.camera] - self.p_world
        return v / np.linalg.norm(v, axis=1, keepdims=True)


def _pixel_of(cam: Camera, p) -> tuple[np.ndarray, np.ndarray]:
    """The pixel of ``cam`` each world point ``p`` (N, 3) falls in, (N, 2) int64 (column, row),
    clipped to the image, and whether it is in front and inside the image (N,) bool: the
    partner pixel :func:`fuse_cameras` compares a point with."""
    q, front = cam.project(p)
    ok = front & cam.in_image(q)
    qi = np.rint(np.where(ok[:, None], q, 0)).astype(np.int64)
    qi[:, 0] = qi[:, 0].clip(0, cam.width - 1)
    qi[:, 1] = qi[:, 1].clip(0, cam.height - 1)
    return qi, ok


def fuse_cameras(maps: list[PointMap], cameras: list[Camera], *, tol_sigmas: float = 4.0,
                 tol_floor: float = 1e-3, average: bool = True,
                 cluster_spacings: float | None = 2.0,
                 min_cluster_fraction: float = 0.1, drop_gains: bool = False) -> FusedPoints:
    """Check every camera's points against the others' and merge them into one cloud.

    For a point ``p`` of camera A seen at pixel ``q_B`` of camera B, let ``d = |p − c_B|`` and
    ``D`` the 3 × 3 median depth of B's own points around ``q_B``, with tolerance
    ``τ = tol_sigmas·sqrt(σ_A² + σ_B²) + tol_floor``:

    * ``d < D − τ``: B looked through the place where ``p`` should be — a free-space violation;
      the point is rejected (reason :data:`OCCLUDED_VIEW` in A's map).
    * ``|d − D| ≤ τ``: confirmed; with ``average`` the point becomes the inverse-variance mean of
      ``p`` and B's point at the nearest pixel (σ shrinks accordingly; when A's and B's points
      are each other's nearest, both average to the same point and one copy is kept).
    * ``d > D + τ`` or B has no point there: no evidence (occluded in B, or unseen).

    The fused σ is that of the weighted mean ``Σ w_i p_i / Σ w_i`` (``w_i = 1/σ_i²``):
    ``σ² = (Σ w_i + 2 Σ_{i<j} w_i w_j C_ij (v_i·v_j)) / (Σ w_i)²``, ``v`` the rays, ``C_ij``
    the covariance of the two depths. Camera–projector points are independent (``C = 0``,
    ``σ² = 1 / Σ w_i``). Camera–camera points are not: A's and B's points of one surface point
    are made from the same two code maps — A's code at A's pixel is among the neighbours of B's
    local fit into A, and B's code at B's pixel among A's — so ``C_ij`` comes from the maps'
    :class:`CodeGains` (and from a third camera both were fitted into). Counted as independent,
    as until this version, that σ was optimistic (plane, two cameras, 0.1 px codes: RMS z
    1.118, 1.10 of the per-camera maps'; now 1.024; the synthetic small face: 1.156, now
    1.071). The weights stay ``1/σ_i²``, so the positions are unchanged: with correlations of
    0.1–0.25 between estimates of similar σ a generalised (correlation-aware) mean would move
    them little.

    Then the fused cloud is split into clusters (points closer than ``cluster_spacings`` times
    the median distance to the 6th-nearest neighbour are linked) and clusters smaller than
    ``min_cluster_fraction`` of the largest are dropped (reason :data:`OUTLIER`): a patch of
    consistently wrong codes (a flipped coarse Gray bit) floats off the surface, and when no
    other camera sees through it the free-space test cannot catch it. Limitation: a wrong patch
    that lands behind the visible surface, attached to it, and hidden from every other camera
    survives with ``x``-only decodes (with ``y`` the camera–projector residual rejects it).

    Parameters
    ----------
    maps : list of PointMap
        One per camera (modified in place: rejected points get a reason).
    cameras : list of Camera
        The same cameras, in the same order.
    tol_sigmas, tol_floor : float, tol_floor in metres
        Agreement tolerance.
    average : bool
        Average confirmed points with the other camera's.
    cluster_spacings : float, optional
        Link distance of the cluster filter in median 6th-neighbour distances (``None``: no
        filter).
    min_cluster_fraction : float, 0..1
        Smallest cluster kept, as a fraction of the largest.
    drop_gains : bool
        Drop each map's :class:`CodeGains` once the cross-camera test has used them (they serve
        this fusion only; 40 of a camera–camera map's 92 bytes a point, which the mesh stage
        frees before the duplicate and cluster search).

    Returns
    -------
    FusedPoints

    Notes
    -----
    Memory: the maps' points are visited in blocks of :data:`_FUSE_CHUNK` (every step of the
    test is per point); the rejections are applied after all cameras were checked (each
    camera's points are checked against the others' as triangulated); the duplicates and the
    clusters are found without an all-pairs list (:func:`_large_clusters`).
    """
    if len(maps) != len(cameras) or not maps:
        raise InputError(f"maps, cameras: expected one point map per camera (>= 1), got "
                         f"{len(maps)} maps and {len(cameras)} cameras")
    # check against the maps as triangulated: the rejections are applied after the loop, so
    # the points, validity and depths below are those of the maps as given
    luts = [m.lookup() for m in maps]
    depth = [m.depth_at for m in maps]  # NaN without a point
    valid = [m.valid_at for m in maps]
    # the fused points, written block by block into arrays of the valid points' count (no
    # per-block pieces left between the blocks' temporaries: they fragment the heap)
    total = sum(int(np.count_nonzero(v)) for v in valid)
    cat = [np.empty((total, 3)), np.empty(total), np.empty(total, np.float32),
           np.empty(total, np.int32), np.empty((total, 2), np.int32), np.empty(total, bool)]
    n, violated = 0, [[] for _ in maps]
    for a, (ma, ca) in enumerate(zip(maps, cameras)):
        sel_all = np.flatnonzero(valid[a])
        for lo in range(0, sel_all.size, _FUSE_CHUNK):
            sel = sel_all[lo:lo + _FUSE_CHUNK]
            part, bad = _fuse_block(a, sel, maps, cameras, luts, depth, valid, tol_sigmas,
                                    tol_floor, average)
            k = part[0].shape[0]
            for out, v in zip(cat, part):
                out[n:n + k] = v
            n += k
            violated[a].append(bad)
            del part
    del luts, depth, valid
    if drop_gains:
        for m in maps:
            m.code_gains = None
    for m, bad in zip(maps, violated):
        if bad:
            m.reject_at(np.concatenate(bad), OCCLUDED_VIEW)
    del violated
    if n < total:
        cat = [_take_freeing(cat, i, slice(0, n)) for i in range(len(cat))]
    # two cameras' mutually nearest confirmed points average to the same point: keep one
    first = _first_of_each_point(cat[0])
    if first.size < cat[0].shape[0]:
        cat = [_take_freeing(cat, i, first) for i in range(len(cat))]
    if cluster_spacings is not None and len(cat[0]) > 1:
        keep = _large_clusters(cat[0], cluster_spacings, min_cluster_fraction)
        for c in np.unique(cat[3][~keep]):
            sel = ~keep & (cat[3] == c)
            maps[c].reject_at(cat[4][sel, 1].astype(np.int64) * maps[c].shape[1]
                              + cat[4][sel, 0], OUTLIER)
        if not keep.all():
            cat = [_take_freeing(cat, i, keep) for i in range(len(cat))]
    return FusedPoints(cat[0], cat[1], cat[2], cat[3], cat[4], cat[5],
                       [c.name for c in cameras], np.stack([c.center_world for c in cameras]))


def _fuse_block(a, sel, maps, cameras, luts, depth, valid, tol_sigmas, tol_floor, average):
    """:func:`fuse_cameras` for the points at positions ``sel`` of camera ``a``'s map:
    ``((p, σ, confidence, camera, pixel, confirmed) of the points kept, flat pixels of the
    violated ones)``."""
    ma = maps[a]
    W = ma.shape[1]
    flat = ma.index[sel]
    rows, cols = np.divmod(flat, W)
    p = ma.points[sel]
    s = ma.point_sigma[sel]
    num = p / s[:, None] ** 2
    den = 1.0 / s**2
    confirmed = np.zeros(p.shape[0], bool)
    violated = np.zeros(p.shape[0], bool)
    # the averaged estimates: (camera, positions of its pixels, weight) per point of A
    terms = [(a, sel, den.copy())]
    pix = {a: (flat, sel)}  # each camera's (flat pixel, position) at A's points
    for b, (mb, cb) in enumerate(zip(maps, cameras)):
        if b == a:
            continue
        qi, ok = _pixel_of(cb, p)
        fb = qi[:, 1] * mb.shape[1] + qi[:, 0]
        pos = luts[b].reshape(-1)[fb].astype(np.int64)  # −1 where B has no ray there
        pix[b] = (fb, pos)
        D = np.full(p.shape[0], np.nan)
        D[ok] = _median3_at(luts[b], depth[b], fb[ok])
        sb = _take(mb.point_sigma, pos, np.nan)
        sb = np.where(np.isfinite(sb), sb, s)
        d = np.linalg.norm(p - cb.center_world, axis=1)
        tau = tol_sigmas * np.sqrt(s**2 + sb**2) + tol_floor
        with np.errstate(invalid="ignore"):
            violated |= d < D - tau
            agree = np.abs(d - D) <= tau
        have = agree & _take(valid[b], pos, False)
        confirmed |= have
        if average and have.any():
            pb = mb.points[pos[have]]
            wb = 1.0 / sb[have] ** 2
            num[have] += pb * wb[:, None]
            den[have] += wb
            terms.append((b, pos, np.where(have, 1.0 / sb**2, 0.0)))
    keep = ~violated
    pf = num[keep] / den[keep, None]
    # Var of the weighted mean Σ w_i·p_i / Σ w_i: Σ w_i²σ_i² = Σ w_i, plus the covariance of
    # estimates made from the same code maps (camera–camera)
    var_num = den + _shared_code_covariance(terms, pix, maps, cameras)
    sig_f = np.sqrt(np.maximum(var_num, 0.0)) / den
    part = (pf, sig_f[keep], ma.point_confidence[sel][keep],
            np.full(int(keep.sum()), a, np.int32),
            np.stack([cols[keep], rows[keep]], 1).astype(np.int32), confirmed[keep])
    return part, flat[violated]


def _take_freeing(cat: list, i: int, sel) -> np.ndarray:
    """``cat[i][sel]`` (a copy), dropping ``cat[i]`` (one field copied at a time)."""
    a = cat[i][sel].copy() if isinstance(sel, slice) else cat[i][sel]
    cat[i] = None
    return a


def _first_of_each_point(p: np.ndarray) -> np.ndarray:
    """Ascending indices of the first occurrence of each distinct row of ``p`` ``(N, 3)``:
    ``np.unique(p, axis=0, return_index=True)[1]``, sorted, without its ``(N, 3)`` copies
    (a stable lexicographic sort, then the rows that differ from their predecessor)."""
    n = p.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    order = np.lexsort((p[:, 2], p[:, 1], p[:, 0]))  # stable: equal rows keep their order
    new = np.zeros(n, bool)
    new[0] = True
    for j in range(3):
        c = p[order, j]
        new[1:] |= c[1:] != c[:-1]
        del c
    first = order[new]
    first.sort()
    return first


def _shared_code_covariance(terms, pix, maps, cameras) -> np.ndarray:
    """``2·Σ_{i<j} w_i·w_j·Cov(δt_i, δt_j)·(v_i·v_j)`` over the estimates one fused point
    averages (:func:`fuse_cameras`), ``(N,)`` metres² times weight²: the covariance of
    camera–camera points made from the same code maps (:class:`CodeGains`), along their rays
    ``v``. 0 for maps without gains (independent, as camera–projector points are).

    ``terms`` holds per averaged estimate ``(camera index, positions in its map (−1: none),
    weight)`` (``(N,)`` each, weight 0 where that camera's point was not averaged in); ``pix``
    every camera's ``(flat pixels, positions)`` at the points (the third camera's code noise is
    read there)."""
    n = terms[0][2].shape[0]
    total = np.zeros(n)
    names = [m.camera for m in maps]
    zero = np.zeros((n, 2))
    var_code = {c: maps[c].code_gains.sigma_code_at(f) ** 2 for c, (f, _) in pix.items()
                if maps[c].code_gains is not None}
    looked = []
    for c, pos, w in terms:
        g = maps[c].code_gains
        if g is None:
            continue
        v = _take(maps[c].points, pos, np.nan) - cameras[c].center_world
        with np.errstate(invalid="ignore", divide="ignore"):
            v = v / np.linalg.norm(v, axis=-1, keepdims=True)
        looked.append((c, w, v, np.nan_to_num(_take(g.dt_dcode, pos, np.nan)),
                       {k: np.nan_to_num(_take(pg, pos, 0.0))
                        for k, pg in g.partner_dt_dcode.items()},
                       {k: _take(h, pos, np.nan) for k, h in g.partner_weight.items()}))
    for i in range(len(looked)):
        for j in range(i + 1, len(looked)):
            ci, wi, vi, si, pi, hi = looked[i]
            cj, wj, vj, sj, pj, hj = looked[j]
            # i's own code in j's fit, and j's own code in i's fit
            cov = ((si * var_code[ci] * pj.get(names[ci], zero)).sum(-1)
                   + (pi.get(names[cj], zero) * var_code[cj] * sj).sum(-1))
            # both fitted into a third camera m near the same code: its neighbours' noise
            for m, name in enumerate(names):
                if m in (ci, cj) or name not in pi or name not in pj or m not in var_code:
                    continue
                with np.errstate(invalid="ignore", divide="ignore"):
                    t = (pi[name] * var_code[m] * pj[name]).sum(-1) / np.sqrt(hi[name] * hj[name])
                cov += np.where(np.isfinite(t), t, 0.0)
            both = (wi > 0) & (wj > 0)
            term = 2.0 * wi * wj * cov * np.einsum("ij,ij->i", vi, vj)
            total += np.where(both & np.isfinite(term), term, 0.0)
    return total


def neighbour_spacing(points, k: int = 6) -> float:
    """Median distance of a point to its ``k``-th nearest neighbour, metres.

    The sampling scale of a point cloud (≈ 1.5–2 point spacings for ``k = 6`` on a surface),
    used for the link distance of the cluster filter and the mesh's trim / observed radius.
    Every point is queried, in blocks of :data:`_QUERY_CHUNK`.
    """
    from scipy.spatial import cKDTree

    p = as_array(points, "points", shape=(None, 3))
    if len(p) < 2:
        raise InputError(f"points: need at least 2 points for a spacing, got {len(p)}")
    tree = cKDTree(p)
    kk = min(k + 1, len(p))
    d = np.empty(len(p))
    for lo in range(0, len(p), _QUERY_CHUNK):
        d[lo:lo + _QUERY_CHUNK] = tree.query(p[lo:lo + _QUERY_CHUNK], k=kk)[0][:, -1]
    return float(np.median(d))


def _large_clusters(p: np.ndarray, spacings: float, min_fraction: float) -> np.ndarray:
    """Points in clusters (linked within ``spacings`` × the median 6th-neighbour distance) of
    ≥ ``min_fraction`` of the largest cluster's size."""
    lab = _components_within(p, spacings * neighbour_spacing(p))
    counts = np.bincount(lab)
    return counts[lab] >= min_fraction * counts.max()


def _components_within(p: np.ndarray, r: float) -> np.ndarray:
    """Connected components of the points ``(N, 3)`` linked within ``r``: a label per point.

    The components of the graph of all pairs within ``r`` (``cKDTree.query_pairs``), found
    without listing all pairs at once (8 M points on a surface have ≈ 100 M such pairs):
    the points sorted by x are cut into slabs of :data:`_SLAB_POINTS`, each slab widened by
    ``r`` on both sides (every pair within ``r`` lies in the widened slab of its lower point),
    each widened slab's pairs reduced to its components, and every point linked to its
    component's first point; the components of those links over all slabs are the graph's.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(p)
    order = np.argsort(p[:, 0], kind="stable")
    xs = p[order, 0]
    src, dst = [], []
    margin = r * (1.0 + 1e-9) + 1e-12  # widened a hair: rounding never drops a pair
    for lo in range(0, n, _SLAB_POINTS):
        hi = min(n, lo + _SLAB_POINTS)
        a = int(np.searchsorted(xs, xs[lo] - margin, side="left"))
        b = int(np.searchsorted(xs, xs[hi - 1] + margin, side="right"))
        idx = order[a:b]
        pairs = cKDTree(p[idx]).query_pairs(r, output_type="ndarray")
        m = idx.size
        g = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
        del pairs
        _, lab = connected_components(g, directed=False)
        del g
        link = np.unique(lab, return_index=True)[1][lab]  # each point's component's first
        linked = link != np.arange(m)
        src.append(idx[linked])
        dst.append(idx[link[linked]])
    src, dst = np.concatenate(src), np.concatenate(dst)
    g = coo_matrix((np.ones(src.size, np.int8), (src, dst)), shape=(n, n))
    return connected_components(g, directed=False)[1]
