"""Per-pixel Lambertian photometric stereo by least squares: the baseline a reflectance model
must beat on real captures (issue 36).

A Lambertian surface point lit by a distant light of direction l and intensity E_l (per
channel c) has the radiance ``R_lc = ρ_c E_lc max(0, n·l)``. Where it is lit, ``R_lc / E_lc =
l · b_c`` with ``b_c = ρ_c n``: linear in b_c, so over the lights fitted (rows ``L``, unit
directions) the least-squares solution with every light weighted equally is

    b_c = pinv(L) (R_c / E_c)                      (Woodham 1980, per channel)

— one 3 × L matrix for all the pixels whose samples are all used. Samples the caller leaves
out (saturated, too dark: a shadow, where ``max(0, ·)`` breaks the linear model, untrusted,
non-finite) change the rows per pixel: those pixels solve their normal equations
``(Σ_l w_l l lᵀ) b_c = Σ_l w_l l R_lc / E_lc`` (w ∈ {0, 1}) as a batch of 3 × 3 systems.
The normal is ``n = normalize(Σ_c b_c)``, the albedo ``ρ_c = |b_c|``, and a light l' is
predicted as ``max(0, l'·b_c) E_l'c`` (:meth:`LambertianFit.predict`).

The held-out protocol (:func:`held_out_lambertian`): fit on every other light
(:func:`split_lights`), predict the others, and report inside a mask

* relative MAE  ``Σ |p − o| / Σ o``,
* relative RMSE ``sqrt(Σ (p − o)²) / sqrt(Σ o²)``,

sums over held-out lights, pixels and channels, in the frames' units (p the prediction, o the
observed value; untrusted observations left out and counted), and the mean and median angle
between the fitted normals and a reference normal map.

Solves in float64, in chunks of pixels (:data:`CHUNK_SAMPLES` samples at a time), so memory is
bounded by a chunk plus the per-pixel results.

References
----------
.. [1] R. J. Woodham, "Photometric method for determining surface orientation from multiple
   images", Optical Engineering 19(1), 1980.
.. [2] B. Shi et al., "A Benchmark Dataset and Evaluation for Non-Lambertian and Uncalibrated
   Photometric Stereo", CVPR 2016 / TPAMI 2019 (DiLiGenT; its least-squares baseline: mean
   angular error 4.1° on ``ball``, 8.4° on ``cat`` with all 96 lights).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from facegeo.checks import as_array, check_choice, check_positive_int, fmt_value
from facegeo.errors import InputError, ShapeError

__all__ = ["CHUNK_SAMPLES", "MIN_RCOND", "LambertianFit", "HeldOutScore", "fit_lambertian",
           "held_out_lambertian", "split_lights", "lights_within", "angular_error_deg"]

log = logging.getLogger(__name__)

#: Samples (pixel × light × channel) read and solved at a time: 16 MB of float64 per chunk.
CHUNK_SAMPLES = 1 << 21
#: Smallest ratio λ_min / λ_max of the used lights' Gram matrix Σ l lᵀ a pixel may have: below
#: it the lights it keeps (nearly coplanar, or fewer than 3) do not determine b, and the pixel
#: has no fit (NaN, ``valid`` False). 1e-6 is a condition number of 1000 for the lights' rows.
MIN_RCOND = 1e-6
#: ``channels`` choices: one b per channel, or one b for the channel means (mean R / mean E).
CHANNELS = ("each", "grey")


@dataclass
class LambertianFit:
    """Per-pixel Lambertian least squares (:func:`fit_lambertian`).

    Attributes
    ----------
    b : (N, C, 3) float64, the lights' frame
        ``ρ_c n`` per channel, in units of the input divided by the light intensities; NaN where
        ``valid`` is False. C is the input's channel count (1 with ``channels="grey"``).
    valid : (N,) bool
        The solve succeeded: at least 3 used lights spanning 3-D (:data:`MIN_RCOND`).
    n_lights_used : (N,) int32
        Lights whose sample the fit used.
    channels : {"each", "grey"}
    normal : (N, 3) float64, unit, the lights' frame
        ``normalize(Σ_c b_c)``; NaN where there is no fit or ``b = 0`` (a black pixel: its
        prediction, 0, is still defined).
    albedo : (N, C) float64
        ``|b_c|``; NaN where there is no fit.
    """

    b: np.ndarray
    valid: np.ndarray
    n_lights_used: np.ndarray
    channels: str
    normal: np.ndarray = field(init=False, repr=False)
    albedo: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        s = self.b.sum(axis=1)
        norm = np.linalg.norm(s, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            self.normal = np.where((norm > 0)[:, None], s / norm[:, None], np.nan)
        self.albedo = np.linalg.norm(self.b, axis=-1)

    @property
    def n_pixels(self) -> int:
        return int(self.b.shape[0])

    def predict(self, directions, intensities=None) -> np.ndarray:
        """Radiance under other lights: ``max(0, l·b_c) E_lc``.

        Parameters
        ----------
        directions : (L', 3) array_like, the lights' frame (normalised here)
        intensities : None, (L',) or (L', 3) array_like, linear, > 0
            As for :func:`fit_lambertian` (default 1; channel mean with a grey fit).

        Returns
        -------
        (N, L', C) float32
            NaN for pixels without a fit.
        """
        D = _unit_directions(directions, "directions")
        E = _intensities(intensities, D.shape[0], self.b.shape[1], self.channels)
        out = np.empty((self.n_pixels, D.shape[0], self.b.shape[1]), np.float32)
        rows = max(1, CHUNK_SAMPLES // max(1, D.shape[0] * self.b.shape[1]))
        for i in range(0, self.n_pixels, rows):
            out[i:i + rows] = _predict(self.b[i:i + rows], D, E)
        return out


@dataclass
class HeldOutScore:
    """Held-out lights predicted by the Lambertian fit (:func:`held_out_lambertian`).

    Attributes
    ----------
    rel_mae : float
        ``Σ |p − o| / Σ o`` over the compared samples (held-out lights × masked pixels with a
        fit × channels, trusted observations only), frames' units. NaN if nothing compared.
    rel_rmse : float
        ``sqrt(Σ (p − o)²) / sqrt(Σ o²)`` over the same samples.
    samples : int
        Held-out (pixel, light) samples compared.
    untrusted : int
        Held-out (pixel, light) samples of fitted pixels left out: saturated, marked invalid by
        the caller, or non-finite.
    pixels : int
        Pixels in the mask.
    pixels_unfitted : int
        Of those, pixels without a fit (fewer than 3 usable fitted lights, or degenerate):
        their samples are not compared.
    normal_mean_error_deg, normal_median_error_deg : float or None
        Mean and median angle between fitted and reference normals over the masked pixels with a
        fit, a defined normal and a finite reference; None without ``normal_ref``.
    normals_compared : int
    fit_lights, held_lights : (k,) int64
        The light indices fitted and predicted.
    fit : LambertianFit
        The fit, every row of the input (rows outside the mask have no fit).
    seconds : float
        Wall time of the fit and the scoring.
    """

    rel_mae: float
    rel_rmse: float
    samples: int
    untrusted: int
    pixels: int
    pixels_unfitted: int
    normal_mean_error_deg: float | None
    normal_median_error_deg: float | None
    normals_compared: int
    fit_lights: np.ndarray
    held_lights: np.ndarray
    fit: LambertianFit = field(repr=False)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        """The figures as JSON-ready numbers (no arrays but the light indices)."""
        return {"rel_mae": self.rel_mae, "rel_rmse": self.rel_rmse, "samples": self.samples,
                "untrusted": self.untrusted, "pixels": self.pixels,
                "pixels_unfitted": self.pixels_unfitted,
                "normal_mean_error_deg": self.normal_mean_error_deg,
                "normal_median_error_deg": self.normal_median_error_deg,
                "normals_compared": self.normals_compared,
                "fit_lights": self.fit_lights.tolist(), "held_lights": self.held_lights.tolist(),
                "seconds": self.seconds}


# --------------------------------------------------------------------------- inputs
def _unit_directions(d, name: str) -> np.ndarray:
    D = as_array(d, name, shape=(None, 3))
    norm = np.linalg.norm(D, axis=1)
    bad = np.flatnonzero(~(norm > 1e-12))
    if bad.size:
        raise InputError(f"{name}[{int(bad[0])}]: zero-length vector, which has no direction")
    return D / norm[:, None]


def _reflectance(R) -> np.ndarray:
    """R as an ``(N, L, C)`` array (a view where possible; NaN allowed)."""
    a = np.asarray(R)
    if a.dtype.kind not in "fiu":
        raise ShapeError(f"R: expected a numeric array, got dtype {a.dtype}")
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] < 1:
        raise ShapeError(f"R: expected shape (N, L) or (N, L, C), got {a.shape}")
    return a


def _intensities(E, L: int, C: int, channels: str) -> np.ndarray:
    """``(L, C_fit)`` float64 intensities (C_fit = 1 for a grey fit)."""
    if E is None:
        e = np.ones((L, C))
    else:
        e = as_array(E, "intensities")
        if e.shape == (L,):
            e = np.repeat(e[:, None], C, axis=1)
        elif e.ndim == 2 and e.shape[0] == L and e.shape[1] != C and C == 1:
            e = e.mean(axis=1, keepdims=True)  # a grey frame lit by an RGB light
        if e.shape != (L, C):
            raise ShapeError(f"intensities: expected shape ({L},) or ({L}, {C}), got {e.shape}")
        if (e <= 0).any():
            k = int(np.argwhere(e <= 0)[0][0])
            raise InputError(f"intensities[{k}]: light intensities must be > 0, got {e[k]}")
    return e.mean(axis=1, keepdims=True) if channels == "grey" else e


def _mask_rows(m, name: str, N: int) -> np.ndarray:
    a = np.asarray(m)
    if a.dtype != bool or a.shape != (N,):
        raise ShapeError(f"{name}: expected an ({N},) bool array, got {a.dtype} {a.shape}")
    return a


def _check_chunk(chunk, L: int, C: int) -> int:
    if chunk is None:
        return max(1, CHUNK_SAMPLES // max(1, L * C))
    return check_positive_int(chunk, "chunk")


# --------------------------------------------------------------------------- kernels
def _usable(Rc: np.ndarray, valid_c, dark, saturation) -> np.ndarray:
    """``(n, L)`` bool: samples a fit may use (finite, trusted, not saturated, not dark)."""
    use = np.isfinite(Rc).all(axis=2)
    if valid_c is not None:
        use &= valid_c
    if saturation is not None:
        use &= ~(Rc >= saturation).any(axis=2)
    if dark is not None:
        use &= Rc.mean(axis=2) > dark
    return use


def _solve_chunk(Rc: np.ndarray, use: np.ndarray, D: np.ndarray, pinv_D: np.ndarray,
                 E: np.ndarray, grey: bool) -> tuple[np.ndarray, np.ndarray]:
    """b ``(n, C, 3)`` (NaN where unsolved) and the used-light counts of one chunk."""
    with np.errstate(invalid="ignore"):
        X = Rc / E[None]  # (n, L, C): R / E, float64
    if grey:
        X = X.mean(axis=2, keepdims=True)
    X = np.where(use[..., None], X, 0.0)  # left-out samples weigh 0 (NaN included)
    n, _, C = X.shape
    B = np.full((n, C, 3), np.nan)
    count = use.sum(axis=1).astype(np.int32)
    full = count == use.shape[1]
    if full.any():  # every sample used: the one pseudo-inverse
        B[full] = np.matmul(X[full].transpose(0, 2, 1), pinv_D.T)
    part = np.flatnonzero(~full & (count >= 3))
    if part.size:  # normal equations of each pixel's own lights, a batch of 3 x 3 systems
        DD = (D[:, :, None] * D[:, None, :]).reshape(-1, 9)
        G = (use[part].astype(np.float64) @ DD).reshape(-1, 3, 3)
        h = np.matmul(X[part].transpose(0, 2, 1), D)  # (m, C, 3)
        ev = np.linalg.eigvalsh(G)
        ok = ev[:, 0] > MIN_RCOND * ev[:, 2]
        if ok.any():
            sol = np.linalg.solve(G[ok], h[ok].transpose(0, 2, 1))  # (m, 3, C)
            B[part[ok]] = sol.transpose(0, 2, 1)
    return B, count


def _predict(b: np.ndarray, D: np.ndarray, E: np.ndarray) -> np.ndarray:
    """``max(0, l·b_c) E_lc``, ``(n, L', C)`` float64 (NaN rows stay NaN)."""
    s = np.matmul(b, D.T).transpose(0, 2, 1)  # (n, L', C)
    return np.maximum(s, 0.0) * E[None]  # np.maximum keeps NaN


# --------------------------------------------------------------------------- public
def fit_lambertian(R, directions, *, intensities=None, channels: str = "each",
                   dark: float | None = None, saturation: float | None = None, valid=None,
                   rows=None, chunk: int | None = None) -> LambertianFit:
    """Per-pixel Lambertian least squares, ``b_c = pinv(L) (R_c / E_c)`` (Woodham 1980).

    Parameters
    ----------
    R : (N, L, C) or (N, L) array_like, linear radiance, frames' units
        One row per pixel, one column per light (e.g. OLAT frames ``(H, W, L, C)`` reshaped).
        NaN marks a sample to leave out. Any dtype; solved in float64, chunk by chunk (a
        memory-mapped R is read one chunk at a time).
    directions : (L, 3) array_like, unit, from the surface toward each light
        Normalised here (published directions are often rounded). The frame of the normals.
    intensities : None, (L,) or (L, C) array_like, linear, > 0, optional
        E_l: each sample is divided by its light's intensity (DiLiGenT's
        ``light_intensities.txt``, a :class:`~facegeo.geometry.lights.LightList`'s
        ``intensities``). Default 1. RGB intensities with grey R: their channel mean.
    channels : {"each", "grey"}
        ``"each"``: one b per channel; ``"grey"``: one b for the channel means, mean_c R / mean_c E.
    dark : float, optional
        Leave out samples whose channel mean (frames' units, before dividing by E) is ≤ this:
        shadows, where the clamp ``max(0, n·l)`` makes the model non-linear. Default: use all.
    saturation : float, optional
        Leave out samples with any channel ≥ this (frames' units; 1.0 for integer frames read
        linearly). Default: use all.
    valid : (N, L) bool array_like, optional
        False where a sample cannot be trusted (``Scan.olat_frame(..., return_mask=True)``).
    rows : (N,) bool array_like, optional
        Fit only these pixels (the others get no fit); default all.
    chunk : int, optional
        Pixels per chunk; default ``CHUNK_SAMPLES // (L·C)``. Results do not depend on it.

    Returns
    -------
    LambertianFit
        Pixels with fewer than 3 used lights, or whose used lights are nearly coplanar
        (:data:`MIN_RCOND`), have NaN and ``valid`` False; the fit never raises for them.

    Raises
    ------
    InputError, ShapeError
        Shapes that do not agree, zero directions or intensities ≤ 0, an unknown ``channels``,
        fitted lights that do not span 3-D (every pixel would be degenerate).
    """
    check_choice(channels, "channels", CHANNELS)
    R, D = _field_and_lights(R, directions)
    N, L, C = R.shape
    E = _intensities(intensities, L, C, channels)
    pinv_D = _pinv_spanning(D, "directions")
    V = None if valid is None else _sample_mask(valid, N, L)
    sel = np.arange(N) if rows is None else np.flatnonzero(_mask_rows(rows, "rows", N))
    dark = None if dark is None else float(dark)
    saturation = None if saturation is None else float(saturation)
    Cf = 1 if channels == "grey" else C
    b = np.full((N, Cf, 3), np.nan)
    used = np.zeros(N, np.int32)
    step = _check_chunk(chunk, L, C)
    for i in range(0, sel.size, step):
        r = sel[i:i + step]
        Rc = np.asarray(R[r], np.float64)
        use = _usable(Rc, None if V is None else V[r], dark, saturation)
        b[r], used[r] = _solve_chunk(Rc, use, D, pinv_D, E, channels == "grey")
    return LambertianFit(b=b, valid=np.isfinite(b).all(axis=(1, 2)), n_lights_used=used,
                         channels=channels)




def _field_and_lights(R, directions):
    """``R`` checked (:func:`_reflectance`) and the unit ``directions`` (L, 3), one per light of
    R's axis 1."""
    R = _reflectance(R)
    D = _unit_directions(directions, "directions")
    if D.shape[0] != R.shape[1]:
        raise ShapeError(f"directions: {D.shape[0]} lights, but R has {R.shape[1]} (axis 1)")
    return R, D

def _add_held_out(sums: np.ndarray, p, obs, trust) -> None:
    """Add a chunk's held-out error to ``sums`` = (Σ|e|, Σe², Σo, Σo²) in place: prediction
    ``p`` and observation ``obs`` (n, Lh, C), only where ``trust`` (n, Lh)."""
    e = np.where(trust[..., None], p - obs, 0.0)
    o = np.where(trust[..., None], obs, 0.0)
    sums += (np.abs(e).sum(), (e * e).sum(), o.sum(), (o * o).sum())


def _relative_errors(sums: np.ndarray, samples: int) -> tuple[float, float]:
    """``(rel_mae, rel_rmse)`` of :func:`_add_held_out`'s sums (NaN without samples)."""
    if not samples:
        return float("nan"), float("nan")
    with np.errstate(invalid="ignore", divide="ignore"):
        return float(sums[0] / sums[2]), float(np.sqrt(sums[1] / sums[3]))


def _normal_errors(normal, ref, m) -> tuple[float | None, float | None, int]:
    """Mean and median angle (degrees) of ``normal`` against ``ref`` over the rows ``m`` where
    both are finite, and how many were compared; ``(None, None, 0)`` without a reference."""
    if ref is None:
        return None, None, 0
    err = angular_error_deg(normal[m], ref[m])
    err = err[np.isfinite(err)]
    if not err.size:
        return None, None, 0
    return float(err.mean()), float(np.median(err)), int(err.size)

def held_out_lambertian(R, directions, *, fit=None, held=None, intensities=None,
                        mask=None, normal_ref=None, channels: str = "each",
                        dark: float | None = None, saturation: float | None = None, valid=None,
                        chunk: int | None = None) -> HeldOutScore:
    """Fit the Lambertian model on some lights and score its prediction of the others.

    Parameters
    ----------
    R : (N, L, C) or (N, L) array_like, linear radiance, frames' units
        Every light's samples (fitted and held out), as for :func:`fit_lambertian`.
    directions : (L, 3) array_like, from the surface toward each light
    fit, held : (k,) int array_like, optional
        Light indices to fit and to predict; default :func:`split_lights` over all lights
        (even positions fitted, odd ones held out). Given one, the other defaults to the rest.
    intensities : None, (L,) or (L, C) array_like
        As for :func:`fit_lambertian`; the prediction is multiplied by them, so errors are in
        the frames' units.
    mask : (N,) bool array_like, optional
        Pixels to fit and score (the object); default all.
    normal_ref : (N, 3) array_like, same frame as ``directions``, optional
        Reference normals (NaN where there are none) for the angular error.
    channels, dark, saturation, valid, chunk
        As for :func:`fit_lambertian`. ``dark`` only selects the fitted samples: a dark
        held-out sample is a measurement the model must predict. Saturated, invalid and
        non-finite held-out samples are left out of the errors (counted in ``untrusted``).

    Returns
    -------
    HeldOutScore
        ``rel_mae = Σ|p − o| / Σ o``, ``rel_rmse = sqrt(Σ(p − o)²) / sqrt(Σ o²)`` over the
        held-out samples of masked, fitted pixels, p = ``max(0, l·b_c) E_lc``; with a grey
        fit, o is the channel mean of R and p uses the channel mean of E.
    """
    t0 = time.perf_counter()
    check_choice(channels, "channels", CHANNELS)
    R, D = _field_and_lights(R, directions)
    N, L, C = R.shape
    fit_l, held_l = _fit_and_held(fit, held, L)
    E = _intensities(intensities, L, C, channels)
    pinv_D = _pinv_spanning(D[fit_l], "directions[fit]")
    V = None if valid is None else _sample_mask(valid, N, L)
    m = np.ones(N, bool) if mask is None else _mask_rows(mask, "mask", N)
    ref = None
    if normal_ref is not None:
        ref = as_array(normal_ref, "normal_ref", shape=(N, 3), finite=False)
    dark = None if dark is None else float(dark)
    saturation = None if saturation is None else float(saturation)
    grey = channels == "grey"
    Cf = 1 if grey else C
    b = np.full((N, Cf, 3), np.nan)
    used = np.zeros(N, np.int32)
    sums = np.zeros(4)  # Σ|e|, Σe², Σo, Σo²
    samples = untrusted = 0
    sel = np.flatnonzero(m)
    step = _check_chunk(chunk, L, C)
    for i in range(0, sel.size, step):
        r = sel[i:i + step]
        Rc = np.asarray(R[r], np.float64)
        Vc = None if V is None else V[r]
        Rf = Rc[:, fit_l]
        use = _usable(Rf, None if Vc is None else Vc[:, fit_l], dark, saturation)
        bc, used[r] = _solve_chunk(Rf, use, D[fit_l], pinv_D, E[fit_l], grey)
        b[r] = bc
        ok = np.isfinite(bc).all(axis=(1, 2))
        obs = Rc[ok][:, held_l]  # (n', Lh, C)
        trust = _usable(obs, None if Vc is None else Vc[ok][:, held_l], None, saturation)
        untrusted += int(trust.size - np.count_nonzero(trust))
        samples += int(np.count_nonzero(trust))
        if grey:
            obs = obs.mean(axis=2, keepdims=True)
        _add_held_out(sums, _predict(bc[ok], D[held_l], E[held_l]), obs, trust)
    result = LambertianFit(b=b, valid=np.isfinite(b).all(axis=(1, 2)), n_lights_used=used,
                           channels=channels)
    rel_mae, rel_rmse = _relative_errors(sums, samples)
    mean_err, median_err, compared = _normal_errors(result.normal, ref, m)
    score = HeldOutScore(
        rel_mae=rel_mae, rel_rmse=rel_rmse, samples=samples, untrusted=untrusted,
        pixels=int(m.sum()), pixels_unfitted=int(np.count_nonzero(m & ~result.valid)),
        normal_mean_error_deg=mean_err, normal_median_error_deg=median_err,
        normals_compared=compared, fit_lights=fit_l, held_lights=held_l, fit=result,
        seconds=time.perf_counter() - t0)
    log.info("Lambertian held-out: %d lights fitted, %d predicted, %d pixels: relative MAE "
             "%.4f, RMSE %.4f%s", fit_l.size, held_l.size, score.pixels, rel_mae, rel_rmse,
             "" if mean_err is None else f", normals {mean_err:.2f} deg mean")
    return score


def split_lights(lights, *, every: int = 2, offset: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Every ``every``-th light to fit, starting at position ``offset``; the rest held out.

    Parameters
    ----------
    lights : int or (k,) int array_like
        The number of lights (indices 0 … L − 1) or the candidate light indices, in order
        (e.g. :func:`lights_within`'s).
    every : int ≥ 2
    offset : int in [0, every)

    Returns
    -------
    fit, held : (k_f,), (k_h,) int64
        Positions ``offset, offset + every, …`` of ``lights`` and the others, each in order.
    """
    idx = np.arange(int(lights)) if np.ndim(lights) == 0 else np.asarray(lights, np.int64)
    every = check_positive_int(every, "every")
    if every < 2:
        raise InputError(f"every: expected an integer ≥ 2 (one light in `every` fitted), got "
                         f"{fmt_value(every)}")
    if not (isinstance(offset, (int, np.integer)) and 0 <= offset < every):
        raise InputError(f"offset: expected an integer in [0, {every}), got {fmt_value(offset)}")
    pick = np.zeros(idx.size, bool)
    pick[offset::every] = True
    return idx[pick], idx[~pick]


def lights_within(directions, axis, max_angle_deg: float) -> np.ndarray:
    """Indices of the lights strictly less than ``max_angle_deg`` from ``axis``, in order.

    Strictly: a light at the limit itself is out (to 1e-9°, so rounding does not decide), e.g.
    Yale B's ``A±050E+00`` for 50° about the camera's direction.

    Parameters
    ----------
    directions : (L, 3) array_like, toward each light (normalised here)
    axis : (3,) array_like, e.g. toward the camera
    max_angle_deg : float, degrees, in (0, 180]

    Returns
    -------
    (k,) int64
    """
    D = _unit_directions(directions, "directions")
    a = _unit_directions(np.reshape(as_array(axis, "axis", shape=(3,)), (1, 3)), "axis")[0]
    lim = float(max_angle_deg)
    if not 0.0 < lim <= 180.0:
        raise InputError(f"max_angle_deg: expected an angle in (0, 180] degrees, got "
                         f"{fmt_value(max_angle_deg)}")
    ang = np.degrees(np.arccos(np.clip(D @ a, -1.0, 1.0)))
    return np.flatnonzero(ang < lim - 1e-9).astype(np.int64)


def angular_error_deg(n, n_ref) -> np.ndarray:
    """Angle between normals, degrees, ``(N,)`` float64: ``atan2(|n × n_ref|, n·n_ref)``
    (accurate at small angles) of the normalised vectors; NaN where either is non-finite or
    zero."""
    a = as_array(n, "n", shape=(None, 3), finite=False)
    r = as_array(n_ref, "n_ref", shape=(a.shape[0], 3), finite=False)
    na, nr = np.linalg.norm(a, axis=1), np.linalg.norm(r, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        a, r = a / na[:, None], r / nr[:, None]
        ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, r), axis=1), (a * r).sum(1)))
    ang[~((na > 0) & (nr > 0))] = np.nan
    return ang


# --------------------------------------------------------------------------- helpers
def _pinv_spanning(D: np.ndarray, name: str) -> np.ndarray:
    """``pinv(D)`` (3, L); InputError when the lights do not span 3-D."""
    if D.shape[0] < 3:
        raise InputError(f"{name}: a Lambertian fit needs at least 3 lights, got {D.shape[0]}")
    s = np.linalg.svd(D, compute_uv=False)
    if s[-1] ** 2 <= MIN_RCOND * s[0] ** 2:
        raise InputError(f"{name}: the lights are (nearly) coplanar (singular values "
                         f"{fmt_value(s.tolist())}); they do not determine a normal")
    return np.linalg.pinv(D)


def _sample_mask(valid, N: int, L: int) -> np.ndarray:
    v = np.asarray(valid)
    if v.dtype != bool or v.shape != (N, L):
        raise ShapeError(f"valid: expected an ({N}, {L}) bool array, got {v.dtype} {v.shape}")
    return v


def _fit_and_held(fit, held, L: int) -> tuple[np.ndarray, np.ndarray]:
    def idx(x, name):
        a = np.asarray(x)
        if a.ndim != 1 or a.dtype.kind not in "iu":
            raise ShapeError(f"{name}: expected a 1-D array of light indices, got {a.dtype} "
                             f"{a.shape}")
        if a.size and (a.min() < 0 or a.max() >= L):
            raise InputError(f"{name}: light indices must lie in [0, {L}), got {a.min()} … "
                             f"{a.max()}")
        return a.astype(np.int64)

    if fit is None and held is None:
        return split_lights(L)
    rest = np.arange(L)
    f = idx(fit, "fit") if fit is not None else np.setdiff1d(rest, idx(held, "held"))
    h = idx(held, "held") if held is not None else np.setdiff1d(rest, f)
    both = np.intersect1d(f, h)
    if both.size:
        raise InputError(f"fit, held: light {int(both[0])} is both fitted and held out; a "
                         "held-out light must not be fitted")
    if h.size == 0:
        raise InputError("held: no light held out; nothing to predict")
    return f, h
