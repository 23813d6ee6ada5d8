"""Z-buffer pre-pass for texel visibility: rasterised depth, exact rays only where ambiguous.

Issue 11: "a z-buffer pre-pass per camera (``cv2.triangleRasterizeDepth``) with exact rays only
where depth is ambiguous is one way to model only what the scene needs". :func:`depth_buffer`
renders the camera-frame depth ``z`` of the nearest surface at every pixel centre of a camera's
*pinhole* part (same K and pose, no distortion) with OpenCV's rasteriser, and
:func:`classify_occlusion` decides from it which texels are certainly visible or certainly
occluded; the rest get an exact Embree ray (:func:`facegeo.surface.reflectance.camera_visibility`
with ``occlusion="zbuffer"``).

Our K with OpenCV's symmetric frustum
-------------------------------------
``triangleRasterizeDepth`` takes a symmetric OpenGL frustum (``fovY``, square pixels, principal
point at the image centre, camera looking along −z with y up). Our pinhole is
``u = fx x / z + cx``, ``v = fy y / z + cy`` (camera frame: x right, y down, z forward, pixel
centres at integers). Pre-transforming each camera-frame vertex by the *linear* map ::

    x' = (fx x + (cx − c_u) z) / f,   y' = (fy y + (cy − c_v) z) / f,   z' = z

with ``f = fy``, ``fovY = 2 atan(H / (2 f))`` and ``c_u = W/2 − ½``, ``c_v = H/2 − ½`` (the
frustum's centre in our pixel-centre convention, measured: OpenCV puts pixel centres at
half-integers) gives ``f x'/z' + c_u = u`` and ``f y'/z' + c_v = v`` exactly, and keeps ``z``:
the buffer holds our camera's depth. A linear map keeps triangles planar, so rasterising the
transformed triangles is rasterising ours; ``world2cam = diag(1, −1, −1)`` turns our axes into
OpenGL's. The tests compare the buffer with Embree's pixel-centre rays (:func:`depth_image`).

Classification (per candidate texel ``p`` with geometric normal ``n``, camera frame)
-------------------------------------------------------------------------------------
Take the 3 × 3 pixel centres around the texel's pinhole projection and, along each one's ray,
the depth ``z_plane`` where the ray meets the texel's tangent plane ``n·(x − p) = 0``. With
``cos θ = n·v`` (``v`` toward the camera) and
``tol = margin_px · (z / f) / cos θ + margin_m``:

* **visible** when all nine buffer depths are within ``tol`` of ``z_plane`` (the pixels around
  the texel see the texel's own surface);
* **occluded** when all nine are nearer than ``z_plane − tol`` (something covers the whole
  neighbourhood in front of it);
* **ambiguous** otherwise, and always when ``cos θ < min_cos`` (0.3; the plane predicts a
  grazing neighbourhood poorly) or the neighbourhood leaves the image: an exact Embree ray
  decides.

Deviation: an occluder thinner than a pixel that covers none of the nine pixel centres is not
seen by the buffer; on a head mesh at camera resolution none exists (agreement with the
all-rays path is measured in the tests and the ``surface.visibility`` benchmark), and
``occlusion="rays"`` remains the reference.
"""

from __future__ import annotations

import numpy as np

from facegeo.checks import as_array
from facegeo.errors import InputError, ShapeError

__all__ = ["depth_buffer", "classify_occlusion", "DEFAULT_MIN_COS_SURE", "DEFAULT_MARGIN_PX",
           "DEFAULT_MARGIN_M"]

#: Texels seen more obliquely than this (cos θ of the geometric normal) are always ambiguous:
#: the tangent plane predicts their neighbourhood poorly (θ ≈ 73°).
DEFAULT_MIN_COS_SURE = 0.3
#: Tolerance of the depth about the tangent plane, in pixel footprints (z / f) along the view
#: (divided by cos θ) ...
DEFAULT_MARGIN_PX = 1.0
#: ... plus metres (curvature within the 3 × 3 neighbourhood, float32 rasterisation).
DEFAULT_MARGIN_M = 5e-4


