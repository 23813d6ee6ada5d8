"""Spectral skin: Donner & Jensen's four-parameter model of skin reflectance, forward and inverse.

Forward: melanin fraction C_m, melanin blend β_m (eumelanin share) and blood fraction C_h give
the absorption and scattering of a thin epidermis over a semi-infinite dermis (D&J 2006
Eqs. 3–8), whose total diffuse reflectance comes from the multipole and dipole diffusion
models (D&J 2005), scaled by the light that crosses the rough, oily surface (Eqs. 1–2), and
integrated against D65 and the CIE 1931 2° observer into linear-sRGB albedo.

Inverse: per texel, (C_m, β_m, C_h) from a linear-RGB albedo (lookup table + vectorised
Levenberg–Marquardt, with gamut and identifiability flags), per spectrum from measured
reflectance; parameter maps on disk; edits (more blood, less melanin) that give a new albedo
for relighting.

Generator: smooth regional parameter maps over a head and the albedo function the synthetic
skin field plugs in.

>>> from facegeo.appearance import spectral
>>> rgb = spectral.skin_rgb(0.03, 0.05, 0.008)              # doctest: +SKIP
>>> fit = spectral.fit_albedo(albedo_map)                      # doctest: +SKIP
>>> flushed = spectral.edit(fit, C_h=lambda c: 1.5 * c)        # doctest: +SKIP

See ``docs/spectral.md`` for the equations, constants, deviations and measured figures.

References
----------
Donner, C., Jensen, H. W. (2006). A Spectral BSSRDF for Shading Human Skin. EGSR 2006.
Donner, C., Jensen, H. W. (2005). Light Diffusion in Multi-Layered Translucent Materials.
SIGGRAPH 2005.
Jensen, H. W., Marschner, S. R., Levoy, M., Hanrahan, P. (2001). A Practical Model for
Subsurface Light Transport. SIGGRAPH 2001.
"""

from facegeo.appearance.spectral._absorption import (
    EUMELANIN_COEFFICIENTS,
    GAMMA_OXY,
    HB_CONCENTRATION_G_PER_L,
    HB_MOLAR_MASS_G_PER_MOL,
    WAVELENGTH_RANGE_NM,
    baseline_absorption,
    dermis_absorption,
    dermis_scattering,
    epidermis_absorption,
    epidermis_scattering,
    eumelanin_absorption,
    haemoglobin_absorption,
    pheomelanin_absorption,
)
from facegeo.appearance.spectral._colour import rgb_weights, spectrum_to_rgb, spectrum_to_xyz
from facegeo.appearance.spectral._diffusion import (
    boundary_coefficient,
    dipole_profile,
    dipole_total_reflectance,
    fresnel_diffuse_reflectance,
    multipole_profiles,
    multipole_totals,
    two_layer_total_reflectance,
)
from facegeo.appearance.spectral._generator import (
    PARAMETER_REGIONS,
    SKIN_TYPES,
    regional_parameter_maps,
    spectral_albedo_fn,
)
from facegeo.appearance.spectral._inverse import (
    FLAG_AT_BOUND,
    FLAG_BETA_M_UNIDENTIFIABLE,
    FLAG_C_H_UNIDENTIFIABLE,
    FLAG_C_M_UNIDENTIFIABLE,
    FLAG_DARK,
    FLAG_OUT_OF_GAMUT,
    FLAG_SKIPPED_STEPS,
    AlbedoFit,
    SpectrumFit,
    edit,
    edit_parameters,
    fit_albedo,
    fit_spectra,
)
from facegeo.appearance.spectral._lut import SkinLUT, default_cache_dir, skin_lut
from facegeo.appearance.spectral._maps import PNG_SCALES, load_parameter_maps, save_parameter_maps
from facegeo.appearance.spectral._model import (
    BECKMANN_M,
    DEFAULT_WAVELENGTHS_NM,
    EPIDERMIS_THICKNESS_MM,
    ETA_SKIN,
    PARAMETER_RANGES,
    SkinParameters,
    rho_dr,
    skin_rgb,
    skin_spectrum,
    subsurface_transmission,
    surface_brdf,
)

__all__ = [
    # constants
    "BECKMANN_M",
    "DEFAULT_WAVELENGTHS_NM",
    "EPIDERMIS_THICKNESS_MM",
    "ETA_SKIN",
    "EUMELANIN_COEFFICIENTS",
    "GAMMA_OXY",
    "HB_CONCENTRATION_G_PER_L",
    "HB_MOLAR_MASS_G_PER_MOL",
    "PARAMETER_RANGES",
    "PARAMETER_REGIONS",
    "PNG_SCALES",
    "SKIN_TYPES",
    "WAVELENGTH_RANGE_NM",
    "FLAG_AT_BOUND",
    "FLAG_BETA_M_UNIDENTIFIABLE",
    "FLAG_C_H_UNIDENTIFIABLE",
    "FLAG_C_M_UNIDENTIFIABLE",
    "FLAG_DARK",
    "FLAG_OUT_OF_GAMUT",
    "FLAG_SKIPPED_STEPS",
    # absorption and scattering (D&J 2006 Eqs. 3-8)
    "eumelanin_absorption",
    "pheomelanin_absorption",
    "baseline_absorption",
    "haemoglobin_absorption",
    "epidermis_absorption",
    "dermis_absorption",
    "epidermis_scattering",
    "dermis_scattering",
    # diffusion
    "fresnel_diffuse_reflectance",
    "boundary_coefficient",
    "dipole_profile",
    "dipole_total_reflectance",
    "multipole_profiles",
    "multipole_totals",
    "two_layer_total_reflectance",
    # colour
    "rgb_weights",
    "spectrum_to_rgb",
    "spectrum_to_xyz",
    # forward model and surface term
    "SkinParameters",
    "rho_dr",
    "subsurface_transmission",
    "surface_brdf",
    "skin_spectrum",
    "skin_rgb",
    # lookup table
    "SkinLUT",
    "skin_lut",
    "default_cache_dir",
    # inverse and edits
    "AlbedoFit",
    "SpectrumFit",
    "fit_albedo",
    "fit_spectra",
    "edit",
    "edit_parameters",
    "save_parameter_maps",
    "load_parameter_maps",
    # generator
    "regional_parameter_maps",
    "spectral_albedo_fn",
]
