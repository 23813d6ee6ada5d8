"""The machine's memory read bandwidth, measured in this run: the physical limit of every
streaming benchmark (decode reads its frames once; relighting reads the field once per map).

:func:`facegeo.pipeline.bench.read_bandwidth` measures it once per run (cached); this benchmark
reports each method and thread count as a row so the limit the other rows cite is visible.
"""

from __future__ import annotations

from facegeo.pipeline.bench import BenchRow, _method_threads, read_bandwidth, register


@register("memory.read_bandwidth")
def bench_read_bandwidth(quick: bool) -> list[BenchRow]:
    bw = read_bandwidth()
    return [
        BenchRow(
            "memory.read_bandwidth", f"read a float32 array once: {method}", gbps, "GB/s",
            extra={"MiB": round(bw.nbytes / 2**20), "best of": 3},
            threads=_method_threads(method),
        )
        for method, gbps in bw.by_method.items()
    ]
