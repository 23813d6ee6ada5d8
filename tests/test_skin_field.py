"""Tests of facegeo.synth.skin: ground-truth skin parameters as solid textures."""

from __future__ import annotations

import json

import numpy as np
import pytest

from facegeo.errors import InputError, ShapeError
from facegeo.synth import skin as skinmod
from facegeo.synth.head import head_landmarks, procedural_head
from facegeo.synth.skin import ALBEDO_MODELS, SkinField, register_albedo_model

# Plausible linear-sRGB skin (per channel, over the whole head and every tested subject).
ALPHA0_RANGE = {"R": (0.25, 0.70), "G": (0.12, 0.45), "B": (0.08, 0.35)}
RHO_S_RANGE = (0.3, 1.0)
ROUGHNESS_RANGE = (0.25, 0.5)
GRAD_MAX = 150.0  # per metre: max |∂param/∂p| by central differences (0.15 per mm)
CURV_MAX = 1e5  # per metre²: max second difference / h²
SEEDS = range(6)


@pytest.fixture(scope="module")
def head():
    return procedural_head(5)


@pytest.fixture(scope="module")
def landmarks(head):
    return head_landmarks(head)


def _lum(a):
    return np.asarray(a, float) @ np.array([0.2126, 0.7152, 0.0722])


def test_seed_determinism_and_difference(head):
    p = np.asarray(head.vertices)
    a = SkinField.for_mesh(head, seed=3).evaluate(p)
    b = SkinField.for_mesh(head, seed=3).evaluate(p)
    c = SkinField.for_mesh(head, seed=4).evaluate(p)
    for k in ("alpha_0", "alpha_1", "rho_s", "roughness"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), f"{k}: same seed, bit-identical"
        diff = np.abs(getattr(a, k) - getattr(c, k)).max()
        assert diff > 1e-3, f"{k}: seeds 3 and 4 differ by max {diff:.3g}"


@pytest.mark.parametrize("seed", SEEDS)
def test_ranges_plausible_over_head(head, seed):
    s = SkinField.for_mesh(head, seed=seed).per_vertex(head)
    n = len(head.vertices)
    assert s.alpha_0.shape == (n, 3) and s.alpha_0.dtype == np.float32, "alpha_0 (N, 3) float32"
    assert s.alpha_1.shape == (n, 3) and s.alpha_1.dtype == np.float32, "alpha_1 (N, 3) float32"
    assert s.rho_s.shape == (n,) and s.roughness.shape == (n,), "scalars (N,)"
    for c, (lo, hi) in enumerate(ALPHA0_RANGE.values()):
        ch = s.alpha_0[:, c]
        assert lo <= ch.min() and ch.max() <= hi, \
            f"alpha_0[{c}] in [{ch.min():.3f}, {ch.max():.3f}]"
    a0 = s.alpha_0
    assert np.all((a0[:, 0] > a0[:, 1]) & (a0[:, 1] > a0[:, 2])), "R > G > B at every vertex"
    sat = lambda a: np.ptp(a, axis=1) / a.mean(axis=1)  # noqa: E731
    assert np.all(sat(s.alpha_1) < sat(a0)), "alpha_1 less saturated than alpha_0 everywhere"
    assert np.all(_lum(s.alpha_1) > _lum(a0)), "alpha_1 lighter than alpha_0 everywhere"
    assert RHO_S_RANGE[0] <= s.rho_s.min() and s.rho_s.max() <= RHO_S_RANGE[1], \
        f"rho_s in [{s.rho_s.min():.3f}, {s.rho_s.max():.3f}]"
    assert ROUGHNESS_RANGE[0] <= s.roughness.min() and s.roughness.max() <= ROUGHNESS_RANGE[1], \
        f"roughness in [{s.roughness.min():.3f}, {s.roughness.max():.3f}]"
    for k in ("alpha_0", "alpha_1", "rho_s", "roughness"):
        assert np.all(np.isfinite(getattr(s, k))), f"{k} finite"


