"""The synthetic generator's own skin BRDF: a Torrance–Sparrow lobe plus an energy-weighted
diffuse term whose colour shifts toward grazing angles.

This is **not** the fitting model of Debevec et al. 2000, §4. The generator renders its ground
truth with it *deliberately mismatched* to that model, so that the fitting stage is tested
against a truth it cannot reproduce by construction; the paper's exact Eq. (6)–(7) chromaticity
ramp lives in ``facegeo.appearance.skin`` (the skin-model stage). The Torrance–Sparrow pieces
(:func:`fresnel_dielectric`, :func:`beckmann_distribution`, :func:`torrance_sparrow_geometry`)
are the standard ones and are shared with that model.

Every function works on unit direction vectors ``(..., 3)`` in one common frame (any frame, as
long as ``n``, ``l`` and ``v`` share it) and broadcasts over leading axes:

* ``n`` — surface normal, outward;
* ``l`` — toward the light (incident direction, angle θ_i to ``n``);
* ``v`` — toward the viewer (reflected direction, angle θ_r to ``n``);
* ``h = (l + v)/|l + v|`` — the half vector, at angle θ_h to ``n`` and θ_d to ``l`` and ``v``.

The model, per colour channel c (linear RGB)::

    f_c   = f_d,c + f_s                                                         (1/sr)
    f_s   = ρ_s F(θ_d) D(θ_h) G / (4 cos θ_i cos θ_r)            Torrance–Sparrow (D&J 2006 Eq. 1)
    f_d,c = T(θ_i) T(θ_r) · [α_0,c cos θ_i cos θ_r + α_1,c (1 − cos θ_i cos θ_r)] / π
    T(θ)  = 1 − ρ_dr(θ),   ρ_dr(θ) = ∫ f_s(l, v) cos θ_i dω_i  with v at angle θ   (D&J 2006 Eq. 2)

with F the exact unpolarised Fresnel reflectance of a dielectric of index η, D the Beckmann
microfacet distribution of RMS slope m and G the Torrance–Sparrow (V-cavity) shadowing and
masking term. The diffuse term is the generator's own colour blend — an RGB mix of α_0 and α_1
that changes brightness as well as chroma, unlike the paper's Eq. (6)–(7) — weighted, as
Donner & Jensen 2006 weight their subsurface term, by the energy the specular lobe leaves
(1 − ρ_dr) on the way in *and* on the way out (the product keeps Helmholtz reciprocity).
ρ_dr is tabulated once per η (:func:`specular_albedo`), so the model is defined by that table.

Energy: the directional albedo ``a(v) = ∫ f cos θ_i dω_i`` is
``ρ_dr(v) + T(v) ∫ T(l) ramp cos θ_i/π dω_i ≤ ρ_dr(v) + (1 − ρ_dr(v)) max(α_0, α_1) ≤ 1`` for
α ≤ 1 and ρ_s ≤ 1 (the unweighted sum reached 1.43 at grazing view; ``tests/test_brdf.py``
checks the bound numerically). ``f`` is zero when the light or the viewer is at or below the
horizon (``n·l <= 0`` or ``n·v <= 0``), where a BRDF is undefined; grazing inputs give finite
values (never NaN or inf); NaN inputs to the unchecked kernel give NaN (never a silent 0).

Radiometry (DESIGN §3): :func:`olat_radiance` is the radiance one OLAT pixel holds under a light
that delivers irradiance E at normal incidence, ``L_r = f · max(0, n·l) · E``; with that
normalisation Σ_l R_l L_l δA_l approximates ∫ f L cos θ_i dω (Debevec et al. 2000, Eq. 4).

References
----------
.. [1] P. Debevec, T. Hawkins, C. Tchou, H.-P. Duiker, W. Sarokin, M. Sagar, "Acquiring the
   Reflectance Field of a Human Face", SIGGRAPH 2000, §4 (the specular lobe; the grazing
   desaturation this generator imitates).
.. [2] C. Donner, H. W. Jensen, "A Spectral BSSRDF for Shading Human Skin", EGSR 2006,
   Eqs. 1–2 (Torrance–Sparrow surface term; the (1 − ρ_dr) weight of the diffuse term).
.. [3] K. E. Torrance, E. M. Sparrow, "Theory for off-specular reflection from roughened
   surfaces", JOSA 57(9), 1967.
.. [4] R. L. Cook, K. E. Torrance, "A reflectance model for computer graphics", ACM TOG 1(1),
   1982 (exact Fresnel form, Beckmann distribution, G term).
.. [5] P. Beckmann, A. Spizzichino, *The Scattering of Electromagnetic Waves from Rough
   Surfaces*, 1963.
"""

