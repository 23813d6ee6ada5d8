"""Benchmark ``mesh.real_bust``: the real two-camera Gray-code bust of the shared data
(3DUNDERWORLD "alexander" at 1/4 resolution, ``structured_light/alexander_quarter``) through
facegeo's import, decode and mesh stages, beside an independent code-centroid baseline on the
same frames, both measured against the scanner's published cloud in one run (issue 34).

The baseline (:func:`code_centroid_baseline`) is what the data set's README describes and
what a user would write with OpenCV: a plain numpy Gray decode of each camera, each code's
pixels averaged, codes common to both cameras triangulated with ``cv2.undistortPoints`` +
``cv2.triangulatePoints``. It makes points only; facegeo makes points and a mesh. Figures from
:func:`facegeo.evaluate.cloud.mesh_to_reference` (mm; coverage = reference points within 1 mm
of the mesh, or of the baseline's points). No speed ratio: the two make different products
(facegeo a mesh, its decode and Poisson on every core; the baseline points on one thread), so
each row states its own threads and seconds. No rows when the shared data is absent.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

from facegeo.bench import BenchRow, register, shared_data_dir

__all__ = ["bench_real_bust", "code_centroid_baseline"]

#: Contrast below which the baseline drops a pixel (white − black, linear), and a bit
#: (|pattern − inverse|): the README's baseline.
_BASELINE_LIT = 0.04
_BASELINE_BIT = 0.01


def code_centroid_baseline(scan) -> np.ndarray:
    """The independent baseline of the data set's README: a plain numpy Gray decode of each
    camera (pattern against inverse, a lost pattern against (white + black) / 2, bits from the
    first pair lost dropped), each code's pixels averaged, codes common to both cameras at the
    coarser camera's bits triangulated with ``cv2.undistortPoints`` + ``cv2.triangulatePoints``.

    Parameters
    ----------
    scan : Scan
        A two-camera Gray-code scan with ``gray_{x,y}_NN`` / ``_inv`` and ``white`` / ``black``
        frames (the 3DUNDERWORLD import).

    Returns
    -------
    (N, 3) float64, metres, world frame
    """
    import cv2

    def frame(cam, name):
        try:
            return scan.sl_frame(cam, name, luminance=True).astype(np.float32)
        except Exception:  # a lost frame
            return None

    def decode(cam):
        w, b = frame(cam, "white"), frame(cam, "black")
        mid = 0.5 * (w + b)
        ok = (w - b) > _BASELINE_LIT
        codes = []
        for axis in ("x", "y"):
            g = np.zeros(w.shape, np.int64)
            used = 0
            ok_a = ok.copy()
            for i in range(10):
                p, q = frame(cam, f"gray_{axis}_{i:02d}"), frame(cam, f"gray_{axis}_{i:02d}_inv")
                if p is None and q is None:
                    break
                d = (p if p is not None else mid) - (q if q is not None else mid)
                ok_a &= np.abs(d) > _BASELINE_BIT
                g = (g << 1) | (d > 0)
                used += 1
            binary = g.copy()
            sh = g >> 1
            while sh.any():
                binary ^= sh
                sh >>= 1
            codes.append((binary, used, ok_a))
        return codes

    dec = {c: decode(c) for c in scan.camera_names}
    used = [min(dec[c][a][1] for c in dec) for a in (0, 1)]
    cent = {}
    for c, ((cx, ux, okx), (cy, uy, oky)) in dec.items():
        ok = okx & oky
        key = ((cx >> (ux - used[0])) << 16) | (cy >> (uy - used[1]))
        rr, cc = np.nonzero(ok)
        uniq, inv, cnt = np.unique(key[ok], return_inverse=True, return_counts=True)
        cent[c] = dict(zip(uniq.tolist(), zip(np.bincount(inv, cc) / cnt,
                                              np.bincount(inv, rr) / cnt)))
    a, b = scan.camera_names[:2]
    common = sorted(set(cent[a]) & set(cent[b]))
    P = []
    for c in (a, b):
        cam = scan.rig.camera(c)
        q = np.array([cent[c][k] for k in common], np.float64).reshape(-1, 1, 2)
        P.append((cv2.undistortPoints(q, cam.K, cam.dist).reshape(-1, 2),
                  np.hstack([cam.T_cam_world.R, cam.T_cam_world.t[:, None]])))
    X = cv2.triangulatePoints(P[0][1], P[1][1], P[0][0].T, P[1][0].T)
    return (X[:3] / X[3]).T


def _coverage_by_points(points, ref, radius_mm: float = 1.0) -> float:
    from scipy.spatial import cKDTree

    return float((cKDTree(np.asarray(points) * 1e3).query(np.asarray(ref) * 1e3)[0]
                  < radius_mm).mean())


@register("mesh.real_bust")
def bench_real_bust(quick: bool) -> list[BenchRow]:
    import open3d as o3d
    import trimesh
    from scipy.spatial import cKDTree
    from threadpoolctl import threadpool_limits

    from facegeo.capture.datasets import import_dataset
    from facegeo.capture.scan import load_scan
    from facegeo.evaluate.cloud import mesh_to_reference
    from facegeo.pipeline.reconstruct import run_reconstruct

    src = shared_data_dir() / "structured_light" / "alexander_quarter"
    if not src.is_dir():
        return []
    rows = []
    with tempfile.TemporaryDirectory(prefix="facegeo-bench-bust-") as tmp:
        root = Path(tmp) / "alexander"
        import_dataset("3dunderworld", src, root)
        scan = load_scan(root)
        ref = np.asarray(o3d.io.read_point_cloud(str(scan.reference_path("point_cloud"))).points)
        with threadpool_limits(1):
            t0 = time.perf_counter()
            base = code_centroid_baseline(scan)
            t_base = time.perf_counter() - t0
        t0 = time.perf_counter()
        run_reconstruct(scan, until="mesh")
        t_ours = time.perf_counter() - t0
        mesh = trimesh.load(scan.out_dir / "mesh" / "mesh.ply", process=False)
        pts = np.asarray(o3d.io.read_point_cloud(
            str(scan.out_dir / "mesh" / "points.ply")).points)
        fig = mesh_to_reference(np.asarray(mesh.vertices), np.asarray(mesh.faces), ref,
                                points=pts)
        d_base = cKDTree(ref * 1e3).query(base * 1e3)[0]
        rows.append(BenchRow(
            "mesh.real_bust", "facegeo import defaults: decode + mesh (camera-camera, hole fill)",
            len(pts) / t_ours, "points/s", fig["points_to_reference_median_mm"],
            "points to the scanner's cloud, median (mm)",
            extra={"points": len(pts), "seconds": round(t_ours, 2),
                   "points p95 mm": fig["points_to_reference_p95_mm"],
                   "mesh point-to-plane median / p95 mm": (
                       fig["mesh_to_reference_plane_median_mm"],
                       fig["mesh_to_reference_plane_p95_mm"]),
                   "reference within 1 mm of the mesh": fig["reference_coverage"]},
            threads=len(os.sched_getaffinity(0))))
        rows.append(BenchRow(
            "mesh.real_bust", "code-centroid baseline (numpy Gray decode, cv2.triangulatePoints)",
            len(base) / t_base, "points/s", round(float(np.median(d_base)), 6),
            "points to the scanner's cloud, median (mm)",
            extra={"points": len(base), "seconds": round(t_base, 2),
                   "points p95 mm": round(float(np.percentile(d_base, 95)), 6),
                   "reference within 1 mm of the points": round(
                       _coverage_by_points(base, ref), 6)},
            threads=1))
    return rows
