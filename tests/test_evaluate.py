"""facegeo.evaluate: stage products against references of any origin, and `facegeo evaluate`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from facegeo.cli import main
from facegeo.errors import InputError

#: The evaluation's figures and the standalone runner's (run_project / run_render: the same
#: comparison reached through the stage's command) agree to this (the issue's 1e-6).
SAME_FIGURE_TOL = 1e-6
#: A sphere of radius 0.1 m: mesh samples to the reference's local plane, median, mm, when the
#: reference cloud sits OFFSET_MM outside the mesh (the icosphere's flat facets lie inside the
#: true sphere by up to ≈ 0.05 mm at subdivision 5, so a loose bound).
OFFSET_MM = 0.5
PLANE_OFFSET_TOL_MM = 0.1
#: The tiny preset's projection figures (the stage reported ≈ 4 % area-weighted with 128 lights
#: on the generator's mesh, visibility agreement 1.0 on 2026-12-02; the bounds of
#: tests/test_reconstruct.py).
PROJECTION_REL_RMSE_TINY = 0.10
VISIBILITY_AGREEMENT_MIN = 0.99
#: Reduced comparison for speed: lights compared and the atlas's density (texels / mm).
TEST_GT_LIGHTS = 8
TEST_TEXELS_PER_MM = 0.3


@pytest.fixture(scope="module")
def projected(tmp_path_factory):
    """A tiny synthetic scan projected on the generator's mesh and rig by the standalone
    runner (which returns the evaluation's figures beside the stage's)."""
    from facegeo.pipeline.project import run_atlas, run_project

    root = tmp_path_factory.mktemp("ev") / "scan"
    assert main(["synth", str(root), "--preset", "tiny", "-q"]) == 0
    run_atlas(root, texels_per_mm=TEST_TEXELS_PER_MM)
    runner = run_project(root, gt_lights=TEST_GT_LIGHTS)
    return root, runner


def test_the_project_stage_writes_no_truth_figures(projected):
    """The stage's own metrics (its manifest) hold no comparison with the generator; what the
    evaluation reads is among its products."""
    root, _ = projected
    doc = json.loads((root / "out" / "project" / "stage.json").read_text())
    for key in ("projection_rel_rmse", "visibility_agreement", "gt_lights"):
        assert key not in doc["metrics"] and key not in doc["settings"], key
    for cam in ("cam_left", "cam_right"):
        assert "visibility_agreement" not in doc["metrics"]["cameras"][cam]
        with np.load(root / "out" / "project" / cam / "visibility.npz") as z:
            assert z["in_image"].dtype == bool and float(z["depth_jump"]) > 0
    assert (root / "out" / "project" / "rig.json").is_file()


def test_facegeo_evaluate_reports_the_projection_as_the_runner_did(projected, capsys):
    root, runner = projected
    capsys.readouterr()
    assert main(["evaluate", str(root), "--gt-lights", str(TEST_GT_LIGHTS), "-q"]) == 0
    printed = capsys.readouterr().out
    assert "projection_rel_rmse" in printed and "metrics:" in printed
    ev = json.loads((root / "out" / "evaluate" / "metrics.json").read_text())["project"]
    assert ev["projection_rel_rmse"] <= PROJECTION_REL_RMSE_TINY
    assert ev["visibility_agreement"] >= VISIBILITY_AGREEMENT_MIN
    compared = 0
    for key, value in ev.items():
        if isinstance(value, float) and not key.startswith("seconds"):
            assert abs(value - runner[key]) <= SAME_FIGURE_TOL, (key, value, runner[key])
            compared += 1
    for cam, entry in ev["cameras"].items():
        for key, value in entry.items():
            if isinstance(value, float) and not key.startswith("seconds"):
                assert abs(value - runner["cameras"][cam][key]) <= SAME_FIGURE_TOL, (cam, key)
                compared += 1
    assert compared >= 20  # 7 overall figures and 9 a camera
    # recorded for the report beside the stages
    doc = json.loads((root / "out" / "metrics.json").read_text())
    assert doc["evaluate"]["project"]["projection_rel_rmse"] == ev["projection_rel_rmse"]
    from facegeo.pipeline.report import summary_rows

    row = {r["stage"]: r for r in summary_rows(doc)}["project"]
    assert row["errors"]["projection_rel_rmse"] == ev["projection_rel_rmse"]


def test_evaluate_without_references_says_so(tmp_path, capsys):
    """A scan whose products have no reference of their kind: nothing compared, said so."""
    from facegeo.evaluate import run_evaluate

    root = tmp_path / "scan"
    assert main(["synth", str(root), "--preset", "tiny", "-q"]) == 0
    m = run_evaluate(root)  # no stage ran: no products
    assert set(m) == {"seconds_by_stage", "seconds"}
    capsys.readouterr()
    assert main(["evaluate", str(root), "-q"]) == 0
    assert "nothing to compare" in capsys.readouterr().out
    assert (root / "out" / "evaluate" / "metrics.json").is_file()


def test_evaluate_refuses_a_bad_setting(projected):
    from facegeo.evaluate import run_evaluate

    root, _ = projected
    with pytest.raises(InputError, match="gt_lights"):
        run_evaluate(root, gt_lights=0)
    with pytest.raises(SystemExit) as exc:  # refused by the parser, before any work
        main(["evaluate", str(root), "--gt-lights", "0"])
    assert exc.value.code == 2


def test_projection_evaluation_needs_the_rig_the_stage_recorded(projected, tmp_path):
    import shutil

    from facegeo.capture.scan import load_scan
    from facegeo.evaluate.projection import evaluate_projection

    root, _ = projected
    out = tmp_path / "out"
    shutil.copytree(root / "out" / "atlas", out / "atlas")
    shutil.copytree(root / "out" / "project", out / "project")
    (out / "project" / "rig.json").unlink()
    with pytest.raises(InputError, match="rig.json is missing"):
        evaluate_projection(load_scan(root), out, gt_lights=TEST_GT_LIGHTS)


def _sphere(radius_m: float):
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=5, radius=radius_m)
    return np.asarray(s.vertices), np.asarray(s.faces)


def test_mesh_to_reference_cloud_measures_a_known_offset():
    """A sphere against a cloud on a sphere OFFSET_MM larger: point-to-plane reads the offset,
    coverage (reference points within 1 mm of the mesh) is whole; at 2 mm it is none."""
    from facegeo.evaluate.cloud import mesh_to_reference

    V, F = _sphere(0.1)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(20_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    near = mesh_to_reference(V, F, d * (0.1 + OFFSET_MM * 1e-3), n_samples=20_000)
    assert abs(near["mesh_to_reference_plane_median_mm"] - OFFSET_MM) <= PLANE_OFFSET_TOL_MM
    # the cloud's spacing adds to point-to-point, never less than the offset
    assert near["mesh_to_reference_median_mm"] >= OFFSET_MM
    assert near["reference_coverage"] == 1.0
    far = mesh_to_reference(V, F, d * (0.1 + 2e-3), n_samples=20_000, extent_mm=5.0)
    assert far["reference_coverage"] == 0.0
    # a reference mesh: the exact surface distance
    Vr, Fr = _sphere(0.1 + OFFSET_MM * 1e-3)
    exact = mesh_to_reference(V, F, Vr, Fr, n_samples=20_000)
    assert abs(exact["mesh_to_reference_plane_median_mm"] - OFFSET_MM) <= PLANE_OFFSET_TOL_MM


def test_intrinsics_and_normal_errors_on_known_answers():
    from facegeo.evaluate.intrinsics import intrinsics_errors
    from facegeo.evaluate.normals import normal_errors
    from facegeo.frames import Pose
    from facegeo.geometry.camera import Camera

    K = np.array([[500.0, 0, 320.0], [0, 510.0, 240.0], [0, 0, 1]])
    cam = Camera("a", 640, 480, np.array([[505.0, 0, 323.0], [0, 510.0, 244.0], [0, 0, 1]]),
                 np.zeros(5), Pose(np.eye(3), np.zeros(3)))
    e = intrinsics_errors(cam, K)
    assert e["focal_rel_error"] == pytest.approx(0.01, abs=1e-12)
    assert e["principal_point_error_px"] == pytest.approx(5.0, abs=1e-12)
    a = np.radians(np.array([1.0, 2.0, 30.0]))
    n = np.stack([np.sin(a), np.zeros(3), np.cos(a)], 1)
    ref = np.array([[0.0, 0.0, 1.0]] * 3)
    ref_nan = np.vstack([ref, [[np.nan] * 3]])
    m = normal_errors(np.vstack([n, [[0.0, 0.0, 1.0]]]), ref_nan)
    assert m["normals_compared"] == 3
    assert m["normal_median_error_deg"] == pytest.approx(2.0, abs=1e-4)
    assert m["normal_mean_error_deg"] == pytest.approx(11.0, abs=1e-4)


@pytest.mark.slow
def test_calibration_figures_equal_the_calibrate_stages(tmp_path):
    """The calibrate stage computed its errors against the generator's rig until issue 35 moved
    them here (the figures of three scans equal before and after to 1.9e-12: docs/calibration.md);
    now the stage's metrics carry none and the evaluation computes them from its rig.json."""
    from facegeo.capture.scan import load_scan
    from facegeo.evaluate.intrinsics import evaluate_calibration
    from facegeo.geometry.rig import Rig
    from facegeo.pipeline import reconstruct
    from facegeo.synth.capture import Preset, generate_scan

    preset = Preset("calibtest", 1 / 2, 4, 2, 3, (64, 48), 12, 1, 3, olat_half=False,
                    sl_supersample=1)
    root = tmp_path / "scan"
    generate_scan(root, preset, seed=0)
    reconstruct.run_reconstruct(root, rig="calibrated", until="calibrate")
    stage = json.loads((root / "out" / "metrics.json").read_text())["calibrate"]
    assert "error" not in stage
    ev = evaluate_calibration(load_scan(root), root / "out")
    rig = Rig.load(root / "out" / "calibrate" / "rig.json")
    truth = Rig.load(root / "ground_truth" / "rig.json")
    compared = 0
    for cam, figures in ev["cameras"].items():
        assert not set(figures) & set(stage["cameras"][cam]), cam  # the stage reads no truth
        c, t = rig.camera(cam), truth.camera(cam)
        assert abs(figures["focal_rel_error"] - max(abs(c.fx / t.fx - 1), abs(c.fy / t.fy - 1))) \
            <= SAME_FIGURE_TOL
        assert abs(figures["principal_point_error_px"] - np.hypot(c.cx - t.cx, c.cy - t.cy)) \
            <= SAME_FIGURE_TOL
        compared += len(figures)
    assert compared == 12  # 6 figures × 2 cameras
    # this preset's projector does not calibrate (too few corners): no projector figures
    assert not (stage.get("projector") or {}).get("calibrated") and "projector" not in ev


