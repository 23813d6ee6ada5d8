"""The scan directory: its ``scan.toml`` manifest, validation, and lazy access to frames.

A real light stage and the synthetic generator (:mod:`facegeo.synth`) write the same layout,
documented key by key in ``docs/scan-format.md``::

    <scan>/scan.toml                        the manifest (this module's schema, version 1)
    <scan>/rig.json                         cameras, projector, light stage (facegeo.rig)
    calib/board.json, calib/<camera>/view_000.png ...
    calib/projector/<camera>/view_00_<frame>.png
    structured_light/<camera>/<frame>.png
    olat/<camera>/0000.exr ...              one per light
    ground_truth/...                        synthetic scans only
    out/                                    stage products

:func:`load_scan` parses and validates a scan and returns a :class:`Scan` whose frames are read
(and linearised) only when asked for. :func:`write_manifest` is the writer's counterpart: it
validates a manifest against the schema *and* the files already on disk before writing
``scan.toml``. Both resolve frame paths with :func:`frame_path`, so they cannot disagree.

Loading never writes into the scan directory (only :attr:`Scan.out_dir` creates ``out/``, on
demand).
"""

from __future__ import annotations

import copy
import datetime as _dt
import functools
import logging
import os
import re
import string
import tomllib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from facegeo.checks import check_choice
from facegeo.errors import FacegeoError, InputError, ScanFormatError
from facegeo.fsutil import atomic_write_text
from facegeo.imageio import (
    READ_SUFFIXES,
    Response,
    clipped_mask,
    parse_response,
    read_image,
    read_image_size,
    saturated_mask,
)

__all__ = [
    "FORMAT",
    "VERSION",
    "MANIFEST_NAME",
    "DEFAULT_RIG",
    "DEFAULT_BOARD",
    "DEFAULT_FILES",
    "DEFAULT_RESPONSES",
    "TEMPLATE_FIELDS",
    "LIGHT_ORDERS",
    "GROUPS",
    "CHECKS",
    "Scan",
    "load_scan",
    "validate_manifest",
    "write_manifest",
    "new_manifest",
    "frame_path",
    "summarize",
]

log = logging.getLogger(__name__)

FORMAT = "facegeo-scan"
VERSION = 1
MANIFEST_NAME = "scan.toml"
DEFAULT_RIG = "rig.json"
DEFAULT_BOARD = "calib/board.json"

#: Frame groups, in the order they are validated and summarised.
GROUPS = ("calib", "calib.projector", "structured_light", "olat")

#: Default path template of each frame group (relative to the scan directory).
DEFAULT_FILES = {
    "calib": "calib/{camera}/view_{view:03d}.png",
    "calib.projector": "calib/projector/{camera}/view_{view:02d}_{frame}.png",
    "structured_light": "structured_light/{camera}/{frame}.png",
    "olat": "olat/{camera}/{light:04d}.exr",
}

#: The fields each group's template must use, every one of them.
TEMPLATE_FIELDS = {
    "calib": ("camera", "view"),
    "calib.projector": ("camera", "view", "frame"),
    "structured_light": ("camera", "frame"),
    "olat": ("camera", "light"),
}

#: Default response of each section that declares one (calib.projector uses calib's).
DEFAULT_RESPONSES = {"calib": "srgb", "structured_light": "srgb", "olat": "linear"}

#: How OLAT file numbers map to the library's light index l = j·n_theta + i.
LIGHT_ORDERS = ("theta-fastest", "phi-fastest")

CHECKS = ("quick", "full")

_FRAME_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")
_SAMPLE_FIELDS = {"camera": "cam", "view": 0, "frame": "white", "light": 0}


# =========================================================================== schema

