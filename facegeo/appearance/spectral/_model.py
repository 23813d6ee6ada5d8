"""The forward spectral skin model: (C_m, β_m, C_h) → reflectance spectrum → linear-sRGB albedo.

Implements Donner & Jensen 2006 with the choices below (each deviation is stated where made):

1. Absorption and reduced scattering of the epidermis and dermis, Eqs. (3)–(8)
   (:mod:`facegeo.appearance.spectral._absorption`).
2. The epidermis (0.25 mm) is a multipole slab, the dermis a dipole half-space, both of index
   η = 1.4 (Donner & Jensen 2005); their totals are combined by the adding relation
   (:func:`~facegeo.appearance.spectral._diffusion.two_layer_total_reflectance`), the zero-frequency term
   of D&J 2005's frequency-domain layer combination. This gives the total diffuse
   reflectance of the subsurface term, the quantity the paper turns into colour.
3. Light crosses the rough oily surface first: the surface term is Torrance–Sparrow with a
   Beckmann distribution (m = 0.35) scaled by ρ_s (:func:`facegeo.appearance.brdf.specular_brdf`), and
   the subsurface term is scaled by (1 − ρ_dr), ρ_dr the hemispherical (diffuse) Fresnel
   reflectance of the η = 1.4 surface, 0.0768 (D&J 2006 Eqs. 1–2, as given in issue #3).

The albedo ``alpha_0`` of the synthetic skin is therefore ``(1 − ρ_dr) · R_ml(λ)`` integrated
against D65 and the CIE 1931 2° observer (:mod:`facegeo.appearance.spectral._colour`).
When the synthetic generator renders with it, its own skin BRDF
(:func:`facegeo.appearance.brdf.synthetic_skin_brdf`, deliberately not the paper's §4 model)
weights the diffuse term once more by the angle-dependent ``(1 − ρ_dr(θ_i))(1 − ρ_dr(θ_r))`` of
its Torrance–Sparrow lobe (ρ_s-scaled, D&J 2006 Eq. 2) so that it conserves energy at grazing
angles; ``alpha_0`` is then the colour before that weight, not the measured normal-incidence
albedo (the two differ by ≈ (1 − 0.028 ρ_s)² at normal incidence).

References
----------
Donner, C., Jensen, H. W. (2006). A Spectral BSSRDF for Shading Human Skin. EGSR 2006.
Donner, C., Jensen, H. W. (2005). Light Diffusion in Multi-Layered Translucent Materials.
SIGGRAPH 2005.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from facegeo.checks import as_array, fmt_value
from facegeo.errors import InputError, ShapeError
from facegeo.appearance.spectral._absorption import (
    DEFAULT_EUMELANIN,
    GAMMA_OXY,
    check_wavelengths,
    dermis_absorption,
    dermis_scattering,
    epidermis_absorption,
    epidermis_scattering,
)
from facegeo.appearance.spectral._colour import spectrum_to_rgb
from facegeo.appearance.spectral._diffusion import two_layer_total_reflectance

__all__ = [
    "ETA_SKIN",
    "EPIDERMIS_THICKNESS_MM",
    "BECKMANN_M",
    "DEFAULT_WAVELENGTHS_NM",
    "PARAMETER_RANGES",
    "SkinParameters",
    "check_skin_parameters",
    "rho_dr",
    "subsurface_transmission",
    "surface_brdf",
    "skin_spectrum",
    "skin_rgb",
]

#: Index of refraction of both skin layers (D&J 2006 §3: "a constant index of refraction of 1.4").
ETA_SKIN = 1.4
#: Epidermis thickness [mm] (D&J 2006 §3).
EPIDERMIS_THICKNESS_MM = 0.25
#: Beckmann RMS slope of the Torrance–Sparrow surface term (D&J 2006 §3).
BECKMANN_M = 0.35
#: Default spectral grid: 380–780 nm every 4 nm, the haemoglobin table's grid (101 samples).
DEFAULT_WAVELENGTHS_NM = np.arange(380.0, 780.0 + 1e-9, 4.0)
DEFAULT_WAVELENGTHS_NM.setflags(write=False)

#: Parameter ranges of the lookup table and the inverse fit (closed intervals). D&J 2006's
#: table gives C_m 0–0.5, β_m 0–1, C_h 0.001–0.1, ρ_s 0–1; C_h is extended to 0.32 (the dermal
#: range of Jimenez et al. 2010, built on the same model) so lips and flushed skin are covered,
#: and C_m starts at 0.001 because the cube-root axes of the table need C > 0.
PARAMETER_RANGES: dict[str, tuple[float, float]] = {
    "C_m": (0.001, 0.5),
    "beta_m": (0.0, 1.0),
    "C_h": (0.001, 0.32),
    "rho_s": (0.0, 1.0),
}


@dataclass(frozen=True)
class SkinParameters:
    """Per-texel physiological parameters, arrays of one common shape ``(...)``.

    Attributes
    ----------
    C_m : (...) float64
        Melanin volume fraction of the epidermis.
    beta_m : (...) float64
        Melanin blend, the eumelanin share (1 = all eumelanin, 0 = all pheomelanin).
    C_h : (...) float64
        Blood volume fraction of the dermis.
    rho_s : (...) float64 or None
        Oiliness: scale of the Torrance–Sparrow surface term.
    """

    C_m: np.ndarray
    beta_m: np.ndarray
    C_h: np.ndarray
    rho_s: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, ...]:
        return np.shape(self.C_m)

    def as_dict(self) -> dict[str, np.ndarray]:
        d = {"C_m": self.C_m, "beta_m": self.beta_m, "C_h": self.C_h}
        if self.rho_s is not None:
            d["rho_s"] = self.rho_s
        return d


def check_skin_parameters(
    C_m, beta_m, C_h, *, ranges: dict[str, tuple[float, float]] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate and broadcast (C_m, β_m, C_h).

    Each must be finite and inside ``ranges`` (default: [0, 1] for all three, the physical
    limits of a volume fraction or a blend). Raises :class:`~facegeo.errors.InputError` naming
    the parameter, the allowed interval and the first bad value, or
    :class:`~facegeo.errors.ShapeError` when the shapes do not broadcast.

    Returns
    -------
    C_m, beta_m, C_h : (...) float64, broadcast to one shape
    """
    ranges = ranges or {"C_m": (0.0, 1.0), "beta_m": (0.0, 1.0), "C_h": (0.0, 1.0)}
    out = []
    for name, value in (("C_m", C_m), ("beta_m", beta_m), ("C_h", C_h)):
        a = as_array(value, name)
        lo, hi = ranges[name]
        bad = (a < lo) | (a > hi)
        if np.any(bad):
            first = a[bad].ravel()[0]
            raise InputError(
                f"{name}: {int(bad.sum())} value(s) outside [{lo:g}, {hi:g}]; first is {first:.6g}"
            )
        out.append(a)
    try:
        return tuple(np.broadcast_arrays(*out))  # type: ignore[return-value]
    except ValueError as exc:
        shapes = ", ".join(str(np.shape(a)) for a in out)
        raise ShapeError(f"C_m, beta_m, C_h: shapes {shapes} do not broadcast") from exc


