"""Rendered novel views against the generator's reference of the same camera (synthetic scans).

Reads one view of the ``render`` stage (``out/render/`` or ``facegeo render``'s ``out/views/``)
by its stem: ``<stem>.json`` (the view's metrics: ``rig``, ``supersample``, ``exposure``),
``<stem>_camera.json`` (the camera it was rendered from), ``<stem>_weights.npy`` (the Eq. (4)
field weights of the environment, ``(L, 3)`` float64), ``<stem>.exr`` (the render),
``<stem>_covered.png`` (255 where the render's pixel was rendered from measured texels) and,
when the stage made them, ``<stem>_naive.exr``, ``<stem>_texture.exr``,
``<stem>_naive_texture.exr`` (the texture-space renders before the image-space detail) and
``<stem>_paper.exr`` (the paper's resynthesis as written, λ = 1). It writes
``<stem>_reference.exr/.png``, ``<stem>_reference_mask.png`` (255 where the reference sees
the head), ``<stem>_seen.png`` (:func:`seen_fraction` × 255) and ``<stem>_error.png`` into
the folder it is given.

Metrics against the generator's reference (same camera, same Eq. (4) weights, its exact
renderer integrating the render's own pixel footprint, ``reference_supersample``;
``mask`` = the reference's pixels that see the head):

* ``psnr_db`` = 10 log10(peak² / MSE), MSE over the mask's pixels and channels, peak = the
  reference's maximum over the mask; ``rel_rmse`` = sqrt(Σ err² / Σ ref²) over the mask;
* the same for the naive baseline (``naive_psnr_db``, ``naive_rel_rmse``) and the gain
  ``psnr_gain_db`` (``psnr_gain_db_covered`` over covered pixels);
* ``paper_psnr_db`` (``_covered``), ``paper_rel_rmse`` (``_covered``) for the paper's λ = 1;
* ``head_coverage``: the fraction of the reference's head mask rendered from measured texels;
  ``black_head_pixels``: the mask's pixels the render left black (0 in every channel);
  ``outside_head_pixels``: pixels outside the mask the render drew (not black), and
  ``silhouette_iou``: the render's drawn pixels against the mask, intersection over union —
  what the figures over the mask do not see, a surface grown past the head;
  the ``*_covered`` variants of PSNR / relative RMSE over covered pixels only;
* with image-space detail: ``texture_*`` and ``texture_naive_*``, the same figures of the
  texture-space renders;
* against the generator's reference, what the capture could have shown (the co-visibility
  mask of novel-view benchmarks, Gao et al. 2022, "Monocular Dynamic View Synthesis: A
  Reality Check", §4: a view's pixels no training view saw are no test of a method):
  :func:`seen_fraction` of each pixel, the share of its reference rays whose true surface
  point some source camera (a camera with OLAT frames) sees — facing it, in its image, not
  occluded; ``seen_pixels`` (every ray seen) and ``unseen_head_pixels`` (none), the gain
  ``psnr_gain_db_seen`` (``psnr_db_seen``, ``naive_psnr_db_seen``) over the seen pixels, and
  ``unseen_error_share`` (the render's squared error over the mask on unseen pixels);
* with a rig other than the true one, the reference is rendered from the camera moved into the
  generator's frame by the gauge alignment of the atlas mesh
  (:func:`facegeo.evaluate.gauge.truth_gauge`; ``gauge_rotation_deg`` /
  ``gauge_translation_mm``).

A real scan's reference images — a witness camera photographed under a known environment —
are ``[reference] images.<camera>.<env> = "reference/…"`` entries (a linear ``.exr`` or
``.hdr`` of the camera's size; ``<env>`` the environment as the view names it: a built-in
name, or a map file's stem): a view of that camera under that environment is compared with it
by :func:`evaluate_view_against_image`, the same figures over the pixels where the reference
is finite and not black (``mask``; the reference's own extent, without a head mask); on a
synthetic scan whose generator wrote that image (its witness camera's) also the seen figures.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.errors import InputError
from facegeo.evaluate.gauge import inferred_atlas_vertices, truth_gauge

__all__ = ["evaluate_view", "evaluate_view_against_image", "has_view_reference",
           "image_metrics", "reference_image_key", "render_gain", "seen_fraction",
           "view_figures", "views_summary"]


def has_view_reference(scan) -> bool:
    """Whether the scan carries the generator's truth a view is compared with."""
    return bool(scan.synthetic and "skin" in scan.ground_truth_keys)


