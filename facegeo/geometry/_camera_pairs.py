"""Camera–camera triangulation through matching projector codes (behind ``triangulation``).

For rigs whose projector is uncalibrated: every camera's pixels are located in every other
camera through the projector codes both decoded (a local affine inverse of the other camera's
code map), triangulated against that camera's rays, and one camera's estimates against several
partners merged along its rays. Everything works on the decoded pixels only
(:class:`facegeo.geometry.code_maps.CodeSet`), in blocks of :data:`_MATCH_CHUNK` pixels: two
16-Mpx cameras decode ≈ 4 M pixels each, and the full-grid version of this module held
≈ 8 GB (issue 34; docs/mesh.md, *Memory at full resolution*).
"""

from __future__ import annotations

import numpy as np

from facegeo.checks import as_array, check_positive
from facegeo.errors import InputError, ShapeError
from facegeo.geometry._point_maps import (NO_CODE, OK, UNCERTAIN, CodeGains, PointMap,
                                          _reject_spikes)
from facegeo.geometry._rays import RayFit, _classify, _map, solve_along_rays
from facegeo.geometry.camera import Camera
from facegeo.geometry.code_maps import CodeSet

#: Smallest ``det Σ / (tr Σ)²`` (≈ smallest / largest eigenvalue) of a camera–camera match's
#: 2 × 2 covariance: below it the match is degenerate (B's neighbouring pixels all on one row or
#: column, so the fit sees no change of that axis with the code and claims zero variance along
#: it; such a point came out with σ ≈ 1e-17 m).
_MIN_COV_RATIO = 1e-6
#: Floor of the default code-distance limit of :func:`match_projector_codes`, projector pixels.
MIN_CODE_DIST = 0.5
#: A pixels per block of the code match and the ray solve (measured: the match's temporaries
#: ≈ 1.3 kB a pixel, 85 MB a block; the solver's less).
_MATCH_CHUNK = 1 << 16


def match_projector_codes(x_a, y_a, x_b, y_b, *, k: int = 8,
                          max_code_dist: float | None = None):
    """Sub-pixel location in camera B of each camera-A pixel's projector code.

    B's decode maps pixel → code; the inverse near A's code is fitted as a local affine map
    ``q_B ≈ M·(x, y) + m`` over B's ``k`` pixels nearest in code space (a k-d tree over B's
    codes), so no projector calibration is needed. A's pixels are matched in blocks of
    :data:`_MATCH_CHUNK`, so the fit's temporaries stay bounded (≈ 1.3 kB a pixel, 85 MB a
    block) whatever the image size. (The ``(H, W)`` outputs here are for callers that want
    maps; :func:`triangulate_code_sets` keeps the matched pixels' values only.)

    Parameters
    ----------
    x_a, y_a : (H_a, W_a) float, projector pixels, NaN invalid
    x_b, y_b : (H_b, W_b) float, projector pixels, NaN invalid
    k : int
        Neighbours of the local affine fit (>= 3).
    max_code_dist : float, projector pixels, optional
        No match when B's nearest code is farther than this from A's. Default twice the median
        code-space spacing of B's pixels, at least :data:`MIN_CODE_DIST`.

    Returns
    -------
    q_b : (H_a, W_a, 2) float64, pixels of B (NaN where unmatched)
    jac : (H_a, W_a, 2, 2) float64, ``∂q_B/∂(x, y)`` (pixels of B per projector pixel), for
        propagating the decode noise.
    """
    q_b, jac, _, _ = _match_codes(x_a, y_a, x_b, y_b, k=k, max_code_dist=max_code_dist)
    return q_b, jac