def depth_buffer(vertices, faces, camera) -> np.ndarray:
    """Rasterised camera-frame depth of the nearest surface at each pixel centre (module doc).

    Parameters
    ----------
    vertices : (V, 3) float64, metres, world frame
    faces : (F, 3) int
    camera : facegeo.geometry.camera.Camera
        Its pinhole part (K and pose; distortion ignored), ``width × height`` pixels.

    Raises
    ------
    ShapeError, InputError
        Malformed vertices or faces (face indices out of range).

    Returns
    -------
    (H, W) float64, metres
        Depth ``z`` (camera frame) of the nearest triangle at each pixel centre; NaN where
        none. Triangles are clipped at a near plane ``z = ½ × (nearest vertex depth > 0)``, so
        only a mesh crossing the camera plane loses parts.
    """
    import cv2

    V = as_array(vertices, "vertices", shape=(None, 3))
    F = as_array(faces, "faces", shape=(None, 3), dtype=None, finite=False)
    if F.dtype.kind not in "iu":
        raise ShapeError(f"faces: expected an integer array, got dtype {F.dtype}")
    if F.size and (F.min() < 0 or F.max() >= len(V)):  # the rasteriser would read out of bounds
        raise InputError(f"faces: indices must lie in [0, {len(V)}), got "
                         f"[{int(F.min())}, {int(F.max())}]")
    p = camera.T_cam_world.apply(V)  # camera frame: x right, y down, z forward
    W, H = camera.width, camera.height
    f = camera.fy
    cu, cv = W / 2.0 - 0.5, H / 2.0 - 0.5
    x = (camera.fx * p[:, 0] + (camera.cx - cu) * p[:, 2]) / f
    y = (camera.fy * p[:, 1] + (camera.cy - cv) * p[:, 2]) / f
    verts = np.ascontiguousarray(np.stack([x, y, p[:, 2]], axis=1), np.float32)
    z_pos = p[:, 2][p[:, 2] > 0]
    if z_pos.size == 0:
        return np.full((H, W), np.nan)
    # The buffer stores OpenGL's normalised depth in float32; converting it back to z loses
    # ≈ z² / (2 z_near) × 6e-8, so z_near is kept as far out as the mesh allows (measured:
    # z_near = 1e-3 z_min gave a 25 µm bias at 1 m, z_min / 2 gives < 1 µm).
    z_near = float(z_pos.min()) * 0.5
    z_max = float(z_pos.max())
    z_far = z_max * 2.0 + 1.0
    buf = np.full((H, W), z_far, np.float32)
    settings = cv2.TriangleRasterizeSettings()
    settings.setCullingMode(cv2.RASTERIZE_CULLING_NONE)
    settings.setShadingType(cv2.RASTERIZE_SHADING_WHITE)
    world2cam = np.diag([1.0, -1.0, -1.0, 1.0])  # ours (y down, z forward) -> OpenGL's
    fov_y = 2.0 * np.arctan(H / (2.0 * f))
    depth = cv2.triangleRasterizeDepth(verts, np.ascontiguousarray(F, np.int32), buf,
                                       world2cam, fov_y, z_near, z_far, settings)
    out = depth.astype(np.float64)
    out[~(out < 0.5 * (z_max + z_far))] = np.nan  # untouched pixels hold ≈ z_far
    return out


def classify_occlusion(depth: np.ndarray, p_cam, n_cam, K, *,
                       min_cos: float = DEFAULT_MIN_COS_SURE,
                       margin_px: float = DEFAULT_MARGIN_PX,
                       margin_m: float = DEFAULT_MARGIN_M) -> tuple[np.ndarray, np.ndarray]:
    """Texels the z-buffer proves visible or occluded (module docstring).

    Parameters
    ----------
    depth : (H, W) float64, metres
        :func:`depth_buffer` (NaN: no surface).
    p_cam : (N, 3) float64, metres, camera frame
        Texel positions (z > 0).
    n_cam : (N, 3) float64, unit, camera frame
        Geometric normals of the texels' faces.
    K : (3, 3) float64, pixels
        The camera matrix the buffer was rendered with.
    min_cos, margin_px, margin_m : float
        See the module docstring.

    Returns
    -------
    visible, occluded : (N,) bool
        Disjoint; texels in neither are ambiguous and need an exact ray.
    """
    H, W = depth.shape
    n = len(p_cam)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    z = p_cam[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = fx * p_cam[:, 0] / z + cx
        v = fy * p_cam[:, 1] / z + cy
        cos = -np.einsum("tc,tc->t", n_cam, p_cam) / np.linalg.norm(p_cam, axis=1)
    c = np.rint(u)
    r = np.rint(v)
    ok = (z > 0) & (c >= 1) & (c <= W - 2) & (r >= 1) & (r <= H - 2) & (cos >= min_cos)
    visible = np.zeros(n, bool)
    occluded = np.zeros(n, bool)
    idx = np.flatnonzero(ok)  # NaN compares False above
    if idx.size == 0:
        return visible, occluded
    off = np.arange(-1, 2)
    rr = (r[idx].astype(np.int64)[:, None, None] + off[None, :, None]) + 0 * off[None, None, :]
    cc = (c[idx].astype(np.int64)[:, None, None] + off[None, None, :]) + 0 * off[None, :, None]
    rr, cc = rr.reshape(-1, 9), cc.reshape(-1, 9)
    nb = depth[rr, cc]
    # Depth of the texel's tangent plane n·(x − p) = 0 along each pixel-centre ray (x/z, y/z, 1).
    nc, pc = n_cam[idx], p_cam[idx]
    npd = np.einsum("tc,tc->t", nc, pc)[:, None]
    den = nc[:, 0, None] * (cc - cx) / fx + nc[:, 1, None] * (rr - cy) / fy + nc[:, 2, None]
    tol = (margin_px * z[idx] * 2.0 / (fx + fy) / cos[idx] + margin_m)[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):  # NaN (no surface) fails every test
        d = nb - npd / den
        visible[idx] = np.all(np.abs(d) <= tol, axis=1)
        occluded[idx] = np.all(d < -tol, axis=1)
    return visible, occluded
