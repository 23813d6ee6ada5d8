"""Silhouettes: where a camera saw the subject end, as oriented points for the filled surface.

A camera that sees the head against the light stage's dark background measures its occluding
contour: the ray through a pixel on the silhouette's edge grazes the head, and the surface
there is tangent to the plane of that ray and its neighbour along the edge. The structured
light reaches the face; the cameras' silhouettes go round the side of the head, the crown and
the jaw, farther than the projector lights — and that is exactly where the filled surface's
Poisson continuation is a guess (issue 37: ≈ 0.07 mm outward per mm past the data, the
crown and the back of the head rendered 1–2 px outside the true silhouette).

:func:`silhouette_mask` finds the subject in a camera's image (the per-pixel maximum over its
one-light-at-a-time frames); :func:`rim_points` turns the mask's edge into *rim points*: on
each edge pixel's ray, the midpoint of the chord a provisional surface cuts (for a ray that
grazes the true surface, the surface's tangent point when the provisional one lies a
uniform distance outside it: the chord of a parallel surface is bisected by the tangent point),
oriented by the tangent plane. They are support points of the filled surface's Poisson solve
(:func:`facegeo.geometry.mesh.poisson_mesh` ``support``): they shape it where they are,
never the trimmed mesh, its trim, or which faces count as measured. This is the visual-hull
constraint (Laurentini 1994) used as data of a smooth surface rather than as a carved volume:
two cameras' hull is far too loose in depth to be a surface, but each rim is a curve the
surface touches.

A ray that misses the provisional surface (the guess lies inside the head there) gives the
point of the ray closest to the surface, within :data:`RIM_MAX_GAP`: the rim pulls a surface
that sagged inside back out as it pulls one that drifted outside in.
"""

from __future__ import annotations

import numpy as np

from facegeo.checks import as_array
from facegeo.errors import InputError

__all__ = ["SILHOUETTE_REL", "BACKGROUND_FRAME", "BORDER_PX", "RIM_MAX_GAP", "silhouette_mask",
           "rim_points"]

#: A pixel is the subject's when its brightest light rises above the background by at least
#: this fraction of the way to the median over the pixels known to be the subject's (where
#: structured-light points project): dark hair at a tenth of skin's albedo stays in, a dark
#: background stays out.
SILHOUETTE_REL = 0.05

#: The background level: the 99th percentile of the brightest image over its outer frame, this
#: fraction of the smaller side wide (at least 2 px) — a light stage's dark background there,
#: noise and black level included (DiLiGenT's 8-bit frames: 3–6 of 255 against the objects'
#: 48–61). Capped at half the subject's level: a frame the subject fills is not background.
BACKGROUND_FRAME = 0.02

#: Edge pixels this close to the image border are left out: there the frame cut the subject,
#: not its contour.
BORDER_PX = 2

#: A silhouette ray that misses the provisional surface gives its point closest to the surface
#: when that is within this, metres: the filled surface sags inside the head by a few
#: millimetres past the data (docs/mesh.md); farther is another object's contour (a shoulder,
#: a stand) or no surface at all.
RIM_MAX_GAP = 0.015

#: Samples along a missing ray (over the surface's depth range from the camera), twice: the
#: second pass over ±2 steps of the first's best.
RIM_SAMPLES = 256


