"""The ``facegeo`` command line. Only this module prints or shows progress."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import tempfile
import time
import traceback
from pathlib import Path

from facegeo import __version__
from facegeo.errors import FacegeoError, InputError
from facegeo.checks import fmt_value

log = logging.getLogger("facegeo")


def _progress_factory(enabled: bool):
    """Return ``(tick, close)``: tick(stage, done, total) drives one tqdm bar per stage."""
    bars = {}
    stream = []  # the console stream the bars write to, opened with the first bar
    if not enabled:
        return (lambda stage, done, total: None), (lambda: None)
    from tqdm import tqdm

    from facegeo.capture.imageio import console_stream

    def tick(stage, done, total):
        bar = bars.get(stage)
        if bar is None:
            for b in bars.values():
                b.close()
            if not stream:  # the real stderr, past the reads' filtering of native noise
                stream.append(console_stream())
            bar = bars[stage] = tqdm(total=total, desc=f"{stage:>18}", unit="frame",
                                     leave=True, file=stream[0], dynamic_ncols=True)
        bar.n = done
        bar.refresh()

    def close():
        for b in bars.values():
            b.close()
        bars.clear()
        while stream:
            stream.pop().close()

    return tick, close


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr (exit status 2)."""

    def __init__(self, *a, **kw):
        kw.setdefault("formatter_class", argparse.ArgumentDefaultsHelpFormatter)
        super().__init__(*a, **kw)

    def error(self, message):  # noqa: D102 - argparse API
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _int_at_least(text: str, low: int) -> int:
    """``text`` as an integer >= ``low``; the message names the bound the option has."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got "
                                         f"{fmt_value(text)}") from None
    if v < low:
        raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {v}")
    return v


def _nonneg_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    return _int_at_least(text, 0)


def _pos_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    return _int_at_least(text, 1)


def _finite_float(text: str, expected: str, ok) -> float:
    """``text`` as a finite float for which ``ok(v)`` holds, else "expected {expected}"."""
    import math

    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {fmt_value(text)}") from None
    if not (math.isfinite(v) and ok(v)):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text}")
    return v


def _nonneg_float(text: str) -> float:
    """argparse type: a finite number >= 0."""
    return _finite_float(text, "a finite number >= 0", lambda v: v >= 0)


def _pos_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    return _finite_float(text, "a finite number > 0", lambda v: v > 0)


#: Largest |angle| of an environment rotation on the command line, degrees (a full turn).
_MAX_ROTATE_DEG = 360.0


def _rotate_deg(text: str) -> float:
    """argparse type: an environment rotation in degrees, finite, |angle| <= 360."""
    return _finite_float(text, f"a finite angle in degrees, |angle| <= {_MAX_ROTATE_DEG:g}",
                         lambda v: abs(v) <= _MAX_ROTATE_DEG)


def _check_output_dir(path: str | os.PathLike, what: str) -> Path:
    """Check that ``path`` is, or can be created as, a writable directory; return it.

    Run before any work starts, so a typo in an output path fails in a second instead of after
    a long computation. The nearest existing ancestor must be a directory in which a file can
    actually be created (a real probe, not ``os.access``: root ignores permission bits, and
    read-only mounts or ``/proc`` refuse anyway).

    Every message names the option, the path given and what is wrong with it (``--out
    /proc/foo: cannot create it: /proc, its nearest existing folder, refuses new files (...)``),
    not only the operating system's reason: creating a file in ``/proc`` fails with "No such
    file or directory", which says nothing about which path or why.

    Raises
    ------
    InputError
        ``path`` (or an ancestor) is an existing file, or no file can be created there.
    """
    from facegeo.errors import InputError

    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InputError(f"{what} {p}: an existing file, not a directory; expected a directory "
                         "(or a path to create one at)")
    probe = p
    while not probe.exists():
        if probe.parent == probe:  # pragma: no cover - the root always exists
            break
        probe = probe.parent
    if not probe.is_dir():
        raise InputError(f"{what} {p}: cannot create it: {probe} is a file, not a directory")
    try:
        tempfile.TemporaryFile(dir=probe).close()
    except OSError as exc:
        why = f"a test file there was refused: {exc.strerror or exc}"
        if probe == p:
            raise InputError(f"{what} {p}: cannot write in this directory ({why}); expected a "
                             "writable directory") from exc
        raise InputError(f"{what} {p}: cannot create it: {probe}, its nearest existing folder, "
                         f"refuses new files ({why}); expected a path in a writable "
                         "directory") from exc
    return p


def _sl_missing_arg(values) -> dict | None:
    """``--sl-missing CAM=FRAME[,FRAME...]`` or ``CAM=PATTERN`` (repeated) as the generator's
    ``sl_missing`` mapping."""
    if not values:
        return None
    from facegeo.synth.sl_conditions import LOST_FRAME_PATTERNS

    out: dict = {}
    for v in values:
        cam, sep, frames = v.partition("=")
        if not sep or not cam or not frames:
            raise InputError(f"--sl-missing: expected CAMERA=FRAME[,FRAME...] or CAMERA=PATTERN "
                             f"({', '.join(LOST_FRAME_PATTERNS)}), got {v!r}")
        out[cam] = frames if frames in LOST_FRAME_PATTERNS else [
            f.strip() for f in frames.split(",") if f.strip()]
    return out


def _cmd_synth(args) -> int:
    from facegeo.synth.capture import generate_scan

    _check_output_dir(args.out, "OUT")
    effects = None
    if args.sl_subsurface != "none" or args.sl_interreflection > 0:
        effects = {"subsurface": args.sl_subsurface, "interreflection": args.sl_interreflection}
    tick, close = _progress_factory(not args.quiet)
    try:
        summary = generate_scan(args.out, args.preset, head=args.head, units=args.units,
                                seed=args.seed, noise=args.noise, skin=args.skin,
                                olat_format=args.olat_format,
                                overwrite=args.overwrite,
                                progress=tick, sl_effects=effects,
                                sl_codes=tuple(c.strip() for c in args.sl_codes.split(",")),
                                sl_phase_steps=args.sl_phase_steps,
                                projector_scale=args.projector_scale,
                                sl_missing=_sl_missing_arg(args.sl_missing),
                                calib_board=args.calib_board, witness=args.witness,
                                light_error_deg=args.light_error,
                                backdrop=args.backdrop)
    finally:
        close()
    secs = " ".join(f"{k}={v:.1f}s" for k, v in summary.seconds.items())
    print(f"wrote {summary.root}: preset {summary.preset}, {summary.n_cameras} cameras "
          f"{summary.image_size[0]}x{summary.image_size[1]}, {summary.n_lights} lights, "
          f"{summary.n_faces} triangles, {summary.frames_written} frames "
          f"({summary.frames_per_second:.1f} frames/s; {secs})")
    if summary.kept:
        print(f"kept {len(summary.kept)} file(s) facegeo did not write: "
              f"{', '.join(summary.kept[:5])}{' ...' if len(summary.kept) > 5 else ''}")
    return 0


#: ``facegeo info`` lists at most this many frame warnings unless -v is given.
_INFO_MAX_WARNINGS = 20


def _cmd_import(args) -> int:
    from facegeo.capture.scan import summarize

    if (args.dataset is None) == (args.description is None):
        raise InputError("give --dataset KIND (a public data set) or --description DESC.toml "
                         "(your own folder), exactly one")
    if args.dataset is not None:
        if args.rig is not None:
            raise InputError("--rig goes with --description; a --dataset writes its own rig")
        from facegeo.capture.datasets import import_dataset

        scan = import_dataset(args.dataset, args.src, args.dest,
                              mode="copy" if args.copy else "link", scale=args.scale)
    else:
        if args.scale is not None:
            raise InputError("--scale goes with --dataset (a known data set's frames are "
                             "reduced on import); a --description imports frames as they are")
        from facegeo.capture.importer import import_folder

        scan = import_folder(args.src, args.dest, args.description, rig=args.rig,
                             mode="copy" if args.copy else None)
    print(summarize(scan))
    print(f"imported into {scan.root}")
    return 0


def _cmd_push(args) -> int:
    """``facegeo push SCAN URL``: the scan's input files into ``URL/scan/`` (docs/scale.md §3)."""
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline._scan_store import put_scan

    scan = load_scan(args.scan)
    tick, close = _progress_factory(not args.quiet)
    try:
        done = put_scan(scan, args.url, progress=tick)
    finally:
        close()
    print(f"pushed {done['files']} files ({done['bytes'] / 1e6:.1f} MB) of {scan.root} to "
          f"{done['location']}")
    return 0


