"""Exact float16 ↔ float32 conversion in compiled (numba) code, one shared copy for every kernel.

Private. Reflectance fields are stored as float16 (``R.npy`` memory-maps, fitted maps); numpy's
casts run at ≈ 2.7 ns (half → float) and ≈ 6 ns (float → half) per value here, which a streamed
skin fit or relight of 10⁸–10⁹ values cannot afford. This module holds

* the scalar conversions :func:`half_to_float32` and :func:`float32_to_half`, inlined into any
  numba kernel that calls them (:mod:`facegeo.lighting._fused` widens halves in its relighting
  loops with :func:`half_to_float32`);
* two row kernels, :func:`decode_rows` and :func:`encode_rows` (``nogil``: callers' threads run
  them in parallel), and their Python wrappers :func:`halves_to_float32` and
  :func:`float32_to_halves` for arrays of any shape;
* a gathering decoder, :func:`decode_gather_rows` / :func:`gather_halves_to_float32`: chosen
  rows of a float16 array (a field's memory map) widened into a reused buffer in one pass,
  with each row's finiteness (the skin fit stage's read);
* the host check :func:`host_has_f16c`.

It sits in ``surface/`` because both ``appearance/`` and ``lighting/`` need it and neither may
import the other (``docs/design.md``, layering conventions ← … ← surface ← appearance, lighting).

Each conversion has two exact implementations, chosen per call by the ``f16c`` flag (a
loop-invariant branch that LLVM moves out of the loops, so each version vectorises on its own):

* ``f16c=True``: LLVM ``fpext half → float`` / ``fptrunc float → half``, which the vectoriser
  turns into the CPU's ``vcvtph2ps`` / ``vcvtps2ph`` (8 values per instruction); only on CPUs with
  F16C (:func:`host_has_f16c`).
* ``f16c=False``: integer bit manipulation for any CPU, computed without data-dependent branches
  (both candidate results, then selects).

Where numba compiles for a CPU without F16C (:func:`host_has_f16c` false, e.g.
``NUMBA_CPU_NAME=x86-64``) only the portable version is compiled and the flag is ignored: LLVM
lowers its ``half`` type there to a runtime call (``__extendhfsf2``) that numba cannot link, and
a kernel containing it aborted even when called with ``f16c=False`` (so did the relighting
kernel before this module). A compile-time flag (``numba.literally``) was tried instead: its
dispatch costs ≈ 16 ms per call. Numba keys its disk cache by CPU, so a cache built with F16C is
not loaded on a CPU without it.

Both directions equal numpy's casts for every input: ``half → float`` is exact for normals,
subnormals, ±0, ±inf and NaN; ``float → half`` rounds to nearest, ties to even, produces half
subnormals, overflows to ±inf from 65520 up (65519.99… rounds to 65504), keeps ±0 and ±inf, and
maps NaN to a quiet NaN of the same sign (the payload need not match: numpy and F16C keep its
top bits, the bit path returns ``0x7E00`` with the sign). ``tests/test_half.py`` checks every half
and the float32 neighbours of every rounding boundary against numpy. No ``fastmath`` in the row
kernels (the portable encoder's ``x + 0.5`` must round as IEEE says).

Numba caches compiled kernels on disk keyed by the calling module's source file: after editing
this module, clear the ``__pycache__`` of modules whose kernels inline its functions
(``lighting/_fused.py``).
"""

from __future__ import annotations

import functools

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic, overload

from facegeo.errors import InputError, ShapeError

__all__ = [
    "decode_gather_rows",
    "decode_rows",
    "encode_rows",
    "float32_to_half",
    "float32_to_halves",
    "gather_halves_to_float32",
    "half_to_float32",
    "halves_to_float32",
    "host_has_f16c",
]


