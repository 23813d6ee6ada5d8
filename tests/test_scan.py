"""The scan directory format (facegeo.capture.scan): write → load round trips and every way it can be wrong."""

from __future__ import annotations

import copy
import os
from pathlib import Path

import numpy as np
import pytest

from facegeo.errors import InputError, ScanFormatError
from facegeo.capture.imageio import encode, linearize, read_image, write_image
from facegeo.capture.scan import (
    DEFAULT_FILES,
    Scan,
    frame_path,
    load_scan,
    new_manifest,
    summarize,
    validate_manifest,
    write_manifest,
)

rig_mod = pytest.importorskip("facegeo.geometry.rig", reason="facegeo.geometry.rig (Rig API) is not available yet")
board_mod = pytest.importorskip("facegeo.geometry.board", reason="facegeo.geometry.board is not available yet")

# Tiny, asymmetric sizes: a transposed width/height fails.
W, H = 24, 16
N_THETA, N_PHI = 2, 2  # 4 lights
SL_FRAMES = ["white", "black", "gray_x_00"]
CALIB_VIEWS = 2
PROJ_VIEWS = 1
FLOAT32_EPS = float(np.finfo(np.float32).eps)


def _make_rig():
    from facegeo.geometry.camera import Camera
    from facegeo.frames import look_at

    K0 = np.array([[30.0, 0, 11.7], [0, 30.4, 8.2], [0, 0, 1]])
    K1 = np.array([[31.0, 0, 12.3], [0, 30.7, 7.6], [0, 0, 1]])
    cams = [
        Camera("cam_a", W, H, K0, None, look_at([-0.3, 0.05, 1.0], [0, 0, 0])),
        Camera("cam_b", W, H, K1, None, look_at([0.3, -0.02, 1.1], [0, 0, 0])),
    ]
    proj = Camera("proj", 40, 30, np.array([[50.0, 0, 20.0], [0, 50.0, 15.0], [0, 0, 1]]),
                  None, look_at([0.0, 0.1, 1.0], [0, 0, 0]))
    return rig_mod.Rig(cams, proj, rig_mod.LightStage(n_theta=N_THETA, n_phi=N_PHI))


def _linear_image(seed, shape=(H, W, 3)):
    return np.random.default_rng(seed).random(shape).astype(np.float32)


def build_scan(root: Path, *, light_order="theta-fastest", olat_png=False, write=True) -> dict:
    """Write a complete tiny scan (frames first, manifest last) and return its manifest."""
    rig = _make_rig()
    rig.save(root / "rig.json")
    board_mod.CharucoBoard().save(root / "calib" / "board.json")
    cams = [c.name for c in rig.cameras]
    m = new_manifest("tiny", synthetic=True, description="test scan")
    m["calib"] = {"views": CALIB_VIEWS, "response": "srgb",
                  "projector": {"views": PROJ_VIEWS}}
    m["structured_light"] = {"projector": "proj", "frames": list(SL_FRAMES),
                             "patterns": {"n_bits_x": 1, "n_bits_y": 0, "inverse": False}}
    olat_files = "olat/{camera}/{light:04d}.png" if olat_png else DEFAULT_FILES["olat"]
    m["olat"] = {"n_lights": N_THETA * N_PHI, "light_order": light_order, "files": olat_files}
    if olat_png:
        m["olat"]["response"] = {"kind": "gamma", "gamma": 2.2}
    m["ground_truth"] = {"mesh": "ground_truth/mesh.ply", "maps": {"albedo": "ground_truth/albedo.exr"}}
    for ci, cam in enumerate(cams):
        for v in range(CALIB_VIEWS):
            img = encode(_linear_image(100 + 10 * ci + v), "srgb", np.uint8)
            write_image(frame_path(root, DEFAULT_FILES["calib"], camera=cam, view=v), img)
        for v in range(PROJ_VIEWS):
            for fi, f in enumerate(SL_FRAMES):
                img = encode(_linear_image(200 + 10 * ci + fi, (H, W)), "srgb", np.uint8)
                write_image(frame_path(root, DEFAULT_FILES["calib.projector"], camera=cam,
                                       view=v, frame=f), img)
        for fi, f in enumerate(SL_FRAMES):
            img = encode(_linear_image(300 + 10 * ci + fi), "srgb", np.uint16)
            write_image(frame_path(root, DEFAULT_FILES["structured_light"], camera=cam, frame=f), img)
        for k in range(N_THETA * N_PHI):  # k: file number in capture order
            img = _linear_image(400 + 10 * ci + k) * (k + 1)
            if olat_png:
                img = encode(img / (k + 1), {"kind": "gamma", "gamma": 2.2}, np.uint16)
            write_image(frame_path(root, olat_files, camera=cam, light=k), img)
    (root / "ground_truth").mkdir(exist_ok=True)
    (root / "ground_truth" / "mesh.ply").write_text("ply\n")
    write_image(root / "ground_truth" / "albedo.exr", _linear_image(1))
    if write:
        write_manifest(root, m)
    return m


