"""Spectral absorption and reduced scattering of the two skin layers (Donner & Jensen 2006, §3).

Every coefficient is in **mm⁻¹**, every wavelength in **nm**. Functions broadcast: parameters of
shape ``(...)`` and wavelengths of shape ``(L,)`` give coefficients of shape ``(..., L)``.

Units of the melanin laws
-------------------------
Donner & Jensen print Eq. (3) as ``σ_a^em(λ) = 6.6 × 10¹¹ λ^−3.33`` with the label mm⁻¹. The
law is Jacques' melanosome absorption (OMLC 1998), which Jacques gives in **cm⁻¹**; converted
to mm⁻¹ it is ``6.6 × 10¹⁰ λ^−3.33``. The same paper converts Jacques' baseline law to mm⁻¹
(Eq. 5: 0.0244 + 8.53 e^…, Jacques' 0.244 + 85.3 e^… cm⁻¹), and with 6.6 × 10¹⁰ the
eumelanin/pheomelanin ratio (1.15 at 400 nm, 1.55 at 500 nm, 2.3 at 650 nm) matches Sarna &
Swartz's measured mass-extinction ratio (1.2, 1.5, 2.7; ``../shared/data/skin``), while the
printed 6.6 × 10¹¹ makes eumelanin ten times stronger than pheomelanin at every wavelength and
makes C_m = 0.5 (the top of the paper's range) an opaque black. We therefore default to
6.6 × 10¹⁰ mm⁻¹ (``"Jacques 1998"``) and keep the printed value selectable
(``"Donner Jensen 2006 printed"``) in :data:`EUMELANIN_COEFFICIENTS`.

References
----------
Donner, C., Jensen, H. W. (2006). A Spectral BSSRDF for Shading Human Skin. Eurographics
Symposium on Rendering, §3, Eqs. (3)–(8).
Jacques, S. L. (1998). Skin optics. Oregon Medical Laser Center News,
https://omlc.org/news/jan98/skinoptics.html.
Prahl, S. (1999). Optical absorption of hemoglobin. https://omlc.org/spectra/hemoglobin/.
"""

from __future__ import annotations

import numpy as np

from facegeo.checks import as_array, check_choice
from facegeo.errors import InputError
from facegeo.appearance.spectral._hemoglobin import HB_EPSILON_DEOXY, HB_EPSILON_OXY, HB_WAVELENGTHS_NM

__all__ = [
    "EUMELANIN_COEFFICIENTS",
    "GAMMA_OXY",
    "HB_CONCENTRATION_G_PER_L",
    "HB_MOLAR_MASS_G_PER_MOL",
    "WAVELENGTH_RANGE_NM",
    "check_wavelengths",
    "eumelanin_absorption",
    "pheomelanin_absorption",
    "baseline_absorption",
    "haemoglobin_absorption",
    "epidermis_absorption",
    "dermis_absorption",
    "epidermis_scattering",
    "dermis_scattering",
]

#: Eq. (3) coefficient a in σ_a^em = a λ^−3.33 [mm⁻¹], keyed by "Author Year".
EUMELANIN_COEFFICIENTS: dict[str, float] = {
    "Jacques 1998": 6.6e10,  # Jacques' 6.6e11 cm⁻¹ converted to mm⁻¹ (default, see module doc)
    "Donner Jensen 2006 printed": 6.6e11,  # the paper's Eq. (3) read literally as mm⁻¹
}
DEFAULT_EUMELANIN = "Jacques 1998"

#: Haemoglobin oxygenation γ (fraction of oxy-haemoglobin), fixed in D&J 2006 §3.
GAMMA_OXY = 0.75
#: Haemoglobin concentration of whole blood [g/L] (Prahl's convention).
HB_CONCENTRATION_G_PER_L = 150.0
#: Molar mass of haemoglobin (tetramer) [g/mol] (Prahl's convention).
HB_MOLAR_MASS_G_PER_MOL = 64500.0
#: Wavelengths the package's haemoglobin table covers [nm].
WAVELENGTH_RANGE_NM = (float(HB_WAVELENGTHS_NM[0]), float(HB_WAVELENGTHS_NM[-1]))


def check_wavelengths(wavelengths, name: str = "wavelengths") -> np.ndarray:
    """Validate a 1-D wavelength grid in nm inside :data:`WAVELENGTH_RANGE_NM`.

    Returns
    -------
    (L,) float64, nm
    """
    wl = as_array(wavelengths, name, shape=(None,))
    if wl.size == 0:
        raise InputError(f"{name}: expected at least one wavelength, got an empty array")
    lo, hi = WAVELENGTH_RANGE_NM
    if wl.min() < lo or wl.max() > hi:
        raise InputError(
            f"{name}: wavelengths must lie in [{lo:g}, {hi:g}] nm (the haemoglobin table's "
            f"range); got [{wl.min():g}, {wl.max():g}] nm"
        )
    return wl


def eumelanin_absorption(wavelength_nm, *, convention: str = DEFAULT_EUMELANIN) -> np.ndarray:
    """Eumelanin absorption σ_a^em(λ) = a λ^−3.33 [mm⁻¹] (D&J 2006 Eq. 3).

    Parameters
    ----------
    wavelength_nm : array_like, nm
    convention : str
        Key of :data:`EUMELANIN_COEFFICIENTS` (see the module docstring for why the default
        differs from the printed constant).
    """
    check_choice(convention, "convention", EUMELANIN_COEFFICIENTS)
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    return EUMELANIN_COEFFICIENTS[convention] * wl ** -3.33


