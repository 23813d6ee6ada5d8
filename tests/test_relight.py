"""Relighting (Debevec et al. 2000 Eq. 3–4): the GEMM path against a float64 reference, the
analytic Lambertian case, consistency with the synthetic generator, orientation on a face."""

from __future__ import annotations

import numpy as np
import pytest

from facegeo.errors import InputError, ShapeError
from facegeo.frames import light_directions, light_solid_angles
from facegeo.lighting import envmap as E
from facegeo.lighting import relight as R

#: GEMM relighting vs a float64 reference sum over the same float16/float32 field:
#: max |Δ| / max |reference|.
GEMM_REL = 2e-6
#: Constant environment of radiance 1 on a Lambertian patch: |L_out/albedo − 1| (issue 12).
ALBEDO_REL = 0.01
#: Relit OLAT frames vs the generator's weighted render: max |Δ| / max image (float32 rounding).
CONSISTENCY_REL = 1e-6
#: Orientation: mean lit channel on the side facing the lobe / on the opposite side, at least.
ORIENTATION_RATIO = 5.0


def _reference(field, w):
    return np.einsum("plc,lc->pc", field.astype(np.float64), w)


@pytest.mark.parametrize("dtype", [np.float16, np.float32])
@pytest.mark.parametrize("sparse", [False, True])
def test_relight_field_matches_reference(dtype, sparse):
    rng = np.random.default_rng(0)
    P, L = 1000, 48
    field = rng.random((P, L, 3)).astype(dtype)
    w = rng.random((L, 3))
    w[rng.random(L) < 0.5] = 0.0
    got = R.relight_field(field, w, chunk_rows=77, sparse=sparse)  # chunks with a remainder
    ref = _reference(field, w)
    assert got.shape == (P, 3) and got.dtype == np.float32
    assert np.max(np.abs(got - ref)) / np.max(np.abs(ref)) <= GEMM_REL


def test_fused_float16_kernel_converts_every_half_exactly():
    # Every float16 bit pattern (normals, subnormals, ±0, ±inf, NaNs) relit with weight 1 on
    # one light must come out as numpy's exact float16 → float32 cast: bit-exact metric.
    pytest.importorskip("numba")
    h = np.arange(65536, dtype=np.uint16).view(np.float16)
    field = np.ascontiguousarray(np.repeat(h[:, None, None], 3, axis=2))  # (65536, 1, 3)
    got = R.relight_field(field, np.ones((1, 3)), kernel="fused")
    want = np.repeat(h.astype(np.float32)[:, None], 3, axis=1)
    finite = np.isfinite(want)
    assert np.array_equal(got[finite], want[finite])
    assert np.array_equal(np.isnan(got), np.isnan(want))
    assert np.array_equal(got[np.isinf(want)], want[np.isinf(want)])


@pytest.mark.parametrize("conversion", ["f16c", "bits"])
def test_both_half_conversions_are_exact_in_every_lane_and_row_of_a_block(conversion):
    # The kernel itself, each conversion (F16C only where the CPU has it): row r holds float16
    # bit pattern r (all 65,536: normals, subnormals, ±0, ±inf, NaNs) at light r mod 11 of 11
    # (so it lands in every SIMD lane and in the vector body and the scalar remainder), zeros
    # elsewhere; rows run in blocks of three plus a remainder. Channel-0 weights 1: the sum is
    # that half exactly. Metric: bit-exact against numpy's cast (NaN compared as NaN).
    pytest.importorskip("numba")
    if conversion == "f16c" and not R._host_has_f16c():
        pytest.skip("this CPU has no F16C")
    kern = R._fused_kernel(conversion)
    n_l = 11
    bits = np.arange(65536, dtype=np.uint16)
    h = np.zeros((bits.size, n_l, 3), np.uint16)
    h[np.arange(bits.size), np.arange(bits.size) % n_l, 0] = bits
    h = h.reshape(bits.size, 3 * n_l)
    w = [np.zeros(3 * n_l, np.float32) for _ in range(3)]
    for c in range(3):
        w[c][c::3] = 1.0
    out = np.empty((bits.size, 3), np.float32)
    kern(h, w[0], w[1], w[2], out)
    want = bits.view(np.float16).astype(np.float32)
    got = out[:, 0]
    assert np.array_equal(np.isnan(got), np.isnan(want))
    ok = ~np.isnan(want)
    assert np.array_equal(got[ok], want[ok])
    fin = np.isfinite(want)
    # three weight vectors (the bit kernel, and the F16C kernel's last n mod 3 rows, which go
    # through it): 0 · half in the other channels, NaN for a NaN/inf half (IEEE); the F16C
    # kernel's interleaved weights: a half reaches only its own channel's sum
    three = np.ones(bits.size, bool)
    if conversion == "f16c":
        three[: bits.size - bits.size % 3] = False
        assert np.all(out[~three, 1:] == 0)
    assert np.all(out[three & fin, 1:] == 0) and np.all(np.isnan(out[three & ~fin, 1:]))


