"""Relighting from a field compressed in the light domain *and* across the image (private to
:mod:`facegeo.lighting.compress`, which re-exports :class:`ImageWaveletField` and
:func:`fit_image_wavelet`).

The transport of an image-space field is a 4-D signal: two light coordinates (φ, θ) and two
image coordinates (row, column). Each reflectance function goes to the non-standard Haar basis
of the light image (Ng, Ramamoorthi & Hanrahan 2003); each resulting coefficient, seen across
the pixels, is an image ("slab" j), which goes to the non-standard Haar basis of the image
grid — the spatial (JPEG-domain) compression of Smith & Rowe 1993 that the paper's "factor of
twenty" refers to, with Haar instead of the 8 × 8 DCT. Both bases are orthonormal, so one global
magnitude threshold on the 4-D coefficients drops exactly the squared error it says (Parseval),
and a relight is, by linearity,

    relit image = H_s⁻¹ ( Σ_{j ∈ top-K of the lighting} ŵ_j · S_j )            (Eq. 4)

with ŵ the lighting's light-Haar coefficients (the K largest, Ng et al.'s non-linear lighting
approximation), S_j slab j's sparse spatial coefficients, and one inverse spatial transform at
the end: the sum runs in the compressed domain and touches only the K slabs' stored entries.

Each slab is stored as :data:`PIECES` pieces by entry magnitude, and the terms are pieces
(largest ``|ŵ_j| · rms(piece)`` first): a slab's small entries are read only where its
lighting coefficient makes them count — a deviation from whole-slab terms that reads 2.1–3.2×
fewer entries (sun 1.3×, ``docs/lighting.md``) for the same relit error. K comes from a target on the truncation error, or on
the total error against exact Eq. (4) (``budget(…, total=True)``: the field's own error under
the lighting estimated on :data:`CHECK_PIXELS` stored exact pixels, combined in quadrature).
"""

from __future__ import annotations

import functools
import logging
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from facegeo.checks import as_array, check_positive, fmt_value
from facegeo.errors import InputError, ShapeError
from facegeo.lighting._compress_haar import (
    _check_pow2,
    _haar_step,
    _nonstandard_levels,
    haar2d_nonstandard,
    selected_lighting_terms,
    top_terms_index_order,
)

log = logging.getLogger(__name__)

#: Bins per octave of the squared-magnitude histogram that chooses the threshold in
#: :func:`fit_image_wavelet` (the threshold is the lower edge of a bin, so the dropped energy is
#: at most the target's; 32 bins per octave of energy ≈ 1 % steps in the threshold).
THRESHOLD_BINS_PER_OCTAVE = 32

#: Entries to scatter below which a relight stays on one thread (a thread hand-off costs
#: ≈ 0.1 ms, ≈ 30,000 entries' work).
PARALLEL_ENTRIES = 100_000

#: Light-coefficient slabs transformed together in the fit (memory: SLAB_CHUNK · 3 · band float64).
SLAB_CHUNK = 32

#: Bits of each channel's magnitude in a packed entry (9-bit two's complement mantissas: three
#: channels and a 5-bit shared exponent fill a uint32): the largest channel keeps 8 significant
#: bits, so the rounding error is ≤ 1/255 of the entry's largest channel (RGBE-like, signed).
MAGNITUDE_BITS = 8
EXPONENT_LEVELS = 32

#: Pixels whose exact rows a fit stores (float16, 12 KB each for 2048 lights) to estimate, per
#: lighting, the relit error the field's compression alone causes (:meth:`ImageWaveletField.
#: field_error_estimate`); the ``budget(…, total=True)`` of a relit target then spends on the
#: lighting's truncation only what is left.
CHECK_PIXELS = 128

#: ``budget(…, total=True)`` aims at ``(1 − TOTAL_MARGIN) · target``: room for the check
#: pixels' sampling error and for the two errors' correlation, which the quadrature sum
#: ignores. Measured on the generator's face (``docs/lighting.md``): with 0.1, 8 random sets of
#: 128 check pixels × 10 maps all landed at ≤ 0.98 % for a 1 % target; one standard error added
#: to the estimate instead (margin 0.03–0.05) gave up to 1.03 % and, on the sun, K = 705.
TOTAL_MARGIN = 0.1

#: Pieces each light coefficient's slab is stored as by a fit (:func:`fit_image_wavelet`): its
#: entries split by magnitude at the global quantiles ``1/n … (n−1)/n`` of all kept entries'
#: RGB magnitudes. A relight's terms are then pieces, largest ``|ŵ_j| · rms(piece)`` first
#: (the error a piece's entries remove per entry read, for orthogonal entries), so the small
#: entries of a slab are read only where its lighting coefficient makes them count. Measured on
#: the generator's face at field target 1.5 % and a 1 % total target (``docs/lighting.md``):
#: entries read 1 piece → 4 pieces 2.1–3.2× fewer on the ten maps (sun 1.3×).
PIECES = 4


def _code_base(big: float) -> int:
    """The exponent base of :func:`encode_rgb` for values of largest magnitude ``big``."""
    top = (1 << MAGNITUDE_BITS) - 1
    return int(np.ceil(np.log2(big / top))) - (EXPONENT_LEVELS - 1) if big > 0 else 0


def encode_rgb(v: np.ndarray, base: int | None = None) -> tuple[np.ndarray, int]:
    """Pack ``(n, 3)`` float RGB coefficients into ``(n,)`` uint32 with one shared exponent per
    entry: three 9-bit two's complement mantissas m (|m| ≤ 255) in bits 0–26 and a 5-bit
    exponent e in bits 27–31; value = m · 2^(e + base). Returns the codes and ``base`` (default:
    the largest entry uses the top exponent; entries more than 2³² below it flush to zero; a
    given ``base`` must be at least that of the largest magnitude, :func:`_code_base`).
    """
    v = np.asarray(v, np.float64)
    big = np.abs(v).max(axis=1)
    top = (1 << MAGNITUDE_BITS) - 1
    if base is None:
        base = _code_base(float(big.max())) if big.size else 0
    with np.errstate(divide="ignore"):
        e = np.ceil(np.log2(np.maximum(big, 1e-300) / top)).astype(np.int64) - base
    e = np.clip(e, 0, EXPONENT_LEVELS - 1)
    mag = np.rint(np.abs(v) / np.ldexp(1.0, (e + base))[:, None]).astype(np.int64)
    over = mag.max(axis=1) > top  # log2 rounding at a power of two: one exponent up
    e[over] += 1
    mag = np.minimum(np.rint(np.abs(v) / np.ldexp(1.0, (e + base))[:, None]), top).astype(np.uint32)
    code = e.astype(np.uint32) << np.uint32(27)
    m = np.where(np.signbit(v), -mag.astype(np.int64), mag.astype(np.int64))
    for c in range(3):
        code |= (m[:, c] & 0x1FF).astype(np.uint32) << np.uint32(9 * c)
    return code, base