from __future__ import annotations

import functools

import numpy as np

from facegeo.checks import as_array, check_unit_vectors, fmt_value
from facegeo.errors import InputError

__all__ = [
    "ETA_SKIN",
    "lambertian_equivalent_albedo",
    "REC709_LUMINANCE",
    "COS_FLOOR",
    "fresnel_dielectric",
    "beckmann_distribution",
    "torrance_sparrow_geometry",
    "specular_brdf",
    "specular_albedo",
    "RHO_DR_M_RANGE",
    "grazing_colour_blend",
    "synthetic_diffuse_brdf",
    "synthetic_skin_brdf",
    "synthetic_skin_brdf_unchecked",
    "olat_radiance",
    "desaturate",
]

#: Index of refraction of the skin surface (oily stratum corneum) for the Fresnel term.
ETA_SKIN = 1.4

#: Rec. 709 / linear-sRGB relative luminance weights (R, G, B).
REC709_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])

#: Floor on the product cos θ_i · cos θ_r in the Torrance–Sparrow denominator (see
#: :func:`specular_brdf`): the bound is active only when *both* directions lie within
#: ≈ 89.4° of the normal's horizon (geometric-mean cosine < 0.01).
COS_FLOOR = 1e-4

#: Tolerance on |n|, |l|, |v| − 1 for the direction arguments.
UNIT_TOL = 1e-6

_TINY = 1e-300  # guards divisions whose result is masked out anyway


# --------------------------------------------------------------------------- validation


def _eta(eta) -> float:
    try:
        e = float(eta)
    except (TypeError, ValueError) as exc:
        raise InputError(f"eta: expected a number > 1, got {fmt_value(eta)}") from exc
    if not np.isfinite(e) or e <= 1.0:
        raise InputError(
            f"eta: expected a finite index of refraction > 1 (skin ≈ 1.4), got {fmt_value(eta)}"
        )
    return e


def _roughness(m) -> np.ndarray:
    m = as_array(m, "m")
    if np.any(m <= 0):
        raise InputError(
            f"m: Beckmann RMS slope must be > 0 everywhere; min is {float(np.min(m)):.6g}"
        )
    return m


def _nonnegative(x, name: str) -> np.ndarray:
    a = as_array(x, name)
    if np.any(a < 0):
        raise InputError(f"{name}: must be >= 0 everywhere; min is {float(np.min(a)):.6g}")
    return a


def _colour(x, name: str) -> np.ndarray:
    return as_array(x, name, shape=(..., 3))


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _unit(x, name: str) -> np.ndarray:
    """``(..., 3)`` unit vectors to within UNIT_TOL (same contract as ``check_unit_vectors``)."""
    a = as_array(x, name, shape=(..., 3))
    err = np.abs(_dot(a, a) - 1.0)
    if np.any(err > 2.0 * UNIT_TOL):
        return check_unit_vectors(a, name, tol=UNIT_TOL)  # raises with the offending index
    return a


def _directions(n, l, v):
    return _unit(n, "n"), _unit(l, "l"), _unit(v, "v")


# --------------------------------------------------------------------------- specular terms


def fresnel_dielectric(cos_d, eta: float = ETA_SKIN) -> np.ndarray:
    """Exact unpolarised Fresnel reflectance of a dielectric, F(θ_d).

    Implements the exact Fresnel equations averaged over the s and p polarisations, in the form
    of Cook & Torrance 1982::

        g = sqrt(η² − 1 + c²),  c = cos θ_d
        F = ½ (g − c)²/(g + c)² · [1 + ((c (g + c) − 1)/(c (g − c) + 1))²]

    the Fresnel term of the Torrance–Sparrow lobe in Debevec et al. 2000, §4.

    Parameters
    ----------
    cos_d : array_like (...) float64, dimensionless
        Cosine of the angle between the light (or view) direction and the half vector,
        ``l·h = v·h``. Values are clipped to [0, 1].
    eta : float
        Relative index of refraction, > 1 (1.4 for skin).

    Returns
    -------
    (...) float64, dimensionless
        Reflectance in [((η−1)/(η+1))², 1]: exactly ((η−1)/(η+1))² at cos_d = 1 and 1 at
        cos_d = 0 (grazing), monotonically decreasing in cos_d. Always finite: ``g ≥ √(η²−1) > 0``
        and ``c (g − c) + 1 ≥ 1`` for c ∈ [0, 1].
    """
    eta = _eta(eta)
    c = np.clip(as_array(cos_d, "cos_d"), 0.0, 1.0)
    g = np.sqrt(eta * eta - 1.0 + c * c)
    a = (g - c) / (g + c)
    b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
    return 0.5 * a * a * (1.0 + b * b)


