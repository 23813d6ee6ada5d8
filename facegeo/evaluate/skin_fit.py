"""The multi-view ``fit`` stage's skin-model fits against the generator's truth (synthetic scans).

Reads ``out/atlas/``, ``out/project/`` (the fields and view directions the fits were made
from), ``out/fit/<camera>/`` (:class:`facegeo.render.FitStore`) and the fit's settings
(``stage.json``: ``rig``, ``near_field``). Over the fitted, valid texels
(``gt_valid_functions``; the medians are null when there are none):

* ``normal_median_error_deg`` — against the generator's shading normal at the texel;
* ``albedo_rel_error`` — median ``|ρ_d − ρ_ref| / |ρ_ref|`` with ρ_ref the albedo of the
  paper's Lambertian lobe that the generator's diffuse term has at the true normal and view
  (:func:`facegeo.appearance.brdf.lambertian_equivalent_albedo`: what a perfect diffuse fit
  returns; the skin model's tests use the same reference). ``albedo_rel_error_alpha0``
  compares with the generator's α_0 (its colour at normal incidence and view) instead, as
  this figure did until 2026-12-02: α_0 is not a Lambertian albedo (the generator's BRDF is
  not the paper's model), and on the small preset α_0 and ρ_ref differ by 7.4 % (median), so
  that figure cannot reach 3 % however good the fit;
* ``specular_energy_rel_error`` — median ``|ρ_s − ρ_s,gen| / ρ_s,gen`` (same caveat);
* ``resynthesis_rel_rmse_<θ>`` for θ in ``gt_angles`` (default 30° and 60°) — the fitted
  functions resynthesised for the source view turned by +θ and by −θ about the vertical axis
  (both, for every function), against the generator's exact functions from that view (its
  renderer's shading of every light, cast shadows included), ``sqrt(Σ err² / Σ ref²)`` over at
  most ``gt_functions`` functions per camera; views from below the true surface are not
  compared, their share is ``resynthesis_backfacing_<θ>``; beside it
  ``resynthesis_naive_rel_rmse_<θ>`` (the measured function reused unchanged) and at 0° the
  projection's own error. Each also as the median over functions of the function's own
  relative RMSE (``…_median``): the pooled figure is dominated by a few functions — on the
  small preset 10 of 14,418 turned functions carry 57 % of Σ err² at 30° — so it moves by
  ±20 % with the sample of functions compared, where the median does not.

A near-field light stage (the fit's ``near_field="auto"``, :func:`facegeo.pipeline.fit._near_field`)
is resynthesised with the fit's own geometry (Eq. 9 with each light where it is). The texels
meet the truth where the ``project`` stage's do
(:meth:`facegeo.synth.render.ReferenceRenderer.texel_truth`); with a rig other than the true
one, after the rigid gauge alignment (:func:`facegeo.evaluate.gauge.truth_gauge`,
``gauge_rotation_deg`` / ``gauge_translation_mm``), the view directions turned with it.

Moved out of ``pipeline/fit.py`` (issue 37): on the tiny scan the figures equal the stage's
(docs/evaluate.md).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.checks import check_positive_int, fmt_value
from facegeo.errors import InputError
from facegeo.evaluate._products import has_stage, stage_manifest
from facegeo.evaluate.gauge import inferred_atlas_vertices, truth_gauge

__all__ = ["GT_ANGLES", "GT_FUNCTIONS", "check_gt_angles", "evaluate_skin_fit",
           "fit_truth_figures"]

#: Functions per camera in the resynthesis comparison (an even subsample of the valid fits).
GT_FUNCTIONS = 256
#: View turns (degrees about +Y) at which resynthesis is compared with the generator.
GT_ANGLES = (30.0, 60.0)


def check_gt_angles(gt_angles) -> list[float]:
    """``gt_angles`` as a list of floats, or an InputError naming the bad angle."""
    angles = list(gt_angles)
    for a in angles:  # 0 would be the source view's own key (resynthesis_rel_rmse_0)
        if isinstance(a, bool) or not isinstance(a, (int, float)) or not 0 < abs(a) < 180:
            raise InputError(f"gt_angles: expected angles in degrees with 0 < |θ| < 180, got "
                             f"{fmt_value(a)} in {fmt_value(angles)}")
    return [float(a) for a in angles]


def _median(a, digits):
    """Rounded median of ``a``, or None when ``a`` is empty (JSON has no NaN)."""
    return round(float(np.median(a)), digits) if a.size else None


def fit_truth_figures(gt: dict) -> dict:
    """The figures from the sums ``gt`` the per-camera comparisons accumulated (keys
    ``n_err``, ``a_err``, ``a0_err``, ``s_err``, ``sums``, ``per_function``, ``backfacing``,
    ``views``); ``{}`` when no valid function was compared."""
    def median(parts, digits):
        return _median(np.concatenate(parts) if parts else np.zeros(0), digits)

    if not gt["n_err"]:
        return {}
    out: dict[str, Any] = {"gt_valid_functions": int(np.concatenate(gt["n_err"]).size),
                           "normal_median_error_deg": median(gt["n_err"], 4),
                           "albedo_rel_error": median(gt["a_err"], 5),
                           "albedo_rel_error_alpha0": median(gt["a0_err"], 5),
                           "specular_energy_rel_error": median(gt["s_err"], 5)}
    out.update({key: round(float(np.sqrt(se / sr)), 5) if sr > 0 else None
                for key, (se, sr) in sorted(gt["sums"].items())})
    # "resynthesis_rel_rmse_30" -> "resynthesis_rel_rmse_30_median"
    out.update({f"{key}_median": median(parts, 5)
                for key, parts in sorted(gt["per_function"].items())})
    out.update({f"resynthesis_backfacing_{key}": round(nb / max(gt["views"][key], 1), 5)
                for key, nb in sorted(gt["backfacing"].items())})
    return out


def _exact_functions(renderer, stage, p, n, v, face_in, sk) -> np.ndarray:
    """The generator's exact OLAT functions ``(N, L, 3)`` of points seen from directions v."""
    from facegeo.synth.render import SurfaceView

    N = p.shape[0]
    view = SurfaceView("fit-truth", (1, N), np.ones((1, N), bool), np.arange(N), p, n, v,
                       face_in, np.asarray(sk.alpha_0, np.float32).reshape(-1, 3),
                       np.asarray(sk.alpha_1, np.float32).reshape(-1, 3),
                       np.asarray(sk.rho_s, np.float32).reshape(-1),
                       np.asarray(sk.roughness, np.float32).reshape(-1))
    return np.stack([renderer.shade_stage_light(view, stage, l) for l in range(stage.n_lights)],
                    axis=1)


