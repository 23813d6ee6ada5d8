"""Ground-truth skin parameters as solid textures: smooth functions of 3-D position.

A :class:`SkinField` gives the parameters of the generator's own skin BRDF of
:mod:`facegeo.appearance.brdf` (deliberately not the paper's §4 fitting model) at any point
in space, so the ground truth can be evaluated at any
texel of any reconstructed atlas, on any mesh:

* ``alpha_0`` — linear-sRGB diffuse colour at normal incidence and view;
* ``alpha_1`` — diffuse colour at grazing angles (desaturated and a little lighter, imitating the
  desaturation the paper observed);
* ``rho_s`` — specular scale on the Fresnel term, in (0.3, 1.0) for the built-in model (0.34–0.93
  on the default head at seed 0); a model that supplies its own (the spectral one's oiliness
  map) may go lower: 0.11–0.74 over the spectral skin types;
* ``roughness`` — Beckmann RMS slope m, in (0.25, 0.5).

Everything is computed in head-normalised coordinates ``u = (p − center)/half_extent`` (face
toward +Z, +Y up, so the face occupies u_z ≈ 0.5…1): smooth regional weights (lips, cheeks,
forehead, nose, under-eye, chin) placed where :func:`facegeo.synth.head.procedural_head` puts
those features — or, for a real face, a frame fitted on its landmarks with every region centred
on its landmark (:meth:`SkinField.for_landmarks`) — plus seeded smooth 3-D noise (random-phase plane waves with wavelengths
8–60 mm). Every map is C^∞ (Gaussians, logistic squashing, sinusoids) so a fit can recover it.

The diffuse colour model is pluggable: ``albedo_model`` names an entry of
:data:`ALBEDO_MODELS` (``"regional"`` built in; register others with
:func:`register_albedo_model`, e.g. a spectral skin model), with JSON parameters in
``albedo_params``; or pass ``albedo_fn(u) -> alpha_0`` directly (not serialisable).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from facegeo.appearance.brdf import desaturate
from facegeo.checks import as_array, fmt_value
from facegeo.errors import InputError

__all__ = [
    "SkinSample",
    "SkinField",
    "ALBEDO_MODELS",
    "register_albedo_model",
    "regional_albedo",
    "region_weights",
    "REGIONS",
    "smooth_noise",
    "FIT_LANDMARKS",
    "REGION_ANCHORS",
    "landmark_frame",
    "region_landmark_distances",
    "procedural_coordinates",
    "PartMaterial",
    "PART_MATERIALS",
    "apply_part_materials",
]

FORMAT = "facegeo.skin_field/1"

_CHUNK = 16384  # points per evaluation block (keeps temporaries in cache)


# --------------------------------------------------------------------------- regions

#: Facial regions in head-normalised coordinates u: name → (centre (3,), radii (3,)).
#: Placed on the landmarks of the default procedural head (facegeo.synth.head.HEAD_LANDMARKS
#: normalised by its bounding box); symmetric pairs are mirrored in x.
REGIONS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "lips": ((0.0, -0.56, 0.77), (0.30, 0.12, 0.30)),
    "left_cheek": ((0.56, -0.27, 0.57), (0.24, 0.24, 0.40)),
    "right_cheek": ((-0.56, -0.27, 0.57), (0.24, 0.24, 0.40)),
    "forehead": ((0.0, 0.58, 0.58), (0.50, 0.25, 0.40)),
    "nose": ((0.0, -0.05, 0.85), (0.14, 0.30, 0.35)),
    "left_under_eye": ((0.42, -0.07, 0.71), (0.15, 0.08, 0.30)),
    "right_under_eye": ((-0.42, -0.07, 0.71), (0.15, 0.08, 0.30)),
    "chin": ((0.0, -0.85, 0.48), (0.22, 0.13, 0.35)),
}

_LN2 = math.log(2.0)


def region_weights(u, centers: dict | None = None) -> dict[str, np.ndarray]:
    """Smooth membership of each region of :data:`REGIONS` at head-normalised points.

    ``w = exp(−ln 2 · q²)`` with ``q = Σ_k ((u_k − c_k)/r_k)²``: a flat-topped (super-Gaussian)
    C^∞ bump, 1 at the centre, ½ on the ellipsoid of radii r, ≈ 0 a few radii away.

    Parameters
    ----------
    u : (..., 3) float64, dimensionless, head-normalised (face toward +Z, +Y up)
    centers : dict of str → (3,), optional
        Region centres (head-normalised) replacing those of :data:`REGIONS` (radii kept):
        a real face's regions placed on its landmarks (``SkinField.region_centers``).

    Returns
    -------
    dict of str → (...) float64 in [0, 1]; also "cheeks" and "under_eye" (both sides summed).
    """
    u = np.asarray(u, dtype=float)
    ux, uy, uz = u[..., 0], u[..., 1], u[..., 2]
    out = {}
    for name, (c, r) in REGIONS.items():
        if centers is not None and name in centers:
            c = centers[name]
        q = ((ux - c[0]) / r[0]) ** 2 + ((uy - c[1]) / r[1]) ** 2 + ((uz - c[2]) / r[2]) ** 2
        out[name] = np.exp(-_LN2 * q * q)
    out["cheeks"] = out["left_cheek"] + out["right_cheek"]
    out["under_eye"] = out["left_under_eye"] + out["right_under_eye"]
    return out


# --------------------------------------------------------------------------- noise


@functools.lru_cache(maxsize=64)
def _waves(seed: int, n_fields: int, n_waves: int, lam_min: float, lam_max: float):
    """Wave vectors (3, F·W) in rad/m, phases (F·W,) and the (F·W, F) mixing matrix that sums
    each field's waves with RMS 1."""
    rng = np.random.default_rng([int(seed), 0x5EED_5C1F])
    n = n_fields * n_waves
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lam = np.exp(rng.uniform(np.log(lam_min), np.log(lam_max), n))
    k = d * (2.0 * np.pi / lam)[:, None]
    phase = rng.uniform(0.0, 2.0 * np.pi, n)
    amp = np.sqrt(lam / lam_max)  # longer waves a little stronger (smooth, red spectrum)
    mix = np.zeros((n, n_fields))
    for f in range(n_fields):
        a = amp[f * n_waves:(f + 1) * n_waves]
        mix[f * n_waves:(f + 1) * n_waves, f] = a / np.sqrt(np.sum(a * a) / 2.0)
    k.setflags(write=False)
    phase.setflags(write=False)
    mix.setflags(write=False)
    return k.T.copy(), phase, mix


