"""Compiled (numba) kernels of the skin-model fit's searches (Debevec et al. 2000, §4.2).

Private module behind :mod:`facegeo.appearance._skin_fit`. Each kernel runs one reflectance
function per iteration of a plain (serial) loop — ``skin.fit_reflectance(threads=)`` runs
whole chunks on worker threads — and fuses
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
  steps, but JᵀJ and Jᵀr from the residuals' analytic derivatives — one branch-free,
  vectorised pass accumulating the Gram matrix of eight per-sample vectors
  (``_polish_jacobian``) instead of P forward-difference residual vectors; reused after a
  rejected step; the second (chromaticity) polish takes the lobe rows' part at its start from
  the first — the 4 × 4 normal equations solved by Gaussian elimination per function;
  a function stops once its steps fall below ``_skin_fit.POLISH_XTOL`` (converged). This one
  is not the reference's arithmetic: it converges to the same minimum (tested against the
  numpy polish and the Jacobian against central differences).
* **Overlapping pattern points reused** (``_cached_value``): after a move at the same step,
  3 or 5 of the 8 new candidates are new; the rest keep the previous iteration's values.

Kernels are compiled on first use and cached on disk (``cache=True``). The per-sample kernels
(separations, the ramp's inputs, ρ_s, d_0's median ratios) are in ``_skin_kernels_samples``.

**Compile time** (a cold cache's first fit; docs/skin.md): no kernel is ``parallel=True`` —
parfor lowering compiled every loop body twice (the serial and the gufunc version, int64 and
uint64 indices) for threads the fit never used; no ``np.partition`` (≈ 12 s alone:
``_skin_kernels_samples._select`` instead); per-sample inputs gathered in explicit loops, not
fancy indexing. ``inline="always"`` stays only where the helper's arithmetic takes the
caller's ``fastmath`` flags (FMA contraction): LLVM-level inlining would keep the helper's own
flags and change results by rounding; helpers without such arithmetic are ordinary calls.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Floors of :func:`facegeo.appearance._skin_fit._misfit_from_sums` (same values).
_TINY = 1e-300

# Grid pattern of _skin_fit.direct_search for P = 2, in its order (meshgrid of [0, -1, 1]²,
# "ij"): the centre first, so that ties keep the centre as there.
_OFFS2 = np.array([[0.0, 0.0], [0.0, -1.0], [0.0, 1.0], [-1.0, 0.0], [-1.0, -1.0], [-1.0, 1.0],
                   [1.0, 0.0], [1.0, -1.0], [1.0, 1.0]])

#: Zero as an int64 for loop-carried counters passed to other kernels: a variable started at a
#: literal ``0`` is typed ``Literal[int](0)`` in numba's first inference pass, and the callee
#: is compiled for that type as well as for int64 (measured: ≈ 0.3–0.9 CPU-s per callee).
_I0 = np.int64(0)

_FM = {"contract"}  # FMA contraction only: sums keep their order (results match to rounding)
#: Branch-free inner loops: reassociation too, so that their sums vectorise (AVX2: 4 lanes);
#: results then differ from the sequential sums by rounding only.
_FMV = {"contract", "reassoc"}


@njit(cache=True, nogil=True, error_model="numpy")
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


@njit(cache=True, nogil=True, error_model="numpy")
def _pattern_move(best, u0, u1, step, halvings, levels):
    """One move of ``_skin_fit.direct_search`` (subset mode): to the best candidate; the step
    halves when the centre stayed best."""
    u0 += _OFFS2[best, 0] * step
    u1 += _OFFS2[best, 1] * step
    if best == 0 and halvings < levels + 1:
        step *= 0.5
        halvings += 1
    return u0, u1, step, halvings


#: ``_IDX2[o_0 + 1, o_1 + 1]``: the index into ``_OFFS2`` of the offset (o_0, o_1).
_IDX2 = np.array([[4, 3, 5], [1, 0, 2], [7, 6, 8]])


@njit(cache=True, nogil=True, error_model="numpy")
def _cached_value(k, shift, prev):
    """Candidate k's objective from the previous iteration, or NaN when it was not evaluated
    there. After a move to the previous pattern's candidate ``shift`` (≥ 1: same step), the new
    pattern overlaps the old in 4 (diagonal move) or 6 (axis move) points; their values are
    the old ones (the same point but for the rounding of ``u + o·step``), so only 5 or 3 of
    the 8 new candidates are evaluated. ``shift`` 0: the step halved, nothing overlaps."""
    if shift <= 0:
        return np.nan
    q0 = int(_OFFS2[k, 0] + _OFFS2[shift, 0])
    q1 = int(_OFFS2[k, 1] + _OFFS2[shift, 1])
    if q0 < -1 or q0 > 1 or q1 < -1 or q1 > 1:
        return np.nan
    return prev[_IDX2[q0 + 1, q1 + 1]]


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
    """Moments over lights with a·l > ρ into ``mom`` (M₁ 3, M₂ 6); the band ``|a·l| ≤ ρ``
    copied into ``band`` (rows lx, ly, lz, wy, wd: contiguous, so that :func:`_lobe_sums`
    vectorises); returns its count."""
    for j in range(9):
        mom[j] = 0.0
    k = 0
    for j in range(lx.size):
        c = ax * lx[j] + ay * ly[j] + az * lz[j]
        if c > rho:
            _add_moments(mom, wy[j], wd[j], lx[j], ly[j], lz[j])
        elif c >= -rho:
            band[0, k] = lx[j]
            band[1, k] = ly[j]
            band[2, k] = lz[j]
            band[3, k] = wy[j]
            band[4, k] = wd[j]
            k += 1
    return k


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _lobe_refine(ax, ay, az, rho, band, nb, mom):
    """:func:`_lobe_anchor` for a new anchor whose ball (radius ρ) lies inside the previous
    one: only the previous band's lights are classified again (into the moments, the band —
    compacted in place — or dropped); returns the new band's count."""
    k = 0
    for b in range(nb):
        x, y, z = band[0, b], band[1, b], band[2, b]
        c = ax * x + ay * y + az * z
        if c > rho:
            _add_moments(mom, band[3, b], band[4, b], x, y, z)
        elif c >= -rho:
            for r in range(5):
                band[r, k] = band[r, b]
            k += 1
    return k


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FMV)
def _lobe_sums(nx, ny, nz, band, nb, mom):
    """``(Σ w δA y max(0, n·l), Σ w δA max(0, n·l)²)`` for a candidate n within the anchor's
    ball: the lit lights' part from the moments, the band's summed (branch-free, so it
    vectorises; reassociated, which changes the sums by rounding only)."""
    sxy = nx * mom[0] + ny * mom[1] + nz * mom[2]
    sxx = (nx * nx * mom[3] + ny * ny * mom[4] + nz * nz * mom[5]
           + 2.0 * (nx * ny * mom[6] + nx * nz * mom[7] + ny * nz * mom[8]))
    bxy = 0.0
    bxx = 0.0
    for b in range(nb):
        x = nx * band[0, b] + ny * band[1, b] + nz * band[2, b]
        x = x if x > 0.0 else 0.0
        bxy += band[3, b] * x
        bxx += band[4, b] * x * x
    return sxy + bxy, sxx + bxx


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
    band = np.empty((5, m))
    mom = np.empty(9)
    n0x, n0y, n0z = ns[i, 0], ns[i, 1], ns[i, 2]
    ax, ay, az = n0x, n0y, n0z
    rho = 0.0
    nb = _lobe_anchor(ax, ay, az, rho, lx, ly, lz, wy, wd, band, mom)
    sxy, sxx = _lobe_sums(n0x, n0y, n0z, band, nb, mom)
    val0 = _misfit(syy, sxy, sxx)
    u0 = 0.0
    u1 = 0.0
    step = step0
    halvings = _I0  # int64, not a literal (see _I0)
    val = val0
    have_centre = False
    sq2 = math.sqrt(2.0)
    prev = np.empty(9)  # the previous pattern's values (_cached_value)
    cur = np.empty(9)
    shift = _I0
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
                nb = _lobe_refine(cx, cy, cz, rho_new, band, nb, mom)
            else:
                nb = _lobe_anchor(cx, cy, cz, rho_new, lx, ly, lz, wy, wd, band, mom)
            ax, ay, az = cx, cy, cz
            rho = rho_new
        best = _I0
        bval = np.inf
        for k in range(9):
            f = _cached_value(k, shift, prev)
            if k == 0 and have_centre:
                f = val
            elif not f == f:  # not cached (NaN): evaluate
                p0 = u0 + _OFFS2[k, 0] * step
                p1 = u1 + _OFFS2[k, 1] * step
                nx, ny, nz = _unit3(n0x + p0 * t1[i, 0] + p1 * t2[i, 0],
                                    n0y + p0 * t1[i, 1] + p1 * t2[i, 1],
                                    n0z + p0 * t1[i, 2] + p1 * t2[i, 2])
                sxy, sxx = _lobe_sums(nx, ny, nz, band, nb, mom)
                f = _misfit(syy, sxy, sxx)
            cur[k] = f
            if f < bval:  # non-finite values never win (+inf in direct_search)
                bval = f
                best = k
        u0, u1, step, halvings = _pattern_move(best, u0, u1, step, halvings, levels)
        prev, cur = cur, prev
        shift = best
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


