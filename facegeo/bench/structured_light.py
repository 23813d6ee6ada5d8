"""Benchmark of Gray-code decoding against the read-once limit and a vectorised numpy reference.

Frames: a smooth camera → projector warp over a random albedo, 10 + 10 Gray bits with inverse
frames (40 float32 frames). Rows:

* ``facegeo decode_gray`` — throughput, the fraction of pixels not decoded to the true projector
  pixel, its ratio to the numpy reference (same frames, same thread count: both are
  single-threaded numpy) and its fraction of the **read-once limit**: the time to read every
  frame once at the memory bandwidth measured in the same run
  (:func:`facegeo.bench.read_bandwidth`), at 1 thread and at the machine's best. The
  limit at ``n`` threads is the strongest probe at ≤ ``n`` threads
  (:meth:`~facegeo.bench.Bandwidth.at_threads`): of a numpy sum, OpenBLAS ``sgemv``
  and — since it joined the probe, usually the strongest, up to 1.4× ``sgemv`` — the compiled
  pure read (:func:`facegeo.bench.pure_read_kernel`); the method that set it is in the
  read-once row's ``extra``. (Against ``sgemv`` alone the fractions were up to 1.4× higher.)
* ``numpy reference decode`` — :func:`reference_decode_gray`, the straightforward vectorised
  numpy decode a competent user would write: per bit, compare pattern vs inverse over the whole
  frame, Gray → binary by a running XOR, shift the bit into an int32 code. (Stacking all bits
  and using ``np.bitwise_xor.accumulate`` / ``np.packbits`` along the bit axis is also plain
  numpy, but measured ~4× slower here; the faster form is the fairer baseline.)
* ``cv2 getProjPixel, per-pixel Python loop`` — OpenCV's ``GrayCodePattern.getProjPixel``
  called once per pixel from Python on a random sample of pixels (8-bit copies of the frames),
  extrapolated to Mpx/s. OpenCV has no vectorised Gray decoder to a projector map (its
  ``decode`` yields stereo disparity), so this is the only OpenCV path for the job; it is
  reported for completeness, not as the headline baseline.
"""

from __future__ import annotations

import numpy as np

from facegeo.bench import BenchRow, best_of, read_bandwidth, register, repeats


def reference_decode_gray(frames, spec, min_contrast: float = 0.01):
    """Plain vectorised numpy Gray decode with inverse frames (the benchmark's baseline).

    Parameters
    ----------
    frames : mapping str -> (H, W) float array
        ``gray_{axis}_{i:02d}`` and ``gray_{axis}_{i:02d}_inv`` frames, MSB first.
    spec : facegeo.geometry.structured_light.PatternSpec
        One code per projector pixel (full ``n_bits``), ``inverse=True``.
    min_contrast : float, frame units
        Pixels whose smallest ``|pattern - inverse|`` is below this are invalid.

    Returns
    -------
    proj_x, proj_y : (H, W) float64, projector pixel (NaN where invalid)
    valid : (H, W) bool
    """
    codes = {}
    valid = None
    for axis in ("x", "y"):
        n = spec.n_bits(axis)
        first = frames[f"gray_{axis}_00"]
        code = np.zeros(first.shape, dtype=np.int32)
        binary = np.zeros(first.shape, dtype=bool)
        contrast = np.full(first.shape, np.inf, dtype=np.float32)
        for i in range(n):  # MSB first; vectorised over all pixels
            diff = frames[f"gray_{axis}_{i:02d}"] - frames[f"gray_{axis}_{i:02d}_inv"]
            binary ^= diff > 0  # Gray → binary: b_i = b_{i-1} XOR g_i
            code = (code << 1) | binary  # pack the bits
            contrast = np.minimum(contrast, np.abs(diff))
        size = spec.width if axis == "x" else spec.height
        ok = (contrast >= min_contrast) & (code < size)
        valid = ok if valid is None else valid & ok
        codes[axis] = code
    proj_x = np.where(valid, codes["x"], np.nan)
    proj_y = np.where(valid, codes["y"], np.nan)
    return proj_x, proj_y, valid


def _frames(w: int, h: int, spec):
    from facegeo.geometry.structured_light import pattern_names, pattern_value_at

    rng = np.random.default_rng(0)
    # a smooth camera → projector warp, so every projector code appears
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    qx = 20 + xx * (980 / w) + 6 * np.sin(yy / 90)
    qy = 15 + yy * (740 / h) + 5 * np.sin(xx / 70)
    q = np.stack([qx, qy], -1)
    albedo = 0.3 + 0.6 * rng.random((h, w))
    names = [n for n in pattern_names(spec) if n.split("_")[0] in spec.codes]
    frames = {n: (albedo * pattern_value_at(spec, n, q)).astype(np.float32) for n in names}
    return frames, names, np.floor(qx + 0.5), np.floor(qy + 0.5), rng


