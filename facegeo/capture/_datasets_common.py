"""Helpers shared by the data-set converters (:mod:`facegeo.capture.datasets`): where each
file of a scan being built came from (so errors name the source file), carrying files, nominal
cameras, and the check that a folder holds the files a data set ships."""

from __future__ import annotations

from contextvars import ContextVar
from pathlib import Path

import numpy as np

from facegeo.capture.importer import _carry as _link_or_copy
from facegeo.errors import InputError

#: Staging path -> the source file it was made from, for the conversion running in this context
#: (set by :func:`import_dataset`), so that an error about a file of the scan being built names
#: the data set's own file instead of the staging folder.
_SOURCES: ContextVar[dict[Path, Path] | None] = ContextVar("_SOURCES", default=None)


def _note_source(dst: Path, src: Path) -> None:
    """Record that the scan's file ``dst`` (in the staging folder) comes from ``src``."""
    sources = _SOURCES.get()
    if sources is not None:
        sources[Path(dst)] = Path(src)


def _carry(src: Path, dst: Path, mode: str) -> str:
    """Hard-link (or copy) one source file into the scan, recording where it came from."""
    _note_source(dst, src)
    return _link_or_copy(src, dst, mode)


def _nominal_camera(name: str, width: int, height: int, eye=(0.0, 0.0, 1.0)):
    """A pinhole camera with f = width, centred principal point, looking at the origin."""
    from facegeo.frames import look_at
    from facegeo.geometry.camera import Camera

    f = float(width)
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return Camera(name, int(width), int(height), K, np.zeros(5), look_at(eye, (0.0, 0.0, 0.0)))


def _image_size(path: Path) -> tuple[int, int]:
    from facegeo.capture.imageio import read_image_size

    return read_image_size(path)


def _need(src: Path, names) -> list[Path]:
    paths = [src / n for n in names]
    missing = [p.name for p in paths if not p.is_file()]
    if missing:
        raise InputError(f"{src}: not the expected data set; missing "
                         f"{', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}")
    return paths


def _frame_bits(path: Path) -> int:
    """Bits per sample of an image file (8 or 16), from its header."""
    from facegeo.capture.imageio import read_image_info

    info = read_image_info(path, verify=False)
    return 16 if np.dtype(info.dtype).itemsize == 2 else 8
