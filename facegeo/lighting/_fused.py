"""The fused float16 relighting kernels (numba): Eq. (4) of Debevec et al. 2000 on float16 rows,
each half widened to float32 in registers and multiplied into three channel accumulators in
the same pass. Private to :mod:`facegeo.lighting.relight` (imported only when numba is
installed); see :func:`facegeo.lighting.relight.relight_field` and ``docs/lighting.md``.

:func:`fused_half_dot` reads three per-channel weight vectors and runs with either conversion;
:func:`fused_half_dot_f16c` (F16C only) gives the same sums in the same order from one
channel-interleaved weight vector that stays in L1, its inner loop written as LLVM IR
(:func:`_make_rows_dot`): the relight at the memory's rate.

The half → float conversion is :func:`facegeo.surface._half.half_to_float32` (shared with the
skin fit's streaming; one copy), inlined into these loops. It has two exact versions, chosen
per call by the ``f16c`` flag (a loop-invariant branch that LLVM moves out of the loops, so each
version vectorises on its own; where numba compiles for a CPU without F16C only the portable one
is compiled, see that module):

* ``f16c=True``: an LLVM ``fpext half → float``, which the vectoriser turns into the CPU's
  ``vcvtph2ps`` (8 halves per instruction); only on CPUs with F16C.
* ``f16c=False``: a branch-free bit manipulation for any CPU (sign, exponent and mantissa moved
  into float32 position, then × 2^112).

Both are exact for normals, subnormals, ±0, ±inf and NaN. ``fastmath`` allows reassociation
and FMA contraction only (vectorised sums), never nnan/ninf, so NaN/inf samples propagate as
IEEE arithmetic says. Compiled once and cached on disk (numba keys the cache by CPU; it does not
see edits to ``surface/_half.py``, so clear this module's ``__pycache__`` after changing that).
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from facegeo.errors import ShapeError
from facegeo.surface._half import half_to_float32 as _half

__all__ = ["INTERLEAVED_ROWS", "fused_half_dot", "fused_half_dot_f16c"]

_FASTMATH = {"reassoc", "contract"}


@njit(nogil=True, cache=True, boundscheck=False, fastmath=_FASTMATH)
def fused_half_dot(h, w0, w1, w2, out, f16c):  # pragma: no cover - compiled
    """``out[p, c] = Σ_j half(h[p, j]) · w_c[j]`` for the rows of ``h``.

    Parameters
    ----------
    h : (n, m) uint16
        Bits of float16 field rows (``m = 3L'``, channel-interleaved as stored).
    w0, w1, w2 : (m,) float32
        Channel c's Eq. (4) weights on the columns of channel c, zero elsewhere (the columns of
        the block weight matrix).
    out : (n, 3) float32
    f16c : bool
        Use the CPU's F16C conversion (the caller checks the CPU has it).

    Three rows are accumulated together (blocking over texels): each weight load, from L1/L2
    (12 bytes per half, 72 KB for 2048 lights), serves three rows' halves; 3 rows × 3 channels
    = 9 vector accumulators fit AVX2's 16 registers (4 rows spill).
    """
    n, m = h.shape
    p = 0
    while p + 2 < n:
        a0 = np.float32(0)
        a1 = np.float32(0)
        a2 = np.float32(0)
        b0 = np.float32(0)
        b1 = np.float32(0)
        b2 = np.float32(0)
        c0 = np.float32(0)
        c1 = np.float32(0)
        c2 = np.float32(0)
        for j in range(m):
            x0 = w0[j]
            x1 = w1[j]
            x2 = w2[j]
            u = _half(h[p, j], f16c)
            v = _half(h[p + 1, j], f16c)
            t = _half(h[p + 2, j], f16c)
            a0 += u * x0
            a1 += u * x1
            a2 += u * x2
            b0 += v * x0
            b1 += v * x1
            b2 += v * x2
            c0 += t * x0
            c1 += t * x1
            c2 += t * x2
        out[p, 0] = a0
        out[p, 1] = a1
        out[p, 2] = a2
        out[p + 1, 0] = b0
        out[p + 1, 1] = b1
        out[p + 1, 2] = b2
        out[p + 2, 0] = c0
        out[p + 2, 1] = c1
        out[p + 2, 2] = c2
        p += 3
    while p < n:
        s0 = np.float32(0)
        s1 = np.float32(0)
        s2 = np.float32(0)
        for j in range(m):
            v = _half(h[p, j], f16c)
            s0 += v * w0[j]
            s1 += v * w1[j]
            s2 += v * w2[j]
        out[p, 0] = s0
        out[p, 1] = s1
        out[p, 2] = s2
        p += 1


#: Rows accumulated together by :func:`fused_half_dot_f16c` (4 rows × 3 phase accumulators = 12
#: ymm registers). Measured out of cache, one thread, 1 GB field, interleaved: 3 rows 17.2–18.9
#: GB/s, **4 rows 18.9–20.9**, 5 rows 18.3, 6 rows 18.2–19.5, 8 rows 18.3 (a pure 4-row read of
#: the same bytes 21.1; the three-weight-vector kernel 13.7–16.6).
INTERLEAVED_ROWS = 4

_F32 = ir.FloatType()
_I8, _I16, _I32, _I64 = (ir.IntType(b) for b in (8, 16, 32, 64))
_V8F = ir.VectorType(_F32, 8)
_V8I16 = ir.VectorType(_I16, 8)
_V8H = ir.VectorType(ir.HalfType(), 8)

#: ``_PHASE[c][k]``: which of the three phase accumulators holds, in lane k, channel c's columns
#: (``(8 r + k) mod 3 == c`` for the accumulator r fed at columns ``j ≡ 8 r (mod 24)``).
_PHASE = tuple(tuple(next(r for r in range(3) if (8 * r + k) % 3 == c) for k in range(8))
               for c in range(3))


def _rows_dot_codegen(n_rows: int):
    """LLVM IR for the intrinsic of :func:`_make_rows_dot`: the Eq. (4) sums of ``n_rows``
    consecutive float16 rows against the channel-interleaved weights, in exactly the order of
    :func:`fused_half_dot`'s vectorised three-row loop (see :func:`fused_half_dot_f16c`)."""

    def codegen(context, builder, signature, args):
        h = context.make_array(signature.args[0])(context, builder, args[0])
        wi = context.make_array(signature.args[2])(context, builder, args[2]).data
        fma8 = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_V8F, [_V8F] * 3),
                                              "llvm.fmuladd.v8f32")
        fma1 = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_F32, [_F32] * 3),
                                              "llvm.fmuladd.f32")
        m = cgutils.unpack_tuple(builder, h.shape, 2)[1]
        row_bytes = cgutils.unpack_tuple(builder, h.strides, 2)[0]
        base = builder.bitcast(h.data, _I8.as_pointer())
        rows = [builder.bitcast(builder.gep(base, [builder.mul(builder.add(args[1], _I64(r)),
                                                                 row_bytes)]),
                                _I16.as_pointer()) for r in range(n_rows)]
        zero = ir.Constant(_V8F, [0.0] * 8)
        acc = [[cgutils.alloca_once_value(builder, zero) for _ in range(3)]
               for _ in range(n_rows)]
        m8 = builder.sub(m, builder.srem(m, _I64(8)))  # the vector part, as the loop vectoriser's
        m24 = builder.sub(m8, builder.srem(m8, _I64(24)))

        def half(r, j):  # scalar half → float (vcvtph2ps)
            bits = builder.load(builder.gep(rows[r], [j]))
            return builder.fpext(builder.bitcast(bits, ir.HalfType()), _F32)

        def chunk(j, phase):  # 8 columns from j (j ≡ 8·phase mod 24) of every row
            w = builder.load(builder.bitcast(builder.gep(wi, [j]), _V8F.as_pointer()), align=4)
            for r in range(n_rows):
                bits = builder.load(builder.bitcast(builder.gep(rows[r], [j]),
                                                    _V8I16.as_pointer()), align=2)
                x = builder.fpext(builder.bitcast(bits, _V8H), _V8F)  # vcvtph2ps
                a = acc[r][phase]
                builder.store(builder.call(fma8, [x, w, builder.load(a)]), a)

        with cgutils.for_range_slice(builder, _I64(0), m24, _I64(24)) as (j, _):
            for phase in range(3):
                chunk(builder.add(j, _I64(8 * phase)), phase)
        for phase in range(2):  # at most two whole 8-column chunks left
            j = builder.add(m24, _I64(8 * phase))
            with builder.if_then(builder.icmp_signed("<", j, m8)):
                chunk(j, phase)
        # first column of channel c at or after m8
        m8_mod3 = builder.srem(m8, _I64(3))
        first = [builder.add(m8, builder.srem(builder.sub(_I64(c + 3), m8_mod3), _I64(3)))
                 for c in range(3)]
        sums = []
        for r in range(n_rows):
            av = [builder.load(a) for a in acc[r]]
            for c in range(3):  # channel c's 8 lanes, reduced in the vectoriser's order
                x = [builder.extract_element(av[_PHASE[c][k]], _I32(k)) for k in range(8)]
                t = builder.fadd(builder.fadd(builder.fadd(x[0], x[4]), builder.fadd(x[2], x[6])),
                                 builder.fadd(builder.fadd(x[1], x[5]), builder.fadd(x[3], x[7])))
                s = cgutils.alloca_once_value(builder, t)
                # the scalar remainder, channel c's columns in order (no reassociation flags)
                with cgutils.for_range_slice(builder, first[c], m, _I64(3)) as (j, _):
                    w = builder.load(builder.gep(wi, [j]))
                    builder.store(builder.call(fma1, [half(r, j), w, builder.load(s)]), s)
                sums.append(builder.load(s))
        return context.make_tuple(builder, signature.return_type, sums)

    return codegen


