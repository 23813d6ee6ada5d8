"""``facegeo evaluate``: every stage product of a scan against every reference the scan has.

:func:`evaluate_products` looks at what is in ``out/`` and compares each product with the
references of its kind (one module each): the calibrated rig with reference intrinsics and the
generator's rig (:mod:`~facegeo.evaluate.intrinsics`), the mesh with a reference cloud or mesh
(:mod:`~facegeo.evaluate.cloud`), the projected fields with the generator's exact shading
(:mod:`~facegeo.evaluate.projection`), the skin-model fits with the generator's
(:mod:`~facegeo.evaluate.skin_fit`), fitted normals with a reference normal map
(:mod:`~facegeo.evaluate.normals`), relit camera views (:mod:`~facegeo.evaluate.relit`) and
rendered views (:mod:`~facegeo.evaluate.views`) with the generator's reference images of the
same camera. It writes ``metrics.json`` (one entry per
stage compared) and the views' reference and error images (``render/``, ``views/``) into its
folder, ``out/evaluate/``; :func:`run_evaluate` stages that folder for the command line, and
``facegeo reconstruct`` runs the same as its last, cached stage.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from facegeo.checks import check_positive_int
from facegeo.evaluate.projection import GT_LIGHTS, GT_WEIGHT_MIN
from facegeo.evaluate.skin_fit import GT_ANGLES, GT_FUNCTIONS, check_gt_angles

log = logging.getLogger(__name__)

__all__ = ["EVALUATE_SETTINGS", "HEADLINES", "evaluate_products", "evaluation_inputs",
           "run_evaluate", "summary_rows"]

#: Settings of the evaluation (the ``evaluate`` stage's cache key): the projection's comparison
#: (:mod:`facegeo.evaluate.projection`), the mesh's (:mod:`facegeo.evaluate.cloud`) and the
#: skin fit's (:mod:`facegeo.evaluate.skin_fit`: functions per camera, view turns in degrees).
EVALUATE_SETTINGS: dict[str, Any] = {"gt_lights": GT_LIGHTS, "gt_weight_min": GT_WEIGHT_MIN,
                                     "mesh_samples": 100_000, "gt_functions": GT_FUNCTIONS,
                                     "gt_angles": list(GT_ANGLES)}

#: The figures :func:`summary_rows` shows per compared stage, in order.
HEADLINES: dict[str, tuple[str, ...]] = {
    "calibrate": ("focal_rel_error_max", "principal_point_error_px_max",
                  "rotation_error_deg_max", "translation_error_mm_max",
                  "reference_focal_rel_error_max", "reference_principal_point_error_px_max"),
    "mesh": ("mesh_to_reference_plane_median_mm", "mesh_to_reference_plane_p95_mm",
             "mesh_to_reference_median_mm", "reference_coverage",
             "points_to_reference_median_mm", "points_rms_error_mm", "mesh_p95_error_mm"),
    "project": ("projection_rel_rmse", "visibility_agreement"),
    "fit": ("normal_median_error_deg", "normal_mean_error_deg", "albedo_rel_error",
            "resynthesis_rel_rmse_30", "resynthesis_rel_rmse_60"),
    "render": ("psnr_db_min", "psnr_gain_db_min", "psnr_gain_db_covered_min",
               "psnr_gain_db_seen_min", "silhouette_iou_min"),
    "views": ("psnr_db_min", "psnr_gain_db_min", "psnr_gain_db_covered_min",
              "psnr_gain_db_seen_min", "silhouette_iou_min"),
}


def evaluation_inputs(scan) -> list[Path]:
    """The scan files the evaluation reads besides the stages' products: the generator's
    ``ground_truth/`` files and the ``[reference]`` files (their content enters its key)."""
    files = [scan.ground_truth_path(k) for k in sorted(scan.ground_truth_keys)]
    files += [scan.reference_path(k) for k in sorted(scan.reference_keys)]
    return [p for p in files if p.is_file()]


def _view_stems(folder: Path, manifest_views: dict | None) -> list[str]:
    """The views of a render folder: the stage's own list, else every ``<stem>_camera.json``."""
    if manifest_views:
        return [s for s in manifest_views if (folder / f"{s}_camera.json").is_file()]
    return sorted(p.name[:-len("_camera.json")] for p in folder.glob("*_camera.json"))


def _evaluate_views(scan, out: Path, part: str, dest: Path, renderer: Callable) -> dict:
    from facegeo.evaluate._products import has_stage, stage_manifest
    from facegeo.evaluate.views import (
        evaluate_view,
        evaluate_view_against_image,
        has_view_reference,
        views_summary,
    )

    folder = out / part
    listed = None
    if has_stage(out, part):
        listed = stage_manifest(out, part).get("metrics", {}).get("views")
    per_view = {}
    for stem in _view_stems(folder, listed):
        # a reference image of the view's camera and environment (a real scan's witness
        # camera), else the generator's render of it
        truth = has_view_reference(scan)
        figures = evaluate_view_against_image(scan, folder, stem, out=out,
                                              renderer=renderer() if truth else None)
        if figures is None and truth:
            figures = evaluate_view(scan, out, folder, stem, dest / part, renderer=renderer())
        if figures is not None:
            per_view[stem] = figures
    if not per_view:
        return {}
    return {"views": per_view, **views_summary(per_view)}