def smooth_noise(x, seed: int, n_fields: int = 1, *, n_waves: int = 12,
                 wavelengths: tuple[float, float] = (0.008, 0.06)) -> np.ndarray:
    """Seeded smooth 3-D noise: sums of random-phase plane waves, RMS 1 per field.

    ``n_f(x) = Σ_k a_k sin(k_k·x + φ_k) / sqrt(Σ_k a_k²/2)`` with random directions, wavelengths
    log-uniform in ``wavelengths`` and ``a_k ∝ sqrt(λ_k)``. C^∞, bounded by ``sqrt(2 n_waves)``.

    Parameters
    ----------
    x : (..., 3) float64, metres
    seed : int
    n_fields : int
        Independent fields returned on the last axis.
    n_waves : int
        Waves per field.
    wavelengths : (float, float), metres

    Returns
    -------
    (..., n_fields) float64
    """
    x = np.asarray(x, dtype=float)
    kT, phase, mix = _waves(int(seed), int(n_fields), int(n_waves), float(wavelengths[0]),
                            float(wavelengths[1]))
    # Phases in float64, reduced to [0, 2π) before a float32 sine (≈ 20× faster than float64;
    # the argument's rounding error is ≈ 5e-7 rad, far below any use of the noise). Chunked so
    # the (chunk, F·W) temporaries stay in cache.
    lead = x.shape[:-1]
    x = x.reshape(-1, 3)
    mix32 = mix.astype(np.float32)
    out = np.empty((x.shape[0], mix.shape[1]), dtype=np.float64)
    two_pi = 2.0 * np.pi
    for i in range(0, x.shape[0], _CHUNK):
        arg = x[i:i + _CHUNK] @ kT
        arg += phase
        arg -= two_pi * np.floor(arg * (1.0 / two_pi))
        out[i:i + _CHUNK] = np.sin(arg.astype(np.float32)) @ mix32
    return out.reshape(lead + (mix.shape[1],))


# --------------------------------------------------------------------------- albedo models


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def _sigmoid(z):
    return 0.5 * (1.0 + np.tanh(0.5 * z))  # logistic, overflow-free


