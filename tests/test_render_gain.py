"""Tests that fail when a render is wrong (issue 37): the resynthesised render's image-space gain
over the naive baseline against the reference, on covered pixels and over the whole head mask,
no black pixel inside the head, and a black or flat image failing the same criterion
(:func:`facegeo.evaluate.views.render_gain`).

Tiny preset with the calibration-only ``witness`` camera and its reference image under
``axis_lobes`` (``facegeo synth --witness``), the true inputs (``--rig ground_truth --mesh
ground_truth``): the ``render`` stage's four orbits of the frontal camera of the two capture
cameras under ``sky`` at its 3 × 3 rays per pixel, against the generator's references, and the
witness camera's view against its reference image, with ``infer`` (the default: what no camera
saw inferred over the surface). The chain (calibrated rig, reconstructed mesh) is not measured
here: the tiny preset's board views are too small to calibrate (docs/synth.md) and the small
preset costs minutes.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

#: Issue 37's bars: resynthesis at least this much over the naive render, on covered pixels and
#: over the whole head mask (dB), and no black pixel inside the head mask.
GAIN_COVERED_DB_MIN = 3.0
GAIN_HEAD_DB_MIN = 1.0
ORBITS = (-60, -30, 30, 60)
VIEWS = ORBITS + ("witness",)
#: Measured (tiny + witness, true rig and mesh, 3 × 3 rays, infer on; 2026-12-03: inferred
#: over the surface, no ``fill_px``; in brackets 2026-12-02's inference on the atlas after a
#: 2 px ``fill_px``), gain in dB, and beside it the render with ``infer=False`` (unseen surface
#: black, the paper's; 2026-12-02):
#:   view                  covered  whole head     inferred px   whole head, black  black px
#:   orbit −60° (sky)       9.77    8.04 (3.43)    32.4 %        0.98               814
#:   orbit −30°             5.41    3.67 (2.00)    13.1 %        0.55               110
#:   orbit +30°             4.27    1.80 (1.47)    13.0 %        0.20                94
#:   orbit +60°             7.27    2.56 (2.04)    31.9 %        0.07               799
#:   witness (axis_lobes)  10.82    3.57 (1.23)    14.9 %        —
#: (54 % of the atlas's texels no capture camera measured: two 80 × 120 px cameras, the back of
#: the head unseen.) The orbits are of the two capture cameras' frontal view (``front_camera``
#: of cam_left and cam_right). The stage's ``orbit:front:D`` averages every camera of its
#: camera table — the generator's three novel cameras, and the witness — so its views sit
#: 5–6° off: there the plain tiny scan reads 10.10 / 5.75 / 2.16 / 7.06 covered (+30° misses
#: the 3 dB bar) and 3.94 / 2.99 / 1.22 / 1.92 whole head.
#: A black image and a flat mean-colour image against the naive render: the criterion's gains
#: are far below zero (measured −13.0 … −34.0 dB covered, −11.6 … −30.2 dB whole head on the
#: orbits), so either bar alone rejects them.


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    """The fixture scan reconstructed with the true inputs up to the fit (≈ 45 s), its four
    orbits rendered with the generator's references beside them and the witness view compared
    with its reference image (≈ 6 s a view)."""
    from facegeo.capture import imageio
    from facegeo.capture.scan import load_scan
    from facegeo.cli import main
    from facegeo.evaluate.views import evaluate_view_against_image
    from facegeo.pipeline.project import stage_rig
    from facegeo.pipeline.reconstruct import RENDER_SUPERSAMPLE, run_reconstruct
    from facegeo.pipeline.render import reference_views, run_render
    from facegeo.render import front_camera, orbit_camera

    root = tmp_path_factory.mktemp("gain") / "scan"
    assert main(["synth", str(root), "--preset", "tiny", "--witness", "-q"]) == 0
    run_reconstruct(root, mesh="ground_truth", rig="ground_truth", until="fit")
    scan = load_scan(root)
    assert reference_views(scan) == [("witness", "axis_lobes")]
    rig, _ = stage_rig(scan, "ground_truth")
    front = front_camera({c: rig.camera(c) for c in ("cam_left", "cam_right")})
    folder = root / "out" / "views"
    got = {}
    for view in VIEWS:
        if view == "witness":
            m = run_render(root, camera_spec="witness", env="axis_lobes", reference=False,
                           supersample=RENDER_SUPERSAMPLE)
            m.update(evaluate_view_against_image(scan, folder, m["name"]))
        else:
            cam = orbit_camera(front, view, name=f"front_orbit{view:g}")
            m = run_render(root, camera_spec=cam, env="sky", supersample=RENDER_SUPERSAMPLE)
        s = m["name"]

        def read(suffix, s=s):
            return imageio.read_image(folder / f"{s}{suffix}")

        v = {"metrics": m, "image": read(".exr"), "naive": read("_naive.exr"),
             "covered": read("_covered.png") > 0, "inferred": read("_inferred.png") > 0}
        if view == "witness":  # the reference image and its own extent (the evaluation's mask)
            ref = imageio.read_image(scan.reference_path("images.witness.axis_lobes"))[..., :3]
            v["ref"] = np.nan_to_num(ref).astype(np.float32)
            v["head"] = np.isfinite(ref).all(axis=2) & (ref.max(axis=2) > 0)
        else:
            v["ref"] = read("_reference.exr")
            v["head"] = read("_reference_mask.png") > 0
        got[view] = v
    return root, got


def _gain(v, image=None):
    from facegeo.evaluate.views import render_gain

    return render_gain(v["image"] if image is None else image, v["naive"], v["ref"], v["head"],
                       v["covered"])


def _cases():
    for view in VIEWS:
        for part in ("covered", "head"):
            name = view if isinstance(view, str) else f"{view:+d}"
            yield pytest.param(view, part, id=f"{name}-{part}")


@pytest.mark.parametrize("orbit, part", list(_cases()))
def test_resynthesis_beats_naive_by_the_issues_bars(views, orbit, part):
    _, got = views
    v = got[orbit]
    g = _gain(v)
    bar = GAIN_COVERED_DB_MIN if part == "covered" else GAIN_HEAD_DB_MIN
    assert g[f"gain_{part}_db"] >= bar, g
    # the evaluation's own figures (facegeo.evaluate.views) are the same criterion
    key = "psnr_gain_db_covered" if part == "covered" else "psnr_gain_db"
    assert v["metrics"][key] == pytest.approx(g[f"gain_{part}_db"], abs=1e-3)


@pytest.mark.parametrize("orbit", VIEWS)
def test_no_black_pixel_inside_the_head(views, orbit):
    _, got = views
    v = got[orbit]
    assert _gain(v)["black_head_pixels"] == 0
    # the render's own silhouette (its rays that hit the mesh) has no black pixel either, and
    # what was inferred is marked, never covered
    assert v["metrics"]["black_surface_pixels"] == 0, v["metrics"]
    assert not (v["inferred"] & v["covered"]).any()
    assert v["metrics"]["inferred_pixel_fraction"] == pytest.approx(
        v["inferred"].mean() / max((v["inferred"] | v["covered"]).mean(), 1e-12), abs=0.02)
    assert 0.0 < v["metrics"]["inferred_texel_fraction"] < 1.0
    # the evaluation reports it too
    assert v["metrics"]["black_head_pixels"] == 0


@pytest.mark.parametrize("orbit", VIEWS)
def test_a_black_or_flat_image_fails_the_criterion(views, orbit):
    _, got = views
    v = got[orbit]
    black = np.zeros_like(v["image"])
    flat = np.where(v["head"][..., None], v["ref"][v["head"]].mean(axis=0), 0.0)
    for name, img in (("black", black), ("flat", flat)):
        g = _gain(v, img.astype(np.float32))
        assert g["gain_covered_db"] < GAIN_COVERED_DB_MIN, (name, g)
        assert g["gain_head_db"] < GAIN_HEAD_DB_MIN, (name, g)
    assert _gain(v, black)["black_head_pixels"] == int(v["head"].sum())


def test_inference_keeps_covered_pixels_bit_for_bit(views, tmp_path):
    """``infer=False`` (the paper: unseen surface black) against the default: the covered
    pixels are the same bit for bit, and only the inferred ones differ."""
    from facegeo.capture import imageio
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.reconstruct import RENDER_SUPERSAMPLE
    from facegeo.pipeline.render import render_one

    root, got = views
    v = got["witness"]
    m = render_one(load_scan(root), root / "out", tmp_path, camera_spec="witness",
                   env="axis_lobes", reference=False, supersample=RENDER_SUPERSAMPLE,
                   infer=False)
    off = imageio.read_image(tmp_path / f"{m['name']}.exr")
    cov = imageio.read_image(tmp_path / f"{m['name']}_covered.png") > 0
    assert np.array_equal(cov, v["covered"])
    assert np.array_equal(off[cov], v["image"][cov])
    assert m["inferred_pixel_fraction"] < v["metrics"]["inferred_pixel_fraction"]
    assert m["black_surface_pixels"] > 0  # without it, unseen surface is black
    doc = json.loads((tmp_path / f"{m['name']}.json").read_text())
    assert doc["infer"] is False and v["metrics"]["infer"] is True


def test_a_surface_grown_past_the_head_shows_in_the_silhouette_figures():
    """``view_figures`` with a head mask: pixels drawn outside it (``outside_head_pixels``),
    black inside it, and the drawn pixels' IoU with it — what the figures over the mask miss."""
    from facegeo.evaluate.views import view_figures

    mask = np.zeros((20, 30), bool)
    mask[5:15, 5:25] = True  # 200 px
    image = np.zeros((20, 30, 3), np.float32)
    image[5:15, 5:27] = 0.5  # 20 px drawn past the head's right edge
    image[14, 5:15] = 0.0  # 10 px of the head left black
    ref = np.where(mask[..., None], np.float32(0.5), np.float32(0.0))
    v = {"image": image, "covered": mask, "texture": None, "naive": None,
         "naive_texture": None, "paper": None}
    got = view_figures(v, ref, mask, head_mask=True)
    assert got["outside_head_pixels"] == 20 and got["black_head_pixels"] == 10
    assert got["silhouette_iou"] == round(190 / 220, 6)
    # without a head mask (a real reference image's own extent) there is no outside
    assert "outside_head_pixels" not in view_figures(v, ref, mask)
    image[5:15, 25:27] = 0.0
    assert view_figures(v, ref, mask, head_mask=True)["silhouette_iou"] == round(190 / 200, 6)
