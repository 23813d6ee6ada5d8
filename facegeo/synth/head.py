"""Heads for synthetic capture: a procedural head and a loader for real head meshes.

:func:`procedural_head` builds a watertight, star-shaped head as a radial displacement of a
subdivided icosphere, ``p(ω) = r(ω) ω``: an ellipsoid-like skull (narrower jaw, flattened sides)
plus smooth (C¹) facial features sized like a real face — a nose that protrudes ≈ 2.75 cm with
steep sides and nostril dimples, eye sockets ≈ 1 cm deep under a brow ridge, cheekbones, upper
and lower lips with a mouth crease, a chin and optional ears. Because every vertex moves along
its own ray from the origin, the mesh keeps the icosphere's connectivity: it stays closed,
manifold and outward-wound whatever the features (each triangle's signed volume
``det[p0, p1, p2] = r0 r1 r2 det[ω0, ω1, ω2] > 0``).

World frame (DESIGN §3): metres, +Y up, the face looks along +Z, the subject's left toward +X
(right-handed: the subject's right is ``forward × up = +Z × +Y = −X``).

:func:`load_head_mesh` reads OBJ (own reader: keeps UV seams, groups and materials), PLY and GLB
(trimesh), converts units to metres and can drop overlay groups.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np

from facegeo.checks import check_choice, fmt_value
from facegeo.errors import InputError

__all__ = [
    "HeadParams",
    "procedural_head",
    "head_radius",
    "head_landmarks",
    "HEAD_LANDMARKS",
    "LANDMARK_NAMES",
    "load_head_mesh",
    "DEFAULT_DROP_GROUPS",
    "UNIT_SCALE",
    "CORE_LANDMARKS",
    "ICT_IBUG68_INDEX",
    "MEDIAPIPE_INDEX",
    "PART_NAMES",
    "part_labels",
    "real_face_landmarks",
    "frame_face",
    "face_box",
    "landmarks_file_for",
]

log = logging.getLogger(__name__)

#: Metres per unit of a mesh file.
UNIT_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001}

#: Overlay groups/materials a renderer should not show (matched case-insensitively as
#: substrings of OBJ ``g``/``o``/``usemtl`` names). The ICT FaceKit mesh names them
#: ``M_LacrimalFluid``, ``M_EyeBlend``, ``M_EyeOcclusion`` and ``M_EyeLashes``.
DEFAULT_DROP_GROUPS = ("lacrimalfluid", "eyeblend", "eyeocclusion", "eyelashes")


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class HeadParams:
    """Shape of the procedural head; lengths in metres (world frame, see module docstring).

    Skull: semi-axes of an ellipsoid split at y = 0 and z = 0 (C¹ across the splits because
    each axis enters squared). Features are C¹ compact bumps ``(1 − q)³`` in the coordinates
    ``(X, Y)`` = world x, y of the skull surface, masked to the front of the head.
    """

    ax: float = 0.083  # half width before side flattening (ears excluded)
    ay_top: float = 0.118  # crown above the centre
    ay_bottom: float = 0.108  # under the chin
    az_front: float = 0.088  # face (without nose) in front of the centre
    az_back: float = 0.093  # back of the skull
    jaw_taper: float = 0.22  # relative narrowing of the width toward the chin
    side_flatten: float = 0.05  # relative radius loss at the sides (∝ ω_x⁴)
    # nose
    nose_height: float = 0.0275  # protrusion of the tip above the skull surface
    nose_tip_y: float = -0.020
    nose_base_y: float = -0.033  # subnasale: the underside meets the upper lip
    nasion_y: float = 0.030
    nasion_height: float = 0.004
    nose_tip_halfwidth: float = 0.018
    nose_bridge_halfwidth: float = 0.010
    ala_offset: float = 0.0160  # nostril wings at x = ±ala_offset
    ala_radius: float = 0.0100
    ala_height: float = 0.010
    nostril_offset: float = 0.0065
    nostril_depth: float = 0.005
    nostril_radius: float = 0.0045
    # eyes and brow
    eye_x: float = 0.032
    eye_y: float = 0.018
    eye_depth: float = 0.013
    eye_rx: float = 0.022
    eye_ry: float = 0.016
    eyeball_height: float = 0.004
    brow_y: float = 0.036
    brow_height: float = 0.005
    brow_halfwidth: float = 0.058
    brow_sigma: float = 0.009
    # cheeks
    cheekbone_x: float = 0.043
    cheekbone_y: float = -0.004
    cheekbone_height: float = 0.006
    cheekbone_radius: float = 0.024
    # mouth and chin
    muzzle_height: float = 0.010
    mouth_y: float = -0.050
    lip_height: float = 0.006
    lip_halfwidth: float = 0.025
    crease_depth: float = 0.004
    chin_y: float = -0.084
    chin_height: float = 0.009
    # ears (only when built with ears=True)
    ear_height: float = 0.018
    ear_y: float = 0.004
    ear_z: float = -0.012

    @classmethod
    def from_seed(cls, seed: int | None) -> HeadParams:
        """Default parameters (``seed=None``) or a seeded subject: each size scaled by a few
        per cent, feature heights by ±10–15 %, keeping the nose within 2.5–3.0 cm."""
        p = cls()
        if seed is None:
            return p
        rng = np.random.default_rng(seed)
        s = rng.uniform(0.97, 1.03)  # overall skull scale

        def u(a, b):
            return float(rng.uniform(a, b))

        return replace(
            p,
            ax=p.ax * s * u(0.98, 1.02),
            ay_top=p.ay_top * s * u(0.98, 1.02),
            ay_bottom=p.ay_bottom * s * u(0.98, 1.02),
            az_front=p.az_front * s,
            az_back=p.az_back * s * u(0.98, 1.02),
            jaw_taper=p.jaw_taper * u(0.85, 1.15),
            nose_height=float(np.clip(p.nose_height * u(0.92, 1.08), 0.0252, 0.0298)),
            nose_tip_halfwidth=p.nose_tip_halfwidth * u(0.92, 1.08),
            nose_tip_y=p.nose_tip_y + u(-0.002, 0.002),
            ala_height=p.ala_height * u(0.9, 1.1),
            eye_depth=p.eye_depth * u(0.9, 1.1),
            brow_height=p.brow_height * u(0.85, 1.15),
            cheekbone_height=p.cheekbone_height * u(0.8, 1.2),
            lip_height=p.lip_height * u(0.85, 1.15),
            mouth_y=p.mouth_y + u(-0.002, 0.002),
            chin_height=p.chin_height * u(0.85, 1.15),
        )

    def to_dict(self) -> dict:
        """JSON-ready mapping of every field."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> HeadParams:
        """Inverse of :meth:`to_dict`; unknown keys raise :class:`InputError`."""
        names = {f.name for f in fields(cls)}
        bad = sorted(set(d) - names)
        if bad:
            raise InputError(
                f"head parameters: unknown key(s) {bad}; expected a subset of {sorted(names)}"
            )
        return cls(**{k: float(v) for k, v in d.items()})


