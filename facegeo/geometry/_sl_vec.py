"""LLVM vector code for the tile kernel of 8-bit RGB pattern / inverse pairs (numba intrinsics).

Private to :mod:`facegeo.geometry._sl_kernels` (imported by its kernel factory only).

:func:`pair_rgb8` folds 32 pixels of one pattern / inverse pair into a tile's accumulators in
one block of vector instructions: both frames' 96 interleaved bytes are loaded, split into their
R, G and B lanes by byte shuffles and summed to int16 channel sums; then the decision bit, the
uint8 margin and the running max / min — exactly what ``_sums_tile`` twice and ``_pair_tile``
(the ``k > 0`` branch) do over the same 32 pixels, bit for bit (tested). numba's own code for
those loops loads the interleaved channels with gathers-by-shuffle per channel and runs the
sums and the update as separate passes through the tile; on AMD znver5 (AVX-512 VBMI) the
block runs at 0.022 against 0.056 ns a pixel for the channel sums in cache, and — with the
prefetch below — a 10-pair group of 1280 × 1024 frames at 1 thread in 2.46 against 5.3 ms
(one read of the 20 frames: 2.13 ms). On other x86 CPUs LLVM lowers the same shuffles to
narrower instructions: slower, the same values.

:func:`prefetch` issues a software prefetch (``llvm.prefetch``: read, high locality) for the
byte at an offset of an array; a hint, never a fault, also past the array's end. The kernel
prefetches the pair's bytes :data:`PREFETCH_BYTES` ahead: a tile reads each frame in one run,
and the hardware prefetcher alone left the core waiting at each of the 40 runs' starts and
between the compute bursts (2.7 ms of the 5.3 above; prefetch distances 512 / 2,048 / 4,096 /
8,192 / 32,768 bytes: 4.6 / 3.1 / 2.5 / 2.5 / 2.6 ms).
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.extending import intrinsic

__all__ = ["LANES", "PREFETCH_BYTES", "pair_rgb8", "prefetch", "source_hash"]

#: Pixels per :func:`pair_rgb8` call.
LANES = 32
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


@intrinsic
def pair_rgb8(typingctx, fp, fq, off, words, bitval, margin, k, hi, lo, t,
              mmin):  # pragma: no cover - compiled
    """Fold pixels ``off … off + 31`` of pattern ``fp`` / inverse ``fq`` (flat uint8 RGB
    frames) into tile positions ``t … t + 31``: ``words[t+i] |= bitval`` where the pattern's
    channel sum is larger, ``margin[t+i] = min(rint(float32(|s_p - s_q|) · k), 255)``,
    ``hi`` / ``lo`` (int16) the running max / min of both sums; ``mmin`` (uint8, or None) the
    running min of the margins (the code family's smallest margin, for the finish)."""
    if not (_c1d(fp, types.uint8) and fq == fp and isinstance(words, types.Array)
            and isinstance(words.dtype, types.Integer) and not words.dtype.signed
            and _c1d(words, words.dtype) and _c1d(margin, types.uint8)
            and _c1d(hi, types.int16) and lo == hi
            and (mmin == margin or isinstance(mmin, types.NoneType))):
        return None
    with_min = not isinstance(mmin, types.NoneType)
    sig = types.void(fp, fq, types.int64, words, words.dtype, margin, types.float32, hi, lo,
                     types.int64, mmin)

    def codegen(context, builder, signature, args):
        fpv, fqv, offv, wv, bvv, mv, kv, hv, lv, tv, mmv = args
        three = builder.mul(offv, ir.Constant(_I64, 3))
        sp = _rgb_sums(builder, builder.gep(_data(context, builder, signature.args[0], fpv),
                                            [three]))
        sq = _rgb_sums(builder, builder.gep(_data(context, builder, signature.args[1], fqv),
                                            [three]))
        wt = _vec(ir.IntType(signature.args[3].dtype.bitwidth))
        wp = _at(builder, _data(context, builder, signature.args[3], wv), tv, wt)
        gt = builder.icmp_signed(">", sp, sq)
        w = builder.load(wp, align=signature.args[3].dtype.bitwidth // 8)
        w = builder.or_(w, builder.select(gt, _splat(builder, bvv, wt), ir.Constant(wt, None)))
        builder.store(w, wp, align=signature.args[3].dtype.bitwidth // 8)
        mx = builder.select(gt, sp, sq)
        mn = builder.select(gt, sq, sp)
        d = builder.sitofp(builder.sext(builder.sub(mx, mn), _vec(_I32)), _vec(_F32))
        rint = _declare(builder.module, "llvm.rint.v32f32",
                        ir.FunctionType(_vec(_F32), [_vec(_F32)]))
        r = builder.fptosi(builder.call(rint, [builder.fmul(d, _splat(builder, kv, _vec(_F32)))]),
                           _vec(_I32))
        top = ir.Constant(_vec(_I32), [255] * LANES)
        r = builder.select(builder.icmp_signed("<", r, top), r, top)
        m8 = builder.trunc(r, _vec(_I8))
        builder.store(m8, _at(builder, _data(context, builder, signature.args[5], mv), tv,
                              _vec(_I8)), align=1)
        if with_min:
            mp = _at(builder, _data(context, builder, signature.args[10], mmv), tv, _vec(_I8))
            old = builder.load(mp, align=1)
            builder.store(builder.select(builder.icmp_unsigned("<", m8, old), m8, old), mp,
                          align=1)
        hp = _at(builder, _data(context, builder, signature.args[7], hv), tv, _vec(_I16))
        lp = _at(builder, _data(context, builder, signature.args[8], lv), tv, _vec(_I16))
        h = builder.load(hp, align=2)
        lo_ = builder.load(lp, align=2)
        builder.store(builder.select(builder.icmp_signed(">", mx, h), mx, h), hp, align=2)
        builder.store(builder.select(builder.icmp_signed("<", mn, lo_), mn, lo_), lp, align=2)
        return context.get_dummy_value()

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
