"""The execution engine (facegeo.pipeline.engine) and the decode stage on it.

What is compared, stated with each assertion:

* products — every file of ``out/decode/<camera>/`` byte for byte (SHA-256) between the
  in-process run and a ``LocalCluster`` of two workers × one thread;
* metrics — the stage's metrics with the timings (``seconds``, ``peak_rss_mb``) and the
  cluster's own ``engine`` entry left out, equal as JSON;
* memory — a task's working set against a worker's budget (``MEMORY_FRACTION`` × limit −
  ``WORKER_BASE_BYTES``), checked before anything runs.

The ``project`` stage on the engine (one task per camera) is compared the same way: its products
byte for byte — each camera's task runs the same code on the same inputs in one process, and the
blend and the preview run on the client in camera order, so nothing depends on where a camera
ran (equal bytes, not merely 1e-6). With ``field_format="zarr"`` each camera's ``R.zarr`` holds
the ``.npy`` run's float16 values exactly, and the relight stage reads it through the
reflectance module's readers.

The cluster tests start two worker processes with a small memory limit and close them (context
manager) whatever happens.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import file_digests, stage_metrics_without

from facegeo.errors import InputError
from facegeo.pipeline.engine import (
    MAX_RESULT_BYTES,
    MEMORY_FRACTION,
    WORKER_BASE_BYTES,
    InProcessEngine,
    Task,
    make_engine,
    parse_memory,
)

#: Memory limit of each worker of the test clusters (the tiny scan's camera needs ≈ 5 MB).
WORKER_LIMIT = "700MiB"
#: Products must be the same bytes whatever the engine.
PRODUCTS_EQUAL = "sha256"
#: Relit texels from a Zarr field against the same field as .npy: the same float16 samples
#: through the same relighting, so equal to float32 rounding (relative, worst texel).
ZARR_RELIT_RTOL = 1e-6
_TIMINGS = ("seconds", "peak_rss_mb", "seconds_visibility", "seconds_projection",
            "texels_per_second", "seconds_shadow_taps", "seconds_blend")


# ------------------------------------------------------------------ task functions (importable)


def _square(x: int) -> dict:
    return {"x": x, "square": x * x}


def _not_a_dict(x: int):
    return [x]


def _too_big(n: int) -> dict:
    return {"payload": b"\0" * n}


def _write_then_return(path: str) -> dict:
    Path(path).write_text("done", encoding="utf-8")
    return {"path": path}


def _fail_later(seconds: float) -> dict:
    time.sleep(seconds)
    raise ValueError("camera broken on purpose")


# ------------------------------------------------------------------ in process


def test_in_process_runs_in_order_with_progress():
    calls = []
    eng = InProcessEngine()
    tasks = [Task(f"t{i}", _square, (i,)) for i in (3, 1, 2)]
    out = eng.map("demo", tasks, progress=lambda *a: calls.append(a))
    assert out == [{"x": 3, "square": 9}, {"x": 1, "square": 1}, {"x": 2, "square": 4}]
    assert calls == [("demo", 0, 3), ("demo", 1, 3), ("demo", 2, 3), ("demo", 3, 3)]
    assert [r.task for r in eng.records] == ["t3", "t1", "t2"]
    assert all(r.worker == "in-process" for r in eng.records)


def test_progress_counts_task_sizes():
    """``progress`` counts each task's ``size`` (a fit task: its functions), not tasks."""
    calls = []
    tasks = [Task(f"t{i}", _square, (i,), size=n) for i, n in ((1, 5), (2, 0), (3, 7))]
    InProcessEngine().map("fit", tasks, progress=lambda *a: calls.append(a))
    assert calls == [("fit", 0, 12), ("fit", 5, 12), ("fit", 5, 12), ("fit", 12, 12)]


def test_results_must_be_small_dicts():
    eng = InProcessEngine()
    with pytest.raises(InputError, match="returned list"):
        eng.map("demo", [Task("a", _not_a_dict, (1,))])
    with pytest.raises(InputError, match="over the"):
        eng.map("demo", [Task("big", _too_big, (MAX_RESULT_BYTES + 10,))])
    with pytest.raises(InputError, match="unique"):
        eng.map("demo", [Task("a", _square, (1,)), Task("a", _square, (2,))])


