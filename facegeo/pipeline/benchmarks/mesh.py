"""Benchmarks of triangulation and Poisson meshing against the true surface.

Geometry: the procedural head (:func:`facegeo.synth.capture.build_head`) seen by the preset's
nominal rig (``--quick``: the tiny preset's 80 × 120 cameras and 256 × 192 projector; full: the
small preset's 240 × 360 and 512 × 384). Each camera pixel's surface point is ray-cast (Embree),
projected into the projector and turned into decode maps by a **noise model** of the code
(:func:`facegeo.pipeline.mesh.decode_from_surface`, projector shadows included):

* ``gray N bits`` — the column/row code of a Gray sequence with N bits: the decoded coordinate is
  the centre of the stripe ``2**(full − N)`` projector pixels wide holding the true one
  (σ = width/√12); full bits is one code per projector pixel.
* ``phase K steps`` — a K-step phase shift with a 16-pixel period, unwrapped without error:
  Gaussian noise σ = P/(2π) · (σ_I/A) · √(2/K) with image noise 5 % of the fringe amplitude
  (σ_I/A = 0.05; ≈ 0.1 projector px for K = 3, the figure issue 10 calls typical).

Rows:

* ``mesh.points`` — per noise model (``--quick``: full and full − 2 Gray bits, 3 phase steps): throughput of :func:`triangulate_maps` + fusion in
  points/s; error = RMS distance of the fused points to the true surface (mm). Ratio against
  ``cv2.triangulatePoints`` (linear DLT of camera and projector rays after ``undistortPoints``,
  x and y, no rejection) on the same maps, 1 thread each; its own error is in ``extra``.
* ``mesh.poisson_depth`` — Open3D screened Poisson (single-threaded, trimmed) at depths 7–10
  (``--quick`` 6–7) on the fused ``phase 3 steps`` points: input points per second; error = 95th
  percentile distance of the mesh's observed region to the true surface (mm); normal median
  error and face count in ``extra``.
"""

from __future__ import annotations

import time

import numpy as np

from facegeo.pipeline.bench import BenchRow, register

_PHASE_PERIOD_PX = 16.0
_IMAGE_NOISE_REL = 0.05


def _views(quick: bool):
    """Rig, head mesh (V, F), scene and per-camera (p, n, mask) of the procedural head."""
    from facegeo.surface.visibility import RayScene
    from facegeo.synth.capture import PRESETS, build_head, build_rig

    preset = PRESETS["tiny" if quick else "small"]
    rig = build_rig(preset)
    head = build_head(subdivisions=preset.head_subdivisions)
    V, F = np.asarray(head.vertices, np.float64), np.asarray(head.faces, np.int64)
    scene = RayScene(V, F)
    views = []
    for cam in rig.cameras:
        o, d = cam.pixel_rays()
        h = scene.closest_hit(o, d, fields=("point", "normal"))
        n = h.normal.copy()
        flip = np.einsum("...i,...i->...", n, d) > 0
        n[flip] *= -1
        views.append((cam, h.point, n, h.hit))
    return rig, V, F, scene, views


def _gray(n_bits: int, width: int, height: int):
    def quantize(q):
        out = np.empty_like(q)
        sig = None
        for i, size in enumerate((width, height)):
            full = int(np.ceil(np.log2(size)))
            w = 2.0 ** max(full - n_bits, 0)
            col = np.floor(q[..., i] + 0.5)  # the projector pixel holding the point
            out[..., i] = np.floor(col / w) * w + (w - 1) / 2
            sig = w / np.sqrt(12.0)
        return out, sig

    return quantize


def _phase_sigma(steps: int) -> float:
    return _PHASE_PERIOD_PX / (2 * np.pi) * _IMAGE_NOISE_REL * np.sqrt(2.0 / steps)


def _models(proj, quick: bool):
    full = int(np.ceil(np.log2(proj.width)))
    bits, steps = ((full, full - 2), (3,)) if quick else ((full, full - 1, full - 2), (3, 4, 8))
    models = [(f"gray {n} bits", _gray(n, proj.width, proj.height), 0.0) for n in bits]
    models += [(f"phase {k} steps", None, _phase_sigma(k)) for k in steps]
    return models


def _maps(rig, scene, views, quantize, noise, seed=0):
    from facegeo.pipeline.mesh import decode_from_surface

    return [decode_from_surface(p, n, m, rig.projector, scene, noise_px=noise, seed=seed + i,
                                quantize=quantize)
            for i, (_, p, n, m) in enumerate(views)]


def _triangulate(rig, views, maps, *, point_maps: bool = False):
    from facegeo.geometry import triangulation as tr

    pms = [tr.triangulate_maps(cam, rig.projector, d["x"], d["y"], valid=d["valid"],
                               confidence=d["confidence"], sigma_x=d["sigma_x"],
                               sigma_y=d["sigma_y"])
           for (cam, *_), d in zip(views, maps)]
    # each map's points as triangulate_maps left them (fuse_cameras rejects in place)
    before = [(pm.valid.copy(), pm.p_world.copy()) for pm in pms] if point_maps else None
    fused = tr.fuse_cameras(pms, [v[0] for v in views])
    return (fused, before) if point_maps else fused


