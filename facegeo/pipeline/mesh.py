"""Pipeline stage ``mesh``: decode maps → triangulated, fused points → trimmed Poisson mesh.

``run_mesh(scan_dir, out_dir)`` reads the decode stage's ``out_dir/decode/<camera>/decode.npz``
(float32 ``x``, ``y``, ``confidence``, ``sigma_x``, ``sigma_y``, bool ``valid``; see the module
of the decode stage) and writes ``out_dir/mesh/``:

    points.ply    fused points: x y z, nx ny nz (toward the observing camera), confidence,
                  sigma (1 σ along the camera ray, metres), camera (index), confirmed
    mesh.ply      the trimmed Poisson mesh (metres, world frame)
    observed_faces.npy
                  (F,) bool: the mesh faces within ``observed_radius`` of a fused point (the
                  observed region; the evaluation's mesh figures are taken over it)
    mesh_filled.ply
                  the filled surface (issue 37): a Poisson solution over a larger cube
                  (``fill_scale``) trimmed only by distance, within ``fill_distance`` of a
                  point, so it closes over what the structured light did not reach (under
                  the jaw, beside the nose, the cheeks and the side of the head past the
                  cameras) — what the atlas and the renders use by default
                  (:mod:`facegeo.pipeline.reconstruct`, atlas setting ``surface``); with
                  OLAT frames its solve also holds the cameras' silhouette rims
                  (``silhouettes``, :func:`silhouette_rims`)
    mesh_filled_inferred.npy
                  (F_filled,) bool: its *inferred* faces, those with a vertex farther than
                  the trim distance (``mesh.max_distance_mm``) from every fused point; the
                  atlas marks their texels, the projection leaves them unmeasured
    stage.json    settings and metrics

``mesh.ply`` stays the measured product: the mesh figures (here and in the evaluation) are
the trimmed mesh's, never the filled one's. The filled surface is written for the Poisson
method only (``fill_distance_mm=None`` writes none); its figures are the metrics' ``filled``.

and records its metrics in ``out_dir/metrics.json`` under ``"mesh"``.

Rig: ``rig="ground_truth"`` (default when the scan has one) uses the true rig the frames were
rendered with, ``rig="scan"`` the scan's ``rig.json``, ``rig="calibrated"`` the ``calibrate``
stage's ``out/calibrate/rig.json`` (or give a rig file); the choice is the ``rig`` of the
metrics.

Triangulation (``"triangulation"`` in the metrics): ``"camera-projector"`` — each camera's rays
against the calibrated projector (:func:`facegeo.geometry.triangulation.triangulate_maps`); or,
when the rig's projector is uncalibrated (a :class:`facegeo.geometry.rig.Projector`: resolution
only), ``"camera-camera"`` — every camera against every other through matching projector codes
(:func:`facegeo.geometry.triangulation.triangulate_camera_pairs`), which needs two or more
cameras whose decodes have both ``x`` and ``y`` (cameras without are left out and listed under
``skipped_cameras``; fewer than two left is a one-line :class:`InputError` saying what would
calibrate the projector). Either way the per-camera point maps go through the same fusion,
normals, Poisson, trimming and metrics.

* ``unobserved_area_mm2`` / ``unobserved_area_fraction``: mesh area farther than
  ``observed_radius`` from every fused point — "no mesh where no camera saw the face"
  (``observed_radius`` defaults to 1.5 sampling spacings, see :func:`mesh_products`); the
  other faces are ``observed_faces.npy``.

The stage reads no truth: the errors against a synthetic scan's true surface (or a real
scan's reference mesh) — ``points_rms_error_mm``, ``mesh_p95_error_mm`` and
``normal_median_error_deg`` over the observed region, with any rig but the true one also
``after_rigid_alignment`` — are :mod:`facegeo.evaluate.cloud`'s, from these products
(``facegeo evaluate``, the ``evaluate`` stage; issue 37 moved them out of this module).

:func:`ground_truth_decode` (:mod:`facegeo.pipeline._mesh_truth`, re-exported here) makes
decode maps from a synthetic scan's per-camera ground-truth geometry (project the true surface
point of each pixel into the projector, drop projector shadows, add Gaussian noise), for tests
and benchmarks.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError
from facegeo.fsutil import READ_AHEAD_WORKERS, atomic_path, atomic_write_text, staged_directory
from facegeo.geometry.mesh import inferred_faces_path
from facegeo.pipeline._mesh_truth import (  # noqa: F401  (re-exported)
    _load_gt_mesh,
    decode_from_surface,
    ground_truth_decode,
)
from facegeo.pipeline._mesh_codes import (  # the stage's code settings, re-exported
    CODE_MIN_COUNT, FILL_GAP_SPACINGS, FILL_MIN_CONFIDENCE, MAX_CODE_SCATTER, SHARED_CODE_LIMIT,
    _fill_centroids, _fill_holes, _interpolated_codes, _mm)

log = logging.getLogger(__name__)

__all__ = [
    "CODE_MIN_COUNT",
    "DECODE_KEYS",
    "FILLED_INFERRED",
    "FILLED_MESH",
    "FILL_GAP_SPACINGS",
    "FILL_MIN_CONFIDENCE",
    "MAX_CODE_SCATTER",
    "SHARED_CODE_LIMIT",
    "decode_from_surface",
    "ground_truth_decode",
    "load_decode",
    "mesh_products",
    "read_points_ply",
    "run_mesh",
    "write_decode_npz",
    "write_points_ply",
]

#: Arrays of a ``decode.npz``.
DECODE_KEYS = ("x", "y", "confidence", "valid", "sigma_x", "sigma_y")


def _scan(scan_dir):
    from facegeo.pipeline.project import _scan as scan_of

    return scan_of(scan_dir)


# ------------------------------------------------------------------------ decode maps


def write_decode_npz(path, maps: dict) -> Path:
    """Write the :data:`DECODE_KEYS` arrays of ``maps`` to ``path`` (atomic)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **{k: maps[k] for k in DECODE_KEYS})
    return path


