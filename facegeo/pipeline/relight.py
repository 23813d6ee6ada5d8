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
metrics beside the images. :func:`relight_maps_products` and :func:`run_relight_maps` do the same
under several maps (``--env A --env B``, or a folder of maps): each map's own files, the field
(or the camera's OLAT frames) read once per batch of :data:`RELIGHT_MAPS_PER_TASK` maps.
``env`` may name a shipped procedural map (``"sky"``, ``"studio"``,
:func:`facegeo.lighting.envmap.shipped_map`). Progress goes through the ``progress`` callback, the
library only logs.

The steps live in private modules and are re-exported here: the texture relight's tasks and
their rows (:func:`relight_rows_task`, :func:`relight_working_set`) in
:mod:`facegeo.pipeline._relight_texture`, ``--model fitted`` (:func:`relight_fitted`) in
:mod:`facegeo.pipeline._relight_fitted`; a camera view under a batch of maps is
:func:`facegeo.lighting.relight.relight_scan_view_maps`. :func:`relight_texture` and the task
sizes it reads (:data:`RELIGHT_TASK_TEXELS`, :data:`RELIGHT_MAPS_PER_TASK`) stay here.
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
# steps in their own modules, re-exported here (module docstring)
from facegeo.pipeline._relight_fitted import FITTED_GRID, _fitted_model_path, relight_fitted
from facegeo.pipeline._relight_texture import (RELIGHT_BYTES_FIXED, RELIGHT_BYTES_PER_SAMPLE,
                                               RELIGHT_BYTES_PER_TEXEL, _project_cameras,
                                               _read_relit_rows, _relit_rows_target,
                                               _texture_dirs, relight_rows_task,
                                               relight_working_set)

log = logging.getLogger(__name__)

__all__ = ["run_relight", "run_relight_maps", "relight_products", "relight_maps_products",
           "relight_rows_task", "relight_texture", "relight_fitted", "relight_working_set",
           "expand_env_maps", "resolve_env", "tone_map", "energy_note",
           "RELIGHT_MAPS_PER_TASK"]

#: Tone mapping: the 99.5th percentile of luminance maps to this display value before sRGB.
TONE_MAP_WHITE = 0.9
#: Below this share of the environment's energy (Σ w / ∫ L, any channel) the lights keep, the
#: metrics and the CLI say so (a dome of the upper hemisphere keeps ≈ 0.79 of a sky).
DOME_ENERGY_NOTE = 0.95


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


#: Texels (rows of a camera's field) per relight task: 32,768 × 512 lights × 3 float16 =
#: 96 MiB of field a task at the modern preset's lights (a camera of 174 k texels: 6 tasks).
RELIGHT_TASK_TEXELS = 32768
#: Environment maps a relight task relights its rows under at once (one GEMM a chunk of rows,
#: :func:`facegeo.lighting.relight.relight_field` with ``(B, L, 3)`` weights: the rows are read
#: once for the B maps). Bounds a task's relit rows (B × 36 B a texel) and the client's blend
#: of a batch. Measured on the tiny scan's texture (80 k texel rows × 128 lights, float16, one
#: thread; ``docs/scale.md`` §1): batched against one map at a time 1.9× at 4 maps, 2.9–3.2×
#: at 8, 3.0–3.2× at 16 — little gain past 8 (the GEMM is compute-bound), only larger tasks.
RELIGHT_MAPS_PER_TASK = 8


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


def _map_batches(n_maps: int, per: int | None = None) -> list[tuple[int, int]]:
    """``[(b0, b1), …]``: maps ``0:n_maps`` in batches of ``per`` (default
    :data:`RELIGHT_MAPS_PER_TASK`)."""
    per = max(1, int(per if per is not None else RELIGHT_MAPS_PER_TASK))
    return [(b0, min(b0 + per, n_maps)) for b0 in range(0, n_maps, per)]


def relight_texture(field_dir: str | os.PathLike | None, weights: Any, *,
                    light_color: Any = None,
                    progress: Callable[[int, int], None] | None = None,
                    project_dir: str | os.PathLike | None = None,
                    atlas_dir: str | os.PathLike | None = None,
                    engine=None, parts_dir: str | os.PathLike | None = None,
                    first_map: int = 0) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Relight the surface reflectance field in texture space (Eq. 4 on every camera's field,
    blended per texel by the camera weights), under one environment or a batch of them.

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
    weights : (L, 3) or (B, L, 3) float
        Eq. (4) weights (δA included), L the scan's lights; ``(B, L, 3)``: B environments,
        relit in batches of :data:`RELIGHT_MAPS_PER_TASK` — a task reads its rows once for
        its batch (one GEMM a chunk of rows, :func:`facegeo.lighting.relight.relight_field`).
        A batch of one map takes the same fused kernel as ``(L, 3)`` (the same bytes); a
        batch of several agrees with one map at a time to float32 rounding (``docs/scale.md``).
    light_color : (3,) or (L, 3), optional
        Divide the weights by the recording light's colour (see
        :func:`facegeo.lighting.relight.relight_field`).
    progress : callable(done, total), optional
        Called as the last task of a (camera, batch of maps) finishes: ``total`` is cameras ×
        batches (one batch for ``(L, 3)`` weights: per camera).
    project_dir, atlas_dir : path, optional
        The ``project`` and ``atlas`` stage folders when they are not ``field_dir/project``
        and ``field_dir/atlas`` (the cached stages of ``facegeo reconstruct``).
    engine : facegeo.pipeline.engine.Engine, optional
        Where the relight tasks run (default in process): each camera's field in tasks of
        :data:`RELIGHT_TASK_TEXELS` rows and one batch of maps (:func:`relight_rows_task`),
        each checked against a worker's memory (:func:`relight_working_set`) before any runs.
        The blend runs here, in camera order: the result is the same whatever the engine.
    parts_dir : path or str, optional
        Where the tasks' relit rows go (``<camera>.npy``, ``<camera>_maps<b0>.npy`` for a
        batch; removed afterwards): a folder, on a cluster one the workers share; or an fsspec
        URL (``s3://bucket/tmp``: a Zarr array per camera and batch, for workers that share no
        disk — with fields in a store too, :func:`facegeo.surface.reflectance.find_field`).
        Default: a temporary folder (in process only).
    first_map : int
        Index of ``weights[0]`` among the maps of a larger run, in the tasks' names
        (``"<camera> <s0>:<s1> maps <b0>:<b1>"`` for ``(B, L, 3)`` weights) and the parts'.

    Returns
    -------
    relit : (T, 3) float32, or (B, T, 3) for ``(B, L, 3)`` weights
        Relit radiance per texel, NaN where no camera measured it.
    weight_sum : (T, 3) float64, or (B, T, 3)
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
    batched = np.ndim(weights) == 3
    w_all = np.asarray(weights) if batched else np.asarray(weights)[None]
    n_maps = w_all.shape[0]
    batches = _map_batches(n_maps)
    engine = InProcessEngine() if engine is None else engine
    if parts_dir is None and engine.kind != "in-process":
        raise InputError("relight_texture: parts_dir: a folder the workers share, for their "
                         "relit rows (a temporary folder of this machine serves in process only)")
    own = parts_dir is None
    parts = tempfile.mkdtemp(prefix="facegeo-relight-") if own else parts_dir
    tasks, layout = [], []
    small: dict = {}  # per camera (texel_index, weight): read once, blended under every map
    try:
        for cam in cams:
            R = open_field(cam)
            idx = np.load(cam / "texel_index.npy")
            wc = np.load(cam / "weight.npy").astype(np.float64)
            small[cam] = (idx, wc)
            if R.ndim != 3 or R.shape[0] != idx.size or wc.shape != idx.shape:
                raise InputError(f"{cam}: R.npy {R.shape}, texel_index.npy {idx.shape} and "
                                 f"weight.npy {wc.shape} disagree (re-run 'facegeo project')")
            if idx.size and (idx.min() < 0 or idx.max() >= n_t):
                raise InputError(f"{cam}/texel_index.npy: indices outside the atlas's {n_t} "
                                 f"texels (the atlas was rebuilt after the projection; re-run "
                                 f"'facegeo project')")
            kind, loc = find_field(cam)  # the field itself: a path, or a store's URL
            for b0, b1 in batches:
                wb = w_all[b0:b1]
                step = _task_rows(R, normalize_weights(wb, R.shape[1], light_color))
                one = not batched
                m0, m1 = first_map + b0, first_map + b1
                name = cam.name if one else f"{cam.name}_maps{m0}"
                relit_path = _relit_rows_target(parts, name, idx.size, step, b1 - b0)
                layout.append((cam, b0, b1, relit_path))
                for s0 in range(0, idx.size, step):
                    s1 = min(s0 + step, idx.size)
                    tasks.append(Task(f"{cam.name} {s0}:{s1}" + ("" if one
                                                                  else f" maps {m0}:{m1}"),
                                      relight_rows_task,
                                      ((kind, str(loc)), relit_path, s0, s1, wb, light_color),
                                      working_set=relight_working_set(
                                          s1 - s0, R.shape[1], R.dtype.itemsize, b1 - b0),
                                      size=int(s1 == idx.size)))  # progress: (camera, batch)
        told = [0]

        def tick(stage, k, n):  # ((camera, batch)s whose last rows are relit, their number)
            if k > told[0]:
                told[0] = k
                progress(k, n)

        engine.map("relight", tasks, progress=tick if progress else None)
        out = np.empty((n_maps, n_t, 3), np.float32)
        wsum_all = np.zeros((n_maps, n_t, 3))
        for j in range(n_maps):  # per map: the blend's float64 sums of one map at a time
            acc = np.zeros((n_t, 3))
            wsum = wsum_all[j]
            for cam, b0, b1, relit_path in layout:  # camera order, wherever the tasks ran
                if not b0 <= j < b1:
                    continue
                idx, wc = small[cam]
                relit = _read_relit_rows(relit_path, j - b0).astype(np.float64)
                ok = np.isfinite(relit)
                # texel_index is unique within a camera: plain fancy-index accumulation is exact
                acc[idx] += np.where(ok, wc[:, None] * np.where(ok, relit, 0.0), 0.0)
                wsum[idx] += np.where(ok, wc[:, None], 0.0)
            with np.errstate(invalid="ignore", divide="ignore"):
                out[j] = np.where(wsum > 0, acc / wsum, np.nan)
    finally:
        if own:
            shutil.rmtree(parts, ignore_errors=True)
        else:
            from facegeo.surface._zarr_field import remove_location

            for *_, relit_path in layout:
                remove_location(relit_path)
    if not batched:
        return out[0], wsum_all[0], [c.name for c in cams]
    return out, wsum_all, [c.name for c in cams]


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
    metrics, settings, _ = relight_maps_products(
        scan, project_dir, dest, envs=[env], rotate=rotate, view=view, atlas_dir=atlas_dir,
        projection=projection, solid_angle=solid_angle, progress=progress,
        read_ahead=read_ahead, model=model, fit_dir=fit_dir, convention=convention,
        engine=engine, store=store)
    return metrics[0], settings[0]