def _dlt(rig, views, maps, *, point_maps: bool = False):
    """cv2.triangulatePoints of camera and projector rays (x and y), every decoded pixel;
    with ``point_maps`` also each camera's ``(H, W, 3)`` map of them (NaN elsewhere)."""
    import cv2

    proj = rig.projector
    Pp = np.hstack([proj.T_cam_world.R, proj.T_cam_world.t[:, None]])
    out, grids = [], []
    for (cam, *_), d in zip(views, maps):
        ok = d["valid"] & np.isfinite(d["y"])
        rows, cols = np.nonzero(ok)
        qc = np.stack([cols, rows], 1).astype(np.float64)[:, None]
        qp = np.stack([d["x"][ok], d["y"][ok]], 1).astype(np.float64)[:, None]
        uc = cv2.undistortPoints(qc, cam.K, cam.dist).reshape(-1, 2).T
        up = cv2.undistortPoints(qp, proj.K, proj.dist).reshape(-1, 2).T
        Pc = np.hstack([cam.T_cam_world.R, cam.T_cam_world.t[:, None]])
        X = cv2.triangulatePoints(Pc, Pp, uc, up)
        out.append((X[:3] / X[3]).T)
        if point_maps:
            m = np.full(ok.shape + (3,), np.nan)
            m[ok] = out[-1]
            grids.append(m)
    return (np.concatenate(out), grids) if point_maps else np.concatenate(out)


@register("mesh.points")
def bench_points(quick: bool) -> list[BenchRow]:
    from facegeo.geometry.mesh import surface_errors

    rig, V, F, scene, views = _views(quick)
    rows = []
    for name, quantize, noise in _models(rig.projector, quick):
        maps = _maps(rig, scene, views, quantize, noise)
        t0 = time.perf_counter()
        fused, before = _triangulate(rig, views, maps, point_maps=True)
        t = time.perf_counter() - t0
        t0 = time.perf_counter()
        p_dlt, dlt_maps = _dlt(rig, views, maps, point_maps=True)
        t_dlt = time.perf_counter() - t0
        err = surface_errors(fused.p_world, V, F)
        err_dlt = surface_errors(p_dlt, V, F)
        # Like for like (one point per pixel, the same pixels): facegeo's points as
        # triangulate_maps gives them, before fusion (fuse_cameras averages the two cameras'
        # confirmed points: the fused figure gains from that averaging and from rejection,
        # not from the triangulation), and the DLT's points of those pixels.
        err_px = surface_errors(np.concatenate([p[v] for v, p in before]), V, F)
        err_dlt_same = surface_errors(np.concatenate(
            [g[v] for (v, _), g in zip(before, dlt_maps)]), V, F)
        n_px = int(sum(d["valid"].sum() for d in maps))
        rows.append(BenchRow(
            "mesh.points", f"triangulate_maps + fuse_cameras, {name}",
            n_px / t / 1e6, "Mpx/s", 1e3 * float(np.sqrt(np.mean(err**2))),
            "RMS distance of the fused points to the true surface (mm)",
            ratios={"vs cv2.triangulatePoints (DLT, x and y, no rejection)": (n_px / t) / (
                len(p_dlt) / t_dlt)},
            extra={"decoded pixels": n_px, "points": len(fused),
                   "code sigma px": round(float(np.nanmedian(maps[0]["sigma_x"])), 4),
                   "cv2 DLT RMS mm": round(1e3 * float(np.sqrt(np.mean(err_dlt**2))), 4),
                   "facegeo per-pixel RMS mm (its own rejections, before fusion)": round(
                       1e3 * float(np.sqrt(np.mean(err_px**2))), 4),
                   "cv2 DLT RMS mm on those pixels": round(
                       1e3 * float(np.sqrt(np.mean(err_dlt_same**2))), 4),
                   "cv2 DLT max mm": round(1e3 * float(err_dlt.max()), 3),
                   "facegeo max mm": round(1e3 * float(err.max()), 3),
                   "preset": "tiny" if quick else "small"},
            threads=1, baseline_threads={
                "vs cv2.triangulatePoints (DLT, x and y, no rejection)": 1}))
    return rows


@register("mesh.poisson_depth")
def bench_poisson_depth(quick: bool) -> list[BenchRow]:
    from facegeo.geometry import mesh as gm
    from facegeo.geometry.triangulation import neighbour_spacing

    rig, V, F, scene, views = _views(quick)
    maps = _maps(rig, scene, views, None, _phase_sigma(3))
    fused = _triangulate(rig, views, maps)
    normals = gm.oriented_normals(fused.p_world, fused.view_dirs)
    r_obs = 1.5 * neighbour_spacing(fused.p_world)
    rows = []
    for depth in ((6, 7) if quick else (7, 8, 9, 10)):
        t0 = time.perf_counter()
        mesh = gm.poisson_mesh(fused.p_world, normals, depth=depth, max_distance=r_obs)
        t = time.perf_counter() - t0
        _, far = gm.area_beyond(mesh.vertices, mesh.faces, fused.p_world, r_obs)
        S, _ = gm.sample_surface(mesh.vertices, mesh.faces[~far], 50_000)
        d = gm.surface_errors(S, V, F)
        vin = np.unique(mesh.faces[~far])
        _, ang = gm.surface_errors(mesh.vertices[vin], V, F, normals=mesh.vertex_normals[vin])
        rows.append(BenchRow(
            "mesh.poisson_depth", f"Open3D screened Poisson depth {depth}, trimmed",
            len(fused) / t / 1e3, "kpoints/s", 1e3 * float(np.percentile(d, 95)),
            "p95 distance of the observed mesh to the true surface (mm)",
            extra={"seconds": round(t, 3), "faces": len(mesh.faces),
                   "normal median deg": round(float(np.degrees(np.median(ang))), 3),
                   "points": len(fused), "preset": "tiny" if quick else "small"},
            threads=1))
    return rows
