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
:mod:`facegeo.capture._scan_files`; every public name is importable from here.
"""

from __future__ import annotations

import copy
import functools
import logging
import os
import re
import tomllib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.capture._scan_files import (
    SATURATED_FRAME_FRACTION,
    CornerView,
    FrameCheck,
    FrameProblem,
    _check_group_files,
    _format_template,
    _Resolver,
    _size_error,
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
from facegeo.checks import check_choice, fmt_value
from facegeo.errors import FacegeoError, InputError, ScanFormatError
from facegeo.fsutil import atomic_write_text
from facegeo.capture.imageio import read_image
from facegeo.capture.response import Response, clipped_mask, parse_response, saturated_mask

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

CHECKS = ("quick", "full")

#: Linear-RGB → luminance weights (Rec. 709 / sRGB primaries, the library's RGB; ITU-R BT.709
#: item 3.2), used by the ``luminance=True`` readers.
LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)

#: A Gray-code frame name of :func:`facegeo.geometry.structured_light.pattern_names`: axis, bit
#: (0 = most significant) and inverse flag; per-camera ``bits_x`` / ``bits_y`` drop bits ≥ n.
_GRAY_FRAME = re.compile(r"^gray_([xy])_(\d+)(_inv)?$")


def _luminance(lin: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 luminance of a linear frame (grey frames pass through)."""
    if lin.ndim == 2:
        return lin
    return np.dot(lin[..., :3], LUMINANCE_WEIGHTS).astype(np.float32, copy=False)


# =========================================================================== Scan


