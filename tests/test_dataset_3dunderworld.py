"""``facegeo import --dataset 3dunderworld``: a 3DUNDERWORLD-SLS capture as a scan.

Real data: ``../shared/data/structured_light/alexander_quarter`` (skipped when absent); the
behaviour that needs no real data runs on a small synthetic source tree of the same layout.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest

from facegeo.capture.datasets import import_dataset
from facegeo.capture.scan import load_scan
from facegeo.errors import InputError
from facegeo.geometry.structured_light import PatternSpec, pattern_names

ALEXANDER = "structured_light/alexander_quarter"
#: The README's lost frames of the right camera: 0020, 0038, 0039, 0041.
RIGHT_MISSING = ["gray_x_09", "gray_y_08", "gray_y_08_inv", "gray_y_09_inv"]
SPEC = PatternSpec(width=1024, height=768, n_bits_x=10, n_bits_y=10, inverse=True,
                   white_black=True)
NAMES = pattern_names(SPEC)

# Tolerances and thresholds (named, with units).
RULE_MAX_PX = 1e-9  # max |K − K_xml scaled by the pixel-centre rule|, pixels
BOX_MEAN_MAX = 0.5  # max |reduced frame − exact block mean|, 8-bit code values (rounding)
LIT_CONTRAST = 0.03  # white − black (linear) above which a pixel sees the projector
LIT_MIN_FRACTION = 0.99  # reference points that must project onto lit pixels (measured 0.995+)
INSIDE_MIN_FRACTION = 0.995  # reference points that must project inside each image (0.9989)


def _source(shared_data) -> Path:
    src = shared_data / ALEXANDER
    if not src.is_dir():
        pytest.skip(f"{src} is absent from the shared data")
    return src


@pytest.fixture(scope="module")
def alexander(tmp_path_factory):
    """The real capture imported once at scale 1 (hard links)."""
    from conftest import SHARED_DATA

    src = SHARED_DATA / ALEXANDER
    if not src.is_dir():
        pytest.skip(f"{src} is absent (set FACEGEO_SHARED_DATA)")
    dest = tmp_path_factory.mktemp("underworld") / "alexander"
    return src, import_dataset("3dunderworld", src, dest)


def _xml_matrix(path: Path, tag: str) -> np.ndarray:
    """An opencv-matrix of a calib.xml, read with ElementTree (independent of cv2)."""
    node = ET.parse(path).getroot().find(f"Camera/{tag}")
    rows, cols = int(node.find("rows").text), int(node.find("cols").text)
    return np.array(node.find("data").text.split(), float).reshape(rows, cols)


def _read_ply_xyz(path: Path) -> np.ndarray:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii")
    assert "binary_little_endian" in header and "property double z" in header
    n = int(header.split("element vertex ")[1].split()[0])
    return np.frombuffer(data, "<f8", count=3 * n, offset=end).reshape(n, 3)


def _k_by_rule(K: np.ndarray, s: float) -> np.ndarray:
    out = K.copy()
    out[0, 0] *= s
    out[1, 1] *= s
    out[:2, 2] = (K[:2, 2] + 0.5) * s - 0.5
    return out


# ------------------------------------------------------------------ the real capture


def test_alexander_imports_and_declares_the_lost_frames(alexander):
    src, scan = alexander
    scan = load_scan(scan.root)  # loads (quick check) from disk
    assert scan.camera_names == ["left", "right"]
    assert not scan.rig.projector_calibrated
    assert (scan.rig.projector.width, scan.rig.projector.height) == (1024, 768)
    assert scan.sl_frames == NAMES
    assert scan.pattern_spec("structured_light") == SPEC
    assert scan.missing_frames("structured_light", "left") == []
    assert scan.missing_frames("structured_light", "right") == RIGHT_MISSING
    assert not scan.has("calib")  # board views deliberately not declared (docs/datasets.md)
    # frames keep the README's order: file k is pattern k, carried byte for byte
    for cam, folder in (("left", "leftCam"), ("right", "rightCam")):
        for k in (0, 1, 2, 21, 22, 40):
            if NAMES[k] in RIGHT_MISSING and cam == "right":
                continue
            assert os.path.samefile(scan.sl_path(cam, NAMES[k]),
                                    src / folder / "dataset1" / f"{k:04d}.png")
    meta = scan.manifest["scan"]["metadata"]
    assert meta["source_frames"]["right"]["gray_x_09_inv"] == "rightCam/dataset1/0021.png"
    assert "gray_x_09" not in meta["source_frames"]["right"]
    assert meta["calibration"]["left"] == {"file": "leftCam/calib/output/calib.xml",
                                           "calibrated_size": [4896, 3264], "scale": 0.25}
    assert meta["board_views"]["declared"] is False


@pytest.mark.parametrize("cam,folder", [("left", "leftCam"), ("right", "rightCam")])
def test_alexander_intrinsics_are_the_xml_scaled_by_the_pixel_centre_rule(alexander, cam,
                                                                          folder):
    src, scan = alexander
    xml = src / folder / "calib" / "output" / "calib.xml"
    c = scan.rig.camera(cam)
    assert c.size == (1224, 816)
    assert np.abs(c.K - _k_by_rule(_xml_matrix(xml, "Matrix"), 0.25)).max() < RULE_MAX_PX
    assert np.array_equal(c.dist, _xml_matrix(xml, "Distortion").ravel())
    assert np.array_equal(c.T_cam_world.R, _xml_matrix(xml, "Rotation"))
    assert np.array_equal(c.T_cam_world.t, _xml_matrix(xml, "Translation").ravel() * 1e-3)


def test_alexander_reference_cloud_is_in_metres_in_the_rigs_world_frame(alexander):
    """The reference cloud, converted to metres, projects through the scaled rig onto the lit
    bust: ≥ 99 % of the points inside each image fall where white − black > 0.03 (the image
    as a whole: about 22 %); a camera with its principal point's x and y swapped gets ~55 %."""
    src, scan = alexander
    p_world = _read_ply_xyz(scan.reference_path("point_cloud"))
    assert p_world.shape == (146064, 3)
    first = np.array(src.joinpath("alexander_reference.obj").open().readline().split()[1:],
                     float)
    assert np.array_equal(p_world[0], first * 1e-3)
    extent = p_world.max(0) - p_world.min(0)
    assert 0.15 < extent.max() < 0.5  # a bust, in metres
    for cam in scan.camera_names:
        c = scan.rig.camera(cam)
        q, ok = c.project(p_world)
        inside = ok & c.in_image(q)
        assert inside.mean() >= INSIDE_MIN_FRACTION
        lit = (scan.sl_frame(cam, "white", luminance=True)
               - scan.sl_frame(cam, "black", luminance=True)) > LIT_CONTRAST
        qi = np.rint(q[inside]).astype(int)
        assert lit[qi[:, 1], qi[:, 0]].mean() >= LIT_MIN_FRACTION, cam


