"""Benchmarks of facegeo.appearance.spectral: forward model throughput and inverse-fit throughput.

Throughput is measured on inputs made with the table's interpolant (fast to make at 1 M
texels); the error column is measured on a separate sample whose albedo comes from the exact
spectral model, so it includes the table's interpolation error.

Threads: the code is numpy (elementwise ufuncs on one thread, matrix products on the BLAS pool);
every row states the BLAS pool size as its thread count, and baselines run in the same process
under the same pool. ``spectral.nearest`` compares the voxel nearest-neighbour lookup of
:class:`~facegeo.appearance.spectral.SkinLUT` with a ``scipy.spatial.cKDTree`` query on the
same table entries (both 1 thread).
"""

from __future__ import annotations

import numpy as np

from facegeo.bench import BenchRow, best_of, blas_threads, register


def _with_threads(rows: list[BenchRow]) -> list[BenchRow]:
    th = blas_threads()
    for r in rows:
        if r.threads is None:
            r.threads = th
        for k in r.ratios:
            r.baseline_threads.setdefault(k, th)
    return rows


def _parameters(n: int, seed: int):
    rng = np.random.default_rng(seed)
    C_m = rng.uniform(np.cbrt(0.002), np.cbrt(0.4), n) ** 3
    beta = rng.uniform(0.0, 1.0, n)
    C_h = rng.uniform(np.cbrt(0.002), np.cbrt(0.3), n) ** 3
    return C_m, beta, C_h


@register("spectral.forward")
def bench_forward(quick: bool) -> list[BenchRow]:
    from facegeo.appearance import spectral

    rows = []
    n = 2_000 if quick else 20_000
    C_m, beta, C_h = _parameters(n, 1)
    wl = spectral.DEFAULT_WAVELENGTHS_NM
    t_exact, _ = best_of(lambda: spectral.skin_spectrum(C_m, beta, C_h), repeat=2 if quick else 3)
    rows.append(
        BenchRow(
            "spectral.forward", f"skin_spectrum, {wl.size} wavelengths (exact two-layer model)",
            n / t_exact, "spectra/s", extra={"n": n, "wavelengths": int(wl.size)},
        )
    )
    t_import, _ = best_of(lambda: spectral.rgb_weights(wl), repeat=1)  # colour-science, once
    t_build, lut = best_of(lambda: spectral.SkinLUT(), repeat=1 if quick else 2)
    rows.append(
        BenchRow(
            "spectral.forward", f"SkinLUT build {lut.shape}", lut.rgb.size / 3 / t_build,
            "entries/s", extra={"seconds": t_build, "first colour-table load, s": t_import},
        )
    )
    m = 200_000 if quick else 1_000_000
    P = _parameters(m, 2)
    t_lut, _ = best_of(lambda: lut.interpolate(*P), repeat=3)
    k = 500
    exact = spectral.skin_rgb(P[0][:k], P[1][:k], P[2][:k])
    err = float(np.max(np.abs(lut.interpolate(P[0][:k], P[1][:k], P[2][:k]) / exact - 1.0)))
    t_rgb, _ = best_of(lambda: spectral.skin_rgb(P[0][:k], P[1][:k], P[2][:k]), repeat=2)
    rows.append(
        BenchRow(
            "spectral.forward", "SkinLUT.interpolate (trilinear) → linear sRGB", m / t_lut,
            "albedos/s", error=err, error_unit="max relative RGB error vs exact",
            ratios={"vs exact skin_rgb": (m / t_lut) / (k / t_rgb)}, extra={"n": m},
        )
    )
    return _with_threads(rows)


