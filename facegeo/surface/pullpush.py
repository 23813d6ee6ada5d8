"""Pull–push hole filling in texture space (Gortler et al. 1996, *The Lumigraph*, §3.4).

Texels no camera sees are *flagged*, never measured; :func:`pull_push` fills them from their
neighbours across a pyramid, for the atlas previews and for the novel-view renderer's inferred
texels (:func:`facegeo.render.novel.infer_texel_colours`: surface no camera saw, marked as
inferred and never counted as measured):

* **pull**: each coarser level holds the weighted mean of 2 × 2 finer texels, with weight the
  sum of the (clamped) finer weights, clamped to 1;
* **push**: each finer texel keeps its own value in proportion to its clamped weight ``w`` and
  takes ``1 − w`` from the coarser level (nearest-neighbour upsampled).

Texels with weight ≥ 1 are returned unchanged, so measured data is never altered; the filled
values are inferences, kept apart from measured ones by the caller's mask.
"""

from __future__ import annotations

import numpy as np

from facegeo.checks import as_array
from facegeo.errors import InputError, ShapeError

__all__ = ["pull_push"]


def _pull(v: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    h, wd = w.shape
    H2, W2 = (h + 1) // 2, (wd + 1) // 2
    wp = np.zeros((2 * H2, 2 * W2), np.float64)
    vp = np.zeros((2 * H2, 2 * W2) + v.shape[2:], np.float64)
    wp[:h, :wd] = w
    vp[:h, :wd] = v * w[..., None]
    ws = wp.reshape(H2, 2, W2, 2).sum(axis=(1, 3))
    vs = vp.reshape(H2, 2, W2, 2, -1).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        vc = np.where(ws[..., None] > 0, vs / ws[..., None], 0.0)
    return vc, np.minimum(ws, 1.0)


def pull_push(values, weights, *, levels: int | None = None) -> np.ndarray:
    """Fill low-weight texels of an image from a weighted pyramid.

    Parameters
    ----------
    values : (H, W) or (H, W, C) float
        Image; values where ``weights == 0`` are ignored (may be NaN).
    weights : (H, W) float, ≥ 0
        Confidence per texel; 0 = unknown, ≥ 1 = fully trusted (kept as is).
    levels : int, optional
        Pyramid depth; default until the coarsest level is 1 × 1.

    Returns
    -------
    (H, W) or (H, W, C) float32
        Filled image; texels are NaN only when every weight is 0.
    """
    v = as_array(values, "values", dtype=np.float64, finite=False)
    if v.ndim not in (2, 3):
        raise ShapeError(f"values: expected shape (H, W) or (H, W, C), got {v.shape}")
    w = as_array(weights, "weights", shape=v.shape[:2])
    if np.any(w < 0):
        raise InputError("weights: expected weights >= 0")
    squeeze = v.ndim == 2
    if squeeze:
        v = v[..., None]
    w = np.minimum(w, 1.0)
    v = np.where(w[..., None] > 0, v, 0.0)
    if not np.all(np.isfinite(v)):
        raise InputError("values: non-finite values where the weight is > 0")
    pyr = [(v, w)]
    n = 0
    while max(pyr[-1][1].shape) > 1 and (levels is None or n < levels):
        pyr.append(_pull(*pyr[-1]))
        n += 1
    cur, cw = pyr[-1]
    out = np.where(cw[..., None] > 0, cur, np.nan)
    for vf, wf in reversed(pyr[:-1]):
        h, wd = wf.shape
        up = np.repeat(np.repeat(out, 2, axis=0), 2, axis=1)[:h, :wd]
        with np.errstate(invalid="ignore"):
            out = np.where(wf[..., None] >= 1, vf,
                           wf[..., None] * vf + (1 - wf[..., None]) * up)
        out = np.where((wf[..., None] > 0) & ~np.isfinite(up), vf, out)
    out = out.astype(np.float32)
    return out[..., 0] if squeeze else out
