"""Meshing of triangulated points: oriented normals, screened Poisson, trimming, error figures.

* :func:`oriented_normals` — PCA normals over the k nearest neighbours (Open3D), each flipped to
  face the camera that observed the point. That orientation is free and exact for
  structured-light points (every point has an observing camera), where a
  consistent-tangent-plane propagation costs about a minute at 1 M points.
* :func:`poisson_mesh` — Open3D's screened Poisson reconstruction (Kazhdan & Hoppe 2013) with
  per-vertex densities; vertices whose density is below the ``trim_quantile`` quantile, or that
  lie farther than ``max_distance`` from every input point, are removed (Poisson closes the
  surface; the face is open, and the closing skin is invented), then connected components
  smaller than ``min_component`` of the largest, then optional quadric decimation. Runs
  single-threaded, so the same input gives the same mesh. ``depth="auto"`` and
  ``max_distance="auto"`` derive both from the points (:func:`poisson_depth_for`,
  :func:`trim_distance_for`) so that the trim agrees with the Poisson cell (issue 34: a fixed
  depth 7 and a trim of 1.5 fine spacings removed 90 % of a real bust's mesh).
  With ``fill_distance`` it also returns the *filled* surface (issue 37): a second solve over
  a cube :data:`AUTO_FILL_SCALE` times the points' extent, trimmed by distance alone, whose
  surface beyond the data is not pressed against the cube's faces.
* :func:`grid_mesh` — the cheap one-camera path: two triangles per 2 × 2 block of pixels that
  all hold points and whose depths do not jump.
* :func:`surface_errors` (in :mod:`facegeo.geometry._mesh_measure`, re-exported here) —
  distances and normal angles against a reference mesh (Open3D
  ``RaycastingScene``), and :func:`area_beyond` — mesh area farther than a radius from any
  observed point.

References
----------
.. [1] Kazhdan & Hoppe, "Screened Poisson Surface Reconstruction", ACM TOG 32(3), 2013.
.. [2] Debevec et al., "Acquiring the Reflectance Field of a Human Face", SIGGRAPH 2000, §2
   (the face geometry from structured light, used to project the reflectance functions).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from facegeo.checks import as_array, check_positive, check_positive_int, fmt_value
from facegeo.errors import InputError, ShapeError
from facegeo.geometry._mesh_measure import (  # noqa: F401  (re-exported)
    _o3d,
    _vertex_normals,
    align_to_surface,
    area_beyond,
    closest_surface_points,
    face_areas,
    sample_surface,
    surface_errors,
)

log = logging.getLogger(__name__)

__all__ = [
    "AUTO_FILL_SCALE",
    "Mesh",
    "PoissonDepth",
    "align_to_surface",
    "area_beyond",
    "closest_surface_points",
    "degenerate_faces",
    "face_areas",
    "fill_depth_for",
    "fill_distance_for",
    "grid_mesh",
    "inferred_faces_path",
    "median_neighbour_distance",
    "oriented_normals",
    "poisson_depth_for",
    "poisson_mesh",
    "sample_surface",
    "surface_errors",
    "trim_distance_for",
]

#: ``depth="auto"``: the smallest octree depth whose cell is at most this many neighbour
#: spacings (the points' median 6th-neighbour distance), so the cell lands in (1.375, 2.75]
#: spacings. Measured (docs/mesh.md, *Poisson depth and trim from the points*): finer cells
#: follow the point noise (normals 2–9× worse below 1.25 spacings on noisy analytic surfaces),
#: coarser ones round off detail; on the real bust (2.3 and 2.5 spacings, two decodes) and the
#: synthetic small face (1.4) this picks the depth with the best normals or distances of those
#: measured.
AUTO_CELL_SPACINGS = 2.75
#: ``depth="auto"`` goes no deeper (time and memory; docs/mesh.md).
AUTO_MAX_DEPTH = 10
#: ``depth="auto"`` goes no shallower (the smallest depth :func:`poisson_mesh` takes).
AUTO_MIN_DEPTH = 4
#: ``max_distance="auto"`` keeps a vertex within ``max(AUTO_TRIM_SPACINGS × spacing,
#: AUTO_TRIM_CELLS × cell)`` of a point (:func:`trim_distance_for`).
AUTO_TRIM_SPACINGS = 1.5
AUTO_TRIM_CELLS = 1.0
#: The density trim never removes a vertex whose Poisson density (≈ log2 of the sampling
#: density its support was splatted at) is within this many octaves of the median density of the
#: vertices near the points: a well-sampled surface is not thinned, whatever the quantile.
DENSITY_FLOOR_OCTAVES = 1.0
#: ``fill_distance="auto"``: the filled surface keeps the Poisson vertices within this fraction of
#: the points' extent (the longest side of their bounding box) of a point — a bound on how far
#: the closed Poisson surface is followed beyond the data (:func:`fill_distance_for`; ≈ 60 mm on
#: the generator's 0.22 m heads). In the trimmed mesh's 1.1 × cube that surface balloons (tiny
#: preset, seed 0: 15–25 mm from the points a median 6 mm from the true head, 40–80 mm out
#: 30 mm) and the bound was 0.15; the filled surface's own solve in the
#: :data:`AUTO_FILL_SCALE` cube stays within a median 1.4 mm of the small preset's head (normals
#: 4.7°) out to 60 mm, 1.5 mm (6.3°) to 90 mm, where it starts to leave it (docs/mesh.md,
#: *The filled surface*).
AUTO_FILL_EXTENT_FRACTION = 0.28
#: The filled surface comes from its own Poisson solve over a bounding cube this many times the
#: points' extent (:func:`poisson_mesh` ``fill_scale``), at the depth whose cell is no coarser
#: than the trimmed mesh's. In PoissonRecon's cube of 1.1 × the extent the closed surface beyond
#: the data is pressed against the cube's faces (Neumann boundary): on the small preset's chain
#: (seed 0) its inferred part lay a median 3.1 mm from the true head, 98 % outside it, normals
#: 17° off, with a flat cap above the head. In a cube of 4 × the extent: 1.1 mm, normals 4.6°
#: (docs/mesh.md, *The filled surface*).
AUTO_FILL_SCALE = 4.0
#: Points queried to estimate the neighbour spacing (an evenly strided subset).
SPACING_QUERIES = 50_000


@dataclass
class Mesh:
    """A triangle mesh with what made it.

    Attributes
    ----------
    vertices : (V, 3) float64, metres, world frame
    faces : (F, 3) int64
    vertex_normals : (V, 3) float64, unit, pointing out of the face (toward the cameras)
    info : dict
        Settings and counts of the reconstruction (depth, point weight, trim quantile, vertices
        removed by each step, seconds).
    inferred_faces : (F,) bool, optional
        Faces of a filled surface that no point supports (:func:`poisson_mesh`
        ``fill_distance``): farther than the trim distance from every point. None: every face
        is measured.
    filled : Mesh, optional
        The same reconstruction with the looser trim that closes over what the points did not
        reach (:func:`poisson_mesh` ``fill_distance``), its ``inferred_faces`` set.
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray
    info: dict = field(default_factory=dict)
    inferred_faces: np.ndarray | None = None
    filled: Mesh | None = None

    @property
    def area(self) -> float:
        """Total area, square metres."""
        return float(face_areas(self.vertices, self.faces).sum())


