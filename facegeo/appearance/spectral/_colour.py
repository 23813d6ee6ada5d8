"""Reflectance spectra to linear-sRGB albedo: CIE 1931 2° observer, CIE D65, IEC 61966-2-1.

``rgb = M_XYZ→sRGB · ∫ R(λ) S_D65(λ) x̄ȳz̄(λ) dλ / ∫ S_D65(λ) ȳ(λ) dλ``, then divided channel-wise
by the same expression for R ≡ 1, so a perfect white reflector maps to exactly (1, 1, 1) (the
sRGB white point is D65; the division only removes the ~1e-3 residue of table rounding).

The spectrum is treated as piecewise linear between its samples (constant beyond the ends),
and the integral is taken on the CIE tables' 1 nm grid, so the weights are exact for any
sample grid, uniform or not. The colour matching functions, D65 and the XYZ → linear-sRGB
matrix all come from colour-science (imported on first use; it takes ~0.7 s): only the
integration weights are computed here, because colour-science's ``sd_to_XYZ`` integrates one
spectrum at a time and interpolates non-1 nm data with Sprague / cubic splines, whereas these
weights are one (3, L) matrix product for any number of spectra and treat the spectrum as piecewise
linear. ``tests/test_library_equivalence.py`` checks them against ``colour.sd_to_XYZ`` +
``colour.XYZ_to_RGB`` on 1 nm data.

References
----------
CIE 015:2004 Colorimetry, 3rd ed. (1931 2° observer, D65).
IEC 61966-2-1:1999 (sRGB primaries and the XYZ → linear sRGB matrix).
Donner & Jensen 2006, §5: spectra computed at 400–700 nm, converted with "the standard CIE 2°
color matching functions, with the D65 illuminant".
"""

from __future__ import annotations

import functools
import warnings

import numpy as np

from facegeo.errors import MissingDependencyError
from facegeo.checks import fmt_value

__all__ = ["XYZ_TO_LINEAR_SRGB", "rgb_weights", "spectrum_to_rgb", "spectrum_to_xyz"]

def _colour_module():
    """colour-science, imported without changing the caller's process: its import sets
    ``np.set_printoptions(legacy="1.13")`` for everyone (a user's printed arrays and doctests
    changed after their first spectral call), so numpy's print options are put back."""
    options = np.get_printoptions()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # colour-science warns that matplotlib is absent
            import colour
    except ImportError as exc:  # pragma: no cover - a declared dependency
        raise MissingDependencyError(
            "facegeo.appearance.spectral needs colour-science for the CIE tables: pip install colour-science"
        ) from exc
    finally:
        np.set_printoptions(**options)
    return colour


@functools.lru_cache(maxsize=1)
def _xyz_to_linear_srgb() -> np.ndarray:
    """IEC 61966-2-1 XYZ (D65, Y = 1) → linear sRGB, from colour-science's sRGB colourspace."""
    m = np.array(_colour_module().models.RGB_COLOURSPACE_sRGB.matrix_XYZ_to_RGB, dtype=np.float64)
    m.setflags(write=False)
    return m


def __getattr__(name: str):
    # XYZ_TO_LINEAR_SRGB stays a module attribute without importing colour-science at import.
    if name == "XYZ_TO_LINEAR_SRGB":
        return _xyz_to_linear_srgb()
    raise AttributeError(f"module {fmt_value(__name__)} has no attribute {fmt_value(name)}")


@functools.lru_cache(maxsize=1)
def _cie_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(λ (nm, 1 nm steps), x̄ȳz̄ (N, 3), D65 (N,)) on 360–830 nm."""
    colour = _colour_module()
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    wl = np.asarray(cmfs.wavelengths, dtype=np.float64)
    xyz = np.asarray(cmfs.values, dtype=np.float64)
    d65 = colour.SDS_ILLUMINANTS["D65"]
    s = np.interp(wl, np.asarray(d65.wavelengths, float), np.asarray(d65.values, float))
    return wl, xyz, s


@functools.lru_cache(maxsize=32)
def _weights_cached(wavelengths: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    grid = np.asarray(wavelengths, dtype=np.float64)
    wl, xyz, s = _cie_tables()
    # hat[j, k]: weight of sample k in the piecewise-linear spectrum at fine wavelength j.
    hat = np.empty((wl.size, grid.size))
    eye = np.eye(grid.size)
    for k in range(grid.size):
        hat[:, k] = np.interp(wl, grid, eye[k])
    k_norm = 1.0 / np.sum(s * xyz[:, 1])
    w_xyz = (xyz * s[:, None]).T @ hat * k_norm  # (3, L), 1 nm steps (Δλ cancels)
    w_rgb = _xyz_to_linear_srgb() @ w_xyz
    w_rgb /= w_rgb.sum(axis=1, keepdims=True)  # R ≡ 1 → (1, 1, 1) exactly
    w_xyz.setflags(write=False)
    w_rgb.setflags(write=False)
    return w_xyz, w_rgb


def rgb_weights(wavelengths) -> tuple[np.ndarray, np.ndarray]:
    """Weights turning a sampled reflectance spectrum into XYZ and linear sRGB.

    Parameters
    ----------
    wavelengths : (L,) float, nm, strictly increasing

    Returns
    -------
    w_xyz : (3, L) float64
        ``XYZ = w_xyz @ R`` (Y of the perfect white reflector = 1, D65).
    w_rgb : (3, L) float64
        ``rgb = w_rgb @ R``, linear sRGB, each row summing to 1.
    """
    wl = np.asarray(wavelengths, dtype=np.float64).ravel()
    return _weights_cached(tuple(float(x) for x in wl))


def spectrum_to_xyz(reflectance, wavelengths) -> np.ndarray:
    """CIE XYZ (D65, 2°, Y_white = 1) of reflectance spectra ``(..., L)`` → ``(..., 3)``."""
    w_xyz, _ = rgb_weights(wavelengths)
    return np.asarray(reflectance, dtype=np.float64) @ w_xyz.T


def spectrum_to_rgb(reflectance, wavelengths) -> np.ndarray:
    """Linear-sRGB albedo of reflectance spectra ``(..., L)`` → ``(..., 3)`` float64.

    A perfect white reflector (R ≡ 1) maps to (1, 1, 1); values are not clipped.
    """
    _, w_rgb = rgb_weights(wavelengths)
    return np.asarray(reflectance, dtype=np.float64) @ w_rgb.T
