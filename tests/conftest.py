"""Shared fixtures. Real third-party data is read from ``../shared/data`` (never copied into the
project); tests that need it skip with a reason when it is absent."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest

_DEFAULT_SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
SHARED_DATA = Path(os.environ.get("FACEGEO_SHARED_DATA", _DEFAULT_SHARED))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ``../shared/data``; skips the test when the folder is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder {SHARED_DATA} is absent (set FACEGEO_SHARED_DATA)")
    return SHARED_DATA


def shared_file(shared_data: Path, rel: str) -> Path:
    """A file under the shared data folder; skips with a reason when it is missing."""
    p = shared_data / rel
    if not p.exists():
        pytest.skip(f"shared data file {p} is absent")
    return p


@pytest.fixture
def baseline_cpu_python(tmp_path):
    """``run(code)``: ``code`` in a fresh interpreter whose numba compiles for a baseline x86-64
    CPU (``NUMBA_CPU_NAME=x86-64``, SSE2 only) into a fresh disk cache, with this checkout's
    facegeo first on the path; returns the ``subprocess.CompletedProcess`` (text output). For
    kernels whose code generation depends on the host's instruction set."""
    import subprocess
    import sys

    import facegeo

    def run(code: str):
        env = dict(os.environ, NUMBA_CPU_NAME="x86-64", NUMBA_CPU_FEATURES="+sse2",
                   NUMBA_CACHE_DIR=str(tmp_path / "numba"),
                   PYTHONPATH=str(Path(facegeo.__file__).resolve().parents[1]))
        return subprocess.run([sys.executable, "-c", code], check=False, capture_output=True,
                              text=True, timeout=600, env=env, cwd=tmp_path)

    return run


#: Memory limit of each worker of the scale tests' two-worker cluster (``cluster``): a test
#: module may set its own ``WORKER_LIMIT``.
SCALE_WORKER_LIMIT = "800MiB"


@pytest.fixture(scope="module")
def cluster(request):
    """A two-worker Dask ``LocalCluster`` engine for one test module (workers limited to the
    module's ``WORKER_LIMIT``, default :data:`SCALE_WORKER_LIMIT`)."""
    from facegeo.pipeline.engine import make_engine

    limit = getattr(request.module, "WORKER_LIMIT", SCALE_WORKER_LIMIT)
    with make_engine(workers=2, memory_limit=limit) as eng:
        yield eng


@pytest.fixture(scope="module")
def projected(tmp_path_factory):
    """A tiny synthetic scan with its atlas and in-process projection (``.npy`` fields), made
    once per test module."""
    from facegeo.pipeline.project import run_atlas, run_project
    from facegeo.synth.capture import generate_scan

    root = tmp_path_factory.mktemp("projected") / "tiny"
    generate_scan(root, "tiny")
    run_atlas(root)
    run_project(root, evaluate=False)
    return root


def _run_shared_dir(tmp_path_factory) -> Path:
    """A folder every test process of this run shares: the parent of the xdist worker's base
    temp folder under ``pytest -n``, else the base temp folder itself (a fresh one per run)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@pytest.fixture
def small_witness_scan(tmp_path_factory, tmp_path) -> Path:
    """The demo's scan (``small`` preset, seed 0) with the calibration-only witness camera and
    its reference image (``synth --witness``), generated once per test run — minutes of the
    generator's — and shared by the test processes (a file lock); each test gets its own copy
    to run stages into: hard links (no stage writes into a scan's input files), but for the
    record of written files, which the stages append to (a copy of its own)."""
    import fcntl
    import shutil

    from facegeo.fsutil import WRITTEN_RECORD
    from facegeo.synth.capture import generate_scan

    def link_or_copy(src, dst):
        return (shutil.copy2 if Path(src).name == WRITTEN_RECORD else os.link)(src, dst)

    shared = _run_shared_dir(tmp_path_factory)
    master = shared / "small_witness_seed0"
    with open(shared / "small_witness_seed0.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (master / WRITTEN_RECORD).is_file():  # the generator writes it last
            shutil.rmtree(master, ignore_errors=True)
            generate_scan(master, "small", seed=0, witness=True)
    root = tmp_path / "small"
    shutil.copytree(master, root, copy_function=link_or_copy,
                    ignore=shutil.ignore_patterns("out"))
    return root


#: The ``fitted`` fixture's atlas (coarser than the default 1 texel/mm) and fit (an even
#: subsample of the functions the views need): a fast fixture, as tests/test_fit_stage.py's.
FITTED_TEXELS_PER_MM = 0.35
FITTED_MAX_TEXELS = 60


@pytest.fixture(scope="module")
def fitted(request, tmp_path_factory):
    """A tiny synthetic scan with its atlas, projection and a subsampled fit for the views of
    the test module's ``VIEWS``, made once per test module."""
    from facegeo.pipeline.fit import run_fit
    from facegeo.pipeline.project import run_project
    from facegeo.synth.capture import generate_scan

    root = tmp_path_factory.mktemp("fitted") / "tiny"
    generate_scan(root, "tiny")
    run_project(root, atlas_settings={"texels_per_mm": FITTED_TEXELS_PER_MM}, evaluate=False)
    run_fit(root, texels="views", views=list(request.module.VIEWS),
            max_texels=FITTED_MAX_TEXELS, mosaic=4)
    return root


def file_digests(folder: Path, skip=("stage.json",)) -> dict[str, str]:
    """SHA-256 of every file below ``folder`` by relative path (but names in ``skip``): the
    byte-for-byte comparison of two runs' products."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(Path(folder).rglob("*")) if p.is_file() and p.name not in skip}


def timeless(doc):
    """``doc`` without the keys naming ``seconds`` (timings), at every depth."""
    if isinstance(doc, dict):
        return {k: timeless(v) for k, v in doc.items() if "seconds" not in k}
    if isinstance(doc, list):
        return [timeless(v) for v in doc]
    return doc


def stage_metrics_without(metrics: dict, keys) -> dict:
    """A copy of a stage's metrics without the engine record and the ``keys`` (timings, task
    counts), at the top and in each of its ``cameras``: what two runs of the stage share."""
    m = json.loads(json.dumps(metrics))
    m.pop("engine", None)
    for part in [m, *m.get("cameras", {}).values()]:
        for k in keys:
            part.pop(k, None)
    return m
