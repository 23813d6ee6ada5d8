"""The projection's blend as engine tasks (issue 38): one task per chunk of texels, each
reading only its rows of every camera's field and writing its rows of the blend — into the
``.npy`` (fields ``.npy``: the workers share the disk) or a Zarr array (Zarr fields, or in the
store beside the cameras' fields, linked from the stage folder).

What is compared, stated with each assertion:

* the blend — its samples bit for bit (float16 bits, NaN payloads included) against the
  in-process :func:`~facegeo.surface.reflectance.blend_fields`, and its ``texel_index``,
  ``weight``, ``n_cameras`` files byte for byte (each texel's sums run in camera order,
  whatever the chunk: the same float32 steps);
* the reader — :func:`~facegeo.surface.reflectance.open_blended` and
  :func:`~facegeo.surface.reflectance.iter_field_chunks` find the blend in whichever format it
  was written (no stage after the projection reads the blend: relight and fit read the cameras'
  fields);
* the store — after the projection each camera's place in the store holds its field only
  (its small files, brought down to the stage folder, removed).
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest

from facegeo.errors import InputError
from facegeo.pipeline.engine import InProcessEngine

#: Memory limit of each worker of the test cluster (a blend task of 4,096 texels × 128 lights
#: needs ≈ 50 MB).
WORKER_LIMIT = "800MiB"
#: Cap on a blend task's texels in the tests: rounded down to the fields' 4,096-texel chunks,
#: the tiny scan's ≈ 52 k blended texels make ≈ 13 tasks (the last one shorter).
TEST_BLEND_TEXELS = 5000
#: Texels per stored chunk of the fields (facegeo.surface._zarr_field.DEFAULT_CHUNK_TEXELS).
FIELD_CHUNK = 4096
_INDEX_FILES = ("texel_index.npy", "weight.npy", "n_cameras.npy")


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _bits(R) -> np.ndarray:
    """A float16/float32 field's samples as their bits (NaN payloads compared too)."""
    a = np.asarray(R[:])
    return a.view(np.uint16 if a.dtype == np.float16 else np.uint32)


def _assert_blend_equal(ref: Path, got: Path) -> None:
    """The blend in ``got`` (any format) equals the in-process one in ``ref`` bit for bit, read
    through the readers; its index files the same bytes."""
    from facegeo.surface.reflectance import BLENDED_FILE, iter_field_chunks, open_blended

    a, b = open_blended(ref), open_blended(got)
    assert a.field().dtype == b.field().dtype and a.field().shape == b.field().shape
    assert np.array_equal(_bits(a.field()), _bits(b.field()))
    streamed = np.concatenate([c for _, c in iter_field_chunks(got, name=BLENDED_FILE)])
    assert np.array_equal(streamed, np.asarray(a.field()[:], np.float32), equal_nan=True)
    for f in _INDEX_FILES:
        assert _sha(ref / f) == _sha(got / f), f


@pytest.mark.parametrize("fmt, store", [("npy", False), ("zarr", False), ("npy", True)],
                         ids=["npy-fields", "zarr-fields", "folder-store"])
