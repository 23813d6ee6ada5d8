"""facegeo.fsutil.NpyRowFile: a preallocated .npy written block by block with pwrite."""

from __future__ import annotations

import numpy as np
import pytest

from facegeo.fsutil import NpyRowFile


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.int64])
def test_blocks_in_any_order_make_the_array_np_load_reads(tmp_path, dtype):
    rng = np.random.default_rng(1)
    want = (rng.random((11, 5, 3)) * 100).astype(dtype)
    f = NpyRowFile(tmp_path / "a.npy", want.shape, dtype)
    # the file has its full size at once (reserved), before any block
    assert (tmp_path / "a.npy").stat().st_size == f.offset + want.nbytes
    for start, stop in ((6, 11), (0, 4), (4, 6)):
        f.write(start, np.ascontiguousarray(want[start:stop]))
    f.close()
    f.close()  # idempotent
    assert np.array_equal(np.load(tmp_path / "a.npy"), want)
    mm = np.load(tmp_path / "a.npy", mmap_mode="r")
    assert mm.shape == want.shape and mm.dtype == want.dtype and np.array_equal(mm, want)


def test_an_existing_file_is_replaced_and_empty_arrays_work(tmp_path):
    p = tmp_path / "b.npy"
    np.save(p, np.arange(1000.0))
    f = NpyRowFile(p, (0, 4), np.float32)
    f.close()
    assert np.load(p).shape == (0, 4)


def test_bad_blocks_are_refused_naming_the_file(tmp_path):
    f = NpyRowFile(tmp_path / "c.npy", (4, 3), np.float16)
    with pytest.raises(ValueError, match=r"c\.npy: expected a C-contiguous float16 block"):
        f.write(0, np.zeros((2, 3), np.float32))
    with pytest.raises(ValueError, match=r"c\.npy: expected a C-contiguous float16 block"):
        f.write(0, np.zeros((2, 4), np.float16))
    with pytest.raises(ValueError, match=r"c\.npy: expected a C-contiguous float16 block"):
        f.write(0, np.zeros((3, 4), np.float16).T)
    with pytest.raises(ValueError, match=r"c\.npy: rows 3\.\.5 outside 0\.\.4"):
        f.write(3, np.zeros((2, 3), np.float16))
    f.close()


@pytest.mark.parametrize("direct", [True, False])
def test_aligned_blocks_direct_and_others_buffered_give_the_same_file(tmp_path, direct):
    """Rows of 4 KB multiples: an aligned block (aligned_empty) may go straight to the disk
    (O_DIRECT where the filesystem has it), a misaligned one through the page cache; the
    file is the same either way, and the data starts on an aligned offset."""
    from facegeo.fsutil import DIRECT_ALIGN, aligned_empty

    rng = np.random.default_rng(2)
    want = rng.random((9, 2048, 3)).astype(np.float16)  # 12 KB rows
    f = NpyRowFile(tmp_path / "d.npy", want.shape, np.float16, direct=direct)
    assert f.offset % DIRECT_ALIGN == 0
    a = aligned_empty((4, 2048, 3), np.float16)
    assert a.ctypes.data % DIRECT_ALIGN == 0 and a.flags.c_contiguous
    a[...] = want[:4]
    f.write(0, a)  # aligned: direct where available
    odd = np.empty(5 * want[0].size + 1, np.float16)[1:].reshape(5, 2048, 3)  # misaligned
    odd[...] = want[4:]
    f.write(4, odd)
    f.close()
    assert np.array_equal(np.load(tmp_path / "d.npy"), want)


def test_without_pwrite_the_file_is_the_same(tmp_path, monkeypatch):
    """Platforms without os.pwrite (Windows): seek and write give the same file."""
    import os

    want = np.arange(24, dtype=np.float32).reshape(6, 4)
    monkeypatch.delattr(os, "pwrite")
    f = NpyRowFile(tmp_path / "e.npy", want.shape, np.float32, direct=False)
    f.write(3, np.ascontiguousarray(want[3:]))
    f.write(0, np.ascontiguousarray(want[:3]))
    f.close()
    assert np.array_equal(np.load(tmp_path / "e.npy"), want)
