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
  single-threaded, so the same input gives the same mesh.
* :func:`grid_mesh` — the cheap one-camera path: two triangles per 2 × 2 block of pixels that
  all hold points and whose depths do not jump.
* :func:`surface_errors` — distances and normal angles against a reference mesh (Open3D
  ``RaycastingScene``), and :func:`area_beyond` — mesh area farther than a radius from any
  observed point.

References
----------
.. [1] Kazhdan & Hoppe, "Screened Poisson Surface Reconstruction", ACM TOG 32(3), 2013.
.. [2] Debevec et al., "Acquiring the Reflectance Field of a Human Face", SIGGRAPH 2000, §2
   (the face geometry from structured light, used to project the reflectance functions).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from facegeo.checks import as_array, check_positive
from facegeo.errors import InputError, ShapeError

__all__ = [
    "Mesh",
    "align_to_surface",
    "area_beyond",
    "face_areas",
    "grid_mesh",
    "oriented_normals",
    "poisson_mesh",
    "sample_surface",
    "surface_errors",
]


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
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray
    info: dict = field(default_factory=dict)

    @property
    def area(self) -> float:
        """Total area, square metres."""
        return float(face_areas(self.vertices, self.faces).sum())


def _o3d():
    import open3d as o3d

    return o3d


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


def face_areas(vertices, faces) -> np.ndarray:
    """Area of each triangle, ``(F,)`` float64, square metres."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    if F.size == 0:
        return np.zeros(0)
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    return 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)


def _vertex_normals(V, F) -> np.ndarray:
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # area-weighted
    n = np.zeros_like(V)
    for j in range(3):
        np.add.at(n, F[:, j], fn)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)


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


def poisson_mesh(points, normals, *, depth: int = 7, point_weight: float = 4.0,
                 scale: float = 1.1, samples_per_node: float = 1.5,
                 trim_quantile: float = 0.02, max_distance: float | None = 2e-3,
                 min_component: float = 0.05, target_faces: int | None = None) -> Mesh:
    """Screened Poisson surface of oriented points, trimmed to where the points are.

    Parameters
    ----------
    points : (N, 3) float64, metres, world frame
    normals : (N, 3) float64, unit, oriented outward (toward the cameras)
    depth : int
        Octree depth (grid ≤ 2^depth per side over ``scale`` × the points' bounding cube).
    point_weight : float
        Screening weight of the point interpolation term (Kazhdan & Hoppe 2013, α).
    scale, samples_per_node
        Open3D / PoissonRecon settings.
    trim_quantile : float, 0..1
        Remove vertices whose Poisson density (the octree depth of the samples supporting them)
        is below this quantile of all vertices' densities.
    max_distance : float, metres, optional
        Also remove vertices farther than this from every input point (no invented skin where
        no camera saw the face). ``None`` keeps them.
    min_component : float, 0..1
        Remove connected components with fewer faces than this fraction of the largest one.
    target_faces : int, optional
        Quadric decimation to at most this many faces (after trimming).

    Returns
    -------
    Mesh
        ``info`` records every setting and how many vertices each step removed.

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
    if isinstance(depth, bool) or int(depth) != depth or not 4 <= depth <= 12:
        raise InputError(f"depth: expected an integer in [4, 12], got {depth!r}")
    if not 0.0 <= trim_quantile < 1.0:
        raise InputError(f"trim_quantile: expected a value in [0, 1), got {trim_quantile!r}")
    if not 0.0 <= min_component <= 1.0:
        raise InputError(f"min_component: expected a fraction in [0, 1], got {min_component!r}")
    check_positive(point_weight, "point_weight", allow_zero=True)
    t0 = time.perf_counter()
    o3d = _o3d()
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        m, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            _pcd(p, n), depth=int(depth), scale=float(scale), linear_fit=False, n_threads=1,
            samples_per_node=float(samples_per_node), point_weight=float(point_weight))
    t1 = time.perf_counter()
    V = np.asarray(m.vertices, np.float64).copy()
    F = np.asarray(m.triangles, np.int64).copy()
    dens = np.asarray(dens, np.float64)
    info = {"depth": int(depth), "point_weight": float(point_weight), "scale": float(scale),
            "samples_per_node": float(samples_per_node), "trim_quantile": float(trim_quantile),
            "max_distance_mm": None if max_distance is None else 1e3 * float(max_distance),
            "min_component": float(min_component), "target_faces": target_faces,
            "points": int(p.shape[0]), "poisson_vertices": len(V),
            "poisson_faces": len(F), "seconds_poisson": round(t1 - t0, 4)}
    keep = np.ones(len(V), bool)
    if trim_quantile > 0 and len(V):
        keep &= dens >= np.quantile(dens, trim_quantile)
    info["trimmed_density"] = int((~keep).sum())
    if max_distance is not None and len(V):
        from scipy.spatial import cKDTree

        dist, _ = cKDTree(p).query(V, k=1, distance_upper_bound=2 * max_distance)
        far = keep & ~(dist <= check_positive(max_distance, "max_distance"))
        keep &= ~far
        info["trimmed_distance"] = int(far.sum())
    V, F, _ = _compact(V, F, keep)
    lab = _components(F, len(V))
    if lab.size:
        counts = np.bincount(lab)
        small = counts < min_component * counts.max()
        drop_f = small[lab]
        info["components"] = int(counts.size)
        info["removed_components"] = int(small.sum())
        F = F[~drop_f]
        used = np.zeros(len(V), bool)
        used[F.ravel()] = True
        V, F, _ = _compact(V, F, used)
    if target_faces is not None and len(F) > target_faces:
        mm = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V),
                                       o3d.utility.Vector3iVector(F.astype(np.int32)))
        mm = mm.simplify_quadric_decimation(int(target_faces))
        mm.remove_unreferenced_vertices()
        V = np.asarray(mm.vertices, np.float64).copy()
        F = np.asarray(mm.triangles, np.int64).copy()
    vn = _vertex_normals(V, F)
    info.update({"vertices": len(V), "faces": len(F),
                 "seconds": round(time.perf_counter() - t0, 4)})
    return Mesh(V, F, vn, info)


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


