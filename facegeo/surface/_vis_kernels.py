"""Compiled (numba) kernels of :class:`facegeo.surface.visibility.RayScene`.

Private: imported on the first ray query, so ``import facegeo`` does not pay for numba. Each
kernel fuses what the numpy version did in 20–40 array passes into one pass per ray and
releases the GIL (``nogil=True``), so the scene's worker threads run them in parallel with
each other and with Embree's own (GIL-free) traversal. No ``fastmath``: vectorised loops
compute the same IEEE operations in the same order, so every layout's results are identical
bit for bit. ``tests/test_visibility.py`` tests
:func:`prepare_rays` against its numpy formulation directly and the refinement through
:class:`~facegeo.surface.visibility.RayScene` against trimesh's float64 ray–triangle test.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

_F32_MAX = float(np.finfo(np.float32).max)
#: :func:`refine_hits` prefetches the face record (and face index) of the ray this many rays
#: ahead: on 1.3 M faces (a 125 MB table) the record gathers are cache misses, which the
#: prefetch overlaps (8, 16 and 32 measured alike; none ahead was slower).
_PREFETCH_AHEAD = 16


@intrinsic
def _prefetch(typingctx, addr):
    """Hint the CPU to fetch the cache line at byte address ``addr`` (``llvm.prefetch``: read,
    high locality, data cache). A hint only: no effect on results, never faults."""
    sig = types.void(types.intp)

    def codegen(context, builder, signature, args):
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = builder.module.declare_intrinsic("llvm.prefetch", [i8p], fnty)
        builder.call(fn, [builder.inttoptr(args[0], i8p), ir.Constant(i32, 0), ir.Constant(i32, 3),
                          ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return sig, codegen


def prepare_rays(o, D, unit, t_shift, tmax, centre, round_down, org32, d32, d64, far32):
    """Float32 Embree rays from float64 rays, one pass that also validates them.

    Every per-ray input has either ``m`` rows (``m = len(d64)``) or one row shared by all rays
    (a broadcast origin, a scalar ``t_shift``/``tmax``), which the loop reads without copying.
    A Python dispatcher: contiguous rays with scalar ``t_shift`` and ``tmax`` (the usual
    query) go to a compiled loop over flat views that LLVM vectorises (AVX: four rays per
    division and square root; 4–5 ns per ray against 8–9 for the general loop, results
    bit-identical), anything else to the general compiled loop.

    Parameters
    ----------
    o : (m, 3) or (1, 3) float64, metres, mesh frame
        Ray origins.
    D : (m, 3) or (1, 3) float64
        Directions, any non-zero length (normalised here: ``D / sqrt(D·D)``).
    unit : bool
        ``D`` is already unit length: used as it is (the re-casts of rejected rays, whose
        directions this pass normalised before).
    t_shift : (m,) or (1,) float64, metres
        Distance the origin is moved along the unit direction before the query.
    tmax : (m,) or (1,) float64, metres
        Farthest accepted distance from the original origin (inf allowed).
    centre : (3,) float64, metres
        The BVH's centring offset, subtracted from the moved origins.
    round_down : bool
        Round the float32 query distance toward zero (never past ``tmax``: any-hit queries);
        otherwise to nearest (closest-hit queries re-check ``tmax`` in float64).
    org32, d32 : (m, 3) float32, out
        Centred moved origins and unit directions for Embree.
    d64 : (m, 3) float64, out
        Unit directions in float64 (for the refinement).
    far32 : (m,) float32, out
        ``min(tmax - t_shift, float32 max)``.

    Returns
    -------
    bool
        False when an origin is not finite or a direction is not finite or has length zero
        (the outputs are then incomplete; the caller names the first bad ray).
    """
    m = len(d64)
    if (not unit and m > 0 and len(D) == m and len(t_shift) == 1 and len(tmax) == 1
            and (len(o) == 1 or o.flags.c_contiguous) and D.flags.c_contiguous
            and org32.flags.c_contiguous and d32.flags.c_contiguous and d64.flags.c_contiguous):
        # The usual batch (rays with their own directions, scalar t_min / t_max): one query
        # distance for all, and a loop per origin layout on flat views, which LLVM vectorises
        # (the (m, 3) indexing of the general loop does not: 8-9 against 4-5 ns per ray).
        flat = (D.reshape(-1), org32.reshape(-1), d32.reshape(-1), d64.reshape(-1), far32)
        if len(o) == 1:
            return _prep_shared_origin(o, t_shift[0], tmax[0], round_down, centre, *flat)
        return _prep_own_origins(o.reshape(-1), t_shift[0], tmax[0], round_down, centre, *flat)
    return _prep_general(o, D, unit, t_shift, tmax, centre, round_down, org32, d32, d64, far32)


@njit(nogil=True, cache=True, boundscheck=False, error_model="numpy")
def _prep_general(o, D, unit, t_shift, tmax, centre, round_down, org32, d32, d64, far32):
    """:func:`prepare_rays` for any layout (one row per ray or one shared row per input)."""
    m = d64.shape[0]
    o1 = o.shape[0] == 1
    D1 = D.shape[0] == 1
    s1 = t_shift.shape[0] == 1
    t1 = tmax.shape[0] == 1
    ok = True
    for i in range(m):
        io = 0 if o1 else i
        iD = 0 if D1 else i
        x, y, z = D[iD, 0], D[iD, 1], D[iD, 2]
        s = 1.0 if unit else np.sqrt(x * x + y * y + z * z)
        if not (s > 0.0 and np.isfinite(s)):
            ok = False
        ts = t_shift[0 if s1 else i]
        for k in range(3):
            ok_k = np.isfinite(o[io, k])
            if not ok_k:
                ok = False
            dk = D[iD, k] / s
            d64[i, k] = dk
            d32[i, k] = np.float32(dk)
            org32[i, k] = np.float32(o[io, k] + dk * ts - centre[k])
        far32[i] = _far32(tmax[0 if t1 else i] - ts, round_down)
    return ok


@njit(nogil=True, cache=True, boundscheck=False, error_model="numpy", inline="always")
def _far32(f, round_down):
    """Float32 Embree query distance for the float64 distance ``f`` (as :func:`prepare_rays`)."""
    if f >= _F32_MAX:
        return np.float32(_F32_MAX)
    f32 = np.float32(f)
    if round_down and np.float64(f32) > f:
        f32 = np.nextafter(f32, np.float32(0.0))
    return f32


@njit(nogil=True, cache=True, boundscheck=False, error_model="numpy", inline="always")
def _put_ray(i, ox, oy, oz, ts, cx, cy, cz, D, org32, d32, d64):
    """Ray ``i`` of the flat views: unit direction (float64 and float32) and the centred,
    moved float32 origin, as the general loop computes them. Returns whether the direction's
    length is finite and non-zero."""
    x, y, z = D[3 * i], D[3 * i + 1], D[3 * i + 2]
    s = np.sqrt(x * x + y * y + z * z)
    dx, dy, dz = x / s, y / s, z / s
    d64[3 * i] = dx
    d64[3 * i + 1] = dy
    d64[3 * i + 2] = dz
    d32[3 * i] = np.float32(dx)
    d32[3 * i + 1] = np.float32(dy)
    d32[3 * i + 2] = np.float32(dz)
    org32[3 * i] = np.float32(ox + dx * ts - cx)
    org32[3 * i + 1] = np.float32(oy + dy * ts - cy)
    org32[3 * i + 2] = np.float32(oz + dz * ts - cz)
    return (s > 0.0) & (s < np.inf)


@njit(nogil=True, cache=True, boundscheck=False, error_model="numpy")
def _prep_shared_origin(o, ts, tmax, round_down, centre, D, org32, d32, d64, far32):
    """:func:`prepare_rays` for one origin ``o`` (1, 3) shared by all rays and scalar ``ts``
    and ``tmax``; ``D``, ``org32``, ``d32``, ``d64`` are the flat (3m,) views of the (m, 3)
    arrays. The same arithmetic as the general loop (bit-identical results), no branches."""
    far = _far32(tmax - ts, round_down)
    for i in range(far32.shape[0]):
        far32[i] = far
    ox, oy, oz = o[0, 0], o[0, 1], o[0, 2]
    cx, cy, cz = centre[0], centre[1], centre[2]
    bad = 0
    for i in range(d64.shape[0] // 3):
        bad += not _put_ray(i, ox, oy, oz, ts, cx, cy, cz, D, org32, d32, d64)
    return bad == 0 and np.isfinite(ox) and np.isfinite(oy) and np.isfinite(oz)


@njit(nogil=True, cache=True, boundscheck=False, error_model="numpy")
def _prep_own_origins(o, ts, tmax, round_down, centre, D, org32, d32, d64, far32):
    """:func:`prepare_rays` for per-ray origins and scalar ``ts`` and ``tmax``; ``o``, ``D``,
    ``org32``, ``d32``, ``d64`` are the flat (3m,) views of the (m, 3) arrays. The same
    arithmetic as the general loop (bit-identical results), without branches."""
    far = _far32(tmax - ts, round_down)
    for i in range(far32.shape[0]):
        far32[i] = far
    cx, cy, cz = centre[0], centre[1], centre[2]
    bad = 0
    for i in range(d64.shape[0] // 3):
        ox, oy, oz = o[3 * i], o[3 * i + 1], o[3 * i + 2]
        bad += not (_put_ray(i, ox, oy, oz, ts, cx, cy, cz, D, org32, d32, d64)
                    & np.isfinite(ox) & np.isfinite(oy) & np.isfinite(oz))
    return bad == 0


@njit(nogil=True, cache=True, boundscheck=False, error_model="numpy")
def refine_hits(o, d, t_shift, tmin, tmax, prim, tfar, u, v, table, prim_to_face, cop_dist,
                bary_tol, hit, t, face, bary, point, normal, rej_idx, rej_te, rej_cop, rej_n):
    """Float64 refinement of Embree's float32 closest hits (module docstring of
    :mod:`facegeo.surface.visibility`, "Precision"), one pass over the rays.

    Per ray: gather the hit face's record of ``table`` (``v0``, unit normal ``n̂``, ``q1``,
    ``q2``); intersect the float64 ray with the face's plane (``t = (v0 - o)·n̂ / d·n̂``);
    barycentrics ``b1 = (p - v0)·q1``, ``b2 = (p - v0)·q2``; keep Embree's ``t``, ``u``, ``v``
    when the float64 point falls more than ``bary_tol`` outside the face; clip rounding-level
    negative weights; reject hits on a face whose plane passes within ``cop_dist`` of the origin
    and hits before ``tmin`` (the caller re-casts them); accept the rest within ``tmax``.

    ``o``, ``t_shift``, ``tmin`` and ``tmax`` have one row per ray or one row shared by all
    (as :func:`prepare_rays`). ``prim_to_face`` is an empty array when primitive ids are face
    indices. Outputs ``hit``,
    ``t``, ``face``, ``bary``, ``point``, ``normal`` are as :class:`~facegeo.surface.visibility.Hits`
    (NaN / -1 where not accepted); each of ``t`` … ``normal`` is written only when it has the
    rays' length (pass a length-0 array for a field not wanted). Rejected rays are listed
    compactly: ``rej_idx[j]`` the ray, ``rej_te[j]`` Embree's distance from ``o``,
    ``rej_cop[j]`` whether the face's plane contains ``o``, ``rej_n[j]`` the face's unit normal
    (these feed the re-casts). Returns the number of rejected rays.
    """
    m = d.shape[0]
    nan = np.nan
    remap = prim_to_face.shape[0] > 0
    o1 = o.shape[0] == 1
    s1 = t_shift.shape[0] == 1
    n1 = tmin.shape[0] == 1
    x1 = tmax.shape[0] == 1
    w_t = t.shape[0] == m
    w_f = face.shape[0] == m
    w_b = bary.shape[0] == m
    w_p = point.shape[0] == m
    w_n = normal.shape[0] == m
    n_rej = 0
    # Prefetch addresses (hints only: an address past an array's end never faults).
    base, rec = table.ctypes.data, table.strides[0]
    p2f_base, p2f_step = prim_to_face.ctypes.data, prim_to_face.strides[0]
    for i in range(m):
        if i + _PREFETCH_AHEAD < m:
            q = prim[i + _PREFETCH_AHEAD]
            if q >= 0:
                a = base + q * rec
                _prefetch(a)
                _prefetch(a + rec - 1)  # a 96-byte record spans two cache lines
                if remap and w_f:
                    _prefetch(p2f_base + q * p2f_step)
        p = prim[i]
        ok = False
        th = nan
        b0 = b1 = b2 = nan
        nx = ny = nz = nan
        ox = oy = oz = 0.0
        dx = dy = dz = 0.0
        io = 0 if o1 else i
        ts = t_shift[0 if s1 else i]
        tx = tmax[0 if x1 else i]
        if p >= 0 and tx >= ts:
            ox, oy, oz = o[io, 0], o[io, 1], o[io, 2]
            dx, dy, dz = d[i, 0], d[i, 1], d[i, 2]
            nx, ny, nz = table[p, 3], table[p, 4], table[p, 5]
            wx, wy, wz = table[p, 0] - ox, table[p, 1] - oy, table[p, 2] - oz
            num = wx * nx + wy * ny + wz * nz
            den = dx * nx + dy * ny + dz * nz
            te = ts + np.float64(tfar[i])
            th = te
            b1 = np.float64(u[i])
            b2 = np.float64(v[i])
            if den != 0.0:
                tr = num / den
                if np.isfinite(tr):
                    px = tr * dx - wx
                    py = tr * dy - wy
                    pz = tr * dz - wz
                    c1 = px * table[p, 6] + py * table[p, 7] + pz * table[p, 8]
                    c2 = px * table[p, 9] + py * table[p, 10] + pz * table[p, 11]
                    c0 = 1.0 - c1 - c2
                    if c0 >= -bary_tol and c1 >= -bary_tol and c2 >= -bary_tol:
                        th = tr
                        b1 = c1
                        b2 = c2
            b0 = 1.0 - b1 - b2
            if b0 < 0.0 or b1 < 0.0 or b2 < 0.0:
                b0 = max(b0, 0.0)
                b1 = max(b1, 0.0)
                b2 = max(b2, 0.0)
                s = b0 + b1 + b2
                b0 /= s
                b1 /= s
                b2 /= s
            cop = abs(num) <= cop_dist
            if cop or not (th >= tmin[0 if n1 else i]):
                rej_idx[n_rej] = i
                rej_te[n_rej] = te
                rej_cop[n_rej] = cop
                rej_n[n_rej, 0] = nx
                rej_n[n_rej, 1] = ny
                rej_n[n_rej, 2] = nz
                n_rej += 1
            else:
                ok = th <= tx
        hit[i] = ok
        if ok:
            if w_t:
                t[i] = th
            if w_f:
                face[i] = prim_to_face[p] if remap else p
            if w_b:
                bary[i, 0] = b0
                bary[i, 1] = b1
                bary[i, 2] = b2
            if w_p:
                point[i, 0] = ox + th * dx
                point[i, 1] = oy + th * dy
                point[i, 2] = oz + th * dz
            if w_n:
                normal[i, 0] = nx
                normal[i, 1] = ny
                normal[i, 2] = nz
        else:
            if w_t:
                t[i] = nan
            if w_f:
                face[i] = -1
            for k in range(3):
                if w_b:
                    bary[i, k] = nan
                if w_p:
                    point[i, k] = nan
                if w_n:
                    normal[i, k] = nan
    return n_rej


@njit(nogil=True, cache=True, boundscheck=False)
def rays_ok(o, D):
    """Whether every origin of ``o`` (n, 3) is finite and every direction of ``D`` (n, 3) is
    finite with a non-zero length, as :func:`prepare_rays` checks (one pass, no outputs)."""
    for i in range(o.shape[0]):
        x, y, z = D[i, 0], D[i, 1], D[i, 2]
        s = np.sqrt(x * x + y * y + z * z)
        if not (s > 0.0 and np.isfinite(s)):
            return False
        for k in range(3):
            if not np.isfinite(o[i, k]):
                return False
    return True
