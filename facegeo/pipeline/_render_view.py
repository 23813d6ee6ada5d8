"""One novel view of a reconstructed scan (private to :mod:`facegeo.pipeline.render`).

:func:`render_one` renders a view from the products of ``out/`` (atlas, projection, fit) into a
folder, with what it shares across the views of a stage (the cross-validated λ, the atlas
check, the view inputs, the relit source images: ``cache``); the environments it accepts
(:func:`builtin_env`, :func:`_load_env`) and the argument checks of ``facegeo render``
(:func:`check_render_args`). :mod:`facegeo.pipeline.render` is the stage around it — the
standalone runner, the ``render`` stage of ``facegeo reconstruct`` and its engine tasks —
and re-exports the public names; its docstring lists the files a view writes.
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

log = logging.getLogger("facegeo.pipeline.render")


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


#: ``fill_px`` of a render that leaves what no camera saw black (``infer=False``): the
#: silhouette ring the projection's ``min_cos`` leaves out takes the nearest covered pixel's
#: colour within this distance (display hole filling).
FILL_PX_NO_INFER = 2.0


def default_fill_px(infer: bool) -> float:
    """The render's default ``fill_px``: 0 with ``infer`` — the texels of the silhouette ring
    are inferred over the surface like every unmeasured texel (continuous; copying one covered
    sample's colour across 2 px made blotches where a few measured samples sat at the grazing
    edge: tiny preset, true mesh, whole-head gain −60° / −30° / +30° / +60° / witness +6.80 /
    +2.06 / +1.47 / +2.06 / +2.24 dB with the copy, +8.04 / +3.67 / +1.80 / +2.56 / +3.57
    without; docs/render.md) — and :data:`FILL_PX_NO_INFER` without."""
    return 0.0 if infer else FILL_PX_NO_INFER


def render_one(scan, out: Path, dest: Path, *, camera_spec, env="axis_lobes",
               rotate_deg: float = 0.0, projection: str = "latlong", supersample: int = 1,
               resynthesis: bool | str = True, baseline: bool = True, reference: bool = True,
               name: str | None = None, blend_power: float | None = None,
               rig: str | None = None, solid_angle: str = "paper",
               fill_px: float | None = None,
               shrinkage: str | float = SHRINKAGE_DEFAULT, light_step: int = 1,
               shadow_taps: bool = True, image_detail: bool = True, progress=None,
               cache: dict | None = None, convention: str = "facegeo",
               infer: bool = True, source_images_dir=None) -> dict:
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
    view), and the rig and the cameras a view may name (:func:`_render_rig`,
    :func:`_view_cameras`: a view task seeded with them reads no rig or camera file).

    ``reference``: with a reference to compare with (synthetic scans), the paper's λ = 1
    render is made beside a shrunk one, for :mod:`facegeo.evaluate.views`; the view never
    reads the reference itself.

    With ``image_detail`` the source cameras' relit captures (:func:`_source_images`, once per
    environment weights in ``cache``) join every render of the view (``render_view(detail=)``);
    they are also kept on disk, in ``source_images_dir`` when given (the view tasks of a
    cluster stage share them so), else without a ``cache`` in ``dest/.source_images``.

    ``fill_px`` None: :func:`default_fill_px` of ``infer``."""
    from facegeo.capture import imageio
    from facegeo.fsutil import atomic_write_text
    from facegeo.lighting import envmap as E
    from facegeo.evaluate.views import has_view_reference
    from facegeo.pipeline.project import check_projection_atlas
    from facegeo.pipeline.relight import tone_map
    from facegeo.render import (
        light_set,
        parse_camera_spec,
        render_view,
        trace_view,
    )
    from facegeo.render.novel import BLEND_POWER

    t_start = time.perf_counter()
    fill_px = default_fill_px(infer) if fill_px is None else fill_px
    out, dest = Path(out), Path(dest)
    shrink_mode = _check_shrinkage(shrinkage)
    supersample = check_positive_int(supersample, "supersample")
    check_view_inputs(out, resynthesis)
    project_settings, the_rig, rig_used = _render_rig(scan, out, rig, cache)
    camera = parse_camera_spec(camera_spec, _view_cameras(scan, the_rig, rig_used, cache))
    stage = the_rig.lights
    w = _field_weights(env, stage, projection, rotate_deg, convention, solid_angle)
    # the skin model's light set only where it resynthesises (a naive render needs none)
    lights = light_set(stage) if resynthesis else None
    atlas, texels, scene, sources = _view_inputs(out, bool(resynthesis), cache,
                                                 check_projection_atlas)
    t_load = time.perf_counter()
    compare = bool(reference and has_view_reference(scan))
    factors, shrink_stats = None, None
    if resynthesis is True and shrink_mode == "cross-validated":
        factors, shrink_stats = _cross_validated_factors(sources, w, lights, light_step, cache)
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
        disk = Path(source_images_dir) if source_images_dir is not None else (
            None if cache is not None else dest / SOURCE_IMAGES_DIR)
        detail, t_sources = _source_images(scan, the_rig, rig_used, sources, w, keys, cache,
                                           disk)
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


