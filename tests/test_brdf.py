"""Tests of facegeo.appearance.brdf: the synthetic generator's own skin BRDF (Torrance–Sparrow
plus an energy-weighted diffuse colour blend; deliberately not the paper's §4 fitting model)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate
from scipy.spatial.transform import Rotation

from facegeo.appearance import brdf
from facegeo.errors import InputError, ShapeError

# Named tolerances (dimensionless unless stated).
REL_TOL_REFERENCE = 1e-10  # vector code vs the angle-based reference, relative
REL_TOL_RECIPROCITY = 1e-12  # f(l, v) vs f(v, l), relative
TOL_BECKMANN_NORM = 1e-4  # |∫ D cos θ_h dω − 1|
TOL_QUADRATURE = 2e-4  # directional albedo quadrature error (checked against 2× finer grid)
TOL_DIFFUSE_ALBEDO = 1e-12  # diffuse-ramp albedo vs analytic (quadrature exact for polynomials)
TOL_RHO_DR_TABLE = 1e-3  # max abs error of the ρ_dr table (m in the generator's 0.25–0.5)
TOL_RHO_DR_TABLE_SHARP = 5e-3  # the same for m down to RHO_DR_M_RANGE[0] = 0.05

ETA = 1.4
ALPHA_0 = np.array([0.45, 0.30, 0.23])  # linear-sRGB skin at normal incidence
ALPHA_1 = np.array([0.48, 0.40, 0.36])  # desaturated and a bit lighter at grazing


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _hemisphere(rng, n, size):
    """Random unit vectors with a positive component along the unit normal(s) ``n``."""
    d = _unit(rng.normal(size=size + (3,)))
    s = np.sign(np.sum(d * n, axis=-1, keepdims=True))
    return d * np.where(s == 0, 1.0, s)


# --------------------------------------------------------------------------- reference


def _reference_specular(theta_i, theta_r, phi, rho_s, m, eta):
    """Torrance–Sparrow from angles by spherical trigonometry (no vector code).

    θ_i, θ_r: polar angles of l and v from n; φ: azimuth between them. The angle 2θ_d between
    l and v follows the spherical law of cosines; cos θ_h = (cos θ_i + cos θ_r)/(2 cos θ_d)
    (projection of the bisector); Fresnel from Snell's law and the s/p amplitudes.
    """
    ci, cr = np.cos(theta_i), np.cos(theta_r)
    cos_2d = ci * cr + np.sin(theta_i) * np.sin(theta_r) * np.cos(phi)
    theta_d = 0.5 * np.arccos(np.clip(cos_2d, -1.0, 1.0))
    cd = np.cos(theta_d)
    ch = (ci + cr) / (2.0 * cd)
    theta_h = np.arccos(np.clip(ch, -1.0, 1.0))
    sin_t = np.sin(theta_d) / eta
    ct = np.sqrt(1.0 - sin_t**2)
    r_s = (cd - eta * ct) / (cd + eta * ct)
    r_p = (eta * cd - ct) / (eta * cd + ct)
    F = 0.5 * (r_s**2 + r_p**2)
    D = np.exp(-np.tan(theta_h) ** 2 / m**2) / (np.pi * m**2 * np.cos(theta_h) ** 4)
    G = np.minimum(1.0, np.minimum(2 * ch * cr / cd, 2 * ch * ci / cd))
    return rho_s * F * D * G / (4.0 * ci * cr)


def test_specular_matches_angle_reference():
    rng = np.random.default_rng(1)
    N = 2000
    theta_i = rng.uniform(0.0, np.radians(85), N)
    theta_r = rng.uniform(0.0, np.radians(85), N)
    phi = rng.uniform(0.0, 2 * np.pi, N)
    rho_s = rng.uniform(0.2, 1.0, N)
    m = rng.uniform(0.15, 0.6, N)
    # Local frame n = e_z, l in the xz plane; then a random rotation so no axis is special.
    R = Rotation.random(random_state=7).as_matrix()
    n_loc = np.array([0.0, 0.0, 1.0])
    l_loc = np.stack([np.sin(theta_i), np.zeros(N), np.cos(theta_i)], -1)
    v_loc = np.stack(
        [np.sin(theta_r) * np.cos(phi), np.sin(theta_r) * np.sin(phi), np.cos(theta_r)], -1
    )
    n, l, v = n_loc @ R.T, l_loc @ R.T, v_loc @ R.T
    got = brdf.specular_brdf(np.broadcast_to(n, (N, 3)), l, v, rho_s, m, eta=ETA)
    want = _reference_specular(theta_i, theta_r, phi, rho_s, m, ETA)
    tiny = want < 1e-200  # far off the lobe the Beckmann exponential underflows in both
    assert np.all(got[tiny] < 1e-200), "underflowed reference values are ~0 here too"
    rel = np.abs(got - want)[~tiny] / want[~tiny]
    assert rel.max() < REL_TOL_REFERENCE, f"max relative error {rel.max():.3g}"


def test_swapped_arguments_are_not_equivalent():
    # Asymmetric fixture: swapping n and l must change the value (guards argument order).
    n = _unit(np.array([0.1, 1.0, 0.2]))
    l = _unit(np.array([0.6, 0.7, 0.3]))
    v = _unit(np.array([-0.2, 0.8, 0.5]))
    a = brdf.specular_brdf(n, l, v, 1.0, 0.3)
    b = brdf.specular_brdf(l, n, v, 1.0, 0.3)
    assert abs(a - b) / a > 1e-3, "relative difference of f_s(n, l, v) and f_s(l, n, v)"


# --------------------------------------------------------------------------- reciprocity


def test_helmholtz_reciprocity():
    rng = np.random.default_rng(2)
    N = 5000
    n = _unit(rng.normal(size=(N, 3)))
    l = _hemisphere(rng, n, (N,))
    v = _hemisphere(rng, n, (N,))
    a0 = rng.uniform(0.05, 0.9, (N, 3))
    a1 = rng.uniform(0.05, 0.9, (N, 3))
    rho_s = rng.uniform(0.0, 1.0, N)
    m = rng.uniform(0.1, 0.8, N)
    f_lv = brdf.synthetic_skin_brdf(n, l, v, a0, a1, rho_s, m)
    f_vl = brdf.synthetic_skin_brdf(n, v, l, a0, a1, rho_s, m)
    rel = np.abs(f_lv - f_vl) / np.maximum(np.abs(f_lv), 1e-300)
    assert rel.max() <= REL_TOL_RECIPROCITY, f"max relative asymmetry {rel.max():.3g}"
    ramp = brdf.grazing_colour_blend(a0, a1, np.sum(n * l, -1), np.sum(n * v, -1))
    ramp_swapped = brdf.grazing_colour_blend(a0, a1, np.sum(n * v, -1), np.sum(n * l, -1))
    assert np.array_equal(ramp, ramp_swapped), "chroma ramp symmetric in (cos_i, cos_r), exact"


# --------------------------------------------------------------------------- Fresnel


def test_fresnel_endpoints_and_monotonic():
    f0 = ((ETA - 1) / (ETA + 1)) ** 2
    assert brdf.fresnel_dielectric(1.0, ETA) == pytest.approx(f0, rel=1e-14), "F(cos=1), rel"
    assert brdf.fresnel_dielectric(0.0, ETA) == pytest.approx(1.0, abs=1e-15), "F(cos=0), abs"
    c = np.linspace(0.0, 1.0, 10001)
    F = brdf.fresnel_dielectric(c, ETA)
    assert np.all(np.isfinite(F)), "F finite on [0, 1]"
    assert np.all(np.diff(F) < 0), "F strictly decreasing in cos θ_d (every step)"
    # Against Snell + s/p amplitudes at interior angles.
    theta = np.arccos(c[1:-1])
    ct = np.sqrt(1 - (np.sin(theta) / ETA) ** 2)
    rs = (c[1:-1] - ETA * ct) / (c[1:-1] + ETA * ct)
    rp = (ETA * c[1:-1] - ct) / (ETA * c[1:-1] + ct)
    ref = 0.5 * (rs**2 + rp**2)
    assert np.max(np.abs(F[1:-1] - ref)) < 1e-14, "max abs error vs Snell/s-p form"


def test_fresnel_rejects_bad_eta():
    with pytest.raises(InputError):
        brdf.fresnel_dielectric(0.5, eta=1.0)
    with pytest.raises(InputError):
        brdf.fresnel_dielectric(0.5, eta=float("nan"))


# --------------------------------------------------------------------------- Beckmann


@pytest.mark.parametrize("m", [0.1, 0.2, 0.35, 0.5, 0.8])
def test_beckmann_normalised(m):
    def integrand(theta):
        return brdf.beckmann_distribution(np.cos(theta), m) * np.cos(theta) * np.sin(theta)

    val, _ = integrate.quad(integrand, 0.0, np.pi / 2, limit=200, epsabs=1e-12)
    total = 2 * np.pi * val
    assert abs(total - 1.0) < TOL_BECKMANN_NORM, f"|∫ D cos dω − 1| = {abs(total - 1):.3g}"


def test_beckmann_below_horizon_and_invalid_m():
    D = brdf.beckmann_distribution(np.array([-0.5, 0.0, 1e-12, 1e-3]), 0.3)
    assert np.all(np.isfinite(D)), "finite at and below the horizon"
    assert D[0] == 0 and D[1] == 0 and D[2] == 0, "exactly 0 for cos_h <= 0 and ~0"
    with pytest.raises(InputError):
        brdf.beckmann_distribution(0.5, 0.0)


def test_geometry_term_range_and_degenerate():
    G = brdf.torrance_sparrow_geometry([0.5, 0.0, 0.3, 0.2], [0.5, 0.4, 0.0, 0.2],
                                       [0.9, 0.7, 0.6, 0.0], [0.8, 0.0, 0.0, 0.0])
    assert np.all(np.isfinite(G)), "G finite when v·h = 0"
    assert np.all((G >= 0) & (G <= 1)), "G in [0, 1]"
    assert G[0] == 1.0, "unshadowed configuration gives G = 1"


# --------------------------------------------------------------------------- energy


def _graded(n, p):
    """Gauss–Legendre nodes/weights on [0, 1] under t → t**p (dense near 0)."""
    x, w = np.polynomial.legendre.leggauss(n)
    t = 0.5 * (x + 1)
    return t**p, p * t ** (p - 1) * 0.5 * w


def _directional_albedo(theta_r, f_of_l, n_mu=192, n_phi=192):
    """∫ f(l, v) cos θ_i dω_i over the upper hemisphere, v at polar angle θ_r, azimuth 0.

    μ = cos θ_i graded toward the horizon, φ graded toward the mirror azimuth π, using the
    symmetry φ → −φ. ``f_of_l(l, v)`` returns (...) or (..., 3).
    """
    mu, w_mu = _graded(n_mu, 3)
    s, w_s = _graded(n_phi, 3)
    phi, w_phi = np.pi * (1 - s), np.pi * w_s
    MU, PHI = np.meshgrid(mu, phi, indexing="ij")
    sn = np.sqrt(1 - MU**2)
    l = np.stack([sn * np.cos(PHI), sn * np.sin(PHI), MU], -1)
    v = np.array([np.sin(theta_r), 0.0, np.cos(theta_r)])
    f = f_of_l(l, v)
    w = 2.0 * MU * w_mu[:, None] * w_phi[None, :]
    if f.ndim == 3:
        w = w[..., None]
    return np.sum(f * w, axis=(0, 1))


VIEW_DEG = [0.0, 30.0, 60.0, 75.0, 85.0, 88.0, 89.0]
N_UP = np.array([0.0, 0.0, 1.0])


@pytest.mark.parametrize("m", [0.2, 0.35, 0.5])
def test_specular_energy_bounded(m):
    """ρ_s = 1: the specular directional albedo stays ≤ 1 at every view angle (max measured
    0.519 at 89°, m = 0.2), and the quadrature is converged."""
    def f_s(l, v):
        return brdf.specular_brdf(N_UP, l, v, 1.0, m)

    albedo = [_directional_albedo(np.radians(deg), f_s) for deg in VIEW_DEG]
    # Convergence where the lobe is sharpest (89°): a grid twice as fine changes little.
    fine = _directional_albedo(np.radians(VIEW_DEG[-1]), f_s, n_mu=384, n_phi=384)
    change = abs(albedo[-1] - fine)
    assert change < TOL_QUADRATURE, f"quadrature change {change:.2g} at 89°"
    albedo = np.array(albedo)
    assert albedo.max() <= 1.0, f"max specular albedo {albedo.max():.4f} (m = {m})"
    assert np.all(np.diff(albedo) > 0), "specular albedo grows toward grazing (Fresnel)"


def _albedo_over_views(theta_r, f_of_l, n_q=192):
    """:func:`_directional_albedo` for many view angles at once: ``(V,)`` or ``(V, 3)``."""
    mu, w_mu = _graded(n_q, 3)
    s, w_s = _graded(n_q, 3)
    phi, w_phi = np.pi * (1 - s), np.pi * w_s
    MU, PHI = np.meshgrid(mu, phi, indexing="ij")
    sn = np.sqrt(1 - MU**2)
    l = np.stack([sn * np.cos(PHI), sn * np.sin(PHI), MU], -1)[None]
    th = np.asarray(theta_r, float)
    v = np.stack([np.sin(th), 0 * th, np.cos(th)], -1)[:, None, None, :]
    f = f_of_l(l, v)
    w = (2.0 * MU * w_mu[:, None] * w_phi[None, :])[None]
    if f.ndim == 4:
        w = w[..., None]
    return np.sum(f * w, axis=(1, 2))


#: View angles 0…89.9° (every 5°, then dense toward grazing), for the energy bound.
VIEW_DEG_ALL = np.concatenate([np.arange(0.0, 85.0, 5.0), [85, 86, 87, 88, 89, 89.5, 89.9]])
#: The generator's parameter ranges (facegeo.synth.skin: α ≤ 0.95, ρ_s in (0.3, 1.0),
#: m in (0.25, 0.5); the spectral colour model keeps ρ_s ≤ 1).
GEN_RHO_S = (0.3, 1.0)
GEN_M = (0.25, 0.35, 0.5)
N_Q_ENERGY = 128  # graded Gauss–Legendre nodes per axis for the energy bound


def test_total_energy_bounded_over_generator_ranges():
    """Directional albedo ∫ f cos θ_i dω ≤ 1 at every view angle 0…89.9° over the generator's
    ρ_s and roughness ranges, with α_0 = α_1 = 1 (the physical limit, above the generator's
    0.95): the albedo is linear and non-decreasing in α_0 and α_1, so α = 1 bounds every
    colour. The unweighted sum reached 1.43 at 89.9° (see the next test).

    Quadrature error: the worst case re-integrated on a grid twice as fine changes by
    ``change`` (< TOL_QUADRATURE), which is added to the measured maximum."""
    th = np.radians(VIEW_DEG_ALL)
    one = np.ones(3)
    worst, where = 0.0, None
    for rho in GEN_RHO_S:
        for m in GEN_M:
            alb = _albedo_over_views(
                th, lambda l, v: brdf.synthetic_skin_brdf(N_UP, l, v, one, one, rho, m),
                n_q=N_Q_ENERGY)[:, 0]
            k = int(np.argmax(alb))
            if alb[k] > worst:
                worst, where = float(alb[k]), (rho, m, float(VIEW_DEG_ALL[k]))
    rho, m, deg = where
    fine = _albedo_over_views(
        np.radians([deg]), lambda l, v: brdf.synthetic_skin_brdf(N_UP, l, v, one, one, rho, m),
        n_q=2 * N_Q_ENERGY)[0, 0]
    change = abs(fine - worst)
    assert change < TOL_QUADRATURE, f"quadrature change {change:.2g} at (ρ_s, m, view°) {where}"
    assert worst + change <= 1.0, (f"max albedo {worst:.5f} (+ quadrature {change:.1g}) at "
                                   f"(ρ_s, m, view°) = {where}")


def test_unweighted_sum_would_exceed_one():
    """The bug the weight fixes: diffuse α = 0.95 plus the ρ_s = 1 lobe at 89.9° (no (1 − ρ_dr)
    weight) exceeds 1, so the bound above is not vacuous."""
    spec = _albedo_over_views(np.radians([89.9]),
                              lambda l, v: brdf.specular_brdf(N_UP, l, v, 1.0, 0.25))
    assert 0.95 + spec[0] > 1.4, f"unweighted albedo {0.95 + spec[0]:.3f}"


def test_specular_albedo_table_matches_quadrature():
    """ρ_dr from the table (off its nodes in m and μ) against a 256 × 256 quadrature of Eq. 2;
    max abs error ≤ TOL_RHO_DR_TABLE in the generator's m range, ≤ ..._SHARP at m = 0.07."""
    deg = np.array([0.0, 23.0, 47.0, 61.0, 77.0, 83.3, 87.1, 89.0, 89.7])
    for m, tol in [(0.25, TOL_RHO_DR_TABLE), (0.33, TOL_RHO_DR_TABLE),
                   (0.5, TOL_RHO_DR_TABLE), (0.07, TOL_RHO_DR_TABLE_SHARP)]:
        ref = _albedo_over_views(np.radians(deg),
                                 lambda l, v: brdf.specular_brdf(N_UP, l, v, 1.0, m), n_q=256)
        got = brdf.specular_albedo(np.cos(np.radians(deg)), 1.0, m)
        err = np.abs(got - ref).max()
        assert err < tol, f"max abs error of the ρ_dr table {err:.2g} (m = {m})"
        assert np.allclose(brdf.specular_albedo(np.cos(np.radians(deg)), 0.4, m), 0.4 * got,
                           rtol=1e-14, atol=0), "linear in ρ_s, relative"


