"""Point maps of :mod:`facegeo.geometry.triangulation`: one camera's points, stored compressed.

A camera decodes a quarter or so of its pixels; at 16 Mpx an ``(H, W, 3)`` float64 point grid
is 384 MB, mostly NaN, and the camera–camera route kept a dozen such grids per camera (7.7 GB
for two cameras on a real capture, issue 34). A :class:`PointMap` keeps its values at the
pixels that got a triangulated ray only (``index``, flat, ascending) and a full ``(H, W)``
``uint8`` grid of reasons; the ``(H, W)`` views (:attr:`PointMap.p_world`, …) are built on
demand for tests and small maps. The 3 × 3 neighbourhood tests (spikes here, the free-space
test of :func:`facegeo.geometry.triangulation.fuse_cameras`) gather their windows through a
temporary ``int32`` lookup grid (:meth:`PointMap.lookup`) in blocks of pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BEHIND", "INCONSISTENT", "NO_CODE", "OCCLUDED_VIEW", "OK", "OUTLIER", "REASONS",
           "UNCERTAIN", "CodeGains", "PointMap"]

#: Reason codes of :attr:`PointMap.reason` (``uint8``).
OK, NO_CODE, BEHIND, UNCERTAIN, INCONSISTENT, OUTLIER, OCCLUDED_VIEW = range(7)
#: Names of the reason codes, indexed by code.
REASONS = ("ok", "no_code", "behind", "uncertain", "inconsistent", "outlier",
           "free_space_violation")

#: Pixels per block of the 3 × 3 window gathers (9 float64 values and their positions a pixel:
#: ≈ 150 B, so ≈ 40 MB a block).
_WINDOW_CHUNK = 1 << 18


def _grid(shape, index, values, fill) -> np.ndarray:
    """``values`` (n, ...) scattered to an ``shape + values.shape[1:]`` grid, ``fill`` elsewhere."""
    values = np.asarray(values)
    out = np.full((shape[0] * shape[1],) + values.shape[1:], fill, dtype=values.dtype)
    out[index] = values
    return out.reshape(tuple(shape) + values.shape[1:])


def _take(values, pos, fill):
    """``values[pos]`` where ``pos >= 0`` (a lookup position), ``fill`` where ``pos < 0``."""
    found = pos >= 0
    out = values[np.where(found, pos, 0)] if values.shape[0] else np.zeros(
        pos.shape + values.shape[1:], values.dtype)
    mask = found.reshape(found.shape + (1,) * (out.ndim - found.ndim))
    return np.where(mask, out, fill)


@dataclass
class CodeGains:
    """How a camera–camera point map's depths follow the decode noise they were made from.

    Camera A's pixel ``q`` matched into B through the codes
    (:func:`facegeo.geometry.triangulation.triangulate_camera_pair`) has, to first order, the
    depth error

        δt = dt_dcodeᵀ·n_A(q) − Σ_j h_j·dt_dcodeᵀ·n_B(j),

    ``n_A(q)`` A's code noise at ``q``, ``n_B(j)`` B's at the ``k`` pixels of the local affine
    fit, ``h_j`` their weights in the fitted location (``Σ h_j = 1``, ``Σ h_j² = (G⁻¹)₃₃``):
    both codes enter through the same ``∂q_B/∂code``. B's pixel ``q_B`` at the match is one of
    those ``j``, with ``h ≈ (G⁻¹)₃₃`` (exact when A's code sits at the neighbours' mean code), and
    ``q_B``'s own point (B against A) is made from ``n_B(q_B)`` and, through *its* fit, from
    ``n_A(q)``: the two cameras' points of one surface point share code noise.
    :func:`facegeo.geometry.triangulation.fuse_cameras` uses these gains for that covariance
    (``Σ`` the diagonal code covariances ``sigma_code²``),

        Cov(δt_A, δt_B) = dt_dcode_Aᵀ·Σ_A·partner_dt_dcode_B[A]
                          + partner_dt_dcode_A[B]ᵀ·Σ_B·dt_dcode_B.

    The per-pixel arrays are on the pixels of the owning :class:`PointMap` (its ``index``).

    Attributes
    ----------
    noise : facegeo.geometry.code_maps.CodeNoise
        The camera's own decode noise (x, y), 1 σ, wherever the decode gives it.
    sigma_px : float, projector pixels
        The noise where ``noise`` gives none (:meth:`sigma_code_at`).
    dt_dcode : (n, 2) float64, metres per projector pixel
        Depth along the ray per unit error of the camera's own code at the pixel; NaN without a
        point.
    partner_dt_dcode : dict of str to (n, 2) float64, metres per projector pixel
        Per partner camera: depth per unit error of that camera's code at the pixel its match
        landed on (``−h·dt_dcode`` of the pair, merged over partners like the depths); 0 where
        that partner did not contribute.
    partner_weight : dict of str to (n,) float64
        Per partner camera: ``h = (G⁻¹)₃₃`` of the fit into it (``Σ_j h_j²``, ≈ 1/k). Two
        cameras' points fitted into the same third camera near the same code share its
        neighbours' noise, ``Cov ≈ partner_dt_dcode_Aᵀ·Σ·partner_dt_dcode_B / sqrt(h_A·h_B)``.
    """

    noise: object
    sigma_px: float
    dt_dcode: np.ndarray
    partner_dt_dcode: dict
    partner_weight: dict

    def sigma_code_at(self, flat) -> np.ndarray:
        """The camera's decode noise at flat pixels ``flat``, ``(k, 2)`` float64, projector
        pixels."""
        return self.noise.at(flat, self.sigma_px)

    @property
    def sigma_code(self) -> np.ndarray:
        """``(H, W, 2)`` float64 view of :meth:`sigma_code_at` (built on access)."""
        return self.noise.grid(self.sigma_px)


@dataclass
class PointMap:
    """One camera's triangulated points, stored at the pixels that got a triangulated ray.

    Attributes
    ----------
    camera : str
        Camera name.
    shape : (int, int)
        ``(H, W)`` of the camera.
    index : (n,) int64
        Flat pixel indices (row-major), ascending, of the pixels whose ray was solved (a point,
        or a reason found after solving it); the per-pixel arrays below are on these pixels.
    points : (n, 3) float64, metres, world frame
        Surface point per pixel of ``index``; NaN where ``reason != OK``.
    point_sigma : (n,) float64, metres
        1-σ along the camera ray (intersection geometry, module docstring of
        :mod:`facegeo.geometry.triangulation`).
    point_chi : (n,) float64
        Reprojection residual in σ (NaN with one coordinate).
    point_confidence : (n,) float32, 0..1
        The decode's confidence.
    reason : (H, W) uint8
        :data:`OK` or why the pixel has no point (:data:`REASONS`), every pixel.
    center_world : (3,) float64, metres
        The camera centre (points' normals are oriented toward it).
    code_gains : CodeGains or None
        Camera–camera maps only: how the depths follow each camera's code noise, for the
        covariance of two cameras' points made from the same code maps
        (:func:`facegeo.geometry.triangulation.fuse_cameras`). ``None`` (camera–projector
        maps): the cameras' points are independent.

    The ``(H, W)`` views :attr:`p_world`, :attr:`sigma`, :attr:`chi`, :attr:`confidence` and
    :attr:`depth` are built on each access (NaN off ``index``): fine for tests and small maps,
    24 bytes a pixel for ``p_world`` — code that scales uses the per-pixel arrays.
    """

    camera: str
    shape: tuple
    index: np.ndarray
    points: np.ndarray
    point_sigma: np.ndarray
    point_chi: np.ndarray
    point_confidence: np.ndarray
    reason: np.ndarray
    center_world: np.ndarray
    code_gains: CodeGains | None = None

    # ------------------------------------------------------------ (H, W) views

    @property
    def p_world(self) -> np.ndarray:
        """``(H, W, 3)`` float64, metres, world frame; NaN where ``reason != OK``."""
        return _grid(self.shape, self.index, self.points, np.nan)

    @property
    def sigma(self) -> np.ndarray:
        """``(H, W)`` float64, metres: :attr:`point_sigma`, NaN off ``index``."""
        return _grid(self.shape, self.index, self.point_sigma, np.nan)

    @property
    def chi(self) -> np.ndarray:
        """``(H, W)`` float64: :attr:`point_chi`, NaN off ``index``."""
        return _grid(self.shape, self.index, self.point_chi, np.nan)

    @property
    def confidence(self) -> np.ndarray:
        """``(H, W)`` float32: :attr:`point_confidence`, NaN off ``index``."""
        return _grid(self.shape, self.index, self.point_confidence, np.nan)

    @property
    def valid(self) -> np.ndarray:
        """``(H, W)`` bool: the pixel has a point."""
        return self.reason == OK

    @property
    def depth(self) -> np.ndarray:
        """Distance from the camera centre, ``(H, W)`` float64, metres (NaN without a point)."""
        return _grid(self.shape, self.index, self.depth_at, np.nan)

    # ------------------------------------------------------------ per pixel of index

    @property
    def valid_at(self) -> np.ndarray:
        """``(n,)`` bool: the pixel of ``index`` has a point."""
        return self.reason.reshape(-1)[self.index] == OK

    @property
    def depth_at(self) -> np.ndarray:
        """``(n,)`` float64, metres: distance of each point from the camera centre (NaN without
        a point); in blocks (no ``(n, 3)`` temporaries)."""
        out = np.empty(self.index.size)
        for lo in range(0, out.size, _WINDOW_CHUNK):
            sl = slice(lo, lo + _WINDOW_CHUNK)
            out[sl] = np.linalg.norm(self.points[sl] - self.center_world, axis=-1)
        return out

    def __len__(self) -> int:
        return int(self.index.size)

    def lookup(self) -> np.ndarray:
        """``(H, W)`` int32: each pixel's position in ``index``, −1 off it (64 MB at 16 Mpx:
        build it where many pixels are looked up, and drop it after)."""
        lut = np.full(self.shape[0] * self.shape[1], -1, np.int32)
        lut[self.index] = np.arange(self.index.size, dtype=np.int32)
        return lut.reshape(self.shape)

    def positions(self, flat) -> np.ndarray:
        """Positions in ``index`` of the flat pixels ``flat`` (int64, −1 where absent)."""
        flat = np.asarray(flat, np.int64)
        if not self.index.size:
            return np.full(flat.shape, -1, np.int64)
        pos = np.minimum(np.searchsorted(self.index, flat), self.index.size - 1)
        return np.where(self.index[pos] == flat, pos, -1)

    def reason_counts(self) -> dict:
        """``{reason name: pixel count}`` over the whole map."""
        counts = np.bincount(self.reason.ravel(), minlength=len(REASONS))
        return {REASONS[i]: int(counts[i]) for i in range(len(REASONS))}

    def reject(self, mask: np.ndarray, code: int) -> None:
        """Mark valid pixels in the ``(H, W)`` bool ``mask`` as rejected with ``code`` (in
        place)."""
        self.reject_at(np.flatnonzero(mask), code)

    def reject_at(self, flat, code: int) -> None:
        """Mark the valid ones of the flat pixels ``flat`` as rejected with ``code`` (in
        place)."""
        flat = np.asarray(flat, np.int64)
        r = self.reason.reshape(-1)
        flat = flat[r[flat] == OK]
        r[flat] = code
        pos = self.positions(flat)
        self.points[pos[pos >= 0]] = np.nan


# ------------------------------------------------------------------ 3 × 3 neighbourhoods


def _median3(a: np.ndarray) -> np.ndarray:
    """3 × 3 NaN-ignoring median (NaN where the window holds fewer than 3 values)."""
    H, W = a.shape
    pad = np.pad(a, 1, constant_values=np.nan)
    win = np.stack([pad[i:i + H, j:j + W] for i in range(3) for j in range(3)], -1)
    return _median_of_windows(win)


def _median_of_windows(win: np.ndarray) -> np.ndarray:
    """The NaN-ignoring median of each row of ``(..., 9)`` windows, NaN with < 3 values."""
    win = np.sort(win, axis=-1)  # NaN sort last
    cnt = np.isfinite(win).sum(-1)
    lo = np.take_along_axis(win, np.maximum(cnt - 1, 0)[..., None] // 2, -1)[..., 0]
    hi = np.take_along_axis(win, (cnt // 2)[..., None], -1)[..., 0]
    return np.where(cnt >= 3, 0.5 * (lo + hi), np.nan)


def _min3(a: np.ndarray) -> np.ndarray:
    """3 × 3 NaN-ignoring minimum."""
    H, W = a.shape
    pad = np.pad(np.where(np.isfinite(a), a, np.inf), 1, constant_values=np.inf)
    m = np.min(np.stack([pad[i:i + H, j:j + W] for i in range(3) for j in range(3)]), axis=0)
    return np.where(np.isfinite(m), m, np.nan)


def _windows_at(lut: np.ndarray, values: np.ndarray, flat: np.ndarray, fill) -> np.ndarray:
    """The 3 × 3 windows ``(k, 9)`` around the flat pixels ``flat`` of a map stored at the
    positions of ``lut`` (:meth:`PointMap.lookup`) with per-position ``values``; ``fill`` off
    the image and where ``lut`` is −1. Equals the windows of the ``(H, W)`` grid of ``values``
    padded with ``fill`` (:func:`_median3`)."""
    H, W = lut.shape
    r, c = np.divmod(np.asarray(flat, np.int64), W)
    out = np.empty((r.size, 9), values.dtype)
    i = 0
    for dr in (-1, 0, 1):
        rr = r + dr
        for dc in (-1, 0, 1):
            cc = c + dc
            inside = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
            pos = np.where(inside, lut[np.clip(rr, 0, H - 1), np.clip(cc, 0, W - 1)], -1)
            out[:, i] = _take(values, pos, fill)
            i += 1
    return out


def _median3_at(lut, values, flat) -> np.ndarray:
    """:func:`_median3` of the map (``lut``, ``values``: :func:`_windows_at`) at ``flat``,
    ``(k,)`` float64, in blocks."""
    out = np.empty(np.size(flat))
    for lo in range(0, out.size, _WINDOW_CHUNK):
        sl = slice(lo, lo + _WINDOW_CHUNK)
        out[sl] = _median_of_windows(_windows_at(lut, values, flat[sl], np.nan))
    return out


def _min3_at(lut, values, flat) -> np.ndarray:
    """:func:`_min3` of the map (``lut``, ``values``: :func:`_windows_at`) at ``flat``,
    ``(k,)`` float64, in blocks."""
    out = np.empty(np.size(flat))
    for lo in range(0, out.size, _WINDOW_CHUNK):
        sl = slice(lo, lo + _WINDOW_CHUNK)
        win = _windows_at(lut, np.where(np.isfinite(values), values, np.inf), flat[sl], np.inf)
        m = np.min(win, axis=1)
        out[sl] = np.where(np.isfinite(m), m, np.nan)
    return out


def _reject_spikes(pm: PointMap, k: float, floor: float) -> None:
    """Reject points farther along their ray from the 3 × 3 median depth than
    ``k·σ_min + floor`` and points with fewer than 3 points in their window (reason
    :data:`OUTLIER`), ``σ_min`` the smallest σ of the valid points in the window."""
    # tolerance from the smallest σ around the pixel: a wrong code inflates its own σ (and its
    # 4-neighbours') through the footprint term, which must not hide it from this test
    valid = pm.valid_at
    sel = np.flatnonzero(valid)
    if not sel.size:
        return
    depth = pm.depth_at  # NaN without a point
    lut = pm.lookup()
    flat = pm.index[sel]
    med = _median3_at(lut, depth, flat)
    s_min = _min3_at(lut, np.where(valid, pm.point_sigma, np.nan), flat)
    del lut
    with np.errstate(invalid="ignore"):
        spike = np.abs(depth[sel] - med) > k * s_min + floor
    lonely = ~np.isfinite(med)  # fewer than 3 points in the 3 × 3 window
    pm.reject_at(flat[spike | lonely], OUTLIER)