#: The tiny preset's mesh against the generator's surface (the bounds of
#: tests/test_reconstruct.py; the mesh stage gave 0.141141 mm / 0.916736 mm / 2.8349° before
#: issue 37 moved the comparison, and the evaluation gives the same to 0 — docs/evaluate.md).
TINY_POINTS_RMS_MM = 0.5
TINY_MESH_P95_MM = 1.0
TINY_MESH_NORMAL_MEDIAN_DEG = 5.0


@pytest.mark.slow
def test_mesh_figures_come_from_the_evaluation(tmp_path):
    """The mesh stage reads no truth (issue 37): it writes its observed region
    (``observed_faces.npy``), and the evaluation, from ``mesh.ply``, ``points.ply`` and that
    region, gives the figures it reported (points RMS, mesh p95 and normal median over the
    observed region) beside the point-to-plane ones."""
    from facegeo.capture.scan import load_scan
    from facegeo.evaluate.cloud import evaluate_mesh_against_reference
    from facegeo.pipeline import reconstruct

    root = tmp_path / "scan"
    assert main(["synth", str(root), "--preset", "tiny", "-q"]) == 0
    # the mesh stage alone: fed the true rig (the figures above were measured with it; the
    # tiny boards calibrate nothing, so the default "auto" would fall back to it after a
    # failed calibration)
    reconstruct.run_reconstruct(root, rig="ground_truth", until="mesh")
    stage = json.loads((root / "out" / "metrics.json").read_text())["mesh"]
    assert not {"points_rms_error_mm", "mesh_p95_error_mm", "normal_median_error_deg"} & set(stage)
    ev = evaluate_mesh_against_reference(load_scan(root), root / "out", n_samples=20_000)
    assert ev["reference"].startswith("generator mesh")
    assert ev["points_rms_error_mm"] <= TINY_POINTS_RMS_MM
    assert ev["mesh_p95_error_mm"] <= TINY_MESH_P95_MM
    assert ev["normal_median_error_deg"] <= TINY_MESH_NORMAL_MEDIAN_DEG
    assert "after_rigid_alignment" not in ev  # the true rig: the generator's own frame
    # the surface error of the mesh itself is of the observed region's order (its p95 is over
    # the observed region only, the point-to-plane over every sample within 2 mm of the head)
    assert ev["mesh_to_reference_plane_p95_mm"] <= 2 * ev["mesh_p95_error_mm"]


