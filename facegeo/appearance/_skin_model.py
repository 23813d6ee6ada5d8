"""Model pieces of the paper's skin reflectance model (Debevec et al. 2000, §4.1–4.2).

Private module behind :mod:`facegeo.appearance.skin`: the light set, the model parameters, the
diffuse chromaticity ramp (Eq. 6–7), the Torrance–Sparrow specular sample (Eq. 8), the forward
"paper mode" and the colour-space separation of §4.2.

Reflectance functions are ``(N, L, 3)`` float32: N functions (texels or pixels), L lights,
linear RGB radiance of one OLAT frame, ``R_l = f_r(l, v) · max(0, n·l) · E_l`` (docs/conventions.md).
Inside the analysis every function is first divided by the per-light intensity ``E_l`` ("white
balanced"), so the light chromaticity ``s`` of Eq. 6 is the unit grey vector ``(1, 1, 1)/√3``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facegeo.appearance.brdf import (
    beckmann_distribution,
    fresnel_dielectric,
    torrance_sparrow_geometry,
)
from facegeo.checks import as_array, check_unit_vectors, fmt_value
from facegeo.errors import InputError, ShapeError
from facegeo.frames import light_directions, light_solid_angles

#: Unit light chromaticity s of Eq. 6 after white balancing by the light intensities.
S_WHITE = np.full(3, 1.0 / np.sqrt(3.0))

#: |d × s|² below which the separation matrix [d, s, d × s] counts as singular (d ∥ s): the
#: diffuse chromaticity is within ≈ 0.57° of the light's (sin² of the angle).
SINGULAR_SIN2 = 1e-4

#: Floor on cosines in the denominators of Eq. 8–9 (same role as brdf.COS_FLOOR).
COS_FLOOR = 1e-4

_TINY = 1e-30


def _dot(a, b):
    return np.einsum("...i,...i->...", a, b)


def normalize(x: np.ndarray, *, fallback: np.ndarray | None = None) -> np.ndarray:
    """Unit vectors along the last axis; zero vectors become ``fallback`` (default: +Z)."""
    x = np.asarray(x, dtype=np.float64)
    nrm = np.sqrt(_dot(x, x))[..., None]
    fb = np.array([0.0, 0.0, 1.0]) if fallback is None else np.asarray(fallback, np.float64)
    ok = nrm > _TINY
    return np.where(ok, x / np.where(ok, nrm, 1.0), fb)


# --------------------------------------------------------------------------- light set


@dataclass(frozen=True)
class LightSet:
    """The lights a set of reflectance functions was measured under.

    Attributes
    ----------
    directions : (L, 3) float64, unit, same frame as normals and views
        Toward each light.
    solid_angles : (L,) float64, steradians
        Quadrature weight δA_l of each light (Eq. 4 of Debevec et al. 2000 on the grid).
    intensities : (L, 3) float64, linear RGB, > 0
        Irradiance each light delivers at normal incidence (E_l).
    grid : (int, int) or None
        ``(n_theta, n_phi)`` when the lights are the light-stage grid of docs/conventions.md
        (then resynthesis interpolates bilinearly on the grid); None for a free list.
    """

    directions: np.ndarray
    solid_angles: np.ndarray
    intensities: np.ndarray
    grid: tuple[int, int] | None = None

    @classmethod
    def from_grid(cls, n_theta: int, n_phi: int, color=(1.0, 1.0, 1.0)) -> LightSet:
        """The light-stage grid (``facegeo.frames.light_directions``) with δA and one colour."""
        dirs = light_directions(n_theta, n_phi)
        col = as_array(color, "color", shape=(3,))
        if np.any(col <= 0):
            raise InputError(f"color: light colour must be > 0 in every channel, got {col}")
        return cls(dirs, light_solid_angles(n_theta, n_phi),
                   np.broadcast_to(col, dirs.shape).copy(), (int(n_theta), int(n_phi)))

    @classmethod
    def from_directions(cls, directions, solid_angles=None, intensities=None) -> LightSet:
        """A free list of lights (real rigs, photometric-stereo domes).

        Parameters
        ----------
        directions : (L, 3) array_like, unit vectors toward the lights
        solid_angles : (L,) array_like, steradians, optional
            δA_l; default ``4π/L`` each (uniform weights).
        intensities : (L,) or (L, 3) array_like, optional
            Per-light irradiance (grey or RGB); default 1.
        """
        dirs = check_unit_vectors(as_array(directions, "directions", shape=(None, 3)),
                                  "directions", tol=1e-6)
        L = dirs.shape[0]
        if L < 3:
            raise InputError(f"directions: need at least 3 lights, got {L}")
        if solid_angles is None:
            sa = np.full(L, 4.0 * np.pi / L)
        else:
            sa = as_array(solid_angles, "solid_angles", shape=(L,))
            if np.any(sa <= 0):
                raise InputError("solid_angles: every δA must be > 0")
        if intensities is None:
            e = np.ones((L, 3))
        else:
            e = as_array(intensities, "intensities")
            if e.shape == (L,):
                e = np.repeat(e[:, None], 3, axis=1)
            if e.shape != (L, 3):
                raise ShapeError(f"intensities: expected shape ({L},) or ({L}, 3), got {e.shape}")
            if np.any(e <= 0):
                raise InputError("intensities: every light intensity must be > 0")
        return cls(dirs, sa, e, None)

    def subset(self, index) -> LightSet:
        """The lights ``index`` (an index or bool array) as a free list (``grid`` None)."""
        return LightSet(self.directions[index], self.solid_angles[index],
                        self.intensities[index], None)

    @property
    def n_lights(self) -> int:
        return int(self.directions.shape[0])


# --------------------------------------------------------------------------- parameters


@dataclass
class SkinParams:
    """Parameters of the paper's skin model for N surface points.

    Attributes
    ----------
    rho_d : (N, 3) float64, linear RGB
        Diffuse albedo ρ_d = a · d_0: its direction is the representative diffuse chromaticity
        d_0 of Eq. 6, its length the Lambertian albedo a (white-balanced units).
    alpha_0, alpha_1 : (N,) float64
        Chromaticity-ramp parameters of Eq. 7.
    rho_s : (N,) float64
        Specular energy: the integral ∫ ρ_s P(h) cos θ_h dω_h of the microfacet distribution of
        Eq. 8 (the forward model uses ρ_s times a unit-normalised Beckmann P).
    roughness : (N,) float64
        Beckmann RMS slope m of P (forward model only; the fit takes P from the data).
    eta : float
        Index of refraction for the Fresnel term F.
    """

    rho_d: np.ndarray
    alpha_0: np.ndarray
    alpha_1: np.ndarray
    rho_s: np.ndarray
    roughness: np.ndarray
    eta: float = 1.4

    def checked(self, n: int) -> SkinParams:
        rho_d = as_array(self.rho_d, "params.rho_d", shape=(n, 3))
        if np.any(rho_d < 0):
            raise InputError("params.rho_d: albedo must be >= 0")
        a0 = np.broadcast_to(as_array(self.alpha_0, "params.alpha_0"), (n,))
        a1 = np.broadcast_to(as_array(self.alpha_1, "params.alpha_1"), (n,))
        rs = np.broadcast_to(as_array(self.rho_s, "params.rho_s"), (n,))
        m = np.broadcast_to(as_array(self.roughness, "params.roughness"), (n,))
        if np.any(rs < 0):
            raise InputError("params.rho_s: must be >= 0")
        if np.any(m <= 0):
            raise InputError("params.roughness: Beckmann m must be > 0")
        eta = float(self.eta)
        if not (np.isfinite(eta) and eta > 1.0):
            raise InputError(f"params.eta: expected an index of refraction > 1, got {fmt_value(self.eta)}")
        return SkinParams(rho_d, a0, a1, rs, m, eta)


# --------------------------------------------------------------------------- Eq. 6–7


def ramp_f(cos_i, cos_r, alpha_0, alpha_1) -> np.ndarray:
    """The chromaticity-ramp weight f(θ_i, θ_r) of Eq. 7 (Debevec et al. 2000).

    ``f = α_0 (cos θ_i cos θ_r) + α_1 (1 − cos θ_i cos θ_r)``; cosines are clipped to [0, 1].
    All arguments broadcast; returns float64.
    """
    x = np.clip(cos_i, 0.0, 1.0) * np.clip(cos_r, 0.0, 1.0)
    return alpha_0 * x + alpha_1 * (1.0 - x)


def ramp_f_from_x(x, alpha_0, alpha_1) -> np.ndarray:
    """Eq. 7 from the clipped product ``x = cos θ_i cos θ_r`` ∈ [0, 1]: ``α_1 + (α_0 − α_1) x``.

    The same f as :func:`ramp_f` (up to rounding), for callers that evaluate many (α_0, α_1)
    at one geometry and precompute x once.
    """
    f = (alpha_0 - alpha_1) * x
    f += alpha_1
    return f


def ramp_chromaticity(d_0, f, s=S_WHITE) -> np.ndarray:
    """Diffuse chromaticity of Eq. 6: ``normalize(d_0 + f (d_0 − s))``.

    Parameters
    ----------
    d_0 : (..., 3) float64, unit RGB
        Representative diffuse chromaticity.
    f : (...) float64
        Ramp weight from :func:`ramp_f`; broadcasts with ``d_0[..., 0]``.
    s : (3,) float64, unit RGB
        Light chromaticity (grey after white balancing).

    Returns
    -------
    (..., 3) float64, unit vectors. Where ``d_0 + f (d_0 − s)`` vanishes (only for
    ``f = −1/(1 − d_0·s)``-like extremes) the result falls back to ``s``: finite, never NaN.
    """
    d_0 = np.asarray(d_0, np.float64)
    f = np.asarray(f, np.float64)[..., None]
    return normalize(d_0 + f * (d_0 - s), fallback=s)


def invert_ramp(c, f, s=S_WHITE):
    """The d_0 that Eq. 6 maps to chromaticity ``c`` under ramp weight ``f`` (inverse of Eq. 6).

    Solves ``normalize((1 + f) d − f s) = c`` for a unit d: with ``(1 + f) d − f s = μ c``,
    ``|d| = 1`` gives ``μ² + 2 f (c·s) μ − (1 + 2 f) = 0``; the positive root is used.

    Returns
    -------
    d : (..., 3) float64, unit
    ok : (...) bool
        False where no unit d exists (discriminant < 0 or 1 + f ≈ 0); there ``d = c``.
    """
    c = np.asarray(c, np.float64)
    f = np.asarray(f, np.float64)
    cs = _dot(c, s)
    disc = f * f * cs * cs + 1.0 + 2.0 * f
    ok = (disc >= 0.0) & (np.abs(1.0 + f) > 1e-6)
    mu = -f * cs + np.sqrt(np.maximum(disc, 0.0))
    den = np.where(ok, 1.0 + f, 1.0)
    d = (mu[..., None] * c + f[..., None] * s) / den[..., None]
    d = normalize(d, fallback=s)
    return np.where(ok[..., None], d, c), ok


# --------------------------------------------------------------------------- Eq. 8


def specular_sample(n, v, l, rho_s, roughness, eta) -> np.ndarray:
    """One light's specular sample ``L_v = ρ_s P F G / (4 n·v)`` (Eq. 8 for a small source).

    Eq. 8 with the integrand constant over the light's solid angle and the light's irradiance
    at normal incidence ``L Ω = 1`` (white balanced): the sample is the specular BRDF times
    cos θ_i, ``ρ_s F(v·h) P(n·h) G / (4 n·v)``, with P a unit-normalised Beckmann distribution
    of RMS slope ``roughness`` (the forward model needs a concrete P; the fit does not).

    Parameters
    ----------
    n, v : (N, 1, 3) or broadcastable float64, unit
    l : (1, L, 3) or broadcastable float64, unit
    rho_s, roughness : (N, 1) broadcastable float64
    eta : float

    Returns
    -------
    (N, L) float64, zero where ``n·l <= 0`` or ``n·v <= 0``; finite at ``l = −v``.
    """
    nl = _dot(n, l)
    nv = _dot(n, v)
    hv = l + v
    hn = np.sqrt(_dot(hv, hv))
    h = hv / np.maximum(hn, _TINY)[..., None]
    nh = _dot(n, h)
    vh = _dot(v, h)
    G = torrance_sparrow_geometry(nl, nv, nh, vh)
    F = fresnel_dielectric(vh, eta)
    P = beckmann_distribution(nh, roughness)
    ok = (nl > 0) & (nv > 0) & (hn > 1e-12)
    val = rho_s * F * P * G / (4.0 * np.maximum(nv, COS_FLOOR))
    return np.where(ok, val, 0.0)


def paper_reflectance(n, v, lights: LightSet, params: SkinParams) -> np.ndarray:
    """The paper's skin model evaluated exactly: reflectance functions ``(N, L, 3)`` float32.

    Implements Debevec et al. 2000 §4.1 as a forward model ("paper mode"), per light l::

        R_l = E_l ⊙ [ (a/π) max(0, n·l) · normalize(d_0 + f (d_0 − s))      Eq. 6–7
                      + ρ_s F G P / (4 n·v) · (1, 1, 1) ]                     Eq. 8

    with ``a = |ρ_d|``, ``d_0 = ρ_d/|ρ_d|``, f of Eq. 7 at ``cos θ_i = n·l``, ``cos θ_r = n·v``,
    s the grey light chromaticity (the functions are in units of each light's intensity E_l),
    and P a unit-normalised Beckmann lobe (the paper takes P from data; a forward model needs
    one). Diffuse brightness is exactly Lambertian; only its chromaticity moves with angle.

    Parameters
    ----------
    n : (N, 3) float64, unit, the light set's frame
    v : (N, 3) or (3,) float64, unit, toward the viewer
    lights : LightSet
    params : SkinParams

    Returns
    -------
    (N, L, 3) float32, linear RGB radiance per OLAT frame. Zero when ``n·v <= 0``.
    """
    n = check_unit_vectors(as_array(n, "n", shape=(None, 3)), "n")
    N = n.shape[0]
    v = check_unit_vectors(np.broadcast_to(as_array(v, "v"), (N, 3)), "v")
    p = params.checked(N)
    l = lights.directions
    a = np.linalg.norm(p.rho_d, axis=1)
    d_0 = normalize(p.rho_d, fallback=S_WHITE)
    nl = n @ l.T  # (N, L)
    nv = np.einsum("ni,ni->n", n, v)
    f = ramp_f(nl, nv[:, None], p.alpha_0[:, None], p.alpha_1[:, None])
    c = ramp_chromaticity(d_0[:, None, :], f)
    lit = (nv[:, None] > 0) & (nl > 0)
    diffuse = np.where(lit, a[:, None] / np.pi * nl, 0.0)[..., None] * c
    spec = specular_sample(n[:, None, :], v[:, None, :], l[None], p.rho_s[:, None],
                           p.roughness[:, None], p.eta)
    R = (diffuse + spec[..., None]) * lights.intensities[None]
    return R.astype(np.float32)


# --------------------------------------------------------------------------- §4.2 separation


def separate_colour(R, d, s=S_WHITE):
    """Colour-space separation of §4.2: ``R = μ_d d + μ_s s + μ_e e`` with ``e = d × s``.

    Inverts the 3 × 3 matrix ``[d, s, e]`` in closed form (Cramer's rule with cross products;
    ``det = |d × s|²``), then ``S = max(μ_s, 0) s`` and ``D = R − S`` so that D + S = R exactly
    (Debevec et al. 2000, §4.2).

    Parameters
    ----------
    R : (..., 3) float, white-balanced RGB
    d : (..., 3) float64, unit diffuse chromaticity; broadcasts with R
    s : (3,) float64, unit light chromaticity

    Returns
    -------
    D, S : (..., 3) float64
        Diffuse and specular parts, D + S = R.
    mu_d, mu_s, mu_e : (...) float64
    singular : (...) bool
        ``|d × s|² < SINGULAR_SIN2`` (diffuse colour ≈ light colour): the matrix is singular;
        there the separation falls back to diffuse only (S = 0, D = R, μ_d = R·d).
    """
    R = np.asarray(R, np.float64)
    d = np.asarray(d, np.float64)
    ds = _dot(d, s)
    det = 1.0 - ds * ds  # |d × s|² for unit d, s
    singular = det < SINGULAR_SIN2
    inv = 1.0 / np.where(singular, 1.0, det)
    Rd = _dot(R, d)
    Rs = _dot(R, s)
    # s × (d × s) = d − s (s·d);  (d × s) × d = s − d (d·s)
    mu_d = np.where(singular, Rd, (Rd - Rs * ds) * inv)
    mu_s = np.where(singular, 0.0, (Rs - Rd * ds) * inv)
    e = np.cross(d, np.broadcast_to(s, d.shape))
    mu_e = np.where(singular, 0.0, _dot(R, e) * inv)
    S = np.maximum(mu_s, 0.0)[..., None] * s
    D = R - S
    return D, S, mu_d, mu_s, mu_e, singular