def _cmd_info(args) -> int:
    from facegeo.capture.scan import load_scan, summarize

    scan = load_scan(args.scan, check="full" if args.full else "quick")
    print(summarize(scan))
    fc = scan.frame_check
    checked = f"checked headers of {fc.n_headers} frames (size, channels, sample type, truncation)"
    if args.full:
        checked += f"; decoded {fc.n_decoded} frames (NaN, inf, negative, all-black, saturated)"
    print(checked)
    warnings = fc.warnings
    if warnings:
        print(f"{len(warnings)} frame warning(s):")
        shown = warnings if args.verbose else warnings[:_INFO_MAX_WARNINGS]
        for w in shown:
            try:
                rel = w.path.relative_to(scan.root)
            except ValueError:  # pragma: no cover - frame_path keeps files inside the root
                rel = w.path
            print(f"  warning: {rel}: {w.message}")
        if len(shown) < len(warnings):
            print(f"  ... and {len(warnings) - len(shown)} more (-v lists them all)")
    print("valid" + (" (every frame decoded)" if args.full else " (quick check: run with --full "
                                                              "to decode every frame)"))
    return 0


def _cmd_bench(args) -> int:
    from facegeo.bench import registered, run_benchmarks, write_reports

    if args.list:
        print("\n".join(registered()))
        return 0
    _check_output_dir(args.out, "--out")
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
        _check_output_dir(root, "SCAN")
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
    print("reconstructing: the whole chain, calibrated rig and reconstructed mesh (stages "
          "cached under out/; a second run does no work):")
    _run_reconstruct(root, args)
    if args.no_diagnostic:
        return 0
    print("the stage-alone pass: the same stages fed the generator's rig and mesh (a "
          "diagnostic, cached under out/diagnostic/):")
    _run_diagnostic(root, args)
    return 0


def _run_diagnostic(root: Path, args) -> None:
    """:func:`facegeo.pipeline.reconstruct.run_diagnostic` with one line per stage, then the
    chain's figures beside the stage-alone ones and the report rewritten with both."""
    from facegeo.pipeline.reconstruct import DIAGNOSTIC_DIR, run_diagnostic
    from facegeo.pipeline.report import chain_and_stage_alone_table, write_report

    out = root / "out"
    tick, close = _progress_factory(not args.quiet)
    try:
        with _engine(args) as engine:
            run_diagnostic(root, progress=tick, engine=engine,
                           on_stage=lambda r: (close(), print(_stage_line(r))))
    finally:
        close()
    write_report(out / DIAGNOSTIC_DIR, title=f"facegeo report: {root.name}, stages alone")
    print("the chain's figures beside the stage-alone ones (evaluate):")
    print(chain_and_stage_alone_table(out))
    _write_report(out, quiet=True)


def _cmd_calibrate(args) -> int:
    """Calibrate the scan's cameras (and projector, when it has board views) from ``calib/``."""
    from facegeo.pipeline.calibrate import SUMMARY_RECORD, run_calibrate

    if args.out is not None:
        _check_output_dir(args.out, "--out")
    # "projector: not calibrated (...)" is printed below, beside the table: not its warning too
    with _without_records("facegeo.pipeline.calibrate", SUMMARY_RECORD, "projector"), \
            _without_records("facegeo.pipeline._calibrate_projector", SUMMARY_RECORD,
                             "projector_skipped"):
        m = run_calibrate(args.scan, args.out, model=args.model, loss=args.loss,
                          reference=args.reference, legacy=args.legacy_board,
                          cross_validation=not args.no_cross_validation,
                          progress=None if args.quiet else (lambda s: print(s, file=sys.stderr)))
    # the errors against the scan's references are the evaluation's (the stage reads none)
    from facegeo.capture.scan import load_scan
    from facegeo.evaluate.intrinsics import with_calibration_errors

    m = with_calibration_errors(load_scan(args.scan), m, Path(args.out) if args.out
                                else Path(args.scan) / "out" / "calibrate")
    # (header, metrics key[, fallback key]): the errors against the generator's truth on a
    # synthetic scan, else against a reference calibration shipped with the data (real scans)
    cols = (("model", "model"), ("rms px", "reprojection_rms_px"), ("views", "views_used"),
            ("cv px", "cross_validation_px"), ("loo px", "leave_one_out_held_out_rms_px"),
            ("unc px", "projection_uncertainty_rms_px"),
            ("focal err", "focal_rel_error", "reference_focal_rel_error"),
            ("pp err px", "principal_point_error_px", "reference_principal_point_error_px"))
    cams = m.get("cameras", {})
    ref = any("focal_rel_error" not in cm and "reference_focal_rel_error" in cm
              for cm in cams.values())
    print("camera      " + "  ".join(f"{c[0]:>10}" for c in cols)
          + ("   (errors against the data set's reference calibration)" if ref else ""))
    for name, cm in cams.items():
        cells = []
        for c in cols:
            v = next((cm[k] for k in c[1:] if cm.get(k) is not None), None)
            if isinstance(v, str):
                cells.append(f"{v:>10.10}")
            else:
                cells.append(f"{v:>10.4g}" if isinstance(v, (int, float)) else f"{'-':>10}")
        print(f"{name:<12}" + "  ".join(cells))
    _print_skipped_views(Path(args.out) if args.out else Path(args.scan) / "out" / "calibrate")
    proj = m.get("projector") or {}
    for why in proj.get("skipped") or ():  # "projector view 0 cam_left: <reason>"
        print(f"skipped {why}")
    if proj.get("calibrated") is False:  # why, and what the calibrated rig.json holds instead
        print(proj["summary"])
    elif proj:
        print("projector: " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                         for k, v in proj.items()
                                         if not isinstance(v, (dict, list))))
    print(f"wrote {args.out or Path(args.scan) / 'out' / 'calibrate'}")
    return 0


@contextlib.contextmanager
def _without_records(logger: str, attr: str, value: str):
    """Drop the records of ``logger`` whose attribute ``attr`` is ``value`` while the block
    runs (a library warning that repeats a line the command prints itself)."""
    def keep(record) -> bool:
        return getattr(record, attr, None) != value

    target = logging.getLogger(logger)
    target.addFilter(keep)
    try:
        yield
    finally:
        target.removeFilter(keep)


