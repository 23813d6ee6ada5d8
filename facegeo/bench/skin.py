"""Benchmarks of facegeo.appearance.skin (Debevec et al. 2000 §4): reflectance functions fitted
per second at 2048 lights (the paper's 64 × 32 grid), resynthesis per second, and the
coarse-to-fine search depth against the error it buys.

Data are paper-mode functions (:func:`facegeo.appearance.skin.paper_reflectance`, the model
that is fitted, so the error column is the fit's own error, not a model mismatch) on random
normals within 25° of the view; the known d_0 is passed so that α errors are meaningful. The
``generator BRDF`` rows fit the generator's own mismatched skin BRDF
(:func:`facegeo.appearance.brdf.synthetic_skin_brdf`, what the fit stage sees; d_0 estimated,
and the chromaticity polish runs on every function) on normals within 40°.
Fits run in the default chunks (64 functions at 2048 lights, ``skin.CHUNK_SAMPLES``) with the
compiled kernels (``_skin_kernels``) on the stated threads (``threads=2``: two workers, each
fitting whole chunks); the numpy reference (``_skin_fit.KERNELS = False``, the implementation
before them) is timed in the same run at the same threads. The machine is shared, so compare
rows of one run; rows also record the process CPU time (``cpu functions/s``, all threads),
which other jobs' load inflates less than wall time.

The generator rows also time the fit with the ramp on all 2048 lights
(``SearchDepth(sample_lights=0)``, the fit before the light subsample) back to back, as a
ratio and its error.

The ``skin.fit_scale`` benchmark times one ``fit_reflectance`` call on 20,480 generator functions (the
512 repeated 40 times; 4,096 with ``--quick``) at two threads, wall and CPU time, the cores it
kept busy (peak memory in the row's own column): the paper preset's 200 k texels per camera are
10× this case, not 400× the 512-function rows (whose per-function CPU time does not hold at
scale: page faults on the outputs, allocator churn, the chunk tail at two threads). Its
``200k functions, s`` column is 10 × its wall time — measured, at the run's load.
``skin.fit_stream`` times the fit stage's own loop (:func:`facegeo.pipeline.fit.fit_chunks`:
float16 field memory map in, D to a float16 store) on 200,704 functions, beside the same
functions' in-cache rate measured in the run.
"""

from __future__ import annotations

import time

import numpy as np

from facegeo.bench import BenchRow, best_of, one_blas_thread, register


def _case(n: int, seed: int, n_theta: int = 64, n_phi: int = 32):
    from facegeo.appearance import skin

    rng = np.random.default_rng(seed)
    lights = skin.LightSet.from_grid(n_theta, n_phi)
    ang = np.radians(rng.uniform(0, 25, n))
    az = rng.uniform(0, 2 * np.pi, n)
    nrm = np.stack([np.sin(ang) * np.cos(az), np.sin(ang) * np.sin(az), np.cos(ang)], 1)
    chroma = skin.normalize(np.array([0.8, 0.5, 0.35]) + rng.normal(0, 0.05, (n, 3)))
    p = skin.SkinParams(rng.uniform(0.3, 0.7, (n, 1)) * chroma, rng.uniform(0.2, 0.4, n),
                        rng.uniform(-0.5, -0.2, n), rng.uniform(0.3, 0.8, n),
                        rng.uniform(0.3, 0.45, n))
    v0 = np.array([0.0, 0.0, 1.0])
    return lights, nrm, p, v0, skin.paper_reflectance(nrm, v0, lights, p)


def _errors(fit, nrm, p):
    ang = np.degrees(np.arccos(np.clip(np.sum(fit.normal * nrm, 1), -1, 1)))
    return {
        "normal median error, deg": float(np.median(ang)),
        "normal max error, deg": float(np.max(ang)),
        "alpha_0 max rel error": float(np.max(np.abs(fit.alpha_0 / p.alpha_0 - 1))),
        "rho_s median rel error": float(np.median(np.abs(fit.rho_s / p.rho_s - 1))),
        "moment normal median error, deg": float(np.median(np.degrees(np.arccos(
            np.clip(np.sum(fit.normal_moment * nrm, 1), -1, 1))))),
    }