@register("structured_light.decode_gray")
def bench_decode_gray(quick: bool) -> list[BenchRow]:
    import cv2

    from facegeo.geometry.structured_light import PatternSpec, decode_gray

    w, h = (320, 256) if quick else (1280, 1024)
    repeat = 2 if quick else 3
    spec = PatternSpec(width=1024, height=768, white_black=False)
    frames, names, truth_x, truth_y, rng = _frames(w, h, spec)
    nbytes = sum(frames[n].nbytes for n in names)
    bw = read_bandwidth()

    def wrong_fraction(px, py, valid):
        return float(np.mean((px != truth_x) | (py != truth_y) | ~valid))

    t, dec = best_of(lambda: decode_gray(frames, spec), repeat)
    t_ref, (rx, ry, rvalid) = best_of(lambda: reference_decode_gray(frames, spec), repeat)
    mpx = w * h / t / 1e6
    ref_mpx = w * h / t_ref / 1e6
    limit_1 = w * h / bw.read_once_seconds(nbytes, threads=1) / 1e6
    limit_all = w * h / bw.read_once_seconds(nbytes) / 1e6
    differ = float(np.mean((rvalid != dec.valid) | (rvalid & ((rx != dec.proj_x) | (ry != dec.proj_y)))))
    size = {"pixels": f"{w}x{h}", "frames": len(names), "MB read once": round(nbytes / 1e6, 1)}
    rows = [
        BenchRow(
            "structured_light.decode_gray", "facegeo decode_gray (vectorised numpy, row chunks)",
            mpx, "Mpx/s", wrong_fraction(dec.proj_x, dec.proj_y, dec.valid),
            "fraction of pixels not decoded to the true projector pixel",
            ratios={
                "vs numpy reference decode": mpx / ref_mpx,
                "of read-once limit at 1-thread bandwidth": mpx / limit_1,
                f"of read-once limit at best bandwidth ({bw.method})": mpx / limit_all,
            },
            extra={**size, "ms": round(1e3 * t, 2),
                   "pixels differing from numpy reference": differ},
            threads=1,
            baseline_threads={
                "vs numpy reference decode": 1,
                "of read-once limit at 1-thread bandwidth": 1,
                f"of read-once limit at best bandwidth ({bw.method})": bw.threads,
            },
        ),
        BenchRow(
            "structured_light.decode_gray",
            "numpy reference decode (per bit: pattern > inverse, running XOR, shift into code)",
            ref_mpx, "Mpx/s", wrong_fraction(rx, ry, rvalid),
            "fraction of pixels not decoded to the true projector pixel",
            extra={**size, "ms": round(1e3 * t_ref, 2)}, threads=1,
        ),
        BenchRow(
            "structured_light.decode_gray",
            "read-once limit: frames read once at the bandwidth measured in this run",
            limit_1, "Mpx/s",
            extra={"1-thread GB/s": round(bw.at_threads(1), 2),
                   "1-thread method": bw.method_at(1),
                   "best GB/s": round(bw.gbps, 2), "best method": bw.method,
                   "Mpx/s at best": round(limit_all, 1)},
            threads=1,
        ),
    ]
    # OpenCV's per-pixel decoder on a random sample of pixels (~10 µs a pixel), extrapolated.
    gc = cv2.structured_light.GrayCodePattern.create(spec.width, spec.height)
    imgs = [np.clip(frames[n] * 255, 0, 255).astype(np.uint8) for n in names]
    pix = rng.integers(0, [w, h], size=(200 if quick else 2000, 2))

    def run_cv():
        out = []
        for x, y in pix:
            err, p = gc.getProjPixel(imgs, int(x), int(y))
            out.append(p if not err else (-1, -1))
        return np.array(out)

    t_cv, cv_pts = best_of(run_cv, 1)
    cv_mpx = len(pix) / t_cv / 1e6
    agree = float(np.mean((cv_pts[:, 0] == dec.proj_x[pix[:, 1], pix[:, 0]])
                          & (cv_pts[:, 1] == dec.proj_y[pix[:, 1], pix[:, 0]])))
    rows.append(
        BenchRow(
            "structured_light.decode_gray",
            f"cv2 GrayCodePattern.getProjPixel, per-pixel Python loop, {len(pix)} sampled "
            "pixels, extrapolated",
            cv_mpx, "Mpx/s", 1 - agree, "fraction of sampled pixels disagreeing with facegeo",
            ratios={"facegeo decode_gray vs this": mpx / cv_mpx},
            extra={"frames": "8-bit copies"}, threads=1,
            baseline_threads={"facegeo decode_gray vs this": 1},
        )
    )
    return rows


