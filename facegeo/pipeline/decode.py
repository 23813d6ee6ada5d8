"""Pipeline stage ``decode``: structured-light frames → projector coordinates per camera pixel.

``run_decode(scan_dir, out_dir)`` streams each camera's structured-light frames (one at a time,
:meth:`facegeo.capture.scan.Scan.sl_frame`) through
:func:`facegeo.geometry.structured_light.decode_stream` and writes ``out_dir/decode/``:

    <camera>/decode.npz   float32 (H, W) ``x``, ``y`` — projector pixel coordinates (pixel-centre
                          convention of docs/conventions.md) of what the camera pixel sees, NaN
                          where invalid (``y`` all NaN when the patterns code no rows);
                          ``confidence`` (0..1); bool ``valid``; float32 ``sigma_x``,
                          ``sigma_y`` (1-σ coordinate noise, projector px, NaN where unknown)
    <camera>/x.png, y.png false-colour maps (turbo over the projector width / height; black =
                          invalid), for looking at only
    stage.json            settings and metrics

and records the metrics in ``out_dir/metrics.json`` under ``"decode"``.

**Cameras with lost frames.** Each camera is decoded from the frames it has
(:meth:`Scan.camera_frames`: the manifest's per-camera ``missing``, ``bits_x`` / ``bits_y``)
with its own pattern set, planned for every camera before any frame is read
(:func:`facegeo.geometry.structured_light.plan_camera_decode`; docs/structured-light.md,
*Cameras with lost frames*): a bit with one frame of its pair left is decoded against
``(white + black) / 2`` (the decoder is fed ``white + black - frame`` as the missing partner);
an axis that lost a bit (both frames) keeps the bits before it, so its codes name blocks of
``2**(n - n')`` of the scan's codes — ``x`` / ``y`` are then the block's centre in the full set's
projector pixels, ``sigma = block / sqrt(12)``; phase is dropped on an axis whose frames are
incomplete or whose blocks outgrow half a period. A camera with no structured-light frame (a
camera of the calibration only) is skipped with a log line and listed in ``skipped_cameras``;
a camera left with nothing to decode stops the stage, naming it and its missing frames, before
any camera is decoded. Each camera's metrics hold its ``plan``
(:meth:`CameraDecodePlan.to_dict`: ``bits`` and ``block_px`` per axis, ``half_pairs`` decoded
against the mid level, ``lost_bits``, ``dropped`` frames, the camera's ``patterns``).

While the stage runs, each finished camera's folder is also kept in
``out_dir/decode/.partial/<camera>/`` (hard links and ``partial.json``: a key of the camera's
plan, the settings, facegeo's code and the size / mtime of the manifest, the response table
and every frame it reads). If a later camera fails, the next run takes the finished cameras
from there (their metrics say ``reused: true``) instead of decoding them again; the folder goes
with the old stage folder when the stage completes.

**Engines.** Each camera's decode is one task (:func:`decode_camera_task`: small arguments —
the loaded scan (manifest and rig, kilobytes), the camera, its plan, the staging folder — and
a small dict back) of an
:class:`facegeo.pipeline.engine.Engine`: in process by default (one camera after another, as
before engines existed), or on a Dask cluster (``--workers N``, ``--scheduler ADDRESS``) where
cameras decode in parallel, each worker writing its camera's folder into the stage's staging
folder and its ``.partial`` copy. The products are byte-identical whatever the engine; the
metrics gain ``engine`` (the workers, their memory limit, each camera's worker, seconds and
peak memory) on a cluster. Each camera's working set (:func:`decode_working_set`, from its
pixel count) is checked against a worker's memory before any task is submitted.

A **phase-only** pattern set (phase shifts and no Gray / XOR / min-SW code, e.g. the shared
three-step face) cannot be unwrapped to absolute projector coordinates: ``decode.npz`` then
holds no valid pixel, one warning says why, and the measurement is written instead per camera:

    <camera>/phase.npz    per phase axis ``a``: float32 (H, W) ``wrapped_a`` (radians in
                          [0, 2 pi), NaN at zero modulation), ``modulation_a`` (fringe
                          amplitude B, fraction of full scale), ``quality_a`` (fringe contrast
                          ``clip(2 B / lit, 0, 1)``, ``lit`` the phase offset 2 A: the decoder's
                          own quality measure), bool ``usable_a`` (not in shadow and
                          ``quality_a >= min_modulation``; saturation is not checked here)
    <camera>/phase_a.png, quality_a.png   false colour (turbo over [0, 2 pi) / [0, 1]; black =
                          not usable / shadow)

with ``phase_only: true`` and ``quality_fraction`` (usable pixels of the image, per camera and
pooled) in the metrics.

Metrics, per camera and pooled: ``skipped_cameras`` (pooled: the list), ``plan`` (per camera,
above), ``valid_fraction`` (of the image, and ``valid_of_surface``: of
the pixels that see the head when the scan has ground truth), per-bit losses (``bits``: per axis
and code family, the lit pixels that leave each bit unresolved and those it invalidates; see
:class:`facegeo.geometry._sl_stream.StreamDecode`), and with ground truth (a synthetic scan's
``ground_truth/geometry_<camera>.npz`` and true rig):

* ``exact_code_fraction`` — over valid pixels of the *interior* (see below), the fraction whose
  decoded projector pixel ``round(x), round(y)`` is one the camera pixel sees: within
  ``0.5 + h`` of the true coordinate of the pixel centre, ``h`` the half extent of the camera
  pixel's footprint in the projector (``0.5 (|∂q/∂col| + |∂q/∂row|)`` per axis). A camera pixel
  that covers two projector pixels integrates both; naming either is exact. On an axis where a
  camera lost bits (and has no phase) its code names a block: exact when within
  ``block / 2 + h`` of the truth.
* ``phase_rms_error_proj_px`` — RMS of ``x - q_x`` (and ``y - q_y``) over valid interior pixels
  on the axes with phase frames, against the pixel centre's true projector coordinate.

The *interior* is the head mask eroded by one pixel, minus pixels whose footprint's half
extent ``h`` (above: the mean of the two central differences of the true projector
coordinate, each half a one-sided jump) reaches 4 projector pixels on either axis — a jump of
≈ 16 projector pixels to one neighbour: occlusion edges, where a pixel mixes two surfaces
and no single true coordinate exists. Smaller jumps (oblique surfaces, a pixel integrating a
few projector pixels) stay in: on the small preset ≈ 150 such pixels carry ≈ 3/4 of
cam_left's squared phase error (its RMS ≈ 0.050 px, ≈ 0.026 without them — a 4-pixel jump
test would drop them).
``exact_code_fraction_all`` counts every valid pixel on the head.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError
from facegeo.fsutil import (
    READ_AHEAD_WORKERS,
    file_state,
    atomic_path,
    atomic_write_text,
    clean_stale_siblings,
    remove_tree,
    staged_directory,
    staging_dir,
    swap_in_dir,
)
from facegeo.rss import peak_rss_mb

log = logging.getLogger(__name__)

__all__ = [
    "DECODE_DEFAULTS",
    "PARTIAL_DIR",
    "camera_plans",
    "DECODE_BYTES_PER_PIXEL",
    "code_accuracy",
    "decode_camera_task",
    "decode_products",
    "decode_working_set",
    "ground_truth_projector",
    "run_decode",
    "scan_decode_settings",
]

#: Settings of :func:`facegeo.geometry.structured_light.decode_stream` used by the stage.
DECODE_DEFAULTS = {"min_contrast": 0.005, "rel_contrast": 0.15, "shadow_threshold": 0.02,
                   "min_modulation": 0.3, "noise_sigma": 0.005, "max_coarse_px": None,
                   "vote_tolerance_px": 0.0, "saturation": 0.98}

_EDGE_JUMP_PX = 4.0

#: Folder of the stage folder (``out/decode/.partial/<camera>/``) where each finished camera's
#: products wait while later cameras decode; removed with the old stage folder when the stage
#: completes (docs/structured-light.md, *Cameras with lost frames*).
PARTIAL_DIR = ".partial"
_PARTIAL_RECORD = "partial.json"


def _scan(scan_dir):
    from facegeo.capture.scan import Scan, load_scan

    return scan_dir if isinstance(scan_dir, Scan) else load_scan(scan_dir)


def ground_truth_projector(scan, camera: str) -> dict[str, np.ndarray] | None:
    """True projector coordinates of a synthetic scan's camera pixels (None without ground truth).

    Returns
    -------
    dict with
        ``q`` (H, W, 2) float64 projector px of the surface point at each pixel centre (NaN off
        the head), ``mask`` (H, W) bool on the head, ``interior`` (H, W) bool (module
        docstring), ``half_extent`` (H, W, 2) float64 projector px.
    """
    from scipy.ndimage import binary_erosion

    from facegeo.geometry.rig import Rig

    key = f"geometry_{camera}"
    if key not in scan.ground_truth_keys or "rig" not in scan.ground_truth_keys:
        return None
    rig = Rig.load(scan.ground_truth_path("rig"))
    with np.load(scan.ground_truth_path(key)) as g:
        mask, p = g["mask"], g["p_world"]
    q, front = rig.projector.project(np.where(mask[..., None], p, np.nan))
    q = np.where((mask & front)[..., None], q, np.nan)
    h = np.stack([0.5 * (np.abs(np.gradient(q[..., a], axis=1))
                         + np.abs(np.gradient(q[..., a], axis=0))) for a in (0, 1)], axis=-1)
    interior = binary_erosion(mask, iterations=1) & np.isfinite(h).all(axis=-1) \
        & (h < _EDGE_JUMP_PX).all(axis=-1)
    return {"q": q, "mask": mask, "interior": interior, "half_extent": h}


def code_accuracy(x, y, valid, gt: dict, *, axes=("x", "y"), phase_axes=(),
                  block_px: dict | None = None) -> dict[str, Any]:
    """``exact_code_fraction`` (interior and all) and ``phase_rms_error_proj_px`` of a decode.

    Parameters
    ----------
    x, y : (H, W) float, projector px (NaN where invalid)
    valid : (H, W) bool
    gt : dict from :func:`ground_truth_projector`
    axes : axes the patterns code (the others are not compared)
    phase_axes : axes with phase frames (the RMS is over these)
    block_px : dict axis -> int, projector px, optional
        Axes whose codes name blocks of this many projector pixels (a camera that lost bits:
        the coordinate is the block's centre): exact there when within ``block / 2 + h`` of
        the truth, i.e. the block holds a projector pixel the camera pixel sees.

    Returns
    -------
    dict with ``exact_code_fraction``, ``exact_code_fraction_all``, ``phase_rms_error_proj_px``
    (None without phase), ``compared_pixels``.
    """
    q, h, mask, interior = gt["q"], gt["half_extent"], gt["mask"], gt["interior"]
    coords = {"x": np.asarray(x, np.float64), "y": np.asarray(y, np.float64)}
    exact = np.ones(mask.shape, bool)
    block_px = block_px or {}
    with np.errstate(invalid="ignore"):
        for i, a in enumerate(("x", "y")):
            if a in axes and block_px.get(a, 1) > 1:
                exact &= np.abs(coords[a] - q[..., i]) <= h[..., i] + 0.5 * block_px[a]
            elif a in axes:
                exact &= np.abs(np.floor(coords[a] + 0.5) - q[..., i]) <= h[..., i] + 0.5
    v_all = np.asarray(valid, bool) & mask
    v_in = v_all & interior
    se, n = 0.0, 0
    for i, a in enumerate(("x", "y")):
        if a in phase_axes and a in axes:
            d = coords[a][v_in] - q[..., i][v_in]
            se += float(np.sum(d * d))
            n += int(d.size)
    return {
        "exact_code_fraction": float(exact[v_in].mean()) if v_in.any() else None,
        "exact_code_fraction_all": float(exact[v_all].mean()) if v_all.any() else None,
        "phase_rms_error_proj_px": float(np.sqrt(se / n)) if n else None,
        "compared_pixels": int(v_in.sum()),
    }


def _false_colour(values: np.ndarray, valid: np.ndarray, size: int, path: Path, *,
                  span: float | None = None) -> None:
    """Turbo PNG of ``values`` over ``[0, span]`` (default ``size - 1``: projector pixels);
    black where not ``valid``."""
    import cv2

    span = max(size - 1, 1) if span is None else span
    v = np.nan_to_num(np.asarray(values, np.float64) / span, nan=0.0)
    u8 = np.clip(np.rint(v * 255.0), 0, 255).astype(np.uint8)
    bgr = cv2.applyColorMap(u8, cv2.COLORMAP_TURBO)
    bgr[~valid] = 0
    with atomic_path(path) as tmp:
        ok, buf = cv2.imencode(".png", bgr)
        if not ok:
            raise InputError(f"{path}: PNG encoding failed")
        Path(tmp).write_bytes(buf.tobytes())


def _axes_coded(spec) -> tuple[str, ...]:
    return tuple(a for a in ("x", "y") if spec.n_bits(a))


def scan_decode_settings(scan) -> dict:
    """The decode settings the scan declares for its captures (``[structured_light.decode]``,
    :data:`DECODE_DEFAULTS` keys; ``docs/scan-format.md``): the stage's defaults for this scan,
    under any setting given to the stage. An importer writes them for a scanner whose frames
    need other thresholds than the generator's (3DUNDERWORLD: ``rel_contrast`` 0.05)."""
    table = scan.manifest.get("structured_light", {}).get("decode") or {}
    unknown = sorted(set(table) - set(DECODE_DEFAULTS))
    if unknown:
        raise InputError(f"{scan.manifest_path}: [structured_light.decode]: unknown "
                         f"{unknown}; valid: {sorted(DECODE_DEFAULTS)}")
    for k, v in table.items():
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))
                              or not math.isfinite(v) or v < 0):
            raise InputError(f"{scan.manifest_path}: [structured_light.decode] {k}: expected "
                             f"a number >= 0, got {fmt_value(v)}")
    return dict(table)


