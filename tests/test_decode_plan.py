"""Tests for per-camera decode plans (cameras with lost structured-light frames, issue 34):
:func:`facegeo.geometry.structured_light.plan_camera_decode`, the stand-in partners of half
pairs (:func:`with_stand_in_partners`) and the ``decode`` stage with such cameras.

Metrics, stated with each assertion:

* equal codes — decoded projector coordinates compared bit for bit (``assert_array_equal``)
  where a half-pair decode and the full-pair decode see the same clean frames;
* block centres — a camera decoding ``n' < n`` bits names blocks of ``2**(n - n')`` of the
  scan's codes: its coordinate is the block's centre, exactly, and ``sigma = block / sqrt(12)``;
* agreement fractions on real frames — of the pixels both decodes keep, the fraction whose
  coordinates differ by at most 0.5 / 1 projector px.
"""

from __future__ import annotations

import json
import logging
import shutil

import numpy as np
import pytest
from conftest import shared_file

from facegeo.errors import InputError
from facegeo.geometry.structured_light import (
    CameraDecodePlan,
    PatternSpec,
    decode_stream,
    pattern_image,
    pattern_names,
    plan_camera_decode,
    with_stand_in_partners,
)

# ---------------------------------------------------------------- named tolerances (units)
SIGMA_RTOL = 1e-6  # sigma of a block code vs block / sqrt(12), relative
CONFIDENCE_ATOL = 1e-3  # half-pair vs full-pair confidence on clean float frames (measured 0)
REAL_HALF_WITHIN_HALF_PX_MIN = 0.99  # alexander left, bit 9 from its inverse (measured 0.994)
REAL_HALF_WITHIN_ONE_PX = 1.0  # ... within 1 projector px (measured 1.0)
TINY_HALF_PAIR_SAME_X_MIN = 0.999  # tiny preset, x of cam_right with bit 7 half (measured 1.0)
BLOCK_EXACT_MIN = 0.99  # tiny preset, exact_code_fraction with 4-px y blocks (measured 0.998)

REAL_LOST = ("gray_x_09", "gray_y_08", "gray_y_08_inv", "gray_y_09_inv")


# ---------------------------------------------------------------- the plan


def test_plan_of_the_real_case_10_plus_10_bits():
    """alexander's right camera: 10 + 10 bits with inverses and white / black, lacking
    gray_x_09, gray_y_08, gray_y_08_inv, gray_y_09_inv → x at 10 bits with bit 9 against the
    mid level, y at 8 bits (4-row blocks; gray_y_09, left alone, is not read)."""
    spec = PatternSpec(1024, 768)
    have = [n for n in pattern_names(spec) if n not in REAL_LOST]
    plan = plan_camera_decode(spec, have, camera="right")
    assert plan.action == "decode" and plan.reason == "" and not plan.complete
    assert (plan.spec.n_bits_x, plan.spec.n_bits_y) == (10, 8)
    assert plan.spec.width == 1024 and plan.spec.height == 768 and plan.spec.white_black
    assert plan.half_pairs == ({"axis": "x", "bit": 9, "code": "gray",
                                "decoded_against": "(white + black) / 2",
                                "present": "gray_x_09_inv", "missing": "gray_x_09"},)
    assert plan.stand_ins == {"gray_x_09_inv": "gray_x_09"}
    assert [(b["axis"], b["bit"], b["missing"]) for b in plan.lost_bits] == [
        ("y", 8, ["gray_y_08", "gray_y_08_inv"])]
    assert plan.unused_frames == ["gray_y_09"]
    assert plan.axes["x"] == {"bits_scan": 10, "bits": 10, "block_px": 1, "codes_per_block": 1,
                              "limited_by": None, "phase": None}
    assert plan.axes["y"] == {"bits_scan": 10, "bits": 8, "block_px": 4, "codes_per_block": 4,
                              "limited_by": "gray bit 8 lost", "phase": None}
    # the frames read: white and black first, then the camera's set without the lost ones
    assert plan.frames[:2] == ("white", "black") and len(plan.frames) == 42 - 4 - 1
    assert set(plan.frames) == set(have) - {"gray_y_09"}
    d = plan.to_dict()
    assert json.loads(json.dumps(d)) == d
    assert d["bits"] == {"x": 10, "y": 8} and d["block_px"] == {"x": 1, "y": 4}
    assert d["patterns"]["n_bits_y"] == 8 and d["frames_read"] == 37