# Each key: (kind, required, default). Kinds are checked by _check_value.
_SCHEMA: dict[str, dict[str, tuple[str, bool, Any]]] = {
    "scan": {
        "format": ("format", True, None),
        "version": ("version", True, None),
        "name": ("text", True, None),
        "synthetic": ("bool", False, False),
        "description": ("str", False, ""),
        "created": ("datetime", False, None),
        "rig": ("path", False, DEFAULT_RIG),
        "metadata": ("table", False, None),
    },
    "calib": {
        "board": ("path", False, DEFAULT_BOARD),
        "response": ("response", False, DEFAULT_RESPONSES["calib"]),
        "views": ("count", True, None),
        "files": ("template", False, DEFAULT_FILES["calib"]),
        "projector": ("section", False, None),
    },
    "calib.projector": {
        "views": ("count", True, None),
        "files": ("template", False, DEFAULT_FILES["calib.projector"]),
    },
    "structured_light": {
        "response": ("response", False, DEFAULT_RESPONSES["structured_light"]),
        "projector": ("text", True, None),
        "frames": ("frames", True, None),
        "files": ("template", False, DEFAULT_FILES["structured_light"]),
        "patterns": ("table", False, {}),
    },
    "olat": {
        "response": ("response", False, DEFAULT_RESPONSES["olat"]),
        "n_lights": ("count", True, None),
        "light_order": ("light_order", False, LIGHT_ORDERS[0]),
        "files": ("template", False, DEFAULT_FILES["olat"]),
    },
}
_SECTIONS = ("scan", "calib", "structured_light", "olat", "ground_truth")


def _err(message: str, *, key: str | None = None, path: Any = None) -> ScanFormatError:
    return ScanFormatError(message, path=path, key=key)


def _type_name(v: Any) -> str:
    return type(v).__name__


def _check_rel_path(rel: Any, key: str, where: Any) -> str:
    """A relative POSIX path that cannot leave the scan directory (string-level check)."""
    if not isinstance(rel, str) or not rel.strip():
        raise _err(
            f"expected a relative path (a non-empty string), got {rel!r}", key=key, path=where
        )
    if "\\" in rel:
        raise _err(f"path {rel!r} contains a backslash; use forward slashes", key=key, path=where)
    p = PurePosixPath(rel)
    if p.is_absolute() or re.match(r"^[A-Za-z]:", rel):
        raise _err(
            f"path {rel!r} is absolute; paths in scan.toml are relative to the scan directory "
            "and may not leave it",
            key=key,
            path=where,
        )
    if ".." in p.parts:
        raise _err(
            f"path {rel!r} contains '..'; paths must stay inside the scan directory",
            key=key,
            path=where,
        )
    return rel


def _check_template(t: Any, group: str, key: str, where: Any) -> str:
    if not isinstance(t, str) or not t:
        raise _err(f"expected a path template string, got {t!r}", key=key, path=where)
    need = TEMPLATE_FIELDS[group]
    example = DEFAULT_FILES[group]
    try:
        parsed = list(string.Formatter().parse(t))
    except ValueError as exc:
        raise _err(
            f"bad template {t!r} ({exc}); for example {example!r}", key=key, path=where
        ) from exc
    used = set()
    for _, name, _, conv in parsed:
        if name is None:
            continue
        if name not in need:
            raise _err(
                f"template {t!r} uses field {{{name}}}; valid fields here: "
                + ", ".join("{" + n + "}" for n in need),
                key=key,
                path=where,
            )
        if conv is not None:
            raise _err(
                f"template {t!r}: conversions (!{conv}) are not allowed", key=key, path=where
            )
        used.add(name)
    missing = [n for n in need if n not in used]
    if missing:
        raise _err(
            f"template {t!r} must use every one of "
            + ", ".join("{" + n + "}" for n in need)
            + f" (missing {', '.join('{' + n + '}' for n in missing)}); for example {example!r}",
            key=key,
            path=where,
        )
    try:
        sample = t.format(**_SAMPLE_FIELDS)
    except (ValueError, TypeError, IndexError, KeyError) as exc:
        raise _err(
            f"template {t!r} cannot be formatted ({exc}); for example {example!r}",
            key=key,
            path=where,
        ) from exc
    _check_rel_path(sample, key, where)
    if PurePosixPath(sample).suffix.lower() not in READ_SUFFIXES:
        raise _err(
            f"template {t!r} must end in an image suffix ({', '.join(READ_SUFFIXES)})",
            key=key,
            path=where,
        )
    return t


