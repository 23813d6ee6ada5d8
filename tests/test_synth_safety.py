"""Data safety of the synthetic generator (issue 7, "Data safety").

``facegeo synth OUT --overwrite`` / ``demo --regenerate`` must never lose a file facegeo did not
write, never touch a real capture, validate everything before touching the disk, follow no
symlink when deleting, and leave the old scan intact when interrupted or failing.

Every check compares SHA-256 hashes of every file (byte-for-byte), so each test fails for the
bug it names: a deleted, truncated or rewritten user file changes the hash set.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import facegeo
from facegeo import fsutil
from facegeo.capture.scan import load_scan
from facegeo.cli import main
from facegeo.errors import InputError
from facegeo.synth.capture import generate_scan

REPO = Path(facegeo.__file__).resolve().parents[1]
#: Kill the interrupted run once its staging directory holds at least this many OLAT frames
#: (tiny: 256 in all), i.e. well into the write, long before the swap.
KILL_AFTER_OLAT_FILES = 10
#: Give up waiting for the subprocess to reach that point after this long (a hung run).
SUBPROCESS_TIMEOUT_S = 120


def tree_hashes(root: Path) -> dict[str, str]:
    """``{relative path: sha256}`` of every entry under ``root`` without following symlinks
    (a symlink hashes as ``link:<target>``); directories are listed with a trailing ``/``."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        d = Path(dirpath)
        for name in dirnames + filenames:
            p = d / name
            rel = p.relative_to(root).as_posix()
            if p.is_symlink():
                out[rel] = "link:" + os.readlink(p)
            elif p.is_dir():
                out[rel + "/"] = "dir"
            else:
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def leftovers(parent: Path) -> list[str]:
    """Staging directories and temporary files facegeo may leave in ``parent`` (recursively)."""
    bad = []
    for dirpath, dirnames, filenames in os.walk(parent, followlinks=False):
        for name in dirnames + filenames:
            if ".facegeo-tmp-" in name or ".facegeo-old-" in name:
                bad.append(os.path.join(dirpath, name))
            elif name.startswith(".") and name != fsutil.WRITTEN_RECORD and "." in name[1:]:
                bad.append(os.path.join(dirpath, name))  # atomic_path's ".name.XXXX.ext"
    return bad


@pytest.fixture(scope="module")
def base_scan(tmp_path_factory):
    """One tiny synthetic scan (seed 0) and the progress calls made while writing it."""
    root = tmp_path_factory.mktemp("base") / "scan"
    calls = []
    generate_scan(root, "tiny", seed=0, progress=lambda s, d, t: calls.append((s, d, t)))
    return root, calls


@pytest.fixture
def old_scan(base_scan, tmp_path):
    """A private copy of the base scan in its own parent directory."""
    root = tmp_path / "scan"
    shutil.copytree(base_scan[0], root, symlinks=True)
    return root


def _set_synthetic(root: Path, value: str | None) -> None:
    toml = root / "scan.toml"
    lines = toml.read_text().splitlines(keepends=True)
    lines = [(f"synthetic = {value}\n" if value is not None else "")
             if ln.startswith("synthetic =") else ln for ln in lines]
    toml.write_text("".join(lines))


# --------------------------------------------------------------------------- what is written


def test_written_record_lists_exactly_the_files_written(base_scan):
    root, _ = base_scan
    recorded = fsutil.read_written_record(root)
    on_disk = set(fsutil.list_files(root)) - {fsutil.WRITTEN_RECORD}
    assert recorded == on_disk
    assert "scan.toml" in recorded and "olat/cam_left/0000.exr" in recorded
    assert not leftovers(root.parent)


