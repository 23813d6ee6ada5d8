"""Diffusion theory for layered translucent media: the dipole and the multipole.

Lengths in **mm**, coefficients in **mm⁻¹**, radial profiles in **mm⁻²** (reflected power per
unit area per unit incident power). All functions broadcast over their coefficient arrays.

* The **dipole** (Jensen et al. 2001, §2.4–2.5) models a semi-infinite medium: a real source one
  reduced mean free path ℓ = 1/σ_t′ below the surface and a negative image source mirrored
  about the extrapolated boundary z = −z_b, z_b = 2AD, D = 1/(3σ_t′).
* The **multipole** (Donner & Jensen 2005, §3) models a slab of thickness d: the dipole is
  mirrored again about the extrapolated boundary below the slab, giving pairs
  ``z_r,i = 2i(d + z_b,0 + z_b,d) + ℓ`` and ``z_v,i = 2i(d + z_b,0 + z_b,d) − ℓ − 2z_b,0``,
  i = −n…n, whose fluxes through the top and bottom faces are the reflectance R(r) and the
  transmittance T(r).

Totals. Integrating one source's flux term over the plane gives a closed form,
``∫₀^∞ z (1 + σ_tr d) e^{−σ_tr d} / d³ · 2πr dr = 2π sign(z) e^{−σ_tr |z|}`` with
``d = √(r² + z²)``, so the dipole's total diffuse reflectance is
``R_d = (α′/2)(e^{−σ_tr ℓ} + e^{−σ_tr (ℓ + 4AD)})`` — Jensen et al.'s
``(α′/2)(1 + e^{−(4/3)A√(3(1−α′))}) e^{−√(3(1−α′))}`` — and the multipole's infinite sums are
geometric series beyond |i| = 2, summed exactly here (no truncation of the pair count).

References
----------
Jensen, H. W., Marschner, S. R., Levoy, M., Hanrahan, P. (2001). A Practical Model for
Subsurface Light Transport. SIGGRAPH 2001, §2.4 (dipole), §2.5 (total diffuse reflectance).
Donner, C., Jensen, H. W. (2005). Light Diffusion in Multi-Layered Translucent Materials.
ACM Trans. Graph. 24(3) (SIGGRAPH 2005), §3 (multipole), §4 (layer combination).
Egan, W. G., Hilgeman, T. W. (1979). Optical Properties of Inhomogeneous Materials
(the polynomial fit of the diffuse Fresnel reflectance F_dr).
"""

from __future__ import annotations

import numpy as np

from facegeo.errors import InputError
from facegeo.checks import fmt_value

__all__ = [
    "fresnel_diffuse_reflectance",
    "boundary_coefficient",
    "dipole_profile",
    "dipole_total_reflectance",
    "multipole_profiles",
    "multipole_totals",
    "two_layer_total_reflectance",
]

_K_EXPLICIT = 2  # pairs |i| <= K are summed term by term; the rest as geometric series


def fresnel_diffuse_reflectance(eta) -> np.ndarray:
    """Internal diffuse Fresnel reflectance F_dr(η) (Egan & Hilgeman polynomial).

    ``η`` is the relative index (medium / outside). For η ≥ 1:
    F_dr = −1.440/η² + 0.710/η + 0.668 + 0.0636 η; for η < 1:
    F_dr = −0.4399 + 0.7099/η − 0.3319/η² + 0.0636/η³ (Jensen et al. 2001, §2.4).
    """
    eta = np.asarray(eta, dtype=np.float64)
    hi = -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta
    lo = -0.4399 + 0.7099 / eta - 0.3319 / eta**2 + 0.0636 / eta**3
    return np.where(eta >= 1.0, hi, lo)


def boundary_coefficient(eta) -> np.ndarray:
    """A = (1 + F_dr)/(1 − F_dr), the internal-reflection boundary term (Jensen 2001, §2.4)."""
    f = fresnel_diffuse_reflectance(eta)
    return (1.0 + f) / (1.0 - f)


