"""The ``project`` stage's products against the generator's truth (synthetic scans).

Reads ``out/atlas/`` (atlas, texels), ``out/project/`` (``rig.json``: the rig the stage used;
per camera ``R.npy``, ``texel_index.npy``, ``weight.npy`` and ``visibility.npz``: its occlusion
decision) and the scan's ``ground_truth/`` (the generator's renderer, per-pixel hits).

* ``visibility_agreement`` per camera: over texels in the image and facing the camera, away from
  silhouettes and occlusion edges, the fraction whose occlusion decision agrees with the
  generator's own per-pixel closest hits (``ground_truth/geometry_<camera>.npz``, true rig): a
  texel is visible in the reference when it is no farther from the camera than the farthest of
  the four ground-truth hits around its projection (+ 1 mm). ``visibility_compared`` /
  ``visibility_compared_fraction``: how many of the in-image, facing texels that is.
* ``projection_rel_rmse``: ``sqrt(Σ_t a_t Σ_{c,l} (R − R_ref)² / Σ_t a_t Σ_{c,l} R_ref²)`` over
  texels with weight above ``gt_weight_min`` (per camera), every camera, a stratified subset of
  at most ``gt_lights`` lights (:func:`facegeo.frames.stratified_light_subset`: every inclination,
  azimuths spread over the circle), ``a_t`` the surface area the texel stands for
  (:func:`facegeo.evaluate.gauge.texel_areas`; so the figure is a mean over the surface, not
  over however the atlas samples it). ``R_ref`` is the generator's exact shading (true rig; the
  same normals, material — ``material_at``, part materials included — and shadow rays as its
  frames) of the texel's surface point from the same camera. The texel's point is itself on the
  ground-truth mesh; on any other mesh (a reconstruction) it is the closest point of the
  ground-truth surface (``projection_reference``, with the area-weighted RMS distance
  ``projection_reference_offset_mm``), so a misplaced surface shows up as misregistration.
  With any rig but the true one, the mesh is first brought onto the true surface by the best
  rigid transform (:func:`facegeo.evaluate.gauge.truth_gauge`: that rig's world frame is its
  own gauge; ``gauge_rotation_deg`` / ``gauge_translation_mm`` say how far it moved), so the
  figure measures the reflectance field, not where the rig put the world's origin.
  Masked (NaN) samples are left out. Beside it, for comparison and diagnosis:
  ``projection_rel_rmse_per_texel`` (every texel counted once, the metric before area
  weighting), ``projection_rel_rmse_all_weights`` (area-weighted over every texel the camera
  weights at all: the grazing views and the feathered bands at silhouettes and occlusion edges
  that the threshold leaves out), ``projection_rel_rmse_off_shadow_edges`` (area-weighted,
  only samples whose four bilinear taps are all lit or all dark in the generator's noiseless
  frame), ``projection_shadow_edge_samples`` (the fraction of compared samples that straddle
  such an edge) and ``projection_shadow_edge_error_share`` (their share of Σ a_t err²). Each
  camera's entry has the same keys.
"""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from facegeo.checks import check_positive_int
from facegeo.frames import stratified_light_subset
from facegeo.evaluate._products import stage_rig_product
from facegeo.evaluate.gauge import inferred_atlas_vertices, texel_areas, truth_gauge
from facegeo.surface.reflectance import has_field

__all__ = ["GT_LIGHTS", "GT_WEIGHT_MIN", "VISIBILITY_FILE", "evaluate_projection",
           "has_projection_truth", "with_projection_figures"]