def test_ground_truth_has_its_own_progress_stage(base_scan):
    """The former silent pause after the OLAT bar (reference renders) reports progress."""
    _, calls = base_scan
    stages = list(dict.fromkeys(s for s, _, _ in calls))
    assert stages == ["calib", "calib.projector", "structured_light", "olat", "ground_truth"]
    gt = [(d, t) for s, d, t in calls if s == "ground_truth"]
    n_cams = 2 + 3  # capture cameras + novel viewpoints at preset tiny
    assert gt[-1] == (1 + 3 * n_cams, 1 + 3 * n_cams)
    assert [d for d, _ in gt] == list(range(len(gt)))  # 0, 1, 2, ... one step at a time
    # nothing else is reported after the last OLAT frame: the renders are in this stage
    last_olat = max(i for i, c in enumerate(calls) if c[0] == "olat")
    assert all(c[0] == "ground_truth" for c in calls[last_olat + 1:])


# --------------------------------------------------------------------------- user files survive


@pytest.mark.slow
def test_overwrite_keeps_user_files_and_removes_only_facegeo_files(old_scan):
    root = old_scan
    user = {
        "out/notes.txt": b"my fit notes",
        "calib/notes.md": b"board was bent",
        "olat/cam_left/extra_exposure.txt": b"1/60 s",
        "README": b"capture of 2026-11-23",
    }
    for rel, data in user.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    (root / "out" / "empty_dir").mkdir()
    # a file facegeo wrote (per the record) that the new run does not write: removed
    (root / "olat" / "cam_left" / "9999.exr").write_bytes(b"stale")
    rec = fsutil.read_written_record(root) | {"olat/cam_left/9999.exr"}
    fsutil.write_written_record(root, rec)

    summary = generate_scan(root, "tiny", seed=1, overwrite=True)

    for rel, data in user.items():
        assert (root / rel).read_bytes() == data, rel
    assert (root / "out" / "empty_dir").is_dir()
    assert not (root / "olat" / "cam_left" / "9999.exr").exists()
    assert sorted(summary.kept) == sorted(list(user) + ["out/empty_dir"])
    scan = load_scan(root, check="full")
    assert "seed 1" in scan.description
    # the new record lists the new scan's files, not the user's
    assert not set(user) & fsutil.read_written_record(root)
    assert not leftovers(root.parent)


def test_products_written_into_the_scan_are_recorded_and_replaced_with_it(old_scan):
    """Products of the stages (a staged folder, single files) go into the scan's record as they
    are written, so regenerating the scan removes them — they were computed from the old scan —
    while the user's own file in ``out/`` stays."""
    from facegeo.pipeline.project import run_atlas

    from facegeo.geometry.rig import Rig

    root = old_scan
    run_atlas(root, texels_per_mm=0.3)  # out/atlas/ (staged) and out/metrics.json (atomic)
    fsutil.atomic_write_text(root / "out" / "views" / "note.json", "{}")
    (root / "out" / "mine.txt").write_text("my notes")
    # saved with the library but not a product: outside out/, or in a scan nested in this one
    Rig.load(root / "rig.json").save(root / "my_rig.json")
    nested = root / "imports" / "inner"
    nested.mkdir(parents=True)
    (nested / "scan.toml").write_text("# another scan's manifest\n")
    fsutil.atomic_write_text(nested / "out" / "metrics.json", "{}")
    rec = fsutil.read_written_record(root)
    assert {"out/metrics.json", "out/atlas/atlas.npz", "out/atlas/texels.npz",
            "out/atlas/stage.json", "out/views/note.json"} <= rec
    assert not {"out/mine.txt", "my_rig.json", "imports/inner/out/metrics.json"} & rec
    assert not any(".facegeo-tmp-" in r for r in rec)  # staging folders never recorded

    summary = generate_scan(root, "tiny", seed=2, overwrite=True)

    assert sorted(summary.kept) == ["imports/inner/out/metrics.json", "imports/inner/scan.toml",
                                    "my_rig.json", "out/mine.txt"]
    assert (root / "out" / "mine.txt").read_text() == "my notes"
    for gone in ("out/metrics.json", "out/atlas", "out/views"):
        assert not (root / gone).exists(), gone
    assert not leftovers(root.parent)