def beckmann_distribution(cos_h, m) -> np.ndarray:
    """Beckmann microfacet distribution D(θ_h).

    Implements ``D = exp(−tan²θ_h / m²) / (π m² cos⁴θ_h)`` (Beckmann & Spizzichino 1963, in the
    normalisation of Cook & Torrance 1982), normalised so that ``∫ D cos θ_h dω_h = 1`` over the
    hemisphere: D is a density of microfacet normals per unit projected area.

    Parameters
    ----------
    cos_h : array_like (...) float64, dimensionless
        ``n·h``, cosine of the angle between the normal and the half vector.
    m : array_like (...) float64, dimensionless, > 0
        RMS microfacet slope (roughness); broadcasts with ``cos_h``.

    Returns
    -------
    (...) float64, 1/sr
        D, exactly 0 for ``cos_h <= 0`` (and, by underflow of the exponential, for
        ``cos_h`` below ~1e-8 whatever m); finite everywhere.
    """
    c = np.clip(as_array(cos_h, "cos_h"), 0.0, 1.0)
    m = _roughness(m)
    ok = c > 1e-8
    c_safe = np.where(ok, c, 1.0)
    c2 = c_safe * c_safe
    tan2 = (1.0 - c2) / c2
    m2 = m * m
    d = np.exp(-tan2 / m2) / (np.pi * m2 * c2 * c2)
    return np.where(ok, d, 0.0)


def torrance_sparrow_geometry(n_dot_l, n_dot_v, n_dot_h, v_dot_h) -> np.ndarray:
    """Torrance–Sparrow (V-cavity) shadowing/masking term G.

    Implements ``G = min(1, 2 (n·h)(n·v)/(v·h), 2 (n·h)(n·l)/(v·h))`` (Torrance & Sparrow 1967,
    in the form of Cook & Torrance 1982), the G of the specular lobe in Debevec et al. 2000, §4.

    Parameters
    ----------
    n_dot_l, n_dot_v, n_dot_h, v_dot_h : array_like (...) float64, dimensionless
        Cosines; broadcast together. Negative cosines are clipped to 0.

    Returns
    -------
    (...) float64, dimensionless, in [0, 1]
        G. Symmetric in ``n_dot_l`` and ``n_dot_v`` (Helmholtz reciprocity). At ``v·h = 0``
        (only possible for ``l = −v``) the two ratios are taken as +inf, so G = 1 when
        ``n·h > 0`` and 0 otherwise — finite, never NaN.
    """
    nl = np.clip(as_array(n_dot_l, "n_dot_l"), 0.0, None)
    nv = np.clip(as_array(n_dot_v, "n_dot_v"), 0.0, None)
    nh = np.clip(as_array(n_dot_h, "n_dot_h"), 0.0, None)
    vh = np.clip(as_array(v_dot_h, "v_dot_h"), 0.0, None)
    pos = vh > 0
    inv_vh = np.where(pos, 1.0 / np.where(pos, vh, 1.0), np.inf)
    with np.errstate(invalid="ignore"):
        g_v = np.nan_to_num(2.0 * nh * nv * inv_vh, nan=0.0, posinf=np.inf)
        g_l = np.nan_to_num(2.0 * nh * nl * inv_vh, nan=0.0, posinf=np.inf)
    return np.minimum(1.0, np.minimum(g_v, g_l))


def _half_angle_cosines(nl, nv, l, v):
    """``cos θ_h = n·h`` and ``cos θ_d = v·h`` from ``l + v`` without normalising h.

    ``|l + v| = 2 cos θ_d`` and ``n·h = (n·l + n·v)/|l + v|``; both are exactly symmetric in
    (l, v), which makes the specular lobe reciprocal to rounding.
    """
    s = l + v
    two_cos_d = np.sqrt(_dot(s, s))
    cos_d = 0.5 * two_cos_d
    cos_h = (nl + nv) / np.maximum(two_cos_d, _TINY)
    return np.clip(cos_h, 0.0, 1.0), np.clip(cos_d, 0.0, 1.0)


