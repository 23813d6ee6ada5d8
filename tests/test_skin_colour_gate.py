"""The colour separation checks the light's chromaticity against the albedo's before moving
energy into S (issue 36): on a near-grey object the paper's separation (§4.2) turned every
sample's chromaticity noise into specular energy (DiLiGenT cat: 18 % of the energy, normals
15° against 8.7° for Lambertian least squares)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import shared_file
from facegeo.appearance import skin

#: Share of a purely diffuse near-grey object's energy the gated separation may call specular
#: (measured 1.6 % on AVX-512 and on a generic x86 target, 1.1 % with numba off; the paper's
#: separation: 10–13 %). Not 0: the noise is 2 % of each sample, so the brightest samples' μ_s
#: noise exceeds 3 × the function's RMS. Before the ramp's physical range was enforced
#: (``_skin_fit.physical_ramp``) the same seed gave 1.7 %, 2.2 % or 3.2 % by the CPU's vector
#: width alone: one function's ramp slid to α_0 = 164, α_1 = −166 and 84 % of it went to S.
GREY_DIFFUSE_S_SHARE = 0.03
#: The same over eight other seeds (measured 1.3–3.0 %, the paper's separation 9.0–11.9 %), and
#: the largest share of any one function (measured ≤ 0.34; the runaway ramp gave 0.84).
GREY_DIFFUSE_S_SHARE_ANY_SEED = 0.035
GREY_FUNCTION_S_SHARE = 0.5
#: DiLiGenT cat, every 10th mask pixel, all 96 lights: the texel fit's mean normal error with
#: the gate must be at least this much below the paper's separation (measured 15.2° → 8.7°)…
CAT_GAIN_DEG = 4.0
#: …and within this of the Lambertian least squares on the same pixels and lights (8.7°).
CAT_VS_LAMBERTIAN_DEG = 0.5


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _grey_diffuse(rng, N=50):
    """Lambertian functions of a near-grey albedo (4° from white) whose every sample's colour
    is off by ≈ 1° of chromaticity noise, under 32 × 16 grid lights."""
    lights = skin.LightSet.from_grid(32, 16)
    n = _unit(rng.normal(size=(N, 3)) * [0.3, 0.3, 0.3] + [0.0, 0.0, 1.0])
    albedo = _unit(np.array([1.0, 0.93, 0.86]))
    x = np.maximum(n @ lights.directions.T, 0.0)
    noise = 1.0 + 0.02 * rng.normal(size=(N, lights.n_lights, 3))
    R = (0.6 * x[..., None] * albedo * noise).astype(np.float32)
    return R, lights


def test_chromaticity_noise_on_a_grey_object_stays_diffuse():
    R, lights = _grey_diffuse(np.random.default_rng(5))
    v = np.array([0.0, 0.0, 1.0])
    paper = skin.fit_reflectance(R, v, lights, chroma_gate=0.0)
    gated = skin.fit_reflectance(R, v, lights)
    share_paper = float(paper.specular.sum() / R.sum())
    share = float(gated.specular.sum() / R.sum())
    print(f"near-grey diffuse: S share {share:.4f} (paper's separation {share_paper:.4f})")
    assert share <= GREY_DIFFUSE_S_SHARE < share_paper
    ulp = np.spacing(np.float32(np.abs(R).max()))
    assert np.abs(gated.diffuse + gated.specular - R).max() <= 2 * ulp


def test_near_grey_ramps_stay_physical_over_seeds():
    """Eq. 6's ramp on near-grey noise: over eight seeds no function's fitted ramp reaches
    f ≤ −1 (the colour through white), none has most of its energy called specular, and the
    object's share stays under the bar — whatever the arithmetic's last bits do."""
    v = np.array([0.0, 0.0, 1.0])
    for seed in range(8):
        R, lights = _grey_diffuse(np.random.default_rng(100 + seed))
        fit = skin.fit_reflectance(R, v, lights)
        assert np.minimum(fit.alpha_0, fit.alpha_1).min() > skin._skin_fit.RAMP_F_MIN
        per = fit.specular.sum(axis=(1, 2)) / R.sum(axis=(1, 2))
        assert per.max() < GREY_FUNCTION_S_SHARE, (seed, per.max())
        assert fit.specular.sum() / R.sum() <= GREY_DIFFUSE_S_SHARE_ANY_SEED, seed


def test_a_ramp_through_white_is_rejected():
    """``physical_ramp``: a ramp whose f reaches −1 on x ∈ [0, 1] (or is not finite) falls
    back to α = 0 and the lobe's normal; others pass unchanged."""
    from facegeo.appearance._skin_fit import physical_ramp

    a0 = np.array([0.8, 163.6, -1.0, 0.2, np.nan])
    a1 = np.array([0.9, -166.0, 0.5, -0.99, 0.1])
    n_ramp = np.tile([0.0, 0.6, 0.8], (5, 1))
    n = np.tile([0.0, 0.0, 1.0], (5, 1))
    b0, b1, nr, bad = physical_ramp(a0, a1, n_ramp, n)
    assert bad.tolist() == [False, True, True, False, True]
    assert np.array_equal(b0, [0.8, 0.0, 0.0, 0.2, 0.0]) and np.array_equal(b1, [0.9, 0, 0, -0.99, 0])
    assert np.array_equal(nr[bad], n[bad]) and np.array_equal(nr[~bad], n_ramp[~bad])
    assert skin.flag_names(skin.FLAG_RAMP_REJECTED) == ["ramp_rejected"]


