"""Pipeline stage ``fit``: the paper's skin model fitted to every camera's projected field.

``run_fit(scan_dir, out_dir=None, **settings)`` reads ``out/atlas/`` and ``out/project/`` and
writes ``out/fit/``:

    <camera>/fit.npz, <camera>/D.npy   per fitted texel: what
                                       :func:`facegeo.appearance.skin.resynthesize` needs
                                       (:mod:`facegeo.render._fitstore`; S = R − D from the field)
    normal.exr/.png, albedo.exr/.png,  Fig. 14-style atlas maps (b: normals, c: diffuse albedo
    specular.exr/.png                  ρ_d, d: specular energy ρ_s), blended over cameras by the
                                       projection weights; 0 where nothing was fitted
    fitted.png                         255 where a texel has a fit
    mosaic.png                         Fig. 3-style mosaic of measured reflectance functions (each
                                       a lat-long image of the light grid, θ across, φ down,
                                       tone-mapped on its own)
    stage.json

The fit runs in chunks of ``chunk`` functions read from the memory-mapped field (bounded
memory). It is slow (hundreds of functions per second at 128 lights), so ``texels`` selects
what to fit: ``"all"`` texels a camera measured, or ``"views"``: only texels some listed view
needs (the renderer's bilinear taps, :func:`facegeo.render.trace_view`); ``max_texels``
subsamples each camera's selection evenly (the tiny preset, tests). The renderer falls back to
a texel's measured function where it has no fit (counted as ``unfitted``).

Metrics: per camera ``functions``, ``seconds``, ``functions_per_second``, ``valid_functions``,
flag counts (``masked``: functions with masked samples, each left out alone); ``valid_functions``
overall (0 is logged as a warning with the flag counts). The stage reads no truth: the fits'
errors against a synthetic scan's generator (normals, albedo, ρs, resynthesis at turned views)
are computed from these products by :mod:`facegeo.evaluate.skin_fit` (``facegeo evaluate``, the
``evaluate`` stage of ``facegeo reconstruct``; its settings ``gt_functions``, ``gt_angles``).

**A single-view scan without geometry** (Yale B, DiLiGenT: one camera, a light list, no
structured light, no mesh) is fitted in image space instead — every masked pixel a texel, the
per-pixel photometric models of :mod:`facegeo.appearance.photometric` chosen by
cross-validation over the lights, the held-out lights scored against the Lambertian least
squares: :func:`fit_image_products` (:mod:`facegeo.pipeline._fit_image`; settings
:data:`IMAGE_FIT_SETTINGS`, ``hold_out`` every other light by default). ``run_fit`` and
``facegeo reconstruct`` take that path when :func:`image_space_scan` says so.

**Near-field light stages** (``near_field="auto"``, default): the generator's stage (radius
1.5 m) is not distant from a head ≈ 0.1 m across — the light directions move by up to ≈ 4°
and their falloff by ±14 % over the face. The fit takes each texel's offset from the stage
centre and fits each light where it is
(:func:`facegeo.appearance.skin.fit_reflectance_near`); the renderer's resynthesis and the
evaluation's use the same geometry (Eq. 9 with true directions, :func:`_near_field`).
docs/skin.md, "Near-field light stages".
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.checks import check_positive_int, fmt_value
from facegeo.errors import InputError
from facegeo.fsutil import staged_directory
from facegeo.pipeline._fit_image import IMAGE_FIT_SETTINGS, fit_image_products, image_space_scan
from facegeo.render.novel import even_subset

log = logging.getLogger(__name__)

__all__ = ["FIT_SETTINGS", "FIT_TASK_CHUNKS", "IMAGE_FIT_SETTINGS", "default_views",
           "fit_chunk_task", "fit_products", "fit_image_products", "fit_working_set",
           "image_space_scan", "needed_texels", "run_fit"]

#: Default settings of the ``fit`` stage (JSON-serialisable, part of its cache key).
FIT_SETTINGS: dict[str, Any] = {
    "texels": "all", "views": None, "max_texels": None, "eta": 1.4, "chunk": 2048,
    "diffuse_dtype": "float16", "mosaic": 8, "rig": None, "polish": None, "supersample": 1,
    "near_field": "auto", "store": None,
}


def default_views(cameras: list[str], novel: list[str] = ()) -> list[str]:
    """The novel views the demo renders: every source camera, ±30° and ±60° orbits of the
    rig's frontal camera (:func:`facegeo.render.front_camera`), and the generator's novel
    cameras."""
    from facegeo.render._cameras import FRONT, NOVEL_ORBITS

    return list(cameras) + [f"orbit:{FRONT}:{d:g}" for d in NOVEL_ORBITS] + list(novel)


def _camera_table(scan, rig) -> dict:
    """Cameras a view spec may name: the rig's, the generator's novel ones, and ``front``
    (:func:`facegeo.render.front_camera`) made from the capture cameras alone — the cameras
    with OLAT frames, so that neither the generator's novel cameras nor a calibration-only
    witness camera moves the rig's frontal view and the orbits around it."""
    import json

    from facegeo.geometry.camera import Camera
    from facegeo.render._cameras import FRONT, front_camera

    cams = {c.name: c for c in rig.cameras}
    capture = scan.cameras_with_frames("olat") if scan.has("olat") else []
    capture = [n for n in capture if n in cams] or list(cams)
    front = front_camera({n: cams[n] for n in capture}) if capture else None
    if "novel_cameras" in scan.ground_truth_keys:
        for d in json.loads(scan.ground_truth_path("novel_cameras").read_text(encoding="utf-8")):
            c = Camera.from_dict(d, where="ground_truth/novel_cameras.json")
            cams[c.name] = c
    if front is not None and FRONT not in cams:
        cams[FRONT] = front
    return cams


