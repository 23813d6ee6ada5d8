"""A scan's input files in a store, for engine tasks on workers that share no disk (issue 38).

``--store URL`` gives the stages a folder or fsspec store (``s3://bucket/prefix``) for what
their tasks write (docs/scale.md §3). A task also has to *read* its inputs — a camera's
frames — and on such a cluster the scan folder is only on the client. The scan's input files
then live in the store too, under ``URL/scan/`` at the same relative paths as in the scan
folder: put there once by :func:`put_scan` (``facegeo push SCAN URL``), or by any tool that
copies folders into the store (``aws s3 sync SCAN s3://bucket/prefix/scan``). A task given
:func:`scan_location` fetches only the files it reads (:func:`fetch_scan_files`: the rig, its
camera's frames, the response tables, the ground truth it compares with) into a temporary
folder of its worker and reads the scan from there
(:meth:`facegeo.capture.scan.Scan.relocated`); the client, which loaded the scan, names those
files (:func:`relative_files`), so a worker never lists the store.

The same two helpers move any stage's input files through a store: :func:`put_files` (by name,
or at paths relative to a folder: the projection's atlas and mesh, the render's inputs) and
:func:`fetch_files` (a task's way back, streamed).
"""

from __future__ import annotations

import logging
from pathlib import Path

from facegeo.errors import InputError

log = logging.getLogger(__name__)

__all__ = ["SCAN_IN_STORE", "scan_location", "has_scan", "put_scan", "relative_files",
           "fetch_scan_files", "sl_task_files", "olat_task_files", "put_files",
           "fetch_files"]

#: The folder of a store holding the scan's input files (``URL/scan/``).
SCAN_IN_STORE = "scan"


def scan_location(store):
    """``store/scan``: where the scan's input files are in a store."""
    from facegeo.surface._zarr_field import store_location

    return store_location(store, SCAN_IN_STORE)


def has_scan(store) -> bool:
    """Whether ``store`` holds a scan (``scan/scan.toml``)."""
    from facegeo.capture.scan import MANIFEST_NAME
    from facegeo.surface._zarr_field import _local, store_location

    loc = _local(store_location(scan_location(store), MANIFEST_NAME))
    if isinstance(loc, Path):
        return loc.is_file()
    import fsspec

    fs, path = fsspec.core.url_to_fs(loc)
    return bool(fs.exists(path))


def relative_files(scan, paths) -> list[str]:
    """``paths`` (files of ``scan``) relative to the scan folder, as POSIX strings."""
    root = Path(scan.root)
    out = []
    for p in paths:
        try:
            out.append(Path(p).relative_to(root).as_posix())
        except ValueError:
            raise InputError(f"{p}: not inside the scan folder {root}") from None
    return out


def put_scan(scan, store, *, progress=None) -> dict:
    """Copy ``scan``'s manifest and every input file it names
    (:meth:`~facegeo.capture.scan.Scan.input_files`: rig, board, responses, corner lists,
    frames, references, ground truth; never ``out/``) into ``store/scan/`` at the same
    relative paths. Returns ``{"files": n, "bytes": b, "location": …}``.
    ``progress(stage, done, total)`` is called per file."""
    from facegeo.surface._zarr_field import put_bytes, store_location

    named = [Path(p) for p in scan.input_files()]  # resolves every frame: once
    files = [scan.manifest_path] + [p for p in named if p.is_file()]
    for p in named:  # directories named as such (a reference folder)
        if p.is_dir():
            files += sorted(q for q in p.rglob("*") if q.is_file())
    rels = relative_files(scan, files)
    dest = scan_location(store)
    n_bytes = 0
    for k, (p, rel) in enumerate(zip(files, rels)):
        data = Path(p).read_bytes()
        put_bytes(store_location(dest, *rel.split("/")), data)
        n_bytes += len(data)
        if progress:
            progress("push", k + 1, len(files))
    log.info("push: %d files, %.1f MB -> %s", len(files), n_bytes / 1e6, dest)
    return {"files": len(files), "bytes": n_bytes, "location": str(dest)}


