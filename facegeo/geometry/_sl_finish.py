"""Compiled end of the streaming structured-light decode: one pass per pixel over its bit words.

Private kernel behind :meth:`facegeo.geometry._sl_stream.StreamDecoder.finish`. For one axis and
a block of pixels it does, per pixel, what the numpy reference (``_sl_stream._bit_words``,
``_decode_axis``, ``_partial_codes``; run with ``_sl_stream.KERNELS = False``) does with
several full-size planes per family: read the pixel's decision word and its ``n`` margins per
code family, apply the XOR base plane (Gupta et al. 2013, Sec. 4.2), Gray → binary, find the
first unresolved plane, the boundary / phase-picked / coarse-block coordinate of a partly
resolved code, the weakest used margin (confidence), the per-bit statistics, and the
consistency vote across families (Sec. 4.3). The method is written down in
``docs/structured-light.md``; the kernel reproduces the reference's arithmetic (the same
float32 / float64 steps in the same order), so codes, validity and statistics are identical and
``x`` / ``y`` / ``sigma`` / ``confidence`` equal to rounding (tested in tests/test_decode.py).

Serial, like the per-frame kernels (``_sl_kernels``: why). The pixels run in blocks of
``_BLOCK``, each counting its own statistics (summed afterwards), so a ``prange`` over blocks
is a one-word change.
"""

from __future__ import annotations

import functools
import math

import numpy as np

__all__ = ["decode_axis", "prepare"]

_BLOCK = 1 << 14  # pixels per block (own statistics row)


