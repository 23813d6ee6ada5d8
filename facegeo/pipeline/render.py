"""Pipeline stage ``render``: novel views of a reconstructed scan under an environment.

``run_render(scan_dir, out_dir=None, *, camera_spec, env, ...)`` reads ``out/atlas/``,
``out/project/`` and ``out/fit/`` and writes into ``out/views/`` (``out/render/`` is the cached
``render`` stage of ``facegeo reconstruct``, :func:`render_products`):

    <name>.exr, <name>.png                the render (Debevec et al. 2000 §4.5,
                                          :func:`facegeo.render.render_view`)
    <name>_naive.exr/.png                 the naive baseline: the source cameras' relit
                                          captures projected per pixel (with
                                          ``image_detail``, the default; else their measured
                                          functions relit and blended), no resynthesis
    .source_images/<hash>.npz             the relit source captures of the image-space detail,
                                          kept for the next view under the same environment
    <name>_camera.json                    the camera the view was rendered from
    <name>_weights.npy                    (L, 3) float64: the environment's Eq. (4) field weights
    <name>_covered.png                    255 where a pixel was rendered from measured texels
    <name>_inferred.png                   255 where a surface pixel holds a value inferred,
                                          not measured (``infer``: surface no camera saw)
    <name>_texture.exr, _naive_texture.exr  with image-space detail: the texture-space renders
    <name>_paper.exr                      with a shrinkage λ ≠ 1 and a reference to compare
                                          with: the paper's resynthesis as written (λ = 1)
    <name>.json                           the view's metrics (``exposure``: of the PNGs)

and merges the view's metrics into ``out/metrics.json`` → ``"views"`` → ``"views"`` → name.

The stage never reads the truth: :mod:`facegeo.evaluate.views` compares these files with the
generator's reference of the same camera (``psnr_db``, ``rel_rmse``, their naive, paper,
texture-space and covered-pixel forms, ``head_coverage``). :func:`run_render`, the standalone
runner, returns those figures beside the view's own (``reference=True``) and writes the
reference and error images beside the view.

Metrics of the view itself: ``coverage``, the fraction of the render's surface pixels (rays
that hit the atlas mesh) whose texels some source camera measured (pixels outside it are
filled from texels inferred over the surface with ``infer``, the default —
:func:`facegeo.render.novel.infer_texel_colours` —, else from the nearest measured pixel
within ``fill_px`` (2 px) and black beyond, in every render); ``inferred_pixel_fraction``
(surface pixels holding an inferred value), ``inferred_texel_fraction`` (atlas texels no
source camera measured), ``black_surface_pixels`` and ``surface_pixel_fraction`` (the image's
share of surface pixels; under :data:`CAMERA_HIT_MIN` a warning says the camera hardly looks
at the surface);
with the cross-validated shrinkage (the default, :func:`facegeo.render.cross_validated_shrinkage`)
``shrinkage_factors`` (λ per source camera) and ``shrinkage_cross_validation``; with
image-space detail (``image_detail``, :mod:`facegeo.render.detail`) ``detail_fraction``
(covered pixels the source images reached) and ``seconds_source_images`` (relighting the
captures; 0 when reused).

Environments: a path to an ``.exr``/``.hdr`` map (``projection`` lat-long by default), or a
built-in name: ``"uniform"`` (radiance 1 everywhere, the generator's ``uniform`` renders),
``"axis_lobes"`` (:func:`facegeo.lighting.envmap.axis_lobe_map`), and the procedural maps
shipped with facegeo, ``"sky"`` (a sky with a 2° sun) and ``"studio"`` (key, fill and rim area
lights) (:func:`facegeo.lighting.envmap.shipped_map`).
"""

from __future__ import annotations

import io
import json
import logging
import os
import time
import uuid
from pathlib import Path

import numpy as np

from facegeo.pipeline._render_view import (  # noqa: F401 (re-exported)
    BUILTIN_ENVS,
    CAMERA_HIT_MIN,
    RENDER_DEFAULT_ENV,
    SHRINKAGE_CHOICES,
    SHRINKAGE_DEFAULT,
    SOURCE_IMAGES_DIR,
    SOURCE_IMAGES_KEEP,
    _check_shrinkage,
    _cross_validated_factors,
    _field_weights,
    _load_env,
    _render_rig,
    _source_images,
    _view_cameras,
    _view_inputs,
    _view_shadows,
    builtin_env,
    check_render_args,
    check_view_inputs,
    read_source_images,
    render_one,
    source_images_key,
    view_input_files,
    write_source_images,
)
from facegeo.surface._zarr_field import (
    copy_files,
    get_bytes,
    put_bytes,
    remove_location,
    store_location,
)

log = logging.getLogger(__name__)

