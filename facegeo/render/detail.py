"""Image-space detail for novel views: the source cameras' relit images, projected per pixel.

The renderer's texture-space path (:mod:`facegeo.render.novel`) reads the reflectance field at
the atlas's texels and interpolates between them, so a novel view carries no detail finer than
a texel (1 mm on the small preset), even where a source camera's image holds it. The naive
baseline in its literal form — "projecting the source cameras' relit images" (view-dependent
texture mapping, Debevec, Taylor & Malik 1996) — reads those images per pixel instead and keeps
that detail. This module does that projection:

for each pixel sample of the novel view (its surface point on the atlas mesh), each source
camera that sees the point (:func:`facegeo.surface.reflectance.camera_visibility`: in the image,
facing, unoccluded, with the projection's own foreshortening and edge-feathering weight
``w_c``) contributes its relit image sampled bilinearly where the point projects
(:func:`facegeo.surface.reflectance.sample_frame`: a tap on a masked pixel leaves that camera
out), blended with the renderer's view-dependent weight ``b_c = w_c / max(θ_c, θ_floor)^p``
(cameras below :data:`facegeo.render._blend.BLEND_MIN_SHARE` of a sample's blend left out, as
for texels).

:func:`facegeo.render.novel.render_view` (``detail=``) adds the difference between this
projection and the texture-space naive render of the same view to every render of it — the
resynthesised one, the naive baseline, the paper's λ = 1 — on the pixels where both exist. The
texture-space path then carries what the skin model predicts for the new view (the change from
the measured functions, smooth at a texel's scale) and the source images the detail; the naive
baseline becomes the per-pixel projection itself, the strongest form of it measured
(docs/render.md, "Image-space detail"). A deviation from the paper, which renders from the
texture maps alone.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from facegeo.checks import as_array, fmt_value
from facegeo.errors import InputError, ShapeError
from facegeo.render._blend import BLEND_MIN_SHARE, SAME_VIEW_RAD, _angle, key_lights

__all__ = ["SourceImage", "check_source_images", "project_source_images", "sample_normals"]


@dataclass(frozen=True)
class SourceImage:
    """One source camera's capture relit under the render's environment.

    Attributes
    ----------
    camera : facegeo.geometry.camera.Camera — the camera the atlas was projected from
    image : (H, W, 3) float32 — ``Σ_l w_l ⊙ frame_l`` (Eq. 4) with the render's weights, in
        the field's units (:func:`facegeo.lighting.relight.relight_scan_view`)
    valid : (H, W) bool — False where some lit frame's pixel is untrusted (saturated)
    key_frames : mapping light -> (frame (H, W, 3), valid (H, W)) — the OLAT frames of the
        environment's key lights (:func:`facegeo.render._blend.key_lights`), for
        shadow-consistent taps at their cast-shadow edges; empty: plain bilinear sampling
    """

    camera: object
    image: np.ndarray
    valid: np.ndarray
    key_frames: dict = field(default_factory=dict)

    def __post_init__(self):
        cam = self.camera
        shape = (int(cam.height), int(cam.width))
        img = np.asarray(self.image)
        if img.shape != shape + (3,):
            raise ShapeError(f"camera {fmt_value(cam.name)}: relit image has shape {img.shape}, "
                             f"expected {shape + (3,)}")
        if np.shape(self.valid) != shape:
            raise ShapeError(f"camera {fmt_value(cam.name)}: valid mask has shape "
                             f"{np.shape(self.valid)}, expected {shape}")
        for light, (frame, ok) in self.key_frames.items():
            if np.shape(frame) != shape + (3,) or np.shape(ok) != shape:
                raise ShapeError(f"camera {fmt_value(cam.name)}: key light {light}'s frame and "
                                 f"mask have shapes {np.shape(frame)}, {np.shape(ok)}, expected "
                                 f"{shape + (3,)}, {shape}")


def check_source_images(images) -> list:
    """``images`` as a list: a non-empty sequence of :class:`SourceImage`, one per camera."""
    if isinstance(images, SourceImage) or not isinstance(images, (list, tuple)):
        raise InputError(f"detail: expected a list of SourceImage (one per source camera), got "
                         f"{type(images).__name__}")
    images = list(images)
    if not images:
        raise InputError("detail: no source images (None renders without image detail)")
    for k, im in enumerate(images):
        if not isinstance(im, SourceImage):
            raise InputError(f"detail[{k}]: expected a SourceImage, got {type(im).__name__}")
    names = [im.camera.name for im in images]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InputError(f"detail: camera(s) {', '.join(map(fmt_value, twice))} given twice")
    return images


def sample_normals(atlas, face, bary) -> tuple[np.ndarray, np.ndarray]:
    """Shading normals (vertex normals interpolated, unit) and geometric normals of the atlas
    mesh at hit points given by ``face`` ``(P,)`` and barycentrics ``bary`` ``(P, 3)``."""
    face = np.asarray(face, np.int64)
    f = atlas.faces[face]
    n = np.einsum("pk,pkc->pc", np.asarray(bary, np.float64), atlas.normals[f])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    v = atlas.vertices
    g = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-300)
    return n, g


def project_source_images(vs, images, scene, atlas, *, blend_power: float, weights=None,
                          shadows=None, visibility: dict | None = None,
                          stats: dict | None = None) -> np.ndarray:
    """Per pixel sample of ``vs``, the source images blended as the module docstring says.

    Parameters
    ----------
    vs : ViewSamples — the novel view's samples (:func:`facegeo.render.novel.trace_view`)
    images : sequence of SourceImage
    scene : RayScene — over the atlas mesh (occlusion toward each source camera)
    atlas : Atlas — its normals (facing test and foreshortening weight)
    blend_power : float — p of the view-dependent weight
    weights : (L, 3) float, optional — the Eq. (4) weights the images were relit with (needed
        with ``shadows``)
    shadows : RenderShadows, optional — shadow-consistent taps in the source images
        (:func:`facegeo.render.novel.render_shadows`, with its ``stage``): for each key light
        of ``weights`` whose frame a :class:`SourceImage` holds, a sample whose bilinear taps
        straddle that light's cast-shadow edge (decided on the atlas mesh) takes the light's
        share from the taps on its own side, ``+ w_l ⊙ (side − bilinear)`` — the
        projection's own :class:`facegeo.surface.shadows.ShadowTaps`
    visibility : dict, optional — ``min_cos``, ``feather_px``, ``depth_jump`` of
        :func:`facegeo.surface.reflectance.camera_visibility`: the projection's own (the
        ``project`` stage's settings), so that the weights ``w_c`` are the texels'; default
        the projection's defaults
    stats : dict, optional — filled with ``detail_cameras`` (samples each camera contributed
        to), ``detail_shadow_samples`` (samples the key lights' taps moved) and
        ``seconds_detail``

    Returns
    -------
    (P, 3) float32 — NaN where no source camera sees the sample's point with trusted pixels
    """
    from facegeo.surface.reflectance import camera_visibility, frame_sampler, sample_frame

    t0 = time.perf_counter()
    images = check_source_images(images)
    if isinstance(blend_power, bool) or not isinstance(blend_power, (int, float, np.number)) \
            or not np.isfinite(blend_power) or blend_power < 0:
        raise InputError(f"blend_power: expected a finite number >= 0, got "
                         f"{fmt_value(blend_power)}")
    vis_kw = dict(visibility or {})
    extra = set(vis_kw) - {"min_cos", "feather_px", "depth_jump"}
    if extra:
        raise InputError(f"visibility: unknown setting(s) {', '.join(sorted(extra))} (expected "
                         "min_cos, feather_px, depth_jump)")
    if vs.face is None or vs.bary is None:
        raise InputError("project_source_images: the view samples keep no faces "
                         "(trace them with trace_view)")
    p = as_array(vs.p_world, "vs.p_world", shape=(None, 3))
    n, g = sample_normals(atlas, vs.face, vs.bary)
    points = SimpleNamespace(p_world=p, n_world=n, n_geom=g)
    P = len(p)
    keys = np.zeros(0, np.int64)
    if shadows is not None:
        if weights is None or getattr(shadows, "stage", None) is None:
            raise InputError("project_source_images: shadows need the weights and a "
                             "RenderShadows with its stage (render_shadows)")
        w = np.asarray(weights, np.float64)
        keys = key_lights(w, shadows.key_share, shadows.max_lights)
    parts = []
    total = np.zeros(P)
    n_moved = 0
    for src in images:
        cam = src.camera
        vis = camera_visibility(points, cam, scene, **vis_kw)
        sel = np.flatnonzero(vis.weight > 0)
        if sel.size == 0:
            parts.append((sel, np.zeros(0), np.zeros((0, 3), np.float32)))
            continue
        sampler = frame_sampler(vis.q[sel], cam.width, cam.height)
        val = sample_frame(np.asarray(src.image, np.float32), sampler,
                           np.asarray(src.valid, bool))
        mine = [int(k) for k in keys if int(k) in src.key_frames]
        if mine:
            from facegeo.surface.shadows import shadow_taps

            taps = shadow_taps(shadows.rays, cam, vis.q[sel], vs.face[sel], vs.bary[sel],
                               shadows.stage)
            for k in mine:
                frame, ok = src.key_frames[k]
                frame = np.asarray(frame, np.float32)
                plain = sample_frame(frame, sampler, np.asarray(ok, bool))
                side = plain.copy()
                if taps.apply(k, frame, side, np.asarray(ok, bool)):
                    # Eq. 4 is linear in the frames: the light's share moves to its side's
                    # taps; rows the taps left alone (equal, or NaN in both) stay as they are
                    same = (side == plain) | (np.isnan(side) & np.isnan(plain))
                    val = val + np.where(same, 0.0, w[k] * (side - plain)).astype(np.float32)
            n_moved += taps.changed
        theta = _angle(vis.v_world[sel], vs.v_world[sel])
        b = vis.weight[sel].astype(np.float64) / np.maximum(theta, SAME_VIEW_RAD) ** blend_power
        ok = np.isfinite(val).all(axis=1)
        sel, b, val = sel[ok], b[ok], val[ok]
        parts.append((sel, b, val))
        total[sel] += b  # sel holds each sample once
    acc = np.zeros((P, 3))
    bsum = np.zeros(P)
    used = {}
    for src, (sel, b, val) in zip(images, parts):
        keep = b >= BLEND_MIN_SHARE * total[sel]
        sel, b, val = sel[keep], b[keep], val[keep]
        used[src.camera.name] = int(sel.size)
        acc[sel] += b[:, None] * val
        bsum[sel] += b
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(bsum[:, None] > 0, acc / np.where(bsum > 0, bsum, 1.0)[:, None], np.nan)
    if stats is not None:
        stats.update({"detail_cameras": used, "detail_shadow_samples": int(n_moved),
                      "seconds_detail": round(time.perf_counter() - t0, 4)})
    return out.astype(np.float32)