@functools.lru_cache(maxsize=1)
def host_has_f16c() -> bool:
    """Whether numba compiles for a CPU with F16C (``vcvtph2ps`` / ``vcvtps2ph``): the host's
    features as numba's code generator sees them (``NUMBA_CPU_FEATURES`` when set, e.g. for a
    ``NUMBA_CPU_NAME=generic`` cache, which has none; no F16C when ``NUMBA_ENABLE_AVX=0``, F16C
    being a VEX instruction). ``False`` when that cannot be determined (the portable conversion
    is then used). Cached for the process."""
    try:
        from numba.core import config
        from numba.core.codegen import get_host_cpu_features

        features = config.CPU_FEATURES
        if features is None:
            features = get_host_cpu_features()
        return bool(config.ENABLE_AVX) and "+f16c" in str(features).split(",")
    except Exception:  # noqa: BLE001 - unknown host: use the portable conversion
        return False


@intrinsic
def _fpext_half(typingctx, x):  # pragma: no cover - compiled
    sig = types.float32(types.uint16)

    def codegen(context, builder, signature, args):
        return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())

    return sig, codegen


@intrinsic
def _fptrunc_half(typingctx, x):  # pragma: no cover - compiled
    sig = types.uint16(types.float32)

    def codegen(context, builder, signature, args):
        return builder.bitcast(builder.fptrunc(args[0], ir.HalfType()), ir.IntType(16))

    return sig, codegen


@intrinsic
def _bits_as_float32(typingctx, x):  # pragma: no cover - compiled
    sig = types.float32(types.uint32)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return sig, codegen


@intrinsic
def _float32_bits(typingctx, x):  # pragma: no cover - compiled
    sig = types.uint32(types.float32)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))

    return sig, codegen


@njit(inline="always", cache=True)
def _half_to_float32_bits(h16):  # pragma: no cover - compiled
    x = np.uint32(h16)
    em = x & np.uint32(0x7FFF)
    big = (em + np.uint32(0x400)) >> np.uint32(15)  # 1 for inf/NaN (exponent 31)
    bits = (((x & np.uint32(0x8000)) << np.uint32(16)) | (em << np.uint32(13))
            | (big * np.uint32(0x7F800000)))
    return _bits_as_float32(bits) * np.float32(5.192296858534828e33)  # × 2^112


@njit(inline="always", cache=True)
def _float32_to_half_bits(x):  # pragma: no cover - compiled
    u = _float32_bits(x)
    sign = (u >> np.uint32(16)) & np.uint32(0x8000)
    a = u & np.uint32(0x7FFFFFFF)
    odd = (a >> np.uint32(13)) & np.uint32(1)
    normal = (a - np.uint32(0x37FFF001) + odd) >> np.uint32(13)  # a - (112 << 23) + 0xFFF
    sub = _float32_bits(_bits_as_float32(a) + np.float32(0.5)) - np.uint32(0x3F000000)
    r = sub if a < np.uint32(0x38800000) else normal  # 0x38800000: 2^-14
    big = np.uint32(0x7E00) if a > np.uint32(0x7F800000) else np.uint32(0x7C00)
    r = big if a >= np.uint32(0x47800000) else r  # 0x47800000: 2^16
    return np.uint16((r | sign) & np.uint32(0xFFFF))


def half_to_float32(h16, f16c):
    """float16 bits ``h16`` (uint16) → float32, exactly (numpy's ``astype(np.float32)``).

    In numba code (inlined): ``f16c=True``: LLVM ``fpext`` (``vcvtph2ps``). ``f16c=False``:
    sign, exponent and mantissa moved into float32 position (exponent 31 → 255 for inf/NaN),
    reinterpreted and multiplied by 2^112, which rebiases normals and normalises subnormals in
    one exact float multiply.
    Called from Python (a reference, not used by the kernels): numpy's cast.
    """
    return np.uint16(h16).view(np.float16).astype(np.float32)