def _print_skipped_views(out: Path) -> None:
    """One line per calibration view the detection skipped, with its reason (from the
    stage's ``detections.json``)."""
    try:
        dets = json.loads((out / "detections.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return
    for cam, views in dets.items() if isinstance(dets, dict) else ():
        for v in views if isinstance(views, list) else ():
            if isinstance(v, dict) and not v.get("found", True):
                print(f"skipped {cam} {v.get('name')}: {v.get('reason')}")


def _print_metrics(title: str, metrics: dict) -> None:
    """A short, flat view of a stage's metrics (nested dicts one level deep)."""
    def fmt(v):
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    def flat(d: dict) -> str:
        return ", ".join(f"{ik}={fmt(iv)}" for ik, iv in d.items()
                         if not isinstance(iv, (dict, list)))

    print(title)
    for k, v in metrics.items():
        if isinstance(v, dict) and v and all(isinstance(iv, dict) for iv in v.values()):
            print(f"  {k}:")  # one entry per camera (say): a line each
            for ik, iv in v.items():
                print(f"    {ik}: {flat(iv)}")
        elif isinstance(v, dict):
            print(f"  {k}: {flat(v)}")
        elif not isinstance(v, list):
            print(f"  {k}: {fmt(v)}")


def _cmd_atlas(args) -> int:
    """The ``atlas`` stage: in ``SCAN/out`` the cached stage of ``facegeo reconstruct`` with
    these settings (so later stages reuse it); with ``--out``, on its own, outside the cache."""
    from facegeo.pipeline.project import run_atlas
    from facegeo.surface.atlas import check_atlas_settings

    settings = {"texels_per_mm": None if args.size is not None else args.texels_per_mm,
                "size": args.size, "padding": args.padding,
                "split_faces": args.split_faces or None, "repair": args.repair}
    check_atlas_settings(texels_per_mm=settings["texels_per_mm"], size=args.size,
                         padding=args.padding)  # before the mesh stages the chain runs first
    if args.out is None:
        results = _run_reconstruct(args.scan, args, until="atlas", settings={"atlas": settings})
        _print_metrics("atlas", _stage_metrics(results, "atlas"))
        return 0
    _check_output_dir(args.out, "--out")
    m = run_atlas(args.scan, args.out, mesh=_standalone_mesh(args), **settings)
    _print_metrics("atlas", m)
    return 0


def _standalone_mesh(args) -> str:
    """``--mesh`` for a stage run outside the cache: ``auto`` is the synthetic scan's true
    mesh (a reconstruction needs the cached stages: run without ``--out``)."""
    if args.mesh != "auto":
        if args.mesh == "reconstructed":
            raise InputError("--mesh reconstructed needs the cached mesh stage: run without "
                             "--out, or give the mesh file (SCAN/out/mesh/mesh.ply)")
        return args.mesh
    return "ground_truth"


def _stage_metrics(results, name: str) -> dict:
    """The metrics of stage ``name`` among a pipeline run's results (ran or cached)."""
    return next((r.metrics for r in results if r.name == name), {})


def _cmd_project(args) -> int:
    """The ``project`` stage: in ``SCAN/out`` the cached stage of ``facegeo reconstruct`` (the
    atlas before it, cached too); with ``--out`` or ``--camera``, on its own, outside the
    cache."""
    from facegeo.pipeline.project import run_project

    from facegeo.pipeline.reconstruct import RIG_CHOICES

    # --gt-lights: the evaluation's comparison with the generator, shown beside the stage's
    gt = {"gt_lights": args.gt_lights} if hasattr(args, "gt_lights") else {}
    kw = {} if args.shadow_taps else {"shadow_taps": False}
    if args.field_format != "npy":
        kw["field_format"] = args.field_format
    # a rig file is not one of the pipeline's rigs: the stage on its own, as with --out
    cached = args.out is None and args.camera is None and args.rig in (None, *RIG_CHOICES)
    if args.store is not None and not cached:
        kw["store"] = args.store  # on its own (in the pipeline: run_reconstruct(store=))
    if cached:
        from facegeo.capture.scan import load_scan
        from facegeo.evaluate.projection import has_projection_truth, with_projection_figures

        args.rig = args.rig or "auto"
        results = _run_reconstruct(args.scan, args, until="project",
                                   settings={"project": {"dtype": args.dtype, **kw}})
        m = _stage_metrics(results, "project")
        scan = load_scan(args.scan)
        if has_projection_truth(scan) and (scan.out_dir / "project" / "rig.json").is_file():
            m = with_projection_figures(scan, scan.out_dir, m, **gt)
        _print_metrics("project", m)
        return 0
    kw.update(gt)
    if args.out is not None:
        _check_output_dir(args.out, "--out")
    with _engine(args) as engine:  # --workers / --scheduler hold for the stage on its own too
        m = run_project(args.scan, args.out, rig=args.rig, mesh=_standalone_mesh(args),
                        cameras=args.camera, dtype=args.dtype, engine=engine,
                        lights_per_task=args.lights_per_task, **kw)
    _print_metrics("project", m)
    return 0


def _lights_per_task_option(s) -> None:
    """``--lights-per-task N`` of the projection (project, reconstruct; docs/scale.md §1)."""
    s.add_argument("--lights-per-task", type=_pos_int, default=None, metavar="N",
                   help="project: split each camera's projection into tasks of N lights "
                        "(rounded up to whole chunks of the field), the same products; default: "
                        "one task per camera, split automatically on --workers / --scheduler "
                        "when the scan has fewer cameras than 2 x workers, not a multiple of "
                        "them (docs/scale.md)")


def _store_option(s) -> None:
    """``--store URL`` of the decode, the projection and the fit (decode, mesh, project, fit,
    reconstruct; docs/scale.md §3)."""
    s.add_argument("--store", default=None, metavar="URL",
                   help="a folder or fsspec store (s3://bucket/prefix) for tasks that write "
                        "to no shared disk: the decode's tasks write through it (and read "
                        "their frames from URL/scan/ once 'facegeo push' put the scan there); "
                        "the cameras' reflectance fields stay there as Zarr arrays, linked "
                        "from the output folder; the fit's tasks write D and their parameters "
                        "through it (docs/scale.md)")


def _add_envmap_options(s) -> None:
    """``--projection`` and ``--envmap-convention`` of an environment file (relight, render;
    docs/lighting.md; the names of facegeo.lighting.envmap.PROJECTIONS / LATLONG_CONVENTIONS,
    listed here so that --help needs no numpy)."""
    s.add_argument("--projection", choices=["latlong", "mirror-ball", "angular", "cube",
                                            "mirrorball"], default="latlong",
                   help="how the map file stores directions: latlong (2:1), mirror-ball (1:1; "
                        "'mirrorball' is the same), angular (1:1), cube (horizontal cross 4:3 "
                        "or strip 6:1)")
    s.add_argument("--envmap-convention", choices=["facegeo", "u0_at_plus_z", "blender"],
                   default="facegeo", metavar="NAME",
                   help="orientation of a lat-long file: facegeo (+Z at the centre column, "
                        "OpenEXR/Mitsuba), u0_at_plus_z (+Z at the left edge: the front-back "
                        "mirror image), blender (+X at the centre: Blender, three.js)")


def _cmd_relight(args) -> int:
    from facegeo.fsutil import READ_AHEAD_WORKERS
    from facegeo.lighting.envmap import SHIPPED_MAPS
    from facegeo.pipeline.relight import run_relight_maps

    if args.out is not None:
        _check_output_dir(args.out, "--out")
    for env in args.env:
        if not Path(env).exists() and env not in SHIPPED_MAPS:
            raise InputError(f"env: {env} is not a file, a folder or a shipped environment map "
                             f"({', '.join(SHIPPED_MAPS)})")
    tick, close = _progress_factory(not args.quiet)
    try:
        with _engine(args) as engine:
            run = run_relight_maps(args.scan, args.env, rotate_deg=args.rotate, view=args.view,
                                   out_dir=args.out, projection=args.projection,
                                   convention=args.envmap_convention,
                                   solid_angle="exact" if args.exact_solid_angles else "paper",
                                   progress=tick, read_ahead=READ_AHEAD_WORKERS,
                                   model=args.model, engine=engine, store=args.store)
    finally:
        close()
    for m in run["relit"]:
        what = ("directions of the fitted model" if m.get("model") == "fitted"
                else "lights lit")
        name = f"{m['env']}: " if run["maps"] > 1 else ""
        print(f"{name}{m['view']}: {m['active_lights']}/{m['n_lights']} {what}, "
              f"sum(w)/integral(L) = {', '.join(f'{r:.4f}' for r in m['energy_ratio'])}, "
              f"{m['seconds']['total']:.2f} s")
        if m.get("energy_note"):
            print(f"note: {m['energy_note']}")
        print(f"wrote {m['files']['exr']} and {m['files']['png']}")
        if "measured" in m["files"]:
            print(f"measured texels: {m['measured_texels']}/{m['texels']} "
                  f"({m['files']['measured']})")
    if run["maps"] > 1:
        print(f"{run['maps']} maps in {run['batches']} batch(es) of up to "
              f"{run['maps_per_batch']}: relit in {run['seconds']['relight']:.2f} s, "
              f"{run['seconds']['total']:.2f} s in all")
    return 0


def _stage_line(result) -> str:
    """One line per stage of a reconstruct run: ran or cached, time, the headline figures."""
    from facegeo.pipeline.report import summary_rows

    m = result.metrics
    rows = summary_rows({result.name: m})
    figs = dict(rows[0]["errors"]) if rows else {}
    for k in ("texels", "valid_fraction", "points", "faces", "error"):
        if k in m and m[k] is not None and not isinstance(m[k], (dict, list)):
            figs[k] = m[k]
    if isinstance(figs.get("error"), str) and len(figs["error"]) > 120:
        figs["error"] = figs["error"][:117] + "..."
    text = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                     for k, v in figs.items())
    if result.ran:  # and why: a user who changed nothing sees "facegeo code changed"
        what = f"ran in {result.seconds:.1f} s" + (f" ({result.reason})" if result.reason
                                                     else "")
    else:
        what = "cached (inputs unchanged)"
    return f"  {result.name:<10} {what}; {text}"


def _run_reconstruct(scan, args, *, from_stage=None, only=None, until=None,
                     settings=None, engine=None) -> list:
    """``run_reconstruct`` with progress bars, one line per stage and the report; ``scan`` is
    the scan directory or the loaded :class:`~facegeo.capture.scan.Scan`; ``engine``: an
    engine the caller holds open (default: the one of ``--workers`` / ``--scheduler``, started
    and closed here)."""
    from facegeo.pipeline.reconstruct import run_reconstruct
    from facegeo.pipeline.report import write_report

    # stage settings from the options given (only then: the default runs' cache keys stay)
    for stage, keys in (("decode", ("max_coarse_px", "rel_contrast")), ("mesh", _MESH_OPTIONS),
                        ("atlas", ("surface",)), ("fit", _FIT_OPTIONS)):
        given = {k: getattr(args, k) for k in keys if getattr(args, k, None) is not None}
        if given:
            settings = {**(settings or {}), stage: given}
    out = (Path(scan) if isinstance(scan, (str, os.PathLike)) else scan.root) / "out"
    tick, close = _progress_factory(not args.quiet)
    try:
        with (_engine(args) if engine is None else contextlib.nullcontext(engine)) as engine:
            results = run_reconstruct(scan, mesh=getattr(args, "mesh", "auto"),
                                      rig=getattr(args, "rig", "auto"), settings=settings,
                                      from_stage=from_stage, only=only, until=until,
                                      progress=tick, engine=engine,
                                      store=getattr(args, "store", None),
                                      lights_per_task=getattr(args, "lights_per_task", None),
                                      on_stage=lambda r: (close(), print(_stage_line(r))))
    except FacegeoError:
        close()
        # the report too, with the failed stage marked (metrics.json's last_run_failed); its
        # own trouble never hides the stage's error
        if (out / "metrics.json").is_file():
            with contextlib.suppress(FacegeoError, OSError):
                write_report(out)
        raise
    finally:
        close()
    _print_run(out)
    _write_report(out)
    return results


def _engine(args):
    """The engine of ``--workers`` / ``--scheduler`` / ``--memory-limit`` (in process when none
    is given; :func:`facegeo.pipeline.engine.make_engine`), to use as a context manager: a
    local cluster is closed with it, whatever happens."""
    from facegeo.pipeline.engine import make_engine

    workers, scheduler = getattr(args, "workers", None), getattr(args, "scheduler", None)
    if (workers is not None or scheduler is not None) and not args.verbose:
        import distributed  # noqa: F401  (sets its loggers to INFO when imported)

        logging.getLogger("distributed").setLevel(logging.WARNING)
    engine = make_engine(workers, scheduler, getattr(args, "memory_limit", None))
    if engine.kind != "in-process":
        limit = ("its own limit" if engine.memory_limit is None
                 else f"{engine.memory_limit / 2 ** 30:.2f} GiB")
        print(f"engine: {engine.kind}, {engine.n_workers} workers × 1 thread, {limit} each; "
              f"dashboard {engine.dashboard}")
    return engine


def _engine_options(s) -> None:
    """``--workers N`` / ``--scheduler ADDRESS`` / ``--memory-limit SIZE`` (docs/scale.md)."""
    g = s.add_mutually_exclusive_group()
    g.add_argument("--workers", type=_pos_int, default=None, metavar="N",
                   help="run the stages' tasks (decode: one per camera; project: per "
                        "camera or block of lights; fit, relight: per chunk of texels, relight "
                        "per batch of maps; render: one per view) on a local "
                        "Dask cluster of N worker processes × 1 thread (default: in this "
                        "process)")
    g.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run them on a running Dask cluster (tcp://host:8786 or a scheduler "
                        "file); its workers must see the scan at the same path")
    s.add_argument("--memory-limit", default=None, metavar="SIZE",
                   help="memory of each --workers worker (e.g. 2GiB; default: the machine's "
                        "memory / N); a task that cannot fit stops the run before it starts")


def _print_run(out: Path) -> None:
    """The rig, mesh and world frame the run's products were made with (``out/run/run.json``,
    :func:`facegeo.pipeline.reconstruct.record_run`)."""
    try:
        run = json.loads((out / "run" / "run.json").read_text(encoding="utf-8"))
        print(f"run: rig {run['rig']}, mesh {run['mesh']}, world frame {run['world']}")
        if run.get("rig_note"):
            print(f"  ({run['rig_note']})")
    except (OSError, ValueError, KeyError, TypeError):
        pass


def _write_report(out: Path, *, quiet: bool = False) -> None:
    from facegeo.pipeline.cache import stale_stages
    from facegeo.pipeline.report import summary_table, write_report

    # read from the stages' manifests once, for the report and the summary printed here
    stale = stale_stages(out)
    path = write_report(out, stale=stale)
    if not quiet:  # (quiet: the demo's second writing, the table printed already)
        print(summary_table(json.loads((out / "metrics.json").read_text()), stale))
    print(f"report: {path}")


def _cmd_stage(args) -> int:
    """``facegeo decode|mesh|fit SCAN``: that stage of ``reconstruct`` and what it needs."""
    print(f"{args.command}: {args.scan} (cached stages under {Path(args.scan) / 'out'})")
    _run_reconstruct(args.scan, args, until=args.command)
    return 0


def _cmd_render(args) -> int:
    from facegeo.pipeline.render import run_render

    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.render import check_render_args

    # loaded and validated once: the checks, the stages up to the fit and the render share it
    scan = load_scan(args.scan)
    from facegeo.pipeline.fit import image_space_scan

    if image_space_scan(scan, getattr(args, "mesh", "auto")):
        raise InputError(
            f"render: {args.scan} is a single-view scan without geometry (one camera, no "
            "structured light, no mesh): it is fitted in image space (per-pixel normals, albedo "
            "and specular lobes), with no surface to see from another viewpoint. What works: "
            f"'facegeo fit {args.scan}' (the fitted maps in out/fit/), 'facegeo relight "
            f"{args.scan} --env ENV --model fitted' (the camera's view under any environment "
            "from the fitted model), or --mesh PATH (a mesh of the object, metres) to fit per "
            "texel and render novel views")
    # before any stage runs (atlas, project and fit take minutes on the larger presets)
    check_render_args(scan, camera_spec=args.camera, env=args.env,
                      projection=args.projection, convention=args.envmap_convention,
                      rotate_deg=args.rotate, shrinkage=args.shrinkage,
                      light_step=args.light_step, resynthesis=not args.naive)
    print(f"render: products of {args.scan} up to the fit (cached):")
    # --workers / --scheduler: one engine for the stages up to the fit and for the view (one
    # task of it, as the render stage's views)
    with _engine(args) as engine:
        _run_reconstruct(scan, args, until="fit", engine=engine)
        tick, close = _progress_factory(not args.quiet)
        try:
            m = run_render(scan, camera_spec=args.camera, env=args.env,
                           projection=args.projection, convention=args.envmap_convention,
                           rotate_deg=args.rotate, supersample=args.supersample,
                           resynthesis=not args.naive, shrinkage=args.shrinkage,
                           light_step=args.light_step, shadow_taps=args.shadow_taps,
                           image_detail=args.image_detail, infer=args.infer, progress=tick,
                           engine=engine)
        finally:
            close()
    figs = {k: m.get(k) for k in ("psnr_db", "naive_psnr_db", "paper_psnr_db", "psnr_gain_db",
                                   "coverage", "inferred_pixel_fraction", "seconds_render")
            if m.get(k) is not None}
    if m.get("shrinkage_factors"):
        figs["shrinkage"] = ", ".join(f"{c} {lam:.3f}" for c, lam in m["shrinkage_factors"].items())
    print(f"rendered {m['name']}: " + ", ".join(f"{k}={v}" for k, v in figs.items()))
    print(f"images: {scan.root / 'out' / 'views' / m['files']['png']} (+ .exr)")
    return 0


def _cmd_evaluate(args) -> int:
    """``facegeo evaluate SCAN``: the products in SCAN/out against the scan's references
    (:mod:`facegeo.evaluate`), a short table and ``out/evaluate/metrics.json``."""
    from facegeo.evaluate import run_evaluate, summary_rows

    out = Path(args.out) if args.out is not None else Path(args.scan) / "out"
    kw = {"gt_lights": args.gt_lights} if hasattr(args, "gt_lights") else {}
    tick, close = _progress_factory(not args.quiet)
    try:
        m = run_evaluate(args.scan, out, progress=tick, **kw)
    finally:
        close()
    rows = summary_rows(m)
    if not rows:
        print(f"evaluate: nothing to compare in {out} (no products with a reference of their "
              "kind: ground_truth/ or [reference])")
    for stage, key, value in rows:
        print(f"  {stage:<10} {key:<40} {value:.6g}" if isinstance(value, float)
              else f"  {stage:<10} {key:<40} {value}")
    print(f"metrics: {out / 'evaluate' / 'metrics.json'}")
    return 0


def _cmd_export(args) -> int:
    """``facegeo export SCAN``: the fitted model as ``OUT/export/model.glb`` + textures."""
    from facegeo.pipeline.export import run_export

    out = Path(args.out) if args.out is not None else Path(args.scan) / "out"
    m = run_export(args.scan, out, format=args.format)
    print(f"export: {m['vertices']} vertices, {m['faces']} faces, atlas "
          f"{m['atlas_size'][0]}x{m['atlas_size'][1]}, {m['fitted_texels']} of {m['texels']} "
          f"texels fitted, roughness {m['roughness']:.3f}")
    print(f"model: {out / 'export' / 'model.glb'} (textures beside it)")
    return 0


def _cmd_report(args) -> int:
    _write_report(Path(args.scan) / "out")
    return 0


def _cmd_reconstruct(args) -> int:
    print(f"reconstructing {args.scan} (products and metrics.json under "
          f"{Path(args.scan) / 'out'})")
    _run_reconstruct(args.scan, args, from_stage=args.from_stage, only=args.only)
    return 0


#: ``facegeo mesh`` / ``reconstruct`` options that are mesh-stage settings of the same name.
_MESH_OPTIONS = ("depth", "max_distance_mm", "min_angle_deg", "code_interpolation",
                 "min_confidence", "hole_fill", "fill_distance_mm", "silhouettes")


def _int_or_auto(text: str):
    """argparse type: ``auto`` or an integer."""
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'auto' or an integer, got {text!r}") from None


def _mm_or_auto(text: str):
    """argparse type: ``auto`` or a finite number > 0."""
    return text if text == "auto" else _pos_float(text)


def _mesh_options(s) -> None:
    """The mesh stage's Poisson, trim and triangulation settings (only sent when given, so
    the cache keys of the default runs do not change)."""
    s.add_argument("--depth", type=_int_or_auto, default=None, metavar="N|auto",
                   help="mesh: Poisson octree depth, 4-12 (default auto: from the points' "
                        "extent and spacing; docs/mesh.md)")
    s.add_argument("--max-distance-mm", type=_mm_or_auto, default=None, metavar="MM|auto",
                   help="mesh: trim mesh vertices farther than this from every point (default "
                        "auto: agreed with the Poisson cell)")
    s.add_argument("--min-angle-deg", type=_nonneg_float, default=None, metavar="DEG",
                   help="mesh: reject points whose rays meet at less than this (default: from "
                        "the rig, a quarter of its median ray angle within [0.5, 3] degrees)")
    s.add_argument("--min-confidence", type=_nonneg_float, default=None, metavar="C",
                   help="mesh: triangulate decoded pixels of at least this confidence, 0-1 "
                        "(default 0.2; the real bust meshes with 0.05 and --rel-contrast 0.05, "
                        "docs/mesh.md)")
    s.add_argument("--code-interpolation", choices=["auto", "on", "off"], default=None,
                   help="mesh, camera-camera route: interpolate codes shared by many pixels "
                        "(default auto: when the cameras out-resolve the projector)")
    s.add_argument("--hole-fill", choices=["auto", "on", "off"], default=None,
                   help="mesh, camera-camera route: fill the holes per-pixel matching leaves "
                        "with code-region centroid points (default auto: on there)")
    s.add_argument("--fill-distance-mm", type=_mm_or_auto, default=None, metavar="MM|auto",
                   help="mesh: the filled surface (mesh_filled.ply, its own Poisson solve in a "
                        "cube 4 x the points' extent) keeps the surface within this of a point "
                        "(default auto: 0.28 x the points' extent; docs/mesh.md)")
    s.add_argument("--silhouettes", choices=["auto", "on", "off"], default=None,
                   help="mesh: shape the filled surface with the cameras' silhouettes in their "
                        "OLAT frames (rim points; default auto: when the scan has OLAT frames; "
                        "docs/mesh.md)")


def _surface_option(s) -> None:
    """The atlas's ``surface`` setting (sent only when given)."""
    s.add_argument("--surface", choices=["filled", "trimmed"], default=None,
                   help="with the reconstructed mesh: build the atlas on the filled surface "
                        "(default; what the structured light did not reach is inferred) or on "
                        "the trimmed mesh.ply alone")


#: ``facegeo fit`` options that are image-space fit settings of the same name
#: (:data:`facegeo.pipeline.fit.IMAGE_FIT_SETTINGS`; a multi-view fit refuses them by name).
_FIT_OPTIONS = ("hold_out", "light_cone_deg", "light_gains", "light_weights", "max_pixels")


def _hold_out(text: str):
    """argparse type of ``--hold-out``: ``every_other``, ``none``, ``EVERY:OFFSET`` or light
    names separated by commas."""
    if text in ("every_other", "none"):
        return text
    every, sep, offset = text.partition(":")
    if sep and every.isdigit() and offset.isdigit():
        if int(every) < 2 or int(offset) >= int(every):
            raise argparse.ArgumentTypeError(f"EVERY:OFFSET: expected EVERY >= 2 and 0 <= OFFSET "
                                             f"< EVERY, got {text!r}")
        return {"every": int(every), "offset": int(offset)}
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"expected every_other, none, EVERY:OFFSET or light "
                                         f"names, got {text!r}")
    return names