def _specular_unchecked(nl, nv, cos_h, cos_d, rho_s, m, eta):
    """Torrance–Sparrow value from cosines, zero below the horizon (no validation)."""
    ok = (nl > 0) & (nv > 0) & (cos_h > 1e-8)
    nl_s = np.where(ok, nl, 1.0)
    nv_s = np.where(ok, nv, 1.0)
    ch = np.where(ok, cos_h, 1.0)
    # G / (4 n·l n·v) = min(1/(4 n·l n·v), n·h/(2 v·h n·l), n·h/(2 v·h n·v)): three finite
    # ratios; the first is the only one that diverges (both directions grazing, G = 1) and is
    # bounded by COS_FLOOR. min(t/n·l, t/n·v) = t/max(n·l, n·v) keeps it symmetric.
    t = ch / (2.0 * np.maximum(cos_d, _TINY))
    g_over = np.minimum(0.25 / np.maximum(nl_s * nv_s, COS_FLOOR), t / np.maximum(nl_s, nv_s))
    # Fresnel (Cook & Torrance 1982 form), as in fresnel_dielectric.
    c = cos_d
    g = np.sqrt(eta * eta - 1.0 + c * c)
    a = (g - c) / (g + c)
    b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
    F = 0.5 * a * a * (1.0 + b * b)
    # Beckmann, as in beckmann_distribution.
    ch2 = ch * ch
    m2 = m * m
    D = np.exp((ch2 - 1.0) / (ch2 * m2)) / (np.pi * m2 * ch2 * ch2)
    return np.where(ok, rho_s * F * D * g_over, 0.0)


def specular_brdf(n, l, v, rho_s, m, eta: float = ETA_SKIN) -> np.ndarray:
    """Torrance–Sparrow specular BRDF of skin, f_s (the colour of the light).

    Implements the specular lobe of the skin model of Debevec et al. 2000, §4 (Torrance &
    Sparrow 1967 in the form of Cook & Torrance 1982)::

        f_s = ρ_s F(θ_d) D(θ_h) G / (4 cos θ_i cos θ_r)

    with F from :func:`fresnel_dielectric`, D from :func:`beckmann_distribution` and G from
    :func:`torrance_sparrow_geometry`. ρ_s is a dimensionless scale on the physical Fresnel
    term (ρ_s = 1: a clean dielectric of index η).

    Deviation at grazing angles (DESIGN §7): ``G / (4 cos θ_i cos θ_r)`` is evaluated as
    ``min(1/(4 max(cos θ_i cos θ_r, COS_FLOOR)), cos θ_h/(2 cos θ_d cos θ_i),
    cos θ_h/(2 cos θ_d cos θ_r))``, which equals the textbook ratio whenever
    ``cos θ_i cos θ_r >= COS_FLOOR`` (1e-4) and stays finite as either cosine → 0 (the G terms
    cancel the vanishing cosine exactly). Only the first ratio, reached when both directions
    graze in the mirror configuration, is bounded. The result is exactly symmetric in
    ``l`` and ``v``.

    Parameters
    ----------
    n, l, v : array_like (..., 3) float64, unit vectors, common frame
        Normal, direction to the light, direction to the viewer; broadcast together.
    rho_s : array_like (...) float64, dimensionless, >= 0
        Specular scale.
    m : array_like (...) float64, dimensionless, > 0
        Beckmann RMS slope.
    eta : float
        Index of refraction (> 1).

    Returns
    -------
    (...) float64, 1/sr
        f_s, 0 where ``n·l <= 0`` or ``n·v <= 0``; finite everywhere.
    """
    n, l, v = _directions(n, l, v)
    return _specular_from_directions(n, l, v, _nonnegative(rho_s, "rho_s"), _roughness(m),
                                     _eta(eta))


def _specular_from_directions(n, l, v, rho_s, m, eta):
    nl = _dot(n, l)
    nv = _dot(n, v)
    cos_h, cos_d = _half_angle_cosines(nl, nv, l, v)
    return _specular_unchecked(nl, nv, cos_h, cos_d, rho_s, m, eta)


# --------------------------------------------------------------------------- ρ_dr table

#: Roughness range [m_min, m_max] of the ρ_dr table; outside it the diffuse weight uses the
#: nearest tabulated m (energy conservation is tested inside this range).
RHO_DR_M_RANGE = (0.05, 1.0)
_RHO_DR_N_MU = 65  # view-cosine nodes, uniform in sqrt(μ) (dense toward grazing)
_RHO_DR_N_M = 16  # roughness nodes, uniform in log m
_RHO_DR_QUAD = 64  # graded Gauss–Legendre nodes per axis of the hemisphere quadrature
_RHO_DR_MU_MIN = 1e-7  # the μ = 0 node is evaluated here (the grazing limit, not 0)