def _pcd(points, normals=None):
    o3d = _o3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals))
    return pcd


def oriented_normals(points, view_dirs, *, k: int = 24) -> np.ndarray:
    """Unit normals of a point cloud, each facing its observing camera.

    Parameters
    ----------
    points : (N, 3) float64, metres, world frame
    view_dirs : (N, 3) float64, world frame
        From each point toward the camera that observed it (any positive length).
    k : int
        Neighbours of the PCA plane fit (Open3D ``estimate_normals`` with a k-NN search).

    Returns
    -------
    (N, 3) float64, unit vectors with ``n · view_dir ≥ 0``.
    """
    p = as_array(points, "points", shape=(None, 3))
    v = as_array(view_dirs, "view_dirs", shape=(p.shape[0], 3))
    if p.shape[0] < 3:
        raise InputError(f"points: need at least 3 points for normals, got {p.shape[0]}")
    if isinstance(k, bool) or int(k) != k or k < 3:
        raise InputError(f"k: expected an integer >= 3, got {k!r}")
    o3d = _o3d()
    pcd = _pcd(p)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=int(min(k, p.shape[0]))))
    n = np.asarray(pcd.normals, np.float64).copy()
    flip = np.einsum("ij,ij->i", n, v) < 0
    n[flip] *= -1.0
    return n


def _compact(V, F, keep_v):
    """Drop vertices not in ``keep_v`` and faces touching them; reindex."""
    keep_f = keep_v[F].all(axis=1)
    F = F[keep_f]
    used = np.zeros(len(V), bool)
    used[F.ravel()] = True
    remap = np.full(len(V), -1, np.int64)
    remap[used] = np.arange(int(used.sum()))
    return V[used], remap[F], used