def sample_surface(vertices, faces, n: int, *, seed: int = 0):
    """Area-uniform random points on a mesh (deterministic for a seed).

    Returns
    -------
    points : (n, 3) float64, metres
    face : (n,) int64, the face each point lies on
    """
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    a = face_areas(V, F)
    if a.sum() <= 0:
        raise InputError("mesh: zero area, nothing to sample")
    rng = np.random.default_rng(seed)
    f = rng.choice(len(F), size=int(n), p=a / a.sum())
    r1, r2 = rng.random(int(n)), rng.random(int(n))
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], 1)
    return np.einsum("nk,nkc->nc", w, V[F[f]]), f


def surface_errors(points, ref_vertices, ref_faces, *, normals=None, ref_normals=None):
    """Distance (and normal angle) of points to a reference surface.

    Parameters
    ----------
    points : (N, 3) float64, metres
    ref_vertices : (V, 3) float64, metres; ref_faces : (F, 3) int
        The reference (ground-truth) mesh.
    normals : (N, 3) float64, optional
        Normals at ``points``; with them the angle to the reference normal at the closest point
        is returned too.
    ref_normals : (V, 3) float64, optional
        Reference vertex normals, interpolated barycentrically at the closest point (default:
        area-weighted vertex normals of the reference mesh).

    Returns
    -------
    distance : (N,) float64, metres (unsigned, float32 precision from Open3D)
    angle : (N,) float64, radians — only when ``normals`` is given (orientation ignored:
        the angle to the nearer of ±n_ref)
    """
    p = as_array(points, "points", shape=(None, 3))
    Vr = as_array(ref_vertices, "ref_vertices", shape=(None, 3))
    Fr = np.asarray(ref_faces, np.int64)
    prim, bary, closest = _closest_points(_closest_scene(Vr, Fr), Vr, Fr, p)
    dist = np.linalg.norm(p - closest, axis=1)
    if normals is None:
        return dist
    n = as_array(normals, "normals", shape=p.shape)
    nr = _vertex_normals(Vr, Fr) if ref_normals is None else as_array(
        ref_normals, "ref_normals", shape=Vr.shape)
    m = np.einsum("nk,nkc->nc", bary, nr[Fr[prim]])
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    nn = n / np.linalg.norm(n, axis=1, keepdims=True)
    cos = np.abs(np.einsum("ij,ij->i", nn, m)).clip(0, 1)
    return dist, np.arccos(cos)


def _closest_scene(Vr, Fr):
    o3d = _o3d()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(Vr.astype(np.float32)),
                        o3d.core.Tensor(Fr.astype(np.uint32)))
    return scene


def _closest_points(scene, Vr, Fr, p):
    """(face, barycentrics, closest point) on the reference surface for each point; the
    closest point in float64 from the barycentrics (Open3D works in float32)."""
    o3d = _o3d()
    cp = scene.compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))
    prim = cp["primitive_ids"].numpy().astype(np.int64)
    uv = cp["primitive_uvs"].numpy().astype(np.float64)
    bary = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], 1)
    return prim, bary, np.einsum("nk,nkc->nc", bary, Vr[Fr[prim]])


