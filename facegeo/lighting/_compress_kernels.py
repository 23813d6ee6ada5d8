"""numba kernels of :class:`facegeo.lighting.compress.ImageWaveletField` (imported only when
numba is installed; the numpy fallbacks in :mod:`facegeo.lighting._compress_image` are the plain
reference implementations they are tested against).

The relight's hot loop is :func:`scatter_add_rgbx`: one 4-lane vector read-modify-write per
stored entry into an interleaved ``(S, 4)`` float32 accumulator (R, G, B and a zero lane; S
coefficient rows in the block layout of ``_compress_image.coefficient_rows``), the entry's
three 9-bit mantissas decoded in the same 4 lanes by one variable shift (LLVM vector IR through
a numba intrinsic: numba's scalar code for the same loop decodes and stores channel by channel).
The inverse spatial transform (:func:`inverse_haar_at_pixels`) then evaluates each coarse level
in one pass of 4-lane vectors and the finest level at the field's pixels alone, so the padded
grid's empty cells cost nothing there.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from facegeo.lighting._fused import _FASTMATH, haar_nonstandard_forward

__all__ = ["entries_below", "inverse_haar_at_pixels", "relight_one_thread", "scatter_add_rgbx",
           "top_k_index_order", "truncation_errors_rgbx"]


_F4 = ir.VectorType(ir.FloatType(), 4)
_I32 = ir.IntType(32)


def _f4_rows(context, builder, signature, args, k):
    """Codegen helper: argument ``k`` (a C-contiguous ``(n, 4)`` float32 array) as a pointer to
    4-lane float vectors."""
    arr = context.make_array(signature.args[k])(context, builder, args[k])
    return builder.bitcast(arr.data, _F4.as_pointer())


def _f4_load(builder, base, i):
    """Codegen helper: the 4-lane row ``i`` of ``base`` (alignment of a float only)."""
    return builder.load(builder.gep(base, [i]), align=4)


def _splat(builder, x, vec_type):
    """Codegen helper: scalar ``x`` in every lane of ``vec_type``."""
    v = builder.insert_element(ir.Constant(vec_type, ir.Undefined), x, ir.Constant(_I32, 0))
    return builder.shuffle_vector(v, ir.Constant(vec_type, ir.Undefined),
                                  ir.Constant(ir.VectorType(_I32, 4), [0] * 4))


@intrinsic
def _axpy_rgbx(typingctx, acc, q, tab, t, code):  # pragma: no cover - compiled
    """``acc[q, :] += mantissas(code) · tab[t, :]`` as 4-lane vector operations.

    ``acc`` and ``tab`` are C-contiguous ``(n, 4)`` float32; the code's 9-bit fields 0, 1, 2
    (lane 3 repeats field 2; ``tab[t, 3]`` is 0) go to the top of each lane by one variable
    left shift and are sign-extended by an arithmetic right shift (see ``encode_rgb``).
    """
    sig = types.void(acc, types.int64, tab, types.int64, types.uint32)

    def codegen(context, builder, signature, args):
        q_v, t_v, code_v = args[1], args[3], args[4]
        i4 = ir.VectorType(_I32, 4)
        pa = builder.gep(_f4_rows(context, builder, signature, args, 0), [q_v])
        c = _splat(builder, code_v, i4)
        m = builder.ashr(builder.shl(c, ir.Constant(i4, [23, 14, 5, 5])),
                         ir.Constant(i4, [23] * 4))
        x = builder.fmul(builder.sitofp(m, _F4),
                         _f4_load(builder, _f4_rows(context, builder, signature, args, 2), t_v))
        builder.store(builder.fadd(builder.load(pa, align=4), x), pa, align=4)
        return context.get_dummy_value()

    return sig, codegen


@njit(nogil=True, cache=True, boundscheck=False, fastmath=_FASTMATH)
def scatter_add_rgbx(ptr, n_seg, pos, code, pw, idx, lw, acc, tab, c0,
                     c1):  # pragma: no cover - compiled
    """``acc[65536·g + pos[e], :3] += value(code[e]) · lw[k]`` over the entries ``e`` of each
    selected slab ``j = idx[k]`` at coefficient rows ``c0 ≤ s < c1`` (the sum of
    ``_compress_image._scatter``, interleaved), **added** to ``acc`` ``(S, 4)`` float32 (lane 3
    stays as it is: zero in a zeroed accumulator).

    ``ptr`` ``(L·n_seg + 1,)`` int64 bounds slab j's entries of segment g (rows ``65536·g …``)
    as ``ptr[j·n_seg + g] : ptr[j·n_seg + g + 1]``, ``pos`` ``(n,)`` uint16 and ``code`` ``(n,)``
    uint32 are the entries (rows sorted within a slab's segment; codes of ``encode_rgb``), ``pw``
    ``(32,)`` float32 the exponent table, ``idx`` ``(K,)`` int64, ``lw`` ``(K, 3)`` float32 the
    lighting coefficients. ``tab`` ``(32, 4)`` float32 scratch (lane 3 zero): the current slab's
    ``pw[e] · lw[k]`` per exponent e (float32 products, rebuilt for each slab's run: 512 bytes
    in L1), which replaces the exponent lookup and three multiplies per entry by one vector
    load. Entries are read through slices (loop index from 0), which lets LLVM drop numba's
    negative-index wraparound (measured ≈ 25 % of the loop).

    Segment-major, each slab's run whole (no tiles: measured 1.3 against 1.5–1.8 ns an entry for
    16,384-cell tiles on the 256 × 256 face grid, and no binary searches; software prefetches
    of the next run's start or of the accumulator rows 8–64 entries ahead measured no gain).
    Positions are sorted within a run, so a range ``c0 … c1`` (threads take disjoint ranges of
    one accumulator) costs one binary search at each end that cuts a segment. The additions
    into each row are in slab order, as the tiled kernel this replaces: the same sums bit for
    bit.
    """
    n_k = idx.size
    g0 = np.int64(c0) >> 16
    g1 = (np.int64(c1) + 65535) >> 16
    for g in range(g0, g1):
        off = np.int64(g) << 16
        lo = max(np.int64(c0) - off, 0)
        hi = min(np.int64(c1) - off, 65536)
        for k in range(n_k):
            for e in range(32):
                for c in range(3):
                    tab[e, c] = pw[e] * lw[k, c]
            r = idx[k] * n_seg + g
            a = ptr[r]
            b = ptr[r + 1]
            if lo > 0:
                a = a + np.searchsorted(pos[a:b], lo)
            if hi < 65536:
                b = a + np.searchsorted(pos[a:b], hi)
            pc = code[a:b]
            pp = pos[a:b]
            for i in range(pc.size):
                v = pc[i]
                _axpy_rgbx(acc, off + np.int64(pp[i]), tab, np.int64(v >> np.uint32(27)), v)


@njit(nogil=True, cache=True, boundscheck=False)
def entries_below(ptr, n_seg, pos, idx, cells):  # pragma: no cover - compiled
    """Entries of the slabs ``idx`` at coefficient rows ``< cells[i]`` for each ``i`` (``(n,)``
    int64, one binary search per slab and row): where to split a scatter into equal parts."""
    out = np.zeros(cells.size, np.int64)
    for i in range(cells.size):
        cell = cells[i]
        for k in range(idx.size):
            for g in range(n_seg):
                a = ptr[idx[k] * n_seg + g]
                b = ptr[idx[k] * n_seg + g + 1]
                if cell >= (g + 1) << 16:
                    out[i] += b - a
                elif cell > g << 16:
                    out[i] += np.searchsorted(pos[a:b], cell - (g << 16))
    return out


def _haar_pixel_intrinsic(lanes: int):
    """An intrinsic ``(ll, lb, det, db, dy, dx, sy, sx, scale, out, ob)``: one pixel of an
    inverse non-standard Haar level from 4-lane rows of ``(N, 4)`` float32 arrays,
    ``out[ob] = ((ll[lb] + sy·det[db+dy]) + sx·(det[db+dx] + sy·det[db+dy+dx]))·scale``;
    ``lanes`` = 4 stores the whole vector into ``out`` ``(M, 4)``, 3 stores R, G, B into
    ``out`` ``(M, 3)``."""

    @intrinsic
    def px(typingctx, ll, lb, det, db, dy, dx, sy, sx, scale, out, ob):  # pragma: no cover
        i64 = types.int64
        sig = types.void(ll, i64, det, i64, i64, i64, types.float32, types.float32,
                         types.float32, out, i64)

        def codegen(context, builder, signature, args):
            lb_v, db_v, dy_v, dx_v, sy_v, sx_v, sc_v, out_v, ob_v = args[1], *args[3:]
            det = _f4_rows(context, builder, signature, args, 2)
            sy = _splat(builder, sy_v, _F4)
            d_dy = builder.add(db_v, dy_v)
            v = builder.fadd(_f4_load(builder, _f4_rows(context, builder, signature, args, 0),
                                      lb_v),
                             builder.fmul(sy, _f4_load(builder, det, d_dy)))
            u = builder.fadd(_f4_load(builder, det, builder.add(db_v, dx_v)),
                             builder.fmul(sy, _f4_load(builder, det, builder.add(d_dy, dx_v))))
            r = builder.fmul(builder.fadd(v, builder.fmul(_splat(builder, sx_v, _F4), u)),
                             _splat(builder, sc_v, _F4))
            if lanes == 4:
                builder.store(r, builder.gep(_f4_rows(context, builder, signature, args, 9),
                                             [ob_v]), align=4)
            else:
                o = context.make_array(signature.args[9])(context, builder, out_v)
                po = builder.gep(o.data, [builder.mul(ob_v, ir.Constant(ir.IntType(64), 3))])
                for c in range(3):
                    builder.store(builder.extract_element(r, ir.Constant(_I32, c)),
                                  builder.gep(po, [ir.Constant(ir.IntType(64), c)]), align=4)
            return context.get_dummy_value()

        return sig, codegen

    return px


_haar_pixel_rgbx = _haar_pixel_intrinsic(4)
_haar_pixel_rgb = _haar_pixel_intrinsic(3)


def _haar_block_intrinsic(clear: bool):
    """An intrinsic ``(ll, lb, det, db, dy, dx, scale, out, ob, stride)``: the 2 × 2 cells
    ``out[ob], out[ob+1], out[ob+stride], out[ob+stride+1]`` of a level stepped on both axes
    from one low-pass row and three detail rows (as :func:`_haar_pixel_intrinsic` with
    s_y, s_x = ±1, four cells per set of loads): ``(LL ± D_y) ± (D_x ± D_xy)``, times
    ``scale``. ``clear``: the three detail rows are zeroed once read (each is read once per
    inverse, so an accumulator is left zeroed for the next relight at no extra pass)."""

    @intrinsic
    def block(typingctx, ll, lb, det, db, dy, dx, scale, out, ob,
              stride):  # pragma: no cover - compiled
        i64 = types.int64
        sig = types.void(ll, i64, det, i64, i64, i64, types.float32, out, i64, i64)

        def codegen(context, builder, signature, args):
            _, lb_v, _, db_v, dy_v, dx_v, sc_v, _, ob_v, st_v = args
            det = _f4_rows(context, builder, signature, args, 2)
            sc = _splat(builder, sc_v, _F4)
            a = _f4_load(builder, _f4_rows(context, builder, signature, args, 0), lb_v)
            d_dy = builder.add(db_v, dy_v)
            p_y, p_x = builder.gep(det, [d_dy]), builder.gep(det, [builder.add(db_v, dx_v)])
            p_xy = builder.gep(det, [builder.add(d_dy, dx_v)])
            d_y, d_x, d_xy = (builder.load(p, align=4) for p in (p_y, p_x, p_xy))
            if clear:
                for p in (p_y, p_x, p_xy):
                    builder.store(ir.Constant(_F4, [0.0] * 4), p, align=4)
            p, m = builder.fadd(a, d_y), builder.fsub(a, d_y)
            q, n = builder.fadd(d_x, d_xy), builder.fsub(d_x, d_xy)
            out = _f4_rows(context, builder, signature, args, 7)
            one = ir.Constant(ir.IntType(64), 1)
            o1 = builder.add(ob_v, st_v)
            for idx, val in ((ob_v, builder.fadd(p, q)),
                             (builder.add(ob_v, one), builder.fsub(p, q)),
                             (o1, builder.fadd(m, n)), (builder.add(o1, one), builder.fsub(m, n))):
                builder.store(builder.fmul(val, sc), builder.gep(out, [idx]), align=4)
            return context.get_dummy_value()

        return sig, codegen

    return block


_haar_block_rgbx = _haar_block_intrinsic(False)
_haar_block_rgbx_clear = _haar_block_intrinsic(True)


@njit(inline="always", cache=True)
def _level_constants(h, w, step_theta, step_phi):  # pragma: no cover - compiled
    """``(hy, hx, dy_rows, dx, scale)`` of a level: halving shifts, detail offsets (rows, columns;
    0 on an axis not stepped) and the factor √½ per stepped axis."""
    hy = 1 if step_phi else 0
    hx = 1 if step_theta else 0
    scale = np.float32(1.0)
    if step_phi:
        scale *= np.float32(np.sqrt(0.5))
    if step_theta:
        scale *= np.float32(np.sqrt(0.5))
    return hy, hx, (h // 2) * hy, (w // 2) * hx, scale


@njit(inline="always", cache=True)
def _clear_rows(det, n_w, y0, y1, x0, x1):  # pragma: no cover - compiled
    """Zero cells ``[y0, y1) × [x0, x1)`` of ``det`` ``(H·W, 4)`` (row stride ``n_w``)."""
    for y in range(y0, y1):
        det[y * n_w + x0:y * n_w + x1] = 0.0


@njit(nogil=True, cache=True, boundscheck=False, fastmath=_FASTMATH)
def inverse_haar_at_pixels(det, n_h, n_w, blocked, levels, pixel_pos, order, out, blocks,
                           block_px, ll, clear):  # pragma: no cover - compiled
    """Inverse non-standard 2-D Haar of the ``n_h × n_w`` grid's coefficients ``det`` ``(S, 4)``
    float32 (RGB + a zero lane), evaluated at the pixels: ``out`` ``(P, 3)`` float32 gets the
    grid cells ``pixel_pos`` ``(P,)`` (``y·W + x``), visited in ``order`` (increasing grid
    index). ``levels`` ``(n, 4)`` rows ``(h, w, step θ, step φ)``, finest first, from
    ``_compress_haar._nonstandard_levels(W, H)`` (the width playing θ).

    Layout of ``det``: ``blocked`` false, the grid row-major (S = H·W); ``blocked`` true (the
    finest level steps both axes), the **block layout** of ``_compress_image.coefficient_rows``:
    rows ``[0, H·W/4)`` the finest level's low-pass quadrant row-major (stride W/2), then three
    rows ``D_y, D_x, D_xy`` per 2 × 2 block of ``blocks`` in that order, so the finest level
    reads its coefficients in one forward sweep and padding blocks take no rows.

    Every level at once per output cell: cell (y, x) of a level of size (h, w) is
    ``(LL[j, i] + s_y D[h/2 + j, i] + s_x (D[j, w/2 + i] + s_y D[h/2 + j, w/2 + i]))·√½^steps``
    with j = y/2, i = x/2 (integer; y, x on an axis not stepped), s = ±1 for even/odd (0 on an
    axis not stepped), D the level's detail coefficients and LL the coarser levels' result.
    The coarse levels write their cells into one low-pass buffer of the finest level's LL size,
    visited backwards so each cell is read before it is overwritten (an output cell is never
    before its input in that order); the finest level is evaluated at the pixels only, so
    padding cells cost nothing there. RGB as one 4-lane vector.

    ``blocks`` ``(n,)`` int64 and ``block_px`` ``(n, 4)`` int32 (may be empty in the grid
    layout): when the finest level steps both axes, its 2 × 2 blocks holding pixels (block
    index ``(y/2)·(W/2) + x/2``, increasing) and the pixel of each cell (slot ``2·(y mod 2) + x
    mod 2``, −1 for none); the finest level is then evaluated a block at a time (one set of
    loads per four cells, measured ≈ 2× fewer cycles than per pixel on a face).

    ``ll`` ``(M, 4)`` float32: scratch for the low-pass buffer (a new one when M is below the
    finest level's LL size). ``clear``: ``det`` is an accumulator to leave zeroed for the next
    relight — each coefficient is zeroed as it is read (the block layout's rows are all read;
    in the grid layout the finest level's cells outside ``blocks`` must already be zero).
    Otherwise ``det`` is read only.
    """
    if levels.shape[0] == 0:  # a 1 × 1 grid
        for q in range(order.size):
            p = order[q]
            for c in range(3):
                out[p, c] = det[pixel_pos[p], c]
        if clear:
            det[0] = 0.0
        return
    hy0, hx0, _, _, _ = _level_constants(n_h, n_w, levels[0, 2], levels[0, 3])
    bw = n_w >> hx0  # the low-pass buffer: (H, W) of level 1, stride bw
    cs = bw if blocked else n_w  # row stride of the coarse levels' coefficients
    if ll.shape[0] < (n_h >> hy0) * bw:
        ll = np.empty(((n_h >> hy0) * bw, 4), np.float32)
    for c in range(4):
        ll[0, c] = det[0, c]
    if clear:
        det[0] = 0.0
    for lev in range(levels.shape[0] - 1, 0, -1):
        h = levels[lev, 0]
        w = levels[lev, 1]
        hy, hx, dy, dx, scale = _level_constants(h, w, levels[lev, 2], levels[lev, 3])
        if hy and hx:  # both axes: 2 × 2 cells per low-pass cell, blocks visited backwards
            for j in range(h // 2 - 1, -1, -1):
                for i in range(w // 2 - 1, -1, -1):
                    if clear:
                        _haar_block_rgbx_clear(ll, j * bw + i, det, j * cs + i, dy * cs, dx,
                                               scale, ll, 2 * j * bw + 2 * i, bw)
                    else:
                        _haar_block_rgbx(ll, j * bw + i, det, j * cs + i, dy * cs, dx, scale,
                                         ll, 2 * j * bw + 2 * i, bw)
            continue
        for y in range(h - 1, -1, -1):
            sy = np.float32(1 - 2 * (y & 1)) if hy else np.float32(0.0)
            j = y >> hy
            for x in range(w - 1, -1, -1):
                sx = np.float32(1 - 2 * (x & 1)) if hx else np.float32(0.0)
                i = x >> hx
                _haar_pixel_rgbx(ll, j * bw + i, det, j * cs + i, dy * cs, dx, sy, sx,
                                 scale, ll, y * bw + x)
        if clear:  # one axis: this level's detail cells (read by several cells) after it
            _clear_rows(det, cs, h >> hy if hy else 0, h, w >> hx if hx else 0, w)
    shift = 0
    while (1 << shift) < n_w:  # W is a power of two: y = index >> log₂ W (no 64-bit division)
        shift += 1
    hy, hx, dy, dx, scale = _level_constants(n_h, n_w, levels[0, 2], levels[0, 3])
    if hy and hx and (blocked or blocks.size):
        blk = np.empty((4, 4), np.float32)
        half = n_w // 2
        base = (n_h // 2) * half - 1  # block layout: block bi's rows base + 3·bi + 1, 2, 3
        for bi in range(blocks.size):
            j = blocks[bi] >> (shift - 1)
            i = blocks[bi] & (half - 1)
            db, ddy, ddx = j * n_w + i, dy * n_w, dx
            if blocked:
                db, ddy, ddx = base + 3 * bi, 1, 2
            if clear:
                _haar_block_rgbx_clear(ll, j * bw + i, det, db, ddy, ddx, scale, blk, 0, 2)
            else:
                _haar_block_rgbx(ll, j * bw + i, det, db, ddy, ddx, scale, blk, 0, 2)
            for slot in range(4):
                p = block_px[bi, slot]
                if p >= 0:
                    for c in range(3):
                        out[p, c] = blk[slot, c]
        return
    for q in range(order.size):
        p = order[q]
        y = np.int64(pixel_pos[p]) >> shift
        x = np.int64(pixel_pos[p]) & (n_w - 1)
        sy = np.float32(1 - 2 * (y & 1)) if hy else np.float32(0.0)
        sx = np.float32(1 - 2 * (x & 1)) if hx else np.float32(0.0)
        j = y >> hy
        i = x >> hx
        _haar_pixel_rgb(ll, j * bw + i, det, j * n_w + i, dy * n_w, dx, sy, sx, scale, out, p)
    if clear:  # the finest level's detail cells (the low-pass quadrant is already zero)
        _clear_rows(det, n_w, 0, n_h, 0, n_w)


@njit(nogil=True, cache=True)
def top_k_index_order(wc, k):  # pragma: no cover - compiled
    """Indices of the ``k`` largest ``Σ_c |wc[l, c]|`` (ties to the lower index), increasing:
    the set of ``_compress_haar.top_terms``. ``wc`` ``(L, 3)`` float64; returns ``(k,)`` int64."""
    n = wc.shape[0]
    mag = np.empty(n)
    for j in range(n):
        mag[j] = abs(wc[j, 0]) + abs(wc[j, 1]) + abs(wc[j, 2])
    out = np.empty(min(k, n), np.int64)
    if k >= n:
        for j in range(n):
            out[j] = j
        return out
    kth = np.partition(mag, n - k)[n - k]  # the k-th largest magnitude
    above = 0
    for j in range(n):
        if mag[j] > kth:
            above += 1
    ties = k - above  # tied at the k-th magnitude: the lowest indices
    c = 0
    for j in range(n):
        if mag[j] > kth or (mag[j] == kth and ties > 0):
            if mag[j] == kth:
                ties -= 1
            out[c] = j
            c += 1
    return out


@njit(inline="always", cache=True)
def _channel(code, c):  # pragma: no cover - compiled
    """Channel ``c`` of a packed entry (see ``_compress_image.encode_rgb``): its 9-bit two's
    complement field moved to the top and sign-extended by an arithmetic shift (branch-free:
    a branch on the sign mispredicts half the time, measured 8 ns an entry against ≈ 2)."""
    return np.float32(np.int32(code << np.uint32(23 - 9 * c)) >> np.int32(23))


@njit(nogil=True, cache=True, boundscheck=False)
def truncation_errors_rgbx(ptr, n_seg, pos, code, pw, idx, lw,
                           full):  # pragma: no cover - compiled
    """Squared error ``‖full − Σ_{k' ≤ k} slab idx[k']‖²`` after each slab ``k`` of ``idx``
    (the twin of ``_compress_image._truncation_errors``).

    Entries and weights as :func:`scatter_add_rgbx`; ``full`` ``(S, 4)`` float32 is its sum over
    all of ``idx``. The residual (float64, interleaved: one cache line per entry) is updated in
    place entry by entry, so the error of every prefix costs one pass over the entries; the
    entries are read through slices (no index wraparound). Returns ``(K,)`` float64."""
    n = full.shape[0]
    d = np.empty((n, 4))
    e2 = 0.0
    for s in range(n):
        for c in range(4):
            d[s, c] = full[s, c]
            e2 += d[s, c] * d[s, c]
    out = np.empty(idx.size)
    for k in range(idx.size):
        j = idx[k]
        x0 = lw[k, 0]
        x1 = lw[k, 1]
        x2 = lw[k, 2]
        for g in range(n_seg):
            off = np.int64(g) << 16
            pc = code[ptr[j * n_seg + g]:ptr[j * n_seg + g + 1]]
            pp = pos[ptr[j * n_seg + g]:ptr[j * n_seg + g + 1]]
            for i in range(pc.size):
                v = pc[i]
                s = off + np.int64(pp[i])
                p = pw[v >> np.uint32(27)]
                o0 = d[s, 0]
                o1 = d[s, 1]
                o2 = d[s, 2]
                n0 = o0 - np.float64(_channel(v, 0) * (p * x0))
                n1 = o1 - np.float64(_channel(v, 1) * (p * x1))
                n2 = o2 - np.float64(_channel(v, 2) * (p * x2))
                e2 += (n0 * n0 + n1 * n1 + n2 * n2) - (o0 * o0 + o1 * o1 + o2 * o2)
                d[s, 0] = n0
                d[s, 1] = n1
                d[s, 2] = n2
        out[k] = max(e2, 0.0)
    return out


@njit(nogil=True, cache=True)
def relight_one_thread(weights, light_levels, n_theta, n_phi, k, ptr, n_seg, pos, code, pw,
                       acc, grid_h, grid_w, blocked, levels, pixel_pos, order, blocks, block_px,
                       ll, tab, clear, out, scale):  # pragma: no cover - compiled
    """A whole one-thread relight in one compiled call (the Python-level steps between the
    kernels cost ≈ 0.5 ms with cold caches): the lighting's non-standard light Haar
    coefficients, the ``k`` largest (``k`` = 0: every non-zero one, at least one) in index
    order, :func:`scatter_add_rgbx` over all coefficient rows into ``acc`` ``(S, 4)`` (zero on
    entry; the ``grid_h × grid_w`` grid in the layout ``blocked``) and
    :func:`inverse_haar_at_pixels` into ``out`` ``(P, 3)`` (``clear``: ``acc`` left zeroed). ``weights`` ``(L, 3)`` float64 (validated),
    ``light_levels`` the light grid's levels, ``ll`` and ``tab`` scratch; the rest as those
    kernels. The same operations as the Python-level path, so the same result bit for bit.
    Returns False, having done nothing, when ``weights`` holds a NaN or infinity (else True).

    ``scale`` ``(L·n,)`` float64: the model stores each light coefficient's slab as ``n`` pieces
    (``n`` = ``scale.size // L``; piece ``p`` of slab ``p // n``); the terms are pieces, the
    ``k`` largest ``Σ_c |wc[p // n, c]| · scale[p]``, each weighted by its slab's coefficient.
    One piece per slab and ``scale`` all ones: the K largest coefficients, as before."""
    for j in range(weights.shape[0]):
        for c in range(3):
            if not np.isfinite(weights[j, c]):
                return False
    img = np.empty((3, n_phi, n_theta))
    for c in range(3):
        for j in range(n_phi):
            for i in range(n_theta):
                img[c, j, i] = weights[j * n_theta + i, c]
    if light_levels.shape[0]:
        haar_nonstandard_forward(img, light_levels)
    n_l = n_theta * n_phi
    wc = np.empty((n_l, 3))
    nonzero = 0
    for j in range(n_phi):
        for i in range(n_theta):
            for c in range(3):
                wc[j * n_theta + i, c] = img[c, j, i]
            if wc[j * n_theta + i, 0] != 0 or wc[j * n_theta + i, 1] != 0 or \
                    wc[j * n_theta + i, 2] != 0:
                nonzero += 1
    n_pc = scale.size // n_l
    if n_pc == 1:
        if k == 0:
            k = max(1, nonzero)
        idx = top_k_index_order(wc, k)
    else:
        ws = np.zeros((scale.size, 3))
        nonzero = 0
        for q in range(scale.size):
            ws[q, 0] = (abs(wc[q // n_pc, 0]) + abs(wc[q // n_pc, 1]) + abs(wc[q // n_pc, 2])) \
                * scale[q]
            if ws[q, 0] != 0:
                nonzero += 1
        if k == 0:
            k = max(1, nonzero)
        idx = top_k_index_order(ws, k)
    lw = np.empty((idx.size, 3), np.float32)
    for q in range(idx.size):
        for c in range(3):
            lw[q, c] = np.float32(wc[idx[q] // n_pc, c])
    scatter_add_rgbx(ptr, n_seg, pos, code, pw, idx, lw, acc, tab, 0, acc.shape[0])
    inverse_haar_at_pixels(acc, grid_h, grid_w, blocked, levels, pixel_pos, order, out, blocks,
                           block_px, ll, clear)
    return True