@pytest.fixture()
def scan_dir(tmp_path) -> Path:
    root = tmp_path / "scan"
    build_scan(root)
    return root


def _toml(root: Path) -> str:
    return (root / "scan.toml").read_text()


def _rewrite(root: Path, old: str, new: str) -> None:
    text = _toml(root)
    assert old in text, f"{old!r} not in scan.toml:\n{text}"
    (root / "scan.toml").write_text(text.replace(old, new, 1))


# =========================================================================== round trips


def test_write_load_round_trip_identical_arrays(scan_dir):
    scan = load_scan(scan_dir, check="full")
    assert scan.name == "tiny" and scan.synthetic and scan.description == "test scan"
    assert scan.camera_names == ["cam_a", "cam_b"]
    assert scan.groups == ("calib", "calib.projector", "structured_light", "olat")
    # EXR linear OLAT: bit-exact
    for ci, cam in enumerate(scan.camera_names):
        for light, frame in scan.iter_olat(cam):
            want = _linear_image(400 + 10 * ci + light) * (light + 1)
            assert frame.dtype == np.float32 and frame.shape == (H, W, 3)
            assert np.array_equal(frame, want)
    # read ahead on two threads: the same frames, in the same order
    for cam in scan.camera_names:
        seq = list(scan.iter_olat(cam, return_mask=True))
        par = list(scan.iter_olat(cam, return_mask=True, read_ahead=2))
        assert [x[0] for x in par] == [x[0] for x in seq]
        for a, b in zip(seq, par):
            assert np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2])
    # uint16 sRGB structured light: exactly linearize(stored codes); within half an LSB of
    # the sRGB slope of the original linear values (worst case over pixels)
    x = _linear_image(300 + 2)  # cam_a, frame index 2
    codes = encode(x, "srgb", np.uint16)
    got = scan.sl_frame("cam_a", "gray_x_00")
    assert np.array_equal(got, linearize(codes, "srgb"))
    # worst case: half an LSB times the steepest slope of the sRGB decode, 2.4/1.055 at c = 1
    half_lsb_times_slope = 0.5 / 65535 * (2.4 / 1.055)
    assert np.abs(got - x).max() <= half_lsb_times_slope + 2 * FLOAT32_EPS
    assert np.array_equal(read_image(scan.sl_path("cam_a", "gray_x_00")), codes)


