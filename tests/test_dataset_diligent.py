"""DiLiGenT objects converted into scans (``facegeo import --dataset diligent``): lights with
their RGB intensities, frames carried byte for byte, the mask, and the ground-truth normals in
the camera frame with the signs checked on the object itself."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from conftest import shared_file
from facegeo.capture.datasets import DATASETS, DILIGENT_FOCAL_PX, import_dataset
from facegeo.capture.imageio import read_image
from facegeo.capture.scan import load_scan
from facegeo.errors import InputError, ScanFormatError

OBJECTS = ("ballPNG", "catPNG")
#: Angle within which the ball's normal at the mask's centre faces the camera, degrees (the
#: mask's centroid lies within a pixel or two of the sphere's centre: measured 1.0 deg).
CENTRE_FACING_DEG = 3.0


@pytest.fixture(scope="module")
def scans(tmp_path_factory, shared_data):
    root = tmp_path_factory.mktemp("diligent")
    out = {}
    for obj in OBJECTS:
        src = shared_data / "olat" / "diligent" / obj
        if src.is_dir():
            out[obj] = import_dataset("diligent", src, root / obj)
    return out


def _scan(scans, obj):
    return scans.get(obj) or pytest.skip(f"olat/diligent/{obj} is absent from the shared data")


def _mask(scan):
    return (read_image(scan.reference_path("mask")) > 0).any(axis=-1)


def test_registered():
    assert "diligent" in DATASETS


@pytest.mark.parametrize("obj", OBJECTS)
def test_converts_validates_and_carries_the_calibration(scans, shared_data, obj):
    scan = _scan(scans, obj)
    src = shared_data / "olat" / "diligent" / obj
    load_scan(scan.root, check="full")
    assert scan.name == f"diligent_{obj[:-3]}" and not scan.synthetic
    lights = scan.rig.lights
    assert lights.n_lights == 96 and scan.light_names[:2] == ["001", "002"]
    # directions as published (normalised), world frame = DiLiGenT's axes; max deviation
    d = np.loadtxt(src / "light_directions.txt")
    assert np.abs(lights.directions - d / np.linalg.norm(d, axis=1, keepdims=True)).max() < 1e-12
    # per-light RGB intensities exactly as published
    np.testing.assert_array_equal(lights.intensities, np.loadtxt(src / "light_intensities.txt"))
    # Voronoi cells clipped at the plane facing the camera: they sum to a hemisphere
    assert lights.solid_angles.sum() == pytest.approx(2 * np.pi, rel=1e-9)
    # frames are the source files byte for byte; linear response
    for k in (0, 47, 95):
        assert scan.olat_path("cam", k).read_bytes() == (src / f"{k + 1:03d}.png").read_bytes()
    assert scan.manifest["olat"]["response"] == "linear"
    cam = scan.rig.camera("cam")
    assert cam.K[0, 0] == pytest.approx(DILIGENT_FOCAL_PX) and DILIGENT_FOCAL_PX == \
        pytest.approx(3623.19, abs=0.01)
    assert "cameras" in scan.manifest["scan"]["metadata"]["nominal"]
    mask = _mask(scan)
    assert mask.shape == (cam.height, cam.width) and mask.any()


@pytest.mark.parametrize("obj", OBJECTS)
def test_reference_normals_are_unit_inside_the_mask_and_nan_outside(scans, obj):
    scan = _scan(scans, obj)
    n = np.load(scan.reference_path("normals"))
    mask = _mask(scan)
    assert n.dtype == np.float64 and n.shape == mask.shape + (3,)
    assert np.isnan(n[~mask]).all()
    assert np.abs(np.linalg.norm(n[mask], axis=-1) - 1).max() < 1e-6


def test_ball_normals_in_the_camera_frame(scans):
    """x right, y down, z forward: at the mask's centre the ball faces the camera (−z); at its
    right edge it points to +x, at its top edge to −y (up in the image), at its bottom to +y.
    A sign left in DiLiGenT's convention (y up, z toward the camera) fails each of these."""
    scan = _scan(scans, "ballPNG")
    n = np.load(scan.reference_path("normals"))
    mask = _mask(scan)
    ys, xs = np.nonzero(mask)
    cy, cx = int(round(ys.mean())), int(round(xs.mean()))
    facing = np.degrees(np.arccos(-n[cy, cx, 2]))
    assert facing < CENTRE_FACING_DEG
    row = np.flatnonzero(mask[cy])
    col = np.flatnonzero(mask[:, cx])
    right, left = n[cy, row.max() - 1], n[cy, row.min() + 1]
    top, bottom = n[col.min() + 1, cx], n[col.max() - 1, cx]
    assert right[0] > 0.9 and left[0] < -0.9
    assert top[1] < -0.9 and bottom[1] > 0.9
    # every visible normal faces the camera (z < 0 in the camera frame)
    assert (n[mask][:, 2] < 0.05).all()


