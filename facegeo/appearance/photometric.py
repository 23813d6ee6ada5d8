"""Per-pixel reflectance from one view under many lights, chosen per pixel by cross-validation
over the lights: never worse than Lambertian on lights it did not see (issue 36).

Every pixel gets four nested models of its radiance under a distant light l of intensity E_l,
per channel c (``y_lc = R_lc / E_lc``, directions in the lights' frame):

0. **Lambertian** — ``y_c = max(0, b_c·l)``, ``b_c = ρ_c n`` (Woodham 1980, as
   :mod:`facegeo.appearance.lambertian`), by robust least squares: a sample enters when the fit
   lights it (``b̄·l > 0``) and it is not in a cast shadow (``ȳ ≥ κ b̄·l``, κ = :data:`KAPPA`);
   the weights are refined with the fit (:data:`ITERATIONS` times), so the clamp's attached
   shadows and the cast shadows do not pull the normal. Saturated and untrusted samples never
   enter.
1. **Lambertian + shadow map** — the same, times the pixel's visibility of the light, V(l):
   Debevec et al. 2000 §4.4's shadow map (brightness against the fit: ``v_l = clip(ȳ_l / b̄·l,
   0, 1)`` where the sample is in a cast shadow, else 1), known at the fitted lights and
   interpolated at any other light from its :data:`SHADOW_NEIGHBOURS` nearest fitted lights
   (weights 1/angle²). Visibility is geometry (the nose between the cheek and the light), not
   reflectance: it is the one part taken from neighbouring lights.
2. **Lambertian + lobe** — ``y_c = max(0, b_c·l) + ρ_s s(l)``, s the Torrance–Sparrow lobe of
   Eq. 8 of Debevec et al. 2000 for a small source, per unit irradiance,
   ``s = F(v·h) P(n·h) G(n, l, v) / (4 n·v)``, with F the unpolarised Fresnel reflectance of
   index η, P the unit-normalised Beckmann distribution of RMS slope m (Cook & Torrance 1982)
   — a parametric P where the paper takes P from the data, so that the lobe can be *evaluated*
   for any light and view (:func:`predict_light`) instead of interpolated between measured
   lights — and G the V-cavity shadowing term (Torrance & Sparrow 1967). The lobe is white after
   the division by E (the light's colour). Its normal n_s (the paper's specular normal beside
   the diffuse n) starts at the robust Lambertian normal and is refined from the lobe model's
   own diffuse part, up to :data:`LOBE_PASSES` fixed-point steps. For each m of
   :data:`ROUGHNESS` the least squares in (b_c, ρ_s) is closed form; the m that lowers the
   error most is kept, subject to: a sample lies in the lobe (``max s ≥`` :data:`COVER` × its
   peak: a lobe narrower than the lights' spacing is not determined), ρ_s > 0, and the
   **chromaticity check** — the colour of the energy the lobe takes must be nearer the light's
   (white) than the pixel's albedo colour, unless the albedo is grey itself (within
   :data:`GREY_DEG`), so a coloured object's diffuse colour is not moved into the lobe.
3. **Lambertian + lobe + shadow map**.

**Choice.** The fitted lights are split into K interleaved folds (:data:`FOLDS`; positions
k, k + K, …); each model is fitted on K − 1 folds and predicts the left-out one (errors in
the frames' units over trusted samples, dark ones included: a shadow is a measurement to
predict); the model with the smallest summed squared error (``criterion="sse"``; or absolute,
``"sae"``), each part it adds (shadow map, lobe) counted :data:`MARGIN` dearer, is the
pixel's, ties going to the simpler (:attr:`PhotometricFit.model`, a map). The final models
are fitted on every fitted light. Shortcuts, all of them light on the choice: the folds'
robust fits start from the final fit's sample weights (restricted to their lights, then
refined on them); the lobe's normal and its table ``s_l(m)`` come from the final fit (the
table is the costly part); a pixel whose final fit has neither a lobe nor a shadowed sample is
not cross-validated — its four models are then one.

**Light gains** (``light_gains="fit"``, an option for rigs without photometric calibration):
after a first fit, each fitted light's intensity relative to the given one is the median over
well-lit pixels of observed / predicted (geometric mean 1), and the models are fitted again
with it. Yale B's flashes differ by ±10–20 % from one another; held-out lights keep their
given intensity (nothing is known of them).

Light weights: uniform by default (each fitted light counts once); ``light_weights=`` takes
per-light weights, e.g. the Voronoi cells' solid angles (:attr:`LightList.solid_angles`) — on
a partial dome those give the outermost lights huge cells (issue 36), so they are an option,
not the default.

What is not here: the paper's Eq. 6–7 chromaticity ramp (its full skin model, model "c" of
issue 36). Its specular P is taken from the data, which cannot predict a light that was not
measured without interpolating the lobe between lights — the highlight smearing issue 36
found — and with a Beckmann P it is model 2 plus the ramp, which the data sets at hand
(grey Yale frames, non-skin DiLiGenT objects) cannot test. :mod:`facegeo.appearance.skin`
stays the multi-view light-stage fit.

References
----------
.. [1] P. Debevec et al., "Acquiring the Reflectance Field of a Human Face", SIGGRAPH 2000,
   §4.1 (Eq. 8), §4.4 (shadow maps).
.. [2] K. E. Torrance, E. M. Sparrow, "Theory for off-specular reflection from roughened
   surfaces", JOSA 57(9), 1967.
.. [3] R. L. Cook, K. E. Torrance, "A reflectance model for computer graphics", ACM TOG 1(1),
   1982 (Beckmann distribution, Fresnel form).
.. [4] R. J. Woodham, "Photometric method for determining surface orientation from multiple
   images", Optical Engineering 19(1), 1980.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from facegeo.appearance import _photometric_kernels as K_
from facegeo.appearance.lambertian import (
    CHANNELS,
    HeldOutScore,
    _add_held_out,
    _field_and_lights,
    _fit_and_held,
    _intensities,
    _mask_rows,
    _normal_errors,
    _relative_errors,
    _sample_mask,
    _unit_directions,
    _usable,
    held_out_lambertian,
)
from facegeo.checks import as_array, check_choice, check_positive_int, fmt_value
from facegeo.errors import InputError, ShapeError

__all__ = ["MODEL_NAMES", "ROUGHNESS", "FOLDS", "PhotometricFit", "PhotometricScore",
           "fit_photometric", "predict_light", "predict_environment", "held_out_photometric",
           "load_photometric"]

log = logging.getLogger(__name__)

#: Names of the models, by index (:attr:`PhotometricFit.model`; −1: no fit).
MODEL_NAMES = ("lambertian", "lambertian+shadow", "lobe", "lobe+shadow")
#: Beckmann RMS slopes the lobe may take (a grid: the scale ρ_s is closed form for each).
ROUGHNESS = (0.05, 0.1, 0.2)
#: Folds of the cross-validation over the fitted lights.
FOLDS = 8
#: A sample darker than κ × the Lambertian prediction is in a cast shadow.
KAPPA = 0.5
#: The fit starts from the samples brighter than this fraction of the pixel's brightest
#: sample (§4.4's 2 % shadow threshold); its iterations then decide by the fit itself.
DARK_FRACTION = 0.02
#: A lobe is admitted only if some sample reaches this fraction of its peak.
COVER = 0.25
#: An albedo within this angle (degrees) of white is grey: colour cannot separate the lobe.
GREY_DEG = 3.0
#: Refinements of the robust Lambertian weights.
ITERATIONS = 3
#: Fitted lights the shadow map is interpolated from, weighted by 1/angle^SHADOW_POWER.
SHADOW_NEIGHBOURS = 4
SHADOW_POWER = 2.0
#: Index of refraction of the lobe's Fresnel term (skin; ρ_s absorbs the scale).
ETA = 1.4
#: Samples (pixel × light × channel) per chunk of the fit.
CHUNK_SAMPLES = 1 << 20
CRITERIA = ("sse", "sae")
#: ``light_gains`` choices: the intensities as given, or each fitted light's gain fitted too.
LIGHT_GAINS = (None, "fit")
#: A model with more parts must beat the simpler one's cross-validation error by this share
#: per part it adds.
MARGIN = 0.01
#: Cross-validation errors within this share of the compared samples' energy are ties.
NOISE_FLOOR = 1e-9
#: Fits of the lobe, each from the normal of the previous one's diffuse part.
LOBE_PASSES = 10
#: Cross-validate every pixel, also those whose four final models coincide.
CV_ALWAYS = False


@dataclass
class PhotometricFit:
    """Per-pixel models of :func:`fit_photometric` (module docstring).

    Attributes
    ----------
    directions : (L, 3) float64, unit, the lights' frame
        The fitted lights (the shadow map's support).
    view : (N, 3) float64, unit, the lights' frame
        Toward the camera, per pixel.
    channels : {"each", "grey"}
    b_lambert, b_lobe : (N, C, 3) float64
        ``ρ_c n`` of the Lambertian models and of the lobe models (NaN where there is no fit),
        in units of the input divided by the light intensities.
    rho_s : (N,) float64
        Lobe scale (0: no lobe); same units.
    roughness : (N,) float64
        Beckmann m of the lobe, NaN without one.
    n_lobe : (N, 3) float64, unit
        The lobe's normal (the robust Lambertian normal).
    visibility : (N, L) float32, in [0, 1]
        The shadow map at the fitted lights.
    model : (N,) int8
        The chosen model (:data:`MODEL_NAMES`), −1 where there is no fit.
    valid : (N,) bool
    n_lights_used : (N,) int32
        Samples the final Lambertian fit used.
    cv_sse, cv_sae : (N, 4) float64
        Cross-validation errors of the four models (frames' units); 0 for a pixel whose four
        final models coincide (no lobe, no shadowed sample: not cross-validated).
    light_gains : (L,) float64
        The fitted lights' intensities relative to the given ones (``light_gains="fit"``; ones
        otherwise). New lights are predicted with the intensity given to :func:`predict_light`.
    eta : float
    shadow_neighbours : int
    """

    directions: np.ndarray
    view: np.ndarray
    channels: str
    b_lambert: np.ndarray
    b_lobe: np.ndarray
    rho_s: np.ndarray
    roughness: np.ndarray
    n_lobe: np.ndarray
    visibility: np.ndarray
    model: np.ndarray
    valid: np.ndarray
    n_lights_used: np.ndarray
    cv_sse: np.ndarray
    cv_sae: np.ndarray
    light_gains: np.ndarray
    eta: float = ETA
    shadow_neighbours: int = SHADOW_NEIGHBOURS
    _b: np.ndarray | None = field(default=None, init=False, repr=False)

    @property
    def n_pixels(self) -> int:
        return int(self.model.shape[0])

    @property
    def b(self) -> np.ndarray:
        """``(N, C, 3)``: the chosen model's ``ρ_c n`` (cached)."""
        if self._b is None:
            lobe = (self.model == K_.LOBE) | (self.model == K_.LOBE_SHADOW)
            self._b = np.where(lobe[:, None, None], self.b_lobe, self.b_lambert)
        return self._b

    @property
    def normal(self) -> np.ndarray:
        """``(N, 3)`` float64 unit, the lights' frame: ``normalize(Σ_c b_c)`` of the chosen
        model; NaN without a fit."""
        s = self.b.sum(axis=1)
        norm = np.linalg.norm(s, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where((norm > 0)[:, None], s / norm[:, None], np.nan)

    @property
    def albedo(self) -> np.ndarray:
        """``(N, C)`` float64: ``|b_c|`` of the chosen model."""
        return np.linalg.norm(self.b, axis=-1)

    @property
    def uses_lobe(self) -> np.ndarray:
        return (self.model == K_.LOBE) | (self.model == K_.LOBE_SHADOW)

    @property
    def uses_shadow(self) -> np.ndarray:
        return (self.model == K_.LAMBERT_SHADOW) | (self.model == K_.LOBE_SHADOW)

    def model_fractions(self, rows=None) -> dict[str, float]:
        """Share of the fitted pixels (of ``rows``, default all) that chose each model."""
        m = self.model if rows is None else self.model[rows]
        m = m[m >= 0]
        tot = max(int(m.size), 1)
        return {name: round(float(np.count_nonzero(m == k)) / tot, 5)
                for k, name in enumerate(MODEL_NAMES)}

    def subset(self, rows) -> PhotometricFit:
        """The models of ``rows`` ((N,) bool or indices) only."""
        kw = {k: getattr(self, k) if k in ("directions", "light_gains") else
              getattr(self, k)[rows] for k in _ARRAYS}
        return PhotometricFit(channels=self.channels, eta=self.eta,
                              shadow_neighbours=self.shadow_neighbours, **kw)

    def save(self, path, **extra) -> Path:
        """Write the fit as a ``.npz`` (:func:`load_photometric` reads it); ``extra`` arrays
        (e.g. the image rows of the pixels) are stored beside it under their names."""
        path = Path(path)
        clash = sorted(set(extra) & (set(_ARRAYS) | {"channels", "eta", "shadow_neighbours"}))
        if clash:
            raise InputError(f"extra: {clash[0]!r} is a name of the fit's own arrays")
        arrays = {k: getattr(self, k) for k in _ARRAYS}
        np.savez_compressed(path, channels=np.array(self.channels), eta=np.array(self.eta),
                            shadow_neighbours=np.array(self.shadow_neighbours), **arrays,
                            **{k: np.asarray(v) for k, v in extra.items()})
        return path


_ARRAYS = ("directions", "view", "b_lambert", "b_lobe", "rho_s", "roughness", "n_lobe",
           "visibility", "model", "valid", "n_lights_used", "cv_sse", "cv_sae", "light_gains")


def load_photometric(path) -> PhotometricFit:
    """Read a :meth:`PhotometricFit.save` file."""
    path = Path(path)
    try:
        z = np.load(path)
        kw = {k: z[k] for k in _ARRAYS}
        return PhotometricFit(channels=str(z["channels"]), eta=float(z["eta"]),
                              shadow_neighbours=int(z["shadow_neighbours"]), **kw)
    except (OSError, KeyError, ValueError) as e:
        raise InputError(f"{path}: not a photometric fit ({e})") from None


@dataclass
class PhotometricScore:
    """Held-out lights predicted by the photometric model and by the Lambertian baseline on
    the same lights, pixels and samples (:func:`held_out_photometric`).

    Attributes
    ----------
    rel_mae, rel_rmse : float
        ``Σ|p − o| / Σ o`` and ``sqrt(Σ(p − o)²) / sqrt(Σ o²)`` over held-out lights × masked
        pixels with a fit × channels, trusted observations only, frames' units (as
        :class:`~facegeo.appearance.lambertian.HeldOutScore` defines them).
    samples, untrusted, pixels, pixels_unfitted : int
    normal_mean_error_deg, normal_median_error_deg : float or None
    normals_compared : int
    model_fractions : dict of str -> float
        Share of the masked fitted pixels per model.
    fit_lights, held_lights : (k,) int64
    fit : PhotometricFit
    lambertian : HeldOutScore
        The baseline (:func:`facegeo.appearance.lambertian.held_out_lambertian`).
    seconds : float
        Wall time of our fit and scoring (the baseline's is ``lambertian.seconds``).
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
    model_fractions: dict
    fit_lights: np.ndarray
    held_lights: np.ndarray
    fit: PhotometricFit = field(repr=False)
    lambertian: HeldOutScore = field(repr=False)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        """The figures as JSON-ready numbers, ours and the baseline's."""
        lam = self.lambertian
        return {"rel_mae": self.rel_mae, "rel_rmse": self.rel_rmse,
                "rel_mae_lambertian": lam.rel_mae, "rel_rmse_lambertian": lam.rel_rmse,
                "samples": self.samples, "untrusted": self.untrusted, "pixels": self.pixels,
                "pixels_unfitted": self.pixels_unfitted,
                "normal_mean_error_deg": self.normal_mean_error_deg,
                "normal_median_error_deg": self.normal_median_error_deg,
                "normal_mean_error_deg_lambertian": lam.normal_mean_error_deg,
                "normal_median_error_deg_lambertian": lam.normal_median_error_deg,
                "normals_compared": self.normals_compared,
                "model_fractions": dict(self.model_fractions),
                "fit_lights": self.fit_lights.tolist(), "held_lights": self.held_lights.tolist(),
                "seconds": self.seconds, "seconds_lambertian": lam.seconds}


# --------------------------------------------------------------------------- helpers
def _views(view, N: int) -> np.ndarray:
    v = as_array(view, "view")
    if v.shape == (3,):
        v = np.broadcast_to(v, (N, 3))
    if v.shape != (N, 3):
        raise ShapeError(f"view: expected shape (3,) or ({N}, 3), got {v.shape}")
    norm = np.linalg.norm(v, axis=1)
    if not (norm > 1e-12).all():
        k = int(np.flatnonzero(~(norm > 1e-12))[0])
        raise InputError(f"view[{k}]: zero-length vector, which has no direction")
    return v / norm[:, None]


def _light_weights(lw, L: int) -> np.ndarray:
    if lw is None:
        return np.ones(L)
    w = as_array(lw, "light_weights", shape=(L,))
    if not (w > 0).all():
        k = int(np.flatnonzero(~(w > 0))[0])
        raise InputError(f"light_weights[{k}]: expected > 0, got {w[k]}")
    return w / w.mean()


def _angles(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Angles (radians) between unit rows of A (p, 3) and B (q, 3), (p, q), accurate near 0."""
    dot = np.clip(A @ B.T, -1.0, 1.0)
    cross = np.linalg.norm(np.cross(A[:, None, :], B[None, :, :]), axis=-1)
    return np.arctan2(cross, dot)


def shadow_neighbours(D_fit: np.ndarray, D_new: np.ndarray, k: int,
                      allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` nearest fitted lights of each new light and their interpolation weights.

    Weights ∝ 1/angle² (normalised); a new light within 1e-9 rad of a fitted one takes its
    value alone. ``allowed`` (q_new, L_fit) bool restricts the candidates (the folds).

    Returns
    -------
    idx : (q, k) int64; w : (q, k) float64
    """
    ang = _angles(D_new, D_fit)
    if allowed is not None:
        ang = np.where(allowed, ang, np.inf)
    k = min(k, D_fit.shape[0])
    idx = np.argsort(ang, axis=1, kind="stable")[:, :k]
    a = np.take_along_axis(ang, idx, 1)
    exact = a[:, :1] < 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(np.isfinite(a), 1.0 / np.maximum(a, 1e-9) ** SHADOW_POWER, 0.0)
    w = np.where(exact, np.eye(1, k)[0][None, :], w)
    s = w.sum(axis=1, keepdims=True)
    w = np.where(s > 0, w / np.where(s > 0, s, 1.0), 0.0)
    return idx.astype(np.int64), w


def lobe_values(n, v, l, m, eta: float = ETA) -> np.ndarray:
    """The Torrance–Sparrow lobe ``F(v·h) P(n·h) G / (4 n·v)`` (Eq. 8 of Debevec et al. 2000
    for a small source, per unit irradiance; the kernels' arithmetic in numpy).

    Parameters
    ----------
    n, v : (N, 3) float64, unit — normals, toward the camera
    l : (Q, 3) float64, unit — toward each light
    m : (N,) float64 — Beckmann RMS slope (NaN: no lobe, value 0)

    Returns
    -------
    (N, Q) float64, 1/sr per unit irradiance; 0 where ``n·l ≤ 0`` or ``n·v ≤ 0``.
    """
    nl = n @ l.T
    nv = np.einsum("ni,ni->n", n, v)[:, None]
    hv = l[None, :, :] + v[:, None, :]
    hn = np.linalg.norm(hv, axis=2)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        nh = np.minimum((nl + nv) / hn, 1.0)
        vh = 0.5 * hn
        c = np.clip(vh, 0.0, 1.0)
        g = np.sqrt(eta * eta - 1.0 + c * c)
        a = (g - c) / (g + c)
        bb = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
        F = 0.5 * a * a * (1.0 + bb * bb)
        m2 = (np.asarray(m, np.float64) ** 2)[:, None]
        nh2 = nh * nh
        P = np.exp((nh2 - 1.0) / (nh2 * m2)) / (np.pi * m2 * nh2 * nh2)
        G = np.minimum(np.minimum(0.25 / nv, nh / (2.0 * vh)), nh * nl / (2.0 * vh * nv))
        s = F * P * G
    ok = (nl > 0) & (nv > 0) & (hn >= 1e-12) & (nh > 1e-8) & np.isfinite(m2)
    return np.where(ok, s, 0.0)


# --------------------------------------------------------------------------- fit
def fit_photometric(R, directions, *, view, intensities=None, channels: str = "each",
                    valid=None, saturation: float | None = None, rows=None, light_weights=None,
                    folds: int = FOLDS, roughness=ROUGHNESS, eta: float = ETA,
                    kappa: float = KAPPA, dark_fraction: float = DARK_FRACTION,
                    cover: float = COVER, grey_deg: float = GREY_DEG,
                    iterations: int = ITERATIONS, models=MODEL_NAMES, criterion: str = "sse",
                    margin: float = MARGIN, light_gains: str | None = None,
                    shadow_neighbours_k: int = SHADOW_NEIGHBOURS, chunk: int | None = None,
                    threads: int = 1) -> PhotometricFit:
    """Fit the four models of the module docstring per pixel and choose one by K-fold
    cross-validation over the lights.

    Parameters
    ----------
    R : (N, L, C) or (N, L) array_like, linear radiance, frames' units
        One row per pixel, one column per fitted light. NaN marks a sample to leave out.
    directions : (L, 3) array_like, toward each light, the lights' frame (normalised here)
    view : (3,) or (N, 3) array_like, toward the camera, same frame (normalised here)
    intensities : None, (L,) or (L, C) array_like, linear, > 0
        As for :func:`facegeo.appearance.lambertian.fit_lambertian`.
    channels : {"each", "grey"}
        ``"grey"``: one model of the channel means (mean R / mean E).
    valid : (N, L) bool array_like, optional — False where a sample cannot be trusted
    saturation : float, optional — samples with any channel ≥ this are left out
    rows : (N,) bool array_like, optional — fit only these pixels
    light_weights : (L,) array_like, > 0, optional
        Least-squares weight per light (normalised to mean 1); default uniform. The Voronoi
        cells' solid angles are the documented alternative (module docstring).
    folds : int ≥ 2 — K of the cross-validation (at most L)
    roughness : sequence of float > 0 — the lobe's grid of Beckmann RMS slopes
    eta : float > 1 — index of refraction of the lobe's Fresnel term
    kappa, dark_fraction, cover, grey_deg, iterations — see :data:`KAPPA`, …
    models : sequence of str — the models the choice may take (:data:`MODEL_NAMES`);
        ``("lambertian",)`` is the robust Lambertian fit alone.
    criterion : {"sse", "sae"} — squared or absolute cross-validation error
    margin : float ≥ 0 — each part a model adds (shadow map, lobe) must lower the
        cross-validation error by this share (:data:`MARGIN`)
    light_gains : {None, "fit"}
        ``"fit"``: after a first fit, each fitted light's intensity relative to the given one
        is estimated (:attr:`PhotometricFit.light_gains`: the median over the well-lit pixels
        of observed / predicted) and the models are fitted again with it — for lights whose
        intensities are nominal (Yale B's flashes vary by ±10–20 %). Twice the time.
    shadow_neighbours_k : int — fitted lights the shadow map is interpolated from
    chunk : int, optional — pixels per chunk (results do not depend on it)
    threads : int — worker threads (chunks run in parallel; the kernels release the GIL)

    Returns
    -------
    PhotometricFit
        Pixels with fewer than 3 usable lights, or nearly coplanar ones, have ``valid``
        False, NaN parameters and model −1; the fit never raises for them.
    """
    check_choice(channels, "channels", CHANNELS)
    check_choice(criterion, "criterion", CRITERIA)
    check_choice(light_gains, "light_gains", LIGHT_GAINS)
    R, D = _field_and_lights(R, directions)
    N, L, C = R.shape
    if L < 3:
        raise InputError(f"directions: a fit needs at least 3 lights, got {L}")
    v = _views(view, N)
    E = _intensities(intensities, L, C, channels)
    lw = _light_weights(light_weights, L)
    V = None if valid is None else _sample_mask(valid, N, L)
    sel = np.arange(N) if rows is None else np.flatnonzero(_mask_rows(rows, "rows", N))
    ms = np.asarray(roughness, np.float64).reshape(-1)
    if ms.size == 0 or not (ms > 0).all():
        raise InputError(f"roughness: expected positive Beckmann slopes, got "
                         f"{fmt_value(roughness)}")
    allowed = _allowed_models(models)
    if float(eta) <= 1.0:
        raise InputError(f"eta: expected an index of refraction > 1, got {fmt_value(eta)}")
    k_folds = check_positive_int(folds, "folds")
    if k_folds < 2:
        raise InputError(f"folds: expected at least 2, got {fmt_value(folds)}")
    k_folds = min(k_folds, L)
    knn = check_positive_int(shadow_neighbours_k, "shadow_neighbours_k")
    fold = (np.arange(L) % k_folds).astype(np.int64)
    nbr_idx, nbr_w = shadow_neighbours(D, D, knn, allowed=fold[:, None] != fold[None, :])
    grey = channels == "grey"
    Cf = 1 if grey else C
    grey_cos = float(np.cos(np.radians(grey_deg)))
    step = chunk if chunk is not None else max(1, CHUNK_SAMPLES // max(1, L * C))
    step = check_positive_int(step, "chunk")
    starts = list(range(0, sel.size, step))
    sat = None if saturation is None else float(saturation)

    def run(s0, E):
        r = sel[s0:s0 + step]
        Rc = np.asarray(R[r], np.float32)
        use = _usable(Rc, None if V is None else V[r], None, sat)
        if grey:
            Rc = Rc.mean(axis=2, keepdims=True)
        Rc = np.where(use[..., None], Rc, np.float32(0.0))  # left-out samples (NaN) weigh 0
        n = r.size
        res = _empty_outputs(n, L, Cf)
        K_.fit_chunk(np.ascontiguousarray(Rc), 1.0 / E, E, use, D, np.ascontiguousarray(v[r]),
                     lw, fold, k_folds, nbr_idx, nbr_w, ms, float(eta), float(kappa),
                     float(dark_fraction), float(cover), grey_cos, int(iterations),
                     LOBE_PASSES, CV_ALWAYS, res["b_lambert"], res["b_lobe"], res["rho_s"],
                     res["m_index"], res["n_lobe"], res["visibility"], res["n_lights_used"],
                     res["valid"], res["cv_sse"], res["cv_sae"], res["cv_energy"],
                     res["cv_folds"])
        return r, res

    def solve(E, gains):
        out = _empty_outputs(N, L, Cf)
        for r, res in _map(lambda s0: run(s0, E), starts, threads):
            for k, a in res.items():
                out[k][r] = a
        m_index = out["m_index"]
        return PhotometricFit(
            directions=D, view=v, channels=channels, b_lambert=out["b_lambert"],
            b_lobe=out["b_lobe"], rho_s=out["rho_s"],
            roughness=np.where(m_index >= 0, ms[np.maximum(m_index, 0)], np.nan),
            n_lobe=out["n_lobe"], visibility=out["visibility"],
            model=_choose(out, allowed, criterion, float(margin)), valid=out["valid"],
            n_lights_used=out["n_lights_used"], cv_sse=out["cv_sse"], cv_sae=out["cv_sae"],
            light_gains=gains, eta=float(eta), shadow_neighbours=knn)

    t0 = time.perf_counter()
    fit = solve(E, np.ones(L))
    if light_gains == "fit":
        gains = _fitted_gains(fit, R, V, sel, sat, E)
        fit = solve(E * gains[:, None], gains)
    log.info("photometric fit: %d pixels, %d lights, %d folds in %.2f s; models %s", sel.size, L,
             k_folds, time.perf_counter() - t0, fit.model_fractions(sel))
    return fit


def _fitted_gains(fit: PhotometricFit, R, V, sel: np.ndarray, sat, E: np.ndarray) -> np.ndarray:
    """Each fitted light's intensity relative to its given one: the median over pixels of
    observed / predicted (channel means) over the trusted samples the fit predicts brighter
    than the median prediction (well lit, off the terminator), normalised to a geometric mean
    of 1 (the gains fix the lights relative to each other, not the overall scale)."""
    L = fit.directions.shape[0]
    rows = sel[fit.valid[sel]]
    step = max(1, CHUNK_SAMPLES // max(1, L * 3))
    obs, prd, ok = [], [], []
    for i in range(0, rows.size, step):
        r = rows[i:i + step]
        o = np.asarray(R[r], np.float64)
        t = _usable(o, None if V is None else V[r], None, sat)
        p = _predict_rows(fit, r, fit.directions, E, fit.view[r]).mean(axis=2)
        obs.append(o.mean(axis=2))
        prd.append(p)
        ok.append(t & np.isfinite(p))
    o, p, t = np.concatenate(obs), np.concatenate(prd), np.concatenate(ok)
    if not t.any():
        return np.ones(L)
    lit = t & (p > np.median(p[t]))
    gains = np.ones(L)
    for l in range(L):
        k = lit[:, l]
        if k.sum() >= 10:
            gains[l] = float(np.median(o[k, l] / p[k, l]))
    gains = np.where(np.isfinite(gains) & (gains > 0), gains, 1.0)
    return gains / np.exp(np.mean(np.log(gains)))


def _allowed_models(models) -> np.ndarray:
    names = [models] if isinstance(models, str) else list(models)
    ok = np.zeros(K_.N_MODELS, bool)
    for m in names:
        if m not in MODEL_NAMES:
            raise InputError(f"models: unknown model {m!r}; expected some of "
                             f"{', '.join(MODEL_NAMES)}")
        ok[MODEL_NAMES.index(m)] = True
    if not ok[K_.LAMBERT]:
        raise InputError("models: 'lambertian' must be among the models (the simplest case, "
                         "the fallback of the choice)")
    return ok


def _empty_outputs(N: int, L: int, C: int) -> dict:
    return {"b_lambert": np.full((N, C, 3), np.nan), "b_lobe": np.full((N, C, 3), np.nan),
            "rho_s": np.zeros(N), "m_index": np.full(N, -1, np.int64),
            "n_lobe": np.full((N, 3), np.nan), "visibility": np.ones((N, L), np.float32),
            "n_lights_used": np.zeros(N, np.int32), "valid": np.zeros(N, bool),
            "cv_sse": np.zeros((N, K_.N_MODELS)), "cv_sae": np.zeros((N, K_.N_MODELS)),
            "cv_energy": np.zeros(N), "cv_folds": np.zeros(N, np.int64)}


def _choose(out: dict, allowed: np.ndarray, criterion: str, margin: float) -> np.ndarray:
    """Per pixel, the allowed model of least cross-validation error, each part a model adds
    (shadow map, lobe) counted as ``1 + margin`` times its error (ties: the simpler);
    a lobe model without a final lobe is the Lambertian one it then equals, a shadow model
    whose shadow map is all lit likewise."""
    err = out["cv_sse"] if criterion == "sse" else out["cv_sae"]
    scale = out["cv_energy"] if criterion == "sse" else np.sqrt(out["cv_energy"])
    parts = np.array([0.0, 1.0, 1.0, 2.0])[None, :]
    # errors at the rounding level of the data are ties (exact data: all models fit)
    err = err * (1.0 + margin * parts) + NOISE_FLOOR * scale[:, None] * parts
    err = np.where(allowed[None, :], err, np.inf)
    choice = np.argmin(err, axis=1).astype(np.int8)  # first minimum: the simpler model
    no_lobe = out["m_index"] < 0
    choice = np.where(no_lobe & (choice >= K_.LOBE), choice - K_.LOBE, choice).astype(np.int8)
    lit = (out["visibility"] >= 1.0).all(axis=1)
    shadow = (choice == K_.LAMBERT_SHADOW) | (choice == K_.LOBE_SHADOW)
    choice = np.where(lit & shadow, choice - 1, choice).astype(np.int8)
    return np.where(out["valid"], choice, np.int8(-1)).astype(np.int8)


def _map(run, starts, threads):
    """``run(s)`` for each start, on ``threads`` worker threads (results in order)."""
    t = check_positive_int(threads, "threads")
    if t == 1 or len(starts) < 2:
        for s in starts:
            yield run(s)
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(t, thread_name_prefix="facegeo-photometric") as pool:
        yield from pool.map(run, starts)


# --------------------------------------------------------------------------- prediction
def predict_light(model: PhotometricFit, direction, intensity=None, view=None) -> np.ndarray:
    """Radiance of every pixel under a distant light, evaluated from the fitted models.

    ``max(0, b_c·l) + ρ_s s(n_s, v, l; m)`` (the lobe of the pixel's model evaluated from its
    parameters, module docstring), times the shadow map interpolated at l where the pixel's
    model has one, times the light's intensity.

    Parameters
    ----------
    model : PhotometricFit
    direction : (3,) or (Q, 3) array_like, toward the light(s), the lights' frame
    intensity : None, float, (C,), (Q,) or (Q, C) array_like, linear, > 0
        E of each light (default 1), as the fit's ``intensities``.
    view : None, (3,) or (N, 3) array_like, toward the camera
        Default the fit's own view; another view moves the lobe (the diffuse part and the
        shadow map do not depend on it).

    Returns
    -------
    (N, C) float32 for one direction given as (3,), else (N, Q, C) float32
        NaN for pixels without a fit.
    """
    d = as_array(direction, "direction")
    single = d.shape == (3,)
    Dq = _unit_directions(d.reshape(1, 3) if single else d, "direction")
    Q = Dq.shape[0]
    C = model.b_lambert.shape[1]
    E = _light_intensities(intensity, Q, C)
    v = model.view if view is None else _views(view, model.n_pixels)
    out = np.empty((model.n_pixels, Q, C), np.float32)
    step = max(1, CHUNK_SAMPLES // max(1, Q * C))
    for i in range(0, model.n_pixels, step):
        s = slice(i, i + step)
        out[s] = _predict_rows(model, s, Dq, E, v[s])
    return out[:, 0] if single else out


def _light_intensities(intensity, Q: int, C: int) -> np.ndarray:
    if intensity is None:
        return np.ones((Q, C))
    e = as_array(intensity, "intensity")
    if e.ndim == 0:
        e = np.full((Q, C), float(e))
    elif e.shape == (C,) and Q != C:
        e = np.broadcast_to(e, (Q, C))
    elif e.shape == (Q,):
        e = np.repeat(e[:, None], C, axis=1)
    elif e.ndim == 2 and e.shape[0] == Q and e.shape[1] != C and C == 1:
        e = e.mean(axis=1, keepdims=True)  # an RGB light on a grey fit
    if e.shape != (Q, C):
        raise ShapeError(f"intensity: expected a number, ({C},), ({Q},) or ({Q}, {C}), got "
                         f"{e.shape}")
    if (e < 0).any():
        raise InputError("intensity: light intensities must be >= 0")
    return np.asarray(e, np.float64)


def _predict_rows(model: PhotometricFit, s: slice, Dq: np.ndarray, E: np.ndarray,
                  v: np.ndarray) -> np.ndarray:
    """``(n, Q, C)`` float64 prediction of rows ``s``."""
    b = model.b[s]
    pred = np.maximum(np.einsum("nci,qi->nqc", b, Dq), 0.0)  # NaN rows stay NaN
    lobe = model.uses_lobe[s] & (model.rho_s[s] > 0)
    if lobe.any():
        sv = lobe_values(np.nan_to_num(model.n_lobe[s][lobe]), v[lobe], Dq,
                         model.roughness[s][lobe], model.eta)
        pred[lobe] += (model.rho_s[s][lobe][:, None] * sv)[..., None]
    shadow = model.uses_shadow[s]
    if shadow.any():
        idx, w = shadow_neighbours(model.directions, Dq, model.shadow_neighbours)
        vis = model.visibility[s][shadow].astype(np.float64)  # (n', L)
        pred[shadow] *= np.einsum("nqk,qk->nq", vis[:, idx], w)[..., None]
    return pred * E[None]


def predict_environment(model: PhotometricFit, directions, radiance, view=None) -> np.ndarray:
    """Radiance of every pixel under an environment given as distant lights: ``Σ_k`` of
    :func:`predict_light` for direction k with intensity ``radiance_k`` (the environment's
    radiance times the solid angle its direction stands for — Eq. 4 of Debevec et al. 2000
    with the fitted model in place of the measured reflectance functions).

    Parameters
    ----------
    directions : (Q, 3) array_like, the lights' frame
    radiance : (Q,) or (Q, C) array_like, linear, ≥ 0
    view : as :func:`predict_light`

    Returns
    -------
    (N, C) float32
    """
    Dq = _unit_directions(directions, "directions")
    C = model.b_lambert.shape[1]
    E = _light_intensities(radiance, Dq.shape[0], C)
    v = model.view if view is None else _views(view, model.n_pixels)
    out = np.zeros((model.n_pixels, C))
    q_step = max(1, CHUNK_SAMPLES // max(1, model.n_pixels * C))
    for j in range(0, Dq.shape[0], q_step):
        q = slice(j, j + q_step)
        out += np.nansum(_predict_rows(model, slice(None), Dq[q], E[q], v), axis=1)
    out[~model.valid] = np.nan
    return out.astype(np.float32)


# --------------------------------------------------------------------------- protocol
def held_out_photometric(R, directions, *, view, fit=None, held=None, intensities=None,
                         mask=None, normal_ref=None, channels: str = "each", valid=None,
                         saturation: float | None = None, **fit_kw) -> PhotometricScore:
    """Fit on some lights, predict the others, and score both this model and the Lambertian
    least squares (:func:`~facegeo.appearance.lambertian.held_out_lambertian`) on the same
    lights, pixels and samples.

    Parameters
    ----------
    R, directions, view, intensities, channels, valid, saturation
        As for :func:`fit_photometric`, with every light (fitted and held out).
    fit, held : (k,) int array_like, optional
        Light indices to fit and to predict (default: even positions fitted, odd held out).
    mask : (N,) bool array_like, optional — the pixels fitted and scored (default all)
    normal_ref : (N, 3) array_like, the lights' frame, optional — reference normals (NaN: none)
    **fit_kw — further arguments of :func:`fit_photometric` (folds, roughness, threads, …)

    Returns
    -------
    PhotometricScore
        Errors over the held-out trusted samples of masked pixels that both fits fitted
        (they fit the same pixels: at least 3 usable, non-coplanar fitted lights).
    """
    t0 = time.perf_counter()
    R, D = _field_and_lights(R, directions)
    N, L, C = R.shape
    fit_l, held_l = _fit_and_held(fit, held, L)
    m = np.ones(N, bool) if mask is None else _mask_rows(mask, "mask", N)
    V = None if valid is None else _sample_mask(valid, N, L)
    ref = None if normal_ref is None else as_array(normal_ref, "normal_ref", shape=(N, 3),
                                                   finite=False)
    E_all = _intensities(intensities, L, C, channels)
    v = _views(view, N)
    lam = held_out_lambertian(R, D, fit=fit_l, held=held_l, intensities=intensities, mask=m,
                              normal_ref=ref, channels=channels, saturation=saturation, valid=V)
    t1 = time.perf_counter()
    model = fit_photometric(R[:, fit_l], D[fit_l], view=v,
                            intensities=None if intensities is None else
                            np.asarray(intensities)[fit_l], channels=channels,
                            valid=None if V is None else V[:, fit_l],
                            saturation=saturation, rows=m, **fit_kw)
    both = m & model.valid & lam.fit.valid
    sums = np.zeros(4)
    samples = untrusted = 0
    sel = np.flatnonzero(both)
    step = max(1, CHUNK_SAMPLES // max(1, held_l.size * C))
    for i in range(0, sel.size, step):
        r = sel[i:i + step]
        obs = np.asarray(R[r][:, held_l], np.float64)
        trust = _usable(obs, None if V is None else V[r][:, held_l], None, saturation)
        untrusted += int(trust.size - np.count_nonzero(trust))
        samples += int(np.count_nonzero(trust))
        if channels == "grey":
            obs = obs.mean(axis=2, keepdims=True)
        _add_held_out(sums, _predict_rows(model, r, D[held_l], E_all[held_l], model.view[r]),
                      obs, trust)
    rel_mae, rel_rmse = _relative_errors(sums, samples)
    mean_err, median_err, compared = _normal_errors(model.normal, ref, m)
    if lam.samples != samples:
        log.warning("held-out: the Lambertian baseline compared %d samples, this model %d "
                    "(pixels one of them could not fit)", lam.samples, samples)
    score = PhotometricScore(
        rel_mae=rel_mae, rel_rmse=rel_rmse, samples=samples, untrusted=untrusted,
        pixels=int(m.sum()), pixels_unfitted=int(np.count_nonzero(m & ~model.valid)),
        normal_mean_error_deg=mean_err, normal_median_error_deg=median_err,
        normals_compared=compared, model_fractions=model.model_fractions(m),
        fit_lights=fit_l, held_lights=held_l, fit=model, lambertian=lam,
        seconds=time.perf_counter() - t1)
    log.info("held-out lights: relative MAE %.4f (Lambertian %.4f), RMSE %.4f (%.4f)%s; %.2f s",
             rel_mae, lam.rel_mae, rel_rmse, lam.rel_rmse,
             "" if mean_err is None else
             f", normals {mean_err:.2f} deg (Lambertian {lam.normal_mean_error_deg:.2f})",
             time.perf_counter() - t0)
    return score
