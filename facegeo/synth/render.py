"""Reference renderer: exact images of a ground-truth head from any camera under any lights.

This is the ground truth every later stage is measured against: the synthetic capture writes its
OLAT frames with it, and novel views and relit images of the fitted model are compared with it.

Model: per surface point, the generator's own skin BRDF of :mod:`facegeo.appearance.brdf` — an
energy-weighted diffuse colour blend plus Torrance–Sparrow specular, deliberately *not* the
paper's §4 fitting model (Debevec et al. 2000) — with
parameters from a solid-texture :class:`~facegeo.synth.skin.SkinField`, cast shadows by exact
Embree shadow rays, no interreflection or subsurface transport (the paper's model has none
either; the OLAT frames are a per-pixel reflectance field that the paper's data-driven
resynthesis can reproduce, while a fit of the paper's parametric model meets a mismatched BRDF).

Radiometry (``docs/conventions.md``): an OLAT pixel is the radiance reflected toward the camera
under a light that delivers irradiance ``E_l = c_l·(r/d)²`` (per RGB channel) at normal
incidence, where ``c_l`` is the light colour, ``r`` the light-stage radius and ``d`` the light's
distance from the surface point (``E_l = c_l`` for distant lights).

Shadows are traced against the (faceted) mesh while shading uses interpolated normals, so a
shadow ray leaving a flat triangle toward a light that the shading normal sees but the
triangle's plane does not would hit the triangle's own neighbours: the shadow-terminator
artefact. Shadow rays therefore start from the shading point lifted onto the smooth surface the
normals describe (Hanika 2021, "Hacking the shadow terminator", Ray Tracing Gems II ch. 4: the
barycentric mean of the point's projections onto the vertices' tangent planes, each applied only
when the point lies below that plane), and a ray whose first hit is on its own face's 1-ring is
traced again from one face edge along the normal (contact shadows closer than a facet are
lost); :func:`terminator_self_shadow_fraction` measures what is left (the fraction of lit
samples shadowed by their own or an adjacent triangle: 2.1 % ICT, 7.1 % MediaPipe, 2.6 % the
procedural head with plain shadow rays; ≤ 0.014 % now, docs/synth.md).
Non-skin mesh parts (eyes, teeth, mouth interior: ``parts``) get uniform materials
(:data:`facegeo.synth.skin.PART_MATERIALS`) instead of skin parameters. Unit irradiance at the stage centre makes the paper's
Eq. (4) sum ``Σ_l R_l L_l δA_l`` the Riemann sum of ``∫ f_r L cos θ dω``.

Every pixel is sampled once, through its centre (OpenCV convention), so the reference is exact
per sample, not box-filtered.
"""

from __future__ import annotations

import logging
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from facegeo.checks import as_array, check_positive_int, fmt_value
from facegeo.errors import InputError
from facegeo.synth._terminator import terminator_self_shadow_fraction  # re-exported

log = logging.getLogger(__name__)

__all__ = ["SurfaceView", "ReferenceRenderer", "smooth_vertex_normals",
           "terminator_self_shadow_fraction"]


