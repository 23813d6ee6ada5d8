"""Relighting a reflectance field with Eq. (3)–(4) of Debevec et al. 2000.

    L̂(x, y) = Σ_l R_xy(l) · L_i(l) · δA(l)                                   (Eq. 4)

with the weights ``w_l = L_i(l)·δA(l)`` produced by :mod:`facegeo.lighting.envmap` (δA already
included). A field is ``(P, L, 3)`` (P pixels of one camera or T texels, L lights, RGB),
float16 or float32. The sum is computed as one matrix product per chunk of rows: the field's
rows ``(P, 3L)`` times a block weight matrix ``(3L, 3B)`` whose column ``3b + c`` holds
environment b's channel-c weights on the rows of channel c — so the field is read once,
contiguously, for any number B of environments (a GEMV-like GEMM; a batch of B maps is one
GEMM). float16 rows are converted chunk-wise to float32 (numpy float16 arithmetic is ≈ 30×
slower, ``einsum`` ≈ 9× — DESIGN §6); for one environment on a float16 field a fused numba
kernel (:mod:`facegeo.lighting._fused`) widens each half in registers (the CPU's F16C
``vcvtph2ps`` where available) and accumulates the three channel sums of several rows at a time
in the same pass, against one channel-interleaved weight vector that stays in L1 (measured
ratios in ``docs/lighting.md``).

Light colour (paper §3.3, "we normalize the reflectance functions based on the light source
color"): an OLAT frame taken with light colour ``c_l`` is ``R_l ⊙ c_l``; pass ``light_color``
and the weights are divided by it, which relights the colour-normalised field.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from facegeo.checks import as_array, check_choice, fmt_value
from facegeo.errors import InputError, ShapeError

log = logging.getLogger(__name__)

__all__ = ["CHUNK_BYTES", "FUSED_CHUNK_BYTES", "tint_clothing", "SPARSE_FRACTION", "normalize_weights", "block_weights",
           "relight_field", "relight_frames", "relight_scan_view", "relight_scan_view_maps"]

#: Target size of one float32 chunk of field rows (fits comfortably in the L2/L3 caches).
CHUNK_BYTES = 4 << 20

#: Size of one chunk of float16 rows handed to a thread by the fused kernel (it needs no
#: conversion buffer, so chunks can be larger: fewer thread hand-offs, 253 for the paper-size
#: field instead of 2000).
FUSED_CHUNK_BYTES = 16 << 20

#: Use only the lights with non-zero weight when at most this fraction of them is active. The
#: gather of the active columns costs more than it saves above ≈ 2 % (measured on a 20,000 ×
#: 2048 × 3 float32 field: sparse / dense time 2.6 at 10 % lit, 1.3 at 3 %, 0.45 at 1 %).
#: Frames streamed from disk (:func:`relight_scan_view`) always skip unlit lights.
SPARSE_FRACTION = 0.02


def normalize_weights(weights: Any, n_lights: int, light_color: Any = None) -> np.ndarray:
    """Validate Eq. (4) weights and divide out the light colour.

    Parameters
    ----------
    weights : (L, 3) or (B, L, 3) float
        ``L_i · δA`` per light (and per environment b).
    n_lights : int
    light_color : (3,) or (L, 3) float, optional
        Colour of the light that took each OLAT frame (``LightStage.color``); > 0.

    Returns
    -------
    (B, L, 3) float64
    """
    w = as_array(weights, "weights")
    if w.ndim == 2:
        w = w[None]
    if w.ndim != 3 or w.shape[1:] != (n_lights, 3):
        raise ShapeError(f"weights: expected shape ({n_lights}, 3) or (B, {n_lights}, 3), "
                         f"got {tuple(np.shape(weights))}")
    if light_color is not None:
        c = as_array(light_color, "light_color")
        if c.shape not in ((3,), (n_lights, 3)):
            raise ShapeError(f"light_color: expected shape (3,) or ({n_lights}, 3), got {c.shape}")
        if np.any(c <= 0):
            raise InputError("light_color: expected every channel > 0 (a light with a zero "
                             "channel recorded no information to normalise)")
        w = w / c
    return w


def block_weights(w: np.ndarray, active: np.ndarray | None = None) -> np.ndarray:
    """The ``(3L', 3B)`` float32 matrix turning field rows ``(P, 3L')`` into ``(P, 3B)``.

    Row ``3l + c`` carries ``w[b, l, c]`` in column ``3b + c`` (zero elsewhere); ``active``
    selects the lights L' kept.
    """
    if active is not None:
        w = w[:, active]
    b, n_l, _ = w.shape
    W = np.zeros((n_l, 3, b, 3), np.float32)
    for c in range(3):
        W[:, c, :, c] = w[:, :, c].T
    return W.reshape(n_l * 3, b * 3)


def _half_to_float32(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Convert a 2-D float16 array into the float32 buffer ``dst`` (same shape), exactly.

    OpenCV's CV_16F → CV_32F conversion uses the CPU's F16C instructions (≈ 2 G values/s
    here, 4× numpy's cast); numpy's cast is the fallback.
    """
    try:
        import cv2

        r = cv2.add(src, 0.0, dst=dst, dtype=cv2.CV_32F)  # x + 0 is exact (−0 becomes +0)
        if r is dst or np.shares_memory(r, dst):
            return dst
        dst[...] = r.reshape(dst.shape)
        return dst
    except Exception:  # noqa: BLE001 - any OpenCV refusal falls back to numpy's exact cast
        dst[...] = src
        return dst


