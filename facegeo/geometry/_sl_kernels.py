"""Compiled per-frame kernels of the streaming structured-light decoder (numba).

Each kernel makes one pass over a frame, where the numpy version of the same update
(:func:`lum_reference`, :func:`pair_reference`, used by the tests as the plain reference) makes
five to twelve. Compiled lazily on first use (``cache=True``: once per machine).
"""

from __future__ import annotations

import functools

import numpy as np

__all__ = ["lum_reference", "luminance", "pair_reference", "pair_update"]


@functools.cache
def _kernels():
    from numba import njit

    @njit(cache=True, nogil=True, boundscheck=False)
    def lum(a, scale, out):  # pragma: no cover - compiled
        H, W, C = a.shape
        for i in range(H):
            for j in range(W):
                s = np.float32(0.0)
                for c in range(C):
                    s += np.float32(a[i, j, c])
                out[i, j] = s * scale

    @njit(cache=True, nogil=True, boundscheck=False)
    def pair(pos, neg, words, bitval, margin, steps, lmax, lmin):  # pragma: no cover
        H, W = pos.shape
        for i in range(H):
            for j in range(W):
                p = pos[i, j]
                q = neg[i, j]
                d = p - q
                if d > 0:
                    words[i, j] |= bitval
                m = abs(d) * steps
                m = min(m, 255.0)
                margin[i, j] = np.uint8(np.rint(m))
                hi = max(q, p)
                lo = min(p, q)
                lmax[i, j] = max(lmax[i, j], hi)
                lmin[i, j] = min(lmin[i, j], lo)

    return lum, pair


def luminance(a: np.ndarray, scale: float) -> np.ndarray:
    """Channel sum of an (H, W, C) frame times ``scale``, float32 (H, W)."""
    out = np.empty(a.shape[:2], np.float32)
    _kernels()[0](np.ascontiguousarray(a), np.float32(scale), out)
    return out


def pair_update(pos, neg, words, bit: int, margin, steps: float, lmax, lmin) -> None:
    """Fold a pattern / inverse pair into the accumulators in place (see ``pair_reference``)."""
    _kernels()[1](pos, neg, words, words.dtype.type(1 << bit), margin, np.float32(steps),
                  lmax, lmin)


def lum_reference(a: np.ndarray, scale: float) -> np.ndarray:
    """Plain numpy :func:`luminance`."""
    return (a.astype(np.float32).sum(axis=2) * np.float32(scale)).astype(np.float32)


def pair_reference(pos, neg, words, bit: int, margin, steps: float, lmax, lmin) -> None:
    """Plain numpy :func:`pair_update`: the decision ``pos > neg`` sets ``bit`` of ``words``,
    ``margin = min(rint(|pos - neg| · steps), 255)`` as uint8, and both frames enter the running
    ``lmax`` / ``lmin``."""
    d = pos - neg
    words |= ((d > 0).astype(words.dtype) << words.dtype.type(bit))
    margin[...] = np.rint(np.minimum(np.abs(d) * np.float32(steps), 255.0)).astype(np.uint8)
    np.maximum(lmax, np.maximum(pos, neg), out=lmax)
    np.minimum(lmin, np.minimum(pos, neg), out=lmin)
