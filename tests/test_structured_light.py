"""Tests for facegeo.geometry.structured_light: patterns, Gray / phase decoding, real captures.

Metrics are stated with each assertion: exact-integer fractions over lit pixels, RMS in
projector pixels, neighbour-pair fractions on the real captures.
"""

from __future__ import annotations

import json
import tomllib

import numpy as np
import pytest

from facegeo.errors import InputError, ShapeError
from facegeo.geometry.structured_light import (
    PatternSpec,
    decode_gray,
    decode_phase,
    gray_decode,
    gray_encode,
    pattern_image,
    pattern_names,
    pattern_value_at,
    unwrap_with_gray,
)

cv2 = pytest.importorskip("cv2")

# ---------------------------------------------------------------- named tolerances (units)
EXACT_FRACTION_MIN = 0.999  # fraction of lit pixels decoded to the exact projector integer
SHADOW_AGREEMENT_MIN = 0.999  # fraction of pixels whose shadow flag matches the truth
PHASE_RMS_NOISELESS_PX = 1e-3  # RMS |x_unwrapped - x_true|, projector pixels, no noise
PHASE_RMS_NOISY_PX = 0.05  # same with sigma = 0.003 additive noise, albedo 0.1 .. 1
MANNEQUIN_MONOTONE_MIN = 0.99  # measured 0.997 (x along rows) / 0.997 (y down columns)
MANNEQUIN_REFERENCE_AGREE_MIN = 0.94  # measured 0.967 (x) / 0.959 (y), within one 8-px stripe
FACE_SMOOTH_MIN = 0.98  # measured 0.994 / 0.995: |wrapped step| < 0.5 rad between neighbours
FACE_REL_MODULATION_MEDIAN_MIN = 0.6  # measured 0.78 (B / A on the face)

# Asymmetric, non-power-of-two projector so swapped axes or bit orders cannot pass by symmetry.
PROJ_W, PROJ_H = 200, 120  # 8 column bits, 7 row bits
CAM_H, CAM_W = 150, 210


# ---------------------------------------------------------------- synthetic scene


def _true_q_proj(shape=(CAM_H, CAM_W)) -> np.ndarray:
    """A smooth camera -> projector warp, (H, W, 2) float64 projector pixels."""
    y, x = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    qx = 0.95 * x - 3.0 + 4.0 * np.sin(y / 17.0) + 0.0004 * x * y
    qy = 0.80 * y + 0.05 * x - 2.0 + 3.0 * np.cos(x / 29.0)
    return np.stack([qx, qy], axis=-1)


def _scene(spec: PatternSpec, *, noise=0.003, seed=7, ambient=0.03):
    """Camera frames of a Lambertian scene lit by ``spec``'s patterns (+ ambient, + noise).

    Returns frames, q_true (H, W, 2), lit (H, W) bool, albedo (H, W).
    """
    rng = np.random.default_rng(seed)
    q = _true_q_proj()
    y, x = np.mgrid[0:CAM_H, 0:CAM_W]
    occluded = (x - 120.0) ** 2 + (y - 70.0) ** 2 < 18.0**2  # an object shadowing the projector
    inside = (
        (q[..., 0] >= -0.5) & (q[..., 0] < spec.width - 0.5)
        & (q[..., 1] >= -0.5) & (q[..., 1] < spec.height - 0.5)
    )
    lit = inside & ~occluded
    albedo = 0.1 + 0.9 * (0.5 + 0.5 * np.sin(x / 13.0) * np.cos(y / 9.0)) * rng.uniform(
        0.6, 1.0, (CAM_H, CAM_W)
    )
    frames = {}
    for name in pattern_names(spec):
        light = np.where(occluded, 0.0, pattern_value_at(spec, name, q))
        img = albedo * (ambient + light) + rng.normal(0.0, noise, albedo.shape)
        frames[name] = img.astype(np.float32)
    return frames, q, lit, albedo


def _expected_proj(q: np.ndarray, spec: PatternSpec, axis: str) -> np.ndarray:
    c = np.floor(q[..., 0 if axis == "x" else 1] + 0.5)
    s = spec.stripe_shift(axis)
    return np.floor(c / 2**s) * 2**s + 0.5 * (2**s - 1)


# ---------------------------------------------------------------- Gray code


