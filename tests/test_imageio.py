"""Image I/O and camera responses (facegeo.capture.imageio)."""

from __future__ import annotations

import logging
import os
import re
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from facegeo.errors import InputError, ScanFormatError
from facegeo.capture.imageio import (
    ImageReadError,
    Response,
    clipped_mask,
    encode,
    linear_to_srgb,
    linearize,
    parse_response,
    read_image,
    read_image_info,
    read_image_size,
    saturated_mask,
    srgb_to_linear,
    write_image,
)

# Named tolerances.
FLOAT32_EPS = float(np.finfo(np.float32).eps)  # relative rounding of a float32 linear value
HDR_RGBE_REL = 1.0 / 128  # Radiance RGBE: 8-bit mantissa sharing one exponent


def _rng(seed=0):
    return np.random.default_rng(seed)


# --------------------------------------------------------------------------- PNG


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [None, 3, 4])
def test_png_round_trip_is_bit_exact_and_rgb_ordered(tmp_path, dtype, channels):
    top = np.iinfo(dtype).max
    shape = (16, 24) if channels is None else (16, 24, channels)
    img = _rng().integers(0, top + 1, size=shape, dtype=dtype)
    if channels:
        img[0, 0, :3] = [top, 0, 0]  # a pure red pixel: a BGR swap would show as blue
    p = write_image(tmp_path / "a.png", img)
    back = read_image(p)
    assert back.dtype == np.dtype(dtype)
    assert back.shape == img.shape
    assert np.array_equal(back, img)
    assert read_image_size(p) == (24, 16)


def test_png_channel_order_matches_opencv_bgr_on_disk(tmp_path):
    import cv2

    img = np.zeros((4, 5, 3), np.uint8)
    img[..., 0] = 200  # red
    write_image(tmp_path / "r.png", img)
    bgr = cv2.imread(str(tmp_path / "r.png"), cv2.IMREAD_UNCHANGED)
    assert bgr[0, 0].tolist() == [0, 0, 200]  # OpenCV sees red in its last channel


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int32])
def test_png_refuses_non_integer_or_wide_dtypes(tmp_path, dtype):
    with pytest.raises(InputError, match="PNG holds uint8 or uint16"):
        write_image(tmp_path / "a.png", np.zeros((4, 4, 3), dtype))
    assert not list(tmp_path.iterdir())  # nothing left behind


def test_write_refuses_unknown_suffix_and_bad_shapes(tmp_path):
    with pytest.raises(InputError, match="writable formats"):
        write_image(tmp_path / "a.bmp", np.zeros((4, 4), np.uint8))
    with pytest.raises(InputError, match="expected an image of shape"):
        write_image(tmp_path / "a.png", np.zeros((4, 4, 2), np.uint8))
    with pytest.raises(InputError, match="half=True only applies to .exr"):
        write_image(tmp_path / "a.png", np.zeros((4, 4), np.uint8), half=True)


# --------------------------------------------------------------------------- EXR


@pytest.mark.parametrize("channels", [None, 3, 4])
def test_exr_float32_round_trip_is_bit_exact(tmp_path, channels):
    shape = (16, 24) if channels is None else (16, 24, channels)
    img = (_rng(1).standard_normal(shape) * 1e3).astype(np.float32)
    img.flat[0] = 34000.0
    img.flat[1] = 1e-30  # a denormal-range value survives float32 storage
    p = write_image(tmp_path / "a.exr", img)
    back = read_image(p)
    assert back.dtype == np.float32 and back.shape == img.shape
    assert np.array_equal(back, img)
    assert read_image_size(p) == (24, 16)


def test_exr_half_round_trip_is_bit_exact(tmp_path):
    img = (_rng(2).random((16, 24, 3)) * 60000).astype(np.float16)
    p = write_image(tmp_path / "h.exr", img, half=True)
    back = read_image(p)
    assert back.dtype == np.float16
    assert np.array_equal(back, img)
    # float32 input stored as half: equal to numpy's own float16 rounding
    x = (_rng(3).random((8, 8)) * 10).astype(np.float32)
    back = read_image(write_image(tmp_path / "h2.exr", x, half=True))
    assert back.shape == (8, 8) and np.array_equal(back, x.astype(np.float16))


def test_exr_channel_names_and_compression(tmp_path):
    import OpenEXR

    write_image(tmp_path / "rgb.exr", np.ones((4, 6, 3), np.float32))
    write_image(tmp_path / "y.exr", np.ones((4, 6), np.float32))
    f = OpenEXR.File(str(tmp_path / "rgb.exr"), separate_channels=True)
    assert set(f.channels()) == {"R", "G", "B"}
    assert f.header()["compression"] == OpenEXR.ZIP_COMPRESSION
    f = OpenEXR.File(str(tmp_path / "y.exr"), separate_channels=True)
    assert set(f.channels()) == {"Y"}
    write_image(tmp_path / "rgba.exr", np.ones((4, 6, 4), np.float32), half=True)
    f = OpenEXR.File(str(tmp_path / "rgba.exr"), separate_channels=True)
    assert set(f.channels()) == {"R", "G", "B", "A"}


def test_exr_refuses_integers_and_half_overflow(tmp_path):
    with pytest.raises(InputError, match="EXR holds float32 or float16, got uint16"):
        write_image(tmp_path / "a.exr", np.zeros((4, 4, 3), np.uint16))
    big = np.full((4, 4), 70000.0, np.float32)
    with pytest.raises(InputError, match="exceed the half-float range"):
        write_image(tmp_path / "a.exr", big, half=True)
    # a NaN beside the overflow must not hide it, whatever its sign
    for v in (65520.0, -1e6):
        mixed = np.array([[np.nan, 1.0], [v, np.inf]], np.float32)
        with pytest.raises(InputError, match="1 value"):
            write_image(tmp_path / "a.exr", mixed, half=True)
    assert not list(tmp_path.iterdir())
    # inf and NaN are not overflows: stored as half inf / NaN
    special = np.array([[np.nan, np.inf], [-np.inf, 65504.0]], np.float32)
    back = read_image(write_image(tmp_path / "s.exr", special, half=True))
    assert np.array_equal(back, special.astype(np.float16), equal_nan=True)