def _fit_options(s) -> None:
    """Settings of the image-space fit of a single-view capture (docs/photometric.md); only
    sent when given."""
    s.add_argument("--hold-out", type=_hold_out, default=None,
                   metavar="every_other|none|EVERY:OFFSET|NAME,...",
                   help="single-view fit: lights left out of the fit and predicted (default "
                        "every_other; 2:1 fits positions 1, 3, ...)")
    s.add_argument("--light-cone-deg", type=_pos_float, default=None, metavar="DEG",
                   help="single-view fit: only lights strictly within DEG of the camera")
    s.add_argument("--light-gains", choices=["auto", "given", "fit"], default=None,
                   help="single-view fit: per-light gains as given, fitted, or fitted when every "
                        "light has the same intensity (auto, default)")
    s.add_argument("--light-weights", choices=["uniform", "cells"], default=None,
                   help="single-view fit: weights of the fitted lights (default uniform; cells: "
                        "their solid angles)")
    s.add_argument("--max-pixels", type=_pos_int, default=None, metavar="N",
                   help="single-view fit: fit at most N pixels of the mask (a regular subset)")


def _max_coarse_option(s) -> None:
    """``--max-coarse-px``: the decode stage's setting (only sent when given, so the cache
    keys of the default runs do not change)."""
    s.add_argument("--max-coarse-px", type=_pos_float, default=None, metavar="PX",
                   help="decode: accept codes naming a block of up to PX projector pixels "
                        "(default: half a phase period on a phase axis, else one stripe; "
                        "docs/structured-light.md)")
    s.add_argument("--rel-contrast", type=_nonneg_float, default=None, metavar="R",
                   help="decode: a bit is reliable when its pattern / inverse margin is at least "
                        "R of the pixel's direct light (default 0.15; lower keeps more pixels "
                        "of a low-contrast capture at some cost in exact codes, "
                        "docs/structured-light.md)")


