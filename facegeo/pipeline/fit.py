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

__all__ = ["FIT_SETTINGS", "IMAGE_FIT_SETTINGS", "default_views", "fit_products",
           "fit_image_products", "image_space_scan", "needed_texels", "run_fit"]

#: Default settings of the ``fit`` stage (JSON-serialisable, part of its cache key).
FIT_SETTINGS: dict[str, Any] = {
    "texels": "all", "views": None, "max_texels": None, "eta": 1.4, "chunk": 2048,
    "diffuse_dtype": "float16", "mosaic": 8, "rig": None, "polish": None, "supersample": 1,
    "near_field": "auto",
}


def default_views(cameras: list[str], novel: list[str] = ()) -> list[str]:
    """The novel views the demo renders: every source camera, ±30° and ±60° orbits of the
    rig's frontal camera (:func:`facegeo.render.front_camera`), and the generator's novel
    cameras."""
    from facegeo.render._cameras import FRONT, NOVEL_ORBITS

    return list(cameras) + [f"orbit:{FRONT}:{d:g}" for d in NOVEL_ORBITS] + list(novel)


def _camera_table(scan, rig) -> dict:
    """Cameras a view spec may name: the rig's and the generator's novel ones."""
    import json

    from facegeo.geometry.camera import Camera

    cams = {c.name: c for c in rig.cameras}
    if "novel_cameras" in scan.ground_truth_keys:
        for d in json.loads(scan.ground_truth_path("novel_cameras").read_text(encoding="utf-8")):
            c = Camera.from_dict(d, where="ground_truth/novel_cameras.json")
            cams[c.name] = c
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
               depth=None, chunk: int = 2048, threads: int = 1, near=None):
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

    def submit(pool, q, got):
        rr, R, _, masked = got
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
            writer.write(rr, texel_index[rr], fit)
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
                 progress=None) -> tuple[dict, dict]:
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
        and in Eq. 9); "off": every light distant, as the paper. Small preset (r = 1.5 m):
        docs/skin.md, "Near-field light stages".
    progress : callable(stage, done, total), optional — called per chunk with functions fitted

    Returns
    -------
    (metrics, settings)
    """
    from facegeo.appearance.skin import FLAG_NAMES, SearchDepth
    from facegeo.capture import imageio
    from facegeo.rss import peak_rss_mb
    from facegeo.pipeline.project import check_projection_atlas, stage_rig
    from facegeo.render import FitWriter, atlas_scene, light_set, load_sources
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
    near_all = _near_field(the_rig.lights, tex, near_field)
    depth = SearchDepth() if polish is None else SearchDepth(polish=int(polish))
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
    n_all = int(sum(r.size for r in selections))
    # both cores when numba has them (the fit is bit-identical at any thread count, so the
    # thread count is not a setting of the stage's cache key)
    import numba

    threads = max(1, min(2, int(numba.config.NUMBA_NUM_THREADS)))
    for src, rows in zip(sources, selections):
        t0 = time.perf_counter()
        writer = FitWriter(dest / src.name, rows.size, lights.n_lights,
                           src.field.shape[2], diffuse_dtype)
        flag_parts = []
        done = 0
        n_valid = 0
        near = None if near_all is None else near_all.take(src.texel_index)
        for rr, fit, _ in fit_chunks(src.field, rows, src.v_world, lights, writer,
                                     src.texel_index, eta=eta, depth=depth, chunk=int(chunk),
                                     threads=threads, near=near):
            flag_parts.append(fit.flags)
            done += len(rr)
            n_valid += int(np.count_nonzero(fit.valid))
            t_id = src.texel_index[rr]
            # masked samples are left out of each fit (fit_chunks): a valid fit counts
            wc = np.where(fit.valid, src.weight[rr].astype(np.float64), 0.0)
            acc["normal"][t_id] += wc[:, None] * fit.normal
            acc["rho_d"][t_id] += wc[:, None] * fit.rho_d
            acc["rho_s"][t_id] += wc * fit.rho_s
            wsum[t_id] += wc
            if progress:
                progress("fit", total + done, n_all)
        writer.close()
        flags = np.concatenate(flag_parts) if flag_parts else np.zeros(0, np.int32)
        total += rows.size
        seconds = time.perf_counter() - t0
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
            mosaic_R = np.asarray(src.field[pick], np.float32)
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
    return metrics, settings


def _flag_summary(counts: dict) -> str:
    """``"black 120, singular 120"``: the non-zero flag counts, or ``"none"``."""
    return ", ".join(f"{k} {x}" for k, x in counts.items() if x) or "none"


def _near_field(stage, tex, mode):
    """The :class:`~facegeo.appearance.skin.NearField` of every texel (the texel's offset from
    the stage centre), or None: ``mode`` "off", distant lights, or a light list."""
    from facegeo.appearance.skin import NearField

    radius = getattr(stage, "radius", np.inf)
    if mode == "off" or not np.isfinite(radius) or not hasattr(stage, "n_theta"):
        return None
    return NearField(tex.p_world - np.asarray(stage.center, np.float64), float(radius))


def run_fit(scan_dir, out_dir=None, **settings) -> dict:
    """Fit the skin model to a scan's projected fields into ``out_dir/fit/`` (staged); on a
    single-view scan without geometry (:func:`image_space_scan`), the per-pixel photometric
    models in image space (:func:`fit_image_products`).

    Parameters
    ----------
    scan_dir : path-like or Scan
    out_dir : path-like, optional — default the scan's ``out/`` (must hold ``atlas/`` and
        ``project/``, except in image space)
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
                                     **settings)
        _record(out, tmp, "fit", used, metrics)
    return metrics
