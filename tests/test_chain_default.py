"""Issue 37: the chain is the default. ``reconstruct`` with ``--rig auto --mesh auto`` runs the
whole chain — the calibrated rig when the boards calibrate, the reconstructed mesh whenever the
scan has structured light, synthetic or not — and the stage-alone figures (the same stages fed
the generator's rig and mesh) are a diagnostic pass of their own (``out/diagnostic/``).

The figures asserted here are the chain's, with the values measured on 2026-12-02 in the
comments (seed 0; ``facegeo demo SCAN --preset tiny|small`` prints both columns).
"""

from __future__ import annotations

import json

import pytest

from facegeo.pipeline import reconstruct

# --------------------------------------------------------------------------- tolerances
# tiny preset (80 × 120 px cameras): the boards show no marker, so "auto" falls back to the
# generator's rig; the mesh is the chain's own (camera–projector structured light)
#: projection against the generator's exact shading, on the reconstructed mesh (measured 8.10 %;
#: 8.08 % on the filled surface's measured texels; 7.26 % with the silhouettes' rim points,
#: 2026-12-03; stage alone, on the true mesh: 4.04 %)
TINY_PROJECTION_REL_RMSE = 0.10
#: novel views: PSNR gain over the naive render on covered pixels, worst of the four orbits
#: (measured +1.19 dB; on the filled surface +1.72 dB at +30°, 2026-12-02; with the
#: silhouettes' rim points +2.80 dB at −30°, 2026-12-03; stage alone +2.16 dB)
TINY_GAIN_COVERED_DB = 2.0
#: ... and over the whole head mask, worst view (measured +0.087 dB at +30° on the filled
#: surface, 2026-12-02; on the trimmed mesh +0.0018–0.0125 dB, its missing geometry black in
#: both renders; stage alone +1.19 dB). The filled surface's inferred texels take the same
#: values in the render and the naive baseline, so the gain over the head stays that of the
#: covered pixels diluted by the inferred ones; what it buys is absolute: +30° 19.72 →
#: 24.76 dB, +60° 15.89 → 20.07 dB, −60° 21.39 → 23.36 dB. With the silhouettes' rim points
#: (2026-12-03) +0.31 dB at +30° (−30° / −60° / +60° +0.85 / +1.65 / +0.38).
TINY_GAIN_HEAD_DB = 0.2
#: Head-mask pixels no surface covers (black), worst view, as a fraction of the head mask: the
#: filled surface closes what the structured light did not reach within its bound (0.15 × the
#: points' extent, 32 mm, measured 0.226 at −60°: 821 of 3,635 px; with its own solve and
#: 0.28 × extent, 2026-12-03, at most 0.128 on the witness scan; with the silhouettes' rim
#: points 0.101 at −60°, 366 px); on the trimmed mesh 0.41 (1,497; ±30° 545 and 482).
TINY_BLACK_HEAD_FRACTION = 0.15
#: The render's drawn pixels against the reference's head mask, intersection over union, worst
#: view: a filled surface grown past the head draws pixels the figures over the mask never see
#: (measured 0.898 at −60°: 9 px drawn outside the head, 362 black inside it; −30° / +30° /
#: +60° 0.979 / 0.976 / 0.909; 2026-12-03). The stage-alone pass draws the true head: 1.0.
TINY_SILHOUETTE_IOU = 0.85
STAGE_ALONE_SILHOUETTE_IOU = 0.999
#: Gain over naive on the head pixels whose true surface a source camera saw
#: (``psnr_gain_db_seen``), worst view: measured +0.68 dB at +30° (−30° / −60° / +60° +1.40 /
#: +3.32 / +0.94; over the whole head −30° / −60° / +30° / +60° +0.86 / +1.65 / +0.31 /
#: +0.38), the 73–578 unseen pixels holding 22–60 % of the render's squared error
#: (2026-12-03; stage alone +2.07 dB worst, 4–32 %).
TINY_GAIN_SEEN_DB = 0.5

