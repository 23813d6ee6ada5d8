"""Turn a folder of frames plus a small description into a scan (``facegeo import``).

A real data set arrives as a folder of images (and maybe a calibration file or a list of
detected corners) named the way its authors chose. The *description* is a version-2
``scan.toml`` written for that folder: its ``files`` templates (``.*`` for mixed suffixes,
``{light_name}`` for named lights), per-camera tables and ``rig`` point at the folder's own
files, relative to it. An optional ``[import]`` table says how to carry files over::

    [import]
    mode = "link"            # "link" (hard links, the default; copies across file systems)
                             # or "copy"

:func:`import_folder` validates the description against the source folder (the full
:func:`~facegeo.capture.scan.load_scan` quick check: every expected frame present, every
header readable, sizes against the rig), then hard-links (or copies) exactly the files the
manifest names — rig, board, response tables, corner lists, frames, references — into the
destination at the same relative paths, and writes the manifest there last, so the new scan is
complete once ``scan.toml`` exists. The source folder is never modified; files it holds that
the description does not name are not carried over.
"""

from __future__ import annotations

import logging
import os
import shutil
import tomllib
from pathlib import Path
from typing import Any

from facegeo.capture._scan_schema import _err
from facegeo.capture.scan import MANIFEST_NAME, Scan, write_manifest
from facegeo.checks import check_choice, fmt_value
from facegeo.errors import InputError, ScanFormatError

__all__ = ["import_folder", "IMPORT_MODES", "check_destination"]

log = logging.getLogger(__name__)

#: How files are carried from the source folder to the scan.
IMPORT_MODES = ("link", "copy")


def check_destination(src: Path, dest: Path) -> None:
    """Where an import may write: a new path or an empty directory, outside the source folder.

    Importing never writes into the source (the data set, a real capture): a destination
    inside it — or the source itself — would add a scan to it. Raises InputError naming the
    destination (shared by :func:`import_folder` and
    :func:`facegeo.capture.datasets.import_dataset`).
    """
    s, d = Path(src).resolve(), Path(dest).resolve()
    if d == s or s in d.parents:
        raise InputError(f"{dest}: inside the source folder {src}; importing never writes into "
                         "the source — choose a destination outside it")
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise InputError(f"{dest}: exists and is not an empty directory; importing never "
                         "overwrites")


def _read_description(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise _err(f"cannot read the description ({exc.strerror or exc})", path=path) from exc
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise _err(f"TOML syntax error: {exc}", path=path) from exc


def _carry(src: Path, dst: Path, mode: str) -> str:
    """Hard-link (or copy) one file; returns how it was carried."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if mode == "link":
        try:
            os.link(src, dst)
            return "link"
        except OSError as exc:  # another file system, or links not supported
            log.debug("cannot hard-link %s (%s); copying", src, exc)
    shutil.copy2(src, dst)
    return "copy"


def import_folder(src: str | os.PathLike, dest: str | os.PathLike,
                  description: str | os.PathLike | dict[str, Any], *,
                  mode: str | None = None, rig: Any = None) -> Scan:
    """Make a scan at ``dest`` from the frames in ``src`` and a description.

    Parameters
    ----------
    src : path-like
        The folder as the data set ships it (read only).
    dest : path-like
        The new scan directory; must not exist or be empty.
    description : path-like or dict
        A version-2 manifest (``docs/scan-format.md``) whose paths are relative to ``src``,
        optionally with an ``[import]`` table (``mode``); a path to such a TOML file or the
        parsed dict.
    mode : {"link", "copy"}, optional
        Overrides ``import.mode`` (default ``"link"``: hard links, falling back to a copy when
        ``dest`` is on another file system).
    rig : Rig or path-like, optional
        The rig, when the data set does not ship a facegeo ``rig.json`` (most do not): a
        :class:`facegeo.geometry.rig.Rig` or the path of a rig file anywhere. It is written to
        ``dest`` at ``scan.rig``; ``src`` then needs no rig file.

    Returns
    -------
    Scan
        The new scan, loaded and validated (quick check) from ``dest``.

    Raises
    ------
    ScanFormatError
        The description is invalid, or does not match ``src`` (a missing frame, a wrong size,
        ...: the message names the source file and the key); ``dest`` is a non-empty directory
        or a file; a file the manifest names is a directory.
    """
    from facegeo.capture.scan import load_scan

    src, dest = Path(src), Path(dest)
    if not src.is_dir():
        raise _err("source folder not found", path=src)
    if isinstance(description, (str, os.PathLike)):
        where = Path(description)
        manifest = _read_description(where)
    else:
        where = src / "(description)"
        manifest = dict(description)
    opts = manifest.pop("import", {})
    if not isinstance(opts, dict) or set(opts) - {"mode"}:
        raise _err(f"[import] takes only mode = \"link\" or \"copy\", got {fmt_value(opts)}",
                   key="import", path=where)
    mode = mode if mode is not None else opts.get("mode", "link")
    check_choice(mode, "mode", IMPORT_MODES)
    check_destination(src, dest)
    source = Scan(src, manifest, manifest_path=where)
    rig_file = source.root / source.manifest["scan"]["rig"]
    if rig is not None:
        from facegeo.geometry.rig import Rig

        if not isinstance(rig, Rig):
            rig = Rig.load(rig)
        source.__dict__["rig"] = rig  # the cached property: validate against this rig
    source.validate("quick")
    files = [p for p in source.input_files() if rig is None or p != rig_file]
    carried = {"link": 0, "copy": 0}
    created = not dest.exists()
    dest.mkdir(parents=True, exist_ok=True)
    try:
        for p in files:
            if p.is_dir():
                raise _err("is a directory; the import carries files (name its files in the "
                           "manifest)", path=p)
            carried[_carry(p, dest / p.relative_to(source.root), mode)] += 1
        if rig is not None:
            rig.save(dest / source.manifest["scan"]["rig"])
        write_manifest(dest, source.manifest)
    except (ScanFormatError, OSError):
        log.debug("import into %s failed; removing what it wrote", dest)
        if created:
            shutil.rmtree(dest, ignore_errors=True)
        else:
            for child in dest.iterdir():
                shutil.rmtree(child) if child.is_dir() else child.unlink()
        raise
    log.info("imported %d file(s) from %s into %s (%d hard link(s), %d copie(s))",
             len(files), src, dest, carried["link"], carried["copy"])
    return load_scan(dest / MANIFEST_NAME)
