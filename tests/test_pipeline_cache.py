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


def test_code_change_reruns_and_says_why(scan, monkeypatch):
    """A change of facegeo's code without a version bump (the code fingerprint) reruns every
    stage, records the fingerprint in the manifest and names the reason; the same fingerprint
    keeps the products."""
    monkeypatch.setattr(cache, "code_fingerprint", lambda: "code-1")
    calls: list[str] = []
    _toy_pipeline(calls).run(scan)
    manifest = json.loads((scan / "out" / "a" / MANIFEST_NAME).read_text())
    assert manifest["facegeo_code"] == "code-1"
    calls.clear()
    res = _toy_pipeline(calls).run(scan)
    assert calls == [] and [r.reason for r in res] == [None, None]
    monkeypatch.setattr(cache, "code_fingerprint", lambda: "code-2")
    res = _toy_pipeline(calls).run(scan)
    assert calls == ["a", "b"]
    assert res[0].reason == "facegeo code changed"
    assert res[1].reason.startswith("facegeo code changed")  # and its upstream a's key
    assert json.loads((scan / "out" / "a" / MANIFEST_NAME).read_text())["reason"] == \
        "facegeo code changed"


def test_products_from_before_code_fingerprints_are_recomputed_once(scan):
    """A manifest written before the fingerprint was part of the key (no ``facegeo_code``)
    is not a crash: the stage reruns once, saying so, and is cached after."""
    calls: list[str] = []
    _toy_pipeline(calls).run(scan)
    for stage in ("a", "b"):  # as an older facegeo wrote it: another key, no fingerprint
        path = scan / "out" / stage / MANIFEST_NAME
        m = json.loads(path.read_text())
        del m["facegeo_code"]
        m["key"] = "0" * 64
        path.write_text(json.dumps(m))
    calls.clear()
    res = _toy_pipeline(calls).run(scan)
    assert calls == ["a", "b"]
    assert "facegeo code changed" in res[0].reason and "predate" in res[0].reason
    calls.clear()
    _toy_pipeline(calls).run(scan)
    assert calls == []


def test_rerun_reasons_name_what_changed(scan):
    calls: list[str] = []
    res = _toy_pipeline(calls).run(scan)
    assert [r.reason for r in res] == ["no finished products yet"] * 2
    res = _toy_pipeline(calls).run(scan, settings={"b": {"scale": 3}})
    assert res[1].reason == "settings changed: scale"
    (scan / "data.txt").write_text("7")
    res = _toy_pipeline(calls).run(scan, settings={"b": {"scale": 3}})
    assert res[0].reason == "input files changed: data.txt"
    assert res[1].reason == "upstream stage a changed"
    res = _toy_pipeline(calls).run(scan, settings={"b": {"scale": 3}}, from_stage="a")
    assert [r.reason for r in res] == ["forced by --from a"] * 2


def test_code_fingerprint_hashes_the_package_sources_only(tmp_path, monkeypatch):
    """The fingerprint reads the ``.py`` files where the imported package is (an installed
    copy as well as a checkout), in path order; byte-code, numba caches and hidden files do
    not change it, an edit, a rename or a new source file does."""
    import facegeo

    pkg = tmp_path / "site-packages" / "facegeo"
    (pkg / "sub" / "__pycache__").mkdir(parents=True)
    (pkg / "__init__.py").write_text("__version__ = '1'\n")
    (pkg / "sub" / "mod.py").write_text("x = 1\n")
    fingerprint = cache._source_fingerprint.__wrapped__  # not memoised: each call reads

    first = fingerprint(pkg)
    assert len(first) == 64
    monkeypatch.setattr(facegeo, "__file__", str(pkg / "__init__.py"))  # installed elsewhere
    assert cache.code_fingerprint() == first
    monkeypatch.undo()
    assert cache.code_fingerprint() != first  # this checkout again
    (pkg / "sub" / "__pycache__" / "mod.cpython-312.pyc").write_bytes(b"\0" * 10)
    (pkg / "sub" / "__pycache__" / "mod.f-1.py312.nbi").write_bytes(b"\0" * 10)
    (pkg / "sub" / "__pycache__" / "stray.py").write_text("y = 2\n")
    (pkg / "sub" / ".#mod.py").write_text("lock\n")
    (pkg / "notes.txt").write_text("not code\n")
    assert fingerprint(pkg) == first
    (pkg / "sub" / "mod.py").write_text("x = 2\n")
    assert fingerprint(pkg) != first
    (pkg / "sub" / "mod.py").write_text("x = 1\n")
    assert fingerprint(pkg) == first
    (pkg / "sub" / "mod.py").rename(pkg / "sub" / "other.py")  # same bytes, another file
    assert fingerprint(pkg) != first
    (pkg / "sub" / "other.py").rename(pkg / "sub" / "mod.py")
    # code that runs in no stage (the command line, benchmarks, the report page) is left out
    (pkg / "pipeline").mkdir()
    (pkg / "bench").mkdir()
    for rel in ("cli.py", "pipeline/report.py", "bench/x.py"):
        (pkg / rel).write_text("edited = True\n")
    assert fingerprint(pkg) == first
    (pkg / "pipeline" / "mesh.py").write_text("")  # stage code is not
    assert fingerprint(pkg) != first
    (pkg / "pipeline" / "mesh.py").unlink()
    (pkg / "new.py").write_text("")
    assert fingerprint(pkg) != first
    monkeypatch.setenv(cache.CODE_KEY_ENV, "ignore")  # a developer's opt-out
    assert cache.code_fingerprint() == "ignored"