def _scan_pattern_spec(scan):
    """The scan's :class:`PatternSpec`: its ``[structured_light.patterns]`` through
    :meth:`Scan.pattern_spec` (``width`` / ``height`` default to the rig's projector), or, when
    the table is absent or empty, the documented defaults for the rig projector's resolution
    (``docs/scan-format.md``). Returns ``(spec, declared)``."""
    from facegeo.geometry.structured_light import PatternSpec

    spec = scan.pattern_spec("structured_light")
    if spec is not None:
        return spec, True
    proj = scan.rig.projector
    if proj is None:
        raise InputError(f"scan {scan.root}: [structured_light] declares no patterns and the rig "
                         "has no projector to take the pattern set's resolution from")
    return PatternSpec(width=proj.width, height=proj.height), False


def _write_phase_products(res, spec, d: Path, min_modulation: float) -> np.ndarray:
    """``phase.npz`` and the phase / quality PNGs of a phase-only decode (module docstring).

    The wrapped phase and modulation are :func:`decode_stream`'s own (``res.wrapped``,
    ``res.modulation``; :func:`facegeo.geometry.structured_light.decode_phase` computes the same
    from whole frames). Returns the (H, W) bool mask usable on every phase axis."""
    arrays, usable_all = {}, None
    lit = np.asarray(res.lit, np.float32)
    for a in spec.phase_axes:
        wrapped, B = res.wrapped[a], res.modulation[a]
        with np.errstate(divide="ignore", invalid="ignore"):
            quality = np.where(lit > 0, np.clip(2.0 * B / lit, 0.0, 1.0), 0.0).astype(np.float32)
        usable = ~res.shadow & (quality >= min_modulation) & np.isfinite(wrapped)
        arrays.update({f"wrapped_{a}": wrapped, f"modulation_{a}": B,
                       f"quality_{a}": quality, f"usable_{a}": usable})
        _false_colour(wrapped, usable, 0, d / f"phase_{a}.png", span=2.0 * np.pi)
        _false_colour(quality, ~res.shadow, 0, d / f"quality_{a}.png", span=1.0)
        usable_all = usable if usable_all is None else usable_all & usable
    with atomic_path(d / "phase.npz") as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    return usable_all


