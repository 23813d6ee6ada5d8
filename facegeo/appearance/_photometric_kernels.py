"""Compiled per-pixel kernels of :mod:`facegeo.appearance.photometric`.

One pixel at a time (:func:`fit_chunk` loops over a chunk of pixels; the caller runs chunks on
worker threads, the kernels release the GIL): the robust Lambertian least squares, the §4.4
shadow map, the Torrance–Sparrow lobe's closed-form scale over a grid of roughnesses, and the
K-fold cross-validation over the fitted lights that chooses the model. The numpy reference of
the same steps is ``tests/test_photometric.py::reference_fit``; the kernels agree with it to
rounding (tested).

Conventions: ``y_lc = R_lc / E_lc`` (radiance per unit light intensity), ``ȳ_l`` its channel
mean, directions unit vectors in the lights' frame, ``w_l`` a sample's least-squares weight (0:
left out; otherwise the light's weight, 1 by default).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Model indices (``PhotometricFit.model``): Lambertian, Lambertian with the shadow map,
#: Lambertian + lobe, Lambertian + lobe with the shadow map.
LAMBERT, LAMBERT_SHADOW, LOBE, LOBE_SHADOW = 0, 1, 2, 3
N_MODELS = 4
#: Smallest λ_min / λ_max of a pixel's weighted light Gram matrix Σ w l lᵀ (as
#: ``lambertian.MIN_RCOND``): below it the lights it keeps do not determine b.
MIN_RCOND = 1e-6


# Slice assignments (``a[:] = b``) cost seconds of compile time each in numba (measured:
# 5.3 of the 6.7 s ``lambert`` took to compile); these loops cost nothing.
@njit(cache=True, nogil=True, error_model="numpy")
def _fill1(a, x):
    for i in range(a.shape[0]):
        a[i] = x


@njit(cache=True, nogil=True, error_model="numpy")
def _fill2(a, x):
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            a[i, j] = x


@njit(cache=True, nogil=True, error_model="numpy")
def _copy1(dst, src):
    for i in range(dst.shape[0]):
        dst[i] = src[i]


@njit(cache=True, nogil=True, error_model="numpy")
def _copy2(dst, src):
    for i in range(dst.shape[0]):
        for j in range(dst.shape[1]):
            dst[i, j] = src[i, j]


@njit(cache=True, nogil=True, error_model="numpy")
def fresnel(c, eta):
    """Unpolarised dielectric Fresnel reflectance (``brdf.fresnel_dielectric``), c = cos θ_d."""
    c = min(max(c, 0.0), 1.0)
    g = math.sqrt(eta * eta - 1.0 + c * c)
    a = (g - c) / (g + c)
    b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
    return 0.5 * a * a * (1.0 + b * b)


@njit(cache=True, nogil=True, error_model="numpy")
def lobe_value(n0, n1, n2, v0, v1, v2, l0, l1, l2, m, eta):
    """Eq. 8 of Debevec et al. 2000 for a small source, per unit irradiance:
    ``F(v·h) P(n·h) G / (4 n·v)`` with P the unit-normalised Beckmann distribution of RMS
    slope m, G the Torrance–Sparrow V-cavity term; 0 where ``n·l ≤ 0`` or ``n·v ≤ 0``.

    ``G / (4 n·v) = min(1/(4 n·v), n·h/(2 v·h), n·h n·l/(2 v·h n·v))``: finite at grazing
    views (the G term cancels the vanishing n·v, as in ``brdf.specular_brdf``)."""
    nl = n0 * l0 + n1 * l1 + n2 * l2
    nv = n0 * v0 + n1 * v1 + n2 * v2
    if nl <= 0.0 or nv <= 0.0:
        return 0.0
    h0, h1, h2 = l0 + v0, l1 + v1, l2 + v2
    hn = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2)  # |l + v| = 2 cos θ_d
    if hn < 1e-12:
        return 0.0
    nh = (nl + nv) / hn
    vh = 0.5 * hn
    if nh <= 1e-8:
        return 0.0
    nh = min(nh, 1.0)
    nh2 = nh * nh
    m2 = m * m
    p = math.exp((nh2 - 1.0) / (nh2 * m2)) / (math.pi * m2 * nh2 * nh2)
    g = min(0.25 / nv, nh / (2.0 * vh), nh * nl / (2.0 * vh * nv))
    return fresnel(vh, eta) * p * g


@njit(cache=True, nogil=True, error_model="numpy")
def lobe_peak(nv, m, eta):
    """The lobe at the mirror direction (h = n, G = 1): ``F(n·v) / (4 π m² n·v)``."""
    nv = max(nv, 1e-6)
    return fresnel(nv, eta) / (4.0 * math.pi * m * m * nv)


@njit(cache=True, nogil=True, error_model="numpy")
def _sym_eig_ratio(a, b, c, d, e, f):
    """λ_min / λ_max of the symmetric PSD matrix [[a, b, c], [b, d, e], [c, e, f]]
    (analytic eigenvalues; 0 when λ_max ≤ 0)."""
    p1 = b * b + c * c + e * e
    q = (a + d + f) / 3.0
    p2 = (a - q) ** 2 + (d - q) ** 2 + (f - q) ** 2 + 2.0 * p1
    if p2 <= 1e-300:  # a multiple of the identity
        return 1.0 if q > 0.0 else 0.0
    p = math.sqrt(p2 / 6.0)
    b00, b11, b22 = (a - q) / p, (d - q) / p, (f - q) / p
    b01, b02, b12 = b / p, c / p, e / p
    r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02)
               + b02 * (b01 * b12 - b11 * b02))
    r = min(max(r, -1.0), 1.0)
    phi = math.acos(r) / 3.0
    e_max = q + 2.0 * p * math.cos(phi)
    e_min = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    if e_max <= 0.0:
        return 0.0
    return max(e_min, 0.0) / e_max


@njit(cache=True, nogil=True, error_model="numpy")
def _inverse3(G, Gi):
    """Gi = G⁻¹ of a symmetric 3 × 3 G (adjugate); False when λ_min/λ_max ≤ MIN_RCOND."""
    a, b, c, d, e, f = G[0, 0], G[0, 1], G[0, 2], G[1, 1], G[1, 2], G[2, 2]
    if _sym_eig_ratio(a, b, c, d, e, f) <= MIN_RCOND:
        return False
    A = d * f - e * e
    B = c * e - b * f
    Cc = b * e - c * d
    det = a * A + b * B + c * Cc
    Gi[0, 0] = A / det
    Gi[0, 1] = B / det
    Gi[0, 2] = Cc / det
    Gi[1, 0] = B / det
    Gi[1, 1] = (a * f - c * c) / det
    Gi[1, 2] = (b * c - a * e) / det
    Gi[2, 0] = Cc / det
    Gi[2, 1] = Gi[1, 2]
    Gi[2, 2] = (a * d - b * b) / det
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def lambert(y, ybar, use, lw, D, iters, kappa, dark_frac, warm, b, w, wprev, Gi, h, G, Gt,
            hh):
    """Robust Lambertian least squares of one pixel over the lights with ``use``.

    Start: the samples brighter than ``dark_frac`` × the brightest used sample (§4.4's shadow
    threshold), or with ``warm`` the weights already in w (the folds start from the final
    fit's, restricted to their lights). Then up to ``iters`` times: keep the samples the fit
    lights (``b̄·l > 0``, b̄ the channel mean of b) that are not in a cast shadow
    (``ȳ ≥ κ b̄·l``) and solve again —
    the least squares of the clamped model ``max(0, b·l)`` with cast shadows left out.
    Writes b (C, 3), the weights w (L,) of the final solve, its G⁻¹ and h = Σ w y_c l
    (C, 3); returns False when even the start does not determine b. G, Gt (3, 3) and hh
    (C, 3): work space (no allocation per call)."""
    L, C = y.shape
    if not warm:
        top = 0.0
        for l in range(L):
            if use[l] and ybar[l] > top:
                top = ybar[l]
        for l in range(L):
            w[l] = lw[l] if (use[l] and ybar[l] > dark_frac * top) else 0.0
    ok = False
    restarted = False
    it = 0
    while it <= iters:
        _fill2(G, 0.0)
        _fill2(hh, 0.0)
        count = 0
        for l in range(L):
            wl = w[l]
            if wl <= 0.0:
                continue
            count += 1
            d0, d1, d2 = D[l, 0], D[l, 1], D[l, 2]
            G[0, 0] += wl * d0 * d0
            G[0, 1] += wl * d0 * d1
            G[0, 2] += wl * d0 * d2
            G[1, 1] += wl * d1 * d1
            G[1, 2] += wl * d1 * d2
            G[2, 2] += wl * d2 * d2
            for c in range(C):
                t = wl * y[l, c]
                hh[c, 0] += t * d0
                hh[c, 1] += t * d1
                hh[c, 2] += t * d2
        if count < 3 or not _inverse3(G, Gt):
            if ok:  # keep the previous solve and its weights
                _copy1(w, wprev)
                break
            if it == 0 and not restarted:  # the dark samples back in: every used sample
                restarted = True
                for l in range(L):
                    w[l] = lw[l] if use[l] else 0.0
                continue
            break
        _copy2(Gi, Gt)
        _copy2(h, hh)
        for c in range(C):
            for i in range(3):
                b[c, i] = Gi[i, 0] * hh[c, 0] + Gi[i, 1] * hh[c, 1] + Gi[i, 2] * hh[c, 2]
        _copy1(wprev, w)
        ok = True
        if it == iters:
            break
        bm0 = bm1 = bm2 = 0.0
        for c in range(C):
            bm0 += b[c, 0]
            bm1 += b[c, 1]
            bm2 += b[c, 2]
        changed = False
        for l in range(L):
            pred = (bm0 * D[l, 0] + bm1 * D[l, 1] + bm2 * D[l, 2]) / C
            keep = use[l] and pred > 0.0 and not (ybar[l] < kappa * pred)
            wl = lw[l] if keep else 0.0
            if wl != w[l]:
                changed = True
            w[l] = wl
        if not changed:
            break
        it += 1
    return ok


@njit(cache=True, nogil=True, error_model="numpy")
def shadow_map(ybar, use, D, b, kappa, vis):
    """§4.4 shadow map on the fitted lights: ``vis_l = clip(ȳ_l / b̄·l, 0, 1)`` where the
    sample is in a cast shadow (``ȳ < κ b̄·l``, ``b̄·l > 0``), else 1 (lit, attached shadow,
    or not used)."""
    L = ybar.shape[0]
    C = b.shape[0]
    bm0 = bm1 = bm2 = 0.0
    for c in range(C):
        bm0 += b[c, 0]
        bm1 += b[c, 1]
        bm2 += b[c, 2]
    for l in range(L):
        vis[l] = 1.0
        if not use[l]:
            continue
        pred = (bm0 * D[l, 0] + bm1 * D[l, 1] + bm2 * D[l, 2]) / C
        if pred > 0.0 and ybar[l] < kappa * pred:
            vis[l] = min(max(ybar[l] / pred, 0.0), 1.0)


@njit(cache=True, nogil=True, error_model="numpy")
def lobe(y, w, D, S, peak, Gi, h, b, cover, grey_cos, b_lobe, scratch):
    """The Torrance–Sparrow lobe of the model ``y_c = b_c·l + ρ_s s_l(m)`` (white after the
    division by E), for each roughness m_j of the grid over the samples with weight w.

    For a fixed m the least squares is closed form: with P⊥ the projection off the lights'
    columns, ``r_c = ⟨P⊥ s, y_c⟩ = Σ w s y_c − gᵀ G⁻¹ h_c`` and ``|P⊥ s|² = Σ w s² − gᵀ G⁻¹ g``
    (g = Σ w s l), ``ρ_s = Σ_c r_c / (C |P⊥ s|²)`` and the squared error falls by
    ``(Σ_c r_c)² / (C |P⊥ s|²)``; ``b_c = G⁻¹ (h_c − ρ_s g)``. A roughness is admitted when
    some weighted sample lies in its lobe (``max s ≥ cover × peak``: a lobe narrower than the
    lights' spacing is not determined), ρ_s > 0, and — with colour — the lobe's colour r is
    nearer white than the pixel's albedo colour |b_c| (a diffuse colour moved into the lobe is
    refused) unless the albedo itself is grey (``cos(albedo, white) ≥ grey_cos``: colour cannot
    tell them apart). Returns (ρ_s, index of m) of the largest fall, ``(0, -1)`` without one;
    b_lobe gets its b. ``scratch``: (6, max(C, 3)) float64 work space."""
    L, C = y.shape
    M = S.shape[1]
    best_gain = 0.0
    best_j = -1
    best_rho = 0.0
    # albedo colour and its angle to white
    a_norm = 0.0
    a_sum = 0.0
    alb = scratch[0, :C]
    for c in range(C):
        alb[c] = math.sqrt(b[c, 0] ** 2 + b[c, 1] ** 2 + b[c, 2] ** 2)
        a_norm += alb[c] * alb[c]
        a_sum += alb[c]
    a_norm = math.sqrt(a_norm)
    check_colour = C > 1 and a_norm > 0.0 and a_sum / (a_norm * math.sqrt(C)) < grey_cos
    r = scratch[1, :C]
    g = scratch[2, :3]
    gbest = scratch[3, :3]
    _fill1(gbest, 0.0)
    Gig = scratch[4, :3]
    sy = scratch[5, :C]
    for j in range(M):
        smax = 0.0
        ss = 0.0
        _fill1(g, 0.0)
        _fill1(sy, 0.0)
        for l in range(L):
            wl = w[l]
            if wl <= 0.0:
                continue
            s = S[l, j]
            if s == 0.0:
                continue
            if s > smax:
                smax = s
            ws = wl * s
            ss += ws * s
            g[0] += ws * D[l, 0]
            g[1] += ws * D[l, 1]
            g[2] += ws * D[l, 2]
            for c in range(C):
                sy[c] += ws * y[l, c]
        if smax < cover * peak[j]:
            continue
        for i in range(3):
            Gig[i] = Gi[i, 0] * g[0] + Gi[i, 1] * g[1] + Gi[i, 2] * g[2]
        sperp = ss - (g[0] * Gig[0] + g[1] * Gig[1] + g[2] * Gig[2])
        if not sperp > 1e-9 * ss:
            continue
        rsum = 0.0
        rnorm = 0.0
        for c in range(C):
            r[c] = sy[c] - (Gig[0] * h[c, 0] + Gig[1] * h[c, 1] + Gig[2] * h[c, 2])
            rsum += r[c]
            rnorm += r[c] * r[c]
        if rsum <= 0.0:
            continue
        if check_colour:
            ra = 0.0
            for c in range(C):
                ra += r[c] * alb[c]
            # cos(r, white) ≥ cos(r, albedo)  ⇔  Σr / √C ≥ r·a / |a|
            if rsum / math.sqrt(C) < ra / a_norm:
                continue
        gain = rsum * rsum / (C * sperp)
        if gain > best_gain:
            best_gain = gain
            best_j = j
            best_rho = rsum / (C * sperp)
            _copy1(gbest, Gig)
    for c in range(C):
        for i in range(3):
            b_lobe[c, i] = b[c, i] - best_rho * gbest[i]
    return best_rho, best_j


@njit(cache=True, nogil=True, error_model="numpy")
def lobe_table(n0, n1, n2, v0, v1, v2, D, ms, eta, S, peak):
    """S[l, j] = the lobe of normal n, view v at light l for roughness m_j (:func:`lobe_value`,
    its geometric factor F G / (4 n·v) computed once per light); peak[j] its value at the
    mirror direction."""
    nv = n0 * v0 + n1 * v1 + n2 * v2
    M = ms.shape[0]
    for j in range(M):
        peak[j] = lobe_peak(nv, ms[j], eta)
    for l in range(D.shape[0]):
        l0, l1, l2 = D[l, 0], D[l, 1], D[l, 2]
        nl = n0 * l0 + n1 * l1 + n2 * l2
        base = 0.0
        nh2 = 1.0
        if nl > 0.0 and nv > 0.0:
            h0, h1, h2 = l0 + v0, l1 + v1, l2 + v2
            hn = math.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
            if hn >= 1e-12:
                nh = (nl + nv) / hn
                if nh > 1e-8:
                    nh = min(nh, 1.0)
                    vh = 0.5 * hn
                    nh2 = nh * nh
                    g = min(0.25 / nv, nh / (2.0 * vh), nh * nl / (2.0 * vh * nv))
                    base = fresnel(vh, eta) * g / (math.pi * nh2 * nh2)
        for j in range(M):
            if base == 0.0:
                S[l, j] = 0.0
            else:
                m2 = ms[j] * ms[j]
                S[l, j] = base * math.exp((nh2 - 1.0) / (nh2 * m2)) / m2


@njit(cache=True, nogil=True, error_model="numpy")
def fit_chunk(R, invE, E, use, D, view, lw, fold, K, nbr_idx, nbr_w, ms, eta, kappa, dark_frac,
              cover, grey_cos, iters, lobe_passes, cv_always, b_lam, b_lobe, rho, m_index,
              n_lobe, vis, n_used, valid, cv_sse, cv_sae, cv_energy, cv_folds):
    """Fit a chunk of pixels: the final models on every fitted light and their K-fold
    cross-validation errors (module docstring of :mod:`facegeo.appearance.photometric`).

    Inputs: R (n, L, C) float32 radiance; invE, E (L, C) float64; use (n, L) bool (finite,
    trusted, unsaturated); D (L, 3) unit; view (n, 3) unit; lw (L,) light weights; fold (L,)
    int64 in [0, K); nbr_idx, nbr_w (L, k): each light's nearest lights outside its fold and
    their interpolation weights; ms (M,) roughness grid. Outputs (first axis n): b_lam,
    b_lobe (C, 3); rho; m_index (−1: no lobe); n_lobe (3,) the lobe's normal; vis (L,)
    float32; n_used; valid; cv_sse, cv_sae (4,) summed over the folds in frames' units;
    cv_energy Σ o² over the same samples; cv_folds (folds whose training lights determined a
    fit). A pixel whose final fit has neither a lobe nor a shadowed sample is not
    cross-validated (its four models coincide; ``cv_always`` does): CV errors 0, cv_folds 0.
    ``lobe_passes``: fits of the lobe, each from the normal of the previous one's diffuse
    part (the first from the robust Lambertian normal)."""
    n, L, C = R.shape
    M = ms.shape[0]
    y = np.empty((L, C))
    ybar = np.empty(L)
    w = np.empty(L)
    wprev = np.empty(L)
    wfin = np.empty(L)
    Gi = np.empty((3, 3))
    h = np.empty((C, 3))
    bA = np.empty((C, 3))
    bB = np.empty((C, 3))
    vk = np.empty(L)
    S = np.empty((L, M))
    peak = np.empty(M)
    tu = np.empty(L, np.bool_)
    G = np.empty((3, 3))
    Gt = np.empty((3, 3))
    hh = np.empty((C, 3))
    scr_b = np.empty((6, max(C, 3)))
    for i in range(n):
        for l in range(L):
            t = 0.0
            for c in range(C):
                y[l, c] = R[i, l, c] * invE[l, c]
                t += y[l, c]
            ybar[l] = t / C
        ok = lambert(y, ybar, use[i], lw, D, iters, kappa, dark_frac, False, bA, w, wprev, Gi, h,
                     G, Gt, hh)
        valid[i] = ok
        for q in range(4):
            cv_sse[i, q] = 0.0
            cv_sae[i, q] = 0.0
        cv_folds[i] = 0
        cv_energy[i] = 0.0
        if not ok:
            n_used[i] = 0
            rho[i] = 0.0
            m_index[i] = -1
            for c in range(C):
                for j in range(3):
                    b_lam[i, c, j] = np.nan
                    b_lobe[i, c, j] = np.nan
            for j in range(3):
                n_lobe[i, j] = np.nan
            for l in range(L):
                vis[i, l] = 1.0
            continue
        cnt = 0
        for l in range(L):
            if w[l] > 0.0:
                cnt += 1
        n_used[i] = cnt
        _copy1(wfin, w)
        _copy2(b_lam[i], bA)
        shadow_map(ybar, use[i], D, bA, kappa, vk)
        for l in range(L):
            vis[i, l] = vk[l]
        # the lobe's normal: the robust Lambertian one, then (where a lobe is found) the
        # normal of the lobe model's diffuse part until it settles; fixed for the folds
        v0, v1, v2 = view[i, 0], view[i, 1], view[i, 2]
        r = 0.0
        jm = -1
        s0 = s1 = s2 = 0.0
        for c in range(C):
            s0 += bA[c, 0]
            s1 += bA[c, 1]
            s2 += bA[c, 2]
        sn = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
        if sn > 0.0:
            s0, s1, s2 = s0 / sn, s1 / sn, s2 / sn
            p0, p1, p2 = s0, s1, s2
            for p in range(lobe_passes):
                lobe_table(s0, s1, s2, v0, v1, v2, D, ms, eta, S, peak)
                r, jm = lobe(y, w, D, S, peak, Gi, h, bA, cover, grey_cos, bB, scr_b)
                if jm < 0:
                    if p > 0:  # the previous normal's lobe, which was found
                        s0, s1, s2 = p0, p1, p2
                        lobe_table(s0, s1, s2, v0, v1, v2, D, ms, eta, S, peak)
                        r, jm = lobe(y, w, D, S, peak, Gi, h, bA, cover, grey_cos, bB, scr_b)
                    break
                t0 = t1 = t2 = 0.0
                for c in range(C):
                    t0 += bB[c, 0]
                    t1 += bB[c, 1]
                    t2 += bB[c, 2]
                tn = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
                if p == lobe_passes - 1 or not tn > 0.0 \
                        or (t0 * s0 + t1 * s1 + t2 * s2) / tn > 1.0 - 1e-14:
                    break  # the last pass, or settled (within ~1e-7 rad)
                p0, p1, p2 = s0, s1, s2
                s0, s1, s2 = t0 / tn, t1 / tn, t2 / tn
            n_lobe[i, 0], n_lobe[i, 1], n_lobe[i, 2] = s0, s1, s2
        else:  # b = 0: no normal, no lobe
            _fill2(S, 0.0)
            _fill1(peak, 1.0)
            _copy2(bB, bA)
        rho[i] = r
        m_index[i] = jm
        _copy2(b_lobe[i], bB)
        shadowed = False
        for l in range(L):
            if vis[i, l] < 1.0:
                shadowed = True
                break
        if jm < 0 and not shadowed and not cv_always:
            continue  # the four final models coincide: nothing to choose (CV errors 0)
        # K-fold cross-validation over the fitted lights
        for k in range(K):
            any_test = False
            for l in range(L):
                tu[l] = use[i, l] and fold[l] != k
                if use[i, l] and fold[l] == k:
                    any_test = True
            if not any_test:
                continue
            for l in range(L):
                w[l] = wfin[l] if tu[l] else 0.0
            if not lambert(y, ybar, tu, lw, D, iters, kappa, dark_frac, True, bA, w, wprev, Gi,
                           h, G, Gt, hh):
                continue
            cv_folds[i] += 1
            shadow_map(ybar, tu, D, bA, kappa, vk)
            rk, jk = lobe(y, w, D, S, peak, Gi, h, bA, cover, grey_cos, bB, scr_b)
            for l in range(L):
                if fold[l] != k or not use[i, l]:
                    continue
                V = 0.0
                for q in range(nbr_idx.shape[1]):
                    V += nbr_w[l, q] * vk[nbr_idx[l, q]]
                sl = rk * S[l, jk] if jk >= 0 else 0.0
                for c in range(C):
                    da = bA[c, 0] * D[l, 0] + bA[c, 1] * D[l, 1] + bA[c, 2] * D[l, 2]
                    db = bB[c, 0] * D[l, 0] + bB[c, 1] * D[l, 1] + bB[c, 2] * D[l, 2]
                    da = max(da, 0.0)
                    db = max(db, 0.0) + sl
                    o = y[l, c]
                    e = E[l, c]
                    cv_energy[i] += (o * e) * (o * e)
                    err = (da - o) * e
                    cv_sse[i, 0] += err * err
                    cv_sae[i, 0] += abs(err)
                    err = (da * V - o) * e
                    cv_sse[i, 1] += err * err
                    cv_sae[i, 1] += abs(err)
                    err = (db - o) * e
                    cv_sse[i, 2] += err * err
                    cv_sae[i, 2] += abs(err)
                    err = (db * V - o) * e
                    cv_sse[i, 3] += err * err
                    cv_sae[i, 3] += abs(err)
