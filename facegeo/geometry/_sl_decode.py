"""Gray-code and phase-shift decoding of whole frame sets (the foundation's decoders).

Private implementation of :func:`facegeo.geometry.structured_light.decode_gray`,
:func:`~facegeo.geometry.structured_light.decode_phase` and
:func:`~facegeo.geometry.structured_light.unwrap_with_gray` (re-exported there; conventions in
that module's docstring). The streaming decoder is :mod:`facegeo.geometry._sl_stream`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from facegeo.checks import as_array, check_choice, fmt_value
from facegeo.errors import InputError, ShapeError
from facegeo.geometry._sl_patterns import (
    _AXES,
    _CHUNK_PIXELS,
    PatternSpec,
    _check_spec,
    _pattern_table,
)

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- frames


def _validated_frames(frames: Any, needed: list[str], what: str) -> dict[str, np.ndarray]:
    """Check presence, dtype and equal shapes of ``frames[name]`` for ``needed`` names."""
    if not isinstance(frames, Mapping):
        raise InputError(f"frames: expected a mapping name -> image, got {type(frames).__name__}")
    missing = [n for n in needed if n not in frames]
    if missing:
        have = sorted(map(str, frames))
        raise InputError(
            f"frames: missing {len(missing)} frame(s) needed for {what}: {missing}; "
            f"frames given: {have if len(have) <= 12 else have[:12] + ['...']}"
        )
    out: dict[str, np.ndarray] = {}
    shape0 = name0 = None
    for n in needed:
        a = np.asarray(frames[n])
        if a.dtype.kind not in "fiu":
            raise ShapeError(f"frames[{fmt_value(n)}]: expected real numbers, got dtype {a.dtype}")
        if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] < 1):
            raise ShapeError(f"frames[{fmt_value(n)}]: expected shape (H, W) or (H, W, C), got {a.shape}")
        if shape0 is None:
            shape0, name0 = a.shape, n
        elif a.shape != shape0:
            raise ShapeError(
                f"frames[{fmt_value(n)}]: shape {a.shape} differs from frames[{fmt_value(name0)}] {shape0}; "
                "all frames of one capture must have the same shape"
            )
        out[n] = a
    return out


def _full_scale(a: np.ndarray, full_scale: float | None) -> float:
    """The value that means "full white" for frame ``a``: dtype max for integers, else 1."""
    if full_scale is not None:
        return full_scale
    if a.dtype.kind in "iu":
        return float(np.iinfo(a.dtype).max)
    return 1.0


def _check_full_scale(full_scale) -> float | None:
    if full_scale is None:
        return None
    v = float(as_array(full_scale, "full_scale", shape=()))
    if not v > 0:
        raise InputError(f"full_scale: expected a number > 0 (the frames' white level), got {v}")
    return v


def _load_chunk(a: np.ndarray, name: str, rows: slice, full_scale: float | None = None
                ) -> np.ndarray:
    """Rows of one frame as float32 (H', W) in fractions of full scale, channel mean for colour
    frames (see the module docstring: integer frames divide by their dtype's maximum)."""
    c = a[rows]
    if c.ndim == 3:
        c = c.mean(axis=2, dtype=np.float32) if c.shape[2] > 1 else c[..., 0]
    c = np.asarray(c, dtype=np.float32)
    scale = _full_scale(a, full_scale)
    if scale != 1.0:
        c = c / np.float32(scale)
    return c


def _raise_if_nonfinite(a: np.ndarray, name: str, rows: slice) -> None:
    """Raise :class:`InputError` naming the frame and the first NaN / inf in ``a[rows]``."""
    if a.dtype.kind != "f":
        return
    ok = np.isfinite(a[rows])
    if not ok.all():
        idx = np.argwhere(~ok)[0]
        raise InputError(
            f"frames[{fmt_value(name)}]: non-finite value (NaN or inf) at row "
            f"{int(idx[0]) + (rows.start or 0)}, column {int(idx[1])}"
        )


def _check_chunk_finite(arrs: Mapping[str, np.ndarray], names: list[str], rows: slice) -> None:
    for n in names:
        _raise_if_nonfinite(arrs[n], n, rows)


# --------------------------------------------------------------------------- Gray decoding


@dataclass(frozen=True, eq=False)
class GrayDecode:
    """Result of :func:`decode_gray`: per camera pixel, the projector pixel it sees.

    Attributes
    ----------
    proj_x : (H, W) float64, projector pixels (column)
        Integer column index (or stripe centre for coarse codes); NaN where not ``valid``.
        All NaN when the spec has no column bits.
    proj_y : (H, W) float64, projector pixels (row)
        Same for rows.
    valid : (H, W) bool
        Not shadow, contrast >= ``min_contrast`` and every decoded code inside the projector.
    contrast : (H, W) float32, fraction of full scale
        Confidence: the smallest ``|frame - inverse|`` over all bits (``2 |frame - threshold|``
        without inverse frames), i.e. the weakest bit decision's margin.
    shadow : (H, W) bool
        The projector does not light the pixel: ``white - black < shadow_threshold`` (without
        white/black frames, the largest bit amplitude over the Gray frames is below it).
    """

    proj_x: np.ndarray
    proj_y: np.ndarray
    valid: np.ndarray
    contrast: np.ndarray
    shadow: np.ndarray

    @property
    def q_proj(self) -> np.ndarray:
        """(H, W, 2) float64 projector pixel coordinates (x, y), NaN where invalid."""
        return np.stack([self.proj_x, self.proj_y], axis=-1)


def decode_gray(
    frames: Mapping[str, Any],
    spec: PatternSpec,
    *,
    min_contrast: float = 0.01,
    shadow_threshold: float = 0.02,
    threshold: float | None = None,
    full_scale: float | None = None,
) -> GrayDecode:
    """Decode Gray-code frames into projector column / row per camera pixel (vectorised).

    Bit decision per pixel and bit:

    * with inverse frames: ``frame > inverse``;
    * else with white/black frames: ``frame > (white + black) / 2``;
    * else ``frame > threshold`` if given, otherwise ``frame > (max + min) / 2`` of that pixel
      over all Gray frames (both axes) — enough codes mix 0 and 1 bits for this to work except
      at the all-zero corner codes, which are usually outside the lit area.

    Gray bits (MSB first) are turned into binary by the running XOR ``b_i = b_{i-1} ^ g_i``.
    Frames are processed in row chunks so each is read from memory once.

    Parameters
    ----------
    frames : mapping str -> (H, W) or (H, W, C) array, linear intensity
        Keys as :func:`pattern_names`; the Gray frames (and inverses, white, black as the spec
        says) must be present; phase or extra frames are ignored.
    spec : PatternSpec
    min_contrast : float, fraction of full scale
        Pixels whose weakest bit margin (see :class:`GrayDecode`) is below this are invalid.
    shadow_threshold : float, fraction of full scale
        Pixels lit by less than this (white - black) are shadow.
    threshold : float, optional, fraction of full scale
        Fixed bit threshold; only for specs without inverse frames.
    full_scale : float, optional, frame units
        The frames' white level; default the dtype's maximum for integer frames, 1 for float
        frames (module docstring). Thresholds are relative to it for every dtype.

    Returns
    -------
    GrayDecode

    Raises
    ------
    InputError
        Missing frames (listed), NaN / inf in a frame (named, with its position), a spec
        without Gray bits, bad thresholds.
    ShapeError
        Frames of different shapes or of a non-image shape.
    """
    spec = _check_spec(spec)
    full_scale = _check_full_scale(full_scale)
    min_contrast = float(as_array(min_contrast, "min_contrast", shape=()))
    shadow_threshold = float(as_array(shadow_threshold, "shadow_threshold", shape=()))
    if threshold is not None:
        threshold = float(as_array(threshold, "threshold", shape=()))
        if spec.inverse:
            raise InputError(
                "threshold: the spec has inverse frames (bit = frame > inverse); a fixed "
                "threshold applies only to specs with inverse=False"
            )
    axes = [(a, spec.n_bits(a)) for a in _AXES if spec.n_bits(a) > 0]
    if not axes or "gray" not in spec.codes:
        raise InputError("spec: has no Gray-code patterns to decode (gray=False, 0 bits or no "
                         "'gray' in codes; decode_stream decodes the other code families)")
    table = _pattern_table(spec)
    needed = [n for n, p in table.items()
              if p.kind in ("white", "black") or (p.kind == "gray" and p.code == "gray")]
    arrs = _validated_frames(frames, needed, "Gray decoding")
    H, W = arrs[needed[0]].shape[:2]

    proj = {a: np.full((H, W), np.nan) if not spec.n_bits(a) else np.empty((H, W)) for a in _AXES}
    valid = np.empty((H, W), dtype=bool)
    contrast = np.empty((H, W), dtype=np.float32)
    shadow = np.empty((H, W), dtype=bool)
    use_minmax = not spec.inverse and not spec.white_black and threshold is None
    rows_per_chunk = max(1, _CHUNK_PIXELS // max(W, 1))

    gray_names = [n for n, p in table.items() if p.kind == "gray" and p.code == "gray"]
    for r0 in range(0, H, rows_per_chunk):
        rows = slice(r0, min(H, r0 + rows_per_chunk))
        h = rows.stop - r0
        cache: dict[str, np.ndarray] = {}

        def load(name: str, rows: slice = rows, cache: dict = cache) -> np.ndarray:
            c = cache.get(name)
            return _load_chunk(arrs[name], name, rows, full_scale) if c is None else c

        # Reference level for the bit decision without inverse frames; shadow from white/black.
        ref: np.ndarray | float | None = None
        shadow_c = None
        if spec.white_black:
            wc, bc = load("white"), load("black")
            lit = wc - bc
            if not np.isfinite(lit).all():
                _check_chunk_finite(arrs, ["white", "black"], rows)
            shadow_c = ~(lit >= shadow_threshold)
            if not spec.inverse:
                ref = 0.5 * (wc + bc) if threshold is None else threshold
        elif not spec.inverse:
            if use_minmax:
                for n in gray_names:
                    cache[n] = _load_chunk(arrs[n], n, rows, full_scale)
                hi = cache[gray_names[0]].copy()
                lo = hi.copy()
                for n in gray_names[1:]:
                    np.maximum(hi, cache[n], out=hi)
                    np.minimum(lo, cache[n], out=lo)
                span = hi - lo
                if not np.isfinite(span).all():
                    _check_chunk_finite(arrs, gray_names, rows)
                shadow_c = ~(span >= shadow_threshold)
                ref = 0.5 * (hi + lo)
            else:
                ref = threshold

        # Per bit: d = frame - reference; bit = d > 0; binary b_i = b_{i-1} ^ g_i appended to
        # the code; |d| folded into the running min (contrast) and max (amplitude; its
        # finiteness also proves every Gray frame finite, NaN and inf both propagate).
        d = np.empty((h, W), dtype=np.float32)
        g = np.empty((h, W), dtype=bool)
        cmin = np.full((h, W), np.inf, dtype=np.float32)
        amax = np.zeros((h, W), dtype=np.float32)
        ok = np.ones((h, W), dtype=bool)
        codes = {}
        for axis, n in axes:
            # The binary code is built in uint8 bytes, MSB byte first (same-dtype ufuncs avoid
            # numpy's slow casting loops), then assembled into one integer per pixel.
            n_bytes = -(-n // 8)
            pad = 8 * n_bytes - n
            code_bytes = np.zeros((n_bytes, h, W), dtype=np.uint8)
            b = np.zeros((h, W), dtype=bool)
            b8 = b.view(np.uint8)
            for i in range(n):
                name = f"gray_{axis}_{i:02d}"
                other = load(name + "_inv") if spec.inverse else ref
                np.subtract(load(name), other, out=d)
                np.greater(d, 0.0, out=g)
                np.bitwise_xor(b, g, out=b)
                byte = code_bytes[(i + pad) // 8]
                np.add(byte, byte, out=byte)
                np.bitwise_or(byte, b8, out=byte)
                np.abs(d, out=d)
                np.minimum(cmin, d, out=cmin)
                np.maximum(amax, d, out=amax)
            code = code_bytes[0].astype(np.uint32 if n > 16 else np.uint16)
            for k in range(1, n_bytes):
                code <<= 8
                code |= code_bytes[k]
            s = spec.stripe_shift(axis)
            size = spec.width if axis == "x" else spec.height
            ok &= code < -(-size // (1 << s))  # only stripes that exist on the projector
            codes[axis] = code
        if not np.isfinite(amax).all():
            # Raises naming the frame; finite frames whose difference overflowed pass on.
            _check_chunk_finite(arrs, [n for n in needed if n not in ("white", "black")], rows)
        if not spec.inverse:
            cmin *= 2.0
            amax *= 2.0
        if shadow_c is None:
            shadow_c = ~(amax >= shadow_threshold)
        ok &= ~shadow_c
        ok &= cmin >= min_contrast
        bad = ~ok
        for axis, code in codes.items():
            step = float(1 << spec.stripe_shift(axis))
            out = proj[axis][rows]
            np.copyto(out, code)
            if step != 1.0:
                out *= step
                out += 0.5 * (step - 1.0)
            np.copyto(out, np.nan, where=bad)
        valid[rows] = ok
        contrast[rows] = cmin
        shadow[rows] = shadow_c

    log.debug(
        "decode_gray: %dx%d px, %d frames, %.1f %% valid",
        W, H, len(needed), 100.0 * valid.mean() if valid.size else 0.0,
    )
    return GrayDecode(proj["x"], proj["y"], valid, contrast, shadow)


# --------------------------------------------------------------------------- phase shift


class PhaseDecode(NamedTuple):
    """Result of :func:`decode_phase` (unpacks as ``phase, modulation = ...``).

    Attributes
    ----------
    phase : (H, W) float64, radians in [0, 2 pi)
        Wrapped phase ``phi mod 2 pi``; NaN where ``modulation <= min_modulation``.
    modulation : (H, W) float32, fraction of full scale
        Fringe amplitude ``B`` in ``I_k = A + B cos(phi - 2 pi k / N)``.
    """

    phase: np.ndarray
    modulation: np.ndarray


def decode_phase(
    frames: Mapping[str, Any],
    spec: PatternSpec,
    axis: str = "x",
    *,
    min_modulation: float = 0.0,
    full_scale: float | None = None,
) -> PhaseDecode:
    """Wrapped phase and modulation from N-step phase-shift frames (least squares, N >= 3).

    With ``delta_k = 2 pi k / N``, ``S = sum_k I_k sin(delta_k)``, ``C = sum_k I_k cos(delta_k)``:
    ``phi = atan2(S, C) mod 2 pi`` and ``B = (2 / N) sqrt(S^2 + C^2)`` (Srinivasan et al. 1984).

    Parameters
    ----------
    frames : mapping str -> (H, W) or (H, W, C) array, linear intensity
        Must hold ``"phase_{axis}_0" ... "phase_{axis}_{N-1}"``.
    spec : PatternSpec
        ``phase_steps`` > 0 and ``axis`` in ``phase_axes``.
    axis : {"x", "y"}
    min_modulation : float, fraction of full scale
        Phase is NaN where the modulation is at or below this (default: only where it is 0,
        where the phase is undefined).
    full_scale : float, optional, frame units
        The frames' white level (default: dtype maximum for integers, 1 for floats).

    Returns
    -------
    PhaseDecode
        ``(phase, modulation)``.
    """
    spec = _check_spec(spec)
    check_choice(axis, "axis", _AXES)
    full_scale = _check_full_scale(full_scale)
    min_modulation = float(as_array(min_modulation, "min_modulation", shape=()))
    if not spec.phase_steps or axis not in spec.phase_axes:
        raise InputError(
            f"spec: has no phase-shift patterns on axis {fmt_value(axis)} "
            f"(phase_steps={spec.phase_steps}, phase_axes={list(spec.phase_axes)})"
        )
    N = spec.phase_steps
    names = [f"phase_{axis}_{k}" for k in range(N)]
    arrs = _validated_frames(frames, names, f"{N}-step phase decoding on {axis}")
    H, W = arrs[names[0]].shape[:2]
    S = np.zeros((H, W), dtype=np.float64)
    C = np.zeros((H, W), dtype=np.float64)
    for k, n in enumerate(names):
        _raise_if_nonfinite(arrs[n], n, slice(0, H))
        f = _load_chunk(arrs[n], n, slice(0, H), full_scale)
        dk = 2.0 * np.pi * k / N
        S += math.sin(dk) * f
        C += math.cos(dk) * f
    phase = np.mod(np.arctan2(S, C), 2.0 * np.pi)
    phase[phase >= 2.0 * np.pi] = 0.0  # mod of -0.0 rounding
    modulation = ((2.0 / N) * np.hypot(S, C)).astype(np.float32)
    phase[~(modulation > min_modulation)] = np.nan
    return PhaseDecode(phase, modulation)


def unwrap_with_gray(wrapped, coarse_proj, spec: PatternSpec, *, axis: str = "x") -> np.ndarray:
    """Sub-pixel projector coordinates from wrapped phase and a Gray-code decode.

    The phase predicted by the coarse coordinate, ``phi_c = 2 pi P (x_c + 0.5) / size``, picks
    the period: ``m = round((phi_c - phi) / 2 pi)``, ``x = (phi + 2 pi m) size / (2 pi P) - 0.5``.
    Correct whenever the coarse coordinate is off by less than half a period
    (``size / (2 P)`` pixels).

    Parameters
    ----------
    wrapped : (H, W) float, radians
        From :func:`decode_phase`; NaN allowed.
    coarse_proj : (H, W) float, projector pixels
        ``GrayDecode.proj_x`` (or ``proj_y`` for ``axis="y"``); NaN allowed.
    spec : PatternSpec
    axis : {"x", "y"}

    Returns
    -------
    (H, W) float64, projector pixels
        NaN where either input is NaN.
    """
    spec = _check_spec(spec)
    check_choice(axis, "axis", _AXES)
    P = spec.phase_periods(axis)
    if not spec.phase_steps or P is None:
        raise InputError(f"spec: has no phase-shift patterns on axis {fmt_value(axis)}")
    phi = as_array(wrapped, "wrapped", finite=False)
    xc = as_array(coarse_proj, "coarse_proj", shape=phi.shape, finite=False)
    if np.isinf(phi).any() or np.isinf(xc).any():
        raise InputError("wrapped / coarse_proj: inf values (use NaN for missing pixels)")
    size = spec.width if axis == "x" else spec.height
    k = 2.0 * np.pi * P / size  # radians per projector pixel
    m = np.round((k * (xc + 0.5) - phi) / (2.0 * np.pi))
    return (phi + 2.0 * np.pi * m) / k - 0.5
