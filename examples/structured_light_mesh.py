"""Reconstruct a face mesh from structured-light frames: decode → triangulate → Poisson.

Run:  python examples/structured_light_mesh.py SCAN
      python examples/structured_light_mesh.py --tiny     (synthesises a tiny scan first)

The scan needs a calibrated projector in its rig (``facegeo calibrate`` finds one from the board
under the patterns). The cached ``decode`` and ``mesh`` stages of ``facegeo reconstruct`` do the
work: a one-pass streaming decoder (per-bit reliability, phase unwrapping), camera-ray ×
projector-ray triangulation with per-point σ, fusion across cameras and a trimmed Poisson
surface. On a synthetic scan the evaluation (``facegeo evaluate``) compares the mesh with the
generator's surface.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path



def reconstruct_mesh(scan: Path) -> dict:
    import trimesh

    from facegeo.evaluate import run_evaluate
    from facegeo.pipeline.reconstruct import run_reconstruct

    results = {r.name: r for r in run_reconstruct(scan, until="mesh")}
    dec, mesh = results["decode"].metrics, results["mesh"].metrics
    print(f"decode: {dec.get('valid_fraction', 0):.1%} of pixels decoded"
          + (f", exact codes {dec['exact_code_fraction']:.2%}" if "exact_code_fraction" in dec
             else ""))
    m = trimesh.load(scan / "out" / "mesh" / "mesh.ply", process=False)
    print(f"mesh: {len(m.vertices)} vertices, {len(m.faces)} faces -> "
          f"{scan / 'out' / 'mesh' / 'mesh.ply'}")
    # the stage reads no truth: its errors against a reference surface are the evaluation's
    errors = run_evaluate(scan, stages=["mesh"]).get("mesh", {})
    for key in ("points_rms_error_mm", "mesh_p95_error_mm", "normal_median_error_deg"):
        if key in errors:
            print(f"  {key}: {errors[key]:.3f}")
    return {**mesh, **errors}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scan", nargs="?", type=Path)
    ap.add_argument("--tiny", action="store_true", help="synthesise a tiny scan first")
    a = ap.parse_args(argv)
    scan = a.scan
    if a.tiny:
        from facegeo.synth.capture import generate_scan

        scan = Path(tempfile.mkdtemp(prefix="facegeo-slmesh-")) / "scan"
        generate_scan(scan, preset="tiny")
    if scan is None:
        ap.error("give SCAN (or --tiny)")
    reconstruct_mesh(scan)
    return 0


if __name__ == "__main__":
    from facegeo.cli import run_script  # one-line errors and exit statuses, as the CLI

    run_script(main)
