"""Compiled (numba) kernels of the reference renderer's per-light shading.

Private to :mod:`facegeo.synth.render`: imported on the first render, so ``import facegeo``
does not pay for numba. :meth:`~facegeo.synth.render.ReferenceRenderer.render_lights` shades
every sample of a view once per light (512 lights × 9 rays per pixel for a view's reference);
the numpy formulation (:meth:`~facegeo.synth.render.ReferenceRenderer._shade` with
:func:`facegeo.appearance.brdf.synthetic_skin_brdf_unchecked`) spent ≈ 60 % of that in 40-odd
array passes per light. These kernels do it in two passes per light and keep what does not
depend on the light (n·v, the view side's specular transmission T(θ_r), the roughness row of
the ρ_dr table) per view.

They compute the generator's skin BRDF — an energy-weighted diffuse colour blend plus
Torrance–Sparrow specular (Beckmann D, Cook–Torrance Fresnel, V-groove G; Debevec et al.
2000 §4's lobe, Donner & Jensen 2006 Eq. (2) for the diffuse transmission) — with the same
IEEE operations in the same order as :mod:`facegeo.appearance.brdf`'s numpy code, including
its float32 promotions (``m²`` and ``log m`` in float32, as numpy computes them on the
view's float32 parameters), and no ``fastmath``. Only ``exp`` and ``log`` come from a
different maths library than numpy's, so a value may differ in its last float64 bit; the
float32 radiance the renderer keeps is then equal but for rare 1-ulp roundings
(``tests/test_synth_shade_kernels.py`` bounds both against the numpy formulation).
"""

from __future__ import annotations

import numpy as np
from numba import njit

_TINY = 1e-300  # facegeo.appearance.brdf._TINY
_KW = {"nogil": True, "cache": True, "boundscheck": False, "error_model": "numpy"}


@njit(inline="always", **_KW)
def _dot3(ax, ay, az, bx, by, bz):
    """``a·b`` summed as numpy's ``einsum("pc,pc->p")`` sums three terms: (x + z) + y."""
    return (ax * bx + az * bz) + ay * by


@njit(inline="always", **_KW)
def _to_light(p, s, pos, directional, stage_radius):
    """Unit direction to the light and its irradiance falloff ``(r/d)²`` at sample ``s``
    (``np.linalg.norm``'s sum order: (x + y) + z)."""
    if directional:
        return pos[0], pos[1], pos[2], 1.0
    tx, ty, tz = pos[0] - p[s, 0], pos[1] - p[s, 1], pos[2] - p[s, 2]
    dist = np.sqrt((tx * tx + ty * ty) + tz * tz)
    q = stage_radius / dist
    return tx / dist, ty / dist, tz / dist, q * q


@njit(inline="always", **_KW)
def _half_angle(lx, ly, lz, vx, vy, vz, nl, nv):
    """``(cos θ_h, cos θ_d)`` from l + v (``brdf._half_angle_cosines``)."""
    sx, sy, sz = lx + vx, ly + vy, lz + vz
    two_cos_d = np.sqrt(_dot3(sx, sy, sz, sx, sy, sz))
    cos_d = min(max(0.5 * two_cos_d, 0.0), 1.0)
    cos_h = min(max((nl + nv) / max(two_cos_d, _TINY), 0.0), 1.0)
    return cos_h, cos_d


@njit(inline="always", **_KW)
def _interp_mu(flat, n_mu, j, fy, mu):
    """``facegeo.appearance.brdf._interp_mu`` for one value: the bilinear ρ_dr table value
    at (sqrt(μ), row j + fy), μ clipped to [0, 1]."""
    x = np.sqrt(min(max(mu, 0.0), 1.0)) * (n_mu - 1)
    i = min(max(int(x), 0), n_mu - 2) if x == x else 0
    fx = x - i
    k = j * n_mu + i
    t0 = flat[k] + fx * (flat[k + 1] - flat[k])
    k = k + n_mu
    t1 = flat[k] + fx * (flat[k + 1] - flat[k])
    return t0 + fy * (t1 - t0)


