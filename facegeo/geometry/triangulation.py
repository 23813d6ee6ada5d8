"""Triangulation of structured-light decodes: camera rays against the projector, fused over cameras.

A camera pixel ``q`` that decoded the projector coordinate ``(x, y)`` lies on the camera ray
``p(t) = o + t·d`` (``o`` the camera centre, ``d`` the unit ray through the pixel centre, ``t``
metres). Every solver here finds ``t`` by weighted least squares on the **projector's
reprojection residual** along that ray,

    r_i(t) = (π_i(o + t·d) − x_i) / σ_i,     i ∈ {x, y} (y only where it was decoded),

where ``π`` is the projector's projection (:meth:`facegeo.geometry.camera.Camera.project`,
distortion included) and ``σ_i`` the decode's 1-σ noise in projector pixels. With ``x`` only this
is the camera ray against the projector's column *plane* (a curved sheet when the projector has
distortion); with ``x`` and ``y`` it is the ray against the projector *ray*, weighted by the
decode's noise (the camera pixel is taken as exact: its centre is where the measurement was made,
so all the error sits in the decoded code). A linear (algebraic) solution starts three
Gauss–Newton steps in float64.

Uncertainty comes from the intersection geometry: with ``J_i = ∂r_i/∂t`` at the solution,
``σ_t = (Σ J_i²)^(-1/2)`` metres along the ray. ``J`` shrinks as the camera ray turns parallel to
the projector's column plane (the projector code stops changing along the ray), so ``σ_t`` grows
without bound there and :func:`triangulate_maps` rejects the point by threshold rather than
placing it anywhere. The decode noise ``σ_i`` is widened by the pixel's **footprint** in the
projector: a camera pixel spanning ``g`` projector pixels (``g`` the largest code step to a
neighbouring pixel) integrates a box of that width. On a smooth surface the code is sampled at
the pixel centre and that box adds no error, so only the excess over ``footprint_ratio`` times
the map's median footprint counts, as a uniform box of variance ``excess²/12``: grazing
surfaces (strongly foreshortened in the camera) and depth discontinuities (a code jump between
neighbours) carry large σ instead of wild points. (An assumption of this module, not of the
paper: a decoder's own σ should grow there too, but a plain Gray decode reports none.) With ``x`` and ``y`` both decoded,
the normalised residual ``χ = sqrt(Σ r_i²)`` (one degree of freedom) is the camera–projector
reprojection consistency test.

:func:`fuse_cameras` checks every camera's points against the other cameras' point maps
(free-space violations are rejected, agreeing points are averaged with inverse-variance weights)
and :func:`triangulate_camera_pair` triangulates two cameras through matching projector codes,
for rigs whose projector is not calibrated (:func:`triangulate_camera_pairs`: every camera
against every other, merged per camera, ready for :func:`fuse_cameras`). There the match's 2-D
covariance in the other camera is used whole (generalised least squares), and the maps carry
how each depth follows each camera's code noise (:class:`CodeGains`), because two cameras'
points are then made from the same code maps and :func:`fuse_cameras` must not count them as
independent.

Layout: the solver and its rejection rules live in ``_rays``, the compressed point maps and
their 3 × 3 neighbourhood tests in ``_point_maps``, fusion in ``_fusion``, the camera–camera
route in ``_camera_pairs``; this module is their public namespace (and the camera–projector
triangulation). Every step works on the pixels that decoded a code, in blocks, so two 16-Mpx
cameras triangulate and fuse in bounded memory (docs/mesh.md, *Memory at full resolution*).

References
----------
.. [1] Debevec et al., "Acquiring the Reflectance Field of a Human Face", SIGGRAPH 2000, §2
   (geometry from structured light projected by a video projector, seen by the two cameras).
.. [2] Hartley & Zisserman, *Multiple View Geometry*, 2nd ed., §12 (triangulation: minimise the
   reprojection error, not an algebraic distance).
"""

from __future__ import annotations

import numpy as np

from facegeo.checks import as_array, check_positive
from facegeo.errors import InputError, ShapeError
from facegeo.geometry._camera_pairs import (MIN_CODE_DIST, _match_codes, match_projector_codes,
                                            triangulate_camera_pair, triangulate_camera_pairs,
                                            triangulate_code_sets)
from facegeo.geometry._fusion import (FusedPoints, _large_clusters, _pixel_of, fuse_cameras,
                                      neighbour_spacing)