@pytest.mark.slow
def test_scan_without_record_keeps_files_its_manifest_does_not_list(old_scan):
    """A synthetic scan written before the record existed: the manifest tells facegeo's files
    from the user's."""
    root = old_scan
    (root / fsutil.WRITTEN_RECORD).unlink()
    (root / "olat" / "cam_left" / "notes.txt").write_bytes(b"user")
    (root / "out").mkdir()
    (root / "out" / "fit.npz").write_bytes(b"user2")
    summary = generate_scan(root, "tiny", seed=1, overwrite=True)
    assert (root / "olat" / "cam_left" / "notes.txt").read_bytes() == b"user"
    assert (root / "out" / "fit.npz").read_bytes() == b"user2"
    assert sorted(summary.kept) == ["olat/cam_left/notes.txt", "out/fit.npz"]  # no .keep files
    load_scan(root, check="full")


# --------------------------------------------------------------------------- real captures


@pytest.mark.parametrize("synthetic", ["false", None], ids=["synthetic-false", "no-marker"])
def test_real_capture_is_refused_and_unchanged(old_scan, synthetic):
    root = old_scan
    _set_synthetic(root, synthetic)
    (root / "out").mkdir()
    (root / "out" / "mine.txt").write_bytes(b"x")
    before = tree_hashes(root.parent)
    with pytest.raises(InputError, match="real capture"):
        generate_scan(root, "tiny", seed=1, overwrite=True)
    assert tree_hashes(root.parent) == before