def test_light_directions_agree_with_the_frames(scans):
    """World +x (DiLiGenT's x right) lights the ball's right half, world +y its top half.
    Metric: mean brightness of the object's halves for the four most oblique lights."""
    scan = _scan(scans, "ballPNG")
    d = scan.rig.lights.directions
    mask = _mask(scan)
    h, w = mask.shape
    for k, axis in ((int(np.argmax(d[:, 0])), 1), (int(np.argmin(d[:, 0])), 1),
                    (int(np.argmax(d[:, 1])), 0), (int(np.argmin(d[:, 1])), 0)):
        g = scan.olat_frame("cam", k).mean(axis=-1)
        if axis == 1:  # right half minus left half, sign of the light's x
            diff = g[:, w // 2:][mask[:, w // 2:]].mean() - g[:, :w // 2][mask[:, :w // 2]].mean()
            assert np.sign(diff) == np.sign(d[k, 0]), k
        else:  # top half minus bottom half, sign of the light's y
            diff = g[:h // 2][mask[:h // 2]].mean() - g[h // 2:][mask[h // 2:]].mean()
            assert np.sign(diff) == np.sign(d[k, 1]), k


@pytest.mark.parametrize("obj", OBJECTS)
def test_frames_follow_the_reference_normals_and_the_lights(scans, obj):
    """The frames divided by the light intensities correlate with max(0, n·l) computed from the
    reference normals brought back to the world frame (n_world = R_cam_worldᵀ n_cam) and the
    rig's lights: the two conventions agree. Metric: median over lights of the Pearson
    correlation over the object's pixels (measured 0.88 ball, 0.70 cat: specular highlights
    and the cat's varying albedo); with the normals' x or y negated (a sign error) it drops to
    0.60 / 0.29 (ball), 0.46 / 0.26 (cat)."""
    scan = _scan(scans, obj)
    lights = scan.rig.lights
    mask = _mask(scan)
    R_cam_world = scan.rig.camera("cam").T_cam_world.R
    n_world = np.load(scan.reference_path("normals"))[mask] @ R_cam_world
    ks = range(0, 96, 5)
    frames = [(scan.olat_frame("cam", k) / lights.intensities[k]).mean(axis=-1)[mask] for k in ks]

    def median_corr(n):
        return float(np.median([np.corrcoef(f, np.maximum(0, n @ lights.directions[k]))[0, 1]
                                for f, k in zip(frames, ks)]))

    right = median_corr(n_world)
    assert right > 0.65, right
    for flip in ((-1, 1, 1), (1, -1, 1)):
        assert median_corr(n_world * flip) < right - 0.2, flip


def _copy(shared_data, tmp_path, obj="ballPNG"):
    src = shared_file(shared_data, f"olat/diligent/{obj}")
    dst = tmp_path / obj
    shutil.copytree(src, dst)
    for q in dst.iterdir():
        q.chmod(0o644)
    dst.chmod(0o755)
    return dst


def test_bad_folders_are_refused_naming_the_file(tmp_path, shared_data):
    src = _copy(shared_data, tmp_path)
    (src / "mask.png").unlink()
    with pytest.raises(InputError, match="missing mask.png"):
        import_dataset("diligent", src, tmp_path / "a")

    src = _copy(shared_data, tmp_path / "b")
    lines = (src / "light_intensities.txt").read_text().splitlines()
    (src / "light_intensities.txt").write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(InputError, match=r"light_intensities.txt: 95 intensities, but "
                                         r"filenames.txt names 96 frames"):
        import_dataset("diligent", src, tmp_path / "b" / "scan")

    src = _copy(shared_data, tmp_path / "c")
    (src / "light_directions.txt").write_text("0 0 1\n0 0 x\n")
    with pytest.raises(InputError, match=r"light_directions.txt, line 2: expected 3 numbers"):
        import_dataset("diligent", src, tmp_path / "c" / "scan")
    assert not [p for p in tmp_path.rglob("*") if "facegeo-tmp" in p.name]


def test_a_frame_of_another_size_is_named_by_its_source_file(tmp_path, shared_data):
    import cv2

    src = _copy(shared_data, tmp_path)
    bad = src / "050.png"
    assert cv2.imwrite(str(bad), np.zeros((10, 12, 3), np.uint8))
    with pytest.raises(ScanFormatError) as info:
        import_dataset("diligent", src, tmp_path / "scan")
    text = str(info.value)
    assert text.startswith(f"{bad} [olat.files]: image is 12×10 px"), text
    assert "(in the scan: olat/cam/050.png)" in text and "facegeo-tmp" not in text


def test_without_ground_truth_there_is_no_normals_reference(tmp_path, shared_data):
    src = _copy(shared_data, tmp_path)
    (src / "Normal_gt.mat").unlink()
    scan = import_dataset("diligent", src, tmp_path / "scan")
    assert scan.reference_keys == ["mask"]
