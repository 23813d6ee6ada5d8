"""Scan format version 2: the hand-written fixture scans in ``tests/fixtures/scans`` (one per
kind of rig), each way of being wrong, version-1 compatibility, and streaming memory."""

from __future__ import annotations

import shutil
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from facegeo.capture.imageio import read_image, srgb_to_linear, write_image
from facegeo.capture.scan import (
    LUMINANCE_WEIGHTS,
    load_scan,
    new_manifest,
    summarize,
    write_manifest,
)
from facegeo.errors import InputError, ScanFormatError

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "scans"
#: float32 round-off of a linearised 8-bit sample (relative), for exact-formula comparisons.
FLOAT32_TOL = 1e-6


def _copy(name: str, tmp_path: Path) -> Path:
    dst = tmp_path / name
    shutil.copytree(FIXTURES / name, dst)
    return dst


def _edit(root: Path, old: str, new: str) -> None:
    p = root / "scan.toml"
    text = p.read_text(encoding="utf-8")
    assert old in text, old
    p.write_text(text.replace(old, new, 1), encoding="utf-8")


# =========================================================================== fixtures load


def test_fixture_folder_is_small():
    """The brief caps the fixture folder at ~300 KB (bytes of the files, not blocks)."""
    total = sum(p.stat().st_size for p in FIXTURES.rglob("*") if p.is_file())
    assert total < 300_000, total


def test_light_stage_v2_loads_and_describes_itself():
    scan = load_scan(FIXTURES / "light_stage_v2", check="full")
    assert scan.version == 2 and not scan.frame_check.problems
    lights = scan.lights
    assert lights.n_lights == 6 and scan.light_names[1] == "A+090E+30"
    # Dome clipped at the horizon: the Voronoi cells cover exactly the upper hemisphere.
    assert abs(lights.solid_angles.sum() - 2 * np.pi) < 1e-9
    assert scan.camera_frames("olat", "cam_b") == [0, 2, 3, 4, 5]
    assert scan.missing_frames("olat", "cam_b") == [1]
    assert scan.olat_path("cam_a", "A+090E+30").name == "A+090E+30.pgm"
    with pytest.raises(InputError, match=r"camera 'cam_b' has no such frame"):
        scan.olat_path("cam_b", "A+090E+30")
    T = scan.world["T_world_rig"]
    assert T.shape == (4, 4) and T[1, 3] == 0.1
    assert scan.reference_path("intrinsics").is_file()
    text = summarize(scan)
    for needle in ["format version 2", "light list: 6 lights (directions)",
                   "dome clipped at the horizon: sum 6.283 sr", "ambient frame",
                   "cam_b: 5 of 6; lacks A+090E+30", "world frame: explicit transform",
                   "reference: 1 entry", "projector: none"]:
        assert needle in text, (needle, text)


def test_light_stage_v2_ambient_subtraction_and_light_names():
    scan = load_scan(FIXTURES / "light_stage_v2")
    d = FIXTURES / "light_stage_v2" / "olat" / "cam_a"
    raw = read_image(d / "A+180E+30.pgm").astype(np.float32) / 255
    amb = read_image(d / "ambient.pgm").astype(np.float32) / 255
    got = scan.olat_frame("cam_a", "A+180E+30", subtract_ambient=True)
    assert got.shape == (6, 8, 3)
    # Metric: max abs difference against the formula (raw − ambient)/255, each channel.
    assert np.abs(got - (raw - amb)[..., None]).max() < FLOAT32_TOL
    assert np.array_equal(scan.olat_frame("cam_a", 2), scan.olat_frame("cam_a", "A+180E+30"))
    lights = [light for light, _ in scan.iter_olat("cam_b")]
    assert lights == [0, 2, 3, 4, 5]


