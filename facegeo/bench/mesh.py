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
* ``mesh.full_resolution`` — decode + mesh of two 16-Mpx cameras with an uncalibrated projector
  (issue 34; ``--quick`` at 1/16 scale): wall time and peak resident memory of each stage in
  its own subprocess, decode errors against the true codes, fused points against the analytic
  ellipsoid (:func:`bench_full_resolution`); ``FACEGEO_BENCH_PREVIOUS=/path/to/checkout``
  adds that checkout's mesh stage on the same decode maps.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from facegeo.bench import BenchRow, register

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


# ------------------------------------------------------------------ full resolution (issue 34)
#
# Two 16-Mpx cameras 20° apart and an uncalibrated 1024 × 768 projector (the real bust's rig at
# full resolution) looking at an analytic head-sized ellipsoid; 42 Gray-code frames per camera
# rendered from the true projector pixel of every camera pixel, the right camera without its
# two finest row bits (8 row bits, as the real right camera). Decode and mesh each run in a
# subprocess of their own so that each peak resident memory is the stage's.

#: Full-resolution camera size (the real bust's cameras), pixels.
_FULL_SIZE = (4896, 3264)
#: Ellipsoid centre (m, world) and semi-axes (m): a head-sized surface, off every axis.
_ELLIPSOID_C = np.array([0.003, -0.004, 0.0])
_ELLIPSOID_A = np.array([0.085, 0.115, 0.095])
#: Gaussian noise of the true projector coordinate before the Gray quantisation, projector px.
_CODE_NOISE_PX = 0.1
#: Frames the right camera lacks (its two finest row bits: 8 row bits, 4-row code blocks).
_RIGHT_MISSING = ("gray_y_08", "gray_y_08_inv", "gray_y_09", "gray_y_09_inv")
#: Rows per block of the generator (its temporaries ≈ 0.3 kB a pixel).
_GEN_ROWS = 128


def _ellipsoid_rig(scale: float = 1.0):
    """The true rig (calibrated projector) of the full-resolution benchmark at ``scale``."""
    from facegeo.frames import look_at
    from facegeo.geometry.camera import Camera
    from facegeo.geometry.rig import Rig

    W, H = (round(_FULL_SIZE[0] * scale), round(_FULL_SIZE[1] * scale))

    def cam(name, eye, up, f, c):
        K = np.array([[f[0] * scale, 0.0, (c[0] + 0.5) * scale - 0.5],
                      [0.0, f[1] * scale, (c[1] + 0.5) * scale - 0.5], [0.0, 0.0, 1.0]])
        return Camera(name, W, H, K, None, look_at(eye, _ELLIPSOID_C, up=up))

    left = cam("left", [0.172, 0.021, -0.978], (0.0, 1.0, 0.0), (11800.0, 11760.0),
               (2441.7, 1627.2))
    right = cam("right", [-0.168, -0.012, -0.962], (0.06, 1.0, 0.0), (11650.0, 11700.0),
                (2460.3, 1610.9))
    K = np.array([[2600.0, 0.0, 515.2], [0.0, 2590.0, 380.9], [0.0, 0.0, 1.0]])
    proj = Camera("projector", 1024, 768, K, None,
                  look_at([0.011, 0.118, -0.921], _ELLIPSOID_C, up=(0.0, 1.0, 0.0)))
    return Rig([left, right], proj, None)


def _ellipsoid_hits(cam, proj, r0: int, r1: int):
    """Rows ``r0:r1`` of ``cam``: the true projector pixel of each camera pixel's ellipsoid
    point ``(rows, W, 2)`` float64 and whether the projector lights it ``(rows, W)`` bool."""
    cols, rows = np.meshgrid(np.arange(cam.width, dtype=np.float64),
                             np.arange(r0, r1, dtype=np.float64))
    o, d = cam.pixel_rays(np.stack([cols, rows], -1))
    u0 = (o - _ELLIPSOID_C) / _ELLIPSOID_A
    ud = d / _ELLIPSOID_A
    a = np.einsum("...i,...i->...", ud, ud)
    b = np.einsum("...i,...i->...", u0, ud)
    c = np.einsum("...i,...i->...", u0, u0) - 1.0
    disc = b * b - a * c
    hit = disc > 0
    t = (-b - np.sqrt(np.where(hit, disc, 0.0))) / a
    p = o + t[..., None] * d
    n = (p - _ELLIPSOID_C) / _ELLIPSOID_A**2
    q, front = proj.project(np.where(hit[..., None], p, 0.0))
    lit = hit & front & proj.in_image(q)
    lit &= np.einsum("...i,...i->...", n, proj.center_world - p) > 0
    return q, lit