def test_f16c_kernel_sums_in_the_order_of_the_three_weight_vector_kernel():
    # fused_half_dot_f16c (one interleaved weight vector, 4 rows per pass, LLVM IR) must give the
    # sums of fused_half_dot (three weight vectors, 3 rows, LLVM's loop vectoriser) in the same
    # order: every width 3L' for L' = 1 … 40 and 2048 (24-column body, left-over 8-column
    # chunks, scalar remainder) and row counts hitting 4-row blocks, single rows and the n mod 3
    # rows. Signed halves over four decades, so a changed summation order changes the rounding.
    # Metric: bit-exact (np.array_equal; −0 == +0).
    pytest.importorskip("numba")
    if not R._host_has_f16c():
        pytest.skip("this CPU has no F16C")
    from numba.core.codegen import get_host_cpu_features

    if "+avx512f" in str(get_host_cpu_features()).split(","):
        pytest.skip("AVX-512: LLVM may vectorise the reference kernel 16 lanes wide")
    from facegeo.lighting._fused import fused_half_dot, fused_half_dot_f16c

    rng = np.random.default_rng(11)
    for n_l in [*range(1, 41), 2048]:
        m = 3 * n_l
        n = 11 if n_l < 2048 else 7
        x = rng.standard_normal((n, m)) * 10.0 ** rng.uniform(-2, 2, (n, m))
        h = x.astype(np.float16).view(np.uint16)
        w = rng.random(m).astype(np.float32)
        wc = [np.where(np.arange(m) % 3 == c, w, 0).astype(np.float32) for c in range(3)]
        want = np.empty((n, 3), np.float32)
        got = np.empty((n, 3), np.float32)
        fused_half_dot(h, wc[0], wc[1], wc[2], want, True)
        fused_half_dot_f16c(h, wc[0], wc[1], wc[2], w, got)
        assert np.array_equal(got, want), f"L' = {n_l}"
    with pytest.raises(ShapeError, match="fused_half_dot_f16c"):  # no unchecked reads past wi
        fused_half_dot_f16c(h, wc[0], wc[1], wc[2], w[:-8].copy(), got)


@pytest.mark.parametrize("kernel", ["fused", "blas"])
def test_kernels_agree_and_masked_samples_only_matter_at_lit_lights(kernel):
    if kernel == "fused":
        pytest.importorskip("numba")
    rng = np.random.default_rng(7)
    P, L = 500, 40  # 3L = 120: not a multiple of any SIMD width
    field = rng.random((P, L, 3)).astype(np.float16)
    w = rng.random((L, 3))
    w[::4] = 0.0  # lights 0, 4, 8, ... unlit
    field[3, 4, 1] = np.nan  # masked sample at an unlit light: must not matter
    field[5, 8, 0] = np.inf  # float16 overflow at an unlit light: must not matter
    field[7, 1, 2] = np.nan  # masked at a lit light: that row is NaN (never a fake value)
    got = R.relight_field(field, w, kernel=kernel, chunk_rows=64)
    f64 = np.nan_to_num(field.astype(np.float64), nan=0.0, posinf=0.0)
    ref = np.einsum("plc,lc->pc", f64, w)
    ok = np.ones(P, bool)
    ok[7] = False
    assert np.max(np.abs(got[ok] - ref[ok])) / np.max(ref) <= GEMM_REL
    assert np.isnan(got[7]).any()
    with pytest.raises(InputError, match="kernel"):
        R.relight_field(field, w, kernel="simd")


def test_relight_field_batch_equals_single_calls_and_channels_are_not_mixed():
    rng = np.random.default_rng(1)
    field = rng.random((300, 20, 3)).astype(np.float16)
    ws = rng.random((4, 20, 3))
    batch = R.relight_field(field, ws)
    assert batch.shape == (4, 300, 3)
    for b in range(4):  # one GEMM vs three GEMVs: equal up to float32 summation order
        single = R.relight_field(field, ws[b])
        assert np.max(np.abs(batch[b] - single)) / np.max(single) <= GEMM_REL
    # weights only in the red channel light only the red output
    w = np.zeros((20, 3))
    w[:, 0] = 1
    out = R.relight_field(field, w)
    assert np.all(out[:, 1:] == 0)
    assert np.allclose(out[:, 0], field[:, :, 0].astype(np.float64).sum(1), rtol=1e-5)


