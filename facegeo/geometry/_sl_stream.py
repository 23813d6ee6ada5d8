"""Streaming structured-light decoder: one pass over ``(name, frame)``, per-pixel accumulators.

Private implementation of :func:`facegeo.geometry.structured_light.decode_stream` (read that
docstring first; the method is written down in ``docs/structured-light.md``).

Speed: the per-frame updates are compiled kernels (``_sl_kernels``: an 8-bit pair or phase
frame is read once, no float32 luminance plane), and so is the per-pixel part of
:meth:`StreamDecoder.finish` (``_sl_finish``; the numpy reference stays, ``KERNELS = False``).
Frames the caller already holds (``decode_frames`` given a mapping, list or tuple) are not
folded one by one: their 8-bit / 16-bit pairs wait in one group (references, no copies) that
:meth:`StreamDecoder.finish` folds chunk by chunk, each chunk's pairs tile-major
(:class:`_sl_kernels.PairGroup`; 8-bit RGB through the vector block of ``_sl_vec``) into
chunk-sized words and margins just before the chunk is finished, so the full-size words and
margin planes are never written. A stream (a
generator) is folded frame by frame: buffering its frames for a group needs copies (the
caller may reuse a frame's buffer), and copied groups measured no faster than frame by frame
(``STREAM_GROUP_BYTES = 0``; ``docs/structured-light.md``). The finish runs its chunks on
``threads`` Python threads (default 1).

Memory, for ``P`` camera pixels and ``n`` stored bit planes (all code families and axes):

* with inverse frames, streamed: one uint8 margin per bit plane and pixel (``|pattern -
  inverse|`` in steps of 1/510 of full scale, saturating at 0.5) and the bit decisions packed
  into one integer word per pixel, family and axis; at most one frame waits for its partner (as
  its exact integer channel sum for 8-bit / 16-bit frames: 2 / 4 bytes a pixel, else float32
  luminance); held: the same for one chunk of pixels per thread only;
* without inverse frames (the bit threshold comes from the data): the frames themselves as
  float16 (2 bytes per plane and pixel), since the per-pixel threshold is known only at the end;
* float32 per pixel: white, black, the running max / min over the binary frames (Nayar et al.
  2006 direct / global split), and three phase sums per phase axis;
* the outputs (float32 ``x, y, sigma_x, sigma_y, confidence``; ``direct``, ``global_`` and
  ``lit`` are written over the accumulators they come from).

A 42-frame 4896 × 3264 RGB set (white, black, 10 + 10 bits with inverses) peaks at 1.24 GB
(measured, tests/test_decode.py), not
the 8.5 GB of holding every frame as float32 RGB.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from facegeo.checks import as_array, fmt_value
from facegeo.errors import InputError, ShapeError
from facegeo.fsutil import aligned_empty
from facegeo.geometry import _sl_kernels as _kern
from facegeo.geometry._sl_codes import base_plane, stripe_table

log = logging.getLogger(__name__)

_AXES = ("x", "y")
_MARGIN_STEPS = 510.0  # uint8 margin quantisation: 1/510 of full scale, saturating at 0.5
#: Pixels per chunk when finishing (a thread's unit of work). 131,072: on the chunk-by-chunk
#: Python path the benchmark's held 1280 × 1024 frames decoded in 14.8 ms at one thread against
#: 15.6 / 17.0 / 19.2 ms with chunks of 65,536 / 32,768 / 16,384 (the per-chunk calls' fixed
#: costs; measured with ``_CHUNK`` set before ``decode_frames`` on ``facegeo bench
#: structured_light.decode_stream``'s frames). The fused kernel (:data:`FUSED`) works through a
#: chunk in sub-runs of :data:`_FUSED_SUB` pixels.
_CHUNK = 1 << 17
#: Byte budget of a group of streamed (not held) 8-bit / 16-bit pair frames copied for the
#: tile-major kernel (``StreamDecoder.group_bytes``); 0: frame by frame.
STREAM_GROUP_BYTES = 0
#: Decode the bits in the compiled per-pixel kernel (``_sl_finish``); False: the numpy
#: reference (``_bit_words`` / ``_decode_axis`` / ``_partial_codes``), used by the tests.
KERNELS = True
#: Held 8-bit RGB frames without phase frames fold and finish in one compiled call a chunk
#: (``_sl_finish.fused_chunk``), :data:`_FUSED_SUB` pixels at a time; False: the chunk-by-chunk
#: Python path (the same values; tests compare them).
FUSED = True
#: Sub-run of the fused kernel: its buffers (words, margins, L_max / L_min, thresholds) stay
#: in cache. The bench's decode, 1 thread, interleaved in one process (30 rounds, best): 8,192 /
#: 16,384 / 32,768 / 65,536 / 131,072 pixels 10.7 / 10.1 / 9.5 / 9.5 / 10.2 ms.
_FUSED_SUB = 32768
#: Alignment (bytes) of the output planes the fused kernel writes: its block loop stores the
#: ones it does not read back non-temporally, which needs each vector aligned (``fused_chunk``).
_ALIGN = 64


@dataclass(frozen=True, eq=False)
class StreamDecode:
    """Result of :func:`~facegeo.geometry.structured_light.decode_stream`.

    Attributes
    ----------
    x, y : (H, W) float32, projector pixels (pixel-centre convention)
        Projector column / row seen by each camera pixel; NaN where not valid on that axis (``y``
        all NaN when the patterns code no rows).
    valid_x, valid_y : (H, W) bool
        The axis has a coordinate (False everywhere for an axis the patterns do not code).
    valid : (H, W) bool
        Valid on every axis the patterns code (Gray / XOR bits, or phase with bits to unwrap).
    confidence : (H, W) float32 in [0, 1]
        Weakest needed evidence relative to the pixel's direct light: the smallest margin of the
        bits the coordinate uses over ``direct`` (Gray only) or the fringe contrast ``2 B /
        direct`` (phase), times the fraction of code families that agree; 0 where invalid.
    sigma_x, sigma_y : (H, W) float32, projector pixels
        Estimated 1-σ coordinate noise: ``w / sqrt(12)`` for a code naming a ``w``-pixel block,
        the propagated intensity noise for phase; NaN where invalid.
    direct, global_ : (H, W) float32, fraction of full scale
        Nayar et al. 2006 split from the binary frames, ``L_d = L_max - L_min``,
        ``L_g = 2 L_min`` (Sec. 3, half the projector lit); NaN without binary frames.
    lit : (H, W) float32, fraction of full scale
        The reference for the relative thresholds: ``white - black`` with those frames, else
        ``direct`` (else the phase offset ``2 A``).
    shadow : (H, W) bool
        ``lit < shadow_threshold``.
    wrapped : dict axis -> (H, W) float32, radians in [0, 2 pi)
        Wrapped phase per phase axis (NaN at zero modulation).
    modulation : dict axis -> (H, W) float32, fraction of full scale
        Fringe amplitude ``B`` per phase axis.
    bits : dict
        Per axis and family, per bit (MSB first): ``"unresolved"`` (lit pixels whose decision
        on that bit is not reliable) and ``"lost"`` (lit pixels invalid on that axis because
        that bit is the first one they could not resolve); per axis ``"votes_disagree"`` (lit
        pixels whose families resolved but did not agree).
    """

    x: np.ndarray
    y: np.ndarray
    valid_x: np.ndarray
    valid_y: np.ndarray
    valid: np.ndarray
    confidence: np.ndarray
    sigma_x: np.ndarray
    sigma_y: np.ndarray
    direct: np.ndarray
    global_: np.ndarray
    lit: np.ndarray
    shadow: np.ndarray
    wrapped: dict = field(default_factory=dict)
    modulation: dict = field(default_factory=dict)
    bits: dict = field(default_factory=dict)


def _check_frame(frame: Any, name: str, shape) -> np.ndarray:
    """Frame as an (H, W) or (H, W, C) real array, validated (size against ``shape``)."""
    a = np.asarray(frame)
    if a.dtype.kind not in "fiu":
        raise ShapeError(f"frames[{fmt_value(name)}]: expected real numbers, got dtype {a.dtype}")
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] < 1):
        raise ShapeError(f"frames[{fmt_value(name)}]: expected shape (H, W) or (H, W, C), "
                         f"got {a.shape}")
    if shape is not None and a.shape[:2] != shape:
        raise ShapeError(f"frames[{fmt_value(name)}]: size {a.shape[1]}x{a.shape[0]} (W x H) "
                         f"differs from the first frame's {shape[1]}x{shape[0]}; all frames of "
                         "one capture must have the same size")
    return a


def _lum_scale(a: np.ndarray, full_scale: float | None) -> float:
    """Luminance = channel sum times this: ``1 / (C · full scale)``."""
    if full_scale is None:
        full_scale = float(_kern.int_max(a.dtype)) if a.dtype.kind in "iu" else 1.0
    C = a.shape[2] if a.ndim == 3 else 1
    return 1.0 / (full_scale * C)


def _luminance(frame: Any, name: str, shape, full_scale: float | None) -> np.ndarray:
    """Frame as float32 (H, W) in fractions of full scale (channel mean), validated."""
    a = _check_frame(frame, name, shape)
    lum = _kern.luminance(a, _lum_scale(a, full_scale))  # one compiled pass
    if a.dtype.kind == "f" and not np.isfinite(lum).all():
        idx = np.argwhere(~np.isfinite(lum))[0]
        raise InputError(f"frames[{fmt_value(name)}]: non-finite value (NaN or inf) at row "
                         f"{int(idx[0])}, column {int(idx[1])}")
    return lum


def _check_threads(threads) -> int:
    """``threads`` as an int in 1 … ``NUMBA_NUM_THREADS``, else :class:`InputError`."""
    import numba

    top = numba.config.NUMBA_NUM_THREADS
    try:
        t = int(threads)
    except (TypeError, ValueError):
        t = 0
    if t != threads or not 1 <= t <= top:
        raise InputError(f"threads: expected an integer from 1 to {top} (NUMBA_NUM_THREADS), "
                         f"got {fmt_value(threads)}")
    return t


def _add_bits(total: dict, part: dict) -> None:
    """Add one chunk's per-bit statistics (``StreamDecode.bits`` layout) into ``total``."""
    for a, ax in part.items():
        for c, d in ax.items():
            if isinstance(d, dict):
                for k, v in d.items():
                    tk = total[a][c][k]
                    for i, x in enumerate(v):
                        tk[i] += x
            else:
                total[a][c] += d