def camera_plans(scan, spec, cameras: list[str], *, declared: bool = True) -> dict:
    """Each camera's :class:`~facegeo.geometry.structured_light.CameraDecodePlan` from the
    frames it has (:meth:`Scan.camera_frames`) and its declared ``bits_x`` / ``bits_y``.

    Raises
    ------
    InputError
        Naming every camera that has structured-light frames but nothing decodable left, and
        the frames it lacks — before any frame is read.
    """
    from facegeo.geometry.structured_light import plan_camera_decode

    plans = {}
    for cam in cameras:
        bits = scan.sl_bits(cam) if declared else None
        plans[cam] = plan_camera_decode(spec, scan.camera_frames("structured_light", cam),
                                        max_bits=bits, camera=cam)
    bad = {c: p for c, p in plans.items() if p.action == "undecodable"}
    if bad:
        what = "; ".join(
            f"camera {c!r}: {p.reason} (it lacks {scan.missing_frames('structured_light', c)[:12]})"
            for c, p in bad.items())
        raise InputError(f"scan {scan.root}: nothing to decode on {len(bad)} camera(s): {what}; "
                         "give the frames, or leave the camera out (cameras=[...], --cameras) "
                         "or mark all its structured-light frames missing to skip it")
    return plans


def _decode_camera(scan, cam: str, plan, d: Path, used: dict, phase_only: bool):
    """Decode ``cam`` with its plan into ``d``; returns ``(metrics, x, y, valid)``."""
    from facegeo.geometry.structured_light import decode_stream, with_stand_in_partners

    tc = time.perf_counter()
    spec = plan.spec
    # the next frames read and decoded meanwhile; half pairs completed by stand-in partners
    frames = scan.iter_sl(cam, list(plan.frames), read_ahead=READ_AHEAD_WORKERS)
    res = decode_stream(with_stand_in_partners(frames, plan), spec, **used)
    d.mkdir(parents=True, exist_ok=True)
    with atomic_path(d / "decode.npz") as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, x=res.x, y=res.y, confidence=res.confidence,
                            valid=res.valid, sigma_x=res.sigma_x, sigma_y=res.sigma_y)
    _false_colour(res.x, res.valid_x, spec.width, d / "x.png")
    _false_colour(res.y, res.valid_y, spec.height, d / "y.png")
    m: dict[str, Any] = {
        "valid_fraction": float(res.valid.mean()),
        "lit_fraction": float((~res.shadow).mean()),
        "bits": res.bits,
        "plan": plan.to_dict(),
    }
    if phase_only:
        usable = _write_phase_products(res, spec, d, used["min_modulation"])
        m["phase_only"] = True
        m["quality_fraction"] = float(usable.mean())
        m["usable_pixels"] = int(usable.sum())
    m["seconds"] = round(time.perf_counter() - tc, 4)
    return m, res.x, res.y, res.valid


