"""Benchmarks of the novel-view renderer (Debevec et al. 2000 §4.5, :mod:`facegeo.render`).

``render.novel_view``: a tiny synthetic scan (generated in a temporary folder, true rig,
ground-truth mesh, atlas at 0.5 texels/mm), its skin-model fit restricted to the texels the view
needs, then the view ``orbit:cam_left:30`` under the built-in sky rendered with resynthesis and
as the naive baseline (measured functions relit and blended). Speed: pixels per second of the
whole render (primary rays, resynthesis of every needed texel from every source camera, Eq. (4)
over the active lights, blending); error: the relative RMSE against the generator's reference
over the head mask. Also reported: texels shaded per second and the fit's functions per second
(the stage that dominates today). With ``quick`` the fit is subsampled (300 functions per
camera; the other texels fall back to their measured functions), so its error is nearer the
naive baseline's.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from facegeo.pipeline.bench import BenchRow, best_of, register


@register("render.novel_view")
def bench_novel_view(quick: bool) -> list[BenchRow]:
    from facegeo.pipeline.fit import run_fit
    from facegeo.pipeline.project import run_project
    from facegeo.pipeline.render import run_render
    from facegeo.synth.capture import generate_scan

    spec = "orbit:cam_left:30"
    rows = []
    with tempfile.TemporaryDirectory(prefix="facegeo-bench-render-") as tmp:
        root = Path(tmp) / "scan"
        generate_scan(root, "tiny")
        run_project(root, atlas_settings={"texels_per_mm": 0.5}, gt_lights=4)
        t0 = time.perf_counter()
        fm = run_fit(root, texels="views", views=[spec], max_texels=300 if quick else None,
                     gt_functions=16)
        t_fit = time.perf_counter() - t0
        out = {}
        for resyn in (True, False):
            sec, m = best_of(lambda r=resyn: run_render(
                root, camera_spec=spec, env="sky", resynthesis=r, baseline=False,
                name=f"bench_{r}"), repeat=1 if quick else 2)
            out[resyn] = (sec, m)
        for resyn, label in ((True, "resynthesis"), (False, "naive baseline")):
            sec, m = out[resyn]
            px = m["size"][0] * m["size"][1]
            rows.append(BenchRow(
                "render.novel_view",
                f"{spec}, sky, tiny preset ({m['size'][0]}×{m['size'][1]}), {label}",
                px / m["seconds_render"], "pixels/s", m.get("rel_rmse"),
                "relative RMSE vs generator reference (head mask)",
                extra={"texels_shaded_per_s": round(m["stats"]["texels"]
                                                    / max(m["stats"]["seconds_shade"], 1e-9), 1),
                       "psnr_db": m.get("psnr_db"), "coverage": m.get("coverage"),
                       "active_lights": m["active_lights"],
                       "seconds_render": m["seconds_render"], "seconds_run_render": round(sec, 3),
                       "fit_functions": fm["functions"],
                       "fit_functions_per_s": fm["functions_per_second"],
                       "fit_seconds": round(t_fit, 2)},
                threads=1))
    return rows
