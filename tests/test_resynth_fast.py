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
    monkeypatch.setattr(_skin_resynth, "VECTOR_KERNEL", False)  # the scalar kernel
    plain = _skin_resynth.resynthesize_relit(fit, vn, w)
    cone = _skin_resynth.resynthesize_relit(fit, vn, w, lobe_tol=0.0)
    ref = _reference(monkeypatch, fit, vn, w)
    scale = np.abs(ref).max()
    assert np.abs(plain - ref).max() <= RELIT_REL * scale
    # the cone at lobe_tol = 0 skips only samples that are exactly zero: bit-identical sums
    assert np.array_equal(cone, plain)


def test_lobe_cone_skips_only_what_it_may(monkeypatch):
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
    monkeypatch.setattr(_skin_resynth, "VECTOR_KERNEL", False)  # the cone is the scalar's
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


# --------------------------------------------------------------- the vectorised grid kernel

#: resynth_relit_grid (branch-free, fewer roots and divisions, polynomial atan2, reassociated
#: sums) against resynth_relit (the scalar kernel): max |Δ| / max |scalar| over functions and
#: channels. Rounding differs (sums reassociated, quotients folded): measured ≈ 1e-15.
VECTOR_REL = 1e-11
#: grid_angles against numpy's arctan2 / arccos: max absolute difference, radians (the
#: polynomial's error is 2.7e-14; arccos near the poles loses ≈ 1e-8 to cancellation, so
#: there φ is compared with arctan2(√(x² + z²), y)).
ANGLE_ABS = 1e-12
#: The lean factors (_diffuse_lean, _gf_ratio) against _diffuse and _geometry·_fresnel:
#: max relative difference (same formulas, quotients folded).
FACTOR_REL = 1e-12


def _relit_both(monkeypatch, fit, vn, w):
    from facegeo.appearance import _skin_resynth_kernels as K

    scalar_calls = []
    scalar = K.resynth_relit

    def spy(*a):
        scalar_calls.append(1)
        return scalar(*a)

    monkeypatch.setattr(K, "resynth_relit", spy)
    vec = _skin_resynth.resynthesize_relit(fit, vn, w)
    taken = not scalar_calls
    monkeypatch.setattr(_skin_resynth, "VECTOR_KERNEL", False)
    ref = _skin_resynth.resynthesize_relit(fit, vn, w)
    monkeypatch.setattr(_skin_resynth, "VECTOR_KERNEL", True)
    return vec, ref, taken


def test_vector_kernel_equals_scalar_kernel_on_hard_cases(monkeypatch, hard):
    """The vectorised kernel against the scalar one on v_n = v_0, back-facing and grazing
    views, normals up to 80° from v_0 (grazing lights), shadowed lights (hidden lobes), zero
    specular, zero diffuse samples and a zero channel — and it is the kernel that ran."""
    _, fit, vn, w = hard
    vec, ref, taken = _relit_both(monkeypatch, fit, vn, w)
    assert taken
    assert np.abs(vec - ref).max() <= VECTOR_REL * np.abs(ref).max()
    assert np.all(vec[3] == 0.0)  # back-facing: 0, as the scalar kernel


def test_vector_kernel_on_random_functions(monkeypatch):
    """Random paper-model functions and views (grazing included: normals up to 85°, views up
    to 85° from them), every light carrying energy, some lights shadowed."""
    rng = np.random.default_rng(45)
    lights = skin.LightSet.from_grid(24, 12, color=(0.9, 1.0, 1.1))
    N = 40
    n = _random_normals(rng, N, 85.0)
    fit = skin.fit_reflectance(skin.paper_reflectance(n, V0, lights, _paper_params(rng, N)),
                               V0, lights, visibility=rng.uniform(size=(N, 288)) > 0.1)
    vn = skin.normalize(_random_normals(rng, N, 85.0))
    w = _weights(rng, lights, 0.0)
    vec, ref, taken = _relit_both(monkeypatch, fit, vn, w)
    assert taken
    assert np.abs(vec - ref).max() <= VECTOR_REL * np.abs(ref).max()


def test_grid_angles_match_numpy():
    """θ = atan2(x, z) mod 2π and φ of the light-stage grid, at random directions, the axes,
    the poles' neighbourhood and the octant boundaries (|x| = |z|, ρ = |y|, a = tan(π/8))."""
    from facegeo.appearance._skin_resynth_kernels import grid_angles

    rng = np.random.default_rng(46)
    d = [rng.normal(size=3) for _ in range(2000)]
    d += [np.array(v, float) for v in ([1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, 0, -1],
                                        [1e-9, 1, 1e-9], [-1e-9, -1, 2e-9], [1, 0.3, 1],
                                        [-1, 1, 1e-3], [np.tan(np.pi / 8), 0.2, 1.0],
                                        [1, np.sqrt(2), -1])]
    worst_t = worst_p = 0.0
    for v in d:
        x, y, z = v / np.linalg.norm(v)
        t, p = grid_angles(x, y, z)
        t_ref = np.mod(np.arctan2(x, z), 2 * np.pi)
        dt = abs(t - t_ref)
        worst_t = max(worst_t, min(dt, 2 * np.pi - dt))
        worst_p = max(worst_p, abs(p - np.arctan2(np.hypot(x, z), y)))
        assert 0.0 <= t < 2 * np.pi and 0.0 <= p <= np.pi
    assert worst_t <= ANGLE_ABS and worst_p <= ANGLE_ABS