def test_opencv_cannot_do_exr(tmp_path):
    """Why EXR goes through the OpenEXR bindings: the OpenCV wheels have no EXR codec."""
    import cv2

    p = write_image(tmp_path / "a.exr", np.ones((4, 4, 3), np.float32))
    if cv2.haveImageReader(str(p)):  # pragma: no cover - a future wheel may add it
        pytest.skip("this OpenCV build reads EXR")
    assert cv2.imread(str(p), cv2.IMREAD_UNCHANGED) is None


# --------------------------------------------------------------------------- HDR


def test_radiance_hdr_round_trip_within_rgbe_precision(tmp_path):
    img = (_rng(4).random((16, 24, 3)) * 100 + 0.01).astype(np.float32)
    img[0, 0] = [5.0, 0.5, 0.05]  # channel order check
    p = write_image(tmp_path / "a.hdr", img)
    back = read_image(p)
    assert back.dtype == np.float32 and back.shape == img.shape
    # RGBE shares the exponent of the largest channel: error <= max channel / 128 per pixel
    worst = (np.abs(back - img) / img.max(axis=-1, keepdims=True)).max()
    assert worst <= HDR_RGBE_REL
    assert back[0, 0, 0] > back[0, 0, 1] > back[0, 0, 2]
    assert read_image_size(p) == (24, 16)


def test_radiance_hdr_refuses_grey_and_negative(tmp_path):
    with pytest.raises(InputError, match="RGB only"):
        write_image(tmp_path / "a.hdr", np.ones((4, 4), np.float32))
    with pytest.raises(InputError, match=">= 0"):
        write_image(tmp_path / "a.hdr", -np.ones((4, 4, 3), np.float32))


# --------------------------------------------------------------------------- read errors


def test_missing_file_raises_scan_format_error_naming_it(tmp_path):
    p = tmp_path / "nope.png"
    with pytest.raises(ImageReadError, match="nope.png: image file not found"):
        read_image(p)
    with pytest.raises(ScanFormatError, match="nope.png"):
        read_image_size(p)


@pytest.mark.parametrize("suffix", [".png", ".exr", ".jpg", ".hdr"])
def test_garbage_file_raises(tmp_path, suffix):
    p = tmp_path / f"bad{suffix}"
    p.write_bytes(b"this is not an image at all" * 4)
    with pytest.raises(ImageReadError, match=f"bad{suffix}"):
        read_image(p)
    with pytest.raises(ImageReadError, match=f"bad{suffix}"):
        read_image_size(p)