def regional_albedo(u, skin: SkinField, *, tone=(0.45, 0.30, 0.23), subject_variation=1.0,
                    lip_tint=(0.80, 0.56, 0.60), blush_tint=(1.02, 0.90, 0.92),
                    under_eye_tint=(0.88, 0.86, 0.90), noise_luminance=0.05,
                    noise_chroma=0.02) -> np.ndarray:
    """The built-in diffuse colour model: subject tone × regional tints × smooth noise.

    ``α_0(u) = tone · s_subject · Π_r tint_r^{w_r(u)} · exp(σ_Y n_Y(x) + σ_C n_C(x) (1, 0, −1))``

    with w_r from :func:`region_weights` (lips redder and darker, cheeks slightly redder,
    under-eye slightly darker), ``x = u · half_extent`` in metres and n seeded noise
    (:func:`smooth_noise`). ``s_subject`` is a seeded per-subject scale (luminance ×
    exp(N(0, 0.12)) and a small red/yellow shift), scaled by ``subject_variation``. Tints
    enter as powers so the map stays C^∞ and strictly positive; R > G > B holds for the default
    parameters everywhere.

    Parameters
    ----------
    u : (..., 3) float64, head-normalised
    skin : SkinField
        Supplies the seed and the head size.
    tone : (3,) linear sRGB
        Mean α_0 of the subject population.
    subject_variation : float
        0 gives exactly ``tone`` (no per-subject change).
    lip_tint, blush_tint, under_eye_tint : (3,)
        Multipliers at the centre of those regions.
    noise_luminance, noise_chroma : float
        RMS of the log-albedo noise (luminance, and red-vs-blue).

    Returns
    -------
    (..., 3) float64, linear sRGB
    """
    u = np.asarray(u, dtype=float)
    rng = np.random.default_rng([int(skin.seed), 0x70E])
    lum = math.exp(subject_variation * float(np.clip(rng.normal(0.0, 0.12), -0.3, 0.3)))
    shift = subject_variation * float(rng.uniform(-0.03, 0.05))  # > 0: redder / more melanin
    base = np.asarray(tone, float) * lum * np.array([1.0, 1.0 - shift, 1.0 - 2.0 * shift])
    w = region_weights(u, skin.region_centers)
    log_a = np.log(base) + (
        w["lips"][..., None] * np.log(np.asarray(lip_tint, float))
        + w["cheeks"][..., None] * np.log(np.asarray(blush_tint, float))
        + w["under_eye"][..., None] * np.log(np.asarray(under_eye_tint, float))
    )
    x = u * np.asarray(skin.half_extent, float)
    n = smooth_noise(x, skin.seed * 7 + 1, 2, n_waves=skin.noise_waves,
                     wavelengths=skin.noise_wavelengths)
    log_a = log_a + noise_luminance * n[..., :1] + noise_chroma * n[..., 1:2] * np.array(
        [1.0, 0.0, -1.0]
    )
    return np.exp(log_a)


def spectral_albedo(u, skin, params="medium", variation=1.0):
    """Donner & Jensen 2006 skin as a diffuse colour model (``albedo_model="spectral"``).

    α₀ comes from the melanin/haemoglobin maps and ρ_s from the oiliness map of
    :func:`facegeo.appearance.spectral.spectral_albedo_fn` (all four parameters drive the
    ground truth); the noise seed is the field's own ``seed``. Imported on first use, so the
    spectral model's tables are built only for fields that ask for it.
    """
    from facegeo.appearance.spectral import spectral_albedo_fn

    fn = spectral_albedo_fn(params, seed=int(skin.seed), variation=variation)
    u = procedural_coordinates(u, skin)
    return {"alpha_0": fn(u), "rho_s": fn.parameter_maps(u).rho_s}


def procedural_coordinates(u, skin: SkinField) -> np.ndarray:
    """Head-normalised coordinates warped so a real face's regions sit where models written
    for the procedural head expect them.

    With ``skin.region_centers`` set (a real face), every region r of :data:`REGIONS` is
    centred on its landmark at ``c'_r`` instead of at its procedural centre ``c_r``; a model
    with its own regions at the procedural centres (the spectral skin's ``PARAMETER_REGIONS``)
    sees ``u' = u + 2 Σ_r w_r(u) (c_r − c'_r) / (1 + Σ_r w_r(u))`` with ``w_r`` the
    landmark-placed memberships (:func:`region_weights`): C^∞, ``u' = c_r`` at an isolated
    region's centre, ``u' = u`` far from every region. Without region centres, ``u``.
    """
    u = np.asarray(u, dtype=float)
    if skin.region_centers is None:
        return u
    w = region_weights(u, skin.region_centers)
    num = np.zeros_like(u)
    den = np.ones(u.shape[:-1])
    for name, (c, _) in REGIONS.items():
        if name in skin.region_centers:
            d = np.asarray(c, float) - np.asarray(skin.region_centers[name], float)
            num += w[name][..., None] * d
            den += w[name]
    return u + 2.0 * num / den[..., None]


#: Diffuse colour models by name: ``model(u, skin, **params) -> alpha_0 (..., 3)``.
ALBEDO_MODELS: dict[str, Callable[..., np.ndarray]] = {
    "regional": regional_albedo,
    "spectral": spectral_albedo,
}


