"""Pipeline stage ``mesh``: decode maps → triangulated, fused points → trimmed Poisson mesh.

``run_mesh(scan_dir, out_dir)`` reads the decode stage's ``out_dir/decode/<camera>/decode.npz``
(float32 ``x``, ``y``, ``confidence``, ``sigma_x``, ``sigma_y``, bool ``valid``; see the module
of the decode stage) and writes ``out_dir/mesh/``:

    points.ply    fused points: x y z, nx ny nz (toward the observing camera), confidence,
                  sigma (1 σ along the camera ray, metres), camera (index), confirmed
    mesh.ply      the trimmed Poisson mesh (metres, world frame)
    stage.json    settings and metrics

and records its metrics in ``out_dir/metrics.json`` under ``"mesh"``.

Rig: ``rig="ground_truth"`` (default when the scan has one) uses the true rig the frames were
rendered with, ``rig="scan"`` the scan's ``rig.json`` (the calibrated rig once calibration feeds
the pipeline).

Ground-truth metrics (synthetic scans; the mesh is ``scan.ground_truth_path("mesh")``):

* ``points_rms_error_mm``: RMS unsigned distance of the fused points to the true surface.
* ``mesh_p95_error_mm``: 95th percentile distance to the true surface of area-uniform samples
  of the mesh inside the observed region (within ``observed_radius`` of a fused point).
* ``normal_median_error_deg``: median angle between the mesh's vertex normals and the true
  surface's interpolated vertex normals at the closest point, observed region only.
* ``unobserved_area_mm2`` / ``unobserved_area_fraction``: mesh area farther than
  ``observed_radius`` from every fused point — "no mesh where no camera saw the face".

:func:`ground_truth_decode` makes decode maps from a synthetic scan's per-camera ground-truth
geometry (project the true surface point of each pixel into the projector, drop projector
shadows, add Gaussian noise), for tests and benchmarks and until the decode stage exists.
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
from facegeo.fsutil import atomic_path, atomic_write_text, staged_directory

log = logging.getLogger(__name__)

__all__ = ["run_mesh", "mesh_products", "ground_truth_decode", "write_decode_npz",
           "load_decode", "write_points_ply", "read_points_ply", "DECODE_KEYS"]

#: Arrays of a ``decode.npz``.
DECODE_KEYS = ("x", "y", "confidence", "valid", "sigma_x", "sigma_y")


def _scan(scan_dir):
    from facegeo.capture.scan import Scan, load_scan

    return scan_dir if isinstance(scan_dir, Scan) else load_scan(scan_dir)


def _rig(scan, rig: str | None):
    has_gt = scan.synthetic and "rig" in scan.ground_truth_keys
    if rig is None:
        rig = "ground_truth" if has_gt else "scan"
    if rig == "ground_truth":
        if not has_gt:
            raise InputError(f"rig: scan {scan.root} has no ground-truth rig; use rig='scan'")
        from facegeo.geometry.rig import Rig

        return Rig.load(scan.ground_truth_path("rig")), rig
    if rig == "scan":
        return scan.rig, rig
    raise InputError(f"rig: expected 'ground_truth' or 'scan', got {fmt_value(rig)}")


# ------------------------------------------------------------------------ decode maps


def ground_truth_decode(scan, camera: str, *, noise_px: float = 0.1, seed: int = 0,
                        with_y: bool = True, scene=None) -> dict:
    """Decode maps of one camera made from a synthetic scan's ground truth.

    Each pixel's true surface point (``ground_truth/geometry_<camera>.npz``) is projected with
    the true rig's projector; pixels whose point the projector does not light (outside its
    image, facing away, or shadowed by the head — an Embree segment test) are invalid. Gaussian
    noise of ``noise_px`` projector pixels is added to ``x`` and ``y``.

    Parameters
    ----------
    scan : Scan
        A synthetic scan with ground truth.
    camera : str
    noise_px : float, projector pixels (1 σ)
    seed : int
    with_y : bool
        False leaves ``y`` all NaN (a column-only decode).
    scene : facegeo.surface.visibility.RayScene, optional
        The true mesh's scene (built here when omitted).

    Returns
    -------
    dict
        The :data:`DECODE_KEYS` arrays (float32, ``valid`` bool) plus ``p_world`` (the true
        points, float64) and ``shadow`` (bool: on the surface but not lit by the projector).
    """
    from facegeo.geometry.rig import Rig

    key = f"geometry_{camera}"
    if key not in scan.ground_truth_keys:
        raise InputError(f"camera: scan {scan.root} has no ground-truth geometry for "
                         f"{fmt_value(camera)} (keys: {', '.join(scan.ground_truth_keys)})")
    rig = Rig.load(scan.ground_truth_path("rig"))
    proj = rig.projector
    if proj is None:
        raise InputError(f"scan {scan.root}: the ground-truth rig has no projector")
    with np.load(scan.ground_truth_path(key)) as g:
        mask, p, n = g["mask"], g["p_world"], g["n_world"]
    if scene is None:
        from facegeo.surface.visibility import RayScene

        V, F = _load_gt_mesh(scan)
        scene = RayScene(V, F)
    q, front = proj.project(np.where(mask[..., None], p, 0.0))
    lit = mask & front & proj.in_image(q)
    to_proj = proj.center_world - p
    with np.errstate(invalid="ignore"):
        lit &= np.einsum("...i,...i->...", to_proj, n) > 0
    idx = np.flatnonzero(lit)
    vis = scene.segment_visible(p.reshape(-1, 3)[idx], proj.center_world,
                                normals=n.reshape(-1, 3)[idx])
    shadow = mask.copy()
    lit.ravel()[idx[~vis]] = False
    shadow &= ~lit
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, noise_px, q.shape) if noise_px > 0 else np.zeros(q.shape)
    x = np.where(lit, q[..., 0] + noise[..., 0], np.nan).astype(np.float32)
    y = np.where(lit, q[..., 1] + noise[..., 1], np.nan).astype(np.float32)
    if not with_y:
        y[:] = np.nan
    s = np.float32(noise_px) if noise_px > 0 else np.float32(np.nan)
    return {"x": x, "y": y, "confidence": lit.astype(np.float32), "valid": lit,
            "sigma_x": np.where(lit, s, np.nan).astype(np.float32),
            "sigma_y": np.where(lit & with_y, s, np.nan).astype(np.float32),
            "p_world": np.where(mask[..., None], p, np.nan), "shadow": shadow}


def write_decode_npz(path, maps: dict) -> Path:
    """Write the :data:`DECODE_KEYS` arrays of ``maps`` to ``path`` (atomic)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **{k: maps[k] for k in DECODE_KEYS})
    return path


def load_decode(path, shape: tuple[int, int] | None = None) -> dict:
    """Read a ``decode.npz``, checking its arrays (names, shapes, dtypes).

    Raises
    ------
    InputError
        Missing file or array, or a map whose shape differs from ``shape`` / the ``x`` map.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no decode maps (run the decode stage first: facegeo decode "
                         "SCAN)")
    try:
        with np.load(path) as z:
            if "x" not in z.files:
                raise InputError(f"{path}: missing array 'x' (expected {', '.join(DECODE_KEYS)})")
            out = {k: z[k] for k in DECODE_KEYS if k in z.files}
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable .npz file ({exc})") from exc
    want = shape if shape is not None else out["x"].shape
    for k, a in out.items():
        if a.shape != tuple(want):
            raise InputError(f"{path}: array {k!r} has shape {a.shape}, expected {tuple(want)} "
                             "(the camera's height × width)")
    return out


def _load_gt_mesh(scan):
    import trimesh.exchange.ply

    with open(scan.ground_truth_path("mesh"), "rb") as fh:
        data = trimesh.exchange.ply.load_ply(fh)
    return np.asarray(data["vertices"], np.float64), np.asarray(data["faces"], np.int64)
