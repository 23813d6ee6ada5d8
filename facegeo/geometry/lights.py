"""Light lists: lights that are not the light stage's θ × φ grid.

Photometric-stereo domes and flash rigs record their lights as a list: a direction (or a
near-field position) and an RGB intensity per light, often with a name (``A+035E+15``).
:class:`LightList` holds such a list and gives it the solid-angle weights the reflectance
integral needs (Debevec et al. 2000, Eq. 4 weights each light by the solid angle δA of the
sphere it stands for); for the grid those are :func:`facegeo.frames.light_solid_angles`, for a
list they come from a spherical Voronoi partition (:func:`voronoi_solid_angles`).

Both :class:`facegeo.geometry.rig.LightStage` and :class:`LightList` satisfy the small
:class:`LightSet` protocol (``n_lights``, ``directions``, ``solid_angles``), which is all a
stage that integrates over lights needs.

References
----------
.. [1] Debevec et al., "Acquiring the Reflectance Field of a Human Face", SIGGRAPH 2000,
   §3 and Eq. 4 (the light-stage integral weighted by δA).
.. [2] Caroli et al., "Robust and efficient Delaunay triangulations of points on or close to a
   sphere", SEA 2010 (the algorithm behind ``scipy.spatial.SphericalVoronoi``).
"""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError

__all__ = ["LightSet", "LightList", "voronoi_solid_angles", "directions_from_azimuth_elevation",
           "light_colors", "LIGHT_LIST_KIND"]


def light_colors(lights) -> np.ndarray:
    """The colour each frame was lit with: ``(3,)`` for a light-stage grid (one colour), the
    per-light ``intensities`` ``(L, 3)`` for a :class:`LightList` (float64, linear RGB). An
    environment's Eq. (4) weights are divided by it to relight frames in the environment's
    units (:func:`facegeo.lighting.envmap.field_weights`)."""
    if hasattr(lights, "n_theta"):
        return np.asarray(lights.color_rgb, np.float64)
    return np.asarray(lights.intensities, np.float64)


#: ``"kind"`` of a light list in ``rig.json``'s ``lights`` entry.
LIGHT_LIST_KIND = "list"

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")
_LIST_KEYS = ("kind", "names", "directions", "positions", "center", "intensities",
              "solid_angles", "horizon_axis")
#: |ω·axis| below this counts as "on the horizon" (about 0.06°).
_HORIZON_EPS = 1e-3


@runtime_checkable
class LightSet(Protocol):
    """What a stage that integrates over lights needs from a set of lights.

    Attributes
    ----------
    n_lights : int
    directions : (L, 3) float64, unit, world frame, from the subject toward each light
    solid_angles : (L,) float64, steradians, the δA weight of each light (Eq. 4)
    """

    @property
    def n_lights(self) -> int: ...

    @property
    def directions(self) -> np.ndarray: ...

    @property
    def solid_angles(self) -> np.ndarray: ...


def _unit_rows(a: Any, name: str) -> np.ndarray:
    v = np.asarray(a, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"{name}: expected an (L, 3) array, got shape {v.shape}")
    if not np.isfinite(v).all():
        raise InputError(f"{name}: contains NaN or inf")
    n = np.linalg.norm(v, axis=1)
    bad = np.flatnonzero(n < 1e-12)
    if bad.size:
        raise InputError(f"{name}[{int(bad[0])}]: zero-length vector, which has no direction")
    return v / n[:, None]


def directions_from_azimuth_elevation(azimuth_deg: Any, elevation_deg: Any) -> np.ndarray:
    """Unit light directions from azimuth and elevation angles, world frame.

    The world frame of ``docs/conventions.md`` (+Y up, the subject looks along +Z): azimuth is
    measured in the horizontal plane from +Z toward +X (the light-stage grid's θ), elevation
    from that plane toward +Y (90° − the grid's φ)::

        ω = (cos e · sin a, sin e, cos e · cos a)

    Data sets name their flashes this way (``A+035E+15``) but differ in the sign of the
    azimuth; negate it when the data set's positive azimuth is toward −X.

    Parameters
    ----------
    azimuth_deg, elevation_deg : (L,) float, degrees
        Broadcast against each other.

    Returns
    -------
    (L, 3) float64, unit
    """
    a = np.radians(np.asarray(azimuth_deg, dtype=np.float64))
    e = np.radians(np.asarray(elevation_deg, dtype=np.float64))
    a, e = np.broadcast_arrays(a, e)
    if not (np.isfinite(a).all() and np.isfinite(e).all()):
        raise InputError("azimuth_deg, elevation_deg: must be finite")
    if (np.abs(np.degrees(e)) > 90.0 + 1e-9).any():
        raise InputError("elevation_deg: expected angles in [-90, 90] degrees")
    return np.stack([np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)], axis=-1).reshape(-1, 3)