@pytest.mark.shared_data
def test_normals_equal_the_image_space_fits_on_diligent(shared_data, tmp_path):
    """An imported DiLiGenT object (real photometric stereo, ``Normal_gt`` as
    ``[reference] normals``): the evaluation, reading out/fit/photometric.npz, reports the
    normal errors the image-space fit stage reports (ball, every pixel of its mask: 3.0017° /
    2.6179° mean / median over 15,791 normals on 2026-12-02)."""
    from conftest import shared_file

    from facegeo.capture.datasets import import_dataset
    from facegeo.capture.scan import load_scan
    from facegeo.evaluate.normals import evaluate_normals
    from facegeo.pipeline.fit import run_fit

    src = shared_file(shared_data, "olat/diligent/ballPNG")
    root = tmp_path / "ball"
    import_dataset("diligent", src, root)
    stage = run_fit(root, max_pixels=3000)
    ev = evaluate_normals(load_scan(root), root / "out")
    assert ev["normals_compared"] == stage["normals_compared"] > 0
    for key in ("normal_mean_error_deg", "normal_median_error_deg"):
        assert abs(ev[key] - stage[key]) <= SAME_FIGURE_TOL, key


# The 3DUNDERWORLD bust through `facegeo evaluate` against the scanner's cloud:
# tests/test_real_bust_mesh.py (one import and mesh of the bust for both).