__all__ = ["BUILTIN_ENVS", "CAMERA_HIT_MIN", "SHRINKAGE_CHOICES", "builtin_env",
           "check_render_args", "reference_views", "render_one", "render_products",
           "render_view_task", "render_working_set", "run_render"]


def run_render(scan_dir, out_dir=None, *, camera_spec, env="axis_lobes", rotate_deg: float = 0.0,
               projection: str = "latlong", supersample: int = 1, resynthesis: bool = True,
               baseline: bool = True, reference: bool = True, name: str | None = None,
               blend_power: float | None = None, rig: str | None = None,
               solid_angle: str = "paper", fill_px: float | None = None,
               shrinkage: str | float = SHRINKAGE_DEFAULT, light_step: int = 1,
               shadow_taps: bool = True, image_detail: bool = True, progress=None,
               convention: str = "facegeo", infer: bool = True, engine=None,
               store=None) -> dict:
    """Render a novel view of a reconstructed scan under an environment; write the images.

    Parameters
    ----------
    scan_dir : path-like or Scan
    out_dir : path-like, optional — default the scan's ``out/`` (holding ``atlas/``,
        ``project/``, ``fit/``); images go to ``out_dir/views/``
    camera_spec : str, dict or Camera — ``"orbit:<camera>:<degrees>"``, a camera name (the
        scan's, or the generator's novel cameras), a camera JSON file or dict
        (:func:`facegeo.render.parse_camera_spec`)
    env : str or EnvironmentMap — an ``.exr``/``.hdr`` file or a built-in name
    rotate_deg : float, degrees — environment rotation about +Y
    projection : {"latlong", "mirror-ball", "angular", "cube"} — of an environment file
    convention : str — of a lat-long environment file
        (:data:`facegeo.lighting.envmap.LATLONG_CONVENTIONS`: "facegeo", "u0_at_plus_z", "blender")
    supersample : int — s × s rays per pixel (a box filter over the pixel); the reference
        integrates the same footprint (``reference_supersample``). 1: pixel centres, where a
        hard shadow edge's point sample is a step no resampling of the captures places
        (docs/render.md, "The pixel footprint"); the ``render`` stage uses
        :data:`facegeo.pipeline.reconstruct.RENDER_SUPERSAMPLE`
    resynthesis : bool or "diffuse" — False: render only the naive baseline as the main
        image; ``"diffuse"``: the diffuse-only ablation (:func:`facegeo.render.shade_texels`)
    baseline : bool — also render the naive baseline
    reference : bool — when the scan has a reference to compare with (synthetic scans), write
        what the comparison reads (the paper's λ = 1 render beside a shrunk one) and return
        the figures of :func:`facegeo.evaluate.views.evaluate_view` beside the view's own,
        the reference and error images written beside the view
    name : str, optional — output stem (default from the camera and environment)
    blend_power : float, optional — view-dependent weight exponent
    rig : str, optional — :func:`facegeo.pipeline.project.stage_rig`; default as the ``project`` stage used
    solid_angle : {"paper", "exact"} — δA rule of the Eq. (4) weights
    fill_px : float, pixels, optional — hole filling of unmeasured hit samples from the nearest
        measured pixel within this distance (:func:`facegeo.render.render_view`; 0: off);
        filled pixels count in ``psnr_db`` / ``rel_rmse`` but not in the ``*_covered`` figures.
        Default 0 with ``infer`` (those samples' texels are inferred over the surface like any
        unmeasured texel), 2 without (:func:`facegeo.pipeline._render_view.default_fill_px`)
    shrinkage : {"cross-validated", "none"} or float in [0, 1] — the share λ of the
        resynthesised change applied per source camera
        (:func:`facegeo.render.cross_validated_shrinkage`, a deviation from the paper measured
        against the other source cameras; ``"none"``: λ = 1, the paper's §4.3 as written; a
        number: that λ for every camera). With λ ≠ 1 and a reference, the paper's render is
        made as well and reported as ``paper_psnr_db`` (``_covered``)
    light_step : int ≥ 1 — speed against accuracy, not the paper: the resynthesis (and the
        shrinkage's cross-validation) evaluates the new functions once per k × k block of
        lights (:func:`facegeo.render.shade_texels`; docs/render.md has time against error);
        the naive and the paper's renders beside it stay exact
    shadow_taps : bool — shadow-consistent texel taps at the cast-shadow edges of the
        environment's key lights, decided on the atlas mesh
        (:func:`facegeo.render.render_shadows`; every render of the view, the naive baseline
        included); False: plain bilinear texel taps
    image_detail : bool — image-space detail (:mod:`facegeo.render.detail`): the source
        cameras' captures relit under ``env`` and projected per pixel move every render of
        the view by their difference from the texture-space naive render, so the naive
        baseline is that per-pixel projection and the resynthesis adds its predicted change
        to it; the texture-space figures are kept as ``texture_*``. False: texture space
        only (the paper)
    infer : bool — cover what no camera saw: surface pixels whose texels no source camera
        measured take values inferred over the surface (pull–push of colour over Lambertian
        shading in space, :func:`facegeo.render.render_view` ``infer``), marked in
        ``<name>_inferred.png``; covered pixels unchanged bit for bit. False: black (the paper)
    progress : callable(stage, done, total), optional — called as stage ``"render"`` after
        each step (rays — with image detail, relighting the source captures too, ≈ 40 s at the
        paper preset the first time under an environment —, render, naive baseline); on a
        Dask engine or with a store, as the view's task finishes
    engine : facegeo.pipeline.engine.Engine, optional — a Dask engine (``--workers`` /
        ``--scheduler``): the view is one task of it, as the ``render`` stage's views
        (:func:`render_products`: the λ, the rig and the relit source captures — kept in
        ``views/.source_images`` as in process — made here, the view on a worker); the same
        files as in process. None or in process: rendered here
    store : path-like or str, optional — ``--store URL``: the view's task reads its inputs from
        and writes its files through this folder or fsspec store, sharing no disk with this
        process (:func:`render_products`; on any engine)

    Returns
    -------
    dict — the view's metrics (files, timings; with a reference ``psnr_db`` …); as a task
    without its ``stats``, with ``inputs_from`` and ``engine`` (not merged into
    ``metrics.json``)
    """
    from facegeo.evaluate.views import evaluate_view, has_view_reference
    from facegeo.pipeline.project import _scan

    scan = _scan(scan_dir)
    out = Path(out_dir) if out_dir is not None else scan.out_dir
    kw = dict(rotate_deg=rotate_deg, projection=projection, supersample=supersample,
              resynthesis=resynthesis, baseline=baseline, reference=reference, name=name,
              blend_power=blend_power, rig=rig, solid_angle=solid_angle, fill_px=fill_px,
              shrinkage=shrinkage, light_step=light_step, shadow_taps=shadow_taps,
              image_detail=image_detail, convention=convention, infer=infer)
    as_task = None
    if store is not None or (engine is not None and engine.kind != "in-process"):
        if engine is None:
            from facegeo.pipeline.engine import InProcessEngine

            engine = InProcessEngine()
        per_view, names, _, inputs_from = _render_views_as_tasks(
            scan, out, out / "views", [(camera_spec, env)], engine, progress, kw, store=store,
            source_images_dir=out / "views" / SOURCE_IMAGES_DIR)
        metrics = next(iter(per_view.values()))
        as_task = {"inputs_from": inputs_from, "engine": engine.stage_metrics("render", names)}
    else:
        metrics = render_one(scan, out, out / "views", camera_spec=camera_spec, env=env,
                             progress=progress, **kw)
    if reference and has_view_reference(scan):
        figures = evaluate_view(scan, out, out / "views", metrics["name"], out / "views")
        metrics["files"].update(figures.pop("files"))
        metrics.update(figures)
    _merge_metrics(out, metrics["name"], metrics)
    return metrics if as_task is None else {**metrics, **as_task}


