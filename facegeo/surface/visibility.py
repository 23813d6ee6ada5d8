"""Ray casting against a triangle mesh: closest hit, occlusion and segment visibility.

This is the visibility stage of the pipeline (DESIGN §2): the reflectance-field projection asks
which texels each camera sees and which lights reach each texel (the shadowing that Debevec et
al. 2000, §4–5, read off the data), and the renderer asks the same for novel viewpoints.
:class:`RayScene` wraps an Embree BVH (through ``embreex``) behind a float64 API.

Precision
---------
Embree works in float32. :class:`RayScene` keeps float64 copies of the mesh and

* builds the BVH on vertices *centred on the bounding-box centre*, so float32 rounding of the
  scene is at most ``2**-24 * scale / 2`` (≈ 3e-8 of the bounding-box diagonal) wherever the mesh
  sits in the world frame;
* recomputes every reported hit in float64 from the hit face and the original ray (ray–plane
  intersection, barycentrics by exact cross products), so ``t``, ``point`` and ``bary`` are
  float64-accurate and ``point`` lies on the face's plane to ~1e-16 relative; when that float64
  point falls outside the face (the float32 ray clipped an edge the float64 ray misses), the
  float32 result is kept — a finite, consistent answer;
* enforces ``t_min <= t <= t_max`` in float64 after the float32 query;
* rejects hits on a face whose supporting plane passes within ``eps / 10`` of the ray origin (a
  ray can meet such a face only at its own origin or by sliding along the face's plane, so the
  float32 "hit" is a self-intersection) and hits before ``t_min``. Such rays are re-cast, at
  most four times: one that starts on the rejected face's plane is *lifted* ``eps`` off it along
  the normal (toward the side it heads to; the front when it runs within 1e-6 of the plane), so
  a ray sliding along a flat surface still finds the wall it runs into; one that hit before
  ``t_min`` starts again ``eps`` past that hit. For lifted rays ``point`` is on the hit face and
  ``t`` is measured along the original ray, so ``origin + t * direction`` is within ``eps`` of
  ``point`` (exact to rounding for every other ray). Rays still rejected after the re-casts are
  reported as misses (logged at debug level).

The default self-intersection epsilon is ``eps = 1e-5 * scale`` (``scale`` = bounding-box
diagonal): about 300 float32 ulps at the scene's extent, so a ray whose origin is moved ``eps``
along its direction leaves the surface it starts on for every direction steeper than ≈ 1° from
the tangent plane, and still small enough (3 µm on a 30 cm head) to be far below any geometric
detail a scan resolves. Rays starting more than ~100 scales from the scene see float32 rounding
of their origin comparable to ``eps``; move such origins closer along the ray first.

:meth:`RayScene.occluded` (and :meth:`RayScene.segment_visible`, built on it) use Embree's
any-hit query, which reports no face, so the float64 checks above cannot run there: a ray
*starting on the surface* and leaving it within ≈ 1° of the tangent plane may report itself
occluded. Pass ``normals`` to :meth:`RayScene.segment_visible` (the origin is then offset by
``eps`` along the normal) or use :meth:`RayScene.closest_hit` for such rays.

The BVH is built with Embree's robust flag (``watertight=True``): without it ~16 % of rays
aimed exactly at a shared vertex of an icosphere slipped through the closed mesh; with it none
did from outside (2 of 642 after the ``eps`` origin shift), at ~10–15 % of throughput.

Speed
-----
Rays are processed in bounded chunks (``chunk_size`` rays, default 65,536 at one thread, at most
16,384 with several) on a small thread pool: embreex releases the GIL while tracing, and the
compiled passes around it release it too. Beyond Embree's traversal a closest-hit query costs
one preparation pass (validation, normalisation, float32 rounding: 4–5 ns per ray with its
data in cache, vectorised for contiguous rays and scalar ``t_min``/``t_max``; ≈ 9 ns in place)
and the float64 refinement (17–20 ns per ray in cache, 25–30 ns in place on 20 k faces, about
half of it writing the 89 result bytes of the default :class:`Hits`, 41 with
``fields=("t", "face", "bary")``; the face records are prefetched 16 rays ahead, and Embree's
primitives are numbered in Z-order so neighbouring rays read neighbouring records). Result
memory is recycled by the allocator: after the first call neither this nor raw embreex takes
a page fault per call, so writing into caller-provided buffers measured no faster. Median CPU
time at one thread, interleaved with raw ``EmbreeScene.run(output=1)`` on the same float32
rays and BVH and with the previous implementation, 2-core machine under a load average of
7–11: 65,536 camera rays on 20 k faces 0.80–0.88 of raw embreex (0.82–0.89 with
``fields=("t", "face", "bary")``; previously 0.75–0.81 and 0.78–0.84); 1 M rays on 1.3 M
faces 0.78–0.82 (0.80–0.86; previously 0.71–0.75 and 0.74–0.77).
Large batches of incoherent rays on large meshes are traced in Z-order of their origins (see
``sort_rays``), which makes shadow rays ~1.5–1.9× faster than raw embreex on the same input
order.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from facegeo.checks import as_array, check_finite, check_positive_int, fmt_value
from facegeo.errors import InputError, MissingDependencyError, ShapeError
from facegeo.surface._vis_util import (
    _cross,
    _default_threads,
    _dot,
    _executor,
    _morton_order,
    _rows,
    _scratch,
)

_F64, _F32, _BOOL = np.dtype(np.float64), np.dtype(np.float32), np.dtype(bool)
_I64 = np.dtype(np.int64)
#: Per-thread buffers of one chunk: contiguous o, tmin, tmax (inputs); org32, d32, d, far
#: (Embree rays); the rejected rays' index, t_e, coplanar flag, n̂ (refinement side outputs).
_CLOSEST_SCRATCH = (((3,), _F64), ((), _F64), ((), _F64), ((3,), _F32), ((3,), _F32),
                    ((3,), _F64), ((), _F32), ((), _I64), ((), _F64), ((), _BOOL), ((3,), _F64))
_OCCLUDED_SCRATCH = (((3,), _F32), ((3,), _F32), ((3,), _F64), ((), _F32))

log = logging.getLogger(__name__)

__all__ = ["EPS_RELATIVE", "Hits", "RayScene"]

#: Default self-intersection epsilon as a fraction of the bounding-box diagonal.
EPS_RELATIVE = 1e-5
#: A face is degenerate (never hit) when |e1 × e2| <= this × max(|e1|², |e2|²), i.e. when the
#: sine of its widest-spread corner angle is below it — collinear to float64 working precision.
_DEGENERATE_SIN = 1e-12
#: A float64-refined hit may lie this far outside its face (in barycentric weight) and still be
#: trusted; beyond it the float32 result is kept.
_BARY_TOL = 1e-3
#: Hits on a face whose plane passes within this × eps of the origin are self-intersections.
_COPLANAR_FRACTION = 0.1
#: Directions within this cosine of a face's plane count as tangent to it (lifted to the front).
_TANGENT_COS = 1e-6
#: Re-casts for rays whose first hit was rejected as a self-intersection.
_MAX_RECASTS = 4
_DEFAULT_CHUNK = 1 << 16
#: With several threads, chunks hold at most this many rays (several chunks per thread).
_THREAD_CHUNK = 1 << 14
#: ``sort_rays=None`` sorts batches of at least this many rays on meshes of at least this many
#: faces (smaller BVHs stay in cache: sorting measured slower there, gathers included).
_SORT_MIN_RAYS = 1 << 16
_SORT_MIN_FACES = 1 << 18
#: ``sort_rays=None`` sorts when the median step between consecutive rays (origin step in
#: scene scales plus unit-direction step) exceeds this: random rays score ~1, a camera's pixel
#: grid or texels in atlas order ~1e-3.
_INCOHERENT_STEP = 0.05
#: ``prim_to_face`` for the kernels when primitive ids are face indices.
_NO_REMAP = np.empty(0, dtype=np.int64)
#: The optional fields of :class:`Hits` (``hit`` is always computed), with their per-ray shape
#: and dtype, and the length-0 stand-ins the kernel gets for fields not asked for.
_FIELDS = {"t": ((), _F64), "face": ((), _I64), "bary": ((3,), _F64), "point": ((3,), _F64),
           "normal": ((3,), _F64)}
_ABSENT = {name: np.empty((0,) + shape, dtype) for name, (shape, dtype) in _FIELDS.items()}
_KERNELS: Any = None


class _BadRays(Exception):
    """A compiled pass met a non-finite ray or a zero-length direction (the caller names it)."""


def _lean(a: np.ndarray, buf: np.ndarray | None = None) -> np.ndarray:
    """A per-ray input ``a`` (m, ...) as the kernels read it: its first row alone when every
    row is that row (broadcast, stride 0: read in place instead of copied), else ``a`` when
    C-contiguous, else its copy into ``buf`` (or ``a`` as it is without ``buf``)."""
    if len(a) > 1 and a.strides[0] == 0:
        return a[:1]
    if buf is None or a.flags.c_contiguous:
        return a
    np.copyto(buf, a)
    return buf


def _kernels():
    """The compiled kernels module (numba imported and kernels loaded on first use)."""
    global _KERNELS
    if _KERNELS is None:
        try:
            from facegeo.surface import _vis_kernels
        except ImportError as exc:  # pragma: no cover - numba is a hard dependency
            raise MissingDependencyError(
                "facegeo.surface.visibility needs numba: pip install numba"
            ) from exc
        _KERNELS = _vis_kernels
    return _KERNELS

@dataclass(frozen=True)
class Hits:
    """Closest hits of a batch of rays; misses are NaN / -1 with ``hit`` False.

    Every field but ``hit`` is None when not asked for (``fields`` of
    :meth:`RayScene.closest_hit`).

    Attributes
    ----------
    hit : (...,) bool
        True where the ray hit a face within ``[t_min, t_max]``.
    t : (...,) float64, metres
        Distance from the ray's original origin to the hit along the unit direction; NaN on miss.
    face : (...,) int64
        Index of the hit face in the scene's ``faces``; -1 on miss.
    bary : (..., 3) float64
        Barycentric weights of the hit face's three vertices (non-negative, summing to 1);
        NaN on miss.
    point : (..., 3) float64, metres, mesh frame
        Hit point ``origin + t * direction``, on the hit face's plane to rounding; NaN on miss.
        (For a ray that started on a face's plane and was lifted off it, within ``eps`` of
        ``origin + t * direction``; see the module docstring.)
    normal : (..., 3) float64, unit, mesh frame
        Geometric normal of the hit face, oriented by its winding (``(v1-v0) × (v2-v0)``);
        NaN on miss.
    """

    hit: np.ndarray
    t: np.ndarray | None
    face: np.ndarray | None
    bary: np.ndarray | None
    point: np.ndarray | None
    normal: np.ndarray | None

    @property
    def shape(self) -> tuple[int, ...]:
        """Leading shape of the ray batch."""
        return self.hit.shape


class RayScene:
    """A triangle mesh prepared for ray queries (Embree BVH, built lazily and cached).

    Parameters
    ----------
    vertices : (V, 3) float64, metres, mesh frame
        Vertex positions; must be finite.
    faces : (F, 3) int
        Vertex indices of each triangle, in ``[0, V)``; at least one face. Degenerate
        (zero-area or collinear) triangles are allowed and never reported as hits.
    eps : float, optional, metres
        Self-intersection epsilon, the default ``t_min``. Default ``EPS_RELATIVE * scale``
        (see the module docstring for why).
    n_threads : int, optional
        Threads used for large batches. Default: the CPUs available to this process (≤ 8).
    chunk_size : int, optional
        Most rays per chunk (bounds the temporary memory: at most ~0.3 kB per ray and thread).
        Default 65,536: each chunk costs ≈ 40–90 µs of fixed work (Python, three compiled
        calls, Embree's per-call set-up), and on the development machine 65,536- and
        131,072-ray chunks traced 4–5 % faster than 16,384-ray ones at one thread. With
        several threads chunks hold at most 16,384 rays (the earlier default), so a batch is
        shared out in several chunks per thread.
    watertight : bool, optional
        Build the BVH with Embree's robust flag (default True). Without it, rays aimed at a
        shared vertex can slip through a closed mesh (measured: ~16 % of vertex-aimed rays on
        an icosphere); the flag costs ~10–15 % throughput.

    Raises
    ------
    ShapeError
        ``vertices`` or ``faces`` has the wrong shape, or ``faces`` is not integer.
    InputError
        Non-finite vertices, out-of-range indices, an empty mesh or a non-positive ``eps``.

    Notes
    -----
    The mesh is copied (float64 vertices, int64 faces); later changes to the arrays passed in
    do not affect the scene. The scene is safe to query from several threads. Besides Embree's
    BVH, the first :meth:`closest_hit` builds a float64 table of 96 bytes per face for the
    float64 refinement (≈ 100 MB for a million faces).
    """

    def __init__(
        self,
        vertices: Any,
        faces: Any,
        *,
        eps: float | None = None,
        n_threads: int | None = None,
        chunk_size: int | None = None,
        watertight: bool = True,
    ):
        V = as_array(vertices, "vertices", shape=(None, 3), copy=True)
        F = as_array(faces, "faces", shape=(None, 3), dtype=None, finite=False)
        if F.dtype.kind not in "iu":
            whole = F.dtype.kind == "f" and np.all(np.isfinite(F)) and np.all(F == np.round(F))
            if whole:  # integral floats (e.g. read from a text file) are accepted
                F = F.astype(np.int64)
            elif F.size:
                raise ShapeError(f"faces: expected an integer array, got dtype {F.dtype}")
        F = np.array(F, dtype=np.int64, copy=True)
        if len(F) == 0:
            raise InputError("faces: the mesh has no faces; expected at least one")
        if len(V) == 0:
            raise InputError("vertices: the mesh has no vertices")
        bad = (F < 0) | (F >= len(V))
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            raise InputError(
                f"faces: {int(bad.any(axis=1).sum())} face(s) index vertices outside "
                f"[0, {len(V)}); first at index {idx} (value {int(F[idx])})"
            )
        V.setflags(write=False)
        F.setflags(write=False)
        self._vertices = V
        self._faces = F

        used = np.zeros(len(V), dtype=bool)
        used[F.ravel()] = True
        Vu = V[used]
        self._bounds = np.stack([Vu.min(axis=0), Vu.max(axis=0)])
        self._bounds.setflags(write=False)
        self._centre = self._bounds.mean(axis=0)
        self._scale = float(np.linalg.norm(self._bounds[1] - self._bounds[0]))

        if eps is None:
            eps = EPS_RELATIVE * self._scale if self._scale > 0 else float(np.finfo(float).tiny)
        else:
            try:
                eps = float(eps)
            except (TypeError, ValueError) as exc:
                raise InputError(f"eps: expected a number, got {fmt_value(eps)}") from exc
            if not (np.isfinite(eps) and eps > 0):
                raise InputError(f"eps: expected a finite number > 0, got {fmt_value(eps)}")
        self._eps = eps

        self.n_threads = _default_threads() if n_threads is None else n_threads
        if chunk_size is None:
            chunk_size = _DEFAULT_CHUNK
        chunk_size = check_positive_int(chunk_size, "chunk_size")
        self._chunk = int(chunk_size)

        self._watertight = bool(watertight)
        self._lock = threading.Lock()
        self._embree = None  # (scene, embree-primitive -> face index map)
        self._table: np.ndarray | None = None
        self._degenerate: np.ndarray | None = None

    # ------------------------------------------------------------------ construction helpers

    @classmethod
    def from_trimesh(cls, mesh, **kwargs) -> RayScene:
        """Build a scene from a :class:`trimesh.Trimesh` (its ``vertices`` and ``faces``).

        Parameters
        ----------
        mesh : trimesh.Trimesh
            The mesh; it is not modified.
        **kwargs
            Passed to :class:`RayScene` (``eps``, ``n_threads``, ``chunk_size``).
        """
        if not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")):
            raise InputError(f"mesh: expected a trimesh.Trimesh, got {type(mesh).__name__}")
        return cls(np.asarray(mesh.vertices), np.asarray(mesh.faces), **kwargs)

    # ------------------------------------------------------------------ properties

    @property
    def vertices(self) -> np.ndarray:
        """(V, 3) float64, metres: the scene's vertices (read-only)."""
        return self._vertices

    @property
    def faces(self) -> np.ndarray:
        """(F, 3) int64: the scene's faces (read-only)."""
        return self._faces

    @property
    def n_faces(self) -> int:
        """Number of faces, degenerate ones included."""
        return len(self._faces)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64, metres: min and max corner of the faces' bounding box."""
        return self._bounds

    @property
    def scale(self) -> float:
        """Bounding-box diagonal, metres."""
        return self._scale

    @property
    def eps(self) -> float:
        """Self-intersection epsilon, metres (the default ``t_min``)."""
        return self._eps

    @property
    def n_threads(self) -> int:
        """Threads used for batches larger than one chunk (settable)."""
        return self._n_threads

    @n_threads.setter
    def n_threads(self, value: int) -> None:
        value = check_positive_int(value, "n_threads")
        self._n_threads = int(value)

    @property
    def degenerate(self) -> np.ndarray:
        """(F,) bool: faces that are never hit (zero area or collinear to float64 precision)."""
        if self._degenerate is None:
            deg = np.empty(len(self._faces), dtype=bool)
            step = 1 << 20
            for s in range(0, len(self._faces), step):
                tri = self._vertices[self._faces[s:s + step]]
                e1 = tri[:, 1] - tri[:, 0]
                e2 = tri[:, 2] - tri[:, 0]
                n = _cross(e1, e2)
                nn = np.sqrt(_dot(n, n))
                ref = np.maximum(_dot(e1, e1), _dot(e2, e2))
                deg[s:s + step] = ~(nn > _DEGENERATE_SIN * ref)
            deg.setflags(write=False)
            self._degenerate = deg
        return self._degenerate

    # ------------------------------------------------------------------ embree

    def _scene(self):
        """The committed Embree scene and its primitive → face map (built once, thread-safe).

        Returns ``(scene, prim_to_face)``; ``scene`` is None when every face is degenerate and
        ``prim_to_face`` is None when primitive ids are face indices.

        Embree gets the non-degenerate faces in Z-order of their first vertex
        (:func:`_morton_order` over the scene's bounds; ``prim_to_face`` maps back). The float64
        refinement gathers a record per hit from a table in primitive order (:meth:`_face_table`);
        in Z-order, neighbouring rays read neighbouring records. In the mesh's own order a
        subdivided mesh scatters neighbouring faces across the table: on 1.3 M faces (a 125 MB
        table) the refinement then took ≈ 140 ns per ray, cache misses, against ≈ 15 ns on a
        table that fits in cache. A ray meeting an edge or vertex shared by several faces at
        the same float32 distance may be reported on another of them than in the mesh's order.
        """
        emb = self._embree
        if emb is not None:
            return emb
        with self._lock:
            if self._embree is not None:
                return self._embree
            try:
                from embreex import rtcore_scene
                from embreex.mesh_construction import TriangleMesh
            except ImportError as exc:  # pragma: no cover - embreex is a hard dependency
                raise MissingDependencyError(
                    "facegeo.surface.visibility needs embreex: pip install embreex"
                ) from exc
            deg = self.degenerate
            if deg.all():
                log.warning("RayScene: all %d faces are degenerate; every ray misses",
                            self.n_faces)
                self._embree = (None, None)
                return self._embree
            keep = np.flatnonzero(~deg)
            first = self._vertices[self._faces[keep, 0]]
            prim_to_face = keep[_morton_order(first, self._bounds[0], self._bounds[1])]
            faces = self._faces[prim_to_face]
            v32 = np.ascontiguousarray(self._vertices - self._centre, dtype=np.float32)
            f32 = np.ascontiguousarray(faces, dtype=np.int32)
            scene = rtcore_scene.EmbreeScene(robust=self._watertight)
            TriangleMesh(scene, v32, f32)  # embreex copies the buffers
            # embreex commits on the first query; do it here, under the lock, so concurrent
            # first queries cannot race on the commit.
            scene.run(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32))
            log.debug("RayScene: built Embree BVH over %d faces", len(faces))
            self._embree = (scene, prim_to_face)
            return self._embree

    def _face_table(self) -> np.ndarray:
        """Per-primitive float64 data for the float64 refinement, one 96-byte record each.

        Record (12 float64): ``v0`` (3), unit normal ``n̂`` (3), ``q1 = (e2 × n) / |n|²`` (3),
        ``q2 = (n × e1) / |n|²`` (3), so that for a point ``p`` in the face's plane the
        barycentric weights of ``v1`` and ``v2`` are ``(p - v0)·q1`` and ``(p - v0)·q2``.
        """
        table = self._table
        if table is not None:
            return table
        _, prim_to_face = self._scene()
        with self._lock:
            if self._table is not None:
                return self._table
            faces = self._faces if prim_to_face is None else self._faces[prim_to_face]
            data = np.empty((len(faces), 12))
            step = 1 << 18
            for s in range(0, len(faces), step):
                tri = self._vertices[faces[s:s + step]]
                v0 = tri[:, 0]
                e1 = tri[:, 1] - v0
                e2 = tri[:, 2] - v0
                n = _cross(e1, e2)
                nn = _dot(n, n)
                block = data[s:s + step]
                block[:, 0:3] = v0
                block[:, 3:6] = n / np.sqrt(nn)[:, None]
                block[:, 6:9] = _cross(e2, n) / nn[:, None]
                block[:, 9:12] = _cross(n, e1) / nn[:, None]
            data.setflags(write=False)
            self._table = data
            return self._table

    def build(self) -> RayScene:
        """Build the BVH now (otherwise it is built on the first query); return ``self``."""
        self._scene()
        return self

    # ------------------------------------------------------------------ input handling

    def _rays(self, origins, directions, oname="origins", dname="directions"):
        """Shapes checked and broadcast: ``(shape, O, D, src)`` with ``O``, ``D`` (n, 3) views.

        The values are checked where they are read, by the compiled pass that prepares the
        Embree rays (:func:`~facegeo.surface._vis_kernels.prepare_rays`): a separate pass cost
        ~0.07 of Embree's time per ray. When that pass reports a bad ray the caller raises
        :class:`_BadRays` and :meth:`_name_bad_ray` (given ``src``) names the first one.
        """
        o = as_array(origins, oname, shape=(..., 3), finite=False)
        d = as_array(directions, dname, shape=(..., 3), finite=False)
        try:
            shape = np.broadcast_shapes(o.shape[:-1], d.shape[:-1])
        except ValueError as exc:
            raise ShapeError(
                f"{oname} {o.shape} and {dname} {d.shape}: leading axes do not broadcast"
            ) from exc
        n = math.prod(shape)
        full = shape + (3,)
        O = (o if o.shape == full else np.broadcast_to(o, full)).reshape(n, 3)
        D = (d if d.shape == full else np.broadcast_to(d, full)).reshape(n, 3)
        return shape, O, D, (o, d, oname, dname)

    @staticmethod
    def _name_bad_ray(src) -> None:
        """Raise the :class:`InputError` naming the first non-finite origin or direction or
        zero-length direction of ``src`` (from :meth:`_rays`); return if there is none."""
        o, d, oname, dname = src
        check_finite(o, oname)
        check_finite(d, dname)
        norm = np.sqrt(np.einsum("...i,...i->...", d, d))
        zero = ~(norm > 0)
        if zero.any():
            idx = tuple(int(i) for i in np.argwhere(zero)[0])
            raise InputError(
                f"{dname}: {int(zero.sum())} zero-length direction(s); first at index {idx}"
            )
        bad = ~np.isfinite(norm)
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            raise InputError(f"{dname}: direction length overflows float64 (components above "
                             f"~1e154); first at index {idx}; scale the directions down")

    def _check_rays(self, O, D, src) -> None:
        """Validate rays ``O``, ``D`` (n, 3) that no query reads (an empty scene, rays with
        ``t_max < t_min``) as :func:`~facegeo.surface._vis_kernels.prepare_rays` does."""
        if not _kernels().rays_ok(O, D):
            self._name_bad_ray(src)

    def _range(self, value, name, shape, *, default=None, allow_inf=False):
        """``t_min``/``t_max`` checked and broadcast to the rays: a flat (n,) float64 view."""
        if value is None:
            value = default
        if type(value) in (float, int, np.float64):  # the usual scalar: no array machinery
            v = float(value)
            if v >= 0 and (v < np.inf or allow_inf):
                n = math.prod(shape)
                return np.ndarray((n,), _F64, np.array([v]), 0, (0,))  # stride 0: v n times
        a = as_array(value, name, finite=False)
        bad = np.isnan(a) if allow_inf else ~np.isfinite(a)
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            what = "NaN" if allow_inf else "NaN or inf"
            raise InputError(f"{name}: {what} not allowed; first at index {idx}")
        if (a < 0).any():
            idx = tuple(int(i) for i in np.argwhere(a < 0)[0])
            raise InputError(f"{name}: expected distances >= 0; first negative at index {idx}")
        try:
            a = np.broadcast_to(a, shape)
        except ValueError as exc:
            raise ShapeError(
                f"{name}: expected a scalar or shape {shape}, got {a.shape}"
            ) from exc
        return a.reshape(-1)

    def _ray_order(self, O: np.ndarray, D: np.ndarray, sort_rays) -> Any:
        """A processing order for the rays: None (input order) or a Morton order of origins.

        Incoherent rays (random origins and directions) over a large mesh are memory-bound:
        on 1.3 M faces raw Embree traced them 2.9× faster in Z-order of their origins, and
        :meth:`occluded` / :meth:`closest_hit` ran 1.7× / 1.5× faster end to end.
        """
        n = len(O)
        if sort_rays is False or n < 2:
            return None
        if sort_rays is None and (n < _SORT_MIN_RAYS or self.n_faces < _SORT_MIN_FACES):
            return None
        if sort_rays is None:
            i = np.unique(np.linspace(0, n - 2, min(n - 1, 4096)).astype(np.intp))
            do = np.linalg.norm(O[i + 1] - O[i], axis=1) / max(self._scale, 1e-300)
            u = D[np.concatenate([i, i + 1])]
            with np.errstate(divide="ignore", invalid="ignore"):  # bad rays: named later
                u = u / np.sqrt(_dot(u, u))[:, None]
            dd = np.linalg.norm(u[len(i):] - u[:len(i)], axis=1)
            if np.median(do + dd) <= _INCOHERENT_STEP:
                return None
        # Cells over the scene's bounding box; origins outside it share the boundary cells.
        return _morton_order(O, self._bounds[0], self._bounds[1])

    def _chunk_rays(self) -> int:
        """Rays per chunk: ``chunk_size`` on one thread, at most ``_THREAD_CHUNK`` on several
        (a batch is then shared out in several chunks per thread)."""
        return self._chunk if self._n_threads == 1 else min(self._chunk, _THREAD_CHUNK)

    def _map_chunks(self, fn, n: int, order=None) -> None:
        """Call ``fn(rows)`` for each chunk: ``rows`` is a slice, or indices when ``order``."""
        chunk = self._chunk_rays()
        starts = range(0, n, chunk)

        def rows(s: int):
            sl = slice(s, min(s + chunk, n))
            return sl if order is None else order[sl]

        if self._n_threads == 1 or n <= chunk:
            for s in starts:
                fn(rows(s))
            return
        ex = _executor(self._n_threads)
        for _ in ex.map(lambda s: fn(rows(s)), starts):
            pass

    # ------------------------------------------------------------------ queries

    def closest_hit(self, origins, directions, *, t_min=None, t_max=np.inf,
                    sort_rays: bool | None = None, fields=None) -> Hits:
        """Nearest face hit by each ray within ``[t_min, t_max]``.

        Parameters
        ----------
        origins : (..., 3) float64, metres, mesh frame
            Ray origins; broadcast against ``directions``.
        directions : (..., 3) float64, mesh frame
            Ray directions, any non-zero length (normalised here).
        t_min : float or (...,) float64, metres, optional
            Nearest accepted distance. Default ``eps``, so rays starting on the surface do not
            report the face they start on.
        t_max : float or (...,) float64, metres, optional
            Farthest accepted distance (inf allowed). Default inf.
        sort_rays : bool, optional
            Trace the rays in Z-order of their origins (results are returned in input order).
            Default: when the batch has ≥ 65,536 rays, the mesh ≥ 262,144 faces and
            consecutive rays are incoherent (a camera's pixel grid is not; random shadow rays
            are).
        fields : collection of str, optional
            The :class:`Hits` fields to compute, some of ``"t"``, ``"face"``, ``"bary"``,
            ``"point"``, ``"normal"`` (``hit`` always is); the others are None. Default: all.
            Each field costs writing its bytes per ray (``point`` and ``normal`` are 48 of the
            89); the float64 refinement and the self-intersection checks run for every choice,
            so the fields computed are identical to those of the default.

        Returns
        -------
        Hits
            Per-ray results with the broadcast leading shape; ``t`` is measured from the
            original origin along the unit direction. Computed in float64 from the face Embree
            reports in float32 (see the module docstring).

        Raises
        ------
        ShapeError
            Wrong shapes, or leading axes that do not broadcast.
        InputError
            NaN or inf in origins or directions (the first bad index is named), a zero-length
            direction, NaN or negative ``t_min``/``t_max``; an unknown name in ``fields``.

        Notes
        -----
        A ray that starts on a face never reports that face (nor any face coplanar with its
        origin). If it runs exactly along the face's plane it may still meet the neighbouring
        faces of a faceted mesh at the edge where it leaves the face; that contact is reported
        when Embree finds it (it is geometry, not rounding). Offset the origin along the normal,
        as :meth:`segment_visible` does with ``normals``, when such contacts are unwanted.
        """
        fields = self._fields(fields)
        shape, O, D, src = self._rays(origins, directions)
        n = len(O)
        tmin = self._range(t_min, "t_min", shape, default=self._eps)
        tmax = self._range(t_max, "t_max", shape, allow_inf=True)

        # Left uninitialised here: every chunk writes all of its rays (first touch of the pages
        # happens in the worker threads).
        hit = np.empty(n, dtype=bool)
        got = {f: np.empty((n,) + _FIELDS[f][0], _FIELDS[f][1]) for f in fields}
        out = (hit,) + tuple(got.get(f, _ABSENT[f]) for f in _FIELDS)
        scene, prim_to_face = self._scene()
        if scene is None:
            self._check_rays(O, D, src)
            hit[:] = False
            for f, a in got.items():
                a[:] = -1 if f == "face" else np.nan
        elif n:
            table = self._face_table()
            order = self._ray_order(O, D, sort_rays)
            p2f = _NO_REMAP if prim_to_face is None else prim_to_face

            def work(rows) -> None:
                if isinstance(rows, slice):
                    views = tuple(a[rows] if len(a) else a for a in out)
                else:
                    views = (np.empty(len(rows), dtype=bool),) + tuple(
                        np.empty((len(rows),) + a.shape[1:], a.dtype) if len(a) else a
                        for a in out[1:])
                self._closest_chunk(scene, p2f, table, _rows(O, rows), _rows(D, rows),
                                    _rows(tmin, rows), _rows(tmax, rows), views)
                if not isinstance(rows, slice):
                    for a, v in zip(out, views):
                        if len(a):
                            a[rows] = v

            try:
                self._map_chunks(work, n, order)
            except _BadRays:
                self._name_bad_ray(src)
                raise
        return Hits(hit=hit.reshape(shape),
                    **{f: got[f].reshape(shape + _FIELDS[f][0]) if f in got else None
                       for f in _FIELDS})

    @staticmethod
    def _fields(fields) -> tuple[str, ...]:
        """The requested optional :class:`Hits` fields, validated, in ``_FIELDS`` order."""
        if fields is None:
            return tuple(_FIELDS)
        if isinstance(fields, str):
            fields = (fields,)
        try:
            asked = set(fields)
        except TypeError as exc:
            raise InputError(f"fields: expected a collection of field names, got "
                             f"{fmt_value(fields)}") from exc
        unknown = sorted(str(f) for f in asked - set(_FIELDS))
        if unknown:
            raise InputError(f"fields: unknown field(s) {', '.join(map(repr, unknown))}; "
                             f"expected some of {', '.join(map(repr, _FIELDS))}")
        return tuple(f for f in _FIELDS if f in asked)

    def _closest_chunk(self, scene, p2f, table, o, D, tmin, tmax, out) -> None:
        """Trace one chunk and write it into ``out`` (views of the result arrays; a length-0
        array for a field not asked for).

        Rays whose hit is rejected as a self-intersection are re-cast, on that subset only, at
        most ``_MAX_RECASTS`` times: a ray that starts on the rejected face's plane is lifted
        ``eps`` off that plane (along the normal, on the side the ray heads to); a ray whose
        hit fell before ``t_min`` starts again ``eps`` past that hit.
        """
        eps = self._eps
        o_c, tmin_c, tmax_c, *bufs = _scratch(len(o), _CLOSEST_SCRATCH)
        # First query: the origin is moved t_min along the ray (t_shift = t_min).
        lo = _lean(tmin, tmin_c)
        d, n_rej, (j, t_e, coplanar, n_hat) = self._trace_refine(
            scene, p2f, table, len(o), _lean(o, o_c), _lean(D), lo, lo, _lean(tmax, tmax_c),
            out, bufs)
        if n_rej == 0:
            return
        full = [np.empty((0,) + a.shape[1:], a.dtype) for a in out[1:]]
        idx = j[:n_rej].copy()  # rejected rays, as rows of the chunk
        base, t_shift = o, tmin
        for _ in range(_MAX_RECASTS):
            sel = j[:n_rej]  # rejected rays, as rows of the last query
            cop = coplanar[:n_rej]
            nr = n_hat[:n_rej]
            dr = d[idx]
            # Back side only for rays clearly heading below the plane; within _TANGENT_COS of
            # it the side is not resolved and the front (the winding's side) is used.
            side = np.where(np.einsum("ij,ij->i", dr, nr) < -_TANGENT_COS, -eps, eps)
            base = base[sel] + np.where(cop, side, 0.0)[:, None] * nr
            t_shift = np.where(cop, t_shift[sel], np.maximum(t_shift[sel], t_e[:n_rej]) + eps)
            m = len(idx)
            # Every field on the re-cast subset: t is corrected below, the rest copied.
            sub = (np.empty(m, dtype=bool),) + tuple(
                np.empty((m,) + a.shape[1:], a.dtype) for a in full)
            _, n_rej, (j, t_e, coplanar, n_hat) = self._trace_refine(
                scene, p2f, table, m, base, dr, t_shift, tmin[idx], tmax[idx], sub, unit=True)
            # Report t along the original ray: the lifted origin is off it by <= eps.
            sub[1][:] += np.einsum("ij,ij->i", base - o[idx], dr)
            for arr, val in zip(out, sub):
                if len(arr):
                    arr[idx] = val
            if n_rej == 0:
                return
            idx = idx[j[:n_rej]]
        log.debug("closest_hit: %d ray(s) still self-intersecting after %d re-casts; "
                  "reported as misses", len(idx), _MAX_RECASTS)

    def _trace_refine(self, scene, p2f, table, m, o, D, t_shift, tmin, tmax, out, bufs=None,
                      unit=False):
        """One float32 Embree query and its float64 refinement, dense over the ``m`` rays given.

        Writes the accepted hits into ``out`` (``hit, t, face, bary, point, normal``; NaN / -1
        elsewhere; ``point`` is ``o + t d``; length-0 arrays are skipped) and returns the unit
        float64 directions, the number ``r`` of hits rejected as self-intersections and, in
        their first ``r`` rows, ``(rows, t_e, coplanar, n̂)``: the rejected rays, Embree's hit
        distance from ``o``, whether the hit face's plane contains ``o`` and its unit normal.
        Both steps are compiled kernels (:mod:`facegeo.surface._vis_kernels`); per-ray inputs
        have one row per ray or one shared row (see :func:`_lean`). ``bufs``: the calling
        thread's scratch buffers (``_CLOSEST_SCRATCH`` from org32 on), else fresh ones.
        ``unit``: ``D`` is already unit length (the re-casts). Raises
        :class:`_BadRays` when a ray is not finite or has a zero-length direction.
        """
        k = _kernels()
        if bufs is None:
            bufs = [np.empty((m,) + shape, dtype) for shape, dtype in _CLOSEST_SCRATCH[3:]]
        org32, d32, d, far, *rejected = bufs
        if not k.prepare_rays(o, D, unit, t_shift, tmax, self._centre, False, org32, d32, d,
                              far):
            raise _BadRays
        res = scene.run(org32, d32, dists=far, output=1)
        n_rej = k.refine_hits(o, d, t_shift, tmin, tmax, res["primID"], res["tfar"], res["u"],
                              res["v"], table, p2f, _COPLANAR_FRACTION * self._eps, _BARY_TOL,
                              *out, *rejected)
        return d, n_rej, rejected

    def occluded(self, origins, directions, t_max, *, t_min=None,
                 sort_rays: bool | None = None) -> np.ndarray:
        """Whether any face lies on each ray within ``[t_min, t_max]`` (any-hit query).

        Parameters
        ----------
        origins : (..., 3) float64, metres, mesh frame
            Ray origins; broadcast against ``directions``.
        directions : (..., 3) float64, mesh frame
            Ray directions, any non-zero length (normalised here).
        t_max : float or (...,) float64, metres
            Farthest distance checked (inf allowed).
        t_min : float or (...,) float64, metres, optional
            Nearest distance checked. Default ``eps``.
        sort_rays : bool, optional
            As :meth:`closest_hit`.

        Returns
        -------
        (...,) bool
            True where the ray is blocked. Decided by Embree in float32: distances within
            float32 rounding of ``t_min``/``t_max`` may go either way, and rays leaving the
            surface within ≈ 1° of its tangent plane may report self-occlusion (see the module
            docstring). Agrees with ``closest_hit(...).t <= t_max`` otherwise.

        Raises
        ------
        ShapeError, InputError
            As :meth:`closest_hit`.
        """
        shape, O, D, src = self._rays(origins, directions)
        tmin = self._range(t_min, "t_min", shape, default=self._eps)
        tmax = self._range(t_max, "t_max", shape, allow_inf=True)
        try:
            return self._occluded_rays(O, D, tmin, tmax, sort_rays).reshape(shape)
        except _BadRays:
            self._name_bad_ray(src)
            raise

    def _occluded_rays(self, O, D, tmin, tmax, sort_rays) -> np.ndarray:
        """:meth:`occluded` on flat rays ``(n, 3)``; raises :class:`_BadRays` on a ray that is
        not finite or has a zero-length direction."""
        n = len(O)
        out = np.zeros(n, dtype=bool)
        scene, _ = self._scene()
        if scene is None or n == 0:
            if n and not _kernels().rays_ok(O, D):
                raise _BadRays
            return out
        k = _kernels()

        def work(rows) -> None:
            lo, hi = _rows(tmin, rows), _rows(tmax, rows)
            o, d = _rows(O, rows), _rows(D, rows)
            keep_all = hi >= lo
            if not keep_all.all():
                if not k.rays_ok(o, d):  # the skipped rays are validated too
                    raise _BadRays
                keep = np.flatnonzero(keep_all)
                lo, hi, o, d = lo[keep], hi[keep], o[keep], d[keep]
            else:
                keep = None
            org32, d32, d64, far = _scratch(len(o), _OCCLUDED_SCRATCH)
            # Rounded toward zero: never look past t_max.
            if not k.prepare_rays(_lean(o), _lean(d), False, _lean(lo), _lean(hi), self._centre,
                                  True, org32, d32, d64, far):
                raise _BadRays
            res = scene.run(org32, d32, query="OCCLUDED", dists=far) == 0
            if keep is not None:
                full = np.zeros(len(keep_all), dtype=bool)
                full[keep] = res
                res = full
            out[rows] = res

        self._map_chunks(work, n, self._ray_order(O, D, sort_rays))
        return out

    def segment_visible(self, p_from, p_to, *, normals=None,
                        sort_rays: bool | None = None) -> np.ndarray:
        """Whether the open segment from ``p_from`` to ``p_to`` is free of faces.

        ``eps`` is excluded at both ends, so a segment from a surface point to a light, a camera
        centre or another surface point is not blocked by the surfaces it starts or ends on.
        This is the shadow-ray and camera/projector visibility test.

        Parameters
        ----------
        p_from : (..., 3) float64, metres, mesh frame
            Start points (typically on the surface).
        p_to : (..., 3) or (3,) float64, metres, mesh frame
            End points (a light position, a camera centre), broadcast against ``p_from``.
        normals : (..., 3) float64, mesh frame, optional
            Surface normals at ``p_from`` (any non-zero length). When given, ``p_from`` is first
            moved ``eps`` along the normal, to the side of ``p_to`` (the front side when ``p_to``
            is within ``eps`` of the tangent plane); this makes grazing segments robust against
            self-occlusion.
        sort_rays : bool, optional
            As :meth:`closest_hit`.

        Returns
        -------
        (...,) bool
            True where nothing blocks the segment. Segments shorter than ``2 eps`` are visible.

        Raises
        ------
        ShapeError, InputError
            Wrong shapes; NaN/inf in any argument; a zero-length normal.
        """
        p0 = as_array(p_from, "p_from", shape=(..., 3))
        p1 = as_array(p_to, "p_to", shape=(..., 3))
        try:
            shape = np.broadcast_shapes(p0.shape, p1.shape)
        except ValueError as exc:
            raise ShapeError(
                f"p_from {p0.shape} and p_to {p1.shape}: leading axes do not broadcast"
            ) from exc
        eps = self._eps
        v = p1 - p0
        if normals is not None:
            nrm = as_array(normals, "normals", shape=(..., 3))
            try:
                shape = np.broadcast_shapes(shape, nrm.shape)
            except ValueError as exc:
                raise ShapeError(
                    f"normals {nrm.shape}: does not broadcast against p_from/p_to {shape}"
                ) from exc
            nlen = np.sqrt(np.einsum("...i,...i->...", nrm, nrm))
            zero = ~(nlen > 0)
            if zero.any():
                idx = tuple(int(i) for i in np.argwhere(zero)[0])
                raise InputError(f"normals: zero-length normal; first at index {idx}")
            # Back side only when p_to lies more than eps below the tangent plane; closer to
            # the plane the side is not resolved and the front (the winding's side) is used.
            height = np.einsum("...i,...i->...", nrm, v) / nlen
            side = np.where(height < -eps, -1.0, 1.0)
            p0 = p0 + (eps * side / nlen)[..., None] * nrm
            v = p1 - p0
        # Straight to the any-hit rays: validated once here, each ray's length computed once,
        # no masked copies when every segment is long (the usual case). Going through the
        # public occluded() re-validated and re-normalised everything and copied the long
        # segments: 25-30 % slower than occluded() on the same rays.
        P0 = np.broadcast_to(p0, shape).reshape(-1, 3)
        V = np.broadcast_to(v, shape).reshape(-1, 3)
        length = np.sqrt(_dot(V, V))
        long = length > 2.0 * eps
        visible = np.ones(len(V), dtype=bool)
        if long.all():
            visible = ~self._occluded_rays(P0, V, np.broadcast_to(eps, length.shape),
                                           length - eps, sort_rays)
        elif long.any():
            sel = np.flatnonzero(long)
            P0, V, length = P0[sel], V[sel], length[sel]
            visible[sel] = ~self._occluded_rays(P0, V, np.broadcast_to(eps, len(sel)),
                                                length - eps, sort_rays)
        return visible.reshape(shape[:-1])