def test_colours_in_the_models_plane_are_not_gated():
    """Exact paper-model functions (skin colour, white lobe): the gate changes nothing."""
    rng = np.random.default_rng(8)
    lights = skin.LightSet.from_grid(32, 16)
    N = 30
    n = _unit(rng.normal(size=(N, 3)) * 0.3 + [0.0, 0.0, 1.0])
    v = np.broadcast_to([0.0, 0.0, 1.0], (N, 3))
    params = skin.SkinParams(rho_d=np.array([0.62, 0.36, 0.26]) * rng.uniform(0.8, 1.1, (N, 1)),
                             alpha_0=rng.uniform(0.1, 0.3, N), alpha_1=rng.uniform(0.3, 0.6, N),
                             rho_s=rng.uniform(0.05, 0.2, N), roughness=rng.uniform(0.2, 0.4, N),
                             eta=1.4)
    R = skin.paper_reflectance(n, v, lights, params)
    a = skin.fit_reflectance(R, v, lights)
    b = skin.fit_reflectance(R, v, lights, chroma_gate=0.0)
    assert np.array_equal(a.diffuse, b.diffuse) and np.array_equal(a.normal, b.normal)


def test_diligent_cat_texel_fit_normals(shared_data):
    from facegeo.appearance.lambertian import fit_lambertian
    from facegeo.capture.datasets import import_dataset
    from facegeo.capture.imageio import read_image
    from facegeo.render import light_set

    src = shared_file(shared_data, "olat/diligent/catPNG")
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        scan = import_dataset("diligent", src, Path(tmp) / "cat")
        lights = scan.rig.lights
        mask = (read_image(scan.reference_path("mask")) > 0).any(axis=-1)
        R_cw = scan.rig.camera("cam").T_cam_world.R
        n_ref = (np.load(scan.reference_path("normals"))[mask] @ R_cw)[::10]
        R = np.stack([scan.olat_frame("cam", k)[mask][::10] for k in range(lights.n_lights)],
                     axis=1)
    R = np.maximum(R, 0.0).astype(np.float32)
    v = -(R_cw.T @ np.array([0.0, 0.0, 1.0]))  # toward the (distant) camera
    ls = light_set(lights)

    def mean_err(nrm, ok):
        cos = np.clip(np.sum(nrm * n_ref, axis=1), -1.0, 1.0)
        return float(np.degrees(np.arccos(cos))[ok].mean())

    gated = skin.fit_reflectance(R, v, ls, threads=2)
    paper = skin.fit_reflectance(R, v, ls, threads=2, chroma_gate=0.0)
    lam = fit_lambertian(R, ls.directions, intensities=ls.intensities)
    ok = gated.valid & paper.valid & lam.valid
    e_g, e_p, e_l = mean_err(gated.normal, ok), mean_err(paper.normal, ok), mean_err(lam.normal, ok)
    print(f"DiLiGenT cat, texel fit over {ok.sum()} pixels: mean normal error {e_g:.2f}° "
          f"(paper's separation {e_p:.2f}°, Lambertian least squares {e_l:.2f}°); S share "
          f"{gated.specular[ok].sum() / R[ok].sum():.3f} vs {paper.specular[ok].sum() / R[ok].sum():.3f}")
    assert e_g <= e_p - CAT_GAIN_DEG
    assert e_g <= e_l + CAT_VS_LAMBERTIAN_DEG