@register("spectral.inverse")
def bench_inverse(quick: bool) -> list[BenchRow]:
    from facegeo.appearance import spectral

    lut = spectral.skin_lut()
    lut.nearest(np.full((1, 3), 0.2))  # build the voxel index outside the timing
    rows = []
    k = 1_000 if quick else 4_000
    E = _parameters(k, 3)
    rgb_exact = spectral.skin_rgb(*E)

    def errors(fit):
        e_m = np.abs(fit.C_m / E[0] - 1.0)
        e_h = np.abs(fit.C_h / E[2] - 1.0)
        ok_m, ok_h = fit.identifiable[..., 0], fit.identifiable[..., 2]
        worst = max(e_m[ok_m].max(initial=0.0), e_h[ok_h].max(initial=0.0))
        return worst, {
            "median |dC_m|/C_m": float(np.median(e_m)),
            "median |dC_h|/C_h": float(np.median(e_h)),
            "identifiable C_m": float(ok_m.mean()),
            "identifiable C_h": float(ok_h.mean()),
        }

    cases = [
        ("lookup stage only (refine='none')", dict(refine="none"), 1 << 20),
        ("LUT + LM, local check (beta_profile=0)", dict(beta_profile=0), 1 << 17),
        ("LUT + LM, global check (default)", dict(), 1 << 14),
        ("LUT + LM, beta_m known (0.5)", dict(beta_m=0.5), 1 << 17),
        ("LUT + LM + exact refinement", dict(refine="exact"), 1 << 9),
    ]
    for name, kwargs, n in cases:
        n = max(256, n // 4) if quick else n
        P = _parameters(n, 4)
        beta = np.full(n, kwargs["beta_m"]) if "beta_m" in kwargs else P[1]
        rgb = lut.interpolate(P[0], beta, P[2])
        t, _ = best_of(lambda: spectral.fit_albedo(rgb, **kwargs), repeat=1 if quick else 2)
        if "beta_m" in kwargs:
            fit = spectral.fit_albedo(spectral.skin_rgb(E[0], kwargs["beta_m"], E[2]), **kwargs)
        else:
            sub = slice(0, 200) if kwargs.get("refine") == "exact" else slice(None)
            fit = spectral.fit_albedo(rgb_exact[sub], **kwargs)
            if sub != slice(None):
                E_sub = tuple(a[sub] for a in E)
                e_m = np.abs(fit.C_m / E_sub[0] - 1.0)
                e_h = np.abs(fit.C_h / E_sub[2] - 1.0)
                ok_m, ok_h = fit.identifiable[:, 0], fit.identifiable[:, 2]
                worst = max(e_m[ok_m].max(initial=0.0), e_h[ok_h].max(initial=0.0))
                extra = {"median |dC_m|/C_m": float(np.median(e_m)),
                         "median |dC_h|/C_h": float(np.median(e_h)),
                         "identifiable C_m": float(ok_m.mean()),
                         "identifiable C_h": float(ok_h.mean())}
                rows.append(BenchRow("spectral.inverse", name, n / t, "texels/s", error=worst,
                                     error_unit="max rel. error of identifiable C_m, C_h",
                                     extra={"n": n, **extra}))
                continue
        worst, extra = errors(fit)
        rows.append(
            BenchRow(
                "spectral.inverse", name, n / t, "texels/s", error=worst,
                error_unit="max rel. error of identifiable C_m, C_h", extra={"n": n, **extra},
            )
        )
    # Spectral fits (the Xiao 2016 test's method) on model spectra over 400–700 nm.
    wl = np.arange(400.0, 701.0, 10.0)
    n = 200
    P = _parameters(n, 5)
    y = spectral.skin_spectrum(*P, wl)
    t, fit = best_of(lambda: spectral.fit_spectra(y, wl), repeat=2)
    rows.append(
        BenchRow(
            "spectral.inverse", "fit_spectra, 31 wavelengths (exact model LM)", n / t, "spectra/s",
            error=float(np.median(fit.rmse)), error_unit="median RMSE (reflectance), model spectra",
            extra={"n": n},
        )
    )
    return _with_threads(rows)


@register("spectral.nearest")
def bench_nearest(quick: bool) -> list[BenchRow]:
    """Voxel nearest-entry lookup (the inverse fit's seed) against ``scipy.spatial.cKDTree``."""
    from scipy.spatial import cKDTree

    from facegeo.appearance import spectral
    from facegeo.appearance.spectral._lut import LOG_FLOOR

    lut = spectral.skin_lut()
    logrgb = np.log(np.maximum(lut.rgb_flat, LOG_FLOOR))
    t_vox_build, _ = best_of(lambda: lut._voxels, 1)  # cached property: first access builds
    t_tree_build, tree = best_of(lambda: cKDTree(logrgb), 1)
    n = 1 << 14 if quick else 1 << 18
    rng = np.random.default_rng(6)
    P = _parameters(n, 7)
    rgb = lut.interpolate(*P) * np.exp(rng.normal(0.0, 0.02, (n, 3)))  # 2 % colour noise
    q = np.log(np.maximum(rgb, LOG_FLOOR))
    repeat = 2 if quick else 3
    t_vox, i_vox = best_of(lambda: lut.nearest(rgb), repeat)
    t_tree, (d_tree, i_tree) = best_of(lambda: tree.query(q), repeat)
    d_vox = np.linalg.norm(logrgb[i_vox] - q, axis=1)
    excess = d_vox - d_tree
    key = "vs cKDTree.query"
    return [
        BenchRow("spectral.nearest", "SkinLUT.nearest (64³ voxel table, approximate)",
                 n / t_vox / 1e6, "Mqueries/s", float(np.max(excess)),
                 "max excess log-RGB distance over the exact nearest entry",
                 ratios={key: t_tree / t_vox},
                 extra={"n": n, "entries": len(logrgb), "build s": round(t_vox_build, 3),
                        "median excess": float(np.median(excess)),
                        "fraction not the exact nearest": float(np.mean(i_vox != i_tree))},
                 threads=1, baseline_threads={key: 1}),
        BenchRow("spectral.nearest", "scipy.spatial.cKDTree.query (exact nearest entry)",
                 n / t_tree / 1e6, "Mqueries/s", 0.0, "excess distance (exact by construction)",
                 extra={"n": n, "build s": round(t_tree_build, 3)}, threads=1),
    ]