def expand_env_maps(envs) -> list:
    """The environment maps named by ``envs`` (a path or name, or a sequence of them): each
    file or shipped map's name as given, each folder replaced by its ``.exr``/``.hdr`` files
    sorted by name. A folder holding none is an :class:`InputError`."""
    items = [envs] if isinstance(envs, (str, os.PathLike)) else list(envs)
    out: list = []
    for e in items:
        p = Path(e)
        if p.is_dir():
            found = sorted((f for f in p.iterdir()
                            if f.is_file() and f.suffix.lower() in (".exr", ".hdr")),
                           key=lambda f: f.name)
            if not found:
                raise InputError(f"env: the folder {p} holds no .exr or .hdr environment map")
            out.extend(found)
        else:
            out.append(e)
    if not out:
        raise InputError("env: no environment map given")
    return out


def _check_map_stems(envs) -> None:
    """Each map's files are named by its stem (:func:`_relit_stem`): two maps of one stem would
    write the same files. Raise an :class:`InputError` naming both."""
    seen: dict[str, Any] = {}
    for e in envs:
        k = _safe_stem(Path(str(e)).stem)
        if k in seen:
            raise InputError(f"env: {e} and {seen[k]} have the same name {k!r} and would write "
                             "the same files; rename one, or relight them in separate runs "
                             "with different --out folders")
        seen[k] = e


