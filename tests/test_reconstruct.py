"""`facegeo reconstruct`: the built stages run once, then come from the cache."""

from __future__ import annotations

import json

import pytest

from facegeo.cli import main
from facegeo.pipeline import reconstruct


@pytest.fixture(scope="module")
def tiny_scan(tmp_path_factory):
    root = tmp_path_factory.mktemp("rec") / "scan"
    assert main(["synth", str(root), "--preset", "tiny", "-q"]) == 0
    return root


def test_second_run_does_no_work_and_metrics_gather(tiny_scan, capsys):
    assert main(["reconstruct", str(tiny_scan), "-q"]) == 0
    first = capsys.readouterr().out
    assert "atlas      ran" in first and "project    ran" in first
    assert main(["reconstruct", str(tiny_scan), "-q"]) == 0
    second = capsys.readouterr().out
    assert second.count("cached (inputs unchanged)") == 2
    metrics = json.loads((tiny_scan / "out" / "metrics.json").read_text())
    assert set(reconstruct.STAGES) <= set(metrics)
    # the projection is compared with the generator's exact shading (tiny preset: ≈ 5–7 %,
    # dominated by bilinear sampling across cast-shadow edges at 80 × 120 px)
    assert metrics["project"]["projection_rel_rmse"] < 0.10
    assert metrics["project"]["visibility_agreement"] > 0.99


def test_setting_change_and_only(tiny_scan):
    ran = []
    reconstruct.run_reconstruct(tiny_scan, on_stage=lambda r: ran.append((r.name, r.ran)))
    assert ran == [("atlas", False), ("project", False)]
    ran.clear()
    reconstruct.run_reconstruct(tiny_scan, settings={"project": {"gt_lights": 8}},
                                on_stage=lambda r: ran.append((r.name, r.ran)))
    assert ran == [("atlas", False), ("project", True)]
    ran.clear()
    reconstruct.run_reconstruct(tiny_scan, only="atlas",
                                on_stage=lambda r: ran.append((r.name, r.ran)))
    assert ran == [("atlas", True)]


def test_failed_stage_keeps_earlier_products(tiny_scan, monkeypatch, capsys):
    from facegeo.pipeline import project

    before = (tiny_scan / "out" / "atlas" / "stage.json").read_bytes()

    def boom(*a, **k):
        raise RuntimeError("injected failure in project")

    monkeypatch.setattr(project, "project_products", boom)
    assert main(["reconstruct", str(tiny_scan), "--from", "project", "-q"]) == 1
    assert "injected failure" in capsys.readouterr().err
    assert (tiny_scan / "out" / "atlas" / "stage.json").read_bytes() == before
    assert (tiny_scan / "out" / "project" / "stage.json").is_file()  # old products intact
    assert not [p for p in (tiny_scan / "out").iterdir() if ".facegeo-tmp-" in p.name]


def test_bad_stage_name_and_missing_mesh(tiny_scan, tmp_path, capsys):
    assert main(["reconstruct", str(tiny_scan), "--only", "mesh", "-q"]) == 2
    assert "unknown stage" in capsys.readouterr().err
    assert main(["reconstruct", str(tiny_scan), "--mesh", str(tmp_path / "none.ply"), "-q"]) == 2
    assert "none.ply" in capsys.readouterr().err
