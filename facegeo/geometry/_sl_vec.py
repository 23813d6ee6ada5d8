"""LLVM vector code of the structured-light decode's hot loops (numba intrinsics).

Private to :mod:`facegeo.geometry._sl_kernels` and :mod:`facegeo.geometry._sl_finish`
(imported by their kernel factories only).

:func:`pair_rgb8` folds 32 pixels of one pattern / inverse pair into a tile's accumulators in
one block of vector instructions: both frames' 96 interleaved bytes are loaded, split into their
R, G and B lanes by byte shuffles and summed to int16 channel sums; then the decision bit, the
uint8 margin and the running max / min — exactly what ``_sums_tile`` twice and ``_pair_tile``
(the ``k > 0`` branch) do over the same 32 pixels, bit for bit (tested). The margin is taken as
a 16-bit high multiply, ``min(((2 d + 1) · m) >> 16, 255)`` (``pmulhuw`` with AVX-512 BW):
``_sl_kernels._int_margin`` finds the ``m`` that gives the float32 margin for every sum
difference, checked exhaustively (the float32 product, rint and conversions were a dozen of
the block's ≈ 60 instructions). numba's own code for
those loops loads the interleaved channels with gathers-by-shuffle per channel and runs the
sums and the update as separate passes through the tile; on AMD znver5 (AVX-512 VBMI) the
block runs at 0.022 against 0.056 ns a pixel for the channel sums in cache, and — with the
prefetch below — a 10-pair group of 1280 × 1024 frames at 1 thread in 2.46 against 5.3 ms
(one read of the 20 frames: 2.13 ms). On other x86 CPUs LLVM lowers the same shuffles to
narrower instructions: slower, the same values.

:func:`pair2_rgb8` folds two pairs of one code family in one block: the family's decision
words, running max / min and smallest margin are loaded and stored once for both pairs (each
pair still stores its own margin plane). With one pair a block those accumulators' load /
store traffic between L1 and L2 was as large as the frames' bytes; the bench decode's 20 pairs
(1280 × 1024, 40 frames, runs of 32,768 pixels) folded in 5.4–5.6 ms one pair a block and in
4.7–4.8 ms two (four a block: 5.4 ms). The kernel prefetches two lines a frame a block (a
block advances 96 bytes a frame, so lines ``q`` and ``q + 64`` cover every byte).

:func:`prefetch` issues a software prefetch (``llvm.prefetch``: read, high locality) for the
byte at an offset of an array; a hint, never a fault, also past the array's end. The kernel
prefetches the pair's bytes :data:`PREFETCH_BYTES` ahead: a tile reads each frame in one run,
and the hardware prefetcher alone left the core waiting at each of the 40 runs' starts and
between the compute bursts (2.7 ms of the 5.3 above; prefetch distances 512 / 2,048 / 4,096 /
8,192 / 32,768 bytes: 4.6 / 3.1 / 2.5 / 2.5 / 2.6 ms). Past the end of a group's run the kernel
prefetches the next group's first bytes.

:func:`direct_block` is the finish's fully resolved pass (``_sl_finish``) over 16 pixels in
<16 x i32 / float> lanes: numba's loop ran 8 lanes wide (int64 words, NaN-safe selects as
compare chains) at 0.65 ns a pixel in cache, the block at 0.42. :func:`lit_rgb8` makes the lit
level (white − black) of 32 pixels from the held 8-bit RGB frames. :func:`start_block` is the
fused finish's start over 32 pixels (``L_max`` / ``L_min`` from the pairs' running channel sums,
direct, global, the reliability threshold, lit, shadow, the confidence's start): the fused
chunk kernel runs it and both axes' direct blocks 32 pixels at a time, so the start's planes
are read back from L1 instead of after a pass over the whole run (the bench decode's start and
axes 2.6–2.7 → 2.0–2.2 ms; the decode 8.9–9.8 → 8.3–8.4 ms in ``facegeo bench``). The
outputs the kernel does not read back are stored non-temporally there when their planes are
aligned (no read for ownership of 25 of the 36 bytes a pixel: the start and axes → 1.7–1.8 ms,
the decode → 7.8–8.7 ms); :func:`store_fence` orders those stores before the kernel returns.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.extending import intrinsic

__all__ = ["DIRECT_LANES", "LANES", "PREFETCH_BYTES", "direct_block", "lit_rgb8", "pair2_rgb8",
           "pair_rgb8", "prefetch", "source_hash", "start_block", "store_fence", "u8_ptr"]

#: Pixels per :func:`pair_rgb8` call.
LANES = 32
#: Pixels per :func:`direct_block` call.
DIRECT_LANES = 16
#: How far ahead of the pixel being folded the kernel prefetches each frame, in bytes.
PREFETCH_BYTES = 4096

_I8, _I16, _I32, _I64 = ir.IntType(8), ir.IntType(16), ir.IntType(32), ir.IntType(64)
_F32 = ir.FloatType()


def source_hash() -> str:
    """SHA-256 of this file: a closure cell of the kernels that inline this code generation,
    so numba's disk cache (which sees only the kernel's own file) compiles them again after
    an edit here."""
    import hashlib
    from pathlib import Path

    return hashlib.sha256(Path(__file__).read_bytes()).hexdigest()


def _c1d(a, dtype) -> bool:
    """A C-contiguous 1-D array of ``dtype`` (the vector block loads and stores consecutive
    elements: a strided view would be read and written in its gaps)."""
    return isinstance(a, types.Array) and a.ndim == 1 and a.layout == "C" and a.dtype == dtype


def _has_feature(context, name: str) -> bool:
    """Whether numba compiles for a CPU with instruction-set feature ``name`` (its target
    machine's features: the host's, or ``NUMBA_CPU_NAME`` / ``NUMBA_CPU_FEATURES``)."""
    features = getattr(context.codegen(), "_tm_features", "") or ""
    return f"+{name}" in features.split(",")


def _vec(t, n: int = LANES) -> ir.VectorType:
    return ir.VectorType(t, n)


def _declare(module, name: str, fnty) -> ir.Function:
    """An LLVM intrinsic's declaration in ``module`` (declared once per module)."""
    try:
        return module.get_global(name)
    except KeyError:
        return ir.Function(module, fnty, name=name)


