"""Relighting from compressed fields: low-rank SVD and Haar wavelets (Ng et al. 2003) on a
synthetic all-frequency field (hard shadows, a sharp specular lobe), smooth and sun maps."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from facegeo.errors import InputError, ShapeError
from facegeo.frames import light_directions
from facegeo.lighting import compress as C
from facegeo.lighting import envmap as E
from facegeo.lighting.relight import relight_field

GRID = (32, 16)
#: Uncompressed (full-rank / zero-threshold) relighting vs direct Eq. (4): relative RMSE.
LOSSLESS_REL = 1e-5
#: Haar round trip: max |Δ| relative to max |x|.
HAAR_ROUNDTRIP = 1e-12


def _field(seed=0, n=300):
    rng = np.random.default_rng(seed)
    d = light_directions(*GRID)
    nrm = rng.normal(size=(n, 3))
    nrm[:, 2] = np.abs(nrm[:, 2]) + 0.5
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    cos = np.maximum(nrm @ d.T, 0)
    occ = rng.normal(size=(n, 3))
    occ /= np.linalg.norm(occ, axis=1, keepdims=True)
    vis = (d @ occ.T).T < rng.uniform(0.0, 0.6, size=(n, 1))  # hard-edged shadow caps
    view = np.array([0.0, 0.0, 1.0])
    refl = 2 * (nrm @ view)[:, None] * nrm - view
    spec = np.maximum(refl @ d.T, 0) ** 60
    albedo = rng.uniform(0.2, 0.9, size=(n, 1, 3))
    f = (albedo / np.pi * cos[..., None] + 0.3 * spec[..., None]) * vis[..., None]
    return f.astype(np.float32)


def _smooth_env():
    return E.analytic_map(lambda v: np.stack([1 + 0.5 * v[..., 1], 1 + 0.3 * v[..., 0],
                                              0.8 + 0.2 * v[..., 2]], -1), 64)


def _sun_env():
    sun = np.array([0.4, 0.6, 0.69])
    sun /= np.linalg.norm(sun)
    return E.analytic_map(lambda v: 0.2 + 2e3 * np.maximum(v @ sun, 0)[..., None] ** 3000
                          * np.array([1.0, 0.9, 0.8]), 128)


@pytest.fixture(scope="module")
def case():
    f = _field()
    ws = {name: E.light_stage_weights(env, *GRID, solid_angle="exact")
          for name, env in (("smooth", _smooth_env()), ("sun", _sun_env()))}
    return f, ws


def test_haar_round_trip_and_parseval():
    x = np.random.default_rng(1).normal(size=(5, GRID[0] * GRID[1]))
    c = C.haar2d(x, *GRID)
    assert np.max(np.abs(C.ihaar2d(c, *GRID) - x)) <= HAAR_ROUNDTRIP * np.abs(x).max()
    assert np.allclose((c ** 2).sum(1), (x ** 2).sum(1), rtol=1e-12)
    with pytest.raises(InputError, match="power of two"):
        C.haar2d(np.zeros(24), 6, 4)


def test_low_rank_full_rank_is_lossless(case):
    f, ws = case
    lr = C.fit_low_rank(f, rank=GRID[0] * GRID[1])
    for w in ws.values():
        assert C.relative_rmse(lr.relight(w), relight_field(f, w)) <= LOSSLESS_REL


def test_low_rank_target_error_and_held_out(case):
    f, ws = case
    lr = C.fit_low_rank(f, target_error=0.05)
    A = f.transpose(0, 2, 1).reshape(-1, f.shape[1]).astype(np.float64)
    approx = lr.U.astype(np.float64) @ lr.SVt.astype(np.float64)
    assert C.relative_rmse(approx, A) <= 0.05
    smaller = C.fit_low_rank(f, rank=lr.rank - 1)
    assert C.relative_rmse(smaller.U.astype(float) @ smaller.SVt.astype(float), A) > 0.05
    # smooth lighting is easy for a low-rank basis; the sun is not
    e_smooth = C.relative_rmse(lr.relight(ws["smooth"]), relight_field(f, ws["smooth"]))
    e_sun = C.relative_rmse(lr.relight(ws["sun"]), relight_field(f, ws["sun"]))
    assert e_smooth <= 0.01 and e_sun > e_smooth
    # held-out lights: the error falls with rank
    errs = C.held_out_error(f, [4, 32, 128])
    assert errs[1] == C.held_out_error(f, 32)
    assert errs[0] > errs[1] > errs[2]


def test_wavelet_lossless_and_target(case):
    f, ws = case
    exact = C.fit_wavelet(f, *GRID, target_error=0.0)
    for w in ws.values():
        assert C.relative_rmse(exact.relight(w), relight_field(f, w)) <= LOSSLESS_REL
    wf = C.fit_wavelet(f, *GRID, target_error=0.02)
    assert wf.kept_fraction < 0.5
    for name, w in ws.items():
        err = C.relative_rmse(wf.relight(w), relight_field(f, w))
        assert err <= 0.02, (name, err)


def test_wavelet_beats_low_rank_on_the_sun_at_equal_storage(case):
    f, ws = case
    wf = C.fit_wavelet(f, *GRID, target_error=0.02)
    k = max(1, int(wf.nbytes / (4 * (3 * f.shape[0] + f.shape[1]))))  # same bytes
    lr = C.fit_low_rank(f, rank=k)
    ref = relight_field(f, ws["sun"])
    assert C.relative_rmse(wf.relight(ws["sun"]), ref) < C.relative_rmse(lr.relight(ws["sun"]), ref)


def test_bad_input():
    with pytest.raises(ShapeError, match=r"\(P, L, 3\)"):
        C.fit_low_rank(np.zeros((4, 8)), rank=2)
    with pytest.raises(InputError, match="exactly one"):
        C.fit_low_rank(np.zeros((4, 8, 3), np.float32))
    with pytest.raises(ShapeError, match="expected shape"):
        C.fit_wavelet(np.zeros((4, 8, 3), np.float32), 4, 4)


def test_low_rank_truncation_equals_a_lower_rank_fit(case):
    f, ws = case
    full = C.fit_low_rank(f, rank=64)
    a = full.truncated(16).relight(ws["smooth"])
    b = C.fit_low_rank(f, rank=16).relight(ws["smooth"])
    assert C.relative_rmse(a, b) <= LOSSLESS_REL


# --------------------------------------------------------------------------- Ng et al. 2003

#: Relighting from all L coefficient slabs vs direct Eq. (4) on the float32 field: relative
#: RMSE; the slabs are float16 (11 significant bits), so ≈ 2^-11 / √(terms summed) and below.
FLOAT16_SLABS_REL = 1e-3


def test_nonstandard_haar_round_trip_parseval_and_point_light_sparsity():
    x = np.random.default_rng(3).normal(size=(4, GRID[0] * GRID[1]))
    c = C.haar2d_nonstandard(x, *GRID)
    back = C.haar2d_nonstandard(c, *GRID, inverse=True)
    assert np.max(np.abs(back - x)) <= HAAR_ROUNDTRIP * np.abs(x).max()
    assert np.allclose((c ** 2).sum(1), (x ** 2).sum(1), rtol=1e-12)
    # a point light: 3 details per 2-D level (4 levels on 32 × 16), 1 θ-only detail, 1 average
    delta = np.zeros(GRID[0] * GRID[1])
    delta[GRID[0] * 5 + 11] = 1.0
    nnz = np.count_nonzero(np.abs(C.haar2d_nonstandard(delta, *GRID)) > 1e-12)
    assert nnz == 3 * 4 + 2 < np.count_nonzero(np.abs(C.haar2d(delta, *GRID)) > 1e-12)


def test_wavelet_lighting_all_terms_is_eq4_and_k_terms_is_the_truncated_lighting(case):
    # All L terms: direct Eq. (4) up to the float16 slabs. K terms: exactly relighting with
    # the lighting whose non-standard Haar expansion keeps its K largest coefficients (the
    # non-linear approximation), computed independently by inverse transform + direct Eq. (4).
    f, ws = case
    wl = C.fit_wavelet_lighting(f, *GRID)
    for w in ws.values():
        assert C.relative_rmse(wl.relight(w), relight_field(f, w)) <= FLOAT16_SLABS_REL
    w = ws["sun"]
    wc = C.haar2d_nonstandard(w.T, *GRID).T
    k = 20
    keep = np.argsort(-np.abs(wc).sum(1), kind="stable")[:k]
    trunc = np.zeros_like(wc)
    trunc[keep] = wc[keep]
    w_k = C.haar2d_nonstandard(trunc.T, *GRID, inverse=True).T
    ref = relight_field(f, w_k)
    assert C.relative_rmse(wl.relight(w, terms=k), ref) <= FLOAT16_SLABS_REL
    assert C.relative_rmse(ref, relight_field(f, w)) > 10 * FLOAT16_SLABS_REL  # K matters


def test_wavelet_lighting_budget_meets_the_target_with_few_terms(case):
    # Budget from a target error (validation pixels = all 300 here, so the estimate is the
    # error): the relit error with the chosen K is within BUDGET_MARGIN · target (plus the
    # float16 slabs' error), one term fewer is not, and the sun needs ≤ 5 % of the lights'
    # coefficients (Ng et al.'s all-frequency claim).
    f, ws = case
    wl = C.fit_wavelet_lighting(f, *GRID, validation_pixels=1000)
    n_l = GRID[0] * GRID[1]
    aim = C.BUDGET_MARGIN * 0.01
    for name, w in ws.items():
        ref = relight_field(f, w)
        k, est = wl.budget(w, 0.01)
        assert est <= aim
        assert C.relative_rmse(wl.relight(w, target_error=0.01), ref) <= aim + FLOAT16_SLABS_REL
        assert C.relative_rmse(wl.relight(w, terms=k - 1), ref) > aim - FLOAT16_SLABS_REL
        if name == "sun":
            assert k <= 0.05 * n_l, k


def test_wavelet_lighting_numpy_fallback_equals_the_kernel(case, monkeypatch):
    pytest.importorskip("numba")
    import facegeo.lighting.relight as RL

    f, ws = case
    wl = C.fit_wavelet_lighting(f, *GRID)
    a = wl.relight(ws["smooth"], terms=37)
    monkeypatch.setattr(RL, "_fused_kernel", lambda conversion=None: False)
    b = wl.relight(ws["smooth"], terms=37)
    assert C.relative_rmse(a, b) <= 1e-6  # float32 summation order only


def test_wavelet_lighting_bad_input(case):
    f, ws = case
    wl = C.fit_wavelet_lighting(f, *GRID)
    with pytest.raises(InputError, match="terms"):
        wl.relight(ws["sun"], terms=0)
    with pytest.raises(InputError, match="not both"):
        wl.relight(ws["sun"], terms=3, target_error=0.01)
    with pytest.raises(ShapeError, match="weights"):
        wl.relight(np.ones((7, 3)))
    bad = f.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        C.fit_wavelet_lighting(bad, *GRID)
    with pytest.raises(InputError, match="power of two"):
        C.fit_wavelet_lighting(np.zeros((2, 24, 3), np.float32), 6, 4)


def test_compiled_nonstandard_haar_equals_numpy():
    pytest.importorskip("numba")
    x = np.random.default_rng(4).normal(size=(3, GRID[0] * GRID[1]))
    a = C.haar2d_nonstandard(x, *GRID)
    b = C.haar2d_nonstandard(x, *GRID, compiled=True)
    assert np.max(np.abs(a - b)) <= HAAR_ROUNDTRIP * np.abs(a).max()


# --------------------------------------------------------------------------- light × image Haar

#: Image-space field compressed at field target 2 %: relit relative RMSE against exact Eq. (4),
#: all lighting terms, for the smooth and the sun map (measured 0.32 % and 0.88 % on this field:
#: a relit image averages the field's error over the lights it sees).
IMAGE_WAVELET_RELIT_AT_2PCT = 0.015
#: Field target 1 % and K from a relit target of 1 %: relit relative RMSE against exact
#: Eq. (4) for the smooth and the sun map (measured 1.05 % and 1.21 %; bound: the budget's 1 %
#: plus the all-terms error, 0.20 % and 0.56 %).
IMAGE_WAVELET_RELIT_AT_BUDGET = 0.015
#: Near-zero threshold, so only the 8-bit shared-exponent codes round: relit relative RMSE
#: against exact Eq. (4) (each entry within 1/255 of its largest channel; measured 0.17 % smooth, 0.44 % sun).
IMAGE_WAVELET_CODES = 6e-3
#: Code round trip: max |decoded − value| over the entry's largest |channel| (half a step of
#: 8 significant bits, the step ≤ max/127.5).
RGB_CODE_ROUNDTRIP = 1 / 255


def _image_field(h=20, w=24, seed=1):
    """A sphere seen from +Z on an (h, w) image: normals, albedo and a hard shadow's occluder
    vary smoothly across the image (spatially coherent, like a face), all-frequency in the
    lights. Returns the field (P, L, 3) float32 and the (row, column) of each pixel."""
    d = light_directions(*GRID)
    yy, xx = np.mgrid[0:h, 0:w]
    u = (xx + 0.5) / w * 2 - 1.1  # off-centre: no mirror symmetry
    v = 1 - (yy + 0.5) / h * 2
    inside = u ** 2 + v ** 2 < 0.95
    pix = np.argwhere(inside)
    u, v = u[inside], v[inside]
    nrm = np.stack([u, v, np.sqrt(1 - u ** 2 - v ** 2)], -1)
    cos = np.maximum(nrm @ d.T, 0)
    occ = np.stack([0.6 + 0.3 * u, 0.5 - 0.2 * v, 0.4 + 0.0 * u], -1)
    occ /= np.linalg.norm(occ, axis=1, keepdims=True)
    vis = (occ @ d.T) < 0.3 + 0.2 * v[:, None]
    refl = 2 * nrm[:, 2:3] * nrm - np.array([0.0, 0.0, 1.0])
    spec = np.maximum(refl @ d.T, 0) ** 60
    albedo = np.stack([0.7 + 0.1 * u, 0.5 + 0.1 * v, 0.4 + 0.05 * u * v], -1)[:, None, :]
    f = (albedo / np.pi * cos[..., None] + 0.3 * spec[..., None]) * vis[..., None]
    return f.astype(np.float32), pix


@pytest.fixture(scope="module")
def image_case(case):
    f, pix = _image_field()
    return f, pix, case[1]


def test_image_wavelet_target_and_relit_error(image_case):
    f, pix, ws = image_case
    m = C.fit_image_wavelet(f, *GRID, pix, target_error=0.02)
    assert m.field_error <= 0.02
    assert m.kept_fraction < 0.5
    for name, w in ws.items():
        err = C.relative_rmse(m.relight(w), relight_field(f, w))
        assert err <= IMAGE_WAVELET_RELIT_AT_2PCT, (name, err)
    # storage is every stored array's bytes
    assert m.nbytes == (m.ptr.nbytes + m.pos.nbytes + m.code.nbytes + m.pixel_pos.nbytes
                        + m.check_index.nbytes + m.check_rows.nbytes + 8)
    assert m.check_rows.dtype == np.float16 and m.check_rows.shape == (128, *f.shape[1:])
    assert m.pos.dtype == np.uint16 and m.code.dtype == np.uint32
    # near-zero threshold: Eq. (4) up to the codes' rounding
    exact = C.fit_image_wavelet(f, *GRID, pix, target_error=1e-6)
    for w in ws.values():
        assert C.relative_rmse(exact.relight(w), relight_field(f, w)) <= IMAGE_WAVELET_CODES


def test_rgb_codes_round_trip():
    from facegeo.lighting._compress_image import decode_rgb, encode_rgb

    rng = np.random.default_rng(5)
    v = rng.normal(size=(2000, 3)) * np.exp(rng.uniform(-12, 3, size=(2000, 1)))
    v[0] = [255.0, -1e-3, 0.0]  # a power of two's neighbour and a tiny, a zero channel
    v[1] = [-2.0 ** -9, 2.0 ** -9, 2.0 ** -10]
    code, base = encode_rgb(v)
    back = decode_rgb(code, base)
    rel = np.abs(back - v).max(axis=1) / np.abs(v).max(axis=1)
    assert rel.max() <= RGB_CODE_ROUNDTRIP, rel.max()
    assert np.array_equal(np.signbit(back[np.abs(back) > 0]), np.signbit(v[np.abs(back) > 0]))


def test_image_wavelet_uses_spatial_coherence(image_case):
    # The same reflectance functions at shuffled image positions lose the coherence the image
    # transform exploits: more entries for the same field error (fails if the spatial Haar is
    # skipped or scrambles positions).
    f, pix, _ = image_case
    rng = np.random.default_rng(0)
    shuffled = pix[rng.permutation(len(pix))]
    a = C.fit_image_wavelet(f, *GRID, pix, target_error=0.03)
    b = C.fit_image_wavelet(f, *GRID, shuffled, target_error=0.03)
    assert a.pos.size < 0.8 * b.pos.size, (a.pos.size, b.pos.size)


def test_image_wavelet_linear_and_pixel_order(image_case):
    f, pix, ws = image_case
    m = C.fit_image_wavelet(f, *GRID, pix, target_error=0.02)
    a = m.relight(2.0 * ws["sun"] + 0.5 * ws["smooth"])
    b = 2.0 * m.relight(ws["sun"]) + 0.5 * m.relight(ws["smooth"])
    assert C.relative_rmse(a, b) <= 1e-5  # float32 sums only
    # rows permuted with their positions: the same relit pixels, permuted
    perm = np.random.default_rng(2).permutation(len(pix))
    mp = C.fit_image_wavelet(f[perm], *GRID, pix[perm], target_error=0.02)
    assert C.relative_rmse(mp.relight(ws["sun"]), m.relight(ws["sun"])[perm]) <= 1e-5


def test_image_wavelet_budget(image_case):
    # K from a target: within it of the all-terms compressed relight (the estimate is on the
    # padded grid, ≥ the pixels' error); against exact Eq. (4) within the target plus the
    # all-terms error (triangle inequality); the sun needs few of the 2048 pieces (measured 108).
    f, pix, ws = image_case
    m = C.fit_image_wavelet(f, *GRID, pix, target_error=0.01)
    for name, w in ws.items():
        allk = m.relight(w)
        k, est = m.budget(w, 0.01)
        assert est <= 0.01
        got = m.relight(w, terms=k)
        assert C.relative_rmse(got, allk) <= est + 1e-6
        assert C.relative_rmse(m.relight(w, target_error=0.01), got) == 0.0
        if k > 1:  # the smallest K: a target just above K − 1 terms' estimate gives K − 1
            e_prev = m.budget(w, est * 1.0001)
            assert e_prev[0] <= k
        ref = relight_field(f, w)
        assert C.relative_rmse(got, ref) <= 0.01 + C.relative_rmse(allk, ref) + 1e-6
        assert C.relative_rmse(got, ref) <= IMAGE_WAVELET_RELIT_AT_BUDGET, name
        if name == "sun":  # K counts pieces (4 per light coefficient)
            assert k <= 0.15 * GRID[0] * GRID[1] * m.pieces, k


#: Field error estimated on check pixels against the same error on all pixels, relative
#: |estimate − true| / true, when every pixel is a check pixel (only the stored rows' float16
#: rounding differs; measured 0.023 % smooth, 0.007 % sun).
CHECK_ALL_PIXELS = 0.005


def test_image_wavelet_field_error_estimate(image_case):
    # Every pixel a check pixel: the estimate is the all-terms relight's true relit error
    # (fails if the check rows or indices are mismatched, or the estimate is not relative).
    f, pix, ws = image_case
    m = C.fit_image_wavelet(f, *GRID, pix, target_error=0.02, check_pixels=len(pix))
    assert np.array_equal(m.check_index, np.arange(len(pix)))
    for name, w in ws.items():
        true = C.relative_rmse(m.relight(w), relight_field(f, w))
        est = m.field_error_estimate(w)
        assert abs(est - true) <= CHECK_ALL_PIXELS * true, (name, est, true)


def test_image_wavelet_total_budget(image_case):
    # K for a total relit target against exact Eq. (4): the field's own relit error (check
    # pixels) and the truncation error combined. At field target 2 % the sun's all-terms error
    # is 0.88 %, so a truncation-only budget at 1 % lands above 1 % in total (measured 1.39 %
    # sun, 1.11 % smooth); the total budget must stay within 1 % (measured 0.91 % sun with
    # K = 135 against 62, 0.96 % smooth; fails if the field's error is ignored).
    f, pix, ws = image_case
    m = C.fit_image_wavelet(f, *GRID, pix, target_error=0.02)
    for name, w in ws.items():
        ref = relight_field(f, w)
        k, est = m.budget(w, 0.01, total=True)
        got = C.relative_rmse(m.relight(w, terms=k), ref)
        assert got <= 0.01, (name, k, got)
        assert est <= 0.01
        assert np.array_equal(m.relight(w, target_error=0.01, total=True),
                              m.relight(w, terms=k))
        k_trunc, _ = m.budget(w, 0.01)
        if name == "sun":
            assert C.relative_rmse(m.relight(w, terms=k_trunc), ref) > 0.01  # the case above
            assert k > k_trunc
    # a total target below the field's own error: every non-zero term
    w = ws["sun"]
    n_nonzero = int(np.count_nonzero(m._piece_terms(m.lighting_coefficients(w))[1]))  # pieces
    k, est = m.budget(w, 0.005, total=True)
    assert k == n_nonzero and est > 0.005
    # without check pixels: the old storage, and a total budget is refused by name
    bare = C.fit_image_wavelet(f, *GRID, pix, target_error=0.02, check_pixels=0)
    assert bare.check_rows is None and bare.nbytes == m.nbytes - m.check_rows.nbytes \
        - m.check_index.nbytes
    assert bare.budget(w, 0.01) == m.budget(w, 0.01)  # the truncation-only budget unchanged
    with pytest.raises(InputError, match="check_pixels"):
        bare.budget(w, 0.01, total=True)
    with pytest.raises(InputError, match="check_pixels"):
        C.fit_image_wavelet(f, *GRID, pix, check_pixels=-1)
    with pytest.raises(InputError, match="check_pixels"):
        C.fit_image_wavelet(f, *GRID, pix, check_pixels=float("inf"))
    with pytest.raises(InputError, match="target_error"):
        m.relight(w, total=True)  # a total target needs the target


def test_image_wavelet_check_rows_keep_float32_beyond_float16(image_case):
    # A float32 field brighter than float16's 65504: the check rows stay float32 (in float16
    # they would be inf and every total-budget estimate NaN); the estimate stays finite.
    f, pix, ws = image_case
    m = C.fit_image_wavelet(np.asarray(f, np.float32) * 1e6, *GRID, pix, target_error=0.02)
    assert m.check_rows.dtype == np.float32 and np.isfinite(m.check_rows).all()
    assert np.isfinite(m.field_error_estimate(ws["sun"]))


def test_image_wavelet_pieces_read_fewer_entries(image_case):
    # Slabs stored as 4 magnitude pieces, largest |ŵ|·rms first: the same entries (the same
    # all-terms relight), and for a 1 % total target fewer entries read than whole slabs
    # (measured 8,528 against 15,747 smooth, 11,212 against 15,523 sun; fails if the pieces
    # are ordered without their magnitude or split wrongly), both within the target.
    f, pix, ws = image_case
    m1 = C.fit_image_wavelet(f, *GRID, pix, target_error=0.02, pieces=1)
    m4 = C.fit_image_wavelet(f, *GRID, pix, target_error=0.02, pieces=4)
    assert m1.pieces == 1 and m4.pieces == 4 and m1.pos.size == m4.pos.size
    assert m4.ptr.size == GRID[0] * GRID[1] * 4 * m4.segments + 1
    for name, w in ws.items():
        assert C.relative_rmse(m4.relight(w), m1.relight(w)) <= 1e-6  # summation order only
        ref = relight_field(f, w)
        k1, _ = m1.budget(w, 0.01, total=True)
        k4, _ = m4.budget(w, 0.01, total=True)
        assert C.relative_rmse(m4.relight(w, terms=k4), ref) <= 0.01
        assert m4.entries_read(w, k4) < 0.8 * m1.entries_read(w, k1), name
    for bad in (0, 2.5, "four", True, float("inf")):
        with pytest.raises(InputError, match="pieces"):
            C.fit_image_wavelet(f, *GRID, pix, pieces=bad)


def test_image_wavelet_numpy_fallback_equals_the_kernels(image_case, monkeypatch):
    pytest.importorskip("numba")
    import facegeo.lighting.relight as RL

    f, pix, ws = image_case
    m = C.fit_image_wavelet(f, *GRID, pix, target_error=0.02)
    a, ka = m.relight(ws["sun"], terms=23), m.budget(ws["smooth"], 0.01)
    ta = m.budget(ws["sun"], 0.01, total=True)
    monkeypatch.setattr(RL, "_fused_kernel", lambda conversion=None: False)
    b, kb = m.relight(ws["sun"], terms=23), m.budget(ws["smooth"], 0.01)
    tb = m.budget(ws["sun"], 0.01, total=True)
    assert C.relative_rmse(a, b) <= 1e-6  # float32 summation order only
    assert ka[0] == kb[0] and abs(ka[1] - kb[1]) <= 1e-6
    assert ta[0] == tb[0] and abs(ta[1] - tb[1]) <= 1e-6


def test_image_wavelet_bad_input(image_case):
    f, pix, ws = image_case
    with pytest.raises(InputError, match="target_error"):
        C.fit_image_wavelet(f, *GRID, pix, target_error=0.0)
    with pytest.raises(InputError, match="target_error"):
        C.fit_image_wavelet(f, *GRID, pix, target_error=-0.01)
    with pytest.raises(ShapeError, match="expected a float field"):
        C.fit_image_wavelet(f[:, :-1], *GRID, pix)
    with pytest.raises(ShapeError, match="pixels"):
        C.fit_image_wavelet(f, *GRID, pix[:-1])
    with pytest.raises(ShapeError, match="pixels"):
        C.fit_image_wavelet(f, *GRID, pix.astype(float))
    dup = pix.copy()
    dup[1] = dup[0]
    with pytest.raises(InputError, match="share an image position"):
        C.fit_image_wavelet(f, *GRID, dup)
    bad = f.copy()
    bad[3, 5, 1] = np.inf
    with pytest.raises(InputError, match="non-finite"):
        C.fit_image_wavelet(bad, *GRID, pix)
    with pytest.raises(InputError, match="power of two"):
        C.fit_image_wavelet(np.zeros((2, 24, 3), np.float32), 6, 4, [[0, 0], [0, 1]])
    m = C.fit_image_wavelet(f, *GRID, pix, target_error=0.05)
    with pytest.raises(InputError, match="terms"):
        m.relight(ws["sun"], terms=0)
    with pytest.raises(InputError, match="not both"):
        m.relight(ws["sun"], terms=3, target_error=0.01)
    with pytest.raises(InputError, match="target_error"):
        m.budget(ws["sun"], 0.0)
    with pytest.raises(ShapeError, match="weights"):
        m.relight(np.ones((7, 3)))
    good = m.relight(ws["sun"], terms=9)
    for bad_w in (np.nan, np.inf):  # a float64 array goes to the kernel, which checks it
        w = np.array(ws["sun"], np.float64)
        w[7, 1] = bad_w
        with pytest.raises(InputError, match=r"weights: 1 non-finite .* index \(7, 1\)"):
            m.relight(w, terms=9)
    assert np.array_equal(m.relight(ws["sun"], terms=9), good)  # the scratch is untouched


def test_image_wavelet_grids_beyond_uint16_positions(monkeypatch):
    # A sparse set of pixels spread over a 300 × 400 image: a 512 × 512 grid, whose block
    # layout (65,536 low-pass rows + 3 per pixel block) needs 2 segments of 65536 uint16
    # positions. Near-zero threshold: Eq. (4) up to the codes; kernels = numpy.
    rng = np.random.default_rng(6)
    pix = np.unique(rng.integers(0, [300, 400], size=(80, 2)), axis=0)
    f = rng.uniform(0.0, 1.0, size=(len(pix), 8, 3)).astype(np.float32)
    w = rng.uniform(0.0, 1.0, size=(8, 3))
    m = C.fit_image_wavelet(f, 4, 2, pix, target_error=1e-6)
    assert m.n_rows > 65536 and m.segments == 2 and m.pos.dtype == np.uint16
    a = m.relight(w)
    assert C.relative_rmse(a, relight_field(f, w)) <= IMAGE_WAVELET_CODES
    import facegeo.lighting.relight as RL

    monkeypatch.setattr(RL, "_fused_kernel", lambda conversion=None: False)
    assert C.relative_rmse(m.relight(w), a) <= 1e-6


def test_image_wavelet_fit_streams_bands_with_the_same_result(image_case, monkeypatch, tmp_path):
    # The fit's bands of image rows (spatial levels finer than the band on the band alone, the
    # rest on the bands' low-pass rows) give the coefficients of one whole-grid transform: the
    # same model for bands of 2 rows, of the whole grid (one band: the plain transform) and
    # the default, with light-transform blocks that split and reorder the bands' rows, and from
    # a memory-mapped field. A wrong band-to-grid placement would move or lose entries.
    from facegeo.lighting import _compress_image as CI

    f, pix, _ = image_case
    ref = C.fit_image_wavelet(f, *GRID, pix, target_error=0.02)
    fields = ("ptr", "segments", "pos", "code", "base", "pixel_pos", "grid")
    path = tmp_path / "field.npy"
    np.save(path, f)
    for band, light_rows, field in ((2, 7, f), (1 << 20, 4096, f), (CI.FIT_BAND_ROWS, 5, None)):
        monkeypatch.setattr(CI, "FIT_BAND_ROWS", band)
        monkeypatch.setattr(CI, "FIT_LIGHT_ROWS", light_rows)
        src = np.load(path, mmap_mode="r") if field is None else field
        m = C.fit_image_wavelet(src, *GRID, pix, target_error=0.02)
        for name in fields:
            assert np.array_equal(getattr(m, name), getattr(ref, name)), (band, name)
        assert abs(m.field_error - ref.field_error) <= 1e-9


def test_image_wavelet_threads_equal_one_thread(image_case, monkeypatch):
    from facegeo.lighting import _compress_image as CI

    f, pix, ws = image_case
    m = C.fit_image_wavelet(f, *GRID, pix, target_error=0.02)
    monkeypatch.setattr(CI, "PARALLEL_ENTRIES", 0)  # split even this small field
    ker = CI._kernels()
    if ker is not None:  # the split counts: none below cell 0, all below G, half in between
        idx = np.arange(m.n_theta * m.n_phi * m.pieces, dtype=np.int64)  # every piece
        g = m.n_rows
        below = ker.entries_below(m.ptr, m.segments, m.pos, idx, np.array([0, g // 2, g]))
        assert below[0] == 0 and below[2] == m.pos.size
        assert below[1] == sum(int(np.count_nonzero(m.pos[m.ptr[j]:m.ptr[j + 1]] < g // 2))
                               for j in idx)
        cuts = CI._cell_ranges(m, idx, 3, ker)
        assert cuts[0] == 0 and cuts[-1] == g and len(cuts) == 4
    for k in (2, 40, 512):
        a = m.relight(ws["sun"], terms=k, workers=1)
        b = m.relight(ws["sun"], terms=k, workers=3)
        assert C.relative_rmse(b, a) <= 1e-6  # float32 summation order only
    with pytest.raises(InputError, match="workers"):
        m.relight(ws["sun"], workers=0)


#: Compiled interleaved scatter vs the numpy reference: max |Δ| over max |acc| (float32 against
#: float64 products and sums, then float32).
SCATTER_RGBX = 1e-5
#: Compiled inverse evaluated at the pixels vs numpy's full inverse (float64): max |Δ|
#: over max |pixel| (float32 rounding through ≤ 2·log₂(size) steps).
INVERSE_AT_PIXELS = 1e-5


def test_scatter_add_rgbx_equals_the_numpy_scatter(image_case):
    pytest.importorskip("numba")
    from facegeo.lighting import _compress_image as CI
    from facegeo.lighting import _compress_kernels as K

    f, pix, ws = image_case
    m = C.fit_image_wavelet(f, *GRID, pix, target_error=0.02)
    idx, lw = CI.selected_lighting_terms(m, ws["sun"], 40, None, index_order=True)
    g = m.n_rows
    planar = np.zeros((3, g), np.float32)
    CI._scatter(m, idx, lw, planar)  # the numpy reference (float64 products, then float32)
    assert np.abs(planar).max() > 0
    tab = np.zeros((32, 4), np.float32)
    for cuts in ([0, g], [0, 17, g // 2, g - 5, g]):  # whole, and ranges cutting every run
        rgbx = np.zeros((g, 4), np.float32)
        rgbx[:, :3] = 1.0  # added to, not overwritten
        for c0, c1 in itertools.pairwise(cuts):
            K.scatter_add_rgbx(m.ptr, m.segments, m.pos, m.code, CI.exponent_table(m.base),
                               idx, lw, rgbx, tab, c0, c1)
        rgbx[:, :3] -= 1.0
        assert np.abs(rgbx[:, :3].T - planar).max() <= SCATTER_RGBX * np.abs(planar).max()
        assert not rgbx[:, 3].any()  # the pad lane stays zero
    # a swapped channel order fails: the lanes are R, G, B
    assert np.abs(rgbx[:, 2::-1].T - planar).max() > SCATTER_RGBX * np.abs(planar).max()


@pytest.mark.parametrize("shape", [(1, 8), (8, 1), (2, 16), (16, 2), (4, 16), (16, 4),
                                   (16, 16), (1, 1)])
def test_inverse_haar_at_pixels_equals_the_full_inverse(shape):
    # Grid layout (read only, and clearing), and on grids with both axes ≥ 2 the block layout
    # of the model's accumulator (coefficients of blocks without pixels zero, as a fit's).
    pytest.importorskip("numba")
    from facegeo.lighting import _compress_image as CI
    from facegeo.lighting import _compress_kernels as K
    from facegeo.lighting._compress_haar import _nonstandard_levels, haar2d_nonstandard

    h, w = shape
    rng = np.random.default_rng(h * 31 + w)
    pixels = rng.permutation(h * w)[: max(1, h * w // 3)].astype(np.int32)
    blocks, block_px = CI.finest_blocks(pixels, shape)
    rows = CI.coefficient_rows(shape, blocks)
    coef = rng.normal(size=(h * w, 4)).astype(np.float32)
    coef[:, 3] = 0
    coef[rows < 0] = 0  # the detail cells of blocks without pixels
    ref = haar2d_nonstandard(coef[:, :3].T.astype(np.float64), w, h, inverse=True).T
    levels = np.array(_nonstandard_levels(w, h), np.int64).reshape(-1, 4)
    ll = np.zeros((0, 4), np.float32)
    none = (np.zeros(0, np.int64), np.zeros((0, 4), np.int32))
    tol = INVERSE_AT_PIXELS * np.abs(ref).max()
    order = np.argsort(pixels)
    for blk in (none, (blocks, block_px)) if blocks.size else (none,):
        for clear in (False, True):
            det = coef.copy()
            out = np.full((pixels.size, 3), np.nan, np.float32)
            K.inverse_haar_at_pixels(det, h, w, False, levels, pixels, order, out, *blk, ll,
                                     clear)
            assert np.abs(out - ref[pixels]).max() <= tol
            assert not det.any() if clear else np.array_equal(det, coef)
    if blocks.size:  # the block layout: S = H·W/4 + 3 · blocks rows
        assert rows.max() + 1 == h * w // 4 + 3 * blocks.size
        packed = np.zeros((rows.max() + 1, 4), np.float32)
        packed[rows[rows >= 0]] = coef[rows >= 0]
        for clear in (False, True):
            det = packed.copy()
            out = np.full((pixels.size, 3), np.nan, np.float32)
            K.inverse_haar_at_pixels(det, h, w, True, levels, pixels, order, out, blocks,
                                     block_px, np.zeros((h * w // 4, 4), np.float32), clear)
            assert np.abs(out - ref[pixels]).max() <= tol
            assert not det.any() if clear else np.array_equal(det, packed)
        # the rows' order matters: the blocks' detail rows swapped fail
        det = packed.copy()
        det[h * w // 4:] = packed[h * w // 4:][::-1]
        K.inverse_haar_at_pixels(det, h, w, True, levels, pixels, order, out, blocks, block_px,
                                 ll, False)
        assert np.abs(out - ref[pixels]).max() > tol


def test_image_wavelet_relight_scratch_stays_zero_and_pickles(image_case):
    # The one-thread relight keeps its accumulator on the model and the inverse zeroes it as
    # it reads: repeated relights with different lightings equal fresh models' relights.
    import pickle

    f, pix, ws = image_case
    m = C.fit_image_wavelet(f, *GRID, pix, target_error=0.02)
    first = {k: m.relight(w, terms=30) for k, w in ws.items()}
    for k, w in ws.items():
        fresh = pickle.loads(pickle.dumps(m))  # stored fields only: no scratch, no lock
        assert "_scratch" not in fresh.__dict__
        assert np.array_equal(fresh.relight(w, terms=30), first[k])
        assert np.array_equal(m.relight(w, terms=30), first[k])
    if "_scratch" in m.__dict__:  # compiled path
        assert not m._scratch[0].any()
    # threads relighting one model at once: one holds the kept scratch, the others get new
    from concurrent.futures import ThreadPoolExecutor

    names = list(ws) * 8
    with ThreadPoolExecutor(max_workers=4) as pool:
        got = list(pool.map(lambda k: m.relight(ws[k], terms=30), names))
    for k, g in zip(names, got, strict=True):
        assert np.array_equal(g, first[k]), k
