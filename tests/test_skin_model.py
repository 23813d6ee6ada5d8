"""The paper's skin reflectance model (Debevec et al. 2000, §4): Eq. 6–9 pieces, exact recovery
on paper-mode data, the mismatched generator's OLAT functions, a real face, and hard cases.

Tolerances are the named module constants below; each states its metric. Hard cases use seeded
random inputs (hypothesis is not installed).
"""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from facegeo.appearance import skin
from facegeo.errors import InputError, ShapeError

# ---------------------------------------------------------------- tolerances (metric stated)
#: Paper mode: median angle between fitted and true normals, degrees.
PAPER_NORMAL_MEDIAN_DEG = 0.5
#: Paper mode: max relative error |x̂/x − 1| of α_0, α_1 and |ρ̂_d − ρ_d|/|ρ_d| (d_0 known).
PAPER_PARAM_REL = 0.01
#: Paper mode: median relative error of ρ_s (a quadrature of the measured lobe).
PAPER_RHO_S_MEDIAN_REL = 0.01
#: Paper mode: relative RMSE ‖R̂ − R‖/‖R‖ of resynthesised functions at 30° and 60°.
PAPER_RESYNTH_REL_RMSE = 0.01
#: Paper mode with d_0 estimated by the median ratios: median normal error, degrees.
PAPER_ESTIMATED_D0_NORMAL_MEDIAN_DEG = 0.5
#: Recombination D + S = R: max |D + S − R| in units of float32 ulp of max |R|.
RECOMBINE_ULPS = 2
#: Generator's (mismatched) BRDF, tiny preset camera, distant lights 16 × 8: median normal
#: error over unshadowed pixels, degrees, for the final normal / the first-moment normal.
SYNTH_NORMAL_MEDIAN_DEG = 5.0
SYNTH_MOMENT_NORMAL_MEDIAN_DEG = 1.5
#: Generator's BRDF, small preset (32 × 16 distant lights, ground-truth mesh normals), issue
#: 13's "Show": median normal error over unshadowed pixels, degrees; median albedo error
#: |ρ̂_d − ρ_d|/|ρ_d| against the generator's own Lambertian albedo (π × the least-squares
#: scale of its exact diffuse radiance f_d cos θ_i onto max(0, n·l), per channel, true normal);
#: resynthesis at 30°/60° must beat reusing the source function by this factor (relative RMSE).
SMALL_NORMAL_MEDIAN_DEG = 2.0
SMALL_ALBEDO_MEDIAN_REL = 0.03
SMALL_RESYNTH_VS_NAIVE = 3.0
#: Small preset, generator BRDF: |Σ S / Σ R − the generator's specular share| over the
#: unshadowed functions, in total and ≥ 45° from the mirror direction (measured 0.2 % / 0.0 %;
#: the lobe criterion alone: 53 % / 36 % too much).
SMALL_S_SHARE_ABS = 0.02
#: The generator's diffuse term alone (no specular lobe; Fresnel-weighted (1 − ρ_dr)² colour
#: blend, 32 × 16 grid): fraction of the total energy the fit puts into S, Σ S / Σ R (measured
#: 1.0 %; 37 % with the lobe criterion alone, SearchDepth(chroma=0)).
DIFFUSE_ONLY_S_SHARE = 0.03
#: The same with Gaussian noise σ = 1 % of each function's maximum: Σ S / Σ R (measured 0.12 %
#: with specular_gate=3; 6.2 % with the paper's plain max(μ_s, 0), the default).
NOISY_DIFFUSE_S_SHARE = 0.02
#: Fast closed-form μ_d of the ramp search against the explicit Eq. 6 chromaticity + §4.2
#: separation: max |μ̂_d − μ_d| / max |R| (float64 rounding only).
FAST_MU_D_REL = 1e-9
#: Fit of the same functions in chunks of different size: max |n_a − n_b| (≈ radians; an
#: arccos angle cannot resolve below ~1e-6°) and max |Δα| (chunks are independent problems;
#: only summation order may differ).
CHUNK_NORMAL_ABS = 1e-8
CHUNK_ALPHA_ABS = 1e-8
#: Forward- against central-difference Jacobian in the ramp's LM polish (paper mode, d_0 known):
#: max |Δα| and max relative |Δρ_s| (measured 8e-6 and 1.5e-4 on 128 functions).
FORWARD_POLISH_ALPHA_ABS = 1e-4
FORWARD_POLISH_RHO_S_REL = 2e-3

#: Compiled kernels (_skin_kernels) against the numpy reference, same fit: max angle between
#: normals, degrees; max |Δ misfit|; max |Δα|; max |Δρ_s| / max ρ_s.
#: Same searches (only summation order and the lobe search's moment/band split differ: a wrong
#: band or a dropped light moves normals by > 0.01°); the polish uses the analytic Jacobian
#: where the reference takes forward differences, so the LM paths differ by O(h) after the
#: polish's 10 steps — measured 6e-11 (joint polish, d_0 known, 2048 lights) to 1.5e-5 (this
#: test's fixed-normal polish).
KERNEL_NORMAL_DEG = 1e-4
KERNEL_MISFIT_ABS = 1e-10
KERNEL_ALPHA_ABS = 1e-4
KERNEL_RHO_S_REL = 1e-4
#: The ramp fit on a light subsample plus one finishing step on all lights (the default at
#: 2048 lights) against the fit on all lights throughout, noisy paper-mode data (0.5 % of the
#: peak): median |Δα| as a fraction of the all-lights fit's own median |α − α_true| (measured
#: 0.009–0.041 over three seeds; without the finishing step 0.17–0.8).
SUBSAMPLE_ALPHA_OF_ERROR = 0.1
#: Analytic Jacobian of the polish residuals against central differences (h = 1e-6): max
#: |ΔJ| / max |J|.
KERNEL_JACOBIAN_REL = 1e-5
#: Σ r² of the polish's residuals from three sums (the LM steps' form) against the summed
#: squares of its residual rows: relative difference (cancellation, where Σ r² > 1e-6)
POLISH_SUMS_REL = 1e-10

V0 = np.array([0.0, 0.0, 1.0])


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def _random_normals(rng, n, max_deg):
    ang = np.radians(rng.uniform(0.0, max_deg, n))
    az = rng.uniform(0.0, 2 * np.pi, n)
    loc = np.stack([np.sin(ang) * np.cos(az), np.sin(ang) * np.sin(az), np.cos(ang)], 1)
    return loc  # within max_deg of +Z (the source view)


def _paper_params(rng, n):
    chroma = skin.normalize(np.array([0.8, 0.5, 0.35]) + rng.normal(0, 0.05, (n, 3)))
    rho_d = rng.uniform(0.3, 0.7, (n, 1)) * chroma
    return skin.SkinParams(rho_d, rng.uniform(0.2, 0.4, n), rng.uniform(-0.5, -0.2, n),
                           rng.uniform(0.3, 0.8, n), rng.uniform(0.3, 0.45, n))


def _view(deg):
    a = np.radians(deg)
    return np.array([np.sin(a), 0.0, np.cos(a)])


@pytest.fixture(scope="module")
def paper_case():
    rng = np.random.default_rng(13)
    lights = skin.LightSet.from_grid(64, 32, color=(0.9, 1.0, 1.1))
    N = 16
    n = _random_normals(rng, N, 25.0)
    p = _paper_params(rng, N)
    R = skin.paper_reflectance(n, V0, lights, p)
    fit = skin.fit_reflectance(R, V0, lights, d_0=skin.normalize(p.rho_d))
    return lights, n, p, R, fit


# ---------------------------------------------------------------- model pieces


def test_ramp_is_eq6_7_as_written():
    rng = np.random.default_rng(0)
    d0 = skin.normalize(rng.uniform(0.2, 1.0, (5, 3)))
    ci, cr = rng.uniform(0, 1, 5), rng.uniform(0, 1, 5)
    a0, a1 = 0.3, -0.4
    f = skin.ramp_f(ci, cr, a0, a1)
    np.testing.assert_allclose(f, a0 * ci * cr + a1 * (1 - ci * cr), rtol=0, atol=1e-15)
    c = skin.ramp_chromaticity(d0, f)
    s = np.ones(3) / np.sqrt(3)
    ref = d0 + f[:, None] * (d0 - s)
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    np.testing.assert_allclose(c, ref, rtol=0, atol=1e-15)  # max abs difference, unit vectors
    # brightness never changes with the ramp: unit chromaticities
    np.testing.assert_allclose(np.linalg.norm(c, axis=1), 1.0, atol=1e-15)
    # inverse of Eq. 6 round-trips (max abs error on unit vectors)
    d_back, ok = skin.invert_ramp(c, f)
    assert ok.all()
    np.testing.assert_allclose(d_back, d0, atol=1e-12)


def test_paper_reflectance_is_lambertian_in_brightness_and_eq8_in_specular():
    lights = skin.LightSet.from_grid(16, 8)
    n = np.array([[0.0, 0.0, 1.0]])
    p = skin.SkinParams(np.array([[0.3, 0.2, 0.1]]), 0.3, -0.3, 0.0, 0.3)
    R = skin.paper_reflectance(n, V0, lights, p)
    a = np.linalg.norm(p.rho_d)
    nl = np.maximum(lights.directions @ n[0], 0)
    # max abs error of the diffuse brightness against (a/π) max(0, n·l)
    np.testing.assert_allclose(np.linalg.norm(R[0], axis=1), a / np.pi * nl, atol=1e-7)
    p2 = replace(p, rho_d=np.zeros((1, 3)), rho_s=np.array([0.5]))
    S = skin.paper_reflectance(n, V0, lights, p2)[0, :, 0]
    ref = skin.specular_sample(n[:, None], V0[None, None], lights.directions[None], 0.5, 0.3, 1.4)
    np.testing.assert_allclose(S, ref[0], rtol=1e-6)