def _rotate_views(v, deg):
    """v turned by ``deg`` degrees about +Y (world frame)."""
    from facegeo.lighting.envmap import rotation_y

    return v @ rotation_y(np.radians(deg)).T


def _angle_deg(a, b):
    """Angle in degrees between the rows of ``a`` and ``b`` (robust near 0 and 180°)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1),
                                 np.einsum("ni,ni->n", a, b)))


def _add(gt, key, est, ref):
    """Add functions ``est`` against ``ref`` (N, L, C) to the pooled sums of ``key`` and their
    per-function relative RMSE (functions with some reference energy) to its list."""
    se, sr = gt["sums"].get(key, (0.0, 0.0))
    ok = np.isfinite(est).all(axis=(1, 2))
    e2 = ((est[ok].astype(np.float64) - ref[ok]) ** 2).sum(axis=(1, 2))
    r2 = (ref[ok].astype(np.float64) ** 2).sum(axis=(1, 2))
    gt["sums"][key] = (se + float(e2.sum()), sr + float(r2.sum()))
    lit = r2 > 0
    gt["per_function"].setdefault(key, []).append(np.sqrt(e2[lit] / r2[lit]))


def _ground_truth(gt, renderer, atlas, tex, src, lights, cam_dir, n_max, angles,
                  T_true=None, near=None):
    """Accumulate the comparisons of one camera's fits into ``gt`` (module docstring).

    The truth is the generator's: its light stage and, with ``T_true`` (the gauge alignment of
    a rig other than the true one), the texels and view directions moved into its frame.
    Fitted normals are compared as they are: the fit places them in the light stage's frame,
    which is the generator's. ``near``: the fit's :class:`~facegeo.appearance.skin.NearField`
    of the camera's rows (None: distant lights)."""
    from facegeo.appearance.brdf import lambertian_equivalent_albedo
    from facegeo.appearance.skin import resynthesize
    from facegeo.render import FitStore
    from facegeo.render.novel import even_subset

    stage = renderer.rig.lights
    to_true = (lambda v: v) if T_true is None else T_true.apply_direction
    store = FitStore.load(cam_dir)
    if store.rows.size == 0:  # a camera with nothing fitted adds nothing (not even a count)
        return
    valid = store.params["valid"].astype(bool)
    truth = renderer.texel_truth(atlas, tex, store.texel_index, T_true=T_true)
    sk = renderer.material_at(truth.p, truth.face)
    a0 = np.asarray(sk.alpha_0, np.float64).reshape(-1, 3)
    rs = np.asarray(sk.rho_s, np.float64).reshape(-1)
    gt["n_err"].append(_angle_deg(store.params["normal"], truth.n)[valid])
    gt["a0_err"].append((np.linalg.norm(store.params["rho_d"] - a0, axis=1)
                         / np.linalg.norm(a0, axis=1))[valid])
    # the albedo of the paper's Lambertian lobe that the generator's (non-Lambertian) diffuse
    # term has at the true normal and view: what a perfect fit returns
    rho_ref = lambertian_equivalent_albedo(
        truth.n[valid], to_true(src.v_world[store.rows[valid]]), a0[valid],
        np.asarray(sk.alpha_1, np.float64).reshape(-1, 3)[valid], rs[valid],
        np.asarray(sk.roughness, np.float64).reshape(-1)[valid], stage.directions,
        lights.solid_angles)
    gt["a_err"].append(np.linalg.norm(store.params["rho_d"][valid] - rho_ref, axis=1)
                       / np.maximum(np.linalg.norm(rho_ref, axis=1), 1e-300))
    gt["s_err"].append((np.abs(store.params["rho_s"] - rs) / np.maximum(rs, 1e-12))[valid])
    sub = np.flatnonzero(valid)[even_subset(int(valid.sum()), n_max)]
    if sub.size == 0:
        return
    R = np.asarray(src.field[store.rows[sub]], np.float32)
    # masked samples (NaN) as the fit took them, 0 (pipeline.fit.fit_chunks): S = R − D = 0
    # there, and the measured function compared as the fit saw it (EXR scans are unchanged)
    R = np.where(np.isfinite(R), R, np.float32(0.0))
    fit = store.skin_fit(sub, R, lights)
    if near is not None:  # the fit's own texel positions (not the truth's)
        fit = replace(fit, near=near.take(store.rows[sub]))
    p, n, face_in = truth.p[sub], truth.n[sub], truth.face[sub]
    skin_sub = renderer.material_at(p, face_in)
    v0 = src.v_world[store.rows[sub]]
    ref0 = _exact_functions(renderer, stage, p, n, to_true(v0), face_in, skin_sub)
    _add(gt, "resynthesis_rel_rmse_0", R, ref0)
    for deg in angles:
        # Both turns, +θ and −θ, for every function: picking per function the turn that keeps
        # the view higher above the surface (as this once did) left out the grazing views and
        # flattered the figure 2.4–3× (docs/render.md). Views from below the true surface see
        # nothing of it: counted (``resynthesis_backfacing_<θ>``), not compared.
        for sign in (1.0, -1.0):
            vn = _rotate_views(v0, sign * float(deg))
            vn_true = to_true(vn)
            front = np.einsum("ni,ni->n", vn_true, n) > 0
            key = f"{deg:g}"
            gt["backfacing"][key] = gt["backfacing"].get(key, 0) + int((~front).sum())
            gt["views"][key] = gt["views"].get(key, 0) + int(front.size)
            if not front.any():
                continue
            f = np.flatnonzero(front)
            ref = _exact_functions(renderer, stage, p[f], n[f], vn_true[f], face_in[f],
                                   renderer.material_at(p[f], face_in[f]))
            est = resynthesize(fit, vn).reflectance[f]
            _add(gt, f"resynthesis_rel_rmse_{key}", est, ref)
            _add(gt, f"resynthesis_naive_rel_rmse_{key}", R[f], ref)


