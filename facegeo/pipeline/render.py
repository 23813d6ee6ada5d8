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
filled from the nearest measured pixel within ``fill_px``, then with ``infer``, the default,
from texels inferred in texture space — :func:`facegeo.render.novel.infer_texel_colours` —,
else black, in every render); ``inferred_pixel_fraction`` (surface pixels holding an inferred
value), ``inferred_texel_fraction`` (atlas texels no source camera measured),
``black_surface_pixels`` and ``surface_pixel_fraction`` (the image's share of surface pixels;
under :data:`CAMERA_HIT_MIN` a warning says the camera hardly looks at the surface);
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

import dataclasses
import hashlib
import json
import logging
import math
import os
import re
import time
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.checks import check_positive_int, fmt_value
from facegeo.errors import InputError
from facegeo.fsutil import file_state

log = logging.getLogger(__name__)

__all__ = ["BUILTIN_ENVS", "CAMERA_HIT_MIN", "SHRINKAGE_CHOICES", "builtin_env",
           "check_render_args", "reference_views", "render_one", "render_products",
           "run_render"]

BUILTIN_ENVS = ("uniform", "axis_lobes", "sky", "studio")
#: The environment of the ``render`` stage of ``facegeo reconstruct``.
RENDER_DEFAULT_ENV = "sky"
#: Values of ``shrinkage`` besides a number in [0, 1] (:func:`run_render`).
SHRINKAGE_CHOICES = ("cross-validated", "none")
SHRINKAGE_DEFAULT = "cross-validated"
#: Where a view rendered on its own (``facegeo render``) keeps the relit source images of the
#: image-space detail, under its folder (``out/views/``), and how many environments' worth.
SOURCE_IMAGES_DIR = ".source_images"
SOURCE_IMAGES_KEEP = 4
_ENV_HEIGHT = 64
#: A view whose pixels hit the atlas mesh less than this share of the image is logged as a
#: warning (a camera file in another world frame, or aimed away from the head).
CAMERA_HIT_MIN = 0.05


def builtin_env(name: str):
    """A built-in :class:`facegeo.lighting.envmap.EnvironmentMap` (see module docstring)."""
    from facegeo.lighting import envmap as E

    if name == "uniform":
        return E.analytic_map(lambda v: np.ones(v.shape[:-1] + (3,)), _ENV_HEIGHT)
    if name == "axis_lobes":
        return E.axis_lobe_map(_ENV_HEIGHT)
    if name in E.SHIPPED_MAPS:  # the procedural maps shipped with facegeo (sky, studio)
        return E.shipped_map(name)
    raise InputError(f"env: unknown built-in environment {fmt_value(name)}; built-ins are "
                     f"{', '.join(BUILTIN_ENVS)} (or give an .exr/.hdr file)")


def _load_env(env, projection: str, rotate_deg: float, convention: str = "facegeo"):
    from facegeo.lighting import envmap as E

    if isinstance(env, E.EnvironmentMap):
        m = env
    elif isinstance(env, str) and env in BUILTIN_ENVS:
        if E.canonical_projection(projection) != "latlong" or convention != "facegeo":
            raise InputError(f"env: the built-in environment {fmt_value(env)} has no file; "
                             f"--projection and --envmap-convention apply to map files")
        m = builtin_env(env)
    else:
        path = Path(env)
        if not path.is_file():
            raise InputError(f"env: {path} is not a file and not a built-in environment "
                             f"({', '.join(BUILTIN_ENVS)})")
        return E.read_envmap(path, projection, rotate_deg=rotate_deg, convention=convention)
    return m.rotated(math.radians(rotate_deg)) if rotate_deg else m