def silhouette_mask(brightest, subject_px, *, rel: float = SILHOUETTE_REL) -> np.ndarray:
    """The subject's pixels in one camera.

    Parameters
    ----------
    brightest : (H, W) float
        Per pixel, the brightest value over the lights (e.g. the maximum over the channels of
        a spread of one-light-at-a-time frames); NaN counts as dark.
    subject_px : (N, 2) float
        Pixels (column, row) known to show the subject (the structured-light points'
        projections); those outside the image are ignored.
    rel : float in (0, 1)
        :data:`SILHOUETTE_REL`.

    Returns
    -------
    (H, W) bool
        The connected regions at or above ``background + rel · (level − background)`` —
        ``level`` the median over the known pixels, ``background`` the image frame's
        (:data:`BACKGROUND_FRAME`) — that hold at least 1 % of ``subject_px``, holes filled
        (eyes, nostrils and mouth are the subject's too). On DiLiGenT's ball and cat (48 of
        their 96 lights, the known pixels a sample of their masks eroded by 15 px) the masks'
        IoU is 0.985 / 0.990, against 0.810 / 0.783 for Otsu's threshold on the same image and
        0.881 / 0.560 for ``rel · level`` alone (its background is not black:
        ``tests/test_silhouette.py``).

    Raises
    ------
    InputError
        ``brightest`` not 2-D, ``rel`` outside (0, 1), no known pixel inside the image, or the
        known pixels dark.
    """
    from scipy import ndimage

    img = np.nan_to_num(np.asarray(brightest, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if img.ndim != 2:
        raise InputError(f"brightest: expected an (H, W) image, got shape {img.shape}")
    if not 0.0 < rel < 1.0:
        raise InputError(f"rel: expected a fraction in (0, 1), got {rel!r}")
    q = as_array(subject_px, "subject_px", shape=(None, 2))
    h, w = img.shape
    c, r = np.rint(q[:, 0]).astype(np.int64), np.rint(q[:, 1]).astype(np.int64)
    inside = (c >= 0) & (c < w) & (r >= 0) & (r < h)
    if not inside.any():
        raise InputError("subject_px: no known subject pixel lies in the image")
    level = float(np.median(img[r[inside], c[inside]]))
    if not level > 0.0:
        raise InputError("brightest: the known subject pixels are dark (median 0): no "
                         "silhouette to find")
    b = max(2, int(BACKGROUND_FRAME * min(h, w)))
    frame = np.concatenate([img[:b].ravel(), img[-b:].ravel(), img[:, :b].ravel(),
                            img[:, -b:].ravel()])
    background = min(max(float(np.percentile(frame, 99)), 0.0), 0.5 * level)
    lab, n = ndimage.label(img >= background + rel * (level - background))
    counts = np.bincount(lab[r[inside], c[inside]], minlength=n + 1)
    keep = np.flatnonzero(counts >= max(1, 0.01 * inside.sum()))
    keep = keep[keep > 0]
    return ndimage.binary_fill_holes(np.isin(lab, keep))


def rim_points(camera, mask, vertices, faces, *, border_px: int = BORDER_PX,
               max_gap: float = RIM_MAX_GAP) -> dict:
    """Oriented rim points of one camera's silhouette against a provisional closed-ish surface.

    Parameters
    ----------
    camera : facegeo.geometry.camera.Camera
        The camera the mask was taken in (world frame).
    mask : (H, W) bool
        :func:`silhouette_mask`; its size must be the camera's.
    vertices : (V, 3) float64, metres, world frame
    faces : (F, 3) int
        The provisional surface (the filled surface of the points alone).
    border_px : int
        :data:`BORDER_PX`.
    max_gap : float, metres
        A ray that misses the surface gives the point of it closest to the surface when that
        is within this (:data:`RIM_MAX_GAP`; 0: never).

    Returns
    -------
    dict
        ``points`` (M, 3) float64 and ``normals`` (M, 3) float64 unit, outward (away from the
        silhouette's inside, perpendicular to the pixel's ray), one per edge pixel whose ray
        cuts the surface at least twice (the chord's midpoint) or passes outside it within
        ``max_gap`` (its closest point); ``pixels`` (M, 2) the edge pixels they came from;
        ``edge_pixels`` (all edge pixels away from the border), ``outside`` (points from
        rays that passed outside the surface) and ``missed`` (edge pixels with no point: a
        single crossing, or farther than ``max_gap`` from the surface).

    Notes
    -----
    The edge pixels are the mask's pixels with a 4-neighbour outside it. The outward image
    normal is the gradient of the mask's smoothed signed distance (σ = 1.5 px); the surface
    normal is that of the plane holding the pixel's ray and the ray one pixel along the edge,
    turned toward the outside.
    """
    from scipy import ndimage

    m = np.asarray(mask, bool)
    if m.shape != (camera.height, camera.width):
        raise InputError(f"mask: shape {m.shape} is not camera {camera.name}'s "
                         f"{(camera.height, camera.width)}")
    V = as_array(vertices, "vertices", shape=(None, 3))
    F = np.asarray(faces, np.int64)
    empty = {"points": np.zeros((0, 3)), "normals": np.zeros((0, 3)),
             "pixels": np.zeros((0, 2)), "edge_pixels": 0, "outside": 0, "missed": 0}
    edge = m & ~ndimage.binary_erosion(m, structure=ndimage.generate_binary_structure(2, 1))
    b = int(border_px)
    if b > 0:
        edge[:b, :] = edge[-b:, :] = False
        edge[:, :b] = edge[:, -b:] = False
    rows, cols = np.nonzero(edge)
    if not len(rows) or not len(F):
        return empty | {"edge_pixels": int(len(rows)), "missed": int(len(rows))}
    sd = ndimage.distance_transform_edt(~m) - ndimage.distance_transform_edt(m)
    gy, gx = np.gradient(ndimage.gaussian_filter(sd, 1.5))
    n2 = np.stack([gx[rows, cols], gy[rows, cols]], axis=-1)
    n2 /= np.maximum(np.linalg.norm(n2, axis=1, keepdims=True), 1e-12)
    t2 = np.stack([-n2[:, 1], n2[:, 0]], axis=-1)  # along the edge
    q = np.stack([cols, rows], axis=-1).astype(np.float64)
    origin, d = camera.pixel_rays(q)
    _, d_out = camera.pixel_rays(q + n2)
    _, d_along = camera.pixel_rays(q + t2)
    normal = np.cross(d, d_along - d)
    normal *= np.where(np.einsum("ij,ij->i", normal, d_out - d) < 0, -1.0, 1.0)[:, None]
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    ok = np.isfinite(d).all(axis=1) & np.isfinite(normal).all(axis=1)
    t_rim, outside = _rim_depths(V, F, origin[ok], d[ok], max_gap)
    found = np.isfinite(t_rim)
    idx = np.flatnonzero(ok)[found]
    t_rim = t_rim[found]
    return {"points": origin[idx] + t_rim[:, None] * d[idx], "normals": normal[idx],
            "pixels": q[idx], "edge_pixels": int(len(rows)),
            "outside": int((found & outside).sum()),
            "missed": int(len(rows) - len(idx))}


def _rim_depths(V, F, origins, directions, max_gap: float) -> tuple[np.ndarray, np.ndarray]:
    """Per ray, the distance along it to its rim point (NaN: none) and whether the ray passed
    outside the surface. A ray that cuts the surface twice or more: the midpoint of its first
    two crossings. A ray that misses it (the surface lies inside the silhouette there): the
    ray's point closest to the surface, when that is within ``max_gap`` — for a surface a
    uniform distance inside the true one, the tangent point again. Open3D's ray casting and
    distance queries."""
    import open3d as o3d

    from facegeo.geometry._mesh_measure import _closest_scene

    scene = _closest_scene(V, F)
    rays = o3d.core.Tensor(np.hstack([origins, directions]).astype(np.float32))
    hits = scene.list_intersections(rays)
    splits = hits["ray_splits"].numpy().astype(np.int64)
    t = hits["t_hit"].numpy().astype(np.float64)
    ray = np.repeat(np.arange(len(origins)), np.diff(splits))
    order = np.lexsort((t, ray))  # by ray, then by distance along it
    t = t[order]
    out = np.full(len(origins), np.nan)
    count = np.diff(splits)
    two = count >= 2
    first = splits[:-1][two]
    out[two] = 0.5 * (t[first] + t[first + 1])
    miss = np.flatnonzero(count == 0)
    if len(miss) and max_gap > 0:
        # the surface's depth range from each camera centre, sampled, then refined once
        reach = np.linalg.norm(V - origins[miss[0]], axis=1)  # one camera: one centre
        lo, hi = float(reach.min()), float(reach.max())
        o, d = origins[miss], directions[miss]
        tt = np.linspace(lo, hi, RIM_SAMPLES)[None, :].repeat(len(miss), axis=0)
        for _ in range(2):
            pts = o[:, None, :] + tt[..., None] * d[:, None, :]
            dist = scene.compute_distance(o3d.core.Tensor(
                pts.reshape(-1, 3).astype(np.float32))).numpy().reshape(tt.shape)
            best = np.argmin(dist, axis=1)
            step = tt[:, 1] - tt[:, 0]
            centre = tt[np.arange(len(miss)), best]
            gap = dist[np.arange(len(miss)), best]
            tt = centre[:, None] + np.linspace(-2, 2, RIM_SAMPLES)[None, :] * step[:, None]
        close = gap <= max_gap
        out[miss[close]] = centre[close]
    return out, count == 0
