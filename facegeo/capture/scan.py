"""The scan directory: its ``scan.toml`` manifest, validation, and lazy access to frames.

A real capture rig and the synthetic generator (:mod:`facegeo.synth`) write the same layout,
documented key by key in ``docs/scan-format.md``::

    <scan>/scan.toml                        the manifest (this module's schema, version 2;
                                            version 1 is still read)
    <scan>/rig.json                         cameras, projector, lights (facegeo.geometry.rig)
    calib/board.json, calib/<camera>/view_000.png ..., calib/<camera>/corners.csv
    calib/projector/<camera>/view_00_<frame>.png
    structured_light/<camera>/<frame>.png
    olat/<camera>/0000.exr ...              one per light (or named after it), ambient frame
    reference/...                           real scans: published answers
    ground_truth/...                        synthetic scans only
    out/                                    stage products

:func:`load_scan` parses and validates a scan and returns a :class:`Scan` whose frames are read
(and linearised) only when asked for. :func:`write_manifest` is the writer's counterpart: it
validates a manifest against the schema *and* the files already on disk before writing
``scan.toml``. Both resolve frame paths with :func:`frame_path`, so they cannot disagree.

Loading never writes into the scan directory (only :attr:`Scan.out_dir` creates ``out/``, on
demand).

The schema (key tables, value and template checks, path-safety checks) lives in the private
module :mod:`facegeo.capture._scan_schema`, file resolution and the on-disk frame checks in
:mod:`facegeo.capture._scan_files`, the frame readers in :mod:`facegeo.capture._scan_readers`, the
validation in :mod:`facegeo.capture._scan_validate` and the summary in
:mod:`facegeo.capture._scan_summary`; every public name is importable from here.
"""

from __future__ import annotations

import copy
import functools
import logging
import os
import re
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.capture._scan_files import (
    SATURATED_FRAME_FRACTION,
    CornerView,
    FrameCheck,
    FrameProblem,
    _format_template,
    _Resolver,
    _SuffixFinder,
    board_from_dict,
    frame_path,
    read_corner_list,
)
from facegeo.capture._scan_schema import (
    ANY_SUFFIX,
    READ_VERSIONS,
    V2_KEYS,
    DEFAULT_BOARD,
    DEFAULT_FILES,
    DEFAULT_RESPONSES,
    DEFAULT_RIG,
    FORMAT,
    GROUPS,
    LIGHT_ORDERS,
    TEMPLATE_FIELDS,
    VERSION,
    _err,
    _flatten_ground_truth,
    validate_manifest,
)
from facegeo.capture._scan_summary import summarize  # noqa: F401 (public name)
from facegeo.capture._scan_readers import LUMINANCE_WEIGHTS, _ScanReaders  # noqa: F401
from facegeo.capture._scan_validate import CHECKS, _ScanValidation
from facegeo.checks import check_choice, fmt_value
from facegeo.errors import FacegeoError, InputError, ScanFormatError
from facegeo.fsutil import atomic_write_text
from facegeo.capture.response import Response, parse_response

__all__ = [
    "FORMAT",
    "VERSION",
    "READ_VERSIONS",
    "V2_KEYS",
    "ANY_SUFFIX",
    "LUMINANCE_WEIGHTS",
    "CornerView",
    "MANIFEST_NAME",
    "DEFAULT_RIG",
    "DEFAULT_BOARD",
    "DEFAULT_FILES",
    "DEFAULT_RESPONSES",
    "TEMPLATE_FIELDS",
    "LIGHT_ORDERS",
    "GROUPS",
    "CHECKS",
    "FrameCheck",
    "FrameProblem",
    "SATURATED_FRAME_FRACTION",
    "Scan",
    "load_scan",
    "validate_manifest",
    "write_manifest",
    "new_manifest",
    "frame_path",
    "summarize",
]

log = logging.getLogger(__name__)

MANIFEST_NAME = "scan.toml"


#: A Gray-code frame name of :func:`facegeo.geometry.structured_light.pattern_names`: axis, bit
#: (0 = most significant) and inverse flag; per-camera ``bits_x`` / ``bits_y`` drop bits ≥ n.
_GRAY_FRAME = re.compile(r"^gray_([xy])_(\d+)(_inv)?$")


