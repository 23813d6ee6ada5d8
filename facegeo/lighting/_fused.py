"""The fused float16 relighting kernel (numba): Eq. (4) of Debevec et al. 2000 on float16 rows,
each half widened to float32 in registers and multiplied into three channel accumulators in
the same pass. Private to :mod:`facegeo.lighting.relight` (imported only when numba is
installed); see :func:`facegeo.lighting.relight.relight_field` and ``docs/lighting.md``.

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
from numba import njit

from facegeo.surface._half import half_to_float32 as _half

__all__ = ["fused_half_dot"]

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
