"""Pipeline stage ``relight``: a scan relit by an environment map (Debevec et al. 2000 §3.3,
Eq. 4), written as EXR and tone-mapped PNG under ``SCAN/out/relit/``.

Two views:

* a camera: its OLAT frames, reading only the lights with non-zero weight;
* ``"texture"``: the surface reflectance field written by ``facegeo project``
  (``out/project/<camera>/R.npy`` ``(T_c, L, 3)`` with ``texel_index.npy``, ``weight.npy``),
  every camera's field relit and blended per texel by the camera weights, written as the
  atlas image (:func:`relight_texture`).

:func:`relight_products` does the work and returns ``(metrics, settings)`` without writing a
JSON file (the cached stage of ``facegeo reconstruct``); :func:`run_relight` wraps it for the CLI
(``facegeo relight SCAN --env FILE|NAME [--rotate DEG] [--view CAMERA|texture]``) and writes the
metrics beside the images. ``env`` may name a shipped procedural map (``"sky"``, ``"studio"``,
:func:`facegeo.lighting.envmap.shipped_map`). Progress goes through the ``progress`` callback, the
library only logs.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.errors import InputError
from facegeo.checks import check_choice, fmt_value

log = logging.getLogger(__name__)

__all__ = ["run_relight", "relight_products", "relight_rows_task", "relight_texture",
           "relight_fitted", "relight_working_set", "resolve_env", "tone_map", "energy_note"]

#: Tone mapping: the 99.5th percentile of luminance maps to this display value before sRGB.
TONE_MAP_WHITE = 0.9
#: Below this share of the environment's energy (Σ w / ∫ L, any channel) the lights keep, the
#: metrics and the CLI say so (a dome of the upper hemisphere keeps ≈ 0.79 of a sky).
DOME_ENERGY_NOTE = 0.95
#: ``model="fitted"``: the environment is sampled on this (n_θ, n_φ) grid of directions (exact
#: cell solid angles, every direction of the sphere) and the fitted model evaluated at each.
FITTED_GRID = (64, 32)


def tone_map(img: np.ndarray, *, percentile: float = 99.5) -> tuple[np.ndarray, float]:
    """Linear ``(H, W, 3)`` radiance → 8-bit sRGB for viewing, and the exposure used.

    A global exposure puts the ``percentile`` of Rec. 709 luminance at :data:`TONE_MAP_WHITE`;
    values above 1 clip. Exposure 1 for an all-black image.
    """
    from facegeo.capture.response import encode

    lum = img @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    ref = float(np.percentile(lum, percentile)) if lum.size else 0.0
    exposure = TONE_MAP_WHITE / ref if ref > 0 else 1.0
    return encode(np.clip(img * np.float32(exposure), 0.0, 1.0), "srgb", np.uint8), exposure


def _safe_stem(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "env"


def _project_cameras(project_dir: Path, texels_path: Path) -> list[Path]:
    """The camera folders of ``project_dir`` that hold a projected field, sorted."""
    from facegeo.surface.reflectance import field_folders

    cams = field_folders(project_dir)  # R.npy or R.zarr
    if not cams or not texels_path.is_file():
        raise InputError(f"{project_dir.parent}: relighting in texture space needs the texture "
                         f"atlas ({texels_path}) and the surface reflectance field "
                         f"({project_dir}/<camera>/R.npy); run 'facegeo project SCAN' first")
    from facegeo.pipeline.project import check_projection_atlas

    check_projection_atlas(project_dir, texels_path)
    return cams


#: Texels (rows of a camera's field) per relight task: 32,768 × 512 lights × 3 float16 =
#: 96 MiB of field a task at the modern preset's lights (a camera of 174 k texels: 6 tasks).
RELIGHT_TASK_TEXELS = 32768
#: Bytes a relight task needs per sample (texel × light × channel) of its rows: the rows read
#: (float16 from a Zarr store, or the memory map's pages, resident once read: 2 B; 4 B for a
#: float32 field).
RELIGHT_BYTES_PER_SAMPLE = 2
#: ... and once: :func:`facegeo.lighting.relight.relight_field`'s chunk buffers (its
#: ``FUSED_CHUNK_BYTES`` = 16 MiB of float16, or ``CHUNK_BYTES`` of float32, per thread: one
#: thread on a worker) and the relit rows (12 B a texel, counted per texel below).
RELIGHT_BYTES_FIXED = 32 << 20
RELIGHT_BYTES_PER_TEXEL = 3 * 4 + 3 * 8


def relight_working_set(n_texels: int, n_lights: int, itemsize: int = 2) -> int:
    """Memory (bytes) one relight task needs for ``n_texels`` rows of a field of ``n_lights``
    lights: the rows (:data:`RELIGHT_BYTES_PER_SAMPLE` × ``itemsize`` / 2 a sample), the relit
    rows and their float64 blend (:data:`RELIGHT_BYTES_PER_TEXEL`), the relighting's chunk
    buffers (:data:`RELIGHT_BYTES_FIXED`)."""
    n, L = int(n_texels), int(n_lights)
    return (n * L * 3 * RELIGHT_BYTES_PER_SAMPLE * int(itemsize) // 2
            + n * RELIGHT_BYTES_PER_TEXEL + RELIGHT_BYTES_FIXED)


def _task_rows(R, w) -> int:
    """Rows per relight task: :data:`RELIGHT_TASK_TEXELS` rounded down to whole chunks of
    :func:`~facegeo.lighting.relight.relight_field` (at least one), so that every task's
    chunks are the whole field's chunks and its relit rows the same bytes."""
    from facegeo.lighting import relight as RL

    n_l = R.shape[1]
    active = np.flatnonzero(np.any(w != 0, axis=(0, 2)))
    n_cols = 3 * (active.size if active.size <= RL.SPARSE_FRACTION * n_l else n_l)
    fused = w.shape[0] == 1 and R.dtype == np.float16 and RL._fused_kernel()
    per = (RL.FUSED_CHUNK_BYTES // (2 * max(n_cols, 1)) if fused
           else RL.CHUNK_BYTES // (4 * max(n_cols, 1)))
    per = max(1, per)
    return max(per, RELIGHT_TASK_TEXELS - RELIGHT_TASK_TEXELS % per)


def relight_rows_task(field: tuple[str, str], relit: str, s0: int, s1: int, weights,
                      light_color=None) -> dict:
    """One relight task: rows ``s0:s1`` of a camera's field relit (Eq. 4,
    :func:`facegeo.lighting.relight.relight_field`) into rows ``s0:s1`` of ``relit``.

    ``field`` is ``(kind, location)`` (:func:`facegeo.surface.reflectance.find_field`: an
    ``R.npy`` path, or a Zarr store — a folder or an fsspec URL); ``relit`` the ``(T_c, 3)``
    float32 rows the stage created: a ``.npy`` file, or a Zarr array (a path ending in
    ``.zarr`` or a URL: workers that share no disk). Tasks write disjoint rows (whole chunks
    of a Zarr array). Reads only its rows (a memory map, or the Zarr chunks they fall in)."""
    from facegeo.lighting.relight import relight_field
    from facegeo.surface._zarr_field import open_zarr_field

    from facegeo.pipeline.fit import _drop_projection_inputs

    t0 = time.perf_counter()
    _drop_projection_inputs()
    kind, loc = field
    R = np.load(loc, mmap_mode="r") if kind == "npy" else open_zarr_field(loc)
    rows = R[s0:s1]  # a view of the memory map, or the Zarr chunks read
    out = relight_field(rows, weights, light_color=light_color, workers=1)
    if _is_zarr_target(relit):
        import zarr

        zarr.open_array(relit, mode="r+")[s0:s1] = out
    else:
        dst = np.load(relit, mmap_mode="r+")
        dst[s0:s1] = out
        dst.flush()
        del dst
    return {"texels": int(s1 - s0), "seconds": time.perf_counter() - t0}


def _is_zarr_target(location: str) -> bool:
    return "://" in str(location) or str(location).endswith(".zarr")


def _relit_rows_target(parts, cam: str, n: int, step: int) -> str:
    """Create the ``(n, 3)`` float32 relit rows of camera ``cam`` in ``parts`` (a folder: a
    ``.npy``; an fsspec URL: a Zarr array chunked by ``step`` rows, one chunk a task)."""
    if isinstance(parts, str) and "://" in parts and not parts.startswith("file://"):
        import zarr

        loc = f"{parts.rstrip('/')}/{cam}.zarr"
        zarr.create_array(store=loc, shape=(n, 3), chunks=(max(min(step, n), 1), 3),
                          dtype="float32", fill_value=np.nan, overwrite=True)
        return loc
    folder = Path(parts[len("file://"):] if isinstance(parts, str)
                  and parts.startswith("file://") else parts)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{cam}.npy"
    np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=(n, 3)).flush()
    return str(path)