def test_code_fingerprint_is_computed_once_per_process(tmp_path, monkeypatch):
    import facegeo

    pkg = tmp_path / "facegeo"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    reads = []
    real = cache.Path.read_bytes
    monkeypatch.setattr(cache.Path, "read_bytes", lambda self: reads.append(self) or real(self))
    monkeypatch.setattr(facegeo, "__file__", str(pkg / "__init__.py"))
    first = cache.code_fingerprint()
    assert reads == [pkg / "__init__.py"]
    assert cache.code_fingerprint() == first and len(reads) == 1


def test_stages_made_from_replaced_upstream_products_are_marked_stale(scan):
    """After an upstream stage runs again on its own (``facegeo mesh`` after a full
    reconstruct), the downstream products on disk were made from its previous products: they
    are stale (the summary table says so, the figures stay) until they run again, and a run of
    the whole chain clears it."""
    from facegeo.pipeline.cache import stale_stages
    from facegeo.pipeline.report import summary_table

    calls: list[str] = []
    _toy_pipeline(calls).run(scan)
    out = scan / "out"
    assert stale_stages(out) == {}
    (scan / "data.txt").write_text("1 2 3 4")
    _toy_pipeline(calls).run(scan, only="a")  # a again, b left as it was
    assert calls == ["a", "b", "a"]
    assert stale_stages(out) == {"b": ["a"]}
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["b"]["total"] == 12  # the figures of the products on disk
    assert "b" in summary_table(doc, stale_stages(out)).split("[stale: made from an older a]")[0]
    assert "[stale" not in summary_table(doc)
    _toy_pipeline(calls).run(scan)  # b reruns
    assert stale_stages(out) == {}


def test_staleness_reaches_every_stage_made_from_replaced_products(tmp_path):
    """a → b → c: when a runs again alone, c (made from b, made from the old a) is as stale
    as b, and both name the stage that ran again."""
    from facegeo.pipeline.cache import stale_stages

    out = tmp_path / "out"
    for name, key, up in (("a", "a2", None), ("b", "b1", {"a": "a1"}), ("c", "c1", {"b": "b1"})):
        (out / name).mkdir(parents=True)
        doc = {"key": key} | ({"upstream": up} if up else {})
        (out / name / "stage.json").write_text(json.dumps(doc))
    (out / "metrics.json").write_text(json.dumps({"a": {}, "b": {}, "c": {}}))
    assert stale_stages(out) == {"b": ["a"], "c": ["a"]}
    (out / "b" / "stage.json").write_text(json.dumps({"key": "b2", "upstream": {"a": "a2"}}))
    assert stale_stages(out) == {"c": ["b"]}


def test_paths_a_stage_records_point_where_its_folder_ends_up(scan):
    """A stage writes into a staging folder and records the files it wrote there; the metrics
    (returned, in its manifest and in out/metrics.json) name them in out/<stage>/, which
    exists after the run (relight's ``files`` pointed into the deleted staging folder)."""
    def run(ctx):
        p = ctx.out_dir / "img.png"
        p.write_text("x")
        return {"files": {"png": str(p), "list": [p, str(ctx.out_dir)]}, "other": "img.png"}

    (res,) = Pipeline([StageSpec("a", run)]).run(scan)
    final = scan / "out" / "a"
    assert res.metrics["files"] == {"png": str(final / "img.png"),
                                    "list": [str(final / "img.png"), str(final)]}
    assert res.metrics["other"] == "img.png"
    manifest = json.loads((final / MANIFEST_NAME).read_text())
    assert manifest["metrics"]["files"]["png"] == str(final / "img.png")
    doc = json.loads((scan / "out" / "metrics.json").read_text())
    assert doc["a"]["files"]["png"] == str(final / "img.png")
    assert (final / "img.png").is_file()


def test_a_stages_own_time_breakdown_is_kept_beside_its_wall_time(scan):
    """``seconds`` is the stage's wall time, a float, for every stage; a stage that records
    its own breakdown there (relight: env, weights, relight, total) keeps it as
    ``seconds_parts`` (the cache used to overwrite it)."""
    parts = {"env": 0.25, "relight": 0.5, "total": 0.75}

    def run_c(ctx):
        (ctx.out_dir / "c.txt").write_text("c")
        return {"seconds": dict(parts)}

    Pipeline([StageSpec("c", run_c)]).run(scan)
    metrics = json.loads((scan / "out" / "c" / MANIFEST_NAME).read_text())["metrics"]
    assert isinstance(metrics["seconds"], float) and metrics["seconds_parts"] == parts
