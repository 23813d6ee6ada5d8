"""Tests for the structured-light code families (``facegeo.geometry._sl_codes``): the long-run
("minsw") Gray code's construction, its patterns and its decoding through the code → stripe
table, alone and in the ensemble of codes.

Metrics, stated with each assertion:

* *min run* — the narrowest interior stripe (a run of equal bits that touches neither end of
  the code) over every plane of a linear code, in stripes (``_sl_codes.run_lengths``);
* *cyclic gap* — the fewest steps between two flips of one bit around the cyclic code;
* decodes of pattern images are compared exactly (integer projector columns).
"""

from __future__ import annotations

import numpy as np
import pytest

import facegeo.geometry._sl_codes as C
from facegeo.errors import InputError
from facegeo.geometry.structured_light import (
    PatternSpec,
    decode_stream,
    pattern_image,
    pattern_names,
    pattern_value_at,
)

# ---------------------------------------------------------------- named tolerances (stripes)
#: Min run (= cyclic gap) the construction reaches for n = 1 … 13 bits, measured; every
#: interior stripe of the linear code is at least this wide. Goddyn & Gvozdjak 2003's optima
#: for 7 … 10 bits are 5, 6, 7, 8 (reached at 7, 8 and 10 bits; 9 bits one short: 6).
MIN_RUN = {1: 1, 2: 2, 3: 2, 4: 2, 5: 4, 6: 4, 7: 5, 8: 6, 9: 6, 10: 8, 11: 8, 12: 8, 13: 9}
#: Gupta et al. 2013's 10-bit "max min-SW" code: narrowest stripe 8 (the optimum).
GUPTA_MIN_RUN_10 = 8
REFLECTED_MIN_RUN = 2  # the reflected Gray code's finest interior stripes (its last plane)


def _one_bit_apart(w):
    d = np.asarray(w[1:], np.int64) ^ np.asarray(w[:-1], np.int64)
    return (d > 0) & ((d & (d - 1)) == 0)


@pytest.mark.parametrize("n", sorted(MIN_RUN))
def test_long_run_code_is_a_gray_code_with_the_claimed_min_run(n):
    """Every n-bit word exactly once, neighbours (and the last and first: a cyclic code) one
    bit apart, every interior stripe at least MIN_RUN[n] wide and one exactly that wide.
    Fails for a construction that repeats a word, jumps two bits or shortens a run."""
    w = C.long_run_words(n)
    assert w.dtype == np.uint16 and w.shape == (1 << n,) and w[0] == 0
    np.testing.assert_array_equal(np.sort(w), np.arange(1 << n))
    assert _one_bit_apart(np.r_[w, w[:1]]).all()
    delta = C.long_run_transitions(n)
    np.testing.assert_array_equal(np.int64(1) << delta[:-1], w[1:] ^ w[:-1])
    assert C.long_run_min_run(n) == MIN_RUN[n]
    runs = C.run_lengths(w, n)
    if n >= 2:
        assert runs.min() == MIN_RUN[n], (n, runs.min())
    # the cyclic gap is a lower bound on the runs of every rotation of the code
    rot = np.roll(w, 3 if n > 1 else 1)
    assert C.run_lengths(rot, n).min(initial=MIN_RUN[n]) >= MIN_RUN[n]


def test_long_run_code_beats_the_reflected_code_and_is_deterministic():
    """At 10 bits the narrowest interior stripe is 8 against the reflected code's 2, as wide as
    Gupta et al. 2013's code; the construction gives the same words twice."""
    k = np.arange(1 << 10)
    assert C.run_lengths(k ^ (k >> 1), 10).min() == REFLECTED_MIN_RUN
    assert C.run_lengths(C.long_run_words(10), 10).min() == MIN_RUN[10] == GUPTA_MIN_RUN_10
    C._transitions.cache_clear()
    C._words.cache_clear()
    again = C.long_run_words(10)
    np.testing.assert_array_equal(again, C._words_from_transitions(C.long_run_transitions(10)))
    assert C._cyclic_min_gap(C.long_run_transitions(10)) == MIN_RUN[10]