# --------------------------------------------------------------------------- radial function


def _sstep(t):
    """C¹ smoothstep on [0, 1]."""
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _bump(q):
    """C² compact bump of a squared normalised radius q: (1 − q)³ for q < 1, else 0."""
    return np.clip(1.0 - q, 0.0, None) ** 3


def _ellipse_bump(X, Y, cx, cy, rx, ry):
    return _bump(((X - cx) / rx) ** 2 + ((Y - cy) / ry) ** 2)


def _skull_radius(w, p: HeadParams):
    """Radius of the skull (ellipsoid with split axes, tapered jaw, flattened sides) along ω."""
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    ay = np.where(y >= 0, p.ay_top, p.ay_bottom)
    az = np.where(z >= 0, p.az_front, p.az_back)
    ax = p.ax * (1.0 - p.jaw_taper * _sstep(-y))
    r = 1.0 / np.sqrt((x / ax) ** 2 + (y / ay) ** 2 + (z / az) ** 2)
    return r * (1.0 - p.side_flatten * x**4)


def _nose(X, Y, p: HeadParams):
    """Nose ridge: height profile along Y times a steep C¹ cross-section, plus alae and
    nostril dimples."""
    H = p.nose_height
    yt, ys, yn = p.nose_tip_y, p.nose_base_y, p.nasion_y
    yg = yn + 0.012  # glabella: the bridge fades into the forehead
    # Profile: 0 at the subnasale -> H at the tip (steep underside) -> nasion_height -> 0.
    below = H * _sstep((Y - ys) / (yt - ys))
    bridge = H - (H - p.nasion_height) * _sstep((Y - yt) / (yn - yt))
    above = p.nasion_height * (1.0 - _sstep((Y - yn) / (yg - yn)))
    h = np.where(Y < yt, below, np.where(Y < yn, bridge, above))
    # Half-width: bridge -> tip, C¹ in Y.
    w = p.nose_bridge_halfwidth + (p.nose_tip_halfwidth - p.nose_bridge_halfwidth) * _sstep(
        (yn - Y) / (yn - yt)
    )
    ridge = h * _bump((X / w) ** 2)
    ala_y = ys + 0.35 * (yt - ys)
    alae = p.ala_height * (
        _ellipse_bump(X, Y, p.ala_offset, ala_y, p.ala_radius, 0.8 * p.ala_radius)
        + _ellipse_bump(X, Y, -p.ala_offset, ala_y, p.ala_radius, 0.8 * p.ala_radius)
    )
    ny = ys + 0.25 * (yt - ys)
    nostrils = p.nostril_depth * (
        _ellipse_bump(X, Y, p.nostril_offset, ny, p.nostril_radius, 0.7 * p.nostril_radius)
        + _ellipse_bump(X, Y, -p.nostril_offset, ny, p.nostril_radius, 0.7 * p.nostril_radius)
    )
    return ridge + alae - nostrils


def _face(X, Y, p: HeadParams):
    """Every frontal feature's radial displacement (metres) at skull coordinates (X, Y)."""
    d = _nose(X, Y, p)
    for sx in (1.0, -1.0):
        # Eye socket (concave) with a shallow eyeball bulge inside.
        d = d - p.eye_depth * _ellipse_bump(X, Y, sx * p.eye_x, p.eye_y, p.eye_rx, p.eye_ry)
        d = d + p.eyeball_height * _ellipse_bump(X, Y, sx * p.eye_x, p.eye_y, 0.5 * p.eye_rx,
                                                 0.5 * p.eye_ry)
        d = d + p.cheekbone_height * _ellipse_bump(X, Y, sx * p.cheekbone_x, p.cheekbone_y,
                                                   p.cheekbone_radius, 0.8 * p.cheekbone_radius)
    # Brow ridge: Gaussian across, compact along.
    d = d + p.brow_height * np.exp(-0.5 * ((Y - p.brow_y) / p.brow_sigma) ** 2) * _bump(
        (X / p.brow_halfwidth) ** 2
    )
    # Muzzle (teeth and maxilla under the lips), lips, mouth crease, chin.
    ym = p.mouth_y
    d = d + p.muzzle_height * _ellipse_bump(X, Y, 0.0, ym + 0.002, 0.042, 0.034)
    d = d + p.lip_height * _ellipse_bump(X, Y, 0.0, ym + 0.0065, p.lip_halfwidth, 0.009)
    d = d + 1.25 * p.lip_height * _ellipse_bump(X, Y, 0.0, ym - 0.0075, 0.9 * p.lip_halfwidth,
                                                0.0095)
    d = d - p.crease_depth * np.exp(-0.5 * ((Y - ym) / 0.0022) ** 2) * _bump(
        (X / (1.1 * p.lip_halfwidth)) ** 2
    )
    d = d - 0.0025 * _ellipse_bump(X, Y, 0.0, ym - 0.018, 0.018, 0.006)  # mentolabial sulcus
    d = d + p.chin_height * _ellipse_bump(X, Y, 0.0, p.chin_y, 0.022, 0.016)
    return d


