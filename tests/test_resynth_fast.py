"""The fast paths of Eq. 4 on resynthesised functions (facegeo.appearance._skin_resynth
``resynthesize_relit``): work skipped without changing the result (zero diffuse samples, the
lobe cone at ``lobe_tol = 0``), and the speed/accuracy options ``lobe_tol > 0`` and
``light_step > 1`` against the exact path."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_skin_model import V0, _paper_params, _random_normals, _resynth_hard_case

from facegeo.appearance import _skin_resynth, skin
from facegeo.errors import InputError

#: resynthesize_relit against resynthesize(...).reflectance @ weights (the numpy reference):
#: max |Δ| / max |ref|; the reference rounds each new sample to float32 before the sum.
RELIT_REL = 1e-6
#: lobe_tol > 0 against the exact path: relative RMSE ≤ this × lobe_tol (each dropped sample
#: is below lobe_tol of the lobe's peak microfacet value; dropping the lobe itself gives ≈ 0.3).
LOBE_TOL_REL_PER_TOL = 1.0
#: light_step = k with every block's energy in one light against the exact path: the block's
#: output light is that light (its direction renormalised), so only rounding differs; max |Δ| /
#: max |exact|.
ONE_LIGHT_BLOCK_REL = 1e-9
#: light_step = 2 under a smooth environment (a sky-like gradient over every light) against
#: the exact path: relative RMSE over functions and channels (measured 1.8e-3 on these
#: paper-model functions, the naive baseline 4e-2; the hard cases — grazing views and lights,
#: shadowed lobes — reach 6e-2).
LIGHT_STEP2_SMOOTH_REL = 1e-2


def _weights(rng, lights, zero_share=0.3):
    w = rng.uniform(0.2, 1.0, (lights.n_lights, 3)) * lights.solid_angles[:, None]
    w[rng.uniform(size=lights.n_lights) < zero_share] = 0.0
    return w


@pytest.fixture(scope="module")
def hard():
    rng = np.random.default_rng(41)
    lights = skin.LightSet.from_grid(32, 16, color=(0.9, 1.0, 1.1))
    fit, vn = _resynth_hard_case(rng, lights)
    # zero diffuse samples (all channels: skipped) and one zero channel (must not be skipped)
    D = fit.diffuse.copy()
    z = rng.uniform(size=D.shape[:2]) < 0.2
    D[z] = 0.0
    D[:, 5, 1] = 0.0
    fit = replace(fit, diffuse=D)
    return lights, fit, vn, _weights(rng, lights)


def _reference(monkeypatch, fit, vn, w):
    monkeypatch.setattr(_skin_resynth, "KERNELS", False)
    return np.einsum("nlc,lc->nc", skin.resynthesize(fit, vn).reflectance, w)


def test_fast_kernel_equals_numpy_reference_on_hard_cases(monkeypatch, hard):
    """The compiled relighting (zero diffuse samples skipped; with lobe_tol = 0 the lobe cone)
    against the numpy reference, on v_n = v_0, back-facing and grazing views, shadowed
    lobes, zero specular, zero diffuse samples and a single zero channel."""
    _, fit, vn, w = hard
    plain = _skin_resynth.resynthesize_relit(fit, vn, w)
    cone = _skin_resynth.resynthesize_relit(fit, vn, w, lobe_tol=0.0)
    ref = _reference(monkeypatch, fit, vn, w)
    scale = np.abs(ref).max()
    assert np.abs(plain - ref).max() <= RELIT_REL * scale
    # the cone at lobe_tol = 0 skips only samples that are exactly zero: bit-identical sums
    assert np.array_equal(cone, plain)


def test_lobe_cone_skips_only_what_it_may():
    """A fit whose lobe is confined (measured specular zero outside a 35° cap around the
    mirror direction): with lobe_tol = 0 the cone excludes most source directions yet the
    result is bit-identical (a wrong axis or too small a margin would drop non-zero samples);
    lobe_tol > 0 moves it by at most LOBE_TOL_REL_PER_TOL × lobe_tol."""
    rng = np.random.default_rng(42)
    lights = skin.LightSet.from_grid(32, 16)
    N = 16
    n = _random_normals(rng, N, 30.0)
    p = _paper_params(rng, N)
    fit = skin.fit_reflectance(skin.paper_reflectance(n, V0, lights, p), V0, lights)
    mirror = 2.0 * (fit.normal @ V0)[:, None] * fit.normal - V0
    cap = mirror @ lights.directions.T > np.cos(np.radians(35.0))  # (N, L)
    fit = replace(fit, specular=np.where(cap[..., None], fit.specular, 0.0).astype(np.float32))
    vn = skin.normalize(_random_normals(rng, N, 40.0))
    w = _weights(rng, lights, 0.0)
    exact = _skin_resynth.resynthesize_relit(fit, vn, w)
    assert np.array_equal(_skin_resynth.resynthesize_relit(fit, vn, w, lobe_tol=0.0), exact)
    tol = 0.05
    approx = _skin_resynth.resynthesize_relit(fit, vn, w, lobe_tol=tol)
    rel = np.sqrt(((approx - exact) ** 2).sum() / (exact ** 2).sum())
    assert rel <= LOBE_TOL_REL_PER_TOL * tol
    with pytest.raises(InputError, match="lobe_tol"):
        _skin_resynth.resynthesize_relit(fit, vn, w, lobe_tol=1.5)


@pytest.mark.parametrize("grid,step", [((32, 16), 2), ((24, 12), 3)])
def test_light_step_with_one_light_per_block_is_exact(grid, step):
    """light_step = k where each k × k block's energy sits in one (random) light: the block's
    output light is that light, so the result equals the exact path — a transposed block,
    a wrong member or a misplaced direction would not."""
    rng = np.random.default_rng(43)
    lights = skin.LightSet.from_grid(*grid, color=(0.9, 1.0, 1.1))
    fit, vn = _resynth_hard_case(rng, lights)
    nt, npf = grid
    w = np.zeros((lights.n_lights, 3))
    for bj in range(npf // step):
        for bi in range(nt // step):
            if rng.uniform() < 0.2:
                continue  # blocks without energy are skipped
            j = bj * step + rng.integers(step)
            i = bi * step + rng.integers(step)
            w[j * nt + i] = rng.uniform(0.2, 1.0, 3)
    exact = _skin_resynth.resynthesize_relit(fit, vn, w)
    got = _skin_resynth.resynthesize_relit(fit, vn, w, light_step=step)
    assert np.abs(got - exact).max() <= ONE_LIGHT_BLOCK_REL * np.abs(exact).max()


def test_light_step_under_a_smooth_environment():
    """light_step = 2 under a smooth sky-like environment, normals and views within 40° of
    each other's axis: close to the exact path, far closer than the naive baseline; v_n = v_0
    rows still give the measured function relit exactly."""
    rng = np.random.default_rng(44)
    lights = skin.LightSet.from_grid(32, 16, color=(0.9, 1.0, 1.1))
    N = 24
    n = _random_normals(rng, N, 40.0)
    fit = skin.fit_reflectance(skin.paper_reflectance(n, V0, lights, _paper_params(rng, N)), V0,
                               lights)
    vn = skin.normalize(_random_normals(rng, N, 40.0))
    vn[:3] = V0
    up = np.clip(lights.directions[:, 1], 0.0, 1.0)
    w = (0.3 + np.outer(up, [0.2, 0.4, 0.9])) * lights.solid_angles[:, None]
    exact = _skin_resynth.resynthesize_relit(fit, vn, w)
    got = _skin_resynth.resynthesize_relit(fit, vn, w, light_step=2)
    naive = np.einsum("nlc,lc->nc", fit.diffuse.astype(np.float64) + fit.specular, w)

    def rel(a):
        return np.sqrt(((a - exact) ** 2).sum() / (exact ** 2).sum())

    assert 0 < rel(got) <= LIGHT_STEP2_SMOOTH_REL < rel(naive)
    assert np.array_equal(got[:3], exact[:3])


def test_light_step_errors(hard):
    lights, fit, vn, w = hard
    for bad in (0, 1.5, 3, "2"):
        with pytest.raises(InputError, match="light_step"):
            _skin_resynth.resynthesize_relit(fit, vn, w, light_step=bad)
    free = skin.LightSet.from_directions(lights.directions, lights.solid_angles)
    with pytest.raises(InputError, match="light_step"):
        _skin_resynth.resynthesize_relit(replace(fit, lights=free), vn, w, light_step=2)