# small preset (240 × 360 px, 512 lights, 30 board views): the calibrated rig (0.20° / 3.56 mm
# from the generator's frame), the reconstructed mesh (0.078 mm points RMS after alignment)
#: projection (measured 4.08 % on 2026-12-02, 3.93 % on the filled surface's measured texels;
#: issue 37 quoted 2.87 % before the evaluation moved; stage alone 1.40 %)
SMALL_PROJECTION_REL_RMSE = 0.05
#: novel views, covered pixels, worst of the four orbits: issue 37's bar is 3 dB; asserted
#: 4.5 dB, 10 % under the worst measured (2026-12-03, with the skin fit's ramps through white
#: refused, docs/skin.md: +4.99 dB at −30°; −60° +9.80, +30° +5.56, +60° +7.63). Before that
#: refusal +3.80 / +8.13 / +4.81 / +4.94 — 0.14 % of the functions' runaway ramps cost 1.2–2.7
#: dB, which this bar now catches; before the filled surface's own solve +3.03 dB at −30°.
SMALL_GAIN_COVERED_DB = 4.5
#: ... over the whole head mask, worst view: measured +0.40 dB at +30° on this test's scan
#: (+60° +0.62) with the silhouettes' rim points in the filled surface (2026-12-03, docs/mesh.md;
#: before them +0.29 / +0.28; before the ramp refusal +0.25 / +0.30; with the old fill cut
#: from the trimmed mesh's solve +0.074 dB worst). At +30° / +60° the inferred side of the head
#: and the back of the head no camera's silhouette reaches hold most of the naive render's
#: error, the same in both renders (docs/render.md, *Where the chain's whole-head error comes
#: from*).
SMALL_GAIN_HEAD_DB = 0.3
#: ... and at −30° / −60°, where issue 37's 1 dB over the whole head is met: measured +1.88 /
#: +3.65 dB with the silhouettes (2026-12-03; before them +1.69 / +2.34 on this scan, +1.31 /
#: +2.07 on the demo's; before the ramp refusal +1.10 / +1.93; the old fill: +0.52 / +1.16).
#: Asserted at the bar: both margins are several times what a machine's floating-point
#: differences have moved a view's gain.
SMALL_GAIN_HEAD_MET_DB = {"front_orbit-30_sky": 1.0, "front_orbit-60_sky": 1.0}
#: Head-mask pixels left black, worst view, fraction of the mask: measured 0.051 at −60°
#: with the silhouettes (1,633 of 32,113 px; +60° 1,612, +30° 303, −30° 297; 2026-12-03);
#: before them 0.116 (3,733; +60° 3,328), the old fill 0.220 (7,054), the trimmed mesh 0.415
#: (13,317).
SMALL_BLACK_HEAD_FRACTION = 0.08
#: The calibration-only witness camera (``synth --witness``: 40° from each capture camera,
#: above the face) against its reference image under ``axis_lobes``, on the chain: issue 37's
#: bars, 3 dB over naive on covered pixels and 1 dB over the whole head. Measured 2026-12-03
#: (inference over the surface, no ``fill_px``): +8.00 / +1.74 dB (+1.75 with the 2 px copy;
#: the scan's orbits, which average the witness into their frontal camera, −30° / −60° / +30° /
#: +60° +1.69 / +2.34 / +0.29 / +0.28 whole head, 5.32 / 10.30 / 5.45 / 7.40 covered). With
#: the silhouettes' rim points in the filled surface: +8.52 / +1.67 dB.
WITNESS_GAIN_COVERED_DB = 3.0
WITNESS_GAIN_HEAD_DB = 1.0
#: ... and its black head pixels: 9 of 25,651 measured, every one in the reference mask's
#: outermost ring (distance 1 px from its edge), where the reference is a fifth of its median
#: (a ray or two of nine on the head): the silhouettes differ by under a pixel — no hole
#: (17 with the silhouettes' rim points, all in that ring).
WITNESS_BLACK_HEAD_FRACTION = 0.001
#: The render's drawn pixels against the reference's head mask (IoU), worst view: measured
#: 0.945 on this test's scan (the demo's: 0.942 at −60°, 119 px drawn outside the head, 1,761
#: black inside it; −30° / +30° / +60° 0.986 / 0.985 / 0.945; 2026-12-03).
SMALL_SILHOUETTE_IOU = 0.92
#: Gain over naive on the head pixels whose true surface a source camera saw (the co-visibility
#: mask, ``psnr_gain_db_seen``), worst orbit: issue 37's 1 dB, over what the capture could
#: show. Measured +1.32 dB at +30° on this test's scan (−30° / −60° / +60° +4.00 / +8.02 /
#: +2.61), where the 639 head pixels (2.3 %) no source camera saw hold 67 % of the render's
#: squared error (−30° / −60° / +60°: 676 / 5,160 / 5,053 px, 58 / 75 / 80 %); 2026-12-03.
SMALL_GAIN_SEEN_DB = 1.0