def test_diffuse_weight_is_one_minus_rho_dr_squared():
    """f_d = (1 − ρ_dr(θ_i))(1 − ρ_dr(θ_r)) · blend/π, against the pieces."""
    rng = np.random.default_rng(5)
    n = _unit(rng.normal(size=(200, 3)))
    l = _hemisphere(rng, n, (200,))
    v = _hemisphere(rng, n, (200,))
    rho_s, m = rng.uniform(0.3, 1.0, 200), rng.uniform(0.25, 0.5, 200)
    ci, cr = np.sum(n * l, -1), np.sum(n * v, -1)
    want = ((1 - brdf.specular_albedo(ci, rho_s, m)) * (1 - brdf.specular_albedo(cr, rho_s, m)))[
        :, None] * brdf.grazing_colour_blend(ALPHA_0, ALPHA_1, ci, cr) / np.pi
    got = brdf.synthetic_diffuse_brdf(n, l, v, ALPHA_0, ALPHA_1, rho_s, m)
    assert np.allclose(got, want, rtol=1e-12, atol=0), "diffuse weight, relative"


def test_unchecked_kernel_propagates_nan():
    """A NaN in any input of the unchecked kernel gives NaN for that sample, never 0."""
    n = np.tile([0.0, 0.0, 1.0], (5, 1))
    l = np.tile(_unit(np.array([0.3, 0.1, 0.9])), (5, 1))
    v = np.tile(_unit(np.array([-0.2, 0.3, 0.9])), (5, 1))
    a0, a1 = np.tile(ALPHA_0, (5, 1)), np.tile(ALPHA_1, (5, 1))
    rho, m = np.full(5, 0.5), np.full(5, 0.3)
    n[0, 2] = np.nan
    l[1, 0] = np.nan
    a0[2, 1] = np.nan
    rho[3] = np.nan
    m[4] = np.nan
    f = brdf.synthetic_skin_brdf_unchecked(n, l, v, a0, a1, rho, m)
    assert np.all(np.isnan(f)), f"NaN in → NaN out for every sample, got {f}"
    ok = brdf.synthetic_skin_brdf_unchecked(n[1:2] * 0 + [0, 0, 1], v[:1], v[:1], a0[:1], a1[:1],
                                            rho[:1], m[:1])
    assert np.all(np.isfinite(ok)), "finite inputs stay finite"