def test_real_capture_refused_through_cli(old_scan, capsys):
    root = old_scan
    _set_synthetic(root, "false")
    before = tree_hashes(root.parent)
    rc = main(["synth", str(root), "--preset", "tiny", "--overwrite", "-q"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and "real capture" in err[0] and str(root) in err[0]
    assert "Traceback" not in err[0]
    assert tree_hashes(root.parent) == before


def test_directory_with_files_but_no_manifest_is_refused(tmp_path):
    root = tmp_path / "capture_in_progress"
    (root / "olat").mkdir(parents=True)
    (root / "olat" / "0000.exr").write_bytes(b"frame")
    before = tree_hashes(tmp_path)
    with pytest.raises(InputError, match="no scan.toml"):
        generate_scan(root, "tiny")
    assert tree_hashes(tmp_path) == before


# --------------------------------------------------------------------------- invalid arguments


@pytest.mark.parametrize("kwargs, match", [
    ({"seed": -1}, "seed: expected an integer >= 0"),
    ({"seed": 1.5}, "seed: expected an integer >= 0"),
    ({"units": "inch"}, "units: unknown 'inch'"),
    ({"head": "/nonexistent/head.obj"}, "no such mesh file"),
    ({"noise": -0.1}, "noise: expected a finite number"),
    ({"noise": float("nan")}, "noise: expected a finite number"),
    ({"skin": "spectral:green"}, "unknown spectral skin type"),
    ({"olat_format": "tiff"}, "olat_format: unknown"),
    ({"backdrop": 1.5}, "backdrop: expected an albedo in \\[0, 1\\]"),
    ({"backdrop": float("nan")}, "backdrop: expected an albedo"),
    ({"preset": "huge"}, "preset: unknown 'huge'"),
], ids=lambda v: str(v) if isinstance(v, dict) else "")
def test_invalid_argument_leaves_old_scan_unchanged(old_scan, kwargs, match):
    root = old_scan
    before = tree_hashes(root.parent)
    args = {"preset": "tiny", "seed": 1, **kwargs}
    with pytest.raises(InputError, match=match):
        generate_scan(root, args.pop("preset"), overwrite=True, **args)
    assert tree_hashes(root.parent) == before


def test_bad_mesh_leaves_no_folders(tmp_path):
    """A fresh OUT (and parents this call would create) does not exist after a failure."""
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nf 1 2 3\n")
    out = tmp_path / "new" / "deeper" / "scan"
    with pytest.raises(InputError, match="bad.obj"):
        generate_scan(out, "tiny", head=str(bad))
    assert sorted(os.listdir(tmp_path)) == ["bad.obj"]


def test_out_that_is_a_file_is_refused(tmp_path, capsys):
    f = tmp_path / "scan"
    f.write_bytes(b"not a scan")
    rc = main(["synth", str(f), "--preset", "tiny", "-q"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and str(f) in err[0] and "expected a directory" in err[0]
    assert f.read_bytes() == b"not a scan"


def test_bad_seed_through_cli_is_one_line(old_scan, capsys):
    before = tree_hashes(old_scan.parent)
    with pytest.raises(SystemExit) as exc:  # argparse rejects it before anything runs
        main(["synth", str(old_scan), "--preset", "tiny", "--overwrite", "-q", "--seed", "-1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(err) == 1 and "seed" in err[0] and "-1" in err[0]
    assert tree_hashes(old_scan.parent) == before


def test_unwritable_parent_is_refused(tmp_path, monkeypatch):
    parent = tmp_path / "ro"
    parent.mkdir()
    real_access = os.access

    def access(path, mode, *a, **kw):  # as for a non-root user on a 0555 directory
        if Path(path) == parent and mode & os.W_OK:
            return False
        return real_access(path, mode, *a, **kw)

    monkeypatch.setattr(os, "access", access)
    with pytest.raises(InputError, match=r"ro: not writable"):
        generate_scan(parent / "new" / "scan", "tiny")
    assert os.listdir(parent) == []


# --------------------------------------------------------------------------- symlinks


@pytest.mark.slow
def test_symlinked_olat_is_not_followed(old_scan, tmp_path):
    root = old_scan
    elsewhere = tmp_path / "bigdisk_olat"
    shutil.move(root / "olat", elsewhere)
    (elsewhere / "keep_me.txt").write_bytes(b"user file on the other disk")
    os.symlink(elsewhere, root / "olat")
    target_before = tree_hashes(elsewhere)

    summary = generate_scan(root, "tiny", seed=1, overwrite=True)

    assert tree_hashes(elsewhere) == target_before  # the link's target: every file intact
    assert (root / "olat").is_dir() and not (root / "olat").is_symlink()  # the new frames
    assert os.readlink(root / "olat.keep") == str(elsewhere)  # the link itself is kept aside
    assert "olat.keep" in summary.kept
    load_scan(root, check="full")


def test_remove_tree_never_follows_symlinks(tmp_path):
    target = tmp_path / "target"
    target.mkdir()
    (target / "f").write_bytes(b"precious")
    d = tmp_path / "d"
    d.mkdir()
    os.symlink(target, d / "link_to_dir")
    os.symlink(target / "f", d / "link_to_file")
    fsutil.remove_tree(d)
    assert not d.exists() and (target / "f").read_bytes() == b"precious"
    link = tmp_path / "link"
    os.symlink(target, link)
    fsutil.remove_tree(link)
    assert not os.path.lexists(link) and (target / "f").read_bytes() == b"precious"


# --------------------------------------------------------------------------- interruptions


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_atomic_path_leaves_nothing_on_keyboard_interrupt(tmp_path):
    target = tmp_path / "f.exr"
    target.write_bytes(b"old")
    with pytest.raises(KeyboardInterrupt):
        with fsutil.atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise KeyboardInterrupt
    assert os.listdir(tmp_path) == ["f.exr"] and target.read_bytes() == b"old"


@pytest.mark.parametrize("exc", [RuntimeError("disk full"), KeyboardInterrupt()],
                         ids=["exception", "ctrl-c"])
def test_failure_mid_write_leaves_old_scan_and_no_temp_files(old_scan, monkeypatch, exc):
    from facegeo.capture import imageio

    root = old_scan
    before = tree_hashes(root.parent)
    real_write = imageio.write_image
    calls = []

    def failing_write(path, img, **kw):
        calls.append(path)
        if len(calls) == 60:  # inside the projector-calibration frames
            with fsutil.atomic_path(path) as tmp:  # fail with a temporary file open
                tmp.write_bytes(b"partial")
                raise exc
        return real_write(path, img, **kw)

    monkeypatch.setattr(imageio, "write_image", failing_write)
    with pytest.raises(type(exc)):
        generate_scan(root, "tiny", seed=1, overwrite=True)
    assert len(calls) == 60
    assert tree_hashes(root.parent) == before  # old scan byte for byte, nothing else left


def test_failure_mid_write_of_fresh_scan_leaves_nothing(tmp_path, monkeypatch):
    from facegeo.capture import imageio

    def failing_write(path, img, **kw):
        raise OSError("disk full")

    monkeypatch.setattr(imageio, "write_image", failing_write)
    with pytest.raises(OSError, match="disk full"):
        generate_scan(tmp_path / "a" / "scan", "tiny")
    assert os.listdir(tmp_path) == []


def test_stale_siblings_are_cleaned_or_restored(tmp_path):
    target = tmp_path / "scan"
    dead = _dead_pid()
    stale_tmp = tmp_path / f".scan.facegeo-tmp-{dead}-abc"
    live_tmp = tmp_path / f".scan.facegeo-tmp-{os.getpid()}-def"  # a run still going
    stale_old = tmp_path / f".scan.facegeo-old-{dead}-ghi"
    other = tmp_path / f".other.facegeo-tmp-{dead}-abc"  # another scan's: not ours
    for d in (stale_tmp, live_tmp, stale_old, other):
        d.mkdir()
    (stale_old / "scan.toml").write_bytes(b"old manifest")
    # killed between the two renames: the target is missing -> the old scan comes back
    fsutil.clean_stale_siblings(target)
    assert (target / "scan.toml").read_bytes() == b"old manifest"
    assert not stale_tmp.exists() and live_tmp.is_dir() and other.is_dir()


@pytest.mark.slow
def test_killed_regeneration_leaves_old_scan_readable(old_scan):
    """SIGKILL (no cleanup possible) part-way through ``synth --overwrite``: the old scan still
    loads with a full check, and the next ``--overwrite`` run succeeds."""
    root = old_scan
    before = tree_hashes(root)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen(
        [sys.executable, "-m", "facegeo.cli", "synth", str(root), "--preset", "tiny",
         "--overwrite", "-q", "--seed", "3"],
        cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + SUBPROCESS_TIMEOUT_S
        n = 0
        while time.monotonic() < deadline and proc.poll() is None:
            n = len(list(root.parent.glob(".scan.facegeo-tmp-*/olat/*/*.exr")))
            if n >= KILL_AFTER_OLAT_FILES:
                break
            time.sleep(0.02)
        assert proc.poll() is None, "the run finished before it could be interrupted"
        assert n >= KILL_AFTER_OLAT_FILES
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert list(root.parent.glob(".scan.facegeo-tmp-*"))  # the killed run's leftovers
    scan = load_scan(root, check="full")
    assert "seed 0" in scan.description
    assert tree_hashes(root) == before

    generate_scan(root, "tiny", seed=4, overwrite=True)
    assert "seed 4" in load_scan(root, check="full").description
    assert not leftovers(root.parent)


def test_written_record_round_trip_and_add(tmp_path):
    assert fsutil.read_written_record(tmp_path) is None
    fsutil.write_written_record(tmp_path, ["b/c.exr", "a.json", fsutil.WRITTEN_RECORD])
    assert fsutil.read_written_record(tmp_path) == {"a.json", "b/c.exr"}
    fsutil.add_to_written_record(tmp_path, ["out/fit.npz"])
    assert fsutil.read_written_record(tmp_path) == {"a.json", "b/c.exr", "out/fit.npz"}
    with pytest.raises(ValueError, match="not a relative path"):
        fsutil.write_written_record(tmp_path, ["../escape"])
    assert fsutil.read_written_record(tmp_path) == {"a.json", "b/c.exr", "out/fit.npz"}


def test_demo_regenerate_refuses_real_capture(old_scan, capsys):
    """``facegeo demo --regenerate`` goes through the same checks as ``synth --overwrite``."""
    _set_synthetic(old_scan, None)
    before = tree_hashes(old_scan.parent)
    rc = main(["demo", str(old_scan), "--preset", "tiny", "--regenerate", "-q"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "real capture" in err[0]
    assert tree_hashes(old_scan.parent) == before
