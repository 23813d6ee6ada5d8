"""Where a scan's files live, and whether they are there (private; used by :mod:`facegeo.capture.scan`).

Filling a group's path template (:func:`_format_template`), joining the result to the scan
directory while refusing anything that leads outside it, symlinks included (:class:`_Resolver`),
the public :func:`frame_path` that writers and the loader share (re-exported by
:mod:`facegeo.capture.scan`), and the on-disk check of one frame group of one camera against the rig
(:func:`_check_group_files`: every file present; every header read for size, channels, sample
type against the declared response and truncation; with ``full`` every frame decoded and its
pixels checked for NaN, inf, negative radiance, all-black and saturated frames, collected in a
:class:`FrameCheck`).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.capture._scan_schema import ANY_SUFFIX, _check_rel_path, _err
from facegeo.capture.imageio import READ_SUFFIXES, read_image, read_image_info
from facegeo.capture.response import saturated_mask
from facegeo.checks import fmt_value
from facegeo.errors import InputError, ScanFormatError


def _format_template(template: str, fields: Mapping[str, Any]) -> str:
    try:
        return template.format(**fields)
    except (KeyError, IndexError, ValueError, TypeError) as exc:
        raise InputError(f"cannot fill template {fmt_value(template)} with {fmt_value(dict(fields))}: {exc}") from exc


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
                f"{fmt_value(rel)} resolves to {real}, outside the scan directory {self.root_real} (a "
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
        capture order; see ``olat.light_order``); version-2 templates may instead use
        ``light_name`` (str), ``index`` (int, 0-based) or ``number`` (int, 1-based) — pass the
        fields the template uses (unused ones are ignored). A template ending in ``.*`` gives a
        path ending in ``.*``: write the frame with a real suffix in its place.

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


#: A decoded frame is flagged as saturated when at least this fraction of its pixels has a
#: channel at the top of the stored integer range (``saturated_mask``).
SATURATED_FRAME_FRACTION = 0.25


@dataclass(frozen=True)
class FrameProblem:
    """One problem with one frame file, found by :meth:`Scan.validate`.

    Attributes
    ----------
    path : Path
    key : str
        The manifest key the file belongs to (``"olat.files"``).
    label : str
        Which frame it is (``"camera 'cam_left', light 50"``).
    severity : {"error", "warning"}
        Errors make the scan invalid; warnings are reported (``facegeo info``) but the frame
        can still be used, through the validity masks of :meth:`Scan.olat_frame`.
    message : str
        What is wrong, without the path.
    """

    path: Path
    key: str
    label: str
    severity: str
    message: str


@dataclass
class FrameCheck:
    """What :meth:`Scan.validate` checked on the frame files and what it found.

    Attributes
    ----------
    n_headers : int
        Frames whose header was read (size, channels, sample type, completeness).
    n_decoded : int
        Frames whose pixels were decoded and inspected (``check="full"`` only).
    problems : list of FrameProblem
        In scan order.
    """

    n_headers: int = 0
    n_decoded: int = 0
    problems: list[FrameProblem] = field(default_factory=list)

    @property
    def errors(self) -> list[FrameProblem]:
        """The problems of severity ``"error"``."""
        return [p for p in self.problems if p.severity == "error"]

    @property
    def warnings(self) -> list[FrameProblem]:
        """The problems of severity ``"warning"``."""
        return [p for p in self.problems if p.severity == "warning"]

    def raise_first_error(self) -> None:
        """Raise the first error as a :class:`ScanFormatError` naming its file (and how many
        other frames failed); do nothing when there is none."""
        errors = self.errors
        if not errors:
            return
        e = errors[0]
        more = ""
        if len(errors) > 1:
            names = ", ".join(f"{p.path.parent.name}/{p.path.name}" for p in errors[1:4])
            more = (f"; {len(errors) - 1} more frame(s) fail the check too: {names}"
                    f"{', ...' if len(errors) > 4 else ''}")
        raise _err(f"{e.message} ({e.label}{more})", key=e.key, path=e.path)


def _bare_message(exc: Exception, path: Path) -> str:
    text = str(exc)
    prefix = f"{path}: "
    return text[len(prefix):] if text.startswith(prefix) else text


def _check_group_files(files, response, group: str, cam, *, full: bool,
                       report: FrameCheck | None = None) -> FrameCheck:
    """Check one frame group of one camera on disk.

    ``files`` is the group's ``[(label, path), …]`` for this camera (``Scan.expected_files``)
    and ``response`` the group's :class:`~facegeo.capture.response.Response`.

    A missing file raises at once (nothing else is worth checking). Otherwise every frame's
    header is read (:func:`~facegeo.capture.imageio.read_image_info` with ``verify``: size,
    channel count, sample type, a file that ends before its data does), and with ``full`` every
    frame is decoded and its pixels inspected: NaN and inf are errors; negative radiance, an
    all-black frame and a frame with at least :data:`SATURATED_FRAME_FRACTION` of its pixels
    saturated are warnings. Problems are appended to ``report`` (returned), not raised.
    """
    report = FrameCheck() if report is None else report
    missing = [(label, p) for label, p in files if not p.is_file()]
    if missing:
        label, p = missing[0]
        more = f" ({len(missing)} of {len(files)} {group} files of this camera are missing)"
        raise _err(
            f"missing {group} frame: camera {fmt_value(cam.name)}, {label}; expected file {p}{more}",
            key=f"{group}.files",
            path=p,
        )
    key = f"{group}.files"
    resp_key = f"{'calib' if group == 'calib.projector' else group}.response"
    expected = (cam.width, cam.height)
    first: tuple[int, np.dtype, Path] | None = None
    response_ok: dict[np.dtype, str | None] = {}
    good: list[tuple[str, Path]] = []

    def add(label, path, severity, message, k=key):
        report.problems.append(
            FrameProblem(path, k, f"camera {cam.name!r}, {label}", severity, message))

    for label, p in files:
        report.n_headers += 1
        try:
            info = read_image_info(p, verify=True)
        except ScanFormatError as exc:
            add(label, p, "error", _bare_message(exc, p))
            continue
        if info.size != expected:
            add(label, p, "error", _size_message(group, cam.name, info.size, expected))
            continue
        if info.channels not in (1, 3, 4):
            add(label, p, "error", f"image has {info.channels} channels; expected grey, RGB or "
                                   "RGBA")
            continue
        if info.dtype not in response_ok:
            try:
                if info.dtype.kind == "f":
                    response.linearize(np.zeros((1, 1), info.dtype))
                else:
                    response.lut(info.dtype)
                response_ok[info.dtype] = None
            except InputError as exc:
                response_ok[info.dtype] = str(exc)
        if response_ok[info.dtype] is not None:
            add(label, p, "error", response_ok[info.dtype], resp_key)
            continue
        if first is None:
            first = (info.channels, info.dtype, p)
        elif (info.channels, info.dtype) != first[:2]:
            add(label, p, "error",
                f"image is {info.dtype} with {info.channels} channel(s) but the group's first "
                f"frame {first[2].name} is {first[1]} with {first[0]}; a group's frames must "
                "agree")
            continue
        good.append((label, p))
    if full:
        for label, p in good:
            report.n_decoded += 1
            try:
                img = read_image(p)
            except ScanFormatError as exc:
                add(label, p, "error", _bare_message(exc, p))
                continue
            for severity, message in _pixel_problems(img):
                add(label, p, severity, message)
    return report


def _pixel_problems(img: np.ndarray) -> list[tuple[str, str]]:
    """``[(severity, message)]`` for one decoded frame (alpha ignored)."""
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    out = []
    n_px = img.shape[0] * img.shape[1]
    if img.dtype.kind == "f":
        nan = np.isnan(img)
        inf = np.isinf(img)
        if nan.any():
            n = int(_channel_any(nan).sum())
            out.append(("error", f"{n} pixel(s) are NaN (first at row, col "
                                 f"{_first_pixel(nan)})"))
        if inf.any():
            n = int(_channel_any(inf).sum())
            out.append(("error", f"{n} pixel(s) are infinite (first at row, col "
                                 f"{_first_pixel(inf)})"))
        finite = img[np.isfinite(img)]
        neg = finite < 0
        if neg.any():
            n = int(_channel_any(img < 0).sum())
            out.append(("warning", f"negative radiance in {n} pixel(s) (min "
                                   f"{fmt_value(float(finite.min()))})"))
        if finite.size == 0 or not (finite > 0).any():
            out.append(("warning", "all black (no pixel above 0)"))
    else:
        if not img.any():
            out.append(("warning", "all black (every sample is 0)"))
        sat = int(saturated_mask(img).sum())
        if sat >= SATURATED_FRAME_FRACTION * n_px:
            out.append(("warning", f"saturated: {100.0 * sat / n_px:.0f} % of pixels at the "
                                   f"top of the {img.dtype} range"))
    return out


def _channel_any(mask: np.ndarray) -> np.ndarray:
    return mask.any(axis=-1) if mask.ndim == 3 else mask


def _first_pixel(mask: np.ndarray) -> tuple[int, int]:
    r, c = np.argwhere(_channel_any(mask))[0]
    return int(r), int(c)


def _size_message(group: str, camera: str, found, expected) -> str:
    return (f"image is {found[0]}×{found[1]} px but camera {camera!r} is {expected[0]}×"
            f"{expected[1]} px in the rig (width × height)")


def _size_error(path: Path, group: str, camera: str, found, expected) -> ScanFormatError:
    return _err(_size_message(group, camera, found, expected), key=f"{group}.files", path=path)


# =========================================================================== v2 helpers


class _SuffixFinder:
    """Finds the one file behind a ``<stem>.*`` path (a template ending in ``.*``, v2): each
    frame may have its own readable image suffix. Directory listings are cached."""

    def __init__(self):
        self._dirs: dict[Path, dict[str, list[str]]] = {}

    def __call__(self, p: Path, key: str) -> Path:
        if not p.name.endswith(ANY_SUFFIX):
            return p
        stem = p.name[: -len(ANY_SUFFIX)]
        d = p.parent
        table = self._dirs.get(d)
        if table is None:
            table = {}
            try:
                names = os.listdir(d)
            except OSError:
                names = []
            for n in names:
                s, dot, suf = n.rpartition(".")
                if dot and "." + suf.lower() in READ_SUFFIXES:
                    table.setdefault(s, []).append(n)
            self._dirs[d] = table
        found = table.get(stem, [])
        if len(found) > 1:
            raise _err(f"{len(found)} files match {p.name}: {', '.join(sorted(found))}; a frame "
                       "must have exactly one file", key=key, path=p)
        return d / found[0] if found else p


@dataclass(frozen=True)
class CornerView:
    """The board corners one camera saw in one calibration view (a corner list entry).

    Attributes
    ----------
    ids : (N,) int64
        Corner ids on the board (for a chessboard: the index in OpenCV's corner order).
    object_points : (N, 3) float64, metres, board frame
    image_points : (N, 2) float64, pixels (pixel centres at integers, ``docs/conventions.md``)
    """

    ids: np.ndarray
    object_points: np.ndarray
    image_points: np.ndarray


#: Arrays of an ``.npz`` corner list and the columns of a ``.csv`` one.
CORNER_ARRAYS = ("view", "ids", "object_points", "image_points")
CORNER_COLUMNS = ("view", "id", "x", "y", "z", "u", "v")
#: Fewest corners a view may have (a homography needs 4 points).
MIN_CORNERS = 4


def read_corner_list(path: Path, *, key: str = "calib.corners") -> dict[int, CornerView]:
    """Read and check one camera's corner list: ``{view: CornerView}``.

    ``.npz``: arrays ``view (N,)`` int, ``ids (N,)`` int, ``object_points (N, 3)`` float metres,
    ``image_points (N, 2)`` float pixels, one row per corner of every view. ``.csv``: a header
    line ``view,id,x,y,z,u,v`` and one row per corner.

    Raises
    ------
    ScanFormatError
        Missing or unreadable file, wrong arrays / columns, a shape mismatch, non-finite values,
        non-integer views or ids, a corner id twice in one view, or a view with fewer than
        :data:`MIN_CORNERS` corners; the message names the file and the key.
    """
    if not path.is_file():
        raise _err(f"corner list not found: {path}", key=key, path=path)
    try:
        if path.suffix.lower() == ".npz":
            with np.load(path, allow_pickle=False) as z:
                names = sorted(z.files)
                if names != sorted(CORNER_ARRAYS):
                    raise _err(f"a corner list holds the arrays {', '.join(CORNER_ARRAYS)}; this "
                               f"one holds {', '.join(names) or 'none'}", key=key, path=path)
                arrays = {k: np.asarray(z[k]) for k in CORNER_ARRAYS}
        else:
            with open(path, encoding="utf-8") as fh:
                header = [h.strip() for h in fh.readline().split(",")]
            if tuple(header) != CORNER_COLUMNS:
                raise _err(f"a CSV corner list starts with the header line "
                           f"{','.join(CORNER_COLUMNS)}; this one has {','.join(header)}",
                           key=key, path=path)
            t = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, dtype=np.float64)
            if t.size and t.shape[1] != len(CORNER_COLUMNS):
                raise _err(f"rows have {t.shape[1]} columns; expected {len(CORNER_COLUMNS)} "
                           f"({','.join(CORNER_COLUMNS)})", key=key, path=path)
            t = t.reshape(-1, len(CORNER_COLUMNS))
            arrays = {"view": t[:, 0], "ids": t[:, 1], "object_points": t[:, 2:5],
                      "image_points": t[:, 5:7]}
    except ScanFormatError:
        raise
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise _err(f"cannot read the corner list ({exc})", key=key, path=path) from exc
    view, ids = arrays["view"], arrays["ids"]
    obj, img = arrays["object_points"], arrays["image_points"]
    n = view.shape[0] if view.ndim == 1 else -1
    want = {"view": (n,), "ids": (n,), "object_points": (n, 3), "image_points": (n, 2)}
    for k, a in arrays.items():
        if n < 0 or a.shape != want[k]:
            shown = {kk: tuple(aa.shape) for kk, aa in arrays.items()}
            raise _err(f"{k} has shape {tuple(a.shape)}; a corner list of N corners has view "
                       f"(N,), ids (N,), object_points (N, 3), image_points (N, 2) (got "
                       f"{shown})", key=key, path=path)
        if a.dtype.kind not in "iuf" or not np.isfinite(a).all():
            raise _err(f"{k} must be finite numbers", key=key, path=path)
    for k in ("view", "ids"):
        a = arrays[k]
        if (a != np.round(a)).any() or (a < 0).any():
            raise _err(f"{k} must be integers ≥ 0", key=key, path=path)
    view = view.astype(np.int64)
    ids = ids.astype(np.int64)
    out = {}
    for v in np.unique(view):
        m = view == v
        if m.sum() < MIN_CORNERS:
            raise _err(f"view {int(v)} has {int(m.sum())} corner(s); a view needs at least "
                       f"{MIN_CORNERS} (drop it from the list instead)", key=key, path=path)
        vid = ids[m]
        if np.unique(vid).size != vid.size:
            raise _err(f"view {int(v)} lists a corner id twice", key=key, path=path)
        out[int(v)] = CornerView(vid, obj[m].astype(np.float64), img[m].astype(np.float64))
    return out


def board_from_dict(d: Any, where: Path, key: str = "calib.board"):
    """A board from ``board.json`` or an inline ``calib.board`` table.

    ``kind = "charuco"`` (or no kind: the version-1 ``board.json``) is a
    :class:`facegeo.geometry.board.CharucoBoard`; ``"chessboard"`` (``cols``, ``rows``,
    ``square_size``) a :class:`~facegeo.geometry._calib_detect.ChessboardSpec`; ``"circles"``
    (``cols``, ``rows``, ``spacing``, ``asymmetric``) a
    :class:`~facegeo.geometry._calib_detect.CircleGridSpec`.
    """
    from facegeo.geometry._calib_detect import ChessboardSpec, CircleGridSpec
    from facegeo.geometry.board import CharucoBoard

    if not isinstance(d, Mapping):
        raise _err(f"a board is a table, got {fmt_value(d)}", key=key, path=where)
    d = dict(d)
    kind = d.pop("kind", "charuco")
    fields = {"chessboard": ("cols", "rows", "square_size"),
              "circles": ("cols", "rows", "spacing", "asymmetric")}
    try:
        if kind == "charuco":
            return CharucoBoard.from_dict(d)
        if kind not in fields:
            raise InputError(f"kind: expected one of charuco, chessboard, circles, got "
                             f"{fmt_value(kind)}")
        d.pop("format", None)
        d.pop("version", None)
        unknown = sorted(set(d) - set(fields[kind]))
        if unknown:
            raise InputError(f"{unknown[0]}: unknown field for a {kind} board (expected "
                             f"{', '.join(fields[kind])})")
        spec = ChessboardSpec if kind == "chessboard" else CircleGridSpec
        return spec(**d)
    except (InputError, TypeError) as exc:
        raise _err(f"bad board: {exc}", key=key, path=where) from exc