def test_structured_light_only_loads_and_describes_itself():
    scan = load_scan(FIXTURES / "structured_light_only", check="full")
    assert not scan.frame_check.problems
    assert scan.lights is None and not scan.rig.projector_calibrated
    assert scan.rig.projector.width == 16
    assert scan.sl_bits("cam_a") == {"x": 2, "y": 1}
    assert scan.sl_bits("cam_b") == {"x": 1, "y": 1}
    assert scan.missing_frames("structured_light", "cam_b") == [
        "gray_x_01", "gray_x_01_inv", "gray_y_00_inv"]
    # Each frame has its own suffix behind the ".*" template.
    assert {scan.sl_path("cam_a", f).suffix for f in scan.sl_frames} == {
        ".png", ".bmp", ".pgm", ".tif"}
    assert scan.reference_path("point_cloud").name == "points.ply"
    text = summarize(scan)
    for needle in ["projector: proj 16×8 px (uncalibrated", "lights: none",
                   "cam_a: 8 of 8", ("cam_b: 5 of 8; lacks gray_x_01, gray_x_01_inv, "
                                     "gray_y_00_inv; resolves bits_x = 1"), "files: structured_light/{camera}/{frame}.*"]:
        assert needle in text, (needle, text)


def test_structured_light_luminance_and_streaming_reader():
    scan = load_scan(FIXTURES / "structured_light_only")
    y = scan.sl_frame("cam_a", "gray_x_00", luminance=True)
    raw = read_image(scan.sl_path("cam_a", "gray_x_00"))
    assert y.dtype == np.float32 and y.shape == (6, 10)
    # Grey frames: luminance is the linearised sample (max abs error vs the sRGB formula).
    assert np.abs(y - srgb_to_linear(raw.astype(np.float32) / 255)).max() < FLOAT32_TOL
    names = [n for n, _ in scan.iter_sl("cam_b", luminance=True)]
    assert names == scan.camera_frames("structured_light", "cam_b")


def test_calibration_corners_loads_and_describes_itself():
    from facegeo.geometry._calib_detect import ChessboardSpec

    scan = load_scan(FIXTURES / "calibration_corners", check="full")
    assert isinstance(scan.board, ChessboardSpec) and scan.board_kind == "chessboard"
    assert not scan.calib_images and scan.calib_view_paths("cam_a") == []
    assert scan.calib_views("cam_a") == [0, 1, 2] and scan.calib_views("cam_b") == [0, 2]
    corners = scan.calib_corners("cam_b")
    assert sorted(corners) == [0, 2]
    c = corners[2]
    assert c.ids.shape == (12,) and c.object_points.shape == (12, 3) and c.image_points.shape == (12, 2)
    # The listed board points are the chessboard's own (max abs difference, metres).
    assert np.abs(c.object_points - scan.board.object_points()[c.ids]).max() < 1e-9
    assert scan.world == {"camera": "cam_a", "board_view": 0}
    text = summarize(scan)
    for needle in ["board inline chessboard", "no images", "cam_b: 2 of 3; lacks view 1",
                   "world frame: board in view 0 seen by cam_a", "lights: none"]:
        assert needle in text, (needle, text)


# =========================================================================== errors


def test_frame_listed_but_absent_names_the_file(tmp_path):
    root = _copy("structured_light_only", tmp_path)
    (root / "structured_light" / "cam_a" / "gray_x_01.png").unlink()
    with pytest.raises(ScanFormatError) as info:
        load_scan(root)
    msg = str(info.value)
    assert "gray_x_01.*" in msg and "[structured_light.files]" in msg and "cam_a" in msg


def test_declared_missing_olat_frame_present_elsewhere_is_fine_but_absent_one_is_not(tmp_path):
    root = _copy("light_stage_v2", tmp_path)
    (root / "olat" / "cam_a" / "A+225E+75.pgm").unlink()
    with pytest.raises(ScanFormatError, match=r"A\+225E\+75\.pgm \[olat.files\]: missing olat "
                                              r"frame: camera 'cam_a', light 5"):
        load_scan(root)


def test_missing_ambient_frame_names_the_file(tmp_path):
    root = _copy("light_stage_v2", tmp_path)
    (root / "olat" / "cam_b" / "ambient.pgm").unlink()
    with pytest.raises(ScanFormatError, match=r"cam_b/ambient\.pgm .*ambient frame"):
        load_scan(root)