def _common_options() -> argparse.ArgumentParser:
    """Options every subcommand accepts after its name (``facegeo info SCAN -v``)."""
    c = argparse.ArgumentParser(add_help=False)
    g = c.add_argument_group("logging")
    # Own dests with default 0/False: a subparser's default would otherwise overwrite the value
    # given before the command name; main() adds the two.
    g.add_argument("-v", "--verbose", dest="sub_verbose", action="count", default=0,
                   help="more logging (-vv: debug); a traceback for internal errors")
    g.add_argument("--debug", dest="sub_debug", action="store_true",
                   help="debug logging and a traceback for every error")
    return c


def build_parser() -> argparse.ArgumentParser:
    from facegeo.pipeline.reconstruct import RIG_CHOICES
    from facegeo.surface.atlas import DEFAULT_SPLIT_FACES

    p = _Parser(
        prog="facegeo",
        description="Light-stage face capture to a relightable, re-viewable reflectance field "
                    "(Debevec et al. 2000).",
    )
    p.add_argument("--version", action="version", version=f"facegeo {__version__}")
    p.add_argument("-v", "--verbose", action="count", default=0,
                   help="more logging (-vv: debug); a traceback for internal errors")
    p.add_argument("--debug", action="store_true",
                   help="debug logging and a traceback for every error")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    common = [_common_options()]

    s = sub.add_parser("synth", parents=common,
                       help="write a synthetic light-stage scan with ground truth")
    s.add_argument("out", metavar="OUT", help="scan directory to create")
    s.add_argument("--preset", default="small",
                   choices=["tiny", "small", "paper", "modern", "modern_tiny"],
                   help="capture size: tiny (seconds; test fixtures), small (demo default), "
                        "paper (2 cameras 480x720, 64x32 lights), modern (16 cameras 80x120, "
                        "16x32 lights), modern_tiny (16 cameras, 8x4 lights; tests)")
    s.add_argument("--head", default="procedural",
                   help="'procedural' or a mesh file (OBJ/PLY/GLB, +Y up, facing +Z)")
    s.add_argument("--units", default="cm", choices=["cm", "mm", "m"], help="units of --head mesh")
    s.add_argument("--seed", type=_nonneg_int, default=0,
                   help="seeds the head details, skin field, board poses and noise (integer >= 0)")
    s.add_argument("--skin", default="regional",
                   help="ground-truth skin colour model: 'regional' or "
                        "'spectral[:light|medium|olive|dark]' (Donner & Jensen 2006)")
    s.add_argument("--olat-format", default="exr", choices=["exr", "png16"],
                   help="OLAT frames as linear EXR or 16-bit sRGB PNG with an exposure")
    s.add_argument("--noise", type=_nonneg_float, default=0.0,
                   help="sensor noise, fraction of white level (0: noise-free)")
    s.add_argument("--sl-subsurface", default="none", choices=["none", "gaussian", "dipole"],
                   help="blur the projected patterns by subsurface scattering (a Gaussian of "
                        "skin's mean free path, or a dipole profile; docs/structured-light.md)")
    s.add_argument("--sl-codes", default="gray", metavar="FAMILIES",
                   help="structured-light code families, comma-separated: gray, xor02, xor04, "
                        "minsw (several: Gupta et al.'s ensemble, decoded with a vote)")
    s.add_argument("--sl-interreflection", type=_nonneg_float, default=0.0,
                   help="strength of a low-frequency interreflection term in the "
                        "structured-light frames (0: none)")
    s.add_argument("--calib-board", default="charuco", choices=["charuco", "chessboard", "circles"],
                   help="the calibration board of the camera and projector views (a plain "
                        "chessboard or an asymmetric circle grid under the projector's Gray "
                        "code: the common procam set-up; docs/calibration.md)")
    s.add_argument("--sl-phase-steps", type=_nonneg_int, default=None, metavar="N",
                   help="phase-shift steps of the structured light (default the preset's; 0: "
                        "Gray code with inverses and white / black only, as many real scanners)")
    s.add_argument("--projector-scale", type=_pos_float, default=None, metavar="N",
                   help="a projector whose pixel covers about N x N camera pixels on the face "
                        "(the cameras out-resolve the projector; docs/synth.md)")
    s.add_argument("--sl-missing", action="append", default=None,
                   metavar="CAM=FRAME[,FRAME...]|CAM=issue34",
                   help="structured-light frames a camera lost (not written, declared missing "
                        "in the manifest); repeat per camera")
    s.add_argument("--light-error", type=_nonneg_float, default=0.0, metavar="DEG",
                   help="light-stage calibration error in rig.json's lights: each light's "
                        "direction off by DEG (1 sigma per axis; 0.5 is realistic) and its "
                        "distance by 5 mm x DEG/0.5, as a light list; ground_truth keeps the "
                        "exact grid (default 0: the exact grid)")
    s.add_argument("--backdrop", type=_nonneg_float, default=0.0, metavar="ALBEDO",
                   help="albedo of a matte backdrop behind the head in the OLAT frames, lit by "
                        "each light (0.04 is like DiLiGenT's background; default 0: black; "
                        "docs/synth.md)")
    s.add_argument("--witness", action="store_true",
                   help="add a calibration-only camera 'witness' (board views only, 40 deg "
                        "from the capture cameras) and its reference images under axis_lobes "
                        "([reference] images.witness.axis_lobes; docs/synth.md)")
    s.add_argument("--overwrite", action="store_true", help="replace an existing synthetic scan at OUT (a real capture is refused; files "
                        "facegeo did not write are kept)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    s.set_defaults(func=_cmd_synth)

    s = sub.add_parser("import", parents=common,
                       help="make a scan from a folder of frames (a description, or a known "
                            "public data set)")
    s.add_argument("src", metavar="SRC", help="the folder as it ships (never modified)")
    s.add_argument("dest", metavar="DEST", help="new scan directory (must not exist or be empty)")
    s.add_argument("--description", metavar="DESC.toml",
                   help="a version-2 scan.toml whose paths are relative to SRC "
                        "(docs/scan-format.md, Importing)")
    s.add_argument("--rig", metavar="RIG.json", help="with --description: the rig file, if "
                   "SRC has none")
    s.add_argument("--dataset", choices=["opencv-stereo", "yale-b", "graycode-mannequin",
                                         "three-phase", "3dunderworld", "diligent"],
                   help="convert a known public data set (docs/datasets.md)")
    s.add_argument("--scale", type=float, choices=(1.0, 0.5, 0.25), default=None,
                   help="with --dataset 3dunderworld: frames reduced by an exact 1/2 or 1/4 box "
                        "mean (written as PNG), intrinsics scaled by the pixel-centre rule; "
                        "relative to the source frames")
    s.add_argument("--copy", action="store_true", help="copy files instead of hard-linking them")
    s.set_defaults(func=_cmd_import)

    s = sub.add_parser("push", parents=common,
                       help="copy a scan's input files into a store (URL/scan/), for --store "
                            "runs whose workers share no disk with this machine")
    s.add_argument("scan", metavar="SCAN", help="scan directory")
    s.add_argument("url", metavar="URL", help="a folder or fsspec store (s3://bucket/prefix)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_push)

    s = sub.add_parser("info", parents=common, help="summarise and validate a scan directory")
    s.add_argument("scan", metavar="SCAN", help="scan directory (or its scan.toml)")
    s.add_argument("--full", action="store_true",
                   help="decode every frame and check its pixels (slower)")
    s.set_defaults(func=_cmd_info)

    s = sub.add_parser("bench", parents=common,
                       help="run registered benchmarks (speed against error)")
    s.add_argument("names", nargs="*", default=[],
                   help="benchmarks to run: names, or the start of names ('visibility', 'vis', "
                        "'visibility.closest'; --list shows them); none: all")
    s.add_argument("--quick", action="store_true", help="smaller problem sizes")
    s.add_argument("--out", default="bench-out", help="folder for bench.json and bench.md")
    s.add_argument("--list", action="store_true", help="list the registered benchmarks")
    s.set_defaults(func=_cmd_bench)

    s = sub.add_parser("calibrate", parents=common,
                       help="calibrate cameras, rig and projector from the scan's board views")
    s.add_argument("scan", metavar="SCAN", help="scan directory")
    s.add_argument("--out", default=None, help="output folder (default: SCAN/out/calibrate)")
    s.add_argument("--model", choices=["auto", "pinhole", "k1", "k1k2", "opencv4", "opencv5",
                                        "rational8"],
                   default="auto", help="lens distortion model of every camera; auto: chosen per "
                   "camera (and for the projector) by leave-one-view-out cross-validation "
                   "(a more complex model only when its held-out gain exceeds the noise; "
                   "degenerate lenses refused)")
    s.add_argument("--loss", choices=["linear", "soft_l1", "huber", "cauchy", "arctan"],
                   default="linear", help="robust loss of the least-squares solves")
    s.add_argument("--reference", default=None,
                   help="camera held fixed in the bundle adjustment (default: the first)")
    s.add_argument("--legacy-board", action="store_const", const=True, default=None,
                   help="ChArUco board in OpenCV's legacy pattern (OpenCV < 4.6, "
                   "setLegacyPattern); default: the board description's legacy key, else "
                   "read both ways where they differ (an even row count)")
    s.add_argument("--no-cross-validation", action="store_true",
                   help="skip the cross-validation (two halves, leave one view out)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    s.set_defaults(func=_cmd_calibrate)

    s = sub.add_parser("atlas", parents=common,
                       help="UV atlas (xatlas) and texel table of the scan's mesh")
    s.add_argument("scan", metavar="SCAN", help="scan directory")
    s.add_argument("--out", default=None,
                   help="products folder (default: SCAN/out, where the atlas is the cached stage "
                        "later stages reuse; another folder: the stage on its own)")
    s.add_argument("--mesh", default="auto",
                   help="auto (the reconstruction when the scan has structured light, else "
                        "a synthetic scan's true mesh), ground_truth, reconstructed (the cached "
                        "mesh stage) or a mesh file in metres")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--texels-per-mm", type=_pos_float, default=1.0,
                   help="atlas resolution on the surface")
    g.add_argument("--size", type=int, default=None,
                   help="atlas size in texels instead (16 to 32768)")
    s.add_argument("--padding", type=_nonneg_int, default=2, help="texels between charts")
    s.add_argument("--split-faces", type=_nonneg_int, default=DEFAULT_SPLIT_FACES,
                   help="parameterise in pieces of about this many triangles (0: one piece)")
    s.add_argument("--repair", action="store_true",
                   help="drop degenerate and non-manifold faces instead of refusing the mesh")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    s.set_defaults(func=_cmd_atlas)

    s = sub.add_parser("project", parents=common,
                       help="project every camera's OLAT frames onto the atlas texels")
    s.add_argument("scan", metavar="SCAN", help="scan directory")
    s.add_argument("--out", default=None,
                   help="products folder (default: SCAN/out, where the projection and the atlas "
                        "before it are cached stages later stages reuse; another folder: the "
                        "stage on its own)")
    s.add_argument("--rig", default=None, metavar="RIG",
                   help="rig to project with: auto (default: as for facegeo reconstruct, the "
                        "calibrated rig when the scan has board views; with --out or --camera "
                        "a synthetic scan's true rig, else rig.json), ground_truth, scan (the "
                        "scan's rig.json), calibrated (SCAN/out/calibrate/rig.json) or a rig file")
    s.add_argument("--mesh", default="auto", help="as for facegeo atlas")
    s.add_argument("--camera", action="append", default=None,
                   help="project only this camera (repeatable; default: all; the stage then "
                        "runs on its own, outside the cache, as with a rig file)")
    s.add_argument("--dtype", choices=["float16", "float32"], default="float16",
                   help="storage type of the fields on disk")
    s.add_argument("--gt-lights", type=_pos_int, default=argparse.SUPPRESS,
                   help="lights compared against ground truth on synthetic scans (a stratified "
                        "subset; default: facegeo.evaluate.projection.GT_LIGHTS, 128)")
    s.add_argument("--no-shadow-taps", dest="shadow_taps", action="store_false",
                   help="plain bilinear sampling everywhere (default: samples whose taps straddle "
                        "a cast-shadow edge take the taps on their own side, decided by the mesh "
                        "and the rig's lights; docs/surface.md)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    s.add_argument("--field-format", choices=["npy", "zarr"], default="npy",
                   help="how each camera's field is stored: R.npy (default) or a chunked "
                        "R.zarr (docs/surface.md, docs/scale.md)")
    _lights_per_task_option(s)
    _store_option(s)
    _engine_options(s)
    s.set_defaults(func=_cmd_project)

    s = sub.add_parser("relight", parents=common,
                       help="relight a camera view of the scan, or its texture atlas (--view texture), "
                            "with an environment map (Eq. 4)")
    s.add_argument("scan", metavar="SCAN", help="scan directory")
    s.add_argument("--env", required=True, action="append", metavar="FILE|NAME|DIR",
                   help=".exr/.hdr environment map, a shipped map (sky, studio), or a folder "
                        "(its .exr/.hdr maps, by name); repeat to relight under several maps, "
                        "each with its own files, the field read once per batch of maps")
    _add_envmap_options(s)
    s.add_argument("--rotate", type=_rotate_deg, default=0.0, metavar="DEG",
                   help="rotate the environment about +Y (degrees, +Z toward +X)")
    s.add_argument("--view", default=None, metavar="CAMERA",
                   help="camera name (default: the first) or 'texture'")
    s.add_argument("--exact-solid-angles", action="store_true",
                   help="exact cell solid angles instead of the paper's sin(phi) rule")
    s.add_argument("--model", choices=["measured", "fitted"], default="measured",
                   help="measured: Eq. 4 on the measured frames (only what the lights cover); "
                        "fitted: a single-view scan's image-space fit (out/fit) evaluated for "
                        "every direction of the environment, specular lobes from the model")
    s.add_argument("--out", default=None, help="output folder (default: SCAN/out/relit)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    _engine_options(s)
    s.add_argument("--store", default=None, metavar="URL",
                   help="--view texture: the tasks' relit rows in this fsspec store "
                        "(s3://bucket/prefix) instead of the output folder, for workers that "
                        "share no disk (docs/scale.md)")
    s.set_defaults(func=_cmd_relight)

    rig_help = ("rig of the stages after calibration: 'auto' (the calibrated one when the scan "
                "has board views and the calibration succeeds, synthetic or not; else the "
                "scan's rig.json, a synthetic scan's true rig), 'ground_truth' (a diagnostic), "
                "'calibrated' or 'scan'")
    mesh_help = ("surface stages' mesh: 'auto' (the reconstructed one when the scan has "
                 "structured light, synthetic or not; else a synthetic scan's ground-truth "
                 "mesh), 'ground_truth' (a diagnostic), 'reconstructed', or a mesh file in "
                 "metres")
    for name, text in (("decode", "decode the structured-light frames (cached stage)"),
                       ("mesh", "decode, triangulate and mesh the structured light (cached)"),
                       ("fit", "fit the skin model to the surface reflectance field (cached, "
                               "with every stage it needs)")):
        s = sub.add_parser(name, parents=common, help=text)
        s.add_argument("scan", metavar="SCAN", help="scan directory")
        s.add_argument("--mesh", default="auto", help=mesh_help)
        s.add_argument("--rig", default="auto", choices=RIG_CHOICES, help=rig_help)
        if name in ("decode", "mesh"):
            _max_coarse_option(s)
            _store_option(s)
        _engine_options(s)
        if name == "mesh":
            _mesh_options(s)
        if name == "fit":
            _fit_options(s)
            _surface_option(s)
            _store_option(s)
        s.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
        s.set_defaults(func=_cmd_stage)

    s = sub.add_parser("render", parents=common,
                       help="render a novel view under an environment map (reflectance field + "
                            "skin model, Debevec et al. 2000 §4.5)")
    s.add_argument("scan", metavar="SCAN", help="scan directory")
    s.add_argument("--camera", required=True, metavar="SPEC",
                   help="'orbit:CAMERA:DEGREES', a camera name of the rig or the generator's "
                        "novel cameras ('front': the rig's frontal view), a camera JSON file, "
                        "or an OpenCV FileStorage camera (.yml/.yaml/.xml: camera_matrix, "
                        "distortion_coefficients, R/T or rvec/tvec in metres), in the world "
                        "frame of the rig the render uses (docs/render.md)")
    s.add_argument("--env", default="sky", help="an .exr/.hdr map (lat-long unless "
                   "--projection), or a built-in: sky, studio, uniform, axis_lobes")
    _add_envmap_options(s)
    s.add_argument("--rotate", type=_rotate_deg, default=0.0, help="environment rotation about +Y, "
                   "degrees")
    s.add_argument("--supersample", type=_pos_int, default=1, help="s x s rays per pixel")
    s.add_argument("--naive", action="store_true", help="no resynthesis: the source cameras' "
                   "measured functions relit and blended (the baseline)")
    s.add_argument("--shrinkage", default="cross-validated", metavar="MODE",
                   help="share of the resynthesised view change applied per source camera: "
                        "'cross-validated' (default: measured against the other source cameras; "
                        "a deviation from the paper, docs/render.md), 'none' (the paper's "
                        "resynthesis as written) or a number in [0, 1]")
    s.add_argument("--light-step", type=_pos_int, default=1, metavar="K",
                   help="speed against accuracy (not the paper): resynthesise once per K x K "
                        "block of lights (default 1: every light; docs/render.md)")
    s.add_argument("--no-shadow-taps", dest="shadow_taps", action="store_false",
                   help="plain bilinear texel taps across the key lights' cast-shadow edges "
                        "(default: taps on the pixel's side of the edge, decided on the mesh; "
                        "docs/render.md)")
    s.add_argument("--no-image-detail", dest="image_detail", action="store_false",
                   help="render in texture space only, the paper's way (default: the source "
                        "cameras' relit captures, projected per pixel, carry the detail finer "
                        "than a texel, and the naive baseline is that projection; "
                        "docs/render.md)")
    s.add_argument("--no-infer", dest="infer", action="store_false",
                   help="leave surface no camera saw black, the paper's way (default: inferred "
                        "from its neighbours on the surface, marked in NAME_inferred.png; "
                        "docs/render.md)")
    s.add_argument("--mesh", default="auto", help=mesh_help)
    s.add_argument("--rig", default="auto", choices=RIG_CHOICES, help=rig_help)
    # the stages up to the fit and then the view (one task) run on this engine
    _engine_options(s)
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    s.set_defaults(func=_cmd_render)

    s = sub.add_parser("reconstruct", parents=common,
                       help="run every stage the scan has input for (calibrate, decode, mesh, "
                            "atlas, project, fit, render) and evaluate the products, cached")
    s.add_argument("scan", metavar="SCAN", help="scan directory")
    s.add_argument("--mesh", default="auto", help=mesh_help)
    s.add_argument("--rig", default="auto", choices=RIG_CHOICES, help=rig_help)
    g = s.add_mutually_exclusive_group()
    g.add_argument("--from", dest="from_stage", default=None, metavar="STAGE",
                   help="rerun this stage and every later one even if cached")
    g.add_argument("--only", default=None, metavar="STAGE",
                   help="run only this stage (its input stages must be current)")
    _max_coarse_option(s)
    _mesh_options(s)
    _surface_option(s)
    _store_option(s)
    _engine_options(s)
    _lights_per_task_option(s)
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    s.set_defaults(func=_cmd_reconstruct)

    s = sub.add_parser("evaluate", parents=common,
                       help="compare the products in SCAN/out with the scan's references "
                            "(ground truth, reference cloud, intrinsics, normals, images)")
    s.add_argument("scan", metavar="SCAN", help="scan directory")
    s.add_argument("--out", default=None,
                   help="products folder (default: SCAN/out); writes OUT/evaluate/")
    s.add_argument("--gt-lights", type=_pos_int, default=argparse.SUPPRESS,
                   help="lights the projection is compared at on synthetic scans (a "
                        "stratified subset; default: facegeo.evaluate.projection.GT_LIGHTS, 128)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    s.set_defaults(func=_cmd_evaluate)

    s = sub.add_parser("export", parents=common,
                       help="write the fitted model (mesh, albedo, normal and roughness) as a "
                            "glTF 2.0 .glb with its textures, for Blender, three.js, trimesh")
    s.add_argument("scan", metavar="SCAN", help="scan directory (its fit done: facegeo fit SCAN)")
    s.add_argument("--out", default=None,
                   help="products folder holding atlas/ and fit/ (default: SCAN/out); writes "
                        "OUT/export/")
    s.add_argument("--format", default="glb", choices=["glb"], help="file format (glTF binary)")
    s.set_defaults(func=_cmd_export)

    s = sub.add_parser("report", parents=common,
                       help="write SCAN/out/report.html from the stages' metrics and images")
    s.add_argument("scan", metavar="SCAN", help="scan directory with out/metrics.json")
    s.set_defaults(func=_cmd_report)

    s = sub.add_parser("demo", parents=common,
                       help="the main job on the embedded default (a synthetic scan)")
    s.add_argument("scan", metavar="SCAN", nargs="?", default="scans/demo", help="scan directory")
    s.add_argument("--preset", default="small", choices=["tiny", "small", "paper"],
                   help="capture size when the scan is synthesised")
    s.add_argument("--seed", type=_nonneg_int, default=0, help="seed when the scan is synthesised")
    s.add_argument("--regenerate", action="store_true", help="rebuild the scan even if present")
    s.add_argument("--no-diagnostic", action="store_true",
                   help="run the chain only, not the stage-alone pass (the same stages fed the "
                        "generator's rig and mesh, into SCAN/out/diagnostic/)")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    s.set_defaults(func=_cmd_demo)
    return p


def _quiet_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush cannot raise again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # pragma: no cover - stdout without a file descriptor
        pass


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text or type(exc).__name__


def run_script(main_fn) -> None:
    """Run a script's ``main()`` (the examples') with the CLI's handling of user mistakes:
    facegeo's errors and the environment's refusals (``OSError``) print one line ``PROG:
    error: ...`` on stderr with status 2, Ctrl-C prints ``interrupted`` with 130; otherwise
    ``main``'s return value is the status. Raises SystemExit."""
    prog = Path(sys.argv[0]).name or "facegeo"
    try:
        code = int(main_fn() or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        code = 130
    except (FacegeoError, OSError) as exc:
        print(f"{prog}: error: {_one_line(exc)}", file=sys.stderr)
        code = 2
    raise SystemExit(code)


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit status.

    Exit status: 0 success; 2 an error the user can act on (bad argument, bad or missing file,
    a scan that fails validation), reported as one line ``facegeo CMD: error: ...`` on stderr;
    1 an internal error (a bug), one line unless ``-v``/``--debug`` asks for the traceback;
    130 interrupted (Ctrl-C); 141 stdout closed early (``facegeo ... | head``), silently.
    """
    command = "facegeo"
    verbose, debug = 0, False
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        verbose = args.verbose + getattr(args, "sub_verbose", 0)
        debug = args.debug or getattr(args, "sub_debug", False)
        level = logging.DEBUG if debug or verbose >= 2 else (
            logging.INFO if verbose == 1 else logging.WARNING)
        logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
        if not getattr(args, "func", None):
            parser.print_help()
            return 2
        command = f"facegeo {args.command}"
        args.verbose, args.debug = verbose, debug
        return int(args.func(args) or 0)
    except BrokenPipeError:
        _quiet_stdout()
        return 141
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (FacegeoError, OSError) as exc:
        # OSError: the environment refused (disk full, permission denied); its message names the
        # file. Both are the user's to act on, so no traceback unless --debug.
        if debug:
            traceback.print_exc()
        print(f"{command}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except Exception as exc:
        if debug or verbose:
            traceback.print_exc()
        print(f"{command}: internal error: {type(exc).__name__}: {_one_line(exc)}; rerun with -v "
              "for the traceback", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
