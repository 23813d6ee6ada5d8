"""Benchmark registry: speed against error, never wall-clock asserts.

A benchmark is a function registered with :func:`register`; it returns a list of
:class:`BenchRow`. Benchmarks live in the modules of the :mod:`facegeo.pipeline.benchmarks` package
(one per stage); :func:`run_benchmarks` imports them all, runs the selected ones and
:func:`write_reports` writes ``bench.json`` and ``bench.md``.

Timings on these shared machines are noisy: a row should carry a *ratio* measured in the same
run (ours against the strongest fair baseline, at the same thread count) beside absolute
throughput, the physical limit where one exists (:func:`read_bandwidth` measures the memory
read bandwidth in the same run), and an error figure whenever the benchmark computes something
with a known answer. Every row states the threads it used (:attr:`BenchRow.threads`) and those of
each baseline (:attr:`BenchRow.baseline_threads`); :func:`run_benchmarks` records each
benchmark's peak resident memory. The rules are in ``docs/benchmarks.md``.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import logging
import os
import pkgutil
import platform
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from facegeo.errors import InputError
from facegeo.fsutil import atomic_write_text
from facegeo.checks import fmt_value

log = logging.getLogger(__name__)

__all__ = [
    "BenchRow",
    "Bandwidth",
    "register",
    "registered",
    "run_benchmarks",
    "write_reports",
    "best_of",
    "read_bandwidth",
    "blas_threads",
    "limit_threads",
    "peak_rss_mb",
    "reset_peak_rss",
]


@dataclass
class BenchRow:
    """One measured line of a benchmark.

    Attributes
    ----------
    benchmark : str
        Registered benchmark name (``"visibility.closest_hit"``).
    case : str
        What was measured (``"facegeo.surface.visibility, 2 threads"``).
    speed : float
        Throughput (higher is better).
    speed_unit : str
        Unit of ``speed`` (``"Mrays/s"``).
    error : float or None
        Error against a known answer, if any.
    error_unit : str or None
        What ``error`` measures (``"max |Δt| / t"``).
    ratios : dict
        Speed ratios against references measured in the same run (``{"vs embreex": 0.97}``).
    extra : dict
        Anything else worth recording (sizes, parameters).
    threads : int or None
        Threads the measured case used (``None``: not stated — :func:`write_reports` shows
        ``?``; every benchmark in this package states it).
    baseline_threads : dict
        Threads used by each baseline, keyed like ``ratios`` (``{"vs embreex": 1}``): a ratio
        is only fair at equal thread counts, and the table shows the count beside each ratio.
    peak_rss_mb : float or None
        Peak resident memory (MiB) of the process while the benchmark ran; filled in by
        :func:`run_benchmarks` (reset before each benchmark where Linux allows it).
    """

    benchmark: str
    case: str
    speed: float
    speed_unit: str
    error: float | None = None
    error_unit: str | None = None
    ratios: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    threads: int | None = None
    baseline_threads: dict = field(default_factory=dict)
    peak_rss_mb: float | None = None


BenchFn = Callable[[bool], list[BenchRow]]
_REGISTRY: dict[str, BenchFn] = {}


def register(name: str) -> Callable[[BenchFn], BenchFn]:
    """Decorator: register ``fn(quick: bool) -> list[BenchRow]`` under ``name``."""

    def deco(fn: BenchFn) -> BenchFn:
        if name in _REGISTRY and _REGISTRY[name] is not fn:
            raise InputError(f"benchmark {fmt_value(name)} registered twice")
        _REGISTRY[name] = fn
        return fn

    return deco


def _discover() -> None:
    import facegeo.pipeline.benchmarks as pkg

    for info in pkgutil.iter_modules(pkg.__path__):
        if not info.name.startswith("_"):
            importlib.import_module(f"{pkg.__name__}.{info.name}")


def registered() -> list[str]:
    """Names of all registered benchmarks, sorted."""
    _discover()
    return sorted(_REGISTRY)


def best_of(fn: Callable[[], object], repeat: int = 3) -> tuple[float, object]:
    """Run ``fn`` ``repeat`` times; return (best wall time in seconds, last result)."""
    best = float("inf")
    out = None
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


# ---------------------------------------------------------------- threads, bandwidth, memory


def blas_threads() -> int:
    """Threads the BLAS library (OpenBLAS under numpy) uses now (1 when none is found)."""
    from threadpoolctl import threadpool_info

    counts = [int(i.get("num_threads", 1)) for i in threadpool_info() if i.get("user_api") == "blas"]
    return max(counts, default=1)


@contextlib.contextmanager
def limit_threads(n: int) -> Iterator[None]:
    """Limit BLAS/OpenMP thread pools to ``n`` threads inside the block (threadpoolctl)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=int(n)):
        yield