def test_separation_recombines_and_recovers_mu():
    rng = np.random.default_rng(1)
    d = skin.normalize(rng.uniform(0.1, 1, (50, 3)))
    s = skin.S_WHITE
    mu_d, mu_s, mu_e = rng.uniform(0, 1, 50), rng.uniform(0, 1, 50), rng.normal(0, 0.01, 50)
    e = np.cross(d, s)
    R = mu_d[:, None] * d + mu_s[:, None] * s + mu_e[:, None] * e
    D, S, md, ms, me, sing = skin.separate_colour(R, d)
    assert not sing.any()
    # max abs error of the coefficients and of D + S − R
    np.testing.assert_allclose(np.stack([md, ms, me]), np.stack([mu_d, mu_s, mu_e]), atol=1e-12)
    np.testing.assert_allclose(D + S, R, atol=1e-15)


# ---------------------------------------------------------------- paper mode: exact recovery


def test_paper_mode_exact_recovery(paper_case):
    lights, n, p, R, fit = paper_case
    assert (fit.flags == 0).all(), [skin.flag_names(f) for f in fit.flags]
    err = _angle_deg(fit.normal, n)
    assert np.median(err) <= PAPER_NORMAL_MEDIAN_DEG, err
    assert np.max(np.abs(fit.alpha_0 / p.alpha_0 - 1)) <= PAPER_PARAM_REL
    assert np.max(np.abs(fit.alpha_1 / p.alpha_1 - 1)) <= PAPER_PARAM_REL
    rd = np.linalg.norm(fit.rho_d - p.rho_d, axis=1) / np.linalg.norm(p.rho_d, axis=1)
    assert rd.max() <= PAPER_PARAM_REL
    assert np.median(np.abs(fit.rho_s / p.rho_s - 1)) <= PAPER_RHO_S_MEDIAN_REL
    # the search improves on (or keeps) the closed-form moment's lobe misfit
    assert np.all(fit.lobe_misfit <= fit.lobe_misfit_moment + 1e-12)


@pytest.mark.parametrize("deg", [30.0, 60.0])
def test_paper_mode_resynthesis(paper_case, deg):
    lights, n, p, R, fit = paper_case
    vn = _view(deg)
    truth = skin.paper_reflectance(n, vn, lights, p)
    out = skin.resynthesize(fit, vn).reflectance
    rel = np.sqrt(np.sum((out - truth) ** 2) / np.sum(truth ** 2))
    naive = np.sqrt(np.sum((R - truth) ** 2) / np.sum(truth ** 2))
    assert rel <= PAPER_RESYNTH_REL_RMSE, (rel, naive)
    assert rel < naive / 3


def test_paper_mode_view_independent_form(paper_case):
    lights, n, p, R, fit = paper_case
    vn = _view(30.0)
    truth = skin.paper_reflectance(n, vn, lights, p)
    out = skin.resynthesize(fit, vn, view_independent_form=True).reflectance
    rel = np.sqrt(np.sum((out - truth) ** 2) / np.sum(truth ** 2))
    assert rel <= 2 * PAPER_RESYNTH_REL_RMSE  # two interpolations instead of one


def test_same_view_reproduces_measured_function_exactly(paper_case):
    lights, n, p, R, fit = paper_case
    out = skin.resynthesize(fit, V0)
    # float32 rounding of D + S only
    ulp = np.spacing(np.float32(np.abs(R).max()))
    assert np.abs(out.reflectance - R).max() <= RECOMBINE_ULPS * ulp


def test_paper_mode_estimated_d0():
    rng = np.random.default_rng(5)
    lights = skin.LightSet.from_grid(32, 16)
    n = _random_normals(rng, 12, 25.0)
    p = _paper_params(rng, 12)
    R = skin.paper_reflectance(n, V0, lights, p)
    fit = skin.fit_reflectance(R, V0, lights)
    assert np.median(_angle_deg(fit.normal, n)) <= PAPER_ESTIMATED_D0_NORMAL_MEDIAN_DEG
    ulp = np.spacing(np.float32(np.abs(R).max()))
    assert np.abs(fit.diffuse + fit.specular - R).max() <= RECOMBINE_ULPS * ulp


def test_free_light_list_with_intensities():
    """A non-grid light set (directions + per-light intensities + solid angles)."""
    rng = np.random.default_rng(2)
    dirs = skin.normalize(rng.normal(size=(300, 3)))
    dirs = dirs[dirs[:, 2] > -0.2]
    E = rng.uniform(0.5, 2.0, dirs.shape[0])
    lights = skin.LightSet.from_directions(dirs, np.full(len(dirs), 4 * np.pi / 300), E)
    n = _random_normals(rng, 8, 20.0)
    p = _paper_params(rng, 8)
    R = skin.paper_reflectance(n, V0, lights, p)
    fit = skin.fit_reflectance(R, V0, lights, d_0=skin.normalize(p.rho_d))
    assert np.median(_angle_deg(fit.normal, n)) <= PAPER_NORMAL_MEDIAN_DEG
    out = skin.resynthesize(fit, V0).reflectance
    assert np.array_equal(out, fit.diffuse + fit.specular)


def test_swapped_views_fail():
    """Resynthesis depends on which view is the source: swapping v_0 and v_n changes it."""
    rng = np.random.default_rng(3)
    lights = skin.LightSet.from_grid(32, 16)
    n = _random_normals(rng, 6, 15.0)
    p = _paper_params(rng, 6)
    R = skin.paper_reflectance(n, V0, lights, p)
    fit = skin.fit_reflectance(R, _view(30.0), lights, d_0=skin.normalize(p.rho_d))
    truth = skin.paper_reflectance(n, _view(30.0), lights, p)
    out = skin.resynthesize(fit, V0).reflectance
    assert np.sqrt(np.sum((out - truth) ** 2) / np.sum(truth ** 2)) > 0.01


# ---------------------------------------------------------------- hard cases (seeded random)


def _hard_case_fit(R, lights, v=V0, **kw):
    fit = skin.fit_reflectance(R, v, lights, **kw)
    for name in ("normal", "normal_moment", "rho_d", "rho_s", "alpha_0", "alpha_1",
                 "diffuse", "specular"):
        assert np.all(np.isfinite(getattr(fit, name))), name
    for vn in (v, _view(60.0), _view(89.9), -np.asarray(v, float)):
        r = skin.resynthesize(fit, vn)
        assert np.all(np.isfinite(r.reflectance))
    return fit


def test_hard_cases_finite_and_flagged():
    rng = np.random.default_rng(7)
    lights = skin.LightSet.from_grid(16, 8)
    L = lights.n_lights
    n = _random_normals(rng, 6, 30.0)
    p = _paper_params(rng, 6)
    R = skin.paper_reflectance(n, V0, lights, p)
    # all black
    fit = _hard_case_fit(np.zeros((3, L, 3), np.float32), lights)
    assert (fit.flags & skin.FLAG_BLACK).all() and not fit.valid.any()
    # fully shadowed by the caller's visibility
    fit = _hard_case_fit(R, lights, visibility=np.zeros((6, L), bool))
    assert (fit.flags & skin.FLAG_SHADOWED).all()
    # saturated samples masked and flagged
    sat = float(np.percentile(R, 99.5))
    fit = _hard_case_fit(np.minimum(R, sat), lights, saturation=sat)
    assert (fit.flags & skin.FLAG_SATURATED).any()
    # diffuse colour = light colour: singular 3 × 3
    pg = replace(p, rho_d=np.full((6, 3), 0.3), alpha_0=0.0, alpha_1=0.0)
    fit = _hard_case_fit(skin.paper_reflectance(n, V0, lights, pg), lights)
    assert (fit.flags & skin.FLAG_SINGULAR).all()
    # grazing view (v·n → 0) and grazing lights
    ng = skin.normalize(np.array([[1.0, 0.0, 1e-3]] * 2))
    Rg = skin.paper_reflectance(ng, V0, lights, replace(p, rho_d=p.rho_d[:2],
                                alpha_0=p.alpha_0[:2], alpha_1=p.alpha_1[:2],
                                rho_s=p.rho_s[:2], roughness=p.roughness[:2]))
    fit = _hard_case_fit(Rg, lights)
    assert (fit.flags != 0).all()
    # specular lobe hidden in shadow: occlude the lights around the mirror direction
    mirror = 2 * (n @ V0)[:, None] * n - V0
    vis = (mirror @ lights.directions.T) < np.cos(np.radians(25))
    fit = _hard_case_fit(R, lights, visibility=vis)
    r = skin.resynthesize(fit, _view(30.0))
    # never a lobe in an occluded direction; the hidden lobe is flagged
    assert np.all(r.specular[~vis] == 0)
    assert (r.flags & skin.FLAG_SPECULAR_IN_SHADOW).any()


def test_l_equals_minus_v_is_finite():
    """H undefined (l = −v): Eq. 8 and Eq. 9 stay finite."""
    lights = skin.LightSet.from_directions(
        skin.normalize(np.array([[0, 0, -1.0], [0, 1, 0.2], [1, 0, 0.3], [0, 0, 1.0],
                                 [0.3, 0.3, 0.9]])))
    n = np.array([[0.0, 0.0, 1.0]])
    p = skin.SkinParams(np.array([[0.3, 0.2, 0.1]]), 0.2, -0.2, 0.5, 0.3)
    R = skin.paper_reflectance(n, V0, lights, p)
    assert np.all(np.isfinite(R))
    _hard_case_fit(R, lights)