def register_albedo_model(name: str, model: Callable[..., np.ndarray], *,
                          overwrite: bool = False) -> None:
    """Add a diffuse colour model to :data:`ALBEDO_MODELS`.

    Parameters
    ----------
    name : str
        Key used in ``SkinField(albedo_model=name)`` and in ``skin.json``.
    model : callable
        ``model(u (..., 3) float64, skin: SkinField, **params) -> alpha_0 (..., 3)`` linear
        sRGB; ``params`` come from ``SkinField.albedo_params`` (JSON-ready values). A model
        that also knows the specular scale (the spectral model's oiliness map) may return a
        mapping ``{"alpha_0": (..., 3), "rho_s": (...)}``; its ``rho_s`` then replaces the
        field's regional one.
    overwrite : bool
        Replace an existing entry instead of raising.
    """
    if not isinstance(name, str) or not name:
        raise InputError(f"albedo model name: expected a non-empty string, got {fmt_value(name)}")
    if not callable(model):
        raise InputError(f"albedo model {fmt_value(name)}: expected a callable, got {type(model).__name__}")
    if name in ALBEDO_MODELS and not overwrite:
        raise InputError(f"albedo model {fmt_value(name)} is already registered (pass overwrite=True)")
    ALBEDO_MODELS[name] = model


# --------------------------------------------------------------------------- the field


@dataclass(frozen=True)
class SkinSample:
    """Skin parameters at a set of points (leading shape ``...`` of the query).

    Attributes
    ----------
    alpha_0 : (..., 3) float32, linear sRGB
        Diffuse colour at normal incidence and view.
    alpha_1 : (..., 3) float32, linear sRGB
        Diffuse colour at grazing angles.
    rho_s : (...) float32, dimensionless
        Specular scale.
    roughness : (...) float32, dimensionless
        Beckmann RMS slope m.
    """

    alpha_0: np.ndarray
    alpha_1: np.ndarray
    rho_s: np.ndarray
    roughness: np.ndarray


def _vec3(x, name: str) -> tuple[float, float, float]:
    a = as_array(x, name, shape=(3,))
    return (float(a[0]), float(a[1]), float(a[2]))


