"""The parametrisation of a calibrated camera: distortion models, the intrinsic parameter vector
θ and the projection kernels the solvers share (:mod:`._calib_solve`, :mod:`._calib_rig`,
:mod:`._calib_select`).

The model is OpenCV's (``facegeo.geometry.camera``, the documentation of
``cv2.calibrateCamera``): pinhole ``K`` with zero skew and the radial-tangential (optionally
rational) distortion ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``; a named model (:data:`MODELS`)
says which coefficients are solved for (:data:`MODEL_FREE`).
"""

from __future__ import annotations

import numpy as np

from facegeo.checks import check_choice
from facegeo.frames import Pose
from facegeo.geometry.camera import Camera

__all__ = ["MODELS", "MODEL_FREE", "model_of_dist", "project_points", "rotate_rvec"]

#: Distortion models by name → length of the camera's OpenCV coefficient vector
#: ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``; :data:`MODEL_FREE` says which of them are solved for
#: (the others stay 0): ``k1`` and ``k1k2`` are the radial-only models of narrow lenses, stored
#: as OpenCV's 4-vector.
MODELS = {"pinhole": 0, "k1": 4, "k1k2": 4, "opencv4": 4, "opencv5": 5, "rational8": 8}

#: Indices (OpenCV order) of the distortion coefficients each model solves for.
MODEL_FREE = {"pinhole": (), "k1": (0,), "k1k2": (0, 1), "opencv4": (0, 1, 2, 3),
              "opencv5": (0, 1, 2, 3, 4), "rational8": tuple(range(8))}

#: The full model of each distortion-vector length (a camera read from a rig file).
_MODEL_OF_LENGTH = {0: "pinhole", 4: "opencv4", 5: "opencv5", 8: "rational8"}


def model_of_dist(dist) -> str:
    """The model that solves every coefficient of an OpenCV distortion vector of this length.

    Parameters
    ----------
    dist : (n,) float64, n ∈ {0, 4, 5, 8}

    Returns
    -------
    str
        A key of :data:`MODELS`.
    """
    return _MODEL_OF_LENGTH[np.asarray(dist).size]


_LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")


# ------------------------------------------------------------------------------ kernels


def rotate_rvec(rvec: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Rotate points by axis-angle vectors (Rodrigues), row by row.

    Parameters
    ----------
    rvec : (N, 3) or (3,) float64, radians
    p : (N, 3) float64

    Returns
    -------
    (N, 3) float64
    """
    theta = np.linalg.norm(rvec, axis=-1, keepdims=True)
    small = theta < 1e-12
    th = np.where(small, 1.0, theta)
    k = rvec / th
    c = np.cos(theta)
    s = np.sin(theta)
    kxp = np.cross(np.broadcast_to(k, p.shape), p)
    kdp = np.sum(k * p, axis=-1, keepdims=True)
    rot = p * c + kxp * s + k * kdp * (1.0 - c)
    # first order for tiny angles: p + r × p
    lin = p + np.cross(np.broadcast_to(rvec, p.shape), p)
    return np.where(small, lin, rot)


def project_points(p_cam: np.ndarray, fx, fy, cx, cy, dist8) -> np.ndarray:
    """OpenCV projection of camera-frame points (no z ≤ 0 check; the solver keeps z > 0).

    Parameters
    ----------
    p_cam : (N, 3) float64, metres, camera frame
    fx, fy, cx, cy : float or (N,) float64, pixels
    dist8 : (8,) or (N, 8) float64, ``(k1, k2, p1, p2, k3, k4, k5, k6)``

    Returns
    -------
    q : (N, 2) float64, pixels
    """
    d = np.asarray(dist8)
    k1, k2, p1, p2, k3, k4, k5, k6 = (d[..., i] for i in range(8))
    x = p_cam[:, 0] / p_cam[:, 2]
    y = p_cam[:, 1] / p_cam[:, 2]
    x2, y2, xy = x * x, y * y, x * y
    r2 = x2 + y2
    g = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * g + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
    yd = y * g + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
    return np.stack([fx * xd + cx, fy * yd + cy], axis=-1)


class _Model:
    """Layout of the intrinsic parameter vector θ for one camera."""

    def __init__(self, model: str, fix_aspect_ratio: float | None):
        check_choice(model, "model", tuple(MODELS))
        self.model = model
        self.nd = MODELS[model]  # length of the camera's distortion vector
        self.free = np.array(MODEL_FREE[model], int)  # solved coefficients (OpenCV order)
        self.aspect = None if fix_aspect_ratio is None else float(fix_aspect_ratio)
        self.names = (["f"] if self.aspect is not None else ["fx", "fy"]) + ["cx", "cy"] + [
            ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")[i] for i in self.free]
        self.n = len(self.names)

    def pack(self, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
        d8 = np.zeros(8)
        d = np.ravel(dist)[:8]
        d8[: d.size] = d
        f = [K[1, 1]] if self.aspect is not None else [K[0, 0], K[1, 1]]
        return np.concatenate([f, [K[0, 2], K[1, 2]], d8[self.free]])

    def unpack(self, theta: np.ndarray):
        """θ (..., n) → fx, fy, cx, cy, dist8 (..., 8)."""
        if self.aspect is not None:
            fy = theta[..., 0]
            fx = self.aspect * fy
            o = 1
        else:
            fx, fy = theta[..., 0], theta[..., 1]
            o = 2
        cx, cy = theta[..., o], theta[..., o + 1]
        d8 = np.zeros(theta.shape[:-1] + (8,))
        d8[..., self.free] = theta[..., o + 2: o + 2 + self.free.size]
        return fx, fy, cx, cy, d8

    def intr_jac(self, dq_dk: np.ndarray) -> np.ndarray:
        """Derivatives in :data:`~._calib_jac.INTRINSIC_ORDER` (…, 2, 12) → θ's (…, 2, n)."""
        if self.aspect is not None:
            f = (self.aspect * dq_dk[..., 0] + dq_dk[..., 1])[..., None]
        else:
            f = dq_dk[..., 0:2]
        return np.concatenate([f, dq_dk[..., 2:4], dq_dk[..., 4 + self.free]], axis=-1)

    def camera(self, theta: np.ndarray, name: str, size) -> Camera:
        fx, fy, cx, cy, d8 = self.unpack(theta)
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return Camera(name, size[0], size[1], K, d8[: self.nd].copy(), Pose.identity())