def _graded_gauss(n: int, p: int = 3):
    """Gauss–Legendre nodes/weights on [0, 1] under t → t**p (dense near 0)."""
    x, w = np.polynomial.legendre.leggauss(n)
    t = 0.5 * (x + 1.0)
    return t**p, p * t ** (p - 1) * 0.5 * w


@functools.lru_cache(maxsize=4)
def _rho_dr_table(eta: float):
    """``(sqrt(μ) nodes, log m nodes, table (n_m, n_mu))``: ρ_dr per unit ρ_s, read-only."""
    s_nodes = np.linspace(0.0, 1.0, _RHO_DR_N_MU)
    mu_v = np.maximum(s_nodes**2, _RHO_DR_MU_MIN)
    logm = np.linspace(np.log(RHO_DR_M_RANGE[0]), np.log(RHO_DR_M_RANGE[1]), _RHO_DR_N_M)
    # Hemisphere of l around n = e_z: μ_l graded toward the horizon, azimuth graded toward the
    # mirror azimuth π (φ → −φ symmetry doubles the weights). v in the xz plane at azimuth 0.
    mu, w_mu = _graded_gauss(_RHO_DR_QUAD)
    t, w_t = _graded_gauss(_RHO_DR_QUAD)
    phi = np.pi * (1.0 - t)
    MU, PHI = np.meshgrid(mu, phi, indexing="ij")
    sn = np.sqrt(1.0 - MU**2)
    l = np.stack([sn * np.cos(PHI), sn * np.sin(PHI), MU], -1)
    W = 2.0 * MU * w_mu[:, None] * (np.pi * w_t)[None, :]
    v = np.stack([np.sqrt(1.0 - mu_v**2), np.zeros_like(mu_v), mu_v], -1)[:, None, None, :]
    nl = MU[None]
    nv = mu_v[:, None, None]
    cos_h, cos_d = _half_angle_cosines(nl, nv, l[None], v)
    table = np.empty((_RHO_DR_N_M, _RHO_DR_N_MU))
    for k, lm in enumerate(logm):  # 16 roughness values: one vectorised quadrature each
        f = _specular_unchecked(nl, nv, cos_h, cos_d, 1.0, np.exp(lm), eta)
        table[k] = np.sum(f * W, axis=(1, 2))
    for a in (s_nodes, logm, table):
        a.setflags(write=False)
    return s_nodes, logm, table


def _m_weights(m, logm):
    """Row index and weight of roughness ``m`` in the table (log-uniform nodes, clamped)."""
    lm = np.log(np.clip(m, RHO_DR_M_RANGE[0], RHO_DR_M_RANGE[1]))
    y = (lm - logm[0]) * (1.0 / (logm[1] - logm[0]))
    with np.errstate(invalid="ignore"):  # NaN inputs: any index; the NaN propagates via fy
        j = np.clip(y.astype(np.intp), 0, len(logm) - 2)
    return j, y - j


def _interp_mu(table, j, fy, mu):
    """Bilinear table value at (sqrt(μ), row j + fy); μ clipped to [0, 1]."""
    n_mu = table.shape[1]
    x = np.sqrt(np.clip(mu, 0.0, 1.0)) * (n_mu - 1)
    with np.errstate(invalid="ignore"):
        i = np.clip(x.astype(np.intp), 0, n_mu - 2)
    fx = x - i
    flat = table.ravel()
    k = j * n_mu + i
    t0 = flat[k] + fx * (flat[k + 1] - flat[k])
    k = k + n_mu
    t1 = flat[k] + fx * (flat[k + 1] - flat[k])
    return t0 + fy * (t1 - t0)


def _rho_dr_unchecked(mu, m, eta):
    """Bilinear interpolation of the ρ_dr table in (sqrt(μ), log m); μ clipped to [0, 1]."""
    _, logm, table = _rho_dr_table(float(eta))
    j, fy = _m_weights(m, logm)
    return _interp_mu(table, j, fy, mu)