def smooth_vertex_normals(vertices: np.ndarray, faces: np.ndarray, *,
                          crease_deg: float = 60.0) -> np.ndarray:
    """Area-weighted vertex normals ``(V, 3)`` float64, unit length, smooth across UV seams.

    A mesh with UV seams stores one vertex per (position, UV) pair, so its topology alone would
    crease the shading along every seam — creases the real surface does not have and that a
    reconstructed (seamless) mesh could not reproduce. Vertices at the same position therefore
    share their face normals, unless their own normals differ by more than ``crease_deg``
    (coincident vertices on genuinely different surfaces, e.g. an eyelid's two sides).
    Vertices used only by zero-area faces get NaN (no hit can ever interpolate them: Embree never
    reports a zero-area triangle).
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # |fn| = 2·area
    own = np.zeros_like(v)
    for k in range(3):
        np.add.at(own, f[:, k], fn)
    own_unit = _unit_or_nan(own)
    # Weld by exact position: pair each vertex with the others at its position (few per seam).
    _, inv, counts = np.unique(v, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    acc = own.copy()
    if counts.max() > 1:
        order = np.argsort(inv, kind="stable")
        size = counts[inv[order]]
        start = np.repeat(np.cumsum(counts) - counts, counts)
        pos = np.arange(len(order)) - start
        cos_crease = np.cos(np.deg2rad(crease_deg))
        for k in range(1, int(counts.max())):
            sel = size > k
            me = order[sel]
            partner = order[start[sel] + (pos[sel] + k) % size[sel]]
            with np.errstate(invalid="ignore"):
                ok = np.einsum("pc,pc->p", own_unit[me], own_unit[partner]) > cos_crease
            np.add.at(acc, me[ok], own[partner[ok]])
    return _unit_or_nan(acc)


def _unit_or_nan(a: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(a, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(norm > 0, a / norm, np.nan)


@dataclass
class SurfaceView:
    """What one camera sees: per-pixel surface samples (pixel-centre rays).

    Attributes
    ----------
    camera_name : str
    shape : (int, int)
        Image (height, width).
    mask : (H, W) bool
        The pixel's centre ray hits the head (with supersampling: at least one of its rays).
    pixel_index : (P,) int64
        Flat indices of the samples that hit: ``(row·W + col)·S + k`` for sub-sample k of S;
        every per-sample array below is (P, ...).
    p_world : (P, 3) float64, metres, world frame
        Hit points.
    n_world : (P, 3) float64
        Unit shading normals (vertex normals interpolated by barycentrics), facing the camera.
    v_world : (P, 3) float64
        Unit directions from the point toward the camera centre.
    face : (P,) int64
        Hit triangle.
    alpha_0, alpha_1 : (P, 3) float32
        Diffuse colour at normal incidence / at grazing (the chromaticity ramp).
    rho_s, roughness : (P,) float32
        Specular scale and Beckmann roughness m.
    """

    camera_name: str
    shape: tuple[int, int]
    mask: np.ndarray
    pixel_index: np.ndarray
    p_world: np.ndarray
    n_world: np.ndarray
    v_world: np.ndarray
    face: np.ndarray
    alpha_0: np.ndarray
    alpha_1: np.ndarray
    rho_s: np.ndarray
    roughness: np.ndarray
    samples_per_pixel: int = 1

    @property
    def n_samples(self) -> int:
        return int(self.pixel_index.size)

    def take(self, idx: np.ndarray) -> SurfaceView:
        """The view restricted to samples ``idx`` (indices into the per-sample arrays); ``mask``
        stays the whole view's, and :meth:`to_image` fills the other pixels."""
        idx = np.asarray(idx, np.int64)
        return SurfaceView(self.camera_name, self.shape, self.mask, self.pixel_index[idx],
                           self.p_world[idx], self.n_world[idx], self.v_world[idx],
                           self.face[idx], self.alpha_0[idx], self.alpha_1[idx],
                           self.rho_s[idx], self.roughness[idx], self.samples_per_pixel)

    def to_image(self, values: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """Scatter per-sample values ``(P, ...)`` into an image ``(H, W, ...)``.

        With several samples per pixel the pixel is their mean (a box filter); samples that miss
        the head count as ``fill``.
        """
        h, w = self.shape
        s = self.samples_per_pixel
        values = np.asarray(values)
        shape = (h * w * s,) + values.shape[1:]
        if fill == 0 and not np.signbit(fill):  # calloc'd zeros: no fill pass
            out = np.zeros(shape, dtype=values.dtype)
        else:
            out = np.full(shape, fill, dtype=values.dtype)
        out[self.pixel_index] = values
        out = out.reshape((h, w, s) + values.shape[1:])
        if s == 1:
            return out[:, :, 0]
        # the box filter: float64 sum over the samples in order, then / s (what
        # out.mean(axis=2, dtype=float64) computes, without its buffered casting: 2× faster)
        acc = out[:, :, 0].astype(np.float64)
        for k in range(1, s):
            acc += out[:, :, k]
        acc /= s
        return acc.astype(values.dtype)


@dataclass
class TexelTruth:
    """Where atlas texels lie on the generator's surface (:meth:`ReferenceRenderer.texel_truth`).

    Attributes
    ----------
    p : (N, 3) float64, metres — the true surface point
    n : (N, 3) float64, unit — the generator's interpolated shading normal there
    face : (N,) int64 — its face of the generator's mesh
    offset : (N,) float64, metres — distance from the texel to ``p`` (0 on the generator's mesh)
    """

    p: np.ndarray
    n: np.ndarray
    face: np.ndarray
    offset: np.ndarray


def _forget(cache: dict, key: int) -> None:
    """Drop ``cache[key]`` when its view has been collected (a new view that reused the id
    keeps its entry)."""
    hit = cache.get(key)
    if hit is not None and hit[0]() is None:
        cache.pop(key, None)


class ReferenceRenderer:
    """Exact renderer of a head mesh with a solid-texture skin field.

    Parameters
    ----------
    vertices : (V, 3) float64, metres, world frame
    faces : (F, 3) int
    skin : facegeo.synth.skin.SkinField
        Ground-truth skin parameters as functions of position.
    eta : float
        Index of refraction of skin for the Fresnel term (1.4).
    shadows : bool
        Trace shadow rays (cast shadows). Off only for analytic tests.
    parts : (F,) int, optional
        Part of each face, indexing ``part_names`` (0 = skin); faces of other parts take the
        uniform material of :data:`facegeo.synth.skin.PART_MATERIALS` instead of the skin
        field's parameters. Default: every face is skin.
    part_names : sequence of str
        Default :data:`facegeo.synth.head.PART_NAMES`.
    """

    def __init__(self, vertices, faces, skin, *, eta: float = 1.4, shadows: bool = True,
                 parts=None, part_names=None):
        from facegeo.synth.head import PART_NAMES

        self.vertices = as_array(vertices, "vertices", shape=(None, 3))
        self.faces = as_array(faces, "faces", shape=(None, 3), dtype=np.int64)
        self.skin = skin
        self.part_names = tuple(PART_NAMES if part_names is None else part_names)
        if parts is None:
            self.parts = None
        else:
            lab = np.asarray(parts)
            if lab.shape != (len(self.faces),) or lab.dtype.kind not in "iu":
                raise InputError(f"parts: expected ({len(self.faces)},) integer part labels, got "
                                 f"{lab.dtype} {lab.shape}")
            if lab.size and (lab.min() < 0 or lab.max() >= len(self.part_names)):
                raise InputError(f"parts: labels must index part_names {self.part_names}")
            self.parts = lab.astype(np.int64) if np.any(lab != 0) else None
        self.eta = float(eta)
        if not (np.isfinite(self.eta) and self.eta > 1.0):
            raise InputError(f"eta: expected a finite index of refraction > 1, got {fmt_value(eta)}")
        self.shadows = bool(shadows)
        self._views: dict[tuple, SurfaceView] = {}
        # id(view) -> (weak reference to the view, its shadow origins); an entry leaves with
        # its view (weakref.finalize), so the cache never keeps a view alive
        self._origins: dict[int, tuple] = {}
        self._terms: dict[int, tuple] = {}  # id(view) -> (weak ref, _view_terms), the same way
        self.rig = None  # the true rig, when rebuilt from a scan (load_ground_truth)

    def material_at(self, p_world, face):
        """Material parameters at surface points: the skin field's, replaced by the part's
        uniform material on non-skin faces.

        Parameters
        ----------
        p_world : (P, 3) float64, metres, world frame
        face : (P,) int
            Face each point lies on.

        Returns
        -------
        facegeo.synth.skin.SkinSample
            Arrays with leading shape (P,).
        """
        from facegeo.synth.skin import apply_part_materials

        skin = self.skin.evaluate(p_world)
        if self.parts is None:
            return skin
        return apply_part_materials(skin, self.parts[np.asarray(face, np.int64)], self.part_names)

    def vertex_parts(self) -> np.ndarray:
        """Part label of every vertex ``(V,)`` int64 (the largest label among its faces)."""
        out = np.zeros(len(self.vertices), np.int64)
        if self.parts is not None:
            for k in range(3):
                np.maximum.at(out, self.faces[:, k], self.parts)
        return out

    @classmethod
    def from_mesh(cls, mesh, skin, **kw) -> ReferenceRenderer:
        """From a ``trimesh.Trimesh``."""
        return cls(np.asarray(mesh.vertices), np.asarray(mesh.faces), skin, **kw)

    @cached_property
    def rays(self):
        """The Embree scene (built on first use)."""
        from facegeo.surface.visibility import RayScene

        return RayScene(self.vertices, self.faces)

    @cached_property
    def vertex_normals(self) -> np.ndarray:
        """Smooth shading normals ``(V, 3)``."""
        return smooth_vertex_normals(self.vertices, self.faces)

    # ------------------------------------------------------------------ geometry

    def is_mesh(self, vertices, vertex_map) -> bool:
        """Whether ``vertices`` (an atlas's, say, with ``vertex_map`` into its input mesh) are
        this renderer's own mesh: same vertex count mapped, same positions to 1 nm."""
        vm = np.asarray(vertex_map)
        return (vm.size > 0 and int(vm.max()) < len(self.vertices)
                and int(vm.min()) >= 0
                and bool(np.allclose(np.asarray(vertices), self.vertices[vm], rtol=0.0,
                                     atol=1e-9)))

    def gauge_alignment(self, vertices):
        """``T_true_mesh`` (:class:`facegeo.frames.Pose`): the rigid transform that best brings
        ``vertices`` (N, 3) — a reconstruction's, in the world frame of the rig it was made
        with — onto the generator's surface (trimmed point-to-plane ICP,
        :func:`facegeo.geometry.mesh.align_to_surface`).

        A calibrated rig's world frame is a gauge choice (``docs/calibration.md``): a head
        reconstructed with it sits millimetres from where the generator put it, and comparing
        its texels with the truth at their own coordinates measures that choice, not the
        reconstruction. The transform uses only the geometry, never the values compared."""
        from facegeo.geometry.mesh import align_to_surface

        return align_to_surface(np.asarray(vertices, np.float64), self.vertices, self.faces)

    def texel_truth(self, atlas, texels, tex=None, *, T_true=None) -> TexelTruth:
        """The generator's surface at atlas texels: the point each texel is compared at.

        On the generator's own mesh (:meth:`is_mesh`; a file holding it included) a texel is its
        own true point, its face read through ``atlas.face_map``; on another mesh (a
        reconstruction) it is the closest point of the generator's surface
        (:func:`facegeo.geometry.mesh.closest_surface_points`). The projection's and the fit's
        ground truth both read it.

        Parameters
        ----------
        atlas : facegeo.surface.atlas.Atlas
        texels : facegeo.surface.atlas.Texels
        tex : (N,) int, optional — texel indices (default all)
        T_true : facegeo.frames.Pose, optional
            Maps the texels' world frame into the generator's (:meth:`gauge_alignment`, for a
            mesh made with a rig other than the true one); the texels are moved by it and then
            take the closest point. ``offset`` is measured after the move.
        """
        from facegeo.geometry.mesh import closest_surface_points

        tex = np.arange(len(texels)) if tex is None else np.asarray(tex, np.int64)
        p_tex = texels.p_world[tex]
        if T_true is not None:
            p_tex = T_true.apply(p_tex)
        if T_true is None and self.is_mesh(atlas.vertices, atlas.vertex_map):
            face, bary, p = atlas.face_map[texels.face[tex]], texels.bary[tex], p_tex
        else:
            face, bary, p = closest_surface_points(self.vertices, self.faces, p_tex)
        n = np.einsum("tk,tkc->tc", bary, self.vertex_normals[self.faces[face]])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return TexelTruth(p, n, np.asarray(face, np.int64), np.linalg.norm(p_tex - p, axis=1))

    def surface_view(self, camera, *, supersample: int = 1) -> SurfaceView:
        """Surface samples seen by ``camera`` (cached per camera).

        ``supersample = s`` traces s × s rays per pixel on a regular sub-pixel grid (for frames
        that should integrate over the pixel, like structured light); 1 traces the pixel centre.
        """
        s = int(supersample)
        if s < 1 or s != supersample:
            raise InputError(f"supersample: expected an integer >= 1, got {fmt_value(supersample)}")
        key = (camera.name, camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(),
               camera.T_cam_world.R.tobytes(), camera.T_cam_world.t.tobytes(), s)
        if key in self._views:
            return self._views[key]
        h, w = camera.height, camera.width
        if s == 1:
            o, d = camera.pixel_rays()
        else:
            off = (np.arange(s) + 0.5) / s - 0.5
            ox, oy = np.meshgrid(off, off)
            sub = np.stack([ox.ravel(), oy.ravel()], axis=-1)  # (s², 2)
            q = camera.pixel_grid()[:, :, None, :] + sub[None, None]
            o, d = camera.pixel_rays(q)
        o = o.reshape(-1, 3)
        d = d.reshape(-1, 3)
        # Pixels whose undistortion did not converge (extreme lenses) have no ray: leave them out.
        finite = np.flatnonzero(np.isfinite(d).all(axis=1))
        hits = self.rays.closest_hit(o[finite], d[finite], t_min=0.0,
                                    fields=("face", "bary", "point"))
        sel = np.flatnonzero(hits.hit)
        idx = finite[sel]
        face = hits.face[sel]
        bary = hits.bary[sel]
        p = hits.point[sel]
        n = np.einsum("pk,pkc->pc", bary, self.vertex_normals[self.faces[face]])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        v = camera.center_world[None, :] - p
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        # Interpolated normals can face away from the camera near silhouettes; flip the
        # component so shading stays defined (the geometric normal faces the camera).
        cos_v = np.einsum("pc,pc->p", n, v)
        back = cos_v < 1e-6
        if back.any():
            n[back] = n[back] - (cos_v[back] - 1e-6)[:, None] * v[back]
            n[back] /= np.linalg.norm(n[back], axis=1, keepdims=True)
        skin = self.material_at(p, face)
        _check_skin_sample(skin, p.shape[0])
        mask = np.zeros(h * w * s * s, bool)
        mask[idx] = True
        view = SurfaceView(
            camera_name=camera.name,
            shape=(h, w),
            mask=mask.reshape(h, w, s * s).any(axis=2),
            pixel_index=idx.astype(np.int64),
            p_world=p,
            n_world=n,
            v_world=v,
            face=face.astype(np.int64),
            alpha_0=np.asarray(skin.alpha_0, np.float32).reshape(-1, 3),
            alpha_1=np.asarray(skin.alpha_1, np.float32).reshape(-1, 3),
            rho_s=np.asarray(skin.rho_s, np.float32).reshape(-1),
            roughness=np.asarray(skin.roughness, np.float32).reshape(-1),
            samples_per_pixel=s * s,
        )
        self._views[key] = view
        return view

    # ------------------------------------------------------------------ shading

    def shade_point_light(self, view: SurfaceView, position, color, *, stage_radius: float,
                          sel: np.ndarray | None = None) -> np.ndarray:
        """Radiance ``(P, 3)`` float32 toward the camera under one near-field point light.

        ``position`` is the light's world position; ``color`` (3,) linear RGB gives the
        irradiance at normal incidence at ``stage_radius`` from the light (so a light on the
        stage delivers ``color`` at the stage centre); the irradiance at a point at distance d is
        ``color·(stage_radius/d)²``. ``sel`` restricts shading to a subset of samples.
        """
        pos = as_array(position, "position", shape=(3,))
        col = as_array(color, "color", shape=(3,))
        p = view.p_world if sel is None else view.p_world[sel]
        to_l = pos[None, :] - p
        dist = np.linalg.norm(to_l, axis=1)
        if np.any(dist <= 0):
            raise InputError("shade_point_light: the light lies on the surface")
        l = to_l / dist[:, None]
        falloff = (float(stage_radius) / dist) ** 2
        return self._shade(view, l, falloff, col, sel=sel, light_pos=pos)

    def shade_directional_light(self, view: SurfaceView, direction, color,
                                sel: np.ndarray | None = None) -> np.ndarray:
        """Radiance ``(P, 3)`` float32 under a distant light from unit ``direction`` (toward the
        light) delivering irradiance ``color`` at normal incidence."""
        d = as_array(direction, "direction", shape=(3,))
        d = d / np.linalg.norm(d)
        col = as_array(color, "color", shape=(3,))
        n_p = view.n_samples if sel is None else int(np.count_nonzero(sel) if sel.dtype == bool else sel.size)
        l = np.broadcast_to(d, (n_p, 3))
        return self._shade(view, l, np.ones(n_p), col, sel=sel, light_dir=d)

    def _shade(self, view, l, falloff, col, *, sel=None, light_pos=None, light_dir=None):
        from facegeo.appearance.brdf import synthetic_skin_brdf_unchecked

        pick = (lambda a: a) if sel is None else (lambda a: a[sel])
        n = pick(view.n_world)
        v = pick(view.v_world)
        cos_i = np.einsum("pc,pc->p", n, l)
        out = np.zeros((n.shape[0], 3), np.float32)
        # lit: indices into the (selected) samples; rows: the same samples' indices in the view
        lit = np.flatnonzero(cos_i > 0)
        if sel is None:
            rows = lit
        else:
            sel_rows = np.flatnonzero(sel) if sel.dtype == bool else np.asarray(sel, np.int64)
            rows = sel_rows[lit]
        n_lit = n.take(lit, axis=0)
        if self.shadows and lit.size:
            vis = self._unshadowed(view.p_world.take(rows, axis=0), view.face.take(rows), n_lit,
                                   light_pos=light_pos, light_dir=light_dir,
                                   origins=self._view_origins(view).take(rows, axis=0))
            if not vis.all():
                lit, rows, n_lit = lit[vis], rows[vis], n_lit[vis]
        if not lit.size:
            return out
        # Hot loop (once per light): the view's normals, directions and skin parameters were
        # checked when the view was built, so the unchecked kernel skips re-validating them.
        # float32 parameters promote exactly to float64 inside the arithmetic.
        f = synthetic_skin_brdf_unchecked(
            n_lit, l.take(lit, axis=0), v.take(lit, axis=0), view.alpha_0.take(rows, axis=0),
            view.alpha_1.take(rows, axis=0), view.rho_s.take(rows), view.roughness.take(rows),
            self.eta,
        )
        e = (cos_i.take(lit) * falloff.take(lit))[:, None] * col[None, :]
        out[lit] = (f * e).astype(np.float32)
        return out

    def shadow_origins(self, p, face) -> np.ndarray:
        """Shadow-ray origins ``(P, 3)``: points on faces lifted onto the smooth surface
        (Hanika 2021; :func:`facegeo.surface.shadows.lifted_origins` with this mesh's shading
        normals)."""
        from facegeo.surface.shadows import lifted_origins

        return lifted_origins(self.vertices, self.faces, self.vertex_normals, p, face)

    @cached_property
    def welded_faces(self) -> np.ndarray:
        """Faces ``(F, 3)`` as indices of distinct vertex positions (UV seams welded)."""
        _, weld = np.unique(self.vertices, axis=0, return_inverse=True)
        return weld.reshape(-1)[self.faces]

    def adjacent(self, face_a, face_b) -> np.ndarray:
        """Whether faces ``face_a[i]`` and ``face_b[i]`` are the same or share a vertex
        position, ``(N,)`` bool."""
        wf = self.welded_faces
        a = wf[np.asarray(face_a, np.int64)]
        b = wf[np.asarray(face_b, np.int64)]
        return np.any(a[:, :, None] == b[:, None, :], axis=(1, 2))

    @cached_property
    def face_size(self) -> np.ndarray:
        """Longest edge of every face ``(F,)``, metres."""
        t = self.vertices[self.faces]
        return np.max(np.linalg.norm(t - np.roll(t, 1, axis=1), axis=2), axis=1)

    def _view_origins(self, view: SurfaceView) -> np.ndarray:
        """:meth:`shadow_origins` of every sample of a view, computed once per view (they do
        not depend on the light), for any view: the cache holds a weak reference and drops the
        entry when the view is collected."""
        key = id(view)
        hit = self._origins.get(key)
        if hit is not None and hit[0]() is view:
            return hit[1]
        origins = self.shadow_origins(view.p_world, view.face)
        self._origins[key] = (weakref.ref(view), origins)
        weakref.finalize(view, _forget, self._origins, key)
        return origins

    def _unshadowed(self, p, face, n, *, light_pos=None, light_dir=None,
                    origins=None) -> np.ndarray:
        """Whether each surface point sees the light.

        Shadow rays start at :meth:`shadow_origins` (Hanika 2021). Hanika's lift alone still
        left 1.28 % (ICT), 3.76 % (MediaPipe) and 1.94 % (procedural, subdivision 5) of lit
        samples shadowed by their own or an adjacent triangle at the ``tiny`` preset (2.10 %,
        7.11 % and 2.64 % without it; docs/synth.md): where the light is
        below a facet's plane the ray enters the mesh through its 1-ring and then meets the
        far side from inside. So a blocked ray whose first hit is on the 1-ring of its own face
        (faces sharing a vertex position) is traced again from an origin offset along the
        shading normal by the face's longest edge, which clears the 1-ring: a shadow then
        needs an occluder beyond the facets' own scale. Contact shadows closer than one
        facet (a crease sharper than the light's elevation) are lost.
        """
        return self._shadow_test(p, face, n, light_pos=light_pos, light_dir=light_dir,
                                 origins=origins)[0]

    def _shadow_test(self, p, face, n, *, light_pos=None, light_dir=None, origins=None):
        """:meth:`_unshadowed` and, per point, the face that blocks the deciding shadow ray
        (−1 where the point is lit). ``origins``: precomputed :meth:`shadow_origins`."""
        o = self.shadow_origins(p, face) if origins is None else origins
        eps = self.rays.eps
        vis = self._visible_from(o, n, eps, light_pos, light_dir)
        blocker = np.full(len(vis), -1, np.int64)
        idx = np.flatnonzero(~vis)
        if idx.size == 0:
            return vis, blocker
        own = np.asarray(face)[idx]
        hits = self._first_hits(o[idx] + n[idx] * eps, light_pos, light_dir)
        vis[idx[~hits.hit]] = True  # the any-hit query's float32 disagreement: no face found
        blocker[idx[hits.hit]] = hits.face[hits.hit]
        ring = hits.hit & self.adjacent(own, hits.face.clip(0))
        if ring.any():
            r = idx[ring]
            lifted = o[r] + n[r] * self.face_size[own[ring]][:, None]
            h2 = self._first_hits(lifted, light_pos, light_dir)
            vis[r] = ~h2.hit
            blocker[r] = np.where(h2.hit, h2.face, -1)
        return vis, blocker

    def _first_hits(self, start, light_pos, light_dir):
        """Closest hits of rays from ``start`` toward the light (up to the light)."""
        eps = self.rays.eps
        if light_pos is not None:
            to_l = np.asarray(light_pos, float)[None, :] - start
            dist = np.linalg.norm(to_l, axis=1)
            return self.rays.closest_hit(start, to_l / dist[:, None],
                                         t_max=np.maximum(dist - eps, eps), fields=("face",))
        d = np.broadcast_to(np.asarray(light_dir, float), start.shape)
        return self.rays.closest_hit(start, d, fields=("face",))

    def _visible_from(self, o, n, eps, light_pos, light_dir) -> np.ndarray:
        if light_pos is not None:
            return self.rays.segment_visible(o, light_pos, normals=n)
        far = np.full(o.shape[0], np.inf)
        return ~self.rays.occluded(o + n * eps, np.broadcast_to(light_dir, o.shape), far)

    # ------------------------------------------------------------------ images

    def shade_stage_light(self, view: SurfaceView, lights, l: int) -> np.ndarray:
        """Radiance ``(P, 3)`` float32 under light ``l`` of a light stage: a near-field point light
        when the stage radius is finite, a distant light otherwise."""
        return self._stage_light_shader(view, lights)(l)

    def _stage_light_shader(self, view: SurfaceView, lights) -> Callable[[int], np.ndarray]:
        """``l -> shade_stage_light(view, lights, l)``: :meth:`_stage_light_rows` scattered
        into every sample of the view (0 where unlit or shadowed)."""
        rows_of = self._stage_light_rows(view, lights)

        def shade(l):
            rows, rad = rows_of(l)
            out = np.zeros((view.n_samples, 3), np.float32)
            out[rows] = rad
            return out

        return shade

    def _stage_light_rows(self, view: SurfaceView, lights):
        """``l -> (rows, radiance (R, 3) float32)``: the samples of ``view`` light ``l`` of the
        stage reaches (lit and unshadowed, in sample order) and their radiance toward the
        camera — what :meth:`shade_point_light` / :meth:`shade_directional_light` give at those
        samples (0 elsewhere), computed by the compiled kernels of
        :mod:`facegeo.synth._shade_kernels` (the light-independent terms once per view)."""
        from facegeo.synth import _shade_kernels as K

        color = np.asarray(lights.color, float)
        directions = np.asarray(lights.directions, float)
        point = bool(np.isfinite(lights.radius))
        center = np.asarray(lights.center, float)
        radius = float(lights.radius) if point else 1.0
        terms = self._view_terms(view)
        origins = self._view_origins(view) if self.shadows else None

        def rows_of(l):
            if point:
                pos = center + radius * directions[l]
                kw = {"light_pos": pos}
            else:
                pos = directions[l] / np.linalg.norm(directions[l])
                kw = {"light_dir": pos}
            try:
                rows = K.lit_rows(view.p_world, view.n_world, pos, not point)
            except ValueError:  # the kernel's one error: a point light on a sample
                raise InputError(f"shade_stage_light: light {l} at {fmt_value(pos.tolist())} "
                                 "lies on the surface") from None
            if self.shadows and rows.size:
                vis = self._unshadowed(view.p_world.take(rows, axis=0), view.face.take(rows),
                                       view.n_world.take(rows, axis=0),
                                       origins=origins.take(rows, axis=0), **kw)
                if not vis.all():
                    rows = rows[vis]
            m2, nv = terms[0], terms[2]
            exp_b = np.exp(K.beckmann_exponents(rows, view.p_world, view.n_world, view.v_world,
                                                nv, m2, pos, not point))
            rad = K.shade_rows(rows, exp_b, view.p_world, view.n_world, view.v_world,
                               view.alpha_0, view.alpha_1, view.rho_s, *terms, self.eta, pos,
                               not point, radius, color)
            return rows, rad

        return rows_of

    def _view_terms(self, view: SurfaceView) -> tuple:
        """The light-independent BRDF terms of a view's samples
        (:func:`facegeo.synth._shade_kernels.view_terms`) and the ρ_dr table they index:
        ``(m², π·m², nv, t_r, j, fy, table, n_mu)``, once per view (cached like
        :meth:`_view_origins`)."""
        from facegeo.synth._shade_kernels import light_independent_terms

        key = id(view)
        hit = self._terms.get(key)
        if hit is not None and hit[0]() is view:
            return hit[1]
        terms = light_independent_terms(view, self.eta)
        self._terms[key] = (weakref.ref(view), terms)
        weakref.finalize(view, _forget, self._terms, key)
        return terms

    def olat_images(self, camera, lights, indices=None, *, workers: int = 2
                    ) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(light index, image (H, W, 3) float32)`` for each light of a light stage.

        ``lights`` is a :class:`facegeo.geometry.rig.LightStage`. Frames come in the order of
        ``indices`` (default: light-index order). Lights are shaded ``workers`` at a time (numpy
        and Embree release the GIL), with at most ``2·workers`` frames in flight, so memory stays
        bounded; every frame is computed independently, so results do not depend on ``workers``.
        """
        view = self.surface_view(camera)
        idx = self._check_indices(lights, indices)
        for l, rad in _ordered_map(self._stage_light_shader(view, lights), idx, workers):
            yield int(l), view.to_image(rad)

    def render_lights(self, camera, lights, weights, *, supersample: int = 1, workers: int = 2,
                      progress: Callable[[int], None] | None = None) -> np.ndarray:
        """Image ``(H, W, 3)`` float32 of the head lit by the light stage with RGB ``weights``.

        ``weights`` is ``(L, 3)``: the image is ``Σ_l weights[l] ⊙ OLAT_l``. To light with an
        environment of radiance ``L(ω)``, pass ``weights[l] = L(ω_l) · δA_l`` — Debevec et al.
        2000 Eq. (4). Lights with zero weight are skipped (only lights that carry energy). The
        sum runs in light-index order in float64 whatever ``workers`` is.

        ``supersample = s`` integrates the pixel's footprint: the mean of s × s rays on the
        regular sub-pixel grid of :meth:`surface_view` (a box filter; rays that miss the head
        count as 0), what a sensor pixel records; 1 (the default, and the OLAT frames) samples
        the pixel centre.
        """
        w = as_array(weights, "weights", shape=(lights.n_lights, 3))
        view = self.surface_view(camera, supersample=check_positive_int(supersample,
                                                                         "supersample"))
        from facegeo.synth._shade_kernels import accumulate

        acc = np.zeros((view.n_samples, 3), np.float64)
        active = np.flatnonzero(np.any(w != 0, axis=1))
        shade = self._stage_light_rows(view, lights)
        for k, (l, (rows, rad)) in enumerate(_ordered_map(shade, active, workers)):
            accumulate(acc, rows, rad, np.ascontiguousarray(w[l], np.float64))  # += rad · w_l
            if progress:
                progress(k)
        return view.to_image(acc.astype(np.float32))

    @staticmethod
    def _check_indices(lights, indices):
        if indices is None:
            return np.arange(lights.n_lights)
        idx = np.asarray(indices).reshape(-1)
        if idx.dtype.kind not in "iu" or np.any((idx < 0) | (idx >= lights.n_lights)):
            raise InputError(f"indices: expected light indices in [0, {lights.n_lights}), "
                             f"got {np.asarray(indices).tolist()!r:.80}")
        return idx


def _check_skin_sample(skin, n: int) -> None:
    """Validate a skin field's output once per view (the shading kernel then trusts it)."""
    for name, shape in (("alpha_0", (n, 3)), ("alpha_1", (n, 3)), ("rho_s", (n,)),
                        ("roughness", (n,))):
        a = np.asarray(getattr(skin, name))
        if a.size != int(np.prod(shape)):
            raise InputError(f"skin field: {name} has {a.size} values, expected shape {shape}")
        if not np.all(np.isfinite(a)):
            raise InputError(f"skin field: {name} holds non-finite values")
    if np.any(np.asarray(skin.rho_s) < 0) or np.any(np.asarray(skin.roughness) <= 0):
        raise InputError("skin field: expected rho_s >= 0 and roughness > 0 everywhere")


def _ordered_map(fn, items, workers: int):
    """Yield ``(item, fn(item))`` in order, computing up to ``2·workers`` items ahead on a thread
    pool (bounded memory; ``workers <= 1`` runs inline)."""
    items = list(items)
    if workers <= 1 or len(items) <= 1:
        for it in items:
            yield it, fn(it)
        return
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending: deque = deque()
        it = iter(items)
        for item in it:
            pending.append((item, pool.submit(fn, item)))
            if len(pending) >= 2 * workers:
                break
        done = object()
        while pending:
            item, fut = pending.popleft()
            nxt = next(it, done)
            if nxt is not done:
                pending.append((nxt, pool.submit(fn, nxt)))
            yield item, fut.result()


def load_ground_truth(scan) -> ReferenceRenderer:
    """The reference renderer of a synthetic scan, rebuilt from its ``ground_truth/`` files.

    Non-skin parts come from ``ground_truth/parts.npz`` when the scan has it. Its ``rig``
    attribute holds the true rig the frames were rendered with
    (``ground_truth/rig.json``); the scan's own ``rig.json`` is the nominal rig, which differs
    from it by what a calibration must recover.

    Parameters
    ----------
    scan : facegeo.capture.scan.Scan or path
        A synthetic scan.
    """
    import json

    import trimesh
    import trimesh.exchange.ply

    from facegeo.geometry.rig import Rig
    from facegeo.capture.scan import Scan, load_scan
    from facegeo.synth.skin import SkinField

    if not isinstance(scan, Scan):
        scan = load_scan(scan)
    with open(scan.ground_truth_path("mesh"), "rb") as fh:
        data = trimesh.exchange.ply.load_ply(fh)  # geometry only: no material/texture loading
    mesh = trimesh.Trimesh(data["vertices"], data["faces"], process=False)
    skin = SkinField.from_dict(json.loads(scan.ground_truth_path("skin").read_text()))
    parts = names = None
    if "parts" in scan.ground_truth_keys:
        with np.load(scan.ground_truth_path("parts")) as z:
            parts, names = z["labels"], [str(x) for x in z["names"]]
    renderer = ReferenceRenderer.from_mesh(mesh, skin, parts=parts, part_names=names)
    renderer.rig = Rig.load(scan.ground_truth_path("rig"))
    return renderer