def _make_rows_dot(n_rows: int):
    """Numba intrinsic ``rows_dot(h, p, wi) -> (3·n_rows,) float32 tuple``: the three channel
    sums of rows ``p … p + n_rows − 1`` of ``h`` ((n, m) uint16, C-contiguous) against ``wi``
    ((m,) float32, C-contiguous). Compile it only where numba targets F16C."""

    @intrinsic
    def rows_dot(typingctx, h, p, wi):
        def c_array(a, dtype, ndim):
            return (isinstance(a, types.Array) and a.dtype == dtype and a.ndim == ndim
                    and a.layout == "C")

        if not (c_array(h, types.uint16, 2) and c_array(wi, types.float32, 1)
                and isinstance(p, types.Integer)):
            return None
        sig = types.UniTuple(types.float32, 3 * n_rows)(h, types.int64, wi)
        return sig, _rows_dot_codegen(n_rows)

    return rows_dot


_rows_dot = _make_rows_dot(INTERLEAVED_ROWS)
_row_dot = _make_rows_dot(1)


@njit(nogil=True, cache=True, boundscheck=False)
def fused_half_dot_f16c(h, w0, w1, w2, wi, out):  # pragma: no cover - compiled
    """:func:`fused_half_dot` with F16C, reading the weights from L1: the same sums, in the same
    order, from one channel-interleaved weight vector instead of three.

    Parameters
    ----------
    h : (n, m) uint16, C-contiguous
        Bits of float16 field rows (``m = 3L'``, channel-interleaved as stored).
    w0, w1, w2 : (m,) float32, C-contiguous
        Channel c's Eq. (4) weights on the columns of channel c, zero elsewhere.
    wi : (m,) float32, C-contiguous
        ``w0 + w1 + w2``: column j's weight for its own channel ``j mod 3``.
    out : (n, 3) float32

    Why: :func:`fused_half_dot` loads three weight vectors (72 KB at 2048 lights, from L2) for
    every eight halves it widens; their L2 → L1 traffic held its out-of-cache stream to 0.82–0.89
    of a one-thread ``sgemv`` (measured, 1 GB field). ``wi`` (24 KB) stays in L1, and one fused
    multiply-add per half (instead of three, two of them by zero) leaves the loop bound by
    memory: 1.06–1.17 of a one-thread ``sgemv``, 0.93–0.99 of a pure read of the same bytes
    (``docs/lighting.md``).

    How: eight halves from column j (a multiple of 8) of a row are widened (``vcvtph2ps``) and
    multiplied by ``wi[j:j+8]`` into one of three 8-lane accumulators, chosen by ``j/8 mod 3``
    (the channels repeat every 24 columns), :data:`INTERLEAVED_ROWS` rows at a time (LLVM IR
    through a numba intrinsic: numba's loop vectoriser does not vectorise this form). Lane k of
    accumulator r then sums exactly the columns ``j ≡ 8r + k (mod 24)``, all of channel
    ``(8r + k) mod 3`` — the columns that lane k of :func:`fused_half_dot`'s channel-c
    accumulator sums with non-zero weight, in the same order. The three channels' lanes are
    gathered back and reduced as that loop reduces them (``((x0+x4)+(x2+x6)) + ((x1+x5)+(x3+x7))``),
    then the columns past the last multiple of 8 are added one by one. The rows that
    :func:`fused_half_dot` handles one at a time (the last ``n mod 3``, a different order) go
    through it. So the results equal :func:`fused_half_dot`'s (``f16c=True``) bit for bit, up to
    the sign of a zero sum, where LLVM's vectoriser keeps that loop's order (tested); a NaN/inf
    half now reaches only its own channel's sum (there it also reached the other two through
    a multiply by zero weight).
    """
    n, m = h.shape
    if (wi.shape[0] != m or w0.shape[0] != m or w1.shape[0] != m or w2.shape[0] != m
            or out.shape[0] != n or out.shape[1] != 3):  # the IR reads without bounds checks
        raise ShapeError("fused_half_dot_f16c: expected weights of h.shape[1] entries and out "
                         "of shape (h.shape[0], 3)")
    n3 = n - n % 3  # rows fused_half_dot sums three at a time
    p = 0
    while p + INTERLEAVED_ROWS <= n3:
        s = _rows_dot(h, p, wi)
        for q in range(INTERLEAVED_ROWS):
            for c in range(3):
                out[p + q, c] = s[3 * q + c]
        p += INTERLEAVED_ROWS
    while p < n3:
        s1 = _row_dot(h, p, wi)
        out[p, 0] = s1[0]
        out[p, 1] = s1[1]
        out[p, 2] = s1[2]
        p += 1
    if n3 < n:
        fused_half_dot(h[n3:], w0, w1, w2, out[n3:], True)