def specular_albedo(cos_theta, rho_s, m, eta: float = ETA_SKIN) -> np.ndarray:
    """ρ_dr(θ): directional albedo of the Torrance–Sparrow lobe, from its table.

    Implements Donner & Jensen 2006 Eq. (2), ``ρ_dr(v) = ∫ f_s(l, v) cos θ_i dω_i`` over the
    hemisphere (equal to the albedo for light arriving from θ, by reciprocity). ρ_dr is linear
    in ρ_s; ρ_dr/ρ_s is tabulated once per η on 65 view cosines (uniform in √μ) × 16 roughness
    values (log-uniform on :data:`RHO_DR_M_RANGE`) by a 64 × 64 graded Gauss–Legendre
    quadrature, and interpolated bilinearly in (√μ, log m). Deviation: at μ = 0 the table holds
    the grazing limit (evaluated at μ = 1e-7), not the 0 the BRDF takes on the horizon; m is
    clamped to :data:`RHO_DR_M_RANGE`. Table + interpolation error, measured against a
    384 × 384 quadrature in ``tests/test_brdf.py``: ≤ 1e-3 absolute for m in [0.25, 0.5]
    (the generator's range), larger for the sharpest lobes.

    Parameters
    ----------
    cos_theta : array_like (...) float64, dimensionless
        cos θ of the view (or light) direction to the normal; clipped to [0, 1].
    rho_s : array_like (...) float64, >= 0
    m : array_like (...) float64, > 0
    eta : float, > 1

    Returns
    -------
    (...) float64, dimensionless
        ρ_dr, in [0, ρ_s).
    """
    mu = as_array(cos_theta, "cos_theta")
    rho_s = _nonnegative(rho_s, "rho_s")
    m = _roughness(m)
    return rho_s * _rho_dr_unchecked(mu, m, _eta(eta))


# --------------------------------------------------------------------------- diffuse term


def grazing_colour_blend(alpha_0, alpha_1, cos_i, cos_r) -> np.ndarray:
    """The generator's diffuse colour blend, ``α_0 cos θ_i cos θ_r + α_1 (1 − cos θ_i cos θ_r)``.

    An RGB mix from α_0 at normal incidence and view to α_1 at grazing angles, imitating the
    desaturation toward grazing that Debevec et al. 2000, §4 observed. Deliberately **not** the
    paper's Eq. (6)–(7) ramp (that one changes chroma only; this one also changes brightness),
    so that a fit of the paper's model meets a mismatched truth.

    Parameters
    ----------
    alpha_0, alpha_1 : array_like (..., 3) float64, linear RGB, dimensionless
        Colour at normal incidence and view, and at grazing angles.
    cos_i, cos_r : array_like (...) float64, dimensionless
        cos θ_i = n·l and cos θ_r = n·v; clipped to [0, 1].

    Returns
    -------
    (..., 3) float64, dimensionless
        The blend (not yet divided by π). Symmetric in (cos_i, cos_r).
    """
    a0 = _colour(alpha_0, "alpha_0")
    a1 = _colour(alpha_1, "alpha_1")
    ci = np.clip(as_array(cos_i, "cos_i"), 0.0, 1.0)
    cr = np.clip(as_array(cos_r, "cos_r"), 0.0, 1.0)
    w = (ci * cr)[..., None]
    return a0 * w + a1 * (1.0 - w)


def _diffuse_unchecked(nl, nv, a0, a1, rho_s, m, eta):
    valid = ((nl > 0) & (nv > 0))[..., None]
    ci = np.clip(nl, 0.0, 1.0)
    cr = np.clip(nv, 0.0, 1.0)
    w = (ci * cr)[..., None]
    # T(θ_i) T(θ_r): the energy the specular lobe leaves (D&J 2006 Eq. 2), clipped at 0 for
    # ρ_s > 1/ρ_dr (outside the generator's range). The roughness row is found once for both.
    _, logm, table = _rho_dr_table(float(eta))
    j, fy = _m_weights(m, logm)
    t_io = (np.clip(1.0 - rho_s * _interp_mu(table, j, fy, ci), 0.0, 1.0)
            * np.clip(1.0 - rho_s * _interp_mu(table, j, fy, cr), 0.0, 1.0))[..., None]
    return np.where(valid, t_io * (a0 * w + a1 * (1.0 - w)) / np.pi, 0.0)


