"""Compiled (numba) kernels of the skin model's resynthesis (Debevec et al. 2000, §4.3, Eq. 9).

Private module behind :mod:`facegeo.appearance._skin_resynth`. One reflectance function per
iteration of a ``prange`` loop (both cores when numba has two threads; :func:`relit_stored_grid`
is serial over a range of functions, run in pieces on Python threads); per function, one loop
over its lights computes what the numpy reference (``_skin_resynth`` with ``KERNELS = False``)
builds as ``(n, L, 3)`` temporaries: the diffuse chroma shift from v_0 to v_n (Eq. 6–7
inverted and re-applied, :func:`_skin_resynth.resynthesize_diffuse`), Eq. 9's specular sample
with G and F (:func:`_skin_resynth.resynthesize_specular`, its interpolation on the light set
included), the same-view guarantee, the skip of negligible specular and the flags. Same
formulas in the same order, so the results agree with the reference to rounding (tested in
``tests/test_skin_model.py``). Work the reference does and no result needs is skipped: the
specular sample's interpolation and G, F are evaluated only for lights that pass Eq. 9's cheap
conditions (lit, n·l_p > 0, n·H > 0, n·l_q > 0), and :func:`resynth_relit` (Eq. 4 on the
resynthesised function) only visits lights whose weight is non-zero.

:func:`resynth_relit_grid` (the default of ``_skin_resynth.resynthesize_relit`` on the
light-stage grid when at least half the lights are visited and no lobe cone is asked for) is
:func:`resynth_relit` reorganised for speed, same samples: per function, the microfacet value
of every node above the horizon up front, then only the lights that can contribute (a zero
diffuse sample with n·l ≤ 0 or an occluded light adds exactly 0: about half the lights),
then one branch-free loop over them with 6 square roots and 5 divisions per light instead
of 8 and 12 (normalisations folded, l_q not renormalised, G·F as one quotient) and the grid
coordinate from a polynomial atan2 instead of libm's atan2 and acos; its sums are
reassociated. It agrees with :func:`resynth_relit` to ≈ 1e-15 relative (tested to 1e-11 in
``tests/test_resynth_fast.py``). Profile of :func:`resynth_relit` per function and light
(one thread, paper-model functions, 2048 lights, CPU time): ≈ 165 ns, of which the
specular sample ≈ 135 (grid coordinate ≈ 15, the interpolation with its node set-up ≈ 45,
the rest H, l_q, G, F: square roots and divisions, which this CPU — AMD EPYC, 128-bit
floating-point units — pays ≈ 5 ns for even when vectorised), the chroma shift ≈ 45
(overlapping). Vectorising the loop over lights (LLVM does, 4 lanes) bought nothing
measurable on that CPU; skipping what adds 0 and removing roots and divisions did.

:func:`relit_stored_grid` runs :func:`resynth_relit_grid`'s per-function code on stored
float16 functions, decoding their bits through a 65,536-entry table (exact) one function at a
time, and gives the measured function's Eq. 4 (the naive value) from the same read
(:func:`relight_stored`: the naive value alone). It serves every light count and, with
block arguments, ``light_step > 1`` (each function's block summaries formed from its decoded
rows by :func:`_block_row`, :func:`block_outputs`'s code); its per-function code is always
the grid kernel's, whose nodes are computed up front — for a map whose energy sits in a few
lights that costs ≈ 20 µs per function, against the scalar kernel's lazy nodes, but the
read it saves costs more.

Kernels are compiled on first use and cached on disk (``cache=True``); the threading layer is
chosen by ``facegeo/__init__.py`` (``NUMBA_THREADING_LAYER_PRIORITY``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from facegeo.appearance._skin_kernels import _FM, _FMV

_S = 1.0 / math.sqrt(3.0)  # a component of S_WHITE
_TWO_PI = 2.0 * math.pi
_THIRD = 1.0 / 3.0


# ------------------------------------------------------------------------------- BRDF factors


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _unit(x, y, z, fx, fy, fz):
    """``_skin_model.normalize`` of one vector: (x, y, z)/|·|, the fallback (fx, fy, fz)
    where the norm is ≤ 1e-30; also returns the norm."""
    r = math.sqrt(x * x + y * y + z * z)
    if r > 1e-30:
        q = 1.0 / r
        return x * q, y * q, z * q, r
    return fx, fy, fz, r


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _fresnel(cos_d, e2):
    """``brdf.fresnel_dielectric`` with ``e2 = η² − 1`` (cos clipped to [0, 1])."""
    c = min(max(cos_d, 0.0), 1.0)
    g = math.sqrt(e2 + c * c)
    a = (g - c) / (g + c)
    b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
    return 0.5 * a * a * (1.0 + b * b)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _geometry(nl, nv, nh, vh):
    """``brdf.torrance_sparrow_geometry``: ``min(1, 2 nh nv / vh, 2 nh nl / vh)`` with the
    cosines clipped at 0; at ``vh <= 0`` the ratios are +inf (0 where their numerator is 0)."""
    nl = max(nl, 0.0)
    nv = max(nv, 0.0)
    nh = max(nh, 0.0)
    if vh > 0.0:
        inv = 1.0 / vh
        return min(1.0, min(2.0 * nh * nv * inv, 2.0 * nh * nl * inv))
    return 1.0 if (nh * nv > 0.0 and nh * nl > 0.0) else 0.0


# ------------------------------------------------------------------------------- interpolation


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _grid_interp(mic, dirs, shadow_i, nt, npf, x, y, z):
    """``_skin_resynth.interpolate_on_lights`` on the light-stage grid at one unit direction:
    bilinear in (θ, φ) grid coordinates of the microfacet values (``mic``, :func:`_node`) and
    of the shadow mask (as 0/1)."""
    theta = math.atan2(x, z)
    if theta < 0.0:
        theta += _TWO_PI
    phi = math.acos(min(max(y, -1.0), 1.0))
    fi = theta * nt / _TWO_PI - 0.5
    fj = phi * npf / math.pi - 0.5
    i0 = math.floor(fi)
    j0 = math.floor(fj)
    fi -= i0
    fj -= j0
    ia = int(i0)  # in [-1, nt - 1] up to rounding: wrap without integer division
    if ia < 0:
        ia += nt
    elif ia >= nt:
        ia -= nt
    ib = ia + 1 if ia + 1 < nt else 0
    j0i = int(j0)
    ja = min(max(j0i, 0), npf - 1)
    jb = min(max(j0i + 1, 0), npf - 1)
    k00, k01 = ja * nt + ia, ja * nt + ib
    k10, k11 = jb * nt + ia, jb * nt + ib
    m = ((1 - fj) * ((1 - fi) * _node(mic, dirs, k00) + fi * _node(mic, dirs, k01))
         + fj * ((1 - fi) * _node(mic, dirs, k10) + fi * _node(mic, dirs, k11)))
    s00 = 1.0 if shadow_i[k00] else 0.0
    s01 = 1.0 if shadow_i[k01] else 0.0
    s10 = 1.0 if shadow_i[k10] else 0.0
    s11 = 1.0 if shadow_i[k11] else 0.0
    sh = ((1 - fj) * ((1 - fi) * s00 + fi * s01) + fj * ((1 - fi) * s10 + fi * s11))
    return m, sh


@njit(cache=True, nogil=True, error_model="numpy")
def _free_interp(mic, shadow_i, dirs, x, y, z):
    """``interpolate_on_lights`` on a free light list: inverse angular-distance weights
    ``1/(1 − cos + 1e-12)`` of the (up to) 3 lights nearest to the direction."""
    L = dirs.shape[0]
    c0 = c1 = c2 = -np.inf
    i0 = i1 = i2 = -1
    for j in range(L):
        c = min(max(x * dirs[j, 0] + y * dirs[j, 1] + z * dirs[j, 2], -1.0), 1.0)
        if c > c0:
            c2, i2 = c1, i1
            c1, i1 = c0, i0
            c0, i0 = c, j
        elif c > c1:
            c2, i2 = c1, i1
            c1, i1 = c, j
        elif c > c2:
            c2, i2 = c, j
    w0 = 1.0 / (1.0 - c0 + 1e-12)
    w1 = 1.0 / (1.0 - c1 + 1e-12) if i1 >= 0 else 0.0
    w2 = 1.0 / (1.0 - c2 + 1e-12) if i2 >= 0 else 0.0
    ws = w0 + w1 + w2
    m = w0 / ws * _node(mic, dirs, i0)
    sh = w0 / ws * (1.0 if shadow_i[i0] else 0.0)
    if i1 >= 0:
        m += w1 / ws * _node(mic, dirs, i1)
        sh += w1 / ws * (1.0 if shadow_i[i1] else 0.0)
    if i2 >= 0:
        m += w2 / ws * _node(mic, dirs, i2)
        sh += w2 / ws * (1.0 if shadow_i[i2] else 0.0)
    return m, sh


# ------------------------------------------------------------------------------- one function


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _prepare(i, D, S, iE, dirs, sa, nrm, v0, eta2m1, skip, micro):
    """Per function: whether its specular part is resynthesised (energy above ``skip`` of the
    total, as ``_skin_resynth.resynthesize``); ``micro[l]`` receives the white-balanced
    specular sample σ_l, which :func:`_node` turns into the microfacet value when Eq. 9 first
    reads node l."""
    L = dirs.shape[0]
    energy = 0.0
    total = 0.0
    for j in range(L):
        s0, s1, s2 = S[i, j, 0] * iE[j, 0], S[i, j, 1] * iE[j, 1], S[i, j, 2] * iE[j, 2]
        sig = (s0 + s1 + s2) * _THIRD
        tot = (abs(D[i, j, 0] * iE[j, 0] + s0) + abs(D[i, j, 1] * iE[j, 1] + s1)
               + abs(D[i, j, 2] * iE[j, 2] + s2)) * _THIRD
        energy += sig * sa[j]
        total += tot * sa[j]
        micro[j] = sig
    return energy > skip * max(total, 1e-300)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _lobe_state(i, nrm, v0, eta2m1, micro, ready):
    """What :func:`_node` needs of function ``i``: its σ samples ``micro`` (overwritten by the
    microfacet values node by node), the flags of the nodes done, n, v_0, n·v_0, max(n·v_0, 0)
    and η² − 1."""
    nx, ny, nz = nrm[i, 0], nrm[i, 1], nrm[i, 2]
    vx, vy, vz = v0[i, 0], v0[i, 1], v0[i, 2]
    nv0 = nx * vx + ny * vy + nz * vz
    return micro, ready, (nx, ny, nz, vx, vy, vz, nv0, max(nv0, 0.0), eta2m1)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _node(mic, dirs, j):
    """The microfacet value on node ``j``, ``σ_j (n·v_0)/(G(v_0, l_j, n) F(v_0·h_j))`` (0 where
    ``G F ≤ 1e-6``) of :func:`_skin_resynth.resynthesize_specular`, computed the first time a
    node is read (Eq. 9 reads only the nodes around the l_q it visits)."""
    micro, ready, st = mic
    if ready[j]:
        return micro[j]
    ready[j] = True
    nx, ny, nz, vx, vy, vz, nv0, nv0p, eta2m1 = st
    lx, ly, lz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
    nl = nx * lx + ny * ly + nz * lz
    if not nl > 0.0 or micro[j] == 0.0:
        micro[j] = 0.0  # G = 0 below the horizon (G F ≤ 1e-6 there), or no sample
        return 0.0
    hx, hy, hz, _ = _unit(lx + vx, ly + vy, lz + vz, nx, ny, nz)
    nh = hx * nx + hy * ny + hz * nz
    vh = hx * vx + hy * vy + hz * vz
    gf = _geometry(nl, nv0, nh, vh) * _fresnel(vh, eta2m1)
    micro[j] = micro[j] * nv0p / gf if gf > 1e-6 else 0.0
    return micro[j]


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _lobe_cone(mic, dirs, tol, delta):
    """The cone of source directions outside which Eq. 9's interpolated lobe is negligible.

    Nodes whose microfacet value ``|micro[l]|`` exceeds ``tol · max|micro|`` (``tol = 0``: every
    non-zero node) lie within angle β of the axis (the node of the largest value); a direction
    l_q farther than β + ``delta`` from the axis (``delta`` ≥ the largest angle between a
    point of a grid cell and the cell's interpolation nodes) interpolates only nodes at or
    below ``tol · max|micro|``. Returns the axis and ``cos(β + delta)`` (−2: no cone, every
    direction inside).
    """
    L = dirs.shape[0]
    micro = mic[0]
    big = 0.0
    k = -1
    for j in range(L):
        a = abs(_node(mic, dirs, j))
        if a > big:
            big = a
            k = j
    if k < 0:
        return 0.0, 0.0, 1.0, 2.0  # no lobe anywhere: every direction outside
    ax, ay, az = dirs[k, 0], dirs[k, 1], dirs[k, 2]
    lim = tol * big
    cmin = 1.0
    for j in range(L):
        if abs(micro[j]) > lim:
            cmin = min(cmin, ax * dirs[j, 0] + ay * dirs[j, 1] + az * dirs[j, 2])
    beta = math.acos(min(max(cmin, -1.0), 1.0)) + delta
    if beta >= math.pi:
        return ax, ay, az, -2.0
    return ax, ay, az, math.cos(beta)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _diffuse(d_r, d_g, d_b, e_r, e_g, e_b, ie_r, ie_g, ie_b, f0, fn):
    """Diffuse sample chroma-shifted from v_0 to v_n (``resynthesize_diffuse``): ``c`` the
    sample's chromaticity, d = Eq. 6 inverted at f0 (``invert_ramp``), Eq. 6 at fn applied,
    brightness |D/E| kept. Returns the new RGB sample in input units."""
    cr, cg, cb, b = _unit(d_r * ie_r, d_g * ie_g, d_b * ie_b, _S, _S, _S)
    cs = cr * _S + cg * _S + cb * _S
    disc = f0 * f0 * cs * cs + 1.0 + 2.0 * f0
    if disc >= 0.0 and abs(1.0 + f0) > 1e-6:
        mu = -f0 * cs + math.sqrt(disc)
        r = 1.0 / (1.0 + f0)
        dr, dg, db, _ = _unit((mu * cr + f0 * _S) * r, (mu * cg + f0 * _S) * r,
                              (mu * cb + f0 * _S) * r, _S, _S, _S)
    else:
        dr, dg, db = cr, cg, cb
    qr = dr + fn * (dr - _S)
    qg = dg + fn * (dg - _S)
    qb = db + fn * (db - _S)
    r = math.sqrt(qr * qr + qg * qg + qb * qb)
    if r > 1e-30:
        r = b / r  # normalised, times the brightness
        return qr * r * e_r, qg * r * e_g, qb * r * e_b
    r = b * _S
    return r * e_r, r * e_g, r * e_b


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _specular(i, j, nrm, v0, vn, lp_dirs, lp_cast, dirs, cast, mic, grid, nt, npf, eta2m1, nvn,
              inv_nvn, cone):
    """Eq. 9's white-balanced specular sample for light ``j`` (``resynthesize_specular``) and
    whether it came from a shadowed source direction (lit l_p, l_q in shadow). Zero where l_p
    is occluded or below the horizon, H is undefined, n·H ≤ 0 or l_q is below the horizon;
    the caller has checked n·v_0 > 0 and n·v_n > 0 and passes n·v_n and
    ``1/max(n·v_n, COS_FLOOR)``. ``cone`` (:func:`_lobe_cone`): an l_q outside it gives 0
    (and False) without the interpolation, G and F. l_p is ``lp_dirs[j]``, occluded where
    ``lp_cast[i, j]``; the measured lobe (``mic``, :func:`_node`; ``cast[i]``) lives on
    ``dirs``."""
    if lp_cast[i, j]:
        return 0.0, False
    nx, ny, nz = nrm[i, 0], nrm[i, 1], nrm[i, 2]
    lx, ly, lz = lp_dirs[j, 0], lp_dirs[j, 1], lp_dirs[j, 2]
    nlp = nx * lx + ny * ly + nz * lz
    if not nlp > 0.0:
        return 0.0, False
    ux, uy, uz = vn[i, 0], vn[i, 1], vn[i, 2]
    hx, hy, hz = ux + lx, uy + ly, uz + lz
    hn = math.sqrt(hx * hx + hy * hy + hz * hz)
    if not hn > 1e-9:
        return 0.0, False
    r = 1.0 / hn
    hx, hy, hz = hx * r, hy * r, hz * r
    nH = hx * nx + hy * ny + hz * nz
    if not nH > 0.0:
        return 0.0, False
    vx, vy, vz = v0[i, 0], v0[i, 1], v0[i, 2]
    hv0 = hx * vx + hy * vy + hz * vz
    qx, qy, qz, _ = _unit(2.0 * hv0 * hx - vx, 2.0 * hv0 * hy - vy, 2.0 * hv0 * hz - vz,
                          nx, ny, nz)
    nlq = qx * nx + qy * ny + qz * nz
    if not nlq > 0.0:
        return 0.0, False
    if qx * cone[0] + qy * cone[1] + qz * cone[2] < cone[3]:
        return 0.0, False
    if grid:
        m_q, sh_q = _grid_interp(mic, dirs, cast[i], nt, npf, qx, qy, qz)
    else:
        m_q, sh_q = _free_interp(mic, cast[i], dirs, qx, qy, qz)
    if m_q == 0.0:  # no lobe at l_q (G and F are finite, so the sample is 0)
        return 0.0, sh_q > 0.5
    vnH = hx * ux + hy * uy + hz * uz
    g = _geometry(nlp, nvn, nH, vnH)
    f = _fresnel(vnH, eta2m1)
    return max(m_q * g * f * inv_nvn, 0.0), sh_q > 0.5


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _ramp_f(nl, nv, a0, a1):
    """Eq. 7: ``α_0 x + α_1 (1 − x)``, ``x = clip(n·l) clip(n·v)`` (``_skin_model.ramp_f``)."""
    x = min(max(nl, 0.0), 1.0) * min(max(nv, 0.0), 1.0)
    return a0 * x + a1 * (1.0 - x)


# ------------------------------------------------------------------------------- kernels


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _view_cosines(i, nrm, v0, vn, do_spec):
    """n·v_0, n·v_n, whether Eq. 9 can give a lobe at all (specular kept, both views above
    the horizon) and ``1/max(n·v_n, COS_FLOOR)``."""
    nx, ny, nz = nrm[i, 0], nrm[i, 1], nrm[i, 2]
    nv0 = nx * v0[i, 0] + ny * v0[i, 1] + nz * v0[i, 2]
    nvn = nx * vn[i, 0] + ny * vn[i, 1] + nz * vn[i, 2]
    return nv0, nvn, do_spec and nv0 > 0.0 and nvn > 0.0, 1.0 / max(nvn, 1e-4)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _sample(i, j, D, E, iE, dirs, cast, nrm, v0, vn, a0, a1, mic, nv0, nvn, lobe, inv_nvn,
            grid, nt, npf, e2, cone, src_dirs, src_cast):
    """Output light ``j`` of function ``i`` resynthesised: the diffuse RGB sample (input units),
    the white-balanced Eq. 9 specular sample and whether it came from a shadowed source
    direction. ``D, E, iE, dirs, cast`` describe the output lights; the measured lobe
    (``mic``, ``src_cast[i]``) lives on ``src_dirs`` (the same arrays when the output
    lights are the measured ones)."""
    d_r, d_g, d_b = D[i, j, 0], D[i, j, 1], D[i, j, 2]
    if d_r == 0.0 and d_g == 0.0 and d_b == 0.0:
        dr = dg = db = 0.0  # what _diffuse gives for a zero sample (brightness 0), exactly
    else:
        nl = nrm[i, 0] * dirs[j, 0] + nrm[i, 1] * dirs[j, 1] + nrm[i, 2] * dirs[j, 2]
        f0 = _ramp_f(nl, nv0, a0[i], a1[i])
        fn = _ramp_f(nl, nvn, a0[i], a1[i])
        dr, dg, db = _diffuse(d_r, d_g, d_b, E[j, 0], E[j, 1], E[j, 2],
                              iE[j, 0], iE[j, 1], iE[j, 2], f0, fn)
    if lobe:
        sw, hid = _specular(i, j, nrm, v0, vn, dirs, cast, src_dirs, src_cast, mic, grid, nt,
                            npf, e2, nvn, inv_nvn, cone)
        return dr, dg, db, sw, hid
    return dr, dg, db, 0.0, False


@njit(cache=True, nogil=True, error_model="numpy", parallel=True, fastmath=_FM)
def resynth_full(D, S, E, dirs, sa, cast, nrm, v0, vn, a0, a1, same, back, grid,
                 nt, npf, eta, skip, flag_skipped, flag_in_shadow):
    """``_skin_resynth.resynthesize`` for 3-channel functions, fused per function.

    Parameters
    ----------
    D, S : (N, L, 3) float32 or float64 — the fit's diffuse and specular components
    E : (L, 3) float64 light intensities; dirs : (L, 3) unit; sa : (L,) δA, steradians
    cast : (N, L) bool — occluded lights (``SkinFit.cast_shadow``)
    nrm, v0, vn : (N, 3) float64, unit; a0, a1 : (N,) float64, Eq. 7
    same, back : (N,) bool — v_n = v_0 (function returned unchanged); n·v_n ≤ 0 (zeroed)
    grid : bool, with (nt, npf) the light-stage grid; eta : float; skip : specular_skip

    Returns
    -------
    refl, diff, spec : (N, L, 3) float32 — D + S, D, S (sums in float64, as the reference)
    flags : (N,) int32 — ``flag_skipped`` / ``flag_in_shadow`` bits set here
    """
    N, L, _ = D.shape
    refl = np.empty((N, L, 3), np.float32)
    diff = np.empty((N, L, 3), np.float32)
    spec = np.empty((N, L, 3), np.float32)
    flags = np.zeros(N, np.int32)
    e2 = eta * eta - 1.0
    iE = 1.0 / E
    no_cone = (0.0, 0.0, 1.0, -2.0)  # the full functions keep every sample and flag
    for i in prange(N):
        if same[i] or back[i]:
            for j in range(L):
                for c in range(3):
                    d = 0.0 if back[i] else np.float64(D[i, j, c])
                    s = 0.0 if back[i] else np.float64(S[i, j, c])
                    refl[i, j, c] = d + s
                    diff[i, j, c] = d
                    spec[i, j, c] = s
            if same[i]:
                continue
        micro = np.empty(L)
        do_spec = _prepare(i, D, S, iE, dirs, sa, nrm, v0, e2, skip, micro)
        mic = _lobe_state(i, nrm, v0, e2, micro, np.zeros(L, np.bool_))
        if not do_spec:
            flags[i] |= flag_skipped
        if back[i]:
            continue
        nv0, nvn, lobe, inv_nvn = _view_cosines(i, nrm, v0, vn, do_spec)
        hidden = False
        for j in range(L):
            dr, dg, db, sw, hid = _sample(i, j, D, E, iE, dirs, cast, nrm, v0, vn, a0, a1, mic,
                                          nv0, nvn, lobe, inv_nvn, grid, nt, npf, e2, no_cone,
                                          dirs, cast)
            hidden |= hid
            sr, sg, sb = sw * E[j, 0], sw * E[j, 1], sw * E[j, 2]
            diff[i, j, 0], diff[i, j, 1], diff[i, j, 2] = dr, dg, db
            spec[i, j, 0], spec[i, j, 1], spec[i, j, 2] = sr, sg, sb
            refl[i, j, 0], refl[i, j, 1], refl[i, j, 2] = dr + sr, dg + sg, db + sb
        if hidden:
            flags[i] |= flag_in_shadow
    return refl, diff, spec, flags


@njit(cache=True, nogil=True, error_model="numpy", parallel=True, fastmath=_FM)
def resynth_relit(D, S, E, dirs, sa, cast, nrm, v0, vn, a0, a1, same, back, grid,
                  nt, npf, eta, skip, Dq, Eq, dq, castq, active, w, lobe_tol, delta):
    """Eq. 4 on the resynthesised functions without building them: per function
    ``Σ_k w[k] ⊙ R_new(l = output light active[k])``.

    Parameters as :func:`resynth_full` for the measured functions (the lobe Eq. 9
    interpolates lives on ``dirs``), plus the output lights where the new function is
    evaluated: ``Dq`` (N, Q, 3) their diffuse samples, ``Eq`` (Q, 3) intensities, ``dq``
    (Q, 3) unit directions, ``castq`` (N, Q) bool occlusion — the measured arrays themselves
    (``D, E, dirs, cast``) for the exact relighting, or per-block summaries
    (:func:`block_outputs`); ``active`` (A,) int64 the output lights visited and ``w`` (A, 3)
    float64 their weights (δA included); ``lobe_tol`` and ``delta`` of :func:`_lobe_cone`
    (``lobe_tol < 0``: no cone; ``lobe_tol = 0`` skips only samples that are exactly 0).

    Returns (N, 3) float64: 0 for back-facing functions and for ``same`` (the caller relights
    the measured function there). The new samples are summed in float64 (the reference
    rounds them to float32 first).
    """
    N = D.shape[0]
    L = dirs.shape[0]
    A = active.size
    out = np.zeros((N, 3))
    e2 = eta * eta - 1.0
    iE = 1.0 / E
    iEq = 1.0 / Eq
    for i in prange(N):
        if back[i] or same[i]:
            continue
        micro = np.empty(L)
        do_spec = _prepare(i, D, S, iE, dirs, sa, nrm, v0, e2, skip, micro)
        mic = _lobe_state(i, nrm, v0, e2, micro, np.zeros(L, np.bool_))
        nv0, nvn, lobe, inv_nvn = _view_cosines(i, nrm, v0, vn, do_spec)
        cone = (0.0, 0.0, 1.0, -2.0)
        if lobe and lobe_tol >= 0.0:
            cone = _lobe_cone(mic, dirs, lobe_tol, delta)
        acc_r = acc_g = acc_b = 0.0
        for k in range(A):
            j = active[k]
            dr, dg, db, sw, _ = _sample(i, j, Dq, Eq, iEq, dq, castq, nrm, v0, vn, a0, a1, mic,
                                        nv0, nvn, lobe, inv_nvn, grid, nt, npf, e2, cone,
                                        dirs, cast)
            acc_r += w[k, 0] * (dr + sw * Eq[j, 0])
            acc_g += w[k, 1] * (dg + sw * Eq[j, 1])
            acc_b += w[k, 2] * (db + sw * Eq[j, 2])
        out[i, 0], out[i, 1], out[i, 2] = acc_r, acc_g, acc_b
    return out


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _block_row(D, di, cast, ci, members, starts, share, Dq, castq, qi):
    """One function's block summaries (:func:`block_outputs`): ``Dq[qi, b]`` and
    ``castq[qi, b]`` from its diffuse samples ``D[di]`` and occlusion ``cast[ci]``."""
    for b in range(starts.size - 1):
        r = g = bl = c = 0.0
        for m in range(starts[b], starts[b + 1]):
            l = members[m]
            s = share[m]
            r += s * D[di, l, 0]
            g += s * D[di, l, 1]
            bl += s * D[di, l, 2]
            if cast[ci, l]:
                c += s
        Dq[qi, b, 0], Dq[qi, b, 1], Dq[qi, b, 2] = r, g, bl
        castq[qi, b] = c > 0.5


@njit(cache=True, nogil=True, error_model="numpy", parallel=True, fastmath=_FM)
def block_outputs(D, cast, members, starts, share):
    """Per function, the diffuse samples and occlusion of output lights that summarise blocks
    of measured lights: ``Dq[i, b] = Σ_m share[m] D[i, members[m]]`` over the block's members
    ``starts[b] ≤ m < starts[b + 1]`` (shares summing to 1 per block) and ``castq[i, b]`` the
    majority (share > 1/2) of the members' occlusion.

    Returns ``Dq`` (N, B, 3) float32 and ``castq`` (N, B) bool.
    """
    N = D.shape[0]
    B = starts.size - 1
    Dq = np.empty((N, B, 3), np.float32)
    castq = np.empty((N, B), np.bool_)
    for i in prange(N):
        _block_row(D, i, cast, i, members, starts, share, Dq, castq, i)
    return Dq, castq


# ------------------------------------------------------------------------------- vector path
#
# resynth_relit_grid: the same samples as resynth_relit (light-stage grid, no lobe cone), see
# the module docstring: nodes up front, the contributing lights compacted per function, one
# branch-free loop over them (LLVM vectorises it) with fewer roots and divisions and a
# polynomial atan2 (≤ 3e-14 rad, :data:`ATAN_POLY`) in place of libm's atan2 and acos.

#: atan(a)/a as a polynomial in s = a², a ∈ [−tan(π/8), tan(π/8)] (least squares on 20,001
#: points; max |error| of a·P(a²) − atan(a) is 2.7e-14 rad on that interval).
ATAN_POLY = (0.9999999999999303, -0.3333333332964721, 0.19999999521855671,
             -0.14285687895258758, 0.11110346677508263, -0.090780911271976,
             0.07562585539285928, -0.05873342587643475, 0.03068131517163226)
_TAN_PI_8 = math.tan(math.pi / 8.0)
_PI_4 = math.pi / 4.0
_PI_2 = math.pi / 2.0


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _atan_poly(t):
    """atan(t) for t ∈ [−tan(π/8), tan(π/8)] (:data:`ATAN_POLY`, Horner in t²)."""
    s = t * t
    p = ATAN_POLY[8]
    p = p * s + ATAN_POLY[7]
    p = p * s + ATAN_POLY[6]
    p = p * s + ATAN_POLY[5]
    p = p * s + ATAN_POLY[4]
    p = p * s + ATAN_POLY[3]
    p = p * s + ATAN_POLY[2]
    p = p * s + ATAN_POLY[1]
    p = p * s + ATAN_POLY[0]
    return t * p


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _octant(r, swap, neg_x, neg_y):
    """atan2 from the first-octant angle ``r`` = atan(min/max): undo the swap of the
    arguments and the signs."""
    r = _PI_2 - r if swap else r
    r = math.pi - r if neg_x else r
    return -r if neg_y else r


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def grid_angles(x, y, z):
    """(θ, φ) of a unit direction as ``_grid_interp`` defines them, θ = atan2(x, z) ∈ [0, 2π)
    and φ = acos(y) ∈ [0, π] (here atan2(√(x² + z²), y): the same angle, better conditioned
    at the poles), without libm calls and with two divisions for both: each atan2 reduced
    to a = min/max ∈ [0, 1] (one shared reciprocal), a > tan(π/8) to (a − 1)/(a + 1) with
    π/4 added (another shared reciprocal), then :data:`ATAN_POLY`. Absolute error ≤ 1e-13
    rad. Branch-free (selects only), so the loop around it vectorises."""
    ax = abs(x)
    az = abs(z)
    rho = math.sqrt(x * x + z * z)
    ay = abs(y)
    m1 = max(max(ax, az), 1e-150)
    n1 = min(ax, az)
    m2 = max(max(rho, ay), 1e-150)
    n2 = min(rho, ay)
    inv = 1.0 / (m1 * m2)
    a1 = n1 * m2 * inv
    a2 = n2 * m1 * inv
    hi1 = a1 > _TAN_PI_8
    hi2 = a2 > _TAN_PI_8
    inv2 = 1.0 / ((a1 + 1.0) * (a2 + 1.0))
    t1 = (a1 - 1.0) * (a2 + 1.0) * inv2 if hi1 else a1
    t2 = (a2 - 1.0) * (a1 + 1.0) * inv2 if hi2 else a2
    r1 = _atan_poly(t1) + (_PI_4 if hi1 else 0.0)
    r2 = _atan_poly(t2) + (_PI_4 if hi2 else 0.0)
    theta = _octant(r1, ax > az, z < 0.0, x < 0.0)
    theta = theta + _TWO_PI if theta < 0.0 else theta
    phi = _octant(r2, rho > ay, y < 0.0, False)
    return theta, phi


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _gf_ratio(nl, nv, nh, vh, e2):
    """G·F (:func:`_geometry` × :func:`_fresnel`) as ``num/den`` without dividing (the
    caller folds the one division into its own): F = ½ (g−c)²(M² + N²)/((g+c)² M²) with
    g = √(η²−1+c²), M = c(g−c) + 1, N = c(g+c) − 1 (the two quotients of the Fresnel
    formula over one denominator) and G = min(vh, 2 nh min(nv, nl))/vh for vh > 0 (vh is
    floored at 1e-200 there so that ``den`` never underflows to 0)."""
    nl = max(nl, 0.0)
    nv = max(nv, 0.0)
    nh = max(nh, 0.0)
    c = min(max(vh, 0.0), 1.0)
    g = math.sqrt(e2 + c * c)
    gp = g + c
    gm = g - c
    M = c * gm + 1.0
    Nn = c * gp - 1.0
    pos = vh > 0.0
    v = max(vh, 1e-200)
    g_num = min(v, 2.0 * nh * min(nv, nl)) if pos else \
        (1.0 if (nh * nv > 0.0 and nh * nl > 0.0) else 0.0)
    num = 0.5 * gm * gm * (M * M + Nn * Nn) * g_num
    den = gp * gp * M * M * (v if pos else 1.0)
    return num, den


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM, inline="always")
def _diffuse_lean(d_r, d_g, d_b, e_r, e_g, e_b, ie_r, ie_g, ie_b, f0, fn):
    """:func:`_diffuse` with two square roots and two divisions fewer (branch-free): the
    normalisations before a second normalisation are dropped (only the direction survives:
    1/(1 + f0) becomes its sign, d = u/|u| is folded into the final normalisation)."""
    wr, wg, wb = d_r * ie_r, d_g * ie_g, d_b * ie_b
    b = math.sqrt(wr * wr + wg * wg + wb * wb)
    nzb = b > 1e-30
    ib = 1.0 / (b if nzb else 1.0)
    cr = wr * ib if nzb else _S
    cg = wg * ib if nzb else _S
    cb = wb * ib if nzb else _S
    cs = cr * _S + cg * _S + cb * _S
    disc = f0 * f0 * cs * cs + 1.0 + 2.0 * f0
    opf = 1.0 + f0
    inv_ok = disc >= 0.0 and abs(opf) > 1e-6
    mu = -f0 * cs + math.sqrt(max(disc, 0.0))
    sg = 1.0 if opf > 0.0 else -1.0
    ur = sg * (mu * cr + f0 * _S)
    ug = sg * (mu * cg + f0 * _S)
    ub = sg * (mu * cb + f0 * _S)
    un = math.sqrt(ur * ur + ug * ug + ub * ub)
    deg = not un > 1e-30 * abs(opf)  # _unit's fallback: d = S
    ur = cr if not inv_ok else (_S if deg else ur)
    ug = cg if not inv_ok else (_S if deg else ug)
    ub = cb if not inv_ok else (_S if deg else ub)
    un = 1.0 if (not inv_ok or deg) else un
    qr = (1.0 + fn) * ur - fn * un * _S
    qg = (1.0 + fn) * ug - fn * un * _S
    qb = (1.0 + fn) * ub - fn * un * _S
    qn = math.sqrt(qr * qr + qg * qg + qb * qb)
    big = qn > 1e-30 * un
    r = b / (qn if big else 1.0)
    return ((qr * r if big else b * _S) * e_r, (qg * r if big else b * _S) * e_g,
            (qb * r if big else b * _S) * e_b)


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FM)
def _micro_nodes(i, nrm, v0, dirs, eta2m1, micro):
    """Every node's microfacet value (:func:`_node`, all at once): ``micro``
    holds σ_l on entry and ``σ_l (n·v_0)⁺/(G F)`` (0 where n·l ≤ 0, σ_l = 0 or G F ≤ 1e-6)
    on return."""
    nx, ny, nz = nrm[i, 0], nrm[i, 1], nrm[i, 2]
    vx, vy, vz = v0[i, 0], v0[i, 1], v0[i, 2]
    nv0 = nx * vx + ny * vy + nz * vz
    nv0p = max(nv0, 0.0)
    for j in range(dirs.shape[0]):
        lx, ly, lz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
        nl = nx * lx + ny * ly + nz * lz
        m = micro[j]
        if not (nl > 0.0 and m != 0.0):  # below the horizon (about half the nodes): 0
            micro[j] = 0.0
            continue
        hx, hy, hz, _ = _unit(lx + vx, ly + vy, lz + vz, nx, ny, nz)
        nh = hx * nx + hy * ny + hz * nz
        vh = hx * vx + hy * vy + hz * vz
        num, den = _gf_ratio(nl, nv0, nh, vh, eta2m1)
        good = num > 1e-6 * den
        micro[j] = m * nv0p * den / (num if good else 1.0) if good else 0.0


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FMV)
def _relit_lights(nx, ny, nz, vx, vy, vz, ux, uy, uz, al0, al1, nv0, nvn, lobe, inv_nvn, e2, nt,
                  npf, micro, dk, lit, lA, eA, ieA, w):
    """The loop over output lights of :func:`resynth_relit_grid` for one function (n, v_0,
    v_n, α_0, α_1 and the cosines of :func:`_view_cosines`): Eq. 4's sums of the resynthesised
    samples. Only loads and three sums (no stores, no early exits), so LLVM vectorises it;
    per light 6 square roots and 5 divisions (:func:`_diffuse_lean`, :func:`grid_angles`,
    :func:`_gf_ratio`; l_q = 2(H·v_0)H − v_0 is unit without renormalising)."""
    scale_t = nt / _TWO_PI
    scale_p = npf / math.pi
    A = lit.size
    acc_r = acc_g = acc_b = 0.0
    for k in range(A):
        lx, ly, lz = lA[k, 0], lA[k, 1], lA[k, 2]
        nl = nx * lx + ny * ly + nz * lz
        f0 = _ramp_f(nl, nv0, al0, al1)
        fn = _ramp_f(nl, nvn, al0, al1)
        dr, dg, db = _diffuse_lean(dk[k, 0], dk[k, 1], dk[k, 2], eA[k, 0], eA[k, 1], eA[k, 2],
                                   ieA[k, 0], ieA[k, 1], ieA[k, 2], f0, fn)
        # Eq. 9 (as _specular, every condition a select)
        hx, hy, hz = ux + lx, uy + ly, uz + lz
        hn = math.sqrt(hx * hx + hy * hy + hz * hz)
        r = 1.0 / max(hn, 1e-300)
        hx, hy, hz = hx * r, hy * r, hz * r
        nH = hx * nx + hy * ny + hz * nz
        hv0 = 2.0 * (hx * vx + hy * vy + hz * vz)
        qx, qy, qz = hv0 * hx - vx, hv0 * hy - vy, hv0 * hz - vz
        nlq = qx * nx + qy * ny + qz * nz
        ok = lobe and lit[k] > 0.5 and nl > 0.0 and hn > 1e-9 and nH > 0.0 and nlq > 0.0
        qx = qx if ok else nx  # a finite direction where the sample is unused
        qy = qy if ok else ny
        qz = qz if ok else nz
        theta, phi = grid_angles(qx, qy, qz)
        fi = theta * scale_t - 0.5
        fj = phi * scale_p - 0.5
        i0 = math.floor(fi)
        j0 = math.floor(fj)
        fi -= i0
        fj -= j0
        ia = int(i0)
        ia = ia + nt if ia < 0 else ia
        ia = ia - nt if ia >= nt else ia
        ib = ia + 1 if ia + 1 < nt else 0
        j0i = int(j0)
        ja = min(max(j0i, 0), npf - 1)
        jb = min(max(j0i + 1, 0), npf - 1)
        m = ((1 - fj) * ((1 - fi) * micro[ja * nt + ia] + fi * micro[ja * nt + ib])
             + fj * ((1 - fi) * micro[jb * nt + ia] + fi * micro[jb * nt + ib]))
        vnH = hx * ux + hy * uy + hz * uz
        num, den = _gf_ratio(nl, nvn, nH, vnH, e2)
        sw = max(m * num * inv_nvn / den, 0.0) if ok else 0.0
        acc_r += w[k, 0] * (dr + sw * eA[k, 0])
        acc_g += w[k, 1] * (dg + sw * eA[k, 1])
        acc_b += w[k, 2] * (db + sw * eA[k, 2])
    return acc_r, acc_g, acc_b


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FMV)
def _active_constants(active, dq, Eq):
    """The output lights' directions, intensities and reciprocal intensities, contiguous in
    visiting order (``active``)."""
    A = active.size
    lA = np.empty((A, 3))
    eA = np.empty((A, 3))
    ieA = np.empty((A, 3))
    for k in range(A):
        j = active[k]
        for c in range(3):
            lA[k, c] = dq[j, c]
            eA[k, c] = Eq[j, c]
            ieA[k, c] = 1.0 / Eq[j, c]
    return lA, eA, ieA


@njit(cache=True, nogil=True, error_model="numpy", parallel=True, fastmath=_FMV)
def resynth_relit_grid(D, S, E, dirs, sa, cast, nrm, v0, vn, a0, a1, same, back, nt, npf, eta,
                       skip, Dq, Eq, dq, castq, active, w):
    """:func:`resynth_relit` on the light-stage grid without the lobe cone, vectorised over
    lights (see the section comment); same parameters minus ``grid``, ``lobe_tol`` and
    ``delta``. Returns (N, 3) float64 (0 for back-facing and ``same`` functions)."""
    N = D.shape[0]
    out = np.zeros((N, 3))
    e2 = eta * eta - 1.0
    iE = 1.0 / E
    lA, eA, ieA = _active_constants(active, dq, Eq)
    for i in prange(N):
        if back[i] or same[i]:
            continue
        out[i, 0], out[i, 1], out[i, 2] = _grid_one(i, i, D, S, iE, dirs, sa, cast, nrm, v0, vn,
                                                     a0, a1, nt, npf, e2, skip, Dq, castq, i,
                                                     active, lA, eA, ieA, w)
    return out


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FMV)
def _grid_one(i, di, D, S, iE, dirs, sa, cast, nrm, v0, vn, a0, a1, nt, npf, e2, skip, Dq,
              castq, qi, active, lA, eA, ieA, w):
    """Eq. 4 on function ``i`` resynthesised (:func:`resynth_relit_grid`'s body): its samples
    are ``D[di]``, ``S[di]`` and ``Dq[di]`` (``di = i`` for whole arrays, 0 for one function's
    decoded scratch rows), the output lights' occlusion ``castq[qi]``, the rest of its data
    at row ``i``. Returns the three sums."""
    L = dirs.shape[0]
    A = active.size
    micro = np.empty(L)
    do_spec = _prepare(di, D, S, iE, dirs, sa, nrm, v0, e2, skip, micro)
    nv0, nvn, lobe, inv_nvn = _view_cosines(i, nrm, v0, vn, do_spec)
    if lobe:
        _micro_nodes(i, nrm, v0, dirs, e2, micro)
    # the lights that can contribute, compacted: a zero diffuse sample with no possible
    # specular sample (n·l ≤ 0, l occluded, no lobe) adds exactly 0 — about half the
    # lights of a function lie below its horizon
    nx, ny, nz = nrm[i, 0], nrm[i, 1], nrm[i, 2]
    dk = np.empty((A, 3))
    lit = np.empty(A)
    lk = np.empty((A, 3))
    ek = np.empty((A, 3))
    iek = np.empty((A, 3))
    wk = np.empty((A, 3))
    m = 0
    for k in range(A):
        j = active[k]
        d0, d1, d2 = Dq[di, j, 0], Dq[di, j, 1], Dq[di, j, 2]
        shadowed = castq[qi, j]
        spec = lobe and not shadowed and nx * lA[k, 0] + ny * lA[k, 1] + nz * lA[k, 2] > 0.0
        if not (spec or d0 != 0.0 or d1 != 0.0 or d2 != 0.0):
            continue
        dk[m, 0], dk[m, 1], dk[m, 2] = d0, d1, d2
        lit[m] = 0.0 if shadowed else 1.0
        for c in range(3):
            lk[m, c] = lA[k, c]
            ek[m, c] = eA[k, c]
            iek[m, c] = ieA[k, c]
            wk[m, c] = w[k, c]
        m += 1
    return _relit_lights(
        nx, ny, nz, v0[i, 0], v0[i, 1], v0[i, 2], vn[i, 0], vn[i, 1], vn[i, 2], a0[i], a1[i],
        nv0, nvn, lobe, inv_nvn, e2, nt, npf, micro, dk[:m], lit[:m], lk[:m], ek[:m],
        iek[:m], wk[:m])


# ------------------------------------------------------------------------------- stored functions
#
# relit_stored_grid: the render's read of a chunk of stored functions and their resynthesis in
# one pass. The field R and the diffuse component D are stored as float16 (numba has no
# float16 type): the kernel reads their raw bits (uint16) and decodes them through a table of
# the 65,536 float32 values numpy's ``astype(np.float32)`` gives (exact: subnormals, ±inf and
# NaN payloads included), one function's rows at a time into scratch rows that stay in cache.


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FMV)
def _naive_row(Rb, r, half, Rf, active, w):
    """Row ``r`` of the float16 bits ``Rb`` decoded into ``Rf[0]`` (float32, exact) and Eq. 4
    of it, ``Σ_k w_k ⊙ R_{active[k]}`` (float64 sums of the float32 samples times the float64
    weights, in light order); NaN sums and False where any sample, at any light, is not
    finite (as ``R.reshape(n, 3L) @ W`` gives). Returns the three sums and that flag."""
    L = Rf.shape[1]
    bad = 0
    for j in range(L):
        for c in range(3):
            x = half[Rb[r, j, c]]
            Rf[0, j, c] = x
            bad += 0 if math.isfinite(x) else 1
    if bad:
        return np.nan, np.nan, np.nan, False
    s0 = s1 = s2 = 0.0
    for k in range(active.size):
        j = active[k]
        s0 += w[k, 0] * Rf[0, j, 0]
        s1 += w[k, 1] * Rf[0, j, 1]
        s2 += w[k, 2] * Rf[0, j, 2]
    return s0, s1, s2, True


@njit(cache=True, nogil=True, error_model="numpy", parallel=True, fastmath=_FMV)
def relight_stored(Rb, rrows, half, active, w):
    """Eq. 4 of stored measured functions from their float16 bits (:func:`_naive_row` per
    row ``rrows[i]`` of ``Rb``): ``(N, 3)`` float64 (NaN rows where a sample is not finite)
    and ``(N,)`` bool, the rows that are finite."""
    N = rrows.size
    L = Rb.shape[1]
    naive = np.empty((N, 3))
    finite = np.empty(N, np.bool_)
    for i in prange(N):
        Rf = np.empty((1, L, 3), np.float32)
        s0, s1, s2, ok = _naive_row(Rb, rrows[i], half, Rf, active, w)
        naive[i, 0], naive[i, 1], naive[i, 2] = s0, s1, s2
        finite[i] = ok
    return naive, finite


@njit(cache=True, nogil=True, error_model="numpy", fastmath=_FMV)
def relit_stored_grid(lo, hi, Rb, rrows, Db, drows, half, todo, E, dirs, sa, cast, nrm, v0, vn, a0,
                      a1, nt, npf, eta, skip, active, w, members, starts, share, dq, Eq, wq, naive,
                      out, finite):
    """Eq. 4 of stored measured functions (the naive value) and of the same functions
    resynthesised for v_n (:func:`resynth_relit_grid`), from float16 bits, in one pass, for
    functions ``lo ≤ i < hi`` (written into ``naive``, ``out``, ``finite``).

    Serial, without the GIL: ``_skin_resynth.relit_stored`` runs pieces of the range on
    Python threads. A ``parallel=True`` loop compiled its body twice (the loop index is
    int64 when typed, uint64 in the outlined loop) and took ≈ 21 CPU-s to compile cold.

    Parameters
    ----------
    Rb : (T, L, 3) uint16 — the field's float16 bits; function i is row ``rrows[i]``
    Db : (F, L, 3) uint16 — the stored diffuse component's float16 bits; row ``drows[i]``
    half : (65536,) float32 — the value of every float16 bit pattern
    todo : (N,) bool — functions to resynthesise (fitted, n·v_n > 0, not the source view)
    E, dirs, sa : the light set's (L, 3) intensities, (L, 3) directions, (L,) solid angles
    cast, nrm, v0, vn, a0, a1 : per function (row i), as :func:`resynth_relit_grid`
    active : (A,) int64 — the lights with weight; w : (A, 3) float64 their weights (the naive
        value, and the resynthesis' output lights when ``starts`` is empty)
    members, starts, share : ``light_step > 1`` — the output lights' blocks of measured
        lights (:func:`block_outputs`: each function's block diffuse samples and occlusion
        are formed here from its decoded D and its cast shadows); ``starts`` of size 0: the
        output lights are the measured lights ``active``
    dq, Eq, wq : (B, 3) float64 — the blocks' directions, intensities and weights (unused
        when ``starts`` is empty)

    Outputs (rows ``lo:hi`` written)
    --------------------------------
    naive : (N, 3) float64 — ``Σ_l w_l ⊙ R_l`` over ``active`` (NaN where any sample of the
        row, at any light, is not finite, as a matrix product with zero weights gives)
    out : (N, 3) float64, zeros on entry — Eq. 4 of the resynthesised function where ``todo``
        and finite; its samples are exactly :func:`resynth_relit_grid`'s with D = R's
        float32 values decoded, S = R − D rounded to float32 (as ``FitStore.skin_fit`` forms
        them)
    finite : (N,) bool
    """
    L = dirs.shape[0]
    B = starts.size - 1
    blocks = B >= 0
    e2 = eta * eta - 1.0
    iE = 1.0 / E
    if blocks:
        qactive = np.arange(B)
        lA, eA, ieA = _active_constants(qactive, dq, Eq)
        wA = wq
    else:
        qactive = active
        lA, eA, ieA = _active_constants(active, dirs, E)
        wA = w
    Rf = np.empty((1, L, 3), np.float32)
    Df = np.empty((1, L, 3), np.float32)
    Sf = np.empty((1, L, 3), np.float32)
    Dq = np.empty((1, max(B, 0), 3), np.float32)
    cq = np.empty((1, max(B, 0)), np.bool_)
    for i in range(lo, hi):
        r = rrows[i]
        s0, s1, s2, ok = _naive_row(Rb, r, half, Rf, active, w)
        naive[i, 0], naive[i, 1], naive[i, 2] = s0, s1, s2
        finite[i] = ok
        if not ok:
            continue
        if not todo[i]:
            continue
        d = drows[i]
        for j in range(L):
            for c in range(3):
                x = half[Db[d, j, c]]
                Df[0, j, c] = x
                Sf[0, j, c] = Rf[0, j, c] - x  # float32 − float32: rounded as numpy's
        # one call site (one compiled specialisation of _grid_one): the output lights'
        # samples and occlusion are the blocks' or the function's own
        if blocks:
            _block_row(Df, 0, cast, i, members, starts, share, Dq, cq, 0)
            Dout, cout, qi = Dq, cq, 0
        else:
            Dout, cout, qi = Df, cast, i
        out[i, 0], out[i, 1], out[i, 2] = _grid_one(i, 0, Df, Sf, iE, dirs, sa, cast, nrm, v0,
                                                    vn, a0, a1, nt, npf, e2, skip, Dout, cout,
                                                    qi, qactive, lA, eA, ieA, wA)