def needed_texels(specs, cameras: dict, atlas, texels, scene=None, *,
                  supersample: int = 1) -> np.ndarray:
    """Sorted texels any of the views ``specs`` needs (their bilinear taps), traced with
    ``supersample × supersample`` rays per pixel (the render's own samples)."""
    from facegeo.render import atlas_scene, parse_camera_spec, trace_view

    scene = scene if scene is not None else atlas_scene(atlas)
    parts = [trace_view(parse_camera_spec(s, cameras), scene, atlas, texels,
                        supersample=supersample).needed_texels
             for s in specs]
    return np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)


def _check_settings(*, texels="all", max_texels=None, chunk=1, supersample=1,
                    near_field="auto", **others) -> None:
    moved = sorted({"gt_functions", "gt_angles"} & set(others))
    if moved:  # issue 37: the stage reads no truth; its comparison is the evaluation's
        raise InputError(f"{', '.join(moved)}: a setting of the evaluation now, not of the fit "
                         "(facegeo.evaluate.run_evaluate(..., gt_functions=…, gt_angles=…), or "
                         "settings={'evaluate': {...}} of facegeo reconstruct)")
    if texels not in ("all", "views"):
        raise InputError(f"texels: expected 'all' or 'views', got {fmt_value(texels)}")
    if near_field not in ("auto", "off"):
        raise InputError(f"near_field: expected 'auto' or 'off', got {fmt_value(near_field)}")
    check_positive_int(supersample, "supersample")
    if max_texels is not None and int(max_texels) < 1:
        raise InputError(f"max_texels: expected a positive count, got {fmt_value(max_texels)}")
    if int(chunk) < 1:
        raise InputError(f"chunk: expected a positive count, got {fmt_value(chunk)}")


def _write_maps(dest: Path, texels, acc: dict, wsum: np.ndarray) -> dict:
    from facegeo.capture import imageio
    from facegeo.capture.response import encode

    fitted = wsum > 0
    safe = np.where(fitted, wsum, 1.0)
    normal = acc["normal"] / safe[:, None]
    nn = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.where(fitted[:, None] & (nn > 0), normal / np.where(nn > 0, nn, 1.0), 0.0)
    rho_d = np.where(fitted[:, None], acc["rho_d"] / safe[:, None], 0.0)
    rho_s = np.where(fitted, acc["rho_s"] / safe, 0.0)
    files = {}
    img_n = texels.to_image(normal.astype(np.float32), fill=0.0)
    files["normal"] = imageio.write_image(dest / "normal.exr", img_n)
    imageio.write_image(dest / "normal.png", np.where(
        texels.to_image(fitted, fill=False)[..., None],
        np.clip((img_n + 1.0) * 127.5 + 0.5, 0, 255), 0).astype(np.uint8))
    img_d = texels.to_image(rho_d.astype(np.float32), fill=0.0)
    files["albedo"] = imageio.write_image(dest / "albedo.exr", img_d)
    imageio.write_image(dest / "albedo.png", encode(np.clip(img_d, 0, 1), "srgb", np.uint8))
    img_s = texels.to_image(rho_s.astype(np.float32), fill=0.0)
    files["specular"] = imageio.write_image(dest / "specular.exr", img_s)
    top = float(np.percentile(rho_s[fitted], 99)) if fitted.any() else 1.0
    imageio.write_image(dest / "specular.png",
                        encode(np.clip(img_s / max(top, 1e-12), 0, 1), "srgb", np.uint8))
    imageio.write_image(dest / "fitted.png",
                        (texels.to_image(fitted, fill=False) * 255).astype(np.uint8))
    return {k: Path(v).name for k, v in files.items()}


