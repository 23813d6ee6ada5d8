"""Binary glTF 2.0 (``.glb``) of a textured mesh with a PBR material: arrays in, file out.

The file is assembled here with numpy and :mod:`struct` (header, a JSON chunk and a BIN chunk,
every chunk and buffer view 4-byte aligned; glTF 2.0 specification §4.4 "GLB File Format
Specification"), not by trimesh's exporter, for two reasons measured on trimesh 4.x (see
docs/export.md): trimesh writes no ``TANGENT`` attribute, so a viewer would compute its own
MikkTSpace frame and the tangent-space normal map — encoded here in *our* frame — would be
read in another; and trimesh decodes and re-encodes the texture images, so the PNG inside the
``.glb`` is not byte-for-byte the PNG written beside it.

Conventions (docs/export.md):

* Positions in metres (glTF's unit), the world frame of docs/conventions.md (+Y up, like glTF).
* ``uv`` in, OBJ / OpenGL convention (origin bottom-left, v up; docs/surface.md); written as
  glTF ``TEXCOORD_0`` with ``v_gltf = 1 − v`` (glTF: origin top-left, v down, §3.7.2.1).
* Tangents ``(V, 4)``: xyz along +u, w = ±1 with the bitangent ``B = w · (N × T)`` along +v
  (image up), the frame glTF's normal textures use (§3.9.3: "+X is right and +Y is up").
* Normal textures hold ``n_tangent = (T·n, B·n, N·n)`` of a world-space normal n, encoded
  ``(n + 1) / 2`` in 8 bits.

References
----------
.. [1] The Khronos Group, "glTF 2.0 Specification",
   https://registry.khronos.org/glTF/specs/2.0/glTF-2.0.html (§3.7.2 meshes, §3.9 materials,
   §4.4 GLB, Appendix B: α = roughness²).
.. [2] M. Mikkelsen, "Simulation of Wrinkled Surfaces Revisited", MSc thesis, 2008
   (MikkTSpace: per-face tangents from UV derivatives, angle-weighted at the vertices).
.. [3] B. Walter et al., "Microfacet Models for Refraction through Rough Surfaces", EGSR 2007
   (Beckmann and GGX share the slope-scale parameter α).
.. [4] The Khronos Group, glTF extensions ``KHR_materials_specular`` (specular strength,
   alpha channel of ``specularTexture``) and ``KHR_materials_ior``,
   https://github.com/KhronosGroup/glTF/tree/main/extensions/2.0/Khronos
"""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.checks import as_array, fmt_value
from facegeo.errors import InputError
from facegeo.fsutil import atomic_write_bytes

__all__ = ["write_glb", "build_glb", "read_glb", "vertex_tangents", "tangent_space_normals",
           "encode_normal_map", "roughness_from_beckmann", "GLB_MAGIC"]

#: ``b"glTF"`` read as a little-endian uint32 (§4.4.3.1).
GLB_MAGIC = 0x46546C67
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# glTF enums (§5): component types, buffer-view targets, sampler filters and wraps
_FLOAT, _UINT32 = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_LINEAR, _LINEAR_MIPMAP_LINEAR, _CLAMP_TO_EDGE = 9729, 9987, 33071
_TRIANGLES = 4


def _unit(a: np.ndarray, fallback: np.ndarray | None = None) -> np.ndarray:
    n = np.linalg.norm(a, axis=-1, keepdims=True)
    out = a / np.where(n > 0, n, 1.0)
    if fallback is not None:
        out = np.where(n > 0, out, fallback)
    return out


