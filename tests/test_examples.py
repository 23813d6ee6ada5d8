"""The scripts in ``examples/`` run on tiny inputs and do what their docstrings say."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_file

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_example_has_a_run_line():
    for p in EXAMPLES.glob("*.py"):
        text = p.read_text()
        assert '"""' in text.splitlines()[0] and "Run:" in text, f"{p.name}: no docstring/Run line"


@pytest.mark.parametrize("script, extra", [("relight_view", ["env.exr"]), ("turntable", []),
                                            ("structured_light_mesh", [])])
def test_examples_report_a_missing_scan_in_one_line(script, extra, tmp_path):
    """A user mistake is one line ``error: ...`` on stderr and status 2, as in the CLI."""
    nope = tmp_path / "nope"
    r = subprocess.run([sys.executable, str(EXAMPLES / f"{script}.py"), str(nope), *extra],
                       capture_output=True, text=True, timeout=300)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert lines == [f"{script}.py: error: {nope}: scan directory not found"], r.stderr


@pytest.mark.slow
def test_relight_view_tiny(tmp_path):
    ex = _load("relight_view")
    assert ex.main(["--tiny", "--out", str(tmp_path)]) == 0
    from facegeo.capture.imageio import read_image

    exr = list(tmp_path.glob("relit_*.exr"))
    png = list(tmp_path.glob("relit_*.png"))
    assert len(exr) == 1 and len(png) == 1
    img = read_image(exr[0])
    assert np.isfinite(img).all() and img.mean() > 0


def test_calibrate_own_board_matches_opencv_on_real_chessboards(shared_data):
    d = shared_file(shared_data, "calibration/opencv_stereo_chessboards")
    ex = _load("calibrate_own_board")
    from facegeo.geometry.calibration import ChessboardSpec

    paths = sorted(d.glob("left*.jpg"))
    r = ex.calibrate(ex.load_gray(paths), ChessboardSpec(9, 6, 0.025), names=[p.name for p in paths])
    # same corners, same model: facegeo's solver reaches OpenCV's optimum
    assert r["rms_px"] == pytest.approx(r["rms_px_opencv"], rel=1e-3)
    np.testing.assert_allclose(r["K"], r["K_opencv"], rtol=1e-3)


@pytest.mark.slow
def test_fixture_example_passes():
    """The pytest-fixture example is itself a passing test file."""
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                        str(EXAMPLES / "test_fixture_example.py")],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "2 passed" in r.stdout


def test_spectral_skin_example(tmp_path):
    r = subprocess.run([sys.executable, str(EXAMPLES / "spectral_skin.py"), str(tmp_path)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    maps = tmp_path / "parameter_maps"
    for name in ("C_m.png", "C_h.png", "beta_m.png", "parameter_maps.json"):
        assert (maps / name).is_file(), name
    assert "identifiable" in r.stdout


@pytest.mark.slow
def test_structured_light_mesh_tiny(tmp_path, monkeypatch):
    ex = _load("structured_light_mesh")
    from facegeo.synth.capture import generate_scan

    scan = tmp_path / "scan"
    generate_scan(scan, preset="tiny")
    m = ex.reconstruct_mesh(scan)
    assert (scan / "out" / "mesh" / "mesh.ply").is_file()
    assert m["points_rms_error_mm"] < 0.5  # tiny preset: 80 x 120 px cameras


@pytest.mark.slow
def test_turntable_tiny(tmp_path):
    ex = _load("turntable")
    from facegeo.synth.capture import generate_scan

    scan = tmp_path / "scan"
    generate_scan(scan, preset="tiny")
    res = ex.turntable(scan, step=90.0, env="sky", naive=True, out_gif=tmp_path / "t.gif")
    assert len(res) == 3 and (tmp_path / "t.gif").stat().st_size > 0
    # the frame at 0 deg is the source camera: the naive render reproduces it closely. On the
    # chain (the reconstructed mesh, issue 37) measured 31.7 dB (the true mesh gave > 35); a
    # flat mean-colour image scores 13.7-17.5 dB, a black one 13.0
    front = [r for r in res if r["camera_spec"].endswith(":0")][0]
    assert front["psnr_db"] > 30


def test_relight_view_on_the_real_yale_capture(shared_data, tmp_path):
    """The example on a real capture whose lights are a list, not the θ × φ grid (it computed
    grid weights and stopped with AttributeError 'n_theta')."""
    from facegeo.capture.datasets import import_dataset

    src = shared_file(shared_data, "olat/yale_b01")
    env = shared_file(shared_data, "envmaps/forest.exr")
    import_dataset("yale-b", src, tmp_path / "yale")
    ex = _load("relight_view")
    assert ex.main([str(tmp_path / "yale"), str(env), "--out", str(tmp_path / "o")]) == 0
    from facegeo.capture.imageio import read_image

    img = read_image(next((tmp_path / "o").glob("relit_*.exr")))
    assert np.isfinite(img).all() and img.mean() > 0