def _check_value(kind: str, v: Any, key: str, where: Any, section: str) -> Any:
    if kind == "format":
        if v != FORMAT:
            raise _err(
                f"format is {v!r}; a facegeo scan says format = {FORMAT!r}", key=key, path=where
            )
        return v
    if kind == "version":
        if isinstance(v, bool) or not isinstance(v, int):
            raise _err(f"version must be an integer, got {v!r}", key=key, path=where)
        if v != VERSION:
            newer = " (newer than this facegeo; upgrade facegeo)" if v > VERSION else ""
            raise _err(
                f"unsupported version {v}{newer}; this facegeo reads version {VERSION}",
                key=key,
                path=where,
            )
        return v
    if kind == "text":
        if not isinstance(v, str) or not v.strip():
            raise _err(f"expected a non-empty string, got {v!r}", key=key, path=where)
        return v
    if kind == "str":
        if not isinstance(v, str):
            raise _err(f"expected a string, got {_type_name(v)} {v!r}", key=key, path=where)
        return v
    if kind == "bool":
        if not isinstance(v, bool):
            raise _err(f"expected true or false, got {v!r}", key=key, path=where)
        return v
    if kind == "datetime":
        if not isinstance(v, (str, _dt.datetime, _dt.date)):
            raise _err(f"expected a TOML date-time or a string, got {v!r}", key=key, path=where)
        return v
    if kind == "count":
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise _err(f"expected an integer > 0, got {v!r}", key=key, path=where)
        return v
    if kind == "path":
        return _check_rel_path(v, key, where)
    if kind == "template":
        return _check_template(v, section, key, where)
    if kind == "response":
        if isinstance(v, str):
            if v not in ("linear", "srgb"):
                raise _err(
                    f"unknown response {v!r}; expected \"linear\", \"srgb\", "
                    "{kind = \"gamma\", gamma = 2.2} or {kind = \"table\", file = \"<file>.npy\"}",
                    key=key,
                    path=where,
                )
            return v
        if isinstance(v, Mapping):
            kind_ = v.get("kind")
            if kind_ == "table":
                extra = set(v) - {"kind", "file"}
                if extra or "file" not in v:
                    raise _err(
                        "a table response is {kind = \"table\", file = \"<file>.npy\"}; "
                        f"got keys {sorted(v)}",
                        key=key,
                        path=where,
                    )
                _check_rel_path(v["file"], f"{key}.file", where)
                return dict(v)
            resp = parse_response(v, key=key, path=where)  # checks gamma and the keys
            return resp.to_spec()
        raise _err(f"expected a response string or table, got {v!r}", key=key, path=where)
    if kind == "light_order":
        if v not in LIGHT_ORDERS:
            raise _err(
                f"unknown light_order {v!r}; expected one of "
                + ", ".join(repr(o) for o in LIGHT_ORDERS),
                key=key,
                path=where,
            )
        return v
    if kind == "frames":
        if not isinstance(v, list) or not v:
            raise _err(f"expected a non-empty array of frame names, got {v!r}", key=key, path=where)
        seen = set()
        for i, name in enumerate(v):
            if not isinstance(name, str) or not _FRAME_NAME.match(name):
                raise _err(
                    f"frame {i} is {name!r}; frame names are letters, digits and _ . + - "
                    "(starting with a letter or digit), since they become file names",
                    key=key,
                    path=where,
                )
            if name in seen:
                raise _err(f"frame name {name!r} appears twice", key=key, path=where)
            seen.add(name)
        return list(v)
    if kind == "table":
        if not isinstance(v, Mapping):
            raise _err(f"expected a table, got {_type_name(v)} {v!r}", key=key, path=where)
        return copy.deepcopy(dict(v))
    raise AssertionError(kind)  # pragma: no cover