def _match_codes(x_a, y_a, x_b, y_b, *, k: int = 8, max_code_dist: float | None = None):
    """:func:`match_projector_codes`, plus the variance of each fitted B location from the local
    fit's misfit, ``(H_a, W_a, 2)`` pixels² of B, and the fit's normalised leverage at A's code,
    ``(H_a, W_a)`` (:func:`_affine_inverse`)."""
    xa, ya = (as_array(v, n, finite=False) for v, n in ((x_a, "x_a"), (y_a, "y_a")))
    xb, yb = (as_array(v, n, finite=False) for v, n in ((x_b, "x_b"), (y_b, "y_b")))
    if xa.shape != ya.shape or xb.shape != yb.shape or xa.ndim != 2 or xb.ndim != 2:
        raise ShapeError(f"x_a/y_a and x_b/y_b: expected two pairs of equal 2-D maps, got "
                         f"{xa.shape}/{ya.shape} and {xb.shape}/{yb.shape}")
    if k < 3:
        raise InputError(f"k: expected >= 3 neighbours for an affine fit, got {k}")
    q_b = np.full(xa.shape + (2,), np.nan)
    jac = np.full(xa.shape + (2, 2), np.nan)
    var_fit = np.full(xa.shape + (2,), np.nan)
    lev = np.full(xa.shape, np.nan)
    codes_a, codes_b = CodeSet.from_maps(xa, ya), CodeSet.from_maps(xb, yb)
    matcher = _CodeMatcher.of(codes_b, k, max_code_dist)
    if matcher is None or not len(codes_a):
        return q_b, jac, var_fit, lev
    ca = np.stack([codes_a.x, codes_a.y], 1)
    for lo in range(0, ca.shape[0], _MATCH_CHUNK):  # bounded memory: (chunk, k, 3) at a time
        sl = slice(lo, lo + _MATCH_CHUNK)
        f = codes_a.index[sl]
        for grid, v in zip((q_b, jac, var_fit, lev), matcher.match(ca[sl])):
            grid.reshape((-1,) + grid.shape[2:])[f] = v
    return q_b, jac, var_fit, lev


class _CodeMatcher:
    """Camera B's side of the code match: a k-d tree over B's codes, B's pixels, and the
    code-distance limit (:func:`match_projector_codes`)."""

    def __init__(self, codes_b: CodeSet, k: int, max_code_dist: float | None):
        from scipy.spatial import cKDTree

        self.k = k
        self.codes = np.stack([codes_b.x, codes_b.y], 1)  # (n_b, 2), B's pixel order
        self.index, self.width = codes_b.index, codes_b.shape[1]
        self.tree = cKDTree(self.codes)
        if max_code_dist is None:
            # never 0: where the cameras out-resolve the projector most of B's pixels share
            # their code with a neighbour and the median spacing is 0
            spacing = np.empty(self.codes.shape[0])
            for lo in range(0, spacing.size, _MATCH_CHUNK):
                spacing[lo:lo + _MATCH_CHUNK] = self.tree.query(
                    self.codes[lo:lo + _MATCH_CHUNK], k=2)[0][:, 1]
            max_code_dist = max(2.0 * float(np.median(spacing)), MIN_CODE_DIST)
        self.max_code_dist = max_code_dist

    @classmethod
    def of(cls, codes_b: CodeSet, k: int, max_code_dist) -> _CodeMatcher | None:
        """The matcher, or None when B has fewer than ``k`` codes."""
        return cls(codes_b, k, max_code_dist) if len(codes_b) >= k else None

    def match(self, ca):
        """:func:`_affine_inverse` of A's codes ``ca`` ``(M, 2)``."""
        return _affine_inverse(self.tree, self.codes, self.index, self.width, ca, self.k,
                               self.max_code_dist)


def _affine_inverse(tree, codes_b, index_b, width_b: int, ca, k: int, max_code_dist: float):
    """B pixel, ``∂q_B/∂code``, the fit's variance and leverage at each code of ``ca``
    ``(M, 2)``, from B's ``k`` nearest codes; NaN where unmatched.

    The variance of the fitted location is the regression's: the residual scatter of B's
    pixels about the local affine map, per axis ``Σ res² / (k − 3)`` (0 for ``k = 3``), times
    the intercept's leverage ``(G⁻¹)₃₃``. The leverage is returned normalised, ``k·(G⁻¹)₃₃``:
    ≈ 1 when A's code sits among the neighbours' codes, large when the fit extrapolates
    (A's code outside them, e.g. at the border of B's decoded region).
    """
    dist, nn = tree.query(ca, k=k)
    X = codes_b[nn] - ca[:, None, :]  # (M, k, 2) centred on A's code
    Xh = np.concatenate([X, np.ones(X.shape[:2] + (1,))], -1)  # (M, k, 3)
    rb, cb_ = np.divmod(index_b[nn], width_b)
    Y = np.stack([cb_, rb], -1).astype(np.float64)  # (M, k, 2) B pixels
    G = np.einsum("mki,mkj->mij", Xh, Xh)
    rhs = np.einsum("mki,mkj->mij", Xh, Y)
    det = np.linalg.det(G)
    scale = np.einsum("mki,mki->m", X, X) / k
    good = (dist[:, 0] <= max_code_dist) & (np.abs(det) > 1e-9 * np.maximum(scale, 1e-12) ** 2)
    sol = np.full((ca.shape[0], 3, 2), np.nan)
    lev = np.full(ca.shape[0], np.nan)
    if good.any():
        sol[good] = np.linalg.solve(G[good], rhs[good])
        lev[good] = np.linalg.inv(G[good])[:, 2, 2]
    qa = sol[:, 2, :]  # value at A's code (X = 0)
    J = np.swapaxes(sol[:, :2, :], 1, 2)  # (M, 2 [q], 2 [code])
    res = Y - np.einsum("mki,mij->mkj", Xh, sol)
    v_fit = (res**2).sum(1) / max(k - 3, 1) * lev[:, None]  # (M, 2), pixels² of B
    # the fitted location must stay among the neighbours (no extrapolation across holes)
    span = np.linalg.norm(Y - Y.mean(1, keepdims=True), axis=-1).max(1)
    far = np.linalg.norm(qa - Y.mean(1), axis=1) > span + 1.0
    qa[far] = np.nan
    return qa, J, v_fit, lev * k