def _generator_case(n: int, seed: int, n_theta: int = 64, n_phi: int = 32):
    """The generator's mismatched skin BRDF (diffuse colour blend + Torrance–Sparrow) as OLAT
    functions under unit distant lights, random normals within 40° of the view."""
    from facegeo.appearance import skin
    from facegeo.appearance.brdf import desaturate, synthetic_skin_brdf

    rng = np.random.default_rng(seed)
    lights = skin.LightSet.from_grid(n_theta, n_phi)
    ang = np.radians(rng.uniform(0, 40, n))
    az = rng.uniform(0, 2 * np.pi, n)
    nrm = np.stack([np.sin(ang) * np.cos(az), np.sin(ang) * np.sin(az), np.cos(ang)], 1)
    a0 = np.array([0.62, 0.36, 0.26]) * rng.uniform(0.8, 1.1, (n, 1))
    a1 = desaturate(a0, rng.uniform(0.3, 0.6, n)) * 1.1
    v0 = np.array([0.0, 0.0, 1.0])
    sh = (n, lights.n_lights, 3)
    f = synthetic_skin_brdf(np.broadcast_to(nrm[:, None], sh),
                            np.broadcast_to(lights.directions[None], sh),
                            np.broadcast_to(v0, sh), a0[:, None], a1[:, None],
                            rng.uniform(0.4, 0.9, (n, 1)), rng.uniform(0.25, 0.5, (n, 1)))
    R = (f * np.maximum(nrm @ lights.directions.T, 0.0)[..., None]).astype(np.float32)
    return lights, nrm, v0, R