def test_corner_list_of_wrong_shape_names_the_file(tmp_path):
    root = _copy("calibration_corners", tmp_path)
    p = root / "calib" / "cam_b" / "corners.csv"
    lines = p.read_text().splitlines()
    lines[3] = ",".join(lines[3].split(",")[:6])  # a row without its v column
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(ScanFormatError) as info:
        load_scan(root)
    assert "cam_b/corners.csv [calib.corners]: cannot read the corner list" in str(info.value)


def test_npz_corner_list_shapes_are_checked(tmp_path):
    root = _copy("calibration_corners", tmp_path)
    _edit(root, 'corners = "calib/{camera}/corners.csv"', 'corners = "calib/{camera}/corners.npz"')
    for cam in ("cam_a", "cam_b"):
        t = np.loadtxt(root / "calib" / cam / "corners.csv", delimiter=",", skiprows=1)
        np.savez(root / "calib" / cam / "corners.npz", view=t[:, 0].astype(int),
                 ids=t[:, 1].astype(int), object_points=t[:, 2:5], image_points=t[:, 5:7])
    scan = load_scan(root)
    csv_scan = load_scan(FIXTURES / "calibration_corners")
    a, b = scan.calib_corners("cam_a")[1], csv_scan.calib_corners("cam_a")[1]
    assert np.array_equal(a.image_points, b.image_points) and np.array_equal(a.ids, b.ids)
    t = np.loadtxt(root / "calib" / "cam_a" / "corners.csv", delimiter=",", skiprows=1)
    np.savez(root / "calib" / "cam_a" / "corners.npz", view=t[:, 0].astype(int),
             ids=t[:, 1].astype(int), object_points=t[:, 2:5], image_points=t[:, 4:7])
    with pytest.raises(ScanFormatError, match=r"cam_a/corners\.npz \[calib\.corners\]: "
                                              r"image_points has shape \(36, 3\)"):
        load_scan(root)


def test_corner_view_with_too_few_corners(tmp_path):
    root = _copy("calibration_corners", tmp_path)
    p = root / "calib" / "cam_a" / "corners.csv"
    lines = p.read_text().splitlines()
    keep = [ln for ln in lines if not ln.startswith("1,") or ln.split(",")[1] in "012"]
    p.write_text("\n".join(keep) + "\n")
    with pytest.raises(ScanFormatError, match=r"view 1 has 3 corner\(s\); a view needs at least 4"):
        load_scan(root)


def test_pattern_spec_not_matching_the_frames_names_the_frame(tmp_path):
    root = _copy("structured_light_only", tmp_path)
    _edit(root, '"gray_x_01", "gray_x_01_inv",', '"gray_x_01",')
    with pytest.raises(ScanFormatError) as info:
        load_scan(root)
    msg = str(info.value)
    assert "scan.toml [structured_light.frames]" in msg
    assert "projects frame 'gray_x_01_inv', which structured_light.frames does not list" in msg


