"""Binary code families for structured light: Gray, Gupta et al.'s XOR codes, long-run Gray.

Private helpers of :mod:`facegeo.geometry.structured_light` (patterns) and
:mod:`facegeo.geometry._sl_stream` (decoding). A family maps a stripe index ``k`` in
``[0, 2**n)`` to ``n`` bit planes, bit ``i = 0`` the most significant (projected first).

* ``"gray"`` — the binary-reflected Gray code ``g = k ^ (k >> 1)`` (Inokuchi et al. 1984). Its
  plane ``i`` has stripes ``2**(n - i)`` wide: the first planes are low-frequency, and under
  interreflection the global light differs between such a pattern and its inverse, which can
  flip the bit (Gupta et al. 2013, Sec. 3).
* ``"xor02"`` / ``"xor04"`` — Gupta et al. 2013, Sec. 4.2: the *base plane* is the Gray plane
  with stripes 2 (the last, ``b = n - 1``) or 4 (``b = n - 2``) wide; every coarser plane
  ``i < b`` is projected XORed with it, ``c_i = g_i XOR g_b``, and the planes ``i >= b`` are
  projected unchanged. Every pattern is then high-frequency, so its global component equals
  its inverse's. Decoding recovers ``g_i = c_i XOR c_b`` — which also means a coarse bit is
  only as reliable as its own decision *and* the base plane's.
* ``"minsw"`` — a *long-run* Gray code (Gupta et al. 2013's "max min-SW" code): consecutive
  stripes still differ in one plane, but every plane's interior stripes are long (at least
  :func:`long_run_min_run` stripes; 8 for 10 bits, the optimum and Gupta et al.'s, against 2
  for the reflected code), so the finest pattern survives a blur that erases the reflected
  code's last planes. Built by :func:`long_run_transitions` (a stored 8-bit code found by a
  symmetric search, and Goddyn, Lawrence & Nemeth 1988, Theorem 1). It has no binary prefix
  structure: decoding goes through a code → stripe table (:func:`stripe_table`).

References
----------
Gupta, Agrawal, Veeraraghavan, Narasimhan. A Practical Approach to 3D Scanning in the Presence
of Interreflections, Subsurface Scattering and Defocus. IJCV 102, 2013, Sec. 4.

Goddyn, Lawrence, Nemeth. Gray codes with optimized run lengths. Utilitas Mathematica 34, 1988,
179–192 (Theorem 1, as restated by Goddyn & Gvozdjak 2003).

Goddyn, Gvozdjak. Binary Gray codes with long bit runs. Electron. J. Combin. 10, 2003, #R27
(the optimum min-runs: 6 for 8 bits, 8 for 10 bits, both reached here — 8 bits by the
symmetric search of ``scripts/search_long_run_codes.py``, this project's, not theirs; their
refined recursive construction is not implemented).
"""

from __future__ import annotations

import functools

import numpy as np

from facegeo.checks import check_choice, fmt_value
from facegeo.errors import InputError

__all__ = ["CODE_FAMILIES", "MINSW_MAX_BITS", "base_plane", "code_bit", "long_run_min_run",
           "long_run_transitions", "long_run_words", "max_bits", "min_bits", "run_lengths",
           "stripe_table"]

#: Code families a :class:`~facegeo.geometry.structured_light.PatternSpec` may project.
CODE_FAMILIES = ("gray", "xor02", "xor04", "minsw")

#: Most bits of a ``"minsw"`` axis: its decode table has ``2**n`` uint16 entries (128 KB at 16),
#: and a 16-bit code names 65536 stripes, more than any projector has pixels.
MINSW_MAX_BITS = 16

#: Depth-first search budget (nodes) per target run of the base codes (n <= _DFS_MAX_BITS).
_DFS_NODES = 20_000
_DFS_MAX_BITS = 6

_BASE_OFFSET = {"xor02": 1, "xor04": 2}


def max_bits(code: str) -> int | None:
    """Most bits per axis family ``code`` can project (None: the pattern set's own limit)."""
    return MINSW_MAX_BITS if code == "minsw" else None


def min_bits(code: str) -> int:
    """Fewest bits per axis family ``code`` needs (the XOR codes need their base plane)."""
    return _BASE_OFFSET.get(code, 1)


def base_plane(code: str, n: int) -> int | None:
    """Index (0 = MSB) of the XOR base plane of family ``code`` with ``n`` bits, or None."""
    off = _BASE_OFFSET.get(code)
    return None if off is None else n - off


