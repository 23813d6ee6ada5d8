"""Compiled (numba) kernels of the skin-model fit's searches (Debevec et al. 2000, §4.2).

Private module behind :mod:`facegeo.appearance._skin_fit`. Each kernel runs one reflectance
function per iteration of a ``prange`` loop (both cores when numba has two threads) and fuses
what the numpy reference (``_skin_fit`` with ``KERNELS = False``) does with ``(n, K, L)``
temporaries into loops over the function's usable lights. They reproduce the reference's
algorithms exactly — the same compass/grid direct search (same candidate order, so the same
tie-breaking), the same Levenberg–Marquardt steps — and agree with it to rounding (tested in
``tests/test_skin_model.py``). Work the reference does and no result needs is skipped:

* **Lobe search, moments instead of sums** (``lobe_search``). The lobe misfit of Eq. 5's
  diffuse lobe needs ``Σ w y max(0, n·l)`` and ``Σ w max(0, n·l)²`` per candidate normal n.
  For lights with ``a·l > ρ`` around an anchor normal a, every candidate within ρ of a has
  ``n·l > 0`` (projecting onto the unit sphere from outside the ball is 1-Lipschitz), so their
  part is ``n·M₁`` and ``nᵀ M₂ n`` with the moments ``M₁ = Σ w y l`` and ``M₂ = Σ w l lᵀ``
  accumulated once; only the band ``|a·l| ≤ ρ`` is summed per candidate, and lights below
  ``−ρ`` contribute nothing. The anchor moves when the pattern would leave the ball or the
  ball is much wider than the step (moments rebuilt, or — when the new ball lies inside the
  old — only the old band sorted again); ρ is a few steps, so at the fine levels the band is
  nearly empty.
* **Centre values carried over**: the pattern's centre was the previous iteration's best.
* **Ramp search fused** (``ramp_search``): μ_d of §4.2 under each candidate ramp in closed
  form (``_skin_fit.ramp_mu_d``), the misfit's three weighted sums accumulated in the same loop.
* **Polish with the analytic Jacobian** (``ramp_polish``): the reference's Levenberg–Marquardt
  steps, but JᵀJ and Jᵀr from the residuals' analytic derivatives (one pass with derivatives
  instead of P forward-difference residual vectors; reused after a rejected step), the 4 × 4
  normal equations solved by Gaussian elimination per function, every sum in a register;
  a function stops once its steps fall below ``_skin_fit.POLISH_XTOL`` (converged). This one
  is not the reference's arithmetic: it converges to the same minimum (tested against the
  numpy polish and the Jacobian against central differences).

Kernels are compiled on first use and cached on disk (``cache=True``). The per-sample kernels
(separations, the ramp's inputs, ρ_s, d_0's median ratios) are in ``_skin_kernels_samples``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

#: Floors of :func:`facegeo.appearance._skin_fit._misfit_from_sums` (same values).
_TINY = 1e-300

# Grid pattern of _skin_fit.direct_search for P = 2, in its order (meshgrid of [0, -1, 1]²,
# "ij"): the centre first, so that ties keep the centre as there.
_OFFS2 = np.array([[0.0, 0.0], [0.0, -1.0], [0.0, 1.0], [-1.0, 0.0], [-1.0, -1.0], [-1.0, 1.0],
                   [1.0, 0.0], [1.0, -1.0], [1.0, 1.0]])

_FM = {"contract"}  # FMA contraction only: sums keep their order (results match to rounding)
#: Branch-free inner loops: reassociation too, so that their sums vectorise (AVX2: 4 lanes);
#: results then differ from the sequential sums by rounding only.
_FMV = {"contract", "reassoc"}


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _misfit(syy, sxy, sxx):
    if sxx > _TINY and syy > _TINY and sxy > 0.0:
        return 1.0 - sxy * sxy / (sxx * syy)
    return 1.0


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _unit3(a0, a1, a2):
    r = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    if r > 1e-30:
        return a0 / r, a1 / r, a2 / r
    return 0.0, 0.0, 1.0


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _pattern_move(best, u0, u1, step, halvings, levels):
    """One move of ``_skin_fit.direct_search`` (subset mode): to the best candidate; the step
    halves when the centre stayed best."""
    u0 += _OFFS2[best, 0] * step
    u1 += _OFFS2[best, 1] * step
    if best == 0 and halvings < levels + 1:
        step *= 0.5
        halvings += 1
    return u0, u1, step, halvings


# ------------------------------------------------------------------------------- lobe search


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _add_moments(mom, wy, wd, x, y, z):
    """One always-lit light into the moments M₁ = Σ w y l (``mom[:3]``) and M₂ = Σ w l lᵀ
    (``mom[3:]``: xx, yy, zz, xy, xz, yz)."""
    mom[0] += wy * x
    mom[1] += wy * y
    mom[2] += wy * z
    mom[3] += wd * x * x
    mom[4] += wd * y * y
    mom[5] += wd * z * z
    mom[6] += wd * x * y
    mom[7] += wd * x * z
    mom[8] += wd * y * z


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _lobe_anchor(ax, ay, az, rho, lx, ly, lz, wy, wd, band, mom):
    """Moments over lights with a·l > ρ into ``mom`` (M₁ 3, M₂ 6); band indices; returns count.
    (:func:`_lobe_refine` over every light, from zero moments.)"""
    for j in range(9):
        mom[j] = 0.0
    for j in range(lx.size):
        band[j] = j
    return _lobe_refine(ax, ay, az, rho, lx, ly, lz, wy, wd, band, lx.size, mom)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _lobe_refine(ax, ay, az, rho, lx, ly, lz, wy, wd, band, nb, mom):
    """:func:`_lobe_anchor` for a new anchor whose ball (radius ρ) lies inside the previous
    one: only the previous band's lights are classified again (into the moments, the band,
    or dropped); returns the new band's count."""
    k = 0
    for b in range(nb):
        j = band[b]
        c = ax * lx[j] + ay * ly[j] + az * lz[j]
        if c > rho:
            _add_moments(mom, wy[j], wd[j], lx[j], ly[j], lz[j])
        elif c >= -rho:
            band[k] = j
            k += 1
    return k


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _lobe_sums(nx, ny, nz, lx, ly, lz, wy, wd, band, nb, mom):
    sxy = nx * mom[0] + ny * mom[1] + nz * mom[2]
    sxx = (nx * nx * mom[3] + ny * ny * mom[4] + nz * nz * mom[5]
           + 2.0 * (nx * ny * mom[6] + nx * nz * mom[7] + ny * nz * mom[8]))
    for b in range(nb):
        j = band[b]
        x = nx * lx[j] + ny * ly[j] + nz * lz[j]
        if x > 0.0:
            sxy += wy[j] * x
            sxx += wd[j] * x * x
    return sxy, sxx


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _lobe_one(y, w, dirs, sa, ns, t1, t2, step0, levels, moves, out_u, i):
    L = y.size
    idx = np.empty(L, np.int64)
    m = 0
    for j in range(L):
        if w[j] > 0.0:
            idx[m] = j
            m += 1
    lx = np.empty(m)
    ly = np.empty(m)
    lz = np.empty(m)
    wy = np.empty(m)
    wd = np.empty(m)
    syy = 0.0
    for q in range(m):
        j = idx[q]
        lx[q] = dirs[j, 0]
        ly[q] = dirs[j, 1]
        lz[q] = dirs[j, 2]
        wd[q] = w[j] * sa[j]
        wy[q] = wd[q] * y[j]
        syy += wy[q] * y[j]
    band = np.empty(m, np.int64)
    mom = np.empty(9)
    n0x, n0y, n0z = ns[i, 0], ns[i, 1], ns[i, 2]
    ax, ay, az = n0x, n0y, n0z
    rho = 0.0
    nb = _lobe_anchor(ax, ay, az, rho, lx, ly, lz, wy, wd, band, mom)
    sxy, sxx = _lobe_sums(n0x, n0y, n0z, lx, ly, lz, wy, wd, band, nb, mom)
    val0 = _misfit(syy, sxy, sxx)
    u0 = 0.0
    u1 = 0.0
    step = step0
    halvings = 0
    val = val0
    have_centre = False
    sq2 = math.sqrt(2.0)
    for _ in range(levels * moves):
        if halvings > levels:
            break
        # centre on the sphere; the pattern stays within step·√2 of it
        cx, cy, cz = _unit3(n0x + u0 * t1[i, 0] + u1 * t2[i, 0],
                            n0y + u0 * t1[i, 1] + u1 * t2[i, 1],
                            n0z + u0 * t1[i, 2] + u1 * t2[i, 2])
        dx, dy, dz = cx - ax, cy - ay, cz - az
        # re-anchor when the pattern could leave the ball, or when the ball (and its band)
        # is much larger than the current step needs
        dist = math.sqrt(dx * dx + dy * dy + dz * dz)
        if dist + step * sq2 > rho or rho > 12.0 * step:
            rho_new = 3.0 * step * sq2
            if rho - dist >= rho_new:
                # the new ball lies inside the old one: lit lights stay lit and dropped ones
                # stay dark, only the band needs sorting again
                nb = _lobe_refine(cx, cy, cz, rho_new, lx, ly, lz, wy, wd, band, nb, mom)
            else:
                nb = _lobe_anchor(cx, cy, cz, rho_new, lx, ly, lz, wy, wd, band, mom)
            ax, ay, az = cx, cy, cz
            rho = rho_new
        best = 0
        bval = np.inf
        for k in range(9):
            if k == 0 and have_centre:
                f = val
            else:
                p0 = u0 + _OFFS2[k, 0] * step
                p1 = u1 + _OFFS2[k, 1] * step
                nx, ny, nz = _unit3(n0x + p0 * t1[i, 0] + p1 * t2[i, 0],
                                    n0y + p0 * t1[i, 1] + p1 * t2[i, 1],
                                    n0z + p0 * t1[i, 2] + p1 * t2[i, 2])
                sxy, sxx = _lobe_sums(nx, ny, nz, lx, ly, lz, wy, wd, band, nb, mom)
                f = _misfit(syy, sxy, sxx)
            if f < bval:  # non-finite values never win (+inf in direct_search)
                bval = f
                best = k
        u0, u1, step, halvings = _pattern_move(best, u0, u1, step, halvings, levels)
        val = bval
        have_centre = True
    out_u[i, 0] = u0
    out_u[i, 1] = u1
    # the lobe's scale k = Σ w δA y x / Σ w δA x² at the result, over every usable light
    nx, ny, nz = _unit3(n0x + u0 * t1[i, 0] + u1 * t2[i, 0],
                        n0y + u0 * t1[i, 1] + u1 * t2[i, 1],
                        n0z + u0 * t1[i, 2] + u1 * t2[i, 2])
    sxy = 0.0
    sxx = 0.0
    for q in range(m):
        x = nx * lx[q] + ny * ly[q] + nz * lz[q]
        if x > 0.0:
            sxy += wy[q] * x
            sxx += wd[q] * x * x
    k = sxy / sxx if sxx > 0.0 else 0.0
    return val0, val, max(k, 0.0)


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def lobe_search(y, w, dirs, sa, ns, t1, t2, step0, levels, moves):
    """Lambertian-lobe direct search of ``_skin_fit.fit_lambertian_lobe`` for N functions.

    Parameters: ``y, w`` ``(N, L)`` float64 (brightness, 0/1 usable), ``dirs`` ``(L, 3)``,
    ``sa`` ``(L,)`` δA, ``ns, t1, t2`` ``(N, 3)`` start normal and its tangent basis.
    Returns ``(u (N, 2) tangent offsets, k (N,) lobe scale ≥ 0, misfit_start (N,),
    misfit (N,))``.
    """
    N = y.shape[0]
    u = np.zeros((N, 2))
    kk = np.empty(N)
    v0 = np.empty(N)
    v1 = np.empty(N)
    for i in prange(N):
        a, b, c = _lobe_one(y[i], w[i], dirs, sa, ns, t1, t2, step0, levels, moves, u, i)
        v0[i] = a
        v1[i] = b
        kk[i] = c
    return u, kk, v0, v1


