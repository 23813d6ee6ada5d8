"""The ``fit`` stage on a single-view scan without geometry (``facegeo fit`` on Yale B and
DiLiGenT): image space, every masked pixel a texel, the held-out lights scored against the
Lambertian least squares of the same run. A synthetic DiLiGenT-layout object through the real
importer and the CLI, then the shared real data (skipped when absent)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from facegeo.appearance.lambertian import angular_error_deg
from facegeo.appearance.photometric import MODEL_NAMES, load_photometric, lobe_values, predict_light
from facegeo.capture.datasets import import_dataset
from facegeo.cli import main
from facegeo.errors import InputError
from facegeo.pipeline.reconstruct import run_reconstruct

#: Image size of the synthetic object (W ≠ H), its lights, its 16-bit scale.
W, H, N_LIGHTS, SCALE = 56, 44, 64, 20000.0
#: Real data: our normals may be at most this much worse than Lambertian's, degrees (mean).
NORMAL_TOL_DEG = 0.25


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _synthetic_diligent(folder, seed=0):
    """A DiLiGenT-layout object folder: an off-centre elliptical dome (x right, y up, z toward
    the camera), coloured albedo, a Torrance–Sparrow lobe on its right part, a cast shadow on
    its top band from lights on the left; RGB light intensities; 16-bit PNGs; Normal_gt.mat.
    Returns the truth (normals, mask, lobe and shadow regions)."""
    import cv2
    import scipy.io

    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True)
    r, c = np.mgrid[0:H, 0:W].astype(np.float64)
    px, py = (c - 30.5) / 22.0, -(r - 20.0) / 17.0
    rr = px ** 2 + py ** 2
    mask = rr < 0.85
    n = _unit(np.stack([px, py, np.sqrt(np.clip(1.0 - rr, 0.02, None))], axis=-1))
    t = np.radians(72.0) * np.sqrt(rng.uniform(0.03, 1.0, N_LIGHTS))
    p = rng.uniform(0.0, 2 * np.pi, N_LIGHTS)
    D = _unit(np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=1)
              + [0.04, -0.03, 0.0])
    E = rng.uniform(0.6, 1.4, (N_LIGHTS, 3))
    alb = np.stack([0.75 + 0.2 * px, 0.5 + 0.1 * py, 0.3 + 0.0 * px], axis=-1)
    lobe = mask & (px > 0.15)
    shadow = mask & (py > 0.45)
    nf, v = n.reshape(-1, 3), np.broadcast_to([0.0, 0.0, 1.0], (H * W, 3))
    diffuse = alb.reshape(-1, 1, 3) * np.maximum(nf @ D.T, 0.0)[..., None]
    spec = 0.6 * lobe.reshape(-1, 1) * lobe_values(nf, v, D, np.full(H * W, 0.1))
    vis = np.where(shadow.reshape(-1, 1) & (D[:, 0] < -0.2)[None, :], 0.03, 1.0)
    R = (diffuse + spec[..., None]) * vis[..., None] * E[None]
    R = R + 0.002 * rng.standard_normal(R.shape)
    R = np.where(mask.reshape(-1, 1, 1), R, 0.0)
    frames = np.clip(np.round(R * SCALE), 0, 65535).astype(np.uint16).reshape(H, W, N_LIGHTS, 3)
    names = [f"{k + 1:03d}.png" for k in range(N_LIGHTS)]
    for k, name in enumerate(names):
        cv2.imwrite(str(folder / name), frames[:, :, k, ::-1])  # OpenCV writes BGR
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", D, fmt="%.6f")
    np.savetxt(folder / "light_intensities.txt", E, fmt="%.6f")
    cv2.imwrite(str(folder / "mask.png"), (mask * 255).astype(np.uint8))
    scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": np.where(mask[..., None], n, 0.0)})
    return {"n": n, "mask": mask, "lobe": lobe, "shadow": shadow, "D": D, "E": E}


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    root = tmp_path_factory.mktemp("single_view")
    truth = _synthetic_diligent(root / "objPNG")
    return import_dataset("diligent", root / "objPNG", root / "scan"), truth


def _fit_metrics(scan_dir):
    return json.loads((scan_dir / "out" / "metrics.json").read_text())["fit"]


def test_facegeo_fit_fits_a_single_view_scan_in_image_space(synthetic):
    scan, truth = synthetic
    assert main(["fit", str(scan.root), "-q"]) == 0  # refused before: no mesh to build
    m = _fit_metrics(scan.root)
    out = scan.root / "out"
    assert not (out / "atlas").exists() and not (out / "project").exists()
    assert m["space"] == "image" and m["channels"] == "each" and m["light_gains"] == "given"
    assert (m["lights_fitted"], m["lights_held_out"]) == (32, 32)  # every other light
    assert m["pixels"] == m["pixels_fitted"] == int(truth["mask"].sum())
    # the held-out lights: well below the Lambertian fit of the same lights (the lobe and the
    # cast shadow are what Lambertian cannot predict); normals against Normal_gt
    assert m["heldout_rel_mae"] < 0.6 * m["heldout_rel_mae_lambertian"], m
    assert m["heldout_rel_rmse"] < 0.6 * m["heldout_rel_rmse_lambertian"], m
    assert m["normal_mean_error_deg"] < m["normal_mean_error_deg_lambertian"], m
    assert sum(m[f"model_fraction_{k.replace('+', '_')}"] for k in MODEL_NAMES) == \
        pytest.approx(1.0, abs=1e-4)
    for f in ("normal.exr", "normal.png", "albedo.exr", "specular.exr", "roughness.exr",
              "model.png", "fitted.png", "photometric.npz"):
        assert (out / "fit" / f).is_file(), f


def test_products_map_the_models_to_the_image_and_predict_the_held_out_frames(synthetic):
    from facegeo.capture.imageio import read_image

    scan, truth = synthetic
    run_reconstruct(scan.root, until="fit")  # cached from the test above, or run here
    fit_dir = scan.root / "out" / "fit"
    z = np.load(fit_dir / "photometric.npz")
    rows, (w, h) = z["rows"], z["image_size"]
    assert (w, h) == (W, H) and rows.size == truth["mask"].sum()
    model = load_photometric(fit_dir / "photometric.npz")
    where = np.zeros(H * W, np.int8) - 1
    where[rows] = model.model
    where = where.reshape(H, W)
    # the shadow map where the lights on the left are blocked, the lobe where it was rendered
    uses_shadow = (where == 1) | (where == 3)
    uses_lobe = (where == 2) | (where == 3)
    assert uses_shadow[truth["shadow"]].mean() > 0.6 > uses_shadow[truth["mask"]
                                                                    & ~truth["shadow"]].mean()
    assert uses_lobe[truth["lobe"]].mean() > 0.4 > uses_lobe[truth["mask"] & ~truth["lobe"]].mean()
    # the normal map is the model's normals, world frame
    nmap = read_image(fit_dir / "normal.exr").reshape(-1, 3)[rows]
    assert np.abs(nmap - model.normal).max() < 1e-6
    assert np.median(angular_error_deg(model.normal, truth["n"].reshape(-1, 3)[rows])) < 1.0
    # a held-out light predicted from the saved models: the frame as imported
    held = list(z["held_light_names"])
    k = int(held[3]) - 1
    frame = scan.olat_frame("cam", k).reshape(-1, 3)[rows]
    pred = predict_light(model, truth["D"][k], truth["E"][k])
    assert np.sqrt(((pred - frame) ** 2).sum() / (frame ** 2).sum()) < 0.2


def test_hold_out_settings(synthetic, tmp_path):
    from facegeo.pipeline._fit_image import fit_image_products

    scan, _ = synthetic
    for d in ("none", "odd", "names", "bad"):
        (tmp_path / d).mkdir()
    m, _ = fit_image_products(scan, tmp_path / "none", hold_out="none", max_pixels=300)
    assert m["lights_fitted"] == N_LIGHTS and m["lights_held_out"] == 0
    assert "heldout_rel_mae" not in m and m["pixels"] == 300
    m, _ = fit_image_products(scan, tmp_path / "odd", hold_out={"every": 2, "offset": 1},
                              max_pixels=300)
    assert (m["lights_fitted"], m["lights_held_out"]) == (32, 32)
    m, _ = fit_image_products(scan, tmp_path / "names", hold_out=["002", "017", "033"],
                              max_pixels=300)
    assert (m["lights_fitted"], m["lights_held_out"]) == (61, 3)
    with pytest.raises(InputError, match="no light named '099'"):
        fit_image_products(scan, tmp_path / "bad", hold_out=["099"])
    with pytest.raises(InputError, match="hold_out: expected 'every_other'"):
        fit_image_products(scan, tmp_path / "bad", hold_out="half")
    with pytest.raises(InputError, match="0 lights lie within 1.0°"):
        fit_image_products(scan, tmp_path / "bad", light_cone_deg=1.0)
    with pytest.raises(InputError, match="light_gains"):
        fit_image_products(scan, tmp_path / "bad", light_gains="calibrated")


def test_a_mesh_given_keeps_the_multi_view_chain(synthetic, tmp_path):
    from facegeo.pipeline.reconstruct import _applicable

    scan, _ = synthetic
    assert _applicable(scan, "auto") == ["fit"]
    assert _applicable(scan, str(tmp_path / "mesh.ply")) == ["atlas", "project", "relight",
                                                             "fit", "render"]


# --------------------------------------------------------------------------- real data
@pytest.fixture(scope="module")
def real(tmp_path_factory, shared_data):
    """Imported scans of the shared single-view data (each absent one skips its test)."""
    root = tmp_path_factory.mktemp("real_single_view")
    srcs = {"yale_b01": ("yale-b", shared_data / "olat" / "yale_b01"),
            "ball": ("diligent", shared_data / "olat" / "diligent" / "ballPNG"),
            "cat": ("diligent", shared_data / "olat" / "diligent" / "catPNG")}
    return {k: (lambda kind=kind, src=src, k=k: import_dataset(kind, src, root / k))
            if src.is_dir() else None for k, (kind, src) in srcs.items()}


#: The issue-36 protocols: Yale B01 the 27 lights strictly within 50° of the camera, every other
#: one fitted; DiLiGenT the even-numbered files (002, 004, …: positions 1, 3, …) fitted (the data
#: README). The cat is subsampled (every other masked pixel) to keep the test short.
PROTOCOLS = {"yale_b01": {"light_cone_deg": 50.0},
             "ball": {"hold_out": {"every": 2, "offset": 1}},
             "cat": {"hold_out": {"every": 2, "offset": 1}, "max_pixels": 22600}}


@pytest.mark.parametrize("name", sorted(PROTOCOLS))
def test_real_single_view_scans_beat_lambertian_on_held_out_lights(real, name):
    make = real[name] or pytest.skip(f"shared data for {name} is absent")
    scan = make()
    res = run_reconstruct(scan.root, settings={"fit": PROTOCOLS[name]}, until="fit")
    m = res[-1].metrics
    assert m["space"] == "image"
    assert m["heldout_rel_mae"] < m["heldout_rel_mae_lambertian"], m
    assert m["heldout_rel_rmse"] < m["heldout_rel_rmse_lambertian"], m
    if name == "yale_b01":
        assert (m["lights"], m["lights_fitted"], m["pixels"]) == (27, 14, 168 * 192)
        assert m["channels"] == "grey" and m["light_gains"] == "fit"
    else:
        assert m["light_gains"] == "given" and m["lights_fitted"] == 48
        assert m["normal_mean_error_deg"] <= m["normal_mean_error_deg_lambertian"] + \
            NORMAL_TOL_DEG, m
