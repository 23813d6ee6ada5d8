"""Geometric shadow maps, and bilinear taps that do not mix lit and shadowed pixels.

Debevec et al. 2000, §4.4, compute "a shadow map for each reflectance function" and note that
"this could be done using our geometric model" (they threshold brightness instead, the geometry
being incomplete). Here the geometric model decides, for a surface point and a light, whether
the light reaches it; the projection (:func:`facegeo.surface.reflectance.project_camera`) uses
it where a frame is resampled across a cast-shadow edge.

Why: a frame is a grid of samples of a shading function with hard shadow edges. A texel that
projects between a lit and a shadowed pixel centre gets, from bilinear interpolation, a mix of
the two, when its own value is one or the other: on the small preset (1 mm pixels) these 2 %
of the samples carried 90 % of the projection's squared error (docs/surface.md). Knowing from
the mesh which taps are lit and whether the texel is, the sample is interpolated from the taps
on the texel's side only (:class:`ShadowTaps`). The interpolation is still linear in the frame
of each light — the taps depend on the light and the geometry, never on pixel values — and the
texel's blending weight stays the same for every light.

The shadow test (:class:`ShadowRays`), for a point with shading normal n and a light at
direction l from it:

* a point with ``n·l <= 0`` faces away from the light (attached shadow): unlit;
* otherwise the segment to the light (or the ray, for a distant light) starts at the point
  **lifted onto the smooth surface** the shading normals describe (Hanika 2021, Ray Tracing
  Gems II ch. 4, :func:`lifted_origins`), ``eps`` along n, and ends ``eps`` short of the
  light; it is traced with Embree's any-hit query
  (:meth:`~facegeo.surface.visibility.RayScene.occluded`, as
  :meth:`~facegeo.surface.visibility.RayScene.segment_visible` does);
* a blocked segment is traced again for its first hit: a hit on the point's own face or a face
  sharing a vertex position with it (its 1-ring) is the faceted mesh shadowing the smooth
  surface it stands for — the terminator problem — and counts as lit, whatever lies beyond
  it. (The synthetic generator retraces such rays from an origin lifted by the face's size
  instead, and its shading normals keep creases sharper than 60°, where a reconstructed or
  atlas mesh's are smooth: the decisions can differ in creases and behind a 1-ring hit.)

How much the origin matters (small preset, ground-truth mesh, 32 stratified lights, texels of
weight > 0.3; ``/tmp/m29`` scripts, docs/surface.md): plain bilinear 3.26 %; shadow-consistent
taps with origins ``eps`` along the geometric normal 2.38 %, with 1-ring hits lit 2.08 %, with
the lift as well 1.37 % (Phong-tessellation origins instead: 2.90 %); with the generator's own
lit/shadowed decisions for every pixel and texel, 1.30 %.

References
----------
J. Hanika, "Hacking the Shadow Terminator", Ray Tracing Gems II, ch. 4, 2021.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from facegeo.checks import as_array, fmt_value
from facegeo.errors import InputError, ShapeError

log = logging.getLogger(__name__)

__all__ = ["lifted_origins", "ShadowRays", "SurfacePoints", "ShadowTaps", "shadow_taps",
           "side_weights", "edge_weights", "light_positions", "light_kwargs",
           "SHADOW_TAPS_MIN_COS"]

#: A sample is re-interpolated only where its texel's shading normal has ``n·l`` at least this:
#: nearer the terminator the shading itself goes to zero smoothly and the lit/unlit split of
#: the taps is decided by normals, not by an occluder. Small preset, 32 lights, ground-truth
#: mesh: 1.37 % with 0.15, 1.64 % with 0 (the terminator band carried 4 % of the bilinear
#: error).
SHADOW_TAPS_MIN_COS = 0.15


def lifted_origins(vertices, faces, vertex_normals, p, face) -> np.ndarray:
    """Shadow-ray origins ``(P, 3)``: points on faces lifted onto the smooth surface.

    Hanika 2021 (Ray Tracing Gems II, ch. 4, "Hacking the shadow terminator"): with
    barycentrics b_k of p on its face, vertices v_k and shading normals n_k,
    ``p' = p − Σ_k b_k min(0, (p − v_k)·n_k) n_k`` — the barycentric mean of p's
    projections onto the vertices' tangent planes, each used only where p lies below the
    plane (convex regions move out, concave ones stay). Zero on flat regions; at most
    ≈ the triangle's sagitta off the faceted surface.

    Parameters
    ----------
    vertices : (V, 3) float64, metres
    faces : (F, 3) int
    vertex_normals : (V, 3) float64, unit
    p : (P, 3) float64, metres — points on the faces
    face : (P,) int — the face of each point

    Returns
    -------
    (P, 3) float64, metres. A point on a degenerate face (no barycentrics) is returned as is.
    """
    p = np.asarray(p, dtype=float)
    f = np.asarray(faces)[np.asarray(face, np.int64)]
    tri = np.asarray(vertices)[f]  # (P, 3, 3)
    nrm = np.asarray(vertex_normals)[f]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    d = p - tri[:, 0]
    d11, d12, d22 = (np.einsum("pc,pc->p", e1, e1), np.einsum("pc,pc->p", e1, e2),
                     np.einsum("pc,pc->p", e2, e2))
    d1, d2 = np.einsum("pc,pc->p", d, e1), np.einsum("pc,pc->p", d, e2)
    den = d11 * d22 - d12 * d12
    with np.errstate(invalid="ignore", divide="ignore"):
        b1 = (d22 * d1 - d12 * d2) / den
        b2 = (d11 * d2 - d12 * d1) / den
    bary = np.stack([1.0 - b1 - b2, b1, b2], axis=1)
    below = np.minimum(np.einsum("pkc,pkc->pk", p[:, None, :] - tri, nrm), 0.0)
    lift = -np.einsum("pk,pkc->pc", bary * below, nrm)
    return np.where(np.isfinite(lift), p + lift, p)


def light_positions(lights) -> tuple[np.ndarray | None, np.ndarray]:
    """Where a rig's lights are.

    Parameters
    ----------
    lights : facegeo.geometry.rig.LightStage or facegeo.geometry.lights.LightList

    Returns
    -------
    positions : (L, 3) float64, metres, world frame, or None when the lights are distant
    directions : (L, 3) float64, unit, world frame — from the stage's centre toward each light
    """
    directions = np.asarray(lights.directions, np.float64)
    if hasattr(lights, "is_distant"):  # a light stage: center + radius·ω unless distant
        return (None if lights.is_distant else np.asarray(lights.positions, np.float64),
                directions)
    pos = getattr(lights, "positions", None)
    return (None if pos is None else np.asarray(pos, np.float64)), directions


def light_kwargs(positions, directions, light: int) -> dict:
    """``position=`` (near-field) or ``direction=`` (distant) of light ``light`` for
    :meth:`ShadowRays.lit`, from :func:`light_positions`' two arrays."""
    if positions is not None:
        return {"position": positions[light]}
    return {"direction": directions[light]}