def test_gray_round_trip_all_12_bit_integers():
    n = np.arange(1 << 12)
    g = gray_encode(n)
    assert np.array_equal(gray_decode(g), n)
    assert np.array_equal(gray_encode(np.arange(8)), [0, 1, 3, 2, 6, 7, 5, 4])
    # Neighbouring codes differ in exactly one bit (the Gray property).
    flips = np.bitwise_xor(g[1:], g[:-1])
    assert np.all(flips & (flips - 1) == 0) and np.all(flips > 0)
    assert gray_decode(np.uint16(0xFFFF)).dtype == np.uint16
    with pytest.raises(InputError, match="non-negative"):
        gray_encode([-1, 2])
    with pytest.raises(InputError, match="integers"):
        gray_decode([0.5])


# ---------------------------------------------------------------- spec and names


def test_spec_defaults_round_trip_and_toml():
    spec = PatternSpec(1000, 768, phase_steps=4, phase_axes=("x", "y"))
    assert (spec.n_bits_x, spec.n_bits_y) == (10, 10)
    assert spec.phase_periods_x == 1000 / 16 and spec.phase_periods_y == 48.0
    d = spec.to_dict()
    assert d["phase_axes"] == ["x", "y"] and isinstance(d["width"], int)
    assert PatternSpec.from_dict(json.loads(json.dumps(d))) == spec
    tomli_w = pytest.importorskip("tomli_w")
    assert PatternSpec.from_dict(tomllib.loads(tomli_w.dumps(d))) == spec
    plain = PatternSpec(64, 48)
    assert "phase_periods_x" not in plain.to_dict()  # None is omitted (TOML has no null)
    assert PatternSpec.from_dict(plain.to_dict()) == plain


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"width": 0, "height": 4}, "width"),
        ({"width": 1.5, "height": 4}, "width.*integer"),
        ({"width": True, "height": 4}, "width"),
        ({"width": 8, "height": 4, "n_bits_x": 30}, "n_bits_x"),
        ({"width": 8, "height": 4, "phase_steps": 2}, "phase_steps"),
        ({"width": 8, "height": 4, "phase_steps": 3, "phase_axes": ("z",)}, "phase_axes"),
        ({"width": 8, "height": 4, "phase_steps": 3, "phase_axes": ("x", "x")}, "repeated"),
        ({"width": 64, "height": 4, "phase_steps": 3, "phase_periods_x": 40}, "2 px per period"),
        ({"width": 8, "height": 4, "phase_steps": 3, "phase_periods_x": float("nan")}, "finite"),
        ({"width": 8, "height": 4, "gray": False, "white_black": False}, "no pattern"),
        ({"width": 8, "height": 4, "inverse": "yes"}, "inverse"),
    ],
)
def test_spec_validation(kwargs, match):
    with pytest.raises(InputError, match=match):
        PatternSpec(**kwargs)


def test_spec_from_dict_rejects_unknown_and_missing_keys():
    with pytest.raises(InputError, match="unknown key.*'bits'.*valid keys"):
        PatternSpec.from_dict({"width": 8, "height": 4, "bits": 3})
    with pytest.raises(InputError, match="missing required key.*height"):
        PatternSpec.from_dict({"width": 8})


def test_pattern_names_order():
    spec = PatternSpec(8, 3, phase_steps=3, phase_axes=("y", "x"))
    assert pattern_names(spec) == [
        "white", "black",
        "gray_x_00", "gray_x_00_inv", "gray_x_01", "gray_x_01_inv", "gray_x_02", "gray_x_02_inv",
        "gray_y_00", "gray_y_00_inv", "gray_y_01", "gray_y_01_inv",
        "phase_y_0", "phase_y_1", "phase_y_2", "phase_x_0", "phase_x_1", "phase_x_2",
    ]
    bare = PatternSpec(8, 3, inverse=False, white_black=False, n_bits_y=0)
    assert pattern_names(bare) == ["gray_x_00", "gray_x_01", "gray_x_02"]
    with pytest.raises(InputError, match="unknown pattern 'gray_z_00'"):
        pattern_image(spec, "gray_z_00")