def test_light_color_normalisation():
    rng = np.random.default_rng(2)
    white = rng.random((50, 16, 3)).astype(np.float32)
    color = np.array([0.9, 0.7, 1.3])
    recorded = (white * color).astype(np.float32)  # OLAT frames under a coloured light
    w = rng.random((16, 3))
    got = R.relight_field(recorded, w, light_color=color)
    assert np.allclose(got, R.relight_field(white, w), rtol=1e-5)
    per_light = np.repeat(color[None], 16, axis=0)
    assert np.allclose(R.relight_field(recorded, w, light_color=per_light), got, rtol=1e-6)


def test_relight_bad_input():
    f = np.zeros((4, 8, 3), np.float32)
    with pytest.raises(ShapeError, match=r"weights: expected shape \(8, 3\)"):
        R.relight_field(f, np.ones((7, 3)))
    with pytest.raises(ShapeError, match="float16 or float32"):
        R.relight_field(f.astype(np.float64), np.ones((8, 3)))
    with pytest.raises(ShapeError, match=r"\(P, L, 3\)"):
        R.relight_field(np.zeros((4, 8)), np.ones((8, 3)))
    with pytest.raises(InputError, match="non-finite"):
        R.relight_field(f, np.full((8, 3), np.nan))
    with pytest.raises(InputError, match="light_color"):
        R.relight_field(f, np.ones((8, 3)), light_color=[1, 0, 1])
    with pytest.raises(InputError, match="given twice"):
        R.relight_frames([(0, np.zeros((2, 2, 3))), (0, np.zeros((2, 2, 3)))], np.ones((8, 3)), 8)


@pytest.mark.parametrize("grid", [(32, 16), (64, 32)])
@pytest.mark.parametrize("solid_angle", ["paper", "exact"])
def test_constant_environment_on_lambertian_patch_gives_albedo(grid, solid_angle):
    # Patch of Lambertian texels with several normals (off every axis) and albedos; OLAT frames
    # under unit irradiance: R_l = ρ/π · max(0, n·ω_l).
    rng = np.random.default_rng(4)
    n = rng.normal(size=(64, 3))
    n[0] = (0, 1, 0)  # facing the pole, the hardest case for the (θ, φ) grid
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    albedo = np.ones((64, 3))
    albedo[1:] = rng.uniform(0.2, 1.0, size=(63, 3))
    d = light_directions(*grid)
    field = (albedo[:, None, :] / np.pi * np.maximum(n @ d.T, 0)[:, :, None]).astype(np.float32)
    env = E.analytic_map(lambda v: np.ones(v.shape[:-1] + (3,)), 32)
    w = E.light_stage_weights(env, *grid, solid_angle=solid_angle)
    out = R.relight_field(field, w)
    assert np.max(np.abs(out / albedo - 1)) <= ALBEDO_REL


# --------------------------------------------------------------------------- synthetic scan


@pytest.fixture(scope="module")
def tiny_scan(tmp_path_factory):
    from facegeo.capture.scan import load_scan
    from facegeo.synth.capture import generate_scan
    from facegeo.synth.render import load_ground_truth

    root = tmp_path_factory.mktemp("relight") / "tiny"
    generate_scan(root, "tiny", seed=5)
    scan = load_scan(root)
    return scan, load_ground_truth(scan)


@pytest.mark.slow
def test_relit_olat_frames_equal_the_generators_render(tiny_scan):
    scan, renderer = tiny_scan
    lights = scan.rig.lights
    env = E.axis_lobe_map(32, exponent=3).rotated(0.4)
    w = E.light_stage_weights(env, lights.n_theta, lights.n_phi)
    name = scan.camera_names[0]
    cam = renderer.rig.camera(name)
    ref = renderer.render_lights(cam, renderer.rig.lights, w)
    got = R.relight_scan_view(scan, name, w)
    assert got.shape == ref.shape
    assert np.max(np.abs(got - ref)) <= CONSISTENCY_REL * np.max(ref)
    # the frames read ahead on two threads: the same image, bit for bit
    assert np.array_equal(R.relight_scan_view(scan, name, w, read_ahead=2), got)


