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

Their float selects are written ``np.maximum`` / ``np.minimum`` (numba vectorises those; builtin
``max`` / ``min`` on floats stayed scalar): the pair update measured 1.49 against 3.37 ms CPU a
pair of 1280 × 1024 RGB pixels. The values are the builtin ones (no NaN reaches them: the
decoder rejects non-finite frames).

The luminance is bit-for-bit the one :func:`luminance` computes (a channel sum of integers
below 2**24 is exact in float32 whichever order it is summed in), so the decode does not change.

**Frames already in memory are read tile-major** (:func:`pairs_tiled`): when the decoder holds
several pairs at once (all of them when ``decode_stream`` is given a mapping, list or tuple),
the pixels are cut into tiles of :data:`TILE` pixels and every pair is folded into a tile before
the next tile, so the tile's accumulators stay in cache and each frame byte is read once; the
decision and the running max / min are taken on the exact integer channel sums (vectorised),
bit for bit the float32 result (the proof is in :func:`pairs_tiled`).

Threads: the frame-by-frame kernels are serial (one call per frame: ``parallel=True`` row loops
with ~50 parallel regions per decode were measured 20× slower on the shared 2-core machine at
load ≈ 7). :func:`pairs_tiled` has one ``prange`` over its tiles — one parallel region per
group and axis (two for a decode of held frames) — on numba's current thread count
(``numba.set_num_threads``).
"""

from __future__ import annotations

import functools

import numpy as np

__all__ = ["TILE", "PairGroup", "channel_sum", "int_max", "lum_reference", "luminance",
           "pair_reference", "pair_update", "pairs_tiled", "phase_reference", "phase_update",
           "sum_dtype", "tiled_ok"]


_EXACT = (np.dtype(np.uint8), np.dtype(np.uint16))  # channel sums exact below 2**24


@functools.cache
def _kernels(C: int, exact: bool):
    """The kernels for frames of ``C`` channels, flattened to 1-D (pixel-major).

    ``C`` is a compile-time constant of these closures, so the channel loop unrolls and the
    pixel loop vectorises (a run-time channel count, or 3-D indexing, kept it scalar: 4-8×
    slower, measured). ``exact``: uint8 / uint16 frames, summed as integers (uint32: exact,
    the same value as the float32 sum).

    The closures hold only ``C`` and the accumulator type (both pickle to the same bytes in
    every process): numba's cache keys a closure on its cells, and the former helper
    dispatcher in a cell made every process compile these kernels again."""
    from numba import njit

    acc = np.uint32 if exact else np.float32  # the channel sum's type

    @njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
    def lum(f, scale, out):  # pragma: no cover - compiled
        for i in range(out.shape[0]):
            s = acc(0)
            for c in range(C):
                s += acc(f[C * i + c])
            out[i] = np.float32(s) * scale

    @njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
    def csum(f, out):  # pragma: no cover - compiled
        for i in range(out.shape[0]):
            s = out.dtype.type(0)
            for c in range(C):
                s += out.dtype.type(f[C * i + c])
            out[i] = s

    @njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
    def pair(stored, ss, f, fs, stored_is_pos, words, bitval, margin, steps, lmax,
             lmin):  # pragma: no cover - compiled
        for i in range(words.shape[0]):
            a = np.float32(stored[i]) * ss
            s = acc(0)
            for c in range(C):
                s += acc(f[C * i + c])
            b = np.float32(s) * fs
            p = a if stored_is_pos else b
            q = b if stored_is_pos else a
            d = p - q
            words[i] |= bitval * words.dtype.type(d > 0)
            m = np.minimum(abs(d) * steps, np.float32(255.0))
            margin[i] = np.uint8(np.rint(m))
            # np.maximum / np.minimum: vectorised, where float max / min stay scalar
            lmax[i] = np.maximum(lmax[i], np.maximum(q, p))
            lmin[i] = np.minimum(lmin[i], np.minimum(p, q))

    @njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
    def phase(f, scale, sk, ck, S, C_, A, pmax):  # pragma: no cover - compiled
        for i in range(S.shape[0]):
            s = acc(0)
            for c in range(C):
                s += acc(f[C * i + c])
            v = np.float32(s) * scale
            pmax[i] = np.maximum(pmax[i], v)
            S[i] += sk * v
            C_[i] += ck * v
            A[i] += v

    return lum, csum, pair, phase


#: Pixels per tile of :func:`pairs_tiled`: the tile's running max / min and channel sums (int16),
#: decision words and margins stay in the core's L2 while every pair of the group passes over
#: it, and each frame is read in runs of ``3 · TILE`` bytes. 65,536: the benchmark's 42 RGB
#: frames of 1280 × 1024 decode in 22.2–22.8 ms at one thread against 28.4–29.7 ms with tiles of
#: 4,096 (AMD znver5, quiet; 23.0–24.1 against 28.6–32.6 ms at two threads; 16,384 / 32,768 /
#: 131,072: 24.3–25.1 / 23.0–23.3 / 22.6–23.1 ms, `/tmp/m24/tile.py`) — fewer switches between
#: the 40 frame streams; an earlier, loaded machine measured no difference between 1,024 and 65,536.
TILE = 65536


# Helpers of the tile kernel, compiled by _tile_helpers(): module globals, not closure cells —
# numba's cache keys a function on the pickled contents of its closure cells, and a cell
# holding a dispatcher pickles differently in every process, so a kernel that closed over its
# helpers was compiled anew in every process.
_sums_tile = _pair_tile = _merge_tile = _pair_tile_int = None


@functools.cache
def _tile_helpers() -> None:
    """Compile the per-tile loops of :func:`_pairs_tiled` into the module globals.

    The loops run over views, bounded by a view's length: indexing a full-size array at
    ``a + t`` kept them scalar (4-5x slower, measured). The channel count is a constant in each
    branch of ``_sums_tile`` (a run-time count in the index kept the loop scalar)."""
    global _sums_tile, _pair_tile, _merge_tile, _pair_tile_int
    from numba import njit

    def sums_tile(f, C, out):  # pragma: no cover - compiled
        z = out.dtype.type(0)  # int16 or int32 lanes (the sum fits, see _pairs_tiled)
        if C == 3:
            for t in range(out.shape[0]):
                out[t] = out.dtype.type(f[3 * t] + z) + out.dtype.type(f[3 * t + 1] + z) + \
                    out.dtype.type(f[3 * t + 2] + z)
        elif C == 1:
            for t in range(out.shape[0]):
                out[t] = f[t]
        else:
            for t in range(out.shape[0]):
                s = z
                for c in range(C):
                    s += out.dtype.type(f[C * t + c])
                out[t] = s

    def pair_tile(sp, sq, scale, wr, bv, mg, steps, hi, lo, k):  # pragma: no cover
        # sp, sq, hi, lo: int16 lanes for 8-bit frames (sums <= 255 C < 2**15), else int32
        if k > 0:  # the margin from |s_pos - s_neg| alone, exactly the float32 one (_diff_margin)
            for t in range(wr.shape[0]):
                a = sp[t]
                b = sq[t]
                wr[t] |= bv * wr.dtype.type(a > b)  # = (pos lum - neg lum > 0)
                mx = max(a, b)
                mn = min(a, b)
                m = np.int32(np.rint(np.float32(np.int32(mx - mn)) * k))  # int32: cvtdq2ps
                mg[t] = np.uint8(min(m, np.int32(255)))
                hi[t] = max(hi[t], mx)
                lo[t] = min(lo[t], mn)
        else:
            for t in range(wr.shape[0]):
                a = sp[t]
                b = sq[t]
                wr[t] |= bv * wr.dtype.type(a > b)
                d = np.float32(a) * scale - np.float32(b) * scale  # the float32 luminances' d
                m = np.int32(np.rint(abs(d) * steps))  # min(rint(x), 255) = rint(min(x, 255))
                mg[t] = np.uint8(min(m, np.int32(255)))
                hi[t] = max(hi[t], max(a, b))
                lo[t] = min(lo[t], min(a, b))

    def pair_tile_int(sp, sq, wr, bv, mg, hi, lo, mul):  # pragma: no cover - compiled
        # the vector block's steps (_sl_vec.pair_rgb8) for a tile's last pixels: the integer
        # margin min(((2 d + 1) mul) >> 16, 255) (_int_margin)
        for t in range(wr.shape[0]):
            a = sp[t]
            b = sq[t]
            wr[t] |= bv * wr.dtype.type(a > b)
            mx = max(a, b)
            mn = min(a, b)
            m = ((np.int64(2) * np.int64(mx - mn) + 1) * mul) >> 16
            mg[t] = np.uint8(min(m, np.int64(255)))
            hi[t] = max(hi[t], mx)
            lo[t] = min(lo[t], mn)

    def merge_tile(hi, lo, scale, lmax, lmin):  # pragma: no cover - compiled
        for t in range(lmax.shape[0]):
            lmax[t] = max(lmax[t], np.float32(hi[t]) * scale)
            lmin[t] = min(lmin[t], np.float32(lo[t]) * scale)

    jit = njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
    _sums_tile, _pair_tile, _merge_tile = jit(sums_tile), jit(pair_tile), jit(merge_tile)
    _pair_tile_int = jit(pair_tile_int)


@functools.cache
def _pairs_tiled(parallel: bool):
    """Tile-major pair kernel for integer frames (see :func:`pairs_tiled`).

    Integer domain: the decision and the running max / min are taken on the exact channel
    sums (``pairs_tiled`` says why that is the float32 result), in int16 lanes for 8-bit frames
    (sums <= 255 C < 2**15: twice the lanes of int32; ``lo_init`` carries the lane type) and,
    when ``k > 0``, the margin from the sums' difference (:func:`_diff_margin`); numba
    vectorises these integer loops, where its float compare-and-select loops stayed scalar
    (measured 0.6 ns against 0.03 ns a pixel for a running max). In cache (one 4096-pixel tile,
    repeated): the channel sums of an RGB frame 0.16 ns a pixel in int16 lanes against 0.30 in
    int32, the pair update 0.31 ns against 0.38 (the float32 products in int32 lanes).

    ``parallel`` is the only closure cell (read in the body: numba's cache keys a kernel on its
    cells, not on the decorator's flags — before, the serial and the parallel kernel shared one
    cache entry and whichever was compiled last ran for both); the helpers are module globals
    (see ``_sums_tile``), so the kernel is compiled once per machine, not once per process."""
    from numba import njit, prange

    _tile_helpers()

    @njit(cache=True, nogil=True, boundscheck=False, error_model="numpy", parallel=parallel)
    def pairs(frames, C, pos, neg, scale, rows, bitvals, planes, words, margin, steps, lmax,
              lmin, tile, lo_init, k, p_lo, p_hi, off):  # pragma: no cover - compiled
        # lo_init: the channel sums' lane type (int16 / int32) at its largest value; pixels
        # p_lo … p_hi - 1 of the frames, accumulator column = pixel - off
        n_tiles = (p_hi - p_lo + tile - 1) // tile
        if not parallel:  # (the cache key, see above)
            n_tiles = n_tiles + 0
        for ti in prange(n_tiles):  # tiles outermost (a thread's share) ...
            a = p_lo + ti * tile
            b = min(p_hi, a + tile)
            a_, b_ = a - off, b - off
            lo = np.full(b - a, lo_init)  # running min / max channel sum
            hi = np.full(b - a, lo_init)
            hi[:] = -1
            sp = np.empty_like(lo)  # the pair's channel sums over the tile
            sq = np.empty_like(lo)
            for o in range(pos.shape[0]):  # ... every pair over the tile, in cache
                _sums_tile(frames[pos[o]][C * a:C * b], C, sp)
                _sums_tile(frames[neg[o]][C * a:C * b], C, sq)
                _pair_tile(sp, sq, scale, words[rows[o]][a_:b_], bitvals[o],
                           margin[planes[o]][a_:b_], steps, hi, lo, k)
            _merge_tile(hi, lo, scale, lmax[a_:b_], lmin[a_:b_])

    return pairs


def _tail(sp, sq, scale, wr, bv, mg, steps, hi, lo, k):  # pragma: no cover - compiled only
    """The 8-bit RGB kernel's last ``n mod 32`` pixels of a tile: ``_pair_tile`` with a float32
    ``k``, ``_pair_tile_int`` with the integer multiplier (the vector block's two margins);
    chosen by ``k``'s type when numba compiles the kernel (:func:`_register_tail`)."""
    raise NotImplementedError("compiled only")


@functools.cache
def _register_tail() -> None:
    """Register :func:`_tail`'s compiled implementations (one per type of ``k``)."""
    from numba import types
    from numba.extending import overload

    @overload(_tail)
    def _tail_impl(sp, sq, scale, wr, bv, mg, steps, hi, lo, k):
        if isinstance(k, types.Integer):
            def impl(sp, sq, scale, wr, bv, mg, steps, hi, lo, k):  # pragma: no cover
                _pair_tile_int(sp, sq, wr, bv, mg, hi, lo, k)
        else:
            def impl(sp, sq, scale, wr, bv, mg, steps, hi, lo, k):  # pragma: no cover
                _pair_tile(sp, sq, scale, wr, bv, mg, steps, hi, lo, k)
        return impl


# The vector block and prefetch of 8-bit RGB pairs (facegeo.geometry._sl_vec), set by
# _pairs_rgb8(): module globals for the same reason as the tile helpers.
_pair_rgb8 = _pair2_rgb8 = _prefetch = _u8_ptr = _prefetch2 = None


@functools.cache
def _pairs_rgb8(parallel: bool, with_min: bool = False):
    """Tile-major pair kernel for 8-bit RGB frames with the one-product margin (``k > 0``):
    :func:`_pairs_tiled`'s loops as one vector block per 32 pixels
    (:func:`facegeo.geometry._sl_vec.pair_rgb8`, the same values bit for bit) with each
    frame prefetched :data:`~facegeo.geometry._sl_vec.PREFETCH_BYTES` ahead; two consecutive
    pairs of one code family (``rows``) fold together
    (:func:`~facegeo.geometry._sl_vec.pair2_rgb8`), an odd one or a change of family alone;
    the tile's last ``n mod 32`` pixels go through the plain helpers. ``with_min``: also the
    running min of each code family's margins (``mmin``, row ``rows[o]``), which the finish
    would otherwise take plane by plane (``_sl_finish``: ``mmin``).

    ``parallel``, ``with_min`` and the source hash of ``_sl_vec.py`` are read in the body, so they
    are closure cells and part of numba's cache key
    (a flag of the decorator alone is not: the serial and the parallel kernel shared one
    cache entry, and whichever was compiled last ran for both)."""
    global _pair_rgb8, _pair2_rgb8, _prefetch, _u8_ptr, _prefetch2
    from numba import carray, njit, prange

    from facegeo.geometry import _sl_vec

    _tile_helpers()
    _register_tail()
    _pair_rgb8, _pair2_rgb8, _prefetch = _sl_vec.pair_rgb8, _sl_vec.pair2_rgb8, _sl_vec.prefetch
    _u8_ptr = _sl_vec.u8_ptr

    def prefetch2(f, g, q):  # pragma: no cover - compiled
        # a block advances 96 bytes a frame: two lines from q cover every byte once
        _prefetch(f, q)
        _prefetch(g, q)
        _prefetch(f, q + 64)
        _prefetch(g, q + 64)

    _prefetch2 = njit(cache=True, nogil=True, inline="always")(prefetch2)
    lanes, ahead = _sl_vec.LANES, _sl_vec.PREFETCH_BYTES
    # numba's disk cache sees this file (its modification time) and the kernel's closure cells,
    # not _sl_vec.py, whose code generation the kernel inlines: the source hash of _sl_vec.py
    # is a cell, read below, so an edit there compiles the kernel again
    vec_source = _sl_vec.source_hash()

    @njit(cache=True, nogil=True, boundscheck=False, error_model="numpy", parallel=parallel)
    def pairs(addrs, size, pos, neg, scale, rows, bitvals, planes, words, margin, steps, lmax,
              lmin, tile, k, p_lo, p_hi, off, mmin, sums, hsum,
              lsum):  # pragma: no cover - compiled
        # addrs / size: the frames' data addresses and their length (uint8 elements, all the
        # same), viewed in place (FrameSet: the caller keeps the arrays alive)
        n_tiles = (p_hi - p_lo + tile - 1) // tile
        if not parallel or not vec_source:  # (the cache key, see above)
            n_tiles = n_tiles + 0
        for ti in prange(n_tiles):
            a = p_lo + ti * tile
            b = min(p_hi, a + tile)
            a_, b_ = a - off, b - off
            n = b - a
            n_vec = n - n % lanes
            if sums:  # the caller's running max / min channel sums (lmax / lmin untouched)
                hi = hsum[a_:b_]
                lo = lsum[a_:b_]
            else:  # the tile's, merged into lmax / lmin below
                lo = np.full(n, np.int16(32767))
                hi = np.full(n, np.int16(-1))
            sp = np.empty(n % lanes, np.int16)  # the tail's channel sums
            sq = np.empty(n % lanes, np.int16)
            n_pairs = pos.shape[0]
            o = 0
            while o < n_pairs:
                # two consecutive pairs of one family fold together (pair2_rgb8): the family's
                # accumulators are loaded and stored once for both
                two = o + 1 < n_pairs and rows[o + 1] == rows[o]
                o2 = o + 1 if two else o
                fp = carray(_u8_ptr(addrs[pos[o]]), size)
                fq = carray(_u8_ptr(addrs[neg[o]]), size)
                fp2 = carray(_u8_ptr(addrs[pos[o2]]), size)
                fq2 = carray(_u8_ptr(addrs[neg[o2]]), size)
                # past the end of this group's run the prefetch runs on into the next group's
                # (the next tile's first group after the last): the core does not wait at
                # each run's start (tiles of 16,384 pixels: 40 runs of 48 KB)
                last = o2 + 1 == n_pairs
                nx = 0 if last else o2 + 1
                nx2 = nx + 1 if nx + 1 < n_pairs and rows[nx + 1] == rows[nx] else nx
                np1 = carray(_u8_ptr(addrs[pos[nx]]), size)
                nq1 = carray(_u8_ptr(addrs[neg[nx]]), size)
                np2 = carray(_u8_ptr(addrs[pos[nx2]]), size)
                nq2 = carray(_u8_ptr(addrs[neg[nx2]]), size)
                skip = 0 if last else 3 * (a - b)
                wv = words[rows[o]][a_:b_]
                mg = margin[planes[o]][a_:b_]
                mg2 = margin[planes[o2]][a_:b_]
                mm = mmin[rows[o]][a_:b_]
                bv, bv2 = bitvals[o], bitvals[o2]
                if two:
                    for t in range(0, n_vec, lanes):
                        q = 3 * (a + t) + ahead
                        if q < 3 * b:
                            _prefetch2(fp, fq, q)
                            _prefetch2(fp2, fq2, q)
                        else:  # (the next group's)
                            _prefetch2(np1, nq1, q + skip)
                            _prefetch2(np2, nq2, q + skip)
                        if with_min:
                            _pair2_rgb8(fp, fq, fp2, fq2, a + t, wv, bv, bv2, mg, mg2, k, hi,
                                        lo, t, mm)
                        else:
                            _pair2_rgb8(fp, fq, fp2, fq2, a + t, wv, bv, bv2, mg, mg2, k, hi,
                                        lo, t, None)
                else:
                    for t in range(0, n_vec, lanes):
                        q = 3 * (a + t) + ahead
                        if q < 3 * b:
                            _prefetch2(fp, fq, q)
                        else:
                            _prefetch2(np1, nq1, q + skip)
                            _prefetch2(np2, nq2, q + skip)
                        if with_min:
                            _pair_rgb8(fp, fq, a + t, wv, bv, mg, k, hi, lo, t, mm)
                        else:
                            _pair_rgb8(fp, fq, a + t, wv, bv, mg, k, hi, lo, t, None)
                if n_vec < n:
                    for oo in range(o, o2 + 1):
                        g = mg if oo == o else mg2
                        _sums_tile(carray(_u8_ptr(addrs[pos[oo]]), size)[3 * (a + n_vec):3 * b],
                                   3, sp)
                        _sums_tile(carray(_u8_ptr(addrs[neg[oo]]), size)[3 * (a + n_vec):3 * b],
                                   3, sq)
                        _tail(sp, sq, scale, wv[n_vec:], bitvals[oo], g[n_vec:], steps,
                              hi[n_vec:], lo[n_vec:], k)
                        if with_min:
                            for t in range(n_vec, n):
                                mm[t] = min(mm[t], g[t])
                o = o2 + 1
            if not sums:
                _merge_tile(hi, lo, scale, lmax[a_:b_], lmin[a_:b_])

    return pairs


def _float_margin(sp, sq, scale, steps) -> np.ndarray:
    """The margin of channel sums ``sp``, ``sq`` as the float32 kernels compute it:
    ``min(rint(|float32(sp) · scale - float32(sq) · scale| · steps), 255)`` (numpy float32)."""
    f32 = np.float32
    d = sp.astype(f32) * f32(scale) - sq.astype(f32) * f32(scale)
    return np.minimum(np.rint(np.abs(d) * f32(steps)), f32(255.0)).astype(np.int64)


@functools.cache
def _int_margin(top: int, k: float) -> int:
    """The multiplier ``m`` of the 8-bit RGB vector block's integer margin
    (``_sl_vec.pair_rgb8``: ``min(((2 d + 1) · m) >> 16, 255)``, a 16-bit high multiply) that
    equals the one-product margin ``min(rint(float32(d) · k), 255)`` (:func:`_diff_margin`'s)
    for **every** sum difference ``0 <= d <= top``, checked exhaustively over the two
    multipliers nearest ``k · 2**15``; 0 when neither does (the kernel then takes the plain
    loops). ``(2 d + 1) m / 2**16 ≈ d k + k / 2``: for ``k = 2/3`` (8-bit RGB at the default
    full scale, ``m = 21846``) ``floor(d · 2/3 + 1/3)`` is ``rint(d · 2/3)``, whose fractions are
    0, 1/3 and 2/3."""
    k32 = np.float32(k)
    if not 0 < k32 or top > 1023:
        return 0
    d = np.arange(top + 1, dtype=np.int64)
    want = np.minimum(np.rint(d.astype(np.float32) * k32), np.float32(255.0)).astype(np.int64)
    base = float(k32) * 32768.0
    for m in sorted({int(np.floor(base)), int(np.ceil(base))}):
        if 0 < m < 2 ** 16 and np.array_equal(np.minimum(((2 * d + 1) * m) >> 16, 255), want):
            return m
    return 0


@functools.cache
def _diff_margin(top: int, scale: float, steps: float) -> float:
    """``k`` (float32) with ``min(rint(float32(|s1 - s2|) · k), 255)`` equal to the float32
    margin (:func:`_float_margin`) for **every** pair of channel sums ``0 <= s1, s2 <= top``,
    checked exhaustively (``(top + 1)**2`` pairs, only for ``top <= 1023``: 8-bit frames of up
    to 4 channels), or 0 when it is not (the kernel then keeps the two products). One convert
    and one product a pixel instead of two converts, two products and a difference; with the
    default full scale the check passes (``k = 2/3`` for RGB: the float32 rounding never lands
    on a rounding tie)."""
    if top > 1023:
        return 0.0
    k = np.float32(np.float32(scale) * np.float32(steps))
    s = np.arange(top + 1, dtype=np.int64)
    s1, s2 = np.meshgrid(s, s, indexing="ij")
    got = np.minimum(np.rint(np.abs(s1 - s2).astype(np.float32) * k), np.float32(255.0))
    return float(k) if np.array_equal(got.astype(np.int64), _float_margin(s1, s2, scale, steps)) \
        else 0.0


@functools.cache
def int_max(dtype) -> int:
    """``np.iinfo(dtype).max``, cached (the lookup costs ≈ 0.5 µs, paid per frame)."""
    return int(np.iinfo(dtype).max)


def tiled_ok(dtype, channels: int, scale: float, steps: float) -> bool:
    """Whether :func:`pairs_tiled` takes frames of this dtype / channel count / luminance
    scale: integer channel sums below 2**22 (so ``sum_a > sum_b`` is exactly ``float32(sum_a) ·
    scale > float32(sum_b) · scale``) and margins ``|d| · steps`` below 2**30 (int32)."""
    dtype = np.dtype(dtype)
    if dtype not in _EXACT or channels < 1 or not 1e-30 < scale:
        return False
    top = float(int_max(dtype)) * channels
    return top < 2 ** 22 and top * scale * steps < 2 ** 30


def pairs_tiled(frames, pos, neg, scale: float, rows, bits, planes, words, margin,
                steps: float, lmax, lmin, *, tile: int = TILE, parallel: bool = True,
                diff_margin: bool = True, vector: bool = True) -> None:
    """Fold several pattern / inverse pairs into the accumulators in place, **tile-major**.

    The pixels are cut into tiles of ``tile`` pixels (outer loop, ``prange`` over the tiles:
    one parallel region for the whole group, on numba's current thread count when
    ``parallel``); for each tile every pair is folded in turn (inner loop), so each frame byte
    is read once from memory and the tile's accumulators (running max / min, decision words,
    channel sums) stay in cache across the pairs — the frame-by-frame :func:`pair_update`
    streams the full-size float32 ``L_max`` / ``L_min`` through memory once per pair.

    Exactly :func:`pair_update` (``pair_reference``) per pair, in the integer domain: all frames
    share one luminance ``scale`` (one dtype and channel count, :func:`tiled_ok`), and for
    channel sums ``0 <= s1 < s2 < 2**22`` the float32 products satisfy ``float32(s2) · scale -
    float32(s1) · scale >= scale (s2 - s1) - 2**-24 scale (s1 + s2) > 0``, so the decision
    ``pos > neg``, the max and the min are taken on the sums, and ``L_max = float32(max sum) ·
    scale`` (rounding is monotone). The margin is computed from the two float32 luminances as
    before, or for 8-bit frames from ``|s_pos - s_neg|`` with one product when that is the same
    for every pair of sums (:func:`_diff_margin`, checked exhaustively). Bit for bit the
    frame-by-frame result in any tile size and thread count (tested).

    Parameters
    ----------
    frames : list of (H, W[, C]) uint8 or uint16 arrays
        One dtype and channel count for all.
    pos, neg : (K,) int
        Indices into ``frames`` of pair ``o``'s pattern and inverse.
    scale : float
        Luminance = channel sum times ``scale`` (float32).
    rows : (K,) int
        Row of ``words`` (the code family) pair ``o`` sets its bit in.
    bits : (K,) int
        Bit of the word pair ``o`` decides (``pattern > inverse``).
    planes : (K,) int
        Plane of ``margin`` pair ``o`` writes.
    words : (F, H, W) unsigned int array, C-contiguous
    margin : (n, H, W) uint8 array, C-contiguous
    steps : float
        Margin quantisation (``min(rint(|pos - neg| steps), 255)``).
    lmax, lmin : (H, W) float32, C-contiguous
        Running max / min of the luminances (updated with the group's).
    diff_margin : bool
        Take the margin from the sums' difference when :func:`_diff_margin` finds that exact
        for this ``scale`` / ``steps`` (8-bit frames); False: always the two float32 products
        (the tests compare both).
    vector : bool
        8-bit RGB frames with the one-product margin: the vector block and prefetch of
        :func:`_pairs_rgb8` (default); False: the plain tile loops (the tests compare both).
    """
    PairGroup(frames, pos, neg, scale, rows, bits, planes, steps, words.dtype,
              parallel=parallel, diff_margin=diff_margin, vector=vector).run(
        words, margin, lmax, lmin, tile=tile)


class FrameSet:
    """Held frames as the pair kernels take them: flat C-contiguous views of one size and
    dtype (kept alive here while any kernel runs on them), their data addresses (int64) and
    element count for the 8-bit RGB kernel, which views each frame in place (``numba.carray``),
    and a numba typed list of them for the plain tile loops, made on first use (≈ 4 µs a frame;
    the 8-bit RGB decode paid it on every call when all kernels took the list). Frames of
    another size or dtype: ValueError (the kernels read every frame as the first one's)."""

    def __init__(self, frames):
        self.arrays = [np.ascontiguousarray(f).reshape(-1) for f in frames]
        kinds = {(a.size, a.dtype) for a in self.arrays}
        if len(kinds) != 1:
            raise ValueError(f"FrameSet: frames of {len(kinds)} different sizes / dtypes "
                             f"({sorted((n, str(d)) for n, d in kinds)[:4]}); one of each only")
        self.size = self.arrays[0].size
        self.addrs = np.array([a.__array_interface__["data"][0] for a in self.arrays], np.int64)
        self._typed = None

    def __len__(self) -> int:
        return len(self.arrays)

    @property
    def typed(self):
        """The frames as a numba typed list (made once)."""
        if self._typed is None:
            from numba.typed import List

            self._typed = List(self.arrays)
        return self._typed


class PairGroup:
    """A group of pattern / inverse pairs prepared once for :func:`pairs_tiled`'s kernels and
    folded over any run of pixels (:meth:`run`), so a decode can fold and finish chunk by chunk
    with chunk-sized accumulators (``StreamDecoder.finish``) without preparing the frames'
    list for every chunk. The parameters are :func:`pairs_tiled`'s; ``word_dtype`` is the
    decision words' dtype; ``flats``: the frames as a :class:`FrameSet`, to share one set
    between groups of the same frames."""

    def __init__(self, frames, pos, neg, scale: float, rows, bits, planes, steps: float,
                 word_dtype, *, parallel: bool = True, diff_margin: bool = True,
                 vector: bool = True, flats=None):
        f0, C = _flat(frames[0])
        if not tiled_ok(f0.dtype, C, scale, steps):
            raise ValueError(f"pairs_tiled: frames of dtype {f0.dtype} with {C} channels at "
                             f"scale {scale} are not exact in the integer domain (check "
                             "tiled_ok first)")
        self.flats = FrameSet(frames) if flats is None else flats
        self.pixels = f0.size // C
        idx = lambda v: np.ascontiguousarray(v, np.int64)
        self.pos, self.neg, self.rows, self.planes = idx(pos), idx(neg), idx(rows), idx(planes)
        wd = np.dtype(word_dtype)
        self.bitvals = (np.ones(len(bits), wd) << np.asarray(bits, wd)).astype(wd)
        top = int_max(f0.dtype) * C
        self.k = np.float32(_diff_margin(top, float(scale), float(steps)) if diff_margin
                            else 0.0)
        self.scale, self.steps, self.C = np.float32(scale), np.float32(steps), C
        lane = np.int16 if top < 2 ** 15 else np.int32  # 8-bit frames: twice the lanes
        self.lo_init = lane(np.iinfo(lane).max)
        self.rgb8 = bool(f0.dtype == np.uint8 and C == 3 and self.k > 0 and vector)
        # the vector block's margin: the integer multiplier where one gives the float32 margins
        # (a 16-bit high multiply), else the float32 k (numba compiles the block for each)
        self.mul = np.int64(_int_margin(top, float(self.k)) if self.k > 0 else 0)
        self.margin_k = self.mul if self.mul > 0 else self.k
        self.parallel = bool(parallel)
        self.kernel = (_pairs_rgb8 if self.rgb8 else _pairs_tiled)(self.parallel)
        # built here, not in the chunk threads that run it (one dispatcher, one compile)
        self.kernel_min = _pairs_rgb8(self.parallel, True) if self.rgb8 else None
        self.plain = _pairs_tiled(self.parallel) if self.rgb8 else self.kernel

    def run(self, words, margin, lmax, lmin, *, start: int = 0, stop: int | None = None,
            offset: int = 0, tile: int = TILE, mmin=None) -> bool:
        """Fold pixels ``start … stop - 1`` (flat, row-major) into the accumulators, whose
        column ``p - offset`` is pixel ``p``: ``words`` (F, N), ``margin`` (n, N), ``lmax`` /
        ``lmin`` (N,), or the full-size (…, H, W) arrays with ``offset`` 0.

        ``mmin``: (F, N) uint8, the running min of each code family's margins, updated when
        the 8-bit RGB vector kernel runs (it costs nothing there); returns whether it was
        (otherwise the finish takes the min plane by plane)."""
        stop = self.pixels if stop is None else int(stop)
        W, M = _view(words, (words.shape[0], -1), "words"), _view(margin, (margin.shape[0], -1),
                                                                   "margin")
        lmax, lmin = _view(lmax, (-1,), "lmax"), _view(lmin, (-1,), "lmin")
        if W.dtype != self.bitvals.dtype:
            raise ValueError(f"PairGroup.run: words of dtype {W.dtype}, prepared for "
                             f"{self.bitvals.dtype}")
        args = (self.pos, self.neg, self.scale, self.rows, self.bitvals, self.planes, W, M,
                self.steps, lmax, lmin, int(tile))
        MM = None if mmin is None else _view(mmin, (mmin.shape[0], -1), "mmin")
        # the vector block stores 32 consecutive elements: C-contiguous accumulators only
        # (a strided view takes the plain loops, which honour strides)
        if self.rgb8 and all(a.flags.c_contiguous for a in (W, M, lmax, lmin)
                             if a is not None):
            no = np.empty(0, np.int16)  # (no caller-held channel sums)
            fs = self.flats
            if MM is not None and MM.flags.c_contiguous:
                self.kernel_min(fs.addrs, fs.size, *args, self.margin_k, int(start), stop,
                                int(offset), MM, False, no, no)
                return True
            self.kernel(fs.addrs, fs.size, *args, self.margin_k, int(start), stop, int(offset),
                        M, False, no, no)
            return False
        self.plain(self.flats.typed, self.C, *args, self.lo_init, self.k, int(start), stop,
                   int(offset))
        return False


def _view(a: np.ndarray, shape: tuple, name: str) -> np.ndarray:
    """``a`` reshaped to ``shape`` as a view of the same memory — the kernels write into it —
    or ValueError: ``reshape`` would copy an accumulator whose layout cannot be reshaped in
    place (a column crop of a larger array, say) and the results would be lost with the copy."""
    v = a.view()
    try:
        v.shape = shape
    except AttributeError:
        raise ValueError(f"{name}: an array of shape {a.shape} and strides {a.strides} that "
                         f"cannot be seen as {shape} without a copy (results written into a "
                         "copy would be lost); pass a C-contiguous array") from None
    return v


def _flat(a: np.ndarray) -> tuple[np.ndarray, int]:
    """A frame as a C-contiguous 1-D array (pixel-major) and its channel count."""
    C = a.shape[2] if a.ndim == 3 else 1
    return np.ascontiguousarray(a).reshape(-1), C


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
    """Channel sum of an (H, W[, C]) frame times ``scale``, float32 (H, W)."""
    f, C = _flat(a)
    out = np.empty(a.shape[:2], np.float32)
    exact = f.dtype in _EXACT and sum_dtype(f.dtype, C) is not None
    _kernels(C, exact)[0](f, np.float32(scale), out.reshape(-1))
    return out


def channel_sum(a: np.ndarray) -> np.ndarray:
    """Exact integer channel sum of a uint8 / uint16 (H, W[, C]) frame, (H, W) of
    :func:`sum_dtype` (the stored half of a pattern / inverse pair)."""
    f, C = _flat(a)
    out = np.empty(a.shape[:2], sum_dtype(a.dtype, C))
    _kernels(C, True)[1](f, out.reshape(-1))
    return out


def pair_update(pos, neg, words, bit: int, margin, steps: float, lmax, lmin, *,
                pos_scale: float = 1.0, neg_scale: float = 1.0) -> None:
    """Fold a pattern / inverse pair into the accumulators in place (see ``pair_reference``).

    ``pos`` / ``neg``: each (H, W) float32 luminance, a :func:`channel_sum` or an (H, W[, C])
    frame, whose luminance is its channel sum times ``pos_scale`` / ``neg_scale`` (formed in
    registers, as :func:`luminance` would). At most one may have channels; the accumulators
    must be C-contiguous (H, W) arrays (written in place)."""
    stored_is_pos = not (pos.ndim == 3 and pos.shape[2] > 1)
    (s, ss), (f, fs) = ((pos, pos_scale), (neg, neg_scale)) if stored_is_pos else \
        ((neg, neg_scale), (pos, pos_scale))
    f, C = _flat(f)
    exact = f.dtype in _EXACT and sum_dtype(f.dtype, C) is not None
    _kernels(C, exact)[2](np.ascontiguousarray(s).reshape(-1), np.float32(ss), f,
                          np.float32(fs), stored_is_pos, words.reshape(-1),
                          words.dtype.type(1 << bit), margin.reshape(-1), np.float32(steps),
                          lmax.reshape(-1), lmin.reshape(-1))


def phase_update(a, scale: float, sin_k: float, cos_k: float, S, C, A, pmax) -> None:
    """Fold a phase frame (its luminance = channel sum times ``scale``) into the phase sums in
    place (see ``phase_reference``): ``a`` an (H, W[, C]) frame, or (H, W) float32 luminance
    with ``scale`` 1. The sums must be C-contiguous (H, W) arrays."""
    f, Ch = _flat(a)
    exact = f.dtype in _EXACT and sum_dtype(f.dtype, Ch) is not None
    _kernels(Ch, exact)[3](f, np.float32(scale), np.float32(sin_k), np.float32(cos_k),
                           S.reshape(-1), C.reshape(-1), A.reshape(-1), pmax.reshape(-1))


def lum_reference(a: np.ndarray, scale: float) -> np.ndarray:
    """Plain numpy :func:`luminance`."""
    a = a[:, :, None] if a.ndim == 2 else a
    return (a.astype(np.float32).sum(axis=2) * np.float32(scale)).astype(np.float32)


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