def lambertian_equivalent_albedo(n, v, alpha_0, alpha_1, rho_s, m, directions, solid_angles,
                                 eta: float = ETA_SKIN, *, block: int = 512) -> np.ndarray:
    """The albedo a Lambertian lobe fitted to the generator's diffuse term returns.

    The generator's diffuse term (:func:`synthetic_diffuse_brdf`) is not Lambertian (its
    Fresnel weights and colour blend change with angle), so its α_0 (the colour at normal
    incidence and view) is not the albedo of the paper's Lambertian lobe (§4.2, Fig. 14 c): on
    the small preset they differ by 7.4 % (median). This is the least-squares fit of
    ``ρ/π · cos θ_i`` to ``f_d cos θ_i`` over the lit lights with the Eq. 4 weights δA,

        ρ = π Σ_l δA_l x_l² f_d(l) / Σ_l δA_l x_l²,   x_l = max(n·ω_l, 0),

    per channel: the reference a perfect diffuse fit reaches.

    Parameters
    ----------
    n, v : (N, 3) float64, unit — normal, toward the camera
    alpha_0, alpha_1 : (N, 3) float64; rho_s, m : (N,) float64 — the generator's parameters
    directions : (L, 3) float64, unit; solid_angles : (L,) float64 — the lights
    eta : float
    block : int — functions per block (bounds the (block, L, 3) temporaries)

    Returns
    -------
    (N, 3) float64 — 0 for a function no light reaches
    """
    n = np.asarray(n, np.float64)
    v = np.asarray(v, np.float64)
    N, L = n.shape[0], len(directions)
    out = np.zeros((N, 3))
    for s in range(0, N, int(block)):
        sl = slice(s, min(N, s + int(block)))
        k = sl.stop - s
        x = np.maximum(n[sl] @ np.asarray(directions, np.float64).T, 0.0)
        nv = np.broadcast_to(_dot(n[sl], v[sl])[:, None], (k, L))
        fd = _diffuse_unchecked(
            x, nv, np.broadcast_to(np.asarray(alpha_0, np.float64)[sl, None, :], (k, L, 3)),
            np.broadcast_to(np.asarray(alpha_1, np.float64)[sl, None, :], (k, L, 3)),
            np.broadcast_to(np.asarray(rho_s, np.float64)[sl, None], (k, L)),
            np.broadcast_to(np.asarray(m, np.float64)[sl, None], (k, L)), float(eta))
        wx = np.asarray(solid_angles, np.float64) * x * x
        den = wx.sum(axis=1)
        out[sl] = np.pi * np.einsum("nl,nlc->nc", wx, fd) / np.where(den > 0, den, 1.0)[:, None]
    return out


def synthetic_diffuse_brdf(n, l, v, alpha_0, alpha_1, rho_s, m, eta: float = ETA_SKIN
                           ) -> np.ndarray:
    """Diffuse part of the generator's skin BRDF: the colour blend weighted by (1 − ρ_dr)².

    Implements ``f_d = T(θ_i) T(θ_r) · blend/π`` with the blend of
    :func:`grazing_colour_blend` and ``T = 1 − ρ_dr`` from :func:`specular_albedo`
    (Donner & Jensen 2006 Eqs. 1–2; see the module docstring). With ρ_s = 0 (T = 1) it is
    exactly α_0/π at normal incidence and view and its directional albedo is
    ``α_1 + ⅔ cos θ_r (α_0 − α_1)``.

    Parameters
    ----------
    n, l, v : array_like (..., 3) float64, unit vectors, common frame
    alpha_0, alpha_1 : array_like (..., 3) float64, linear RGB, dimensionless
    rho_s : array_like (...) float64, >= 0
        Specular scale (sets how much energy the lobe takes first).
    m : array_like (...) float64, > 0
        Beckmann RMS slope.
    eta : float, > 1

    Returns
    -------
    (..., 3) float64, 1/sr
        f_d, 0 where ``n·l <= 0`` or ``n·v <= 0``.
    """
    n, l, v = _directions(n, l, v)
    return _diffuse_unchecked(_dot(n, l), _dot(n, v), _colour(alpha_0, "alpha_0"),
                              _colour(alpha_1, "alpha_1"), _nonnegative(rho_s, "rho_s"),
                              _roughness(m), _eta(eta))


# --------------------------------------------------------------------------- full model


def synthetic_skin_brdf(n, l, v, alpha_0, alpha_1, rho_s, m, eta: float = ETA_SKIN
                        ) -> np.ndarray:
    """The generator's skin BRDF: energy-weighted diffuse colour blend plus white specular lobe.

    Implements ``f = f_d + f_s · (1, 1, 1)``: :func:`synthetic_diffuse_brdf` plus
    :func:`specular_brdf` (the specular reflection has the colour of the light). Not the
    paper's §4 fitting model (module docstring); directional albedo ≤ 1 for α ≤ 1, ρ_s ≤ 1.

    Parameters
    ----------
    n, l, v : array_like (..., 3) float64, unit vectors, common frame
        Normal, toward the light, toward the viewer.
    alpha_0, alpha_1 : array_like (..., 3) float64, linear RGB, dimensionless
        Diffuse colour at normal incidence/view and at grazing angles.
    rho_s : array_like (...) float64, dimensionless, >= 0
        Specular scale on the Fresnel term.
    m : array_like (...) float64, dimensionless, > 0
        Beckmann RMS slope.
    eta : float
        Index of refraction (> 1).

    Returns
    -------
    (..., 3) float64, 1/sr
        f per RGB channel; 0 below either horizon; finite everywhere.
    """
    n, l, v = _directions(n, l, v)
    return synthetic_skin_brdf_unchecked(
        n, l, v, _colour(alpha_0, "alpha_0"), _colour(alpha_1, "alpha_1"),
        _nonnegative(rho_s, "rho_s"), _roughness(m), _eta(eta))