def test_scan_accessors(scan_dir):
    scan = load_scan(scan_dir)
    assert scan.sl_frames == SL_FRAMES
    assert scan.sl_patterns == {"n_bits_x": 1, "n_bits_y": 0, "inverse": False,
                                "width": 40, "height": 30}
    assert scan.sl_projector == "proj"
    views = scan.calib_view_paths("cam_b")
    assert [p.relative_to(scan.root).as_posix() for p in views] == [
        "calib/cam_b/view_000.png", "calib/cam_b/view_001.png"]
    pv = scan.projector_view_paths("cam_a", 0)
    assert list(pv) == SL_FRAMES
    assert pv["black"].relative_to(scan.root).as_posix() == "calib/projector/cam_a/view_00_black.png"
    assert scan.olat_path("cam_a", 3).relative_to(scan.root).as_posix() == "olat/cam_a/0003.exr"
    assert scan.ground_truth_keys == ["mesh", "maps.albedo"]
    assert scan.ground_truth_path("maps.albedo") == scan.root / "ground_truth" / "albedo.exr"
    with pytest.raises(ScanFormatError, match=r"\[ground_truth.normals\].*entries: mesh, maps.albedo"):
        scan.ground_truth_path("normals")
    assert scan.rig.lights.n_lights == 4
    assert scan.board.squares_x == 7
    m = scan.manifest
    assert m["olat"]["response"] == "linear" and m["calib"]["board"] == "calib/board.json"
    m["scan"]["name"] = "changed"  # a copy
    assert scan.name == "tiny"
    with pytest.raises(InputError, match="cam_c.*cam_a"):
        scan.olat_path("cam_c", 0)
    with pytest.raises(InputError, match=r"index 4 out of range \[0, 4\)"):
        scan.olat_path("cam_a", 4)
    with pytest.raises(InputError, match="unknown value 'red'"):
        scan.sl_frame("cam_a", "red")


def test_manifest_written_is_normalised_toml(scan_dir):
    import tomllib

    text = _toml(scan_dir)
    assert text.startswith("# facegeo scan manifest")
    m = tomllib.loads(text)
    assert m["scan"]["format"] == "facegeo-scan" and m["scan"]["version"] == 2
    assert m["olat"]["files"] == DEFAULT_FILES["olat"]  # defaults spelled out
    assert m["structured_light"]["response"] == "srgb"
    assert m["calib"]["projector"]["files"] == DEFAULT_FILES["calib.projector"]


def test_phi_fastest_file_order_maps_to_light_index(tmp_path):
    root = tmp_path / "scan"
    build_scan(root, light_order="phi-fastest")
    scan = load_scan(root)
    # light l = j·n_theta + i is file number k = i·n_phi + j
    for light in range(4):
        i, j = light % N_THETA, light // N_THETA
        k = i * N_PHI + j
        assert scan.olat_path("cam_b", light).name == f"{k:04d}.exr"
        assert np.array_equal(scan.olat_frame("cam_b", light), _linear_image(410 + k) * (k + 1))


def test_olat_png_with_gamma_response_and_masks(tmp_path):
    root = tmp_path / "scan"
    build_scan(root, olat_png=True)
    p = root / "olat" / "cam_a" / "0001.png"
    codes = read_image(p)
    codes[0, 0, 1] = 65535  # saturated
    codes[1, 1, 0] = 0  # black-clipped
    write_image(p, codes)
    scan = load_scan(root, check="full")
    frame, valid = scan.olat_frame("cam_a", 1, return_mask=True)
    assert np.array_equal(frame, linearize(codes, {"kind": "gamma", "gamma": 2.2}))
    assert valid.shape == (H, W) and not valid[0, 0] and not valid[1, 1]
    assert valid.sum() == H * W - 2
    light, f2, v2 = next(scan.iter_olat("cam_a", [1], return_mask=True))
    assert light == 1 and np.array_equal(f2, frame) and np.array_equal(v2, valid)


def test_scan_without_olat_is_valid(tmp_path):
    root = tmp_path / "scan"
    m = build_scan(root, write=False)
    del m["olat"]
    write_manifest(root, m)
    scan = load_scan(root, check="full")
    assert "olat" not in scan.groups
    with pytest.raises(ScanFormatError, match=r"\[olat\]: this scan has no \[olat\] section"):
        scan.olat_path("cam_a", 0)