def _splat(builder, x, vt: ir.VectorType):
    v = builder.insert_element(ir.Constant(vt, ir.Undefined), x, ir.Constant(_I32, 0))
    return builder.shuffle_vector(v, ir.Constant(vt, ir.Undefined),
                                  ir.Constant(_vec(_I32, vt.count), [0] * vt.count))


def _data(context, builder, aty, aval):
    return context.make_array(aty)(context, builder, aval).data


def _at(builder, base, off, elt):
    """Pointer to a vector of ``elt`` at element ``off`` of ``base``."""
    return builder.bitcast(builder.gep(base, [off]), elt.as_pointer())


def _rgb_sums(builder, p):
    """The channel sums of the 32 interleaved RGB pixels at byte pointer ``p``, <32 x i16>."""
    v64, v32 = _vec(_I8, 64), _vec(_I8, 32)
    a = builder.load(builder.bitcast(p, v64.as_pointer()), align=1)
    b = builder.load(builder.bitcast(builder.gep(p, [ir.Constant(_I64, 64)]),
                                     v32.as_pointer()), align=1)
    b = builder.shuffle_vector(b, ir.Constant(v32, ir.Undefined),
                               ir.Constant(_vec(_I32, 64), list(range(32)) + [0] * 32))
    acc = None
    for c in range(3):
        ch = builder.shuffle_vector(a, b, ir.Constant(_vec(_I32), [3 * t + c for t in range(32)]))
        w = builder.zext(ch, _vec(_I16))
        acc = w if acc is None else builder.add(acc, w)
    return acc


def _margin_float(builder, mx, mn, kv):
    """``min(rint(float32(mx - mn) · k), 255)`` as <32 x i8> (``k`` float32)."""
    d = builder.sitofp(builder.sext(builder.sub(mx, mn), _vec(_I32)), _vec(_F32))
    rint = _declare(builder.module, "llvm.rint.v32f32", ir.FunctionType(_vec(_F32), [_vec(_F32)]))
    r = builder.fptosi(builder.call(rint, [builder.fmul(d, _splat(builder, kv, _vec(_F32)))]),
                       _vec(_I32))
    top = ir.Constant(_vec(_I32), [255] * LANES)
    r = builder.select(builder.icmp_signed("<", r, top), r, top)
    return builder.trunc(r, _vec(_I8))


