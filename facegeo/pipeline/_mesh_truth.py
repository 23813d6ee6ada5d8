"""Decode maps made from a surface whose per-pixel points are known — a synthetic scan's
ground truth (:func:`ground_truth_decode`) or any known surface (:func:`decode_from_surface`):
the mesh stage's tests and benchmarks feed them to :func:`facegeo.pipeline.mesh.mesh_products`
in place of a real decode. The stage itself never calls them (it reads the decode stage's
maps). Re-exported by :mod:`facegeo.pipeline.mesh`.
"""

from __future__ import annotations

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError

__all__ = ["decode_from_surface", "ground_truth_decode"]


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

        scene = RayScene(*_load_gt_mesh(scan))
    return decode_from_surface(p, n, mask, proj, scene, noise_px=noise_px, seed=seed,
                               with_y=with_y)


def decode_from_surface(p_world, n_world, mask, projector, scene, *, noise_px: float = 0.1,
                        seed: int = 0, with_y: bool = True, quantize=None) -> dict:
    """Decode maps of a camera whose per-pixel surface points are known.

    Parameters
    ----------
    p_world, n_world : (H, W, 3) float64, metres / unit, world frame (NaN off the surface)
    mask : (H, W) bool, the pixel sees the surface
    projector : Camera
    scene : facegeo.surface.visibility.RayScene of the surface (projector shadows)
    noise_px : float, projector pixels, Gaussian 1 σ added to ``x`` and ``y``
    seed : int
    with_y : bool
    quantize : callable, optional
        ``quantize(q) -> (q_decoded, sigma_px)`` applied to the true projector coordinates
        ``(H, W, 2)`` before the noise (e.g. Gray stripes); ``sigma_px`` is added in quadrature.

    Returns
    -------
    dict
        As :func:`ground_truth_decode`.
    """
    p, n, proj = p_world, n_world, projector
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
    s2 = noise_px**2
    if quantize is not None:
        q, sq = quantize(q)
        s2 = s2 + sq**2
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, noise_px, q.shape) if noise_px > 0 else np.zeros(q.shape)
    x = np.where(lit, q[..., 0] + noise[..., 0], np.nan).astype(np.float32)
    y = np.where(lit, q[..., 1] + noise[..., 1], np.nan).astype(np.float32)
    if not with_y:
        y[:] = np.nan
    s = np.float32(np.sqrt(s2)) if s2 > 0 else np.float32(np.nan)
    return {"x": x, "y": y, "confidence": lit.astype(np.float32), "valid": lit,
            "sigma_x": np.where(lit, s, np.nan).astype(np.float32),
            "sigma_y": np.where(lit & with_y, s, np.nan).astype(np.float32),
            "p_world": np.where(mask[..., None], p, np.nan), "shadow": shadow}


def _load_gt_mesh(scan):
    """The true mesh's ``(V, F)`` (float64 metres, int64)."""
    from facegeo.pipeline.project import load_mesh

    V, F, _ = load_mesh(scan, "ground_truth")
    return V, F