def _check_table(section: str, table: Any, where: Any) -> dict:
    if not isinstance(table, Mapping):
        raise _err(
            f"expected a table [{section}], got {_type_name(table)}", key=section, path=where
        )
    spec = _SCHEMA[section]
    unknown = sorted(set(table) - set(spec))
    if unknown:
        raise _err(
            f"unknown key {unknown[0]!r} in [{section}]; valid keys: {', '.join(spec)}",
            key=f"{section}.{unknown[0]}",
            path=where,
        )
    out = {}
    for k, (kind, required, default) in spec.items():
        key = f"{section}.{k}"
        if kind == "section":
            continue
        if k not in table:
            if required:
                raise _err(f"missing required key {k!r} in [{section}]", key=key, path=where)
            if default is not None:
                out[k] = copy.deepcopy(default)
            continue
        out[k] = _check_value(kind, table[k], key, where, section)
    return out


def _flatten_ground_truth(table: Any, prefix: str, where: Any, out: dict) -> dict:
    if not isinstance(table, Mapping):
        raise _err(f"expected a table, got {_type_name(table)}", key=prefix, path=where)
    for k, v in table.items():
        key = f"{prefix}.{k}"
        if isinstance(v, Mapping):
            _flatten_ground_truth(v, key, where, out)
        else:
            _check_rel_path(v, key, where)
            out[key[len("ground_truth."):]] = v
    return out


def validate_manifest(manifest: Mapping[str, Any], *, path: Any = None) -> dict:
    """Check a manifest against the schema (no file system access) and fill in defaults.

    Parameters
    ----------
    manifest : dict
        The parsed ``scan.toml``.
    path : path-like, optional
        Where it came from, for error messages.

    Returns
    -------
    dict
        A normalised deep copy: every optional key with a default is present.

    Raises
    ------
    ScanFormatError
        Unknown or missing key, wrong type or value; the message names the dotted key and says
        what would be right.
    """
    if not isinstance(manifest, Mapping):
        raise _err(f"a manifest is a table (dict), got {_type_name(manifest)}", path=path)
    unknown = [k for k in manifest if k not in _SECTIONS]
    if unknown:
        raise _err(
            f"unknown section [{unknown[0]}]; valid sections: "
            + ", ".join(f"[{s}]" for s in _SECTIONS),
            key=unknown[0],
            path=path,
        )
    if "scan" not in manifest:
        raise _err(
            f"missing section [scan] (it needs at least format = {FORMAT!r}, version = {VERSION}, "
            "name = \"...\")",
            key="scan",
            path=path,
        )
    out: dict[str, Any] = {"scan": _check_table("scan", manifest["scan"], path)}
    if "calib" in manifest:
        out["calib"] = _check_table("calib", manifest["calib"], path)
        if "projector" in manifest["calib"]:
            out["calib"]["projector"] = _check_table(
                "calib.projector", manifest["calib"]["projector"], path
            )
    for section in ("structured_light", "olat"):
        if section in manifest:
            out[section] = _check_table(section, manifest[section], path)
    if "projector" in out.get("calib", {}) and "structured_light" not in out:
        raise _err(
            "[calib.projector] names its frames after structured_light.frames, but there is no "
            "[structured_light] section",
            key="calib.projector",
            path=path,
        )
    if "ground_truth" in manifest:
        if not out["scan"]["synthetic"]:
            raise _err(
                "[ground_truth] is for synthetic scans only; set scan.synthetic = true or "
                "remove it",
                key="ground_truth",
                path=path,
            )
        _flatten_ground_truth(manifest["ground_truth"], "ground_truth", path, {})
        out["ground_truth"] = copy.deepcopy(dict(manifest["ground_truth"]))
    return out


# =========================================================================== paths


def _format_template(template: str, fields: Mapping[str, Any]) -> str:
    try:
        return template.format(**fields)
    except (KeyError, IndexError, ValueError, TypeError) as exc:
        raise InputError(f"cannot fill template {template!r} with {dict(fields)!r}: {exc}") from exc


