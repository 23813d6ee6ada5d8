"""Haar bases on the light grid and the non-linear lighting approximation shared by the
wavelet schemes of :mod:`facegeo.lighting.compress` (private; the public names are re-exported
there). Ng, Ramamoorthi & Hanrahan 2003, §4 (non-standard decomposition) and §5 (non-linear
approximation of the lighting).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError


def _check_pow2(n_theta: int, n_phi: int) -> None:
    for name, n in (("n_theta", n_theta), ("n_phi", n_phi)):
        if n < 1 or n & (n - 1):
            raise InputError(f"{name}: the Haar basis needs a power of two, got {n}")


def _haar_step(x: np.ndarray, axis: int, n: int, inverse: bool) -> None:
    """One orthonormal Haar step in place on the first ``n`` entries of ``axis`` (−1 or −2) of
    ``x`` (forward: pairs → ``[averages | details]``; inverse: the reverse)."""
    r = np.sqrt(0.5)

    def sl(s: slice) -> tuple:
        return (Ellipsis, s) if axis == -1 else (Ellipsis, s, slice(None))

    if not inverse:
        a = x[sl(slice(0, n, 2))].copy()
        b = x[sl(slice(1, n, 2))]
        d = (a - b) * r
        a += b
        a *= r
        x[sl(slice(0, n // 2))] = a
        x[sl(slice(n // 2, n))] = d
    else:
        s = x[sl(slice(0, n // 2))].copy()
        d = x[sl(slice(n // 2, n))].copy()
        x[sl(slice(0, n, 2))] = (s + d) * r
        x[sl(slice(1, n, 2))] = (s - d) * r


def _nonstandard_levels(n_theta: int, n_phi: int) -> list[tuple[int, int, bool, bool]]:
    """The non-standard decomposition's levels: ``(h, w, step θ, step φ)`` per level."""
    levels = []
    h, w = n_phi, n_theta
    while h > 1 or w > 1:
        levels.append((h, w, w > 1, h > 1))
        h, w = max(1, h // 2), max(1, w // 2)
    return levels


def haar2d_nonstandard(x: Any, n_theta: int, n_phi: int, *, inverse: bool = False,
                       compiled: bool = False) -> np.ndarray:
    """Orthonormal **non-standard** 2-D Haar transform of light images (Ng et al. 2003 §4).

    At every level one Haar step runs along θ and along φ over the current low-pass block,
    then the recursion continues on its low-low quarter (when one side reaches 1 the other
    continues alone). Unlike the tensor-product (standard) transport of :func:`haar2d`, a point
    light (one cell) has only ``3·log₂(n_φ) + 2`` non-zero coefficients (17 on the 64 × 32 grid
    instead of 42), which is what makes a sun cheap to approximate.

    ``x`` is ``(..., L)`` in light-index order (``l = j·n_theta + i``); returns ``(..., L)``
    float64 (``inverse=True`` undoes it). ``compiled=True`` runs the forward transform in a numba
    loop when numba is installed (one lighting per relight: the numpy steps' overhead is
    ≈ 30 µs each).
    """
    _check_pow2(n_theta, n_phi)
    a = np.asarray(x, np.float64)
    img = np.array(a.reshape(a.shape[:-1] + (n_phi, n_theta)), np.float64, copy=True)
    levels = _nonstandard_levels(n_theta, n_phi)
    if compiled and not inverse and levels:
        from facegeo.lighting.relight import _fused_kernel

        if _fused_kernel():  # numba present
            from facegeo.lighting._fused import haar_nonstandard_forward

            flat = img.reshape((-1, n_phi, n_theta))
            haar_nonstandard_forward(flat, np.array(levels, np.int64))
            return flat.reshape(a.shape)
    for h, w, st, sp in (reversed(levels) if inverse else levels):
        block = img[..., :h, :w]
        if not inverse:
            if st:
                _haar_step(block, -1, w, False)
            if sp:
                _haar_step(block, -2, h, False)
        else:
            if sp:
                _haar_step(block, -2, h, True)
            if st:
                _haar_step(block, -1, w, True)
    return img.reshape(a.shape)


def lighting_order(wc: np.ndarray) -> np.ndarray:
    """Lighting coefficients ``(L, 3)`` by decreasing magnitude (summed over channels): the
    non-linear approximation's order (Ng et al. 2003)."""
    return np.argsort(-np.abs(wc).sum(axis=1), kind="stable")


def top_terms(wc: np.ndarray, k: int) -> np.ndarray:
    """The first ``k`` of :func:`lighting_order` (ties to the lower index) in O(L + k log k)."""
    mag = np.abs(wc).sum(axis=1)
    if k >= mag.size:
        return lighting_order(wc)
    kth = np.partition(mag, mag.size - k)[mag.size - k]  # the k-th largest magnitude
    above = np.flatnonzero(mag > kth)
    sel = np.concatenate([above, np.flatnonzero(mag == kth)[: k - above.size]])
    sel.sort()
    return sel[np.argsort(-mag[sel], kind="stable")]


def top_terms_index_order(wc: np.ndarray, k: int) -> np.ndarray:
    """The same set as :func:`top_terms` in increasing index (the stored slabs' order), without
    sorting by magnitude: one partition and one pass, compiled when numba is installed
    (measured 0.11 → ≈ 0.01 ms for L = 2048, a tenth of a compressed relight)."""
    from facegeo.lighting.relight import _fused_kernel

    if _fused_kernel():  # numba present
        from facegeo.lighting._compress_kernels import top_k_index_order

        return top_k_index_order(np.ascontiguousarray(wc, np.float64), int(k))
    return np.sort(top_terms(wc, k))


def selected_lighting_terms(model: Any, weights: Any, terms: int | None,
                            target_error: float | None, *,
                            index_order: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The K largest lighting coefficients of a wavelet-lighting model (Ng et al. 2003's
    non-linear approximation): K = ``terms``, or from ``model.budget(weights, target_error)``,
    or (neither) every non-zero coefficient. Returns their indices ``(K,)`` int64 and values
    ``(K, 3)`` float32, largest first (``index_order=True``: the same K in increasing index,
    for a sum whose order does not matter). ``model`` has ``lighting_coefficients`` and
    ``budget``.
    """
    if terms is not None and target_error is not None:
        raise InputError("relight: give terms or target_error, not both")
    wc = model.lighting_coefficients(weights)
    n_l = wc.shape[0]
    if target_error is not None:
        k, _ = model.budget(weights, target_error)
    elif terms is not None:
        k = int(terms)
        if not 1 <= k <= n_l:
            raise InputError(f"terms: expected 1 … {n_l}, got {fmt_value(terms)}")
    else:
        k = max(1, int(np.count_nonzero(np.abs(wc).sum(axis=1))))
    pick = top_terms_index_order if index_order else top_terms
    idx = np.ascontiguousarray(pick(wc, k), np.int64)
    return idx, np.ascontiguousarray(wc[idx], np.float32)