def test_plan_of_a_complete_camera_is_the_scan_set():
    spec = PatternSpec(200, 120, phase_steps=3)
    plan = plan_camera_decode(spec, pattern_names(spec))
    assert plan.complete and plan.spec == spec and plan.frames == tuple(pattern_names(spec))
    assert plan.stand_ins == {} and plan.axes["x"]["phase"] == "used"


def test_plan_without_white_black_loses_the_half_pair():
    """No white / black frames: a lone pattern frame has nothing to be decoded against, so its
    bit is lost and the axis stops before it."""
    spec = PatternSpec(1024, 768, white_black=False)
    have = [n for n in pattern_names(spec) if n not in REAL_LOST]
    plan = plan_camera_decode(spec, have)
    assert (plan.spec.n_bits_x, plan.spec.n_bits_y) == (9, 8) and not plan.spec.white_black
    assert plan.half_pairs == () and plan.stand_ins == {}
    lost = {(b["axis"], b["bit"]): b for b in plan.lost_bits}
    assert lost[("x", 9)]["present"] == ["gray_x_09_inv"] and "no white / black" in \
        lost[("x", 9)]["why"]
    assert plan.unused_frames == ["gray_x_09_inv", "gray_y_09"]
    # a scan with white / black, a camera that lacks its black frame: the same, and the lone
    # white frame is dropped (recorded)
    spec = PatternSpec(1024, 768)
    have = [n for n in pattern_names(spec) if n not in REAL_LOST + ("black",)]
    plan = plan_camera_decode(spec, have)
    assert (plan.spec.n_bits_x, plan.spec.n_bits_y) == (9, 8) and not plan.spec.white_black
    assert {"what": "white_black", "frames": ["white"], "why": "black frame missing"} in \
        plan.dropped
    assert "white" not in plan.frames


def test_plan_with_one_axis_lost_and_declared_bits():
    spec = PatternSpec(1024, 768)
    names = pattern_names(spec)
    # the row MSB lost: rows are not decoded on this camera, columns are
    plan = plan_camera_decode(spec, [n for n in names if not n.startswith("gray_y_00")])
    assert plan.action == "decode" and (plan.spec.n_bits_x, plan.spec.n_bits_y) == (10, 0)
    assert plan.axes["y"]["bits"] == 0 and plan.axes["y"]["block_px"] is None
    assert len(plan.unused_frames) == 18 and "y" not in plan.to_dict()["block_px"]
    # declared bits (Scan.sl_bits): the camera's frames stop there, and the plan says why
    have = [n for n in names if not (n.startswith("gray_x_") and int(n[7:9]) >= 8)]
    plan = plan_camera_decode(spec, have, max_bits={"x": 8, "y": 10})
    assert plan.spec.n_bits_x == 8 and plan.axes["x"]["limited_by"] == "bits_x = 8 (declared)"
    assert plan.axes["x"]["block_px"] == 4 and plan.unused_frames == []
    with pytest.raises(InputError, match=r"max_bits\['x'\]: expected an integer >= 0"):
        plan_camera_decode(spec, names, max_bits={"x": -1})
    with pytest.raises(InputError, match="not in the pattern set"):
        plan_camera_decode(spec, names + ["gray_x_10"])