#: Lights the ground-truth comparison shades by default (a stratified subset). On the small preset
#: (512 lights) 128 estimate the all-lights figure within 0.5 % of itself (plain bilinear: 3.096
#: against 3.110 %)
#: at ≈ 2 s a camera; 32 scattered by ±0.27 points between subsets (random draws) and a stride
#: of 16 (the former choice: two azimuths, in front of and behind the face) read 2.870 %.
GT_LIGHTS = 128
#: Texels whose projection weight is at or below this are left out of the headline figures.
GT_WEIGHT_MIN = 0.3
#: The per-camera file of the ``project`` stage holding its occlusion decision.
VISIBILITY_FILE = "visibility.npz"
_GT_DEPTH_TOL_M = 1e-3


def has_projection_truth(scan) -> bool:
    """Whether the scan carries the generator's truth the projection is compared with."""
    return bool(scan.synthetic and {"skin", "mesh", "rig"} <= set(scan.ground_truth_keys))


def _visibility_agreement(scan, cam_name: str, camera, texels, vis, depth_jump: float):
    """Agreement of the occlusion decision with the generator's per-pixel hits (see module)."""
    key = f"geometry_{cam_name}"
    if key not in scan.ground_truth_keys:
        return None
    with np.load(scan.ground_truth_path(key)) as g:
        mask, p_gt = g["mask"], g["p_world"]
    H, W = mask.shape
    idx = np.flatnonzero(vis.in_image & vis.facing)
    q = vis.q[idx]
    x0 = np.clip(np.floor(q[:, 0]).astype(np.int64), 0, W - 2)
    y0 = np.clip(np.floor(q[:, 1]).astype(np.int64), 0, H - 2)
    c = camera.center_world
    d_gt = np.linalg.norm(p_gt - c, axis=-1)
    d_gt[~mask] = np.nan
    quad = np.stack([d_gt[y0, x0], d_gt[y0, x0 + 1], d_gt[y0 + 1, x0], d_gt[y0 + 1, x0 + 1]], 1)
    smooth = np.all(np.isfinite(quad), axis=1)
    with np.errstate(invalid="ignore"):  # a quad with a miss is NaN here: not smooth anyway
        # (np.nanmax warned "All-NaN slice" on the terminal of every reconstruct)
        smooth &= (quad.max(axis=1) - quad.min(axis=1)) < depth_jump
    # away from silhouettes: no miss within 2 pixels
    import cv2

    near_sil = cv2.dilate((~mask).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    smooth &= ~near_sil[np.rint(q[:, 1]).astype(int).clip(0, H - 1),
                        np.rint(q[:, 0]).astype(int).clip(0, W - 1)]
    d_t = np.linalg.norm(texels.p_world[idx] - c, axis=1)
    ref = d_t <= np.nanmax(np.where(np.isfinite(quad), quad, -np.inf), axis=1) + _GT_DEPTH_TOL_M
    sel = np.flatnonzero(smooth)
    if sel.size == 0:
        return None
    agree = ref[sel] == vis.unoccluded[idx[sel]]
    return {"agreement": float(agree.mean()), "compared": int(sel.size),
            "candidates": int(idx.size),
            "occluded_reference": int(np.count_nonzero(~ref[sel]))}


def _tap_pixels(view, q: np.ndarray):
    """``view`` restricted to the pixels a bilinear sample at positions ``q`` ``(N, 2)`` can
    touch: ``floor(x) … floor(x) + 2`` and the same in y (``cv2.remap`` rounds a position to
    1/32 px, which can move its left tap one pixel right), clipped to the image. Shading only
    these pixels gives the same samples as shading the whole view at a fraction of the cost."""
    h, w = view.shape
    fx = np.floor(q[:, 0]).astype(np.int64)
    fy = np.floor(q[:, 1]).astype(np.int64)
    need = np.zeros(h * w, bool)
    for dy in range(3):
        for dx in range(3):
            need[np.clip(fy + dy, 0, h - 1) * w + np.clip(fx + dx, 0, w - 1)] = True
    pix = view.pixel_index // view.samples_per_pixel
    return view.take(np.flatnonzero(need[pix]))


def _projection_error(renderer, camera, texels, ref, field, area,
                      n_lights: int, gt_lights: int, weight_min: float,
                      stage_lights=None) -> dict[str, float]:
    """Error sums of projected vs exactly shaded samples for one camera (module docstring).

    ``field`` has ``texel_index``, ``weight`` and ``directory`` (the camera's folder of the
    ``project`` stage, :class:`facegeo.surface.reflectance.ProjectedField` or the files read
    back). Field light ``k`` is the true rig's light ``stage_lights[k]`` (default ``k``).

    Returns ``se``/``sr`` (Σ a_t err², Σ a_t ref², area-weighted), ``se_texel``/``sr_texel``
    (every texel counted once, the former metric), ``se_off``/``sr_off`` (area-weighted,
    samples off shadow edges), ``edge_samples``, ``samples`` — all over texels with weight
    above ``weight_min`` — and ``se_all``/``sr_all`` (area-weighted, every weighted texel).
    """
    from facegeo.surface.reflectance import frame_sampler, gather_field_samples, sample_frame
    from facegeo.synth.render import SurfaceView

    # Every weighted texel is compared; the headline sums keep those above weight_min (the
    # all-texel sums, se_all / sr_all, show what the threshold leaves out: grazing views and
    # the feathered bands at silhouettes and occlusion edges).
    keep = field.weight > 0
    sel = np.flatnonzero(keep)
    out = dict.fromkeys(("se", "sr", "se_texel", "sr_texel", "se_off", "sr_off",
                         "edge_samples", "samples", "se_all", "sr_all"), 0.0)
    if sel.size == 0:
        return out
    tex = field.texel_index[sel]
    p, face, n = ref.p[tex], ref.face[tex], ref.n[tex]
    rig = renderer.rig  # the true rig: the frames were rendered from its cameras
    true_cam = rig.camera(camera.name)
    # The generator's own shading normals (ref.n) and material at these points.
    v = true_cam.center_world[None, :] - p
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    mat = renderer.material_at(p, face)
    view = SurfaceView(true_cam.name, (1, sel.size), np.ones((1, sel.size), bool),
                       np.arange(sel.size), p, n, v, face,
                       np.asarray(mat.alpha_0, np.float32).reshape(-1, 3),
                       np.asarray(mat.alpha_1, np.float32).reshape(-1, 3),
                       np.asarray(mat.rho_s, np.float32).reshape(-1),
                       np.asarray(mat.roughness, np.float32).reshape(-1))
    # Shadow edges: samples whose bilinear taps mix pixels the generator lit and left dark
    # (its noiseless frame of the same light, from the pixel-centre view it rendered).
    # The taps are where the texel was sampled: its projection by the stage's camera.
    q = camera.project(texels.p_world[tex])[0]
    sampler = frame_sampler(q, camera.width, camera.height)
    pixels = _tap_pixels(renderer.surface_view(true_cam), q)
    lights = stratified_light_subset(n_lights, gt_lights)
    # The compared samples, in the stored dtype (bounded resident memory: the rows are read
    # a chunk at a time; at the paper preset 174 k texels × 128 lights × 3 float16, 134 MB).
    est_all = gather_field_samples(field.directory, sel, lights)
    a_all = np.asarray(area, np.float64)[tex]
    heavy = field.weight[sel] > weight_min
    a = np.where(heavy, a_all, 0.0)
    stage = np.arange(n_lights) if stage_lights is None else np.asarray(stage_lights)
    for k, l in enumerate(stage[lights]):
        r = renderer.shade_stage_light(view, rig.lights, int(l)).astype(np.float64)
        lit = renderer.shade_stage_light(pixels, rig.lights, int(l)).sum(axis=1) > 0
        lit_img = pixels.to_image(lit.astype(np.float32))
        mix = sample_frame(np.repeat(lit_img[..., None], 3, axis=2), sampler)[:, 0]
        est = est_all[:, k].astype(np.float64)
        ok = np.isfinite(est).all(axis=1)
        e2 = np.where(ok, ((est - r) ** 2).sum(axis=1), 0.0)
        r2 = np.where(ok, (r ** 2).sum(axis=1), 0.0)
        off = ok & ((mix <= 0.0) | (mix >= 1.0))
        out["se_all"] += float(a_all @ e2)
        out["sr_all"] += float(a_all @ r2)
        ok &= heavy
        off &= heavy
        out["se"] += float(a @ e2)
        out["sr"] += float(a @ r2)
        out["se_texel"] += float(e2[heavy].sum())
        out["sr_texel"] += float(r2[heavy].sum())
        out["se_off"] += float(a[off] @ e2[off])
        out["sr_off"] += float(a[off] @ r2[off])
        out["edge_samples"] += int(np.count_nonzero(ok & ~off))
        out["samples"] += int(np.count_nonzero(ok))
    return out


def _error_metrics(e: dict[str, float]) -> dict[str, Any]:
    """The ``projection_*`` metrics from the sums of :func:`_projection_error`."""
    def rel(se, sr):
        return round(float(np.sqrt(se / sr)), 6) if sr > 0 else None

    return {
        "projection_rel_rmse": rel(e["se"], e["sr"]),
        "projection_rel_rmse_per_texel": rel(e["se_texel"], e["sr_texel"]),
        "projection_rel_rmse_all_weights": rel(e.get("se_all", 0.0), e.get("sr_all", 0.0)),
        "projection_rel_rmse_off_shadow_edges": rel(e["se_off"], e["sr_off"]),
        "projection_shadow_edge_samples": (round(e["edge_samples"] / e["samples"], 6)
                                           if e["samples"] else None),
        "projection_shadow_edge_error_share": (round(1.0 - e["se_off"] / e["se"], 6)
                                               if e["se"] > 0 else None),
    }


def _camera_products(folder: Path, texels, camera):
    """One camera's projection as written (field rows, weights, occlusion decision)."""
    from facegeo.errors import InputError

    field = SimpleNamespace(directory=folder,
                            texel_index=np.load(folder / "texel_index.npy").astype(np.int64),
                            weight=np.load(folder / "weight.npy"))
    vis = None
    path = folder / VISIBILITY_FILE
    if path.is_file():
        with np.load(path) as z:
            if z["in_image"].shape != (len(texels),):
                raise InputError(f"evaluate: {path} holds {z['in_image'].shape[0]} texels, the "
                                 f"atlas {len(texels)}; rerun the project stage")
            vis = SimpleNamespace(in_image=z["in_image"], facing=z["facing"],
                                  unoccluded=z["unoccluded"],
                                  q=camera.project(texels.p_world)[0],
                                  depth_jump=float(z["depth_jump"]))
    return field, vis


def evaluate_projection(scan, out, *, gt_lights: int = GT_LIGHTS,
                        gt_weight_min: float = GT_WEIGHT_MIN, renderer=None) -> dict:
    """The ``project`` products in ``out`` against the generator's truth (module docstring).

    Parameters
    ----------
    scan : facegeo.capture.scan.Scan
        A synthetic scan (``ground_truth/`` with ``skin``, ``mesh``, ``rig``).
    out : path-like
        The folder holding ``atlas/`` and ``project/`` (the scan's ``out/``).
    gt_lights : int
        At most this many lights, a stratified subset (:data:`GT_LIGHTS`).
    gt_weight_min : float
        Texels with a projection weight above this enter the headline figures.
    renderer : facegeo.synth.render.ReferenceRenderer, optional
        The generator's truth already loaded (default: loaded from the scan).

    Returns
    -------
    dict
        ``cameras`` (per camera ``visibility_agreement``, ``visibility_compared``,
        ``visibility_compared_fraction``, the ``projection_*`` figures,
        ``seconds_projection_error``), ``visibility_agreement`` (the worst camera's), the
        ``projection_*`` figures over every camera, ``projection_weight_min``,
        ``projection_reference`` (+ ``projection_reference_offset_mm``), the gauge figures.
        Empty when the scan has no generator truth.
    """
    from facegeo.surface.atlas import Atlas, Texels

    gt_lights = check_positive_int(gt_lights, "gt_lights")
    out = Path(out)
    if not scan.synthetic:
        return {}
    the_rig, rig_used = stage_rig_product(out, "project")
    atlas = Atlas.load(out / "atlas" / "atlas.npz")
    texels = Texels.load(out / "atlas" / "texels.npz")
    truth = has_projection_truth(scan)
    ref = None
    gauge: dict[str, float] = {}
    if truth:
        if renderer is None:
            from facegeo.synth.render import load_ground_truth

            renderer = load_ground_truth(scan)
        T_true, gauge = truth_gauge(renderer, atlas, rig_used,
                                    skip=inferred_atlas_vertices(out, atlas))
        ref = renderer.texel_truth(atlas, texels, T_true=T_true)
        area = texel_areas(atlas, texels)
    names = [c.name for c in the_rig.cameras if has_field(out / "project" / c.name)]
    per_cam: dict[str, Any] = {}
    err_sums: dict[str, float] = {}
    for name in names:
        camera = the_rig.camera(name)
        field, vis = _camera_products(out / "project" / name, texels, camera)
        entry: dict[str, Any] = {}
        if vis is not None:
            agr = _visibility_agreement(scan, name, camera, texels, vis, vis.depth_jump)
            if agr is not None:
                entry["visibility_agreement"] = round(agr["agreement"], 6)
                entry["visibility_compared"] = agr["compared"]
                # what the comparison leaves out (silhouettes, depth jumps) is not hidden
                entry["visibility_compared_fraction"] = round(
                    agr["compared"] / max(agr["candidates"], 1), 6)
        if truth:
            t3 = time.perf_counter()
            e = _projection_error(renderer, camera, texels, ref, field, area, scan.n_lights,
                                  gt_lights, gt_weight_min)
            for k, x in e.items():
                err_sums[k] = err_sums.get(k, 0.0) + x
            entry.update(_error_metrics(e))
            entry["seconds_projection_error"] = round(time.perf_counter() - t3, 4)
        if entry:
            per_cam[name] = entry
    metrics: dict[str, Any] = {"cameras": per_cam} if per_cam else {}
    agrs = [c["visibility_agreement"] for c in per_cam.values()
            if "visibility_agreement" in c]
    if agrs:
        metrics["visibility_agreement"] = round(float(min(agrs)), 6)
    if truth and err_sums.get("sr", 0.0) > 0:
        metrics.update(_error_metrics(err_sums))
        metrics["projection_weight_min"] = gt_weight_min
        on_truth = not ref.offset.any()
        metrics["projection_reference"] = "texel" if on_truth else (
            "closest ground-truth point after the rigid gauge alignment" if gauge
            else "closest ground-truth point")
        metrics.update(gauge)
        if not on_truth:
            metrics["projection_reference_offset_mm"] = round(
                float(np.sqrt(area @ ref.offset ** 2 / area.sum())) * 1e3, 6)
    return metrics


def with_projection_figures(scan, out, metrics: dict, **settings) -> dict:
    """The ``project`` stage's ``metrics`` with :func:`evaluate_projection`'s figures beside
    them (per camera and overall): what ``facegeo project`` and
    :func:`facegeo.pipeline.project.run_project` show. ``settings``: ``gt_lights``,
    ``gt_weight_min``."""
    figures = evaluate_projection(scan, out, **settings)
    merged = {**metrics, "cameras": {k: dict(v) for k, v in metrics.get("cameras", {}).items()}}
    for name, entry in figures.pop("cameras", {}).items():
        merged["cameras"].setdefault(name, {}).update(entry)
    merged.update(figures)
    return merged
