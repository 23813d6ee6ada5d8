"""Compiled per-frame kernels of the streaming structured-light decoder (numba).

Each kernel makes one pass over a frame, where the numpy version of the same update
(:func:`lum_reference`, :func:`pair_reference`, :func:`phase_reference`, used by the tests as
the plain reference) makes five to twelve. Compiled lazily on first use (``cache=True``: once
per machine).

**8-bit / 16-bit frames are read once.** For ``uint8`` / ``uint16`` frames the decoder
materialises no float32 luminance plane for a pattern / inverse pair or a phase frame:

* the first frame of a pair is reduced to its exact integer channel sum (:func:`channel_sum`,
  uint16 for 8-bit frames, uint32 for 16-bit ones — half / the same bytes as the float32
  luminance, and the frame itself can be dropped at once);
* the second frame and that sum go through :func:`pair_update` together: both luminances
  ``float32(channel sum) · scale`` are formed in registers, then the decision bit, the uint8
  margin and the running ``L_max`` / ``L_min`` are written;
* a phase frame goes through :func:`phase_update` (luminance, the three phase sums and the
  running maximum in one pass).

The luminance is bit-for-bit the one :func:`luminance` computes (a channel sum of integers
below 2**24 is exact in float32 whichever order it is summed in), so the decode does not change.

Threads: the kernels are ``parallel=True`` over image rows (``prange``); they use as many
threads as numba has (``numba.set_num_threads``; 2 on the project machine by default).
"""

from __future__ import annotations

import functools

import numpy as np

__all__ = ["channel_sum", "lum_reference", "luminance", "pair_reference", "pair_update",
           "phase_reference", "phase_update", "sum_dtype"]


@functools.cache
def _kernels():
    from numba import njit, prange

    @njit(cache=True, nogil=True, boundscheck=False, inline="always")
    def _lum_at(a, i, j, scale):  # pragma: no cover - compiled
        s = np.float32(0.0)
        for c in range(a.shape[2]):
            s += np.float32(a[i, j, c])
        return s * scale

    @njit(cache=True, nogil=True, boundscheck=False, inline="always")
    def _lum_at_int(a, i, j, scale):  # pragma: no cover - compiled
        # integer frames / channel sums below 2**24: the integer sum is exact, and so is its
        # float32 conversion -- the same value _lum_at forms, one conversion instead of C
        s = np.int64(0)
        for c in range(a.shape[2]):
            s += np.int64(a[i, j, c])
        return np.float32(s) * scale

    def make_pair(lum_at):
        @njit(cache=True, nogil=True, boundscheck=False, parallel=True)
        def pair(pos, ps, neg, ns, words, bitval, margin, steps, lmax, lmin):  # pragma: no cover
            H, W, _ = pos.shape
            for i in prange(H):
                for j in range(W):
                    p = lum_at(pos, i, j, ps)
                    q = lum_at(neg, i, j, ns)
                    d = p - q
                    if d > 0:
                        words[i, j] |= bitval
                    m = abs(d) * steps
                    m = min(m, np.float32(255.0))
                    margin[i, j] = np.uint8(np.rint(m))
                    hi = max(q, p)
                    lo = min(p, q)
                    lmax[i, j] = max(lmax[i, j], hi)
                    lmin[i, j] = min(lmin[i, j], lo)
        return pair

    @njit(cache=True, nogil=True, boundscheck=False, parallel=True)
    def lum(a, scale, out):  # pragma: no cover - compiled
        H, W, _ = a.shape
        for i in prange(H):
            for j in range(W):
                out[i, j] = _lum_at(a, i, j, scale)

    @njit(cache=True, nogil=True, boundscheck=False, parallel=True)
    def csum(a, out):  # pragma: no cover - compiled
        H, W, C = a.shape
        for i in prange(H):
            for j in range(W):
                s = np.uint32(0)
                for c in range(C):
                    s += np.uint32(a[i, j, c])
                out[i, j, 0] = s

    @njit(cache=True, nogil=True, boundscheck=False, parallel=True)
    def phase(a, scale, sk, ck, S, C, A, pmax):  # pragma: no cover - compiled
        H, W, _ = a.shape
        for i in prange(H):
            for j in range(W):
                v = _lum_at_int(a, i, j, scale)
                m = pmax[i, j]
                if not v <= m:  # np.maximum: NaN propagates
                    pmax[i, j] = v if (v > m or v != v) else m
                S[i, j] += sk * v
                C[i, j] += ck * v
                A[i, j] += v

    return lum, csum, make_pair(_lum_at), phase, make_pair(_lum_at_int)