def test_plan_of_nothing_skips_and_of_too_little_is_undecodable():
    spec = PatternSpec(1024, 768)
    plan = plan_camera_decode(spec, [], camera="calib_only")
    assert plan.action == "skip" and "calibration only" in plan.reason and plan.spec is None
    plan = plan_camera_decode(spec, ["white", "black"])
    assert plan.action == "undecodable" and "no code bit left on any axis" in plan.reason
    both_msb = {"gray_x_00", "gray_x_00_inv", "gray_y_00", "gray_y_00_inv"}
    plan = plan_camera_decode(spec, [n for n in pattern_names(spec) if n not in both_msb])
    assert plan.action == "undecodable" and plan.spec is None
    assert "gray_x_00" in plan.reason and "gray_y_00_inv" in plan.reason
    # a phase-only set: a camera without one complete phase axis has nothing to decode
    phase = PatternSpec(200, 120, gray=False, inverse=False, white_black=False, phase_steps=3,
                        phase_axes=("x", "y"))
    plan = plan_camera_decode(phase, ["phase_x_0", "phase_x_1", "phase_y_2"])
    assert plan.action == "undecodable" and "no complete phase axis" in plan.reason
    plan = plan_camera_decode(phase, ["phase_y_0", "phase_y_1", "phase_y_2", "phase_x_0"])
    assert plan.action == "decode" and plan.spec.phase_axes == ("y",)
    assert plan.axes["x"]["phase"].startswith("dropped: frames ['phase_x_1', 'phase_x_2']")


def test_plan_drops_phase_the_codes_can_no_longer_unwrap():
    """Phase needs blocks of at most half a period: 256 px with a 16-px period unwraps from 5
    bits (8-px blocks), not from 4 (16-px blocks); an incomplete phase axis is dropped."""
    spec = PatternSpec(256, 192, n_bits_x=8, n_bits_y=8, phase_steps=3, phase_periods_x=16.0)
    names = pattern_names(spec)
    five = plan_camera_decode(spec, [n for n in names if not n.startswith("gray_x_05")])
    assert five.spec.n_bits_x == 5 and five.spec.phase_axes == ("x",)
    assert five.spec.phase_steps == 3 and five.axes["x"]["block_px"] == 8
    four = plan_camera_decode(spec, [n for n in names if not n.startswith("gray_x_04")])
    assert four.spec.phase_steps == 0 and four.axes["x"]["phase"].startswith("dropped: 4 bits")
    assert {"phase_x_0", "phase_x_1", "phase_x_2"} <= set(four.unused_frames)
    gone = plan_camera_decode(spec, [n for n in names if n != "phase_x_2"])
    assert gone.spec.phase_steps == 0 and gone.spec.n_bits_x == 8
    assert gone.axes["x"]["phase"] == "dropped: frames ['phase_x_2'] missing"


def test_plan_of_other_code_families():
    """XOR / long-run codes have no shorter prefix: a family that lost a bit is dropped, and so
    is every other family once the Gray code keeps fewer bits; half pairs of any family are
    decoded against the mid level; a long-run-only camera that lost a bit is undecodable."""
    spec = PatternSpec(256, 64, n_bits_y=0, codes=("gray", "xor04"))
    names = pattern_names(spec)
    plan = plan_camera_decode(spec, [n for n in names if not n.startswith("xor04_x_03")])
    assert plan.spec.codes == ("gray",) and plan.spec.n_bits_x == 8
    assert plan.dropped[0]["what"] == "code xor04" and "bit 3 of x lost" in plan.dropped[0]["why"]
    plan = plan_camera_decode(spec, [n for n in names if not n.startswith("gray_x_07")])
    assert plan.spec.codes == ("gray",) and plan.spec.n_bits_x == 7
    assert "Gray code keeps fewer bits" in plan.dropped[0]["why"]
    plan = plan_camera_decode(spec, [n for n in names if n != "xor04_x_02"])
    assert plan.spec == spec and plan.stand_ins == {"xor04_x_02_inv": "xor04_x_02"}
    minsw = PatternSpec(256, 64, n_bits_y=0, codes=("minsw",))
    plan = plan_camera_decode(minsw, [n for n in pattern_names(minsw)
                                      if not n.startswith("minsw_x_05")])
    assert plan.action == "undecodable"


