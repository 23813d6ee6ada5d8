"""The render stage's views as engine tasks (issue 38): one task a view on a cluster.

What is compared, stated with each assertion:

* products — every image and array file of the stage's folder (``.exr``, ``.png``, ``.npy``):
  byte for byte (SHA-256) between the in-process stage and the one on a two-worker
  ``LocalCluster``; the JSON files (the views' metrics and cameras) equal as parsed, the keys
  naming ``seconds`` (timings) left out;
* metrics — the stage's per-view metrics equal except the timings, the views in the same order;
* failure — an error in a view's task reaches the client as the class (and message) the
  in-process stage raises, and the tasks' folder is not left behind;
* memory — a view's working set against a worker's budget, checked before any task runs.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from conftest import timeless

from facegeo.errors import InputError

#: Memory limit of each worker of the test cluster (as tests/test_scale_stages.py; a tiny
#: scan's view task peaks at ≈ 140 MiB over the interpreter).
WORKER_LIMIT = "800MiB"
#: The views of the stage under test (the ``fitted`` fixture of tests/conftest.py fits them):
#: novel orbits of the front camera, supersampled as the ``render`` stage of ``facegeo
#: reconstruct`` is (2 × 2 here: faster).
VIEWS = ("orbit:cam_left:30", "orbit:cam_left:-30", "orbit:cam_left:60")
SETTINGS = {"env": "sky", "supersample": 2}


def _products(folder: Path) -> dict:
    """Every file of ``folder`` (hidden ones included): SHA-256 of its bytes, or for a JSON
    file its parsed content without timings."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            name = str(p.relative_to(folder))
            out[name] = (timeless(json.loads(p.read_text())) if p.suffix == ".json"
                         else hashlib.sha256(p.read_bytes()).hexdigest())
    return out


def _render(scan_root: Path, dest: Path, engine=None) -> dict:
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.render import render_products

    return render_products(load_scan(scan_root), scan_root / "out", dest, views=list(VIEWS),
                           engine=engine, **SETTINGS)


def test_render_views_on_two_workers_equal_in_process(fitted, tmp_path, cluster):
    """Each view one task on a two-worker cluster: every image and array the same bytes as
    the in-process stage's, every JSON equal without timings, the metrics equal except
    timings; each view ran as a task on a worker of the cluster within its memory limit."""
    one = _render(fitted, tmp_path / "one")
    two = _render(fitted, tmp_path / "two", cluster)
    got, want = _products(tmp_path / "two"), _products(tmp_path / "one")
    assert got.keys() == want.keys(), sorted(set(got) ^ set(want))
    assert any(n.endswith(".exr") for n in want) and any(n.endswith("_weights.npy")
                                                         for n in want)
    for name in want:
        assert got[name] == want[name], name  # bytes (SHA-256), or JSON without timings
    assert list(two["views"]) == list(one["views"]) == [
        f"cam_left_orbit{d}_sky" for d in ("30", "-30", "60")]
    assert timeless(two["views"]) == timeless(one["views"])
    assert two["env"] == one["env"] and "engine" not in one
    eng = two["engine"]
    assert eng["kind"] == "local-cluster" and len(eng["tasks"]) == len(VIEWS)
    for t in eng["tasks"].values():
        assert t["worker"].startswith("tcp://") and t["peak_rss_mb"] < eng["memory_limit_mb"]
    # the cross-validated λ came from the client, not from a task's own computation
    assert all(v["shrinkage_factors"] == one["views"][n]["shrinkage_factors"]
               for n, v in two["views"].items())
    # the source captures were relit once, on the client: every task read them (0: reused)
    assert [v["seconds_source_images"] for v in two["views"].values()] == [0.0] * len(VIEWS)
    assert "seconds_source_images" in two and "seconds_source_images" not in one


def test_render_progress_counts_views_on_a_cluster(fitted, tmp_path, cluster):
    """On a cluster the stage's progress counts views as their tasks finish."""
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.render import render_products

    calls = []
    render_products(load_scan(fitted), fitted / "out", tmp_path / "v", views=list(VIEWS[:2]),
                    engine=cluster, progress=lambda *a: calls.append(a), env="uniform",
                    resynthesis=False, baseline=False)
    assert calls[0] == ("render", 0, 2) and calls[-1] == ("render", 2, 2)
    assert len(calls) == 3


def test_a_failing_view_task_raises_the_in_process_error_class(fitted, tmp_path, cluster):
    """A light step of 0, which only the view's render checks (without a cross-validated λ or
    image detail the client computes nothing with it), fails each view's task on its worker;
    the client raises the class the in-process stage raises, and no task folder is left."""
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.render import VIEW_TASKS_DIR, render_products

    bad = dict(env="sky", shrinkage="none", image_detail=False, light_step=0)
    scan = load_scan(fitted)
    with pytest.raises(InputError, match="light_step") as in_process:
        render_products(scan, fitted / "out", tmp_path / "one", views=list(VIEWS), **bad)
    with pytest.raises(Exception) as on_cluster:
        render_products(scan, fitted / "out", tmp_path / "two", views=list(VIEWS),
                        engine=cluster, **bad)
    assert type(on_cluster.value) is type(in_process.value)
    assert str(on_cluster.value) == str(in_process.value)
    # raised in the view's task on a worker, not by the client
    assert "render_view_task" in {e.name for e in on_cluster.traceback}
    assert not (tmp_path / "two" / VIEW_TASKS_DIR).exists()


def test_render_working_set_and_the_memory_check(fitted, tmp_path, cluster, monkeypatch):
    """A view's working set is the stated sum; a view that cannot fit a worker stops the
    stage before any task runs, naming the task."""
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline import render as PR
    from facegeo.render import load_sources
    from facegeo.render.novel import CHUNK_SAMPLES, SHADOW_MAX_LIGHTS

    class Cam:
        width, height = 7, 5

    sources = load_sources(fitted / "out" / "project", fitted / "out" / "fit")
    need = PR.render_working_set(Cam, 2, sources, 1000, 300, detail_pixels=11)
    rows = sum(min(a.shape[0], PR.RENDER_TAPS_PER_SAMPLE * 140) * a[0].nbytes
               for s in sources for a in (s.field, s.fit.D))
    # 7 × 5 px at s = 2: 140 samples, under the fields' rows (the cap at 4 taps a sample)
    assert rows < sum(a.nbytes for s in sources for a in (s.field, s.fit.D))
    assert need == (PR.RENDER_BASE_BYTES + 140 * PR.RENDER_BYTES_PER_SAMPLE
                    + 1000 * PR.RENDER_BYTES_PER_TEXEL + 300 * PR.RENDER_BYTES_PER_FACE
                    + CHUNK_SAMPLES * PR.RENDER_BYTES_PER_CHUNK_SAMPLE + rows
                    + 11 * PR.RENDER_BYTES_PER_SOURCE_PIXEL * (1 + SHADOW_MAX_LIGHTS))
    monkeypatch.setattr(PR, "RENDER_BYTES_PER_SAMPLE", 1 << 40)
    with pytest.raises(InputError, match=r"render: task '000 orbit:cam_left:30 sky' needs"):
        PR.render_products(load_scan(fitted), fitted / "out", tmp_path / "v",
                           views=list(VIEWS), engine=cluster, **SETTINGS)
    assert not (tmp_path / "v").exists()