def render_products(scan, out: Path, dest: Path, *, views, env=RENDER_DEFAULT_ENV,
                    progress=None, engine=None, store=None, **settings) -> dict:
    """The ``render`` stage of ``facegeo reconstruct``: every view in ``views`` under ``env``
    into ``dest`` (:func:`render_one`); returns the stage's metrics.

    Besides ``views``, every scan camera with a reference image ``[reference]
    images.<camera>.<env>`` (a witness camera; :func:`reference_views`) is rendered under that
    environment, so the evaluation compares it
    (:func:`facegeo.evaluate.views.evaluate_view_against_image`).

    ``engine`` (:mod:`facegeo.pipeline.engine`): None or in process — the views one after
    another sharing one cache (:func:`render_one`); a Dask engine — each view is one task
    (:func:`render_view_task`) writing into its own folder under ``dest``, whose files the
    client moves into ``dest`` in view order. The cross-validated λ is computed once per
    environment on the client first (:func:`_shared_shrinkage`) and handed to the tasks, so
    every task renders with the λ the in-process stage uses, and so are the rig and the
    cameras a view may name (the tasks read no rig or camera file of the scan); the source
    captures of the image-space detail are relit there too, once per environment
    (:func:`_shared_source_images`), and written one ``.npz`` an environment into
    ``dest/.view_tasks/.source_images``, which each task loads into its cache (their
    ``seconds_source_images`` are 0; the client's are the stage's
    ``seconds_source_images``). The files are the same bytes whatever the engine; the folder
    ``dest/.view_tasks`` is removed when the stage ends.

    ``store`` (``--store URL``: a folder or an fsspec URL; issue 38): the view tasks share no
    disk with the client (on any engine, in process too — one task after another). The client
    puts what they read into ``URL/render/run-<id>/inputs/``: the files of ``out`` a view
    reads (:func:`view_input_files`; a field kept in a store by the projection is read where
    it is, through its link) under ``out/``, and the relit source captures, one ``.npz`` an
    environment, under ``source_images/``. Each task fetches the files into a temporary
    folder of its worker, renders from that copy — seeded, as above, with the λ, the rig, the
    cameras and its environment's captures: it reads nothing of the scan either —, and puts
    its view's files into ``URL/render/run-<id>/views/<k>/``; the client brings them into
    ``dest`` in view order and removes the run's folder from the store. The same bytes as
    without a store.

    Metrics: ``views`` (per view, as :func:`render_one`), ``env`` and ``seconds`` (the views'
    sum); as tasks ``seconds_source_images``, ``inputs_from`` (``"store"``: the fetched copy;
    ``"stage folder"``: ``out`` on a shared disk) and ``engine``
    (:meth:`facegeo.pipeline.engine.Engine.stage_metrics`). The
    figures against references (``psnr_db_min`` …, the novel-view goal of issue 14:
    resynthesis at least 3 dB better than the naive baseline) are the ``evaluate`` stage's
    (:mod:`facegeo.evaluate.views`).
    """
    jobs = [(spec, env) for spec in views] + reference_views(scan)
    if store is not None or (engine is not None and engine.kind != "in-process"):
        if engine is None:
            from facegeo.pipeline.engine import InProcessEngine

            engine = InProcessEngine()
        per_view, names, t_sources, inputs_from = _render_views_as_tasks(
            scan, Path(out), Path(dest), jobs, engine, progress, settings, store=store)
    else:
        per_view, names = {}, None
        # the cross-validated λ, the atlas check and the relit source images, once a stage
        cache: dict = {}
        for k, (spec, view_env) in enumerate(jobs):
            tick = (lambda stage, d, n, k=k: progress("render", k * n + d, len(jobs) * n)) \
                if progress else None
            m = render_one(scan, out, dest, camera_spec=spec, env=view_env, progress=tick,
                           cache=cache, **settings)
            per_view[m["name"]] = {key: v for key, v in m.items() if key != "stats"}
    metrics = {"views": per_view, "env": str(env),
               "seconds": round(sum(v.get("seconds", 0.0) for v in per_view.values()), 4)}
    if names is not None:
        metrics["seconds_source_images"] = t_sources  # on the client, before the tasks
        metrics["inputs_from"] = inputs_from
        metrics["engine"] = engine.stage_metrics("render", names)
    return metrics


