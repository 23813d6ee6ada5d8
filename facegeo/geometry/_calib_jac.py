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

__all__ = ["INTRINSIC_ORDER", "BlockJacobian", "GroupLayout", "block_lm", "group_indicator",
           "held_out_residual", "leave_out_steps", "project_with_jac", "reduced_blocks",
           "rodrigues_batch", "rotate_with_jac"]

#: Column order of the intrinsic derivatives returned by :func:`project_with_jac`.
INTRINSIC_ORDER = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


def rodrigues_batch(rvecs: np.ndarray, jac: bool = True):
    """Rotation matrices and their derivatives for a batch of axis-angle vectors.

    Parameters
    ----------
    rvecs : (V, 3) float64, radians
    jac : bool
        Also return the derivative.

    Returns
    -------
    R : (V, 3, 3) float64
    dR : (V, 3, 3, 3) float64 (with ``jac``)
        ``dR[v, k, i, j] = ∂R_ij / ∂r_k``.
    """
    rvecs = np.asarray(rvecs, np.float64).reshape(-1, 3)
    V = rvecs.shape[0]
    R = np.empty((V, 3, 3))
    dR = np.empty((V, 3, 3, 3))
    for v in range(V):  # one 3-vector per view (2 µs a call: faster than numpy's overhead)
        Rv, J = cv2.Rodrigues(rvecs[v])
        R[v] = Rv
        dR[v] = J.reshape(3, 3, 3)  # OpenCV: J[k, 3 i + j] = ∂R_ij/∂r_k
    return (R, dR) if jac else R


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


class GroupLayout:
    """Rows grouped into a padded ``(n_groups, L, …)`` array, ``L`` the largest group.

    Per-group sums become one batched matrix product (``A[g]ᵀ A[g]``) instead of a sparse
    product over outer products: 5× faster on a 13-view calibration. Rows already sorted by
    group in groups of equal size (a single camera's views with whole boards) are a reshape;
    otherwise they are scattered into zero padding (zero rows add nothing to any sum).

    Parameters
    ----------
    group : (M,) int
        Group of each row.
    n_groups : int
    """

    def __init__(self, group: np.ndarray, n_groups: int):
        group = np.asarray(group, np.intp)
        G = int(n_groups)
        counts = np.bincount(group, minlength=G)
        self.n_groups, self.L, self.M = G, int(counts.max(initial=0)), group.shape[0]
        sorted_equal = (self.L * G == self.M and bool(np.all(group[:-1] <= group[1:]))
                        if self.M else True)
        if sorted_equal:
            self.pos = None
        else:  # row m → g·L + (its rank within its group)
            order = np.argsort(group, kind="stable")
            starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
            rank = np.empty(self.M, np.intp)
            rank[order] = np.arange(self.M) - np.repeat(starts, counts)
            self.pos = group * self.L + rank

    def pad(self, A: np.ndarray) -> np.ndarray:
        """Rows ``(M, k)`` → ``(n_groups, L, k)`` (zeros where a group has fewer rows)."""
        if self.pos is None:
            return A.reshape(self.n_groups, self.L, -1)
        out = np.zeros((self.n_groups * self.L, A.shape[1]))
        out[self.pos] = A
        return out.reshape(self.n_groups, self.L, -1)


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

    def __init__(self, Ja, Jb, group, n_groups, indicator=None, layout=None):
        # ``indicator`` (a :func:`group_indicator` matrix) is accepted for older callers and
        # unused: the per-group sums go through a :class:`GroupLayout`
        self.Ja, self.Jb, self.group, self.n_groups = Ja, Jb, group, int(n_groups)
        self._layout = layout

    @property
    def layout(self) -> GroupLayout:
        if self._layout is None:
            self._layout = GroupLayout(self.group, self.n_groups)
        return self._layout

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

    def grams(self, r) -> np.ndarray:
        """Per group g, the Gram matrix of its rows of ``[Ja | Jb | r]``: ``(G, k, k)`` with
        ``k = n_dense + block + 1`` — its blocks are group g's share of ``JᵀJ`` and ``Jᵀr``."""
        A = self.layout.pad(np.concatenate([self.Ja, self.Jb, r[:, None]], axis=1))
        return A.transpose(0, 2, 1) @ A

    def normal(self, r, grams=None):
        """Blocks of ``JᵀJ`` and ``Jᵀr``: ``U (na, na)``, ``W (G, na, b)``, ``V (G, b, b)``,
        ``ga (na,)``, ``gb (G, b)``."""
        na, b = self.Ja.shape[1], self.Jb.shape[1]
        Gm = self.grams(r) if grams is None else grams
        return (Gm[:, :na, :na].sum(0), Gm[:, :na, na:na + b], Gm[:, na:na + b, na:na + b],
                Gm[:, :na, -1].sum(0), Gm[:, na:na + b, -1])

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


def reduced_blocks(grams: np.ndarray, na: int):
    """Each group's share of the Schur-reduced normal equations on the dense parameters.

    With group g's blocks ``U_g = Ja_gᵀJa_g``, ``W_g = Ja_gᵀJb_g``, ``V_g = Jb_gᵀJb_g``,
    ``a_g = Ja_gᵀr_g``, ``b_g = Jb_gᵀr_g`` (from :meth:`BlockJacobian.grams`), eliminating the
    group's own block gives ``S_g = U_g − W_g V_g⁻¹ W_gᵀ`` and ``s_g = a_g − W_g V_g⁻¹ b_g``:
    the Gauss–Newton step of the dense parameters over any set F of groups solves
    ``(Σ_{g∈F} S_g) δ = −Σ_{g∈F} s_g`` (the bundle-adjustment Schur complement, summed by group).

    Parameters
    ----------
    grams : (G, k, k) float64
    na : int
        Number of dense parameters (the first ``na`` columns).

    Returns
    -------
    S : (G, na, na) float64
    s : (G, na) float64
    """
    U = grams[:, :na, :na]
    W = grams[:, :na, na:-1]
    V = grams[:, na:-1, na:-1]
    a = grams[:, :na, -1]
    b = grams[:, na:-1, -1]
    WVi = np.linalg.solve(V, W.transpose(0, 2, 1)).transpose(0, 2, 1)  # W V⁻¹ (V symmetric)
    S = U - WVi @ W.transpose(0, 2, 1)
    s = a - np.einsum("gab,gb->ga", WVi, b)
    return S, s


