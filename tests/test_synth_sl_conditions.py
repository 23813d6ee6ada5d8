"""The generator's structured-light conditions of real captures (issue 34, DESIGN §9).

A real two-camera Gray-code capture had (a) cameras that out-resolve the projector — many camera
pixels share one projector code — and (b) a camera that lost four structured-light frames,
declared in ``[structured_light.cameras.<camera>] missing``. The generator makes both
(``generate_scan(..., projector_scale=, sl_phase_steps=0, sl_missing=)``); these tests check
it does, on tiny scans with 8 lights and the fewest board views (≈ 1–2 s a scan).
"""

from __future__ import annotations

import tomllib
from dataclasses import replace

import numpy as np
import pytest

from facegeo.capture.scan import load_scan
from facegeo.errors import InputError
from facegeo.geometry.structured_light import PatternSpec, pattern_names
from facegeo.synth.capture import PRESETS, generate_scan
from facegeo.synth.sl_conditions import (
    camera_px_per_projector_px,
    issue34_lost_frames,
    shared_code_fraction,
)

#: ``tiny`` with 4 × 2 lights and one board view of each kind: the structured-light frames and
#: ground-truth geometry of ``tiny``, in a fraction of its time.
FAST_TINY = replace(PRESETS["tiny"], n_theta=4, n_phi=2, calib_views=1, projector_views=1)
SEED = 3

#: Measured on FAST_TINY, seed 3, projector_scale = 4 (a 48 × 36 projector; docs/synth.md):
#: fraction of head pixels whose true projector pixel equals a 4-neighbour's, per camera.
SHARED_AT_SCALE_4 = {"cam_left": 0.9917, "cam_right": 0.9902}
#: Absolute tolerance on that fraction (≈ 30 of the ≈ 2,900 head pixels of a camera).
SHARED_FRACTION_TOL = 0.01
#: Median camera pixels per projector pixel (linear) against the projector_scale asked for,
#: relative (the projector size is rounded to its 4:3 steps: 48 × 36 for 46.6 × 35.0).
SCALE_REL_TOL = 0.05
#: The default tiny projector (256 × 192) out-resolves the cameras: ≈ 0.75 camera px per
#: projector px, and few codes shared (measured 0.076 / 0.050).
DEFAULT_TINY_SCALE = 0.75
DEFAULT_SHARED_MAX = 0.1

#: issue34_lost_frames for the 48 × 36 projector's 6 column and 6 row bits.
LOST_6_BITS = ["gray_x_05", "gray_y_04", "gray_y_04_inv", "gray_y_05_inv"]


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """The same noisy Gray-only scan at projector_scale 4, with and without cam_right's lost
    frames."""
    d = tmp_path_factory.mktemp("sl_conditions")
    kw = dict(seed=SEED, noise=0.01, projector_scale=4, sl_phase_steps=0)
    lost = generate_scan(d / "lost", FAST_TINY, sl_missing={"cam_right": "issue34"}, **kw)
    full = generate_scan(d / "full", FAST_TINY, **kw)
    return lost, full


def _shared_reference(q):
    """Plain-loop reference for shared_code_fraction."""
    h, w = q.shape[:2]
    n = shared = 0
    for r in range(h):
        for c in range(w):
            if not np.isfinite(q[r, c]).all():
                continue
            n += 1
            code = tuple(np.floor(q[r, c] + 0.5))
            for rr, cc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
                if 0 <= rr < h and 0 <= cc < w and np.isfinite(q[rr, cc]).all() \
                        and tuple(np.floor(q[rr, cc] + 0.5)) == code:
                    shared += 1
                    break
    return shared / n


# ---------------------------------------------------------------------------- lost frames


def test_issue34_lost_frames_are_the_real_captures():
    """For the real 1024 × 768 projector (10 + 10 bits): column bit 9's pattern frame, both
    frames of row bit 8, row bit 9's inverse."""
    spec = PatternSpec(width=1024, height=768)
    assert issue34_lost_frames(spec) == ["gray_x_09", "gray_y_08", "gray_y_08_inv",
                                         "gray_y_09_inv"]
    # fewer bits: the same positions from the end; the first code family names them
    spec = PatternSpec(width=48, height=36, codes=("minsw", "gray"))
    assert issue34_lost_frames(spec) == [f.replace("gray", "minsw") for f in LOST_6_BITS]
    with pytest.raises(InputError, match="inverse"):
        issue34_lost_frames(PatternSpec(width=48, height=36, inverse=False))


