"""Texture atlas of a head mesh (xatlas) and its texel table.

The surface reflectance field (Debevec et al. 2000, §2.1: the surface ``A`` chosen to be the
scanned face, Fig. 1(b)) is sampled at the *texels* of a texture atlas: every atlas pixel whose
centre lies inside a chart triangle is one surface point with a position, normals, a face and
barycentrics. :func:`build_atlas` parameterises the mesh with xatlas; :func:`rasterize_texels`
builds the texel table and the index map atlas pixel ↔ texel; :func:`export_mesh_uv` writes the
mesh with UVs (OBJ, GLB) through trimesh.

UV convention (also in ``docs/surface.md``)
-------------------------------------------
* The atlas is an image of ``height × width`` texels indexed ``[row, col]``; row 0 is the *top*
  row of the image as written to a PNG.
* ``uv`` follows OBJ / OpenGL: origin at the image's *bottom-left* corner, ``u`` to the right,
  ``v`` *up*, both in [0, 1] over the whole image (texel edges, not centres).
* Texel ``(row r, col c)`` has its centre at ``u = (c + ½) / width``,
  ``v = 1 − (r + ½) / height``; in "atlas pixel" coordinates ``x = u·width − ½``,
  ``y = (1 − v)·height − ½`` texel centres are integers, as in ``docs/conventions.md``.
* A texel exists where its centre lies inside (or on the edge of) a chart triangle in UV space;
  a centre on an edge shared by two triangles belongs to the lower face index.

Mesh checks
-----------
xatlas needs clean input: :func:`check_mesh` reports faces with repeated or collinear vertices
(degenerate) and edges shared by more than two faces (non-manifold) with counts and the first
offending index, and with ``repair=True`` drops them (degenerate faces first, then every face
after the second on a non-manifold edge) and says how many it dropped.

Speed
-----
xatlas grows worse than linearly with the triangle count (DESIGN §6: ≈ 11 s for 50 k triangles,
≈ 3 min for 1 M), and its chart computation (not the packing: a 4× coarser atlas costs the
same) dominates, growing steeply with the faces per chart and per mesh. Two limits keep both
small: ``split_faces`` (default 12,000) cuts larger meshes into spatially compact pieces by
recursive median bisection of face centroids, added to one ``xatlas.Atlas`` as separate meshes
(charted independently, on xatlas's worker threads, and packed together; piece boundaries
become seams); ``max_chart_faces`` (default 300) caps each chart's area at that many average
faces. On a 100 k-face face this cut xatlas's CPU time ≈ 10× (more, smaller charts at the same
utilisation; ``facegeo bench surface.atlas``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.checks import as_array, check_positive_int, fmt_value
from facegeo.errors import InputError, MissingDependencyError, ShapeError
from facegeo.geometry.mesh import degenerate_faces

log = logging.getLogger(__name__)

__all__ = [
    "MeshReport", "Atlas", "Texels", "check_mesh", "check_atlas_settings", "split_mesh", "build_atlas",
    "rasterize_texels", "vertex_normals", "export_mesh_uv", "DEFAULT_SPLIT_FACES",
    "DEFAULT_MAX_CHART_FACES",
]

#: Faces per piece when splitting a mesh for xatlas (DESIGN §6: halves the time at 50 k;
#: 12 k pieces measured 2–4× cheaper than 25 k ones with the chart limit below).
DEFAULT_SPLIT_FACES = 12_000
#: Charts are limited to the area of this many average faces (xatlas ``max_chart_area``):
#: xatlas's cost grows steeply with the faces per chart; 300 measured ≈ 10× less CPU than
#: unlimited charts on a 100 k-face face at the same utilisation (docs/surface.md).
DEFAULT_MAX_CHART_FACES = 300
#: A texel centre is inside a triangle when every UV barycentric is >= -this.
_INSIDE_TOL = 1e-9
#: Candidate texel centres tested per rasterisation batch (bounds temporary memory, ~100 B each).
_RASTER_BATCH = 1 << 21


@dataclass(frozen=True)
class MeshReport:
    """What :func:`check_mesh` found (and dropped with ``repair=True``).

    Attributes
    ----------
    n_vertices, n_faces : int
        Input counts.
    degenerate_faces : (D,) int64
        Input faces with a repeated vertex index or collinear/zero-area corners.
    nonmanifold_edges : int
        Edges (vertex pairs) shared by more than two faces.
    nonmanifold_faces : (N,) int64
        Faces dropped by the repair to make every edge manifold (empty without repair).
    kept_faces : (K,) int64
        Indices of the input faces kept (all faces without repair).
    """

    n_vertices: int
    n_faces: int
    degenerate_faces: np.ndarray
    nonmanifold_edges: int
    nonmanifold_faces: np.ndarray
    kept_faces: np.ndarray

    @property
    def clean(self) -> bool:
        """True when nothing was degenerate or non-manifold."""
        return self.degenerate_faces.size == 0 and self.nonmanifold_edges == 0

    def summary(self) -> str:
        """One line of statistics (used in error messages)."""
        return (f"{self.n_vertices} vertices, {self.n_faces} faces, "
                f"{self.degenerate_faces.size} degenerate faces, "
                f"{self.nonmanifold_edges} non-manifold edges")


def _mesh_arrays(vertices: Any, faces: Any) -> tuple[np.ndarray, np.ndarray]:
    V = as_array(vertices, "vertices", shape=(None, 3))
    F = as_array(faces, "faces", shape=(None, 3), dtype=None, finite=False)
    if F.size and F.dtype.kind not in "iu":
        if not (F.dtype.kind == "f" and np.all(np.isfinite(F)) and np.all(F == np.round(F))):
            raise ShapeError(f"faces: expected an integer array, got dtype {F.dtype}")
    F = np.asarray(F, dtype=np.int64)
    if len(F) == 0:
        raise InputError("faces: the mesh has no faces; expected at least one triangle")
    if len(V) == 0:
        raise InputError("vertices: the mesh has no vertices")
    bad = (F < 0) | (F >= len(V))
    if bad.any():
        i = int(np.argwhere(bad)[0][0])
        raise InputError(f"faces: {int(bad.any(axis=1).sum())} face(s) index vertices outside "
                         f"[0, {len(V)}); first is face {i} = {F[i].tolist()}")
    return V, F


def _edge_keys(F: np.ndarray, n_vertices: int) -> np.ndarray:
    """(3F,) int64 undirected edge keys, edges of face f at rows f, F + f, 2F + f."""
    a = np.concatenate([F[:, 0], F[:, 1], F[:, 2]])
    b = np.concatenate([F[:, 1], F[:, 2], F[:, 0]])
    return np.minimum(a, b) * np.int64(n_vertices) + np.maximum(a, b)


def check_mesh(vertices: Any, faces: Any, *, repair: bool = False
               ) -> tuple[np.ndarray, np.ndarray, MeshReport]:
    """Check (and optionally repair) a triangle mesh before parameterising it.

    Parameters
    ----------
    vertices : (V, 3) float64, metres, world frame
    faces : (F, 3) int
        At least one face.
    repair : bool
        Drop degenerate faces, then every face beyond the second on each non-manifold edge
        (in face order), instead of raising.

    Returns
    -------
    vertices : (V, 3) float64
        Unchanged (unused vertices are kept; xatlas ignores them).
    faces : (K, 3) int64
        The kept faces.
    report : MeshReport

    Raises
    ------
    InputError
        No faces; indices out of range; without ``repair``: degenerate faces or non-manifold
        edges (the message gives the counts and the first offending face).
    """
    V, F = _mesh_arrays(vertices, faces)
    degen = np.flatnonzero(degenerate_faces(V, F))
    if degen.size and not repair:
        raise InputError(
            f"faces: {degen.size} degenerate face(s) (repeated or collinear vertices); first is "
            f"face {int(degen[0])} = {F[degen[0]].tolist()}; pass repair=True to drop them")
    keep = np.ones(len(F), bool)
    keep[degen] = False
    idx = np.flatnonzero(keep)
    Fk = F[idx]
    keys = _edge_keys(Fk, len(V))
    order = np.lexsort((np.tile(np.arange(len(Fk)), 3), keys))  # by edge, then face order
    sk = keys[order]
    start = np.r_[True, sk[1:] != sk[:-1]]
    group = np.cumsum(start) - 1
    counts = np.bincount(group)
    n_nonmanifold = int(np.count_nonzero(counts > 2))
    dropped = np.zeros(0, np.int64)
    if n_nonmanifold:
        first = int(idx[order[np.flatnonzero(counts[group] > 2)[0]] % len(Fk)])
        if not repair:
            raise InputError(
                f"faces: {n_nonmanifold} non-manifold edge(s) shared by more than two faces; "
                f"first involves face {first} = {F[first].tolist()}; pass repair=True to drop "
                f"the extra faces")
        rank = np.arange(len(sk)) - np.flatnonzero(start)[group]  # position within its edge
        extra = np.unique(order[rank >= 2] % len(Fk))
        dropped = idx[extra]
        keep[dropped] = False
        idx = np.flatnonzero(keep)
        if idx.size == 0:
            raise InputError("faces: no face is left after dropping non-manifold faces")
    report = MeshReport(len(V), len(F), degen.astype(np.int64), n_nonmanifold,
                        dropped.astype(np.int64), idx.astype(np.int64))
    if not report.clean:
        log.info("check_mesh: dropped %d degenerate and %d non-manifold faces (%s)",
                 degen.size, dropped.size, report.summary())
    return V, F[idx], report


def split_mesh(vertices: Any, faces: Any, max_faces: int = DEFAULT_SPLIT_FACES
               ) -> list[np.ndarray]:
    """Partition faces into spatially compact pieces of at most ``max_faces`` faces.

    Recursive median bisection of face centroids along the longest axis of each piece's
    bounding box (a loop over pieces, not faces).

    Returns
    -------
    list of (F_i,) int64
        Face indices of each piece, covering every face once.
    """
    V, F = _mesh_arrays(vertices, faces)
    max_faces = check_positive_int(max_faces, "max_faces")
    c = V[F].mean(axis=1)
    todo = [np.arange(len(F))]
    out: list[np.ndarray] = []
    while todo:
        idx = todo.pop()
        if len(idx) <= max_faces:
            out.append(idx)
            continue
        p = c[idx]
        axis = int(np.argmax(p.max(axis=0) - p.min(axis=0)))
        order = np.argsort(p[:, axis], kind="stable")
        half = len(idx) // 2
        todo.extend([idx[order[half:]], idx[order[:half]]])
    return out


def vertex_normals(vertices: Any, faces: Any) -> np.ndarray:
    """Area-weighted unit vertex normals ``(V, 3)`` float64 (NaN for unused vertices).

    Vertices at exactly the same position share their normals, so UV seams in the input do not
    crease the shading.
    """
    V, F = _mesh_arrays(vertices, faces)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # |fn| = 2·area
    acc = np.zeros_like(V)
    for k in range(3):
        np.add.at(acc, F[:, k], fn)
    _, inv = np.unique(V, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    welded = np.zeros((inv.max() + 1, 3))
    np.add.at(welded, inv, acc)
    n = welded[inv]
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(norm > 0, n / norm, np.nan)


@dataclass
class Atlas:
    """A mesh with a UV parameterisation (vertices split along chart seams).

    Attributes
    ----------
    vertices : (V', 3) float64, metres, world frame
        Positions of the atlas vertices (a vertex on a seam appears once per chart).
    faces : (F', 3) int64
        Triangles indexing ``vertices``/``uv``; face ``i`` is input face ``face_map[i]``.
    uv : (V', 2) float64
        Texture coordinates, OBJ convention (origin bottom-left, v up; see module docstring).
    normals : (V', 3) float64, unit
        Interpolation (shading) normals, smooth across seams.
    vertex_map : (V',) int64
        Input vertex of each atlas vertex.
    face_map : (F',) int64
        Input face of each atlas face.
    width, height : int
        Atlas size in texels.
    texels_per_metre : float
        xatlas's scale (texels per metre of surface, along each axis).
    n_charts : int
    report : MeshReport
    seconds : float
        Wall time of the xatlas ``generate`` call.
    n_pieces : int
        Pieces the mesh was split into (``split_faces``).
    meta : dict
        ``utilization`` (xatlas: fraction of the atlas covered by charts) and the
        ``max_chart_area`` used (m²), when built here (not saved).
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    normals: np.ndarray
    vertex_map: np.ndarray
    face_map: np.ndarray
    width: int
    height: int
    texels_per_metre: float
    n_charts: int
    report: MeshReport
    seconds: float = 0.0
    n_pieces: int = 1
    meta: dict = field(default_factory=dict)

    def save(self, path) -> None:
        """Write the arrays to an ``.npz`` (see :meth:`load`)."""
        np.savez(path, vertices=self.vertices, faces=self.faces, uv=self.uv,
                 normals=self.normals, vertex_map=self.vertex_map, face_map=self.face_map,
                 size=np.array([self.width, self.height]),
                 texels_per_metre=np.array(self.texels_per_metre),
                 n_charts=np.array(self.n_charts), n_pieces=np.array(self.n_pieces),
                 seconds=np.array(self.seconds),
                 degenerate_faces=self.report.degenerate_faces,
                 nonmanifold_faces=self.report.nonmanifold_faces,
                 report_counts=np.array([self.report.n_vertices, self.report.n_faces,
                                         self.report.nonmanifold_edges]))

    @classmethod
    def load(cls, path) -> "Atlas":
        """Read an atlas written by :meth:`save`."""
        with np.load(path) as d:
            nv, nf, nme = (int(x) for x in d["report_counts"])
            fm = d["face_map"].astype(np.int64)
            rep = MeshReport(nv, nf, d["degenerate_faces"], nme, d["nonmanifold_faces"],
                             np.unique(fm))
            return cls(d["vertices"], d["faces"].astype(np.int64), d["uv"], d["normals"],
                       d["vertex_map"].astype(np.int64), fm, int(d["size"][0]),
                       int(d["size"][1]), float(d["texels_per_metre"]), int(d["n_charts"]),
                       rep, float(d["seconds"]), int(d["n_pieces"]))


def check_atlas_settings(*, texels_per_mm=None, size=None, padding=0) -> None:
    """Raise :class:`InputError` naming the setting when the atlas resolution or padding is
    not one :func:`build_atlas` accepts (checked by the command line before the stages that
    build the mesh run, so that a wrong ``--size`` costs no decode)."""
    if texels_per_mm is not None and size is not None:
        raise InputError("texels_per_mm and size: give one resolution, not both")
    if texels_per_mm is not None and not (np.isfinite(texels_per_mm) and texels_per_mm > 0):
        raise InputError(f"texels_per_mm: expected a finite number > 0, got {fmt_value(texels_per_mm)}")
    if size is not None and (int(size) != size or not 16 <= size <= 1 << 15):
        raise InputError(f"size: expected an integer in [16, 32768], got {fmt_value(size)}")
    if int(padding) != padding or padding < 0:
        raise InputError(f"padding: expected an integer >= 0, got {fmt_value(padding)}")


def build_atlas(vertices: Any, faces: Any, *, texels_per_mm: float | None = None,
                size: int | None = None, padding: int = 2, max_chart_area: float = 0.0,
                max_boundary_length: float = 0.0, max_iterations: int = 1,
                max_chart_faces: float | None = DEFAULT_MAX_CHART_FACES,
                split_faces: int | None = DEFAULT_SPLIT_FACES, repair: bool = False,
                normals: Any = None) -> Atlas:
    """Parameterise a mesh with xatlas and pack its charts into one atlas.

    Parameters
    ----------
    vertices : (V, 3) float64, metres, world frame
    faces : (F, 3) int
    texels_per_mm : float, optional
        Resolution as texels per millimetre of surface (along each axis). Exclusive with
        ``size``.
    size : int, optional
        Approximate atlas width/height in texels (xatlas picks the scale). Default 1024 when
        neither is given.
    padding : int
        Empty texels around each chart (≥ 0).
    max_chart_area, max_boundary_length : float
        xatlas chart limits in mesh units (m², m); 0 means unlimited.
    max_iterations : int
        xatlas chart-growing iterations (more: better charts, slower).
    max_chart_faces : float or None
        When ``max_chart_area`` is 0: limit charts to the area of this many average faces
        (``max_chart_area = max_chart_faces × mean face area``); None or 0: unlimited. xatlas's
        cost grows steeply with the faces per chart (module docstring, "Speed").
    split_faces : int or None
        Split meshes with more faces into pieces of at most this many (see module docstring);
        None or 0 never splits.
    repair : bool
        Passed to :func:`check_mesh`.
    normals : (V, 3) float64, optional
        Shading normals per input vertex; default :func:`vertex_normals`.

    Returns
    -------
    Atlas

    Raises
    ------
    InputError
        Bad mesh (see :func:`check_mesh`), bad options, or xatlas failing (the message carries
        the mesh statistics).
    MissingDependencyError
        xatlas is not installed.
    """
    try:
        import xatlas
    except ImportError as exc:  # pragma: no cover - a declared dependency
        raise MissingDependencyError("build_atlas needs xatlas (pip install xatlas)") from exc
    V, F, report = check_mesh(vertices, faces, repair=repair)
    check_atlas_settings(texels_per_mm=texels_per_mm, size=size, padding=padding)
    if normals is None:
        N = vertex_normals(V, F)
    else:
        N = as_array(normals, "normals", shape=(len(V), 3))
    split = int(split_faces or 0)
    pieces = split_mesh(V, F, split) if split and len(F) > split else [np.arange(len(F))]

    if not (np.isfinite(max_chart_area) and max_chart_area >= 0):
        raise InputError(f"max_chart_area: expected a finite number >= 0 (m²), got "
                         f"{fmt_value(max_chart_area)}")
    if max_chart_faces is not None and not (np.isfinite(max_chart_faces)
                                            and max_chart_faces >= 0):
        raise InputError(f"max_chart_faces: expected a number >= 0 or None, got "
                         f"{fmt_value(max_chart_faces)}")
    # Every check before the first add_mesh: xatlas queues each mesh on its worker threads, and
    # an Atlas destroyed before generate() has joined them can deadlock (an InputError raised
    # after add_mesh hung 2 runs in 8).
    atlas = xatlas.Atlas()
    piece_verts = []
    for idx in pieces:
        used, local = np.unique(F[idx], return_inverse=True)
        piece_verts.append(used)
        atlas.add_mesh(np.ascontiguousarray(V[used], np.float32),
                       np.ascontiguousarray(local.reshape(-1, 3), np.uint32))
    chart_area = float(max_chart_area)
    if chart_area == 0 and max_chart_faces:
        area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                    axis=1)
        chart_area = float(max_chart_faces) * float(area.mean())
    co = xatlas.ChartOptions()
    co.max_chart_area = chart_area
    co.max_boundary_length = float(max_boundary_length)
    co.max_iterations = int(max_iterations)
    po = xatlas.PackOptions()
    po.padding = int(padding)
    po.bilinear = True
    if texels_per_mm is not None:
        po.texels_per_unit = float(texels_per_mm) * 1000.0
        po.resolution = 0
    else:
        po.resolution = int(size or 1024)
        po.texels_per_unit = 0.0
    t0 = time.perf_counter()
    try:
        atlas.generate(chart_options=co, pack_options=po)
    except Exception as exc:  # xatlas raises plain RuntimeError/ValueError
        raise InputError(f"xatlas failed on the mesh ({report.summary()}, {len(pieces)} "
                         f"piece(s)): {exc}") from exc
    seconds = time.perf_counter() - t0
    if atlas.atlas_count != 1 or atlas.width == 0:
        raise InputError(f"xatlas produced {atlas.atlas_count} atlases of {atlas.width} × "
                         f"{atlas.height} texels (expected one) for a mesh with "
                         f"{report.summary()}; lower the resolution")

    verts, fcs, uvs, vmaps, fmaps = [], [], [], [], []
    base = 0
    for i, idx in enumerate(pieces):
        vmap, ind, uv = atlas[i]
        ind = ind.astype(np.int64)
        if len(ind) != len(idx):
            raise InputError(f"xatlas dropped {len(idx) - len(ind)} of {len(idx)} faces of "
                             f"piece {i} ({report.summary()})")
        vm = piece_verts[i][vmap.astype(np.int64)]
        verts.append(V[vm])
        vmaps.append(vm)
        uvs.append(uv.astype(np.float64))
        fcs.append(ind + base)
        fmaps.append(report.kept_faces[idx])
        base += len(vm)
    vmap_all = np.concatenate(vmaps)
    uv = np.concatenate(uvs)
    uv[:, 1] = 1.0 - uv[:, 1]  # xatlas: y down from the top row; OBJ: v up
    out = Atlas(
        vertices=np.concatenate(verts), faces=np.concatenate(fcs), uv=uv,
        normals=N[vmap_all], vertex_map=vmap_all, face_map=np.concatenate(fmaps),
        width=int(atlas.width), height=int(atlas.height),
        texels_per_metre=float(atlas.texels_per_unit), n_charts=int(atlas.chart_count),
        report=report, seconds=seconds, n_pieces=len(pieces),
        meta={"utilization": float(np.mean(atlas.utilization)), "max_chart_area": chart_area},
    )
    log.info("atlas: %d faces in %d piece(s) -> %d charts, %d × %d texels, %.2f s",
             len(F), len(pieces), out.n_charts, out.width, out.height, seconds)
    return out


@dataclass
class Texels:
    """The texel table of an atlas: one row per texel whose centre lies in a chart triangle.

    Attributes
    ----------
    row, col : (T,) int64
        Atlas pixel of each texel (row 0 at the top; see the module docstring).
    face : (T,) int64
        Atlas face containing the texel centre (``Atlas.face_map[face]`` is the input face).
    bary : (T, 3) float64
        Barycentric weights of the face's corners (non-negative, sum 1).
    p_world : (T, 3) float64, metres, world frame
        Surface position.
    n_world : (T, 3) float64, unit, world frame
        Interpolated (shading) normal.
    n_geom : (T, 3) float64, unit, world frame
        Geometric normal of the face (its winding's side).
    index_map : (H, W) int64
        Texel index of each atlas pixel; -1 where no texel.
    """

    row: np.ndarray
    col: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    p_world: np.ndarray
    n_world: np.ndarray
    n_geom: np.ndarray
    index_map: np.ndarray

    def __len__(self) -> int:
        return int(self.row.size)

    @property
    def shape(self) -> tuple[int, int]:
        """Atlas (height, width)."""
        return tuple(self.index_map.shape)  # type: ignore[return-value]

    def to_image(self, values: Any, fill: float = np.nan) -> np.ndarray:
        """Scatter per-texel values ``(T, ...)`` into an atlas image ``(H, W, ...)``."""
        values = np.asarray(values)
        if values.shape[:1] != (len(self),):
            raise ShapeError(f"values: expected {len(self)} rows (one per texel), got "
                             f"{values.shape}")
        h, w = self.shape
        out = np.full((h, w) + values.shape[1:], fill,
                      dtype=np.result_type(values.dtype, np.float32)
                      if np.isnan(fill) else values.dtype)
        out[self.row, self.col] = values
        return out

    def save(self, path) -> None:
        np.savez(path, row=self.row, col=self.col, face=self.face, bary=self.bary,
                 p_world=self.p_world, n_world=self.n_world, n_geom=self.n_geom,
                 shape=np.array(self.shape))

    @classmethod
    def load(cls, path) -> "Texels":
        with np.load(path) as d:
            row, col = d["row"], d["col"]
            h, w = (int(x) for x in d["shape"])
            index_map = np.full((h, w), -1, np.int64)
            index_map[row, col] = np.arange(row.size)
            return cls(row, col, d["face"], d["bary"], d["p_world"], d["n_world"],
                       d["n_geom"], index_map)


def rasterize_texels(atlas: Atlas) -> Texels:
    """Find every texel whose centre lies inside a chart triangle (vectorised).

    Triangles are sorted by the size of their texel bounding boxes and processed in batches:
    each batch tests a padded grid of candidate centres per triangle with 2-D barycentrics in
    float64 (no loop per texel or per triangle). Barycentrics in UV space equal those on the 3-D
    triangle (the map between them is affine), so ``p_world`` is exact to rounding.

    Parameters
    ----------
    atlas : Atlas

    Returns
    -------
    Texels
    """
    W, H = atlas.width, atlas.height
    F = atlas.faces
    # Atlas pixel coordinates: texel centres at integers (module docstring).
    x = atlas.uv[:, 0] * W - 0.5
    y = (1.0 - atlas.uv[:, 1]) * H - 0.5
    tx, ty = x[F], y[F]  # (F, 3)
    x0 = np.clip(np.ceil(tx.min(axis=1) - _INSIDE_TOL), 0, W - 1).astype(np.int64)
    x1 = np.clip(np.floor(tx.max(axis=1) + _INSIDE_TOL), -1, W - 1).astype(np.int64)
    y0 = np.clip(np.ceil(ty.min(axis=1) - _INSIDE_TOL), 0, H - 1).astype(np.int64)
    y1 = np.clip(np.floor(ty.max(axis=1) + _INSIDE_TOL), -1, H - 1).astype(np.int64)
    bw = np.maximum(x1 - x0 + 1, 0)
    bh = np.maximum(y1 - y0 + 1, 0)
    # Signed doubled area in pixel coordinates; zero-area UV triangles hold no texel.
    area2 = ((tx[:, 1] - tx[:, 0]) * (ty[:, 2] - ty[:, 0])
             - (tx[:, 2] - tx[:, 0]) * (ty[:, 1] - ty[:, 0]))
    live = np.flatnonzero((bw > 0) & (bh > 0) & (area2 != 0))
    live = live[np.argsort((bw * bh)[live], kind="stable")]
    faces_out, pix_out, bary_out = [], [], []
    s = 0
    while s < len(live):
        # Grow the batch while the padded candidate grid stays under the budget.
        cells = np.maximum.accumulate(bw[live[s:]]) * np.maximum.accumulate(bh[live[s:]])
        n = int(np.searchsorted(cells * np.arange(1, len(cells) + 1), _RASTER_BATCH,
                                side="right"))
        n = max(n, 1)
        f = live[s:s + n]
        s += n
        mw, mh = int(bw[f].max()), int(bh[f].max())
        oy, ox = np.divmod(np.arange(mw * mh), mw)
        cx = x0[f, None] + ox[None, :]
        cy = y0[f, None] + oy[None, :]
        ok = (ox[None, :] < bw[f, None]) & (oy[None, :] < bh[f, None])
        ax, ay = tx[f, 0, None], ty[f, 0, None]
        e1x, e1y = tx[f, 1, None] - ax, ty[f, 1, None] - ay
        e2x, e2y = tx[f, 2, None] - ax, ty[f, 2, None] - ay
        px, py = cx - ax, cy - ay
        inv = 1.0 / area2[f, None]
        b1 = (px * e2y - py * e2x) * inv
        b2 = (e1x * py - e1y * px) * inv
        b0 = 1.0 - b1 - b2
        ok &= (b0 >= -_INSIDE_TOL) & (b1 >= -_INSIDE_TOL) & (b2 >= -_INSIDE_TOL)
        ti, ci = np.nonzero(ok)
        faces_out.append(f[ti])
        pix_out.append(cy[ti, ci] * W + cx[ti, ci])
        bary_out.append(np.stack([b0[ti, ci], b1[ti, ci], b2[ti, ci]], axis=1))
    face = np.concatenate(faces_out) if faces_out else np.zeros(0, np.int64)
    pix = np.concatenate(pix_out) if pix_out else np.zeros(0, np.int64)
    bary = np.concatenate(bary_out) if bary_out else np.zeros((0, 3))
    # One texel per pixel: on shared edges keep the lowest face index; order texels by pixel.
    order = np.lexsort((face, pix))
    pix, face, bary = pix[order], face[order], bary[order]
    first = np.r_[True, pix[1:] != pix[:-1]] if pix.size else np.zeros(0, bool)
    pix, face, bary = pix[first], face[first], bary[first]
    bary = np.clip(bary, 0.0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    row, col = np.divmod(pix, W)
    tri = atlas.vertices[atlas.faces[face]]  # (T, 3, 3)
    p = np.einsum("tk,tkc->tc", bary, tri)
    ng = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ng /= np.linalg.norm(ng, axis=1, keepdims=True)
    ni = np.einsum("tk,tkc->tc", bary, atlas.normals[atlas.faces[face]])
    nlen = np.linalg.norm(ni, axis=1, keepdims=True)
    # A corner without a normal (NaN) or normals cancelling out: fall back to the face normal.
    ni = np.where(np.isfinite(nlen) & (nlen > 1e-12), ni / np.where(nlen > 0, nlen, 1), ng)
    index_map = np.full((H, W), -1, np.int64)
    index_map[row, col] = np.arange(row.size)
    return Texels(row=row, col=col, face=face, bary=bary, p_world=p, n_world=ni, n_geom=ng,
                  index_map=index_map)


def export_mesh_uv(atlas: Atlas, path) -> Path:
    """Write the atlas mesh with UVs and normals through trimesh (``process=False``).

    Parameters
    ----------
    atlas : Atlas
    path : path-like
        ``.obj`` (``vt`` UVs in OBJ's v-up convention, ``vn`` normals, 9 digits, and a
        ``<stem>.mtl`` beside it) or ``.glb``
        (trimesh converts to glTF's v-down convention itself, with a plain PBR material).

    Returns
    -------
    pathlib.Path
    """
    import trimesh

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".obj", ".glb"):
        raise InputError(f"path: expected a .obj or .glb file name, got {fmt_value(str(path))}")
    mesh = trimesh.Trimesh(atlas.vertices, atlas.faces, vertex_normals=atlas.normals,
                           process=False)
    # A PBR material without an image: trimesh's default material needs Pillow.
    mesh.visual = trimesh.visual.TextureVisuals(
        uv=atlas.uv, material=trimesh.visual.material.PBRMaterial(name="facegeo_atlas"))
    if suffix == ".obj":
        from trimesh.exchange.obj import export_obj

        text, files = export_obj(mesh, include_normals=True, include_texture=True, digits=9,
                                 write_texture=False, return_texture=True,
                                 mtl_name=path.stem + ".mtl")
        for name, data in files.items():  # the .mtl the OBJ names (no image: Pillow-free)
            (path.parent / name).write_bytes(data)
        path.write_text(text)
    else:
        path.write_bytes(trimesh.exchange.gltf.export_glb(trimesh.Scene(mesh)))
    return path
