"""The multi-view ``fit`` stage's skin-model fits against the generator's truth (synthetic scans).

Reads ``out/atlas/``, ``out/project/`` (the fields and view directions the fits were made
from), ``out/fit/<camera>/`` (:class:`facegeo.render.FitStore`) and the fit's settings
(``stage.json``: ``rig``, ``gt_functions``, ``gt_angles``, ``near_field``), and gives the
figures the stage reports today (``pipeline/fit.py`` module docstring):
``normal_median_error_deg``, ``albedo_rel_error`` (and ``_alpha0``),
``specular_energy_rel_error``, ``resynthesis_rel_rmse_<θ>`` / ``_naive_`` / ``_median`` /
``resynthesis_backfacing_<θ>``, ``gt_valid_functions`` and, with a rig other than the true
one, the gauge figures.

Until the stage drops its copy (issue 37), the per-camera comparison is the stage's own
``_ground_truth`` (with ``_near_field`` and ``_median``), called here on the products — not
copied; :func:`fit_truth_figures` is the one assembly of the figures from its sums, which
``pipeline/fit.py`` repeats inline for now.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from facegeo.evaluate._products import has_stage, stage_manifest
from facegeo.evaluate.gauge import truth_gauge

__all__ = ["evaluate_skin_fit", "fit_truth_figures"]


def fit_truth_figures(gt: dict) -> dict:
    """The figures from the sums ``gt`` the per-camera comparisons accumulated (keys
    ``n_err``, ``a_err``, ``a0_err``, ``s_err``, ``sums``, ``per_function``, ``backfacing``,
    ``views``); ``{}`` when no valid function was compared."""
    def median(parts, digits):
        a = np.concatenate(parts) if parts else np.zeros(0)
        return round(float(np.median(a)), digits) if a.size else None

    if not gt["n_err"]:
        return {}
    out: dict[str, Any] = {"gt_valid_functions": int(np.concatenate(gt["n_err"]).size),
                           "normal_median_error_deg": median(gt["n_err"], 4),
                           "albedo_rel_error": median(gt["a_err"], 5),
                           "albedo_rel_error_alpha0": median(gt["a0_err"], 5),
                           "specular_energy_rel_error": median(gt["s_err"], 5)}
    out.update({key: round(float(np.sqrt(se / sr)), 5) if sr > 0 else None
                for key, (se, sr) in sorted(gt["sums"].items())})
    out.update({f"{key}_median": median(parts, 5)
                for key, parts in sorted(gt["per_function"].items())})
    out.update({f"resynthesis_backfacing_{key}": round(nb / max(gt["views"][key], 1), 5)
                for key, nb in sorted(gt["backfacing"].items())})
    return out


def evaluate_skin_fit(scan, out, *, renderer=None) -> dict:
    """The fits in ``out/fit/`` against the generator (module docstring); ``{}`` without a
    multi-view fit or without the generator's truth."""
    from facegeo.appearance.skin import resynthesize
    from facegeo.pipeline.fit import _ground_truth, _near_field
    from facegeo.pipeline.project import stage_rig
    from facegeo.render import light_set, load_sources
    from facegeo.surface.atlas import Atlas, Texels

    out = Path(out)
    fit_dir = out / "fit"
    if not (scan.synthetic and "skin" in scan.ground_truth_keys and has_stage(out, "fit")
            and (out / "project").is_dir()):
        return {}
    cams = [p.parent.name for p in sorted(fit_dir.glob("*/fit.npz"))]
    if not cams:  # an image-space fit (photometric.npz): evaluate.normals
        return {}
    settings = stage_manifest(out, "fit").get("settings", {})
    if renderer is None:
        from facegeo.synth.render import load_ground_truth

        renderer = load_ground_truth(scan)
    the_rig, rig_used = stage_rig(scan, settings.get("rig"))
    lights = light_set(the_rig.lights)
    atlas = Atlas.load(out / "atlas" / "atlas.npz")
    tex = Texels.load(out / "atlas" / "texels.npz")
    T_true, gauge = truth_gauge(renderer, atlas, rig_used)
    near_all = _near_field(the_rig.lights, tex, settings.get("near_field", "off"))
    gt: dict[str, Any] = {"n_err": [], "a_err": [], "a0_err": [], "s_err": [], "sums": {},
                          "per_function": {}, "backfacing": {}, "views": {}}
    for src in load_sources(out / "project", cameras=cams):
        near = None if near_all is None else near_all.take(src.texel_index)
        _ground_truth(gt, renderer, atlas, tex, src, lights, fit_dir / src.name,
                      int(settings.get("gt_functions", 256)),
                      settings.get("gt_angles", [30.0, 60.0]), resynthesize, T_true, near)
    figures = fit_truth_figures(gt)
    return {**gauge, **figures} if figures else {}