def code_bit(code: str, n: int, bit: int, stripe: np.ndarray) -> np.ndarray:
    """Projected bit ``bit`` (0 = MSB) of family ``code`` with ``n`` bits at stripe indices.

    Parameters
    ----------
    code : {"gray", "xor02", "xor04", "minsw"}
    n : int
        Bits on this axis.
    bit : int
        Plane, ``0 <= bit < n``.
    stripe : array_like of int, >= 0
        Stripe index (projector pixel ``>> stripe_shift``).

    Returns
    -------
    numpy.ndarray of int, same shape: 0 or 1
    """
    s = np.asarray(stripe)
    if code == "minsw":
        return (long_run_words(n)[s].astype(np.int64) >> (n - 1 - bit)) & 1
    g = s ^ (s >> 1)
    v = (g >> (n - 1 - bit)) & 1
    b = base_plane(code, n)
    if b is not None and bit < b:
        v = v ^ ((g >> (n - 1 - b)) & 1)
    return v


# --------------------------------------------------------------------------- long-run Gray codes


def _check_long_run_bits(n) -> int:
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) \
            or not 1 <= int(n) <= MINSW_MAX_BITS:
        raise InputError(f"n: expected an integer in [1, {MINSW_MAX_BITS}] bits for a 'minsw' "
                         f"code (its decode table has 2**n entries), got {fmt_value(n)}")
    return int(n)


def _words_from_transitions(delta: np.ndarray) -> np.ndarray:
    """Words of the Gray code starting at 0 whose step ``k`` flips bit ``delta[k]``: (N,) int64
    (the last transition, back to the first word, is not applied)."""
    w = np.zeros(delta.size, np.int64)
    w[1:] = np.bitwise_xor.accumulate(np.int64(1) << delta[:-1].astype(np.int64))
    return w


def _cyclic_min_gap(delta: np.ndarray) -> int:
    """Smallest distance, around the cycle, between two transitions of the same bit."""
    N = delta.size
    order = np.argsort(delta, kind="stable")  # per bit, its positions in increasing order
    b = delta[order]
    same = b[1:] == b[:-1]
    gaps = np.diff(order)[same]
    starts = np.flatnonzero(np.r_[True, ~same])
    ends = np.r_[starts[1:] - 1, N - 1]
    wrap = order[starts] + N - order[ends]  # last transition of a bit to its first, around
    return int(min(gaps.min(initial=N), wrap.min()))


def _dfs_transitions(n: int, r: int, budget: int) -> np.ndarray | None:
    """A cyclic n-bit Gray code whose same-bit transitions are >= ``r`` steps apart (around
    the cycle too): depth-first search from word 0, bits tried in increasing order. None when
    there is none or ``budget`` placed words did not find one. Deterministic; for the base
    codes only (n <= 6: 64 words deep)."""
    N = 1 << n
    seen = np.zeros(N, bool)
    seen[0] = True
    last = [-N] * n  # step of each bit's latest transition
    delta: list[int] = []
    nodes = 0

    def extend(w: int, k: int) -> bool:
        nonlocal nodes
        if k == N - 1:  # every word placed: the last step must return to word 0
            j = w.bit_length() - 1
            if w != 1 << j or k - last[j] < r or N - k + delta.index(j) < r:
                return False
            delta.append(j)
            return True
        for j in range(n):
            v = w ^ (1 << j)
            if k - last[j] < r or seen[v]:
                continue
            nodes += 1
            if nodes > budget:
                raise TimeoutError
            seen[v], prev = True, last[j]
            last[j] = k
            delta.append(j)
            if extend(v, k + 1):
                return True
            delta.pop()
            seen[v], last[j] = False, prev
        return False

    try:
        found = extend(0, 0)
    except TimeoutError:
        return None
    return np.array(delta, np.int64) if found else None


#: Long-run codes found by a search for codes invariant under a free group of affine maps of
#: the n-cube (``scripts/search_long_run_codes.py``, which regenerates them): ``n`` -> (first
#: block of transitions ``T``, the bit permutation ``pi`` as its cycles, number of blocks ``G``).
#: The code is ``T, pi(T), pi**2(T), …`` (``G`` blocks, ``pi`` applied to each transition).
_ORBIT_CODES = {
    # gap 6 (Goddyn & Gvozdjak 2003's optimum for 8 bits): S = 17, 479 306 search nodes
    8: ("01264703265710325471032576103546", ((0, 1, 2, 3), (4, 5, 6, 7)), 8),
}