@njit(cache=True, nogil=True, error_model="numpy")
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
    for i in range(N):
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


@njit(cache=True, nogil=True, error_model="numpy")
def _take_row(a, i, idx):
    """``a[i, idx]`` as a new array, in one loop: the same values as the fancy-indexing
    expression, whose numba implementation costs far more compile time."""
    out = np.empty(idx.size)
    for q in range(idx.size):
        out[q] = a[i, idx[q]]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def ramp_search(x, nl, wd, A, Rd, Rdms, ds, step0, levels, moves, sing_sin2):
    """(α_0, α_1) grid direct search of ``_skin_fit.fit_ramp`` at a fixed normal, N functions.

    ``x`` ``(N, L)`` clipped cos θ_i cos θ_r, ``nl`` clipped n·l, ``wd`` weights (0: unused),
    ``A, Rd, Rdms`` ``(N, L)`` and ``ds`` ``(N,)`` as in ``_skin_fit.ramp_mu_d``.
    Returns ``(p (N, 2), misfit (N,))``.
    """
    N, L = x.shape
    p = np.zeros((N, 2))
    val = np.empty(N)
    for i in range(N):
        idx = _compact(wd[i], L)
        m = idx.size
        xs = _take_row(x, i, idx)
        nls = _take_row(nl, i, idx)
        wds = _take_row(wd, i, idx)
        As = _take_row(A, i, idx)
        Rds = _take_row(Rd, i, idx)
        Rms = _take_row(Rdms, i, idx)
        two_1mds = 2.0 * (1.0 - ds[i])
        ds2k = 1.0 - ds[i] * ds[i]
        sxx = 0.0
        for j in range(m):
            sxx += wds[j] * nls[j] * nls[j]
        u0 = 0.0
        u1 = 0.0
        step = step0
        halvings = _I0
        v = np.inf
        have_centre = False
        prev = np.empty(9)  # the previous pattern's values (_cached_value)
        cur = np.empty(9)
        shift = _I0
        for _ in range(levels * moves):
            if halvings > levels:
                break
            best = _I0
            bval = np.inf
            for k in range(9):
                f = _cached_value(k, shift, prev)
                if k == 0 and have_centre:
                    f = v
                elif not f == f:  # not cached (NaN): evaluate
                    f = _ramp_value(u0 + _OFFS2[k, 0] * step, u1 + _OFFS2[k, 1] * step, xs, nls,
                                    wds, As, Rds, Rms, two_1mds, ds2k, sxx, sing_sin2)
                cur[k] = f
                if f < bval:  # non-finite values never win (+inf in direct_search)
                    bval = f
                    best = k
            u0, u1, step, halvings = _pattern_move(best, u0, u1, step, halvings, levels)
            prev, cur = cur, prev
            shift = best
            v = bval
            have_centre = True
        p[i, 0] = u0
        p[i, 1] = u1
        val[i] = v
    return p, val