def light_independent_terms(view, eta: float) -> tuple:
    """What :func:`shade_rows` needs of a view (``facegeo.synth.render.SurfaceView``) whatever
    the light: ``(m², π·m², nv, t_r, j, fy, table, n_mu)`` — m² and π·m² in the roughness's
    own precision and ``log m`` by numpy, as ``facegeo.appearance.brdf`` computes them (float32
    for a view's float32 parameters), the rest by :func:`view_terms`; ``table`` the flattened
    ρ_dr table of ``eta`` with ``n_mu`` view cosines a row."""
    from facegeo.appearance.brdf import RHO_DR_M_RANGE, _rho_dr_table

    _, logm, table = _rho_dr_table(float(eta))
    flat = np.ascontiguousarray(table, np.float64).ravel()
    n_mu = int(table.shape[1])
    m = view.roughness
    log_m = np.log(np.clip(m, RHO_DR_M_RANGE[0], RHO_DR_M_RANGE[1]))
    m2 = m * m
    return (m2, np.pi * m2, *view_terms(view.n_world, view.v_world, view.rho_s, log_m,
                                        np.asarray(logm, np.float64), flat, n_mu), flat, n_mu)


@njit(**_KW)
def view_terms(n, v, rho_s, log_m, logm, flat, n_mu):
    """What the BRDF needs of each sample whatever the light: ``(nv, t_r, j, fy)``.

    ``nv = n·v``; ``t_r = clip(1 − ρ_s ρ_dr(n·v)/ρ_s, 0, 1)``, the view side's transmission
    T(θ_r) (Donner & Jensen 2006 Eq. (2)); ``j``, ``fy``: the roughness row and weight in the
    ρ_dr table (``brdf._m_weights`` from ``log_m``, numpy's float32 log of the clipped
    float32 roughness: numba's float32 log rounds differently).
    """
    p = n.shape[0]
    nv_out = np.empty(p)
    t_r = np.empty(p)
    j_out = np.empty(p, np.int64)
    fy_out = np.empty(p)
    inv = 1.0 / (logm[1] - logm[0])
    n_m = logm.shape[0]
    for s in range(p):
        nv = _dot3(n[s, 0], n[s, 1], n[s, 2], v[s, 0], v[s, 1], v[s, 2])
        y = (np.float64(log_m[s]) - logm[0]) * inv
        j = min(max(int(y), 0), n_m - 2) if y == y else 0
        fy = y - j
        tr = 1.0 - np.float64(rho_s[s]) * _interp_mu(flat, n_mu, j, fy, min(max(nv, 0.0), 1.0))
        nv_out[s] = nv
        t_r[s] = min(max(tr, 0.0), 1.0)
        j_out[s] = j
        fy_out[s] = fy
    return nv_out, t_r, j_out, fy_out


@njit(**_KW)
def lit_rows(p, n, pos, directional):
    """The samples a light faces (``cos θ_i > 0``), in sample order.

    ``pos`` is the light's position (a point light) or its unit direction (``directional``).
    A point light exactly on a sample has no direction there: ``ValueError`` (the caller says
    which light, as :meth:`~facegeo.synth.render.ReferenceRenderer.shade_point_light` does).
    """
    count = p.shape[0]
    rows = np.empty(count, np.int64)
    k = 0
    for s in range(count):
        if not directional and p[s, 0] == pos[0] and p[s, 1] == pos[1] and p[s, 2] == pos[2]:
            raise ValueError("the light lies on the surface")
        lx, ly, lz, _ = _to_light(p, s, pos, directional, 1.0)
        if _dot3(n[s, 0], n[s, 1], n[s, 2], lx, ly, lz) > 0.0:
            rows[k] = s
            k += 1
    return rows[:k]