def test_pattern_images_values():
    spec = PatternSpec(PROJ_W, PROJ_H, phase_steps=3)
    col = np.arange(PROJ_W)
    for i in range(spec.n_bits_x):
        img = pattern_image(spec, f"gray_x_{i:02d}")
        assert img.shape == (PROJ_H, PROJ_W) and img.dtype == np.float32
        assert np.array_equal(img[5], (gray_encode(col) >> (7 - i)) & 1)  # MSB first
        assert np.all(img == img[0])  # column patterns are constant down each column
        assert np.array_equal(pattern_image(spec, f"gray_x_{i:02d}_inv"), 1 - img)
    row = np.arange(PROJ_H)
    assert np.array_equal(pattern_image(spec, "gray_y_00")[:, 3], (gray_encode(row) >> 6) & 1)
    ph = pattern_image(spec, "phase_x_1")[0]
    want = 0.5 + 0.5 * np.cos(2 * np.pi * 12.5 * (col + 0.5) / PROJ_W - 2 * np.pi / 3)
    assert np.max(np.abs(ph - want)) < 1e-6
    assert np.all(pattern_image(spec, "white") == 1) and np.all(pattern_image(spec, "black") == 0)


def test_pattern_value_at_matches_images_and_pixel_edges():
    spec = PatternSpec(PROJ_W, PROJ_H, n_bits_x=6, phase_steps=4, phase_axes=("x", "y"))
    yy, xx = np.mgrid[0:PROJ_H, 0:PROJ_W]
    rng = np.random.default_rng(3)
    # Any point inside a projector pixel's square sees that pixel's (hard-edged) value.
    jitter = rng.uniform(-0.5, 0.4999, (PROJ_H, PROJ_W, 2))
    q_centres = np.stack([xx, yy], -1).astype(np.float64)
    for name in pattern_names(spec):
        img = pattern_image(spec, name)
        at_centres = pattern_value_at(spec, name, q_centres)
        assert np.max(np.abs(at_centres - img)) < 1e-6, name
        if not name.startswith("phase"):
            assert np.array_equal(pattern_value_at(spec, name, q_centres + jitter), img), name
    # Outside the projector and NaN: no light. Edge x = -0.5 is inside, x = W - 0.5 outside.
    q = np.array([[-0.5, 3.0], [PROJ_W - 0.5, 3.0], [np.nan, 2.0], [5.0, -0.51], [0.4999, 0.0]])
    assert np.array_equal(pattern_value_at(spec, "white", q), [1, 0, 0, 0, 1])
    # Pixel boundary 2.5 belongs to pixel 3.
    spec2 = PatternSpec(8, 2)
    v = pattern_value_at(spec2, "gray_x_02", np.array([[2.4999, 0.0], [2.5, 0.0]]))
    assert np.array_equal(v, [(gray_encode(2) & 1), (gray_encode(3) & 1)])


# ---------------------------------------------------------------- OpenCV reference


@pytest.mark.parametrize("size", [(10, 6), (200, 120), (37, 100), (64, 48)])
def test_gray_frames_equal_opencv(size):
    """OpenCV's GrayCodePattern: columns then rows, MSB first, pattern then inverse, white = 1.

    That is exactly our order with inverse=True, white_black=False; an x/y swap or a reversed bit
    order makes this fail (the sizes are asymmetric and not powers of two).
    """
    w, h = size
    ok, cv_patterns = cv2.structured_light.GrayCodePattern.create(w, h).generate()
    assert ok
    spec = PatternSpec(w, h, inverse=True, white_black=False)
    names = pattern_names(spec)
    assert len(names) == len(cv_patterns)
    for name, cv_img in zip(names, cv_patterns):
        assert cv_img.shape == (h, w)
        assert np.array_equal(pattern_image(spec, name), cv_img / 255.0), name
    # The reversed bit order and the transposed spec really differ (the test has teeth).
    lsb_first = pattern_image(spec, f"gray_x_{spec.n_bits_x - 1:02d}")
    assert not np.array_equal(lsb_first, cv_patterns[0] / 255.0)
    black, white = cv2.structured_light.GrayCodePattern.create(w, h).getImagesForShadowMasks(
        np.zeros((h, w), np.uint8), np.zeros((h, w), np.uint8)
    )
    spec_wb = PatternSpec(w, h)
    assert np.array_equal(pattern_image(spec_wb, "white"), white / 255.0)
    assert np.array_equal(pattern_image(spec_wb, "black"), black / 255.0)