class _Resolver:
    """Joins relative paths to a root and refuses any that lead outside it (symlinks too)."""

    def __init__(self, root: Path):
        self.root = root
        self.root_real = os.path.realpath(root)
        self._dirs: dict[str, str] = {}

    def __call__(self, rel: str, *, key: str | None = None, where: Any = None) -> Path:
        _check_rel_path(rel, key or "path", where)
        p = self.root / rel
        parent = str(p.parent)
        real_parent = self._dirs.get(parent)
        if real_parent is None:
            real_parent = os.path.realpath(parent)
            self._dirs[parent] = real_parent
        real = os.path.join(real_parent, p.name)
        if os.path.islink(real):
            real = os.path.realpath(real)
        if real != self.root_real and not real.startswith(self.root_real + os.sep):
            raise _err(
                f"{rel!r} resolves to {real}, outside the scan directory {self.root_real} (a "
                "symlink out of the scan); every scan file must live inside the scan directory",
                key=key,
                path=p,
            )
        return p


def frame_path(root: str | os.PathLike, template: str, **fields: Any) -> Path:
    """The path of one frame: ``root / template.format(**fields)``, checked to stay in ``root``.

    Writers and the loader both call this, so they cannot disagree about where a frame lives.

    Parameters
    ----------
    root : path-like
        The scan directory.
    template : str
        A group's path template (:data:`DEFAULT_FILES` or the manifest's ``files``).
    **fields
        ``camera`` (str), ``view`` (int), ``frame`` (str), ``light`` (int, the *file* number in
        capture order; see ``olat.light_order``).

    Raises
    ------
    ScanFormatError
        The filled path is absolute, contains ``..``, or resolves (through a symlink) outside
        ``root``.
    InputError
        A field the template needs is missing or has the wrong type.
    """
    rel = _format_template(template, fields)
    return _Resolver(Path(root))(rel, key="files")


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
        self._resolve = _Resolver(self.root)
        self._responses: dict[str, Response] = {}

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
        """The scan's :class:`facegeo.rig.Rig` (loaded on first use)."""
        from facegeo.rig import Rig

        rel = self._m["scan"]["rig"]
        p = self._resolve(rel, key="scan.rig", where=self.manifest_path)
        if not p.is_file():
            raise _err(
                f"rig file not found: {p} (scan.rig = {rel!r})",
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
        """The rig's :class:`facegeo.camera.Camera` called ``name``."""
        for c in self.rig.cameras:
            if c.name == name:
                return c
        check_choice(name, "camera", self.camera_names)
        raise AssertionError  # pragma: no cover

    @functools.cached_property
    def board(self):
        """The calibration board (:class:`facegeo.board.CharucoBoard`, loaded on first use)."""
        from facegeo.board import CharucoBoard

        rel = self._section("calib")["board"]
        p = self._resolve(rel, key="calib.board", where=self.manifest_path)
        if not p.is_file():
            raise _err(f"board file not found: {p}", key="calib.board", path=self.manifest_path)
        try:
            return CharucoBoard.load(p)
        except ScanFormatError:
            raise
        except (FacegeoError, ValueError, KeyError, TypeError, OSError) as exc:
            raise _err(f"cannot load the board: {exc}", key="calib.board", path=p) from exc

    def response(self, group: str) -> Response:
        """The declared :class:`~facegeo.imageio.Response` of a frame group
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

    def _path(self, group: str, **fields: Any) -> Path:
        template = self._section(group)["files"]
        return self._resolve(_format_template(template, fields), key=f"{group}.files")

    def _check_camera(self, camera: str) -> None:
        if camera not in self.camera_names:
            check_choice(camera, "camera", self.camera_names)

    @property
    def n_lights(self) -> int:
        """``olat.n_lights``."""
        return int(self._section("olat")["n_lights"])

    def _olat_file_number(self, light: int) -> int:
        order = self._section("olat")["light_order"]
        if order == "theta-fastest":
            return light
        lights = self.rig.lights
        i, j = light % lights.n_theta, light // lights.n_theta
        return i * lights.n_phi + j

    def _check_light(self, light: Any) -> int:
        if isinstance(light, (bool, np.bool_)) or not isinstance(light, (int, np.integer)):
            raise InputError(f"light: expected an integer light index, got {light!r}")
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
        light = self._check_light(light)
        return self._path("olat", camera=camera, light=self._olat_file_number(light))

    def sl_path(self, camera: str, frame: str) -> Path:
        """Path of structured-light frame ``frame`` of ``camera``."""
        self._check_camera(camera)
        check_choice(frame, "frame", self.sl_frames)
        return self._path("structured_light", camera=camera, frame=frame)

    def calib_view_paths(self, camera: str) -> list[Path]:
        """Paths of the calibration-board views of ``camera``, in view order."""
        self._check_camera(camera)
        n = self._section("calib")["views"]
        return [self._path("calib", camera=camera, view=v) for v in range(n)]

    def projector_view_paths(self, camera: str, view: int) -> dict[str, Path]:
        """Paths of the board seen by ``camera`` in projector-calibration view ``view`` under
        every structured-light pattern: ``{frame name: path}`` in :attr:`sl_frames` order."""
        self._check_camera(camera)
        n = self._section("calib.projector")["views"]
        if isinstance(view, bool) or not isinstance(view, (int, np.integer)) or not 0 <= view < n:
            raise InputError(f"view: expected an integer in [0, {n}), got {view!r}")
        return {
            f: self._path("calib.projector", camera=camera, view=int(view), frame=f)
            for f in self.sl_frames
        }

    @property
    def sl_frames(self) -> list[str]:
        """Structured-light frame names, in capture order."""
        return list(self._section("structured_light")["frames"])

    @property
    def sl_patterns(self) -> dict:
        """The free-form pattern spec (``[structured_light.patterns]``), a deep copy."""
        return copy.deepcopy(self._section("structured_light")["patterns"])

    @property
    def sl_projector(self) -> str:
        """``structured_light.projector``: the rig's projector name."""
        return self._section("structured_light")["projector"]

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
                f"no ground-truth entry {key!r}; entries: {', '.join(flat) or '(none)'}",
                key=f"ground_truth.{key}",
                path=self.manifest_path,
            )
        return self._resolve(flat[key], key=f"ground_truth.{key}", where=self.manifest_path)

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

    def olat_frame(self, camera: str, light: int, *, return_mask: bool = False):
        """One OLAT frame, linear.

        Parameters
        ----------
        camera : str
        light : int
            Light index ``l = j·n_theta + i``.
        return_mask : bool
            Also return where the samples can be trusted.

        Returns
        -------
        frame : (H, W, 3) float32, linear
            Grey frames are repeated to three channels; alpha is dropped.
        valid : (H, W) bool, only with ``return_mask``
            False where a sample is saturated or black-clipped (integer frames) or non-finite
            (float frames).
        """
        lin, valid = self._read("olat", camera, self.olat_path(camera, light),
                                return_mask=return_mask)
        if lin.ndim == 2:
            lin = np.repeat(lin[..., None], 3, axis=-1)
        elif lin.shape[-1] == 4:
            lin = np.ascontiguousarray(lin[..., :3])
        return (lin, valid) if return_mask else lin

    def iter_olat(self, camera: str, lights: Sequence[int] | None = None, *,
                  return_mask: bool = False) -> Iterator[tuple]:
        """Yield ``(light, frame)`` (or ``(light, frame, valid)``) for ``lights`` (default all,
        in light-index order), reading one frame at a time."""
        for light in range(self.n_lights) if lights is None else lights:
            out = self.olat_frame(camera, light, return_mask=return_mask)
            yield (light, *out) if return_mask else (light, out)

    def sl_frame(self, camera: str, frame: str, *, return_mask: bool = False):
        """One structured-light frame, linear.

        Returns
        -------
        frame : (H, W) or (H, W, 3) float32, linear, channels as stored (alpha dropped)
        valid : (H, W) bool, only with ``return_mask`` (see :meth:`olat_frame`)
        """
        lin, valid = self._read("structured_light", camera, self.sl_path(camera, frame),
                                return_mask=return_mask)
        if lin.ndim == 3 and lin.shape[-1] == 4:
            lin = np.ascontiguousarray(lin[..., :3])
        return (lin, valid) if return_mask else lin

    # ------------------------------------------------------------------ validation

    def expected_files(self, group: str, camera: str) -> list[tuple[str, Path]]:
        """Every file a group should hold for ``camera``: ``[(label, path), ...]`` in order."""
        sect = self._section(group)
        if group == "calib":
            return [(f"view {v}", self._path(group, camera=camera, view=v))
                    for v in range(sect["views"])]
        if group == "calib.projector":
            return [
                (f"view {v} frame {f!r}", self._path(group, camera=camera, view=v, frame=f))
                for v in range(sect["views"]) for f in self.sl_frames
            ]
        if group == "structured_light":
            return [(f"frame {f!r}", self._path(group, camera=camera, frame=f))
                    for f in self.sl_frames]
        out = []
        for light in range(sect["n_lights"]):
            k = self._olat_file_number(light)
            label = f"light {light}" + (f" (file number {k})" if k != light else "")
            out.append((label, self._path(group, camera=camera, light=k)))
        return out

    def validate(self, check: str = "quick") -> Scan:
        """Check the scan against its rig and the files on disk.

        Parameters
        ----------
        check : {"quick", "full"}
            ``"quick"``: the rig (and its cross-checks), response tables, ground-truth entries,
            that every expected frame exists inside the scan, and the header size of the first
            and last frame of each (group, camera). ``"full"``: additionally the header size of
            every frame, the board file, and a decode of every frame (corruption, dtype against
            the declared response).

        Returns
        -------
        Scan
            ``self``.

        Raises
        ------
        ScanFormatError
            The first problem found, naming the file and/or key and what would be right.
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
        if len(set(names)) != len(names):
            raise _err(
                f"the rig's camera names are not unique: {names}", key="scan.rig", path=where
            )
        if self.has("olat"):
            lights = getattr(rig, "lights", None)
            if lights is None:
                raise _err("[olat] is present but the rig has no light stage", key="olat",
                           path=where)
            if self.n_lights != lights.n_lights:
                raise _err(
                    f"n_lights = {self.n_lights} but the rig's light stage has "
                    f"{lights.n_lights} lights ({lights.n_theta} × {lights.n_phi}); they must be "
                    "equal",
                    key="olat.n_lights",
                    path=where,
                )
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
                    f"projector = {self.sl_projector!r} but the rig's projector is {proj.name!r}",
                    key="structured_light.projector",
                    path=where,
                )
        for sect in ("calib", "structured_light", "olat"):
            if self.has(sect):
                self.response(sect)
        if self.has("calib"):
            board = self._resolve(self._m["calib"]["board"], key="calib.board", where=where)
            if not board.is_file():
                raise _err(f"board file not found: {board}", key="calib.board", path=where)
            if check == "full":
                self.__dict__.pop("board", None)
                _ = self.board
        for key in self.ground_truth_keys:
            p = self.ground_truth_path(key)
            if not p.exists():
                raise _err(f"ground-truth file not found: {p}", key=f"ground_truth.{key}",
                           path=where)
        for group in self.groups:
            for cam in cameras:
                self._check_group_files(group, cam, full=(check == "full"))
        return self

    def _check_group_files(self, group: str, cam, *, full: bool) -> None:
        files = self.expected_files(group, cam.name)
        missing = [(label, p) for label, p in files if not p.is_file()]
        if missing:
            label, p = missing[0]
            more = f" ({len(missing)} of {len(files)} {group} files of this camera are missing)"
            raise _err(
                f"missing {group} frame: camera {cam.name!r}, {label}; expected file {p}{more}",
                key=f"{group}.files",
                path=p,
            )
        expected = (cam.width, cam.height)
        to_size = files if full else ([files[0], files[-1]] if len(files) > 1 else files)
        for _, p in to_size:
            size = read_image_size(p)
            if size != expected:
                raise _size_error(p, group, cam.name, size, expected)
        if full:
            response = self.response(group)
            for _, p in files:
                img = read_image(p)
                h, w = img.shape[:2]
                if (w, h) != expected:
                    raise _size_error(p, group, cam.name, (w, h), expected)
                if img.ndim == 3 and img.shape[2] not in (3, 4):
                    raise _err(
                        f"image has {img.shape[2]} channels; expected grey, RGB or RGBA",
                        key=f"{group}.files",
                        path=p,
                    )
                try:
                    if img.dtype.kind == "f":
                        response.linearize(img[:1, :1])
                    else:
                        response.lut(img.dtype)
                except InputError as exc:
                    sect = "calib" if group == "calib.projector" else group
                    raise _err(f"{exc}", key=f"{sect}.response", path=p) from exc


def _size_error(path: Path, group: str, camera: str, found, expected) -> ScanFormatError:
    return _err(
        f"image is {found[0]}×{found[1]} px but camera {camera!r} is {expected[0]}×{expected[1]} "
        "px in the rig (width × height)",
        key=f"{group}.files",
        path=path,
    )


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
        raise InputError(f"name: expected a non-empty string, got {name!r}")
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
        f"# facegeo scan manifest, format {FORMAT} version {VERSION}; see docs/scan-format.md\n"
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


def _du(path: Path, skip: Path | None = None) -> int:
    total = 0
    for dirpath, dirnames, filenames in os.walk(path):
        if skip is not None:
            dirnames[:] = [d for d in dirnames if Path(dirpath, d) != skip]
        for f in filenames:
            try:
                st = os.lstat(os.path.join(dirpath, f))
            except OSError:
                continue
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


def summarize(scan: Scan) -> str:
    """A human-readable summary of a scan: name, cameras, projector, light grid, frame groups,
    responses, ground truth and size on disk."""
    m = scan._m
    lines = [f"scan {scan.name!r} ({'synthetic' if scan.synthetic else 'real capture'})",
             f"  root: {scan.root}"]
    if scan.description:
        lines.append(f"  description: {scan.description}")
    rig = scan.rig
    lines.append(f"  rig: {m['scan']['rig']}, {len(rig.cameras)} camera(s)")
    for c in rig.cameras:
        lines.append(f"    camera {c.name}: {c.width}×{c.height} px")
    proj = getattr(rig, "projector", None)
    lines.append(f"  projector: {proj.name} {proj.width}×{proj.height} px" if proj is not None
                 else "  projector: none")
    lights = getattr(rig, "lights", None)
    if lights is not None:
        lines.append(
            f"  light stage: {lights.n_lights} lights ({lights.n_theta} azimuths × "
            f"{lights.n_phi} inclinations)"
        )
    else:
        lines.append("  light stage: none")
    n_cam = len(rig.cameras)
    lines.append("  frame groups:" if scan.groups else "  frame groups: none")
    for g in scan.groups:
        s = scan._section(g)
        if g == "calib":
            per, what = s["views"], "view(s)"
            extra = f", response {_fmt_response(s['response'])}, board {s['board']}"
        elif g == "calib.projector":
            per = s["views"] * len(scan.sl_frames)
            what = f"file(s) ({s['views']} view(s) × {len(scan.sl_frames)} frames)"
            extra = f", response {_fmt_response(m['calib']['response'])}"
        elif g == "structured_light":
            per, what = len(s["frames"]), "frame(s)"
            extra = f", response {_fmt_response(s['response'])}, projector {s['projector']!r}"
        else:
            per, what = s["n_lights"], "light(s)"
            extra = f", response {_fmt_response(s['response'])}, order {s['light_order']}"
        lines.append(f"    {g}: {per} {what} × {n_cam} camera(s) = {per * n_cam} files{extra}")
        lines.append(f"      files: {s['files']}")
    gt = scan._gt or {}
    if gt:
        lines.append(f"  ground truth: {len(gt)} entr{'y' if len(gt) == 1 else 'ies'}")
        for k, v in gt.items():
            lines.append(f"    {k} = {v}")
    out = scan.root / "out"
    size_in = _du(scan.root, skip=out)
    size_out = _du(out) if out.is_dir() else 0
    lines.append(f"  size on disk: {_fmt_bytes(size_in)} (inputs), {_fmt_bytes(size_out)} (out/)")
    return "\n".join(lines)
