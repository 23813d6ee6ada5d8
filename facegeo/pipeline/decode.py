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

Metrics, per camera and pooled: ``valid_fraction`` (of the image, and ``valid_of_surface``: of
the pixels that see the head when the scan has ground truth), per-bit losses (``bits``: per axis
and code family, the lit pixels that leave each bit unresolved and those it invalidates; see
:class:`facegeo.geometry._sl_stream.StreamDecode`), and with ground truth (a synthetic scan's
``ground_truth/geometry_<camera>.npz`` and true rig):

* ``exact_code_fraction`` — over valid pixels of the *interior* (see below), the fraction whose
  decoded projector pixel ``round(x), round(y)`` is one the camera pixel sees: within
  ``0.5 + h`` of the true coordinate of the pixel centre, ``h`` the half extent of the camera
  pixel's footprint in the projector (``0.5 (|∂q/∂col| + |∂q/∂row|)`` per axis). A camera pixel
  that covers two projector pixels integrates both; naming either is exact.
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

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError
from facegeo.fsutil import READ_AHEAD_WORKERS, atomic_path, staged_directory
from facegeo.pipeline.bench import peak_rss_mb

log = logging.getLogger(__name__)

__all__ = [
    "DECODE_DEFAULTS",
    "code_accuracy",
    "decode_products",
    "ground_truth_projector",
    "run_decode",
]

#: Settings of :func:`facegeo.geometry.structured_light.decode_stream` used by the stage.
DECODE_DEFAULTS = {"min_contrast": 0.005, "rel_contrast": 0.15, "shadow_threshold": 0.02,
                   "min_modulation": 0.3, "noise_sigma": 0.005, "max_coarse_px": None,
                   "vote_tolerance_px": 0.0, "saturation": 0.98}

_EDGE_JUMP_PX = 4.0


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


def code_accuracy(x, y, valid, gt: dict, *, axes=("x", "y"), phase_axes=()) -> dict[str, Any]:
    """``exact_code_fraction`` (interior and all) and ``phase_rms_error_proj_px`` of a decode.

    Parameters
    ----------
    x, y : (H, W) float, projector px (NaN where invalid)
    valid : (H, W) bool
    gt : dict from :func:`ground_truth_projector`
    axes : axes the patterns code (the others are not compared)
    phase_axes : axes with phase frames (the RMS is over these)

    Returns
    -------
    dict with ``exact_code_fraction``, ``exact_code_fraction_all``, ``phase_rms_error_proj_px``
    (None without phase), ``compared_pixels``.
    """
    q, h, mask, interior = gt["q"], gt["half_extent"], gt["mask"], gt["interior"]
    coords = {"x": np.asarray(x, np.float64), "y": np.asarray(y, np.float64)}
    exact = np.ones(mask.shape, bool)
    with np.errstate(invalid="ignore"):
        for i, a in enumerate(("x", "y")):
            if a in axes:
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


