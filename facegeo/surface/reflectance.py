"""Per-camera visibility of atlas texels and projection of OLAT frames onto them.

The surface reflectance field (Debevec et al. 2000, §2.1) is measured camera by camera: each
camera pixel's reflectance function ``R_xy(θ, φ) = L_θφ(x, y)`` (Eq. 2, §3.2) is carried onto
the surface point the pixel sees. Here the surface points are atlas texels
(:mod:`facegeo.surface.atlas`); for camera ``c`` the field is ``R_c[texel, light, rgb]``, with a
weight ``w_c[texel]`` and a view direction ``v_c[texel]``.

Visibility (:func:`camera_visibility`)
--------------------------------------
A texel is visible in camera ``c`` when

1. it projects in front of the camera, inside the lens model's valid region (``Camera.project``'s
   mask) and far enough inside the image that all four bilinear taps exist
   (``0 <= x <= W − 1``, ``0 <= y <= H − 1``);
2. it faces the camera: both the geometric and the interpolated normal have ``n·v > min_cos``
   (default 0.1, i.e. views within ≈ 84° of the normal);
3. nothing blocks the segment from the texel to the camera centre (Embree occlusion,
   :meth:`~facegeo.surface.visibility.RayScene.occluded`, the origin offset ``eps`` along the
   *geometric* normal so the ray never hits its own triangle — DESIGN §7's terminator case —
   and ``eps`` excluded at both ends, as in ``RayScene.segment_visible``).

Weights (view-dependent texture mapping, course notes §"VDTM": "the contribution of each input
pixel ... should be weighted so that pixels viewed at oblique angles contribute less ... the dot
product between the camera viewing direction and the surface normal", and "the pixel weights are
ramped down near the boundary of the projected images")::

    w_c = (n · v) · s(d_edge / feather_px)

with ``s`` the smoothstep on [0, 1] and ``d_edge`` the distance in pixels from the texel's
projection to the nearest silhouette or occlusion edge of the camera's depth image, or to the
image border. Depth edges are pixels whose 4-neighbour sees background, or a surface deeper or
shallower by more than ``max(depth_jump, jump_px · z / f)`` — the second term is ``jump_px``
pixel footprints, so a smooth surface seen at up to atan(jump_px) ≈ 85° from its normal (what
``min_cos`` still lets through) never counts as an edge on a coarse camera. The depth image is
traced with pixel-centre rays of the camera's *pinhole* part (same K and pose, no distortion)
and the texel's edge distance is read at its pinhole projection: distortion only moves pixels by
a smooth 1-to-1 map, so the distance is off by the local scale of the distortion (< 2 % on
these lenses). The weight depends
on geometry only, so it is **identical for every light** and relighting stays linear.

Occlusion is decided by a z-buffer pre-pass by default (``occlusion="zbuffer"``,
:mod:`facegeo.surface.zbuffer`): ``cv2.triangleRasterizeDepth`` renders the pinhole camera's
depth with our K exactly (vertices pre-transformed so its symmetric frustum reproduces fx ≠ fy
and the off-centre principal point); texels whose 3 × 3 pixel neighbourhood agrees with their
own depth are visible, those covered by nearer surface are occluded, and only the ambiguous
rest (edges, grazing views) get the exact ray of 3. The same buffer is the depth image of the
weights. ``occlusion="rays"`` traces every candidate and the depth image (the reference).

Projection (:func:`project_camera`)
-----------------------------------
Every OLAT frame is sampled at the visible texels' projected positions by bilinear
interpolation with ``cv2.remap`` (``INTER_LINEAR``; the float32 maps are built once per camera,
folded into rows of 16,384 texels). With float maps and float32 frames OpenCV 5 interpolates at
the exact float32 position (measured: a linear ramp is reproduced with zero error at random
positions), and it is ≈ 9× faster than a numpy gather of precomputed taps
(:func:`bilinear_taps`, kept as the plain reference implementation the tests compare against).
Bilinear is kept on purpose: the synthetic frames are point samples at pixel centres, and
where a cast-shadow edge runs between two pixel centres at an unknown position the bilinear
value is the conditional mean of the truth. On the small preset bicubic measured 2.94 % and
nearest 4.29 % against bilinear's 2.85 %, and shifting the positions by 0.25 px made it worse
(docs/surface.md, "Where the small preset's projection error comes from"). The edge's
position is not unknown to the geometry, though: with ``shadows``
(:mod:`facegeo.surface.shadows`) a sample whose taps mix lit and shadowed pixels is read from
the taps on its texel's side only (small preset, ground-truth mesh: 3.10 → 1.40 %).

The validity mask is remapped the same way (as a float image of the *invalid* pixels): a sample
with any weight on a masked pixel (whatever the caller's mask holds: the project stage masks
saturated and non-finite pixels, and counts black-clipped ones as the measured dark values they
are — docs/scan-format.md) is stored as NaN — never trusted, never a fake value — while the
texel's weight stays light-independent.

Transpose strategy and memory: a frame is one light for all texels, the on-disk field is chunked
along texels (``(T_c, L, 3)`` C order, each texel's function contiguous). Frames are gathered
frame-major into a float32 block of ``block_lights`` lights (``B × T_c × 3 × 4`` bytes, 154 MB
for 200 k texels and B = 64; each sampled frame is one contiguous write), which is transposed
into the memory-mapped ``.npy`` in steps of 4,096 texels (each texel's B lights contiguous on
disk, ``B × 3 × 2`` bytes); each step's pages are flushed and released from the process
(``madvise(MADV_DONTNEED)``) at once — a texel-major write touches a page of every texel, and
file-backed pages count as resident — so resident memory stays at one block plus one frame
whatever L and T_c are. :func:`iter_field_chunks` releases the pages it read the same way. Writing every frame straight into the texel-major file (B = 1) touches every page of the
field once per light and measured 2.9× slower (``facegeo bench surface.project``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from facegeo.checks import as_array, check_positive_int, fmt_value
from facegeo.errors import InputError, ShapeError
from facegeo.surface._blend import (
    BLENDED_FILE,
    BlendedField,
    blend_block,
    blend_compiled,
    blend_fields,
    blend_rows_task,
    blend_sources,
    blend_weights,
    open_blended,
    save_blend_index,
)
from facegeo.surface._field_io import (
    _chunk_rows,
    _release_rows,
    has_field,
    open_field,
)
from facegeo.surface._zarr_field import (
    DEFAULT_FIELD_FORMAT,
    FIELD_FORMATS,
    create_field,
    field_chunk_bounds,
    field_location,
    find_field,
    open_zarr_field,
    write_field,
    write_field_chunk,
)

log = logging.getLogger(__name__)

__all__ = [
    "CameraVisibility", "ProjectedField", "FrameSampler", "camera_visibility", "depth_image",
    "bilinear_taps", "frame_sampler", "sample_frame", "sample_olat_frame", "fill_light_columns",
    "sample_taps",
    "project_camera",
    "open_field", "has_field", "field_folders", "iter_field_chunks", "gather_field_samples",
    "FIELD_FORMATS", "DEFAULT_FIELD_FORMAT", "create_field", "field_chunk_bounds",
    "field_location", "find_field", "open_zarr_field", "write_field", "write_field_chunk",
    "BlendedField", "blend_fields", "open_blended", "blend_sources", "blend_block",
    "blend_compiled", "blend_weights", "blend_rows_task", "save_blend_index",
    "BLENDED_FILE", "DEFAULT_MIN_COS", "DEFAULT_FEATHER_PX",
    "DEFAULT_DEPTH_JUMP", "DEFAULT_JUMP_PX", "DEFAULT_BLOCK_LIGHTS", "OCCLUSION_METHODS",
]

#: Facing threshold on n·v (both normals): ≈ 84° from the normal.
DEFAULT_MIN_COS = 0.1
#: Weight ramps from 0 at a silhouette/occlusion edge or the image border to full over this.
DEFAULT_FEATHER_PX = 3.0
#: Depth step (metres) between neighbouring pixels that counts as an occlusion edge ...
DEFAULT_DEPTH_JUMP = 0.005
#: ... and at least this many pixel footprints (z / f): tan(85°) ≈ 11.4.
DEFAULT_JUMP_PX = 12.0
#: Lights gathered in RAM before one strided write to the on-disk field.
DEFAULT_BLOCK_LIGHTS = 64
#: How camera_visibility decides occlusion: a z-buffer pre-pass with rays where ambiguous,
#: or a ray for every candidate texel (the reference).
OCCLUSION_METHODS = ("zbuffer", "rays")
_F16_MAX = float(np.finfo(np.float16).max)
#: Texels per step of the blocked transpose from frame-major RAM to texel-major disk.
_TRANSPOSE_TEXELS = 4096


@dataclass
class CameraVisibility:
    """Which texels one camera sees, and how much each measurement is trusted.

    Attributes
    ----------
    camera : str
    q : (T, 2) float64, pixels
        Projection of every texel (NaN behind the camera).
    v_world : (T, 3) float64, unit, world frame
        Direction from each texel toward the camera centre.
    in_image : (T,) bool
        In front, inside the lens model's valid region, all four bilinear taps in the image.
    facing : (T,) bool
        Both normals have ``n·v > min_cos``.
    unoccluded : (T,) bool
        Nothing blocks the segment to the camera centre (only traced where ``in_image &
        facing``; False elsewhere).
    cos_view : (T,) float64
        ``n_world · v_world`` (interpolated normal).
    edge_px : (T,) float32, pixels
        Distance to the nearest silhouette/occlusion edge or image border (NaN where not
        ``in_image``).
    weight : (T,) float32
        ``cos_view · smoothstep(edge_px / feather_px)`` where visible, 0 elsewhere.
    """

    camera: str
    q: np.ndarray
    v_world: np.ndarray
    in_image: np.ndarray
    facing: np.ndarray
    unoccluded: np.ndarray
    cos_view: np.ndarray
    edge_px: np.ndarray
    weight: np.ndarray

    @property
    def visible(self) -> np.ndarray:
        """(T,) bool: in image, facing and unoccluded."""
        return self.in_image & self.facing & self.unoccluded

    @property
    def visible_fraction(self) -> float:
        """Fraction of all texels visible (0 for an empty table)."""
        n = self.visible.size
        return float(np.count_nonzero(self.visible) / n) if n else 0.0


def _texel_arrays(texels: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    p = as_array(getattr(texels, "p_world", None), "texels.p_world", shape=(None, 3))
    n = as_array(getattr(texels, "n_world", None), "texels.n_world", shape=(len(p), 3))
    g = as_array(getattr(texels, "n_geom", None), "texels.n_geom", shape=(len(p), 3))
    return p, n, g


def depth_image(scene, camera) -> np.ndarray:
    """Depth ``z`` (metres, camera frame) along the pinhole pixel-centre rays of ``camera``.

    Parameters
    ----------
    scene : facegeo.surface.visibility.RayScene
    camera : facegeo.geometry.camera.Camera
        Its distortion is ignored (pinhole part: K and pose).

    Returns
    -------
    (H, W) float64
        NaN where the ray misses the mesh.
    """
    pin = camera.replace(dist=np.zeros_like(camera.dist))
    o, d = pin.pixel_rays()
    hits = scene.closest_hit(o.reshape(-1, 3), d.reshape(-1, 3), t_min=0.0, fields=("t",))
    d_cam = d.reshape(-1, 3) @ camera.T_cam_world.R.T
    z = hits.t * d_cam[:, 2]
    return z.reshape(camera.height, camera.width)


def _edge_distance(depth: np.ndarray, depth_jump: float, footprint: float = 0.0,
                   jump_px: float = 0.0) -> np.ndarray:
    """Distance (pixels, float32) from each pixel to the nearest depth edge (L2)."""
    import cv2

    hit = np.isfinite(depth)
    z = np.where(hit, depth, 0.0)
    edge = np.zeros(depth.shape, bool)
    for axis in (0, 1):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis] = slice(1, None)
        b[axis] = slice(None, -1)
        ha, hb = hit[tuple(a)], hit[tuple(b)]
        za, zb = z[tuple(a)], z[tuple(b)]
        limit = np.maximum(depth_jump, jump_px * footprint * np.maximum(za, zb))
        jump = (ha != hb) | (ha & hb & (np.abs(za - zb) > limit))
        edge[tuple(a)] |= jump
        edge[tuple(b)] |= jump
    src = np.where(edge, 0, 255).astype(np.uint8)
    if not edge.any():
        return np.full(depth.shape, np.inf, np.float32)
    return cv2.distanceTransform(src, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def camera_visibility(texels: Any, camera, scene, *, min_cos: float = DEFAULT_MIN_COS,
                      feather_px: float = DEFAULT_FEATHER_PX,
                      depth_jump: float = DEFAULT_DEPTH_JUMP,
                      occlusion: str = "zbuffer") -> CameraVisibility:
    """Visibility and blending weight of every texel in one camera (module docstring).

    Parameters
    ----------
    texels : facegeo.surface.atlas.Texels
        Anything with ``p_world``, ``n_world``, ``n_geom`` ``(T, 3)`` float64 arrays.
    camera : facegeo.geometry.camera.Camera
    scene : facegeo.surface.visibility.RayScene
        The mesh the texels lie on.
    min_cos : float
        Facing threshold on ``n·v`` in [0, 1).
    feather_px : float
        Width (pixels) of the weight ramp at edges; 0 disables feathering.
    depth_jump : float, metres
        Smallest depth step between neighbouring pixels counted as an occlusion edge (the
        step must also exceed ``DEFAULT_JUMP_PX`` pixel footprints).
    occlusion : {"zbuffer", "rays"}
        ``"zbuffer"``: a rasterised depth buffer of the pinhole camera
        (:mod:`facegeo.surface.zbuffer`) decides the texels it proves visible or occluded and
        serves as the depth image of the weights; only ambiguous texels get an Embree ray.
        ``"rays"``: every candidate texel gets a ray and the depth image is ray-traced (the
        reference; also used when the mesh reaches behind the camera, where the rasteriser's
        near plane would clip it).

    Returns
    -------
    CameraVisibility
    """
    p, n, g = _texel_arrays(texels)
    if not (0.0 <= float(min_cos) < 1.0):
        raise InputError(f"min_cos: expected a number in [0, 1), got {fmt_value(min_cos)}")
    if not (np.isfinite(feather_px) and feather_px >= 0):
        raise InputError(f"feather_px: expected a finite number >= 0, got {fmt_value(feather_px)}")
    if not (np.isfinite(depth_jump) and depth_jump > 0):
        raise InputError(f"depth_jump: expected a finite number > 0 (metres), got {fmt_value(depth_jump)}")
    if occlusion not in OCCLUSION_METHODS:
        raise InputError(f"occlusion: expected one of {', '.join(OCCLUSION_METHODS)}, got "
                         f"{fmt_value(occlusion)}")
    T = len(p)
    q, valid = camera.project(p)
    W, H = camera.width, camera.height
    with np.errstate(invalid="ignore"):
        in_image = (valid & (q[:, 0] >= 0) & (q[:, 0] <= W - 1)
                    & (q[:, 1] >= 0) & (q[:, 1] <= H - 1))
    c = camera.center_world
    v = c[None, :] - p
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    cos_view = np.einsum("tc,tc->t", n, v)
    cos_geom = np.einsum("tc,tc->t", g, v)
    facing = (cos_view > min_cos) & (cos_geom > min_cos)
    unoccluded = np.zeros(T, bool)
    cand = np.flatnonzero(in_image & facing)
    pin = camera.replace(dist=np.zeros_like(camera.dist))
    depth = None
    if occlusion == "zbuffer" and camera.T_cam_world.apply(scene.vertices)[:, 2].min() <= 0:
        # The rasteriser clips at a near plane: a mesh reaching behind the camera could hide an
        # occluder there, so every candidate gets its ray.
        log.info("camera %s: the mesh crosses the camera plane; occlusion by rays only",
                 camera.name)
        occlusion = "rays"
    if occlusion == "zbuffer":
        from facegeo.surface.zbuffer import classify_occlusion, depth_buffer

        depth = depth_buffer(scene.vertices, scene.faces, camera)
        if cand.size:
            sure_vis, sure_occ = classify_occlusion(
                depth, camera.T_cam_world.apply(p[cand]),
                camera.T_cam_world.apply_direction(g[cand]), camera.K)
            unoccluded[cand[sure_vis]] = True
            cand = cand[~(sure_vis | sure_occ)]  # ambiguous: an exact ray below
    if cand.size:
        # The segment texel -> camera centre, its origin lifted eps along the geometric normal
        # (the camera is on the normal's side: cos_geom > min_cos), eps excluded at both ends.
        # Same decision as RayScene.segment_visible(p, c, normals=g); calling occluded directly
        # skips its broadcasting and normal checks (measured ≈ 1.6× faster on these rays).
        eps = scene.eps
        o = p[cand] + eps * g[cand]
        d = c[None, :] - o
        length = np.sqrt(np.einsum("tc,tc->t", d, d))
        d /= length[:, None]
        far = length - eps
        long = far > 2.0 * eps
        hit = np.zeros(cand.size, bool)
        if long.any():
            hit[long] = scene.occluded(o[long], d[long], far[long], t_min=eps)
        unoccluded[cand] = ~hit
    vis = in_image & facing & unoccluded
    edge_px = np.full(T, np.nan, np.float32)
    weight = np.zeros(T, np.float32)
    idx = np.flatnonzero(in_image)
    if idx.size:
        border = np.minimum.reduce([q[idx, 0] + 0.5, W - 0.5 - q[idx, 0],
                                    q[idx, 1] + 0.5, H - 0.5 - q[idx, 1]])
        if depth is None:
            depth = depth_image(scene, camera)
        dist = _edge_distance(depth, float(depth_jump), 2.0 / (camera.fx + camera.fy),
                              DEFAULT_JUMP_PX)
        qp = pin.project(p[idx])[0]
        col = np.clip(np.rint(qp[:, 0]), 0, W - 1).astype(np.int64)
        row = np.clip(np.rint(qp[:, 1]), 0, H - 1).astype(np.int64)
        edge_px[idx] = np.minimum(border, dist[row, col])
    if feather_px > 0:
        ramp = _smoothstep(np.nan_to_num(edge_px, nan=0.0) / feather_px)
    else:
        ramp = np.ones(T)
    weight[vis] = (cos_view[vis] * ramp[vis]).astype(np.float32)
    return CameraVisibility(camera=camera.name, q=q, v_world=v, in_image=in_image,
                            facing=facing, unoccluded=unoccluded, cos_view=cos_view,
                            edge_px=edge_px, weight=weight)


def bilinear_taps(q: Any, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel indices and weights of bilinear interpolation at pixel positions.

    Parameters
    ----------
    q : (N, 2) float64, pixels (integers are pixel centres)
        Must satisfy ``0 <= x <= W − 1`` and ``0 <= y <= H − 1``.
    width, height : int

    Returns
    -------
    index : (N, 4) int64
        ``row · W + col`` of the taps (top-left, top-right, bottom-left, bottom-right).
    weight : (N, 4) float32
        Bilinear weights (computed in float64, sum 1 to float32 rounding).
    """
    q = as_array(q, "q", shape=(None, 2))
    x, y = q[:, 0], q[:, 1]
    if np.any((x < 0) | (x > width - 1) | (y < 0) | (y > height - 1)):
        raise InputError(f"q: bilinear positions must lie in [0, {width - 1}] × "
                         f"[0, {height - 1}] (all four taps inside the image)")
    x0 = np.minimum(np.floor(x), max(width - 2, 0)).astype(np.int64)
    y0 = np.minimum(np.floor(y), max(height - 2, 0)).astype(np.int64)
    fx, fy = x - x0, y - y0
    x1 = np.minimum(x0 + 1, width - 1)
    y1 = np.minimum(y0 + 1, height - 1)
    index = np.stack([y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1], 1)
    weight = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    return index, weight.astype(np.float32)