def _relit_stem(env, env_map, rotate, view, solid_angle, lights) -> str:
    """``<map stem>[_projection][_convention]_rot<deg>_<view>[_rule]`` of a map's files."""
    rot = f"{float(rotate):g}".replace("-", "m")
    # the projection and the δA rule are part of the name when they are not the defaults (a
    # map read as a mirror ball, or an exact-solid-angle relight, does not overwrite the others)
    rule = ("" if solid_angle == "paper" or not hasattr(lights, "n_theta")  # a list: its own δA
            else f"_{_safe_stem(solid_angle)}")
    proj_tag = ("" if env_map.projection == "latlong" else f"_{env_map.projection}") + (
        "" if env_map.convention == "facegeo" else f"_{env_map.convention}")
    return f"{_safe_stem(Path(str(env)).stem)}{proj_tag}_rot{rot}_{_safe_stem(view)}{rule}"


def relight_maps_products(scan, project_dir: str | os.PathLike | None,
                          dest: str | os.PathLike, *, envs, rotate: float = 0.0,
                          view: str = "texture", atlas_dir: str | os.PathLike | None = None,
                          projection: str = "latlong", solid_angle: str = "paper",
                          progress: Callable[[str, int, int], None] | None = None,
                          read_ahead: int = 0, model: str = "measured",
                          fit_dir: str | os.PathLike | None = None,
                          convention: str = "facegeo", engine=None,
                          store: str | os.PathLike | None = None
                          ) -> tuple[list[dict], list[dict], dict]:
    """:func:`relight_products` under every map of ``envs`` (Eq. 4 per map), the field read once
    per batch of :data:`RELIGHT_MAPS_PER_TASK` maps.

    ``envs`` is a sequence of map files, shipped maps' names or folders
    (:func:`expand_env_maps`); every other argument applies to every map, as in
    :func:`relight_products`. Each map writes the files a run with it alone writes (named by its
    stem: two maps of one stem are an :class:`InputError`). The texture view relights a batch
    in the same tasks (:func:`relight_texture` with ``(B, L, 3)`` weights: one GEMM a chunk of
    rows); a camera view reads each OLAT frame lit by any map of the batch once and accumulates
    every map's image in float64 in light order (the same bytes as one map alone). A batch of
    one map is the one-map path; a texture batch of several agrees with it to float32 rounding
    (the GEMM's order of sums; ``docs/scale.md``). ``model="fitted"`` relights map by map.
    ``progress(stage, done, total)``: texture view per (camera, batch), camera view per frame
    read.

    Returns
    -------
    metrics : list of dict
        Per map, :func:`relight_products`'s metrics; with several maps also ``batch``
        (``index``, ``maps`` in it, ``batches``, its relight ``seconds``), and each map's
        ``seconds.relight`` is its batch's divided by the batch's maps.
    settings : list of dict
        Per map, the settings that determine its products.
    batch : dict
        ``maps``, ``batches``, ``maps_per_batch``, ``view``, ``seconds`` (``env``, ``weights``,
        ``relight``, ``write``, ``total``).
    """
    from facegeo.lighting import envmap as E

    t0 = time.perf_counter()
    check_choice(solid_angle, "solid_angle", ("paper", "exact"))
    check_choice(model, "model", ("measured", "fitted"))
    names = scan.camera_names
    texture = view == "texture"
    fitted_path = proj = texels_path = None
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
    envs = expand_env_maps(envs)
    _check_map_stems(envs)
    lights = scan.rig.lights
    jobs: list[dict] = []
    all_metrics: list[dict] = []
    all_settings: list[dict] = []
    t_start = t0
    for env in envs:  # the maps' weights (each map read, projected and dropped)
        env_map = resolve_env(env, projection, rotate_deg=rotate, convention=convention)
        settings = {"env": str(env), "rotate": float(rotate), "view": view,
                    "projection": env_map.projection, "solid_angle": solid_angle,
                    "model": model}
        if env_map.convention != "facegeo":  # only then: the default keeps the cache key
            settings["convention"] = env_map.convention
        t_env = time.perf_counter()
        integral = env_map.integral()
        if fitted_path is not None:
            m, s = _relight_fitted_products(scan, view, env_map, fitted_path, Path(dest), env,
                                            rotate, settings, t_start, integral)
            all_metrics.append(m)
            all_settings.append(s)
            t_start = time.perf_counter()
            continue
        w = E.light_weights(env_map, lights, solid_angle=solid_angle)  # a grid or a list
        t_w = time.perf_counter()
        jobs.append({"env": env, "settings": settings, "integral": integral, "w": w,
                     "stem": _relit_stem(env, env_map, rotate, view, solid_angle, lights),
                     "projection": env_map.projection, "convention": env_map.convention,
                     "seconds": {"env": t_env - t_start, "weights": t_w - t_env}})
        del env_map
        t_start = t_w
    batches = _map_batches(len(jobs))
    batch = {"maps": len(envs), "batches": len(batches) if jobs else len(envs),
             "maps_per_batch": RELIGHT_MAPS_PER_TASK, "view": view,
             "seconds": {"env": sum(j["seconds"]["env"] for j in jobs),
                         "weights": sum(j["seconds"]["weights"] for j in jobs),
                         "relight": 0.0, "write": 0.0}}
    if fitted_path is not None:
        batch["seconds"]["total"] = time.perf_counter() - t0
        return all_metrics, all_settings, batch
    # progress totals: texture per (camera, batch); camera view per frame read of each batch
    actives = [int(np.count_nonzero(np.any(np.stack([j["w"] for j in jobs[b0:b1]]) != 0,
                                           axis=(0, 2)))) for b0, b1 in batches]
    for i, (b0, b1) in enumerate(batches):
        group = jobs[b0:b1]
        t_b = time.perf_counter()
        if texture:
            tick = ((lambda k, n, i=i: progress("relight", i * n + k, n * len(batches)))
                    if progress else None)
            results, extras = _relight_texture_batch(group, lights, proj, texels_path, dest,
                                                     tick, engine, store, first_map=b0)
        else:
            done = sum(actives[:i])
            tick = ((lambda k, done=done: progress("relight", done + k + 1, sum(actives)))
                    if progress else None)
            from facegeo.lighting.relight import relight_scan_view_maps

            results = [(img, img.reshape(-1, 3)) for img in relight_scan_view_maps(
                scan, view, [j["w"] for j in group], progress=tick, read_ahead=read_ahead)]
            extras = [{} for _ in group]
        t_relit = time.perf_counter() - t_b
        batch["seconds"]["relight"] += t_relit
        eng = None
        if texture and engine is not None and engine.kind != "in-process":
            eng = engine.stage_metrics(
                "relight", [r.task for r in engine.records if r.stage == "relight"])
        for j, (img, mean_src), extra in zip(group, results, extras):
            t_m = time.perf_counter()
            m = _write_relit_map(scan, view, j, img, mean_src, extra, Path(dest), rotate,
                                 solid_angle, model, lights)
            t_write = time.perf_counter() - t_m
            batch["seconds"]["write"] += t_write
            m["seconds"] = {**j["seconds"], "relight": t_relit / len(group)}
            m["seconds"]["total"] = sum(m["seconds"].values()) + t_write
            if len(envs) > 1:
                m["batch"] = {"index": i, "maps": len(group), "batches": len(batches),
                              "seconds": t_relit}
            if eng is not None:
                m["engine"] = eng
            log.info("relit %s with %s (%d active lights) in %.2f s", view, j["env"],
                     m["active_lights"], m["seconds"]["total"])
            all_metrics.append(m)
            all_settings.append(j["settings"])
    batch["seconds"]["total"] = time.perf_counter() - t0
    return all_metrics, all_settings, batch