@pytest.fixture(scope="module")
def tiny_demo(tmp_path_factory):
    """``facegeo demo ROOT --preset tiny``, run in-process: the synthetic scan, the chain, then
    the stage-alone pass. Returns the scan's root and what the command printed."""
    import contextlib
    import io

    from facegeo.cli import main

    root = tmp_path_factory.mktemp("chain") / "tiny"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["demo", str(root), "--preset", "tiny", "-q"]) == 0
    return root, printed.getvalue()


@pytest.fixture(scope="module")
def tiny_chain(tiny_demo):
    """The tiny demo's metrics: the chain's and the stage-alone pass's."""
    root, _ = tiny_demo
    chain = json.loads((root / "out" / "metrics.json").read_text())
    alone = json.loads((root / "out" / reconstruct.DIAGNOSTIC_DIR / "metrics.json").read_text())
    return root, chain, alone


@pytest.mark.slow
def test_demo_synth_info_round_trip(tiny_demo, capsys):
    """The demo command end to end (its run is the fixture every tiny-chain test reads): what
    it prints, a second run that reuses the scan and does no work, ``info`` on the scan, and
    ``synth`` refusing to overwrite it."""
    from facegeo.cli import main

    root, out = tiny_demo
    assert "synthesised" in out and "cam_left" in out
    # issue 37: the chain (its own mesh; the tiny boards show no marker, so the rig "auto"
    # falls back to, and says so), then the stage-alone pass, and the two side by side
    assert "run: rig ground_truth, mesh reconstructed" in out and "calibration failed" in out
    assert "the stage-alone pass" in out and "stage alone" in out
    assert (root / "out" / "diagnostic" / "evaluate" / "stage.json").is_file()
    assert "The chain and the stages alone" in (root / "out" / "report.html").read_text()
    assert main(["demo", str(root), "--preset", "tiny", "-q"]) == 0  # reuses the scan
    again = capsys.readouterr().out
    assert "using the existing synthetic scan" in again
    assert " ran in " not in again  # a second demo does no work, in either pass
    assert main(["info", str(root), "--full"]) == 0
    assert "every frame decoded" in capsys.readouterr().out
    # synth refuses to overwrite, with a clear message and status 2
    assert main(["synth", str(root), "--preset", "tiny", "-q"]) == 2
    assert "already holds a scan" in capsys.readouterr().err


@pytest.mark.slow
def test_the_default_run_is_the_chain(tiny_chain):
    root, chain, alone = tiny_chain
    assert chain["run"]["mesh"] == "reconstructed"
    # the tiny boards calibrate nothing: "auto" falls back, and the record says why
    assert "error" in chain["calibrate"]
    assert chain["run"]["rig"] == "ground_truth"
    assert chain["run"]["rig_note"].startswith("rig auto: the calibration failed")
    # the atlas is built on the chain's mesh, not the generator's
    atlas = json.loads((root / "out" / "atlas" / "stage.json").read_text())
    assert atlas["settings"]["mesh"] == "reconstructed"
    # the diagnostic pass: the true rig and mesh, no calibration of its own
    assert alone["run"] == {"rig": "ground_truth", "mesh": "ground_truth",
                            "world": "the generator's (ground_truth/rig.json)"}
    assert "calibrate" not in alone


