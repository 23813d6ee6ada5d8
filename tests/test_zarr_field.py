"""Reflectance fields stored as Zarr (facegeo.surface._zarr_field) and the format-transparent
readers of facegeo.surface.reflectance.

What is compared, stated with each assertion:

* round trips — every stored value against the array written, exactly (``array_equal`` with
  NaN equal: float16 → float16, float32 → float32; a float32 block written into a float16
  field against numpy's own float16 rounding of it);
* chunked writes from two processes into one array — the array read back against the blocks
  each process wrote, exactly, with no chunk left at the NaN fill;
* reading a chunk — a chunk reads correctly with every other chunk's object deleted from the
  store (a read touches only the chunks it covers).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from facegeo.errors import InputError, ShapeError
from facegeo.surface import reflectance as rf
from facegeo.surface._zarr_field import field_location

T, L = 37, 11  # texels, lights: neither a multiple of the chunks (an edge chunk on each axis)
CHUNKS = (8, 4)


def _field(dtype="float16", seed=0):
    rng = np.random.default_rng(seed)
    R = rng.random((T, L, 3), dtype=np.float32) * 2.0
    R[3, 5, 1] = np.nan  # a masked sample survives
    return R.astype(dtype)


@pytest.mark.parametrize("dtype", ["float16", "float32"])
def test_round_trip_both_formats_read_the_same(tmp_path, dtype):
    R = _field(dtype)
    (tmp_path / "npy").mkdir()
    np.save(tmp_path / "npy" / "R.npy", R)
    loc = rf.write_field(tmp_path / "zarr", np.load(tmp_path / "npy" / "R.npy", mmap_mode="r"),
                         chunks=CHUNKS)
    assert Path(loc) == tmp_path / "zarr" / "R.zarr"
    Z = rf.open_field(tmp_path / "zarr")
    assert Z.shape == (T, L, 3) and Z.dtype == np.dtype(dtype) and Z.chunks == (8, 4, 3)
    np.testing.assert_array_equal(Z[:], R)  # exact, NaN equal
    np.testing.assert_array_equal(Z[5:20, 3:9], R[5:20, 3:9])
    # iter_field_chunks: the same float32 chunks from either format
    a = list(rf.iter_field_chunks(tmp_path / "npy", chunk_texels=10))
    b = list(rf.iter_field_chunks(tmp_path / "zarr", chunk_texels=10))
    assert [s for s, _ in a] == [s for s, _ in b] == [0, 10, 20, 30]
    for (_, x), (_, y) in zip(a, b):
        assert x.dtype == y.dtype == np.float32
        np.testing.assert_array_equal(x, y)
    # default step on a Zarr field: whole stored chunks of texels
    steps = [s for s, _ in rf.iter_field_chunks(tmp_path / "zarr")]
    assert all(s % CHUNKS[0] == 0 for s in steps)
    # gather_field_samples: unsorted, repeated rows and lights
    rows, lights = np.array([30, 2, 2, 17]), np.array([10, 0, 5])
    np.testing.assert_array_equal(rf.gather_field_samples(tmp_path / "zarr", rows, lights),
                                  rf.gather_field_samples(tmp_path / "npy", rows, lights))


def test_float32_block_into_float16_field_rounds_like_numpy(tmp_path):
    loc = rf.create_field(tmp_path, (T, L, 3), dtype="float16", chunks=CHUNKS)
    block = _field("float32", seed=1)[:8, :4]
    rf.write_field_chunk(loc, 0, 0, block)
    Z = rf.open_field(tmp_path)
    np.testing.assert_array_equal(Z[:8, :4], block.astype(np.float16))
    assert np.isnan(Z[8:, :]).all() and np.isnan(Z[:, 4:]).all()  # never written: NaN


def test_chunk_writes_must_cover_whole_chunks(tmp_path):
    loc = rf.create_field(tmp_path, (T, L, 3), chunks=CHUNKS)
    with pytest.raises(InputError, match="not on the chunk grid"):
        rf.write_field_chunk(loc, 4, 0, np.zeros((8, 4, 3)))
    with pytest.raises(InputError, match="not on the chunk grid"):
        rf.write_field_chunk(loc, 0, 0, np.zeros((5, 4, 3)))
    with pytest.raises(InputError, match="outside"):
        rf.write_field_chunk(loc, 32, 0, np.zeros((8, 4, 3)))
    with pytest.raises(ShapeError, match="block"):
        rf.write_field_chunk(loc, 0, 0, np.zeros((8, 4)))
    rf.write_field_chunk(loc, 32, 8, np.ones((5, 3, 3)))  # the edge chunk ends at the array's end
    with pytest.raises(InputError, match="already"):
        rf.create_field(tmp_path, (T, L, 3), chunks=CHUNKS)
    with pytest.raises(InputError, match="dtype"):
        rf.create_field(tmp_path / "b", (T, L, 3), dtype="float64")


def test_two_processes_write_one_array(tmp_path):
    """Two processes, started together, each write every other chunk of the same array."""
    R = _field("float32", seed=2)
    np.save(tmp_path / "src.npy", R)
    loc = rf.create_field(tmp_path / "f", R.shape, dtype="float32", chunks=CHUNKS)
    bounds = rf.field_chunk_bounds(loc)
    assert len(bounds) == 5 * 3
    code = textwrap.dedent("""
        import sys, numpy as np
        from facegeo.surface.reflectance import field_chunk_bounds, write_field_chunk
        loc, src, part = sys.argv[1], sys.argv[2], int(sys.argv[3])
        R = np.load(src)
        for i, (t0, t1, l0, l1) in enumerate(field_chunk_bounds(loc)):
            if i % 2 == part:
                write_field_chunk(loc, t0, l0, R[t0:t1, l0:l1])
        print(part)
    """)
    procs = [subprocess.Popen([sys.executable, "-c", code, str(loc), str(tmp_path / "src.npy"),
                               str(k)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for k in (0, 1)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    np.testing.assert_array_equal(rf.open_field(tmp_path / "f")[:], R)


def test_reading_a_chunk_touches_only_that_chunk(tmp_path):
    R = _field("float16", seed=3)
    loc = Path(rf.write_field(tmp_path, R, chunks=CHUNKS))
    chunk_files = sorted(p for p in (loc / "c").rglob("*") if p.is_file())
    assert len(chunk_files) == 15
    keep = loc / "c" / "1" / "2" / "0"  # texels 8:16, lights 8:11
    for p in chunk_files:
        if p != keep:
            p.unlink()
    Z = rf.open_field(tmp_path)
    np.testing.assert_array_equal(Z[8:16, 8:11], R[8:16, 8:11])
    assert np.isnan(Z[0:8, 0:4]).all()  # a deleted chunk reads as the NaN fill


def test_open_field_errors_and_fsspec_url(tmp_path):
    with pytest.raises(InputError, match="neither R.npy nor R.zarr"):
        rf.open_field(tmp_path)
    R = _field("float32", seed=4)
    url = f"memory://facegeo-test-{tmp_path.name}"
    loc = rf.write_field(url, R, chunks=CHUNKS)
    assert loc == f"{url}/R.zarr"
    np.testing.assert_array_equal(rf.open_field(url)[:], R)
    assert field_location(url, rf.BLENDED_FILE) == f"{url}/R_blend.zarr"


def test_project_camera_writes_either_format(tmp_path):
    """project_camera(field_format="zarr") stores the same values as the .npy default."""
    from facegeo.surface.reflectance import CameraVisibility

    rng = np.random.default_rng(5)
    W, H, n_t, n_l = 23, 17, 300, 9
    q = np.column_stack([rng.uniform(0, W - 1, n_t), rng.uniform(0, H - 1, n_t)])
    ones = np.ones(n_t, bool)
    vis = CameraVisibility("cam", q, np.tile([0.0, 0.0, 1.0], (n_t, 1)), ones, ones, ones,
                           np.ones(n_t), np.ones(n_t, np.float32), np.ones(n_t, np.float32))
    frames = [rng.random((H, W, 3), dtype=np.float32) for _ in range(n_l)]
    a = rf.project_camera(enumerate(frames), vis, (W, H), n_l, tmp_path / "npy", block_lights=4)
    b = rf.project_camera(enumerate(frames), vis, (W, H), n_l, tmp_path / "zarr", block_lights=4,
                          field_format="zarr")
    assert (tmp_path / "npy" / "R.npy").is_file() and not (tmp_path / "zarr" / "R.npy").exists()
    assert (tmp_path / "zarr" / "R.zarr" / "zarr.json").is_file()
    np.testing.assert_array_equal(a.field()[:], b.field()[:])  # exact: same float16 rounding
    with pytest.raises(InputError, match="field_format"):
        rf.project_camera(enumerate(frames), vis, (W, H), n_l, tmp_path / "x",
                          field_format="hdf5")
    # writing .npy again over the zarr folder removes the store (open_field reads one format)
    rf.project_camera(enumerate(frames), vis, (W, H), n_l, tmp_path / "zarr", block_lights=4)
    assert not (tmp_path / "zarr" / "R.zarr").exists()
