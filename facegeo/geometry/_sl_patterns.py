"""Structured-light patterns: :class:`PatternSpec`, the Gray / XOR / long-run / phase-shift frames and their
values at projector pixels (the part of :mod:`facegeo.geometry.structured_light` the decoders
build on; every name is re-exported there).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, NamedTuple

import numpy as np

from facegeo.checks import as_array, check_choice, fmt_value
from facegeo.errors import InputError

log = logging.getLogger(__name__)

__all__ = ["PatternSpec", "gray_decode", "gray_encode", "pattern_image", "pattern_names",
           "pattern_value_at"]

_MAX_BITS = 24
_AXES = ("x", "y")
# Pixels per processing chunk in decode_gray: keeps the per-bit temporaries in L2 cache.
_CHUNK_PIXELS = 1 << 16


# --------------------------------------------------------------------------- Gray code


def gray_encode(n) -> np.ndarray:
    """Binary-reflected Gray code of non-negative integers: ``g = n ^ (n >> 1)``.

    Parameters
    ----------
    n : array_like of int, any shape, >= 0

    Returns
    -------
    numpy.ndarray
        Same shape, same integer dtype (int64 for Python ints).
    """
    a = _as_nonneg_int(n, "n")
    return a ^ (a >> 1)


def gray_decode(g) -> np.ndarray:
    """Inverse of :func:`gray_encode`: the integer whose Gray code is ``g`` (prefix XOR).

    Parameters
    ----------
    g : array_like of int, any shape, >= 0

    Returns
    -------
    numpy.ndarray
        Same shape, same integer dtype (int64 for Python ints).
    """
    a = _as_nonneg_int(g, "g").copy()
    shift = 1
    while shift < a.dtype.itemsize * 8:
        a ^= a >> shift
        shift *= 2
    return a


def _as_nonneg_int(x, name: str) -> np.ndarray:
    a = np.asarray(x)
    if a.dtype.kind not in "iu":
        if a.dtype.kind == "O" or a.size == 0:
            a = np.asarray(x, dtype=np.int64)
        else:
            raise InputError(f"{name}: expected integers, got dtype {a.dtype}")
    if a.dtype.kind == "i" and a.size and int(a.min()) < 0:
        raise InputError(f"{name}: expected non-negative integers, got min {int(a.min())}")
    return a


# --------------------------------------------------------------------------- pattern spec


def _bits_for(size: int) -> int:
    """ceil(log2(size)) for size >= 1 (0 for a single pixel)."""
    return (int(size) - 1).bit_length()


def _check_int(value: Any, name: str, lo: int, hi: int | None = None) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InputError(f"PatternSpec.{name}: expected an integer, got {fmt_value(value)}")
    v = int(value)
    if v < lo or (hi is not None and v > hi):
        rng = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise InputError(f"PatternSpec.{name}: expected an integer {rng}, got {v}")
    return v


def _check_bool(value: Any, name: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise InputError(f"PatternSpec.{name}: expected true or false, got {fmt_value(value)}")
    return bool(value)


@dataclass(frozen=True)
class PatternSpec:
    """What the projector shows, in projection order (see :func:`pattern_names`).

    Attributes
    ----------
    width, height : int
        Projector resolution, pixels.
    gray : bool
        Project Gray-code bit planes.
    n_bits_x, n_bits_y : int
        Gray-code bits for columns / rows; default ``ceil(log2(width))`` / ``ceil(log2(height))``
        (one code per pixel). Fewer bits code stripes ``2**(full - n)`` pixels wide; 0 skips
        that axis.
    inverse : bool
        Follow each Gray frame by its inverse; the bit is then ``frame > inverse`` per pixel,
        robust to albedo and ambient light.
    white_black : bool
        Project a full-white and a full-black frame first (shadow / albedo masks; the
        threshold ``(white + black) / 2`` when there are no inverse frames).
    phase_steps : int
        N of the N-step phase shift (0 = none, else >= 3).
    phase_periods_x, phase_periods_y : float
        Sinusoid periods across the projector width / height. Default: a 16-pixel period
        (``width / 16``), resolved when ``phase_steps > 0``.
    phase_axes : tuple of {"x", "y"}
        Axes that get phase-shift sequences, in projection order.
    codes : tuple of {"gray", "xor02", "xor04", "minsw"}
        Binary code families projected, in this order, each with ``n_bits_x`` / ``n_bits_y``
        bits (Gupta et al. 2013's ensemble of codes): ``"gray"`` the reflected Gray code;
        ``"xor02"`` / ``"xor04"`` its bit planes XORed with the plane of stripe width 2 / 4
        (every projected pattern is high-frequency, so the global light of interreflections
        is the same under a pattern and its inverse); ``"minsw"`` a long-run Gray code (every
        interior stripe of every plane >= 8 stripes wide at 10 bits: it survives subsurface
        blur; at most 16 bits). See :mod:`facegeo.geometry._sl_codes`.
        Frames of family ``c`` are named ``"{c}_{axis}_{bit:02d}"``; the default
        ``("gray",)`` keeps the classic names (and is left out of :meth:`to_dict`).

    Raises
    ------
    InputError
        Any field out of range or of the wrong type; a spec that produces no pattern.
    """

    width: int
    height: int
    gray: bool = True
    n_bits_x: int | None = None
    n_bits_y: int | None = None
    inverse: bool = True
    white_black: bool = True
    phase_steps: int = 0
    phase_periods_x: float | None = None
    phase_periods_y: float | None = None
    phase_axes: tuple[str, ...] = ("x",)
    codes: tuple[str, ...] = ("gray",)

    def __post_init__(self) -> None:
        put = functools.partial(object.__setattr__, self)
        put("width", _check_int(self.width, "width", 1))
        put("height", _check_int(self.height, "height", 1))
        for name in ("gray", "inverse", "white_black"):
            put(name, _check_bool(getattr(self, name), name))
        for axis, size in (("x", self.width), ("y", self.height)):
            key = f"n_bits_{axis}"
            val = getattr(self, key)
            put(key, _bits_for(size) if val is None else _check_int(val, key, 0, _MAX_BITS))
        if self.gray and self.n_bits_x == 0 and self.n_bits_y == 0:
            raise InputError(
                f"PatternSpec: gray=True but n_bits_x = n_bits_y = 0 for a "
                f"{self.width}x{self.height} projector; set gray=False or give bits"
            )
        steps = _check_int(self.phase_steps, "phase_steps", 0, 64)
        if steps in (1, 2):
            raise InputError(
                f"PatternSpec.phase_steps: expected 0 (no phase shift) or >= 3, got {steps} "
                "(fewer than 3 steps cannot separate offset, amplitude and phase)"
            )
        put("phase_steps", steps)
        axes = self.phase_axes
        if isinstance(axes, str):
            axes = (axes,)
        try:
            axes = tuple(axes)
        except TypeError:
            raise InputError(
                f"PatternSpec.phase_axes: expected a list of 'x'/'y', got {fmt_value(self.phase_axes)}"
            ) from None
        for a in axes:
            check_choice(a, "PatternSpec.phase_axes", _AXES)
        if len(set(axes)) != len(axes):
            raise InputError(f"PatternSpec.phase_axes: repeated axis in {list(axes)}")
        if steps and not axes:
            raise InputError("PatternSpec.phase_axes: empty, but phase_steps > 0")
        put("phase_axes", axes)
        for axis, size in (("x", self.width), ("y", self.height)):
            key = f"phase_periods_{axis}"
            val = getattr(self, key)
            if val is None:
                if steps:
                    put(key, float(size) / 16.0)
                continue
            if isinstance(val, (bool, np.bool_)):
                raise InputError(f"PatternSpec.{key}: expected a number, got {fmt_value(val)}")
            try:
                p = float(val)
            except (TypeError, ValueError):
                raise InputError(f"PatternSpec.{key}: expected a number, got {fmt_value(val)}") from None
            if not (math.isfinite(p) and p > 0):
                raise InputError(f"PatternSpec.{key}: expected a finite number > 0, got {fmt_value(val)}")
            if steps and axis in axes and size / p < 2.0:
                raise InputError(
                    f"PatternSpec.{key}: {p} periods across {size} px is a period of "
                    f"{size / p:.3g} px; the projector needs >= 2 px per period"
                )
            put(key, p)
        put("codes", _check_codes(self.codes, self.n_bits_x, self.n_bits_y))
        if not (self.gray or self.white_black or steps):
            raise InputError("PatternSpec: produces no pattern (gray, white_black and phase off)")

    # ---------------------------------------------------------------- derived

    def stripe_shift(self, axis: str) -> int:
        """``s``: Gray codes on ``axis`` name stripes ``2**s`` projector pixels wide."""
        check_choice(axis, "axis", _AXES)
        size, n = (self.width, self.n_bits_x) if axis == "x" else (self.height, self.n_bits_y)
        return max(_bits_for(size) - n, 0)

    def n_bits(self, axis: str) -> int:
        """Gray-code bits projected on ``axis`` (0 when ``gray`` is off)."""
        check_choice(axis, "axis", _AXES)
        if not self.gray:
            return 0
        return self.n_bits_x if axis == "x" else self.n_bits_y

    def phase_periods(self, axis: str) -> float | None:
        """Sinusoid periods across the projector along ``axis``."""
        check_choice(axis, "axis", _AXES)
        return self.phase_periods_x if axis == "x" else self.phase_periods_y

    # ---------------------------------------------------------------- (de)serialisation

    def to_dict(self) -> dict[str, Any]:
        """Plain ints / bools / floats / lists, ready for JSON or TOML (``None`` omitted)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None or (f.name == "codes" and v == ("gray",)):
                continue  # the default family is left out: older readers know no "codes"
            out[f.name] = list(v) if isinstance(v, tuple) else v
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PatternSpec:
        """Build from a mapping as written by :meth:`to_dict`; unknown keys raise InputError."""
        if not isinstance(d, Mapping):
            raise InputError(f"PatternSpec.from_dict: expected a mapping, got {type(d).__name__}")
        known = [f.name for f in fields(cls)]
        unknown = sorted(set(d) - set(known))
        if unknown:
            raise InputError(
                f"PatternSpec: unknown key(s) {unknown}; valid keys are {known}"
            )
        missing = [k for k in ("width", "height") if k not in d]
        if missing:
            raise InputError(f"PatternSpec: missing required key(s) {missing}")
        return cls(**dict(d))


class _Pattern(NamedTuple):
    kind: str  # "white", "black", "gray", "phase"
    axis: str | None
    index: int  # bit (MSB = 0) or phase step
    inverse: bool
    code: str = "gray"  # code family of a binary ("gray"-kind) pattern


@functools.lru_cache(maxsize=64)
def _pattern_table(spec: PatternSpec) -> dict[str, _Pattern]:
    table: dict[str, _Pattern] = {}
    if spec.white_black:
        table["white"] = _Pattern("white", None, 0, False)
        table["black"] = _Pattern("black", None, 0, False)
    for code in spec.codes:
        for axis in _AXES:
            for i in range(spec.n_bits(axis)):
                table[f"{code}_{axis}_{i:02d}"] = _Pattern("gray", axis, i, False, code)
                if spec.inverse:
                    table[f"{code}_{axis}_{i:02d}_inv"] = _Pattern("gray", axis, i, True, code)
    for axis in spec.phase_axes if spec.phase_steps else ():
        for k in range(spec.phase_steps):
            table[f"phase_{axis}_{k}"] = _Pattern("phase", axis, k, False)
    return table


def _check_codes(codes: Any, n_bits_x: int, n_bits_y: int) -> tuple[str, ...]:
    from facegeo.geometry._sl_codes import CODE_FAMILIES, max_bits, min_bits

    if isinstance(codes, str):
        codes = (codes,)
    try:
        codes = tuple(codes)
    except TypeError:
        raise InputError(f"PatternSpec.codes: expected a list of code families, got "
                         f"{fmt_value(codes)}") from None
    if not codes:
        raise InputError(f"PatternSpec.codes: empty; expected some of {list(CODE_FAMILIES)}")
    for c in codes:
        check_choice(c, "PatternSpec.codes", CODE_FAMILIES)
    if len(set(codes)) != len(codes):
        raise InputError(f"PatternSpec.codes: repeated family in {list(codes)}")
    for c in codes:
        for axis, n in (("x", n_bits_x), ("y", n_bits_y)):
            if 0 < n < min_bits(c):
                raise InputError(f"PatternSpec.codes: {c!r} needs >= {min_bits(c)} bits, "
                                 f"n_bits_{axis} is {n}")
            hi = max_bits(c)
            if hi is not None and n > hi:
                raise InputError(f"PatternSpec.codes: {c!r} takes <= {hi} bits (its decode "
                                 f"table has 2**n entries), n_bits_{axis} is {n}; give fewer "
                                 f"bits (stripes 2**(ceil(log2(size)) - n) px wide)")
    return codes


def _check_spec(spec: Any) -> PatternSpec:
    if not isinstance(spec, PatternSpec):
        raise InputError(f"spec: expected a PatternSpec, got {type(spec).__name__}")
    return spec


def pattern_names(spec: PatternSpec) -> list[str]:
    """Names of the patterns in projection order.

    ``"white", "black"`` (if ``white_black``), then ``"gray_x_00"`` (column MSB),
    ``"gray_x_00_inv"`` (if ``inverse``), ... ``"gray_x_{n-1}"`` (column LSB), then the same for
    ``y`` (rows), then ``"phase_x_0" ... "phase_x_{N-1}"`` and ``"phase_y_*"`` in
    ``spec.phase_axes`` order.

    Parameters
    ----------
    spec : PatternSpec

    Returns
    -------
    list of str
    """
    return list(_pattern_table(_check_spec(spec)))


def _lookup(spec: PatternSpec, name: str) -> _Pattern:
    table = _pattern_table(_check_spec(spec))
    try:
        return table[name]
    except (KeyError, TypeError):
        names = list(table)
        shown = ", ".join(names[:8]) + (f", ... ({len(names)} in all)" if len(names) > 8 else "")
        raise InputError(f"name: unknown pattern {fmt_value(name)} for this spec; valid: {shown}") from None


def _gray_bit(spec: PatternSpec, axis: str, bit: int, coord: np.ndarray, code: str = "gray"
              ) -> np.ndarray:
    """Bit ``bit`` (0 = MSB) of code family ``code`` at integer projector coordinates ``coord``."""
    from facegeo.geometry._sl_codes import code_bit

    return code_bit(code, spec.n_bits(axis), bit, coord >> spec.stripe_shift(axis))


def _phase_value(spec: PatternSpec, axis: str, k: int, coord: np.ndarray) -> np.ndarray:
    size = spec.width if axis == "x" else spec.height
    phi = (2.0 * np.pi * spec.phase_periods(axis) / size) * (coord + 0.5)
    return 0.5 + 0.5 * np.cos(phi - 2.0 * np.pi * k / spec.phase_steps)


def pattern_image(spec: PatternSpec, name: str) -> np.ndarray:
    """The projector image of pattern ``name``, sampled at projector pixel centres.

    Parameters
    ----------
    spec : PatternSpec
    name : str
        One of :func:`pattern_names` (``spec``).

    Returns
    -------
    (height, width) float32 in [0, 1]
        Gray frames are exactly 0 / 1 (1 = bit set, the ``_inv`` frame is ``1 - bit``); phase
        frames follow the module docstring's sinusoid.
    """
    p = _lookup(spec, name)
    shape = (spec.height, spec.width)
    if p.kind in ("white", "black"):
        return np.full(shape, 1.0 if p.kind == "white" else 0.0, dtype=np.float32)
    size = spec.width if p.axis == "x" else spec.height
    coord = np.arange(size, dtype=np.int64)
    if p.kind == "gray":
        line = _gray_bit(spec, p.axis, p.index, coord, p.code).astype(np.float32)
        if p.inverse:
            line = 1.0 - line
    else:
        line = _phase_value(spec, p.axis, p.index, coord.astype(np.float64)).astype(np.float32)
    line = line[None, :] if p.axis == "x" else line[:, None]
    return np.ascontiguousarray(np.broadcast_to(line, shape), dtype=np.float32)


def pattern_value_at(spec: PatternSpec, name: str, q_proj) -> np.ndarray:
    """Sample pattern ``name`` at continuous projector pixel coordinates.

    Binary patterns (white, black, Gray) take the value of the projector pixel containing
    ``q_proj`` (pixel ``c`` covers ``[c - 0.5, c + 0.5)``: projector pixels are hard-edged);
    phase patterns evaluate the exact sinusoid at ``q_proj``. Points outside the projector image
    ``[-0.5, width - 0.5) x [-0.5, height - 0.5)`` and non-finite points get 0 (no light).

    Parameters
    ----------
    spec : PatternSpec
    name : str
        One of :func:`pattern_names` (``spec``).
    q_proj : (..., 2) float, projector pixels (x = column, y = row)
        NaN allowed (no light).

    Returns
    -------
    (...,) float32 in [0, 1]
    """
    p = _lookup(spec, name)
    q = as_array(q_proj, "q_proj", shape=(..., 2), finite=False)
    x, y = q[..., 0], q[..., 1]
    with np.errstate(invalid="ignore"):
        inside = (x >= -0.5) & (x < spec.width - 0.5) & (y >= -0.5) & (y < spec.height - 0.5)
    out = np.zeros(x.shape, dtype=np.float32)
    if p.kind == "black" or not inside.any():
        return out
    if p.kind == "white":
        out[inside] = 1.0
        return out
    c = (x if p.axis == "x" else y)[inside]
    if p.kind == "gray":
        ic = np.floor(c + 0.5).astype(np.int64)
        v = _gray_bit(spec, p.axis, p.index, ic, p.code)
        out[inside] = (1 - v) if p.inverse else v
    else:
        out[inside] = _phase_value(spec, p.axis, p.index, c)
    return out


