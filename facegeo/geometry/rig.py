"""The capture rig: cameras, the structured-light projector and the lights.

A :class:`Rig` is what calibration produces and every later stage consumes. It saves to and loads
from a small JSON file (``calib/default_rig.json`` is :func:`default_rig` written out). Real rigs
differ from the paper's: the projector may be uncalibrated (:class:`Projector`: resolution only),
the lights may be a list (:class:`facegeo.geometry.lights.LightList`) instead of the θ × φ grid
(:class:`LightStage`), or absent (``lights = None``: structured light or calibration only); see
``docs/scan-format.md``, *Lights*.

Regenerate the shipped calibration files (``calib/default_rig.json`` and
``calib/charuco_board.json``) after changing :func:`default_rig` or the default
:class:`facegeo.geometry.board.CharucoBoard` with::

    python -m facegeo.geometry.rig            # writes <repo>/calib/
    python -m facegeo.geometry.rig OUT_DIR    # writes OUT_DIR/

``tests/test_rig.py`` and ``tests/test_board.py`` check that the shipped files equal what the code
produces.

References
----------
.. [1] Debevec et al., "Acquiring the Reflectance Field of a Human Face", SIGGRAPH 2000, §2
   (the light stage: a light spun in θ and lowered in φ once per revolution; two cameras and a
   structured-light video projector).
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.geometry.camera import Camera
from facegeo.checks import as_array, check_positive, fmt_value
from facegeo.errors import InputError
from facegeo.frames import light_directions, light_solid_angles, look_at
from facegeo.fsutil import atomic_write_text, load_json_file
from facegeo.geometry.lights import LIGHT_LIST_KIND, LightList, LightSet

__all__ = [
    "LightStage",
    "LightList",
    "LightSet",
    "Projector",
    "Rig",
    "default_rig",
    "RIG_FORMAT",
    "RIG_VERSION",
    "LIGHT_ORDER",
    "write_default_calib",
]

#: ``"format"`` tag of a rig file.
RIG_FORMAT = "facegeo-rig"
#: Version of the rig file layout.
RIG_VERSION = 1
#: Capture order of the light stage: θ varies fastest, ``l = j·n_theta + i``.
LIGHT_ORDER = "theta-fastest"

_LIGHT_KEYS = ("n_theta", "n_phi", "radius", "center", "color", "light_order")
_RIG_KEYS = ("format", "version", "cameras", "projector", "lights")
_PROJECTOR_KEYS = ("name", "width", "height", "calibrated")


def _vec3(value: Any, name: str) -> tuple[float, float, float]:
    a = as_array(value, name, shape=(3,))
    return (float(a[0]), float(a[1]), float(a[2]))


def _check_json_numbers(d: Any, where: str, keys: tuple[str, ...]) -> None:
    """Reject non-numeric JSON values under ``keys`` of the mapping ``d``, naming the field.

    ``numpy.asarray`` and ``int()`` would accept the JSON string ``"366"`` for a focal length (or
    ``true`` for a width); a rig file must hold JSON numbers. Nested lists and mappings (``K``,
    ``T_cam_world.R``) are walked; the error names the element, e.g.
    ``cameras[0].K[0][0]: expected a JSON number, got the string '366'``.
    """
    if not isinstance(d, dict):
        return  # the from_dict methods report the wrong type themselves

    def walk(v: Any, name: str) -> None:
        if isinstance(v, dict):
            for k, x in v.items():
                walk(x, f"{name}.{k}")
        elif isinstance(v, list):
            for i, x in enumerate(v):
                walk(x, f"{name}[{i}]")
        elif isinstance(v, bool) or not isinstance(v, (int, float)):
            kind = {str: "the string", type(None): "null"}.get(type(v), type(v).__name__)
            shown = "" if v is None else f" {v!r}"
            raise InputError(f"{name}: expected a JSON number, got {kind}{shown}")

    for k in keys:
        if k in d:
            walk(d[k], f"{where}.{k}" if where else k)


_CAMERA_NUMERIC = ("width", "height", "K", "dist", "T_cam_world")


def _json_text(obj: Any, level: int = 0) -> str:
    """Strict JSON, indented by 2, with lists of scalars (vectors, matrix rows) on one line."""
    pad, pad1 = "  " * level, "  " * (level + 1)
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        items = [f"{pad1}{json.dumps(str(k))}: {_json_text(v, level + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, (list, tuple)):
        if all(not isinstance(v, (dict, list, tuple)) for v in obj):
            return json.dumps(list(obj), allow_nan=False)
        items = [pad1 + _json_text(v, level + 1) for v in obj]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    return json.dumps(obj, allow_nan=False)


def _check_keys(d: Any, where: str, required: tuple[str, ...], allowed: tuple[str, ...]) -> None:
    """Check a mapping's keys; ``where`` prefixes field names (``""`` at the top level)."""
    if not isinstance(d, dict):
        raise InputError(f"{where or 'rig'}: expected a mapping, got {type(d).__name__}")
    pre = f"{where}." if where else ""
    for k in required:
        if k not in d:
            raise InputError(f"{pre}{k}: missing field (expected {', '.join(allowed)})")
    unknown = sorted(set(d) - set(allowed))
    if unknown:
        raise InputError(f"{pre}{unknown[0]}: unknown field (expected only {', '.join(allowed)})")