def test_a_nan_pixel_in_a_frame_is_an_error_naming_the_file(tiny_scan, tmp_path):
    """A corrupt frame (a NaN pixel) read by the relighting is named in the error, as
    ``facegeo info --full`` names it — not a message about the relit image's encoding."""
    import shutil

    from facegeo.capture import imageio
    from facegeo.capture.scan import load_scan

    scan = tiny_scan[0]
    root = tmp_path / "nan"
    shutil.copytree(scan.root, root)
    copy = load_scan(root)
    name = copy.camera_names[0]
    path = copy.olat_path(name, 3)
    frame = imageio.read_image(path).astype(np.float32)
    frame[5, 7, 1] = np.nan
    path.unlink()
    imageio.write_image(path, frame)
    lights = copy.rig.lights
    w = np.tile(lights.solid_angles[:, None], (1, 3))  # every light: frame 3 is read
    with pytest.raises(InputError, match=r"0003\.exr: 1 pixel\(s\) are NaN or infinite "
                                         r"\(first at row, col \(5, 7\)\).*light 3"):
        R.relight_scan_view(copy, name, w)
    # with return_mask the pixel is flagged untrusted instead (the renderer's image-space
    # detail leaves it out), and every other pixel is the plain relighting's
    img, valid = R.relight_scan_view(copy, name, w, return_mask=True)
    assert not valid[5, 7] and valid.sum() == valid.size - 1
    assert np.array_equal(img[5, 7], np.zeros(3, np.float32))
    plain = R.relight_scan_view(scan, name, w)
    assert np.abs(img - plain)[valid].max() <= 1e-6 * np.abs(plain).max()
    w[3] = 0.0  # the bad frame carries no energy: not read, no error
    assert np.isfinite(R.relight_scan_view(copy, name, w)).all()
    assert R.relight_scan_view(copy, name, w, return_mask=True)[1].all()


@pytest.mark.slow
@pytest.mark.parametrize("axis", [(1, 0, 0), (-1, 0, 0), (0, 1, 0)])
def test_axis_lobe_lights_the_face_from_the_expected_side(tiny_scan, axis):
    scan, renderer = tiny_scan
    lights = scan.rig.lights
    env = E.axis_lobe_map(32, exponent=4, axes=[axis])
    w = E.light_stage_weights(env, lights.n_theta, lights.n_phi)
    name = scan.camera_names[0]
    img = R.relight_scan_view(scan, name, w)
    view = renderer.surface_view(renderer.rig.camera(name))
    n_img = view.to_image(view.n_world.astype(np.float32), fill=np.nan)
    facing = n_img @ np.asarray(axis, float)
    colour = np.asarray(E.AXIS_LOBE_COLORS[axis])
    lit = colour > 0
    toward = img[facing > 0.3][:, lit].mean()
    away = img[facing < -0.3][:, lit].mean()
    assert toward > ORIENTATION_RATIO * away, (toward, away)
    assert np.all(img[..., ~lit] == 0)  # the lobe's colour and nothing else


# --------------------------------------------------------------------------- pipeline stage


@pytest.mark.slow
def test_run_relight_writes_exr_png_and_metrics(tiny_scan, tmp_path):
    from facegeo.capture import imageio
    from facegeo.pipeline.relight import run_relight

    scan, _ = tiny_scan
    env_file = imageio.write_image(tmp_path / "lobes.exr", E.axis_lobe_map(32).image)
    calls = []
    m = run_relight(scan.root, env_file, rotate_deg=30, view=scan.camera_names[1],
                    out_dir=tmp_path / "out", progress=lambda *a: calls.append(a))
    exr = imageio.read_image(m["files"]["exr"])
    lights = scan.rig.lights
    env = E.read_envmap(env_file, rotate_deg=30)
    w = E.light_stage_weights(env, lights.n_theta, lights.n_phi)
    assert np.array_equal(exr, R.relight_scan_view(scan, scan.camera_names[1], w))
    png = imageio.read_image(m["files"]["png"])
    assert png.dtype == np.uint8 and png.shape == exr.shape
    assert m["active_lights"] == len(calls) and m["view"] == scan.camera_names[1]
    # Σ w vs ∫ L: the paper's midpoint δA on the tiny 16 × 8 grid reads 0.6 % high
    assert np.allclose(m["energy_ratio"], 1.0, atol=0.01)
    # the exact δA rule writes files of its own beside the paper rule's, never over them
    mx = run_relight(scan.root, env_file, rotate_deg=30, view=scan.camera_names[1],
                     out_dir=tmp_path / "out", solid_angle="exact")
    assert mx["files"]["exr"] != m["files"]["exr"] and mx["files"]["exr"].endswith("_exact.exr")
    assert np.array_equal(imageio.read_image(m["files"]["exr"]), exr)