class ShadowRays:
    """Whether surface points of a mesh see a light (module docstring: the shadow test).

    Parameters
    ----------
    scene : facegeo.surface.visibility.RayScene
        The mesh.
    vertex_normals : (V, 3) float64, unit
        Shading normals of the scene's vertices (NaN for vertices no face uses).
    """

    def __init__(self, scene, vertex_normals) -> None:
        # NaN rows (vertices whose face normals cancel) are allowed: their points are never lit
        n = as_array(vertex_normals, "vertex_normals", shape=(len(scene.vertices), 3),
                     finite=False)
        self.scene = scene
        self.vertex_normals = n
        _, weld = np.unique(scene.vertices, axis=0, return_inverse=True)
        # faces as indices of distinct positions: the 1-ring test sees across UV seams
        self._welded = weld.reshape(-1)[scene.faces]

    def points(self, face, bary) -> SurfacePoints:
        """The surface points at barycentrics of faces of the mesh.

        Parameters
        ----------
        face : (P,) int — face indices into the scene's ``faces``
        bary : (P, 3) float64 — barycentric weights of each face's corners

        Returns
        -------
        SurfacePoints
            Positions, shading normals (interpolated, unit; ``ok`` False where undefined),
            lifted shadow-ray origins and the rays' starts.
        """
        face = np.asarray(face, np.int64)
        bary = np.asarray(bary, np.float64)
        V, F = self.scene.vertices, self.scene.faces
        tri = V[F[face]]
        p = np.einsum("pk,pkc->pc", bary, tri)
        n = np.einsum("pk,pkc->pc", bary, self.vertex_normals[F[face]])
        with np.errstate(invalid="ignore", divide="ignore"):
            n = n / np.linalg.norm(n, axis=1, keepdims=True)
        ok = np.isfinite(n).all(axis=1)
        o = p.copy()
        if ok.any():
            o[ok] = lifted_origins(V, F, self.vertex_normals, p[ok], face[ok])
        n = np.where(ok[:, None], n, 0.0)
        return SurfacePoints(p=p, origin=o, n=n, face=face, ok=ok,
                             start=o + self.scene.eps * n)

    def adjacent(self, face_a, face_b) -> np.ndarray:
        """Whether faces ``face_a[i]`` and ``face_b[i]`` (``(N,)`` int each) are the same or
        share a vertex position (UV seams welded); ``(N,)`` bool."""
        a = self._welded[np.asarray(face_a, np.int64)]
        b = self._welded[np.asarray(face_b, np.int64)]
        return np.any(a[:, :, None] == b[:, None, :], axis=(1, 2))

    def lit(self, pts: SurfacePoints, rows=None, *, position=None, direction=None) -> np.ndarray:
        """Which points the light reaches (module docstring: the shadow test).

        Parameters
        ----------
        pts : SurfacePoints
        rows : (N,) int, optional
            Rows of ``pts`` to test (default all).
        position : (3,) float64, metres, world frame, optional
            A near-field light's position ...
        direction : (3,) float64, unit, world frame, optional
            ... or a distant light's direction (toward it); exactly one of the two.

        Returns
        -------
        (N,) bool
            True where the light reaches the point; points with ``ok`` False are unlit.
        """
        if (position is None) == (direction is None):
            raise InputError("lit: give the light's position or its direction (one of them)")
        if rows is None:
            start, n, ok, face = pts.start, pts.n, pts.ok, pts.face
        else:
            rows = np.asarray(rows)
            if rows.dtype.kind not in "iu":
                raise InputError(f"rows: expected integer row indices, got dtype {rows.dtype}")
            rows = rows.astype(np.int64, copy=False)
            start, n, ok, face = pts.start[rows], pts.n[rows], pts.ok[rows], pts.face[rows]
        scene = self.scene
        eps = scene.eps
        # The segment from the lifted origin, moved eps along the shading normal (toward the
        # light: the point faces it), to the light, eps short of it (RayScene.segment_visible).
        if position is not None:
            to_l = np.asarray(position, np.float64)[None, :] - start
        else:
            to_l = np.broadcast_to(np.asarray(direction, np.float64), start.shape)
        idx = np.flatnonzero(ok & (np.einsum("pc,pc->p", n, to_l) > 0))
        out = np.zeros(len(start), bool)
        if idx.size == 0:
            return out
        s, d = start[idx], to_l[idx]
        if position is not None:
            far = np.sqrt(np.einsum("pc,pc->p", d, d)) - eps
            blocked = scene.occluded(s, d, np.maximum(far, eps), t_min=eps)
        else:
            far = np.full(idx.size, np.inf)
            blocked = scene.occluded(s, d, far, t_min=eps)
        out[idx] = ~blocked
        b = np.flatnonzero(blocked)
        if b.size:
            # first hit of each blocked segment: on the point's own 1-ring it is the facets
            # shadowing the smooth surface (terminator), and the point counts as lit
            hits = scene.closest_hit(s[b], d[b], t_min=eps, t_max=np.maximum(far[b], eps),
                                     fields=("face",))
            out[idx[b[~hits.hit | self.adjacent(face[idx[b]], hits.face.clip(0))]]] = True
        return out