#: Folder of ``dest`` holding the view tasks' folders while a render stage runs on a cluster
#: (:func:`render_products`); removed when the stage ends.
VIEW_TASKS_DIR = ".view_tasks"


#: Sub-folders of a render run's place in the ``--store`` (``URL/render/run-<id>/``): the
#: inputs the client puts there for the view tasks (``out/`` — the stage products —, and
#: ``source_images/``), and the views' files the tasks put (``views/<k>/``).
STORE_INPUTS = "inputs"
STORE_SOURCE_IMAGES = "source_images"
STORE_VIEWS = "views"


def _render_views_as_tasks(scan, out: Path, dest: Path, jobs: list, engine, progress,
                           settings: dict, *, store=None,
                           source_images_dir=None) -> tuple[dict, list[str], float, str]:
    """The views ``jobs`` (``(camera_spec, env)``) as tasks of ``engine``, one a view
    (:func:`render_view_task`), each into ``dest/.view_tasks/<k>`` — with ``store``, from
    and into the store (:func:`render_products`) —; their files moved into ``dest`` in view
    order (a later view of the same name replaces an earlier one's files, as in process).

    The client relights the source captures once per environment (kept in
    ``source_images_dir`` too when given: :func:`run_render`'s ``views/.source_images``, as in
    process) and hands each task its environment's as one ``.npz``
    (:func:`_put_source_images`), which the task loads into its cache: no task derives the
    captures' file name from the scan's frames and facegeo's code fingerprint (a worker
    started after an edit of facegeo's code computes another one, and relit its own).
    Returns the per-view metrics, the tasks' names, the seconds the client spent relighting
    the source captures (:func:`_shared_source_images`) and where the tasks read their inputs
    (``"store"`` or ``"stage folder"``)."""
    import shutil

    from facegeo.pipeline.engine import Task

    opts = {**_render_one_defaults(), **settings}
    if store is not None:  # named here, before anything goes up to the store
        check_view_inputs(out, opts["resynthesis"])
    seeds: dict = {}  # the rig and the cameras a view may name, resolved once, here
    sizes = _client_inputs(scan, out, opts, seeds)
    root = dest / VIEW_TASKS_DIR
    needs = [0 if sizes is None else _view_working_set(scan, spec, opts, sizes, seeds)
             for spec, _ in jobs]
    run_loc = None if store is None else store_location(
        store, "render", f"run-{uuid.uuid4().hex[:12]}")

    def task_dir(k: int) -> str:
        return str(root / f"{k:03d}") if run_loc is None else \
            str(store_location(run_loc, STORE_VIEWS, f"{k:03d}"))

    def tasks_with(shared: dict, via, captures: list) -> list:
        return [Task(f"{k:03d} {spec if isinstance(spec, str) else 'camera'} "
                     f"{view_env if isinstance(view_env, str) else 'env'}", render_view_task,
                     (scan, str(out), task_dir(k), spec, view_env, shared, settings, None, via,
                      captures[k]),
                     working_set=need)
                for k, ((spec, view_env), need) in enumerate(zip(jobs, needs))]

    engine.check_fits("render", tasks_with({}, None, [()] * len(jobs)))  # before the client's
    made = not dest.exists()
    shared, t_sources, via = dict(seeds), 0.0, None
    try:
        images: dict = {}
        if sizes is not None:
            shared.update(_shared_shrinkage(jobs, opts, sizes))
            t_sources = _shared_source_images(
                scan, jobs, opts, sizes, None if source_images_dir is None
                else Path(source_images_dir), images)
        captures = _put_source_images(images, jobs, root / SOURCE_IMAGES_DIR if run_loc is None
                                      else store_location(run_loc, STORE_INPUTS,
                                                          STORE_SOURCE_IMAGES))
        if run_loc is not None:
            via = _put_view_inputs(out, opts, store_location(run_loc, STORE_INPUTS))
        sizes = images = None  # the client's inputs go before the tasks run
        tasks = tasks_with(shared, via, captures)
        results = engine.map("render", tasks, progress=progress)
        dest.mkdir(parents=True, exist_ok=True)
        per_view: dict = {}
        for k, r in enumerate(results):  # in view order, whatever order they finished in
            if run_loc is not None:
                copy_files(task_dir(k), dest)
            else:
                for f in sorted((root / f"{k:03d}").iterdir()):
                    os.replace(f, dest / f.name)
            m = r["metrics"]
            per_view.pop(m["name"], None)  # a later view of the same name: last, as in process
            per_view[m["name"]] = m
    finally:
        shutil.rmtree(root, ignore_errors=True)
        if run_loc is not None:
            remove_location(run_loc)
        if made and dest.is_dir() and not any(dest.iterdir()):
            dest.rmdir()  # a stage that failed leaves no folder it made
    return (per_view, [t.name for t in tasks], t_sources,
            "stage folder" if run_loc is None else "store")


