"""Benchmarks of the novel-view renderer (Debevec et al. 2000 §4.5, :mod:`facegeo.render`).

``render.novel_view``: a tiny synthetic scan (generated in a temporary folder, true rig,
ground-truth mesh, atlas at 0.5 texels/mm), its skin-model fit restricted to the texels the view
needs, then the view ``orbit:cam_left:30`` under the built-in sky rendered with resynthesis and
as the naive baseline (measured functions relit and blended). Speed: pixels per second of the
whole render (primary rays, resynthesis of every needed texel from every source camera, Eq. (4)
over the active lights, blending); error: the relative RMSE against the generator's reference
over the head mask. Also reported: texels shaded per second and the fit's functions per second
(the stage that dominates today). With ``quick`` the fit is subsampled (300 functions per
camera; the other texels fall back to their measured functions), so its error is nearer the
naive baseline's.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from facegeo.bench import BenchRow, best_of, register


@register("render.novel_view")
def bench_novel_view(quick: bool) -> list[BenchRow]:
    from facegeo.pipeline.fit import run_fit
    from facegeo.pipeline.project import run_project
    from facegeo.pipeline.render import run_render
    from facegeo.synth.capture import generate_scan

    spec = "orbit:cam_left:30"
    rows = []
    with tempfile.TemporaryDirectory(prefix="facegeo-bench-render-") as tmp:
        root = Path(tmp) / "scan"
        generate_scan(root, "tiny")
        run_project(root, atlas_settings={"texels_per_mm": 0.5}, gt_lights=4)
        t0 = time.perf_counter()
        fm = run_fit(root, texels="views", views=[spec], max_texels=300 if quick else None)
        t_fit = time.perf_counter() - t0
        out = {}
        for resyn in (True, False):
            sec, m = best_of(lambda r=resyn: run_render(
                root, camera_spec=spec, env="sky", resynthesis=r, baseline=False,
                name=f"bench_{r}"), repeat=1 if quick else 2)
            out[resyn] = (sec, m)
        for resyn, label in ((True, "resynthesis"), (False, "naive baseline")):
            sec, m = out[resyn]
            px = m["size"][0] * m["size"][1]
            rows.append(BenchRow(
                "render.novel_view",
                f"{spec}, sky, tiny preset ({m['size'][0]}×{m['size'][1]}), {label}",
                px / m["seconds_render"], "pixels/s", m.get("rel_rmse"),
                "relative RMSE vs generator reference (head mask)",
                extra={"texels_shaded_per_s": round(m["stats"]["texels"]
                                                    / max(m["stats"]["seconds_shade"], 1e-9), 1),
                       "psnr_db": m.get("psnr_db"), "coverage": m.get("coverage"),
                       "active_lights": m["active_lights"],
                       "seconds_render": m["seconds_render"], "seconds_run_render": round(sec, 3),
                       "fit_functions": fm["functions"],
                       "fit_functions_per_s": fm["functions_per_second"],
                       "fit_seconds": round(t_fit, 2)},
                threads=1))
    return rows


# ----------------------------------------------------------------- paper-preset novel view

#: Size of the paper-preset novel view (width, height), pixels.
PAPER_VIEW_SIZE = (640, 480)
#: Functions generated per chunk (bounded (n, L, 3) temporaries at 2048 lights).
_GEN_CHUNK = 2048


def _paper_geometry(seed: int = 0, size: tuple[int, int] | None = None):
    """The paper preset's head (its icosphere subdivisions), its atlas at the reconstruct
    default of 1 texel/mm, the paper rig and a 640 × 480 camera orbited 30° from ``cam_left``
    (its intrinsics scaled so the face fills the same share of the image height)."""
    import numpy as np

    from facegeo.render._cameras import orbit_camera
    from facegeo.render.novel import atlas_scene
    from facegeo.surface.atlas import build_atlas, rasterize_texels
    from facegeo.synth.capture import PRESETS, build_head, build_rig

    preset = PRESETS["paper"]
    mesh = build_head("procedural", subdivisions=preset.head_subdivisions, seed=seed)
    atlas = build_atlas(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces),
                        texels_per_mm=1.0)
    texels = rasterize_texels(atlas)
    rig = build_rig(preset)
    cam = rig.cameras[0]
    w, h = PAPER_VIEW_SIZE if size is None else size
    s = h / cam.height
    K = cam.K.copy()
    K[:2] *= s
    K[0, 2] = (w - 1) / 2.0 + (cam.K[0, 2] - (cam.width - 1) / 2.0) * s
    K[1, 2] = (h - 1) / 2.0 + (cam.K[1, 2] - (cam.height - 1) / 2.0) * s
    novel = orbit_camera(cam.replace(width=w, height=h, K=K), 30.0)
    return atlas, texels, atlas_scene(atlas), rig, novel


def _texel_params(texel_ids, seed: int):
    """Skin-model parameters per texel (paper mode), seeded by the texel index so that every
    camera sees the same surface."""
    import numpy as np

    from facegeo.appearance import skin

    n = texel_ids.size
    rng = np.random.default_rng([seed, 11])
    u = rng.random((int(texel_ids.max()) + 1 if n else 1, 8))[texel_ids]
    chroma = skin.normalize(np.array([0.8, 0.5, 0.35]) + 0.05 * (u[:, :3] - 0.5))
    return skin.SkinParams((0.3 + 0.4 * u[:, 3:4]) * chroma, 0.2 + 0.2 * u[:, 4],
                           -0.5 + 0.3 * u[:, 5], 0.3 + 0.5 * u[:, 6], 0.3 + 0.15 * u[:, 7])




def _paper_diffuse(n, v, lights, params):
    """The diffuse part of :func:`facegeo.appearance.skin.paper_reflectance` (Eq. 6–7, no
    specular term), ``(N, L, 3)`` float32: what an exact separation gives as D."""
    import numpy as np

    from facegeo.appearance._skin_model import normalize, ramp_chromaticity, ramp_f

    nl = n @ lights.directions.T
    nv = np.einsum("ni,ni->n", n, v)[:, None]
    f = ramp_f(nl, nv, params.alpha_0[:, None], params.alpha_1[:, None])
    c = ramp_chromaticity(normalize(params.rho_d)[:, None, :], f)
    a = np.linalg.norm(params.rho_d, axis=1)[:, None]
    lit = (nv > 0) & (nl > 0)
    D = np.where(lit, a / np.pi * nl, 0.0)[..., None] * c * lights.intensities[None]
    return D.astype(np.float32)


def _subset_params(prm, sel):
    from facegeo.appearance import skin

    return skin.SkinParams(prm.rho_d[sel], prm.alpha_0[sel], prm.alpha_1[sel], prm.rho_s[sel],
                           prm.roughness[sel], prm.eta)


def _paper_sources(texels, need, rig, scene, lights, pool_step: int, seed: int = 0):
    """Source cameras at paper-preset sizes with generator-exact fits.

    Every texel of ``need`` that a rig camera sees becomes a row of that camera's field, with
    the projection's weight and view direction (:func:`camera_visibility`). Its function is the
    paper model's (:func:`facegeo.appearance.skin.paper_reflectance`) for the surface point of
    its *pool texel* — every ``pool_step``-th needed texel, each texel taking the nearest pool
    texel at or before it in atlas order (a neighbour a few texels away): normal, view from
    that camera and skin parameters of the pool texel. Generating 2048-light functions costs
    ≈ 3 ms each here, so the pool keeps the setup to about a minute while every texel is still
    its own row, read and resynthesised on its own. The field R is float16 (as the
    projection stores it); the fit is a :class:`facegeo.render._fitstore.FitStore` in memory
    with the generator's parameters and D its exact diffuse part (float16, as the fit stage
    stores it), no cast shadows.

    Returns
    -------
    sources : list of SourceCamera
    pool : (P,) int64 — the pool texels
    params : SkinParams of the pool texels
    """
    import numpy as np

    from facegeo.appearance import skin
    from facegeo.render._fitstore import _MAPS, _PER_FUNCTION, FitStore
    from facegeo.render.novel import SourceCamera
    from facegeo.surface.reflectance import camera_visibility

    L = lights.n_lights
    pool = need[::pool_step]
    prm = _texel_params(pool, seed)
    nrm_pool = texels.n_world[pool]
    out = []
    for cam in rig.cameras:
        vis = camera_visibility(texels, cam, scene)
        idx = np.intersect1d(np.flatnonzero(vis.visible), need)
        parent = np.searchsorted(need, idx) // pool_step  # pool position of each texel
        gen, inv = np.unique(parent, return_inverse=True)
        v_gen = cam.center_world[None, :] - texels.p_world[pool[gen]]
        v_gen /= np.linalg.norm(v_gen, axis=1, keepdims=True)
        R = np.empty((gen.size, L, 3), np.float16)
        D = np.empty((gen.size, L, 3), np.float16)
        for s in range(0, gen.size, _GEN_CHUNK):
            sl = slice(s, min(gen.size, s + _GEN_CHUNK))
            p = _subset_params(prm, gen[sl])
            n_s = nrm_pool[gen[sl]]
            R[sl] = skin.paper_reflectance(n_s, v_gen[sl], lights, p)
            D[sl] = _paper_diffuse(n_s, v_gen[sl], lights, p)
        n_c = idx.size
        nrm = nrm_pool[parent]
        params = {k: np.zeros(n_c) for k in _PER_FUNCTION}
        params.update(view=v_gen[inv], normal=nrm, normal_moment=nrm, normal_initial=nrm,
                      d_0=skin.normalize(prm.rho_d)[parent], alpha_0=prm.alpha_0[parent],
                      alpha_1=prm.alpha_1[parent], rho_d=prm.rho_d[parent],
                      rho_s=prm.rho_s[parent], flags=np.zeros(n_c, np.int32),
                      valid=np.ones(n_c, bool))
        params.update({k: np.zeros((n_c, (L + 7) // 8), np.uint8) for k in _MAPS})
        fit = FitStore(None, np.arange(n_c), idx, params, D[inv], float(prm.eta), False)
        out.append(SourceCamera(cam.name, idx, vis.weight[idx], vis.v_world[idx], R[inv], fit))
    return out, pool, prm


#: The sun-like environment of ``render.novel_view_paper``: a disc of this angular radius
#: (radians) and radiance, from this direction (world frame), over a dim uniform sky.
SUN = {"direction": (0.5, 0.6, 0.6), "radius": 0.05, "radiance": 400.0, "sky": 0.02}


def _sun_map(sky: float | None = None):
    """A sun-like environment: :data:`SUN`'s disc over a dim uniform sky (every light carries
    some energy, one block of lights nearly all of it); ``sky = 0``: the disc alone (only the
    few lights it covers carry energy — the case where the renderer visits fewest lights)."""
    import numpy as np

    from facegeo.lighting import envmap as E

    d = np.asarray(SUN["direction"], np.float64)
    d /= np.linalg.norm(d)
    cos_r = np.cos(SUN["radius"])

    def fn(v):
        sun = (v @ d) >= cos_r
        dim = SUN["sky"] if sky is None else float(sky)
        return np.where(sun[..., None], SUN["radiance"], dim) * np.ones(3)

    return E.analytic_map(fn, 128, supersample=4)


def _generator_texel_colours(texels, ids, pos, center, prm, lights, w, normals):
    """The generator's answer at texels ``ids`` (pool positions ``pos``): their paper-model
    functions (the pool texel's parameters and normal) seen from the novel camera centre,
    relit by Eq. 4 — ``(n, 3)`` float64."""
    import numpy as np

    from facegeo.appearance import skin

    v = center[None, :] - texels.p_world[ids]
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    R = skin.paper_reflectance(normals, v, lights, _subset_params(prm, pos))
    return np.einsum("nlc,lc->nc", R.astype(np.float64), w)


def _rel_rmse(a, b) -> float:
    import numpy as np

    ok = np.isfinite(a).all(axis=-1) & np.isfinite(b).all(axis=-1)
    return float(np.sqrt(((a[ok] - b[ok]) ** 2).sum() / max((b[ok] ** 2).sum(), 1e-300)))


@register("render.novel_view_paper")
def bench_novel_view_paper(quick: bool) -> list[BenchRow]:
    """A 640 × 480 novel view at the paper preset's sizes: seconds per view against error.

    Sizes: the paper preset's head (6 icosphere subdivisions, 81,920 faces), its atlas at the
    reconstruct default of 1 texel/mm (≈ 115,000 texels), its two source cameras
    (``cam_left``, ``cam_right``) and 64 × 32 = 2048 lights; the view orbits ``cam_left`` by
    30° (640 × 480, focal length scaled so that the face fills the image height as in the
    source cameras; ≈ 48,000 texels needed, ≈ 80,000 camera functions). Fit inputs: the
    paper-preset scan is too slow to synthesise here, so every camera function is the
    generator-exact paper model (:func:`_paper_sources`: paper-mode skin functions with
    per-texel parameters, D the exact diffuse part, float16 storage like the pipeline's; every
    ``pool_step``-th texel's function reused by its neighbours — 4, 16 with ``quick`` — so
    generation takes about a minute while every texel is still read and resynthesised on
    its own; ``quick`` also renders a 160 × 120 view under ``sky`` only, without
    ``light_step=2``: a smoke run of the rows, not the paper figures). Environments: the
    built-in ``sky``, a sun-like map (:data:`SUN`: every light carries energy, one block of
    lights nearly all of it) and its sun disc alone (only the few lights it covers carry
    energy), Eq. (4) weights with the paper's δA.

    Per environment, one row per renderer setting, all in the same run: the exact path
    (``light_step=1``, every light), the speed/accuracy option ``light_step`` = 2 and 4
    (:func:`facegeo.render.shade_texels`) and the naive baseline; each with the
    cross-validated shrinkage λ the render stage uses. λ depends on the environment, the
    source cameras and ``light_step`` only, so it is computed once per environment and timed
    apart (``seconds_shrinkage_per_environment``; ``seconds_first_view_with_shrinkage`` is a
    first view's whole cost). Speed: views per second (whole render: trace, shading, image;
    ``cpu_seconds_per_view``: its process time, both threads — the figure to compare when
    other jobs share the cores;
    writing EXR + PNG timed separately). Error: the image's relative RMSE against the exact path over the
    covered pixels; extras: the relative RMSE of texel colours against the generator's exact
    answer (its functions at the novel view, relit) over an even subset of ≤ 1024 pool texels,
    for the setting and for the exact path, and the profile (seconds reading the fields,
    reading the fits, resynthesising, the rest of the shading = blending and bookkeeping).
    The exact row also times the same view with the render stage's shadow-consistent texel
    taps (``seconds_per_view_with_shadow_taps``, ``seconds_shadow_taps_build_per_stage``,
    ``shadow_lights``, ``shadow_edge_samples``; :func:`facegeo.render.render_shadows`) and
    with the taps and the stage's image-space detail (``seconds_per_view_with_taps_and_
    image_detail``, ``seconds_image_detail``, ``image_detail_pixels``;
    :mod:`facegeo.render.detail`; blank source captures stand in — the time does not depend
    on their pixels).
    """
    from facegeo.capture import imageio
    from facegeo.lighting import envmap as E
    from facegeo.pipeline.relight import tone_map
    from facegeo.pipeline.render import builtin_env
    from facegeo.render._fitstore import light_set
    import numpy as np

    from facegeo.render.detail import SourceImage
    from facegeo.render.novel import (
        cross_validated_shrinkage,
        even_subset,
        key_lights,
        render_shadows,
        render_view,
        shade_texels,
        trace_view,
    )

    t0 = time.perf_counter()
    # quick (the test suite's smoke run): a 160 × 120 view of the same head, atlas and lights,
    # under one environment — the rows' shape, not the paper figures
    size = (160, 120) if quick else PAPER_VIEW_SIZE
    atlas, texels, scene, rig, novel = _paper_geometry(size=size)
    t_geo = time.perf_counter() - t0
    t0, c0 = time.perf_counter(), time.process_time()
    vs = trace_view(novel, scene, atlas, texels)
    t_trace = time.perf_counter() - t0
    cpu_trace = time.process_time() - c0
    need = vs.needed_texels
    lights = light_set(rig.lights)
    pool_step = 16 if quick else 4
    t0 = time.perf_counter()
    sources, pool, prm = _paper_sources(texels, need, rig, scene, lights, pool_step)
    t_gen = time.perf_counter() - t0
    n_fun = sum(s.texel_index.size for s in sources)
    # texels where the generator's answer is computed: pool texels (their own function)
    ref_pos = even_subset(pool.size, 1024)
    ref_ids = pool[ref_pos]
    stage = rig.lights
    rows = []
    settings = (("exact (every light)", True, 1), ("light_step=2", True, 2),
                ("light_step=4", True, 4), ("naive baseline", False, 1))
    envs = (("sky", builtin_env("sky")),) if quick else (("sky", builtin_env("sky")),
                                                          ("sun", _sun_map()),
                                                          ("sun disc only", _sun_map(0.0)))
    if quick:
        settings = (settings[0], settings[2], settings[3])
    for env_name, env in envs:
        w = E.light_stage_weights(env, stage.n_theta, stage.n_phi) / stage.color_rgb[None, :]
        truth = _generator_texel_colours(texels, ref_ids, ref_pos, novel.center_world, prm,
                                         lights, w, texels.n_world[pool][ref_pos])
        results = {}
        for label, resyn, step in settings:
            # λ depends on the environment, the sources and light_step, not on the view:
            # computed once per environment and reused by every view rendered under it, so
            # it is timed apart from the view (seconds_shrinkage_per_environment)
            t0 = time.perf_counter()
            factors = None
            if resyn:
                factors, _ = cross_validated_shrinkage(sources, w, lights, light_step=step)
            t_shrink = time.perf_counter() - t0
            t0, c0 = time.perf_counter(), time.process_time()
            res = render_view(novel, scene, atlas, texels, sources, w, lights, samples=vs,
                              resynthesis=resyn, shrinkage=factors, light_step=step)
            t_view = time.perf_counter() - t0 + t_trace
            cpu_view = time.process_time() - c0 + cpu_trace
            with tempfile.TemporaryDirectory(prefix="facegeo-bench-render-") as tmp:
                t1 = time.perf_counter()
                imageio.write_image(Path(tmp) / "view.exr", res.image)
                imageio.write_image(Path(tmp) / "view.png", tone_map(res.image)[0])
                t_write = time.perf_counter() - t1
            col = shade_texels(ref_ids, texels.p_world[ref_ids], novel.center_world, sources, w,
                               lights, resynthesis=resyn, shrinkage=factors, light_step=step)
            if label == settings[0][0]:
                # what the render stage's default shadow-consistent texel taps add to the
                # exact view (their accuracy is an image's, measured in docs/render.md)
                t0 = time.perf_counter()
                shadows = render_shadows(atlas, scene, texels, stage)
                t_build = time.perf_counter() - t0
                t0 = time.perf_counter()
                tapped = render_view(novel, scene, atlas, texels, sources, w, lights,
                                     samples=vs, resynthesis=resyn, shrinkage=factors,
                                     light_step=step, shadows=shadows)
                t_taps = time.perf_counter() - t0 + t_trace
                # and what the image-space detail adds (facegeo.render.detail): the source
                # images' projection and their key lights' shadow-consistent taps; its time
                # does not depend on the pixels, so blank captures of the source cameras'
                # size stand in (relighting a scan's frames is timed in docs/render.md)
                keys = key_lights(w, shadows.key_share, shadows.max_lights)
                blank = []
                for cam in (rig.camera(src.name) for src in sources):
                    img = np.zeros((cam.height, cam.width, 3), np.float32)
                    ok = np.ones((cam.height, cam.width), bool)
                    blank.append(SourceImage(cam, img, ok, {int(k): (img, ok) for k in keys}))
                t0 = time.perf_counter()
                detailed = render_view(novel, scene, atlas, texels, sources, w, lights,
                                       samples=vs, resynthesis=resyn, shrinkage=factors,
                                       light_step=step, shadows=shadows, detail=blank)
                taps_extra = {
                    "seconds_per_view_with_shadow_taps": round(t_taps, 3),
                    "seconds_shadow_taps_build_per_stage": round(t_build, 3),
                    "shadow_lights": tapped.stats["shadow_lights"],
                    "shadow_edge_samples": tapped.stats["shadow_edge_samples"],
                    "seconds_shadows": tapped.stats["seconds_shadows"],
                    "seconds_per_view_with_taps_and_image_detail": round(
                        time.perf_counter() - t0 + t_trace, 3),
                    "seconds_image_detail": detailed.stats["seconds_detail"],
                    "image_detail_pixels": detailed.stats["detail_pixels"]}
            results[label] = (res, t_view, t_shrink, t_write, factors, col, cpu_view)
        exact, exact_col = results[settings[0][0]][0], results[settings[0][0]][5]
        cov = exact.covered
        naive_change = _rel_rmse(results["naive baseline"][0].image[cov], exact.image[cov])
        for label, (res, t_view, t_shrink, t_write, factors, col, cpu_view) in results.items():
            s = res.stats
            err = _rel_rmse(res.image[cov], exact.image[cov])
            rest = s["seconds_shade"] - s["seconds_read"] - s["seconds_fit"] \
                - s["seconds_resynthesis"]
            rows.append(BenchRow(
                "render.novel_view_paper",
                f"{size[0]}×{size[1]} novel view (cam_left +30°), paper preset sizes, "
                f"{env_name}, {label}",
                1.0 / t_view, "views/s", err,
                "relative RMSE vs the exact path's image (covered pixels)",
                extra={"seconds_per_view": round(t_view, 3),
                       "cpu_seconds_per_view": round(cpu_view, 3),
                       "texel_rel_rmse_vs_generator": round(_rel_rmse(col, truth), 6),
                       "exact_texel_rel_rmse_vs_generator": round(_rel_rmse(exact_col, truth),
                                                                  6),
                       "share_of_resynthesis_change": round(err / max(naive_change, 1e-12), 4)
                       if label != "naive baseline" else 1.0,
                       "naive_vs_exact_rel_rmse": round(naive_change, 6),
                       "seconds_trace": round(t_trace, 3),
                       "seconds_shrinkage_per_environment": round(t_shrink, 3),
                       "seconds_first_view_with_shrinkage": round(t_view + t_shrink, 3),
                       "seconds_read_fields": s["seconds_read"],
                       "seconds_read_fits": s["seconds_fit"],
                       "seconds_resynthesis_relight": s["seconds_resynthesis"],
                       "seconds_blend_other": round(rest, 3),
                       "seconds_image": s["seconds_image"],
                       "seconds_write_exr_png": round(t_write, 3),
                       "lambda": factors, "active_lights": s["active_lights"],
                       "texels": s["texels"], "camera_functions": s["samples"],
                       "resynthesized": s["resynthesized"],
                       "setup_seconds": {"geometry": round(t_geo, 1),
                                         "generate_functions": round(t_gen, 1)},
                       "camera_functions_stored": n_fun, "pool_step": pool_step,
                       **(taps_extra if label == settings[0][0] else {})},
                threads=2))
    return rows


# ----------------------------------------------------------------- the resynthesis kernels

#: Functions of ``render.resynth_kernel`` (``quick``: a quarter).
KERNEL_FUNCTIONS = 600


def _kernel_inputs(n: int, seed: int = 0):
    """``n`` paper-model functions on the paper preset's 64 × 32 light grid as the paper
    benchmark builds and stores them (:func:`_texel_params`; R and D float16, S = R − D;
    normals within 70° of v_0 = +z), novel
    views ≈ 30° away, and the ``sky`` weights. Returns the fit (R, D widened to float32), the
    views, the weights and the stored float16 R and D."""
    import numpy as np

    from facegeo.appearance import skin
    from facegeo.lighting import envmap as E
    from facegeo.pipeline.render import builtin_env

    rng = np.random.default_rng(seed)
    lights = skin.LightSet.from_grid(64, 32, color=(0.9, 1.0, 1.1))
    ang = np.radians(rng.uniform(0.0, 70.0, n))
    az = rng.uniform(0.0, 2.0 * np.pi, n)
    nrm = np.stack([np.sin(ang) * np.cos(az), np.sin(ang) * np.sin(az), np.cos(ang)], 1)
    prm = _texel_params(np.arange(n), seed)  # the paper benchmark's per-texel parameters
    v0 = np.tile([0.0, 0.0, 1.0], (n, 1))
    R16 = skin.paper_reflectance(nrm, v0, lights, prm).astype(np.float16)
    D16 = _paper_diffuse(nrm, v0, lights, prm).astype(np.float16)
    R, D = R16.astype(np.float32), D16.astype(np.float32)
    z = np.zeros(n)
    no = np.zeros((n, lights.n_lights), bool)
    fit = skin.SkinFit(lights=lights, view=v0, normal=nrm, normal_moment=nrm,
                       normal_initial=nrm, lobe_misfit_moment=z, lobe_misfit=z,
                       d_0=skin.normalize(prm.rho_d), alpha_0=prm.alpha_0, alpha_1=prm.alpha_1,
                       rho_d=prm.rho_d, rho_s=prm.rho_s, diffuse=D, specular=R - D, shadow=no,
                       cast_shadow=no, saturated=no, flags=np.zeros(n, np.int32),
                       valid=np.ones(n, bool), eta=prm.eta, single_channel=False)
    a = np.radians(30.0)
    vn = skin.normalize(np.tile([np.sin(a), 0.0, np.cos(a)], (n, 1))
                        + rng.normal(0.0, 0.05, (n, 3)))
    w = E.light_stage_weights(builtin_env("sky"), 64, 32)
    return fit, vn, w, R16, D16


def _read_then_resynthesize(fit, R16, D16, vn, w):
    """What the render did per chunk before the fused pass: R and D widened to float32 by
    numpy, the naive Eq. 4 as ``(n, 3L) @ (3L, 3)`` sgemm, S = R − D, then
    ``resynthesize_relit``. Returns the naive and the resynthesised sums."""
    from dataclasses import replace

    import numpy as np

    from facegeo.appearance import _skin_resynth as RS
    from facegeo.render.novel import _relight, _relight_matrix

    R = np.asarray(R16, np.float32)
    naive = _relight(R, _relight_matrix(w))
    D = np.asarray(D16, np.float32)
    f = replace(fit, diffuse=D, specular=R - D)
    return naive, RS.resynthesize_relit(f, vn, w)


def _stored_pass(fit, R16, D16, vn, w):
    """The fused pass (``_skin_resynth.relit_stored``) on the same stored functions."""
    import numpy as np

    from facegeo.appearance import _skin_resynth as RS

    n = R16.shape[0]
    naive, relit, _ = RS.relit_stored(
        R16, np.arange(n), D16, np.arange(n), np.ones(n, bool), normal=fit.normal,
        view=fit.view, alpha_0=fit.alpha_0, alpha_1=fit.alpha_1, cast_shadow=fit.cast_shadow,
        eta=fit.eta, lights=fit.lights, v_n=vn, weights=w)
    return naive, relit


@register("render.resynth_kernel")
def bench_resynth_kernel(quick: bool) -> list[BenchRow]:
    """Eq. 9 + Eq. 4 on resynthesised functions (``resynthesize_relit``), the kernels alone:
    the grid kernel ``resynth_relit_grid`` (the default) against the scalar ``resynth_relit``
    (the kernel before it, kept as its reference), at 1 and 2 threads, exact (every light)
    and ``light_step=4`` (which runs the scalar kernel); and the read of the stored float16
    functions with them: the render's path before the fused pass (R and D widened by numpy,
    naive Eq. 4 by sgemm, S = R − D, the grid kernel: :func:`_read_then_resynthesize`)
    against the fused pass that decodes the bits in the kernel (``relit_stored``). Speed:
    function-lights per second (wall); extras: CPU nanoseconds per function and light
    (process time, both threads — steadier than wall time when other jobs share the cores).
    Error: max |Δ| / max |scalar| of the resynthesised sums (and for the two read rows, of
    the naive sums: max |Δ| / max |naive| against the sgemm's).
    """
    import numpy as np
    from numba import get_num_threads, set_num_threads

    from facegeo.appearance import _skin_resynth as RS

    n = KERNEL_FUNCTIONS // (4 if quick else 1)
    fit, vn, w, R16, D16 = _kernel_inputs(n)
    L = fit.lights.n_lights
    active = int(np.any(w != 0, axis=1).sum())
    rows = []
    saved_threads, saved_vec = get_num_threads(), RS.VECTOR_KERNEL
    try:
        for threads in (1, 2):
            set_num_threads(min(threads, saved_threads))
            got = {}

            def kernel(vec, step):
                def call():
                    RS.VECTOR_KERNEL = vec
                    return None, RS.resynthesize_relit(fit, vn, w, light_step=step)
                return call

            cases = (("scalar resynth_relit, exact", kernel(False, 1)),
                     ("grid resynth_relit_grid, exact", kernel(True, 1)),
                     ("light_step=4", kernel(True, 4)),
                     ("read float16 + sgemm + grid kernel (before)",
                      lambda: _read_then_resynthesize(fit, R16, D16, vn, w)),
                     ("fused float16 pass relit_stored",
                      lambda: _stored_pass(fit, R16, D16, vn, w)))
            for label, run in cases:
                run()  # compiled, warm
                wall, cpu = float("inf"), float("inf")
                for _ in range(2 if quick else 3):
                    t0, c0 = time.perf_counter(), time.process_time()
                    naive, out = run()
                    wall = min(wall, time.perf_counter() - t0)
                    cpu = min(cpu, time.process_time() - c0)
                got[label] = (wall, cpu, out, naive)
                RS.VECTOR_KERNEL = saved_vec
            ref = got["scalar resynth_relit, exact"]
            before = got["read float16 + sgemm + grid kernel (before)"]
            naive_ref = before[3]
            for label, (wall, cpu, out, naive) in got.items():
                work = n * active  # function-lights of the exact path
                rows.append(BenchRow(
                    "render.resynth_kernel",
                    f"{label}, {n} paper-model functions, {L} lights ({active} with energy), "
                    f"sky, {threads} thread(s)",
                    work / wall, "function-lights/s",
                    float(np.abs(out - ref[2]).max() / np.abs(ref[2]).max()),
                    "max |Δ| / max |scalar exact|",
                    ratios={"vs scalar": round(ref[0] / wall, 3),
                            "vs read before": round(before[0] / wall, 3)},
                    baseline_threads={"vs scalar": threads, "vs read before": threads},
                    extra={"cpu_ns_per_function_light": round(cpu / work * 1e9, 1),
                           "wall_ns_per_function_light": round(wall / work * 1e9, 1),
                           "cpu_us_per_function": round(cpu / n * 1e6, 1),
                           "naive_max_rel_vs_sgemm": None if naive is None else
                           float(np.abs(naive - naive_ref).max() / np.abs(naive_ref).max())},
                    threads=threads))
    finally:
        set_num_threads(saved_threads)
        RS.VECTOR_KERNEL = saved_vec
    return rows