@pytest.mark.slow
def test_relight_products_camera_view_metrics_files_and_settings(tiny_scan, tmp_path):
    # The stage function for 'facegeo reconstruct': the shipped sky map on a camera view.
    # The EXR holds exactly the relit image; relit-vs-reference (the evaluation's comparison,
    # facegeo.evaluate.relit: the stage reads no truth): the generator's render under the same
    # Eq. (4) weights equals the relit OLAT frames to float32 precision (relative RMSE,
    # CONSISTENCY_REL); energy Σw/∫L is the paper δA's midpoint excess on the tiny 16 × 8 grid
    # (h/sin h − 1 = 0.65 %, the same in every channel); no JSON of its own.
    from facegeo.capture import imageio
    from facegeo.evaluate.relit import relit_error
    from facegeo.pipeline.relight import relight_products

    scan, _ = tiny_scan
    cam = scan.camera_names[1]
    m, settings = relight_products(scan, None, tmp_path / "d", env="sky", rotate=-40, view=cam)
    assert settings == {"env": "sky", "rotate": -40.0, "view": cam, "projection": "latlong",
                        "solid_angle": "paper", "model": "measured"}
    assert "reference" not in m, "the stage computes no error against the truth"
    lights = scan.rig.lights
    w = E.light_stage_weights(E.shipped_map("sky").rotated(np.radians(-40)), lights.n_theta,
                              lights.n_phi)
    exr = imageio.read_image(m["files"]["exr"])
    assert np.array_equal(exr, R.relight_scan_view(scan, cam, w, normalize_color=True))
    ref = relit_error(scan, cam, w, exr)
    assert ref["computed"] and ref["pixels"] > 0
    assert ref["relative_rmse"] <= CONSISTENCY_REL and ref["max_abs_over_max"] <= CONSISTENCY_REL
    h = np.pi / (2 * lights.n_phi)
    assert np.allclose(m["energy_ratio"], h / np.sin(h), rtol=1e-4)
    assert sorted(p.suffix for p in (tmp_path / "d").iterdir()) == [".exr", ".png"]
    assert "seconds" in m and set(m["seconds"]) == {"env", "weights", "relight", "total"}
    with pytest.raises(InputError, match="solid_angle"):
        relight_products(scan, None, tmp_path / "f", env="sky", view=cam, solid_angle="midpoint")


@pytest.mark.slow
def test_relight_products_reference_error_detects_a_wrong_image(tiny_scan, tmp_path,
                                                               monkeypatch):
    # The reference metric (facegeo.evaluate.relit) must be able to fail: relighting with
    # weights that forgot δA (the bug Eq. 4's δA guards against) is far from the generator's
    # render.
    import facegeo.lighting.relight as RL
    from facegeo.capture import imageio
    from facegeo.evaluate.relit import relit_error
    from facegeo.pipeline.relight import relight_products

    scan, _ = tiny_scan
    real = RL.relight_scan_view
    dA = light_solid_angles(scan.rig.lights.n_theta, scan.rig.lights.n_phi)
    monkeypatch.setattr(RL, "relight_scan_view",
                        lambda sc, cam, w, **kw: real(sc, cam, w / dA[:, None], **kw))
    cam = scan.camera_names[0]
    m, _ = relight_products(scan, None, tmp_path, env="studio", view=cam)
    w = E.light_stage_weights(E.shipped_map("studio"), scan.rig.lights.n_theta,
                              scan.rig.lights.n_phi)
    got = relit_error(scan, cam, w, imageio.read_image(m["files"]["exr"]))
    assert got["relative_rmse"] > 0.5


