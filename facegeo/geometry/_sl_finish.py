"""Compiled end of the streaming structured-light decode: the bit decode of a run of pixels.

Private kernel behind :meth:`facegeo.geometry._sl_stream.StreamDecoder.finish`. For one axis and
a run of pixels it does what the numpy reference (``_sl_stream._bit_words``, ``_decode_axis``,
``_partial_codes``; run with ``_sl_stream.KERNELS = False``) does with several full-size planes
per family: read each pixel's decision word and its ``n`` margins per code family, apply the XOR
base plane (Gupta et al. 2013, Sec. 4.2), Gray → binary (or a long-run code's code → stripe
table), find the first unresolved plane, the
boundary / phase-picked / coarse-block coordinate of a partly resolved code, the weakest used
margin (confidence), the per-bit statistics and the consistency vote across families
(Sec. 4.3); on an axis with phase frames also the wrapped phase and fringe amplitude
(:func:`phase`, Srinivasan et al. 1984) and the unwrapping with the code (:func:`phase_merge`).
The method is written down in ``docs/structured-light.md``.

Tiles of ``_TILE`` pixels. Per family the smallest of the pixel's ``n`` margins is taken
plane by plane over the tile (uint8 ``min``, vectorised); a pixel is *fully resolved* when that
smallest margin is reliable — ``float32(m) · mscale >= tau`` is monotone in ``m``, so the
smallest margin passes exactly when every plane does — and fully resolved pixels decode in one
vectorised pass (XOR base, Gray → binary, coordinate, σ, confidence; with one family the
axis's outputs are written there, ``NaN`` as ``0 / 0``). Only the other pixels take the scalar
path: their reliable planes one by one, partial codes, statistics; a tile without such pixels
skips it. Then the vote. The kernel does the reference's arithmetic (the same float32 / float64
steps in the same order), so codes, validity and statistics are identical and ``x`` / ``y`` /
``sigma`` / ``confidence`` equal (tested in tests/test_decode.py; bit for bit against the
former kernel on the benchmark's frames). Margins are never NaN here (the decoder rejects
non-finite frames), so plain ``min`` stands for ``np.minimum``.

The fully-resolved pass of a lone family writing the final outputs runs over the whole run at
once, 16 pixels at a time in a block of LLVM vector code (``_sl_vec.direct_block``; a scalar
loop with the same steps for the last pixels): 1.42 → 0.78 ns a pixel-axis for the benchmark's
chunks (the 512-pixel tiles' fixed costs and numba's 8-lane loop); other passes write their
selects as ``np.maximum`` / ``np.minimum`` (numba vectorises those, not ``min`` / ``max`` /
conditional expressions on floats). One axis of the benchmark's
1280 × 1024 frames (10 Gray bits, every pixel resolved) in one call, 1 thread, CPU time, load
≈ 11: 5.5–5.8 ns a pixel, against 13.3–18.4 for the former kernel (a per-pixel threshold
search, ten per-plane reliability passes, a separate store loop with a gather), interleaved.
The kernels are serial; ``StreamDecoder.finish`` runs the chunks on its ``threads`` Python
threads (the kernels release the GIL).

:func:`fused_chunk` runs the whole fold and finish of a chunk of held 8-bit RGB frames in one
compiled call (pair kernel, start, axes, validity), in cache-sized sub-runs.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from facegeo.geometry._sl_codes import long_run_words, stripe_table

__all__ = ["code_tables", "decode_axis", "fused_chunk", "phase", "phase_merge", "prepare",
           "stripe_gray_tables", "stripe_gray_words"]

_TILE = 512  # pixels per tile: the plane-major passes run over a tile in cache


# The compiled helpers are module globals, set by _kernel(): numba's cache keys a function on
# the pickled contents of its closure cells, and a dispatcher pickles differently in every
# process, so kernels that closed over their helpers were compiled again in every process
# (~20 s, measured); globals are not part of the key.
_min_nan = _max_nan = _store = _binary = _direct = _start = _direct_block = _lit_rgb8 = None
_direct_consts = _xor_base = _start_block = _store_fence = None
_lanes = 16


@functools.cache
def _kernel():
    global _min_nan, _max_nan, _store, _binary, _direct, _start, _direct_block, _lanes, _lit_rgb8
    global _direct_consts, _xor_base, _start_block, _store_fence
    from numba import njit

    from facegeo.geometry import _sl_vec

    _direct_block, _lanes, _lit_rgb8 = _sl_vec.direct_block, _sl_vec.DIRECT_LANES, _sl_vec.lit_rgb8
    _start_block, _store_fence = _sl_vec.start_block, _sl_vec.store_fence
    # numba's cache sees this file, not _sl_vec.py, whose code the kernels inline: its source
    # hash is a closure cell of direct (read there), so an edit of _sl_vec.py compiles again
    vec_source = _sl_vec.source_hash()

    def min_nan(a, b):  # np.minimum: NaN propagates
        if a <= b:
            return a
        return b if (b < a or b != b) else a

    def max_nan(a, b):  # np.maximum: NaN propagates, ties keep a
        if a >= b:
            return a
        return b if (b > a or b != b) else a

    def store(p, final, ok, coord, sig, conf, coord_out, sig_out, ok_out, conf_out):
        # final: the axis's outputs as decode_stream returns them (NaN where invalid) and the
        # running min of the confidence over the axes; else the raw values for the phase step
        ok_out[p] = ok
        if final and not ok:
            coord_out[p] = np.nan
            sig_out[p] = np.nan
            conf_out[p] = _min_nan(conf_out[p], np.float32(0.0))
            return
        coord_out[p] = np.float32(coord)
        sig_out[p] = np.float32(sig)
        conf_out[p] = _min_nan(conf_out[p], conf) if final else conf

    def binary(word, high, sb):
        # a decision word as a binary stripe index: for an XOR code the planes above the base
        # were projected XORed with it (``high`` their mask, ``sb`` the base's shift; high = 0
        # for other codes), then Gray -> binary as a prefix XOR (n <= 32)
        x = np.int64(word)
        x ^= high * ((x >> sb) & 1)
        x ^= x >> 1
        x ^= x >> 2
        x ^= x >> 4
        x ^= x >> 8
        x ^= x >> 16
        return x

    def direct_consts(step, coarse_lim):
        # the fully resolved pass's per-axis constants: a stripe's centre offset, whether a
        # fully resolved code names one stripe, and its sigma (float32)
        return (0.5 * (step - 1.0), step <= coarse_lim + 1e-9,
                np.float32(1.0 * step / math.sqrt(12.0)))

    def xor_base(b, n):
        # a family's XOR base plane b (or -1) as the pass takes it: the planes above it as a
        # mask, and the bit that holds the base
        if b > 0:
            return ((np.int64(1) << b) - 1) << (n - b), n - 1 - b
        return np.int64(0), 0

    def direct(sg, mi, tau, lit, ref, cov, sov, oov, qov, slv, mscale, high, sb, n_stripes,
               one_stripe_ok, step, c0, sig_one):
        # the fully resolved pass of one family writing the axis's final outputs (see
        # axis_pixels), 16 pixels a block of _sl_vec.direct_block and this loop's same steps
        # for the rest (numba's own loop of them: 0.65 ns a pixel in cache, the block 0.42).
        # A slow pixel (a plane below tau) keeps its running min of the confidence (its own
        # path sets it after) and is flagged in slv.
        zero = np.float32(0.0)
        one = np.float32(1.0)
        tiny = np.float32(1e-12)
        if not vec_source:  # (the cache key, see above)
            zero = one
        n_slow = np.int32(0)
        h32 = np.int32(high)
        s32 = np.int32(sb)
        ns32 = np.int32(min(n_stripes, 2 ** 31 - 1))
        P = tau.shape[0]
        lanes = _lanes
        n_vec = P - P % lanes
        for t in range(0, n_vec, lanes):  # _sl_vec.direct_block: the same steps, 16 lanes
            n_slow += np.int32(_direct_block(sg, mi, tau, lit, ref, cov, sov, oov, qov, slv, t,
                                             mscale, high, sb, n_stripes, one_stripe_ok, step,
                                             c0, sig_one, False))
        for t in range(n_vec, P):  # the tail
            x = np.int32(sg[t])  # n <= 31 bits
            x ^= h32 * ((x >> s32) & np.int32(1))
            x ^= x >> np.int32(1)
            x ^= x >> np.int32(2)
            x ^= x >> np.int32(4)
            x ^= x >> np.int32(8)
            x ^= x >> np.int32(16)
            m = np.float32(mi[t]) * mscale
            good = m >= tau[t]
            slv[t] = np.uint8(not good)
            n_slow += np.int32(not good)
            o = lit[t] & (x < ns32) & one_stripe_ok & good
            z = zero / np.float32(o)  # + z: NaN where not ok (x86's 0 / 0, as the block)
            oov[t] = o
            cov[t] = np.float32(np.float64(x) * step + c0) + z
            sov[t] = sig_one + z
            r = ref[t]
            q = m / (r if (r >= tiny or r != r) else tiny)  # np.maximum(r, tiny)
            q = q if (q >= zero or q != q) else zero  # np.maximum(q, 0)
            q = q if (q <= one or q != q) else one  # np.minimum(q, 1)
            v = q * np.float32(o)
            qo = qov[t]
            w = qo if (qo <= v or qo != qo) else v  # np.minimum(qo, v)
            qov[t] = w if good else qo
        return n_slow

    helper = njit(cache=True, nogil=True, boundscheck=False, inline="always")
    _binary = helper(binary)
    _direct = njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")(direct)
    _min_nan = helper(min_nan)
    _max_nan = helper(max_nan)
    _store = helper(store)
    _direct_consts = helper(direct_consts)
    _xor_base = helper(xor_base)

    def start(white, black, w_scale, b_scale, has_wb, hsum, lsum, scale, shadow_thr, min_c,
              rel_c, direct, glob, lit_out, shadow, litb, tau, conf):
        # fused_chunk's prepare over one run (views): prepare's steps with separate outputs,
        # L_max / L_min from the pair kernel's running max / min channel sums (times scale:
        # the max of the products is the product of the max, float32 rounding being monotone,
        # so the same values as the kernel's own merge), lit = white - black from the held
        # 8-bit RGB frames (their luminance as _sl_kernels.luminance computes it), the lit
        # flags the axis kernel takes and the running confidence's start; returns the lit
        # pixels
        zero = np.float32(0.0)
        if not vec_source:  # (the cache key: _sl_vec's code is inlined)
            zero = np.float32(1.0)
        for t in range(hsum.shape[0]):
            mx = np.float32(hsum[t]) * scale
            mn = np.float32(lsum[t]) * scale
            d = mx - mn
            direct[t] = d
            glob[t] = np.float32(2.0) * _max_nan(mn, zero)
            tau[t] = _max_nan(min_c, rel_c * d)
        P = hsum.shape[0]
        if has_wb:  # the luminance kernel's steps: exact channel sums, then float32
            n_vec = P - P % 32
            for t in range(0, n_vec, 32):  # _sl_vec.lit_rgb8: the same, 32 pixels a block
                _lit_rgb8(white, black, t, w_scale, b_scale, lit_out)
            for t in range(n_vec, P):
                sw = np.uint32(white[3 * t]) + np.uint32(white[3 * t + 1]) + \
                    np.uint32(white[3 * t + 2])
                sb = np.uint32(black[3 * t]) + np.uint32(black[3 * t + 1]) + \
                    np.uint32(black[3 * t + 2])
                lit_out[t] = np.float32(sw) * w_scale - np.float32(sb) * b_scale
        else:
            for t in range(P):
                lit_out[t] = direct[t]
        n = 0
        for t in range(P):
            li = lit_out[t]
            sh = not (li >= shadow_thr)
            shadow[t] = sh
            litb[t] = not sh
            n += np.int64(not sh)
            conf[t] = np.float32(1.0)
        return n

    _start = njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")(start)

    @njit(cache=True, nogil=True, boundscheck=False)
    def prepare(white, black, has_wb, lmax, lmin, shadow_thr, min_c, rel_c, lit_out, shadow,
                tau):  # pragma: no cover - compiled
        # _finish_chunk's per-pixel start with binary frames: direct / global over lmax / lmin
        # (in place), lit, shadow, the reliability threshold
        P = lmax.shape[0]
        if True:
            for p in range(P):
                mx = lmax[p]
                mn = lmin[p]
                d = mx - mn
                lit = white[p] - black[p] if has_wb else d
                lmax[p] = d
                lmin[p] = np.float32(2.0) * _max_nan(mn, np.float32(0.0))
                lit_out[p] = lit
                shadow[p] = not (lit >= shadow_thr)
                tau[p] = _max_nan(min_c, rel_c * d)

    @njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
    def axis_pixels(signs, marg, mscale, kidx, base, tabs, words, use_tabs, n, step, n_stripes,
                    coarse_lim, tol, p0, tau, ref, lit, phi, pok, has_hint, kk, period,
                    coord_out, sig_out, ok_out, conf_out, final, counts, mmin,
                    has_min, fast_done, slow_in):  # pragma: no cover
        # fast_done: one family writing the final outputs whose fully resolved pass has run
        # already (the fused chunk kernel's block loop) with the slow flags in slow_in: only
        # the slow pixels are decoded here
        F = signs.shape[0]
        P = tau.shape[0]
        if not vec_source:  # (the cache key: _direct inlines _sl_vec's code)
            P = P + 0
        full = (np.int64(1) << n) - 1
        half_pi = 0.5 * math.pi
        two_pi64 = 2.0 * math.pi
        inf32 = np.float32(np.inf)
        tiny = np.float32(1e-12)
        sqrt12 = math.sqrt(12.0)
        direct = F == 1 and final
        # one family writing the final outputs needs no per-family rows: the whole run is one
        # tile (its fast pass in one call; a tile's fixed costs were 0.3 ns a pixel at 512)
        T = max(P, 1) if direct else _TILE
        Tf = 1 if direct else T
        mi = np.empty(T, marg.dtype)  # the smallest stored margin of a family
        slow = np.empty(T, np.uint8)  # 1: a plane is unreliable (the scalar path)
        cf = np.empty((F, Tf))
        sf = np.empty((F, Tf))
        wf = np.empty((F, Tf))
        qf = np.empty((F, Tf), np.float32)
        of = np.empty((F, Tf), np.bool_)
        agree = np.zeros(F, np.int64)
        c0, one_stripe_ok, sig_one32 = _direct_consts(step, coarse_lim)
        sig_one = 1.0 * step / sqrt12
        zero32 = np.float32(0.0)
        for t0 in range(0, P, T):
            nt = min(T, P - t0)
            a0 = p0 + t0
            miv = mi[:nt]
            slv = slow[:nt]
            tauv = tau[t0:t0 + nt]
            litv = lit[t0:t0 + nt]
            refv = ref[t0:t0 + nt]
            cov = coord_out[t0:t0 + nt]
            sov = sig_out[t0:t0 + nt]
            oov = ok_out[t0:t0 + nt]
            qov = conf_out[t0:t0 + nt]
            for f in range(F):
                # the smallest margin over the planes (the XOR base lowers the margins above it
                # to its own: the smallest is unchanged); a pass per plane over the tile
                if has_min and not direct:  # taken while the pairs were folded (mmin)
                    mrow = mmin[f, a0:a0 + nt]
                    for t in range(nt):
                        miv[t] = mrow[t]
                for i in range(0 if has_min else n):
                    mrow = marg[kidx[f, i], a0:a0 + nt]
                    if i == 0:
                        for t in range(nt):
                            miv[t] = mrow[t]
                    else:
                        for t in range(nt):
                            miv[t] = min(miv[t], mrow[t])
                # every plane is reliable <=> the smallest margin is ("float32(m) * mscale >=
                # tau" is monotone in m): those pixels decode fully resolved in one vectorised
                # pass (np.maximum / np.minimum are the NaN-propagating selects of the
                # reference and vectorise where numba's float min / max / conditional
                # expressions stay scalar); the others (few) take the scalar path after
                sg = signs[f][a0:a0 + nt]  # (C-contiguous: the vector block's type)
                ut = use_tabs[f]  # a table code: sg holds its stripes' Gray words
                b = base[f]
                high, sb = _xor_base(b, n)
                n_slow = np.int32(0)
                if direct and fast_done:  # the slow flags of the pass that ran
                    slv = slow_in[t0:t0 + nt]
                    n_slow = np.int32(1)
                elif direct:  # one family, final outputs: written here (the store, fused)
                    dargs = (tauv, litv, refv, cov, sov, oov, qov, slv, mscale, high, sb,
                             n_stripes, one_stripe_ok, step, c0, sig_one32)
                    if has_min:
                        n_slow = _direct(sg, mmin[f][a0:a0 + nt], *dargs)
                    else:
                        n_slow = _direct(sg, miv, *dargs)
                else:
                    cfv = cf[f, :nt]
                    sfv = sf[f, :nt]
                    wfv = wf[f, :nt]
                    ofv = of[f, :nt]
                    qfv = qf[f, :nt]
                    for t in range(nt):
                        x = _binary(sg[t], high, sb)
                        m = np.float32(miv[t]) * mscale
                        sl = np.uint8(not (m >= tauv[t]))
                        slv[t] = sl
                        n_slow += np.int32(sl)
                        cfv[t] = np.float64(np.int32(x)) * step + c0  # x < 2**31 (n <= 31)
                        sfv[t] = sig_one
                        wfv[t] = step
                        ofv[t] = litv[t] & (x < n_stripes) & one_stripe_ok
                        q = m / np.maximum(refv[t], tiny)
                        qfv[t] = np.minimum(np.maximum(q, zero32), np.float32(1.0))
                # ... then the pixels with unresolved planes: their reliable planes, partial
                # codes, statistics
                for t in range(nt if n_slow else 0):
                    if slv[t] == 0:
                        continue
                    tt = tauv[t]
                    r = np.int64(0)
                    for i in range(n):
                        m = np.float32(marg[kidx[f, i], a0 + t]) * mscale
                        if m >= tt:
                            r |= np.int64(1) << (n - 1 - i)
                    if b > 0:
                        r &= (full & ~high) | (high * ((r >> sb) & 1))
                    u = ~r & full
                    isl = lit[t0 + t]
                    binary = _binary(sg[t], high, sb)
                    bl = 0
                    t2 = u
                    while t2:
                        bl += 1
                        t2 >>= 1
                    first = n - bl
                    single = (u & (u - 1)) == 0
                    if ut:  # the other candidate: the projected word (words[stripe]) with its
                        # unresolved plane flipped, through the code -> stripe table
                        flip = np.int64(tabs[f, np.int64(words[f, binary])
                                             ^ (np.int64(1) << (n - 1 - first))])
                    else:  # Gray: the binary index with the bits below the prefix flipped
                        flip = binary ^ ((np.int64(1) << (n - first)) - 1)
                    edge = single and abs(flip - binary) == 1
                    picked = False
                    bsel = binary
                    if has_hint and single and not edge and pok[t0 + t]:
                        ca = binary * step + c0
                        cb = flip * step + c0
                        xa = phi[t0 + t] - kk * (ca + 0.5)
                        xb = phi[t0 + t] - kk * (cb + 0.5)
                        # the angles wrapped to [-pi, pi] by arithmetic alone (the reference
                        # does the same): sin / cos / atan2 differ by an ulp between libm and
                        # numpy's SIMD code (AVX-512), and a pick at the threshold flipped
                        da = abs(xa - two_pi64 * np.rint(xa / two_pi64))
                        db = abs(xb - two_pi64 * np.rint(xb / two_pi64))
                        dmin = min(da, db)
                        dmax = max(da, db)
                        picked = dmin < half_pi and (dmax >= half_pi or abs(ca - cb) < 0.5 * period)
                        if picked and db < da:
                            bsel = flip
                    weff = 1.0
                    if edge:
                        cst = 0.5 * (binary + flip)
                        exists = max(binary, flip) < n_stripes
                    elif picked:
                        cst = float(bsel)
                        exists = bsel < n_stripes
                    else:
                        weff = float(np.int64(1) << (n - first))
                        block = bsel >> (n - first)
                        cst = block * weff + 0.5 * (weff - 1)
                        # a table code has no prefix blocks: it names no stripe
                        exists = block * weff < n_stripes and not ut
                    ok = isl and exists and (weff * step <= coarse_lim + 1e-9 or edge or picked)
                    # confidence: the weakest margin among the planes the coordinate uses
                    limit = n if (edge or picked) else first
                    ms = inf32
                    for i in range(n):
                        bad = (u >> (n - 1 - i)) & 1
                        if bad and isl:
                            counts[f, i] += 1
                        if not bad and limit > i:
                            m = np.float32(marg[kidx[f, i], a0 + t]) * mscale
                            if b > 0 and i < b:  # as the XOR base lowered it
                                m = min(m, np.float32(marg[kidx[f, b], a0 + t]) * mscale)
                            ms = _min_nan(ms, m)
                    if not np.isfinite(ms):
                        ms = np.float32(0.0)
                    if isl and not ok:
                        counts[f, n + first] += 1
                    r = ref[t0 + t]
                    q = ms / (r if (r >= tiny or r != r) else tiny)
                    q = min(max(q, np.float32(0.0)), np.float32(1.0)) if q == q else q
                    sig = 0.5 * step if edge else weff * step / sqrt12
                    if direct:
                        z = zero32 / np.float32(ok)
                        oov[t] = ok
                        cov[t] = np.float32(cst * step + c0) + z
                        sov[t] = np.float32(sig) + z
                        # (the fast pass left a slow pixel's running min as it was)
                        qov[t] = np.minimum(qov[t], q * np.float32(ok))
                        continue
                    cf[f, t] = cst * step + c0
                    sf[f, t] = sig
                    wf[f, t] = weff * step
                    qf[f, t] = q
                    of[f, t] = ok
            if direct:
                continue
            if F == 1:
                for t in range(nt):
                    _store(t0 + t, final, of[0, t], cf[0, t], sf[0, t], qf[0, t], coord_out,
                           sig_out, ok_out, conf_out)
                continue
            for t in range(nt):  # consistency vote (Gupta et al. 2013, Sec. 4.3)
                for f in range(F):
                    agree[f] = 0
                for i in range(F):
                    for j in range(i + 1, F):
                        if of[i, t] and of[j, t] and abs(cf[i, t] - cf[j, t]) <= \
                                0.5 * (wf[i, t] + wf[j, t]) / 2 + tol:
                            agree[i] += 1
                            agree[j] += 1
                best = 0
                best_score = -np.inf
                n_ok = 0
                for f in range(F):
                    sg = sf[f, t] if of[f, t] else np.inf
                    score = agree[f] * 1e6 - min(sg, 1e5)
                    if score > best_score:  # np.argmax: the first maximum
                        best_score = score
                        best = f
                    n_ok += of[f, t]
                nbest = agree[best]
                okv = nbest >= 1 or n_ok == 1
                if lit[t0 + t] and n_ok >= 2 and not okv:
                    counts[0, 2 * n] += 1
                _store(t0 + t, final, okv, cf[best, t], sf[best, t],
                       np.float32(float(qf[best, t]) * (nbest + 1) / F), coord_out, sig_out,
                       ok_out, conf_out)

    @njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
    def phase_pixels(S, C, pmax, ref, shadow, two_over_n, min_mod, saturation, wrapped, B_out,
                     phi_out, pconf_out, pok_out):  # pragma: no cover - compiled
        two_pi = np.float32(2.0 * math.pi)
        zero = np.float32(0.0)
        tiny = np.float32(1e-12)
        for p in range(S.shape[0]):
            # np.mod(float32(arctan2(float64(S), float64(C))), float32(2 pi)) in float32
            # (numpy's divmod rule). The arctangent in float64, rounded once: float32 atan2
            # differs by an ulp between libm and numpy's SIMD code (AVX-512: 41 % of the pixels
            # of a test decode), float64 rounded to float32 practically never
            m = np.float32(math.atan2(np.float64(S[p]), np.float64(C[p])))  # in [-pi, pi]
            if m != 0:
                if m < 0:
                    m += two_pi
            else:
                m = zero
            if m >= two_pi:
                m = zero
            B = two_over_n * math.hypot(S[p], C[p])
            B_out[p] = B
            phi_out[p] = m
            wrapped[p] = m if B > 0 else np.float32(np.nan)
            r = ref[p]
            q = (np.float32(2.0) * B) / (r if (r >= tiny or r != r) else tiny)
            q = min(max(q, zero), np.float32(1.0)) if q == q else q
            pconf_out[p] = q
            # a clipped fringe biases the phase: saturated pixels fall back to the code
            pok_out[p] = (not shadow[p]) and q >= min_mod and pmax[p] < saturation

    @njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
    def phase_merge(coord, sig, ok, conf, phi, B, pconf, pok, k, sig_c, keep_sig,
                    coord_out, sig_out, ok_out, conf_all):  # pragma: no cover - compiled
        two_pi = 2.0 * math.pi
        tiny = np.float32(1e-12)
        for p in range(coord.shape[0]):
            use = ok[p] and pok[p]
            # coarse-only pixels keep a coordinate only if exact to one stripe
            keep = ok[p] and not pok[p] and sig[p] <= keep_sig
            if use:
                mm = np.rint((k * (np.float64(coord[p]) + 0.5) - phi[p]) / two_pi)
                c = np.float32((phi[p] + two_pi * mm) / k - 0.5)
                b = B[p]
                sg = (sig_c / (b if (b >= tiny or b != b) else tiny)) / np.float32(k)
                q = _min_nan(conf[p], pconf[p])
            elif keep:
                c, sg, q = coord[p], sig[p], conf[p]
            else:
                c, sg, q = np.float32(np.nan), np.float32(np.nan), np.float32(0.0)
            v = use or keep
            _store(p, True, v, c, sg, q, coord_out, sig_out, ok_out, conf_all)

    return axis_pixels, prepare, phase_pixels, phase_merge


# The kernels the fused chunk kernel calls, set by _fused(): module globals (see _min_nan).
_pairs_min = _axis_px = None


@functools.cache
def _fused():
    """The fused chunk kernel of a decode of held 8-bit RGB frames (see :func:`fused_chunk`).

    It calls the pair kernel of ``_sl_kernels`` and :func:`decode_axis`'s kernel, compiled into
    it: the sources of ``_sl_kernels.py``, ``_sl_vec.py`` and this file are a closure cell read
    in the body, so numba's disk cache (which sees this file only) compiles it again after an
    edit of any of them."""
    global _pairs_min, _axis_px
    import hashlib
    from pathlib import Path

    from numba import njit

    from facegeo.geometry import _sl_kernels

    _axis_px = _kernel()[0]
    _pairs_min = _sl_kernels._pairs_rgb8(False, True)
    here = Path(__file__).parent
    sources = hashlib.sha256(b"".join(
        (here / f).read_bytes() for f in ("_sl_finish.py", "_sl_kernels.py", "_sl_vec.py"))
    ).hexdigest()

    @njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")
    def fused(addrs, size, p_lo, p_hi, sub, scale, k, steps, mscale, gx, gy, ax, ay, bx, by,
              margin, hsum, lsum, tau, litb, white, black, w_scale, b_scale, has_wb, shadow_thr,
              min_c, rel_c, direct, glob, lit_out, shadow, conf, valid, ox, oy,
              nt):  # pragma: no cover
        n_lit = 0
        if not sources:  # (the cache key, see above)
            n_lit = 1
        no_f = tau[:0]  # (the pair kernel's L_max / L_min: unused with caller-held sums)
        has_x = ax[0].shape[0] > 0
        has_y = ay[0].shape[0] > 0
        # the block loop below: every coded axis of one family
        fast = (has_x or has_y) and (not has_x or bx[0].shape[0] == 1) and (
            not has_y or by[0].shape[0] == 1)
        slx = np.empty(sub if fast else 1, np.uint8)  # the block loop's slow flags
        sly = np.empty(sub if fast else 1, np.uint8)
        c0x, okx, sgx = _direct_consts(ax[7], ax[9])
        c0y, oky, sgy = _direct_consts(ay[7], ay[9])
        hx, sbx = _xor_base(ax[1][0] if has_x else -1, ax[5])
        hy, sby = _xor_base(ay[1][0] if has_y else -1, ay[5])
        for a in range(p_lo, p_hi, sub):
            b = min(p_hi, a + sub)
            S = b - a
            hsum[:S] = -1  # the running max / min channel sums of both axes' pairs
            lsum[:S] = 32767
            # the axes' pairs over pixels a … b - 1, into columns 0 … S - 1 of the buffers
            if has_x:
                bx[0][:, :S] = 0
                bx[1][:, :S] = 255
                _pairs_min(addrs, size, gx[0], gx[1], scale, gx[2], gx[3], gx[4], bx[0],
                           margin, steps, no_f, no_f, S, k, a, b, a, bx[1], True, hsum, lsum)
                for f in range(bx[0].shape[0]):  # a table code: its stripes' Gray words
                    if ax[3][f]:
                        w = bx[0][f, :S]
                        for t in range(S):
                            w[t] = ax[6][f, w[t]]
            if has_y:
                by[0][:, :S] = 0
                by[1][:, :S] = 255
                _pairs_min(addrs, size, gy[0], gy[1], scale, gy[2], gy[3], gy[4], by[0],
                           margin, steps, no_f, no_f, S, k, a, b, a, by[1], True, hsum, lsum)
                for f in range(by[0].shape[0]):
                    if ay[3][f]:
                        w = by[0][f, :S]
                        for t in range(S):
                            w[t] = ay[6][f, w[t]]
            # every coded axis of one code family (its fully resolved pass writes the final
            # outputs): the start and both axes' passes 32 pixels a block (_sl_vec.start_block,
            # direct_block), so the start's planes are read back from L1, not from L2 after a
            # pass over the whole run; then each axis's slow pixels (a plane below tau), and
            # the run's last S mod 32 pixels (or, with an ensemble of codes, the whole run)
            # phase by phase. The same values: each pixel takes the same steps, and the running
            # confidence's min over the axes commutes
            nv = S - S % 32 if fast else 0
            dv = direct[a:b]
            cv = conf[a:b]
            wv = white[3 * a:3 * b] if has_wb else white
            kv = black[3 * a:3 * b] if has_wb else black
            n_sx = 0
            n_sy = 0
            for t in range(0, nv, 32):
                n_lit += _start_block(hsum, lsum, scale, wv, kv, w_scale, b_scale, has_wb, min_c,
                                      rel_c, shadow_thr, dv, glob[a:b], lit_out[a:b],
                                      shadow[a:b], litb, tau, cv, t, nt)
                if has_x:
                    for u in (t, t + 16):
                        n_sx += _direct_block(bx[0][0], bx[1][0], tau, litb, dv, ox[0][a:b],
                                              ox[1][a:b], ox[2][a:b], cv, slx, u, mscale, hx,
                                              sbx, ax[8], okx, ax[7], c0x, sgx, nt)
                if has_y:
                    for u in (t, t + 16):
                        n_sy += _direct_block(by[0][0], by[1][0], tau, litb, dv, oy[0][a:b],
                                              oy[1][a:b], oy[2][a:b], cv, sly, u, mscale, hy,
                                              sby, ay[8], oky, ay[7], c0y, sgy, nt)
            if n_sx:
                _axis_px(bx[0], margin, mscale, ax[0], ax[1], ax[2], ax[4], ax[3], ax[5],
                         ax[7], ax[8], ax[9], ax[10], 0, tau[:nv], dv[:nv], litb[:nv],
                         ax[11], ax[12], False, 0.0, 0.0, ox[0][a:a + nv], ox[1][a:a + nv],
                         ox[2][a:a + nv], cv[:nv], True, ox[3], bx[1], True, True, slx)
            if n_sy:
                _axis_px(by[0], margin, mscale, ay[0], ay[1], ay[2], ay[4], ay[3], ay[5],
                         ay[7], ay[8], ay[9], ay[10], 0, tau[:nv], dv[:nv], litb[:nv],
                         ay[11], ay[12], False, 0.0, 0.0, oy[0][a:a + nv], oy[1][a:a + nv],
                         oy[2][a:a + nv], cv[:nv], True, oy[3], by[1], True, True, sly)
            if nv < S:
                # prepare's per-pixel start (the same steps), into the full-size outputs (loops
                # over views of the run: indexing the full-size arrays at a + t kept them
                # scalar)
                c = a + nv
                n_lit += _start(white[3 * c:3 * b] if has_wb else white,
                                black[3 * c:3 * b] if has_wb else black, w_scale, b_scale,
                                has_wb, hsum[nv:S], lsum[nv:S], scale, shadow_thr, min_c, rel_c,
                                direct[c:b], glob[c:b], lit_out[c:b], shadow[c:b], litb[nv:S],
                                tau[nv:S], conf[c:b])
                if has_x:
                    _axis_px(bx[0], margin, mscale, ax[0], ax[1], ax[2], ax[4], ax[3], ax[5],
                             ax[7], ax[8], ax[9], ax[10], nv, tau[nv:S], direct[c:b],
                             litb[nv:S], ax[11], ax[12], False, 0.0, 0.0, ox[0][c:b],
                             ox[1][c:b], ox[2][c:b], conf[c:b], True, ox[3], bx[1], True, False,
                             slx)
                if has_y:
                    _axis_px(by[0], margin, mscale, ay[0], ay[1], ay[2], ay[4], ay[3], ay[5],
                             ay[7], ay[8], ay[9], ay[10], nv, tau[nv:S], direct[c:b],
                             litb[nv:S], ay[11], ay[12], False, 0.0, 0.0, oy[0][c:b],
                             oy[1][c:b], oy[2][c:b], conf[c:b], True, oy[3], by[1], True, False,
                             sly)
            vv = valid[a:b]
            if has_x and has_y:
                vx = ox[2][a:b]
                vy = oy[2][a:b]
                for t in range(S):
                    vv[t] = vx[t] & vy[t]
            else:
                vv[:] = ox[2][a:b] if has_x else oy[2][a:b]
        if nt:
            _store_fence()
        return n_lit

    return fused


def fused_chunk(frames, start, stop, sub, scale, k, steps, mscale, pairs, axes, bufs, white,
                black, wb_scales, thresholds, outs) -> int:
    """Fold and finish pixels ``start … stop - 1`` of held 8-bit RGB pattern / inverse pairs
    in one compiled call, ``sub`` pixels at a time: per sub-run the pair kernel
    (``_sl_kernels._pairs_rgb8``, with each family's smallest margin) of each axis into
    sub-run-sized words, margins and the running max / min channel sums of both axes' pairs
    (``L_max`` / ``L_min`` are those times ``scale``), a table code's words translated
    (:func:`stripe_gray_words`), :func:`prepare`'s start written to the outputs (``lit`` from
    the held white / black frames' channel sums), each axis decoded (:func:`decode_axis` with
    ``out``), and ``valid``. When every coded axis has one code family, the start and both
    axes' fully resolved passes run 32 pixels a block (``_sl_vec.start_block``,
    ``direct_block``), then each axis's slow pixels (``axis_pixels`` with ``fast_done``) and
    the sub-run's last ``S mod 32`` pixels step by step. The same kernels and steps as the
    chunk-by-chunk Python path (``StreamDecoder._fold_chunk`` / ``_finish_chunk``), so the same
    values (tested); the buffers stay in cache and no Python runs between the steps (that
    path's per-call costs were ≈ 1 ms of a 12 ms decode, and its chunks too large for the
    buffers to stay in L2).

    ``frames``: the held pair frames (``_sl_kernels.FrameSet``). ``scale``, ``k``, ``steps``:
    the pair kernel's (``k`` the integer margin multiplier or the float32 ``k``,
    ``_sl_kernels.PairGroup.margin_k``); ``mscale``: the margins' unit. ``pairs``: per axis
    ``(pos, neg, rows, bitvals, planes)`` (empty arrays for an axis without bits); ``axes``: per
    axis ``(kidx, base, tabs, use, words, n, gray tables (F, 2**n), step, n_stripes,
    coarse_lim, tol, phi, pok)`` (``StreamDecoder._fused_plan``); ``bufs``: per axis ``(words,
    mmin)`` (F, ≥ sub) plus the shared ``(margin, hsum, lsum, tau, lit)`` (``hsum`` / ``lsum``
    int16); ``white``, ``black``: the held frames, flat (empty without them), ``wb_scales``
    their luminance scales; ``thresholds``: ``(has_wb, shadow, min_contrast, rel_contrast)``; ``outs``:
    ``(direct, global, lit, shadow, confidence, valid)`` flat and per axis ``(coord, sigma, ok,
    counts)``. Returns the number of lit pixels."""
    (gx, gy), (ax, ay), ((bx, by), shared), (ox, oy) = pairs, axes, bufs, outs[6:]
    margin, hsum, lsum, tau, litb = shared
    has_wb, shadow_thr, min_c, rel_c = thresholds
    direct, glob, lit_out, shadow, conf, valid = outs[:6]
    # the block loop's outputs the kernel does not read back (global, shadow, each axis's
    # coordinate and sigma, and lit with white / black frames: without them lit may be direct's
    # own plane) are stored non-temporally when every block of them is aligned to its vector:
    # the planes at 64 bytes (StreamDecoder allocates them so) and every sub-run starting at a
    # multiple of 32 pixels. Measured (bench decode, 1 thread): the start and the axes 5.1-5.4
    # -> 4.5-4.6 M cycles, the decode 7.75-7.93 -> 7.31-7.56 ms
    planes = [glob, lit_out, shadow] + [o[i] for o in (ox, oy) if o[0].size for i in (0, 1)]
    start, stop, sub = int(start), int(stop), int(sub)
    nt = start % 32 == 0 and (sub % 32 == 0 or stop - start <= sub) and all(
        p.ctypes.data % 64 == 0 for p in planes)
    return _fused()(frames.addrs, frames.size, start, stop, sub, np.float32(scale), k,
                    np.float32(steps), np.float32(mscale), gx, gy, ax, ay, bx, by, margin,
                    hsum, lsum, tau, litb, white, black, np.float32(wb_scales[0]),
                    np.float32(wb_scales[1]), bool(has_wb), np.float32(shadow_thr),
                    np.float32(min_c), np.float32(rel_c), direct, glob, lit_out, shadow, conf,
                    valid, ox, oy, bool(nt))


def prepare(white, black, lmax, lmin, shadow_threshold, min_contrast, rel_contrast, lit_out,
            shadow, tau) -> None:
    """Per-pixel start of the finish with binary frames, in place on (P,) float32 views:
    ``lmax`` becomes ``direct = lmax - lmin``, ``lmin`` becomes ``global = 2 max(lmin, 0)``
    (Nayar et al. 2006), ``lit_out = white - black`` (``direct`` when ``white`` is None),
    ``shadow = not (lit >= shadow_threshold)``, ``tau = max(min_contrast, rel_contrast ·
    direct)``. ``lit_out`` may be ``white`` or ``lmax`` itself (each pixel is read first)."""
    has_wb = white is not None
    if not has_wb:
        white = black = lmax
    _kernel()[1](white, black, has_wb, lmax, lmin, np.float32(shadow_threshold),
                 np.float32(min_contrast), np.float32(rel_contrast), lit_out, shadow, tau)


def decode_axis(signs, marg, mscale, kidx, base, n, step, n_stripes, coarse_lim, tol, tau, ref,
                lit, hint=None, out=None, p0=0, tables=None, mmin=None):
    """Decode one axis for a run of pixels (see the module docstring).

    Parameters
    ----------
    signs : (F, N) unsigned int, C-contiguous
        Per code family, the packed decisions (plane ``i`` at bit ``n - 1 - i``); the run's
        pixels are columns ``p0 … p0 + P - 1``.
    marg : (K, N) uint8 or float32, C-contiguous
        Stored margins (same columns); plane ``i`` of family ``f`` is row ``kidx[f, i]``, in
        units of ``mscale`` (uint8 steps of 1/510 of full scale, or float32 with ``mscale`` 1).
    mscale : float
    kidx : (F, n) int64
    base : (F,) int64
        The family's XOR base plane, or -1.
    n : int
        Bits on this axis.
    step, n_stripes, coarse_lim, tol : float, int, float, float
        Stripe width (projector px), stripes on the axis, the widest block that still gives a
        coordinate (projector px), ``vote_tolerance_px``.
    tau, ref : (P,) float32
        Reliability threshold and the reference light of the confidence.
    lit : (P,) bool
    hint : tuple, optional
        ``(phi, usable, k, period)``: wrapped phase (P,) float32, (P,) bool, rad / px, px.
    tables : sequence of (str or None), optional
        Per family the code family name when it decodes through a code → stripe table (the
        long-run ``"minsw"``), else None. Such a family's ``signs`` must already hold the
        Gray words of its stripes (:func:`stripe_gray_words`), so the Gray loops decode it
        unchanged; a pixel with one unresolved plane gets the two candidates' boundary or
        the phase's pick, as a Gray one (the candidates: the table at the projected word and
        at the word with that plane flipped); otherwise it is invalid (a resolved subset of
        its planes names no block of stripes).
    mmin : (F, N) array of ``marg``'s dtype, optional
        Per family the smallest of its planes' margins (same columns), when the pair kernel
        kept it (``_sl_kernels.PairGroup.run(mmin=)``): the kernel then skips its plane-by-plane
        min (the same values).

    out : tuple, optional
        ``(coord, sig, ok, conf_all)`` (P,) arrays to write the axis's final outputs into
        (``coord`` / ``sig`` NaN where not ok, ``conf_all = min(conf_all, conf if ok else
        0)``), as ``_finish_chunk`` does for an axis without phase.

    Returns
    -------
    coord, sig : (P,) float32, projector px
    ok : (P,) bool
    conf : (P,) float32 (``conf_all`` with ``out``)
    unresolved, lost : (F, n) int64
    votes_disagree : int
    """
    F = signs.shape[0]
    P = tau.shape[0]
    if out is None:
        coord, sig = np.empty(P, np.float32), np.empty(P, np.float32)
        ok, conf = np.empty(P, bool), np.empty(P, np.float32)
    else:
        coord, sig, ok, conf = out
    counts = np.zeros((F, 2 * n + 1), np.int64)
    if hint is None:
        phi, pok, kk, period, has = np.zeros(1, np.float32), np.zeros(1, bool), 0.0, 0.0, False
    else:
        phi, pok, kk, period = hint
        has = True
    tabs, words, use = code_tables(tables if tables is not None else [None] * F, n)
    _kernel()[0](signs, marg, np.float32(mscale), np.asarray(kidx, np.int64),
              np.asarray(base, np.int64), tabs, words, use, int(n), float(step), int(n_stripes),
              float(coarse_lim), float(tol), int(p0), tau, ref, lit, phi, pok, has, float(kk),
              float(period), coord, sig, ok, conf, out is not None, counts,
              mmin if mmin is not None else marg[:1], mmin is not None, False,
              np.zeros(1, np.uint8))
    c = counts
    return coord, sig, ok, conf, c[:, :n], c[:, n:2 * n], int(c[0, 2 * n])


def phase(S, C, pmax, ref, shadow, N, min_modulation, saturation, wrapped, modulation):
    """Wrapped phase and fringe amplitude of a run of pixels (Srinivasan et al. 1984):
    ``phi = atan2(S, C) mod 2 pi``, ``B = (2 / N) hypot(S, C)``, written to ``wrapped`` (NaN
    where ``B = 0``) and ``modulation``; returns ``phi`` (P,) float32, the fringe contrast
    ``pconf = clip(2 B / ref, 0, 1)`` and ``usable = not shadow, pconf >= min_modulation, max
    phase frame < saturation`` — what the numpy lines of ``_finish_chunk`` compute."""
    P = S.shape[0]
    phi, pconf, usable = np.empty(P, np.float32), np.empty(P, np.float32), np.empty(P, bool)
    _kernel()[2](S, C, pmax, ref, shadow, np.float32(2.0 / N), np.float32(min_modulation),
                 np.float32(saturation), wrapped, modulation, phi, pconf, usable)
    return phi, pconf, usable


def phase_merge(coord, sig, ok, conf, phi, B, pconf, usable, k, noise_sigma, N, step, out):
    """Unwrap the phase with the code coordinate and write the axis's outputs: where the code
    and the phase are both usable ``x = (phi + 2 pi m) / k - 0.5`` with ``m = round((k (code
    + 0.5) - phi) / 2 pi)``, σ ``= noise_sigma sqrt(2 / N) / B / k`` and confidence
    ``min(conf, pconf)``; where only the code is, it stands if it names one stripe; ``out =
    (x, sigma, valid, conf_all)`` as in :func:`decode_axis`."""
    _kernel()[3](coord, sig, ok, conf, phi, B, pconf, usable, float(k),
                 np.float32(noise_sigma * math.sqrt(2.0 / N)),
                 np.float32(step / math.sqrt(12.0) + 1e-6), *out)


def code_tables(tables, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`decode_axis`'s per-family tables for ``tables`` (per family a table code's name
    or None): the code → stripe tables and the projected words (F, 2**n) uint16 (one zero
    column when no family has a table) and which families use them (F,) bool."""
    F = len(tables)
    use = np.array([t is not None for t in tables], bool)
    tabs = np.zeros((F, (1 << n) if use.any() else 1), np.uint16)
    words = np.zeros_like(tabs)
    for f in np.flatnonzero(use):
        tabs[f] = stripe_table(tables[f], n)
        words[f] = long_run_words(n)
    return tabs, words, use


def stripe_gray_tables(tables, n: int, dtype) -> np.ndarray:
    """Per family (``tables`` as in :func:`code_tables`) the table :func:`stripe_gray_words`
    applies, (F, 2**n) of the words' ``dtype`` (one zero column when no family has a table)."""
    out = np.zeros((len(tables), (1 << n) if any(t is not None for t in tables) else 1), dtype)
    for f, c in enumerate(tables):
        if c is not None:
            out[f] = _stripe_gray(c, n)
    return out


@functools.cache
def _stripe_gray(code: str, n: int) -> np.ndarray:
    t = stripe_table(code, n)
    return t ^ (t >> 1)


def stripe_gray_words(code: str, n: int, signs: np.ndarray) -> None:
    """In place: a table family's decision words ``signs`` (plane ``i`` at bit ``n - 1 - i``)
    become the reflected Gray words of the stripes they name, ``g = k ^ (k >> 1)`` with ``k
    = table[word]``, so :func:`decode_axis` decodes them with its Gray arithmetic, unchanged
    (the Gray path does not pay for the table). Stored once per decode, before the chunks."""
    signs[...] = _stripe_gray(code, n)[signs]