@pytest.mark.parametrize("fixture, old, new, pattern", [
    pytest.param("structured_light_only", "n_bits_y = 1", "n_bits_y = 0",
                 r"frame 'gray_y_00' is not a pattern of structured_light.patterns",
                 id="frame-not-in-pattern-spec"),
    pytest.param("structured_light_only", "n_bits_x = 2", 'kind = "gray"\nbits_x = 2',
                 r"\[structured_light.patterns\]: PatternSpec: unknown key",
                 id="old-doc-pattern-keys"),
    pytest.param("structured_light_only", "bits_x = 1", "bits_x = 3",
                 r"\[structured_light.cameras.cam_b.bits_x\]: bits_x = 3 but the patterns code "
                 r"2 bits on x", id="bits-beyond-spec"),
    pytest.param("structured_light_only", "[structured_light.cameras.cam_b]",
                 "[structured_light.cameras.cam_z]",
                 r"\[structured_light.cameras.cam_z\]: no camera 'cam_z' in the rig",
                 id="unknown-camera"),
    pytest.param("light_stage_v2", 'missing = ["A+090E+30"]', 'missing = ["A+091E+30"]',
                 r"\[olat.cameras.cam_b.missing\]: .*no light named 'A\+091E\+30'",
                 id="unknown-light-name"),
    pytest.param("calibration_corners", 'world = { camera = "cam_a", board_view = 0 }',
                 'world = { camera = "cam_b", board_view = 1 }',
                 r"\[scan.world.board_view\]: camera 'cam_b' has no calibration view 1",
                 id="world-view-not-seen"),
    pytest.param("light_stage_v2", "[0.0, 0.0, -1.0, 0.1]", "[0.0, 0.0, -2.0, 0.1]",
                 r"\[scan.world.transform\]: expected a rigid", id="world-not-rigid"),
    pytest.param("light_stage_v2", "n_lights = 6", "n_lights = 7",
                 r"\[olat.n_lights\]: n_lights = 7 but the rig's light list has 6 lights",
                 id="light-list-size"),
    pytest.param("calibration_corners", "views = [0, 2]", "views = [0]",
                 r"cam_b/corners\.csv \[calib\.corners\]: the corner list has view 2",
                 id="corner-view-not-the-cameras"),
    pytest.param("calibration_corners", 'corners = "calib/{camera}/corners.csv"', "",
                 r"\[calib.images\]: images = false needs corner lists", id="no-images-no-corners"),
])
def test_edited_fixture_is_refused_naming_file_and_key(tmp_path, fixture, old, new, pattern):
    """One way of being wrong per case: the fixture with one edit of its scan.toml."""
    root = _copy(fixture, tmp_path)
    _edit(root, old, new)
    with pytest.raises(ScanFormatError, match=pattern):
        load_scan(root)


def test_two_files_for_one_frame_is_ambiguous(tmp_path):
    root = _copy("structured_light_only", tmp_path)
    d = root / "structured_light" / "cam_a"
    shutil.copy(d / "white.png", d / "white.bmp")
    with pytest.raises(ScanFormatError, match=r"white\.\* \[structured_light.files\]: 2 files "
                                              r"match white\.\*: white\.bmp, white\.png"):
        load_scan(root)


def test_olat_without_lights_is_refused(tmp_path):
    root = _copy("structured_light_only", tmp_path)
    with open(root / "scan.toml", "a") as fh:
        fh.write('\n[olat]\nn_lights = 4\nfiles = "olat/{camera}/{light:04d}.png"\n')
    with pytest.raises(ScanFormatError, match=r"\[olat\]: \[olat\] is present but the rig has "
                                              r"no lights"):
        load_scan(root)


# =========================================================================== version 1

V1_MANIFEST = """\
# facegeo scan manifest, format facegeo-scan version 1; see docs/scan-format.md
[scan]
format = "facegeo-scan"
version = 1
name = "old"
synthetic = false
description = ""
rig = "rig.json"

[structured_light]
response = "srgb"
projector = "proj"
frames = ["white", "black", "gray_x_00"]
files = "structured_light/{camera}/{frame}.png"

[structured_light.patterns]
kind = "gray"
bits_x = 1
bits_y = 0
"""


def _v1_scan(root: Path) -> None:
    from facegeo.frames import look_at
    from facegeo.geometry.camera import Camera
    from facegeo.geometry.rig import LightStage, Rig

    K = np.array([[30.0, 0, 11.7], [0, 30.4, 8.2], [0, 0, 1]])
    cams = [Camera(n, 24, 16, K, None, look_at([x, 0.0, 1.0], [0, 0, 0]))
            for n, x in (("cam_a", -0.2), ("cam_b", 0.2))]
    proj = Camera("proj", 40, 30, K, None, look_at([0.0, 0.1, 1.0], [0, 0, 0]))
    Rig(cams, proj, LightStage(2, 2)).save(root / "rig.json")
    for c in ("cam_a", "cam_b"):
        for f in ("white", "black", "gray_x_00"):
            write_image(root / "structured_light" / c / f"{f}.png",
                        np.full((16, 24), 128, np.uint8))
    (root / "scan.toml").write_text(V1_MANIFEST, encoding="utf-8")