@pytest.mark.slow
def test_the_chains_figures_on_the_tiny_preset(tiny_chain):
    _, chain, alone = tiny_chain
    ev, ev_alone = chain["evaluate"], alone["evaluate"]
    assert ev["project"]["projection_rel_rmse"] <= TINY_PROJECTION_REL_RMSE
    assert ev["render"]["psnr_gain_db_covered_min"] >= TINY_GAIN_COVERED_DB
    assert ev["render"]["psnr_gain_db_min"] >= TINY_GAIN_HEAD_DB
    assert ev["render"]["silhouette_iou_min"] >= TINY_SILHOUETTE_IOU
    assert ev_alone["render"]["silhouette_iou_min"] >= STAGE_ALONE_SILHOUETTE_IOU
    # over the pixels the capture saw, and where the shared error of what it did not see sits
    assert ev["render"]["psnr_gain_db_seen_min"] >= TINY_GAIN_SEEN_DB
    for stem, v in ev["render"]["views"].items():
        assert v["psnr_gain_db_seen"] > v["psnr_gain_db"], stem
        assert v["unseen_head_pixels"] > 0 and v["seen_pixels"] > 0.75 * v["mask_pixels"], stem
    # the chain's mesh costs the surface stages something: the stage-alone figures are better
    assert ev_alone["project"]["projection_rel_rmse"] < ev["project"]["projection_rel_rmse"]
    assert ev_alone["render"]["psnr_gain_db_covered_min"] \
        > ev["render"]["psnr_gain_db_covered_min"]


@pytest.mark.slow
def test_the_chain_renders_the_filled_surface(tiny_chain):
    """Issue 37: the atlas is the filled surface (``mesh_filled.ply``), its inferred texels are
    not measured by any camera but inferred in the renders, the mesh figures stay the trimmed
    mesh's, and no view leaves more than a quarter of the head black."""
    import numpy as np

    root, chain, _ = tiny_chain
    out = root / "out"
    atlas = json.loads((out / "atlas" / "stage.json").read_text())
    assert atlas["settings"]["surface"] == reconstruct.SURFACE_DEFAULT == "filled"
    assert atlas["metrics"]["mesh"].endswith("mesh_filled.ply")
    inferred = np.load(out / "atlas" / "inferred_texels.npy")
    assert inferred.shape == (chain["atlas"]["texels"],)
    assert chain["atlas"]["inferred_texels"] == int(inferred.sum()) > 0
    seen = np.load(out / "project" / "seen.npy")
    assert not (seen & inferred).any()  # no camera measures an inferred texel
    # the measured product stays the trimmed mesh (its figures: tests/test_mesh.py)
    assert chain["mesh"]["filled"]["faces"] > chain["mesh"]["faces"]
    # the cameras' silhouettes shaped the filled surface (docs/mesh.md)
    sil = chain["mesh"]["silhouettes"]
    assert set(sil["cameras"]) == {"cam_left", "cam_right"}
    assert sil["rim_points"] > 0
    assert chain["mesh"]["filled"]["support_points"] == sil["rim_points"]
    for stem, v in chain["evaluate"]["render"]["views"].items():
        assert v["black_head_pixels"] <= TINY_BLACK_HEAD_FRACTION * v["mask_pixels"], stem
    # the renders say which pixels were inferred
    for stem in chain["evaluate"]["render"]["views"]:
        assert (out / "render" / f"{stem}_inferred.png").is_file()


