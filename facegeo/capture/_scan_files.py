"""Where a scan's files live, and whether they are there (private; used by :mod:`facegeo.capture.scan`).

Filling a group's path template (:func:`_format_template`), joining the result to the scan
directory while refusing anything that leads outside it, symlinks included (:class:`_Resolver`),
the public :func:`frame_path` that writers and the loader share (re-exported by
:mod:`facegeo.capture.scan`), and the on-disk check of one frame group of one camera against the rig
(:func:`_check_group_files`: every file present, right size, decodable with the declared
response).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from facegeo.capture._scan_schema import _check_rel_path, _err
from facegeo.errors import InputError, ScanFormatError
from facegeo.capture.imageio import read_image, read_image_size


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


def _check_group_files(files, response, group: str, cam, *, full: bool) -> None:
    """Check one frame group of one camera on disk; raise the first problem found.

    ``files`` is the group's ``[(label, path), …]`` for this camera (``Scan.expected_files``)
    and ``response`` the group's :class:`~facegeo.capture.response.Response`.
    """
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