def test_lean_factors_match_the_scalar_ones():
    """_diffuse_lean against _diffuse (zero sample, f0 = −1 where the ramp cannot be
    inverted, negative 1 + f0) and _gf_ratio against _geometry·_fresnel (vh ≤ 0, vh = 0,
    grazing cosines)."""
    from facegeo.appearance import _skin_resynth_kernels as K

    rng = np.random.default_rng(47)
    e = (0.9, 1.0, 1.1)
    ie = tuple(1.0 / x for x in e)
    cases = [(*rng.uniform(0, 1, 3), *rng.uniform(-1.5, 1.0, 2)) for _ in range(300)]
    cases += [(0.0, 0.0, 0.0, 0.3, -0.2), (0.2, 0.1, 0.1, -1.0, 0.4),
              (0.2, 0.1, 0.05, -1.4, -1.2), (0.3, 0.3, 0.3, 0.0, 0.0)]
    for dr, dg, db, f0, fn in cases:
        a = np.array(K._diffuse(dr, dg, db, *e, *ie, f0, fn))
        b = np.array(K._diffuse_lean(dr, dg, db, *e, *ie, f0, fn))
        assert np.abs(a - b).max() <= FACTOR_REL * max(np.abs(a).max(), 1e-300)
    e2 = 1.38 ** 2 - 1.0
    for nl, nv, nh, vh in [tuple(rng.uniform(-0.2, 1.0, 4)) for _ in range(300)] + \
            [(0.5, 0.5, 0.9, 0.0), (0.5, 0.5, 0.9, -0.1), (1e-6, 0.9, 0.5, 0.3),
             (0.0, 0.5, 0.5, 0.5)]:
        gf = K._geometry(nl, nv, nh, vh) * K._fresnel(vh, e2)
        num, den = K._gf_ratio(nl, nv, nh, vh, e2)
        assert den > 0.0 and abs(num / den - gf) <= FACTOR_REL * max(gf, 1e-300)


# ----------------------------------------------------------------------------- float16 storage

#: The fused pass over float16 storage (``relit_stored``) against the float32 path it replaces
#: (R and D widened by numpy, S = R − D, ``resynthesize_relit``): per function, |Δ| relative to
#: the function's largest |value|. The samples are bit-identical and the resynthesis runs the
#: same per-function code, so only the order of float64 sums could differ.
STORED_RELIT_REL = 1e-12
#: The fused naive value (float64 sums of the float32 samples times float64 weights) against
#: the float32 matrix product ``R.reshape(n, 3L) @ W``: per function and channel, |Δ| relative
#: to Σ_l |w_l R_l| (the sgemm rounds weights and partial sums to float32: ≈ 1e-7 of that).
STORED_NAIVE_REL = 1e-6


def _float16_bits_to_float32(bits):
    """An independent decoder (IEEE 754 binary16 → value, float64 arithmetic) of every
    non-NaN bit pattern."""
    b = bits.astype(np.int64)
    sign = np.where(b >> 15, -1.0, 1.0)
    e = (b >> 10) & 0x1F
    m = (b & 0x3FF).astype(np.float64)
    val = np.where(e == 0, m * 2.0 ** -24, (1.0 + m / 1024.0) * 2.0 ** (e - 15.0))
    val = np.where(e == 0x1F, np.inf, val)
    return sign * val


def test_half_table_decodes_every_float16_exactly():
    """The decode table against an independent bit decoder for all 65,536 patterns: ±0 (sign
    kept), subnormals (2⁻²⁴ … ), the largest finite 65504, ±inf; NaN patterns stay NaN with
    their sign. And it is what numpy's astype gives."""
    t = _skin_resynth.half_table()
    bits = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16)
    nan = (bits & 0x7C00) == 0x7C00
    nan &= (bits & 0x3FF) != 0
    want = _float16_bits_to_float32(bits[~nan]).astype(np.float32)
    assert np.array_equal(t[~nan].view(np.uint32), want.view(np.uint32))  # bit for bit
    assert np.isnan(t[nan]).all() and np.array_equal(np.signbit(t[nan]), bits[nan] >= 0x8000)
    assert t[0x0001] == 2.0 ** -24 and t[0x03FF] == 1023 * 2.0 ** -24 and t[0x7BFF] == 65504
    assert np.signbit(t[0x8000]) and t[0x8000] == 0.0
    r = np.random.default_rng(3).normal(0, 100, 1000).astype(np.float16)
    assert np.array_equal(t[r.view(np.uint16)].view(np.uint32), r.astype(np.float32).view(np.uint32))


