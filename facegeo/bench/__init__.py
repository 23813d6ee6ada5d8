"""Benchmark registry: speed against error, never wall-clock asserts.

A benchmark is a function registered with :func:`register`; it returns a list of
:class:`BenchRow`. Benchmarks live in this package's modules, one per stage (they may use the
generator and the evaluation, which the stages never do); :func:`run_benchmarks` imports them
all, runs the selected ones and :func:`write_reports` writes ``bench.json`` and ``bench.md``.

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
import functools
import importlib
import itertools
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

from facegeo.checks import fmt_value
from facegeo.errors import InputError, ShapeError
from facegeo.fsutil import atomic_write_text
from facegeo.rss import peak_rss_mb, reset_peak_rss

log = logging.getLogger(__name__)

__all__ = [
    "BLAS_SPIN_SECONDS",
    "PURE_READ",
    "READ_ROW",
    "Bandwidth",
    "BenchRow",
    "best_of",
    "blas_threads",
    "limit_threads",
    "peak_rss_mb",
    "pure_read",
    "pure_read_kernel",
    "read_bandwidth",
    "register",
    "registered",
    "reset_peak_rss",
    "run_benchmarks",
    "select_benchmarks",
    "write_reports",
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
    for info in pkgutil.iter_modules(__path__):
        if not info.name.startswith("_"):
            importlib.import_module(f"{__name__}.{info.name}")


def shared_data_dir() -> Path:
    """The real data sets' folder benchmarks measure on: ``FACEGEO_SHARED_DATA``, else
    ``../shared/data`` beside the checkout (a benchmark gives no rows when it is absent)."""
    default = Path(__file__).resolve().parents[3] / "shared" / "data"
    return Path(os.environ.get("FACEGEO_SHARED_DATA", default))


def registered() -> list[str]:
    """Names of all registered benchmarks, sorted."""
    _discover()
    return sorted(_REGISTRY)


#: At most this many timed repetitions of anything (None: as each benchmark asks). The test
#: suite sets 1: it checks the rows' form, not their speed.
MAX_REPEAT: int | None = None


def repeats(n: int) -> int:
    """``n`` timed repetitions, at most :data:`MAX_REPEAT`, at least 1."""
    return max(1, n if MAX_REPEAT is None else min(n, MAX_REPEAT))


def best_of(fn: Callable[[], object], repeat: int = 3) -> tuple[float, object]:
    """Run ``fn`` ``repeat`` times (:func:`repeats`); return (best wall time in seconds, last
    result)."""
    best = float("inf")
    out = None
    for _ in range(repeats(repeat)):
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


#: Seconds to wait after a multi-threaded BLAS call before timing anything else: OpenBLAS's idle
#: workers busy-wait (by default ≈ 2^28 cycles, ≈ 0.1 s) before they sleep, holding a core.
#: Measured (quiet rounds, 1.5 GB field): a two-thread relight right after a two-thread
#: ``sgemv`` read 19.6 GB/s (best of 8; process CPU 1.94 × wall, the spinning worker
#: included), after a 0.3 s pause 30.6 GB/s — the interleaved probes had been slowing the
#: relight they were compared with (and inflating its CPU time).
BLAS_SPIN_SECONDS = 0.3

#: Row width (float32 values, 12 KB: the paper field's 2048-light rows) in which the pure read
#: (:func:`pure_read_kernel`) reads its bytes.
READ_ROW = 3072

#: Name of the compiled pure read in :attr:`Bandwidth.by_method` (before ``, N thread(s)``).
PURE_READ = "pure read (numba float32 sum, 12 KB rows, 4 at a time)"


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
        Bytes of the array read (≥ 512 MiB by default: far larger than any cache). The pure
        read reads the whole 12 KB rows the array holds (all but its last < 12 KB) and is rated
        by the bytes it read.
    by_method : dict
        ``{"numpy sum, 1 thread": GB/s, "<PURE_READ>, 1 thread": …, "sgemv (OpenBLAS),
        2 threads": …, …}``; every key ends in ``, N thread(s)``.
    unavailable : dict
        Methods that could not run, with the reason (``{PURE_READ: "numba: …"}``); empty when
        every method ran.
    """

    gbps: float
    method: str
    threads: int
    nbytes: int
    by_method: dict
    unavailable: dict = field(default_factory=dict)

    def method_at(self, n: int) -> str:
        """The strongest method that used at most ``n`` threads (the one that sets the limit a
        job on ``n`` threads is held against; :attr:`method` when none used so few)."""
        within = [k for k in self.by_method if _method_threads(k) <= n]
        return max(within, key=self.by_method.get, default=self.method)

    def at_threads(self, n: int) -> float:
        """Best bandwidth (GB/s) among methods that used at most ``n`` threads: the strongest
        probe a job on ``n`` threads is measured against (:meth:`method_at` names it)."""
        return self.by_method.get(self.method_at(n), self.gbps)

    def read_once_seconds(self, nbytes: float, threads: int | None = None) -> float:
        """Seconds to read ``nbytes`` once at this bandwidth (at ``threads``, else the best)."""
        bw = self.gbps if threads is None else self.at_threads(threads)
        return float(nbytes) / (bw * 1e9)