def _any_perpendicular(n: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to each unit ``n`` (for vertices with no UV gradient)."""
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    return _unit(np.cross(n, helper))


def vertex_tangents(vertices: Any, faces: Any, uv: Any, normals: Any) -> np.ndarray:
    """Per-vertex tangent frames from the UV parameterisation (MikkTSpace-like).

    Each face's tangent ``T_f = ∂p/∂u`` and bitangent ``B_f = ∂p/∂v`` solve
    ``[e1 e2] = [T_f B_f] [[du1, du2], [dv1, dv2]]`` for its edges ``e1 = p1 − p0``,
    ``e2 = p2 − p0``; normalised, they are summed at the face's corners weighted by the corner
    angle [2], orthogonalised against the vertex normal (Gram–Schmidt) and the handedness
    ``w = sign((N × T) · B)`` kept. Faces with a degenerate UV triangle contribute nothing; a
    vertex no face gives a tangent gets any unit vector perpendicular to its normal (w = +1).

    Parameters
    ----------
    vertices : (V, 3) float64, metres
    faces : (F, 3) int
    uv : (V, 2) float64, OBJ convention (v up; docs/surface.md)
    normals : (V, 3) float64, unit

    Returns
    -------
    (V, 4) float64 — xyz unit, ⟂ normal; w = ±1 (glTF ``TANGENT``, §3.7.2.1)
    """
    p = as_array(vertices, "vertices", shape=(None, 3))
    f = as_array(faces, "faces", shape=(None, 3), dtype=np.int64)
    t = as_array(uv, "uv", shape=(p.shape[0], 2))
    n = _unit(as_array(normals, "normals", shape=(p.shape[0], 3)))
    if f.size and (f.min() < 0 or f.max() >= p.shape[0]):
        raise InputError(f"faces: indices must be in [0, {p.shape[0]}), got "
                         f"[{f.min()}, {f.max()}]")
    e1, e2 = p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]]
    d1, d2 = t[f[:, 1]] - t[f[:, 0]], t[f[:, 2]] - t[f[:, 0]]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    ok = np.abs(det) > 1e-20
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)[:, None]
    T_f = _unit((e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * inv)
    B_f = _unit((e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * inv)
    # corner angles (MikkTSpace weights each face's contribution by its angle at the vertex)
    T_acc, B_acc = np.zeros_like(p), np.zeros_like(p)
    for k in range(3):
        a = p[f[:, (k + 1) % 3]] - p[f[:, k]]
        b = p[f[:, (k + 2) % 3]] - p[f[:, k]]
        ang = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
        w = np.where(ok, ang, 0.0)[:, None]
        np.add.at(T_acc, f[:, k], T_f * w)
        np.add.at(B_acc, f[:, k], B_f * w)
    T = T_acc - np.einsum("ij,ij->i", T_acc, n)[:, None] * n
    T = _unit(T, fallback=_any_perpendicular(n))
    handed = np.einsum("ij,ij->i", np.cross(n, T), B_acc)
    return np.concatenate([T, np.where(handed < 0, -1.0, 1.0)[:, None]], axis=1)


def tangent_space_normals(n_world: Any, face: Any, bary: Any, faces: Any, normals: Any,
                          tangents: Any) -> np.ndarray:
    """World-space normals at surface points expressed in the mesh's tangent frame.

    At each point the frame a glTF viewer builds is rebuilt: the corner normals and tangents
    interpolated by the barycentrics, ``N`` normalised, ``T`` orthogonalised against it,
    ``B = w (N × T)``; then ``n_tangent = TBNᵀ n_world = (T·n, B·n, N·n)``.

    Parameters
    ----------
    n_world : (P, 3) float64, unit, world frame
    face : (P,) int — face of each point
    bary : (P, 3) float64 — barycentric weights of the face's corners
    faces : (F, 3) int
    normals : (V, 3) float64, unit — the mesh's vertex (shading) normals
    tangents : (V, 4) float64 — :func:`vertex_tangents`

    Returns
    -------
    (P, 3) float64, unit, tangent frame (+z along the interpolated normal)
    """
    n = as_array(n_world, "n_world", shape=(None, 3))
    fi = as_array(face, "face", shape=(n.shape[0],), dtype=np.int64)
    w = as_array(bary, "bary", shape=(n.shape[0], 3))
    f = as_array(faces, "faces", shape=(None, 3), dtype=np.int64)
    vn = as_array(normals, "normals", shape=(None, 3))
    vt = as_array(tangents, "tangents", shape=(vn.shape[0], 4))
    corners = f[fi]  # (P, 3)
    N = _unit(np.einsum("pk,pkc->pc", w, vn[corners]))
    T = np.einsum("pk,pkc->pc", w, vt[corners, :3])
    T = _unit(T - np.einsum("pc,pc->p", T, N)[:, None] * N, fallback=_any_perpendicular(N))
    hand = np.where(np.einsum("pk,pk->p", w, vt[corners, 3]) < 0, -1.0, 1.0)
    B = hand[:, None] * np.cross(N, T)
    out = np.stack([np.einsum("pc,pc->p", T, n), np.einsum("pc,pc->p", B, n),
                    np.einsum("pc,pc->p", N, n)], axis=1)
    return _unit(out, fallback=np.array([0.0, 0.0, 1.0]))


def encode_normal_map(n: Any) -> np.ndarray:
    """Unit normals ``(..., 3)`` in [−1, 1] → uint8 ``round((n + 1) / 2 · 255)`` (glTF §3.9.3)."""
    a = as_array(n, "n", shape=(..., 3))
    return np.clip(np.rint((a + 1.0) * 127.5), 0, 255).astype(np.uint8)


def roughness_from_beckmann(m: Any) -> np.ndarray:
    """glTF ``roughness`` of a Beckmann lobe of RMS slope m: ``sqrt(m)``.

    glTF's specular lobe is GGX with α = roughness² (spec Appendix B); the paper's
    Torrance–Sparrow model uses a Beckmann distribution of RMS slope m (docs/skin.md). Taking
    α_GGX = m matches the two lobes near their peak (they share the slope scale, [3]); GGX's
    tail is longer, so the exported highlight is slightly wider at grazing half-angles.
    """
    a = as_array(m, "m", shape=None)
    if np.any(a <= 0):
        raise InputError(f"m: Beckmann RMS slope must be > 0, got {fmt_value(a.min())}")
    return np.sqrt(a)


def _png_bytes(x: Any, name: str) -> bytes:
    data = x if isinstance(x, (bytes, bytearray)) else None
    if data is None:
        path = Path(x)
        if not path.is_file():
            raise InputError(f"{name}: no PNG file at {path}")
        data = path.read_bytes()
    if bytes(data[:8]) != _PNG_SIGNATURE:
        raise InputError(f"{name}: not a PNG (the first 8 bytes are not the PNG signature)"
                         + ("" if isinstance(x, (bytes, bytearray)) else f": {x}"))
    return bytes(data)


class _Bin:
    """The BIN chunk under construction: 4-byte aligned buffer views and their accessors."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.size = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        pad = (-self.size) % 4
        if pad:
            self.parts.append(b"\0" * pad)
            self.size += pad
        v = {"buffer": 0, "byteOffset": self.size, "byteLength": len(data)}
        if target is not None:
            v["target"] = target
        self.parts.append(data)
        self.size += len(data)
        self.views.append(v)
        return len(self.views) - 1

    def accessor(self, a: np.ndarray, kind: str, target: int, *, bounds: bool = False) -> int:
        ctype = _UINT32 if a.dtype == np.uint32 else _FLOAT
        acc = {"bufferView": self.view(np.ascontiguousarray(a).tobytes(), target),
               "componentType": ctype, "count": int(a.shape[0]), "type": kind}
        if bounds:  # required for POSITION (§3.7.2.1)
            acc["min"] = [float(x) for x in a.reshape(a.shape[0], -1).min(axis=0)]
            acc["max"] = [float(x) for x in a.reshape(a.shape[0], -1).max(axis=0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def bytes(self) -> bytes:
        out = b"".join(self.parts)
        return out + b"\0" * ((-len(out)) % 4)


def build_glb(vertices: Any, faces: Any, uv: Any, normals: Any, *, base_color_png: Any,
              normal_png: Any, metallic_roughness_png: Any = None, tangents: Any = None,
              roughness_factor: float = 1.0, metallic_factor: float = 0.0,
              specular_png: Any = None, ior: float | None = None,
              name: str = "facegeo", extras: dict | None = None) -> bytes:
    """The bytes of a ``.glb``: one mesh, one node, one PBR material (see :func:`write_glb`)."""
    p = as_array(vertices, "vertices", shape=(None, 3))
    f = as_array(faces, "faces", shape=(None, 3), dtype=np.int64)
    t = as_array(uv, "uv", shape=(p.shape[0], 2))
    n = as_array(normals, "normals", shape=(p.shape[0], 3))
    if p.shape[0] == 0 or f.shape[0] == 0:
        raise InputError(f"vertices/faces: an empty mesh ({p.shape[0]} vertices, "
                         f"{f.shape[0]} faces)")
    if f.min() < 0 or f.max() >= p.shape[0]:
        raise InputError(f"faces: indices must be in [0, {p.shape[0]}), got "
                         f"[{f.min()}, {f.max()}]")
    tan = (vertex_tangents(p, f, t, n) if tangents is None
           else as_array(tangents, "tangents", shape=(p.shape[0], 4)))
    for v, nm in ((roughness_factor, "roughness_factor"), (metallic_factor, "metallic_factor")):
        if not 0.0 <= float(v) <= 1.0:
            raise InputError(f"{nm}: expected a number in [0, 1], got {fmt_value(v)}")
    images = {"baseColor": _png_bytes(base_color_png, "base_color_png"),
              "normal": _png_bytes(normal_png, "normal_png")}
    if metallic_roughness_png is not None:
        images["metallicRoughness"] = _png_bytes(metallic_roughness_png,
                                                 "metallic_roughness_png")
    if specular_png is not None:
        images["specular"] = _png_bytes(specular_png, "specular_png")
    if ior is not None and not (np.isfinite(float(ior)) and float(ior) >= 1.0):
        raise InputError(f"ior: expected a finite number >= 1, got {fmt_value(ior)}")

    b = _Bin()
    uv_gltf = np.stack([t[:, 0], 1.0 - t[:, 1]], axis=1)  # v up (OBJ) → v down (glTF)
    attributes = {
        "POSITION": b.accessor(p.astype(np.float32), "VEC3", _ARRAY_BUFFER, bounds=True),
        "NORMAL": b.accessor(_unit(n).astype(np.float32), "VEC3", _ARRAY_BUFFER),
        "TANGENT": b.accessor(tan.astype(np.float32), "VEC4", _ARRAY_BUFFER),
        "TEXCOORD_0": b.accessor(uv_gltf.astype(np.float32), "VEC2", _ARRAY_BUFFER),
    }
    indices = b.accessor(f.astype(np.uint32).reshape(-1), "SCALAR", _ELEMENT_ARRAY_BUFFER)
    tex_index = {}
    gl_images, textures = [], []
    for key, data in images.items():
        gl_images.append({"bufferView": b.view(data), "mimeType": "image/png", "name": key})
        textures.append({"source": len(gl_images) - 1, "sampler": 0})
        tex_index[key] = len(textures) - 1
    pbr = {"baseColorTexture": {"index": tex_index["baseColor"], "texCoord": 0},
           "metallicFactor": float(metallic_factor), "roughnessFactor": float(roughness_factor)}
    if "metallicRoughness" in tex_index:
        pbr["metallicRoughnessTexture"] = {"index": tex_index["metallicRoughness"],
                                           "texCoord": 0}
    extensions = {}
    if "specular" in tex_index:  # strength in the texture's alpha channel
        extensions["KHR_materials_specular"] = {
            "specularFactor": 1.0,
            "specularTexture": {"index": tex_index["specular"], "texCoord": 0}}
    if ior is not None:
        extensions["KHR_materials_ior"] = {"ior": float(ior)}
    material = {"name": name, "pbrMetallicRoughness": pbr,
                "normalTexture": {"index": tex_index["normal"], "texCoord": 0, "scale": 1.0},
                "doubleSided": False}
    if extensions:
        material["extensions"] = extensions
    binary = b.bytes()
    doc = {
        "asset": {"version": "2.0", "generator": "facegeo (facegeo.render.gltf)"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": name}],
        "meshes": [{"name": name, "primitives": [{"attributes": attributes, "indices": indices,
                                                  "material": 0, "mode": _TRIANGLES}]}],
        "materials": [material],
        "textures": textures,
        "images": gl_images,
        "samplers": [{"magFilter": _LINEAR, "minFilter": _LINEAR_MIPMAP_LINEAR,
                      "wrapS": _CLAMP_TO_EDGE, "wrapT": _CLAMP_TO_EDGE}],
        "accessors": b.accessors,
        "bufferViews": b.views,
        "buffers": [{"byteLength": len(binary)}],
    }
    if extensions:  # optional: a viewer without them keeps core glTF's F0 = 0.04, weight 1
        doc["extensionsUsed"] = sorted(extensions)
    if extras:
        doc["extras"] = extras
    js = json.dumps(doc, separators=(",", ":"), allow_nan=False).encode("utf-8")
    js += b" " * ((-len(js)) % 4)  # the JSON chunk is padded with spaces (§4.4.3.2)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return b"".join([struct.pack("<III", GLB_MAGIC, 2, total),
                     struct.pack("<II", len(js), _CHUNK_JSON), js,
                     struct.pack("<II", len(binary), _CHUNK_BIN), binary])


def write_glb(path: Any, vertices: Any, faces: Any, uv: Any, normals: Any, *,
              base_color_png: Any, normal_png: Any, metallic_roughness_png: Any = None,
              tangents: Any = None, roughness_factor: float = 1.0,
              metallic_factor: float = 0.0, specular_png: Any = None,
              ior: float | None = None, name: str = "facegeo",
              extras: dict | None = None) -> Path:
    """Write a textured triangle mesh with a glTF metallic-roughness material (atomically).

    Parameters
    ----------
    path : path-like, ``.glb``
    vertices : (V, 3) float64, metres, world frame
    faces : (F, 3) int — counter-clockwise seen from the front (glTF §3.7.2.1)
    uv : (V, 2) float64, OBJ convention (origin bottom-left, v up; docs/surface.md); written
        with v flipped to glTF's top-left origin
    normals : (V, 3) float64, unit, world frame — shading normals
    base_color_png : path-like or bytes — sRGB PNG (``baseColorTexture``)
    normal_png : path-like or bytes — tangent-space normal map in the frame of ``tangents``
        (:func:`tangent_space_normals`, :func:`encode_normal_map`)
    metallic_roughness_png : path-like or bytes, optional — linear PNG, G = roughness,
        B = metallic (glTF §3.9.2); multiplied by the factors
    tangents : (V, 4) float64, optional — default :func:`vertex_tangents` of the mesh; written
        as ``TANGENT`` so viewers read the normal map in the frame it was encoded in
    roughness_factor, metallic_factor : float in [0, 1]
    specular_png : path-like or bytes, optional — PNG whose alpha channel is the specular
        strength (``KHR_materials_specular``'s ``specularTexture``, linear, factor 1)
    ior : float ≥ 1, optional — index of refraction (``KHR_materials_ior``; core glTF: 1.5)
    name : str — node, mesh and material name
    extras : dict, optional — JSON-serialisable, stored as the glTF root's ``extras``

    Returns
    -------
    pathlib.Path
        ``path``. The PNGs are embedded byte for byte.
    """
    path = Path(path)
    if path.suffix.lower() != ".glb":
        raise InputError(f"path: expected a .glb file name, got {fmt_value(str(path))}")
    data = build_glb(vertices, faces, uv, normals, base_color_png=base_color_png,
                     normal_png=normal_png, metallic_roughness_png=metallic_roughness_png,
                     tangents=tangents, roughness_factor=roughness_factor,
                     metallic_factor=metallic_factor, specular_png=specular_png, ior=ior,
                     name=name, extras=extras)
    atomic_write_bytes(path, data)
    return path


def read_glb(path: Any) -> tuple[dict, bytes]:
    """The JSON document and BIN chunk of a ``.glb`` (header and chunk lengths checked)."""
    path = Path(path)
    data = path.read_bytes()
    if len(data) < 20:
        raise InputError(f"{path}: too short for a GLB ({len(data)} bytes)")
    magic, version, total = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC or version != 2 or total != len(data):
        raise InputError(f"{path}: not a glTF 2.0 GLB (magic {magic:#x}, version {version}, "
                         f"length {total} for a {len(data)}-byte file)")
    jlen, jtype = struct.unpack_from("<II", data, 12)
    if jtype != _CHUNK_JSON:
        raise InputError(f"{path}: the first chunk is not JSON (type {jtype:#x})")
    doc = json.loads(data[20:20 + jlen].decode("utf-8"))
    binary = b""
    if 20 + jlen < len(data):
        blen, btype = struct.unpack_from("<II", data, 20 + jlen)
        if btype != _CHUNK_BIN:
            raise InputError(f"{path}: the second chunk is not BIN (type {btype:#x})")
        binary = data[28 + jlen:28 + jlen + blen]
    return doc, binary