def fetch_scan_files(scan, location, rels, local_root) -> object:
    """Fetch the files ``rels`` (relative paths, :func:`relative_files`) of the scan at
    ``location`` (``store/scan``) into ``local_root`` (:func:`fetch_files`) and return ``scan``
    read from there (:meth:`~facegeo.capture.scan.Scan.relocated`). A file missing in the store
    is an :class:`InputError` naming it."""
    fetch_files(location, rels, local_root, what="the scan's file",
                hint="put the scan there first: facegeo push SCAN URL")
    return scan.relocated(Path(local_root))


def fetch_files(location, rels, root, *, what: str = "the file",
                hint: str = "removed while the stage ran?") -> None:
    """Fetch the files ``rels`` (POSIX paths relative to the store folder ``location``) into the
    folder ``root`` at the same relative paths, streamed (a field is not read into memory; a
    task's temporary copy: no fsync). The way back of :func:`put_files` with ``root``.

    A file missing in the store is an :class:`InputError`
    ``"<location>: <what> <rel> is not in the store (<hint>)"``."""
    import shutil

    from facegeo.surface._zarr_field import store_location

    for rel in rels:
        src, dst = store_location(location, *rel.split("/")), Path(root) / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        try:
            if isinstance(src, Path):
                shutil.copyfile(src, dst)
            else:
                import fsspec

                fs, path = fsspec.core.url_to_fs(src)
                fs.get_file(path, str(dst))
        except (FileNotFoundError, OSError) as exc:
            raise InputError(f"{src}: {what} {rel} is not in the store ({hint})") from exc


def sl_task_files(scan, camera: str, frames) -> list[str]:
    """What a decode task of ``camera`` reads from the scan: the rig file, the camera's
    structured-light ``frames``, the structured-light response table (if any) and, on a
    synthetic scan, the ground truth its accuracy figures compare with (the true rig and the
    camera's geometry) — relative paths for :func:`fetch_scan_files`."""
    from collections.abc import Mapping

    m = scan.manifest
    paths = [scan.root / m["scan"]["rig"]]
    paths += [scan.sl_path(camera, f) for f in frames]
    spec = m.get("structured_light", {}).get("response")
    if isinstance(spec, Mapping) and spec.get("kind") == "table":
        paths.append(scan.root / spec["file"])
    keys = scan.ground_truth_keys
    for k in ("rig", f"geometry_{camera}"):
        if k in keys:
            paths.append(scan.ground_truth_path(k))
    return relative_files(scan, paths)


def olat_task_files(scan, camera: str, *, ground_truth_mesh: bool = False) -> list[str]:
    """What a projection task of ``camera`` reads from the scan: the rig file, the camera's
    OLAT frames and ambient frame (:meth:`~facegeo.capture.scan.Scan.expected_files`), the
    OLAT response table (if any) and, with ``ground_truth_mesh`` (``--mesh ground_truth``),
    the true mesh — relative paths for :func:`fetch_scan_files`."""
    from collections.abc import Mapping

    m = scan.manifest
    paths = [scan.root / m["scan"]["rig"]]
    paths += [p for _, p in scan.expected_files("olat", camera)]
    spec = m.get("olat", {}).get("response")
    if isinstance(spec, Mapping) and spec.get("kind") == "table":
        paths.append(scan.root / spec["file"])
    if ground_truth_mesh:
        paths.append(scan.ground_truth_path("mesh"))
    return relative_files(scan, paths)


def put_files(paths, location, *, root=None) -> list[str]:
    """Copy files of this machine into the store folder ``location``, streamed (a field is not
    read into memory); into a folder store atomically.

    Without ``root``, ``paths`` are files put by their names: the stage products a task reads
    (the atlas, the mesh), put once by the client for every task, which brings them down with
    :func:`facegeo.surface._zarr_field.copy_files`. With ``root``, ``paths`` are POSIX paths
    relative to ``root``, put at the same relative paths (a render's inputs, brought down by
    :func:`fetch_files`). Returns the names (relative paths) put."""
    import shutil

    from facegeo.fsutil import atomic_path
    from facegeo.surface._zarr_field import store_location

    names = []
    for p in paths:
        src, rel = (Path(p), Path(p).name) if root is None else (Path(root) / p, str(p))
        dst = store_location(location, *rel.split("/"))
        if isinstance(dst, Path):
            with atomic_path(dst) as tmp:
                shutil.copyfile(src, tmp)
        else:
            import fsspec

            fs, path = fsspec.core.url_to_fs(dst)
            fs.put_file(str(src), path)
        names.append(rel)
    return names
