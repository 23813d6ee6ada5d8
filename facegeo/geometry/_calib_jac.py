"""Analytic Jacobians of the calibration residuals: OpenCV projection and rigid poses.

The projection is OpenCV's (``facegeo.geometry.camera``; the same expressions as
:func:`facegeo.geometry._calib_solve.project_points`): with ``x = X/Z``, ``y = Y/Z``,
``r² = x² + y²``,

    g  = (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
    x' = x g + 2 p1 x y + p2 (r² + 2 x²)
    y' = y g + p1 (r² + 2 y²) + 2 p2 x y
    u  = fx x' + cx,   v = fy y' + cy

(OpenCV's 5-term model is ``k4 = k5 = k6 = 0``, the rational 8-term model all eight). The
derivatives below are those of these expressions, by hand; ``tests/test_calibration.py`` checks
them against central differences. Rotations are axis-angle vectors (Rodrigues); their derivative
``∂R/∂r`` is OpenCV's (``cv2.Rodrigues`` returns it), one call per view — views, not pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["INTRINSIC_ORDER", "BlockJacobian", "block_lm", "group_indicator", "project_with_jac",
           "rodrigues_batch", "rotate_with_jac"]

#: Column order of the intrinsic derivatives returned by :func:`project_with_jac`.
INTRINSIC_ORDER = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


def rodrigues_batch(rvecs: np.ndarray):
    """Rotation matrices and their derivatives for a batch of axis-angle vectors.

    Parameters
    ----------
    rvecs : (V, 3) float64, radians

    Returns
    -------
    R : (V, 3, 3) float64
    dR : (V, 3, 3, 3) float64
        ``dR[v, k, i, j] = ∂R_ij / ∂r_k``.
    """
    rvecs = np.asarray(rvecs, np.float64).reshape(-1, 3)
    V = rvecs.shape[0]
    R = np.empty((V, 3, 3))
    dR = np.empty((V, 3, 3, 3))
    for v in range(V):  # one 3-vector per view
        Rv, J = cv2.Rodrigues(rvecs[v])
        R[v] = Rv
        dR[v] = J.reshape(3, 3, 3)  # OpenCV: J[k, 3 i + j] = ∂R_ij/∂r_k
    return R, dR


def rotate_with_jac(R, dR, p):
    """``R p`` per point and its derivative with respect to the axis-angle vector.

    Parameters
    ----------
    R : (N, 3, 3), dR : (N, 3, 3, 3)
        Per point (already gathered by view), as from :func:`rodrigues_batch`.
    p : (N, 3)

    Returns
    -------
    Rp : (N, 3)
    dRp_dr : (N, 3, 3)
        ``[n, i, k] = ∂(R p)_i / ∂r_k``.
    """
    Rp = np.einsum("nij,nj->ni", R, p)
    d = np.einsum("nkij,nj->nik", dR, p)
    return Rp, d


def project_with_jac(pc: np.ndarray, fx, fy, cx, cy, d8):
    """OpenCV projection of camera-frame points with its analytic derivatives.

    Parameters
    ----------
    pc : (N, 3) float64, metres, camera frame (z > 0)
    fx, fy, cx, cy : float or (N,) float64, pixels
    d8 : (8,) or (N, 8) float64, ``(k1, k2, p1, p2, k3, k4, k5, k6)``

    Returns
    -------
    q : (N, 2) float64, pixels
    dq_dp : (N, 2, 3) float64
        Derivative with respect to the camera-frame point.
    dq_dk : (N, 2, 12) float64
        Derivative with respect to the intrinsics in :data:`INTRINSIC_ORDER`.
    """
    d = np.asarray(d8, np.float64)
    k1, k2, p1, p2, k3, k4, k5, k6 = (d[..., i] for i in range(8))
    fx = np.asarray(fx, np.float64)
    fy = np.asarray(fy, np.float64)
    iz = 1.0 / pc[:, 2]
    x = pc[:, 0] * iz
    y = pc[:, 1] * iz
    x2, y2, xy = x * x, y * y, x * y
    r2 = x2 + y2
    r4 = r2 * r2
    r6 = r4 * r2
    num = 1.0 + k1 * r2 + k2 * r4 + k3 * r6
    den = 1.0 + k4 * r2 + k5 * r4 + k6 * r6
    iden = 1.0 / den
    g = num * iden
    dnum = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4
    dden = k4 + 2.0 * k5 * r2 + 3.0 * k6 * r4
    gp = (dnum - g * dden) * iden  # ∂g/∂r²
    xd = x * g + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
    yd = y * g + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
    N = pc.shape[0]
    q = np.empty((N, 2))
    q[:, 0] = fx * xd + cx
    q[:, 1] = fy * yd + cy
    # ∂(x', y')/∂(x, y)
    dxd_dx = g + 2.0 * x2 * gp + 2.0 * p1 * y + 6.0 * p2 * x
    dxd_dy = 2.0 * xy * gp + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dx = 2.0 * xy * gp + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dy = g + 2.0 * y2 * gp + 6.0 * p1 * y + 2.0 * p2 * x
    # ∂(x, y)/∂(X, Y, Z) = [[1/Z, 0, −x/Z], [0, 1/Z, −y/Z]]
    dq_dp = np.empty((N, 2, 3))
    dq_dp[:, 0, 0] = fx * dxd_dx * iz
    dq_dp[:, 0, 1] = fx * dxd_dy * iz
    dq_dp[:, 0, 2] = -fx * (dxd_dx * x + dxd_dy * y) * iz
    dq_dp[:, 1, 0] = fy * dyd_dx * iz
    dq_dp[:, 1, 1] = fy * dyd_dy * iz
    dq_dp[:, 1, 2] = -fy * (dyd_dx * x + dyd_dy * y) * iz
    dq_dk = np.zeros((N, 2, 12))
    dq_dk[:, 0, 0] = xd
    dq_dk[:, 1, 1] = yd
    dq_dk[:, 0, 2] = 1.0
    dq_dk[:, 1, 3] = 1.0
    fxx, fyy = fx * x, fy * y
    for col, dg in ((4, r2 * iden), (5, r4 * iden), (8, r6 * iden),
                    (9, -g * r2 * iden), (10, -g * r4 * iden), (11, -g * r6 * iden)):
        dq_dk[:, 0, col] = fxx * dg
        dq_dk[:, 1, col] = fyy * dg
    dq_dk[:, 0, 6] = fx * 2.0 * xy
    dq_dk[:, 1, 6] = fy * (r2 + 2.0 * y2)
    dq_dk[:, 0, 7] = fx * (r2 + 2.0 * x2)
    dq_dk[:, 1, 7] = fy * 2.0 * xy
    return q, dq_dp, dq_dk


# ------------------------------------------------------------------------------ block LM


def group_indicator(group: np.ndarray, n_groups: int):
    """Sparse ``(n_groups, M)`` 0/1 matrix summing rows by group (``S[g, m] = group[m] == g``)."""
    from scipy.sparse import csr_matrix

    M = group.shape[0]
    return csr_matrix((np.ones(M), (group, np.arange(M))), shape=(int(n_groups), M))


class BlockJacobian:
    """A calibration Jacobian in its block-sparse form.

    Columns ``[0, n_dense)`` (intrinsics, camera poses) touch every residual; then ``n_groups``
    blocks of ``block`` columns (board poses), block g touching only the residuals whose
    ``group[row]`` is g.

    Attributes
    ----------
    Ja : (M, n_dense) float64
    Jb : (M, block) float64
        Row m's derivatives with respect to its own group's block.
    group : (M,) int
    n_groups : int
    """

    def __init__(self, Ja, Jb, group, n_groups, indicator=None):
        self.Ja, self.Jb, self.group, self.n_groups = Ja, Jb, group, int(n_groups)
        self._S = group_indicator(group, n_groups) if indicator is None else indicator

    def matvec(self, dx: np.ndarray) -> np.ndarray:
        """``J · dx``, (M,)."""
        na = self.Ja.shape[1]
        b = self.Jb.shape[1]
        db = dx[na:].reshape(self.n_groups, b)
        return self.Ja @ dx[:na] + np.einsum("mk,mk->m", self.Jb, db[self.group])

    @property
    def shape(self):
        return (self.Ja.shape[0], self.Ja.shape[1] + self.n_groups * self.Jb.shape[1])

    def dense(self) -> np.ndarray:
        """The full ``(M, n_dense + n_groups · block)`` matrix."""
        M, na = self.Ja.shape
        b = self.Jb.shape[1]
        J = np.zeros(self.shape)
        J[:, :na] = self.Ja
        J[np.arange(M)[:, None], na + b * self.group[:, None] + np.arange(b)] = self.Jb
        return J

    def normal(self, r):
        """Blocks of ``JᵀJ`` and ``Jᵀr``: ``U (na, na)``, ``W (G, na, b)``, ``V (G, b, b)``,
        ``ga (na,)``, ``gb (G, b)``."""
        Ja, Jb, S = self.Ja, self.Jb, self._S
        M, na = Ja.shape
        b = Jb.shape[1]
        G = self.n_groups
        U = Ja.T @ Ja
        W = np.asarray(S @ (Ja[:, :, None] * Jb[:, None, :]).reshape(M, na * b)).reshape(G, na, b)
        V = np.asarray(S @ (Jb[:, :, None] * Jb[:, None, :]).reshape(M, b * b)).reshape(G, b, b)
        ga = Ja.T @ r
        gb = np.asarray(S @ (Jb * r[:, None]))
        return U, W, V, ga, gb

    def jtj(self) -> np.ndarray:
        """The dense normal matrix ``JᵀJ`` (for the covariance), from the blocks."""
        U, W, V, _, _ = self.normal(np.zeros(self.Ja.shape[0]))
        na = U.shape[0]
        b = self.Jb.shape[1]
        n = na + self.n_groups * b
        A = np.zeros((n, n))
        A[:na, :na] = U
        A[:na, na:] = W.transpose(1, 0, 2).reshape(na, -1)
        A[na:, :na] = A[:na, na:].T
        for g in range(self.n_groups):  # block diagonal, one 6×6 per view
            s = na + b * g
            A[s:s + b, s:s + b] = V[g]
        return A


def _schur_step(U, W, V, ga, gb, lam):
    """Solve ``(JᵀJ + λ diag JᵀJ) δ = −Jᵀr`` by the Schur complement on the dense block."""
    na = U.shape[0]
    b = V.shape[1]
    Ud = U + lam * np.diag(np.diag(U)) + 1e-300 * np.eye(na)
    idx = np.arange(b)
    Vd = V.copy()
    Vd[:, idx, idx] *= 1.0 + lam
    Vi = np.linalg.inv(Vd)  # (G, b, b)
    WVi = np.einsum("gab,gbc->gac", W, Vi)  # (G, na, b)
    Sm = Ud - np.einsum("gab,gcb->ac", WVi, W)
    rhs = -ga + np.einsum("gab,gb->a", WVi, gb)
    da = np.linalg.solve(Sm, rhs)
    db = -np.einsum("gab,gb->ga", Vi, gb + np.einsum("gab,a->gb", W, da))
    return np.concatenate([da, db.ravel()])


def block_lm(fun_jac, x0, *, max_iter: int = 100, ftol: float = 1e-12):
    """Levenberg–Marquardt over a block-sparse problem (the bundle-adjustment Schur trick).

    Marquardt's scaled damping ``JᵀJ + λ diag(JᵀJ)`` with Nielsen's update of λ from the gain
    ratio (actual over predicted decrease of ``‖r‖²``).

    Parameters
    ----------
    fun_jac : callable
        ``fun_jac(x, jac: bool) -> (r (M,), BlockJacobian or None)``.
    x0 : (n,) float64
        Start; the first ``n_dense`` entries are the dense parameters, then the blocks.
    max_iter : int
        Jacobian evaluations at most.
    ftol : float
        Stop when the predicted or the actual relative decrease of ``‖r‖²`` falls below it.

    Returns
    -------
    x : (n,) float64
    r : (M,) float64
    J : BlockJacobian at ``x``
    n_iter : int
    """
    x = np.asarray(x0, np.float64).copy()
    r, J = fun_jac(x, True)
    cost = float(r @ r)
    lam, nu = 1e-3, 2.0
    it = 0
    for it in range(1, max_iter + 1):
        U, W, V, ga, gb = J.normal(r)
        done = False
        while True:
            try:
                dx = _schur_step(U, W, V, ga, gb, lam)
            except np.linalg.LinAlgError:
                dx = None
            if dx is None or not np.all(np.isfinite(dx)):
                lam *= nu
                nu *= 2.0
                if lam > 1e16:
                    done = True
                    break
                continue
            r_lin = r + J.matvec(dx)
            pred = cost - float(r_lin @ r_lin)
            if pred <= ftol * cost:  # converged: no decrease left to predict
                done = True
                break
            r_new, _ = fun_jac(x + dx, False)
            cost_new = float(r_new @ r_new) if np.all(np.isfinite(r_new)) else np.inf
            rho = (cost - cost_new) / pred
            if rho > 0:
                done = cost - cost_new <= ftol * cost
                x, cost = x + dx, cost_new
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                break
            lam *= nu
            nu *= 2.0
            if lam > 1e16:
                done = True
                break
        r, J = fun_jac(x, True)
        if done:
            break
    return x, r, J, it
