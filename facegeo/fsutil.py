"""Safe file output: atomic files, staged directories, a record of what facegeo wrote.

* :func:`atomic_path` / :func:`atomic_write_bytes` / :func:`atomic_write_text`: write to a
  temporary file beside the target, then rename. A reader never sees a half-written file, and a
  failure (an exception or Ctrl-C) leaves the previous file (or nothing) and no temporary file.
* :func:`staging_dir` / :func:`swap_in_dir` / :func:`clean_stale_siblings`: build a whole
  directory beside its destination (``.NAME.facegeo-tmp-PID-XXXX``) and swap it in only once
  complete, so an interrupted or failing run leaves the old directory intact.
* :func:`read_written_record` / :func:`write_written_record`: the list of files facegeo wrote in
  a scan directory (:data:`WRITTEN_RECORD`), so that replacing a scan removes only those and
  carries every other file over (:func:`carry_over`).
* :func:`remove_tree`: deletes a directory tree without ever following a symlink.
* :class:`NpyRowFile`: a ``.npy`` file of known shape, preallocated and written block by block
  (direct writes for aligned blocks, :func:`aligned_empty`): large arrays written in chunks
  without a page fault per page of a memory map or new page-cache memory per write.
* :func:`read_ahead`: files read (decoded) a few ahead of their consumer on worker threads, in
  order, with a bound on the bytes in flight.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import re
import shutil
import stat
import tempfile
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from facegeo.checks import fmt_value

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_text", "load_json_file",
           "WRITTEN_RECORD", "read_written_record", "write_written_record", "add_to_written_record",
           "list_files",
           "remove_tree", "staging_dir", "swap_in_dir", "clean_stale_siblings", "carry_over",
           "staged_directory", "NpyRowFile", "aligned_empty", "DIRECT_ALIGN", "read_ahead",
           "READ_AHEAD_WORKERS", "file_state"]

log = logging.getLogger(__name__)


def file_state(path: str | os.PathLike) -> tuple | None:
    """``(size, mtime_ns)`` of ``path``, or None when it cannot be stat-ed (a cache key part:
    a rewritten file changes it without reading the file)."""
    try:
        st = Path(path).stat()
    except OSError:
        return None
    return st.st_size, st.st_mtime_ns

#: Name of the record, at the top of a scan directory, of every file facegeo wrote there: a
#: text file, one POSIX path relative to the scan directory per line, ``#`` lines are comments.
WRITTEN_RECORD = ".facegeo-written"

_RECORD_HEADER = (
    "# facegeo: the files facegeo wrote in this scan directory, one relative POSIX path per line.\n"
    "# Replacing the scan (facegeo synth --overwrite) removes only these; every other file is\n"
    "# carried over into the new scan. Do not list your own files here.\n"
)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    Parameters
    ----------
    path : path-like
        Final destination. Its parent directory is created if needed.
    suffix : str, optional
        Suffix of the temporary file (default: ``path``'s own suffix, so writers that pick a
        format by extension keep working).

    Notes
    -----
    On an exception (``KeyboardInterrupt`` included) the temporary file is removed and
    ``path`` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=path.suffix if suffix is None else suffix, dir=path.parent
    )
    tmp_path = Path(tmp)
    try:  # from here on, any exception or Ctrl-C removes the temporary file
        os.close(fd)
        # mkstemp creates 0600 files; give the result the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise
    _note_written(path.parent, [path.name])


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | os.PathLike, text: str, *, encoding: str = "utf-8") -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding=encoding)


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 hex digest of a file's bytes (read in blocks, not held in memory)."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def load_json_file(path: str | os.PathLike, what: str, parse):
    """Read a JSON file and build an object from it with ``parse(dict)``.

    Every failure becomes a :class:`~facegeo.errors.ScanFormatError` naming the file: unreadable
    file, invalid JSON (with line and column), or an :class:`~facegeo.errors.InputError` from
    ``parse`` — whose ``"field: message"`` prefix becomes the error's ``key``.

    Parameters
    ----------
    path : path-like
    what : str
        What the file holds, for messages (``"rig"``, ``"board"``).
    parse : callable(object) -> T
    """
    import json

    from facegeo.errors import InputError, ScanFormatError

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ScanFormatError(f"cannot read {what} file ({exc.strerror})", path=path) from exc
    try:
        d = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ScanFormatError(
            f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}", path=path
        ) from exc
    try:
        return parse(d)
    except InputError as exc:
        key, sep, rest = str(exc).partition(": ")
        if not sep:
            key, rest = None, str(exc)
        raise ScanFormatError(f"malformed {what}: {rest}", path=path, key=key) from exc


# =========================================================================== written-files record


def read_written_record(root: str | os.PathLike) -> set[str] | None:
    """The relative POSIX paths listed in ``root / WRITTEN_RECORD``, or None if it is absent.

    Raises
    ------
    OSError
        The record exists but cannot be read.
    """
    p = Path(root) / WRITTEN_RECORD
    if not p.is_file() or p.is_symlink():
        return None
    lines = p.read_text(encoding="utf-8").splitlines()
    return {ln.strip() for ln in lines if ln.strip() and not ln.lstrip().startswith("#")}


def write_written_record(root: str | os.PathLike, rel_paths: Iterable[str]) -> Path:
    """Write (atomically, replacing any previous one) the record of the files facegeo wrote.

    Parameters
    ----------
    root : path-like
        The scan directory.
    rel_paths : iterable of str
        POSIX paths relative to ``root``. The record itself is implied and left out.
    """
    paths = sorted({str(r) for r in rel_paths} - {WRITTEN_RECORD})
    for r in paths:
        if r.startswith("/") or ".." in r.split("/") or "\n" in r:
            raise ValueError(f"written record: {fmt_value(r)} is not a relative path inside the scan")
    target = Path(root) / WRITTEN_RECORD
    atomic_write_text(target, _RECORD_HEADER + "".join(r + "\n" for r in paths))
    return target


def add_to_written_record(root: str | os.PathLike, rel_paths: Iterable[str]) -> Path:
    """Add paths to the record of the files facegeo wrote in ``root`` (created if absent).

    Products written into a scan (``out/...``) are added by :func:`atomic_path` and
    :func:`staged_directory` themselves (:func:`_note_written`), so a later ``facegeo synth
    --overwrite`` removes them with the scan they were computed from instead of carrying them
    over as the user's files.
    """
    return write_written_record(root, (read_written_record(root) or set()) | set(rel_paths))


#: How many directories above a written file :func:`_note_written` looks for the scan it lies
#: in (``SCAN/out/<stage>/<camera>/file`` is four below ``SCAN``).
_RECORD_SEARCH_DEPTH = 5
#: The folder of a scan whose files :func:`_note_written` records: the products folder.
_PRODUCTS = "out"
#: A record grown past this by appends (the same products written run after run) is rewritten
#: without its repeated lines.
_RECORD_COMPACT_BYTES = 1 << 20
_record_lock = threading.Lock()


def _note_written(parent: Path, names: list[str]) -> None:
    """Add products just written (``parent / name``) to the written record of the scan they
    lie in: the nearest of ``parent``'s first :data:`_RECORD_SEARCH_DEPTH` ancestors holding
    a ``scan.toml`` (so a scan nested in another owns its files), when it carries a record
    (only synthetic scans do) and the files lie in its products folder ``out/`` — what a file
    saved elsewhere in the scan with the library (a rig of yours, say) is not: it stays the
    user's. Files inside hidden directories (staging folders, ``.NAME.facegeo-tmp-…``) are
    skipped. The lines are appended under a file lock (two processes writing into one scan
    keep both their entries). A record that cannot be updated costs a warning, never the
    write that succeeded."""
    try:
        here = Path(parent).absolute()
        d = here
        for _ in range(_RECORD_SEARCH_DEPTH):
            if (d / "scan.toml").is_file():
                break
            if d.parent == d:
                return
            d = d.parent
        else:
            return
        if not (d / WRITTEN_RECORD).is_file():
            return
        prefix = here.relative_to(d).as_posix()
    except (OSError, ValueError):
        return
    rels = []
    for name in names:
        rel = name if prefix == "." else f"{prefix}/{name}"
        parts = rel.split("/")
        if (parts[0] != _PRODUCTS or len(parts) < 2 or "\n" in rel
                or any(p.startswith(".") for p in parts[:-1])):
            continue
        rels.append(rel)
    if not rels:
        return
    try:
        with _record_lock, open(d / WRITTEN_RECORD, "a", encoding="utf-8") as fh:
            with contextlib.suppress(ImportError, OSError):
                import fcntl

                fcntl.flock(fh, fcntl.LOCK_EX)  # released when the file closes
            fh.write("".join(r + "\n" for r in rels))
            fh.flush()
            if fh.tell() > _RECORD_COMPACT_BYTES:  # reruns append the same paths again
                write_written_record(d, read_written_record(d) or ())
    except OSError as exc:
        log.warning("%s: could not add %d written file(s) to the record (%s); a later "
                    "'facegeo synth --overwrite' keeps them", d / WRITTEN_RECORD, len(rels), exc)


def list_files(root: str | os.PathLike) -> list[str]:
    """Every non-directory entry under ``root`` (files and symlinks, never descending into a
    symlinked directory), as sorted POSIX paths relative to ``root``."""
    root = Path(root)
    out: list[str] = []

    def walk(d: Path, prefix: str) -> None:
        with os.scandir(d) as it:
            for e in it:
                rel = prefix + e.name
                if e.is_dir(follow_symlinks=False):
                    walk(Path(e.path), rel + "/")
                else:
                    out.append(rel)

    walk(root, "")
    return sorted(out)


# =========================================================================== deleting


def remove_tree(path: str | os.PathLike) -> None:
    """Delete ``path`` without following symlinks.

    A symlink (to a file or a directory, dangling or not) is unlinked, never its target; a real
    directory is removed with :func:`shutil.rmtree`, which unlinks the symlinks inside it
    without descending into them; a file is unlinked. A missing ``path`` is not an error.
    """
    p = os.fspath(path)
    if os.path.islink(p):
        os.unlink(p)
    elif os.path.isdir(p):
        shutil.rmtree(p)
    elif os.path.lexists(p):
        os.unlink(p)


# =========================================================================== staged directories

_STAGE_KINDS = ("tmp", "old")


def _sibling_pattern(target: Path, kind: str) -> re.Pattern:
    return re.compile(rf"^\.{re.escape(target.name)}\.facegeo-{kind}-(\d+)-[A-Za-z0-9_]+$")


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return True
    return True


def staging_dir(target: str | os.PathLike, kind: str = "tmp") -> Path:
    """Create an empty directory beside ``target`` named ``.NAME.facegeo-KIND-PID-XXXX``.

    The process id in the name lets :func:`clean_stale_siblings` tell a leftover of a killed
    run from the directory of a run still going. The directory gets the permissions a plain
    ``mkdir`` would give (``mkdtemp`` makes it private), or ``target``'s if it exists.
    """
    target = Path(target)
    if kind not in _STAGE_KINDS:
        raise ValueError(f"kind: expected one of {_STAGE_KINDS}, got {fmt_value(kind)}")
    d = Path(tempfile.mkdtemp(prefix=f".{target.name}.facegeo-{kind}-{os.getpid()}-",
                              dir=target.parent))
    if target.is_dir():
        mode = stat.S_IMODE(os.stat(target).st_mode)
    else:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o777 & ~umask
    os.chmod(d, mode)
    return d


def clean_stale_siblings(target: str | os.PathLike) -> list[Path]:
    """Tidy up after a run on ``target`` that was killed (SIGKILL, power loss).

    * If ``target`` is missing but a stale ``.NAME.facegeo-old-PID-*`` exists (killed between
      the two renames of :func:`swap_in_dir`), the newest one is renamed back to ``target``:
      the old directory is restored, never deleted.
    * Stale ``.NAME.facegeo-tmp-PID-*`` (an unfinished new directory) and, once ``target``
      exists, stale ``.NAME.facegeo-old-PID-*`` (an old directory already swapped out) are
      deleted with :func:`remove_tree`.

    A sibling is stale when it is a real directory (not a symlink) whose name matches and whose
    process id is no longer running on this machine; anything else is left alone.

    Returns
    -------
    list of Path
        What was removed or restored.
    """
    target = Path(target)
    parent = target.parent
    if not parent.is_dir():
        return []
    stale: dict[str, list[Path]] = {k: [] for k in _STAGE_KINDS}
    for kind in _STAGE_KINDS:
        pat = _sibling_pattern(target, kind)
        with os.scandir(parent) as it:
            for e in it:
                m = pat.match(e.name)
                if m and e.is_dir(follow_symlinks=False) and not _pid_alive(int(m.group(1))):
                    stale[kind].append(Path(e.path))
    done: list[Path] = []
    if not os.path.lexists(target) and stale["old"]:
        newest = max(stale["old"], key=lambda p: p.lstat().st_mtime)
        os.rename(newest, target)
        log.warning("restored %s from %s (left by an interrupted run)", target, newest.name)
        stale["old"].remove(newest)
        done.append(newest)
    for p in stale["tmp"] + (stale["old"] if os.path.lexists(target) else []):
        log.info("removing %s, left by an interrupted run", p)
        remove_tree(p)
        done.append(p)
    return done


def swap_in_dir(new: str | os.PathLike, target: str | os.PathLike) -> None:
    """Put the complete directory ``new`` at ``target``; delete the old ``target`` after.

    The old directory is renamed aside (``.NAME.facegeo-old-PID-XXXX``), ``new`` is renamed to
    ``target``, then the old tree is removed with :func:`remove_tree`. If the second rename
    fails the first is undone. ``new`` must be on the same file system (a sibling).
    """
    new, target = Path(new), Path(target)
    if not os.path.lexists(target):
        os.rename(new, target)
        return
    aside = staging_dir(target, "old")
    os.rename(target, aside)  # replaces the empty directory just made
    try:
        os.rename(new, target)
    except BaseException:
        os.rename(aside, target)
        raise
    try:
        remove_tree(aside)
    except OSError as exc:  # the new scan is in place; the old one is only garbage now
        log.warning("could not remove the replaced directory %s (%s); delete it by hand",
                    aside, exc)


def carry_over(old: str | os.PathLike, new: str | os.PathLike, ours: set[str]) -> list[str]:
    """Bring every entry of directory ``old`` that is not in ``ours`` into directory ``new``.

    Files are hard-linked (copied where the file system cannot link), so ``old`` is unchanged
    and nothing is moved until the caller swaps ``new`` in; symlinks are recreated with the
    same target and never followed; empty directories are recreated. An entry whose path the
    new directory already uses is kept beside it as ``PATH.keep`` (``PATH.keep2``, …).

    Parameters
    ----------
    old, new : path-like
        The directory being replaced and its replacement (same file system).
    ours : set of str
        Relative POSIX paths of the entries facegeo wrote in ``old`` (not carried over).

    Returns
    -------
    list of str
        Relative paths (in ``new``) of the entries carried over.

    Raises
    ------
    OSError
        An entry that is neither a file, a directory nor a symlink (a socket, a FIFO), or a
        file system error; ``old`` is untouched either way.
    """
    old, new = Path(old), Path(new)
    carried: list[str] = []

    def dest_for(rel: str) -> Path:
        d = new / rel
        n = 1
        while os.path.lexists(d):
            d = new / (rel + (".keep" if n == 1 else f".keep{n}"))
            n += 1
        if d != new / rel:
            log.warning("%s: the new scan writes this path; your old entry is kept as %s",
                        rel, d.relative_to(new).as_posix())
        return d

    def walk(d: Path, prefix: str) -> None:
        with os.scandir(d) as it:
            entries = sorted(it, key=lambda e: e.name)
        if not entries and prefix and not os.path.lexists(new / prefix.rstrip("/")):
            (new / prefix.rstrip("/")).mkdir(parents=True)
            carried.append(prefix.rstrip("/"))
        for e in entries:
            rel = prefix + e.name
            if e.is_symlink():
                if rel in ours:
                    continue
                dst = dest_for(rel)
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.symlink(os.readlink(e.path), dst)
                carried.append(dst.relative_to(new).as_posix())
            elif e.is_dir(follow_symlinks=False):
                if os.path.lexists(new / rel) and not (new / rel).is_dir():
                    raise OSError(f"{old / rel}: a directory where the new scan has a file")
                walk(Path(e.path), rel + "/")
            elif e.is_file(follow_symlinks=False):
                if rel in ours:
                    continue
                dst = dest_for(rel)
                dst.parent.mkdir(parents=True, exist_ok=True)
                try:
                    os.link(e.path, dst)
                except OSError:
                    shutil.copy2(e.path, dst)
                carried.append(dst.relative_to(new).as_posix())
            else:
                raise OSError(f"{old / rel}: cannot carry over a special file (not a regular "
                              "file, directory or symlink); move it out of the scan first")

    walk(old, "")
    return carried


@contextlib.contextmanager
def staged_directory(target: str | os.PathLike) -> Iterator[Path]:
    """Yield an empty directory beside ``target``; swap it onto ``target`` if the block succeeds.

    The products of a step are written into the yielded directory; only when the block
    finishes does :func:`swap_in_dir` put them at ``target`` (the old ``target`` is removed
    after). On an exception (Ctrl-C included) the staging directory is removed, ``target``
    is untouched, and the parent folders this call created are removed again while empty.
    Leftovers of killed runs are tidied first (:func:`clean_stale_siblings`).
    """
    target = Path(target)
    created = [p for p in target.absolute().parents if not p.exists()]  # innermost first
    target.parent.mkdir(parents=True, exist_ok=True)
    clean_stale_siblings(target)
    tmp = staging_dir(target, "tmp")
    try:
        yield tmp
        swap_in_dir(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            remove_tree(tmp)
        for p in created:  # innermost first; a folder something else wrote into stays
            try:
                p.rmdir()
            except OSError:
                break
        raise
    _note_written(target.parent, [target.name + "/" + r for r in list_files(target)])


def _pwrite(fd: int, data, pos: int) -> int:
    """``os.pwrite`` where the platform has it (not Windows: seek, then write)."""
    if hasattr(os, "pwrite"):
        return os.pwrite(fd, data, pos)
    os.lseek(fd, pos, os.SEEK_SET)
    return os.write(fd, data)


#: Alignment of :class:`NpyRowFile`'s data and of direct (``O_DIRECT``) writes, bytes.
DIRECT_ALIGN = 4096


def aligned_empty(shape, dtype, align: int = DIRECT_ALIGN):
    """``np.empty(shape, dtype)`` whose data starts at a multiple of ``align`` bytes (what a
    direct write needs of its buffer; :meth:`NpyRowFile.write`)."""
    import numpy as np

    dtype = np.dtype(dtype)
    n = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    raw = np.empty(n + align, np.uint8)
    skip = (-raw.ctypes.data) % align
    return raw[skip:skip + n].view(dtype).reshape(shape)


class NpyRowFile:
    """A ``.npy`` file of a known shape, written block of rows by block of rows.

    The file (header and all its data) is created at once and its blocks reserved
    (``posix_fallocate``; a plain size where the filesystem cannot). The header is padded to
    :data:`DIRECT_ALIGN` bytes, so that a block whose buffer, length and place in the file are
    multiples of it (:func:`aligned_empty`; rows of 12 KB at 2048 lights × 3 float16) goes to
    the disk directly (``O_DIRECT``, past the page cache); any other block, or a filesystem
    without direct I/O (tmpfs), is written through the page cache with ``pwrite``. Why
    (measured here, ext4 on a virtual disk, 1.2 GB in blocks of 25 MB): new page-cache memory
    costs the guest ≈ 3 ms of kernel time per MB (a memory map of a new file written in place:
    a page fault per 4 KB on top), so a buffered write of 1.2 GB took 4.1 s of CPU, a direct
    one 0.08 s of CPU and 1.1 s of waiting for the disk. The price: a reader right after
    finds the data on disk, not in the page cache (1.2 GB read back through a memory map in
    2.2 s). The file opens with ``np.load`` (``mmap_mode`` too) like any ``.npy``.

    Parameters
    ----------
    path : path
        Created or replaced (written in place: callers stage the directory it is in).
    shape : tuple of int
        The whole array's shape; rows are along the first axis.
    dtype : numpy dtype
    direct : bool
        Try direct writes for aligned blocks (default); False: always through the page cache.
    """

    def __init__(self, path, shape, dtype, *, direct: bool = True):
        import numpy as np

        self.path = Path(path)
        self.dtype = np.dtype(dtype)
        self.shape = tuple(int(x) for x in shape)
        if not self.shape or min(self.shape) < 0:
            raise ValueError(f"NpyRowFile: expected a non-empty shape of sizes >= 0, got {shape}")
        # the .npy 1.0 header (magic, version, length, dict), padded with spaces to the
        # alignment, so that the data starts on an aligned offset
        text = ("{'descr': %r, 'fortran_order': False, 'shape': %r, }"
                % (np.lib.format.dtype_to_descr(self.dtype), self.shape))
        self.offset = DIRECT_ALIGN * -(-(len(text) + 11) // DIRECT_ALIGN)
        head = (b"\x93NUMPY\x01\x00" + (self.offset - 10).to_bytes(2, "little")
                + (text + " " * (self.offset - 11 - len(text)) + "\n").encode("latin1"))
        self.row_shape = self.shape[1:]
        self.row_bytes = int(np.prod(self.row_shape, dtype=np.int64)) * self.dtype.itemsize
        size = self.offset + self.shape[0] * self.row_bytes
        self._direct = None
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o666)
        try:
            os.write(self._fd, head)
            try:
                os.posix_fallocate(self._fd, 0, size)
            except (AttributeError, OSError):  # no reservation here: a sparse file of that size
                os.ftruncate(self._fd, size)
            if direct and hasattr(os, "O_DIRECT"):
                try:
                    self._direct = os.open(self.path, os.O_WRONLY | os.O_DIRECT)
                except OSError:  # e.g. tmpfs: page-cache writes only
                    self._direct = None
        except BaseException:
            os.close(self._fd)
            raise

    def write(self, start: int, block) -> None:
        """Write ``block`` (``(k, *row shape)``, this file's dtype, C-contiguous) as rows
        ``start … start + k − 1``."""
        import numpy as np

        start = int(start)
        if not (isinstance(block, np.ndarray) and block.dtype == self.dtype
                and block.shape[1:] == self.row_shape and block.flags.c_contiguous):
            got = (block.dtype, block.shape) if isinstance(block, np.ndarray) else type(block)
            raise ValueError(f"{self.path}: expected a C-contiguous {self.dtype} block of rows "
                             f"{self.row_shape}, got {got}")
        if start < 0 or start + block.shape[0] > self.shape[0]:
            raise ValueError(f"{self.path}: rows {start}..{start + block.shape[0]} outside "
                             f"0..{self.shape[0]}")
        view = memoryview(block.reshape(-1).view(np.uint8))
        pos = self.offset + start * self.row_bytes
        fd = self._fd
        if (self._direct is not None and pos % DIRECT_ALIGN == 0
                and view.nbytes % DIRECT_ALIGN == 0 and block.ctypes.data % DIRECT_ALIGN == 0):
            fd = self._direct
        while view.nbytes:
            try:
                n = _pwrite(fd, view, pos)
            except OSError:
                if fd != self._direct:
                    raise
                os.close(self._direct)  # direct writes refused here: the page cache from now on
                self._direct = None
                fd = self._fd
                continue
            view, pos = view[n:], pos + n

    def close(self) -> None:
        """Close the file (idempotent)."""
        for name in ("_direct", "_fd"):
            fd = getattr(self, name, None)
            if fd is not None:
                setattr(self, name, None)
                os.close(fd)

    def __del__(self):
        try:
            self.close()
        except OSError:  # pragma: no cover - shutdown
            pass


def _nbytes(x) -> int:
    """Bytes of the arrays in ``x`` (an array, or a tuple / list of them and other values)."""
    if isinstance(x, (tuple, list)):
        return sum(_nbytes(v) for v in x)
    return int(getattr(x, "nbytes", 0) or 0)


#: Threads the stages read frames ahead on (project, decode, ``facegeo relight --view``): the
#: paper preset's OLAT frames take 9–16 ms each to read and decode, and a camera's projection
#: took 28–35 s reading them in turn against 18–25 s with two threads ahead; the machines have
#: two cores.
READ_AHEAD_WORKERS = 2


def read_ahead(fn: Callable, items: Iterable, *, workers: int = READ_AHEAD_WORKERS,
               max_bytes: int = 256 << 20) -> Iterator:
    """Yield ``fn(item)`` for each item, in order, computed ahead on ``workers`` threads.

    For reading and decoding files (image decoders release the GIL) while the consumer works on
    the previous result. At most ``2·workers`` results are in flight, fewer when the first
    result is large: ``max(1, max_bytes // its size)`` (a 4896 × 3264 float32 RGB frame, 192 MB,
    is read one ahead). An exception of ``fn`` is raised where its item would have been
    yielded; closing the generator early cancels what has not started and waits for the reads
    that have. ``workers <= 1`` reads in the caller's thread, one at a time.
    """
    if workers <= 1:
        for item in items:
            yield fn(item)
        return
    from concurrent.futures import ThreadPoolExecutor

    it = iter(items)
    depth = 2 * workers
    pending: deque = deque()
    pool = ThreadPoolExecutor(workers, thread_name_prefix="facegeo-read-ahead")

    def fill() -> None:
        while len(pending) < depth:
            try:
                item = next(it)
            except StopIteration:
                return
            pending.append(pool.submit(fn, item))

    try:
        fill()
        first = True
        while pending:
            result = pending.popleft().result()
            if first:
                first = False
                depth = max(1, min(depth, max_bytes // max(_nbytes(result), 1)))
            fill()  # the next reads run while the consumer works on this result
            yield result
    finally:
        for f in pending:
            f.cancel()
        pool.shutdown(wait=True, cancel_futures=True)