def decode_products(scan, dest: Path, *, cameras: list[str] | None = None,
                    partial_dir: Path | None = None, engine=None, progress=None,
                    store=None, **settings) -> tuple[dict, dict]:
    """Write the ``decode`` products of ``scan`` into ``dest`` (module docstring).

    The work of :func:`run_decode` without the staging. ``settings`` are
    :data:`DECODE_DEFAULTS` keys. Every camera is planned first (:func:`camera_plans`: an
    undecodable camera stops the stage before any work); each is then decoded with its own
    pattern set, as one task of ``engine`` (:mod:`facegeo.pipeline.engine`; default in
    process, one camera after another) writing its folder ``dest/<camera>``. ``partial_dir``
    (the stage folder's ``.partial``, :data:`PARTIAL_DIR`): each finished camera is also kept
    there, and a camera whose frames and settings are unchanged since is taken from there
    instead of decoded again — so a camera that fails does not cost the ones finished before
    it (nor, on a cluster, the ones finished beside it). ``progress(stage, done, total)`` is
    called as cameras finish. Returns ``(metrics, settings)``.

    With a cluster engine the workers must see ``dest`` and the scan at the same paths (one
    machine, or a shared file system) — unless ``store`` is given; each camera's working set
    (:func:`decode_working_set`) is checked against a worker's memory before any is submitted.

    With ``store`` (``--store URL``: a folder or an fsspec URL) the tasks write nothing to a
    shared disk: each decodes into a temporary folder of its worker and copies its products
    to ``URL/decode/run-<id>/<camera>/files/``, which this function brings into ``dest`` and
    then removes from the store. When the store also holds the scan (``URL/scan/``,
    :func:`facegeo.pipeline._scan_store.put_scan`, ``facegeo push``) each task fetches only
    the files it reads from there (:func:`facegeo.pipeline._scan_store.sl_task_files`), so
    the workers need no copy of the scan folder either; else they read the scan folder. The
    metrics' ``frames_from`` says which. ``partial_dir`` is not used with a store (a finished
    camera is kept by the stage, not by the tasks).
    """
    from facegeo.pipeline.engine import InProcessEngine, Task

    unknown = sorted(set(settings) - set(DECODE_DEFAULTS))
    if unknown:
        raise InputError(f"decode settings: unknown {unknown}; valid: {sorted(DECODE_DEFAULTS)}")
    if not scan.has("structured_light"):
        raise InputError(f"scan {scan.root}: no structured-light frames to decode (the manifest "
                         "has no [structured_light] group)")
    used = {**DECODE_DEFAULTS, **scan_decode_settings(scan), **settings}
    spec, declared = _scan_pattern_spec(scan)
    _check_frames_are_the_set(scan, spec, declared)
    cams = list(scan.camera_names) if cameras is None else list(cameras)
    for c in cams:
        if c not in scan.camera_names:
            raise InputError(f"cameras: unknown camera {fmt_value(c)}; the scan has {scan.camera_names}")
    plans = camera_plans(scan, spec, cams, declared=declared)
    engine = InProcessEngine() if engine is None else engine
    t0 = time.perf_counter()
    phase_only = bool(spec.phase_steps and spec.phase_axes) and not _axes_coded(spec)
    if phase_only:
        log.warning(
            "decode: the pattern set is phase-only (%d-step phase on axis %s, no Gray code): "
            "without code bits the wrapped phase cannot be unwrapped to absolute projector "
            "coordinates, so decode.npz has no valid pixel; the wrapped phase and its quality "
            "map are written to <camera>/phase.npz (and phase_*.png, quality_*.png)",
            spec.phase_steps, ", ".join(spec.phase_axes))
    skipped = [c for c in cams if plans[c].action == "skip"]
    for cam in skipped:
        log.info("decode %s: skipped, %s", cam, plans[cam].reason)
    run_loc = frames_from = None
    if store is not None:
        import uuid

        from facegeo.pipeline._scan_store import has_scan, scan_location, sl_task_files
        from facegeo.surface._zarr_field import (STORE_FILES, copy_files, remove_location,
                                                 store_location)

        run_loc = store_location(store, "decode", f"run-{uuid.uuid4().hex[:12]}")
        frames_from = scan_location(store) if has_scan(store) else None
        partial_dir = None
    # the loaded scan travels as it is (its manifest and rig: kilobytes), checked once here:
    # a worker loading it again would validate every frame's header per task
    tasks = []
    for cam in cams:
        if cam in skipped:
            continue
        via = None
        if run_loc is not None:
            via = {"store_dir": str(store_location(run_loc, cam)),
                   "frames_from": None if frames_from is None else str(frames_from),
                   "files": (sl_task_files(scan, cam, plans[cam].frames)
                             if frames_from is not None else [])}
        tasks.append(Task(cam, decode_camera_task,
                          (scan, cam, plans[cam], str(dest), used, phase_only,
                           None if partial_dir is None else str(partial_dir), via),
                          working_set=decode_working_set(scan, cam)))
    try:
        results = engine.map("decode", tasks, progress=progress)
        if run_loc is not None:  # the tasks' products, from the store into the stage folder
            for t in tasks:
                copy_files(store_location(run_loc, t.name, STORE_FILES), Path(dest) / t.name)
    finally:
        if run_loc is not None:
            remove_location(run_loc)
    per_cam: dict[str, dict] = {}
    pooled = dict.fromkeys(_POOLED, 0)
    pooled.update(exact=0.0, se=0.0)
    for t, r in zip(tasks, results):  # in camera order, whatever order they finished in
        per_cam[t.name] = r["metrics"]
        for k in _POOLED:
            pooled[k] += r["pooled"][k]
    metrics: dict[str, Any] = {
        "cameras": per_cam,
        "skipped_cameras": skipped,
        "patterns": spec.to_dict(),
        "valid_fraction": pooled["valid"] / max(pooled["pixels"], 1),
    }
    if phase_only:
        metrics["phase_only"] = True
        metrics["quality_fraction"] = pooled["usable"] / max(pooled["pixels"], 1)
    if pooled["surface"]:
        metrics["valid_of_surface"] = pooled["valid_surface"] / pooled["surface"]
        metrics["exact_code_fraction"] = (pooled["exact"] / pooled["compared"]
                                          if pooled["compared"] else None)
        metrics["phase_rms_error_proj_px"] = (float(np.sqrt(pooled["se"] / pooled["n_phase"]))
                                              if pooled["n_phase"] else None)
    from_scan = {k: used[k] for k in scan_decode_settings(scan) if k not in settings}
    if from_scan:
        metrics["settings_from_scan"] = from_scan  # [structured_light.decode], not overridden
    if store is not None:
        metrics["frames_from"] = "store" if frames_from is not None else "scan folder"
    metrics["seconds"] = round(time.perf_counter() - t0, 4)
    metrics["peak_rss_mb"] = round(peak_rss_mb(), 1)
    if engine.kind != "in-process":
        metrics["engine"] = engine.stage_metrics("decode", [t.name for t in tasks])
    return metrics, {**used, "cameras": cams, **({"store": str(store)} if store else {})}