#: Σ r² above which :func:`_polish_residuals` (``rows=False``) takes the lobe rows' sum from
#: the first pass's three sums instead of summing the residuals (error ≤ 1e-10 of it there).
_SUMS_MIN = 1e-6


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FMV)
def _polish_residuals(p, nrm, normal, t1, t2, v, lx, ly, lz, sqw, A, Rd, Rdms, two_1mds, ds2k,
                      sing_sin2, r_out, xs_fix, nl_fix, B, cw, chroma, rows=True):
    """Residuals √w (μ_d − k x)/√Σw μ_d² of ``_skin_fit.fit_ramp``'s polish into ``r_out``;
    returns Σ r² plus, with ``chroma``, the chromaticity rows Σ (c_j μ_s,j)² (``cw`` = c_j,
    ``B`` as in ``_skin_fit.ramp_mu_s``). ``nrm``: polish the normal too (p has 4 entries).
    The loops are straight-line (selects), so they vectorise; at a fixed normal n·l is
    recomputed from ``normal`` (equal to ``nl_fix``, ``xs_fix`` to rounding).

    ``rows`` False (the LM steps need Σ r² only): where the lobe rows' Σ r² from the first
    pass's sums, ``1 − s_xy²/(s_xx s_yy)``, exceeds :data:`_SUMS_MIN` it is returned as is and
    the second pass (the residuals themselves) is skipped; ``r_out`` then holds √w μ_d. The
    form's absolute error is ≈ 1e-16 (cancellation), ≤ 1e-10 of the value there; below it,
    as on paper-mode data near the minimum (1e-15), the residuals are summed."""
    m = r_out.size
    nx, ny, nz, nvc = _polish_frame(p, nrm, normal, t1, t2, v)[:4]
    da = p[0] - p[1]
    p1 = p[1]
    thr = -1.0 if not _maybe_singular(p[0], p[1], two_1mds, ds2k, sing_sin2) else sing_sin2
    syy = 0.0
    sxy = 0.0
    sxx = 0.0
    # first pass: μ_d · √w into r_out and the three sums; second pass: the residuals
    for j in range(m):
        c = nx * lx[j] + ny * ly[j] + nz * lz[j]
        nlj = c if c > 0.0 else 0.0
        xc = (nlj if nlj < 1.0 else 1.0) * nvc
        mu, _ = _mu_d_df(da * xc + p1, A[j], Rd[j], Rdms[j], two_1mds, ds2k, thr)
        mm = mu * sqw[j]
        xw = nlj * sqw[j]
        r_out[j] = mm
        syy += mm * mm
        sxy += mm * xw
        sxx += xw * xw
    ok = sxx > _TINY and syy > _TINY and sxy > 0.0
    k = sxy / sxx if ok else 0.0
    if not rows and ok:
        tot = 1.0 - k * sxy / syy
        if tot > _SUMS_MIN:
            if chroma:
                tot += _polish_residuals_chroma(p, nrm, normal, t1, t2, v, lx, ly, lz, A, B, cw)
            return tot
    inv = 1.0 / math.sqrt(syy if syy > _TINY else 1.0)
    tot = 0.0
    for j in range(m):
        c = nx * lx[j] + ny * ly[j] + nz * lz[j]
        nlj = c if c > 0.0 else 0.0
        r = (r_out[j] - k * nlj * sqw[j]) * inv
        r_out[j] = r
        tot += r * r
    if chroma:
        tot += _polish_residuals_chroma(p, nrm, normal, t1, t2, v, lx, ly, lz, A, B, cw)
    return tot


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FMV)
def _polish_residuals_chroma(p, nrm, normal, t1, t2, v, lx, ly, lz, A, B, cw):
    """The chromaticity rows' part of :func:`_polish_residuals`: Σ (c_j μ_s,j)²."""
    nx, ny, nz, nvc = _polish_frame(p, nrm, normal, t1, t2, v)[:4]
    da = p[0] - p[1]
    p1 = p[1]
    tot = 0.0
    for j in range(lx.size):
        c = nx * lx[j] + ny * ly[j] + nz * lz[j]
        nlj = c if c > 0.0 else 0.0
        xc = (nlj if nlj < 1.0 else 1.0) * nvc
        ms, _ = _mu_s_df(da * xc + p1, A[j], B[j])
        rc = cw[j] * ms
        tot += rc * rc
    return tot


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _polish_geometry(j, nx, ny, nz, nvc, dnvc0, dnvc1, d0x, d0y, d0z, d1x, d1y, d1z, lx, ly, lz):
    """Sample j's ``max(0, n·l)``, ``x = clip(n·l) clip(n·v)`` and the derivatives of both
    along the normal's tangent offsets (``(nl, x, dnl_0, dnl_1, dx_0, dx_1)``; zero where a
    clamp or clip is active, and wherever the ``d*`` directions are zero). Straight-line code
    (selects only), so that the loops calling it vectorise."""
    c = nx * lx[j] + ny * ly[j] + nz * lz[j]
    e0 = d0x * lx[j] + d0y * ly[j] + d0z * lz[j]
    e1 = d1x * lx[j] + d1y * ly[j] + d1z * lz[j]
    lit = c > 0.0
    nlj = c if lit else 0.0
    dn0 = e0 if lit else 0.0
    dn1 = e1 if lit else 0.0
    inside = nlj <= 1.0
    nlc = nlj if inside else 1.0
    dl0 = dn0 if inside else 0.0
    dl1 = dn1 if inside else 0.0
    return (nlj, nlc * nvc, dn0, dn1, dl0 * nvc + nlc * dnvc0, dl1 * nvc + nlc * dnvc1)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _mu_d_df(f, A, Rd, Rdms, two_1mds, ds2k, thr):
    """μ_d of §4.2 under ramp weight f (:func:`_mu_d`) and its derivative dμ_d/df, without
    branches: the singular form where ``g² |d_0 × s|² < thr |u|²`` (``thr`` = ``sing_sin2``,
    or −1 when the ramp is known regular: never)."""
    g = 1.0 + f
    uu0 = 1.0 + two_1mds * f * g
    pos = uu0 >= 1e-300
    duu = two_1mds * (1.0 + 2.0 * f) if pos else 0.0
    uu = uu0 if pos else 1e-300
    su = math.sqrt(uu)
    isu = 1.0 / su  # two reciprocals instead of six divisions (they bound the loops' speed)
    ig = 1.0 / g
    dsu = 0.5 * duu * isu
    num = Rd + f * Rdms
    sing = g * g * ds2k < thr * uu
    mu = num * isu if sing else A * su * ig
    dmu = (Rdms - num * dsu * isu) * isu if sing else A * (dsu - su * ig) * ig
    return mu, dmu


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _mu_s_df(f, A, B):
    """μ_s of §4.2 under ramp weight f, ``B + A f/(1 + f)`` (``_skin_fit.ramp_mu_s``), and
    dμ_s/df = A/(1 + f)²; both 0 where 1 + f ≈ 0. Without branches."""
    g = 1.0 + f
    ok = abs(g) > 1e-6
    ig = 1.0 / (g if ok else 1.0)
    ms = B + A * f * ig
    dms = A * ig * ig
    return (ms if ok else 0.0), (dms if ok else 0.0)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _polish_frame(p, nrm, normal, t1, t2, v):
    """The polish's normal n, ``clip(n·v)`` and their derivatives along the tangent offsets
    (zero at a fixed normal, whose n·l then equals ``nl_fix`` to rounding: the loops need no
    branch on ``nrm``). Returns ``(nx, ny, nz, nvc, dnvc0, dnvc1, ∂n/∂u (3), ∂n/∂w (3))``."""
    u2 = p[2] if nrm else 0.0
    u3 = p[3] if nrm else 0.0
    qx = normal[0] + u2 * t1[0] + u3 * t2[0]
    qy = normal[1] + u2 * t1[1] + u3 * t2[1]
    qz = normal[2] + u2 * t1[2] + u3 * t2[2]
    qn = math.sqrt(qx * qx + qy * qy + qz * qz)
    nx, ny, nz = _unit3(qx, qy, qz)
    d0x = d0y = d0z = d1x = d1y = d1z = dnvc0 = dnvc1 = 0.0
    nv = nx * v[0] + ny * v[1] + nz * v[2]
    nvc = min(max(nv, 0.0), 1.0)
    if nrm:
        a = nx * t1[0] + ny * t1[1] + nz * t1[2]
        b = nx * t2[0] + ny * t2[1] + nz * t2[2]
        d0x, d0y, d0z = (t1[0] - nx * a) / qn, (t1[1] - ny * a) / qn, (t1[2] - nz * a) / qn
        d1x, d1y, d1z = (t2[0] - nx * b) / qn, (t2[1] - ny * b) / qn, (t2[2] - nz * b) / qn
        if 0.0 < nv < 1.0:
            dnvc0 = d0x * v[0] + d0y * v[1] + d0z * v[2]
            dnvc1 = d1x * v[0] + d1y * v[1] + d1z * v[2]
    return nx, ny, nz, nvc, dnvc0, dnvc1, d0x, d0y, d0z, d1x, d1y, d1z


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FMV)
def _polish_jacobian(p, nrm, normal, t1, t2, v, lx, ly, lz, sqw, A, Rd, Rdms, two_1mds, ds2k,
                     sing_sin2, xs_fix, nl_fix, JtJ, g, B, cw, chroma):
    """JᵀJ ``(P, P)`` and ``g = Jᵀ r`` ``(P,)`` of :func:`_polish_residuals`'s residuals at p,
    from their analytic derivatives, in one pass over the samples without storing any.

    r_j = (m_j − k x_j)/√s_yy with m_j = √w_j μ_d(f_j) (Eq. 6–7 and §4.2, f_j = α_1 +
    (α_0 − α_1) cos θ_i cos θ_r), x_j = √w_j max(0, n·l_j), k = s_xy/s_xx; the normal
    n = (n_0 + u t_1 + w t_2)/|·| (P = 4). Derivatives through k and s_yy included (the
    residual's variable projection); clamps and clips contribute zero derivative where active.

    Each Jacobian column is a combination of eight per-sample vectors with per-function
    coefficients: ``J_a = ι D_a − ι k W_a + ι'_a m − (ι k'_a + k ι'_a) x`` with ι = 1/√s_yy,
    ``D_a = ∂m/∂p_a``, ``W_a = ∂x/∂p_a`` (0 for the α's), k'_a, ι'_a their derivatives, and
    ``r = ι m − ι k x``. So the pass accumulates the 36 inner products of (m, x, D_0..D_3,
    W_2, W_3) — every one a scalar register sum, no stores, so it vectorises — and JᵀJ = CᵀGC,
    Jᵀr = CᵀG c_r afterwards (C the 8 × P coefficients). The k, ι cancellations are O(1e-16)
    of the sums, far below what moves an LM step. With ``chroma`` the chromaticity rows
    ρ_j = c_j μ_s(f_j) of :func:`_polish_residuals` are added (dρ_j/dp = c_j dμ_s/df df/dp;
    they do not enter k or s_yy) from a second branch-free pass.
    """
    m = lx.size
    P = 4 if nrm else 2
    nx, ny, nz, nvc, dnvc0, dnvc1, d0x, d0y, d0z, d1x, d1y, d1z = _polish_frame(
        p, nrm, normal, t1, t2, v)
    da = p[0] - p[1]
    p1 = p[1]
    thr = -1.0 if not _maybe_singular(p[0], p[1], two_1mds, ds2k, sing_sin2) else sing_sin2
    # the Gram sums of (m, x, D0, D1, D2, D3, W2, W3), in scalar (register) accumulators
    Gmm = Gmx = Gxx = Gm0 = Gm1 = Gm2 = Gm3 = Gx0 = Gx1 = Gx2 = Gx3 = 0.0
    GmW2 = GmW3 = GxW2 = GxW3 = 0.0
    G00 = G01 = G02 = G03 = G11 = G12 = G13 = G22 = G23 = G33 = 0.0
    G0W2 = G0W3 = G1W2 = G1W3 = G2W2 = G2W3 = G3W2 = G3W3 = 0.0
    GW22 = GW23 = GW33 = 0.0
    for j in range(m):
        nlj, xc, dn0, dn1, dx0, dx1 = _polish_geometry(
            j, nx, ny, nz, nvc, dnvc0, dnvc1, d0x, d0y, d0z, d1x, d1y, d1z, lx, ly, lz)
        mu, dmu = _mu_d_df(da * xc + p1, A[j], Rd[j], Rdms[j], two_1mds, ds2k, thr)
        sw = sqw[j]
        mm = mu * sw
        xw = nlj * sw
        dmu *= sw
        e0 = dmu * xc
        e1 = dmu * (1.0 - xc)
        e2 = dmu * da * dx0
        e3 = dmu * da * dx1
        w2 = dn0 * sw
        w3 = dn1 * sw
        Gmm += mm * mm
        Gmx += mm * xw
        Gxx += xw * xw
        Gm0 += mm * e0
        Gm1 += mm * e1
        Gx0 += xw * e0
        Gx1 += xw * e1
        G00 += e0 * e0
        G01 += e0 * e1
        G11 += e1 * e1
        Gm2 += mm * e2
        Gm3 += mm * e3
        Gx2 += xw * e2
        Gx3 += xw * e3
        GmW2 += mm * w2
        GmW3 += mm * w3
        GxW2 += xw * w2
        GxW3 += xw * w3
        G02 += e0 * e2
        G03 += e0 * e3
        G12 += e1 * e2
        G13 += e1 * e3
        G22 += e2 * e2
        G23 += e2 * e3
        G33 += e3 * e3
        G0W2 += e0 * w2
        G0W3 += e0 * w3
        G1W2 += e1 * w2
        G1W3 += e1 * w3
        G2W2 += e2 * w2
        G2W3 += e2 * w3
        G3W2 += e3 * w2
        G3W3 += e3 * w3
        GW22 += w2 * w2
        GW23 += w2 * w3
        GW33 += w3 * w3
    G = np.empty((8, 8))
    vals = (Gmm, Gmx, Gm0, Gm1, Gm2, Gm3, GmW2, GmW3,
            Gxx, Gx0, Gx1, Gx2, Gx3, GxW2, GxW3,
            G00, G01, G02, G03, G0W2, G0W3,
            G11, G12, G13, G1W2, G1W3,
            G22, G23, G2W2, G2W3,
            G33, G3W2, G3W3,
            GW22, GW23,
            GW33)
    q = 0
    for a in range(8):
        for b in range(a, 8):
            G[a, b] = vals[q]
            G[b, a] = vals[q]
            q += 1
    syy, sxy, sxx = Gmm, Gmx, Gxx
    ok = sxx > _TINY and syy > _TINY and sxy > 0.0
    k = sxy / sxx if ok else 0.0
    big = syy > _TINY
    inv = 1.0 / math.sqrt(syy if big else 1.0)
    # C: column a = the coefficients of J_a over the basis; column P: those of r
    C = np.zeros((8, P + 1))
    for a in range(P):
        dsyy = 2.0 * G[0, 2 + a]
        dsxy = G[1, 2 + a] + (G[0, 4 + a] if a >= 2 else 0.0)
        dsxx = 2.0 * G[1, 4 + a] if a >= 2 else 0.0
        dk = (dsxy - k * dsxx) / sxx if ok else 0.0
        di = -0.5 * inv * inv * inv * dsyy if big else 0.0
        C[0, a] = di
        C[1, a] = -(inv * dk + k * di)
        C[2 + a, a] = inv
        if a >= 2:
            C[4 + a, a] = -inv * k
    C[0, P] = inv
    C[1, P] = -inv * k
    GC = _gram_times(G, C, P + 1)
    for a in range(P):
        acc = 0.0
        for u in range(8):
            acc += C[u, a] * GC[u, P]
        g[a] = acc
        for b in range(a, P):
            acc = 0.0
            for u in range(8):
                acc += C[u, a] * GC[u, b]
            JtJ[a, b] = acc
            JtJ[b, a] = acc
    if chroma:
        _polish_jacobian_chroma(p, nrm, normal, t1, t2, v, lx, ly, lz, A, B, cw, JtJ, g)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FMV)