# ------------------------------------------------------------------------------- ramp


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _mu_d(f, A, Rd, Rdms, two_1mds, ds2k, sing_sin2, regular=False):
    """μ_d of §4.2 under ramp weight f (``_skin_fit.ramp_mu_d`` for one sample); ``regular``:
    the caller knows no sample of the ramp is singular (:func:`_maybe_singular`)."""
    g = 1.0 + f
    uu = max(1.0 + two_1mds * f * g, 1e-300)
    su = math.sqrt(uu)
    if regular:
        return A * su / g
    if g * g * ds2k < sing_sin2 * uu:
        return (Rd + f * Rdms) / su
    return A * su / g


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _maybe_singular(a0, a1, two_1mds, ds2k, sing_sin2):
    """Whether any sample can be singular under ramp (α_0, α_1): f is linear in x ∈ [0, 1], so
    |g| is bounded below and |u|² (convex in f) above by the ramp's two ends
    (``_skin_fit.ramp_mu_d``'s bound)."""
    g0 = 1.0 + a0
    g1 = 1.0 + a1
    gmin = min(abs(g0), abs(g1)) if g0 * g1 > 0.0 else 0.0
    uumax = 1.0 + two_1mds * max(a0 * g0, a1 * g1)
    return gmin * gmin * ds2k < sing_sin2 * uumax


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FMV)
def _ramp_sums_regular(da, a1, x, nl, wd, A, two_1mds):
    """Σ w μ_d² and Σ w μ_d n·l when no sample is singular: branch-free, so it vectorises."""
    syy = 0.0
    sxy = 0.0
    for j in range(x.size):
        f = da * x[j] + a1
        g = 1.0 + f
        uu = max(1.0 + two_1mds * f * g, 1e-300)
        mm = A[j] * math.sqrt(uu) / g
        t = wd[j] * mm
        syy += t * mm
        sxy += t * nl[j]
    return syy, sxy


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _ramp_value(a0, a1, x, nl, wd, A, Rd, Rdms, two_1mds, ds2k, sxx, sing_sin2):
    syy = 0.0
    sxy = 0.0
    da = a0 - a1
    if not _maybe_singular(a0, a1, two_1mds, ds2k, sing_sin2):
        syy, sxy = _ramp_sums_regular(da, a1, x, nl, wd, A, two_1mds)
    else:
        for j in range(x.size):
            f = da * x[j] + a1
            mm = _mu_d(f, A[j], Rd[j], Rdms[j], two_1mds, ds2k, sing_sin2)
            syy += wd[j] * mm * mm
            sxy += wd[j] * mm * nl[j]
    if sxx > _TINY and syy > _TINY and sxy > 0.0:
        return 1.0 - sxy * sxy / (sxx * syy)
    if syy > _TINY:
        return 1.0
    return syy


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _compact(w_i, L):
    idx = np.empty(L, np.int64)
    m = 0
    for j in range(L):
        if w_i[j] > 0.0:
            idx[m] = j
            m += 1
    return idx[:m]


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def ramp_search(x, nl, wd, A, Rd, Rdms, ds, step0, levels, moves, sing_sin2):
    """(α_0, α_1) grid direct search of ``_skin_fit.fit_ramp`` at a fixed normal, N functions.

    ``x`` ``(N, L)`` clipped cos θ_i cos θ_r, ``nl`` clipped n·l, ``wd`` weights (0: unused),
    ``A, Rd, Rdms`` ``(N, L)`` and ``ds`` ``(N,)`` as in ``_skin_fit.ramp_mu_d``.
    Returns ``(p (N, 2), misfit (N,))``.
    """
    N, L = x.shape
    p = np.zeros((N, 2))
    val = np.empty(N)
    for i in prange(N):
        idx = _compact(wd[i], L)
        xs = x[i][idx]
        nls = nl[i][idx]
        wds = wd[i][idx]
        As = A[i][idx]
        Rds = Rd[i][idx]
        Rms = Rdms[i][idx]
        two_1mds = 2.0 * (1.0 - ds[i])
        ds2k = 1.0 - ds[i] * ds[i]
        sxx = 0.0
        for j in range(idx.size):
            sxx += wds[j] * nls[j] * nls[j]
        u0 = 0.0
        u1 = 0.0
        step = step0
        halvings = 0
        v = np.inf
        have_centre = False
        for _ in range(levels * moves):
            if halvings > levels:
                break
            best = 0
            bval = np.inf
            for k in range(9):
                if k == 0 and have_centre:
                    f = v
                else:
                    f = _ramp_value(u0 + _OFFS2[k, 0] * step, u1 + _OFFS2[k, 1] * step, xs, nls,
                                    wds, As, Rds, Rms, two_1mds, ds2k, sxx, sing_sin2)
                if f < bval:  # non-finite values never win (+inf in direct_search)
                    bval = f
                    best = k
            u0, u1, step, halvings = _pattern_move(best, u0, u1, step, halvings, levels)
            v = bval
            have_centre = True
        p[i, 0] = u0
        p[i, 1] = u1
        val[i] = v
    return p, val


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _mu_s_df(f, A, B):
    """μ_s of §4.2 under ramp weight f, ``B + A f/(1 + f)`` (``_skin_fit.ramp_mu_s``), and
    dμ_s/df = A/(1 + f)²; both 0 where 1 + f ≈ 0."""
    g = 1.0 + f
    if abs(g) > 1e-6:
        return B + A * f / g, A / (g * g)
    return 0.0, 0.0


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FMV)
def _polish_residuals(p, nrm, normal, t1, t2, v, lx, ly, lz, sqw, A, Rd, Rdms, two_1mds, ds2k,
                      sing_sin2, r_out, xs_fix, nl_fix, B, cw, chroma):
    """Residuals √w (μ_d − k x)/√Σw μ_d² of ``_skin_fit.fit_ramp``'s polish into ``r_out``;
    returns Σ r² plus, with ``chroma``, the chromaticity rows Σ (c_j μ_s,j)² (``cw`` = c_j,
    ``B`` as in ``_skin_fit.ramp_mu_s``). ``nrm``: polish the normal too (p has 4 entries)."""
    m = r_out.size
    nx = ny = nz = nvc = 0.0
    if nrm:
        nx, ny, nz = _unit3(normal[0] + p[2] * t1[0] + p[3] * t2[0],
                            normal[1] + p[2] * t1[1] + p[3] * t2[1],
                            normal[2] + p[2] * t1[2] + p[3] * t2[2])
        nv = nx * v[0] + ny * v[1] + nz * v[2]
        nvc = min(max(nv, 0.0), 1.0)
    da = p[0] - p[1]
    regular = not _maybe_singular(p[0], p[1], two_1mds, ds2k, sing_sin2)
    syy = 0.0
    sxy = 0.0
    sxx = 0.0
    # first pass: μ_d · √w into r_out and the three sums; second pass: the residuals
    for j in range(m):
        if nrm:
            c = nx * lx[j] + ny * ly[j] + nz * lz[j]
            nlj = max(c, 0.0)
            xc = min(nlj, 1.0) * nvc
        else:
            nlj = nl_fix[j]
            xc = xs_fix[j]
        f = da * xc + p[1]
        mm = _mu_d(f, A[j], Rd[j], Rdms[j], two_1mds, ds2k, sing_sin2, regular) * sqw[j]
        xw = nlj * sqw[j]
        r_out[j] = mm
        syy += mm * mm
        sxy += mm * xw
        sxx += xw * xw
    ok = sxx > _TINY and syy > _TINY and sxy > 0.0
    k = sxy / sxx if ok else 0.0
    inv = 1.0 / math.sqrt(syy if syy > _TINY else 1.0)
    tot = 0.0
    for j in range(m):
        if nrm:
            c = nx * lx[j] + ny * ly[j] + nz * lz[j]
            nlj = max(c, 0.0)
        else:
            nlj = nl_fix[j]
        r = (r_out[j] - k * nlj * sqw[j]) * inv
        r_out[j] = r
        tot += r * r
    if chroma:
        for j in range(m):
            if nrm:
                c = nx * lx[j] + ny * ly[j] + nz * lz[j]
                xc = min(max(c, 0.0), 1.0) * nvc
            else:
                xc = xs_fix[j]
            ms, _ = _mu_s_df(da * xc + p[1], A[j], B[j])
            rc = cw[j] * ms
            tot += rc * rc
    return tot


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _mu_d_df(f, A, Rd, Rdms, two_1mds, ds2k, sing_sin2, regular=False):
    """μ_d of §4.2 under ramp weight f and its derivative dμ_d/df (``_mu_d``)."""
    g = 1.0 + f
    uu = 1.0 + two_1mds * f * g
    duu = two_1mds * (1.0 + 2.0 * f) if uu >= 1e-300 else 0.0
    uu = max(uu, 1e-300)
    su = math.sqrt(uu)
    dsu = 0.5 * duu / su
    if regular:
        return A * su / g, A * (dsu * g - su) / (g * g)
    if g * g * ds2k < sing_sin2 * uu:
        num = Rd + f * Rdms
        return num / su, Rdms / su - num * dsu / uu
    return A * su / g, A * (dsu * g - su) / (g * g)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FMV)
