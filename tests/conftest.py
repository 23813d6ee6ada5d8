"""Shared fixtures. Real third-party data is read from ``../shared/data`` (never copied into the
project); tests that need it skip with a reason when it is absent."""

from __future__ import annotations

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