def check_render_args(scan, *, camera_spec, env="axis_lobes", rotate_deg: float = 0.0,
                      projection: str = "latlong", shrinkage: str | float = SHRINKAGE_DEFAULT,
                      light_step: int = 1, resynthesis: bool | str = True, rig=None,
                      convention: str = "facegeo") -> None:
    """Check a render request against the scan before any stage runs; raise InputError.

    :func:`render_one` checks the same (with the same messages) once its inputs are there, but
    ``facegeo render`` first builds atlas, project and fit (minutes on the larger presets): the
    CLI calls this first. Checked: the camera spec against the cameras a view may name (the
    rig's — every rig a scan's stages use has the scan's cameras — and the generator's novel
    ones), the environment (a built-in name, or a file that reads as a map), the shrinkage and,
    with resynthesis, the light step against the light-stage grid."""
    from facegeo.appearance._skin_resynth import check_light_step
    from facegeo.pipeline.fit import _camera_table
    from facegeo.render import light_set, parse_camera_spec

    rig = scan.rig if rig is None else rig
    parse_camera_spec(camera_spec, _camera_table(scan, rig))
    _load_env(env, projection, rotate_deg, convention)
    _check_shrinkage(shrinkage)
    if resynthesis:
        check_light_step(light_step, light_set(rig.lights))


def _check_shrinkage(shrinkage):
    """``"cross-validated"``, ``"none"`` (→ None) or a float λ in [0, 1]."""
    if isinstance(shrinkage, str):
        if shrinkage == "none":
            return None
        if shrinkage in SHRINKAGE_CHOICES:
            return shrinkage
        try:
            shrinkage = float(shrinkage)
        except ValueError:
            raise InputError(f"shrinkage: expected {' or '.join(SHRINKAGE_CHOICES)} or a number "
                             f"in [0, 1], got {fmt_value(shrinkage)}") from None
    if shrinkage is None:
        return None
    lam = float(shrinkage)
    if not (0.0 <= lam <= 1.0):
        raise InputError(f"shrinkage: a factor must lie in [0, 1] (1 = the paper's resynthesis, "
                         f"0 = the naive baseline), got {fmt_value(shrinkage)}")
    return lam


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]+", "_", text).strip("_") or "view"