def leave_out_steps(S: np.ndarray, s: np.ndarray, folds) -> np.ndarray:
    """One Gauss–Newton step of the dense parameters with each fold of groups left out.

    From a solution of the whole problem, the problem without fold F starts at the same point
    with normal equations ``Σ_{g∉F} S_g`` and gradient ``Σ_{g∉F} s_g`` (:func:`reduced_blocks`);
    its step ``δ_F = −(Σ_{g∉F} S_g)⁻¹ Σ_{g∉F} s_g`` is the leave-out solution to first order
    (exact for a linear model, where it is the PRESS / jackknife identity; the board poses of
    the other groups follow from the Schur back-substitution and are not needed here).

    Parameters
    ----------
    S : (G, na, na), s : (G, na)
        From :func:`reduced_blocks`.
    folds : sequence of sequences of int
        The groups of each fold.

    Returns
    -------
    (F, na) float64
        ``δ_F`` per fold (NaN where the remaining normal matrix is singular).
    """
    S_all, s_all = S.sum(0), s.sum(0)
    out = np.full((len(folds), S.shape[1]), np.nan)
    for f, F in enumerate(folds):
        F = np.asarray(F, np.intp)
        A = S_all - S[F].sum(0)
        g = s_all - s[F].sum(0)
        try:
            out[f] = -np.linalg.solve(A, g)
        except np.linalg.LinAlgError:
            pass
    return out


def held_out_residual(grams: np.ndarray, na: int, delta: np.ndarray) -> np.ndarray:
    """Per group, ``min over δb of ‖r + Ja δ + Jb δb‖²`` from its Gram blocks
    (:meth:`BlockJacobian.grams`): the group's squared residual, to second order, after its own
    block is re-solved for a change ``δ`` of the dense parameters (the PRESS identity of linear
    least squares when δ is the leave-out step).

    Parameters
    ----------
    grams : (G, k, k) float64
    na : int
    delta : (G, na) float64
        The change of the dense parameters, per group.

    Returns
    -------
    (G,) float64
    """
    U = grams[:, :na, :na]
    W = grams[:, :na, na:-1]
    V = grams[:, na:-1, na:-1]
    a = grams[:, :na, -1]
    b = grams[:, na:-1, -1]
    rr = grams[:, -1, -1]
    e2 = rr + 2.0 * np.einsum("ga,ga->g", a, delta) + np.einsum("ga,gab,gb->g", delta, U, delta)
    h = b + np.einsum("gab,ga->gb", W, delta)
    e2 -= np.einsum("gb,gb->g", h, np.linalg.solve(V, h[..., None])[..., 0])
    return np.clip(e2, 0.0, None)


def _schur_step(U, W, V, ga, gb, lam):
    """Solve ``(JᵀJ + λ diag JᵀJ) δ = −Jᵀr`` by the Schur complement on the dense block.

    Returns ``δ`` and the decrease of ``‖r‖²`` the linear model predicts for it,
    ``−2 δᵀJᵀr − δᵀJᵀJ δ`` (from the blocks: no pass over the residuals).
    """
    na = U.shape[0]
    b = V.shape[1]
    Ud = U + lam * np.diag(np.diag(U)) + 1e-300 * np.eye(na)
    idx = np.arange(b)
    Vd = V.copy()
    Vd[:, idx, idx] *= 1.0 + lam
    Vi = np.linalg.inv(Vd)  # (G, b, b)
    WVi = W @ Vi  # (G, na, b)
    Sm = Ud - np.einsum("gab,gcb->ac", WVi, W)
    rhs = -ga + np.einsum("gab,gb->a", WVi, gb)
    da = np.linalg.solve(Sm, rhs)
    db = -np.einsum("gab,gb->ga", Vi, gb + np.einsum("gab,a->gb", W, da))
    quad = (da @ U @ da + 2.0 * np.einsum("a,gab,gb->", da, W, db)
            + np.einsum("ga,gab,gb->", db, V, db))
    pred = -2.0 * (ga @ da + np.sum(gb * db)) - quad
    return np.concatenate([da, db.ravel()]), float(pred)


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
                dx, pred = _schur_step(U, W, V, ga, gb, lam)
            except np.linalg.LinAlgError:
                dx = None
            if dx is None or not np.all(np.isfinite(dx)):
                lam *= nu
                nu *= 2.0
                if lam > 1e16:
                    done = True
                    break
                continue
            if pred <= ftol * cost:  # converged: no decrease left to predict
                done = True
                break
            # the Jacobian with the trial residuals: steps are mostly accepted, and an accepted
            # step then needs no second evaluation
            r_new, J_new = fun_jac(x + dx, True)
            cost_new = float(r_new @ r_new) if np.all(np.isfinite(r_new)) else np.inf
            rho = (cost - cost_new) / pred
            if rho > 0:
                done = cost - cost_new <= ftol * cost
                x, cost, r, J = x + dx, cost_new, r_new, J_new
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                break
            lam *= nu
            nu *= 2.0
            if lam > 1e16:
                done = True
                break
        if done:
            break
    return x, r, J, it