def _orbit_transitions(T: str, cycles: tuple, G: int) -> np.ndarray:
    """Transitions of the code ``T, pi(T), …, pi**(G - 1)(T)``: (G * len(T),) int64.

    ``T`` is the first block, one decimal digit per transition (bit index, so ``n <= 10``);
    ``pi`` the bit permutation given by its ``cycles`` (each cycle maps an entry to the next);
    block ``j + 1`` is ``pi`` applied to every transition of block ``j``."""
    n = sum(len(c) for c in cycles)
    pi = np.arange(n)
    for c in cycles:
        pi[list(c)] = np.roll(c, -1)
    block = np.array([int(ch) for ch in T], np.int64)
    out = [block]
    for _ in range(G - 1):
        out.append(pi[out[-1]])
    return np.concatenate(out)


def _compose(A: np.ndarray, n: int, B: np.ndarray, m: int, s: int) -> np.ndarray:
    """Goddyn, Lawrence & Nemeth 1988, Theorem 1: an (n + m)-bit cyclic Gray code from an
    n-bit one (transitions ``A``) and an m-bit one (``B``), ``n >= m``, odd ``s``, ``t = 2**m
    - s`` (odd). A word ``Z`` of ``2**m`` letters, ``s`` a's and ``t`` b's spread evenly
    (Bresenham), repeated ``2**n`` times; the a's take ``A`` cyclically (``s`` rounds) and the
    b's ``B + n`` cyclically. A bit of ``A`` then waits about ``2**m / s`` times its gap in
    ``A``, a bit of ``B`` about ``2**m / t`` times its gap in ``B``."""
    L = 1 << m
    i = np.arange(L)
    is_a = np.tile((i + 1) * s // L > i * s // L, 1 << n)
    out = np.empty(is_a.size, np.int64)
    na = int(np.count_nonzero(is_a))
    out[is_a] = np.resize(A, na)
    out[~is_a] = np.resize(B, is_a.size - na) + n
    return out


@functools.cache
def _transitions(n: int) -> tuple[np.ndarray, int]:
    """(transitions, cyclic min gap) of the long-run code with ``n`` bits (see
    :func:`long_run_transitions`)."""
    if n <= _DFS_MAX_BITS:
        for r in range(n, 0, -1):
            d = _dfs_transitions(n, r, _DFS_NODES)
            if d is not None:
                return d, r
    best = None
    if n in _ORBIT_CODES:
        d = _orbit_transitions(*_ORBIT_CODES[n])
        best = (d, _cyclic_min_gap(d))
    for m in range(1, n // 2 + 1):
        A, _ = _transitions(n - m)
        B, _ = _transitions(m)
        for s in range(1, 1 << m, 2):
            d = _compose(A, n - m, B, m, s)
            g = _cyclic_min_gap(d)
            if best is None or g > best[1]:
                best = (d, g)
    return best


def long_run_transitions(n: int) -> np.ndarray:
    """Transition sequence of an ``n``-bit cyclic Gray code with long bit runs.

    Step ``k`` of the code flips bit ``delta[k]`` (bit 0 the least significant of the word);
    around the cycle, two flips of the same bit are at least :func:`long_run_min_run`
    (``n``) steps apart. Construction, deterministic:

    * ``n <= 6``: depth-first search from word 0 (bits in increasing order) for the largest
      gap ``r <= n`` it finds within 20 000 placed words: 1, 2, 2, 2, 4, 4 for ``n = 1 …
      6`` (optimal up to 5 bits: the search exhausts ``r + 1`` without a cycle, e.g. no
      3- or 4-bit cycle has gap 3; for 6 bits the search for 5 runs out of budget);
    * ``n = 8``: a stored code of gap 6 (``_ORBIT_CODES``), the orbit of a 32-transition block
      under the affine map ``x -> pi(x) XOR S`` of the 8-cube (``pi`` two 4-cycles of bits,
      ``S = 17``), which acts freely with order 8: 8 blocks, block ``j + 1`` is ``pi`` of
      block ``j``. Found by the depth-first search of ``scripts/search_long_run_codes.py``
      (numba, 479 306 nodes, about 11 CPU-s; it regenerates the stored block, a slow test checks
      that) — the symmetry is what makes it tractable: every placed transition places 8
      words;
    * ``n >= 7``: Goddyn, Lawrence & Nemeth 1988, Theorem 1 (:func:`_compose`), over every
      split ``n = (n - m) + m`` with ``m <= n / 2`` and every odd ``s < 2**m``, keeping the
      largest cyclic gap (the stored code when it is as good; first found on ties). From the
      8-bit code of gap 6, ``10 = 8 + 2`` with ``s = 3`` gives gap 8: a bit of the 8-bit code
      waits at least 6 of its letters plus 2 of the 2-bit code's (one every 4 letters), a bit
      of the 2-bit code 2 × 4 letters.

    Reached: 5, 6, 6, 8, 8, 8 for ``n = 7 … 12`` and 9, 9, 11, 11 for ``13 … 16`` (the table
    in ``docs/structured-light.md``, tested up to 12). Goddyn & Gvozdjak 2003 list the optima
    5, 6, 7, 8 for ``n = 7 … 10``: all reached but 9 bits (6; the orbit search for gap 7 with
    two 4-cycles and a fixed bit ran out of budget). Theorem 1 alone stops at 7 for 10 bits
    (10 = 5 + 5 needs ``s, t = 15, 17``, and a gap of 4 in the 5-bit code of the 17 letters
    meets the two adjacent letters of every period: 7 steps).

    Parameters
    ----------
    n : int in [1, MINSW_MAX_BITS]

    Returns
    -------
    (2**n,) int64 in [0, n)

    Raises
    ------
    InputError
        ``n`` out of range.
    """
    d, _ = _transitions(_check_long_run_bits(n))
    return d.copy()


def long_run_min_run(n: int) -> int:
    """Smallest gap between two flips of one bit of :func:`long_run_transitions` (``n``),
    around the cycle: a lower bound on every interior stripe's width (:func:`run_lengths`)."""
    return _transitions(_check_long_run_bits(n))[1]


@functools.cache
def _words(n: int) -> np.ndarray:
    w = _words_from_transitions(_transitions(n)[0]).astype(np.uint16)
    w.setflags(write=False)
    return w


def long_run_words(n: int) -> np.ndarray:
    """The ``"minsw"`` code's words in stripe order: stripe ``k`` is coded by word ``w[k]``,
    plane ``i`` (0 = projected first) its bit ``n - 1 - i``; ``w[0] = 0``.

    Returns
    -------
    (2**n,) uint16, read-only
        A permutation of ``0 … 2**n - 1``; neighbours differ in one bit.
    """
    return _words(_check_long_run_bits(n))


@functools.cache
def _table(n: int) -> np.ndarray:
    w = _words(n)
    t = np.empty(w.size, np.uint16)
    t[w] = np.arange(w.size, dtype=np.uint16)
    t.setflags(write=False)
    return t


def stripe_table(code: str, n: int) -> np.ndarray | None:
    """Code → stripe lookup of family ``code`` with ``n`` bits, or None for the families the
    decoder inverts arithmetically (Gray prefix XOR, the XOR base).

    Returns
    -------
    (2**n,) uint16, read-only, or None
        ``table[word]`` is the stripe whose projected planes read ``word`` (plane ``i`` at
        bit ``n - 1 - i``): the inverse permutation of :func:`long_run_words`.

    Raises
    ------
    InputError
        Unknown family; ``n`` out of range for ``"minsw"``.
    """
    check_choice(code, "code", CODE_FAMILIES)
    if code != "minsw":
        return None
    return _table(_check_long_run_bits(n))


def run_lengths(words: np.ndarray, n: int, interior: bool = True) -> np.ndarray:
    """Stripe widths of every plane of a linear code: the lengths of the runs of equal bits.

    Parameters
    ----------
    words : (N,) int
        Code words in stripe order.
    n : int
        Bits.
    interior : bool
        Leave out each plane's first and last run (cut by the projector's edge).

    Returns
    -------
    (R,) int64
        All planes' runs, concatenated (empty when no plane has an interior run).
    """
    w = np.asarray(words, np.int64)
    out = []
    for j in range(n):
        b = (w >> j) & 1
        edges = np.flatnonzero(np.diff(b)) + 1
        runs = np.diff(np.r_[0, edges, b.size])
        out.append(runs[1:-1] if interior else runs)
    return np.concatenate(out) if out else np.zeros(0, np.int64)
