"""Conventions as code: poses, the world and camera frames, and the light-stage grid.

See ``docs/conventions.md`` for the prose version. In brief:

* **World frame**: right-handed, +Y up, the subject looks along +Z, origin near the head centre.
  Metres.
* **Camera frame**: OpenCV's, x right, y down, z forward.
* **Poses**: ``T_a_b`` maps coordinates in frame b to frame a,
  ``p_a = R_a_b @ p_b + t_a_b`` (OpenCV's rvec/tvec for ``T_cam_world``).
* **Light directions**: unit vectors from the subject toward the light, world frame. Azimuth
  ``θ_i = 2π(i + ½)/n_theta`` measured from +Z toward +X; inclination ``φ_j = π(j + ½)/n_phi``
  measured from +Y; ``ω = (sin φ sin θ, cos φ, sin φ cos θ)``; light index ``l = j·n_theta + i``.
* **Solid angle** of a grid cell, the weight of Debevec et al. 2000 Eq. (4):
  ``δA = (2π/n_theta)(π/n_phi) sin φ_j``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facegeo.checks import as_array, check_positive_int, fmt_value
from facegeo.errors import InputError

__all__ = [
    "Pose",
    "look_at",
    "rotation_from_rvec",
    "rvec_from_rotation",
    "light_grid_angles",
    "light_directions",
    "light_index",
    "light_grid_indices",
    "stratified_light_subset",
    "light_solid_angles",
    "direction_angles",
    "nearest_light_index",
]


# --------------------------------------------------------------------------- rotations


def rotation_from_rvec(rvec) -> np.ndarray:
    """Rodrigues: axis-angle ``(3,)`` (radians) to a rotation matrix ``(3, 3)``.

    Same convention as ``cv2.Rodrigues``.
    """
    r = as_array(rvec, "rvec", shape=(3,))
    theta = float(np.linalg.norm(r))
    if theta < 1e-12:
        k = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
        return np.eye(3) + k
    k = r / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * kx + (1.0 - np.cos(theta)) * (kx @ kx)


def rvec_from_rotation(R) -> np.ndarray:
    """Inverse Rodrigues: rotation ``(3, 3)`` to axis-angle ``(3,)``, stable near 0 and π."""
    R = as_array(R, "R", shape=(3, 3))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    # atan2 keeps full precision at both ends, where arccos of the trace loses half the digits
    theta = float(np.arctan2(0.5 * np.linalg.norm(w), 0.5 * (np.trace(R) - 1.0)))
    if theta < 1e-6:
        return 0.5 * w
    if np.pi - theta < 1e-4:
        # Near π: axis from the symmetric part, sign from w.
        # symmetric part: (R + Rᵀ)/2 = cos θ I + (1 − cos θ) k kᵀ
        cos_t = np.cos(theta)
        B = (0.5 * (R + R.T) - cos_t * np.eye(3)) / (1.0 - cos_t)
        axis = np.sqrt(np.clip(np.diag(B), 0.0, None))
        i = int(np.argmax(axis))
        axis = B[i] / max(axis[i], 1e-12)
        axis /= np.linalg.norm(axis)
        if np.dot(axis, w) < 0:
            axis = -axis
        return axis * theta
    return w * (theta / (2.0 * np.sin(theta)))


# --------------------------------------------------------------------------- poses


@dataclass(frozen=True)
class Pose:
    """A rigid transform ``T_a_b``: ``p_a = R @ p_b + t``.

    Name variables after both frames (``T_cam_world``); compose as ``T_a_c = T_a_b @ T_b_c``.

    Parameters
    ----------
    R : (3, 3) float64
        Rotation, orthonormal with det +1 (checked to 1e-6).
    t : (3,) float64, metres
        Translation.
    """

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self):
        R = as_array(self.R, "R", shape=(3, 3), copy=True)
        t = as_array(self.t, "t", shape=(3,), copy=True)
        err = np.abs(R @ R.T - np.eye(3)).max()
        if err > 1e-6 or np.linalg.det(R) < 0:
            raise InputError(
                f"R: not a rotation (max |R Rᵀ - I| = {err:.3g}, det = {np.linalg.det(R):.6g})"
            )
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    @classmethod
    def identity(cls) -> Pose:
        """The identity transform."""
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, T) -> Pose:
        """From a ``(4, 4)`` homogeneous matrix."""
        T = as_array(T, "T", shape=(4, 4))
        return cls(T[:3, :3], T[:3, 3])

    @classmethod
    def from_rvec_tvec(cls, rvec, tvec) -> Pose:
        """From OpenCV's ``rvec`` (axis-angle, radians) and ``tvec`` (metres)."""
        return cls(rotation_from_rvec(np.ravel(rvec)), np.ravel(as_array(tvec, "tvec")))

    @property
    def matrix(self) -> np.ndarray:
        """``(4, 4)`` homogeneous matrix."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T

    @property
    def rvec(self) -> np.ndarray:
        """OpenCV ``rvec`` ``(3,)``."""
        return rvec_from_rotation(self.R)

    @property
    def tvec(self) -> np.ndarray:
        """OpenCV ``tvec`` ``(3,)``."""
        return self.t.copy()

    def inverse(self) -> Pose:
        """``T_b_a`` from ``T_a_b``."""
        return Pose(self.R.T, -self.R.T @ self.t)

    def __matmul__(self, other: Pose) -> Pose:
        if not isinstance(other, Pose):
            return NotImplemented
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    def apply(self, p_b) -> np.ndarray:
        """Map points ``(..., 3)`` from frame b to frame a."""
        p = as_array(p_b, "p_b", shape=(..., 3), finite=False)
        return p @ self.R.T + self.t

    def apply_direction(self, v_b) -> np.ndarray:
        """Rotate directions ``(..., 3)`` from frame b to frame a (no translation)."""
        v = as_array(v_b, "v_b", shape=(..., 3), finite=False)
        return v @ self.R.T

    @property
    def origin_of_a_in_b(self) -> np.ndarray:
        """Where frame a's origin lies in frame b: for ``T_cam_world``, the camera centre."""
        return -self.R.T @ self.t

    def to_dict(self) -> dict:
        """JSON-ready ``{"R": [[...]], "t": [...]}``."""
        return {"R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> Pose:
        """Inverse of :meth:`to_dict`."""
        if not isinstance(d, dict) or "R" not in d or "t" not in d:
            raise InputError(f"pose: expected a mapping with keys 'R' and 't', got {d!r:.80}")
        return cls(np.asarray(d["R"], float), np.asarray(d["t"], float))

    def __eq__(self, other) -> bool:  # dataclass eq on arrays is ambiguous
        return isinstance(other, Pose) and np.array_equal(self.R, other.R) and np.array_equal(
            self.t, other.t
        )

    __hash__ = None  # type: ignore[assignment]


def nearest_rotation(M) -> np.ndarray:
    """The rotation nearest to a 3 × 3 matrix in the Frobenius norm (SVD projection, det +1).

    Used for the chordal mean of rotations (M = Σ R_i) and for Kabsch alignment
    (M = Σ b_i a_iᵀ gives the R minimising Σ |b_i − R a_i|²; the two-halves check of
    :func:`facegeo.geometry.calibration.cross_validate`).
    """
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=np.float64))
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> Pose:
    """Pose ``T_cam_world`` of an OpenCV camera at ``eye`` looking at ``target``.

    The camera's z axis points from ``eye`` to ``target``; its y axis (image down) is as close
    as possible to ``-up``.

    Parameters
    ----------
    eye, target : (3,) float64, metres, world frame
    up : (3,) float64, world frame
        World direction that appears up in the image.

    Raises
    ------
    InputError
        ``eye == target`` or the viewing direction is parallel to ``up``.
    """
    eye = as_array(eye, "eye", shape=(3,))
    target = as_array(target, "target", shape=(3,))
    up = as_array(up, "up", shape=(3,))
    z = target - eye
    nz = np.linalg.norm(z)
    if nz < 1e-12:
        raise InputError("look_at: eye and target coincide")
    z /= nz
    x = np.cross(-up, z)  # x = y × z with y ≈ -up
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise InputError("look_at: viewing direction is parallel to 'up'")
    x /= nx
    y = np.cross(z, x)
    R_world_cam = np.stack([x, y, z], axis=1)
    R_cam_world = R_world_cam.T
    return Pose(R_cam_world, -R_cam_world @ eye)


