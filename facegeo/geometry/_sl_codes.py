"""Binary code families for structured light: Gray and Gupta et al.'s XOR codes.

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

References
----------
Gupta, Agrawal, Veeraraghavan, Narasimhan. A Practical Approach to 3D Scanning in the Presence
of Interreflections, Subsurface Scattering and Defocus. IJCV 102, 2013, Sec. 4.
"""

from __future__ import annotations

import numpy as np

__all__ = ["CODE_FAMILIES", "base_plane", "code_bit", "min_bits"]

#: Code families a :class:`~facegeo.geometry.structured_light.PatternSpec` may project.
CODE_FAMILIES = ("gray", "xor02", "xor04")

_BASE_OFFSET = {"xor02": 1, "xor04": 2}


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
    code : {"gray", "xor02", "xor04"}
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
    g = s ^ (s >> 1)
    v = (g >> (n - 1 - bit)) & 1
    b = base_plane(code, n)
    if b is not None and bit < b:
        v = v ^ ((g >> (n - 1 - b)) & 1)
    return v