def ellipsoid_distance(p) -> np.ndarray:
    """Distance of points ``(N, 3)`` (metres, world) to the benchmark's ellipsoid, metres:
    ``f / |∇f|`` with ``f = |(p − c)/a| − 1`` (exact to first order in the distance, which is
    ≪ the radii of curvature here)."""
    u = (np.asarray(p, np.float64) - _ELLIPSOID_C) / _ELLIPSOID_A
    r = np.linalg.norm(u, axis=-1)
    grad = u / r[..., None] / _ELLIPSOID_A
    return np.abs(r - 1.0) / np.linalg.norm(grad, axis=-1)


def _ellipsoid_pixels(cam, proj, seed: int):
    """Each camera pixel's projector pixel (with the code noise), ``(H, W)`` int16 per axis,
    −1 where the projector does not light the ellipsoid there (or nothing is seen)."""
    rng = np.random.default_rng(seed)
    ix = np.full((cam.height, cam.width), -1, np.int16)
    iy = np.full((cam.height, cam.width), -1, np.int16)
    for r0 in range(0, cam.height, _GEN_ROWS):
        r1 = min(cam.height, r0 + _GEN_ROWS)
        q, lit = _ellipsoid_hits(cam, proj, r0, r1)
        q = q + rng.normal(0.0, _CODE_NOISE_PX, q.shape)
        k = np.floor(q + 0.5)
        lit &= (k[..., 0] >= 0) & (k[..., 0] < proj.width) & (k[..., 1] >= 0) & (
            k[..., 1] < proj.height)
        ix[r0:r1] = np.where(lit, k[..., 0], -1)
        iy[r0:r1] = np.where(lit, k[..., 1], -1)
    return ix, iy


def _ellipsoid_frames(ix, iy, spec, names):
    """The named Gray-code frames ``(H, W)`` uint8 of one camera, one at a time (the Gray
    code of each pixel's stripe is computed once per axis, int16)."""
    lit = ix >= 0
    on, dark = np.uint8(200), np.uint8(6)  # albedo × projector white; ambient
    gray = {}
    for axis, i in (("x", ix), ("y", iy)):
        stripe = np.maximum(i, 0) >> spec.stripe_shift(axis)
        gray[axis] = stripe ^ (stripe >> 1)
        del stripe
    for name in names:
        if name in ("white", "black"):
            yield name, np.where(lit, on if name == "white" else dark, dark)
            continue
        _, axis, bit, *inv = name.split("_")
        v = ((gray[axis] >> (spec.n_bits(axis) - 1 - int(bit))) & 1).astype(bool)
        if inv:
            v = ~v
        yield name, np.where(lit & v, on, dark)


def write_full_resolution_scan(root, scale: float = 1.0) -> Path:
    """A scan folder with the full-resolution benchmark's rig (projector uncalibrated): the
    cameras and ``rig.json`` only; decode maps go into ``root/out/decode``."""
    from facegeo.capture.scan import new_manifest, write_manifest
    from facegeo.geometry.rig import Projector, Rig

    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    true = _ellipsoid_rig(scale)
    p = true.projector
    Rig(true.cameras, Projector(p.name, p.width, p.height), None).save(root / "rig.json")
    man = new_manifest("full_resolution_ellipsoid", synthetic=False, description=(
        "facegeo.bench.mesh: two cameras 20 degrees apart, an analytic "
        "ellipsoid, an uncalibrated 1024 x 768 projector"))
    write_manifest(root, man, overwrite=True)
    return root