def _read_relit_rows(location: str) -> np.ndarray:
    if _is_zarr_target(location):
        import zarr

        return np.asarray(zarr.open_array(location, mode="r")[:])
    return np.load(location)


def relight_texture(field_dir: str | os.PathLike | None, weights: Any, *,
                    light_color: Any = None,
                    progress: Callable[[int, int], None] | None = None,
                    project_dir: str | os.PathLike | None = None,
                    atlas_dir: str | os.PathLike | None = None,
                    engine=None, parts_dir: str | os.PathLike | None = None,
                    ) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Relight the surface reflectance field in texture space (Eq. 4 on every camera's field,
    blended per texel by the camera weights).

    For texel t seen by cameras c with weights ``w_c(t)`` (light-independent, see
    ``docs/surface.md``)::

        L̂(t) = Σ_c w_c(t) · Σ_l R_c(t, l) ⊙ w_l  /  Σ_c w_c(t)

    which equals relighting the blended field ``Σ_c w_c R_c / Σ_c w_c`` because the camera
    weights are the same for every light: relighting stays linear in the environment. A
    camera whose relit value is NaN/inf for a texel's channel (a masked sample at a lit light)
    is left out of that texel's blend (the remaining cameras are renormalised); a texel no
    camera measured is NaN.

    Parameters
    ----------
    field_dir : path or None
        Folder holding ``atlas/texels.npz`` and ``project/<camera>/`` (``SCAN/out``).
    weights : (L, 3) float
        Eq. (4) weights (δA included), L the scan's lights.
    light_color : (3,) or (L, 3), optional
        Divide the weights by the recording light's colour (see
        :func:`facegeo.lighting.relight.relight_field`).
    progress : callable(done, total), optional
        Called as each camera's last task finishes (in process: after each camera).
    project_dir, atlas_dir : path, optional
        The ``project`` and ``atlas`` stage folders when they are not ``field_dir/project``
        and ``field_dir/atlas`` (the cached stages of ``facegeo reconstruct``).
    engine : facegeo.pipeline.engine.Engine, optional
        Where the relight tasks run (default in process): each camera's field in tasks of
        :data:`RELIGHT_TASK_TEXELS` rows (:func:`relight_rows_task`), each checked against a
        worker's memory (:func:`relight_working_set`) before any runs. The blend runs here,
        in camera order: the result is the same whatever the engine.
    parts_dir : path or str, optional
        Where the tasks' relit rows go (``<camera>.npy``, removed afterwards): a folder, on a
        cluster one the workers share; or an fsspec URL (``s3://bucket/tmp``: a Zarr array
        per camera, for workers that share no disk — with fields in a store too,
        :func:`facegeo.surface.reflectance.find_field`). Default: a temporary folder (in
        process only).

    Returns
    -------
    relit : (T, 3) float32
        Relit radiance per texel, NaN where no camera measured it.
    weight_sum : (T, 3) float64
        ``Σ_c w_c(t)`` over the cameras blended (per channel); 0 where unmeasured.
    cameras : list of str
    """
    import shutil
    import tempfile

    from facegeo.lighting.relight import normalize_weights
    from facegeo.pipeline.engine import InProcessEngine, Task
    from facegeo.surface.atlas import Texels
    from facegeo.surface.reflectance import find_field, open_field

    proj, texels_path = _texture_dirs(field_dir, project_dir, atlas_dir)
    cams = _project_cameras(proj, texels_path)
    n_t = len(Texels.load(texels_path))
    engine = InProcessEngine() if engine is None else engine
    if parts_dir is None and engine.kind != "in-process":
        raise InputError("relight_texture: parts_dir: a folder the workers share, for their "
                         "relit rows (a temporary folder of this machine serves in process only)")
    own = parts_dir is None
    parts = tempfile.mkdtemp(prefix="facegeo-relight-") if own else parts_dir
    tasks, layout = [], []
    try:
        for cam in cams:
            R = open_field(cam)
            idx = np.load(cam / "texel_index.npy")
            wc = np.load(cam / "weight.npy").astype(np.float64)
            if R.ndim != 3 or R.shape[0] != idx.size or wc.shape != idx.shape:
                raise InputError(f"{cam}: R.npy {R.shape}, texel_index.npy {idx.shape} and "
                                 f"weight.npy {wc.shape} disagree (re-run 'facegeo project')")
            if idx.size and (idx.min() < 0 or idx.max() >= n_t):
                raise InputError(f"{cam}/texel_index.npy: indices outside the atlas's {n_t} "
                                 f"texels (the atlas was rebuilt after the projection; re-run "
                                 f"'facegeo project')")
            step = _task_rows(R, normalize_weights(weights, R.shape[1], light_color))
            relit_path = _relit_rows_target(parts, cam.name, idx.size, step)
            layout.append((cam, relit_path))
            kind, loc = find_field(cam)  # the field itself: a path, or a store's URL
            for s0 in range(0, idx.size, step):
                s1 = min(s0 + step, idx.size)
                tasks.append(Task(f"{cam.name} {s0}:{s1}", relight_rows_task,
                                  ((kind, str(loc)), relit_path, s0, s1, weights, light_color),
                                  working_set=relight_working_set(s1 - s0, R.shape[1],
                                                                  R.dtype.itemsize),
                                  size=int(s1 == idx.size)))  # progress: per camera
        told = [0]

        def tick(stage, k, n):  # (cameras whose last rows are relit, cameras)
            if k > told[0]:
                told[0] = k
                progress(k, n)

        engine.map("relight", tasks, progress=tick if progress else None)
        acc = np.zeros((n_t, 3))
        wsum = np.zeros((n_t, 3))
        for cam, relit_path in layout:  # camera order, wherever the tasks ran
            idx = np.load(cam / "texel_index.npy")
            wc = np.load(cam / "weight.npy").astype(np.float64)
            relit = _read_relit_rows(relit_path).astype(np.float64)
            ok = np.isfinite(relit)
            # texel_index is unique within a camera: plain fancy-index accumulation is exact
            acc[idx] += np.where(ok, wc[:, None] * np.where(ok, relit, 0.0), 0.0)
            wsum[idx] += np.where(ok, wc[:, None], 0.0)
    finally:
        if own:
            shutil.rmtree(parts, ignore_errors=True)
        else:
            from facegeo.surface._zarr_field import remove_location

            for _, relit_path in layout:
                remove_location(relit_path)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(wsum > 0, acc / wsum, np.nan).astype(np.float32)
    return out, wsum, [c.name for c in cams]


def _texture_dirs(field_dir, project_dir, atlas_dir) -> tuple[Path, Path]:
    """``(project folder, texels.npz path)`` from ``field_dir`` or the explicit folders."""
    if field_dir is None and (project_dir is None or atlas_dir is None):
        raise InputError("relight_texture: give field_dir, or both project_dir and atlas_dir")
    proj = Path(project_dir) if project_dir is not None else Path(field_dir) / "project"
    atlas = Path(atlas_dir) if atlas_dir is not None else Path(field_dir) / "atlas"
    return proj, atlas / "texels.npz"


def resolve_env(env: str | os.PathLike, projection: str = "latlong", *, rotate_deg: float = 0.0,
                convention: str = "facegeo"):
    """An :class:`~facegeo.lighting.envmap.EnvironmentMap` from a file, or a shipped map's name.

    ``env`` is an existing ``.exr``/``.hdr`` path (read with ``projection``), or the name of a
    procedural map shipped with facegeo (:data:`facegeo.lighting.envmap.SHIPPED_MAPS`:
    ``"sky"``, ``"studio"``; lat-long). A file of that name in the working folder wins.
    """
    from facegeo.lighting import envmap as E

    if not math.isfinite(float(rotate_deg)):
        raise InputError(f"rotate: expected a finite angle in degrees, got {fmt_value(rotate_deg)}")
    if not Path(env).exists() and str(env) in E.SHIPPED_MAPS:
        if convention != "facegeo":
            raise InputError(f"convention: the shipped map {fmt_value(str(env))} is in facegeo's "
                             f"lat-long convention; --envmap-convention applies to map files")
        if projection != "latlong":
            raise InputError(f"projection: the shipped map {fmt_value(str(env))} is lat-long; "
                             f"--projection {projection} applies to map files")
        return E.shipped_map(str(env)).rotated(math.radians(float(rotate_deg)))
    return E.read_envmap(env, projection, rotate_deg=rotate_deg, convention=convention)


def relight_products(scan, project_dir: str | os.PathLike | None, dest: str | os.PathLike, *,
                     env: str | os.PathLike, rotate: float = 0.0, view: str = "texture",
                     atlas_dir: str | os.PathLike | None = None, projection: str = "latlong",
                     solid_angle: str = "paper",
                     progress: Callable[[str, int, int], None] | None = None,
                     read_ahead: int = 0, model: str = "measured",
                     fit_dir: str | os.PathLike | None = None,
                     convention: str = "facegeo", engine=None,
                     store: str | os.PathLike | None = None) -> tuple[dict, dict]:
    """Write the ``relight`` products of ``scan`` into ``dest``: the relit image as EXR and a
    tone-mapped PNG (Debevec et al. 2000 §3.3, Eq. 4).

    The work of :func:`run_relight` without its JSON file, for the cached stage of
    ``facegeo reconstruct`` (the stage cache gathers the returned metrics).

    Parameters
    ----------
    scan : facegeo.capture.scan.Scan
        The loaded scan.
    project_dir : path or None
        The ``project`` stage's folder (``<camera>/R.npy`` ``(T_c, L, 3)`` float16,
        ``texel_index.npy``, ``weight.npy``); needed for ``view="texture"`` only.
    dest : path
        Output folder (created).
    env : path or str
        Environment map file, or a shipped map's name (``"sky"``, ``"studio"``; see
        :func:`resolve_env`).
    rotate : float, degrees
        Rotation of the environment about +Y (right-hand rule: +Z turns toward +X).
    view : str
        ``"texture"``: the texture atlas relit from the projected field
        (:func:`relight_texture`); or a camera name: that camera's OLAT frames, reading only lit
        lights.
    atlas_dir : path, optional
        The ``atlas`` stage's folder (``texels.npz``); default ``project_dir/../atlas``.
    projection : {"latlong", "mirror-ball", "angular", "cube"} (or "mirrorball")
        Of an environment file.
    convention : str
        Of a lat-long environment file (:data:`facegeo.lighting.envmap.LATLONG_CONVENTIONS`).
    solid_angle : {"paper", "exact"}
        δA rule of the light-basis projection (:func:`facegeo.lighting.envmap.light_stage_weights`).
    progress : callable(stage, done, total), optional
    read_ahead : int
        Camera view: threads reading the next OLAT frames meanwhile
        (:func:`facegeo.lighting.relight.relight_scan_view`).
    model : {"measured", "fitted"}
        ``"measured"`` (default): Eq. 4 on the measured OLAT frames or field — the image holds
        only what the lights cover. ``"fitted"``: the camera view from the fitted per-pixel
        models of an image-space fit (``fit_dir/photometric.npz``, :func:`relight_fitted`):
        the environment sampled on every direction (:data:`FITTED_GRID`), each direction's
        light predicted by the model — the specular lobe evaluated from its fitted parameters,
        not interpolated between measured lights.
    fit_dir : path, optional
        The ``fit`` stage's folder for ``model="fitted"`` (default ``SCAN/out/fit``).
    engine : facegeo.pipeline.engine.Engine, optional
        Where the texture view's relight tasks run (:func:`relight_texture`; their relit rows
        go to ``dest/.parts``, removed afterwards); default in process. The metrics gain
        ``engine`` on a cluster.
    store : str or path, optional
        ``--store URL``: the texture view's relit rows go to Zarr arrays under
        ``URL/relight/`` (removed afterwards) instead of ``dest/.parts``, for workers that
        share no disk; the fields are read wherever they are (a ``R.zarr.url`` link in a
        camera folder names a field in a store, :func:`facegeo.surface._zarr_field.link_field`).

    Returns
    -------
    metrics : dict
        ``files`` (``exr``, ``png``; ``measured`` for the texture view), ``energy_ratio``
        (``Σ_l w_l / ∫ L dω`` per channel: the light-basis projection's energy check, 1 up to the
        δA rule), ``energy_note`` (a sentence when the lights keep less than
        :data:`DOME_ENERGY_NOTE` of the environment's energy, e.g. a dome's upper hemisphere,
        else None), ``model``, ``active_lights``, ``mean_radiance``, ``seconds``. The stage reads
        no truth: a camera view's error against the generator's render under the same weights
        is :func:`facegeo.evaluate.relit.evaluate_relit`'s (``facegeo evaluate``, from the
        files :func:`run_relight` writes).
    settings : dict
        The settings that determine the products (for the stage cache key).
    """
    from facegeo.capture import imageio
    from facegeo.lighting import envmap as E
    from facegeo.lighting.relight import relight_scan_view
    from facegeo.surface._zarr_field import store_location

    t0 = time.perf_counter()
    check_choice(solid_angle, "solid_angle", ("paper", "exact"))
    check_choice(model, "model", ("measured", "fitted"))
    names = scan.camera_names
    texture = view == "texture"
    fitted_path = None
    if model == "fitted":
        fitted_path = _fitted_model_path(scan, view, fit_dir)
    elif texture:
        if project_dir is None:
            raise InputError("project_dir: view='texture' relights the projected surface "
                             "reflectance field; give the 'project' stage's folder (run "
                             "'facegeo project SCAN' first)")
        proj, texels_path = _texture_dirs(None, project_dir, atlas_dir if atlas_dir is not None
                                          else Path(project_dir).parent / "atlas")
        _project_cameras(proj, texels_path)  # clear error before reading the environment
    else:
        if not scan.has("olat"):
            raise InputError(f"{scan.root}: the scan has no OLAT frames to relight")
        if view not in names:
            raise InputError(f"view: unknown camera {fmt_value(view)}; the scan has "
                             f"{', '.join(names)} (or 'texture')")
    env_map = resolve_env(env, projection, rotate_deg=rotate, convention=convention)
    settings = {"env": str(env), "rotate": float(rotate), "view": view,
                "projection": env_map.projection, "solid_angle": solid_angle,
                "model": model}
    if env_map.convention != "facegeo":  # only then: the default keeps the stage's cache key
        settings["convention"] = env_map.convention
    lights = scan.rig.lights
    t_env = time.perf_counter()
    integral = env_map.integral()
    if fitted_path is not None:
        return _relight_fitted_products(scan, view, env_map, fitted_path, Path(dest), env,
                                        rotate, settings, t0, integral)
    w = E.light_weights(env_map, lights, solid_angle=solid_angle)  # a grid or a light list
    active = int(np.count_nonzero(np.any(w != 0, axis=1)))
    t_w = time.perf_counter()
    extra: dict[str, Any] = {}
    if texture:
        from facegeo.surface.atlas import Texels

        tick = (lambda k, n: progress("relight", k, n)) if progress else None
        # each light's own colour (a list's per-light intensities; a dark light weighs 0)
        parts = (Path(dest) / ".parts" if store is None
                 else str(store_location(store, "relight", f"parts-{os.getpid()}")))
        try:
            texel_rgb, _, cams = relight_texture(None, E.field_weights(w, lights),
                                                 progress=tick, project_dir=proj,
                                                 atlas_dir=texels_path.parent, engine=engine,
                                                 parts_dir=parts)
        finally:
            import shutil

            if store is None:
                shutil.rmtree(parts, ignore_errors=True)
        texels = Texels.load(texels_path)
        measured = np.isfinite(texel_rgb).all(axis=1)
        img = texels.to_image(np.where(measured[:, None], texel_rgb, 0.0).astype(np.float32),
                              fill=0.0)
        extra = {"cameras": cams, "texels": int(measured.size),
                 "measured_texels": int(measured.sum()),
                 "mask": texels.to_image(measured.astype(np.uint8) * 255, fill=0)}
        mean_src = texel_rgb[measured]
        t_relit = time.perf_counter()
    else:
        tick = (lambda k: progress("relight", k + 1, active)) if progress else None
        img = relight_scan_view(scan, view, w, normalize_color=True, progress=tick,
                                read_ahead=read_ahead)
        mean_src = img.reshape(-1, 3)
        t_relit = time.perf_counter()

    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    rot = f"{float(rotate):g}".replace("-", "m")
    # the projection and the δA rule are part of the name when they are not the defaults (a
    # map read as a mirror ball, or an exact-solid-angle relight, does not overwrite the others)
    rule = ("" if solid_angle == "paper" or not hasattr(lights, "n_theta")  # a list: its own δA
            else f"_{_safe_stem(solid_angle)}")
    proj_tag = ("" if env_map.projection == "latlong" else f"_{env_map.projection}") + (
        "" if env_map.convention == "facegeo" else f"_{env_map.convention}")
    stem = f"{_safe_stem(Path(str(env)).stem)}{proj_tag}_rot{rot}_{_safe_stem(view)}{rule}"
    exr = imageio.write_image(dest / f"{stem}.exr", img)  # atomic (temporary file + rename)
    png_img, exposure = tone_map(img)
    png = imageio.write_image(dest / f"{stem}.png", png_img)
    files = {"exr": str(exr), "png": str(png)}
    if texture:
        files["measured"] = str(imageio.write_image(dest / f"{stem}_measured.png",
                                                    extra.pop("mask")))
    metrics = {
        "scan": str(scan.root), "view": view, "env": str(env),
        "projection": env_map.projection, "envmap_convention": env_map.convention,
        "rotate_deg": float(rotate), "solid_angle": solid_angle, "n_lights": int(lights.n_lights), "active_lights": active,
        "energy_ratio": (ratio := (w.sum(0) / np.where(integral > 0, integral, 1))).tolist(),
        "energy_note": energy_note(ratio, lights.n_lights), "model": model,
        "mean_radiance": (mean_src.mean(0) if len(mean_src) else np.zeros(3)).tolist(),
        "tone_map_exposure": exposure, "files": files, **extra,
        "seconds": {"env": t_env - t0, "weights": t_w - t_env, "relight": t_relit - t_w,
                    "total": time.perf_counter() - t0},
    }
    if texture and engine is not None and engine.kind != "in-process":
        metrics["engine"] = engine.stage_metrics(
            "relight", [r.task for r in engine.records if r.stage == "relight"])
    log.info("relit %s with %s (%d active lights) in %.2f s", view, env, active,
             metrics["seconds"]["total"])
    return metrics, settings


def energy_note(ratio, n_lights: int) -> str | None:
    """The sentence a user reads when the lights keep only part of the environment's energy
    (``Σ w / ∫ L`` below :data:`DOME_ENERGY_NOTE` in any channel), else None."""
    r = float(np.min(ratio))
    if not r < DOME_ENERGY_NOTE:
        return None
    return (f"the {n_lights} lights keep only {r:.0%} of the environment's energy "
            f"(sum(w)/integral(L) = {r:.2f}): the rest arrives from directions no light covers "
            "(e.g. below a dome) and is missing from the relit image; --model fitted predicts "
            "every direction from a single-view scan's fitted model")


def _fitted_model_path(scan, view: str, fit_dir) -> Path:
    """``fit_dir/photometric.npz`` of an image-space fit of ``view``, or a clear error."""
    if view == "texture" or view not in scan.camera_names:
        raise InputError(f"view: --model fitted relights a camera of a single-view scan fitted "
                         f"in image space; got {fmt_value(view)} (cameras: "
                         f"{', '.join(scan.camera_names)})")
    path = (Path(fit_dir) if fit_dir is not None else scan.out_dir / "fit") / "photometric.npz"
    if not path.is_file():
        raise InputError(f"{path} is missing: --model fitted needs the image-space fit of a "
                         f"single-view scan; run 'facegeo fit {scan.root}' first (a scan with a "
                         "mesh is fitted per texel: relight it with --model measured or render "
                         "it with 'facegeo render')")
    return path


def relight_fitted(path, env_map, *, grid=FITTED_GRID) -> tuple[np.ndarray, np.ndarray]:
    """The camera image under an environment predicted by an image-space fit's models.

    Eq. 4 of Debevec et al. 2000 with the fitted per-pixel models in place of measured
    reflectance functions: ``Σ_k L̄_k δA_k ⊙ f(ω_k)``, ω_k every cell centre of a
    ``grid = (n_θ, n_φ)`` lat-long grid over the sphere (exact cell solid angles, so
    ``Σ w = ∫ L``), f the pixel's model evaluated at ω_k
    (:func:`facegeo.appearance.photometric.predict_environment`: Lambertian, shadow map, and
    the Torrance–Sparrow lobe from its fitted parameters). A grey fit is relit channel by
    channel (its albedo times each channel's light).

    Parameters
    ----------
    path : path — ``photometric.npz`` with ``rows`` and ``image_size`` (the fit stage's)
    env_map : EnvironmentMap
    grid : (int, int)

    Returns
    -------
    image : (H, W, 3) float32 — 0 where no pixel was fitted
    weights : (n_θ n_φ, 3) float64 — the Eq. 4 weights used (δA included)
    """
    from facegeo.appearance.photometric import load_photometric, predict_environment
    from facegeo.appearance.skin import LightSet
    from facegeo.lighting import envmap as E

    model = load_photometric(path)
    with np.load(path) as z:
        if "rows" not in z.files or "image_size" not in z.files:
            raise InputError(f"{path}: no 'rows' / 'image_size' arrays (not written by the fit "
                             "stage; re-run 'facegeo fit')")
        rows = z["rows"].astype(np.int64)
        W, H = (int(x) for x in z["image_size"])
    nt, npf = (int(g) for g in grid)
    w = E.light_stage_weights(env_map, nt, npf, solid_angle="exact")
    dirs = LightSet.from_grid(nt, npf).directions
    lit = np.any(w != 0, axis=1)
    if model.b_lambert.shape[1] == 3:
        vals = predict_environment(model, dirs[lit], w[lit])
    else:
        vals = np.concatenate([predict_environment(model, dirs[lit], w[lit, c])
                               for c in range(3)], axis=1)
    img = np.zeros((H * W, 3), np.float32)
    img[rows] = np.nan_to_num(vals, nan=0.0)
    return img.reshape(H, W, 3), w


def _relight_fitted_products(scan, view, env_map, path, dest: Path, env, rotate, settings, t0,
                             integral) -> tuple[dict, dict]:
    """:func:`relight_products` for ``model="fitted"``."""
    from facegeo.capture import imageio

    t_w = time.perf_counter()
    img, w = relight_fitted(path, env_map)
    t_relit = time.perf_counter()
    dest.mkdir(parents=True, exist_ok=True)
    rot = f"{float(rotate):g}".replace("-", "m")
    proj_tag = ("" if env_map.projection == "latlong" else f"_{env_map.projection}") + (
        "" if env_map.convention == "facegeo" else f"_{env_map.convention}")
    stem = f"{_safe_stem(Path(str(env)).stem)}{proj_tag}_rot{rot}_{_safe_stem(view)}_fitted"
    exr = imageio.write_image(dest / f"{stem}.exr", img)
    png_img, exposure = tone_map(img)
    png = imageio.write_image(dest / f"{stem}.png", png_img)
    ratio = w.sum(0) / np.where(integral > 0, integral, 1)
    flat = img.reshape(-1, 3)
    lit_px = flat[np.any(flat != 0, axis=1)]
    metrics = {
        "scan": str(scan.root), "view": view, "env": str(env), "model": "fitted",
        "fit": str(path), "projection": env_map.projection,
        "envmap_convention": env_map.convention, "rotate_deg": float(rotate),
        "solid_angle": "exact", "n_lights": int(w.shape[0]),
        "active_lights": int(np.count_nonzero(np.any(w != 0, axis=1))),
        "grid": list(FITTED_GRID), "energy_ratio": ratio.tolist(),
        "energy_note": energy_note(ratio, int(w.shape[0])),
        "mean_radiance": (lit_px.mean(0) if len(lit_px) else np.zeros(3)).tolist(),
        "tone_map_exposure": exposure, "files": {"exr": str(exr), "png": str(png)},
        "seconds": {"env": t_w - t0, "weights": 0.0, "relight": t_relit - t_w,
                    "total": time.perf_counter() - t0},
    }
    log.info("relit %s from the fitted model with %s in %.2f s", view, env,
             metrics["seconds"]["total"])
    return metrics, settings


def run_relight(scan_dir: str | os.PathLike, env_path: str | os.PathLike, *,
                rotate_deg: float = 0.0, view: str | None = None,
                out_dir: str | os.PathLike | None = None, projection: str = "latlong",
                solid_angle: str = "paper", field_dir: str | os.PathLike | None = None,
                progress: Callable[[str, int, int], None] | None = None,
                read_ahead: int = 0, model: str = "measured", convention: str = "facegeo",
                engine=None, store: str | os.PathLike | None = None) -> dict:
    """Relight one camera of a scan, or its texture atlas, with an environment map and write
    the images.

    Parameters
    ----------
    scan_dir : path
        Scan directory (``scan.toml``) with OLAT frames.
    env_path : path or str
        ``.exr``/``.hdr`` environment map, or a shipped map's name (``"sky"``, ``"studio"``).
    rotate_deg : float, degrees
        Rotation of the environment about +Y (right-hand rule: +Z turns toward +X).
    view : str, optional
        Camera name (default: the scan's first camera), or ``"texture"``: the surface
        reflectance field of ``facegeo project`` relit and blended per texel
        (:func:`relight_texture`); the output is the atlas image, 0 where no camera measured a
        texel (and outside the charts), with ``<stem>_measured.png`` marking measured texels.
    out_dir : path, optional
        Default ``SCAN/out/relit`` (``out/relight`` is the cached stage of ``facegeo
        reconstruct``, which replaces its folder when it reruns).
    projection : {"latlong", "mirror-ball", "angular", "cube"} (or "mirrorball")
    convention : str
        Of a lat-long environment file (:data:`facegeo.lighting.envmap.LATLONG_CONVENTIONS`).
    solid_angle : {"paper", "exact"}
        δA rule of the light-basis projection (:func:`facegeo.lighting.envmap.light_stage_weights`).
    field_dir : path, optional
        For ``view="texture"``: the folder with ``atlas/`` and ``project/`` (default
        ``SCAN/out``).
    progress : callable(stage, done, total), optional
        Per active light (camera view) or per camera (texture view).
    read_ahead : int
        See :func:`relight_products` (the CLI reads two ahead).
    model : {"measured", "fitted"}
        See :func:`relight_products` (``"fitted"``: the image-space fit in
        ``field_dir/fit``, default ``SCAN/out/fit``).
    engine : facegeo.pipeline.engine.Engine, optional
        Where the texture view's tasks run (:func:`relight_texture`); default in process.
    store : str or path, optional
        See :func:`relight_products`.

    Returns
    -------
    dict
        Metrics: the files written, the view, the environment, the active lights, the energy
        check ``Σ w / ∫ L`` per channel, the image's mean radiance, timings.
    """
    from facegeo.capture.scan import load_scan
    from facegeo.fsutil import atomic_write_text

    if not math.isfinite(float(rotate_deg)):
        raise InputError(f"rotate: expected a finite angle in degrees, got {fmt_value(rotate_deg)}")
    scan = load_scan(scan_dir)
    if view is None:
        view = scan.camera_names[0]
    fdir = Path(field_dir) if field_dir is not None else scan.out_dir
    out = Path(out_dir) if out_dir is not None else scan.out_dir / "relit"
    metrics, _ = relight_products(scan, fdir / "project", out, env=env_path, rotate=rotate_deg,
                                  view=view, atlas_dir=fdir / "atlas", projection=projection,
                                  solid_angle=solid_angle,
                                  progress=progress, read_ahead=read_ahead, model=model,
                                  fit_dir=fdir / "fit", convention=convention,
                                  engine=engine, store=store)
    stem = Path(metrics["files"]["exr"]).stem
    atomic_write_text(out / f"{stem}.json", json.dumps(metrics, indent=2))
    return metrics
