"""Atlas, texel table, mesh checks, UV export and pull–push (facegeo.surface.atlas/pullpush).

Tolerances are named below, each with its metric.
"""

from __future__ import annotations

import numpy as np
import pytest

from facegeo.errors import InputError, ShapeError
from facegeo.surface.atlas import (
    Atlas, Texels, build_atlas, check_mesh, export_mesh_uv, rasterize_texels, split_mesh,
    vertex_normals,
)
from facegeo.surface.pullpush import pull_push

#: Texel count vs total UV area of the charts (in texels²): relative difference. Counting
#: centres inside triangles estimates the area to O(perimeter / area).
TEXEL_AREA_REL_TOL = 0.02
#: Worst distance (metres) of a texel position from its face's plane, float64 rounding.
PLANE_TOL_M = 1e-12
#: Worst UV/position difference after an OBJ round trip (9 significant digits).
OBJ_ROUNDTRIP_TOL = 1e-8
#: Worst UV difference after a GLB round trip (float32 storage).
GLB_UV_TOL = 1e-6
#: A chart's 3-D area may exceed xatlas's max_chart_area by this fraction (float32 areas;
#: measured ≤ 0: 49.97 average faces for a limit of 50).
CHART_AREA_REL_TOL = 0.01


def _sphere(subdivisions: int = 3, radius: float = 0.1):
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = np.asarray(s.vertices) * radius * np.array([1.0, 1.2, 0.9])  # asymmetric
    return v, np.asarray(s.faces, np.int64)


@pytest.fixture(scope="module")
def sphere_atlas():
    v, f = _sphere()
    atlas = build_atlas(v, f, texels_per_mm=0.5, padding=2)
    return v, f, atlas, rasterize_texels(atlas)


def test_atlas_covers_every_face_and_maps_back(sphere_atlas):
    v, f, atlas, _ = sphere_atlas
    assert sorted(atlas.face_map.tolist()) == list(range(len(f)))
    # every atlas face is the input face it maps to, vertex for vertex
    np.testing.assert_array_equal(atlas.vertex_map[atlas.faces], f[atlas.face_map])
    assert np.all((atlas.uv >= 0) & (atlas.uv <= 1))
    assert atlas.n_charts >= 1 and atlas.width > 16 and atlas.height > 16


def test_texel_count_matches_uv_area_and_positions_lie_on_faces(sphere_atlas):
    _, _, atlas, tx = sphere_atlas
    F = atlas.faces
    x = atlas.uv[:, 0] * atlas.width
    y = atlas.uv[:, 1] * atlas.height
    area = 0.5 * np.abs((x[F[:, 1]] - x[F[:, 0]]) * (y[F[:, 2]] - y[F[:, 0]])
                        - (x[F[:, 2]] - x[F[:, 0]]) * (y[F[:, 1]] - y[F[:, 0]])).sum()
    assert abs(len(tx) - area) / area < TEXEL_AREA_REL_TOL
    tri = atlas.vertices[atlas.faces[tx.face]]
    dist = np.abs(np.einsum("tc,tc->t", tx.p_world - tri[:, 0], tx.n_geom))
    assert dist.max() < PLANE_TOL_M
    assert np.all(tx.bary >= 0) and np.allclose(tx.bary.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(tx.n_world, axis=1), 1.0, atol=1e-12)
    # index map is the inverse of (row, col)
    assert np.array_equal(tx.index_map[tx.row, tx.col], np.arange(len(tx)))
    assert np.count_nonzero(tx.index_map >= 0) == len(tx)


def test_texel_centres_follow_the_uv_convention(sphere_atlas):
    """Texel (r, c) has its centre at u = (c+½)/W, v = 1 − (r+½)/H: interpolating the face's
    UVs with the texel's barycentrics gives exactly that (a flipped v or a half-texel shift
    fails)."""
    _, _, atlas, tx = sphere_atlas
    uv = np.einsum("tk,tkc->tc", tx.bary, atlas.uv[atlas.faces[tx.face]])
    np.testing.assert_allclose(uv[:, 0], (tx.col + 0.5) / atlas.width, atol=1e-9)
    np.testing.assert_allclose(uv[:, 1], 1.0 - (tx.row + 0.5) / atlas.height, atol=1e-9)