def decode_full_resolution(root, scale: float = 1.0, seed: int = 0) -> dict:
    """Decode both cameras of :func:`write_full_resolution_scan` from their 42 (right: 38)
    Gray-code frames, streamed, into ``root/out/decode/<camera>/decode.npz``; returns
    ``{"seconds", "seconds_frames", "valid_fraction", "lit_pixels", "wrong_codes",
    "undecoded_lit_pixels"}`` (frame rendering timed apart; a wrong code: a lit pixel decoded
    to another block than the one of its true, noisy projector pixel)."""
    from facegeo.fsutil import atomic_path
    from facegeo.geometry.structured_light import (PatternSpec, decode_stream, pattern_names,
                                                   plan_camera_decode, with_stand_in_partners)
    from facegeo.pipeline.decode import DECODE_DEFAULTS

    root = Path(root)
    rig = _ellipsoid_rig(scale)
    spec = PatternSpec(width=1024, height=768, phase_steps=0)
    out = {"seconds": 0.0, "seconds_frames": 0.0, "valid_fraction": {}}
    for i, cam in enumerate(rig.cameras):
        t0 = time.perf_counter()
        ix, iy = _ellipsoid_pixels(cam, rig.projector, seed + i)
        have = [n for n in pattern_names(spec)
                if not (cam.name == "right" and n in _RIGHT_MISSING)]
        plan = plan_camera_decode(spec, have, camera=cam.name)
        t_gen = time.perf_counter() - t0
        timed = _timed(_ellipsoid_frames(ix, iy, plan.spec, plan.frames))
        res = decode_stream(with_stand_in_partners(timed, plan), plan.spec, **DECODE_DEFAULTS)
        # the true code: the block centre of each lit pixel's projector pixel (noise included)
        lit = ix >= 0
        wrong, lit_n = 0, int(lit.sum())
        for axis, i, dec in (("x", ix, res.x), ("y", iy, res.y)):
            w = 1 << plan.spec.stripe_shift(axis)
            true = (i.astype(np.float64) // w) * w + (w - 1) / 2.0
            wrong += int(np.count_nonzero(res.valid & lit & (dec != true)))
            del true
        out["wrong_codes"] = out.get("wrong_codes", 0) + wrong
        out["lit_pixels"] = out.get("lit_pixels", 0) + lit_n
        out["undecoded_lit_pixels"] = out.get("undecoded_lit_pixels", 0) + int(
            np.count_nonzero(lit & ~res.valid))
        del ix, iy, lit
        d = root / "out" / "decode" / cam.name
        d.mkdir(parents=True, exist_ok=True)
        with atomic_path(d / "decode.npz") as tmp, open(tmp, "wb") as fh:
            np.savez(fh, x=res.x, y=res.y, confidence=res.confidence, valid=res.valid,
                     sigma_x=res.sigma_x, sigma_y=res.sigma_y)
        out["valid_fraction"][cam.name] = round(float(res.valid.mean()), 4)
        del res
        out["seconds"] += time.perf_counter() - t0
        out["seconds_frames"] += t_gen + timed.seconds
    return out


class _timed:
    """An iterator wrapper that adds up the time spent producing its items."""

    def __init__(self, it):
        self.it, self.seconds = iter(it), 0.0

    def __iter__(self):
        return self

    def __next__(self):
        t0 = time.perf_counter()
        try:
            return next(self.it)
        finally:
            self.seconds += time.perf_counter() - t0


#: The mesh stage's worker: self-contained (the public stage API and ``/proc``), so that
#: ``FACEGEO_BENCH_PREVIOUS``'s checkout runs it too. Prints one JSON line.
_MESH_WORKER = """
import json, sys, time
import numpy as np
from facegeo.capture.scan import load_scan
from facegeo.pipeline.mesh import mesh_products, read_points_ply
root, dest = sys.argv[1], sys.argv[2]
scan = load_scan(root)
t0 = time.perf_counter()
m, _ = mesh_products(scan, scan.out_dir / "decode", dest)
seconds = time.perf_counter() - t0
peak = [float(l.split()[1]) / 1024 for l in open("/proc/self/status") if l.startswith("VmHWM")]
pts = read_points_ply(dest + "/points.ply")
p = np.stack([pts["x"], pts["y"], pts["z"]], 1)
u = (p - np.array(C)) / np.array(A)
r = np.linalg.norm(u, axis=1)
d = np.abs(r - 1.0) / np.linalg.norm(u / r[:, None] / np.array(A), axis=1)
print(json.dumps({"seconds": seconds, "peak_rss_mb": peak[0], "points": m["points"],
                  "faces": m["faces"], "depth": m["mesh"]["depth"],
                  "steps": {k: v for k, v in m.items() if k.startswith("seconds_")},
                  "rms_mm": 1e3 * float(np.sqrt(np.mean(d ** 2))),
                  "p95_mm": 1e3 * float(np.percentile(d, 95)),
                  "median_mm": 1e3 * float(np.median(d))}))
"""

_DECODE_WORKER = """
import json, sys, time
from facegeo.bench.mesh import decode_full_resolution
root, scale = sys.argv[1], float(sys.argv[2])
r = decode_full_resolution(root, scale)
r["peak_rss_mb"] = [float(l.split()[1]) / 1024 for l in open("/proc/self/status")
                    if l.startswith("VmHWM")][0]
print(json.dumps(r))
"""

#: Threads of the workers (numpy's BLAS, OpenMP in Open3D, numba): one, stated in the rows.
_WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
               "NUMBA_NUM_THREADS": "1"}