@pytest.mark.parametrize("deg", VIEW_DEG)
def test_diffuse_albedo_analytic(deg):
    th = np.radians(deg)
    # ρ_s = 0: no specular lobe, so the (1 − ρ_dr) weight is 1 and the blend alone remains.
    got = _directional_albedo(
        th, lambda l, v: brdf.synthetic_diffuse_brdf(N_UP, l, v, ALPHA_0, ALPHA_1, 0.0, 0.3),
        n_mu=16, n_phi=16)
    want = ALPHA_1 + (2.0 / 3.0) * np.cos(th) * (ALPHA_0 - ALPHA_1)
    err = np.abs(got - want).max()
    assert err < TOL_DIFFUSE_ALBEDO, f"max abs error vs α_1 + ⅔ cos θ_r (α_0 − α_1): {err:.3g}"


# --------------------------------------------------------------------------- hard cases


def test_grazing_and_below_horizon_are_finite():
    n = np.array([0.0, 1.0, 0.0])
    s = np.sqrt(0.5)
    cases = {
        "n·l = 0": (np.array([1.0, 0.0, 0.0]), np.array([0.0, s, s])),
        "n·v = 0": (np.array([0.0, s, s]), np.array([0.0, 0.0, 1.0])),
        "n·l < 0": (np.array([0.0, -s, s]), np.array([0.0, s, s])),
        "n·v < 0": (np.array([0.0, s, s]), np.array([s, -s, 0.0])),
        "l = v = n": (n, n),
        "l = -v": (np.array([s, s, 0.0]), np.array([-s, -s, 0.0])),
        "l = -v tangent": (np.array([1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0])),
    }
    for name, (l, v) in cases.items():
        for m in (0.05, 0.35):
            f = brdf.synthetic_skin_brdf(n, l, v, ALPHA_0, ALPHA_1, 1.0, m)
            r = brdf.olat_radiance(n, l, v, ALPHA_0, ALPHA_1, 1.0, m)
            assert np.all(np.isfinite(f)) and np.all(np.isfinite(r)), f"finite at {name}"
            assert np.all(f >= 0) and np.all(r >= 0), f"non-negative at {name}"
            if name != "l = v = n":
                assert np.all(f == 0), f"0 at or below the horizon ({name})"