_FUSED: Any = None  # the compiled kernel, None until first use, False when numba is missing
#: How the fused kernel widens halves on this host: "f16c" (the CPU's vcvtph2ps, through an
#: LLVM ``fpext half → float``) or "bits" (branch-free integer bit manipulation); set on first
#: use of :func:`_fused_kernel`.
FUSED_CONVERSION: str | None = None

#: Field rows accumulated together by the fused kernel: 4 with F16C
#: (:func:`facegeo.lighting._fused.fused_half_dot_f16c`, one channel-interleaved weight vector
#: held in L1; 4 rows × 3 phase accumulators), 3 with the portable bit conversion
#: (:func:`facegeo.lighting._fused.fused_half_dot`, three weight vectors; 3 rows × 3 channels = 9
#: vector accumulators; measured in cache on one core, 200 rows × 2048 lights: 1 row 7.2 G
#: halves/s, 2 rows 11.9, 3 rows 14.7, 4 rows 13.6, register spills). Set with
#: :data:`FUSED_CONVERSION` on first use of :func:`_fused_kernel`.
FUSED_ROWS: int | None = None


def _host_has_f16c() -> bool:
    """Whether the CPU has F16C (:func:`facegeo.surface._half.host_has_f16c`; ``False`` without
    numba, imported here on first use so ``import`` stays light)."""
    try:
        from facegeo.surface._half import host_has_f16c
    except ImportError:  # numba missing: the fused kernel is not used either
        return False
    return host_has_f16c()


