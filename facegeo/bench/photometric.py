"""Benchmark ``photometric.real``: the image-space fit of single-view real captures (issue 36)
against the per-pixel Lambertian least squares, side by side.

For Extended Yale B subject B01 (grey, the 27 lights strictly within 50° of the camera, every
other one fitted) and DiLiGenT ``ball`` and ``cat`` (RGB, 96 calibrated lights, the
even-numbered files fitted — the data set's own split): held-out relative MAE and RMSE, mean
and median normal error against ``Normal_gt.mat`` (DiLiGenT) and time per pixel, for
facegeo's per-pixel model choice (:func:`facegeo.appearance.photometric.held_out_photometric`
through the fit stage, :func:`facegeo.pipeline._fit_image.fit_image_products`) and the
baseline named exactly: **per-pixel Lambertian least squares** (a pseudo-inverse on the same
fitted lights, pixels and samples, numpy + OpenBLAS, computed in the same call). Both run at
the same thread count (the BLAS pool limited to it, the fit's workers set to it).

The data come from ``../shared/data/olat`` (``FACEGEO_SHARED_DATA``); without it the benchmark
returns no rows. ``quick``: at most 2,000 pixels per object, one thread count.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from facegeo.bench import BenchRow, limit_threads, register

#: The objects: (name, importer, folder under olat/, fit-stage settings of the protocol).
OBJECTS = (
    ("Yale B01", "yale-b", "yale_b01", {"light_cone_deg": 50.0}),
    ("DiLiGenT ball", "diligent", "diligent/ballPNG", {"hold_out": {"every": 2, "offset": 1}}),
    ("DiLiGenT cat", "diligent", "diligent/catPNG", {"hold_out": {"every": 2, "offset": 1}}),
)
QUICK_PIXELS = 2000
BASELINE = "per-pixel Lambertian least squares (pinv, numpy)"


@register("photometric.real")
def bench_real(quick: bool) -> list[BenchRow]:
    from facegeo.capture.datasets import import_dataset
    from facegeo.pipeline._fit_image import fit_image_products
    from facegeo.bench import shared_data_dir

    root = shared_data_dir() / "olat"
    rows: list[BenchRow] = []
    thread_counts = (1,) if quick else (1, 2)
    with tempfile.TemporaryDirectory(prefix="facegeo-bench-photometric-") as tmp:
        for name, kind, rel, protocol in OBJECTS:
            src = root / rel
            if not src.is_dir():
                continue
            scan = import_dataset(kind, src, Path(tmp) / rel.replace("/", "_"))
            settings = dict(protocol, max_pixels=QUICK_PIXELS if quick else None)
            for t in thread_counts:
                dest = Path(tmp) / f"fit_{rel.replace('/', '_')}_{t}"
                dest.mkdir()
                with limit_threads(t):
                    m, _ = fit_image_products(scan, dest, threads=t, **settings)
                px = max(int(m["pixels"]), 1)
                t_fit, t_lam = m["seconds_fit"], m["seconds_lambertian"]
                common = {"object": name, "pixels": px, "lights_fitted": m["lights_fitted"],
                          "lights_held_out": m["lights_held_out"], "channels": m["channels"]}
                ours = {"heldout_rel_mae": m["heldout_rel_mae"],
                        "heldout_rel_rmse": m["heldout_rel_rmse"],
                        "normal_mean_error_deg": m.get("normal_mean_error_deg"),
                        "normal_median_error_deg": m.get("normal_median_error_deg"),
                        "us_per_pixel": round(1e6 * t_fit / px, 2)}
                lam = {"heldout_rel_mae": m["heldout_rel_mae_lambertian"],
                       "heldout_rel_rmse": m["heldout_rel_rmse_lambertian"],
                       "normal_mean_error_deg": m.get("normal_mean_error_deg_lambertian"),
                       "normal_median_error_deg": m.get("normal_median_error_deg_lambertian"),
                       "us_per_pixel": round(1e6 * t_lam / px, 2)}
                rows.append(BenchRow(
                    "photometric.real",
                    f"{name}: facegeo per-pixel model choice (Lambertian / +shadow / +lobe / both)",
                    px / max(t_fit, 1e-12), "pixels/s", error=m["heldout_rel_mae"],
                    error_unit="held-out relative MAE",
                    ratios={f"vs {BASELINE}": t_lam / max(t_fit, 1e-12)},
                    extra={**common, **ours,
                           **{f"{k}_lambertian": v for k, v in lam.items()}},
                    threads=t, baseline_threads={f"vs {BASELINE}": t}))
                rows.append(BenchRow(
                    "photometric.real", f"{name}: {BASELINE}", px / max(t_lam, 1e-12),
                    "pixels/s", error=m["heldout_rel_mae_lambertian"],
                    error_unit="held-out relative MAE", extra={**common, **lam}, threads=t))
    return rows