def test_version_1_scan_written_literally_still_loads(tmp_path):
    """A version-1 manifest as the previous release wrote it, free-form patterns included."""
    _v1_scan(tmp_path)
    scan = load_scan(tmp_path, check="full")
    assert scan.version == 1 and scan.sl_frames == ["white", "black", "gray_x_00"]
    assert scan.camera_frames("structured_light", "cam_b") == ["white", "black", "gray_x_00"]
    assert scan.sl_frame("cam_a", "black").shape == (16, 24)
    assert "format version 1" in summarize(scan)


def test_version_1_manifest_may_not_use_version_2_keys(tmp_path):
    _v1_scan(tmp_path)
    with open(tmp_path / "scan.toml", "a") as fh:
        fh.write("\n[structured_light.cameras.cam_b]\nmissing = [\"black\"]\n")
    with pytest.raises(ScanFormatError, match=r"\[structured_light.cameras\]: structured_light."
                                              r"cameras is a version-2 feature .* set "
                                              r"scan.version = 2"):
        load_scan(tmp_path)


def test_new_manifest_writes_version_2():
    assert new_manifest("x", synthetic=True)["scan"]["version"] == 2


# =========================================================================== projector captures


def test_projector_calibration_captures_without_a_subject_group(tmp_path):
    """[calib.projector] with its own frames and pattern spec, read linearised and as luminance."""
    from facegeo.frames import look_at
    from facegeo.geometry.camera import Camera
    from facegeo.geometry.rig import Projector, Rig

    K = np.array([[30.0, 0, 11.7], [0, 30.4, 8.2], [0, 0, 1]])
    cam = Camera("cam", 24, 16, K, None, look_at([0.0, 0.0, 1.0], [0, 0, 0]))
    Rig([cam], Projector("proj", 16, 8), None).save(tmp_path / "rig.json")
    (tmp_path / "calib").mkdir()
    (tmp_path / "calib" / "board.json").write_text(
        '{"kind": "circles", "cols": 4, "rows": 5, "spacing": 0.02, "asymmetric": true}')
    frames = ["white", "black", "gray_x_00", "gray_x_00_inv"]
    rgb = np.random.default_rng(3).integers(0, 256, (16, 24, 3), dtype=np.uint8)
    for v in range(2):
        for f in frames:
            write_image(tmp_path / "calib" / "projector" / "cam" / f"view_{v:02d}_{f}.png", rgb)
    m = new_manifest("proj-calib", synthetic=False)
    m["calib"] = {"views": 1, "images": False, "corners": "calib/{camera}/corners.csv",
                  "projector": {"views": 2, "frames": frames,
                                "patterns": {"n_bits_x": 1, "n_bits_y": 0}}}
    (tmp_path / "calib" / "cam").mkdir()
    (tmp_path / "calib" / "cam" / "corners.csv").write_text(
        "view,id,x,y,z,u,v\n" + "".join(f"0,{i},{i * 0.01},0,0,{i + 3.5},4.25\n" for i in range(4)))
    write_manifest(tmp_path, m)
    scan = load_scan(tmp_path, check="full")
    assert not scan.has("structured_light") and scan.projector_frames == frames
    assert scan.pattern_spec("calib.projector").n_bits_x == 1
    assert scan.board_kind == "circles" and scan.board.asymmetric
    lin = srgb_to_linear(rgb.astype(np.float32) / 255)
    got = scan.projector_frame("cam", 1, "gray_x_00")
    assert np.abs(got - lin).max() < FLOAT32_TOL  # max abs error vs the sRGB formula
    y = scan.projector_frame("cam", 1, "gray_x_00", luminance=True)
    assert np.abs(y - lin @ LUMINANCE_WEIGHTS).max() < FLOAT32_TOL
    assert [n for n, _ in scan.iter_projector("cam", 0, luminance=True)] == frames