def _worker(script: str, args: list, checkout) -> dict:
    """Run a worker script in a fresh interpreter with ``checkout`` first on ``sys.path``:
    its own process, so its peak resident memory is its own."""
    import json
    import os
    import subprocess
    import sys

    from facegeo.errors import InputError

    env = {**os.environ, **_WORKER_ENV, "PYTHONPATH": str(checkout)}
    script = script.replace("np.array(C)", f"np.array({list(map(float, _ELLIPSOID_C))})").replace(
        "np.array(A)", f"np.array({list(map(float, _ELLIPSOID_A))})")
    run = subprocess.run([sys.executable, "-c", script, *map(str, args)], capture_output=True,
                         text=True, env=env, cwd=str(checkout))
    if run.returncode != 0:
        raise InputError(f"benchmark worker ({checkout}) failed: {run.stderr.strip()[-2000:]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


@register("mesh.full_resolution")
def bench_full_resolution(quick: bool) -> list[BenchRow]:
    """Decode + mesh of two 16-Mpx cameras (issue 34): wall time and peak resident memory.

    The rig and surface of :func:`_ellipsoid_rig` (``--quick``: at 1/16 scale, 306 × 204
    cameras): two 4896 × 3264 cameras 20° apart, a 1024 × 768 projector left uncalibrated
    (camera–camera triangulation), an analytic head-sized ellipsoid (≈ 27 % of each image
    decoded). The decode renders each camera's 42 Gray-code frames (the right camera 38: its
    two finest row bits lost, as the real bust's) as 8-bit images from every pixel's true
    projector pixel (0.1 px noise), streamed into
    :func:`facegeo.geometry.structured_light.decode_stream` one at a time, and writes the
    decode maps; the mesh stage (:func:`facegeo.pipeline.mesh.mesh_products`, defaults) reads
    them. Each runs in a subprocess of its own at one thread (BLAS, OpenMP, numba), so each
    peak resident memory (``VmHWM``) is that stage's alone, libraries included. Rows: decode,
    mesh, decode + mesh (wall time without the frame rendering; peak the larger of the two),
    and with ``FACEGEO_BENCH_PREVIOUS=/path/to/checkout`` the previous checkout's mesh stage
    on the same decode maps (the full-grid version needs ≈ 10 GB at full size). Errors:
    decode — lit pixels decoded to another code block than the true one; mesh — RMS distance
    of the fused points to the ellipsoid (mm; median and p95 in ``extra``).
    """
    import os
    import tempfile

    import facegeo

    scale = 1 / 16 if quick else 1.0
    here = Path(facegeo.__file__).resolve().parent.parent
    previous = os.environ.get("FACEGEO_BENCH_PREVIOUS")
    W, H = round(_FULL_SIZE[0] * scale), round(_FULL_SIZE[1] * scale)
    mpx = 2 * W * H / 1e6
    size = {"cameras": f"2 x {W} x {H}", "projector": "1024 x 768, uncalibrated",
            "frames": "42 (right: 38, 8 row bits)"}
    with tempfile.TemporaryDirectory(prefix="facegeo-bench-fullres-") as d:
        root = write_full_resolution_scan(Path(d) / "scan", scale)
        dec = _worker(_DECODE_WORKER, [root, scale], here)
        (Path(d) / "mesh").mkdir()
        mesh = _worker(_MESH_WORKER, [root, Path(d) / "mesh"], here)
        prev = None
        if previous:
            (Path(d) / "mesh_previous").mkdir()
            prev = _worker(_MESH_WORKER, [root, Path(d) / "mesh_previous"],
                           Path(previous).resolve())
    t_dec = dec["seconds"] - dec["seconds_frames"]
    err = "RMS distance of the fused points to the analytic ellipsoid (mm)"

    def mesh_extra(m):
        return {**size, "seconds": round(m["seconds"], 1), "points": m["points"],
                "faces": m["faces"], "Poisson depth": m["depth"],
                "median mm": round(m["median_mm"], 4), "p95 mm": round(m["p95_mm"], 4),
                **{k: round(v, 1) for k, v in m["steps"].items()}}

    rows = [
        BenchRow("mesh.full_resolution",
                 "decode: 42 Gray-code frames per camera, 8-bit, streamed (decode_stream), "
                 "subprocess", mpx / t_dec, "Mpx/s",
                 dec["wrong_codes"] / max(dec["lit_pixels"], 1),
                 "fraction of lit pixels decoded to another code block than the true one",
                 extra={**size, "seconds (frames rendered apart)": round(t_dec, 1),
                        "seconds rendering frames": round(dec["seconds_frames"], 1),
                        "lit pixels undecoded": dec["undecoded_lit_pixels"],
                        "valid fraction": dec["valid_fraction"]},
                 threads=1, peak_rss_mb=round(dec["peak_rss_mb"], 1)),
        BenchRow("mesh.full_resolution",
                 "mesh stage (mesh_products: camera-camera, fusion, normals, Poisson), "
                 "subprocess", mpx / mesh["seconds"], "Mpx/s", mesh["rms_mm"], err,
                 ratios={} if prev is None else {
                     "vs previous checkout's mesh stage": prev["seconds"] / mesh["seconds"]},
                 extra=mesh_extra(mesh), threads=1,
                 baseline_threads={} if prev is None else {
                     "vs previous checkout's mesh stage": 1},
                 peak_rss_mb=round(mesh["peak_rss_mb"], 1)),
        BenchRow("mesh.full_resolution",
                 "decode + mesh, two cameras (peak: the larger stage's)",
                 mpx / (t_dec + mesh["seconds"]), "Mpx/s", mesh["rms_mm"], err,
                 extra={**size, "seconds": round(t_dec + mesh["seconds"], 1),
                        "decode peak MiB": round(dec["peak_rss_mb"], 1),
                        "mesh peak MiB": round(mesh["peak_rss_mb"], 1)},
                 threads=1, peak_rss_mb=round(max(dec["peak_rss_mb"], mesh["peak_rss_mb"]), 1)),
    ]
    if prev is not None:
        rows.append(BenchRow(
            "mesh.full_resolution", f"previous checkout's mesh stage ({previous}), subprocess",
            mpx / prev["seconds"], "Mpx/s", prev["rms_mm"], err,
            extra=mesh_extra(prev), threads=1, peak_rss_mb=round(prev["peak_rss_mb"], 1)))
    return rows
