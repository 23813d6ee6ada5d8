"""Search for a long-run cyclic Gray code with a free symmetry group (regenerates the data of
``facegeo.geometry._sl_codes._ORBIT_CODES``).

The code is sought as the orbit of one block under an affine map of the n-cube,
``A(x) = pi(x) XOR S`` (``pi`` a permutation of the bits, ``S`` a word): the transition sequence
is ``G`` blocks of ``P = 2**n / G`` transitions, block ``j`` being ``pi**j`` applied to the
first block ``T``, so the words are ``w[j P + i] = W_j XOR pi**j(p_i)`` with ``p_i`` the prefix
XOR of ``T`` and ``W_{j+1} = W_j XOR pi**j(S)``, ``S = p_P``. Only ``T`` (``P`` transitions)
is searched; each placed transition places ``G`` words at once, which prunes hard (restricting
a Gray-code search to codes with a symmetry is a standard device; this particular search is
this project's). The group must act freely on the words: for ``n = 8`` a rotation of all eight bits
cannot (``A**4`` then has fixed points for every even-weight ``S``), two 4-cycles with ``S``
odd on each can (``A**4`` is the complement, ``A**8`` the identity: ``G = 8``).

Depth-first, deterministic: ``S`` in increasing order, bits in increasing order, ``T[0] = 0``
free (every ``S`` whose block start words ``W_j`` are distinct is tried), a node budget per
``S``. Constraints checked when a transition is placed: the cyclic gap ``r`` inside ``T`` and
across the block boundary (the next block's transitions are ``pi`` of ``T``'s), every new word
unvisited, and the Hamming distance from ``p_i`` to ``S`` within the steps left.

Usage, from the repository root (numba; the default takes 479 306 nodes, about 11 CPU-s)::

    python scripts/search_long_run_codes.py                    # 8 bits, gap 6 (stored code)
    python scripts/search_long_run_codes.py 9 7 "[[0,1,2,3],[4,5,6,7],[8]]" 8 3000000

Arguments: bits, gap, the bit permutation's cycles, blocks G, node budget per S. The block is
printed one digit per transition (bit index), as ``_ORBIT_CODES`` stores it: ``n <= 10``.
"""

from __future__ import annotations

import ast
import sys
import time
from pathlib import Path

import numba as nb
import numpy as np

#: The stored search: 8 bits, gap 6, two 4-cycles, 8 blocks, 3 M nodes per S.
DEFAULT = (8, 6, ((0, 1, 2, 3), (4, 5, 6, 7)), 8, 3_000_000)


@nb.njit(cache=True)
def _permute_word(x, perm, n):
    y = 0
    for b in range(n):
        if (x >> b) & 1:
            y |= 1 << perm[b]
    return y


@nb.njit(cache=True)
def _search_block(n, r, S, perms, G, budget):
    """First block ``T`` for start ``S`` (empty when none; nodes, -1 over budget)."""
    N = 1 << n
    P = N // G
    order = perms.shape[0]
    W = np.zeros(G + 1, np.int64)
    for j in range(G):
        W[j + 1] = W[j] ^ _permute_word(S, perms[j % order], n)
    none = np.zeros(0, np.int64)
    if W[G] != 0:
        return none, 0
    seen = np.zeros(N, np.uint8)
    for j in range(G):
        if seen[W[j]]:
            return none, 0
        seen[W[j]] = 1
    pi = perms[1 % order]
    T = np.full(P, -1, np.int64)
    p = np.zeros(P + 1, np.int64)
    nxt = np.zeros(P, np.int64)
    ws = np.zeros(G, np.int64)
    i = 0
    nodes = 0
    while i >= 0:
        placed = False
        while nxt[i] < n:
            b = nxt[i]
            nxt[i] += 1
            ok = True
            for k in range(max(0, i - r + 1), i):  # gap inside the block
                if T[k] == b:
                    ok = False
                    break
            if ok and i > P - r:  # gap to the next block's first transitions, pi(T[k])
                for k in range(i + r - P):
                    if pi[T[k]] == b:
                        ok = False
                        break
            if not ok:
                continue
            q = p[i] ^ (1 << b)
            if i == P - 1:
                if q == S:
                    T[i] = b
                    return T, nodes
                continue
            x = q ^ S
            c = 0
            while x:
                x &= x - 1
                c += 1
            if c > P - 1 - i:
                continue
            jbad = -1
            for j in range(G):
                ws[j] = W[j] ^ _permute_word(q, perms[j % order], n)
                if seen[ws[j]]:
                    jbad = j
                    break
                seen[ws[j]] = 1
            if jbad >= 0:
                for jj in range(jbad):
                    seen[ws[jj]] = 0
                continue
            nodes += 1
            if nodes > budget:
                return none, -1
            T[i] = b
            p[i + 1] = q
            i += 1
            nxt[i] = 0
            placed = True
            break
        if not placed:
            i -= 1
            if i >= 0:
                q = p[i + 1]
                for j in range(G):
                    seen[W[j] ^ _permute_word(q, perms[j % order], n)] = 0
                T[i] = -1
    return none, nodes


def bit_permutation_powers(cycles) -> np.ndarray:
    """(order, n) int64: row ``j`` maps bit ``b`` to ``pi**j(b)``, ``pi`` given by its cycles."""
    n = sum(len(c) for c in cycles)
    pi = list(range(n))
    for c in cycles:
        for a, b in zip(c, tuple(c[1:]) + tuple(c[:1])):
            pi[a] = b
    perms = [list(range(n))]
    while True:
        nxt = [pi[x] for x in perms[-1]]
        if nxt == list(range(n)):
            break
        perms.append(nxt)
    return np.array(perms, np.int64)


def search(n, r, cycles, G, budget, log=None):
    """First ``(S, T, nodes)`` over ``S = 0, 1, …`` (None if every S fails or runs out)."""
    perms = bit_permutation_powers(cycles)
    for S in range(1 << n):
        T, nodes = _search_block(n, r, S, perms, G, budget)
        if T.size:
            return S, "".join(map(str, T)), nodes
        if log is not None and nodes:
            log(f"S = {S}: {'over budget' if nodes < 0 else f'none ({nodes} nodes)'}")
    return None


def main(argv):
    if argv:
        if len(argv) != 5:
            print(__doc__)
            return 2
        n, r = int(argv[0]), int(argv[1])
        cycles = ast.literal_eval(argv[2])
        G, budget = int(argv[3]), int(argv[4])
    else:
        n, r, cycles, G, budget = DEFAULT
    t0 = time.perf_counter()
    res = search(n, r, cycles, G, budget, log=print)
    dt = time.perf_counter() - t0
    if res is None:
        print(f"no {n}-bit code with gap {r} found ({dt:.1f} s)")
        return 1
    S, T, nodes = res
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's facegeo
    from facegeo.geometry._sl_codes import (
        _cyclic_min_gap,
        _orbit_transitions,
        _words_from_transitions,
    )

    d = _orbit_transitions(T, cycles, G)  # the library's expansion, checked independently
    w = _words_from_transitions(d)
    ok = np.unique(w).size == 1 << n and w[-1] == 1 << d[-1] and _cyclic_min_gap(d) >= r
    print(f"n = {n}, gap {r}, cycles {cycles}, {G} blocks: S = {S}, T = {T!r}, "
          f"{nodes} nodes, {dt:.1f} s; expanded code: every word once, cyclic gap "
          f"{_cyclic_min_gap(d)} ({'ok' if ok else 'FAILED'})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
