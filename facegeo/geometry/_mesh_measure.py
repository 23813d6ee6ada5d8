"""Measures of a triangle mesh against points and other meshes: areas, vertex normals,
area-uniform samples, distances and normal angles to a reference surface (Open3D
``RaycastingScene``), closest points, rigid alignment (ICP) and the area beyond a radius of
observed points. Re-exported by :mod:`facegeo.geometry.mesh`, which builds meshes with them.
"""

from __future__ import annotations

import numpy as np

from facegeo.checks import as_array, check_positive
from facegeo.errors import InputError

__all__ = [
    "align_to_surface",
    "area_beyond",
    "closest_surface_points",
    "face_areas",
    "sample_surface",
    "surface_errors",
]


def _o3d():
    import open3d as o3d

    return o3d


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
