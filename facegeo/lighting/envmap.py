"""Environment maps: reading, projections ↔ world directions, rotation, and projection onto a
light basis (Debevec et al. 2000 §3.3, Eq. 4).

Conventions (written out in ``docs/lighting.md``, with a picture): facegeo's world frame (+Y
up, the subject looks along +Z). The lat-long (in facegeo's convention), mirror-ball and angular
projections put **+Z at the image centre** and +Y at the top:

* ``"latlong"`` — OpenEXR's ``Imf::LatLongMap`` orientation: longitude
  ``atan2(x, z)`` runs from +π at the left edge through 0 (+Z) at the centre column to −π at
  the right edge (so +X is the left quarter, −X the right quarter), latitude +π/2 (+Y) at the
  top. In facegeo's light-grid angles: ``θ = (π − 2π u) mod 2π``, ``φ = π v`` with
  ``u = (x + ½)/W``, ``v = (y + ½)/H``. Deviation: OpenEXR maps the *centres* of the first and
  last columns to ±π; facegeo treats a pixel as an area, so the left *edge* of column 0 is +π
  (the usual convention for HDRI files; the difference is half a pixel).
* ``"mirror-ball"`` (alias ``"mirrorball"``) — a mirrored sphere photographed from +Z
  (orthographic): disc coordinates
  ``(a, b) ∈ [−1, 1]²`` (a right, b up, r² = a² + b² ≤ 1) give the reflected direction
  ``ω = (2a√(1−r²), 2b√(1−r²), 1 − 2r²)``: centre +Z (toward the camera), rim −Z.
* ``"angular"`` — Debevec's angular map: ``(a, b) = (ω_x, ω_y)·arccos(ω_z)/(π·√(ω_x²+ω_y²))``:
  the distance from the centre is proportional to the angle from +Z.
* ``"cube"`` — six 90° faces in a horizontal cross (4:3) or a horizontal strip (6:1), OpenGL's
  cube-map rule with facegeo's world mapped to its left-handed frame by ``r = (−x, y, z)``
  (:data:`CUBE_LAYOUTS`, :data:`CUBE_FACES`); exact texel solid angles; bilinear across seams.

Lat-long files in other orientations read with ``convention`` (:data:`LATLONG_CONVENTIONS`:
``"u0_at_plus_z"``, ``"blender"``).

Rotation ``rotation`` (radians) turns the environment about +Y by the right-hand rule (a feature
at +Z moves toward +X): ``L_rot(ω) = L(R_y(−α) ω)``.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.checks import as_array, check_choice, fmt_value
from facegeo.errors import InputError, ShapeError
from facegeo.frames import direction_angles, light_solid_angles
from facegeo.lighting._cubemap import (CUBE_FACES, CUBE_LAYOUTS, cube_bilinear, cube_dir,
                                       cube_face_coords, cube_face_origin, cube_geometry,
                                       cube_layout, cube_texel_solid_angles)

log = logging.getLogger(__name__)

__all__ = [
    "PROJECTIONS", "PROJECTION_ALIASES", "LATLONG_CONVENTIONS", "CUBE_LAYOUTS", "CUBE_FACES",
    "canonical_projection", "check_convention", "cube_layout", "NEGATIVE_CLIP_TOLERANCE",
    "EnvironmentMap", "read_envmap", "axis_lobe_map",
    "analytic_map", "pixel_directions", "pixel_solid_angles", "directions_to_pixels",
    "rotation_y", "light_stage_radiance", "light_stage_weights", "direction_weights",
    "light_weights", "field_weights",
    "SHIPPED_MAPS", "procedural_map", "shipped_map", "shipped_map_path", "write_shipped_maps",
]

#: The supported projections (canonical names; :data:`PROJECTION_ALIASES` are accepted too).
PROJECTIONS = ("latlong", "mirror-ball", "angular", "cube")

#: Other spellings accepted for a projection → its canonical name (what metrics record).
PROJECTION_ALIASES = {"mirrorball": "mirror-ball"}

#: Lat-long conventions: name → ``(s, c)`` with ``u_file = (s · u_facegeo + c) mod 1`` (rows
#: are the same in all: +Y at the top). ``"facegeo"``: +Z at the centre column, +X the left
#: quarter (OpenEXR ``Imf::LatLongMap``; Mitsuba's ``envmap``, ``u = atan2(x, −z)/2π``).
#: ``"u0_at_plus_z"``: ``u = θ/2π`` with θ the light grid's azimuth (+Z at the left edge, +X
#: the left quarter, −Z the centre, −X the right quarter — the columns of the paper's
#: reflectance-function images; the front–back mirror image of ``"facegeo"``).
#: ``"blender"``: +X at the centre, +Z the right quarter — Blender's equirectangular
#: environment texture (``u = ½ − atan2(y, x)/2π`` in its Z-up world, mapped to facegeo's by
#: glTF's axes ``(x, z, −y)``) and three.js's ``equirectUv`` (``u = atan2(z, x)/2π + ½``);
#: a 90° rotation of ``"facegeo"``. ``docs/lighting.md`` has the picture.
LATLONG_CONVENTIONS = {"facegeo": (1, 0.0), "u0_at_plus_z": (-1, 0.5), "blender": (1, 0.25)}

#: Negative values down to ``−NEGATIVE_CLIP_TOLERANCE × max(1, 99th percentile)`` are clipped
#: to 0 with a logged note (filtered or compressed HDR files carry small ringing negatives; the
#: shared maps go down to −0.004); anything more negative is an error.
NEGATIVE_CLIP_TOLERANCE = 0.01

_ASPECT = {"latlong": 2.0, "mirror-ball": 1.0, "angular": 1.0}


def rotation_y(angle: float) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` float64 about +Y by ``angle`` radians (right-hand rule:
    +Z turns toward +X)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


# --------------------------------------------------------------------------- projections


def canonical_projection(projection: str) -> str:
    """The canonical name of a projection (``"mirrorball"`` → ``"mirror-ball"``); InputError
    listing the valid names for an unknown one."""
    p = projection
    if isinstance(p, str):
        p = PROJECTION_ALIASES.get(p, p)
    return check_choice(p, "projection", PROJECTIONS)


_check_projection = canonical_projection


def check_convention(convention: str, projection: str = "latlong") -> str:
    """``convention`` if it names a lat-long convention (:data:`LATLONG_CONVENTIONS`) usable
    with ``projection`` (a non-default one applies to lat-long maps only); else InputError."""
    check_choice(convention, "convention", LATLONG_CONVENTIONS)
    if convention != "facegeo" and canonical_projection(projection) != "latlong":
        raise InputError(f"convention: {fmt_value(convention)} is a lat-long convention; a "
                         f"{canonical_projection(projection)} map takes convention='facegeo' "
                         f"(its layout is fixed, docs/lighting.md)")
    return convention


def _pixel_uv(h: int, w: int, s: int) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel sample centres ``u = (x + (k + ½)/s)/W`` (columns) and ``v`` (rows)."""
    u = (np.arange(w * s) + 0.5) / (w * s)
    v = (np.arange(h * s) + 0.5) / (h * s)
    return u, v