def _fused_kernel(conversion: str | None = None):
    """The fused float16 dot-product kernel, or ``False`` when numba is not installed (the
    OpenCV/BLAS path is used instead).

    Returns ``kernel(h, w0, w1, w2, out, wi=None)`` (``h`` (n, 3L') uint16 bits of float16
    rows, C-contiguous; ``w_c`` (3L',) float32 channel c's weights on its columns, zero
    elsewhere; ``wi = w0 + w1 + w2``, computed when not given; ``out`` (n, 3) float32) with the
    half → float conversion fixed: ``conversion`` ``"f16c"`` (the CPU's ``vcvtph2ps``;
    :func:`facegeo.lighting._fused.fused_half_dot_f16c`, the weights interleaved in one vector
    that stays in L1) or ``"bits"`` (portable bit manipulation;
    :func:`facegeo.lighting._fused.fused_half_dot`); default the host's best, recorded in
    :data:`FUSED_CONVERSION` and :data:`FUSED_ROWS`. Both give the same sums in the same order
    (up to the sign of a zero sum). Compiled on first use and cached on disk. Measured in cache
    on one core, 2048-light rows: 4.3 G halves/s for the bit manipulation one row at a time, 7.2
    with F16C, 14.7 with F16C and three rows per pass; out of cache the interleaved kernel
    reads as fast as a pure read of the field (``docs/lighting.md``).
    """
    global _FUSED, FUSED_CONVERSION, FUSED_ROWS
    if conversion is None:
        if _FUSED is None:
            FUSED_CONVERSION = "f16c" if _host_has_f16c() else "bits"
            _FUSED = _fused_kernel(FUSED_CONVERSION)
            if _FUSED:
                from facegeo.lighting._fused import INTERLEAVED_ROWS

                FUSED_ROWS = INTERLEAVED_ROWS if FUSED_CONVERSION == "f16c" else 3
        return _FUSED
    check_choice(conversion, "conversion", ("f16c", "bits"))
    try:
        from facegeo.lighting._fused import fused_half_dot, fused_half_dot_f16c
    except ImportError:
        return False
    if conversion == "f16c" and _host_has_f16c():
        def kernel(h, w0, w1, w2, out, wi=None):
            if wi is None:
                wi = w0 + w1 + w2
            fused_half_dot_f16c(np.ascontiguousarray(h), w0, w1, w2, wi, out)
    else:  # without F16C the "f16c" flag is ignored (surface._half): the bit conversion
        f16c = conversion == "f16c"

        def kernel(h, w0, w1, w2, out, wi=None):
            fused_half_dot(h, w0, w1, w2, out, f16c)

    return kernel