def test_truncated_png_and_exr_fail_on_decode_but_not_header(tmp_path):
    png = write_image(tmp_path / "t.png", _rng().integers(0, 65535, (64, 64, 3), dtype=np.uint16))
    exr = write_image(tmp_path / "t.exr", _rng().random((64, 64, 3)).astype(np.float32))
    for p in (png, exr):
        data = p.read_bytes()
        p.write_bytes(data[: len(data) // 2])
        assert read_image_size(p) == (64, 64)  # the header is intact
        with pytest.raises(ImageReadError, match=p.name):
            read_image(p)


def _image_cases(tmp_path):
    """One file of every kind read_image_info must describe without decoding."""
    import cv2

    rng = _rng(3)
    out = []
    for dtype in (np.uint8, np.uint16):
        for shape in ((13, 29), (13, 29, 3), (13, 29, 4)):
            a = rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype)
            out.append(write_image(tmp_path / f"{dtype.__name__}_{len(shape)}_{shape[-1]}.png", a))
    for half in (False, True):
        for shape in ((13, 29), (13, 29, 3), (13, 29, 4)):
            a = rng.random(shape).astype(np.float32)
            out.append(write_image(tmp_path / f"h{int(half)}_{len(shape)}_{shape[-1]}.exr", a,
                                   half=half))
    out.append(write_image(tmp_path / "a.hdr", rng.random((13, 29, 3)).astype(np.float32)))
    for name, shape in (("grey.jpg", (13, 29)), ("rgb.jpg", (13, 29, 3))):
        cv2.imwrite(str(tmp_path / name), rng.integers(0, 255, shape, dtype=np.uint8))
        out.append(tmp_path / name)
    return out


def test_image_info_equals_what_read_image_returns(tmp_path):
    # Pillow / the EXR header parser replace the hand-written PNG and JPEG header readers: the
    # header must agree exactly with the decoded array (size, channels, dtype).
    for p in _image_cases(tmp_path):
        img = read_image(p)
        info = read_image_info(p)
        got = (info.height, info.width, info.channels, info.dtype)
        want = (img.shape[0], img.shape[1], 1 if img.ndim == 2 else img.shape[2], img.dtype)
        assert got == want, p.name
        assert read_image_size(p) == (img.shape[1], img.shape[0]), p.name
        assert info.verified == (p.suffix != ".hdr"), p.name


@pytest.mark.parametrize("suffix", [".exr", ".png"])
def test_verify_catches_every_truncation(tmp_path, suffix):
    # Every prefix of a valid file must be reported as broken by the header-only check
    # (PNG: except a cut inside the final IEND CRC, which loses no pixel data).
    rng = _rng(4)
    if suffix == ".exr":
        img = rng.random((40, 24, 3)).astype(np.float32)  # ZIP: 3 chunks of 16 rows
        spare = 0
    else:
        img = rng.integers(0, 65535, (40, 24, 3), dtype=np.uint16)
        spare = 4
    p = write_image(tmp_path / f"full{suffix}", img)
    data = p.read_bytes()
    cut = tmp_path / f"cut{suffix}"
    missed = []
    # every cut in the header, chunk table and last 32 bytes; every 61st byte in between
    ends = set(range(200)) | set(range(200, len(data), 61)) | set(range(len(data) - 32, len(data)))
    for n in sorted(e for e in ends if e < len(data) - spare):
        cut.write_bytes(data[:n])
        try:
            read_image_info(cut)
        except ImageReadError as exc:
            assert "cut" + suffix in str(exc)
        else:
            missed.append(n)
    assert missed == []
    cut.write_bytes(data)
    assert read_image_info(cut).verified


def test_not_an_exr_and_truncated_exr_are_one_clear_error_without_library_noise(tmp_path):
    # Run in a subprocess: the OpenEXR C library writes to file descriptor 2 directly.
    good = write_image(tmp_path / "good.exr", _rng().random((64, 64, 3)).astype(np.float32))
    data = good.read_bytes()
    (tmp_path / "short.exr").write_bytes(data[: len(data) // 2])
    (tmp_path / "fake.exr").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    code = (
        "import sys\n"
        "from facegeo.capture.imageio import read_image, ImageReadError\n"
        "for p in sys.argv[1:]:\n"
        "    try:\n"
        "        read_image(p)\n"
        "    except ImageReadError as e:\n"
        "        print(e)\n"
    )
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "short.exr"),
                        str(tmp_path / "fake.exr")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stderr == ""  # no "(EXR_ERR_...)" or "Warning: Exception raised ..." noise
    lines = r.stdout.splitlines()
    assert len(lines) == 2
    assert "short.exr" in lines[0] and "truncated" in lines[0]
    assert "fake.exr" in lines[1] and "not an OpenEXR file" in lines[1]
    assert "76 2f 31 01" in lines[1]


def test_native_noise_is_hidden_even_when_the_structure_check_passes(tmp_path, capfd):
    # Overwrite the middle of the file (chunk leaders and data) but keep the header and chunk
    # table intact: the OpenEXR library itself fails and prints "Warning: Exception raised
    # reading pixel data" to std::cout; read_image must raise one error and keep fds 1, 2 clean.
    good = write_image(tmp_path / "z.exr", _rng().random((64, 64, 3)).astype(np.float32))
    data = bytearray(good.read_bytes())
    n = len(data) // 2
    data[n:n + 500] = _rng(1).integers(0, 255, 500, dtype=np.uint8).tobytes()
    good.write_bytes(bytes(data))
    with pytest.raises(ImageReadError, match="z.exr: corrupt OpenEXR file"):
        read_image(good)
    out = capfd.readouterr()
    assert out.err == "" and out.out == ""


def test_empty_and_unsupported_files(tmp_path):
    (tmp_path / "e.png").write_bytes(b"")
    with pytest.raises(ImageReadError, match="e.png"):
        read_image(tmp_path / "e.png")
    (tmp_path / "x.gif").write_bytes(b"GIF89a")
    with pytest.raises(ImageReadError, match="unsupported image format"):
        read_image(tmp_path / "x.gif")
    (tmp_path / "d.png").mkdir()
    with pytest.raises(ImageReadError, match="directory"):
        read_image(tmp_path / "d.png")


def test_jpeg_header_size(tmp_path):
    import cv2

    p = tmp_path / "a.jpg"
    cv2.imwrite(str(p), np.zeros((13, 29, 3), np.uint8))
    assert read_image_size(p) == (29, 13)
    assert read_image(p).shape == (13, 29, 3)


# --------------------------------------------------------------------------- shared env maps


@pytest.mark.shared_data
def test_reads_the_shared_environment_maps(shared_data):
    folder = shared_data / "envmaps"
    files = sorted(folder.glob("*.exr")) if folder.is_dir() else []
    if len(files) < 8:
        pytest.skip(f"expected eight .exr maps in {folder}, found {len(files)}")
    peaks = []
    for p in files:
        assert read_image_size(p) == (1024, 512), p.name
        img = read_image(p)
        assert img.shape == (512, 1024, 3) and img.dtype == np.float32, p.name
        assert np.isfinite(img).all(), p.name
        # DWAB-compressed sources carry small negative ringing (down to about -0.004):
        # consumers (facegeo.envmap) must clip, the reader must not hide it.
        assert img.min() > -0.01, p.name
        peaks.append(float(img.max()))
    # The brightest map peaks near the 32,000–34,000 clamp of its source.
    assert 1e4 < max(peaks) < 4e4


# --------------------------------------------------------------------------- responses


def test_parse_response_values():
    assert parse_response("linear").kind == "linear"
    assert parse_response("srgb").kind == "srgb"
    assert parse_response({"kind": "srgb"}).kind == "srgb"
    r = parse_response({"kind": "gamma", "gamma": 2.2})
    assert r.kind == "gamma" and r.gamma == 2.2
    assert r.to_spec() == {"kind": "gamma", "gamma": 2.2}
    with pytest.raises(ScanFormatError, match="unknown response 'sRGB'"):
        parse_response("sRGB", key="olat.response")
    with pytest.raises(ScanFormatError, match=r"\[olat.response.gamma\].*> 0"):
        parse_response({"kind": "gamma", "gamma": -1}, key="olat.response")
    with pytest.raises(ScanFormatError, match="unknown key"):
        parse_response({"kind": "srgb", "gamma": 2})
    with pytest.raises(ScanFormatError, match="needs key"):
        parse_response({"kind": "gamma"})
    with pytest.raises(ScanFormatError, match="unknown response kind"):
        parse_response({"kind": "log"})


def test_table_response_file(tmp_path):
    t = np.linspace(0, 4, 256) ** 2  # arbitrary scale: normalised on load
    np.save(tmp_path / "response.npy", t)
    r = parse_response({"kind": "table", "file": "response.npy"}, base_dir=tmp_path)
    assert r.kind == "table" and r.table.max() == 1.0
    assert r.to_spec() == {"kind": "table", "file": "response.npy"}
    np.save(tmp_path / "bad.npy", t[::-1])
    with pytest.raises(ScanFormatError, match="bad.npy.*non-decreasing.*codes 0 and 1"):
        parse_response({"kind": "table", "file": "bad.npy"}, base_dir=tmp_path)
    with pytest.raises(ScanFormatError, match="missing.npy.*not found"):
        parse_response({"kind": "table", "file": "missing.npy"}, base_dir=tmp_path)
    with pytest.raises(InputError, match="256 levels but the frames are uint16"):
        r.linearize(np.zeros((2, 2), np.uint16))


def test_srgb_curve_reference_values():
    # IEC 61966-2-1: the curve is continuous at the knee and maps 0.5 to 0.21404.
    assert abs(float(srgb_to_linear(0.5)) - 0.214041) < 1e-6
    assert abs(float(srgb_to_linear(0.04045)) - 0.04045 / 12.92) < 1e-12
    x = np.linspace(0, 1, 1001)
    assert np.abs(srgb_to_linear(linear_to_srgb(x)) - x).max() < 1e-12


def test_linearize_known_values():
    img = np.array([[0, 128, 255]], np.uint8)
    assert np.allclose(linearize(img, "linear"), [[0, 128 / 255, 1]], rtol=0, atol=1e-7)
    assert np.allclose(
        linearize(img, {"kind": "gamma", "gamma": 2.0}), [[0, (128 / 255) ** 2, 1]], atol=1e-7
    )
    out = linearize(img, "srgb")
    assert out.dtype == np.float32 and out[0, 0] == 0 and out[0, 2] == 1
    img16 = np.array([0, 32768, 65535], np.uint16)
    assert np.allclose(linearize(img16, "linear"), [0, 32768 / 65535, 1], atol=1e-7)


def test_linearize_float_only_with_linear_response():
    x = np.array([[0.5, 2.0]], np.float64)
    out = linearize(x, "linear")
    assert out.dtype == np.float32 and np.array_equal(out, x.astype(np.float32))
    with pytest.raises(InputError, match="already linear"):
        linearize(x.astype(np.float32), "srgb")
    with pytest.raises(InputError, match="cannot encode"):
        encode(x, "srgb", np.float32)


def _round_trip_bound(resp: Response, codes: np.ndarray, code_max: int) -> np.ndarray:
    """Half an LSB times the local slope: max(f(c+½) − f(c), f(c) − f(c−½))."""
    f = resp._decode
    c = codes.astype(np.float64)
    up = f(np.clip((c + 0.5) / code_max, 0, 1)) - f(c / code_max)
    down = f(c / code_max) - f(np.clip((c - 0.5) / code_max, 0, 1))
    return np.maximum(up, down)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize(
    "spec", ["linear", "srgb", {"kind": "gamma", "gamma": 2.2}, {"kind": "gamma", "gamma": 0.45}]
)
def test_encode_linearize_round_trip_within_half_lsb(dtype, spec):
    """linearize(encode(x)) is within half an LSB of the encoded slope of x (worst case)."""
    resp = parse_response(spec)
    code_max = int(np.iinfo(dtype).max)
    x = np.concatenate([_rng(5).random(20000), np.linspace(0, 1, 1001), [0.0, 1.0]])
    codes = encode(x, resp, dtype)
    assert codes.dtype == np.dtype(dtype)
    back = linearize(codes, resp).astype(np.float64)
    bound = _round_trip_bound(resp, codes, code_max) + 2 * FLOAT32_EPS
    err = np.abs(back - x)
    assert (err <= bound).all(), float((err - bound).max())
    # and the codes themselves round-trip exactly
    all_codes = np.arange(code_max + 1, dtype=dtype)
    assert np.array_equal(encode(linearize(all_codes, resp), resp, dtype), all_codes)


def test_encode_clips_out_of_range():
    x = np.array([-1.0, 0.0, 1.0, 7.0])
    assert encode(x, "srgb", np.uint8).tolist() == [0, 0, 255, 255]
    with pytest.raises(InputError, match="non-finite"):
        encode(np.array([np.nan]), "srgb", np.uint8)


def _srgb8_formula(x32: np.ndarray) -> np.ndarray:
    """The reference: the sRGB curve in float64, rounded to 8-bit codes (the non-table path)."""
    x = np.clip(x32.astype(np.float64), 0.0, 1.0)
    return np.rint(linear_to_srgb(x) * 255).astype(np.uint8)


def test_srgb8_table_equals_formula_at_every_boundary():
    """The float32 → sRGB uint8 table gives the formula's code at each code boundary, one float32
    step below it, and on random, out-of-range and signed-zero inputs (exact: codes equal)."""
    from facegeo.capture.response import _srgb8_tables

    base, thr = _srgb8_tables()
    t = np.sort(thr[np.isfinite(thr)])
    assert t.size == 255  # one boundary per code 1..255
    below = np.nextafter(t, np.float32(-1.0))
    x = np.concatenate([t, below, _rng(11).random(200_000).astype(np.float32) ** 3,
                        np.array([-0.0, 0.0, -3.0, 1.0, 1.5, 7e30, np.float32(1e-45)], np.float32)])
    got = encode(x, "srgb", np.uint8)
    assert got.dtype == np.uint8
    assert np.array_equal(got, _srgb8_formula(x))
    # a boundary off by one float32 step would fail here: the codes just below are one less
    assert np.array_equal(encode(below, "srgb", np.uint8).astype(int) + 1,
                          encode(t, "srgb", np.uint8).astype(int))
    # an image keeps its shape
    img = _rng(12).random((5, 7, 3)).astype(np.float32)
    assert np.array_equal(encode(img, "srgb", np.uint8), _srgb8_formula(img))


@pytest.mark.slow
def test_srgb8_table_equals_formula_for_every_float32_in_unit_interval():
    """Exhaustive: all 1,065,353,217 float32 values of [0, 1] encode to the formula's code."""
    one = int(np.float32(1.0).view(np.uint32))
    step = 1 << 23
    for start in range(0, one + 1, step):
        bits = np.arange(start, min(start + step, one + 1), dtype=np.uint32)
        x = bits.view(np.float32)
        got = encode(x, "srgb", np.uint8)
        want = _srgb8_formula(x)
        bad = np.flatnonzero(got != want)
        assert bad.size == 0, (float(x[bad[0]]), int(got[bad[0]]), int(want[bad[0]]))


def test_table_response_round_trip_per_channel():
    levels = 256
    code = np.arange(levels) / (levels - 1)
    table = np.stack([code**2.2, code**2.0, code**1.8], axis=-1) * 3.0
    resp = Response.from_table(table)
    x = _rng(6).random((100, 3))
    codes = encode(x, resp, np.uint8)
    back = linearize(codes, resp).astype(np.float64)
    t = resp.table
    # worst case: half the gap between neighbouring table entries around the chosen code
    c = codes.astype(int)
    gap = np.maximum(
        t[np.minimum(c + 1, levels - 1), np.arange(3)] - t[c, np.arange(3)],
        t[c, np.arange(3)] - t[np.maximum(c - 1, 0), np.arange(3)],
    )
    assert (np.abs(back - x) <= 0.5 * gap + 2 * FLOAT32_EPS).all()
    with pytest.raises(InputError, match="one curve per channel"):
        linearize(np.zeros((4, 4), np.uint8), resp)


def test_response_table_rules():
    with pytest.raises(InputError, match="non-decreasing"):
        Response.from_table(np.array([0.0, 1.0, 0.5]))
    with pytest.raises(InputError, match="finite"):
        Response.from_table(np.array([0.0, np.nan, 1.0]))
    with pytest.raises(InputError, match="shape"):
        Response.from_table(np.zeros((4, 2)))
    with pytest.raises(InputError, match="unknown kind"):
        Response("log")


# --------------------------------------------------------------------------- masks


def test_saturated_and_clipped_masks():
    img = np.full((2, 3, 3), 100, np.uint8)
    img[0, 0, 1] = 255
    img[1, 2, 2] = 0
    sat = saturated_mask(img)
    clip = clipped_mask(img)
    assert sat.shape == (2, 3) and sat.tolist() == [[True, False, False], [False, False, False]]
    assert clip.tolist() == [[False, False, False], [False, False, True]]
    assert clipped_mask(img, low=100).all()
    img16 = np.array([[65535, 65534]], np.uint16)
    assert saturated_mask(img16).tolist() == [[True, False]]
    f = np.array([[1.0, np.inf, 5.0]], np.float32)
    assert saturated_mask(f).tolist() == [[False, True, False]]
    assert saturated_mask(f, max_value=5.0).tolist() == [[False, True, True]]
    assert clipped_mask(np.array([[0.0, 1e-3, np.nan]])).tolist() == [[True, False, True]]


# --------------------------------------------------------------------------- BMP and Netpbm


@pytest.mark.parametrize("suffix, shape, dtype", [
    (".bmp", (5, 7, 3), np.uint8), (".bmp", (5, 7), np.uint8),
    (".pgm", (5, 7), np.uint8), (".pgm", (5, 7), np.uint16), (".ppm", (5, 7, 3), np.uint8),
])
def test_bmp_and_netpbm_read_bit_exact_with_header_info(tmp_path, suffix, shape, dtype):
    """Written by OpenCV (BGR on disk), read back RGB and bit-exact; the header-only info
    agrees with the decode; a file cut short is refused by the verified header read."""
    import cv2

    img = np.random.default_rng(5).integers(0, np.iinfo(dtype).max, shape, dtype=dtype)
    p = tmp_path / f"x{suffix}"
    assert cv2.imwrite(str(p), img[..., ::-1] if img.ndim == 3 else img)
    got = read_image(p)
    assert got.dtype == dtype and np.array_equal(got, img)
    info = read_image_info(p)
    assert (info.width, info.height, info.channels, info.dtype) == (
        7, 5, 1 if img.ndim == 2 else 3, np.dtype(dtype)) and info.verified
    p.write_bytes(p.read_bytes()[:-4])
    with pytest.raises(ScanFormatError, match=r"truncated (BMP|PPM) file"):
        read_image_info(p)


def test_console_stream_reaches_stderr_while_an_image_is_read(capfd):
    """Progress written to console_stream() while another thread reads an image reaches the
    real stderr; so does what is printed to sys.stderr meanwhile (it used to be hidden)."""
    from facegeo.capture import imageio as io_

    with io_._quiet_native_output():  # as a read on another thread would hold it
        stream = io_.console_stream()
        stream.write("progress 1/2\n")
        print("printed meanwhile", file=sys.stderr)
    stream.write("progress 2/2\n")
    stream.close()
    err = capfd.readouterr().err
    assert "progress 1/2" in err and "progress 2/2" in err
    assert "printed meanwhile" in err


# --------------------------------------------------------------------------- native output
# Image reads keep what native decoders print on a corrupt file off the terminal; everything
# else printed meanwhile, by any thread, on fds 1 / 2 or through sys.stdout / sys.stderr, must
# get through (a user audit lost 88 of 128 lines printed during iter_olat(read_ahead=2)).


class _GatedCv2:
    """OpenCV whose first ``imdecode`` waits, inside the read's output hiding, until
    ``release`` is set (``inside`` tells that it is waiting): a read that is certainly running
    while another thread prints."""

    def __init__(self):
        import cv2

        self._cv2 = cv2
        self.IMREAD_UNCHANGED = cv2.IMREAD_UNCHANGED
        self.inside, self.release = threading.Event(), threading.Event()

    def imdecode(self, data, flags):
        if not self.inside.is_set():
            self.inside.set()
            assert self.release.wait(30)
        return self._cv2.imdecode(data, flags)


def _fd_id(fd):
    st = os.fstat(fd)
    return st.st_dev, st.st_ino


def _corrupt_files(tmp_path):
    """Files whose decoding makes a native library print, with what it prints (checked against
    the debug log, so that "nothing on the terminal" is not passed by printing nothing). An
    entry that is a tuple is met by any one of its lines: which library reports a truncated PNG
    depends on OpenCV's version (libpng up to 5.0; 5.1 checks the stream itself)."""
    rng = _rng(6)
    out = {}
    exr = write_image(tmp_path / "mid.exr", rng.random((64, 64, 3)).astype(np.float32))
    data = bytearray(exr.read_bytes())  # header and chunk table intact, chunk leaders not
    n = len(data) // 2
    data[n:n + 500] = rng.integers(0, 255, 500, dtype=np.uint8).tobytes()
    exr.write_bytes(bytes(data))
    out[exr] = ("(EXR_ERR_BAD_CHUNK_LEADER)", "Warning: Exception raised reading pixel data")
    png = write_image(tmp_path / "cut.png", rng.integers(0, 255, (40, 48, 3), dtype=np.uint8))
    png.write_bytes(png.read_bytes()[:200])
    out[png] = (("PNG input buffer is incomplete", "Unexpected end of input stream"),)
    png = write_image(tmp_path / "filter.png", rng.integers(0, 255, (40, 48, 3), dtype=np.uint8))
    data = bytearray(png.read_bytes())
    n = len(data) // 2
    data[n:n + 64] = rng.integers(0, 255, 64, dtype=np.uint8).tobytes()
    png.write_bytes(bytes(data))
    out[png] = ("libpng error",)
    import cv2

    for name in ("cut.bmp", "cut.tif"):
        p = tmp_path / name
        cv2.imwrite(str(p), rng.integers(0, 255, (40, 48, 3), dtype=np.uint8))
        p.write_bytes(p.read_bytes()[:100])
        out[p] = ("loadsave.cpp" if name.endswith(".bmp") else "TIFF_Error",)
    return out


def test_native_noise_of_every_decoder_is_hidden_and_logged(tmp_path, capfd, caplog):
    """OpenEXR (fd 2 and sys.stdout), libpng, OpenCV's logger (libtiff, BMP, with its trailing
    empty line): nothing on fds 1 / 2, every line in the debug log."""
    caplog.set_level(logging.DEBUG, logger="facegeo.capture.imageio")
    files = _corrupt_files(tmp_path)
    for p in files:
        with pytest.raises(ImageReadError, match=p.name):
            read_image(p)
    out = capfd.readouterr()
    assert out.out == "" and out.err == ""
    logged = "\n".join(r.getMessage() for r in caplog.records)
    for p, says in files.items():
        for s in says:
            alternatives = s if isinstance(s, tuple) else (s,)
            assert any(a in logged for a in alternatives), (p.name, s)


def test_other_threads_prints_reach_stdout_while_images_are_read_ahead(tmp_path, capfd,
                                                                       monkeypatch):
    """A user's prints from another thread (through sys.stdout and on fd 1) and the consumer's
    own prints during read_ahead all reach stdout, in order, while a read is certainly running;
    the corrupt files read meanwhile still print nothing."""
    from facegeo.capture import imageio as io_
    from facegeo.fsutil import read_ahead

    rng = _rng(7)
    good = [write_image(tmp_path / f"f{i}.png", rng.integers(0, 255, (9, 11, 3), dtype=np.uint8))
            for i in range(6)]
    paths = good[:1] + list(_corrupt_files(tmp_path)) + good[1:]
    gate = _GatedCv2()
    monkeypatch.setattr(io_, "_cv2", lambda: gate)

    def user():
        assert gate.inside.wait(30)
        for i in range(64):
            print(f"user print {i}")
        for i in range(64):
            os.write(1, f"user fd {i}\n".encode())
        print("user stderr", file=sys.stderr)
        gate.release.set()

    def read(p):
        try:
            return read_image(p).shape
        except ImageReadError:
            return None

    t = threading.Thread(target=user)
    t.start()
    for k, shape in enumerate(read_ahead(read, paths, workers=2)):
        print(f"frame {k} {shape}")
    t.join()
    out = capfd.readouterr()
    # two threads write fd 1 at once, and a print is two writes (text, then its newline, with
    # PYTHONUNBUFFERED): lines of different threads may share a line of the output, as on any
    # terminal, so each thread's lines are looked for as text, in order
    assert re.findall(r"user print (\d+)", out.out) == [str(i) for i in range(64)]
    assert re.findall(r"user fd (\d+)", out.out) == [str(i) for i in range(64)]
    assert re.findall(r"frame \d+ (?:\(9, 11, 3\)|None)", out.out) == [
        f"frame {k} {(9, 11, 3) if p in good else None}" for k, p in enumerate(paths)]
    rest = re.sub(r"user print \d+|user fd \d+|frame \d+ (?:\(9, 11, 3\)|None)", "", out.out)
    assert rest.strip() == ""  # and no noise
    assert out.err == "user stderr\n"


def test_prints_of_other_threads_reach_the_real_stdout_in_a_subprocess(tmp_path):
    """As the audit ran it: real descriptors, sys.stdout a pipe-backed (block-buffered) stream,
    read ahead on two threads over good and corrupt files, 128 lines printed by another thread
    (the first 64 while a read certainly runs, the rest as it happens)."""
    for i in range(42):
        write_image(tmp_path / f"{i:02d}.png", _rng(i).integers(0, 255, (9, 11, 3), dtype=np.uint8))
    broken = sorted(_corrupt_files(tmp_path))
    code = (
        "import sys, threading\n"
        "from pathlib import Path\n"
        "from facegeo.capture import _native_output as no_, imageio as io_\n"
        "from facegeo.fsutil import read_ahead\n"
        "cv2 = io_._cv2()\n"
        "inside, release = threading.Event(), threading.Event()\n"
        "class Gated:\n"  # the first decode waits for the first 64 lines (see _GatedCv2)
        "    IMREAD_UNCHANGED = cv2.IMREAD_UNCHANGED\n"
        "    def imdecode(data, flags):\n"
        "        if not inside.is_set():\n"
        "            inside.set()\n"
        "            release.wait(30)\n"
        "        return cv2.imdecode(data, flags)\n"
        "io_._cv2 = lambda: Gated\n"
        "d = Path(sys.argv[1])\n"
        "paths = sorted(d.glob('[0-9]*.png')) + [d / n for n in sys.argv[2:]]\n"
        "def read(p):\n"
        "    try:\n"
        "        return io_.read_image(p).shape\n"
        "    except io_.ImageReadError:\n"
        "        return None\n"
        "def user():\n"
        "    inside.wait(30)\n"
        "    for i in range(128):\n"
        "        print(f'user line {i}')\n"
        "        if i == 63:\n"
        "            release.set()\n"
        "t = threading.Thread(target=user)\n"
        "t.start()\n"
        "frames = list(read_ahead(read, paths * 4, workers=2))\n"
        "t.join()\n"
        "print('frames', len(frames), frames.count(None))\n"
    )
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path), *(p.name for p in broken)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stderr == ""  # no decoder noise
    want = [f"user line {i}" for i in range(128)] + [
        f"frames {4 * (42 + len(broken))} {4 * len(broken)}"]
    # every line's text, once and in order. Its newline may land elsewhere: print() holds the
    # stream it fetched, so a line started just before a read and finished just after it has
    # its text in the pipe and its newline straight on the terminal — the limitation
    # _quiet_native_output documents ("a stream object kept from before the read"), seen once
    # in a CI run at load 5 ('', 'user line 127frames 188 20')
    assert r.stdout.replace("\n", "") == "".join(want)
    assert r.stdout.count("\n") == len(want)


def test_an_exception_inside_a_read_restores_descriptors_and_streams(tmp_path, capfd):
    from facegeo.capture import _native_output as no_, imageio as io_

    before = {fd: _fd_id(fd) for fd in (1, 2)}
    out, err = sys.stdout, sys.stderr

    class Boom(Exception):
        pass

    with pytest.raises(Boom):
        with io_._quiet_native_output():
            with io_._quiet_native_output():  # nested, as _read_exr and _exr_open are
                assert _fd_id(1) != before[1] and _fd_id(2) != before[2]
                assert sys.stdout is not out and sys.stderr is not err
                os.write(1, b"written inside\n")
                raise Boom
    assert {fd: _fd_id(fd) for fd in (1, 2)} == before
    assert sys.stdout is out and sys.stderr is err
    assert no_._quiet_users == 0 and no_._quiet_window is None
    exr = next(p for p in _corrupt_files(tmp_path) if p.suffix == ".exr")
    with pytest.raises(ImageReadError, match="mid.exr"):  # raised inside the hiding
        read_image(exr)
    assert {fd: _fd_id(fd) for fd in (1, 2)} == before
    assert sys.stdout is out and sys.stderr is err and no_._quiet_users == 0
    print("printed after")
    assert capfd.readouterr().out == "written inside\nprinted after\n"


def test_partial_lines_pass_at_once_and_a_full_pipe_does_not_block(capfd):
    """A line without its newline is forwarded while the read still runs (a progress bar's
    ``\\r`` update); megabytes written meanwhile neither block the writer nor lose a byte."""
    from facegeo.capture import imageio as io_

    big = b"".join(b"%07d\n" % i for i in range(400_000))  # 3.2 MB, more than a pipe holds
    with io_._quiet_native_output():
        os.write(1, b"\r50% done")
        seen, deadline = "", time.monotonic() + 30
        while "50% done" not in seen and time.monotonic() < deadline:
            seen += capfd.readouterr().out
            time.sleep(0.01)
        assert seen == "\r50% done"

        def write_all():
            view = memoryview(big)
            while view:
                view = view[os.write(2, view):]

        t = threading.Thread(target=write_all, daemon=True)
        t.start()
        t.join(60)
        assert not t.is_alive()  # the pipe was drained as it filled
        os.write(2, b"tail without newline")
    assert capfd.readouterr().err == big.decode() + "tail without newline"


@pytest.mark.parametrize("closed", [1, 2])
def test_a_closed_stdout_or_stderr_stays_closed_and_reads_work(tmp_path, closed):
    exr = next(p for p in _corrupt_files(tmp_path) if p.suffix == ".exr")
    good = write_image(tmp_path / "good.png", _rng().integers(0, 255, (5, 7, 3), dtype=np.uint8))
    code = (
        "import os, sys\n"
        "from facegeo.capture.imageio import read_image, ImageReadError\n"
        "closed, other = int(sys.argv[1]), 3 - int(sys.argv[1])\n"
        "os.close(closed)\n"
        "try:\n"
        "    read_image(sys.argv[2])\n"
        "except ImageReadError as e:\n"
        "    os.write(other, b'error: mid.exr\\n' if 'mid.exr' in str(e) else b'?\\n')\n"
        "os.write(other, b'shape: %r\\n' % (read_image(sys.argv[3]).shape,))\n"
        "try:\n"
        "    os.fstat(closed)\n"
        "except OSError:\n"
        "    os.write(other, b'still closed\\n')\n"
    )
    r = subprocess.run([sys.executable, "-c", code, str(closed), str(exr), str(good)],
                       capture_output=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert (r.stderr if closed == 1 else r.stdout) == (
        b"error: mid.exr\nshape: (5, 7, 3)\nstill closed\n")


def test_descriptors_forwarded_by_a_thread_each_where_pipes_cannot_be_selected(capfd,
                                                                                monkeypatch):
    """The Windows path (no ``select`` on pipes): the same sorting, one blocking thread per
    pipe; restoring does not wait for them (it cannot tell whether they are done)."""
    from facegeo.capture import _native_output as no_, imageio as io_

    monkeypatch.setattr(no_, "_PIPES_SELECTABLE", False)
    monkeypatch.setattr(no_, "_pump", None)  # a pump of that kind, for this test only
    with io_._quiet_native_output():
        assert len(no_._pump.threads) == 2
        os.write(2, b"x.exr: (EXR_ERR_BAD_CHUNK_LEADER) Preparing to read scanline 32\n")
        os.write(2, b"user line\n")
        os.write(1, b"partial")
    out, err, deadline = "", "", time.monotonic() + 30
    while (out, err) != ("partial", "user line\n") and time.monotonic() < deadline:
        got = capfd.readouterr()
        out, err = out + got.out, err + got.err
        time.sleep(0.01)
    assert (out, err) == ("partial", "user line\n")


def test_a_child_process_started_during_a_read_keeps_its_output(capfd):
    """It inherits the pipe behind fd 1; what it prints after the read ended still arrives."""
    from facegeo.capture import imageio as io_

    with io_._quiet_native_output():
        child = subprocess.Popen([sys.executable, "-c",
                                  "import time; time.sleep(0.2); print('child, late')"])
    assert child.wait(60) == 0
    out, deadline = "", time.monotonic() + 30
    while "child, late" not in out and time.monotonic() < deadline:
        out += capfd.readouterr().out
        time.sleep(0.01)
    assert out == "child, late\n"


def test_a_descriptor_someone_else_redirects_meanwhile_is_left_to_them(capfd):
    """``facegeo``'s broken-pipe handling points stdout at /dev/null, possibly while a read
    runs on another thread: restoring must not put the broken pipe back."""
    from facegeo.capture import imageio as io_

    before = _fd_id(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        with io_._quiet_native_output():
            os.dup2(devnull, 1)
        assert _fd_id(1) == _fd_id(devnull) != before
    finally:
        os.close(devnull)
    os.write(1, b"lost to /dev/null\n")
    assert capfd.readouterr().out == ""


def test_noise_patterns_do_not_take_facegeos_own_messages(tmp_path):
    """Our errors may quote a library's message; a user printing them must see them."""
    from facegeo.capture import _native_output as no_

    ours = [str(ImageReadError("cannot read OpenEXR pixel data (truncated or corrupt file: "
                               "x.exr: (EXR_ERR_BAD_CHUNK_LEADER) bad)", path=tmp_path / "x.exr")),
            "facegeo: error: a.png: cannot decode .png image (truncated, corrupt, or not PNG)",
            "Warning: 3 frames are saturated", "[ WARN ] progress", ""]
    assert [ln for ln in ours if no_._NOISE_RE.search(ln)] == []
    assert all(no_._NOISE_RE.search(ln) for ln in (
        "/a/b.exr: (EXR_ERR_BAD_CHUNK_LEADER) Preparing to read scanline 32 (chunk 2)",
        "Warning: Exception raised reading pixel data for part 0 - Unable to query scanline",
        "libpng error: bad adaptive filter value",
        "Corrupt JPEG data: 563 extraneous bytes before marker 0xd9",
        "[ WARN:0@0.021] global grfmt_png.cpp:793 readFromStreamOrBuffer PNG input buffer is",
        "[ERROR:0@0.022] global loadsave.cpp:1390 imdecode_ imdecode_(''): can't read data"))


def test_a_descriptor_saved_during_a_read_and_put_back_after_does_not_loop(capfd):
    """The dup / dup2 idiom around a read leaves fd 1 on the readers' pipe after it ends; the
    next read must keep sending lines to the real stdout (it took the pipe for the
    destination: the pump wrote its own output back into the pipe, spinning, and everything
    printed after was lost)."""
    from facegeo.capture import _native_output as no_

    with no_._quiet_native_output():
        saved = os.dup(1)  # a user silencing fd 1 meanwhile ...
    os.dup2(saved, 1)  # ... and putting it back after the read: fd 1 is now the pipe
    os.close(saved)
    with no_._quiet_native_output():
        os.write(1, b"during the next read\n")
    os.write(1, b"after it\n")
    print("printed after", flush=True)
    deadline = time.monotonic() + 10
    out = ""
    while time.monotonic() < deadline and "printed after" not in out:
        out += capfd.readouterr().out
        time.sleep(0.01)
    assert out.splitlines() == ["during the next read", "after it", "printed after"]


def _run_python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60)


def test_a_child_forked_during_a_read_writes_to_the_real_stdout():
    """A child forked while a read is open (multiprocessing with fork beside read-ahead
    threads) writes to the process's real stdout, not into the parent's pipe that nothing in
    the child drains (its output was lost once the parent exited)."""
    r = _run_python(
        "import os, time\n"
        "from facegeo.capture import _native_output as no_\n"
        "with no_._quiet_native_output():\n"
        "    pid = os.fork()\n"
        "    if pid == 0:\n"
        "        time.sleep(0.5)\n"  # the parent is gone by then
        "        os.write(1, b'child done\\n')\n"
        "        with no_._quiet_native_output():\n"  # the child's own reads work
        "            os.write(1, b'child read\\n')\n"
        "        os._exit(0)\n"
        "print('parent done', flush=True)\n")
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == ["parent done", "child done", "child read"]


def test_lines_printed_while_a_read_is_open_at_exit_are_not_lost():
    """A read still open when the interpreter exits (a daemon thread inside one): what was
    printed meanwhile reaches stdout / stderr (it was left in the pipe: 0–2 of 5 lines
    arrived, the stderr line never)."""
    r = _run_python(
        "import os, threading, time\n"
        "from facegeo.capture import _native_output as no_\n"
        "inside = threading.Event()\n"
        "def reader():\n"
        "    with no_._quiet_native_output():\n"
        "        inside.set()\n"
        "        time.sleep(30)\n"
        "threading.Thread(target=reader, daemon=True).start()\n"
        "inside.wait(10)\n"
        "for i in range(5):\n"
        "    print(f'line {i}')\n"
        "os.write(2, b'err line\\n')\n")
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == [f"line {i}" for i in range(5)]
    assert r.stderr == "err line\n"


def test_exr_noise_is_hidden_whatever_the_path():
    """OpenEXR's own line names the file first; a path with parentheses (``scan (2)``) is
    still noise, facegeo's message quoting one is not."""
    from facegeo.capture import _native_output as no_

    assert no_._NOISE_RE.search("/tmp/scan (2)/mid.exr: (EXR_ERR_BAD_CHUNK_LEADER) Preparing "
                                "to read scanline 32")
    assert not no_._NOISE_RE.search(
        "/tmp/scan (2)/mid.exr: cannot read OpenEXR pixel data (truncated or corrupt file: "
        "/tmp/scan (2)/mid.exr: (EXR_ERR_BAD_CHUNK_LEADER) bad)")