def one_blas_thread(fn: BenchFn) -> BenchFn:
    """Decorator: run a benchmark with BLAS limited to one thread (``threadpoolctl``), so that
    its rows can honestly say ``threads=1`` for numpy/scipy code that calls BLAS."""

    @functools.wraps(fn)
    def wrapped(quick: bool) -> list[BenchRow]:
        from threadpoolctl import threadpool_limits

        with threadpool_limits(1, user_api="blas"):
            return fn(quick)

    return wrapped


def _method_threads(key: str) -> int:
    return int(key.rsplit(", ", 1)[1].split()[0])


def _threads_label(n: int) -> str:
    return f"{n} thread{'s' if n > 1 else ''}"


@functools.lru_cache(maxsize=1)
def _compile_pure_read() -> tuple[Callable | None, str | None]:
    """The compiled pure read and ``None``, or ``None`` and why it could not be compiled."""
    try:
        from numba import njit
    except ImportError as exc:
        return None, f"numba not importable ({exc})"

    @njit(nogil=True, boundscheck=False, fastmath=True)
    def read_rows(a):  # pragma: no cover - compiled
        n, m = a.shape
        s = np.float32(0)
        p = 0
        while p + 3 < n:  # four rows a pass: four independent load streams
            x0 = np.float32(0)
            x1 = np.float32(0)
            x2 = np.float32(0)
            x3 = np.float32(0)
            for j in range(m):
                x0 += a[p, j]
                x1 += a[p + 1, j]
                x2 += a[p + 2, j]
                x3 += a[p + 3, j]
            s += x0 + x1 + x2 + x3
            p += 4
        while p < n:  # the last n % 4 rows: every byte counted is read
            x0 = np.float32(0)
            for j in range(m):
                x0 += a[p, j]
            s += x0
            p += 1
        return s

    try:
        read_rows(np.zeros((5, 8), np.float32))  # compile now, outside any timing
    except Exception as exc:  # noqa: BLE001 - any compile failure leaves sgemv as the probe
        log.warning("pure-read probe not compiled, sgemv and numpy sum only: %s", exc)
        return None, f"numba compile failed ({type(exc).__name__}: {exc})"
    return read_rows, None


def pure_read_kernel() -> Callable | None:
    """The compiled pure read, ``read(a) -> float32``: sums a C-contiguous ``(n, m)`` float32
    array four rows at a time (vectorised, ``fastmath`` so the sums use parallel lanes; the
    result only keeps the loads from being optimised away), then the last ``n % 4`` rows;
    ``nogil``, so Python threads run it in parallel. Compiled on first use (≈ 1 s, outside
    any timing); ``None`` when numba is missing or the compile fails (the reason is in
    :attr:`Bandwidth.unavailable`).

    The strongest read measured here, so the memory-read limit (DESIGN §8: a flattering ratio
    is a bug): a kernel at the memory's limit scores above 1 against ``sgemv`` alone. Measured
    (quiet rounds, paper-size relighting field, best of 5, two threads on two halves): this
    float32 sum 38.4 GB/s, a uint32 OR of four rows 32.0, a uint16 OR 28.3, two-thread
    ``sgemv`` 27.7; one thread 20.1 / 19.6 / 17.6. 12 KB rows (:data:`READ_ROW`) read faster
    four at a time than 4 KB rows (``sgemv``'s 1024 columns) or one at a time (one thread,
    1 GB, load ≈ 4: 21.1 against 19.3 and 15.4; ``sgemv`` 15.1).
    """
    return _compile_pure_read()[0]


