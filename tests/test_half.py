"""The shared float16 ↔ float32 conversion (``facegeo.surface._half``): both kernels, both
implementations (F16C where the CPU has it, and the portable bit path), against numpy's casts.

Metric everywhere: bit-exact equality with numpy (``astype``) on the uint16 / uint32 bit
patterns; NaN compared as "is NaN" only (numpy keeps a NaN's top payload bits, F16C and the bit
path return the canonical quiet NaN). No tolerance: any rounding difference is a failure.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from facegeo.errors import InputError, ShapeError

pytest.importorskip("numba")
H = pytest.importorskip("facegeo.surface._half")

#: Random float32 values in the encode test, drawn over every exponent a half can reach and
#: beyond (2^-30 … 2^20, both signs, random mantissas).
N_RANDOM = 1_200_000
#: Rows per test batch: not a multiple of a SIMD width, so vector bodies and scalar remainders
#: both run.
ROW = 1021


def _f16c_values():
    """The conversions to test: the portable one always, F16C only on CPUs that have it."""
    return [False, pytest.param(True, marks=pytest.mark.skipif(
        not H.host_has_f16c(), reason="this CPU has no F16C"))]


def _as_rows(a: np.ndarray) -> np.ndarray:
    """Pad a 1-D array to a multiple of :data:`ROW` and reshape to ``(n, ROW)`` (C order)."""
    pad = (-a.size) % ROW
    return np.resize(a, a.size + pad).reshape(-1, ROW)  # pads by repeating a


def _encode(x32: np.ndarray, f16c: bool) -> np.ndarray:
    rows = _as_rows(x32)
    out = np.empty(rows.shape, np.uint16)
    H.encode_rows(rows, out, f16c)
    return out.reshape(-1)[:x32.size]


def _decode(bits: np.ndarray, f16c: bool) -> np.ndarray:
    rows = _as_rows(bits)
    out = np.empty(rows.shape, np.float32)
    H.decode_rows(rows, out, f16c)
    return out.reshape(-1)[:bits.size]


def _numpy_half_bits(x32: np.ndarray) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # overflow to inf is the point
        return x32.astype(np.float16).view(np.uint16)


def _assert_encode_matches_numpy(x32: np.ndarray, f16c: bool) -> None:
    got = _encode(x32, f16c)
    want = _numpy_half_bits(x32)
    nan = np.isnan(x32)
    assert np.all(np.isnan(got[nan].view(np.float16)))
    bad = np.flatnonzero((got != want) & ~nan)
    assert bad.size == 0, (f"{bad.size} values differ from numpy, e.g. x={x32[bad[:5]]!r} "
                           f"got {got[bad[:5]]} want {want[bad[:5]]}")


@pytest.mark.parametrize("f16c", _f16c_values())
def test_decode_equals_numpy_for_every_half(f16c):
    bits = np.arange(65536, dtype=np.uint16)
    got = _decode(bits, f16c)
    want = bits.view(np.float16).astype(np.float32)
    nan = np.isnan(want)
    assert np.array_equal(np.isnan(got), nan)
    assert np.array_equal(got[~nan].view(np.uint32), want[~nan].view(np.uint32))  # ±0 too


def _boundary_values() -> np.ndarray:
    """Every half widened, every midpoint between consecutive halves of one sign, and the
    float32 neighbours (nextafter down/up) of both; both signs."""
    h = np.arange(0x7C01, dtype=np.uint16).view(np.float16).astype(np.float32)  # 0 … inf
    lo, hi = h[:-1].astype(np.float64), h[1:].astype(np.float64)
    mid = ((lo + hi) / 2).astype(np.float32)  # exact in float32 (one more mantissa bit)
    pos = np.concatenate([h, mid])
    pos = np.concatenate([pos, np.nextafter(pos, np.float32(0)),
                          np.nextafter(pos, np.float32(np.inf))])
    return np.concatenate([pos, -pos])


def _special_values() -> np.ndarray:
    f32 = np.float32
    tiny = np.finfo(np.float32).smallest_subnormal
    vals = [0.0, 65504.0, 65519.99, np.nextafter(f32(65520), f32(0)), 65520.0, 65535.99, 65536.0,
            70000.0, 1e6, 3.0e38, np.finfo(np.float32).max, np.inf, np.nan,
            2.0 ** -24, 2.0 ** -25, np.nextafter(f32(2.0 ** -25), f32(1)), 2.0 ** -26,
            2.0 ** -14, 2.0 ** -14 - 2.0 ** -25, 1e-30, tiny, tiny * 7,
            np.finfo(np.float32).tiny, 1.0, 1.0 + 2.0 ** -11, 1.0 + 3 * 2.0 ** -11]
    x = np.array(vals, np.float32)
    x = np.concatenate([x, -x])
    # float32 subnormals densely (all of them round to ±0 in a half)
    sub = np.arange(1, 1 << 23, 97, dtype=np.uint32).view(np.float32)
    # NaNs with assorted payloads, quiet and signalling, both signs
    nan = np.array([0x7FC00000, 0x7F800001, 0x7FBFFFFF, 0x7FFFFFFF, 0x7FC01234],
                   np.uint32).view(np.float32)
    return np.concatenate([x, sub, -sub, nan, -nan])


def _random_values() -> np.ndarray:
    rng = np.random.default_rng(20001)
    mant = rng.integers(0, 1 << 23, N_RANDOM, dtype=np.uint32)
    exp = rng.integers(127 - 30, 127 + 21, N_RANDOM, dtype=np.uint32)
    sign = rng.integers(0, 2, N_RANDOM, dtype=np.uint32)
    return ((sign << 31) | (exp << 23) | mant).view(np.float32)


def _subnormal_range() -> np.ndarray:
    """The half subnormal range (|x| < 2^-14, step 2^-24) and a little beyond, densely: every
    1/16 of a half subnormal step, and every 499th float32 from 2^-25 to 1.01 · 2^-14."""
    step = np.arange(0, 16 * 1024 * 1.01) * 2.0 ** -28
    lo = np.float32(2.0 ** -25).view(np.uint32)
    hi = np.float32(2.0 ** -14 * 1.01).view(np.uint32)
    swept = np.arange(lo, hi, 499, dtype=np.uint32).view(np.float32)
    return np.concatenate([step.astype(np.float32), swept])


@pytest.mark.parametrize("f16c", _f16c_values())
def test_encode_equals_numpy_at_every_rounding_boundary(f16c):
    _assert_encode_matches_numpy(_boundary_values(), f16c)


@pytest.mark.parametrize("f16c", _f16c_values())
def test_encode_equals_numpy_on_special_subnormal_and_random_values(f16c):
    x = np.concatenate([_special_values(), _subnormal_range(), _random_values()])
    _assert_encode_matches_numpy(x, f16c)
    got = _encode(np.array([0.0, -0.0, np.inf, -np.inf, 65520.0, -65520.0], np.float32), f16c)
    assert list(got) == [0x0000, 0x8000, 0x7C00, 0xFC00, 0x7C00, 0xFC00]  # ±0 and ±inf kept


@pytest.mark.parametrize("f16c", _f16c_values())
def test_round_trip_keeps_every_half(f16c):
    bits = np.arange(65536, dtype=np.uint16)
    back = _encode(_decode(bits, f16c), f16c)
    nan = np.isnan(bits.view(np.float16))
    assert np.array_equal(back[~nan], bits[~nan])
    assert np.all(np.isnan(back[nan].view(np.float16)))


def test_wrappers_convert_any_shape_in_place_and_equal_numpy():
    rng = np.random.default_rng(3)
    x32 = (rng.standard_normal((4, 5, 7)) * 300).astype(np.float32)
    x32[0, 0, 0] = np.nan
    h = H.float32_to_halves(x32)
    assert h.dtype == np.float16 and h.shape == x32.shape
    assert np.array_equal(h.view(np.uint16)[1:], _numpy_half_bits(x32)[1:])
    out = np.full(x32.shape, -1.0, np.float32)
    back = H.halves_to_float32(h, out)
    assert back is out
    assert np.array_equal(out, h.astype(np.float32), equal_nan=True)
    out16 = np.empty(x32.shape, np.float16)
    assert H.float32_to_halves(x32, out16) is out16
    assert np.array_equal(out16.view(np.uint16)[1:], h.view(np.uint16)[1:])
    # 1-D, 0-d and empty arrays; a read-only float16 source (a memory-map opened mode="r")
    ro = h.reshape(-1).copy()
    ro.flags.writeable = False
    assert np.array_equal(H.halves_to_float32(ro), ro.astype(np.float32), equal_nan=True)
    assert H.halves_to_float32(np.array(np.float16(1.5))) == np.float32(1.5)
    assert H.float32_to_halves(np.zeros((0, 3), np.float32)).shape == (0, 3)


def test_float16_memmap_chunks_convert_in_place(tmp_path):
    path = tmp_path / "R.npy"
    mm = np.lib.format.open_memmap(path, mode="w+", dtype=np.float16, shape=(6, 4, 3))
    x32 = np.linspace(-70000, 70000, 72, dtype=np.float32).reshape(6, 4, 3)
    H.float32_to_halves(x32[2:5], mm[2:5])
    mm.flush()
    del mm
    ro = np.load(path, mmap_mode="r")
    assert np.array_equal(ro[2:5].view(np.uint16), _numpy_half_bits(x32[2:5]))
    assert np.array_equal(H.halves_to_float32(ro[2:5]), ro[2:5].astype(np.float32))


@pytest.mark.parametrize("f16c", _f16c_values())
def test_gather_decode_equals_numpy_and_finds_non_finite_rows(f16c):
    """decode_gather_rows: every half (64 rows of 1024) gathered in a shuffled order with
    repeats equals numpy's take-then-cast, and each row's finiteness equals numpy's (rows
    holding ±inf or NaN are not finite; the largest finite halves and subnormals are)."""
    bits = np.arange(65536, dtype=np.uint16).reshape(64, 1024)
    rng = np.random.default_rng(7)
    rows = np.concatenate([rng.permutation(64), [3, 3, 63]]).astype(np.int64)
    out = np.empty((rows.size, 1024), np.float32)
    finite = np.empty(rows.size, bool)
    H.decode_gather_rows(bits, rows, out, finite, f16c)
    want = bits.view(np.float16)[rows].astype(np.float32)
    assert np.array_equal(out, want, equal_nan=True)
    assert np.array_equal(finite, np.isfinite(want).all(axis=1))
    assert 0 < finite.sum() < rows.size  # both kinds present


def test_gather_wrapper_reads_a_memmap_and_rejects_bad_arguments(tmp_path):
    path = tmp_path / "R.npy"
    mm = np.lib.format.open_memmap(path, mode="w+", dtype=np.float16, shape=(9, 4, 3))
    mm[...] = np.arange(108, dtype=np.float16).reshape(9, 4, 3)
    mm[5, 2, 1] = np.nan
    mm.flush()
    del mm
    ro = np.load(path, mmap_mode="r")
    out = np.full((3, 4, 3), -1.0, np.float32)
    ok = H.gather_halves_to_float32(ro, [8, 5, 0], out)
    assert np.array_equal(out, ro[[8, 5, 0]].astype(np.float32), equal_nan=True)
    assert ok.tolist() == [True, False, True]
    with pytest.raises(InputError, match=r"rows: expected indices in \[0, 9\), got 0\.\.9"):
        H.gather_halves_to_float32(ro, [0, 9], np.empty((2, 4, 3), np.float32))
    with pytest.raises(ShapeError, match=r"out: expected shape \(2, 4, 3\)"):
        H.gather_halves_to_float32(ro, [0, 1], np.empty((2, 12), np.float32))
    with pytest.raises(ShapeError, match=r"a16: expected a float16 ndarray, got float32"):
        H.gather_halves_to_float32(out, [0], out[:1])
    buf = np.zeros(48, np.float32)
    with pytest.raises(InputError, match=r"out: overlaps a16"):
        H.gather_halves_to_float32(buf.view(np.float16).reshape(8, 12), [0],
                                   buf[12:24].reshape(1, 12))


def test_wrappers_reject_bad_arrays_naming_the_argument():
    x32 = np.zeros((4, 6), np.float32)
    x16 = np.zeros((4, 6), np.float16)
    with pytest.raises(ShapeError, match=r"a16: expected a float16 ndarray, got float32"):
        H.halves_to_float32(x32)
    with pytest.raises(ShapeError, match=r"a32: expected a float32 ndarray, got float64"):
        H.float32_to_halves(np.zeros(3))
    with pytest.raises(ShapeError, match=r"a32: expected a float32 ndarray, got list"):
        H.float32_to_halves([1.0])
    with pytest.raises(ShapeError, match=r"a16: expected a C-contiguous"):
        H.halves_to_float32(x16[:, ::2])
    with pytest.raises(ShapeError, match=r"out: expected shape \(4, 6\)"):
        H.halves_to_float32(x16, np.empty((6, 4), np.float32))
    with pytest.raises(ShapeError, match=r"out: expected a float16 ndarray, got uint16"):
        H.float32_to_halves(x32, np.empty((4, 6), np.uint16))
    with pytest.raises(ShapeError, match=r"out: expected a C-contiguous"):
        H.float32_to_halves(x32, np.empty((4, 6), np.float16, order="F"))
    ro = np.empty((4, 6), np.float16)
    ro.flags.writeable = False
    with pytest.raises(InputError, match=r"out: the array is read-only"):
        H.float32_to_halves(x32, ro)
    buf = np.zeros(48, np.float32)
    with pytest.raises(InputError, match=r"out: overlaps a16"):
        H.halves_to_float32(buf[:24].view(np.float16).reshape(4, 12), buf[:48].reshape(4, 12))


@pytest.mark.slow
def test_kernels_compile_and_stay_exact_for_a_cpu_without_f16c(baseline_cpu_python):
    """Numba compiling for a CPU without F16C (``NUMBA_CPU_NAME=x86-64``, a fresh disk cache, in
    a fresh interpreter): the kernels must not contain LLVM's ``half`` type (lowered there to an
    unlinkable ``__extendhfsf2`` call: the process aborted or crashed, even with
    ``f16c=False``), the host check must say no F16C, and the portable conversions must equal
    numpy (bit-exact, every half both ways; the relighting kernel too, which inlines the
    decoder)."""
    code = (
        "import numpy as np, warnings\n"
        "warnings.simplefilter('ignore')\n"
        "from facegeo.surface import _half as H\n"
        "from facegeo.lighting import relight as R\n"
        "assert not H.host_has_f16c() and not R._host_has_f16c()\n"
        "h = np.arange(65536, dtype=np.uint16).view(np.float16).reshape(64, 1024)\n"
        "f = H.halves_to_float32(h)\n"
        "ok = ~np.isnan(f)\n"
        "assert np.array_equal(f[ok], h.astype(np.float32)[ok])\n"
        "back = H.float32_to_halves(f)\n"
        "assert np.array_equal(back.view(np.uint16)[ok], h.view(np.uint16)[ok])\n"
        "field = np.repeat(h.reshape(-1, 1, 1), 3, axis=2)\n"
        "got = R.relight_field(field, np.ones((1, 3)), kernel='fused')[:, 0]\n"
        "assert np.array_equal(got[ok.ravel()], f.ravel()[ok.ravel()])\n"
        "print('ok')\n")
    out = baseline_cpu_python(code)
    assert out.returncode == 0 and out.stdout.strip() == "ok", (out.returncode, out.stderr[-2000:])
