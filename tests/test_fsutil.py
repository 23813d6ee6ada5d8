"""facegeo.fsutil: NpyRowFile (a preallocated .npy written block by block) and read_ahead."""

from __future__ import annotations

import numpy as np
import pytest

from facegeo.fsutil import NpyRowFile, read_ahead


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


@pytest.mark.parametrize("workers", [0, 1, 2, 3])
def test_read_ahead_yields_in_order_and_bounds_what_is_in_flight(workers):
    import threading
    import time

    lock = threading.Lock()
    state = {"running": 0, "peak": 0, "started": 0}

    def fn(i):
        with lock:
            state["started"] += 1
            state["running"] += 1
            state["peak"] = max(state["peak"], state["running"])
        time.sleep(0.002 * (i % 3))  # out-of-order completion
        with lock:
            state["running"] -= 1
        return i, np.zeros(10)

    got = [i for i, _ in read_ahead(fn, range(40), workers=workers)]
    assert got == list(range(40))
    assert state["peak"] <= max(workers, 1)
    # early close: nothing more starts than was in flight
    state["started"] = 0
    gen = read_ahead(fn, range(1000), workers=workers)
    next(gen)
    gen.close()
    assert state["started"] <= 1 + 2 * max(workers, 1)


def test_read_ahead_bounds_bytes_and_raises_in_place():
    seen = []

    def big(i):
        seen.append(i)
        return np.zeros(1000)  # 8 kB

    gen = read_ahead(big, range(100), workers=2, max_bytes=8000)  # one 8 kB result ahead
    next(gen)
    import time

    time.sleep(0.05)
    # the first batch (2 · workers) went out before the size was known; with one result
    # allowed in flight and three pending, nothing more is started (without the bound: a fifth)
    assert len(seen) == 4
    gen.close()

    def bad(i):
        if i == 5:
            raise ValueError("frame 5 is corrupt")
        return i

    out = []
    with pytest.raises(ValueError, match="frame 5"):
        for x in read_ahead(bad, range(10), workers=2):
            out.append(x)
    assert out == [0, 1, 2, 3, 4]


def test_staged_directory_leaves_no_parent_it_made_when_the_block_fails(tmp_path):
    """A failed stage leaves the folders as they were: the parents the staging created are
    removed again (``facegeo atlas --out NEW --size 0`` left an empty NEW), a parent that
    existed or that something else wrote into stays; success keeps them all."""
    from facegeo.fsutil import staged_directory

    target = tmp_path / "new" / "out" / "atlas"
    with pytest.raises(RuntimeError):
        with staged_directory(target) as tmp:
            (tmp / "half.npz").write_bytes(b"x")
            raise RuntimeError("bad --size")
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    (tmp_path / "new").mkdir()
    (tmp_path / "new" / "mine.txt").write_text("keep")
    with pytest.raises(RuntimeError):
        with staged_directory(target):
            raise RuntimeError("again")
    assert sorted(p.name for p in (tmp_path / "new").iterdir()) == ["mine.txt"]
    with staged_directory(target) as tmp:
        (tmp / "atlas.npz").write_bytes(b"ok")
    assert (target / "atlas.npz").read_bytes() == b"ok"


def test_written_record_appends_products_and_compacts(tmp_path, monkeypatch):
    """Products written into a scan's out/ are appended to its record (a rerun appends the
    same paths again); past a size the record is rewritten once per path, header kept."""
    from facegeo import fsutil

    root = tmp_path / "scan"
    root.mkdir()
    (root / "scan.toml").write_text("")
    fsutil.write_written_record(root, ["scan.toml"])
    monkeypatch.setattr(fsutil, "_RECORD_COMPACT_BYTES", 600)
    for _ in range(30):
        fsutil.atomic_write_text(root / "out" / "metrics.json", "{}")
    text = (root / fsutil.WRITTEN_RECORD).read_text()
    assert fsutil.read_written_record(root) == {"scan.toml", "out/metrics.json"}
    assert text.startswith("#") and len(text) <= 600 + 40, len(text)