# --------------------------------------------------------------------------- light grid


def _check_grid(n_theta: int, n_phi: int) -> tuple[int, int]:
    if int(n_theta) != n_theta or int(n_phi) != n_phi or n_theta < 1 or n_phi < 1:
        raise InputError(
            f"light grid: n_theta and n_phi must be positive integers, got {fmt_value(n_theta)}, {fmt_value(n_phi)}"
        )
    return int(n_theta), int(n_phi)


def light_grid_angles(n_theta: int, n_phi: int) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth θ and inclination φ of every light, in light-index order.

    Returns
    -------
    theta, phi : (L,) float64, radians
        ``θ_i = 2π(i + ½)/n_theta`` (from +Z toward +X), ``φ_j = π(j + ½)/n_phi`` (from +Y),
        for light index ``l = j·n_theta + i``, ``L = n_theta·n_phi``.
    """
    n_theta, n_phi = _check_grid(n_theta, n_phi)
    i = np.arange(n_theta)
    j = np.arange(n_phi)
    theta = 2.0 * np.pi * (i + 0.5) / n_theta
    phi = np.pi * (j + 0.5) / n_phi
    return np.tile(theta, n_phi), np.repeat(phi, n_theta)


def light_directions(n_theta: int, n_phi: int) -> np.ndarray:
    """Unit directions toward every light, ``(L, 3)`` float64, world frame, light-index order.

    ``ω = (sin φ sin θ, cos φ, sin φ cos θ)``.
    """
    theta, phi = light_grid_angles(n_theta, n_phi)
    s = np.sin(phi)
    return np.stack([s * np.sin(theta), np.cos(phi), s * np.cos(theta)], axis=-1)


def light_index(i_theta, j_phi, n_theta: int):
    """Light index ``l = j·n_theta + i`` from azimuth index i and inclination index j."""
    return np.asarray(j_phi) * int(n_theta) + np.asarray(i_theta)


def light_grid_indices(l, n_theta: int) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`light_index`: ``(i_theta, j_phi)`` from light index ``l``."""
    l = np.asarray(l)
    return l % int(n_theta), l // int(n_theta)