#: Counts each camera's task adds into the pooled metrics (in camera order).
_POOLED = ("valid", "pixels", "surface", "valid_surface", "exact", "compared", "se", "n_phase",
           "usable")

#: Bytes of memory one camera pixel costs a decode task, all frames streamed
#: (:func:`decode_working_set`): :func:`decode_stream`'s state and temporaries, measured at
#: 69 B/px (42 uint8 RGB frames of 2448 x 1632, peak RSS above the interpreter's), plus the
#: frames in flight — the one decoded and :data:`READ_AHEAD_WORKERS` read ahead, float32 RGB
#: (12 B/px each) — plus the products written (x, y, confidence, sigma_x, sigma_y, valid and
#: the PNGs' buffers, ≈ 30 B/px).
DECODE_BYTES_PER_PIXEL = 69 + 12 * (READ_AHEAD_WORKERS + 1) + 30
#: ... and with ground truth, for the accuracy figures: the true surface points (float64
#: (H, W, 3)), the projector coordinates and footprints (2 × float64 (H, W, 2)), masks and
#: temporaries ≈ 100 B/px.
DECODE_GT_BYTES_PER_PIXEL = 100


def decode_working_set(scan, camera: str) -> int:
    """Memory (bytes) one camera's decode task needs: the camera's pixels (from the rig) times
    :data:`DECODE_BYTES_PER_PIXEL` (plus :data:`DECODE_GT_BYTES_PER_PIXEL` on a synthetic scan
    with ground truth)."""
    cam = scan.rig.camera(camera)
    per_px = DECODE_BYTES_PER_PIXEL + (DECODE_GT_BYTES_PER_PIXEL if scan.synthetic else 0)
    return int(cam.width) * int(cam.height) * per_px