def test_minimal_scan_only_scan_section(tmp_path):
    root = tmp_path / "scan"
    root.mkdir()
    _make_rig().save(root / "rig.json")
    write_manifest(root, new_manifest("empty", synthetic=False))
    scan = load_scan(root, check="full")
    assert scan.groups == () and not scan.synthetic
    assert "frame groups: none" in summarize(scan)


def test_summarize(scan_dir):
    text = summarize(load_scan(scan_dir))
    for needle in ["'tiny' (synthetic, format version 2)", "camera cam_a: 24×16 px",
                   "projector: proj 40×30 px", "4 lights (2 azimuths × 2 inclinations)",
                   "olat: 4 light(s) per camera, 8 files, response linear",
                   "structured_light: 3 frame(s) per camera, 6 files, response srgb",
                   "      cam_b: 3 of 3\n",
                   "calib: 2 view(s)", "maps.albedo = ground_truth/albedo.exr",
                   "size on disk (hard links counted once):"]:
        assert needle in text, (needle, text)


def _snapshot(root: Path) -> dict:
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for n in dirnames + filenames:
            p = Path(dirpath, n)
            st = p.lstat()
            out[p.relative_to(root).as_posix()] = (st.st_mtime_ns, st.st_size)
    return out


def test_load_never_writes_into_the_scan(scan_dir):
    before = _snapshot(scan_dir)
    scan = load_scan(scan_dir, check="full")
    list(scan.iter_olat("cam_a", return_mask=True))
    scan.sl_frame("cam_b", "white")
    scan.board
    summarize(scan)
    assert _snapshot(scan_dir) == before
    assert not (scan_dir / "out").exists()
    assert scan.out_dir.is_dir()  # only out_dir creates out/, on demand


def test_write_manifest_refuses_to_overwrite(scan_dir):
    before = _toml(scan_dir)
    m = load_scan(scan_dir).manifest
    m["scan"]["description"] = "second"
    with pytest.raises(ScanFormatError, match=r"scan.toml: already exists; refusing to overwrite"):
        write_manifest(scan_dir, m)
    assert _toml(scan_dir) == before
    write_manifest(scan_dir, m, overwrite=True)
    assert load_scan(scan_dir).description == "second"


def test_write_manifest_checks_files_before_writing(tmp_path):
    root = tmp_path / "scan"
    m = build_scan(root, write=False)
    (root / "olat" / "cam_b" / "0002.exr").unlink()
    with pytest.raises(ScanFormatError, match="missing olat frame: camera 'cam_b', light 2"):
        write_manifest(root, m)
    assert not (root / "scan.toml").exists()


def test_frame_path_stays_inside(tmp_path):
    assert frame_path(tmp_path, DEFAULT_FILES["olat"], camera="c", light=7) == \
        tmp_path / "olat" / "c" / "0007.exr"
    with pytest.raises(ScanFormatError, match=r"contains '\.\.'"):
        frame_path(tmp_path, DEFAULT_FILES["olat"], camera="../../etc", light=0)
    with pytest.raises(InputError, match="cannot fill template"):
        frame_path(tmp_path, DEFAULT_FILES["olat"], camera="c")


# =========================================================================== errors


def test_missing_directory_and_manifest(tmp_path):
    with pytest.raises(ScanFormatError, match="nowhere: scan directory not found"):
        load_scan(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ScanFormatError, match=r"empty/scan.toml: no scan.toml in this directory"):
        load_scan(tmp_path / "empty")


def test_toml_syntax_error_names_line(scan_dir):
    text = _toml(scan_dir).splitlines()
    text.insert(3, "name = = 'x'")
    (scan_dir / "scan.toml").write_text("\n".join(text))
    with pytest.raises(ScanFormatError, match=r"scan.toml: TOML syntax error: .*line 4"):
        load_scan(scan_dir)