def test_the_surface_setting_chooses_the_mesh_stage_file(tmp_path):
    from facegeo.errors import InputError

    (tmp_path / "mesh.ply").write_text("trimmed")
    assert reconstruct.reconstructed_surface(tmp_path, "trimmed") == tmp_path / "mesh.ply"
    # no filled surface made (the grid method, fill_distance_mm=None): the trimmed one
    assert reconstruct.reconstructed_surface(tmp_path, "filled") == tmp_path / "mesh.ply"
    (tmp_path / "mesh_filled.ply").write_text("filled")
    assert reconstruct.reconstructed_surface(tmp_path) == tmp_path / "mesh_filled.ply"
    assert reconstruct.reconstructed_surface(tmp_path, "trimmed") == tmp_path / "mesh.ply"
    with pytest.raises(InputError, match="filled, trimmed"):
        reconstruct.reconstructed_surface(tmp_path, "balloon")


@pytest.mark.slow
def test_both_passes_meet_the_same_references(tiny_chain):
    """The stage-alone pass renders the chain's views (moved into the generator's frame), so
    the two are compared with one set of reference images, rendered once."""
    root, chain, alone = tiny_chain
    views, views_alone = chain["evaluate"]["render"]["views"], \
        alone["evaluate"]["render"]["views"]
    assert set(views) == set(views_alone) and len(views) == len(reconstruct.RENDER_ORBITS)
    refs = sorted((root / "out" / ".reference-renders").glob("*.npy"))
    assert len(refs) == len(views)  # one per view, not one per view and pass
    from facegeo.capture.imageio import read_image

    for stem in views:
        a = read_image(root / "out" / "evaluate" / "render" / f"{stem}_reference.exr")
        b = read_image(root / "out" / reconstruct.DIAGNOSTIC_DIR / "evaluate" / "render"
                       / f"{stem}_reference.exr")
        assert (a == b).all(), stem  # bit for bit


@pytest.mark.slow
def test_the_report_shows_chain_and_stage_alone(tiny_chain):
    from facegeo.pipeline.report import chain_and_stage_alone, write_report

    root, chain, alone = tiny_chain
    rows = {(r["stage"], r["figure"]): r for r in chain_and_stage_alone(root / "out")}
    r = rows[("project", "projection_rel_rmse")]
    assert r["chain"] == chain["evaluate"]["project"]["projection_rel_rmse"]
    assert r["stage_alone"] == alone["evaluate"]["project"]["projection_rel_rmse"]
    assert rows[("render", "psnr_gain_db_covered_min")]["stage_alone"] \
        == alone["evaluate"]["render"]["psnr_gain_db_covered_min"]
    page = write_report(root / "out").read_text()
    assert "The chain and the stages alone" in page
    # without a diagnostic pass there is nothing to show beside the chain
    assert chain_and_stage_alone(root / "out" / "nowhere") == []


def test_auto_takes_the_calibrated_rig_and_reconstructed_mesh_before_any_run(tmp_path):
    """Resolved from what the scan holds: board views → the calibrated rig, structured light
    → the reconstructed mesh, synthetic or not; the truth only when asked for."""
    from facegeo.capture.scan import load_scan
    from facegeo.synth.capture import Preset, generate_scan

    preset = Preset("choices", 1 / 6, 4, 2, 2, (64, 48), 2, 1, 0, olat_half=False,
                    sl_supersample=1)
    generate_scan(tmp_path / "scan", preset, seed=0)
    scan = load_scan(tmp_path / "scan")
    assert reconstruct.run_choices(scan)["rig"] == "calibrated"
    assert reconstruct.run_choices(scan)["mesh"] == "reconstructed"
    assert reconstruct.run_choices(scan, rig="ground_truth", mesh="ground_truth") == {
        "rig": "ground_truth", "mesh": "ground_truth",
        "world": "the generator's (ground_truth/rig.json)"}
    # a calibration that failed: the fallback is on record
    got = reconstruct.run_choices(scan, calibration_error="no board found")
    assert got["rig"] == "ground_truth" and "no board found" in got["rig_note"]
    # the stages of the default pipeline wait for the calibration and the mesh
    spec = {s.name: s for s in reconstruct.reconstruct_pipeline(scan).stages}
    assert "calibrate" in spec["project"].after and "mesh" in spec["atlas"].after
    assert spec["project"].settings["rig"] == "calibrated"
    assert spec["atlas"].settings["mesh"] == "reconstructed"
    # the diagnostic pipeline: the truth, no calibration, its own folder
    diag = reconstruct.reconstruct_pipeline(scan, rig="ground_truth", mesh="ground_truth",
                                            diagnostic=True)
    assert "calibrate" not in diag.names and diag.out_name == "out/diagnostic"
    assert {s.name: s for s in diag.stages}["project"].settings["rig"] == "ground_truth"
    from facegeo.errors import InputError

    with pytest.raises(InputError, match="diagnostic pass feeds"):
        reconstruct.reconstruct_pipeline(scan, diagnostic=True)


