"""Camera responses: how stored 8/16-bit code values map to linear exposure, and back.

Radiometry (``docs/conventions.md``): every pixel value inside the library is linear float32.
8/16-bit frames are linearised by a declared :class:`Response` (``"linear"``, ``"srgb"``, a
gamma, or a tabulated Debevec–Malik curve); saturated and black-clipped samples are flagged by
:func:`saturated_mask` and :func:`clipped_mask` and must never be trusted.

This module works on pixel arrays; image files are read and written by :mod:`facegeo.capture.imageio`,
which re-exports every public name here (``facegeo.capture.imageio.linearize`` and
``facegeo.capture.response.linearize`` are the same function). The only file it reads is a response
table's ``.npy`` (:func:`load_response_table`).

References
----------
Debevec, P. E., Malik, J. (1997). Recovering High Dynamic Range Radiance Maps from
Photographs. SIGGRAPH 97.
IEC 61966-2-1:1999, the sRGB transfer function.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.checks import as_array, fmt_value
from facegeo.errors import InputError, ScanFormatError

__all__ = [
    "RESPONSE_KINDS",
    "Response",
    "parse_response",
    "load_response_table",
    "linearize",
    "encode",
    "saturated_mask",
    "clipped_mask",
    "srgb_to_linear",
    "linear_to_srgb",
]

RESPONSE_KINDS = ("linear", "srgb", "gamma", "table")

_INT_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16))


# --------------------------------------------------------------------------- transfer curves
#
# Kept in numpy rather than ``colour.cctf_decoding / cctf_encoding(function="sRGB")``: the
# results are identical (max difference 0.0, but 2.3e-9 at exactly c = 0.04045 where colour
# takes the power branch; tests/test_library_equivalence.py), but colour-science was 1.2–1.6× slower on a 1280×1024×3
# float64 frame (encode 341 vs 548 ms, decode 914 vs 1105 ms, best of 5, shared machine at load
# ≈ 10) and importing it takes 0.7 s idle (4–8 s under that load) — a cost every 8/16-bit frame
# read (``facegeo info``, the decoders) would pay for two lines of arithmetic.


def srgb_to_linear(c: Any) -> np.ndarray:
    """The sRGB decoding curve (IEC 61966-2-1), encoded ``[0, 1]`` to linear ``[0, 1]``."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: Any) -> np.ndarray:
    """The sRGB encoding curve (IEC 61966-2-1), linear ``[0, 1]`` to encoded ``[0, 1]``."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1.0 / 2.4) - 0.055)


#: Float32 bit patterns are bucketed by their top bits (sign, exponent and 7 mantissa bits) for
#: :func:`_srgb8_from_float32`; every bucket of [0, 1] holds at most one uint8 code boundary.
_SRGB8_BUCKET_SHIFT = 16


@functools.cache
def _srgb8_tables() -> tuple[np.ndarray, np.ndarray]:
    """Look-up tables of :func:`_srgb8_from_float32`, derived from the curve itself.

    For each code ``c`` in 1..255 the threshold ``t_c`` is the smallest float32 ``x`` in
    ``[0, 1]`` whose formula code ``rint(255 · linear_to_srgb(x))`` is at least ``c`` (bisection
    over the float32 bit patterns, which order non-negative floats). A bucket of bit patterns
    ``b >> 16`` then stores ``base`` (the number of thresholds below the bucket's first value)
    and ``thr`` (the one threshold inside it, +inf when none).

    Returns
    -------
    base : (B,) uint8
    thr : (B,) float32
    """
    code_max = 255
    c = np.arange(1, code_max + 1)
    one = int(np.float32(1.0).view(np.uint32))
    lo = np.zeros(code_max, np.int64)
    hi = np.full(code_max, one, np.int64)
    while np.any(lo < hi):
        mid = (lo + hi) // 2
        x = mid.astype(np.uint32).view(np.float32).astype(np.float64)
        ok = np.rint(linear_to_srgb(x) * code_max) >= c
        hi = np.where(ok, mid, hi)
        lo = np.where(ok, lo, mid + 1)
    t_bits = lo.astype(np.uint32)
    bucket = t_bits >> _SRGB8_BUCKET_SHIFT
    n_buckets = (one >> _SRGB8_BUCKET_SHIFT) + 1
    if np.bincount(bucket).max() > 1:  # the curve's steepest part decides; fixed by the curve
        raise RuntimeError("sRGB look-up: a bucket holds two code boundaries; lower the shift")
    starts = np.arange(n_buckets, dtype=np.uint32) << _SRGB8_BUCKET_SHIFT
    base = np.searchsorted(t_bits, starts, side="left").astype(np.uint8)
    thr = np.full(n_buckets, np.inf, np.float32)
    thr[bucket] = t_bits.view(np.float32)
    base.setflags(write=False)
    thr.setflags(write=False)
    return base, thr


def _srgb8_from_float32(x: np.ndarray) -> np.ndarray:
    """``rint(255 · linear_to_srgb(clip(x, 0, 1)))`` as uint8 for finite float32 ``x``, by table.

    Identical to the formula for every float32 input (checked for all 1,065,353,217 float32s of
    [0, 1] in ``tests/test_imageio.py``; values outside clip first), ≈ 10× faster: two gathers
    and a compare instead of a float64 power per channel. The code is the number of thresholds
    ``t_c <= x`` (:func:`_srgb8_tables`); a bucket holds at most one.
    """
    x = np.clip(x, np.float32(0.0), np.float32(1.0))
    # clip keeps -0.0: drop the sign bit so it lands in bucket 0 like +0.0
    i = (x.view(np.uint32) & np.uint32(0x7FFFFFFF)) >> _SRGB8_BUCKET_SHIFT
    base, thr = _srgb8_tables()
    return base[i] + (x >= thr[i]).view(np.uint8)


# --------------------------------------------------------------------------- responses


@dataclass(frozen=True, eq=False)
class Response:
    """A camera response: how stored 8/16-bit code values map to linear exposure.

    Parameters
    ----------
    kind : {"linear", "srgb", "gamma", "table"}
        ``"linear"``: value = code / code_max. ``"srgb"``: the IEC 61966-2-1 curve.
        ``"gamma"``: value = (code / code_max) ** gamma. ``"table"``: a tabulated
        Debevec–Malik curve, value = table[code].
    gamma : float, optional
        Exponent for ``kind="gamma"`` (> 0).
    table : (levels,) or (levels, 3) float64, optional
        For ``kind="table"``: linear exposure per code value (one curve, or one per RGB
        channel), finite, >= 0 and non-decreasing along ``levels``. It is normalised so its
        largest entry is 1, so linearised values lie in [0, 1]. ``levels`` must be 256 for
        uint8 frames and 65536 for uint16 frames.
    file : str, optional
        For ``kind="table"``: the manifest's relative path of the ``.npy`` file (kept for
        :meth:`to_spec`).
    """

    kind: str
    gamma: float | None = None
    table: np.ndarray | None = None
    file: str | None = None
    _luts: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        if self.kind not in RESPONSE_KINDS:
            raise InputError(
                f"response: unknown kind {fmt_value(self.kind)}; expected one of "
                + ", ".join(repr(k) for k in RESPONSE_KINDS)
            )
        if self.kind == "gamma":
            g = self.gamma
            bad = isinstance(g, bool) or not isinstance(g, (int, float))
            if bad or not np.isfinite(g) or g <= 0:
                raise InputError(f"response: gamma must be a finite number > 0, got {fmt_value(g)}")
            object.__setattr__(self, "gamma", float(g))
        if self.kind == "table":
            if self.table is None:
                raise InputError("response: kind 'table' needs a table")
            object.__setattr__(self, "table", _check_table(self.table, "response table"))

    # -- constructors / serialisation

    @classmethod
    def from_table(cls, table: Any, *, file: str | None = None) -> Response:
        """A tabulated response (see the class docstring for the table's rules)."""
        return cls("table", table=np.asarray(table), file=file)

    def to_spec(self) -> str | dict:
        """The manifest value: ``"linear"``, ``"srgb"``, ``{"kind": "gamma", "gamma": g}`` or
        ``{"kind": "table", "file": ...}``."""
        if self.kind in ("linear", "srgb"):
            return self.kind
        if self.kind == "gamma":
            return {"kind": "gamma", "gamma": self.gamma}
        if self.file is None:
            raise InputError("response: an in-memory table has no manifest form; save it first")
        return {"kind": "table", "file": self.file}

    def __repr__(self) -> str:
        if self.kind == "gamma":
            return f"Response('gamma', gamma={self.gamma})"
        if self.kind == "table":
            return f"Response('table', levels={self.table.shape[0]}, file={self.file!r})"
        return f"Response({self.kind!r})"

    # -- evaluation

    def _decode(self, c: np.ndarray) -> np.ndarray:
        """Encoded value in [0, 1] → linear in [0, 1] (analytic kinds)."""
        if self.kind == "linear":
            return c
        if self.kind == "srgb":
            return srgb_to_linear(c)
        return np.clip(c, 0.0, 1.0) ** self.gamma

    def _encode(self, x: np.ndarray) -> np.ndarray:
        """Linear in [0, 1] → encoded value in [0, 1] (analytic kinds)."""
        x = np.clip(x, 0.0, 1.0)
        if self.kind == "linear":
            return x
        if self.kind == "srgb":
            return linear_to_srgb(x)
        return x ** (1.0 / self.gamma)

    def lut(self, dtype: Any) -> np.ndarray:
        """Look-up table code → linear value for an integer dtype.

        Returns
        -------
        (code_max + 1,) or (code_max + 1, 3) float32
        """
        dtype = np.dtype(dtype)
        if dtype not in _INT_DTYPES:
            raise InputError(
                f"response: no look-up table for dtype {dtype}; expected uint8 or uint16"
            )
        lut = self._luts.get(dtype)
        if lut is None:
            levels = int(np.iinfo(dtype).max) + 1
            if self.kind == "table":
                if self.table.shape[0] != levels:
                    raise InputError(
                        f"response table has {self.table.shape[0]} levels but the frames are "
                        f"{dtype} ({levels} levels)"
                    )
                lut = self.table.astype(np.float32)
            else:
                codes = np.arange(levels, dtype=np.float64) / (levels - 1)
                lut = self._decode(codes).astype(np.float32)
            lut.setflags(write=False)
            self._luts[dtype] = lut
        return lut

    def linearize(self, img: Any) -> np.ndarray:
        """See :func:`linearize`."""
        a = np.asarray(img)
        if a.dtype in _INT_DTYPES:
            lut = self.lut(a.dtype)
            if lut.ndim == 1:
                return lut[a]
            if a.ndim < 1 or a.shape[-1] != lut.shape[1]:
                raise InputError(
                    f"linearize: the response table has one curve per channel ({lut.shape[1]}), "
                    f"but the image has shape {a.shape}"
                )
            return np.stack([lut[a[..., k], k] for k in range(lut.shape[1])], axis=-1)
        if a.dtype.kind == "f":
            if self.kind != "linear":
                raise InputError(
                    f"linearize: {a.dtype} pixels are already linear; a float image cannot have "
                    f"response {fmt_value(self)} (declare response = \"linear\")"
                )
            return a.astype(np.float32, copy=False)
        raise InputError(f"linearize: expected uint8, uint16 or float pixels, got {a.dtype}")

    def encode(self, img_linear: Any, dtype: Any) -> np.ndarray:
        """See :func:`encode`."""
        dtype = np.dtype(dtype)
        x = as_array(img_linear, "img_linear", dtype=None)
        if x.dtype.kind not in "fiu":
            raise InputError(f"encode: expected numeric linear values, got {x.dtype}")
        if dtype.kind == "f":
            if self.kind != "linear":
                raise InputError(
                    f"encode: float output is linear by definition; cannot encode with {fmt_value(self)}"
                )
            return x.astype(dtype)
        if dtype not in _INT_DTYPES:
            raise InputError(f"encode: expected dtype uint8, uint16 or float, got {dtype}")
        code_max = int(np.iinfo(dtype).max)
        if self.kind == "srgb" and dtype == np.uint8 and x.dtype == np.float32:
            return _srgb8_from_float32(x)  # the same codes as the formula below, by table
        x = np.clip(x.astype(np.float64, copy=False), 0.0, 1.0)
        if self.kind != "table":
            return np.rint(self._encode(x) * code_max).astype(dtype)
        lut = self.lut(dtype).astype(np.float64)
        if lut.ndim == 1:
            return _nearest_code(lut, x).astype(dtype)
        if x.ndim < 1 or x.shape[-1] != lut.shape[1]:
            raise InputError(
                f"encode: the response table has one curve per channel ({lut.shape[1]}), "
                f"but the image has shape {x.shape}"
            )
        out = [_nearest_code(lut[:, k], x[..., k]) for k in range(lut.shape[1])]
        return np.stack(out, axis=-1).astype(dtype)


def _nearest_code(curve: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Index of the entry of a non-decreasing ``curve`` nearest to each ``x``."""
    hi = np.clip(np.searchsorted(curve, x, side="left"), 1, curve.size - 1)
    lo = hi - 1
    pick_lo = (x - curve[lo]) <= (curve[hi] - x)
    return np.where(pick_lo, lo, hi)


def _check_table(table: Any, name: str) -> np.ndarray:
    t = np.asarray(table)
    if t.dtype.kind not in "fiu":
        raise InputError(f"{name}: expected a numeric array, got dtype {t.dtype}")
    t = t.astype(np.float64)
    if not (t.ndim == 1 or (t.ndim == 2 and t.shape[1] == 3)) or t.shape[0] < 2:
        raise InputError(f"{name}: expected shape (levels,) or (levels, 3), got {t.shape}")
    if not np.isfinite(t).all() or (t < 0).any():
        raise InputError(f"{name}: values must be finite and >= 0 (linear exposure)")
    steps = np.diff(t, axis=0)
    if (steps < 0).any():
        first = int(np.argwhere(steps < 0)[0][0])
        raise InputError(
            f"{name}: must be non-decreasing (monotone) along the code axis; it decreases "
            f"between codes {first} and {first + 1}"
        )
    top = float(t.max())
    if top <= 0:
        raise InputError(f"{name}: all entries are zero")
    t = t / top
    t.setflags(write=False)
    return t


def load_response_table(path: str | os.PathLike, *, key: str | None = None) -> np.ndarray:
    """Load and check a Debevec–Malik response table (``.npy``).

    Returns
    -------
    (levels,) or (levels, 3) float64
        Linear exposure per code value, normalised to a maximum of 1.

    Raises
    ------
    ScanFormatError
        Missing or unreadable file, or a table that breaks the rules of :class:`Response`.
    """
    path = Path(path)
    if not path.is_file():
        raise ScanFormatError("response table file not found", path=path, key=key)
    try:
        t = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise ScanFormatError(
            f"cannot read response table (expected a .npy array: {exc})", path=path, key=key
        ) from exc
    try:
        return _check_table(t, "response table")
    except InputError as exc:
        raise ScanFormatError(str(exc), path=path, key=key) from exc


def parse_response(
    spec: Any,
    *,
    base_dir: str | os.PathLike | None = None,
    key: str = "response",
    path: str | os.PathLike | None = None,
) -> Response:
    """A :class:`Response` from its manifest value.

    Parameters
    ----------
    spec : str or dict or Response
        ``"linear"``, ``"srgb"``, ``{"kind": "gamma", "gamma": 2.2}`` or
        ``{"kind": "table", "file": "response.npy"}``. The tables ``{"kind": "linear"}`` and
        ``{"kind": "srgb"}`` are accepted too.
    base_dir : path-like, optional
        Directory the table's ``file`` is relative to (the scan root). The caller is
        responsible for checking the path stays inside it.
    key, path :
        Where the value came from, for error messages.

    Raises
    ------
    ScanFormatError
        An unknown kind, a missing or extra field, a bad gamma, or a bad table.
    """
    if isinstance(spec, Response):
        return spec
    kinds = ", ".join(repr(k) for k in RESPONSE_KINDS)
    if isinstance(spec, str):
        if spec in ("linear", "srgb"):
            return Response(spec)
        raise ScanFormatError(
            f"unknown response {fmt_value(spec)}; expected \"linear\", \"srgb\", "
            "{kind = \"gamma\", gamma = 2.2} or {kind = \"table\", file = \"response.npy\"}",
            path=path,
            key=key,
        )
    if not isinstance(spec, Mapping):
        raise ScanFormatError(
            f"response must be a string or a table, got {type(spec).__name__} {fmt_value(spec)}",
            path=path,
            key=key,
        )
    kind = spec.get("kind")
    allowed = {"linear": {"kind"}, "srgb": {"kind"}, "gamma": {"kind", "gamma"},
               "table": {"kind", "file"}}
    if kind not in allowed:
        raise ScanFormatError(
            f"unknown response kind {fmt_value(kind)}; expected one of {kinds}", path=path, key=f"{key}.kind"
        )
    extra = set(spec) - allowed[kind]
    if extra:
        raise ScanFormatError(
            f"unknown key(s) {sorted(extra)} for a {fmt_value(kind)} response; valid keys: "
            f"{sorted(allowed[kind])}",
            path=path,
            key=key,
        )
    missing = allowed[kind] - set(spec)
    if missing:
        raise ScanFormatError(
            f"a {fmt_value(kind)} response needs key(s) {sorted(missing)}", path=path, key=key
        )
    if kind == "gamma":
        try:
            return Response("gamma", gamma=spec["gamma"])
        except InputError as exc:
            raise ScanFormatError(str(exc), path=path, key=f"{key}.gamma") from exc
    if kind == "table":
        rel = spec["file"]
        if not isinstance(rel, str) or not rel:
            raise ScanFormatError(
                f"file must be a non-empty relative path, got {fmt_value(rel)}", path=path, key=f"{key}.file"
            )
        full = Path(base_dir or ".") / rel
        table = load_response_table(full, key=f"{key}.file")
        return Response("table", table=table, file=rel)
    return Response(kind)


def _as_response(response: Any) -> Response:
    return response if isinstance(response, Response) else parse_response(response)


def linearize(img: Any, response: Any) -> np.ndarray:
    """Linear float32 values from stored pixels.

    Parameters
    ----------
    img : (...) uint8, uint16 or float ndarray
        Stored pixels as returned by :func:`read_image`.
    response : Response or manifest value
        How the codes were encoded.

    Returns
    -------
    (...) float32
        For integer input, linear values in [0, 1] (code / code_max through the response; a
        table is a direct look-up). Float input is passed through as float32, and only with a
        ``"linear"`` response.

    Raises
    ------
    InputError
        Float input with a non-linear response, a table whose levels do not match the dtype,
        or an unsupported dtype.

    Notes
    -----
    The values say nothing about trust: mask saturated and black-clipped samples with
    :func:`saturated_mask` and :func:`clipped_mask` on the *stored* image.
    """
    return _as_response(response).linearize(img)


def encode(img_linear: Any, response: Any, dtype: Any) -> np.ndarray:
    """Stored pixels from linear values: the inverse of :func:`linearize`.

    Parameters
    ----------
    img_linear : (...) float ndarray, linear, finite
        Values outside [0, 1] are clipped for integer output.
    response : Response or manifest value
    dtype : uint8, uint16, float16 or float32
        Float output is allowed for ``"linear"`` only (a cast).

    Returns
    -------
    (...) ndarray of ``dtype``

    Notes
    -----
    Analytic responses round in the encoded domain, so
    ``|linearize(encode(x)) - x| <= max(f(c + ½) - f(c), f(c) - f(c - ½))`` with
    ``c = encode(x)`` in code units and ``f`` the decoding curve: half an LSB times the local
    slope of the curve. A table picks the nearest tabulated value, so the error is at most
    half the gap between neighbouring table entries.
    """
    return _as_response(response).encode(img_linear, dtype)


# --------------------------------------------------------------------------- masks


def _channel_any(mask: np.ndarray, img: np.ndarray) -> np.ndarray:
    return mask.any(axis=-1) if img.ndim == 3 else mask


def saturated_mask(img_raw: Any, *, max_value: float | None = None) -> np.ndarray:
    """Pixels where any channel is saturated (at the top of the stored range).

    Parameters
    ----------
    img_raw : (H, W, C) or (H, W) ndarray, as stored (before linearisation)
    max_value : float, optional
        Saturation level. Default: the dtype's maximum for integer images (255, 65535); for
        float images there is no intrinsic level and, without ``max_value``, only non-finite
        values count as saturated.

    Returns
    -------
    (H, W) bool
        True where the sample must not be trusted.
    """
    a = np.asarray(img_raw)
    if a.dtype.kind in "ui":
        top = np.iinfo(a.dtype).max if max_value is None else max_value
        m = a >= top
    elif a.dtype.kind == "f":
        m = ~np.isfinite(a)
        if max_value is not None:
            m |= a >= max_value
    else:
        raise InputError(f"saturated_mask: expected integer or float pixels, got {a.dtype}")
    return _channel_any(m, a)


def clipped_mask(img_raw: Any, low: float = 0) -> np.ndarray:
    """Pixels where any channel is black-clipped (at or below ``low``).

    Parameters
    ----------
    img_raw : (H, W, C) or (H, W) ndarray, as stored
    low : number
        Clipping level in stored units (default 0). Non-finite float values count as clipped.

    Returns
    -------
    (H, W) bool
    """
    a = np.asarray(img_raw)
    if a.dtype.kind not in "uif":
        raise InputError(f"clipped_mask: expected integer or float pixels, got {a.dtype}")
    m = a <= low
    if a.dtype.kind == "f":
        m |= ~np.isfinite(a)
    return _channel_any(m, a)