def test_rasterisation_matches_brute_force_on_a_patch(sphere_atlas):
    """Independent check: every pixel centre of a window tested against every face."""
    _, _, atlas, tx = sphere_atlas
    F = atlas.faces
    x = atlas.uv[:, 0] * atlas.width - 0.5
    y = (1 - atlas.uv[:, 1]) * atlas.height - 0.5
    r0, c0 = tx.row[len(tx) // 2] - 10, tx.col[len(tx) // 2] - 10
    rows, cols = np.meshgrid(np.arange(r0, r0 + 20), np.arange(c0, c0 + 20), indexing="ij")
    px, py = cols.ravel()[:, None].astype(float), rows.ravel()[:, None].astype(float)
    ax, ay = x[F[:, 0]], y[F[:, 0]]
    e1x, e1y = x[F[:, 1]] - ax, y[F[:, 1]] - ay
    e2x, e2y = x[F[:, 2]] - ax, y[F[:, 2]] - ay
    d = e1x * e2y - e2x * e1y
    with np.errstate(divide="ignore", invalid="ignore"):
        b1 = ((px - ax) * e2y - (py - ay) * e2x) / d
        b2 = (e1x * (py - ay) - e1y * (px - ax)) / d
    inside = ((b1 >= -1e-9) & (b2 >= -1e-9) & (1 - b1 - b2 >= -1e-9)).any(axis=1)
    got = tx.index_map[rows.ravel(), cols.ravel()] >= 0
    np.testing.assert_array_equal(got, inside)


def test_split_pieces_cover_faces_once_and_atlas_keeps_them():
    v, f = _sphere(4)
    pieces = split_mesh(v, f, 1000)
    assert all(len(p) <= 1000 for p in pieces) and len(pieces) >= len(f) // 1000
    assert np.array_equal(np.sort(np.concatenate(pieces)), np.arange(len(f)))
    atlas = build_atlas(v, f, texels_per_mm=0.3, split_faces=1000)
    assert atlas.n_pieces == len(pieces)
    assert sorted(atlas.face_map.tolist()) == list(range(len(f)))
    np.testing.assert_array_equal(atlas.vertex_map[atlas.faces], f[atlas.face_map])


def test_size_option_and_exclusive_resolutions():
    v, f = _sphere(2)
    atlas = build_atlas(v, f, size=256)
    assert 128 <= max(atlas.width, atlas.height) <= 300
    with pytest.raises(InputError, match="texels_per_mm and size"):
        build_atlas(v, f, size=256, texels_per_mm=1.0)
    with pytest.raises(InputError, match="padding"):
        build_atlas(v, f, padding=-1)


def test_mesh_without_faces_is_an_error():
    v, _ = _sphere(1)
    with pytest.raises(InputError, match="no faces"):
        build_atlas(v, np.zeros((0, 3), np.int64))
    with pytest.raises(ShapeError, match="faces"):
        build_atlas(v, np.zeros((4, 2), np.int64))


def test_unreadable_mesh_files_are_input_errors(tmp_path):
    """A mesh path that is not a mesh (an image, random bytes, a point cloud) is the user's
    mistake: an InputError naming the file, not trimesh's own exception."""
    from facegeo.pipeline.project import load_mesh

    (tmp_path / "env.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    (tmp_path / "noise.ply").write_bytes(bytes(range(256)))
    (tmp_path / "cloud.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\n"
                                        "property float x\nproperty float y\nproperty float z\n"
                                        "end_header\n0 0 0\n1 0 0\n0 1 0\n")
    for name in ("env.png", "noise.ply", "cloud.ply"):
        with pytest.raises(InputError, match=name):
            load_mesh(None, str(tmp_path / name))


def test_degenerate_faces_are_reported_or_dropped():
    v, f = _sphere(2)
    bad = np.vstack([f, [[0, 0, 1]], [[0, 1, 1]]])  # repeated indices
    # collinear corners: a new vertex midway along an edge
    v2 = np.vstack([v, 0.5 * (v[f[0, 0]] + v[f[0, 1]])])
    bad = np.vstack([bad, [[f[0, 0], f[0, 1], len(v)]]])
    with pytest.raises(InputError, match=r"3 degenerate face\(s\).*first is face 320"):
        check_mesh(v2, bad)
    _, kept, report = check_mesh(v2, bad, repair=True)
    assert report.degenerate_faces.tolist() == [320, 321, 322]
    assert np.array_equal(kept, f)
    atlas = build_atlas(v2, bad, texels_per_mm=0.3, repair=True)
    assert sorted(atlas.face_map.tolist()) == list(range(len(f)))


def test_nonmanifold_edges_are_reported_or_dropped():
    v, f = _sphere(2)
    # a fin: a third face on the edge (f0[0], f0[1])
    v2 = np.vstack([v, [[0.0, 0.0, 0.5]]])
    bad = np.vstack([f, [[f[0, 0], f[0, 1], len(v)]]])
    with pytest.raises(InputError, match=r"1 non-manifold edge"):
        check_mesh(v2, bad)
    _, kept, report = check_mesh(v2, bad, repair=True)
    assert report.nonmanifold_edges == 1 and report.nonmanifold_faces.tolist() == [len(f)]
    assert np.array_equal(kept, f)


def test_export_obj_and_glb_round_trip(tmp_path, sphere_atlas):
    import trimesh

    _, _, atlas, _ = sphere_atlas
    obj = export_mesh_uv(atlas, tmp_path / "mesh_uv.obj")
    glb = export_mesh_uv(atlas, tmp_path / "mesh_uv.glb")
    assert (tmp_path / "mesh_uv.mtl").is_file()
    m = trimesh.load(obj, process=False)
    assert m.faces.shape == atlas.faces.shape
    assert np.abs(m.vertices - atlas.vertices).max() < OBJ_ROUNDTRIP_TOL
    assert np.abs(m.visual.uv - atlas.uv).max() < OBJ_ROUNDTRIP_TOL
    g = next(iter(trimesh.load(glb, process=False).geometry.values()))
    assert np.abs(g.visual.uv - atlas.uv).max() < GLB_UV_TOL
    with pytest.raises(InputError, match=".obj or .glb"):
        export_mesh_uv(atlas, tmp_path / "mesh.ply")


def test_atlas_and_texels_save_load(tmp_path, sphere_atlas):
    _, _, atlas, tx = sphere_atlas
    atlas.save(tmp_path / "atlas.npz")
    tx.save(tmp_path / "texels.npz")
    a2 = Atlas.load(tmp_path / "atlas.npz")
    t2 = Texels.load(tmp_path / "texels.npz")
    assert np.array_equal(a2.faces, atlas.faces) and np.array_equal(a2.uv, atlas.uv)
    assert (a2.width, a2.height) == (atlas.width, atlas.height)
    assert np.array_equal(t2.index_map, tx.index_map)
    assert np.array_equal(t2.p_world, tx.p_world)


def test_vertex_normals_are_welded_across_seams():
    v, f = _sphere(2)
    # duplicate vertex 0 as a seam copy used by one face
    v2 = np.vstack([v, v[:1]])
    f2 = f.copy()
    k = np.flatnonzero((f == 0).any(axis=1))[0]
    f2[k][f2[k] == 0] = len(v)
    n = vertex_normals(v2, f2)
    np.testing.assert_allclose(n[0], n[len(v)], atol=1e-15)
    np.testing.assert_allclose(n[0], vertex_normals(v, f)[0], atol=1e-12)


def test_pull_push_keeps_trusted_and_fills_holes():
    rng = np.random.default_rng(0)
    img = rng.random((37, 50, 3)).astype(np.float32)
    w = np.ones((37, 50))
    w[10:20, 5:30] = 0.0
    holes = img.copy()
    holes[w == 0] = np.nan
    out = pull_push(holes, w)
    assert np.array_equal(out[w >= 1], img[w >= 1])
    assert np.all(np.isfinite(out))
    # a constant image is filled with that constant
    const = np.where(w[..., None] > 0, 0.25, np.nan)
    np.testing.assert_allclose(pull_push(const, w), 0.25, atol=1e-6)
    with pytest.raises(InputError, match="weights"):
        pull_push(img, -w)


def _chart_labels(atlas):
    """Chart of each atlas face: faces sharing an atlas vertex (UVs are split at seams)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    nf = len(atlas.faces)
    A = sp.coo_matrix((np.ones(3 * nf), (np.repeat(np.arange(nf), 3), atlas.faces.ravel())),
                      shape=(nf, len(atlas.vertices))).tocsr()
    return connected_components(A @ A.T, directed=False)


def test_max_chart_faces_caps_every_chart_area():
    """Every chart's 3-D area is at most max_chart_faces × the mean face area (the default
    limit that keeps xatlas fast); without the limit some chart is larger."""
    from facegeo.synth.head import procedural_head

    m = procedural_head(4)
    V, F = np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                axis=1)
    biggest = {}
    for limit in (None, 50):
        atlas = build_atlas(V, F, texels_per_mm=0.5, max_chart_faces=limit)
        n, lab = _chart_labels(atlas)
        assert n == atlas.n_charts
        biggest[limit] = np.bincount(lab, weights=area[atlas.face_map]).max() / area.mean()
    assert biggest[50] <= 50 * (1 + CHART_AREA_REL_TOL)
    assert biggest[None] > 50 * (1 + CHART_AREA_REL_TOL)
    with pytest.raises(InputError, match="max_chart_faces"):
        build_atlas(V, F, texels_per_mm=0.5, max_chart_faces=-1)