def _put_source_images(images: dict, jobs: list, location) -> list:
    """The relit source captures ``images`` (``{environment: (cache key, [SourceImage])}``,
    :func:`_shared_source_images`) written one ``.npz`` an environment
    (:func:`write_source_images`) into ``location`` — a folder of the stage's (on the disk the
    workers share) or of the store. Returns per job of ``jobs`` the captures its task loads
    (:func:`render_view_task`): ``[(cache key, file, cameras)]``, empty without image
    detail."""
    captures = {}
    for i, (env_id, (key, imgs)) in enumerate(images.items()):
        buf = io.BytesIO()
        write_source_images(buf, imgs)
        f = store_location(location, f"{i:03d}.npz")
        put_bytes(f, buf.getvalue())
        captures[env_id] = (key, str(f), {im.camera.name: im.camera for im in imgs})
    return [[captures[_env_id(env)]] if _env_id(env) in captures else [] for _, env in jobs]


def _put_view_inputs(out: Path, opts: dict, location) -> dict:
    """Put the files of ``out`` a view reads (:func:`view_input_files`) into the store folder
    ``location/out`` (``URL/render/run-<id>/inputs/out``); returns the tasks' ``via``
    (:func:`render_view_task`): the store folder and the files."""
    from facegeo.pipeline._scan_store import put_files

    rels = view_input_files(out, bool(opts["resynthesis"]))
    put_files(rels, store_location(location, "out"), root=out)
    return {"inputs": str(location), "files": rels}


def _client_inputs(scan, out: Path, opts: dict, seeds: dict | None = None) -> dict | None:
    """What the client of a cluster render stage reads once before the views' tasks: the rig,
    the source cameras (``with_fit`` as the views), the atlas's texel and triangle counts —
    for :func:`_shared_shrinkage` and the tasks' working sets — after the check that the
    projection indexes this atlas; the rig resolved into ``seeds`` (the tasks' caches,
    :func:`_render_rig`). None when an input is missing (each task then raises
    :func:`render_one`'s error itself)."""
    from facegeo.pipeline.project import check_projection_atlas

    with_fit = bool(opts["resynthesis"])
    if not all((out / f).is_file() for f in ("atlas/atlas.npz", "atlas/texels.npz")) or (
            with_fit and not (out / "fit").is_dir()):
        return None
    _, the_rig, rig_used = _render_rig(scan, out, opts["rig"], seeds)
    atlas, texels, scene, sources = _view_inputs(out, with_fit, None, check_projection_atlas)
    return {"rig": the_rig, "rig_used": rig_used, "atlas": atlas, "texels": texels,
            "scene": scene, "sources": sources}


