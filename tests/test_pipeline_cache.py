"""Stage caching: a stage reruns only when its inputs, settings, upstream or version change;
interrupted runs leave earlier products intact and resume."""

from __future__ import annotations

import json

import pytest

from facegeo.errors import InputError
from facegeo.pipeline import cache
from facegeo.pipeline.cache import MANIFEST_NAME, Pipeline, StageSpec


def _toy_pipeline(calls: list[str], *, fail_in: str | None = None) -> Pipeline:
    """a: reads scan file 'data.txt' and doubles numbers; b: sums a's output times a setting."""

    def run_a(ctx):
        calls.append("a")
        nums = [int(x) for x in (ctx.scan_dir / "data.txt").read_text().split()]
        (ctx.out_dir / "doubled.txt").write_text(" ".join(str(2 * n) for n in nums))
        if fail_in == "a":
            raise RuntimeError("boom in a")
        return {"count": len(nums)}

    def run_b(ctx):
        calls.append("b")
        nums = [int(x) for x in (ctx.upstream["a"] / "doubled.txt").read_text().split()]
        if fail_in == "b":
            (ctx.out_dir / "half-written.txt").write_text("x")
            raise RuntimeError("boom in b")
        total = sum(nums) * ctx.settings["scale"]
        (ctx.out_dir / "total.txt").write_text(str(total))
        return {"total": total}

    return Pipeline([
        StageSpec("a", run_a, inputs=lambda d: [d / "data.txt"]),
        StageSpec("b", run_b, after=("a",), settings={"scale": 1}),
    ])


@pytest.fixture
def scan(tmp_path):
    d = tmp_path / "scan"
    d.mkdir()
    (d / "data.txt").write_text("1 2 3")
    return d


def _partials(scan):
    return [p.name for p in (scan / "out").iterdir() if ".facegeo-tmp-" in p.name or ".facegeo-old-" in p.name]


def test_second_run_does_no_work(scan):
    calls: list[str] = []
    res = _toy_pipeline(calls).run(scan)
    assert calls == ["a", "b"] and [r.ran for r in res] == [True, True]
    assert (scan / "out" / "b" / "total.txt").read_text() == "12"
    calls.clear()
    res = _toy_pipeline(calls).run(scan)
    assert calls == [] and [r.ran for r in res] == [False, False]
    assert res[1].metrics["total"] == 12
    metrics = json.loads((scan / "out" / "metrics.json").read_text())
    assert metrics["a"]["count"] == 3 and metrics["b"]["total"] == 12


def test_setting_change_reruns_that_stage_only(scan):
    calls: list[str] = []
    _toy_pipeline(calls).run(scan)
    calls.clear()
    _toy_pipeline(calls).run(scan, settings={"b": {"scale": 10}})
    assert calls == ["b"]
    assert (scan / "out" / "b" / "total.txt").read_text() == "120"


def test_input_change_reruns_stage_and_those_after(scan):
    calls: list[str] = []
    _toy_pipeline(calls).run(scan)
    calls.clear()
    (scan / "data.txt").write_text("1 2 3 4")
    _toy_pipeline(calls).run(scan)
    assert calls == ["a", "b"]
    assert (scan / "out" / "b" / "total.txt").read_text() == "20"


def test_same_content_rewritten_is_still_cached(scan):
    calls: list[str] = []
    _toy_pipeline(calls).run(scan)
    calls.clear()
    (scan / "data.txt").write_text("1 2 3")  # new mtime, same bytes
    _toy_pipeline(calls).run(scan)
    assert calls == []


def test_version_change_reruns(scan, monkeypatch):
    calls: list[str] = []
    _toy_pipeline(calls).run(scan)
    calls.clear()
    monkeypatch.setattr(cache, "__version__", "99.0")
    _toy_pipeline(calls).run(scan)
    assert calls == ["a", "b"]


def test_interrupted_stage_keeps_earlier_products_and_resumes(scan):
    calls: list[str] = []
    _toy_pipeline(calls).run(scan)
    before_b = (scan / "out" / "b" / "total.txt").read_text()
    (scan / "data.txt").write_text("5 5")
    calls.clear()
    with pytest.raises(RuntimeError, match="boom in b"):
        _toy_pipeline(calls, fail_in="b").run(scan)
    assert calls == ["a", "b"]
    # a's new products landed; b's old products are intact; no partial folder left
    assert (scan / "out" / "a" / "doubled.txt").read_text() == "10 10"
    assert (scan / "out" / "b" / "total.txt").read_text() == before_b
    assert not (scan / "out" / "b" / "half-written.txt").exists()
    assert _partials(scan) == []
    # metrics.json keeps b's previous figures (its products are still those) and says it failed
    import json

    b = json.loads((scan / "out" / "metrics.json").read_text())["b"]
    assert b["total"] == int(before_b) and b["last_run_failed"] == "RuntimeError: boom in b"
    calls.clear()
    _toy_pipeline(calls).run(scan)
    assert calls == ["b"]  # resumes: a is current
    assert (scan / "out" / "b" / "total.txt").read_text() == "20"
    b = json.loads((scan / "out" / "metrics.json").read_text())["b"]
    assert "last_run_failed" not in b  # the successful run replaced the entry