def _disc_ab(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Disc coordinates (a right, b up) ∈ [−1, 1] of image coordinates u, v ∈ [0, 1]."""
    return 2.0 * u - 1.0, 1.0 - 2.0 * v


def pixel_directions(projection: str, height: int, width: int, *, supersample: int = 1,
                     convention: str = "facegeo") -> tuple[np.ndarray, np.ndarray]:
    """World directions of the (sub-)pixel centres of an environment map.

    Parameters
    ----------
    projection : {"latlong", "mirror-ball", "angular", "cube"} (or an alias,
        :data:`PROJECTION_ALIASES`)
    height, width : int
        Map size in pixels (a cube map's layout follows from it, :func:`cube_layout`).
    supersample : int
        ``s``: each pixel is split into ``s × s`` equal sub-pixels.
    convention : str
        Lat-long convention (:data:`LATLONG_CONVENTIONS`); other projections take "facegeo".

    Returns
    -------
    v_world : (H·s, W·s, 3) float64, unit directions toward the environment, world frame
        NaN outside the disc of a mirror-ball or angular map and in a cross's empty cells.
    valid : (H·s, W·s) bool
        False there.
    """
    projection = _check_projection(projection)
    check_convention(convention, projection)
    u, v = _pixel_uv(int(height), int(width), int(supersample))
    if projection == "latlong":
        sgn, c = LATLONG_CONVENTIONS[convention]
        theta = np.pi - 2.0 * np.pi * (sgn * (u - c))  # u_facegeo = s·(u_file − c)
        phi = np.pi * v
        st, ct = np.sin(theta), np.cos(theta)
        sp, cp = np.sin(phi), np.cos(phi)
        d = np.stack([sp[:, None] * st[None, :], np.broadcast_to(cp[:, None], (v.size, u.size)),
                      sp[:, None] * ct[None, :]], axis=-1)
        return d, np.ones(d.shape[:2], bool)
    if projection == "cube":
        _, table = cube_geometry(height, width)
        nr, nc = table.shape
        gx, gy = u * nc, v * nr  # in face cells
        col, row = np.floor(gx).astype(np.int64), np.floor(gy).astype(np.int64)
        face = table[row[:, None], col[None, :]]
        valid = face >= 0
        sc = np.broadcast_to(2.0 * (gx - col) - 1.0, face.shape)
        tc = np.broadcast_to((2.0 * (gy - row) - 1.0)[:, None], face.shape)
        d = cube_dir(np.where(valid, face, 0), sc, tc)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        d[~valid] = np.nan
        return d, valid
    a, b = _disc_ab(u[None, :], v[:, None])
    r2 = a * a + b * b
    valid = r2 <= 1.0
    r2c = np.minimum(r2, 1.0)
    if projection == "mirror-ball":
        k = 2.0 * np.sqrt(1.0 - r2c)
        d = np.stack([k * a, k * b, 1.0 - 2.0 * r2c], axis=-1)
    else:  # angular
        r = np.sqrt(r2c)
        gamma = np.pi * r
        with np.errstate(invalid="ignore", divide="ignore"):
            sinc = np.where(r > 0, np.sin(gamma) / np.where(r > 0, r, 1.0), np.pi)
        d = np.stack([sinc * a, sinc * b, np.cos(gamma)], axis=-1)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    d[~valid] = np.nan
    return d, valid


def pixel_solid_angles(projection: str, height: int, width: int, *, supersample: int = 1
                       ) -> np.ndarray:
    """Solid angle of every (sub-)pixel, ``(H·s, W·s)`` float64, steradians (0 outside the disc
    and in a cross's empty cells).

    Lat-long: exact, ``(2π/(W·s))(cos φ⁻ − cos φ⁺)`` (the same in every lat-long convention).
    Mirror ball: ``4 ΔA`` (the mirror ball's Jacobian is constant on the unit disc). Angular
    map: ``π sin(π r)/r · ΔA`` at the sub-pixel centre. ``ΔA = (2/(W·s))(2/(H·s))`` is the
    sub-pixel area in disc units. Cube: exact (:func:`cube_texel_solid_angles`). Over a whole
    map the sum is 4π up to the disc's rim (exactly for lat-long and cube).
    """
    projection = _check_projection(projection)
    h, w, s = int(height) * int(supersample), int(width) * int(supersample), int(supersample)
    if projection == "latlong":
        edges = np.pi * np.arange(h + 1) / h
        rows = (2.0 * np.pi / w) * (np.cos(edges[:-1]) - np.cos(edges[1:]))
        return np.repeat(rows[:, None], w, axis=1)
    if projection == "cube":
        a, table = cube_geometry(height, width)
        face = cube_texel_solid_angles(a * s)
        return np.kron(table >= 0, np.ones((a * s, a * s))) * np.tile(face, table.shape)
    u, v = _pixel_uv(h // s, w // s, s)
    a, b = _disc_ab(u[None, :], v[:, None])
    r = np.sqrt(a * a + b * b)
    dA = (2.0 / w) * (2.0 / h)
    if projection == "mirror-ball":
        jac = np.full(r.shape, 4.0)
    else:
        with np.errstate(invalid="ignore", divide="ignore"):
            rs = np.where(r > 0, r, 1.0)
            jac = np.where(r > 0, np.pi * np.sin(np.pi * np.minimum(r, 1.0)) / rs, np.pi * np.pi)
    return np.where(r <= 1.0, jac * dA, 0.0)


def directions_to_pixels(projection: str, v_world: Any, height: int, width: int, *,
                         convention: str = "facegeo") -> np.ndarray:
    """Continuous pixel coordinates ``(..., 2)`` = (x, y) of world directions (pixel centres are
    integers, :doc:`conventions`); the inverse of :func:`pixel_directions`.

    Parameters
    ----------
    projection : {"latlong", "mirror-ball", "angular", "cube"}
    v_world : (..., 3) float, directions (need not be unit), world frame
    height, width : int
    convention : str
        Lat-long convention (:data:`LATLONG_CONVENTIONS`).
    """
    projection = _check_projection(projection)
    check_convention(convention, projection)
    v = as_array(v_world, "v_world", shape=(..., 3))
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    if projection == "latlong":
        theta, phi = direction_angles(v)
        u = np.mod(np.pi - theta, 2.0 * np.pi) / (2.0 * np.pi)
        sgn, c = LATLONG_CONVENTIONS[convention]
        u = np.mod(sgn * u + c, 1.0)
        vv = phi / np.pi
    elif projection == "cube":
        a, _ = cube_geometry(height, width)
        face, sc, tc = cube_face_coords(v)
        origin = cube_face_origin(height, width)[face]
        x = (origin[..., 0] + (sc + 1.0) / 2.0) * a - 0.5
        y = (origin[..., 1] + (tc + 1.0) / 2.0) * a - 0.5
        return np.stack([x, y], axis=-1)
    else:
        rxy = np.hypot(v[..., 0], v[..., 1])
        if projection == "mirror-ball":
            # ω_z = 1 − 2r² → r = √((1 − ω_z)/2); (a, b) along (ω_x, ω_y)
            r = np.sqrt(np.clip((1.0 - v[..., 2]) / 2.0, 0.0, 1.0))
        else:
            r = np.arccos(np.clip(v[..., 2], -1.0, 1.0)) / np.pi
        with np.errstate(invalid="ignore", divide="ignore"):
            k = np.where(rxy > 0, r / np.where(rxy > 0, rxy, 1.0), 0.0)
        a, b = k * v[..., 0], k * v[..., 1]
        u, vv = (a + 1.0) / 2.0, (1.0 - b) / 2.0
    return np.stack([u * width - 0.5, vv * height - 0.5], axis=-1)


# --------------------------------------------------------------------------- the map object


@dataclass(frozen=True)
class EnvironmentMap:
    """An environment of incident radiance ``L(ω)``.

    Attributes
    ----------
    image : (H, W, 3) float32, linear radiance (W/(sr·m²) up to a global scale)
        Finite and ≥ 0 (validated).
    projection : {"latlong", "mirror-ball", "angular", "cube"}
        Stored canonical (an alias such as ``"mirrorball"`` is accepted).
    rotation : float, radians
        Rotation about +Y applied on lookup (right-hand rule).
    source : str
        Where the map came from (file name), for messages.
    convention : str
        Lat-long convention of the image (:data:`LATLONG_CONVENTIONS`; "facegeo" otherwise).
    """

    image: np.ndarray
    projection: str = "latlong"
    rotation: float = 0.0
    source: str = "<array>"
    convention: str = "facegeo"
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "projection", _check_projection(self.projection))
        check_convention(self.convention, self.projection)
        img = _validate_image(self.image, self.projection, self.source)
        object.__setattr__(self, "image", img)
        rot = float(self.rotation)
        if not math.isfinite(rot):
            raise InputError(f"rotation: expected a finite angle in radians, got {fmt_value(self.rotation)}")
        object.__setattr__(self, "rotation", rot)

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    def rotated(self, angle: float) -> EnvironmentMap:
        """The same map turned by a further ``angle`` radians about +Y."""
        return EnvironmentMap(self.image, self.projection, self.rotation + float(angle),
                              self.source, self.convention)

    def radiance(self, v_world: Any) -> np.ndarray:
        """Radiance ``(..., 3)`` float32 toward directions ``(..., 3)`` (world frame), bilinear
        (lat-long wraps in longitude; disc maps clamp to the image; a cube map reads across
        its face seams, :func:`cube_bilinear`)."""
        v = as_array(v_world, "v_world", shape=(..., 3))
        v_map = v @ rotation_y(self.rotation)  # R_y(−α) ω as row vectors: ω · R_y(α)
        if self.projection == "cube":
            return cube_bilinear(self.image, v_map)
        q = directions_to_pixels(self.projection, v_map, self.height, self.width,
                                 convention=self.convention)
        return _bilinear(self.image, q, wrap_x=self.projection == "latlong")

    def integral(self) -> np.ndarray:
        """``∫ L(ω) dω`` over the sphere, ``(3,)`` float64 (pixel-area quadrature)."""
        om = pixel_solid_angles(self.projection, self.height, self.width)
        return np.einsum("hw,hwc->c", om, self.image.astype(np.float64))


def _bilinear(img: np.ndarray, q: np.ndarray, *, wrap_x: bool) -> np.ndarray:
    h, w = img.shape[:2]
    x, y = q[..., 0], q[..., 1]
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    x1 = x0 + 1
    y1 = np.clip(y0 + 1, 0, h - 1)
    y0 = np.clip(y0, 0, h - 1)
    if wrap_x:
        x0, x1 = np.mod(x0, w), np.mod(x1, w)
    else:
        x0, x1 = np.clip(x0, 0, w - 1), np.clip(x1, 0, w - 1)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return (top * (1 - fy) + bot * fy).astype(np.float32)


def _validate_image(img: Any, projection: str, source: str) -> np.ndarray:
    """Shape, aspect, finiteness and sign checks; clip small negatives with a logged note."""
    projection = _check_projection(projection)
    a = np.asarray(img)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if a.ndim != 3 or a.shape[-1] not in (3, 4) or min(a.shape[:2]) < 2:
        raise ShapeError(f"{source}: expected an environment image of shape (H, W, 3), "
                         f"got {tuple(a.shape)}")
    if a.dtype.kind not in "fiu":
        raise ShapeError(f"{source}: expected a numeric image, got dtype {a.dtype}")
    a = np.ascontiguousarray(a[..., :3], dtype=np.float32)
    h, w = a.shape[:2]
    if projection == "cube":
        try:
            cube_layout(h, w)
        except ShapeError as exc:
            raise ShapeError(f"{source}: {exc}; pass the right projection (one of "
                             f"{', '.join(PROJECTIONS)})") from None
    elif abs(w / h - (want := _ASPECT[projection])) > 0.02 * want:
        raise ShapeError(
            f"{source}: a {projection} environment map must be {int(want)}:1 (width:height), "
            f"got {w} × {h}; pass the right projection (one of {', '.join(PROJECTIONS)})"
        )
    ok = np.isfinite(a)
    if not ok.all():
        bad = np.argwhere(~ok)[0]
        raise InputError(f"{source}: {int((~ok).sum())} NaN/inf value(s) in the environment map "
                         f"(first at row {bad[0]}, column {bad[1]}); fix or re-export the map")
    lo = float(a.min())
    if lo < 0:
        scale = max(1.0, float(np.percentile(a, 99)))
        if lo < -NEGATIVE_CLIP_TOLERANCE * scale:
            bad = np.argwhere(a == lo)[0]
            raise InputError(
                f"{source}: negative radiance {lo:.4g} at row {bad[0]}, column {bad[1]} (allowed "
                f"down to {-NEGATIVE_CLIP_TOLERANCE * scale:.3g}); an environment map holds "
                f"radiance, which is never negative"
            )
        n = int((a < 0).sum())
        log.info("%s: clipped %d small negative value(s) (min %.3g) to 0", source, n, lo)
        a = np.maximum(a, 0.0)
    return a


def read_envmap(path: str | os.PathLike, projection: str = "latlong", *,
                rotate_deg: float = 0.0, response: Any = None,
                convention: str = "facegeo") -> EnvironmentMap:
    """Read an environment map file.

    Parameters
    ----------
    path : path-like
        ``.exr`` or ``.hdr`` (linear float), or an 8/16-bit image with ``response``.
    projection : {"latlong", "mirror-ball", "angular", "cube"} (or ``"mirrorball"``)
    rotate_deg : float, degrees
        Rotation about +Y (right-hand rule).
    response : str or Response, optional
        Response of an 8/16-bit file (``"srgb"``, ``"linear"``, …); required for integer files.
    convention : str
        Orientation of a lat-long file (:data:`LATLONG_CONVENTIONS`): ``"facegeo"`` (+Z at the
        centre column), ``"u0_at_plus_z"`` (+Z at the left edge, the front–back mirror image)
        or ``"blender"`` (+X at the centre).

    Raises
    ------
    ImageReadError
        Unreadable file.
    InputError, ShapeError
        NaN/inf or large negative values, unknown projection or convention, wrong aspect, an
        integer file without ``response``.
    """
    from facegeo.capture import imageio

    projection = _check_projection(projection)
    check_convention(convention, projection)
    path = Path(path)
    raw = imageio.read_image(path)
    if raw.dtype.kind in "iu":
        if response is None:
            raise InputError(f"{path}: an {raw.dtype} environment map needs a response "
                             f"(e.g. response='srgb') to be linearised")
        raw = imageio.linearize(raw, response)
    return EnvironmentMap(raw, projection, math.radians(float(rotate_deg)), str(path), convention)


# --------------------------------------------------------------------------- synthetic maps


def analytic_map(fn, height: int, *, projection: str = "latlong", supersample: int = 4,
                 convention: str = "facegeo", layout: str = "cross") -> EnvironmentMap:
    """Rasterise an analytic environment ``fn(v_world (..., 3)) -> (..., 3)`` as the box-filtered
    (``supersample²`` sub-pixels, solid-angle weighted) pixel means.

    ``height`` rows; the width follows from the projection: 2 × for lat-long (stored in
    ``convention``), 1 × for the disc maps, ``4/3 ×`` for a cube cross (``height`` a multiple
    of 3) and 6 × for a cube strip (``layout``, :data:`CUBE_LAYOUTS`)."""
    projection = _check_projection(projection)
    check_choice(layout, "layout", CUBE_LAYOUTS)
    if projection == "cube" and layout == "cross" and height % 3:
        raise InputError(f"height: a cube cross has 3 rows of faces; got {height} rows, not a "
                         f"multiple of 3")
    w = {"latlong": 2 * height, "cube": (4 * height // 3 if layout == "cross" else 6 * height)
         }.get(projection, height)
    s = int(supersample)
    d, valid = pixel_directions(projection, height, w, supersample=s, convention=convention)
    om = pixel_solid_angles(projection, height, w, supersample=s)
    vals = np.zeros(d.shape[:2] + (3,))
    vals[valid] = np.asarray(fn(d[valid]), float)
    num = (vals * om[..., None]).reshape(height, s, w, s, 3).sum(axis=(1, 3))
    den = om.reshape(height, s, w, s).sum(axis=(1, 3))[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        img = np.where(den > 0, num / np.where(den > 0, den, 1), 0.0)
    return EnvironmentMap(img.astype(np.float32), projection, 0.0, "<analytic>", convention)


#: Axis → colour of the orientation test map (+X red, +Y green, +Z blue; −X cyan, −Y magenta,
#: −Z yellow), each a lobe ``max(0, ω·a)^k``.
AXIS_LOBE_COLORS = {
    (1, 0, 0): (1.0, 0.0, 0.0), (0, 1, 0): (0.0, 1.0, 0.0), (0, 0, 1): (0.0, 0.0, 1.0),
    (-1, 0, 0): (0.0, 1.0, 1.0), (0, -1, 0): (1.0, 0.0, 1.0), (0, 0, -1): (1.0, 1.0, 0.0),
}


def axis_lobe_map(height: int = 64, *, projection: str = "latlong", exponent: float = 8.0,
                  axes: Any = None, convention: str = "facegeo", layout: str = "cross"
                  ) -> EnvironmentMap:
    """The orientation test map: one coloured lobe ``max(0, ω·a)^exponent`` per axis ``a``
    (colours :data:`AXIS_LOBE_COLORS`, or the subset ``axes``); ``convention`` and ``layout``
    as in :func:`analytic_map`."""
    table = AXIS_LOBE_COLORS if axes is None else {tuple(a): AXIS_LOBE_COLORS[tuple(a)]
                                                   for a in axes}

    def fn(v):
        out = np.zeros(v.shape[:-1] + (3,))
        for a, c in table.items():
            out += np.maximum(v @ np.asarray(a, float), 0.0)[..., None] ** exponent * np.asarray(c)
        return out

    return analytic_map(fn, height, projection=projection, convention=convention, layout=layout)


# --------------------------------------------------------------------------- light basis


def _samples(env: EnvironmentMap, min_per_cell: float):
    """(Sub-)pixel directions (rotated into the world), solid angles and radiance."""
    s = max(1, min(16, int(math.ceil(min_per_cell))))
    d, valid = pixel_directions(env.projection, env.height, env.width, supersample=s,
                                convention=env.convention)
    om = pixel_solid_angles(env.projection, env.height, env.width, supersample=s)
    d = d[valid]
    om = om[valid]
    rad = np.repeat(np.repeat(env.image, s, axis=0), s, axis=1)[valid].astype(np.float64)
    if env.rotation != 0.0:
        d = d @ rotation_y(env.rotation).T
    return d, om, rad


def light_stage_radiance(env: EnvironmentMap, n_theta: int, n_phi: int, *,
                         supersample: int | None = None) -> np.ndarray:
    """Mean radiance of the environment over each light-stage grid cell, ``(L, 3)`` float64.

    The map is treated as piecewise constant over its pixels; each pixel is split into
    ``s × s`` sub-pixels (default: enough for ≥ 4 sub-pixels per cell edge — for a
    cube map also ≥ 2 across the polar cells — at most 16), each
    sub-pixel is assigned to the grid cell ``[θ_i⁻, θ_i⁺) × [φ_j⁻, φ_j⁺)`` containing its centre
    and contributes ``L · Ω_subpixel``. The cell's integral divided by the solid angle of its
    samples is the mean radiance. Cells no sample falls in (maps coarser than the grid) take
    the bilinear lookup at the cell centre. Summed over cells, ``mean · Ω_samples`` equals the
    map's integral exactly — the projection preserves energy.
    """
    from facegeo.frames import light_directions, nearest_light_index

    n_l = int(n_theta) * int(n_phi)
    if supersample is None:
        # sub-pixels per cell edge ≥ 4: cell width 2π/n_theta vs pixel width
        px = (0.5 * np.pi / cube_geometry(env.height, env.width)[0] if env.projection == "cube"
              else 2.0 * np.pi / env.width)
        cell = min(2.0 * np.pi / n_theta, np.pi / n_phi)
        supersample = 4.0 * px / cell
        if env.projection == "cube":
            # a cube's pixels do not follow the grid's rows: ≥ 2 sub-pixels across the polar
            # cells' azimuthal width too (measured: 32 × 16 grid, face 32 px, the axis-lobe map
            # against lat-long: max |Δw| 3.1 % of max w at s = 1, 0.4 % at s = 6)
            polar = 2.0 * np.pi / n_theta * math.sin(np.pi / (2 * n_phi))
            supersample = max(supersample, 2.0 * px / polar)
    d, om, rad = _samples(env, supersample)
    idx = nearest_light_index(d, n_theta, n_phi)
    area = np.bincount(idx, weights=om, minlength=n_l)
    integ = np.stack([np.bincount(idx, weights=om * rad[:, c], minlength=n_l) for c in range(3)],
                     axis=-1)
    out = np.empty((n_l, 3))
    has = area > 0
    out[has] = integ[has] / area[has, None]
    if not has.all():
        out[~has] = env.radiance(light_directions(n_theta, n_phi)[~has])
    return out


def light_stage_weights(env: EnvironmentMap, n_theta: int, n_phi: int, *,
                        solid_angle: str = "paper", supersample: int | None = None
                        ) -> np.ndarray:
    """Eq. (4) weights ``w_l = L̄_l · δA_l`` for a light-stage grid, ``(L, 3)`` float64.

    The returned weights **include δA** (applied here, exactly once): relight with
    ``Σ_l R_l ⊙ w_l`` and never multiply by δA again.

    Parameters
    ----------
    env : EnvironmentMap
    n_theta, n_phi : int
        The grid (facegeo.frames conventions).
    solid_angle : {"paper", "exact"}
        ``"paper"``: Debevec et al. 2000's ``δA = (2π/n_θ)(π/n_φ) sin φ`` (midpoint rule; a
        map reads high by h/sin h − 1 ≈ (π/n_φ)²/24 in every row, h = π/(2n_φ): 0.65 % at
        n_φ = 8, 0.16 % at 16, 0.04 % at 32).
        ``"exact"``: the cell area ``(2π/n_θ)(cos φ⁻ − cos φ⁺)``; ``Σ w`` then equals the map's
        integral to rounding.
    supersample : int, optional
        See :func:`light_stage_radiance`.
    """
    check_choice(solid_angle, "solid_angle", ("paper", "exact"))
    mean = light_stage_radiance(env, n_theta, n_phi, supersample=supersample)
    dA = light_solid_angles(n_theta, n_phi, exact=solid_angle == "exact")
    return mean * dA[:, None]


def direction_weights(env: EnvironmentMap, directions: Any, *, supersample: int = 2
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (4) weights for an arbitrary set of light directions (a real rig).

    Each light gets its spherical Voronoi cell (``scipy.spatial.SphericalVoronoi``) as its
    solid angle; the environment is integrated over the cell by assigning every (sub-)pixel to
    the nearest light (which is the cell containing it).

    Parameters
    ----------
    env : EnvironmentMap
    directions : (N, 3) float, unit directions toward the lights, world frame, N ≥ 4, distinct
    supersample : int
        Sub-pixels per pixel edge.

    Returns
    -------
    weights : (N, 3) float64
        ``∫_cell L dω`` — mean radiance times the Voronoi cell area (δA included).
    solid_angles : (N,) float64, steradians
        Voronoi cell areas (sum 4π).
    """
    from scipy.spatial import SphericalVoronoi

    v = as_array(directions, "directions", shape=(None, 3))
    if v.shape[0] < 4:
        raise ShapeError(f"directions: need at least 4 light directions, got {v.shape[0]}")
    norm = np.linalg.norm(v, axis=1)
    if np.any(np.abs(norm - 1.0) > 1e-6):
        raise InputError("directions: expected unit vectors toward the lights")
    try:
        sv = SphericalVoronoi(v, radius=1.0, threshold=1e-6)
    except ValueError as exc:
        raise InputError(f"directions: cannot build the spherical Voronoi cells ({exc}); "
                         f"directions must be distinct and not all on one great circle") from exc
    areas = sv.calculate_areas()
    return _nearest_light_mean(env, v, supersample) * areas[:, None], areas


def _nearest_light_mean(env: EnvironmentMap, v: np.ndarray, supersample: int,
                        horizon_axis: Any = None) -> np.ndarray:
    """Mean radiance ``(N, 3)`` of the environment over the directions nearest each light
    direction ``v`` (its spherical Voronoi cell, by assigning every (sub-)pixel to the nearest
    light; above the horizon only, with ``horizon_axis``); a light no sample falls nearest
    takes the map's value in its own direction."""
    from scipy.spatial import cKDTree

    d, om, rad = _samples(env, supersample)
    if horizon_axis is not None:
        keep = d @ np.asarray(horizon_axis, np.float64) >= 0.0
        d, om, rad = d[keep], om[keep], rad[keep]
    _, idx = cKDTree(v).query(d)
    area = np.bincount(idx, weights=om, minlength=v.shape[0])
    integ = np.stack([np.bincount(idx, weights=om * rad[:, c], minlength=v.shape[0])
                      for c in range(3)], axis=-1)
    mean = np.empty_like(integ)
    has = area > 0
    mean[has] = integ[has] / area[has, None]
    if not has.all():
        mean[~has] = env.radiance(v[~has])
    return mean


def light_weights(env: EnvironmentMap, lights: Any, *, solid_angle: str = "paper",
                  supersample: int = 2) -> np.ndarray:
    """Eq. (4) weights ``(L, 3)`` for a rig's lights, whichever kind: the light-stage grid
    (:func:`light_stage_weights`, with its ``solid_angle`` rule) or a list of lights
    (:class:`facegeo.geometry.lights.LightList`: a real rig's directions, e.g. a flash dome).

    For a list, ``w_l = L̄_l · δA_l``: ``δA_l`` the list's own solid angles (its Voronoi cells,
    clipped at the horizon for a dome — what every stage integrating over these lights uses),
    ``L̄_l`` the environment's mean radiance over the directions nearest light ``l`` (over the
    hemisphere above the horizon for a dome; a light no sample falls nearest takes the map's
    value in its direction). ``solid_angle`` applies to the grid only.
    """
    if hasattr(lights, "n_theta") and hasattr(lights, "n_phi"):
        return light_stage_weights(env, lights.n_theta, lights.n_phi, solid_angle=solid_angle)
    v = as_array(lights.directions, "lights.directions", shape=(None, 3))
    om_l = np.asarray(lights.solid_angles, np.float64)
    mean = _nearest_light_mean(env, v, supersample, getattr(lights, "horizon_axis", None))
    return mean * om_l[:, None]


def field_weights(weights, lights) -> np.ndarray:
    """Eq. (4) weights ``(L, 3)`` in the units of a reflectance field measured under ``lights``.

    A frame under light l holds ``f · cos θ · e_l`` for the light's own RGB intensity e_l, so
    an environment's weights (:func:`light_weights`) are divided by it light by light: the
    grid's one colour, a list's per-light ``intensities`` (a light of intensity 0 in a channel
    has black frames there and gets weight 0). The image is then in the environment's units.
    """
    from facegeo.geometry.lights import light_colors

    w = np.asarray(weights, np.float64)
    e = light_colors(lights)
    e = np.broadcast_to(e, w.shape) if e.shape == (3,) and w.ndim == 2 else e
    if e.shape != w.shape:
        raise ShapeError(f"weights: expected shape {e.shape} for these lights, got {w.shape}")
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(e > 0, w / np.where(e > 0, e, 1.0), 0.0)


# --------------------------------------------------------------------------- shipped maps

#: Names of the procedural environment maps shipped with facegeo (``facegeo/data/envmaps``).
SHIPPED_MAPS = ("sky", "studio")

#: Height of the shipped lat-long maps (width 2×); small: the light stage's densest preset
#: grid (64 × 32) samples cells of 5.6°, the shipped maps' pixels are 2.8°.
SHIPPED_HEIGHT = 64

#: The sky's sun: direction (world frame: up 35°, toward +X and +Z, i.e. front-left of a
#: subject looking along +Z), angular radius (radians; ≈ 7× the real sun's, so a 64-pixel map
#: and the light grid resolve it) and radiance.
SKY_SUN = {"direction": (0.5, 0.5736, 0.6494), "radius": math.radians(2.0),
           "radiance": (1400.0, 1300.0, 1150.0)}

#: The studio's three rectangular area lights: centre direction, half-extents (tangent of the
#: half-angle along the light's horizontal and vertical axes) and radiance. Key: a large
#: warm softbox front-left and above; fill: a dim cool one front-right, low; rim: behind and
#: above on the right.
STUDIO_LIGHTS = (
    {"name": "key", "direction": (0.55, 0.42, 0.72), "half": (0.30, 0.22),
     "radiance": (9.0, 8.4, 7.5)},
    {"name": "fill", "direction": (-0.70, 0.10, 0.70), "half": (0.25, 0.25),
     "radiance": (1.6, 1.8, 2.1)},
    {"name": "rim", "direction": (-0.45, 0.55, -0.70), "half": (0.12, 0.35),
     "radiance": (7.0, 7.0, 7.0)},
)


def _sky(v: np.ndarray) -> np.ndarray:
    """Clear sky with a sun over a grey-brown ground (world directions ``(..., 3)``)."""
    y = v[..., 1]
    up = np.clip(y, 0.0, 1.0)[..., None]
    horizon = np.array([0.90, 0.92, 0.95])
    zenith = np.array([0.18, 0.32, 0.75])
    sky = horizon + (zenith - horizon) * np.sqrt(up)
    ground = np.array([0.22, 0.19, 0.15])
    out = np.where((y >= 0.0)[..., None], sky, ground)
    sun = np.asarray(SKY_SUN["direction"], float)
    sun = sun / np.linalg.norm(sun)
    in_sun = (v @ sun) >= math.cos(SKY_SUN["radius"])
    return np.where(in_sun[..., None], np.asarray(SKY_SUN["radiance"]), out)


def _studio(v: np.ndarray) -> np.ndarray:
    """Dark studio (radiance 0.02) with three rectangular area lights (:data:`STUDIO_LIGHTS`)."""
    out = np.full(v.shape[:-1] + (3,), 0.02)
    up = np.array([0.0, 1.0, 0.0])
    for light in STUDIO_LIGHTS:
        c = np.asarray(light["direction"], float)
        c = c / np.linalg.norm(c)
        t1 = np.cross(up, c)
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(c, t1)
        dc = v @ c
        with np.errstate(invalid="ignore", divide="ignore"):
            x = (v @ t1) / dc
            yy = (v @ t2) / dc
        hx, hy = light["half"]
        inside = (dc > 0) & (np.abs(x) <= hx) & (np.abs(yy) <= hy)
        out = np.where(inside[..., None], np.asarray(light["radiance"]), out)
    return out


_PROCEDURAL = {"sky": _sky, "studio": _studio}


def procedural_map(name: str, height: int = SHIPPED_HEIGHT) -> EnvironmentMap:
    """One of the procedural environment maps shipped with facegeo, rasterised (lat-long).

    * ``"sky"``: a clear sky (horizon ``(0.90, 0.92, 0.95)`` → zenith ``(0.18, 0.32, 0.75)``,
      blended by ``√y``), a ground of radiance ``(0.22, 0.19, 0.15)`` below the horizon and a
      sun disc (:data:`SKY_SUN`) carrying ≈ 50 % of the map's energy — a sun-like, all-frequency
      environment;
    * ``"studio"``: a dark room (0.02) with three rectangular area lights
      (:data:`STUDIO_LIGHTS`: key, fill, rim) — hard-edged, medium-frequency lighting.

    Every pixel is the solid-angle-weighted mean over 4 × 4 sub-pixels (:func:`analytic_map`).
    The shipped files ``facegeo/data/envmaps/<name>.exr`` are this function's output at
    :data:`SHIPPED_HEIGHT` stored as half floats (``tests/test_envmap.py`` checks they match).

    Parameters
    ----------
    name : {"sky", "studio"}
    height : int
        Rows of the lat-long map (width ``2 · height``).
    """
    check_choice(name, "name", SHIPPED_MAPS)
    env = analytic_map(_PROCEDURAL[name], int(height))
    return EnvironmentMap(env.image, "latlong", 0.0, f"<procedural {name}>")


def shipped_map_path(name: str) -> Path:
    """Path of the shipped map file ``facegeo/data/envmaps/<name>.exr`` (may be missing in a
    source tree that never wrote it; :func:`shipped_map` then rasterises it)."""
    check_choice(name, "name", SHIPPED_MAPS)
    return Path(__file__).resolve().parent.parent / "data" / "envmaps" / f"{name}.exr"


def shipped_map(name: str) -> EnvironmentMap:
    """A shipped procedural environment map (lat-long, :data:`SHIPPED_HEIGHT` rows): read from
    the package's ``data/envmaps/<name>.exr``, or rasterised by :func:`procedural_map` when the
    file is absent."""
    path = shipped_map_path(name)
    if path.is_file():
        env = read_envmap(path, "latlong")
        return EnvironmentMap(env.image, "latlong", 0.0, str(path))
    log.info("%s missing: rasterising the procedural map %r", path, name)
    return procedural_map(name)


def write_shipped_maps(folder: str | os.PathLike | None = None) -> list[Path]:
    """Write every shipped map as a half-float EXR (``folder`` default: the package's
    ``data/envmaps``). How the files in the package were made."""
    from facegeo.capture import imageio

    out = []
    for name in SHIPPED_MAPS:
        path = shipped_map_path(name) if folder is None else Path(folder) / f"{name}.exr"
        path.parent.mkdir(parents=True, exist_ok=True)
        out.append(imageio.write_image(path, procedural_map(name).image, half=True))
    return out