def test_decode_agrees_with_opencv_getprojpixel():
    spec = PatternSpec(PROJ_W, PROJ_H, inverse=True, white_black=False)
    frames, q, lit, _ = _scene(spec, noise=0.0)
    dec = decode_gray(frames, spec)
    cv_imgs = [np.clip(frames[n] * 255.0, 0, 255).astype(np.uint8) for n in pattern_names(spec)]
    gcp = cv2.structured_light.GrayCodePattern.create(PROJ_W, PROJ_H)
    rng = np.random.default_rng(11)
    rows, cols = np.nonzero(lit & dec.valid)
    pick = rng.choice(rows.size, 300, replace=False)
    agree = checked = 0
    for r, c in zip(rows[pick], cols[pick]):
        err, (px, py) = gcp.getProjPixel(cv_imgs, int(c), int(r))
        if err:  # OpenCV found a bit below its white threshold; not a comparison
            continue
        checked += 1
        agree += (px, py) == (dec.proj_x[r, c], dec.proj_y[r, c])
    assert checked >= 250 and agree == checked, f"{agree}/{checked} pixels agree with OpenCV"


# ---------------------------------------------------------------- synthetic decode


@pytest.mark.parametrize(
    "kwargs",
    [
        {"inverse": True, "white_black": True},
        {"inverse": False, "white_black": True},  # threshold (white + black) / 2
        {"inverse": True, "white_black": False},  # OpenCV's set
        {"inverse": False, "white_black": False},  # per-pixel (max + min) / 2
        {"inverse": True, "white_black": True, "n_bits_x": 6, "n_bits_y": 5},  # 4-px stripes
    ],
    ids=["inv+wb", "wb", "inv", "bare", "coarse"],
)
def test_decode_gray_synthetic(kwargs):
    spec = PatternSpec(PROJ_W, PROJ_H, **kwargs)
    frames, q, lit, albedo = _scene(spec)
    dec = decode_gray(frames, spec)
    for a in (dec.proj_x, dec.proj_y):
        assert a.shape == (CAM_H, CAM_W) and a.dtype == np.float64
    ex, ey = _expected_proj(q, spec, "x"), _expected_proj(q, spec, "y")
    exact = (dec.proj_x == ex) & (dec.proj_y == ey)
    frac = exact[lit].mean()
    assert frac >= EXACT_FRACTION_MIN, f"exact decode on {frac:.5f} of lit pixels"
    # Valid pixels are right (no confident wrong codes), invalid ones are NaN.
    assert exact[dec.valid].mean() >= EXACT_FRACTION_MIN
    assert np.all(np.isnan(dec.proj_x[~dec.valid])) and np.all(np.isnan(dec.proj_y[~dec.valid]))
    # Shadow: unlit (outside the projector or occluded) pixels flagged, lit ones not.
    agree = (dec.shadow == ~lit).mean()
    assert agree >= SHADOW_AGREEMENT_MIN, f"shadow mask agrees on {agree:.5f} of pixels"
    assert not np.any(dec.valid & ~lit)
    if spec.inverse:  # |frame - inverse| = albedo for a fully lit / dark bit pair
        err = np.abs(dec.contrast[lit] - albedo[lit])
        assert np.median(err) < 0.01, f"median |contrast - albedo| {np.median(err):.4f}"


def test_decode_gray_colour_frames_and_integer_frames():
    spec = PatternSpec(PROJ_W, PROJ_H, white_black=False)
    frames, q, lit, _ = _scene(spec, noise=0.0)
    grey = decode_gray(frames, spec)
    tint = np.array([0.7, 1.0, 0.4], np.float32)
    colour = decode_gray({n: f[..., None] * tint for n, f in frames.items()}, spec,
                         min_contrast=0.005)
    assert np.array_equal(colour.proj_x[lit], grey.proj_x[lit])
    u16 = {n: np.round(f * 60000).clip(0, 65535).astype(np.uint16) for n, f in frames.items()}
    dec16 = decode_gray(u16, spec, min_contrast=0.01 * 60000 / 65535)  # thresholds: full scale
    assert np.array_equal(dec16.proj_y[lit], grey.proj_y[lit])
    same = decode_gray(u16, spec, full_scale=60000)  # the float frames' white level
    assert np.array_equal(same.shadow, grey.shadow), "full_scale=60000 reads u16 as the floats"


@pytest.mark.parametrize("spec_kw", [{}, {"inverse": False}, {"inverse": False,
                                                             "white_black": False}],
                         ids=["inverse", "white_black", "minmax"])