# =========================================================================== Scan


class Scan(_ScanReaders, _ScanValidation):
    """A validated scan directory with lazy access to its frames.

    Construct with :func:`load_scan`. Frames are read from disk only when asked for and returned
    linear float32 (``docs/conventions.md``, radiometry).

    Attributes
    ----------
    root : Path
        The scan directory (absolute).
    manifest_path : Path
        ``root / "scan.toml"``.
    """

    def __init__(self, root: str | os.PathLike, manifest: Mapping[str, Any], *,
                 manifest_path: str | os.PathLike | None = None):
        self.root = Path(root).absolute()
        self.manifest_path = Path(manifest_path) if manifest_path else self.root / MANIFEST_NAME
        self._m = validate_manifest(manifest, path=self.manifest_path)
        self._gt = (
            _flatten_ground_truth(self._m["ground_truth"], "ground_truth", self.manifest_path, {})
            if "ground_truth" in self._m else None
        )
        self._ref = (
            _flatten_ground_truth(self._m["reference"], "reference", self.manifest_path, {})
            if "reference" in self._m else None
        )
        self._resolve = _Resolver(self.root)
        self._find = _SuffixFinder()
        self._ambient: dict[str, np.ndarray] = {}
        self._responses: dict[str, Response] = {}
        #: What the last :meth:`validate` found on the frame files (None before it ran).
        self.frame_check: FrameCheck | None = None

    def __repr__(self) -> str:
        return f"Scan({self.name!r}, root={str(self.root)!r})"

    def relocated(self, root: str | os.PathLike) -> Scan:
        """This scan read from another folder that holds (some of) its files at the same
        relative paths — a worker's local copy of the frames its task needs, fetched from a
        store (:mod:`facegeo.pipeline._scan_store`). The manifest, the rig and the responses
        already read are shared, not read again; every path resolves under ``root``."""
        other = copy.copy(self)
        other.root = Path(root).absolute()
        other.manifest_path = other.root / MANIFEST_NAME
        other._resolve = _Resolver(other.root)
        other._find = _SuffixFinder()
        other._ambient = dict(self._ambient)
        other._responses = dict(self._responses)
        return other

    # ------------------------------------------------------------------ manifest

    @property
    def manifest(self) -> dict:
        """The normalised manifest (defaults filled in), a deep copy."""
        return copy.deepcopy(self._m)

    @property
    def name(self) -> str:
        """``scan.name``."""
        return self._m["scan"]["name"]

    @property
    def version(self) -> int:
        """``scan.version``: 1 or 2 (both read; :func:`new_manifest` writes 2)."""
        return int(self._m["scan"]["version"])

    @property
    def synthetic(self) -> bool:
        """``scan.synthetic``: True for scans written by :mod:`facegeo.synth`."""
        return bool(self._m["scan"]["synthetic"])

    @property
    def description(self) -> str:
        """``scan.description``."""
        return self._m["scan"].get("description", "")

    def has(self, group: str) -> bool:
        """Whether the scan holds a frame group (``"calib"``, ``"calib.projector"``,
        ``"structured_light"``, ``"olat"``) or ``"ground_truth"``."""
        check_choice(group, "group", GROUPS + ("ground_truth",))
        if group == "calib.projector":
            return "projector" in self._m.get("calib", {})
        return group in self._m

    @property
    def groups(self) -> tuple[str, ...]:
        """The frame groups present, in :data:`GROUPS` order."""
        return tuple(g for g in GROUPS if self.has(g))

    def _section(self, group: str) -> dict:
        if not self.has(group):
            raise _err(f"this scan has no [{group}] section", key=group, path=self.manifest_path)
        if group == "calib.projector":
            return self._m["calib"]["projector"]
        return self._m[group]

    # ------------------------------------------------------------------ rig, board, responses

    @functools.cached_property
    def rig(self):
        """The scan's :class:`facegeo.geometry.rig.Rig` (loaded on first use)."""
        from facegeo.geometry.rig import Rig

        rel = self._m["scan"]["rig"]
        p = self._resolve(rel, key="scan.rig", where=self.manifest_path)
        if not p.is_file():
            raise _err(
                f"rig file not found: {p} (scan.rig = {fmt_value(rel)})",
                key="scan.rig",
                path=self.manifest_path,
            )
        try:
            return Rig.load(p)
        except ScanFormatError:
            raise
        except (FacegeoError, ValueError, KeyError, TypeError, OSError) as exc:
            raise _err(f"cannot load the rig: {exc}", key="scan.rig", path=p) from exc

    @property
    def camera_names(self) -> list[str]:
        """Names of the rig's cameras, in rig order (every group has frames for each)."""
        return [c.name for c in self.rig.cameras]

    def camera(self, name: str):
        """The rig's :class:`facegeo.geometry.camera.Camera` called ``name`` (error lists the valid ones)."""
        return self.rig.camera(name)

    @functools.cached_property
    def board(self):
        """The calibration board, loaded on first use: a
        :class:`facegeo.geometry.board.CharucoBoard`, or (``kind = "chessboard"`` /
        ``"circles"``, in ``board.json`` or inline in ``calib.board``) a
        :class:`~facegeo.geometry._calib_detect.ChessboardSpec` /
        :class:`~facegeo.geometry._calib_detect.CircleGridSpec`."""
        from facegeo.fsutil import load_json_file

        spec = self._section("calib")["board"]
        if isinstance(spec, Mapping):
            return board_from_dict(spec, self.manifest_path)
        p = self._resolve(spec, key="calib.board", where=self.manifest_path)
        if not p.is_file():
            raise _err(f"board file not found: {p}", key="calib.board", path=self.manifest_path)
        try:
            return load_json_file(p, "board", lambda d: board_from_dict(d, p))
        except ScanFormatError:
            raise
        except (FacegeoError, ValueError, KeyError, TypeError, OSError) as exc:
            raise _err(f"cannot load the board: {exc}", key="calib.board", path=p) from exc

    @property
    def board_kind(self) -> str:
        """``"charuco"``, ``"chessboard"`` or ``"circles"`` (reads the board)."""
        from facegeo.geometry._calib_detect import ChessboardSpec

        b = self.board
        if isinstance(b, ChessboardSpec):
            return "chessboard"
        return "circles" if hasattr(b, "spacing") else "charuco"

    def response(self, group: str) -> Response:
        """The declared :class:`~facegeo.capture.imageio.Response` of a frame group
        (``calib.projector`` frames: ``calib.projector.response`` when declared — board
        Gray-code frames may be float EXR beside 8-bit sRGB board photos — else
        ``calib.response``)."""
        sect = group
        if group == "calib.projector" and self._section(group).get("response") is None:
            sect = "calib"
        r = self._responses.get(sect)
        if r is None:
            spec = self._section(sect)["response"]
            key = f"{sect}.response"
            if isinstance(spec, Mapping) and spec.get("kind") == "table":
                self._resolve(spec["file"], key=f"{key}.file", where=self.manifest_path)
            r = parse_response(spec, base_dir=self.root, key=key, path=self.manifest_path)
            self._responses[sect] = r
        return r

    # ------------------------------------------------------------------ paths

    def _path(self, group: str, key: str = "files", **fields: Any) -> Path:
        template = self._section(group)[key]
        k = f"{group}.{key}"
        # The v2 alternatives of the group's item field ({index}, {number}, {light_name});
        # str.format ignores the fields a template does not use.
        if group in ("calib", "calib.projector") and "view" in fields:
            # the fields the description declares per view ({pose} ...), by the view's index
            for name, vals in (self._section(group).get("fields") or {}).items():
                fields[name] = vals[fields["view"]] if isinstance(vals, list) else vals
        if group == "calib" and "view" in fields:
            fields.update(index=fields["view"], number=fields["view"] + 1)
        elif group == "calib.projector" and "frame" in fields:
            i = {f: i for i, f in enumerate(self.projector_frames)}.get(fields["frame"], 0)
            fields.update(index=i, number=i + 1)
        elif group == "structured_light" and "frame" in fields:
            i = self._frame_positions.get(fields["frame"], 0)
            fields.update(index=i, number=i + 1)
        elif group == "olat" and "light" in fields:
            fields.update(index=fields["light"], number=fields["light"] + 1)
        return self._find(self._resolve(_format_template(template, fields), key=k), k)

    @functools.cached_property
    def _frame_positions(self) -> dict[str, int]:
        return {f: i for i, f in enumerate(self._section("structured_light")["frames"])}

    # ------------------------------------------------------------------ per-camera frames

    def _cam_table(self, group: str, camera: str) -> dict:
        return self._section(group).get("cameras", {}).get(camera, {})

    def _all_keys(self, group: str) -> list:
        sect = self._section(group)
        if group == "calib":
            return list(range(sect["views"]))
        if group == "calib.projector":
            return [(v, f) for v in range(sect["views"]) for f in self.projector_frames]
        if group == "structured_light":
            return list(sect["frames"])
        return list(range(sect["n_lights"]))

    def _declared_missing(self, group: str, camera: str) -> set:
        """Keys a camera lacks by declaration (``missing``, ``views``, ``bits_x``/``bits_y``)."""
        t = self._cam_table(group, camera)
        sect = self._section(group)
        out: set = set()
        if group in ("calib", "calib.projector"):
            n = sect["views"]
            views = set(t["views"]) if "views" in t else set(range(n)) - set(t.get("missing", ()))
            gone = set(range(n)) - views
            if group == "calib":
                return gone
            return {(v, f) for v in gone for f in self.projector_frames}
        if group == "structured_light":
            out = set(t.get("missing", ()))
            for axis in ("x", "y"):
                bits = t.get(f"bits_{axis}")
                if bits is None:
                    continue
                for f in sect["frames"]:
                    m = _GRAY_FRAME.match(f)
                    if m and m.group(1) == axis and int(m.group(2)) >= bits:
                        out.add(f)
            return out
        for x in t.get("missing", ()):
            out.add(self._light_index(x) if isinstance(x, str) else x)
        return out

    def camera_frames(self, group: str, camera: str) -> list:
        """The frames of ``group`` that ``camera`` has, in order.

        Keys are view indices (``"calib"``), ``(view, frame)`` pairs (``"calib.projector"``),
        frame names (``"structured_light"``) or light indices (``"olat"``). A camera lacks a
        frame when its ``[<group>.cameras.<camera>]`` table lists it in ``missing``, leaves its
        view out of ``views``, or (structured light) the frame codes a Gray bit at or beyond the
        camera's ``bits_x`` / ``bits_y``.
        """
        self._check_camera(camera)
        gone = self._declared_missing(group, camera)
        return [k for k in self._all_keys(group) if k not in gone]

    def cameras_with_frames(self, group: str) -> list[str]:
        """The cameras that have at least one frame of ``group``, in rig order: a camera that
        declares every frame of the group missing (a calibration-only camera, seen in the
        board views alone) is left out. Empty when the scan has no such group."""
        if not self.has(group):
            return []
        keys = set(self._all_keys(group))
        return [c for c in self.camera_names if keys - self._declared_missing(group, c)]

    def missing_frames(self, group: str, camera: str) -> list:
        """The frames of ``group`` that ``camera`` lacks (see :meth:`camera_frames`)."""
        self._check_camera(camera)
        gone = self._declared_missing(group, camera)
        return [k for k in self._all_keys(group) if k in gone]

    def _frame_check(self, group: str, camera: str, key: Any, what: str) -> None:
        if key in self._declared_missing(group, camera):
            raise InputError(f"{what}: camera {camera!r} has no such frame ({group}.cameras."
                             f"{camera} declares it missing); use Scan.camera_frames")

    def _check_camera(self, camera: str) -> None:
        if camera not in self.camera_names:
            check_choice(camera, "camera", self.camera_names)

    @property
    def n_lights(self) -> int:
        """``olat.n_lights``."""
        return int(self._section("olat")["n_lights"])

    @property
    def lights(self):
        """The rig's lights: a :class:`~facegeo.geometry.rig.LightStage`, a
        :class:`~facegeo.geometry.lights.LightList`, or None (no light stage)."""
        return getattr(self.rig, "lights", None)

    @property
    def light_names(self) -> list[str] | None:
        """Names of the lights of a light list (None for the grid or no lights)."""
        names = getattr(self.lights, "names", None)
        return None if names is None else list(names)

    def _light_index(self, light: Any) -> int:
        if isinstance(light, str):
            names = self.light_names
            if names is None:
                raise InputError(f"light: {fmt_value(light)} is a light name, but the rig's "
                                 "lights have no names (only a light list has)")
            if light not in names:
                shown = ", ".join(names[:6]) + (", ..." if len(names) > 6 else "")
                raise InputError(f"light: no light named {fmt_value(light)}; names: {shown}")
            return names.index(light)
        return self._check_light(light)

    def _olat_file_number(self, light: int) -> int:
        order = self._section("olat")["light_order"]
        if order == "theta-fastest" or not hasattr(self.rig.lights, "n_theta"):
            return light
        lights = self.rig.lights
        i, j = light % lights.n_theta, light // lights.n_theta
        return i * lights.n_phi + j

    def _check_light(self, light: Any) -> int:
        if isinstance(light, (bool, np.bool_)) or not isinstance(light, (int, np.integer)):
            raise InputError(f"light: expected an integer light index, got {fmt_value(light)}")
        n = self.n_lights
        if not 0 <= int(light) < n:
            raise InputError(f"light: index {int(light)} out of range [0, {n})")
        return int(light)

    def olat_path(self, camera: str, light: int) -> Path:
        """Path of the OLAT frame of ``camera`` lit by light ``light``.

        ``light`` is the library's light index ``l = j·n_theta + i`` (``docs/conventions.md``);
        ``olat.light_order`` maps it to the file number.
        """
        self._check_camera(camera)
        light = self._light_index(light)
        self._frame_check("olat", camera, light, f"light {light}")
        return self._olat_file(camera, light)

    def _olat_file(self, camera: str, light: int) -> Path:
        names = getattr(self.lights, "names", None)
        fields = {"light": self._olat_file_number(light)}
        if names is not None:
            fields["light_name"] = names[light]
        return self._path("olat", camera=camera, **fields)

    def ambient_path(self, camera: str) -> Path | None:
        """Path of ``camera``'s ambient frame (``olat.ambient``; None when the scan has none)."""
        self._check_camera(camera)
        if "ambient" not in self._section("olat"):
            return None
        return self._path("olat", "ambient", camera=camera)

    def sl_path(self, camera: str, frame: str) -> Path:
        """Path of structured-light frame ``frame`` of ``camera``."""
        self._check_camera(camera)
        check_choice(frame, "frame", self.sl_frames)
        self._frame_check("structured_light", camera, frame, f"frame {frame!r}")
        return self._path("structured_light", camera=camera, frame=frame)

    def calib_views(self, camera: str) -> list[int]:
        """The calibration views ``camera`` has (``calib.cameras.<camera>``), in order."""
        return self.camera_frames("calib", camera)

    @property
    def calib_images(self) -> bool:
        """``calib.images``: whether the calibration views have image files (v1: always)."""
        return bool(self._section("calib").get("images", True))

    def calib_view_paths(self, camera: str) -> list[Path]:
        """Paths of the calibration-board views ``camera`` has, in view order (see
        :meth:`calib_views` for their view indices; empty with ``calib.images = false``)."""
        if not self.calib_images:
            self._check_camera(camera)
            return []
        return [self._path("calib", camera=camera, view=v) for v in self.calib_views(camera)]

    def calib_corners(self, camera: str) -> dict[int, CornerView]:
        """``camera``'s corner list (``calib.corners``): ``{view: CornerView}``, one entry per
        view in which corners were found (a subset of :meth:`calib_views`)."""
        self._check_camera(camera)
        if "corners" not in self._section("calib"):
            raise _err("this scan has no corner lists (calib.corners)", key="calib.corners",
                       path=self.manifest_path)
        p = self._path("calib", "corners", camera=camera)
        corners = read_corner_list(p)
        views = set(self.calib_views(camera))
        extra = sorted(set(corners) - views)
        if extra:
            raise _err(f"the corner list has view {extra[0]}, which camera {camera!r} does not "
                       f"have (calib.views = {self._section('calib')['views']}, this camera's "
                       f"views: {sorted(views)})", key="calib.corners", path=p)
        return corners

    @property
    def projector_frames(self) -> list[str]:
        """Frame names of the projector-calibration captures: ``calib.projector.frames`` when
        given (v2), else :attr:`sl_frames`."""
        cp = self._section("calib.projector")
        return list(cp["frames"]) if "frames" in cp else self.sl_frames

    def projector_view_paths(self, camera: str, view: int) -> dict[str, Path]:
        """Paths of the board seen by ``camera`` in projector-calibration view ``view`` under
        every pattern: ``{frame name: path}`` in :attr:`projector_frames` order."""
        self._check_camera(camera)
        n = self._section("calib.projector")["views"]
        if isinstance(view, bool) or not isinstance(view, (int, np.integer)) or not 0 <= view < n:
            raise InputError(f"view: expected an integer in [0, {n}), got {fmt_value(view)}")
        frames = self.projector_frames
        self._frame_check("calib.projector", camera, (int(view), frames[0]), f"view {view}")
        return {
            f: self._path("calib.projector", camera=camera, view=int(view), frame=f)
            for f in frames
        }

    @property
    def sl_frames(self) -> list[str]:
        """Structured-light frame names, in capture order."""
        return list(self._section("structured_light")["frames"])

    @property
    def sl_patterns(self) -> dict:
        """The pattern spec (``[structured_light.patterns]``), a deep copy, with the projector's
        ``width`` / ``height`` from the rig filled in when the table is non-empty and omits
        them; ``PatternSpec.from_dict`` accepts it."""
        return self._patterns("structured_light")

    def _patterns(self, group: str) -> dict:
        pat = copy.deepcopy(self._section(group).get("patterns") or {})
        if pat:
            proj = getattr(self.rig, "projector", None)
            if proj is not None:
                pat.setdefault("width", proj.width)
                pat.setdefault("height", proj.height)
        return pat

    def pattern_spec(self, group: str = "structured_light"):
        """The :class:`~facegeo.geometry.structured_light.PatternSpec` of ``group``
        (``"structured_light"`` or ``"calib.projector"``; the latter falls back to the former),
        or None when the group declares no patterns."""
        from facegeo.geometry.structured_light import PatternSpec

        if group == "calib.projector" and "patterns" not in self._section(group):
            if not self.has("structured_light"):
                return None
            group = "structured_light"
        pat = self._patterns(group)
        if not pat:
            return None
        try:
            return PatternSpec.from_dict(pat)
        except InputError as exc:
            raise _err(f"{exc}", key=f"{group}.patterns", path=self.manifest_path) from exc

    def sl_bits(self, camera: str) -> dict[str, int]:
        """Gray-code bits ``camera`` resolves per axis: ``{"x": n, "y": n}`` (the camera's
        ``bits_x`` / ``bits_y`` or the pattern spec's; needs ``patterns``)."""
        self._check_camera(camera)
        spec = self.pattern_spec()
        if spec is None:
            raise _err("no pattern spec: [structured_light.patterns] is empty",
                       key="structured_light.patterns", path=self.manifest_path)
        t = self._cam_table("structured_light", camera)
        return {a: int(t.get(f"bits_{a}", spec.n_bits(a))) for a in ("x", "y")}

    @property
    def sl_projector(self) -> str:
        """``structured_light.projector``: the rig's projector name."""
        return self._section("structured_light")["projector"]

    @property
    def world(self) -> dict | None:
        """``scan.world`` (v2), or None: ``{"camera": name, "board_view": v}`` (the world frame
        is the board's frame in that view as that camera saw it) or ``{"T_world_rig": (4, 4)
        float64}`` (``p_world = T_world_rig · p_rig``, metres)."""
        w = self._m["scan"].get("world")
        if w is None:
            return None
        if "transform" in w:
            return {"T_world_rig": np.asarray(w["transform"], dtype=np.float64)}
        return dict(w)

    @property
    def reference_keys(self) -> list[str]:
        """Dotted keys of the ``[reference]`` entries (v2; reference answers of a real scan)."""
        return list(self._ref or {})

    def reference_path(self, key: str) -> Path:
        """Path of reference entry ``key`` (``"point_cloud"``, ``"intrinsics.cam_a"``)."""
        flat = self._ref
        if flat is None or key not in flat:
            raise _err(f"no reference entry {fmt_value(key)}; entries: "
                       f"{', '.join(flat or {}) or '(none)'}", key=f"reference.{key}",
                       path=self.manifest_path)
        return self._resolve(flat[key], key=f"reference.{key}", where=self.manifest_path)

    @property
    def ground_truth_keys(self) -> list[str]:
        """Dotted keys of the ``[ground_truth]`` entries (empty for real scans)."""
        return list(self._gt or {})

    def ground_truth_path(self, key: str) -> Path:
        """Path of ground-truth entry ``key`` (dotted for nested tables, ``"maps.albedo"``)."""
        flat = self._gt
        if flat is None:
            raise _err("this scan has no [ground_truth] section", key="ground_truth",
                       path=self.manifest_path)
        if key not in flat:
            raise _err(
                f"no ground-truth entry {fmt_value(key)}; entries: {', '.join(flat) or '(none)'}",
                key=f"ground_truth.{key}",
                path=self.manifest_path,
            )
        return self._resolve(flat[key], key=f"ground_truth.{key}", where=self.manifest_path)

    def input_files(self) -> list[Path]:
        """Every input file the manifest names, in a stable order: the rig, a board file,
        response tables, corner lists, every expected frame of every camera (each ``.*`` frame
        resolved to its file), references and ground-truth entries (directories as such).

        Used by :func:`facegeo.capture.importer.import_folder` to carry a scan's files over.
        """
        out = [self._resolve(self._m["scan"]["rig"], key="scan.rig", where=self.manifest_path)]
        if self.has("calib") and isinstance(self._m["calib"]["board"], str):
            out.append(self._resolve(self._m["calib"]["board"], key="calib.board",
                                     where=self.manifest_path))
        for sect in ("calib", "structured_light", "olat"):
            spec = self._m.get(sect, {}).get("response")
            if isinstance(spec, Mapping) and spec.get("kind") == "table":
                out.append(self._resolve(spec["file"], key=f"{sect}.response.file",
                                         where=self.manifest_path))
        cams = self.camera_names
        if self.has("calib") and "corners" in self._section("calib"):
            out += [self._path("calib", "corners", camera=c) for c in cams if self.calib_views(c)]
        for group in self.groups:
            for c in cams:
                out += [p for _, p in self.expected_files(group, c)]
        out += [self.reference_path(k) for k in self.reference_keys]
        out += [self.ground_truth_path(k) for k in self.ground_truth_keys]
        seen: set[Path] = set()
        return [p for p in out if not (p in seen or seen.add(p))]

    @property
    def out_dir(self) -> Path:
        """``root / "out"``, created on first access (the only place facegeo writes)."""
        d = self.root / "out"
        d.mkdir(exist_ok=True)
        return d

    # ------------------------------------------------------------------ frames

    def expected_files(self, group: str, camera: str) -> list[tuple[str, Path]]:
        """Every file a group should hold for ``camera``: ``[(label, path), ...]`` in order
        (the frames :meth:`camera_frames` lists; OLAT adds the ambient frame, if any)."""
        keys = self.camera_frames(group, camera)
        if group == "calib":
            if not self.calib_images:
                return []
            return [(f"view {v}", self._path(group, camera=camera, view=v)) for v in keys]
        if group == "calib.projector":
            return [(f"view {v} frame {f!r}", self._path(group, camera=camera, view=v, frame=f))
                    for v, f in keys]
        if group == "structured_light":
            return [(f"frame {f!r}", self._path(group, camera=camera, frame=f)) for f in keys]
        out = []
        names = self.light_names
        for light in keys:
            k = self._olat_file_number(light)
            label = f"light {light}" + (f" (file number {k})" if k != light else "")
            if names is not None:
                label += f" ({names[light]!r})"
            out.append((label, self._olat_file(camera, light)))
        amb = self.ambient_path(camera)
        if amb is not None:
            out.append(("ambient frame", amb))
        return out