def test_grazing_limits_are_finite_and_continuous():
    """Approach the horizon in the mirror configuration (the only divergent limit)."""
    n = np.array([0.0, 0.0, 1.0])
    eps = np.logspace(-12, -1, 23)
    ct = eps
    st = np.sqrt(1 - ct**2)
    l = np.stack([st, 0 * st, ct], -1)
    v_mirror = np.stack([-st, 0 * st, ct], -1)
    v_fixed = np.broadcast_to(_unit(np.array([-0.3, 0.1, 0.9])), l.shape)
    f_mirror = brdf.specular_brdf(n, l, v_mirror, 1.0, 0.3)
    f_one = brdf.specular_brdf(n, l, v_fixed, 1.0, 0.3)
    assert np.all(np.isfinite(f_mirror)), "finite as both directions graze"
    bound = 1.0 / (4 * brdf.COS_FLOOR) / (np.pi * 0.3**2)  # F ≤ 1, D ≤ D(0), G/4cc ≤ cap
    assert f_mirror.max() <= bound * (1 + 1e-12), f"max {f_mirror.max():.4g} vs cap {bound:.4g}"
    # One direction grazing: G cancels the vanishing cosine, the limit is finite and smooth.
    assert np.all(np.isfinite(f_one)), "finite as n·l → 0 with v fixed"
    rel_step = np.abs(np.diff(f_one[:10])) / f_one[:10].max()
    assert rel_step.max() < 1e-6, f"converges as n·l → 0 (max relative step {rel_step.max():.2g})"