def decode_camera_task(scan, cam: str, plan, dest: str, used: dict, phase_only: bool,
                       partial_dir: str | None, via: dict | None = None) -> dict:
    """One camera's share of the stage, run by an engine (in process or on a worker).

    Takes the camera from ``partial_dir`` when an earlier run finished it, else decodes it
    into ``dest/<cam>`` and keeps it there; computes its metrics (and accuracy, with ground
    truth). Returns ``{"metrics": ..., "pooled": ...}``: the camera's metrics and its counts
    for the pooled figures (:data:`_POOLED`) — small, whatever the camera's size.

    ``via`` (``--store``, :func:`decode_products`): ``store_dir`` — decode into a temporary
    folder and copy the products to ``store_dir/files/``; ``frames_from`` and ``files`` — read
    the scan's ``files`` from the store's copy of the scan (fetched into the temporary folder)
    instead of the scan folder.
    """
    if via is None:
        return _decode_camera_task(scan, cam, plan, dest, used, phase_only, partial_dir)
    import tempfile

    from facegeo.pipeline._scan_store import fetch_scan_files
    from facegeo.surface._zarr_field import STORE_FILES, copy_files, store_location

    with tempfile.TemporaryDirectory(prefix="facegeo-decode-") as tmp:
        scan = _scan(scan)
        if via.get("frames_from"):
            scan = fetch_scan_files(scan, via["frames_from"], via["files"], Path(tmp) / "scan")
        out = _decode_camera_task(scan, cam, plan, str(Path(tmp) / "out"), used, phase_only,
                                  None)
        copy_files(Path(tmp) / "out" / cam, store_location(via["store_dir"], STORE_FILES))
    return out