# =========================================================================== streaming

N_STREAM, STREAM_H, STREAM_W = 40, 1024, 1280
#: One linear float32 RGB frame of the streaming group, bytes.
FRAME_F32_RGB = STREAM_H * STREAM_W * 3 * 4
#: Peak Python-heap allocation allowed while iterating the group: a few frames (the decoded
#: 8-bit frame, its float32 linearisation and the luminance), against 40 frames if it held them.
STREAM_PEAK_FRAMES = 3


@pytest.mark.slow
def test_iterating_a_40_frame_rgb_group_holds_only_a_few_frames(tmp_path):
    """Peak traced memory (tracemalloc, numpy buffers included) while summing 40 1280 × 1024 RGB
    frames read one at a time as luminance, against the group's 40 × 15.7 MB as float32 RGB."""
    from facegeo.frames import look_at
    from facegeo.geometry.camera import Camera
    from facegeo.geometry.rig import Projector, Rig

    K = np.array([[1500.0, 0, 639.2], [0, 1502.0, 511.7], [0, 0, 1]])
    Rig([Camera("cam", STREAM_W, STREAM_H, K, None, look_at([0, 0, 1.0], [0, 0, 0]))],
        Projector("proj", 1024, 768), None).save(tmp_path / "rig.json")
    frames = [f"f{k:02d}" for k in range(N_STREAM)]
    d = tmp_path / "structured_light" / "cam"
    img = np.zeros((STREAM_H, STREAM_W, 3), np.uint8)
    img[::7] = 200
    write_image(d / "f00.png", img)
    for f in frames[1:]:
        (d / f"{f}.png").hardlink_to(d / "f00.png")  # 40 frames, one file's worth of disk
    m = new_manifest("stream", synthetic=False)
    m["structured_light"] = {"projector": "proj", "frames": frames}
    write_manifest(tmp_path, m)
    scan = load_scan(tmp_path)
    acc = np.zeros((STREAM_H, STREAM_W), np.float64)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        n = 0
        for _, y in scan.iter_sl("cam", luminance=True):
            acc += y
            n += 1
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    print(f"peak {peak / 1e6:.1f} MB = {peak / FRAME_F32_RGB:.2f} float32 RGB frames")
    assert n == N_STREAM
    assert peak < STREAM_PEAK_FRAMES * FRAME_F32_RGB, (peak / FRAME_F32_RGB)
    assert abs(acc[0, 0] - N_STREAM * float(srgb_to_linear(np.float32(200 / 255)))) < 1e-3


def test_every_documented_manifest_passes_the_schema():
    """Each ```toml block of docs/scan-format.md with a [scan] section is a valid manifest;
    the [calib.projector] fragment is valid under a minimal [scan]."""
    import re
    import tomllib

    from facegeo.capture.scan import validate_manifest

    doc = Path(__file__).resolve().parents[1] / "docs" / "scan-format.md"
    if not doc.is_file():
        pytest.skip(f"{doc} is absent")
    blocks = re.findall(r"```toml\n(.*?)```", doc.read_text(encoding="utf-8"), re.DOTALL)
    assert len(blocks) >= 5
    head = '[scan]\nformat = "facegeo-scan"\nversion = 2\nname = "x"\n'
    for block in blocks:
        if block.lstrip().startswith("[import]"):  # the importer's option table, not a manifest
            continue
        m = tomllib.loads(block if "[scan]" in block else head + block)
        validate_manifest(m)


# =========================================================================== import


