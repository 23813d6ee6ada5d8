"""The benchmark registry, its reports, and every registered benchmark run in its quick form.

No timing asserts: the benchmarks run to check that their rows are well-formed (positive speed,
finite errors, thread counts and named baselines) and that the report renders.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from facegeo.errors import InputError, ShapeError
from facegeo import bench
from facegeo.bench import (
    PURE_READ,
    READ_ROW,
    Bandwidth,
    BenchRow,
    pure_read,
    read_bandwidth,
    register,
    registered,
    render_table,
    run_benchmarks,
    write_reports,
)

# Benchmarks whose quick form takes more than a few seconds here (measured: spectral ≈ 24 s,
# synth ≈ 27 s, mesh.full_resolution ≈ 16 s — two subprocesses — on the shared 2-core machine).
_SLOW = {"spectral.forward", "spectral.inverse", "synth.generate", "surface.project",
         "surface.resolution", "relight.compress", "mesh.full_resolution",
         "mesh.real_bust", "photometric.real", "scale.decode", "scale.project"}


@pytest.fixture(autouse=True)
def _small_bandwidth_array(monkeypatch):
    """64 MiB instead of 512 MiB for the bandwidth figure, and one timed run of anything
    (``bench.MAX_REPEAT``): these tests check form, not speed."""
    monkeypatch.setattr(bench, "BANDWIDTH_BYTES", 64 << 20)
    monkeypatch.setattr(bench, "MAX_REPEAT", 1)


def _cells(line: str) -> int:
    """Number of Markdown table cells in ``line`` (``\\|`` is an escaped pipe, not a border)."""
    return line.replace("\\|", "").count("|") - 1


def test_every_stage_registers_benchmarks():
    names = registered()
    for expected in ("visibility.closest_hit", "visibility.occluded", "synth.generate",
                     "structured_light.decode_gray", "memory.read_bandwidth"):
        assert expected in names


def test_unknown_benchmark_lists_available():
    with pytest.raises(InputError, match="available: .*visibility.closest_hit"):
        run_benchmarks(["no.such.bench"])


def test_names_select_by_prefix_of_the_whole_name():
    """A name selects every benchmark it starts (``facegeo bench --help``: "names, or the start
    of names"), also inside a dotted part — except a whole registered name, which selects
    itself alone; one that selects nothing lists every name."""
    from facegeo.bench import select_benchmarks

    names = registered()
    vis = [n for n in names if n.startswith("visibility.")]
    assert vis == ["visibility.closest_hit", "visibility.occluded"]
    assert select_benchmarks(["visibility.closest"]) == ["visibility.closest_hit"]
    assert select_benchmarks(["vis"]) == vis
    assert select_benchmarks(["visibility"]) == vis
    assert select_benchmarks(["visibility.occluded"]) == ["visibility.occluded"]
    # in registry order, each once; "surface.visibility" is not under "vis"
    assert select_benchmarks(["visibility.occ", "vis", "spectral.f"]) == \
        ["spectral.forward"] + vis
    assert select_benchmarks([]) == select_benchmarks(None) == names
    # a whole name selects itself alone, not the names it starts ("skin.fit_scale" …)
    assert select_benchmarks(["skin.fit"]) == ["skin.fit"]
    assert select_benchmarks(["render.novel_view"]) == ["render.novel_view"]
    assert select_benchmarks(["skin.fit_"]) == ["skin.fit_scale", "skin.fit_stream"]
    with pytest.raises(InputError, match=r"unknown benchmark\(s\) 'visibility.closer'.*"
                                         r"available: .*visibility.closest_hit"):
        select_benchmarks(["visibility.closer", "vis"])


def test_bench_cli_runs_a_prefix_of_a_dotted_part(monkeypatch, tmp_path, capsys):
    from facegeo.cli import main

    ran = []
    registered()  # the real ones imported first (a later import would register them twice)
    monkeypatch.setattr(bench, "read_bandwidth", lambda *a, **k: None)
    for name in ("visibility.closest_hit", "visibility.occluded"):
        monkeypatch.setitem(bench._REGISTRY, name, lambda quick, name=name: ran.append(name)
                            or [BenchRow(name, "stub", 1.0, "x/s", threads=1)])
    assert main(["bench", "visibility.closest", "--quick", "--out", str(tmp_path)]) == 0
    assert ran == ["visibility.closest_hit"]


def test_reports_written_and_escaped(tmp_path):
    @register("test.dummy")
    def _dummy(quick):
        return [BenchRow("test.dummy", "a|b", 2.0, "x/s", error=0.5, error_unit="max |e|",
                         ratios={"vs |ref|": 1.5},
                         extra={"n |x|": 3, "s": "p|q\nr", "flag": np.bool_(True),
                                "v": np.float32(0.25)},
                         threads=1, baseline_threads={"vs |ref|": 2})]

    rows = run_benchmarks(["test.dummy"], quick=True)
    assert rows[0].peak_rss_mb is not None and rows[0].peak_rss_mb > 0
    j, m = write_reports(rows, tmp_path)
    data = json.loads(j.read_text())
    assert data["rows"][0]["ratios"] == {"vs |ref|": 1.5}
    assert data["rows"][0]["baseline_threads"] == {"vs |ref|": 2}
    assert data["meta"]["read bandwidth"]["gbps"] > 0  # measured in the same run
    assert data["rows"][0]["extra"]["flag"] is True  # numpy scalars written as JSON values
    table = [ln for ln in m.read_text().splitlines() if ln.startswith("|")]
    assert len(table) == 3
    assert {_cells(ln) for ln in table} == {8}  # pipes inside cells (keys too) are escaped
    line = table[2]
    assert "a\\|b" in line and "max \\|e\\|" in line and "vs \\|ref\\| [2 thr]: 1.5" in line
    assert "n \\|x\\|=3" in line and "\n" not in line


def test_report_folder_errors_name_the_folder(tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    with pytest.raises(InputError, match=f"bench output folder {a_file}: an existing file"):
        write_reports([], a_file)
    with pytest.raises(InputError, match=f"{a_file / 'sub' / 'x'}: cannot create it: {a_file} "
                                         "is a file, not a directory"):
        write_reports([], a_file / "sub" / "x")


def test_table_cell_count_fails_for_an_unescaped_pipe():
    """The cell-count check above can fail: an unescaped | adds a cell."""
    row = BenchRow("b", "case", 1.0, "x/s", threads=1)
    good = render_table([row])[2]
    assert _cells(good) == 8
    assert _cells(good.replace("case", "ca|se")) == 9


def test_read_bandwidth_measures_methods_and_threads():
    bw = read_bandwidth(32 << 20, repeat=1, fresh=True)
    assert bw.nbytes == 32 << 20
    assert "numpy sum, 1 thread" in bw.by_method and bw.gbps == max(bw.by_method.values())
    assert all(v > 0 and math.isfinite(v) for v in bw.by_method.values())
    assert bw.at_threads(1) <= bw.gbps
    # reading 1 GB once at 1 GB/s takes 1 s
    assert bw.read_once_seconds(bw.gbps * 1e9) == pytest.approx(1.0)
    with pytest.raises(InputError, match="nbytes"):
        read_bandwidth(10)


def test_read_bandwidth_includes_the_pure_read_at_one_and_two_threads(monkeypatch):
    """A tiny array (1 MiB, one pass each): the compiled pure read is a method beside numpy sum
    and sgemv at 1 and 2 threads, and the best figure is the maximum over all of them."""
    monkeypatch.setattr(bench, "_BANDWIDTH", {})
    bw = read_bandwidth(1 << 20, repeat=1, max_threads=2)
    assert set(bw.by_method) == {
        "numpy sum, 1 thread", f"{PURE_READ}, 1 thread", f"{PURE_READ}, 2 threads",
        "sgemv (OpenBLAS), 1 thread", "sgemv (OpenBLAS), 2 threads"}
    assert bw.unavailable == {}
    assert bw.gbps == max(bw.by_method.values()) and bw.by_method[bw.method] == bw.gbps
    assert bw.threads == bench._method_threads(bw.method)
    assert bw.at_threads(1) == max(v for k, v in bw.by_method.items() if k.endswith("1 thread"))


def test_at_threads_is_the_strongest_method_within_the_thread_count():
    """Figures chosen so that each wrong rule gives a different answer: the best method overall
    runs on 2 threads, the best at 1 thread is not the pure read, and a 3-thread method is
    weaker than a 2-thread one."""
    by = {"numpy sum, 1 thread": 11.0, f"{PURE_READ}, 1 thread": 14.0,
          "sgemv (OpenBLAS), 1 thread": 15.0, f"{PURE_READ}, 2 threads": 28.0,
          "sgemv (OpenBLAS), 2 threads": 21.0, "sgemv (OpenBLAS), 3 threads": 25.0}
    bw = Bandwidth(28.0, f"{PURE_READ}, 2 threads", 2, 1 << 20, by)
    assert bw.at_threads(1) == 15.0  # sgemv beats the pure read at 1 thread here
    assert bw.method_at(1) == "sgemv (OpenBLAS), 1 thread"
    assert bw.at_threads(2) == 28.0
    assert bw.at_threads(3) == 28.0  # max over ≤ 3 threads, not the 3-thread method
    assert bw.method_at(3) == f"{PURE_READ}, 2 threads"
    assert bw.read_once_seconds(15e9, threads=1) == pytest.approx(1.0)


def test_pure_read_reads_every_row_on_any_thread_count():
    """The kernel's sum over small integers is exact, so it shows every row was read: 4k + 3
    rows (the tail the four-row loop leaves) split over 1, 2 and 3 Python threads."""
    rows = np.arange(4 * 5 + 3, dtype=np.float32)[:, None] * np.ones((1, READ_ROW), np.float32)
    rows[:, 1] += 1.0  # not constant along a row
    want = float(rows.sum(dtype=np.float64))
    for threads in (1, 2, 3):
        assert pure_read(rows, threads) == want, threads
    assert pure_read(rows[:5], 1) == float(rows[:5].sum(dtype=np.float64))


def test_pure_read_rejects_what_it_cannot_read():
    a = np.ones((8, 64), np.float32)
    with pytest.raises(ShapeError, match="rows: expected a C-contiguous"):
        pure_read(a[:, ::2], 1)
    with pytest.raises(ShapeError, match="float64"):
        pure_read(a.astype(np.float64), 1)
    with pytest.raises(InputError, match="threads"):
        pure_read(a, 0)


def test_read_bandwidth_pauses_for_blas_spin_after_multithread_sgemv(monkeypatch):
    """OpenBLAS's idle workers spin after a multi-threaded call: the probe sleeps
    BLAS_SPIN_SECONDS after each one (so also before returning), never after one thread."""
    slept = []
    monkeypatch.setattr(bench.time, "sleep", slept.append)
    monkeypatch.setattr(bench, "_BANDWIDTH", {})
    read_bandwidth(1 << 20, repeat=1, max_threads=1)
    assert slept == []
    read_bandwidth(1 << 20, repeat=1, max_threads=2, fresh=True)
    assert slept == [bench.BLAS_SPIN_SECONDS]


def test_read_bandwidth_without_the_compiled_read_keeps_sgemv_and_says_so(monkeypatch):
    monkeypatch.setattr(bench, "_compile_pure_read", lambda: (None, "numba compile failed (test)"))
    monkeypatch.setattr(bench, "_BANDWIDTH", {})
    bw = read_bandwidth(1 << 20, repeat=1, max_threads=2)
    assert not any(k.startswith("pure read") for k in bw.by_method)
    assert {"sgemv (OpenBLAS), 1 thread", "sgemv (OpenBLAS), 2 threads"} <= set(bw.by_method)
    assert bw.unavailable == {PURE_READ: "numba compile failed (test)"}
    with pytest.raises(InputError, match="numba compile failed"):
        pure_read(np.ones((4, 8), np.float32), 1)
    from facegeo.bench.memory import bench_read_bandwidth

    monkeypatch.setattr(bench, "BANDWIDTH_BYTES", 1 << 20)
    rows = bench_read_bandwidth(True)
    assert all("numba compile failed" in r.extra["not measured"] for r in rows)


def test_peak_rss_sees_an_allocation():
    """Reset, allocate 64 MiB, read the peak. In a fresh interpreter: after other tests (the
    mesh tests' Open3D and numba thread pools) the kernel's per-thread RSS counters can leave
    the reset peak above the process's resident size, and the allocation then shows no rise."""
    import subprocess
    import sys

    code = ("import numpy as np\n"
            "from facegeo import bench\n"
            "assert bench.reset_peak_rss()\n"
            "before = bench.peak_rss_mb()\n"
            "a = np.ones(64 << 20, dtype=np.uint8)\n"
            "print(bench.peak_rss_mb() - before)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True)
    assert float(out.stdout.strip()) >= 60


def _check_rows(name: str, rows: list[BenchRow]) -> None:
    assert rows, f"{name} returned no rows"
    for r in rows:
        assert r.benchmark == name
        assert isinstance(r.case, str) and r.case
        assert math.isfinite(r.speed) and r.speed > 0, (r.case, r.speed)
        assert r.speed_unit
        if r.error is not None:
            assert math.isfinite(r.error), (r.case, r.error)
            assert r.error_unit, r.case
        assert isinstance(r.threads, int) and r.threads >= 1, (r.case, r.threads)
        for key, ratio in r.ratios.items():
            assert math.isfinite(ratio) and ratio > 0, (r.case, key, ratio)
            # every ratio names its baseline and the baseline's thread count
            assert isinstance(key, str) and len(key) > 3
            assert isinstance(r.baseline_threads.get(key), int), (r.case, key)
        assert r.peak_rss_mb is not None and r.peak_rss_mb > 0
    table = render_table(rows)
    assert {_cells(ln) for ln in table} == {8}


#: Benchmarks that measure on the real data in ``../shared/data`` (no rows without it).
_SHARED_DATA = {"calibration.real", "calibration.stereo", "mesh.real_bust", "photometric.real"}


def _bench_params():
    out = []
    for name in registered():
        if name.startswith("test."):
            continue
        marks = [pytest.mark.slow] if name in _SLOW else []
        if name in _SHARED_DATA:
            from conftest import SHARED_DATA

            marks.append(pytest.mark.skipif(not SHARED_DATA.is_dir(), reason=(
                f"{name} measures on ../shared/data, absent here ({SHARED_DATA})")))
        out.append(pytest.param(name, marks=marks, id=name))
    return out


#: ``scale.reconstruct``'s quick rows (the ``modern_tiny`` preset, 16 cameras, through
#: ``reconstruct`` up to the fit, then the relight, in one process and on clusters of one and
#: two workers): every stage's products against the in-process run's, the largest relative
#: difference of any array (measured 0.0: every array equal; one file's bytes differ), as
#: tests/test_scale_stages.py's ``PRODUCTS_RTOL``. This row is the suite's check that the
#: whole reconstruction on workers equals the one-process run (it had a run of its own).
SCALE_RECONSTRUCT_RTOL = 1e-6


def _check_scale_reconstruct(rows) -> None:
    assert [r.case for r in rows] == ["reconstruct, in-process",
                                      "reconstruct, LocalCluster, 1 worker × 1 thread",
                                      "reconstruct, LocalCluster, 2 workers × 1 thread"]
    for r in rows:
        assert r.extra["files compared"] > 100, r.case  # every stage's products
        assert r.error <= SCALE_RECONSTRUCT_RTOL, (r.case, r.error)
    for r in rows[1:]:  # the stages ran as tasks on the cluster's workers
        tasks = r.extra["tasks per stage"]
        assert all(tasks[st] > 0 for st in ("decode", "project", "fit", "relight")), tasks


@pytest.mark.parametrize("name", _bench_params())
def test_registered_benchmark_quick_rows_well_formed(name, tmp_path):
    rows = run_benchmarks([name], quick=True)
    _check_rows(name, rows)
    if name == "scale.reconstruct":
        _check_scale_reconstruct(rows)
    _, m = write_reports(rows, tmp_path)
    table = [ln for ln in m.read_text().splitlines() if ln.startswith("|")]
    assert len(table) == len(rows) + 2
    assert {_cells(ln) for ln in table} == {8}


def test_decode_benchmark_reports_reference_and_read_once_limit():
    rows = run_benchmarks(["structured_light.decode_gray"], quick=True)
    ours = rows[0]
    assert ours.case.startswith("facegeo decode_gray")
    assert "vs numpy reference decode" in ours.ratios
    assert any(k.startswith("of read-once limit") for k in ours.ratios)
    assert ours.error == 0.0  # synthetic frames decode exactly
    assert ours.extra["pixels differing from numpy reference"] == 0.0
    cv = [r for r in rows if "getProjPixel" in r.case]
    assert cv and "per-pixel Python loop" in cv[0].case and "extrapolated" in cv[0].case


def test_reference_decode_matches_truth_on_small_frames():
    from facegeo.geometry.structured_light import PatternSpec
    from facegeo.bench.structured_light import _frames, reference_decode_gray

    spec = PatternSpec(width=1024, height=768, white_black=False)
    frames, _, tx, ty, _ = _frames(64, 48, spec)
    px, py, valid = reference_decode_gray(frames, spec)
    assert valid.all()
    np.testing.assert_array_equal(px, tx)
    np.testing.assert_array_equal(py, ty)
    # a flipped bit plane must show up (the reference is not vacuous)
    frames["gray_x_03"], frames["gray_x_03_inv"] = frames["gray_x_03_inv"], frames["gray_x_03"]
    px2, _, _ = reference_decode_gray(frames, spec)
    assert np.mean(px2 != tx) > 0.5


def test_previous_checkout_copy_is_one_cached_folder_per_checkout(tmp_path, monkeypatch):
    """``FACEGEO_BENCH_PREVIOUS``: the previous checkout's visibility modules are copied into
    one cache folder per checkout, reused by later runs (files unchanged, so numba's cache of
    the kernels beside them stays valid); nothing is left in the temporary folder per run."""
    import sys
    import tempfile
    from pathlib import Path

    import facegeo
    from facegeo.bench import visibility as vis_bench

    pkg = "_facegeo_previous_vis"
    checkout = Path(facegeo.__file__).resolve().parent.parent
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    monkeypatch.setenv("FACEGEO_CACHE_DIR", str(tmp_path / "cache"))

    def forget() -> dict:
        return {m: sys.modules.pop(m) for m in list(sys.modules)
                if m == pkg or m.startswith(pkg + ".")}

    def load():
        monkeypatch.setattr(sys, "path", list(sys.path))
        forget()
        return vis_bench._load_previous(str(checkout))

    saved = forget()
    try:
        scene_cls = load()
        assert scene_cls.__name__ == "RayScene" and scene_cls.__module__ == f"{pkg}.visibility"
        folder = vis_bench._previous_package_dir(checkout)
        assert folder.parent == tmp_path / "cache" / "prev-vis"
        files = sorted(p.name for p in (folder / pkg).glob("*.py"))
        assert files == ["__init__.py", "_vis_kernels.py", "_vis_util.py", "visibility.py"]
        stamps = {p: p.stat().st_mtime_ns for p in (folder / pkg).glob("*.py")}
        assert "from facegeo.surface import _vis" not in (folder / pkg / "visibility.py").read_text()
        load()  # a second run: the same folder, no file rewritten
        assert sorted((tmp_path / "cache" / "prev-vis").iterdir()) == [folder]
        assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
        assert list(tmp.iterdir()) == []  # no facegeo-prev-vis-* left per run
    finally:
        forget()
        sys.modules.update(saved)