@pytest.mark.slow
def test_the_chains_figures_on_the_small_preset(small_witness_scan):
    """The demo's scan with the calibration-only witness camera: the whole chain on the
    calibrated rig, as ``facegeo demo`` runs it, and the witness's view against its reference
    image (issue 37: a camera no capture shares, brought into the world by the boards alone,
    runs with no workaround). Minutes (``slow``)."""
    import numpy as np

    from facegeo.capture.imageio import read_image

    root = small_witness_scan
    reconstruct.run_reconstruct(root)
    m = json.loads((root / "out" / "metrics.json").read_text())
    assert m["run"]["rig"] == "calibrated" and m["run"]["mesh"] == "reconstructed"
    assert "rig_note" not in m["run"]
    ev = m["evaluate"]
    print({k: ev["project"][k] for k in ("projection_rel_rmse", "visibility_agreement")},
          {k: v for k, v in ev["render"].items() if k != "views"})
    assert ev["project"]["projection_rel_rmse"] <= SMALL_PROJECTION_REL_RMSE
    assert ev["render"]["psnr_gain_db_covered_min"] >= SMALL_GAIN_COVERED_DB
    assert ev["render"]["psnr_gain_db_min"] >= SMALL_GAIN_HEAD_DB
    for stem, least in SMALL_GAIN_HEAD_MET_DB.items():
        assert ev["render"]["views"][stem]["psnr_gain_db"] >= least, stem
    for stem, v in ev["render"]["views"].items():
        assert v["black_head_pixels"] <= SMALL_BLACK_HEAD_FRACTION * v["mask_pixels"], stem
    assert ev["render"]["silhouette_iou_min"] >= SMALL_SILHOUETTE_IOU
    assert ev["render"]["psnr_gain_db_seen_min"] >= SMALL_GAIN_SEEN_DB
    w = ev["render"]["views"]["witness_axis_lobes"]
    assert w["psnr_gain_db_covered"] >= WITNESS_GAIN_COVERED_DB, w
    assert w["psnr_gain_db"] >= WITNESS_GAIN_HEAD_DB, w
    assert w["black_head_pixels"] <= WITNESS_BLACK_HEAD_FRACTION * w["mask_pixels"], w
    # the seen figures of a reference image the generator wrote (measured +3.24 dB over the
    # seen pixels, the 1,391 unseen of 25,651 holding 55 % of the error; 2026-12-03)
    assert w["psnr_gain_db_seen"] > w["psnr_gain_db"] and w["unseen_head_pixels"] > 0, w
    # ... and those are in the reference's outermost ring: no hole inside the head
    ref = read_image(root / "reference" / "witness_axis_lobes.exr")[..., :3]
    head = np.isfinite(ref).all(axis=2) & (np.nan_to_num(ref).max(axis=2) > 0)
    img = read_image(root / "out" / "render" / "witness_axis_lobes.exr")[..., :3]
    from scipy import ndimage

    inner = ndimage.binary_erosion(head, iterations=1)
    assert not (inner & (img.max(axis=2) <= 0)).any()
