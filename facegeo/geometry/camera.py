"""A pinhole camera with OpenCV's lens distortion: projection, unprojection and pixel rays.

Conventions (``docs/conventions.md``, :mod:`facegeo.frames`):

* **Pose**: ``T_cam_world`` maps world points to the camera frame,
  ``p_cam = R_cam_world @ p_world + t_cam_world`` (OpenCV's rvec/tvec).
* **Camera frame**: OpenCV's, x right, y down, z forward.
* **Pixels**: ``q = (x, y)`` = (column, row); integer coordinates are pixel centres, so the image
  covers ``[-0.5, W - 0.5) × [-0.5, H - 0.5)``.
* **Normalised image coordinates** ``x_n = (X/Z, Y/Z)`` (undistorted) and ``x_d`` (distorted), with
  ``q = (fx·x_d + cx, fy·y_d + cy)``.
* **Distortion**: OpenCV's rational/radial-tangential model, coefficients in OpenCV's order
  ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``; 0, 4, 5 or 8 of them::

      r² = x² + y²,   g = (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
      x_d = x g + 2 p1 x y + p2 (r² + 2 x²)
      y_d = y g + p1 (r² + 2 y²) + 2 p2 x y

Per-element failure (a point behind the camera, an undistortion that does not converge) is NaN
plus a boolean mask, never an exception.

References
----------
.. [1] OpenCV, "Camera Calibration and 3D Reconstruction" (calib3d module documentation).
.. [2] Debevec et al., "Acquiring the Reflectance Field of a Human Face", SIGGRAPH 2000, §2.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from facegeo.checks import as_array, check_positive, check_positive_int, fmt_value
from facegeo.errors import InputError, ShapeError
from facegeo.frames import Pose

__all__ = ["Camera", "DIST_LENGTHS", "UNDISTORT_TOL", "UNDISTORT_MAX_ITER"]

#: Allowed numbers of distortion coefficients (OpenCV order).
DIST_LENGTHS = (0, 4, 5, 8)

#: Convergence threshold of :meth:`Camera.undistort`: max |distort(x_n) − x_d|, normalised image
#: units (1e-13 ≈ 1e-10 px at f = 1000 px).
UNDISTORT_TOL = 1e-13

#: Newton iterations allowed in :meth:`Camera.undistort` (it needs 3–6 for realistic lenses).
UNDISTORT_MAX_ITER = 30

_CAMERA_KEYS = ("name", "width", "height", "K", "dist", "T_cam_world")


def _check_int(value: Any, name: str) -> int:
    """A positive integer (Python or numpy int, or an integral float); else :class:`InputError`."""
    return check_positive_int(value, name)


def _dist8(dist: np.ndarray) -> np.ndarray:
    """Pad OpenCV distortion coefficients to the 8-vector (k1, k2, p1, p2, k3, k4, k5, k6)."""
    d = np.zeros(8)
    d[: dist.shape[0]] = dist
    return d


@functools.lru_cache(maxsize=256)
def _fold_radius(dist: tuple) -> float:
    """Normalised radius r_fold where the radial(+rational) distortion stops increasing.

    Along a ray of normalised radius r the distorted radius is ``r_d(r) = r·P(s)/Q(s)``,
    ``s = r²``, ``P = 1 + k1 s + k2 s² + k3 s³``, ``Q = 1 + k4 s + k5 s² + k6 s³`` (the radial
    part of the model in the module docstring). ``dr_d/dr = N(s)/Q(s)²`` with
    ``N = P Q + 2 s (P′ Q − P Q′)``, so the model folds over (or meets the pole Q = 0) at the
    smallest positive real root of N·Q; ``inf`` when there is none. Exact (polynomial roots,
    once per coefficient tuple, cached). Deviation: the tangential terms p1, p2 are left out
    (they are small and make the fold direction-dependent); the fold is then that of the
    radial model.
    """
    d = np.zeros(8)
    d[: len(dist)] = dist
    k1, k2, _p1, _p2, k3, k4, k5, k6 = d
    P = np.polynomial.Polynomial([1.0, k1, k2, k3])
    Q = np.polynomial.Polynomial([1.0, k4, k5, k6])
    s = np.polynomial.Polynomial([0.0, 1.0])
    N = P * Q + 2.0 * s * (P.deriv() * Q - P * Q.deriv())
    best = np.inf
    for poly in (N, Q):
        c = poly.trim(tol=0.0).coef
        if len(c) < 2:
            continue  # constant 1 (+ terms exactly 0): never 0
        for root in np.roots(c[::-1]):
            if abs(root.imag) <= 1e-12 * max(1.0, abs(root.real)) and root.real > 0:
                best = min(best, float(root.real))
    return float(np.sqrt(best)) if np.isfinite(best) else np.inf


@dataclass(frozen=True, eq=False)
class Camera:
    """A calibrated camera (or projector): intrinsics, OpenCV distortion and pose.

    Immutable: the arrays are read-only copies; derive variants with :meth:`scaled` or
    :func:`dataclasses.replace`.

    Parameters
    ----------
    name : str
        Identifier, unique within a rig (``"cam_left"``).
    width, height : int, pixels
        Image size: ``width`` columns, ``height`` rows.
    K : (3, 3) float64, pixels
        ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``: zero skew, ``fx, fy > 0``.
    dist : (n,) float64
        OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``, n ∈ {0, 4, 5, 8}.
        ``None`` means no distortion.
    T_cam_world : facegeo.frames.Pose
        World-to-camera transform (metres). For a projector, the projector's pose.

    Raises
    ------
    InputError, ShapeError
        A field is malformed; the message starts with the field's name.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    T_cam_world: Pose

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise InputError(f"name: expected a non-empty string, got {fmt_value(self.name)}")
        width = _check_int(self.width, "width")
        height = _check_int(self.height, "height")
        K = as_array(self.K, "K", shape=(3, 3), copy=True)
        off = [K[0, 1], K[1, 0], K[2, 0], K[2, 1]]
        if any(v != 0.0 for v in off) or K[2, 2] != 1.0:
            raise InputError(
                "K: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (zero skew), got "
                f"{np.array2string(K, separator=', ')}"
            )
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise InputError(f"K: focal lengths must be > 0, got fx={fmt_value(K[0, 0])}, fy={fmt_value(K[1, 1])}")
        dist = np.zeros(0) if self.dist is None else self.dist
        dist = as_array(dist, "dist", shape=(None,), copy=True)
        if dist.shape[0] not in DIST_LENGTHS:
            raise ShapeError(
                f"dist: expected 0, 4, 5 or 8 OpenCV coefficients (k1, k2, p1, p2[, k3[, k4, k5, "
                f"k6]]), got {dist.shape[0]}"
            )
        if not isinstance(self.T_cam_world, Pose):
            got = type(self.T_cam_world).__name__
            raise InputError(f"T_cam_world: expected a facegeo.frames.Pose, got {got}")
        K.setflags(write=False)
        dist.setflags(write=False)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)

    # ------------------------------------------------------------------ basic properties

    @property
    def fx(self) -> float:
        """Horizontal focal length, pixels."""
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        """Vertical focal length, pixels."""
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        """Principal point column, pixels (pixel-centre convention)."""
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        """Principal point row, pixels (pixel-centre convention)."""
        return float(self.K[1, 2])

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)``, pixels (OpenCV's ``imageSize`` order)."""
        return (self.width, self.height)

    @property
    def center_world(self) -> np.ndarray:
        """Centre of projection, ``(3,)`` float64, metres, world frame."""
        return self.T_cam_world.origin_of_a_in_b

    @property
    def has_distortion(self) -> bool:
        """True if any distortion coefficient is non-zero."""
        return bool(np.any(self.dist != 0.0))

    def __eq__(self, other) -> bool:
        return (
            isinstance(other, Camera)
            and self.name == other.name
            and self.width == other.width
            and self.height == other.height
            and np.array_equal(self.K, other.K)
            and np.array_equal(self.dist, other.dist)
            and self.T_cam_world == other.T_cam_world
        )

    __hash__ = None  # type: ignore[assignment]

    # ------------------------------------------------------------------ distortion

    def distort(self, x_n) -> np.ndarray:
        """Apply lens distortion to normalised image coordinates.

        Parameters
        ----------
        x_n : (..., 2) float64, normalised image coordinates (X/Z, Y/Z), camera frame
            NaN passes through.

        Returns
        -------
        x_d : (..., 2) float64, distorted normalised image coordinates
        """
        x_n = as_array(x_n, "x_n", shape=(..., 2), finite=False)
        if not self.has_distortion:
            return x_n.copy()
        return self._distort(x_n, jacobian=False)[0]

    def _distort(self, x_n: np.ndarray, *, jacobian: bool):
        """Distortion ``(..., 2)`` and, if asked, its Jacobian ``(..., 2, 2)`` (d x_d / d x_n)."""
        xd, yd, jac = self._distort_xy(x_n[..., 0], x_n[..., 1], jacobian=jacobian)
        out = np.stack([xd, yd], axis=-1)
        if not jacobian:
            return out, None
        jxx, jxy, jyy = jac
        J = np.stack([np.stack([jxx, jxy], -1), np.stack([jxy, jyy], -1)], -2)
        return out, J

    def _distort_xy(self, x: np.ndarray, y: np.ndarray, *, jacobian: bool):
        """Kernel of :meth:`distort` on separate x, y arrays.

        Returns ``x_d, y_d`` and, if ``jacobian``, ``(j_xx, j_xy, j_yy)``: the Jacobian of this
        model is symmetric (``d x_d / d y == d y_d / d x``).
        """
        k1, k2, p1, p2, k3, k4, k5, k6 = _dist8(self.dist)
        x2 = x * x
        y2 = y * y
        xy = x * y
        r2 = x2 + y2
        a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        b = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        with np.errstate(divide="ignore", invalid="ignore"):
            g = a / b
        xd = x * g + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
        yd = y * g + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
        if not jacobian:
            return xd, yd, None
        da = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        db = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
        with np.errstate(divide="ignore", invalid="ignore"):
            dg = (da * b - a * db) / (b * b)  # dg / d(r²)
        jxx = g + 2.0 * x2 * dg + 2.0 * p1 * y + 6.0 * p2 * x
        jxy = 2.0 * xy * dg + 2.0 * p1 * x + 2.0 * p2 * y
        jyy = g + 2.0 * y2 * dg + 6.0 * p1 * y + 2.0 * p2 * x
        return xd, yd, (jxx, jxy, jyy)

    def undistort(self, x_d, *, return_converged: bool = False):
        """Invert :meth:`distort` by Newton's method with the analytic Jacobian.

        Starts from ``x_n = x_d`` and iterates each element until
        ``max |distort(x_n) − x_d| ≤`` :data:`UNDISTORT_TOL` (3–5 iterations for realistic
        lenses). Elements that do not converge within :data:`UNDISTORT_MAX_ITER` iterations, or
        converge onto a fold of the distortion model (Jacobian determinant ≤ 0, where the inverse
        is ambiguous), are NaN.

        Parameters
        ----------
        x_d : (..., 2) float64, distorted normalised image coordinates
        return_converged : bool, optional
            Also return the convergence mask.

        Returns
        -------
        x_n : (..., 2) float64, undistorted normalised image coordinates; NaN where not converged
        converged : (...,) bool
            Only if ``return_converged``.
        """
        x_d = as_array(x_d, "x_d", shape=(..., 2), finite=False)
        if not self.has_distortion:
            x_n = x_d.copy()
            ok = np.isfinite(x_n).all(axis=-1)
            x_n[~ok] = np.nan
            return (x_n, ok) if return_converged else x_n
        shape = x_d.shape[:-1]
        tx = np.ascontiguousarray(x_d[..., 0]).ravel()
        ty = np.ascontiguousarray(x_d[..., 1]).ravel()
        x = tx.copy()
        y = ty.copy()
        ok = np.zeros(tx.shape, dtype=bool)
        idx = np.flatnonzero(np.isfinite(tx) & np.isfinite(ty))  # elements still iterating
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            for _ in range(UNDISTORT_MAX_ITER + 1):
                if idx.size == 0:
                    break
                xi, yi = x[idx], y[idx]
                fx, fy, (jxx, jxy, jyy) = self._distort_xy(xi, yi, jacobian=True)
                rx = fx - tx[idx]
                ry = fy - ty[idx]
                det = jxx * jyy - jxy * jxy
                done = (np.maximum(np.abs(rx), np.abs(ry)) <= UNDISTORT_TOL) & (det > 0)
                ok[idx[done]] = True
                # Newton step on the rest: solve J s = r with the explicit 2×2 inverse.
                keep = ~done & np.isfinite(rx) & np.isfinite(ry)
                idx = idx[keep]
                jxx, jxy, jyy, det, rx, ry = (a[keep] for a in (jxx, jxy, jyy, det, rx, ry))
                x[idx] = xi[keep] - (jyy * rx - jxy * ry) / det
                y[idx] = yi[keep] - (jxx * ry - jxy * rx) / det
        x_n = np.stack([x, y], axis=-1).reshape(shape + (2,))
        ok = ok.reshape(shape)
        x_n[~ok] = np.nan
        return (x_n, ok) if return_converged else x_n

    # ------------------------------------------------------------------ projection

    def project_cam(self, p_cam):
        """Project camera-frame points to pixels.

        Parameters
        ----------
        p_cam : (..., 3) float64, metres, camera frame

        Returns
        -------
        q : (..., 2) float64, pixels (x = column, y = row; integers are pixel centres)
            NaN where the point is not validly projected (see ``in_front``).
        in_front : (...,) bool
            Valid projection: ``z > 0``, finite, and inside the fold radius of the distortion
            (:meth:`fold_radius`); a point at or beyond the fold, where the model bends back
            and would land inside the image, is invalid (DESIGN §7).
        """
        p = as_array(p_cam, "p_cam", shape=(..., 3), finite=False)
        z = p[..., 2]
        in_front = (z > 0) & np.isfinite(p).all(axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_n = p[..., :2] / z[..., None]
        if self.has_distortion:
            r_fold = self.fold_radius()
            if np.isfinite(r_fold):
                with np.errstate(invalid="ignore"):
                    in_front &= np.einsum("...i,...i->...", x_n, x_n) < r_fold * r_fold
        x_n[~in_front] = np.nan
        x_d = self._distort(x_n, jacobian=False)[0] if self.has_distortion else x_n
        q = np.empty(x_d.shape)
        q[..., 0] = self.K[0, 0] * x_d[..., 0] + self.K[0, 2]
        q[..., 1] = self.K[1, 1] * x_d[..., 1] + self.K[1, 2]
        return q, in_front

    def project(self, p_world):
        """Project world points to pixels; equals ``cv2.projectPoints`` for points in front.

        Parameters
        ----------
        p_world : (..., 3) float64, metres, world frame

        Returns
        -------
        q : (..., 2) float64, pixels; NaN where the projection is invalid
        in_front : (...,) bool
            Valid: in front of the camera (z > 0), finite, and closer to the axis than the
            distortion's fold (:meth:`project_cam`).
        """
        p = as_array(p_world, "p_world", shape=(..., 3), finite=False)
        return self.project_cam(self.T_cam_world.apply(p))

    def fold_radius(self) -> float:
        """Normalised radius ``r = |(X/Z, Y/Z)|`` where the radial distortion folds over.

        The distorted radius increases with r up to this radius and not beyond; ``inf`` for a
        camera without distortion or a model that never folds. Computed once per coefficient
        set (cached). See :func:`_fold_radius` for the formula and the deviation (tangential
        terms ignored).
        """
        if not self.has_distortion:
            return np.inf
        return _fold_radius(tuple(float(c) for c in self.dist))

    def unproject(self, q, *, return_valid: bool = False):
        """Ray direction through pixels, camera frame, scaled to ``z = 1``.

        Parameters
        ----------
        q : (..., 2) float64, pixels
        return_valid : bool, optional
            Also return the validity mask (finite input and converged undistortion).

        Returns
        -------
        v_cam : (..., 3) float64, camera frame, ``v_cam[..., 2] == 1``; NaN where the
            undistortion failed or converged beyond the fold radius (:meth:`fold_radius`),
            i.e. on the branch :meth:`project` rejects
        valid : (...,) bool
            Only if ``return_valid``.
        """
        q = as_array(q, "q", shape=(..., 2), finite=False)
        x_d = np.empty(q.shape)
        x_d[..., 0] = (q[..., 0] - self.K[0, 2]) / self.K[0, 0]
        x_d[..., 1] = (q[..., 1] - self.K[1, 2]) / self.K[1, 1]
        x_n, ok = self.undistort(x_d, return_converged=True)
        r_fold = self.fold_radius()
        if np.isfinite(r_fold):
            with np.errstate(invalid="ignore"):
                ok = ok & (np.einsum("...i,...i->...", x_n, x_n) < r_fold * r_fold)
            x_n = np.where(ok[..., None], x_n, np.nan)
        v = np.empty(q.shape[:-1] + (3,))
        v[..., :2] = x_n
        v[..., 2] = np.where(ok, 1.0, np.nan)
        return (v, ok) if return_valid else v

    def pixel_grid(self) -> np.ndarray:
        """Every pixel centre, ``(H, W, 2)`` float64, pixels: ``grid[r, c] = (c, r)``."""
        xs, ys = np.meshgrid(
            np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64)
        )
        return np.stack([xs, ys], axis=-1)

    def pixel_rays(self, q=None):
        """World-frame rays through pixels.

        Parameters
        ----------
        q : (..., 2) float64, pixels, optional
            Default: every pixel centre, giving ``(H, W, 3)`` outputs.

        Returns
        -------
        origins_world : (..., 3) float64, metres, world frame
            The centre of projection, repeated.
        directions_world : (..., 3) float64, unit vectors, world frame
            NaN where the undistortion failed.
        """
        if q is None:
            q = self.pixel_grid()
        v_cam = self.unproject(q)
        v_cam = v_cam / np.linalg.norm(v_cam, axis=-1, keepdims=True)
        d_world = v_cam @ self.T_cam_world.R  # R_world_cam @ v  ==  v @ R_cam_world
        origins = np.broadcast_to(self.center_world, d_world.shape).copy()
        return origins, d_world

    def in_image(self, q) -> np.ndarray:
        """Whether pixels lie inside the image ``[-0.5, W - 0.5) × [-0.5, H - 0.5)``.

        Parameters
        ----------
        q : (..., 2) float64, pixels (NaN gives False)

        Returns
        -------
        (...,) bool
        """
        q = as_array(q, "q", shape=(..., 2), finite=False)
        x = q[..., 0]
        y = q[..., 1]
        return (x >= -0.5) & (x < self.width - 0.5) & (y >= -0.5) & (y < self.height - 0.5)

    # ------------------------------------------------------------------ interop

    def to_opencv(self):
        """OpenCV parameters.

        Returns
        -------
        K : (3, 3) float64
        dist : (n,) float64
        rvec : (3,) float64, radians (axis-angle of ``R_cam_world``)
        tvec : (3,) float64, metres
        """
        return self.K.copy(), self.dist.copy(), self.T_cam_world.rvec, self.T_cam_world.tvec

    @classmethod
    def from_opencv(cls, name: str, width: int, height: int, K, dist, rvec, tvec) -> Camera:
        """Build a camera from OpenCV's ``cameraMatrix``, ``distCoeffs``, ``rvec``, ``tvec``.

        ``dist`` and the vectors may have any shape with the right number of elements (OpenCV
        returns ``(1, n)`` and ``(3, 1)``).
        """
        dist = np.zeros(0) if dist is None else np.ravel(as_array(dist, "dist", finite=True))
        rvec = np.ravel(as_array(rvec, "rvec"))
        tvec = np.ravel(as_array(tvec, "tvec"))
        if rvec.shape != (3,) or tvec.shape != (3,):
            raise ShapeError(
                f"rvec/tvec: expected 3 elements each, got {rvec.shape[0]} and {tvec.shape[0]}"
            )
        return cls(name, width, height, K, dist, Pose.from_rvec_tvec(rvec, tvec))

    def scaled(self, factor: float) -> Camera:
        """The camera for images resized by ``factor`` (to ``W·factor × H·factor`` pixels).

        Focal lengths scale by ``factor``; the principal point maps pixel-centre-correctly,
        ``c' = (c + ½)·factor − ½``. Distortion (in normalised coordinates) and pose are
        unchanged.

        Raises
        ------
        InputError
            ``factor`` is not positive, or ``W·factor`` / ``H·factor`` is not an integer.
        """
        s = check_positive(factor, "factor")
        sizes = []
        for label, n in (("width", self.width), ("height", self.height)):
            v = n * s
            r = round(v)
            if abs(v - r) > 1e-6 or r < 1:
                raise InputError(
                    f"factor: {label} {n} × {fmt_value(s)} = {fmt_value(v)} is not a positive integer; choose a "
                    "factor that divides the image size"
                )
            sizes.append(int(r))
        K = self.K.copy()
        K[0, 0] *= s
        K[1, 1] *= s
        K[0, 2] = (K[0, 2] + 0.5) * s - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * s - 0.5
        return Camera(self.name, sizes[0], sizes[1], K, self.dist, self.T_cam_world)

    def replace(self, **changes) -> Camera:
        """A copy with some fields changed (:func:`dataclasses.replace`)."""
        return dataclasses.replace(self, **changes)

    # ------------------------------------------------------------------ JSON

    def to_dict(self) -> dict:
        """JSON-ready mapping: name, width, height, K (rows), dist, T_cam_world ({R, t})."""
        return {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "T_cam_world": self.T_cam_world.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: Any, *, where: str = "camera") -> Camera:
        """Inverse of :meth:`to_dict`.

        Parameters
        ----------
        d : dict
        where : str, optional
            Location used in error messages (``"cameras[1]"``).

        Raises
        ------
        InputError
            Not a mapping, a missing or unknown key, or a bad value; the message names the field
            as ``<where>.<key>``.
        """
        if not isinstance(d, dict):
            raise InputError(f"{where}: expected a mapping, got {type(d).__name__}")
        missing = [k for k in _CAMERA_KEYS if k not in d]
        if missing:
            raise InputError(
                f"{where}.{missing[0]}: missing field (a camera needs {', '.join(_CAMERA_KEYS)})"
            )
        unknown = sorted(set(d) - set(_CAMERA_KEYS))
        if unknown:
            raise InputError(
                f"{where}.{unknown[0]}: unknown field (expected only {', '.join(_CAMERA_KEYS)})"
            )
        try:
            pose = Pose.from_dict(d["T_cam_world"])
        except InputError as exc:
            raise InputError(f"{where}.T_cam_world: {exc}") from exc
        try:
            K = as_array(d["K"], "K", shape=(3, 3))
            dist = as_array(d["dist"], "dist", shape=(None,))
            return cls(d["name"], d["width"], d["height"], K, dist, pose)
        except InputError as exc:
            raise type(exc)(f"{where}.{exc}") from exc