@pytest.mark.slow
def test_run_relight_bad_arguments(tiny_scan, tmp_path):
    from facegeo.capture import imageio
    from facegeo.pipeline.relight import run_relight

    scan, _ = tiny_scan
    env_file = imageio.write_image(tmp_path / "c.exr", np.ones((8, 16, 3), np.float32))
    with pytest.raises(InputError, match="texture atlas"):
        run_relight(scan.root, env_file, view="texture")
    with pytest.raises(InputError, match="unknown camera 'nope'"):
        run_relight(scan.root, env_file, view="nope")
    with pytest.raises(ShapeError, match="1:1"):
        run_relight(scan.root, env_file, projection="mirrorball")
    # a shipped map is lat-long: another projection is a mistake, not silently ignored
    with pytest.raises(InputError, match="shipped map 'sky' is lat-long"):
        run_relight(scan.root, "sky", projection="mirrorball")
    # a square map read as a mirror ball and as an angular map writes two images, not one
    # over the other
    square = imageio.write_image(tmp_path / "sq.exr", np.ones((16, 16, 3), np.float32))
    names = {run_relight(scan.root, square, projection=p, out_dir=tmp_path / "o")["files"]["exr"]
             for p in ("mirrorball", "angular")}
    assert len(names) == 2, names


# --------------------------------------------------------------------------- texture space


@pytest.fixture(scope="module")
def projected(tiny_scan, tmp_path_factory):
    """The tiny scan's atlas and surface reflectance field (``facegeo project``) in a folder of
    their own (so the camera-view tests still see a scan without them)."""
    from facegeo.pipeline.project import run_project

    scan, _ = tiny_scan
    out = tmp_path_factory.mktemp("projected") / "out"
    run_project(scan.root, out, gt_lights=4)
    return scan, out


def _blend_fields(field_dir, per_camera):
    """Independent reference: Σ_c w_c f_c(R_c) / Σ_c w_c in float64 with ``np.add.at``, where
    ``f_c`` maps a float32 chunk ``(n, L, 3)`` to ``(n, 3)``; non-finite values left out."""
    from facegeo.surface.atlas import Texels
    from facegeo.surface.reflectance import iter_field_chunks

    n_t = len(Texels.load(field_dir / "atlas" / "texels.npz"))
    acc = np.zeros((n_t, 3))
    wsum = np.zeros((n_t, 3))
    for cam in sorted((field_dir / "project").glob("*/R.npy")):
        idx = np.load(cam.parent / "texel_index.npy")
        wc = np.load(cam.parent / "weight.npy").astype(np.float64)
        for s, chunk in iter_field_chunks(cam.parent):
            v = per_camera(chunk.astype(np.float64))
            ok = np.isfinite(v)
            sl = slice(s, s + len(chunk))
            np.add.at(acc, idx[sl], np.where(ok, v, 0.0) * wc[sl, None])
            np.add.at(wsum, idx[sl], np.where(ok, wc[sl, None], 0.0))
    with np.errstate(invalid="ignore"):
        return np.where(wsum > 0, acc / np.where(wsum > 0, wsum, 1), np.nan)