def test_import_folder_links_exactly_the_named_files(tmp_path):
    """A folder plus its description becomes a scan: every named file hard-linked at the same
    relative path (same inode), nothing else carried, the manifest written last."""
    import tomllib

    from facegeo.capture.importer import import_folder

    src = tmp_path / "dataset"
    shutil.copytree(FIXTURES / "structured_light_only", src)
    desc = tmp_path / "describe.toml"
    (src / "scan.toml").rename(desc)
    (src / "README.txt").write_text("not part of the scan")
    scan = import_folder(src, tmp_path / "scan", desc)
    dest = tmp_path / "scan"
    assert scan.root == dest.absolute() and scan.version == 2
    assert not (dest / "README.txt").exists()
    a = src / "structured_light" / "cam_a" / "black.bmp"
    b = dest / "structured_light" / "cam_a" / "black.bmp"
    assert a.stat().st_ino == b.stat().st_ino
    assert tomllib.loads((dest / "scan.toml").read_text())["scan"]["name"] == "structured_light_only"
    assert "hard links counted once" in summarize(scan)
    copied = import_folder(src, tmp_path / "copy", desc, mode="copy")
    assert (copied.root / "rig.json").stat().st_ino != (src / "rig.json").stat().st_ino


def test_import_refuses_a_description_that_does_not_match_the_folder(tmp_path):
    from facegeo.capture.importer import import_folder

    src = tmp_path / "dataset"
    shutil.copytree(FIXTURES / "light_stage_v2", src)
    desc = tmp_path / "describe.toml"
    (src / "scan.toml").rename(desc)
    (src / "olat" / "cam_a" / "A+045E+75.pgm").unlink()
    with pytest.raises(ScanFormatError, match=r"dataset/olat/cam_a/A\+045E\+75\.pgm \[olat.files\]"):
        import_folder(src, tmp_path / "scan", desc)
    assert not (tmp_path / "scan").exists()
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(InputError, match=r"not an empty directory"):
        import_folder(src, tmp_path / "full", desc)
    # never into the source (a data set, a real capture): not inside it, not the folder itself
    before = sorted(p.relative_to(src).as_posix() for p in src.rglob("*"))
    for dest in (src / "scan", src, src / "olat" / "x"):
        with pytest.raises(InputError, match=r"inside the source folder"):
            import_folder(src, dest, desc)
    assert sorted(p.relative_to(src).as_posix() for p in src.rglob("*")) == before


def test_flat_one_camera_folder_with_numbered_and_named_files(tmp_path):
    """A data set as shipped: one camera, no camera folder, structured-light frames numbered
    from 1 ({number}) and flashes named after their light (P00{light_name}.pgm), plus an
    ambient frame; a version-1 manifest may not use these template fields."""
    from facegeo.frames import look_at
    from facegeo.geometry.camera import Camera
    from facegeo.geometry.lights import LightList
    from facegeo.geometry.rig import Projector, Rig

    K = np.array([[30.0, 0, 11.7], [0, 30.4, 8.2], [0, 0, 1]])
    names = ["A+000E+00", "A+090E+00", "A-090E+00", "A+000E+90", "A+180E+00", "A+000E-90"]
    dirs = [[0, 0, 1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, 0, -1], [0, -1, 0]]
    Rig([Camera("cam", 24, 16, K, None, look_at([0, 0, 1.0], [0, 0, 0]))],
        Projector("proj", 4, 2), LightList(directions=dirs, names=names)).save(tmp_path / "rig.json")
    frames = ["white", "black", "gray_x_00", "gray_x_00_inv"]
    grey = np.full((16, 24), 90, np.uint8)
    for i, _ in enumerate(frames):
        write_image(tmp_path / f"{i + 1}.png", grey)
    for n in names + ["_Ambient"]:
        write_image(tmp_path / f"P00{n}.png", grey)
    m = new_manifest("flat", synthetic=False)
    m["structured_light"] = {"projector": "proj", "frames": frames, "files": "{number}.png",
                             "patterns": {"n_bits_x": 1, "n_bits_y": 0}}
    m["olat"] = {"n_lights": 6, "response": "srgb", "files": "P00{light_name}.png",
                 "ambient": "P00_Ambient.png"}
    write_manifest(tmp_path, m)
    scan = load_scan(tmp_path, check="full")
    assert scan.sl_path("cam", "gray_x_00").name == "3.png"
    assert scan.olat_path("cam", "A+000E+90").name == "P00A+000E+90.png"
    # The six octahedron directions split the sphere equally (exact by symmetry, sr).
    assert np.abs(scan.lights.solid_angles - 4 * np.pi / 6).max() < 1e-9
    text = (tmp_path / "scan.toml").read_text().replace("version = 2", "version = 1")
    text = text.replace('ambient = "P00_Ambient.png"\n', "")
    (tmp_path / "scan.toml").write_text(text)
    with pytest.raises(ScanFormatError, match=r"\[structured_light.files\]: structured_light."
                                              r"files is a version-2 feature"):
        load_scan(tmp_path)