def load_decode(path, shape: tuple[int, int] | None = None) -> dict:
    """Read a ``decode.npz``, checking its arrays (names, shapes, dtypes).

    Raises
    ------
    InputError
        Missing file or array, or a map whose shape differs from ``shape`` / the ``x`` map.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no decode maps (run the decode stage first: facegeo decode "
                         "SCAN)")
    try:
        with np.load(path) as z:
            if "x" not in z.files:
                raise InputError(f"{path}: missing array 'x' (expected {', '.join(DECODE_KEYS)})")
            out = {k: z[k] for k in DECODE_KEYS if k in z.files}
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not a readable .npz file ({exc})") from exc
    want = shape if shape is not None else out["x"].shape
    for k, a in out.items():
        if a.shape != tuple(want):
            raise InputError(f"{path}: array {k!r} has shape {a.shape}, expected {tuple(want)} "
                             "(the camera's height × width)")
    return out


# ------------------------------------------------------------------------ PLY output

_POINT_FIELDS = [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("nx", "<f4"), ("ny", "<f4"),
                 ("nz", "<f4"), ("confidence", "<f4"), ("sigma", "<f4"), ("camera", "<i4"),
                 ("confirmed", "u1")]
_PLY_TYPES = {"<f8": "double", "<f4": "float", "<i4": "int", "u1": "uchar"}


def write_points_ply(path, points, normals, confidence, sigma, camera, confirmed) -> Path:
    """Write a binary little-endian PLY of oriented points with per-point quality (atomic).

    Vertex properties: ``x y z`` (double, metres), ``nx ny nz`` (float), ``confidence`` (float,
    0..1), ``sigma`` (float, metres, 1 σ), ``camera`` (int), ``confirmed`` (uchar).
    """
    n = len(points)
    rec = np.empty(n, dtype=_POINT_FIELDS)
    for i, k in enumerate("xyz"):
        rec[k] = points[:, i]
        rec["n" + k] = normals[:, i]
    rec["confidence"], rec["sigma"] = confidence, sigma
    rec["camera"], rec["confirmed"] = camera, confirmed
    head = ["ply", "format binary_little_endian 1.0", "comment facegeo mesh stage: metres, world frame",
            f"element vertex {n}"]
    head += [f"property {_PLY_TYPES[t]} {k}" for k, t in _POINT_FIELDS] + ["end_header", ""]
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write("\n".join(head).encode("ascii"))
        fh.write(rec.view(np.uint8))  # no bytes copy of the records
    return path


def read_points_ply(path) -> np.ndarray:
    """Read a :func:`write_points_ply` file back as a structured array."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    names = [ln.split()[-1] for ln in header if ln.startswith("property")]
    if names != [k for k, _ in _POINT_FIELDS]:
        raise InputError(f"{path}: not a facegeo points PLY (properties {names})")
    n = int(next(ln.split()[-1] for ln in header if ln.startswith("element vertex")))
    return np.frombuffer(data, dtype=_POINT_FIELDS, count=n, offset=end)


def _write_mesh_ply(path, V, F) -> None:
    import trimesh

    with atomic_path(path) as tmp:
        trimesh.Trimesh(V, F, process=False).export(tmp, file_type="ply")


# ------------------------------------------------------------------------ the stage


def _record(out_dir: Path, stage_dir: Path, settings: dict, metrics: dict) -> None:
    from facegeo.pipeline.cache import record_metrics

    atomic_write_text(stage_dir / "stage.json", json.dumps(
        {"stage": "mesh", "settings": settings, "metrics": metrics}, indent=2, sort_keys=True))
    record_metrics(out_dir, "mesh", metrics)


def run_mesh(scan_dir, out_dir=None, **settings) -> dict:
    """Triangulate, fuse and mesh a scan's decode maps into ``out_dir/mesh/``.

    Parameters
    ----------
    scan_dir : path-like or Scan
    out_dir : path-like, optional
        Default the scan's ``out/``; the decode maps are read from ``out_dir/decode/``.
    **settings
        See :func:`mesh_products`.

    Returns
    -------
    dict
        The metrics (see :func:`mesh_products`).
    """
    scan = _scan(scan_dir)
    out = Path(out_dir) if out_dir is not None else scan.out_dir
    with staged_directory(out / "mesh") as tmp:
        metrics, used = mesh_products(scan, out / "decode", tmp, **settings)
        _record(out, tmp, used, metrics)
    return metrics


