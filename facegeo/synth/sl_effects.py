"""Skin effects on synthetic structured-light frames: subsurface blur and interreflection.

The generator's structured-light frames are the projector's direct light on the skin BRDF:
every stripe is as sharp as the camera's pixel. Real skin is not (Gupta et al. 2013, Sec. 3):

* **Subsurface scattering** carries light that enters at one point out at another, a few
  millimetres away — a *short-range* global term that blurs the projected pattern. Modelled as a
  convolution of the pattern-lit image with a radial kernel: a Gaussian whose σ is the skin's
  mean free path (:data:`SKIN_MEAN_FREE_PATH_MM`), or Jensen et al. 2001's dipole profile
  ``R_d(r)`` (:func:`facegeo.appearance.spectral.dipole_profile`, coefficients per colour channel,
  :data:`SKIN1_SIGMA_A` / :data:`SKIN1_SIGMA_S_PRIME`); both in camera pixels through the
  camera's footprint on the face (mm per pixel at the face's median depth). The kernel is
  normalised (unit sum): the render's albedo already holds the energy the skin reflects; the blur
  only moves it. ``subsurface_fraction`` of the light takes the blurred path, the rest (surface
  reflection) stays sharp. The convolution is normalised inside the head mask, so light does not
  leak onto the background.
* **Interreflection** (nose–cheek, eye sockets) adds a *long-range*, low-frequency global term:
  ``strength · G_σ * (mask · I)`` — a Gaussian of σ = ``ir_sigma_px`` (default an eighth of the
  head's extent) of the lit head — inside the mask. A pattern lighting half the face adds light to
  the other half, which can flip the coarse Gray bits of dark (low-albedo) skin.

Both act on the **direct, pattern-modulated** image (linear radiance); the ambient term and the
sensor noise are added after them by the generator. Image-space convolution is an approximation:
a surface kernel seen at a slant is foreshortened, which a constant image kernel ignores.

References
----------
Jensen, Marschner, Levoy, Hanrahan. A Practical Model for Subsurface Light Transport. SIGGRAPH
2001, Sec. 2.4 and Table 2 (skin1). — Gupta, Agrawal, Veeraraghavan, Narasimhan. A Practical
Approach to 3D Scanning in the Presence of Interreflections, Subsurface Scattering and Defocus.
IJCV 102, 2013.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from facegeo.checks import as_array, check_choice, fmt_value
from facegeo.errors import InputError, ShapeError

__all__ = [
    "SKIN1_SIGMA_A",
    "SKIN1_SIGMA_S_PRIME",
    "SKIN_MEAN_FREE_PATH_MM",
    "SkinEffects",
    "apply_effects",
    "footprint_mm",
    "interreflection",
    "render_sl_frames",
    "subsurface_blur",
    "subsurface_kernel",
]

#: Jensen et al. 2001, Table 2, skin1: absorption σ_a and reduced scattering σ_s′ (mm⁻¹), R, G, B.
SKIN1_SIGMA_A = (0.032, 0.17, 0.48)
SKIN1_SIGMA_S_PRIME = (0.74, 0.88, 1.01)
SKIN1_ETA = 1.3
#: Reduced mean free path 1/(σ_a + σ_s′) of skin1 in red light, mm (the Gaussian kernel's σ).
SKIN_MEAN_FREE_PATH_MM = 1.0 / (SKIN1_SIGMA_A[0] + SKIN1_SIGMA_S_PRIME[0])


@dataclass(frozen=True)
class SkinEffects:
    """Parameters of :func:`apply_effects` (``None`` / 0 disables an effect).

    Attributes
    ----------
    subsurface : {"none", "gaussian", "dipole"}
        Kernel of the subsurface blur.
    mean_free_path_mm : float, mm
        σ of the Gaussian kernel (default skin1's reduced mean free path in red, 1.3 mm).
    sigma_a, sigma_s_prime : tuple of float, mm⁻¹
        Dipole coefficients, one per colour channel (or one for all).
    eta : float
        Relative index of refraction for the dipole.
    subsurface_fraction : float in [0, 1]
        Share of the reflected light that scatters below the surface.
    scale : float
        Multiplies the kernel's size (a thicker or more translucent skin than skin1; a
        stress test).
    interreflection : float >= 0
        Strength of the low-frequency global term.
    ir_sigma_px : float, optional, camera pixels
        Its Gaussian σ (default: an eighth of the head mask's larger extent).
    """

    subsurface: str = "gaussian"
    mean_free_path_mm: float = SKIN_MEAN_FREE_PATH_MM
    sigma_a: tuple = SKIN1_SIGMA_A
    sigma_s_prime: tuple = SKIN1_SIGMA_S_PRIME
    eta: float = SKIN1_ETA
    subsurface_fraction: float = 0.8
    scale: float = 1.0
    interreflection: float = 0.0
    ir_sigma_px: float | None = None

    def __post_init__(self) -> None:
        check_choice(self.subsurface, "SkinEffects.subsurface", ("none", "gaussian", "dipole"))
        for key in ("mean_free_path_mm", "eta", "scale"):
            v = float(as_array(getattr(self, key), f"SkinEffects.{key}", shape=()))
            if not v > 0:
                raise InputError(f"SkinEffects.{key}: expected a number > 0, got {fmt_value(v)}")
        f = float(as_array(self.subsurface_fraction, "SkinEffects.subsurface_fraction", shape=()))
        if not 0.0 <= f <= 1.0:
            raise InputError(f"SkinEffects.subsurface_fraction: expected a number in [0, 1], got {f}")
        s = float(as_array(self.interreflection, "SkinEffects.interreflection", shape=()))
        if s < 0:
            raise InputError(f"SkinEffects.interreflection: expected a number >= 0, got {s}")
        if self.ir_sigma_px is not None and not float(self.ir_sigma_px) > 0:
            raise InputError(f"SkinEffects.ir_sigma_px: expected a number > 0, got "
                             f"{fmt_value(self.ir_sigma_px)}")

    def to_dict(self) -> dict[str, Any]:
        """Plain numbers / strings / lists (for a scan manifest); ``None`` left out."""
        out = {}
        for k in self.__dataclass_fields__:
            v = getattr(self, k)
            if v is not None:
                out[k] = list(v) if isinstance(v, tuple) else v
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SkinEffects:
        """Build from a mapping of the attribute names (unknown keys raise InputError)."""
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - known)
        if unknown:
            raise InputError(f"SkinEffects: unknown key(s) {unknown}; valid keys are {sorted(known)}")
        d = dict(d)
        for k in ("sigma_a", "sigma_s_prime"):
            if isinstance(d.get(k), list):
                d[k] = tuple(d[k])
        return cls(**d)


def footprint_mm(camera, p_world, mask=None) -> float:
    """Camera pixel footprint on the face, mm per pixel at the median depth of ``p_world``.

    Parameters
    ----------
    camera : facegeo.geometry.camera.Camera
    p_world : (..., 3) float, metres, world frame
        Surface points seen by the camera (NaN allowed where nothing is seen).
    mask : (...) bool, optional
        Points to use.

    Returns
    -------
    float, mm / pixel
        ``median(z_cam) / f`` with ``f`` the mean of the focal lengths in pixels.
    """
    p = as_array(p_world, "p_world", shape=(..., 3), finite=False)
    if mask is not None:
        p = p[np.asarray(mask, bool)]
    p = p.reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    if not len(p):
        raise InputError("p_world: no finite surface point to measure the camera footprint on")
    T = camera.T_cam_world
    z = (p @ np.asarray(T.R).T + np.asarray(T.t))[:, 2]
    f = 0.5 * (camera.K[0, 0] + camera.K[1, 1])
    return float(np.median(z) / f * 1000.0)


def subsurface_kernel(effects: SkinEffects, pixel_mm: float, channels: int = 1) -> np.ndarray:
    """The normalised subsurface kernel on the camera pixel grid.

    Parameters
    ----------
    effects : SkinEffects
    pixel_mm : float, mm / pixel
        Camera footprint (:func:`footprint_mm`).
    channels : int
        1, or the colour channels (the dipole kernel is per channel).

    Returns
    -------
    (K, K, channels) float32
        Odd ``K``; each channel sums to 1. Gaussian: ``σ = scale · mean_free_path / pixel_mm``
        pixels, out to 4 σ. Dipole: ``R_d(scale · r)`` averaged over 4 × 4 sub-pixel samples,
        out to the radius holding 99 % of the profile's energy.
    """
    px = float(pixel_mm)
    if not px > 0:
        raise InputError(f"pixel_mm: expected a number > 0, got {fmt_value(pixel_mm)}")
    if effects.subsurface == "gaussian":
        sigma = effects.scale * effects.mean_free_path_mm / px
        r = max(1, int(np.ceil(4.0 * sigma)))
        t = np.arange(-r, r + 1, dtype=np.float64)
        g = np.exp(-0.5 * (t / max(sigma, 1e-6)) ** 2)
        k = np.outer(g, g)
        k = np.repeat((k / k.sum())[..., None], channels, axis=2)
        return k.astype(np.float32)
    if effects.subsurface != "dipole":
        raise InputError("effects.subsurface: 'none' has no kernel")
    from facegeo.appearance.spectral import dipole_profile

    sa = np.broadcast_to(np.asarray(effects.sigma_a, np.float64), (channels,)) \
        if np.size(effects.sigma_a) in (1, channels) else None
    ss = np.broadcast_to(np.asarray(effects.sigma_s_prime, np.float64), (channels,)) \
        if np.size(effects.sigma_s_prime) in (1, channels) else None
    if sa is None or ss is None:
        raise ShapeError(f"SkinEffects.sigma_a / sigma_s_prime: expected 1 or {channels} values "
                         f"(one per channel), got {np.size(effects.sigma_a)} and "
                         f"{np.size(effects.sigma_s_prime)}")
    # radius: where the cumulative energy of r·R_d(r) reaches 99 % (a fine 1-D integral)
    rr = np.linspace(1e-4, 60.0, 6000)  # mm
    prof = dipole_profile(rr[:, None], sa[None], ss[None], effects.eta) * rr[:, None]
    cum = np.cumsum(prof, axis=0)
    r99 = float(rr[np.argmax(cum >= 0.99 * cum[-1], axis=0)].max()) * effects.scale
    R = max(1, int(np.ceil(r99 / px)))
    sub = (np.arange(4) + 0.5) / 4.0 - 0.5
    t = np.arange(-R, R + 1, dtype=np.float64)
    xs = (t[:, None] + sub[None, :]).reshape(-1)
    d = np.hypot(xs[:, None], xs[None, :]) * px / effects.scale  # mm in the unscaled profile
    k = dipole_profile(d[..., None], sa, ss, effects.eta)
    k = k.reshape(len(t), 4, len(t), 4, channels).mean(axis=(1, 3))
    k /= k.sum(axis=(0, 1), keepdims=True)
    return k.astype(np.float32)


def _convolve(img: np.ndarray, kernel2d: np.ndarray) -> np.ndarray:
    from scipy.signal import fftconvolve

    return fftconvolve(img, kernel2d, mode="same")


def subsurface_blur(image, mask, kernel) -> np.ndarray:
    """Blur a pattern-lit image with a subsurface kernel, normalised inside ``mask``.

    ``out = f_ss · (K * (m I)) / (K * m) + (1 - f_ss) · I`` is applied by :func:`apply_effects`;
    this function returns the blurred part ``(K * (m I)) / (K * m)`` (0 outside the mask).

    Parameters
    ----------
    image : (H, W) or (H, W, C) float, linear radiance
    mask : (H, W) bool
        Pixels on the head.
    kernel : (K, K, C') float
        From :func:`subsurface_kernel`; ``C'`` is 1 or ``C``.

    Returns
    -------
    Same shape as ``image``, float32.
    """
    img = np.asarray(image, np.float32)
    m = np.asarray(mask, bool)
    if m.shape != img.shape[:2]:
        raise ShapeError(f"mask: expected shape {img.shape[:2]}, got {m.shape}")
    k = np.asarray(kernel, np.float64)
    if k.ndim != 3 or k.shape[0] != k.shape[1] or k.shape[0] % 2 != 1:
        raise ShapeError(f"kernel: expected (K, K, C) with odd K, got {k.shape}")
    img3 = img[..., None] if img.ndim == 2 else img
    C = img3.shape[2]
    if k.shape[2] not in (1, C):
        raise ShapeError(f"kernel: {k.shape[2]} channels for an image of {C}")
    mf = m.astype(np.float64)
    out = np.zeros(img3.shape, np.float32)
    norm = {}
    for c in range(C):
        kc = k[..., c if k.shape[2] > 1 else 0]
        key = c if k.shape[2] > 1 else 0
        if key not in norm:
            norm[key] = _convolve(mf, kc)
        num = _convolve(img3[..., c] * mf, kc)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[..., c] = np.where(m, num / np.maximum(norm[key], 1e-12), 0.0)
    return out[..., 0] if img.ndim == 2 else out


def interreflection(image, mask, strength: float, sigma_px: float | None = None) -> np.ndarray:
    """The low-frequency global term ``strength · G_σ * (m I)`` inside ``mask`` (float32).

    ``sigma_px`` defaults to an eighth of the mask's larger extent (rows or columns).
    """
    from scipy.ndimage import gaussian_filter

    img = np.asarray(image, np.float32)
    m = np.asarray(mask, bool)
    if m.shape != img.shape[:2]:
        raise ShapeError(f"mask: expected shape {img.shape[:2]}, got {m.shape}")
    if sigma_px is None:
        rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
        extent = max(np.ptp(rows) + 1 if rows.size else 1, np.ptp(cols) + 1 if cols.size else 1)
        sigma_px = extent / 8.0
    sig = (sigma_px, sigma_px) + ((0,) if img.ndim == 3 else ())
    g = gaussian_filter(img * (m[..., None] if img.ndim == 3 else m), sig, mode="constant")
    mm = m[..., None] if img.ndim == 3 else m
    return (np.float32(strength) * g * mm).astype(np.float32)


def apply_effects(image, mask, effects: SkinEffects, *, pixel_mm: float,
                  kernel: np.ndarray | None = None) -> np.ndarray:
    """Subsurface blur then interreflection of a direct, pattern-lit image (module docstring).

    ``I' = (1 - f) I + f · blur(I)``; ``I'' = I' + interreflection(I')``.

    Parameters
    ----------
    image : (H, W) or (H, W, C) float, linear radiance (direct light only, no ambient)
    mask : (H, W) bool, pixels on the head
    effects : SkinEffects
    pixel_mm : float, mm / pixel (:func:`footprint_mm`)
    kernel : (K, K, C) float, optional
        A precomputed :func:`subsurface_kernel` (saves recomputing it for every frame).

    Returns
    -------
    Same shape, float32.
    """
    if not isinstance(effects, SkinEffects):
        raise InputError(f"effects: expected a SkinEffects, got {type(effects).__name__}")
    img = np.asarray(image, np.float32)
    out = img
    if effects.subsurface != "none" and effects.subsurface_fraction > 0:
        if kernel is None:
            kernel = subsurface_kernel(effects, pixel_mm, img.shape[2] if img.ndim == 3 else 1)
        f = np.float32(effects.subsurface_fraction)
        out = (1 - f) * img + f * subsurface_blur(img, mask, kernel)
    if effects.interreflection > 0:
        out = out + interreflection(out, mask, effects.interreflection, effects.ir_sigma_px)
    return out.astype(np.float32)


def render_sl_frames(renderer, spec, camera, *, projector=None, supersample: int = 3,
                     exposure: float = 3.0, ambient: float = 0.02,
                     effects: SkinEffects | None = None):
    """Yield ``(name, frame)``: noise-free linear structured-light frames of ``camera``.

    The generator's model (``facegeo.synth.capture._write_scan``): the skin BRDF shaded under the
    projector as a point light with Embree shadows, modulated per projector pixel by
    :func:`~facegeo.geometry.structured_light.pattern_value_at`, times ``exposure``, plus an
    ambient ``ambient · α₀ / π``; with ``effects``, the pattern-lit part passes through
    :func:`apply_effects` first.

    Parameters
    ----------
    renderer : facegeo.synth.render.ReferenceRenderer
    spec : PatternSpec
    camera : facegeo.geometry.camera.Camera
    projector : facegeo.geometry.camera.Camera, optional
        Default ``renderer.rig.projector`` (set by
        :func:`facegeo.synth.render.load_ground_truth`).
    supersample, exposure, ambient, effects
        As above.

    Yields
    ------
    name : str
    frame : (H, W, 3) float32, linear
    """
    from facegeo.geometry.structured_light import pattern_names, pattern_value_at

    proj = renderer.rig.projector if projector is None else projector
    view = renderer.surface_view(camera, supersample=supersample)
    unit = renderer.shade_point_light(view, proj.center_world, np.ones(3),
                                      stage_radius=float(np.linalg.norm(proj.center_world)))
    q_proj, in_front = proj.project(view.p_world)
    amb = view.to_image((exposure * ambient * view.alpha_0 / np.pi).astype(np.float32))
    kernel = pixel_mm = None
    if effects is not None:
        mask = view.mask
        pixel_mm = footprint_mm(camera, view.p_world)
        if effects.subsurface != "none":
            kernel = subsurface_kernel(effects, pixel_mm, 3)
    q = np.nan_to_num(q_proj, nan=-1e9)
    for name in pattern_names(spec):
        pat = np.where(in_front, pattern_value_at(spec, name, q), 0.0).astype(np.float32)
        direct = view.to_image((exposure * unit * pat[:, None]).astype(np.float32))
        if effects is not None:
            direct = apply_effects(direct, mask, effects, pixel_mm=pixel_mm, kernel=kernel)
        yield name, direct + amb