def _polish_jacobian(p, nrm, normal, t1, t2, v, lx, ly, lz, sqw, A, Rd, Rdms, two_1mds, ds2k,
                     sing_sin2, r_out, xs_fix, nl_fix, dm, dxw, JtJ, g, B, cw, chroma):
    """Residuals of :func:`_polish_residuals` into ``r_out`` with the analytic Jacobian,
    accumulated as ``JtJ`` ``(P, P)`` and ``g = Jᵀ r`` ``(P,)``; returns Σ r².

    r_j = (m_j − k x_j)/√s_yy with m_j = √w_j μ_d(f_j) (Eq. 6–7 and §4.2, f_j = α_1 +
    (α_0 − α_1) cos θ_i cos θ_r), x_j = √w_j max(0, n·l_j), k = s_xy/s_xx; the normal
    n = (n_0 + u t_1 + w t_2)/|·| (P = 4). Derivatives through k and s_yy included (the
    residual's variable projection); clamps and clips contribute zero derivative where active.
    ``dm`` ``(P, m)`` and ``dxw`` ``(2, m)`` are scratch. With ``chroma`` the chromaticity
    rows ρ_j = c_j μ_s(f_j) of :func:`_polish_residuals` are added (dρ_j/dp = c_j dμ_s/df
    df/dp; they do not enter k or s_yy).
    """
    m = r_out.size
    nx = ny = nz = nvc = dnvc0 = dnvc1 = 0.0
    d0x = d0y = d0z = d1x = d1y = d1z = 0.0
    if nrm:
        qx = normal[0] + p[2] * t1[0] + p[3] * t2[0]
        qy = normal[1] + p[2] * t1[1] + p[3] * t2[1]
        qz = normal[2] + p[2] * t1[2] + p[3] * t2[2]
        qn = math.sqrt(qx * qx + qy * qy + qz * qz)
        nx, ny, nz = _unit3(qx, qy, qz)
        a = nx * t1[0] + ny * t1[1] + nz * t1[2]
        b = nx * t2[0] + ny * t2[1] + nz * t2[2]
        d0x, d0y, d0z = (t1[0] - nx * a) / qn, (t1[1] - ny * a) / qn, (t1[2] - nz * a) / qn
        d1x, d1y, d1z = (t2[0] - nx * b) / qn, (t2[1] - ny * b) / qn, (t2[2] - nz * b) / qn
        nv = nx * v[0] + ny * v[1] + nz * v[2]
        nvc = min(max(nv, 0.0), 1.0)
        if 0.0 < nv < 1.0:
            dnvc0 = d0x * v[0] + d0y * v[1] + d0z * v[2]
            dnvc1 = d1x * v[0] + d1y * v[1] + d1z * v[2]
    da = p[0] - p[1]
    regular = not _maybe_singular(p[0], p[1], two_1mds, ds2k, sing_sin2)
    # every sum in a scalar (register) accumulator, not an array element: arrays could alias
    # the inputs, so LLVM would keep them in memory and the loop would not vectorise
    syy = sxy = sxx = 0.0
    dsyy0 = dsyy1 = dsyy2 = dsyy3 = 0.0
    dsxy0 = dsxy1 = dsxy2 = dsxy3 = 0.0
    dsxx2 = dsxx3 = 0.0
    ctot = 0.0
    cg0 = cg1 = cg2 = cg3 = 0.0
    c00 = c01 = c02 = c03 = c11 = c12 = c13 = c22 = c23 = c33 = 0.0
    for j in range(m):
        dn0 = 0.0
        dn1 = 0.0
        if nrm:
            c = nx * lx[j] + ny * ly[j] + nz * lz[j]
            nlj = max(c, 0.0)
            if c > 0.0:
                dn0 = d0x * lx[j] + d0y * ly[j] + d0z * lz[j]
                dn1 = d1x * lx[j] + d1y * ly[j] + d1z * lz[j]
            nlc = nlj
            dl0 = dn0
            dl1 = dn1
            if nlj > 1.0:
                nlc = 1.0
                dl0 = 0.0
                dl1 = 0.0
            xc = nlc * nvc
            dx0 = dl0 * nvc + nlc * dnvc0
            dx1 = dl1 * nvc + nlc * dnvc1
        else:
            nlj = nl_fix[j]
            xc = xs_fix[j]
            dx0 = 0.0
            dx1 = 0.0
        f = da * xc + p[1]
        if chroma:
            ms, dms = _mu_s_df(f, A[j], B[j])
            rc = cw[j] * ms
            dms *= cw[j]
            q0 = dms * xc
            q1 = dms * (1.0 - xc)
            ctot += rc * rc
            cg0 += q0 * rc
            cg1 += q1 * rc
            c00 += q0 * q0
            c01 += q0 * q1
            c11 += q1 * q1
            if nrm:
                q2 = dms * da * dx0
                q3 = dms * da * dx1
                cg2 += q2 * rc
                cg3 += q3 * rc
                c02 += q0 * q2
                c03 += q0 * q3
                c12 += q1 * q2
                c13 += q1 * q3
                c22 += q2 * q2
                c23 += q2 * q3
                c33 += q3 * q3
        mu, dmu = _mu_d_df(f, A[j], Rd[j], Rdms[j], two_1mds, ds2k, sing_sin2, regular)
        sw = sqw[j]
        mm = mu * sw
        xw = nlj * sw
        dmu *= sw
        r_out[j] = mm
        syy += mm * mm
        sxy += mm * xw
        sxx += xw * xw
        e0 = dmu * xc
        e1 = dmu * (1.0 - xc)
        dm[0, j] = e0
        dm[1, j] = e1
        dsyy0 += 2.0 * mm * e0
        dsyy1 += 2.0 * mm * e1
        dsxy0 += e0 * xw
        dsxy1 += e1 * xw
        if nrm:
            e2 = dmu * da * dx0
            e3 = dmu * da * dx1
            w0 = dn0 * sw
            w1 = dn1 * sw
            dm[2, j] = e2
            dm[3, j] = e3
            dxw[0, j] = w0
            dxw[1, j] = w1
            dsyy2 += 2.0 * mm * e2
            dsyy3 += 2.0 * mm * e3
            dsxy2 += e2 * xw + mm * w0
            dsxy3 += e3 * xw + mm * w1
            dsxx2 += 2.0 * xw * w0
            dsxx3 += 2.0 * xw * w1
    ok = sxx > _TINY and syy > _TINY and sxy > 0.0
    k = sxy / sxx if ok else 0.0
    dk0 = dk1 = dk2 = dk3 = 0.0
    if ok:
        dk0 = dsxy0 / sxx
        dk1 = dsxy1 / sxx
        dk2 = (dsxy2 - k * dsxx2) / sxx
        dk3 = (dsxy3 - k * dsxx3) / sxx
    big = syy > _TINY
    inv = 1.0 / math.sqrt(syy if big else 1.0)
    di0 = di1 = di2 = di3 = 0.0
    if big:
        h = -0.5 * inv * inv * inv
        di0 = h * dsyy0
        di1 = h * dsyy1
        di2 = h * dsyy2
        di3 = h * dsyy3
    # JᵀJ (10 unique entries) and Jᵀr accumulated in scalars, not in the arrays: register
    # accumulators (the arrays could alias the inputs, so LLVM keeps those in memory)
    a00 = a01 = a02 = a03 = a11 = a12 = a13 = a22 = a23 = a33 = 0.0
    g0 = g1 = g2 = g3 = 0.0
    tot = 0.0
    for j in range(m):
        if nrm:
            c = nx * lx[j] + ny * ly[j] + nz * lz[j]
            nlj = max(c, 0.0)
        else:
            nlj = nl_fix[j]
        xw = nlj * sqw[j]
        e = r_out[j] - k * xw
        r = e * inv
        r_out[j] = r
        tot += r * r
        j0 = (dm[0, j] - dk0 * xw) * inv + e * di0
        j1 = (dm[1, j] - dk1 * xw) * inv + e * di1
        g0 += j0 * r
        g1 += j1 * r
        a00 += j0 * j0
        a01 += j0 * j1
        a11 += j1 * j1
        if nrm:
            j2 = (dm[2, j] - dk2 * xw - k * dxw[0, j]) * inv + e * di2
            j3 = (dm[3, j] - dk3 * xw - k * dxw[1, j]) * inv + e * di3
            g2 += j2 * r
            g3 += j3 * r
            a02 += j0 * j2
            a03 += j0 * j3
            a12 += j1 * j2
            a13 += j1 * j3
            a22 += j2 * j2
            a23 += j2 * j3
            a33 += j3 * j3
    if chroma:
        # the chromaticity rows' part (they do not enter k or s_yy): same sums, added once
        g0, g1, g2, g3 = g0 + cg0, g1 + cg1, g2 + cg2, g3 + cg3
        a00, a01, a02, a03 = a00 + c00, a01 + c01, a02 + c02, a03 + c03
        a11, a12, a13 = a11 + c11, a12 + c12, a13 + c13
        a22, a23, a33 = a22 + c22, a23 + c23, a33 + c33
        tot += ctot
    g[0], g[1] = g0, g1
    JtJ[0, 0], JtJ[0, 1], JtJ[1, 0], JtJ[1, 1] = a00, a01, a01, a11
    if nrm:
        g[2], g[3] = g2, g3
        JtJ[0, 2], JtJ[0, 3], JtJ[1, 2], JtJ[1, 3] = a02, a03, a12, a13
        JtJ[2, 0], JtJ[3, 0], JtJ[2, 1], JtJ[3, 1] = a02, a03, a12, a13
        JtJ[2, 2], JtJ[2, 3], JtJ[3, 2], JtJ[3, 3] = a22, a23, a23, a33
    return tot


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _solve_small(A, b, P):
    """Gaussian elimination with partial pivoting in place; False when singular."""
    for c in range(P):
        piv = c
        for r in range(c + 1, P):
            if abs(A[r, c]) > abs(A[piv, c]):
                piv = r
        if A[piv, c] == 0.0 or not np.isfinite(A[piv, c]):
            return False
        if piv != c:
            for q in range(P):
                A[c, q], A[piv, q] = A[piv, q], A[c, q]
            b[c], b[piv] = b[piv], b[c]
        for r in range(c + 1, P):
            fct = A[r, c] / A[c, c]
            for q in range(c, P):
                A[r, q] -= fct * A[c, q]
            b[r] -= fct * b[c]
    for c in range(P - 1, -1, -1):
        acc = b[c]
        for q in range(c + 1, P):
            acc -= A[c, q] * b[q]
        b[c] = acc / A[c, c]
    return True


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def ramp_polish(p0, normal, t1, t2, v, dirs, x_fix, nl_fix, wd, A, Rd, Rdms, ds, iterations,
                sing_sin2, B, cw, chroma, xtol):
    """Levenberg–Marquardt polish of ``fit_ramp``'s residuals for N functions: the steps of
    ``_skin_fit.gauss_newton_polish`` (same damping, a step kept only where it lowers Σ r²)
    with the analytic Jacobian of :func:`_polish_jacobian` instead of finite differences, and
    JᵀJ, Jᵀr reused after a rejected step (x unchanged); trial points by their residuals only
    (:func:`_polish_residuals`, ≈ 1/20 of a pass with derivatives), derivatives only after an
    accepted step that is not the last. ``p0`` ``(N, 2)`` (ramp at the fixed
    normal) or ``(N, 4)`` (ramp and tangent offsets of the normal). With ``chroma`` the
    chromaticity rows ``cw μ_s`` (``B``, ``cw`` ``(N, L)``) join the residuals.

    A function stops before ``iterations`` once converged: when a proposed step has every
    ``|Δp| ≤ xtol`` and was either rejected (later steps, with the same JᵀJ and more damping,
    are shorter still) or accepted undamped (λ ≤ 1e-6: a Gauss–Newton step). Steps that small
    only move p by rounding (0: every function takes all ``iterations``). Returns
    ``(p, Σ r²)``."""
    N, P = p0.shape
    L = wd.shape[1]
    nrm = P == 4
    out = p0.copy()
    val = np.empty(N)
    for i in prange(N):
        idx = _compact(wd[i], L)
        m = idx.size
        lx = dirs[idx, 0].copy()
        ly = dirs[idx, 1].copy()
        lz = dirs[idx, 2].copy()
        sqw = np.sqrt(wd[i][idx])  # array
        As = A[i][idx]
        Rds = Rd[i][idx]
        Rms = Rdms[i][idx]
        xs = x_fix[i][idx]
        nls = nl_fix[i][idx]
        Bs = B[i][idx]
        cws = cw[i][idx]
        two_1mds = 2.0 * (1.0 - ds[i])
        ds2k = 1.0 - ds[i] * ds[i]
        x = out[i].copy()
        r = np.empty(m)
        rn = np.empty(m)
        pt = np.empty(P)
        JtJ = np.empty((P, P))
        g = np.empty(P)
        Am = np.empty((P, P))
        lam = 1e-8
        dm = np.empty((P, m))
        dxw = np.empty((2, m))
        # JtJ, g are those of the current x (kept across rejected steps)
        cur = _polish_jacobian(x, nrm, normal[i], t1[i], t2[i], v[i], lx, ly, lz, sqw, As, Rds,
                               Rms, two_1mds, ds2k, sing_sin2, r, xs, nls, dm, dxw, JtJ, g, Bs,
                               cws, chroma)
        for it in range(iterations):
            for a in range(P):
                for q in range(P):
                    Am[a, q] = JtJ[a, q]
                Am[a, a] += lam * max(JtJ[a, a], 1e-30)
                pt[a] = -g[a]
            if not _solve_small(Am, pt, P):
                break
            tiny = True
            for a in range(P):
                if not np.isfinite(pt[a]):
                    pt[a] = 0.0
                tiny = tiny and abs(pt[a]) <= xtol
                pt[a] += x[a]
            vn = _polish_residuals(pt, nrm, normal[i], t1[i], t2[i], v[i], lx, ly, lz, sqw, As,
                                   Rds, Rms, two_1mds, ds2k, sing_sin2, rn, xs, nls, Bs, cws,
                                   chroma)
            if np.isfinite(vn) and vn < cur:
                for a in range(P):
                    x[a] = pt[a]
                cur = vn
                if (tiny and lam <= 1e-6) or it == iterations - 1:
                    break  # an undamped (Gauss–Newton) step below xtol: converged; or the last
                _polish_jacobian(x, nrm, normal[i], t1[i], t2[i], v[i], lx, ly, lz, sqw, As,
                                 Rds, Rms, two_1mds, ds2k, sing_sin2, r, xs, nls, dm, dxw, JtJ,
                                 g, Bs, cws, chroma)
                lam *= 0.1
            else:
                if tiny:
                    break  # rejected below xtol: later steps (more damping, same JᵀJ) are smaller
                lam *= 10.0
        for a in range(P):
            out[i, a] = x[a]
        val[i] = cur
    return out, val
