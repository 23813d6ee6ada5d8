"""``facegeo reconstruct``: the stages built so far, cached under ``SCAN/out/<stage>/``.

Today the chain is ``atlas → project`` (issue 11) on the scan's mesh — the synthetic scan's
ground-truth mesh until structured-light meshing lands — with calibrate, decode, mesh and fit to
join it as their issues land. Each stage is a :class:`facegeo.pipeline.cache.StageSpec`: it
reruns only when the content of the files it reads, its settings, an earlier stage's key or the
facegeo version changed (:mod:`facegeo.pipeline.cache`), and every stage's metrics are gathered
in ``SCAN/out/metrics.json``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from facegeo.errors import InputError
from facegeo.pipeline.cache import Pipeline, StageContext, StageResult, StageSpec

__all__ = ["STAGES", "reconstruct_pipeline", "run_reconstruct"]

#: The stages ``facegeo reconstruct`` runs, in order.
STAGES = ("atlas", "project")


def _mesh_inputs(scan, mesh: str) -> list[Path]:
    if mesh == "ground_truth":
        if "mesh" not in scan.ground_truth_keys:
            raise InputError(f"scan {scan.root}: no ground-truth mesh, and structured-light "
                             "meshing is not built yet; give --mesh PATH (a mesh in metres)")
        return [scan.ground_truth_path("mesh")]
    return [Path(mesh)]


def _project_inputs(scan, mesh: str) -> list[Path]:
    files = [scan.manifest_path, scan.root / scan.manifest["scan"]["rig"]]
    for cam in scan.camera_names:
        files += [p for _, p in scan.expected_files("olat", cam)]
    # ground truth feeds the accuracy metrics (and, on synthetic scans, the true rig)
    files += [scan.ground_truth_path(k) for k in sorted(scan.ground_truth_keys)
              if scan.ground_truth_path(k).is_file()]
    return files + _mesh_inputs(scan, mesh)


def reconstruct_pipeline(scan, *, mesh: str = "ground_truth") -> Pipeline:
    """The :class:`~facegeo.pipeline.cache.Pipeline` of ``facegeo reconstruct`` for one scan.

    Parameters
    ----------
    scan : facegeo.capture.scan.Scan
        The loaded scan (loaded and validated once; every stage reads it from here).
    mesh : str
        ``"ground_truth"`` (a synthetic scan's mesh) or a mesh file in metres.
    """
    from facegeo.pipeline.project import atlas_products, project_products

    atlas_settings = {"mesh": mesh, "texels_per_mm": 1.0, "size": None, "padding": 2,
                      "split_faces": 25_000, "repair": False}
    project_settings = {"mesh": mesh, "rig": None, "dtype": "float16", "gt_lights": 32,
                        "gt_weight_min": 0.3}

    def run_atlas(ctx: StageContext) -> dict:
        return atlas_products(scan, ctx.out_dir, **ctx.settings)

    def run_project(ctx: StageContext) -> dict:
        metrics, _ = project_products(scan, ctx.upstream["atlas"], ctx.out_dir, **ctx.settings)
        return metrics

    return Pipeline([
        StageSpec("atlas", run_atlas, inputs=lambda d: _mesh_inputs(scan, mesh),
                  settings=atlas_settings),
        StageSpec("project", run_project, after=("atlas",),
                  inputs=lambda d: _project_inputs(scan, mesh), settings=project_settings),
    ])


def run_reconstruct(scan_dir, *, mesh: str = "ground_truth",
                    settings: Mapping[str, Mapping[str, Any]] | None = None,
                    from_stage: str | None = None, only: str | None = None,
                    progress: Callable[[str, int, int], None] | None = None,
                    on_stage: Callable[[StageResult], None] | None = None) -> list[StageResult]:
    """Run every stage of ``facegeo reconstruct`` whose products are missing or stale.

    Parameters
    ----------
    scan_dir : path-like
    mesh : str
        See :func:`reconstruct_pipeline`.
    settings : mapping of stage -> mapping, optional
        Overrides of a stage's settings (``{"atlas": {"texels_per_mm": 2.0}}``); a changed
        setting reruns that stage and the ones after it.
    from_stage, only : str, optional
        ``--from STAGE`` reruns that stage and every later one; ``--only STAGE`` runs one stage
        (its inputs must be current).
    progress, on_stage : callable, optional
        See :meth:`facegeo.pipeline.cache.Pipeline.run`.
    """
    from facegeo.capture.scan import load_scan

    scan_dir = Path(scan_dir)
    scan = load_scan(scan_dir)  # validated once, before any stage starts
    if settings:
        json.dumps(settings)  # fail early on values that cannot enter a cache key
    return reconstruct_pipeline(scan, mesh=mesh).run(scan_dir, settings=settings,
                                               from_stage=from_stage, only=only,
                                               progress=progress, on_stage=on_stage)