def _word_dtype(n: int):
    return np.uint8 if n <= 8 else np.uint16 if n <= 16 else np.uint32


class StreamDecoder:
    """Accumulate structured-light frames one at a time; :meth:`finish` decodes.

    Parameters
    ----------
    spec : PatternSpec
    full_scale : float, optional
        The frames' white level (default: dtype maximum for integer frames, 1 for floats).
    """

    def __init__(self, spec, *, full_scale: float | None = None, group_bytes: float = 0,
                 copy_group: bool = True, threads: int = 1):
        from facegeo.geometry._sl_decode import _check_full_scale
        from facegeo.geometry._sl_patterns import _pattern_table

        self.spec = spec
        self.full_scale = _check_full_scale(full_scale)
        self.table = _pattern_table(spec)
        self.seen: set[str] = set()
        self.shape: tuple[int, int] | None = None
        # binary planes: (code, axis, bit) -> storage index
        self.planes = [(p.code, p.axis, p.index) for p in self.table.values()
                       if p.kind == "gray" and not p.inverse]
        self.plane_index = {k: i for i, k in enumerate(self.planes)}
        self.families = [(c, a) for c in spec.codes for a in _AXES if spec.n_bits(a)]
        self.pending: dict[tuple, tuple[bool, np.ndarray, float]] = {}
        self.finished = False
        # tile-major groups of 8-bit / 16-bit pair frames (see add): [(key, inverse, frame,
        # scale)], their bytes, the byte budget and whether buffered frames are copies
        self.group: list[tuple[tuple, bool, np.ndarray, float]] = []
        self.group_nbytes = 0
        self.group_bytes = float(group_bytes)
        self.copy_group = bool(copy_group)
        # every frame is held by the caller until finish (decode_frames with a mapping, list or
        # tuple): pairs wait uncopied in one group, a white / black frame is kept as it is
        self.holds_frames = math.isinf(self.group_bytes) and not self.copy_group
        self.threads = _check_threads(threads)
        self.folded = False  # a pair frame went into the full-size accumulators

    # ---------------------------------------------------------------- accumulation

    def _allocate(self, shape) -> None:
        H, W = shape
        self.shape = (H, W)
        spec = self.spec
        n = len(self.planes)
        # with inverse frames the full-size margins and decision words are made, and L_max /
        # L_min set to -inf / inf, when the first pair is folded into them (_start_fold): a
        # decode that folds and finishes chunk by chunk (finish) has no such planes, and
        # writes L_max / L_min (the direct / global outputs) chunk by chunk
        self.margin = self.sign_words = self.signs = None
        if not spec.inverse:
            self.values = np.zeros((n, H, W), np.float16)
        if n and spec.inverse:  # (aligned: the fused chunk kernel's non-temporal stores)
            self.lmax, self.lmin = (aligned_empty((H, W), np.float32, _ALIGN) for _ in range(2))
        else:
            self.lmax = np.full((H, W), -np.inf, np.float32) if n else None
            self.lmin = np.full((H, W), np.inf, np.float32) if n else None
        self.fold_started = not (n and spec.inverse)
        self.white = self.black = None
        self.raw_wb = {}  # kind -> (held 8-bit RGB frame, luminance scale): see add
        N = spec.phase_steps
        self.phase_max = np.zeros((H, W), np.float32) if N else None
        self.phase = {a: [np.zeros((H, W), np.float32) for _ in range(3)]
                      for a in (spec.phase_axes if N else ())}

    def add(self, name: str, frame) -> None:
        """Fold frame ``name`` (one of ``pattern_names(spec)``) into the accumulators.

        Raises
        ------
        InputError
            Unknown or repeated frame name; NaN / inf in a float frame.
        ShapeError
            A frame whose size differs from the first one's, or not an image.
        """
        if self.finished:
            raise InputError("StreamDecoder.add: the decoder is finished; start a new one")
        p = self.table.get(name) if isinstance(name, str) else None
        if p is None:
            names = list(self.table)
            shown = ", ".join(names[:8]) + (f", ... ({len(names)} in all)" if len(names) > 8 else "")
            raise InputError(f"frames: unknown frame name {fmt_value(name)} for this pattern "
                             f"set; expected one of {shown}")
        if name in self.seen:
            raise InputError(f"frames: frame {fmt_value(name)} given twice")
        a = _check_frame(frame, name, self.shape)
        scale = _lum_scale(a, self.full_scale)
        # uint8 / uint16 frames of a pair or a phase sequence: read once by a fused kernel, no
        # float32 luminance plane (_sl_kernels); other frames: their luminance first
        fused = (_kern.sum_dtype(a.dtype, a.shape[2] if a.ndim == 3 else 1) is not None
                 and (p.kind == "phase" or (p.kind == "gray" and self.spec.inverse)))
        # a held 8-bit RGB white / black frame is kept as it is: the fused chunk kernel sums
        # its channels where it needs them (no float32 plane); others, or if that kernel does
        # not run, get their luminance (_wb_luminance)
        raw = (p.kind in ("white", "black") and self.holds_frames and a.dtype == np.uint8
               and a.ndim == 3 and a.shape[2] == 3 and a.flags.c_contiguous)
        if not fused and not raw:
            lum = _luminance(a, name, None, self.full_scale)
            a, scale = lum, 1.0
        if self.shape is None:
            self._allocate(a.shape[:2])
        self.seen.add(name)
        if raw:
            self.raw_wb[p.kind] = (a, scale)
        elif p.kind == "white":
            self.white = lum
        elif p.kind == "black":
            self.black = lum
        elif p.kind == "phase":
            N = self.spec.phase_steps
            dk = 2.0 * math.pi * p.index / N
            S, C, A = self.phase[p.axis]
            _kern.phase_update(a, scale, math.sin(dk), math.cos(dk), S, C, A, self.phase_max)
        else:
            k = self.plane_index[(p.code, p.axis, p.index)]
            if not self.spec.inverse:
                np.maximum(self.lmax, lum, out=self.lmax)
                np.minimum(self.lmin, lum, out=self.lmin)
                self.values[k] = lum
                return
            key = (p.code, p.axis, p.index)
            # a held frame that is not C-contiguous (a channel-reversed view) would be copied
            # whole for the tile kernel: it takes the frame-by-frame path instead
            if fused and self.group_bytes > 0 and key not in self.pending and _kern.tiled_ok(
                    a.dtype, a.shape[2] if a.ndim == 3 else 1, scale, _MARGIN_STEPS) and (
                    self.copy_group or a.flags.c_contiguous):
                self._add_to_group(key, p.inverse, a, scale)
                return
            if any(g[0] == key for g in self.group):
                self._flush_group()  # its partner waits in the group: make it pending first
            self._fold_pair(key, p.inverse, a, scale, fused)

    def _fold_pair(self, key, inverse: bool, a, scale: float, fused: bool) -> None:
        """Frame by frame: fold a pair frame with its waiting partner, or make it wait (as its
        exact channel sum when ``fused``, else ``a`` is its float32 luminance)."""
        self._start_fold()
        other = self.pending.pop(key, None)
        if other is None:
            # the waiting half of the pair: its exact channel sum (or luminance)
            self.pending[key] = (inverse, _kern.channel_sum(a) if fused else a, scale)
            return
        (pos, ps), (neg, ns) = ((other[1], other[2]), (a, scale)) if inverse else \
            ((a, scale), (other[1], other[2]))
        code, axis, index = key
        # one compiled pass: both luminances, decision bit, uint8 margin, L_max / L_min
        _kern.pair_update(pos, neg, self.signs[(code, axis)], self.spec.n_bits(axis) - 1 - index,
                          self.margin[self.plane_index[key]], _MARGIN_STEPS, self.lmax,
                          self.lmin, pos_scale=ps, neg_scale=ns)

    def _start_fold(self) -> None:
        """Before the first pair is folded into the full-size accumulators: make the margins
        and decision words, set L_max / L_min to -inf / inf; marks the accumulators as used
        (no chunk-by-chunk finish then)."""
        self.folded = True
        if self.fold_started:
            return
        spec, (H, W) = self.spec, self.shape
        self.margin = np.zeros((len(self.planes), H, W), np.uint8)
        # per axis one (families, H, W) block, so the finish kernel reads them together
        self.sign_words = {a: np.zeros((len(spec.codes), H, W), _word_dtype(spec.n_bits(a)))
                           for a in _AXES if spec.n_bits(a)}
        self.signs = {(c, a): self.sign_words[a][spec.codes.index(c)] for c, a in self.families}
        self.lmax.fill(-np.inf)
        self.lmin.fill(np.inf)
        self.fold_started = True

    def _add_to_group(self, key, inverse: bool, a: np.ndarray, scale: float) -> None:
        """Buffer a pair frame for the tile-major group kernel; flush at the byte budget."""
        if self.group and (a.dtype != self.group[0][2].dtype or a.shape != self.group[0][2].shape
                           or scale != self.group[0][3]):
            self._flush_group()  # one dtype, channel count and luminance scale per group
        if self.copy_group:  # the caller may reuse the buffer of a streamed frame
            a = np.array(a, order="C", copy=True)
        self.group.append((key, inverse, a, scale))
        self.group_nbytes += a.nbytes
        if self.group_nbytes >= self.group_bytes:
            self._flush_group()

    def _flush_group(self) -> None:
        """Fold the group's complete pairs in one tile-major pass per axis
        (:func:`_sl_kernels.pairs_tiled`); a frame whose partner has not come yet waits as
        its exact channel sum, as in the frame-by-frame path."""
        group, self.group, self.group_nbytes = self.group, [], 0
        if not group:
            return
        self._start_fold()
        where = {(key, inv): j for j, (key, inv, _, _) in enumerate(group)}
        frames = [g[2] for g in group]
        import numba

        for axis in _AXES:
            pairs = [(where[(k, False)], where[(k, True)], k) for (k, inv), _ in where.items()
                     if not inv and k[1] == axis and (k, True) in where]
            if not pairs:
                continue
            n = self.spec.n_bits(axis)
            old = numba.get_num_threads()
            numba.set_num_threads(self.threads)
            try:
                _kern.pairs_tiled(
                    frames, [q[0] for q in pairs], [q[1] for q in pairs], group[0][3],
                    [self.spec.codes.index(q[2][0]) for q in pairs],
                    [n - 1 - q[2][2] for q in pairs], [self.plane_index[q[2]] for q in pairs],
                    self.sign_words[axis], self.margin, _MARGIN_STEPS, self.lmax, self.lmin,
                    parallel=self.threads > 1)
            finally:
                numba.set_num_threads(old)
        for (key, inv), j in where.items():
            if (key, not inv) not in where:  # fold with a pending partner, or wait
                self._fold_pair(key, inv, group[j][2], group[j][3], True)

    # ---------------------------------------------------------------- decoding

    def finish(self, *, min_contrast: float = 0.005, rel_contrast: float = 0.15,
               shadow_threshold: float = 0.02, min_modulation: float = 0.3,
               noise_sigma: float = 0.005, max_coarse_px: float | None = None,
               vote_tolerance_px: float = 0.0, saturation: float = 0.98) -> StreamDecode:
        """Decode the accumulated frames (see ``decode_stream`` for the parameters)."""
        spec = self.spec
        missing = [n for n in self.table if n not in self.seen]
        if missing:
            raise InputError(
                f"frames: {len(self.seen)} frame(s) given, the pattern set has "
                f"{len(self.table)}; missing {missing[:12]}{' ...' if len(missing) > 12 else ''}")
        vals = {}
        for key, v in (("min_contrast", min_contrast), ("rel_contrast", rel_contrast),
                       ("shadow_threshold", shadow_threshold), ("min_modulation", min_modulation),
                       ("noise_sigma", noise_sigma), ("vote_tolerance_px", vote_tolerance_px),
                       ("saturation", saturation)):
            vals[key] = float(as_array(v, key, shape=()))
            if vals[key] < 0:
                raise InputError(f"{key}: expected a number >= 0, got {v}")
        if max_coarse_px is not None:
            max_coarse_px = float(as_array(max_coarse_px, "max_coarse_px", shape=()))
        H, W = self.shape
        if self.finished:
            raise InputError("StreamDecoder.finish: already finished (its accumulators hold the "
                             "result now); start a new decoder")
        # frames the caller holds, none folded yet: folded and finished chunk by chunk below
        groups = self._chunk_groups()
        if groups is None:
            self._flush_group()
        self.finished = True
        # an axis with bits or phase frames is written at every pixel by _finish_chunk (no
        # fill: a fresh plane's pages are touched once, by the kernel); the others stay NaN
        out = {}
        for a in _AXES:
            written = spec.n_bits(a) or a in self.phase
            for k in (a, f"sigma_{a}"):
                out[k] = aligned_empty((H, W), np.float32, _ALIGN) if written else \
                    np.full((H, W), np.nan, np.float32)
        # direct / global / lit are written over the accumulators they come from (chunk by
        # chunk, after the chunk has read them): 3 full-size planes less at the peak
        fused_ok = self._fused_ok(groups)
        if fused_ok and spec.white_black:  # lit from the held white / black frames
            self.white = aligned_empty((H, W), np.float32, _ALIGN)
        else:
            self._wb_luminance()
        nan_plane = lambda: np.full((H, W), np.nan, np.float32)
        out["direct"] = self.lmax if self.planes else nan_plane()
        out["global_"] = self.lmin if self.planes else nan_plane()
        out["lit"] = self.white if spec.white_black else (
            out["direct"] if self.planes else nan_plane())
        # the fused chunk kernel writes every pixel of these (coded axes): no fill
        for k in ("valid_x", "valid_y", "confidence", "shadow"):
            written = fused_ok and (k[-2:] not in ("_x", "_y") or spec.n_bits(k[-1]))
            dt = np.float32 if k == "confidence" else bool
            out[k] = aligned_empty((H, W), dt, _ALIGN) if written else np.zeros((H, W), dt)
        wrapped = {a: np.full((H, W), np.nan, np.float32) for a in self.phase}
        modulation = {a: np.zeros((H, W), np.float32) for a in self.phase}
        bits = {a: {c: {"unresolved": [0] * spec.n_bits(a), "lost": [0] * spec.n_bits(a)}
                    for c in spec.codes} | {"votes_disagree": 0}
                for a in _AXES if spec.n_bits(a)}
        flat = {k: v.reshape(-1) for k, v in out.items()}
        fw = {a: v.reshape(-1) for a, v in wrapped.items()}
        fm = {a: v.reshape(-1) for a, v in modulation.items()}
        P = H * W
        if KERNELS and spec.inverse and groups is None:
            # the compiled finish decodes a table code (the long-run "minsw") from its
            # stripes' Gray words: its stored decision words are translated once, here (a
            # chunk-by-chunk finish translates each chunk's, _fold_chunk)
            from facegeo.geometry._sl_finish import stripe_gray_words

            for a in _AXES:
                for f, c in enumerate(spec.codes):
                    if spec.n_bits(a) and stripe_table(c, spec.n_bits(a)) is not None:
                        stripe_gray_words(c, spec.n_bits(a), self.sign_words[a][f])
        chunks = [slice(p0, min(P, p0 + _CHUNK)) for p0 in range(0, P, _CHUNK)]
        threads = self.threads if KERNELS else 1
        fused = self._fused_plan(groups, flat, vals, max_coarse_px) if groups else None
        if fused is not None:  # one compiled call a chunk (_sl_finish.fused_chunk)
            out["valid"] = fused["valid"].reshape(H, W)
            if threads == 1:  # one call for the image (its sub-runs keep the buffers small)
                chunks = [slice(0, P)]

            def run(sl):
                b = {a: {c: {k: [0] * len(v) for k, v in d.items()} if isinstance(d, dict)
                         else 0 for c, d in ax.items()} for a, ax in bits.items()}
                return self._fused_chunk(fused, sl, b), b

            if threads > 1 and len(chunks) > 1:
                from concurrent.futures import ThreadPoolExecutor

                with ThreadPoolExecutor(threads) as pool:
                    done = list(pool.map(run, chunks))
            else:
                done = [run(sl) for sl in chunks]
            for _, b in done:
                _add_bits(bits, b)
            if not sum(n for n, _ in done):
                self._no_lit(out, shadow_threshold)
            return StreamDecode(wrapped=wrapped, modulation=modulation, bits=bits, **out)
        if threads > 1 and len(chunks) > 1:
            # the chunks write disjoint slices; the compiled kernels release the GIL, so
            # Python threads run them in parallel (per-chunk statistics, summed after)
            from concurrent.futures import ThreadPoolExecutor

            def run(sl):
                b = {a: {c: {k: [0] * len(v) for k, v in d.items()} if isinstance(d, dict)
                         else 0 for c, d in ax.items()} for a, ax in bits.items()}
                self._finish_chunk(sl, flat, fw, fm, b, vals, max_coarse_px,
                                   self._fold_chunk(sl, groups) if groups else None)
                return b

            with ThreadPoolExecutor(threads) as pool:
                for b in pool.map(run, chunks):
                    _add_bits(bits, b)
        else:
            for sl in chunks:
                self._finish_chunk(sl, flat, fw, fm, bits, vals, max_coarse_px,
                                   self._fold_chunk(sl, groups) if groups else None)
        coded = [a for a in _AXES if spec.n_bits(a)]
        if out["shadow"].all():
            self._no_lit(out, shadow_threshold)
        out["valid"] = np.full((H, W), bool(coded))  # no coded axis: nothing is valid
        for a in coded:
            out["valid"] &= out[f"valid_{a}"]
        return StreamDecode(wrapped=wrapped, modulation=modulation, bits=bits, **out)

    @staticmethod
    def _no_lit(out, shadow_threshold) -> None:
        """Raise the error for frames where no pixel is lit by the projector."""
        lit = out["lit"]
        top = float(np.nanmax(lit)) if np.isfinite(lit).any() else 0
        raise InputError(
            f"frames: no pixel is lit by the projector (lit level below shadow_threshold="
            f"{shadow_threshold} of full scale everywhere; max lit {top:.4g}): all-dark "
            "frames, a wrong full_scale or frames of another capture")

    def _wb_luminance(self) -> None:
        """The float32 luminance of white / black frames kept as they were (``raw_wb``)."""
        for kind, (a, scale) in self.raw_wb.items():
            setattr(self, kind, _kern.luminance(a, scale))
        self.raw_wb = {}

    def _fused_ok(self, groups) -> bool:
        """Whether :meth:`finish` takes the fused chunk kernel (see :meth:`_fused_plan`)."""
        if not (FUSED and KERNELS and groups and not self.phase
                and all(g.rgb8 for g in groups.values())):
            return False
        if self.spec.white_black and len(self.raw_wb) != 2:
            return False
        g0 = next(iter(groups.values()))
        return all(g.scale == g0.scale and g.margin_k == g0.margin_k and g.flats is g0.flats
                   for g in groups.values())

    def _fused_plan(self, groups, flat, vals, max_coarse_px) -> dict | None:
        """What :func:`_sl_finish.fused_chunk` needs, prepared once per decode — or None when
        the decode takes the chunk-by-chunk Python path: frames other than 8-bit RGB (the
        pair kernel's vector block), phase frames, the numpy reference (``KERNELS = False``)
        or ``FUSED = False``."""
        spec = self.spec
        if not self._fused_ok(groups):
            return None
        g0 = next(iter(groups.values()))
        from facegeo.geometry import _sl_finish as fin

        F = len(spec.codes)
        plan = {"flats": g0.flats, "scale": g0.scale, "k": g0.margin_k, "steps": g0.steps,
                "pairs": [], "axes": [], "outs": [], "n": {}, "words": {}}
        e64 = np.zeros(0, np.int64)
        for axis in _AXES:
            n = spec.n_bits(axis)
            g = groups.get(axis)
            if g is None:  # an axis without bits: empty stand-ins of the same types
                plan["pairs"].append((e64, e64, e64, np.zeros(0, np.uint8), e64))
                plan["axes"].append((np.zeros((0, 1), np.int64), e64, np.zeros((1, 1), np.uint16),
                                     np.zeros(1, bool), np.zeros((1, 1), np.uint16), 1,
                                     np.zeros((1, 1), np.uint8), 1.0, 1, 1.0, 0.0,
                                     np.zeros(1, np.float32), np.zeros(1, bool)))
                plan["outs"].append((np.zeros(0, np.float32), np.zeros(0, np.float32),
                                     np.zeros(0, bool)))
                plan["words"][axis] = np.uint8
                continue
            size = spec.width if axis == "x" else spec.height
            s = spec.stripe_shift(axis)
            tables = [c if stripe_table(c, n) is not None else None for c in spec.codes]
            tabs, words, use = fin.code_tables(tables, n)
            wd = _word_dtype(n)
            plan["pairs"].append((g.pos, g.neg, g.rows, g.bitvals, g.planes))
            plan["axes"].append((
                np.array([[self.plane_index[(c, axis, i)] for i in range(n)]
                          for c in spec.codes], np.int64),
                np.array([-1 if base_plane(c, n) is None else base_plane(c, n)
                          for c in spec.codes], np.int64),
                tabs, use, words, int(n), fin.stripe_gray_tables(tables, n, wd),
                float(1 << s), int(-(-size // (1 << s))),
                float(max_coarse_px if max_coarse_px is not None else float(1 << s)),
                float(vals["vote_tolerance_px"]), np.zeros(1, np.float32), np.zeros(1, bool)))
            plan["outs"].append((flat[axis], flat[f"sigma_{axis}"], flat[f"valid_{axis}"]))
            plan["n"][axis] = n
            plan["words"][axis] = wd
        plan["valid"] = np.empty(flat["direct"].size, bool)
        has_wb = bool(spec.white_black)
        empty = np.zeros(0, np.uint8)
        plan["white"] = self.raw_wb["white"][0].reshape(-1) if has_wb else empty
        plan["black"] = self.raw_wb["black"][0].reshape(-1) if has_wb else empty
        plan["wb_scales"] = (self.raw_wb["white"][1], self.raw_wb["black"][1]) if has_wb \
            else (1.0, 1.0)
        plan["thresholds"] = (has_wb, vals["shadow_threshold"], vals["min_contrast"],
                              vals["rel_contrast"])
        plan["flat"] = (flat["direct"], flat["global_"], flat["lit"], flat["shadow"],
                        flat["confidence"], plan["valid"])
        plan["F"], plan["K"] = F, len(self.planes)
        fin._fused()  # built here, not in the chunk threads (one dispatcher, one compile)
        return plan

    def _fused_chunk(self, plan, sl, bits) -> int:
        """Fold and finish pixels ``sl`` in one compiled call (``_sl_finish.fused_chunk``) with
        this thread's buffers; adds the chunk's per-bit statistics to ``bits``; returns the
        number of lit pixels."""
        from facegeo.geometry import _sl_finish as fin

        sub = max(1, min(_FUSED_SUB, sl.stop - sl.start))  # (an empty image: no sub-runs)
        bufs = getattr(self._chunk_local, "fused", None)
        if bufs is None or bufs[1][1].size < sub:
            F = plan["F"]
            per_axis = tuple((np.empty((F, sub), plan["words"][a]), np.empty((F, sub), np.uint8))
                             for a in _AXES)
            shared = (np.empty((plan["K"], sub), np.uint8), np.empty(sub, np.int16),
                      np.empty(sub, np.int16), np.empty(sub, np.float32), np.empty(sub, bool))
            bufs = (per_axis, shared)
            self._chunk_local.fused = bufs
        counts = {a: np.zeros((plan["F"], 2 * plan["n"].get(a, 0) + 1), np.int64) for a in _AXES}
        outs = tuple(o + (counts[a],) for o, a in zip(plan["outs"], _AXES))
        n_lit = fin.fused_chunk(
            plan["flats"], sl.start, sl.stop, sub, plan["scale"], plan["k"], plan["steps"],
            1.0 / _MARGIN_STEPS, plan["pairs"], plan["axes"], bufs, plan["white"],
            plan["black"], plan["wb_scales"], plan["thresholds"], plan["flat"] + outs)
        for a, n in plan["n"].items():
            c = counts[a]
            for f, code in enumerate(self.spec.codes):
                st = bits[a][code]
                for i in range(n):
                    st["unresolved"][i] += int(c[f, i])
                    st["lost"][i] += int(c[f, n + i])
            bits[a]["votes_disagree"] += int(c[0, 2 * n])
        return n_lit

    def _chunk_lum(self, arr, sl):
        return None if arr is None else arr.reshape(-1)[sl]

    def _chunk_groups(self) -> dict | None:
        """The pair frames as one :class:`~facegeo.geometry._sl_kernels.PairGroup` per axis
        when the finish can fold them chunk by chunk — the compiled kernels, inverse frames,
        every pair frame still held in the group (nothing folded or pending: frames the caller
        holds, ``decode_frames`` with a mapping, list or tuple) — else None.

        Folding a chunk's pairs just before finishing it keeps the decision words, the margins
        and the channel sums in chunk-sized buffers in cache: the full-size words (2 bytes a
        pixel per family and axis) and margin planes (1 byte a pixel per bit) are never written
        and read back, nor held at the peak. The same kernels and values as the whole-image
        fold (tested)."""
        if not (KERNELS and self.spec.inverse and self.planes) or self.folded or self.pending:
            return None
        where = {(key, inv): j for j, (key, inv, _, _) in enumerate(self.group)}
        if len(where) != len(self.group) or len(where) != 2 * len(self.planes) or any(
                (pl, inv) not in where for pl in self.planes for inv in (False, True)):
            return None
        frames = [g[2] for g in self.group]
        flats = _kern.FrameSet(frames)  # one set for both axes
        groups = {}
        for axis in _AXES:
            n = self.spec.n_bits(axis)
            keys = [pl for pl in self.planes if pl[1] == axis]
            if not keys:
                continue
            groups[axis] = _kern.PairGroup(
                frames, [where[(k, False)] for k in keys], [where[(k, True)] for k in keys],
                self.group[0][3], [self.spec.codes.index(k[0]) for k in keys],
                [n - 1 - k[2] for k in keys], [self.plane_index[k] for k in keys],
                _MARGIN_STEPS, _word_dtype(n), parallel=False, flats=flats)
        self.group, self.group_nbytes = [], 0
        self._chunk_local = threading.local()  # _fold_chunk's buffers, one set per thread
        return groups

    def _fold_chunk(self, sl, groups) -> tuple:
        """Fold the pairs over pixels ``sl`` into chunk-sized words and margins (columns from
        0) and into L_max / L_min at ``sl``; returns ``(margin, words by axis, mmin)`` for
        :meth:`_finish_chunk`, and by axis each code family's smallest margin where the pair
        kernel kept it (``mmin``)."""
        n_pix = sl.stop - sl.start
        # chunk buffers kept per thread (flat, so a short last chunk's views stay contiguous)
        bufs = getattr(self._chunk_local, "bufs", None)
        if bufs is None or bufs[0].size < len(self.planes) * n_pix:
            F = len(self.spec.codes)
            bufs = (np.empty(len(self.planes) * n_pix, np.uint8),
                    {a: np.empty(F * n_pix, _word_dtype(self.spec.n_bits(a))) for a in groups},
                    {a: np.empty(F * n_pix, np.uint8) for a in groups})
            self._chunk_local.bufs = bufs
        margin = bufs[0][:len(self.planes) * n_pix].reshape(-1, n_pix)  # every plane written
        words, mmin = {}, {}
        for a, w in bufs[1].items():
            words[a] = w[:len(self.spec.codes) * n_pix].reshape(-1, n_pix)
            words[a].fill(0)
            mmin[a] = bufs[2][a][:len(self.spec.codes) * n_pix].reshape(-1, n_pix)
            mmin[a].fill(255)
        lmax, lmin = self.lmax.reshape(-1)[sl], self.lmin.reshape(-1)[sl]
        lmax.fill(-np.inf)
        lmin.fill(np.inf)
        for a, g in groups.items():
            if not g.run(words[a], margin, lmax, lmin, start=sl.start, stop=sl.stop,
                         offset=sl.start, mmin=mmin[a]):
                del mmin[a]  # not kept by this kernel: the finish takes it plane by plane
        from facegeo.geometry._sl_finish import stripe_gray_words

        for a in groups:
            n = self.spec.n_bits(a)
            for f, c in enumerate(self.spec.codes):
                if stripe_table(c, n) is not None:
                    stripe_gray_words(c, n, words[a][f])
        return margin, words, mmin

    def _finish_chunk(self, sl, flat, fw, fm, bits, vals, max_coarse_px, acc=None) -> None:
        """Finish pixels ``sl``; ``acc``: the chunk's own ``(margin, words, mmin)`` from
        :meth:`_fold_chunk` in place of the full-size accumulators."""
        spec = self.spec
        has_bin = bool(self.planes)
        lmax = self._chunk_lum(self.lmax, sl)
        lmin = self._chunk_lum(self.lmin, sl)
        compiled = has_bin and KERNELS  # lit / direct / global / shadow / tau in one pass below
        direct = lmax - lmin if has_bin and not compiled else None
        if compiled:
            lit = None
        elif spec.white_black:
            lit = self._chunk_lum(self.white, sl) - self._chunk_lum(self.black, sl)
        elif has_bin:
            lit = direct
        else:
            a0 = next(iter(self.phase))
            lit = 2.0 * self.phase[a0][2].reshape(-1)[sl] / spec.phase_steps
        lit = None if lit is None else np.asarray(lit, np.float32)
        thr = None
        if has_bin and not spec.inverse:
            if spec.white_black:
                thr = 0.5 * (self._chunk_lum(self.white, sl) + self._chunk_lum(self.black, sl))
            else:
                thr = 0.5 * (lmax + lmin)
        n_pix = sl.stop - sl.start
        # the chunk's accumulators are read: overwrite them with the outputs (see finish)
        if compiled:  # one compiled pass, in place
            from facegeo.geometry._sl_finish import prepare

            tau = np.empty(n_pix, np.float32)
            shadow = flat["shadow"][sl]
            prepare(self._chunk_lum(self.white, sl) if spec.white_black else None,
                    self._chunk_lum(self.black, sl), lmax, lmin, vals["shadow_threshold"],
                    vals["min_contrast"], vals["rel_contrast"], flat["lit"][sl], shadow, tau)
            ref = direct = flat["direct"][sl]
        else:
            if has_bin:
                flat["global_"][sl] = 2.0 * np.maximum(lmin, 0.0)
                flat["direct"][sl] = direct
            flat["lit"][sl] = lit
            shadow = ~(lit >= vals["shadow_threshold"])
            flat["shadow"][sl] = shadow
            ref = direct if has_bin else lit
            tau = np.maximum(np.float32(vals["min_contrast"]),
                             np.float32(vals["rel_contrast"]) * ref)
        conf_all = np.ones(n_pix, np.float32)
        any_axis = False
        for axis in _AXES:
            n = spec.n_bits(axis)
            phase_here = axis in self.phase
            if not n and not phase_here:
                continue
            any_axis = True
            size = spec.width if axis == "x" else spec.height
            s = spec.stripe_shift(axis)
            step = float(1 << s)
            period = size / spec.phase_periods(axis) if phase_here else None
            if max_coarse_px is not None:
                coarse_lim = max_coarse_px
            else:
                coarse_lim = period / 2.0 if phase_here else step
            if KERNELS and n and not phase_here:  # the kernel writes the axis's outputs
                self._decode_axis_compiled(
                    axis, n, s, size, sl, tau, ref, shadow, thr, coarse_lim, vals, bits[axis],
                    out=(flat[axis][sl], flat[f"sigma_{axis}"][sl], flat[f"valid_{axis}"][sl],
                         conf_all), acc=acc)
                continue
            coord = np.full(n_pix, np.nan, np.float32)
            sig = np.full(n_pix, np.nan, np.float32)
            conf = np.zeros(n_pix, np.float32)
            ok = np.zeros(n_pix, bool)
            hint = None
            if KERNELS and phase_here and n:  # compiled: phase, bits, unwrapping, outputs
                from facegeo.geometry import _sl_finish as fin

                S, C, _ = (v.reshape(-1)[sl] for v in self.phase[axis])
                N = spec.phase_steps
                k = 2.0 * np.pi * spec.phase_periods(axis) / size
                B = fm[axis][sl]
                phi, pconf, pok = fin.phase(
                    S, C, self.phase_max.reshape(-1)[sl], ref, shadow, N,
                    vals["min_modulation"], vals["saturation"], fw[axis][sl], B)
                coord, sig, ok, conf = self._decode_axis_compiled(
                    axis, n, s, size, sl, tau, ref, shadow, thr, coarse_lim, vals, bits[axis],
                    (phi, pok, k, period), acc=acc)
                fin.phase_merge(coord, sig, ok, conf, phi, B, pconf, pok, k,
                                vals["noise_sigma"], N, step,
                                (flat[axis][sl], flat[f"sigma_{axis}"][sl],
                                 flat[f"valid_{axis}"][sl], conf_all))
                continue
            if phase_here:
                S, C, _ = (v.reshape(-1)[sl] for v in self.phase[axis])
                N = spec.phase_steps
                phi = np.mod(np.arctan2(S.astype(np.float64), C.astype(np.float64)).astype(
                    np.float32), np.float32(2 * np.pi)).astype(np.float32)
                phi[phi >= 2 * np.pi] = 0.0
                B = (2.0 / N) * np.hypot(S, C)
                fm[axis][sl] = B
                phi_out = phi.copy()
                phi_out[~(B > 0)] = np.nan
                fw[axis][sl] = phi_out
                pconf = np.clip(2.0 * B / np.maximum(ref, 1e-12), 0.0, 1.0).astype(np.float32)
                # a clipped fringe biases the phase: saturated pixels fall back to the code
                pok = ~shadow & (pconf >= vals["min_modulation"]) \
                    & (self.phase_max.reshape(-1)[sl] < vals["saturation"])
                hint = (phi, pok, 2.0 * np.pi * spec.phase_periods(axis) / size, period)
            if n:
                decode = self._decode_axis_compiled if KERNELS else self._decode_axis
                coord, sig, ok, conf = decode(
                    axis, n, s, size, sl, tau, ref, shadow, thr, coarse_lim, vals, bits[axis],
                    hint, **({"acc": acc} if KERNELS else {}))
            if phase_here:
                k = 2.0 * np.pi * spec.phase_periods(axis) / size
                if n:
                    with np.errstate(invalid="ignore"):
                        m = np.round((k * (coord.astype(np.float64) + 0.5) - phi) / (2 * np.pi))
                    xp = (phi + 2 * np.pi * m) / k - 0.5
                    use = ok & pok
                    psig = (vals["noise_sigma"] * math.sqrt(2.0 / N)
                            / np.maximum(B, 1e-12) / k).astype(np.float32)
                    # Coarse-only pixels keep a coordinate only if exact to one stripe.
                    keep_coarse = ok & ~pok & (sig <= step / math.sqrt(12.0) + 1e-6)
                    coord = np.where(use, xp, np.where(keep_coarse, coord, np.nan)).astype(np.float32)
                    sig = np.where(use, psig, np.where(keep_coarse, sig, np.nan)).astype(np.float32)
                    conf = np.where(use, np.minimum(conf, pconf), np.where(keep_coarse, conf, 0))
                    ok = use | keep_coarse
                # phase without binary codes: no unwrapping, the axis stays invalid
            flat[axis][sl] = np.where(ok, coord, np.nan)
            flat[f"sigma_{axis}"][sl] = np.where(ok, sig, np.nan)
            flat[f"valid_{axis}"][sl] = ok
            conf_all = np.minimum(conf_all, np.where(ok, conf, 0.0))
        if any_axis:
            flat["confidence"][sl] = conf_all

    def _plane_vs_threshold(self, k, sl, thr):
        """Without inverse frames: stored plane ``k`` against the pixel threshold, as the
        decision ``value > thr`` and the margin ``2 |value - thr|`` (float32)."""
        v = self.values[k].reshape(-1)[sl].astype(np.float32) - thr
        return v > 0, 2.0 * np.abs(v)

    def _decode_axis_compiled(self, axis, n, s, size, sl, tau, ref, shadow, thr, coarse_lim,
                              vals, stats, hint=None, out=None, acc=None):
        """:meth:`_decode_axis` in the compiled per-pixel kernel (``_sl_finish``): the same
        results, one pass per pixel over its words and margins instead of numpy planes.
        ``out``: write the axis's final outputs there (see ``_sl_finish.decode_axis``)."""
        from facegeo.geometry._sl_finish import decode_axis, stripe_gray_words

        codes = self.spec.codes
        F = len(codes)
        n_pix = sl.stop - sl.start
        if self.spec.inverse:  # the stored words and margins, columns sl (or the chunk's
            # own, from column 0: _fold_chunk)
            p0 = 0 if acc is not None else sl.start
            signs = acc[1][axis] if acc is not None else self.sign_words[axis].reshape(F, -1)
            marg = acc[0] if acc is not None else self.margin.reshape(len(self.planes), -1)
            kidx = np.array([[self.plane_index[(c, axis, i)] for i in range(n)] for c in codes])
            mscale = 1.0 / _MARGIN_STEPS
        else:  # decisions and margins against the pixel's threshold, then the same kernel
            dt = _word_dtype(n)
            signs = np.zeros((F, n_pix), dt)
            marg = np.empty((F * n, n_pix), np.float32)
            for f, c in enumerate(codes):
                for i in range(n):
                    positive, marg[f * n + i] = self._plane_vs_threshold(
                        self.plane_index[(c, axis, i)], sl, thr)
                    signs[f] |= positive.astype(dt) << dt(n - 1 - i)
            kidx = np.arange(F * n).reshape(F, n)
            mscale, p0 = 1.0, 0
        base = [-1 if base_plane(c, n) is None else base_plane(c, n) for c in codes]
        n_stripes = -(-size // (1 << s))
        tables = [c if stripe_table(c, n) is not None else None for c in codes]
        if not self.spec.inverse:  # the stored words were translated in finish()
            for f, c in enumerate(tables):
                if c is not None:
                    stripe_gray_words(c, n, signs[f])
        coord, sig, ok, conf, unresolved, lost, disagree = decode_axis(
            signs, marg, mscale, kidx, base, n, float(1 << s), n_stripes, coarse_lim,
            vals["vote_tolerance_px"], tau, ref, ~shadow, hint, out, p0, tables,
            acc[2].get(axis) if acc is not None else None)
        for f, c in enumerate(codes):
            for i in range(n):
                stats[c]["unresolved"][i] += int(unresolved[f, i])
                stats[c]["lost"][i] += int(lost[f, i])
        stats["votes_disagree"] += disagree
        return coord, sig, ok, conf

    def _bit_words(self, code, axis, n, sl, tau, thr):
        """(signs, reliable) packed words of family ``code`` on ``axis`` for pixels ``sl``, and
        the smallest margin over each bit as (n, P) float32."""
        dt = _word_dtype(n)
        n_pix = sl.stop - sl.start
        rel = np.zeros(n_pix, dt)
        margins = np.empty((n, n_pix), np.float32)
        if self.spec.inverse:
            signs = self.signs[(code, axis)].reshape(-1)[sl].copy()
        else:
            signs = np.zeros(n_pix, dt)
        for i in range(n):
            k = self.plane_index[(code, axis, i)]
            if self.spec.inverse:
                m = self.margin[k].reshape(-1)[sl].astype(np.float32) * np.float32(1.0 / _MARGIN_STEPS)
            else:
                positive, m = self._plane_vs_threshold(k, sl, thr)
                signs |= positive.astype(dt) << dt(n - 1 - i)
            margins[i] = m
            rel |= (m >= tau).astype(dt) << dt(n - 1 - i)
        b = base_plane(code, n)
        if b is not None and b > 0:
            high = dt(((1 << b) - 1) << (n - b))  # planes i < b
            base_sign = (signs >> dt(n - 1 - b)) & dt(1)
            signs ^= base_sign * high
            base_rel = (rel >> dt(n - 1 - b)) & dt(1)
            rel &= np.where(base_rel.astype(bool), dt((1 << n) - 1), dt(~high & ((1 << n) - 1)))
            margins[:b] = np.minimum(margins[:b], margins[b])
        return signs, rel, margins

    def _decode_axis(self, axis, n, s, size, sl, tau, ref, shadow, thr, coarse_lim, vals, stats,
                     hint=None):
        """Per family: coordinate from the resolved bits; then the vote across families.

        ``hint = (phi, usable, k, period)``: the wrapped phase on this axis picks between the two
        candidate codes of a pixel with one unresolved plane (the one whose predicted phase
        ``k (x + 0.5)`` is within a quarter period of ``phi``, when the other is not or both
        lie within half a period of each other)."""
        step = float(1 << s)
        n_stripes = -(-size // (1 << s))
        full = (1 << n) - 1
        lit = ~shadow
        results = []
        for code in self.spec.codes:
            signs, rel, margins = self._bit_words(code, axis, n, sl, tau, thr)
            table = stripe_table(code, n)
            word = signs.astype(np.int64)
            if table is not None:  # long-run code: the code -> stripe table
                binary = table[word].astype(np.int64)
            else:  # Gray -> binary, a prefix XOR
                binary = word.copy()
                shift = 1
                while shift < n:
                    binary ^= binary >> shift
                    shift *= 2
            u = (~rel.astype(np.int64)) & full  # unresolved planes
            P = u.size
            first = np.full(P, n, np.int64)  # first unresolved plane (MSB index), n if none
            c_st = binary.astype(np.float64)  # coordinate in stripes
            w_eff = np.ones(P)  # width of the named block, stripes
            exists = binary < n_stripes
            edge = np.zeros(P, bool)
            picked = np.zeros(P, bool)
            idx = np.flatnonzero(u)  # only pixels with unresolved planes need more work
            if idx.size:
                sub = None if hint is None else (hint[0][idx], hint[1][idx], hint[2], hint[3])
                (first[idx], c_st[idx], w_eff[idx], exists[idx], edge[idx],
                 picked[idx]) = _partial_codes(binary[idx], u[idx], n, step, n_stripes, sub,
                                               table, word[idx])
            ok = lit & exists & ((w_eff * step <= coarse_lim + 1e-9) | edge | picked)
            coord = c_st * step + 0.5 * (step - 1.0)
            sig = np.where(edge, 0.5 * step, w_eff * step / math.sqrt(12.0))
            # confidence: weakest margin among the planes used, over the direct light
            mmin = margins.min(axis=0)
            st = stats[code]
            if idx.size:
                limit = np.where(edge[idx] | picked[idx], n, first[idx])
                us, lit_s = u[idx], lit[idx]
                ms = np.full(idx.size, np.inf, np.float32)
                for i in range(n):
                    bad_i = ((us >> (n - 1 - i)) & 1).astype(bool)
                    st["unresolved"][i] += int(np.count_nonzero(bad_i & lit_s))
                    np.minimum(ms, np.where(bad_i | (limit <= i), np.inf, margins[i, idx]), out=ms)
                ms[~np.isfinite(ms)] = 0.0
                mmin[idx] = ms
            lost = np.bincount(first[lit & ~ok], minlength=n + 1)
            for i in range(n):
                st["lost"][i] += int(lost[i])
            conf = np.clip(mmin / np.maximum(ref, 1e-12), 0.0, 1.0)
            results.append((coord, sig, ok, conf, w_eff * step))
        if len(results) == 1:
            coord, sig, ok, conf, _ = results[0]
            return (coord.astype(np.float32), sig.astype(np.float32), ok,
                    conf.astype(np.float32))
        # Consistency vote (Gupta et al. 2013, Sec. 4.3): a family's coordinate counts when
        # another family's agrees within half their block widths + vote_tolerance_px, or when
        # it is the only family that resolved the pixel.
        F = len(results)
        agree = np.zeros((F, results[0][0].size), np.int64)
        for i in range(F):
            for j in range(i + 1, F):
                ci, _, oi, _, wi = results[i]
                cj, _, oj, _, wj = results[j]
                with np.errstate(invalid="ignore"):
                    a = oi & oj & (np.abs(ci - cj) <= 0.5 * (wi + wj) / 2 + vals["vote_tolerance_px"])
                agree[i] += a
                agree[j] += a
        # choose the family with most agreement, ties to the smaller σ, then the listed order
        sigs = np.stack([np.where(r[2], r[1], np.inf) for r in results])
        score = agree * 1e6 - np.minimum(sigs, 1e5)
        best = np.argmax(score, axis=0)
        pick = lambda k: np.take_along_axis(np.stack([r[k] for r in results]), best[None], 0)[0]
        coord, sig, conf = pick(0), pick(1), pick(3)
        nbest = np.take_along_axis(agree, best[None], 0)[0]
        n_ok = np.stack([r[2] for r in results]).sum(axis=0)
        # A lone resolved family stands when every other one is unresolved (no contradiction:
        # fine XOR bases blur away under subsurface scattering); two that disagree do not.
        ok = (nbest >= 1) | (n_ok == 1)
        stats["votes_disagree"] += int(np.count_nonzero(lit & (n_ok >= 2) & ~ok))
        conf = conf * (nbest + 1) / F
        return (coord.astype(np.float32), sig.astype(np.float32), ok, conf.astype(np.float32))



def _partial_codes(binary, u, n, step, n_stripes, hint, table=None, word=None):
    """Coordinates of pixels with unresolved planes ``u`` (int64 words, all non-zero).

    Returns ``first`` (first unresolved plane), ``c_st`` (coordinate, stripes), ``w_eff`` (block
    width, stripes), ``exists`` (the block is on the projector), ``edge``, ``picked`` — see
    :func:`facegeo.geometry.structured_light.decode_stream`:

    * (a) one unresolved plane at an edge of that plane: the two candidate codes are neighbours
      (Gray codes change one plane between neighbours) → the boundary between them;
    * (c) one unresolved plane, candidates far apart: the phase ``hint = (phi, usable, k,
      period)`` picks the one whose predicted phase ``k (x + 0.5)`` is within a quarter period;
    * (b) otherwise the resolved prefix names a block of ``2**(n - first)`` stripes.

    With ``table`` (a long-run code's code → stripe table, ``word`` the decision words) the
    candidates of (a) / (c) are ``table[word]`` and ``table[word ^ plane]``; (b) does not
    exist (its resolved planes name no block): such pixels get ``exists = False``.
    """
    first = n - np.frexp(u.astype(np.float64))[1].astype(np.int64)
    single = (u & (u - 1)) == 0
    if table is None:  # Gray: the binary index with the bits below the prefix flipped
        flip = binary ^ ((np.int64(1) << (n - first)) - 1)
    else:  # the word with its (first) unresolved plane flipped, through the table
        flip = table[word ^ (np.int64(1) << (n - 1 - first))].astype(np.int64)
    edge = single & (np.abs(flip - binary) == 1)
    picked = np.zeros(u.shape, bool)
    if hint is not None:
        phi, usable, kk, period = hint
        amb = np.flatnonzero(single & ~edge & usable)
        if amb.size:
            ca = binary[amb] * step + 0.5 * (step - 1.0)
            cb = flip[amb] * step + 0.5 * (step - 1.0)
            # wrapped to [-pi, pi] by arithmetic alone, as the kernel does (no libm / SIMD
            # differences in sin, cos, atan2 at the pick's threshold)
            xa = phi[amb] - kk * (ca + 0.5)
            xb = phi[amb] - kk * (cb + 0.5)
            da = np.abs(xa - 2 * np.pi * np.rint(xa / (2 * np.pi)))
            db = np.abs(xb - 2 * np.pi * np.rint(xb / (2 * np.pi)))
            dmin, dmax = np.minimum(da, db), np.maximum(da, db)
            good = (dmin < 0.5 * np.pi) & ((dmax >= 0.5 * np.pi) | (np.abs(ca - cb) < 0.5 * period))
            picked[amb] = good
            binary = binary.copy()
            swap = amb[good & (db < da)]
            binary[swap] = flip[swap]
    w = (np.int64(1) << (n - first)).astype(np.float64)
    block = binary >> (n - first)
    c_st = np.where(edge, 0.5 * (binary + flip), np.where(picked, binary, block * w + 0.5 * (w - 1)))
    w_eff = np.where(edge | picked, 1.0, w)
    exists = np.where(edge, np.maximum(binary, flip), np.where(picked, binary, block * w)) < n_stripes
    if table is not None:
        exists &= edge | picked
    return first, c_st, w_eff, exists, edge, picked


def decode_frames(frames: Iterable, spec, *, full_scale=None, threads: int = 1,
                  **settings) -> StreamDecode:
    """Feed ``(name, frame)`` pairs to a :class:`StreamDecoder` and finish it.

    ``threads``: of the tile-major pair kernel and of the finish (1 … ``NUMBA_NUM_THREADS``).
    Default 1: on the shared 2-core machine two threads were 1.6× faster than one when idle
    but slower whenever another job ran (docs/structured-light.md)."""
    from collections.abc import ItemsView, Mapping

    if isinstance(frames, Mapping):
        frames = frames.items()
    # frames the caller already holds (a mapping, list or tuple): one tile-major group over all
    # of them, no copies; a stream (generator): groups of copies up to STREAM_GROUP_BYTES
    held = isinstance(frames, (ItemsView, list, tuple))
    dec = StreamDecoder(spec, full_scale=full_scale,
                        group_bytes=math.inf if held else STREAM_GROUP_BYTES,
                        copy_group=not held, threads=threads)
    try:
        it = iter(frames)
    except TypeError:
        raise InputError(f"frames: expected an iterable of (name, frame) pairs, got "
                         f"{type(frames).__name__}") from None
    for item in it:
        try:
            name, frame = item
        except (TypeError, ValueError):
            raise InputError("frames: expected (name, frame) pairs, got an item of type "
                             f"{type(item).__name__}") from None
        dec.add(name, frame)
    if dec.shape is None:
        raise InputError("frames: empty; expected the frames named by pattern_names(spec)")
    return dec.finish(**settings)