def test_stored_orbit_code_is_a_symmetric_gray_code_with_gap_6():
    """The searched 8-bit code (``_ORBIT_CODES[8]``): 8 blocks of 32 transitions, block j + 1
    the bit permutation pi (two 4-cycles) of block j; every word once, cyclic, gap 6. With
    the 2-bit code and s = 3 (Theorem 1) it gives the 10-bit code of gap 8. Fails if the data
    or its expansion is corrupted (two transitions swapped: a repeated word or a gap < 6)."""
    T, cycles, G = C._ORBIT_CODES[8]
    d = C._orbit_transitions(T, cycles, G)
    assert d.shape == (256,) and len(T) == 32 and G == 8
    pi = np.array([1, 2, 3, 0, 5, 6, 7, 4])
    np.testing.assert_array_equal(d.reshape(8, 32)[1:], pi[d.reshape(8, 32)[:-1]])
    w = C._words_from_transitions(d)
    np.testing.assert_array_equal(np.sort(w), np.arange(256))
    assert w[-1] ^ (1 << d[-1]) == 0  # the last transition closes the cycle
    assert C._cyclic_min_gap(d) == MIN_RUN[8]
    np.testing.assert_array_equal(C.long_run_transitions(8), d)
    d10 = C._compose(d, 8, C.long_run_transitions(2), 2, 3)
    np.testing.assert_array_equal(C.long_run_transitions(10), d10)
    # a corrupted block (two neighbouring transitions swapped) is caught by the checks above
    bad = T[:5] + T[6] + T[5] + T[7:]
    db = C._orbit_transitions(bad, cycles, G)
    wb = C._words_from_transitions(db)
    assert np.unique(wb).size < 256 or C._cyclic_min_gap(db) < MIN_RUN[8]


@pytest.mark.slow
def test_search_script_regenerates_the_stored_orbit_code(monkeypatch):
    """``scripts/search_long_run_codes.py`` with its defaults finds exactly the stored block
    (deterministic depth-first search, numba; 11 CPU-s, 26-34 s wall under load)."""
    import importlib.util
    import sys
    from pathlib import Path

    pytest.importorskip("numba")
    path = Path(__file__).resolve().parents[1] / "scripts" / "search_long_run_codes.py"
    spec = importlib.util.spec_from_file_location("search_long_run_codes", path)
    mod = importlib.util.module_from_spec(spec)
    # registered under its name, as an import would: numba's disk cache of a kernel that calls
    # another looks the callee's module up by name (else the second run fails to load it)
    monkeypatch.setitem(sys.modules, spec.name, mod)
    spec.loader.exec_module(mod)
    n, r, cycles, G, budget = mod.DEFAULT
    S, T, _ = mod.search(n, r, cycles, G, budget)
    assert (T, tuple(map(tuple, cycles)), G) == C._ORBIT_CODES[n] and S == 17
    assert C._cyclic_min_gap(C._orbit_transitions(T, cycles, G)) == r


def test_gap_and_run_helpers_on_known_codes():
    """The reflected code's transitions 0 1 0 2 0 1 0 2 have cyclic gap 2; a hand-made linear
    code's runs; Theorem 1 of Goddyn, Lawrence & Nemeth from two 2-bit codes is a 4-bit
    cycle."""
    assert C._cyclic_min_gap(np.array([0, 1, 0, 2, 0, 1, 0, 2])) == 2
    assert C._cyclic_min_gap(np.array([0, 1, 2, 0, 1, 2])) == 3
    # bit 0: 0 1 1 1 0 0 -> interior run 3; bit 1: 0 0 1 1 1 1 -> none
    np.testing.assert_array_equal(C.run_lengths([0, 1, 3, 3, 2, 2], 2), [3])
    np.testing.assert_array_equal(C.run_lengths([0, 1, 3, 3, 2, 2], 2, interior=False),
                                  [1, 3, 2, 2, 4])
    A = C.long_run_transitions(2)
    d = C._compose(A, 2, A, 2, 1)
    w = C._words_from_transitions(d)
    np.testing.assert_array_equal(np.sort(w), np.arange(16))
    assert _one_bit_apart(np.r_[w, w[:1]]).all()


def test_stripe_table_inverts_the_words_and_code_bit_reads_them():
    n = 9
    w, t = C.long_run_words(n), C.stripe_table("minsw", n)
    assert t.dtype == np.uint16
    np.testing.assert_array_equal(t[w], np.arange(1 << n))
    k = np.arange(1 << n)
    planes = np.stack([C.code_bit("minsw", n, i, k) for i in range(n)])
    np.testing.assert_array_equal((planes << np.arange(n - 1, -1, -1)[:, None]).sum(0), w)
    assert C.stripe_table("gray", n) is None and C.stripe_table("xor04", n) is None