def _relight_texture_batch(group, lights, proj, texels_path, dest, tick, engine, store,
                           first_map: int = 0):
    """The texture view under a batch of maps (:func:`relight_texture`, one task set): per map
    ``(atlas image, measured texels' radiance)`` and its extra metrics (with the mask image)."""
    from facegeo.lighting import envmap as E
    from facegeo.surface._zarr_field import store_location
    from facegeo.surface.atlas import Texels

    # each light's own colour (a list's per-light intensities; a dark light weighs 0)
    W = np.stack([E.field_weights(j["w"], lights) for j in group])
    parts = (Path(dest) / ".parts" if store is None
             else str(store_location(store, "relight", f"parts-{os.getpid()}")))
    try:
        relit, _, cams = relight_texture(None, W if len(group) > 1 else W[0], progress=tick,
                                         project_dir=proj, atlas_dir=texels_path.parent,
                                         engine=engine, parts_dir=parts, first_map=first_map)
    finally:
        import shutil

        if store is None:
            shutil.rmtree(parts, ignore_errors=True)
    relit = relit.reshape(len(group), -1, 3)
    texels = Texels.load(texels_path)
    results, extras = [], []
    for texel_rgb in relit:
        measured = np.isfinite(texel_rgb).all(axis=1)
        img = texels.to_image(np.where(measured[:, None], texel_rgb, 0.0).astype(np.float32),
                              fill=0.0)
        results.append((img, texel_rgb[measured]))
        extras.append({"cameras": cams, "texels": int(measured.size),
                       "measured_texels": int(measured.sum()),
                       "mask": texels.to_image(measured.astype(np.uint8) * 255, fill=0)})
    return results, extras