#: Pixels per block of :func:`half_slab_dot`: the block's three float32 sums (24 KB) stay in L1
#: while the K slabs stream through.
SLAB_BLOCK = 2048


@njit(nogil=True, cache=True, boundscheck=False, fastmath=_FASTMATH)
def half_slab_dot(coef, idx, lw, out, f16c):  # pragma: no cover - compiled
    """``out[c, p] += Σ_k half(coef[idx[k], c, p]) · lw[k, c]``: relighting from K selected
    coefficient slabs (:class:`facegeo.lighting.compress.WaveletLightingField`).

    ``coef`` ``(L, 3, P)`` uint16 bits of float16, ``idx`` ``(K,)`` int64, ``lw`` ``(K, 3)``
    float32, ``out`` ``(3, P)`` float32 (accumulated into). Blocked over pixels
    (:data:`SLAB_BLOCK`) so the partial sums stay in L1; four slabs per pass over a block.
    Contiguous slices (not 3-D indexing in the inner loop) let LLVM vectorise: measured in
    cache, 100 slabs × 10,000 px, 15 G halves/s against 1.2 with indexing.
    """
    n_p = coef.shape[2]
    n_k = idx.size
    for p0 in range(0, n_p, SLAB_BLOCK):
        p1 = min(n_p, p0 + SLAB_BLOCK)
        for c in range(3):
            o = out[c, p0:p1]
            k = 0
            while k + 3 < n_k:
                a = coef[idx[k], c, p0:p1]
                b = coef[idx[k + 1], c, p0:p1]
                d = coef[idx[k + 2], c, p0:p1]
                e = coef[idx[k + 3], c, p0:p1]
                xa = lw[k, c]
                xb = lw[k + 1, c]
                xd = lw[k + 2, c]
                xe = lw[k + 3, c]
                for i in range(o.size):
                    o[i] += ((_half(a[i], f16c) * xa + _half(b[i], f16c) * xb)
                             + (_half(d[i], f16c) * xd + _half(e[i], f16c) * xe))
                k += 4
            while k < n_k:
                a = coef[idx[k], c, p0:p1]
                xa = lw[k, c]
                for i in range(o.size):
                    o[i] += _half(a[i], f16c) * xa
                k += 1


