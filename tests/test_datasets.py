"""Public data sets converted into scans (``facegeo.capture.datasets``), loaded and checked."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from conftest import shared_file
from facegeo.capture.datasets import DATASETS, import_dataset, yale_light_direction
from facegeo.capture.scan import load_scan, summarize
from facegeo.errors import InputError

SOURCES = {
    "opencv-stereo": "calibration/opencv_stereo_chessboards",
    "yale-b": "olat/yale_b01",
    "graycode-mannequin": "structured_light/graycode_mannequin",
    "three-phase": "structured_light/face_threephase",
}


@pytest.fixture(scope="module")
def converted(tmp_path_factory, request):
    from conftest import SHARED_DATA

    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder {SHARED_DATA} is absent (set FACEGEO_SHARED_DATA)")
    root = tmp_path_factory.mktemp("datasets")
    out = {}
    for kind, rel in SOURCES.items():
        src = SHARED_DATA / rel
        if src.is_dir():
            out[kind] = import_dataset(kind, src, root / kind)
    return out


@pytest.mark.parametrize("kind", sorted(SOURCES))
def test_each_dataset_converts_and_validates_fully(converted, kind):
    if kind not in converted:
        pytest.skip(f"{SOURCES[kind]} is absent from the shared data")
    scan = load_scan(converted[kind].root, check="full")
    assert scan.version == 2 and not scan.synthetic
    text = summarize(scan)
    assert scan.name in text
    # what the data set does not publish is marked as nominal
    assert scan.manifest["scan"]["metadata"]["nominal"]
    # frames are the source's files, byte for byte (hard links or copies)
    from conftest import SHARED_DATA

    src = SHARED_DATA / SOURCES[kind]
    carried = [p for g in scan.groups for c in scan.camera_names
               for _, p in scan.expected_files(g, c)]
    assert carried
    source_bytes = {q.read_bytes() for q in src.iterdir() if q.is_file()}
    assert all(p.read_bytes() in source_bytes for p in carried[:5])


def test_opencv_stereo_keeps_the_published_intrinsics(converted):
    scan = converted.get("opencv-stereo") or pytest.skip("no OpenCV stereo data")
    assert scan.calib_views("left") == list(range(13)) == scan.calib_views("right")
    ref = json.loads(scan.reference_path("intrinsics").read_text())
    # left: OpenCV's single-camera calibration of these images; stereo_calib's kept apart
    K = np.array(ref["cameras"]["left"]["K"])
    assert K.shape == (3, 3) and K[0, 2] == pytest.approx(342.283, abs=1e-3)
    assert np.array(ref["stereo_calib"]["left"]["K"])[0, 0] == pytest.approx(534.803, abs=1e-3)
    assert np.array(ref["left_single_camera"]["K"])[0, 2] == pytest.approx(342.283, abs=1e-3)


def test_yale_light_directions_agree_with_the_frames(converted):
    """A flash on world −x lights the image's left half (the camera looks down −z from +z)."""
    scan = converted.get("yale-b") or pytest.skip("no Yale B data")
    lights = scan.rig.lights
    assert lights.n_lights == 64
    assert lights.solid_angles.sum() == pytest.approx(4 * np.pi, rel=1e-9)
    checked = 0
    for l, name in enumerate(scan.light_names):
        d = lights.directions[l]
        if abs(d[0]) < 0.6:
            continue
        img = scan.olat_frame("cam", l, subtract_ambient=True)[..., 0]
        w = img.shape[1]
        left, right = img[:, : w // 2].mean(), img[:, w // 2:].mean()
        assert np.sign(right - left) == np.sign(d[0]), name
        checked += 1
    assert checked >= 8
    np.testing.assert_allclose(yale_light_direction(0, 90), [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(yale_light_direction(90, 0), [-1, 0, 0], atol=1e-12)


def test_yale_ambient_is_subtracted(converted):
    """Metric: max |difference| against max(raw − ambient, 0), linear units (exact: one float32
    subtraction)."""
    scan = converted.get("yale-b") or pytest.skip("no Yale B data")
    raw = scan.olat_frame("cam", 0)
    amb = scan.ambient_frame("cam")
    np.testing.assert_allclose(scan.olat_frame("cam", 0, subtract_ambient=True),
                               np.maximum(raw - amb, 0), atol=1e-7)
    assert amb.mean() > 0


# ------------------------------------------------------- Yale subjects as shipped (issue 36)
def _fake_yale_subject(shared_data, folder, ambient=None):
    """yale_b01's 64 flashes copied into ``folder``, with ``ambient`` (uint8 array) written as
    its ``_Ambient.pgm`` instead of the real one (None: the real one)."""
    import cv2

    src = shared_file(shared_data, "olat/yale_b01")
    folder.mkdir()
    for q in src.iterdir():
        shutil.copyfile(q, folder / q.name)
    if ambient is not None:
        assert cv2.imwrite(str(folder / "yaleB01_P00_Ambient.pgm"), ambient)
    return folder


def test_yale_uncropped_ambient_is_dropped_with_a_warning_naming_the_source(
        tmp_path, shared_data, caplog):
    """Most Extended Yale B subjects ship a 640 x 480 (uncropped) ambient frame beside 168 x 192
    flashes; the crop is not published, so the scan goes without an ambient frame."""
    import logging

    rng = np.random.default_rng(1)
    src = _fake_yale_subject(shared_data, tmp_path / "yaleB11",
                             rng.integers(0, 30, (480, 640), dtype=np.uint8))
    with caplog.at_level(logging.WARNING, logger="facegeo.capture.datasets"):
        scan = import_dataset("yale-b", src, tmp_path / "scan")
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and str(src / "yaleB01_P00_Ambient.pgm") in warned[0]
    assert "640 x 480" in warned[0] and "facegeo-tmp" not in warned[0]
    assert "ambient" not in scan.manifest["olat"] and scan.ambient_path("cam") is None
    assert scan.manifest["scan"]["metadata"]["ambient"]["size"] == [640, 480]
    assert "dropped" in scan.manifest["scan"]["description"]
    assert scan.rig.lights.n_lights == 64
    load_scan(scan.root, check="full")
    from facegeo.errors import ScanFormatError

    with pytest.raises(ScanFormatError, match="no ambient frame"):
        scan.olat_frame("cam", 0, subtract_ambient=True)


def test_dataset_errors_name_the_source_file_not_the_staging_folder(tmp_path, shared_data):
    """A flash of the wrong size fails validation in the staging folder; the message names the
    data set's file (and where it would have gone in the scan), never the staging path."""
    import cv2

    from facegeo.errors import ScanFormatError

    src = _fake_yale_subject(shared_data, tmp_path / "yaleB02")
    bad = src / "yaleB01_P00A+035E+15.pgm"
    assert cv2.imwrite(str(bad), np.zeros((480, 640), np.uint8))
    with pytest.raises(ScanFormatError) as info:
        import_dataset("yale-b", src, tmp_path / "scan")
    text = str(info.value)
    assert text.startswith(f"{bad} [olat.files]: image is 640×480 px"), text
    assert "(in the scan: olat/cam/A+035E+15.pgm)" in text
    assert "facegeo-tmp" not in text and info.value.path == bad
    assert info.value.key == "olat.files"
    assert not (tmp_path / "scan").exists()
    assert not [p for p in tmp_path.iterdir() if "facegeo-tmp" in p.name]


# ------------------------------------------------------- ambient subtraction clipped at 0
def test_subtract_ambient_clips_at_zero_and_counts_the_clipped_pixels(tmp_path, shared_data):
    """An ambient frame brighter than the flashes in places (the user's subject: differences
    down to -0.16): the subtraction returns max(frame - ambient, 0), which the skin fit accepts;
    the clipped pixels come back as a mask and a per-frame count. Metric: exact equality
    (one float32 subtraction, then 0)."""
    import cv2

    from facegeo.appearance._skin_fit import check_reflectance
    from facegeo.appearance.skin import LightSet

    rng = np.random.default_rng(2)
    ambient = rng.integers(0, 60, (192, 168), dtype=np.uint8)  # up to 0.23 in linear units
    src = _fake_yale_subject(shared_data, tmp_path / "yaleB13", ambient)
    scan = import_dataset("yale-b", src, tmp_path / "scan")
    amb = ambient.astype(np.float32) / 255
    raw = scan.olat_frame("cam", "A+000E+00")
    diff = raw - amb[..., None]
    assert diff.min() < -0.15  # the condition the user met

    out, valid, clipped = scan.olat_frame("cam", "A+000E+00", subtract_ambient=True,
                                          return_mask=True, return_clipped=True)
    assert out.dtype == np.float32 and out.min() == 0.0
    np.testing.assert_array_equal(out, np.maximum(diff, 0))
    np.testing.assert_array_equal(clipped, (diff < 0).any(axis=-1))
    # a clipped sample is a measured dark value, not an untrusted one: the mask is unchanged
    np.testing.assert_array_equal(valid, scan.olat_frame("cam", "A+000E+00", return_mask=True)[1])
    light = scan.light_names.index("A+000E+00")
    assert scan.ambient_clipped("cam") == {("cam", light): int(clipped.sum())}
    # the compatible call: a bare frame
    assert isinstance(scan.olat_frame("cam", 0, subtract_ambient=True), np.ndarray)
    assert scan.olat_frame("cam", 0, return_clipped=True)[1].sum() == 0  # no subtraction

    # every frame through iter_olat: non-negative, counted, accepted by the fit
    frames, total = [], 0
    for _, f, c in scan.iter_olat("cam", subtract_ambient=True, return_clipped=True):
        assert f.min() >= 0.0
        frames.append(f[::16, ::16].reshape(-1, 3))
        total += int(c.sum())
    counts = scan.ambient_clipped("cam")
    assert len(counts) == 64 and sum(counts.values()) == total > 0
    R = np.stack(frames, axis=1)  # (N, 64, 3)
    lights = LightSet.from_directions(scan.rig.lights.directions)
    check_reflectance(R, lights, None)  # raised "R: reflectance must be >= 0" before


def test_subtract_ambient_frame_keeps_nan_and_marks_channels():
    from facegeo.capture._scan_readers import subtract_ambient_frame

    f = np.array([[[0.5, 0.2, np.nan], [0.1, 0.1, 0.1]]], np.float32)  # (1, 2, 3)
    a = np.array([[[0.4, 0.3, 0.0], [0.0, 0.0, 0.0]]], np.float32)
    d, clipped = subtract_ambient_frame(f, a)
    assert np.isnan(d[0, 0, 2]) and d[0, 0, 1] == 0.0
    assert d[0, 0, 0] == np.float32(0.5) - np.float32(0.4)
    np.testing.assert_array_equal(clipped, [[True, False]])


def test_graycode_mannequin_bits_are_interleaved_rows_first(converted):
    """Frame 1 is the row MSB (horizontal bands), frame 2 the column MSB (vertical bands)."""
    scan = converted.get("graycode-mannequin") or pytest.skip("no mannequin data")
    assert scan.sl_frames[:4] == ["gray_y_00", "gray_x_00", "gray_y_01", "gray_x_01"]
    for name, axis in (("gray_y_00", 1), ("gray_x_00", 0), ("gray_y_01", 1), ("gray_x_01", 0)):
        b = scan.sl_frame("cam", name, luminance=True) > 0.15
        along_cols, along_rows = b.mean(0).std(), b.mean(1).std()
        assert (along_rows > along_cols) == (axis == 1), name


def test_three_phase_is_a_phase_only_spec(converted):
    scan = converted.get("three-phase") or pytest.skip("no phase data")
    spec = scan.pattern_spec("structured_light")
    assert spec.phase_steps == 3 and not spec.gray
    assert scan.sl_frames == ["phase_y_0", "phase_y_1", "phase_y_2"]


def test_three_phase_declares_the_axis_its_fringes_vary_along(converted):
    """The imported scan's frames, decoded on the axis the scan declares: the wrapped phase
    must advance along that image axis. Metric: median |wrapped step| between neighbouring
    face pixels (intensity > 0.01, below the bright band of the top 20 rows), radians per pixel
    (measured 0.10 down the rows, 0.03 across the columns: the fringes are horizontal bands)."""
    from facegeo.geometry.structured_light import decode_phase

    scan = converted.get("three-phase") or pytest.skip("no phase data")
    spec = scan.pattern_spec("structured_light")
    (axis,) = spec.phase_axes
    frames = {n: scan.sl_frame("cam", n) for n in scan.sl_frames}
    wrapped, _ = decode_phase(frames, spec, axis)
    face = np.mean([f.mean(axis=-1) if f.ndim == 3 else f for f in frames.values()], axis=0) > 0.01
    face[:20] = False

    def median_step(img_axis):
        d = np.angle(np.exp(1j * np.diff(wrapped, axis=img_axis)))
        both = np.diff(face.astype(np.int8), axis=img_axis) == 0
        both &= np.take(face, range(face.shape[img_axis] - 1), axis=img_axis)
        return float(np.median(np.abs(d[both & np.isfinite(d)])))

    along_rows, along_cols = median_step(0), median_step(1)
    # projector axis "y" (rows) must vary down the image, "x" (columns) across it
    declared, other = (along_rows, along_cols) if axis == "y" else (along_cols, along_rows)
    assert declared > 2.0 * other, (axis, along_rows, along_cols)


def test_bad_input_is_refused_and_leaves_nothing(tmp_path, shared_data):
    src = shared_file(shared_data, "structured_light/graycode_mannequin")
    with pytest.raises(InputError, match="dataset"):
        import_dataset("nonsense", src, tmp_path / "x")
    partial = tmp_path / "partial"
    shutil.copytree(src, partial)
    (partial / "7.jpg").unlink()
    with pytest.raises(InputError, match="missing 7.jpg"):
        import_dataset("graycode-mannequin", partial, tmp_path / "scan")
    assert not (tmp_path / "scan").exists()
    assert not [p for p in tmp_path.iterdir() if "facegeo-tmp" in p.name]
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "mine.txt").write_text("keep")
    with pytest.raises(InputError, match="never overwrites"):
        import_dataset("graycode-mannequin", src, busy)
    assert (busy / "mine.txt").read_text() == "keep"
    # never into the source folder (it wrote a scan into the shared data set)
    before = sorted(p.name for p in partial.iterdir())
    with pytest.raises(InputError, match="inside the source folder"):
        import_dataset("graycode-mannequin", partial, partial / "scan")
    assert sorted(p.name for p in partial.iterdir()) == before
    with pytest.raises(InputError, match="not the expected data set"):
        import_dataset("three-phase", src, tmp_path / "other")


def test_registry_lists_every_converter():
    # 3dunderworld and diligent have their own modules, tests/test_dataset_3dunderworld.py
    # (subfolders per camera, a scale option, a reference cloud) and test_dataset_diligent.py
    assert set(DATASETS) == set(SOURCES) | {"3dunderworld", "diligent"}


def test_cli_import_dataset_and_description(tmp_path, shared_data, capsys):
    from facegeo.cli import main

    src = shared_file(shared_data, "structured_light/face_threephase")
    assert main(["import", str(src), str(tmp_path / "a"), "--dataset", "three-phase",
                 "--copy"]) == 0
    assert "imported into" in capsys.readouterr().out
    assert (tmp_path / "a" / "scan.toml").is_file()
    # importing a scan's own folder by its manifest: the description route
    assert main(["import", str(tmp_path / "a"), str(tmp_path / "b"), "--description",
                 str(tmp_path / "a" / "scan.toml")]) == 0
    # exactly one of --dataset / --description
    assert main(["import", str(src), str(tmp_path / "c")]) == 2
    assert "exactly one" in capsys.readouterr().err


def test_reference_intrinsics_in_all_three_forms(tmp_path):
    from pathlib import Path

    from facegeo.capture.references import read_reference_intrinsics
    from facegeo.errors import ScanFormatError

    fixtures = Path(__file__).parent / "fixtures" / "scans"
    a = read_reference_intrinsics(fixtures / "light_stage_v2" / "reference" / "intrinsics.json")
    assert a["cam_a"][0, 0] == 9.0 and a["cam_b"][1, 2] == 2.6
    b = read_reference_intrinsics(fixtures / "calibration_corners" / "reference" / "intrinsics.json")
    assert b["cam_b"][0, 0] == 598.1
    p = tmp_path / "bad.json"
    p.write_text(json.dumps({"cameras": {"x": {"K": [[0, 0, 1], [0, 1, 1], [0, 0, 1]]}}}))
    with pytest.raises(ScanFormatError, match="bad.json.*fx, fy > 0"):
        read_reference_intrinsics(p)


def test_calibrating_the_opencv_scan_reports_errors_against_the_published_intrinsics(converted):
    """The same metrics code compares with a real scan's [reference] as with ground truth."""
    scan = converted.get("opencv-stereo") or pytest.skip("no OpenCV stereo data")
    from facegeo.pipeline.calibrate import calibrate_products

    dest = scan.root / "out" / "calib_test"
    dest.mkdir(parents=True)
    metrics, _ = calibrate_products(scan, dest, cross_validation=False)
    from facegeo.evaluate.intrinsics import with_calibration_errors

    metrics = with_calibration_errors(scan, metrics, dest)  # the stage reads no [reference]
    for cam in ("left", "right"):
        m = metrics["cameras"][cam]
        assert m["reprojection_rms_px"] < 0.5
        # OpenCV's stereo_calib solved both cameras jointly with other flags: agreement within
        # 1 % in focal length and 15 px in principal point is what the two models allow
        assert m["reference_focal_rel_error"] < 0.01
        assert m["reference_principal_point_error_px"] < 15.0
    assert "focal_rel_error" not in metrics["cameras"]["left"]  # no ground truth in a real scan