def _check_coefficients(sigma_a, sigma_s_prime) -> tuple[np.ndarray, np.ndarray]:
    sa = np.asarray(sigma_a, dtype=np.float64)
    ss = np.asarray(sigma_s_prime, dtype=np.float64)
    if not (np.all(np.isfinite(sa)) and np.all(np.isfinite(ss))):
        raise InputError("sigma_a, sigma_s_prime: non-finite absorption or scattering coefficient")
    if np.any(sa <= 0) or np.any(ss <= 0):
        raise InputError(
            "sigma_a, sigma_s_prime: diffusion needs sigma_a > 0 and sigma_s_prime > 0 (mm^-1); "
            f"got min sigma_a = {sa.min():.3g}, min sigma_s_prime = {ss.min():.3g}"
        )
    return sa, ss


def _optics(sigma_a, sigma_s_prime):
    sa, ss = _check_coefficients(sigma_a, sigma_s_prime)
    st = sa + ss  # reduced extinction σ_t′
    alpha = ss / st  # reduced albedo α′
    sigma_tr = np.sqrt(3.0 * sa * st)  # effective transport coefficient
    ell = 1.0 / st  # depth of the real source: one reduced mean free path
    D = 1.0 / (3.0 * st)  # diffusion constant
    return alpha, sigma_tr, ell, D


def _flux_profile(r, z, sigma_tr):
    """z (1 + σ_tr d) e^{−σ_tr d} / d³, d = √(r² + z²): one source's flux through a face."""
    d = np.sqrt(r * r + z * z)
    return z * (1.0 + sigma_tr * d) * np.exp(-sigma_tr * d) / d**3


def dipole_profile(r, sigma_a, sigma_s_prime, eta) -> np.ndarray:
    """Radial diffuse reflectance R_d(r) of a semi-infinite medium [mm⁻²] (Jensen 2001, §2.4).

    R_d(r) = α′/(4π) [z_r (1 + σ_tr d_r) e^{−σ_tr d_r}/d_r³ + z_v (1 + σ_tr d_v) e^{−σ_tr d_v}/d_v³]
    with z_r = ℓ = 1/σ_t′, z_v = ℓ + 4AD.

    Parameters
    ----------
    r : (...) float, mm
        Distance from the point of entry.
    sigma_a, sigma_s_prime : (...) float, mm⁻¹
        Absorption and reduced scattering; broadcast against ``r``.
    eta : float
        Relative index of refraction (medium / outside).

    Returns
    -------
    (...) float64, mm⁻²
    """
    alpha, sigma_tr, ell, D = _optics(sigma_a, sigma_s_prime)
    A = boundary_coefficient(eta)
    r = np.asarray(r, dtype=np.float64)
    z_r = ell
    z_v = ell + 4.0 * A * D
    return alpha / (4.0 * np.pi) * (
        _flux_profile(r, z_r, sigma_tr) + _flux_profile(r, z_v, sigma_tr)
    )


def dipole_total_reflectance(sigma_a, sigma_s_prime, eta) -> np.ndarray:
    """Total diffuse reflectance of a semi-infinite medium (Jensen 2001, §2.5, closed form).

    R_d = (α′/2)(1 + e^{−(4/3)A√(3(1−α′))}) e^{−√(3(1−α′))} = ∫ R_d(r) 2πr dr.

    Parameters
    ----------
    sigma_a, sigma_s_prime : (...) float, mm⁻¹
    eta : float or (...) float
        Relative index (medium / outside).

    Returns
    -------
    (...) float64, unitless
    """
    alpha, _, _, _ = _optics(sigma_a, sigma_s_prime)
    A = boundary_coefficient(eta)
    s = np.sqrt(3.0 * (1.0 - alpha))
    return 0.5 * alpha * (1.0 + np.exp(-4.0 / 3.0 * A * s)) * np.exp(-s)


