"""Pipeline stage ``relight``: a scan's OLAT frames of one camera relit by an environment map
(Debevec et al. 2000 §3.3, Eq. 4), written as EXR and tone-mapped PNG under
``SCAN/out/relight/``.

The CLI (``facegeo relight SCAN --env FILE [--rotate DEG] [--view CAMERA]``) calls
:func:`run_relight`; progress goes through the ``progress`` callback, the library only logs.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from facegeo.errors import InputError
from facegeo.checks import fmt_value

log = logging.getLogger(__name__)

__all__ = ["run_relight", "tone_map"]

#: Tone mapping: the 99.5th percentile of luminance maps to this display value before sRGB.
TONE_MAP_WHITE = 0.9


def tone_map(img: np.ndarray, *, percentile: float = 99.5) -> tuple[np.ndarray, float]:
    """Linear ``(H, W, 3)`` radiance → 8-bit sRGB for viewing, and the exposure used.

    A global exposure puts the ``percentile`` of Rec. 709 luminance at :data:`TONE_MAP_WHITE`;
    values above 1 clip. Exposure 1 for an all-black image.
    """
    from facegeo.capture.response import encode

    lum = img @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    ref = float(np.percentile(lum, percentile)) if lum.size else 0.0
    exposure = TONE_MAP_WHITE / ref if ref > 0 else 1.0
    return encode(np.clip(img * np.float32(exposure), 0.0, 1.0), "srgb", np.uint8), exposure


def _safe_stem(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "env"


def run_relight(scan_dir: str | os.PathLike, env_path: str | os.PathLike, *,
                rotate_deg: float = 0.0, view: str | None = None,
                out_dir: str | os.PathLike | None = None, projection: str = "latlong",
                solid_angle: str = "paper",
                progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Relight one camera of a scan with an environment map and write the images.

    Parameters
    ----------
    scan_dir : path
        Scan directory (``scan.toml``) with OLAT frames.
    env_path : path
        ``.exr``/``.hdr`` environment map.
    rotate_deg : float, degrees
        Rotation of the environment about +Y (right-hand rule: +Z turns toward +X).
    view : str, optional
        Camera name (default: the scan's first camera). ``"texture"`` needs the texture atlas,
        which the pipeline does not build yet (clear error).
    out_dir : path, optional
        Default ``SCAN/out/relight``.
    projection : {"latlong", "mirrorball", "angular"}
    solid_angle : {"paper", "exact"}
        δA rule of the light-basis projection (:func:`facegeo.lighting.envmap.light_stage_weights`).
    progress : callable(stage, done, total), optional

    Returns
    -------
    dict
        Metrics: the files written, the view, the environment, the active lights, the energy
        check ``Σ w / ∫ L`` per channel, the image's mean radiance, timings.
    """
    from facegeo.capture import imageio
    from facegeo.capture.scan import load_scan
    from facegeo.fsutil import atomic_write_text
    from facegeo.lighting import envmap as E
    from facegeo.lighting.relight import relight_scan_view

    t0 = time.perf_counter()
    if view == "texture":
        raise InputError("view: relighting in texture space needs the scan's texture atlas and "
                         "surface reflectance field (facegeo atlas / project), which are not "
                         "built yet; pass a camera name instead")
    if not math.isfinite(float(rotate_deg)):
        raise InputError(f"rotate: expected a finite angle in degrees, got {fmt_value(rotate_deg)}")
    scan = load_scan(scan_dir)
    if not scan.has("olat"):
        raise InputError(f"{scan.root}: the scan has no OLAT frames to relight")
    names = scan.camera_names
    view = names[0] if view is None else view
    if view not in names:
        raise InputError(f"view: unknown camera {fmt_value(view)}; the scan has {', '.join(names)} "
                         f"(or 'texture')")
    env = E.read_envmap(env_path, projection, rotate_deg=rotate_deg)
    lights = scan.rig.lights
    t_env = time.perf_counter()
    w = E.light_stage_weights(env, lights.n_theta, lights.n_phi, solid_angle=solid_angle)
    integral = env.integral()
    active = int(np.count_nonzero(np.any(w != 0, axis=1)))
    t_w = time.perf_counter()
    tick = (lambda k: progress("relight", k + 1, active)) if progress else None
    img = relight_scan_view(scan, view, w, normalize_color=True, progress=tick)
    t_relit = time.perf_counter()

    out = Path(out_dir) if out_dir is not None else scan.out_dir / "relight"
    out.mkdir(parents=True, exist_ok=True)
    rot = f"{float(rotate_deg):g}".replace("-", "m")
    stem = f"{_safe_stem(Path(env_path).stem)}_rot{rot}_{_safe_stem(view)}"
    exr = imageio.write_image(out / f"{stem}.exr", img)  # atomic (temporary file + rename)
    png_img, exposure = tone_map(img)
    png = imageio.write_image(out / f"{stem}.png", png_img)
    metrics = {
        "scan": str(scan.root), "view": view, "env": str(env_path), "projection": projection,
        "rotate_deg": float(rotate_deg), "solid_angle": solid_angle,
        "n_lights": int(lights.n_lights), "active_lights": active,
        "energy_ratio": (w.sum(0) / np.where(integral > 0, integral, 1)).tolist(),
        "mean_radiance": img.reshape(-1, 3).mean(0).tolist(),
        "tone_map_exposure": exposure,
        "files": {"exr": str(exr), "png": str(png)},
        "seconds": {"env": t_env - t0, "weights": t_w - t_env, "relight": t_relit - t_w,
                    "total": time.perf_counter() - t0},
    }
    atomic_write_text(out / f"{stem}.json", json.dumps(metrics, indent=2))
    log.info("relit %s with %s (%d active lights) in %.2f s", view, env_path, active,
             metrics["seconds"]["total"])
    return metrics