def test_killed_run_leftovers_are_cleaned(scan):
    calls: list[str] = []
    _toy_pipeline(calls).run(scan)
    stale = scan / "out" / ".b.facegeo-tmp-999999999-abc"  # a pid that is not running
    stale.mkdir()
    (stale / "junk").write_text("x")
    user_file = scan / "out" / "my-notes.txt"
    user_file.write_text("keep me")
    _toy_pipeline(calls).run(scan)
    assert not stale.exists()
    assert user_file.read_text() == "keep me"


def test_corrupt_manifest_reruns(scan):
    calls: list[str] = []
    _toy_pipeline(calls).run(scan)
    (scan / "out" / "a" / MANIFEST_NAME).write_text("{not json")
    calls.clear()
    _toy_pipeline(calls).run(scan)
    assert calls == ["a"]  # b's key depends only on a's key, which is unchanged


def test_products_of_a_standalone_command_are_rebuilt_with_a_warning(scan, caplog):
    """A stage folder whose manifest has no key (``facegeo atlas`` / ``project`` write their
    own) cannot be trusted by the cache: rebuilt, and the log says so — not silently."""
    import json
    import logging

    calls: list[str] = []
    (scan / "out" / "a").mkdir(parents=True)
    (scan / "out" / "a" / MANIFEST_NAME).write_text(json.dumps(
        {"stage": "a", "settings": {"texels_per_mm": 2.0}, "metrics": {}}))
    with caplog.at_level(logging.WARNING, logger="facegeo.pipeline.cache"):
        _toy_pipeline(calls).run(scan)
    assert calls == ["a", "b"]
    assert "outside the stage cache" in caplog.text and "texels_per_mm" in caplog.text


def test_from_and_only(scan):
    calls: list[str] = []
    p = _toy_pipeline(calls)
    p.run(scan)
    calls.clear()
    p.run(scan, from_stage="a")
    assert calls == ["a", "b"]
    calls.clear()
    p.run(scan, only="b")
    assert calls == ["b"]
    with pytest.raises(InputError, match="unknown stage"):
        p.run(scan, only="c")


def test_only_needs_current_upstream(tmp_path):
    d = tmp_path / "fresh"
    d.mkdir()
    (d / "data.txt").write_text("1")
    with pytest.raises(InputError, match="input stage 'a' has no current products"):
        _toy_pipeline([]).run(d, only="b")


def test_bad_definitions_and_settings(scan):
    def run(ctx):
        return {}

    with pytest.raises(InputError, match="do not come before"):
        Pipeline([StageSpec("b", run, after=("a",)), StageSpec("a", run)])
    with pytest.raises(InputError, match="listed twice"):
        Pipeline([StageSpec("a", run), StageSpec("a", run)])
    with pytest.raises(InputError, match="JSON-serialisable"):
        Pipeline([StageSpec("a", run, settings={"x": object()})]).run(scan)
    with pytest.raises(InputError, match="unknown stages"):
        Pipeline([StageSpec("a", run)]).run(scan, settings={"zz": {}})
    with pytest.raises(InputError, match="does not exist"):
        Pipeline([StageSpec("a", run, inputs=lambda d: [d / "missing.bin"])]).run(scan)


def test_a_lost_or_corrupt_metrics_file_is_whole_again_after_a_cached_run(scan, caplog):
    """Cached stages put their manifest's metrics back into metrics.json (a deleted file made
    'facegeo report' fail until every stage reran; a corrupt one was silently replaced by the
    stages that reran alone)."""
    import json
    import logging

    calls: list[str] = []
    _toy_pipeline(calls).run(scan)
    path = scan / "out" / "metrics.json"
    want = json.loads(path.read_text())
    path.unlink()
    calls.clear()
    _toy_pipeline(calls).run(scan)
    assert calls == [] and json.loads(path.read_text()) == want
    path.write_text("{not json")
    with caplog.at_level(logging.WARNING, logger="facegeo.pipeline.cache"):
        _toy_pipeline(calls).run(scan)
    assert "unreadable" in caplog.text and json.loads(path.read_text()) == want


def test_stage_settings_are_checked_before_any_stage_runs(scan):
    """A misspelt setting, or a stage's settings that are not a mapping, is an InputError
    before anything runs (it was a TypeError inside the stage, after the stages before it)."""
    calls: list[str] = []
    with pytest.raises(InputError, match=r"settings\['b'\]: unknown \['scal'\]; the stage's "
                                         r"settings are scale"):
        _toy_pipeline(calls).run(scan, settings={"b": {"scal": 2}})
    with pytest.raises(InputError, match=r"settings\['b'\]: expected a mapping"):
        _toy_pipeline(calls).run(scan, settings={"b": "x"})
    assert calls == []
