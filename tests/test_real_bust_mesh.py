"""The real two-camera Gray-code bust (shared data, 3DUNDERWORLD "alexander" at 1/4 resolution)
through the CLI: import, decode, mesh — against the scanner's published cloud and an independent
OpenCV code-centroid baseline measured in the same run (issue 34).

Distances to the reference are in millimetres. The reference is a point cloud spaced 0.35 mm
(median nearest neighbour), so a point-to-point distance from a perfect surface's samples is
already ≈ 0.13 mm at the median: the mesh is measured point-to-plane against the reference's
local plane (its 8 nearest points) as well, which is what the surface error is.

Measured (this version, 2 cores): facegeo 137,432 points (the import's decode setting
``rel_contrast = 0.05``; 2,000-odd of them code-region centroid points filling holes), points →
reference 0.161 / 0.361 mm (median / p95); baseline 36,790 points, 0.183 / 0.422 mm; mesh (depth
8 auto, trim auto) point-to-plane 0.049 / 0.241 mm, reference points within 1 mm of the mesh
0.995 (before the hole fill and the import's decode setting: 0.96; docs/mesh.md, *Holes*).
"""

from __future__ import annotations

import numpy as np
import pytest

from conftest import SHARED_DATA

SRC = SHARED_DATA / "structured_light" / "alexander_quarter"

pytestmark = [
    pytest.mark.skipif(not SRC.is_dir(), reason=f"{SRC} is absent (set FACEGEO_SHARED_DATA)"),
    pytest.mark.slow,
]

#: Fused points to the reference cloud, median, mm: at most the baseline's (measured 0.161;
#: the independent baseline 0.183 here, 0.179 in the data set's README).
POINTS_MEDIAN_MM = 0.18
#: Fused points to the reference, 95th percentile, mm (measured 0.361; baseline 0.42–0.47).
POINTS_P95_MM = 0.40
#: Mesh samples to the reference's local plane, median / 95th percentile, mm (measured
#: 0.049 / 0.241; the issue's bounds).
MESH_PLANE_MEDIAN_MM = 0.15
MESH_PLANE_P95_MM = 0.35
#: Reference points within 1 mm of the mesh, fraction (measured 0.995; the issue's bound).
MESH_COVERAGE = 0.99


def _reference(scan) -> np.ndarray:
    import open3d as o3d

    return np.asarray(o3d.io.read_point_cloud(str(scan.reference_path("point_cloud"))).points)


def code_centroid_baseline(scan) -> np.ndarray:
    """The independent baseline of the data set's README: a plain numpy Gray decode of each
    camera (pattern against inverse, a lost pattern against (white + black) / 2, bits from the
    first pair lost dropped), each code's pixels averaged, codes common to both cameras at the
    coarser camera's bits triangulated with ``cv2.undistortPoints`` + ``cv2.triangulatePoints``.
    Returns (N, 3) metres, world frame."""
    import cv2

    def frame(cam, name):
        try:
            return scan.sl_frame(cam, name, luminance=True).astype(np.float32)
        except Exception:
            return None

    def decode(cam):
        w, b = frame(cam, "white"), frame(cam, "black")
        mid = 0.5 * (w + b)
        ok = (w - b) > 0.04
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
                ok_a &= np.abs(d) > 0.01
                g = (g << 1) | (d > 0)
                used += 1
            b_ = g.copy()
            sh = g >> 1
            while sh.any():
                b_ ^= sh
                sh >>= 1
            codes.append((b_, used, ok_a))
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


@pytest.fixture(scope="module")
def bust(tmp_path_factory):
    from facegeo.capture.scan import load_scan
    from facegeo.cli import main

    root = tmp_path_factory.mktemp("bust") / "alexander"
    assert main(["import", "--dataset", "3dunderworld", str(SRC), str(root)]) == 0
    assert main(["mesh", str(root), "-q"]) == 0
    return load_scan(root)


def test_real_bust_meshes_through_the_cli_and_beats_the_baseline(bust):
    import json

    import open3d as o3d
    import trimesh
    from scipy.spatial import cKDTree

    ref = _reference(bust) * 1e3
    tree = cKDTree(ref)
    m = json.loads((bust.out_dir / "metrics.json").read_text())
    # the right camera lost four frames: decoded from what it has
    plan = m["decode"]["cameras"]["right"]["plan"]
    assert plan["bits"]["y"] == 8 and plan["half_pairs"]
    assert m["mesh"]["triangulation"] == "camera-camera"
    # the right camera (8 row bits: 4-row blocks) shares its codes; the left (10 + 10 bits)
    # mostly does not at this resolution
    assert m["mesh"]["code_interpolation"]["right"]["interpolated"]
    # the scan's own decode setting (written by the import) was used; holes were filled
    assert bust.manifest["structured_light"]["decode"] == {"rel_contrast": 0.05}
    assert m["decode"]["settings_from_scan"] == {"rel_contrast": 0.05}
    assert m["mesh"]["hole_fill"]["points"] > 0

    pts = np.asarray(o3d.io.read_point_cloud(str(bust.out_dir / "mesh" / "points.ply")).points)
    d = tree.query(pts * 1e3)[0]
    base = code_centroid_baseline(bust) * 1e3
    db = tree.query(base)[0]
    assert np.median(d) <= min(POINTS_MEDIAN_MM, np.median(db))
    assert np.percentile(d, 95) <= min(POINTS_P95_MM, np.percentile(db, 95))
    assert len(pts) > 3 * len(base)

    tm = trimesh.load(bust.out_dir / "mesh" / "mesh.ply", process=False)
    V = np.asarray(tm.vertices) * 1e3
    tm = trimesh.Trimesh(V, tm.faces, process=False)
    S, _ = trimesh.sample.sample_surface(tm, 100_000, seed=0)
    _, nn = tree.query(S, k=8)
    Q = ref[nn]
    c = Q.mean(1)
    X = Q - c[:, None]
    normal = np.linalg.eigh(np.einsum("nki,nkj->nij", X, X))[1][:, :, 0]
    plane = np.abs(np.einsum("ni,ni->n", S - c, normal))
    near = tree.query(S)[0] < 2.0  # the reference's extent
    assert np.median(plane[near]) <= MESH_PLANE_MEDIAN_MM
    assert np.percentile(plane[near], 95) <= MESH_PLANE_P95_MM
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)),
                        o3d.core.Tensor(np.asarray(tm.faces, np.uint32)))
    dr = scene.compute_distance(o3d.core.Tensor(ref.astype(np.float32))).numpy()
    assert (dr < 1.0).mean() >= MESH_COVERAGE