@functools.cache
def _kernel():
    from numba import njit

    @njit(cache=True, nogil=True, boundscheck=False, inline="always")
    def _min_nan(a, b):  # np.minimum: NaN propagates
        if a <= b:
            return a
        return b if (b < a or b != b) else a

    @njit(cache=True, nogil=True, boundscheck=False, inline="always")
    def _max_nan(a, b):  # np.maximum: NaN propagates, ties keep a
        if a >= b:
            return a
        return b if (b > a or b != b) else a

    @njit(cache=True, nogil=True, boundscheck=False, inline="always")
    def _store(p, final, ok, coord, sig, conf, coord_out, sig_out, ok_out, conf_out):
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

    @njit(cache=True, nogil=True, boundscheck=False)
    def prepare(white, black, has_wb, lmax, lmin, shadow_thr, min_c, rel_c, lit_out, shadow,
                tau):  # pragma: no cover - compiled
        # _finish_chunk's per-pixel start with binary frames: direct / global over lmax / lmin
        # (in place), lit, shadow, the reliability threshold
        P = lmax.shape[0]
        for blk in range((P + _BLOCK - 1) // _BLOCK):
            for p in range(blk * _BLOCK, min(P, (blk + 1) * _BLOCK)):
                mx = lmax[p]
                mn = lmin[p]
                d = mx - mn
                lit = white[p] - black[p] if has_wb else d
                lmax[p] = d
                lmin[p] = np.float32(2.0) * _max_nan(mn, np.float32(0.0))
                lit_out[p] = lit
                shadow[p] = not (lit >= shadow_thr)
                tau[p] = _max_nan(min_c, rel_c * d)

    @njit(cache=True, nogil=True, boundscheck=False)
    def axis_pixels(signs, marg, mscale, kidx, base, n, step, n_stripes, coarse_lim, tol,
                    tau, ref, lit, phi, pok, has_hint, kk, period,
                    coord_out, sig_out, ok_out, conf_out, final, counts):  # pragma: no cover
        F = signs.shape[0]
        P = tau.shape[0]
        full = (np.int64(1) << n) - 1
        nblk = counts.shape[0]
        half_pi = 0.5 * math.pi
        inf32 = np.float32(np.inf)
        tiny = np.float32(1e-12)
        sqrt12 = math.sqrt(12.0)
        for blk in range(nblk):
            lo = blk * _BLOCK
            hi = min(P, lo + _BLOCK)
            cnt = counts[blk]  # (F, 2 n + 1): unresolved[i], lost[i], votes_disagree
            mg = np.empty(n, np.float32)
            cf = np.empty(F)
            sf = np.empty(F)
            wf = np.empty(F)
            qf = np.empty(F, np.float32)
            of = np.zeros(F, np.bool_)
            agree = np.zeros(F, np.int64)
            for p in range(lo, hi):
                t = tau[p]
                isl = lit[p]
                r = ref[p]
                rden = r if (r >= tiny or r != r) else tiny  # np.maximum(ref, 1e-12)
                for f in range(F):
                    w = np.int64(signs[f, p])
                    rel = np.int64(0)
                    for i in range(n):
                        m = np.float32(marg[kidx[f, i], p]) * mscale
                        mg[i] = m
                        if m >= t:
                            rel |= np.int64(1) << (n - 1 - i)
                    b = base[f]
                    if b > 0:  # XOR code: planes above the base were projected XORed with it
                        high = ((np.int64(1) << b) - 1) << (n - b)
                        if (w >> (n - 1 - b)) & 1:
                            w ^= high
                        if not ((rel >> (n - 1 - b)) & 1):
                            rel &= ~high & full
                        mb = mg[b]
                        for i in range(b):
                            if not (mg[i] <= mb):  # np.minimum (NaN propagates)
                                mg[i] = mb if (mb < mg[i] or mb != mb) else mg[i]
                    binary = w  # Gray -> binary: prefix XOR
                    sh = 1
                    while sh < n:
                        binary ^= binary >> sh
                        sh *= 2
                    u = ~rel & full  # unresolved planes
                    first = n
                    cst = float(binary)
                    weff = 1.0
                    exists = binary < n_stripes
                    edge = False
                    picked = False
                    if u != 0:
                        bl = 0
                        t2 = u
                        while t2:
                            bl += 1
                            t2 >>= 1
                        first = n - bl
                        single = (u & (u - 1)) == 0
                        flip = binary ^ ((np.int64(1) << (n - first)) - 1)
                        edge = single and abs(flip - binary) == 1
                        bsel = binary
                        if has_hint and single and not edge and pok[p]:
                            ca = binary * step + 0.5 * (step - 1.0)
                            cb = flip * step + 0.5 * (step - 1.0)
                            xa = phi[p] - kk * (ca + 0.5)
                            xb = phi[p] - kk * (cb + 0.5)
                            da = abs(math.atan2(math.sin(xa), math.cos(xa)))
                            db = abs(math.atan2(math.sin(xb), math.cos(xb)))
                            dmin = min(da, db)
                            dmax = max(da, db)
                            good = dmin < half_pi and (dmax >= half_pi
                                                       or abs(ca - cb) < 0.5 * period)
                            picked = good
                            if good and db < da:
                                bsel = flip
                        if edge:
                            cst = 0.5 * (binary + flip)
                            exists = max(binary, flip) < n_stripes
                        elif picked:
                            cst = float(bsel)
                            exists = bsel < n_stripes
                        else:
                            wb = np.int64(1) << (n - first)
                            wbf = float(wb)
                            block = bsel >> (n - first)
                            cst = block * wbf + 0.5 * (wbf - 1)
                            weff = wbf
                            exists = block * wbf < n_stripes
                    ok = isl and exists and (weff * step <= coarse_lim + 1e-9 or edge or picked)
                    # confidence: weakest margin among the planes used
                    if u == 0:
                        mm = mg[0]
                        for i in range(1, n):
                            v = mg[i]
                            if not (mm <= v):
                                mm = v if (v < mm or v != v) else mm
                    else:
                        limit = n if (edge or picked) else first
                        mm = inf32
                        for i in range(n):
                            bad = (u >> (n - 1 - i)) & 1
                            if bad and isl:
                                cnt[f, i] += 1
                            if not bad and limit > i:
                                v = mg[i]
                                if not (mm <= v):
                                    mm = v if (v < mm or v != v) else mm
                        if not np.isfinite(mm):
                            mm = np.float32(0.0)
                    if isl and not ok and first < n:
                        cnt[f, n + first] += 1
                    q = mm / rden
                    if q < 0:
                        q = np.float32(0.0)
                    elif q > 1:
                        q = np.float32(1.0)
                    cf[f] = cst * step + 0.5 * (step - 1.0)
                    sf[f] = 0.5 * step if edge else weff * step / sqrt12
                    wf[f] = weff * step
                    qf[f] = q
                    of[f] = ok
                if F == 1:
                    _store(p, final, of[0], cf[0], sf[0], qf[0], coord_out, sig_out, ok_out,
                           conf_out)
                    continue
                # consistency vote (Gupta et al. 2013, Sec. 4.3)
                for f in range(F):
                    agree[f] = 0
                for i in range(F):
                    for j in range(i + 1, F):
                        if of[i] and of[j] and abs(cf[i] - cf[j]) <= \
                                0.5 * (wf[i] + wf[j]) / 2 + tol:
                            agree[i] += 1
                            agree[j] += 1
                best = 0
                best_score = -np.inf
                n_ok = 0
                for f in range(F):
                    sg = sf[f] if of[f] else np.inf
                    score = agree[f] * 1e6 - min(sg, 1e5)
                    if score > best_score:  # np.argmax: the first maximum
                        best_score = score
                        best = f
                    n_ok += of[f]
                nbest = agree[best]
                okv = nbest >= 1 or n_ok == 1
                if isl and n_ok >= 2 and not okv:
                    cnt[0, 2 * n] += 1
                _store(p, final, okv, cf[best], sf[best],
                       np.float32(float(qf[best]) * (nbest + 1) / F), coord_out, sig_out, ok_out,
                       conf_out)

    return axis_pixels, prepare


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
                lit, hint=None, out=None):
    """Decode one axis for a run of pixels (see the module docstring).

    Parameters
    ----------
    signs : (F, P) unsigned int
        Per code family, the packed decisions (plane ``i`` at bit ``n - 1 - i``).
    marg : (K, P) uint8 or float32
        Stored margins; plane ``i`` of family ``f`` is row ``kidx[f, i]``, in units of
        ``mscale`` (uint8 steps of 1/510 of full scale, or float32 with ``mscale`` 1).
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
    counts = np.zeros((max(1, -(-P // _BLOCK)), F, 2 * n + 1), np.int64)
    if hint is None:
        phi, pok, kk, period, has = np.zeros(1, np.float32), np.zeros(1, bool), 0.0, 0.0, False
    else:
        phi, pok, kk, period = hint
        has = True
    _kernel()[0](signs, marg, np.float32(mscale), np.asarray(kidx, np.int64),
              np.asarray(base, np.int64), int(n), float(step), int(n_stripes),
              float(coarse_lim), float(tol), tau, ref, lit, phi, pok, has, float(kk),
              float(period), coord, sig, ok, conf, out is not None, counts)
    c = counts.sum(axis=0)
    return coord, sig, ok, conf, c[:, :n], c[:, n:2 * n], int(c[0, 2 * n])