def pure_read(rows: np.ndarray, threads: int = 1, kernel: Callable | None = None) -> float:
    """Read ``rows`` once with the pure read on ``threads`` Python threads, each running
    :func:`pure_read_kernel` on one contiguous part (``threads == 1``: in the calling thread).

    Parameters
    ----------
    rows : (n, m) float32, C-contiguous
        The bytes to read, as rows (:data:`READ_ROW` values wide for the kernel's best speed).
    threads : int
        Python threads (≥ 1); part ``i`` is rows ``[n·i // threads, n·(i+1) // threads)``.
    kernel : callable, optional
        The compiled read (default :func:`pure_read_kernel`; pass it to skip the lookup).

    Returns
    -------
    float
        The sum of every value read (what keeps the loads from being optimised away; ``fastmath``
        reorders it, exact only for values whose partial sums are exact in float32).

    Raises
    ------
    ShapeError
        ``rows`` not a C-contiguous 2-D float32 array.
    InputError
        ``threads`` < 1, or the kernel unavailable (numba missing or not compiling).
    """
    import threading

    if not (isinstance(rows, np.ndarray) and rows.ndim == 2 and rows.dtype == np.float32
            and rows.flags.c_contiguous):
        got = (f"{type(rows).__name__}" if not isinstance(rows, np.ndarray) else
               f"{rows.dtype} array of shape {rows.shape}"
               f"{'' if rows.flags.c_contiguous else ', not C-contiguous'}")
        raise ShapeError(f"rows: expected a C-contiguous (n, m) float32 array, got {got}")
    if int(threads) < 1:
        raise InputError(f"threads: expected at least 1, got {threads}")
    read = kernel if kernel is not None else pure_read_kernel()
    if read is None:
        raise InputError(f"pure read unavailable: {_compile_pure_read()[1]}")
    threads = int(threads)
    if threads == 1:
        return float(read(rows))
    n = rows.shape[0]
    bounds = [n * i // threads for i in range(threads + 1)]
    sums = [0.0] * threads

    def part(i: int, b0: int, b1: int) -> None:
        sums[i] = float(read(rows[b0:b1]))

    ts = [threading.Thread(target=part, args=(i, b0, b1))
          for i, (b0, b1) in enumerate(itertools.pairwise(bounds))]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    return sum(sums)


_BANDWIDTH: dict[int, Bandwidth] = {}

#: Bytes :func:`read_bandwidth` reads by default (512 MiB, far beyond any cache; tests lower it).
BANDWIDTH_BYTES = 512 << 20


def read_bandwidth(nbytes: int | None = None, *, repeat: int = 3, max_threads: int | None = None,
                   fresh: bool = False) -> Bandwidth:
    """Measure the memory read bandwidth in this run (cached per run and size).

    Reads one float32 array of ``nbytes`` (≥ 512 MiB by default), best of ``repeat`` passes
    each, with three methods:

    * a numpy sum, 1 thread;
    * the compiled pure read (:func:`pure_read_kernel`: 12 KB rows, four at a time) on 1 …
      ``max_threads`` Python threads, one contiguous part each (:func:`pure_read`) — usually
      the strongest here (measured 1.13–1.38× what ``sgemv`` reads at one thread, load
      0.5–2.6; at two threads ``sgemv`` won one of ten probes);
    * an OpenBLAS ``sgemv`` (``A @ x``, ``A`` of shape (N, 1024)) on 1 … ``max_threads`` BLAS
      threads; after each multi-threaded call the probe sleeps :data:`BLAS_SPIN_SECONDS`, so
      OpenBLAS's spinning workers slow neither the next method nor whatever the caller times
      after this returns.

    Without numba (or when the compile fails) the pure read is left out, the reason goes to
    :attr:`Bandwidth.unavailable` and the methods' names say what was measured. A job on ``n``
    threads is held against :meth:`Bandwidth.at_threads` ``(n)``, the strongest method at ≤ ``n``
    threads. :func:`run_benchmarks` clears the cache, so every run measures its own figure under
    the same machine load as its benchmarks.

    Parameters
    ----------
    nbytes : int, optional
        Size of the array read, bytes (rounded down to whole rows of 4 KiB; at least one 12 KiB
        row of the pure read); default :data:`BANDWIDTH_BYTES`.
    repeat : int
        Passes per method; the best is kept.
    max_threads : int, optional
        Largest thread count tried (default: the CPU count).
    fresh : bool
        Measure again even if this size was measured in this run.
    """
    nbytes = BANDWIDTH_BYTES if nbytes is None else int(nbytes)
    if nbytes < 4 * READ_ROW:
        raise InputError(f"nbytes: expected at least {4 * READ_ROW} bytes (one {READ_ROW}-value "
                         f"float32 row of the pure read), got {nbytes}")
    if not fresh and nbytes in _BANDWIDTH:
        return _BANDWIDTH[nbytes]
    cols = 1024
    a = np.ones((nbytes // (4 * cols), cols), dtype=np.float32)
    x = np.ones(cols, dtype=np.float32)
    size = a.nbytes
    n_rows = a.size // READ_ROW
    rows = a.reshape(-1)[: n_rows * READ_ROW].reshape(n_rows, READ_ROW)  # a view: same bytes
    read, why_not = _compile_pure_read()
    by: dict[str, float] = {}
    t, _ = best_of(lambda: a.sum(dtype=np.float32), repeat)
    by["numpy sum, 1 thread"] = size / t / 1e9
    for n in range(1, (max_threads or os.cpu_count() or 1) + 1):
        if read is not None:
            t, _ = best_of(lambda n=n: pure_read(rows, n, read), repeat)
            by[f"{PURE_READ}, {_threads_label(n)}"] = rows.nbytes / t / 1e9
        with limit_threads(n):
            t, _ = best_of(lambda: a @ x, repeat)
        by[f"sgemv (OpenBLAS), {_threads_label(n)}"] = size / t / 1e9
        if n > 1:  # OpenBLAS's idle workers stop spinning before anything else is timed
            time.sleep(BLAS_SPIN_SECONDS)
    method = max(by, key=by.get)
    bw = Bandwidth(by[method], method, _method_threads(method), size, by,
                   {} if read is not None else {PURE_READ: why_not})
    _BANDWIDTH[nbytes] = bw
    return bw


def select_benchmarks(names: list[str] | None = None) -> list[str]:
    """The registered benchmarks that ``names`` select, in registry (sorted) order.

    An entry that is a registered name selects that benchmark alone (``"skin.fit"``, not
    ``skin.fit_scale`` beside it); any other entry selects every registered name that **starts
    with** it, as text: a stage (``"visibility"``), part of a stage's name (``"vis"``: every
    ``visibility.*``) or part of a dotted part (``"visibility.closest"``:
    ``visibility.closest_hit``). No names (or None): all of them.

    Raises
    ------
    InputError
        An entry that selects nothing; the message lists every registered name.
    """
    available = registered()
    if not names:
        return available
    unknown = [q for q in names if not any(n.startswith(q) for n in available)]
    if unknown:
        raise InputError(
            f"unknown benchmark(s) {', '.join(map(repr, unknown))} (not a registered name or the "
            f"start of one); available: {', '.join(available)}"
        )
    exact = set(names) & set(available)
    return [n for n in available
            if n in exact or any(n.startswith(q) for q in names if q not in exact)]


def run_benchmarks(
    names: list[str] | None = None,
    *,
    quick: bool = False,
    progress: Callable[[str], None] | None = None,
) -> list[BenchRow]:
    """Run the selected benchmarks (all by default) and return their rows.

    ``names``: registered names or prefixes of them (:func:`select_benchmarks`).
    """
    chosen = select_benchmarks(names)
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
    """Write ``bench.json`` and ``bench.md`` into ``out_dir`` (atomically); return their paths.

    Raises
    ------
    InputError
        ``out_dir`` cannot be created (an existing file, a file on its path, a folder that
        refuses it); the message names ``out_dir`` and the reason.
    """
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise InputError(f"bench output folder {out}: an existing file, not a directory") from None
    except OSError as exc:
        base = out.parent
        while not base.exists() and base.parent != base:
            base = base.parent
        why = (f"{base} is a file, not a directory" if not base.is_dir() else
               f"{base}, its nearest existing folder, refuses it ({exc.strerror or exc})")
        raise InputError(f"bench output folder {out}: cannot create it: {why}") from exc
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
        (f"facegeo bench, {meta['time']}: {meta['cpus']} CPUs, BLAS threads "
         f"{meta['blas threads']}, Python {meta['python']}, load average {meta['load average']} "
         "(other jobs slow every figure; compare ratios from one run)."),
    ]
    if "read bandwidth" in meta:
        bw = meta["read bandwidth"]
        figs = ", ".join(f"{k} {v:.1f}" for k, v in bw["by_method"].items())
        head.append(
            f"Memory read bandwidth measured in this run ({bw['nbytes'] / 2**20:.0f} MiB array, "
            f"GB/s): {figs}."
            + "".join(f" Not measured: {k} ({v})." for k, v in bw["unavailable"].items())
        )
    head.append("Rules: docs/benchmarks.md (equal thread counts; baselines named for what they "
                "are; physical limits measured in the same run).")
    lines = head + [""] + render_table(rows)
    mpath = out / "bench.md"
    atomic_write_text(mpath, "\n".join(lines) + "\n")
    return jpath, mpath