def _as3(a: np.ndarray) -> np.ndarray:
    return a[:, :, None] if a.ndim == 2 else a


def sum_dtype(dtype, channels: int):
    """Integer dtype that holds a pixel's channel sum exactly *and* below 2**24 (so its float32
    conversion is exact too), or None when the frame must take the float32 luminance path."""
    dtype = np.dtype(dtype)
    if dtype == np.uint8 and channels <= 257:
        return np.dtype(np.uint16)
    if dtype == np.uint16 and channels <= 256:
        return np.dtype(np.uint32)
    return None


def luminance(a: np.ndarray, scale: float) -> np.ndarray:
    """Channel sum of an (H, W, C) frame times ``scale``, float32 (H, W)."""
    out = np.empty(a.shape[:2], np.float32)
    _kernels()[0](_as3(np.ascontiguousarray(a)), np.float32(scale), out)
    return out


def channel_sum(a: np.ndarray) -> np.ndarray:
    """Exact integer channel sum of a uint8 / uint16 (H, W[, C]) frame, as (H, W, 1) of
    :func:`sum_dtype` (the stored half of a pattern / inverse pair)."""
    a = _as3(a)
    out = np.empty(a.shape[:2] + (1,), sum_dtype(a.dtype, a.shape[2]))
    _kernels()[1](a, out)
    return out


def pair_update(pos, neg, words, bit: int, margin, steps: float, lmax, lmin, *,
                pos_scale: float = 1.0, neg_scale: float = 1.0) -> None:
    """Fold a pattern / inverse pair into the accumulators in place (see ``pair_reference``).

    ``pos`` / ``neg``: (H, W) float32 luminance, or an (H, W[, C]) frame / a
    :func:`channel_sum`, whose luminance is its channel sum times ``pos_scale`` / ``neg_scale``
    (formed in registers, as :func:`luminance` would)."""
    pos, neg = _as3(pos), _as3(neg)
    integer = pos.dtype.kind in "iu" and neg.dtype.kind in "iu"
    _kernels()[4 if integer else 2](pos, np.float32(pos_scale), neg, np.float32(neg_scale), words,
                  words.dtype.type(1 << bit), margin, np.float32(steps), lmax, lmin)


def phase_update(a, scale: float, sin_k: float, cos_k: float, S, C, A, pmax) -> None:
    """Fold a phase frame (its luminance = channel sum times ``scale``) into the phase sums in
    place (see ``phase_reference``).

    ``a``: an (H, W[, C]) uint8 / uint16 frame (exact integer channel sums), or float32 (H, W)
    luminance with ``scale`` 1."""
    a = _as3(a)
    if a.dtype.kind == "f":
        phase_reference(a, scale, sin_k, cos_k, S, C, A, pmax)
        return
    _kernels()[3](_as3(a), np.float32(scale), np.float32(sin_k), np.float32(cos_k), S, C, A,
                  pmax)


def lum_reference(a: np.ndarray, scale: float) -> np.ndarray:
    """Plain numpy :func:`luminance`."""
    return (_as3(a).astype(np.float32).sum(axis=2) * np.float32(scale)).astype(np.float32)


def pair_reference(pos, neg, words, bit: int, margin, steps: float, lmax, lmin, *,
                   pos_scale: float = 1.0, neg_scale: float = 1.0) -> None:
    """Plain numpy :func:`pair_update`: the decision ``pos > neg`` sets ``bit`` of ``words``,
    ``margin = min(rint(|pos - neg| · steps), 255)`` as uint8, and both frames enter the running
    ``lmax`` / ``lmin``."""
    pos = lum_reference(pos, pos_scale)
    neg = lum_reference(neg, neg_scale)
    d = pos - neg
    words |= ((d > 0).astype(words.dtype) << words.dtype.type(bit))
    margin[...] = np.rint(np.minimum(np.abs(d) * np.float32(steps), 255.0)).astype(np.uint8)
    np.maximum(lmax, np.maximum(pos, neg), out=lmax)
    np.minimum(lmin, np.minimum(pos, neg), out=lmin)


def phase_reference(a, scale: float, sin_k: float, cos_k: float, S, C, A, pmax) -> None:
    """Plain numpy :func:`phase_update`: ``S += sin_k L``, ``C += cos_k L``, ``A += L``,
    ``pmax = max(pmax, L)`` with ``L`` the frame's luminance."""
    lum = lum_reference(a, scale)
    np.maximum(pmax, lum, out=pmax)
    S += np.float32(sin_k) * lum
    C += np.float32(cos_k) * lum
    A += lum
