"""Physiological parameter maps over a head, and the spectral albedo they imply.

:func:`regional_parameter_maps` maps head-normalised positions u (face toward +Z, +Y up,
u ∈ [−1, 1]³, the coordinates of :class:`facegeo.synth.skin.SkinField`) to smooth maps of
(C_m, β_m, C_h, ρ_s): a base skin type, regional multipliers (more blood in the lips, cheeks,
nose tip and ears; oilier forehead, nose and chin; less melanin on the lips), and seeded
smooth noise. :func:`spectral_albedo_fn` turns those maps into the linear-sRGB ``alpha_0`` the
synthetic skin field takes as its ``albedo_fn``; :mod:`facegeo.synth.skin` serves it as
its named, serialisable ``"spectral"`` albedo model.

Everything is a pure function of (u, seed): the same point always gets the same skin.

The base skin types come from fitting the model to the 4,392 measured spectra of Xiao et al.
2016 (``docs/spectral.md``): C_m 5th/50th/95th percentiles 0.013/0.025/0.065 and C_h
0.0024/0.0083/0.018; the fits put β_m at 0 for 95 % of them (pheomelanin's steeper spectrum
explains the measured blue absorption best). ``"dark"`` extends beyond that set (C_m = 0.15).
The regional factors are plausible choices, not measurements.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from facegeo.checks import as_array, check_choice, fmt_value
from facegeo.errors import InputError
from facegeo.appearance.spectral._lut import SkinLUT, skin_lut
from facegeo.appearance.spectral._model import PARAMETER_RANGES, SkinParameters

__all__ = [
    "SKIN_TYPES",
    "PARAMETER_REGIONS",
    "regional_parameter_maps",
    "spectral_albedo_fn",
]

#: Base parameters of named skin types (see the module docstring for their source).
SKIN_TYPES: dict[str, dict[str, float]] = {
    "light": {"C_m": 0.015, "beta_m": 0.05, "C_h": 0.006, "rho_s": 0.25},
    "medium": {"C_m": 0.03, "beta_m": 0.05, "C_h": 0.008, "rho_s": 0.3},
    "olive": {"C_m": 0.06, "beta_m": 0.2, "C_h": 0.01, "rho_s": 0.3},
    "dark": {"C_m": 0.15, "beta_m": 0.5, "C_h": 0.012, "rho_s": 0.35},
}

#: Regions: name → (centre u (3,), radii (3,), {parameter: (kind, amount)}), kind "mul"
#: (multiply by 1 + (amount − 1)·w) or "add" (add amount·w). x is mirrored (|u_x|) for
#: symmetric pairs, whose centre has x > 0. Centres follow facegeo.synth.skin.REGIONS.
_Region = tuple[tuple[float, ...], tuple[float, ...], dict[str, tuple[str, float]]]
PARAMETER_REGIONS: dict[str, _Region] = {
    "lips": ((0.0, -0.56, 0.77), (0.30, 0.12, 0.30),
             {"C_h": ("mul", 6.0), "C_m": ("mul", 0.7), "rho_s": ("add", 0.15)}),
    "cheeks": ((0.56, -0.27, 0.57), (0.24, 0.24, 0.40), {"C_h": ("mul", 2.0)}),
    "forehead": ((0.0, 0.58, 0.58), (0.50, 0.25, 0.40), {"rho_s": ("add", 0.3)}),
    "nose": ((0.0, -0.05, 0.85), (0.14, 0.30, 0.35),
             {"rho_s": ("add", 0.35), "C_h": ("mul", 1.6)}),
    "under_eyes": ((0.42, -0.07, 0.71), (0.15, 0.08, 0.30),
                   {"C_m": ("mul", 1.2), "C_h": ("mul", 1.3)}),
    "chin": ((0.0, -0.85, 0.48), (0.22, 0.13, 0.35), {"rho_s": ("add", 0.15)}),
    "ears": ((0.95, 0.0, 0.0), (0.12, 0.25, 0.25), {"C_h": ("mul", 1.5)}),
}

#: Amplitude of the seeded noise: relative (log) for C_m and C_h, absolute for β_m and ρ_s.
_NOISE = {"C_m": 0.12, "beta_m": 0.05, "C_h": 0.2, "rho_s": 0.05}
_N_WAVES = 8
_NAMES = ("C_m", "beta_m", "C_h", "rho_s")


def _bump(u: np.ndarray, centre, radii, mirror: bool) -> np.ndarray:
    """exp(−ln 2 · q²), q = Σ ((u − c)/r)²: 1 at the centre, ½ on the ellipsoid (C^∞)."""
    v = u.copy()
    if mirror:
        v[..., 0] = np.abs(v[..., 0])
    q = np.sum(((v - np.asarray(centre)) / np.asarray(radii)) ** 2, axis=-1)
    return np.exp(-np.log(2.0) * q * q)


def _noise(u: np.ndarray, seed: int) -> dict[str, np.ndarray]:
    """Seeded smooth noise, zero mean, unit variance per parameter: random plane waves."""
    rng = np.random.default_rng([int(seed), 0x5C1])
    out = {}
    for name in _NAMES:
        f = rng.normal(0.0, 1.5, size=(_N_WAVES, 3))  # cycles per unit of u
        phase = rng.uniform(0.0, 2.0 * np.pi, size=_N_WAVES)
        arg = 2.0 * np.pi * (u @ f.T) + phase
        out[name] = np.sqrt(2.0 / _N_WAVES) * np.cos(arg).sum(axis=-1)
    return out


def _base(params) -> dict[str, float]:
    if isinstance(params, str):
        check_choice(params, "params", SKIN_TYPES)
        return dict(SKIN_TYPES[params])
    if isinstance(params, SkinParameters):
        params = params.as_dict()
    if not isinstance(params, dict):
        raise InputError(
            f"params: expected a skin type name ({', '.join(SKIN_TYPES)}), a dict or "
            f"SkinParameters, got {type(params).__name__}"
        )
    base = dict(SKIN_TYPES["medium"])
    unknown = set(params) - set(_NAMES)
    if unknown:
        raise InputError(f"params: unknown key(s) {sorted(unknown)}; expected {list(_NAMES)}")
    for k, v in params.items():
        v = float(np.asarray(v))
        lo, hi = PARAMETER_RANGES[k]
        if not (np.isfinite(v) and lo <= v <= hi):
            raise InputError(f"params[{fmt_value(k)}]: expected a value in [{lo:g}, {hi:g}], got {fmt_value(v)}")
        base[k] = v
    return base


def regional_parameter_maps(
    u, params="medium", *, seed: int = 0, variation: float = 1.0
) -> SkinParameters:
    """Smooth maps of (C_m, β_m, C_h, ρ_s) over a head.

    Parameters
    ----------
    u : (..., 3) array_like float
        Head-normalised positions (face toward +Z, +Y up, the head spans [−1, 1]³).
    params : str, dict or SkinParameters
        Base skin: a name of :data:`SKIN_TYPES` or scalar values for any of C_m, beta_m,
        C_h, rho_s (the rest from ``"medium"``).
    seed : int
        Seed of the smooth noise.
    variation : float
        Scale of the regional factors and of the noise (0: uniform skin).

    Returns
    -------
    SkinParameters
        Arrays of shape (...), clipped to :data:`PARAMETER_RANGES`.
    """
    u = as_array(u, "u", shape=(..., 3))
    if not (np.isfinite(variation) and variation >= 0):
        raise InputError(f"variation: expected a finite number >= 0, got {fmt_value(variation)}")
    base = _base(params)
    shape = u.shape[:-1]
    log_cm = np.full(shape, np.log(base["C_m"]))
    log_ch = np.full(shape, np.log(base["C_h"]))
    beta = np.full(shape, base["beta_m"])
    rho = np.full(shape, base["rho_s"])
    for centre, radii, effects in PARAMETER_REGIONS.values():
        w = variation * _bump(u, centre, radii, mirror=centre[0] > 0)
        for name, (kind, amount) in effects.items():
            if name == "C_m":
                log_cm += w * np.log(amount)
            elif name == "C_h":
                log_ch += w * np.log(amount)
            elif name == "beta_m":
                beta += w * amount
            else:
                rho += w * amount
    if variation > 0:
        n = _noise(u, seed)
        log_cm += variation * _NOISE["C_m"] * n["C_m"]
        log_ch += variation * _NOISE["C_h"] * n["C_h"]
        beta += variation * _NOISE["beta_m"] * n["beta_m"]
        rho += variation * _NOISE["rho_s"] * n["rho_s"]
    out = {}
    values = {"C_m": np.exp(log_cm), "beta_m": beta, "C_h": np.exp(log_ch), "rho_s": rho}
    for name, value in values.items():
        lo, hi = PARAMETER_RANGES[name]
        out[name] = np.clip(value, lo, hi)
    return SkinParameters(**out)


def spectral_albedo_fn(
    params="medium",
    *,
    seed: int = 0,
    variation: float = 1.0,
    lut: SkinLUT | None = None,
    exact: bool = False,
) -> Callable[[np.ndarray], np.ndarray]:
    """A pure function ``albedo(u) -> alpha_0`` for :class:`facegeo.synth.skin.SkinField`.

    Parameters
    ----------
    params, seed, variation
        As :func:`regional_parameter_maps`.
    lut : SkinLUT, optional
        Table to interpolate (default :func:`facegeo.appearance.spectral.skin_lut` ()); its error is
        ≤ 0.12 % relative.
    exact : bool
        Evaluate the spectral model at every point instead (≈ 100× slower).

    Returns
    -------
    callable
        ``albedo(u: (..., 3)) -> (..., 3) float32`` linear sRGB. The callable also carries
        ``albedo.parameter_maps(u) -> SkinParameters`` (the ground truth behind the colour).
    """
    _base(params)  # validate now, not at the first evaluation
    table = lut

    def parameter_maps(u) -> SkinParameters:
        return regional_parameter_maps(u, params, seed=seed, variation=variation)

    def albedo(u) -> np.ndarray:
        p = parameter_maps(u)
        if exact:
            from facegeo.appearance.spectral._model import skin_rgb

            rgb = skin_rgb(p.C_m, p.beta_m, p.C_h)
        else:
            rgb = (table or skin_lut()).interpolate(p.C_m, p.beta_m, p.C_h)
        return rgb.astype(np.float32)

    albedo.parameter_maps = parameter_maps  # type: ignore[attr-defined]
    return albedo
