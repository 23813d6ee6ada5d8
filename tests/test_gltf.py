"""glTF 2.0 export: the ``.glb`` writer (facegeo.render.gltf) and ``facegeo export``."""

from __future__ import annotations

import struct

import cv2
import numpy as np
import pytest

from facegeo.errors import InputError
from facegeo.render.gltf import (
    GLB_MAGIC,
    build_glb,
    encode_normal_map,
    read_glb,
    roughness_from_beckmann,
    tangent_space_normals,
    vertex_tangents,
    write_glb,
)

#: Positions are stored as float32: a few metres' worth of float32 rounding (|p| < 0.3 m).
POSITION_TOL_M = 1e-7
#: UVs are stored as float32 in [0, 1].
UV_TOL = 1e-7
#: One 8-bit step of a normal map is 2/255 in [−1, 1]; rounding moves a component by ≤ half.
NORMAL_8BIT_TOL = 1.0 / 255 + 1e-9
#: An 8-bit linear channel (the specular strength) holds a value in [0, 1] to half a step.
CHANNEL_8BIT_TOL = 0.5 / 255 + 1e-9
#: Tangent-space round trip in floating point (float64 frames): unit vectors equal to rounding.
FRAME_TOL = 1e-9
#: Angle between a fitted world normal and the one a glTF viewer decodes from the 8-bit map
#: with the file's float32 NORMAL/TANGENT: ≤ 3 half-steps of 1/127.5 ≈ 0.39°; worst case.
VIEWER_NORMAL_DEG_MAX = 0.6
#: The fitted normals lie near the shading normal (median error ≈ 1° against the truth on the
#: tiny preset): tangent-space z of a fitted texel, median over texels.
FITTED_Z_MEDIAN_MIN = 0.98

_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
_BYTES = {5126: 4, 5125: 4}


def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img[..., ::-1] if img.ndim == 3 else img)
    assert ok
    return buf.tobytes()


def _box():
    """A box 0.10 × 0.06 × 0.04 m off the origin, 24 vertices (seams per side), UVs in an
    asymmetric 3 × 2 layout of a non-square atlas (v up), faces counter-clockwise outward."""
    size = np.array([0.10, 0.06, 0.04])
    centre = np.array([0.03, -0.02, 0.15])
    V, F, UV, N = [], [], [], []
    for k, (axis, sign) in enumerate([(0, 1), (0, -1), (1, 1), (1, -1), (2, 1), (2, -1)]):
        n = np.zeros(3)
        n[axis] = sign
        a, b = [i for i in range(3) if i != axis]
        u_dir, v_dir = np.zeros(3), np.zeros(3)
        u_dir[a], v_dir[b] = 1.0, 1.0
        if np.dot(np.cross(u_dir, v_dir), n) < 0:
            u_dir = -u_dir
        base = len(V)
        for s, t in ((0, 0), (1, 0), (1, 1), (0, 1)):
            V.append(centre + n * size / 2 + (s - 0.5) * u_dir * size + (t - 0.5) * v_dir * size)
            col, row = k % 3, k // 3
            UV.append([(col + 0.1 + 0.8 * s) / 3, (row + 0.1 + 0.7 * t) / 2])
            N.append(n)
        F += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return np.array(V), np.array(F), np.array(UV), np.array(N)


def _accessor(doc, binary, index):
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = np.float32 if acc["componentType"] == 5126 else np.uint32
    k = _COMPONENTS[acc["type"]]
    a = np.frombuffer(binary, dtype, acc["count"] * k, view.get("byteOffset", 0) +
                      acc.get("byteOffset", 0))
    return a.reshape(acc["count"], k) if k > 1 else a