def test_fewer_gray_bits_are_the_first_planes_of_the_full_code():
    """A reflected Gray code of n' < n bits over the same width is the first n' planes of the
    n-bit one (gray(c) >> s == gray(c >> s)): the pattern images are equal, pixel for pixel, on
    a power-of-two and on a non-power-of-two projector."""
    for w, h in ((1024, 768), (200, 120)):
        full = PatternSpec(w, h)
        for nx, ny in ((8, 7), (3, 1)):
            part = PatternSpec(w, h, n_bits_x=nx, n_bits_y=ny)
            for n in pattern_names(part):
                np.testing.assert_array_equal(pattern_image(part, n), pattern_image(full, n))


# ---------------------------------------------------------------- decoding with the plan


def _albedo_frames(spec, *, h=24, dtype=np.float32, channels=0):
    """Clean frames of an identity camera (camera column c sees projector column c) under
    ``spec``: ``albedo (0.05 + 0.9 P) + 0.01`` with a smooth albedo, linear."""
    rows, cols = np.mgrid[0:h, 0:spec.width].astype(np.float32)
    albedo = 0.35 + 0.3 * np.sin(cols / 97.0) * np.cos(rows / 7.0) + 0.2 * (cols / spec.width)
    out = {}
    for n in pattern_names(spec):
        f = albedo * (0.05 + 0.9 * pattern_image(spec, n)[:h]) + 0.01
        if channels:
            f = np.stack([f * k for k in (0.9, 1.0, 1.1)[:channels]], axis=-1)
        out[n] = f.astype(np.float32) if dtype == np.float32 else \
            np.clip(np.rint(f * 255), 0, 255).astype(dtype)
    return out


@pytest.mark.parametrize("dtype,channels", [(np.float32, 0), (np.uint8, 3)])
def test_half_pair_decodes_the_same_codes_as_the_full_pair(dtype, channels):
    """On clean linear frames ``white + black - frame`` is the inverse frame itself: the camera
    that lacks gray_x_09 (and another that lacks gray_x_04_inv) decodes the same columns, bit
    for bit, as the one with every pair (float frames; 8-bit RGB frames too, where the stand-in
    is in fractions of full scale)."""
    spec = PatternSpec(1024, 24, n_bits_y=0)
    frames = _albedo_frames(spec, dtype=dtype, channels=channels)
    ref = decode_stream(dict(frames), spec)
    assert ref.valid.all()
    np.testing.assert_array_equal(ref.x, np.broadcast_to(np.arange(1024.0), ref.x.shape))
    for gone in ("gray_x_09", "gray_x_04_inv"):
        plan = plan_camera_decode(spec, [n for n in frames if n != gone])
        assert plan.spec == spec and len(plan.stand_ins) == 1
        res = decode_stream(with_stand_in_partners(((n, frames[n]) for n in plan.frames), plan),
                            plan.spec)
        np.testing.assert_array_equal(res.x, ref.x)
        np.testing.assert_array_equal(res.valid, ref.valid)
        if dtype == np.float32:
            np.testing.assert_allclose(res.confidence, ref.confidence, atol=CONFIDENCE_ATOL)