from facegeo.geometry._point_maps import (BEHIND, INCONSISTENT, NO_CODE, OCCLUDED_VIEW, OK,
                                          OUTLIER, REASONS, UNCERTAIN, CodeGains, PointMap,
                                          _median3, _min3, _reject_spikes)
from facegeo.geometry._rays import (MIN_ANGLE_CAP_DEG, MIN_ANGLE_FLOOR_DEG, MIN_ANGLE_FRACTION,
                                    RayFit, _classify, _map, rig_min_angle_deg,
                                    solve_along_rays)
from facegeo.geometry.camera import Camera

__all__ = [
    "BEHIND",
    "INCONSISTENT",
    "MIN_ANGLE_CAP_DEG",
    "MIN_ANGLE_FLOOR_DEG",
    "MIN_ANGLE_FRACTION",
    "MIN_CODE_DIST",
    "NO_CODE",
    "OCCLUDED_VIEW",
    "OK",
    "OUTLIER",
    "REASONS",
    "UNCERTAIN",
    "CodeGains",
    "FusedPoints",
    "PointMap",
    "RayFit",
    "code_footprint",
    "fuse_cameras",
    "match_projector_codes",
    "neighbour_spacing",
    "rig_min_angle_deg",
    "solve_along_rays",
    "triangulate_camera_pair",
    "triangulate_camera_pairs",
    "triangulate_code_sets",
    "triangulate_maps",
]

# private helpers the tests use, reached through this namespace
_PRIVATE = (_large_clusters, _match_codes, _median3, _min3, _pixel_of)


def code_footprint(code: np.ndarray) -> np.ndarray:
    """Projector pixels spanned by each camera pixel: the largest code step to a 4-neighbour.

    Parameters
    ----------
    code : (H, W) float, projector pixels (NaN invalid)

    Returns
    -------
    (H, W) float64, projector pixels; 0 where no neighbour is decoded.
    """
    c = np.asarray(code, np.float64)
    g = np.zeros(c.shape)
    with np.errstate(invalid="ignore"):
        dx = np.abs(np.diff(c, axis=1))
        dy = np.abs(np.diff(c, axis=0))
    dx = np.nan_to_num(dx, nan=0.0)
    dy = np.nan_to_num(dy, nan=0.0)
    g[:, 1:] = np.maximum(g[:, 1:], dx)
    g[:, :-1] = np.maximum(g[:, :-1], dx)
    g[1:] = np.maximum(g[1:], dy)
    g[:-1] = np.maximum(g[:-1], dy)
    return g


def _excess_footprint(code: np.ndarray, ok: np.ndarray, ratio: float) -> np.ndarray:
    g = code_footprint(code)
    sel = ok & (g > 0)
    if not sel.any():
        return np.zeros(code.shape)
    return np.maximum(g - ratio * float(np.median(g[sel])), 0.0)


