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

from facegeo.pipeline.bench import BenchRow, best_of, register


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
        fm = run_fit(root, texels="views", views=[spec], max_texels=300 if quick else None,
                     gt_functions=16)
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


def _paper_geometry(seed: int = 0):
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
    w, h = PAPER_VIEW_SIZE
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