def test_single_channel_is_diffuse_only(caplog):
    rng = np.random.default_rng(4)
    lights = skin.LightSet.from_grid(32, 16)
    n = _random_normals(rng, 8, 30.0)
    a = rng.uniform(0.2, 0.8, 8)
    R = (a[:, None] / np.pi * np.maximum(n @ lights.directions.T, 0)).astype(np.float32)
    with caplog.at_level("INFO"):
        fit = skin.fit_reflectance(R, V0, lights)
    assert "single-channel" in caplog.text
    assert (fit.flags & skin.FLAG_SINGLE_CHANNEL).all()
    assert np.all(fit.specular == 0)
    assert np.median(_angle_deg(fit.normal, n)) <= PAPER_NORMAL_MEDIAN_DEG


def test_input_errors_name_the_argument():
    lights = skin.LightSet.from_grid(8, 4)
    with pytest.raises(ShapeError, match="R"):
        skin.fit_reflectance(np.zeros((2, 5, 3)), V0, lights)
    with pytest.raises(InputError, match="R"):
        skin.fit_reflectance(-np.ones((2, 32, 3)), V0, lights)
    with pytest.raises(InputError, match="v"):
        skin.fit_reflectance(np.ones((2, 32, 3)), [0, 0, 2.0], lights)
    with pytest.raises(ShapeError, match="visibility"):
        skin.fit_reflectance(np.ones((2, 32, 3)), V0, lights, visibility=np.ones((2, 3), bool))
    with pytest.raises(InputError, match="specular_gate"):
        skin.fit_reflectance(np.ones((2, 32, 3)), V0, lights, specular_gate=-1.0)
    with pytest.raises(InputError, match="directions"):
        skin.LightSet.from_directions([[0, 0, 1.0], [0, 1, 0]])


# ---------------------------------------------------------------- the generator's OLAT frames


@pytest.mark.slow
def test_generator_olat_functions():
    """The default (mismatched) generator BRDF: image-space reflectance functions of one camera's
    head pixels (tiny preset, distant lights on the 16 × 8 grid), ground-truth normals."""
    from facegeo.synth.capture import PRESETS, build_head, build_rig
    from facegeo.synth.render import ReferenceRenderer
    from facegeo.synth.skin import SkinField

    mesh = build_head("procedural", subdivisions=4, seed=0)
    rig = build_rig(PRESETS["tiny"])
    stage = replace(rig.lights, radius=float("inf"))
    field = SkinField.for_mesh(mesh, seed=0)
    col = np.asarray(stage.color, float)
    out = []
    for shadows in (True, False):
        ren = ReferenceRenderer.from_mesh(mesh, field, shadows=shadows)
        view = ren.surface_view(rig.cameras[0])
        out.append((view, np.stack([ren.shade_directional_light(view, d, col)
                                    for d in stage.directions], axis=1)))
    (view, R), (_, R_noshadow) = out
    rng = np.random.default_rng(0)
    idx = np.sort(rng.choice(view.n_samples, 600, replace=False))
    R, R_noshadow = R[idx], R_noshadow[idx]
    unshadowed = np.all(np.abs(R - R_noshadow) <= 1e-7 + 1e-6 * np.abs(R_noshadow), axis=(1, 2))
    lights = skin.LightSet.from_grid(stage.n_theta, stage.n_phi, stage.color)
    fit = skin.fit_reflectance(R, view.v_world[idx], lights)
    n_true = view.n_world[idx]
    err = _angle_deg(fit.normal, n_true)[unshadowed]
    err_m = _angle_deg(fit.normal_moment, n_true)[unshadowed]
    print(f"generator BRDF: median normal error over {unshadowed.sum()} unshadowed pixels "
          f"{np.median(err):.2f}° (moment {np.median(err_m):.2f}°)")
    assert np.median(err) <= SYNTH_NORMAL_MEDIAN_DEG
    assert np.median(err_m) <= SYNTH_MOMENT_NORMAL_MEDIAN_DEG
    ulp = np.spacing(np.float32(np.abs(R).max()))
    assert np.abs(fit.diffuse + fit.specular - R).max() <= RECOMBINE_ULPS * ulp
    same = skin.resynthesize(fit, view.v_world[idx]).reflectance
    assert np.abs(same - R).max() <= RECOMBINE_ULPS * ulp


# ---------------------------------------------------------------- small preset, generator BRDF


def _rotate_views(v, deg):
    """Each view rotated by ``deg`` about the axis v × up (exactly ``deg`` from its source)."""
    ax = skin.normalize(np.cross(v, [0.0, 1.0, 0.0]))
    th = np.radians(deg)
    return (v * np.cos(th) + np.cross(ax, v) * np.sin(th)
            + ax * np.sum(ax * v, 1, keepdims=True) * (1 - np.cos(th)))


@pytest.fixture(scope="module")
def small_case():
    """400 random head pixels of the small preset's first camera: OLAT functions of the
    generator's (mismatched) BRDF under the 32 × 16 grid as distant lights, with and without
    cast shadows, the same points' exact functions seen from views 30° and 60° away, and the
    fit with the default depth."""
    from facegeo.appearance.brdf import synthetic_diffuse_brdf
    from facegeo.synth.capture import PRESETS, build_head, build_rig
    from facegeo.synth.render import ReferenceRenderer
    from facegeo.synth.skin import SkinField

    pre = PRESETS["small"]
    mesh = build_head("procedural", subdivisions=pre.head_subdivisions, seed=0)
    rig = build_rig(pre)
    stage = replace(rig.lights, radius=float("inf"))
    ren = ReferenceRenderer.from_mesh(mesh, SkinField.for_mesh(mesh, seed=0))
    view = ren.surface_view(rig.cameras[0])
    col = np.asarray(stage.color, float)
    idx = np.sort(np.random.default_rng(0).choice(view.n_samples, 400, replace=False))
    sel = np.zeros(view.n_samples, bool)
    sel[idx] = True

    def olat(vw, shadows=True):
        ren.shadows = shadows
        return np.stack([ren.shade_directional_light(vw, d, col, sel=sel)
                         for d in stage.directions], axis=1)

    R, R_free = olat(view), olat(view, shadows=False)
    v0, n = view.v_world[idx], view.n_world[idx]
    novel = {}
    for deg in (30.0, 60.0):
        vn = _rotate_views(v0, deg)
        v_all = view.v_world.copy()
        v_all[idx] = vn
        novel[deg] = (vn, olat(replace(view, v_world=v_all)))
    unshadowed = np.all(np.abs(R - R_free) <= 1e-7 + 1e-6 * np.abs(R_free), axis=(1, 2))
    lights = skin.LightSet.from_grid(stage.n_theta, stage.n_phi, stage.color)
    L = lights.n_lights
    l = np.broadcast_to(lights.directions[None], (len(idx), L, 3))
    fd = synthetic_diffuse_brdf(np.broadcast_to(n[:, None], l.shape), l,
                                np.broadcast_to(v0[:, None], l.shape),
                                view.alpha_0[idx][:, None].astype(float),
                                view.alpha_1[idx][:, None].astype(float),
                                view.rho_s[idx][:, None].astype(float),
                                view.roughness[idx][:, None].astype(float))
    x = np.maximum(n @ lights.directions.T, 0.0)
    wx = lights.solid_angles * x
    rho_true = np.pi * np.einsum("nl,nlc->nc", wx, fd * x[..., None]) / np.sum(wx * x, 1)[:, None]
    fit = skin.fit_reflectance(R, v0, lights)
    # the generator's own specular part (unshadowed functions): R minus its diffuse term
    S_true = R_free - fd * x[..., None] * lights.intensities[None]
    return {"R": R, "v0": v0, "n": n, "novel": novel, "unshadowed": unshadowed,
            "lights": lights, "rho_true": rho_true, "fit": fit, "S_true": S_true}


def _small_resynthesis_errors(case, deg):
    vn, truth = case["novel"][deg]
    m = case["unshadowed"] & (np.sum(case["n"] * vn, 1) > np.cos(np.radians(75)))
    out = skin.resynthesize(case["fit"], vn).reflectance

    def rel(a):
        return float(np.sqrt(np.sum((a[m] - truth[m]) ** 2) / np.sum(truth[m] ** 2)))

    return rel(out), rel(case["R"]), int(m.sum())


@pytest.mark.slow
def test_small_preset_generator_normals_and_exact_recombination(small_case):
    c = small_case
    fit, R, un = c["fit"], c["R"], c["unshadowed"]
    err = _angle_deg(fit.normal, c["n"])[un]
    err_m = _angle_deg(fit.normal_moment, c["n"])[un]
    print(f"small preset, generator BRDF: median normal error over {un.sum()} unshadowed "
          f"pixels {np.median(err):.3f}° (moment {np.median(err_m):.2f}°)")
    assert np.median(err) <= SMALL_NORMAL_MEDIAN_DEG
    ulp = np.spacing(np.float32(np.abs(R).max()))
    assert np.abs(fit.diffuse + fit.specular - R).max() <= RECOMBINE_ULPS * ulp
    same = skin.resynthesize(fit, c["v0"]).reflectance
    assert np.abs(same - R).max() <= RECOMBINE_ULPS * ulp


@pytest.mark.slow
def test_small_preset_generator_albedo_and_resynthesis(small_case):
    """Issue 13's bar on the mismatched generator: albedo and resynthesis. Failed (albedo
    56 %, resynthesis 3× worse than naive) while the ramp's polish could slide along the lobe
    criterion's flat scale direction; the chromaticity rows (SearchDepth.chroma) pin it."""
    c = small_case
    fit, un = c["fit"], c["unshadowed"]
    rel = np.linalg.norm(fit.rho_d - c["rho_true"], axis=1) / np.linalg.norm(c["rho_true"], axis=1)
    figures = {deg: _small_resynthesis_errors(c, deg) for deg in (30.0, 60.0)}
    print(f"small preset, generator BRDF: median albedo error {np.median(rel[un]):.3f}; "
          + "; ".join(f"{deg:.0f}°: resynthesis relative RMSE {r:.3f}, naive {nv:.3f} "
                      f"({m} pixels)" for deg, (r, nv, m) in figures.items()))
    assert np.median(rel[un]) <= SMALL_ALBEDO_MEDIAN_REL
    for r, naive, _ in figures.values():
        assert r * SMALL_RESYNTH_VS_NAIVE <= naive