def voronoi_solid_angles(directions: Any, horizon_axis: Any = None) -> np.ndarray:
    """Solid angle of each light's cell in a spherical Voronoi partition of its directions.

    Each light stands for the part of the sphere of directions closer to it than to any other
    light: the weight δA of Debevec et al. 2000, Eq. 4, for lights that are not on a grid.

    Parameters
    ----------
    directions : (L, 3) float, world frame
        Directions toward the lights (normalised here), all distinct, L ≥ 4 for a full sphere.
    horizon_axis : (3,) float or None
        ``None``: the lights cover the whole sphere, cells sum to 4π. A vector ``a``: the rig is a
        dome covering only the half-space ``ω·a ≥ 0``; cells are **clipped at the horizon**
        (the plane ``ω·a = 0``) and sum to 2π. Implemented by adding the mirror image of every
        light across the horizon plane: the bisector of a light and its mirror is the horizon
        itself, so each original cell of the enlarged set is exactly its cell in the dome
        clipped at the horizon. A light on the horizon (``|ω·a| < 1e-3``) is its own mirror;
        its cell is symmetric about the horizon and it gets half of it.

    Returns
    -------
    (L,) float64, steradians

    Raises
    ------
    InputError
        Wrong shape, non-finite or zero vectors, repeated directions, a light below the horizon,
        or too few / coplanar directions for a partition.

    Notes
    -----
    The unclipped treatment of a dome (no ``horizon_axis``) would hand the whole lower
    hemisphere to the lowest ring of lights, inflating their weights by up to ~2π/n.
    """
    d = _unit_rows(directions, "directions")
    n_orig = d.shape[0]
    points = d
    half = np.zeros(n_orig, dtype=bool)
    if horizon_axis is not None:
        a = _unit_rows(np.reshape(np.asarray(horizon_axis, dtype=np.float64), (1, 3)),
                       "horizon_axis")[0]
        h = d @ a
        below = np.flatnonzero(h < -_HORIZON_EPS)
        if below.size:
            raise InputError(
                f"directions[{int(below[0])}]: light is below the horizon (ω·axis = "
                f"{h[below[0]]:.3g}); a dome with horizon_axis {fmt_value(a.tolist())} covers "
                f"only ω·axis ≥ 0 ({below.size} light(s) below)")
        half = np.abs(h) <= _HORIZON_EPS
        up = ~half
        mirror = d[up] - 2.0 * np.outer(h[up], a)
        points = np.concatenate([d, mirror])
    if points.shape[0] < 4:
        raise InputError(
            f"directions: a spherical Voronoi partition needs at least 4 directions (with "
            f"mirrors), got {points.shape[0]}")
    # Repeated directions make the partition degenerate: report the pair.
    dots = d @ d.T
    np.fill_diagonal(dots, -2.0)
    i, j = np.unravel_index(int(np.argmax(dots)), dots.shape)
    if dots[i, j] > 1.0 - 1e-12:
        raise InputError(f"directions[{min(i, j)}] and directions[{max(i, j)}] are the same "
                         "direction; every light needs its own")
    from scipy.spatial import SphericalVoronoi  # deferred: scipy.spatial is slow to import

    try:
        sv = SphericalVoronoi(points, radius=1.0, center=np.zeros(3))
        sv.sort_vertices_of_regions()
        areas = sv.calculate_areas()
    except (ValueError, RuntimeError) as exc:
        raise InputError(f"directions: no spherical Voronoi partition ({exc}); are the "
                         "lights all on one great circle?") from exc
    out = np.asarray(areas[:n_orig], dtype=np.float64)
    out[half] *= 0.5
    return out