def _decode_camera_task(scan, cam: str, plan, dest: str, used: dict, phase_only: bool,
                        partial_dir: str | None) -> dict:
    """:func:`decode_camera_task` reading the scan where it is and writing into ``dest``."""
    scan = _scan(scan)
    d = Path(dest) / cam
    partial = None if partial_dir is None else Path(partial_dir)
    if not plan.complete:
        log.info("decode %s: %s", cam, _plan_summary(plan))
    key = _partial_key(scan, cam, plan, used) if partial is not None else None
    m = _reuse_partial(partial, cam, key, d)
    if m is not None:
        with np.load(d / "decode.npz") as z:
            x, y, valid = z["x"], z["y"], z["valid"]
        log.info("decode %s: taken from %s (decoded by an earlier run that did not finish)",
                 cam, partial / cam)
    else:
        m, x, y, valid = _decode_camera(scan, cam, plan, d, used, phase_only)
        _keep_partial(partial, cam, key, d, m)
    pooled = dict.fromkeys(_POOLED, 0)
    pooled.update(exact=0.0, se=0.0)
    pooled["usable"] += m.pop("usable_pixels", 0) if phase_only else 0
    pooled["valid"] += int(valid.sum())
    pooled["pixels"] += int(valid.size)
    gt = ground_truth_projector(scan, cam) if scan.synthetic else None
    if gt is not None:
        m.update(_accumulate_accuracy(x, y, valid, gt, plan, pooled))
    if phase_only:
        log.info("decode %s: phase only, %.1f %% of the pixels above the quality threshold",
                 cam, 100 * m["quality_fraction"])
    else:
        log.info("decode %s: %.1f %% valid", cam, 100 * m["valid_fraction"])
    return {"metrics": m, "pooled": pooled}


def _check_frames_are_the_set(scan, spec, declared: bool) -> None:
    """``structured_light.frames`` must be ``spec``'s pattern set (the cameras' own subsets
    are planned per camera)."""
    from facegeo.geometry.structured_light import pattern_names

    names = scan.sl_frames
    spec_names = pattern_names(spec)
    if sorted(names) != sorted(spec_names):
        extra = sorted(set(names) - set(spec_names))
        missing = [n for n in spec_names if n not in names]
        what = ("the pattern set [structured_light.patterns]" if declared else
                f"[structured_light.patterns] is absent, so the default pattern set of the "
                f"{spec.width} x {spec.height} projector was assumed; it")
        raise InputError(
            f"scan {scan.root}: structured_light.frames lists {len(names)} frames, {what} has "
            f"{len(spec_names)}; missing {missing[:8]}, extra {extra[:8]}"
            + ("" if declared else "; declare the patterns in the manifest"))


def _plan_summary(plan) -> str:
    """One line: what a camera with lost frames decodes."""
    parts = [f"{a}: {v['bits']} of {v['bits_scan']} bits"
             + (f" ({v['block_px']}-px blocks, {v['limited_by']})" if v["limited_by"] else "")
             for a, v in plan.axes.items() if v["bits_scan"]]
    if plan.half_pairs:
        parts.append("half pairs against (white + black) / 2: "
                     + ", ".join(h["present"] for h in plan.half_pairs))
    parts += [f"{d['what']} dropped ({d['why']})" for d in plan.dropped
              if not d["what"].startswith("gray ")]
    return "; ".join(parts)


def _accumulate_accuracy(x, y, valid, gt: dict, plan, pooled: dict) -> dict:
    """The camera's :func:`code_accuracy` and ``valid_of_surface``, added into ``pooled``."""
    spec = plan.spec
    axes = _axes_coded(spec)
    phase_axes = tuple(spec.phase_axes) if spec.phase_steps else ()
    block = {a: v["block_px"] for a, v in plan.axes.items()
             if v["bits"] and v["codes_per_block"] > 1 and a not in phase_axes}
    acc = code_accuracy(x, y, valid, gt, axes=axes, phase_axes=phase_axes, block_px=block)
    on = valid & gt["mask"]
    acc["valid_of_surface"] = float(on.sum() / max(gt["mask"].sum(), 1))
    pooled["surface"] += int(gt["mask"].sum())
    pooled["valid_surface"] += int(on.sum())
    if acc["exact_code_fraction"] is not None:
        pooled["exact"] += acc["exact_code_fraction"] * acc["compared_pixels"]
        pooled["compared"] += acc["compared_pixels"]
    if acc["phase_rms_error_proj_px"] is not None:
        k = acc["compared_pixels"] * sum(a in axes for a in phase_axes)
        pooled["se"] += acc["phase_rms_error_proj_px"] ** 2 * k
        pooled["n_phase"] += k
    return acc