def closest_surface_points(vertices, faces, points):
    """The closest point of a triangle mesh to each query point.

    Parameters
    ----------
    vertices : (V, 3) float64, metres; faces : (F, 3) int
    points : (N, 3) float64, metres

    Returns
    -------
    face : (N,) int64 — the face holding the closest point
    bary : (N, 3) float64 — its barycentric weights on that face
    point : (N, 3) float64 — the closest point, from the barycentrics in float64 (Open3D's
        query runs in float32: ≈ 1e-8 m at head size)
    """
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    return _closest_points(_closest_scene(V, F), V, F, np.asarray(points, np.float64))


def align_to_surface(points, ref_vertices, ref_faces, *, iterations: int = 50,
                     keep: float = 0.9, tol: float = 1e-9):
    """Rigid transform bringing points onto a reference surface (trimmed point-to-plane ICP).

    Each iteration pairs every point with its closest point on the reference surface, keeps the
    ``keep`` fraction of pairs with the smallest distances (trimmed ICP, Chetverikov et al. 2002:
    robust to points where the reference has no surface) and takes the Gauss–Newton step of the
    point-to-plane distances ``((R q + t − c) · n)²`` with ``n`` the closest face's normal
    (Chen & Medioni 1992; converges in a few steps where point-to-point ICP crawls along a
    smooth surface). Stops when a step moves the points by less than ``tol`` metres RMS. Used
    to separate a reconstruction's shape error from the gauge of its world frame (a calibrated
    rig's frame against the true one).

    Parameters
    ----------
    points : (N, 3) float64, metres, N ≥ 6
    ref_vertices : (V, 3) float64; ref_faces : (F, 3) int

    Returns
    -------
    T_ref_points : facegeo.frames.Pose — ``p_ref ≈ T.apply(p)``
    """
    from facegeo.frames import Pose, rotation_from_rvec

    p = as_array(points, "points", shape=(None, 3))
    Vr = as_array(ref_vertices, "ref_vertices", shape=(None, 3))
    Fr = np.asarray(ref_faces, np.int64)
    if not 0.0 < keep <= 1.0:
        raise InputError(f"keep: expected a fraction in (0, 1], got {keep}")
    if len(p) < 6:
        raise InputError(f"points: a rigid alignment needs at least 6 points, got {len(p)}")
    scene = _closest_scene(Vr, Fr)
    fn = np.cross(Vr[Fr[:, 1]] - Vr[Fr[:, 0]], Vr[Fr[:, 2]] - Vr[Fr[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    T = Pose.identity()
    q = p
    n_keep = max(6, round(keep * len(p)))
    for _ in range(int(iterations)):
        prim, _, c = _closest_points(scene, Vr, Fr, q)
        d = np.linalg.norm(q - c, axis=1)
        sel = np.argpartition(d, n_keep - 1)[:n_keep] if n_keep < len(p) else slice(None)
        qs, n = q[sel], fn[prim[sel]]
        A = np.concatenate([np.cross(qs, n), n], axis=1)
        b = -np.einsum("ij,ij->i", qs - c[sel], n)
        x = np.linalg.lstsq(A, b, rcond=None)[0]
        step = Pose(rotation_from_rvec(x[:3]), x[3:])
        q_new = step.apply(q)
        T = step @ T
        moved = float(np.sqrt(np.mean(np.sum((q_new - q) ** 2, axis=1))))
        q = q_new
        if moved < tol:
            break
    return T


def area_beyond(vertices, faces, points, radius: float) -> tuple[float, np.ndarray]:
    """Mesh area whose faces' centroids lie farther than ``radius`` from every point.

    Parameters
    ----------
    vertices : (V, 3) float64, metres; faces : (F, 3) int
    points : (N, 3) float64, metres — the observed points
    radius : float, metres

    Returns
    -------
    area : float, square metres
    far : (F,) bool, the faces counted
    """
    from scipy.spatial import cKDTree

    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    r = check_positive(radius, "radius")
    if len(F) == 0:
        return 0.0, np.zeros(0, bool)
    cen = V[F].mean(axis=1)
    d, _ = cKDTree(np.asarray(points, np.float64)).query(cen, k=1, distance_upper_bound=2 * r)
    far = ~(d <= r)
    return float(face_areas(V, F)[far].sum()), far
