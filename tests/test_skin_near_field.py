"""The skin model on a near-field light stage (issue 36): each light where it is.

The generator's light stage has a radius of 1.5 m; a head ≈ 0.1 m across sees its lights up to
≈ 4° away from the stage directions, with ±14 % falloff. Fitting them as distant lights (the
paper's assumption) cost the fit stage its normals, its albedo and most of Eq. 9's gain
(docs/skin.md, "Near-field light stages"); :func:`skin.fit_reflectance_near` fits and
resynthesises with every light's true direction and falloff.

A few hundred pixels of the small preset's first camera, exact generator functions (its
mismatched BRDF, cast shadows) under the near-field stage: seconds.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from facegeo.appearance import skin

#: Median normal error of the near-field fit over valid functions, degrees (measured 0.18°;
#: the distant-light fit of the same functions 1.34°).
NEAR_NORMAL_MEDIAN_DEG = 0.5
#: Median albedo error against the generator's Lambertian-equivalent albedo (measured 3.0 %
#: on 400 pixels; the stage 2.4 %; issue 13's bar 3 % with a margin for the sample).
NEAR_ALBEDO_MEDIAN_REL = 0.04
#: Resynthesis relative RMSE (pooled over both turns about +Y, views in front of the true
#: surface) at least this many times lower than the naive reuse's (issue 13's bar; measured
#: 3.5× / 3.6× at 30° / 60° on 400 pixels; distant lights 0.86× / 1.5×).
NEAR_RESYNTH_VS_NAIVE = 3.0
#: The same with the stage given as a light list with positions (pipeline.fit._near_field: the
#: lights' mean distance as the radius): measured 0.150° (0.144° with the lights' distances
#: jittered 5 mm), the distant-light fit 1.285°; resampled by the 3 nearest lights' weights
#: instead of the triangulation (skin_resynth.barycentric_on_lights) it read 0.544°.
LIST_NORMAL_MEDIAN_DEG = NEAR_NORMAL_MEDIAN_DEG
#: D + S = R for the measured functions, in float32 ulps of the largest sample.
RECOMBINE_ULPS = 2
#: Compiled near-field steps against their numpy reference, relative to the largest sample.
KERNEL_REL = 1e-6
PIXELS = 300


@pytest.fixture(scope="module")
def near_case():
    from facegeo.lighting.envmap import rotation_y
    from facegeo.synth.capture import PRESETS, build_head, build_rig
    from facegeo.synth.render import ReferenceRenderer
    from facegeo.synth.skin import SkinField

    pre = PRESETS["small"]
    mesh = build_head("procedural", subdivisions=pre.head_subdivisions, seed=0)
    rig = build_rig(pre)
    stage = rig.lights
    assert np.isfinite(stage.radius), "the generator's stage is near-field"
    ren = ReferenceRenderer.from_mesh(mesh, SkinField.for_mesh(mesh, seed=0))
    view = ren.surface_view(rig.cameras[0])
    idx = np.sort(np.random.default_rng(0).choice(view.n_samples, PIXELS, replace=False))
    sel = np.zeros(view.n_samples, bool)
    sel[idx] = True
    pos = np.asarray(stage.center) + stage.radius * stage.directions
    col = np.asarray(stage.color, float)

    def olat(vw):
        return np.stack([ren.shade_point_light(vw, pos[l], col, stage_radius=stage.radius,
                                               sel=sel) for l in range(stage.n_lights)], axis=1)

    v0, n = view.v_world[idx], view.n_world[idx]
    novel = {}
    for deg in (30.0, 60.0):
        for sign in (1.0, -1.0):
            vn = v0 @ rotation_y(np.radians(sign * deg)).T
            v_all = view.v_world.copy()
            v_all[idx] = vn
            novel[(deg, sign)] = (vn, olat(replace(view, v_world=v_all)))
    lights = skin.LightSet.from_grid(stage.n_theta, stage.n_phi, stage.color)
    near = skin.NearField(view.p_world[idx] - np.asarray(stage.center), stage.radius)
    return {"R": olat(view), "v0": v0, "n": n, "novel": novel, "lights": lights, "near": near,
            "material": (view.alpha_0[idx], view.alpha_1[idx], view.rho_s[idx],
                         view.roughness[idx])}


def _median_normal_error(fit, n):
    cos = np.clip(np.sum(fit.normal * n, axis=1), -1.0, 1.0)
    return float(np.median(np.degrees(np.arccos(cos))[fit.valid]))


def _resynthesis_vs_naive(fit, case, deg):
    """(relative RMSE of the resynthesis, of the naive reuse) pooled over both turns."""
    se = sn = sr = 0.0
    for sign in (1.0, -1.0):
        vn, ref = case["novel"][(deg, sign)]
        front = (np.sum(vn * case["n"], axis=1) > 0) & fit.valid
        est = skin.resynthesize(fit, vn).reflectance
        se += float(((est[front] - ref[front]) ** 2).sum())
        sn += float(((case["R"][front] - ref[front]) ** 2).sum())
        sr += float((ref[front] ** 2).sum())
    return np.sqrt(se / sr), np.sqrt(sn / sr)


def test_near_field_fit_recovers_normals_and_albedo(near_case):
    from facegeo.appearance.brdf import lambertian_equivalent_albedo

    c = near_case
    fit = skin.fit_reflectance_near(c["R"], c["v0"], c["lights"], c["near"])
    distant = skin.fit_reflectance(c["R"], c["v0"], c["lights"])
    err, err_far = _median_normal_error(fit, c["n"]), _median_normal_error(distant, c["n"])
    ref = lambertian_equivalent_albedo(c["n"], c["v0"], *c["material"],
                                       c["lights"].directions, c["lights"].solid_angles)
    alb = np.linalg.norm(fit.rho_d - ref, axis=1) / np.linalg.norm(ref, axis=1)
    print(f"near-field fit: normals {err:.3f}° (as distant lights {err_far:.3f}°), "
          f"albedo {np.median(alb[fit.valid]):.4f}")
    assert err <= NEAR_NORMAL_MEDIAN_DEG
    assert err < err_far, "the near-field fit must beat the distant-light one"
    assert np.median(alb[fit.valid]) <= NEAR_ALBEDO_MEDIAN_REL


def test_near_field_resynthesis_beats_naive_3x(near_case):
    c = near_case
    fit = skin.fit_reflectance_near(c["R"], c["v0"], c["lights"], c["near"])
    ulp = np.spacing(np.float32(np.abs(c["R"]).max()))
    assert np.abs(fit.diffuse + fit.specular - c["R"]).max() <= RECOMBINE_ULPS * ulp
    same = skin.resynthesize(fit, c["v0"]).reflectance
    assert np.abs(same - c["R"]).max() <= RECOMBINE_ULPS * ulp, "the source view is kept"
    for deg in (30.0, 60.0):
        ours, naive = _resynthesis_vs_naive(fit, c, deg)
        print(f"near-field resynthesis {deg:.0f}°: {ours:.3f} vs naive {naive:.3f} "
              f"({naive / ours:.2f}×)")
        assert ours * NEAR_RESYNTH_VS_NAIVE <= naive


def test_near_field_rejects_points_outside_the_stage():
    from facegeo.errors import InputError

    with pytest.raises(InputError, match="inside the light sphere"):
        skin.NearField(np.array([[0.0, 0.0, 2.0]]), 1.5)
    with pytest.raises(InputError, match="radius"):
        skin.NearField(np.zeros((1, 3)), np.inf)


def test_near_field_masked_samples_stay_out_and_zero(near_case):
    """Masked samples (NaN in a projected field) are left out and get D = S = 0."""
    c = near_case
    R = c["R"][:40].copy()
    masked = np.zeros(R.shape[:2], bool)
    masked[:, ::7] = True
    R[masked] = np.nan
    fit = skin.fit_reflectance_near(R, c["v0"][:40], c["lights"], c["near"].take(np.arange(40)),
                                    masked=masked)
    assert np.all(fit.diffuse[masked] == 0) and np.all(fit.specular[masked] == 0)
    assert np.isfinite(fit.normal).all() and np.isfinite(fit.diffuse).all()
    assert np.all(fit.flags[fit.valid] & skin.FLAG_MASKED)


@pytest.mark.parametrize("with_mask", [False, True])
def test_kernels_match_the_numpy_reference(near_case, with_mask, monkeypatch):
    """The compiled near-field steps (``_near_field.KERNELS``) against the numpy path: the
    resampled functions and the measured separation, max |difference| relative to the
    largest sample (float32 storage: a few ulps)."""
    from facegeo.appearance import _near_field

    c = near_case
    R = c["R"][:60].astype(np.float32)
    near = c["near"].take(np.arange(60))
    masked = None
    if with_mask:
        masked = np.zeros(R.shape[:2], bool)
        masked[:, ::5] = True
        R = np.where(masked[..., None], np.float32(0.0), R)
    got = {}
    for k in (True, False):
        monkeypatch.setattr(_near_field, "KERNELS", k)
        Rd, md = _near_field.distant_equivalent(R, near, c["lights"], masked)
        fit = skin.fit_reflectance_near(R, c["v0"][:60], c["lights"], near, masked=masked)
        got[k] = (Rd, md, fit.diffuse)
    scale = float(np.abs(R).max())
    assert np.abs(got[True][0] - got[False][0]).max() <= KERNEL_REL * scale
    assert np.abs(got[True][2] - got[False][2]).max() <= KERNEL_REL * scale
    if with_mask:
        assert np.array_equal(got[True][1], got[False][1])


def _stage_as_list(case, radius_jitter_m=0.0):
    """The near case's stage grid as a light list with positions (a real rig's form), its
    lights moved along their own directions by ``radius_jitter_m`` (1 σ, seeded)."""
    from facegeo.geometry.lights import LightList
    from facegeo.synth.capture import PRESETS, build_rig

    stage = build_rig(PRESETS["small"]).lights
    r = stage.radius + radius_jitter_m * np.random.default_rng(3).standard_normal(stage.n_lights)
    return stage, LightList(positions=np.asarray(stage.center) + r[:, None] * stage.directions,
                            intensities=np.tile(np.asarray(stage.color, float),
                                                (stage.n_lights, 1)),
                            center=stage.center)


@pytest.mark.parametrize("jitter_m", [0.0, 0.005])
def test_a_light_list_with_positions_is_fitted_near_field(near_case, jitter_m):
    """The fit stage's near field for a light list (pipeline.fit._near_field): its lights'
    mean distance as the radius. Before, a list was fitted as distant lights (docs/synth.md:
    the grid written as a list cost the fit 1.2° of normals on ``tiny``)."""
    from types import SimpleNamespace

    from facegeo.pipeline.fit import _near_field
    from facegeo.render import light_set

    c = near_case
    stage, lights_list = _stage_as_list(c, jitter_m)
    tex = SimpleNamespace(p_world=c["near"].offsets + np.asarray(stage.center))
    near = _near_field(lights_list, tex, "auto")
    assert near is not None and abs(near.radius - stage.radius) < 3 * jitter_m + 1e-12
    lights = light_set(lights_list)
    fit = skin.fit_reflectance_near(c["R"], c["v0"], lights, near)
    distant = skin.fit_reflectance(c["R"], c["v0"], lights)
    err, err_far = _median_normal_error(fit, c["n"]), _median_normal_error(distant, c["n"])
    print(f"light list (radius jitter {jitter_m * 1e3:g} mm): normals {err:.3f}° near field, "
          f"{err_far:.3f}° as distant lights")
    assert err <= LIST_NORMAL_MEDIAN_DEG
    assert err < 0.5 * err_far


def test_a_light_list_far_from_a_sphere_is_fitted_as_distant_with_a_warning(near_case, caplog):
    from types import SimpleNamespace

    from facegeo.geometry.lights import LightList
    from facegeo.pipeline.fit import _near_field

    stage, _ = _stage_as_list(near_case)
    r = np.where(np.arange(stage.n_lights) % 2, 1.0, 2.0)  # half the lights at 1 m, half at 2
    lst = LightList(positions=np.asarray(stage.center) + r[:, None] * stage.directions,
                    center=stage.center)
    tex = SimpleNamespace(p_world=near_case["near"].offsets + np.asarray(stage.center))
    with caplog.at_level("WARNING"):
        assert _near_field(lst, tex, "auto") is None
    assert "33.3 % off their mean" in caplog.text
    assert _near_field(lst, tex, "off") is None
    directions_only = LightList(directions=stage.directions)
    assert _near_field(directions_only, tex, "auto") is None  # distant lights


def test_barycentric_interpolation_on_a_light_list_is_exact_for_linear_functions():
    """skin_resynth.barycentric_on_lights: the lights' values back at the lights, and a function
    linear in the direction (f(ω) = a·ω, which gnomonic barycentric weights reproduce up to
    the ray's length along each triangle: f(q)·Σλ = a·q) exactly, on a jittered sphere list
    and a hemisphere dome (queries outside the dome: weights clipped, still a convex mix)."""
    from facegeo.appearance._skin_resynth import barycentric_on_lights

    rng = np.random.default_rng(1)
    for kind in ("sphere", "dome"):
        d = rng.standard_normal((200, 3))
        if kind == "dome":
            d[:, 1] = np.abs(d[:, 1]) + 0.1
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        a = np.array([0.3, -1.2, 0.7])
        vals = np.stack([d @ a, np.ones(len(d))], axis=1)[None]  # (1, L, 2)
        at_lights = barycentric_on_lights(vals, d, d[None])
        np.testing.assert_allclose(at_lights[0], vals[0], atol=1e-12)
        q = rng.standard_normal((1, 500, 3))
        if kind == "dome":
            q[..., 1] = np.abs(q[..., 1]) + 0.2
        q /= np.linalg.norm(q, axis=2, keepdims=True)
        got = barycentric_on_lights(vals, d, q)[0]
        np.testing.assert_allclose(got[:, 1], 1.0, atol=1e-12)  # weights sum to 1
        lo, hi = vals[0, :, 0].min(), vals[0, :, 0].max()
        assert np.all((got[:, 0] >= lo - 1e-12) & (got[:, 0] <= hi + 1e-12))
        if kind == "sphere":  # every ray meets a triangle: f(q) = a·q / Σλ, compared along q
            from facegeo.appearance._skin_resynth import _light_triangulation

            tris, inv, _, _ = _light_triangulation(d)
            lam = np.einsum("fij,qj->qfi", inv, q[0])
            inside = (lam.min(axis=2) >= -1e-9)
            f = inside.argmax(axis=1)
            s_lam = lam[np.arange(len(f)), f].sum(axis=1)
            np.testing.assert_allclose(got[:, 0] * s_lam, q[0] @ a, atol=1e-9)


def test_barycentric_interpolation_falls_back_on_a_flat_ring():
    """Lights on one great circle have no triangulation: the 3 nearest lights' weights."""
    from facegeo.appearance._skin_resynth import barycentric_on_lights, interpolate_on_lights

    a = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    d = np.stack([np.cos(a), np.zeros_like(a), np.sin(a)], axis=1)
    vals = np.random.default_rng(2).random((1, 12, 3))
    q = np.random.default_rng(3).standard_normal((1, 40, 3))
    q /= np.linalg.norm(q, axis=2, keepdims=True)
    ring = skin.LightSet.from_directions(d)
    np.testing.assert_array_equal(barycentric_on_lights(vals, d, q),
                                  interpolate_on_lights(vals, ring, q))