def run_render(scan_dir, out_dir=None, *, camera_spec, env="axis_lobes", rotate_deg: float = 0.0,
               projection: str = "latlong", supersample: int = 1, resynthesis: bool = True,
               baseline: bool = True, reference: bool = True, name: str | None = None,
               blend_power: float | None = None, rig: str | None = None,
               solid_angle: str = "paper", fill_px: float = 2.0,
               shrinkage: str | float = SHRINKAGE_DEFAULT, light_step: int = 1,
               shadow_taps: bool = True, image_detail: bool = True, progress=None,
               convention: str = "facegeo", infer: bool = True) -> dict:
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
    fill_px : float, pixels — hole filling of unmeasured hit samples from the nearest measured
        pixel within this distance (:func:`facegeo.render.render_view`; 0: off); filled
        pixels count in ``psnr_db`` / ``rel_rmse`` but not in the ``*_covered`` figures
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
        measured take values inferred in texture space (pull–push of colour over Lambertian
        shading, :func:`facegeo.render.render_view` ``infer``), marked in
        ``<name>_inferred.png``; covered pixels unchanged bit for bit. False: black (the paper)
    progress : callable(stage, done, total), optional — called as stage ``"render"`` after
        each step (rays — with image detail, relighting the source captures too, ≈ 40 s at the
        paper preset the first time under an environment —, render, naive baseline)

    Returns
    -------
    dict — the view's metrics (files, timings; with a reference ``psnr_db`` …)
    """
    from facegeo.evaluate.views import evaluate_view, has_view_reference
    from facegeo.pipeline.project import _scan

    scan = _scan(scan_dir)
    out = Path(out_dir) if out_dir is not None else scan.out_dir
    metrics = render_one(scan, out, out / "views", camera_spec=camera_spec, env=env,
                         rotate_deg=rotate_deg, projection=projection, supersample=supersample,
                         resynthesis=resynthesis, baseline=baseline, reference=reference,
                         name=name, blend_power=blend_power, rig=rig, solid_angle=solid_angle,
                         fill_px=fill_px, shrinkage=shrinkage, light_step=light_step,
                         shadow_taps=shadow_taps, image_detail=image_detail,
                         progress=progress, convention=convention, infer=infer)
    if reference and has_view_reference(scan):
        figures = evaluate_view(scan, out, out / "views", metrics["name"], out / "views")
        metrics["files"].update(figures.pop("files"))
        metrics.update(figures)
    _merge_metrics(out, metrics["name"], metrics)
    return metrics


def render_one(scan, out: Path, dest: Path, *, camera_spec, env="axis_lobes",
               rotate_deg: float = 0.0, projection: str = "latlong", supersample: int = 1,
               resynthesis: bool | str = True, baseline: bool = True, reference: bool = True,
               name: str | None = None, blend_power: float | None = None,
               rig: str | None = None, solid_angle: str = "paper", fill_px: float = 2.0,
               shrinkage: str | float = SHRINKAGE_DEFAULT, light_step: int = 1,
               shadow_taps: bool = True, image_detail: bool = True, progress=None,
               cache: dict | None = None, convention: str = "facegeo",
               infer: bool = True) -> dict:
    """Render one view of ``scan`` from the products in ``out`` (``atlas/``, ``project/``,
    ``fit/``) into the folder ``dest``; returns the view's metrics (:func:`run_render` without
    the merge into ``out/metrics.json``; ``metrics["name"]`` is the files' stem).

    With full resynthesis the shrunk render, the naive baseline (λ = 0) and the paper's λ = 1
    come from one read of the fields and one resynthesis (``render_view(shrinkage_set=)``, each
    bit for bit its own render). ``cache``: a dict shared by the views of one stage for what
    does not depend on the view: the cross-validated λ (once per environment weights and light
    step), the check that the projection indexes this atlas (``check_projection_atlas``
    hashes ``texels.npz``, ≈ 10 MB on the small preset: once per stage, keyed by the files'
    size and modification time, not once per view) and the atlas, texel table, ray scene and
    source cameras (:func:`_view_inputs`: read once, the fields' memory maps reopened per
    view).

    ``reference``: with a reference to compare with (synthetic scans), the paper's λ = 1
    render is made beside a shrunk one, for :mod:`facegeo.evaluate.views`; the view never
    reads the reference itself.

    With ``image_detail`` the source cameras' relit captures (:func:`_source_images`, once per
    environment weights in ``cache``) join every render of the view (``render_view(detail=)``)."""
    from facegeo.capture import imageio
    from facegeo.fsutil import atomic_write_text
    from facegeo.lighting import envmap as E
    from facegeo.pipeline.fit import _camera_table
    from facegeo.evaluate.views import has_view_reference
    from facegeo.pipeline.project import check_projection_atlas, stage_rig
    from facegeo.pipeline.relight import tone_map
    from facegeo.render import (
        cross_validated_shrinkage,
        light_set,
        parse_camera_spec,
        render_view,
        trace_view,
    )
    from facegeo.render.novel import BLEND_POWER

    t_start = time.perf_counter()
    out, dest = Path(out), Path(dest)
    shrink_mode = _check_shrinkage(shrinkage)
    supersample = check_positive_int(supersample, "supersample")
    for need in ("atlas/atlas.npz", "atlas/texels.npz"):
        if not (out / need).is_file():
            raise InputError(f"render: {out / need} is missing; run 'facegeo reconstruct SCAN' first")
    if resynthesis and not (out / "fit").is_dir():
        raise InputError(f"render: {out / 'fit'} is missing; run 'facegeo fit SCAN' first (or "
                         "render the naive baseline with resynthesis=False)")
    try:
        project_settings = json.loads((out / "project" / "stage.json").read_text())["settings"]
    except (OSError, ValueError, KeyError, TypeError):
        project_settings = {}
    if not isinstance(project_settings, dict):
        project_settings = {}
    if rig is None:
        rig = project_settings.get("rig")
    the_rig, rig_used = stage_rig(scan, rig)
    camera = parse_camera_spec(camera_spec, _camera_table(scan, the_rig))
    environment = _load_env(env, projection, rotate_deg, convention)
    stage = the_rig.lights
    w = E.light_weights(environment, stage, solid_angle=solid_angle)  # a grid or a light list
    w = E.field_weights(w, stage)  # image in the environment's units (field = intensity × R)
    # the skin model's light set only where it resynthesises (a naive render needs none)
    lights = light_set(stage) if resynthesis else None
    atlas, texels, scene, sources = _view_inputs(out, bool(resynthesis), cache,
                                                 check_projection_atlas)
    t_load = time.perf_counter()
    compare = bool(reference and has_view_reference(scan))
    factors, shrink_stats = None, None
    if resynthesis is True and shrink_mode == "cross-validated":
        key = (hashlib.sha1(np.ascontiguousarray(w, np.float64).tobytes()).hexdigest(),
               int(light_step))
        if cache is not None and key in cache:
            factors, shrink_stats = cache[key]
        else:
            factors, shrink_stats = cross_validated_shrinkage(sources, w, lights,
                                                              light_step=light_step)
            if cache is not None:
                cache[key] = (factors, shrink_stats)
    elif resynthesis is True and isinstance(shrink_mode, float):
        factors = {src.name: shrink_mode for src in sources}
    shrunk = factors is not None and any(f != 1.0 for f in factors.values())
    paper_too = bool(shrunk and compare)
    steps = 2 + int(bool(baseline and resynthesis)) + int(paper_too)

    def tick(k: int) -> None:
        if progress:
            progress("render", k, steps)

    samples = trace_view(camera, scene, atlas, texels, supersample=supersample)
    light_dirs = np.asarray(stage.directions, np.float64) if infer else None
    hit_fraction = float(samples.mask.mean())
    if hit_fraction < CAMERA_HIT_MIN:
        log.warning("render: camera %s (%s) hardly looks at the reconstructed surface: %.2f %% "
                    "of its pixels hit the mesh (under %g %%); a camera file must be in the "
                    "rig's world frame (%s rig; docs/render.md)",
                    camera_spec if isinstance(camera_spec, (str, Path)) else "given",
                    camera.name, 100 * hit_fraction, 100 * CAMERA_HIT_MIN, rig_used)
    shadows = _view_shadows(atlas, scene, texels, stage, cache) if shadow_taps else None
    # the source images' visibility weights as the projection's (its stage's settings)
    vis_kw = {k: project_settings[k] for k in ("min_cos", "feather_px", "depth_jump")
              if k in project_settings}
    if image_detail:
        from facegeo.render.novel import key_lights

        keys = () if shadows is None else tuple(int(k) for k in key_lights(
            w, shadows.key_share, shadows.max_lights))
        # a stage keeps them in memory for its views; a view rendered on its own keeps them
        # on disk for the next view under the same environment (at the paper preset they
        # take ≈ 40 s: 2 × 2048 frames read)
        detail, t_sources = _source_images(scan, the_rig, rig_used, sources, w, keys, cache,
                                           None if cache is not None
                                           else dest / SOURCE_IMAGES_DIR)
    else:
        detail, t_sources = None, None
    tick(1)
    bp = BLEND_POWER if blend_power is None else float(blend_power)
    naive = paper = None
    # the paper's §4.3 as written (λ = 1), for the metrics, shares the pass only at the same
    # light step (the paper's render always evaluates every light)
    share_paper = paper_too and light_step == 1
    shared = resynthesis is True and (baseline or share_paper)
    if shared:
        sets = [factors] + ([{src.name: 0.0 for src in sources}] if baseline else [])
        sets += [None] if share_paper else []
        got = render_view(camera, scene, atlas, texels, sources, w, lights, blend_power=bp,
                          samples=samples, fill_px=fill_px, light_step=light_step,
                          shrinkage_set=sets, shadows=shadows, detail=detail,
                          detail_visibility=vis_kw, infer=infer, light_directions=light_dirs)
        res = got[0]
        naive = got[1] if baseline else None
        paper = got[-1] if share_paper else None
        tick(2 + int(naive is not None) + int(paper is not None))
    else:
        res = render_view(camera, scene, atlas, texels, sources, w, lights,
                          resynthesis=resynthesis, blend_power=bp, samples=samples,
                          fill_px=fill_px, shrinkage=factors, shadows=shadows,
                          light_step=light_step if resynthesis is True else 1, detail=detail,
                          detail_visibility=vis_kw, infer=infer, light_directions=light_dirs)
        tick(2)
        if baseline and resynthesis:
            naive = render_view(camera, scene, atlas, texels, sources, w, lights,
                                resynthesis=False, blend_power=bp, samples=samples,
                                fill_px=fill_px, shadows=shadows, detail=detail,
                                detail_visibility=vis_kw, infer=infer, light_directions=light_dirs)
            tick(3)
    if paper_too and paper is None:
        paper = render_view(camera, scene, atlas, texels, sources, w, lights, resynthesis=True,
                            blend_power=bp, samples=samples, fill_px=fill_px, shadows=shadows,
                            detail=detail, detail_visibility=vis_kw, infer=infer,
                            light_directions=light_dirs)
        tick(3 + int(naive is not None))
    # a map file read with another projection or convention names its own files (as relight's)
    from facegeo.lighting.envmap import canonical_projection

    proj = canonical_projection(projection)
    env_tag = env if isinstance(env, str) and env in BUILTIN_ENVS else (
        (Path(env).stem if isinstance(env, (str, Path)) else "env")
        + ("" if proj == "latlong" else f"_{proj}")
        + ("" if convention == "facegeo" else f"_{convention}"))
    stem = _safe(name or f"{camera.name}_{env_tag}")
    dest.mkdir(parents=True, exist_ok=True)
    files = {"exr": imageio.write_image(dest / f"{stem}.exr", res.image).name}
    png, exposure = tone_map(res.image)
    files["png"] = imageio.write_image(dest / f"{stem}.png", png).name
    if naive is not None:
        imageio.write_image(dest / f"{stem}_naive.exr", naive.image)
        files["naive_png"] = imageio.write_image(
            dest / f"{stem}_naive.png", _expose(naive.image, exposure)).name
    metrics: dict[str, Any] = {
        "camera": camera.name, "camera_spec": camera_spec if isinstance(camera_spec, str)
        else camera.to_dict(), "env": str(env) if not isinstance(env, E.EnvironmentMap)
        else "EnvironmentMap", "rotate_deg": float(rotate_deg), "supersample": int(supersample),
        "resynthesis": resynthesis, "blend_power": bp, "fill_px": float(fill_px),
        "shadow_taps": bool(shadow_taps), "image_detail": bool(image_detail),
        "detail_fraction": round(res.stats["detail_pixels"] / max(int(res.covered.sum()), 1), 6)
        if detail is not None else None,
        # relighting the source cameras' captures for the detail (0: another view's reused)
        "seconds_source_images": t_sources,
        "shrinkage": shrink_mode, "shrinkage_factors": factors,
        "light_step": int(light_step) if resynthesis is True else 1,
        "shrinkage_cross_validation": shrink_stats,
        "rig": rig_used,
        "size": [camera.width, camera.height], "active_lights": res.stats["active_lights"],
        "stats": res.stats, "seconds_render": res.stats["seconds"],
        # one pass rendered the naive baseline (and the paper's λ = 1) beside the view: its
        # time is in seconds_render, and there is no separate naive time
        "shared_pass": bool(shared),
        "seconds_naive": naive.stats["seconds"] if naive is not None and not shared else None,
        "seconds_load": round(t_load - t_start, 4),
        "coverage": round(float(res.covered.sum() / max(res.mask.sum(), 1)), 6),
        "surface_pixel_fraction": round(hit_fraction, 6),
        # what no camera saw (infer): the atlas's texels no source camera measured, and the
        # surface pixels of the view holding an inferred sample (<stem>_inferred.png)
        "infer": bool(infer),
        "inferred_texel_fraction": _unmeasured_texel_fraction(texels, sources),
        "inferred_pixel_fraction": round(float(
            res.inferred.sum() / max(res.mask.sum(), 1)), 6),
        "black_surface_pixels": int((res.mask & ~(res.image > 0).any(axis=2)).sum()),
    }
    # what the evaluation reads (facegeo.evaluate.views): the camera, the weights, the
    # covered pixels and the renders beside the main one
    atomic_write_text(dest / f"{stem}_camera.json", json.dumps(camera.to_dict(), indent=2))
    np.save(dest / f"{stem}_weights.npy", np.asarray(w, np.float64))
    imageio.write_image(dest / f"{stem}_covered.png",
                        np.where(res.covered, 255, 0).astype(np.uint8))
    imageio.write_image(dest / f"{stem}_inferred.png",
                        np.where(res.inferred, 255, 0).astype(np.uint8))
    if detail is not None:  # the texture-space renders (the paper's render path)
        imageio.write_image(dest / f"{stem}_texture.exr", res.texture)
        if naive is not None:
            imageio.write_image(dest / f"{stem}_naive_texture.exr", naive.texture)
    if paper is not None:
        imageio.write_image(dest / f"{stem}_paper.exr", paper.image)
    metrics["exposure"] = float(exposure)
    metrics["files"] = files
    metrics["name"] = stem
    metrics["seconds"] = round(time.perf_counter() - t_start, 4)
    atomic_write_text(dest / f"{stem}.json", json.dumps(metrics, indent=2, allow_nan=False))
    log.info("rendered %s (%s) in %.2f s", stem, camera.name, metrics["seconds"])
    return metrics


def _unmeasured_texel_fraction(texels, sources) -> float:
    """The share of the atlas's texels that no source camera measured (a row of no projected
    field): what a render with ``infer`` covers by inference."""
    seen = np.zeros(len(texels), bool)
    for src in sources:
        seen[np.asarray(src.texel_index, np.int64)] = True
    return round(float(1.0 - seen.mean()), 6) if seen.size else 0.0


def _source_images(scan, the_rig, rig_used: str, sources, w, keys: tuple,
                   cache: dict | None, disk: Path | None = None) -> tuple:
    """The source cameras' OLAT captures relit with the render's weights ``w``
    (:class:`facegeo.render.detail.SourceImage`, the rig's cameras: the ones the projection
    used) with the frames of the key lights ``keys`` (shadow-consistent taps), and the seconds
    this call spent building them (0: reused).

    Kept once per weights, key lights, rig and cameras in ``cache`` (a stage's views) and, with
    ``disk``, in a file there named by those, facegeo's code fingerprint, the OLAT response
    curve and the state (path, size, modification time) of the scan manifest and of every frame
    the relighting reads: read back instead of relit while none of them changed (a file that
    does not read is removed and the images relit), written atomically, the
    :data:`SOURCE_IMAGES_KEEP` most recently used kept; a failed write only logs a warning."""
    from facegeo.fsutil import READ_AHEAD_WORKERS, atomic_path
    from facegeo.lighting.relight import relight_scan_view
    from facegeo.render.detail import SourceImage

    names = tuple(src.name for src in sources)
    key = ("source_images", hashlib.sha1(np.ascontiguousarray(w, np.float64).tobytes())
           .hexdigest(), rig_used, names, keys)
    if cache is not None and key in cache:
        return cache[key], 0.0
    path = None
    if disk is not None:
        lit = [int(k) for k in np.flatnonzero(np.any(np.asarray(w) != 0, axis=1))]
        files = [f for f in [getattr(scan, "manifest_path", None)] if f is not None]
        files += [scan.olat_path(c, k) for c in names for k in sorted(set(lit) | set(keys))]
        state = [(str(f), file_state(f)) for f in files]  # a missing frame: None, and the
        try:                                                 # relighting below names it
            resp = scan.response("olat")
            state.append((resp.kind, resp.gamma, resp.file, None if resp.table is None else
                          hashlib.sha1(np.ascontiguousarray(resp.table).tobytes()).hexdigest()))
        except (OSError, KeyError, ValueError):
            state = None  # the response does not read: no cache, the relighting names it
        if state is not None:
            from facegeo.pipeline.cache import code_fingerprint

            name = hashlib.sha1(repr((key, state, code_fingerprint())).encode()).hexdigest()[:24]
            path = disk / f"{name}.npz"
    if path is not None and path.is_file():
        try:
            with np.load(path) as z:
                images = [SourceImage(the_rig.camera(c), z[f"{c}/image"], z[f"{c}/valid"],
                                      {k: (z[f"{c}/{k}/frame"], z[f"{c}/{k}/valid"])
                                       for k in keys})
                          for c in names]
            os.utime(path)  # most recently used: kept longest
            if cache is not None:
                cache[key] = images
            return images, 0.0
        except Exception as exc:  # truncated or foreign: a cache, not an input — rebuild it
            log.warning("%s: unreadable (%s); relighting the source images again", path, exc)
            path.unlink(missing_ok=True)
    t0 = time.perf_counter()
    images = []
    for src in sources:
        img, valid = relight_scan_view(scan, src.name, w, return_mask=True,
                                       read_ahead=READ_AHEAD_WORKERS)
        frames = {k: scan.olat_frame(src.name, k, return_mask=True, black_clipped="dark")
                  for k in keys}
        images.append(SourceImage(the_rig.camera(src.name), img, valid, frames))
    if cache is not None:
        cache[key] = images
    if path is not None:
        arrays = {}
        for im in images:
            c = im.camera.name
            arrays[f"{c}/image"], arrays[f"{c}/valid"] = im.image, im.valid
            for k, (frame, ok) in im.key_frames.items():
                arrays[f"{c}/{k}/frame"], arrays[f"{c}/{k}/valid"] = frame, ok
        try:
            with atomic_path(path) as tmp:
                np.savez(tmp, **arrays)
            _prune(disk, SOURCE_IMAGES_KEEP)
        except OSError as exc:  # the render does not need the cache
            log.warning("%s: could not keep the relit source images (%s)", disk, exc)
    return images, round(time.perf_counter() - t0, 4)


def _prune(folder: Path, keep: int) -> None:
    """Remove all but the ``keep`` most recently modified ``*.npz`` files of ``folder``
    (hidden ones — another process's file being written — left alone)."""
    dated = []
    for f in folder.glob("*.npz"):
        if f.name.startswith("."):
            continue
        try:
            dated.append((f.stat().st_mtime_ns, f))
        except FileNotFoundError:  # removed meanwhile by another render
            continue
    for _, f in sorted(dated)[:-keep]:
        f.unlink(missing_ok=True)


def _view_shadows(atlas, scene, texels, stage, cache: dict | None):
    """:func:`facegeo.render.render_shadows` of the atlas under ``stage``, once a stage (kept in
    ``cache`` beside the view inputs it was built from)."""
    from facegeo.render import render_shadows
    from facegeo.surface.shadows import light_positions

    positions, directions = light_positions(stage)
    # the cached value holds the scene (its rays), so its id names no other live scene
    key = ("view_shadows", id(scene), hashlib.sha1(
        np.ascontiguousarray(directions).tobytes()
        + (b"" if positions is None else np.ascontiguousarray(positions).tobytes())).hexdigest())
    if cache is not None and cache.get("view_shadows", (None,))[0] == key:
        return cache["view_shadows"][1]
    shadows = render_shadows(atlas, scene, texels, stage)
    if cache is not None:
        cache["view_shadows"] = (key, shadows)
    return shadows



def _inputs_state(out: Path, with_fit: bool) -> tuple:
    """(path, size, mtime_ns) of every file :func:`_view_inputs` reads: the atlas and texel
    table, the projected fields' folders and, with the fits, the fit folders."""
    files = [out / "atlas" / "atlas.npz", out / "atlas" / "texels.npz"]
    for part in ("project", "fit") if with_fit else ("project",):
        files += sorted(p for p in (out / part).glob("*/*") if p.is_file())
    return tuple((str(f), file_state(f)) for f in files)


def _fresh_map(a):
    """A new read-only memory map of the file behind ``a`` (``a`` itself if it is not one)."""
    path = getattr(a, "filename", None)
    return np.load(path, mmap_mode="r") if path else a


def _view_inputs(out: Path, with_fit: bool, cache: dict | None, check) -> tuple:
    """``(atlas, texels, scene, sources)`` of a view: ``out/atlas/atlas.npz``, its texel table,
    the atlas mesh's ray scene and :func:`facegeo.render.load_sources` of ``out/project`` (and
    ``out/fit`` when ``with_fit``), after ``check`` (:func:`_check_projection_atlas_once`).

    With a ``cache`` (one render stage's views) they are read once and shared by the views: one
    slot, replaced when a view asks for other inputs or a file changed (size, mtime_ns), so the
    stage holds one set, as one view did. The fields ``R`` and the fits' ``D`` are memory maps,
    opened afresh per view: the pages a view reads leave the resident set with its maps, as
    they did when every view loaded its own."""
    from facegeo.render import atlas_scene, load_sources
    from facegeo.surface.atlas import Atlas, Texels

    key = ("view_inputs", str(out), with_fit, _inputs_state(out, with_fit)) \
        if cache is not None else None
    slot = cache.get("view_inputs") if cache is not None else None
    if slot is not None and slot[0] == key:
        atlas, texels, scene, sources = slot[1]
        _check_projection_atlas_once(check, out, cache)
    else:
        if cache is not None:
            cache.pop("view_inputs", None)  # one set at a time
        atlas = Atlas.load(out / "atlas" / "atlas.npz")
        texels = Texels.load(out / "atlas" / "texels.npz")
        _check_projection_atlas_once(check, out, cache)
        sources = load_sources(out / "project", (out / "fit") if with_fit else None)
        scene = atlas_scene(atlas)
        if cache is None:
            return atlas, texels, scene, sources
        cache["view_inputs"] = (key, (atlas, texels, scene, sources))
    return atlas, texels, scene, [dataclasses.replace(
        src, field=_fresh_map(src.field),
        fit=None if src.fit is None else dataclasses.replace(src.fit, D=_fresh_map(src.fit.D)))
        for src in sources]


def _check_projection_atlas_once(check, out: Path, cache: dict | None) -> None:
    """``check(out/project, out/atlas/texels.npz)`` (``check_projection_atlas``: a SHA-256 of
    the texel table), skipped when ``cache`` holds a pass for the same two files at the same
    (size, mtime_ns): the views of one render stage share the atlas and the projection."""
    from facegeo.pipeline.project import ATLAS_FINGERPRINT

    texels, fingerprint = out / "atlas" / "texels.npz", out / "project" / ATLAS_FINGERPRINT
    key = ("projection_atlas_checked", str(texels), file_state(texels),
           file_state(fingerprint))
    if cache is not None and key in cache:
        return
    check(out / "project", texels)
    if cache is not None:
        cache[key] = True


def render_products(scan, out: Path, dest: Path, *, views, env=RENDER_DEFAULT_ENV,
                    progress=None, **settings) -> dict:
    """The ``render`` stage of ``facegeo reconstruct``: every view in ``views`` under ``env``
    into ``dest`` (:func:`render_one`); returns the stage's metrics.

    Besides ``views``, every scan camera with a reference image ``[reference]
    images.<camera>.<env>`` (a witness camera; :func:`reference_views`) is rendered under that
    environment, so the evaluation compares it
    (:func:`facegeo.evaluate.views.evaluate_view_against_image`).

    Metrics: ``views`` (per view, as :func:`render_one`), ``env`` and ``seconds`` (the views'
    sum). The figures against references (``psnr_db_min`` …, the novel-view goal of issue 14:
    resynthesis at least 3 dB better than the naive baseline) are the ``evaluate`` stage's
    (:mod:`facegeo.evaluate.views`).
    """
    per_view = {}
    # the cross-validated λ, the atlas check and the relit source images, once a stage
    cache: dict = {}
    jobs = [(spec, env) for spec in views] + reference_views(scan)
    for k, (spec, view_env) in enumerate(jobs):
        tick = (lambda stage, d, n, k=k: progress("render", k * n + d, len(jobs) * n)) \
            if progress else None
        m = render_one(scan, out, dest, camera_spec=spec, env=view_env, progress=tick,
                       cache=cache, **settings)
        per_view[m["name"]] = {key: v for key, v in m.items() if key != "stats"}
    return {"views": per_view, "env": str(env),
            "seconds": round(sum(v.get("seconds", 0.0) for v in per_view.values()), 4)}


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


def _expose(img, exposure: float) -> np.ndarray:
    """8-bit sRGB with a given exposure (so a render and its reference share one)."""
    from facegeo.capture.response import encode

    return encode(np.clip(img * np.float32(exposure), 0.0, 1.0), "srgb", np.uint8)


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
