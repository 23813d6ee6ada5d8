"""Relighting under a batch of environment maps (issue 38, "relighting per batch of maps"):
``facegeo relight SCAN --env A --env B …`` writes each map's own files, reads the field (or a
camera's OLAT frames) once per batch, and its products equal each map relit alone."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from facegeo.errors import InputError

#: A texture batch of several maps (one GEMM a chunk of rows) against each map alone (the fused
#: float16 kernel): max |batched − alone| / |alone| over every measured texel and channel —
#: float32 sums in another order (measured 6–7.4e-7 on the tiny scan, 4–16 maps).
BATCH_REL = 1e-6


def _write_maps(folder: Path, names=("a", "b", "c"), seed: int = 7) -> list[Path]:
    """Small lat-long EXR maps, each a different asymmetric sky (positive radiance)."""
    from facegeo.capture import imageio

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    out = []
    for k, n in enumerate(names):
        img = rng.uniform(0.05, 1.0, (8, 16, 3)).astype(np.float32)
        img[: 2 + k, 3 * k: 3 * k + 4] *= 8.0  # a bright patch, elsewhere for each map
        out.append(imageio.write_image(folder / f"{n}.exr", img))
    (folder / "notes.txt").write_text("not a map")  # a folder's other files are ignored
    return out


def _images(folder: Path) -> dict[str, np.ndarray]:
    from facegeo.capture import imageio

    return {p.name: imageio.read_image(p) for p in sorted(folder.iterdir())
            if p.suffix in (".exr", ".png")}


def _digests(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.iterdir()) if p.suffix in (".exr", ".png")}


def _max_rel(got: np.ndarray, ref: np.ndarray) -> float:
    ok = np.isfinite(ref)
    assert np.array_equal(ok, np.isfinite(got))
    return float(np.max(np.abs(got[ok] - ref[ok]) / np.maximum(np.abs(ref[ok]), 1e-30)))


def _count_field_reads(monkeypatch) -> list:
    """Record the weights' shape of every ``relight_field`` call (one call = one read of a
    task's rows)."""
    from facegeo.lighting import relight as RL

    shapes, real = [], RL.relight_field

    def counted(field, weights, **kw):
        shapes.append(np.shape(weights))
        return real(field, weights, **kw)

    monkeypatch.setattr(RL, "relight_field", counted)
    return shapes