def _blas_single_thread():
    """Context limiting BLAS to one thread (chunks are spread over Python threads instead: many
    small BLAS calls each waking a thread pool cost more than they gain on a busy machine)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional: without it BLAS keeps its own threads
        import contextlib

        return contextlib.nullcontext()
    return threadpool_limits(1, user_api="blas")


def relight_field(field: Any, weights: Any, *, light_color: Any = None,
                  chunk_rows: int | None = None, sparse: bool | None = None,
                  workers: int = 2, kernel: str | None = None) -> np.ndarray:
    """Relight an image-space or texel reflectance field with one or a batch of environments.

    Implements Eq. (4) of Debevec et al. 2000 (the weights carry δA). The field is read once,
    in chunks of rows. One environment on a float16 field: the fused kernel (see ``kernel``).
    Otherwise a float16 chunk is converted to float32 into a cache-resident buffer;
    one environment is three BLAS GEMVs over the chunk (one per channel, the weight vector
    zero on the other channels' columns: the chunk stays in cache, so memory is read once); a
    batch of B environments is one GEMM ``(rows, 3L) @ (3L, 3B)``.

    Parameters
    ----------
    field : (P, L, 3) float16 or float32 array (a ``numpy.memmap`` streams from disk)
        Reflectance field: P pixels or texels, L lights, RGB, light-index order.
    weights : (L, 3) or (B, L, 3) float
        Eq. (4) weights ``L_i·δA`` (from :func:`facegeo.lighting.envmap.light_stage_weights`).
    light_color : (3,) or (L, 3), optional
        Divide the weights by the recording light's colour (colour-normalised field).
    chunk_rows : int, optional
        Rows per chunk (default: :data:`CHUNK_BYTES` of float32; :data:`FUSED_CHUNK_BYTES` of
        float16 for the fused kernel).
    sparse : bool, optional
        Read only lights with non-zero weight (default: when ≤ :data:`SPARSE_FRACTION` of the
        lights are active).
    workers : int
        Python threads sharing the chunks (BLAS itself runs single-threaded meanwhile).
    kernel : {"fused", "blas"}, optional
        ``"fused"``: one environment on a float16 field goes through a compiled (numba) kernel
        that converts each row's halves to float32 in registers (F16C where the CPU has it)
        and accumulates the dot products of :data:`FUSED_ROWS` rows in the same pass (no
        converted chunk is written back to memory; exact conversion, float32 accumulation in
        vector lanes). ``"blas"``: OpenCV's F16C conversion into a cache-resident chunk, then
        BLAS. Default: ``"fused"`` when numba is installed and the call is one environment on a
        float16 field, else ``"blas"``.

    Returns
    -------
    (P, 3) float32, or (B, P, 3) for batched weights
        Relit radiance. A row whose sample is NaN/inf at a *lit* light is NaN/inf (masked
        samples are never trusted); masked samples at unlit lights do not matter (such rows
        are recomputed from the lit lights only, in float64 — NaN · 0 would otherwise poison
        the BLAS sum).
    """
    f = np.asarray(field)
    if f.ndim != 3 or f.shape[2] != 3:
        raise ShapeError(f"field: expected shape (P, L, 3), got {tuple(f.shape)}")
    if f.dtype not in (np.float16, np.float32):
        raise ShapeError(f"field: expected float16 or float32, got {f.dtype}")
    if kernel not in (None, "fused", "blas"):
        raise InputError(f"kernel: expected 'fused', 'blas' or None, got {fmt_value(kernel)}")
    batched = np.ndim(weights) == 3
    w = normalize_weights(weights, f.shape[1], light_color)
    n_p, n_l, _ = f.shape
    active = np.flatnonzero(np.any(w != 0, axis=(0, 2)))
    if sparse is None:
        sparse = active.size <= SPARSE_FRACTION * n_l
    n_b = w.shape[0]
    if active.size == 0 or n_p == 0:
        out = np.zeros((n_b, n_p, 3), np.float32)
        return out if batched else out[0]
    W = block_weights(w, active if sparse else None)  # (3L', 3B)
    n_cols = W.shape[0]
    single = n_b == 1
    fused = _fused_kernel() if (kernel != "blas" and single and f.dtype == np.float16) else False
    if kernel == "fused" and not fused:
        raise InputError("kernel: 'fused' needs numba installed, one environment (L, 3) "
                         "weights and a float16 field")
    if single:
        Wc = [np.ascontiguousarray(W[:, c]) for c in range(3)]
        Wi = Wc[0] + Wc[1] + Wc[2]  # column j's weight for its own channel j mod 3
    per_chunk = FUSED_CHUNK_BYTES // (2 * n_cols) if fused else CHUNK_BYTES // (4 * n_cols)
    rows = int(chunk_rows or max(1, per_chunk))
    out = np.empty((n_p, 3 * n_b), np.float32)
    f2 = f.reshape(n_p, n_l * 3)

    def run(r0: int, buf: np.ndarray) -> None:
        r1 = min(n_p, r0 + rows)
        if sparse:
            src = f[r0:r1][:, active].reshape(r1 - r0, n_cols)
        else:
            src = f2[r0:r1]
        if fused:
            fused(np.asarray(src).view(np.uint16), Wc[0], Wc[1], Wc[2], out[r0:r1], Wi)
            return
        if src.dtype != np.float32:
            # float16 → float32, chunk-wise (never float16 arithmetic)
            src = _half_to_float32(np.ascontiguousarray(src), buf[: r1 - r0])
        with np.errstate(invalid="ignore"):  # NaN · 0 from masked samples: fixed up below
            if single:
                for c in range(3):
                    out[r0:r1, c] = src @ Wc[c]
            else:
                np.matmul(src, W, out=out[r0:r1])

    starts = list(range(0, n_p, rows))
    need_buf = f.dtype != np.float32 and not fused

    def new_buf() -> np.ndarray:
        return np.empty((min(rows, n_p), n_cols), np.float32)

    import contextlib

    # the fused kernel calls no BLAS: no thread-pool limit to set (≈ 0.1 ms a call)
    with contextlib.nullcontext() if fused else _blas_single_thread():
        if workers <= 1 or len(starts) < 2:
            buf = new_buf() if need_buf else None
            for r0 in starts:
                run(r0, buf)
        else:
            import threading
            from concurrent.futures import ThreadPoolExecutor

            local = threading.local()

            def task(r0: int) -> None:
                if need_buf and getattr(local, "buf", None) is None:
                    local.buf = new_buf()
                run(r0, getattr(local, "buf", None))

            with ThreadPoolExecutor(max_workers=int(workers)) as pool:
                for _ in pool.map(task, starts):
                    pass
    if not sparse:
        _recompute_nonfinite_rows(f, w, active, out)
    out = out.reshape(n_p, n_b, 3).transpose(1, 0, 2)
    return np.ascontiguousarray(out) if batched else np.ascontiguousarray(out[0])


def _recompute_nonfinite_rows(f: np.ndarray, w: np.ndarray, active: np.ndarray,
                              out: np.ndarray) -> None:
    """Redo rows of ``out`` ``(P, 3B)`` that came out NaN/inf from the lit lights only.

    A masked sample (NaN, or inf from float16 overflow) at an unlit light makes the dense sum
    NaN (NaN · 0); the row's true value uses the lit lights only. Rows still non-finite have a
    masked sample at a lit light and stay so. One flat pass over ``out``; the field rows are
    read again only for the (rare) bad rows.
    """
    ok = np.isfinite(out)
    if ok.all():  # the usual case, one flat pass (a per-row .all(axis=1) over 3 channels costs
        return  # ≈ 25 ns a row: ≈ 9 ms for the paper's 345,600 pixels, ≈ 6 % of a relight)
    bad = np.flatnonzero(~ok.all(axis=1))
    sub = np.asarray(f[bad][:, active], np.float64)  # (n_bad, L', 3)
    redo = np.einsum("plc,blc->pbc", sub, w[:, active])
    out[bad] = redo.reshape(bad.size, -1).astype(np.float32)


def relight_frames(frames: Iterable[tuple[int, np.ndarray]], weights: Any, n_lights: int, *,
                   light_color: Any = None,
                   progress: Callable[[int], None] | None = None) -> np.ndarray:
    """Relight from OLAT frames streamed one at a time (Eq. 4).

    Parameters
    ----------
    frames : iterable of (light index, (H, W, 3) float frame)
        Typically ``scan.iter_olat(camera, lights)`` restricted to the active lights.
    weights : (L, 3) float
        Eq. (4) weights (δA included).
    n_lights : int
    light_color : (3,) or (L, 3), optional
        See :func:`relight_field`.
    progress : callable(k), optional

    Returns
    -------
    (H, W, 3) float32
        ``Σ_l w_l ⊙ frame_l``, accumulated in float64 in the order of ``frames``.
    """
    w = normalize_weights(weights, n_lights, light_color)[0]
    acc = None
    seen = set()
    for k, (l, img) in enumerate(frames):
        l = int(l)
        if not 0 <= l < n_lights:
            raise InputError(f"frames: light index {l} outside [0, {n_lights})")
        if l in seen:
            raise InputError(f"frames: light {l} given twice")
        seen.add(l)
        img = np.asarray(img)
        if img.ndim != 3 or img.shape[-1] != 3:
            raise ShapeError(f"frames: light {l}: expected an (H, W, 3) frame, got {img.shape}")
        if acc is None:
            acc = np.zeros(img.shape, np.float64)
        elif img.shape != acc.shape:
            raise ShapeError(f"frames: light {l}: frame shape {img.shape} differs from the "
                             f"first frame's {acc.shape}")
        if np.any(w[l] != 0):
            acc += img * w[l]
        if progress:
            progress(k)
    if acc is None:
        raise InputError("frames: no OLAT frames given")
    return acc.astype(np.float32)


def relight_scan_view(scan, camera: str, weights: Any, *, normalize_color: bool = False,
                      progress: Callable[[int], None] | None = None,
                      read_ahead: int = 0, return_mask: bool = False):
    """Relight one camera of a scan from its OLAT frames, reading only lights with non-zero
    weight (Eq. 4).

    Parameters
    ----------
    scan : facegeo.capture.scan.Scan
    camera : str
    weights : (L, 3) float
        Eq. (4) weights for the scan's light stage (δA included).
    normalize_color : bool
        Divide by the rig's light colour (the frames then read as for a white light).
    progress : callable(k), optional
    read_ahead : int
        Threads reading the next frames meanwhile (``Scan.iter_olat(read_ahead=)``; what
        ``progress`` prints meanwhile reaches the terminal: image reads hide only native
        libraries' own failure messages).
    return_mask : bool
        Also return where the relit image can be trusted: False where a lit frame's pixel is
        untrusted (saturated or non-finite; black-clipped pixels count as measured dark
        values, as the projection reads them: ``Scan.olat_frame(black_clipped="dark")``).
        Such pixels are 0 in the image, and no error is raised for them.

    Returns
    -------
    (H, W, 3) float32, and with ``return_mask`` ``valid`` (H, W) bool

    Raises
    ------
    InputError
        A frame read holds NaN or infinite pixels (naming the first such file; the relit image
        is checked once, and only then are the frames read again to find it).
    """
    from facegeo.lighting.envmap import field_weights

    n_l = scan.n_lights
    w = normalize_weights(weights, n_l)[0]
    if normalize_color:  # each light's own colour (a list's per-light intensities)
        w = field_weights(w, scan.rig.lights)
    active = np.flatnonzero(np.any(w != 0, axis=1))
    cam = scan.camera(camera)
    valid = np.ones((cam.height, cam.width), bool)
    if active.size == 0:
        img = np.zeros((cam.height, cam.width, 3), np.float32)
        return (img, valid) if return_mask else img
    if return_mask:
        def frames():
            for l, frame, ok in scan.iter_olat(camera, active.tolist(), return_mask=True,
                                               read_ahead=read_ahead, black_clipped="dark"):
                ok = ok & np.isfinite(frame).all(axis=-1)
                valid[...] &= ok
                yield l, np.where(ok[..., None], frame, 0.0)
        img = relight_frames(frames(), w, n_l, progress=progress)
        img[~valid] = 0.0
        valid &= np.isfinite(img).all(axis=-1)  # an overflowing weight
        img[~valid] = 0.0
        return img, valid
    img = relight_frames(scan.iter_olat(camera, active.tolist(), read_ahead=read_ahead), w,
                         n_l, progress=progress)
    if not np.isfinite(img).all():
        _raise_first_nonfinite_frame(scan, camera, active)
    return img


def relight_scan_view_maps(scan, camera: str, weights: list, *,
                           progress: Callable[[int], None] | None = None,
                           read_ahead: int = 0) -> list[np.ndarray]:
    """One camera of a scan relit under a batch of environments (Eq. 4 per map), each OLAT
    frame read once: ``[(H, W, 3) float32 per map]``, normalised by the rig's light colour
    (:func:`relight_scan_view` with ``normalize_color=True``).

    One map is :func:`relight_scan_view`. Several: the frames lit by any map of the batch, each
    read once and added to every map lighting it, ``acc_b += frame · w_b[l]`` in float64 in
    light order — the arithmetic of :func:`relight_frames`, so each image is the same bytes as
    the map relit alone. Holds B float64 images (24 B a pixel and map). ``progress(k)`` after
    each frame read.

    Raises
    ------
    InputError
        A lit frame with a non-finite pixel (named), or weights that overflow float32.
    """
    from facegeo.lighting.envmap import field_weights

    if len(weights) == 1:
        return [relight_scan_view(scan, camera, weights[0], normalize_color=True,
                                  progress=progress, read_ahead=read_ahead)]
    n_l = scan.n_lights
    # each light's own colour, as relight_scan_view(normalize_color=True)
    W = [field_weights(normalize_weights(w, n_l)[0], scan.rig.lights) for w in weights]
    lit = np.stack([np.any(w != 0, axis=1) for w in W])  # (B, L)
    active = np.flatnonzero(lit.any(axis=0))
    acc: list = [None] * len(W)
    for k, (l, frame) in enumerate(scan.iter_olat(camera, active.tolist(),
                                                  read_ahead=read_ahead)):
        frame = np.asarray(frame)
        for b, w in enumerate(W):
            if lit[b, l]:
                if acc[b] is None:
                    acc[b] = np.zeros(frame.shape, np.float64)
                acc[b] += frame * w[l]
        if progress:
            progress(k)
    cam = scan.camera(camera)
    out = []
    for b, a in enumerate(acc):
        img = (np.zeros((cam.height, cam.width, 3), np.float32) if a is None
               else a.astype(np.float32))
        if not np.isfinite(img).all():
            _raise_first_nonfinite_frame(scan, camera, np.flatnonzero(lit[b]))
        out.append(img)
    return out


def _raise_first_nonfinite_frame(scan, camera: str, lights) -> None:
    """Raise an InputError naming the first of ``lights``' frames with a non-finite pixel."""
    for l, frame in scan.iter_olat(camera, [int(x) for x in lights]):
        bad = ~np.isfinite(frame).all(axis=-1)
        if bad.any():
            r, c = (int(x) for x in np.argwhere(bad)[0])
            raise InputError(
                f"{scan.olat_path(camera, l)}: {int(bad.sum())} pixel(s) are NaN or infinite "
                f"(first at row, col ({r}, {c})) (camera {camera!r}, light {l}); "
                f"`facegeo info {scan.root} --full` checks every frame")
    raise InputError(f"camera {camera!r}: the relit image is not finite (the weights or the "
                     f"light colour overflow float32)")


def tint_clothing(white: Any, black: Any, color: Any) -> np.ndarray:
    """Change the colour of the subject's clothing (Debevec et al. 2000 §3.3, Fig. 7).

    The indirect light the clothing reflects onto the face is the difference of a capture in
    white clothing and one in black clothing; tinted by the new clothing's reflectance and added
    back to the black-clothing capture::

        tinted = black + color ⊙ (white − black)

    Everything is linear in the light, so this applies equally to OLAT frames, reflectance
    fields ``(P, L, 3)`` or images relit from both fields (relight each, then tint, or tint the
    fields and relight once: the same result). ``color = (1, 1, 1)`` gives the white capture,
    ``(0, 0, 0)`` the black one. Deviation: nothing forces ``white − black ≥ 0`` (noise can make
    it slightly negative); the result is returned as computed, not clipped.

    Parameters
    ----------
    white, black : (..., 3) float arrays, same shape
        Linear radiance captured with white and with black clothing (same lighting and view).
    color : (3,) float
        Linear RGB reflectance of the new clothing relative to the white clothing, ≥ 0.

    Returns
    -------
    (..., 3) float32
    """
    w = as_array(white, "white", finite=False)  # masked (NaN) samples stay masked
    b = as_array(black, "black", finite=False)
    if w.shape != b.shape or w.ndim < 1 or w.shape[-1] != 3:
        raise ShapeError(f"white, black: expected two (..., 3) arrays of the same shape, got "
                         f"{w.shape} and {b.shape}")
    c = as_array(color, "color", shape=(3,))
    if np.any(c < 0):
        raise InputError(f"color: expected a reflectance ≥ 0 per channel, got {c.tolist()}")
    out = np.asarray(b, np.float64) + c * (np.asarray(w, np.float64) - np.asarray(b, np.float64))
    return out.astype(np.float32)
