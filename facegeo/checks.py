"""Input validation shared by every public boundary.

One helper, :func:`as_array`, checks shape, dtype kind and finiteness and raises a
:class:`~facegeo.errors.ShapeError` / :class:`~facegeo.errors.InputError` that names the argument,
the expected shape and the shape received. Use it instead of ``assert``.

Shape specifications are tuples whose entries are an ``int`` (that exact length), ``None`` (any
length) or a leading ``...`` (any number of leading axes, including none)::

    as_array(p, "points", shape=(..., 3))        # (..., 3)
    as_array(K, "K", shape=(3, 3))
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from numbers import Integral
from typing import Any

import numpy as np

from facegeo.errors import InputError, ShapeError

__all__ = [
    "as_array",
    "check_finite",
    "check_positive",
    "check_positive_int",
    "check_choice",
    "check_unit_vectors",
    "format_shape",
    "fmt_value",
]


def fmt_value(x: Any) -> str:
    """A value as a user should read it in an error message.

    numpy scalars print as plain numbers (``0.5``, not ``np.float64(0.5)``, which is what
    ``f"{x!r}"`` gives since numpy 2), floats with up to 6 significant digits unless their
    shortest repr is already short (``0.1``, ``366.0``), strings quoted, ``bool`` as
    ``True``/``False``, arrays and sequences element by element (long arrays summarised).

    Examples
    --------
    >>> fmt_value(np.float64(0.5)), fmt_value(np.int64(3)), fmt_value("366")
    ('0.5', '3', "'366'")
    >>> fmt_value(np.array([1.0, np.nan])), fmt_value((np.float32(0.1), 2))
    ('[1.0, nan]', '(0.1, 2)')
    """
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, bool) or x is None:
        return repr(x)
    if isinstance(x, float):
        r = repr(x)
        return r if len(r) <= 10 else f"{x:.6g}"
    if isinstance(x, int):
        return str(x)
    if isinstance(x, str):
        return repr(x)
    if isinstance(x, np.ndarray):
        if x.size > 12:
            return (f"array of shape {tuple(x.shape)} ({x.dtype}, min {fmt_value(np.nanmin(x))}"
                    f", max {fmt_value(np.nanmax(x))})") if x.dtype.kind in "uif" else \
                f"array of shape {tuple(x.shape)} ({x.dtype})"
        return fmt_value(x.tolist())
    if isinstance(x, list):
        return "[" + ", ".join(fmt_value(v) for v in x) + "]"
    if isinstance(x, tuple):
        inner = ", ".join(fmt_value(v) for v in x)
        return f"({inner},)" if len(x) == 1 else f"({inner})"
    return repr(x)


def format_shape(shape: Sequence[Any]) -> str:
    """Return a shape spec as text, ``(..., 3)`` style."""
    parts = []
    for s in shape:
        if s is Ellipsis:
            parts.append("...")
        elif s is None:
            parts.append("N")
        else:
            parts.append(str(int(s)))
    if len(parts) == 1:
        return f"({parts[0]},)"
    return "(" + ", ".join(parts) + ")"


def _shape_matches(actual: tuple[int, ...], spec: Sequence[Any]) -> bool:
    spec = tuple(spec)
    if spec and spec[0] is Ellipsis:
        tail = spec[1:]
        if len(actual) < len(tail):
            return False
        actual = actual[len(actual) - len(tail):]
        spec = tail
    if len(actual) != len(spec):
        return False
    return all(s is None or int(s) == a for a, s in zip(actual, spec))


def as_array(
    x: Any,
    name: str,
    *,
    shape: Sequence[Any] | None = None,
    dtype: Any = np.float64,
    finite: bool = True,
    copy: bool = False,
) -> np.ndarray:
    """Convert ``x`` to an array and validate it.

    Parameters
    ----------
    x : array_like
        The value to check.
    name : str
        The argument's name, used in error messages.
    shape : sequence, optional
        Shape spec (see module docstring). ``None`` accepts any shape.
    dtype : dtype, optional
        Target dtype (default float64). ``None`` keeps the input's dtype.
    finite : bool, optional
        Reject NaN and inf (only checked for floating dtypes).
    copy : bool, optional
        Always return a copy.

    Returns
    -------
    numpy.ndarray
        The validated array.

    Raises
    ------
    ShapeError
        Wrong shape, or a value that cannot be converted to ``dtype``.
    InputError
        Non-finite values when ``finite`` is true.
    """
    try:
        a = np.array(x, dtype=dtype, copy=True) if copy else np.asarray(x, dtype=dtype)
    except (TypeError, ValueError) as exc:
        want = np.dtype(dtype).name if dtype is not None else "numeric"
        raise ShapeError(f"{name}: cannot convert to a {want} array ({exc})") from exc
    if shape is not None and not _shape_matches(a.shape, shape):
        raise ShapeError(
            f"{name}: expected shape {format_shape(shape)}, got {tuple(a.shape)}"
        )
    if finite and a.dtype.kind in "fc":
        check_finite(a, name)
    return a


def check_finite(a: np.ndarray, name: str) -> None:
    """Raise :class:`InputError` if ``a`` holds NaN or inf, saying where the first one is."""
    ok = np.isfinite(a)
    if not ok.all():
        bad = np.argwhere(~ok)
        first = tuple(int(i) for i in bad[0])
        raise InputError(
            f"{name}: {int((~ok).sum())} non-finite value(s) (NaN or inf); first at index {first}"
        )


def check_positive(value: Any, name: str, *, allow_zero: bool = False) -> float:
    """Return ``float(value)`` if it is finite and > 0 (or >= 0); else raise :class:`InputError`."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a number, got {fmt_value(value)}") from exc
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        rel = ">= 0" if allow_zero else "> 0"
        raise InputError(f"{name}: expected a finite number {rel}, got {fmt_value(value)}")
    return v


def check_positive_int(value: Any, name: str) -> int:
    """Return ``int(value)`` for a positive integer (Python or numpy int, or an integral float;
    not a bool); else raise :class:`InputError` naming ``name``."""
    v = None
    if isinstance(value, bool):
        pass
    elif isinstance(value, Integral):
        v = int(value)
    elif (isinstance(value, (float, np.floating)) and np.isfinite(value)
          and float(value).is_integer()):
        v = int(value)
    if v is None or v <= 0:
        raise InputError(f"{name}: expected a positive integer, got {fmt_value(value)}")
    return v


def check_choice(value: Any, name: str, choices: Iterable[Any]) -> Any:
    """Return ``value`` if it is one of ``choices``; else raise :class:`InputError` listing them."""
    choices = list(choices)
    if value not in choices:
        listed = ", ".join(fmt_value(c) for c in choices)
        raise InputError(f"{name}: unknown value {fmt_value(value)}; expected one of {listed}")
    return value


def check_unit_vectors(v: Any, name: str, *, tol: float = 1e-6) -> np.ndarray:
    """Validate ``(..., 3)`` unit vectors (|1 - |v|| <= tol) and return them as float64."""
    a = as_array(v, name, shape=(..., 3))
    norm = np.linalg.norm(a, axis=-1)
    bad = np.abs(norm - 1.0) > tol
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise InputError(
            f"{name}: expected unit vectors; {int(bad.sum())} have |v| off by more than {tol} "
            f"(first at index {idx}, |v| = {norm[idx]:.6g})"
        )
    return a
