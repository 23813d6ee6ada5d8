"""numba kernels of :class:`facegeo.lighting.compress.ImageWaveletField` (imported only when
numba is installed; the numpy fallbacks in :mod:`facegeo.lighting._compress_image` are the plain
reference implementations they are tested against).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from facegeo.lighting._fused import _FASTMATH

__all__ = ["haar_nonstandard_inverse", "scatter_slabs", "truncation_errors"]


@njit(inline="always", cache=True)
def _channel(code, c):  # pragma: no cover - compiled
    """Channel ``c`` of a packed entry (see ``_compress_image.encode_rgb``): its 9-bit two's
    complement field moved to the top and sign-extended by an arithmetic shift (branch-free:
    a branch on the sign mispredicts half the time, measured 8 ns an entry against ≈ 2)."""
    return np.float32(np.int32(code << np.uint32(23 - 9 * c)) >> np.int32(23))


@njit(nogil=True, cache=True, boundscheck=False, fastmath=_FASTMATH)
def scatter_slabs(ptr, n_seg, pos, code, pw, idx, lw, acc):  # pragma: no cover - compiled
    """``acc[c, 65536·g + pos[e]] += value(code[e], c) · lw[k, c]`` for the entries ``e`` of
    each selected light-coefficient slab ``j = idx[k]``, segment g
    (``ptr[j·n_seg + g] ≤ e < ptr[j·n_seg + g + 1]``).

    ``ptr`` ``(L·n_seg + 1,)`` int64, ``pos`` ``(n,)`` uint16 spatial coefficient index within
    its segment of 65536,
    ``code`` ``(n,)`` uint32 packed RGB (three 9-bit two's complement mantissas, a 5-bit
    shared exponent: value = mantissa · ``pw[exponent]``), ``pw`` ``(32,)`` float32, ``idx``
    ``(K,)`` int64, ``lw`` ``(K, 3)`` float32, ``acc`` ``(3, G)`` float32 (accumulated into).
    Entries of a slab are sorted by ``pos``, so the scatter walks ``acc`` forward.
    """
    for k in range(idx.size):
        j = idx[k]
        x0 = lw[k, 0]
        x1 = lw[k, 1]
        x2 = lw[k, 2]
        for e0 in range(j * n_seg, (j + 1) * n_seg):
            off = (e0 - j * n_seg) << 16
            for e in range(ptr[e0], ptr[e0 + 1]):
                s = off + np.int64(pos[e])
                v = code[e]
                p = pw[v >> np.uint32(27)]
                acc[0, s] += _channel(v, 0) * (p * x0)
                acc[1, s] += _channel(v, 1) * (p * x1)
                acc[2, s] += _channel(v, 2) * (p * x2)


@njit(nogil=True, cache=True, boundscheck=False, fastmath=_FASTMATH)
def haar_nonstandard_inverse(img, levels):  # pragma: no cover - compiled
    """In-place inverse non-standard 2-D Haar transform of ``img`` ``(C, H, W)`` float32.

    ``levels`` ``(n, 4)`` int64 rows ``(h, w, step θ, step φ)`` from
    :func:`facegeo.lighting._compress_haar._nonstandard_levels` (the columns' axis is the image's
    width here); the compiled twin of ``haar2d_nonstandard(..., inverse=True)``. The step along
    the rows' axis combines whole rows (contiguous, vectorised) through a row buffer.
    """
    r = np.float32(np.sqrt(0.5))
    n_c, n_h, n_w = img.shape
    rows = np.empty((n_h, n_w), np.float32)
    tmp = np.empty(n_w, np.float32)
    for lev in range(levels.shape[0] - 1, -1, -1):
        h = levels[lev, 0]
        w = levels[lev, 1]
        for c in range(n_c):
            if levels[lev, 3]:  # undo the step along the rows' axis first (reverse order)
                for i in range(h // 2):
                    s = img[c, i, :w]
                    d = img[c, h // 2 + i, :w]
                    a = rows[2 * i, :w]
                    b = rows[2 * i + 1, :w]
                    for x in range(w):
                        a[x] = (s[x] + d[x]) * r
                        b[x] = (s[x] - d[x]) * r
                for i in range(h):
                    img[c, i, :w] = rows[i, :w]
            if levels[lev, 2]:
                for y in range(h):
                    row = img[c, y]
                    for i in range(w // 2):
                        tmp[2 * i] = (row[i] + row[w // 2 + i]) * r
                        tmp[2 * i + 1] = (row[i] - row[w // 2 + i]) * r
                    row[:w] = tmp[:w]


@njit(nogil=True, cache=True, boundscheck=False)
def truncation_errors(ptr, n_seg, pos, code, pw, idx, lw, full):  # pragma: no cover
    """Squared error ``‖full − Σ_{k' ≤ k} slab idx[k']‖²`` after each slab ``k`` of ``idx``.

    Same entries and weights as :func:`scatter_slabs`; ``full`` ``(3, G)`` float32 is the sum
    over all of ``idx``. The residual is updated in place per entry (float64), so the error of
    every prefix costs one pass over the entries. Returns ``(K,)`` float64.
    """
    d = full.astype(np.float64)
    e2 = 0.0
    for c in range(3):
        for s in range(d.shape[1]):
            e2 += d[c, s] * d[c, s]
    out = np.empty(idx.size)
    for k in range(idx.size):
        j = idx[k]
        for e0 in range(j * n_seg, (j + 1) * n_seg):
            off = (e0 - j * n_seg) << 16
            for e in range(ptr[e0], ptr[e0 + 1]):
                s = off + np.int64(pos[e])
                p = pw[code[e] >> np.uint32(27)]
                for c in range(3):
                    old = d[c, s]
                    new = old - np.float64(_channel(code[e], c) * (p * lw[k, c]))
                    e2 += new * new - old * old
                    d[c, s] = new
        out[k] = max(e2, 0.0)
    return out