def head_radius(w, params: HeadParams | None = None, *, ears: bool = False) -> np.ndarray:
    """Radius r(ω) of the procedural head's surface along unit directions ``ω``.

    Parameters
    ----------
    w : (..., 3) float64, unit vectors, world frame
    params : HeadParams, optional
        Defaults to ``HeadParams()``.
    ears : bool
        Add ear bumps on the sides.

    Returns
    -------
    (...) float64, metres, > 0
        The surface point along ω is ``r(ω) ω``.
    """
    p = params or HeadParams()
    w = np.asarray(w, dtype=float)
    r0 = _skull_radius(w, p)
    X = r0 * w[..., 0]
    Y = r0 * w[..., 1]
    front = _sstep((w[..., 2] - 0.05) / 0.30)
    r = r0 + front * _face(X, Y, p)
    if ears:
        Z = r0 * w[..., 2]
        side = _sstep((np.abs(w[..., 0]) - 0.55) / 0.3)
        r = r + p.ear_height * side * _ellipse_bump(Y, Z, p.ear_y, p.ear_z, 0.030, 0.017)
    return r


# --------------------------------------------------------------------------- mesh


def _icosphere(subdivisions: int):
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    w = np.asarray(ico.vertices, dtype=float)
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    return w, np.asarray(ico.faces, dtype=np.int64)


def procedural_head(subdivisions: int = 5, *, ears: bool = False, seed: int | None = None):
    """A closed procedural head mesh (``trimesh.Trimesh``, ``process=False``), metres.

    Radial displacement ``r(ω) ω`` (:func:`head_radius`) of a subdivided icosphere: watertight,
    manifold, consistently outward-wound, genus 0, star-shaped about the origin. About
    0.16 m wide, 0.23 m tall and 0.20 m deep (nose included), +Y up, face toward +Z.

    Parameters
    ----------
    subdivisions : int
        Icosphere subdivisions: 4 → 5,120 faces, 5 → 20,480, 6 → 81,920, 7 → 327,680.
    ears : bool
        Add ear bumps on the sides.
    seed : int, optional
        ``None``: the default head; an int: a seeded subject (:meth:`HeadParams.from_seed`).

    Returns
    -------
    trimesh.Trimesh
        ``metadata["facegeo_head"]`` holds ``{"params": ..., "ears": ..., "seed": ...,
        "subdivisions": ...}`` so :func:`head_landmarks` can find landmarks on it.
    """
    import trimesh

    if int(subdivisions) != subdivisions or not 0 <= int(subdivisions) <= 8:
        raise InputError(f"subdivisions: expected an integer in [0, 8], got {fmt_value(subdivisions)}")
    params = HeadParams.from_seed(seed)
    w, faces = _icosphere(int(subdivisions))
    r = head_radius(w, params, ears=ears)
    mesh = trimesh.Trimesh(vertices=w * r[:, None], faces=faces, process=False)
    mesh.metadata["facegeo_head"] = {
        "params": params.to_dict(),
        "ears": bool(ears),
        "seed": seed,
        "subdivisions": int(subdivisions),
    }
    return mesh


# --------------------------------------------------------------------------- landmarks

#: Landmark names, in a fixed order. "left"/"right" are the subject's (left = +X).
LANDMARK_NAMES = (
    "nose_tip",
    "left_eye",
    "right_eye",
    "mouth_center",
    "chin",
    "forehead",
    "left_cheek",
    "right_cheek",
    "left_brow",
    "right_brow",
    "left_under_eye",
    "right_under_eye",
    "upper_lip",
    "lower_lip",
    "nose_bridge",
)


def _landmark_xy(p: HeadParams) -> dict[str, tuple[float, float]]:
    """Skull-surface coordinates (X, Y) of every landmark, metres."""
    return {
        "nose_tip": (0.0, p.nose_tip_y),
        "left_eye": (p.eye_x, p.eye_y),
        "right_eye": (-p.eye_x, p.eye_y),
        "mouth_center": (0.0, p.mouth_y),
        "chin": (0.0, p.chin_y),
        "forehead": (0.0, 0.068),
        "left_cheek": (0.044, -0.026),
        "right_cheek": (-0.044, -0.026),
        "left_brow": (p.eye_x, p.brow_y),
        "right_brow": (-p.eye_x, p.brow_y),
        "left_under_eye": (p.eye_x, p.eye_y - 0.021),
        "right_under_eye": (-p.eye_x, p.eye_y - 0.021),
        "upper_lip": (0.0, p.mouth_y + 0.0065),
        "lower_lip": (0.0, p.mouth_y - 0.0075),
        "nose_bridge": (0.0, 0.5 * (p.eye_y + p.nose_tip_y)),
    }


def _direction_of_xy(X, Y, p: HeadParams) -> np.ndarray:
    """Unit ω (..., 3) on the front whose skull point has world (x, y) = (X, Y).

    Fixed-point iteration ``ω ← normalise(X, Y, sqrt(r_skull(ω)² − X² − Y²))``; the skull
    radius varies slowly, so it converges to 1e-14 in a few dozen steps.
    """
    X, Y = np.broadcast_arrays(np.asarray(X, float), np.asarray(Y, float))
    w = np.stack([X, Y, np.full(X.shape, p.az_front)], axis=-1)
    w /= np.linalg.norm(w, axis=-1, keepdims=True)
    for _ in range(100):
        r0 = _skull_radius(w, p)
        z = np.sqrt(np.maximum(r0 * r0 - X * X - Y * Y, 1e-12))
        w_new = np.stack([X, Y, z], axis=-1)
        w_new /= np.linalg.norm(w_new, axis=-1, keepdims=True)
        done = np.abs(w_new - w).max() < 1e-14
        w = w_new
        if done:
            break
    return w


