"""Compiled weighted blend of float16 camera fields (private; :func:`reflectance.blend_fields`).

The blend ``R_b = Σ_c w_c R_c / Σ_c w_c`` over the finite samples of each texel, light and
channel, done on the fields' float16 bits: each camera's rows are widened in registers
(:func:`facegeo.surface._half.half_to_float32`, F16C where the CPU has it) and added into the
chunk's float32 numerator and denominator; the quotient is rounded back to float16 bits in one
more pass. The float32 operations are numpy's, in the same order (``w · x`` then the running
sum per camera; ``num / den``; a NaN where no camera has a finite sample), and the roundings
are numpy's casts, so the result is bit for bit the numpy path's
(``tests/test_reflectance.py``). Why compiled: numpy's float16 casts cost ≈ 2.7 ns (widen) and
≈ 6 ns (narrow) a value, most of the paper preset's 18–19 s blend of two cameras.
"""

from __future__ import annotations

from numba import njit

from facegeo.surface._half import float32_to_half, half_to_float32

__all__ = ["accumulate_rows", "quotient_rows"]


@njit(nogil=True, cache=True, boundscheck=False)
def accumulate_rows(bits, pos, w, num, den, f16c):  # pragma: no cover - compiled
    """``num[pos[i]] += w[i]·x``, ``den[pos[i]] += w[i]`` where ``x = bits[i]`` widened is finite.

    Parameters
    ----------
    bits : (n, m) uint16 — one camera's rows (float16 bits, ``m = L·3``)
    pos : (n,) int64 — their rows in ``num`` / ``den`` (each in range; unique)
    w : (n,) float32 — the camera's weights
    num, den : (U, m) float32 — updated
    f16c : bool
    """
    m = bits.shape[1]
    zero = num.dtype.type(0.0)
    for i in range(pos.size):
        b = bits[i]
        nu = num[pos[i]]
        de = den[pos[i]]
        wi = w[i]
        for j in range(m):
            x = half_to_float32(b[j], f16c)
            ok = (x - x) == zero  # finite
            nu[j] += wi * x if ok else zero
            de[j] += wi if ok else zero


@njit(nogil=True, cache=True, boundscheck=False, error_model="numpy")
def quotient_rows(num, den, out, f16c):  # pragma: no cover - compiled
    """``out = float16 bits of num / den`` where ``den > 0``, of NaN elsewhere.

    Parameters
    ----------
    num, den : (n, m) float32
    out : (n, m) uint16 — written
    f16c : bool
    """
    nan = num.dtype.type(float("nan"))
    zero = num.dtype.type(0.0)
    for i in range(num.shape[0]):
        a = num[i]
        d = den[i]
        o = out[i]
        for j in range(num.shape[1]):
            o[j] = float32_to_half(a[j] / d[j] if d[j] > zero else nan, f16c)