_REMAP_COLS = 1 << 14


@dataclass(frozen=True)
class FrameSampler:
    """Bilinear sampling positions of N texels in one camera, as ``cv2.remap`` maps.

    Attributes
    ----------
    map_x, map_y : (rows, 16384) float32, pixels
        Positions, padded with 0 past ``n``.
    n : int
    """

    map_x: np.ndarray
    map_y: np.ndarray
    n: int


def frame_sampler(q: Any, width: int, height: int) -> FrameSampler:
    """Sampling maps for positions ``q`` ``(N, 2)`` float64 (pixels, all four bilinear taps
    inside the ``width × height`` image: ``0 <= x <= W − 1``, ``0 <= y <= H − 1``)."""
    q = as_array(q, "q", shape=(None, 2))
    if np.any((q[:, 0] < 0) | (q[:, 0] > width - 1) | (q[:, 1] < 0) | (q[:, 1] > height - 1)):
        raise InputError(f"q: bilinear positions must lie in [0, {width - 1}] × "
                         f"[0, {height - 1}] (all four taps inside the image)")
    n = len(q)
    rows = max(1, -(-n // _REMAP_COLS))
    mx = np.zeros(rows * _REMAP_COLS, np.float32)
    my = np.zeros(rows * _REMAP_COLS, np.float32)
    mx[:n] = q[:, 0]
    my[:n] = q[:, 1]
    return FrameSampler(mx.reshape(rows, -1), my.reshape(rows, -1), n)


def sample_frame(frame: np.ndarray, sampler: FrameSampler,
                 valid: np.ndarray | None = None) -> np.ndarray:
    """Bilinear samples ``(N, 3)`` float32 of an ``(H, W, 3)`` float32 frame (``cv2.remap``).

    A sample with a non-zero weight on a pixel where ``valid`` ``(H, W)`` is False is NaN.
    Linear in ``frame`` (the interpolation weights depend on the positions only).
    """
    import cv2

    frame = np.ascontiguousarray(frame, np.float32)
    out = cv2.remap(frame, sampler.map_x, sampler.map_y, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    out = out.reshape(-1, frame.shape[-1])[:sampler.n]
    if valid is not None and not np.all(valid):
        bad = cv2.remap((~np.asarray(valid, bool)).astype(np.float32), sampler.map_x,
                        sampler.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out = out.copy()
        out[bad.reshape(-1)[:sampler.n] > 0] = np.nan
    return out


def sample_taps(frame: np.ndarray, index: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Reference bilinear samples ``(N, 3)`` from :func:`bilinear_taps` (a numpy gather)."""
    flat = np.asarray(frame, np.float32).reshape(-1, frame.shape[-1])
    return np.einsum("nk,nkc->nc", weight, np.take(flat, index, axis=0), dtype=np.float32)


@dataclass
class ProjectedField:
    """One camera's reflectance field on the atlas, as written by :func:`project_camera`.

    Attributes
    ----------
    camera : str
    directory : pathlib.Path
        Holds ``R.npy`` ``(T_c, L, 3)`` (float16 or float32, C order: chunked along texels),
        ``texel_index.npy`` ``(T_c,)`` int64, ``weight.npy`` ``(T_c,)`` float32 and
        ``v_world.npy`` ``(T_c, 3)`` float64.
    texel_index : (T_c,) int64
        Texels with a non-zero weight, in texel order.
    weight : (T_c,) float32
    v_world : (T_c, 3) float64, unit, world frame
    n_lights : int
    n_masked : int
        Samples stored as NaN (a bilinear tap on a masked pixel).
    n_overflow : int
        Finite samples beyond the float16 range (stored as ±inf when ``dtype`` is float16).
    seconds : float
    """

    camera: str
    directory: Path
    texel_index: np.ndarray
    weight: np.ndarray
    v_world: np.ndarray
    n_lights: int
    n_masked: int
    n_overflow: int
    seconds: float

    def field(self) -> np.ndarray:
        """The memory-mapped ``R_c`` ``(T_c, L, 3)`` (read-only)."""
        return open_field(self.directory)


def _new_field(directory: Path, field_format: str, dtype: str, shape: tuple, lights: int,
               field_store=None):
    """The writable field of :func:`project_camera`: ``R.npy`` memory-mapped, or the Zarr
    store ``R.zarr`` chunked ``_TRANSPOSE_TEXELS × lights`` — in ``directory``, or in
    ``field_store`` (a folder or an fsspec URL) with a link to it in ``directory``
    (:func:`~facegeo.surface._zarr_field.link_field`). The other format's file of an earlier
    run is removed: :func:`open_field` would read it first."""
    zarr_loc = field_location(directory, "R.npy")
    if field_format == "npy":
        if Path(zarr_loc).exists():
            import shutil

            shutil.rmtree(zarr_loc)
        return np.lib.format.open_memmap(directory / "R.npy", mode="w+", dtype=dtype,
                                         shape=shape)
    (directory / "R.npy").unlink(missing_ok=True)
    loc = create_field(directory if field_store is None else field_store, shape, dtype=dtype,
                       chunks=(_TRANSPOSE_TEXELS, lights), overwrite=True)
    if field_store is not None:
        from facegeo.surface._zarr_field import link_field

        link_field(directory, loc)
    return open_zarr_field(loc, mode="r+")


def project_camera(frames: Iterable, vis: CameraVisibility, size: tuple[int, int],
                   n_lights: int, directory, *, dtype: str = "float16",
                   block_lights: int = DEFAULT_BLOCK_LIGHTS,
                   shadows=None, field_format: str = DEFAULT_FIELD_FORMAT,
                   field_store=None) -> ProjectedField:
    """Project one camera's OLAT frames onto its visible texels, streaming frame by frame.

    Implements Debevec et al. 2000 Eq. (2) per texel: ``R_c[t, l] = L_l(q_c(t))``, the frame of
    light l sampled (bilinearly) where texel t projects; with ``shadows``, samples whose taps
    mix lit and shadowed pixels are interpolated from the taps on the texel's side
    (:mod:`facegeo.surface.shadows`, the geometric shadow maps of §4.4).

    Parameters
    ----------
    frames : iterable of (light, frame) or (light, frame, valid)
        In light-index order ``0 … L−1`` (e.g. ``Scan.iter_olat(camera, return_mask=True)``);
        ``frame`` ``(H, W, 3)`` float32 linear radiance, ``valid`` ``(H, W)`` bool.
    vis : CameraVisibility
        This camera's visibility; texels with ``weight > 0`` are projected.
    size : (int, int)
        The camera's (width, height) in pixels.
    n_lights : int
        Number of frames expected.
    directory : path-like
        Created; receives the files listed in :class:`ProjectedField`.
    dtype : {"float16", "float32"}
        On-disk type of ``R`` (computation is float32).
    block_lights : int
        Lights gathered in RAM before one write (module docstring).
    shadows : facegeo.surface.shadows.ShadowTaps, optional
        Built for this camera's projected texels (those with ``weight > 0``, in texel order) and
        the frames' lights; its running totals count the samples it changed.
    field_format : {"npy", "zarr"}
        ``R.npy`` (default; what the other stages look for) or the Zarr store ``R.zarr``
        chunked ``4096 texels × block_lights lights`` (:mod:`facegeo.surface._zarr_field`:
        each light block fills whole chunks). :func:`open_field` reads either.
    field_store : path-like or str, optional
        ``field_format="zarr"`` only: create the Zarr store in this folder or fsspec URL
        (``s3://bucket/…/cam_0``; ``--store``) instead of ``directory``, which gets a link to
        it (``R.zarr.url``, :func:`~facegeo.surface._zarr_field.link_field`) beside the small
        files; every reader follows the link.

    Returns
    -------
    ProjectedField

    Raises
    ------
    ShapeError
        A frame of the wrong size or channel count (the message names the camera and light).
    InputError
        Frames out of order, or a count different from ``n_lights``.
    """
    t0 = time.perf_counter()
    if dtype not in ("float16", "float32"):
        raise InputError(f"dtype: expected 'float16' or 'float32', got {fmt_value(dtype)}")
    n_lights = check_positive_int(n_lights, "n_lights")
    block_lights = check_positive_int(block_lights, "block_lights")
    if field_format not in FIELD_FORMATS:
        raise InputError(f"field_format: expected one of {', '.join(FIELD_FORMATS)}, got "
                         f"{fmt_value(field_format)}")
    if field_store is not None and field_format != "zarr":
        raise InputError(f"field_store: a field in a store is a Zarr field; got field_format "
                         f"{fmt_value(field_format)}")
    W, H = (int(s) for s in size)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    sel = np.flatnonzero(vis.weight > 0)
    sampler = frame_sampler(vis.q[sel], W, H)
    if shadows is not None and len(shadows.index) != sel.size:
        raise ShapeError(f"camera {fmt_value(vis.camera)}: shadows holds {len(shadows.index)} "
                         f"samples, the camera projects {sel.size} texels")
    L = int(n_lights)
    B = int(min(block_lights, L))
    R = _new_field(directory, field_format, dtype, (sel.size, L, 3), B, field_store)
    n_masked, n_overflow = fill_light_columns(R, frames, sampler, shadows, (0, L), B, dtype,
                                              vis.camera, (W, H))
    del R
    np.save(directory / "texel_index.npy", sel.astype(np.int64))
    np.save(directory / "weight.npy", vis.weight[sel])
    np.save(directory / "v_world.npy", vis.v_world[sel])
    seconds = time.perf_counter() - t0
    log.info("project %s: %d texels × %d lights in %.2f s (%d masked samples)",
             vis.camera, sel.size, L, seconds, n_masked)
    return ProjectedField(camera=vis.camera, directory=directory, texel_index=sel,
                          weight=vis.weight[sel], v_world=vis.v_world[sel], n_lights=L,
                          n_masked=n_masked, n_overflow=n_overflow, seconds=seconds)


def fill_light_columns(R, frames, sampler, shadows, lights: tuple[int, int], block: int,
                       dtype: str, camera: str, size: tuple[int, int]) -> tuple[int, int]:
    """Columns ``l0:l1`` of a camera's field ``R`` (``(T_c, L, 3)``, a memory map or a Zarr
    array) from its OLAT ``frames`` (``(light, frame)`` or ``(light, frame, valid)``, lights
    ``l0 … l1−1`` in order): each frame sampled at the projected texels
    (:func:`sample_olat_frame`, Eq. 2), ``block`` lights gathered frame-major in RAM, then
    written with a blocked transpose ``(B, T, 3) → (T, B, 3)`` a few thousand texels at a time
    (source rows and destination pages stay in cache; converted to the disk dtype) and the
    written pages released. The loop of :func:`project_camera` (``(0, L)``) and of the
    projection's light-block tasks (:mod:`facegeo.pipeline._project_blocks`). Returns the
    masked samples and those beyond float16's range.

    Raises
    ------
    InputError
        Frames out of order, more than ``l1 − l0`` of them, or fewer.
    ShapeError
        A frame or mask of another size than ``size`` ``(W, H)``.
    """
    l0, l1 = (int(v) for v in lights)
    W, H = (int(v) for v in size)
    n = int(R.shape[0])
    buf = np.empty((min(int(block), l1 - l0), n, 3), np.float32)  # frame-major rows
    B = buf.shape[0]
    n_masked = n_overflow = 0
    count = b0 = l0
    where = "" if (l0, l1) == (0, R.shape[1]) else f" (block {l0}:{l1})"

    def flush(upto: int) -> None:
        for t0 in range(0, n, _TRANSPOSE_TEXELS):
            t1 = min(t0 + _TRANSPOSE_TEXELS, n)
            R[t0:t1, b0:upto] = buf[:upto - b0, t0:t1].transpose(1, 0, 2)
            _release_rows(R, t0, t1, write=True)

    for item in frames:
        if len(item) == 3:
            light, frame, valid = item
        else:
            (light, frame), valid = item, None
        if int(light) != count:
            raise InputError(f"camera {fmt_value(camera)}: expected OLAT frame of light {count}"
                             f"{where}, got light {light} (frames must come in light-index order)")
        if count >= l1:
            raise InputError(f"camera {fmt_value(camera)}: more OLAT frames than the "
                             f"{l1 - l0} lights{where}")
        frame = np.asarray(frame)
        if frame.shape != (H, W, 3):
            raise ShapeError(f"camera {fmt_value(camera)}, light {light}: OLAT frame has shape "
                             f"{frame.shape}, expected ({H}, {W}, 3)")
        if valid is not None and np.shape(valid) != (H, W):
            raise ShapeError(f"camera {fmt_value(camera)}, light {light}: mask has shape "
                             f"{np.shape(valid)}, expected ({H}, {W})")
        s, masked, overflow = sample_olat_frame(frame, sampler, valid, shadows, count, dtype)
        n_masked += masked
        n_overflow += overflow
        buf[count - b0] = s
        count += 1
        if count - b0 == B:
            flush(count)
            b0 = count
    if count != l1:
        raise InputError(f"camera {fmt_value(camera)}: got {count - l0} OLAT frames, expected "
                         f"{l1 - l0}{where} (one per light)")
    if count > b0:
        flush(count)
    return n_masked, n_overflow


def sample_olat_frame(frame, sampler, valid, shadows, light: int, dtype: str):
    """One OLAT frame of a camera sampled at its projected texels (Eq. 2, ``R_c[t, l] =
    L_l(q_c(t))``; :func:`sample_frame`), through the shadow-consistent ``shadows`` taps when
    given: ``(samples (T_c, 3) float32, masked samples, samples beyond float16's range when
    ``dtype`` is ``"float16"``)`` — the per-frame step of :func:`fill_light_columns`."""
    s = sample_frame(frame, sampler, valid)
    if shadows is not None:
        shadows.apply(light, frame, s, valid)
    masked = overflow = 0
    if np.isnan(s.sum()):  # one cheap reduction; count only when something is missing
        masked = int(np.count_nonzero(np.isnan(s).any(axis=1)))
    if dtype == "float16":
        big = float(np.abs(s).max(initial=0.0)) if s.size else 0.0
        if big > _F16_MAX:
            with np.errstate(invalid="ignore"):
                overflow = int(np.count_nonzero(np.isfinite(s) & (np.abs(s) > _F16_MAX)))
    return s, masked, overflow


def field_folders(project_dir) -> list[Path]:
    """The camera folders of a ``project`` stage folder that hold a projected field (either
    format), sorted by name; none when ``project_dir`` is not a folder."""
    project_dir = Path(project_dir)
    if not project_dir.is_dir():
        return []
    return sorted(p for p in project_dir.iterdir() if p.is_dir() and has_field(p))


def iter_field_chunks(directory, chunk_texels: int | None = None, name: str = "R.npy"):
    """Yield ``(start, R[start:stop] as float32)`` chunks along texels (never computing in
    float16); ``name`` as in :func:`open_field` (either format). Default ``chunk_texels``: as
    many as make a 32 MB float32 chunk (a fixed 8,192 made 201 MB chunks at 2048 lights, and a
    caller's temporaries several times that); for a Zarr field rounded to whole chunks of its
    store (at least one), so that no stored chunk is read twice."""
    R = open_field(directory, name)
    chunk_texels = _chunk_rows(R, chunk_texels)
    for s in range(0, R.shape[0], chunk_texels):
        chunk = np.array(R[s:s + chunk_texels], dtype=np.float32)
        _release_rows(R, s, s + len(chunk), write=False)  # keep resident memory at one chunk
        yield s, chunk


def _index_array(a, name: str) -> np.ndarray:
    """``a`` as a 1-D int64 index array; a bool mask or non-integer values are an error."""
    a = np.asarray(a)
    if a.size and a.dtype.kind not in "iu":
        raise InputError(f"{name}: expected integer indices, got dtype {a.dtype}")
    return a.astype(np.int64).reshape(-1)


def gather_field_samples(directory, rows, lights, *, chunk_texels: int | None = None,
                         name: str = "R.npy") -> np.ndarray:
    """Chosen rows and lights of a stored field, read straight from its memory map.

    ``R[rows][:, lights]`` in the stored dtype, ``chunk_texels`` rows at a time (the pages read
    are released after each step, as :func:`iter_field_chunks` does): no float32 copy of whole
    rows when a few lights of many texels are wanted (a comparison with ground truth).

    Parameters
    ----------
    directory : path-like — a camera folder (``name`` as in :func:`open_field`)
    rows : (n,) int — rows of ``R`` (texels of the field, in any order)
    lights : (K,) int — light indices
    chunk_texels : int, optional — rows per step (default: a 32 MB float32 chunk of rows)

    Returns
    -------
    (n, K, C) array, the field's dtype (C = 3 for RGB)

    Raises
    ------
    InputError
        Indices that are not integers or out of range, a bad ``chunk_texels``.
    """
    R = open_field(directory, name)
    rows = _index_array(rows, "rows")
    lights = _index_array(lights, "lights")
    step = _chunk_rows(R, chunk_texels)
    if rows.size and (rows.min() < 0 or rows.max() >= R.shape[0]):
        raise InputError(f"rows: expected indices in [0, {R.shape[0]}) of {directory}, got "
                         f"{rows.min()}..{rows.max()}")
    if lights.size and (lights.min() < 0 or lights.max() >= R.shape[1]):
        raise InputError(f"lights: expected indices in [0, {R.shape[1]}) of {directory}, got "
                         f"{lights.min()}..{lights.max()}")
    out = np.empty((rows.size, lights.size) + R.shape[2:], R.dtype)
    zarr_field = not isinstance(R, np.ndarray)
    for a in range(0, rows.size, step):
        r = rows[a:a + step]
        if zarr_field:  # orthogonal selection: the chunks holding these rows and lights
            out[a:a + r.size] = R.get_orthogonal_selection((r, lights, slice(None)))
        else:
            out[a:a + r.size] = R[r[:, None], lights[None, :]]
        _release_rows(R, int(r.min()), int(r.max()) + 1, write=False)
    return out