@pytest.fixture
def box_glb(tmp_path):
    V, F, UV, N = _box()
    rng = np.random.default_rng(3)
    base = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)  # 7 wide, 5 high: not square
    normal = np.zeros((4, 6, 3), np.uint8) + np.array([128, 128, 255], np.uint8)
    mr = np.zeros((3, 3, 3), np.uint8)
    mr[..., 1] = 200
    spec = np.full((2, 2, 4), 255, np.uint8)
    spec[..., 3] = [[10, 20], [30, 40]]
    pngs = {"base": _png(base), "normal": _png(normal), "mr": _png(mr),
            "spec": cv2.imencode(".png", spec)[1].tobytes()}
    (tmp_path / "albedo.png").write_bytes(pngs["base"])
    path = write_glb(tmp_path / "box.glb", V, F, UV, N, base_color_png=tmp_path / "albedo.png",
                     normal_png=pngs["normal"], metallic_roughness_png=pngs["mr"],
                     roughness_factor=0.6, specular_png=pngs["spec"], ior=1.4,
                     extras={"facegeo": {"units": "metres"}})
    return path, (V, F, UV, N), base, pngs


def test_trimesh_loads_box_with_material(box_glb):
    import trimesh

    path, (V, F, UV, _), base, _ = box_glb
    scene = trimesh.load(path, process=False)
    (mesh,) = scene.geometry.values()
    assert np.abs(mesh.vertices - V).max() <= POSITION_TOL_M
    assert np.array_equal(mesh.faces, F)
    # trimesh converts glTF's v-down TEXCOORD_0 back to v up: the UVs we gave
    assert np.abs(mesh.visual.uv - UV).max() <= UV_TOL
    mat = mesh.visual.material
    assert np.array_equal(np.asarray(mat.baseColorTexture)[..., :3], base)
    assert mat.roughnessFactor == pytest.approx(0.6, abs=1e-12)
    assert mat.metallicFactor == 0.0
    assert mat.normalTexture is not None and mat.metallicRoughnessTexture is not None
    assert np.asarray(mat.metallicRoughnessTexture)[..., 1].min() == 200


def test_texcoord_stored_v_down(box_glb):
    """glTF §3.7.2.1: TEXCOORD_0's origin is the image's top-left; ours is bottom-left."""
    path, (_, _, UV, _), _, _ = box_glb
    doc, binary = read_glb(path)
    st = _accessor(doc, binary, doc["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"])
    assert np.abs(st[:, 0] - UV[:, 0]).max() <= UV_TOL
    assert np.abs(st[:, 1] - (1.0 - UV[:, 1])).max() <= UV_TOL
    assert np.abs(st[:, 1] - UV[:, 1]).max() > 0.1, "not flipped"