def check_view_inputs(out: Path, resynthesis) -> None:
    """Raise the :class:`InputError` :func:`render_one` raises when a stage product a view
    reads is missing from ``out``: the atlas and texel table, and with ``resynthesis`` the
    fits' folder."""
    out = Path(out)
    for need in ("atlas/atlas.npz", "atlas/texels.npz"):
        if not (out / need).is_file():
            raise InputError(f"render: {out / need} is missing; run 'facegeo reconstruct SCAN' first")
    if resynthesis and not (out / "fit").is_dir():
        raise InputError(f"render: {out / 'fit'} is missing; run 'facegeo fit SCAN' first (or "
                         "render the naive baseline with resynthesis=False)")


def _render_rig(scan, out: Path, rig, cache: dict | None = None) -> tuple:
    """``(project_settings, rig, rig_used)`` of a view: the ``project`` stage's settings
    (``out/project/stage.json``; {} when unreadable) and :func:`facegeo.pipeline.project.stage_rig`
    of ``rig`` — by default the rig the projection used. With a ``cache`` the rig is resolved
    once (key ``("stage_rig", rig)``): the views of a stage share it, and a view task seeded by
    its client (:func:`facegeo.pipeline.render.render_products`) reads no rig file of the scan."""
    from facegeo.pipeline.project import stage_rig

    try:
        project_settings = json.loads((out / "project" / "stage.json").read_text())["settings"]
    except (OSError, ValueError, KeyError, TypeError):
        project_settings = {}
    if not isinstance(project_settings, dict):
        project_settings = {}
    if rig is None:
        rig = project_settings.get("rig")
    key = ("stage_rig", rig)
    got = cache.get(key) if cache is not None else None
    if got is None:
        got = stage_rig(scan, rig)
        if cache is not None:
            cache[key] = got
    the_rig, rig_used = got
    return project_settings, the_rig, rig_used


def _view_cameras(scan, the_rig, rig_used: str, cache: dict | None = None) -> dict:
    """The cameras a view spec may name (:func:`facegeo.pipeline.fit._camera_table`: the rig's,
    the generator's novel ones — ``ground_truth/novel_cameras.json`` —, ``front``); with a
    ``cache`` made once a rig (key ``("camera_table", rig_used)``), as :func:`_render_rig`."""
    from facegeo.pipeline.fit import _camera_table

    key = ("camera_table", rig_used)
    if cache is not None and key in cache:
        return cache[key]
    table = _camera_table(scan, the_rig)
    if cache is not None:
        cache[key] = table
    return table


def _field_weights(env, stage, projection: str, rotate_deg: float, convention: str,
                   solid_angle: str) -> np.ndarray:
    """(L, 3) float64: the environment ``env``'s Eq. (4) weights of the light stage's lights
    (Debevec et al. 2000 §4.2) divided by each light's intensity, so that the field's image
    is in the environment's units (field = intensity × R)."""
    from facegeo.lighting import envmap as E

    environment = _load_env(env, projection, rotate_deg, convention)
    w = E.light_weights(environment, stage, solid_angle=solid_angle)  # a grid or a light list
    return E.field_weights(w, stage)


def _cross_validated_factors(sources, w, lights, light_step: int, cache: dict | None) -> tuple:
    """``(factors, stats)`` of :func:`facegeo.render.cross_validated_shrinkage` for the weights
    ``w`` at ``light_step``: kept in ``cache`` under ``("shrinkage", sha1(w), light_step)``,
    so the views of a stage under one environment share one λ per source camera."""
    from facegeo.render import cross_validated_shrinkage

    key = ("shrinkage", hashlib.sha1(np.ascontiguousarray(w, np.float64).tobytes())
           .hexdigest(), int(light_step))
    if cache is not None and key in cache:
        return cache[key]
    got = cross_validated_shrinkage(sources, w, lights, light_step=light_step)
    if cache is not None:
        cache[key] = got
    return got


def _unmeasured_texel_fraction(texels, sources) -> float:
    """The share of the atlas's texels that no source camera measured (a row of no projected
    field): what a render with ``infer`` covers by inference."""
    seen = np.zeros(len(texels), bool)
    for src in sources:
        seen[np.asarray(src.texel_index, np.int64)] = True
    return round(float(1.0 - seen.mean()), 6) if seen.size else 0.0


