"""The ``scan.toml`` schema (private; the public names are re-exported by :mod:`facegeo.capture.scan`).

The format's constants (:data:`FORMAT`, :data:`VERSION`, the default paths, templates and
responses of each frame group), the key table of every section, the type and value checks of
each key, the path-template checks, the string-level path-safety check
(:func:`_check_rel_path`: relative, forward slashes, no ``..``) and :func:`validate_manifest`,
which applies them all to a parsed manifest. Nothing here touches the file system: that is
:mod:`facegeo.capture._scan_files` (and, for the rig, board and frames, :class:`facegeo.capture.scan.Scan`).
Documented key by key in ``docs/scan-format.md``.
"""

from __future__ import annotations

import copy
import datetime as _dt
import re
import string
from collections.abc import Mapping
from pathlib import PurePosixPath
from typing import Any

from facegeo.errors import ScanFormatError
from facegeo.capture.imageio import READ_SUFFIXES
from facegeo.capture.response import parse_response
from facegeo.checks import fmt_value

FORMAT = "facegeo-scan"
VERSION = 1
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
        "exposure": ("positive", False, 1.0),
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
            f"expected a relative path (a non-empty string), got {fmt_value(rel)}", key=key, path=where
        )
    if "\\" in rel:
        raise _err(f"path {fmt_value(rel)} contains a backslash; use forward slashes", key=key, path=where)
    p = PurePosixPath(rel)
    if p.is_absolute() or re.match(r"^[A-Za-z]:", rel):
        raise _err(
            f"path {fmt_value(rel)} is absolute; paths in scan.toml are relative to the scan directory "
            "and may not leave it",
            key=key,
            path=where,
        )
    if ".." in p.parts:
        raise _err(
            f"path {fmt_value(rel)} contains '..'; paths must stay inside the scan directory",
            key=key,
            path=where,
        )
    return rel


def _check_template(t: Any, group: str, key: str, where: Any) -> str:
    if not isinstance(t, str) or not t:
        raise _err(f"expected a path template string, got {fmt_value(t)}", key=key, path=where)
    need = TEMPLATE_FIELDS[group]
    example = DEFAULT_FILES[group]
    try:
        parsed = list(string.Formatter().parse(t))
    except ValueError as exc:
        raise _err(
            f"bad template {fmt_value(t)} ({exc}); for example {fmt_value(example)}", key=key, path=where
        ) from exc
    used = set()
    for _, name, _, conv in parsed:
        if name is None:
            continue
        if name not in need:
            raise _err(
                f"template {fmt_value(t)} uses field {{{name}}}; valid fields here: "
                + ", ".join("{" + n + "}" for n in need),
                key=key,
                path=where,
            )
        if conv is not None:
            raise _err(
                f"template {fmt_value(t)}: conversions (!{conv}) are not allowed", key=key, path=where
            )
        used.add(name)
    missing = [n for n in need if n not in used]
    if missing:
        raise _err(
            f"template {fmt_value(t)} must use every one of "
            + ", ".join("{" + n + "}" for n in need)
            + f" (missing {', '.join('{' + n + '}' for n in missing)}); for example {fmt_value(example)}",
            key=key,
            path=where,
        )
    try:
        sample = t.format(**_SAMPLE_FIELDS)
    except (ValueError, TypeError, IndexError, KeyError) as exc:
        raise _err(
            f"template {fmt_value(t)} cannot be formatted ({exc}); for example {fmt_value(example)}",
            key=key,
            path=where,
        ) from exc
    _check_rel_path(sample, key, where)
    if PurePosixPath(sample).suffix.lower() not in READ_SUFFIXES:
        raise _err(
            f"template {fmt_value(t)} must end in an image suffix ({', '.join(READ_SUFFIXES)})",
            key=key,
            path=where,
        )
    return t


def _check_value(kind: str, v: Any, key: str, where: Any, section: str) -> Any:
    if kind == "format":
        if v != FORMAT:
            raise _err(
                f"format is {fmt_value(v)}; a facegeo scan says format = {fmt_value(FORMAT)}", key=key, path=where
            )
        return v
    if kind == "version":
        if isinstance(v, bool) or not isinstance(v, int):
            raise _err(f"version must be an integer, got {fmt_value(v)}", key=key, path=where)
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
            raise _err(f"expected a non-empty string, got {fmt_value(v)}", key=key, path=where)
        return v
    if kind == "str":
        if not isinstance(v, str):
            raise _err(f"expected a string, got {_type_name(v)} {fmt_value(v)}", key=key, path=where)
        return v
    if kind == "bool":
        if not isinstance(v, bool):
            raise _err(f"expected true or false, got {fmt_value(v)}", key=key, path=where)
        return v
    if kind == "datetime":
        if not isinstance(v, (str, _dt.datetime, _dt.date)):
            raise _err(f"expected a TOML date-time or a string, got {fmt_value(v)}", key=key, path=where)
        return v
    if kind == "count":
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise _err(f"expected an integer > 0, got {fmt_value(v)}", key=key, path=where)
        return v
    if kind == "positive":
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0 < v < float("inf")):
            raise _err(f"expected a finite number > 0, got {fmt_value(v)}", key=key, path=where)
        return float(v)
    if kind == "path":
        return _check_rel_path(v, key, where)
    if kind == "template":
        return _check_template(v, section, key, where)
    if kind == "response":
        if isinstance(v, str):
            if v not in ("linear", "srgb"):
                raise _err(
                    f"unknown response {fmt_value(v)}; expected \"linear\", \"srgb\", "
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
        raise _err(f"expected a response string or table, got {fmt_value(v)}", key=key, path=where)
    if kind == "light_order":
        if v not in LIGHT_ORDERS:
            raise _err(
                f"unknown light_order {fmt_value(v)}; expected one of "
                + ", ".join(repr(o) for o in LIGHT_ORDERS),
                key=key,
                path=where,
            )
        return v
    if kind == "frames":
        if not isinstance(v, list) or not v:
            raise _err(f"expected a non-empty array of frame names, got {fmt_value(v)}", key=key, path=where)
        seen = set()
        for i, name in enumerate(v):
            if not isinstance(name, str) or not _FRAME_NAME.match(name):
                raise _err(
                    f"frame {i} is {fmt_value(name)}; frame names are letters, digits and _ . + - "
                    "(starting with a letter or digit), since they become file names",
                    key=key,
                    path=where,
                )
            if name in seen:
                raise _err(f"frame name {fmt_value(name)} appears twice", key=key, path=where)
            seen.add(name)
        return list(v)
    if kind == "table":
        if not isinstance(v, Mapping):
            raise _err(f"expected a table, got {_type_name(v)} {fmt_value(v)}", key=key, path=where)
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
            f"unknown key {fmt_value(unknown[0])} in [{section}]; valid keys: {', '.join(spec)}",
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
                raise _err(f"missing required key {fmt_value(k)} in [{section}]", key=key, path=where)
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
            f"missing section [scan] (it needs at least format = {fmt_value(FORMAT)}, version = {VERSION}, "
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
