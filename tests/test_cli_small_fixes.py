"""Small fixes of the command line: what it prints once, what it computes once, and what its
messages say."""

from __future__ import annotations

import json
import logging

import test_calibration
import test_mesh_camera_pair
from test_calibration import _projector_variant

#: Module-scoped fixtures of other stages' tests: a scan with projector board views, and the
#: tiny scan with decode maps from its ground truth.
projector_scan = test_calibration.projector_scan
tiny = test_mesh_camera_pair.tiny


def test_calibrate_says_projector_not_calibrated_once(projector_scan, tmp_path, capsys,
                                                      caplog):
    """``facegeo calibrate`` on a scan whose projector it cannot calibrate says so once, on
    stdout beside the table (it also came as the stage's warning on stderr); the stage's
    metrics keep the summary, and the stage called as a library still logs the warning."""
    from facegeo.cli import main
    from facegeo.pipeline.calibrate import run_calibrate

    scan = tmp_path / "scan"
    _projector_variant(projector_scan, scan, projector="uncalibrated", views=False)
    out = tmp_path / "cal"
    with caplog.at_level(logging.WARNING):
        assert main(["calibrate", str(scan), "--out", str(out), "-q",
                     "--no-cross-validation"]) == 0
    said = capsys.readouterr()
    pm = json.loads((out / "metrics.json").read_text())["calibrate"]["projector"]
    assert pm["calibrated"] is False and pm["summary"].startswith("projector: not calibrated (")
    logged = [r.getMessage() for r in caplog.records if "not calibrated" in r.getMessage()]
    printed = [ln for ln in (said.out + said.err).splitlines() if "not calibrated" in ln]
    assert printed == [pm["summary"]] and not logged, (printed, logged)
    assert pm["summary"] in said.out
    # the library's callers (facegeo reconstruct, scripts) still get the warning
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="facegeo.pipeline.calibrate"):
        m = run_calibrate(scan, tmp_path / "lib", cross_validation=False)
    assert [r.getMessage() for r in caplog.records
            if "not calibrated" in r.getMessage()] == [m["projector"]["summary"]]
    assert m["projector"] == pm


def _stale_out(root):
    """``root/out`` with stages a → b → c whose ``a`` ran again since b was made (b and c
    stale)."""
    out = root / "out"
    for name, key, up in (("a", "a2", None), ("b", "b1", {"a": "a1"}), ("c", "c1", {"b": "b1"})):
        (out / name).mkdir(parents=True)
        doc = {"key": key} | ({"upstream": up} if up else {})
        (out / name / "stage.json").write_text(json.dumps(doc))
    (out / "metrics.json").write_text(json.dumps({"a": {"seconds": 1.0}, "b": {"seconds": 2.0},
                                                  "c": {"seconds": 3.0}}))
    return out


def test_cli_reads_stale_stages_once_for_report_and_summary(tmp_path, monkeypatch, capsys):
    """``facegeo report`` (and every command that ends with the summary) reads the stages'
    staleness once and gives it to both the report and the printed table, which come out as
    before (each computing its own)."""
    import re

    import facegeo.pipeline.cache as cache
    import facegeo.pipeline.report as report
    from facegeo.cli import main

    out = _stale_out(tmp_path / "scan")
    expected = cache.stale_stages(out)
    assert expected == {"b": ["a"], "c": ["a"]}
    table = report.summary_table(json.loads((out / "metrics.json").read_text()), expected)
    page = report.write_report(out).read_text()
    calls = []
    real = cache.stale_stages
    counting = lambda d: calls.append(d) or real(d)  # noqa: E731
    monkeypatch.setattr(cache, "stale_stages", counting)
    monkeypatch.setattr(report, "stale_stages", counting)
    assert main(["report", str(tmp_path / "scan")]) == 0
    assert calls == [out], calls
    printed = capsys.readouterr().out
    assert table in printed and "[stale: made from an older a]" in table
    written = re.sub(r"written [0-9: -]+\.", "", (out / "report.html").read_text())
    assert written == re.sub(r"written [0-9: -]+\.", "", page)


