"""Atomic file output: write to a temporary file beside the target, then rename.

A reader never sees a half-written file, and a failure leaves the previous file (or nothing)
in place.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_text"]


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
    On an exception the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=path.suffix if suffix is None else suffix, dir=path.parent
    )
    os.close(fd)
    tmp_path = Path(tmp)
    # mkstemp creates 0600 files; give the result the permissions a plain open() would.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | os.PathLike, text: str, *, encoding: str = "utf-8") -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding=encoding)


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