#: Fractional part of the golden ratio: the offsets ``frac(k·g)`` spread as evenly as any
#: sequence can (a Kronecker sequence), whatever the number of strata.
_GOLDEN = 0.6180339887498949


def stratified_light_subset(n_lights: int, k: int) -> np.ndarray:
    """``min(k, n_lights)`` light indices, sorted, that stand for all ``n_lights`` lights.

    For an error summed over a few lights as an estimate of the sum over all of them (every
    light counted equally). The index range is cut into ``k`` strata of consecutive lights and
    stratum ``s`` gives the light at offset ``⌊frac(s·g)·len_s⌋``, ``g`` the golden ratio's
    fractional part. In the light stage's theta-fastest order (``l = j·n_theta + i``) a stratum
    is a run of azimuths within one or a few inclinations, so with ``k ≥ n_phi`` the subset
    covers every inclination evenly (with fewer lights, one in every ``n_phi / k`` inclinations)
    and spreads its azimuths over the whole circle. A plain stride
    (``arange(0, L, L // k)``) does not: when the stride is a multiple of ``n_theta / 2`` it
    keeps one or two azimuths (512 lights, stride 16 on 32 azimuths: the plane in front of and
    behind the face only). Works for any light order (a light list too); no randomness.
    """
    n, k = check_positive_int(n_lights, "n_lights"), check_positive_int(k, "k")
    if k >= n:
        return np.arange(n)
    s = np.arange(k)
    start = s * n // k
    length = (s + 1) * n // k - start
    offset = np.floor(np.mod(s * _GOLDEN, 1.0) * length).astype(np.int64)
    return start + np.minimum(offset, length - 1)


