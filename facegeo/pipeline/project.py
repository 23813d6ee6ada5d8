"""Pipeline stages ``atlas`` and ``project``: the surface reflectance field of a scan on disk.

``run_atlas(scan_dir, out_dir)`` parameterises the scan's mesh and writes ``out_dir/atlas/``:

    mesh_uv.obj, mesh_uv.mtl, mesh_uv.glb   the mesh with UVs (docs/surface.md)
    atlas.npz                              facegeo.surface.atlas.Atlas
    texels.npz                             facegeo.surface.atlas.Texels (index map rebuilt on load)
    inferred_texels.npy                    (T,) bool, when the mesh marks inferred faces: the
                                           texels on them (surface no point supported)
    stage.json                             settings and metrics

A mesh file may come with its inferred faces beside it: ``<stem>_inferred.npy``, ``(F,)`` bool
over the file's faces (the ``mesh`` stage's ``mesh_filled.ply`` has
``mesh_filled_inferred.npy``: the filled surface's faces farther than the trim distance from
every structured-light point, :mod:`facegeo.pipeline.mesh`). The atlas carries them to its
texels (``inferred_texels.npy``; metrics ``inferred_faces``, ``inferred_texels``) and the
projection measures none of those texels — no camera weight, as if no camera saw them — so the
fit leaves them unfitted and the renders infer their appearance from the measured texels around
them (:func:`facegeo.render.novel.infer_texel_colours`), marked in ``<view>_inferred.png``:
the filled geometry's position is a guess, and a camera's pixel projected onto it would be
another point's radiance. The cameras' visibility is that of the measured faces alone (the
inferred ones neither occlude a texel nor make an edge the weights feather toward), so a
measured texel's weight is what it is on the trimmed mesh: with the filled surface's faces in
the scene, the texels at the edge of the structured light's reach — its least accurate
geometry — lost their feathering and raised the tiny preset's ``projection_rel_rmse`` from 8.1
to 11.2 %. The shadow-consistent taps cast shadow rays against the whole atlas mesh, filled
part included (the head is there, where the filled surface guesses it; casting none from the
inferred faces changed no figure of the tiny preset's chain by more than 0.01 dB).

``run_project(scan_dir, out_dir)`` reads ``out_dir/atlas/`` (running the atlas stage first when
it is missing) and writes ``out_dir/project/``:

    <camera>/R.npy            (T_c, L, 3) float16, chunked along texels (memory-mapped)
    <camera>/texel_index.npy  (T_c,) int64; weight.npy (T_c,) float32; v_world.npy (T_c, 3)
    seen.npy                  (T,) bool: some camera has a non-zero weight
    blended/R_blend.npy       (U, L, 3) float16: Σ_c w_c R_c / Σ_c w_c per texel, for
                              fixed-viewpoint uses (facegeo.surface.reflectance.blend_fields;
                              R_blend.zarr, or a link to it, when a cluster blends Zarr fields);
    blended/texel_index.npy   (U,) int64; weight.npy (U,) float32 Σ_c w_c; n_cameras.npy (U,)
                              (read with facegeo.surface.reflectance.open_blended)
    preview.png               the mean over lights, blended over cameras, pull–push filled
                              (display only: unseen texels are never counted as measured)
    atlas.sha256              SHA-256 of the atlas's texels.npz the fields index: readers
                              refuse a projection onto another atlas (check_projection_atlas)
    stage.json

Each stage writes into a temporary sibling folder that replaces the old one only when complete,
and records its metrics in ``out_dir/metrics.json`` under ``"atlas"`` / ``"project"``.

Mesh: the synthetic scan's ground-truth mesh (``mesh="ground_truth"``) or a mesh file
(``mesh=<path>``, e.g. the ``mesh`` stage's ``out/mesh/mesh.ply``; ``facegeo reconstruct``
chooses, see :mod:`facegeo.pipeline.reconstruct`).
Rig: ``rig="ground_truth"`` (default when the scan has one) uses the true rig the frames were
rendered with — so the accuracy figures measure the projection, not a rig's error;
``rig="calibrated"`` the ``calibrate`` stage's rig (the chain end to end), ``rig="scan"`` the
scan's (nominal) ``rig.json``, or a rig file.
Shadow-consistent taps (``shadow_taps=True``, the default): where a sample's bilinear taps
straddle a cast-shadow edge, the atlas mesh and the rig's lights decide which taps share the
texel's side and only those are read (:mod:`facegeo.surface.shadows`); per camera
``shadow_edge_samples`` (fraction re-interpolated) and ``seconds_shadow_taps`` (their part of
``seconds_projection``). The rig's lights must be in its world frame (a calibrated rig's are
the scan's nominal ones: its gauge, ≈ 0.2° and 3.6 mm on the small preset, moves a shadow edge
on the skin by ≈ 0.1 mm); wrong light positions pick the wrong side of an edge.

**Engines and formats** (issue 38). Each camera is one task (:func:`project_camera_task`:
small arguments — the loaded scan and rig, paths, settings — and a small dict back) of an
:class:`facegeo.pipeline.engine.Engine`: in process by default (one camera after another, the
same bytes as before engines existed), or on a Dask cluster (``facegeo reconstruct --workers N``
/ ``--scheduler ADDRESS``) whose workers write their camera's folder into the stage's staging
folder; the products are byte-identical whatever the engine (the blend's values too, its
format following the engine and the fields: below), and the metrics gain ``engine``
(workers, memory limit, each camera's worker, seconds and peak memory) on a cluster. Each
camera's working set (:func:`project_working_set`) is checked against a worker's memory before
any task is submitted. A camera may also be split into tasks by blocks of lights
(``lights_per_task``; automatically on a Dask engine when the scan has fewer cameras than 2 ×
the workers and not a whole multiple of them; :mod:`facegeo.pipeline._project_blocks`): its visibility task, then one task per
block writing its lights' columns of the camera's field — the same bytes; metrics ``tasks``
and ``lights_per_task``. The preview follows on the client, in camera order; the blend too in
process, and on a cluster as tasks of whole chunks of texels (:func:`blend_on_engine`: each
reads only its rows of every camera's field and writes its rows of the blend, the same bits).
With ``field_format="zarr"`` each camera's field is the Zarr store ``<camera>/R.zarr`` instead
of ``R.npy``; the later stages find and read either
(:func:`facegeo.surface.reflectance.field_folders`, ``open_field``). The blend is
``R_blend.npy`` in process whatever the format (the same bytes as before); on a cluster it
follows the fields: ``R_blend.npy`` written in place by the tasks for ``.npy`` fields,
``blended/R_blend.zarr`` for Zarr fields, and with ``store=`` the Zarr array in the store beside
the cameras' fields, linked (``R_blend.zarr.url``); :func:`facegeo.surface.reflectance.
open_blended` reads any of them.

The stage never reads the truth: it writes what it measured, and :mod:`facegeo.evaluate`
compares it with references (:mod:`facegeo.evaluate.projection`: the generator's exact shading
and per-pixel hits on synthetic scans). For the comparison it also writes ``rig.json`` (the rig
it used) and per camera ``visibility.npz`` (its occlusion decision: ``in_image``, ``facing``,
``unoccluded`` per texel, and the ``depth_jump`` it used). :func:`run_project`, the standalone
runner, returns the evaluation's figures beside the stage's (``evaluate=True``).

The stage's inputs (:func:`stage_rig`, :func:`load_mesh`, a worker's cached texels and scenes)
and a camera's projection steps live in :mod:`facegeo.pipeline._project_tasks`, re-exported
here; the engine's task functions (:func:`project_camera_task`, :func:`light_visibility_task`,
:func:`light_block_task`) and the blend on an engine (:func:`blend_on_engine`) stay here.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.errors import InputError
from facegeo.fsutil import READ_AHEAD_WORKERS, atomic_write_text, file_sha256, staged_directory
from facegeo.rss import peak_rss_mb
from facegeo.surface.atlas import DEFAULT_SPLIT_FACES
from facegeo.checks import check_positive_int, fmt_value
from facegeo.geometry.mesh import inferred_faces_path  # re-exported

log = logging.getLogger(__name__)

__all__ = ["run_atlas", "run_project", "atlas_products", "project_products", "load_mesh",
           "peak_rss_mb", "project_camera_task", "project_working_set", "stage_rig",
           "blend_on_engine", "blend_task_rows", "blend_working_set", "light_visibility_task",
           "light_block_task",
           "inferred_faces_path", "load_inferred_faces", "INFERRED_TEXELS", "STAGE_RIGS"]

# The evaluation's comparison that run_project(evaluate=True) returns beside the stage's
# figures and its defaults (issue 37; the visibility file it reads: _project_tasks).
from facegeo.evaluate.projection import (  # noqa: E402
    GT_LIGHTS,
    GT_WEIGHT_MIN,
    with_projection_figures,
)
# The stage's inputs and per-camera steps, re-exported (module docstring).
from facegeo.pipeline._project_tasks import (  # noqa: E402
    _INPUTS_CACHE,
    INFERRED_TEXELS,
    PROJECT_BYTES_PER_FACE,
    PROJECT_BYTES_PER_PIXEL,
    PROJECT_BYTES_PER_TEXEL,
    PROJECT_BYTES_PER_TEXEL_LIGHT,
    STAGE_RIGS,
    _camera_inputs,
    _camera_taps,
    _mesh_faces,
    _project_camera,
    _save_visibility,
    _scan,
    _visible_texels,
    load_inferred_faces,
    load_mesh,
    project_working_set,
    stage_rig,
)


#: File in the ``project`` folder naming the atlas its fields index (SHA-256 of texels.npz).
ATLAS_FINGERPRINT = "atlas.sha256"


def check_projection_atlas(project_dir, texels_path) -> None:
    """Raise an InputError when the fields in ``project_dir`` were projected onto another
    atlas than ``texels_path`` (``texel_index.npy`` would index the wrong texels: an atlas
    rebuilt with other settings after the projection). Projections written before the
    fingerprint was recorded are not checked (their index ranges still are, by the readers)."""
    f = Path(project_dir) / ATLAS_FINGERPRINT
    if not f.is_file():
        return
    if f.read_text(encoding="utf-8").strip() != file_sha256(texels_path):
        raise InputError(f"{project_dir} was projected onto another atlas than {texels_path} "
                         f"(the atlas was rebuilt after the projection); re-run 'facegeo "
                         f"project' (or 'facegeo reconstruct') so the fields index this atlas")


def _record(out_dir: Path, stage_dir: Path, name: str, settings: dict, metrics: dict) -> None:
    from facegeo.pipeline.cache import record_metrics

    atomic_write_text(stage_dir / "stage.json", json.dumps(
        {"stage": name, "settings": settings, "metrics": metrics}, indent=2, sort_keys=True))
    record_metrics(out_dir, name, metrics)


def atlas_products(scan, dest: Path, *, mesh: str, texels_per_mm: float | None,
                    size: int | None, padding: int, split_faces: int | None,
                    repair: bool) -> dict:
    from facegeo.surface.atlas import build_atlas, export_mesh_uv, rasterize_texels

    t0 = time.perf_counter()
    V, F, what = load_mesh(scan, mesh)
    atlas = build_atlas(V, F, texels_per_mm=texels_per_mm, size=size, padding=padding,
                        split_faces=split_faces, repair=repair)
    t1 = time.perf_counter()
    texels = rasterize_texels(atlas)
    t2 = time.perf_counter()
    atlas.save(dest / "atlas.npz")
    texels.save(dest / "texels.npz")
    export_mesh_uv(atlas, dest / "mesh_uv.obj")
    export_mesh_uv(atlas, dest / "mesh_uv.glb")
    inferred = {}
    flags = load_inferred_faces(scan, mesh, len(F))
    if flags is not None:
        on_inferred = flags[atlas.face_map][texels.face]
        np.save(dest / INFERRED_TEXELS, on_inferred)
        inferred = {"inferred_faces": int(flags[atlas.face_map].sum()),
                    "inferred_texels": int(on_inferred.sum()),
                    "inferred_texel_fraction": round(float(on_inferred.mean())
                                                     if len(texels) else 0.0, 6)}
    return {
        "mesh": what, "faces": int(len(F)), "vertices": int(len(V)),
        "dropped_degenerate": int(atlas.report.degenerate_faces.size),
        "dropped_nonmanifold": int(atlas.report.nonmanifold_faces.size),
        "pieces": atlas.n_pieces, "charts": atlas.n_charts,
        "utilization": round(atlas.meta.get("utilization", float("nan")), 4),
        "width": atlas.width, "height": atlas.height,
        "texels_per_mm": round(atlas.texels_per_metre / 1000.0, 6),
        "texels": int(len(texels)),
        "texel_fill": round(len(texels) / (atlas.width * atlas.height), 4),
        "seconds_xatlas": round(atlas.seconds, 4),
        "seconds_parameterise": round(t1 - t0, 4),
        "seconds_rasterise": round(t2 - t1, 4),
        "seconds": round(time.perf_counter() - t0, 4),
        "peak_rss_mb": round(peak_rss_mb(), 1),
        **inferred,
    }


def run_atlas(scan_dir, out_dir=None, *, mesh: str = "ground_truth",
              texels_per_mm: float | None = 1.0, size: int | None = None, padding: int = 2,
              split_faces: int | None = DEFAULT_SPLIT_FACES, repair: bool = False) -> dict:
    """Build the atlas and texel table of a scan's mesh into ``out_dir/atlas/``.

    Parameters
    ----------
    scan_dir : path-like or Scan
    out_dir : path-like, optional
        Default the scan's ``out/``.
    mesh : str
        ``"ground_truth"`` or a mesh file (metres); its ``<stem>_inferred.npy``, when there
        is one, marks inferred faces (module docstring).
    texels_per_mm, size, padding, split_faces, repair
        See :func:`facegeo.surface.atlas.build_atlas` (give ``size`` with
        ``texels_per_mm=None``).

    Returns
    -------
    dict
        Metrics: ``texels``, atlas size, charts, ``seconds`` (and its parts), ``peak_rss_mb``.
    """
    scan = _scan(scan_dir)
    out = Path(out_dir) if out_dir is not None else scan.out_dir
    settings = {"mesh": mesh, "texels_per_mm": texels_per_mm, "size": size,
                "padding": padding, "split_faces": split_faces, "repair": repair}
    with staged_directory(out / "atlas") as tmp:
        metrics = atlas_products(scan, tmp, **settings)
        _record(out, tmp, "atlas", settings, metrics)
    return metrics


def run_project(scan_dir, out_dir=None, *, rig: str | None = None, mesh: str = "ground_truth",
                min_cos: float | None = None, feather_px: float | None = None,
                depth_jump: float | None = None, dtype: str = "float16",
                block_lights: int | None = None, gt_lights: int = GT_LIGHTS,
                gt_weight_min: float = GT_WEIGHT_MIN, cameras: list[str] | None = None,
                atlas_settings: dict | None = None, shadow_taps: bool = True,
                evaluate: bool = True, field_format: str = "npy", engine=None,
                progress=None, store=None, lights_per_task: int | None = None) -> dict:
    """Project every camera's OLAT frames onto the atlas texels into ``out_dir/project/``.

    Parameters
    ----------
    scan_dir : path-like or Scan
    out_dir : path-like, optional
        Default the scan's ``out/``; ``out_dir/atlas/`` is built first when missing.
    rig : str, optional
        Which rig places the cameras: ``"ground_truth"``, ``"scan"``, ``"calibrated"`` or a rig
        file (:func:`stage_rig`).
    mesh : str
        The mesh the texels lie on (must be the atlas's mesh).
    min_cos, feather_px, depth_jump
        See :func:`facegeo.surface.reflectance.camera_visibility`.
    dtype, block_lights
        See :func:`facegeo.surface.reflectance.project_camera`.
    shadow_taps : bool
        Interpolate samples whose bilinear taps straddle a cast-shadow edge from the taps on the
        texel's side, deciding lit and shadowed with the atlas mesh and the rig's lights
        (:mod:`facegeo.surface.shadows`); False: plain bilinear everywhere. Needs the rig's
        lights; without them the projection is plain bilinear and ``shadow_taps`` reads false.
    gt_lights, gt_weight_min
        The evaluation's comparison with the generator (``evaluate``): at most this many
        lights (a stratified subset, :data:`facegeo.evaluate.projection.GT_LIGHTS` by
        default); texels above this weight.
    cameras : list of str, optional
        Default every camera of the scan.
    atlas_settings : dict, optional
        Keyword arguments for :func:`run_atlas` when the atlas is missing.
    field_format : {"npy", "zarr"}
        How each camera's field is stored: ``<camera>/R.npy`` (default) or the Zarr store
        ``<camera>/R.zarr`` chunked along texels and lights
        (:func:`facegeo.surface.reflectance.project_camera`); the readers
        (:func:`facegeo.surface.reflectance.open_field`, :func:`~facegeo.surface.reflectance.
        field_folders`) take either. The blend is ``blended/R_blend.npy`` in process, and on a
        cluster follows the fields (:func:`blend_on_engine`).
    store : path-like or str, optional
        ``--store URL``: the fields as Zarr arrays in this folder or fsspec store, linked from
        the stage folder (:func:`project_products`).
    engine : facegeo.pipeline.engine.Engine, optional
        Where the cameras' tasks run (default in process, one camera after another;
        :func:`facegeo.pipeline.engine.make_engine` for ``--workers`` / ``--scheduler``; the
        workers must see the scan and ``out_dir`` at the same paths).
    progress : callable(stage, done, total), optional
        Called as cameras finish (as lights are projected when cameras are split into light
        blocks).
    lights_per_task : int, optional
        Split each camera's projection into tasks of this many lights (rounded up to whole
        chunks of the field's ``block_lights``; :mod:`facegeo.pipeline._project_blocks`): a
        visibility task per camera, then one task per block of lights, writing disjoint
        columns of the camera's field — the same bytes as one task per camera. None (default):
        one task per camera in process, and on a Dask engine the automatic rule — split when
        the scan has fewer cameras than 2 × the workers and not a whole multiple of them, into
        blocks of at least 256 lights making at least 2 × workers tasks
        (:func:`facegeo.pipeline._project_blocks.auto_lights_per_task`); at least the scan's
        lights: one task per camera. Not with ``store``; ``.npy`` fields only with every worker
        on one machine (the columns are written in place through a memory map).
    evaluate : bool
        After the stage, compare its products with the scan's references
        (:func:`facegeo.evaluate.projection.evaluate_projection`) and return the figures
        beside the stage's metrics (and record them in ``out_dir/metrics.json``); the stage
        itself (:func:`project_products`) never reads the truth.

    Returns
    -------
    dict
        ``texels``, ``cameras`` (per camera ``visible_fraction``, ``weighted_texels``,
        ``seconds_visibility``, ``seconds_projection``, ``texels_per_second``,
        ``masked_samples``; with ``evaluate`` on synthetic scans ``visibility_agreement``, the
        ``projection_*`` figures and ``seconds_projection_error``), ``unseen_fraction``,
        ``blended_texels``, ``seconds_blend``, ``tasks`` (the projection's tasks, the blend's
        not counted), ``lights_per_task`` (None: one task per camera), ``seconds``,
        ``peak_rss_mb``; with ``evaluate``
        ``projection_rel_rmse`` and its companions (synthetic scans,
        :mod:`facegeo.evaluate.projection`).
    """
    scan = _scan(scan_dir)
    if evaluate:
        gt_lights = check_positive_int(gt_lights, "gt_lights")
    out = Path(out_dir) if out_dir is not None else scan.out_dir
    atlas_dir = out / "atlas"
    if not (atlas_dir / "texels.npz").is_file():
        run_atlas(scan, out, mesh=mesh, **(atlas_settings or {}))
    with staged_directory(out / "project") as tmp:
        metrics, settings = project_products(
            scan, atlas_dir, tmp, rig=rig, mesh=mesh, min_cos=min_cos, feather_px=feather_px,
            depth_jump=depth_jump, dtype=dtype, block_lights=block_lights, cameras=cameras,
            shadow_taps=shadow_taps, field_format=field_format, engine=engine,
            progress=progress, store=store, lights_per_task=lights_per_task)
        _record(out, tmp, "project", settings, metrics)
    if evaluate:
        from facegeo.pipeline.cache import record_metrics

        metrics = with_projection_figures(scan, out, metrics, gt_lights=gt_lights,
                                          gt_weight_min=gt_weight_min)
        record_metrics(out, "project", metrics)
    return metrics


def project_products(scan, atlas_dir: Path, dest: Path, *, rig: str | None = None,
                     mesh: str = "ground_truth", min_cos: float | None = None,
                     feather_px: float | None = None, depth_jump: float | None = None,
                     dtype: str = "float16", block_lights: int | None = None,
                     cameras: list[str] | None = None, shadow_taps: bool = True,
                     field_format: str = "npy", engine=None,
                     progress=None, store=None,
                     lights_per_task: int | None = None) -> tuple[dict, dict]:
    """Write the ``project`` products of ``scan`` into ``dest`` from the atlas in ``atlas_dir``.

    The work of :func:`run_project` without the staging (the stage cache of
    :mod:`facegeo.pipeline.cache` stages it too). Returns ``(metrics, settings)``. Besides
    the fields it writes what the evaluation compares (module docstring): ``rig.json`` and
    per camera ``visibility.npz``.

    Each camera is one task of ``engine`` (:func:`project_camera_task`; default in process,
    one camera after another, the same bytes as before engines existed); its working set
    (:func:`project_working_set`) is checked against a worker's memory before any task is
    submitted. The preview runs here afterwards, streaming the cameras' fields chunk by chunk
    in camera order, and so does the blend in process; another engine blends in tasks of
    texel chunks (:func:`blend_on_engine`, the same bits). ``progress(stage, done, total)`` is
    called as cameras finish. With ``lights_per_task`` (or the automatic rule on a Dask
    engine, :mod:`facegeo.pipeline._project_blocks`) a camera is a visibility task and then
    one task per block of lights, all checked against a worker's memory first; the products
    are the same bytes.

    With ``store`` (``--store URL``: a folder or an fsspec URL) the fields are Zarr arrays in
    the store, under ``project/run-<id>/<camera>/R.zarr`` (a new ``<id>`` each run, so a
    cached stage's links never point at a later run's data), and each camera folder of
    ``dest`` holds a link to its field (``R.zarr.url``) beside its small files, which the
    tasks put in the store and this function brings down (then removes from the store): the
    tasks write nothing to a shared disk. When the store also holds the scan (``URL/scan/``,
    :func:`facegeo.pipeline._scan_store.put_scan`, ``facegeo push``) they read nothing from it
    either: this function puts the atlas and a mesh file into ``project/run-<id>/inputs``
    (removed when the tasks are done) and each task fetches them with its camera's OLAT
    frames (:func:`project_camera_task`; ``metrics["frames_from"]``). On a cluster the blend
    is there too, ``project/run-<id>/blended/
    R_blend.zarr``, linked from ``dest/blended``.
    The stage folder — links included — is still swapped in whole; an earlier run's data in
    the store is left there (remove it yourself once no stage folder links to it).
    """
    from facegeo.pipeline.engine import InProcessEngine, Task
    from facegeo.surface import reflectance as rf
    from facegeo.surface.atlas import Texels
    from facegeo.surface.pullpush import pull_push

    if field_format not in rf.FIELD_FORMATS:
        raise InputError(f"field_format: expected one of {', '.join(rf.FIELD_FORMATS)}, got "
                         f"{fmt_value(field_format)}")
    engine = InProcessEngine() if engine is None else engine
    run_loc = None
    if store is not None:  # a field in a store is a Zarr field
        import uuid

        from facegeo.surface._zarr_field import (STORE_FILES, copy_files, remove_location,
                                                 store_location)

        run_loc = store_location(store, "project", f"run-{uuid.uuid4().hex[:12]}")
        field_format = "zarr"
    t_start = time.perf_counter()
    texels = Texels.load(atlas_dir / "texels.npz")
    the_rig, rig_used = stage_rig(scan, rig)
    names = list(cameras) if cameras is not None else scan.cameras_with_frames("olat")
    for n in names:
        if n not in scan.camera_names:
            raise InputError(f"cameras: unknown camera {fmt_value(n)}; the scan has {scan.camera_names}")
    if cameras is None:  # a calibration-only camera (every OLAT frame declared missing)
        for n in scan.camera_names:
            if n not in names:
                log.info("project %s: skipped, every OLAT frame declared missing (a camera of "
                         "the calibration only)", n)
    vis_kw = {k: v for k, v in (("min_cos", min_cos), ("feather_px", feather_px),
                                ("depth_jump", depth_jump)) if v is not None}
    block = block_lights or rf.DEFAULT_BLOCK_LIGHTS
    settings = {"rig": rig_used, "mesh": mesh, **vis_kw, "dtype": dtype,
                "block_lights": block, "cameras": names, "shadow_taps": bool(shadow_taps)}
    if field_format != "npy":  # the default leaves stage.json as it was
        settings["field_format"] = field_format
    if run_loc is not None:
        settings["store"] = str(store)
    use_taps = bool(shadow_taps)
    if shadow_taps and (the_rig.lights is None or the_rig.lights.n_lights != scan.n_lights):
        have = "no lights" if the_rig.lights is None else f"{the_rig.lights.n_lights} lights"
        log.warning("project: the rig has %s, the scan's frames %d: samples at shadow edges "
                    "stay plain bilinear (shadow_taps reads false per camera)", have,
                    scan.n_lights)
        use_taps = False
    the_rig.save(dest / "rig.json")  # the rig the fields were projected with (evaluate reads it)
    n_faces = _mesh_faces(scan, mesh)
    inputs_loc = via = None
    if run_loc is not None:
        from facegeo.pipeline._scan_store import has_scan, put_files

        if has_scan(store):  # the tasks read the scan's copy in the store, and the inputs here
            inputs_loc = store_location(run_loc, STORE_INPUTS)
            atlas_files = [Path(atlas_dir) / f for f in ("atlas.npz", "texels.npz",
                                                         INFERRED_TEXELS)]
            put_files([f for f in atlas_files if f.is_file()],
                      store_location(inputs_loc, "atlas"))
            if mesh != "ground_truth":
                put_files([f for f in (Path(mesh), inferred_faces_path(mesh)) if f.is_file()],
                          store_location(inputs_loc, "mesh"))
            via = {"inputs": str(inputs_loc)}
    # the loaded scan and rig travel as they are (kilobytes); each task loads the atlas, the
    # texels and the mesh itself (once per process: _camera_inputs)
    from facegeo.pipeline import _project_blocks as pb

    chunk = min(block, scan.n_lights)  # the field's lights per chunk
    lpt = pb.plan_lights_per_task(lights_per_task, engine=engine, n_cameras=len(names),
                                  n_lights=scan.n_lights, chunk=chunk,
                                  field_format=field_format, in_store=run_loc is not None)
    scratch = str(dest / pb.SCRATCH_DIR)
    whole, visibility, blocks = [], [], []
    split: dict[str, list[str]] = {}  # camera -> its visibility task and light blocks
    for name in names:
        camera = the_rig.camera(name)
        if lpt is not None and scan.camera_frames("olat", name) == list(range(scan.n_lights)):
            common = (scan, str(atlas_dir), str(dest), name, the_rig, mesh)
            visibility.append(Task(f"{name} visibility", light_visibility_task,
                                   (*common, vis_kw, dtype, chunk, use_taps, field_format,
                                    scratch),
                                   working_set=project_working_set(camera, len(texels),
                                                                   n_faces, 0, use_taps),
                                   size=0))
            split[name] = [visibility[-1].name]
            for l0, l1 in pb.light_blocks(scan.n_lights, lpt):
                blocks.append(Task(f"{name} lights {l0}:{l1}", light_block_task,
                                   (*common, dtype, (l0, l1), chunk, use_taps, field_format,
                                    scratch),
                                   working_set=project_working_set(
                                       camera, len(texels), n_faces, min(chunk, l1 - l0),
                                       use_taps),
                                   size=l1 - l0))
                split[name].append(blocks[-1].name)
            continue
        task_via = None
        if via is not None:
            from facegeo.pipeline._scan_store import olat_task_files, scan_location

            task_via = {**via, "frames_from": str(scan_location(store)),
                        "files": olat_task_files(scan, name,
                                                 ground_truth_mesh=mesh == "ground_truth")}
        whole.append(Task(name, project_camera_task,
                          (scan, str(atlas_dir), str(dest), name, the_rig, mesh, vis_kw, dtype,
                           block, use_taps, field_format,
                           None if run_loc is None else str(store_location(run_loc, name)),
                           task_via),
                          working_set=project_working_set(camera, len(texels), n_faces, chunk,
                                                          use_taps),
                          size=1 if lpt is None else scan.n_lights))
    try:
        results = pb.run_rounds(engine, whole, visibility, blocks, progress)
    finally:  # in process the scenes go with the stage (a worker keeps one set for the next run)
        _INPUTS_CACHE.clear()
        pb.remove_scratch(dest)
        if inputs_loc is not None:
            remove_location(inputs_loc)
    per_cam: dict[str, Any] = {}
    for name in names:  # camera order
        if name in split:
            vis_task, *block_tasks = split[name]
            per_cam[name] = pb.camera_block_metrics(
                results[vis_task]["metrics"], [results[b]["metrics"] for b in block_tasks],
                scan.n_lights)
        else:
            per_cam[name] = results[name]["metrics"]
    tasks = whole + visibility + blocks
    if run_loc is not None:  # the tasks' small files, from the store into the stage folder
        for name in names:
            copy_files(store_location(run_loc, name, STORE_FILES), dest / name)
            remove_location(store_location(run_loc, name, STORE_FILES))  # down: not kept twice
    T = len(texels)
    seen = np.zeros(T, bool)
    colour = np.zeros((T, 3))
    wsum = np.zeros(T)
    for name in names:  # camera order, whatever order the tasks finished in
        idx = np.load(dest / name / "texel_index.npy")
        weight = np.load(dest / name / "weight.npy")
        seen[idx] = True
        for s, chunk in rf.iter_field_chunks(dest / name):
            sl = idx[s:s + len(chunk)]
            w = weight[s:s + len(chunk)].astype(np.float64)
            m = np.nanmean(chunk, axis=1)
            ok = np.isfinite(m).all(axis=1)
            colour[sl[ok]] += w[ok, None] * m[ok]
            wsum[sl[ok]] += w[ok]
    np.save(dest / "seen.npy", seen)
    t_b = time.perf_counter()
    blend_names: list[str] = []
    if engine.kind == "in-process":  # one loop here, as before engines existed (the same bytes)
        blended = rf.blend_fields([dest / n for n in names], dest / BLEND_DIR, dtype=dtype)
    else:  # tasks per chunk of texels, each reading its rows of the fields where they are
        blended, blend_names = blend_on_engine(engine, [dest / n for n in names],
                                               dest / BLEND_DIR, dtype=dtype,
                                               store_dir=None if run_loc is None
                                               else store_location(run_loc, BLEND_DIR))
    seconds_blend = time.perf_counter() - t_b
    preview = np.where(wsum[:, None] > 0, colour / np.maximum(wsum, 1e-30)[:, None], np.nan)
    img = pull_push(texels.to_image(preview), texels.to_image(
        np.where(wsum > 0, 1.0, 0.0), fill=0.0))
    import cv2

    scale = np.nanpercentile(preview, 99) if np.isfinite(preview).any() else 1.0
    png = np.clip(np.nan_to_num(img) / max(scale, 1e-12), 0, 1) ** (1 / 2.2)
    cv2.imwrite(str(dest / "preview.png"),
                (png[..., ::-1] * 255 + 0.5).astype(np.uint8))
    atomic_write_text(dest / ATLAS_FINGERPRINT, file_sha256(atlas_dir / "texels.npz") + "\n")
    metrics: dict[str, Any] = {
        "texels": int(T), "lights": int(scan.n_lights), "rig": rig_used,
        "cameras": per_cam,
        "unseen_fraction": round(float(1 - seen.mean()) if T else 0.0, 6),
        "blended_texels": int(blended.texel_index.size),
        "seconds_blend": round(seconds_blend, 4),
        "tasks": len(tasks), "lights_per_task": lpt,
    }
    metrics["seconds"] = round(time.perf_counter() - t_start, 4)
    metrics["peak_rss_mb"] = round(peak_rss_mb(), 1)
    if run_loc is not None:  # where the tasks read the frames, the atlas and the mesh
        metrics["frames_from"] = "store" if via is not None else "scan folder"
    if engine.kind != "in-process":
        metrics["engine"] = engine.stage_metrics("project",
                                                 [t.name for t in tasks] + blend_names)
    return metrics, settings


#: Folder of the blend, in the stage folder and (``store=``) beside the cameras in the store.
BLEND_DIR = "blended"
#: Rows (texels) of the blend a task computes at most, whatever a worker's memory allows (as a
#: fit task's 16,384 functions: enough to amortise opening every camera's field).
BLEND_TASK_TEXELS = 16384
#: Bytes a blend task needs per sample (texel × light × channel) of its rows: the float32
#: numerator and denominator (8 B), the block written (≤ 4 B) and one camera's rows read
#: (widened to float32 with the numpy path's masks and products: ≤ 20 B).
BLEND_BYTES_PER_SAMPLE = 32
#: ... per row and camera: the row's place in the block (int64) and weight (float32), sent
#: with the task.
BLEND_BYTES_PER_ROW_CAMERA = 12


def blend_working_set(n_rows: int, n_lights: int, n_cameras: int) -> int:
    """Memory (bytes) of one blend task of ``n_rows`` texels: :data:`BLEND_BYTES_PER_SAMPLE`
    × its samples (``n_rows × n_lights × 3``) + :data:`BLEND_BYTES_PER_ROW_CAMERA` × rows ×
    cameras (an upper bound: every camera counted as seeing every row)."""
    n = int(n_rows)
    return n * (int(n_lights) * 3 * BLEND_BYTES_PER_SAMPLE
                + int(n_cameras) * BLEND_BYTES_PER_ROW_CAMERA)


def blend_task_rows(n_lights: int, n_cameras: int, field_chunk: int,
                    budget: int | None) -> tuple[int, int]:
    """``(rows, chunk)``: texels per blend task and per chunk of a Zarr blend.

    As many rows as fit ``budget`` (a worker's task budget; None: unlimited) by
    :func:`blend_working_set`, at most :data:`BLEND_TASK_TEXELS`; rounded down to whole
    ``field_chunk`` (the fields' texels per stored chunk) when that many fit, and then the
    blend's chunk is the fields' (a task writes whole chunks of it), else the blend's chunk is
    the task's rows."""
    rows = int(BLEND_TASK_TEXELS)
    if budget is not None:
        per_row = blend_working_set(1, n_lights, n_cameras)
        rows = min(rows, max(1, int(budget) // per_row))
    unit = max(1, int(field_chunk))
    if rows >= unit:
        return rows - rows % unit, unit
    return rows, rows


def blend_on_engine(engine, fields: list, directory: Path, *, dtype: str = "float16",
                    store_dir=None):
    """The blend of :func:`facegeo.surface.reflectance.blend_fields` — the same values, bit
    for bit — as tasks of ``engine``, one per chunk of texels (:func:`blend_task_rows`), each
    reading only its rows of each camera's field (:func:`~facegeo.surface.reflectance.
    blend_rows_task`) where the field is (an ``.npy`` memory map, a Zarr store, a store linked
    from the camera folder).

    Where the blend goes follows the fields: ``.npy`` fields (the workers share the stage
    folder) — ``directory/R_blend.npy``, created whole here, each task writing its rows in
    place; Zarr fields — the Zarr array ``directory/R_blend.zarr`` chunked along texels (each
    task writes whole chunks: no lock); with ``store_dir`` (``store=``), whatever the fields,
    the array ``store_dir/R_blend.zarr`` linked from ``directory`` (``R_blend.zarr.url``, as
    the cameras' fields are). ``texel_index``, ``weight`` and ``n_cameras`` are written here.

    Returns ``(BlendedField, task names)``.
    """
    from facegeo.pipeline.engine import Task
    from facegeo.surface import reflectance as rf
    from facegeo.surface._zarr_field import (DEFAULT_CHUNK_LIGHTS, DEFAULT_CHUNK_TEXELS,
                                             create_field, link_field)

    if dtype not in ("float16", "float32"):
        raise InputError(f"dtype: expected 'float16' or 'float32', got {fmt_value(dtype)}")
    fields = [Path(f) for f in fields]
    cams, U = rf.blend_sources(fields)
    found = [rf.find_field(f) for f in fields]
    L = int(cams[0][1].shape[1])
    zarr_blend = store_dir is not None or any(kind == "zarr" for kind, _ in found)
    field_chunk = (cams[0][1].chunks[0] if not isinstance(cams[0][1], np.ndarray)
                   else DEFAULT_CHUNK_TEXELS)
    rows, chunk = blend_task_rows(L, len(cams), field_chunk, engine.task_budget())
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if not zarr_blend:  # the workers share this disk: they wrote the fields here
        out = np.lib.format.open_memmap(directory / rf.BLENDED_FILE, mode="w+", dtype=dtype,
                                        shape=(U.size, L, 3))
        del out
        out_loc = str(directory / rf.BLENDED_FILE)
    else:
        out_loc = str(create_field(directory if store_dir is None else store_dir,
                                   (U.size, L, 3), dtype=dtype, name=rf.BLENDED_FILE,
                                   chunks=(chunk, DEFAULT_CHUNK_LIGHTS)))
    compiled = rf.blend_compiled(cams, dtype)
    tasks = []
    for s in range(0, U.size, rows):
        u = U[s:s + rows]
        sources = []
        for (_, _, idx, w), (kind, loc) in zip(cams, found):
            a, b = (int(i) for i in np.searchsorted(idx, [u[0], u[-1] + 1]))
            if b > a:
                sources.append((kind, str(loc), a, b, np.searchsorted(u, idx[a:b]), w[a:b]))
        tasks.append(Task(f"blend {s}:{s + u.size}", rf.blend_rows_task,
                          (sources, out_loc, s, int(u.size), L, dtype, compiled),
                          working_set=blend_working_set(u.size, L, len(sources))))
    engine.map("project", tasks)
    if store_dir is not None:
        link_field(directory, out_loc, name=rf.BLENDED_FILE)
    wsum, ncam = rf.blend_weights(cams, U)
    rf.save_blend_index(directory, U, wsum, ncam)
    log.info("blend: %d cameras -> %d texels × %d lights in %d tasks", len(cams), U.size, L,
             len(tasks))
    return rf.BlendedField(directory, U, wsum, ncam, L), [t.name for t in tasks]


#: Sub-folder of a run's place in the ``--store`` holding the stage inputs the tasks read
#: (the atlas, the mesh), put there by the client when the store holds the scan.
STORE_INPUTS = "inputs"


def project_camera_task(scan, atlas_dir: str, dest: str, name: str, the_rig, mesh: str,
                        vis_kw: dict, dtype: str, block_lights: int, shadow_taps: bool,
                        field_format: str = "npy", store_dir: str | None = None,
                        via: dict | None = None) -> dict:
    """One camera's share of the ``project`` stage, run by an engine (in process or on a
    worker): its visibility, shadow taps and field written into ``dest/<name>``
    (:func:`facegeo.surface.reflectance.project_camera`) with ``visibility.npz``. Returns
    ``{"metrics": ...}``: the camera's metrics, small whatever its size.

    With ``store_dir`` (a folder or fsspec URL in the ``--store``, one per camera) the task
    writes nothing to a shared disk (it reads the scan's frames and the atlas): the Zarr field is written at ``store_dir/R.zarr``, the small files
    (``texel_index``, ``weight``, ``v_world``, ``visibility.npz`` and the field's link) into a
    temporary folder of the worker and copied to ``store_dir/files/``, from where
    :func:`project_products` brings them into ``dest/<name>``.

    ``via`` (the store holds the scan, :func:`facegeo.pipeline._scan_store.put_scan`): the
    task reads nothing from the client's disk either — it fetches its camera's OLAT frames
    (``files`` of the scan's copy ``frames_from``), the atlas and the mesh (``inputs``, put
    there by :func:`project_products`) into its temporary folder and projects from those."""
    if store_dir is None:
        return _project_camera(scan, atlas_dir, Path(dest) / name, name, the_rig, mesh,
                               vis_kw, dtype, block_lights, shadow_taps, field_format, None)
    import tempfile

    from facegeo.surface._zarr_field import STORE_FILES, copy_files, store_location

    with tempfile.TemporaryDirectory(prefix="facegeo-project-") as tmp:
        if via is not None:
            from facegeo.pipeline._scan_store import fetch_scan_files

            scan = fetch_scan_files(scan, via["frames_from"], via["files"], Path(tmp) / "scan")
            atlas_dir = str(Path(tmp) / "atlas")
            copy_files(store_location(via["inputs"], "atlas"), atlas_dir)
            if mesh != "ground_truth":
                copy_files(store_location(via["inputs"], "mesh"), Path(tmp) / "mesh")
                mesh = str(Path(tmp) / "mesh" / Path(mesh).name)
        d = Path(tmp) / name
        out = _project_camera(scan, atlas_dir, d, name, the_rig, mesh, vis_kw, dtype,
                              block_lights, shadow_taps, "zarr", store_dir)
        copy_files(d, store_location(store_dir, STORE_FILES))
    return out


def light_visibility_task(scan, atlas_dir: str, dest: str, name: str, the_rig, mesh: str,
                          vis_kw: dict, dtype: str, chunk: int, shadow_taps: bool,
                          field_format: str, scratch: str) -> dict:
    """The visibility task of a camera split into blocks of lights
    (:mod:`facegeo.pipeline._project_blocks`): its visibility (:func:`_visible_texels`, as a
    whole camera's task), small files, ``visibility.npz`` and empty field in ``dest/<name>``
    (:func:`~facegeo.pipeline._project_blocks.prepare_split_camera`). Returns
    ``{"metrics": ...}``."""
    from facegeo.pipeline import _project_blocks as pb

    scan = _scan(scan)
    d = Path(dest) / name
    _, _, _, vis, inferred_seen, t_vis = _visible_texels(scan, atlas_dir, name, the_rig, mesh,
                                                         vis_kw, shadow_taps)
    entry = pb.prepare_split_camera(d, vis, scan.n_lights, dtype, chunk, field_format, scratch,
                                    name)
    _save_visibility(d, vis, vis_kw)
    entry["seconds_visibility"] = round(t_vis, 4)
    if inferred_seen is not None:
        entry["inferred_texels_unmeasured"] = inferred_seen
    return {"metrics": entry}


def light_block_task(scan, atlas_dir: str, dest: str, name: str, the_rig, mesh: str,
                     dtype: str, lights: tuple[int, int], chunk: int, shadow_taps: bool,
                     field_format: str, scratch: str) -> dict:
    """One block of lights ``(l0, l1)`` of a camera split into blocks
    (:mod:`facegeo.pipeline._project_blocks`), after its visibility task: the camera's shadow
    taps rebuilt for the saved texels, then only these lights' OLAT frames projected into
    their columns of the field (:func:`~facegeo.pipeline._project_blocks.
    project_light_block`). Returns ``{"metrics": ...}`` with ``seconds_projection``."""
    from facegeo.pipeline import _project_blocks as pb

    scan = _scan(scan)
    texels, _, shadow_rays, _ = _camera_inputs(scan, Path(atlas_dir), mesh, shadow_taps)
    camera = the_rig.camera(name)
    d = Path(dest) / name
    sel, q = pb.load_selection(d, scratch, name)
    t0 = time.perf_counter()
    taps = _camera_taps(shadow_rays, camera, q, texels, sel, the_rig.lights)
    frames = scan.iter_olat(name, range(int(lights[0]), int(lights[1])), return_mask=True,
                            read_ahead=READ_AHEAD_WORKERS, black_clipped="dark")
    out = pb.project_light_block(frames, d, q, (camera.width, camera.height), name, lights,
                                 chunk, dtype, taps, field_format)
    out["seconds_projection"] = round(time.perf_counter() - t0, 4)
    log.info("project %s: lights %d:%d, %d texels in %.2f s", name, lights[0], lights[1],
             sel.size, out["seconds_projection"])
    return {"metrics": out}