@pytest.mark.parametrize("seed", SEEDS)
def test_regional_contrasts_at_landmarks(head, landmarks, seed):
    sk = SkinField.for_mesh(head, seed=seed)
    at = {k: sk.evaluate(v) for k, v in landmarks.items()}
    rg = {k: float(s.alpha_0[0] / s.alpha_0[1]) for k, s in at.items()}
    for lip in ("upper_lip", "lower_lip", "mouth_center"):
        for cheek in ("left_cheek", "right_cheek"):
            assert rg[lip] > rg[cheek], f"R/G {lip} {rg[lip]:.3f} > {cheek} {rg[cheek]:.3f}"
            assert _lum(at[lip].alpha_0) < _lum(at[cheek].alpha_0), f"{lip} darker than {cheek}"
    for cheek in ("left_cheek", "right_cheek"):
        assert rg[cheek] > rg["forehead"], f"blush: R/G {cheek} {rg[cheek]:.3f} > forehead"
        assert at["forehead"].rho_s > at[cheek].rho_s, "forehead oilier (rho_s) than cheek"
        assert at["nose_tip"].rho_s > at[cheek].rho_s, "nose oilier (rho_s) than cheek"
        assert at["forehead"].roughness < at[cheek].roughness, "forehead smoother (m) than cheek"


def test_under_eye_darker_without_noise(head, landmarks):
    quiet = {"noise_luminance": 0.0, "noise_chroma": 0.0}
    for seed in SEEDS:
        sk = SkinField.for_mesh(head, seed=seed, albedo_params=quiet)
        for side in ("left", "right"):
            under = _lum(sk.evaluate(landmarks[f"{side}_under_eye"]).alpha_0)
            fore = _lum(sk.evaluate(landmarks["forehead"]).alpha_0)
            assert under < 0.95 * fore, f"{side} under-eye luminance {under:.3f} vs {fore:.3f}"


