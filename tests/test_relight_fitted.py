"""``facegeo relight --model fitted`` (issue 36): a single-view scan's image-space fit relit
under any environment, every direction predicted by the fitted models (specular lobes from
their parameters); the dome-energy note of the measured relight; ``facegeo render``'s message
on such a scan."""

from __future__ import annotations

import json

import numpy as np
import pytest

from facegeo.capture.datasets import import_dataset
from facegeo.cli import main
from facegeo.errors import InputError
from test_fit_single_view import SCALE, _synthetic_diligent

#: Uniform environment of radiance 1: a Lambertian pixel's relit radiance is π b (b its fitted
#: albedo vector's channel); median relative error over the diffuse, unshadowed pixels
#: against π × the true albedo in frame units (measured 0.1 %; the noise of the fit).
UNIFORM_REL = 0.02


@pytest.fixture(scope="module")
def fitted_scan(tmp_path_factory):
    root = tmp_path_factory.mktemp("relight_fitted")
    truth = _synthetic_diligent(root / "objPNG")
    scan = import_dataset("diligent", root / "objPNG", root / "scan")
    assert main(["fit", str(scan.root), "-q"]) == 0
    return scan, truth


def test_fitted_relight_of_a_uniform_environment_is_pi_times_the_albedo(fitted_scan):
    from facegeo.lighting import envmap as E
    from facegeo.pipeline.relight import relight_fitted

    scan, truth = fitted_scan
    uniform = E.analytic_map(lambda v: np.ones(v.shape[:-1] + (3,)), 32)
    img, w = relight_fitted(scan.out_dir / "fit" / "photometric.npz", uniform)
    assert w.sum(axis=0) == pytest.approx(uniform.integral(), rel=1e-6)  # every direction
    H, W = truth["mask"].shape
    r, c = np.mgrid[0:H, 0:W]
    px, py = (c - 30.5) / 22.0, -(r - 20.0) / 17.0
    alb = np.stack([0.75 + 0.2 * px, 0.5 + 0.1 * py, 0.3 + 0.0 * px], axis=-1)
    # the frames were written as radiance × SCALE in 16 bits, read linearly (/ 65535)
    want = np.pi * alb * SCALE / 65535.0
    plain = truth["mask"] & ~truth["lobe"] & ~truth["shadow"]
    rel = np.abs(img[plain] - want[plain]) / want[plain]
    print(f"uniform environment, fitted model: median relative error {np.median(rel):.4f}")
    assert np.median(rel) <= UNIFORM_REL
    assert np.all(img[~truth["mask"]] == 0)


def test_cli_relight_fitted_and_the_dome_energy_note(fitted_scan, capsys):
    scan, _ = fitted_scan
    assert main(["relight", str(scan.root), "--env", "sky", "--model", "fitted", "-q"]) == 0
    out = capsys.readouterr().out
    assert "directions of the fitted model" in out and "note:" not in out
    m = json.loads(next((scan.out_dir / "relit").glob("*_fitted.json")).read_text())
    assert m["model"] == "fitted" and m["energy_note"] is None
    assert min(m["energy_ratio"]) == pytest.approx(1.0, abs=1e-6)
    # the measured frames: the lights (within 72° of the camera) keep part of the sky's energy
    assert main(["relight", str(scan.root), "--env", "sky", "-q"]) == 0
    out = capsys.readouterr().out
    m = json.loads((scan.out_dir / "relit" / "sky_rot0_cam.json").read_text())
    assert m["energy_note"] is not None and min(m["energy_ratio"]) < 0.95
    assert f"keep only {min(m['energy_ratio']):.0%}" in out


def test_fitted_relight_needs_an_image_space_fit(tmp_path):
    from facegeo.pipeline.relight import run_relight

    truth = _synthetic_diligent(tmp_path / "objPNG", seed=1)
    scan = import_dataset("diligent", tmp_path / "objPNG", tmp_path / "scan")
    with pytest.raises(InputError, match="photometric.npz is missing.*facegeo fit"):
        run_relight(scan.root, "sky", model="fitted")
    with pytest.raises(InputError, match="single-view scan"):
        run_relight(scan.root, "sky", model="fitted", view="texture")
    assert truth["mask"].any()


def test_render_on_a_single_view_scan_says_what_works(fitted_scan, capsys):
    scan, _ = fitted_scan
    assert main(["render", str(scan.root), "--camera", "cam", "-q"]) != 0
    err = capsys.readouterr().err
    assert "single-view scan without geometry" in err and "--model fitted" in err
    assert "atlas.npz" not in err