@pytest.mark.parametrize("call,match", [
    (lambda: C.long_run_words(C.MINSW_MAX_BITS + 1), r"n: expected an integer in \[1, 16\]"),
    (lambda: C.long_run_words(0), r"in \[1, 16\].*got 0"),
    (lambda: C.long_run_transitions(3.0), "integer"),
    (lambda: C.stripe_table("minsw", 20), "2\\*\\*n entries"),
    (lambda: C.stripe_table("bogus", 8), "code"),
    (lambda: PatternSpec(64, 64, n_bits_x=17, codes=("minsw",)), r"'minsw' takes <= 16 bits.*n_bits_x is 17"),
    (lambda: PatternSpec(1 << 17, 8, codes=("gray", "minsw")), r"n_bits_x is 17"),
    (lambda: PatternSpec(64, 64, codes=("gray", "minsw3")), "PatternSpec.codes"),
])
def test_bad_input(call, match):
    with pytest.raises(InputError, match=match):
        call()


# ---------------------------------------------------------------- patterns and decoding


def test_minsw_patterns_have_wide_stripes_and_pattern_value_at_agrees():
    """Every projected minsw plane on a 512-px axis with 8 bits (stripes 2 px) has interior
    stripes >= MIN_RUN[8] · 2 px; pattern_value_at serves the frames; the spec round-trips."""
    spec = PatternSpec(512, 40, n_bits_x=8, codes=("gray", "minsw"))
    assert spec.stripe_shift("x") == 1
    line = np.stack([pattern_image(spec, f"minsw_x_{i:02d}")[0] for i in range(8)])
    for i, row in enumerate(line):
        edges = np.flatnonzero(np.diff(row) != 0) + 1
        runs = np.diff(np.r_[0, edges, row.size])[1:-1]
        assert runs.min() >= MIN_RUN[8] * 2, (i, runs.min())
    gray_lsb = pattern_image(spec, "gray_x_07")[0]
    edges = np.flatnonzero(np.diff(gray_lsb) != 0) + 1
    assert np.diff(edges).min() == REFLECTED_MIN_RUN * 2
    q = np.stack(np.meshgrid(np.arange(512.0) + 0.3, [5.0]), -1)[0]
    for n in ("minsw_x_00", "minsw_x_05_inv", "minsw_y_02"):
        np.testing.assert_array_equal(pattern_value_at(spec, n, q), pattern_image(spec, n)[5])
    d = spec.to_dict()
    assert d["codes"] == ["gray", "minsw"] and PatternSpec.from_dict(d) == spec


@pytest.mark.parametrize("kernels", [True, False])
@pytest.mark.parametrize("kw", [{}, {"inverse": False}, {"n_bits_x": 6, "n_bits_y": 5}])
def test_minsw_pattern_images_decode_exactly(kw, kernels, monkeypatch):
    """Identity camera (pixel (r, c) sees projector pixel (c, r)) on a 200 x 120 projector
    (non-power-of-two: the code is cut at 200 / 120 stripes): every pixel decodes to its
    stripe's centre, in the compiled kernel and the numpy reference. Fails if the table is
    the words instead of their inverse, or a plane is read in the wrong order."""
    import facegeo.geometry._sl_stream as S

    monkeypatch.setattr(S, "KERNELS", kernels)
    spec = PatternSpec(200, 120, codes=("minsw",), **kw)
    frames = {n: pattern_image(spec, n) for n in pattern_names(spec)}
    res = decode_stream(frames, spec)
    assert res.valid.all()
    for axis, size, grid in (("x", 200, res.x), ("y", 120, res.y)):
        s = spec.stripe_shift(axis)
        want = ((np.arange(size) >> s) << s) + 0.5 * ((1 << s) - 1)
        want = want[None, :] if axis == "x" else want[:, None]
        np.testing.assert_array_equal(grid, np.broadcast_to(want, grid.shape), err_msg=axis)


def _one_row(spec, blank):
    """A 1 x 256 identity camera of the x patterns with the planes ``blank`` unresolved
    (pattern = inverse = 0.5)."""
    frames = {}
    for name in pattern_names(spec):
        img = pattern_image(spec, name)[:1]
        if any(name.startswith(f"minsw_x_{i:02d}") for i in blank):
            img = np.full_like(img, 0.5)
        frames[name] = img
    return frames