@pytest.mark.parametrize(
    ("old", "new", "pattern"),
    [
        ('format = "facegeo-scan"', 'format = "other"',
         r"\[scan.format\]: format is 'other'; a facegeo scan says format = 'facegeo-scan'"),
        ("version = 2", "version = 3",
         r"\[scan.version\]: unsupported version 3 \(newer .*reads versions 1, 2"),
        ("n_lights = 4", "n_lights = 0", r"\[olat.n_lights\]: expected an integer > 0, got 0"),
        ("n_lights = 4", "n_lights = 5",
         r"\[olat.n_lights\]: n_lights = 5 but the rig's light stage has 4 lights"),
        ("n_lights = 4", 'n_lights = "4"', r"\[olat.n_lights\]: expected an integer > 0, got '4'"),
        ('light_order = "theta-fastest"', 'light_order = "random"',
         r"\[olat.light_order\]: unknown light_order 'random'; expected one of 'theta-fastest', "
         r"'phi-fastest'"),
        ('response = "linear"', 'response = "log"',
         r"\[olat.response\]: unknown response 'log'"),
        ('response = "linear"', 'response = { kind = "gamma", gamma = 0 }',
         r"\[olat.response.gamma\]: .*> 0"),
        ("n_lights = 4", "n_lights = 4\ngain = 2.0",
         r"\[olat.gain\]: unknown key 'gain' in \[olat\]; valid keys: response, n_lights, "
         r"light_order, exposure, files"),
        ("[olat]", "[extra]\na = 1\n\n[olat]",
         r"\[extra\]: unknown section \[extra\]; valid sections: \[scan\], \[calib\]"),
        ("synthetic = true", "synthetic = false",
         r"\[ground_truth\]: \[ground_truth\] is for synthetic scans only"),
        ("synthetic = true", 'synthetic = "yes"', r"\[scan.synthetic\]: expected true or false"),
        ('projector = "proj"', 'projector = "beamer"',
         r"\[structured_light.projector\]: projector = 'beamer' but the rig's projector is 'proj'"),
        ('"black",', '"white",',
         r"\[structured_light.frames\]: frame name 'white' appears twice"),
        ('"black",', '"bl/ack",', r"\[structured_light.frames\]: frame 1 is 'bl/ack'"),
        ('files = "olat/{camera}/{light:04d}.exr"', 'files = "olat/{light:04d}.exr"',
         r"\[olat.files\]: template 'olat/\{light:04d\}.exr' has no \{camera\} but the rig "
         r"has 2 cameras"),
        ('files = "olat/{camera}/{light:04d}.exr"', 'files = "olat/{camera}/x.exr"',
         r"\[olat.files\]: template 'olat/\{camera\}/x.exr' must use every one of "
         r"\{camera\}, \{light\} \(missing \{light\}\)"),
        ('files = "olat/{camera}/{light:04d}.exr"', 'files = "olat/{camera}/{view}.exr"',
         r"\[olat.files\]: template .* uses field \{view\}; valid fields here: \{camera\}, \{light\}"),
        ('files = "olat/{camera}/{light:04d}.exr"', 'files = "olat/{camera}/{light:04d}.raw"',
         r"\[olat.files\]: template .* must end in an image suffix"),
        ("views = 2", "views = -1", r"\[calib.views\]: expected an integer > 0, got -1"),
    ],
)
def test_bad_manifest_values(scan_dir, old, new, pattern):
    _rewrite(scan_dir, old, new)
    with pytest.raises(ScanFormatError, match=pattern) as info:
        load_scan(scan_dir)
    assert "scan.toml" in str(info.value)


def test_missing_required_keys_and_sections():
    m = new_manifest("x", synthetic=False)
    m["olat"] = {"files": DEFAULT_FILES["olat"]}
    with pytest.raises(ScanFormatError, match=r"\[olat.n_lights\]: missing required key 'n_lights'"):
        validate_manifest(m)
    with pytest.raises(ScanFormatError, match=r"\[scan\]: missing section \[scan\]"):
        validate_manifest({"olat": {"n_lights": 4}})
    m = new_manifest("x", synthetic=False)
    m["calib"] = {"views": 1, "projector": {"views": 1}}
    with pytest.raises(ScanFormatError, match=r"\[calib.projector\]: .*no \[structured_light\]"):
        validate_manifest(m)
    m = new_manifest("x", synthetic=False)
    del m["scan"]["version"]
    with pytest.raises(ScanFormatError, match=r"\[scan.version\]: missing required key"):
        validate_manifest(m)