@register("structured_light.decode_stream")
def bench_decode_stream(quick: bool) -> list[BenchRow]:
    """Streaming decode (:func:`facegeo.geometry.structured_light.decode_stream`).

    Frames: the warp of :func:`_frames`, white / black + 10 + 10 Gray bits with inverses
    (42 frames), as 8-bit RGB (what a camera delivers). Rows:

    * in memory (a mapping: every frame held, so the pairs are folded tile-major in one
      group), at 1 thread and at ``NUMBA_NUM_THREADS`` (``decode_frames(threads=...)``: the
      tiles of the pair kernel and the chunks of the finish share the threads) — throughput,
      the fraction of pixels not decoded to the true projector pixel, its fraction of the
      **read-once limit** at the bandwidth of the same thread count, and (1 thread) its ratio to
      :func:`reference_decode_gray` (single-threaded numpy) run on the same frames already
      reduced to float32 luminance (the reference does less: no per-bit reliability, no
      luminance conversion, no statistics);
    * streamed (a generator, 1 thread): the frame-by-frame path, what a camera feeds;
    * the long-run code (``codes=("minsw",)``, the same warp, 10 + 10 bits, in memory, 1
      thread): decoded through its code → stripe table (docs/structured-light.md), its time
      against the Gray decode's in the same run;
    * the read-once limit: the bytes of the frames as they sit in memory (42 × H × W × 3
      bytes of 8-bit RGB) read once at the 1-thread bandwidth measured in the same run
      (:meth:`~facegeo.bench.Bandwidth.at_threads`: the strongest of numpy sum,
      ``sgemv`` and the compiled pure read at ≤ that thread count, usually the pure read; the
      method that set it and the best bandwidth in ``extra``);
    * end to end from files — the frames written as PNG, then read one at a
      time (``cv2.imread``) and streamed into the decoder; the read alone is timed separately,
      so the decode's share of the wall time is visible.
    """
    import functools
    import tempfile
    import time
    from pathlib import Path

    import cv2

    from facegeo.fsutil import read_ahead
    from facegeo.geometry._sl_stream import decode_frames
    from facegeo.geometry.structured_light import (
        PatternSpec,
        decode_stream,
        pattern_names,
    )

    w, h = (320, 256) if quick else (1280, 1024)
    repeat = 2 if quick else 3
    spec = PatternSpec(width=1024, height=768)
    names = pattern_names(spec)
    gray_frames, gnames, truth_x, truth_y, _ = _frames(w, h, spec)

    def as_rgb(frames, names):
        out = {}
        for n in names:
            f = frames.get(n)
            if f is None:  # white / black
                f = np.full((h, w), 1.0 if n == "white" else 0.0, np.float32) * 0.9
            u8 = np.clip(np.rint(f * 255), 0, 255).astype(np.uint8)
            out[n] = np.repeat(u8[..., None], 3, axis=2)
        return out

    rgb = as_rgb(gray_frames, names)
    lum = {n: (rgb[n].mean(axis=2, dtype=np.float32) / 255.0) for n in gnames}
    nbytes = sum(a.nbytes for a in rgb.values())  # the frames as they sit in memory
    bw = read_bandwidth()

    def wrong(px, py, valid):
        return float(np.mean((np.floor(px + 0.5) != truth_x) | (np.floor(py + 0.5) != truth_y)
                             | ~valid))

    import numba

    t_ref, (rx, ry, rv) = best_of(lambda: reference_decode_gray(lum, spec), repeat)
    ref_mpx = w * h / t_ref / 1e6
    size = {"pixels": f"{w}x{h}", "frames": len(names),
            "MB read once (8-bit RGB as in memory)": round(nbytes / 1e6, 1)}
    limit_1 = w * h / bw.read_once_seconds(nbytes, threads=1) / 1e6
    limit_all = w * h / bw.read_once_seconds(nbytes) / 1e6
    def cpu_ms(fn):  # CPU seconds of the process (all threads), best of ``repeat``: less
        # sensitive than wall time to other jobs on a shared machine
        best = float("inf")
        for _ in range(repeats(repeat)):
            c0 = time.process_time()
            fn()
            best = min(best, time.process_time() - c0)
        return round(1e3 * best, 1)

    def best_with_faults(fn, n):  # best_of, and the minor page faults of the best run
        import resource

        best = (float("inf"), None, 0)
        for _ in range(repeats(n)):
            f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            t0 = time.perf_counter()
            out = fn()
            dt = time.perf_counter() - t0
            if dt < best[0]:
                best = (dt, out, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
        return best

    runs, cpu, faults = {}, {}, {}
    cpu_ref = cpu_ms(lambda: reference_decode_gray(lum, spec))
    for nt in sorted({1, numba.config.NUMBA_NUM_THREADS}):
        # a mapping: every frame is held, one tile-major group over all of them
        # (decode_frames: decode_stream's implementation, with its thread count). One call
        # first (compiled code loaded, buffers made); the best of the rest, whose page faults
        # are reported: a run that writes its ≈ 47 MB of outputs to pages the process has
        # not touched yet pays ≈ 2 µs a 4 KB page here (a virtual machine), ≈ 12 ms
        held = lambda: decode_frames(rgb, spec, threads=nt)
        held()
        t_nt, res_nt, faults[nt] = best_with_faults(held, repeat + 2)
        runs[nt] = (t_nt, res_nt)
        cpu[nt] = cpu_ms(held)
    # beside the read-once limit, the physical floor with the outputs: the frames read once plus
    # the decode's output planes written once (memset into pages already touched, best of 3)
    def write_outputs_once(res):  # seconds, bytes
        planes = [np.empty_like(getattr(res, k)) for k in
                  ("x", "y", "sigma_x", "sigma_y", "confidence", "direct", "global_", "lit",
                   "valid", "valid_x", "valid_y", "shadow")]
        fill = lambda: [a.fill(0) for a in planes]
        fill()  # the pages touched
        return best_of(fill, repeat)[0], sum(a.nbytes for a in planes)

    t_write, out_bytes = write_outputs_once(runs[1][1])
    t_rw = bw.read_once_seconds(nbytes, threads=1) + t_write
    limit_rw = w * h / t_rw / 1e6
    # a generator: the streaming path, frame by frame (what a camera feeds)
    streamed = lambda: decode_stream(((n, a) for n, a in rgb.items()), spec)
    t_s, res_s = best_of(streamed, repeat)
    cpu_s = cpu_ms(streamed)
    # the long-run code, same warp and bit counts, frames in memory, 1 thread
    mspec = PatternSpec(width=1024, height=768, codes=("minsw",))
    m_frames = _frames(w, h, mspec)[0]
    m_rgb = as_rgb(m_frames, pattern_names(mspec))
    del m_frames
    minsw = functools.partial(decode_frames, m_rgb, mspec, threads=1)
    t_m, res_m = best_of(minsw, repeat)
    cpu_m = cpu_ms(minsw)
    del minsw, m_rgb  # 165 MB of frames
    rows = []
    for nt, (t, res) in runs.items():
        mpx = w * h / t / 1e6
        # ratios only against baselines at the same thread count (docs/benchmarks.md)
        limit_nt = w * h / bw.read_once_seconds(nbytes, threads=nt) / 1e6
        ratios = {f"of read-once limit at {nt}-thread bandwidth": mpx / limit_nt}
        if nt == 1:
            ratios = {"vs numpy reference decode (float32 luminance given)": mpx / ref_mpx,
                      **ratios, "of read-once + write-outputs-once limit": mpx / limit_rw}
        rows.append(BenchRow(
            "structured_light.decode_stream",
            f"facegeo decode_stream, frames in memory (8-bit RGB, tile-major), {nt} thread"
            + ("s" if nt > 1 else ""), mpx, "Mpx/s", wrong(res.x, res.y, res.valid),
            "fraction of pixels not decoded to the true projector pixel", ratios=ratios,
            extra={**size, "ms": round(1e3 * t, 1), "CPU ms (all threads)": cpu[nt],
                   "minor page faults (best run)": faults[nt],
                   f"{nt}-thread GB/s": round(bw.at_threads(nt), 2),
                   f"{nt}-thread method": bw.method_at(nt)}, threads=nt,
            baseline_threads={k: nt if "read-once" in k else 1 for k in ratios}))
    mpx_s = w * h / t_s / 1e6
    mpx_m = w * h / t_m / 1e6
    rows += [
        BenchRow("structured_light.decode_stream",
                 "facegeo decode_stream, long-run (minsw) code through its code -> stripe table, "
                 "frames in memory, 1 thread", mpx_m, "Mpx/s",
                 wrong(res_m.x, res_m.y, res_m.valid),
                 "fraction of pixels not decoded to the true projector pixel",
                 ratios={"vs the Gray decode in memory (same run)": runs[1][0] / t_m},
                 extra={**size, "ms": round(1e3 * t_m, 1), "CPU ms": cpu_m}, threads=1,
                 baseline_threads={"vs the Gray decode in memory (same run)": 1}),
        BenchRow("structured_light.decode_stream",
                 "facegeo decode_stream, frames streamed one at a time (generator), 1 thread",
                 mpx_s, "Mpx/s", wrong(res_s.x, res_s.y, res_s.valid),
                 "fraction of pixels not decoded to the true projector pixel",
                 ratios={"of read-once limit at 1-thread bandwidth": mpx_s / limit_1},
                 extra={**size, "ms": round(1e3 * t_s, 1), "CPU ms": cpu_s}, threads=1,
                 baseline_threads={"of read-once limit at 1-thread bandwidth": 1}),
        BenchRow("structured_light.decode_stream", "numpy reference decode on float32 luminance",
                 ref_mpx, "Mpx/s", wrong(rx, ry, rv),
                 "fraction of pixels not decoded to the true projector pixel",
                 extra={**size, "ms": round(1e3 * t_ref, 1), "CPU ms": cpu_ref}, threads=1),
        BenchRow("structured_light.decode_stream",
                 f"read-once + write-outputs-once limit: the frames read once at the 1-thread "
                 f"bandwidth and the decode's {out_bytes / 1e6:.0f} MB of output planes written "
                 "once (memset, pages already touched), measured in this run", limit_rw,
                 "Mpx/s", extra={**size, "ms reading": round(1e3 * (t_rw - t_write), 2),
                                 "ms writing": round(1e3 * t_write, 2),
                                 "output MB": round(out_bytes / 1e6, 1)}, threads=1),
        BenchRow("structured_light.decode_stream",
                 f"read-once limit: the {len(names)} 8-bit RGB frames as they sit in memory "
                 f"({nbytes / 1e6:.0f} MB), read once at the 1-thread bandwidth measured in this "
                 "run", limit_1, "Mpx/s",
                 extra={**size, "1-thread GB/s": round(bw.at_threads(1), 2),
                        "1-thread method": bw.method_at(1),
                        "best GB/s": round(bw.gbps, 2), "best method": bw.method,
                        "Mpx/s at best": round(limit_all, 1)}, threads=1),
    ]
    with tempfile.TemporaryDirectory(prefix="facegeo-bench-sl-") as d:
        paths = {}
        for n, a in rgb.items():
            paths[n] = Path(d) / f"{n}.png"
            cv2.imwrite(str(paths[n]), a)

        def read_only():
            return sum(int(cv2.imread(str(p)).shape[0]) for p in paths.values())

        def end_to_end():
            return decode_stream(((n, cv2.imread(str(p))[..., ::-1]) for n, p in paths.items()),
                                 spec)

        def end_to_end_ahead():  # as the decode stage reads: the next PNGs decoded meanwhile
            return decode_stream(read_ahead(lambda n: (n, cv2.imread(str(paths[n]))[..., ::-1]),
                                            list(paths), workers=2), spec)

        t_read, _ = best_of(read_only, 1 if quick else 2)
        t_e2e, res2 = best_of(end_to_end, 1 if quick else 2)
        t_ahead, res3 = best_of(end_to_end_ahead, 1 if quick else 2)
    rows.append(BenchRow(
        "structured_light.decode_stream", "facegeo decode_stream end to end from PNG files",
        w * h / t_e2e / 1e6, "Mpx/s", wrong(res2.x, res2.y, res2.valid),
        "fraction of pixels not decoded to the true projector pixel",
        extra={**size, "ms": round(1e3 * t_e2e, 1), "ms reading PNGs alone": round(1e3 * t_read, 1),
               "decode share of wall time": round(1 - t_read / t_e2e, 3)},
        threads=1))
    rows.append(BenchRow(
        "structured_light.decode_stream",
        "facegeo decode_stream end to end from PNG files, two threads reading ahead "
        "(fsutil.read_ahead, as the decode stage reads)",
        w * h / t_ahead / 1e6, "Mpx/s", wrong(res3.x, res3.y, res3.valid),
        "fraction of pixels not decoded to the true projector pixel",
        ratios={"vs reading in turn (row above)": t_e2e / t_ahead},
        extra={**size, "ms": round(1e3 * t_ahead, 1)}, threads=2,
        baseline_threads={"vs reading in turn (row above)": 1}))
    return rows