def test_blend_tasks_on_two_workers_equal_in_process(projected, tmp_path, cluster, monkeypatch,
                                                    fmt, store):
    """``run_project`` on a two-worker ``LocalCluster``: the blend runs as tasks of whole
    4,096-texel chunks and equals the in-process blend bit for bit — written into
    ``R_blend.npy`` (the same bytes) for ``.npy`` fields, as ``R_blend.zarr`` for Zarr fields,
    and in the store beside the cameras (linked) with ``store=``; the store keeps no camera's
    small files once the client has them."""
    import facegeo.pipeline.project as proj
    from facegeo.surface._zarr_field import find_field, open_zarr_field
    from facegeo.surface.reflectance import BLENDED_FILE

    monkeypatch.setattr(proj, "BLEND_TASK_TEXELS", TEST_BLEND_TEXELS)
    out = tmp_path / "out"
    shutil.copytree(projected / "out" / "atlas", out / "atlas")
    where = tmp_path / "store"
    m = proj.run_project(projected, out, evaluate=False, engine=cluster, field_format=fmt,
                         store=str(where) if store else None)
    ref, got = projected / "out" / "project" / "blended", out / "project" / "blended"
    _assert_blend_equal(ref, got)
    blend_tasks = [n for n in m["engine"]["tasks"] if n.startswith("blend ")]
    U = m["blended_texels"]
    assert len(blend_tasks) == -(-U // FIELD_CHUNK) > 1, blend_tasks
    kind, loc = find_field(got, BLENDED_FILE)
    if fmt == "npy" and not store:
        assert kind == "npy" and _sha(ref / BLENDED_FILE) == _sha(got / BLENDED_FILE)
        return
    assert kind == "zarr" and not (got / BLENDED_FILE).exists()
    assert open_zarr_field(loc).chunks[0] == FIELD_CHUNK  # the fields' chunking
    if not store:
        assert loc == got / "R_blend.zarr"
        return
    assert (got / "R_blend.zarr.url").is_file() and not (got / "R_blend.zarr").exists()
    (run,) = (where / "project").iterdir()
    assert Path(loc) == run / "blended" / "R_blend.zarr"
    assert sorted(p.name for p in run.iterdir()) == ["blended", "cam_left", "cam_right"]
    for cam in ("cam_left", "cam_right"):  # the field only: files/ brought down and removed
        assert [p.name for p in (run / cam).iterdir()] == ["R.zarr"], cam
        assert (out / "project" / cam / "texel_index.npy").is_file()


def test_projection_into_a_memory_store_in_process_removes_the_files(projected, tmp_path):
    """In process with a ``memory://`` store the blend stays ``R_blend.npy`` (today's bytes),
    and each camera's ``files/`` copy is gone from the store once brought down."""
    import fsspec

    from facegeo.pipeline.project import run_project
    from facegeo.surface.reflectance import BLENDED_FILE

    shutil.copytree(projected / "out" / "atlas", tmp_path / "out" / "atlas")
    root = f"facegeo-blend-{tmp_path.name}"
    run_project(projected, tmp_path / "out", evaluate=False, store=f"memory://{root}")
    fs = fsspec.filesystem("memory")
    try:
        (run,) = fs.ls(f"/{root}/project", detail=False)
        for cam in ("cam_left", "cam_right"):
            names = sorted(Path(p).name for p in fs.ls(f"{run}/{cam}", detail=False))
            assert names == ["R.zarr"], (cam, names)
        assert not fs.exists(f"{run}/blended")
        ref = projected / "out" / "project" / "blended"
        got = tmp_path / "out" / "project" / "blended"
        assert _sha(ref / BLENDED_FILE) == _sha(got / BLENDED_FILE)
    finally:
        fs.rm(f"/{root}", recursive=True)


@pytest.mark.parametrize("kernels, dtype", [(True, "float16"), (False, "float32")])
def test_blend_on_engine_in_process_equals_blend_fields(projected, tmp_path, monkeypatch,
                                                       kernels, dtype):
    """:func:`blend_on_engine` run by the in-process engine in tasks of 1,000 texels (not a
    multiple of anything: the ``.npy`` blend has no chunk grid) equals
    :func:`blend_fields` bit for bit, with the compiled kernels and the numpy path, float16
    and float32; into a Zarr store with ``store_dir`` (a chunk per task)."""
    import facegeo.pipeline.project as proj
    from facegeo.surface import _blend
    from facegeo.surface import reflectance as rf
    from facegeo.surface._zarr_field import open_zarr_field

    monkeypatch.setattr(_blend, "BLEND_KERNELS", kernels)
    monkeypatch.setattr(proj, "BLEND_TASK_TEXELS", 1000)
    cams = rf.field_folders(projected / "out" / "project")
    ref = rf.blend_fields(cams, tmp_path / "ref", dtype=dtype)
    eng = InProcessEngine()
    got, names = proj.blend_on_engine(eng, cams, tmp_path / "npy", dtype=dtype)
    assert len(names) == -(-ref.texel_index.size // 1000)
    assert _sha(tmp_path / "ref" / rf.BLENDED_FILE) == _sha(tmp_path / "npy" / rf.BLENDED_FILE)
    _assert_blend_equal(tmp_path / "ref", tmp_path / "npy")
    assert np.array_equal(got.weight, ref.weight) and np.array_equal(got.n_cameras,
                                                                     ref.n_cameras)
    proj.blend_on_engine(eng, cams, tmp_path / "linked", dtype=dtype,
                         store_dir=tmp_path / "store")
    _assert_blend_equal(tmp_path / "ref", tmp_path / "linked")
    Z = open_zarr_field(tmp_path / "store" / "R_blend.zarr")
    assert Z.chunks[0] == 1000 and str(Z.dtype) == dtype


def test_blend_task_rows_follow_the_budget_and_the_chunks():
    """Rows per task: the cap, or what the budget holds, rounded down to whole field chunks
    when a chunk fits (the blend's chunk then the fields'), else the rows themselves."""
    from facegeo.pipeline.project import (BLEND_TASK_TEXELS, blend_task_rows,
                                          blend_working_set)

    assert blend_task_rows(128, 2, 4096, None) == (BLEND_TASK_TEXELS, 4096)
    per_row = blend_working_set(1, 2048, 16)
    assert per_row == 2048 * 3 * 32 + 16 * 12
    assert blend_task_rows(2048, 16, 1024, 5000 * per_row) == (4096, 1024)
    assert blend_task_rows(2048, 16, 4096, 3000 * per_row) == (3000, 3000)
    assert blend_task_rows(2048, 16, 4096, 0) == (1, 1)  # fits nothing: the check names it


def test_blend_task_over_a_workers_memory_is_refused(projected, tmp_path):
    """A worker too small for one blend row: the stage stops before any task runs, naming the
    blend's task, and writes no row."""
    from facegeo.pipeline.engine import WORKER_BASE_BYTES
    from facegeo.pipeline.project import blend_on_engine
    from facegeo.surface.reflectance import field_folders

    eng = InProcessEngine(memory_limit=WORKER_BASE_BYTES)  # budget below zero
    with pytest.raises(InputError, match=r"task 'blend 0:1' needs"):
        blend_on_engine(eng, field_folders(projected / "out" / "project"), tmp_path / "b")
    assert not eng.records