def test_integer_and_float_frames_decode_identically(spec_kw):
    """The same frames as uint8, uint16 (= uint8 · 257) and float32 (= uint8 / 255) give the
    same codes, the same valid mask and the same non-trivial shadow mask: thresholds are
    fractions of full scale for every dtype (they used to be absolute, so integer frames got
    no shadow mask)."""
    spec = PatternSpec(PROJ_W, PROJ_H, **spec_kw)
    frames, q, lit, _ = _scene(spec, noise=0.002)
    u8 = {n: np.round(np.clip(f, 0, 1) * 255).astype(np.uint8) for n, f in frames.items()}
    u16 = {n: f.astype(np.uint16) * np.uint16(257) for n, f in u8.items()}
    f32 = {n: f.astype(np.float32) / np.float32(255) for n, f in u8.items()}
    d8, d16, df = (decode_gray(fr, spec) for fr in (u8, u16, f32))
    assert df.shadow.any() and (~df.shadow).any(), "the scene has shadow and lit pixels"
    assert (df.shadow == ~lit).mean() > 0.9, "the float decode's shadow mask is the real one"
    for name, d in (("uint8", d8), ("uint16", d16)):
        assert np.array_equal(d.shadow, df.shadow), f"{name}: same shadow mask as float32"
        assert np.array_equal(d.valid, df.valid), f"{name}: same valid mask as float32"
        assert np.array_equal(d.proj_x, df.proj_x, equal_nan=True), f"{name}: same columns"
        assert np.array_equal(d.proj_y, df.proj_y, equal_nan=True), f"{name}: same rows"
        assert np.abs(d.contrast - df.contrast).max() < 1e-6, f"{name}: contrast, full scale"
    with pytest.raises(InputError, match="full_scale"):
        decode_gray(u8, spec, full_scale=0)


def test_decode_gray_fixed_threshold_and_single_axis():
    spec = PatternSpec(PROJ_W, PROJ_H, n_bits_y=0, inverse=False, white_black=False)
    frames, q, lit, albedo = _scene(spec, noise=0.0, ambient=0.0)
    bright = lit & (albedo > 0.3)
    dec = decode_gray(frames, spec, threshold=0.1)
    assert np.all(np.isnan(dec.proj_y))  # no row bits: rows unknown, not 0
    assert (dec.proj_x[bright] == _expected_proj(q, spec, "x")[bright]).mean() >= 0.999
    with pytest.raises(InputError, match="inverse"):
        decode_gray(frames, PatternSpec(PROJ_W, PROJ_H), threshold=0.5)


# ---------------------------------------------------------------- phase shift


@pytest.mark.parametrize("steps", [3, 4])
@pytest.mark.parametrize("axis", ["x", "y"])
def test_phase_decode_and_unwrap_subpixel(steps, axis):
    spec = PatternSpec(PROJ_W, PROJ_H, phase_steps=steps, phase_axes=("x", "y"))
    k = 0 if axis == "x" else 1
    rms = {}
    for noise in (0.0, 0.003):
        frames, q, lit, albedo = _scene(spec, noise=noise)
        gd = decode_gray(frames, spec)
        wrapped, modulation = decode_phase(frames, spec, axis)
        assert wrapped.shape == (CAM_H, CAM_W) and modulation.dtype == np.float32
        ok = lit & gd.valid
        assert np.all((wrapped[ok] >= 0) & (wrapped[ok] < 2 * np.pi))
        # The fringe amplitude is albedo * 0.5 (patterns span 0 .. 1).
        assert np.median(np.abs(modulation[ok] - 0.5 * albedo[ok])) < 0.01
        coarse = gd.proj_x if axis == "x" else gd.proj_y
        fine = unwrap_with_gray(wrapped, coarse, spec, axis=axis)
        assert np.all(np.isnan(fine[~gd.valid]))
        err = fine[ok] - q[..., k][ok]
        rms[noise] = float(np.sqrt(np.mean(err**2)))
        if noise == 0.0:  # the sub-pixel position lies in the Gray-decoded projector pixel
            assert np.max(np.abs(fine[ok] - coarse[ok])) <= 0.5 + 1e-6
    assert rms[0.0] < PHASE_RMS_NOISELESS_PX, f"noiseless RMS {rms[0.0]:.2e} px"
    assert rms[0.003] < PHASE_RMS_NOISY_PX, f"noisy RMS {rms[0.003]:.4f} px"