def triangulate_camera_pair(cam_a: Camera, cam_b: Camera, x_a, y_a, x_b, y_b, *,
                            sigma_px: float = 0.3, sigma_x=None, sigma_y=None, k: int = 8,
                            max_sigma_ratio: float = 5.0, min_angle_deg: float | None = None,
                            max_chi: float = 4.0,
                            max_leverage: float | None = 3.0) -> PointMap:
    """Triangulate camera A's pixels against camera B through matching projector codes.

    For rigs with an uncalibrated projector: each A pixel is matched to the sub-pixel location in
    B that decoded the same projector code (:func:`match_projector_codes`), then the A ray is
    intersected with B's ray by minimising B's reprojection error (:func:`solve_along_rays`
    with B as the "other" view); the B-epipolar residual is the consistency check
    (``max_chi``).

    The matching noise in B is a 2 × 2 covariance with two parts: A's decode noise
    (``sigma_x``, ``sigma_y``, else ``sigma_px``) mapped through the local ``∂q_B/∂code``,
    ``J·diag(σ_x², σ_y²)·Jᵀ``, and the variance of the local fit itself per pixel axis (its
    residual scatter times the intercept's leverage), which carries B's own decode noise —
    averaged over the ``k`` neighbours — and the misfit of a locally affine code → B-pixel map.
    A's ray is intersected with B's by generalised least squares on that covariance
    (:func:`solve_along_rays` with ``cov_other``). Deviation from the per-axis σ used until
    this version: ``J`` mixes the code axes into both of B's pixel axes whenever B's image is
    turned against the projector's, and with a coarse row code beside a fine column code
    (Gray ``y`` 0.3 px, phase ``x`` 0.08 px) the two pixel errors are strongly correlated;
    weighted per axis the points were worse and σ misstated (plane, camera B rolled 30°:
    depth RMS 0.239 → 0.181 mm, RMS z 0.92 → 0.96; the synthetic small face, 0.1 px codes:
    0.229 → 0.206 mm; its real decode: 0.177 → 0.106 mm). The fit's part stays per axis
    (not its 2 × 2 scatter): its cross term rests on ``k − 3`` = 5 residual degrees of
    freedom, and weighting by it made σ 10–15 % optimistic (RMS z 1.14 against 1.01 on the
    small face with 0.08 / 0.29 px codes) and kept ≈ 1 % more, worse points (0.184 against
    0.171 mm). (Before the previous version ``sigma_px`` was taken as A's and B's noise added
    in quadrature, which over-stated σ by √2.) A match the fit extrapolates (normalised
    leverage ``k·(G⁻¹)₃₃`` above ``max_leverage``: A's code lies
    outside B's neighbouring codes, as at the border of B's decoded region) gets no point
    (reason :data:`UNCERTAIN`): on the tiny synthetic scan those ≈ 7 % of the matches carried
    2.2 mm RMS depth error against 0.6 mm for the rest, and made the mesh's 95th-percentile
    error 1.3 mm instead of 0.7. So does a degenerate match (the covariance's
    ``det / trace²`` below ``1e-6``: B's neighbours all on one pixel row, the fit sees no change
    of that axis with the code and claimed zero variance across it — σ ≈ 1e-17 m, which then
    outweighed every other estimate in a merge or fusion).

    Not modelled: at grazing incidence the affine match's misfit exceeds what the residual
    scatter shows (on the sphere's limb RMS z is 1.2–1.5, against 1.00–1.05 elsewhere).

    The point map carries :class:`CodeGains` (how each depth follows A's and B's code noise)
    for :func:`fuse_cameras`.

    Parameters
    ----------
    cam_a, cam_b : Camera
    x_a, y_a : (H_a, W_a) float, projector pixels (NaN invalid); both coordinates are needed
    x_b, y_b : (H_b, W_b) float
    sigma_px : float, projector pixels
        A's decode noise (1 σ) where ``sigma_x`` / ``sigma_y`` give none.
    sigma_x, sigma_y : (H_a, W_a) float, projector pixels, optional
        A's decode noise per pixel and axis (NaN → ``sigma_px``), as in
        :func:`triangulate_maps`: e.g. a phase-shift column with a Gray-code row, σ 0.08 and
        0.29 px.
    k, max_sigma_ratio, min_angle_deg, max_chi
        See :func:`match_projector_codes` and :func:`triangulate_maps`.
    max_leverage : float or None
        Largest normalised leverage of the code match (≈ 1 inside B's codes); ``None`` keeps
        every match.

    Returns
    -------
    PointMap
        On A's pixel grid.
    """
    xa = as_array(x_a, "x_a", shape=(cam_a.height, cam_a.width), finite=False)
    shape = xa.shape
    sx = None if sigma_x is None else _map(sigma_x, "sigma_x", shape)
    sy = None if sigma_y is None else _map(sigma_y, "sigma_y", shape)
    codes_a = _codes_of(cam_a, xa, y_a, sx, sy)
    codes_b = _codes_of(cam_b, x_b, y_b, None, None, check_shape=False)
    _check_pair_settings(k, max_leverage)
    return _camera_pair(cam_a, cam_b, codes_a, _CodeMatcher.of(codes_b, k, None),
                        sigma_px=check_positive(sigma_px, "sigma_px"), k=k,
                        max_sigma_ratio=max_sigma_ratio, min_angle_deg=min_angle_deg,
                        max_chi=max_chi, max_leverage=max_leverage, with_var_fit=False)[0]


