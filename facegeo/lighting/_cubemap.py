"""Cube-map environments (private; the public names are re-exported by
:mod:`facegeo.lighting.envmap`): the face layouts, OpenGL's face-coordinate rule in facegeo's
world frame, exact texel solid angles and a bilinear lookup across face seams.
``docs/lighting.md`` (*Cube maps*) describes the layouts with a picture."""

from __future__ import annotations

import numpy as np

from facegeo.errors import ShapeError

#: Cube-map layouts: name → (columns, rows) of face cells and the cell ``(column, row)`` of
#: each face, the faces named as OpenGL names them (:data:`CUBE_FACES`). ``"cross"``: the
#: horizontal cross (4:3); ``"strip"``: the horizontal strip (6:1) in OpenGL's face order.
CUBE_LAYOUTS = {
    "cross": ((4, 3), {"+Y": (1, 0), "-X": (0, 1), "+Z": (1, 1), "+X": (2, 1), "-Z": (3, 1),
                       "-Y": (1, 2)}),
    "strip": ((6, 1), {"+X": (0, 0), "-X": (1, 0), "+Y": (2, 0), "-Y": (3, 0), "+Z": (4, 0),
                       "-Z": (5, 0)}),
}

#: Cube faces in OpenGL's order, with the face-coordinate rule of the OpenGL 4.6 core spec
#: §8.13, Table 8.19 in the cube-map frame ``r``: (major axis, its sign, s_c axis, sign,
#: t_c axis, sign); ``s = (s_c/|m_a| + 1)/2`` runs along the face's columns, ``t`` down its
#: rows. The cube-map frame is left-handed (RenderMan's); facegeo's world maps to it by
#: ``r = (−x, y, z)``, so every face is the unmirrored view from the cube's centre, +Z is the
#: front face and OpenGL's "+X" face is facegeo's −X (and "−X" is +X).
CUBE_FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
_CUBE_RULE = np.array([
    (0, +1, 2, -1, 1, -1),  # +X: s_c = −r_z, t_c = −r_y
    (0, -1, 2, +1, 1, -1),  # −X: s_c = +r_z, t_c = −r_y
    (1, +1, 0, +1, 2, +1),  # +Y: s_c = +r_x, t_c = +r_z
    (1, -1, 0, +1, 2, -1),  # −Y: s_c = +r_x, t_c = −r_z
    (2, +1, 0, +1, 1, -1),  # +Z: s_c = +r_x, t_c = −r_y
    (2, -1, 0, -1, 1, -1),  # −Z: s_c = −r_x, t_c = −r_y
])
_WORLD_TO_CUBE = np.array([-1.0, 1.0, 1.0])  # r = ω ⊙ this (and back: ω = r ⊙ this)


def cube_layout(height: int, width: int) -> str:
    """The cube-map layout (:data:`CUBE_LAYOUTS`) of an image of this size: ``"cross"`` for
    4:3 (face ``H/3``), ``"strip"`` for 6:1 (face ``H``); ShapeError otherwise."""
    h, w = int(height), int(width)
    if h % 3 == 0 and 3 * w == 4 * h:
        return "cross"
    if w == 6 * h:
        return "strip"
    raise ShapeError(f"a cube environment map must be a horizontal cross (4:3, height a "
                     f"multiple of 3) or a horizontal strip (6:1), got {w} × {h}")


def cube_geometry(height: int, width: int) -> tuple[int, np.ndarray]:
    """Face size ``a`` (pixels) and the ``(rows, columns)`` table of face indices of the
    layout's cells (−1: an empty cell of the cross)."""
    (nc, nr), cells = CUBE_LAYOUTS[cube_layout(height, width)]
    table = np.full((nr, nc), -1, np.int64)
    for name, (c, r) in cells.items():
        table[r, c] = CUBE_FACES.index(name)
    return int(height) // nr, table


def cube_face_origin(height: int, width: int) -> np.ndarray:
    """``(6, 2)`` cell ``(column, row)`` of every face in the layout."""
    _, cells = CUBE_LAYOUTS[cube_layout(height, width)]
    return np.array([cells[f] for f in CUBE_FACES], np.int64)