def _view_working_set(scan, spec, opts: dict, sizes: dict, seeds: dict | None = None) -> int:
    """:func:`render_working_set` of the view ``spec`` (its camera parsed here: a bad spec
    raises before any task runs; the cameras a view may name kept in ``seeds``,
    :func:`_view_cameras`)."""
    from facegeo.render import parse_camera_spec

    camera = parse_camera_spec(spec, _view_cameras(scan, sizes["rig"], sizes["rig_used"],
                                                   seeds))
    detail_px = sum(int(c.width) * int(c.height) for c in (
        sizes["rig"].camera(src.name) for src in sizes["sources"])) if opts["image_detail"] \
        else 0
    return render_working_set(camera, int(opts["supersample"]), sizes["sources"],
                              len(sizes["texels"]), len(sizes["atlas"].faces),
                              detail_pixels=detail_px)


#: Bytes a view task needs whatever its size, over the engine's ``WORKER_BASE_BYTES``: the
#: renderer's imports and compiled kernels. With the figures below, measured against a
#: worker's peak resident memory less a 246 MiB interpreter (the engine's measured figure):
#: tiny preset (80 × 120 px, s = 3, 2 × 128 lights) 130–141 MiB, estimated 158 MiB; small
#: preset (240 × 360 px, s = 3, 2 × 512 lights) 709–724 MiB, estimated 745 MiB.
RENDER_BASE_BYTES = 64 << 20
#: ... per ray sample (pixels × supersample²): the samples' hit points,
#: texel taps and weights (:func:`facegeo.render.trace_view`), their colours in up to three
#: renders (shrunk, naive, paper's) with the texture-space copies and the fill-in's
#: accumulators (float64) ≈ 400 B.
RENDER_BYTES_PER_SAMPLE = 400
#: ... per atlas texel: the texel table (positions, normals, faces, barycentrics), the
#: shadow taps' arrays and the inferred colours ≈ 200 B.
RENDER_BYTES_PER_TEXEL = 200
#: ... per atlas triangle: the atlas mesh and Embree's BVH ≈ 250 B (as the projection's).
RENDER_BYTES_PER_FACE = 250
#: ... per source-camera pixel with image-space detail: its relit capture and validity
#: (float32 RGB + bool, 13 B) and as many frames of the key lights
#: (:data:`facegeo.render.novel.SHADOW_MAX_LIGHTS` at most).
RENDER_BYTES_PER_SOURCE_PIXEL = 13
#: ... per function-light sample of the resynthesis's chunk
#: (:data:`facegeo.render.novel.CHUNK_SAMPLES` at a time): RGB float64 in ≈ 4 temporaries.
RENDER_BYTES_PER_CHUNK_SAMPLE = 3 * 8 * 4
#: Field rows a ray sample can read per source camera (its bilinear texel taps).
RENDER_TAPS_PER_SAMPLE = 4


def render_working_set(camera, supersample: int, sources, n_texels: int, n_faces: int, *,
                       detail_pixels: int = 0) -> int:
    """Memory (bytes) one view's task needs (an upper bound): :data:`RENDER_BASE_BYTES` +
    :data:`RENDER_BYTES_PER_SAMPLE` × the view's ray samples + :data:`RENDER_BYTES_PER_TEXEL`
    × texels + :data:`RENDER_BYTES_PER_FACE` × triangles + the resynthesis chunk's
    (:data:`RENDER_BYTES_PER_CHUNK_SAMPLE` × ``CHUNK_SAMPLES``) + per
    source camera the field rows the samples can touch (memory-mapped pages count in a
    worker's resident memory: at most :data:`RENDER_TAPS_PER_SAMPLE` rows a sample, at most
    the field, R and the fit's D) + the source captures of the image-space detail, relit
    and with their key-light frames: :data:`RENDER_BYTES_PER_SOURCE_PIXEL` × (1 +
    ``SHADOW_MAX_LIGHTS``) × ``detail_pixels``.

    Parameters
    ----------
    camera : facegeo.calib.Camera — the view's camera (its width and height)
    supersample : int — s: s × s rays a pixel
    sources : list of facegeo.render.SourceCamera — ``field`` (rows, L, 3) and ``fit.D``
    n_texels, n_faces : int — of the atlas
    detail_pixels : int — the source cameras' pixels, summed, with image-space detail
        (:mod:`facegeo.render.detail`); 0 without
    """
    from facegeo.render.novel import CHUNK_SAMPLES, SHADOW_MAX_LIGHTS

    samples = int(camera.width) * int(camera.height) * int(supersample) ** 2
    total = (RENDER_BASE_BYTES + samples * RENDER_BYTES_PER_SAMPLE
             + int(n_texels) * RENDER_BYTES_PER_TEXEL
             + int(n_faces) * RENDER_BYTES_PER_FACE
             + CHUNK_SAMPLES * RENDER_BYTES_PER_CHUNK_SAMPLE)
    for src in sources:
        for a in (src.field, None if src.fit is None else src.fit.D):
            if a is None:
                continue
            rows = int(a.shape[0])
            row_bytes = int(np.prod(a.shape[1:])) * np.dtype(a.dtype).itemsize
            total += min(rows, RENDER_TAPS_PER_SAMPLE * samples) * row_bytes
    return int(total + int(detail_pixels) * RENDER_BYTES_PER_SOURCE_PIXEL
               * (1 + SHADOW_MAX_LIGHTS))


