"""The projection of one camera split into tasks by blocks of lights (issue 38,
facegeo.pipeline._project_blocks).

What is compared, stated with each assertion:

* products — every file of ``out/project/`` but ``stage.json``, byte for byte (SHA-256),
  between one task per camera and light blocks (in process and on the two-worker ``cluster``;
  ``.npy`` and Zarr fields): each block samples its frames at the positions its camera's
  visibility task saved and writes its columns, in the same chunks of lights, so the bytes are
  the same, not merely close;
* metrics — the stage's metrics without timings, the engine's record and the two new entries
  (``tasks``, ``lights_per_task``), equal as JSON (the per-camera counts are sums over blocks);
* the automatic rule and the settings' errors, on small stand-ins for an engine.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest

from conftest import file_digests, stage_metrics_without

from facegeo.errors import InputError

#: Products must be the same bytes whatever the split.
PRODUCTS_EQUAL = "sha256"
#: The tiny preset's lights (16 × 8) and the default light chunk of a field (block_lights).
TINY_LIGHTS, CHUNK = 128, 64
_TIMINGS = ("seconds", "peak_rss_mb", "seconds_visibility", "seconds_projection",
            "texels_per_second", "seconds_shadow_taps", "seconds_blend", "tasks",
            "lights_per_task")


def _without_timings(metrics: dict) -> dict:
    return stage_metrics_without(metrics, _TIMINGS)


def _project(root: Path, out: Path, **kw) -> dict:
    from facegeo.pipeline.project import run_project

    if not (out / "atlas").exists():
        shutil.copytree(root / "out" / "atlas", out / "atlas")
    return run_project(root, out, evaluate=False, **kw)


def test_light_blocks_in_process_equal_one_task_per_camera(projected, tmp_path):
    """lights_per_task=50 (rounded up to one chunk of 64: two blocks per camera) in process:
    the same bytes as the fixture's one task per camera, the same metrics but for timings;
    a visibility task and two block tasks per camera; progress counts lights; no scratch."""
    ref = json.loads((projected / "out" / "project" / "stage.json").read_text())["metrics"]
    calls = []
    m = _project(projected, tmp_path, lights_per_task=50, progress=lambda *a: calls.append(a))
    a = file_digests(projected / "out" / "project")
    b = file_digests(tmp_path / "project")
    assert a.keys() == b.keys() and "cam_left/R.npy" in a
    assert a == b, PRODUCTS_EQUAL
    assert _without_timings(m) == _without_timings(ref)
    assert m["lights_per_task"] == CHUNK and m["tasks"] == 2 * (1 + TINY_LIGHTS // CHUNK)
    assert ref["tasks"] == 2 and ref["lights_per_task"] is None
    assert calls[-1] == ("project", 2 * TINY_LIGHTS, 2 * TINY_LIGHTS)
    assert not (tmp_path / "project" / "_light_blocks").exists()


def test_light_blocks_on_two_workers_equal_one_task_per_camera(projected, tmp_path, cluster):
    """On the two-worker cluster, ``.npy`` fields (columns written in place by two processes
    through memory maps of one R.npy) and Zarr fields (disjoint whole chunks): the same bytes
    as one task per camera in process; each block ran on a worker within its memory limit."""
    m = _project(projected, tmp_path / "npy", lights_per_task=CHUNK, engine=cluster)
    assert file_digests(projected / "out" / "project") == file_digests(tmp_path / "npy" / "project"), \
        PRODUCTS_EQUAL
    tasks = m["engine"]["tasks"]
    assert {"cam_left visibility", "cam_left lights 0:64", "cam_left lights 64:128",
            "cam_right lights 64:128"} <= set(tasks)
    assert all(t["worker"].startswith("tcp://") for t in tasks.values())
    assert all(t["peak_rss_mb"] < m["engine"]["memory_limit_mb"] for t in tasks.values())
    ref = _project(projected, tmp_path / "zarr_one", field_format="zarr")
    got = _project(projected, tmp_path / "zarr_blocks", field_format="zarr",
                   lights_per_task=CHUNK, engine=cluster)
    a, b = file_digests(tmp_path / "zarr_one" / "project"), file_digests(tmp_path / "zarr_blocks"
                                                                   / "project")
    assert "cam_left/R.zarr/zarr.json" in a and not any(k.endswith("R.npy") for k in a)
    # the blend follows the engine (R_blend.npy in process, R_blend.zarr on a cluster: the same
    # values, docs/scale.md): compared as values; every other file as bytes
    blend = {k for k in a.keys() | b.keys() if k.startswith("blended/R_blend")}
    assert {k: v for k, v in a.items() if k not in blend} == \
        {k: v for k, v in b.items() if k not in blend}, PRODUCTS_EQUAL
    import numpy as np

    from facegeo.surface.reflectance import BLENDED_FILE, open_field

    np.testing.assert_array_equal(  # NaN where masked, in the same places
        np.asarray(open_field(tmp_path / "zarr_one" / "project" / "blended", BLENDED_FILE)),
        np.asarray(open_field(tmp_path / "zarr_blocks" / "project" / "blended",
                              BLENDED_FILE)[:]))
    assert _without_timings(got) == _without_timings(ref) and got["tasks"] == 6


class _Engine(SimpleNamespace):
    """A stand-in for an engine: its kind, workers and (a scheduler's) workers' addresses."""

    def __init__(self, kind="local-cluster", n_workers=2, addresses=()):
        info = {"workers": {a: {} for a in addresses}}
        client = SimpleNamespace(scheduler_info=lambda: info) if addresses else None
        super().__init__(kind=kind, n_workers=n_workers, client=client)


def test_automatic_rule():
    """Split on a Dask engine when cameras < 2 × workers and not a whole multiple of them,
    into blocks of whole chunks of at least AUTO_MIN_LIGHTS lights making >= 2 × workers
    tasks; never in process."""
    from facegeo.pipeline._project_blocks import AUTO_MIN_LIGHTS, auto_lights_per_task

    assert auto_lights_per_task(1, 2048, 64, _Engine("in-process", 1)) is None
    assert auto_lights_per_task(4, 2048, 64, _Engine(n_workers=2)) is None  # 4 >= 2 × 2
    assert auto_lights_per_task(2, 2048, 64, _Engine(n_workers=2)) is None  # one each
    assert auto_lights_per_task(4, 2048, 64, _Engine(n_workers=4)) is None
    # 3 cameras on 2 workers: 2 blocks each, 6 tasks (whole: the second round half idle)
    assert auto_lights_per_task(3, 2048, 64, _Engine(n_workers=2)) == 1024
    # the paper's rig: 1 camera × 2,048 lights on 2 workers → 4 blocks of 512
    assert auto_lights_per_task(1, 2048, 64, _Engine(n_workers=2)) == 512
    # 3 cameras on 8 workers: 6 blocks each
    assert auto_lights_per_task(3, 2048, 64, _Engine(n_workers=8)) == 384
    # never below AUTO_MIN_LIGHTS (whole chunks of 96: 288), nor the whole camera
    assert auto_lights_per_task(1, 2048, 96, _Engine(n_workers=16)) == 288 >= AUTO_MIN_LIGHTS
    assert auto_lights_per_task(1, TINY_LIGHTS, CHUNK, _Engine(n_workers=2)) is None


def test_lights_per_task_errors_and_rounding():
    from facegeo.pipeline._project_blocks import plan_lights_per_task

    def plan(value, engine=None, fmt="npy", store=False):
        return plan_lights_per_task(value, engine=engine or _Engine("in-process", 1),
                                    n_cameras=1, n_lights=512, chunk=64, field_format=fmt,
                                    in_store=store)

    assert plan(None) is None and plan(100) == 128 and plan(512) is None
    for bad in (0, -64, 1.5, True, "64"):
        with pytest.raises(InputError, match="lights_per_task"):
            plan(bad)
    with pytest.raises(InputError, match="not available with store"):
        plan(64, fmt="zarr", store=True)
    assert plan(None, _Engine(n_workers=2), fmt="zarr", store=True) is None
    two_hosts = _Engine("scheduler", 2, ("tcp://10.0.0.1:4000", "tcp://10.0.0.2:4000"))
    with pytest.raises(InputError, match="several machines"):
        plan(64, two_hosts)
    assert plan(None, two_hosts) is None  # .npy: no automatic split across machines
    assert plan(None, two_hosts, fmt="zarr") == 256  # 1 camera, 2 workers: 2 blocks
    one_host = _Engine("scheduler", 2, ("tcp://10.0.0.1:4000", "tcp://10.0.0.1:4001"))
    assert plan(64, one_host) == 64


def test_block_memory_check_before_anything_runs(projected, tmp_path):
    """Every task's working set (visibility and blocks) is checked before the first runs."""
    from facegeo.pipeline.engine import MEMORY_FRACTION, WORKER_BASE_BYTES, InProcessEngine

    eng = InProcessEngine(memory_limit=int((1 << 20) + WORKER_BASE_BYTES / MEMORY_FRACTION))
    with pytest.raises(InputError, match="project: task 'cam_left visibility' needs"):
        _project(projected, tmp_path, lights_per_task=CHUNK, engine=eng)
    assert not (tmp_path / "project").exists() and not eng.records


def test_cli_lights_per_task(tmp_path, capsys, monkeypatch):
    """``facegeo project --lights-per-task N --out DIR`` hands N (and the engine) to the stage;
    without --out (the cached chain) and on ``facegeo reconstruct`` N goes to
    ``run_reconstruct`` (not a stage setting: the products are the same bytes)."""
    from facegeo import cli
    from facegeo.pipeline import project, reconstruct

    got = {}
    monkeypatch.setattr(project, "run_project", lambda *a, **kw: got.update(kw) or {})
    scan = tmp_path / "scan"
    assert cli.main(["project", str(scan), "--out", str(tmp_path / "out"),
                     "--lights-per-task", "64", "-q"]) == 0
    assert got["lights_per_task"] == 64 and got["engine"].kind == "in-process"
    got.clear()
    assert cli.main(["project", str(scan), "--out", str(tmp_path / "out"), "-q"]) == 0
    assert got["lights_per_task"] is None
    chain = {}

    def fake_reconstruct(*a, **kw):
        chain.update(kw)
        raise cli.InputError("stopped here")

    monkeypatch.setattr(reconstruct, "run_reconstruct", fake_reconstruct)
    for cmd in ("project", "reconstruct"):
        chain.clear()
        assert cli.main([cmd, str(scan), "--lights-per-task", "64", "-q"]) != 0
        assert chain["lights_per_task"] == 64 and "settings" in chain
        assert "lights_per_task" not in (chain["settings"] or {}).get("project", {})
    with pytest.raises(SystemExit):
        cli.main(["project", str(scan), "--out", str(tmp_path), "--lights-per-task", "0"])