# --------------------------------------------------------------------------- partial products



def _partial_key(scan, cam: str, plan, used: dict) -> str | None:
    """SHA-256 of what a camera's decode depends on: its plan, the settings, facegeo's code and
    the state (size, mtime_ns) of the manifest, of the response table and of every frame the
    plan reads; None when that state cannot be read (no partial kept)."""
    from facegeo.pipeline.cache import code_fingerprint

    try:
        files = [scan.manifest_path] + [scan.sl_path(cam, f) for f in plan.frames]
        resp = scan.response("structured_light")
    except (OSError, InputError):
        return None
    state = [(str(f), file_state(f)) for f in files]
    table = None if resp.table is None else hashlib.sha256(
        np.ascontiguousarray(resp.table).tobytes()).hexdigest()
    doc = {"camera": cam, "plan": plan.to_dict(), "settings": used, "files": state,
           "response": [resp.kind, resp.gamma, table], "code": code_fingerprint()}
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()


def _reuse_partial(partial_dir: Path | None, cam: str, key: str | None, d: Path) -> dict | None:
    """Link ``partial_dir/<cam>``'s products into ``d`` when its key is ``key``; returns the
    camera's stored metrics (marked ``reused``), else None (nothing, stale or unreadable)."""
    if partial_dir is None or key is None:
        return None
    src = partial_dir / cam
    try:
        rec = json.loads((src / _PARTIAL_RECORD).read_text(encoding="utf-8"))
        if not isinstance(rec, dict) or rec.get("key") != key:
            return None
        d.mkdir(parents=True, exist_ok=True)
        for f in sorted(src.iterdir()):
            if f.name != _PARTIAL_RECORD and f.is_file():
                _link_or_copy(f, d / f.name)
        return {**rec["metrics"], "reused": True}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        if (src / _PARTIAL_RECORD).exists():
            log.warning("%s: unusable (%s); decoding %s again", src, exc, cam)
        remove_tree(d)
        return None


def _keep_partial(partial_dir: Path | None, cam: str, key: str | None, d: Path,
                  m: dict) -> None:
    """Keep camera ``cam``'s finished products (folder ``d``) in ``partial_dir/<cam>`` (hard
    links, swapped in whole; the record with ``key`` and the metrics written last). A failure
    only logs a warning: the stage does not need it."""
    if partial_dir is None or key is None:
        return
    target = partial_dir / cam
    tmp = None
    try:
        partial_dir.mkdir(parents=True, exist_ok=True)
        clean_stale_siblings(target)
        tmp = staging_dir(target)
        for f in sorted(d.iterdir()):
            if f.is_file():
                _link_or_copy(f, tmp / f.name)
        atomic_write_text(tmp / _PARTIAL_RECORD, json.dumps(
            {"camera": cam, "key": key, "metrics": m}, indent=1, sort_keys=True))
        swap_in_dir(tmp, target)
    except OSError as exc:
        log.warning("%s: could not keep camera %s's finished decode (%s)", target, cam, exc)
        if tmp is not None:
            remove_tree(tmp)


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def run_decode(scan_dir, out_dir=None, *, cameras: list[str] | None = None, engine=None,
               progress=None, store=None, **settings) -> dict:
    """Decode every camera's structured-light frames into ``out_dir/decode/``.

    Parameters
    ----------
    scan_dir : path-like or Scan
    out_dir : path-like, optional
        Default the scan's ``out/``.
    cameras : list of str, optional
        Default every camera.
    engine : facegeo.pipeline.engine.Engine, optional
        Where the cameras' tasks run (default: in this process, one camera after another;
        :func:`facegeo.pipeline.engine.make_engine` for ``--workers`` / ``--scheduler``). The
        products are the same bytes whatever the engine.
    progress : callable(stage, done, total), optional
        Called as cameras finish.
    store : str or path, optional
        ``--store URL``: the tasks write through the store and read their frames from its
        copy of the scan when it has one (:func:`decode_products`).
    **settings
        :func:`facegeo.geometry.structured_light.decode_stream` thresholds
        (:data:`DECODE_DEFAULTS`).

    Returns
    -------
    dict
        The metrics (module docstring).
    """
    from facegeo.pipeline.cache import record_metrics

    scan = _scan(scan_dir)
    out = Path(out_dir) if out_dir is not None else scan.out_dir
    with staged_directory(out / "decode") as tmp:
        metrics, used = decode_products(scan, tmp, cameras=cameras,
                                        partial_dir=out / "decode" / PARTIAL_DIR,
                                        engine=engine, progress=progress, store=store,
                                        **settings)
        atomic_write_text(tmp / "stage.json", json.dumps(
            {"stage": "decode", "settings": used, "metrics": metrics}, indent=2, sort_keys=True))
        record_metrics(out, "decode", metrics)
    return metrics