def test_glb_structure_follows_spec(box_glb):
    path, (V, F, _, N), _, pngs = box_glb
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<III", data)
    assert (magic, version, length) == (GLB_MAGIC, 2, len(data))
    jlen, jtype = struct.unpack_from("<II", data, 12)
    blen, btype = struct.unpack_from("<II", data, 20 + jlen)
    assert jtype == 0x4E4F534A and btype == 0x004E4942
    assert jlen % 4 == 0 and blen % 4 == 0 and 28 + jlen + blen == len(data)
    doc, binary = read_glb(path)
    assert doc["asset"]["version"] == "2.0"
    assert doc["scenes"][doc["scene"]]["nodes"] == [0] and doc["nodes"][0]["mesh"] == 0
    assert doc["buffers"] == [{"byteLength": blen}] and "uri" not in doc["buffers"][0]
    for view in doc["bufferViews"]:
        assert {"buffer", "byteLength"} <= view.keys() and view["buffer"] == 0
        assert view["byteOffset"] % 4 == 0
        assert view["byteOffset"] + view["byteLength"] <= blen
    for acc in doc["accessors"]:
        assert {"bufferView", "componentType", "count", "type"} <= acc.keys()
        need = acc["count"] * _COMPONENTS[acc["type"]] * _BYTES[acc["componentType"]]
        assert need <= doc["bufferViews"][acc["bufferView"]]["byteLength"]
    prim = doc["meshes"][0]["primitives"][0]
    assert prim["mode"] == 4 and set(prim["attributes"]) == {"POSITION", "NORMAL", "TANGENT",
                                                             "TEXCOORD_0"}
    pos = doc["accessors"][prim["attributes"]["POSITION"]]
    p32 = V.astype(np.float32)
    assert pos["min"] == p32.min(axis=0).tolist() and pos["max"] == p32.max(axis=0).tolist()
    idx = _accessor(doc, binary, prim["indices"])
    assert doc["accessors"][prim["indices"]]["componentType"] == 5125
    assert np.array_equal(idx.reshape(-1, 3), F)
    for name in prim["attributes"]:
        assert doc["accessors"][prim["attributes"][name]]["count"] == V.shape[0], name
    tan = _accessor(doc, binary, prim["attributes"]["TANGENT"])
    assert set(np.unique(tan[:, 3])) <= {-1.0, 1.0}
    assert np.abs(np.einsum("ij,ij->i", tan[:, :3], N)).max() <= 1e-6, "tangent ⟂ normal"
    # the images are the PNGs given, byte for byte, and the material points at them
    mat = doc["materials"][0]
    embedded = {}
    for key, ref in (("base", mat["pbrMetallicRoughness"]["baseColorTexture"]),
                     ("normal", mat["normalTexture"]),
                     ("mr", mat["pbrMetallicRoughness"]["metallicRoughnessTexture"]),
                     ("spec", mat["extensions"]["KHR_materials_specular"]["specularTexture"])):
        img = doc["images"][doc["textures"][ref["index"]]["source"]]
        view = doc["bufferViews"][img["bufferView"]]
        embedded[key] = binary[view["byteOffset"]:view["byteOffset"] + view["byteLength"]]
        assert img["mimeType"] == "image/png"
    assert embedded == pngs
    assert mat["pbrMetallicRoughness"]["metallicFactor"] == 0.0
    assert doc["extras"] == {"facegeo": {"units": "metres"}}
    assert mat["extensions"]["KHR_materials_ior"] == {"ior": 1.4}
    assert mat["extensions"]["KHR_materials_specular"]["specularFactor"] == 1.0
    assert doc["extensionsUsed"] == ["KHR_materials_ior", "KHR_materials_specular"]
    assert "extensionsRequired" not in doc, "optional: core viewers still open the file"


def _rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_flat_quad_geometric_normal_encodes_neutral():
    """A quad off every axis, UVs an asymmetric affine map of it: the geometric normal is
    (0, 0, 1) in tangent space, (0.5, 0.5, 1.0) in the map."""
    rng = np.random.default_rng(7)
    R = _rotation(rng)
    local = np.array([[0, 0, 0], [0.08, 0.01, 0], [0.09, 0.05, 0], [0.005, 0.04, 0.0]])
    V = local @ R.T + [0.02, 0.1, -0.03]
    F = np.array([[0, 1, 2], [0, 2, 3]])
    A = np.array([[7.0, 2.0], [-1.5, 11.0]])  # uv = A · (x, y) + c
    UV = local[:, :2] @ A.T + [0.1, 0.2]
    n_geom = R[:, 2]
    N = np.tile(n_geom, (4, 1))
    tangents = vertex_tangents(V, F, UV, N)
    face = rng.integers(0, 2, 50)
    bary = rng.dirichlet(np.ones(3), 50)
    n_t = tangent_space_normals(np.tile(n_geom, (50, 1)), face, bary, F, N, tangents)
    assert np.abs(n_t - [0.0, 0.0, 1.0]).max() <= FRAME_TOL
    encoded = encode_normal_map(n_t) / 255.0
    assert np.abs(encoded - [0.5, 0.5, 1.0]).max() <= NORMAL_8BIT_TOL / 2