def source_images_key(w, rig_used: str, names: tuple, keys: tuple) -> tuple:
    """The ``cache`` key of the relit source captures (:func:`_source_images`) under the
    weights ``w`` of the cameras ``names`` of the rig ``rig_used`` with the key lights
    ``keys``: ``("source_images", sha1(w), rig_used, names, keys)``."""
    return ("source_images", hashlib.sha1(np.ascontiguousarray(w, np.float64).tobytes())
            .hexdigest(), rig_used, tuple(names), tuple(keys))


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
    key = source_images_key(w, rig_used, names, keys)
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
            images = read_source_images(path, {c: the_rig.camera(c) for c in names}, keys)
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
        try:
            with atomic_path(path) as tmp:
                write_source_images(tmp, images)
            _prune(disk, SOURCE_IMAGES_KEEP)
        except OSError as exc:  # the render does not need the cache
            log.warning("%s: could not keep the relit source images (%s)", disk, exc)
    return images, round(time.perf_counter() - t0, 4)


def write_source_images(file, images) -> None:
    """The relit source captures ``images`` (:class:`facegeo.render.detail.SourceImage`, as
    :func:`_source_images` makes them) as one ``.npz`` into ``file`` (a path or a binary
    file object): per camera ``<camera>/image``, ``<camera>/valid`` and per key light ``k``
    ``<camera>/<k>/frame``, ``<camera>/<k>/valid``."""
    arrays = {}
    for im in images:
        c = im.camera.name
        arrays[f"{c}/image"], arrays[f"{c}/valid"] = im.image, im.valid
        for k, (frame, ok) in im.key_frames.items():
            arrays[f"{c}/{k}/frame"], arrays[f"{c}/{k}/valid"] = frame, ok
    np.savez(file, **arrays)


def read_source_images(file, cameras: dict, keys: tuple) -> list:
    """The relit source captures :func:`write_source_images` wrote into ``file`` (a path or a
    binary file object), of the cameras ``cameras`` (``{name: Camera}``, in the sources'
    order) with the frames of the key lights ``keys``."""
    from facegeo.render.detail import SourceImage

    with np.load(file) as z:
        return [SourceImage(cam, z[f"{c}/image"], z[f"{c}/valid"],
                            {k: (z[f"{c}/{k}/frame"], z[f"{c}/{k}/valid"]) for k in keys})
                for c, cam in cameras.items()]


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


def view_input_files(out: Path, with_fit: bool) -> list[str]:
    """Every file under ``out`` a view reads (:func:`render_one`), relative to ``out`` as POSIX
    paths: the atlas and texel table, the ``project`` stage's settings and atlas fingerprint
    (when there), per camera folder with a field its texel index, weights, view directions and
    field — ``R.npy``, the files of a Zarr store ``R.zarr`` in the folder, or the link
    ``R.zarr.url`` to a field kept in a store (read where it is) — and, when ``with_fit``, the
    camera's fit (``fit/<camera>/fit.npz``, ``D.npy``). What the view tasks of a render stage
    without a shared disk fetch (:func:`facegeo.pipeline.render.render_products`)."""
    from facegeo.pipeline.project import ATLAS_FINGERPRINT
    from facegeo.render._fitstore import DIFFUSE_FILE, FIT_FILE
    from facegeo.surface._zarr_field import LINK_SUFFIX, field_location
    from facegeo.surface.reflectance import field_folders, find_field

    out = Path(out)
    files = [out / "atlas" / "atlas.npz", out / "atlas" / "texels.npz"]
    files += [f for f in (out / "project" / "stage.json", out / "project" / ATLAS_FINGERPRINT)
              if f.is_file()]
    for d in field_folders(out / "project"):
        files += [d / n for n in ("texel_index.npy", "weight.npy", "v_world.npy")]
        kind, loc = find_field(d)
        if kind == "npy":
            files.append(Path(loc))
        elif isinstance(loc, Path) and loc.parent == d:  # a Zarr store in the folder
            files += sorted(f for f in loc.rglob("*") if f.is_file())
        else:  # a link to a field in a store
            files.append(Path(str(field_location(d)) + LINK_SUFFIX))
        if with_fit:
            files += [out / "fit" / d.name / FIT_FILE, out / "fit" / d.name / DIFFUSE_FILE]
    # one missing is not put: the view then raises what it raises reading the stage folder
    return [f.relative_to(out).as_posix() for f in files if f.is_file()]


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


def _expose(img, exposure: float) -> np.ndarray:
    """8-bit sRGB with a given exposure (so a render and its reference share one)."""
    from facegeo.capture.response import encode

    return encode(np.clip(img * np.float32(exposure), 0.0, 1.0), "srgb", np.uint8)