def image_metrics(img, ref, mask) -> dict:
    """PSNR (dB, peak = max of ``ref`` over ``mask``) and relative RMSE over ``mask``.

    Parameters
    ----------
    img, ref : (H, W, 3) float32, linear radiance
    mask : (H, W) bool
    """
    m = np.asarray(mask, bool)
    if not m.any():
        return {"psnr_db": None, "rel_rmse": None, "pixels": 0}
    e = img[m].astype(np.float64) - ref[m]
    mse = float((e ** 2).mean())
    peak = float(ref[m].max())
    den = float((ref[m].astype(np.float64) ** 2).sum())
    psnr = 10.0 * math.log10(peak ** 2 / mse) if mse > 0 and peak > 0 else math.inf
    return {"psnr_db": round(psnr, 4) if math.isfinite(psnr) else None,
            "rel_rmse": round(math.sqrt(float((e ** 2).sum()) / den), 6) if den > 0 else None,
            "pixels": int(m.sum())}


def render_gain(image, naive, ref, head_mask, covered) -> dict:
    """What a render gains over the naive baseline against a reference, in image space: the
    criterion of issue 37 ("tests that fail when the render is wrong").

    Parameters
    ----------
    image, naive, ref : (H, W, 3) float32, linear radiance — the render, the naive baseline
        and the reference of the same camera and environment
    head_mask : (H, W) bool — the reference's pixels that see the head
    covered : (H, W) bool — the render's pixels rendered from measured texels

    Returns
    -------
    dict
        ``gain_covered_db``: PSNR(image) − PSNR(naive) over ``head_mask & covered``;
        ``gain_head_db``: the same over ``head_mask``; ``black_head_pixels``: pixels of
        ``head_mask`` where ``image`` is 0 (or not finite) in every channel. A PSNR is
        ``image_metrics``'s (peak = the reference's maximum over the pixels); a gain is None
        when a mask is empty or a PSNR infinite.
    """
    image, naive, ref = (np.asarray(a, np.float32) for a in (image, naive, ref))
    head = np.asarray(head_mask, bool)
    cov = head & np.asarray(covered, bool)

    def gain(mask):
        a, b = image_metrics(image, ref, mask), image_metrics(naive, ref, mask)
        if a["psnr_db"] is None or b["psnr_db"] is None:
            return None
        return round(a["psnr_db"] - b["psnr_db"], 4)

    dark = ~(np.isfinite(image) & (image > 0)).any(axis=2)
    return {"gain_covered_db": gain(cov), "gain_head_db": gain(head),
            "black_head_pixels": int((head & dark).sum())}


def seen_fraction(view, scene, cameras) -> np.ndarray:
    """Of each pixel's rays on the surface, the share whose surface point some camera of
    ``cameras`` sees.

    A point is seen by a camera when its normal faces the camera's centre, it projects inside
    the camera's image, and the segment to the centre is free of faces (``scene``'s
    :meth:`~facegeo.surface.visibility.RayScene.segment_visible`, lifted off the surface along
    the normal). With the generator's surface and true source cameras, a pixel of 0 shows
    surface no capture camera recorded: no reconstruction from the capture measures its shape
    or its reflectance (the co-visibility mask of Gao et al. 2022, §4).

    Parameters
    ----------
    view : facegeo.synth.render.SurfaceView — a camera's rays on the surface (the reference's)
    scene : facegeo.surface.visibility.RayScene — of the same surface
    cameras : sequence of facegeo.geometry.camera.Camera, in the surface's frame

    Returns
    -------
    (H, W) float32 in [0, 1] — 0 also off the surface
    """
    p, n = view.p_world, view.n_world
    seen = np.zeros(len(p), bool)
    for cam in cameras:
        c = np.asarray(cam.center_world, np.float64).reshape(3)
        todo = np.flatnonzero(~seen & (np.einsum("ij,ij->i", c - p, n) > 0))
        if not todo.size:
            continue
        q, ok = cam.project(p[todo])
        inside = ok & cam.in_image(q)
        todo = todo[inside]
        if todo.size:
            seen[todo] = scene.segment_visible(p[todo], c[None, :], normals=n[todo])
    hit = view.to_image(np.ones(len(p), np.float32))
    return np.where(hit > 0, view.to_image(seen.astype(np.float32)) / np.maximum(hit, 1e-30),
                    np.float32(0.0)).astype(np.float32)