@njit(nogil=True, cache=True, boundscheck=False)
def haar_nonstandard_forward(img, levels):  # pragma: no cover - compiled
    """In-place forward non-standard 2-D Haar transform of ``img`` ``(C, H, W)`` float64.

    ``levels`` ``(n, 4)`` int64 rows ``(h, w, step θ, step φ)`` from
    :func:`facegeo.lighting._compress_haar._nonstandard_levels`; the compiled twin of
    :func:`facegeo.lighting.compress.haar2d_nonstandard` for one lighting per relight (the numpy
    version's per-step overhead dominated a relight of K slabs; tested equal).
    """
    r = np.sqrt(0.5)
    n_c, n_h, n_w = img.shape
    tmp = np.empty(max(n_h, n_w))
    for lev in range(levels.shape[0]):
        h = levels[lev, 0]
        w = levels[lev, 1]
        for c in range(n_c):
            if levels[lev, 2]:
                for y in range(h):
                    for i in range(w // 2):
                        a = img[c, y, 2 * i]
                        b = img[c, y, 2 * i + 1]
                        tmp[i] = (a + b) * r
                        tmp[w // 2 + i] = (a - b) * r
                    for i in range(w):
                        img[c, y, i] = tmp[i]
            if levels[lev, 3]:
                for x in range(w):
                    for i in range(h // 2):
                        a = img[c, 2 * i, x]
                        b = img[c, 2 * i + 1, x]
                        tmp[i] = (a + b) * r
                        tmp[h // 2 + i] = (a - b) * r
                    for i in range(h):
                        img[c, i, x] = tmp[i]