@pytest.mark.parametrize(
    ("old", "new", "pattern"),
    [
        ('rig = "rig.json"', 'rig = "/etc/rig.json"', r"\[scan.rig\]: path '/etc/rig.json' is absolute"),
        ('rig = "rig.json"', 'rig = "../rig.json"', r"\[scan.rig\]: path '../rig.json' contains '\.\.'"),
        ('board = "calib/board.json"', 'board = "calib/../../board.json"',
         r"\[calib.board\]: path .* contains '\.\.'"),
        ('mesh = "ground_truth/mesh.ply"', 'mesh = "/tmp/mesh.ply"',
         r"\[ground_truth.mesh\]: path '/tmp/mesh.ply' is absolute"),
        ('files = "olat/{camera}/{light:04d}.exr"', 'files = "../olat/{camera}/{light:04d}.exr"',
         r"\[olat.files\]: path '../olat/cam/0000.exr' contains '\.\.'"),
    ],
)
def test_paths_may_not_leave_the_scan(scan_dir, old, new, pattern):
    _rewrite(scan_dir, old, new)
    with pytest.raises(ScanFormatError, match=pattern):
        load_scan(scan_dir)


def test_symlink_out_of_the_scan_is_refused(scan_dir, tmp_path):
    outside = tmp_path / "outside.exr"
    target = scan_dir / "olat" / "cam_b" / "0001.exr"
    outside.write_bytes(target.read_bytes())
    target.unlink()
    target.symlink_to(outside)
    with pytest.raises(ScanFormatError, match=r"0001.exr \[olat.files\]: 'olat/cam_b/0001.exr' "
                                              r"resolves to .*outside.exr, outside the scan"):
        load_scan(scan_dir)
    # a symlinked directory that leads out is refused too
    gt = scan_dir / "ground_truth"
    (tmp_path / "gt_elsewhere").mkdir()
    os.rename(gt, tmp_path / "gt_elsewhere" / "ground_truth")
    gt.symlink_to(tmp_path / "gt_elsewhere" / "ground_truth")
    target.unlink()
    os.rename(outside, target)
    with pytest.raises(ScanFormatError, match=r"\[ground_truth.mesh\]: .* outside the scan"):
        load_scan(scan_dir)


def test_symlink_inside_the_scan_is_fine(scan_dir):
    target = scan_dir / "olat" / "cam_b" / "0001.exr"
    (scan_dir / "store").mkdir()
    os.rename(target, scan_dir / "store" / "0001.exr")
    target.symlink_to(scan_dir / "store" / "0001.exr")
    load_scan(scan_dir, check="full")


def test_missing_frame_names_camera_index_and_path(scan_dir):
    (scan_dir / "olat" / "cam_b" / "0002.exr").unlink()
    (scan_dir / "olat" / "cam_b" / "0003.exr").unlink()
    with pytest.raises(
        ScanFormatError,
        match=r"0002.exr \[olat.files\]: missing olat frame: camera 'cam_b', light 2; expected "
              r"file .*olat/cam_b/0002.exr \(2 of 4 olat files of this camera are missing\)",
    ):
        load_scan(scan_dir)


def test_missing_sl_and_projector_frames(scan_dir):
    os.remove(scan_dir / "calib" / "projector" / "cam_a" / "view_00_black.png")
    with pytest.raises(ScanFormatError,
                       match=r"missing calib.projector frame: camera 'cam_a', view 0 frame 'black'"):
        load_scan(scan_dir)
    build_scan(scan_dir, write=False)  # restore
    os.remove(scan_dir / "structured_light" / "cam_b" / "white.png")
    with pytest.raises(ScanFormatError,
                       match=r"missing structured_light frame: camera 'cam_b', frame 'white'"):
        load_scan(scan_dir)