@dataclass(frozen=True)
class SurfacePoints:
    """Points on a :class:`ShadowRays` mesh: ``p`` ``(P, 3)`` metres, shadow-ray ``origin``
    ``(P, 3)`` (:func:`lifted_origins`), unit shading normal ``n`` ``(P, 3)``, ``face`` ``(P,)``,
    ``ok`` ``(P,)`` (False where the normal is undefined or no surface: never lit) and the rays'
    ``start`` ``origin + eps·n`` ``(P, 3)``."""

    p: np.ndarray
    origin: np.ndarray
    n: np.ndarray
    face: np.ndarray
    ok: np.ndarray
    start: np.ndarray

    def take(self, rows) -> SurfacePoints:
        """The points ``rows`` (an integer index array)."""
        rows = np.asarray(rows, np.int64)
        return SurfacePoints(self.p[rows], self.origin[rows], self.n[rows], self.face[rows],
                             self.ok[rows], self.start[rows])


@dataclass
class ShadowTaps:
    """Shadow-consistent bilinear taps of one camera's samples (module docstring).

    Built by :func:`shadow_taps`; :meth:`apply` re-interpolates one light's samples.

    Attributes
    ----------
    size : (int, int) — the camera's (width, height), pixels
    index : (N, 4) int64 — flat pixel index of each sample's bilinear taps
    weight : (N, 4) float32 — their bilinear weights
    tap : (N, 4) int64 — each tap's row in ``pixels``
    pixels : SurfacePoints — the surface point each tap pixel's centre ray hits (``ok`` False
        where it hits nothing: never counted lit or dark)
    texels : SurfacePoints — the samples' own points
    rays : ShadowRays
    positions : (L, 3) float64, metres, world frame, or None (distant lights)
    directions : (L, 3) float64, unit, world frame — toward each light
    min_cos : float — :data:`SHADOW_TAPS_MIN_COS`
    changed, samples, seconds : running totals — samples re-interpolated, samples seen, seconds
        spent building (:func:`shadow_taps`) and in :meth:`apply`
    """

    size: tuple[int, int]
    index: np.ndarray
    weight: np.ndarray
    tap: np.ndarray
    pixels: SurfacePoints
    texels: SurfacePoints
    rays: ShadowRays
    positions: np.ndarray | None
    directions: np.ndarray
    min_cos: float = SHADOW_TAPS_MIN_COS
    changed: int = 0
    samples: int = 0
    seconds: float = 0.0

    @cached_property
    def _tap_columns(self) -> np.ndarray:
        """:attr:`tap` transposed, ``(4, N)`` C order."""
        return np.ascontiguousarray(self.tap.T)

    def _pixel_codes(self, kw: dict) -> np.ndarray:
        """Each tap pixel's code under the light: 1 lit, 2 shadowed, 0 no surface."""
        code = np.where(self.rays.lit(self.pixels, **kw), 1, 2).astype(np.uint8)
        code[~self.pixels.ok] = 0
        return code


    def apply(self, light: int, frame: np.ndarray, samples: np.ndarray,
              valid: np.ndarray | None = None) -> int:
        """Re-interpolate, in place, the samples whose taps mix lit and shadowed pixels.

        Such a sample takes the bilinear weights of the taps on its texel's side (lit or
        shadowed), renormalised; it is left as it was when its texel's ``n·l`` is below
        ``min_cos``, or no tap is on its side.

        Parameters
        ----------
        light : int — the frame's light index
        frame : (H, W, 3) float32 or float16, linear radiance
        samples : (N, 3) float32 — the frame's bilinear samples (``sample_frame``), in the
            order of :attr:`index`; changed in place
        valid : (H, W) bool, optional — a re-interpolated sample with weight on a masked tap is
            NaN (as :func:`facegeo.surface.reflectance.sample_frame`); one whose masked taps
            are all on the other side is finite

        Returns
        -------
        int
            The number of samples changed.
        """
        t0 = time.perf_counter()
        if not 0 <= int(light) < len(self.directions):
            raise InputError(f"light: index {fmt_value(light)} out of range "
                             f"[0, {len(self.directions)})")
        n = len(self.index)
        if samples.shape != (n, 3):
            raise ShapeError(f"samples: expected shape ({n}, 3), got {samples.shape}")
        if np.shape(frame) != (*self.size[::-1], 3):
            raise ShapeError(f"frame: expected shape ({self.size[1]}, {self.size[0]}, 3), "
                             f"got {np.shape(frame)}")
        if valid is not None and np.shape(valid) != self.size[::-1]:
            raise ShapeError(f"valid: expected shape ({self.size[1]}, {self.size[0]}), "
                             f"got {np.shape(valid)}")
        kw = light_kwargs(self.positions, self.directions, int(light))
        # per tap pixel: 1 lit, 2 shadowed, 0 no surface; a sample is mixed when its taps' codes
        # OR to 3
        code = self._pixel_codes(kw)
        # one gather per tap column (contiguous): 5.5× faster than a reduce over (N, 4) rows
        cols = self._tap_columns
        mixed = np.flatnonzero((code[cols[0]] | code[cols[1]] | code[cols[2]] | code[cols[3]])
                               == 3)
        changed = 0
        if mixed.size:
            rows, w = edge_weights(self.rays, self.texels, mixed, self.weight[mixed],
                                   code[self.tap[mixed]], min_cos=self.min_cos, **kw)
            if rows.size:
                total = w.sum(axis=1)
                flat = np.asarray(frame).reshape(-1, frame.shape[-1])
                taps = flat[self.index[rows]].astype(np.float32, copy=False)  # (M, 4, 3)
                # a tap left out must not reach the value, not even as 0 · NaN
                taps = np.where((w > 0)[..., None], taps, np.float32(0))
                value = np.einsum("mk,mkc->mc", w / total[:, None], taps, dtype=np.float32)
                if valid is not None:
                    bad = ~np.asarray(valid, bool).reshape(-1)[self.index[rows]]
                    value[(bad & (w > 0)).any(axis=1)] = np.nan
                samples[rows] = value
                changed = int(rows.size)
        self.changed += changed
        self.samples += n
        self.seconds += time.perf_counter() - t0
        return changed