def decode_products(scan, dest: Path, *, cameras: list[str] | None = None,
                    **settings) -> tuple[dict, dict]:
    """Write the ``decode`` products of ``scan`` into ``dest`` (module docstring).

    The work of :func:`run_decode` without the staging. ``settings`` are
    :data:`DECODE_DEFAULTS` keys. Returns ``(metrics, settings)``.
    """
    from facegeo.geometry.structured_light import decode_stream, pattern_names

    unknown = sorted(set(settings) - set(DECODE_DEFAULTS))
    if unknown:
        raise InputError(f"decode settings: unknown {unknown}; valid: {sorted(DECODE_DEFAULTS)}")
    used = {**DECODE_DEFAULTS, **settings}
    if not scan.has("structured_light"):
        raise InputError(f"scan {scan.root}: no structured-light frames to decode (the manifest "
                         "has no [structured_light] group)")
    spec, declared = _scan_pattern_spec(scan)
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
    cams = list(scan.camera_names) if cameras is None else list(cameras)
    for c in cams:
        if c not in scan.camera_names:
            raise InputError(f"cameras: unknown camera {fmt_value(c)}; the scan has {scan.camera_names}")
    t0 = time.perf_counter()
    per_cam: dict[str, dict] = {}
    pooled = {"valid": 0, "pixels": 0, "surface": 0, "valid_surface": 0,
              "exact": 0.0, "compared": 0, "se": 0.0, "n_phase": 0}
    axes = _axes_coded(spec)
    phase_axes = tuple(spec.phase_axes) if spec.phase_steps else ()
    phase_only = bool(phase_axes) and not axes
    if phase_only:
        log.warning(
            "decode: the pattern set is phase-only (%d-step phase on axis %s, no Gray code): "
            "without code bits the wrapped phase cannot be unwrapped to absolute projector "
            "coordinates, so decode.npz has no valid pixel; the wrapped phase and its quality "
            "map are written to <camera>/phase.npz (and phase_*.png, quality_*.png)",
            spec.phase_steps, ", ".join(phase_axes))
        pooled["usable"] = 0
    for cam in cams:
        tc = time.perf_counter()
        # the next frames read and decoded meanwhile
        frames = scan.iter_sl(cam, names, read_ahead=READ_AHEAD_WORKERS)
        res = decode_stream(frames, spec, **used)
        d = dest / cam
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
            "seconds": round(time.perf_counter() - tc, 4),
        }
        if phase_only:
            usable = _write_phase_products(res, spec, d, used["min_modulation"])
            m["phase_only"] = True
            m["quality_fraction"] = float(usable.mean())
            pooled["usable"] += int(usable.sum())
        pooled["valid"] += int(res.valid.sum())
        pooled["pixels"] += int(res.valid.size)
        gt = ground_truth_projector(scan, cam) if scan.synthetic else None
        if gt is not None:
            acc = code_accuracy(res.x, res.y, res.valid, gt, axes=axes, phase_axes=phase_axes)
            m.update(acc)
            m["valid_of_surface"] = float((res.valid & gt["mask"]).sum() / max(gt["mask"].sum(), 1))
            pooled["surface"] += int(gt["mask"].sum())
            pooled["valid_surface"] += int((res.valid & gt["mask"]).sum())
            if acc["exact_code_fraction"] is not None:
                pooled["exact"] += acc["exact_code_fraction"] * acc["compared_pixels"]
                pooled["compared"] += acc["compared_pixels"]
            if acc["phase_rms_error_proj_px"] is not None:
                k = acc["compared_pixels"] * sum(a in axes for a in phase_axes)
                pooled["se"] += acc["phase_rms_error_proj_px"] ** 2 * k
                pooled["n_phase"] += k
        per_cam[cam] = m
        if phase_only:
            log.info("decode %s: phase only, %.1f %% of the pixels above the quality threshold",
                     cam, 100 * m["quality_fraction"])
        else:
            log.info("decode %s: %.1f %% valid", cam, 100 * m["valid_fraction"])
    metrics: dict[str, Any] = {
        "cameras": per_cam,
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
    metrics["seconds"] = round(time.perf_counter() - t0, 4)
    metrics["peak_rss_mb"] = round(peak_rss_mb(), 1)
    return metrics, {**used, "cameras": cams}


def run_decode(scan_dir, out_dir=None, *, cameras: list[str] | None = None,
               **settings) -> dict:
    """Decode every camera's structured-light frames into ``out_dir/decode/``.

    Parameters
    ----------
    scan_dir : path-like or Scan
    out_dir : path-like, optional
        Default the scan's ``out/``.
    cameras : list of str, optional
        Default every camera.
    **settings
        :func:`facegeo.geometry.structured_light.decode_stream` thresholds
        (:data:`DECODE_DEFAULTS`).

    Returns
    -------
    dict
        The metrics (module docstring).
    """
    from facegeo.fsutil import atomic_write_text
    from facegeo.pipeline.cache import record_metrics

    scan = _scan(scan_dir)
    out = Path(out_dir) if out_dir is not None else scan.out_dir
    with staged_directory(out / "decode") as tmp:
        metrics, used = decode_products(scan, tmp, cameras=cameras, **settings)
        atomic_write_text(tmp / "stage.json", json.dumps(
            {"stage": "decode", "settings": used, "metrics": metrics}, indent=2, sort_keys=True))
        record_metrics(out, "decode", metrics)
    return metrics
