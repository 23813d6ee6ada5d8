"""Board-capture file templates (issue 35): named per-view fields the description declares
(``{pose}``), ``{index}`` / ``{number}`` of the projector frames, ``{view:04d}`` — and a
``response`` of the projector's board Gray-code frames apart from the board photos'."""

from __future__ import annotations

import numpy as np
import pytest

from facegeo.capture.imageio import srgb_to_linear, write_image
from facegeo.capture.scan import load_scan, new_manifest, write_manifest
from facegeo.errors import ScanFormatError

#: float32 round-off of a linearised 8-bit sample (relative)
FLOAT32_TOL = 1e-6

FRAMES = ["white", "black", "gray_x_00", "gray_x_00_inv"]
POSES = [40, 7, 12]  # the capture's own pose numbers, not 0..2


def _rig(root):
    from facegeo.frames import look_at
    from facegeo.geometry.camera import Camera
    from facegeo.geometry.rig import Projector, Rig

    K = np.array([[30.0, 0, 11.7], [0, 30.4, 8.2], [0, 0, 1]])
    cam = Camera("cam", 24, 16, K, None, look_at([0.0, 0.0, 1.0], [0, 0, 0]))
    Rig([cam], Projector("proj", 16, 8), None).save(root / "rig.json")
    (root / "calib").mkdir(exist_ok=True)
    (root / "calib" / "board.json").write_text(
        '{"kind": "circles", "cols": 4, "rows": 5, "spacing": 0.02, "asymmetric": true}')


def _scan(root, *, calib_files, proj_files, fields=None, proj_fields=None, proj_response=None):
    """A one-camera scan whose board photos and projector captures follow the templates given
    (files written where the templates put them); returns the manifest written."""
    _rig(root)
    rng = np.random.default_rng(5)
    m = new_manifest("templates", synthetic=False)
    m["calib"] = {"views": len(POSES), "files": calib_files,
                  "projector": {"views": len(POSES), "files": proj_files, "frames": FRAMES,
                                "patterns": {"n_bits_x": 1, "n_bits_y": 0}}}
    if fields is not None:
        m["calib"]["fields"] = fields
    if proj_fields is not None:
        m["calib"]["projector"]["fields"] = proj_fields
    if proj_response is not None:
        m["calib"]["projector"]["response"] = proj_response
    images = {}
    for v, pose in enumerate(POSES):
        f = calib_files.format(camera="cam", view=v, pose=pose, index=v, number=v + 1)
        img = rng.integers(0, 256, (16, 24, 3), dtype=np.uint8)
        write_image(root / f, img)
        images[("calib", v)] = img
        for i, fr in enumerate(FRAMES):
            f = proj_files.format(camera="cam", view=v, pose=pose, index=i, number=i + 1,
                                  frame=fr)
            img = rng.integers(0, 256, (16, 24, 3), dtype=np.uint8)
            write_image(root / f, img)
            images[(v, fr)] = img
    write_manifest(root, m)
    return images


def test_declared_pose_field_and_frame_index_fill_the_templates(tmp_path):
    """``capture_{pose}/graycode_{index:02d}.png`` (the projector captures of pose 40, 7, 12,
    frames numbered by their position) and ``calib/{camera}/{pose}.png``: every view finds
    its own files, in view order."""
    images = _scan(tmp_path, calib_files="calib/{camera}/board_{pose}.png",
                   proj_files="capture_{pose}/graycode_{index:02d}.png",
                   fields={"pose": POSES}, proj_fields={"pose": POSES})
    scan = load_scan(tmp_path, check="full")
    paths = scan.calib_view_paths("cam")
    assert [p.name for p in paths] == [f"board_{p}.png" for p in POSES]
    pv = scan.projector_view_paths("cam", 1)
    assert [p.relative_to(tmp_path).as_posix() for p in pv.values()] == [
        f"capture_7/graycode_{i:02d}.png" for i in range(len(FRAMES))]
    got = scan.projector_frame("cam", 2, "gray_x_00")
    lin = srgb_to_linear(images[(2, "gray_x_00")].astype(np.float32) / 255)
    assert np.abs(got - lin).max() < FLOAT32_TOL


def test_view_and_frame_numbers_with_widths(tmp_path):
    """``calib_sl/{camera}/{view:04d}/{index:04d}.png``: no declared field needed."""
    _scan(tmp_path, calib_files="calib/{camera}/{number:03d}.png",
          proj_files="calib_sl/{camera}/{view:04d}/{index:04d}.png")
    scan = load_scan(tmp_path, check="full")
    assert scan.projector_view_paths("cam", 2)["gray_x_00"].relative_to(tmp_path).as_posix() \
        == "calib_sl/cam/0002/0002.png"
    assert scan.calib_view_paths("cam")[0].name == "001.png"


def test_projector_frames_have_their_own_response(tmp_path):
    """Board photos in sRGB, the projector's board Gray-code frames declared linear: each group
    is linearised by its own response (one response for both mislabelled one of them)."""
    images = _scan(tmp_path, calib_files="calib/{camera}/view_{view:03d}.png",
                   proj_files="calib/projector/{camera}/view_{view:02d}_{frame}.png",
                   proj_response="linear")
    scan = load_scan(tmp_path, check="full")
    assert scan.response("calib").kind != scan.response("calib.projector").kind
    got = scan.projector_frame("cam", 0, "white")
    assert np.abs(got - images[(0, "white")].astype(np.float32) / 255).max() < FLOAT32_TOL


@pytest.mark.parametrize("fields, match", [
    ({"pose": [40, 7]}, r"2 values for 3 views"),
    ({"pose": [40, 7, 7]}, r"views 1 and 2 fill .* with the same fields"),
    ({"view": [1, 2, 3]}, r"field name 'view': expected an identifier other than"),
    ({"pose": [1.5, 2, 3]}, r"expected an integer or a string"),
])
def test_bad_declared_fields_name_the_key(tmp_path, fields, match):
    _rig(tmp_path)
    m = new_manifest("bad", synthetic=False)
    m["calib"] = {"views": 3, "files": "calib/{camera}/board_{pose}.png", "fields": fields}
    with pytest.raises(ScanFormatError, match=match) as e:  # the writer validates too
        write_manifest(tmp_path, m)
    assert "[calib.fields" in str(e.value)


def test_undeclared_field_lists_the_valid_ones(tmp_path):
    _rig(tmp_path)
    m = new_manifest("bad", synthetic=False)
    m["calib"] = {"views": 3, "files": "calib/{camera}/board_{pose}.png"}
    with pytest.raises(ScanFormatError, match=r"uses field \{pose\}; valid fields here"):
        write_manifest(tmp_path, m)
