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
#: The version :func:`facegeo.capture.scan.new_manifest` writes.
VERSION = 2
#: Versions the loader reads (version 1 is version 2 without the v2 keys, :data:`V2_KEYS`).
READ_VERSIONS = (1, 2)
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

#: The fields each group's template must use, every one of them (olat: ``{light}`` or, in
#: version 2, ``{light_name}`` instead).
TEMPLATE_FIELDS = {
    "calib": ("camera", "view"),
    "calib.projector": ("camera", "view", "frame"),
    "structured_light": ("camera", "frame"),
    "olat": ("camera", "light"),
    "calib.corners": ("camera",),
    "olat.ambient": ("camera",),
}
#: Fields a template may use instead of a required one (v2): ``{field: replacements}``.
#: ``{index}`` is the 0-based and ``{number}`` the 1-based position of the frame (the view, the
#: frame in ``frames``, the OLAT file number), for data sets that number their files.
_ALT_FIELDS = {
    "olat": {"light": ("light_name", "index", "number")},
    "calib": {"view": ("index", "number")},
    "calib.projector": {"frame": ("index", "number")},
    "structured_light": {"frame": ("index", "number")},
}
#: Groups whose description may declare named per-view template fields (``fields = { pose =
#: [3, 7, 12] }``, v2): each a list of one integer or string per view, or one value for all.
FIELD_GROUPS = ("calib", "calib.projector")
#: Fields that only a version-2 template may use.
V2_TEMPLATE_FIELDS = ("light_name", "index", "number")
#: A template ending in this suffix matches one file of any readable image suffix (v2).
ANY_SUFFIX = ".*"
#: Suffixes of a corner-list file.
CORNER_SUFFIXES = (".npz", ".csv")
#: Board kinds (``calib.board`` inline table or ``board.json``'s ``kind``).
BOARD_KINDS = ("charuco", "chessboard", "circles")

#: Keys (dotted) that exist only in version 2; a version-1 manifest using one is an error.
V2_KEYS = ("scan.world", "calib.images", "calib.corners", "calib.cameras", "calib.fields",
           "calib.projector.frames", "calib.projector.patterns", "calib.projector.cameras",
           "calib.projector.fields", "calib.projector.response",
           "structured_light.cameras", "olat.ambient", "olat.cameras", "reference")

#: Default response of each section that declares one (calib.projector: its own ``response``
#: when it declares one — its Gray-code frames may be float EXR where the board photos are
#: 8-bit sRGB — else calib's).
DEFAULT_RESPONSES = {"calib": "srgb", "structured_light": "srgb", "olat": "linear"}

#: How OLAT file numbers map to the library's light index l = j·n_theta + i.
LIGHT_ORDERS = ("theta-fastest", "phi-fastest")

_FRAME_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")
_SAMPLE_FIELDS = {"camera": "cam", "view": 0, "frame": "white", "light": 0, "light_name": "L0",
                  "index": 0, "number": 1}


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
        "world": ("world", False, None),
    },
    "calib": {
        "board": ("board", False, DEFAULT_BOARD),
        "response": ("response", False, DEFAULT_RESPONSES["calib"]),
        "views": ("count", True, None),
        "files": ("template", False, DEFAULT_FILES["calib"]),
        "images": ("bool", False, None),
        "corners": ("template", False, None),
        "cameras": ("cameras", False, None),
        "fields": ("fields", False, None),
        "projector": ("section", False, None),
    },
    "calib.projector": {
        "views": ("count", True, None),
        "response": ("response", False, None),
        "fields": ("fields", False, None),
        "files": ("template", False, DEFAULT_FILES["calib.projector"]),
        "frames": ("frames", False, None),
        "patterns": ("table", False, None),
        "cameras": ("cameras", False, None),
    },
    "structured_light": {
        "response": ("response", False, DEFAULT_RESPONSES["structured_light"]),
        "projector": ("text", True, None),
        "frames": ("frames", True, None),
        "files": ("template", False, DEFAULT_FILES["structured_light"]),
        "patterns": ("table", False, {}),
        "decode": ("table", False, None),
        "cameras": ("cameras", False, None),
    },
    "olat": {
        "response": ("response", False, DEFAULT_RESPONSES["olat"]),
        "n_lights": ("count", True, None),
        "light_order": ("light_order", False, LIGHT_ORDERS[0]),
        "exposure": ("positive", False, 1.0),
        "files": ("template", False, DEFAULT_FILES["olat"]),
        "ambient": ("template", False, None),
        "cameras": ("cameras", False, None),
    },
}
_SECTIONS = ("scan", "calib", "structured_light", "olat", "ground_truth", "reference")