def test_decode_phase_errors():
    spec = PatternSpec(PROJ_W, PROJ_H, phase_steps=3)
    frames, *_ = _scene(spec, noise=0.0)
    with pytest.raises(InputError, match="no phase-shift patterns on axis 'y'"):
        decode_phase(frames, spec, "y")
    with pytest.raises(InputError, match="no phase-shift"):
        decode_phase(frames, PatternSpec(PROJ_W, PROJ_H), "x")
    del frames["phase_x_2"]
    with pytest.raises(InputError, match=r"missing 1 frame.*\['phase_x_2'\]"):
        decode_phase(frames, spec, "x")
    wrapped = np.zeros((4, 5))
    with pytest.raises(ShapeError, match="coarse_proj"):
        unwrap_with_gray(wrapped, np.zeros((5, 4)), spec)


# ---------------------------------------------------------------- bad input


def _small_frames(spec):
    return {n: np.full((6, 7), 0.5, np.float32) for n in pattern_names(spec)}


def test_decode_gray_missing_frames_listed():
    spec = PatternSpec(16, 8)
    frames = _small_frames(spec)
    for n in ("black", "gray_x_02_inv", "gray_y_01"):
        del frames[n]
    with pytest.raises(InputError, match="missing 3 frame") as exc:
        decode_gray(frames, spec)
    for n in ("'black'", "'gray_x_02_inv'", "'gray_y_01'"):
        assert n in str(exc.value)


def test_decode_gray_mismatched_shapes_and_bad_types():
    spec = PatternSpec(16, 8)
    frames = _small_frames(spec)
    frames["gray_y_00"] = np.zeros((6, 8), np.float32)
    with pytest.raises(ShapeError, match=r"gray_y_00.*\(6, 8\).*\(6, 7\)"):
        decode_gray(frames, spec)
    frames = _small_frames(spec)
    frames["white"] = np.zeros(7, np.float32)
    with pytest.raises(ShapeError, match=r"'white'.*\(H, W\)"):
        decode_gray(frames, spec)
    with pytest.raises(InputError, match="mapping"):
        decode_gray(list(_small_frames(spec).values()), spec)
    with pytest.raises(InputError, match="PatternSpec"):
        decode_gray(_small_frames(spec), {"width": 16, "height": 8})
    with pytest.raises(InputError, match="no Gray-code"):
        decode_gray(_small_frames(spec), PatternSpec(16, 8, gray=False))


@pytest.mark.parametrize("name", ["white", "gray_x_03", "gray_y_02_inv"])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
@pytest.mark.parametrize("kwargs", [{}, {"inverse": False, "white_black": False}])
def test_decode_gray_nonfinite_frames(name, bad, kwargs):
    spec = PatternSpec(16, 8, **kwargs)
    frames = _small_frames(spec)
    if name not in frames:
        name = "gray_y_02"
    frames[name] = frames[name].copy()
    frames[name][4, 2] = bad
    with pytest.raises(InputError, match=rf"frames\['{name}'\].*non-finite.*row 4, column 2"):
        decode_gray(frames, spec)


# ---------------------------------------------------------------- real captures


def shared_file(shared_data, rel: str):
    """A file under the shared data folder; skips with a reason when it is missing."""
    p = shared_data / rel
    if not p.exists():
        pytest.skip(f"shared data file {p} is absent")
    return p


def _srgb_to_linear(u8: np.ndarray) -> np.ndarray:
    c = u8.astype(np.float32) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


