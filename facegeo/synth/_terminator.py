"""The shadow-terminator measure of the reference renderer
(:func:`terminator_self_shadow_fraction`, re-exported by :mod:`facegeo.synth.render`; the
renderer's module docstring and docs/synth.md give its figures)."""

from __future__ import annotations

import numpy as np

__all__ = ["terminator_self_shadow_fraction"]


def terminator_self_shadow_fraction(renderer, cameras, lights, indices=None) -> dict:
    """Fraction of lit samples that the renderer shadows by their own or an adjacent triangle.

    For every camera and stage light (``indices``, default all), a sample is *lit* when its
    shading normal faces the light (cos θᵢ > 0) — the samples the shading would light without
    shadows. The renderer decides which lit samples are shadowed, exactly as in every frame,
    and reports the face that blocks the deciding shadow ray; the sample counts as
    *self-shadowed* when that face is its own or shares a vertex position with it (welded
    across UV seams): the terminator artefact, not a cast shadow.

    Parameters
    ----------
    renderer : facegeo.synth.render.ReferenceRenderer
    cameras : Camera or sequence of Camera
    lights : facegeo.geometry.rig.LightStage
    indices : sequence of int, optional
        Light indices (default every light).

    Returns
    -------
    dict
        ``fraction`` (self-shadowed / lit samples, summed over cameras and lights),
        ``self_shadowed``, ``lit``, ``shadowed`` (all blocked lit samples) as counts.
    """
    cams = [cameras] if hasattr(cameras, "pixel_rays") else list(cameras)
    # the renderer's own class (this module is imported by facegeo.synth.render)
    idx = type(renderer)._check_indices(lights, indices)
    n_lit = n_self = n_shadow = 0
    for cam in cams:
        view = renderer.surface_view(cam)
        for l in idx:
            if np.isfinite(lights.radius):
                pos = np.asarray(lights.center, float) + lights.radius * lights.directions[l]
                to_l = pos[None, :] - view.p_world
                dist = np.linalg.norm(to_l, axis=1)
                ldir = to_l / dist[:, None]
                kw = {"light_pos": pos}
            else:
                ldir = np.broadcast_to(lights.directions[l], view.p_world.shape)
                dist = np.full(view.n_samples, np.inf)
                kw = {"light_dir": np.asarray(lights.directions[l], float)}
            lit = np.einsum("pc,pc->p", view.n_world, ldir) > 0
            if not lit.any():
                continue
            p, face, n = view.p_world[lit], view.face[lit], view.n_world[lit]
            vis, blocker = renderer._shadow_test(p, face, n, **kw)
            blocked = ~vis
            n_lit += int(lit.sum())
            n_shadow += int(blocked.sum())
            if blocked.any():
                n_self += int(np.count_nonzero(renderer.adjacent(face[blocked], blocker[blocked])))
    return {"fraction": n_self / n_lit if n_lit else 0.0, "self_shadowed": n_self, "lit": n_lit,
            "shadowed": n_shadow}