def _generator_diffuse(rng, lights, N):
    """The generator's diffuse term alone (brdf.synthetic_diffuse_brdf: skin-like α_0, a
    desaturated α_1, Fresnel weights (1 − ρ_dr)²) for N random normals, seen from V0:
    ``(N, L, 3)`` float32 OLAT radiance under unit lights."""
    from facegeo.appearance.brdf import desaturate, synthetic_diffuse_brdf

    n = _random_normals(rng, N, 40.0)
    a0 = np.array([0.62, 0.36, 0.26]) * rng.uniform(0.8, 1.1, (N, 1))
    a1 = desaturate(a0, rng.uniform(0.3, 0.6, N)) * 1.1
    sh = (N, lights.n_lights, 3)
    fd = synthetic_diffuse_brdf(np.broadcast_to(n[:, None], sh),
                                np.broadcast_to(lights.directions[None], sh),
                                np.broadcast_to(V0, sh), a0[:, None], a1[:, None],
                                rng.uniform(0.4, 0.9, (N, 1)), rng.uniform(0.25, 0.5, (N, 1)))
    return (fd * np.maximum(n @ lights.directions.T, 0.0)[..., None]).astype(np.float32)


def test_generator_diffuse_alone_stays_diffuse():
    """Functions with no specular lobe at all — the generator's Fresnel-weighted diffuse colour
    blend (not the paper's ramp: its brightness falls off faster than Lambert's at grazing
    angles) — must not be separated into a large S. The lobe-shape criterion alone lets the
    ramp's polish absorb that fall-off by moving white light into S (37 % of the energy)."""
    lights = skin.LightSet.from_grid(32, 16)
    R = _generator_diffuse(np.random.default_rng(3), lights, 60)
    fit = skin.fit_reflectance(R, V0, lights)
    share = float(fit.specular.sum() / R.sum())
    print(f"generator diffuse alone: S holds {share:.4f} of the energy")
    assert share <= DIFFUSE_ONLY_S_SHARE


def test_noise_does_not_become_specular():
    """Noise on purely diffuse functions: the plain clamp max(μ_s, 0) keeps every positive
    excursion as S; the gate (``specular_gate=3``: μ_s above 3 σ of the function's negative
    μ_s) returns it to D."""
    lights = skin.LightSet.from_grid(32, 16)
    R = _generator_diffuse(np.random.default_rng(3), lights, 60)
    rng = np.random.default_rng(4)
    R = np.maximum(R + 0.01 * R.max(axis=(1, 2), keepdims=True) * rng.normal(size=R.shape), 0)
    R = R.astype(np.float32)
    fit = skin.fit_reflectance(R, V0, lights, specular_gate=3.0)
    share = float(fit.specular.sum() / R.sum())
    print(f"noisy diffuse: S holds {share:.4f} of the energy")
    assert share <= NOISY_DIFFUSE_S_SHARE
    ulp = np.spacing(np.float32(np.abs(R).max()))
    assert np.abs(fit.diffuse + fit.specular - R).max() <= RECOMBINE_ULPS * ulp


def test_gate_specular_keeps_lobes_above_the_noise():
    """gate_specular on a known μ_s: Gaussian noise (σ = 0.01) plus a few specular samples of
    0.2: the noise-level positives go back to D (D + S unchanged), the lobe stays whole."""
    from facegeo.appearance import _skin_fit

    rng = np.random.default_rng(9)
    mu_s = rng.normal(0.0, 0.01, (4, 500))
    mu_s[:, :10] = 0.2
    D0 = rng.uniform(0.1, 1.0, (4, 500, 3))
    D = D0 - (np.maximum(mu_s, 0.0) / np.sqrt(3.0))[..., None]
    Dg, mg, y = _skin_fit.gate_specular(D, mu_s, np.ones((4, 500)), 3.0)
    assert np.array_equal(mg[:, :10], mu_s[:, :10]), "the lobe is kept"
    # a Gaussian exceeds 3σ with probability 0.13 %: positives that survive are that rare
    # (without the gate, half the noise samples are S)
    assert np.mean(mg[:, 10:] > 0.0) <= 0.01, "noise-level positives are gated"
    Sg = (np.maximum(mg, 0.0) / np.sqrt(3.0))[..., None]
    assert np.abs(Dg + Sg - D0).max() <= 1e-12, "D + S unchanged"
    assert np.allclose(y, np.linalg.norm(Dg, axis=2))


@pytest.mark.slow
def test_small_preset_specular_only_where_the_generator_has_it(small_case):
    """Issue 13's diagnosis as a check: the share of the energy S holds by angle between the
    light and the mirror direction, against the generator's own specular part. With the lobe
    criterion alone (SearchDepth(chroma=0)) the polish put 27 % of the energy 45°–90° from the
    mirror and 9 % beyond 90° (the generator: 0.6 % and 0)."""
    c = small_case
    R, un, lights = c["R"], c["unshadowed"], c["lights"]
    v0, n = c["v0"], c["n"]
    r = 2.0 * np.sum(n * v0, 1, keepdims=True) * n - v0
    ang = np.degrees(np.arccos(np.clip(r @ lights.directions.T, -1.0, 1.0)))[un]
    edges = (0.0, 20.0, 45.0, 90.0, 180.1)
    tot = R[un].sum()

    def shares(S):
        S = S[un].sum(axis=2)
        return np.array([S[(ang >= a) & (ang < b)].sum() / tot
                         for a, b in zip(edges[:-1], edges[1:])])

    truth = shares(c["S_true"])
    ours = shares(c["fit"].specular)
    lobe_only = shares(skin.fit_reflectance(R, v0, lights,
                                            depth=skin.SearchDepth(chroma=0.0)).specular)
    for name, sh in (("generator", truth), ("fit", ours), ("lobe criterion alone", lobe_only)):
        print(f"S share by angle from the mirror direction 0-20/20-45/45-90/>90°, {name}: "
              + " / ".join(f"{x:.3f}" for x in sh))
    assert abs(ours.sum() - truth.sum()) <= SMALL_S_SHARE_ABS
    assert ours[2:].sum() <= truth[2:].sum() + SMALL_S_SHARE_ABS


# ---------------------------------------------------------------- a real face (Yale B01)

_YALE_NAME = re.compile(r"yaleB01_P00A([+-]\d{3})E([+-]\d{2})\.pgm$")


def _load_yale(folder):
    """All ``*.pgm`` frames (8-bit), light directions from the azimuth/elevation in the names,
    the ambient frame apart. The folder's ``.info`` lists only a 21-frame subset (plus the
    ambient), so the names, not it, enumerate the 64 flashes."""
    import cv2

    ambient = None
    frames, dirs = [], []
    for p in sorted(folder.glob("*.pgm")):
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert img is not None and img.dtype == np.uint8, f"{p}: not an 8-bit PGM"
        m = _YALE_NAME.search(p.name)
        if m is None:
            if "Ambient" in p.name:
                ambient = img.astype(np.float32)
            continue
        A, E = np.radians(float(m.group(1))), np.radians(float(m.group(2)))
        dirs.append([-np.cos(E) * np.sin(A), np.sin(E), np.cos(E) * np.cos(A)])
        frames.append(img)
    return np.array(frames), np.array(dirs), ambient


def _voronoi_solid_angles(dirs):
    """Solid angle (sr) of each light's spherical Voronoi cell over the unit sphere (sums to 4π);
    the scan format's own light list with Voronoi weights is not in yet."""
    from scipy.spatial import SphericalVoronoi

    sv = SphericalVoronoi(dirs, radius=1.0)
    return sv.calculate_areas()


def test_real_face_yale_b01(shared_data):
    """Diffuse-only fit on half the lights within 50° of the camera, relight the other half;
    compared with a plain least-squares Lambertian fit on the same samples and masks."""
    from conftest import shared_file

    folder = shared_file(shared_data, "olat/yale_b01")
    frames, dirs, ambient = _load_yale(folder)
    assert frames.shape[0] == 64 and ambient is not None
    saturated = frames >= 255
    I = np.clip(frames.astype(np.float32) - ambient[None], 0, None)  # linear, ambient removed
    near = np.flatnonzero(dirs[:, 2] >= np.cos(np.radians(50)))
    fit_l, test_l = near[0::2], near[1::2]
    H, W = I.shape[1:]
    Rall = I.reshape(len(I), -1).T  # (P, L)
    sat = saturated.reshape(len(I), -1).T
    bright = Rall[:, near].mean(axis=1)
    px = np.flatnonzero(bright > 0.25 * np.percentile(bright, 90))[::4]
    R, sat = Rall[px], sat[px]
    sa = _voronoi_solid_angles(dirs)
    assert abs(sa.sum() - 4 * np.pi) <= 1e-6
    lights = skin.LightSet.from_directions(dirs[fit_l], sa[fit_l])
    fit = skin.fit_reflectance(R[:, fit_l], V0, lights, saturation=254.5)
    assert fit.single_channel and (fit.flags & skin.FLAG_SINGLE_CHANNEL).all()
    k_ours = np.linalg.norm(fit.rho_d, axis=1) / np.pi
    # baseline: plain least squares b = argmin Σ δA (b·l − y)² over the same unmasked fit
    # samples (the same Voronoi weights as the fit)
    mask_fit = (~fit.shadow & ~sat[:, fit_l]) * sa[fit_l]
    Lf = dirs[fit_l]
    A = np.einsum("pl,li,lj->pij", mask_fit, Lf, Lf) + 1e-9 * np.eye(3)
    rhs = np.einsum("pl,pl,li->pi", mask_fit, R[:, fit_l], Lf)
    b = np.linalg.solve(A, rhs[..., None])[..., 0]
    # held-out lights, with shadowed (dark) and saturated samples masked for both
    y = R[:, test_l]
    ref = np.percentile(R[:, fit_l], 99, axis=1)
    mask = (y > skin.SHADOW_THRESHOLD * ref[:, None]) & ~sat[:, test_l] & fit.valid[:, None]
    pred_ours = k_ours[:, None] * np.maximum(fit.normal @ dirs[test_l].T, 0)
    pred_ls = np.maximum(b @ dirs[test_l].T, 0)
    err_ours = np.sqrt(np.sum(((pred_ours - y) * mask) ** 2) / np.sum((y * mask) ** 2))
    err_ls = np.sqrt(np.sum(((pred_ls - y) * mask) ** 2) / np.sum((y * mask) ** 2))
    print(f"Yale B01, {len(px)} pixels, fit on {len(fit_l)} lights, relit {len(test_l)}: "
          f"relative RMSE ours {err_ours:.4f}, least-squares Lambertian {err_ls:.4f}")
    assert err_ours <= err_ls