@functools.lru_cache(maxsize=8)
def rho_dr(eta: float = ETA_SKIN) -> float:
    """ρ_dr: hemispherical (cosine-weighted) Fresnel reflectance of a smooth dielectric (outside).

    ρ_dr = 2 ∫₀¹ F(μ) μ dμ with F the exact unpolarised Fresnel reflectance
    (:func:`facegeo.appearance.brdf.fresnel_dielectric`), by 64-point Gauss–Legendre quadrature.
    ρ_dr(1.4) = 0.0768; the fraction (1 − ρ_dr) of diffuse light enters the skin.
    """
    from facegeo.appearance.brdf import fresnel_dielectric

    if not (np.isfinite(eta) and eta >= 1.0):
        raise InputError(f"eta: expected a relative index >= 1, got {fmt_value(eta)}")
    x, w = np.polynomial.legendre.leggauss(64)
    mu = 0.5 * (x + 1.0)
    return float(np.sum(w * 0.5 * 2.0 * fresnel_dielectric(mu, eta) * mu))


def subsurface_transmission(eta: float = ETA_SKIN) -> float:
    """1 − ρ_dr, the scale of the subsurface term (D&J 2006 Eq. 2 as given in issue #3)."""
    return 1.0 - rho_dr(eta)


def surface_brdf(n, l, v, rho_s, *, m: float = BECKMANN_M, eta: float = ETA_SKIN) -> np.ndarray:
    """The surface term f_s = ρ_s · Torrance–Sparrow(Beckmann m = 0.35, η = 1.4) [1/sr].

    D&J 2006 Eq. (1); delegates to :func:`facegeo.appearance.brdf.specular_brdf` (shared with the
    Debevec et al. 2000 skin model). ``n, l, v`` are (..., 3) unit vectors in one frame.
    """
    from facegeo.appearance.brdf import specular_brdf

    return specular_brdf(n, l, v, rho_s, m, eta)