def cube_dir(face: np.ndarray, sc: np.ndarray, tc: np.ndarray) -> np.ndarray:
    """World directions (not unit) of face coordinates ``s_c, t_c ∈ [−1, 1]`` (may reach
    beyond, onto the face's plane) of ``face`` (indices into :data:`CUBE_FACES`)."""
    rule = _CUBE_RULE[face]
    r = np.zeros(face.shape + (3,))
    idx = np.arange(face.size).reshape(face.shape)
    flat = r.reshape(-1, 3)
    flat[idx.ravel(), rule[..., 0].ravel()] = rule[..., 1].ravel()
    flat[idx.ravel(), rule[..., 2].ravel()] = (sc * rule[..., 3]).ravel()
    flat[idx.ravel(), rule[..., 4].ravel()] = (tc * rule[..., 5]).ravel()
    return r * _WORLD_TO_CUBE


def cube_face_coords(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Face index and face coordinates ``s_c/|m_a|, t_c/|m_a| ∈ [−1, 1]`` of world
    directions ``(..., 3)`` (OpenGL's rule, :data:`CUBE_FACES`)."""
    r = v * _WORLD_TO_CUBE
    axis = np.argmax(np.abs(r), axis=-1)
    ma = np.take_along_axis(r, axis[..., None], -1)[..., 0]
    face = 2 * axis + (ma < 0)
    rule = _CUBE_RULE[face]
    with np.errstate(invalid="ignore", divide="ignore"):
        sc = np.take_along_axis(r, rule[..., 2:3], -1)[..., 0] * rule[..., 3] / np.abs(ma)
        tc = np.take_along_axis(r, rule[..., 4:5], -1)[..., 0] * rule[..., 5] / np.abs(ma)
    return face, sc, tc


def cube_texel_solid_angles(n: int) -> np.ndarray:
    """Exact solid angles ``(n, n)`` of the texels of one cube face split ``n × n``:
    ``Ω = A(x₀, y₀) − A(x₀, y₁) − A(x₁, y₀) + A(x₁, y₁)`` with
    ``A(x, y) = atan2(x·y, √(x² + y² + 1))`` over the texel's corners in face coordinates
    ``[−1, 1]`` — the integral of ``(1 + x² + y²)^(−3/2)`` over the texel (Driscoll, "Cubemap
    texel solid angle", 2012; AMD CubeMapGen's ``TexelCoordSolidAngle``). Six faces sum to 4π
    exactly (up to rounding)."""
    e = 2.0 * np.arange(n + 1) / n - 1.0
    x, y = np.meshgrid(e, e, indexing="xy")
    a = np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))
    return a[:-1, :-1] - a[1:, :-1] - a[:-1, 1:] + a[1:, 1:]


def cube_bilinear(img: np.ndarray, v_map: np.ndarray) -> np.ndarray:
    """Bilinear lookup ``(..., 3)`` float32 of a cube map across face seams: the four taps
    around a direction's face coordinates; a tap beyond the face's edge takes the texel of the
    neighbouring face that its point on the extended face plane projects into (at a cube
    corner, where three faces meet, the nearest of them)."""
    h, w = img.shape[:2]
    a, _ = cube_geometry(h, w)
    origin = cube_face_origin(h, w)
    face, sc, tc = cube_face_coords(v_map)
    x = (sc + 1.0) / 2.0 * a - 0.5
    y = (tc + 1.0) / 2.0 * a - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    out = np.zeros(face.shape + (3,))
    for dx, dy, wt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                       (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        tx, ty = x0 + dx, y0 + dy
        inside = (tx >= 0) & (tx < a) & (ty >= 0) & (ty < a)
        f2 = face.copy()
        if not inside.all():  # taps beyond an edge: onto the neighbouring face
            d = cube_dir(face, 2.0 * (tx + 0.5) / a - 1.0, 2.0 * (ty + 0.5) / a - 1.0)
            f_o, sc_o, tc_o = cube_face_coords(d[~inside])
            f2[~inside] = f_o
            tx = tx.copy()
            ty = ty.copy()
            tx[~inside] = np.floor((sc_o + 1.0) / 2.0 * a)
            ty[~inside] = np.floor((tc_o + 1.0) / 2.0 * a)
        tx = np.clip(tx, 0, a - 1).astype(np.int64)
        ty = np.clip(ty, 0, a - 1).astype(np.int64)
        o = origin[f2]
        out += img[o[..., 1] * a + ty, o[..., 0] * a + tx] * wt
    return out.astype(np.float32)