@njit(**_KW)
def beckmann_exponents(rows, p, n, v, nv_s, m2_s, pos, directional):
    """The Beckmann exponent ``(cos²θ_h − 1)/(cos²θ_h m²)`` of each of ``rows`` (0 where the
    specular lobe is 0): its ``exp`` is taken by numpy between the kernels, so it is
    numpy's ``exp`` bit for bit (``brdf._specular_unchecked``)."""
    count = rows.shape[0]
    out = np.zeros(count)
    for k in range(count):
        s = rows[k]
        lx, ly, lz, _ = _to_light(p, s, pos, directional, 1.0)
        nl = _dot3(n[s, 0], n[s, 1], n[s, 2], lx, ly, lz)
        nv = nv_s[s]
        cos_h, _ = _half_angle(lx, ly, lz, v[s, 0], v[s, 1], v[s, 2], nl, nv)
        if nl > 0.0 and nv > 0.0 and cos_h > 1e-8:
            ch2 = cos_h * cos_h
            out[k] = (ch2 - 1.0) / (ch2 * np.float64(m2_s[s]))
    return out


@njit(**_KW)
def shade_rows(rows, exp_b, p, n, v, a0, a1, rho_s, m2_s, pi_m2_s, nv_s, t_r, j_s, fy_s, flat,
               n_mu, eta, pos, directional, stage_radius, col):
    """Radiance ``(R, 3)`` float32 toward the camera at samples ``rows`` (lit and unshadowed)
    under one light of colour ``col``: ``f_r(l, v) cos θ_i E``, ``E = col (r/d)²`` for a point
    light at ``pos`` (``col`` for a distant one), f_r the generator's skin BRDF
    (``brdf.synthetic_skin_brdf_unchecked``); ``exp_b`` = ``exp`` of
    :func:`beckmann_exponents`; ``m2_s`` = m·m and ``pi_m2_s`` = π·m² as numpy computes them
    from the view's roughness (in float32 for float32 parameters)."""
    count = rows.shape[0]
    out = np.empty((count, 3), np.float32)
    g0 = eta * eta - 1.0
    for k in range(count):
        s = rows[k]
        lx, ly, lz, fall = _to_light(p, s, pos, directional, stage_radius)
        nx, ny, nz = n[s, 0], n[s, 1], n[s, 2]
        nl = _dot3(nx, ny, nz, lx, ly, lz)
        nv = nv_s[s]
        cos_h, cos_d = _half_angle(lx, ly, lz, v[s, 0], v[s, 1], v[s, 2], nl, nv)
        rs = np.float64(rho_s[s])
        spec = 0.0  # Torrance–Sparrow (brdf._specular_unchecked)
        if nl > 0.0 and nv > 0.0 and cos_h > 1e-8:
            t = cos_h / (2.0 * max(cos_d, _TINY))
            g_over = min(0.25 / max(nl * nv, 1e-4), t / max(nl, nv))
            c = cos_d
            g = np.sqrt(g0 + c * c)
            a = (g - c) / (g + c)
            b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
            F = 0.5 * a * a * (1.0 + b * b)
            ch2 = cos_h * cos_h
            D = exp_b[k] / (np.float64(pi_m2_s[s]) * ch2 * ch2)
            spec = rs * F * D * g_over
        e = nl * fall  # cos θ_i (r/d)²
        if nl > 0.0 and nv > 0.0:  # diffuse colour blend (brdf._diffuse_unchecked)
            w = min(max(nl, 0.0), 1.0) * min(max(nv, 0.0), 1.0)
            ti = min(max(1.0 - rs * _interp_mu(flat, n_mu, j_s[s], fy_s[s],
                                                min(max(nl, 0.0), 1.0)), 0.0), 1.0)
            t_io = ti * t_r[s]
            for ch in range(3):
                d = t_io * (np.float64(a0[s, ch]) * w + np.float64(a1[s, ch]) * (1.0 - w)) / np.pi
                out[k, ch] = np.float32((d + spec) * (e * col[ch]))
        else:
            for ch in range(3):
                out[k, ch] = np.float32((0.0 + spec) * (e * col[ch]))
    return out


@njit(**_KW)
def accumulate(acc, rows, rad, w):
    """``acc[rows] += rad · w`` in float64 (rad float32 ``(R, 3)``, w ``(3,)``)."""
    for k in range(rows.shape[0]):
        s = rows[k]
        for ch in range(3):
            acc[s, ch] += np.float64(rad[k, ch]) * w[ch]