def float32_to_half(x, f16c):
    """float32 ``x`` → float16 bits (uint16), exactly numpy's ``np.float32(x).astype(np.float16)``
    (round to nearest even; NaN → a quiet NaN, payload need not match).

    In numba code (inlined): ``f16c=True``: LLVM ``fptrunc`` (``vcvtps2ph``). ``f16c=False``,
    on the bits of ``a = |x|`` (F. Giesen's round-to-nearest-even float → half):

    * ``a ≥ 2^16`` (65536, inf, NaN): ``0x7C00`` (inf), or ``0x7E00`` (NaN) above inf's bits;
    * ``a < 2^-14`` (half subnormal or zero): ``a + 0.5`` in float32 puts the value's multiple
      of 2^-24 (the half subnormal step) in the low mantissa bits, rounded to nearest even by
      the FPU; subtracting 0.5's bits leaves the half bits (0x400 when it rounds up to the
      smallest normal);
    * otherwise: rebias the exponent (−112 << 23) and add ``0xFFF`` plus the kept mantissa's
      lowest bit (ties to even) before dropping 13 bits; a carry rolls into the exponent, and
      65520 ≤ a < 65536 carries into exponent 31 with a zero mantissa: inf.

    All three are computed and selected (no data-dependent branches). Called from Python (a
    reference, not used by the kernels): numpy's cast.
    """
    with np.errstate(over="ignore"):
        return np.float32(x).astype(np.float16).view(np.uint16)


@overload(half_to_float32, inline="always")
def _half_to_float32_jit(h16, f16c):
    if not host_has_f16c():  # never LLVM's half type where it cannot be compiled
        return lambda h16, f16c: _half_to_float32_bits(h16)  # pragma: no cover - compiled

    def impl(h16, f16c):  # pragma: no cover - compiled
        if f16c:
            return _fpext_half(h16)
        return _half_to_float32_bits(h16)

    return impl


@overload(float32_to_half, inline="always")
def _float32_to_half_jit(x, f16c):
    if not host_has_f16c():
        return lambda x, f16c: _float32_to_half_bits(x)  # pragma: no cover - compiled

    def impl(x, f16c):  # pragma: no cover - compiled
        if f16c:
            return _fptrunc_half(x)
        return _float32_to_half_bits(x)

    return impl


@njit(nogil=True, cache=True, boundscheck=False)
def decode_rows(bits, out, f16c):  # pragma: no cover - compiled
    """``out[i, j] = half_to_float32(bits[i, j])``.

    Parameters
    ----------
    bits : (n, m) uint16, C-contiguous
        float16 values as their bits (``a.view(np.uint16)``; reshape other shapes to 2-D).
    out : (n, m) float32, C-contiguous
        Written.
    f16c : bool
        Use the CPU's F16C conversion (ignored where numba compiles for a CPU without it).
    """
    n, m = bits.shape
    for i in range(n):
        b = bits[i]
        o = out[i]
        for j in range(m):
            o[j] = half_to_float32(b[j], f16c)


@njit(nogil=True, cache=True, boundscheck=False)
def decode_gather_rows(bits, rows, out, finite, f16c):  # pragma: no cover - compiled
    """``out[q, j] = half_to_float32(bits[rows[q], j])`` and ``finite[q]`` = no infinity or NaN
    in that row, in one pass (no gathered float16 copy, no separate finiteness pass).

    Parameters
    ----------
    bits : (T, m) uint16, C-contiguous
        float16 values as their bits.
    rows : (n,) int64, each in [0, T) (not checked here: :func:`gather_halves_to_float32`)
    out : (n, m) float32, C-contiguous
    finite : (n,) bool
    f16c : bool
    """
    m = bits.shape[1]
    for q in range(rows.size):
        b = bits[rows[q]]
        o = out[q]
        # bit 15 of (exponent bits + 0x0400) is set only for an all-ones exponent (inf, NaN):
        # an integer OR reduction, which vectorises beside the conversion
        acc = np.int32(0)
        for j in range(m):
            h = b[j]
            acc |= (np.int32(h) & np.int32(0x7C00)) + np.int32(0x0400)
            o[j] = half_to_float32(h, f16c)
        finite[q] = (acc & np.int32(0x8000)) == 0