def triangulate_maps(camera: Camera, projector: Camera, x, y=None, *, valid=None,
                     confidence=None, sigma_x=None, sigma_y=None, min_confidence: float = 0.2,
                     default_sigma_px: float = 0.3, footprint_ratio: float | None = 2.0,
                     max_sigma_ratio: float = 5.0, max_sigma: float | None = None,
                     min_angle_deg: float | None = None, max_chi: float = 4.0, spike_sigmas: float = 6.0,
                     spike_floor: float = 1e-3) -> PointMap:
    """Triangulate one camera's decode maps against the projector.

    Parameters
    ----------
    camera : Camera
        The camera that saw the patterns; its size must equal the maps'.
    projector : Camera
        The projector (an inverse camera).
    x, y : (H, W) float, projector pixels (pixel-centre convention, NaN invalid)
        Decoded projector column and row; ``y`` ``None`` or all-NaN triangulates against
        column planes only.
    valid : (H, W) bool, optional
        The decoder's validity mask (default: finite ``x``).
    confidence : (H, W) float, 0..1, optional
        Pixels below ``min_confidence`` get no point (reason :data:`NO_CODE`).
    sigma_x, sigma_y : (H, W) float, projector pixels, optional
        Decode noise (1 σ); NaN or missing → ``default_sigma_px``.
    footprint_ratio : float or None
        Widen σ by the pixel's footprint in the projector beyond this multiple of the map's
        median footprint (module docstring); ``None`` disables it.
    max_sigma_ratio : float
        Reject points whose σ exceeds this multiple of the map's median σ (reason
        :data:`UNCERTAIN`): near-parallel ray/plane, grazing surfaces, silhouettes.
    max_sigma : float, metres, optional
        Absolute σ limit as well.
    min_angle_deg : float, degrees, optional
        Reject points whose effective triangulation angle (:attr:`RayFit.sin_angle`) is below
        this (reason :data:`UNCERTAIN`): a camera ray nearly parallel to the projector's plane.
        Default from the rig: :func:`rig_min_angle_deg` of the solved rays (at most 3°).
    max_chi : float
        Reject points whose camera–projector residual exceeds this many σ (reason
        :data:`INCONSISTENT`; only where ``y`` was decoded).
    spike_sigmas, spike_floor : float, metres
        Reject points farther along their ray from the 3 × 3 median depth than
        ``spike_sigmas·σ_min + spike_floor`` (``σ_min`` the smallest σ in the 3 × 3 window) (reason :data:`OUTLIER`; isolated wrong codes).

    Returns
    -------
    PointMap

    Notes
    -----
    Implements the ray/plane and ray/ray triangulation of the module docstring. Deviation from
    a plain midpoint: the projector's reprojection error is minimised, because the decoded code
    carries the noise and the camera pixel centre does not.
    """
    if not isinstance(camera, Camera) or not isinstance(projector, Camera):
        uncal = ("; an uncalibrated projector (a rig.Projector: resolution only) must be "
                 "calibrated first" if getattr(projector, "calibrated", True) is False else "")
        raise InputError("camera, projector: expected facegeo.geometry.camera.Camera objects, "
                         f"got {type(camera).__name__}, {type(projector).__name__}{uncal}")
    x = as_array(x, "x", shape=(None, None), finite=False)
    shape = x.shape
    if shape != (camera.height, camera.width):
        raise ShapeError(f"x: expected the camera {camera.name!r}'s image shape "
                         f"{(camera.height, camera.width)}, got {shape}")
    y = np.full(shape, np.nan) if y is None else _map(y, "y", shape)
    ok = np.isfinite(x) if valid is None else _map(valid, "valid", shape, bool) & np.isfinite(x)
    conf = (np.ones(shape, np.float32) if confidence is None
            else _map(confidence, "confidence", shape, np.float32))
    with np.errstate(invalid="ignore"):
        ok &= ~(conf < min_confidence)
    d0 = check_positive(default_sigma_px, "default_sigma_px")
    sx = np.full(shape, d0) if sigma_x is None else _map(sigma_x, "sigma_x", shape)
    sy = np.full(shape, d0) if sigma_y is None else _map(sigma_y, "sigma_y", shape)
    sx = np.where(np.isfinite(sx) & (sx > 0), sx, d0)
    sy = np.where(np.isfinite(sy) & (sy > 0), sy, d0)
    xm = np.where(ok, x, np.nan)
    ym = np.where(ok, y, np.nan)
    if footprint_ratio is not None:
        sx = np.sqrt(sx**2 + _excess_footprint(xm, ok, footprint_ratio) ** 2 / 12.0)
        sy = np.sqrt(sy**2 + _excess_footprint(ym, ok, footprint_ratio) ** 2 / 12.0)
    reason = np.where(ok, OK, NO_CODE).astype(np.uint8)
    idx = np.flatnonzero(ok)
    o, dirs = camera.pixel_rays(np.stack([idx % shape[1], idx // shape[1]], 1).astype(np.float64))
    fit = solve_along_rays(o, dirs, projector,
                           np.stack([x.ravel()[idx], y.ravel()[idx]], 1),
                           np.stack([sx.ravel()[idx], sy.ravel()[idx]], 1))
    fit.chi = np.where(fit.n_constraints == 2, fit.chi, np.nan)
    p = o + fit.t[:, None] * dirs
    del o, dirs
    reason.reshape(-1)[idx] = _classify(fit, p, max_sigma_ratio=max_sigma_ratio,
                                        max_sigma=max_sigma, min_angle_deg=min_angle_deg,
                                        max_chi=max_chi)
    pm = PointMap(camera.name, shape, idx, p, fit.sigma_t, fit.chi,
                  conf.reshape(-1)[idx].astype(np.float32), reason, camera.center_world.copy())
    _reject_spikes(pm, spike_sigmas, spike_floor)
    return pm