def _components(F, n_vertices):
    """Connected component label of each face (shared vertices connect faces)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(F) == 0:
        return np.zeros(0, np.int64)
    rows = np.repeat(np.arange(len(F)), 3)
    # face–vertex incidence; components of the bipartite graph
    A = coo_matrix((np.ones(rows.size), (rows, len(F) + F.ravel())),
                   shape=(len(F) + n_vertices,) * 2)
    _, lab = connected_components(A, directed=False)
    return lab[: len(F)]


@dataclass(frozen=True)
class PoissonDepth:
    """The octree depth chosen for a point cloud, and the figures it was chosen from.

    Attributes
    ----------
    depth : int
    cell : float, metres
        Side of a finest octree cell, ``scale × side / 2^depth``.
    side : float, metres
        Longest side of the points' axis-aligned bounding box (Open3D's PoissonRecon grids the
        cube of ``scale`` × this side around the box's centre).
    spacing : float, metres
        The points' median 6th-neighbour distance (:func:`median_neighbour_distance`).
    limited_by : {"spacing", "max_depth", "min_depth"}
        What set the depth: the spacing rule, or one of the bounds.
    """

    depth: int
    cell: float
    side: float
    spacing: float
    limited_by: str


def median_neighbour_distance(points, k: int = 6, *, max_queries: int = SPACING_QUERIES,
                              tree=None) -> float:
    """Median distance of a point to its ``k``-th nearest neighbour, metres.

    The sampling scale of a point cloud (≈ 1.4 point spacings for ``k = 6`` on a surface); the
    same figure as :func:`facegeo.geometry.triangulation.neighbour_spacing`, which queries every
    point, estimated here from at most ``max_queries`` evenly strided points (exact when there
    are fewer): at 3 M points the full query holds ≈ 340 MB of neighbour lists for one number.

    Parameters
    ----------
    points : (N, 3) float64, metres, N ≥ 2
    k : int
    max_queries : int
    tree : scipy.spatial.cKDTree, optional
        A tree already built over ``points`` (reused, not rebuilt).
    """
    p = as_array(points, "points", shape=(None, 3))
    if len(p) < 2:
        raise InputError(f"points: need at least 2 points for a spacing, got {len(p)}")
    k = check_positive_int(k, "k")
    m = check_positive_int(max_queries, "max_queries")
    if tree is None:
        from scipy.spatial import cKDTree

        tree = cKDTree(p)
    stride = -(-len(p) // m)  # ceil: at most m queries
    d, _ = tree.query(p[::stride], k=min(k + 1, len(p)))
    return float(np.median(d[:, -1]))


def _cube_side(p) -> float:
    return float((p.max(axis=0) - p.min(axis=0)).max())


def _check_depth(depth, name="depth", *, allow_auto=True):
    if allow_auto and isinstance(depth, str) and depth == "auto":
        return "auto"
    ok = not isinstance(depth, (bool, str))
    if ok:
        try:
            ok = int(depth) == depth and 4 <= int(depth) <= 12
        except (TypeError, ValueError, OverflowError):
            ok = False
    if not ok:
        what = "'auto' or an integer" if allow_auto else "an integer"
        raise InputError(f"{name}: expected {what} in [4, 12], got {fmt_value(depth)}")
    return int(depth)


def poisson_depth_for(points, *, spacing: float | None = None, scale: float = 1.1,
                      cell_spacings: float = AUTO_CELL_SPACINGS,
                      min_depth: int = AUTO_MIN_DEPTH,
                      max_depth: int = AUTO_MAX_DEPTH) -> PoissonDepth:
    """The Poisson octree depth whose cell matches the points' sampling.

    The smallest depth whose cell ``scale × side / 2^depth`` is at most ``cell_spacings`` ×
    the points' median 6th-neighbour distance, within ``[min_depth, max_depth]``: with the
    default 2.75 the cell lands in (1.375, 2.75] spacings, fine enough to keep what the sampling
    resolves and coarse enough that screened Poisson does not follow the point noise (measured
    on noisy analytic surfaces, the synthetic faces and the real bust: docs/mesh.md).

    Parameters
    ----------
    points : (N, 3) float64, metres, N ≥ 2
    spacing : float, metres, optional
        The points' median 6th-neighbour distance, when already known (default: measured,
        :func:`median_neighbour_distance`).
    scale : float
        PoissonRecon's bounding-cube scale (:func:`poisson_mesh`).
    cell_spacings : float
        Largest cell, in spacings.
    min_depth, max_depth : int, in [4, 12]
        Bounds of the depth; ``max_depth`` bounds time and memory, which follow the octree
        (≈ 4× a level): 1–3 M points at depth 9 ≈ 15 s and ≈ 0.35–0.5 GB, 3 M at depth 10
        64 s and 1.4 GB (docs/mesh.md).

    Returns
    -------
    PoissonDepth

    Raises
    ------
    InputError
        A bound outside [4, 12] or ``min_depth > max_depth``; points with no extent or a zero
        spacing (most points duplicated).
    """
    p = as_array(points, "points", shape=(None, 3))
    lo = _check_depth(min_depth, "min_depth", allow_auto=False)
    hi = _check_depth(max_depth, "max_depth", allow_auto=False)
    if lo > hi:
        raise InputError(f"min_depth: {lo} is above max_depth {hi}")
    s = check_positive(scale, "scale")
    c = check_positive(cell_spacings, "cell_spacings")
    h = _spacing_of(p, spacing)
    side = _cube_side(p)
    if side <= 0:
        raise InputError("points: all points coincide; there is no extent to grid")
    # smallest d with s·side/2^d ≤ c·h
    want = int(np.ceil(np.log2(s * side / (c * h)) - 1e-9))
    depth = min(max(want, lo), hi)
    limited_by = "spacing" if depth == want else ("max_depth" if want > hi else "min_depth")
    return PoissonDepth(depth, s * side / 2**depth, side, h, limited_by)


def _spacing_of(p, spacing, tree=None) -> float:
    if spacing is not None:
        return check_positive(spacing, "spacing")
    h = median_neighbour_distance(p, tree=tree)
    if h <= 0:
        raise InputError("points: the median 6th-neighbour distance is 0 (most points are "
                         "duplicated); remove the duplicates or pass spacing=")
    return h


def trim_distance_for(spacing: float, cell: float) -> float:
    """The distance from the points beyond which a Poisson vertex counts as invented, metres.

    ``max(AUTO_TRIM_SPACINGS × spacing, AUTO_TRIM_CELLS × cell)`` = ``max(1.5 h, 1 cell)``. A
    vertex of a well-sampled analytic surface lies within ≈ 0.8 spacings of a sample; a coarse
    cell rounds the surface off, by up to ≈ 0.2 cell on analytic detail and by more on a real
    capture's gaps and correlated errors (on the real bust at quarter resolution, depth 8, the
    vertices on the reference surface are within 1.05 spacings of a point at the 95th
    percentile, 2.5 at the 98th; the skin Poisson invents starts ≈ 6 spacings out). At the auto
    depth the trim is 1.5–2.75 spacings. A fixed 1.5 spacings removed 90 % of a depth-7 bust at
    full resolution, whose 2 mm cells were ≈ 13 spacings (issue 34).

    Parameters
    ----------
    spacing : float, metres — the points' median 6th-neighbour distance
    cell : float, metres — the Poisson cell (:class:`PoissonDepth`)
    """
    h = check_positive(spacing, "spacing")
    c = check_positive(cell, "cell")
    return max(AUTO_TRIM_SPACINGS * h, AUTO_TRIM_CELLS * c)


def _check_max_distance(max_distance, name="max_distance"):
    if max_distance is None or (isinstance(max_distance, str) and max_distance == "auto"):
        return max_distance
    bad = isinstance(max_distance, (bool, str))
    if not bad:
        try:
            v = float(max_distance)
            bad = not (np.isfinite(v) and v > 0)
        except (TypeError, ValueError):
            bad = True
    if bad:
        raise InputError(f"{name}: expected 'auto', None or a distance > 0 in metres, got "
                         f"{fmt_value(max_distance)}")
    return v


def poisson_mesh(points, normals, *, depth: int | str = 7, point_weight: float = 4.0,
                 scale: float = 1.1, samples_per_node: float = 1.5,
                 trim_quantile: float = 0.02, max_distance: float | str | None = 2e-3,
                 spacing: float | None = None, max_depth: int = AUTO_MAX_DEPTH,
                 min_component: float = 0.05, target_faces: int | None = None,
                 fill_distance: float | str | None = None,
                 fill_scale: float = AUTO_FILL_SCALE, support=None) -> Mesh:
    """Screened Poisson surface of oriented points, trimmed to where the points are.

    Parameters
    ----------
    points : (N, 3) float64, metres, world frame
    normals : (N, 3) float64, unit, oriented outward (toward the cameras)
    depth : int in [4, 12], or "auto"
        Octree depth (grid ≤ 2^depth per side over ``scale`` × the points' bounding cube).
        ``"auto"``: the depth whose cell matches the points' spacing
        (:func:`poisson_depth_for`, at most ``max_depth``).
    point_weight : float
        Screening weight of the point interpolation term (Kazhdan & Hoppe 2013, α).
    scale, samples_per_node
        Open3D / PoissonRecon settings.
    trim_quantile : float, 0..1
        Remove vertices whose Poisson density (≈ log2 of the sampling density of the samples
        supporting them) is below this quantile of all vertices' densities — but never a vertex
        within :data:`DENSITY_FLOOR_OCTAVES` of the median density of the vertices near the
        points (within ``max_distance``; all vertices without a distance trim), so a
        well-sampled surface is not thinned into holes.
    max_distance : float (metres), "auto" or None
        Also remove vertices farther than this from every input point (no invented skin where
        no camera saw the face). ``"auto"``: :func:`trim_distance_for` the spacing and the
        Poisson cell, so the trim agrees with the depth. ``None`` keeps them.
    spacing : float, metres, optional
        The points' median 6th-neighbour distance if already known (default: measured when
        ``depth`` or ``max_distance`` is ``"auto"``).
    max_depth : int in [4, 12]
        Deepest depth ``"auto"`` chooses.
    min_component : float, 0..1
        Remove connected components with fewer faces than this fraction of the largest one.
    target_faces : int, optional
        Quadric decimation to at most this many faces (after trimming).
    fill_distance : float (metres), "auto" or None
        Also make the *filled* surface (``Mesh.filled``): a Poisson solution (its own, in the
        ``fill_scale`` cube) trimmed only by distance — vertices within ``fill_distance`` of a
        point (at least the trim distance), no density trim — so it closes over holes and
        continues the surface past the edge of what the points reached, but no farther than
        this bound from the data (no balloon). Its faces with a vertex farther than the trim distance (``max_distance``)
        from every point are ``inferred_faces``. ``"auto"``: :func:`fill_distance_for`.
        None (default): no filled surface. Needs ``max_distance``.
    fill_scale : float
        The filled surface's Poisson solve grids a cube of ``fill_scale`` × the points' extent
        (:data:`AUTO_FILL_SCALE`), at the smallest depth (at most 12) whose cell is no coarser
        than this solve's: a second solve, whose surface away from the data is not pressed
        against the cube's faces. Equal to ``scale``: the filled surface is cut from this
        solve (its measured faces are then exactly the trimmed mesh's). Its zero-area faces
        (repeated or collinear corners, which the atlas refuses) are dropped
        (``info["degenerate_faces_dropped"]``).
    support : callable, optional
        ``support(filled) -> (points, normals)``, (S, 3) float64 each: oriented points that
        shape the filled surface only, found against the filled surface of the points alone —
        the cameras' silhouette rims (:func:`facegeo.geometry.silhouette.rim_points`). When it
        returns any, the filled surface is solved again with them (its own solve, whatever
        ``fill_scale``; the trimmed mesh's solve is not repeated): they are part of its Poisson
        solve and of its distance bound, but never of the trimmed mesh, its trim, the fill
        distance ``"auto"`` measures, or which faces count as measured (a face near a support
        point alone stays inferred). ``info["support_points"]`` counts them.

    Returns
    -------
    Mesh
        ``info`` records every setting, the chosen depth (``depth``, ``depth_auto``,
        ``depth_limited_by``), ``cell_mm``, ``spacing_mm`` (None when not needed),
        ``max_distance_mm`` and ``max_distance_auto``, the density threshold, and how many
        vertices each step removed (``trimmed_density``, ``trimmed_distance``,
        ``trimmed_components``, ``decimated``). With ``fill_distance``, ``filled`` holds the
        filled surface; its ``info`` has ``fill_distance_mm``, ``fill_scale``, ``fill_depth``,
        ``fill_cell_mm``, ``faces``, ``vertices`` and ``inferred_faces`` (their count).

    Raises
    ------
    InputError
        Fewer than 10 points; ``depth`` not ``"auto"`` nor an integer in [4, 12];
        ``max_distance`` not ``"auto"``, None nor a positive distance; ``fill_distance``
        without ``max_distance``; a setting out of range.

    Notes
    -----
    Open3D runs PoissonRecon with ``n_threads=1`` here: its multi-threaded solve is not
    bit-for-bit repeatable, and the stage promises the same mesh for the same points.
    """
    import time

    p = as_array(points, "points", shape=(None, 3))
    n = as_array(normals, "normals", shape=(p.shape[0], 3))
    if p.shape[0] < 10:
        raise InputError(f"points: need at least 10 oriented points for a Poisson mesh, got "
                         f"{p.shape[0]}")
    depth = _check_depth(depth)
    max_depth = _check_depth(max_depth, "max_depth", allow_auto=False)
    max_distance = _check_max_distance(max_distance)
    fill_distance = _check_max_distance(fill_distance, "fill_distance")
    if fill_distance is not None and max_distance is None:
        raise InputError("fill_distance: the filled surface marks the faces beyond the trim "
                         "distance as inferred; give max_distance too ('auto' or metres)")
    if not 0.0 <= trim_quantile < 1.0:
        raise InputError(f"trim_quantile: expected a value in [0, 1), got {trim_quantile!r}")
    if not 0.0 <= min_component <= 1.0:
        raise InputError(f"min_component: expected a fraction in [0, 1], got {min_component!r}")
    check_positive(point_weight, "point_weight", allow_zero=True)
    scale = check_positive(scale, "scale")
    fill_scale = check_positive(fill_scale, "fill_scale")
    if spacing is not None:
        spacing = check_positive(spacing, "spacing")
    if support is not None and fill_distance is None:
        raise InputError("support: its points shape the filled surface only; give "
                         "fill_distance too ('auto' or metres)")
    t0 = time.perf_counter()
    tree = None
    if max_distance is not None or (spacing is None and depth == "auto"):
        from scipy.spatial import cKDTree

        tree = cKDTree(p)
    if spacing is None and "auto" in (depth, max_distance):
        spacing = _spacing_of(p, None, tree)
    if depth == "auto":
        grid = poisson_depth_for(p, spacing=spacing, scale=scale, max_depth=max_depth)
        depth_used, cell, limited_by = grid.depth, grid.cell, grid.limited_by
    else:
        depth_used, cell, limited_by = depth, scale * _cube_side(p) / 2**depth, "given"
    r = trim_distance_for(spacing, cell) if max_distance == "auto" else max_distance
    log.debug("poisson_mesh: %d points, depth %d (%s), cell %.3g mm, spacing %s mm, trim %s mm",
              len(p), depth_used, limited_by, 1e3 * cell,
              None if spacing is None else f"{1e3 * spacing:.3g}",
              None if r is None else f"{1e3 * r:.3g}")
    t_poisson = time.perf_counter()
    V, F, dens = _poisson_solve(p, n, depth_used, scale, samples_per_node, point_weight)
    t1 = time.perf_counter()
    info = {"depth": int(depth_used), "depth_auto": depth == "auto",
            "depth_limited_by": limited_by, "cell_mm": 1e3 * cell,
            "spacing_mm": None if spacing is None else 1e3 * spacing,
            "point_weight": float(point_weight), "scale": float(scale),
            "samples_per_node": float(samples_per_node), "trim_quantile": float(trim_quantile),
            "max_distance_mm": None if r is None else 1e3 * r,
            "max_distance_auto": max_distance == "auto",
            "min_component": float(min_component), "target_faces": target_faces,
            "points": int(p.shape[0]), "poisson_vertices": len(V),
            "poisson_faces": len(F), "seconds_spacing": round(t_poisson - t0, 4),
            "seconds_poisson": round(t1 - t_poisson, 4)}
    near = np.ones(len(V), bool)
    dist = np.zeros(len(V))
    r_fill = None if fill_distance is None else max(
        fill_distance_for(p) if fill_distance == "auto" else fill_distance, r)
    if r is not None and len(V):
        dist, _ = tree.query(V, k=1, distance_upper_bound=2 * max(r, r_fill or 0.0))
        near = dist <= r
    def fill(sp=None, sn=None) -> Mesh:
        """The filled surface (issue 37), with support points ``sp``/``sn`` in its solve."""
        fill_info = info | {"fill_distance_mm": 1e3 * r_fill,
                            "fill_distance_auto": fill_distance == "auto",
                            "fill_scale": fill_scale,
                            "support_points": 0 if sp is None else len(sp)}
        if fill_scale == scale and sp is None:  # cut from this solve
            Vf, Ff, dist_f = V, F, dist
            fill_info.update(fill_depth=int(depth_used), fill_cell_mm=1e3 * cell)
        else:  # its own solve in the larger cube, no coarser a cell
            t_fill = time.perf_counter()
            depth_f = fill_depth_for(_cube_side(p), cell, fill_scale)
            pf, nf = (p, n) if sp is None else (np.vstack([p, sp]), np.vstack([n, sn]))
            Vf, Ff, _ = _poisson_solve(pf, nf, depth_f, fill_scale, samples_per_node,
                                       point_weight)
            del pf, nf
            dist_f, _ = tree.query(Vf, k=1, distance_upper_bound=2 * r_fill)
            if sp is not None and len(Vf):
                from scipy.spatial import cKDTree

                dist_f = np.minimum(dist_f, cKDTree(sp).query(
                    Vf, k=1, distance_upper_bound=2 * r_fill)[0])
            fill_info.update(fill_depth=depth_f,
                             fill_cell_mm=1e3 * fill_scale * _cube_side(p) / 2**depth_f,
                             seconds_fill_poisson=round(time.perf_counter() - t_fill, 4))
            info["seconds_fill_poisson"] = fill_info["seconds_fill_poisson"]
        return _filled_surface(Vf, Ff, dist_f <= r_fill, min_component, target_faces, tree,
                               r, fill_info)

    filled = None
    if r_fill is not None:
        filled = fill()
        if support is not None:
            sp, sn = support(filled)
            sp = as_array(sp, "support points", shape=(None, 3))
            sn = as_array(sn, "support normals", shape=(sp.shape[0], 3))
            if len(sp):
                filled = fill(sp, sn)
    del dist, tree
    keep = np.ones(len(V), bool)
    info["density_threshold"] = None
    if trim_quantile > 0 and len(V):
        floor = np.median(dens[near] if near.any() else dens) - DENSITY_FLOOR_OCTAVES
        thr = min(float(np.quantile(dens, trim_quantile)), float(floor))
        keep &= dens >= thr
        info["density_threshold"] = round(thr, 4)
    info["trimmed_density"] = int((~keep).sum())
    if r is not None:
        far = keep & ~near
        keep &= near
        info["trimmed_distance"] = int(far.sum())
    V, F, _ = _compact(V, F, keep)
    n_before = len(V)
    V, F, counts, removed = _drop_small_components(V, F, min_component)
    if counts is not None:
        info["components"], info["removed_components"] = counts, removed
    info["trimmed_components"] = n_before - len(V)
    n_before = len(V)
    V, F = _decimate(V, F, target_faces)
    info["decimated"] = n_before - len(V)
    vn = _vertex_normals(V, F)
    info.update({"vertices": len(V), "faces": len(F),
                 "seconds": round(time.perf_counter() - t0, 4)})
    return Mesh(V, F, vn, info, filled=filled)


def _poisson_solve(p, n, depth, scale, samples_per_node, point_weight):
    """Open3D's screened Poisson reconstruction (Kazhdan & Hoppe 2013), single-threaded:
    ``(V, F, density)``, float64 / int64 / float64."""
    o3d = _o3d()
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        m, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            _pcd(p, n), depth=int(depth), scale=float(scale), linear_fit=False,
            n_threads=1, samples_per_node=float(samples_per_node),
            point_weight=float(point_weight))
    return (np.asarray(m.vertices, np.float64).copy(), np.asarray(m.triangles, np.int64).copy(),
            np.asarray(dens, np.float64).copy())


def fill_depth_for(side: float, cell: float, fill_scale: float) -> int:
    """The octree depth of the filled surface's solve: the smallest whose cell
    ``fill_scale × side / 2^depth`` is at most ``cell`` (the trimmed mesh's), in [4, 12].

    Parameters
    ----------
    side : float, metres — the longest side of the points' bounding box
    cell : float, metres — the trimmed mesh's Poisson cell
    fill_scale : float — the filled surface's cube, in extents (:data:`AUTO_FILL_SCALE`)
    """
    s = check_positive(side, "side")
    c = check_positive(cell, "cell")
    f = check_positive(fill_scale, "fill_scale")
    want = int(np.ceil(np.log2(f * s / c) - 1e-9))
    return min(max(want, AUTO_MIN_DEPTH), 12)


def _drop_small_components(V, F, min_component):
    """Remove connected components with fewer faces than ``min_component`` × the largest's:
    ``(V, F, components, removed)`` (the counts None for a mesh without faces)."""
    lab = _components(F, len(V))
    if not lab.size:
        return V, F, None, None
    counts = np.bincount(lab)
    small = counts < min_component * counts.max()
    F = F[~small[lab]]
    used = np.zeros(len(V), bool)
    used[F.ravel()] = True
    V, F, _ = _compact(V, F, used)
    return V, F, int(counts.size), int(small.sum())


def _decimate(V, F, target_faces):
    """Quadric decimation (Open3D) to at most ``target_faces`` faces; None or fewer faces:
    unchanged."""
    if target_faces is None or len(F) <= target_faces:
        return V, F
    o3d = _o3d()
    mm = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V),
                                   o3d.utility.Vector3iVector(F.astype(np.int32)))
    mm = mm.simplify_quadric_decimation(int(target_faces))
    mm.remove_unreferenced_vertices()
    return (np.asarray(mm.vertices, np.float64).copy(),
            np.asarray(mm.triangles, np.int64).copy())


def inferred_faces_path(mesh_path) -> Path:
    """Where a mesh file's inferred-face flags lie (:attr:`Mesh.inferred_faces`, ``(F,)``
    bool): ``<stem>_inferred.npy`` beside it — the mesh stage writes them for its filled
    surface, the atlas reads them for any mesh file."""
    mesh_path = Path(mesh_path)
    return mesh_path.with_name(mesh_path.stem + "_inferred.npy")


def fill_distance_for(points) -> float:
    """How far from the points the filled surface follows the Poisson solution, metres:
    :data:`AUTO_FILL_EXTENT_FRACTION` × the longest side of the points' bounding box (a
    head's missing strips — under the jaw, beside the nose, the cheeks past the cameras' view —
    are a share of the head, whatever the sampling; ≈ 30 mm on a 0.2 m head).

    Parameters
    ----------
    points : (N, 3) float64, metres
    """
    p = as_array(points, "points", shape=(None, 3))
    return AUTO_FILL_EXTENT_FRACTION * float(np.ptp(p, axis=0).max())


def _filled_surface(V, F, keep, min_component, target_faces, tree, r, info) -> Mesh:
    """The filled surface of :func:`poisson_mesh`: the Poisson vertices in ``keep`` (within
    the fill distance), components smaller than ``min_component`` of the largest removed,
    decimated like the trimmed mesh; a face is inferred when a vertex of it lies farther than
    ``r`` (the trim distance) from every point (after decimation, measured again)."""
    V, F, _ = _compact(V, F, keep)
    V, F, _, _ = _drop_small_components(V, F, min_component)
    V, F = _decimate(V, F, target_faces)
    # marching cubes leaves the odd zero-area face, which the atlas refuses (ICT head, 4 × cube)
    flat = degenerate_faces(V, F)
    if flat.any():
        used = np.zeros(len(V), bool)
        used[F[~flat].ravel()] = True
        V, F, _ = _compact(V, F[~flat], used)
    if len(V):
        d, _ = tree.query(V, k=1, distance_upper_bound=2 * r)
        inferred = ~(d <= r)[F].all(axis=1)
    else:
        inferred = np.zeros(len(F), bool)
    info = {k: info[k] for k in ("depth", "cell_mm", "spacing_mm", "max_distance_mm",
                                 "fill_distance_mm", "fill_distance_auto", "fill_scale",
                                 "fill_depth", "fill_cell_mm", "support_points", "min_component",
                                 "target_faces", "poisson_vertices", "poisson_faces")}
    info.update({"vertices": len(V), "faces": len(F), "inferred_faces": int(inferred.sum()),
                 "degenerate_faces_dropped": int(flat.sum())})
    return Mesh(V, F, _vertex_normals(V, F), info, inferred_faces=inferred)


#: A face is degenerate when ``|e1 × e2| <= DEGENERATE_SIN × max(|e1|², |e2|²)`` (collinear to
#: float64 working precision; the same test as :mod:`facegeo.surface.visibility`) or it repeats
#: a vertex: :func:`degenerate_faces`, which the atlas uses too.
DEGENERATE_SIN = 1e-12


def degenerate_faces(V, F) -> np.ndarray:
    """``(F,)`` bool: faces with a repeated vertex or collinear corners (the filled surface
    drops them; :func:`facegeo.surface.atlas.check_mesh` reports or repairs them)."""
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    if not len(F):
        return np.zeros(0, bool)
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    cr = np.linalg.norm(np.cross(e1, e2), axis=1)
    big = np.maximum(np.einsum("ij,ij->i", e1, e1), np.einsum("ij,ij->i", e2, e2))
    repeated = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 0] == F[:, 2])
    return repeated | ~(cr > DEGENERATE_SIN * big)


def grid_mesh(p_grid, valid=None, *, max_edge_ratio: float = 4.0,
              center_world=None) -> Mesh:
    """Triangulate one camera's point map directly on its pixel grid (the cheap path).

    Two triangles per 2 × 2 block of pixels whose four points exist and whose longest edge is
    at most ``max_edge_ratio`` times the map's median edge (a depth jump at an occlusion is not
    bridged).

    Parameters
    ----------
    p_grid : (H, W, 3) float64, metres, world frame (NaN where no point)
    valid : (H, W) bool, optional (default: finite points)
    max_edge_ratio : float
    center_world : (3,) float64, metres, optional
        The camera centre; faces are wound so their normals face it (default: the winding of
        the image grid seen by an OpenCV camera, which faces the camera).

    Returns
    -------
    Mesh
    """
    P = as_array(p_grid, "p_grid", shape=(None, None, 3), finite=False)
    H, W, _ = P.shape
    ok = np.isfinite(P).all(-1)
    if valid is not None:
        v = as_array(valid, "valid", dtype=bool)
        if v.shape != (H, W):
            raise ShapeError(f"valid: expected shape {(H, W)}, got {v.shape}")
        ok &= v
    idx = np.arange(H * W).reshape(H, W)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    quad_ok = ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, :-1] & ok[1:, 1:]
    Pf = P.reshape(-1, 3)
    # image x right, y down, camera z forward: (a, c, b) is counter-clockwise seen from the camera
    tri = np.concatenate([np.stack([a, c, b], -1)[quad_ok], np.stack([b, c, d], -1)[quad_ok]])
    if len(tri):
        e = np.stack([np.linalg.norm(Pf[tri[:, i]] - Pf[tri[:, (i + 1) % 3]], axis=1)
                      for i in range(3)], 1).max(1)
        tri = tri[e <= max_edge_ratio * np.median(e)]
    used = np.zeros(H * W, bool)
    used[tri.ravel()] = True
    V, F, _ = _compact(np.nan_to_num(Pf), tri.astype(np.int64), used)
    vn = _vertex_normals(V, F)
    if center_world is not None and len(V):
        c = as_array(center_world, "center_world", shape=(3,))
        if np.einsum("ij,ij->", vn, c - V) < 0:
            F = F[:, ::-1].copy()
            vn = -vn
    return Mesh(V, F, vn, {"faces": len(F), "vertices": len(V),
                           "max_edge_ratio": float(max_edge_ratio)})