def _render_one_defaults() -> dict:
    """:func:`render_one`'s keyword defaults (what a stage's ``settings`` leave out)."""
    import inspect

    return {k: p.default for k, p in inspect.signature(render_one).parameters.items()
            if p.kind is p.KEYWORD_ONLY and p.default is not p.empty}


def _distinct_envs(jobs: list) -> list:
    """The environments of ``jobs`` (``(camera_spec, env)``), each once, in first-seen order
    (names and paths by value, map objects by identity)."""
    found = {}
    for _, env in jobs:
        found.setdefault(_env_id(env), env)
    return list(found.values())


def _env_id(env):
    """An environment's identity among a stage's jobs: a name or path by value, a map object
    by identity."""
    return env if isinstance(env, (str, Path)) else id(env)


def _shared_shrinkage(jobs: list, opts: dict, inputs: dict) -> dict:
    """The cross-validated λ of every environment among ``jobs``, computed here as the
    in-process stage computes it for its first view under that environment
    (:func:`_cross_validated_factors`, in one process, from the same inputs): ``{cache key:
    (factors, stats)}``, kilobytes, for the view tasks' caches (each task computing its own
    could differ in the last bits: a worker's numba runs one thread). Empty when the views
    take no cross-validated λ. ``inputs``: :func:`_client_inputs`. Measured on the tiny
    preset: 0.02 s an environment once numba's kernels are compiled (8.6 s with the compile,
    the first time in a process)."""
    from facegeo.render import light_set

    if opts["resynthesis"] is not True or _check_shrinkage(opts["shrinkage"]) != \
            "cross-validated":
        return {}
    stage = inputs["rig"].lights
    lights = light_set(stage)
    cache: dict = {}
    for env in _distinct_envs(jobs):
        w = _field_weights(env, stage, opts["projection"], opts["rotate_deg"],
                           opts["convention"], opts["solid_angle"])
        _cross_validated_factors(inputs["sources"], w, lights, opts["light_step"], cache)
    return cache


def _shared_source_images(scan, jobs: list, opts: dict, inputs: dict, disk: Path | None,
                          found: dict | None = None) -> float:
    """The source cameras' captures relit under every environment among ``jobs``, with the
    frames of the key lights, as :func:`render_one` makes them for a view
    (:func:`_source_images`), kept in ``disk`` when given (:func:`run_render`'s
    ``views/.source_images``: read back there while the frames and the code are unchanged)
    and into ``found``: ``{environment (its :func:`_env_id`): (cache key, images)}``
    (:func:`source_images_key`), what the view tasks are handed (:func:`_put_source_images`).
    Relit once here rather than once a worker (measured on the small preset: 12 s in process,
    19–20 s in each of two one-thread workers at once). Returns the seconds spent; 0 without
    image detail. ``inputs``: :func:`_client_inputs`."""
    from facegeo.render.novel import key_lights

    if not opts["image_detail"]:
        return 0.0
    stage = inputs["rig"].lights
    shadows = _view_shadows(inputs["atlas"], inputs["scene"], inputs["texels"], stage,
                            None) if opts["shadow_taps"] else None
    seconds = 0.0
    for env in _distinct_envs(jobs):
        w = _field_weights(env, stage, opts["projection"], opts["rotate_deg"],
                           opts["convention"], opts["solid_angle"])
        keys = () if shadows is None else tuple(int(k) for k in key_lights(
            w, shadows.key_share, shadows.max_lights))
        got, t = _source_images(scan, inputs["rig"], inputs["rig_used"], inputs["sources"], w,
                                keys, None, disk)
        if found is not None:
            found[_env_id(env)] = (source_images_key(
                w, inputs["rig_used"], [src.name for src in inputs["sources"]], keys), got)
        seconds += t
    return round(seconds, 4)