def _layer_reflectance(C_m, beta_m, C_h, wl, convention, gamma, thickness, eta):
    sa_epi = epidermis_absorption(wl, C_m, beta_m, convention=convention)
    sa_derm = dermis_absorption(wl, C_h, gamma=gamma)
    return two_layer_total_reflectance(
        sa_epi, epidermis_scattering(wl), thickness, sa_derm, dermis_scattering(wl), eta
    )


def skin_spectrum(
    C_m,
    beta_m,
    C_h,
    wavelengths=None,
    *,
    convention: str = DEFAULT_EUMELANIN,
    gamma: float = GAMMA_OXY,
    thickness: float = EPIDERMIS_THICKNESS_MM,
    eta: float = ETA_SKIN,
    surface_loss: bool = True,
    chunk: int = 8192,
) -> np.ndarray:
    """Diffuse reflectance spectrum of skin, (1 − ρ_dr) · R_d(λ) (D&J 2006 §3–4).

    Parameters
    ----------
    C_m, beta_m, C_h : array_like (...) float, fractions in [0, 1]
        Melanin fraction, melanin blend (eumelanin share), blood fraction; broadcast together.
    wavelengths : (L,) array_like float, nm, optional
        Inside 380–780 nm. Default :data:`DEFAULT_WAVELENGTHS_NM` (every 4 nm).
    convention : str
        Eumelanin constant (see :data:`facegeo.appearance.spectral.EUMELANIN_COEFFICIENTS`).
    gamma : float
        Haemoglobin oxygenation (0.75).
    thickness : float, mm
        Epidermis thickness (0.25).
    eta : float
        Index of both layers (1.4).
    surface_loss : bool
        Multiply by (1 − ρ_dr) (default). False returns the two-layer R_d of the light that
        entered.
    chunk : int
        Parameter sets per vectorised block (bounds the memory to ~chunk · L · 200 bytes).

    Returns
    -------
    (..., L) float64
        Reflectance, unitless in [0, 1].
    """
    C_m, beta_m, C_h = check_skin_parameters(C_m, beta_m, C_h)
    wl = (
        DEFAULT_WAVELENGTHS_NM if wavelengths is None else check_wavelengths(wavelengths)
    )
    shape = C_m.shape
    flat = [np.ravel(a) for a in (C_m, beta_m, C_h)]
    n = flat[0].size
    out = np.empty((n, wl.size))
    for s in range(0, n, max(1, int(chunk))):
        e = min(n, s + int(chunk))
        out[s:e] = _layer_reflectance(
            flat[0][s:e], flat[1][s:e], flat[2][s:e], wl, convention, gamma, thickness, eta
        )
    if surface_loss:
        out *= subsurface_transmission(eta)
    return out.reshape(shape + (wl.size,))


def skin_rgb(C_m, beta_m, C_h, *, wavelengths=None, **kwargs) -> np.ndarray:
    """Linear-sRGB albedo of skin (D65, CIE 1931 2°; white reflector → (1, 1, 1)).

    Parameters
    ----------
    C_m, beta_m, C_h : array_like (...) float, fractions in [0, 1]
    wavelengths : (L,) float, nm, optional
        Integration grid (default every 4 nm over 380–780 nm).
    **kwargs
        Passed to :func:`skin_spectrum`.

    Returns
    -------
    (..., 3) float64, linear sRGB
    """
    wl = DEFAULT_WAVELENGTHS_NM if wavelengths is None else check_wavelengths(wavelengths)
    spec = skin_spectrum(C_m, beta_m, C_h, wl, **kwargs)
    return spectrum_to_rgb(spec, wl)
