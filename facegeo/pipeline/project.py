"""Pipeline stages ``atlas`` and ``project``: the surface reflectance field of a scan on disk.

``run_atlas(scan_dir, out_dir)`` parameterises the scan's mesh and writes ``out_dir/atlas/``:

    mesh_uv.obj, mesh_uv.mtl, mesh_uv.glb   the mesh with UVs (docs/surface.md)
    atlas.npz                              facegeo.surface.atlas.Atlas
    texels.npz                             facegeo.surface.atlas.Texels (index map rebuilt on load)
    stage.json                             settings and metrics

``run_project(scan_dir, out_dir)`` reads ``out_dir/atlas/`` (running the atlas stage first when
it is missing) and writes ``out_dir/project/``:

    <camera>/R.npy            (T_c, L, 3) float16, chunked along texels (memory-mapped)
    <camera>/texel_index.npy  (T_c,) int64; weight.npy (T_c,) float32; v_world.npy (T_c, 3)
    seen.npy                  (T,) bool: some camera has a non-zero weight
    blended/R_blend.npy       (U, L, 3) float16: Σ_c w_c R_c / Σ_c w_c per texel, for
                              fixed-viewpoint uses (facegeo.surface.reflectance.blend_fields);
    blended/texel_index.npy   (U,) int64; weight.npy (U,) float32 Σ_c w_c; n_cameras.npy (U,)
                              (read with facegeo.surface.reflectance.open_blended)
    preview.png               the mean over lights, blended over cameras, pull–push filled
                              (display only: unseen texels are never counted as measured)
    atlas.sha256              SHA-256 of the atlas's texels.npz the fields index: readers
                              refuse a projection onto another atlas (check_projection_atlas)
    stage.json

Each stage writes into a temporary sibling folder that replaces the old one only when complete,
and records its metrics in ``out_dir/metrics.json`` under ``"atlas"`` / ``"project"``.

Mesh: the synthetic scan's ground-truth mesh (``mesh="ground_truth"``) or a mesh file
(``mesh=<path>``, e.g. the ``mesh`` stage's ``out/mesh/mesh.ply``; ``facegeo reconstruct``
chooses, see :mod:`facegeo.pipeline.reconstruct`).
Rig: ``rig="ground_truth"`` (default when the scan has one) uses the true rig the frames were
rendered with — so the accuracy figures measure the projection, not a rig's error;
``rig="calibrated"`` the ``calibrate`` stage's rig (the chain end to end), ``rig="scan"`` the
scan's (nominal) ``rig.json``, or a rig file.
Shadow-consistent taps (``shadow_taps=True``, the default): where a sample's bilinear taps
straddle a cast-shadow edge, the atlas mesh and the rig's lights decide which taps share the
texel's side and only those are read (:mod:`facegeo.surface.shadows`); per camera
``shadow_edge_samples`` (fraction re-interpolated) and ``seconds_shadow_taps`` (their part of
``seconds_projection``). The rig's lights must be in its world frame (a calibrated rig's are
the scan's nominal ones: its gauge, ≈ 0.2° and 3.6 mm on the small preset, moves a shadow edge
on the skin by ≈ 0.1 mm); wrong light positions pick the wrong side of an edge.

Ground-truth metrics (synthetic scans):

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
  (:func:`texel_areas`; so the figure is a mean over the surface, not over however the atlas
  samples it). ``R_ref`` is the generator's exact shading (true rig; the same normals,
  material — ``material_at``, part materials included — and shadow rays as its frames) of the
  texel's surface point from the same camera. The texel's point is itself on the ground-truth
  mesh; on any other mesh (a reconstruction) it is the closest point of the ground-truth
  surface (``projection_reference``, with the area-weighted RMS distance
  ``projection_reference_offset_mm``), so a misplaced surface shows up as misregistration.
  With any rig but the true one, the mesh is first brought onto the true surface by the best
  rigid transform (:func:`truth_gauge`: that rig's world frame is its own gauge;
  ``gauge_rotation_deg`` / ``gauge_translation_mm`` say how far it moved), so the figure
  measures the reflectance field, not where the rig put the world's origin.
  Masked (NaN) samples are left out. Beside it, for comparison and diagnosis:
  ``projection_rel_rmse_per_texel`` (every texel counted once, the metric before area
  weighting), ``projection_rel_rmse_all_weights`` (area-weighted over every texel the camera
  weights at all: the grazing views and the feathered bands at silhouettes and occlusion edges
  that the threshold leaves out), ``projection_rel_rmse_off_shadow_edges`` (area-weighted,
  only samples whose four bilinear taps are all lit or all dark in the generator's noiseless
  frame),
  ``projection_shadow_edge_samples`` (the fraction of compared samples that straddle such an
  edge) and ``projection_shadow_edge_error_share`` (their share of Σ a_t err²). Each camera's
  entry has the same keys.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.errors import InputError
from facegeo.frames import stratified_light_subset
from facegeo.fsutil import READ_AHEAD_WORKERS, atomic_write_text, file_sha256, staged_directory
from facegeo.pipeline.bench import peak_rss_mb
from facegeo.surface.atlas import DEFAULT_SPLIT_FACES
from facegeo.checks import check_positive_int, fmt_value

log = logging.getLogger(__name__)

__all__ = ["run_atlas", "run_project", "atlas_products", "project_products", "load_mesh",
           "peak_rss_mb", "stage_rig", "STAGE_RIGS", "texel_areas"]

_GT_DEPTH_TOL_M = 1e-3


def _scan(scan_dir):
    from facegeo.capture.scan import Scan, load_scan

    return scan_dir if isinstance(scan_dir, Scan) else load_scan(scan_dir)


def load_mesh(scan, mesh: str = "ground_truth") -> tuple[np.ndarray, np.ndarray, str]:
    """Vertices ``(V, 3)`` float64 (metres, world frame), faces ``(F, 3)`` and a description.

    ``mesh`` is ``"ground_truth"`` (a synthetic scan's ``ground_truth/mesh.ply``) or a path to a
    mesh file in metres (PLY/OBJ/GLB, loaded with ``process=False``).
    """
    import trimesh

    if mesh == "ground_truth":
        if "mesh" not in scan.ground_truth_keys:
            raise InputError(
                f"scan {scan.root}: no ground-truth mesh; pass mesh=<path to a mesh file in "
                f"metres> (facegeo reconstruct --mesh reconstructed builds one from the "
                f"structured light)")
        path = scan.ground_truth_path("mesh")
        import trimesh.exchange.ply

        with open(path, "rb") as fh:
            data = trimesh.exchange.ply.load_ply(fh)
        return (np.asarray(data["vertices"], np.float64), np.asarray(data["faces"], np.int64),
                f"ground truth ({path.name})")
    path = Path(mesh)
    if not path.is_file():
        raise InputError(f"mesh: {path} is not a file")
    try:
        m = trimesh.load(path, process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for unknown or unreadable files
        raise InputError(f"mesh: cannot read {path} as a mesh (PLY, OBJ, GLB, STL, OFF): "
                         f"{type(exc).__name__}: {exc}") from exc
    if len(getattr(m, "faces", ())) == 0:  # a point cloud, a scene without triangles
        raise InputError(f"mesh: {path} holds no triangles (read a {type(m).__name__} with "
                         f"{len(getattr(m, 'vertices', ()))} vertices)")
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64), str(path)


#: File in the ``project`` folder naming the atlas its fields index (SHA-256 of texels.npz).
ATLAS_FINGERPRINT = "atlas.sha256"


def check_projection_atlas(project_dir, texels_path) -> None:
    """Raise an InputError when the fields in ``project_dir`` were projected onto another
    atlas than ``texels_path`` (``texel_index.npy`` would index the wrong texels: an atlas
    rebuilt with other settings after the projection). Projections written before the
    fingerprint was recorded are not checked (their index ranges still are, by the readers)."""
    f = Path(project_dir) / ATLAS_FINGERPRINT
    if not f.is_file():
        return
    if f.read_text(encoding="utf-8").strip() != file_sha256(texels_path):
        raise InputError(f"{project_dir} was projected onto another atlas than {texels_path} "
                         f"(the atlas was rebuilt after the projection); re-run 'facegeo "
                         f"project' (or 'facegeo reconstruct') so the fields index this atlas")


def _record(out_dir: Path, stage_dir: Path, name: str, settings: dict, metrics: dict) -> None:
    from facegeo.pipeline.cache import record_metrics

    atomic_write_text(stage_dir / "stage.json", json.dumps(
        {"stage": name, "settings": settings, "metrics": metrics}, indent=2, sort_keys=True))
    record_metrics(out_dir, name, metrics)


def atlas_products(scan, dest: Path, *, mesh: str, texels_per_mm: float | None,
                    size: int | None, padding: int, split_faces: int | None,
                    repair: bool) -> dict:
    from facegeo.surface.atlas import build_atlas, export_mesh_uv, rasterize_texels

    t0 = time.perf_counter()
    V, F, what = load_mesh(scan, mesh)
    atlas = build_atlas(V, F, texels_per_mm=texels_per_mm, size=size, padding=padding,
                        split_faces=split_faces, repair=repair)
    t1 = time.perf_counter()
    texels = rasterize_texels(atlas)
    t2 = time.perf_counter()
    atlas.save(dest / "atlas.npz")
    texels.save(dest / "texels.npz")
    export_mesh_uv(atlas, dest / "mesh_uv.obj")
    export_mesh_uv(atlas, dest / "mesh_uv.glb")
    return {
        "mesh": what, "faces": int(len(F)), "vertices": int(len(V)),
        "dropped_degenerate": int(atlas.report.degenerate_faces.size),
        "dropped_nonmanifold": int(atlas.report.nonmanifold_faces.size),
        "pieces": atlas.n_pieces, "charts": atlas.n_charts,
        "utilization": round(atlas.meta.get("utilization", float("nan")), 4),
        "width": atlas.width, "height": atlas.height,
        "texels_per_mm": round(atlas.texels_per_metre / 1000.0, 6),
        "texels": int(len(texels)),
        "texel_fill": round(len(texels) / (atlas.width * atlas.height), 4),
        "seconds_xatlas": round(atlas.seconds, 4),
        "seconds_parameterise": round(t1 - t0, 4),
        "seconds_rasterise": round(t2 - t1, 4),
        "seconds": round(time.perf_counter() - t0, 4),
        "peak_rss_mb": round(peak_rss_mb(), 1),
    }


def run_atlas(scan_dir, out_dir=None, *, mesh: str = "ground_truth",
              texels_per_mm: float | None = 1.0, size: int | None = None, padding: int = 2,
              split_faces: int | None = DEFAULT_SPLIT_FACES, repair: bool = False) -> dict:
    """Build the atlas and texel table of a scan's mesh into ``out_dir/atlas/``.

    Parameters
    ----------
    scan_dir : path-like or Scan
    out_dir : path-like, optional
        Default the scan's ``out/``.
    mesh : str
        ``"ground_truth"`` or a mesh file (metres).
    texels_per_mm, size, padding, split_faces, repair
        See :func:`facegeo.surface.atlas.build_atlas` (give ``size`` with
        ``texels_per_mm=None``).

    Returns
    -------
    dict
        Metrics: ``texels``, atlas size, charts, ``seconds`` (and its parts), ``peak_rss_mb``.
    """
    scan = _scan(scan_dir)
    out = Path(out_dir) if out_dir is not None else scan.out_dir
    settings = {"mesh": mesh, "texels_per_mm": texels_per_mm, "size": size,
                "padding": padding, "split_faces": split_faces, "repair": repair}
    with staged_directory(out / "atlas") as tmp:
        metrics = atlas_products(scan, tmp, **settings)
        _record(out, tmp, "atlas", settings, metrics)
    return metrics


#: Rig choices of the stages after calibration (``rig=``); a rig file's path is accepted too.
STAGE_RIGS = ("ground_truth", "scan", "calibrated")


def stage_rig(scan, rig: str | None):
    """The rig a stage works with, and its name for the metrics.

    ``"ground_truth"`` — a synthetic scan's true rig (the default when there is one);
    ``"scan"`` — the scan's own ``rig.json`` (the nominal rig; the default otherwise);
    ``"calibrated"`` — ``out/calibrate/rig.json`` written by ``facegeo calibrate``;
    any other string — a rig file (``facegeo-rig`` JSON), e.g. another calibration's.
    """
    from facegeo.geometry.rig import Rig

    has_gt = scan.synthetic and "rig" in scan.ground_truth_keys
    if rig is None:
        rig = "ground_truth" if has_gt else "scan"
    if rig == "ground_truth":
        if not has_gt:
            raise InputError(f"rig: scan {scan.root} has no ground-truth rig; use rig='scan' or "
                             "'calibrated'")
        return Rig.load(scan.ground_truth_path("rig")), rig
    if rig == "scan":
        return scan.rig, rig
    path = scan.out_dir / "calibrate" / "rig.json" if rig == "calibrated" else Path(rig)
    if not path.is_file():
        if rig == "calibrated":
            raise InputError(f"rig 'calibrated': {path} does not exist; run `facegeo calibrate "
                             f"{scan.root}` first")
        raise InputError(f"rig: expected one of {', '.join(STAGE_RIGS)} or a rig file, got "
                         f"{fmt_value(rig)} (no such file)")
    the_rig = Rig.load(path)
    missing = [n for n in scan.camera_names if n not in the_rig.camera_names]
    if missing:
        raise InputError(f"rig {path}: lacks the scan's camera(s) {', '.join(missing)}")
    return the_rig, rig


def truth_gauge(renderer, atlas, rig_used: str) -> tuple[Any, dict]:
    """Where a stage's texels meet the generator's truth: ``(T_true_world, metrics)``.

    With the true rig (``rig_used == "ground_truth"``) the stage's world frame is the
    generator's: ``(None, {})``. With any other rig (a calibration's, the nominal
    ``rig.json``, a rig file) the world frame is that rig's gauge choice, so the atlas mesh is
    first brought onto the true surface by the best rigid transform
    (:meth:`facegeo.synth.render.ReferenceRenderer.gauge_alignment`, geometry only) — the
    ``mesh`` stage's ``after_rigid_alignment`` figures do the same — and the metrics say how
    far that was (``gauge_rotation_deg``, ``gauge_translation_mm``). Shared by the
    ``project``, ``fit`` and ``render`` stages' ground-truth comparisons. Without it a
    calibrated rig's 0.2° / 3.5 mm frame offset (small preset, seed 0) read as a
    ``projection_rel_rmse`` of 12.0 % where the aligned figure is 3.0 % (true rig: 3.1 %; both
    plain bilinear, before the shadow-consistent taps).
    The alignment (≈ 1.6 s on the small preset's reconstruction) is kept for the process,
    keyed by the two meshes' contents, so the stages of one ``reconstruct`` compute it once.
    """
    if rig_used == "ground_truth":
        return None, {}
    import hashlib

    key = hashlib.sha1(b"".join(np.ascontiguousarray(a).tobytes() for a in (
        atlas.vertices, atlas.faces, renderer.vertices, renderer.faces))).hexdigest()
    T = _GAUGES.get(key)
    if T is None:
        T = renderer.gauge_alignment(atlas.vertices)
        if len(_GAUGES) >= 8:
            _GAUGES.pop(next(iter(_GAUGES)))
        _GAUGES[key] = T
    return T, {"gauge_rotation_deg": round(float(np.degrees(np.linalg.norm(T.rvec))), 6),
               "gauge_translation_mm": round(float(np.linalg.norm(T.t)) * 1e3, 4)}


#: truth_gauge's alignments of this process, by the meshes' contents (a few at most).
_GAUGES: dict[str, Any] = {}


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


def texel_areas(atlas, texels) -> np.ndarray:
    """Surface area each texel stands for, ``(T,)`` float64, m².

    A texel is one unit square of the atlas; the affine UV map of its face scales area by
    ``area_3d / area_uv`` (``area_uv`` in texel units), so a texel on a stretched chart stands
    for more surface. Weighting a per-texel statistic by this makes it a mean over the surface,
    independent of how the atlas samples it (docs/surface.md, "Atlas").

    Parameters
    ----------
    atlas : facegeo.surface.atlas.Atlas
    texels : facegeo.surface.atlas.Texels
        The texel table of ``atlas``.

    Returns
    -------
    (T,) float64, m²
        Summed over the texels it gives the charted surface's area up to the chart-boundary
        texels (a texel whose face has no UV area — none by construction — gets 0).
    """
    tri = atlas.vertices[atlas.faces]
    a3 = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    uv = atlas.uv[atlas.faces] * np.array([atlas.width, atlas.height], float)
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    auv = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        per_face = np.where(auv > 0, a3 / auv, 0.0)
    return per_face[texels.face]


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


#: Lights the ground-truth comparison shades by default (a stratified subset). On the small preset
#: (512 lights) 128 estimate the all-lights figure within 0.5 % of itself (plain bilinear: 3.096
#: against 3.110 %)
#: at ≈ 2 s a camera; 32 scattered by ±0.27 points between subsets (random draws) and a stride
#: of 16 (the former choice: two azimuths, in front of and behind the face) read 2.870 %.
GT_LIGHTS = 128


def _projection_error(renderer, camera, texels, ref, field, area,
                      n_lights: int, gt_lights: int, weight_min: float,
                      stage_lights=None) -> dict[str, float]:
    """Error sums of projected vs exactly shaded samples for one camera (see ``run_project``).

    Field light ``k`` is the true rig's light ``stage_lights[k]`` (default ``k``).

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


def run_project(scan_dir, out_dir=None, *, rig: str | None = None, mesh: str = "ground_truth",
                min_cos: float | None = None, feather_px: float | None = None,
                depth_jump: float | None = None, dtype: str = "float16",
                block_lights: int | None = None, gt_lights: int = GT_LIGHTS,
                gt_weight_min: float = 0.3, cameras: list[str] | None = None,
                atlas_settings: dict | None = None, shadow_taps: bool = True) -> dict:
    """Project every camera's OLAT frames onto the atlas texels into ``out_dir/project/``.

    Parameters
    ----------
    scan_dir : path-like or Scan
    out_dir : path-like, optional
        Default the scan's ``out/``; ``out_dir/atlas/`` is built first when missing.
    rig : str, optional
        Which rig places the cameras: ``"ground_truth"``, ``"scan"``, ``"calibrated"`` or a rig
        file (:func:`stage_rig`).
    mesh : str
        The mesh the texels lie on (must be the atlas's mesh).
    min_cos, feather_px, depth_jump
        See :func:`facegeo.surface.reflectance.camera_visibility`.
    dtype, block_lights
        See :func:`facegeo.surface.reflectance.project_camera`.
    shadow_taps : bool
        Interpolate samples whose bilinear taps straddle a cast-shadow edge from the taps on the
        texel's side, deciding lit and shadowed with the atlas mesh and the rig's lights
        (:mod:`facegeo.surface.shadows`); False: plain bilinear everywhere. Needs the rig's
        lights; without them the projection is plain bilinear and ``shadow_taps`` reads false.
    gt_lights, gt_weight_min
        Ground-truth comparison: at most this many lights (a stratified subset,
        :data:`GT_LIGHTS` by default); texels above this weight.
    cameras : list of str, optional
        Default every camera of the scan.
    atlas_settings : dict, optional
        Keyword arguments for :func:`run_atlas` when the atlas is missing.

    Returns
    -------
    dict
        ``texels``, ``cameras`` (per camera ``visible_fraction``, ``weighted_texels``,
        ``seconds_visibility``, ``seconds_projection``, ``texels_per_second``,
        ``masked_samples``, ``visibility_agreement``, the ``projection_*`` figures and
        ``seconds_projection_error`` on synthetic scans), ``unseen_fraction``,
        ``blended_texels``, ``seconds_blend``,
        ``projection_rel_rmse`` and its companions (synthetic scans; module docstring),
        ``seconds``, ``peak_rss_mb``.
    """
    scan = _scan(scan_dir)
    out = Path(out_dir) if out_dir is not None else scan.out_dir
    atlas_dir = out / "atlas"
    if not (atlas_dir / "texels.npz").is_file():
        run_atlas(scan, out, mesh=mesh, **(atlas_settings or {}))
    with staged_directory(out / "project") as tmp:
        metrics, settings = project_products(
            scan, atlas_dir, tmp, rig=rig, mesh=mesh, min_cos=min_cos, feather_px=feather_px,
            depth_jump=depth_jump, dtype=dtype, block_lights=block_lights, gt_lights=gt_lights,
            gt_weight_min=gt_weight_min, cameras=cameras, shadow_taps=shadow_taps)
        _record(out, tmp, "project", settings, metrics)
    return metrics


def project_products(scan, atlas_dir: Path, dest: Path, *, rig: str | None = None,
                     mesh: str = "ground_truth", min_cos: float | None = None,
                     feather_px: float | None = None, depth_jump: float | None = None,
                     dtype: str = "float16", block_lights: int | None = None,
                     gt_lights: int = GT_LIGHTS, gt_weight_min: float = 0.3,
                     cameras: list[str] | None = None,
                     shadow_taps: bool = True) -> tuple[dict, dict]:
    """Write the ``project`` products of ``scan`` into ``dest`` from the atlas in ``atlas_dir``.

    The work of :func:`run_project` without the staging (the stage cache of
    :mod:`facegeo.pipeline.cache` stages it too). Returns ``(metrics, settings)``.
    """
    from facegeo.surface import reflectance as rf
    from facegeo.surface.atlas import Atlas, Texels
    from facegeo.surface.pullpush import pull_push
    from facegeo.surface.visibility import RayScene

    gt_lights = check_positive_int(gt_lights, "gt_lights")
    t_start = time.perf_counter()
    atlas = Atlas.load(atlas_dir / "atlas.npz")
    texels = Texels.load(atlas_dir / "texels.npz")
    V, F, _ = load_mesh(scan, mesh)
    scene = RayScene(V, F)
    the_rig, rig_used = stage_rig(scan, rig)
    names = list(cameras) if cameras is not None else scan.camera_names
    for n in names:
        if n not in scan.camera_names:
            raise InputError(f"cameras: unknown camera {fmt_value(n)}; the scan has {scan.camera_names}")
    vis_kw = {k: v for k, v in (("min_cos", min_cos), ("feather_px", feather_px),
                                ("depth_jump", depth_jump)) if v is not None}
    jump = depth_jump if depth_jump is not None else rf.DEFAULT_DEPTH_JUMP
    settings = {"rig": rig_used, "mesh": mesh, **vis_kw, "dtype": dtype,
                "block_lights": block_lights or rf.DEFAULT_BLOCK_LIGHTS,
                "gt_lights": gt_lights, "gt_weight_min": gt_weight_min, "cameras": names,
                "shadow_taps": bool(shadow_taps)}
    shadow_rays = None
    if shadow_taps:
        if the_rig.lights is None or the_rig.lights.n_lights != scan.n_lights:
            have = ("no lights" if the_rig.lights is None
                    else f"{the_rig.lights.n_lights} lights")
            log.warning("project: the rig has %s, the scan's frames %d: samples at shadow edges "
                        "stay plain bilinear (shadow_taps reads false per camera)", have,
                        scan.n_lights)
        else:
            from facegeo.surface.shadows import ShadowRays

            # the atlas's own mesh and shading normals: the texels' faces index it
            shadow_rays = ShadowRays(RayScene(atlas.vertices, atlas.faces), atlas.normals)
    renderer = ref = None
    gauge: dict[str, float] = {}
    if scan.synthetic and {"skin", "mesh", "rig"} <= set(scan.ground_truth_keys):
        from facegeo.synth.render import load_ground_truth

        renderer = load_ground_truth(scan)
        T_true, gauge = truth_gauge(renderer, atlas, rig_used)
        ref = renderer.texel_truth(atlas, texels, T_true=T_true)
        area = texel_areas(atlas, texels)
    T = len(texels)
    per_cam: dict[str, Any] = {}
    seen = np.zeros(T, bool)
    colour = np.zeros((T, 3))
    wsum = np.zeros(T)
    err_sums: dict[str, float] = {}
    for name in names:
        camera = the_rig.camera(name)
        t0 = time.perf_counter()
        vis = rf.camera_visibility(texels, camera, scene, **vis_kw)
        t1 = time.perf_counter()
        taps = None
        if shadow_rays is not None:  # built and applied within seconds_projection
            from facegeo.surface.shadows import shadow_taps as make_taps

            sel = np.flatnonzero(vis.weight > 0)
            taps = make_taps(shadow_rays, camera, vis.q[sel], texels.face[sel],
                             texels.bary[sel], the_rig.lights)
        field = rf.project_camera(
            # black-clipped pixels are the dark samples a one-light frame is mostly made of:
            # measured (below one code value), not masked — masking them left 59 % of a 16-bit
            # PNG scan's samples NaN and every function incomplete; saturated ones stay masked
            scan.iter_olat(name, return_mask=True, read_ahead=READ_AHEAD_WORKERS,
                           black_clipped="dark"),
            vis, (camera.width, camera.height),
            scan.n_lights, dest / name, dtype=dtype,
            block_lights=block_lights or rf.DEFAULT_BLOCK_LIGHTS, shadows=taps)
        t2 = time.perf_counter()
        seen[field.texel_index] = True
        for s, chunk in rf.iter_field_chunks(dest / name):
            sl = field.texel_index[s:s + len(chunk)]
            w = field.weight[s:s + len(chunk)].astype(np.float64)
            m = np.nanmean(chunk, axis=1)
            ok = np.isfinite(m).all(axis=1)
            colour[sl[ok]] += w[ok, None] * m[ok]
            wsum[sl[ok]] += w[ok]
        entry = {
            "visible_fraction": round(vis.visible_fraction, 6),
            "weighted_texels": int(field.texel_index.size),
            "seconds_visibility": round(t1 - t0, 4),
            "seconds_projection": round(t2 - t1, 4),
            "texels_per_second": round(field.texel_index.size * scan.n_lights
                                       / max(t2 - t1, 1e-9), 1),
            "masked_samples": field.n_masked,
            "float16_overflow": field.n_overflow,
            "shadow_taps": taps is not None,
        }
        if taps is not None:
            entry["shadow_edge_samples"] = round(taps.changed / max(taps.samples, 1), 6)
            entry["seconds_shadow_taps"] = round(taps.seconds, 4)
        if scan.synthetic:
            agr = _visibility_agreement(scan, name, camera, texels, vis, jump)
            if agr is not None:
                entry["visibility_agreement"] = round(agr["agreement"], 6)
                entry["visibility_compared"] = agr["compared"]
                # what the comparison leaves out (silhouettes, depth jumps) is not hidden
                entry["visibility_compared_fraction"] = round(
                    agr["compared"] / max(agr["candidates"], 1), 6)
        if renderer is not None:
            t3 = time.perf_counter()
            e = _projection_error(renderer, camera, texels, ref, field, area, scan.n_lights,
                                  gt_lights, gt_weight_min)
            for k, x in e.items():
                err_sums[k] = err_sums.get(k, 0.0) + x
            entry.update(_error_metrics(e))
            entry["seconds_projection_error"] = round(time.perf_counter() - t3, 4)
        per_cam[name] = entry
    np.save(dest / "seen.npy", seen)
    t_b = time.perf_counter()
    blended = rf.blend_fields([dest / n for n in names], dest / "blended", dtype=dtype)
    seconds_blend = time.perf_counter() - t_b
    preview = np.where(wsum[:, None] > 0, colour / np.maximum(wsum, 1e-30)[:, None], np.nan)
    img = pull_push(texels.to_image(preview), texels.to_image(
        np.where(wsum > 0, 1.0, 0.0), fill=0.0))
    import cv2

    scale = np.nanpercentile(preview, 99) if np.isfinite(preview).any() else 1.0
    png = np.clip(np.nan_to_num(img) / max(scale, 1e-12), 0, 1) ** (1 / 2.2)
    cv2.imwrite(str(dest / "preview.png"),
                (png[..., ::-1] * 255 + 0.5).astype(np.uint8))
    atomic_write_text(dest / ATLAS_FINGERPRINT, file_sha256(atlas_dir / "texels.npz") + "\n")
    metrics: dict[str, Any] = {
        "texels": int(T), "lights": int(scan.n_lights), "rig": rig_used,
        "cameras": per_cam,
        "unseen_fraction": round(float(1 - seen.mean()) if T else 0.0, 6),
        "blended_texels": int(blended.texel_index.size),
        "seconds_blend": round(seconds_blend, 4),
    }
    agrs = [c["visibility_agreement"] for c in per_cam.values()
            if "visibility_agreement" in c]
    if agrs:
        metrics["visibility_agreement"] = round(float(min(agrs)), 6)
    if renderer is not None and err_sums.get("sr", 0.0) > 0:
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
    metrics["seconds"] = round(time.perf_counter() - t_start, 4)
    metrics["peak_rss_mb"] = round(peak_rss_mb(), 1)
    return metrics, settings
