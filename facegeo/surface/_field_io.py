"""Reading a projected field, wherever it is (private to :mod:`facegeo.surface`).

The readers :mod:`facegeo.surface.reflectance` (which re-exports :func:`open_field` and
:func:`has_field`) and its blend (:mod:`facegeo.surface._blend`) share: a field opened from
its folder in either format (an ``.npy`` memory map, a Zarr store, a link into a store:
:func:`facegeo.surface._zarr_field.find_field`), the rows a streamed step reads, and the
release of a memory map's rows from the resident set.
"""

from __future__ import annotations

import mmap
import sys
from pathlib import Path

import numpy as np

from facegeo.checks import check_positive_int
from facegeo.errors import InputError
from facegeo.surface._zarr_field import field_location, find_field, open_zarr_field

#: Bytes of one float32 chunk when a field is streamed along texels (texels × lights × 3 × 4;
#: :func:`iter_field_chunks`, :func:`blend_fields`): the callers' temporaries are a few times
#: this (the paper preset's 2048 lights at a fixed 8,192 texels made 201 MB chunks and a
#: 1.97 GB peak of the projection stage, the blend's doing).
_STREAM_CHUNK_BYTES = 32 << 20


def open_field(directory, name: str = "R.npy"):
    """A camera's field ``R`` ``(T_c, L, 3)``, read-only (``name=BLENDED_FILE``: the blended
    field of :func:`blend_fields`), in either format: ``directory/R.npy`` memory-mapped, else
    the Zarr store ``directory/R.zarr`` (:mod:`facegeo.surface._zarr_field`; ``directory`` may
    then be an fsspec URL). Both index like arrays along texels and lights (``R[t0:t1]``,
    ``R[t0:t1, l0:l1]`` return numpy arrays; a Zarr field reads only the chunks covered)."""
    found = find_field(directory, name)
    if found is None:
        where = field_location(directory, name)
        raise InputError(f"{directory}: no projected field here (neither {name} nor "
                         f"{Path(str(where)).name}; run the projection first)")
    return _open_found(*found)


def _open_found(kind: str, loc):
    """The field :func:`find_field` found (``kind``, ``loc``), read-only: an ``.npy`` memory map
    or a Zarr array (what :func:`open_field` returns; a blend task opens its cameras' fields
    with it, from the locations the client found)."""
    return np.load(loc, mmap_mode="r") if kind == "npy" else open_zarr_field(loc)


def has_field(directory, name: str = "R.npy") -> bool:
    """True when ``directory`` holds the field ``name`` in either format (``R.npy`` or the
    Zarr store ``R.zarr``): what :func:`open_field` would open."""
    return find_field(directory, name) is not None


def _chunk_rows(R, chunk_texels) -> int:
    """Rows of ``R`` per streamed step: ``chunk_texels`` (checked), or by default as many as
    make a :data:`_STREAM_CHUNK_BYTES` float32 chunk."""
    if chunk_texels is not None:
        return check_positive_int(chunk_texels, "chunk_texels")
    rows = max(1, _STREAM_CHUNK_BYTES // (max(int(np.prod(R.shape[1:])), 1) * 4))
    stored = getattr(R, "chunks", None)  # a Zarr field: whole chunks of texels
    if isinstance(stored, tuple) and stored and not isinstance(R, np.ndarray):
        rows = max(stored[0], rows - rows % stored[0])
    return rows


def _release_rows(mm: np.memmap, t0: int, t1: int, *, write: bool) -> None:
    """Drop rows ``t0:t1`` of a memory-mapped array from this process's resident set.

    File-backed pages count in the resident set once touched; a texel-major write of a light
    block touches a page of every texel, so without this the resident set would grow toward the
    size of the field. The pages are released with ``madvise(MADV_DONTNEED)``: on Linux a
    shared file mapping's dirty pages stay dirty in the page cache (the kernel writes them back
    once, later). They used to be flushed (``msync``) first, which wrote every touched page to
    the disk once per light block: 68 GB of disk writes for a paper-preset camera's 2.1 GB
    field (32 blocks of 64 lights; 174 k texels, 47.7 s), against 2.1–4.2 GB and 26–28 s without
    (``/tmp/m23/projw.py``, issue 11). Elsewhere (``MADV_DONTNEED`` may discard a
    shared mapping's changes) written pages are still flushed first.
    """
    m = getattr(mm, "_mmap", None)
    if m is None or t1 <= t0:
        return
    row = int(np.prod(mm.shape[1:])) * mm.dtype.itemsize
    base = int(getattr(mm, "offset", 0)) % mmap.ALLOCATIONGRANULARITY
    lo = base + t0 * row
    hi = base + t1 * row
    lo -= lo % mmap.PAGESIZE
    hi = min(hi + (-hi) % mmap.PAGESIZE, len(m))
    if write and not sys.platform.startswith("linux"):
        m.flush(lo, hi - lo)
    if hasattr(m, "madvise") and hasattr(mmap, "MADV_DONTNEED"):
        m.madvise(mmap.MADV_DONTNEED, lo, hi - lo)