def test_working_set_over_the_budget_stops_before_any_task(tmp_path):
    limit = 1 << 30
    budget = int(limit * MEMORY_FRACTION) - WORKER_BASE_BYTES
    eng = InProcessEngine(memory_limit=limit)
    assert eng.task_budget() == budget
    marker = tmp_path / "ran.txt"
    tasks = [Task("first", _write_then_return, (str(marker),), working_set=budget),
             Task("cam_big", _square, (1,), working_set=budget + 1)]
    with pytest.raises(InputError, match=r"task 'cam_big' needs .* MiB") as info:
        eng.map("decode", tasks)
    assert "--memory-limit" in str(info.value)
    assert not marker.exists()  # checked before the first task ran
    # at the budget it runs
    assert eng.map("decode", tasks[:1]) == [{"path": str(marker)}]
    # no limit: no check
    assert InProcessEngine().map("decode", tasks[1:]) == [{"x": 1, "square": 1}]


@pytest.mark.parametrize("value,expected", [
    (None, None), (1024, 1024), ("2GiB", 2 << 30), ("1.5 GB", 1_500_000_000),
    ("512MB", 512_000_000), ("700MiB", 700 << 20)])
def test_parse_memory(value, expected):
    assert parse_memory(value) == expected


@pytest.mark.parametrize("bad", ["lots", "2 parsecs", -1, 0, True, [1]])
def test_parse_memory_rejects(bad):
    with pytest.raises(InputError, match="memory_limit"):
        parse_memory(bad)


def test_make_engine_options():
    with pytest.raises(InputError, match="give one"):
        make_engine(workers=2, scheduler="tcp://127.0.0.1:1")
    with pytest.raises(InputError, match="own"):
        make_engine(scheduler="tcp://127.0.0.1:1", memory_limit="1GiB")
    eng = make_engine()
    assert eng.kind == "in-process" and eng.memory_limit is None
    assert make_engine(memory_limit="1GiB").memory_limit == 1 << 30


