"""The render stage's view tasks without a shared disk (``--store``, issue 38), and an engine
for the standalone ``facegeo render``.

What is compared, stated with each assertion:

* products — every image and array file of the views' folder (``.exr``, ``.png``, ``.npy``):
  byte for byte (SHA-256) between the in-process stage without a store and the tasks through a
  store; the JSON files (the views' metrics and cameras) equal as parsed, without timings;
* no shared disk — the scan folder (and with it the stage folders under ``out/``) is moved
  away while the tasks run (:class:`_AwayEngine`): a task that read ``out`` or the scan instead
  of its fetched copy fails;
* the store — the run's folder ``render/run-<id>`` is gone once the stage ends.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

from conftest import timeless

#: Memory limit of each worker of the test cluster (a tiny scan's view task peaks at ≈ 140 MiB
#: over the interpreter; tests/test_scale_render.py).
WORKER_LIMIT = "800MiB"
#: Two novel orbits (the ``fitted`` fixture of tests/conftest.py fits them), supersampled
#: 2 × 2 (the stage's is 3 × 3: slower).
VIEWS = ("orbit:cam_left:30", "orbit:cam_left:-30")
SETTINGS = {"env": "sky", "supersample": 2}


@pytest.fixture(scope="module")
def in_process(fitted, tmp_path_factory):
    """The stage's views rendered in process without a store: ``(folder, metrics)``."""
    dest = tmp_path_factory.mktemp("render_in_process") / "views"
    return dest, _render(fitted, dest)


class _AwayEngine:
    """An engine whose tasks run while the scan folder ``root`` (its ``out/`` stage folders
    included) is moved away: what a task reads must come from the store."""

    def __init__(self, engine, root: Path):
        self._engine, self._root = engine, Path(root)
        self.moved = 0

    def __getattr__(self, name):
        return getattr(self._engine, name)

    def map(self, stage, tasks, progress=None):
        away = self._root.with_name(self._root.name + ".away")
        os.rename(self._root, away)
        try:
            self.moved += 1
            return self._engine.map(stage, tasks, progress=progress)
        finally:
            os.rename(away, self._root)


def _products(folder: Path, skip: str | None = None) -> dict:
    """Every file of ``folder`` (hidden ones included, those under ``skip`` by name only):
    SHA-256 of its bytes, or for a JSON file its parsed content without timings."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            name = str(p.relative_to(folder))
            if skip is not None and name.startswith(skip):
                out[name] = None
            elif p.suffix == ".json":
                out[name] = timeless(json.loads(p.read_text()))
            else:
                out[name] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _assert_same(got: dict, want: dict) -> None:
    assert got.keys() == want.keys(), sorted(set(got) ^ set(want))
    assert any(n.endswith(".exr") for n in want) and any(n.endswith("_weights.npy")
                                                         for n in want)
    for name in want:
        assert got[name] == want[name], name  # bytes (SHA-256), or JSON without timings


def _render(scan_root: Path, dest: Path, views=VIEWS, **kw) -> dict:
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.render import render_products

    return render_products(load_scan(scan_root), scan_root / "out", dest, views=list(views),
                           **SETTINGS, **kw)


def test_render_stage_through_a_memory_store_in_process(fitted, in_process, tmp_path):
    """In process with a ``memory://`` store the views run as tasks that read only their
    fetched copy (the scan folder is away while they run): every product the same bytes as
    the stage without a store, the λ and the relit captures from the client, the run's store
    folder removed."""
    import fsspec

    from facegeo.pipeline.engine import InProcessEngine

    folder, one = in_process
    store = f"memory://h2-render-{tmp_path.name}"
    engine = _AwayEngine(InProcessEngine(), fitted)
    two = _render(fitted, tmp_path / "two", engine=engine, store=store)
    assert engine.moved == 1
    _assert_same(_products(tmp_path / "two"), _products(folder))
    assert timeless(two["views"]) == timeless(one["views"])
    assert two["inputs_from"] == "store" and "inputs_from" not in one
    assert [v["seconds_source_images"] for v in two["views"].values()] == [0.0] * len(VIEWS)
    fs, path = fsspec.core.url_to_fs(store)
    assert not fs.exists(f"{path}/render") or fs.ls(f"{path}/render") == []


def test_render_stage_through_a_folder_store_on_two_workers(fitted, in_process, tmp_path,
                                                            cluster):
    """On a two-worker cluster with a folder as the store, the scan folder away while the
    tasks run: the same bytes as the in-process stage without a store; each view ran on a
    worker; no run folder left in the store, no task folder in the stage's."""
    from facegeo.pipeline.render import VIEW_TASKS_DIR

    folder, one = in_process
    engine = _AwayEngine(cluster, fitted)
    two = _render(fitted, tmp_path / "two", engine=engine, store=tmp_path / "store")
    assert engine.moved == 1
    _assert_same(_products(tmp_path / "two"), _products(folder))
    assert timeless(two["views"]) == timeless(one["views"])
    assert two["inputs_from"] == "store"
    eng = two["engine"]
    assert eng["kind"] == "local-cluster" and len(eng["tasks"]) == len(VIEWS)
    assert all(t["worker"].startswith("tcp://") for t in eng["tasks"].values())
    assert list((tmp_path / "store" / "render").iterdir()) == []
    assert not (tmp_path / "two" / VIEW_TASKS_DIR).exists()