def _read_manifest(path: Path) -> dict:
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise _err(f"cannot read the manifest ({exc.strerror or exc})", path=path) from exc
    try:
        return tomllib.loads(text.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise _err(f"the manifest is not UTF-8 text ({exc})", path=path) from exc
    except tomllib.TOMLDecodeError as exc:
        raise _err(f"TOML syntax error: {exc}", path=path) from exc


def load_scan(path: str | os.PathLike, *, check: str = "quick") -> Scan:
    """Open and validate a scan directory.

    Parameters
    ----------
    path : path-like
        The scan directory, or its ``scan.toml``.
    check : {"quick", "full"}
        How much to check (see :meth:`Scan.validate`).

    Returns
    -------
    Scan

    Raises
    ------
    ScanFormatError
        Missing directory or ``scan.toml``, a TOML syntax error (with its line), or any
        problem :func:`validate_manifest` and :meth:`Scan.validate` find.
    """
    check_choice(check, "check", CHECKS)
    p = Path(path)
    if p.is_dir():
        root, toml = p, p / MANIFEST_NAME
    elif p.is_file() and p.suffix.lower() != ".toml":
        raise _err("not a directory: a scan is a directory holding scan.toml (give the "
                   "directory, or its scan.toml)", path=p)
    elif p.is_file():
        root, toml = p.parent, p
    else:
        raise _err("scan directory not found", path=p)
    if not toml.is_file():
        raise _err(
            f"no {MANIFEST_NAME} in this directory; a scan directory starts with its manifest "
            "(see docs/scan-format.md)",
            path=toml,
        )
    scan = Scan(root, _read_manifest(toml), manifest_path=toml)
    scan.validate(check)
    log.debug("loaded scan %r from %s (%s check)", scan.name, scan.root, check)
    return scan


def new_manifest(name: str, *, synthetic: bool, description: str = "") -> dict:
    """A skeleton manifest with only the ``[scan]`` section; add frame groups to it.

    Examples
    --------
    >>> m = new_manifest("demo", synthetic=True)
    >>> m["olat"] = {"n_lights": 2048, "files": DEFAULT_FILES["olat"]}
    """
    if not isinstance(name, str) or not name.strip():
        raise InputError(f"name: expected a non-empty string, got {fmt_value(name)}")
    return {
        "scan": {
            "format": FORMAT,
            "version": VERSION,
            "name": name,
            "synthetic": bool(synthetic),
            "description": description,
            "rig": DEFAULT_RIG,
        }
    }


def write_manifest(root: str | os.PathLike, manifest: Mapping[str, Any], *,
                   overwrite: bool = False) -> Path:
    """Validate a manifest against the schema and the files already written, then write
    ``root / "scan.toml"`` atomically.

    Write every frame, the rig and the board first: the manifest goes last, so a scan with a
    ``scan.toml`` is complete. The file written is the normalised manifest (defaults spelled
    out), so a later change of default cannot change what an old scan means.

    Parameters
    ----------
    root : path-like
        The scan directory.
    manifest : dict
        See ``docs/scan-format.md``; :func:`new_manifest` gives a skeleton.
    overwrite : bool
        Replace an existing ``scan.toml``. Off by default: inputs are never overwritten.

    Returns
    -------
    Path
        The manifest's path.

    Raises
    ------
    ScanFormatError
        ``scan.toml`` exists and ``overwrite`` is false, or the manifest or the files fail the
        quick check of :meth:`Scan.validate`.
    """
    root = Path(root)
    target = root / MANIFEST_NAME
    if target.exists() and not overwrite:
        raise _err(
            "already exists; refusing to overwrite a scan's manifest (pass overwrite=True to "
            "replace it)",
            path=target,
        )
    scan = Scan(root, manifest, manifest_path=target)
    scan.validate("quick")
    import tomli_w  # deferred

    try:
        text = tomli_w.dumps(scan.manifest)
    except (TypeError, ValueError) as exc:
        raise _err(f"the manifest cannot be written as TOML: {exc}", path=target) from exc
    header = (
        f"# facegeo scan manifest, format {FORMAT} version {scan.version}; see "
        "docs/scan-format.md\n"
    )
    atomic_write_text(target, header + text)
    log.debug("wrote %s", target)
    return target


# =========================================================================== summary