def evaluate_skin_fit(scan, out, *, renderer=None, gt_functions: int = GT_FUNCTIONS,
                      gt_angles=GT_ANGLES) -> dict:
    """The fits in ``out/fit/`` against the generator (module docstring); ``{}`` without a
    multi-view fit or without the generator's truth.

    Parameters
    ----------
    scan : facegeo.capture.scan.Scan
    out : path-like — the scan's ``out/`` (``atlas/``, ``project/``, ``fit/``)
    renderer : ReferenceRenderer, optional — the generator's (loaded when not given)
    gt_functions : int — functions per camera in the resynthesis comparison
    gt_angles : sequence of float, degrees — the view turns compared (0 < |θ| < 180)
    """
    from facegeo.pipeline.fit import _near_field
    from facegeo.pipeline.project import stage_rig
    from facegeo.render import light_set, load_sources
    from facegeo.surface.atlas import Atlas, Texels

    gt_functions = check_positive_int(gt_functions, "gt_functions")
    angles = check_gt_angles(gt_angles)
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
    T_true, gauge = truth_gauge(renderer, atlas, rig_used,
                                skip=inferred_atlas_vertices(out, atlas))
    near_all = _near_field(the_rig.lights, tex, settings.get("near_field", "off"))
    gt: dict[str, Any] = {"n_err": [], "a_err": [], "a0_err": [], "s_err": [], "sums": {},
                          "per_function": {}, "backfacing": {}, "views": {}}
    for src in load_sources(out / "project", cameras=cams):
        if not (fit_dir / src.name / "fit.npz").is_file():
            continue
        near = None if near_all is None else near_all.take(src.texel_index)
        _ground_truth(gt, renderer, atlas, tex, src, lights, fit_dir / src.name,
                      gt_functions, angles, T_true, near)
    figures = fit_truth_figures(gt)
    return {**gauge, **figures} if figures else {}
