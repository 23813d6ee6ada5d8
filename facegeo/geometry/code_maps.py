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

__all__ = ["CodeInterpolation", "code_region_size", "interpolate_code_map",
           "shared_code_fraction"]

#: Rows per strip of :func:`interpolate_code_map` (its float64 moment planes are held for one
#: strip plus the window's halo: ≈ 12 planes × strip × width × 8 bytes).
_STRIP_ROWS = 256


def _maps(x, y):
    xa = as_array(x, "x", finite=False)
    ya = as_array(y, "y", shape=xa.shape, finite=False)
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
    kx = np.floor(xa[ok] + 0.5).astype(np.int64)
    ky = np.floor(ya[ok] + 0.5).astype(np.int64)
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


def interpolate_code_map(code, *, window: int, min_count: int = 8,
                         max_departure=None) -> CodeInterpolation:
    """The least-squares plane of a code map over a square window, at each pixel.

    For every valid pixel ``(u, v)``, fit ``c ≈ a + b (u' − u) + d (v' − v)`` to the valid
    codes ``c`` of the pixels ``(u', v')`` within the ``window × window`` square centred on it;
    the interpolated code is ``a``. The moments are box sums (``cv2.filter2D`` with the centred
    coordinate kernels), computed in strips of :data:`_STRIP_ROWS` rows so the working set is
    bounded whatever the image size.

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
    import cv2

    c = as_array(code, "code", finite=False)
    if c.ndim != 2:
        raise ShapeError(f"code: expected an (H, W) map, got shape {c.shape}")
    if isinstance(window, bool) or int(window) != window or window < 3 or window % 2 == 0:
        raise InputError(f"window: expected an odd integer >= 3, got {window!r}")
    if isinstance(min_count, bool) or int(min_count) != min_count or min_count < 3:
        raise InputError(f"min_count: expected an integer >= 3, got {min_count!r}")
    window, min_count = int(window), int(min_count)
    H, W = c.shape
    r = window // 2
    off = np.arange(-r, r + 1, dtype=np.float64)
    du = np.broadcast_to(off[None, :], (window, window))
    dv = np.broadcast_to(off[:, None], (window, window))
    kernels = {"n": np.ones((window, window)), "u": du, "v": dv, "uu": du * du, "vv": dv * dv,
               "uv": du * dv}
    out = np.full((H, W), np.nan)
    sig = np.full((H, W), np.nan, np.float32)
    dep = None if max_departure is None else np.broadcast_to(
        np.asarray(max_departure, np.float64), (H, W))
    for r0 in range(0, H, _STRIP_ROWS):
        r1 = min(H, r0 + _STRIP_ROWS)
        a0, a1 = max(0, r0 - r), min(H, r1 + r)
        cs = c[a0:a1]
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
        own = c[r0:r1][idx]
        lim = dep[r0:r1][idx] if dep is not None else np.maximum(1.0, rms * math.sqrt(12.0))
        keep = fit & (np.abs(theta[:, 0] - own) <= lim)
        rows, cols = idx[0][keep] + r0, idx[1][keep]
        out[rows, cols] = theta[keep, 0]
        sig[rows, cols] = rms[keep]
    return CodeInterpolation(out, sig, window)