def test_alexander_half_scale_from_a_few_frames(shared_data, tmp_path):
    """``scale=0.5`` on a source tree holding a few of the frames: frames are the exact 2 × 2
    block means (to rounding), K follows the rule from the xml with s = 1/8, and the frames
    the tree lacks are declared missing per camera."""
    real = _source(shared_data)
    src = tmp_path / "src"
    keep = {"leftCam": [0, 1, 20], "rightCam": [0, 1, 21]}
    for folder, ks in keep.items():
        (src / folder / "dataset1").mkdir(parents=True)
        (src / folder / "calib" / "output").mkdir(parents=True)
        os.link(real / folder / "calib/output/calib.xml",
                src / folder / "calib/output/calib.xml")
        for k in ks:
            os.link(real / folder / "dataset1" / f"{k:04d}.png",
                    src / folder / "dataset1" / f"{k:04d}.png")
    scan = import_dataset("3dunderworld", src, tmp_path / "half", scale=0.5)
    assert scan.missing_frames("structured_light", "left") == [
        n for k, n in enumerate(NAMES) if k not in keep["leftCam"]]
    assert scan.missing_frames("structured_light", "right") == [
        n for k, n in enumerate(NAMES) if k not in keep["rightCam"]]
    assert scan.reference_keys == []  # the tree has no .obj
    for cam, folder in (("left", "leftCam"), ("right", "rightCam")):
        c = scan.rig.camera(cam)
        assert c.size == (612, 408)
        xml_K = _xml_matrix(src / folder / "calib/output/calib.xml", "Matrix")
        assert np.abs(c.K - _k_by_rule(xml_K, 0.125)).max() < RULE_MAX_PX
        k = keep[folder][-1]
        full = cv2.imread(str(src / folder / "dataset1" / f"{k:04d}.png"), cv2.IMREAD_UNCHANGED)
        half = cv2.imread(str(scan.sl_path(cam, NAMES[k])), cv2.IMREAD_UNCHANGED)
        assert scan.sl_path(cam, NAMES[k]).suffix == ".png" and half.dtype == np.uint8
        mean = full.astype(np.float64).reshape(408, 2, 612, 2).mean(axis=(1, 3))
        assert np.abs(half - mean).max() <= BOX_MEAN_MAX
    assert scan.manifest["scan"]["metadata"]["frames_scale"] == 0.5


# ------------------------------------------------------------------ synthetic source trees