@pytest.mark.parametrize("mirror", [False, True])
def test_tangent_axes_follow_u_and_image_up(mirror):
    """+x of the map is +u, +y is +v (up in the image, glTF §3.9.3), also on a chart whose UVs
    are mirrored (w = −1). A tangent frame with the bitangent along glTF's v (down) fails."""
    V = np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0.0]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    UV = V[:, :2] * 5 + 0.2
    if mirror:
        UV[:, 0] = 1.0 - UV[:, 0]
    N = np.tile([0, 0, 1.0], (4, 1))
    tangents = vertex_tangents(V, F, UV, N)
    assert np.all(tangents[:, 3] == (-1.0 if mirror else 1.0))
    s = np.sin(np.radians(20))
    tilt_x = [s, 0, np.sqrt(1 - s * s)]  # toward +X: +u, or −u when mirrored
    tilt_y = [0, s, np.sqrt(1 - s * s)]  # toward +Y: +v either way
    n_t = tangent_space_normals(np.array([tilt_x, tilt_y]), [0, 1], [[1 / 3] * 3] * 2, F, N,
                                tangents)
    sx = -1.0 if mirror else 1.0
    want = np.array([[sx * s, 0, np.sqrt(1 - s * s)], [0, s, np.sqrt(1 - s * s)]])
    assert np.abs(n_t - want).max() <= FRAME_TOL