def reflectance_mosaic(R, n_theta: int, n_phi: int, *, scale: int = 4, cols: int = 8,
                       gap: int = 1) -> np.ndarray:
    """Fig. 3-style mosaic ``(H, W, 3)`` uint8 of reflectance functions ``(N, L, 3)``.

    Each function is shown as a lat-long image of the light grid (θ across, φ down; the light
    order of docs/conventions.md, θ fastest), magnified ``scale`` times, tone-mapped by its
    own 99th percentile, sRGB.
    """
    from facegeo.capture.response import encode

    R = np.nan_to_num(np.asarray(R, np.float32))
    N = R.shape[0]
    rows = max(1, -(-N // cols))
    th, tw = n_phi * scale, n_theta * scale
    out = np.zeros((rows * (th + gap) + gap, cols * (tw + gap) + gap, 3), np.float32)
    for k in range(N):  # a handful of tiles, not a per-texel loop
        img = R[k].reshape(n_phi, n_theta, 3)
        top = float(np.percentile(img, 99))
        img = np.repeat(np.repeat(img / max(top, 1e-12), scale, 0), scale, 1)
        r, c = divmod(k, cols)
        out[gap + r * (th + gap):gap + r * (th + gap) + th,
            gap + c * (tw + gap):gap + c * (tw + gap) + tw] = img
    return encode(np.clip(out, 0, 1), "srgb", np.uint8)


def fit_chunks(field, rows, v_world, lights, writer, texel_index, *, eta: float = 1.4,
               depth=None, chunk: int = 2048, threads: int = 1, near=None,
               per_row: bool = True):
    """Fit rows ``rows`` of a camera's projected field chunk by chunk into ``writer``; yields
    ``(rows of the chunk, SkinFit, finite)`` per chunk (the fit stage's loop, also timed by
    ``facegeo bench skin.fit_stream``).

    Bounded memory and no fresh memory per chunk: the rows are gathered and widened to float32
    into reused buffers (one compiled pass for a float16 field); D is written by the fit
    straight into a reused buffer of the store's dtype, from which the writer stores it; S is
    not formed (the store keeps D; S = R − D). Non-finite samples (the projection's masked
    pixels: black-clipped, saturated or non-finite) are masked sample by sample
    (``fit_reflectance(masked=…)``: left out of the analysis, D = 0 there, ``FLAG_MASKED``);
    ``finite`` is False for a function that had any. A 16-bit PNG scan's black-clipped
    shadows are masked in every function, so masking whole functions fitted none of them.
    Pipelined: while one
    chunk is fitted (on a background thread, which runs ``fit_reflectance`` and its
    ``threads`` workers), the next chunk's rows are read, the previous chunk is stored and the
    caller handles its results, so the cores do not wait for the serial steps (two sets of
    buffers: a yielded fit's ``diffuse`` is overwritten after the generator resumes; copy it
    to keep it). The results are those of fitting each chunk in turn.

    Parameters
    ----------
    field : (T, L, C) float16 or float32 array or memmap
    rows : (n,) int, increasing — the rows to fit
    v_world : (T, 3) float64 — toward the camera, per row
    lights : LightSet
    writer : FitWriter — announced for ``n`` functions
    texel_index : (T,) int — each row's texel
    eta, depth, chunk, threads — as :func:`facegeo.appearance.skin.fit_reflectance`
    near : NearField of every row (T rows), optional — a near-field light stage: each chunk is
        fitted by :func:`facegeo.appearance.skin.fit_reflectance_near` (each light where it is)
    per_row : bool — True (default): ``v_world``, ``texel_index`` and ``near`` hold every row
        of the field (indexed by row); False: one entry per entry of ``rows`` (indexed by
        position; a fit task holds only its own functions', :func:`fit_chunk_task`)

    Yields
    ------
    rows : (k,) int64; fit : SkinFit; finite : (k,) bool — no sample of the function was masked
    """
    from concurrent.futures import ThreadPoolExecutor

    from facegeo.appearance.skin import fit_reflectance, fit_reflectance_near
    from facegeo.fsutil import aligned_empty

    rows = np.asarray(rows, np.int64)
    chunk = int(chunk)
    k_max = max(1, min(chunk, rows.size))
    L, C = field.shape[1], field.shape[2]
    starts = list(range(0, rows.size, chunk))
    # a float16 field (a C-contiguous memory map, as the project stage writes it) is gathered
    # and widened in one compiled pass that also finds the non-finite rows: no float16 copy,
    # no separate pass (≈ 4 ms a chunk of 2,048 at 2048 lights against ≈ 38 ms)
    half = field.dtype == np.float16 and field.flags.c_contiguous
    # two sets: (gathered rows, widened rows, D) — chunk q in set q % 2
    sets = [(None if half else np.empty((k_max, L, C), field.dtype),
             np.empty((k_max, L, C), np.float32) if field.dtype != np.float32 else None,
             aligned_empty((k_max, L, C), writer.dtype))  # aligned: a direct write
            for _ in range(min(2, len(starts)))]

    def read(q):
        # chunk q's rows, widened, and their masked samples (None: none), in buffer set q % 2
        rr = rows[starts[q]:starts[q] + chunk]
        gathered, wide, _ = sets[q % 2]
        k = rr.size
        if half:
            from facegeo.surface._half import gather_halves_to_float32

            R = wide[:k]
            ok = gather_halves_to_float32(field.view(np.ndarray), rr, R)
        else:
            g = np.take(field, rr, axis=0, out=gathered[:k], mode="clip")  # rows are in range
            R = g if wide is None else _float32_rows(g, wide[:k])
            ok = np.isfinite(R).all(axis=(1, 2))
        masked = None
        if not ok.all():  # masked samples, sample by sample (only the rows that have any)
            bad = np.flatnonzero(~ok)
            m = ~np.isfinite(R[bad]).all(axis=2)
            R[bad] = np.where(m[..., None], np.float32(0.0), R[bad])
            masked = np.zeros((k, L), bool)
            masked[bad] = m
        return rr, R, ok, masked

    def at(q, rr):  # the entries of v_world / texel_index / near for chunk q's rows
        return rr if per_row else np.arange(starts[q], starts[q] + rr.size)

    def submit(pool, q, got):
        rr, R, _, masked = got
        rr = at(q, rr)
        if near is not None:
            return pool.submit(fit_reflectance_near, R, v_world[rr], lights, near.take(rr),
                               masked=masked, eta=eta, depth=depth, threads=threads,
                               diffuse_out=sets[q % 2][2][:rr.size], specular=False)
        return pool.submit(fit_reflectance, R, v_world[rr], lights, masked=masked, eta=eta,
                           depth=depth, threads=threads,
                           diffuse_out=sets[q % 2][2][:rr.size], specular=False)

    if not starts:
        return
    with ThreadPoolExecutor(1, thread_name_prefix="facegeo-fit") as pool:
        cur = read(0)
        job = submit(pool, 0, cur)
        for q in range(len(starts)):
            nxt = read(q + 1) if q + 1 < len(starts) else None  # while chunk q is fitted
            fit = job.result()
            if nxt is not None:
                job = submit(pool, q + 1, nxt)  # the cores fit q + 1 while q is stored
            rr, _, ok, _ = cur
            writer.write(rr, texel_index[at(q, rr)], fit)
            yield rr, fit, ok  # the caller's work on chunk q runs while q + 1 is fitted
            cur = nxt


def _float32_rows(a, out):
    """``a`` widened into ``out`` (float32, same shape); returns ``out``. float16: the compiled
    exact conversion (numpy's cast costs ≈ 6× more here)."""
    if a.dtype == np.float16:
        from facegeo.surface._half import halves_to_float32

        return halves_to_float32(a, out)
    np.copyto(out, a, casting="same_kind")
    return out


def fit_products(scan, project_dir, dest, *, atlas_dir=None, texels: str = "all",
                 views: list | None = None, max_texels: int | None = None, eta: float = 1.4,
                 chunk: int = 2048, diffuse_dtype: str = "float16", mosaic: int = 8,
                 rig: str | None = None,
                 polish: int | None = None, supersample: int = 1, near_field: str = "auto",
                 engine=None, progress=None, store=None) -> tuple[dict, dict]:
    """Fit the skin model to every camera's projected field; write the ``fit`` products.

    Parameters
    ----------
    scan : Scan
    project_dir : path — the ``project`` stage folder (``<camera>/R.npy`` …)
    dest : path — folder to write into (the stage cache's temporary folder)
    atlas_dir : path, optional — default ``project_dir/../atlas``
    texels : {"all", "views"} — fit every measured texel, or only those ``views`` need
    views : list of camera specs, optional — default :func:`default_views`
    supersample : int — with ``texels="views"``, the views' rays per pixel (s × s): the texels
        their supersampled renders tap (the ``render`` stage's own setting)
    max_texels : int, optional — at most this many functions per camera (even subsample)
    eta : float — index of refraction (ρ_s, Eq. 9)
    chunk : int — functions read and fitted at a time
    diffuse_dtype : {"float16", "float32"} — storage of D
    mosaic : int — the mosaic shows mosaic × mosaic functions (0: none)
    rig : str, optional — rig for view specs (:func:`facegeo.pipeline.project.stage_rig`)
    polish : int or None — Levenberg–Marquardt iterations after the ramp search
        (``SearchDepth.polish``); None (default) keeps the skin module's default depth (10
        steps, then the chromaticity polish that pins the ramp's scale, docs/skin.md). Small
        preset: normals 1.44°, albedo 10.9 %, ρs 17 %, resynthesis 2.9× / 1.9× better than naive
        at 30° / 60° over the one-sided turns measured then; ``polish=0`` gives 4.11°, 14.5 %,
        96 %, 1.6× / 1.2× (docs/render.md). Over both turns (another run: all texels): 2.5× /
        1.6× where the one-sided rule read 3.1× / 2.0×. (These errors are
        :mod:`facegeo.evaluate.skin_fit`'s figures now.)
    near_field : {"auto", "off"} — "auto" (default): on a light stage of finite radius, each
        light where it is (:func:`facegeo.appearance.skin.fit_reflectance_near`: the texel's
        offset from the stage centre gives every light's true direction and falloff, in the fit
        and in Eq. 9); "off": every light distant, as the paper. A light list with positions
        is near-field too, at its lights' mean distance (:func:`_near_field`). Small preset
        (r = 1.5 m): docs/skin.md, "Near-field light stages".
    engine : facegeo.pipeline.engine.Engine, optional — where the fit tasks run (default in
        process): each camera's selection in tasks of :data:`FIT_TASK_CHUNKS` fit chunks
        (:func:`fit_chunk_task`), each checked against a worker's memory
        (:func:`fit_working_set`) before any runs; the products are the same whatever the
        engine (the maps are blended here afterwards, in camera and chunk order)
    progress : callable(stage, done, total), optional — called as fit tasks finish, with
        the functions fitted
    store : path or str, optional — ``--store URL`` (a folder or an fsspec URL): tasks that
        write nothing to a shared disk. Each task gets its functions' rows, view directions,
        texels and offsets with it (≈ 64 B a function), reads the field from where the
        projection put it (its own folder, or the store it links to), writes its D rows into
        a Zarr array and its parameters into a file under ``store/fit/run-<id>/<camera>/``;
        the client merges the parameters as always and streams D into the stage's ``D.npy``
        (the renderer's compiled kernels read D memory-mapped), then removes the run's
        folder from the store. The products equal the run without a store.

    Returns
    -------
    (metrics, settings)
    """
    from facegeo.appearance.skin import FLAG_NAMES, SearchDepth
    from facegeo.capture import imageio
    from facegeo.fsutil import NpyRowFile
    from facegeo.pipeline.engine import InProcessEngine, Task
    from facegeo.render._fitstore import DIFFUSE_FILE
    from facegeo.rss import peak_rss_mb
    from facegeo.pipeline.project import check_projection_atlas, stage_rig
    from facegeo.render import atlas_scene, light_set, load_sources
    from facegeo.surface.atlas import Atlas, Texels

    t_start = time.perf_counter()
    project_dir = Path(project_dir)
    dest = Path(dest)
    atlas_dir = Path(atlas_dir) if atlas_dir is not None else project_dir.parent / "atlas"
    _check_settings(texels=texels, max_texels=max_texels, chunk=chunk,
                    supersample=supersample, near_field=near_field)
    for f in ("atlas.npz", "texels.npz"):
        if not (atlas_dir / f).is_file():
            raise InputError(f"fit: {atlas_dir / f} is missing; run 'facegeo reconstruct SCAN' "
                             "(the atlas stage) first")
    atlas = Atlas.load(atlas_dir / "atlas.npz")
    tex = Texels.load(atlas_dir / "texels.npz")
    check_projection_atlas(project_dir, atlas_dir / "texels.npz")
    sources = load_sources(project_dir)
    the_rig, rig_used = stage_rig(scan, rig)
    lights = light_set(the_rig.lights)
    if sources[0].field.shape[1] != lights.n_lights:
        raise InputError(f"{project_dir}: fields hold {sources[0].field.shape[1]} lights, the rig "
                         f"{lights.n_lights}")
    settings = {"texels": texels, "views": views, "max_texels": max_texels, "eta": eta,
                "chunk": int(chunk), "diffuse_dtype": diffuse_dtype, "mosaic": mosaic,
                "rig": rig_used, "polish": polish, "supersample": int(supersample),
                "near_field": near_field}
    run_loc = None
    if store is not None:
        import uuid

        from facegeo.surface._zarr_field import store_location

        run_loc = store_location(store, "fit", f"run-{uuid.uuid4().hex[:12]}")
        settings["store"] = str(store)
    near_all = _near_field(the_rig.lights, tex, near_field)
    if polish is not None:  # a bad polish fails here, before any task is submitted
        SearchDepth(polish=int(polish))
    cam_table = _camera_table(scan, the_rig)
    need = None
    t_views = 0.0
    if texels == "views":
        t0 = time.perf_counter()
        specs = views if views is not None else default_views(
            [c.name for c in the_rig.cameras],
            [n for n in cam_table if n not in the_rig.camera_names])
        settings["views"] = list(specs)
        need = needed_texels(specs, cam_table, atlas, tex, atlas_scene(atlas),
                             supersample=supersample)
        t_views = time.perf_counter() - t0
    T = len(tex)
    acc = {"normal": np.zeros((T, 3)), "rho_d": np.zeros((T, 3)), "rho_s": np.zeros(T)}
    wsum = np.zeros(T)
    per_cam: dict[str, Any] = {}
    mosaic_R = None
    total = 0
    selections = []
    for src in sources:
        rows = np.arange(src.texel_index.size)
        if need is not None:
            r, seen = src.rows_of(need)
            rows = np.unique(r[seen])
        selections.append(rows[even_subset(rows.size, max_texels)])
    # each camera's selection in tasks of whole fit chunks (the same chunks as one loop over
    # the camera: the fits are those of fitting each chunk in turn, wherever a task runs)
    engine = InProcessEngine() if engine is None else engine
    parts_dir = dest / _PARTS
    tasks = []
    for src, rows in zip(sources, selections):
        (dest / src.name).mkdir(parents=True, exist_ok=True)
        d_shape = (rows.size, lights.n_lights, src.field.shape[2])
        offsets = None if near_all is None else near_all.offsets[src.texel_index[rows]]
        if run_loc is None:
            cam_parts = parts_dir / src.name
            cam_parts.mkdir(parents=True, exist_ok=True)
            np.save(cam_parts / "rows.npy", rows)
            if offsets is not None:  # each selected function's offset from the stage centre
                np.save(cam_parts / "offsets.npy", offsets)
            diffuse = str(dest / src.name / DIFFUSE_FILE)
            NpyRowFile(diffuse, d_shape, diffuse_dtype).close()
            field_at = str(project_dir / src.name)
        else:  # the task's inputs travel with it; D and the parameters go to the store
            from facegeo.surface._zarr_field import create_field, find_field

            cam_parts = store_location(run_loc, src.name)
            diffuse = str(create_field(cam_parts, d_shape, dtype=diffuse_dtype,
                                       name=DIFFUSE_FILE,
                                       chunks=(int(chunk), lights.n_lights)))
            field_at = str(find_field(project_dir / src.name)[1])
            v_all = np.load(project_dir / src.name / "v_world.npy", mmap_mode="r")
        for a, b in task_bounds(rows.size, int(chunk)):
            inputs = None
            if run_loc is not None:
                r = rows[a:b]
                inputs = {"rows": r, "v_world": np.asarray(v_all[r], np.float64),
                          "texel_index": src.texel_index[r],
                          "offsets": None if offsets is None else offsets[a:b]}
            tasks.append(Task(
                f"{src.name} {a}:{b}", fit_chunk_task,
                (field_at, str(cam_parts), diffuse, a, b,
                 the_rig.lights, None if near_all is None else float(near_all.radius), eta,
                 polish, int(chunk), diffuse_dtype, inputs),
                working_set=fit_working_set(b - a, lights.n_lights, src.field.shape[2],
                                            int(chunk), diffuse_dtype,
                                            gathered=not isinstance(src.field, np.ndarray)),
                size=b - a))
    results = engine.map("fit", tasks, progress=progress)
    by_task = dict(zip((t.name for t in tasks), results))
    for src, rows in zip(sources, selections):
        t0 = time.perf_counter()
        names = [f"{src.name} {a}:{b}" for a, b in task_bounds(rows.size, int(chunk))]
        cam_parts = (parts_dir / src.name if run_loc is None
                     else store_location(run_loc, src.name))
        fits = merge_fit_parts(dest / src.name, cam_parts, names, lights.n_lights)
        if run_loc is not None:  # D from the store into the stage folder, chunk by chunk
            _copy_diffuse(store_location(cam_parts, "D.zarr"), dest / src.name / DIFFUSE_FILE,
                          int(chunk))
        n_valid = int(np.count_nonzero(fits["valid"]))
        rr, t_id = fits["rows"], fits["texel_index"]
        # masked samples are left out of each fit (fit_chunks): a valid fit counts
        wc = np.where(fits["valid"], src.weight[rr].astype(np.float64), 0.0)
        acc["normal"][t_id] += wc[:, None] * fits["normal"]
        acc["rho_d"][t_id] += wc[:, None] * fits["rho_d"]
        acc["rho_s"][t_id] += wc * fits["rho_s"]
        wsum[t_id] += wc
        flags = fits["flags"]
        total += rows.size
        seconds = sum(by_task[n]["seconds"] for n in names) + time.perf_counter() - t0
        per_cam[src.name] = {
            "functions": int(rows.size), "measured_texels": int(src.texel_index.size),
            "seconds": round(seconds, 4),
            "functions_per_second": round(rows.size / max(seconds, 1e-9), 1),
            "valid_functions": n_valid,
            "flags": {name: int(np.count_nonzero(flags & bit)) for bit, name in FLAG_NAMES.items()},
        }
        if rows.size and n_valid == 0:
            log.warning("fit: camera %s: none of its %d functions has a valid fit (flags: %s)",
                        src.name, rows.size, _flag_summary(per_cam[src.name]["flags"]))
        if mosaic and mosaic_R is None and rows.size:
            pick = rows[even_subset(rows.size, int(mosaic) ** 2)]
            mosaic_R = np.asarray(_take_rows(src.field, pick), np.float32)
    shutil.rmtree(parts_dir, ignore_errors=True)
    if run_loc is not None:  # the run's D arrays and parameter files, now in the stage
        from facegeo.surface._zarr_field import remove_location

        remove_location(run_loc)
    files = _write_maps(dest, tex, acc, wsum)
    if mosaic_R is not None and hasattr(the_rig.lights, "n_theta"):  # a θ × φ grid to lay out
        imageio.write_image(dest / "mosaic.png", reflectance_mosaic(
            mosaic_R, the_rig.lights.n_theta, the_rig.lights.n_phi, cols=int(mosaic)))
        files["mosaic"] = "mosaic.png"
    metrics: dict[str, Any] = {
        "cameras": per_cam, "functions": int(total), "lights": int(lights.n_lights),
        "texels_fitted": int(np.count_nonzero(wsum > 0)), "texels": int(T),
        "seconds_views": round(t_views, 4),
        "functions_per_second": round(total / max(sum(c["seconds"] for c in per_cam.values()),
                                                  1e-9), 1),
        "files": files,
    }
    metrics["valid_functions"] = int(sum(c["valid_functions"] for c in per_cam.values()))
    if total and not metrics["valid_functions"]:
        counts: dict[str, int] = {}
        for c in per_cam.values():
            for k, x in c["flags"].items():
                counts[k] = counts.get(k, 0) + x
        log.warning("fit: no valid function among %d (flags: %s); the maps are empty", total,
                    _flag_summary(counts))
    metrics["seconds"] = round(time.perf_counter() - t_start, 4)
    metrics["peak_rss_mb"] = round(peak_rss_mb(), 1)
    if engine.kind != "in-process":
        metrics["engine"] = engine.stage_metrics("fit", [t.name for t in tasks])
    return metrics, settings


#: Fit chunks per fit task: a task fits ``FIT_TASK_CHUNKS × chunk`` functions of one camera
#: (16,384 at the default chunk), enough to amortise a task's start (opening the field, a
#: few ms) and few enough that a camera of 174 k functions is ≈ 11 tasks for the workers.
FIT_TASK_CHUNKS = 8
#: Bytes a fit task needs per sample (function × light × channel) of a fit chunk: the two
#: buffer sets of :func:`fit_chunks` (float32 rows and D, ≤ 8 B each) and the fit's own
#: temporaries — 10 B/sample with distant lights (2,048 functions × 512 lights, one thread:
#: RSS 181 → 212 MB), more near-field (each function's light directions and falloff): a fresh
#: worker's fit task of the ``modern`` preset (one chunk of 1,500 functions × 512 lights × 3,
#: near field) peaked at 425–428 MiB, ≈ 165 MiB over a worker's 257–262 MiB after its decode
#: tasks (part of it the fit's compiled kernels, loaded once): 64 B/sample (141 MiB) keeps this
#: set plus ``WORKER_BASE_BYTES`` (300 MiB) above the measured peaks (``bench
#: scale.reconstruct``).
FIT_BYTES_PER_CHUNK_SAMPLE = 64
#: ... per function of the task: its fit parameters until they are saved (23 float64, flags,
#: valid: 189 B), its row, texel, view and offset (64 B); plus 3 bit-packed maps of L bits.
FIT_BYTES_PER_FUNCTION = 256
_PARTS = ".parts"


def task_bounds(n: int, chunk: int, chunks_per_task: int | None = None) -> list[tuple[int, int]]:
    """``(a, b)`` ranges of a camera's ``n`` selected functions, one per fit task: whole
    multiples of ``chunk`` (so each task's chunks are the one-loop run's chunks)."""
    step = int(chunk) * int(chunks_per_task or FIT_TASK_CHUNKS)
    return [(a, min(a + step, n)) for a in range(0, int(n), step)]


def fit_working_set(n_functions: int, n_lights: int, channels: int, chunk: int,
                    diffuse_dtype: str = "float16", *, gathered: bool = False) -> int:
    """Memory (bytes) one fit task needs: :data:`FIT_BYTES_PER_CHUNK_SAMPLE` × the samples of a
    fit chunk + (:data:`FIT_BYTES_PER_FUNCTION` + 3 × L / 8) × the task's functions, + the
    task's field rows as float16 when they are ``gathered`` from a Zarr store first (2 B a
    sample; a ``.npy`` field is memory-mapped and read chunk by chunk)."""
    n, L, C = int(n_functions), int(n_lights), int(channels)
    k = min(int(chunk), max(n, 1))
    return (k * L * C * FIT_BYTES_PER_CHUNK_SAMPLE + n * (FIT_BYTES_PER_FUNCTION + 3 * -(-L // 8))
            + (n * L * C * 2 if gathered else 0))


class _PartWriter:
    """The :class:`~facegeo.render.FitWriter` of one fit task: D rows ``a:b`` written in place
    into the camera's D — its ``D.npy`` (created whole by the stage; tasks write disjoint rows)
    or, with a store, its Zarr array ``D.zarr`` (chunked by fit chunks: a task writes whole
    chunks) — the fit parameters kept for :meth:`save`."""

    def __init__(self, diffuse_path: str, rows: np.ndarray, a: int, dtype: str):
        from facegeo.render._fitstore import _MAPS, _PER_FUNCTION

        self.path = diffuse_path
        self.dtype = np.dtype(dtype)
        self.rows = rows  # the camera's rows of this task's functions
        self.done = 0
        self._a = int(a)
        self._fd = self._zarr = None
        if str(diffuse_path).endswith(".zarr"):
            from facegeo.surface._zarr_field import open_zarr_field

            self._zarr = open_zarr_field(diffuse_path, mode="r+")
            dt = self._zarr.dtype
        else:
            with open(diffuse_path, "rb") as fh:
                np.lib.format.read_magic(fh)
                shape, _, dt = np.lib.format.read_array_header_1_0(fh)
                self._offset = fh.tell()
            self._row_bytes = int(np.prod(shape[1:], dtype=np.int64)) * self.dtype.itemsize
            self._start = self._offset + self._a * self._row_bytes
        if np.dtype(dt) != self.dtype:
            raise InputError(f"{diffuse_path}: D is {dt}, the task writes {self.dtype}")
        if self._zarr is None:
            self._fd = os.open(diffuse_path, os.O_WRONLY)
        self._names = (_PER_FUNCTION, _MAPS)
        self.parts: dict[str, list] = {k: [] for k in _PER_FUNCTION + _MAPS}
        self.texels: list[np.ndarray] = []
        self.eta, self.single = 1.4, False

    def write(self, rows, texel_index, fit) -> None:
        k = len(rows)
        d = np.ascontiguousarray(fit.diffuse, dtype=self.dtype)
        if self._zarr is not None:
            r0 = self._a + self.done
            self._zarr[r0:r0 + k] = d
        else:
            view, pos = memoryview(d).cast("B"), self._start + self.done * self._row_bytes
            while view:
                n = os.pwrite(self._fd, view, pos)
                view, pos = view[n:], pos + n
        self.done += k
        self.texels.append(np.asarray(texel_index, np.int64))
        per_function, maps = self._names
        for name in per_function:
            self.parts[name].append(np.asarray(getattr(fit, name)))
        for name in maps:
            self.parts[name].append(np.packbits(np.asarray(getattr(fit, name), bool), axis=1))
        self.eta, self.single = float(fit.eta), bool(fit.single_channel)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def save(self, path) -> None:
        """The parameters to ``path`` (in the stage's own staging folder, or a store)."""
        self.close()
        if self.done != self.rows.size:
            raise InputError(f"{self.path}: {self.done} fits written, {self.rows.size} announced")
        arrays = {k: np.concatenate(v) for k, v in self.parts.items() if v}
        import io

        buf = io.BytesIO()
        np.savez(buf, rows=self.rows, texel_index=np.concatenate(self.texels),
                 eta=np.array(self.eta), single_channel=np.array(self.single), **arrays)
        from facegeo.surface._zarr_field import put_bytes

        put_bytes(path, buf.getvalue())


def _copy_diffuse(location, path: Path, chunk: int) -> None:
    """The Zarr D at ``location`` into the ``.npy`` ``path``, ``chunk`` rows at a time."""
    from facegeo.fsutil import NpyRowFile
    from facegeo.surface._zarr_field import open_zarr_field

    Z = open_zarr_field(location)
    out = NpyRowFile(path, Z.shape, Z.dtype)
    try:
        for r0 in range(0, Z.shape[0], chunk):
            out.write(r0, np.ascontiguousarray(Z[r0:r0 + chunk]))
    finally:
        out.close()


def _take_rows(field, rows) -> np.ndarray:
    """``field[rows]`` of a memory-mapped ``.npy`` or a Zarr field (reading only the chunks the
    rows fall in)."""
    if isinstance(field, np.ndarray):
        return np.asarray(field[rows])
    return np.ascontiguousarray(field.oindex[np.asarray(rows, np.int64)])


def _drop_projection_inputs() -> None:
    """Drop the projection's per-process inputs (texels, ray scenes) that a worker keeps from
    the ``project`` stage for its next camera: a fit or relight task does not need them. (It
    does not bring a worker's resident memory back down by itself, measured: the engine's
    check before each stage restarts a worker that holds too much,
    :meth:`facegeo.pipeline.engine.DaskEngine._resident_check`.)"""
    import sys

    # the cache lives in _project_tasks (project re-exports it): loaded only where a
    # projection task ran in this process
    tasks = sys.modules.get("facegeo.pipeline._project_tasks")
    if tasks is not None and tasks._INPUTS_CACHE:
        tasks._INPUTS_CACHE.clear()


def fit_chunk_task(field_dir: str, parts_dir: str, diffuse_path: str, a: int, b: int, stage,
                   radius: float | None, eta: float, polish: int | None, chunk: int,
                   diffuse_dtype: str, inputs: dict | None = None) -> dict:
    """One fit task: functions ``a:b`` of a camera's selection (``parts_dir/rows.npy``) fitted
    chunk by chunk (:func:`fit_chunks`), D written into rows ``a:b`` of ``diffuse_path``, the
    parameters into ``parts_dir/<a>.npz``. Reads only its rows of the field (a ``.npy`` memory
    map, or the Zarr chunks they fall in), of ``v_world.npy`` and ``texel_index.npy``.
    With ``inputs`` (``--store``: ``rows``, ``v_world``, ``texel_index``, ``offsets`` of its
    functions) it reads no file of the stages' folders: ``field_dir`` is then the field itself
    (an ``R.npy`` path or a Zarr store's location), ``diffuse_path`` a Zarr D and
    ``parts_dir`` a place in the store. Returns ``{"functions", "seconds"}``."""
    from facegeo.appearance.skin import NearField, SearchDepth
    from facegeo.render import light_set
    from facegeo.surface.reflectance import open_field

    t0 = time.perf_counter()
    _drop_projection_inputs()
    if inputs is None:
        d, parts = Path(field_dir), Path(parts_dir)
        rows = np.array(np.load(parts / "rows.npy", mmap_mode="r")[a:b], np.int64)
        R = open_field(d)
        v_world = np.asarray(np.load(d / "v_world.npy", mmap_mode="r")[rows], np.float64)
        texel_index = np.asarray(np.load(d / "texel_index.npy", mmap_mode="r")[rows], np.int64)
        offsets = (None if radius is None
                   else np.load(parts / "offsets.npy", mmap_mode="r")[a:b])
        part_file = parts / f"{a:012d}.npz"
    else:
        from facegeo.surface._zarr_field import open_zarr_field, store_location

        rows = np.asarray(inputs["rows"], np.int64)
        R = (np.load(field_dir, mmap_mode="r") if field_dir.endswith(".npy")
             else open_zarr_field(field_dir))
        v_world = np.asarray(inputs["v_world"], np.float64)
        texel_index = np.asarray(inputs["texel_index"], np.int64)
        offsets = inputs["offsets"]
        part_file = store_location(parts_dir, f"{a:012d}.npz")
    near = None if radius is None else NearField(offsets, radius)
    if isinstance(R, np.ndarray):  # memory-mapped: fit_chunks gathers each chunk's rows
        field, frows = R, rows
    else:  # Zarr: the task's rows, read once from the chunks they fall in
        field, frows = _take_rows(R, rows), np.arange(rows.size)
    import numba

    threads = max(1, min(2, int(numba.config.NUMBA_NUM_THREADS)))
    depth = SearchDepth() if polish is None else SearchDepth(polish=int(polish))
    writer = _PartWriter(diffuse_path, rows, a, diffuse_dtype)
    try:
        for _ in fit_chunks(field, frows, v_world, light_set(stage), writer, texel_index,
                            eta=eta, depth=depth, chunk=chunk, threads=threads, near=near,
                            per_row=False):
            pass
    finally:
        if writer.done != rows.size:
            writer.close()
    writer.save(part_file)
    return {"functions": int(rows.size), "seconds": time.perf_counter() - t0}


def merge_fit_parts(cam_dir: Path, parts_dir, task_names: list[str],
                    n_lights: int) -> dict:
    """Write ``cam_dir/fit.npz`` from the camera's fit tasks' parameters (in row order; what
    :class:`~facegeo.render.FitWriter` writes; ``parts_dir`` a folder or a place in a store);
    returns the merged arrays."""
    from facegeo.render._fitstore import _MAPS, _PER_FUNCTION, FIT_FILE

    got: dict[str, list] = {k: [] for k in ("rows", "texel_index") + _PER_FUNCTION + _MAPS}
    eta, single = np.array(1.4), np.array(False)
    import io

    from facegeo.surface._zarr_field import get_bytes, store_location

    for name in task_names:
        a = int(name.rsplit(" ", 1)[1].split(":")[0])
        with np.load(io.BytesIO(get_bytes(store_location(parts_dir, f"{a:012d}.npz")))) as z:
            for k in got:
                if k in z.files:
                    got[k].append(z[k])
            eta, single = z["eta"], z["single_channel"]
    arrays = {k: (np.concatenate(v) if v else np.zeros((0,))) for k, v in got.items()}
    if not got["rows"]:
        arrays["rows"] = arrays["texel_index"] = np.zeros(0, np.int64)
    front = {k: arrays.pop(k) for k in ("rows", "texel_index")}
    np.savez(cam_dir / FIT_FILE, **front, eta=eta, single_channel=single,
             n_lights=np.array(int(n_lights)), **arrays)
    return {**front, **arrays}


def _flag_summary(counts: dict) -> str:
    """``"black 120, singular 120"``: the non-zero flag counts, or ``"none"``."""
    return ", ".join(f"{k} {x}" for k, x in counts.items() if x) or "none"


#: A light list's lights may sit at different distances from its centre; the near field takes
#: their mean (:func:`_near_field`) while the farthest is within this fraction of it.
LIST_RADIUS_SPREAD = 0.05


def _near_field(stage, tex, mode):
    """The :class:`~facegeo.appearance.skin.NearField` of every texel (the texel's offset from
    the stage centre), or None: ``mode`` "off" or distant lights.

    A light-stage grid gives its radius r. A light list with positions (a real rig's measured
    lights, or the generator's ``light_error_deg`` list) gives the mean distance r̄ of its
    lights from its centre: :class:`NearField` has one radius, and a light at r_l = r̄ + Δ is
    then placed Δ off along its own direction, which moves its direction seen from a point δ
    off the centre by at most |δ||Δ|/r̄² and its falloff by at most 2|δ||Δ|/r̄² (relative) —
    0.013° and 4.4e-4 for a head point 0.1 m off centre, lights at 1.5 m ± 5 mm, against the
    ≈ 4° and ±14 % the distant treatment costs there. A list whose distances spread by more
    than :data:`LIST_RADIUS_SPREAD` of r̄ is fitted as distant lights, with a warning (the
    treatment before lists had a near field)."""
    from facegeo.appearance.skin import NearField

    if mode == "off":
        return None
    center = np.asarray(stage.center, np.float64)
    if hasattr(stage, "n_theta"):
        radius = float(getattr(stage, "radius", np.inf))
        if not np.isfinite(radius):
            return None
    else:
        positions = getattr(stage, "positions", None)
        if positions is None:  # a list of directions: distant lights
            return None
        dist = np.linalg.norm(np.asarray(positions, np.float64) - center, axis=1)
        radius = float(dist.mean())
        spread = float(np.abs(dist - radius).max()) / radius
        if spread > LIST_RADIUS_SPREAD:
            log.warning("fit: the light list's lights lie %.4g–%.4g m from its centre, %.1f %% "
                        "off their mean (the near field takes one radius, at most %g %% off): "
                        "fitting them as distant lights", dist.min(), dist.max(),
                        100 * spread, 100 * LIST_RADIUS_SPREAD)
            return None
    return NearField(tex.p_world - center, radius)


def run_fit(scan_dir, out_dir=None, *, engine=None, **settings) -> dict:
    """Fit the skin model to a scan's projected fields into ``out_dir/fit/`` (staged); on a
    single-view scan without geometry (:func:`image_space_scan`), the per-pixel photometric
    models in image space (:func:`fit_image_products`).

    Parameters
    ----------
    scan_dir : path-like or Scan
    out_dir : path-like, optional — default the scan's ``out/`` (must hold ``atlas/`` and
        ``project/``, except in image space)
    engine : facegeo.pipeline.engine.Engine, optional — where the fit tasks run
        (:func:`fit_products`; image space: in process)
    **settings — see :func:`fit_products` (image space: :func:`fit_image_products`)

    Returns
    -------
    dict — the metrics (also recorded in ``out_dir/metrics.json`` under ``"fit"``)
    """
    from facegeo.pipeline.project import _record, _scan

    scan = _scan(scan_dir)
    out = Path(out_dir) if out_dir is not None else scan.out_dir
    if image_space_scan(scan):
        with staged_directory(out / "fit") as tmp:
            metrics, used = fit_image_products(scan, tmp, **settings)
            _record(out, tmp, "fit", used, metrics)
        return metrics
    _check_settings(**settings)
    if not (out / "project").is_dir():
        raise InputError(f"fit: {out / 'project'} is missing; run 'facegeo reconstruct SCAN' first")
    with staged_directory(out / "fit") as tmp:
        metrics, used = fit_products(scan, out / "project", tmp, atlas_dir=out / "atlas",
                                     engine=engine, **settings)
        _record(out, tmp, "fit", used, metrics)
    return metrics
