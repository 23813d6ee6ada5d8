"""Real head meshes in the generator (issue 8): skin regions on facial landmarks, non-skin
parts with their own materials, face framing, saved transform, terminator self-shadowing.

All tests need ``../shared/data/faces`` (skipped with a reason when absent).
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from conftest import shared_file
from facegeo.errors import InputError

HEADS = ["ict_facekit_generic_neutral.obj", "mediapipe_canonical_face.obj"]

#: Goal of issue 8: every region's location on the surface within 1 cm of its landmark
#: (metric: distance from the region core's membership-weighted centroid, moved onto the
#: surface along its mean normal, to the landmark; mm).
REGION_TOL_MM = 10.0
#: A region must reach the skin: its largest membership on a skin face (1 at its centre).
REGION_PEAK_MIN = 0.5
#: Issue 8: lit samples shadowed by their own or an adjacent triangle, fraction.
TERMINATOR_MAX = 0.005
#: The face box must span at least this fraction of each capture camera's image height (the
#: framing targets 0.8 of the width, the limiting axis for a portrait camera and a face box).
FACE_FILL_MIN = 0.6
#: ... and its centre must project within this fraction of the image size of the image centre.
FACE_CENTRE_TOL = 0.1
#: Light subset for the terminator measurement (every k-th light of the tiny stage: 32 lights).
LIGHT_STEP = 4


@pytest.fixture(scope="module")
def heads(shared_data):
    """name → (mesh, skin field, renderer, nominal tiny rig framed on the face), built as
    generate_scan builds them."""
    from facegeo.synth.capture import PRESETS, build_head, build_rig, frame_rig
    from facegeo.synth.render import ReferenceRenderer
    from facegeo.synth.skin import SkinField

    out = {}
    for name in HEADS:
        mesh = build_head(str(shared_file(shared_data, f"faces/{name}")), units="cm")
        lm = mesh.metadata["face_landmarks"]
        skin = SkinField.for_landmarks(lm)
        out[name] = (mesh, skin,
                     ReferenceRenderer.from_mesh(mesh, skin, parts=mesh.metadata["part_labels"]),
                     frame_rig(build_rig(PRESETS["tiny"]), lm))
    return out


@pytest.mark.shared_data
@pytest.mark.parametrize("name", HEADS)
def test_regions_within_1cm_of_landmarks(heads, name):
    from facegeo.synth.skin import SkinField, region_landmark_distances

    mesh, skin, _, _ = heads[name]
    lm = mesh.metadata["face_landmarks"]
    skin_faces = mesh.metadata["part_labels"] == 0
    rep = region_landmark_distances(skin, mesh.vertices, mesh.faces, lm, face_mask=skin_faces)
    far = {k: round(v["distance_to_landmark_mm"], 1) for k, v in rep.items()
           if not v["distance_to_landmark_mm"] <= REGION_TOL_MM}
    assert not far, f"{name}: regions farther than {REGION_TOL_MM} mm from their landmark: {far}"
    weak = {k: v["peak_weight"] for k, v in rep.items() if v["peak_weight"] < REGION_PEAK_MIN}
    assert not weak, f"{name}: regions that barely touch the skin: {weak}"
    assert SkinField.from_dict(json.loads(json.dumps(skin.to_dict()))) == skin, "skin.json round trip"
    # The same metric flags the old bounding-box placement (the bug of issue 8).
    old = region_landmark_distances(SkinField.for_mesh(mesh), mesh.vertices, mesh.faces, lm,
                                    face_mask=skin_faces)
    assert max(v["distance_to_landmark_mm"] for v in old.values()) > REGION_TOL_MM


@pytest.mark.shared_data
def test_landmark_indices_are_the_published_ones(heads):
    mesh = heads["ict_facekit_generic_neutral.obj"][0]
    assert "iBUG" in mesh.metadata["landmark_source"]
    for name in HEADS:
        lm = heads[name][0].metadata["face_landmarks"]
        # subject's left = +X, nose tip the most forward landmark, eyes above mouth above chin
        assert lm["left_eye"][0] > 0 > lm["right_eye"][0], name
        assert lm["nose_tip"][2] == max(v[2] for v in lm.values()), name
        assert lm["left_eye"][1] > lm["nose_tip"][1] > lm["mouth_center"][1] > lm["menton"][1]
        iod = np.linalg.norm(lm["left_eye"] - lm["right_eye"])
        assert 0.05 < iod < 0.075, f"{name}: interocular distance {iod} m"


@pytest.mark.shared_data
def test_parts_get_their_own_materials(heads):
    from facegeo.synth.head import PART_NAMES
    from facegeo.synth.skin import PART_MATERIALS

    mesh, skin, renderer, _ = heads["ict_facekit_generic_neutral.obj"]
    labels = mesh.metadata["part_labels"]
    counts = np.bincount(labels, minlength=len(PART_NAMES))
    assert np.all(counts > 0), f"every part labelled on ICT: {dict(zip(PART_NAMES, counts))}"
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
    centroid = tri.mean(axis=1)
    faces = np.arange(len(labels))
    got = renderer.material_at(centroid, faces)
    field = skin.evaluate(centroid)
    for k, part in enumerate(PART_NAMES):
        sel = labels == k
        if part == "skin":
            assert np.array_equal(got.alpha_0[sel], field.alpha_0[sel]), "skin keeps the field"
            continue
        mat = PART_MATERIALS[part]
        assert np.allclose(got.alpha_0[sel], mat.albedo) and np.allclose(got.alpha_1[sel], mat.albedo)
        assert np.all(got.rho_s[sel] == np.float32(mat.rho_s)), part
        assert np.all(got.roughness[sel] == np.float32(mat.roughness)), part
    # MediaPipe has no parts: all skin, renderer without overrides
    assert heads["mediapipe_canonical_face.obj"][2].parts is None


@pytest.mark.shared_data
@pytest.mark.parametrize("name", HEADS)
def test_face_fills_the_frame(heads, name):
    from facegeo.synth.capture import PRESETS, build_rig, face_fill
    from facegeo.synth.head import face_box

    mesh, _, _, rig = heads[name]
    lm = mesh.metadata["face_landmarks"]
    centre = 0.5 * np.add(*face_box(lm))
    for cam in rig.cameras:
        fill = face_fill(cam, lm)
        assert fill["inside"], f"{name}: face box leaves {cam.name}'s image: {fill}"
        assert fill["height"] >= FACE_FILL_MIN, f"{name}: face spans {fill} of {cam.name}"
        q, _ = cam.project(centre[None])
        off = np.abs(q[0] / [cam.width, cam.height] - 0.5)
        assert np.all(off <= FACE_CENTRE_TOL), f"{name}: face centre off by {off} in {cam.name}"
    # the unframed default rig (aimed at the head centre) leaves the face small
    for cam in build_rig(PRESETS["tiny"]).cameras:
        assert face_fill(cam, lm)["height"] < FACE_FILL_MIN


@pytest.mark.shared_data
@pytest.mark.parametrize("name", HEADS)
def test_terminator_self_shadowing(heads, name):
    from facegeo.synth.render import terminator_self_shadow_fraction

    _, _, renderer, rig = heads[name]
    idx = np.arange(0, rig.lights.n_lights, LIGHT_STEP)
    res = terminator_self_shadow_fraction(renderer, rig.cameras, rig.lights, idx)
    assert res["lit"] > 10000
    assert res["fraction"] <= TERMINATOR_MAX, f"{name}: {res}"


@pytest.mark.shared_data
def test_terminator_measure_can_fail(heads):
    """Without the lifted origins and re-trace (plain shading-point shadow rays) the measure
    reports the 2–8 % of issue 8."""
    from facegeo.synth.render import ReferenceRenderer, terminator_self_shadow_fraction

    mesh, skin, _, tiny_rig = heads["mediapipe_canonical_face.obj"]
    plain = ReferenceRenderer.from_mesh(mesh, skin)
    plain.shadow_origins = lambda p, face: np.asarray(p, float)
    plain.face_size = np.zeros(len(mesh.faces))
    idx = np.arange(0, tiny_rig.lights.n_lights, LIGHT_STEP)
    res = terminator_self_shadow_fraction(plain, tiny_rig.cameras, tiny_rig.lights, idx)
    assert res["fraction"] > 4 * TERMINATOR_MAX, res


@pytest.mark.shared_data
def test_ground_truth_transform_parts_and_landmarks(heads, tmp_path, shared_data):
    from facegeo.synth.capture import _write_head_truth

    name = "ict_facekit_generic_neutral.obj"
    mesh, skin, renderer, tiny_rig = heads[name]
    written = _write_head_truth(tmp_path, mesh, tiny_rig, skin, renderer)
    assert set(written) == {"parts", "landmarks", "head_transform", "vertex_map"}
    T = np.array(json.loads((tmp_path / "head_transform.json").read_text())["world_from_file"])
    vm = np.load(tmp_path / "vertex_map.npz")
    path = shared_file(shared_data, f"faces/{name}")
    with open(path) as fh:
        raw = np.array([ln.split()[1:4] for ln in fh if ln.startswith("v ")], float)
    src = vm["source_vertex_index"]
    world = raw[src] @ T[:3, :3].T + T[:3, 3]
    assert np.allclose(world, mesh.vertices, atol=1e-12), "file → world transform reproduces the mesh"
    back = vm["output_vertex_of_source"]
    used = back >= 0
    assert np.array_equal(src[back[used]], np.flatnonzero(used)), "input → output vertex map"
    parts = np.load(tmp_path / "parts.npz")
    assert parts["labels"].shape == (len(mesh.faces),) and "teeth" in list(parts["names"])
    doc = json.loads((tmp_path / "landmarks.json").read_text())
    assert set(doc["regions"]) >= {"lips", "nose", "forehead", "chin", "left_cheek"}
    assert all(v["distance_to_landmark_mm"] <= REGION_TOL_MM for v in doc["regions"].values())
    assert "nose_tip" in doc["landmarks"] and set(doc["framing"]) == {c.name for c in tiny_rig.cameras}


@pytest.mark.shared_data
def test_landmarks_file_beside_any_mesh(shared_data, tmp_path):
    from facegeo.synth.head import MEDIAPIPE_INDEX, load_head_mesh, real_face_landmarks

    src = shared_file(shared_data, "faces/mediapipe_canonical_face.obj")
    obj = tmp_path / "face.obj"
    shutil.copy(src, obj)
    lm_file = tmp_path / "face.landmarks.json"
    lm_file.write_text(json.dumps({"vertex_indices": MEDIAPIPE_INDEX}))
    mesh = load_head_mesh(obj)
    assert mesh.metadata["landmark_source"] == str(lm_file)
    lm = real_face_landmarks(mesh)
    assert np.allclose(lm["nose_tip"], load_head_mesh(src).vertices[1])
    bad = dict(MEDIAPIPE_INDEX)
    del bad["menton"]
    lm_file.write_text(json.dumps({"vertex_indices": bad}))
    with pytest.raises(InputError, match="face.landmarks.json.*menton"):
        load_head_mesh(obj)
    lm_file.write_text(json.dumps({"vertex_indices": {**MEDIAPIPE_INDEX, "menton": 10**6}}))
    with pytest.raises(InputError, match="face.landmarks.json.*menton"):
        load_head_mesh(obj)


@pytest.mark.shared_data
@pytest.mark.slow
def test_ict_scan_round_trip(shared_data, tmp_path):
    """An ICT tiny scan: ground truth (with parts.npz) reproduces an OLAT frame bit for bit,
    and its landmarks.json holds every region within 1 cm and the framing."""
    from facegeo.capture.scan import load_scan
    from facegeo.synth.capture import generate_scan
    from facegeo.synth.render import load_ground_truth

    mesh = shared_file(shared_data, "faces/ict_facekit_generic_neutral.obj")
    generate_scan(tmp_path / "ict", "tiny", head=str(mesh), units="cm", seed=2)
    scan = load_scan(tmp_path / "ict", check="full")
    for key in ("parts", "landmarks", "head_transform", "vertex_map"):
        assert key in scan.ground_truth_keys, key
    gt = load_ground_truth(scan)
    assert gt.parts is not None, "eyes, teeth and mouth come back from parts.npz"
    cam = gt.rig.cameras[0]
    view = gt.surface_view(cam)
    assert np.any(gt.parts[view.face] != 0), "the eyes are seen by the camera"
    (_, img), = gt.olat_images(cam, gt.rig.lights, indices=[40])
    assert np.array_equal(img, scan.olat_frame(cam.name, 40))
    doc = json.loads(scan.ground_truth_path("landmarks").read_text())
    assert all(v["distance_to_landmark_mm"] <= REGION_TOL_MM for v in doc["regions"].values())
    assert all(f["inside"] and f["height"] >= FACE_FILL_MIN for f in doc["framing"].values())


#: Spectral skin's regions (written at the procedural head's centres) must be centred on the
#: real face's landmark-placed regions: |warped u − procedural centre| · half_extent, mm.
SPECTRAL_CENTRE_TOL_MM = 3.0


@pytest.mark.shared_data
@pytest.mark.parametrize("name", HEADS)
def test_spectral_regions_follow_landmarks(heads, name):
    from facegeo.synth.skin import REGION_ANCHORS, REGIONS, procedural_coordinates

    mesh, skin, _, _ = heads[name]
    lm = mesh.metadata["face_landmarks"]
    h = np.asarray(skin.half_extent)
    warped, plain = {}, {}
    for region, anchor in REGION_ANCHORS.items():
        u = skin.normalised(lm[anchor])
        c = np.asarray(REGIONS[region][0])
        warped[region] = 1000 * np.linalg.norm((procedural_coordinates(u, skin) - c) * h)
        plain[region] = 1000 * np.linalg.norm((u - c) * h)
    assert max(warped.values()) <= SPECTRAL_CENTRE_TOL_MM, f"{name}: {warped}"
    assert max(plain.values()) > SPECTRAL_CENTRE_TOL_MM, "the fitted frame alone is not enough"