def test_lost_frames_are_declared_absent_and_load(scans):
    lost, full = scans
    assert lost.sl_missing == {"cam_right": LOST_6_BITS}
    assert full.frames_written - lost.frames_written == len(LOST_6_BITS)
    manifest = tomllib.loads((lost.root / "scan.toml").read_text())
    assert manifest["structured_light"]["cameras"] == {"cam_right": {"missing": LOST_6_BITS}}
    assert "cameras" not in tomllib.loads((full.root / "scan.toml").read_text())["structured_light"]

    scan = load_scan(lost.root, check="full")  # every expected frame present and readable
    assert scan.missing_frames("structured_light", "cam_right") == LOST_6_BITS
    assert scan.missing_frames("structured_light", "cam_left") == []
    for name in scan.sl_frames:
        right = lost.root / "structured_light" / "cam_right" / f"{name}.png"
        assert right.exists() == (name not in LOST_6_BITS), name
        assert (lost.root / "structured_light" / "cam_left" / f"{name}.png").exists(), name


def test_lost_frames_leave_the_other_frames_unchanged(scans):
    """Noise is drawn for a lost frame too: every frame written equals the full scan's, bit for
    bit (noise on, so a shifted noise stream would show)."""
    lost, full = scans
    a, b = load_scan(lost.root), load_scan(full.root)
    for cam in a.camera_names:
        for name in a.camera_frames("structured_light", cam):
            assert np.array_equal(a.sl_frame(cam, name), b.sl_frame(cam, name)), (cam, name)
        for light in (0, a.n_lights - 1):
            assert np.array_equal(a.olat_frame(cam, light), b.olat_frame(cam, light))


# ---------------------------------------------------------------------------- out-resolving cameras


def test_projector_scale_makes_cameras_share_codes(scans):
    """projector_scale = 4: a 48 × 36 projector, ≈ 4 × 4 camera pixels per projector pixel, and
    ≥ 0.99 of each camera's head pixels share their true code with a neighbour (issue 34's
    camera: 0.97), from the ground truth (decode.ground_truth_projector) and a plain-loop
    count; Gray code with inverses, white and black only."""
    from facegeo.pipeline.decode import ground_truth_projector

    lost, _ = scans
    scan = load_scan(lost.root)
    assert lost.projector_size == (48, 36) == (scan.rig.projector.width, scan.rig.projector.height)
    spec = PatternSpec(width=48, height=36)
    assert scan.sl_frames == pattern_names(spec)  # no phase frames
    assert not any(f.startswith("phase") for f in scan.sl_frames)
    info = scan.manifest["scan"]["metadata"]["projector_scale"]
    assert info["requested"] == 4 and info["projector_size"] == [48, 36]
    for cam in scan.camera_names:
        q = ground_truth_projector(scan, cam)["q"]
        shared = shared_code_fraction(q)
        assert shared == pytest.approx(_shared_reference(q), abs=1e-12)
        assert shared >= 0.9
        assert shared == pytest.approx(SHARED_AT_SCALE_4[cam], abs=SHARED_FRACTION_TOL), cam
        assert info["shared_code_fraction"][cam] == pytest.approx(shared, abs=1e-12)
        ratio = camera_px_per_projector_px(q)
        assert ratio == pytest.approx(4.0, rel=SCALE_REL_TOL), cam
        assert info["camera_px_per_projector_px"][cam] == pytest.approx(ratio, abs=1e-12)