def _polish_jacobian_chroma(p, nrm, normal, t1, t2, v, lx, ly, lz, A, B, cw, JtJ, g):
    """The chromaticity rows' part of :func:`_polish_jacobian`, added into ``JtJ`` and ``g``
    (the rows do not enter k or s_yy); one branch-free pass."""
    m = lx.size
    nx, ny, nz, nvc, dnvc0, dnvc1, d0x, d0y, d0z, d1x, d1y, d1z = _polish_frame(
        p, nrm, normal, t1, t2, v)
    da = p[0] - p[1]
    p1 = p[1]
    cg0 = cg1 = cg2 = cg3 = 0.0
    c00 = c01 = c02 = c03 = c11 = c12 = c13 = c22 = c23 = c33 = 0.0
    for j in range(m):
        nlj, xc, dn0, dn1, dx0, dx1 = _polish_geometry(
            j, nx, ny, nz, nvc, dnvc0, dnvc1, d0x, d0y, d0z, d1x, d1y, d1z, lx, ly, lz)
        ms, dms = _mu_s_df(da * xc + p1, A[j], B[j])
        rc = cw[j] * ms
        dms *= cw[j]
        q0 = dms * xc
        q1 = dms * (1.0 - xc)
        q2 = dms * da * dx0
        q3 = dms * da * dx1
        cg0 += q0 * rc
        cg1 += q1 * rc
        c00 += q0 * q0
        c01 += q0 * q1
        c11 += q1 * q1
        cg2 += q2 * rc
        cg3 += q3 * rc
        c02 += q0 * q2
        c03 += q0 * q3
        c12 += q1 * q2
        c13 += q1 * q3
        c22 += q2 * q2
        c23 += q2 * q3
        c33 += q3 * q3
    g[0] += cg0
    g[1] += cg1
    JtJ[0, 0] += c00
    JtJ[0, 1] += c01
    JtJ[1, 0] += c01
    JtJ[1, 1] += c11
    if nrm:
        g[2] += cg2
        g[3] += cg3
        JtJ[0, 2] += c02
        JtJ[2, 0] += c02
        JtJ[0, 3] += c03
        JtJ[3, 0] += c03
        JtJ[1, 2] += c12
        JtJ[2, 1] += c12
        JtJ[1, 3] += c13
        JtJ[3, 1] += c13
        JtJ[2, 2] += c22
        JtJ[2, 3] += c23
        JtJ[3, 2] += c23
        JtJ[3, 3] += c33


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _gram_times(G, C, K):
    """``G @ C`` for the 8 × 8 Gram matrix and its 8 × K coefficients (no BLAS call)."""
    out = np.zeros((8, K))
    for u in range(8):
        for w in range(8):
            gu = G[u, w]
            for c in range(K):
                out[u, c] += gu * C[w, c]
    return out


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