def test_roughness_mapping_and_input_errors(tmp_path):
    assert roughness_from_beckmann(0.36) == pytest.approx(0.6, abs=1e-12)
    with pytest.raises(InputError, match="m:"):
        roughness_from_beckmann(0.0)
    V, F, UV, N = _box()
    png = _png(np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(InputError, match="base_color_png: not a PNG"):
        build_glb(V, F, UV, N, base_color_png=b"GIF89a..", normal_png=png)
    with pytest.raises(InputError, match="normal_png: no PNG file"):
        build_glb(V, F, UV, N, base_color_png=png, normal_png=tmp_path / "missing.png")
    with pytest.raises(InputError, match="roughness_factor"):
        build_glb(V, F, UV, N, base_color_png=png, normal_png=png, roughness_factor=1.5)
    with pytest.raises(InputError, match="ior"):
        build_glb(V, F, UV, N, base_color_png=png, normal_png=png, ior=0.9)
    with pytest.raises(InputError, match=r"\.glb"):
        write_glb(tmp_path / "m.gltf", V, F, UV, N, base_color_png=png, normal_png=png)
    with pytest.raises(InputError, match="faces"):
        build_glb(V, F + 100, UV, N, base_color_png=png, normal_png=png)


# --- facegeo export on the tiny synthetic scan ----------------------------------------------

#: Coarse atlas and few fitted functions: a fast fixture (as tests/test_fit_stage.py).
TEST_TEXELS_PER_MM = 0.35
TEST_MAX_TEXELS = 60


@pytest.fixture(scope="module")
def fitted_scan(tmp_path_factory):
    from facegeo.cli import main
    from facegeo.pipeline.fit import run_fit
    from facegeo.pipeline.project import run_project

    root = tmp_path_factory.mktemp("export") / "scan"
    assert main(["synth", str(root), "--preset", "tiny", "-q"]) == 0
    run_project(root, atlas_settings={"texels_per_mm": TEST_TEXELS_PER_MM})
    run_fit(root, texels="views", views=["cam_left"], max_texels=TEST_MAX_TEXELS, mosaic=4)
    return root


def test_export_command_end_to_end(fitted_scan, capsys):
    import trimesh

    from facegeo.capture.imageio import read_image
    from facegeo.cli import main
    from facegeo.surface.atlas import Atlas, Texels

    root = fitted_scan
    assert main(["export", str(root)]) == 0
    assert "model.glb" in capsys.readouterr().out
    dest = root / "out" / "export"
    for name in ("model.glb", "albedo.png", "albedo.exr", "normal.png", "normal_tangent.exr",
                 "normal_world.exr", "specular.exr", "specular_weight.png", "export.json"):
        assert (dest / name).is_file(), name
    atlas = Atlas.load(root / "out" / "atlas" / "atlas.npz")
    texels = Texels.load(root / "out" / "atlas" / "texels.npz")
    (mesh,) = trimesh.load(dest / "model.glb", process=False).geometry.values()
    assert np.abs(mesh.vertices - atlas.vertices).max() <= POSITION_TOL_M
    assert np.array_equal(mesh.faces, atlas.faces)
    assert np.abs(mesh.visual.uv - atlas.uv).max() <= UV_TOL
    albedo = cv2.imread(str(root / "out" / "fit" / "albedo.png"), cv2.IMREAD_COLOR)[..., ::-1]
    assert np.array_equal(np.asarray(mesh.visual.material.baseColorTexture)[..., :3], albedo)
    assert mesh.visual.material.metallicFactor == 0.0

    # A viewer's decoding: the file's NORMAL/TANGENT interpolated at each fitted texel,
    # B = w N × T, n = T x + B y + N z from the 8-bit map → the fit's world normal.
    doc, binary = read_glb(dest / "model.glb")
    attrs = doc["meshes"][0]["primitives"][0]["attributes"]
    vn = _accessor(doc, binary, attrs["NORMAL"]).astype(np.float64)
    vt = _accessor(doc, binary, attrs["TANGENT"]).astype(np.float64)
    fitted = read_image(root / "out" / "fit" / "fitted.png")[texels.row, texels.col] > 0
    assert fitted.sum() > 0
    rows, cols = texels.row[fitted], texels.col[fitted]
    corners = atlas.faces[texels.face[fitted]]
    w = texels.bary[fitted]
    N = np.einsum("pk,pkc->pc", w, vn[corners])
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    T = np.einsum("pk,pkc->pc", w, vt[corners, :3])
    T -= np.einsum("pc,pc->p", T, N)[:, None] * N
    T /= np.linalg.norm(T, axis=1, keepdims=True)
    B = np.sign(np.einsum("pk,pk->p", w, vt[corners, 3]))[:, None] * np.cross(N, T)
    code = cv2.imread(str(dest / "normal.png"), cv2.IMREAD_COLOR)[..., ::-1]
    x = code[rows, cols].astype(np.float64) / 127.5 - 1.0
    n_dec = T * x[:, :1] + B * x[:, 1:2] + N * x[:, 2:3]
    n_dec /= np.linalg.norm(n_dec, axis=1, keepdims=True)
    n_fit = read_image(root / "out" / "fit" / "normal.exr")[rows, cols].astype(np.float64)
    err = np.degrees(np.arccos(np.clip(np.einsum("pc,pc->p", n_dec, n_fit), -1, 1)))
    assert err.max() <= VIEWER_NORMAL_DEG_MAX, err.max()
    assert np.median(x[:, 2]) >= FITTED_Z_MEDIAN_MIN
    # the specular strength (KHR_materials_specular, alpha) is the fit's ρ_s in 8 bits
    rho_s = read_image(root / "out" / "fit" / "specular.exr")[rows, cols]
    alpha = cv2.imread(str(dest / "specular_weight.png"), cv2.IMREAD_UNCHANGED)[rows, cols, 3]
    assert np.abs(alpha / 255.0 - np.clip(rho_s, 0, 1)).max() <= CHANNEL_8BIT_TOL
    assert rho_s.max() > 0, "some specular energy fitted"
    # unfitted texels hold the mesh's own normal
    other = texels.row[~fitted][:50], texels.col[~fitted][:50]
    assert np.array_equal(code[other], np.tile([128, 128, 255], (other[0].size, 1)))


def test_export_without_fit_names_the_stage(tmp_path, capsys):
    from facegeo.cli import main

    root = tmp_path / "scan"
    (root / "out" / "atlas").mkdir(parents=True)
    assert main(["export", str(root)]) == 2
    err = capsys.readouterr().err
    assert "missing atlas.npz, texels.npz" in err and f"facegeo fit {root}" in err
