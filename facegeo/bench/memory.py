"""The machine's memory read bandwidth, measured in this run: the physical limit of every
streaming benchmark (decode reads its frames once; relighting reads the field once per map).

:func:`facegeo.bench.read_bandwidth` measures it once per run (cached); this benchmark
reports each method and thread count as a row so the limit the other rows cite is visible: a
numpy sum (1 thread), the compiled pure read (:func:`facegeo.bench.pure_read_kernel`,
1 … N Python threads) and OpenBLAS ``sgemv`` (1 … N BLAS threads). A benchmark on ``n``
threads is held against the strongest of them at ≤ ``n`` threads
(:meth:`~facegeo.bench.Bandwidth.at_threads`) — here usually the pure read, up to
1.4× what ``sgemv`` reads. A method that could not run (the pure read without numba) is named
with its reason in every row's ``not measured``.
"""

from __future__ import annotations

from facegeo.bench import BenchRow, _method_threads, read_bandwidth, register


@register("memory.read_bandwidth")
def bench_read_bandwidth(quick: bool) -> list[BenchRow]:
    bw = read_bandwidth()
    rows = []
    for method, gbps in bw.by_method.items():
        n = _method_threads(method)
        extra = {"MiB": round(bw.nbytes / 2**20), "best of": 3,
                 # the figure a job on n threads is held against (Bandwidth.at_threads)
                 "sets the limit at this thread count": method == bw.method_at(n)}
        if bw.unavailable:
            extra["not measured"] = "; ".join(f"{k}: {v}" for k, v in bw.unavailable.items())
        rows.append(BenchRow("memory.read_bandwidth", f"read a float32 array once: {method}",
                             gbps, "GB/s", extra=extra, threads=n))
    return rows