@pytest.mark.parametrize("kernels", [True, False])
def test_minsw_partial_codes_boundary_or_invalid(kernels, monkeypatch):
    """One unresolved plane: the two candidates are the table's entries for the word and the
    word with that plane flipped; where they are neighbours (the plane flips between them)
    the pixel sits on their boundary (k ± 0.5, valid), elsewhere it is invalid (a long-run
    code has no prefix block), even when ``max_coarse_px`` would accept any block. Two
    unresolved planes: invalid everywhere. The per-plane statistics count them. Fails if a
    table pixel falls back to the Gray prefix block."""
    import facegeo.geometry._sl_stream as S

    monkeypatch.setattr(S, "KERNELS", kernels)
    spec = PatternSpec(256, 4, n_bits_y=0, codes=("minsw",), white_black=True)
    n, i = 8, 3
    w = C.long_run_words(n).astype(np.int64)
    res = decode_stream(_one_row(spec, [i]), spec)
    k = np.arange(256)
    bit = 1 << (n - 1 - i)
    right = np.r_[(w[1:] ^ w[:-1]) == bit, False]  # stripe k and k + 1 differ in plane i
    left = np.r_[False, right[:-1]]
    want = np.where(right, k + 0.5, np.where(left, k - 0.5, np.nan))
    np.testing.assert_array_equal(res.valid[0], right | left)
    np.testing.assert_array_equal(res.x[0], want)
    assert (right | left).sum() == 2 * right.sum() > 0
    st = res.bits["x"]["minsw"]
    assert st["unresolved"][i] == 256 and st["lost"][i] == 256 - (right | left).sum()
    res2 = decode_stream(_one_row(spec, [i, 6]), spec)
    assert not res2.valid.any() and res2.bits["x"]["minsw"]["lost"][i] == 256
    # however wide a block the caller accepts: the resolved planes name none
    assert not decode_stream(_one_row(spec, [i, 6]), spec, max_coarse_px=1e6).valid.any()
    assert (decode_stream(_one_row(spec, [i]), spec, max_coarse_px=1e6).valid[0]
            == (right | left)).all()


@pytest.mark.parametrize("kernels", [True, False])
def test_minsw_partial_code_picked_by_the_phase(kernels, monkeypatch):
    """One unresolved plane with far-apart candidates and a phase sequence on the axis: the
    candidate whose predicted phase is within a quarter period of the measured one (and the
    other's is not) is kept, so pixels beside the boundary ones decode, each to its own
    column (sub-pixel phase, unwrapped with the picked stripe). Fails if the pick takes the
    other candidate (a wrong column) or never happens."""
    import facegeo.geometry._sl_stream as S

    monkeypatch.setattr(S, "KERNELS", kernels)
    spec = PatternSpec(256, 4, n_bits_y=0, codes=("minsw",), phase_steps=4,
                       phase_periods_x=256 / 64)
    n, i = 8, 5
    w = C.long_run_words(n).astype(np.int64)
    boundary = np.r_[(w[1:] ^ w[:-1]) == 1 << (n - 1 - i), False]
    boundary |= np.r_[False, boundary[:-1]]
    res = decode_stream(_one_row(spec, [i]), spec)
    v = res.valid[0]
    # picked pixels beside the boundary ones (measured 116 valid, 68 boundary pixels)
    assert (v & ~boundary).sum() >= 32, (v.sum(), boundary.sum())
    np.testing.assert_allclose(res.x[0][v], np.arange(256.0)[v], atol=1e-3)


def test_compiled_finish_equals_numpy_reference_with_minsw(monkeypatch):
    """Kernel against numpy reference on blurred noisy 8-bit frames of Gray + min-SW + XOR-04
    with phase (partial codes, boundaries, phase picks and votes in every family): identical
    validity and statistics, coordinates within 1e-4 px."""
    from scipy.ndimage import gaussian_filter

    import facegeo.geometry._sl_stream as S

    rng = np.random.default_rng(7)
    spec = PatternSpec(200, 120, codes=("gray", "minsw", "xor04"), phase_steps=4,
                       phase_axes=("x",))
    y, x = np.mgrid[0:90, 0:130].astype(np.float64)
    q = np.stack([1.4 * x - 2 + 4 * np.sin(y / 17), 1.2 * y + 0.05 * x - 2], -1)
    alb = 0.15 + 0.75 * rng.random(q.shape[:2])
    frames = {}
    for name in pattern_names(spec):
        f = 0.02 + 0.8 * alb * pattern_value_at(spec, name, q) + 0.01 * rng.standard_normal(alb.shape)
        frames[name] = np.clip(np.rint(gaussian_filter(f, 1.2) * 255), 0, 255).astype(np.uint8)
    out = {}
    for k in (True, False):
        monkeypatch.setattr(S, "KERNELS", k)
        out[k] = decode_stream(frames, spec)
    got, want = out[True], out[False]
    assert sum(want.bits["x"]["minsw"]["unresolved"]) > 50 and want.valid.any()
    assert got.bits == want.bits
    for name in ("valid_x", "valid_y"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    for name in ("x", "y", "sigma_x"):
        a, b = getattr(got, name), getattr(want, name)
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-4)
    np.testing.assert_allclose(got.confidence, want.confidence, rtol=0, atol=1e-6)
