"""The real two-camera Gray-code bust (shared data, 3DUNDERWORLD "alexander" at 1/4 resolution)
through the CLI: import, decode, mesh, evaluate — against the scanner's published cloud and an
independent OpenCV code-centroid baseline measured in the same run (issues 34, 37: the figures
are `facegeo evaluate`'s, facegeo.evaluate.cloud; `facegeo bench mesh.real_bust` prints both
side by side).

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
from facegeo.bench.real_bust import code_centroid_baseline

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


@pytest.fixture(scope="module")
def bust(tmp_path_factory):
    from facegeo.capture.scan import load_scan
    from facegeo.cli import main

    root = tmp_path_factory.mktemp("bust") / "alexander"
    assert main(["import", "--dataset", "3dunderworld", str(SRC), str(root)]) == 0
    assert main(["mesh", str(root), "-q"]) == 0
    return load_scan(root)


def test_real_bust_meshes_through_the_cli_and_beats_the_baseline(bust, capsys):
    import json

    from scipy.spatial import cKDTree

    ref = _reference(bust) * 1e3
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

    # facegeo's figures from `facegeo evaluate` (facegeo.evaluate.cloud): the mesh and points
    # against the scanner's cloud
    from facegeo.cli import main

    capsys.readouterr()
    assert main(["evaluate", str(bust.root), "-q"]) == 0
    assert "mesh_to_reference_plane_median_mm" in capsys.readouterr().out
    ev = json.loads((bust.out_dir / "evaluate" / "metrics.json").read_text())["mesh"]
    assert ev["reference"].startswith("reference point_cloud")
    base = code_centroid_baseline(bust) * 1e3
    db = cKDTree(ref).query(base)[0]
    assert ev["points_to_reference_median_mm"] <= min(POINTS_MEDIAN_MM, np.median(db))
    assert ev["points_to_reference_p95_mm"] <= min(POINTS_P95_MM, np.percentile(db, 95))
    assert m["mesh"]["points"] > 3 * len(base)
    assert ev["mesh_to_reference_plane_median_mm"] <= MESH_PLANE_MEDIAN_MM
    assert ev["mesh_to_reference_plane_p95_mm"] <= MESH_PLANE_P95_MM
    assert ev["reference_coverage"] >= MESH_COVERAGE
    # point-to-point includes the cloud's 0.35 mm spacing: above the point-to-plane figure
    assert ev["mesh_to_reference_median_mm"] > ev["mesh_to_reference_plane_median_mm"]