class Scan:
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
        (``calib.projector`` frames use ``calib.response``)."""
        sect = "calib" if group == "calib.projector" else group
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
        if group == "calib" and "view" in fields:
            fields.update(index=fields["view"], number=fields["view"] + 1)
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

    def _read(self, group: str, camera: str, path: Path, *, return_mask: bool):
        raw = read_image(path)
        cam = self.camera(camera)
        h, w = raw.shape[:2]
        if (w, h) != (cam.width, cam.height):
            raise _size_error(path, group, camera, (w, h), (cam.width, cam.height))
        try:
            lin = self.response(group).linearize(raw)
        except InputError as exc:
            raise _err(f"{exc}", key=f"{group}.response", path=path) from exc
        if not return_mask:
            return lin, None
        if raw.dtype.kind == "f":
            valid = np.isfinite(raw) if raw.ndim == 2 else np.isfinite(raw).all(axis=-1)
        else:
            valid = ~(saturated_mask(raw) | clipped_mask(raw))
        return lin, valid

    def olat_frame(self, camera: str, light: int | str, *, return_mask: bool = False,
                   subtract_ambient: bool = False):
        """One OLAT frame, linear.

        Parameters
        ----------
        camera : str
        light : int or str
            Light index (``l = j·n_theta + i`` for the grid; the list position for a light
            list) or a light list's light name.
        return_mask : bool
            Also return where the samples can be trusted.
        subtract_ambient : bool
            Subtract :meth:`ambient_frame` (needs ``olat.ambient``). The difference is not
            clipped: noise leaves small negative values where a light adds nothing.

        Returns
        -------
        frame : (H, W, 3) float32, linear radiance
            The linearised pixel values divided by ``[olat] exposure``. Grey frames are
            repeated to three channels; alpha is dropped.
        valid : (H, W) bool, only with ``return_mask``
            False where a sample is saturated or black-clipped (integer frames) or non-finite
            (float frames).
        """
        lin, valid = self._olat_read(camera, self.olat_path(camera, light), return_mask)
        if subtract_ambient:
            lin = lin - self.ambient_frame(camera)
        return (lin, valid) if return_mask else lin

    def _olat_read(self, camera: str, path: Path, return_mask: bool):
        lin, valid = self._read("olat", camera, path, return_mask=return_mask)
        exposure = float(self._section("olat").get("exposure", 1.0))
        if exposure != 1.0:
            lin = lin / np.float32(exposure)
        if lin.ndim == 2:
            lin = np.repeat(lin[..., None], 3, axis=-1)
        elif lin.shape[-1] == 4:
            lin = np.ascontiguousarray(lin[..., :3])
        return lin, valid

    def ambient_frame(self, camera: str) -> np.ndarray:
        """``camera``'s ambient frame (no light on), ``(H, W, 3)`` float32 linear, divided by
        ``olat.exposure`` like the OLAT frames; read once and cached.

        Raises
        ------
        ScanFormatError
            The scan declares no ``olat.ambient``.
        """
        a = self._ambient.get(camera)
        if a is None:
            p = self.ambient_path(camera)
            if p is None:
                raise _err("this scan has no ambient frame (olat.ambient)", key="olat.ambient",
                           path=self.manifest_path)
            a = self._olat_read(camera, p, False)[0]
            a.setflags(write=False)
            self._ambient[camera] = a
        return a

    def iter_olat(self, camera: str, lights: Sequence[int] | None = None, *,
                  return_mask: bool = False, subtract_ambient: bool = False) -> Iterator[tuple]:
        """Yield ``(light, frame)`` (or ``(light, frame, valid)``) for ``lights`` (default the
        lights ``camera`` has, in light-index order), reading one frame at a time."""
        for light in self.camera_frames("olat", camera) if lights is None else lights:
            out = self.olat_frame(camera, light, return_mask=return_mask,
                                  subtract_ambient=subtract_ambient)
            yield (light, *out) if return_mask else (light, out)

    def sl_frame(self, camera: str, frame: str, *, return_mask: bool = False,
                 luminance: bool = False):
        """One structured-light frame, linear.

        Parameters
        ----------
        camera, frame : str
        return_mask : bool
            Also return where the samples can be trusted.
        luminance : bool
            Return single-channel luminance ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` of the
            linear frame (:data:`LUMINANCE_WEIGHTS`): a third of the memory of RGB, all a
            Gray-code or phase decoder needs.

        Returns
        -------
        frame : (H, W) or (H, W, 3) float32, linear, channels as stored (alpha dropped);
            ``(H, W)`` with ``luminance``
        valid : (H, W) bool, only with ``return_mask`` (see :meth:`olat_frame`)
        """
        return self._sl_like("structured_light", camera, self.sl_path(camera, frame),
                             return_mask, luminance)

    def _sl_like(self, group, camera, path, return_mask, luminance):
        lin, valid = self._read(group, camera, path, return_mask=return_mask)
        if luminance:
            lin = _luminance(lin)
        elif lin.ndim == 3 and lin.shape[-1] == 4:
            lin = np.ascontiguousarray(lin[..., :3])
        return (lin, valid) if return_mask else lin

    def iter_sl(self, camera: str, frames: Sequence[str] | None = None, *,
                luminance: bool = False, return_mask: bool = False) -> Iterator[tuple]:
        """Yield ``(name, frame)`` (or ``(name, frame, valid)``) for ``frames`` (default the
        frames ``camera`` has, in capture order), reading one frame at a time: only the frame
        being yielded is held, so a decoder that accumulates bit planes never holds the group.
        See :meth:`sl_frame` for ``luminance``."""
        for name in self.camera_frames("structured_light", camera) if frames is None else frames:
            out = self.sl_frame(camera, name, return_mask=return_mask, luminance=luminance)
            yield (name, *out) if return_mask else (name, out)

    def projector_frame(self, camera: str, view: int, frame: str, *, return_mask: bool = False,
                        luminance: bool = False):
        """One projector-calibration frame (the board in view ``view`` under pattern
        ``frame``), linearised with ``calib.response``; see :meth:`sl_frame` for the options."""
        paths = self.projector_view_paths(camera, view)
        check_choice(frame, "frame", list(paths))
        return self._sl_like("calib.projector", camera, paths[frame], return_mask, luminance)

    def iter_projector(self, camera: str, view: int, *, luminance: bool = False,
                       return_mask: bool = False) -> Iterator[tuple]:
        """Yield ``(name, frame)`` over the patterns of projector-calibration view ``view``,
        one frame at a time (see :meth:`projector_frame`)."""
        for name in self.projector_frames:
            out = self.projector_frame(camera, view, name, return_mask=return_mask,
                                       luminance=luminance)
            yield (name, *out) if return_mask else (name, out)

    # ------------------------------------------------------------------ validation

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

    def validate(self, check: str = "quick") -> Scan:
        """Check the scan against its rig and the files on disk.

        Parameters
        ----------
        check : {"quick", "full"}
            ``"quick"``: the rig (and its cross-checks), response tables, ground-truth entries,
            that every expected frame exists inside the scan, and the header of **every**
            frame, read without decoding pixels: size against the rig, channel count, sample
            type against the declared response and against the group's first frame, and a file
            that ends before its data does (truncated; see
            :func:`~facegeo.capture.imageio.read_image_info`). ``"full"``: additionally the
            board file, and a decode of every frame whose pixels are checked: NaN or inf are
            errors; negative radiance, an all-black frame and a mostly saturated one are
            warnings, kept in :attr:`frame_check` and not raised.

        Returns
        -------
        Scan
            ``self``.

        Raises
        ------
        ScanFormatError
            The first problem found, naming the file and/or key and what would be right (with
            the number and first names of the other frames that fail).

        Notes
        -----
        After the frame checks ran, :attr:`frame_check` (a
        :class:`~facegeo.capture._scan_files.FrameCheck`) says how many headers were read, how
        many frames decoded, and lists every problem per frame, warnings included.
        """
        check_choice(check, "check", CHECKS)
        where = self.manifest_path
        rig = self.rig
        cameras = list(rig.cameras)
        if self.groups and not cameras:
            raise _err(
                "the rig has no cameras, but the scan lists frames", key="scan.rig", path=where
            )
        names = [c.name for c in cameras]
        if len(names) > 1:
            for group in self.groups:
                for k in ("files", "ambient", "corners"):
                    t = self._section(group).get(k)
                    if isinstance(t, str) and "{camera" not in t:
                        raise _err(f"template {t!r} has no {{camera}} but the rig has "
                                   f"{len(names)} cameras, whose files would collide; only a "
                                   "one-camera rig may leave {camera} out",
                                   key=f"{group}.{k}", path=where)
        if len(set(names)) != len(names):
            raise _err(
                f"the rig's camera names are not unique: {names}", key="scan.rig", path=where
            )
        if self.has("olat"):
            self._validate_olat(rig, where)
        if self.has("structured_light"):
            proj = getattr(rig, "projector", None)
            if proj is None:
                raise _err(
                    "[structured_light] is present but the rig has no projector",
                    key="structured_light.projector",
                    path=where,
                )
            if self.sl_projector != proj.name:
                raise _err(
                    f"projector = {fmt_value(self.sl_projector)} but the rig's projector is {fmt_value(proj.name)}",
                    key="structured_light.projector",
                    path=where,
                )
        for sect in ("calib", "structured_light", "olat"):
            if self.has(sect):
                self.response(sect)
        self._validate_cameras_tables(names, where)
        if self.has("structured_light"):
            self._validate_patterns("structured_light", self.sl_frames, where)
        if self.has("calib.projector") and "frames" in self._section("calib.projector"):
            self._validate_patterns("calib.projector", self.projector_frames, where)
        self._validate_world(names, where)
        if self.has("calib") and "corners" in self._section("calib"):
            for cam in names:
                if self.calib_views(cam):  # a camera that saw no view needs no corner list
                    self.calib_corners(cam)
        for key in self.reference_keys:
            p = self.reference_path(key)
            if not p.exists():
                raise _err(f"reference file not found: {p}", key=f"reference.{key}", path=where)
        if self.has("calib"):
            spec = self._m["calib"]["board"]
            if isinstance(spec, str):
                board = self._resolve(spec, key="calib.board", where=where)
                if not board.is_file():
                    raise _err(f"board file not found: {board}", key="calib.board", path=where)
            if check == "full" or not isinstance(spec, str):
                self.__dict__.pop("board", None)
                _ = self.board
        for key in self.ground_truth_keys:
            p = self.ground_truth_path(key)
            if not p.exists():
                raise _err(f"ground-truth file not found: {p}", key=f"ground_truth.{key}",
                           path=where)
        report = FrameCheck()
        for group in self.groups:
            for cam in cameras:
                _check_group_files(
                    self.expected_files(group, cam.name), self.response(group), group, cam,
                    full=(check == "full"), report=report,
                )
        self.frame_check = report
        report.raise_first_error()
        return self

    def _validate_olat(self, rig, where) -> None:
        lights = getattr(rig, "lights", None)
        if lights is None:
            raise _err("[olat] is present but the rig has no lights (rig.json lights = null)",
                       key="olat", path=where)
        grid = hasattr(lights, "n_theta")
        if self.n_lights != lights.n_lights:
            what = (f"light stage has {lights.n_lights} lights ({lights.n_theta} × "
                    f"{lights.n_phi})" if grid else f"light list has {lights.n_lights} lights")
            raise _err(
                f"n_lights = {self.n_lights} but the rig's {what}; "
                "they must be equal",
                key="olat.n_lights",
                path=where,
            )
        sect = self._section("olat")
        if not grid and sect["light_order"] != "theta-fastest":
            raise _err("light_order applies to the θ × φ grid; a light list's file order is its "
                       "list order (leave light_order out)", key="olat.light_order", path=where)
        if grid and "{light_name" in sect["files"]:
            raise _err("{light_name} needs a light list with names in the rig (rig.json lights "
                       "kind = \"list\"); the θ × φ grid has light numbers ({light})",
                       key="olat.files", path=where)

    def _validate_cameras_tables(self, names: list[str], where) -> None:
        """``[<group>.cameras.<camera>]``: known cameras, known views / frames / lights, bits
        within the pattern spec's."""
        for group in self.groups:
            tables = self._section(group).get("cameras", {})
            for cam, t in tables.items():
                key = f"{group}.cameras.{cam}"
                if cam not in names:
                    raise _err(f"no camera {cam!r} in the rig; cameras: {', '.join(names)}",
                               key=key, path=where)
                if group in ("calib", "calib.projector"):
                    n = self._section(group)["views"]
                    for k in ("views", "missing"):
                        bad = [v for v in t.get(k, ()) if v >= n]
                        if bad:
                            raise _err(f"view {bad[0]} is out of range: {group}.views = {n} "
                                       f"(views 0 … {n - 1})", key=f"{key}.{k}", path=where)
                elif group == "structured_light":
                    frames = self.sl_frames
                    bad = [f for f in t.get("missing", ()) if f not in frames]
                    if bad:
                        raise _err(f"{bad[0]!r} is not one of structured_light.frames",
                                   key=f"{key}.missing", path=where)
                    for axis in ("x", "y"):
                        if f"bits_{axis}" not in t:
                            continue
                        spec = self.pattern_spec()
                        if spec is None:
                            raise _err("per-camera bits need a pattern spec "
                                       "([structured_light.patterns])", key=f"{key}.bits_{axis}",
                                       path=where)
                        if t[f"bits_{axis}"] > spec.n_bits(axis):
                            raise _err(f"bits_{axis} = {t[f'bits_{axis}']} but the patterns "
                                       f"code {spec.n_bits(axis)} bits on {axis}",
                                       key=f"{key}.bits_{axis}", path=where)
                else:
                    for x in t.get("missing", ()):
                        try:
                            self._light_index(x)
                        except InputError as exc:
                            raise _err(f"{exc}", key=f"{key}.missing", path=where) from exc

    def _validate_patterns(self, group: str, frames: list[str], where) -> None:
        """The pattern spec must produce exactly the frame list (a missing inverse frame is a
        load error naming it)."""
        from facegeo.geometry.structured_light import pattern_names

        try:
            spec = self.pattern_spec(group)
        except ScanFormatError:
            if self.version == 1:  # version 1's patterns table was free-form, never parsed
                log.debug("%s: version-1 patterns table is not a PatternSpec; not checked",
                          self.manifest_path)
                return
            raise
        if spec is None:
            return
        if group == "structured_light":
            proj = getattr(self.rig, "projector", None)
            if proj is not None and (spec.width, spec.height) != (proj.width, proj.height):
                raise _err(f"patterns are for a {spec.width}×{spec.height} projector but the rig's "
                           f"projector is {proj.width}×{proj.height}",
                           key=f"{group}.patterns", path=where)
        want = pattern_names(spec)
        fkey = f"{group}.frames"
        missing = [n for n in want if n not in frames]
        if missing:
            raise _err(f"the pattern spec ({group}.patterns) projects frame {missing[0]!r}, which "
                       f"{fkey} does not list ({len(missing)} missing: "
                       f"{', '.join(missing[:4])}{', ...' if len(missing) > 4 else ''})",
                       key=fkey, path=where)
        extra = [f for f in frames if f not in want]
        if extra:
            raise _err(f"frame {extra[0]!r} is not a pattern of {group}.patterns (it projects "
                       f"{', '.join(want[:6])}{', ...' if len(want) > 6 else ''})",
                       key=fkey, path=where)

    def _validate_world(self, names: list[str], where) -> None:
        w = self._m["scan"].get("world")
        if w is None or "transform" in w:
            return
        if not self.has("calib"):
            raise _err("world = { camera, board_view } needs a [calib] section",
                       key="scan.world", path=where)
        if w["camera"] not in names:
            raise _err(f"no camera {w['camera']!r} in the rig; cameras: {', '.join(names)}",
                       key="scan.world.camera", path=where)
        if w["board_view"] not in self.calib_views(w["camera"]):
            raise _err(f"camera {w['camera']!r} has no calibration view {w['board_view']} (its "
                       f"views: {self.calib_views(w['camera'])})", key="scan.world.board_view",
                       path=where)

# =========================================================================== entry points


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


def _fmt_bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"  # pragma: no cover


def _du(path: Path, skip: Path | None = None, seen: set | None = None) -> int:
    """Bytes in the files under ``path`` (symlinks not followed), each inode counted once:
    hard links (a scan that links frames from another, say) do not double the size."""
    total = 0
    seen = set() if seen is None else seen
    for dirpath, dirnames, filenames in os.walk(path):
        if skip is not None:
            dirnames[:] = [d for d in dirnames if Path(dirpath, d) != skip]
        for f in filenames:
            try:
                st = os.lstat(os.path.join(dirpath, f))
            except OSError:
                continue
            ident = (st.st_dev, st.st_ino)
            if ident in seen:
                continue
            seen.add(ident)
            total += st.st_size
    return total


def _fmt_response(r: Any) -> str:
    if isinstance(r, str):
        return r
    if r.get("kind") == "gamma":
        return f"gamma {r['gamma']}"
    if r.get("kind") == "table":
        return f"table {r['file']}"
    return str(r.get("kind"))


def _fmt_keys(keys: list, limit: int = 4) -> str:
    shown = [f"view {k[0]} {k[1]}" if isinstance(k, tuple) else str(k) for k in keys[:limit]]
    return ", ".join(shown) + (f", ... ({len(keys)} in all)" if len(keys) > limit else "")


def summarize(scan: Scan) -> str:
    """A human-readable summary of a scan: name and version, cameras, projector, lights, frame
    groups, what each camera has and lacks per group, board, world frame, responses, reference
    answers, ground truth and size on disk (hard links counted once).

    This is what ``facegeo info`` prints."""
    m = scan._m
    lines = [(f"scan {scan.name!r} ({'synthetic' if scan.synthetic else 'real capture'}, "
              f"format version {scan.version})"),
             f"  root: {scan.root}"]
    if scan.description:
        lines.append(f"  description: {scan.description}")
    rig = scan.rig
    lines.append(f"  rig: {m['scan']['rig']}, {len(rig.cameras)} camera(s)")
    for c in rig.cameras:
        lines.append(f"    camera {c.name}: {c.width}×{c.height} px")
    proj = getattr(rig, "projector", None)
    if proj is None:
        lines.append("  projector: none")
    else:
        cal = "" if getattr(rig, "projector_calibrated", True) else " (uncalibrated: intrinsics unknown)"
        lines.append(f"  projector: {proj.name} {proj.width}×{proj.height} px{cal}")
    lights = getattr(rig, "lights", None)
    if lights is None:
        lines.append("  lights: none")
    elif hasattr(lights, "n_theta"):
        lines.append(
            f"  light stage: {lights.n_lights} lights ({lights.n_theta} azimuths × "
            f"{lights.n_phi} inclinations)"
        )
    else:
        where = "directions" if lights.is_distant else "near-field positions"
        cover = ("a dome clipped at the horizon" if lights.horizon_axis is not None
                 else "the full sphere")
        lines.append(f"  light list: {lights.n_lights} lights ({where}), Voronoi solid angles "
                     f"over {cover}: sum {lights.solid_angles.sum():.3f} sr")
    world = m["scan"].get("world")
    if world is not None:
        lines.append("  world frame: " + ("explicit transform T_world_rig" if "transform" in world
                                          else f"board in view {world['board_view']} seen by "
                                               f"{world['camera']}"))
    lines.append("  frame groups:" if scan.groups else "  frame groups: none")
    cams = scan.camera_names
    for g in scan.groups:
        s = scan._section(g)
        total = sum(len(scan.expected_files(g, c)) for c in cams)
        if g == "calib":
            per, what = s["views"], "view(s)"
            board = s["board"] if isinstance(s["board"], str) else f"inline {s['board']['kind']}"
            extra = f", response {_fmt_response(s['response'])}, board {board}"
            if "corners" in s:
                extra += f", corner lists {s['corners']}"
            if not scan.calib_images:
                extra += ", no images"
        elif g == "calib.projector":
            nf = len(scan.projector_frames)
            per = s["views"] * nf
            what = f"file(s) ({s['views']} view(s) × {nf} frames)"
            extra = f", response {_fmt_response(m['calib']['response'])}"
        elif g == "structured_light":
            per, what = len(s["frames"]), "frame(s)"
            extra = f", response {_fmt_response(s['response'])}, projector {s['projector']!r}"
        else:
            per, what = s["n_lights"], "light(s)"
            extra = f", response {_fmt_response(s['response'])}"
            if hasattr(lights, "n_theta"):
                extra += f", order {s['light_order']}"
            if "ambient" in s:
                extra += ", ambient frame"
        lines.append(f"    {g}: {per} {what} per camera, {total} files{extra}")
        lines.append(f"      files: {s['files']}")
        for c in cams:
            have = scan.camera_frames(g, c)
            lack = scan.missing_frames(g, c)
            line = f"      {c}: {len(have)} of {per}"
            if lack:
                if g == "olat" and scan.light_names is not None:
                    lack = [scan.light_names[k] for k in lack]
                elif g == "calib":
                    lack = [f"view {k}" for k in lack]
                line += f"; lacks {_fmt_keys(lack)}"
            if g == "structured_light" and "cameras" in s and c in s["cameras"]:
                bits = {k: v for k, v in s["cameras"][c].items() if k.startswith("bits_")}
                if bits:
                    line += "; resolves " + ", ".join(f"{k} = {v}" for k, v in bits.items())
            lines.append(line)
    for title, flat in (("reference", scan._ref or {}), ("ground truth", scan._gt or {})):
        if flat:
            lines.append(f"  {title}: {len(flat)} entr{'y' if len(flat) == 1 else 'ies'}")
            for k, v in flat.items():
                lines.append(f"    {k} = {v}")
    out = scan.root / "out"
    seen: set = set()
    size_in = _du(scan.root, skip=out, seen=seen)
    size_out = _du(out, seen=seen) if out.is_dir() else 0
    lines.append(f"  size on disk (hard links counted once): {_fmt_bytes(size_in)} (inputs), "
                 f"{_fmt_bytes(size_out)} (out/)")
    return "\n".join(lines)
