"""facegeo.synth._shade_kernels: the compiled per-light shading of the reference renderer
equals its numpy formulation (ReferenceRenderer.shade_point_light / shade_directional_light
with facegeo.appearance.brdf's skin BRDF) bit for bit, so OLAT frames and reference renders
are the same images whichever path made them."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from facegeo.cli import main

#: Lights compared one by one (of the tiny preset's 128): spread over the stage, including
#: lights behind the head (few or no lit samples) and the last index.
LIGHTS = (0, 5, 31, 64, 77, 100, 127)


@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    """The tiny preset's generator truth (skin field, eyes / teeth / mouth parts, true rig)."""
    from facegeo.capture.scan import load_scan
    from facegeo.synth.render import load_ground_truth

    root = tmp_path_factory.mktemp("shade") / "scan"
    assert main(["synth", str(root), "--preset", "tiny", "-q"]) == 0
    return load_ground_truth(load_scan(root))


@pytest.mark.parametrize("supersample", [1, 2])
def test_compiled_stage_light_equals_numpy_point_light(truth, supersample):
    cam, lights = truth.rig.cameras[0], truth.rig.lights
    view = truth.surface_view(cam, supersample=supersample)
    shade = truth._stage_light_shader(view, lights)
    centre, color = np.asarray(lights.center, float), np.asarray(lights.color, float)
    lit = 0
    for l in LIGHTS:
        ref = truth.shade_point_light(view, centre + lights.radius * lights.directions[l], color,
                                      stage_radius=lights.radius)
        np.testing.assert_array_equal(shade(l), ref, err_msg=f"light {l}")
        lit += int(np.count_nonzero(ref.any(axis=1)))
    assert lit > 0.1 * view.n_samples * len(LIGHTS)  # the comparison shaded something


def test_compiled_stage_light_equals_numpy_directional_light(truth):
    cam = truth.rig.cameras[1]
    lights = dataclasses.replace(truth.rig.lights, radius=math.inf)
    view = truth.surface_view(cam)
    shade = truth._stage_light_shader(view, lights)
    for l in LIGHTS:
        ref = truth.shade_directional_light(view, lights.directions[l],
                                            np.asarray(lights.color, float))
        np.testing.assert_array_equal(shade(l), ref, err_msg=f"light {l}")


def test_render_lights_is_the_eq4_sum_of_numpy_olat_radiance(truth):
    """Debevec et al. 2000 Eq. (4): Σ_l w_l ⊙ OLAT_l in light order, float64, then float32."""
    cam, lights = truth.rig.cameras[0], truth.rig.lights
    w = np.random.default_rng(1).random((lights.n_lights, 3))
    w[::3] = 0.0  # lights without energy are skipped, not shaded
    s = 2
    view = truth.surface_view(cam, supersample=s)
    acc = np.zeros((view.n_samples, 3))
    centre, color = np.asarray(lights.center, float), np.asarray(lights.color, float)
    for l in np.flatnonzero(w.any(axis=1)):
        acc += truth.shade_point_light(view, centre + lights.radius * lights.directions[l],
                                       color, stage_radius=lights.radius) * w[l][None, :]
    np.testing.assert_array_equal(truth.render_lights(cam, lights, w, supersample=s),
                                  view.to_image(acc.astype(np.float32)))


def test_compiled_shading_follows_float64_parameters(truth):
    """A view built by a caller with float64 materials (numpy then computes m² and π·m² in
    float64, not float32) is shaded as numpy shades it, through shade_stage_light."""
    cam, lights = truth.rig.cameras[0], truth.rig.lights
    v32 = truth.surface_view(cam)
    view = dataclasses.replace(v32, **{k: getattr(v32, k).astype(np.float64) for k in
                                       ("alpha_0", "alpha_1", "rho_s", "roughness")})
    centre, color = np.asarray(lights.center, float), np.asarray(lights.color, float)
    for l in LIGHTS:
        ref = truth.shade_point_light(view, centre + lights.radius * lights.directions[l], color,
                                      stage_radius=lights.radius)
        np.testing.assert_array_equal(truth.shade_stage_light(view, lights, l), ref,
                                      err_msg=f"light {l}")


def test_a_stage_light_on_the_surface_is_refused_by_both_paths(truth):
    """A point light exactly on a sample has no direction there: the compiled path refuses it
    as the numpy reference does (before, it left that sample unlit without a word)."""
    from facegeo.errors import InputError

    cam, lights = truth.rig.cameras[0], truth.rig.lights
    view = truth.surface_view(cam)
    l = LIGHTS[1]
    pos = np.asarray(lights.center, float) + lights.radius * lights.directions[l]
    p = view.p_world.copy()
    p[view.n_samples // 2] = pos  # one sample moved onto the light
    on = dataclasses.replace(view, p_world=p)
    with pytest.raises(InputError, match="lies on the surface"):
        truth.shade_point_light(on, pos, np.asarray(lights.color, float),
                                stage_radius=lights.radius)
    with pytest.raises(InputError, match=f"light {l} at .* lies on the surface"):
        truth._stage_light_shader(on, lights)(l)
    truth._stage_light_shader(view, lights)(l)  # the untouched view shades
