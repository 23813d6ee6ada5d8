"""Compiled (numba) per-sample kernels of the skin-model fit (Debevec et al. 2000, §4.2).

Private module beside :mod:`facegeo.appearance._skin_kernels` (the searches and the polish):
the steps between the searches that the numpy reference (``_skin_fit`` with
``KERNELS = False``) does with whole-chunk ``(n, L, 3)`` temporaries, fused into one pass per
function — the §4.2 separations with the Eq. 6–7 ramp chromaticity, the ramp search's
per-sample inputs, the specular energy ρ_s (Fig. 14 d) and d_0's median ratios. Each is tested
equal to its numpy reference in ``tests/test_skin_model.py``. Compiled on first use, cached on
disk; serial loops over the functions, as in ``_skin_kernels`` (see its compile-time notes).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from facegeo.appearance._skin_kernels import _FM, _I0

# ------------------------------------------------------------------------------- separation


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _chromaticity(d0x, d0y, d0z, f, s):
    """Eq. 6's ``c = normalize(d_0 + f (d_0 − s))`` (s where that vanishes), ``c·s`` and
    ``|c × s|² = 1 − (c·s)²``. Straight-line (selects), so that per-sample loops vectorise."""
    cx = d0x + f * (d0x - s)
    cy = d0y + f * (d0y - s)
    cz = d0z + f * (d0z - s)
    cn = math.sqrt(cx * cx + cy * cy + cz * cz)
    ok = cn > 1e-30
    cx = cx / cn if ok else s
    cy = cy / cn if ok else s
    cz = cz / cn if ok else s
    ds = (cx + cy + cz) * s
    return cx, cy, cz, ds, 1.0 - ds * ds


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _separate_sample(r0, r1, r2, cx, cy, cz, ds, det, sing_sin2, s):
    """One sample's §4.2 separation with chromaticity c: ``(μ_s, D)`` (μ_s = 0 where
    ``|c × s|² < sing_sin2``). Straight-line code (the division runs on singular samples
    too, its result discarded)."""
    Rd = r0 * cx + r1 * cy + r2 * cz
    Rs = (r0 + r1 + r2) * s
    ms = (Rs - Rd * ds) / det
    ms = 0.0 if det < sing_sin2 else ms
    sp = max(ms, 0.0) * s
    return ms, r0 - sp, r1 - sp, r2 - sp


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _separate_uniform_row(R, i, cx, cy, cz, ds, det, sing_sin2, y):
    """The initial separation of function i (chromaticity d_0 for every sample): ``|D|``
    into ``y``; whether its samples are singular."""
    s = 1.0 / math.sqrt(3.0)
    L = y.size
    for j in range(L):
        _, e0, e1, e2 = _separate_sample(R[i, j, 0], R[i, j, 1], R[i, j, 2], cx, cy, cz, ds,
                                         det, sing_sin2, s)
        y[j] = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    return L > 0 and det < sing_sin2


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _separate_ramp_row(R, i, d0, nrm, v, dirs, a0, a1, sing_sin2, mu_s, y):
    """The final separation of function i with the ramp chromaticity: ``μ_s`` and ``|D|``
    into ``mu_s``, ``y``; the number of singular samples. Branch-free per sample (selects)
    and with two outputs only, so that it vectorises (D follows from μ_s:
    :func:`_diffuse_row`)."""
    s = 1.0 / math.sqrt(3.0)
    L = y.size
    nx, ny, nz = nrm[i, 0], nrm[i, 1], nrm[i, 2]
    nv = nx * v[i, 0] + ny * v[i, 1] + nz * v[i, 2]
    nv = min(max(nv, 0.0), 1.0)
    d0x, d0y, d0z = d0[i, 0], d0[i, 1], d0[i, 2]
    b0, b1 = a0[i], a1[i]
    nsing = 0
    for j in range(L):
        nl = nx * dirs[j, 0] + ny * dirs[j, 1] + nz * dirs[j, 2]
        x = min(max(nl, 0.0), 1.0) * nv
        f = b0 * x + b1 * (1.0 - x)
        cx, cy, cz, ds, det = _chromaticity(d0x, d0y, d0z, f, s)
        nsing += 1 if det < sing_sin2 else 0
        ms, e0, e1, e2 = _separate_sample(R[i, j, 0], R[i, j, 1], R[i, j, 2], cx, cy, cz, ds,
                                          det, sing_sin2, s)
        mu_s[j] = ms
        y[j] = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    return nsing


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _diffuse_row(R, i, mu_s, E, D, out, direct):
    """D = R − max(μ_s, 0) s of function i (the same arithmetic as
    :func:`_separate_sample`): ``D ⊙ E`` as float32 into ``out[i]`` (``direct``), else D
    into ``D`` ``(L, 3)``."""
    s = 1.0 / math.sqrt(3.0)
    L = mu_s.size
    if direct:
        for j in range(L):
            sp = max(mu_s[j], 0.0) * s
            out[i, j, 0] = np.float32((R[i, j, 0] - sp) * E[j, 0])
            out[i, j, 1] = np.float32((R[i, j, 1] - sp) * E[j, 1])
            out[i, j, 2] = np.float32((R[i, j, 2] - sp) * E[j, 2])
    else:
        for j in range(L):
            sp = max(mu_s[j], 0.0) * s
            D[j, 0] = R[i, j, 0] - sp
            D[j, 1] = R[i, j, 1] - sp
            D[j, 2] = R[i, j, 2] - sp


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def separate_ramp(R, d0, nrm, v, dirs, a0, a1, uniform, sing_sin2, E, out):
    """§4.2 colour-space separation of every sample with the Eq. 6–7 ramp chromaticity.

    The fused form of ``separate_colour(R, ramp_chromaticity(d_0, ramp_f(n·l, n·v, α_0, α_1)))``
    (``_skin_model``; same formulas, s = (1, 1, 1)/√3): per sample
    ``c = normalize(d_0 + f (d_0 − s))`` (s where that vanishes), ``μ_s = (R·s − (R·c)(c·s))/|c × s|²``
    (0 where ``|c × s|² < sing_sin2``), ``D = R − max(μ_s, 0) s``. With ``uniform`` the
    chromaticity is d_0 itself (f = 0: the initial separation).

    Parameters
    ----------
    R : (N, L, 3) float64, white balanced
    d0, nrm, v : (N, 3) float64, unit
    dirs : (L, 3) float64
    a0, a1 : (N,) float64
    E : (L, 3) float64, light intensities; out : (N, L, 3) float32 or ``(0, 0, 3)``
        With ``out`` of N rows, ``D ⊙ E`` is written there in float32 (the fit's output, as
        ``float32(D * E)`` rounds it) instead of returning D: no float64 D, no numpy pass.

    Returns
    -------
    D : (N, L, 3) float64 (``(N, 0, 3)`` with ``uniform``: the initial separation needs |D|
        only; also with ``out``)
    mu_s : (N, L) float64 (``(N, 0)`` with ``uniform``)
    y : (N, L) float64, |D|
    singular : (N,) bool, any sample singular
    """
    N, L, _ = R.shape
    s = 1.0 / math.sqrt(3.0)
    Lw = 0 if uniform else L  # the initial separation only needs |D|
    direct = out.shape[0] == N and N > 0 and not uniform
    D = np.empty((N, 0 if direct else Lw, 3))
    mu_s = np.empty((N, Lw))
    y = np.empty((N, L))
    singular = np.zeros(N, np.bool_)
    for i in range(N):
        if uniform:
            # the chromaticity is the function's d_0 for every sample (once, not per sample)
            cx, cy, cz, ds, det = _chromaticity(d0[i, 0], d0[i, 1], d0[i, 2], 0.0, s)
            singular[i] = _separate_uniform_row(R, i, cx, cy, cz, ds, det, sing_sin2, y[i])
        else:
            singular[i] = _separate_ramp_row(R, i, d0, nrm, v, dirs, a0, a1, sing_sin2,
                                             mu_s[i], y[i]) > 0
            _diffuse_row(R, i, mu_s[i], E, D[i], out, direct)
    return D, mu_s, y, singular


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def ramp_inputs(R, w, sa, dirs, nrm, v, d0, mirror_sigma):
    """Per-sample inputs of ``_skin_fit.fit_ramp`` (its numpy preamble, fused): the weights
    ``w δA (1 − exp(−(1 − l·r)/σ))`` with ``r = 2(n·v)n − v`` (mirror samples down-weighted),
    ``x = clip(n·l) clip(n·v)``, ``max(0, n·l)``, and ``A``, ``R·d_0``, ``R·d_0 − R·s`` of
    ``ramp_mu_d``; ``d_0·s`` per function. Arrays ``(N, L)``, the last ``(N,)``."""
    N, L, _ = R.shape
    s = 1.0 / math.sqrt(3.0)
    wd = np.empty((N, L))
    xf = np.empty((N, L))
    nlf = np.empty((N, L))
    A = np.empty((N, L))
    Rd = np.empty((N, L))
    Rdms = np.empty((N, L))
    ds = np.empty(N)
    for i in range(N):
        nx, ny, nz = nrm[i, 0], nrm[i, 1], nrm[i, 2]
        nv0 = nx * v[i, 0] + ny * v[i, 1] + nz * v[i, 2]
        rx, ry, rz = 2.0 * nv0 * nx - v[i, 0], 2.0 * nv0 * ny - v[i, 1], 2.0 * nv0 * nz - v[i, 2]
        nvc = min(max(nv0, 0.0), 1.0)
        dsi = (d0[i, 0] + d0[i, 1] + d0[i, 2]) * s
        ds[i] = dsi
        ds2 = 1.0 - dsi * dsi
        # three loops of few outputs each: the first two vectorise (the exp of the third
        # cannot: no vector math library), and only usable samples take the exp
        _ramp_geometry_row(dirs, nx, ny, nz, nvc, nlf[i], xf[i])
        _ramp_colour_row(R, i, d0[i, 0], d0[i, 1], d0[i, 2], dsi, ds2, Rd[i], Rdms[i], A[i])
        for j in range(L):
            if w[i, j] > 0.0:
                lx, ly, lz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
                wm = 1.0 - np.exp(-(1.0 - (rx * lx + ry * ly + rz * lz)) / mirror_sigma)
                wd[i, j] = w[i, j] * sa[j] * wm
            else:
                wd[i, j] = 0.0
    return wd, xf, nlf, A, Rd, Rdms, ds


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _ramp_geometry_row(dirs, nx, ny, nz, nvc, nlf, xf):
    """``max(0, n·l)`` and ``x = min(n·l, 1) clip(n·v)`` of one function (:func:`ramp_inputs`)."""
    for j in range(nlf.size):
        nl = max(nx * dirs[j, 0] + ny * dirs[j, 1] + nz * dirs[j, 2], 0.0)
        nlf[j] = nl
        xf[j] = min(nl, 1.0) * nvc


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _ramp_colour_row(R, i, d0x, d0y, d0z, dsi, ds2, Rd, Rdms, A):
    """``R·d_0``, ``R·d_0 − R·s`` and A of function i (:func:`ramp_inputs`)."""
    s = 1.0 / math.sqrt(3.0)
    regular = ds2 > 0.0
    for j in range(Rd.size):
        r0, r1, r2 = R[i, j, 0], R[i, j, 1], R[i, j, 2]
        rd = r0 * d0x + r1 * d0y + r2 * d0z
        rs = (r0 + r1 + r2) * s
        Rd[j] = rd
        Rdms[j] = rd - rs
        a = (rd - rs * dsi) / ds2
        A[j] = a if regular else 0.0


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def specular_energy(S, shadow, dirs, sa, nrm, v, eta):
    """ρ_s of ``_skin_fit.specular_energy`` (Fig. 14 d), fused: per function
    ``Σ_l S_l (n·v)(n·h_l) / (F G (v·h_l)) δA_l`` over unshadowed lights with S > 0, n·l > 0,
    n·v > 0 and ``F G (v·h) > 1e-6``; F the exact unpolarised dielectric Fresnel term and G
    the Torrance–Sparrow attenuation, as ``brdf.fresnel_dielectric`` and
    ``brdf.torrance_sparrow_geometry`` write them (tested equal to the numpy reference)."""
    N, L = S.shape
    out = np.zeros(N)
    e2 = eta * eta - 1.0
    for i in range(N):
        nx, ny, nz = nrm[i, 0], nrm[i, 1], nrm[i, 2]
        vx, vy, vz = v[i, 0], v[i, 1], v[i, 2]
        nv = nx * vx + ny * vy + nz * vz
        if not nv > 0.0:
            continue
        acc = 0.0
        for j in range(L):
            s = S[i, j]
            if not s > 0.0 or shadow[i, j]:
                continue
            lx, ly, lz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
            nl = nx * lx + ny * ly + nz * lz
            if not nl > 0.0:
                continue
            hx, hy, hz = lx + vx, ly + vy, lz + vz
            hn = math.sqrt(hx * hx + hy * hy + hz * hz)
            if hn > 1e-30:
                hx, hy, hz = hx / hn, hy / hn, hz / hn
            else:
                hx, hy, hz = nx, ny, nz
            nh = nx * hx + ny * hy + nz * hz
            vh = vx * hx + vy * hy + vz * hz
            if not vh > 0.0:
                continue
            c = min(vh, 1.0)
            g = math.sqrt(e2 + c * c)
            a = (g - c) / (g + c)
            b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
            F = 0.5 * a * a * (1.0 + b * b)
            nhc = max(nh, 0.0)
            G = min(1.0, min(2.0 * nhc * nv / vh, 2.0 * nhc * nl / vh))
            den = F * G * vh
            if den > 1e-6:
                acc += s * nv * nhc / den * sa[j]
        out[i] = max(acc, 0.0)
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _select(a, k, i0):
    """The ``i0``-th smallest of ``a[:k]`` and the smallest value after it in that order
    (``(a_(i0), a_(i0+1))``, both a_(i0) when ``i0 = k − 1``), with ``a[:k]`` reordered:
    Wirth's selection (Hoare partitions around ``a[i0]``; equal values are swapped, so ties
    cost no more than distinct values), O(k) expected. The same order statistics as
    ``np.partition`` — whose numba implementation took ≈ 12 s of the first fit's compile
    (bounds checks formatting error messages, ``np.unique`` of the kth). No NaN in ``a[:k]``."""
    lo = 0
    hi = k - 1
    while lo < hi:
        x = a[i0]
        i = lo
        j = hi
        while True:
            while a[i] < x:
                i += 1
            while x < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
            if i > j:
                break
        if j < i0:
            lo = i
        if i0 < i:
            hi = j
    x = a[i0]
    y = x
    if i0 + 1 < k:
        y = a[i0 + 1]
        for j in range(i0 + 2, k):
            if a[j] < y:
                y = a[j]
    return x, y


@njit(cache=True, nogil=True, error_model="numpy")
def _percentile_select(a, k, q):
    """Linear-interpolation quantile ``q`` of ``a[:k]`` (numpy's default, as
    ``_skin_fit._row_nanquantile`` computes it; NaN when k = 0) without sorting: the two order
    statistics it needs by selection (:func:`_select` on a copy, O(k)). No NaN in ``a[:k]``."""
    if k == 0:
        return np.nan
    pos = q * (k - 1)
    i0 = int(math.floor(pos))
    lo, hi = _select(a[:k].copy(), k, i0)
    t = pos - i0
    if t >= 0.5:
        return hi - (hi - lo) * (1.0 - t)
    return lo + (hi - lo) * t


@njit(cache=True, nogil=True, error_model="numpy")
def _percentile_high(a, k, q):
    """:func:`_percentile_select` for a high quantile (the 99th percentile of 2048 samples
    needs the 21st and 22nd largest values): the ``k − ⌊q (k − 1)⌋`` largest values kept in a
    small sorted buffer in one pass (one comparison per sample once it is full), instead of
    ``np.partition``'s copy and selection. The same order statistics, so the same value.
    Falls back to :func:`_percentile_select` when more than 64 values would be kept. No NaN
    in ``a[:k]``."""
    if k == 0:
        return np.nan
    pos = q * (k - 1)
    i0 = int(math.floor(pos))
    top = k - i0
    if top > 64:
        return _percentile_select(a, k, q)
    buf = np.empty(top)  # the largest values seen, ascending
    cnt = 0
    for j in range(k):
        x = a[j]
        if cnt < top:
            p_ = cnt
            while p_ > 0 and buf[p_ - 1] > x:
                buf[p_] = buf[p_ - 1]
                p_ -= 1
            buf[p_] = x
            cnt += 1
        elif x > buf[0]:
            p_ = 0
            while p_ + 1 < top and buf[p_ + 1] < x:
                buf[p_] = buf[p_ + 1]
                p_ += 1
            buf[p_] = x
    lo = buf[0]  # the i0-th smallest
    hi = buf[1] if top > 1 else lo
    t = pos - i0
    if t >= 0.5:
        return hi - (hi - lo) * (1.0 - t)
    return lo + (hi - lo) * t


@njit(cache=True, nogil=True, error_model="numpy")
def median_ratios(R, valid, lo, hi):
    """The two medians of ``_skin_fit.initial_diffuse_chromaticity`` (§4.2), per function:
    over valid samples with brightness (R + G + B) in ``[lo, hi] ×`` the 90th percentile of
    the valid brightnesses and G, B > 0, R ≥ 0, the medians of R/G and of G/B. NaN where no
    sample qualifies. Order statistics by selection, not sorting (same values). Returns
    ``(r/g (N,), g/b (N,))``."""
    N, L, _ = R.shape
    mrg = np.empty(N)
    mgb = np.empty(N)
    for i in range(N):
        b = np.empty(L)
        k = _I0
        for j in range(L):
            if valid[i, j]:
                b[k] = R[i, j, 0] + R[i, j, 1] + R[i, j, 2]
                k += 1
        p90 = _percentile_select(b, k, 0.9)
        if not np.isfinite(p90):
            p90 = 0.0
        rg = np.empty(L)
        gb = np.empty(L)
        m = _I0
        for j in range(L):
            if not valid[i, j]:
                continue
            r0, r1, r2 = R[i, j, 0], R[i, j, 1], R[i, j, 2]
            bj = r0 + r1 + r2
            if bj >= lo * p90 and bj <= hi * p90 and r1 > 0.0 and r2 > 0.0 and r0 >= 0.0:
                rg[m] = r0 / r1
                gb[m] = r1 / r2
                m += 1
        mrg[i] = _percentile_select(rg, m, 0.5)
        mgb[i] = _percentile_select(gb, m, 0.5)
    return mrg, mgb


# ------------------------------------------------------------------------------- chunk set-up


@njit(cache=True, nogil=True, error_model="numpy")
def prepare_chunk(R, E, saturation, threshold, visibility, has_visibility):
    """The fit's per-sample set-up of one chunk (``skin.fit_reflectance`` before §4.2), fused.

    White balance ``R / E``; saturated samples (any channel ≥ ``saturation`` in input units;
    ``saturation`` +inf: none); the §4.4 shadow map of ``skin.shadow_map`` (brightness
    ``ΣR/E`` at or below ``threshold`` × its 99th percentile over the function's samples,
    saturated ones counted as 0; lights ``visibility`` hides). Plus what ``_fit_chunk`` needs
    of the same pass: each function's largest unsaturated brightness (black functions) and the
    99th percentile of ``|R/E|`` (saturated as 0; the cast-shadow test). No fastmath: the sums
    keep numpy's order, so the results equal the numpy steps bit for bit (tested).

    Parameters
    ----------
    R : (N, L, C) float32 or float64, ≥ 0
    E : (L, C) float64, light intensities
    saturation, threshold : float
    visibility : (N, L) bool (ignored unless ``has_visibility``)

    Returns
    -------
    Rw : (N, L, C) float64
    sat, shadow : (N, L) bool
    bmax, ref : (N,) float64
    """
    N, L, C = R.shape
    Rw = np.empty((N, L, C))
    sat = np.zeros((N, L), np.bool_)
    shadow = np.empty((N, L), np.bool_)
    bmax = np.empty(N)
    ref = np.empty(N)
    for i in range(N):
        b = np.empty(L)
        bz = np.empty(L)
        nz = np.empty(L)
        top = -np.inf
        for j in range(L):
            s_ = False
            acc = 0.0
            sq = 0.0
            for c in range(C):
                r = np.float64(R[i, j, c])
                if r >= saturation:
                    s_ = True
                rw = r / E[j, c]
                Rw[i, j, c] = rw
                if c == 0:
                    acc = rw
                    sq = rw * rw
                else:
                    acc = acc + rw
                    sq = sq + rw * rw
            sat[i, j] = s_
            b[j] = acc
            bz[j] = 0.0 if s_ else acc
            nz[j] = 0.0 if s_ else math.sqrt(sq)
            if bz[j] > top:
                top = bz[j]
        bmax[i] = top
        lim = threshold * _percentile_high(bz, L, 0.99)
        for j in range(L):
            shadow[i, j] = b[j] <= lim or (has_visibility and not visibility[i, j])
        ref[i] = _percentile_high(nz, L, 0.99)
    return Rw, sat, shadow, bmax, ref


# ------------------------------------------------------------------------------- ramp rows


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def chroma_rows(R, w, sa, dirs, nrm, v, A, ds, rows, chroma_sigma):
    """The chromaticity rows of ``_skin_fit.fit_ramp``'s second polish for the functions
    ``rows`` (``_skin_fit._chroma_rows``, fused; no copy of ``R[rows]``): ``B = R·s −
    A (d_0·s)`` and the unit row weights ``√w_c / √Σ w_c |R|²`` with ``w_c = w δA (1 −
    exp(−(1 − l·r)/σ_c))⁴``, ``r = 2(n·v)n − v``.

    Parameters
    ----------
    R : (N, L, 3) float64, white balanced
    w : (N, L) float64, 0/1 usable samples
    sa : (L,) δA; dirs : (L, 3)
    nrm, v : (n, 3) float64, unit, of the selected functions
    A : (n, L), ds : (n,) float64, of the selected functions (``ramp_inputs``)
    rows : (n,) int64, indices into R and w

    Returns
    -------
    B, cw : (n, L) float64
    """
    n = rows.size
    L = R.shape[1]
    s = 1.0 / math.sqrt(3.0)
    B = np.empty((n, L))
    cw = np.empty((n, L))
    for q in range(n):
        i = rows[q]
        nx, ny, nz = nrm[q, 0], nrm[q, 1], nrm[q, 2]
        nv = nx * v[q, 0] + ny * v[q, 1] + nz * v[q, 2]
        rx, ry, rz = 2.0 * nv * nx - v[q, 0], 2.0 * nv * ny - v[q, 1], 2.0 * nv * nz - v[q, 2]
        acc = 0.0
        _chroma_b_row(R, i, A[q], ds[q], B[q])  # vectorises; the exp below cannot
        for j in range(L):
            r0, r1, r2 = R[i, j, 0], R[i, j, 1], R[i, j, 2]
            wc = 0.0
            if w[i, j] > 0.0:
                cos_lr = rx * dirs[j, 0] + ry * dirs[j, 1] + rz * dirs[j, 2]
                t = 1.0 - math.exp(-(1.0 - cos_lr) / chroma_sigma)
                t *= t
                wc = w[i, j] * sa[j] * t * t
                acc += wc * (r0 * r0 + r1 * r1 + r2 * r2)
            cw[q, j] = wc
        inv = 1.0 / math.sqrt(max(acc, 1e-300))
        for j in range(L):
            cw[q, j] = math.sqrt(cw[q, j]) * inv
    return B, cw


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _chroma_b_row(R, i, A, ds, B):
    """``B = R·s − A (d_0·s)`` of function i (:func:`chroma_rows`)."""
    s = 1.0 / math.sqrt(3.0)
    for j in range(B.size):
        B[j] = (R[i, j, 0] + R[i, j, 1] + R[i, j, 2]) * s - A[j] * ds


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def colour_scatter(R, valid, b1, b2):
    """Per function, the scatter of the valid samples' colours in the plane ⊥ s
    (``_skin_fit._d0_from_ratios``): with ``u_1 = R·b_1``, ``u_2 = R·b_2``, the sums
    ``(Σ u_1², Σ u_1 u_2, Σ u_2²)`` over valid samples, each ``(N,)``."""
    N, L, _ = R.shape
    a = np.empty(N)
    b = np.empty(N)
    c = np.empty(N)
    for i in range(N):
        s11 = s12 = s22 = 0.0
        for j in range(L):
            if valid[i, j]:
                r0, r1, r2 = R[i, j, 0], R[i, j, 1], R[i, j, 2]
                u1 = r0 * b1[0] + r1 * b1[1] + r2 * b1[2]
                u2 = r0 * b2[0] + r1 * b2[1] + r2 * b2[2]
                s11 += u1 * u1
                s12 += u1 * u2
                s22 += u2 * u2
        a[i] = s11
        b[i] = s12
        c[i] = s22
    return a, b, c


# ------------------------------------------------------------------------------- small glue
# Per-function steps that numpy does in a dozen small calls per chunk (≈ 2 ms of Python glue
# per 64 functions, held under the GIL while the other worker waits): one call each.


@njit(cache=True, nogil=True, error_model="numpy")
def tangent_basis(n):
    """``_skin_fit._tangent_basis``: two unit vectors ``(N, 3)`` orthogonal to ``n`` and to
    each other, ``t_1 = normalize(n × a)`` (a = x̂, or ŷ where |n_x| ≥ 0.9; +Z where the
    cross product vanishes, as ``normalize``), ``t_2 = n × t_1``. Same arithmetic as the
    numpy steps (``np.cross``, ``normalize``)."""
    N = n.shape[0]
    t1 = np.empty((N, 3))
    t2 = np.empty((N, 3))
    for i in range(N):
        n0, n1, n2 = n[i, 0], n[i, 1], n[i, 2]
        a0, a1, a2 = (1.0, 0.0, 0.0) if abs(n0) < 0.9 else (0.0, 1.0, 0.0)
        c0 = n1 * a2 - n2 * a1
        c1 = n2 * a0 - n0 * a2
        c2 = n0 * a1 - n1 * a0
        r = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        if r > 1e-30:
            c0, c1, c2 = c0 / r, c1 / r, c2 / r
        else:
            c0, c1, c2 = 0.0, 0.0, 1.0
        t1[i, 0], t1[i, 1], t1[i, 2] = c0, c1, c2
        t2[i, 0] = n1 * c2 - n2 * c1
        t2[i, 1] = n2 * c0 - n0 * c2
        t2[i, 2] = n0 * c1 - n1 * c0
    return t1, t2


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def moment_normal(y, w, sa, dirs, fallback):
    """``_skin_fit.moment_normal``: ``normalize(Σ_l y_l w_l δA_l ω_l)`` per function (Ma et
    al. 2007), ``fallback`` where the moment vanishes (|m| ≤ 1e-300). ``y, w`` ``(N, L)``,
    ``sa`` ``(L,)``, ``dirs`` ``(L, 3)``, ``fallback`` ``(N, 3)``. Sums in light order (the
    numpy steps use a matrix product: equal to rounding)."""
    N, L = y.shape
    out = np.empty((N, 3))
    for i in range(N):
        m0 = m1 = m2 = 0.0
        for j in range(L):
            q = y[i, j] * w[i, j] * sa[j]
            m0 += q * dirs[j, 0]
            m1 += q * dirs[j, 1]
            m2 += q * dirs[j, 2]
        r = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
        if r > 1e-300:
            out[i, 0], out[i, 1], out[i, 2] = m0 / r, m1 / r, m2 / r
        else:
            out[i, 0], out[i, 1], out[i, 2] = fallback[i, 0], fallback[i, 1], fallback[i, 2]
    return out


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def cast_shadow(shadow, n, dirs, k, lim):
    """The cast-shadow test of ``skin._fit_chunk``: shadowed samples that the fitted lobe
    says are lit, ``shadow & (max(k, 0) max(0, n·l) > lim)``; ``shadow`` ``(N, L)`` bool,
    ``n`` ``(N, 3)``, ``k, lim`` ``(N,)``."""
    N, L = shadow.shape
    out = np.zeros((N, L), np.bool_)
    for i in range(N):
        kk = max(k[i], 0.0)
        for j in range(L):
            if shadow[i, j]:
                x = max(n[i, 0] * dirs[j, 0] + n[i, 1] * dirs[j, 1] + n[i, 2] * dirs[j, 2], 0.0)
                out[i, j] = kk * x > lim[i]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _unit_or(x0, x1, x2, f0, f1, f2):
    """``_skin_model.normalize`` of one vector (``f`` where |x| ≤ 1e-30)."""
    r = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    if r > 1e-30:
        return x0 / r, x1 / r, x2 / r
    return f0, f1, f2


@njit(cache=True, nogil=True, error_model="numpy")
def d0_from_ratios(mrg, mgb, a, b, c, b1, b2):
    """``_skin_fit._d0_from_ratios`` after its scatter sums (``colour_scatter``): d_0 =
    ``normalize(r/g, 1, 1/(g/b))`` (s where no sample qualified), projected onto the plane
    through s with the least colour scatter (normal e: the smallest-eigenvalue eigenvector of
    ``[[a, b], [b, c]]`` in the basis ``b1, b2`` ⊥ s). The numpy steps' arithmetic, one call
    instead of ≈ 40 small ones. Returns ``(d_0 (N, 3), found (N,))``."""
    N = mrg.shape[0]
    s = 1.0 / math.sqrt(3.0)
    d = np.empty((N, 3))
    found = np.empty(N, np.bool_)
    for i in range(N):
        fnd = np.isfinite(mrg[i]) and np.isfinite(mgb[i]) and mgb[i] > 0.0
        found[i] = fnd
        x0 = mrg[i] if fnd else 1.0
        x2 = 1.0 / mgb[i] if fnd else 1.0
        d0, d1, d2 = _unit_or(x0, 1.0, x2, s, s, s)
        ai, bi, ci = a[i], b[i], c[i]
        if fnd and (ai + ci) > 0.0:
            lam = 0.5 * (ai + ci) - math.sqrt(0.25 * ((ai - ci) * (ai - ci)) + bi * bi)
            if abs(bi) > 1e-300:
                ex, ey = bi, lam - ai
            else:
                ex, ey = (1.0, 0.0) if ai <= ci else (0.0, 1.0)
            e0, e1, e2 = _unit_or(ex * b1[0] + ey * b2[0], ex * b1[1] + ey * b2[1],
                                  ex * b1[2] + ey * b2[2], b1[0], b1[1], b1[2])
            de = d0 * e0 + d1 * e1 + d2 * e2
            d0, d1, d2 = _unit_or(d0 - de * e0, d1 - de * e1, d2 - de * e2, s, s, s)
        d[i, 0], d[i, 1], d[i, 2] = d0, d1, d2
    return d, found
