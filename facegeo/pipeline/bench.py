"""Benchmark registry: speed against error, never wall-clock asserts.

A benchmark is a function registered with :func:`register`; it returns a list of
:class:`BenchRow`. Benchmarks live in the modules of the :mod:`facegeo.pipeline.benchmarks` package
(one per stage); :func:`run_benchmarks` imports them all, runs the selected ones and
:func:`write_reports` writes ``bench.json`` and ``bench.md``.

Timings on these shared machines are noisy: a row should carry a *ratio* measured in the same
run (ours against a reference implementation) beside absolute throughput, and an error figure
whenever the benchmark computes something with a known answer.
"""

from __future__ import annotations

import importlib
import json
import logging
import pkgutil
import platform
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from facegeo.errors import InputError
from facegeo.fsutil import atomic_write_text

log = logging.getLogger(__name__)

__all__ = ["BenchRow", "register", "registered", "run_benchmarks", "write_reports", "best_of"]


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
    """

    benchmark: str
    case: str
    speed: float
    speed_unit: str
    error: float | None = None
    error_unit: str | None = None
    ratios: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)


BenchFn = Callable[[bool], list[BenchRow]]
_REGISTRY: dict[str, BenchFn] = {}


def register(name: str) -> Callable[[BenchFn], BenchFn]:
    """Decorator: register ``fn(quick: bool) -> list[BenchRow]`` under ``name``."""

    def deco(fn: BenchFn) -> BenchFn:
        if name in _REGISTRY and _REGISTRY[name] is not fn:
            raise InputError(f"benchmark {name!r} registered twice")
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
    rows: list[BenchRow] = []
    for name in chosen:
        if progress:
            progress(name)
        log.info("benchmark %s", name)
        rows.extend(_REGISTRY[name](quick))
    return rows


def _fmt(x) -> str:
    if x is None:
        return "—"
    if isinstance(x, float):
        return f"{x:.4g}"
    return str(x).replace("|", "\\|")  # a bare | would split a Markdown table cell


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
    try:
        import os

        meta["cpus"] = os.cpu_count()
    except Exception:  # pragma: no cover
        pass
    jpath = out / "bench.json"
    atomic_write_text(jpath, json.dumps({"meta": meta, "rows": [asdict(r) for r in rows]}, indent=2))
    lines = [
        "| benchmark | case | speed | error | ratios | notes |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        err = "—" if r.error is None else f"{_fmt(r.error)} ({_fmt(r.error_unit)})"
        ratios = ", ".join(f"{k}: {v:.3g}" for k, v in r.ratios.items()) or "—"
        extra = ", ".join(f"{k}={_fmt(v)}" for k, v in r.extra.items()) or ""
        lines.append(
            f"| {_fmt(r.benchmark)} | {_fmt(r.case)} | {_fmt(r.speed)} {_fmt(r.speed_unit)} | {err} "
            f"| {ratios} | {extra} |"
        )
    mpath = out / "bench.md"
    atomic_write_text(mpath, "\n".join(lines) + "\n")
    return jpath, mpath
