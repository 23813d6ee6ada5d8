"""The scan directory: its ``scan.toml`` manifest, validation, and lazy access to frames.

A real light stage and the synthetic generator (:mod:`facegeo.synth`) write the same layout,
documented key by key in ``docs/scan-format.md``::

    <scan>/scan.toml                        the manifest (this module's schema, version 1)
    <scan>/rig.json                         cameras, projector, light stage (facegeo.geometry.rig)
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

The schema (key tables, value and template checks, path-safety checks) lives in the private
module :mod:`facegeo.capture._scan_schema`, file resolution and the on-disk frame checks in
:mod:`facegeo.capture._scan_files`; every public name is importable from here.
"""

from __future__ import annotations

import copy
import functools
import logging
import os
import tomllib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.capture._scan_files import (
    SATURATED_FRAME_FRACTION,
    FrameCheck,
    FrameProblem,
    _check_group_files,
    _format_template,
    _Resolver,
    _size_error,
    frame_path,
)
from facegeo.capture._scan_schema import (
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
        """The calibration board (:class:`facegeo.geometry.board.CharucoBoard`, loaded on first use)."""
        from facegeo.geometry.board import CharucoBoard

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
            raise InputError(f"view: expected an integer in [0, {n}), got {fmt_value(view)}")
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
                f"no ground-truth entry {fmt_value(key)}; entries: {', '.join(flat) or '(none)'}",
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
        frame : (H, W, 3) float32, linear radiance
            The linearised pixel values divided by ``[olat] exposure``. Grey frames are
            repeated to three channels; alpha is dropped.
        valid : (H, W) bool, only with ``return_mask``
            False where a sample is saturated or black-clipped (integer frames) or non-finite
            (float frames).
        """
        lin, valid = self._read("olat", camera, self.olat_path(camera, light),
                                return_mask=return_mask)
        exposure = float(self.manifest["olat"].get("exposure", 1.0))
        if exposure != 1.0:
            lin = lin / np.float32(exposure)
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
                    f"projector = {fmt_value(self.sl_projector)} but the rig's projector is {fmt_value(proj.name)}",
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
    seen: set = set()
    size_in = _du(scan.root, skip=out, seen=seen)
    size_out = _du(out, seen=seen) if out.is_dir() else 0
    lines.append(f"  size on disk: {_fmt_bytes(size_in)} (inputs), {_fmt_bytes(size_out)} (out/)")
    return "\n".join(lines)