def _stored(hard):
    """The hard cases stored as float16 (R = D + S and D), with float16 extremes planted in R
    and D: zeros, subnormals, the largest finite value, values whose difference R − D rounds
    in float32 (65504 − 2⁻²⁴), and one row with an inf and one with a NaN sample."""
    lights, fit, vn, w = hard
    R16 = (fit.diffuse.astype(np.float64) + fit.specular).astype(np.float16)
    D16 = fit.diffuse.astype(np.float16)
    bits = R16.view(np.uint16)
    dbits = D16.view(np.uint16)
    bits[1, :40, 0] = 0x0001  # the smallest subnormal
    bits[2, :40, 1] = 0x03FF  # the largest subnormal
    bits[3, 7, :] = 0x7BFF  # 65504
    dbits[3, 7, :] = 0x0001  # R − D = 65504 − 2⁻²⁴: rounds in float32
    bits[4, :, 2] = 0  # a zero channel
    dbits[6, :, :] = 0x0002
    bits[8, 11, 1] = 0x7C00  # +inf
    bits[9, 3, 0] = 0x7E00  # NaN
    return lights, fit, vn, w, R16, D16


def _stored_reference(fit, R16, D16, vn, w):
    """The path the fused pass replaces: R, D widened by numpy, S = R − D in float32, the
    naive value as a float32 matrix product, ``resynthesize_relit`` on the widened fit."""
    R = R16.astype(np.float32)
    D = D16.astype(np.float32)
    n, L, _ = R.shape
    W = np.zeros((L, 3, 3))
    W[:, np.arange(3), np.arange(3)] = w
    with np.errstate(invalid="ignore"):  # the planted inf and NaN rows
        naive = (R.reshape(n, -1) @ W.reshape(3 * L, 3).astype(np.float32)).astype(np.float64)
    ok = np.isfinite(naive).all(axis=1)
    relit = np.zeros((n, 3))
    f = replace(fit, diffuse=D[ok], specular=R[ok] - D[ok], normal=fit.normal[ok],
                view=fit.view[ok], alpha_0=fit.alpha_0[ok], alpha_1=fit.alpha_1[ok],
                cast_shadow=fit.cast_shadow[ok], flags=fit.flags[ok])
    relit[ok] = _skin_resynth.resynthesize_relit(f, vn[ok], w)
    with np.errstate(invalid="ignore"):
        mag = np.einsum("nlc,lc->nc", np.abs(R.astype(np.float64)), np.abs(w))
    return naive, relit, ok, mag


def test_stored_pass_equals_the_float32_path_on_hard_cases_and_float16_extremes(hard):
    """relit_stored (float16 bits decoded in the kernel, naive value and resynthesis in one
    pass) against the float32 path on the hard cases (v_n = v_0, back-facing and grazing
    views, shadowed lobes, zero specular, zero diffuse samples) with float16 extremes: the
    resynthesised sums to STORED_RELIT_REL, the naive sums to STORED_NAIVE_REL, non-finite
    rows flagged with NaN naive values. A decode that mishandled subnormals, the largest
    value or the float32 rounding of R − D, or a finite check that missed inf/NaN, fails."""
    lights, fit, vn, w, R16, D16 = _stored(hard)
    n = R16.shape[0]
    assert _skin_resynth.stored_kernel_applies(R16, D16, lights, False)
    rows = np.arange(n)[::-1].copy()  # rows read out of order, as a field's gather
    naive, relit, finite = _skin_resynth.relit_stored(
        R16[::-1].copy(), rows, D16, np.arange(n), np.ones(n, bool), normal=fit.normal,
        view=fit.view, alpha_0=fit.alpha_0, alpha_1=fit.alpha_1, cast_shadow=fit.cast_shadow,
        eta=fit.eta, lights=lights, v_n=vn, weights=w)
    ref_naive, ref_relit, ref_ok, mag = _stored_reference(fit, R16, D16, vn, w)
    assert np.array_equal(finite, ref_ok) and not finite[8] and not finite[9]
    assert np.isnan(naive[~finite]).all()
    ok = finite
    assert np.all(np.abs(naive[ok] - ref_naive[ok]) <= STORED_NAIVE_REL * mag[ok])
    scale = np.abs(ref_relit).max(axis=1, keepdims=True)
    assert np.all(np.abs(relit - ref_relit) <= STORED_RELIT_REL * scale)
    assert np.all(relit[~finite] == 0.0)
    # the naive-only kernel gives the same naive values bit for bit
    naive2, finite2 = _skin_resynth.relight_stored(R16, np.arange(n), w)
    assert np.array_equal(finite2, finite) and np.array_equal(naive2[ok], naive[ok])