#: Folder under the scan's ``out/`` where the generator's reference renders of the views are
#: kept (:class:`_CachedReferences`), shared by the chain's evaluation and the stage-alone
#: pass's (``out/diagnostic/``), which renders the chain's own views.
REFERENCE_CACHE = ".reference-renders"
#: At most this many reference renders are kept (the oldest go first): a demo's passes need 4.
REFERENCE_CACHE_MAX = 16


class _CachedReferences:
    """The generator's truth (``facegeo.synth.render.ReferenceRenderer``) with its
    :meth:`render_lights` — a view's reference image, the evaluation's dominant cost (≈ 12 s
    a view on the small preset with the compiled shading, ≈ 20 s before) — kept on disk under ``folder``, keyed by what the image
    depends on: the camera (its ``to_dict``), the lights' weights, the supersampling, the
    generator's truth files' content and facegeo's code (:func:`facegeo.pipeline.cache.
    code_fingerprint`). Everything else is the renderer's own."""

    def __init__(self, renderer, folder: Path, truth_digest: str):
        self._r, self._folder, self._truth = renderer, Path(folder), truth_digest

    def __getattr__(self, name):
        return getattr(self._r, name)

    def _key(self, camera, lights, weights, supersample: int) -> str:
        import hashlib

        import numpy as np

        from facegeo.pipeline.cache import code_fingerprint

        h = hashlib.sha256()
        h.update(json.dumps({"camera": camera.to_dict(), "supersample": int(supersample),
                             "n_lights": int(lights.n_lights), "truth": self._truth,
                             "code": code_fingerprint()}, sort_keys=True).encode())
        h.update(np.ascontiguousarray(np.asarray(weights, np.float64)).tobytes())
        return h.hexdigest()[:32]

    def render_lights(self, camera, lights, weights, *, supersample: int = 1, **kw):
        import numpy as np

        from facegeo.fsutil import atomic_path

        path = self._folder / f"{self._key(camera, lights, weights, supersample)}.npy"
        if path.is_file():
            try:
                log.info("evaluate: reference render of %s from the cache", camera.name)
                return np.load(path)
            except (OSError, ValueError):  # a damaged entry: rendered again
                pass
        image = self._r.render_lights(camera, lights, weights, supersample=supersample, **kw)
        self._folder.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.save(f, image)
        kept = sorted(self._folder.glob("*.npy"), key=lambda q: q.stat().st_mtime)
        for old in kept[:max(0, len(kept) - REFERENCE_CACHE_MAX)]:
            old.unlink(missing_ok=True)
        return image


def _truth_digest(scan) -> str:
    """The content of the generator's truth files (``ground_truth/``: what a reference render
    depends on besides its camera and weights)."""
    import hashlib

    from facegeo.fsutil import file_sha256

    h = hashlib.sha256()
    for k in sorted(scan.ground_truth_keys):
        path = scan.ground_truth_path(k)
        if path.is_file() and k in ("mesh", "rig", "skin", "vertex_params", "parts"):
            h.update(f"{k}:{file_sha256(path)};".encode())
    return h.hexdigest()