@njit(nogil=True, cache=True, boundscheck=False)
def encode_rows(x, out, f16c):  # pragma: no cover - compiled
    """``out[i, j] = float32_to_half(x[i, j])``: float16 bits, rounded as numpy rounds.

    Parameters
    ----------
    x : (n, m) float32, C-contiguous
    out : (n, m) uint16, C-contiguous
        Written with float16 bits (``a16.view(np.uint16)``).
    f16c : bool
        Use the CPU's F16C conversion (ignored where numba compiles for a CPU without it).
    """
    n, m = x.shape
    for i in range(n):
        a = x[i]
        o = out[i]
        for j in range(m):
            o[j] = float32_to_half(a[j], f16c)


def _rows(a: np.ndarray, *, readonly: bool = False) -> np.ndarray:
    """A C-contiguous array as a plain 2-D ndarray view of one row (the whole array: rows of the
    last axis — three values for an ``(N, L, 3)`` field — left the kernels' inner loops too
    short to vectorise, 2 ns a value against 0.3). ``readonly``: the view is marked read-only,
    so writable and read-only sources (a memory-map opened ``mode="r"``) share one compiled
    specialisation of the kernels."""
    v = np.asarray(a)
    v = v.reshape(1, -1)
    if readonly:
        v = v.view()
        v.flags.writeable = False
    return v


def _check_pair(src, name: str, dtype, out, out_name: str, out_dtype) -> None:
    """Validate a conversion's source and (optional) output array."""
    if not isinstance(src, np.ndarray) or src.dtype != dtype:
        got = src.dtype if isinstance(src, np.ndarray) else type(src).__name__
        raise ShapeError(f"{name}: expected a {np.dtype(dtype).name} ndarray, got {got}")
    if not src.flags.c_contiguous:
        raise ShapeError(f"{name}: expected a C-contiguous array (np.ascontiguousarray), got "
                         f"strides {src.strides} for shape {src.shape}")
    if out is None:
        return
    if not isinstance(out, np.ndarray) or out.dtype != out_dtype:
        got = out.dtype if isinstance(out, np.ndarray) else type(out).__name__
        raise ShapeError(f"{out_name}: expected a {np.dtype(out_dtype).name} ndarray, got {got}")
    if out.shape != src.shape:
        raise ShapeError(f"{out_name}: expected shape {src.shape} (that of {name}), got "
                         f"{out.shape}")
    if not out.flags.c_contiguous:
        raise ShapeError(f"{out_name}: expected a C-contiguous array, got strides "
                         f"{out.strides} for shape {out.shape}")
    if not out.flags.writeable:
        raise InputError(f"{out_name}: the array is read-only (a memory-map opened with "
                         f"mode='r'?); pass a writable array")
    if np.shares_memory(src, out):
        raise InputError(f"{out_name}: overlaps {name}; pass a separate output array")


def _convert(kernel, src, name: str, dtype, out, out_dtype) -> np.ndarray:
    """Validate, allocate ``out`` when ``None``, and run the row ``kernel`` on 2-D views (float16
    arrays as their uint16 bits)."""
    _check_pair(src, name, dtype, out, "out", out_dtype)
    if out is None:
        out = np.empty(src.shape, out_dtype)
    if src.size:
        bits = (lambda a: a.view(np.uint16) if a.dtype == np.float16 else a)
        kernel(_rows(bits(src), readonly=True), _rows(bits(out)), host_has_f16c())
    return out