def test_texture_batch_equals_each_map_alone(projected, tmp_path, monkeypatch):
    """Three maps (a folder) in batches of 2: two GEMM maps within :data:`BATCH_REL` of each map
    alone, the batch of one the same bytes; each task's rows read once per batch; progress per
    (camera, batch); each map's files named as alone."""
    from facegeo.lighting import relight as RL
    from facegeo.pipeline import relight as PR

    maps = _write_maps(tmp_path / "maps")
    monkeypatch.setattr(PR, "RELIGHT_MAPS_PER_TASK", 2)
    L = np.load(projected / "out" / "project" / "cam_left" / "R.npy", mmap_mode="r").shape[1]
    monkeypatch.setattr(RL, "CHUNK_BYTES", 227 * 4 * 3 * L)  # GEMM chunks of 227 rows …
    monkeypatch.setattr(RL, "FUSED_CHUNK_BYTES", 227 * 2 * 3 * L)
    monkeypatch.setattr(PR, "RELIGHT_TASK_TEXELS", 500)  # … tasks of 454 rows
    singles = {}
    for m in maps:
        singles[m.stem] = PR.run_relight(projected, m, view="texture",
                                         out_dir=tmp_path / "one" / m.stem)
    reads = _count_field_reads(monkeypatch)
    calls = []
    run = PR.run_relight_maps(projected, [tmp_path / "maps"], view="texture",
                              out_dir=tmp_path / "batch", progress=lambda *a: calls.append(a))
    assert (run["maps"], run["batches"]) == (3, 2)
    assert [m["env"] for m in run["relit"]] == [str(p) for p in maps]  # sorted by name
    assert [m["batch"]["maps"] for m in run["relit"]] == [2, 2, 1]
    assert calls == [("relight", k, 4) for k in (1, 2, 3, 4)]  # 2 cameras × 2 batches
    rows = sum(-(-np.load(projected / "out" / "project" / c / "R.npy", mmap_mode="r").shape[0]
                 // 454) for c in ("cam_left", "cam_right"))
    assert rows > 2  # several tasks a camera
    assert sorted(reads) == sorted([(2, L, 3)] * rows + [(1, L, 3)] * rows)
    got = _images(tmp_path / "batch")
    names = {f.name for m in maps for f in (tmp_path / "one" / m.stem).iterdir()}
    assert {p.name for p in (tmp_path / "batch").iterdir()} == names  # the json files too
    for m in maps:
        ref = _images(tmp_path / "one" / m.stem)
        stem = Path(singles[m.stem]["files"]["exr"]).stem
        exr = f"{stem}.exr"
        if m.stem == "c":  # the batch of one: the one-map path, the same bytes
            assert _digests(tmp_path / "batch").get(exr) == _digests(tmp_path / "one" / "c")[exr]
            assert np.array_equal(got[exr], ref[exr])
        else:
            assert 0 < _max_rel(got[exr], ref[exr]) <= BATCH_REL  # another order of sums
        assert np.array_equal(got[f"{stem}_measured.png"], ref[f"{stem}_measured.png"])


def test_camera_view_batch_reads_each_frame_once_and_equals_each_map_alone(projected, tmp_path,
                                                                          monkeypatch):
    """A camera view under three maps: every OLAT frame lit by any map read once, each map's
    image the same bytes as the map alone (float64 sums in the same light order)."""
    from facegeo.capture.scan import Scan
    from facegeo.pipeline import relight as PR

    maps = _write_maps(tmp_path / "maps", seed=11)
    for m in maps:
        PR.run_relight(projected, m, view="cam_right", out_dir=tmp_path / "one")
    real, read = Scan.iter_olat, []

    def counted(self, camera, lights=None, **kw):
        for item in real(self, camera, lights, **kw):
            read.append(int(item[0]))
            yield item

    monkeypatch.setattr(Scan, "iter_olat", counted)
    run = PR.run_relight_maps(projected, maps, view="cam_right", out_dir=tmp_path / "batch")
    assert (run["maps"], run["batches"]) == (3, 1)
    assert len(read) == len(set(read)) == max(m["active_lights"] for m in run["relit"])
    assert _digests(tmp_path / "batch") == _digests(tmp_path / "one")


def test_bad_batches_are_refused_and_the_cli_relights_a_folder(projected, tmp_path):
    """Two maps of one stem would write the same files; an empty folder holds no map. The CLI
    takes ``--env`` repeated or a folder and writes every map's files."""
    from facegeo.capture import imageio
    from facegeo.cli import main
    from facegeo.pipeline.relight import (RELIGHT_BYTES_PER_TEXEL, relight_working_set,
                                          run_relight_maps)

    maps = _write_maps(tmp_path / "maps", names=("a", "b"))
    other = imageio.write_image(tmp_path / "elsewhere" / "a.exr", np.ones((8, 16, 3), np.float32))
    with pytest.raises(InputError, match="same name 'a'"):
        run_relight_maps(projected, [maps[0], other], view="texture", out_dir=tmp_path / "x")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="holds no .exr or .hdr"):
        run_relight_maps(projected, [tmp_path / "empty"], view="texture", out_dir=tmp_path / "x")
    assert not (tmp_path / "x").exists()
    # the per-texel term grows with the maps of a task, the rows' term does not
    assert (relight_working_set(1000, 128, 2, 8) - relight_working_set(1000, 128, 2, 1)
            == 1000 * 7 * RELIGHT_BYTES_PER_TEXEL)
    assert main(["relight", str(projected), "--env", str(tmp_path / "maps"), "--env", "sky",
                 "--view", "texture", "--out", str(tmp_path / "cli"), "-q"]) == 0
    assert sorted(p.name for p in (tmp_path / "cli").glob("*.exr")) == [
        "a_rot0_texture.exr", "b_rot0_texture.exr", "sky_rot0_texture.exr"]


@pytest.mark.slow
def test_texture_batch_on_two_workers_equals_in_process(projected, tmp_path, monkeypatch,
                                                        cluster):
    """The batch's tasks on the two-worker cluster: the same bytes as in process, every task
    on a worker, each map within :data:`BATCH_REL` of the map alone."""
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline import relight as PR

    maps = _write_maps(tmp_path / "maps", seed=3)
    monkeypatch.setattr(PR, "RELIGHT_MAPS_PER_TASK", 2)
    scan = load_scan(projected)
    out = projected / "out"
    runs = {}
    for tag, engine in (("in-process", None), ("cluster", cluster)):
        runs[tag] = PR.relight_maps_products(scan, out / "project", tmp_path / tag, envs=maps,
                                             atlas_dir=out / "atlas", engine=engine)
    assert _digests(tmp_path / "in-process") == _digests(tmp_path / "cluster")
    eng = runs["cluster"][0][0]["engine"]
    assert eng["kind"] == "local-cluster" and any("maps 0:2" in t for t in eng["tasks"])
    assert all(t["worker"].startswith("tcp://") for t in eng["tasks"].values())
    got = _images(tmp_path / "cluster")
    for m in maps[:2]:  # the GEMM batch
        PR.relight_products(scan, out / "project", tmp_path / "one", env=m,
                            atlas_dir=out / "atlas")
        exr = f"{m.stem}_rot0_texture.exr"
        assert _max_rel(got[exr], _images(tmp_path / "one")[exr]) <= BATCH_REL
