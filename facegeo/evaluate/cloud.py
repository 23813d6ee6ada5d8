"""A reconstructed mesh (and its points) against a reference point cloud or mesh.

The reference is a real scanner's published cloud (``[reference] point_cloud``, e.g. the
3DUNDERWORLD bust: metres, the scan's world frame) or, on a synthetic scan, the generator's
mesh (``ground_truth/mesh.ply``: its vertices as the cloud, its triangles as the surface).
Distances are in millimetres.

* ``mesh_to_reference_median_mm`` / ``_p95_mm`` (point-to-point): ``n_samples`` area-uniform
  samples of the mesh (seed 0) to their nearest reference point;
* ``mesh_to_reference_plane_median_mm`` / ``_p95_mm`` (point-to-plane): the same samples to
  the reference's local plane — the least-squares plane of its ``k_plane`` nearest points for
  a cloud (a cloud spaced 0.35 mm already puts a perfect surface's samples ≈ 0.13 mm from its
  nearest point, so this is the surface error), the exact closest point of the surface for a
  reference mesh. Both over the samples within ``extent_mm`` of a reference point (the
  reference's extent: a scanner sees less than the mesh may cover);
* ``reference_coverage``: the share of reference points within ``coverage_mm`` (1 mm) of the
  mesh (what of the reference the mesh reproduces);
* ``points_to_reference_median_mm`` / ``_p95_mm``: the stage's fused points
  (``out/mesh/points.ply``) to their nearest reference point (to the surface, for a reference
  mesh — and then ``points_rms_error_mm``, the ``mesh`` stage's own figure against the
  generator's mesh), when there are points.

Against a reference mesh, over the mesh stage's observed region (``out/mesh/observed_faces.npy``:
the faces within its observed radius of a fused point) — the figures the ``mesh`` stage
reported until issue 37 moved them here (:func:`observed_surface_errors`):

* ``mesh_p95_error_mm``: 95th percentile distance to the reference surface of ``n_samples``
  area-uniform samples (seed 0) of the observed faces;
* ``normal_median_error_deg``: median angle between the mesh's vertex normals (of the observed
  faces) and the reference's interpolated vertex normals at the closest point (the generator's
  shading normals, ``ground_truth/vertex_params.npz``, where it has them);
* on the generator's mesh, with a mesh stage ``rig`` other than the true one (its world frame
  is its own gauge), the same three figures again under ``after_rigid_alignment``, after the
  rigid transform that best fits the points to the true surface
  (:func:`facegeo.geometry.mesh.align_to_surface`), with ``alignment_rotation_deg`` /
  ``alignment_translation_mm``.

A reference mesh is compared through its surface: the cloud is ``n_samples`` area-uniform
samples of it (its vertices may lie millimetres apart) and the point-to-plane distance is the
exact distance to its triangles.

The measurement is the one ``tests/test_real_bust_mesh.py`` makes by hand on the bust.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facegeo.errors import InputError

__all__ = ["CLOUD_SETTINGS", "evaluate_mesh_against_reference", "mesh_to_reference",
           "observed_surface_errors", "reference_surface"]

#: Settings of the comparison (the ``evaluate`` stage's, under ``mesh``).
CLOUD_SETTINGS = {"n_samples": 100_000, "k_plane": 8, "extent_mm": 2.0, "coverage_mm": 1.0}


def reference_surface(scan) -> tuple[np.ndarray, np.ndarray | None, str] | None:
    """The scan's reference surface: ``(points (N, 3) float64 metres, faces or None, what)``;
    None when it has none. A published cloud (``[reference] point_cloud`` or ``mesh``) first,
    else the generator's mesh of a synthetic scan."""
    import trimesh

    for key in ("mesh", "point_cloud"):
        if key in scan.reference_keys:
            path = scan.reference_path(key)
            try:
                m = trimesh.load(path, process=False)
            except Exception as exc:  # trimesh raises many types for unreadable files
                raise InputError(f"[reference] {key}: cannot read {path} as a point cloud or "
                                 f"mesh: {type(exc).__name__}: {exc}") from exc
            V = np.asarray(getattr(m, "vertices", np.zeros((0, 3))), np.float64)
            if len(V) == 0:
                raise InputError(f"[reference] {key}: {path} holds no points")
            F = np.asarray(m.faces, np.int64) if len(getattr(m, "faces", ())) else None
            return V, F, f"reference {key} ({path.name})"
    if scan.synthetic and "mesh" in scan.ground_truth_keys:
        path = scan.ground_truth_path("mesh")
        m = trimesh.load(path, process=False, force="mesh")
        return (np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64),
                f"generator mesh ({path.name})")
    return None