def _codes_of(cam, x, y, sigma_x, sigma_y, confidence=None, *, check_shape=True) -> CodeSet:
    """A camera's :class:`CodeSet` from ``(H, W)`` maps (:func:`_match_codes`' checks)."""
    xa = as_array(x, "x", finite=False)
    ya = as_array(y, "y", finite=False)
    if xa.ndim != 2 or xa.shape != ya.shape:
        raise ShapeError(f"x/y of camera {cam.name!r}: expected two equal 2-D maps, got "
                         f"{xa.shape}/{ya.shape}")
    if check_shape and xa.shape != (cam.height, cam.width):
        raise ShapeError(f"x of camera {cam.name!r}: expected its image shape "
                         f"{(cam.height, cam.width)}, got {xa.shape}")
    return CodeSet.from_maps(xa, ya, sigma_x=sigma_x, sigma_y=sigma_y, confidence=confidence)


def _check_pair_settings(k: int, max_leverage) -> None:
    if k < 3:
        raise InputError(f"k: expected >= 3 neighbours for an affine fit, got {k}")
    if max_leverage is not None:
        check_positive(max_leverage, "max_leverage")  # also refuses NaN (no silent 'off')


def _camera_pair(cam_a, cam_b, codes_a: CodeSet, matcher: _CodeMatcher | None, *,
                 sigma_px: float, k: int, max_sigma_ratio, min_angle_deg, max_chi,
                 max_leverage, with_var_fit: bool = True) -> tuple[PointMap, np.ndarray | None]:
    """:func:`triangulate_camera_pair` on A's compressed codes and B's matcher, plus the local
    fit's share of each point's variance (B's codes and the affine misfit, independent of A's
    code), ``(n,)`` metres² on the map's pixels (NaN without a point; None unless
    ``with_var_fit``: only a merge of several partners needs it).

    A's pixels are matched and solved in blocks of :data:`_MATCH_CHUNK`; what is kept per
    solved pixel is its flat index, depth, σ, χ, angle, point, gains and fit variance."""
    shape = codes_a.shape
    H, W = shape
    reason = np.full(H * W, NO_CODE, np.uint8)
    n_a = len(codes_a) if matcher is not None else 0
    # the solved pixels' values, written block by block into arrays of A's code count (no
    # per-block pieces left between the blocks' temporaries: they fragment the heap)
    a = {"index": np.empty(n_a, np.int64), "p": np.empty((n_a, 3)),
         "dt_dcode": np.empty((n_a, 2)), **{k: np.empty(n_a) for k in (
             "t", "sigma_t", "chi", "sin_angle", "h")}}
    if with_var_fit:
        a["var_fit"] = np.empty(n_a)
    n = 0
    for lo in range(0, n_a, _MATCH_CHUNK):
        sl = slice(lo, lo + _MATCH_CHUNK)
        flat = codes_a.index[sl]
        q_b, jac, var_fit, lev = matcher.match(np.stack([codes_a.x[sl], codes_a.y[sl]], 1))
        s = codes_a.noise.at(flat, sigma_px)  # (m, 2 [code]), projector pixels
        # covariance of q_B: A's code noise through ∂q_B/∂code, J·diag(s²)·Jᵀ, with the
        # correlation of the two pixel axes; plus the local fit's variance per axis (B's codes
        # and the affine misfit, estimated from 5 residual degrees of freedom for k = 8: too
        # few for a cross term worth weighting by; see triangulate_camera_pair)
        cov_a = np.einsum("...ik,...k,...jk->...ij", jac, s**2, jac)  # (m, 2, 2), pixels² of B
        cov = cov_a + var_fit[..., None] * np.eye(2)
        del cov_a
        ok = np.isfinite(q_b).all(-1) & np.isfinite(cov).all((-2, -1))
        with np.errstate(invalid="ignore"):
            extrapolated = (ok & (lev > max_leverage) if max_leverage is not None
                            else ok & False)
            # B's neighbours on one pixel row (or column): the fit sees no change of that axis
            # with the code, and the location claims zero variance along it
            det = cov[..., 0, 0] * cov[..., 1, 1] - cov[..., 0, 1] * cov[..., 1, 0]
            tr2 = (cov[..., 0, 0] + cov[..., 1, 1]) ** 2
            degenerate = ok & ~(det > _MIN_COV_RATIO * tr2)
        ok &= ~extrapolated & ~degenerate
        reason[flat[extrapolated | degenerate]] = UNCERTAIN
        idx = np.flatnonzero(ok)
        if not idx.size:
            continue
        f = flat[idx]
        o, d = cam_a.pixel_rays(np.stack([f % W, f // W], 1).astype(np.float64))
        fit = solve_along_rays(o, d, cam_b, q_b[idx], cov_other=cov[idx])
        # the depth's gains on the code noise (CodeGains): δt = gᵀ·δq_B,
        # δq_B = J·(n_A − Σ h_j n_B(j))
        g = fit.dt_dq  # (k, 2), metres per pixel of B
        out = slice(n, n + idx.size)
        a["index"][out] = f
        a["t"][out], a["sigma_t"][out], a["chi"][out] = fit.t, fit.sigma_t, fit.chi
        a["sin_angle"][out] = fit.sin_angle
        a["p"][out] = o + fit.t[:, None] * d
        a["dt_dcode"][out] = np.einsum("nij,ni->nj", jac[idx], g)
        if with_var_fit:  # the fit's share of σ², metres² (B's codes, misfit)
            a["var_fit"][out] = np.einsum("ni,ni->n", g * g, var_fit[idx])
        a["h"][out] = lev[idx] / k  # (G⁻¹)₃₃: weight of B's pixel at the match in the fit
        n += idx.size
    for name in list(a):  # to the solved count, one kept array at a time
        a[name] = a[name][:n].copy() if n < n_a and name not in ("t", "sin_angle", "h") else (
            a[name][:n])
    fit = RayFit(a.pop("t"), a["sigma_t"], a["chi"], np.zeros(0), a.pop("sin_angle"))
    r = _classify(fit, a["p"], max_sigma_ratio=max_sigma_ratio, max_sigma=None,
                  min_angle_deg=min_angle_deg, max_chi=max_chi)
    reason[a["index"]] = r
    live = r == OK
    dt_dcode, var_fit_t, h = a["dt_dcode"], a.get("var_fit"), a["h"]
    dt_dcode[~live] = np.nan
    if var_fit_t is not None:
        var_fit_t[~live] = np.nan
    partner = np.where(live[:, None], -h[:, None] * dt_dcode, 0.0)
    gains = CodeGains(codes_a.noise, sigma_px, dt_dcode, {cam_b.name: partner},
                      {cam_b.name: np.where(live, h, np.nan)})
    conf = (np.ones(a["index"].size, np.float32) if codes_a.confidence is None else
            codes_a.confidence[np.searchsorted(codes_a.index, a["index"])])
    pm = PointMap(cam_a.name, shape, a["index"], a["p"], a["sigma_t"], a["chi"], conf,
                  reason.reshape(shape), cam_a.center_world.copy(), gains)
    return pm, var_fit_t


def triangulate_camera_pairs(cameras: list[Camera], x: list, y: list, *, confidence=None,
                             sigma_px=0.3, sigma_x=None, sigma_y=None, k: int = 8,
                             max_sigma_ratio: float = 5.0, min_angle_deg: float | None = None,
                             max_chi: float = 4.0, max_leverage: float | None = 3.0,
                             tol_sigmas: float = 4.0, tol_floor: float = 1e-3,
                             spike_sigmas: float = 6.0,
                             spike_floor: float = 1e-3) -> tuple[list[PointMap], dict]:
    """Every camera's points against every other camera, through matching projector codes.

    The camera–camera counterpart of calling :func:`triangulate_maps` once per camera, for rigs
    whose projector is uncalibrated: camera A's pixels are triangulated against each other
    camera B in turn (:func:`triangulate_camera_pair`, all ordered pairs), and the estimates of
    one A pixel — all on A's ray — are merged: the inverse-variance mean of the depths that
    agree with the most certain one within ``tol_sigmas·sqrt(σ_i² + σ_best²) + tol_floor``
    (the others are dropped). A's own code noise is common to all of A's pairs, so it is not
    averaged down but propagated once: with normalised weights ``ŵ_i``, ``s_i`` pair i's depth
    gain on A's code (:attr:`CodeGains.dt_dcode`) and ``f_i`` its fit's variance (B's codes,
    independent between partners), ``σ² = (Σ ŵ_i s_i)ᵀ·Σ_A·(Σ ŵ_i s_i) + Σ ŵ_i² f_i``. The
    gains are vectors over the code axes: a horizontal partner reads mostly A's column code, a
    vertical one its row code, so the pairs' own-code errors are not perfectly correlated, as
    the previous version's ``(Σ ŵ_i σ_i √a_i)²`` took them (plane, three cameras: RMS z 0.88,
    now 1.01). Isolated wrong depths are then
    rejected as in :func:`triangulate_maps` (reason :data:`OUTLIER`). The result, one map per
    camera on its own pixel grid, goes to :func:`fuse_cameras` like the camera–projector maps,
    with the merged :class:`CodeGains`.
    Memory: the maps are compressed (:class:`PointMap`); the codes are compressed first
    (:class:`facegeo.geometry.code_maps.CodeSet`, :func:`triangulate_code_sets`) and matched
    in blocks of :data:`_MATCH_CHUNK` pixels, so besides the inputs and the finished maps only
    camera A's maps against its partners and B's k-d tree of codes are held at a time.

    Parameters
    ----------
    cameras : list of Camera
        At least two; the maps' sizes are the cameras'.
    x, y : list of (H_c, W_c) float, projector pixels (NaN invalid)
        Each camera's decoded projector column and row; mask invalid or low-confidence codes as
        NaN first (they are neither triangulated nor matched against).
    confidence : list of (H_c, W_c) float, 0..1, optional
        Stored in the maps (default 1).
    sigma_px : float or sequence of float, projector pixels
        Each camera's decode noise (1 σ) where ``sigma_x`` / ``sigma_y`` give none.
    sigma_x, sigma_y : list of (H_c, W_c) float (or None), projector pixels, optional
        Each camera's decode noise per pixel and axis (:func:`triangulate_camera_pair`).
    k, max_sigma_ratio, min_angle_deg, max_chi, max_leverage
        :func:`triangulate_camera_pair`.
    tol_sigmas, tol_floor : float, tol_floor in metres
        Agreement of one pixel's estimates from different partners.
    spike_sigmas, spike_floor : float, spike_floor in metres
        :func:`triangulate_maps`.

    Returns
    -------
    maps : list of PointMap
        One per camera, in order; ``reason`` where no partner gave a point is the furthest any
        partner got (e.g. :data:`INCONSISTENT` over :data:`NO_CODE`).
    partners : dict
        ``{camera A: {camera B: points of A triangulated against B}}``.
    """
    cams = list(cameras)
    if len(cams) < 2 or len(x) != len(cams) or len(y) != len(cams):
        raise InputError(f"cameras, x, y: expected two or more cameras with one x and one y map "
                         f"each, got {len(cams)} cameras, {len(x)} x and {len(y)} y maps")
    s = _sigma_px_per_camera(cams, sigma_px)
    for name, maps_ in (("sigma_x", sigma_x), ("sigma_y", sigma_y), ("confidence", confidence)):
        if maps_ is not None and len(maps_) != len(cams):
            raise InputError(f"{name}: expected one map (or None) per camera ({len(cams)}), got "
                             f"{len(maps_)}")
    _check_pair_settings(k, max_leverage)
    codes = []
    for a, ca in enumerate(cams):
        shape = (ca.height, ca.width)
        xa = as_array(x[a], "x_a", shape=shape, finite=False)
        sx = None if sigma_x is None or sigma_x[a] is None else _map(sigma_x[a], "sigma_x", shape)
        sy = None if sigma_y is None or sigma_y[a] is None else _map(sigma_y[a], "sigma_y", shape)
        conf = (None if confidence is None or confidence[a] is None else
                _map(confidence[a], "confidence", shape, np.float32))
        codes.append(_codes_of(ca, xa, y[a], sx, sy, conf))
    return triangulate_code_sets(cams, codes, sigma_px=s, k=k, max_sigma_ratio=max_sigma_ratio,
                                 min_angle_deg=min_angle_deg, max_chi=max_chi,
                                 max_leverage=max_leverage, tol_sigmas=tol_sigmas,
                                 tol_floor=tol_floor, spike_sigmas=spike_sigmas,
                                 spike_floor=spike_floor)


def _sigma_px_per_camera(cams, sigma_px) -> np.ndarray:
    sp = np.asarray(sigma_px, np.float64)
    if sp.ndim > 1 or (sp.ndim == 1 and sp.size not in (1, len(cams))):
        raise InputError(f"sigma_px: expected one number or one per camera ({len(cams)}), got "
                         f"shape {sp.shape}")
    s = np.broadcast_to(sp.reshape(-1) if sp.ndim else sp, (len(cams),))
    for c, v in zip(cams, s):
        check_positive(float(v), f"sigma_px ({c.name})")
    return s


def triangulate_code_sets(cameras: list[Camera], codes: list[CodeSet], *, sigma_px=0.3,
                          k: int = 8, max_sigma_ratio: float = 5.0,
                          min_angle_deg: float | None = None, max_chi: float = 4.0,
                          max_leverage: float | None = 3.0, tol_sigmas: float = 4.0,
                          tol_floor: float = 1e-3, spike_sigmas: float = 6.0,
                          spike_floor: float = 1e-3) -> tuple[list[PointMap], dict]:
    """:func:`triangulate_camera_pairs` on compressed codes.

    Parameters
    ----------
    cameras : list of Camera
        At least two.
    codes : list of facegeo.geometry.code_maps.CodeSet
        Each camera's codes at its usable pixels (mask invalid or low-confidence codes out
        first), its decode noise and confidence; shapes the cameras'.
    sigma_px, k, max_sigma_ratio, min_angle_deg, max_chi, max_leverage, tol_sigmas, tol_floor,
    spike_sigmas, spike_floor
        :func:`triangulate_camera_pairs`.

    Returns
    -------
    maps, partners
        :func:`triangulate_camera_pairs`.
    """
    cams = list(cameras)
    if len(cams) < 2 or len(codes) != len(cams):
        raise InputError(f"cameras, codes: expected two or more cameras with one code set "
                         f"each, got {len(cams)} cameras and {len(codes)} code sets")
    for c, cs in zip(cams, codes):
        if not isinstance(cs, CodeSet) or cs.shape != (c.height, c.width):
            got = cs.shape if isinstance(cs, CodeSet) else type(cs).__name__
            raise ShapeError(f"codes: expected a CodeSet of camera {c.name!r}'s image shape "
                             f"{(c.height, c.width)}, got {got}")
    s = _sigma_px_per_camera(cams, sigma_px)
    _check_pair_settings(k, max_leverage)
    maps, partners = [], {}
    for a, ca in enumerate(cams):
        pair_maps, shares = [], []
        partners[ca.name] = {}
        for b, cb in enumerate(cams):
            if b == a:
                continue
            pm, share = _camera_pair(
                ca, cb, codes[a], _CodeMatcher.of(codes[b], k, None), sigma_px=float(s[a]), k=k,
                max_sigma_ratio=max_sigma_ratio, min_angle_deg=min_angle_deg, max_chi=max_chi,
                max_leverage=max_leverage, with_var_fit=len(cams) > 2)
            partners[ca.name][cb.name] = int(np.count_nonzero(pm.valid_at))
            pair_maps.append(pm)
            shares.append(share)
        pm = _merge_along_rays(pair_maps, shares, codes[a], tol_sigmas, tol_floor)
        del pair_maps, shares
        _reject_spikes(pm, spike_sigmas, spike_floor)
        maps.append(pm)
    return maps, partners


def _merge_along_rays(maps: list[PointMap], var_fit: list[np.ndarray], codes: CodeSet,
                      tol_sigmas: float, tol_floor: float) -> PointMap:
    """One camera's point maps against several partners, merged into one
    (:func:`triangulate_camera_pairs`); ``var_fit`` the fit's share of each map's variance (on
    its pixels), ``codes`` the camera's code set (its confidence)."""
    if len(maps) == 1:
        return maps[0]
    index = np.unique(np.concatenate([m.index for m in maps]))  # (u,) every solved pixel
    J, u = len(maps), index.size
    pos = [np.searchsorted(index, m.index) for m in maps]

    def stack(values, fill, extra=()):
        out = np.full((J, u) + extra, fill, dtype=np.result_type(values[0], type(fill)))
        for j, v in enumerate(values):
            out[j, pos[j]] = v
        return out

    D = stack([m.depth_at for m in maps], np.nan)  # (J, u), NaN without a point
    S = stack([np.where(m.valid_at, m.point_sigma, np.nan) for m in maps], np.nan)
    ok = np.isfinite(D) & np.isfinite(S)
    best = np.argmin(np.where(ok, S, np.inf), axis=0)[None]
    d0 = np.take_along_axis(D, best, 0)
    s0 = np.take_along_axis(S, best, 0)
    with np.errstate(invalid="ignore"):
        agree = ok & (np.abs(D - d0) <= tol_sigmas * np.sqrt(S**2 + s0**2) + tol_floor)
    S1 = np.where(agree, S, 1.0)
    w = np.where(agree, 1.0 / S1**2, 0.0)
    wsum = w.sum(0)
    have = wsum > 0
    wn = w / np.where(have, wsum, 1.0)
    depth = (wn * np.where(agree, D, 0.0)).sum(0)
    del D, S, S1, w
    # A's own code enters every pair through its gain: propagate it once, the fits apart
    gains = [m.code_gains for m in maps]
    sig_code = gains[0].sigma_code_at(index)
    dt_dcode = (wn[..., None] * np.nan_to_num(stack([g.dt_dcode for g in gains], np.nan,
                                                     (2,)))).sum(0)
    var = ((dt_dcode * sig_code) ** 2).sum(-1)
    var += (wn**2 * np.nan_to_num(stack(var_fit, np.nan))).sum(0)
    partner, weight = {}, {}
    for j, (wj, aj, g) in enumerate(zip(wn, agree, gains)):
        for name, pg in g.partner_dt_dcode.items():
            pgu = np.zeros((u, 2))
            pgu[pos[j]] = pg  # 0 where that partner did not contribute
            partner[name] = partner.get(name, 0.0) + wj[..., None] * pgu
            hu = np.full(u, np.nan)
            hu[pos[j]] = g.partner_weight[name]
            weight[name] = np.where(aj, hu, np.nan)
    p_best = np.take_along_axis(stack([m.points for m in maps], np.nan, (3,)),
                                best[..., None], 0)[0]
    c = maps[0].center_world
    with np.errstate(invalid="ignore", divide="ignore"):
        ray = (p_best - c) / d0[0][..., None]
    p = np.where(have[..., None], c + depth[..., None] * ray, np.nan)
    chi = np.take_along_axis(stack([m.point_chi for m in maps], np.nan), best, 0)[0]
    reason = np.stack([m.reason for m in maps]).max(0)
    reason.reshape(-1)[index[have]] = OK
    code_gains = CodeGains(gains[0].noise, gains[0].sigma_px,
                           np.where(have[..., None], dt_dcode, np.nan), partner, weight)
    conf = (np.ones(u, np.float32) if codes.confidence is None else
            codes.confidence[np.searchsorted(codes.index, index)])
    return PointMap(maps[0].camera, maps[0].shape, index, p, np.where(have, np.sqrt(var), np.nan),
                    np.where(have, chi, np.nan), conf, reason, c.copy(), code_gains)