# =========================================================================== real layouts

#: A nominal 640 × 480 camera for real sets whose intrinsics calibration will find.
_NOMINAL_K = [[530.0, 0.0, 319.5], [0.0, 530.0, 239.5], [0.0, 0.0, 1.0]]


def test_real_stereo_chessboard_folder_is_expressible(shared_data, tmp_path):
    """OpenCV's stereo sample (left01.jpg … right14.jpg, pose 10 absent on both cameras, a
    9 × 6 chessboard) imported as shipped: numbered files, per-camera missing views."""
    import json

    from facegeo.capture.importer import import_folder
    from conftest import shared_file

    src = shared_file(shared_data, "calibration/opencv_stereo_chessboards")
    rig = {"format": "facegeo-rig", "version": 1, "projector": None, "lights": None,
           "cameras": [{"name": n, "width": 640, "height": 480, "K": _NOMINAL_K, "dist": [],
                        "T_cam_world": {"R": np.eye(3).tolist(), "t": [x, 0.0, 0.0]}}
                       for n, x in (("left", 0.0), ("right", -0.06))]}
    (tmp_path / "rig.json").write_text(json.dumps(rig))
    m = {"scan": {"format": "facegeo-scan", "version": 2, "name": "opencv_stereo",
                  "rig": "rig.json"},
         "calib": {"board": {"kind": "chessboard", "cols": 9, "rows": 6, "square_size": 0.025},
                   "views": 14, "files": "{camera}{number:02d}.jpg",
                   "cameras": {"left": {"missing": [9]}, "right": {"missing": [9]}}},
         "reference": {"intrinsics": "intrinsics.yml"}}
    scan = import_folder(src, tmp_path / "scan", m, rig=tmp_path / "rig.json")
    assert not (src / "rig.json").exists() and (tmp_path / "scan" / "rig.json").is_file()
    assert scan.calib_views("left") == [0, 1, 2, 3, 4, 5, 6, 7, 8, 10, 11, 12, 13]
    assert scan.calib_view_paths("right")[-1].name == "right14.jpg"
    assert "left: 13 of 14; lacks view 9" in summarize(scan)


def test_projector_frames_without_patterns_and_a_camera_with_no_views(tmp_path):
    """[calib.projector] with its own frames but no pattern spec loads (nothing to check the
    frames against); a camera listed with views = [] needs no corner list."""
    root = _copy("calibration_corners", tmp_path)
    _edit(root, "views = [0, 2]", "views = []")
    (root / "calib" / "cam_b" / "corners.csv").unlink()
    with open(root / "scan.toml", "a") as fh:
        fh.write('\n[calib.projector]\nviews = 1\nframes = ["white"]\n'
                 'files = "calib/projector/{camera}/{view}_{frame}.png"\n'
                 '[calib.projector.cameras.cam_b]\nviews = []\n')
    write_image(root / "calib" / "projector" / "cam_a" / "0_white.png",
                np.full((480, 640), 200, np.uint8))
    scan = load_scan(root)
    assert scan.calib_views("cam_b") == [] and scan.pattern_spec("calib.projector") is None
    assert scan.camera_frames("calib.projector", "cam_a") == [(0, "white")]
    assert "cam_b: 0 of 1; lacks view 0 white" in summarize(scan)