@dataclass
class Bandwidth:
    """Memory read bandwidth measured in this run (the roofline for streaming benchmarks).

    Attributes
    ----------
    gbps : float
        Best read bandwidth over all methods, GB/s (1e9 bytes per second).
    method : str
        The method and thread count that reached ``gbps``.
    threads : int
        Threads of that method.
    nbytes : int
        Bytes read per pass (the array is ≥ 512 MiB by default: far larger than any cache).
    by_method : dict
        ``{"numpy sum, 1 thread": GB/s, "sgemv (OpenBLAS), 1 thread": …, …}``.
    """

    gbps: float
    method: str
    threads: int
    nbytes: int
    by_method: dict

    def at_threads(self, n: int) -> float:
        """Best bandwidth (GB/s) among methods that used at most ``n`` threads."""
        best = [v for k, v in self.by_method.items() if _method_threads(k) <= n]
        return max(best, default=self.gbps)

    def read_once_seconds(self, nbytes: float, threads: int | None = None) -> float:
        """Seconds to read ``nbytes`` once at this bandwidth (at ``threads``, else the best)."""
        bw = self.gbps if threads is None else self.at_threads(threads)
        return float(nbytes) / (bw * 1e9)


def one_blas_thread(fn: BenchFn) -> BenchFn:
    """Decorator: run a benchmark with BLAS limited to one thread (``threadpoolctl``), so that
    its rows can honestly say ``threads=1`` for numpy/scipy code that calls BLAS."""
    import functools

    @functools.wraps(fn)
    def wrapped(quick: bool) -> list[BenchRow]:
        from threadpoolctl import threadpool_limits

        with threadpool_limits(1, user_api="blas"):
            return fn(quick)

    return wrapped


def _method_threads(key: str) -> int:
    return int(key.rsplit(", ", 1)[1].split()[0])


_BANDWIDTH: dict[int, Bandwidth] = {}

#: Bytes :func:`read_bandwidth` reads by default (512 MiB, far beyond any cache; tests lower it).
BANDWIDTH_BYTES = 512 << 20


