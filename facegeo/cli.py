"""The ``facegeo`` command line. Only this module prints or shows progress."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from facegeo import __version__
from facegeo.errors import FacegeoError

log = logging.getLogger("facegeo")


def _progress_factory(enabled: bool):
    """Return ``(tick, close)``: tick(stage, done, total) drives one tqdm bar per stage."""
    bars = {}
    if not enabled:
        return (lambda stage, done, total: None), (lambda: None)
    from tqdm import tqdm

    def tick(stage, done, total):
        bar = bars.get(stage)
        if bar is None:
            for b in bars.values():
                b.close()
            bar = bars[stage] = tqdm(total=total, desc=f"{stage:>18}", unit="frame",
                                     leave=True, file=sys.stderr, dynamic_ncols=True)
        bar.n = done
        bar.refresh()

    def close():
        for b in bars.values():
            b.close()

    return tick, close


def _cmd_synth(args) -> int:
    from facegeo.synth.capture import generate_scan

    tick, close = _progress_factory(not args.quiet)
    try:
        summary = generate_scan(args.out, args.preset, head=args.head, units=args.units,
                                seed=args.seed, noise=args.noise, skin=args.skin,
                                olat_format=args.olat_format,
                                overwrite=args.overwrite,
                                progress=tick)
    finally:
        close()
    secs = " ".join(f"{k}={v:.1f}s" for k, v in summary.seconds.items())
    print(f"wrote {summary.root}: preset {summary.preset}, {summary.n_cameras} cameras "
          f"{summary.image_size[0]}x{summary.image_size[1]}, {summary.n_lights} lights, "
          f"{summary.n_faces} triangles, {summary.frames_written} frames "
          f"({summary.frames_per_second:.1f} frames/s; {secs})")
    return 0


def _cmd_info(args) -> int:
    from facegeo.capture.scan import load_scan, summarize

    scan = load_scan(args.scan, check="full" if args.full else "quick")
    print(summarize(scan))
    print("valid" + (" (every frame decoded)" if args.full else " (quick check: run with --full "
                                                              "to decode every frame)"))
    return 0


def _cmd_bench(args) -> int:
    from facegeo.pipeline.bench import registered, run_benchmarks, write_reports

    if args.list:
        print("\n".join(registered()))
        return 0
    rows = run_benchmarks(args.names or None, quick=args.quick,
                          progress=lambda n: print(f"running {n} ...", file=sys.stderr))
    jpath, mpath = write_reports(rows, args.out)
    print(mpath.read_text())
    print(f"wrote {jpath} and {mpath}")
    return 0


def _cmd_demo(args) -> int:
    """Main job on the embedded default: synthesise the small scan (if absent) and summarise."""
    from facegeo.capture.scan import load_scan, summarize
    from facegeo.synth.capture import generate_scan

    root = Path(args.scan)
    if (root / "scan.toml").exists() and not args.regenerate:
        print(f"using the existing synthetic scan {root} (--regenerate to rebuild it)")
    else:
        print(f"synthesising the default scan (preset {args.preset}) into {root} ...")
        tick, close = _progress_factory(not args.quiet)
        t0 = time.perf_counter()
        try:
            generate_scan(root, args.preset, seed=args.seed, overwrite=args.regenerate, progress=tick)
        finally:
            close()
        print(f"synthesised in {time.perf_counter() - t0:.1f} s")
    scan = load_scan(root)
    print(summarize(scan))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="facegeo",
        description="Light-stage face capture to a relightable, re-viewable reflectance field "
                    "(Debevec et al. 2000).",
    )
    p.add_argument("--version", action="version", version=f"facegeo {__version__}")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv: debug)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    s = sub.add_parser("synth", help="write a synthetic light-stage scan with ground truth")
    s.add_argument("out", help="scan directory to create")
    s.add_argument("--preset", default="small", choices=["tiny", "small", "paper"],
                   help="capture size: tiny (seconds; test fixtures), small (demo default), "
                        "paper (2 cameras 480x720, 64x32 lights)")
    s.add_argument("--head", default="procedural",
                   help="'procedural' (default) or a mesh file (OBJ/PLY/GLB, +Y up, facing +Z)")
    s.add_argument("--units", default="cm", choices=["cm", "mm", "m"], help="units of --head mesh")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--skin", default="regional",
                   help="ground-truth skin colour model: 'regional' (default) or "
                        "'spectral[:light|medium|olive|dark]' (Donner & Jensen 2006)")
    s.add_argument("--olat-format", default="exr", choices=["exr", "png16"],
                   help="OLAT frames as linear EXR (default) or 16-bit sRGB PNG with an exposure")
    s.add_argument("--noise", type=float, default=0.0,
                   help="sensor noise, fraction of white level (default 0: noise-free)")
    s.add_argument("--overwrite", action="store_true", help="replace an existing scan at OUT")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    s.set_defaults(func=_cmd_synth)

    s = sub.add_parser("info", help="summarise and validate a scan directory")
    s.add_argument("scan")
    s.add_argument("--full", action="store_true", help="decode every frame (slower)")
    s.set_defaults(func=_cmd_info)

    s = sub.add_parser("bench", help="run registered benchmarks (speed against error)")
    s.add_argument("names", nargs="*", help="benchmarks or prefixes (default: all)")
    s.add_argument("--quick", action="store_true", help="smaller problem sizes")
    s.add_argument("--out", default="bench-out", help="folder for bench.json and bench.md")
    s.add_argument("--list", action="store_true", help="list the registered benchmarks")
    s.set_defaults(func=_cmd_bench)

    s = sub.add_parser("demo", help="the main job on the embedded default (a synthetic scan)")
    s.add_argument("scan", nargs="?", default="scans/demo", help="scan directory (default scans/demo)")
    s.add_argument("--preset", default="small", choices=["tiny", "small", "paper"])
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--regenerate", action="store_true", help="rebuild the scan even if present")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    s.set_defaults(func=_cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except FacegeoError as exc:
        print(f"facegeo {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
