"""Decoded code maps whose codes are shared by many camera pixels: how much, and interpolation.

When the cameras out-resolve the projector (a 4896 × 3264 camera against a 1024 × 768
projector, or a camera that resolves fewer Gray bits than the projector shows), each decoded
projector code covers a region of several camera pixels: the code map is a staircase. Matching
codes between two cameras pixel by pixel then has no sub-pixel answer — every pixel of a region
names the same code, and the local affine inverse of
:func:`facegeo.geometry.triangulation.match_projector_codes` has nothing to fit (all ``k``
neighbours at code distance 0). On the real two-camera bust of the shared data 97 % of one
camera's full-resolution pixels share their code with a 4-neighbour.

:func:`interpolate_code_map` replaces the staircase by the least-squares plane of the codes over
a window around each pixel (a window spanning a few code regions): the plane's value at the
pixel centre is a continuous, sub-region code, the way a region's centroid is a sub-pixel
location of its code, but at every pixel. This is the "code map interpolated within a region"
alternative to matching region centroids; on the bust at quarter resolution the mesh stage's
points lie 0.166 mm median / 0.318 mm p95 from the scanner's reference cloud (188 k points),
against 0.183 / 0.422 mm for 37 k code-centroid matches (``tests/test_real_bust_mesh.py``
measures both in one run; ``docs/mesh.md``).

References
----------
Herakleous & Poullis, *3DUNDERWORLD-SLS: an open-source structured-light scanning system*
(2014) — the code-centroid matching this replaces.
"""

from __future__ import annotations

import math

import numpy as np

from facegeo.checks import as_array
from facegeo.errors import InputError, ShapeError

__all__ = ["CodeInterpolation", "CodeNoise", "CodeSet", "code_region_size",
           "interpolate_code_map", "interpolate_code_values", "shared_code_fraction"]

#: Rows per strip of :func:`interpolate_code_map` (its float64 moment planes are held for one
#: strip plus the window's halo: ≈ 12 planes × strip × width × 8 bytes).
_STRIP_ROWS = 256


def _float_dtype(a):
    """The dtype to check ``a`` as: its own when floating (a float32 decode map stays float32,
    half the memory of a float64 copy; every use converts its values exactly), else float64."""
    a = np.asarray(a)
    return a.dtype if a.dtype.kind == "f" else np.float64


def _maps(x, y):
    xa = as_array(x, "x", dtype=_float_dtype(x), finite=False)
    ya = as_array(y, "y", dtype=_float_dtype(y), shape=xa.shape, finite=False)
    if xa.ndim != 2:
        raise ShapeError(f"x, y: expected two (H, W) code maps, got shape {xa.shape}")
    return xa, ya


def shared_code_fraction(x, y) -> float:
    """Fraction of the valid pixels whose code equals a 4-neighbour's exactly.

    A Gray-code decode names a block's centre, the same float for every pixel of the region;
    a phase-shift decode is continuous and two pixels' codes are never equal (rounding them
    would count a camera that merely out-samples the projector).

    Parameters
    ----------
    x, y : (H, W) float, projector pixels, NaN where invalid

    Returns
    -------
    float in [0, 1]
        0 for a continuous (phase-shift) decode, close to 1 when the cameras out-resolve the
        projector; 0 when no pixel is valid.
    """
    xa, ya = _maps(x, y)
    ok = np.isfinite(xa) & np.isfinite(ya)
    if not ok.any():
        return 0.0
    kx = np.where(ok, xa, np.nan)
    ky = np.where(ok, ya, np.nan)
    same = np.zeros(ok.shape, bool)
    for sl_a, sl_b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                       ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        eq = (kx[sl_a] == kx[sl_b]) & (ky[sl_a] == ky[sl_b])
        same[sl_a] |= eq
        same[sl_b] |= eq
    return float(same[ok].mean())


def code_region_size(x, y) -> float:
    """Median number of camera pixels that share one integer code (valid pixels only).

    Parameters
    ----------
    x, y : (H, W) float, projector pixels, NaN where invalid

    Returns
    -------
    float, pixels (1.0 when no pixel is valid)
    """
    xa, ya = _maps(x, y)
    ok = np.isfinite(xa) & np.isfinite(ya)
    if not ok.any():
        return 1.0
    # in float64, as the codes' own values (x + 0.5 in float32 would round)
    kx = np.floor(xa[ok].astype(np.float64) + 0.5).astype(np.int64)
    ky = np.floor(ya[ok].astype(np.float64) + 0.5).astype(np.int64)
    key = (kx - kx.min()) * (int(ky.max() - ky.min()) + 1) + (ky - ky.min())
    _, counts = np.unique(key, return_counts=True)
    # the median over pixels (a pixel's region size), not over regions
    return float(np.median(np.repeat(counts, counts)))