def _multipole_geometry(sigma_a, sigma_s_prime, thickness, eta_top, eta_bottom):
    alpha, sigma_tr, ell, D = _optics(sigma_a, sigma_s_prime)
    d = np.asarray(thickness, dtype=np.float64)
    if np.any(~np.isfinite(d)) or np.any(d <= 0):
        raise InputError(f"thickness: expected a finite slab thickness > 0 mm, got {fmt_value(thickness)}")
    z_b0 = 2.0 * boundary_coefficient(eta_top) * D
    z_bd = 2.0 * boundary_coefficient(eta_bottom) * D
    L = d + z_b0 + z_bd  # half the period of the image-source lattice
    # Deviation: the real source sits at one reduced mean free path, which leaves the slab
    # when l > d (the sums then change sign and T goes negative). We keep it inside, at
    # min(l, d), which is continuous at l = d. For the skin epidermis (d = 0.25 mm) this only
    # acts above ~770 nm, where the colour matching functions are negligible.
    ell = np.minimum(ell, d * (1.0 - 1e-9))
    return alpha, sigma_tr, ell, d, z_b0, L


def multipole_profiles(
    r, sigma_a, sigma_s_prime, thickness, eta_top, eta_bottom, *, n_pairs: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Radial reflectance R(r) and transmittance T(r) of a slab [mm⁻²] (D&J 2005, §3).

    R(r) = α′/(4π) Σ_i [z_r,i F(r, z_r,i) − z_v,i F(r, z_v,i)],
    T(r) = α′/(4π) Σ_i [(d − z_r,i) F(r, d − z_r,i) − (d − z_v,i) F(r, d − z_v,i)],
    F(r, z) = (1 + σ_tr √(r²+z²)) e^{−σ_tr √(r²+z²)} / (r²+z²)^{3/2}, i = −n…n.

    Parameters
    ----------
    r : (...) float, mm
    sigma_a, sigma_s_prime : (...) float, mm⁻¹
    thickness : float, mm
    eta_top, eta_bottom : float
        Relative indices (slab / neighbour) at the lit face and at the far face.
    n_pairs : int, optional
        Pairs on each side of i = 0. Default: enough for the lattice terms to decay below
        e^−30 of the first (at most 2000).

    Returns
    -------
    R, T : (...) float64, mm⁻²
    """
    alpha, sigma_tr, ell, d, z_b0, L = _multipole_geometry(
        sigma_a, sigma_s_prime, thickness, eta_top, eta_bottom
    )
    r = np.asarray(r, dtype=np.float64)
    if n_pairs is None:
        decay = float(np.min(2.0 * sigma_tr * L))
        n_pairs = int(min(2000, np.ceil(30.0 / max(decay, 1e-6)) + 1))
    R = np.zeros(np.broadcast_shapes(r.shape, alpha.shape, L.shape))
    T = np.zeros_like(R)
    for i in range(-n_pairs, n_pairs + 1):
        z_r = 2.0 * i * L + ell
        z_v = 2.0 * i * L - ell - 2.0 * z_b0
        R += _flux_profile(r, z_r, sigma_tr) - _flux_profile(r, z_v, sigma_tr)
        T += _flux_profile(r, d - z_r, sigma_tr) - _flux_profile(r, d - z_v, sigma_tr)
    k = alpha / (4.0 * np.pi)
    return k * R, k * T


def _signed_decay(z, sigma_tr):
    """sign(z) e^{−σ_tr |z|}: the plane integral of one source's flux term, over 2π."""
    return np.sign(z) * np.exp(-sigma_tr * np.abs(z))


def multipole_totals(
    sigma_a, sigma_s_prime, thickness, eta_top, eta_bottom
) -> tuple[np.ndarray, np.ndarray]:
    """Total reflectance and transmittance of a slab (D&J 2005, §3, integrated in closed form).

    R = (α′/2) Σ_i [sign(z_r,i) e^{−σ_tr|z_r,i|} − sign(z_v,i) e^{−σ_tr|z_v,i|}],
    T = (α′/2) Σ_i [sign(d−z_r,i) e^{−σ_tr|d−z_r,i|} − sign(d−z_v,i) e^{−σ_tr|d−z_v,i|}],
    summed over all i ∈ ℤ: terms with |i| ≤ 2 explicitly, the rest as geometric series in
    q = e^{−2σ_tr L}, L = d + z_b,0 + z_b,d (for |i| > 2 every sign is fixed because
    2z_b,0 > ℓ whenever A > 3/4, which holds for every η ≥ 0.7).

    Parameters
    ----------
    sigma_a, sigma_s_prime : (...) float, mm⁻¹
    thickness : float or (...) float, mm
    eta_top, eta_bottom : float
        Relative indices at the lit face and at the far face.

    Returns
    -------
    R, T : (...) float64, unitless (fractions of the power entering at the lit face)
    """
    alpha, sigma_tr, ell, d, z_b0, L = _multipole_geometry(
        sigma_a, sigma_s_prime, thickness, eta_top, eta_bottom
    )
    if np.any(2.0 * _K_EXPLICIT * z_b0 <= ell):
        raise InputError(
            "eta_top: boundary term too small for the closed-form multipole sum "
            "(needs 4 z_b > l, i.e. A > 3/8); use multipole_profiles instead"
        )
    R = np.zeros(np.broadcast_shapes(alpha.shape, L.shape))
    T = np.zeros_like(R)
    for i in range(-_K_EXPLICIT, _K_EXPLICIT + 1):
        z_r = 2.0 * i * L + ell
        z_v = 2.0 * i * L - ell - 2.0 * z_b0
        R += _signed_decay(z_r, sigma_tr) - _signed_decay(z_v, sigma_tr)
        T += _signed_decay(d - z_r, sigma_tr) - _signed_decay(d - z_v, sigma_tr)
    # Tails |i| >= K+1: sum_{k>=K+1} e^{-σ(2kL + c)} = e^{-σ(2(K+1)L + c)} / (1 - e^{-2σL}).
    first = 2.0 * (_K_EXPLICIT + 1) * L
    inv = 1.0 / -np.expm1(-2.0 * sigma_tr * L)

    def tail(c):
        return np.exp(-sigma_tr * (first + c)) * inv

    # i >= K+1: z_r, z_v > 0;  i <= -(K+1): z_r, z_v < 0.
    R += tail(ell) - tail(-ell - 2.0 * z_b0)  # i > 0
    R += -tail(-ell) + tail(ell + 2.0 * z_b0)  # i < 0
    # i >= K+1: d - z_r, d - z_v < 0;  i <= -(K+1): d - z_r, d - z_v > 0.
    T += -tail(ell - d) + tail(-ell - 2.0 * z_b0 - d)  # i > 0
    T += tail(d - ell) - tail(d + ell + 2.0 * z_b0)  # i < 0
    return 0.5 * alpha * R, 0.5 * alpha * T


def two_layer_total_reflectance(
    sigma_a_top, sigma_s_prime_top, thickness_top, sigma_a_bottom, sigma_s_prime_bottom, eta
) -> np.ndarray:
    """Total diffuse reflectance of a thin slab over a semi-infinite layer (D&J 2005, §4).

    The slab (multipole) and the half-space (dipole, relative index 1 at the shared interface
    because both layers have index η) are combined by the adding relation, which is the
    zero-frequency term of D&J 2005's frequency-domain convolution of the R and T profiles::

        R = R₁↓ + T₁↓ R₂ T₁↑ / (1 − R₁↑ R₂)

    ↓ is the slab lit from above (relative index η above, 1 below), ↑ the slab lit from below
    (1 at the lit face, η at the far face). D&J 2005 use the downward R₁, T₁ for both
    directions; the upward pair is the same multipole with the boundaries swapped and costs
    one more closed-form sum.

    Parameters
    ----------
    sigma_a_top, sigma_s_prime_top : (...) float, mm⁻¹
    thickness_top : float, mm
    sigma_a_bottom, sigma_s_prime_bottom : (...) float, mm⁻¹
    eta : float
        Index of both layers relative to the outside.

    Returns
    -------
    (...) float64, fraction of the power entering the top face that leaves it again.
    """
    R1d, T1d = multipole_totals(sigma_a_top, sigma_s_prime_top, thickness_top, eta, 1.0)
    R1u, T1u = multipole_totals(sigma_a_top, sigma_s_prime_top, thickness_top, 1.0, eta)
    R2 = dipole_total_reflectance(sigma_a_bottom, sigma_s_prime_bottom, 1.0)
    return R1d + T1d * R2 * T1u / (1.0 - R1u * R2)