def test_smooth_finite_differences(head):
    """Central differences bounded and second differences scale as h² (C¹, no kinks)."""
    sk = SkinField.for_mesh(head, seed=1)
    rng = np.random.default_rng(5)
    p = np.asarray(head.vertices)
    d = rng.normal(size=p.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    curv = {}
    for h in (1e-3, 1e-4):
        a, b, c = (sk.evaluate(p + s * h * d) for s in (1.0, 0.0, -1.0))
        for k in ("alpha_0", "alpha_1", "rho_s", "roughness"):
            A, B, C = (np.asarray(getattr(x, k), float) for x in (a, b, c))
            grad = np.abs(A - C).max() / (2 * h)
            assert grad < GRAD_MAX, f"{k}: max |∂/∂p| {grad:.1f} /m at h = {h}"
            curv[(k, h)] = np.abs(A - 2 * B + C).max() / h**2
    for k in ("alpha_0", "alpha_1", "rho_s", "roughness"):
        c3, c4 = curv[(k, 1e-3)], curv[(k, 1e-4)]
        assert c3 < CURV_MAX and c4 < 1.5 * c3 + 10.0, f"{k}: |Δ²|/h² {c3:.0f}, {c4:.0f} /m²"


def test_to_dict_round_trip_bit_exact(head):
    sk = SkinField.for_mesh(head, seed=11, grazing_lift=1.07,
                            albedo_params={"tone": (0.47, 0.31, 0.22), "noise_chroma": 0.015})
    text = json.dumps(sk.to_dict())
    back = SkinField.from_dict(json.loads(text))
    assert back == sk, "fields equal after JSON round trip"
    p = np.asarray(head.vertices)
    a, b = sk.evaluate(p), back.evaluate(p)
    for k in ("alpha_0", "alpha_1", "rho_s", "roughness"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), f"{k}: bit-identical after round trip"


def test_from_dict_errors():
    good = SkinField(center=(0, 0, 0), half_extent=(0.08, 0.11, 0.1)).to_dict()
    with pytest.raises(InputError, match="unknown key"):
        SkinField.from_dict({**good, "colour": 1})
    with pytest.raises(InputError, match="format"):
        SkinField.from_dict({**good, "format": "something/9"})
    with pytest.raises(InputError, match="unknown model"):
        SkinField.from_dict({**good, "albedo_model": "nope"})


def test_albedo_hook_and_registry(head):
    p = np.asarray(head.vertices)
    grey = np.array([0.4, 0.3, 0.2])
    sk = SkinField.for_mesh(head, seed=0, albedo_fn=lambda u: np.broadcast_to(grey, u.shape))
    s = sk.evaluate(p)
    assert np.array_equal(s.alpha_0, np.broadcast_to(grey.astype(np.float32), s.alpha_0.shape)), \
        "albedo_fn replaces the colour model"
    with pytest.raises(InputError, match="register"):
        sk.to_dict()

    def flat(u, skin, *, colour=(0.5, 0.3, 0.2)):
        return np.broadcast_to(np.asarray(colour, float), u.shape)

    register_albedo_model("test-flat", flat)
    try:
        with pytest.raises(InputError, match="already registered"):
            register_albedo_model("test-flat", flat)
        named = SkinField.for_mesh(head, albedo_model="test-flat",
                                   albedo_params={"colour": [0.6, 0.35, 0.25]})
        back = SkinField.from_dict(json.loads(json.dumps(named.to_dict())))
        s1, s2 = named.evaluate(p), back.evaluate(p)
        assert np.allclose(s1.alpha_0, [0.6, 0.35, 0.25], rtol=0, atol=1e-7), "named model used"
        assert np.array_equal(s1.alpha_1, s2.alpha_1), "named model survives the round trip"
    finally:
        ALBEDO_MODELS.pop("test-flat", None)
    with pytest.raises(InputError, match="unknown model"):
        SkinField.for_mesh(head, albedo_model="test-flat")


def test_bad_albedo_fn_shape(head):
    sk = SkinField.for_mesh(head, albedo_fn=lambda u: u[..., :2])
    with pytest.raises(InputError, match="shape"):
        sk.evaluate(np.zeros((3, 3)))


def test_shapes_and_per_vertex(head):
    sk = SkinField.for_mesh(head, seed=2)
    rng = np.random.default_rng(6)
    p = rng.uniform(-0.1, 0.1, (4, 5, 3))
    s = sk.evaluate(p)
    assert s.alpha_0.shape == (4, 5, 3) and s.rho_s.shape == (4, 5), "leading axes kept"
    flat = sk.evaluate(p.reshape(-1, 3))
    assert np.array_equal(flat.alpha_0.reshape(4, 5, 3), s.alpha_0), "pointwise (any grouping)"
    one = sk.evaluate(p[1, 2])
    assert one.alpha_0.shape == (3,) and one.rho_s.shape == (), "single point"
    big = rng.uniform(-0.1, 0.1, (40000, 3))  # spans several evaluation blocks
    blocks = sk.evaluate(big)
    parts = [sk.evaluate(big[i:i + 7000]).alpha_0 for i in range(0, len(big), 7000)]
    assert np.array_equal(blocks.alpha_0, np.concatenate(parts)), "block size does not matter"
    pv = sk.per_vertex(head)
    assert np.array_equal(pv.rho_s, sk.evaluate(np.asarray(head.vertices)).rho_s), "per_vertex"


def test_input_validation(head):
    with pytest.raises(InputError):
        SkinField(center=(0, 0, 0), half_extent=(0.1, 0.0, 0.1))
    with pytest.raises(ShapeError):
        SkinField(center=(0, 0), half_extent=(0.1, 0.1, 0.1))
    with pytest.raises(InputError):
        SkinField(center=(0, 0, 0), half_extent=(0.1, 0.1, 0.1), rho_s_base=1.2)
    sk = SkinField.for_mesh(head)
    with pytest.raises(InputError):
        sk.evaluate(np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(ShapeError):
        sk.evaluate(np.zeros((4, 2)))
    with pytest.raises(InputError):
        SkinField.for_mesh(np.zeros((3, 3)))


def test_noise_is_unit_rms_and_seeded():
    rng = np.random.default_rng(8)
    x = rng.uniform(-0.2, 0.2, (200000, 3))
    n = skinmod.smooth_noise(x, 5, 3)
    rms = np.sqrt(np.mean(n**2, axis=0))
    assert np.all(np.abs(rms - 1) < 0.15), f"RMS per field {rms} ≈ 1 (±0.15)"
    corr = np.corrcoef(n.T)[np.triu_indices(3, 1)]
    assert np.all(np.abs(corr) < 0.2), f"fields nearly uncorrelated: {corr}"
    assert np.array_equal(n, skinmod.smooth_noise(x, 5, 3)), "seeded: identical"