def _margin_mulhi(context, builder, mx, mn, kv):
    """``min(((2 (mx - mn) + 1) · k) >> 16, 255)`` as <32 x i8> (``k`` an integer below 2**16):
    a high multiply of 16-bit lanes — ``pmulhuw`` where the target has AVX-512 BW (one
    instruction for 32 lanes, where the float32 product, rint and conversions of
    :func:`_margin_float` take a dozen), the same value from 32-bit products elsewhere."""
    v16, v32i = _vec(_I16), _vec(_I32)
    d2 = builder.add(builder.shl(builder.sub(mx, mn), ir.Constant(v16, [1] * LANES)),
                     ir.Constant(v16, [1] * LANES))  # 2 d + 1 <= 2 * 1023 + 1
    mul16 = _splat(builder, builder.trunc(kv, _I16), v16)
    if _has_feature(context, "avx512bw"):
        mulhu = _declare(builder.module, "llvm.x86.avx512.pmulhu.w.512",
                         ir.FunctionType(v16, [v16, v16]))
        r16 = builder.call(mulhu, [d2, mul16])
    else:
        prod = builder.mul(builder.zext(d2, v32i), builder.zext(mul16, v32i))
        r16 = builder.trunc(builder.lshr(prod, ir.Constant(v32i, [16] * LANES)), v16)
    top = ir.Constant(v16, [255] * LANES)
    r16 = builder.select(builder.icmp_unsigned("<", r16, top), r16, top)
    return builder.trunc(r16, _vec(_I8))


def _pair_args_ok(fp, fq, words, margin, hi, lo, k, mmin) -> bool:
    return (_c1d(fp, types.uint8) and fq == fp and isinstance(words, types.Array)
            and isinstance(words.dtype, types.Integer) and not words.dtype.signed
            and _c1d(words, words.dtype) and _c1d(margin, types.uint8)
            and _c1d(hi, types.int16) and lo == hi
            and (mmin == margin or isinstance(mmin, types.NoneType))
            and isinstance(k, (types.Integer, types.Float)))


def _fold_pairs(context, builder, frames, three, kv, int_k):
    """Per pair of ``frames`` (``(type, value)`` of pattern and inverse) its decision, larger
    and smaller channel sum and uint8 margin over the 32 pixels at byte ``three``."""
    out = []
    for (pty, pv), (qty, qv) in frames:
        sp = _rgb_sums(builder, builder.gep(_data(context, builder, pty, pv), [three]))
        sq = _rgb_sums(builder, builder.gep(_data(context, builder, qty, qv), [three]))
        gt = builder.icmp_signed(">", sp, sq)
        mx = builder.select(gt, sp, sq)
        mn = builder.select(gt, sq, sp)
        m8 = (_margin_mulhi(context, builder, mx, mn, kv) if int_k
              else _margin_float(builder, mx, mn, kv))
        out.append((gt, mx, mn, m8))
    return out