def test_nominal_rig_rejecting_every_point_names_the_scan_and_what_to_do(tiny, tmp_path):
    """Camera–camera route with the scan's nominal cameras (rig.json, not calibrated) and an
    uncalibrated projector: every decoded pixel is inconsistent with the rig. The one-line
    error starts with the scan (it started with the decode folder), names the rig, and says
    what to do: calibrate the cameras and mesh with the calibrated rig."""
    import pytest

    from facegeo.errors import InputError
    from facegeo.geometry.rig import Projector, Rig
    from facegeo.pipeline.mesh import mesh_products

    scan, _ = tiny
    p = scan.rig.projector
    nominal = Rig(scan.rig.cameras, Projector(p.name, p.width, p.height), scan.rig.lights)
    rig_path = nominal.save(tmp_path / "rig_nominal.json")
    dest = tmp_path / "mesh"
    dest.mkdir()
    with pytest.raises(InputError) as err:
        mesh_products(scan, scan.out_dir / "decode", dest, depth=6, rig=str(rig_path))
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"scan {scan.root}: "), msg
    for part in ("only 0 points", str(rig_path), "camera-camera", "inconsistent",
                 str(scan.out_dir / "decode"), f"facegeo calibrate {scan.root}",
                 "--rig calibrated"):
        assert part in msg, (part, msg)


#: The start of the warning ``--rig auto`` logs when it takes the true rig over an
#: uncalibrated rig.json projector.
_AUTO_RIG_WARNING = ("rig auto: using the generator's true rig; rig.json's projector is "
                     "uncalibrated")


def test_rig_auto_over_uncalibrated_projector_warns_once_per_run(tiny, tmp_path, caplog,
                                                                 capsys, monkeypatch):
    """``--rig auto`` on a synthetic scan whose rig.json projector is uncalibrated and whose
    calibration failed (the tiny boards; issue 37: ``auto`` is the calibrated rig when the
    calibration succeeds) falls back to the generator's true rig, and says so in one warning
    of the pipeline's logger: once when the chain is built (not once per stage that uses the
    rig), once through ``facegeo mesh`` (stderr, as a logged warning). With the scan's own
    calibrated projector, an explicit ``--rig``, a calibration that succeeded, or a run that
    does not mesh (``facegeo project`` with the true mesh, ``--only atlas``), nothing is said."""
    from facegeo.pipeline.cache import StageResult

    failed = "calib/ views: no ArUco markers found"
    import facegeo.cli as cli
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.cache import Pipeline
    from facegeo.pipeline.reconstruct import reconstruct_pipeline

    scan_cal, _ = tiny
    assert scan_cal.rig.projector_calibrated
    root = tmp_path / "scan"
    _projector_variant(scan_cal.root, root, projector="uncalibrated", views=True)
    scan = load_scan(root)
    assert not scan.rig.projector_calibrated

    def warned() -> list[str]:
        return [r.getMessage() for r in caplog.records if r.name == "facegeo.pipeline.reconstruct"
                and _AUTO_RIG_WARNING in r.getMessage()]

    with caplog.at_level(logging.WARNING, logger="facegeo.pipeline.reconstruct"):
        pipeline = reconstruct_pipeline(scan, rig="auto", calibration_error=failed)
    rigs = {s.name: s.settings["rig"] for s in pipeline.stages if "rig" in s.settings}
    assert "mesh" in rigs and set(rigs.values()) == {"ground_truth"}, rigs  # the choice is kept
    assert len(warned()) == 1, warned()
    assert "--rig scan" in warned()[0]

    for s, rig, error in ((scan_cal, "auto", failed), (scan, "scan", None),
                          (scan, "ground_truth", None), (scan, "auto", None)):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="facegeo.pipeline.reconstruct"):
            reconstruct_pipeline(s, rig=rig, calibration_error=error)
        assert warned() == [], (s.root, rig, warned())
    # only a run that may mesh says it: until / only a stage before the mesh stage, or one
    # that needs none, is silent (the chain's atlas and project now wait for the mesh stage)
    full = reconstruct_pipeline(scan, rig="auto", calibration_error=failed)
    for kw, meshes in ((dict(until="mesh"), True), (dict(only="mesh"), True),
                       (dict(until="decode"), False), (dict(only="atlas"), False),
                       (dict(until="project"), True), (dict(until="project", only="mesh"), True)):
        assert ("mesh" in full.stages_run(**kw)) == meshes, kw
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="facegeo.pipeline.reconstruct"):
            reconstruct_pipeline(scan, rig="auto", calibration_error=failed, **kw)
        assert len(warned()) == int(meshes), (kw, warned())

    # the command line: the chain is built once per run; the stages themselves are not run
    # (the calibration, run first by "auto", records the failure the tiny boards give)
    runs = []

    def fake_run(self, *a, **k):
        runs.append(self)
        if k.get("until") == "calibrate":
            return [StageResult("calibrate", "key", True, 0.0, {"error": failed},
                                root / "out" / "calibrate")]
        return []

    monkeypatch.setattr(Pipeline, "run", fake_run)
    monkeypatch.setattr(cli, "_write_report", lambda out, **kw: None)
    caplog.clear()
    capsys.readouterr()
    with caplog.at_level(logging.WARNING):
        assert cli.main(["mesh", str(root), "-q"]) == 0
    said = capsys.readouterr()
    printed = [ln for ln in (said.out + said.err).splitlines() if _AUTO_RIG_WARNING in ln]
    # two runs: the calibration first, then the chain it decides
    assert len(runs) == 2 and len(warned()) == 1 and printed == [], (runs, warned(), printed)
    caplog.clear()  # facegeo project on the true mesh does not mesh: nothing said
    with caplog.at_level(logging.WARNING):
        assert cli.main(["project", str(root), "--mesh", "ground_truth", "-q"]) == 0
    assert warned() == [], (runs, warned())