def _nose_tip_direction(p: HeadParams, ears: bool) -> np.ndarray:
    """ω of the most +Z point of the smooth surface on the midline near the nose tip."""
    Y = np.linspace(p.nose_tip_y - 0.012, p.nose_tip_y + 0.012, 2401)  # 10 µm steps
    w = _direction_of_xy(np.zeros_like(Y), Y, p)
    z = head_radius(w, p, ears=ears) * w[:, 2]
    return w[int(np.argmax(z))]


def _ray_hit_star_mesh(w: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Point where the ray ``t ω`` (t > 0) leaves a mesh that is star-shaped about the origin
    (Möller–Trumbore against every triangle, farthest hit)."""
    v0 = vertices[faces[:, 0]]
    e1 = vertices[faces[:, 1]] - v0
    e2 = vertices[faces[:, 2]] - v0
    pvec = np.cross(w[None, :], e2)
    det = np.einsum("fi,fi->f", e1, pvec)
    ok = np.abs(det) > 1e-18
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = -v0
    u = np.einsum("fi,fi->f", tvec, pvec) * inv
    qvec = np.cross(tvec, e1)
    v = (qvec @ w) * inv
    t = np.einsum("fi,fi->f", e2, qvec) * inv
    eps = 1e-9
    hit = ok & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps) & (t > 0)
    if not hit.any():
        raise InputError("head_landmarks: a landmark ray misses the mesh (not a procedural head?)")
    return float(t[hit].max()) * w


def head_landmarks(mesh=None, *, params: HeadParams | None = None, ears: bool = False,
                   seed: int | None = None) -> dict[str, np.ndarray]:
    """Facial landmarks of a procedural head: name → (3,) float64 point, metres, world frame.

    Each landmark is a direction ω from the origin (chosen where the skull surface has the
    landmark's (x, y)); its point is where that ray meets the surface — the procedural mesh
    when ``mesh`` is given (exactly on its triangles), else the smooth surface ``r(ω) ω``.

    Parameters
    ----------
    mesh : trimesh.Trimesh, optional
        A mesh from :func:`procedural_head` (its ``metadata["facegeo_head"]`` gives the shape).
    params : HeadParams, optional
        Shape when no mesh is given; default from ``seed``.
    ears, seed
        As in :func:`procedural_head`, when no mesh is given.

    Returns
    -------
    dict of str → (3,) float64
        Keys :data:`LANDMARK_NAMES` ("left"/"right" are the subject's; left = +X): nose_tip (the
        most +Z point of the smooth surface on the midline), left/right_eye (socket centre),
        mouth_center (on the mouth crease), chin, forehead,
        left/right_cheek, left/right_brow, left/right_under_eye, upper/lower_lip, nose_bridge
        (the ridge halfway between the eye line and the nose tip).
    """
    if mesh is not None:
        meta = getattr(mesh, "metadata", {}).get("facegeo_head")
        if meta is None:
            raise InputError(
                "head_landmarks: the mesh has no metadata['facegeo_head'] (landmarks are known "
                "only for meshes from procedural_head)"
            )
        p = HeadParams.from_dict(meta["params"])
        verts = np.asarray(mesh.vertices, dtype=float)
        faces = np.asarray(mesh.faces, dtype=np.int64)
    else:
        p = params or HeadParams.from_seed(seed)
    ears = bool(meta["ears"]) if mesh is not None else ears
    xy = _landmark_xy(p)
    dirs = _direction_of_xy([v[0] for v in xy.values()], [v[1] for v in xy.values()], p)
    out = {}
    for name, w in zip(xy, dirs):
        if name == "nose_tip":
            w = _nose_tip_direction(p, ears)
        if mesh is not None:
            out[name] = _ray_hit_star_mesh(w, verts, faces)
        else:
            out[name] = float(head_radius(w, p, ears=ears)) * w
    return out


#: Landmarks of the default procedural head (``seed=None``) on its smooth surface.
HEAD_LANDMARKS: dict[str, np.ndarray] = head_landmarks()


# --------------------------------------------------------------------------- loading


def _parse_obj(path: Path):
    """Minimal OBJ reader: v, vt, f (any polygon, fan-triangulated), g/o/usemtl names.

    Returns positions (V, 3), texcoords (T, 2) or None, triangles (F, 3) of position indices,
    triangles (F, 3) of texcoord indices or None, and per-triangle labels (F,) str
    ("object|group|material").
    """
    text = path.read_text(errors="replace")
    v_list: list[str] = []
    vt_list: list[str] = []
    tri_v: list[tuple[int, int, int]] = []
    tri_t: list[tuple[int, int, int]] = []
    labels: list[str] = []
    obj = grp = mtl = ""
    has_t = True
    n_poly = 0
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line[0] == "#":
            continue
        tag, _, rest = line.partition(" ")
        if tag == "v":
            v_list.append(rest)
        elif tag == "vt":
            vt_list.append(rest)
        elif tag == "f":
            toks = rest.split()
            if len(toks) < 3:
                raise InputError(f"{path}:{lineno}: face with fewer than 3 vertices: {fmt_value(line)}")
            vi, ti = [], []
            for tok in toks:
                parts = tok.split("/")
                try:
                    a = int(parts[0])
                    vi.append(a - 1 if a > 0 else len(v_list) + a)
                    if len(parts) > 1 and parts[1]:
                        b = int(parts[1])
                        ti.append(b - 1 if b > 0 else len(vt_list) + b)
                except ValueError as exc:
                    raise InputError(f"{path}:{lineno}: bad face entry {fmt_value(tok)}") from exc
            if len(ti) != len(vi):
                has_t = False
            n_poly += 1
            label = f"{obj}|{grp}|{mtl}"
            for k in range(1, len(vi) - 1):  # fan triangulation (quads: 0-1-2, 0-2-3)
                tri_v.append((vi[0], vi[k], vi[k + 1]))
                tri_t.append((ti[0], ti[k], ti[k + 1]) if len(ti) == len(vi) else (0, 0, 0))
                labels.append(label)
        elif tag == "o":
            obj = rest.strip()
        elif tag == "g":
            grp = rest.strip()
        elif tag == "usemtl":
            mtl = rest.strip()
    if not v_list or not tri_v:
        raise InputError(f"{path}: not a triangle mesh (found {len(v_list)} vertices and "
                         f"{n_poly} faces)")
    V = np.array([s.split()[:3] for s in v_list], dtype=float)
    T = np.array([s.split()[:2] for s in vt_list], dtype=float) if vt_list else None
    Fv = np.array(tri_v, dtype=np.int64)
    if Fv.min() < 0 or Fv.max() >= len(V):
        raise InputError(f"{path}: face indices out of range (0..{len(V) - 1})")
    Ft = None
    if has_t and T is not None:
        Ft = np.array(tri_t, dtype=np.int64)
        if Ft.min() < 0 or Ft.max() >= len(T):
            raise InputError(f"{path}: texture-coordinate indices out of range (0..{len(T) - 1})")
    return V, T, Fv, Ft, np.array(labels, dtype=object)


def _mesh_from_obj(path: Path, drop_groups):
    import trimesh

    V, T, Fv, Ft, labels = _parse_obj(path)
    names = sorted(set(labels))
    dropped: list[str] = []
    if drop_groups:
        pats = [str(g).lower() for g in drop_groups]
        drop_label = {lab: any(pt in part.lower() for pt in pats for part in lab.split("|") if part)
                      for lab in names}
        dropped = [lab for lab in names if drop_label[lab]]
        keep = np.array([not drop_label[lab] for lab in labels], dtype=bool)
        Fv, labels = Fv[keep], labels[keep]
        Ft = None if Ft is None else Ft[keep]
        if len(Fv) == 0:
            raise InputError(f"{path}: drop_groups={tuple(drop_groups)} removes every face")
    if Ft is not None:
        # One output vertex per distinct (position, texcoord) pair: UV seams stay split, no
        # positions are merged; order follows the file's vertex order.
        pairs = np.stack([Fv.ravel(), Ft.ravel()], axis=1)
        uniq, inverse = np.unique(pairs, axis=0, return_inverse=True)
        faces = inverse.reshape(-1, 3)
        src = uniq[:, 0]
        vertices = V[src]
        visual = trimesh.visual.TextureVisuals(uv=T[uniq[:, 1]])
    else:
        src, inverse = np.unique(Fv.ravel(), return_inverse=True)
        faces = inverse.reshape(-1, 3)
        vertices = V[src]
        visual = None
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, visual=visual, process=False)
    mesh.metadata["source_vertex_index"] = src  # index into the file's `v` list
    mesh.metadata["n_source_vertices"] = len(V)
    mesh.metadata["face_labels"] = labels  # "object|group|material" per triangle
    mesh.metadata["groups"] = names
    mesh.metadata["dropped_groups"] = dropped
    return mesh


def load_head_mesh(path, *, units: str = "cm", center: bool = True,
                   drop_groups=DEFAULT_DROP_GROUPS):
    """Load a head mesh (OBJ, PLY, GLB/GLTF, …) as a triangle mesh in metres.

    OBJ files go through a small reader of our own, kept after measuring trimesh 5.2's
    ``load_obj`` as its replacement: trimesh names per-material pieces ``obj``, ``obj_1``, …
    when the ``.mtl`` file is absent (the ICT FaceKit OBJ ships without it), so overlay groups
    cannot be recognised and faces carry no group label; it cuts the surface apart at material
    boundaries; it resolves negative (relative) face indices from the end of the file rather
    than from the vertices read so far, as the OBJ format defines them; and it took 1.98 s
    against this reader's 1.03 s on the 2.5 MB ICT head. On the geometry both produce the two
    agree exactly (``tests/test_head.py::test_shared_obj_matches_trimesh``: the same multiset
    of triangles on both shared faces and on a hand-written OBJ). Ours keeps one vertex per distinct (position, texcoord) pair — UV seams split,
    nothing merged — fan-triangulates polygons (quads → 2 triangles) and records per-triangle
    ``"object|group|material"`` labels. Other formats load with ``trimesh.load(process=False)``
    (scenes concatenated).

    Parameters
    ----------
    path : str or Path
    units : {"cm", "mm", "m"}
        Units of the file; converted to metres.
    center : bool
        Translate so the bounding-box centre is at the origin. The shared real meshes are
        already +Y up and face +Z; no rotation is applied.
    drop_groups : sequence of str
        OBJ ``o``/``g``/``usemtl`` names to drop, matched case-insensitively as substrings
        (default :data:`DEFAULT_DROP_GROUPS`: the ICT FaceKit overlay materials). ``()`` keeps
        everything. Ignored for non-OBJ formats.

    Returns
    -------
    trimesh.Trimesh
        ``process=False``; UVs in ``visual.uv`` when the file has them. ``metadata`` holds
        ``units``, ``scale_to_m``, ``translation_m`` (added after scaling),
        ``source_vertex_index`` (output vertex → index into the file's vertex list),
        ``n_source_vertices``, ``landmark_indices`` and ``landmark_source`` (when the mesh's
        landmarks are known, see :func:`real_face_landmarks`) and, for OBJ, ``face_labels``,
        ``groups`` and ``dropped_groups``.

    Raises
    ------
    InputError
        Missing file, unknown units, not a triangle mesh, or every face dropped.
    """
    import trimesh

    path = Path(path)
    check_choice(units, "units", UNIT_SCALE)
    if not path.is_file():
        raise InputError(f"load_head_mesh: no such file {path}")
    if path.suffix.lower() == ".obj":
        mesh = _mesh_from_obj(path, drop_groups)
    else:
        try:
            loaded = trimesh.load(str(path), process=False)
        except Exception as exc:  # trimesh raises many types for unreadable files
            raise InputError(f"load_head_mesh: cannot read {path}: {exc}") from exc
        if isinstance(loaded, trimesh.Scene):
            geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
            if not geoms:
                raise InputError(f"{path}: not a triangle mesh (scene without triangle geometry)")
            mesh = geoms[0] if len(geoms) == 1 else trimesh.util.concatenate(geoms)
        elif isinstance(loaded, trimesh.Trimesh):
            mesh = loaded
        else:
            raise InputError(f"{path}: not a triangle mesh (loaded a {type(loaded).__name__})")
        if len(mesh.faces) == 0:
            raise InputError(f"{path}: not a triangle mesh (no faces)")
    if "source_vertex_index" not in mesh.metadata:  # trimesh keeps the file's order
        mesh.metadata["source_vertex_index"] = np.arange(len(mesh.vertices))
        mesh.metadata["n_source_vertices"] = len(mesh.vertices)
    scale = UNIT_SCALE[units]
    verts = np.asarray(mesh.vertices, dtype=float) * scale
    shift = np.zeros(3)
    if center:
        lo, hi = verts.min(axis=0), verts.max(axis=0)
        shift = -(lo + hi) / 2.0
        verts = verts + shift
    mesh.vertices = verts
    mesh.metadata.update({"units": units, "scale_to_m": scale, "translation_m": shift.tolist(),
                          "source_path": str(path)})
    found = _find_landmark_indices(path, int(mesh.metadata["n_source_vertices"]))
    if found is not None:
        mesh.metadata["landmark_indices"], mesh.metadata["landmark_source"] = found
    log.debug("loaded %s: %d vertices, %d faces, extent %s m", path, len(mesh.vertices),
              len(mesh.faces), np.ptp(verts, axis=0))
    return mesh


# --------------------------------------------------------------------------- real faces: landmarks

#: Landmarks every real face needs (``left``/``right`` are the subject's; left = +X), found
#: from published vertex indices or a ``HEAD.landmarks.json`` file beside the mesh.
CORE_LANDMARKS = (
    "nose_tip",
    "menton",  # lowest point of the chin on the face contour ("chin" in the 68-point scheme)
    "right_eye_outer",
    "right_eye_inner",
    "left_eye_inner",
    "left_eye_outer",
    "right_mouth_corner",
    "left_mouth_corner",
    "upper_lip",  # outer (vermilion) midpoint of the upper lip
    "lower_lip",  # outer midpoint of the lower lip
)

#: Positions of :data:`CORE_LANDMARKS` in the iBUG 300-W 68-point scheme (0-based: 8 chin,
#: 30 nose tip, 36/39 and 42/45 the eye corners on the image's left/right, i.e. the subject's
#: right/left eye, 48/54 mouth corners, 51/57 outer lip midpoints). The ICT FaceKit ships the
#: vertex of each of the 68 points as ``idx_to_landmark_verts`` in
#: ``ict_facekit_vertex_indices.json`` beside the mesh (github.com/ICT-VGL/ICT-FaceKit).
ICT_IBUG68_INDEX = {
    "nose_tip": 30, "menton": 8, "right_eye_outer": 36, "right_eye_inner": 39,
    "left_eye_inner": 42, "left_eye_outer": 45, "right_mouth_corner": 48,
    "left_mouth_corner": 54, "upper_lip": 51, "lower_lip": 57,
}

#: Vertex indices of :data:`CORE_LANDMARKS` on MediaPipe's 468-vertex canonical face mesh
#: (``canonical_face_model.obj`` / its UV visualisation ``canonical_face_model_uv_visualization.png``
#: in google/mediapipe, mediapipe/modules/face_geometry/data; the same numbering as the Face
#: Mesh landmarks): 1 nose tip, 152 chin, 33/133 right eye outer/inner corner, 362/263 left
#: eye inner/outer corner, 61/291 mouth corners, 0/17 upper/lower lip outer midpoints.
MEDIAPIPE_INDEX = {
    "nose_tip": 1, "menton": 152, "right_eye_outer": 33, "right_eye_inner": 133,
    "left_eye_inner": 362, "left_eye_outer": 263, "right_mouth_corner": 61,
    "left_mouth_corner": 291, "upper_lip": 0, "lower_lip": 17,
}

#: Vertex counts of MediaPipe's canonical face (468) and of its variant with irises (478).
MEDIAPIPE_VERTEX_COUNTS = (468, 478)
ICT_INDEX_FILE = "ict_facekit_vertex_indices.json"


def landmarks_file_for(path) -> Path:
    """``HEAD.landmarks.json`` beside a mesh ``HEAD.obj`` (any suffix)."""
    path = Path(path)
    return path.with_name(path.stem + ".landmarks.json")


def _read_landmarks_file(lm_path: Path, n_vertices: int) -> dict[str, int]:
    import json

    try:
        data = json.loads(lm_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{lm_path}: cannot read the landmarks file ({exc})") from exc
    idx = data.get("vertex_indices") if isinstance(data, dict) else None
    if not isinstance(idx, dict):
        raise InputError(f"{lm_path}: expected an object with \"vertex_indices\": "
                         f"{{NAME: index}}, names {list(CORE_LANDMARKS)}")
    missing = [k for k in CORE_LANDMARKS if k not in idx]
    if missing:
        raise InputError(f"{lm_path}: vertex_indices lacks {missing} (needs every one of "
                         f"{list(CORE_LANDMARKS)})")
    out = {}
    for k in CORE_LANDMARKS:
        v = idx[k]
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < n_vertices:
            raise InputError(f"{lm_path}: vertex_indices[{k!r}] = {fmt_value(v)}; expected a "
                             f"0-based index into the mesh file's {n_vertices} vertices")
        out[k] = v
    return out


def _find_landmark_indices(path: Path, n_vertices: int):
    """``(name → file vertex index, description)`` of a mesh's landmarks, or None.

    In order: ``HEAD.landmarks.json`` beside the mesh; the ICT FaceKit's
    ``ict_facekit_vertex_indices.json`` beside it (68-point landmark vertices); a mesh with
    MediaPipe's canonical vertex count (468 or 478).
    """
    import json

    lm = landmarks_file_for(path)
    if lm.is_file():
        return _read_landmarks_file(lm, n_vertices), str(lm)
    ict = path.with_name(ICT_INDEX_FILE)
    if ict.is_file():
        try:
            verts68 = json.loads(ict.read_text(encoding="utf-8"))["idx_to_landmark_verts"]
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as exc:
            raise InputError(f"{ict}: cannot read idx_to_landmark_verts ({exc})") from exc
        if len(verts68) != 68:
            raise InputError(f"{ict}: idx_to_landmark_verts has {len(verts68)} entries, expected 68")
        out = {k: int(verts68[i]) for k, i in ICT_IBUG68_INDEX.items()}
        if max(out.values()) < n_vertices:
            return out, f"{ict} (iBUG 68-point landmark vertices)"
        log.debug("%s does not fit %s (vertex index %d >= %d vertices); ignored", ict, path,
                  max(out.values()), n_vertices)
    if n_vertices in MEDIAPIPE_VERTEX_COUNTS:
        return dict(MEDIAPIPE_INDEX), "MediaPipe canonical face mesh vertex indices"
    return None


# --------------------------------------------------------------------------- real faces: parts

#: Mesh parts with their own material (index = label in ``ground_truth/parts.npz``).
PART_NAMES = ("skin", "sclera", "iris", "teeth", "mouth_interior")

#: Substrings of OBJ object/group/material names (lower case) that select a part, tried in
#: order; everything else is skin (the ICT FaceKit's ``M_Face`` and ``M_BackHead``).
_PART_PATTERNS = (
    ("iris", ("iris", "pupil", "cornea")),
    ("sclera", ("sclera", "eyeball", "eye")),
    ("teeth", ("teeth", "tooth")),
    ("mouth_interior", ("gum", "tongue", "mouth")),
)


def part_labels(mesh) -> np.ndarray:
    """Per-face part label ``(F,)`` int64 indexing :data:`PART_NAMES` (0 = skin).

    From the OBJ object/group/material names the loader keeps in ``metadata["face_labels"]``
    (the ICT FaceKit: ``M_ScleraLeft``/``Right`` → sclera, ``M_IrisLeft``/``Right`` → iris,
    ``M_Teeth`` → teeth, ``M_GumsTongue`` → mouth_interior). Meshes without names (the
    procedural head, PLY, the MediaPipe face) are all skin.
    """
    n = len(mesh.faces)
    names = getattr(mesh, "metadata", {}).get("face_labels")
    out = np.zeros(n, np.int64)
    if names is None or len(names) != n:
        return out
    uniq, inv = np.unique(np.asarray(names, dtype=str), return_inverse=True)
    lab = np.zeros(len(uniq), np.int64)
    for i, name in enumerate(uniq):
        low = name.lower()
        for part, pats in _PART_PATTERNS:
            if any(pt in low for pt in pats):
                lab[i] = PART_NAMES.index(part)
                break
    return lab[inv.reshape(-1)]


# --------------------------------------------------------------------------- real faces: frame

#: Where the face's derived landmarks sit, in units of the interocular distance (IOD, between
#: the eye centres) from the eye line / midline: the proportions of the procedural head
#: (:func:`_landmark_xy`, IOD = 2·eye_x = 64 mm), so a region placed on either head lands on
#: the same feature.
_DERIVED_IOD = {
    "forehead": (0.0, 0.78),  # 50 mm above the eye line
    "cheek": (0.69, -0.69),  # 44 mm out, 44 mm below
    "under_eye": (None, -0.33),  # below each eye centre
}
#: The chin (mental protuberance) this far from the lower lip toward the menton.
_CHIN_FRACTION = 0.5
#: The face box spans the eye line + this many IODs (the hairline) down to the menton, and
#: ± this many IODs about the midline (cheek to cheek).
_FACE_TOP_IOD = 1.0
_FACE_HALF_WIDTH_IOD = 1.1


def _front_hits(mesh, skin_faces: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """First skin surface point seen looking along −Z at each ``(x, y)`` (N, 3); NaN on a miss."""
    from facegeo.surface.visibility import RayScene

    v = np.asarray(mesh.vertices, dtype=float)
    f = np.asarray(mesh.faces, dtype=np.int64)[skin_faces]
    scene = RayScene(v, f)
    z0 = v[:, 2].max() + 0.1
    o = np.column_stack([xy, np.full(len(xy), z0)])
    d = np.broadcast_to([0.0, 0.0, -1.0], o.shape)
    hits = scene.closest_hit(o, d, t_min=0.0, fields=("point",))
    return np.where(hits.hit[:, None], hits.point, np.nan)


def real_face_landmarks(mesh) -> dict[str, np.ndarray] | None:
    """Facial landmarks of a loaded real face, metres, in the mesh's current frame.

    The :data:`CORE_LANDMARKS` are mesh vertices (``metadata["landmark_indices"]``, set by
    :func:`load_head_mesh`). Derived from them: ``left_eye``/``right_eye`` (midpoint of each
    eye's corners), ``mouth_center``, ``forehead``, ``left/right_cheek``,
    ``left/right_under_eye``, ``nose_bridge`` and ``chin`` — the skin point seen from the front (−Z ray, skin
    faces only) at a position set by the eyes and mouth in the procedural head's proportions
    (:data:`_DERIVED_IOD`), so these carry the names of :func:`head_landmarks`.

    Returns
    -------
    dict of str → (3,) float64, or None when the mesh has no known landmarks.

    Raises
    ------
    InputError
        A landmark vertex is not used by any face, or a derived point misses the skin.
    """
    meta = getattr(mesh, "metadata", {})
    idx = meta.get("landmark_indices")
    if idx is None:
        return None
    src = np.asarray(meta["source_vertex_index"])
    v = np.asarray(mesh.vertices, dtype=float)
    first = {}
    order = np.argsort(src, kind="stable")
    pos = np.searchsorted(src[order], [idx[k] for k in CORE_LANDMARKS])
    out: dict[str, np.ndarray] = {}
    for k, p_ in zip(CORE_LANDMARKS, pos):
        if p_ >= len(src) or src[order[p_]] != idx[k]:
            raise InputError(f"{meta.get('landmark_source')}: landmark {k!r} is file vertex "
                             f"{idx[k]}, which no face of {meta.get('source_path')} uses")
        first[k] = order[p_]
        out[k] = v[first[k]].copy()
    eye_r = 0.5 * (out["right_eye_outer"] + out["right_eye_inner"])
    eye_l = 0.5 * (out["left_eye_outer"] + out["left_eye_inner"])
    out["right_eye"], out["left_eye"] = eye_r, eye_l
    iod = float(np.linalg.norm(eye_l - eye_r))
    x_mid = 0.5 * (eye_l[0] + eye_r[0])
    y_eye = 0.5 * (eye_l[1] + eye_r[1])
    mouth = 0.5 * (out["upper_lip"] + out["lower_lip"])
    fx, fy = _DERIVED_IOD["forehead"]
    cx, cy = _DERIVED_IOD["cheek"]
    uy = _DERIVED_IOD["under_eye"][1]
    chin_y = out["lower_lip"][1] + _CHIN_FRACTION * (out["menton"][1] - out["lower_lip"][1])
    want = {
        "mouth_center": (mouth[0], mouth[1]),
        "forehead": (x_mid + fx * iod, y_eye + fy * iod),
        "left_cheek": (x_mid + cx * iod, y_eye + cy * iod),
        "right_cheek": (x_mid - cx * iod, y_eye + cy * iod),
        "left_under_eye": (eye_l[0], y_eye + uy * iod),
        "right_under_eye": (eye_r[0], y_eye + uy * iod),
        "chin": (x_mid, chin_y),
        "nose_bridge": (out["nose_tip"][0], 0.5 * (y_eye + out["nose_tip"][1])),
    }
    skin = part_labels(mesh) == 0
    pts = _front_hits(mesh, skin, np.array(list(want.values()), dtype=float))
    for (k, _), p_ in zip(want.items(), pts):
        if not np.all(np.isfinite(p_)):
            raise InputError(f"{meta.get('source_path')}: derived landmark {k!r} misses the skin "
                             "seen from the front (is the face toward +Z and +Y up?)")
        out[k] = p_
    return out


def face_box(landmarks: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box ``(lo, hi)`` (3,) of the face, metres: cheek to cheek
    (± :data:`_FACE_HALF_WIDTH_IOD` IOD), menton to hairline (eye line +
    :data:`_FACE_TOP_IOD` IOD), and in depth from the eye centres to the nose tip."""
    eye_l, eye_r = landmarks["left_eye"], landmarks["right_eye"]
    iod = float(np.linalg.norm(eye_l - eye_r))
    mid = 0.5 * (eye_l + eye_r)
    lo = np.array([mid[0] - _FACE_HALF_WIDTH_IOD * iod, landmarks["menton"][1],
                   min(eye_l[2], eye_r[2])])
    hi = np.array([mid[0] + _FACE_HALF_WIDTH_IOD * iod, mid[1] + _FACE_TOP_IOD * iod,
                   landmarks["nose_tip"][2]])
    return lo, hi


def frame_face(mesh, landmarks: dict[str, np.ndarray]) -> np.ndarray:
    """Translate a real face so that the rig, aimed at the origin, frames the face.

    The face box's (:func:`face_box`) centre goes to x = y = 0 and the nose tip to the
    procedural head's nose-tip depth (``HEAD_LANDMARKS["nose_tip"][2]``, so a real head sits
    in the light stage where the procedural one does, instead of its bounding box — neck
    included — being centred). Updates ``mesh.vertices``, ``metadata["translation_m"]``
    (cumulative, after scaling) and the ``landmarks`` in place.

    Returns
    -------
    (3,) float64, metres: the translation added.
    """
    lo, hi = face_box(landmarks)
    centre = 0.5 * (lo + hi)
    shift = np.array([-centre[0], -centre[1],
                      float(HEAD_LANDMARKS["nose_tip"][2]) - landmarks["nose_tip"][2]])
    mesh.vertices = np.asarray(mesh.vertices, dtype=float) + shift
    meta = mesh.metadata
    meta["translation_m"] = (np.asarray(meta.get("translation_m", np.zeros(3))) + shift).tolist()
    for k in landmarks:
        landmarks[k] = landmarks[k] + shift
    return shift