def _update(context, builder, sig, folded, bitvals, margins, wv, hv, lv, mmv, tv, iw, ih, imm):
    """Store the folded pairs into the accumulators at tile position ``tv``: the decision bits
    ORed into the words (argument ``iw``), each pair's margin into its plane, the running
    max / min of the sums (``ih``, ``ih + 1``) and, with ``imm``, the family's smallest margin."""
    wbits = sig.args[iw].dtype.bitwidth
    wt = _vec(ir.IntType(wbits))
    wp = _at(builder, _data(context, builder, sig.args[iw], wv), tv, wt)
    w = builder.load(wp, align=wbits // 8)
    mx = mn = m_lo = None
    for (gt, x, y, m8), bv, (mty, mv) in zip(folded, bitvals, margins):
        w = builder.or_(w, builder.select(gt, _splat(builder, bv, wt), ir.Constant(wt, None)))
        builder.store(m8, _at(builder, _data(context, builder, mty, mv), tv, _vec(_I8)), align=1)
        mx = x if mx is None else builder.select(builder.icmp_signed(">", x, mx), x, mx)
        mn = y if mn is None else builder.select(builder.icmp_signed("<", y, mn), y, mn)
        m_lo = m8 if m_lo is None else builder.select(builder.icmp_unsigned("<", m8, m_lo),
                                                      m8, m_lo)
    builder.store(w, wp, align=wbits // 8)
    if imm is not None:
        mp = _at(builder, _data(context, builder, sig.args[imm], mmv), tv, _vec(_I8))
        old = builder.load(mp, align=1)
        builder.store(builder.select(builder.icmp_unsigned("<", m_lo, old), m_lo, old), mp,
                      align=1)
    hp = _at(builder, _data(context, builder, sig.args[ih], hv), tv, _vec(_I16))
    lp = _at(builder, _data(context, builder, sig.args[ih + 1], lv), tv, _vec(_I16))
    h = builder.load(hp, align=2)
    lo_ = builder.load(lp, align=2)
    builder.store(builder.select(builder.icmp_signed(">", mx, h), mx, h), hp, align=2)
    builder.store(builder.select(builder.icmp_signed("<", mn, lo_), mn, lo_), lp, align=2)


@intrinsic
def pair_rgb8(typingctx, fp, fq, off, words, bitval, margin, k, hi, lo, t,
              mmin):  # pragma: no cover - compiled
    """Fold pixels ``off … off + 31`` of pattern ``fp`` / inverse ``fq`` (flat uint8 RGB
    frames) into tile positions ``t … t + 31``: ``words[t+i] |= bitval`` where the pattern's
    channel sum is larger, ``margin[t+i] = min(rint(float32(|s_p - s_q|) · k), 255)`` for a
    float ``k``, or ``min(((2 |s_p - s_q| + 1) · k) >> 16, 255)`` for an integer ``k`` (the
    multiplier of ``_sl_kernels._int_margin``: the same margins, checked there for every
    difference),
    ``hi`` / ``lo`` (int16) the running max / min of both sums; ``mmin`` (uint8, or None) the
    running min of the margins (the code family's smallest margin, for the finish)."""
    if not _pair_args_ok(fp, fq, words, margin, hi, lo, k, mmin):
        return None
    with_min = not isinstance(mmin, types.NoneType)
    int_k = isinstance(k, types.Integer)
    sig = types.void(fp, fq, types.int64, words, words.dtype, margin,
                     types.int64 if int_k else types.float32, hi, lo, types.int64, mmin)

    def codegen(context, builder, signature, args):
        fpv, fqv, offv, wv, bvv, mv, kv, hv, lv, tv, mmv = args
        A = signature.args
        three = builder.mul(offv, ir.Constant(_I64, 3))
        folded = _fold_pairs(context, builder, [((A[0], fpv), (A[1], fqv))], three, kv, int_k)
        _update(context, builder, signature, folded, [bvv], [(A[5], mv)], wv, hv, lv, mmv,
                tv, 3, 7, 10 if with_min else None)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def pair2_rgb8(typingctx, fp, fq, fp2, fq2, off, words, bitval, bitval2, margin, margin2, k, hi,
               lo, t, mmin):  # pragma: no cover - compiled
    """:func:`pair_rgb8` for two pairs of one code family at once (``fp`` / ``fq`` with
    ``bitval`` and ``margin``, ``fp2`` / ``fq2`` with ``bitval2`` and ``margin2``): the same
    values as two calls, with the family's words, running max / min and smallest margin
    loaded and stored once for both (those accumulators' traffic between the caches bounded
    the fold: a 20-pair decode's pairs ran at ≈ 0.7 of the frames' read speed)."""
    if not (_pair_args_ok(fp, fq, words, margin, hi, lo, k, mmin) and fp2 == fp and fq2 == fp
            and margin2 == margin):
        return None
    with_min = not isinstance(mmin, types.NoneType)
    int_k = isinstance(k, types.Integer)
    sig = types.void(fp, fq, fp2, fq2, types.int64, words, words.dtype, words.dtype, margin,
                     margin2, types.int64 if int_k else types.float32, hi, lo, types.int64, mmin)

    def codegen(context, builder, signature, args):
        fpv, fqv, fp2v, fq2v, offv, wv, bvv, bv2v, mv, m2v, kv, hv, lv, tv, mmv = args
        A = signature.args
        three = builder.mul(offv, ir.Constant(_I64, 3))
        folded = _fold_pairs(context, builder, [((A[0], fpv), (A[1], fqv)),
                                                ((A[2], fp2v), (A[3], fq2v))], three, kv, int_k)
        _update(context, builder, signature, folded, [bvv, bv2v], [(A[8], mv), (A[9], m2v)],
                wv, hv, lv, mmv, tv, 5, 11, 14 if with_min else None)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def u8_ptr(typingctx, addr):  # pragma: no cover - compiled
    """The address ``addr`` (int64) as a ``uint8`` pointer, for ``numba.carray``: the pair
    kernel views each held frame in place from its data address (``_sl_kernels.FrameSet``),
    where a numba typed list of the frames cost ≈ 4 µs a frame to build for every decode."""
    if not isinstance(addr, types.Integer):
        return None
    sig = types.CPointer(types.uint8)(types.int64)

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], _I8.as_pointer())

    return sig, codegen