@register("skin.fit")
@one_blas_thread
def bench_fit(quick: bool) -> list[BenchRow]:
    import numba

    from facegeo.appearance import _skin_fit, skin

    n = 128 if quick else 512
    lights, nrm, p, v0, R = _case(n, 1)
    d0 = skin.normalize(p.rho_d)
    g_lights, g_nrm, g_v0, g_R = _generator_case(n, 3)
    # compile / load the kernels' cache, for both paths (the d_0 estimate has its own kernel)
    skin.fit_reflectance(R[:4], v0, lights, d_0=d0[:4])
    skin.fit_reflectance(R[:4], v0, lights)
    cores = min(2, numba.config.NUMBA_NUM_THREADS)
    minutes = "paper preset 200k texels, extrapolated minutes"

    def fit(depth=None, threads=1, known=True, generator=False):
        """(seconds, fit, CPU functions/s) of one timed fit."""
        c = time.process_time()
        if generator:
            t, out = best_of(lambda: skin.fit_reflectance(g_R, g_v0, g_lights, depth=depth,
                                                          threads=threads), repeat=1)
        else:
            t, out = best_of(lambda: skin.fit_reflectance(
                R, v0, lights, d_0=d0 if known else None, depth=depth, threads=threads),
                repeat=1)
        return t, out, n / max(time.process_time() - c, 1e-9)

    def reference(threads):
        # the numpy reference (the implementation before the compiled kernels), same process
        _skin_fit.KERNELS = False
        try:
            return fit(threads=threads)
        finally:
            _skin_fit.KERNELS = True

    t_ref, fit_ref, cpu_ref = reference(1)
    rows = []
    for levels, polish in ((4, 3), (7, 6), (10, 10), (14, 20)):
        depth = skin.SearchDepth(levels=levels, alpha_levels=min(levels, 4), polish=polish)
        t, res, cpu = fit(depth)
        e = _errors(res, nrm, p)
        default = depth == skin.SearchDepth()
        rows.append(BenchRow(
            "skin.fit", f"fit_reflectance, 2048 lights, depth {levels} levels + {polish} LM"
            + (" (default)" if default else ""),
            n / t, "functions/s", error=e["normal median error, deg"],
            error_unit="median normal error, degrees (paper mode)", threads=1,
            ratios={"vs numpy reference": t_ref / t} if default else {},
            baseline_threads={"vs numpy reference": 1} if default else {},
            extra={**e, "n": n, "seconds": t, "cpu functions/s": cpu,
                   minutes: 200_000 / (n / t) / 60},
        ))
    e = _errors(fit_ref, nrm, p)
    rows.append(BenchRow(
        "skin.fit", "fit_reflectance, numpy reference (KERNELS off), default depth",
        n / t_ref, "functions/s", error=e["normal median error, deg"],
        error_unit="median normal error, degrees (paper mode)", threads=1,
        extra={**e, "n": n, "seconds": t_ref, "cpu functions/s": cpu_ref}))
    if cores >= 2:
        # both cores for the fit: whole chunks on two workers; against one thread and the
        # numpy reference on two workers, timed back to back
        t2, res, cpu2 = fit(threads=cores)
        t1, _, _ = fit(threads=1)
        t_ref2, _, _ = reference(cores)
        e = _errors(res, nrm, p)
        rows.append(BenchRow(
            "skin.fit", f"fit_reflectance, 2048 lights, default depth, {cores} threads",
            n / t2, "functions/s", error=e["normal median error, deg"],
            error_unit="median normal error, degrees (paper mode)", threads=cores,
            ratios={"vs 1 thread": t1 / t2, "vs numpy reference": t_ref2 / t2},
            baseline_threads={"vs 1 thread": 1, "vs numpy reference": cores},
            extra={**e, "n": n, "seconds": t2, "cpu functions/s": cpu2,
                   minutes: 200_000 / (n / t2) / 60}))
    t, res, cpu = fit(known=False)
    e = _errors(res, nrm, p)
    rows.append(BenchRow(
        "skin.fit", "fit_reflectance, 2048 lights, default depth, d_0 from median ratios",
        n / t, "functions/s", error=e["normal median error, deg"],
        error_unit="median normal error, degrees (paper mode)", threads=1,
        extra={**e, "n": n, "cpu functions/s": cpu, minutes: 200_000 / (n / t) / 60}))
    # the ramp on all 2048 lights (the fit before issue 13's fourth round), back to back
    every = skin.SearchDepth(sample_lights=0)
    for threads in (1, cores) if cores >= 2 else (1,):
        t_all, res_all, cpu_all = fit(every, threads=threads, generator=True)
        t, res, cpu = fit(threads=threads, generator=True)
        ang = np.degrees(np.arccos(np.clip(np.sum(res.normal * g_nrm, 1), -1, 1)))
        ang_all = np.degrees(np.arccos(np.clip(np.sum(res_all.normal * g_nrm, 1), -1, 1)))
        rows.append(BenchRow(
            "skin.fit", f"fit_reflectance, 2048 lights, generator BRDF (mismatched), default "
            f"depth, {threads} thread{'s' if threads > 1 else ''}", n / t, "functions/s",
            error=float(np.median(ang)),
            error_unit="median normal error, degrees (generator BRDF, d_0 estimated)",
            threads=threads,
            ratios={"vs the ramp on all lights (sample_lights=0)": t_all / t},
            baseline_threads={"vs the ramp on all lights (sample_lights=0)": threads},
            extra={"n": n, "seconds": t, "cpu functions/s": cpu,
                   "specular share of the energy": float(res.specular.sum() / g_R.sum()),
                   "all lights: functions/s": n / t_all, "all lights: cpu functions/s": cpu_all,
                   "all lights: median normal error, deg": float(np.median(ang_all)),
                   minutes: 200_000 / (n / t) / 60}))
    return rows