def _quantiles_mm(d_mm: np.ndarray, prefix: str) -> dict:
    if d_mm.size == 0:
        return {f"{prefix}_median_mm": None, f"{prefix}_p95_mm": None}
    return {f"{prefix}_median_mm": round(float(np.median(d_mm)), 6),
            f"{prefix}_p95_mm": round(float(np.percentile(d_mm, 95)), 6)}


def mesh_to_reference(V, F, ref_points, ref_faces=None, points=None, *,
                      n_samples: int = 100_000, k_plane: int = 8, extent_mm: float = 2.0,
                      coverage_mm: float = 1.0) -> dict:
    """The figures of the module docstring.

    Parameters
    ----------
    V : (V, 3) float64, metres, world frame
    F : (F, 3) int
        The mesh.
    ref_points : (N, 3) float64, metres, world frame
        The reference cloud (a reference mesh's vertices).
    ref_faces : (M, 3) int, optional
        The reference's triangles (a reference mesh: distances to its surface are exact —
        :func:`facegeo.geometry.mesh.surface_errors` —, and its cloud is ``n_samples``
        area-uniform samples of it, seed 1, so that point-to-point and coverage do not depend
        on how coarsely it is triangulated); None: a cloud.
    points : (P, 3) float64, metres, optional
        The fused points the mesh was made from.
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    from facegeo.geometry import mesh as gm

    V = np.asarray(V, np.float64)
    S = gm.sample_surface(V, F, int(n_samples), seed=0)[0]
    if ref_faces is None:
        ref = np.asarray(ref_points, np.float64)
    else:
        ref = gm.sample_surface(ref_points, ref_faces, int(n_samples), seed=1)[0]
    tree = cKDTree(ref * 1e3)
    S_mm = S * 1e3
    d_pp = tree.query(S_mm)[0]
    if ref_faces is None:
        _, nn = tree.query(S_mm, k=int(k_plane))
        Q = ref[nn] * 1e3
        c = Q.mean(1)
        X = Q - c[:, None]
        normal = np.linalg.eigh(np.einsum("nki,nkj->nij", X, X))[1][:, :, 0]
        d_plane = np.abs(np.einsum("ni,ni->n", S_mm - c, normal))
        near = d_pp < float(extent_mm)
    else:
        d_plane = gm.surface_errors(S, ref_points, ref_faces) * 1e3
        near = d_plane < float(extent_mm)
    out = {"reference_points": int(len(ref)), "mesh_samples": int(len(S)),
           "mesh_samples_compared": int(near.sum())}
    out.update(_quantiles_mm(d_pp[near], "mesh_to_reference"))
    out.update(_quantiles_mm(d_plane[near], "mesh_to_reference_plane"))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((V * 1e3).astype(np.float32)),
                        o3d.core.Tensor(np.asarray(F, np.uint32)))
    dr = scene.compute_distance(o3d.core.Tensor((ref * 1e3).astype(np.float32))).numpy()
    out["reference_coverage"] = round(float((dr < float(coverage_mm)).mean()), 6)
    out["coverage_mm"] = float(coverage_mm)
    if points is not None and len(points):
        points = np.asarray(points, np.float64)
        if ref_faces is None:
            d = tree.query(points * 1e3)[0]
        else:  # the exact distance to the surface: the mesh stage's points_rms_error_mm
            d_m = gm.surface_errors(points, ref_points, ref_faces)
            out["points_rms_error_mm"] = round(float(np.sqrt(np.mean(d_m ** 2))) * 1e3, 6)
            d = d_m * 1e3
        out.update(_quantiles_mm(d, "points_to_reference"))
    return out


def _mm(v) -> float:
    return round(float(v) * 1e3, 6)


def observed_surface_errors(V, F, observed, points, ref_V, ref_F, ref_normals=None, *,
                            n_samples: int = 100_000, align: bool = False) -> dict:
    """``points_rms_error_mm``, ``mesh_p95_error_mm``, ``normal_median_error_deg`` of a mesh
    against a reference surface over its observed faces (module docstring).

    Parameters
    ----------
    V : (V, 3) float64, metres; F : (F, 3) int — the mesh
    observed : (F,) bool — the observed faces (``observed_faces.npy``)
    points : (P, 3) float64, metres — the fused points
    ref_V, ref_F — the reference surface (metres, the same world frame)
    ref_normals : (len(ref_V), 3), optional — its shading normals (default: from its faces)
    n_samples : int — area-uniform samples of the observed faces
    align : bool — also the figures after the best rigid alignment of the points to the
        reference (``after_rigid_alignment``)
    """
    from facegeo.geometry import mesh as gm

    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    keep_f = np.asarray(observed, bool)
    if keep_f.shape != (len(F),):
        raise InputError(f"observed_faces: expected {len(F)} flags (one per mesh face), got "
                         f"shape {keep_f.shape}; rerun the mesh stage")

    def errors(pts, verts, vn) -> dict:
        d_pts = gm.surface_errors(pts, ref_V, ref_F)
        got = {"points_rms_error_mm": _mm(np.sqrt(np.mean(d_pts ** 2)))}
        if keep_f.any():
            S, _ = gm.sample_surface(verts, F[keep_f], int(n_samples))
            got["mesh_p95_error_mm"] = _mm(np.percentile(gm.surface_errors(S, ref_V, ref_F), 95))
            vin = np.zeros(len(verts), bool)
            vin[F[keep_f].ravel()] = True
            _, ang = gm.surface_errors(verts[vin], ref_V, ref_F, normals=vn[vin],
                                       ref_normals=ref_normals)
            got["normal_median_error_deg"] = round(float(np.degrees(np.median(ang))), 4)
        return got

    vn = gm._vertex_normals(V, F)  # the mesh stage's own normals (geometry.mesh.Mesh)
    out = errors(points, V, vn)
    if align:
        T = gm.align_to_surface(points, ref_V, ref_F)
        out["after_rigid_alignment"] = {
            **errors(T.apply(points), T.apply(V), T.apply_direction(vn)),
            "alignment_rotation_deg": round(float(np.degrees(np.linalg.norm(T.rvec))), 6),
            "alignment_translation_mm": _mm(np.linalg.norm(T.t))}
    return out


def _generator_normals(scan, n_vertices: int) -> np.ndarray | None:
    """The generator's shading normals of its mesh's vertices, or None."""
    if not (scan.synthetic and "vertex_params" in scan.ground_truth_keys):
        return None
    with np.load(scan.ground_truth_path("vertex_params")) as z:
        if "normals" in z.files and z["normals"].shape == (n_vertices, 3):
            return z["normals"].astype(np.float64)
    return None


def evaluate_mesh_against_reference(scan, out, **settings) -> dict:
    """``out/mesh/mesh.ply`` (and ``points.ply``) against :func:`reference_surface`; ``{}``
    when the scan has no reference surface or the mesh stage has no mesh."""
    import trimesh

    out = Path(out)
    path = out / "mesh" / "mesh.ply"
    ref = reference_surface(scan)
    if ref is None or not path.is_file():
        return {}
    m = trimesh.load(path, process=False, force="mesh")
    points = None
    if (out / "mesh" / "points.ply").is_file():
        import open3d as o3d

        points = np.asarray(o3d.io.read_point_cloud(str(out / "mesh" / "points.ply")).points)
    kw = {**CLOUD_SETTINGS, **settings}
    V, F = np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)
    figures = mesh_to_reference(V, F, ref[0], ref[1], points, **kw)
    observed = out / "mesh" / "observed_faces.npy"
    if ref[1] is not None and points is not None and len(points) and observed.is_file():
        from facegeo.evaluate._products import has_stage, stage_manifest

        generator = ref[2].startswith("generator mesh")
        rig = (stage_manifest(out, "mesh").get("settings", {}).get("rig")
               if has_stage(out, "mesh") else None)
        figures.update(observed_surface_errors(
            V, F, np.load(observed), points, ref[0], ref[1],
            _generator_normals(scan, len(ref[0])) if generator else None,
            n_samples=kw["n_samples"], align=generator and rig != "ground_truth"))
    return {"reference": ref[2], **figures}