def test_flat_patch_normal_incidence_is_alpha0_over_pi():
    n = np.array([0.0, 1.0, 0.0])  # +Y up, light straight above, viewer straight above
    fd = brdf.synthetic_diffuse_brdf(n, n, n, ALPHA_0, ALPHA_1, 0.0, 0.3)
    assert np.array_equal(fd, ALPHA_0 / np.pi), "ρ_s = 0: diffuse at normal = α_0/π exactly"
    m, rho = 0.3, 0.7
    f = brdf.synthetic_skin_brdf(n, n, n, ALPHA_0, ALPHA_1, rho, m)
    f0 = ((ETA - 1) / (ETA + 1)) ** 2
    spec = rho * f0 / (np.pi * m**2) / 4.0  # F(0) D(0) G=1 / (4·1·1)
    t = 1.0 - brdf.specular_albedo(1.0, rho, m)
    assert np.allclose(f - t * t * ALPHA_0 / np.pi, spec, rtol=1e-13, atol=0), \
        "specular at normal, relative (diffuse weighted by (1 − ρ_dr(0))²)"
    E = np.array([2.0, 1.0, 0.5])
    r = brdf.olat_radiance(n, n, n, ALPHA_0, ALPHA_1, rho, m, irradiance=E)
    assert np.allclose(r, f * E, rtol=1e-15, atol=0), "radiance = f · cos θ_i · E at cos = 1"