def _error_heatmap(img, ref, mask) -> np.ndarray:
    import cv2

    err = np.linalg.norm(img.astype(np.float64) - ref, axis=2)
    top = float(np.percentile(np.linalg.norm(ref[mask], axis=1), 99)) if mask.any() else 1.0
    g = np.clip(err / max(0.25 * top, 1e-12), 0, 1)
    bgr = cv2.applyColorMap((g * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
    return np.where(mask[..., None], bgr[..., ::-1], 0).astype(np.uint8)


def _read_view(folder: Path, stem: str) -> dict:
    """The files of one rendered view (module docstring); missing optional ones are None."""
    from facegeo.capture import imageio
    from facegeo.geometry.camera import Camera

    need = [folder / f"{stem}.json", folder / f"{stem}_camera.json",
            folder / f"{stem}_weights.npy", folder / f"{stem}.exr", folder / f"{stem}_covered.png"]
    missing = [p.name for p in need if not p.is_file()]
    if missing:
        raise InputError(f"evaluate: view {stem!r} in {folder} lacks {', '.join(missing)} "
                         "(rendered before the views recorded them?); render it again")
    meta = json.loads(need[0].read_text(encoding="utf-8"))
    cam = Camera.from_dict(json.loads(need[1].read_text(encoding="utf-8")),
                           where=str(need[1]))

    def image(suffix):
        p = folder / f"{stem}{suffix}.exr"
        return imageio.read_image(p).astype(np.float32) if p.is_file() else None

    return {"meta": meta, "camera": cam, "weights": np.load(need[2]),
            "image": image(""), "naive": image("_naive"), "texture": image("_texture"),
            "naive_texture": image("_naive_texture"), "paper": image("_paper"),
            "covered": imageio.read_image(need[4]) > 0}


def evaluate_view(scan, out, views_dir, stem: str, dest, *, renderer=None) -> dict:
    """One rendered view against the generator's reference (module docstring).

    Parameters
    ----------
    scan : facegeo.capture.scan.Scan
        A synthetic scan (:func:`has_view_reference`).
    out : path-like
        The folder holding ``atlas/`` (the gauge alignment's mesh).
    views_dir : path-like
        The folder holding the view's files.
    stem : str
        The view's file stem (its ``name``).
    dest : path-like
        Where the reference and the error heat map are written.
    renderer : facegeo.synth.render.ReferenceRenderer, optional
        The generator's truth already loaded (default: loaded from the scan).

    Returns
    -------
    dict
        The figures (module docstring), ``seconds_reference``, ``reference_supersample``,
        ``files`` (``reference_png``, ``error_png``, relative to ``dest``).
    """
    from facegeo.capture import imageio
    from facegeo.capture.response import encode

    views_dir, dest = Path(views_dir), Path(dest)
    v = _read_view(views_dir, stem)
    meta = v["meta"]
    supersample = int(meta.get("supersample", 1))
    t0 = time.perf_counter()
    if renderer is None:
        from facegeo.synth.render import load_ground_truth

        renderer = load_ground_truth(scan)
    ref_camera, gauge = _truth_camera(renderer, out, v)
    metrics: dict[str, Any] = dict(gauge)
    # the reference integrates the render's own pixel footprint (s × s box): a point
    # sample of a hard shadow edge is not what a camera records, and comparing pixel
    # centres with a box-filtered render (or the reverse) would measure the sampling
    ref = renderer.render_lights(ref_camera, renderer.rig.lights, v["weights"],
                                 supersample=supersample)
    sv = renderer.surface_view(ref_camera, supersample=supersample)
    mask = sv.mask
    seen = _seen_by_sources(scan, renderer, sv)
    metrics["seconds_reference"] = round(time.perf_counter() - t0, 4)
    metrics["reference_supersample"] = supersample
    dest.mkdir(parents=True, exist_ok=True)
    imageio.write_image(dest / f"{stem}_reference.exr", ref)
    imageio.write_image(dest / f"{stem}_reference_mask.png",
                        np.where(mask, 255, 0).astype(np.uint8))
    exposure = np.float32(meta.get("exposure", 1.0))
    files = {"seen_png": imageio.write_image(
        dest / f"{stem}_seen.png", np.round(seen * 255).astype(np.uint8)).name,
        "reference_png": imageio.write_image(
        dest / f"{stem}_reference.png",
        encode(np.clip(ref * exposure, 0.0, 1.0), "srgb", np.uint8)).name,
        "error_png": imageio.write_image(dest / f"{stem}_error.png",
                                         _error_heatmap(v["image"], ref, mask)).name}
    metrics.update(view_figures(v, ref, mask, head_mask=True, seen=seen))
    metrics["files"] = files
    return metrics


def _truth_camera(renderer, out, v: dict):
    """The view's camera in the generator's frame (moved by the gauge alignment of the atlas
    mesh when the rig is not the true one) and the alignment's figures."""
    from facegeo.surface.atlas import Atlas

    atlas = Atlas.load(Path(out) / "atlas" / "atlas.npz")
    T_true, gauge = truth_gauge(renderer, atlas, v["meta"].get("rig"),
                                skip=inferred_atlas_vertices(out, atlas))
    camera = v["camera"]
    if T_true is not None:
        camera = dataclasses.replace(camera, T_cam_world=camera.T_cam_world @ T_true.inverse())
    return camera, gauge


def _seen_by_sources(scan, renderer, view) -> np.ndarray:
    """:func:`seen_fraction` of a view's rays on the generator's surface, by the scan's source
    cameras (those with OLAT frames) at their true poses."""
    sources = set(scan.cameras_with_frames("olat"))
    return seen_fraction(view, renderer.rays,
                         [c for c in renderer.rig.cameras if c.name in sources])


def view_figures(v: dict, ref, mask, *, head_mask: bool = False, seen=None) -> dict:
    """The figures of a view's renders ``v`` (:func:`_read_view`) against a reference image
    ``ref`` ``(H, W, 3)`` over the pixels ``mask`` ``(H, W)`` (module docstring). With
    ``head_mask`` (``mask`` is where the reference sees the head, not merely where it is
    non-black) also ``outside_head_pixels`` and ``silhouette_iou``; with ``seen``
    (:func:`seen_fraction` ``(H, W)``) the seen and unseen figures."""
    metrics: dict[str, Any] = {}
    cov = mask & v["covered"]
    # of the head the generator sees from this camera, the part rendered from measured
    # texels (`coverage` counts against the render's own surface, which lacks whatever the
    # reconstruction lacks: a camera-camera mesh ends where one camera stopped decoding)
    metrics["head_coverage"] = round(float(cov.sum() / max(mask.sum(), 1)), 6)

    def figures(prefix, image):
        """``{prefix}psnr_db``, ``rel_rmse`` and their ``_covered`` forms; the two PSNRs."""
        a, c = image_metrics(image, ref, mask), image_metrics(image, ref, cov)
        metrics.update({f"{prefix}psnr_db": a["psnr_db"], f"{prefix}rel_rmse": a["rel_rmse"],
                        f"{prefix}psnr_db_covered": c["psnr_db"],
                        f"{prefix}rel_rmse_covered": c["rel_rmse"]})
        return a, c

    m, mc = figures("", v["image"])
    metrics["mask_pixels"] = m["pixels"]
    # a render that leaves seen head black (surface no camera saw, without infer)
    drawn = (np.isfinite(v["image"]) & (v["image"] > 0)).any(axis=2)
    metrics["black_head_pixels"] = int((mask & ~drawn).sum())
    if head_mask:  # surface drawn where the reference sees none: the figures over the mask
        # cannot see a surface grown outward, which only ever covers black pixels
        metrics["outside_head_pixels"] = int((~mask & drawn).sum())
        metrics["silhouette_iou"] = round(float((mask & drawn).sum()
                                                / max(int((mask | drawn).sum()), 1)), 6)
    if v["texture"] is not None:  # the texture-space figures (the paper's render path)
        figures("texture_", v["texture"])
    if v["naive"] is not None:
        nm, nc = figures("naive_", v["naive"])
        if v["naive_texture"] is not None:
            figures("texture_naive_", v["naive_texture"])
        if m["psnr_db"] is not None and nm["psnr_db"] is not None:
            metrics["psnr_gain_db"] = round(m["psnr_db"] - nm["psnr_db"], 4)
        if mc["psnr_db"] is not None and nc["psnr_db"] is not None:
            metrics["psnr_gain_db_covered"] = round(mc["psnr_db"] - nc["psnr_db"], 4)
    if v["paper"] is not None:
        figures("paper_", v["paper"])
    if seen is not None:
        metrics.update(_seen_figures(v, ref, mask, np.asarray(seen, np.float32)))
    return metrics


def _seen_figures(v: dict, ref, mask, seen) -> dict:
    """``seen_pixels``, ``unseen_head_pixels``, ``unseen_error_share``, ``psnr_db_seen``,
    ``naive_psnr_db_seen`` and ``psnr_gain_db_seen`` (module docstring)."""
    whole, none = mask & (seen >= 1.0), mask & (seen <= 0.0)
    err = ((v["image"].astype(np.float64) - ref) ** 2).sum(axis=2)
    total = float(err[mask].sum())
    out: dict[str, Any] = {
        "seen_pixels": int(whole.sum()), "unseen_head_pixels": int(none.sum()),
        "unseen_error_share": round(float(err[none].sum()) / total, 6) if total > 0 else None}
    a = image_metrics(v["image"], ref, whole)
    out["psnr_db_seen"] = a["psnr_db"]
    if v["naive"] is not None:
        b = image_metrics(v["naive"], ref, whole)
        out["naive_psnr_db_seen"] = b["psnr_db"]
        if a["psnr_db"] is not None and b["psnr_db"] is not None:
            out["psnr_gain_db_seen"] = round(a["psnr_db"] - b["psnr_db"], 4)
    return out


def reference_image_key(camera: str, env: str) -> str:
    """The ``[reference]`` key of a reference image of ``camera`` under ``env``: a built-in
    environment's name or a map file's stem (the render's ``env`` as it recorded it)."""
    return f"images.{camera}.{Path(str(env)).stem}"


def evaluate_view_against_image(scan, views_dir, stem: str, *, out=None,
                                 renderer=None) -> dict | None:
    """One rendered view against the scan's reference image of its camera and environment
    (module docstring); None when the scan has none for it.

    With the generator's truth (``renderer``, and ``out`` holding ``atlas/``: a synthetic
    scan whose generator wrote the reference image, such as its witness camera's) also the
    seen figures, the view's camera moved into the generator's frame as :func:`evaluate_view`
    moves it.
    """
    from facegeo.capture import imageio

    v = _read_view(Path(views_dir), stem)
    key = reference_image_key(v["camera"].name, v["meta"].get("env", ""))
    if key not in scan.reference_keys:
        return None
    path = scan.reference_path(key)
    ref = np.asarray(imageio.read_image(path), np.float32)
    if ref.ndim == 2:
        ref = np.repeat(ref[..., None], 3, axis=2)
    if ref.shape[:2] != v["image"].shape[:2] or ref.shape[2] < 3:
        raise InputError(f"[reference] {key}: {path} is {ref.shape[1]} x {ref.shape[0]} with "
                         f"{ref.shape[2]} channel(s); the view {stem!r} is "
                         f"{v['image'].shape[1]} x {v['image'].shape[0]} RGB")
    ref = ref[..., :3]
    mask = np.isfinite(ref).all(axis=2) & (ref.max(axis=2) > 0)
    seen = None
    if renderer is not None and out is not None:
        camera, _ = _truth_camera(renderer, out, v)
        view = renderer.surface_view(camera, supersample=int(v["meta"].get("supersample", 1)))
        seen = _seen_by_sources(scan, renderer, view)
    return {"reference": f"{key} ({path.name})",
            **view_figures(v, np.nan_to_num(ref), mask, seen=seen)}


def views_summary(per_view: dict) -> dict:
    """The figures over several views: ``psnr_db_min`` / ``_mean``, ``naive_psnr_db_mean``,
    ``psnr_gain_db_min``, ``psnr_gain_db_covered_min``, ``paper_psnr_db_mean``,
    ``silhouette_iou_min``, ``psnr_gain_db_seen_min`` (each over the views that have it)."""
    def values(key):
        return [v[key] for v in per_view.values() if v.get(key) is not None]

    metrics: dict[str, Any] = {}
    psnr, naive = values("psnr_db"), values("naive_psnr_db")
    gain, gain_cov = values("psnr_gain_db"), values("psnr_gain_db_covered")
    if psnr:
        metrics["psnr_db_min"] = round(min(psnr), 4)
        metrics["psnr_db_mean"] = round(float(np.mean(psnr)), 4)
    if naive:
        metrics["naive_psnr_db_mean"] = round(float(np.mean(naive)), 4)
    if gain:
        metrics["psnr_gain_db_min"] = round(min(gain), 4)
    if gain_cov:
        metrics["psnr_gain_db_covered_min"] = round(min(gain_cov), 4)
    paper = values("paper_psnr_db")
    if paper:
        metrics["paper_psnr_db_mean"] = round(float(np.mean(paper)), 4)
    iou = values("silhouette_iou")
    if iou:
        metrics["silhouette_iou_min"] = round(min(iou), 6)
    gain_seen = values("psnr_gain_db_seen")
    if gain_seen:
        metrics["psnr_gain_db_seen_min"] = round(min(gain_seen), 4)
    return metrics