def test_missing_rig_board_and_ground_truth(scan_dir):
    os.remove(scan_dir / "ground_truth" / "mesh.ply")
    with pytest.raises(ScanFormatError, match=r"\[ground_truth.mesh\]: ground-truth file not found"):
        load_scan(scan_dir)
    os.remove(scan_dir / "calib" / "board.json")
    with pytest.raises(ScanFormatError, match=r"\[calib.board\]: board file not found"):
        load_scan(scan_dir)
    os.remove(scan_dir / "rig.json")
    with pytest.raises(ScanFormatError, match=r"\[scan.rig\]: rig file not found"):
        load_scan(scan_dir)


def test_malformed_rig_and_board(scan_dir):
    (scan_dir / "calib" / "board.json").write_text("{not json")
    load_scan(scan_dir)  # quick: the board file exists
    with pytest.raises(ScanFormatError, match=r"board.json: not valid JSON"):
        load_scan(scan_dir, check="full")
    (scan_dir / "rig.json").write_text("{not json")
    with pytest.raises(ScanFormatError, match=r"rig.json: not valid JSON"):
        load_scan(scan_dir)


def test_wrong_image_size_first_or_last_found_by_quick(scan_dir):
    p = scan_dir / "olat" / "cam_a" / "0003.exr"  # the last light
    write_image(p, np.zeros((W, H, 3), np.float32))  # transposed
    with pytest.raises(ScanFormatError,
                       match=r"0003.exr \[olat.files\]: image is 16×24 px but camera 'cam_a' is "
                             r"24×16 px in the rig"):
        load_scan(scan_dir)


def test_wrong_image_size_in_the_middle_found_by_quick(scan_dir):
    scan = load_scan(scan_dir)
    p = scan_dir / "structured_light" / "cam_b" / "black.png"  # neither first nor last
    write_image(p, np.zeros((H + 1, W, 3), np.uint16))
    # quick reads every header, not only the first and last of a group
    with pytest.raises(ScanFormatError, match=r"black.png .*image is 24×17 px but camera 'cam_b'"):
        load_scan(scan_dir)
    with pytest.raises(ScanFormatError, match=r"black.png .*image is 24×17 px"):
        scan.sl_frame("cam_b", "black")  # the lazy reader checks too


def test_corrupt_image(scan_dir):
    p = scan_dir / "olat" / "cam_a" / "0001.exr"  # middle: header intact, pixels truncated
    data = p.read_bytes()
    scan = load_scan(scan_dir)
    p.write_bytes(data[: len(data) - 64])
    # the quick check compares the EXR chunk table with the file size
    with pytest.raises(ScanFormatError, match=r"0001.exr \[olat.files\]: truncated OpenEXR file"):
        load_scan(scan_dir)
    with pytest.raises(ScanFormatError, match=r"0001.exr"):
        scan.olat_frame("cam_a", 1)
    first = scan_dir / "calib" / "cam_b" / "view_000.png"
    first.write_bytes(b"garbage")
    with pytest.raises(ScanFormatError, match=r"view_000.png \[calib.files\]: not a PNG file"):
        load_scan(scan_dir)


def test_float_frame_with_srgb_response_is_refused(scan_dir):
    m = load_scan(scan_dir).manifest
    m["olat"]["response"] = "srgb"
    # the quick check reads every header's sample type: write_manifest refuses, so does load_scan
    with pytest.raises(ScanFormatError, match=r"0000.exr \[olat.response\]: .*already linear"):
        write_manifest(scan_dir, m, overwrite=True)
    _write_toml(scan_dir, m)
    with pytest.raises(ScanFormatError, match=r"0000.exr \[olat.response\]: .*already linear"):
        load_scan(scan_dir)
    scan = Scan(scan_dir, m)  # schema only, no file checks: the lazy reader refuses too
    with pytest.raises(ScanFormatError, match=r"\[olat.response\]"):
        scan.olat_frame("cam_a", 0)