def test_default_tiny_projector_out_resolves_the_cameras():
    """Without projector_scale the tiny projector is finer than the cameras on the face, so the
    condition needs the option: ≈ 0.75 camera px per projector px, few shared codes."""
    from facegeo.synth.capture import build_head, build_rig, perturbed_rig
    from facegeo.synth.render import ReferenceRenderer
    from facegeo.synth.skin import SkinField
    from facegeo.synth.sl_conditions import projector_coordinates

    mesh = build_head("procedural", subdivisions=FAST_TINY.head_subdivisions, seed=SEED)
    mesh.vertices = np.asarray(mesh.vertices, np.float32).astype(np.float64)
    rig = perturbed_rig(build_rig(FAST_TINY), SEED)  # the true rig, as generate_scan builds it
    renderer = ReferenceRenderer.from_mesh(mesh, SkinField.for_mesh(mesh, seed=SEED))
    for cam in rig.cameras:
        q = projector_coordinates(renderer.surface_view(cam), rig.projector)
        assert camera_px_per_projector_px(q) == pytest.approx(DEFAULT_TINY_SCALE, rel=SCALE_REL_TOL)
        assert shared_code_fraction(q) < DEFAULT_SHARED_MAX


def test_code_sharing_and_scale_on_known_grids():
    """Analytic cases, with different block sizes per axis (3 columns × 2 rows of camera
    pixels per projector pixel) and codes that repeat along one axis only, so a neighbour test
    that looked along one axis, or a half-pixel offset in the code, fails."""
    rows, cols = np.mgrid[0:30, 0:40].astype(float)
    # 3 camera columns and 2 camera rows per projector pixel, pixel centres on integers
    q = np.stack([(cols - 1.0) / 3.0, (rows - 0.5) / 2.0], axis=-1)
    assert camera_px_per_projector_px(q) == pytest.approx(np.sqrt(6.0), rel=1e-12)
    assert shared_code_fraction(q) == 1.0
    # one camera pixel per projector pixel: every code distinct
    q1 = np.stack([cols, rows], axis=-1)
    assert shared_code_fraction(q1) == 0.0
    assert camera_px_per_projector_px(q1) == pytest.approx(1.0)
    # codes that change every column but repeat in blocks of 4 rows: shared with a vertical
    # neighbour only (a horizontal-only test gives 0)
    q2 = np.stack([cols, rows / 4.0 - 0.5], axis=-1)
    assert shared_code_fraction(q2) == pytest.approx(_shared_reference(q2))
    assert shared_code_fraction(q2) == 1.0
    # off-surface pixels never share
    q3 = q.copy()
    q3[::2, :] = np.nan
    q3[:, ::2] = np.nan
    assert shared_code_fraction(q3) == 0.0
    assert np.isnan(shared_code_fraction(np.full((4, 4, 2), np.nan)))


# ---------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("kwargs, message", [
    ({"sl_missing": {"cam_middle": ["gray_x_00"]}},
     r"unknown camera 'cam_middle'.*cam_left, cam_right"),
    ({"sl_missing": {"cam_left": ["gray_x_11"]}},
     r"unknown frame\(s\) 'gray_x_11'.*white, black, gray_x_00"),
    ({"sl_missing": {"cam_left": "issue35"}}, r"unknown pattern 'issue35'.*issue34"),
    ({"sl_missing": {"cam_left": ["white", "white"]}}, r"listed twice"),
    ({"sl_missing": ["cam_left"]}, r"sl_missing: expected a mapping"),
    ({"projector_scale": 0}, r"projector_scale: expected a finite number > 0"),
    ({"projector_scale": float("nan")}, r"projector_scale: expected a finite number > 0"),
    ({"projector_scale": "4"}, r"projector_scale: expected a finite number > 0"),
    ({"projector_scale": 1000}, r"projector_scale: .*use a projector_scale below"),
    ({"sl_phase_steps": 2}, r"sl_phase_steps: expected 0 \(Gray code only\)"),
    ({"sl_phase_steps": True}, r"sl_phase_steps: expected 0"),
])
def test_bad_input_names_the_argument_and_writes_nothing(tmp_path, kwargs, message):
    out = tmp_path / "new" / "scan"
    with pytest.raises(InputError, match=message):
        generate_scan(out, FAST_TINY, seed=SEED, **kwargs)
    assert list(tmp_path.iterdir()) == []