@pytest.mark.slow
def test_texture_relight_with_one_light_equals_the_projected_olat_sample(projected):
    # Linearity / consistency: a weight vector lighting only light l (asymmetric channel
    # weights) relights the texture-space field to the camera-weighted blend of the projected
    # OLAT samples of light l. Metric: max |Δ| / max |reference| over measured texels, and the
    # same set of unmeasured (NaN) texels.
    from facegeo.pipeline.relight import relight_texture

    scan, out = projected
    n_l = scan.n_lights
    gain = np.array([0.7, 1.1, 1.3])
    for l in (0, n_l // 3, n_l - 5):
        w = np.zeros((n_l, 3))
        w[l] = gain
        got, wsum, cams = relight_texture(out, w)
        ref = _blend_fields(out, lambda c: c[:, l, :] * gain)
        assert cams == sorted(scan.camera_names)
        assert np.array_equal(np.isnan(got), np.isnan(ref))
        ok = np.isfinite(ref)
        assert ok.mean() > 0.3  # the tiny preset's two frontal cameras see ≈ 46 % of the head
        assert np.max(np.abs(got[ok] - ref[ok])) <= GEMM_REL * np.max(np.abs(ref[ok]))


@pytest.mark.slow
def test_texture_relight_of_a_uniform_environment_writes_the_irradiance_weighted_atlas(
        projected, tmp_path):
    # A constant environment of radiance 0.5 through the whole stage (EXR → Eq. 4 weights δA →
    # every camera's field → per-texel blend → atlas EXR): each texel equals the camera blend
    # of Σ_l R(l)·0.5·δA_l / colour_l computed independently in float64.
    from facegeo.capture import imageio
    from facegeo.pipeline.relight import run_relight
    from facegeo.surface.atlas import Texels

    scan, out = projected
    env_file = imageio.write_image(tmp_path / "grey.exr", np.full((16, 32, 3), 0.5, np.float32))
    calls = []
    m = run_relight(scan.root, env_file, view="texture", field_dir=out, out_dir=tmp_path / "o",
                    progress=lambda *a: calls.append(a))
    lights = scan.rig.lights
    w = E.light_stage_weights(E.read_envmap(env_file), lights.n_theta, lights.n_phi)
    assert np.allclose(w, 0.5 * light_solid_angles(lights.n_theta, lights.n_phi)[:, None],
                       rtol=1e-3)  # the uniform map's Eq. 4 weights are 0.5 · δA (paper δA)
    wn = w / np.broadcast_to(lights.color_rgb, w.shape)
    ref = _blend_fields(out, lambda c: np.einsum("tlc,lc->tc", c, wn))
    texels = Texels.load(out / "atlas" / "texels.npz")
    exr = imageio.read_image(m["files"]["exr"])
    assert exr.shape == texels.shape + (3,)
    got = exr[texels.row, texels.col]
    ok = np.isfinite(ref).all(axis=1)
    assert np.max(np.abs(got[ok] - ref[ok])) <= GEMM_REL * np.max(ref[ok])
    assert np.all(got[~ok] == 0)  # unmeasured texels are 0 in the image and flagged
    measured = imageio.read_image(m["files"]["measured"])
    assert np.array_equal(measured[texels.row, texels.col] > 0, ok)
    assert m["measured_texels"] == int(ok.sum()) and m["view"] == "texture"
    assert [c[1:] for c in calls] == [(k + 1, len(scan.camera_names))
                                      for k in range(len(scan.camera_names))]
    png = imageio.read_image(m["files"]["png"])
    assert png.dtype == np.uint8 and png.shape == exr.shape


@pytest.mark.slow
def test_texture_relight_without_a_projected_field_says_what_to_run(tiny_scan, tmp_path):
    from facegeo.pipeline.relight import relight_texture

    with pytest.raises(InputError, match="facegeo project"):
        relight_texture(tmp_path, np.ones((tiny_scan[0].n_lights, 3)))


def test_a_projection_onto_another_atlas_is_refused(projected, tmp_path):
    """The atlas rebuilt after the projection (other texel density): the fields' texel indices
    would address other texels — a garbage image, silently, when they stay in range. The
    readers compare the projection's recorded atlas fingerprint and say what to re-run."""
    import shutil

    from facegeo.pipeline.fit import run_fit
    from facegeo.pipeline.project import ATLAS_FINGERPRINT, run_atlas
    from facegeo.pipeline.relight import relight_texture
    from facegeo.pipeline.render import run_render

    scan, out = projected
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    assert (copy / "project" / ATLAS_FINGERPRINT).is_file()
    w = np.ones((scan.n_lights, 3))
    relight_texture(copy, w)  # the projection's own atlas: fine
    run_atlas(scan.root, copy, texels_per_mm=2.0)  # more texels: every old index in range
    with pytest.raises(InputError, match="projected onto another atlas"):
        relight_texture(copy, w)
    with pytest.raises(InputError, match="projected onto another atlas"):
        run_fit(scan.root, copy)
    with pytest.raises(InputError, match="projected onto another atlas"):
        run_render(scan.root, copy, camera_spec=scan.camera_names[0], resynthesis=False)


@pytest.mark.slow
def test_relight_products_texture_view_reads_the_stage_folders(projected, tmp_path):
    # relight_products with the 'project' stage folder (atlas found beside it) writes the same
    # atlas image as run_relight on the parent folder (bit-exact), and needs project_dir.
    from facegeo.capture import imageio
    from facegeo.pipeline.relight import relight_products, run_relight

    scan, out = projected
    m, settings = relight_products(scan, out / "project", tmp_path / "a", env="studio",
                                   view="texture")
    assert settings["view"] == "texture" and "reference" not in m
    assert m["measured_texels"] > 0
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == [
        "studio_rot0_texture.exr", "studio_rot0_texture.png", "studio_rot0_texture_measured.png"]
    r = run_relight(scan.root, "studio", view="texture", field_dir=out, out_dir=tmp_path / "b")
    assert np.array_equal(imageio.read_image(m["files"]["exr"]),
                          imageio.read_image(r["files"]["exr"]))
    with pytest.raises(InputError, match="project_dir"):
        relight_products(scan, None, tmp_path / "c", env="studio", view="texture")


# --------------------------------------------------------------------------- clothing colour


def test_tint_clothing_adds_tinted_indirect_light_and_commutes_with_relighting():
    # Paper Fig. 7: black + c ⊙ (white − black). With white = black + indirect, the result is
    # black + c ⊙ indirect (max |Δ| relative, GEMM_REL); c = 1 and 0 give the two captures;
    # tinting two fields then relighting equals relighting each then tinting (linearity).
    rng = np.random.default_rng(11)
    black = rng.random((200, 24, 3)).astype(np.float32)
    indirect = 0.3 * rng.random((200, 24, 3)).astype(np.float32)
    white = black + indirect
    c = np.array([0.1, 0.8, 0.2])
    got = R.tint_clothing(white, black, c)
    assert got.dtype == np.float32
    want = black.astype(np.float64) + c * indirect
    assert np.max(np.abs(got - want)) <= GEMM_REL * np.max(want)
    assert np.allclose(R.tint_clothing(white, black, np.ones(3)), white, rtol=1e-6)
    assert np.array_equal(R.tint_clothing(white, black, np.zeros(3)), black)
    w = rng.random((24, 3))
    a = R.relight_field(R.tint_clothing(white, black, c), w)
    b = R.tint_clothing(R.relight_field(white, w), R.relight_field(black, w), c)
    assert np.max(np.abs(a - b)) <= GEMM_REL * np.max(np.abs(a))
    with pytest.raises(ShapeError, match="same shape"):
        R.tint_clothing(white, black[:10], c)
    with pytest.raises(InputError, match="color"):
        R.tint_clothing(white, black, [0.5, -0.1, 0.2])


def test_a_real_capture_with_a_list_of_lights_relights(shared_data, tmp_path):
    """The Yale B capture (64 flash directions: a list of lights, not the θ × φ grid) relights
    through the CLI's path — it stopped with AttributeError 'n_theta' — with the weights of
    its own lights (envmap.light_weights): the energy check Σ w / ∫ L within 1 % (the list's
    Voronoi cells tile the sphere; measured 1.006–1.007 under sky, 1.000 under a flat map),
    and the image is Eq. 4 of its frames."""
    from facegeo.capture import imageio
    from facegeo.capture.datasets import import_dataset
    from facegeo.pipeline.relight import run_relight

    src = shared_data / "olat" / "yale_b01"
    if not src.is_dir():
        pytest.skip(f"{src} is absent")
    scan = import_dataset("yale-b", src, tmp_path / "yale")
    m = run_relight(scan.root, "sky", out_dir=tmp_path / "out")
    assert np.allclose(m["energy_ratio"], 1.0, atol=0.01), m["energy_ratio"]
    img = imageio.read_image(m["files"]["exr"])
    w = E.light_weights(E.shipped_map("sky"), scan.rig.lights)
    np.testing.assert_allclose(img, R.relight_scan_view(scan, m["view"], w,
                                                        normalize_color=True), rtol=1e-6)
    assert img.max() > 0


def test_a_light_list_relights_each_frame_by_its_own_intensity(shared_data, tmp_path):
    """A list of lights with uneven intensities: the scan view relit with colour normalisation
    is Eq. 4 with each light's weight divided by that light's own intensity, not by their mean
    (light_colors); the grid's is its one colour."""
    import json

    from facegeo.capture.datasets import import_dataset
    from facegeo.capture.scan import load_scan
    from facegeo.geometry.lights import light_colors
    from facegeo.geometry.rig import LightStage

    grid = LightStage(8, 4, color=(0.9, 1.0, 1.1))
    assert np.array_equal(light_colors(grid), [0.9, 1.0, 1.1])
    src = shared_data / "olat" / "yale_b01"
    if not src.is_dir():
        pytest.skip(f"{src} is absent")
    scan = import_dataset("yale-b", src, tmp_path / "yale")
    doc = json.loads((scan.root / "rig.json").read_text())
    n = scan.rig.lights.n_lights
    e = np.linspace(0.5, 2.0, 3 * n).reshape(n, 3)
    doc["lights"]["intensities"] = e.tolist()
    (scan.root / "rig.json").write_text(json.dumps(doc))
    scan = load_scan(scan.root)
    assert np.array_equal(light_colors(scan.rig.lights), e)
    view = scan.camera_names[0]
    w = E.light_weights(E.shipped_map("sky"), scan.rig.lights)
    got = R.relight_scan_view(scan, view, w, normalize_color=True)
    want = R.relight_scan_view(scan, view, w / e, normalize_color=False)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7 * float(want.max()))
    mean = R.relight_scan_view(scan, view, w / e.mean(axis=0), normalize_color=False)
    assert not np.allclose(got, mean, rtol=1e-3)