#: Keys of a per-camera table ``[<group>.cameras.<camera>]``, by group.
CAMERA_KEYS = {
    "calib": ("views", "missing"),
    "calib.projector": ("views", "missing"),
    "structured_light": ("missing", "bits_x", "bits_y"),
    "olat": ("missing",),
}


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


def _check_fields(v: Any, key: str, where: Any) -> dict:
    """``<group>.fields`` (v2): ``{name: value or [value per view]}``, each value an integer or
    a string; names are identifiers other than the built-in template fields."""
    if not isinstance(v, Mapping) or not v:
        raise _err(f"expected a table of named fields (e.g. {{ pose = [3, 7, 12] }}), got "
                   f"{fmt_value(v)}", key=key, path=where)
    builtin = set(_SAMPLE_FIELDS)
    out = {}
    for name, vals in v.items():
        k = f"{key}.{name}"
        if not isinstance(name, str) or not name.isidentifier() or name in builtin:
            raise _err(f"field name {fmt_value(name)}: expected an identifier other than the "
                       f"built-in fields {', '.join(sorted(builtin))}", key=k, path=where)
        items = vals if isinstance(vals, list) else [vals]
        bad = [x for x in items if isinstance(x, bool) or not isinstance(x, (int, str))]
        if not items or bad:
            raise _err(f"expected an integer or a string, or a list of one per view, got "
                       f"{fmt_value(bad[0] if bad else vals)}", key=k, path=where)
        out[name] = list(vals) if isinstance(vals, list) else vals
    return out


def _template_names(t: str) -> set:
    return {name for _, name, _, _ in string.Formatter().parse(t) if name is not None}


def _check_template(t: Any, group: str, key: str, where: Any, declared=None) -> str:
    """A group's path template: its fields valid for ``group`` (built-in ones and the names
    ``declared`` in the group's ``fields``, which stand for ``{view}``), every required field
    used, a relative path with an image (or corner-list) suffix."""
    if not isinstance(t, str) or not t:
        raise _err(f"expected a path template string, got {fmt_value(t)}", key=key, path=where)
    declared = dict(declared or {})
    need = TEMPLATE_FIELDS[group]
    alt = _ALT_FIELDS.get(group, {})
    example = DEFAULT_FILES.get(group, {"calib.corners": "calib/{camera}/corners.npz",
                                        "olat.ambient": "olat/{camera}/ambient.png"}.get(group))
    try:
        parsed = list(string.Formatter().parse(t))
    except ValueError as exc:
        raise _err(
            f"bad template {fmt_value(t)} ({exc}); for example {fmt_value(example)}", key=key, path=where
        ) from exc
    used = set()
    valid = need + tuple(a for alts in alt.values() for a in alts) + tuple(declared)
    for _, name, _, conv in parsed:
        if name is None:
            continue
        if name not in valid:
            raise _err(
                f"template {fmt_value(t)} uses field {{{name}}}; valid fields here: "
                + ", ".join("{" + n + "}" for n in valid),
                key=key,
                path=where,
            )
        if conv is not None:
            raise _err(
                f"template {fmt_value(t)}: conversions (!{conv}) are not allowed", key=key, path=where
            )
        used.add(name)
    for n, alts in alt.items():
        both = [f for f in (n,) + alts if f in used]
        if len(both) > 1:
            raise _err(f"template {fmt_value(t)} uses " + " and ".join("{" + f + "}" for f in both)
                       + "; they name the same thing, use one", key=key, path=where)
        if both:
            used.add(n)
    if used & set(declared):  # a declared per-view field names the view
        used.add("view")
    # v2: a template may leave out {camera} when the rig has one camera (checked at load).
    missing = [n for n in need if n not in used and n != "camera"]
    if missing:
        raise _err(
            f"template {fmt_value(t)} must use every one of "
            + ", ".join("{" + n + "}" for n in need)
            + f" (missing {', '.join('{' + n + '}' for n in missing)}); for example {fmt_value(example)}",
            key=key,
            path=where,
        )
    try:
        sample = t.format(**_SAMPLE_FIELDS, **{n: (v[0] if isinstance(v, list) else v)
                                               for n, v in declared.items()})
    except (ValueError, TypeError, IndexError, KeyError) as exc:
        raise _err(
            f"template {fmt_value(t)} cannot be formatted ({exc}); for example {fmt_value(example)}",
            key=key,
            path=where,
        ) from exc
    _check_rel_path(sample, key, where)
    suffix = PurePosixPath(sample).suffix.lower()
    if group == "calib.corners":
        if suffix not in CORNER_SUFFIXES:
            raise _err(f"template {fmt_value(t)} must end in {' or '.join(CORNER_SUFFIXES)} (a "
                       "corner list)", key=key, path=where)
    elif suffix not in READ_SUFFIXES and not sample.endswith(ANY_SUFFIX):
        raise _err(
            f"template {fmt_value(t)} must end in an image suffix ({', '.join(READ_SUFFIXES)}) "
            f"or in {ANY_SUFFIX!r} (any of them, one file per frame)",
            key=key,
            path=where,
        )
    return t


