"""Relight a captured camera view with an HDR environment map (Debevec et al. 2000, Eq. 4).

Run:  python examples/relight_view.py SCAN ENV.exr [--camera NAME] [--rotate DEG] [--out DIR]
      python examples/relight_view.py --tiny [--out DIR]     (synthesises a tiny scan first and
                                                               uses a procedural coloured map)

What it shows, in library calls (the CLI's ``facegeo relight`` does the same with caching and
metrics):

1. ``load_scan`` validates the scan and hands out linear OLAT frames lazily;
2. ``read_envmap`` reads a lat-long ``.exr``/``.hdr`` map (or ``axis_lobe_map`` makes one whose
   six coloured lobes pin the orientation: +x red, +y green, +z blue, −x cyan, −y magenta,
   −z yellow);
3. ``light_stage_weights`` integrates the map over each light-stage cell (δA applied once);
4. ``relight_scan_view`` sums the frames with those weights, reading only lights that carry
   energy;
5. the image is written as EXR (linear) and as a tone-mapped PNG.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from facegeo.capture import imageio
from facegeo.capture.scan import Scan, load_scan
from facegeo.lighting import envmap
from facegeo.lighting.relight import relight_scan_view
from facegeo.pipeline.relight import tone_map


def relight(scan: Scan, env: envmap.EnvironmentMap, camera: str | None, out: Path) -> Path:
    camera = camera or scan.camera_names[0]
    lights = scan.rig.lights
    w = envmap.light_weights(env, lights)  # the θ × φ grid or a real rig's list of lights
    active = int(np.count_nonzero(np.any(w != 0, axis=1)))
    img = relight_scan_view(scan, camera, w, normalize_color=True)
    out.mkdir(parents=True, exist_ok=True)
    imageio.write_image(out / f"relit_{camera}.exr", img)
    png, exposure = tone_map(img)
    path = imageio.write_image(out / f"relit_{camera}.png", png)
    print(f"{camera}: {active} of {lights.n_lights} lights carry energy; mean radiance "
          f"{[round(float(c), 4) for c in img.reshape(-1, 3).mean(0)]}; PNG exposure x{exposure:.3g}")
    print(f"wrote {out / f'relit_{camera}.exr'} and {path}")
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scan", nargs="?", type=Path)
    ap.add_argument("env", nargs="?", type=Path)
    ap.add_argument("--camera")
    ap.add_argument("--rotate", type=float, default=0.0, help="degrees about +Y")
    ap.add_argument("--tiny", action="store_true", help="synthesise a tiny scan and use a "
                    "procedural map")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    if a.tiny:
        from facegeo.synth.capture import generate_scan

        # the scan lives only as long as the relight; the images stay (in --out, or a folder
        # of their own that the script prints)
        out = a.out or Path(tempfile.mkdtemp(prefix="facegeo-example-relit-"))
        with tempfile.TemporaryDirectory(prefix="facegeo-example-") as tmp:
            scan_dir = Path(tmp) / "scan"
            generate_scan(scan_dir, preset="tiny")
            relight(load_scan(scan_dir), envmap.axis_lobe_map(32), a.camera, out)
        return 0
    if a.scan is None or a.env is None:
        ap.error("give SCAN and ENV (or --tiny)")
    scan = load_scan(a.scan)  # a wrong SCAN fails before the map is read
    env = envmap.read_envmap(a.env, rotate_deg=a.rotate)
    relight(scan, env, a.camera, a.out or a.scan / "out" / "example_relight")
    return 0


if __name__ == "__main__":
    from facegeo.cli import run_script  # one-line errors and exit statuses, as the CLI

    run_script(main)