@dataclass(frozen=True)
class SkinField:
    """Ground-truth skin parameters as solid textures over a head.

    Parameters
    ----------
    center : (3,) float, metres, world frame
        Head-frame origin (bounding-box centre).
    half_extent : (3,) float, metres, > 0
        Head-frame half sizes: ``u = (p − center)/half_extent``.
    seed : int
        Seeds the subject tone and every noise field.
    albedo_model : str
        Key of :data:`ALBEDO_MODELS` (``"regional"``).
    albedo_params : dict
        Keyword arguments of that model (JSON-ready).
    grazing_desaturation : float in [0, 1]
        α_1 = desaturate(α_0, this) · grazing_lift.
    grazing_lift : float
        Lightening of α_1 relative to α_0's luminance (α_1 capped at 0.95).
    rho_s_base, rho_s_oily : float in (0.3, 1.0)
        Specular scale on dry skin and at the centre of the oily T-zone (forehead, nose).
    roughness_base, roughness_oily : float in (0.25, 0.5)
        Beckmann m on dry skin and in the T-zone.
    spec_noise : float
        RMS of the specular noise, in logit units.
    noise_waves : int
        Plane waves per noise field.
    noise_wavelengths : (float, float), metres
        Shortest and longest noise wavelength.
    region_centers : dict of str → (3,), optional
        Head-normalised centres replacing those of :data:`REGIONS` for the named regions
        (a real face's regions on its landmarks, :meth:`for_landmarks`); None keeps
        :data:`REGIONS` (the procedural head). Serialised only when set.
    albedo_fn : callable, optional
        ``albedo_fn(u) -> alpha_0``; replaces the named model. Not serialisable.
    """

    center: tuple[float, float, float]
    half_extent: tuple[float, float, float]
    seed: int = 0
    albedo_model: str = "regional"
    albedo_params: dict = field(default_factory=dict)
    grazing_desaturation: float = 0.5
    grazing_lift: float = 1.10
    rho_s_base: float = 0.42
    rho_s_oily: float = 0.85
    roughness_base: float = 0.42
    roughness_oily: float = 0.29
    spec_noise: float = 0.35
    noise_waves: int = 12
    noise_wavelengths: tuple[float, float] = (0.008, 0.06)
    region_centers: dict | None = None
    albedo_fn: Callable | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "center", _vec3(self.center, "center"))
        he = _vec3(self.half_extent, "half_extent")
        if min(he) <= 0:
            raise InputError(f"half_extent: expected > 0 in every axis, got {he}")
        object.__setattr__(self, "half_extent", he)
        if int(self.seed) != self.seed:
            raise InputError(f"seed: expected an integer, got {fmt_value(self.seed)}")
        object.__setattr__(self, "seed", int(self.seed))
        if self.albedo_fn is None and self.albedo_model not in ALBEDO_MODELS:
            known = ", ".join(sorted(ALBEDO_MODELS))
            raise InputError(
                f"albedo_model: unknown model {fmt_value(self.albedo_model)}; registered: {known} "
                "(add one with register_albedo_model)"
            )
        if not isinstance(self.albedo_params, dict):
            raise InputError(
                f"albedo_params: expected a dict, got {type(self.albedo_params).__name__}"
            )
        # A JSON-shaped copy (tuples → lists): equal to itself after a to_dict/from_dict trip.
        object.__setattr__(self, "albedo_params", _jsonable(self.albedo_params))
        if not 0.0 <= self.grazing_desaturation <= 1.0:
            raise InputError(
                f"grazing_desaturation: expected [0, 1], got {self.grazing_desaturation}"
            )
        for name, lo, hi in (("rho_s_base", 0.3, 1.0), ("rho_s_oily", 0.3, 1.0),
                             ("roughness_base", 0.25, 0.5), ("roughness_oily", 0.25, 0.5)):
            val = float(getattr(self, name))
            if not lo < val < hi:
                raise InputError(f"{name}: expected a value in ({lo}, {hi}), got {val}")
        lam = tuple(float(x) for x in self.noise_wavelengths)
        if len(lam) != 2 or not 0 < lam[0] <= lam[1]:
            raise InputError(
                f"noise_wavelengths: expected (min, max) > 0, got {self.noise_wavelengths}"
            )
        object.__setattr__(self, "noise_wavelengths", lam)
        if int(self.noise_waves) < 1:
            raise InputError(f"noise_waves: expected >= 1, got {self.noise_waves}")
        if self.region_centers is not None:
            if not isinstance(self.region_centers, dict):
                raise InputError("region_centers: expected a dict of region name → (3,) centre, "
                                 f"got {type(self.region_centers).__name__}")
            bad = sorted(set(self.region_centers) - set(REGIONS))
            if bad:
                raise InputError(f"region_centers: unknown region(s) {bad}; expected a subset "
                                 f"of {sorted(REGIONS)}")
            object.__setattr__(self, "region_centers", {
                str(k): list(_vec3(v, f"region_centers[{k!r}]"))
                for k, v in self.region_centers.items()})

    # ---------------------------------------------------------------- construction

    @classmethod
    def for_mesh(cls, mesh_or_vertices, seed: int = 0, **params) -> SkinField:
        """A field whose head frame is the bounding box of a mesh (or of ``(N, 3)`` vertices)."""
        v = getattr(mesh_or_vertices, "vertices", mesh_or_vertices)
        v = as_array(v, "vertices", shape=(None, 3))
        if len(v) == 0:
            raise InputError("for_mesh: no vertices")
        lo, hi = v.min(axis=0), v.max(axis=0)
        half = (hi - lo) / 2.0
        if np.any(half <= 0):
            raise InputError(f"for_mesh: degenerate bounding box (half sizes {half.tolist()})")
        return cls(center=(lo + hi) / 2.0, half_extent=half, seed=seed, **params)

    @classmethod
    def for_landmarks(cls, landmarks: dict, seed: int = 0, **params) -> SkinField:
        """A field for a real face: head frame fitted on its landmarks (:func:`landmark_frame`)
        and every region of :data:`REGIONS` centred on its landmark (:data:`REGION_ANCHORS`).

        Parameters
        ----------
        landmarks : dict of str → (3,) float64, metres, world frame
            As :func:`facegeo.synth.head.real_face_landmarks` returns them.
        seed, **params
            As the constructor.
        """
        center, half = landmark_frame(landmarks)
        centers = {name: ((np.asarray(landmarks[a], float) - center) / half).tolist()
                   for name, a in REGION_ANCHORS.items()}
        return cls(center=center, half_extent=half, seed=seed, region_centers=centers, **params)

    # ---------------------------------------------------------------- evaluation

    def normalised(self, p_world) -> np.ndarray:
        """Head-normalised coordinates ``u = (p − center)/half_extent``, (..., 3) float64."""
        p = as_array(p_world, "p_world", shape=(..., 3))
        return (p - np.asarray(self.center)) / np.asarray(self.half_extent)

    def _alpha_0(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The colour model's α₀ at ``u`` and, when the model provides one, its ρ_s."""
        if self.albedo_fn is not None:
            out = self.albedo_fn(u)
            name = "albedo_fn"
        else:
            if self.albedo_model not in ALBEDO_MODELS:
                known = ", ".join(sorted(ALBEDO_MODELS))
                raise InputError(
                    f"albedo_model: unknown model {fmt_value(self.albedo_model)}; registered: {known}"
                )
            out = ALBEDO_MODELS[self.albedo_model](u, self, **self.albedo_params)
            name = f"albedo model {self.albedo_model!r}"
        rho_s = None
        if isinstance(out, dict):
            if "alpha_0" not in out:
                raise InputError(f"{name}: returned a mapping without 'alpha_0'")
            if out.get("rho_s") is not None:
                rho_s = np.asarray(out["rho_s"], dtype=float)
                if rho_s.shape != u.shape[:-1] or not np.all(np.isfinite(rho_s) & (rho_s >= 0)):
                    raise InputError(f"{name}: rho_s must be finite, >= 0 and of shape "
                                     f"{u.shape[:-1]}, got shape {rho_s.shape}")
            out = out["alpha_0"]
        a = np.asarray(out, dtype=float)
        if a.shape != u.shape:
            raise InputError(f"{name}: returned shape {a.shape}, expected {u.shape}")
        return a, rho_s

    def evaluate(self, p_world) -> SkinSample:
        """Skin parameters at world points.

        Parameters
        ----------
        p_world : (..., 3) float64, metres, world frame

        Returns
        -------
        SkinSample
            float32 arrays with the query's leading shape.
        """
        u = self.normalised(p_world)
        lead = u.shape[:-1]
        u = u.reshape(-1, 3)
        n_pts = u.shape[0]
        a0 = np.empty((n_pts, 3), np.float32)
        a1 = np.empty((n_pts, 3), np.float32)
        rho_s = np.empty(n_pts, np.float32)
        m = np.empty(n_pts, np.float32)
        for i in range(0, n_pts, _CHUNK):
            sl = slice(i, i + _CHUNK)
            a0[sl], a1[sl], rho_s[sl], m[sl] = self._evaluate_block(u[sl])
        return SkinSample(
            alpha_0=a0.reshape(lead + (3,)),
            alpha_1=a1.reshape(lead + (3,)),
            rho_s=rho_s.reshape(lead),
            roughness=m.reshape(lead),
        )

    def _evaluate_block(self, u: np.ndarray):
        a0, model_rho_s = self._alpha_0(u)
        # Grazing colour: desaturated toward luminance, a little lighter (imitating the
        # grazing desaturation of Debevec et al. 2000 §4 with the generator's own blend).
        a1 = np.minimum(desaturate(a0, self.grazing_desaturation) * self.grazing_lift, 0.95)
        w = region_weights(u, self.region_centers)
        oil = w["forehead"] + w["nose"] + 0.35 * w["chin"]
        moist = w["lips"]
        x = u * np.asarray(self.half_extent)
        n = smooth_noise(x, self.seed * 7 + 2, 2, n_waves=self.noise_waves,
                         wavelengths=self.noise_wavelengths)
        # ρ_s in (0.3, 1): logistic of base + T-zone oiliness + noise.
        z0 = _logit((self.rho_s_base - 0.3) / 0.7)
        z1 = _logit((self.rho_s_oily - 0.3) / 0.7)
        z = z0 + (z1 - z0) * oil + 0.4 * (z1 - z0) * moist + self.spec_noise * n[..., 0]
        rho_s = 0.3 + 0.7 * _sigmoid(z)
        # m in (0.25, 0.5): oily and moist skin is smoother; noise partly anti-correlated.
        y0 = _logit((self.roughness_base - 0.25) / 0.25)
        y1 = _logit((self.roughness_oily - 0.25) / 0.25)
        y = (y0 + (y1 - y0) * oil + 0.6 * (y1 - y0) * moist
             - 0.5 * self.spec_noise * n[..., 0] + 0.5 * self.spec_noise * n[..., 1])
        m = 0.25 + 0.25 * _sigmoid(y)
        if model_rho_s is not None:
            rho_s = model_rho_s
        return a0, a1, rho_s, m

    def per_vertex(self, mesh) -> SkinSample:
        """:meth:`evaluate` at every vertex of a mesh (``mesh.vertices``, metres)."""
        return self.evaluate(np.asarray(mesh.vertices, dtype=float))

    # ---------------------------------------------------------------- serialisation

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready mapping; :meth:`from_dict` recreates an identical field.

        Raises
        ------
        InputError
            The field uses a bare ``albedo_fn``: register it with
            :func:`register_albedo_model` and pass its name as ``albedo_model`` instead.
        """
        if self.albedo_fn is not None:
            raise InputError(
                "SkinField.to_dict: a bare albedo_fn cannot be serialised; register it with "
                "register_albedo_model(name, model) and use albedo_model=name"
            )
        d: dict[str, Any] = {"format": FORMAT}
        for f in fields(self):
            if f.name == "albedo_fn":
                continue
            val = getattr(self, f.name)
            if f.name == "region_centers" and val is None:
                continue  # absent: the procedural head's skin.json is unchanged
            d[f.name] = list(val) if isinstance(val, tuple) else val
        d["albedo_params"] = _jsonable(self.albedo_params)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SkinField:
        """Inverse of :meth:`to_dict`; unknown keys and formats raise :class:`InputError`."""
        if not isinstance(d, dict):
            raise InputError(f"skin field: expected a mapping, got {type(d).__name__}")
        d = dict(d)
        fmt = d.pop("format", FORMAT)
        if fmt != FORMAT:
            raise InputError(f"skin field: unknown format {fmt_value(fmt)}; expected {fmt_value(FORMAT)}")
        names = {f.name for f in fields(cls)} - {"albedo_fn"}
        bad = sorted(set(d) - names)
        if bad:
            raise InputError(
                f"skin field: unknown key(s) {bad}; expected a subset of {sorted(names)}"
            )
        for key in ("center", "half_extent", "noise_wavelengths"):
            if key in d:
                d[key] = tuple(float(x) for x in d[key])
        return cls(**d)


def _jsonable(x):
    """Tuples → lists, numpy scalars/arrays → Python, recursively (values stay bit-exact)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


# --------------------------------------------------------------------------- landmark placement

#: Landmarks a real face's head frame is fitted on (names of facegeo.synth.head.head_landmarks).
FIT_LANDMARKS = ("nose_tip", "left_eye", "right_eye", "mouth_center", "upper_lip", "lower_lip",
                 "chin", "forehead", "left_cheek", "right_cheek", "left_under_eye",
                 "right_under_eye")

#: The landmark each region of :data:`REGIONS` is placed on (its distance to it is reported).
REGION_ANCHORS = {
    "lips": "mouth_center",
    "left_cheek": "left_cheek",
    "right_cheek": "right_cheek",
    "forehead": "forehead",
    "nose": "nose_bridge",
    "left_under_eye": "left_under_eye",
    "right_under_eye": "right_under_eye",
    "chin": "chin",
}


@functools.lru_cache(maxsize=1)
def _procedural_frame() -> tuple[np.ndarray, np.ndarray]:
    """Centre and half extent (3,) of the default procedural head at the ``small`` preset's
    resolution (subdivision 5): the frame :data:`REGIONS` were placed in."""
    from facegeo.synth.head import procedural_head

    v = np.asarray(procedural_head(5).vertices, dtype=float)
    lo, hi = v.min(axis=0), v.max(axis=0)
    return (lo + hi) / 2.0, (hi - lo) / 2.0


def landmark_frame(landmarks: dict) -> tuple[np.ndarray, np.ndarray]:
    """Head frame ``(center, half_extent)`` that puts a real face's landmarks where the
    default procedural head has them in head-normalised coordinates.

    For x and y, a least-squares line ``u_k = (p_k − c_k)/h_k`` through the pairs (real
    landmark p, procedural landmark u) for the :data:`FIT_LANDMARKS`; in depth the scale is the
    procedural one times the mean x/y scale ratio and only the offset is fitted. Every region of :data:`REGIONS`
    (and of any other model written in head-normalised coordinates, such as the spectral
    skin's) then lands on the same feature of the real face as on the procedural one,
    whatever the real mesh's bounding box holds (a neck, a back of the head, nothing but a
    face mask).

    Parameters
    ----------
    landmarks : dict of str → (3,) float64, metres, world frame

    Returns
    -------
    center, half_extent : (3,) float64, metres

    Raises
    ------
    InputError
        A landmark of :data:`FIT_LANDMARKS` is missing, or an axis's fit is degenerate
        (non-positive scale: the face is not +Y up, facing +Z).
    """
    from facegeo.synth.head import HEAD_LANDMARKS

    missing = [k for k in FIT_LANDMARKS if k not in landmarks]
    if missing:
        raise InputError(f"landmark_frame: landmarks lack {missing}")
    c0, h0 = _procedural_frame()
    p = np.array([landmarks[k] for k in FIT_LANDMARKS], dtype=float)
    u = (np.array([HEAD_LANDMARKS[k] for k in FIT_LANDMARKS]) - c0) / h0
    center = np.empty(3)
    half = np.empty(3)
    for k in range(2):
        a, b = np.polyfit(p[:, k], u[:, k], 1)
        if not (np.isfinite(a) and a > 0):
            raise InputError(f"landmark_frame: axis {'xy'[k]} fits a scale {a:.3g} (expected > 0); "
                             "is the face +Y up and facing +Z?")
        half[k] = 1.0 / a
        center[k] = -b / a
    # Depth: the landmarks span only ≈ 4 cm of it, too little to fit a scale (it came out 30 %
    # deeper than the procedural head's on the ICT face, stretching every region back toward
    # the neck); scale it like the face's width and height, fit only the offset.
    half[2] = h0[2] * float(np.mean(half[:2] / h0[:2]))
    center[2] = float(np.mean(p[:, 2] - u[:, 2] * half[2]))
    return center, half


def region_landmark_distances(skin: SkinField, vertices, faces, landmarks: dict, *,
                              face_mask=None) -> dict[str, dict]:
    """Where each skin region lands on a mesh, and how far that is from its landmark.

    A region's location is the centroid of its core — the faces (``face_mask``) whose
    membership (:func:`region_weights` at the face centroid) is at least half the largest one
    found, weighted by membership × area — moved onto the surface along the core's mean
    normal (the nearer hit of the two directions; the closest face centroid if both miss).
    A region placed off the face (on the neck, in the air, inside the head) shows up as a large
    distance or a small ``peak_weight``.

    Parameters
    ----------
    skin : SkinField
    vertices : (V, 3) float64, metres, world frame
    faces : (F, 3) int
    landmarks : dict of str → (3,) float64
        Must hold the landmarks named in :data:`REGION_ANCHORS`.
    face_mask : (F,) bool, optional
        Faces that carry skin (default all).

    Returns
    -------
    dict of region name → {"landmark": str, "distance_to_landmark_mm": float,
    "location_m": [x, y, z], "peak_weight": float (largest membership at a skin face)}
    """
    from facegeo.surface.visibility import RayScene

    v = as_array(vertices, "vertices", shape=(None, 3))
    f = as_array(faces, "faces", shape=(None, 3), dtype=np.int64)
    if face_mask is not None:
        f = f[np.asarray(face_mask, bool)]
    tri = v[f]
    centroid = tri.mean(axis=1)
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # |fn| = 2·area
    area = 0.5 * np.linalg.norm(fn, axis=1)
    weights = region_weights(skin.normalised(centroid), skin.region_centers)
    scene = RayScene(v, f)
    out = {}
    for name, anchor in REGION_ANCHORS.items():
        if anchor not in landmarks:
            raise InputError(f"region_landmark_distances: no landmark {anchor!r} for region {name!r}")
        w = weights[name]
        peak = float(w.max()) if w.size else 0.0
        core = w >= 0.5 * peak
        if peak <= 0 or not core.any():
            loc = np.full(3, np.nan)
        else:
            wa = (w * area)[core]
            c = (wa[:, None] * centroid[core]).sum(axis=0) / wa.sum()
            n = (w[core, None] * fn[core]).sum(axis=0)
            n = n / max(float(np.linalg.norm(n)), 1e-300)
            hits = scene.closest_hit(np.stack([c, c]), np.stack([n, -n]), t_min=0.0,
                                    fields=("t", "point"))
            if hits.hit.any():
                t = np.where(hits.hit, hits.t, np.inf)
                loc = hits.point[int(np.argmin(t))]
            else:
                loc = centroid[core][int(np.argmin(np.linalg.norm(centroid[core] - c, axis=1)))]
        d = float(np.linalg.norm(loc - np.asarray(landmarks[anchor], float)))
        out[name] = {"landmark": anchor, "distance_to_landmark_mm": 1000.0 * d,
                     "location_m": loc.tolist(), "peak_weight": peak}
    return out


# --------------------------------------------------------------------------- non-skin parts


@dataclass(frozen=True)
class PartMaterial:
    """A simple uniform material for a non-skin mesh part, in the generator BRDF's terms.

    ``alpha_0 = alpha_1 = albedo`` (no grazing colour shift: that is a skin property), a
    uniform specular scale and Beckmann roughness; no skin-field parameters, no noise.
    """

    albedo: tuple[float, float, float]
    rho_s: float
    roughness: float


#: Materials of the mesh parts of :data:`facegeo.synth.head.PART_NAMES` other than skin:
#: a bright, wet sclera and a dark, wet iris (low roughness: the tear film), ivory teeth,
#: dark-red gums, tongue and mouth interior.
PART_MATERIALS: dict[str, PartMaterial] = {
    "sclera": PartMaterial((0.62, 0.56, 0.52), 0.9, 0.15),
    "iris": PartMaterial((0.10, 0.06, 0.035), 0.9, 0.15),
    "teeth": PartMaterial((0.66, 0.60, 0.48), 0.6, 0.25),
    "mouth_interior": PartMaterial((0.30, 0.07, 0.07), 0.6, 0.30),
}


def apply_part_materials(sample: SkinSample, labels, names) -> SkinSample:
    """Replace the skin parameters of points on non-skin parts by their part's material.

    Parameters
    ----------
    sample : SkinSample
        Skin-field parameters at P points (leading shape (P,)).
    labels : (P,) int
        Part of each point, indexing ``names``; 0 (``names[0] == "skin"``) keeps the skin.
    names : sequence of str
        Part names; every non-skin name must be in :data:`PART_MATERIALS`.

    Returns
    -------
    SkinSample
        A copy with the part materials written in (float32).
    """
    labels = np.asarray(labels).reshape(-1)
    a0 = np.array(sample.alpha_0, np.float32, copy=True)
    a1 = np.array(sample.alpha_1, np.float32, copy=True)
    rho = np.array(sample.rho_s, np.float32, copy=True)
    m = np.array(sample.roughness, np.float32, copy=True)
    for k, name in enumerate(names):
        if name == "skin":
            continue
        if name not in PART_MATERIALS:
            raise InputError(f"part {name!r}: no material; expected one of {sorted(PART_MATERIALS)}")
        sel = labels == k
        if sel.any():
            mat = PART_MATERIALS[name]
            a0[sel] = mat.albedo
            a1[sel] = mat.albedo
            rho[sel] = mat.rho_s
            m[sel] = mat.roughness
    return SkinSample(alpha_0=a0, alpha_1=a1, rho_s=rho, roughness=m)