class CodeInterpolation:
    """Result of :func:`interpolate_code_map`.

    Attributes
    ----------
    code : (H, W) float64, projector pixels
        The plane's value at each pixel centre; NaN where the window held too few valid pixels
        or the plane departs from the pixel's own code by more than its region.
    sigma : (H, W) float32, projector pixels
        RMS residual of the window's codes about the plane (for a clean staircase of
        ``w``-pixel codes ≈ ``w / sqrt(12)``); NaN where ``code`` is.
    window : int
        Side of the square window, pixels.
    """

    __slots__ = ("code", "sigma", "window")

    def __init__(self, code, sigma, window):
        self.code, self.sigma, self.window = code, sigma, window


def _check_fit_settings(code, window, min_count):
    c = as_array(code, "code", dtype=_float_dtype(code), finite=False)
    if c.ndim != 2:
        raise ShapeError(f"code: expected an (H, W) map, got shape {c.shape}")
    if isinstance(window, bool) or int(window) != window or window < 3 or window % 2 == 0:
        raise InputError(f"window: expected an odd integer >= 3, got {window!r}")
    if isinstance(min_count, bool) or int(min_count) != min_count or min_count < 3:
        raise InputError(f"min_count: expected an integer >= 3, got {min_count!r}")
    return c, int(window), int(min_count)


def interpolate_code_map(code, *, window: int, min_count: int = 8,
                         max_departure=None) -> CodeInterpolation:
    """The least-squares plane of a code map over a square window, at each pixel.

    For every valid pixel ``(u, v)``, fit ``c ≈ a + b (u' − u) + d (v' − v)`` to the valid
    codes ``c`` of the pixels ``(u', v')`` within the ``window × window`` square centred on it;
    the interpolated code is ``a``. The moments are box sums (``cv2.filter2D`` with the centred
    coordinate kernels), computed in strips of :data:`_STRIP_ROWS` rows so the working set is
    bounded whatever the image size (:func:`interpolate_code_values` gives the codes at chosen
    pixels only, without the ``(H, W)`` outputs).

    Parameters
    ----------
    code : (H, W) float, projector pixels, NaN where invalid
    window : int, odd, >= 3
        Should span a few code regions (e.g. ``2 ceil(sqrt(region size)) + 1``).
    min_count : int, >= 3
        Fewest valid pixels in the window for a fit.
    max_departure : float or (H, W) float, projector pixels, optional
        A pixel whose plane value departs from its own code by more than this is dropped (an
        occlusion edge mixing two surfaces, a wrong code). Default ``max(1, σ·√12)``, σ the window's RMS residual
        per pixel: one code region of the window's own staircase.

    Returns
    -------
    CodeInterpolation
    """
    c, window, min_count = _check_fit_settings(code, window, min_count)
    H, W = c.shape
    out = np.full((H, W), np.nan)
    sig = np.full((H, W), np.nan, np.float32)
    for rows, cols, a, rms in _plane_fits(c, window, min_count, max_departure):
        out[rows, cols] = a
        sig[rows, cols] = rms
    return CodeInterpolation(out, sig, window)