def mesh_products(scan, decode_dir, dest, *, rig: str | None = None,
                  cameras: list[str] | None = None, method: str = "poisson",
                  min_confidence: float = 0.2, default_sigma_px: float = 0.3,
                  max_sigma_ratio: float = 5.0, max_chi: float = 4.0,
                  min_angle_deg: float | None = None, code_interpolation: str = "auto",
                  hole_fill: str = "auto", fill_min_confidence: float = FILL_MIN_CONFIDENCE,
                  fuse_sigmas: float = 4.0, normals_k: int = 24, depth: int | str = "auto",
                  point_weight: float = 4.0, trim_quantile: float = 0.02,
                  max_distance_mm: float | str | None = "auto", min_component: float = 0.05,
                  target_faces: int | None = None,
                  observed_radius_mm: float | None = None,
                  fill_distance_mm: float | str | None = "auto",
                  fill_scale: float | None = None,
                  silhouettes: str = "auto") -> tuple[dict, dict]:
    """Write ``points.ply`` and ``mesh.ply`` of ``scan`` into ``dest`` from ``decode_dir``.

    The work of :func:`run_mesh` without the staging. Returns ``(metrics, settings)``.

    Parameters
    ----------
    scan : Scan
    decode_dir : path-like
        Holds ``<camera>/decode.npz`` per camera.
    dest : path-like
        An existing directory.
    rig : str, optional
        ``"ground_truth"``, ``"scan"``, ``"calibrated"`` or a rig file
        (:func:`facegeo.pipeline.project.stage_rig`; module docstring).
    cameras : list of str, optional
        Default every camera with decode maps in ``decode_dir``.
    method : {"poisson", "grid"}
        Poisson over all cameras' fused points, or the direct pixel-grid mesh of the first
        camera (the cheap one-camera path).
    min_confidence, default_sigma_px, max_sigma_ratio, max_chi, min_angle_deg
        :func:`facegeo.geometry.triangulation.triangulate_maps` (camera-camera:
        :func:`facegeo.geometry.triangulation.triangulate_camera_pairs`); ``min_angle_deg``
        None derives it from the rig (:func:`facegeo.geometry.triangulation.rig_min_angle_deg`).
    code_interpolation : {"auto", "on", "off"}
        Camera-camera only: match interpolated codes
        (:func:`facegeo.geometry.code_maps.interpolate_code_map`) for a camera whose decoded
        pixels share their codes (``"auto"``: at least :data:`SHARED_CODE_LIMIT` of them); the
        metrics' ``code_interpolation`` says per camera what was done.
    hole_fill : {"auto", "on", "off"}
        Camera-camera only (``"auto"``: there): after fusion, add code-region centroid points
        (:func:`facegeo.geometry.code_regions.centroid_fill_points`) where no per-pixel point
        is within :data:`FILL_GAP_SPACINGS` point spacings — the holes per-pixel matching left
        (hair, oblique cheeks); the metrics' ``hole_fill`` counts them.
    fill_min_confidence : float
        The hole fill's code regions average decoded pixels of at least this confidence
        (:data:`FILL_MIN_CONFIDENCE`); filled points carry it as their confidence.
    fuse_sigmas : float
        :func:`facegeo.geometry.triangulation.fuse_cameras` tolerance.
    normals_k : int
        :func:`facegeo.geometry.mesh.oriented_normals`.
    depth, point_weight, trim_quantile, min_component, target_faces
        :func:`facegeo.geometry.mesh.poisson_mesh`; ``depth="auto"`` (default) from the points'
        extent and spacing (:func:`facegeo.geometry.mesh.poisson_depth_for`).
    max_distance_mm : float, millimetres, "auto" or None
        Trim mesh vertices farther than this from every point. ``"auto"`` (default): agreed
        with the Poisson cell (:func:`facegeo.geometry.mesh.trim_distance_for`); None: the
        observed radius (``observed_radius_mm``), as before issue 34, which on a real scan at
        full resolution (0.23 mm) trimmed away 9,911 of 11,080 vertices of a depth-7 mesh.
    observed_radius_mm : float, millimetres, optional
        The observed region (``observed_faces.npy``, ``unobserved_area_mm2``): within
        this of a fused point. Default 1.5 × the points' median 6th-neighbour distance
        (:func:`facegeo.geometry.triangulation.neighbour_spacing`; ≈ 2.0 mm on the small
        preset, 5.5 mm on the tiny one), recorded in the metrics.
    fill_distance_mm : float, millimetres, "auto" or None
        The filled surface's bound (``mesh_filled.ply``, module docstring): Poisson vertices
        within this of a fused point (at least the trim distance). ``"auto"`` (default):
        :func:`facegeo.geometry.mesh.fill_distance_for` (0.28 × the points' extent, ≈ 60 mm
        on a head); None: no filled surface.
    fill_scale : float, optional
        The filled surface's own Poisson solve grids a cube of this many times the points'
        extent (:func:`facegeo.geometry.mesh.poisson_mesh` ``fill_scale``; default
        :data:`facegeo.geometry.mesh.AUTO_FILL_SCALE`, 4; ``1.1``, the trimmed mesh's cube, cuts
        the filled surface from the trimmed mesh's solve as before).
    silhouettes : {"auto", "on", "off"}
        Shape the filled surface with the cameras' silhouettes (:func:`silhouette_rims`): the
        rim points of every camera with one-light-at-a-time frames join its Poisson solve as
        support points. ``"auto"`` (default): when the scan has such frames and there is a
        filled surface; ``"on"`` insists (an error without OLAT frames); the metrics'
        ``silhouettes`` count per camera what was found.

    Returns
    -------
    metrics : dict
        ``triangulation`` (``"camera-projector"`` or ``"camera-camera"``, module docstring),
        ``cameras`` (per camera: pixels with a point, counts per rejection reason, median σ in
        mm; camera-camera also ``partners``: points against each other camera, and
        ``decode_sigma_px``: the decode's median ``x``/``y`` σ), ``skipped_cameras`` (when
        any), ``points``, ``confirmed_fraction``, ``median_sigma_mm``, ``mesh`` (the
        reconstruction's settings and counts: depth, point weight, trim quantile, …),
        ``faces``, ``vertices``, ``area_mm2``, ``unobserved_area_mm2``, ``warnings`` (when a
        camera lost most of its triangulated pixels as inconsistent with the rig,
        :data:`INCONSISTENT_WARN_FRACTION`: also logged),
        ``unobserved_area_fraction``, seconds per step; ``filled`` (with a filled surface:
        ``fill_distance_mm``, ``faces``, ``vertices``, ``area_mm2``, ``inferred_faces``,
        ``inferred_area_mm2``, ``inferred_area_fraction``).
    settings : dict
    """
    from facegeo.geometry import mesh as gm
    from facegeo.geometry import triangulation as tr

    t_start = time.perf_counter()
    decode_dir, dest = Path(decode_dir), Path(dest)
    if method not in ("poisson", "grid"):
        raise InputError(f"method: expected 'poisson' or 'grid', got {fmt_value(method)}")
    for key, v in (("code_interpolation", code_interpolation), ("hole_fill", hole_fill),
                   ("silhouettes", silhouettes)):
        if v not in ("auto", "on", "off"):
            raise InputError(f"{key}: expected 'auto', 'on' or 'off', got {fmt_value(v)}")
    if not (np.isfinite(fill_min_confidence) and 0.0 <= fill_min_confidence <= 1.0):
        raise InputError(f"fill_min_confidence: expected a confidence in [0, 1], got "
                         f"{fmt_value(fill_min_confidence)}")
    if min_angle_deg is not None and not 0.0 <= float(min_angle_deg) < 90.0:
        raise InputError(f"min_angle_deg: expected an angle in [0, 90) degrees or None (from "
                         f"the rig), got {fmt_value(min_angle_deg)}")
    from facegeo.pipeline.project import stage_rig

    the_rig, rig_used = stage_rig(scan, rig)
    if the_rig.projector is None:
        raise InputError(f"scan {scan.root}: the rig has no projector to triangulate against")
    pair_route = not the_rig.projector_calibrated
    if cameras is None:
        # (a scan without structured-light frames may bring its decode maps: every camera)
        sl_cams = (scan.cameras_with_frames("structured_light")
                   if scan.has("structured_light") else scan.camera_names)
        for n in scan.camera_names:
            if n not in sl_cams:
                log.info("mesh %s: skipped, every structured-light frame declared missing (a "
                         "camera of the calibration only)", n)
        names = [n for n in sl_cams if (decode_dir / n / "decode.npz").is_file()]
        if not names:
            raise InputError(f"{decode_dir}: no <camera>/decode.npz for any of the scan's cameras "
                             f"({', '.join(scan.camera_names)}); run the decode stage first")
    else:
        names = list(cameras)
        for n in names:
            if n not in scan.camera_names:
                raise InputError(f"cameras: unknown camera {fmt_value(n)}; the scan has "
                                 f"{scan.camera_names}")
    settings = {"rig": rig_used, "cameras": names, "method": method,
                "min_confidence": min_confidence, "default_sigma_px": default_sigma_px,
                "max_sigma_ratio": max_sigma_ratio, "max_chi": max_chi,
                "min_angle_deg": min_angle_deg, "code_interpolation": code_interpolation,
                "hole_fill": hole_fill, "fill_min_confidence": fill_min_confidence,
                "fuse_sigmas": fuse_sigmas, "normals_k": normals_k, "depth": depth,
                "point_weight": point_weight, "trim_quantile": trim_quantile,
                "max_distance_mm": max_distance_mm, "min_component": min_component,
                "target_faces": target_faces, "observed_radius_mm": observed_radius_mm,
                "fill_distance_mm": fill_distance_mm,
                "fill_scale": gm.AUTO_FILL_SCALE if fill_scale is None else fill_scale,
                "silhouettes": silhouettes}
    from facegeo.checks import check_positive

    if fill_distance_mm is not None and fill_distance_mm != "auto":
        check_positive(fill_distance_mm, "fill_distance_mm")
    sil_cams = silhouette_cameras(scan, the_rig)
    if silhouettes == "on" and not sil_cams:
        raise InputError(f"silhouettes 'on': no camera of scan {scan.root} has "
                         "one-light-at-a-time frames to find its silhouette in")
    if silhouettes == "on" and (method != "poisson" or fill_distance_mm is None):
        raise InputError("silhouettes 'on': they shape the filled surface, which only the "
                         "Poisson method with a fill distance makes")
    check_positive(settings["fill_scale"], "fill_scale")
    cams = [the_rig.camera(n) for n in names]
    extra: dict[str, Any] = {}
    t0 = time.perf_counter()
    if pair_route:
        cams, maps, extra = _camera_pair_maps(
            scan, the_rig, rig_used, cams, decode_dir, min_confidence=min_confidence,
            default_sigma_px=default_sigma_px, max_sigma_ratio=max_sigma_ratio, max_chi=max_chi,
            min_angle_deg=min_angle_deg, code_interpolation=code_interpolation,
            fill_min_confidence=fill_min_confidence if hole_fill != "off" else None)
        names = [c.name for c in cams]
    else:
        maps = []
        for cam in cams:
            d = load_decode(decode_dir / cam.name / "decode.npz", (cam.height, cam.width))
            maps.append(tr.triangulate_maps(
                cam, the_rig.projector, d["x"], d.get("y"), valid=d.get("valid"),
                confidence=d.get("confidence"), sigma_x=d.get("sigma_x"),
                sigma_y=d.get("sigma_y"), min_confidence=min_confidence,
                default_sigma_px=default_sigma_px, max_sigma_ratio=max_sigma_ratio,
                max_chi=max_chi, min_angle_deg=min_angle_deg))
    _return_freed_memory()
    t1 = time.perf_counter()
    fused = tr.fuse_cameras(maps, cams, tol_sigmas=fuse_sigmas, drop_gains=True)
    if pair_route and hole_fill != "off" and len(fused) >= 10:
        fused, extra["hole_fill"] = _fill_holes(fused, cams, extra.pop("centroids"),
                                                fill_min_confidence, max_chi=max_chi,
                                                min_angle_deg=min_angle_deg)
    t2 = time.perf_counter()
    if len(fused) < 10:
        raise _too_few_points(scan, rig_used, decode_dir, len(fused), names, maps, pair_route,
                              settings)
    per_cam = {m.camera: _camera_metrics(m, extra if pair_route else None) for m in maps}
    # the maps are done with (the grid mesh reads the first one's points)
    grid_map = maps[0] if method == "grid" else None
    del maps
    _return_freed_memory()
    normals = gm.oriented_normals(fused.p_world, fused.view_dirs, k=normals_k)
    t3 = time.perf_counter()
    # the points' file and figures first: Poisson gets the points and normals alone
    write_points_ply(dest / "points.ply", fused.p_world, normals, fused.confidence,
                     fused.sigma, fused.camera, fused.confirmed)
    n_points = len(fused)
    confirmed_fraction = round(float(fused.confirmed.mean()), 6)
    median_sigma_mm = _mm(np.median(fused.sigma))
    points = fused.p_world
    del fused
    _return_freed_memory()
    t3b = time.perf_counter()
    spacing = tr.neighbour_spacing(points)
    _return_freed_memory()  # its k-d tree's (a quarter GB of 6.6 M points')
    r_obs = 1.5 * spacing if observed_radius_mm is None else observed_radius_mm * 1e-3
    max_d = r_obs if max_distance_mm is None else (
        "auto" if max_distance_mm == "auto" else float(max_distance_mm) * 1e-3)
    fill = None if fill_distance_mm is None else (
        "auto" if fill_distance_mm == "auto" else float(fill_distance_mm) * 1e-3)
    if method == "poisson":
        support = None
        if fill is not None and sil_cams and silhouettes != "off":
            def support(first_fill):
                """Rim points against the filled surface of the points alone, which
                poisson_mesh then solves again with them."""
                t_sil = time.perf_counter()
                rims = silhouette_rims(scan, the_rig, sil_cams, points, first_fill,
                                       strict=silhouettes == "on")
                extra["silhouettes"] = rims["metrics"] | {
                    "seconds": round(time.perf_counter() - t_sil, 4)}
                return rims["points"], rims["normals"]

        mesh = gm.poisson_mesh(points, normals, depth=depth, point_weight=point_weight,
                               trim_quantile=trim_quantile, max_distance=max_d, spacing=spacing,
                               min_component=min_component, target_faces=target_faces,
                               fill_distance=fill, fill_scale=settings["fill_scale"],
                               support=support)
    else:
        mesh = gm.grid_mesh(grid_map.p_world, grid_map.valid, center_world=cams[0].center_world)
    t4 = time.perf_counter()
    del normals
    _write_mesh_ply(dest / "mesh.ply", mesh.vertices, mesh.faces)
    area_out, far = gm.area_beyond(mesh.vertices, mesh.faces, points, r_obs)
    with atomic_path(dest / "observed_faces.npy") as tmp:
        with open(tmp, "wb") as f:
            np.save(f, ~far)
    filled = _write_filled(dest, mesh.filled) if mesh.filled is not None else None
    area = mesh.area
    metrics: dict[str, Any] = {
        "rig": rig_used,
        "triangulation": "camera-camera" if pair_route else "camera-projector",
        "cameras": per_cam, "points": n_points,
        "confirmed_fraction": confirmed_fraction,
        "median_sigma_mm": median_sigma_mm,
        "neighbour_spacing_mm": _mm(spacing), "observed_radius_mm": _mm(r_obs),
        "method": method, "mesh": mesh.info, "faces": len(mesh.faces),
        "vertices": len(mesh.vertices), "area_mm2": round(area * 1e6, 3),
        "unobserved_area_mm2": round(area_out * 1e6, 3),
        "unobserved_area_fraction": round(area_out / area, 6) if area > 0 else None,
        "seconds_triangulate": round(t1 - t0, 4), "seconds_fuse": round(t2 - t1, 4),
        "seconds_normals": round(t3 - t2, 4), "seconds_mesh": round(t4 - t3b, 4),
    }
    if filled is not None:
        metrics["filled"] = filled
    if extra.get("skipped_cameras"):
        metrics["skipped_cameras"] = extra["skipped_cameras"]
    if extra.get("code_interpolation"):
        metrics["code_interpolation"] = extra["code_interpolation"]
    if extra.get("hole_fill"):
        metrics["hole_fill"] = extra["hole_fill"]
    if extra.get("silhouettes"):
        metrics["silhouettes"] = extra["silhouettes"]
    warnings = _geometry_warnings(per_cam, pair_route)
    if warnings:
        metrics["warnings"] = warnings
    metrics["seconds"] = round(time.perf_counter() - t_start, 4)
    return metrics, settings


