"""Benchmarks of the synthetic capture generator: frames per second per stage, with the storage
error of the OLAT frames (disk against the reference renderer) as the error column.

Threads: the reference renderer shades lights on 2 worker threads (``olat_images(workers=2)``);
numpy inside may use the BLAS pool too. ``cpu_seconds`` (process CPU time, all threads) is the
figure to compare across runs on a shared machine, where wall time follows the load. There is no
outside baseline for the generator."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from facegeo.bench import BenchRow, register


@register("synth.generate")
def bench_generate(quick: bool) -> list[BenchRow]:
    from facegeo.capture.scan import load_scan
    from facegeo.synth.capture import generate_scan
    from facegeo.synth.render import load_ground_truth

    preset = "tiny" if quick else "small"
    with tempfile.TemporaryDirectory(prefix="facegeo-bench-synth-") as tmp:
        root = Path(tmp) / preset
        t0, c0 = time.perf_counter(), time.process_time()
        summary = generate_scan(root, preset, seed=0)
        wall = time.perf_counter() - t0
        cpu = time.process_time() - c0  # every thread's CPU: the figure a loaded machine keeps
        scan = load_scan(root)
        renderer = load_ground_truth(scan)
        rig = renderer.rig  # the true rig the frames were rendered with
        worst = 0.0
        for cam in rig.cameras:  # every OLAT frame written, against the reference render
            for l, ref in renderer.olat_images(cam, rig.lights):
                disk = scan.olat_frame(cam.name, l)
                scale = max(float(ref.max()), 1e-12)
                worst = max(worst, float(np.abs(disk - ref).max()) / scale)
    n_olat = summary.n_cameras * summary.n_lights
    rows = [
        BenchRow("synth.generate", f"{preset}: whole scan", summary.frames_written / wall, "frames/s",
                 error=worst, error_unit="every OLAT frame: max abs(disk − reference) / max",
                 extra={"frames": summary.frames_written, "seconds": round(wall, 2),
                        "cpu_seconds": round(cpu, 2),
                        "pixels": summary.image_size[0] * summary.image_size[1],
                        "triangles": summary.n_faces},
                 threads=2),
        BenchRow("synth.generate", f"{preset}: OLAT stage", n_olat / summary.seconds["olat"], "frames/s",
                 extra={"lights": summary.n_lights, "cameras": summary.n_cameras},
                 threads=2),
    ]
    rows[0].extra.update({f"{k}_s": round(v, 2) for k, v in summary.seconds.items()})
    return rows
