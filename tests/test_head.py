"""Tests of facegeo.synth.head: the procedural head and the real-mesh loader."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import shared_file
from facegeo.errors import InputError
from facegeo.synth import head as headmod
from facegeo.synth.head import (
    HEAD_LANDMARKS,
    HeadParams,
    head_landmarks,
    head_radius,
    load_head_mesh,
    procedural_head,
)

# Named tolerances and ranges (metres unless stated).
WIDTH_RANGE = (0.14, 0.18)  # procedural head without ears
HEIGHT_RANGE = (0.21, 0.25)
DEPTH_RANGE = (0.18, 0.23)
NOSE_PROTRUSION_RANGE = (0.025, 0.030)  # tip above the skull surface
NOSE_TIP_TOL = 0.005  # max-z vertex vs nose_tip landmark (mesh edge ≈ 3.4 mm at subdiv 5)
NOSE_TIP_Z_TOL = 0.0005  # landmark z vs max vertex z
EYE_SOCKET_MIN_DEPTH = 0.005  # eye behind the brow–under-eye line by at least this
MIN_FACE_AREA = 1e-9  # m², "no degenerate faces"

SEEDS = [None, 1, 2, 3]


@pytest.fixture(scope="module")
def head5():
    return procedural_head(5)


def _face_extent(mesh):
    return np.ptp(np.asarray(mesh.vertices), axis=0)


# --------------------------------------------------------------------------- topology


@pytest.mark.parametrize("subdivisions, n_faces", [(4, 5120), (5, 20480)])
def test_procedural_head_is_closed_manifold_outward(subdivisions, n_faces):
    m = procedural_head(subdivisions)
    assert len(m.faces) == n_faces, "face count of the subdivided icosphere"
    assert m.is_watertight, "every edge shared by exactly two faces"
    assert m.is_winding_consistent, "neighbouring faces wound consistently"
    assert m.volume > 0, f"signed volume {m.volume:.3g} m³ > 0 (outward winding)"
    assert m.euler_number == 2, f"Euler characteristic {m.euler_number} (sphere: 2)"
    assert m.area_faces.min() > MIN_FACE_AREA, f"smallest face {m.area_faces.min():.3g} m²"
    # Radial construction: every face normal has a positive component along its centroid.
    c = m.triangles_center
    assert np.all(np.einsum("fi,fi->f", m.face_normals, c) > 0), "all faces face outward"


@pytest.mark.parametrize("seed", SEEDS)
def test_procedural_head_size(seed):
    m = procedural_head(4, seed=seed)
    w, h, d = _face_extent(m)
    assert WIDTH_RANGE[0] <= w <= WIDTH_RANGE[1], f"width {w:.4f} m"
    assert HEIGHT_RANGE[0] <= h <= HEIGHT_RANGE[1], f"height {h:.4f} m"
    assert DEPTH_RANGE[0] <= d <= DEPTH_RANGE[1], f"depth {d:.4f} m"
    centre = m.bounds.mean(axis=0)
    assert np.abs(centre).max() < 0.02, f"bbox centre {centre} within 2 cm of the origin"


def test_seed_determinism():
    a = procedural_head(4, seed=7)
    b = procedural_head(4, seed=7)
    c = procedural_head(4, seed=8)
    d = procedural_head(4)
    assert np.array_equal(a.vertices, b.vertices), "same seed → identical vertices"
    assert np.array_equal(a.faces, c.faces), "seed changes shape only, not connectivity"
    assert np.abs(a.vertices - c.vertices).max() > 1e-3, "different seeds differ by > 1 mm"
    assert np.array_equal(d.vertices, procedural_head(4, seed=None).vertices), "None: default"
    assert a.metadata["facegeo_head"]["seed"] == 7, "seed recorded in metadata"


def test_ears_add_width_and_stay_closed():
    m = procedural_head(4, ears=True)
    plain = procedural_head(4)
    gain = _face_extent(m)[0] - _face_extent(plain)[0]
    assert gain > 0.02, f"ears widen the head by {gain * 1000:.1f} mm (> 20 mm)"
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0, "still closed, outward"


def test_invalid_subdivisions():
    with pytest.raises(InputError):
        procedural_head(2.5)
    with pytest.raises(InputError):
        procedural_head(-1)


# --------------------------------------------------------------------------- features


def test_nose_tip_is_most_forward_point(head5):
    lm = head_landmarks(head5)
    v = np.asarray(head5.vertices)
    top = v[np.argmax(v[:, 2])]
    dist = np.linalg.norm(top - lm["nose_tip"])
    assert dist < NOSE_TIP_TOL, f"max-z vertex {dist * 1000:.2f} mm from the nose tip"
    assert lm["nose_tip"][2] >= v[:, 2].max() - NOSE_TIP_Z_TOL, "landmark z ≈ max z"
    assert set(headmod.LANDMARK_NAMES) == set(lm), "every landmark present"


@pytest.mark.parametrize("seed", SEEDS)
def test_nose_protrudes(seed):
    p = HeadParams.from_seed(seed)
    w = headmod._nose_tip_direction(p, False)
    protrusion = float(head_radius(w, p) - headmod._skull_radius(w, p))
    lo, hi = NOSE_PROTRUSION_RANGE
    assert lo <= protrusion <= hi, f"nose protrudes {protrusion * 1000:.1f} mm"


def test_nose_casts_shadow_on_cheek_under_side_light(head5):
    """A point on the subject's right cheek beside the nose, lit from the subject's left at 60°
    from the front, is occluded by the nose; lit from its own side it is not."""
    p = HeadParams()
    w = headmod._direction_of_xy(-0.022, -0.012, p)
    point = headmod._ray_hit_star_mesh(w, np.asarray(head5.vertices), np.asarray(head5.faces))
    n = point / np.linalg.norm(point)  # outward enough for a ray offset
    origin = (point + 1e-4 * n)[None, :]
    a = np.radians(60.0)
    from_left = np.array([[np.sin(a), 0.1, np.cos(a)]])
    from_right = np.array([[-np.sin(a), 0.1, np.cos(a)]])
    assert head5.ray.intersects_any(origin, from_left / np.linalg.norm(from_left))[0], \
        "cheek beside the nose shadowed by the nose (light from the other side)"
    assert not head5.ray.intersects_any(origin, from_right / np.linalg.norm(from_right))[0], \
        "same point unshadowed when lit from its own side"


def test_nostril_dimples_are_concave():
    p = HeadParams()
    ny = p.nose_base_y + 0.25 * (p.nose_tip_y - p.nose_base_y)
    w = headmod._direction_of_xy(np.array([p.nostril_offset, -p.nostril_offset]),
                                 np.array([ny, ny]), p)
    flat = HeadParams(**{**p.to_dict(), "nostril_depth": 0.0})
    dent = head_radius(w, flat) - head_radius(w, p)
    assert np.all(dent > 0.9 * p.nostril_depth), f"nostril dent {dent * 1000} mm"


@pytest.mark.parametrize("side", ["left", "right"])
def test_eye_sockets_are_concave(head5, side):
    lm = head_landmarks(head5)
    eye, brow, under = lm[f"{side}_eye"], lm[f"{side}_brow"], lm[f"{side}_under_eye"]
    t = (eye[1] - under[1]) / (brow[1] - under[1])
    z_line = under[2] + t * (brow[2] - under[2])
    depth = z_line - eye[2]
    assert depth > EYE_SOCKET_MIN_DEPTH, f"{side} eye {depth * 1000:.1f} mm behind brow–cheek line"


def test_mouth_crease_and_lips(head5):
    lm = head_landmarks(head5)
    assert lm["mouth_center"][2] < lm["upper_lip"][2], "crease behind the upper lip (z)"
    assert lm["mouth_center"][2] < lm["lower_lip"][2], "crease behind the lower lip (z)"
    assert lm["chin"][1] < lm["lower_lip"][1] < lm["mouth_center"][1] < lm["nose_tip"][1], \
        "vertical order chin < lower lip < mouth < nose tip (y)"
    assert lm["left_eye"][0] > 0 > lm["right_eye"][0], "subject's left eye toward +X"


def test_landmarks_smooth_surface_match_mesh(head5):
    lm = head_landmarks(head5)
    worst = max(np.linalg.norm(lm[k] - HEAD_LANDMARKS[k]) for k in lm)
    assert worst < 0.003, f"mesh vs smooth-surface landmarks, worst {worst * 1000:.2f} mm"
    with pytest.raises(InputError):
        import trimesh

        head_landmarks(trimesh.creation.box())


def test_radius_is_c1():
    """Second differences of r(ω) along random great circles scale as h² (no kinks)."""
    rng = np.random.default_rng(4)
    w = rng.normal(size=(4000, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    t = rng.normal(size=(4000, 3))
    t -= np.sum(t * w, axis=1, keepdims=True) * w
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    p = HeadParams()
    curv = []
    for h in (1e-3, 1e-4):
        r = [head_radius(np.cos(s) * w + np.sin(s) * t, p, ears=True) for s in (-h, 0.0, h)]
        curv.append(np.abs(r[0] - 2 * r[1] + r[2]).max() / h**2)
    assert curv[1] < 2.0 * curv[0] + 1e-3, f"max |Δ²r|/h² at h=1e-3, 1e-4: {curv} (bounded)"


# --------------------------------------------------------------------------- loading


@pytest.mark.shared_data
def test_load_mediapipe_face(shared_data):
    path = shared_file(shared_data, "faces/mediapipe_canonical_face.obj")
    m = load_head_mesh(path, units="cm")
    w, h, d = _face_extent(m)
    assert 0.10 < w < 0.22 and 0.12 < h < 0.25 and 0.05 < d < 0.15, f"face size {w, h, d} m"
    assert len(m.vertices) == 468 and len(m.faces) == 898, "MediaPipe canonical topology"
    assert m.visual.uv.shape == (len(m.vertices), 2), "UVs kept per vertex"
    assert np.abs(m.bounds.mean(axis=0)).max() < 1e-12, "bbox centred at the origin"


@pytest.mark.shared_data
def test_load_ict_head_drops_overlays(shared_data):
    path = shared_file(shared_data, "faces/ict_facekit_generic_neutral.obj")
    full = load_head_mesh(path, drop_groups=())
    clean = load_head_mesh(path)
    w, h, d = _face_extent(clean)
    assert 0.15 < w < 0.30 and 0.20 < h < 0.40 and 0.15 < d < 0.30, f"head size {w, h, d} m"
    assert len(clean.faces) < len(full.faces), "dropping overlay groups reduces the face count"
    dropped = " ".join(clean.metadata["dropped_groups"]).lower()
    for g in ("lacrimalfluid", "eyeblend", "eyeocclusion", "eyelashes"):
        assert g in dropped, f"overlay {g} dropped"
    assert not any("face" in g.lower() for g in clean.metadata["dropped_groups"]), "face kept"
    with open(path) as fh:
        lines = fh.readlines()
    n_poly = sum(1 for line in lines if line.startswith("f "))
    assert len(full.faces) > n_poly, "quads triangulated (more triangles than OBJ faces)"
    assert full.visual.uv.shape == (len(full.vertices), 2), "UVs kept"
    src = full.metadata["source_vertex_index"]
    raw = np.array([ln.split()[1:4] for ln in lines if ln.startswith("v ")], float)
    assert np.allclose(full.vertices, raw[src] * 0.01 + full.metadata["translation_m"],
                       atol=1e-12), "vertices = file positions × 0.01 + translation"


def test_load_ply_roundtrip_and_units(tmp_path, head5):
    path = tmp_path / "head.ply"
    head5.export(path)
    m = load_head_mesh(path, units="m", center=False)
    assert len(m.faces) == len(head5.faces), "PLY keeps the triangles"
    assert np.allclose(np.sort(m.vertices, axis=0), np.sort(head5.vertices, axis=0),
                       atol=1e-6), "vertices unchanged in metres (max abs)"
    mm = load_head_mesh(path, units="mm", center=False)
    assert np.allclose(_face_extent(mm), _face_extent(m) * 1e-3, rtol=1e-6), "mm → m scale"


def test_load_errors(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        load_head_mesh(tmp_path / "missing.obj")
    p = tmp_path / "points.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(InputError, match="not a triangle mesh"):
        load_head_mesh(p)
    q = tmp_path / "tri.obj"
    q.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nusemtl skin\nf 1 2 4 3\n")
    with pytest.raises(InputError, match="units"):
        load_head_mesh(q, units="inch")
    m = load_head_mesh(q, units="m", center=False)
    assert len(m.faces) == 2, "a quad becomes two triangles"
    with pytest.raises(InputError, match="removes every face"):
        load_head_mesh(q, drop_groups=("skin",))


# --------------------------------------------------------------------------- OBJ vs trimesh
# facegeo keeps its own OBJ reader (trimesh 5.2's loses material names without the .mtl, cannot
# label faces by group and was 2× slower on the ICT head; see load_head_mesh). These tests check
# it against trimesh's reader on the geometry both produce: the multiset of triangles (vertex
# positions, quads split on the 0–2 diagonal as trimesh does) must be identical, and the UV of
# every triangle corner equal. Metric: exact equality of positions read from the same decimal
# text (both parse with float64), so the tolerance is 0.


def _triangle_multiset(tris: np.ndarray) -> np.ndarray:
    """(F, 3, 3) triangles → (F, 9) canonical rows, sorted, to compare multisets as arrays.

    Each triangle starts at its lexicographically smallest corner (a rotation: the winding is
    kept, so a flipped triangle still differs)."""
    tris = np.asarray(tris, dtype=float)
    rots = np.stack([np.roll(tris, -k, axis=1).reshape(len(tris), 9) for k in range(3)], axis=1)
    first = np.lexsort(rots.transpose(2, 0, 1)[::-1], axis=-1)[:, 0]
    flat = rots[np.arange(len(tris)), first]
    return flat[np.lexsort(flat.T[::-1])]


def _trimesh_triangles(path):
    import trimesh

    loaded = trimesh.load(str(path), process=False, skip_materials=True)
    geoms = loaded.dump() if isinstance(loaded, trimesh.Scene) else [loaded]
    return np.concatenate([np.asarray(g.triangles) for g in geoms])


def _our_triangles(path):
    from pathlib import Path

    V, T, Fv, Ft, labels = headmod._parse_obj(Path(path))
    return V[Fv], T, Ft, labels


_SMALL_OBJ = """# hand-written: quads, a triangle, a pentagon, groups, UVs
o part_a
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0.5 1.5 0.25
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vt 0.5 1
g front
usemtl skin
f 1/1 2/2 3/3 4/4
f 1/1 3/3 5/5
o part_b
v 2 0 0
v 3 0 1
v 3 1 1
v 2 1 0
v 2.5 1.5 0.5
g back
usemtl Eye_Lashes
f 6/1 7/2 8/3 9/4 10/5
"""


def test_small_obj_matches_trimesh(tmp_path):
    p = tmp_path / "small.obj"
    p.write_text(_SMALL_OBJ)
    ours, T, Ft, labels = _our_triangles(p)
    assert len(ours) == 2 + 1 + 3, "quad → 2, triangle → 1, pentagon → 3 (fan)"
    np.testing.assert_array_equal(_triangle_multiset(ours), _triangle_multiset(_trimesh_triangles(p)))
    assert list(labels) == ["part_a|front|skin"] * 3 + ["part_b|back|Eye_Lashes"] * 3
    np.testing.assert_array_equal(T[Ft[2]], [[0, 0], [1, 1], [0.5, 1]])
    # OBJ negative indices count back from the vertices read *so far* (trimesh 5.2 counts from
    # the end of the file instead, so this case is checked against the positive form only)
    q = tmp_path / "negative.obj"
    q.write_text(_SMALL_OBJ.replace("f 1/1 3/3 5/5", "f -5/-5 -3/-3 -1/-1"))
    neg, T2, Ft2, _ = _our_triangles(q)
    np.testing.assert_array_equal(neg, ours)
    np.testing.assert_array_equal(T2[Ft2], T[Ft])
    m = load_head_mesh(p, units="m", center=False, drop_groups=("lashes",))
    assert len(m.faces) == 3 and m.metadata["dropped_groups"] == ["part_b|back|Eye_Lashes"]
    assert m.visual.uv.shape == (len(m.vertices), 2)


def test_obj_check_can_fail(tmp_path):
    """A reader that split quads on the other diagonal would be caught by the comparison."""
    p = tmp_path / "small.obj"
    p.write_text(_SMALL_OBJ)
    ours, *_ = _our_triangles(p)
    theirs = _triangle_multiset(_trimesh_triangles(p))
    rotated = ours.copy()
    rotated[0] = ours[0][[1, 2, 0]]  # the same triangle, another starting corner: still equal
    np.testing.assert_array_equal(_triangle_multiset(rotated), theirs)
    flipped = ours.copy()
    flipped[0] = ours[0][[0, 2, 1]]  # reversed winding: caught
    assert not np.array_equal(_triangle_multiset(flipped), theirs)
    diagonal = ours.copy()  # the quad split on the 1–3 diagonal instead of 0–2: caught
    a, b, c = ours[0]
    d = ours[1][2]
    diagonal[0], diagonal[1] = [a, b, d], [b, c, d]
    assert not np.array_equal(_triangle_multiset(diagonal), theirs)


@pytest.mark.shared_data
@pytest.mark.parametrize("name", [
    "mediapipe_canonical_face.obj",
    pytest.param("ict_facekit_generic_neutral.obj", marks=pytest.mark.slow),
])
def test_shared_obj_matches_trimesh(shared_data, name):
    path = shared_file(shared_data, f"faces/{name}")
    ours, *_ = _our_triangles(path)
    theirs = _trimesh_triangles(path)
    assert ours.shape == theirs.shape
    np.testing.assert_array_equal(_triangle_multiset(ours), _triangle_multiset(theirs))