def test_negligible_specular_skips_specular_work():
    rng = np.random.default_rng(9)
    lights = skin.LightSet.from_grid(32, 16)
    n = _random_normals(rng, 4, 20.0)
    p = replace(_paper_params(rng, 4), rho_s=np.zeros(4))
    R = skin.paper_reflectance(n, V0, lights, p)
    fit = skin.fit_reflectance(R, V0, lights, d_0=skin.normalize(p.rho_d))
    r = skin.resynthesize(fit, _view(30.0))
    assert (r.flags & skin.FLAG_SPECULAR_SKIPPED).all()
    assert np.all(r.specular == 0)
    truth = skin.paper_reflectance(n, _view(30.0), lights, p)
    # diffuse-only functions: the chroma shift alone reproduces the new view (relative RMSE)
    assert np.sqrt(np.sum((r.reflectance - truth) ** 2) / np.sum(truth ** 2)) <= 1e-4
    # a view below the horizon of every normal: flagged, zero, finite
    back = skin.resynthesize(fit, -V0)
    assert (back.flags & skin.FLAG_BACKFACING).all() and np.all(back.reflectance == 0)


# ---------------------------------------------------------------- fast path (issue 13 speed)


def test_fast_ramp_mu_d_equals_explicit_separation():
    """The ramp search's closed-form μ_d equals Eq. 6 + the 3 × 3 separation of §4.2, including
    candidates whose separation is singular (1 + f ≈ 0) and d_0 ∥ s."""
    from facegeo.appearance._skin_fit import ramp_mu_d

    rng = np.random.default_rng(7)
    n_f, K, L = 5, 7, 40
    d0 = skin.normalize(np.array([0.8, 0.5, 0.35]) + rng.normal(0, 0.1, (n_f, 3)))
    d0[-1] = skin.S_WHITE  # d_0 = s: singular for every candidate
    R = rng.uniform(0.0, 1.0, (n_f, L, 3))
    xcos = rng.uniform(0.0, 1.0, (n_f, 1, L))
    p = rng.uniform(-0.6, 0.6, (n_f, K, 2))
    p[0, 0] = (-1.0, -1.0)  # f = −1 everywhere: u = s, singular
    p[1, 1] = (-0.999999, -1.0000001)  # 1 + f crosses 0 between the ramp's ends
    s = skin.S_WHITE
    Rd, Rs = np.einsum("nlc,nc->nl", R, d0), R @ s
    ds = d0 @ s
    ds2 = 1.0 - ds * ds
    A = np.where((ds2 > 0)[:, None], (Rd - Rs * ds[:, None]) / np.where(ds2 > 0, ds2, 1)[:, None], 0)
    fast = ramp_mu_d(p, xcos, A, Rd, Rd - Rs, ds)
    f = skin.ramp_f(xcos, 1.0, p[..., 0:1], p[..., 1:2])  # (n, K, L)
    c = skin.ramp_chromaticity(d0[:, None, None, :], f)
    _, _, mu_d, _, _, sing = skin.separate_colour(R[:, None], c)
    assert sing[0, 0].all() and sing[-1].all() and not sing[2].any()
    err = np.abs(fast - mu_d).max() / np.abs(R).max()
    assert err <= FAST_MU_D_REL, err


def test_direct_search_subset_stops_converged_problems_at_same_minimum():
    """subset=True evaluates only unconverged problems and reaches the same minimum to within
    the finest step as the all-problems search."""
    rng = np.random.default_rng(3)
    N, P = 40, 2
    centre = rng.uniform(-0.8, 0.8, (N, P))
    scale = rng.uniform(0.5, 50.0, (N, 1))
    calls = []

    def objective(cand, rows=None):
        c = centre if rows is None else centre[rows]
        sc = scale if rows is None else scale[rows]
        calls.append(cand.shape[0])
        return np.sum(sc[:, None, :] * (cand - c[:, None, :]) ** 2, axis=-1)

    x0 = np.zeros((N, P))
    full, _ = skin.direct_search(objective, x0, 0.25, 8, 6)
    assert set(calls) == {N}
    calls.clear()
    sub, _ = skin.direct_search(objective, x0, 0.25, 8, 6, subset=True)
    finest = 0.25 / 2 ** 8
    assert np.abs(sub - centre).max() <= finest
    assert np.abs(full - centre).max() <= finest
    assert np.abs(sub - full).max() <= finest
    assert min(calls) < N and calls == sorted(calls, reverse=True)  # converged ones stop


def test_chunk_size_does_not_change_the_fit():
    rng = np.random.default_rng(11)
    lights = skin.LightSet.from_grid(32, 16)
    n = _random_normals(rng, 10, 25.0)
    p = _paper_params(rng, 10)
    R = skin.paper_reflectance(n, V0, lights, p)
    a = skin.fit_reflectance(R, V0, lights, chunk=3)
    b = skin.fit_reflectance(R, V0, lights, chunk=10)
    assert np.abs(a.normal - b.normal).max() <= CHUNK_NORMAL_ABS
    assert np.abs(a.alpha_0 - b.alpha_0).max() <= CHUNK_ALPHA_ABS
    assert np.abs(a.alpha_1 - b.alpha_1).max() <= CHUNK_ALPHA_ABS


def test_forward_difference_polish_matches_central(paper_case, monkeypatch):
    from facegeo.appearance import _skin_fit

    lights, _n, p, R, fit = paper_case
    assert _skin_fit.POLISH_FORWARD  # the fixture's fit used the fast path
    monkeypatch.setattr(_skin_fit, "POLISH_FORWARD", False)
    central = skin.fit_reflectance(R, V0, lights, d_0=skin.normalize(p.rho_d))
    assert np.abs(central.alpha_0 - fit.alpha_0).max() <= FORWARD_POLISH_ALPHA_ABS
    assert np.abs(central.alpha_1 - fit.alpha_1).max() <= FORWARD_POLISH_ALPHA_ABS
    rel = np.abs(central.rho_s - fit.rho_s) / central.rho_s
    assert rel.max() <= FORWARD_POLISH_RHO_S_REL, rel.max()
    # and both recover the generator's ramp (the fast path is not worse)
    for f in (fit, central):
        assert np.max(np.abs(f.alpha_0 / p.alpha_0 - 1)) <= PAPER_PARAM_REL


def test_row_nanquantile_equals_numpy():
    from facegeo.appearance._skin_fit import _row_nanquantile

    rng = np.random.default_rng(2)
    a = rng.uniform(0, 1, (30, 17))
    a[rng.uniform(size=a.shape) < 0.4] = np.nan
    a[3] = np.nan  # no finite value
    a[4, 1:] = np.nan  # one
    for q in (0.5, 0.9):
        with np.errstate(all="ignore"), pytest.warns(RuntimeWarning):
            ref = np.nanquantile(a, q, axis=1)
        got = _row_nanquantile(a, q)
        assert np.array_equal(np.isnan(got), np.isnan(ref))
        ok = ~np.isnan(ref)
        assert np.abs(got[ok] - ref[ok]).max() <= 1e-15  # same interpolation to rounding


def test_skinfit_save_load_round_trip_bit_exact(paper_case, tmp_path):
    lights, _n, _p, R, fit = paper_case
    path = tmp_path / "fit.npz"
    fit.save(path)
    back = skin.SkinFit.load(path)
    for k in skin._SKINFIT_ARRAYS:
        a, b = getattr(fit, k), getattr(back, k)
        assert a.dtype == b.dtype and np.array_equal(a, b), k
    assert back.lights.grid == lights.grid and back.eta == fit.eta
    assert back.single_channel == fit.single_channel
    for k in ("directions", "solid_angles", "intensities"):
        assert np.array_equal(getattr(back.lights, k), getattr(lights, k)), k
    # a loaded fit resynthesises exactly like the original
    vn = _view(30.0)
    assert np.array_equal(skin.resynthesize(back, vn).reflectance,
                          skin.resynthesize(fit, vn).reflectance)
    free = skin.LightSet.from_directions(lights.directions[:8], None, None)
    fit2 = skin.fit_reflectance(R[:2, :8], V0, free)
    fit2.save(tmp_path / "free.npz")
    assert skin.SkinFit.load(tmp_path / "free.npz").lights.grid is None