def _check_value(kind: str, v: Any, key: str, where: Any, section: str, declared=None) -> Any:
    if kind == "format":
        if v != FORMAT:
            raise _err(
                f"format is {fmt_value(v)}; a facegeo scan says format = {fmt_value(FORMAT)}", key=key, path=where
            )
        return v
    if kind == "version":
        if isinstance(v, bool) or not isinstance(v, int):
            raise _err(f"version must be an integer, got {fmt_value(v)}", key=key, path=where)
        if v not in READ_VERSIONS:
            newer = " (newer than this facegeo; upgrade facegeo)" if v > VERSION else ""
            raise _err(
                f"unsupported version {v}{newer}; this facegeo reads versions "
                f"{', '.join(map(str, READ_VERSIONS))}",
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
        sub = {"calib.corners": "calib.corners", "olat.ambient": "olat.ambient"}.get(key, section)
        return _check_template(v, sub, key, where, declared if sub == section else None)
    if kind == "fields":
        return _check_fields(v, key, where)
    if kind == "board":
        if isinstance(v, str):
            return _check_rel_path(v, key, where)
        if isinstance(v, Mapping):
            if v.get("kind") not in BOARD_KINDS:
                raise _err(f"an inline board needs kind = one of "
                           f"{', '.join(repr(k) for k in BOARD_KINDS)}, got {fmt_value(v.get('kind'))}",
                           key=f"{key}.kind", path=where)
            return copy.deepcopy(dict(v))
        raise _err(f"expected a board file path or an inline board table, got {fmt_value(v)}",
                   key=key, path=where)
    if kind == "world":
        return _check_world(v, key, where)
    if kind == "cameras":
        return _check_cameras(v, section, key, where)
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


def _check_int_list(v: Any, key: str, where: Any, what: str) -> list:
    if not isinstance(v, list):
        raise _err(f"expected an array of {what}, got {fmt_value(v)}", key=key, path=where)
    seen = set()
    for i, x in enumerate(v):
        if isinstance(x, bool) or not isinstance(x, (int, str)) or (isinstance(x, int) and x < 0):
            raise _err(f"entry {i} is {fmt_value(x)}; expected {what}", key=key, path=where)
        if x in seen:
            raise _err(f"{fmt_value(x)} appears twice", key=key, path=where)
        seen.add(x)
    return list(v)


def _check_cameras(v: Any, group: str, key: str, where: Any) -> dict:
    """``[<group>.cameras.<camera>]`` tables: per-camera frame lists and usable bits (v2).

    Only the shape is checked here; camera names, views, frame and light names are checked
    against the rig and the group by :meth:`facegeo.capture.scan.Scan.validate`.
    """
    if not isinstance(v, Mapping):
        raise _err(f"expected a table of cameras, got {fmt_value(v)}", key=key, path=where)
    allowed = CAMERA_KEYS[group]
    out = {}
    for cam, t in v.items():
        ck = f"{key}.{cam}"
        if not isinstance(t, Mapping):
            raise _err(f"expected a table, got {fmt_value(t)}", key=ck, path=where)
        unknown = sorted(set(t) - set(allowed))
        if unknown:
            raise _err(f"unknown key {fmt_value(unknown[0])}; valid keys: {', '.join(allowed)}",
                       key=f"{ck}.{unknown[0]}", path=where)
        if "views" in t and "missing" in t:
            raise _err("give either views (the views this camera has) or missing (those it "
                       "lacks), not both", key=ck, path=where)
        entry = {}
        for k, x in t.items():
            if k == "views" or (k == "missing" and group.startswith("calib")):
                entry[k] = _check_int_list(x, f"{ck}.{k}", where, "view indices (integers ≥ 0)")
                if any(isinstance(y, str) for y in x):
                    raise _err("views are integers", key=f"{ck}.{k}", path=where)
            elif k == "missing":
                what = ("frame names" if group == "structured_light"
                        else "light indices or light names")
                entry[k] = _check_int_list(x, f"{ck}.{k}", where, what)
            else:  # bits_x / bits_y
                if isinstance(x, bool) or not isinstance(x, int) or x < 0:
                    raise _err(f"expected an integer ≥ 0 (Gray-code bits this camera resolves), "
                               f"got {fmt_value(x)}", key=f"{ck}.{k}", path=where)
                entry[k] = x
        out[str(cam)] = entry
    return out


def _check_world(v: Any, key: str, where: Any) -> dict:
    """``scan.world``: ``{camera, board_view}`` or ``{transform = 4×4}`` (v2)."""
    if not isinstance(v, Mapping):
        raise _err(f"expected a table, got {fmt_value(v)}", key=key, path=where)
    keys = set(v)
    if keys == {"camera", "board_view"}:
        if not isinstance(v["camera"], str) or not v["camera"]:
            raise _err(f"expected a camera name, got {fmt_value(v['camera'])}",
                       key=f"{key}.camera", path=where)
        bv = v["board_view"]
        if isinstance(bv, bool) or not isinstance(bv, int) or bv < 0:
            raise _err(f"expected a view index ≥ 0, got {fmt_value(bv)}", key=f"{key}.board_view",
                       path=where)
        return dict(v)
    if keys == {"transform"}:
        import numpy as np  # deferred

        t = v["transform"]
        ok = (isinstance(t, list) and len(t) == 4 and all(isinstance(r, list) and len(r) == 4
                                                           for r in t)
              and all(not isinstance(x, bool) and isinstance(x, (int, float))
                      for r in t for x in r))
        if not ok:
            raise _err(f"expected a 4×4 array of numbers (rows), got {fmt_value(t)}",
                       key=f"{key}.transform", path=where)
        T = np.asarray(t, dtype=np.float64)
        R = T[:3, :3]
        if (not np.isfinite(T).all() or not np.allclose(T[3], [0, 0, 0, 1])
                or not np.allclose(R @ R.T, np.eye(3), atol=1e-6)
                or np.linalg.det(R) <= 0):
            raise _err("expected a rigid transform T_world_rig: a rotation (orthonormal, det "
                       "+1) and a translation in metres, last row [0, 0, 0, 1]",
                       key=f"{key}.transform", path=where)
        return {"transform": [[float(x) for x in r] for r in t]}
    raise _err(f"expected {{ camera = \"<name>\", board_view = <int> }} or {{ transform = "
               f"<4×4 rows> }}, got keys {sorted(keys)}", key=key, path=where)


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
    declared = (_check_fields(table["fields"], f"{section}.fields", where)
                if "fields" in table and "fields" in spec else None)
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
        out[k] = _check_value(kind, table[k], key, where, section, declared)
    if declared:
        _check_declared_views(section, out, declared, where)
    return out


def _check_declared_views(section: str, out: dict, declared: dict, where: Any) -> None:
    """A group's declared per-view fields: one value per view, and — when its template names a
    view by them alone (no ``{view}``, ``{index}``, ``{number}``) — a different file per view."""
    n = out["views"]
    for name, vals in declared.items():
        if isinstance(vals, list) and len(vals) != n:
            raise _err(f"{len(vals)} values for {n} views ({section}.views); give one per view, "
                       "or one value for all", key=f"{section}.fields.{name}", path=where)
    names = _template_names(out["files"])
    if names & {"view", "index", "number"} - ({"index", "number"} if section != "calib" else set()):
        return
    per_view = [tuple((vals[v] if isinstance(vals, list) else vals)
                      for name, vals in sorted(declared.items()) if name in names)
                for v in range(n)]
    seen: dict = {}
    for v, key in enumerate(per_view):
        if key in seen:
            raise _err(f"views {seen[key]} and {v} fill {fmt_value(out['files'])} with the same "
                       f"fields {key}: two views, one file; give each view its own values (or use "
                       "{view})", key=f"{section}.fields", path=where)
        seen[key] = v


def _v2_keys_used(manifest: Mapping[str, Any]) -> list[str]:
    """The version-2 keys present in a manifest (dotted), and ``"files"`` templates that use
    v2 template features."""
    used = []
    for dotted in V2_KEYS:
        node: Any = manifest
        for part in dotted.split("."):
            node = node.get(part) if isinstance(node, Mapping) else None
            if node is None:
                break
        if node is not None:
            used.append(dotted)
    board = manifest.get("calib", {}).get("board") if isinstance(manifest.get("calib"), Mapping) else None
    if isinstance(board, Mapping):
        used.append("calib.board")
    for dotted in ("calib.files", "calib.projector.files", "structured_light.files", "olat.files"):
        node = manifest
        for part in dotted.split("."):
            node = node.get(part) if isinstance(node, Mapping) else None
        if isinstance(node, str) and (node.endswith(ANY_SUFFIX) or "{camera" not in node
                                      or any("{" + f in node for f in V2_TEMPLATE_FIELDS)):
            used.append(dotted)
    return used


def _flatten_ground_truth(table: Any, prefix: str, where: Any, out: dict) -> dict:
    if not isinstance(table, Mapping):
        raise _err(f"expected a table, got {_type_name(table)}", key=prefix, path=where)
    for k, v in table.items():
        key = f"{prefix}.{k}"
        if isinstance(v, Mapping):
            _flatten_ground_truth(v, key, where, out)
        else:
            _check_rel_path(v, key, where)
            out[key[len(key.split(".")[0]) + 1:]] = v
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
    if out["scan"]["version"] == 1:
        v2 = _v2_keys_used(manifest)
        if v2:
            raise _err(
                f"{v2[0]} is a version-2 feature but the manifest says version = 1; set "
                "scan.version = 2 (a version-2 reader reads every version-1 manifest unchanged)",
                key=v2[0], path=path)
    if "calib" in manifest:
        out["calib"] = _check_table("calib", manifest["calib"], path)
        if "projector" in manifest["calib"]:
            out["calib"]["projector"] = _check_table(
                "calib.projector", manifest["calib"]["projector"], path
            )
    for section in ("structured_light", "olat"):
        if section in manifest:
            out[section] = _check_table(section, manifest[section], path)
    cp = out.get("calib", {}).get("projector")
    if cp is not None and "structured_light" not in out and "frames" not in cp:
        raise _err(
            "[calib.projector] names its frames after structured_light.frames, but there is no "
            "[structured_light] section; give the projector-calibration captures their own "
            "frames (and patterns) in [calib.projector] (version 2)",
            key="calib.projector",
            path=path,
        )
    if "calib" in out:
        c = out["calib"]
        images = c.get("images", True)
        if not images and "corners" not in c:
            raise _err("images = false needs corner lists (calib.corners): without images or "
                       "corners there is nothing to calibrate from", key="calib.images", path=path)
        if out["scan"]["version"] >= 2:
            c.setdefault("images", True)
    if "reference" in manifest:
        _flatten_ground_truth(manifest["reference"], "reference", path, {})
        out["reference"] = copy.deepcopy(dict(manifest["reference"]))
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