#: The fit stage's figures on this fixture (tiny scan, atlas 0.3 texel/mm, ``run_fit(root,
#: max_texels=200)``, the comparison's ``gt_functions=64``) before the comparison moved out of
#: pipeline/fit.py (2026-12-02, issue 37; the moved code gave them again to 0 on
#: /tmp/i37fit, docs/evaluate.md). A changed fit moves them: these are bounds, not equalities.
SKIN_FIT_NORMAL_MEDIAN_DEG_MAX = 1.0   # 0.3064° then
SKIN_FIT_ALBEDO_REL_MAX = 0.06        # 0.03117 then
#: Resynthesis at 30° must beat reusing the measured function (0.069 vs 0.516 then).
SKIN_FIT_RESYNTH_VS_NAIVE = 2.0


def test_skin_fit_figures_come_from_the_evaluation(projected, tmp_path):
    """The fit stage reads no truth (issue 37): its metrics hold no figure against the
    generator; ``facegeo evaluate`` (and the reconstruct's evaluate stage) computes them from
    the fit's products with its own settings (gt_functions, gt_angles)."""
    from facegeo.capture.scan import load_scan
    from facegeo.evaluate import run_evaluate
    from facegeo.evaluate.skin_fit import evaluate_skin_fit
    from facegeo.pipeline.fit import run_fit

    root, _ = projected
    stage = run_fit(root, max_texels=200)
    assert not {"gt_valid_functions", "normal_median_error_deg", "resynthesis_rel_rmse_30",
                "gauge_rotation_deg"} & set(stage), sorted(stage)
    m = run_evaluate(root, stages=["fit"], gt_functions=64)
    ev = m["fit"]
    assert "computed_by" not in ev and ev["gt_valid_functions"] == stage["valid_functions"] > 0
    assert json.loads((root / "out" / "metrics.json").read_text())["evaluate"]["fit"] == ev
    assert ev["normal_median_error_deg"] <= SKIN_FIT_NORMAL_MEDIAN_DEG_MAX
    assert ev["albedo_rel_error"] <= SKIN_FIT_ALBEDO_REL_MAX
    assert ev["resynthesis_rel_rmse_30"] * SKIN_FIT_RESYNTH_VS_NAIVE \
        <= ev["resynthesis_naive_rel_rmse_30"]
    # the settings reach the comparison: one angle, fewer functions
    one = evaluate_skin_fit(load_scan(root), root / "out", gt_functions=16, gt_angles=[45])
    assert "resynthesis_rel_rmse_45" in one and "resynthesis_rel_rmse_30" not in one
    assert one["normal_median_error_deg"] == ev["normal_median_error_deg"]  # all valid texels
    for bad in ([30.0, 0.0], [180], [True]):  # 0 would be the source view's own figure
        with pytest.raises(InputError, match="gt_angles"):
            run_evaluate(root, tmp_path / "x", stages=["fit"], gt_angles=bad)