@intrinsic
def prefetch(typingctx, a, off):  # pragma: no cover - compiled
    """Prefetch (read, high locality) the byte at element ``off`` of array ``a``."""
    if not isinstance(a, types.Array):
        return None
    sig = types.void(a, types.int64)

    def codegen(context, builder, signature, args):
        p8 = _I8.as_pointer()
        p = builder.bitcast(builder.gep(_data(context, builder, signature.args[0], args[0]),
                                        [args[1]]), p8)
        fn = _declare(builder.module, "llvm.prefetch.p0",
                      ir.FunctionType(ir.VoidType(), [p8, _I32, _I32, _I32]))
        builder.call(fn, [p, ir.Constant(_I32, 0), ir.Constant(_I32, 3), ir.Constant(_I32, 1)])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def direct_block(typingctx, sg, mi, tau, lit, ref, cov, sov, oov, qov, slv, t, mscale, high, sb,
                 n_stripes, one_ok, step, c0, sig_one, nt):  # pragma: no cover - compiled
    """The fully resolved pass of ``_sl_finish``'s ``direct`` over pixels ``t … t + 15`` in
    one block of <16 x i32 / float> lanes (numba's loop ran 8 lanes wide with int64 words and
    NaN-safe selects as compare chains: 0.65 ns a pixel). Per pixel, as that loop: the decision
    word ``sg`` (uint8 / 16 / 32) as a binary stripe index (the XOR base folded in with
    ``high`` / ``sb``, then Gray → binary by a prefix XOR), the family's smallest margin ``mi``
    (uint8 steps, or float32) times ``mscale`` against ``tau`` (``slv`` = not reliable),
    validity ``oov`` = ``lit`` and index < ``n_stripes`` and ``one_ok`` and reliable,
    ``cov = float32(float64(x) · step + c0)`` and ``sov = sig_one`` (+ NaN where not valid),
    and the running confidence ``qov = min(qov, clip(m / max(ref, 1e-12), 0, 1) · valid)``
    where reliable — with numpy's NaN rules
    for ``np.maximum`` / ``np.minimum``. ``nt``: ``cov`` / ``sov`` stored non-temporally (the
    caller guarantees 64-byte aligned vectors; :func:`_store_out`). Returns how many of the 16
    are not reliable."""
    ok = (isinstance(sg, types.Array) and isinstance(sg.dtype, types.Integer)
          and not sg.dtype.signed and _c1d(sg, sg.dtype)
          and (_c1d(mi, types.uint8) or _c1d(mi, types.float32))
          and _c1d(tau, types.float32) and _c1d(lit, types.boolean) and _c1d(ref, types.float32)
          and _c1d(cov, types.float32) and _c1d(sov, types.float32)
          and _c1d(oov, types.boolean) and _c1d(qov, types.float32) and _c1d(slv, types.uint8))
    if not ok:
        return None
    sig = types.int64(sg, mi, tau, lit, ref, cov, sov, oov, qov, slv, types.int64, types.float32,
                      types.int64, types.int64, types.int64, types.boolean, types.float64,
                      types.float64, types.float32, types.boolean)
    n = DIRECT_LANES

    def codegen(context, builder, signature, args):
        (sgv, miv, tauv, litv, refv, covv, sovv, oovv, qovv, slvv, tv, msc, hi, sbv, nsv, oneok,
         stepv, c0v, sigv, ntv) = args
        A = signature.args
        v32, vf, vd, v8, v1 = _vec(_I32, n), _vec(_F32, n), _vec(ir.DoubleType(), n), \
            _vec(_I8, n), _vec(ir.IntType(1), n)

        def ptr(i, elt):
            return _at(builder, _data(context, builder, A[i], args[i]), tv, elt)

        wbits = A[0].dtype.bitwidth
        w = builder.load(ptr(0, _vec(ir.IntType(wbits), n)), align=wbits // 8)
        x = builder.zext(w, v32) if wbits < 32 else w
        # the XOR base: planes above it were projected XORed with it (high = 0 otherwise)
        bit = builder.and_(builder.lshr(x, _splat(builder, builder.trunc(sbv, _I32), v32)),
                           ir.Constant(v32, [1] * n))
        x = builder.xor(x, builder.mul(_splat(builder, builder.trunc(hi, _I32), v32), bit))
        for k in (1, 2, 4, 8, 16):  # Gray -> binary
            x = builder.xor(x, builder.lshr(x, ir.Constant(v32, [k] * n)))
        mv = builder.load(ptr(1, v8), align=1) if A[1].dtype == types.uint8 else \
            builder.load(ptr(1, vf), align=4)
        m = builder.fmul(builder.uitofp(mv, vf) if A[1].dtype == types.uint8 else mv,
                         _splat(builder, msc, vf))
        good = builder.fcmp_ordered(">=", m, builder.load(ptr(2, vf), align=4))
        bad = builder.not_(good)
        builder.store(builder.zext(bad, v8), ptr(9, v8), align=1)
        lit8 = builder.load(ptr(3, v8), align=1)
        big = ir.Constant(_I64, 2**31 - 1)  # n_stripes as int32 (words < 2**31)
        ns = builder.trunc(builder.select(builder.icmp_signed(">", nsv, big), big, nsv), _I32)
        o = builder.and_(builder.icmp_unsigned("!=", lit8, ir.Constant(v8, None)),
                         builder.icmp_signed("<", x, _splat(builder, ns, v32)))
        o = builder.and_(o, good)
        o = builder.and_(o, _splat(builder, builder.trunc(oneok, ir.IntType(1))
                                   if oneok.type != ir.IntType(1) else oneok, v1))
        builder.store(builder.zext(o, v8), ptr(7, v8), align=1)
        # the NaN of x86's 0 / 0 (sign bit set), as the former kernel made it at run time
        nan = builder.bitcast(ir.Constant(v32, [0xFFC00000 - 2**32] * n), vf)
        z = builder.select(o, ir.Constant(vf, [0.0] * n), nan)
        c = builder.fadd(builder.fmul(builder.sitofp(x, vd), _splat(builder, stepv, vd)),
                         _splat(builder, c0v, vd))
        nt = _flag(builder, ntv)
        _store_out(builder, builder.fadd(builder.fptrunc(c, vf), z), ptr(5, vf), nt, 4 * n)
        _store_out(builder, builder.fadd(_splat(builder, sigv, vf), z), ptr(6, vf), nt, 4 * n)
        r = builder.load(ptr(4, vf), align=4)
        tiny = _splat(builder, ir.Constant(_F32, 1e-12), vf)
        r = builder.select(builder.fcmp_unordered(">=", r, tiny), r, tiny)  # np.maximum
        q = builder.fdiv(m, r)
        zero, one = ir.Constant(vf, [0.0] * n), ir.Constant(vf, [1.0] * n)
        q = builder.select(builder.fcmp_unordered(">=", q, zero), q, zero)  # np.maximum(q, 0)
        q = builder.select(builder.fcmp_unordered("<=", q, one), q, one)  # np.minimum(q, 1)
        v = builder.fmul(q, builder.uitofp(o, vf))
        qp = ptr(8, vf)
        qo = builder.load(qp, align=4)
        keep = builder.or_(builder.fcmp_ordered("<=", qo, v),
                           builder.fcmp_unordered("uno", qo, qo))  # np.minimum(qo, v)
        w_ = builder.select(keep, qo, v)
        builder.store(builder.select(good, w_, qo), qp, align=4)
        cnt = builder.bitcast(bad, ir.IntType(n))
        ctpop = _declare(builder.module, f"llvm.ctpop.i{n}",
                         ir.FunctionType(ir.IntType(n), [ir.IntType(n)]))
        return builder.zext(builder.call(ctpop, [cnt]), _I64)

    return sig, codegen


def _lit_lanes(context, builder, white, black, tv, ws, bs):
    """White − black of pixels ``t … t + 31`` of two flat 8-bit RGB frames (``(type, value)``
    each), ``float32(Σ white) · ws − float32(Σ black) · bs``, <32 x float>."""
    vf = _vec(_F32)
    three = builder.mul(tv, ir.Constant(_I64, 3))
    sw, sb = (builder.uitofp(_rgb_sums(builder, builder.gep(
        _data(context, builder, ty, v), [three])), vf) for ty, v in (white, black))
    return builder.fsub(builder.fmul(sw, _splat(builder, ws, vf)),
                        builder.fmul(sb, _splat(builder, bs, vf)))


@intrinsic
def lit_rgb8(typingctx, white, black, t, w_scale, b_scale,
             out):  # pragma: no cover - compiled
    """``out[t … t + 31] = float32(Σ white) · w_scale − float32(Σ black) · b_scale`` over
    the channel sums of pixels ``t … t + 31`` of two flat 8-bit RGB frames (the byte shuffles of
    :func:`pair_rgb8`): white − black as ``_sl_kernels.luminance`` makes each, bit for bit (a
    sum of three bytes is exact in int16 and in float32)."""
    if not (_c1d(white, types.uint8) and black == white and _c1d(out, types.float32)):
        return None
    sig = types.void(white, black, types.int64, types.float32, types.float32, out)

    def codegen(context, builder, signature, args):
        wv, bv, tv, ws, bs, ov = args
        A = signature.args
        li = _lit_lanes(context, builder, (A[0], wv), (A[1], bv), tv, ws, bs)
        builder.store(li, _at(builder, _data(context, builder, A[5], ov), tv, _vec(_F32)),
                      align=4)
        return context.get_dummy_value()

    return sig, codegen


def _store_out(builder, v, p, nt, align: int) -> None:
    """Store output vector ``v`` at ``p``: a non-temporal store (``!nontemporal``: no read for
    ownership, the line goes to memory past the caches) where the run-time flag ``nt`` is set
    — the caller guarantees ``p`` is then aligned to ``align`` bytes (one vector, at most
    64) — else a plain store."""
    with builder.if_else(nt) as (streaming, plain):
        with streaming:
            st = builder.store(v, p, align=align)
            st.set_metadata("nontemporal", builder.module.add_metadata([ir.Constant(_I32, 1)]))
        with plain:
            el = v.type.element
            builder.store(v, p, align=4 if isinstance(el, ir.FloatType) else el.width // 8)


@intrinsic
def store_fence(typingctx):  # pragma: no cover - compiled
    """Order the non-temporal stores before it ahead of every later store (``llvm.x86.sse.sfence``
    on x86; nothing elsewhere): they are weakly ordered, and another thread reads the outputs
    once the kernel returns."""
    sig = types.void()

    def codegen(context, builder, signature, args):
        if _has_feature(context, "sse"):
            fn = _declare(builder.module, "llvm.x86.sse.sfence",
                          ir.FunctionType(ir.VoidType(), []))
            builder.call(fn, [])
        else:
            builder.fence("seq_cst")
        return context.get_dummy_value()

    return sig, codegen


def _flag(builder, v):
    """A numba boolean argument as an i1."""
    return v if v.type == ir.IntType(1) else builder.trunc(v, ir.IntType(1))


def _max_nan_v(builder, a, b):
    """``_sl_finish``'s ``max_nan`` (``np.maximum``: NaN propagates, ties keep ``a``) on
    float vectors: ``a`` where ``a >= b``, else ``b`` where ``b > a`` or ``b`` is NaN, else
    ``a``."""
    take_b = builder.or_(builder.fcmp_ordered(">", b, a), builder.fcmp_unordered("uno", b, b))
    return builder.select(builder.fcmp_ordered(">=", a, b), a,
                          builder.select(take_b, b, a))


@intrinsic
def start_block(typingctx, hsum, lsum, scale, white, black, w_scale, b_scale, has_wb, min_c,
                rel_c, shadow_thr, direct, glob, lit, shadow, litb, tau, conf, t,
                nt):  # pragma: no cover - compiled
    """The fused finish's start over pixels ``t … t + 31`` of a run (``_sl_finish``'s
    ``start``, the same values bit for bit): ``L_max`` / ``L_min`` as the running max / min
    channel sums ``hsum`` / ``lsum`` (int16) times ``scale``, ``direct = L_max - L_min``,
    ``glob = 2 max(L_min, 0)``, ``tau = max(min_c, rel_c · direct)`` (NaN-propagating
    maxima), ``lit`` = white − black from the held 8-bit RGB frames' channel sums when
    ``has_wb`` (:func:`lit_rgb8`), else ``direct``; ``shadow = not (lit >= shadow_thr)``, ``litb
    = not shadow``, ``conf = 1``. ``nt``: ``glob``, ``shadow`` and, with white / black frames,
    ``lit`` (which the kernel does not read back; without them ``lit`` may be ``direct``'s own
    plane) stored non-temporally (the caller guarantees aligned vectors: 128 bytes of float32,
    32 of flags). Returns how many of the 32 are lit."""
    f32 = types.float32
    ok = (_c1d(hsum, types.int16) and lsum == hsum and _c1d(white, types.uint8)
          and black == white and all(_c1d(x, f32) for x in (direct, glob, lit, tau, conf))
          and _c1d(shadow, types.boolean) and _c1d(litb, types.boolean))
    if not ok:
        return None
    sig = types.int64(hsum, lsum, f32, white, black, f32, f32, types.boolean, f32, f32, f32,
                      direct, glob, lit, shadow, litb, tau, conf, types.int64, types.boolean)

    def codegen(context, builder, signature, args):
        (hv, lv, sc, wv, bv, ws, bs, hwb, mnc, rlc, thr, dv, gv, lov, shv, lbv, tav, cfv,
         tv, ntv) = args
        A = signature.args
        vf, v16, v8 = _vec(_F32), _vec(_I16), _vec(_I8)

        def ptr(i, elt):
            return _at(builder, _data(context, builder, A[i], args[i]), tv, elt)

        s = _splat(builder, sc, vf)
        mx = builder.fmul(builder.sitofp(builder.load(ptr(0, v16), align=2), vf), s)
        mn = builder.fmul(builder.sitofp(builder.load(ptr(1, v16), align=2), vf), s)
        d = builder.fsub(mx, mn)
        builder.store(d, ptr(11, vf), align=4)
        nt = _flag(builder, ntv)
        zero = ir.Constant(vf, [0.0] * LANES)
        _store_out(builder, builder.fmul(ir.Constant(vf, [2.0] * LANES),
                                         _max_nan_v(builder, mn, zero)), ptr(12, vf), nt, 64)
        builder.store(_max_nan_v(builder, _splat(builder, mnc, vf),
                                 builder.fmul(_splat(builder, rlc, vf), d)), ptr(16, vf), align=4)
        with builder.if_else(_flag(builder, hwb)) as (with_wb, without):
            with with_wb:
                lw = _lit_lanes(context, builder, (A[3], wv), (A[4], bv), tv, ws, bs)
                from_wb = builder.block
            with without:
                from_d = builder.block
        li = builder.phi(vf)
        li.add_incoming(lw, from_wb)
        li.add_incoming(d, from_d)
        # without white / black frames lit is direct, and its plane may be direct's own
        # (StreamDecoder.finish), which the axes read back: stored plainly then
        _store_out(builder, li, ptr(13, vf), builder.and_(nt, _flag(builder, hwb)), 64)
        lit_ = builder.fcmp_ordered(">=", li, _splat(builder, thr, vf))  # not shadow
        _store_out(builder, builder.zext(builder.not_(lit_), v8), ptr(14, v8), nt, LANES)
        builder.store(builder.zext(lit_, v8), ptr(15, v8), align=1)
        builder.store(ir.Constant(vf, [1.0] * LANES), ptr(17, vf), align=4)
        ctpop = _declare(builder.module, f"llvm.ctpop.i{LANES}",
                         ir.FunctionType(ir.IntType(LANES), [ir.IntType(LANES)]))
        return builder.zext(builder.call(ctpop, [builder.bitcast(lit_, ir.IntType(LANES))]),
                            _I64)

    return sig, codegen
