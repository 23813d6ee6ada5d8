"""Reflectance fields ``R[texel, light, rgb]`` stored as Zarr arrays (issue 38).

The ``.npy`` field (:func:`facegeo.surface.reflectance.open_field`) is one file memory-mapped by
one machine. A Zarr array is a grid of independently compressed chunks, chunked along texels
**and** lights, so that

* a task writes only its chunk (:func:`write_field_chunk`) — several processes, or workers of a
  cluster, fill one array at once without a lock, as long as each writes whole chunks (the only
  write allowed here: a region that starts and ends on chunk boundaries, or at the array's end);
* a task reads only its chunk (``R[t0:t1, l0:l1]`` touches the chunks it covers, nothing else);
* the store is a local directory by default, or any fsspec URL (``s3://bucket/scan/R.zarr``,
  ``memory://…``) for a cluster whose workers do not share a disk.

On disk a field ``R.npy`` becomes ``R.zarr/`` beside it (the same stem: ``R_blend.zarr`` for the
blend), a Zarr v3 array of shape ``(T, L, 3)``, float16 or float32, zstd-compressed chunks of
:data:`DEFAULT_CHUNK_TEXELS` × :data:`DEFAULT_CHUNK_LIGHTS` × 3 by default, and fill value NaN:
a chunk never written reads as NaN (a missing sample, never a fake value — docs/conventions.md).
The ``.npy`` format stays the default (:data:`DEFAULT_FIELD_FORMAT`); the readers of
:mod:`facegeo.surface.reflectance` read either (:func:`find_field`).

A Zarr store written chunk by chunk is not one atomic file: a stage writes it inside its staging
folder (:func:`facegeo.fsutil.staged_directory`), swapped in whole when the stage completes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facegeo.checks import check_positive_int, fmt_value
from facegeo.errors import InputError, ShapeError

__all__ = [
    "DEFAULT_CHUNK_LIGHTS",
    "DEFAULT_CHUNK_TEXELS",
    "DEFAULT_FIELD_FORMAT",
    "FIELD_FORMATS",
    "ZARR_SUFFIX",
    "create_field",
    "field_chunk_bounds",
    "field_location",
    "find_field",
    "LINK_SUFFIX",
    "is_url",
    "link_field",
    "open_zarr_field",
    "store_location",
    "copy_files",
    "get_bytes",
    "put_bytes",
    "STORE_FILES",
    "remove_location",
    "write_field",
    "write_field_chunk",
]

#: On-disk formats of a reflectance field.
FIELD_FORMATS = ("npy", "zarr")
#: The format stages write unless told otherwise (other stages read ``R.npy`` by name).
DEFAULT_FIELD_FORMAT = "npy"
#: Suffix of a Zarr field's store (``R.npy`` → ``R.zarr``).
ZARR_SUFFIX = ".zarr"
#: Texels per chunk: 4,096 × 64 lights × 3 × 2 B = 1.5 MiB float16 (3 MiB float32) a chunk.
DEFAULT_CHUNK_TEXELS = 4096
#: Lights per chunk: the projection's light block (``DEFAULT_BLOCK_LIGHTS``), so one block of
#: frames fills whole chunks.
DEFAULT_CHUNK_LIGHTS = 64
_DTYPES = ("float16", "float32")


def is_url(location) -> bool:
    """True for an fsspec URL (``s3://…``, ``memory://…``; ``file://`` counts as a path)."""
    return isinstance(location, str) and "://" in location and not location.startswith("file://")


def _local(location) -> str | Path:
    if isinstance(location, str) and location.startswith("file://"):
        return Path(location[len("file://"):])
    return location if is_url(location) else Path(location)


def field_location(directory, name: str = "R.npy") -> str | Path:
    """The Zarr store of the field ``name`` in ``directory`` (a folder or an fsspec URL):
    ``directory/<stem>.zarr`` (``R.npy`` → ``R.zarr``)."""
    stem = name[:-4] if name.endswith(".npy") else name
    stem = stem if stem.endswith(ZARR_SUFFIX) else stem + ZARR_SUFFIX
    d = _local(directory)
    return f"{d.rstrip('/')}/{stem}" if isinstance(d, str) else d / stem


def _store_exists(location) -> bool:
    loc = _local(location)
    if isinstance(loc, Path):
        return (loc / "zarr.json").is_file()
    import fsspec

    fs, path = fsspec.core.url_to_fs(loc)
    return fs.exists(f"{path.rstrip('/')}/zarr.json")


#: Suffix of a link file: ``R.zarr.url`` in a stage folder holds the URL of the camera's field
#: kept in a store elsewhere (``--store URL``, :func:`link_field`).
LINK_SUFFIX = ".url"


#: Sub-folder of a task's place in a ``--store`` holding its small products on their way to
#: the stage folder (the projection's and the decode's tasks: :func:`copy_files`).
STORE_FILES = "files"


def store_location(store, *parts: str) -> str | Path:
    """``store/part/part…``: a place in a store (a folder, a ``file://`` URL or an fsspec URL
    such as ``s3://bucket/scan``; ``memory://`` in tests). A folder stays a :class:`Path`."""
    if not isinstance(store, (str, Path)) or not str(store).strip():
        raise InputError(f"store: expected a folder or an fsspec URL (s3://bucket/prefix), got "
                         f"{fmt_value(store)}")
    d = _local(store)
    if isinstance(d, Path):
        return d.joinpath(*parts)
    return "/".join([d.rstrip("/")] + [p.strip("/") for p in parts])


def link_field(directory, location, name: str = "R.npy") -> Path:
    """Record in the folder ``directory`` that its field ``name`` is the Zarr store at
    ``location`` (e.g. in ``s3://…``): the file ``<stem>.zarr.url`` (written atomically), which
    :func:`find_field` — and so every reader of :mod:`facegeo.surface.reflectance` — follows.
    Returns the link file's path."""
    from facegeo.fsutil import atomic_write_text

    if not _store_exists(location):
        raise InputError(f"{location}: no Zarr field here to link to (create_field first)")
    link = Path(str(field_location(directory, name)) + LINK_SUFFIX)
    link.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(link, str(location) + "\n")
    return link


def put_bytes(location, data: bytes) -> None:
    """``data`` as the file ``location``: a path (written atomically, its folder created) or
    an fsspec URL."""
    loc = _local(location)
    if isinstance(loc, Path):
        from facegeo.fsutil import atomic_write_bytes

        loc.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(loc, data)
    else:
        import fsspec

        fs, path = fsspec.core.url_to_fs(loc)
        fs.pipe_file(path, data)


def get_bytes(location) -> bytes:
    """The file ``location`` (a path or an fsspec URL)."""
    loc = _local(location)
    if isinstance(loc, Path):
        return loc.read_bytes()
    import fsspec

    fs, path = fsspec.core.url_to_fs(loc)
    return fs.cat_file(path)


def remove_location(location) -> None:
    """Remove a file or a folder — a path or a place in an fsspec store — whatever it holds;
    nothing when it is not there."""
    loc = _local(location)
    if isinstance(loc, Path):
        if loc.is_dir():
            import shutil

            shutil.rmtree(loc, ignore_errors=True)
        else:
            loc.unlink(missing_ok=True)
        return
    import fsspec

    fs, path = fsspec.core.url_to_fs(loc)
    if fs.exists(path):
        fs.rm(path, recursive=True)


def copy_files(src, dst) -> list[str]:
    """Copy the files directly inside ``src`` (not its sub-folders) into ``dst``; either may be
    a folder or an fsspec URL (``--store``: a task's small products go up to the store, the
    client brings them down into its stage folder; :func:`put_bytes`, :func:`get_bytes`).
    Returns the names copied, sorted."""
    import fsspec

    loc = _local(src)
    fs, path = fsspec.core.url_to_fs(str(loc))
    names = sorted(Path(e["name"]).name for e in fs.ls(path, detail=True)
                   if e.get("type") == "file")
    for n in names:
        put_bytes(store_location(dst, n), get_bytes(store_location(src, n)))
    return names


def find_field(directory, name: str = "R.npy") -> tuple[str, str | Path] | None:
    """``("npy", path)`` when ``directory/name`` is a file, else ``("zarr", store)`` when the
    Zarr store of the same stem exists, or a link file (:func:`link_field`) names one, else
    None (``directory`` may be an fsspec URL: Zarr only)."""
    d = _local(directory)
    if isinstance(d, Path) and (d / name).is_file():
        return "npy", d / name
    loc = field_location(directory, name)
    if _store_exists(loc):
        return "zarr", loc
    if isinstance(loc, Path):
        link = Path(str(loc) + LINK_SUFFIX)
        if link.is_file():
            target = link.read_text(encoding="utf-8").strip()
            if not _store_exists(target):
                raise InputError(f"{link}: the field it names, {target}, is not there (the "
                                 "store was removed or is not reachable from here)")
            return "zarr", _local(target)
    return None


def create_field(directory, shape, *, dtype: str = "float16", name: str = "R.npy",
                 chunks: tuple[int, int] | None = None, overwrite: bool = False):
    """Create an empty Zarr field ``(T, L, 3)`` (metadata only; every chunk reads NaN until
    written) and return the store's location, for :func:`write_field_chunk`.

    Parameters
    ----------
    directory : path-like or str
        A folder (created) or an fsspec URL; the store is ``directory/<stem>.zarr``.
    shape : (int, int, int)
        ``(T, L, C)``: texels, lights, channels (3 for RGB).
    dtype : {"float16", "float32"}
    name : str
        The field's ``.npy`` name (``"R.npy"``, ``BLENDED_FILE``): gives the store's stem.
    chunks : (int, int), optional
        ``(texels, lights)`` per chunk, clipped to the shape (default
        :data:`DEFAULT_CHUNK_TEXELS`, :data:`DEFAULT_CHUNK_LIGHTS`).
    overwrite : bool
        Replace an existing store (else an existing store is an error).

    Raises
    ------
    InputError
        A bad shape, dtype or chunk size; an existing store without ``overwrite``.
    """
    import zarr

    if dtype not in _DTYPES:
        raise InputError(f"dtype: expected 'float16' or 'float32', got {fmt_value(dtype)}")
    shape = tuple(int(s) for s in shape)
    if len(shape) != 3 or min(shape) < 0 or shape[1] < 1 or shape[2] < 1:
        raise ShapeError(f"shape: expected (T, L, C) with L, C >= 1, got {shape}")
    ct, cl = chunks if chunks is not None else (DEFAULT_CHUNK_TEXELS, DEFAULT_CHUNK_LIGHTS)
    ct = min(check_positive_int(ct, "chunks[0] (texels)"), max(shape[0], 1))
    cl = min(check_positive_int(cl, "chunks[1] (lights)"), shape[1])
    loc = field_location(directory, name)
    if isinstance(loc, Path):
        loc.parent.mkdir(parents=True, exist_ok=True)
    if not overwrite and _store_exists(loc):
        raise InputError(f"{loc}: a field is stored here already (overwrite=True replaces it)")
    zarr.create_array(store=str(loc) if isinstance(loc, Path) else loc, shape=shape,
                      chunks=(ct, cl, shape[2]), dtype=dtype, fill_value=np.nan,
                      overwrite=overwrite)
    return loc


def open_zarr_field(location, mode: str = "r"):
    """The Zarr array at ``location`` (a store made by :func:`create_field`); ``mode`` ``"r"``
    (read only) or ``"r+"``.

    Raises
    ------
    InputError
        No field there, or not a ``(T, L, C)`` float array.
    """
    import zarr

    loc = _local(location)
    if not _store_exists(loc):
        raise InputError(f"{location}: no Zarr field here (no zarr.json; run the projection "
                         "first, or create_field)")
    R = zarr.open_array(str(loc) if isinstance(loc, Path) else loc, mode=mode)
    if R.ndim != 3 or R.dtype.kind != "f":
        raise ShapeError(f"{location}: expected a (T, L, C) float field, got shape {R.shape} "
                         f"dtype {R.dtype}")
    return R


def field_chunk_bounds(location) -> list[tuple[int, int, int, int]]:
    """Every chunk of the field as ``(t0, t1, l0, l1)``, texel-major: the regions a set of tasks
    writes (or reads) one each."""
    R = open_zarr_field(location)
    T, L = R.shape[:2]
    ct, cl = R.chunks[:2]
    return [(t, min(t + ct, T), l, min(l + cl, L))
            for t in range(0, T, ct) for l in range(0, L, cl)]


def write_field_chunk(location, t0: int, l0: int, block) -> None:
    """Write ``block`` ``(n, m, C)`` into the field at texels ``t0:t0+n``, lights ``l0:l0+m``.

    The region must cover whole chunks (start on a chunk boundary; end on one or at the array's
    end) so that writers never share a chunk: two processes writing different chunks of one
    array need no lock. Values are converted to the field's dtype (computation is float32;
    never compute in float16).

    Raises
    ------
    InputError
        A region off the chunk grid or outside the array; ShapeError for a wrong channel count.
    """
    R = location if hasattr(location, "chunks") else open_zarr_field(location, mode="r+")
    block = np.asarray(block)
    if block.ndim != 3 or block.shape[2] != R.shape[2]:
        raise ShapeError(f"block: expected (n, m, {R.shape[2]}), got {block.shape}")
    t0, l0 = int(t0), int(l0)
    n, m = block.shape[:2]
    T, L = R.shape[:2]
    ct, cl = R.chunks[:2]
    for what, a, k, c, size in (("texels", t0, n, ct, T), ("lights", l0, m, cl, L)):
        b = a + k
        if a < 0 or b > size:
            raise InputError(f"{location}: {what} {a}:{b} outside the field's 0:{size}")
        if a % c or (b % c and b != size):
            raise InputError(f"{location}: {what} {a}:{b} is not on the chunk grid ({c} {what} "
                             f"a chunk): writers must cover whole chunks so that they never "
                             "share one")
    R[t0:t0 + n, l0:l0 + m] = block.astype(R.dtype, copy=False)


def write_field(directory, R, *, dtype: str | None = None, name: str = "R.npy",
                chunks: tuple[int, int] | None = None, overwrite: bool = False):
    """Store the field ``R`` ``(T, L, C)`` (an array or a memory map, e.g. an ``R.npy``) as a
    Zarr field in ``directory``, one chunk row of texels at a time (resident memory: one row
    of chunks, float32). Returns the store's location.

    ``dtype`` defaults to ``R``'s (float16 or float32).
    """
    dtype = str(np.dtype(R.dtype)) if dtype is None else dtype
    loc = create_field(directory, R.shape, dtype=dtype, name=name, chunks=chunks,
                       overwrite=overwrite)
    Z = open_zarr_field(loc, mode="r+")
    ct = Z.chunks[0]
    for t0 in range(0, R.shape[0], ct):
        write_field_chunk(Z, t0, 0, np.asarray(R[t0:t0 + ct], dtype=np.float32))
    return loc