def pheomelanin_absorption(wavelength_nm) -> np.ndarray:
    """Pheomelanin absorption σ_a^pm(λ) = 2.9 × 10¹⁴ λ^−4.75 [mm⁻¹] (D&J 2006 Eq. 4)."""
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    return 2.9e14 * wl ** -4.75


def baseline_absorption(wavelength_nm) -> np.ndarray:
    """Baseline (bloodless, melanin-free) skin absorption [mm⁻¹] (D&J 2006 Eq. 5).

    σ_a^baseline(λ) = 0.0244 + 8.53 exp(−(λ − 154)/66.2), Jacques' rat-skin law in mm⁻¹.
    """
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    return 0.0244 + 8.53 * np.exp(-(wl - 154.0) / 66.2)


def haemoglobin_absorption(wavelength_nm) -> tuple[np.ndarray, np.ndarray]:
    """Absorption of whole blood, fully oxygenated and fully deoxygenated [mm⁻¹].

    σ_a = ln(10) · ε(λ) · c_Hb / 10 with ε Prahl's molar extinction [cm⁻¹ M⁻¹] linearly
    interpolated from the package table (380–780 nm every 4 nm), c_Hb = 150 g/L / 64 500 g/mol
    = 2.326 mM, and /10 for cm⁻¹ → mm⁻¹. At 542 nm, σ_a^oxy ≈ 28.5 mm⁻¹.

    Parameters
    ----------
    wavelength_nm : (L,) array_like, nm, inside :data:`WAVELENGTH_RANGE_NM`

    Returns
    -------
    sigma_a_oxy, sigma_a_deoxy : (L,) float64, mm⁻¹
    """
    wl = check_wavelengths(np.atleast_1d(wavelength_nm), "wavelength_nm")
    c_molar = HB_CONCENTRATION_G_PER_L / HB_MOLAR_MASS_G_PER_MOL
    k = np.log(10.0) * c_molar / 10.0
    oxy = k * np.interp(wl, HB_WAVELENGTHS_NM, HB_EPSILON_OXY)
    deoxy = k * np.interp(wl, HB_WAVELENGTHS_NM, HB_EPSILON_DEOXY)
    return oxy, deoxy


def epidermis_absorption(
    wavelength_nm, C_m, beta_m, *, convention: str = DEFAULT_EUMELANIN
) -> np.ndarray:
    """Epidermis absorption [mm⁻¹] (D&J 2006 Eq. 6).

    σ_a^epi = C_m (β_m σ_a^em + (1 − β_m) σ_a^pm) + (1 − C_m) σ_a^baseline.

    Parameters
    ----------
    wavelength_nm : (L,) float, nm
    C_m : (...) float
        Melanin volume fraction of the epidermis.
    beta_m : (...) float
        Melanin blend: the eumelanin share of the melanin (1 = all eumelanin).

    Returns
    -------
    (..., L) float64, mm⁻¹
    """
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    C_m = np.asarray(C_m, dtype=np.float64)[..., None]
    beta_m = np.asarray(beta_m, dtype=np.float64)[..., None]
    em = eumelanin_absorption(wl, convention=convention)
    pm = pheomelanin_absorption(wl)
    return C_m * (beta_m * em + (1.0 - beta_m) * pm) + (1.0 - C_m) * baseline_absorption(wl)


def dermis_absorption(wavelength_nm, C_h, *, gamma: float = GAMMA_OXY) -> np.ndarray:
    """Dermis absorption [mm⁻¹] (D&J 2006 Eq. 7).

    σ_a^derm = C_h (γ σ_a^oxy + (1 − γ) σ_a^deoxy) + (1 − C_h) σ_a^baseline, γ = 0.75.

    Parameters
    ----------
    wavelength_nm : (L,) float, nm
    C_h : (...) float
        Blood (haemoglobin) volume fraction of the dermis.

    Returns
    -------
    (..., L) float64, mm⁻¹
    """
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    C_h = np.asarray(C_h, dtype=np.float64)[..., None]
    oxy, deoxy = haemoglobin_absorption(wl)
    blood = gamma * oxy + (1.0 - gamma) * deoxy
    return C_h * blood + (1.0 - C_h) * baseline_absorption(wl)


def epidermis_scattering(wavelength_nm) -> np.ndarray:
    """Reduced scattering of the epidermis σ_s′ [mm⁻¹] (D&J 2006 Eq. 8).

    σ_s′(λ) = 14.74 λ^−0.22 + 2.2 × 10¹¹ λ^−4 (twice Jacques' dermal Mie + Rayleigh law,
    73.7 λ^−0.22 + 1.1 × 10¹² λ^−4 cm⁻¹). At 500 nm: 7.28 mm⁻¹.
    """
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    return 14.74 * wl ** -0.22 + 2.2e11 * wl ** -4.0


def dermis_scattering(wavelength_nm) -> np.ndarray:
    """Reduced scattering of the dermis [mm⁻¹]: 50 % of the epidermis's (D&J 2006 §3)."""
    return 0.5 * epidermis_scattering(wavelength_nm)