@register("skin.fit_scale")
@one_blas_thread
def bench_fit_scale(quick: bool) -> list[BenchRow]:
    """One ``fit_reflectance`` call on 40 copies of 512 generator functions (8 with
    ``quick``; every function fitted in full: nothing is reused between copies), two threads,
    wall and process CPU time. Its own benchmark, so that its peak memory (≈ 2 GB: R, D and S
    of 20 k functions) is not charged to the small rows."""
    import resource

    import numba

    from facegeo.appearance import skin

    threads = min(2, numba.config.NUMBA_NUM_THREADS)
    lights, nrm, v0, R = _generator_case(512, 3)
    skin.fit_reflectance(R[:4], v0, lights, threads=threads)  # compile / load the kernels
    reps = 8 if quick else 40
    big = np.concatenate([R] * reps)
    n = big.shape[0]
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    fit = skin.fit_reflectance(big, v0, lights, threads=threads)
    t = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    user, sys_ = r1.ru_utime - r0.ru_utime, r1.ru_stime - r0.ru_stime
    cpu = user + sys_
    k = R.shape[0]
    ang = np.degrees(np.arccos(np.clip(np.sum(fit.normal[:k] * nrm, 1), -1, 1)))
    same = all(np.array_equal(fit.normal[i * k:(i + 1) * k], fit.normal[:k]) for i in range(reps))
    return [BenchRow(
        "skin.fit_scale", f"fit_reflectance at scale: {n} generator-BRDF functions in one call, 2048 "
        f"lights, default depth, {threads} threads", n / t, "functions/s",
        error=float(np.median(ang)),
        error_unit="median normal error, degrees (generator BRDF, d_0 estimated)",
        threads=threads,
        extra={"n": n, "seconds": t, "cpu seconds": cpu, "system cpu seconds": sys_,
               "cpu functions/s": n / cpu, "cores busy (cpu s / wall s)": cpu / t,
               f"200k functions, s ({200_000 / n:.3g} x this row's wall; measured, at this load)":
                   200_000 / (n / t),
               "copies fitted identically": same})]


@register("skin.fit_stream")
@one_blas_thread
def bench_fit_stream(quick: bool) -> list[BenchRow]:
    """The fit stage's own loop (:func:`facegeo.pipeline.fit.fit_chunks`) on the paper preset's
    per-camera size: 200,704 generator functions (98 copies of 2,048; 2 with ``quick``)
    stored as a float16 field memory map on disk, as the project stage writes it, fitted in
    chunks of 2,048 on two threads into a ``FitWriter`` (D float16 on disk). Beside it, the
    same functions' in-cache rate (the 2,048 fitted in one call, repeated): the limit a
    stream of them can approach, all reading and writing removed."""
    import resource
    import tempfile
    from pathlib import Path

    import numba

    from facegeo.appearance import skin
    from facegeo.pipeline.fit import fit_chunks
    from facegeo.render import FitWriter

    threads = min(2, numba.config.NUMBA_NUM_THREADS)
    base = 2048
    lights, nrm, v0, R = _generator_case(base, 3)
    skin.fit_reflectance(R[:4], v0, lights, threads=threads)  # compile / load the kernels
    reps = 2 if quick else 98
    n = base * reps
    R16 = R.astype(np.float16)
    R32 = R16.astype(np.float32)  # the values the stream fits
    t_cache, _ = best_of(lambda: skin.fit_reflectance(R32, v0, lights, threads=threads), 2)
    with tempfile.TemporaryDirectory(prefix="facegeo-bench-") as tmp:
        field = np.lib.format.open_memmap(Path(tmp) / "R.npy", mode="w+", dtype=np.float16,
                                          shape=(n, lights.n_lights, 3))
        for i in range(reps):
            field[i * base:(i + 1) * base] = R16
        field.flush()
        del field
        field = np.load(Path(tmp) / "R.npy", mmap_mode="r")
        v_world = np.broadcast_to(v0, (n, 3))
        rows = np.arange(n)
        writer = FitWriter(Path(tmp) / "cam", n, lights.n_lights, 3, "float16")
        r0 = resource.getrusage(resource.RUSAGE_SELF)
        t0 = time.perf_counter()
        normals = [fit.normal.copy() for _, fit, _ in fit_chunks(
            field, rows, v_world, lights, writer, rows, chunk=base, threads=threads)]
        writer.close()
        t = time.perf_counter() - t0
        r1 = resource.getrusage(resource.RUSAGE_SELF)
    user, sys_ = r1.ru_utime - r0.ru_utime, r1.ru_stime - r0.ru_stime
    cpu = user + sys_
    normal = np.concatenate(normals)
    ang = np.degrees(np.arccos(np.clip(np.sum(normal[:base] * nrm, 1), -1, 1)))
    same = all(np.array_equal(normal[i * base:(i + 1) * base], normal[:base])
               for i in range(reps))
    rate = n / t
    return [BenchRow(
        "skin.fit_stream", f"the fit stage's loop: {n} generator-BRDF functions from a float16 "
        f"field on disk, chunks of {base}, D to a float16 store, 2048 lights, default depth, "
        f"{threads} threads", rate, "functions/s",
        error=float(np.median(ang)),
        error_unit="median normal error, degrees (generator BRDF, d_0 estimated)",
        threads=threads, ratios={"vs in-cache fit": rate / (base / t_cache)},
        baseline_threads={"vs in-cache fit": threads},
        extra={"n": n, "seconds": t, "cpu seconds": cpu, "system cpu seconds": sys_,
               "cpu functions/s": n / cpu, "cores busy (cpu s / wall s)": cpu / t,
               "in-cache functions/s (2048 in one call, float32, best of 2)": base / t_cache,
               f"200k functions, s ({200_000 / n:.3g} x this row's wall; measured, at this load)":
                   200_000 / rate,
               "copies fitted identically": same})]


