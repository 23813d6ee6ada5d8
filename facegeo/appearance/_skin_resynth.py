"""Resynthesis of reflectance functions for novel views (Debevec et al. 2000, §4.3, Eq. 9).

Private module behind :mod:`facegeo.appearance.skin`. The numpy functions here are the
reference; with ``KERNELS`` (default) :func:`resynthesize` and :func:`resynthesize_relit` run
the compiled kernels of ``_skin_resynth_kernels`` instead (same formulas, one function per
thread, no ``(N, L, 3)`` temporaries; equal to the reference to rounding, tested in
``tests/test_skin_model.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from facegeo.appearance._skin_fit import (
    FLAG_BACKFACING,
    FLAG_SPECULAR_IN_SHADOW,
    FLAG_SPECULAR_SKIPPED,
    check_views,
)
from facegeo.appearance._skin_model import (
    COS_FLOOR,
    S_WHITE,
    LightSet,
    invert_ramp,
    normalize,
    ramp_chromaticity,
    ramp_f,
)
from facegeo.appearance.brdf import fresnel_dielectric, torrance_sparrow_geometry
from facegeo.checks import as_array, fmt_value
from facegeo.errors import InputError

#: Functions whose specular energy is below this fraction of their total energy skip the
#: specular resynthesis (their specular part is dropped and flagged).
SPECULAR_SKIP = 1e-4

#: A v_n within this distance of v_0 counts as the source view: the measured function is
#: returned unchanged (the paper's guarantee, without interpolation rounding).
SAME_VIEW_TOL = 1e-12

#: Run :func:`resynthesize` and :func:`resynthesize_relit` in the compiled kernels of
#: ``_skin_resynth_kernels`` (numba; one function per ``prange`` iteration, no ``(N, L, 3)``
#: temporaries). False: the numpy reference below, which the kernels are tested against.
KERNELS = True

#: On the light-stage grid without a lobe cone, with at least half the lights to visit,
#: :func:`resynthesize_relit` runs ``_skin_resynth_kernels.resynth_relit_grid`` (branch-free
#: loop over lights, fewer square roots and divisions, a polynomial atan2, every node's
#: microfacet value computed up front) instead of ``resynth_relit`` (libm atan2/acos, nodes
#: computed when first read, which pays when few lights are visited: ``light_step > 1``);
#: the two agree to rounding (tested in ``tests/test_resynth_fast.py``). False: always
#: ``resynth_relit``.
VECTOR_KERNEL = True


@dataclass
class Resynthesis:
    """Reflectance functions resynthesised for a novel view.

    Attributes
    ----------
    reflectance : (N, L, C) float32 — diffuse + specular, input units
    diffuse, specular : (N, L, C) float32
    flags : (N,) int32 — the fit's flags plus FLAG_SPECULAR_IN_SHADOW / FLAG_SPECULAR_SKIPPED /
        FLAG_BACKFACING
    """

    reflectance: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray
    flags: np.ndarray


def _dot(a, b):
    return np.einsum("...i,...i->...", a, b)


def interpolate_on_lights(values, lights: LightSet, dirs, *, free: str = "nearest3"):
    """Values of a function on the light set, interpolated at directions ``dirs``.

    On the light-stage grid: bilinear in (θ, φ) grid coordinates (wrapping in θ, clamped at the
    polar rows); exact at the grid's nodes up to rounding. On a free light list, by ``free``:
    ``"nearest3"`` (default; what the compiled Eq. 9 kernels do) inverse angular-distance
    weighting of the 3 nearest lights; ``"barycentric"`` (:func:`barycentric_on_lights`) the
    lights' spherical triangulation.

    Parameters
    ----------
    values : (n, L, K) float64
    lights : LightSet
    dirs : (n, M, 3) float64, unit
    free : {"nearest3", "barycentric"}

    Returns
    -------
    (n, M, K) float64
    """
    n, M, _ = dirs.shape
    if lights.grid is None and free == "barycentric":
        return barycentric_on_lights(values, lights.directions, dirs)
    if free not in ("nearest3", "barycentric"):
        raise InputError(f"free: expected 'nearest3' or 'barycentric', got {fmt_value(free)}")
    if lights.grid is not None:
        nt, npf = lights.grid
        theta = np.mod(np.arctan2(dirs[..., 0], dirs[..., 2]), 2.0 * np.pi)
        phi = np.arccos(np.clip(dirs[..., 1], -1.0, 1.0))
        i = theta * nt / (2.0 * np.pi) - 0.5
        j = phi * npf / np.pi - 0.5
        i0 = np.floor(i)
        j0 = np.floor(j)
        fi = (i - i0)[..., None]
        fj = (j - j0)[..., None]
        i0 = i0.astype(np.int64)
        j0 = j0.astype(np.int64)
        ia, ib = np.mod(i0, nt), np.mod(i0 + 1, nt)
        ja, jb = np.clip(j0, 0, npf - 1), np.clip(j0 + 1, 0, npf - 1)

        def g(jj, ii):
            return np.take_along_axis(values, (jj * nt + ii)[..., None], axis=1)

        return ((1 - fj) * ((1 - fi) * g(ja, ia) + fi * g(ja, ib))
                + fj * ((1 - fi) * g(jb, ia) + fi * g(jb, ib)))
    cosang = np.clip(dirs @ lights.directions.T, -1.0, 1.0)  # (n, M, L)
    k = min(3, lights.n_lights)
    idx = np.argpartition(-cosang, k - 1, axis=2)[..., :k]
    c = np.take_along_axis(cosang, idx, axis=2)
    w = 1.0 / (1.0 - c + 1e-12)
    w /= w.sum(axis=2, keepdims=True)
    vals = np.take_along_axis(values[:, None, :, :], idx[..., None], axis=2)  # (n, M, k, K)
    return np.einsum("nmk,nmkc->nmc", w, vals)


#: A ray counts as passing through a triangle of :func:`barycentric_on_lights` when its
#: smallest barycentric weight is at least −this (rounding at edges and vertices).
BARY_EDGE_TOL = 1e-9

_TRIANGULATIONS: dict = {}


def _light_triangulation(directions):
    """The spherical Delaunay triangulation of unit ``directions`` (the faces of their convex
    hull that face away from the centre), each triangle's inverse vertex matrix, each light's
    triangles (padded with −1), a k-d tree of the lights; None where the hull fails (fewer
    than 4 lights, all on one plane). Cached by the directions' bytes (a light list's
    triangulation is made once a process)."""
    from scipy.spatial import ConvexHull, QhullError, cKDTree

    d = np.ascontiguousarray(directions, np.float64)
    key = d.tobytes()
    if key in _TRIANGULATIONS:
        return _TRIANGULATIONS[key]
    out = None
    if len(d) >= 4:
        try:
            hull = ConvexHull(d)
        except QhullError:
            hull = None
        # the spherical triangles: hull faces with the centre on their inner side (a dome's
        # flat base, whose plane has the centre outside or on it, is not one)
        tris = None if hull is None else hull.simplices[hull.equations[:, 3] < -1e-9]
        if tris is not None and len(tris):
            m = np.stack([d[tris[:, 0]], d[tris[:, 1]], d[tris[:, 2]]], axis=2)
            inv = np.linalg.inv(m)
            # each light's triangles, padded with −1: sort the (light, triangle) pairs by light
            light = tris.ravel()
            order = np.argsort(light, kind="stable")
            deg = np.bincount(light, minlength=len(d))
            start = np.concatenate([[0], np.cumsum(deg)[:-1]])
            slot = np.arange(light.size) - np.repeat(start, deg)
            inc = np.full((len(d), max(int(deg.max()), 1)), -1, np.int64)
            inc[light[order], slot] = (np.arange(light.size) // 3)[order]
            out = (tris, inv, inc, cKDTree(d))
    if len(_TRIANGULATIONS) > 16:
        _TRIANGULATIONS.clear()
    _TRIANGULATIONS[key] = out
    return out


def barycentric_on_lights(values, directions, dirs):
    """Values on a free light list at directions ``dirs`` by the lights' spherical triangulation.

    The lights' unit directions span a convex hull whose faces are their spherical Delaunay
    triangles; a ray along q passes through one triangle (A, B, C), and q = λ_A A + λ_B B +
    λ_C C gives its weights λ / Σλ (gnomonic barycentric coordinates): exact at the lights,
    linear across each triangle — what bilinear interpolation is on the grid. The triangle is
    found among those of the 3 lights nearest q (a k-d tree); where none holds q within
    :data:`BARY_EDGE_TOL` (q outside a partial dome's lights, or rare obtuse cases), the best
    candidate's weights are clipped at 0 and renormalised (and where nothing is left, the
    nearest light's value is taken). Lists the hull cannot triangulate
    (fewer than 4 lights, all on one plane) fall back to the 3 nearest lights' inverse
    angular-distance weights (:func:`interpolate_on_lights`).

    Why (a deviation from the nearest-3 weights elsewhere): resampling a near-field list to its
    distant-equivalent directions (:func:`facegeo.appearance._near_field.distant_equivalent`)
    with the nearest-3 weights cost the fit 0.54° of median normal error on the small preset's
    stage as a list; with this 0.15° (the grid's bilinear: 0.17°), 3.5× faster
    (``tests/test_skin_near_field.py``).

    Parameters
    ----------
    values : (n, L, K) float64
    directions : (L, 3) float64, unit — the lights
    dirs : (n, M, 3) float64, unit

    Returns
    -------
    (n, M, K) float64
    """
    n, M, _ = dirs.shape
    tri = _light_triangulation(directions)
    if tri is None:
        L = len(directions)
        return interpolate_on_lights(values, LightSet(np.asarray(directions), np.ones(L),
                                                      np.ones((L, 3))), dirs)
    tris, inv, inc, tree = tri
    q = np.ascontiguousarray(dirs, np.float64).reshape(-1, 3)
    _, near = tree.query(q, k=min(3, len(directions)))
    cand = inc[near.reshape(len(q), -1)].reshape(len(q), -1)  # (Q, candidates)
    have = cand >= 0
    c = np.where(have, cand, 0)
    lam = np.einsum("qkij,qj->qki", inv[c], q)
    score = np.where(have, lam.min(axis=2), -np.inf)
    best = score.argmax(axis=1)
    rows = np.arange(len(q))
    w = lam[rows, best]
    outside = score[rows, best] < -BARY_EDGE_TOL
    if outside.any():
        w[outside] = np.maximum(w[outside], 0.0)
    total = w.sum(axis=1)
    lost = ~(total > 0)  # no candidate triangle, or every weight clipped: the nearest light
    w[lost] = (1.0, 0.0, 0.0)
    total[lost] = 1.0
    w /= total[:, None]
    idx = tris[c[rows, best]]  # (Q, 3) lights
    if lost.any():
        idx[lost, 0] = near.reshape(len(q), -1)[lost, 0]
    func = np.repeat(np.arange(n), M)
    return np.einsum("qk,qkc->qc", w, values[func[:, None], idx]).reshape(n, M, -1)


def resynthesize_diffuse(D, E, n, v0, vn, alpha_0, alpha_1, lights, dirs=None):
    """Diffuse component chroma-shifted from v_0 to v_n (§4.3).

    For each sample, the chrominance shift of the original view is inverted (Eq. 6 inverted,
    with the sample's own chromaticity in place of d_0) and that of the new view applied;
    the brightness is kept (Lambertian: view-independent).

    Parameters
    ----------
    D : (n, L, 3) float64, input units; E : (L, 3) light intensities
    n, v0, vn : (n, 3) float64, unit; alpha_0, alpha_1 : (n,) float64
    dirs : (n, L, 3) float64, unit, optional
        Each function's own light directions (a near-field stage,
        :mod:`facegeo.appearance._near_field`); default the light set's.

    Returns
    -------
    (n, L, 3) float64
    """
    Dw = D / E[None]
    b = np.linalg.norm(Dw, axis=2)
    c = normalize(Dw, fallback=S_WHITE)
    nl = n @ lights.directions.T if dirs is None else np.einsum("ni,nli->nl", n, dirs)
    f0 = ramp_f(nl, _dot(n, v0)[:, None], alpha_0[:, None], alpha_1[:, None])
    fn = ramp_f(nl, _dot(n, vn)[:, None], alpha_0[:, None], alpha_1[:, None])
    d, _ = invert_ramp(c, f0)
    return b[..., None] * ramp_chromaticity(d, fn) * E[None]


def resynthesize_specular(sigma, shadow, n, v0, vn, lights, eta, near=None):
    """Specular reflectance function for a novel view by Eq. 9 (Debevec et al. 2000, §4.3).

    For each light l_p: ``H = normalize(v_n + l_p)``, the source light
    ``l_q = 2 (H·v_0) H − v_0`` that saw the same microfacets from v_0, the measured sample at
    l_q interpolated on the light set, and

        L_vn = L_v0(l_q) · G(v_n, l_p, n) F(v_n·H) (v_0·n) / (G(v_0, l_q, n) F(v_0·H) (v_n·n))

    Deviation, same equation: the interpolation on the light set is applied to the measured
    samples divided by their own view's factors, ``S(l)(v_0·n)/(G(v_0, l, n) F(v_0·h_l))`` (the
    microfacet distribution sampled at the nodes, Fig. 12 e), rather than to S itself; at a
    node both are identical, between nodes the smooth distribution interpolates far better
    than a lobe whose G and F fall to zero at grazing l.

    Zero (no lobe) where l_p is occluded (§4.4: never a specular lobe in a shadowed direction),
    where l_q is below the horizon; where l_q was occluded in the source the measured sample
    (dark) is used as is and the function flagged (a lobe hidden in shadow is unrecoverable),
    where n·l_p ≤ 0 or n·v_n ≤ 0, and where H is undefined (l_p = −v_n). Denominators are
    floored at COS_FLOOR; results are finite.

    Near-field stage (``near``, :mod:`facegeo.appearance._near_field`): l_p is each light's
    true direction from the point, the measured samples are divided by their falloff before
    the interpolation, l_q is read where the ray from the point along it meets the light
    sphere, and the result carries the target light's falloff: Eq. 9 with every light where it
    is (the paper's stage is treated as distant).

    Parameters
    ----------
    sigma : (n, L) float64 — white-balanced specular sample per colour channel
    shadow : (n, L) bool, occluded lights (``SkinFit.cast_shadow``)
    n, v0, vn : (n, 3) float64, unit
    near : NearField of the n functions, optional

    Returns
    -------
    spec : (n, L) float64
    hidden : (n,) bool — some l_q fell in a shadowed source direction with lit l_p
    """
    if near is None:
        lp = lights.directions[None]
        nlp = n @ lights.directions.T  # (n, L)
        fall = None
    else:
        lp, fall = near.light_geometry(lights.directions)
        nlp = np.einsum("ni,nli->nl", n, lp)
        sigma = sigma / fall
    nv0 = _dot(n, v0)[:, None]
    nvn = _dot(n, vn)[:, None]
    # the measured samples as microfacet values ρ_s P(h_l) ∝ S_l (n·v_0)/(G F) on the nodes
    h0 = normalize(lp + v0[:, None, :], fallback=n[:, None, :] * np.ones_like(lp))
    nh0 = _dot(h0, n[:, None, :])
    vh0 = _dot(h0, v0[:, None, :])
    gf0 = torrance_sparrow_geometry(nlp, nv0, nh0, vh0) * fresnel_dielectric(vh0, eta)
    good0 = gf0 > 1e-6
    micro = np.where(good0, sigma * np.maximum(nv0, 0.0) / np.where(good0, gf0, 1.0), 0.0)
    hv = vn[:, None, :] + lp
    hn = np.linalg.norm(hv, axis=2)
    H = hv / np.maximum(hn, 1e-300)[..., None]
    Hv0 = _dot(H, v0[:, None, :])
    lq = 2.0 * Hv0[..., None] * H - v0[:, None, :]
    lq = normalize(lq, fallback=n[:, None, :] * np.ones_like(lq))
    where = lq
    if near is not None:  # the stage direction of the light the point sees along l_q
        where = near.stage_directions(lq)
    vals = interpolate_on_lights(np.stack([micro, shadow.astype(np.float64)], axis=2), lights,
                                 where)
    m_q, sh_q = vals[..., 0], vals[..., 1] > 0.5
    nH = _dot(H, n[:, None, :])
    nlq = _dot(lq, n[:, None, :])
    vnH = _dot(H, vn[:, None, :])
    G_n = torrance_sparrow_geometry(nlp, nvn, nH, vnH)
    F_n = fresnel_dielectric(vnH, eta)
    ok = (hn > 1e-9) & (nH > 0) & (nlp > 0) & (nlq > 0) & (nvn > 0) & (nv0 > 0) & ~shadow
    hidden_l = ok & sh_q  # the source saw these microfacets only through an occluded light
    spec = np.where(ok, m_q * G_n * F_n / np.maximum(nvn, COS_FLOOR), 0.0)
    if fall is not None:
        spec *= fall
    return np.maximum(spec, 0.0), hidden_l.any(axis=1)


def _views_and_masks(fit, v_n):
    """The checked novel views ``(N, 3)``, the input flags with FLAG_BACKFACING, and the
    same-view / back-facing masks of :func:`resynthesize`."""
    N = fit.diffuse.shape[0]
    vn = check_views(v_n, N)
    same = np.linalg.norm(vn - fit.view, axis=1) <= SAME_VIEW_TOL
    back = np.einsum("ni,ni->n", fit.normal, vn) <= 0
    flags = fit.flags.astype(np.int32) | np.where(back, FLAG_BACKFACING, 0).astype(np.int32)
    return vn, flags, same, back


def _kernel_args(fit, vn, same, back, specular_skip):
    """The arguments :mod:`_skin_resynth_kernels` shares between its two kernels."""
    c = np.ascontiguousarray
    lights = fit.lights
    grid = lights.grid is not None
    nt, npf = lights.grid if grid else (1, 1)

    def comp(a):  # float32 components are read as they are (the reference widens them)
        return c(a) if a.dtype in (np.float32, np.float64) else c(a, np.float64)

    return (comp(fit.diffuse), comp(fit.specular), c(lights.intensities, np.float64),
            c(lights.directions, np.float64), c(lights.solid_angles, np.float64),
            c(fit.cast_shadow, np.bool_), c(fit.normal, np.float64), c(fit.view, np.float64),
            c(vn, np.float64), c(fit.alpha_0, np.float64), c(fit.alpha_1, np.float64),
            c(same), c(back), grid, int(nt), int(npf), float(fit.eta), float(specular_skip))


def resynthesize(fit, v_n, *, view_independent_form: bool = False,
                 specular_skip: float = SPECULAR_SKIP) -> Resynthesis:
    """Reflectance functions as seen from a novel view v_n (Debevec et al. 2000, §4.3, Fig. 12).

    Diffuse: chroma-shifted from v_0 to v_n (:func:`resynthesize_diffuse`). Specular: Eq. 9
    (:func:`resynthesize_specular`). Functions whose v_n equals v_0 (within SAME_VIEW_TOL) get
    the measured function back unchanged — the paper's guarantee. Functions whose specular
    energy is below ``specular_skip`` of their total skip the specular work
    (FLAG_SPECULAR_SKIPPED). With ``view_independent_form`` the functions are first
    transformed to the view-independent form (v = n, Fig. 12 e; :func:`view_independent`) and
    resynthesised from there. Single-channel fits keep their (diffuse) function unchanged.

    With ``KERNELS`` (default) the work runs in the compiled kernel
    ``_skin_resynth_kernels.resynth_full`` (one function per thread, no ``(N, L, 3)``
    temporaries); it equals this module's numpy path to rounding. A near-field fit
    (``fit.near``, :func:`facegeo.appearance.skin.fit_reflectance_near`) runs the numpy path
    with each light's true direction and falloff (:func:`resynthesize_specular`).

    Parameters
    ----------
    fit : SkinFit
    v_n : (3,) or (N, 3) array_like, unit, the light set's frame

    Returns
    -------
    Resynthesis
    """
    fit._need_specular("resynthesize")
    if view_independent_form:
        check_views(v_n, fit.diffuse.shape[0])
        fit = view_independent(fit, specular_skip=specular_skip)
    vn, flags, same, back = _views_and_masks(fit, v_n)
    todo = np.flatnonzero(~same)
    if fit.single_channel or todo.size == 0:
        D = fit.diffuse.astype(np.float64)
        S = fit.specular.astype(np.float64)
        return Resynthesis((D + S).astype(np.float32), D.astype(np.float32),
                           S.astype(np.float32), flags)
    if KERNELS and getattr(fit, "near", None) is None:
        from facegeo.appearance._skin_resynth_kernels import resynth_full

        refl, diff, spec, kflags = resynth_full(
            *_kernel_args(fit, vn, same, back, specular_skip),
            FLAG_SPECULAR_SKIPPED, FLAG_SPECULAR_IN_SHADOW)
        return Resynthesis(refl, diff, spec, flags | kflags)
    return _resynthesize_numpy(fit, vn, flags, same, back, todo, specular_skip)


def _resynthesize_numpy(fit, vn, flags, same, back, todo, specular_skip) -> Resynthesis:
    """The numpy reference of :func:`resynthesize` (``KERNELS = False``) for a 3-channel fit
    with at least one function to resynthesise."""
    D = fit.diffuse.astype(np.float64)
    S = fit.specular.astype(np.float64)
    D_new = D.copy()
    S_new = S.copy()
    E = fit.lights.intensities
    n, v0 = fit.normal[todo], fit.view[todo]
    near = getattr(fit, "near", None)
    dirs = None
    if near is not None:
        dirs, _ = near.take(todo).light_geometry(fit.lights.directions)
    D_new[todo] = resynthesize_diffuse(D[todo], E, n, v0, vn[todo], fit.alpha_0[todo],
                                       fit.alpha_1[todo], fit.lights, dirs)
    sigma = (S[todo] / E[None]).mean(axis=2)
    total = np.abs((D[todo] + S[todo]) / E[None]).mean(axis=2) @ fit.lights.solid_angles
    energy = sigma @ fit.lights.solid_angles
    do_spec = energy > specular_skip * np.maximum(total, 1e-300)
    flags[todo[~do_spec]] |= FLAG_SPECULAR_SKIPPED
    S_new[todo] = 0.0
    ts = todo[do_spec]
    if ts.size:
        spec, hidden = resynthesize_specular(sigma[do_spec], fit.cast_shadow[ts], fit.normal[ts],
                                             fit.view[ts], vn[ts], fit.lights, fit.eta,
                                             None if near is None else near.take(ts))
        S_new[ts] = spec[..., None] * E[None]
        flags[ts[hidden]] |= FLAG_SPECULAR_IN_SHADOW
    D_new[back] = 0.0
    S_new[back] = 0.0
    return Resynthesis((D_new + S_new).astype(np.float32), D_new.astype(np.float32),
                       S_new.astype(np.float32), flags)


def resynthesize_relit(fit, v_n, weights, *, specular_skip: float = SPECULAR_SKIP,
                       lobe_tol: float | None = None, light_step: int = 1) -> np.ndarray:
    """Relit radiance of the functions resynthesised for v_n: Eq. 4 on :func:`resynthesize`.

    ``out[i] = Σ_l w_l ⊙ R_new,i(l)`` (Debevec et al. 2000, Eq. 4, with the δA_l inside the
    weights), where ``R_new`` is :func:`resynthesize`'s ``reflectance`` — without building it:
    with ``KERNELS`` the compiled ``_skin_resynth_kernels.resynth_relit`` visits, per function,
    only the lights whose weight is non-zero (the lights that carry energy). Functions with
    ``n·v_n <= 0`` (FLAG_BACKFACING) give 0 as in :func:`resynthesize`; callers that want
    another fallback test ``fit.normal · v_n <= 0`` themselves.

    Deviation from ``resynthesize(fit, v_n).reflectance @ weights``: the new samples are summed
    in float64 (the reference rounds each to float32 first), a relative difference of order
    1e-7.

    Work skipped without changing the result: lights whose diffuse sample is 0 (below the
    horizon, shadowed) skip the chroma shift; with ``lobe_tol = 0``, per function, Eq. 9's
    interpolation, G and F run only where the source direction l_q can reach a node with a
    non-zero microfacet value (a cone around the lobe, :func:`_skin_resynth_kernels._lobe_cone`,
    light-stage grid only; measured functions hold storage rounding and noise at every node,
    so the cone rarely excludes anything and is off by default).

    Speed against accuracy (``lobe_tol > 0``, not the paper): nodes whose microfacet value is
    at most ``lobe_tol`` of the function's largest count as zero for that cone, so the
    specular work is confined to the lobe. Each dropped specular sample is at most
    ``lobe_tol`` times the lobe's peak microfacet value times G F/(n·v_n) (G, F ≤ 1); with
    float16 fields the nodes far from the lobe hold storage rounding, not signal. On skin's
    broad lobes the cone covers most of the hemisphere, so this buys little (measured in
    ``facegeo bench render.novel_view_paper``).

    Speed against accuracy (``light_step = k > 1``, not the paper): the new function is
    evaluated at one output light per ``k × k`` block of the light-stage grid instead of at
    every light — at the block's energy centroid (its lights' directions averaged with the
    weights' channel mean ω_l), with the block's diffuse samples and intensities ω-averaged,
    its occlusion by ω-majority and its weights summed (:func:`_output_blocks`). The measured
    lobe Eq. 9 interpolates stays at full resolution. Eq. 4 on the measured diffuse part is
    kept exactly where the weights' colour is constant over a block (a block holding a sun
    evaluates at the sun); what changes is that Eq. 9 and the chroma shift are evaluated
    once per block (the midpoint rule of a smooth function over the block): ``k²`` times
    fewer evaluations.

    Parameters
    ----------
    fit : SkinFit
    v_n : (3,) or (N, 3) array_like, unit, the light set's frame
    weights : (L, C) array_like — per-light, per-channel weights in the field's units
    lobe_tol : float in [0, 1) or None — see above; None (default, no cone) and 0 give the
        exact result. Ignored by the numpy reference (``KERNELS = False``) and for free light
        lists.
    light_step : int ≥ 1 — see above; 1 (default) gives the exact result. Needs the kernels
        and a light-stage grid that ``light_step`` divides.

    Returns
    -------
    (N, C) float64
    """
    fit._need_specular("resynthesize_relit")
    N, L, C = fit.diffuse.shape
    w = as_array(weights, "weights", shape=(L, C))
    tol = -1.0 if lobe_tol is None else float(lobe_tol)
    if lobe_tol is not None and not 0.0 <= tol < 1.0:
        raise InputError(f"lobe_tol: expected a fraction in [0, 1), got {fmt_value(lobe_tol)}")
    step = check_light_step(light_step, fit.lights)
    if step > 1 and (not KERNELS or fit.single_channel or C != 3):
        raise InputError("light_step > 1 needs the compiled kernels (KERNELS) and a 3-channel "
                         "fit")
    near = getattr(fit, "near", None) is not None
    if step > 1 and near:
        raise InputError("light_step > 1: a near-field fit (SkinFit.near) is resynthesised at "
                         "every light; use light_step=1")
    if not KERNELS or fit.single_channel or C != 3 or near:
        r = resynthesize(fit, v_n, specular_skip=specular_skip)
        return np.einsum("nlc,lc->nc", r.reflectance, w)
    vn, _, same, back = _views_and_masks(fit, v_n)
    if not (~same).any():
        # resynthesize returns the measured functions unchanged here (back-facing ones too)
        R = fit.diffuse.astype(np.float64) + fit.specular.astype(np.float64)
        return np.einsum("nlc,lc->nc", R, w)
    from facegeo.appearance._skin_resynth_kernels import resynth_relit

    args = _kernel_args(fit, vn, same, back, specular_skip)
    if step == 1:
        active = np.flatnonzero(np.any(w != 0, axis=1)).astype(np.int64)
        D, E, dirs, cast = args[0], args[2], args[3], args[5]
        outputs = (D, E, dirs, cast, active, np.ascontiguousarray(w[active], np.float64))
    else:
        from facegeo.appearance._skin_resynth_kernels import block_outputs

        members, starts, share, dq, Eq, wq = _output_blocks(fit.lights, w, step)
        Dq, castq = block_outputs(args[0], args[5], members, starts, share)
        outputs = (Dq, Eq, dq, castq, np.arange(dq.shape[0], dtype=np.int64), wq)
    many = 2 * outputs[4].size >= fit.lights.n_lights  # nodes computed up front pay off
    if VECTOR_KERNEL and args[13] and tol < 0.0 and many:
        from facegeo.appearance._skin_resynth_kernels import resynth_relit_grid

        out = resynth_relit_grid(*args[:13], *args[14:], *outputs)
    else:
        out = resynth_relit(*args, *outputs, tol, _cone_margin(fit.lights))
    keep = np.flatnonzero(same & ~back)  # the source's own view: the measured function
    if keep.size:
        R = fit.diffuse[keep].astype(np.float64) + fit.specular[keep].astype(np.float64)
        out[keep] = np.einsum("nlc,lc->nc", R, w)
    return out


#: Functions per work item of the compiled float16 passes: of :func:`relight_stored`'s
#: parallel loop (numba's dynamic scheduling, ``numba.parallel_chunksize``) and of the
#: pieces :func:`relit_stored` hands to its threads. Functions differ in cost (back-facing
#: and source-view ones are skipped), and with numba's default static split one thread
#: waits for the other at the end of every call.
PARALLEL_CHUNK = 32


def _on_threads(run, n: int) -> None:
    """``run(lo, hi)`` over pieces of ``range(n)`` of :data:`PARALLEL_CHUNK` functions, taken
    in turn by ``numba.get_num_threads()`` Python threads (the serial kernels release the
    GIL): dynamic scheduling without a ``parallel=True`` kernel to compile."""
    import itertools
    import threading

    from numba import get_num_threads

    k = PARALLEL_CHUNK
    threads = min(get_num_threads(), -(-n // k))
    if threads <= 1:
        run(0, n)
        return
    pieces = itertools.count(0, k)
    lock = threading.Lock()
    errors: list = []

    def worker():
        try:
            while True:
                with lock:
                    lo = next(pieces)
                if lo >= n or errors:
                    return
                run(lo, min(n, lo + k))
        except BaseException as e:  # re-raised in the caller
            errors.append(e)

    pool = [threading.Thread(target=worker) for _ in range(threads - 1)]
    for t in pool:
        t.start()
    worker()
    for t in pool:
        t.join()
    if errors:
        raise errors[0]


def _scheduled(kernel, *args):
    """``kernel(*args)`` with its ``prange`` loop scheduled dynamically in work items of
    :data:`PARALLEL_CHUNK` iterations."""
    from numba import parallel_chunksize

    with parallel_chunksize(PARALLEL_CHUNK):
        return kernel(*args)


_HALF_TABLE: np.ndarray | None = None


def half_table() -> np.ndarray:
    """``(65536,)`` float32, read-only: the value of every float16 bit pattern, as numpy's
    ``astype(np.float32)`` gives it (exact: subnormals, ±0, ±inf and NaN payloads included);
    the decode table of :func:`relit_stored` (numba has no float16 type)."""
    global _HALF_TABLE
    if _HALF_TABLE is None:
        t = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16).view(np.float16)
        _HALF_TABLE = t.astype(np.float32)
        _HALF_TABLE.setflags(write=False)
    return _HALF_TABLE


def relight_stored(field, field_rows, weights):
    """Eq. 4 of stored float16 measured functions, ``Σ_l w_l ⊙ R_l``, read in one compiled
    pass from their bits (``_skin_resynth_kernels.relight_stored``; no float32 copy of the
    rows, no matrix product): float64 sums of the exact float32 samples times the float64
    weights, the naive value :func:`relit_stored` gives.

    Parameters
    ----------
    field : (T, L, 3) float16 array or memmap; field_rows : (n,) int
    weights : (L, 3)

    Returns
    -------
    (n, 3) float64 — NaN where any of the row's samples is not finite; (n,) bool — finite
    """
    from facegeo.appearance._skin_resynth_kernels import relight_stored as kernel

    if field.dtype != np.float16 or field.ndim != 3 or field.shape[2] != 3:
        raise InputError(f"field: expected (T, L, 3) float16, got {field.shape} {field.dtype}")
    w = as_array(weights, "weights", shape=(field.shape[1], 3))
    active = np.flatnonzero(np.any(w != 0, axis=1)).astype(np.int64)
    return _scheduled(kernel, np.asarray(field).view(np.uint16),
                      np.ascontiguousarray(field_rows, np.int64), half_table(), active,
                      np.ascontiguousarray(w[active], np.float64))


def stored_kernel_applies(field, diffuse, lights, single_channel: bool) -> bool:
    """Whether :func:`relit_stored` serves these stored functions: the compiled kernels on
    (``KERNELS``, ``VECTOR_KERNEL``), a light-stage grid, a 3-channel fit, and field and
    diffuse component both stored as ``(·, L, 3)`` float16. Any number of lights with
    energy (a map whose energy sits in a few lights costs the per-function read and set-up
    plus those lights), any ``light_step``."""
    return bool(KERNELS and VECTOR_KERNEL and lights.grid is not None and not single_channel
                and field.dtype == np.float16 and diffuse.dtype == np.float16
                and field.ndim == 3 and field.shape[1:] == (lights.n_lights, 3)
                and diffuse.ndim == 3 and diffuse.shape[1:] == field.shape[1:])


def relit_stored(field, field_rows, diffuse, diffuse_rows, todo, *, normal, view, alpha_0,
                 alpha_1, cast_shadow, eta, lights, v_n, weights,
                 specular_skip: float = SPECULAR_SKIP, light_step: int = 1):
    """Eq. 4 of stored measured functions and of the same functions resynthesised for v_n
    (§4.3, Eq. 9), in one compiled pass over their float16 storage.

    What a renderer otherwise does in three steps — the rows of the field read and widened to
    float32 and relit (``R.reshape(n, 3L) @ W``), D read and widened, S = R − D, then
    :func:`resynthesize_relit` — with R, D and S never widened into arrays: the kernel
    ``_skin_resynth_kernels.relit_stored_grid`` decodes one function's float16 bits at a time
    (:func:`half_table`, exact) and runs ``resynth_relit_grid``'s per-function code on them.
    The samples are bit-identical to that path's (S = R − D rounded to float32 as numpy
    does); the resynthesised sums are the grid kernel's, the naive sums are float64 sums of
    the float32 samples times the float64 weights (the sgemm rounds weights and partial sums
    to float32: a relative difference of order 1e-7). Only where
    :func:`stored_kernel_applies`.

    Parameters
    ----------
    field : (T, L, 3) float16 array or memmap — measured functions R; function i is row
        ``field_rows[i]``
    diffuse : (F, L, 3) float16 array or memmap — the fit's diffuse component D; row
        ``diffuse_rows[i]``
    todo : (n,) bool — functions to resynthesise (others get only the naive value)
    normal, view : (n, 3) float64, unit; alpha_0, alpha_1 : (n,) float64; cast_shadow :
        (n, L) bool; eta : float — the fit's parameters of each function (``SkinFit``)
    lights : LightSet; v_n : (3,) or (n, 3) unit, the light set's frame
    weights : (L, 3) — Eq. 4 weights
    light_step : int ≥ 1 — the resynthesised function evaluated once per ``k × k`` block of
        the grid (:func:`resynthesize_relit`'s option, not the paper; its block summaries of
        D and of the occlusion formed from the decoded rows as ``block_outputs`` forms them);
        the naive value keeps every light

    Returns
    -------
    naive : (n, 3) float64 — Eq. 4 of the measured function; NaN where any of its samples is
        not finite (as a matrix product gives)
    relit : (n, 3) float64 — Eq. 4 of the resynthesised function where ``todo``, finite and
        ``n·v_n > 0``; the measured function's where v_n is the source view (SAME_VIEW_TOL);
        0 elsewhere
    finite : (n,) bool
    """
    field_rows = np.ascontiguousarray(field_rows, np.int64)
    n = field_rows.size
    L = lights.n_lights
    w = as_array(weights, "weights", shape=(L, 3))
    vn = check_views(v_n, n)
    normal = np.ascontiguousarray(normal, np.float64)
    view = np.ascontiguousarray(view, np.float64)
    same = np.linalg.norm(vn - view, axis=1) <= SAME_VIEW_TOL
    todo = np.asarray(todo, bool) & (np.einsum("ni,ni->n", normal, vn) > 0)
    active = np.flatnonzero(np.any(w != 0, axis=1)).astype(np.int64)
    nt, npf = lights.grid
    c = np.ascontiguousarray
    step = check_light_step(light_step, lights)
    if step == 1:  # the output lights are the measured ones (``starts`` empty)
        none = np.zeros(0, np.int64)
        blocks = (none, none, np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)))
    else:
        blocks = _output_blocks(lights, w, step)
    from facegeo.appearance._skin_resynth_kernels import relit_stored_grid

    naive = np.empty((n, 3))
    relit = np.zeros((n, 3))
    finite = np.empty(n, bool)
    args = (np.asarray(field).view(np.uint16), field_rows, np.asarray(diffuse).view(np.uint16),
            c(diffuse_rows, np.int64), half_table(), c(todo & ~same),
            c(lights.intensities, np.float64), c(lights.directions, np.float64),
            c(lights.solid_angles, np.float64), c(cast_shadow, np.bool_), normal, view, vn,
            c(alpha_0, np.float64), c(alpha_1, np.float64), int(nt), int(npf), float(eta),
            float(specular_skip), active, c(w[active], np.float64), *blocks, naive, relit,
            finite)
    _on_threads(lambda lo, hi: relit_stored_grid(lo, hi, *args), n)
    keep = np.flatnonzero(todo & same & finite)  # the source's own view: the measured function
    if keep.size:
        R = np.asarray(field[field_rows[keep]], np.float32)
        D = np.asarray(diffuse[np.asarray(diffuse_rows, np.int64)[keep]], np.float32)
        relit[keep] = np.einsum("nlc,lc->nc", D.astype(np.float64) + (R - D), w)
    return naive, relit, finite


def check_light_step(light_step, lights) -> int:
    """``light_step`` as an int ≥ 1 that divides the light-stage grid (any value > 1 needs the
    grid); raises InputError naming what is wrong."""
    ok = (isinstance(light_step, (int, float, np.integer, np.floating))
          and not isinstance(light_step, bool) and float(light_step).is_integer()
          and light_step >= 1)
    if not ok:
        raise InputError(f"light_step: expected an integer >= 1, got {fmt_value(light_step)}")
    k = int(light_step)
    if k > 1 and (lights.grid is None or lights.grid[0] % k or lights.grid[1] % k):
        raise InputError(f"light_step: {k} must divide the light-stage grid (n_theta, n_phi) = "
                         f"{lights.grid} (1 keeps every light)")
    return k


def _output_blocks(lights, w, step: int):
    """The output lights of ``light_step = step`` (:func:`resynthesize_relit`): per ``step ×
    step`` block of the grid with energy, its members (block-major), the offsets of each
    block's members, their shares ω_l/Σω (ω_l the mean |w_l| over channels), the block's
    energy-centroid direction and ω-mean intensity, and its summed weights."""
    nt, npf = lights.grid
    k = int(step)
    mt, mp = nt // k, npf // k
    idx = np.arange(nt * npf).reshape(mp, k, mt, k).transpose(0, 2, 1, 3).reshape(mp * mt, k * k)
    om = np.abs(w).mean(axis=1)[idx]
    tot = om.sum(axis=1)
    keep = tot > 0
    idx, om, tot = idx[keep], om[keep], tot[keep]
    share = om / tot[:, None]
    d = np.einsum("bm,bmi->bi", share, lights.directions[idx])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    E = np.einsum("bm,bmc->bc", share, lights.intensities[idx])
    wq = w[idx].sum(axis=1)
    starts = np.arange(0, idx.size + 1, k * k, dtype=np.int64)
    c = np.ascontiguousarray
    return (c(idx.ravel(), np.int64), starts, c(share.ravel(), np.float64), c(d, np.float64),
            c(E, np.float64), c(wq, np.float64))


def _cone_margin(lights) -> float:
    """The largest angle (radians) between a direction and the nodes its interpolation on the
    light set reads: ``2π/n_θ + π/n_φ`` on the grid (a path along the meridian, then the
    parallel, within one cell); 4 (> π: no cone) for a free light list, whose 3 nearest
    lights can be arbitrarily far."""
    if lights.grid is None:
        return 4.0
    nt, npf = lights.grid
    return 2.0 * np.pi / nt + np.pi / npf


def view_independent(fit, *, specular_skip: float = SPECULAR_SKIP):
    """The fit's functions transformed to the view-independent form v = n (Fig. 12 e).

    Returns a copy of ``fit`` whose view is the normal and whose diffuse and specular
    components are those resynthesised for v_n = n; resynthesis from it no longer needs v_0.
    """
    r = resynthesize(fit, fit.normal, specular_skip=specular_skip)
    return replace(fit, view=fit.normal.copy(), diffuse=r.diffuse, specular=r.specular,
                   flags=r.flags)