def _check_names(names: Any, n: int) -> tuple[str, ...]:
    if names is None:
        return tuple(f"{k:04d}" for k in range(n))
    if isinstance(names, str) or len(names) != n:
        raise InputError(f"names: expected {n} light names (one per light), got {fmt_value(names)}")
    out = []
    for k, s in enumerate(names):
        if not isinstance(s, str) or not _NAME.match(s):
            raise InputError(
                f"names[{k}]: {fmt_value(s)} is not a valid light name (letters, digits and "
                "_ . + -, starting with a letter or digit: names become file names)")
        out.append(s)
    dup = sorted({s for s in out if out.count(s) > 1})
    if dup:
        raise InputError(f"names: light names must be unique; repeated: {', '.join(dup)}")
    return tuple(out)


@dataclass(frozen=True, eq=False)
class LightList:
    """A list of lights: directions or near-field positions, RGB intensities, δA weights.

    Parameters
    ----------
    directions : (L, 3) float, world frame, optional
        Directions from ``center`` toward each light (normalised). Give this *or* ``positions``.
    positions : (L, 3) float, metres, world frame, optional
        Near-field light positions; ``directions`` become ``(positions − center) / |…|``.
    intensities : (L, 3) float, linear RGB, optional
        Relative radiant intensity of each light per channel, ≥ 0 (default all ones).
    solid_angles : (L,) float, steradians, optional
        δA weights; default :func:`voronoi_solid_angles` of the directions.
    names : sequence of str, optional
        Unique, file-name-safe names (``files = "olat/{camera}/{light_name}.pgm"``); default
        ``"0000"``, ``"0001"``, ...
    center : (3,) float, metres, world frame
        Where the subject is (the origin of ``directions``).
    horizon_axis : (3,) float or None
        The dome's up axis when the lights cover only a hemisphere (cells clipped at the
        horizon, see :func:`voronoi_solid_angles`); ``None`` for a full sphere.

    Attributes
    ----------
    n_lights : int
    directions : (L, 3) float64, unit
    positions : (L, 3) float64 or None
    intensities : (L, 3) float64
    solid_angles : (L,) float64
    names : tuple of str
    """

    directions: Any = None
    positions: Any = None
    intensities: Any = None
    solid_angles: Any = None
    names: Any = None
    center: Any = (0.0, 0.0, 0.0)
    horizon_axis: Any = None

    def __post_init__(self):
        put = functools.partial(object.__setattr__, self)  # frozen dataclass
        c = np.asarray(self.center, dtype=np.float64)
        if c.shape != (3,) or not np.isfinite(c).all():
            raise InputError(f"center: expected 3 finite numbers, got {fmt_value(self.center)}")
        put("center", c)
        if (self.directions is None) == (self.positions is None):
            raise InputError("LightList: give directions (distant lights) or positions "
                             "(near-field lights), exactly one of them")
        if self.positions is not None:
            p = np.asarray(self.positions, dtype=np.float64)
            if p.ndim != 2 or p.shape[1] != 3 or not np.isfinite(p).all():
                raise InputError(f"positions: expected a finite (L, 3) array, got shape {p.shape}")
            put("positions", p)
            put("directions", _unit_rows(p - c, "positions - center"))
        else:
            put("directions", _unit_rows(self.directions, "directions"))
        n = self.directions.shape[0]
        if n < 1:
            raise InputError("directions: a light list needs at least one light")
        if self.horizon_axis is not None:
            put("horizon_axis", _unit_rows(np.reshape(
                np.asarray(self.horizon_axis, dtype=np.float64), (1, 3)), "horizon_axis")[0])
        e = np.ones((n, 3)) if self.intensities is None else np.asarray(self.intensities,
                                                                          dtype=np.float64)
        if e.shape == (n,):
            e = np.repeat(e[:, None], 3, axis=1)
        if e.shape != (n, 3) or not np.isfinite(e).all() or (e < 0).any():
            raise InputError(f"intensities: expected ({n}, 3) finite linear RGB values ≥ 0, got "
                             f"shape {e.shape}")
        put("intensities", e)
        if self.solid_angles is None:
            put("solid_angles", voronoi_solid_angles(self.directions, self.horizon_axis))
        else:
            w = np.asarray(self.solid_angles, dtype=np.float64)
            if w.shape != (n,) or not np.isfinite(w).all() or (w <= 0).any():
                raise InputError(f"solid_angles: expected ({n},) finite values > 0 (sr), got "
                                 f"shape {w.shape}")
            if w.sum() > 4.0 * math.pi * (1 + 1e-6):
                raise InputError(f"solid_angles: sum to {w.sum():.4g} sr, more than the whole "
                                 "sphere (4π)")
            put("solid_angles", w)
        put("names", _check_names(self.names, n))
        for k in ("directions", "intensities", "solid_angles") + (
                ("positions",) if self.positions is not None else ()):
            getattr(self, k).setflags(write=False)

    @property
    def n_lights(self) -> int:
        """Number of lights L."""
        return int(self.directions.shape[0])

    @property
    def is_distant(self) -> bool:
        """True when the lights are given as directions only (no positions)."""
        return self.positions is None

    @property
    def color_rgb(self) -> np.ndarray:
        """Mean intensity over the lights, ``(3,)`` float64, linear RGB (the grid's ``color``)."""
        return self.intensities.mean(axis=0)

    def index(self, name: str) -> int:
        """Index of the light called ``name`` (error lists a few valid names)."""
        try:
            return self.names.index(name)
        except ValueError:
            shown = ", ".join(self.names[:6]) + (", ..." if self.n_lights > 6 else "")
            raise InputError(f"light: no light named {fmt_value(name)}; names: {shown}") from None

    def to_dict(self) -> dict:
        """JSON-ready mapping (``kind = "list"``), the inverse of :meth:`from_dict`."""
        out: dict[str, Any] = {"kind": LIGHT_LIST_KIND, "names": list(self.names)}
        if self.positions is not None:
            out["positions"] = self.positions.tolist()
        else:
            out["directions"] = self.directions.tolist()
        out["center"] = self.center.tolist()
        out["intensities"] = self.intensities.tolist()
        out["solid_angles"] = self.solid_angles.tolist()
        if self.horizon_axis is not None:
            out["horizon_axis"] = self.horizon_axis.tolist()
        return out

    @classmethod
    def from_dict(cls, d: Any, *, where: str = "lights") -> LightList:
        """Build from ``rig.json``'s ``lights`` entry; errors name ``<where>.<key>``."""
        if not isinstance(d, dict):
            raise InputError(f"{where}: expected a mapping, got {type(d).__name__}")
        unknown = sorted(set(d) - set(_LIST_KEYS))
        if unknown:
            raise InputError(f"{where}.{unknown[0]}: unknown field (expected only "
                             f"{', '.join(_LIST_KEYS)})")
        if d.get("kind") != LIGHT_LIST_KIND:
            raise InputError(f"{where}.kind: expected {LIGHT_LIST_KIND!r}, got {fmt_value(d.get('kind'))}")
        kwargs = {k: d[k] for k in _LIST_KEYS[1:] if k in d}
        for k, v in kwargs.items():
            if k != "names" and v is not None and _has_non_number(v):
                raise InputError(f"{where}.{k}: expected JSON numbers, got {fmt_value(v)}")
        try:
            return cls(**kwargs)
        except InputError as exc:
            raise InputError(f"{where}.{exc}") from exc

    def __eq__(self, other) -> bool:
        if not isinstance(other, LightList) or other.n_lights != self.n_lights:
            return False
        return (self.names == other.names and _same(self.positions, other.positions)
                and np.array_equal(self.directions, other.directions)
                and np.array_equal(self.intensities, other.intensities)
                and np.array_equal(self.solid_angles, other.solid_angles)
                and np.array_equal(self.center, other.center)
                and _same(self.horizon_axis, other.horizon_axis))

    __hash__ = None  # type: ignore[assignment]


def _same(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    """Equal arrays, or both None."""
    if a is None or b is None:
        return a is None and b is None
    return np.array_equal(a, b)


def _has_non_number(v: Any) -> bool:
    if isinstance(v, (list, tuple)):
        return any(_has_non_number(x) for x in v)
    return isinstance(v, bool) or not isinstance(v, (int, float))