def test_standalone_render_on_two_workers_equals_in_process(fitted, tmp_path, cluster,
                                                             monkeypatch):
    """``run_render`` on a cluster: the view one task on a worker, every file of ``views/``
    the same bytes as in process (the relit captures' cache file under the same name), the
    returned figures equal without timings. The client's code fingerprint differs from the
    workers' (as after an edit of facegeo's code while the cluster runs): the task still uses
    the client's captures — it relights nothing and writes no cache file of its own."""
    import facegeo.pipeline.cache as C
    from facegeo.pipeline.render import SOURCE_IMAGES_DIR, run_render

    monkeypatch.setattr(C, "code_fingerprint", lambda: "the client's code")

    outs = []
    for k in range(2):
        out = tmp_path / f"out{k}"
        for part in ("atlas", "project", "fit"):
            shutil.copytree(fitted / "out" / part, out / part)
        outs.append(out)
    kw = dict(camera_spec=VIEWS[0], **SETTINGS)
    one = run_render(fitted, outs[0], **kw)
    two = run_render(fitted, outs[1], engine=cluster, **kw)
    _assert_same(_products(outs[1] / "views", skip=SOURCE_IMAGES_DIR),
                 _products(outs[0] / "views", skip=SOURCE_IMAGES_DIR))
    assert sum(n.startswith(SOURCE_IMAGES_DIR) for n in _products(outs[0] / "views")) == 1
    assert two["seconds_source_images"] == 0.0 < one["seconds_source_images"]
    assert two["engine"]["kind"] == "local-cluster" and len(two["engine"]["tasks"]) == 1
    assert two["inputs_from"] == "stage folder"
    assert two["psnr_db"] == one["psnr_db"] and two["name"] == one["name"]
    assert timeless({k: v for k, v in two.items() if k not in ("engine", "inputs_from")}) \
        == timeless({k: v for k, v in one.items() if k != "stats"})


def test_render_command_runs_the_view_on_the_engine_of_its_options(fitted, monkeypatch):
    """``facegeo render --memory-limit SIZE`` hands ``run_render`` the engine of its options
    (in process, with that budget) — the one engine the stages up to the fit ran on, not a
    second; ``--workers`` and ``--scheduler`` exclude each other."""
    import facegeo.cli as cli
    import facegeo.pipeline.render as PR

    got, stages = {}, {}

    def fake_render(scan, **kw):
        got.update(kw)
        return {"name": "v", "files": {"png": "v.png"}}

    monkeypatch.setattr(cli, "_run_reconstruct", lambda *a, **k: stages.update(k) or [])
    monkeypatch.setattr(PR, "run_render", fake_render)
    assert cli.main(["render", str(fitted), "--camera", VIEWS[0], "--memory-limit", "1GiB",
                     "-q"]) == 0
    assert got["engine"].kind == "in-process" and got["engine"].memory_limit == 1 << 30
    assert stages["until"] == "fit" and stages["engine"] is got["engine"]
    with pytest.raises(SystemExit):
        cli.main(["render", str(fitted), "--camera", VIEWS[0], "--workers", "2",
                  "--scheduler", "tcp://localhost:1"])


def test_reconstruct_passes_its_store_to_the_render_stage(fitted, tmp_path, monkeypatch):
    """``facegeo reconstruct --store URL``: the ``render`` stage's ``render_products`` and the
    ``relight`` stage's ``relight_products`` are given the store, the ``project`` stage's
    ``project_products`` the run's ``lights_per_task`` (none of them a setting: the products
    are the same bytes)."""
    import facegeo.pipeline.project as PP
    import facegeo.pipeline.relight as PL
    import facegeo.pipeline.render as PR
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.cache import StageContext
    from facegeo.pipeline.reconstruct import reconstruct_pipeline

    got: dict = {}

    def fake(name, ret):
        return lambda *a, **kw: got.setdefault(name, kw) and ret

    monkeypatch.setattr(PR, "render_products", fake("render", {}))
    monkeypatch.setattr(PL, "relight_products", fake("relight", ({}, {})))
    monkeypatch.setattr(PP, "project_products", fake("project", ({}, {})))
    pipeline = reconstruct_pipeline(load_scan(fitted), store="memory://h2-wired",
                                    lights_per_task=64)
    up = {s: fitted / "out" / s for s in ("atlas", "project", "mesh")}
    for name in ("render", "relight", "project"):
        spec = next(s for s in pipeline.stages if s.name == name)
        assert "lights_per_task" not in spec.settings
        if name != "project":
            assert "store" not in spec.settings
        spec.run(StageContext(fitted, tmp_path / name, dict(spec.settings), up))
    assert got["render"]["store"] == got["relight"]["store"] == "memory://h2-wired"
    assert got["project"]["lights_per_task"] == 64