def render_view_task(scan, out: str, task_dir: str, camera_spec, env, shared: dict,
                     settings: dict, source_images_dir: str | None = None,
                     via: dict | None = None, captures=()) -> dict:
    """One view of the ``render`` stage, run by an engine's worker: :func:`render_one` into
    ``task_dir`` with a cache of its own seeded with ``shared`` (the stage's cross-validated λ,
    :func:`_shared_shrinkage`; the rig and the cameras a view may name) and with the relit
    source captures of the image-space detail ``captures`` (``[(cache key, file,
    cameras)]``, :func:`_put_source_images`: a path or a place in the store); a view whose
    captures are not among them relights its own, kept in ``source_images_dir`` when given.

    ``via`` (a ``--store``, :func:`render_products`): the task shares no disk with the client.
    It fetches the files ``via["files"]`` of ``via["inputs"]/out`` into a temporary folder and
    renders from that copy (``out`` is not read) into a temporary folder whose files it puts
    into ``task_dir``, a folder of the store. Returns ``{"metrics": ...}``: the view's metrics
    without its ``stats``, small whatever the view's size."""
    from facegeo.pipeline.project import _scan

    cache = dict(shared)
    for key, loc, cameras in captures:
        cache[key] = read_source_images(io.BytesIO(get_bytes(loc)), cameras, key[4])
    seeded = set(cache)
    if via is None:
        m = render_one(_scan(scan), Path(out), Path(task_dir), camera_spec=camera_spec,
                       env=env, cache=cache, source_images_dir=source_images_dir, **settings)
    else:
        import tempfile

        from facegeo.pipeline._scan_store import fetch_files

        with tempfile.TemporaryDirectory(prefix="facegeo-render-") as tmp:
            local = Path(tmp) / "out"
            fetch_files(store_location(via["inputs"], "out"), via["files"], local,
                        what="the render's input")
            view = Path(tmp) / "view"
            m = render_one(_scan(scan), local, view, camera_spec=camera_spec, env=env,
                           cache=cache, source_images_dir=source_images_dir, **settings)
            copy_files(view, task_dir)
    added = {k[0] for k in set(cache) - seeded if isinstance(k, tuple)}
    if "source_images" in added:
        log.warning("render %s: the task relit the source captures itself from the scan's "
                    "frames (its key lights or weights differ from the stage's)", m["name"])
    if "shrinkage" in added:
        log.warning("render %s: the cross-validated λ was computed again in the task (its "
                    "weights differ from the stage's); it may differ from the in-process "
                    "stage's in the last bits", m["name"])
    return {"metrics": {k: v for k, v in m.items() if k != "stats"}}


def reference_views(scan) -> list[tuple[str, str]]:
    """``(camera, env)`` of every ``[reference] images.<camera>.<env>`` key of ``scan`` whose
    camera is one of the scan's and whose environment is a built-in one (:data:`BUILTIN_ENVS`);
    the keys only, never the images (the evaluation reads those). A reference under a map
    file is skipped with a log line: the key names the file's stem, not the file."""
    try:
        keys = list(scan.reference_keys)
        cameras = set(scan.camera_names)
    except (AttributeError, TypeError):
        return []
    found = []
    for key in sorted(keys):
        parts = key.split(".", 2)
        if len(parts) != 3 or parts[0] != "images" or parts[1] not in cameras:
            continue
        if parts[2] not in BUILTIN_ENVS:
            log.info("render: [reference] %s is under %r, not a built-in environment (%s); "
                     "render that camera with 'facegeo render --env FILE'", key, parts[2],
                     ", ".join(BUILTIN_ENVS))
            continue
        found.append((parts[1], parts[2]))
    return found


def _views_summary(per_view: dict) -> dict:
    """The views' ``seconds`` (their sum) and, over the views that have them, the evaluation's
    figures (:func:`facegeo.evaluate.views.views_summary`: ``psnr_db_min`` …)."""
    from facegeo.evaluate.views import views_summary

    return {**views_summary(per_view),
            "seconds": round(sum(v.get("seconds", 0.0) for v in per_view.values()), 4)}


def _merge_metrics(out: Path, stem: str, metrics: dict) -> None:
    from facegeo.pipeline.cache import record_metrics

    try:
        doc = json.loads((out / "metrics.json").read_text(encoding="utf-8")).get("views", {})
        if not isinstance(doc, dict):
            doc = {}
    except (OSError, ValueError, AttributeError):
        doc = {}
    views = doc.get("views", {}) if isinstance(doc.get("views"), dict) else {}
    views[stem] = {k: v for k, v in metrics.items() if k not in ("stats",)}
    # the summary figures beside the views, as the render stage records them (the report's
    # speed-against-error row)
    record_metrics(out, "views", {"views": views, **_views_summary(views)})