def test_fewer_bit_decode_gives_block_centres_in_full_projector_pixels():
    """A camera that lost column bit 8 decodes PatternSpec(width=1024, n_bits_x=8) from the
    scan's own first 8 planes: every column c decodes to the centre of its 4-px block,
    ``4 (c // 4) + 1.5``, with ``sigma = 4 / sqrt(12)``."""
    spec = PatternSpec(1024, 24, n_bits_y=0)
    frames = _albedo_frames(spec)
    plan = plan_camera_decode(spec, [n for n in frames if not n.startswith("gray_x_08")])
    assert plan.spec == PatternSpec(1024, 24, n_bits_x=8, n_bits_y=0)
    assert plan.axes["x"]["block_px"] == 4 and plan.axes["x"]["codes_per_block"] == 4
    res = decode_stream(with_stand_in_partners(((n, frames[n]) for n in plan.frames), plan),
                        plan.spec)
    c = np.arange(1024)
    assert res.valid.all()
    np.testing.assert_array_equal(res.x, np.broadcast_to(4.0 * (c // 4) + 1.5, res.x.shape))
    np.testing.assert_allclose(res.sigma_x, 4.0 / np.sqrt(12.0), rtol=SIGMA_RTOL)


def test_stand_ins_stream_one_frame_at_a_time_and_need_white_black_first():
    spec = PatternSpec(64, 8, n_bits_y=0)
    frames = _albedo_frames(spec, h=8)
    plan = plan_camera_decode(spec, [n for n in frames if n != "gray_x_05"])
    taken = []

    def source():
        for n in plan.frames:
            taken.append(n)
            yield n, frames[n]

    it = with_stand_in_partners(source(), plan)
    assert next(it)[0] == "white" and taken == ["white"]  # lazy: no frame read ahead
    rest = list(it)
    names = [n for n, _ in rest]
    i = names.index("gray_x_05_inv")
    assert names[i + 1] == "gray_x_05" and rest[i + 1][1].dtype == np.float32
    np.testing.assert_allclose(rest[i + 1][1], frames["gray_x_05"], rtol=1e-6, atol=1e-7)
    late = [n for n in plan.frames if n not in ("white", "black")] + ["white", "black"]
    with pytest.raises(InputError, match="came before the white and black frames"):
        list(with_stand_in_partners(((n, frames[n]) for n in late), plan))
    with pytest.raises(InputError, match="action is 'decode'"):
        list(with_stand_in_partners([], CameraDecodePlan(None, "skip")))


@pytest.mark.shared_data
def test_real_half_pair_against_the_mid_level(shared_data):
    """alexander_quarter's left camera has every frame: decoding column bit 9 from its inverse
    alone against (white + black) / 2 (as the right camera must) and from the pair agree
    within 0.5 projector px on >= 99 % of the pixels both keep (measured 0.994), within 1 px on
    all: the half pair resolves the LSB where the pair called it unresolved (a stripe
    boundary, x.5). Frames linearised as sRGB (the data states no response)."""
    cv2 = pytest.importorskip("cv2")
    spec = PatternSpec(1024, 768)
    names = pattern_names(spec)
    root = "structured_light/alexander_quarter/leftCam/dataset1"
    paths = [shared_file(shared_data, f"{root}/{i:04d}.png") for i in range(len(names))]

    def frames(plan):
        for n in plan.frames:
            c = cv2.imread(str(paths[names.index(n)]), cv2.IMREAD_GRAYSCALE) / np.float32(255)
            yield n, np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4) \
                .astype(np.float32)

    full = plan_camera_decode(spec, names)
    half = plan_camera_decode(spec, [n for n in names if n != "gray_x_09"])
    a = decode_stream(frames(full), full.spec)
    b = decode_stream(with_stand_in_partners(frames(half), half), half.spec)
    both = a.valid_x & b.valid_x
    d = np.abs(a.x[both] - b.x[both])
    assert both.sum() > 0.8 * a.valid_x.sum()
    assert (d <= 0.5).mean() >= REAL_HALF_WITHIN_HALF_PX_MIN, (d <= 0.5).mean()
    assert (d <= 1.0).mean() >= REAL_HALF_WITHIN_ONE_PX


# ---------------------------------------------------------------- the decode stage


@pytest.fixture(scope="module")
def tiny_scan(tmp_path_factory):
    from facegeo.synth.capture import generate_scan

    root = tmp_path_factory.mktemp("decode_plan") / "tiny"
    generate_scan(root, "tiny", noise=0.005)
    return root


def _with_missing(src, dst, missing: dict):
    """A copy of scan ``src`` whose cameras lack ``missing[camera]`` (files deleted, declared in
    ``[structured_light.cameras.<camera>] missing``)."""
    from facegeo.capture.scan import load_scan

    shutil.copytree(src, dst)
    text = (dst / "scan.toml").read_text()
    for cam, frames in missing.items():
        for f in frames:
            (dst / "structured_light" / cam / f"{f}.png").unlink()
        text += (f"\n[structured_light.cameras.{cam}]\nmissing = "
                 + json.dumps(list(frames)) + "\n")
    (dst / "scan.toml").write_text(text)
    return load_scan(dst)


def test_stage_decodes_each_camera_from_its_own_frames(tiny_scan, tmp_path, caplog):
    """cam_right lacks gray_x_07 (decoded against the mid level) and gray_y_06 with its inverse
    (rows at 6 bits: 4-row blocks); the plan is in the metrics; x equals the full decode's
    where both are valid; y is the centre of the 4-row block (or the boundary of two) and
    within it of the truth. A camera with no structured-light frame is skipped, not an
    error."""
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.decode import run_decode

    full = run_decode(load_scan(tiny_scan), tmp_path / "out_full")
    lost = ["gray_x_07", "gray_y_06", "gray_y_06_inv"]
    scan = _with_missing(tiny_scan, tmp_path / "lost", {"cam_right": lost})
    with caplog.at_level(logging.INFO, logger="facegeo.pipeline.decode"):
        m = run_decode(scan, tmp_path / "out")
    assert m["skipped_cameras"] == []
    plan = m["cameras"]["cam_right"]["plan"]
    assert plan["bits"] == {"x": 8, "y": 6} and plan["block_px"] == {"x": 1, "y": 4}
    assert plan["half_pairs"][0]["present"] == "gray_x_07_inv"
    assert plan["lost_bits"][0]["missing"] == ["gray_y_06", "gray_y_06_inv"]
    assert m["cameras"]["cam_left"]["plan"]["half_pairs"] == []
    assert any("cam_right: x: 8 of 8 bits; y: 6 of 8 bits" in r.getMessage()
               for r in caplog.records)
    assert m["cameras"]["cam_right"]["exact_code_fraction"] >= BLOCK_EXACT_MIN
    assert len(m["cameras"]["cam_right"]["bits"]["y"]["gray"]["lost"]) == 6
    with np.load(tmp_path / "out_full" / "decode" / "cam_right" / "decode.npz") as a, \
            np.load(tmp_path / "out" / "decode" / "cam_right" / "decode.npz") as b:
        both = a["valid"] & b["valid"]
        assert both.sum() >= 0.99 * a["valid"].sum()
        same_x = (a["x"][both] == b["x"][both]).mean()
        assert same_x >= TINY_HALF_PAIR_SAME_X_MIN, same_x
        y = b["y"][b["valid"]]
        assert np.isin(y % 4.0, (1.5, 3.5)).all()  # block centre, or two blocks' boundary
        assert np.abs(b["y"][both] - a["y"][both]).max() <= 2.5
        np.testing.assert_allclose(np.unique(b["sigma_y"][b["valid"]])[0], 4 / np.sqrt(12),
                                   rtol=SIGMA_RTOL)
    assert not (tmp_path / "out" / "decode" / ".partial").exists()
    assert m["cameras"]["cam_left"]["valid_fraction"] == full["cameras"]["cam_left"][
        "valid_fraction"]

    # a camera of the calibration only (every structured-light frame missing): skipped
    calib_only = _with_missing(tiny_scan, tmp_path / "calib_only",
                               {"cam_left": load_scan(tiny_scan).sl_frames})
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="facegeo.pipeline.decode"):
        m = run_decode(calib_only, tmp_path / "out_calib")
    assert m["skipped_cameras"] == ["cam_left"] and list(m["cameras"]) == ["cam_right"]
    assert not (tmp_path / "out_calib" / "decode" / "cam_left").exists()
    assert any("cam_left: skipped, no structured-light frames" in r.getMessage()
               for r in caplog.records)


def test_stage_refuses_an_undecodable_camera_before_any_work(tiny_scan, tmp_path):
    from facegeo.pipeline.decode import run_decode

    msb = ["gray_x_00", "gray_x_00_inv", "gray_y_00", "gray_y_00_inv"]
    scan = _with_missing(tiny_scan, tmp_path / "msb", {"cam_right": msb})
    with pytest.raises(InputError, match=r"camera 'cam_right': no code bit left on any axis "
                                         r"\(missing \['gray_x_00'.*it lacks \['gray_x_00'"):
        run_decode(scan, tmp_path / "out")
    assert not (tmp_path / "out" / "decode").exists()  # cam_left was not decoded first


def test_a_finished_camera_survives_a_later_cameras_failure(tiny_scan, tmp_path, caplog):
    """cam_right's frame does not read: the stage fails, cam_left's finished decode waits in
    out/decode/.partial; changed settings decode it again (its key changes); once the frame is
    back, the next run takes cam_left from there (the same arrays) and the stage's completion
    removes .partial."""
    from facegeo.capture.scan import load_scan
    from facegeo.pipeline.decode import run_decode

    shutil.copytree(tiny_scan, tmp_path / "scan")
    scan = load_scan(tmp_path / "scan")
    bad = tmp_path / "scan" / "structured_light" / "cam_right" / "gray_x_03.png"
    good = bad.read_bytes()
    bad.write_bytes(b"not a png")
    out = tmp_path / "out"
    with pytest.raises(Exception):  # the reader's own error, naming the file
        run_decode(scan, out)
    record = out / "decode" / ".partial" / "cam_left" / "partial.json"
    key = json.loads(record.read_text())["key"]
    assert sorted(p.name for p in record.parent.iterdir()) == [
        "decode.npz", "partial.json", "x.png", "y.png"]
    assert not (out / "decode" / ".partial" / "cam_right").exists()
    with pytest.raises(Exception):
        run_decode(scan, out, rel_contrast=0.2)
    assert json.loads(record.read_text())["key"] != key  # other settings: decoded again
    bad.write_bytes(good)
    with caplog.at_level(logging.INFO, logger="facegeo.pipeline.decode"):
        m = run_decode(scan, out, rel_contrast=0.2)
    assert m["cameras"]["cam_left"].get("reused") is True
    assert "reused" not in m["cameras"]["cam_right"]
    assert any("cam_left: taken from" in r.getMessage() for r in caplog.records)
    assert not (out / "decode" / ".partial").exists()
    fresh = run_decode(scan, tmp_path / "fresh", rel_contrast=0.2)
    with np.load(out / "decode" / "cam_left" / "decode.npz") as a, \
            np.load(tmp_path / "fresh" / "decode" / "cam_left" / "decode.npz") as b:
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k])
    for k in ("valid_fraction", "exact_code_fraction", "valid_of_surface"):
        assert m["cameras"]["cam_left"][k] == fresh["cameras"]["cam_left"][k]