def halves_to_float32(a16: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """float16 → float32, exactly as ``a16.astype(np.float32)``, compiled (F16C where the CPU
    has it).

    Parameters
    ----------
    a16 : (...) float16, C-contiguous
        Any shape (a ``numpy.memmap`` chunk is read in place).
    out : (...) float32, C-contiguous, writable, optional
        Same shape as ``a16``; allocated when ``None``.

    Returns
    -------
    (...) float32
        ``out``.

    Raises
    ------
    ShapeError
        Wrong dtype, a shape that differs from ``a16``'s, or a non-contiguous array.
    InputError
        ``out`` read-only or overlapping ``a16``.
    """
    return _convert(decode_rows, a16, "a16", np.float16, out, np.float32)


def float32_to_halves(a32: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """float32 → float16, exactly as ``a32.astype(np.float16)`` (round to nearest even, ±inf
    from 65520 up; NaN stays NaN), compiled (F16C where the CPU has it).

    Parameters
    ----------
    a32 : (...) float32, C-contiguous
        Any shape.
    out : (...) float16, C-contiguous, writable, optional
        Same shape as ``a32`` (e.g. a chunk of a float16 ``numpy.memmap`` opened ``r+``/``w+``);
        allocated when ``None``.

    Returns
    -------
    (...) float16
        ``out``.

    Raises
    ------
    ShapeError
        Wrong dtype, a shape that differs from ``a32``'s, or a non-contiguous array.
    InputError
        ``out`` read-only or overlapping ``a32``.
    """
    return _convert(encode_rows, a32, "a32", np.float32, out, np.float16)


def gather_halves_to_float32(a16: np.ndarray, rows, out: np.ndarray) -> np.ndarray:
    """Rows ``rows`` of a float16 array widened to float32 into ``out``, exactly as
    ``a16[rows].astype(np.float32)``, in one compiled pass; returns each row's finiteness.

    Parameters
    ----------
    a16 : (T, ...) float16, C-contiguous
        E.g. a reflectance field's memory map (read in place, never written).
    rows : (n,) int array_like, each in [0, T)
    out : (n, ...) float32, C-contiguous, writable
        The trailing shape of ``a16``; not overlapping it.

    Returns
    -------
    (n,) bool
        True where the row holds no infinity or NaN.

    Raises
    ------
    ShapeError
        Wrong dtypes or shapes, a non-contiguous array.
    InputError
        A row index out of range; ``out`` read-only or overlapping ``a16``.
    """
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    if rows.ndim != 1:
        raise ShapeError(f"rows: expected a 1-D index array, got shape {rows.shape}")
    if not isinstance(a16, np.ndarray) or a16.dtype != np.float16 or a16.ndim < 1:
        got = a16.dtype if isinstance(a16, np.ndarray) else type(a16).__name__
        raise ShapeError(f"a16: expected a float16 ndarray, got {got}")
    T = a16.shape[0]
    if rows.size and (rows.min() < 0 or rows.max() >= T):
        raise InputError(f"rows: expected indices in [0, {T}), got {rows.min()}..{rows.max()}")
    if not isinstance(out, np.ndarray) or out.shape != (rows.size,) + a16.shape[1:]:
        got = out.shape if isinstance(out, np.ndarray) else type(out).__name__
        raise ShapeError(f"out: expected shape {(rows.size,) + a16.shape[1:]}, got {got}")
    _check_pair(a16, "a16", np.float16, None, "out", np.float32)
    if out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ShapeError(f"out: expected a C-contiguous float32 array, got {out.dtype}")
    if not out.flags.writeable:
        raise InputError("out: the array is read-only; pass a writable array")
    if np.shares_memory(a16, out):
        raise InputError("out: overlaps a16; pass a separate output array")
    finite = np.ones(rows.size, bool)
    if rows.size and out.size:
        m = int(np.prod(a16.shape[1:], dtype=np.int64))
        bits = a16.view(np.uint16).reshape(T, m)
        bits.flags.writeable = False  # one specialisation for writable and read-only sources
        decode_gather_rows(bits, rows, out.reshape(rows.size, m), finite, host_has_f16c())
    return finite
