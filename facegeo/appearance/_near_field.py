"""Near-field light stages: the skin model's analysis and resynthesis with each light where it is.

Private module behind :mod:`facegeo.appearance.skin`. The paper's analysis (§4.2) and Eq. 9
(§4.3) take every light as distant: one direction ω_l per light for every point of the face.
A light stage of radius r seen from a point p off its centre c sees light l from

    ω_l(p) = (r ω_l − δ) / |r ω_l − δ|,   δ = p − c,

with the irradiance falloff a_l(p) = (r / |r ω_l − δ|)² (the light delivers its intensity at
the centre). On the generator's small preset (r = 1.5 m, the head ≈ 0.1 m about the centre)
the directions move by up to ≈ 4° and the falloff by ±14 % across the lights: treating the
lights as distant cost the fit stage its normals (1.34° median against 0.08° with distant
lights), its albedo and most of Eq. 9's gain (resynthesis at 30° 0.86× the naive baseline's
pooled error on exact generator functions, 5.0× with distant lights; docs/skin.md).

What this module does (a deviation from the paper, which does not model it; exact where the
model's assumptions hold):

* :func:`distant_equivalent` — each reflectance function divided by its falloff and resampled
  at the stage's own directions ω_l as seen from p: the value at ω_l is read where the ray
  from p along ω_l meets the light sphere (bilinear on the grid, barycentric on a free list's
  spherical triangulation: :func:`facegeo.appearance._skin_resynth.interpolate_on_lights`).
  The fit runs on it
  unchanged (the paper's distant-light analysis, §4.2).
* :func:`separate_measured` — the final separation of §4.2 (Eq. 6 per sample, then the
  colour-space separation) applied to the *measured* samples with their true directions ω_l(p),
  so that D + S = R holds for the measured function and Eq. 9 reads measured samples.
* :meth:`NearField.light_geometry`, :meth:`NearField.stage_directions` — what Eq. 9 needs
  (:func:`facegeo.appearance._skin_resynth.resynthesize_specular`): the true directions and
  falloffs of the target lights, and the stage direction of each source direction l_q, so the
  measured sample is read where it was measured.

References
----------
.. [1] P. Debevec et al., "Acquiring the Reflectance Field of a Human Face", SIGGRAPH 2000,
   §4.2–4.3, Eq. 6 and 9.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from facegeo.appearance._skin_model import (
    S_WHITE,
    LightSet,
    normalize,
    ramp_chromaticity,
    ramp_f,
    separate_colour,
)
from facegeo.checks import as_array, fmt_value
from facegeo.errors import InputError

#: Functions per block of the numpy steps (bounds their (block, L, 3) float64 temporaries).
BLOCK = 256
#: Run :func:`distant_equivalent` (on a grid) and :func:`separate_measured` in the compiled
#: kernels of ``_near_field_kernels`` (same formulas, tested against the numpy path below).
KERNELS = True


@dataclass(frozen=True)
class NearField:
    """Where each reflectance function's point sits in a near-field light stage.

    Attributes
    ----------
    offsets : (N, 3) float64, metres, the light set's frame
        δ = p − c: each function's surface point relative to the stage centre.
    radius : float, metres
        The stage radius r (> |δ| for every point).
    """

    offsets: np.ndarray
    radius: float

    def __post_init__(self):
        d = as_array(self.offsets, "offsets", shape=(None, 3), finite=True)
        r = float(self.radius)
        if not (math.isfinite(r) and r > 0):
            raise InputError(f"radius: expected a finite stage radius > 0 (metres), got "
                             f"{fmt_value(self.radius)}")
        reach = float(np.linalg.norm(d, axis=1).max()) if len(d) else 0.0
        if not np.isfinite(d).all() or reach >= r:
            raise InputError(f"offsets: every point must lie inside the light sphere of radius "
                             f"{r:g} m; the farthest is {reach:g} m from its centre")
        object.__setattr__(self, "offsets", np.ascontiguousarray(d, np.float64))
        object.__setattr__(self, "radius", r)

    def take(self, idx) -> NearField:
        """The near field of the functions ``idx``."""
        return NearField(self.offsets[idx], self.radius)

    def light_geometry(self, directions):
        """:func:`light_geometry` of every function: ``(dirs (N, L, 3), falloff (N, L))``."""
        return light_geometry(self.offsets, directions, self.radius)

    def stage_directions(self, u):
        """:func:`stage_directions` of every function along ``u`` ``(N, M, 3)``."""
        return stage_directions(self.offsets, u, self.radius)


def light_geometry(offsets, directions, radius):
    """True light directions and falloffs seen from points off the stage centre.

    Parameters
    ----------
    offsets : (n, 3) float64 — δ = p − c
    directions : (L, 3) float64, unit — the stage's ω_l
    radius : float — r

    Returns
    -------
    dirs : (n, L, 3) float64, unit — ω_l(p) = (r ω_l − δ)/|r ω_l − δ|
    falloff : (n, L) float64 — a_l(p) = (r / |r ω_l − δ|)²
    """
    x = float(radius) * directions[None] - offsets[:, None, :]
    d = np.linalg.norm(x, axis=2)
    return x / d[..., None], (float(radius) / d) ** 2


def stage_directions(offsets, u, radius):
    """Stage directions of the light-sphere points that points ``offsets`` see along ``u``.

    The ray p + t u (t > 0) meets the sphere |x − c| = r at t = −δ·u + √((δ·u)² − |δ|² + r²)
    (one positive root: p is inside); the result is (δ + t u)/r.

    Parameters
    ----------
    offsets : (n, 3) float64; u : (n, M, 3) float64, unit; radius : float

    Returns
    -------
    (n, M, 3) float64, unit
    """
    du = np.einsum("ni,nmi->nm", offsets, u)
    t = -du + np.sqrt(np.maximum(du * du - np.sum(offsets * offsets, 1)[:, None]
                                 + float(radius) ** 2, 0.0))
    return normalize(offsets[:, None, :] + t[..., None] * u)


def distant_equivalent(R, near: NearField, lights: LightSet, masked=None):
    """Reflectance functions as a distant-light stage would have measured them at the points.

    ``R̃_l = R(ω_l as seen from p) / a`` (module docstring), float32, with the masked samples
    (taken as 0) spreading to every resampled sample that reads them.

    Parameters
    ----------
    R : (N, L, C) float32, finite (masked samples 0)
    near : NearField of the N functions
    lights : LightSet — the stage's grid (bilinear) or a free list (barycentric)
    masked : (N, L) bool, optional

    Returns
    -------
    Rd : (N, L, C) float32; masked_d : (N, L) bool or None
    """
    from facegeo.appearance._skin_resynth import interpolate_on_lights

    N, L, C = R.shape
    out = np.empty((N, L, C), np.float32)
    mout = None if masked is None else np.zeros((N, L), bool)
    if KERNELS and lights.grid is not None:
        from facegeo.appearance._near_field_kernels import distant_equivalent_grid

        nt, npf = lights.grid
        distant_equivalent_grid(np.ascontiguousarray(R, np.float32),
                                np.zeros((0, 0), bool) if masked is None
                                else np.ascontiguousarray(masked, bool),
                                near.offsets, float(near.radius),
                                np.ascontiguousarray(lights.directions, np.float64), int(nt),
                                int(npf), out, np.zeros((0, 0), bool) if mout is None else mout)
        return out, mout
    for s in range(0, N, BLOCK):
        sl = slice(s, min(N, s + BLOCK))
        delta = near.offsets[sl]
        src = stage_directions(delta, np.broadcast_to(lights.directions[None],
                                                      (delta.shape[0], L, 3)), near.radius)
        _, a_src = light_geometry(delta, lights.directions, near.radius)
        parts = [R[sl].astype(np.float64) / a_src[..., None]]
        if masked is not None:
            parts.append(masked[sl, :, None].astype(np.float64))
        vals = interpolate_on_lights(np.concatenate(parts, axis=2), lights, src,
                                     free="barycentric")
        out[sl] = vals[..., :C]
        if masked is not None:
            mout[sl] = vals[..., C] > 0.0
    return out, mout


def separate_measured(R, fit, near: NearField, out, *, masked=None) -> None:
    """The final separation of §4.2 on the measured samples, written into ``out`` (D).

    Per sample the diffuse chromaticity of Eq. 6 with the fitted ramp (Eq. 7) at the light's
    true direction ω_l(p), then :func:`separate_colour` (S = max(μ_s, 0) s, D = R − S). Where
    the fit is not valid (black, shadowed) or single-channel, D = R; masked samples D = 0.

    Parameters
    ----------
    R : (N, L, C) float32, masked samples 0
    fit : SkinFit of the distant-equivalent functions (its normals, d_0, α's)
    near : NearField
    out : (N, L, C) float32 or float16, written
    masked : (N, L) bool, optional
    """
    N, L, C = R.shape
    E = fit.lights.intensities
    if KERNELS and C == 3 and not fit.single_channel:
        from facegeo.appearance._near_field_kernels import separate_measured_kernel
        from facegeo.appearance._skin_model import SINGULAR_SIN2

        c = np.ascontiguousarray
        dest = out if out.dtype == np.float32 else np.empty((N, L, C), np.float32)
        separate_measured_kernel(c(R, np.float32), c(E, np.float64), near.offsets,
                                 float(near.radius), c(fit.lights.directions, np.float64),
                                 c(fit.normal, np.float64), c(fit.view, np.float64),
                                 c(fit.d_0, np.float64), c(fit.alpha_0, np.float64),
                                 c(fit.alpha_1, np.float64), c(fit.valid, np.bool_),
                                 np.zeros((0, 0), bool) if masked is None else c(masked, bool),
                                 float(SINGULAR_SIN2), dest)
        if dest is not out:
            out[...] = dest
        return
    for s in range(0, N, BLOCK):
        sl = slice(s, min(N, s + BLOCK))
        Rs = R[sl].astype(np.float64)
        if C == 3 and not fit.single_channel:
            dirs, _ = light_geometry(near.offsets[sl], fit.lights.directions, near.radius)
            n = fit.normal[sl]
            f = ramp_f(np.einsum("ni,nli->nl", n, dirs),
                       np.einsum("ni,ni->n", n, fit.view[sl])[:, None],
                       fit.alpha_0[sl, None], fit.alpha_1[sl, None])
            d = ramp_chromaticity(fit.d_0[sl, None, :], f)
            D, *_ = separate_colour(Rs / E[None], d, S_WHITE)
            D *= E[None]
            D = np.where(fit.valid[sl, None, None], D, Rs)
        else:
            D = Rs
        if masked is not None:
            D[masked[sl]] = 0.0
        out[sl] = D