def test_olat_radiance_cosine_and_broadcast():
    rng = np.random.default_rng(3)
    n = _unit(rng.normal(size=(4, 5, 3)))
    l = _unit(rng.normal(size=(4, 5, 3)))
    v = _hemisphere(rng, n, (4, 5))
    rho_s = rng.uniform(0.3, 1.0, (4, 5))
    m = rng.uniform(0.25, 0.5, (4, 5))
    r = brdf.olat_radiance(n, l, v, ALPHA_0, ALPHA_1, rho_s, m, irradiance=3.0)
    f = brdf.synthetic_skin_brdf(n, l, v, ALPHA_0, ALPHA_1, rho_s, m)
    cos = np.clip(np.sum(n * l, -1), 0, None)[..., None]
    assert r.shape == (4, 5, 3), "output shape broadcasts over leading axes"
    # rtol 4 ulp: f·cos·E and E·f·cos round differently in the last bit.
    assert np.allclose(r, 3.0 * f * cos, rtol=1e-15 * 4, atol=0), "f · max(0, n·l) · E, relative"


def test_input_validation():
    n = np.array([0.0, 1.0, 0.0])
    with pytest.raises(InputError):
        brdf.synthetic_skin_brdf(n * 2, n, n, ALPHA_0, ALPHA_1, 1.0, 0.3)  # not unit
    with pytest.raises(ShapeError):
        brdf.synthetic_skin_brdf(n[:2], n, n, ALPHA_0, ALPHA_1, 1.0, 0.3)
    with pytest.raises(InputError):
        brdf.synthetic_skin_brdf(n, n, n, ALPHA_0, ALPHA_1, -1.0, 0.3)  # rho_s < 0
    with pytest.raises(InputError):
        brdf.synthetic_skin_brdf(n, n, n, ALPHA_0, ALPHA_1, 1.0, 0.0)  # m = 0
    with pytest.raises(InputError):
        brdf.synthetic_skin_brdf(n, np.array([np.nan, 1.0, 0.0]), n, ALPHA_0, ALPHA_1, 1.0, 0.3)


def test_desaturate():
    a1 = brdf.desaturate(ALPHA_0, 0.5)
    Y0 = ALPHA_0 @ brdf.REC709_LUMINANCE
    assert a1 @ brdf.REC709_LUMINANCE == pytest.approx(Y0, rel=1e-14), "luminance kept, rel"
    assert np.ptp(a1) == pytest.approx(0.5 * np.ptp(ALPHA_0), rel=1e-12), "channel spread halved"
    assert np.array_equal(brdf.desaturate(ALPHA_0, 0.0), ALPHA_0), "amount 0 is identity"
    assert np.allclose(brdf.desaturate(ALPHA_0, 1.0), Y0, rtol=1e-14, atol=0), "amount 1 is grey"
    many = brdf.desaturate(np.tile(ALPHA_0, (3, 1)), np.array([0.0, 0.5, 1.0]))
    assert many.shape == (3, 3), "broadcasts amount over leading axes"
    with pytest.raises(InputError):
        brdf.desaturate(ALPHA_0, 1.5)