def edge_weights(rays: ShadowRays, samples: SurfacePoints, rows, weight, codes, *,
                 position=None, direction=None, min_cos: float = SHADOW_TAPS_MIN_COS
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Which samples across a cast-shadow edge are re-interpolated, and with which weights.

    Of the samples ``rows`` whose bilinear taps mix lit and shadowed points under one light,
    those whose own shading normal has ``n·l >= min_cos`` take the weights of the taps on
    their own side (:func:`side_weights`); nearer the terminator the shading goes to zero
    smoothly and the split is the normals', not an occluder's. Shared by the projection
    (:meth:`ShadowTaps.apply`) and the novel-view renderer
    (:func:`facegeo.render.novel.render_view`).

    Parameters
    ----------
    rays : ShadowRays
    samples : SurfacePoints — the samples' own points
    rows : (M,) int64 — rows of ``samples`` whose taps are mixed
    weight, codes : (M, 4) — those rows' bilinear weights and tap codes (1 lit, 2 shadowed,
        0 no surface)
    position, direction : the light (:meth:`ShadowRays.lit`)
    min_cos : float

    Returns
    -------
    rows : (K,) int64 — the samples to re-interpolate
    weight : (K, 4) — their taps' weights on their own side, not renormalised (each row has
        a positive sum)
    """
    rows = np.asarray(rows, np.int64)
    if position is not None:
        l = np.asarray(position, np.float64)[None, :] - samples.start[rows]
        l /= np.linalg.norm(l, axis=1, keepdims=True)
    else:
        l = np.asarray(direction, np.float64)[None, :]
    steep = np.einsum("pc,pc->p", samples.n[rows], l) >= min_cos
    if not steep.any():
        return rows[:0], np.asarray(weight)[:0]
    sel = rows[steep]
    own = np.where(rays.lit(samples, sel, position=position, direction=direction), 1,
                   2).astype(np.uint8)
    w, keep = side_weights(np.asarray(weight)[steep], np.asarray(codes)[steep], own)
    return sel[keep], w[keep]


def side_weights(weight, codes, own) -> tuple[np.ndarray, np.ndarray]:
    """The bilinear weights of the taps on a sample's own side of a cast-shadow edge.

    Shared by the projection (:meth:`ShadowTaps.apply`: camera pixels as taps, texels as
    samples) and the novel-view renderer (:func:`facegeo.render.novel.render_view`: texels as
    taps, pixels as samples).

    Parameters
    ----------
    weight : (M, 4) float — the samples' bilinear weights
    codes : (M, 4) uint8 — each tap's code under the light: 1 lit, 2 shadowed, 0 no surface
    own : (M,) uint8 — the sample's own code (1 or 2)

    Returns
    -------
    weight : (M, 4) float — ``weight`` where the tap's code is the sample's, else 0 (not
        renormalised)
    keep : (M,) bool — some tap is on the sample's side (the others keep their weights)
    """
    w = weight * (codes == np.asarray(own)[:, None])
    return w, w.sum(axis=1) > 0


def shadow_taps(rays: ShadowRays, camera, q, face, bary, lights, *,
                min_cos: float = SHADOW_TAPS_MIN_COS) -> ShadowTaps:
    """The :class:`ShadowTaps` of samples at pixel positions ``q`` ``(N, 2)`` of ``camera``:
    their bilinear taps, the surface point each tap pixel's centre ray hits, and the samples'
    own surface points.

    Parameters
    ----------
    rays : ShadowRays
        The mesh the samples lie on.
    camera : facegeo.geometry.camera.Camera
    q : (N, 2) float64, pixels — where each sample is read (all four taps inside the image)
    face, bary : (N,) int, (N, 3) float64 — each sample's surface point on ``rays``' mesh
    lights : LightStage or LightList — the frames' lights, in light-index order
    min_cos : float — :data:`SHADOW_TAPS_MIN_COS`

    Returns
    -------
    ShadowTaps
    """
    from facegeo.surface.reflectance import bilinear_taps

    t0 = time.perf_counter()
    if not 0.0 <= float(min_cos) < 1.0:
        raise InputError(f"min_cos: expected a number in [0, 1), got {fmt_value(min_cos)}")
    face = np.asarray(face)
    bary = as_array(bary, "bary", shape=(None, 3))
    if not (len(q) == len(face) == len(bary)):
        raise ShapeError(f"q, face, bary: one row per sample, got {len(q)}, {len(face)}, "
                         f"{len(bary)} rows")
    index, weight = bilinear_taps(q, camera.width, camera.height)
    upix, tap = np.unique(index, return_inverse=True)
    tap = tap.reshape(index.shape)
    qp = np.stack([upix % camera.width, upix // camera.width], axis=1).astype(np.float64)
    o, d = camera.pixel_rays(qp)
    ok_ray = np.isfinite(d).all(axis=1)
    face_p = np.zeros(upix.size, np.int64)
    bary_p = np.full((upix.size, 3), 1.0 / 3.0)
    hit = np.zeros(upix.size, bool)
    if ok_ray.any():
        h = rays.scene.closest_hit(o[ok_ray], d[ok_ray], fields=("face", "bary"))
        r = np.flatnonzero(ok_ray)[h.hit]
        face_p[r], bary_p[r], hit[r] = h.face[h.hit], h.bary[h.hit], True
    pixels = rays.points(face_p, bary_p)
    pixels.ok[~hit] = False
    positions, directions = light_positions(lights)
    texels = rays.points(face, bary)
    return ShadowTaps(size=(int(camera.width), int(camera.height)), index=index, weight=weight,
                      tap=tap, pixels=pixels, texels=texels, rays=rays, positions=positions,
                      directions=directions, min_cos=float(min_cos),
                      seconds=time.perf_counter() - t0)