@njit(cache=True, nogil=True, error_model="numpy")
def _polish_start(JtJ, g, cur, row, P, save):
    """:func:`ramp_polish`'s recorded start: ``save`` writes JᵀJ, Jᵀr and Σ r² (``cur``) into
    ``row`` (``P² + P + 1``), else reads JᵀJ and Jᵀr back and returns the recorded Σ r²."""
    q = 0
    for a in range(P):
        for b in range(P):
            if save:
                row[q] = JtJ[a, b]
            else:
                JtJ[a, b] = row[q]
            q += 1
    for a in range(P):
        if save:
            row[q] = g[a]
        else:
            g[a] = row[q]
        q += 1
    if save:
        row[q] = cur
    return row[q]


@njit(cache=True, nogil=True, error_model="numpy")
def ramp_polish(p0, normal, t1, t2, v, dirs, x_fix, nl_fix, wd, A, Rd, Rdms, ds, iterations,
                sing_sin2, B, cw, chroma, xtol, start, start_mode):
    """Levenberg–Marquardt polish of ``fit_ramp``'s residuals for N functions: the steps of
    ``_skin_fit.gauss_newton_polish`` (same damping, a step kept only where it lowers Σ r²)
    with the analytic Jacobian of :func:`_polish_jacobian` instead of finite differences, and
    JᵀJ, Jᵀr reused after a rejected step (x unchanged); trial points by their Σ r² only
    (:func:`_polish_residuals` with ``rows=False``: ≈ 1/4 of a pass with derivatives, its
    second loop skipped where Σ r² > ``_SUMS_MIN``), derivatives only after an accepted step
    that is not the last. ``p0`` ``(N, 2)`` (ramp at the fixed
    normal) or ``(N, 4)`` (ramp and tangent offsets of the normal). With ``chroma`` the
    chromaticity rows ``cw μ_s`` (``B``, ``cw`` ``(N, L)``) join the residuals.

    A function stops before ``iterations`` once converged: when a proposed step has every
    ``|Δp| ≤ xtol`` and was either rejected (later steps, with the same JᵀJ and more damping,
    are shorter still) or accepted undamped (λ ≤ 1e-6: a Gauss–Newton step). Steps that small
    only move p by rounding (0: every function takes all ``iterations``).

    ``start`` ``(N, P² + P + 1)``: the lobe rows' JᵀJ, Jᵀr and Σ r² at ``p0``. ``start_mode``
    1 records them (a polish without the chromaticity rows), 2 uses them instead of
    recomputing (a polish with the rows from the same ``p0``: only the rows' part is
    computed), 0 neither. The second polish of ``fit_ramp`` restarts from the first one's
    start, so this saves one pass with derivatives per function. Returns ``(p, Σ r²)``."""
    N, P = p0.shape
    L = wd.shape[1]
    nrm = P == 4
    out = p0.copy()
    val = np.empty(N)
    for i in range(N):
        idx = _compact(wd[i], L)
        m = idx.size
        lx = np.empty(m)
        ly = np.empty(m)
        lz = np.empty(m)
        sqw = np.empty(m)
        for q in range(m):
            j = idx[q]
            lx[q] = dirs[j, 0]
            ly[q] = dirs[j, 1]
            lz[q] = dirs[j, 2]
            sqw[q] = math.sqrt(wd[i, j])
        As = _take_row(A, i, idx)
        Rds = _take_row(Rd, i, idx)
        Rms = _take_row(Rdms, i, idx)
        xs = _take_row(x_fix, i, idx)
        nls = _take_row(nl_fix, i, idx)
        Bs = _take_row(B, i, idx)
        cws = _take_row(cw, i, idx)
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
        # JtJ, g are those of the current x (kept across rejected steps)
        if start_mode == 2:
            # the lobe rows' part at p0 from the earlier polish, plus the chromaticity rows'
            save = start_mode == 1  # False here (a bool variable: one compiled _polish_start)
            cur = _polish_start(JtJ, g, 0.0, start[i], P, save) + _polish_residuals_chroma(
                x, nrm, normal[i], t1[i], t2[i], v[i], lx, ly, lz, As, Bs, cws)
            _polish_jacobian_chroma(x, nrm, normal[i], t1[i], t2[i], v[i], lx, ly, lz, As, Bs,
                                    cws, JtJ, g)
        else:
            cur = _polish_residuals(x, nrm, normal[i], t1[i], t2[i], v[i], lx, ly, lz, sqw, As,
                                    Rds, Rms, two_1mds, ds2k, sing_sin2, r, xs, nls, Bs, cws,
                                    chroma, False)
            _polish_jacobian(x, nrm, normal[i], t1[i], t2[i], v[i], lx, ly, lz, sqw, As, Rds,
                             Rms, two_1mds, ds2k, sing_sin2, xs, nls, JtJ, g, Bs, cws, chroma)
            if start_mode == 1:
                _polish_start(JtJ, g, cur, start[i], P, start_mode == 1)
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
                                   chroma, False)
            if np.isfinite(vn) and vn < cur:
                for a in range(P):
                    x[a] = pt[a]
                cur = vn
                if (tiny and lam <= 1e-6) or it == iterations - 1:
                    break  # an undamped (Gauss–Newton) step below xtol: converged; or the last
                _polish_jacobian(x, nrm, normal[i], t1[i], t2[i], v[i], lx, ly, lz, sqw, As,
                                 Rds, Rms, two_1mds, ds2k, sing_sin2, xs, nls, JtJ, g, Bs, cws,
                                 chroma)
                lam *= 0.1
            else:
                if tiny:
                    break  # rejected below xtol: later steps (more damping, same JᵀJ) are smaller
                lam *= 10.0
        for a in range(P):
            out[i, a] = x[a]
        val[i] = cur
    return out, val
