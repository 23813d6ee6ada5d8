"""Error types shared by every facegeo module.

Every exception facegeo raises on purpose derives from :class:`FacegeoError`. Errors about bad
input also derive from :class:`ValueError` so callers that already catch ``ValueError`` keep
working. Per-element numerical failure (a ray that misses, a texel no camera sees) is *not* an
exception: it is NaN plus a boolean mask.
"""

from __future__ import annotations

from pathlib import Path

__all__ = [
    "FacegeoError",
    "InputError",
    "ShapeError",
    "ScanFormatError",
    "MissingDependencyError",
]


class FacegeoError(Exception):
    """Base class of every error facegeo raises on purpose."""


class InputError(FacegeoError, ValueError):
    """An argument has a wrong value: non-finite, out of range, unknown option."""


class ShapeError(InputError):
    """An array argument has the wrong shape or dtype kind."""


class ScanFormatError(FacegeoError, ValueError):
    """A scan directory or manifest is malformed.

    Parameters
    ----------
    message : str
        What is wrong and what would be right.
    path : str or Path, optional
        The file (or directory) at fault.
    key : str, optional
        The manifest key at fault, dotted (``"olat.cameras.cam_left"``).
    """

    def __init__(self, message: str, *, path: str | Path | None = None, key: str | None = None):
        self.path = None if path is None else Path(path)
        self.key = key
        where = []
        if path is not None:
            where.append(str(path))
        if key is not None:
            where.append(f"[{key}]")
        prefix = (" ".join(where) + ": ") if where else ""
        super().__init__(prefix + message)


class MissingDependencyError(FacegeoError, ImportError):
    """An optional or system dependency is missing; the message says what to install."""
