"""The facegeo command line, run in-process."""

from __future__ import annotations

import subprocess
import sys

import pytest

from facegeo.cli import main


def test_help_is_fast_and_lists_commands():
    out = subprocess.run([sys.executable, "-m", "facegeo.cli", "--help"], capture_output=True,
                         text=True, check=True).stdout
    for cmd in ("synth", "info", "bench", "demo"):
        assert cmd in out
    # --help must not import the heavy dependencies
    code = ("import sys, facegeo.cli; facegeo.cli.build_parser(); "
            "print(sorted(m for m in ('open3d', 'trimesh', 'embreex', 'cv2', 'OpenEXR') if m in sys.modules))")
    heavy = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert heavy.strip() == "[]"


def test_demo_synth_info_round_trip(tmp_path, capsys):
    root = tmp_path / "demo"
    assert main(["demo", str(root), "--preset", "tiny", "-q"]) == 0
    out = capsys.readouterr().out
    assert "synthesised" in out and "cam_left" in out
    assert main(["demo", str(root), "--preset", "tiny", "-q"]) == 0  # reuses the scan
    assert "using the existing synthetic scan" in capsys.readouterr().out
    assert main(["info", str(root), "--full"]) == 0
    assert "every frame decoded" in capsys.readouterr().out
    # synth refuses to overwrite, with a clear message and status 2
    assert main(["synth", str(root), "--preset", "tiny", "-q"]) == 2
    assert "already holds a scan" in capsys.readouterr().err


def test_info_reports_a_broken_scan(tmp_path, capsys):
    root = tmp_path / "demo"
    assert main(["synth", str(root), "--preset", "tiny", "-q"]) == 0
    capsys.readouterr()
    victim = sorted((root / "olat" / "cam_right").glob("*.exr"))[5]
    victim.unlink()
    assert main(["info", str(root)]) == 2
    err = capsys.readouterr().err
    assert "cam_right" in err and victim.name in err


def test_synth_rejects_bad_arguments(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["synth", str(tmp_path / "x"), "--preset", "huge"])
    assert main(["synth", str(tmp_path / "x"), "--preset", "tiny", "--head", str(tmp_path / "nope.obj"), "-q"]) == 2
    assert "no such mesh file" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()  # nothing written for bad arguments