def test_skinfit_load_errors_name_the_file(tmp_path):
    from facegeo.errors import ScanFormatError

    with pytest.raises(ScanFormatError, match="missing.npz"):
        skin.SkinFit.load(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    np.savez(bad, normal=np.zeros((2, 3)))
    with pytest.raises(ScanFormatError, match="bad.npz.*missing arrays"):
        skin.SkinFit.load(bad)


def test_compiled_kernels_match_numpy_reference(monkeypatch):
    """The numba searches and polish (_skin_kernels) against the numpy reference (KERNELS off):
    same algorithm, so the same fit to rounding — estimated d_0, a free light list with
    shadows (lobe band/moment split exercised at the terminator), the fixed-normal polish, and
    mismatched functions on which the chromaticity polish runs (on a subset of the chunk)."""
    from facegeo.appearance import _skin_fit

    rng = np.random.default_rng(21)
    lights = skin.LightSet.from_grid(32, 16)
    n = _random_normals(rng, 12, 60.0)
    p = _paper_params(rng, 12)
    R = skin.paper_reflectance(n, V0, lights, p)
    vis = rng.uniform(size=R.shape[:2]) > 0.1
    # mismatched functions: the chromaticity polish runs on some of them (not on paper data)
    Rg = _generator_diffuse(rng, lights, 8)
    Rg[:3] = R[:3]  # both kinds in one chunk: the second polish on a subset
    fits = {}
    for kern in (True, False):
        monkeypatch.setattr(_skin_fit, "KERNELS", kern)
        fits[kern] = (skin.fit_reflectance(R, V0, lights, visibility=vis),
                      skin.fit_reflectance(R, V0, lights, d_0=skin.normalize(p.rho_d),
                                           depth=skin.SearchDepth(polish_normal=False)),
                      skin.fit_reflectance(Rg, V0, lights),
                      # the ramp on a 16 × 8 subsample, then the finishing step on all lights
                      skin.fit_reflectance(Rg, V0, lights,
                                           depth=skin.SearchDepth(sample_lights=128)))
    for a, b in zip(fits[True], fits[False]):
        for k in ("normal", "normal_initial"):
            assert _angle_deg(getattr(a, k), getattr(b, k)).max() <= KERNEL_NORMAL_DEG, k
        for k in ("lobe_misfit", "lobe_misfit_moment"):
            assert np.abs(getattr(a, k) - getattr(b, k)).max() <= KERNEL_MISFIT_ABS, k
        assert np.abs(a.alpha_0 - b.alpha_0).max() <= KERNEL_ALPHA_ABS
        assert np.abs(a.alpha_1 - b.alpha_1).max() <= KERNEL_ALPHA_ABS
        assert np.abs(a.rho_s - b.rho_s).max() <= KERNEL_RHO_S_REL * b.rho_s.max()
        assert np.array_equal(a.flags, b.flags) and np.array_equal(a.cast_shadow, b.cast_shadow)
        assert np.abs(a.diffuse - b.diffuse).max() <= 1e-4 * np.abs(a.reflectance).max()


def test_light_subsample_is_even_and_only_for_large_sets():
    """The ramp fit's light subsample: every other azimuth of every other inclination on the
    64 × 32 grid (512 lights), every 4th light of a 2048-light free list, none where the set
    has at most twice the lights asked for (or 0 asked)."""
    from facegeo.appearance._skin_fit import light_subsample
    from facegeo.frames import light_grid_indices

    grid = skin.LightSet.from_grid(64, 32)
    m = light_subsample(grid, 512)
    i, j = light_grid_indices(np.arange(grid.n_lights), 64)
    assert m.sum() == 512 and np.array_equal(m, (i % 2 == 0) & (j % 2 == 0))
    assert light_subsample(skin.LightSet.from_grid(128, 64), 512).sum() == 512  # stride 4
    free = skin.LightSet.from_directions(grid.directions)
    assert np.array_equal(np.flatnonzero(light_subsample(free, 512)), np.arange(0, 2048, 4))
    assert light_subsample(skin.LightSet.from_grid(32, 16), 512) is None
    assert light_subsample(grid, 1024) is None and light_subsample(grid, 0) is None


def test_light_subsample_fit_reaches_the_all_lights_fit():
    """At 2048 lights the ramp's search and polishes run on 512 lights and one
    Levenberg–Marquardt step on all lights finishes (SearchDepth.sample_lights, .finish): on
    noisy paper-mode data the α's land where the all-lights fit does, far inside that fit's
    own noise error (without the finishing step they do not), and the normals agree."""
    rng = np.random.default_rng(13)
    lights = skin.LightSet.from_grid(64, 32, color=(0.9, 1.0, 1.1))
    n = _random_normals(rng, 64, 25.0)
    p = _paper_params(rng, 64)
    R = skin.paper_reflectance(n, V0, lights, p)
    R = np.maximum(R + rng.normal(0.0, 0.005 * R.max(), R.shape), 0.0)
    d0 = skin.normalize(p.rho_d)
    every = skin.fit_reflectance(R, V0, lights, d_0=d0, depth=skin.SearchDepth(sample_lights=0))
    for depth, reaches in ((skin.SearchDepth(), True), (skin.SearchDepth(finish=0), False)):
        sub = skin.fit_reflectance(R, V0, lights, d_0=d0, depth=depth)
        for name, truth in (("alpha_0", p.alpha_0), ("alpha_1", p.alpha_1)):
            gap = np.median(np.abs(getattr(sub, name) - getattr(every, name)))
            err = np.median(np.abs(getattr(every, name) - truth))
            assert (gap <= SUBSAMPLE_ALPHA_OF_ERROR * err) == reaches, (depth, name, gap, err)
    assert np.median(_angle_deg(sub.normal, n)) <= PAPER_NORMAL_MEDIAN_DEG


@pytest.mark.parametrize("chroma", [False, True])
@pytest.mark.parametrize("with_normal", [True, False])
def test_polish_analytic_jacobian_equals_central_differences(with_normal, chroma):
    """The polish's analytic JᵀJ and Jᵀr against central differences of its residuals, with
    and without the chromaticity rows (whose residuals _polish_residuals only sums: their
    Jacobian is checked through the gradient of the total)."""
    from facegeo.appearance import _skin_kernels as K

    rng = np.random.default_rng(5)
    m = 300
    l = skin.normalize(rng.normal(size=(m, 3)) + [0, 0, 1.5])
    lx, ly, lz = (np.ascontiguousarray(l[:, i]) for i in range(3))
    normal = skin.normalize(np.array([0.2, -0.1, 1.0]))
    t1 = skin.normalize(np.cross(normal, [1.0, 0, 0]))
    t2 = np.cross(normal, t1)
    v = skin.normalize(np.array([0.1, 0.3, 1.0]))
    sqw = rng.uniform(0.1, 1.0, m)
    A, Rd, Rdms = rng.uniform(0.2, 1.0, m), rng.uniform(0.2, 1.0, m), rng.uniform(-0.2, 0.2, m)
    B, cw = rng.uniform(-0.5, 0.5, m), rng.uniform(0.0, 0.3, m)
    nl_fix = np.maximum(l @ normal, 0.0)
    xs_fix = np.clip(nl_fix, 0, 1) * np.clip(normal @ v, 0, 1)
    ds = 0.9
    args = (2.0 * (1.0 - ds), 1.0 - ds * ds, 1e-4)
    p = np.array([0.3, -0.4, 0.05, -0.03]) if with_normal else np.array([0.3, -0.4])
    P = p.size
    JtJ, g = np.empty((P, P)), np.empty(P)
    K._polish_jacobian(p, with_normal, normal, t1, t2, v, lx, ly, lz, sqw, A, Rd, Rdms, *args,
                       xs_fix, nl_fix, JtJ, g, B, cw, chroma)
    tot = K._polish_residuals(p, with_normal, normal, t1, t2, v, lx, ly, lz, sqw, A, Rd, Rdms,
                              *args, np.empty(m), xs_fix, nl_fix, B, cw, chroma)

    def rows(q):
        """Every residual row: the lobe rows, then the chromaticity rows c_j μ_s (numpy)."""
        out = np.empty(m)
        K._polish_residuals(q, with_normal, normal, t1, t2, v, lx, ly, lz, sqw, A, Rd, Rdms,
                            *args, out, xs_fix, nl_fix, B, cw, False)
        if not chroma:
            return out
        if with_normal:
            nq = skin.normalize(normal + q[2] * t1 + q[3] * t2)
            x = np.clip(l @ nq, 0, 1) * np.clip(nq @ v, 0, 1)
        else:
            x = xs_fix
        f = q[1] + (q[0] - q[1]) * x
        return np.concatenate([out, cw * (B + A * f / (1 + f))])

    rr0 = rows(p)
    assert np.sum(rr0 ** 2) == pytest.approx(tot, rel=1e-12)
    # the LM steps' Σ r² without the residual rows: from the first pass's sums where it is
    # large (here ≈ 0.1–1), relative error of that cancelling form ≤ 1e-10
    assert tot > 10 * K._SUMS_MIN
    tot_sums = K._polish_residuals(p, with_normal, normal, t1, t2, v, lx, ly, lz, sqw, A, Rd,
                                   Rdms, *args, np.empty(m), xs_fix, nl_fix, B, cw, chroma, False)
    assert tot_sums == pytest.approx(tot, rel=POLISH_SUMS_REL)
    J = np.empty((P, rr0.size))
    h = 1e-6
    for a in range(P):
        q1, q2 = p.copy(), p.copy()
        q1[a] += h
        q2[a] -= h
        J[a] = (rows(q1) - rows(q2)) / (2 * h)
    assert np.abs(J @ J.T - JtJ).max() <= KERNEL_JACOBIAN_REL * np.abs(JtJ).max()
    assert np.abs(J @ rr0 - g).max() <= KERNEL_JACOBIAN_REL * np.abs(J).max() * np.abs(rr0).max()


def test_threads_do_not_change_the_fit():
    """Each function is one problem on one thread: the fit is bit-identical at any thread count."""
    import numba

    rng = np.random.default_rng(8)
    lights = skin.LightSet.from_grid(32, 16)
    n = _random_normals(rng, 9, 30.0)
    R = skin.paper_reflectance(n, V0, lights, _paper_params(rng, 9))
    a = skin.fit_reflectance(R, V0, lights, threads=1)
    b = skin.fit_reflectance(R, V0, lights, threads=numba.config.NUMBA_NUM_THREADS)
    for k in ("normal", "alpha_0", "alpha_1", "rho_d", "rho_s", "diffuse"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    with pytest.raises(InputError, match="threads"):
        skin.fit_reflectance(R, V0, lights, threads=0)


#: Compiled polish stopping converged functions (_skin_fit.POLISH_XTOL) against every
#: iteration (POLISH_XTOL = 0), same functions: max |Δα| (paper mode, d_0 known and
#: estimated, and mismatched functions on which the chromaticity polish runs; measured 9e-10
#: here, ≤ 1e-8 at 2048 lights). Stopping at steps of 1e-3 instead moves α's by 5e-6.
POLISH_STOP_ALPHA_ABS = 1e-6


def _mixed_functions(rng, lights, n_paper, n_generator):
    """Paper-mode functions (the polish converges in a few steps) and the generator's diffuse
    term (the chromaticity polish runs), interleaved, with their paper-mode d_0."""
    n = _random_normals(rng, n_paper, 50.0)
    p = _paper_params(rng, n_paper)
    R = np.concatenate([skin.paper_reflectance(n, V0, lights, p),
                        _generator_diffuse(rng, lights, n_generator)])
    order = rng.permutation(len(R))
    return R[order], order


def test_polish_early_stop_matches_all_iterations(monkeypatch):
    from facegeo.appearance import _skin_fit

    rng = np.random.default_rng(31)
    lights = skin.LightSet.from_grid(32, 16)
    R, _ = _mixed_functions(rng, lights, 14, 10)
    fits = {}
    for xtol in (_skin_fit.POLISH_XTOL, 0.0):
        monkeypatch.setattr(_skin_fit, "POLISH_XTOL", xtol)
        fits[xtol] = skin.fit_reflectance(R, V0, lights)
    a, b = fits.values()
    assert np.abs(a.alpha_0 - b.alpha_0).max() <= POLISH_STOP_ALPHA_ABS
    assert np.abs(a.alpha_1 - b.alpha_1).max() <= POLISH_STOP_ALPHA_ABS
    assert _angle_deg(a.normal, b.normal).max() <= KERNEL_NORMAL_DEG


def test_parallel_chunks_equal_serial_fit():
    """threads=2 fits whole chunks on two worker threads: bit-identical to one thread. Chunks
    of 5 functions, so that both workers run several chunks each, interleaved; saturation and
    visibility exercise every output slice the workers write."""
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread")
    rng = np.random.default_rng(32)
    lights = skin.LightSet.from_grid(32, 16)
    R, _ = _mixed_functions(rng, lights, 15, 8)
    vis = rng.uniform(size=R.shape[:2]) > 0.05
    kw = dict(visibility=vis, saturation=float(np.quantile(R, 0.999)), chunk=5)
    a = skin.fit_reflectance(R, V0, lights, threads=1, **kw)
    b = skin.fit_reflectance(R, V0, lights, threads=2, **kw)
    for k in ("normal", "normal_moment", "normal_initial", "lobe_misfit", "d_0", "alpha_0",
              "alpha_1", "rho_d", "rho_s", "diffuse", "specular", "shadow", "cast_shadow",
              "saturated", "flags"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k


def test_fit_kernels_are_serial():
    """The fit's kernels run one function per loop iteration on the calling thread
    (``threads=`` parallelises whole chunks): none may be compiled with ``parallel=True``,
    whose parfor lowering compiled every loop body twice (a serial and a gufunc version, with
    int64 and uint64 indices) and made up about half of a cold first fit's ≈ 100 CPU-s
    (docs/skin.md, compile time)."""
    from numba.core.registry import CPUDispatcher

    from facegeo.appearance import _skin_kernels, _skin_kernels_samples

    found = 0
    for mod in (_skin_kernels, _skin_kernels_samples):
        for name, obj in vars(mod).items():
            if isinstance(obj, CPUDispatcher) and obj.__module__ == mod.__name__:
                found += 1
                assert not obj.targetoptions.get("parallel"), f"{mod.__name__}.{name}"
    assert found >= 30


def test_selection_equals_numpy_quantile():
    """The kernels' order-statistic selection (``_percentile_select``, replacing
    ``np.partition``) against ``np.quantile``, exactly: ties (integer values), one value,
    sorted and reversed input, the quantiles the fit uses; the input is not modified."""
    from facegeo.appearance._skin_kernels_samples import _percentile_select

    rng = np.random.default_rng(35)
    cases = [rng.normal(size=301), rng.integers(0, 4, 257).astype(np.float64), np.ones(9),
             np.arange(50.0), np.arange(50.0)[::-1].copy(), np.array([2.5])]
    for a in cases:
        for k in sorted({1, a.size // 2 + 1, a.size}):
            for q in (0.0, 0.5, 0.9, 0.99, 1.0):
                before = a.copy()
                assert _percentile_select(a, k, q) == np.quantile(a[:k], q), (a[:5], k, q)
                assert np.array_equal(a, before)
    assert np.isnan(_percentile_select(np.zeros(3), 0, 0.5))


def test_chunk_setup_kernel_equals_numpy_steps():
    """The fused set-up (white balance, saturation, §4.4 shadow map, brightness statistics)
    against the numpy steps it replaces, bit for bit: float32 and float64 input, per-light
    colour intensities, saturated samples, caller visibility, a black and a fully saturated
    function."""
    from facegeo.appearance._skin_kernels_samples import prepare_chunk

    rng = np.random.default_rng(34)
    L = 300
    E = rng.uniform(0.5, 2.0, (L, 3))
    R = (rng.uniform(0, 1, (9, L, 3)) ** 3 * rng.uniform(0.1, 1, (9, 1, 3))).astype(np.float32)
    R[2] = 0.0
    R[4] = 1.0
    vis = rng.uniform(size=(9, L)) > 0.2
    level = 0.6
    for arr in (R, R.astype(np.float64)):
        for sat_level, v in ((level, vis), (None, None)):
            Rw, sat, shadow, bmax, ref = prepare_chunk(
                arr, E, np.inf if sat_level is None else sat_level, 0.02,
                np.ones((1, 1), bool) if v is None else v, v is not None)
            Rc = np.asarray(arr, np.float64)
            sat_np = (np.zeros(R.shape[:2], bool) if sat_level is None
                      else (Rc >= sat_level).any(axis=2))
            Rw_np = Rc / E[None]
            assert np.array_equal(Rw, Rw_np) and np.array_equal(sat, sat_np)
            assert sat[4].all() == (sat_level is not None)
            assert np.array_equal(shadow, skin.shadow_map(Rw_np, threshold=0.02, visibility=v,
                                                          saturated=sat_np))
            assert np.array_equal(bmax, np.where(sat_np, 0.0, Rw_np.sum(axis=2)).max(axis=1))
            assert np.array_equal(ref, np.percentile(
                np.where(sat_np, 0.0, np.linalg.norm(Rw_np, axis=2)), 99, axis=1))


def test_specular_energy_kernel_equals_numpy_reference(monkeypatch):
    """ρ_s by the compiled kernel against the numpy reference (brdf's F and G), including
    shadowed lights, l = −v (H undefined) and grazing views."""
    from facegeo.appearance import _skin_fit

    rng = np.random.default_rng(4)
    lights = skin.LightSet.from_grid(32, 16)
    N = 40
    n = _random_normals(rng, N, 80.0)
    v = _random_normals(rng, N, 85.0)
    v[0] = -lights.directions[5]  # l_5 = −v
    S = rng.uniform(0, 1, (N, lights.n_lights)) * (rng.uniform(size=(N, lights.n_lights)) > 0.3)
    shadow = rng.uniform(size=S.shape) > 0.8
    got = _skin_fit.specular_energy(S, shadow, lights, n, v, 1.4)
    monkeypatch.setattr(_skin_fit, "KERNELS", False)
    ref = _skin_fit.specular_energy(S, shadow, lights, n, v, 1.4)
    assert np.all(np.isfinite(got))
    assert np.abs(got - ref).max() <= 1e-12 * max(1.0, np.abs(ref).max())


def test_median_ratio_kernel_equals_numpy_reference(monkeypatch):
    """d_0's median ratios (§4.2) by the compiled kernel against the numpy reference, with
    masked samples, zero channels and a function without any usable sample."""
    from facegeo.appearance import _skin_fit

    rng = np.random.default_rng(6)
    R = rng.uniform(0, 1, (25, 200, 3)) * rng.uniform(0.2, 1, (25, 1, 3))
    R[rng.uniform(size=R.shape) < 0.05] = 0.0
    valid = rng.uniform(size=R.shape[:2]) > 0.3
    valid[3] = False
    got, found = _skin_fit.initial_diffuse_chromaticity(R, valid)
    monkeypatch.setattr(_skin_fit, "KERNELS", False)
    ref, found_ref = _skin_fit.initial_diffuse_chromaticity(R, valid)
    assert np.array_equal(found, found_ref) and not found[3]
    assert np.abs(got - ref).max() <= 1e-14


# ---------------------------------------------------------------- compiled resynthesis (issue 14)

#: Compiled resynthesis (_skin_resynth_kernels) against the numpy reference (KERNELS off):
#: max |Δ| over reflectance, diffuse and specular / max |reference reflectance|. Same formulas
#: up to float64 rounding (reciprocals for divisions, FMA contraction), which the float32
#: outputs hide: measured bit-identical on these cases; a wrong factor, light or interpolation
#: node moves samples by > 1e-3 (tried: F at 0.999 v·H, l_q's z scaled by 0.9999).
RESYNTH_KERNEL_REL = 1e-5
#: resynthesize_relit against resynthesize(...).reflectance @ weights: max |Δ| / max |ref|.
#: The reference rounds each new sample to float32 before the sum (≈ 6e-8 relative).
RESYNTH_RELIT_REL = 1e-6


def _resynth_hard_case(rng, lights, N=24):
    """A fit with the hard cases of Eq. 9 and per-function novel views: v_n = v_0, back-facing
    and grazing v_n, normals up to 80° from the view (grazing lights), randomly shadowed
    lights (hidden lobes) and functions whose specular part is zero (skipped)."""
    n = _random_normals(rng, N, 80.0)
    p = _paper_params(rng, N)
    R = skin.paper_reflectance(n, V0, lights, p)
    vis = rng.uniform(size=R.shape[:2]) > 0.15
    fit = skin.fit_reflectance(R, V0, lights, visibility=vis)
    spec = fit.specular.copy()
    spec[-3:] = 0.0
    fit = replace(fit, specular=spec)
    vn = skin.normalize(_random_normals(rng, N, 60.0) + rng.normal(0, 0.05, (N, 3)))
    vn[:3] = V0  # the source view: measured function back
    vn[3] = -fit.normal[3]  # below the horizon
    vn[4] = skin.normalize(-fit.normal[4] + V0)
    t = skin.normalize(np.cross(fit.normal[5:7], [0.0, 1.0, 0.0]))
    vn[5:7] = skin.normalize(t + 1e-3 * fit.normal[5:7])  # grazing v_n
    return fit, vn


@pytest.mark.parametrize("free", [False, True])
def test_resynthesis_kernel_equals_numpy_reference(monkeypatch, free):
    """resynthesize by the compiled kernel against the numpy reference on the grid and on a
    free light list, with v_n = v_0, grazing and back-facing views, shadowed lights and
    zero specular in one call — values and flags."""
    from facegeo.appearance import _skin_resynth

    rng = np.random.default_rng(31)
    if free:
        dirs = skin.normalize(rng.normal(size=(260, 3)))
        lights = skin.LightSet.from_directions(dirs[dirs[:, 2] > -0.3], None,
                                               rng.uniform(0.5, 2.0, (dirs[:, 2] > -0.3).sum()))
    else:
        lights = skin.LightSet.from_grid(32, 16, color=(0.9, 1.0, 1.1))
    fit, vn = _resynth_hard_case(rng, lights)
    got = skin.resynthesize(fit, vn)
    monkeypatch.setattr(_skin_resynth, "KERNELS", False)
    ref = skin.resynthesize(fit, vn)
    scale = np.abs(ref.reflectance).max()
    for k in ("reflectance", "diffuse", "specular"):
        a, b = getattr(got, k), getattr(ref, k)
        assert a.dtype == np.float32 and np.all(np.isfinite(a)), k
        assert np.abs(a - b).max() <= RESYNTH_KERNEL_REL * scale, k
    assert np.array_equal(got.flags, ref.flags)
    # every hard case is exercised
    for flag in (skin.FLAG_BACKFACING, skin.FLAG_SPECULAR_SKIPPED, skin.FLAG_SPECULAR_IN_SHADOW):
        assert (ref.flags & flag).any(), flag
    assert np.array_equal(got.reflectance[:3], (fit.diffuse[:3].astype(np.float64)
                                                + fit.specular[:3]).astype(np.float32))
    # never a lobe in an occluded direction (the same-view functions keep the measured one)
    assert np.all(got.specular[3:][fit.cast_shadow[3:]] == 0)
    assert np.any(got.specular[7:] > 0)


def test_resynthesis_kernel_view_independent_form_and_all_same(monkeypatch):
    """The view-independent form (resynthesis twice) and a call where every v_n is v_0 (the
    early return, back-facing functions kept) agree with the numpy reference."""
    from facegeo.appearance import _skin_resynth

    rng = np.random.default_rng(32)
    lights = skin.LightSet.from_grid(16, 8)
    fit, vn = _resynth_hard_case(rng, lights, N=10)
    out = {}
    for kern in (True, False):
        monkeypatch.setattr(_skin_resynth, "KERNELS", kern)
        out[kern] = (skin.resynthesize(fit, vn, view_independent_form=True),
                     skin.resynthesize(fit, fit.view))
    for a, b in zip(out[True], out[False]):
        scale = np.abs(b.reflectance).max()
        assert np.abs(a.reflectance - b.reflectance).max() <= RESYNTH_KERNEL_REL * scale
        assert np.array_equal(a.flags, b.flags)


@pytest.mark.parametrize("kernels", [True, False])
def test_resynthesize_relit_equals_relit_resynthesis(monkeypatch, kernels):
    """resynthesize_relit (Eq. 4 on the resynthesised functions, zero-weight lights skipped)
    equals relighting resynthesize's reflectance; also when every v_n is v_0."""
    from facegeo.appearance import _skin_resynth

    rng = np.random.default_rng(33)
    lights = skin.LightSet.from_grid(32, 16, color=(0.9, 1.0, 1.1))
    fit, vn = _resynth_hard_case(rng, lights)
    w = rng.uniform(0.0, 1.0, (lights.n_lights, 3)) * lights.solid_angles[:, None]
    w[rng.uniform(size=lights.n_lights) < 0.5] = 0.0
    monkeypatch.setattr(_skin_resynth, "KERNELS", kernels)
    for v in (vn, fit.view):
        ref = np.einsum("nlc,lc->nc", skin.resynthesize(fit, v).reflectance, w)
        got = _skin_resynth.resynthesize_relit(fit, v, w)
        assert got.shape == (vn.shape[0], 3)
        assert np.abs(got - ref).max() <= RESYNTH_RELIT_REL * np.abs(ref).max()
    with pytest.raises(ShapeError, match="weights"):
        _skin_resynth.resynthesize_relit(fit, vn, w[:-1])


def test_resynthesis_kernel_threads_do_not_change_the_result():
    """One function per thread: resynthesize and resynthesize_relit are bit-identical at any
    numba thread count (a race on the per-function scratch would show here)."""
    import numba

    from facegeo.appearance import _skin_resynth

    rng = np.random.default_rng(34)
    lights = skin.LightSet.from_grid(16, 8)
    fit, vn = _resynth_hard_case(rng, lights, N=40)
    w = rng.uniform(0.0, 1.0, (lights.n_lights, 3))
    out = {}
    old = numba.get_num_threads()
    try:
        for t in sorted({1, numba.config.NUMBA_NUM_THREADS}):
            numba.set_num_threads(t)
            out[t] = (skin.resynthesize(fit, vn), _skin_resynth.resynthesize_relit(fit, vn, w))
    finally:
        numba.set_num_threads(old)
    a, b = out[1], out[max(out)]
    for k in ("reflectance", "diffuse", "specular", "flags"):
        assert np.array_equal(getattr(a[0], k), getattr(b[0], k)), k
    assert np.array_equal(a[1], b[1])


def test_fit_writes_into_caller_outputs():
    """diffuse_out float32: the same D, written where the caller said (chunks of 4, two
    threads); float16: D is float16(D) of the float32 fit and S is formed from that rounded D
    (D + S = R to one float32 rounding); specular=False: S is not formed, every parameter the
    same; a fit without S refuses what needs it."""
    rng = np.random.default_rng(41)
    lights = skin.LightSet.from_grid(32, 16)
    R, _ = _mixed_functions(rng, lights, 6, 4)
    R = R.astype(np.float32)
    ref = skin.fit_reflectance(R, V0, lights, chunk=4, threads=2)
    out32 = np.full(R.shape, np.nan, np.float32)
    a = skin.fit_reflectance(R, V0, lights, chunk=4, threads=2, diffuse_out=out32)
    assert a.diffuse is out32 and np.array_equal(out32, ref.diffuse)
    assert np.array_equal(a.specular, ref.specular)
    out16 = np.full(R.shape, np.nan, np.float16)
    b = skin.fit_reflectance(R, V0, lights, chunk=4, threads=2, diffuse_out=out16)
    assert b.diffuse is out16 and np.array_equal(out16, ref.diffuse.astype(np.float16))
    assert np.array_equal(b.specular, R - out16.astype(np.float32))
    c = skin.fit_reflectance(R, V0, lights, chunk=4, threads=2, specular=False)
    assert c.specular is None and np.array_equal(c.diffuse, ref.diffuse)
    for k in ("normal", "alpha_0", "alpha_1", "rho_d", "rho_s", "flags", "shadow"):
        assert np.array_equal(getattr(c, k), getattr(ref, k)), k
        assert np.array_equal(getattr(b, k), getattr(ref, k)), k
    with pytest.raises(InputError, match="specular=False"):
        c.reflectance
    with pytest.raises(InputError, match="specular=False"):
        skin.resynthesize(c, np.array([0.5, 0.0, np.sqrt(0.75)]))


def test_fit_output_arrays_are_checked():
    rng = np.random.default_rng(42)
    lights = skin.LightSet.from_grid(16, 8)
    R = skin.paper_reflectance(_random_normals(rng, 3, 20.0), V0, lights,
                               _paper_params(rng, 3)).astype(np.float32)
    ro = np.zeros(R.shape, np.float32)
    ro.setflags(write=False)
    for bad, err, what in [(np.zeros((3, lights.n_lights, 1), np.float32), ShapeError, "shape"),
                           (np.zeros(R.shape), InputError, "dtype"),
                           (ro, InputError, "read-only"),
                           (np.zeros((3, lights.n_lights, 6), np.float32)[..., :3], InputError,
                            "C-contiguous"),
                           (R, InputError, "overlaps"),
                           ([[0.0]], InputError, "numpy array")]:
        with pytest.raises(err, match=what):
            skin.fit_reflectance(R, V0, lights, diffuse_out=bad)