def read_bandwidth(nbytes: int | None = None, *, repeat: int = 3, max_threads: int | None = None,
                   fresh: bool = False) -> Bandwidth:
    """Measure the memory read bandwidth in this run (cached per run and size).

    Reads one float32 array of ``nbytes`` (≥ 512 MiB by default) with a numpy sum on one thread
    and with an OpenBLAS ``sgemv`` (``A @ x``, ``A`` of shape (N, 1024)) on 1 … ``max_threads``
    threads; best of ``repeat`` passes each. :func:`run_benchmarks` clears the cache, so every
    run measures its own figure under the same machine load as its benchmarks.

    Parameters
    ----------
    nbytes : int, optional
        Size of the array read, bytes (rounded down to whole rows of 4 KiB); default
        :data:`BANDWIDTH_BYTES`.
    repeat : int
        Passes per method; the best is kept.
    max_threads : int, optional
        Largest BLAS thread count tried (default: the CPU count).
    fresh : bool
        Measure again even if this size was measured in this run.
    """
    nbytes = BANDWIDTH_BYTES if nbytes is None else int(nbytes)
    if nbytes < 4096:
        raise InputError(f"nbytes: expected at least 4096 bytes, got {nbytes}")
    if not fresh and nbytes in _BANDWIDTH:
        return _BANDWIDTH[nbytes]
    cols = 1024
    a = np.ones((nbytes // (4 * cols), cols), dtype=np.float32)
    x = np.ones(cols, dtype=np.float32)
    size = a.nbytes
    by: dict[str, float] = {}
    t, _ = best_of(lambda: a.sum(dtype=np.float32), repeat)
    by["numpy sum, 1 thread"] = size / t / 1e9
    for n in range(1, (max_threads or os.cpu_count() or 1) + 1):
        with limit_threads(n):
            t, _ = best_of(lambda: a @ x, repeat)
        by[f"sgemv (OpenBLAS), {n} thread{'s' if n > 1 else ''}"] = size / t / 1e9
    del a
    method = max(by, key=by.get)
    bw = Bandwidth(by[method], method, _method_threads(method), size, by)
    _BANDWIDTH[nbytes] = bw
    return bw


def _status_kib(field_name: str) -> float | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field_name + ":"):
                    return float(line.split()[1])
    except OSError:
        return None
    return None


def reset_peak_rss() -> bool:
    """Reset the process's peak-RSS counter (Linux ``/proc/self/clear_refs``); True if it did."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def peak_rss_mb() -> float:
    """Peak resident memory of this process, MiB (since the last :func:`reset_peak_rss`)."""
    kib = _status_kib("VmHWM")
    if kib is None:  # pragma: no cover - non-Linux
        import resource

        kib = float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
    return kib / 1024.0


def run_benchmarks(
    names: list[str] | None = None,
    *,
    quick: bool = False,
    progress: Callable[[str], None] | None = None,
) -> list[BenchRow]:
    """Run the selected benchmarks (all by default) and return their rows.

    ``names`` entries match a registered name exactly or as a prefix (``"visibility"``).
    """
    available = registered()
    if names:
        chosen = [n for n in available if any(n == q or n.startswith(q + ".") for q in names)]
        unknown = [q for q in names if not any(n == q or n.startswith(q + ".") for n in available)]
        if unknown:
            raise InputError(
                f"unknown benchmark(s) {', '.join(unknown)}; available: {', '.join(available)}"
            )
    else:
        chosen = available
    _BANDWIDTH.clear()  # measured again in this run, under this run's load ...
    if progress:
        progress("memory read bandwidth")
    read_bandwidth()  # ... before the benchmarks, so its 512 MiB array is in no peak RSS
    rows: list[BenchRow] = []
    for name in chosen:
        if progress:
            progress(name)
        log.info("benchmark %s", name)
        reset_peak_rss()
        new = _REGISTRY[name](quick)
        peak = peak_rss_mb()
        for r in new:
            if r.peak_rss_mb is None:
                r.peak_rss_mb = peak
        rows.extend(new)
    return rows


def _cell(x) -> str:
    """Text of one Markdown table cell: ``|`` escaped, line breaks flattened."""
    text = str(x).replace("\r", " ").replace("\n", " ")
    return text.replace("|", "\\|")  # a bare | would split the cell


def _fmt(x) -> str:
    if x is None:
        return "—"
    if isinstance(x, (float, np.floating)):
        return f"{float(x):.4g}"
    if isinstance(x, np.integer):
        return str(int(x))
    return _cell(x)


def _ratio_text(r: BenchRow) -> str:
    parts = []
    for k, v in r.ratios.items():
        th = r.baseline_threads.get(k)
        label = _cell(k) if th is None else f"{_cell(k)} [{th} thr]"
        parts.append(f"{label}: {float(v):.3g}")
    return ", ".join(parts) or "—"


def render_table(rows: list[BenchRow]) -> list[str]:
    """Markdown lines of the rows' table (header, rule, one line per row)."""
    lines = [
        "| benchmark | case | threads | speed | error | ratios [baseline threads] | peak RSS | notes |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        err = "—" if r.error is None else f"{_fmt(r.error)} ({_fmt(r.error_unit)})"
        extra = ", ".join(f"{_cell(k)}={_fmt(v)}" for k, v in r.extra.items()) or ""
        threads = "?" if r.threads is None else str(r.threads)
        rss = "—" if r.peak_rss_mb is None else f"{r.peak_rss_mb:.0f} MiB"
        lines.append(
            f"| {_fmt(r.benchmark)} | {_fmt(r.case)} | {threads} | {_fmt(r.speed)} "
            f"{_fmt(r.speed_unit)} | {err} | {_ratio_text(r)} | {rss} | {extra} |"
        )
    return lines


def _json_default(x):
    """numpy scalars and arrays in ``extra`` → plain JSON values."""
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"bench.json: cannot write a {type(x).__name__}")


def write_reports(rows: list[BenchRow], out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``bench.json`` and ``bench.md`` into ``out_dir`` (atomically); return their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "processor": platform.processor(),
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    meta["cpus"] = os.cpu_count()
    try:
        meta["load average"] = [round(x, 2) for x in os.getloadavg()]
    except OSError:  # pragma: no cover - not available
        meta["load average"] = None
    try:
        meta["blas threads"] = blas_threads()
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency
        meta["blas threads"] = None
    if _BANDWIDTH:
        bw = max(_BANDWIDTH.values(), key=lambda b: b.nbytes)
        meta["read bandwidth"] = asdict(bw)
    jpath = out / "bench.json"
    atomic_write_text(jpath, json.dumps({"meta": meta, "rows": [asdict(r) for r in rows]}, indent=2,
                                        default=_json_default))
    head = [
        f"facegeo bench, {meta['time']}: {meta['cpus']} CPUs, BLAS threads {meta['blas threads']}, "
        f"Python {meta['python']}, load average {meta['load average']} (other jobs slow "
        "every figure; compare ratios from one run).",
    ]
    if "read bandwidth" in meta:
        bw = meta["read bandwidth"]
        figs = ", ".join(f"{k} {v:.1f}" for k, v in bw["by_method"].items())
        head.append(
            f"Memory read bandwidth measured in this run ({bw['nbytes'] / 2**20:.0f} MiB array, "
            f"GB/s): {figs}."
        )
    head.append("Rules: docs/benchmarks.md (equal thread counts; baselines named for what they "
                "are; physical limits measured in the same run).")
    lines = head + [""] + render_table(rows)
    mpath = out / "bench.md"
    atomic_write_text(mpath, "\n".join(lines) + "\n")
    return jpath, mpath