def synthetic_skin_brdf_unchecked(n, l, v, alpha_0, alpha_1, rho_s, m,
                                  eta: float = ETA_SKIN) -> np.ndarray:
    """:func:`synthetic_skin_brdf` without input validation, for hot loops over checked data.

    The caller guarantees what :func:`synthetic_skin_brdf` checks: ``n, l, v`` unit
    ``(..., 3)`` arrays, finite colours, ``rho_s >= 0``, ``m > 0``, ``eta > 1``; results are
    then identical. A NaN anywhere in a sample's inputs (direction, colour, ρ_s, m) gives NaN
    in all three channels of that sample — never a silent 0 — so a caller's missed check shows.
    """
    nl = _dot(n, l)
    nv = _dot(n, v)
    cos_h, cos_d = _half_angle_cosines(nl, nv, l, v)
    spec = _specular_unchecked(nl, nv, cos_h, cos_d, rho_s, m, eta)
    f = _diffuse_unchecked(nl, nv, alpha_0, alpha_1, rho_s, m, eta) + spec[..., None]
    bad = np.isnan(nl + nv + rho_s + m)[..., None] | np.isnan(alpha_0 + alpha_1)
    if np.any(bad):
        f = np.where(np.any(bad, axis=-1, keepdims=True), np.nan, f)
    return f


def olat_radiance(
    n, l, v, alpha_0, alpha_1, rho_s, m, eta: float = ETA_SKIN, irradiance=1.0
) -> np.ndarray:
    """Radiance reflected toward ``v`` under one distant light: what one OLAT pixel holds.

    Implements ``L_r = f(l, v) · max(0, n·l) · E`` with f from :func:`synthetic_skin_brdf` and E the
    irradiance the light delivers at normal incidence (DESIGN §3 radiometry). With this
    normalisation Σ_l R_l L_l δA_l approximates ∫ f L cos θ_i dω, Debevec et al. 2000, Eq. 4.
    Shadowing by other geometry is not modelled here (the renderer decides visibility).

    Parameters
    ----------
    n, l, v, alpha_0, alpha_1, rho_s, m, eta
        As in :func:`synthetic_skin_brdf`.
    irradiance : float or array_like broadcastable to (..., 3), W/m² (or any linear unit)
        E at normal incidence, per channel if given with a trailing axis of 3; use
        ``E[..., None]`` for a per-sample grey irradiance.

    Returns
    -------
    (..., 3) float64, radiance in the unit of E per sr
        0 where the light or viewer is below the horizon.
    """
    E = _nonnegative(irradiance, "irradiance")
    n_ = _unit(n, "n")
    l_ = _unit(l, "l")
    f = synthetic_skin_brdf(n_, l_, v, alpha_0, alpha_1, rho_s, m, eta)
    cos_i = np.clip(_dot(n_, l_), 0.0, None)[..., None]
    return f * cos_i * E


def desaturate(alpha_0, amount) -> np.ndarray:
    """Make a grazing colour α_1 by mixing α_0 toward its luminance.

    ``α_1 = (1 − a) α_0 + a Y(α_0) (1, 1, 1)`` with ``Y = 0.2126 R + 0.7152 G + 0.0722 B``
    (Rec. 709 linear luminance). Keeps the luminance of α_0; a = 0 returns α_0, a = 1 grey.
    This helper only builds plausible ground truth for the generator's own colour blend.

    Parameters
    ----------
    alpha_0 : array_like (..., 3) float64, linear RGB
    amount : float or array_like (...) float64, in [0, 1]

    Returns
    -------
    (..., 3) float64, linear RGB
    """
    a0 = _colour(alpha_0, "alpha_0")
    a = as_array(amount, "amount")
    if np.any((a < 0) | (a > 1)):
        raise InputError(
            f"amount: expected values in [0, 1], got min {a.min():.6g}, max {a.max():.6g}"
        )
    Y = a0 @ REC709_LUMINANCE
    a = a[..., None]
    return (1.0 - a) * a0 + a * Y[..., None]