def _write_relit_map(scan, view: str, job: dict, img, mean_src, extra: dict, dest: Path,
                     rotate, solid_angle: str, model: str, lights) -> dict:
    """Write one map's relit image (EXR, tone-mapped PNG; the texture's measured mask) and
    return its metrics (without ``seconds``)."""
    from facegeo.capture import imageio

    dest.mkdir(parents=True, exist_ok=True)
    stem = job["stem"]
    extra = dict(extra)
    exr = imageio.write_image(dest / f"{stem}.exr", img)  # atomic (temporary file + rename)
    png_img, exposure = tone_map(img)
    png = imageio.write_image(dest / f"{stem}.png", png_img)
    files = {"exr": str(exr), "png": str(png)}
    if "mask" in extra:
        files["measured"] = str(imageio.write_image(dest / f"{stem}_measured.png",
                                                    extra.pop("mask")))
    w, integral = job["w"], job["integral"]
    ratio = w.sum(0) / np.where(integral > 0, integral, 1)
    return {
        "scan": str(scan.root), "view": view, "env": str(job["env"]),
        "projection": job["projection"], "envmap_convention": job["convention"],
        "rotate_deg": float(rotate), "solid_angle": solid_angle,
        "n_lights": int(lights.n_lights),
        "active_lights": int(np.count_nonzero(np.any(w != 0, axis=1))),
        "energy_ratio": ratio.tolist(), "energy_note": energy_note(ratio, lights.n_lights),
        "model": model,
        "mean_radiance": (mean_src.mean(0) if len(mean_src) else np.zeros(3)).tolist(),
        "tone_map_exposure": exposure, "files": files, **extra,
    }


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
    return run_relight_maps(scan_dir, [env_path], rotate_deg=rotate_deg, view=view,
                            out_dir=out_dir, projection=projection, solid_angle=solid_angle,
                            field_dir=field_dir, progress=progress, read_ahead=read_ahead,
                            model=model, convention=convention, engine=engine,
                            store=store)["relit"][0]