@pytest.mark.shared_data
def test_real_graycode_mannequin(shared_data):
    """18 JPEGs, no inverse / white / black: odd files row bits, even files column bits, MSB
    first (GrayDecoder.pde: level L = file L+1; even L -> y bit L/2, odd L -> x bit L/2).
    9 bits on a 1024 x 768 projector: 2-px stripes (the sketch's 4/3 factor on y says the row
    code spans 1024 virtual rows of which 768 exist).
    """
    spec = PatternSpec(1024, 768, n_bits_x=9, n_bits_y=9, inverse=False, white_black=False)
    frames, brightness = {}, {}
    for k in range(1, 19):
        p = shared_file(shared_data, f"structured_light/graycode_mannequin/{k}.jpg")
        bgr = cv2.imread(str(p))
        level = k - 1
        name = f"gray_{'y' if level % 2 == 0 else 'x'}_{level // 2:02d}"
        frames[name] = _srgb_to_linear(bgr[..., ::-1])
        brightness[name] = bgr.max(axis=2)  # Processing's brightness()
    dec = decode_gray(frames, spec)
    assert dec.proj_x.shape == (480, 640)
    valid_frac, lit_frac = dec.valid.mean(), (~dec.shadow).mean()
    assert 0.15 < valid_frac <= lit_frac < 0.5, (valid_frac, lit_frac)  # measured 0.22, 0.31

    # Smooth, monotone decode: projector x grows to the right, y downwards (wall and mannequin).
    dx = np.diff(dec.proj_x, axis=1)
    dy = np.diff(dec.proj_y, axis=0)
    mono_x = (dx[np.isfinite(dx)] >= 0).mean()
    mono_y = (dy[np.isfinite(dy)] >= 0).mean()
    assert mono_x >= MANNEQUIN_MONOTONE_MIN and mono_y >= MANNEQUIN_MONOTONE_MIN, (mono_x, mono_y)
    # Over 16 camera pixels (~50 projector px on the wall) x strictly increases.
    dx16 = dec.proj_x[:, 16:] - dec.proj_x[:, :-16]
    assert (dx16[np.isfinite(dx16)] > 0).mean() >= 0.98

    # Independent reference: the capture's own decoder (fixed cutoff 100 on max(R, G, B)).
    # The finest bits are below the camera's resolution (2 projector px ~ 0.6 camera px), so
    # compare within one 8-px stripe.
    def sketch_decode(axis):
        b = np.zeros((480, 640), bool)
        code = np.zeros((480, 640), np.int64)
        for i in range(9):
            b ^= brightness[f"gray_{axis}_{i:02d}"] > 100
            code = code * 2 + b
        return 2.0 * code + 0.5

    v = dec.valid
    for axis, mine in (("x", dec.proj_x), ("y", dec.proj_y)):
        agree = (np.abs(mine[v] - sketch_decode(axis)[v]) <= 8).mean()
        assert agree >= MANNEQUIN_REFERENCE_AGREE_MIN, f"{axis}: {agree:.4f} agree with the sketch"


@pytest.mark.shared_data
def test_real_face_threephase(shared_data):
    """Three-step phase shift on a real face, fringes along camera y (response unknown; the
    8-bit PNGs are linearised as sRGB). Face = mean linear intensity > 0.01, below the bright
    band in the top 20 rows."""
    spec = PatternSpec(640, 480, gray=False, white_black=False, phase_steps=3, phase_axes=("y",))
    frames = {}
    for k in range(3):
        p = shared_file(shared_data, f"structured_light/face_threephase/phase{k + 1}.png")
        frames[f"phase_y_{k}"] = _srgb_to_linear(cv2.imread(str(p))[..., ::-1])
    wrapped, modulation = decode_phase(frames, spec, "y")
    A = np.mean([f.mean(axis=-1) for f in frames.values()], axis=0)
    face = A > 0.01
    face[:20] = False
    assert 0.2 < face.mean() < 0.5  # measured 0.32
    rel = modulation / np.maximum(A, 1e-6)
    assert np.median(rel[face]) >= FACE_REL_MODULATION_MEDIAN_MIN, np.median(rel[face])
    assert np.percentile(rel[face], 5) >= 0.4  # measured 0.61
    dark = A == 0  # no light at all: no fringe
    assert dark.any() and np.all(modulation[dark] == 0)
    assert np.all(np.isfinite(wrapped[face]))
    assert np.all(np.isnan(wrapped[modulation == 0]))  # undefined phase is NaN, not 0

    def wrapped_step(a, b):
        return np.angle(np.exp(1j * (b - a)))

    sy = wrapped_step(wrapped[:-1], wrapped[1:])[face[:-1] & face[1:]]
    sx = wrapped_step(wrapped[:, :-1], wrapped[:, 1:])[face[:, :-1] & face[:, 1:]]
    smooth_y, smooth_x = (np.abs(sy) < 0.5).mean(), (np.abs(sx) < 0.5).mean()
    assert smooth_y >= FACE_SMOOTH_MIN and smooth_x >= FACE_SMOOTH_MIN, (smooth_y, smooth_x)
    # Fringes run along y: phase advances ~0.1 rad per row (period ~64 rows), little along x.
    assert 0.05 < np.median(sy) < 0.2 and abs(np.median(sx)) < 0.02