def _write_calib_xml(path: Path, size=(96, 64), *, skip: str | None = None) -> None:
    """A calib.xml in the scanner's spelling (millimetres), optionally without one key."""
    path.parent.mkdir(parents=True, exist_ok=True)
    K = np.array([[120.5, 0.0, 47.3], [0.0, 121.25, 31.6], [0.0, 0.0, 1.0]])
    R = cv2.Rodrigues(np.array([0.1, -0.3, 0.05]))[0]
    entries = {"Calibrated": 1, "Matrix": K,
               "Distortion": np.array([[0.01, -0.02, 1e-4, -2e-4, 0.003]]), "Rotation": R,
               "Translation": np.array([[12.0], [-30.0], [950.0]]),
               "Height": size[1], "Width": size[0]}
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.startWriteStruct("Camera", cv2.FileNode_MAP)
    for k, v in entries.items():
        if k != skip:
            fs.write(k, v)
    fs.endWriteStruct()
    fs.release()


def _synthetic_source(root: Path, *, size=(48, 32), xml_size=(96, 64), frames=None,
                      obj: bool = True) -> Path:
    rng = np.random.default_rng(1)
    frames = frames or {"leftCam": range(42), "rightCam": [k for k in range(42) if k != 5]}
    for folder, ks in frames.items():
        _write_calib_xml(root / folder / "calib" / "output" / "calib.xml", xml_size)
        (root / folder / "dataset1").mkdir(parents=True, exist_ok=True)
        for k in ks:
            cv2.imwrite(str(root / folder / "dataset1" / f"{k:04d}.png"),
                        rng.integers(0, 256, (size[1], size[0]), dtype=np.uint8))
    if obj:
        (root / "scan_output.obj").write_text("# points\nv 1.5 -2.0 900.25\nv 0 0 1000\n")
    return root


def test_synthetic_tree_converts_at_scale_1_and_quarter(tmp_path):
    src = _synthetic_source(tmp_path / "src")
    scan = import_dataset("3dunderworld", src, tmp_path / "full")
    c = scan.rig.camera("left")
    assert c.size == (48, 32)
    assert np.abs(c.K - _k_by_rule(_xml_matrix(src / "leftCam/calib/output/calib.xml",
                                               "Matrix"), 0.5)).max() < RULE_MAX_PX
    assert c.T_cam_world.t[2] == pytest.approx(0.95, rel=1e-12)
    assert scan.missing_frames("structured_light", "right") == ["gray_x_01_inv"]  # frame 0005
    assert np.array_equal(_read_ply_xyz(scan.reference_path("point_cloud")),
                          [[1.5e-3, -2.0e-3, 0.90025], [0.0, 0.0, 1.0]])
    q = import_dataset("3dunderworld", src, tmp_path / "quarter", scale=0.25)
    assert q.rig.camera("right").size == (12, 8)
    assert load_scan(q.root, check="full").camera_names == ["left", "right"]


def test_bad_scales_are_refused(tmp_path):
    src = _synthetic_source(tmp_path / "src", size=(50, 30), xml_size=(100, 60))
    with pytest.raises(InputError, match=r"scale: expected 1, 0.5 or 0.25.*got 0.3"):
        import_dataset("3dunderworld", src, tmp_path / "a", scale=0.3)
    with pytest.raises(InputError, match=r"0000\.png: 50 x 30 pixels do not divide by 4"):
        import_dataset("3dunderworld", src, tmp_path / "b", scale=0.25)
    with pytest.raises(InputError, match=r"scale: the yale-b converter .* only 3dunderworld"):
        import_dataset("yale-b", src, tmp_path / "c", scale=0.5)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]  # no staging folder left


def test_bad_source_trees_give_clear_errors(tmp_path):
    src = _synthetic_source(tmp_path / "src")
    (src / "rightCam/calib/output/calib.xml").unlink()
    with pytest.raises(InputError, match=r"rightCam/calib/output.*missing calib\.xml"):
        import_dataset("3dunderworld", src, tmp_path / "a")
    _write_calib_xml(src / "rightCam/calib/output/calib.xml", skip="Translation")
    with pytest.raises(InputError, match=r"rightCam/calib/output/calib\.xml "
                                         r"\[Camera/Translation\]: missing"):
        import_dataset("3dunderworld", src, tmp_path / "b")
    _write_calib_xml(src / "rightCam/calib/output/calib.xml", size=(96, 60))  # not 2:1 of 48x32
    with pytest.raises(InputError, match=r"calib\.xml: calibrated at 96 x 60.*uniform"):
        import_dataset("3dunderworld", src, tmp_path / "c")
    _write_calib_xml(src / "rightCam/calib/output/calib.xml")
    cv2.imwrite(str(src / "leftCam/dataset1/0042.png"), np.zeros((32, 48), np.uint8))
    with pytest.raises(InputError, match=r"0042\.png: frame 42, but the scanner's patterns "
                                         r"have 42"):
        import_dataset("3dunderworld", src, tmp_path / "d")
    (src / "leftCam/dataset1/0042.png").unlink()
    (src / "leftCam/calib/output/calib.xml").write_text("not a calibration\n")
    with pytest.raises(InputError, match=r"leftCam/calib/output/calib\.xml: not an OpenCV "
                                         "FileStorage file"):
        import_dataset("3dunderworld", src, tmp_path / "e")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]