def run_relight_maps(scan_dir: str | os.PathLike, envs, *, rotate_deg: float = 0.0,
                     view: str | None = None, out_dir: str | os.PathLike | None = None,
                     projection: str = "latlong", solid_angle: str = "paper",
                     field_dir: str | os.PathLike | None = None,
                     progress: Callable[[str, int, int], None] | None = None,
                     read_ahead: int = 0, model: str = "measured", convention: str = "facegeo",
                     engine=None, store: str | os.PathLike | None = None) -> dict:
    """:func:`run_relight` under every map of ``envs`` (files, shipped maps' names, folders of
    ``.exr``/``.hdr`` maps: :func:`expand_env_maps`), the field read once per batch of
    :data:`RELIGHT_MAPS_PER_TASK` maps (:func:`relight_maps_products`). Every map writes the
    files and the metrics JSON a run with it alone writes; the other arguments apply to every
    map.

    Returns
    -------
    dict
        ``relit``: each map's metrics (:func:`run_relight`'s, in the order of the maps);
        ``maps``, ``batches``, ``maps_per_batch``, ``view``, ``seconds`` of the whole run.
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
    metrics, _, batch = relight_maps_products(
        scan, fdir / "project", out, envs=envs, rotate=rotate_deg, view=view,
        atlas_dir=fdir / "atlas", projection=projection, solid_angle=solid_angle,
        progress=progress, read_ahead=read_ahead, model=model, fit_dir=fdir / "fit",
        convention=convention, engine=engine, store=store)
    for m in metrics:
        stem = Path(m["files"]["exr"]).stem
        atomic_write_text(out / f"{stem}.json", json.dumps(m, indent=2))
    return {**batch, "relit": metrics}
