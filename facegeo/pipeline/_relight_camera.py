"""A camera view of ``facegeo relight`` under a batch of environment maps (Debevec et al. 2000
§3.3, Eq. 4 on the OLAT frames), split out of :mod:`facegeo.pipeline.relight`
(:func:`facegeo.pipeline.relight.relight_maps_products` calls it per batch).
"""

from __future__ import annotations

import numpy as np


def _relight_camera_batch(scan, view: str, weights: list, progress, read_ahead: int) -> list:
    """A camera view under a batch of maps: per map ``(image, its pixels' radiance)``.

    One map: :func:`facegeo.lighting.relight.relight_scan_view`. Several: Eq. 4 from the OLAT
    frames lit by any map of the batch, each frame read once and added to every map lighting
    it, ``acc_b += frame · w_b[l]`` in float64 in light order — the arithmetic of
    :func:`facegeo.lighting.relight.relight_frames`, so each image is the same bytes as the map
    alone. Holds B float64 images (24 B a pixel and map)."""
    from facegeo.lighting.envmap import field_weights
    from facegeo.lighting.relight import (_raise_first_nonfinite_frame, normalize_weights,
                                          relight_scan_view)

    if len(weights) == 1:
        img = relight_scan_view(scan, view, weights[0], normalize_color=True,
                                progress=progress, read_ahead=read_ahead)
        return [(img, img.reshape(-1, 3))]
    n_l = scan.n_lights
    # each light's own colour, as relight_scan_view(normalize_color=True)
    W = [field_weights(normalize_weights(w, n_l)[0], scan.rig.lights) for w in weights]
    lit = np.stack([np.any(w != 0, axis=1) for w in W])  # (B, L)
    active = np.flatnonzero(lit.any(axis=0))
    acc: list = [None] * len(W)
    for k, (l, frame) in enumerate(scan.iter_olat(view, active.tolist(),
                                                  read_ahead=read_ahead)):
        frame = np.asarray(frame)
        for b, w in enumerate(W):
            if lit[b, l]:
                if acc[b] is None:
                    acc[b] = np.zeros(frame.shape, np.float64)
                acc[b] += frame * w[l]
        if progress:
            progress(k)
    cam = scan.camera(view)
    out = []
    for b, a in enumerate(acc):
        img = (np.zeros((cam.height, cam.width, 3), np.float32) if a is None
               else a.astype(np.float32))
        if not np.isfinite(img).all():
            _raise_first_nonfinite_frame(scan, view, np.flatnonzero(lit[b]))
        out.append((img, img.reshape(-1, 3)))
    return out