@register("skin.resynthesize")
@one_blas_thread
def bench_resynthesize(quick: bool) -> list[BenchRow]:
    from facegeo.appearance import _skin_resynth, skin

    n = 32 if quick else 128
    lights, nrm, p, v0, R = _case(n, 2)
    fit = skin.fit_reflectance(R, v0, lights, d_0=skin.normalize(p.rho_d))
    rows = []
    vn = np.array([0.5, 0.0, np.sqrt(0.75)])
    w = np.where((lights.directions[:, 1] > 0)[:, None], lights.solid_angles[:, None], 0.0)
    w = np.repeat(w, 3, axis=1)
    # compile / load the kernels' cache
    skin.resynthesize(fit, vn)
    _skin_resynth.resynthesize_relit(fit, vn, w)
    with skin._numba_threads(1):  # the compiled kernel on one thread, as the rows state
        for deg in (30.0, 60.0):
            a = np.radians(deg)
            vn = np.array([np.sin(a), 0.0, np.cos(a)])
            truth = skin.paper_reflectance(nrm, vn, lights, p)
            t, out = best_of(lambda: skin.resynthesize(fit, vn), repeat=2 if quick else 3)
            rel = float(np.sqrt(np.sum((out.reflectance - truth) ** 2) / np.sum(truth ** 2)))
            naive = float(np.sqrt(np.sum((R - truth) ** 2) / np.sum(truth ** 2)))
            rows.append(BenchRow(
                "skin.resynthesize",
                f"resynthesize (Eq. 9), 2048 lights, view {deg:.0f}° from source",
                n / t, "functions/s", error=rel, error_unit="relative RMSE vs paper model at v_n",
                ratios={"error vs naive (reuse source function)": rel / naive}, threads=1,
                baseline_threads={"error vs naive (reuse source function)": 1},
                extra={"naive relative RMSE": naive, "n": n}))
        # the compiled kernel against the numpy reference (KERNELS off), same run, 1 thread each;
        # and resynthesize_relit (Eq. 4 fused, no (N, L, 3) result) under a sky-like half dome
        t_k, out_k = best_of(lambda: skin.resynthesize(fit, vn), repeat=3 if quick else 5)
        t_relit, _ = best_of(lambda: _skin_resynth.resynthesize_relit(fit, vn, w),
                             repeat=3 if quick else 5)
        _skin_resynth.KERNELS = False
        try:
            t_ref, out_ref = best_of(lambda: skin.resynthesize(fit, vn), repeat=1 if quick else 2)
        finally:
            _skin_resynth.KERNELS = True
    diff = float(np.abs(out_k.reflectance - out_ref.reflectance).max()
                 / np.abs(out_ref.reflectance).max())
    rows.append(BenchRow(
        "skin.resynthesize", "resynthesize, compiled kernel, 2048 lights, view 30° "
        "(vs numpy reference, KERNELS off)", n / t_k, "functions/s", error=diff,
        error_unit="max |kernel − numpy| / max |R|", threads=1,
        ratios={"vs numpy reference": t_ref / t_k}, baseline_threads={"vs numpy reference": 1},
        extra={"n": n, "numpy reference functions/s": n / t_ref,
               "resynthesize_relit functions/s (upper-half lights)": n / t_relit,
               "relit vs full kernel": t_k / t_relit}))
    return rows
