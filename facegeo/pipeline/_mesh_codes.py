"""Camera-camera code handling of the mesh stage (:mod:`facegeo.pipeline.mesh`): codes
interpolated where the cameras out-resolve the projector, and the hole fill from code-region
centroids (issue 34; docs/mesh.md, *Cameras that out-resolve the projector* and *Holes*)."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

log = logging.getLogger("facegeo.pipeline.mesh")

__all__ = ["CODE_MIN_COUNT", "FILL_GAP_SPACINGS", "FILL_MIN_CONFIDENCE", "MAX_CODE_SCATTER",
           "SHARED_CODE_LIMIT"]


#: ``code_interpolation="auto"`` interpolates a camera's codes when at least this fraction of its
#: decoded pixels have exactly a 4-neighbour's code (a staircase code map: the camera
#: out-resolves the projector; :func:`facegeo.geometry.code_maps.shared_code_fraction`). A
#: phase-shift decode's codes are continuous (≈ 0); the real bust's decodes at quarter
#: resolution 0.16 (left) / 0.50 (right); the generator at 4:1 0.99. With the limit at 0.1
#: (both of the bust's cameras interpolated): 194,060 points at 0.167 / 0.356 mm to the
#: reference, mesh coverage 0.977, mesh point-to-plane p95 0.39 mm; at 0.25 (only the right):
#: 187,855 points at 0.166 / 0.318 mm, coverage 0.96, p95 ≈ 0.2 mm.
SHARED_CODE_LIMIT = 0.25
#: A pixel whose window's codes scatter about their plane by more than this many times its
#: code block's own staircase (σ_block = block / √12) is dropped: the window mixes surfaces or
#: wrong codes. Measured on the real bust at quarter resolution (points → reference median /
#: p95 mm, mesh coverage of the reference within 1 mm): 1.5 → 0.158 / 0.259, 89.8 % (points);
#: 3 → 0.162 / 0.305, 96.0 % (mesh); 5 → 0.165 / 0.357, 98.9 %; no limit → 0.171 / 0.879,
#: 99.5 % (with 5.7 % of the mesh > 2 mm off).
MAX_CODE_SCATTER = 5.0
#: Fewest valid pixels in a window for the code plane (:func:`interpolate_code_map`).
CODE_MIN_COUNT = 8


def _interpolated_codes(x, y, sx, sy, confidence, default_sigma_px: float, mode: str):
    """One camera's codes for camera-camera matching, compressed to its decoded pixels
    (:class:`facegeo.geometry.code_maps.CodeSet`): interpolated
    (:func:`facegeo.geometry.code_maps.interpolate_code_values`) when many pixels share a code
    (``mode`` ``"auto"``: :data:`SHARED_CODE_LIMIT`; ``"on"``; ``"off"``), else as decoded.

    ``x``, ``y`` are the ``(H, W)`` code maps masked to the usable pixels (NaN elsewhere),
    ``sx``, ``sy`` the decode's σ maps (or None), ``confidence`` its confidence map (or None).
    Returns the code set and a metrics dict."""
    import math

    from facegeo.geometry.code_maps import (CodeNoise, CodeSet, code_region_size,
                                            interpolate_code_values, shared_code_fraction)

    frac = shared_code_fraction(x, y)
    info = {"shared_code_fraction": round(frac, 4), "interpolated": False}
    if mode == "off" or (mode == "auto" and frac < SHARED_CODE_LIMIT):
        return CodeSet.from_maps(x, y, sigma_x=sx, sigma_y=sy, confidence=confidence), info
    size = code_region_size(x, y)
    window = max(5, 2 * math.ceil(math.sqrt(size)) + 1)
    index = np.flatnonzero(np.isfinite(x) & np.isfinite(y))
    out, sig = [], []
    ok = np.ones(index.size, bool)
    for c, s in ((x, sx), (y, sy)):
        # the decode's own σ is its code block's staircase, block / √12 (Gray code)
        if s is None:
            s_block = np.full(index.size, default_sigma_px)
        else:
            s = s.reshape(-1)[index]
            s_block = np.where(np.isfinite(s) & (s > 0), s, default_sigma_px)
        code, rms = interpolate_code_values(c, index, window=window, min_count=CODE_MIN_COUNT)
        with np.errstate(invalid="ignore"):
            ok &= np.isfinite(code) & (rms <= MAX_CODE_SCATTER * np.maximum(
                s_block, 1.0 / math.sqrt(12.0)))
        out.append(code)
        sig.append(np.maximum(rms, s_block).astype(np.float32))
    conf = None if confidence is None else confidence.reshape(-1)[index[ok]]
    # σ is known where the plane was fitted (NaN elsewhere, as the decode's off its pixels)
    codes = CodeSet(x.shape, index[ok], out[0][ok], out[1][ok], confidence=conf,
                    noise=CodeNoise(x.shape, index, np.stack(sig, 1)))
    info.update({"interpolated": True, "window": window, "region_pixels": round(size, 2),
                 "pixels": int(ok.sum()), "pixels_decoded": int(index.size)})
    return codes, info


#: The hole fill's code regions average decoded pixels of at least this confidence: lower
#: than the per-pixel matching's 0.2, since a region's centroid averages its pixels' noise
#: away. Real bust, 1/4 resolution (reference points within 1 mm of the mesh): default decode
#: (rel_contrast 0.15) no fill 96.0 %, fill from pixels ≥ 0.05 97.3 %; the import's decode
#: (rel_contrast 0.05), per-pixel points of confidence ≥ 0.05: fill from pixels ≥ 0.2 99.32 %,
#: ≥ 0.05 99.46 %.
FILL_MIN_CONFIDENCE = 0.05
#: The hole fill keeps a centroid point only where no per-pixel point is within this many
#: point spacings (the points' median 6th-neighbour distance): the holes, not the covered
#: surface, whose per-pixel points are finer (0.166 mm median against the bust's reference,
#: centroid points 0.33 mm).
FILL_GAP_SPACINGS = 2.0



def _fill_centroids(x, y, d: dict, conf, min_confidence: float):
    """One camera's code-region centroids for the hole fill, over its decoded pixels of at
    least ``min_confidence``, at its own code block (per axis, from the decode's σ maps:
    :func:`facegeo.geometry.code_regions.code_block`)."""
    from facegeo.geometry.code_regions import code_block, code_region_centroids

    ok = np.isfinite(x) & np.isfinite(y)
    if "valid" in d:
        ok &= d["valid"].astype(bool)
    if conf is not None:
        with np.errstate(invalid="ignore"):
            ok &= conf >= min_confidence
    block = tuple(code_block(d[k][ok]) if d.get(k) is not None else 1.0
                  for k in ("sigma_x", "sigma_y"))
    cen = code_region_centroids(np.where(ok, x, np.nan), np.where(ok, y, np.nan),
                                block_x=block[0], block_y=block[1])
    return cen, block


def _fill_holes(fused, cams: list, centroids: list, min_confidence: float, *, max_chi: float,
                min_angle_deg) -> tuple[Any, dict]:
    """``fused`` with the hole fill's centroid points added where no point is within
    :data:`FILL_GAP_SPACINGS` spacings
    (:func:`facegeo.geometry.code_regions.centroid_fill_points`), and its metrics."""
    import dataclasses

    from facegeo.geometry import mesh as gm
    from facegeo.geometry._rays import MIN_ANGLE_FLOOR_DEG
    from facegeo.geometry.code_regions import centroid_fill_points

    spacing = gm.median_neighbour_distance(fused.p_world)
    f = centroid_fill_points(cams, [c for c, _ in centroids], [b for _, b in centroids],
                             fused.p_world, min_gap=FILL_GAP_SPACINGS * spacing,
                             max_chi=max_chi, min_angle_deg=MIN_ANGLE_FLOOR_DEG
                             if min_angle_deg is None else float(min_angle_deg))
    n = len(f["p_world"])
    info = {"points": n, "min_gap_mm": _mm(FILL_GAP_SPACINGS * spacing),
            "blocks": {c.name: list(b) for c, (_, b) in zip(cams, centroids)},
            "pairs": f["counts"]}
    if n == 0:
        return fused, info
    cat = np.concatenate
    fused = dataclasses.replace(
        fused, p_world=cat([fused.p_world, f["p_world"]]),
        sigma=cat([fused.sigma, f["sigma"]]),
        confidence=cat([fused.confidence, np.full(n, min_confidence, fused.confidence.dtype)]),
        camera=cat([fused.camera, f["camera"].astype(fused.camera.dtype)]),
        pixel=cat([fused.pixel, f["pixel"].astype(fused.pixel.dtype)]),
        confirmed=cat([fused.confirmed, np.ones(n, bool)]))
    log.info("mesh: hole fill added %d code-region centroid points (no per-pixel point within "
             "%.2f mm)", n, info["min_gap_mm"])
    return fused, info


def _mm(v) -> float:
    return round(float(v) * 1e3, 6)