def _write_toml(root, manifest):
    """Write scan.toml without write_manifest's validation (to test what load_scan refuses)."""
    import tomli_w

    (root / "scan.toml").write_text(tomli_w.dumps(manifest))


def test_response_table_in_scan(scan_dir):
    table = np.linspace(0.0, 1.0, 256) ** 2.0
    np.save(scan_dir / "calib" / "response.npy", table)
    m = load_scan(scan_dir).manifest
    m["calib"]["response"] = {"kind": "table", "file": "calib/response.npy"}
    write_manifest(scan_dir, m, overwrite=True)
    scan = load_scan(scan_dir, check="full")
    assert scan.response("calib.projector").kind == "table"
    np.save(scan_dir / "calib" / "response.npy", table[::-1])
    with pytest.raises(ScanFormatError, match=r"response.npy \[calib.response.file\]: .*non-decreasing"):
        load_scan(scan_dir)
    np.save(scan_dir / "calib" / "response.npy", np.linspace(0, 1, 65536))
    with pytest.raises(ScanFormatError, match=r"view_000.png \[calib.response\]: response table has "
                                              r"65536 levels but the frames are uint8"):
        load_scan(scan_dir)


def test_write_manifest_rejects_bad_dicts(tmp_path):
    root = tmp_path / "scan"
    m = build_scan(root, write=False)
    bad = copy.deepcopy(m)
    bad["olat"]["n_lights"] = 3
    with pytest.raises(ScanFormatError, match=r"\[olat.n_lights\]: n_lights = 3"):
        write_manifest(root, bad)
    bad = copy.deepcopy(m)
    bad["scan"]["metadata"] = {"operator": None}
    with pytest.raises(ScanFormatError, match="cannot be written as TOML"):
        write_manifest(root, bad)
    assert not (root / "scan.toml").exists()


def test_check_argument_is_validated(scan_dir):
    with pytest.raises(InputError, match="check: unknown value 'deep'"):
        load_scan(scan_dir, check="deep")
    assert isinstance(load_scan(scan_dir / "scan.toml"), Scan)  # the manifest path works too


def test_documented_example_manifest_is_valid():
    """The example in docs/scan-format.md passes the schema (keeps the document honest)."""
    import re
    import tomllib

    doc = Path(__file__).resolve().parents[1] / "docs" / "scan-format.md"
    if not doc.is_file():
        pytest.skip(f"{doc} is absent")
    block = re.search(r"```toml\n(.*?)```", doc.read_text(encoding="utf-8"), re.S).group(1)
    m = validate_manifest(tomllib.loads(block))
    assert m["olat"]["n_lights"] == 2048 and m["calib"]["projector"]["views"] == 4
    assert m["structured_light"]["patterns"] == {"n_bits_x": 1, "n_bits_y": 1}
    from facegeo.geometry.structured_light import PatternSpec, pattern_names

    spec = PatternSpec.from_dict({"width": 1024, "height": 768, **m["structured_light"]["patterns"]})
    assert pattern_names(spec) == m["structured_light"]["frames"]


def test_olat_exposure_must_be_positive_and_divides_frames(tmp_path):
    """``[olat] exposure`` is validated (a finite number > 0, named in the error)."""
    from facegeo.capture._scan_schema import validate_manifest
    from facegeo.errors import ScanFormatError
    from facegeo.capture.scan import new_manifest

    m = new_manifest("x", synthetic=True)
    m["olat"] = {"n_lights": 4, "exposure": 0.0}
    with pytest.raises(ScanFormatError, match=r"\[olat.exposure\].*> 0"):
        validate_manifest(m)
    m["olat"]["exposure"] = 2
    assert validate_manifest(m)["olat"]["exposure"] == 2.0
