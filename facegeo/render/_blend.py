"""What the texture-space renderer (:mod:`facegeo.render.novel`) and the image-space detail
(:mod:`facegeo.render.detail`) share: the view-dependent blend's constants, the angle between
views, and the environment's key lights."""

from __future__ import annotations

import numpy as np

#: Angles below this (radians) count as the source view itself: its measured function is used
#: unchanged (the paper's guarantee), and θ is floored here in the weight.
SAME_VIEW_RAD = 1e-7
#: A source camera whose blend weight is below this share of a texel's total is left out of
#: that texel (not read, not resynthesised); the others are renormalised, so the blend moves by
#: at most this fraction of the difference between cameras.
BLEND_MIN_SHARE = 1e-3


def _angle(a, b):
    """Angle between unit vectors, accurate near 0 (atan2 of |a×b| and a·b)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("...i,...i->...", a, b))


def key_lights(weights, key_share: float, max_lights: int) -> np.ndarray:
    """Lights carrying at least ``key_share`` of the energy of Eq. (4) ``weights`` ``(L, 3)``
    (summed over channels), the strongest first, at most ``max_lights``."""
    e = np.abs(np.asarray(weights, np.float64)).sum(axis=1)
    total = e.sum()
    if not total > 0:
        return np.zeros(0, np.int64)
    order = np.argsort(-e, kind="stable")
    return order[e[order] >= key_share * total][:max_lights].astype(np.int64)