# --------------------------------------------------------------------------- light stage


@dataclass(frozen=True)
class LightStage:
    """The light stage's grid of light positions (Debevec et al. 2000 §2).

    The light is spun in azimuth θ while it is lowered in inclination φ once per revolution,
    so the capture order is *theta-fastest*: frame / light index ``l = j·n_theta + i`` for
    azimuth index i and inclination index j (:data:`LIGHT_ORDER`). Directions follow
    :func:`facegeo.frames.light_directions`.

    Parameters
    ----------
    n_theta : int
        Azimuth steps (64 in the paper).
    n_phi : int
        Inclination steps (32 in the paper).
    radius : float, metres
        Distance of the point lights from ``center``; ``math.inf`` means distant (directional)
        lights.
    center : (3,) float, metres, world frame
        Centre of the light sphere.
    color : (3,) float, linear RGB
        Emitted colour (relative radiant intensity per channel), all ≥ 0.
    """

    n_theta: int = 64
    n_phi: int = 32
    radius: float = 1.5
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)

    light_order = LIGHT_ORDER  # class constant, not a field

    def __post_init__(self):
        for name in ("n_theta", "n_phi"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise InputError(f"{name}: expected a positive integer, got {fmt_value(v)}")
            object.__setattr__(self, name, int(v))
        try:
            r = float(self.radius)
        except (TypeError, ValueError):
            raise InputError(
                f"radius: expected a number > 0 or inf, got {fmt_value(self.radius)}"
            ) from None
        if not r > 0:
            raise InputError(
                f"radius: expected a number > 0 or inf, got {fmt_value(self.radius)}"
            )
        object.__setattr__(self, "radius", r)
        object.__setattr__(self, "center", _vec3(self.center, "center"))
        color = _vec3(self.color, "color")
        if min(color) < 0:
            raise InputError(f"color: expected linear RGB values >= 0, got {color}")
        object.__setattr__(self, "color", color)

    @property
    def n_lights(self) -> int:
        """Number of lights ``L = n_theta·n_phi``."""
        return self.n_theta * self.n_phi

    @property
    def is_distant(self) -> bool:
        """True when the lights are directional (``radius`` is inf)."""
        return math.isinf(self.radius)

    @property
    def directions(self) -> np.ndarray:
        """Unit directions from ``center`` toward each light, ``(L, 3)`` float64, world frame."""
        return light_directions(self.n_theta, self.n_phi)

    @property
    def solid_angles(self) -> np.ndarray:
        """Solid angle of each light's grid cell, ``(L,)`` float64, steradians (Eq. 4 weight)."""
        return light_solid_angles(self.n_theta, self.n_phi)

    @property
    def positions(self) -> np.ndarray:
        """Light positions ``center + radius·ω``, ``(L, 3)`` float64, metres, world frame.

        Raises
        ------
        InputError
            The lights are distant (``radius`` is inf): use :attr:`directions`.
        """
        if self.is_distant:
            raise InputError(
                "positions: the light stage has distant lights (radius = inf), which have no "
                "position; use LightStage.directions"
            )
        return np.asarray(self.center) + self.radius * self.directions

    @property
    def color_rgb(self) -> np.ndarray:
        """``(3,)`` float64, linear RGB."""
        return np.asarray(self.color, dtype=np.float64)

    def to_dict(self) -> dict:
        """JSON-ready mapping (``radius`` inf is written as the string ``"inf"``)."""
        return {
            "n_theta": self.n_theta,
            "n_phi": self.n_phi,
            "radius": "inf" if self.is_distant else self.radius,
            "center": list(self.center),
            "color": list(self.color),
            "light_order": LIGHT_ORDER,
        }

    @classmethod
    def from_dict(cls, d: Any, *, where: str = "lights") -> LightStage:
        """Inverse of :meth:`to_dict`; errors name the field as ``<where>.<key>``."""
        _check_keys(d, where, ("n_theta", "n_phi", "radius"), _LIGHT_KEYS)
        _check_json_numbers(d, where, ("n_theta", "n_phi", "center", "color"))
        order = d.get("light_order", LIGHT_ORDER)
        if order != LIGHT_ORDER:
            raise InputError(
                f"{where}.light_order: only {fmt_value(LIGHT_ORDER)} is supported, got {fmt_value(order)}"
            )
        radius = d["radius"]
        if radius == "inf":
            radius = math.inf
        elif isinstance(radius, str) or isinstance(radius, bool):
            raise InputError(
                f"{where}.radius: expected a number > 0 or \"inf\", got {fmt_value(radius)}"
            )
        kwargs = {k: d[k] for k in ("center", "color") if k in d}
        try:
            return cls(d["n_theta"], d["n_phi"], radius, **kwargs)
        except InputError as exc:
            raise type(exc)(f"{where}.{exc}") from exc


# --------------------------------------------------------------------------- projector


@dataclass(frozen=True)
class Projector:
    """A projector whose resolution is known but whose intrinsics and pose are not (yet).

    What a real structured-light scan has before projector calibration: the decoder needs only
    the resolution (:class:`facegeo.geometry.structured_light.PatternSpec`); calibration finds
    ``K``, distortion and pose and replaces this with a
    :class:`facegeo.geometry.camera.Camera`. In ``rig.json``:
    ``{"name": "projector", "width": 1024, "height": 768, "calibrated": false}``.

    Parameters
    ----------
    name : str
    width, height : int
        Resolution, pixels.
    """

    name: str
    width: int
    height: int

    #: Always False: an uncalibrated projector has no intrinsics (``Camera`` has them).
    calibrated = False

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name.strip():
            raise InputError(f"name: expected a non-empty string, got {fmt_value(self.name)}")
        for k in ("width", "height"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise InputError(f"{k}: expected a positive integer (pixels), got {fmt_value(v)}")
            object.__setattr__(self, k, int(v))

    def to_dict(self) -> dict:
        """``{"name", "width", "height", "calibrated": false}``."""
        return {"name": self.name, "width": self.width, "height": self.height,
                "calibrated": False}

    @classmethod
    def from_dict(cls, d: Any, *, where: str = "projector") -> Projector:
        """Inverse of :meth:`to_dict`; errors name ``<where>.<key>``."""
        _check_keys(d, where, ("name", "width", "height", "calibrated"), _PROJECTOR_KEYS)
        if d["calibrated"] is not False:
            raise InputError(f"{where}.calibrated: an entry with only name, width and height is "
                             "an uncalibrated projector and says \"calibrated\": false; a "
                             "calibrated one is a camera entry (K, dist, T_cam_world)")
        try:
            return cls(d["name"], d["width"], d["height"])
        except InputError as exc:
            raise InputError(f"{where}.{exc}") from exc


def _lights_from_dict(d: Any, where: str = "lights") -> LightStage | LightList | None:
    """``rig.json``'s ``lights``: null (no light stage), a grid, or ``{"kind": "list", ...}``."""
    if d is None:
        return None
    if isinstance(d, dict) and "kind" in d:
        if d["kind"] != LIGHT_LIST_KIND:
            raise InputError(f"{where}.kind: expected {LIGHT_LIST_KIND!r} (a light list) or no "
                             f"kind (the θ × φ grid), got {fmt_value(d['kind'])}")
        return LightList.from_dict(d, where=where)
    return LightStage.from_dict(d, where=where)


# --------------------------------------------------------------------------- rig


@dataclass
class Rig:
    """Cameras, an optional projector and optional lights, all in one world frame.

    Parameters
    ----------
    cameras : list of Camera
        At least one, unique names.
    projector : Camera, Projector or None
        The structured-light projector as an inverse camera: its own resolution and
        intrinsics; ``T_cam_world`` is the projector pose. A :class:`Projector` when only its
        resolution is known (not calibrated yet).
    lights : LightStage, LightList or None
        The θ × φ grid of Debevec et al. 2000, a list of lights
        (:class:`facegeo.geometry.lights.LightList`), or None for a rig without lights
        (structured light or calibration only). Both kinds satisfy
        :class:`facegeo.geometry.lights.LightSet`.
    """

    cameras: list[Camera]
    projector: Camera | Projector | None = None
    lights: LightStage | LightList | None = LightStage()

    def __post_init__(self):
        cams = list(self.cameras) if not isinstance(self.cameras, Camera) else [self.cameras]
        if not cams:
            raise InputError("cameras: a rig needs at least one camera")
        for i, c in enumerate(cams):
            if not isinstance(c, Camera):
                raise InputError(f"cameras[{i}]: expected a Camera, got {type(c).__name__}")
        names = [c.name for c in cams]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise InputError(f"cameras: camera names must be unique; repeated: {', '.join(dup)}")
        if self.projector is not None and not isinstance(self.projector, (Camera, Projector)):
            raise InputError(
                f"projector: expected a Camera, a Projector or None, got "
                f"{type(self.projector).__name__}"
            )
        if self.lights is not None and not isinstance(self.lights, (LightStage, LightList)):
            raise InputError(f"lights: expected a LightStage, a LightList or None, got "
                             f"{type(self.lights).__name__}")
        self.cameras = cams

    @property
    def projector_calibrated(self) -> bool:
        """True when the rig has a projector with intrinsics and pose (a ``Camera``)."""
        return isinstance(self.projector, Camera)

    @property
    def camera_names(self) -> list[str]:
        """Names of the cameras, in rig order."""
        return [c.name for c in self.cameras]

    def camera(self, name: str) -> Camera:
        """The camera called ``name``.

        Raises
        ------
        InputError
            No such camera; the message lists the valid names.
        """
        for c in self.cameras:
            if c.name == name:
                return c
        raise InputError(
            f"camera: no camera named {fmt_value(name)}; valid names: {', '.join(self.camera_names)}"
        )

    def scaled(self, factor: float) -> Rig:
        """The rig with every camera image resized by ``factor`` (the projector is unchanged).

        See :meth:`facegeo.geometry.camera.Camera.scaled`.
        """
        check_positive(factor, "factor")
        return Rig([c.scaled(factor) for c in self.cameras], self.projector, self.lights)

    # ------------------------------------------------------------------ JSON

    def to_dict(self) -> dict:
        """JSON-ready mapping: format, version, cameras, projector (or null), lights (or
        null)."""
        return {
            "format": RIG_FORMAT,
            "version": RIG_VERSION,
            "cameras": [c.to_dict() for c in self.cameras],
            "projector": None if self.projector is None else self.projector.to_dict(),
            "lights": None if self.lights is None else self.lights.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: Any) -> Rig:
        """Inverse of :meth:`to_dict`.

        Raises
        ------
        InputError
            A missing, unknown or bad field; the message names it (``cameras[1].K: ...``).
        """
        _check_keys(d, "", ("cameras",), _RIG_KEYS)
        fmt = d.get("format", RIG_FORMAT)
        if fmt != RIG_FORMAT:
            raise InputError(f"format: expected {fmt_value(RIG_FORMAT)}, got {fmt_value(fmt)}")
        version = d.get("version", RIG_VERSION)
        if version != RIG_VERSION:
            raise InputError(
                f"version: this facegeo reads rig version {RIG_VERSION}, got {fmt_value(version)}"
            )
        cams = d["cameras"]
        if not isinstance(cams, list):
            raise InputError(f"cameras: expected a list of cameras, got {type(cams).__name__}")
        for i, c in enumerate(cams):
            _check_json_numbers(c, f"cameras[{i}]", _CAMERA_NUMERIC)
        cameras = [Camera.from_dict(c, where=f"cameras[{i}]") for i, c in enumerate(cams)]
        proj = d.get("projector")
        _check_json_numbers(proj, "projector", _CAMERA_NUMERIC)
        if proj is None:
            projector = None
        elif isinstance(proj, dict) and "calibrated" in proj:
            projector = Projector.from_dict(proj, where="projector")
        else:
            projector = Camera.from_dict(proj, where="projector")
        lights = _lights_from_dict(d.get("lights"), where="lights")
        return cls(cameras, projector, lights)

    def to_json(self) -> str:
        """Pretty, strict JSON text (no NaN/inf literals), newline-terminated."""
        return _json_text(self.to_dict()) + "\n"

    def save(self, path) -> Path:
        """Write the rig to ``path`` as pretty JSON, atomically. Returns the path."""
        path = Path(path)
        atomic_write_text(path, self.to_json())
        return path

    @classmethod
    def load(cls, path) -> Rig:
        """Read a rig written by :meth:`save`.

        Raises
        ------
        facegeo.errors.ScanFormatError
            The file is missing, is not JSON, or has a missing / unknown / bad field; the message
            names the file and the field.
        """
        return load_json_file(path, "rig", cls.from_dict)

    def __eq__(self, other) -> bool:
        return (
            isinstance(other, Rig)
            and self.cameras == other.cameras
            and self.projector == other.projector
            and self.lights == other.lights
        )


# --------------------------------------------------------------------------- default rig

#: Parameters of :func:`default_rig` (degrees / metres / pixels), kept together for reference.
_DEFAULT = {
    "width": 480,
    "height": 720,
    # f ≈ 720 px · 1.1 m / 0.36 m: a 0.30 m head fills ~83 % of the image height at 1.1 m.
    "cameras": [
        # name, yaw about +Y from +Z (deg), distance (m), height (m), fx, fy/fx, cx, cy, dist
        ("cam_left", -15.0, 1.10, 0.035, 2200.0, 1.003, 242.7, 356.1,
         (-0.062, 0.11, 2.5e-4, -1.8e-4, -0.05)),
        ("cam_right", 15.0, 1.12, -0.020, 2236.0, 0.9968, 236.9, 363.4,
         (-0.055, 0.09, -1.6e-4, 2.2e-4, 0.0)),
    ],
    # 1024 × 768 projector; a 0.30 m head spans ~560 of its 768 rows at 1.06 m.
    "projector": ("projector", 1024, 768, (0.0, 0.16, 1.05), 1980.0, 1983.5, 515.3, 395.8),
    "target": (0.0, 0.0, 0.0),
}


def default_rig() -> Rig:
    """A rig shaped like Debevec et al. 2000's light stage, built in code.

    World frame: +Y up, the subject looks along +Z, head centre at the origin, metres. Two
    480 × 720 (portrait) cameras on the +Z side, yawed −15° (``cam_left``, at −X: the left as
    seen from the cameras) and +15° (``cam_right``) about +Y, 1.10 m and 1.12 m from the origin at
    slightly different heights, both aiming at the head centre. Focal lengths (≈ 2200 px) frame a
    0.30 m head; fx ≠ fy by ~0.3 %, principal points a few pixels off-centre, mild distortion
    (under ~1 px at the image corners). Between them a 1024 × 768 projector slightly above the
    +Z axis, its own intrinsics, no distortion. Light stage: 64 × 32 lights at 1.5 m.

    ``calib/default_rig.json`` is this rig written by ``python -m facegeo.geometry.rig``.
    """
    W, H = _DEFAULT["width"], _DEFAULT["height"]
    target = np.asarray(_DEFAULT["target"], dtype=np.float64)
    cameras = []
    for name, yaw_deg, dist_m, height_m, fx, aspect, cx, cy, dist in _DEFAULT["cameras"]:
        yaw = math.radians(yaw_deg)
        eye = np.array([dist_m * math.sin(yaw), height_m, dist_m * math.cos(yaw)])
        K = np.array([[fx, 0.0, cx], [0.0, fx * aspect, cy], [0.0, 0.0, 1.0]])
        cameras.append(Camera(name, W, H, K, np.asarray(dist), look_at(eye, target)))
    pname, pw, ph, peye, pfx, pfy, pcx, pcy = _DEFAULT["projector"]
    Kp = np.array([[pfx, 0.0, pcx], [0.0, pfy, pcy], [0.0, 0.0, 1.0]])
    projector = Camera(pname, pw, ph, Kp, np.zeros(0), look_at(np.asarray(peye), target))
    return Rig(cameras, projector, LightStage(64, 32, 1.5))


def _repo_calib_dir() -> Path:
    return Path(__file__).resolve().parents[2] / "calib"


def write_default_calib(out_dir=None) -> list[Path]:
    """Write ``default_rig.json`` and ``charuco_board.json`` to ``out_dir`` (default: the
    repository's ``calib/``). Returns the paths written."""
    from facegeo.geometry.board import CharucoBoard  # local import: board needs cv2

    out = _repo_calib_dir() if out_dir is None else Path(out_dir)
    return [
        default_rig().save(out / "default_rig.json"),
        CharucoBoard().save(out / "charuco_board.json"),
    ]


def main(argv: list[str] | None = None) -> int:
    """``python -m facegeo.geometry.rig [OUT_DIR]``: regenerate the shipped calibration files."""
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) > 1 or (argv and argv[0] in ("-h", "--help")):
        print("usage: python -m facegeo.geometry.rig [OUT_DIR]   (default: <repo>/calib)")
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    for p in write_default_calib(argv[0] if argv else None):
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