def test_relit_view_figures_come_from_the_evaluation(projected, monkeypatch):
    """A relit camera view (facegeo relight --view CAMERA) against the generator's render
    under the same weights: the relight stage reads no truth; the evaluation, from the files
    written, compares (the OLAT sum reproduces the render: 0 up to float rounding — the
    figures the stage gave before issue 37 moved them: 0.0 / 0.0 over 9,600 pixels), and the
    comparison can fail (weights that forgot Eq. 4's δA)."""
    import facegeo.lighting.relight as RL
    from facegeo.capture.scan import load_scan
    from facegeo.frames import light_solid_angles
    from facegeo.pipeline.relight import run_relight

    root, _ = projected
    scan = load_scan(root)
    stage = run_relight(root, "sky", view="cam_left")
    assert "reference" not in stage and "reference" not in stage["seconds"]
    (figures,) = _relit_figures(scan, root)
    assert figures["computed"] and figures["pixels"] > 0
    assert figures["relative_rmse"] <= RELIT_CONSISTENCY_REL
    assert figures["max_abs_over_max"] <= RELIT_CONSISTENCY_REL
    real = RL.relight_scan_view
    dA = light_solid_angles(scan.rig.lights.n_theta, scan.rig.lights.n_phi)
    monkeypatch.setattr(RL, "relight_scan_view",
                        lambda sc, cam, w, **kw: real(sc, cam, w / dA[:, None], **kw))
    run_relight(root, "sky", view="cam_left")
    (wrong,) = _relit_figures(scan, root)
    assert wrong["relative_rmse"] > RELIT_WRONG_REL_MIN
    monkeypatch.undo()
    run_relight(root, "sky", view="cam_left")  # the module's scan keeps a right relit view


#: A relit view against the generator's render: float32 rounding of the OLAT sum.
RELIT_CONSISTENCY_REL = 1e-5
#: Weights without δA are ≈ 1/δA too bright: far off (relative RMSE measured ≫ 1).
RELIT_WRONG_REL_MIN = 0.5


def _relit_figures(scan, root) -> list[dict]:
    """``facegeo evaluate``'s relit figures per view (the relit views only)."""
    from facegeo.evaluate import run_evaluate

    return list(run_evaluate(scan, stages=["relit"])["relit"]["views"].values())


#: A reference image 10 % brighter than the render: relative RMSE 0.1 / 1.1 over its pixels.
BRIGHTER = 1.1


def test_a_view_is_compared_with_a_reference_image_of_its_camera(projected, tmp_path):
    """A real scan's witness camera: ``[reference] images.<camera>.<env>`` holds its photograph
    under that environment; a view of that camera under that map is compared with it (here the
    render itself, and the render 10 % brighter: known answers)."""
    import shutil

    from facegeo.capture import imageio
    from facegeo.capture.scan import load_scan
    from facegeo.evaluate.views import evaluate_view_against_image
    from facegeo.pipeline.render import run_render

    root, _ = projected
    m = run_render(root, camera_spec="cam_right", env="sky", resynthesis=False, name="w",
                   reference=False)
    views = root / "out" / "views"
    img = imageio.read_image(views / "w.exr")
    scan_copy = tmp_path / "scan"
    shutil.copytree(root, scan_copy, ignore=shutil.ignore_patterns("out"))
    (scan_copy / "reference").mkdir()
    imageio.write_image(scan_copy / "reference" / "same.exr", img)
    imageio.write_image(scan_copy / "reference" / "brighter.exr", img * np.float32(BRIGHTER))
    manifest = scan_copy / "scan.toml"
    base = manifest.read_text(encoding="utf-8")
    got = {}
    for name in ("same", "brighter"):
        manifest.write_text(base + f'\n[reference.images.cam_right]\nsky = "reference/{name}.exr"\n',
                            encoding="utf-8")
        got[name] = evaluate_view_against_image(load_scan(scan_copy), views, m["name"])
    assert got["same"]["rel_rmse"] == 0.0 and got["same"]["psnr_db"] is None  # no error
    assert got["brighter"]["rel_rmse"] == pytest.approx((BRIGHTER - 1) / BRIGHTER, abs=1e-5)
    assert got["brighter"]["mask_pixels"] == int((img.max(axis=2) > 0).sum())
    manifest.write_text(base, encoding="utf-8")  # no reference image of it: None
    assert evaluate_view_against_image(load_scan(scan_copy), views, m["name"]) is None