#: Lights whose frames give a camera's silhouette (:func:`silhouette_rims`): at most this many,
#: spread evenly over its light list — any surface a camera sees faces a few of them.
SILHOUETTE_LIGHTS = 64


def silhouette_cameras(scan, the_rig) -> list[str]:
    """The cameras of ``the_rig`` with one-light-at-a-time frames in ``scan``: the ones whose
    silhouettes :func:`silhouette_rims` can find."""
    if not scan.has("olat"):
        return []
    return [n for n in scan.cameras_with_frames("olat") if n in the_rig.camera_names]


def silhouette_rims(scan, the_rig, names, points, filled, *, strict: bool = False) -> dict:
    """Rim points of the cameras ``names``' silhouettes against the filled surface ``filled``
    (:mod:`facegeo.geometry.silhouette`).

    Each camera's silhouette is :func:`facegeo.geometry.silhouette.silhouette_mask` of the
    per-pixel brightest value (channel maximum) over :data:`SILHOUETTE_LIGHTS` of its
    one-light-at-a-time frames, the structured-light ``points`` telling the subject's pixels.
    A camera whose silhouette cannot be found (no point in its image, its known pixels dark,
    frames of another size than the rig's camera) is left out with a warning and its ``error``
    in the metrics; with ``strict`` it raises.

    Returns
    -------
    dict
        ``points``, ``normals`` (M, 3) over every camera; ``metrics``: per camera ``lights``
        read, ``mask_pixels``, ``edge_pixels``, ``rim_points``, ``outside`` (of them, from
        rays that passed outside ``filled``) and ``missed`` (edge pixels with no rim point,
        :func:`facegeo.geometry.silhouette.rim_points`).
    """
    from facegeo.geometry.silhouette import rim_points, silhouette_mask

    pts, nrm, per_cam = [], [], {}
    for name in names:
        cam = the_rig.camera(name)
        lights = scan.camera_frames("olat", name)
        step = max(1, -(-len(lights) // SILHOUETTE_LIGHTS))
        brightest = None
        for _, frame in scan.iter_olat(name, lights[::step], read_ahead=READ_AHEAD_WORKERS):
            f = np.nan_to_num(np.asarray(frame, np.float32), nan=0.0)
            f = f.max(axis=-1) if f.ndim == 3 else f
            brightest = f if brightest is None else np.maximum(brightest, f)
        q, front = cam.project(points)
        try:
            mask = silhouette_mask(brightest, q[front])
            rim = rim_points(cam, mask, filled.vertices, filled.faces)
        except InputError as e:
            if strict:
                raise InputError(f"silhouettes, camera {name}: {e}") from None
            log.warning("mesh: no silhouette of camera %s (%s); the filled surface goes without "
                        "it", name, e)
            per_cam[name] = {"lights": len(lights[::step]), "error": str(e)}
            continue
        pts.append(rim["points"])
        nrm.append(rim["normals"])
        per_cam[name] = {"lights": len(lights[::step]), "mask_pixels": int(mask.sum()),
                         "edge_pixels": rim["edge_pixels"], "rim_points": len(rim["points"]),
                         "outside": rim["outside"], "missed": rim["missed"]}
    return {"points": np.vstack(pts) if pts else np.zeros((0, 3)),
            "normals": np.vstack(nrm) if nrm else np.zeros((0, 3)),
            "metrics": {"cameras": per_cam,
                        "rim_points": int(sum(v.get("rim_points", 0)
                                              for v in per_cam.values()))}}


#: The filled surface's files in the mesh stage's folder (module docstring).
FILLED_MESH = "mesh_filled.ply"
FILLED_INFERRED = inferred_faces_path(FILLED_MESH).name


def _write_filled(dest: Path, filled) -> dict:
    """Write the filled surface and its inferred-face flags; return its metrics."""
    from facegeo.geometry.mesh import face_areas

    _write_mesh_ply(dest / FILLED_MESH, filled.vertices, filled.faces)
    with atomic_path(inferred_faces_path(dest / FILLED_MESH)) as tmp, open(tmp, "wb") as f:
        np.save(f, np.asarray(filled.inferred_faces, bool))
    a = face_areas(filled.vertices, filled.faces)
    total, inferred = float(a.sum()), float(a[filled.inferred_faces].sum())
    return {"fill_distance_mm": round(filled.info["fill_distance_mm"], 4),
            "fill_scale": filled.info["fill_scale"], "fill_depth": filled.info["fill_depth"],
            "fill_cell_mm": round(filled.info["fill_cell_mm"], 4),
            "support_points": int(filled.info.get("support_points", 0)),
            "faces": len(filled.faces), "vertices": len(filled.vertices),
            "area_mm2": round(total * 1e6, 3),
            "inferred_faces": int(filled.info["inferred_faces"]),
            "inferred_area_mm2": round(inferred * 1e6, 3),
            "inferred_area_fraction": round(inferred / total, 6) if total > 0 else None}


_MALLOC_TRIM = None


def _return_freed_memory() -> None:
    """Give the C heap's free pages back to the system (glibc ``malloc_trim``; a no-op
    elsewhere). numpy takes arrays under 32 MB — the steps' per-block temporaries — from the
    heap, and glibc keeps the freed ones resident: between the stage's steps at full
    resolution that was ≈ 0.3–0.7 GB of the next step's peak (docs/mesh.md, *Memory at full
    resolution*)."""
    global _MALLOC_TRIM
    if _MALLOC_TRIM is None:
        _MALLOC_TRIM = False
        try:
            import ctypes

            _MALLOC_TRIM = ctypes.CDLL("libc.so.6").malloc_trim
        except (OSError, AttributeError):
            pass
    if _MALLOC_TRIM:
        _MALLOC_TRIM(0)


def _camera_metrics(pm, extra: dict | None) -> dict:
    """One camera's metrics from its point map (``extra``: the camera-camera route's)."""
    v = pm.valid_at
    out = {"points": int(np.count_nonzero(v)), "rejected": pm.reason_counts(),
           "median_sigma_mm": _mm(np.median(pm.point_sigma[v])) if v.any() else None}
    if extra is not None:
        out["partners"] = extra["partners"][pm.camera]
        out["decode_sigma_px"] = extra["decode_sigma_px"][pm.camera]
    return out


def _camera_pair_maps(scan, the_rig, rig_used: str, cams: list, decode_dir: Path, *,
                      min_confidence: float, default_sigma_px: float, max_sigma_ratio: float,
                      max_chi: float, min_angle_deg, code_interpolation: str = "auto",
                      fill_min_confidence: float | None = None) -> tuple[list, list, dict]:
    """Point maps of the cameras triangulated against each other through matching projector
    codes (the rig's projector is uncalibrated): ``(cameras used, maps, extra metrics)``.

    One camera's ``(H, W)`` decode maps are held at a time, reduced to its decoded pixels
    (:class:`facegeo.geometry.code_maps.CodeSet`) before the next is read; the triangulation
    works on those (:func:`facegeo.geometry.triangulation.triangulate_code_sets`).

    Each camera's codes are masked to its valid pixels with ``confidence >= min_confidence``
    and both ``x`` and ``y``; its decode noise is its ``sigma_x``/``sigma_y`` maps
    (``default_sigma_px`` where they give none; their medians are recorded as
    ``decode_sigma_px``). Cameras without any such pixel are left out (``skipped_cameras``);
    fewer than two left raises :class:`InputError`.

    With ``fill_min_confidence`` given, each camera's code-region centroids over its decoded
    pixels of at least that confidence, at its own code block, are kept for the hole fill
    (``extra["centroids"]``: a list of ``(RegionCentroids, (block_x, block_y))``).
    """
    from facegeo.geometry import triangulation as tr

    if len(cams) < 2:
        one = cams[0].name if cams else None
        why = (f"the scan has one ({one!r})" if len(scan.camera_names) < 2 else
               f"only {one!r} is meshed (the cameras with decode maps, or the cameras setting)")
        raise _uncalibrated_projector_error(scan, the_rig, rig_used, why)
    used, codes, sig, skipped, interp, cens = [], [], {}, {}, {}, []
    for cam in cams:
        # one camera's (H, W) maps at a time, reduced to its decoded pixels (a CodeSet)
        d = load_decode(decode_dir / cam.name / "decode.npz", (cam.height, cam.width))
        x, y = d.pop("x"), d.pop("y", None)
        ok = np.isfinite(x) & (np.isfinite(y) if y is not None else False)
        if "valid" in d:
            ok &= d.pop("valid").astype(bool)
        conf = d.pop("confidence", None)
        if conf is not None:
            with np.errstate(invalid="ignore"):
                ok &= ~(conf < min_confidence)
        if not ok.any():
            skipped[cam.name] = "no valid pixel with both x and y codes"
            continue
        sig[cam.name] = {}
        for axis in ("x", "y"):
            m = d.get("sigma_" + axis)
            v = m[ok] if m is not None else np.zeros(0)
            v = v[np.isfinite(v) & (v > 0)]
            sig[cam.name][axis] = round(float(np.median(v)), 6) if v.size else None
        used.append(cam)
        if fill_min_confidence is not None:
            cens.append(_fill_centroids(x, y, d, conf, fill_min_confidence))
        xm, ym = np.where(ok, x, np.nan), np.where(ok, y, np.nan)
        del x, y, ok
        cs, interp[cam.name] = _interpolated_codes(
            xm, ym, d.get("sigma_x"), d.get("sigma_y"), conf, default_sigma_px,
            code_interpolation)
        del d, xm, ym, conf
        codes.append(cs)
        _return_freed_memory()
        if interp[cam.name]["interpolated"]:
            log.info("mesh %s: %.0f %% of the decoded pixels share their code with a neighbour "
                     "(the camera out-resolves the projector): codes interpolated over a %d-px "
                     "window, %d pixels kept", cam.name,
                     100 * interp[cam.name]["shared_code_fraction"], interp[cam.name]["window"],
                     interp[cam.name]["pixels"])
    if len(used) < 2:
        lack = list(skipped)
        why = (f"{', '.join(repr(n) for n in lack)} {'has' if len(lack) == 1 else 'have'} no "
               "valid pixel with both x and y codes (a column-only or row-only decode cannot be "
               "matched between cameras)")
        if used:
            why += f", leaving only {used[0].name!r}"
        raise _uncalibrated_projector_error(scan, the_rig, rig_used, why)
    if skipped:
        log.warning("mesh: camera-camera triangulation without %s (%s)", ", ".join(skipped),
                    "; ".join(f"{k}: {v}" for k, v in skipped.items()))
    maps, partners = tr.triangulate_code_sets(
        used, codes, sigma_px=default_sigma_px, max_sigma_ratio=max_sigma_ratio,
        max_chi=max_chi, min_angle_deg=min_angle_deg)
    del codes
    extra = {"partners": partners, "decode_sigma_px": sig, "skipped_cameras": skipped,
             "code_interpolation": interp}
    if fill_min_confidence is not None:
        extra["centroids"] = cens
    return used, maps, extra


def _rejection_thresholds(settings: dict) -> dict:
    """Per rejection reason, the threshold that decided it with its value and the setting (and
    CLI option) that changes it — for :func:`_too_few_points`."""
    angle = settings.get("min_angle_deg")
    angle = (f"min_angle_deg={angle}°" if angle is not None else
             "min_angle_deg from the rig (a quarter of its median ray angle, 0.5–3°)")
    return {
        "no_code": (f"no decoded code, or confidence below min_confidence="
                    f"{settings.get('min_confidence')} (--min-confidence)"),
        "behind": "the rays meet behind a camera",
        "uncertain": (f"rays meeting at less than {angle} (--min-angle-deg), or depth σ above "
                      f"max_sigma_ratio={settings.get('max_sigma_ratio')} × the median "
                      "(stage setting max_sigma_ratio)"),
        "inconsistent": (f"residual above max_chi={settings.get('max_chi')} σ (stage setting "
                         "max_chi)"),
        "outlier": "an isolated depth spike among its 3 × 3 neighbours",
        "free_space_violation": (f"another camera sees through it by more than fuse_sigmas="
                                 f"{settings.get('fuse_sigmas')} σ (stage setting "
                                 "fuse_sigmas)"),
    }


def _too_few_points(scan, rig_used: str, decode_dir: Path, n: int, names: list, maps: list,
                    pair_route: bool, settings: dict | None = None) -> InputError:
    """The one-line :class:`InputError` when triangulation leaves fewer than 10 points: the
    scan and rig first, what rejected the decoded pixels — each reason with its threshold's
    value and the setting that changes it — and what to do when it was the consistency test
    (the rig's geometry does not fit the decodes)."""
    from facegeo.geometry.triangulation import REASONS

    counts = dict.fromkeys(REASONS[2:], 0)
    for m in maps:
        for k, v in m.reason_counts().items():
            if k in counts:
                counts[k] += v
    route = "camera-camera" if pair_route else "camera-projector"
    what = (f"scan {scan.root}: the mesh stage triangulated only {n} points with the "
            f"{rig_used!r} rig ({route} triangulation of cameras {', '.join(names)}, decodes "
            f"in {decode_dir})")
    rejected = {k: v for k, v in sorted(counts.items(), key=lambda kv: -kv[1]) if v}
    if not rejected:
        return InputError(f"{what}; the decode maps hold no usable codes: check the "
                          "structured-light frames and rerun the decode stage (`facegeo decode "
                          f"{scan.root}`)")
    limits = _rejection_thresholds(settings or {})
    why = ", ".join(f"{k} {v} ({limits[k]})" if k in limits else f"{k} {v}"
                    for k, v in rejected.items())
    hint = ""
    if next(iter(rejected)) == "inconsistent":
        if scan.has("calib"):
            fix = (f"run `facegeo calibrate {scan.root}` (its [calib] board views) and mesh "
                   "with --rig calibrated")
        else:
            fix = ("the scan has no [calib] board views to calibrate from: put a calibrated "
                   "rig into its rig.json and mesh with --rig scan")
        residual = ("the epipolar residual between the cameras: the cameras' calibration "
                    "does not fit the decodes" if pair_route
                    else "the camera-projector reprojection residual")
        hint = ("; 'inconsistent' means the codes disagree with the rig's geometry by more "
                f"than max_chi σ ({residual}), as with a nominal rig.json, which is no "
                f"calibration; to fix it, {fix}")
    return InputError(f"{what}; the decoded pixels were rejected as: {why}{hint}")


#: A camera whose decoded pixels disagree with the rig's geometry ('inconsistent') at more than
#: this fraction of those it triangulated is warned about: a calibrated rig loses next to none
#: there (the small preset: 0–5 of ≈ 24,000 a camera, either route), a projector kept at its
#: nominal numbers without calibration all of one camera's (24,885 of 24,885).
INCONSISTENT_WARN_FRACTION = 0.5


def _geometry_warnings(per_cam: dict, pair_route: bool) -> list[str]:
    """Warnings (logged, and listed in the metrics) for cameras that lost most of their
    decoded pixels as inconsistent with the rig: the geometry does not fit the decode."""
    out = []
    for name, c in per_cam.items():
        r = c["rejected"]
        # every pixel that got a triangulation (the rest had no code, or one too uncertain)
        tried = sum(v for k, v in r.items() if k not in ("no_code", "behind", "uncertain"))
        if tried and r.get("inconsistent", 0) > INCONSISTENT_WARN_FRACTION * tried:
            fix = ("the cameras' calibration does not fit the decodes: calibrate them "
                   "(`facegeo calibrate`) and mesh with --rig calibrated" if pair_route else
                   "a projector kept at nominal (datasheet) numbers, or cameras or projector "
                   "moved since calibration? calibrate the projector ([calib.projector] board "
                   "views, `facegeo calibrate`, --rig calibrated), or mark it uncalibrated in "
                   "rig.json (\"calibrated\": false) to mesh camera against camera")
            out.append(f"camera {name}: {r['inconsistent']} of {tried} triangulated pixels "
                       f"({100.0 * r['inconsistent'] / tried:.0f} %) disagree with the rig's "
                       f"geometry ('inconsistent') and were dropped; {fix}")
    for w in out:
        log.warning("mesh: %s", w)
    return out


def _uncalibrated_projector_error(scan, the_rig, rig_used: str, why: str) -> InputError:
    """The one-line :class:`InputError` for a rig whose projector is uncalibrated (a
    :class:`facegeo.geometry.rig.Projector`: resolution only, no intrinsics or pose) when the
    cameras cannot be triangulated against each other either; ``why`` says what is missing."""
    proj = the_rig.projector
    return InputError(
        f"scan {scan.root}: the projector {proj.name!r} of the {rig_used!r} rig is uncalibrated "
        f"(resolution {proj.width} x {proj.height} only, no intrinsics or pose), so the mesh "
        "stage triangulates camera against camera through matching projector codes "
        "(facegeo.geometry.triangulation.triangulate_camera_pairs), which needs two or more "
        f"cameras whose decodes have both x and y codes, and {why}; to mesh from "
        "camera-projector correspondences instead, calibrate the projector: run `facegeo "
        "calibrate` on a scan with projector board views ([calib.projector]) and mesh with "
        "--rig calibrated, or put a calibrated projector into the scan's rig.json and mesh "
        "with --rig scan (rig=PATH from Python)")