def test_calibrate_says_camera_with_few_views_once(tmp_path, capsys, caplog):
    """``facegeo calibrate`` on a rig whose camera saw 2 board views: the warning that its
    intrinsics stay nominal comes once on stderr (it came as the stage's logged warning and
    again through the progress lines), with or without ``-q``; the metrics keep it, and the
    stage called as a library without ``progress`` still logs it."""
    from facegeo.cli import main
    from facegeo.pipeline.calibrate import run_calibrate
    from test_calibration import _corner_list_scan

    root = tmp_path / "scan"
    root.mkdir()
    _corner_list_scan(root, nominal_intrinsics=True, views_b=[0, 2])
    said_it = "camera cam_b: 2 usable board view(s)"
    for quiet in ((), ("-q",)):
        out = tmp_path / f"cal{len(quiet)}"
        caplog.clear()
        capsys.readouterr()
        with caplog.at_level(logging.WARNING):
            assert main(["calibrate", str(root), "--out", str(out), "--no-cross-validation",
                         *quiet]) == 0
        said = capsys.readouterr()
        # a logged record reaches stderr through the CLI's logging handler
        logged = [r.getMessage() for r in caplog.records if said_it in r.getMessage()]
        printed = [ln for ln in (said.out + said.err).splitlines() if said_it in ln]
        assert len(logged) + len(printed) == 1, (quiet, logged, printed)
        cm = json.loads((out / "metrics.json").read_text())["calibrate"]["cameras"]["cam_b"]
        assert cm["intrinsics"] == "nominal" and said_it in cm["warning"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="facegeo.pipeline.calibrate"):
        m = run_calibrate(root, tmp_path / "lib", cross_validation=False)
    assert [r.getMessage() for r in caplog.records
            if said_it in r.getMessage()] == [m["cameras"]["cam_b"]["warning"]]


def test_fill_distance_and_surface_options_reach_their_stages(tmp_path, monkeypatch):
    """``--fill-distance-mm`` is the mesh stage's ``fill_distance_mm``, ``--surface`` the
    atlas's ``surface``; options not given send nothing (the default runs' cache keys stay)."""
    import facegeo.pipeline.reconstruct as R
    from facegeo import cli
    from facegeo.errors import InputError

    seen = []

    def fake(scan, **kw):
        seen.append(kw["settings"])
        raise InputError("stopped by the test")

    monkeypatch.setattr(R, "run_reconstruct", fake)
    argv = ["reconstruct", str(tmp_path), "-q"]
    assert cli.main(argv + ["--surface", "trimmed", "--fill-distance-mm", "20"]) == 2
    assert cli.main(argv) == 2
    assert cli.main(["fit", str(tmp_path), "-q", "--surface", "filled"]) == 2
    assert seen == [{"mesh": {"fill_distance_mm": 20.0}, "atlas": {"surface": "trimmed"}},
                    None, {"atlas": {"surface": "filled"}}]