def test_the_pipeline_keeps_finished_cameras_too(tiny_scan, tmp_path, monkeypatch):
    """Through the stage cache (``facegeo decode`` / ``reconstruct``): cam_right's decode fails
    (here: the decoder raises, as a Ctrl-C would), cam_left waits in out/decode/.partial and is
    taken from there on the next run; the finished stage has no .partial."""
    import facegeo.geometry.structured_light as sl
    from facegeo.pipeline.reconstruct import run_reconstruct

    shutil.copytree(tiny_scan, tmp_path / "scan")
    decode_stream_ = sl.decode_stream
    calls = []

    def failing_second(frames, spec, **kw):
        calls.append(spec)
        if len(calls) == 2:
            raise RuntimeError("interrupted")
        return decode_stream_(frames, spec, **kw)

    monkeypatch.setattr(sl, "decode_stream", failing_second)
    with pytest.raises(RuntimeError, match="interrupted"):
        run_reconstruct(tmp_path / "scan", only="decode")
    partial = tmp_path / "scan" / "out" / "decode" / ".partial"
    assert [p.name for p in partial.iterdir()] == ["cam_left"]
    monkeypatch.setattr(sl, "decode_stream", decode_stream_)
    run_reconstruct(tmp_path / "scan", only="decode")
    m = json.loads((tmp_path / "scan" / "out" / "metrics.json").read_text())["decode"]
    assert m["cameras"]["cam_left"]["reused"] is True and "reused" not in m["cameras"]["cam_right"]
    assert not partial.exists() and (partial.parent / "cam_left" / "decode.npz").is_file()