def test_in_process_path_imports_no_dask(tmp_path):
    """The default path (make demo, the tests) needs no cluster: neither dask nor distributed
    is imported by the engine or the decode stage's module."""
    code = (
        "import sys\n"
        "from facegeo.pipeline.engine import make_engine, Task\n"
        "import facegeo.pipeline.decode\n"
        "e = make_engine()\n"
        "print(e.map('s', [Task('a', dict, ())]))\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120)
    assert out.stdout.splitlines() == ["[{}]", "[]"], out.stdout + out.stderr


# ------------------------------------------------------------------ the decode stage


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from facegeo.synth.capture import generate_scan

    root = tmp_path_factory.mktemp("engine") / "tiny"
    generate_scan(root, "tiny", noise=0.005)
    return root


def _without_timings(metrics: dict) -> dict:
    return stage_metrics_without(metrics, _TIMINGS)


def test_decode_memory_check_names_the_camera(tiny, tmp_path):
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.decode import decode_working_set, run_decode

    scan = load_scan(tiny)
    need = decode_working_set(scan, "cam_left")
    assert need == 80 * 120 * (need // (80 * 120)) and need > 0
    # a budget one byte short of the camera's working set
    limit = int((need - 1 + WORKER_BASE_BYTES) / MEMORY_FRACTION)
    eng = InProcessEngine(memory_limit=limit)
    assert eng.task_budget() < need
    with pytest.raises(InputError, match="task 'cam_left' needs"):
        run_decode(scan, tmp_path / "out", engine=eng)
    assert not (tmp_path / "out" / "decode").exists()


def _assert_same_run_on_two_workers(stage, a, b, m, ref, calls):
    """A stage run on the two-worker cluster against the in-process run: the same product
    bytes (``a``, ``b``: digests), the same metrics but for timings and the engine's record,
    progress from 0 to 2 cameras, one task per camera on a worker within its memory limit."""
    assert a == b, PRODUCTS_EQUAL
    assert _without_timings(m) == _without_timings(ref)
    assert calls[0] == (stage, 0, 2) and calls[-1] == (stage, 2, 2)
    eng = m["engine"]
    assert eng["kind"] == "local-cluster" and eng["workers"] == 2
    assert eng["memory_limit_mb"] == parse_memory(WORKER_LIMIT) / 2 ** 20
    # one task per camera (and the projection's blend, in tasks of texel chunks)
    cams = {"cam_left", "cam_right"}
    assert cams <= set(eng["tasks"])
    assert all(k.startswith("blend ") for k in set(eng["tasks"]) - cams)
    assert stage == "project" or set(eng["tasks"]) == cams
    for t in eng["tasks"].values():
        assert t["worker"].startswith("tcp://")
        assert t["peak_rss_mb"] < eng["memory_limit_mb"]
    assert "engine" not in ref  # the in-process metrics are as before


@pytest.mark.slow
def test_decode_two_workers_equals_in_process(tiny, tmp_path, cluster):
    """Every decode product is the same bytes in process and on two workers; the metrics are
    equal but for timings; each camera ran as its own task on a worker of the cluster."""
    from facegeo.pipeline.decode import run_decode

    ref = run_decode(tiny, tmp_path / "one")
    calls = []
    m = run_decode(tiny, tmp_path / "two", engine=cluster, progress=lambda *a: calls.append(a))
    a, b = file_digests(tmp_path / "one" / "decode"), file_digests(tmp_path / "two" / "decode")
    assert a.keys() == b.keys() and any(k.endswith("decode.npz") for k in a)
    _assert_same_run_on_two_workers("decode", a, b, m, ref, calls)


@pytest.mark.slow
def test_cluster_failure_raises_and_keeps_finished_work(tmp_path, cluster):
    done = tmp_path / "finished.txt"
    tasks = [Task("good", _write_then_return, (str(done),)),
             Task("bad", _fail_later, (1.0,))]
    with pytest.raises(ValueError, match="broken on purpose"):
        cluster.map("demo", tasks)
    assert done.read_text(encoding="utf-8") == "done"
    # the cluster is still usable, and results come back in task order
    out = cluster.map("demo", [Task(f"s{i}", _square, (i,)) for i in range(4)])
    assert [r["square"] for r in out] == [0, 1, 4, 9]


@pytest.mark.slow
def test_cluster_checks_results_on_the_worker(cluster):
    with pytest.raises(InputError, match="over the"):
        cluster.map("demo", [Task("big", _too_big, (MAX_RESULT_BYTES + 10,))])
    budget = cluster.task_budget()
    assert budget == int(parse_memory(WORKER_LIMIT) * cluster.memory_fraction) - WORKER_BASE_BYTES
    with pytest.raises(InputError, match="task 'huge' needs"):
        cluster.map("demo", [Task("huge", _square, (1,), working_set=budget + 1)])


@pytest.mark.slow
def test_a_camera_failing_on_a_worker_keeps_the_others(tiny, tmp_path, cluster):
    """cam_right's frame does not read on its worker: the stage fails with the reader's error,
    cam_left's finished decode waits in out/decode/.partial (written by its own worker); once
    the frame is back the next cluster run takes cam_left from there, byte-identical."""
    import shutil

    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.decode import run_decode

    shutil.copytree(tiny, tmp_path / "scan")
    scan = load_scan(tmp_path / "scan")  # validated while whole; the frame breaks later
    bad = tmp_path / "scan" / "structured_light" / "cam_right" / "gray_x_03.png"
    good = bad.read_bytes()
    bad.write_bytes(b"not a png")
    out = tmp_path / "out"
    with pytest.raises(Exception, match="gray_x_03"):  # the reader's own error, naming the file
        run_decode(scan, out, engine=cluster)
    record = out / "decode" / ".partial" / "cam_left" / "partial.json"
    assert record.is_file()
    kept = file_digests(record.parent)
    assert not (out / "decode" / ".partial" / "cam_right").exists()
    assert not (out / "decode" / "stage.json").exists()  # no finished stage
    bad.write_bytes(good)
    m = run_decode(scan, out, engine=cluster)
    assert m["cameras"]["cam_left"].get("reused") is True
    assert "reused" not in m["cameras"]["cam_right"]
    now = file_digests(out / "decode" / "cam_left")
    assert now == {k: v for k, v in kept.items() if k != "partial.json"}
    assert not (out / "decode" / ".partial").exists()  # gone with the stage's completion


@pytest.mark.slow
def test_scheduler_address_runs_the_same_path(tiny, tmp_path, cluster):
    """``--scheduler ADDRESS``: a client of a running scheduler (here the test cluster's) sees
    its workers and their memory limit, decodes the same bytes, and closing it leaves the
    cluster running."""
    from facegeo.pipeline.decode import run_decode

    address = cluster.cluster.scheduler_address
    with make_engine(scheduler=address) as eng:
        assert eng.kind == "scheduler" and eng.n_workers == 2
        assert eng.memory_limit == cluster.memory_limit
        run_decode(tiny, tmp_path / "sched", engine=eng)
    run_decode(tiny, tmp_path / "local", engine=cluster)  # still running
    assert file_digests(tmp_path / "sched" / "decode") == file_digests(tmp_path / "local" / "decode")
    from facegeo.pipeline.engine import DaskEngine

    with pytest.raises(InputError, match="cannot connect"):  # nothing listens on port 9
        DaskEngine.connect("tcp://127.0.0.1:9", timeout="2s")


# ------------------------------------------------------------------ the project stage


def test_project_memory_check_names_the_camera(tiny, tmp_path):
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.project import run_atlas, run_project

    scan = load_scan(tiny)
    run_atlas(scan, tmp_path / "out")
    eng = InProcessEngine(memory_limit=int((1 << 20) + WORKER_BASE_BYTES / MEMORY_FRACTION))
    assert 0 < eng.task_budget() < 2 << 20  # ≈ 0.8 MiB: below any camera's need
    with pytest.raises(InputError, match="project: task 'cam_left' needs"):
        run_project(scan, tmp_path / "out", engine=eng, evaluate=False)
    assert not (tmp_path / "out" / "project").exists()


def test_working_set_grows_with_what_the_task_holds():
    from types import SimpleNamespace

    from facegeo.pipeline.project import (
        PROJECT_BYTES_PER_PIXEL,
        PROJECT_BYTES_PER_TEXEL_LIGHT,
        project_working_set,
    )

    cam = SimpleNamespace(width=640, height=480)  # only the pixel count is read
    a = project_working_set(cam, 10_000, 5_000, 64)
    assert a - project_working_set(SimpleNamespace(width=320, height=480), 10_000, 5_000, 64) \
        == 320 * 480 * PROJECT_BYTES_PER_PIXEL
    assert project_working_set(cam, 10_000, 5_000, 128) - a == \
        10_000 * 64 * PROJECT_BYTES_PER_TEXEL_LIGHT
    assert project_working_set(cam, 10_000, 5_000, 64, shadow_taps=False) < a


@pytest.mark.slow
def test_project_two_workers_equals_in_process(tiny, tmp_path, cluster):
    """Every project product is the same bytes in process and on two workers; the metrics are
    equal but for timings; each camera ran as its own task on a worker."""
    from facegeo.pipeline.project import run_atlas, run_project

    run_atlas(tiny, tmp_path / "one")
    run_atlas(tiny, tmp_path / "two")
    ref = run_project(tiny, tmp_path / "one", evaluate=False)
    calls = []
    m = run_project(tiny, tmp_path / "two", engine=cluster, evaluate=False,
                    progress=lambda *a: calls.append(a))
    a, b = file_digests(tmp_path / "one" / "project"), file_digests(tmp_path / "two" / "project")
    assert a.keys() == b.keys() and "cam_left/R.npy" in a and "preview.png" in a
    _assert_same_run_on_two_workers("project", a, b, m, ref, calls)


def test_zarr_fields_end_to_end(tiny, tmp_path):
    """``field_format="zarr"`` through ``facegeo reconstruct --until project`` writes
    ``<camera>/R.zarr`` (no R.npy) holding the .npy run's values; the relight stage reads it."""
    import shutil

    from facegeo.pipeline.reconstruct import run_reconstruct
    from facegeo.pipeline.relight import relight_texture
    from facegeo.surface.reflectance import field_folders, open_field

    scans = {}
    for fmt in ("npy", "zarr"):
        shutil.copytree(tiny, tmp_path / fmt)
        run_reconstruct(tmp_path / fmt, until="project",
                        settings={"project": {"field_format": fmt}})
        scans[fmt] = tmp_path / fmt / "out"
    proj_z = scans["zarr"] / "project"
    cams = field_folders(proj_z)
    assert [c.name for c in cams] == ["cam_left", "cam_right"]
    for c in cams:
        assert (c / "R.zarr" / "zarr.json").is_file() and not (c / "R.npy").exists()
        a = np.asarray(open_field(scans["npy"] / "project" / c.name))
        b = np.asarray(open_field(c)[:])
        assert a.dtype == b.dtype == np.float16
        np.testing.assert_array_equal(a, b)  # the same float16 samples, NaN where masked
    L = a.shape[1]
    w = np.random.default_rng(3).uniform(0.0, 1.0, (L, 3)).astype(np.float32) / L
    relit = {}
    for fmt, out in scans.items():
        r, _, names = relight_texture(out, w)
        assert names == ["cam_left", "cam_right"]
        relit[fmt] = r
    ok = np.isfinite(relit["npy"])
    assert ok.any() and np.array_equal(ok, np.isfinite(relit["zarr"]))
    rel = np.abs(relit["zarr"][ok] - relit["npy"][ok]) / np.maximum(np.abs(relit["npy"][ok]),
                                                                    1e-12)
    assert rel.max() <= ZARR_RELIT_RTOL


def test_unknown_field_format_is_an_error(tiny, tmp_path):
    from facegeo.pipeline.project import run_atlas, run_project

    run_atlas(tiny, tmp_path / "out")
    with pytest.raises(InputError, match="field_format: expected one of npy, zarr"):
        run_project(tiny, tmp_path / "out", field_format="hdf5", evaluate=False)


# ------------------------------------------------------------------ decode through a store


def test_decode_through_a_store_reads_the_pushed_scan_and_writes_through_it(tiny, tmp_path,
                                                                           monkeypatch):
    """``run_decode(store=URL)`` after ``put_scan``: each task fetches only its camera's
    frames (and the rig, the ground truth it compares with) from ``URL/scan``, decodes from
    that copy, writes through ``URL/decode/run-…`` (removed after), and the stage's products
    are the folder run's bytes. Without a pushed scan the tasks read the scan folder."""
    import facegeo.pipeline.decode as dec
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline._scan_store import put_scan
    from facegeo.pipeline.decode import run_decode

    scan = load_scan(tiny)
    ref = run_decode(scan, tmp_path / "ref")
    store = tmp_path / "store"
    pushed = put_scan(scan, store)
    assert pushed["files"] == 1 + sum(1 for p in scan.input_files() if p.is_file())
    assert (store / "scan" / "scan.toml").is_file()
    roots = []
    real = dec._decode_camera_task
    monkeypatch.setattr(dec, "_decode_camera_task",
                        lambda s, *a: roots.append(Path(s.root)) or real(s, *a))
    m = run_decode(scan, tmp_path / "via", store=store)
    assert m["frames_from"] == "store"
    assert len(roots) == 2 and all(str(r).startswith(tempfile.gettempdir()) for r in roots)
    assert all(r != scan.root for r in roots)
    a, b = file_digests(tmp_path / "ref" / "decode"), file_digests(tmp_path / "via" / "decode")
    assert a == b and any(k.endswith("decode.npz") for k in a)
    assert _without_timings({**m, "frames_from": None}) == _without_timings(
        {**ref, "frames_from": None})
    assert not any((store / "decode").iterdir())  # the run's folder removed
    # only what a task reads is fetched: not the OLAT frames, not the calibration views
    from facegeo.pipeline._scan_store import sl_task_files

    files = sl_task_files(scan, "cam_left", scan.sl_frames)
    assert files and all("olat" not in f and "calib" not in f for f in files)
    assert "rig.json" in files
    roots.clear()
    m2 = run_decode(scan, tmp_path / "plain", store=tmp_path / "empty_store")
    assert m2["frames_from"] == "scan folder" and roots == [scan.root, scan.root]
    assert file_digests(tmp_path / "plain" / "decode") == a


@pytest.mark.slow
def test_decode_through_a_store_on_two_workers(tiny, tmp_path, cluster):
    """The same on the two-worker cluster: the products are the in-process run's bytes."""
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline._scan_store import put_scan
    from facegeo.pipeline.decode import run_decode

    scan = load_scan(tiny)
    ref = run_decode(scan, tmp_path / "ref")
    put_scan(scan, tmp_path / "store")
    m = run_decode(scan, tmp_path / "two", engine=cluster, store=tmp_path / "store")
    assert m["frames_from"] == "store" and set(m["engine"]["tasks"]) == {"cam_left", "cam_right"}
    assert file_digests(tmp_path / "ref" / "decode") == file_digests(tmp_path / "two" / "decode")
    assert _without_timings({**m, "frames_from": None}) == _without_timings(
        {**ref, "frames_from": None})


def test_a_file_missing_from_the_store_is_named(tiny, tmp_path):
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline._scan_store import fetch_scan_files, put_scan, scan_location

    scan = load_scan(tiny)
    put_scan(scan, tmp_path / "store")
    with pytest.raises(InputError, match=r"structured_light/nope\.png: the scan's file .* is "
                                         r"not in the store"):
        fetch_scan_files(scan, scan_location(tmp_path / "store"),
                         ["rig.json", "structured_light/nope.png"], tmp_path / "local")
