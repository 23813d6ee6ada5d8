"""Render a turntable of novel views of a reconstructed face under an environment map.

Run:  python examples/turntable.py SCAN [--step 30] [--env sky|studio|FILE.exr] [--naive]
      python examples/turntable.py --tiny [--step 60]    (synthesises a tiny scan first)

Each frame is a view of the rig's frontal camera orbited about the vertical axis through the
head (``orbit:front:DEGREES``), rendered by :func:`facegeo.pipeline.render.run_render`: Embree
rays → atlas texels → each source camera's reflectance function resynthesised for the new view
(Debevec et al. 2000, Eq. 9, with the cross-validated shrinkage of docs/render.md) → relit
(Eq. 4) → blended. The stages it needs (atlas, project,
fit) run first and are cached, so a second turntable reuses them. The frames are written to
``SCAN/out/views/`` and gathered into ``turntable.gif``.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np


def turntable(scan: Path, *, step: float, env: str, naive: bool, out_gif: Path) -> list[dict]:
    from PIL import Image

    from facegeo.pipeline.reconstruct import run_reconstruct
    from facegeo.pipeline.render import run_render

    run_reconstruct(scan, until="fit")  # cached after the first time
    angles = np.arange(-90.0, 90.0 + 1e-9, step)
    frames, results = [], []
    for a in angles:
        m = run_render(scan, camera_spec=f"orbit:front:{a:g}", env=env, resynthesis=not naive,
                       baseline=False, name=f"turntable_{a:+04.0f}")
        results.append(m)
        frames.append(Image.open(scan / "out" / "views" / m["files"]["png"]).convert("RGB"))
        psnr = m.get("psnr_db")
        print(f"{a:+6.1f} deg: {m['seconds']:.1f} s" + (f", PSNR {psnr:.1f} dB against the "
                                                         "generator" if psnr else ""))
    frames[0].save(out_gif, save_all=True, append_images=frames[1:], duration=400, loop=0)
    print(f"wrote {out_gif} ({len(frames)} frames)")
    return results


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scan", nargs="?", type=Path)
    ap.add_argument("--step", type=float, default=30.0, help="degrees between frames")
    ap.add_argument("--env", default="sky", help="sky, studio, or an .exr/.hdr lat-long map")
    ap.add_argument("--naive", action="store_true", help="no resynthesis (faster baseline)")
    ap.add_argument("--tiny", action="store_true", help="synthesise a tiny scan first")
    a = ap.parse_args(argv)
    if not a.step > 0:
        ap.error("--step must be > 0")
    scan = a.scan
    if a.tiny:
        from facegeo.synth.capture import generate_scan

        scan = Path(tempfile.mkdtemp(prefix="facegeo-turntable-")) / "scan"
        generate_scan(scan, preset="tiny")
    if scan is None:
        ap.error("give SCAN (or --tiny)")
    turntable(scan, step=a.step, env=a.env, naive=a.naive, out_gif=scan / "out" / "turntable.gif")
    return 0


if __name__ == "__main__":
    from facegeo.cli import run_script  # one-line errors and exit statuses, as the CLI

    run_script(main)