def light_solid_angles(n_theta: int, n_phi: int, *, exact: bool = False) -> np.ndarray:
    """Solid angle of every grid cell, ``(L,)`` float64, steradians.

    By default the weight of Debevec et al. 2000 Eq. (4),
    ``δA = (2π/n_theta)(π/n_phi) sin φ_j``: it sums to 4π up to the midpoint rule's error,
    ``≈ 4π · (π/n_phi)²/24`` (0.04 % at n_phi = 32). With ``exact=True``, the exact cell area
    ``(2π/n_theta)(cos φ_j⁻ − cos φ_j⁺)``, which sums to 4π to rounding.
    """
    n_theta, n_phi = _check_grid(n_theta, n_phi)
    j = np.arange(n_phi)
    if exact:
        lo = np.pi * j / n_phi
        hi = np.pi * (j + 1) / n_phi
        per_row = (2.0 * np.pi / n_theta) * (np.cos(lo) - np.cos(hi))
    else:
        phi = np.pi * (j + 0.5) / n_phi
        per_row = (2.0 * np.pi / n_theta) * (np.pi / n_phi) * np.sin(phi)
    return np.repeat(per_row, n_theta)


def direction_angles(v) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth θ ∈ [0, 2π) and inclination φ ∈ [0, π] of directions ``(..., 3)``.

    Directions need not be unit length; zero vectors give NaN.
    """
    v = as_array(v, "v", shape=(..., 3), finite=False)
    r = np.linalg.norm(v, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        phi = np.arccos(np.clip(v[..., 1] / r, -1.0, 1.0))
    theta = np.mod(np.arctan2(v[..., 0], v[..., 2]), 2.0 * np.pi)
    bad = ~(r > 0)
    if np.any(bad):
        phi = np.where(bad, np.nan, phi)
        theta = np.where(bad, np.nan, theta)
    return theta, phi


def nearest_light_index(v, n_theta: int, n_phi: int, *, return_valid: bool = False):
    """Index of the light-grid cell containing each direction.

    Parameters
    ----------
    v : array_like (..., 3) float64, world frame
        Directions toward the light; need not be unit length.
    n_theta, n_phi : int
        The grid (DESIGN §3 light convention).
    return_valid : bool
        How directions that name no cell (a zero vector, or any NaN or ±inf component) are
        reported. False (default): raise :class:`~facegeo.errors.InputError` naming how many
        there are and the first one. True: return them flagged instead.

    Returns
    -------
    index : (...) int64
        ``l = j·n_theta + i`` of the cell. With ``return_valid=True`` invalid entries hold −1,
        which is *not* a usable index (numpy would read it as the last light): always select
        with ``valid`` first.
    valid : (...) bool
        Only with ``return_valid=True``: True where ``index`` names a cell.
    """
    n_theta, n_phi = _check_grid(n_theta, n_phi)
    a = as_array(v, "v", shape=(..., 3), finite=False)
    theta, phi = direction_angles(a)
    ok = np.all(np.isfinite(a), axis=-1) & np.isfinite(theta) & np.isfinite(phi)
    if not return_valid and not np.all(ok):
        bad = np.argwhere(~ok)
        first = tuple(int(k) for k in bad[0]) if bad.shape[1] else ()
        raise InputError(
            f"v: {int(np.count_nonzero(~ok))} direction(s) name no light cell (zero, NaN or inf); "
            f"first at index {first}: {np.asarray(a)[first].tolist()}; expected finite non-zero "
            "vectors (or pass return_valid=True to get them flagged)"
        )
    th = np.where(ok, theta, 0.0)
    ph = np.where(ok, phi, 0.0)
    i = np.clip(np.floor(th / (2 * np.pi) * n_theta), 0, n_theta - 1)
    j = np.clip(np.floor(ph / np.pi * n_phi), 0, n_phi - 1)
    index = np.where(ok, (j * n_theta + i).astype(np.int64), -1)
    if return_valid:
        return index, ok
    return index
