"""Novel-view rendering of a reflectance-field face (Debevec et al. 2000, §4.5).

For a camera the light stage never had, under an environment given as Eq. (4) light weights:

1. **Primary rays** (Embree, :class:`facegeo.surface.visibility.RayScene` over the atlas mesh)
   give each pixel sample a surface point, its atlas face and barycentrics; the face's UVs give
   an atlas position, and the four texels around it (bilinear taps, docs/surface.md UV
   convention) carry the reflectance data. Taps on another chart (farther than
   :data:`TAP_MAX_TEXELS` texel spacings from the hit) or outside every chart are dropped and
   the rest renormalised.
2. **Per texel**, only for the texels some pixel needs, for each source camera c that measured
   it (a row of its projected field ``R_c``): its reflectance function resynthesised for the
   new view v_n (the skin model, §4.3 Eq. 9: :func:`facegeo.appearance.skin.resynthesize`),
   then relit with the environment (Eq. 4: ``Σ_l R(l) ⊙ w_l`` over the lights with non-zero
   weight only).
3. **Blended across source cameras** with view-dependent weights (Debevec, Taylor & Malik 1996,
   view-dependent texture mapping; the paper's §4.5 "blend ... weighted by the angle"):
   ``b_c = w_c(t) / max(θ_c, θ_floor)^p`` with θ_c the angle at the surface point between the
   source view v_c and v_n, ``w_c(t)`` the projection's own light-independent weight
   (foreshortening and occlusion-edge feathering, docs/surface.md) and ``p =``
   :data:`BLEND_POWER`. A view equal to a source camera (θ below :data:`SAME_VIEW_RAD`) takes
   that camera's measured function unchanged, and its weight dominates every other by
   ≥ 10¹⁴, so the render reproduces that camera's relit image. Cameras whose share of a
   texel's blend is below :data:`BLEND_MIN_SHARE` are skipped (not read, not resynthesised).
4. **Image**: pixel samples are the tap-weighted texel colours, averaged over s × s sub-pixel
   samples with supersampling; pixels whose taps no camera measured are not covered (0, and
   False in ``RenderResult.covered``); with ``fill_px > 0`` such samples take the colour of
   the nearest pixel with measured samples within that distance (hole filling for display:
   the silhouette ring the projection leaves out) and stay False in ``covered``; with
   ``infer`` (not the paper) every other hit sample takes its texels' values inferred from
   their measured neighbours on the surface (:func:`infer_texel_colours`: pull–push of
   colour over Lambertian shading over the texels' positions), else the nearest pixel's, and
   is marked in ``RenderResult.inferred``: no surface pixel is black.
   **Shadow-consistent texel taps** (``shadows=``, :func:`render_shadows`; the paper's §4.4
   shadow maps "using our geometric model", as the projection does them,
   :mod:`facegeo.surface.shadows`): for each *key light* of the environment (a sun, a studio
   key: at least :data:`SHADOW_KEY_SHARE` of the weights' energy), the mesh decides which
   texel taps and which pixel samples the light reaches; a sample whose taps straddle the
   light's cast-shadow edge takes that light's share of its value from the taps on its own
   side only: ``Σ_k b_k C_k + Σ_k (b_k(l) − b_k) C_k(l)``, with C_k(l) the texel relit by
   light l alone (Eq. 4 is linear in the weights; the blend and λ_c are the environment's).
   Without it, a texel ramp 1 mm wide blurs the sun's shadow edge in every novel view
   (docs/render.md: small preset, generator's mesh, +30°: 1.82 → 1.30 % relative RMSE).
5. **Image-space detail** (``detail=``, :mod:`facegeo.render.detail`; the render stage's
   default; a deviation from the paper, which renders from the texture maps alone): the source
   cameras' captures relit with the same weights, projected per pixel sample and blended with
   the same weights ``b_c`` (shadow-consistent taps in the images at the key lights' edges),
   minus the texture-space naive render of the view, are added to every render of it. The
   texels carry the change the skin model predicts for the new view; the images carry what is
   finer than a texel. The naive baseline becomes the per-pixel projection of the relit
   source images — stronger than through the texels (small preset, reconstructed mesh, +30°,
   shadow-consistent taps in both: 2.40 → 2.19 % relative RMSE).

Where the fitted normal puts v_n at or below the horizon although the mesh sees the texel
(``FLAG_BACKFACING``, grazing views with a normal a few degrees off), resynthesis would give
black; the texel keeps its measured function from that camera instead (counted in
``stats["backfacing_fallback"]``).

The naive baseline (``resynthesis=False``) is the same pipeline with the source cameras'
measured functions relit unchanged (projecting the relit source views onto the geometry;
with ``detail``, per pixel from the images themselves).

**Cross-validated shrinkage (a deviation from the paper, optional).** With ``shrinkage`` a
source camera's resynthesised relit value becomes ``naive + λ_c (resynthesised − naive)``: only
the share λ_c ∈ [0, 1] of the change the skin model predicts is applied. λ_c is measured, not
chosen: :func:`cross_validated_shrinkage` resynthesises camera c's fits for the *other* source
cameras' views, where the answer was captured, and takes the least-squares λ between the
predicted and the measured change under the same lighting. λ = 1 is the paper's §4.3; λ = 0 the
naive baseline. Why: on the generator's data the fitted specular part holds twice the true
specular energy (the generator's diffuse term is outside the paper's model, docs/render.md), so
the predicted change overshoots and its errors are anti-correlated with the naive baseline's;
the cross-validated λ is 0.43–0.58 on the small preset under ``sky``. With one source camera there is nothing to
cross-validate and λ = 1.
``render_view(..., shrinkage_set=[...])`` renders several λ mappings (e.g. the shrunk render,
λ = 0 = the naive baseline and λ = 1 = the paper) from one read of the fields and one
resynthesis, each equal bit for bit to its own call.

Resynthesis is relit in one fused pass (:func:`facegeo.appearance.skin.resynthesize_relit`):
Eq. 9 still interpolates the measured lobe over the whole light set, but the resynthesised
samples are computed only at the lights that carry energy and never stored.
Where the field and the fit's D are stored as float16 (the default), each chunk of texels
(:data:`STORED_CHUNK` functions) is read, relit naively and resynthesised in one compiled pass
(:data:`FUSED_READ`, :meth:`facegeo.render._fitstore.FitStore.relit_rows`), at any
``light_step`` and whatever number of lights carry energy: the float16 bits are decoded
exactly inside the kernel, R, D and S are never widened into float32 arrays and the naive
Eq. 4 is no matrix product (same samples, same resynthesis code; the naive sums are float64,
the sgemm's were float32).

**Speed against accuracy (optional, not the paper):** ``light_step = k > 1`` evaluates the
resynthesised function once per k × k block of the light grid, at the block's energy centroid
(:func:`shade_texels`); measured in ``facegeo bench render.novel_view_paper``.

References
----------
.. [1] P. Debevec et al., "Acquiring the Reflectance Field of a Human Face", SIGGRAPH 2000, §4.5.
.. [2] P. Debevec, C. J. Taylor, J. Malik, "Modeling and Rendering Architecture from
   Photographs", SIGGRAPH 1996 (view-dependent texture mapping).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from facegeo.checks import as_array, fmt_value
from facegeo.errors import InputError, ShapeError
from facegeo.render._blend import (
    BLEND_MIN_SHARE,
    SAME_VIEW_RAD,
    _angle,
    key_lights,
)
from facegeo.render._infer import infer_texel_colours, lambert_irradiance

log = logging.getLogger(__name__)

__all__ = [
    "BLEND_POWER",
    "SAME_VIEW_RAD",
    "SHRINK_FUNCTIONS",
    "SHADOW_KEY_SHARE",
    "SHADOW_MAX_LIGHTS",
    "RenderResult",
    "RenderShadows",
    "SourceCamera",
    "ViewSamples",
    "atlas_scene",
    "cross_validated_shrinkage",
    "even_subset",
    "infer_texel_colours",
    "lambert_irradiance",
    "key_lights",
    "load_sources",
    "pixel_sample_rays",
    "render_shadows",
    "render_view",
    "shade_texels",
    "trace_view",
]

#: Exponent p of the view-dependent weight 1/θ^p. The naive baseline is strongest from about
#: 8 on (small preset, ±30° / ±60°, relative RMSE over covered pixels: p = 2 → 8 lowers it by
#: 1–6 %, 8 → 32 by ≤ 0.2 %); the resynthesis moves by ±4 % either way (docs/render.md). 8 is
#: the baseline's best, so the comparison is against the strongest naive render.
BLEND_POWER = 8.0
#: A bilinear tap farther than this many texel spacings from the hit point lies on another chart.
TAP_MAX_TEXELS = 3.0
#: Read, relight and resynthesise float16 fields and fits in one compiled pass
#: (:meth:`facegeo.render._fitstore.FitStore.relit_rows`) where it applies (full resynthesis,
#: float16 field and D on the light-stage grid; any ``light_step``, any number of lights with
#: energy). False: always the numpy read (float32 copies of R, D and S, Eq. 4 as a matrix
#: product, the block summaries by ``block_outputs``), which it is tested against.
FUSED_READ = True
#: A light of the environment takes part in the shadow-consistent texel taps
#: (:func:`render_shadows`) when it carries at least this share of the weights' energy: a
#: sun, a studio key light. Lights below it cast soft, faint edges that a texel's bilinear
#: ramp already follows.
SHADOW_KEY_SHARE = 0.02
#: At most this many lights (the strongest) take part in the shadow-consistent texel taps.
SHADOW_MAX_LIGHTS = 8
#: Functions per resynthesis chunk: ``CHUNK_SAMPLES // L`` (bounded temporaries).
CHUNK_SAMPLES = 1 << 19
#: Functions per call of the compiled float16 passes (the fused read and the naive baseline's
#: Eq. 4 from the bits): they hold no ``(n, L, 3)`` temporaries, only the chunk's unpacked
#: cast-shadow map (``n·L`` bytes), so a chunk is large — each call ends with one thread
#: waiting for the other, which at ``CHUNK_SAMPLES // L`` = 256 functions cost ≈ 40 % more
#: CPU time than the work itself (paper view, 2 threads).
STORED_CHUNK = 16384
#: Functions per ordered camera pair that :func:`cross_validated_shrinkage` resynthesises
#: (an even subset of the texels both cameras measured; λ is one scalar per camera).
SHRINK_FUNCTIONS = 4096


@dataclass
class ViewSamples:
    """What a camera sees on the atlas: per pixel sample, a surface point and its texel taps.

    Attributes
    ----------
    camera_name : str
    shape : (int, int) — image (height, width)
    samples_per_pixel : int — s² with s × s supersampling
    pixel_index : (P,) int64 — ``(row·W + col)·s² + k`` of each sample that hit the mesh
    p_world : (P, 3) float64, metres, world frame
    v_world : (P, 3) float64, unit — toward the camera centre
    taps : (P, 4) int64 — texel index of each bilinear tap, -1 where none
    tap_weight : (P, 4) float64 — bilinear weights of the kept taps, summing to 1 (0 when none)
    face : (P,) int64 or None — the atlas face each sample hit (None: not kept)
    bary : (P, 3) float64 or None — its barycentrics there
    """

    camera_name: str
    shape: tuple[int, int]
    samples_per_pixel: int
    pixel_index: np.ndarray
    p_world: np.ndarray
    v_world: np.ndarray
    taps: np.ndarray
    tap_weight: np.ndarray
    face: np.ndarray | None = None
    bary: np.ndarray | None = None

    @property
    def needed_texels(self) -> np.ndarray:
        """Sorted unique texels with a non-zero tap weight."""
        return np.unique(self.taps[self.tap_weight > 0])

    @property
    def mask(self) -> np.ndarray:
        """``(H, W)`` bool: some sample of the pixel hits the mesh."""
        h, w = self.shape
        m = np.zeros(h * w * self.samples_per_pixel, bool)
        m[self.pixel_index] = True
        return m.reshape(h, w, self.samples_per_pixel).any(axis=2)

    def to_image(self, values, fill: float = 0.0) -> np.ndarray:
        """Per-sample values ``(P, ...)`` → image ``(H, W, ...)`` (box filter over sub-samples;
        samples that miss count as ``fill``)."""
        h, w = self.shape
        s = self.samples_per_pixel
        values = np.asarray(values)
        out = np.full((h * w * s,) + values.shape[1:], fill, values.dtype)
        out[self.pixel_index] = values
        out = out.reshape((h, w, s) + values.shape[1:])
        return out[:, :, 0] if s == 1 else out.mean(axis=2, dtype=np.float64).astype(values.dtype)


@dataclass
class SourceCamera:
    """One source camera's measured data on the atlas.

    Attributes
    ----------
    name : str
    texel_index : (T_c,) int64, increasing — texels of the projected field's rows
    weight : (T_c,) float — light-independent projection weight w_c(t) > 0
    v_world : (T_c, 3) float64, unit — toward this camera (v_0)
    field : (T_c, L, C) array (memory map) — the projected field R_c
    fit : FitStore or None — skin-model fits (needed for resynthesis)
    """

    name: str
    texel_index: np.ndarray
    weight: np.ndarray
    v_world: np.ndarray
    field: np.ndarray
    fit: object = None

    def rows_of(self, texels) -> tuple[np.ndarray, np.ndarray]:
        """Field row of each texel and whether this camera measured it."""
        texels = np.asarray(texels, np.int64)
        pos = np.searchsorted(self.texel_index, texels)
        pos_c = np.minimum(pos, max(self.texel_index.size - 1, 0))
        if self.texel_index.size == 0:
            return pos_c, np.zeros(texels.shape, bool)
        return pos_c, (pos < self.texel_index.size) & (self.texel_index[pos_c] == texels)


@dataclass
class RenderResult:
    """A rendered view.

    Attributes
    ----------
    image : (H, W, 3) float32, linear radiance
    covered : (H, W) bool — every sample of the pixel hit the mesh and had measured texels
    mask : (H, W) bool — some sample of the pixel hit the mesh
    stats : dict — counts and timings (texels shaded, samples resynthesised, active lights …)
    texture : (H, W, 3) float32 or None — with image-space detail, the texture-space image
        before it (``render_view(detail=)``); None otherwise
    inferred : (H, W) bool — pixels of ``mask`` holding a hit sample whose value was not
        measured but inferred (``fill_px``, and with ``render_view(infer=True)`` the inferred
        texels and the nearest-pixel fill); none of them is ``covered``
    """

    image: np.ndarray
    covered: np.ndarray
    mask: np.ndarray
    stats: dict = field(default_factory=dict)
    texture: np.ndarray | None = None
    inferred: np.ndarray | None = None


def atlas_scene(atlas):
    """The Embree scene of the atlas mesh (faces = atlas faces, so hits index its UVs)."""
    from facegeo.surface.visibility import RayScene

    return RayScene(atlas.vertices, atlas.faces)


@dataclass
class RenderShadows:
    """Shadow-consistent texel taps for a render (module docstring, step 4, "Shadow-consistent
    texel taps").

    Built by :func:`render_shadows`.

    Attributes
    ----------
    rays : facegeo.surface.shadows.ShadowRays — the atlas mesh and its shading normals
    texels : facegeo.surface.shadows.SurfacePoints — every texel's point on it
    positions : (L, 3) float64, metres, or None (distant lights)
    directions : (L, 3) float64, unit — toward each light of the stage, in light-index order
    key_share : float — a light takes part when it carries at least this share of the
        environment's energy (:data:`SHADOW_KEY_SHARE`)
    max_lights : int — at most this many lights, the strongest first
        (:data:`SHADOW_MAX_LIGHTS`)
    min_cos : float — :data:`facegeo.surface.shadows.SHADOW_TAPS_MIN_COS`
    stage : LightStage or LightList, optional — the lights themselves (the image-space detail's
        shadow-consistent taps in the source images, :mod:`facegeo.render.detail`)
    """

    rays: object
    texels: object
    positions: np.ndarray | None
    directions: np.ndarray
    key_share: float
    max_lights: int
    min_cos: float
    stage: object = None

    def light(self, light: int) -> dict:
        """``position=`` or ``direction=`` of one light (:meth:`ShadowRays.lit`)."""
        from facegeo.surface.shadows import light_kwargs

        return light_kwargs(self.positions, self.directions, light)


def render_shadows(atlas, scene, texels, stage, *, key_share: float | None = None,
                   max_lights: int | None = None) -> RenderShadows:
    """The :class:`RenderShadows` of an atlas under a light stage.

    Parameters
    ----------
    atlas : facegeo.surface.atlas.Atlas — its mesh and vertex normals decide the shadows
    scene : RayScene — over the atlas mesh (:func:`atlas_scene`)
    texels : facegeo.surface.atlas.Texels
    stage : LightStage or LightList — the lights of the fields, in light-index order
    key_share : float in (0, 1], optional — :data:`SHADOW_KEY_SHARE`
    max_lights : int ≥ 1, optional — :data:`SHADOW_MAX_LIGHTS`
    """
    from facegeo.surface.shadows import SHADOW_TAPS_MIN_COS, ShadowRays, light_positions

    share = SHADOW_KEY_SHARE if key_share is None else key_share
    if isinstance(share, bool) or not isinstance(share, (int, float, np.number)) \
            or not 0.0 < float(share) <= 1.0:
        raise InputError(f"key_share: expected a number in (0, 1], got {fmt_value(key_share)}")
    most = SHADOW_MAX_LIGHTS if max_lights is None else max_lights
    if isinstance(most, bool) or not isinstance(most, (int, float, np.number)) \
            or not np.isfinite(most) or int(most) != most or most < 1:
        raise InputError(f"max_lights: expected an integer >= 1, got {fmt_value(max_lights)}")
    if not hasattr(stage, "directions"):
        raise InputError(f"stage: expected the rig's lights (a LightStage or LightList), got "
                         f"{fmt_value(stage)}")
    if scene.n_faces != len(atlas.faces):
        raise ShapeError(f"scene: {scene.n_faces} faces, but the atlas has {len(atlas.faces)}; "
                         "build it with atlas_scene(atlas)")
    rays = ShadowRays(scene, atlas.normals)
    positions, directions = light_positions(stage)
    return RenderShadows(rays, rays.points(texels.face, texels.bary), positions, directions,
                         float(share), int(most), SHADOW_TAPS_MIN_COS, stage)


def _check_shadows(shadows, scene, texels, weights) -> None:
    """``shadows`` was built for this render's atlas (scene, texel table) and lights."""
    if not isinstance(shadows, RenderShadows):
        raise InputError(f"shadows: expected a RenderShadows (render_shadows), got "
                         f"{type(shadows).__name__}")
    if shadows.rays.scene is not scene or len(shadows.texels.p) != len(texels):
        raise InputError("shadows: built for another atlas; build them with "
                         "render_shadows(atlas, scene, texels, stage) of this render")
    n = np.shape(weights)[0]
    if len(shadows.directions) != n:
        raise ShapeError(f"shadows: built for {len(shadows.directions)} lights, but the "
                         f"weights have {n}")


def _shadow_edges(vs: ViewSamples, shadows: RenderShadows, weights) -> list:
    """Per key light, the samples whose taps mix lit and shadowed texels and the weights of
    the taps on the sample's side: ``[(light, rows (M,), side weights (M, 4)), …]``."""
    from facegeo.surface.shadows import edge_weights

    if vs.face is None:
        raise InputError("shadows: the view samples lack their faces; trace them with "
                         "trace_view")
    lights = key_lights(weights, shadows.key_share, shadows.max_lights)
    if lights.size == 0 or vs.taps.size == 0:
        return []
    rays = shadows.rays
    used = vs.taps >= 0
    tex, inv = np.unique(vs.taps[used], return_inverse=True)
    t_pts = shadows.texels.take(tex)
    codes = np.zeros(vs.taps.shape, np.uint8)
    edges = []
    for light in lights:
        kw = shadows.light(int(light))
        code = np.where(rays.lit(t_pts, **kw), 1, 2).astype(np.uint8)
        code[~t_pts.ok] = 0
        codes[used] = code[inv]
        mixed = np.flatnonzero(np.bitwise_or.reduce(codes, axis=1) == 3)
        if mixed.size == 0:
            continue
        # the samples' own points (lifted shadow-ray origins) only where the taps are mixed
        pts = rays.points(vs.face[mixed], vs.bary[mixed])
        local, w = edge_weights(rays, pts, np.arange(mixed.size), vs.tap_weight[mixed],
                                codes[mixed], min_cos=shadows.min_cos, **kw)
        if local.size:
            edges.append((int(light), mixed[local], w))
    return edges


def pixel_sample_rays(camera, supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Rays through s × s regular sub-pixel samples of every pixel (s = 1: the pixel centres).

    Returns
    -------
    origins, directions : (H·W·s², 3) float64, world frame
        Row-major over pixels, the s² sub-samples of a pixel consecutive (row-major within the
        pixel); directions NaN where the camera's undistortion did not converge.
    """
    s = int(supersample)
    if s == 1:
        o, d = camera.pixel_rays()
    else:
        off = (np.arange(s) + 0.5) / s - 0.5
        ox, oy = np.meshgrid(off, off)
        sub = np.stack([ox.ravel(), oy.ravel()], axis=-1)
        o, d = camera.pixel_rays(camera.pixel_grid()[:, :, None, :] + sub[None, None])
    return o.reshape(-1, 3), d.reshape(-1, 3)


def trace_view(camera, scene, atlas, texels, *, supersample: int = 1) -> ViewSamples:
    """Primary rays of ``camera`` → surface points → bilinear texel taps (see module docstring).

    Parameters
    ----------
    camera : facegeo.geometry.camera.Camera
    scene : RayScene
        Over ``atlas.vertices`` / ``atlas.faces`` (:func:`atlas_scene`).
    atlas : facegeo.surface.atlas.Atlas
    texels : facegeo.surface.atlas.Texels
    supersample : int ≥ 1
        s × s rays per pixel on a regular sub-pixel grid (box filter).

    Returns
    -------
    ViewSamples
    """
    s = int(supersample)
    if s < 1 or s != supersample:
        raise InputError(f"supersample: expected an integer >= 1, got {fmt_value(supersample)}")
    if scene.n_faces != len(atlas.faces):
        raise ShapeError(f"scene: {scene.n_faces} faces, but the atlas has {len(atlas.faces)}; "
                         "build it with atlas_scene(atlas)")
    h, w = camera.height, camera.width
    o, d = pixel_sample_rays(camera, s)
    finite = np.flatnonzero(np.isfinite(d).all(axis=1))
    hits = scene.closest_hit(o[finite], d[finite], t_min=0.0)
    sel = np.flatnonzero(hits.hit)
    idx = finite[sel].astype(np.int64)
    face = hits.face[sel]
    bary = hits.bary[sel]
    p = hits.point[sel]
    v = camera.center_world[None, :] - p
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    uv = np.einsum("pk,pkc->pc", bary, atlas.uv[atlas.faces[face]])
    H, W = texels.shape
    x = uv[:, 0] * W - 0.5
    y = (1.0 - uv[:, 1]) * H - 0.5
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    cols = np.stack([x0, x0 + 1, x0, x0 + 1], axis=1)
    rows = np.stack([y0, y0, y0 + 1, y0 + 1], axis=1)
    wts = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
    inside = (cols >= 0) & (cols < W) & (rows >= 0) & (rows < H)
    taps = np.where(inside, texels.index_map[rows.clip(0, H - 1), cols.clip(0, W - 1)], -1)
    ok = taps >= 0
    spacing = 1.0 / max(float(atlas.texels_per_metre), 1e-12)
    dist = np.linalg.norm(texels.p_world[np.where(ok, taps, 0)] - p[:, None, :], axis=2)
    ok &= dist <= TAP_MAX_TEXELS * spacing
    wts = np.where(ok, wts, 0.0)
    # a centre exactly on a tap gives that tap weight 1 and its neighbours 0: keep it
    tot = wts.sum(axis=1, keepdims=True)
    wts = np.where(tot > 0, wts / np.where(tot > 0, tot, 1.0), 0.0)
    taps = np.where(wts > 0, taps, -1)
    return ViewSamples(camera.name, (h, w), s * s, idx, p, v, taps, wts,
                       face.astype(np.int64), bary)


def load_sources(project_dir, fit_dir=None, *, cameras=None) -> list[SourceCamera]:
    """The source cameras of a ``project`` stage folder (and their fits from ``fit_dir``).

    Parameters
    ----------
    project_dir : path — ``out/project`` (``<camera>/R.npy``, ``texel_index.npy`` …)
    fit_dir : path, optional — ``out/fit`` (``<camera>/fit.npz``); None: no fits (naive only)
    cameras : list of str, optional — default every camera folder with a field
    """
    from facegeo.render._fitstore import FitStore
    from facegeo.surface.reflectance import field_folders, open_field

    project_dir = Path(project_dir)
    fit_dir = None if fit_dir is None else Path(fit_dir)
    dirs = field_folders(project_dir)  # R.npy or R.zarr
    if cameras is not None:
        known = {p.name: p for p in dirs}
        missing = [c for c in cameras if c not in known]
        if missing:
            raise InputError(f"{project_dir}: no projected field for cameras {missing}; it has "
                             f"{sorted(known)}")
        dirs = [known[c] for c in cameras]
    if not dirs:
        raise InputError(f"{project_dir}: no projected fields (<camera>/R.npy); run "
                         "'facegeo reconstruct SCAN' first")
    out = []
    for d in dirs:
        R = open_field(d)
        idx = np.load(d / "texel_index.npy").astype(np.int64)
        wt = np.load(d / "weight.npy")
        v = np.load(d / "v_world.npy")
        if R.shape[0] != idx.size or wt.shape != idx.shape or v.shape != (idx.size, 3):
            raise InputError(f"{d}: R.npy {R.shape}, texel_index.npy {idx.shape}, weight.npy "
                             f"{wt.shape} and v_world.npy {v.shape} disagree (re-run the projection)")
        if idx.size > 1 and np.any(np.diff(idx) <= 0):
            raise InputError(f"{d}/texel_index.npy: expected increasing texel indices")
        fit = FitStore.load(fit_dir / d.name) if fit_dir is not None else None
        out.append(SourceCamera(d.name, idx, wt, v, R, fit))
    return out


def _check_weights(weights, n_lights):
    w = as_array(weights, "weights", shape=(n_lights, 3))
    return w


def _lights_with_energy(sources, weights):
    """``L``, the checked ``(L, 3)`` weights, the indices of the lights with non-zero weight and
    their weights (only those lights are resynthesised)."""
    if not sources:
        raise InputError("sources: no source cameras")
    L = sources[0].field.shape[1]
    w = _check_weights(weights, L)
    active = np.flatnonzero(np.any(w != 0, axis=1))
    return L, w, active, w[active]


def _relight_matrix(w) -> np.ndarray:
    """Eq. (4) as one matrix product: ``(3L, 3)`` float64 ``W`` with ``W[3l + c, c] = w[l, c]``,
    so that ``R.reshape(n, 3L) @ W = Σ_l R[:, l, :] ⊙ w_l`` (BLAS; lights without energy
    contribute exact zeros)."""
    L = w.shape[0]
    W = np.zeros((L, 3, 3))
    W[:, np.arange(3), np.arange(3)] = w
    return W.reshape(3 * L, 3)


def _relight(R, W) -> np.ndarray:
    """Eq. (4) of the functions ``R`` ``(n, L, 3)``: ``(n, 3)`` float64, non-finite where a
    sample is (NaN · 0 stays NaN, so a row with any non-finite sample is caught). A float32
    product (BLAS sgemm: no float64 copy of the functions; relative rounding ≈ 1e-7 per
    term, well inside the float32 colours it produces)."""
    R = np.asarray(R, np.float32)
    return (R.reshape(R.shape[0], -1) @ W.astype(np.float32)).astype(np.float64)


def _stored_half(field) -> bool:
    """Whether the field is stored as ``(T, L, 3)`` float16 (read from its bits by the
    compiled passes)."""
    return field.dtype == np.float16 and field.ndim == 3 and field.shape[2] == 3


def _naive_rows(field, rows, W, w):
    """Eq. (4) of field rows, ``(n, 3)`` float64, and which rows are finite: from the float16
    bits in one compiled pass (:func:`facegeo.appearance._skin_resynth.relight_stored`, the
    naive value the fused pass gives, float64 sums), else :func:`_relight`."""
    if _stored_half(field):
        from facegeo.appearance._skin_resynth import relight_stored

        return relight_stored(field, rows, w)
    out = _relight(field[rows], W)
    return out, np.isfinite(out).all(axis=1)


def _check_light_step(light_step, lights) -> int:
    from facegeo.appearance._skin_resynth import check_light_step

    return check_light_step(light_step, lights)


def cross_validated_shrinkage(sources, weights, lights, *,
                              max_functions: int = SHRINK_FUNCTIONS,
                              light_step: int = 1) -> tuple[dict, dict]:
    """λ_c per source camera: the share of the resynthesised change that the other cameras confirm.

    For each source camera c with a fit and each other source camera b, over an even subset of
    the texels c fitted and b measured (at most ``max_functions`` per pair): c's functions
    resynthesised for b's view directions (§4.3, Eq. 9) and relit (Eq. 4, ``weights``) give the
    predicted value ``p``; c's measured functions relit give the naive value ``q``; b's measured
    functions relit give what was captured, ``m``. λ_c is the least-squares factor of
    ``q + λ (p − q) ≈ m`` over all those texels and channels,

        λ_c = clip(Σ (p − q)·(m − q) / Σ |p − q|², 0, 1),

    an estimate of how much of the view change the model predicts is real (a deviation from the
    paper: see the module docstring). Texels where the fitted normal puts b's view below the
    horizon keep ``p = q`` (as the renderer does). Noise in b's measurement is independent of
    ``p − q`` and does not bias λ.

    Parameters
    ----------
    sources : list of SourceCamera — with fits (``fit`` not None) for the cameras to estimate
    weights : (L, 3) float — Eq. (4) weights of the environment the render uses
    lights : LightSet — the fits' light set
    max_functions : int ≥ 1
    light_step : int — resynthesise on a grid this many times coarser, as the render does
        (:func:`shade_texels`)

    Returns
    -------
    factors : dict str -> float — λ_c for every camera with a fit (1.0 where no other camera
        measured any of its fitted texels: nothing to cross-validate, the paper's resynthesis)
    stats : dict str -> dict — per camera ``functions``, ``pairs`` and the cross-validation's
        relative RMSE against ``m`` of the naive value, the full resynthesis and the shrunk one
        (``xval_rel_rmse_naive``, ``_resynthesis``, ``_shrunk``; the last is in-sample: λ was
        fitted on the same texels)
    """
    if int(max_functions) < 1:
        raise InputError(f"max_functions: expected an integer >= 1, got {fmt_value(max_functions)}")
    L, w, active, w_act = _lights_with_energy(sources, weights)
    step = _check_light_step(light_step, lights)
    W = _relight_matrix(w)
    chunk = max(16, CHUNK_SAMPLES // max(L, 1))
    factors: dict[str, float] = {}
    stats: dict[str, dict] = {}
    for src in sources:
        if src.fit is None:
            continue
        fitted = src.fit.texel_index[src.fit.params["valid"].astype(bool)]
        sums = np.zeros(5)  # Σ(p−q)(m−q), Σ|p−q|², Σ|q−m|², Σ|p−m|², Σ|m|²
        n_fun, pairs = 0, []
        for other in sources:
            if other is src or active.size == 0:
                continue
            rows_o, seen = other.rows_of(fitted)
            tex = fitted[seen]
            rows_o = rows_o[seen]
            if tex.size == 0:
                continue
            pick = even_subset(tex.size, int(max_functions))
            tex, rows_o = tex[pick], rows_o[pick]
            rows_s, _ = src.rows_of(tex)
            fidx, _ = src.fit.locate(rows_s)
            pairs.append(other.name)
            fused = FUSED_READ and src.fit.uses_stored_kernel(src.field, lights)
            n_chunk = STORED_CHUNK if fused else chunk
            for c0 in range(0, tex.size, n_chunk):
                sl = slice(c0, min(tex.size, c0 + n_chunk))
                vb = other.v_world[rows_o[sl]]
                m, ok = _naive_rows(other.field, rows_o[sl], W, w)
                if fused:  # as shade_texels: one compiled pass over the float16 storage
                    q, p, ok_q, back = src.fit.relit_rows(src.field, rows_s[sl], fidx[sl],
                                                          np.ones(vb.shape[0], bool), vb, w,
                                                          lights, step)
                    ok &= ok_q
                    q, p, m, back = q[ok], p[ok], m[ok], back[ok]
                else:
                    q, ok_q = _naive_rows(src.field, rows_s[sl], W, w)
                    ok &= ok_q
                    if not ok.any():
                        continue
                    R = np.asarray(src.field[rows_s[sl][ok]], np.float32)
                    q, m = q[ok], m[ok]
                    fit = src.fit.skin_fit(fidx[sl][ok], R, lights)
                    p, back = _resynthesize_relit(fit, vb[ok], w, active, w_act,
                                                  light_step=step)
                if not ok.any():
                    continue
                p = np.where(back[:, None], q, p)
                d = p - q
                sums += [float((d * (m - q)).sum()), float((d * d).sum()),
                         float(((q - m) ** 2).sum()), float(((p - m) ** 2).sum()),
                         float((m * m).sum())]
                n_fun += int(ok.sum())
        if n_fun == 0 or sums[1] <= 0.0:
            factors[src.name] = 1.0
            stats[src.name] = {"functions": n_fun, "pairs": pairs, "lambda": 1.0,
                               "reason": "no other camera measured its fitted texels"
                               if n_fun == 0 else "resynthesis changes nothing"}
            continue
        lam = float(np.clip(sums[0] / sums[1], 0.0, 1.0))
        # Σ|q + λd − m|² = Σ|q−m|² + 2λ Σ d(q−m) + λ² Σ|d|²
        shrunk = sums[2] - 2.0 * lam * sums[0] + lam * lam * sums[1]
        den = max(sums[4], 1e-300)
        factors[src.name] = lam
        stats[src.name] = {"functions": n_fun, "pairs": pairs, "lambda": round(lam, 6),
                           "xval_rel_rmse_naive": round(float(np.sqrt(sums[2] / den)), 6),
                           "xval_rel_rmse_resynthesis": round(float(np.sqrt(sums[3] / den)), 6),
                           "xval_rel_rmse_shrunk": round(float(np.sqrt(max(shrunk, 0.0) / den)),
                                                         6)}
    return factors, stats


def even_subset(n: int, k: int | None) -> np.ndarray:
    """At most ``k`` indices of ``range(n)`` spread evenly, increasing (all when ``k`` is None
    or ≥ n); used for the shrinkage's samples and the fit stage's subsets."""
    if k is None or k >= n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, int(k)).round().astype(np.int64))


def shade_texels(texel_ids, p_world, center_world, sources, weights, lights, *,
                 resynthesis: bool = True, blend_power: float = BLEND_POWER,
                 shrinkage=None, light_step: int = 1, stats: dict | None = None,
                 shrinkage_set=None):
    """Relit radiance of texels seen from a camera centre, blended over source cameras.

    Parameters
    ----------
    texel_ids : (K,) int64 — the texels to shade
    p_world : (K, 3) float64, metres — their positions
    center_world : (3,) float64, metres — the novel camera's centre
    sources : list of SourceCamera
    weights : (L, 3) float — Eq. (4) light weights (δA included), in the field's units
    lights : LightSet — the light set the fits were made with (resynthesis)
    resynthesis : bool or "diffuse" — True: §4.3 resynthesis; False: the naive baseline
        (measured functions relit unchanged); ``"diffuse"``: an ablation, not the paper —
        the diffuse component resynthesised (chroma shift), the measured specular component
        kept (see docs/render.md for what it measures)
    blend_power : float — p of the view-dependent weight
    shrinkage : mapping str -> float, optional — λ_c per source camera (full resynthesis only):
        a resynthesised value becomes ``naive + λ_c (resynthesised − naive)``
        (:func:`cross_validated_shrinkage`; cameras not in the mapping: λ = 1, the paper)
    light_step : int ≥ 1 — speed against accuracy, not the paper: with k > 1 the resynthesised
        function is evaluated once per k × k block of the light grid, at the block's energy
        centroid (k² times fewer evaluations of Eq. 9 and the chroma shift:
        :func:`facegeo.appearance.skin.resynthesize_relit`); the measured lobe and the
        measured functions (the naive value, a source camera's own view) stay at full
        resolution. 1 (default): every light, the paper's resynthesis
    stats : dict, optional — filled with counts and the seconds spent reading the fields
        (``seconds_read``: rows gathered, converted to float32, relit by Eq. 4), reading the
        fits (``seconds_fit``: D, S = R − D, maps) and resynthesising
        (``seconds_resynthesis``); with the fused float16 pass (``fused_read`` True) the
        reads happen inside it and are counted in ``seconds_resynthesis``
    shrinkage_set : sequence of (mapping str -> float or None), optional — several
        ``shrinkage`` values at once (full resynthesis only; ``shrinkage`` is then ignored):
        the fields are read and the functions resynthesised once, and each value blends its
        own ``naive + λ_c (resynthesised − naive)`` (None: λ = 1, the paper; λ = 0 for every
        camera gives the naive baseline's colours exactly). For a render stage that wants
        the shrunk render, the naive baseline and the paper's λ = 1 of one view

    Returns
    -------
    colour : (K, 3) float32 — NaN where no source camera measured the texel; ``(V, K, 3)``
        with ``shrinkage_set`` (V values, in its order)
    """
    if resynthesis not in (True, False, "diffuse"):
        raise InputError(f"resynthesis: expected True, False or 'diffuse', got "
                         f"{fmt_value(resynthesis)}")
    if shrinkage_set is not None and resynthesis is not True:
        raise InputError(f"shrinkage_set: needs resynthesis=True, got resynthesis="
                         f"{fmt_value(resynthesis)}")
    sets = [shrinkage] if shrinkage_set is None else list(shrinkage_set)
    if not sets:
        raise InputError("shrinkage_set: expected at least one shrinkage (None: λ = 1)")
    V = len(sets)
    texel_ids = np.asarray(texel_ids, np.int64)
    K = texel_ids.size
    L, w, active, w_act = _lights_with_energy(sources, weights)
    step = _check_light_step(light_step, lights) if resynthesis else 1
    W = _relight_matrix(w)
    acc = np.zeros((V, K, 3))
    bsum = np.zeros(K)
    st = stats if stats is not None else {}
    st.update({"active_lights": int(active.size), "texels": int(K), "samples": 0,
               "resynthesized": 0, "unfitted": 0, "same_view": 0, "backfacing_fallback": 0,
               "light_step": step, "seconds_read": 0.0, "seconds_fit": 0.0,
               "seconds_resynthesis": 0.0})
    if K == 0 or active.size == 0:
        colour = np.where(bsum[:, None] > 0, acc, np.nan).astype(np.float32)
        return colour if shrinkage_set is not None else colour[0]
    chunk = max(16, CHUNK_SAMPLES // max(L, 1))
    c_new = np.asarray(center_world, np.float64).reshape(3)
    # pass 1 (no field reads): every camera's blend weight, so that cameras whose share of a
    # texel's blend is below BLEND_MIN_SHARE are never read or resynthesised
    plan = []
    total_b = np.zeros(K)
    for src in sources:
        rows, seen = src.rows_of(texel_ids)
        k_idx = np.flatnonzero(seen)
        rows = rows[k_idx]
        vn = c_new[None, :] - p_world[k_idx]
        vn /= np.linalg.norm(vn, axis=1, keepdims=True)
        theta = _angle(src.v_world[rows], vn)
        b = src.weight[rows].astype(np.float64) / np.maximum(theta, SAME_VIEW_RAD) ** blend_power
        plan.append((src, k_idx, rows, vn, theta < SAME_VIEW_RAD, b))
        np.add.at(total_b, k_idx, b)
    for src, k_idx, rows, vn, same, b in plan:
        keep = b >= BLEND_MIN_SHARE * total_b[k_idx]
        st["skipped_small_weight"] = st.get("skipped_small_weight", 0) + int((~keep).sum())
        k_idx, rows, vn, same, b = k_idx[keep], rows[keep], vn[keep], same[keep], b[keep]
        if k_idx.size == 0:
            continue
        st["same_view"] += int(same.sum())
        lams = [1.0 if (sh is None or resynthesis == "diffuse") else
                float(sh.get(src.name, 1.0)) for sh in sets]
        if resynthesis:
            if src.fit is None:
                raise InputError(f"camera {src.name}: resynthesis needs its skin-model fit "
                                 "(run 'facegeo fit SCAN')")
            fidx, fitted = src.fit.locate(rows)
        fused = (FUSED_READ and resynthesis is True
                 and src.fit.uses_stored_kernel(src.field, lights))
        st["fused_read"] = st.get("fused_read", False) or fused
        n_chunk = STORED_CHUNK if fused or (not resynthesis and _stored_half(src.field)) \
            else chunk
        for c0 in range(0, k_idx.size, n_chunk):
            sl = slice(c0, min(k_idx.size, c0 + n_chunk))
            t0 = time.perf_counter()
            if fused:  # read, naive value and resynthesis in one compiled pass
                want = fitted[sl] & ~same[sl]
                out, relit, ok, back = src.fit.relit_rows(src.field, rows[sl], fidx[sl], want,
                                                          vn[sl], w, lights, step)
                st["seconds_resynthesis"] += time.perf_counter() - t0
                st["samples"] += int(ok.sum())
                st["unfitted"] += int(np.count_nonzero(ok & ~fitted[sl]))
                todo = np.flatnonzero(ok & want)
                use = todo[~back[todo]]
                outs = [_shrunk(out, use, relit[use], lam, copy=V > 1) for lam in lams]
                st["resynthesized"] += int(use.size)
                st["backfacing_fallback"] += int(back[todo].sum())
            else:
                outs, ok = _read_and_resynthesize(
                    src, rows[sl], fidx[sl] if resynthesis else None,
                    fitted[sl] if resynthesis else None, same[sl], vn[sl], W, w, active, w_act,
                    lights, V, lams, resynthesis, step, st, t0)
            kk = k_idx[sl][ok]
            for v in range(V):
                acc[v, kk] += b[sl][ok, None] * outs[v][ok]
            bsum[kk] += b[sl][ok]
    with np.errstate(invalid="ignore", divide="ignore"):
        colour = np.where(bsum[:, None] > 0, acc / np.where(bsum > 0, bsum, 1.0)[:, None],
                          np.nan).astype(np.float32)
    for key in ("seconds_read", "seconds_fit", "seconds_resynthesis"):
        st[key] = round(st[key], 4)
    return colour if shrinkage_set is not None else colour[0]


def _read_and_resynthesize(src, rows, fidx, fitted, same, vn, W, w, active, w_act, lights, V,
                           lams, resynthesis, step, st, t0):
    """One chunk of :func:`shade_texels` without the fused pass (the naive baseline, the
    ``"diffuse"`` ablation, fits not stored as float16): Eq. 4 of the
    field rows (from the float16 bits as the fused pass does it, else a float32 matrix
    product), then for resynthesis the rows widened to float32, the fits read (D,
    S = R − D) and :func:`_resynthesize_relit`. Returns each shrinkage's values ``(n, 3)``
    and the rows whose samples are all finite; updates the counts and seconds in ``st``."""
    out, ok = _naive_rows(src.field, rows, W, w)
    outs = [out] * V
    st["samples"] += int(ok.sum())
    t1 = time.perf_counter()
    st["seconds_read"] += t1 - t0
    if resynthesis:
        todo = np.flatnonzero(ok & fitted & ~same)
        st["unfitted"] += int(np.count_nonzero(ok & ~fitted))
        if todo.size:
            every = todo.size == len(rows)  # no copy of the chunk when all are to do
            R = np.asarray(src.field[rows if every else rows[todo]], np.float32)
            fit = src.fit.skin_fit(fidx if every else fidx[todo], R, lights)
            t2 = time.perf_counter()
            st["seconds_fit"] += t2 - t1
            relit, back = _resynthesize_relit(fit, vn[todo], w, active, w_act,
                                              diffuse_only=resynthesis == "diffuse",
                                              light_step=step)
            st["seconds_resynthesis"] += time.perf_counter() - t2
            # the fitted normal puts v_n below the horizon while the mesh sees the
            # texel (grazing views): keep the measured function rather than black
            use = todo[~back]
            outs = [_shrunk(out, use, relit[~back], lam, copy=V > 1) for lam in lams]
            st["resynthesized"] += int(use.size)
            st["backfacing_fallback"] += int(back.sum())
    return outs, ok


def _shrunk(naive, use, relit, lam: float, *, copy: bool):
    """Relit values with rows ``use`` moved from the naive value toward the resynthesised
    one: ``naive + λ (relit − naive)`` (λ = 1: ``relit`` exactly); a copy when ``copy``."""
    out = naive.copy() if copy else naive
    out[use] = naive[use] + lam * (relit - naive[use]) if lam != 1.0 else relit
    return out


def _fill_uncovered(vs: ViewSamples, val, cov, max_px: float):
    """Give uncovered hit samples the mean colour of the nearest pixel with covered samples
    (Euclidean distance transform, OpenCV), if it lies within ``max_px`` pixels; returns the
    new values and the samples filled ``(P,)`` bool."""
    import cv2

    h, w = vs.shape
    pix = vs.pixel_index // vs.samples_per_pixel
    acc = np.zeros((h * w, 3))
    cnt = np.zeros(h * w)
    np.add.at(acc, pix[cov], val[cov])
    np.add.at(cnt, pix[cov], 1.0)
    has = cnt > 0
    miss = np.flatnonzero(~cov)
    if not has.any() or miss.size == 0:
        return val, np.zeros(cov.shape, bool)
    mean = acc / np.maximum(cnt, 1.0)[:, None]
    src = np.where(has, 0, 1).astype(np.uint8).reshape(h, w)
    dist, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, cv2.DIST_MASK_PRECISE,
                                                   labelType=cv2.DIST_LABEL_PIXEL)
    # DIST_LABEL_PIXEL numbers the zero pixels 1, 2, … in raster order
    nearest = np.flatnonzero(has)[labels.ravel() - 1]
    near = dist.ravel()[pix[miss]] <= max_px
    out = val.copy()
    out[miss[near]] = mean[nearest[pix[miss[near]]]]
    done = np.zeros(cov.shape, bool)
    done[miss[near]] = True
    return out, done


def _resynthesize_relit(fit, vn, w, active, w_act, *, diffuse_only: bool = False,
                        light_step: int = 1):
    """Eq. 4 on the functions resynthesised for v_n, ``(n, 3)``, and where the fit called v_n
    back-facing. Full resynthesis: :func:`facegeo.appearance.skin.resynthesize_relit` (fused,
    only the lights with non-zero weight, no ``(n, L, 3)`` result), on the grid
    ``light_step`` times coarser when > 1 (:func:`shade_texels`); the ``"diffuse"`` ablation
    relights :func:`_resynthesize`'s functions at the active lights."""
    from facegeo.appearance.skin import FLAG_BACKFACING, resynthesize_relit

    if diffuse_only:
        res, back = _resynthesize(fit, vn, diffuse_only=True)
        return np.einsum("nlc,lc->nc", res[:, active, :], w_act), back
    back = ((fit.flags & FLAG_BACKFACING) != 0) | (np.einsum("ni,ni->n", fit.normal, vn) <= 0)
    return resynthesize_relit(fit, vn, w, light_step=light_step), back


def _resynthesize(fit, vn, *, diffuse_only: bool = False):
    """Resynthesised functions ``(n, L, C)`` and where the fit called v_n back-facing."""
    from facegeo.appearance.skin import FLAG_BACKFACING, resynthesize

    r = resynthesize(fit, vn)
    back = (r.flags & FLAG_BACKFACING) != 0
    if diffuse_only:
        return r.diffuse + fit.specular, back
    return r.reflectance, back


def render_view(camera, scene, atlas, texels, sources, weights, lights, *,
                supersample: int = 1, resynthesis: bool = True,
                blend_power: float = BLEND_POWER, samples: ViewSamples | None = None,
                fill_px: float = 0.0, shrinkage=None, light_step: int = 1,
                shrinkage_set=None, shadows: RenderShadows | None = None,
                detail=None, detail_visibility: dict | None = None, infer: bool = False,
                light_directions=None) -> RenderResult | list[RenderResult]:
    """Render ``camera`` under Eq. (4) light ``weights`` from the measured reflectance field.

    See the module docstring for the steps (Debevec et al. 2000 §4.5).

    Parameters
    ----------
    camera : Camera — intrinsics and pose of the novel view
    scene : RayScene — over the atlas mesh (:func:`atlas_scene`)
    atlas, texels : the ``atlas`` stage's Atlas and Texels
    sources : list of SourceCamera — per-camera fields and fits (:func:`load_sources`)
    weights : (L, 3) float — Eq. (4) weights of the environment (δA included), field units
    lights : LightSet — the light set of the fits
    supersample : int — s × s rays per pixel
    resynthesis : bool or "diffuse" — False renders the naive baseline; see :func:`shade_texels`
    blend_power : float — view-dependent weight exponent
    samples : ViewSamples, optional — a :func:`trace_view` result to reuse
    fill_px : float, pixels — hit samples whose texels no camera measured take the colour of
        the nearest pixel with measured samples within this distance (0: left black); they
        stay False in ``covered`` (hole filling for display; see :func:`_fill_uncovered`)
    shrinkage : mapping str -> float, optional — λ per source camera (:func:`shade_texels`)
    light_step : int — resynthesis on a k times coarser light grid (:func:`shade_texels`;
        1: every light)
    shrinkage_set : sequence of (mapping or None), optional — several shrinkages rendered
        from one pass over the fields and one resynthesis (:func:`shade_texels`): e.g.
        ``[factors, {c: 0.0 for c in cameras}, None]`` gives the shrunk render, the naive
        baseline and the paper's λ = 1 render of the view, each equal to its own
        ``render_view`` call (full resynthesis only)
    shadows : RenderShadows, optional — shadow-consistent texel taps for the environment's
        key lights (:func:`render_shadows`; module docstring, step 4); None: plain bilinear.
        Its mesh and lights must be this render's (the lights in the atlas's world frame)
    detail : sequence of SourceImage, optional — image-space detail (module docstring, step 5;
        :mod:`facegeo.render.detail`): the source cameras' captures relit with these
        ``weights``; every render of the view moves by (their per-pixel projection − the
        texture-space naive render) where both exist, so the naive baseline becomes that
        projection. None: texture space only (the paper)
    detail_visibility : dict, optional — the projection's visibility settings (``min_cos``,
        ``feather_px``, ``depth_jump``) for the source images' weights
        (:func:`facegeo.render.detail.project_source_images`); default the projection's
        defaults
    infer : bool — cover what no camera saw: every hit sample gets a value, those whose texels
        no source camera measured from their texels inferred over the surface
        (:func:`infer_texel_colours`, pull–push in space; after ``fill_px``), a sample with no
        tap on a chart from the nearest pixel with a value; marked in
        ``RenderResult.inferred``, never ``covered``. Covered pixels are the same bit for bit
        with or without it. False: such samples stay black (the paper)
    light_directions : (L, 3) float64, unit, world frame, optional — toward each light of the
        rig: with ``infer``, the inference is of colour over each texel's Lambertian
        irradiance (:func:`infer_texel_colours`); None: of colour

    Returns
    -------
    RenderResult, or a list of them (one per ``shrinkage_set`` entry, sharing the trace and
    the shading's counts and seconds)
        ``stats`` holds :func:`shade_texels`'s counts and seconds, ``seconds_trace``,
        ``seconds_shade``, ``seconds_image`` (taps → image) and the total ``seconds``; with
        ``shadows``, ``shadow_lights`` (key lights whose edges moved some sample),
        ``shadow_edge_samples`` (samples moved, summed over those lights) and
        ``seconds_shadows`` (within ``seconds_shade``); with ``detail``, ``detail_pixels``
        (pixels the source images moved), ``detail_cameras``, ``detail_shadow_samples`` and
        ``seconds_detail``, and
        ``RenderResult.texture`` holds the texture-space image before the detail.
    """
    args = (camera, scene, atlas, texels, sources, weights, lights)
    kw = dict(supersample=supersample, blend_power=blend_power, fill_px=fill_px,
              light_step=light_step, shadows=shadows, infer=bool(infer),
              light_directions=light_directions)
    if detail is None:
        return _render_texture(*args, samples=samples, resynthesis=resynthesis,
                               shrinkage=shrinkage, shrinkage_set=shrinkage_set, **kw)
    from facegeo.render.detail import check_source_images, project_source_images

    detail = check_source_images(detail)
    if shrinkage_set is not None and not list(shrinkage_set):
        raise InputError("shrinkage_set: expected at least one shrinkage (None: λ = 1)")
    t0 = time.perf_counter()
    vs = samples if samples is not None else trace_view(camera, scene, atlas, texels,
                                                         supersample=supersample)
    t_trace = time.perf_counter() - t0  # the texture pass gets the samples traced
    single = shrinkage_set is None
    if resynthesis is True:  # the naive render (λ = 0) from the same pass
        sets = ([shrinkage] if single else list(shrinkage_set)) + \
            [{src.name: 0.0 for src in sources}]
        got = _render_texture(*args, samples=vs, resynthesis=True, shrinkage=None,
                              shrinkage_set=sets, **kw)
        results, naive = got[:-1], got[-1]
    else:
        results = [_render_texture(*args, samples=vs, resynthesis=resynthesis,
                                   shrinkage=shrinkage, shrinkage_set=shrinkage_set, **kw)]
        naive = results[0] if resynthesis is False else _render_texture(
            *args, samples=vs, resynthesis=False, shrinkage=None, shrinkage_set=None, **kw)
    t_naive = naive.stats["seconds"] if resynthesis == "diffuse" else 0.0  # its own pass
    t1 = time.perf_counter()
    st: dict = {}
    d_img = vs.to_image(project_source_images(vs, detail, scene, atlas, blend_power=blend_power,
                                              weights=weights, shadows=shadows,
                                              visibility=detail_visibility, stats=st),
                        fill=np.nan)
    use = naive.covered & np.isfinite(d_img).all(axis=2)
    delta = np.where(use[..., None], d_img - naive.image, 0.0).astype(np.float32)
    st["detail_pixels"] = int(use.sum())
    t_detail = time.perf_counter() - t1  # the projection, its image and the difference
    for r in results:
        r.texture = r.image
        r.image = r.image + delta
        r.stats.update(st)
        r.stats["seconds_trace"] = round(r.stats["seconds_trace"] + t_trace, 4)
        r.stats["seconds"] = round(r.stats["seconds"] + t_trace + t_naive + t_detail, 4)
    return results[0] if single else results


def _render_texture(camera, scene, atlas, texels, sources, weights, lights, *, supersample,
                    resynthesis, blend_power, samples, fill_px, shrinkage, light_step,
                    shrinkage_set, shadows, infer=False, light_directions=None):
    """:func:`render_view` in texture space only (no ``detail``)."""
    t0 = time.perf_counter()
    vs = samples if samples is not None else trace_view(camera, scene, atlas, texels,
                                                         supersample=supersample)
    t1 = time.perf_counter()
    need = vs.needed_texels
    stats: dict = {}
    # with infer and resynthesis, the naive colours (λ = 0) from the same pass: what the
    # texels no camera measured are inferred from, in every render (infer_texel_colours)
    with_naive = bool(infer) and resynthesis is True
    sets = shrinkage_set
    if with_naive:
        sets = ([shrinkage] if shrinkage_set is None else list(shrinkage_set)) \
            + [{src.name: 0.0 for src in sources}]
    colour = shade_texels(need, texels.p_world[need], camera.center_world, sources, weights,
                          lights, resynthesis=resynthesis, blend_power=blend_power,
                          shrinkage=None if with_naive else shrinkage, light_step=light_step,
                          stats=stats, shrinkage_set=sets)
    base = None
    if with_naive:
        base = colour[-1]
        colour = colour[:-1] if shrinkage_set is not None else colour[0]
    edges = []
    if shadows is not None:
        _check_shadows(shadows, scene, texels, weights)
        # per key light: the samples across its cast-shadow edges, and the texels they read
        # relit by that light alone (Eq. 4 is linear in the weights; λ_c and the blend are
        # the environment's), for the correction Σ_k (b_k(l) − b_k) C_k(l) of _view_image
        ts = time.perf_counter()
        n_rows = 0
        for light, rows, w_side in _shadow_edges(vs, shadows, weights):
            tex = np.unique(vs.taps[rows][vs.taps[rows] >= 0])
            w_one = np.zeros_like(np.asarray(weights, np.float64))
            w_one[light] = np.asarray(weights, np.float64)[light]
            one = shade_texels(tex, texels.p_world[tex], camera.center_world, sources, w_one,
                               lights, resynthesis=resynthesis, blend_power=blend_power,
                               shrinkage=shrinkage, light_step=light_step,
                               shrinkage_set=shrinkage_set)
            edges.append((rows, w_side, tex, one))
            n_rows += rows.size
        stats.update({"shadow_lights": len(edges), "shadow_edge_samples": int(n_rows),
                      "seconds_shadows": round(time.perf_counter() - ts, 4)})
    inferred = [None] * (1 if shrinkage_set is None else len(colour))
    if infer:
        ti = time.perf_counter()
        cols = colour[None] if shrinkage_set is None else colour
        src_col = cols[-1:] if base is None else base[None]
        shading = None
        if light_directions is not None and not np.isfinite(src_col).all():
            shading = lambert_irradiance(texels.n_world[need], light_directions, weights,
                                         p_world=texels.p_world[need],
                                         scene=scene)
        filled, miss = infer_texel_colours(texels, need, src_col, shading=shading)
        inferred = cols.copy()
        inferred[:, miss] = filled[0, miss]
        stats.update({"texels_inferred": int(miss.sum()),
                      "seconds_infer": round(time.perf_counter() - ti, 4)})
    t2 = time.perf_counter()
    if shrinkage_set is None:
        return _view_image(vs, need, colour, fill_px, stats, t0, t1, t2, edges, inferred[0])
    return [_view_image(vs, need, c, fill_px, dict(stats), t0, t1, t2,
                        [(r, ws, tx, one[v]) for r, ws, tx, one in edges], inferred[v])
            for v, c in enumerate(colour)]


def _view_image(vs: ViewSamples, need, colour, fill_px, stats, t0, t1, t2,
                edges=(), inferred_colour=None) -> RenderResult:
    """:func:`render_view`'s last step: texel colours → tap-weighted pixel samples → image,
    with ``covered``, hole filling and the timings (``t0``–``t2``: start, traced, shaded).

    ``inferred_colour`` ``(K, 3)``: ``colour`` with the texels no camera measured inferred
    (:func:`infer_texel_colours`); given, every hit sample gets a value: covered samples keep
    theirs (bit for bit), then ``fill_px``, then the inferred texels, then the nearest pixel
    with a value at any distance (a sample with no tap on a chart). The pixels holding such a
    sample are ``RenderResult.inferred``.

    ``edges``: per key light ``(rows, side weights (M, 4), texels, their colours under that
    light alone (T, 3))``; a row's value moves by ``Σ_k (b_k(l) − b_k) C_k(l)``, with b(l)
    the side weights and b the plain ones, both over the taps with a colour, renormalised."""
    pos = np.searchsorted(need, np.where(vs.taps >= 0, vs.taps, 0))
    pos = np.minimum(pos, max(need.size - 1, 0))
    tap_col = colour[pos] if need.size else np.full(vs.taps.shape + (3,), np.nan, np.float32)
    good = (vs.taps >= 0) & np.isfinite(tap_col).all(axis=2)
    wt = np.where(good, vs.tap_weight, 0.0)
    tot = wt.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        val = np.einsum("pk,pkc->pc", wt, np.where(good[..., None], tap_col, 0.0)) / \
            np.where(tot > 0, tot, 1.0)[:, None]
    cov = tot > 0
    for rows, w_side, tex, one in edges:
        pos_l = np.minimum(np.searchsorted(tex, np.where(vs.taps[rows] >= 0, vs.taps[rows], 0)),
                           max(tex.size - 1, 0))
        c_l = one[pos_l]
        g = good[rows] & np.isfinite(c_l).all(axis=2)
        new = np.where(g, w_side, 0.0)
        t_new = new.sum(axis=1)
        # a tap with a colour but none under the light alone: leave the row as it is
        ok = (t_new > 0) & cov[rows] & ~(good[rows] & ~g).any(axis=1)
        old = wt[rows] / np.where(tot[rows] > 0, tot[rows], 1.0)[:, None]
        delta = new / np.where(t_new > 0, t_new, 1.0)[:, None] - old
        corr = np.einsum("mk,mkc->mc", delta, np.where(g[..., None], c_l, 0.0))
        val[rows[ok]] += corr[ok]
    val = np.where(cov[:, None], val, 0.0).astype(np.float32)
    filled = np.zeros(cov.shape, bool)
    if fill_px > 0:
        val, filled = _fill_uncovered(vs, val, cov, float(fill_px))
    from_texels = np.zeros(cov.shape, bool)
    nearest = np.zeros(cov.shape, bool)
    if inferred_colour is not None:
        # samples no measured tap reached: their inferred texels (pull–push over the surface,
        # infer_texel_colours), then whatever has no tap on a chart the nearest pixel's colour
        todo = np.flatnonzero(~cov & ~filled)
        if todo.size and need.size:
            c_i = inferred_colour[pos[todo]]
            g = (vs.taps[todo] >= 0) & np.isfinite(c_i).all(axis=2)
            w_i = np.where(g, vs.tap_weight[todo], 0.0)
            t_i = w_i.sum(axis=1)
            ok = t_i > 0
            v_i = np.einsum("pk,pkc->pc", w_i[ok], np.where(g[ok][..., None], c_i[ok], 0.0)) \
                / t_i[ok, None]
            val[todo[ok]] = v_i
            from_texels[todo[ok]] = True
        if not (cov | filled | from_texels).all():
            val, nearest = _fill_uncovered(vs, val, cov | filled | from_texels, np.inf)
    image = vs.to_image(val)
    covered = vs.to_image(cov.astype(np.float32)) >= 1.0 - 1e-6
    inferred = vs.to_image((~cov & (filled | from_texels | nearest)).astype(np.float32)) > 0
    stats["samples_filled"] = int(filled.sum())
    if inferred_colour is not None:
        stats["samples_inferred_texels"] = int(from_texels.sum())
        stats["samples_inferred_nearest"] = int(nearest.sum())
    stats.update({"pixels": int(vs.shape[0] * vs.shape[1]),
                  "samples_hit": int(vs.pixel_index.size),
                  "samples_covered": int(cov.sum()),
                  "seconds_trace": round(t1 - t0, 4), "seconds_shade": round(t2 - t1, 4),
                  "seconds_image": round(time.perf_counter() - t2, 4),
                  "seconds": round(time.perf_counter() - t0, 4)})
    return RenderResult(image, covered & vs.mask, vs.mask, stats,
                        inferred=inferred & vs.mask)