def interpolate_code_values(code, index, *, window: int, min_count: int = 8,
                            max_departure=None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`interpolate_code_map` at the pixels ``index`` only (no ``(H, W)`` outputs).

    Parameters
    ----------
    code : (H, W) float, projector pixels, NaN where invalid
    index : (n,) int, flat pixel indices (row-major), ascending
    window, min_count, max_departure
        :func:`interpolate_code_map`.

    Returns
    -------
    code : (n,) float64, projector pixels (NaN where :func:`interpolate_code_map` gives NaN)
    sigma : (n,) float32, projector pixels (likewise)
    """
    c, window, min_count = _check_fit_settings(code, window, min_count)
    index = np.asarray(index, np.int64)
    out = np.full(index.size, np.nan)
    sig = np.full(index.size, np.nan, np.float32)
    W = c.shape[1]
    for rows, cols, a, rms in _plane_fits(c, window, min_count, max_departure):
        flat = rows * W + cols
        pos = np.minimum(np.searchsorted(index, flat), max(index.size - 1, 0))
        hit = index[pos] == flat if index.size else np.zeros(flat.size, bool)
        out[pos[hit]] = a[hit]
        sig[pos[hit]] = rms[hit]
    return out, sig


def _plane_fits(c, window: int, min_count: int, max_departure):
    """The plane fits of :func:`interpolate_code_map`, one strip of :data:`_STRIP_ROWS` rows at
    a time: yields ``(rows, cols, code (k,) float64, rms (k,) float64)`` of the kept pixels."""
    import cv2

    H, W = c.shape
    r = window // 2
    off = np.arange(-r, r + 1, dtype=np.float64)
    du = np.broadcast_to(off[None, :], (window, window))
    dv = np.broadcast_to(off[:, None], (window, window))
    kernels = {"n": np.ones((window, window)), "u": du, "v": dv, "uu": du * du, "vv": dv * dv,
               "uv": du * dv}
    dep = None if max_departure is None else np.broadcast_to(
        np.asarray(max_departure, np.float64), (H, W))
    for r0 in range(0, H, _STRIP_ROWS):
        r1 = min(H, r0 + _STRIP_ROWS)
        a0, a1 = max(0, r0 - r), min(H, r1 + r)
        cs = c[a0:a1].astype(np.float64)  # float64 sums (exact from a float32 map)
        ok = np.isfinite(cs)
        w = ok.astype(np.float64)
        cz = np.where(ok, cs, 0.0)
        # correlation (filter2D does not flip): M[p] = sum_o K[o] f[p + o]
        f = lambda img, k: cv2.filter2D(img, cv2.CV_64F, k, borderType=cv2.BORDER_CONSTANT)
        m = {k: f(w, kern) for k, kern in kernels.items()}
        sc, suc, svc = f(cz, kernels["n"]), f(cz, du), f(cz, dv)
        scc = f(cz * cz, kernels["n"])
        s = slice(r0 - a0, r0 - a0 + (r1 - r0))
        m = {k: v[s] for k, v in m.items()}
        sc, suc, svc, scc, oks = sc[s], suc[s], svc[s], scc[s], ok[s]
        good = oks & (m["n"] >= min_count)
        if not good.any():
            continue
        idx = np.nonzero(good)
        A = np.empty((idx[0].size, 3, 3))
        A[:, 0, 0], A[:, 0, 1], A[:, 0, 2] = m["n"][idx], m["u"][idx], m["v"][idx]
        A[:, 1, 1], A[:, 1, 2], A[:, 2, 2] = m["uu"][idx], m["uv"][idx], m["vv"][idx]
        A[:, 1, 0], A[:, 2, 0], A[:, 2, 1] = A[:, 0, 1], A[:, 0, 2], A[:, 1, 2]
        b = np.stack([sc[idx], suc[idx], svc[idx]], -1)
        # a window whose valid pixels lie on one line has no plane: skip it
        det = np.linalg.det(A)
        scale = (A[:, 1, 1] + A[:, 2, 2]) * A[:, 0, 0]
        fit = det > 1e-6 * np.maximum(scale, 1e-12) * np.maximum(A[:, 1, 1] + A[:, 2, 2], 1e-12)
        theta = np.full((idx[0].size, 3), np.nan)
        if fit.any():
            theta[fit] = np.linalg.solve(A[fit], b[fit][..., None])[..., 0]
        rss = np.maximum(scc[idx] - np.einsum("ni,ni->n", theta, b), 0.0)
        dof = np.maximum(m["n"][idx] - 3.0, 1.0)
        rms = np.sqrt(rss / dof)
        own = cs[s][idx]
        lim = dep[r0:r1][idx] if dep is not None else np.maximum(1.0, rms * math.sqrt(12.0))
        keep = fit & (np.abs(theta[:, 0] - own) <= lim)
        yield idx[0][keep] + r0, idx[1][keep], theta[keep, 0], rms[keep]


class CodeNoise:
    """A camera's decode noise per pixel and code axis, stored where it is known.

    The ``sigma_x`` / ``sigma_y`` maps of a decode are NaN wherever nothing was decoded; this
    keeps the pixels where either is finite (``index``, flat, ascending) and their values, so
    that the noise can be read at any pixel (:meth:`at`) without ``(H, W)`` maps.

    Attributes
    ----------
    shape : (int, int)
        ``(H, W)`` of the camera.
    index : (m,) int64
        Flat pixel indices (row-major), ascending.
    sigma : (m, 2) float32 or float64, projector pixels
        ``(σ_x, σ_y)`` (1 σ) at ``index``; NaN where that axis gives none.
    """

    __slots__ = ("index", "shape", "sigma")

    def __init__(self, shape, index, sigma):
        self.shape = tuple(int(v) for v in shape)
        self.index = np.asarray(index, np.int64)
        self.sigma = np.asarray(sigma)
        if self.sigma.shape != (self.index.size, 2):
            raise ShapeError(f"sigma: expected shape ({self.index.size}, 2) (one (x, y) per "
                             f"pixel of index), got {self.sigma.shape}")

    @classmethod
    def from_maps(cls, shape, sigma_x=None, sigma_y=None) -> CodeNoise:
        """From ``(H, W)`` maps (or None: unknown), NaN where unknown; values kept in their
        floating dtype."""
        shape = tuple(int(v) for v in shape)
        maps = []
        for m, name in ((sigma_x, "sigma_x"), (sigma_y, "sigma_y")):
            if m is not None:
                m = as_array(m, name, dtype=_float_dtype(m), finite=False)
                if m.shape != shape:
                    raise ShapeError(f"{name}: expected shape {shape} (the decode's x map), got "
                                     f"{m.shape}")
            maps.append(m)
        known = np.zeros(shape, bool)
        for m in maps:
            if m is not None:
                known |= np.isfinite(m)
        index = np.flatnonzero(known)
        dtype = np.result_type(*[m.dtype for m in maps if m is not None], np.float32)
        sigma = np.full((index.size, 2), np.nan, dtype)
        for i, m in enumerate(maps):
            if m is not None:
                sigma[:, i] = m.reshape(-1)[index]
        return cls(shape, index, sigma)

    def at(self, flat, default: float) -> np.ndarray:
        """``(k, 2)`` float64 noise at the flat pixels ``flat``: the stored value where it is
        finite and positive, else ``default``."""
        flat = np.asarray(flat, np.int64)
        out = np.full(flat.shape + (2,), np.nan)
        if self.index.size:
            pos = np.minimum(np.searchsorted(self.index, flat), self.index.size - 1)
            hit = self.index[pos] == flat
            out[hit] = self.sigma[pos[hit]]
        return np.where(np.isfinite(out) & (out > 0), out, default)

    def grid(self, default: float) -> np.ndarray:
        """The ``(H, W, 2)`` float64 map of :meth:`at` (tests and small maps)."""
        return self.at(np.arange(self.shape[0] * self.shape[1]), default).reshape(
            self.shape + (2,))


class CodeSet:
    """One camera's decoded projector codes at the pixels that have both, compressed.

    A full-resolution camera decodes about a quarter of its 16 M pixels; its ``(H, W)`` code
    maps are mostly NaN. Camera–camera triangulation
    (:func:`facegeo.geometry.triangulation.triangulate_code_sets`) works on these arrays only.

    Attributes
    ----------
    shape : (int, int)
        ``(H, W)`` of the camera.
    index : (n,) int64
        Flat pixel indices (row-major) of the pixels with both codes, ascending.
    x, y : (n,) float64, projector pixels
        The codes there.
    confidence : (n,) float32, 0..1, or None
        The decode's confidence there (None: 1).
    noise : CodeNoise
        The decode noise (``sigma_x``, ``sigma_y``), at any pixel where it is known.
    """

    __slots__ = ("confidence", "index", "noise", "shape", "x", "y")

    def __init__(self, shape, index, x, y, *, confidence=None, noise=None):
        self.shape = tuple(int(v) for v in shape)
        self.index = np.asarray(index, np.int64)
        n = self.index.size
        self.x = as_array(x, "x", shape=(n,), finite=False)
        self.y = as_array(y, "y", shape=(n,), finite=False)
        self.confidence = (None if confidence is None else
                           as_array(confidence, "confidence", shape=(n,), dtype=np.float32,
                                    finite=False))
        self.noise = noise if noise is not None else CodeNoise(
            self.shape, np.zeros(0, np.int64), np.zeros((0, 2), np.float32))

    def __len__(self) -> int:
        return int(self.index.size)

    @classmethod
    def from_maps(cls, x, y, *, sigma_x=None, sigma_y=None, confidence=None) -> CodeSet:
        """From ``(H, W)`` maps: ``x``, ``y`` (NaN invalid; the pixels with both finite are
        kept), optional ``sigma_x``, ``sigma_y`` (kept wherever finite) and ``confidence``."""
        xa, ya = _maps(x, y)
        if xa.ndim != 2:
            raise ShapeError(f"x, y: expected two (H, W) code maps, got shape {xa.shape}")
        index = np.flatnonzero(np.isfinite(xa) & np.isfinite(ya))
        conf = None
        if confidence is not None:
            c = as_array(confidence, "confidence", dtype=np.float32, finite=False)
            if c.shape != xa.shape:
                raise ShapeError(f"confidence: expected shape {xa.shape} (the decode's x map), "
                                 f"got {c.shape}")
            conf = c.reshape(-1)[index]
        return cls(xa.shape, index, xa.reshape(-1)[index].astype(np.float64),
                   ya.reshape(-1)[index].astype(np.float64), confidence=conf,
                   noise=CodeNoise.from_maps(xa.shape, sigma_x, sigma_y))

    def grids(self) -> tuple[np.ndarray, np.ndarray]:
        """The ``(H, W)`` float64 code maps (NaN elsewhere)."""
        out = []
        for v in (self.x, self.y):
            g = np.full(self.shape[0] * self.shape[1], np.nan)
            g[self.index] = v
            out.append(g.reshape(self.shape))
        return out[0], out[1]