def exponent_table(base: int) -> np.ndarray:
    """``(32,)`` float32 ``2^(e + base)`` for the exponent field of :func:`encode_rgb`."""
    return np.ldexp(1.0, np.arange(EXPONENT_LEVELS) + base).astype(np.float32)


def decode_rgb(code: np.ndarray, base: int) -> np.ndarray:
    """Inverse of :func:`encode_rgb`: ``(n, 3)`` float32."""
    code = np.asarray(code, np.uint32)
    out = np.empty((code.size, 3), np.float32)
    p = exponent_table(base)[code >> np.uint32(27)]
    for c in range(3):  # the 9-bit field to the top, then an arithmetic shift sign-extends it
        m = (code << np.uint32(23 - 9 * c)).view(np.int32) >> np.int32(23)
        out[:, c] = m.astype(np.float32) * p
    return out


def _pow2(n: int) -> int:
    return 1 << max(0, int(n - 1).bit_length())


@dataclass
class ImageWaveletField:
    """An image-space reflectance field as thresholded 4-D Haar coefficients (light × image),
    stored light-coefficient-major for relighting from the top K lighting coefficients.

    Attributes
    ----------
    ptr : (L · pieces · segments + 1,) int64
        Entries of piece q (of light-coefficient slab ``q // pieces``) whose coefficient row
        lies in segment g (rows ``65536·g … 65536·g + 65535``) are
        ``ptr[q·segments + g] : ptr[q·segments + g + 1]``.
    segments : int
        ``⌈S / 65536⌉`` (S = :attr:`n_rows`): the segments let positions be uint16 on any grid.
    pos : (n,) uint16
        Spatial coefficient row of each entry (:func:`coefficient_rows`: the grid's
        coefficients in the block layout) minus its segment's start, sorted in a slab's
        segment.
    code : (n,) uint32
        The entry's RGB coefficients packed by :func:`encode_rgb` (6 bytes an entry with
        ``pos``).
    base : int
        Exponent base of the codes.
    pixel_pos : (P,) int32
        Grid index of each field row (pixel).
    n_theta, n_phi : int
        The light grid (powers of two).
    grid : (int, int)
        ``(H, W)`` of the image grid, powers of two (the pixels' bounding box, padded).
    kept_fraction : float
        Kept entries (one per light coefficient and grid cell, RGB together) over P · L.
    field_error : float
        Relative Frobenius error of the field from the threshold (exact by Parseval; the
        8-bit rounding of the kept values not included).
    check_index : (n,) int32 or None
        Field rows of the check pixels (a uniform random sample, sorted; :data:`CHECK_PIXELS`).
    check_rows : (n, L, 3) float16 (float32 where float16 would overflow) or None
        Their exact reflectance functions (as given to the fit, rounded to float16): the relit
        error of the compressed field under a lighting is estimated on them
        (:meth:`field_error_estimate`).
    pieces : int
        Pieces per slab (:data:`PIECES`; 1: whole slabs, the earlier models). Piece
        ``j·pieces + b`` holds slab j's entries of magnitude band b (0 the largest).
    """

    ptr: np.ndarray
    segments: int
    pos: np.ndarray
    code: np.ndarray
    base: int
    pixel_pos: np.ndarray
    n_theta: int
    n_phi: int
    grid: tuple[int, int]
    kept_fraction: float
    field_error: float
    check_index: np.ndarray | None = None
    check_rows: np.ndarray | None = None
    pieces: int = 1

    def __post_init__(self) -> None:
        self._scratch_lock = threading.Lock()

    def __getstate__(self) -> dict:
        """The stored fields only (the derived tables and the relight's scratch are rebuilt)."""
        return {name: getattr(self, name) for name in self.__dataclass_fields__}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.__post_init__()

    def _relight_one_call(self, ker: Any, weights: Any, terms: int | None) -> np.ndarray:
        """:meth:`relight` on one thread with K = ``terms`` (or every non-zero term) as one
        compiled call (:func:`_compress_kernels.relight_one_thread`) into the model's kept
        scratch: an accumulator the inverse leaves zeroed (no allocation, no 16·S-byte memset
        per call), or a new zeroed one while another thread holds it. A C-contiguous float64
        ``(L, 3)`` array goes straight to the kernel, which checks it is finite (numpy's checks
        cost ≈ 0.1 ms with cold caches); anything else through :func:`facegeo.checks.as_array`."""
        n_l = self.n_theta * self.n_phi
        wts = weights
        if not (type(wts) is np.ndarray and wts.dtype == np.float64 and wts.shape == (n_l, 3)
                and wts.flags.c_contiguous):
            wts = np.ascontiguousarray(as_array(weights, "weights", shape=(n_l, 3)))
        k = 0
        if terms is not None:
            k = int(terms)
            if not 1 <= k <= n_l * self.pieces:
                raise InputError(f"terms: expected 1 … {n_l * self.pieces}, got "
                                 f"{fmt_value(terms)}")
        out = np.empty((self.n_pixels, 3), np.float32)
        owned = self._scratch_lock.acquire(blocking=False)
        try:
            if owned:
                if "_scratch" not in self.__dict__:  # zeroed once; the kernels keep it zeroed
                    self._scratch = _scratch(self)
                acc, ll, tab = self._scratch
            else:
                acc, ll, tab = _scratch(self)
            lighting, entries, inverse = self._kernel_args
            finite = ker.relight_one_thread(wts, *lighting, k, *entries, acc, *inverse, ll, tab,
                                            owned, out, self._piece_scale)
        finally:
            if owned:
                self._scratch_lock.release()
        if not finite:
            as_array(wts, "weights", shape=(n_l, 3))  # raises: names the non-finite values
        return out

    @functools.cached_property
    def _kernel_args(self) -> tuple[tuple, tuple, tuple]:
        """The model's arguments of :func:`_compress_kernels.relight_one_thread` (derived,
        cached): the light grid's, the stored entries', the inverse's."""
        h, w = self.grid
        return ((self._light_levels, self.n_theta, self.n_phi),
                (self.ptr, self.segments, self.pos, self.code, self._exponents),
                (h, w, _blocked(self.grid), self._levels, self.pixel_pos, self._grid_order,
                 *self._finest_blocks))

    @property
    def n_rows(self) -> int:
        """S, the coefficient rows of the spatial layout (:func:`coefficient_rows`)."""
        h, w = self.grid
        return h * w // 4 + 3 * self._finest_blocks[0].size if _blocked(self.grid) else h * w

    @functools.cached_property
    def _grid_of_row(self) -> np.ndarray:
        """The grid cell of each coefficient row ``(S,)`` int64 (derived, cached)."""
        rows = coefficient_rows(self.grid, self._finest_blocks[0])
        cell = np.flatnonzero(rows >= 0)
        out = np.empty(self.n_rows, np.int64)
        out[rows[cell]] = cell
        return out

    @functools.cached_property
    def _light_levels(self) -> np.ndarray:
        """The light grid's non-standard Haar levels ``(n, 4)`` int64 (derived, cached)."""
        return np.array(_nonstandard_levels(self.n_theta, self.n_phi), np.int64).reshape(-1, 4)

    @functools.cached_property
    def _exponents(self) -> np.ndarray:
        """:func:`exponent_table` of :attr:`base` (derived, cached)."""
        return exponent_table(self.base)

    @functools.cached_property
    def _grid_order(self) -> np.ndarray:
        """Field rows by increasing grid index (derived, cached)."""
        return np.argsort(self.pixel_pos, kind="stable")

    @functools.cached_property
    def _finest_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`finest_blocks` of the pixels (derived, cached)."""
        return finest_blocks(self.pixel_pos, self.grid)

    @functools.cached_property
    def _levels(self) -> np.ndarray:
        """The spatial transform's levels ``(n, 4)`` int64 (derived, cached)."""
        h, w = self.grid
        return np.array(_nonstandard_levels(w, h), np.int64).reshape(-1, 4)

    @functools.cached_property
    def _piece_scale(self) -> np.ndarray:
        """Each piece's RMS entry magnitude ``(L·pieces,)`` float64 (derived from the codes,
        cached); all ones for one piece per slab (the terms are then the largest ``|ŵ_j|``)."""
        n = self.n_theta * self.n_phi * self.pieces
        if self.pieces == 1:
            return np.ones(n)
        rows = np.arange(n) * self.segments
        count = self.ptr[rows + self.segments] - self.ptr[rows]
        piece = np.repeat(np.arange(n), count)
        m2 = (decode_rgb(self.code, self.base).astype(np.float64) ** 2).sum(axis=1)
        return np.sqrt(np.bincount(piece, weights=m2, minlength=n) / np.maximum(count, 1))

    def _piece_terms(self, wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The terms of lighting coefficients ``wc`` ``(L, 3)``: each piece's weights
        ``(L·pieces, 3)`` (its slab's coefficient) and its score ``Σ_c |ŵ| · rms(piece)``
        (one piece per slab: ``Σ_c |ŵ|``, the order of :func:`lighting_order`)."""
        if self.pieces == 1:
            return wc, np.abs(wc).sum(axis=1)
        wrep = np.repeat(wc, self.pieces, axis=0)
        return wrep, np.abs(wrep).sum(axis=1) * self._piece_scale

    def _selected_terms(self, weights: Any, terms: int | None,
                        target_error: float | None) -> tuple[np.ndarray, np.ndarray]:
        """The relight's terms (pieces) in index order and their weights ``(K, 3)`` float32:
        K = ``terms``, from :meth:`budget`, or every non-zero one (the Python-level twin of the
        selection in :func:`_compress_kernels.relight_one_thread`)."""
        if self.pieces == 1:
            return selected_lighting_terms(self, weights, terms, target_error, index_order=True)
        if terms is not None and target_error is not None:
            raise InputError("relight: give terms or target_error, not both")
        wrep, score = self._piece_terms(self.lighting_coefficients(weights))
        if target_error is not None:
            k, _ = self.budget(weights, target_error)
        elif terms is not None:
            k = int(terms)
            if not 1 <= k <= score.size:
                raise InputError(f"terms: expected 1 … {score.size}, got {fmt_value(terms)}")
        else:
            k = max(1, int(np.count_nonzero(score)))
        sc = np.zeros((score.size, 3))
        sc[:, 0] = score
        idx = np.ascontiguousarray(top_terms_index_order(sc, k), np.int64)
        return idx, np.ascontiguousarray(wrep[idx], np.float32)

    def entries_read(self, weights: Any, terms: int | None = None) -> int:
        """Stored entries a relight under ``weights`` with K = ``terms`` (default every
        non-zero term) reads: the scatter's work, ≈ 1.3 ns each (``docs/lighting.md``)."""
        idx, _ = self._selected_terms(weights, terms, None)
        return int((self.ptr[(idx + 1) * self.segments] - self.ptr[idx * self.segments]).sum())

    @property
    def n_pixels(self) -> int:
        return int(self.pixel_pos.size)

    @property
    def nbytes(self) -> int:
        """Storage, every array counted: slab pointers, spatial indices, codes, pixel map, the
        check pixels' indices and exact rows (and the exponent base)."""
        check = sum(a.nbytes for a in (self.check_index, self.check_rows) if a is not None)
        return int(self.ptr.nbytes + self.pos.nbytes + self.code.nbytes + self.pixel_pos.nbytes
                   + check + 8)

    def lighting_coefficients(self, weights: Any) -> np.ndarray:
        """The Eq. (4) weights ``(L, 3)`` (δA included) in the non-standard light Haar basis."""

        n_l = self.n_theta * self.n_phi
        w = as_array(weights, "weights", shape=(n_l, 3))
        return haar2d_nonstandard(w.T, self.n_theta, self.n_phi, compiled=True).T

    def budget(self, weights: Any, target_error: float, *,
               total: bool = False) -> tuple[int, float]:
        """The smallest K whose relight from the K largest lighting terms (the pieces of
        :data:`PIECES`, largest ``|ŵ|·rms`` first; with one piece per slab the lighting
        coefficients) is within ``target_error`` (relative RMSE), and that error's estimate.

        ``total=False``: within ``target_error`` of the relight from all the coefficients —
        the truncation error e_t(K) alone, measured in the spatial coefficient domain on the
        whole grid (Parseval: the padded grid includes the pixels, so this is ≥ the error on
        the pixels), against this compressed field's full relight; the error against exact
        Eq. (4) is then up to this plus the field's own relit error (:attr:`field_error` for
        the field; far less for a relit image).

        ``total=True``: within ``target_error`` of **exact Eq. (4)**: the field's own relit
        error under this lighting, e_f, estimated on the check pixels
        (:meth:`field_error_estimate`), and e_t(K) combined as orthogonal errors add,
        ``√(e_f² + e_t(K)²) ≤ (1 − TOTAL_MARGIN) · target`` (:data:`TOTAL_MARGIN`). Where the
        field is already accurate under this lighting the truncation may take almost the
        whole target (fewer terms); where e_f alone exceeds the aim, every non-zero term. The
        returned error is ``√(e_f² + e_t(K)²)``. Deviation from Ng et al. 2003 (who fix the
        term count): the count follows the error asked for. Needs a model fitted with check
        pixels.

        Costs two passes over the stored entries (a full relight, then every prefix's error by
        updating the residual entry by entry); ``total`` adds one inverse at the pixels and the
        check pixels' exact relight.
        """
        t = check_positive(target_error, "target_error")
        if total and (self.check_index is None or self.check_index.size == 0):
            raise InputError("budget: total=True needs check pixels; fit with check_pixels > 0 "
                             "(fit_image_wavelet)")
        wrep, score = self._piece_terms(self.lighting_coefficients(weights))
        order = np.argsort(-score, kind="stable")  # one piece per slab: lighting_order
        order = np.ascontiguousarray(order[score[order] > 0], np.int64)
        if order.size == 0:
            return 1, 0.0
        lw = np.ascontiguousarray(wrep[order], np.float32)
        g = self.n_rows
        ker = _kernels()
        if ker is not None:  # interleaved: the relight's scatter, then the prefix errors
            full, ll, tab = _scratch(self)
            pw = self._exponents
            ker.scatter_add_rgbx(self.ptr, self.segments, self.pos, self.code, pw, order, lw,
                                 full, tab, 0, g)
            e2 = ker.truncation_errors_rgbx(self.ptr, self.segments, self.pos, self.code, pw,
                                            order, lw, full)
            norm2 = max(float((full.astype(np.float64) ** 2).sum()), 1e-300)
            if total:
                h, w = self.grid
                relit = np.empty((self.n_pixels, 3), np.float32)
                ker.inverse_haar_at_pixels(full, h, w, _blocked(self.grid), self._levels,
                                           self.pixel_pos, self._grid_order, relit,
                                           *self._finest_blocks, ll, False)
        else:
            full = np.zeros((3, g), np.float32)
            _scatter(self, order, lw, full)
            e2 = _truncation_errors(self, order, lw, full)
            norm2 = max(float((full.astype(np.float64) ** 2).sum()), 1e-300)
            if total:
                relit = self._pixels_from_planar(full)
        if not total:
            ok = np.flatnonzero(e2 <= t * t * norm2)
            k = int(ok[0]) if ok.size else order.size - 1
            return k + 1, float(np.sqrt(e2[k] / norm2))
        e_f = self._check_error(relit[self.check_index], weights)
        room = ((1.0 - TOTAL_MARGIN) * t) ** 2 - e_f * e_f
        ok = np.flatnonzero(e2 <= room * norm2) if room > 0 else np.zeros(0, np.int64)
        k = int(ok[0]) if ok.size else order.size - 1
        return k + 1, float(np.sqrt(e_f * e_f + e2[k] / norm2))

    def field_error_estimate(self, weights: Any) -> float:
        """The relit error the field's compression causes under ``weights``: relative RMSE of
        the relight from every lighting coefficient against exact Eq. (4), on the check pixels
        (a ratio estimate, ``‖Δ‖ / ‖exact‖`` over the sample; the exact relight from their
        stored rows). Needs a model fitted with check pixels."""
        if self.check_index is None or self.check_index.size == 0:
            raise InputError("field_error_estimate: needs check pixels; fit with "
                             "check_pixels > 0 (fit_image_wavelet)")
        return self._check_error(self.relight(weights)[self.check_index], weights)

    def _check_error(self, got: np.ndarray, weights: Any) -> float:
        """Relative RMSE of the relit check pixels ``got`` ``(n, 3)`` against their exact
        Eq. (4) relight under ``weights`` (float64 sums of the stored float16 rows), as a ratio
        estimate ``√(Σ_i a_i / Σ_i b_i)``: a the squared error, b the squared exact value of
        check pixel i."""
        n_l = self.n_theta * self.n_phi
        w = as_array(weights, "weights", shape=(n_l, 3))
        ref = np.einsum("plc,lc->pc", self.check_rows.astype(np.float32), w.astype(np.float32),
                        dtype=np.float64, optimize=False)
        num = float(np.linalg.norm(got.astype(np.float64) - ref))
        return num / max(float(np.linalg.norm(ref)), 1e-300)

    def _pixels_from_planar(self, acc: np.ndarray) -> np.ndarray:
        """Numpy reference: planar spatial coefficients ``(3, S)`` → relit pixels ``(P, 3)``
        (full inverse on the grid, then the pixels' cells)."""
        h, w = self.grid
        grid = np.zeros((3, h * w), np.float32)
        grid[:, self._grid_of_row] = acc
        img = _inverse_spatial(grid.reshape(3, h, w))
        return np.ascontiguousarray(img.reshape(3, h * w)[:, self.pixel_pos].T)

    def relight(self, weights: Any, *, terms: int | None = None,
                target_error: float | None = None, total: bool = False,
                workers: int = 1) -> np.ndarray:
        """Eq. (4) from the compressed field: ``(P, 3)`` float32.

        Parameters
        ----------
        weights : (L, 3) float
            Eq. (4) weights (δA included).
        terms : int, optional
            K, the pieces of lighting coefficients kept, 1 … L·``pieces`` (Ng et al. 2003's
            non-linear approximation; with ``pieces=1`` the coefficients themselves).
        target_error : float, optional
            Instead of ``terms``: K from :meth:`budget`. Neither: every non-zero lighting
            coefficient (the compressed transport's own error only).
        total : bool
            With ``target_error``: ``budget(…, total=True)``, the target for the error against
            exact Eq. (4) (the field's own error on this lighting included); default the
            truncation error alone.
        workers : int
            Threads for the scatter: compiled, each thread takes a range of coefficient rows holding
            about an equal share of the entries (one accumulator, disjoint cells); numpy, the
            K slabs split in parts, one accumulator each, summed. Default 1: a relight takes
            about a millisecond, and on the loaded shared machine a thread hand-off can cost
            as much.
        """

        if int(workers) < 1:
            raise InputError(f"workers: expected ≥ 1, got {fmt_value(workers)}")
        if total and target_error is None:
            raise InputError("relight: total=True needs target_error (the total relit error "
                             "to reach)")
        if total and target_error is not None:
            if terms is not None:
                raise InputError("relight: give terms or target_error, not both")
            terms, target_error = self.budget(weights, target_error, total=True)[0], None
        h, w = self.grid
        ker = _kernels()
        if ker is not None and int(workers) == 1 and target_error is None:
            return self._relight_one_call(ker, weights, terms)
        idx, lw = self._selected_terms(weights, terms, target_error)
        if ker is None:  # numpy reference: planar accumulator, full inverse, pixel gather
            acc = _scatter_in_parts(self, idx, lw, (3, self.n_rows), _scatter, int(workers))
            return self._pixels_from_planar(acc)
        acc, ll, _ = _scratch(self)
        args = (self.ptr, self.segments, self.pos, self.code, self._exponents, idx, lw, acc)
        cuts = _cell_ranges(self, idx, int(workers), ker)
        if len(cuts) > 2:  # threads scatter into disjoint cell ranges of the one accumulator
            list(_pool(len(cuts) - 1).map(
                lambda i: ker.scatter_add_rgbx(*args, np.zeros((32, 4), np.float32), cuts[i],
                                               cuts[i + 1]), range(len(cuts) - 1)))
        else:
            ker.scatter_add_rgbx(*args, np.zeros((32, 4), np.float32), 0, self.n_rows)
        out = np.empty((self.n_pixels, 3), np.float32)
        ker.inverse_haar_at_pixels(acc, h, w, _blocked(self.grid), self._levels, self.pixel_pos,
                                   self._grid_order, out, *self._finest_blocks, ll, False)
        return out


def _blocked(grid: tuple[int, int]) -> bool:
    """Whether a grid's coefficients use the block layout (the finest level steps both axes)."""
    return grid[0] >= 2 and grid[1] >= 2


def finest_blocks(pixel_pos: np.ndarray, grid: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The grid's finest-level 2 × 2 blocks holding pixels ``(n,)`` int64 (index ``(y/2)·(W/2)
    + x/2``, increasing) and the field row in each of their cells ``(n, 4)`` int32 (slot
    ``2·(y mod 2) + x mod 2``, −1 for none); empty when a grid axis has size 1."""
    if not _blocked(grid):
        return np.zeros(0, np.int64), np.zeros((0, 4), np.int32)
    w = grid[1]
    y, x = np.divmod(np.asarray(pixel_pos, np.int64), w)
    blocks, which = np.unique((y >> 1) * (w // 2) + (x >> 1), return_inverse=True)
    block_px = np.full((blocks.size, 4), -1, np.int32)
    block_px[which.ravel(), 2 * (y & 1) + (x & 1)] = np.arange(y.size)
    return blocks, block_px


def coefficient_rows(grid: tuple[int, int], blocks: np.ndarray) -> np.ndarray:
    """The row of each spatial coefficient ``(H·W,)`` int64 (grid cell ``y·W + x`` in the
    non-standard Haar layout) in the **block layout**: rows ``[0, H·W/4)`` the finest level's
    low-pass quadrant row-major (stride W/2), then rows ``H·W/4 + 3·b + (0, 1, 2)`` the detail
    coefficients ``D_y, D_x, D_xy`` of the b-th block of ``blocks`` (:func:`finest_blocks`);
    −1 for the detail cells of blocks without pixels, which are zero (never stored). The
    relight's accumulator then holds S = H·W/4 + 3·n rows (0.56 MB instead of 1 MB on the 256 ×
    256 face grid: it shares the per-core L2 better) and the finest inverse level reads them in
    one forward sweep. Identity (the grid row-major) when a grid axis has size 1."""
    h, w = grid
    if not _blocked(grid):
        return np.arange(h * w, dtype=np.int64)
    hh, hw = h // 2, w // 2
    y, x = np.divmod(np.arange(h * w, dtype=np.int64), w)
    rows = np.full(h * w, -1, np.int64)
    low = (y < hh) & (x < hw)
    rows[low] = y[low] * hw + x[low]
    block = (y % hh) * hw + x % hw  # the block a detail cell belongs to
    b = np.searchsorted(blocks, block)
    held = ~low & (b < blocks.size) & (blocks[np.minimum(b, blocks.size - 1)] == block)
    kind = (y >= hh).astype(np.int64) + 2 * (x >= hw) - 1  # D_y 0, D_x 1, D_xy 2
    rows[held] = hh * hw + 3 * b[held] + kind[held]
    return rows


def _scratch(f: ImageWaveletField) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A compiled relight's zeroed scratch: the accumulator ``(S, 4)``, the inverse's low-pass
    buffer (``(H·W/4, 4)`` in the block layout, else ``(H·W, 4)``: a bound) and the scatter's
    exponent table ``(32, 4)``, float32."""
    h, w = f.grid
    return (np.zeros((f.n_rows, 4), np.float32),
            np.zeros((h * w // 4 if _blocked(f.grid) else h * w, 4), np.float32),
            np.zeros((32, 4), np.float32))


def _scatter_in_parts(f: ImageWaveletField, idx: np.ndarray, lw: np.ndarray, shape: tuple,
                      scatter: Any, workers: int) -> np.ndarray:
    """Zeroed accumulator of ``shape`` with ``scatter(f, idx, lw, acc)`` added; with ``workers``
    > 1 and enough entries, the K slabs split in parts of equal entry counts, one accumulator
    per thread, summed."""
    acc = np.zeros(shape, np.float32)
    n = f.segments
    counts = f.ptr[(idx + 1) * n] - f.ptr[idx * n]
    if workers > 1 and idx.size > 1 and counts.sum() >= PARALLEL_ENTRIES:
        from concurrent.futures import ThreadPoolExecutor

        cum = np.cumsum(counts)
        cuts = np.searchsorted(cum, cum[-1] * np.arange(1, workers) / workers)
        parts = np.split(np.arange(idx.size), np.unique(np.clip(cuts + 1, 1, idx.size - 1)))
        accs = [acc] + [np.zeros_like(acc) for _ in parts[1:]]
        with ThreadPoolExecutor(max_workers=len(parts)) as pool:  # nogil kernels
            list(pool.map(lambda i: scatter(f, idx[parts[i]], lw[parts[i]], accs[i]),
                          range(len(parts))))
        for a in accs[1:]:
            acc += a
    else:
        scatter(f, idx, lw, acc)
    return acc


#: Candidate split rows per thread when a compiled relight runs on several threads.
SPLIT_CANDIDATES = 8

_POOLS: dict = {}


def _pool(n: int):
    """A persistent pool of ``n`` threads for the compiled relight (creating one per call costs
    ≈ 0.1–0.2 ms, a sixth of a relight)."""
    if n not in _POOLS:
        from concurrent.futures import ThreadPoolExecutor

        _POOLS[n] = ThreadPoolExecutor(max_workers=n, thread_name_prefix="facegeo-compress")
    return _POOLS[n]


def _cell_ranges(f: ImageWaveletField, idx: np.ndarray, workers: int, ker: Any) -> list[int]:
    """Coefficient-row bounds ``[0, …, S]`` splitting the selected entries into ``workers``
    parts of about equal count (cuts on a grid of :data:`SPLIT_CANDIDATES` · workers rows), or
    ``[0, S]`` for one thread or fewer than :data:`PARALLEL_ENTRIES` entries."""
    g = f.n_rows
    n = f.segments
    total = int((f.ptr[(idx + 1) * n] - f.ptr[idx * n]).sum())
    if workers <= 1 or total < PARALLEL_ENTRIES:
        return [0, g]
    cells = np.unique(np.linspace(0, g, SPLIT_CANDIDATES * workers + 1).astype(np.int64))
    if cells.size < 3:
        return [0, g]
    below = ker.entries_below(f.ptr, f.segments, f.pos, idx, cells)
    at = np.searchsorted(below, total * np.arange(1, workers) / workers)
    return [0] + sorted({int(c) for c in cells[np.clip(at, 1, cells.size - 2)]}) + [g]


def _kernels():
    """The numba kernels module, or ``None`` without numba (``relight._fused_kernel`` is the
    project's one switch for compiled kernels, so tests can turn them all off)."""
    from facegeo.lighting import relight as _relight

    if not _relight._fused_kernel():
        return None
    from facegeo.lighting import _compress_kernels as K

    return K


def _scatter(f: ImageWaveletField, idx: np.ndarray, lw: np.ndarray, acc: np.ndarray) -> None:
    """``acc[c, pos] += val[., c] · lw[k, c]`` over the entries of slabs ``idx`` (numpy
    reference of :func:`_compress_kernels.scatter_add_rgbx`: one weighted histogram per channel)."""
    sel, p = _slab_entries(f, idx)
    rep = np.repeat(np.arange(idx.size),
                    f.ptr[(idx + 1) * f.segments] - f.ptr[idx * f.segments])
    val = decode_rgb(f.code[sel], f.base)
    for c in range(3):
        acc[c] += np.bincount(p,
                              weights=val[:, c].astype(np.float64) * lw[rep, c],
                              minlength=acc.shape[1]).astype(np.float32)


def _slab_entries(f: ImageWaveletField, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry indices of slabs ``idx`` (in that order) and their full grid positions (int64)."""
    n = f.segments
    rows = (idx[:, None] * n + np.arange(n)).ravel()  # (slab, segment) rows
    counts = f.ptr[rows + 1] - f.ptr[rows]
    sel = np.concatenate([np.arange(f.ptr[r], f.ptr[r + 1]) for r in rows]) if rows.size \
        else np.zeros(0, np.int64)
    seg = np.repeat(rows % n, counts)
    return sel, (seg << 16) + f.pos[sel].astype(np.int64)


def _truncation_errors(f: ImageWaveletField, idx: np.ndarray, lw: np.ndarray,
                       full: np.ndarray) -> np.ndarray:
    """``‖full − Σ_{k' ≤ k} slab_k'‖²`` for every prefix k of ``idx`` (``(K,)`` float64; numpy
    reference of :func:`_compress_kernels.truncation_errors_rgbx`, one slab at a time)."""
    d = full.astype(np.float64)
    out = np.empty(idx.size)
    for k, j in enumerate(idx):
        sel, p = _slab_entries(f, np.array([j]))
        d[:, p] -= (decode_rgb(f.code[sel], f.base) * lw[k]).T.astype(np.float64)
        out[k] = (d ** 2).sum()
    return out


def _inverse_spatial(img: np.ndarray) -> np.ndarray:
    """Inverse non-standard 2-D Haar of ``(3, H, W)`` float32 spatial coefficients (numpy
    reference of :func:`_compress_kernels.inverse_haar_at_pixels`)."""
    h, w = img.shape[1:]
    return haar2d_nonstandard(img.reshape(3, h * w), w, h, inverse=True).astype(np.float32)


def _check_pixels(pixels: Any, n_p: int) -> tuple[np.ndarray, tuple[int, int]]:
    """Grid index of each pixel (bounding box shifted to the origin, padded to powers of two)."""
    q = np.asarray(pixels)
    if q.shape != (n_p, 2) or q.dtype.kind not in "iu":
        raise ShapeError(f"pixels: expected ({n_p}, 2) integer (row, column) image positions "
                         f"of the field's rows, got {q.shape} {q.dtype}")
    q = q.astype(np.int64) - q.min(axis=0)
    h, w = _pow2(int(q[:, 0].max()) + 1), _pow2(int(q[:, 1].max()) + 1)
    flat = q[:, 0] * w + q[:, 1]
    if np.unique(flat).size != n_p:
        raise InputError("pixels: two field rows share an image position; expected one row "
                         "per pixel")
    return flat.astype(np.int32), (h, w)


#: Image rows per band of :func:`fit_image_wavelet` (a power of two): the spatial Haar levels
#: finer than the band are local to it, so the fit holds one band's light coefficients at a
#: time (≈ 16 · W pixels · L · 3 float32) and the bands' low-pass rows (L · 3 · G / 16² float64).
FIT_BAND_ROWS = 16

#: Field rows per block of the light transform in the fit (float64, a few copies of 512 · L · 3
#: · 8 bytes = 25 MB at L = 2048; 4096 rows made the transform the fit's peak, ≈ 0.6 GB).
FIT_LIGHT_ROWS = 512


def _band_layout(grid: tuple[int, int], band: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Where the cells of a band of ``band`` image rows go after the first log₂(band) levels of
    the grid's non-standard Haar transform (computed on the band alone): the full grid index
    of cell c of band b is ``base[c] + b · step[c]`` for detail cells; the band's low-pass
    cells (row 0, columns ``< w_k``) have ``base`` −1 and go to row b, column c of the
    ``(H/band, w_k)`` low-pass grid. Returns ``base, step`` ``(band·W,)`` int64 and ``w_k``."""
    gh, gw = grid
    r, c = np.divmod(np.arange(band * gw, dtype=np.int64), gw)
    base = np.full(r.size, -1, np.int64)
    step = np.zeros(r.size, np.int64)
    hb, w, hf = band, gw, gh  # level size in the band (rows), columns, full-grid rows
    while hb > 1:  # every level here halves the rows (band ≤ H); columns while w > 1
        w_next = max(1, w // 2)
        level = (r < hb) & (c < w) & ~((r < hb // 2) & (c < w_next))
        lower = level & (r >= hb // 2)  # the row-detail half: H_i/2 + b·hb/2 + (r − hb/2)
        upper = level & (r < hb // 2)  # b·hb/2 + r
        base[lower] = (hf // 2 + r[lower] - hb // 2) * gw + c[lower]
        base[upper] = r[upper] * gw + c[upper]
        step[level] = (hb // 2) * gw
        hb, w, hf = hb // 2, w_next, hf // 2
    return base, step, w


def _band_forward(x: np.ndarray, grid: tuple[int, int], band: int) -> None:
    """The first log₂(band) levels of the grid's non-standard Haar transform
    (:func:`haar2d_nonstandard`, image width as θ) on a band ``(..., band, W)`` float64, in
    place: the same steps on the same values as the whole grid's transform."""
    levels = _nonstandard_levels(grid[1], grid[0])
    hb = band
    for _, w, st, sp in levels[: band.bit_length() - 1]:
        block = x[..., :hb, :w]
        if st:
            _haar_step(block, -1, w, False)
        if sp:
            _haar_step(block, -2, hb, False)
        hb //= 2


def _energy_bins(m2: np.ndarray, lo: float) -> np.ndarray:
    """Histogram bin of each squared magnitude (> 0) for the fit's threshold."""
    n_bins = 140 * THRESHOLD_BINS_PER_OCTAVE
    return np.clip(((np.log2(m2) - lo) * THRESHOLD_BINS_PER_OCTAVE).astype(np.int64), 0, n_bins)


def _count(x: Any, name: str, lo: int) -> int:
    """``x`` as an integer ≥ ``lo``, else :class:`InputError` naming ``name``."""
    try:
        n = int(x)
        ok = not isinstance(x, (bool, np.bool_)) and n == x and n >= lo
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise InputError(f"{name}: expected an integer ≥ {lo}, got {fmt_value(x)}")
    return n


def fit_image_wavelet(field: Any, n_theta: int, n_phi: int, pixels: Any, *,
                      target_error: float = 0.01, check_pixels: int = CHECK_PIXELS,
                      seed: int = 0, pieces: int = PIECES) -> ImageWaveletField:
    """Compress an image-space field in the light domain and across the image (4-D Haar).

    Every reflectance function (per channel) goes to the non-standard light Haar basis
    (:func:`facegeo.lighting.compress.haar2d_nonstandard`), every light coefficient's image to
    the non-standard Haar basis of the pixels' padded bounding box; one global threshold τ on
    the RGB magnitude ``√(Σ_c c²)`` keeps the entries ``≥ τ`` (RGB together: one spatial index
    for three values), τ the smallest whose dropped energy is ≤ ``target_error²`` of the
    field's (a histogram of 32 bins per octave of energy, so at most the target). Kept values
    are packed three channels and a shared exponent to 32 bits (:func:`encode_rgb`: 8
    significant bits for an entry's largest channel; with its uint16 position, 6 bytes an
    entry, the same as one light of the float16 field).

    Parameters
    ----------
    field : (P, L, 3) float16/float32, L = n_theta · n_phi
    n_theta, n_phi : int, powers of two
    pixels : (P, 2) int
        Image (row, column) of each field row, unique (e.g. ``numpy.argwhere(mask)``).
    target_error : float
        Relative Frobenius error of the field, > 0 (the relit error under a smooth
        environment is much smaller; under a sun it is that of one light's image).
    check_pixels : int
        Pixels (uniform random, ``seed``) whose exact rows are stored as float16 for
        :meth:`ImageWaveletField.field_error_estimate` and ``budget(…, total=True)``; 0: none
        (the storage of the earlier models). Counted in :attr:`ImageWaveletField.nbytes`.
    seed : int
        Seed of the check pixels' sample.
    pieces : int
        Pieces per light coefficient's slab (:data:`PIECES`), split by entry magnitude at the
        global quantiles; 1: whole slabs (the earlier models, terms = light coefficients).

    Notes
    -----
    Streams the field in bands of :data:`FIT_BAND_ROWS` image rows, twice (an energy histogram
    for the threshold, then the kept entries): each band's light coefficients (float32, as
    the in-memory transform's) go through the spatial levels finer than the band on the band
    alone; the bands' low-pass rows (float64) then take the remaining levels together. The same
    steps on the same values as one transform of the whole grid, so the same coefficients.
    Memory: one band's light coefficients, :data:`SLAB_CHUNK` slabs of one band's grid, the
    low-pass grid ``L · 3 · G / FIT_BAND_ROWS²`` float64 and the kept entries (20 bytes each
    until sorted) — not the whole field's coefficients (``P · L · 3`` float32, twice a float16
    field; ``field`` may be a ``numpy.memmap``). Deviations from the papers:
    Haar, not the 8 × 8 DCT of JPEG, across the image (one orthonormal transform whose
    threshold error is exact); fixed-size RGBE-like codes, not entropy-coded quantised values (a
    relight must read them directly).
    """

    f = field if isinstance(field, np.ndarray) else np.asarray(field)
    if f.ndim != 3 or f.shape[1:] != (n_theta * n_phi, 3) or f.dtype.kind != "f":
        raise ShapeError(f"field: expected a float field of shape (P, {n_theta * n_phi}, 3), "
                         f"got {f.shape} {f.dtype}")
    _check_pow2(n_theta, n_phi)
    t = check_positive(target_error, "target_error")
    n_p, n_l, _ = f.shape
    n_check = _count(check_pixels, "check_pixels", 0)
    n_pc = _count(pieces, "pieces", 1)
    pixel_pos, (gh, gw) = _check_pixels(pixels, n_p)
    grid = (gh, gw)
    blocks, _ = finest_blocks(pixel_pos, grid)
    row_of = coefficient_rows(grid, blocks)
    n_rows = gh * gw // 4 + 3 * blocks.size if _blocked(grid) else gh * gw
    band = min(FIT_BAND_ROWS, gh)
    base_of, step_of, wk = _band_layout(grid, band)
    detail = base_of >= 0
    low_cells = np.flatnonzero(~detail)  # the band's low-pass cells: row 0, columns < w_k
    n_band = gh // band
    y_pix = pixel_pos.astype(np.int64) // gw
    by_band = np.argsort(y_pix // band, kind="stable")
    band_ptr = np.searchsorted((y_pix // band)[by_band], np.arange(n_band + 1))
    coarse = np.zeros((n_l, 3, n_band, wk))  # the bands' low-pass rows

    def band_slabs(b: int):
        """Slab chunks of band b: ``(j0, coefficients (C, 3, band·W) float64, full grid index
        of each detail cell)`` after the band's spatial levels (low-pass rows to ``coarse``)."""
        rows = by_band[band_ptr[b]:band_ptr[b + 1]]
        cells = pixel_pos[rows].astype(np.int64) - b * band * gw
        light = np.empty((n_l, 3, rows.size), np.float32)
        for r0 in range(0, rows.size, FIT_LIGHT_ROWS):
            fr = np.asarray(f[np.sort(rows[r0:r0 + FIT_LIGHT_ROWS])], np.float64)
            inv = np.argsort(np.argsort(rows[r0:r0 + FIT_LIGHT_ROWS]))  # back to `rows` order
            c = haar2d_nonstandard(fr[inv].transpose(0, 2, 1), n_theta, n_phi)  # (r, 3, L)
            light[:, :, r0:r0 + c.shape[0]] = c.transpose(2, 1, 0)
        full = base_of[detail] + b * step_of[detail]
        for j0 in range(0, n_l, SLAB_CHUNK):
            x = np.zeros((min(n_l, j0 + SLAB_CHUNK) - j0, 3, band * gw))
            x[:, :, cells] = light[j0:j0 + x.shape[0]]
            xb = x.reshape(x.shape[0], 3, band, gw)
            _band_forward(xb, grid, band)
            coarse[j0:j0 + x.shape[0], :, b, :] = x[:, :, low_cells]
            yield j0, x[:, :, detail], full

    def coarse_slabs():
        """Slab chunks of the low-pass grid after its remaining levels, full grid indices."""
        cy, cx = np.divmod(np.arange(n_band * wk, dtype=np.int64), wk)
        full = cy * gw + cx
        for j0 in range(0, n_l, SLAB_CHUNK):
            c = coarse[j0:j0 + SLAB_CHUNK].reshape(-1, 3, n_band * wk)
            yield j0, haar2d_nonstandard(c, wk, n_band), full

    # the field's energy (Parseval: the 4-D coefficients' up to their float32 rounding), read
    # once without transforms
    total = 0.0
    for r0 in range(0, n_p, FIT_LIGHT_ROWS):
        total += float((np.asarray(f[r0:r0 + FIT_LIGHT_ROWS], np.float64) ** 2).sum())
    if not np.isfinite(total):
        raise InputError("field: non-finite samples (masked pixels) cannot be compressed; fill "
                         "or drop those pixels first")
    if total == 0.0:
        raise InputError("field: all zero; nothing to compress")
    # pass 1: histogram of squared RGB magnitudes (energy per bin) → threshold; the largest
    # channel magnitude → the codes' exponent base
    lo = np.log2(total) - 120.0
    energy = np.zeros(140 * THRESHOLD_BINS_PER_OCTAVE + 1)
    big = 0.0

    def histogram(x: np.ndarray) -> float:
        m2 = (x ** 2).sum(axis=1).ravel()
        m2 = m2[m2 > 0]
        energy[:] += np.bincount(_energy_bins(m2, lo), weights=m2, minlength=energy.size)
        return float(np.abs(x).max(initial=0.0))

    for b in range(n_band):
        for _, x, _ in band_slabs(b):
            big = max(big, histogram(x))
    coarse_done = list(coarse_slabs())
    for _, c, _ in coarse_done:
        big = max(big, histogram(c))
    dropped = np.cumsum(energy)  # energy of bins 0 … i
    i = int(np.searchsorted(dropped, t * t * total, side="right"))  # bins < i can be dropped
    tau2 = 2.0 ** (lo + i / THRESHOLD_BINS_PER_OCTAVE) if i > 0 else 0.0
    field_error = float(np.sqrt(dropped[i - 1] / total)) if i > 0 else 0.0
    code_base = _code_base(big)
    # pass 2: keep entries ≥ τ (never zeros: padding cells, τ = 0), encoded at once
    keys, codes, mags = [], [], []

    def keep(j0: int, x: np.ndarray, full: np.ndarray) -> None:
        m2 = (x ** 2).sum(axis=1)
        jj, cc = np.nonzero((m2 >= tau2) & (m2 > 0))
        rows = row_of[full[cc]]  # a detail cell of a block without pixels is 0, never kept
        keys.append((jj + j0).astype(np.int64) * n_rows + rows)
        codes.append(encode_rgb(x[jj, :, cc], code_base)[0])
        if n_pc > 1:  # the magnitudes only where they split slabs into pieces
            mags.append(m2[jj, cc])

    for b in range(n_band):
        for j0, x, full in band_slabs(b):
            keep(j0, x, full)
    for j0, c, full in coarse_done:
        keep(j0, c, full)
    key = np.concatenate(keys)
    if n_pc > 1 and key.size:  # slab j → pieces j·n + b by magnitude band b (0 the largest)
        m2 = np.concatenate(mags)
        edges = np.quantile(m2, np.arange(1, n_pc) / n_pc)
        band = (n_pc - 1) - np.searchsorted(edges, m2, side="right")
        slab, row = np.divmod(key, n_rows)
        key = (slab * n_pc + band) * n_rows + row
    order = np.argsort(key, kind="stable")  # by piece, then coefficient row
    key = key[order]
    code = np.concatenate(codes)[order]
    n_seg = -(-n_rows // (1 << 16))
    slab, row = np.divmod(key, n_rows)  # slab: the piece
    ptr = np.zeros(n_l * n_pc * n_seg + 1, np.int64)
    ptr[1:] = np.cumsum(np.bincount(slab * n_seg + (row >> 16), minlength=n_l * n_pc * n_seg))
    pos = (row & 0xFFFF).astype(np.uint16)
    frac = pos.size / (n_p * n_l)
    log.info("image wavelet field: %d entries (%.3g %% of P·L), field error %.3g for target %g",
             pos.size, 100 * frac, field_error, t)
    check = np.sort(np.random.default_rng(seed).choice(n_p, min(n_check, n_p), replace=False))
    check_rows = None
    if check.size:
        # float16 like a stored field, unless that would overflow (then float32: an inf row
        # would make every estimate NaN)
        rows32 = np.asarray(f[check], np.float32)
        big = np.abs(rows32[np.isfinite(rows32)]).max(initial=0.0) > np.finfo(np.float16).max
        check_rows = rows32 if big else rows32.astype(np.float16)
    return ImageWaveletField(ptr, int(n_seg), pos, code, int(code_base), pixel_pos, int(n_theta),
                             int(n_phi), grid, float(frac), field_error,
                             check.astype(np.int32) if check.size else None, check_rows, n_pc)