def evaluate_products(scan, out, dest, *, gt_lights: int = GT_LIGHTS,
                      gt_weight_min: float = GT_WEIGHT_MIN, mesh_samples: int = 100_000,
                      gt_functions: int = GT_FUNCTIONS, gt_angles=GT_ANGLES,
                      stages: list[str] | None = None,
                      progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Compare the products in ``out`` with the scan's references; write ``dest/metrics.json``.

    Parameters
    ----------
    scan : facegeo.capture.scan.Scan
    out : path-like
        The scan's ``out/`` (``calibrate/``, ``mesh/``, ``atlas/``, ``project/``, ``fit/``,
        ``render/``, ``views/`` — whichever exist).
    dest : path-like
        The evaluation's folder (``out/evaluate/`` or its staging folder).
    gt_lights, gt_weight_min
        The projection's comparison (:func:`facegeo.evaluate.projection.evaluate_projection`).
    mesh_samples : int
        Area-uniform samples of the mesh (:func:`facegeo.evaluate.cloud.mesh_to_reference`).
    gt_functions, gt_angles
        The skin fit's comparison (:func:`facegeo.evaluate.skin_fit.evaluate_skin_fit`):
        functions per camera, view turns in degrees.
    stages : list of str, optional
        Compare only these stages' products (default: every stage with products).
    progress : callable(stage, done, total), optional
        Called as stage ``"evaluate"`` after each comparison.

    Returns
    -------
    dict
        One entry per compared stage (its figures) and ``seconds`` per comparison under
        ``seconds_by_stage``; stages without products or references are absent.
    """
    from facegeo.evaluate import cloud, intrinsics, normals, projection, relit, skin_fit, views
    from facegeo.evaluate._products import has_stage
    from facegeo.fsutil import atomic_write_text

    gt_lights = check_positive_int(gt_lights, "gt_lights")
    mesh_samples = check_positive_int(mesh_samples, "mesh_samples")
    gt_functions = check_positive_int(gt_functions, "gt_functions")
    gt_angles = check_gt_angles(gt_angles)
    out, dest = Path(out), Path(dest)
    truth: dict[str, Any] = {}

    def renderer():
        if "r" not in truth:
            from facegeo.synth.render import load_ground_truth

            # the views' reference renders kept across runs and passes (the chain's and the
            # stage-alone one share them: the latter renders the chain's views)
            truth["r"] = _CachedReferences(load_ground_truth(scan),
                                           scan.out_dir / REFERENCE_CACHE, _truth_digest(scan))
        return truth["r"]

    def wanted(name: str) -> bool:
        return stages is None or name in stages

    jobs: list[tuple[str, Callable[[], dict]]] = []
    if wanted("calibrate"):
        jobs.append(("calibrate", lambda: intrinsics.evaluate_calibration(scan, out)))
    if wanted("mesh"):
        jobs.append(("mesh", lambda: cloud.evaluate_mesh_against_reference(
            scan, out, n_samples=mesh_samples)))
    if wanted("project") and has_stage(out, "project") and projection.has_projection_truth(scan):
        jobs.append(("project", lambda: projection.evaluate_projection(
            scan, out, gt_lights=gt_lights, gt_weight_min=gt_weight_min,
            renderer=renderer())))
    if wanted("fit"):  # a multi-view fit against the generator; an image-space one's normals
        jobs.append(("fit", lambda: {**skin_fit.evaluate_skin_fit(
            scan, out, renderer=renderer() if views.has_view_reference(scan) else None,
            gt_functions=gt_functions, gt_angles=gt_angles),
            **normals.evaluate_normals(scan, out)}))
    if wanted("relit"):  # facegeo relight's camera views (the relight stage's is the atlas)
        jobs.append(("relit", lambda: relit.evaluate_relit(scan, out)))
    images = any(k.startswith("images.") for k in scan.reference_keys)
    for part in ("render", "views"):
        if wanted(part) and (out / part).is_dir() and (views.has_view_reference(scan)
                                                       or images):
            jobs.append((part, lambda part=part: _evaluate_views(scan, out, part, dest,
                                                                 renderer)))
    metrics: dict[str, Any] = {}
    seconds: dict[str, float] = {}
    for k, (name, job) in enumerate(jobs):
        t0 = time.perf_counter()
        figures = job()
        if figures:
            metrics[name] = figures
            seconds[name] = round(time.perf_counter() - t0, 4)
        if progress:
            progress("evaluate", k + 1, len(jobs))
    metrics["seconds_by_stage"] = seconds
    dest.mkdir(parents=True, exist_ok=True)
    atomic_write_text(dest / "metrics.json",
                      json.dumps(metrics, indent=2, sort_keys=True, allow_nan=False))
    return metrics


def run_evaluate(scan_dir, out_dir=None, **settings) -> dict:
    """Evaluate a scan's products into ``out_dir/evaluate/`` (staged: the folder is replaced
    only when complete) and record the figures in ``out_dir/metrics.json`` under
    ``"evaluate"``.

    Parameters
    ----------
    scan_dir : path-like or facegeo.capture.scan.Scan
    out_dir : path-like, optional — default the scan's ``out/``
    **settings — see :func:`evaluate_products`

    Returns
    -------
    dict — the figures (:func:`evaluate_products`) and ``seconds``
    """
    from facegeo.capture.scan import Scan, load_scan
    from facegeo.fsutil import atomic_write_text, staged_directory
    from facegeo.pipeline.cache import record_metrics

    scan = scan_dir if isinstance(scan_dir, Scan) else load_scan(scan_dir)
    out = Path(out_dir) if out_dir is not None else scan.out_dir
    t0 = time.perf_counter()
    used = {**EVALUATE_SETTINGS, **{k: v for k, v in settings.items() if k != "progress"}}
    with staged_directory(out / "evaluate") as tmp:
        metrics = evaluate_products(scan, out, tmp, **used, progress=settings.get("progress"))
        metrics["seconds"] = round(time.perf_counter() - t0, 4)
        atomic_write_text(tmp / "stage.json", json.dumps(
            {"stage": "evaluate", "settings": used, "metrics": metrics}, indent=2,
            sort_keys=True, allow_nan=False))
    record_metrics(out, "evaluate", metrics)
    return metrics


def summary_rows(metrics: dict) -> list[tuple[str, str, Any]]:
    """``(stage, figure, value)`` of the headline figures (:data:`HEADLINES`) present in an
    evaluation's metrics, in pipeline order."""
    rows = []
    for stage, keys in HEADLINES.items():
        m = metrics.get(stage)
        if not isinstance(m, dict):
            continue
        rows += [(stage, k, m[k]) for k in keys if m.get(k) is not None]
    return rows
