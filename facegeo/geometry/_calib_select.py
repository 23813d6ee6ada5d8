"""Distortion model per camera (``model="auto"``): held-out error, parsimony, no degenerate lens.

A narrow camera (the synthetic rig's ≈ 12° field) does not constrain OpenCV's 5-term model:
k2, k3 and the tangential terms trade against the principal point (σ(k3) ≈ 10⁵, corr(c, k3) up
to 0.7), and the solve fits the noise with them. A wide real lens needs them. And a flexible
model can fit real corners with a lens no real lens is: on OpenCV's own left camera the
rational model reached coefficients of 10–106 whose terms cancel (1250× their net effect) for a
held-out gain of 0.0016 px, and was chosen. The choice is therefore measured, per camera, on
the camera's own views, and checked:

1. every candidate (simplest first) is solved on all usable views, warm-started from the
   previous candidate's solution (the coefficients it adds start at 0);
2. a candidate whose lens is degenerate over the image is refused (:func:`lens_degeneracy`:
   the radial factor changes sign or meets a pole, the distorted radius folds back, numerator
   and denominator share a root, or coefficients cancel each other — large terms, small net
   effect);
3. its held-out error: each view is left out in turn (``folds=None``; or k folds of views), the
   intrinsics solved without it (one Gauss–Newton step from the solution on all views,
   :func:`~._calib_jac.leave_out_steps`: within ≈ 0.03 px of a full re-solve on fx, cx, cy of
   OpenCV's chessboards), the view's board pose re-solved with those intrinsics fixed
   (to second order, from the view's blocks of the normal equations: the PRESS identity), and
   its corners' mean squared residual is the model's held-out error on that view;
4. parsimony: going through the admissible candidates in order, a candidate replaces the model
   chosen so far only if its mean held-out gain over it, per view, exceeds the noise: one
   standard error (:data:`AUTO_GAIN_NOISE`) of the per-view paired differences — a gain a
   different set of views would not reproduce is no gain. (The held-out error's *own* standard
   error, tried first, is dominated by how much the views' error levels differ, not the
   models: on OpenCV's right camera it refused ``k1k2`` over ``k1`` for a gain of 4.2 paired
   standard errors, then took ``opencv5`` over ``k1``.) Every candidate not taken says why.

The held-out view's pose is refitted (six parameters per view of ≥ 12 corners), so a model is
judged on what the pose cannot absorb: the shape of its projection over the image. The flip
side: what a pose can absorb is not scored; tangential terms of ≈ 1e-3 are mostly a tilt of the
held-out board, and the rule drops them unless the views are many or precise.

References
----------
.. [1] T. Hastie, R. Tibshirani, J. Friedman, *The Elements of Statistical Learning*, 2nd ed.,
   §7.10 (cross-validation, the one-standard-error rule).
.. [2] D. Kogan, mrcal: cross-validation and the projection uncertainty,
   https://mrcal.secretsauce.net/
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from facegeo.checks import check_choice
from facegeo.errors import InputError
from facegeo.geometry._calib_jac import leave_out_steps
from facegeo.geometry._calib_solve import (
    MODELS,
    CameraCalibration,
    _check_views,
    fit_model,
    rotate_rvec,
    zhang_start,
)

log = logging.getLogger(__name__)

__all__ = ["AUTO_CANDIDATES", "AUTO_FALLBACK", "AUTO_GAIN_NOISE", "lens_degeneracy",
           "select_model"]

#: Candidate models of ``model="auto"``, simplest first (the parsimony order).
AUTO_CANDIDATES = ("pinhole", "k1", "k1k2", "opencv5", "rational8")

#: Differences of mean squared held-out error below this (px²) are ties (noise-free data, where
#: a model and its superset both fit to rounding and the standard error is rounding too).
AUTO_TIE_PX2 = 1e-12

#: Model used when there are too few views to hold any out (OpenCV's default model).
AUTO_FALLBACK = "opencv5"

#: How many standard errors (across views, of the per-view paired difference of held-out mean
#: squared error) a more complex candidate's held-out gain must exceed.
AUTO_GAIN_NOISE = 1.0

#: Cancellation: a lens whose radial terms add up, in absolute value, to more than this many
#: times their net effect (and to more than :data:`CANCEL_MIN_PX` at the image's edge) is
#: refused. Real fits on OpenCV's and synthetic lenses: 1.0–2.9; the degenerate rational fits
#: of OpenCV's cameras: 37–1800.
CANCEL_RATIO = 10.0

#: Below this gross radial displacement (pixels, at the image's edge) cancellation is harmless.
CANCEL_MIN_PX = 1.0

#: Roots of numerator and denominator this close (relative, in r) count as shared.
SHARED_ROOT_REL = 0.1

#: Radii sampled along a ray, over [0, 4 × the image corner's distorted radius].
_RADIUS_SAMPLES = 2048

#: Iterations of each candidate's solve during the selection (OpenCV's default count for
#: ``calibrateCamera``): an ill-conditioned model crawls along its valley for 40–70 iterations
#: on OpenCV's chessboards (the rational model) and is judged where it got to; the chosen
#: model, if it had not converged, is solved to convergence from there.
AUTO_MAX_ITER = 30


def _image_edge_radius(camera) -> float:
    """Largest distorted normalised radius of the image's four outer corners."""
    w, h = camera.width, camera.height
    u = np.array([-0.5, w - 0.5, -0.5, w - 0.5])
    v = np.array([-0.5, -0.5, h - 0.5, h - 0.5])
    return float(np.max(np.hypot((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy)))


def _positive_real_roots(c) -> np.ndarray:
    """Real roots > 0 of ``1 + c0 s + c1 s² + c2 s³`` (s = r²)."""
    coef = np.array([c[2], c[1], c[0], 1.0])
    nz = np.flatnonzero(coef != 0)
    if nz.size == 0 or nz[0] == 3:
        return np.zeros(0)
    z = np.roots(coef[nz[0]:])
    z = z[np.abs(z.imag) <= 1e-9 * np.maximum(1.0, np.abs(z.real))].real
    return np.sort(z[z > 0])


def lens_degeneracy(camera, *, r_data: float = 0.0) -> dict:
    """Whether a camera's radial distortion is a lens over its image, or a degenerate fit.

    Along a ray of undistorted normalised radius r (``s = r²``) OpenCV's radial factor is
    ``g = (1 + k1 s + k2 s² + k3 s³) / (1 + k4 s + k5 s² + k6 s³)`` and the distorted radius
    ``r_d = r g``. Sampled over ``r ∈ [0, r_max]`` (``r_max``: where ``r_d`` reaches the
    image's outer corners, or the data's largest radius ``r_data`` if beyond), a lens is
    refused when

    * ``g ≤ 0`` or the denominator ``≤ 0`` (sign change, pole), or ``r_d`` stops increasing
      (the model folds back: two rays on one pixel) — or ``r_d`` never reaches the image's
      corners (they have no ray);
    * numerator and denominator both have a real root in ``(0, r_max²]`` (a shared root: the
      factor is their ratio of two near-zero numbers there);
    * the radial terms cancel: ``max Σ|k_i sⁱ|`` over the radii exceeds :data:`CANCEL_RATIO`
      × ``max |g − 1|`` while amounting to more than :data:`CANCEL_MIN_PX` pixels at the edge.

    Tangential terms are not checked (small, direction-dependent).

    Parameters
    ----------
    camera : Camera
    r_data : float
        Largest undistorted normalised radius of the corners the lens was fitted to.

    Returns
    -------
    dict
        ``degenerate`` (bool), ``reason`` (str, or None for a lens), ``r_max`` (the radius
        checked), ``cancellation`` (``max Σ|terms| / max |g − 1|``; 1 for a single term).
    """
    d8 = np.zeros(8)
    d8[: camera.dist.size] = camera.dist
    k1, k2, _, _, k3, k4, k5, k6 = d8
    rd_img = _image_edge_radius(camera)
    out = {"degenerate": False, "reason": None, "r_max": float("nan"), "cancellation": 1.0}
    if not np.any(d8[[0, 1, 4, 5, 6, 7]]):
        out["r_max"] = max(rd_img, r_data)
        return out
    r = np.linspace(0.0, 4.0 * max(rd_img, r_data, 1e-6), _RADIUS_SAMPLES)
    s = r * r
    num = 1.0 + s * (k1 + s * (k2 + s * k3))
    den = 1.0 + s * (k4 + s * (k5 + s * k6))
    with np.errstate(divide="ignore", invalid="ignore"):
        g = num / den
    rd = r * g
    fold = np.r_[False, np.diff(rd) <= 0]
    bad = {"the radial factor's denominator reaches 0 (a pole)": den <= 0,
           "the radial factor changes sign": num <= 0,
           "the distorted radius folds back (two rays on one pixel)": fold}
    any_bad = np.flatnonzero((den <= 0) | (num <= 0) | fold)
    i_bad = int(any_bad[0]) if any_bad.size else r.size
    # along the ray, up to the first breakdown, where the image's corners are reached
    reach = np.flatnonzero(rd[:i_bad] >= rd_img)
    r_img = r[reach[0]] if reach.size else np.inf
    r_max = max(r_img, r_data)
    out["r_max"] = float(min(r_max, r[-1]))
    rn = np.sqrt(_positive_real_roots((k1, k2, k3)))
    rq = np.sqrt(_positive_real_roots((k4, k5, k6)))
    if i_bad < r.size and r[i_bad] <= r_max:
        why = next(w for w, m in bad.items() if m[i_bad])
        near = [a for a in rn for b in rq if abs(a - b) <= SHARED_ROOT_REL * a
                and abs(a - r[i_bad]) <= SHARED_ROOT_REL * a]
        if near:
            why = (f"numerator and denominator share a root (r ≈ {near[0]:.3g}): the factor is "
                   "a ratio of two near-zero numbers there")
        where = ("inside the image (its corners at r = {:.3g}, normalised)".format(r_img)
                 if np.isfinite(r_img) else
                 "before the image's corners (distorted radius {:.3g}) are reached: they have "
                 "no ray".format(rd_img))
        out.update(degenerate=True, reason=f"{why} at r = {r[i_bad]:.3g}, {where}")
        return out
    if not np.isfinite(r_max):
        out.update(degenerate=True,
                   reason=f"the distorted radius never reaches the image's corners "
                          f"({rd_img:.3g}, normalised) before r = {r[-1]:.3g}")
        return out
    inside = r <= r_max
    rn, rq = rn[rn <= r_max], rq[rq <= r_max]
    if rn.size and rq.size:  # both vanish inside the image (between samples, or a double root)
        out.update(degenerate=True, reason=(
            f"numerator and denominator share a root inside the image (r = {rn[0]:.3g} and "
            f"{rq[0]:.3g}, image corners at r = {r_max:.3g}): the factor is a ratio of two "
            "near-zero numbers there"))
        return out
    ss, ri = s[inside], r[inside]
    gross = (abs(k1) + abs(k4)) * ss + (abs(k2) + abs(k5)) * ss**2 + (abs(k3) + abs(k6)) * ss**3
    net = np.abs(g[inside] - 1.0)
    ratio = float(gross.max() / net.max()) if net.max() > 0 else float("inf")
    out["cancellation"] = ratio
    f = max(camera.fx, camera.fy)
    gross_px, net_px = float(np.max(gross * ri) * f), float(np.max(net * ri) * f)
    if ratio > CANCEL_RATIO and gross_px > CANCEL_MIN_PX:
        out.update(degenerate=True, reason=(
            f"the radial terms cancel: their magnitudes add up to {ratio:.3g}× their net effect "
            f"({gross_px:.3g} px of terms for {net_px:.3g} px of distortion within the image)"))
    return out


def _data_radius(c: CameraCalibration) -> float:
    """Largest undistorted normalised radius of the used views' corners."""
    used = np.flatnonzero(c.views_used)
    P = [c._object_points[i] for i in used]
    ps = c._poses_all[used]
    vidx = np.repeat(np.arange(used.size), [p.shape[0] for p in P])
    pc = rotate_rvec(ps[vidx, :3], np.concatenate(P)) + ps[vidx, 3:]
    return float(np.max(np.hypot(pc[:, 0], pc[:, 1]) / pc[:, 2]))


def _held_out(c: CameraCalibration, folds, seed: int) -> np.ndarray:
    """Per view, the held-out mean squared residual (px²): leave-one-out (``folds=None``) or
    k folds of the used views; views not used in the solve (outliers) at its intrinsics."""
    if folds is None:
        return c.held_out_mse()
    used = np.flatnonzero(c.views_used)
    perm = np.random.default_rng(seed).permutation(used.size)
    fold_of = np.empty(used.size, int)
    fold_of[perm] = np.arange(used.size) % int(folds)
    groups = [np.flatnonzero(fold_of == f) for f in range(int(folds))]
    groups = [g for g in groups if g.size]
    steps = leave_out_steps(*c._reduced, groups)
    thetas = np.tile(c._theta, (c.views_used.size, 1))
    for g, st in zip(groups, steps):
        thetas[used[g]] += st
    return c.held_out_mse(thetas)


def _select(P, Q, size, usable, reasons, *, candidates=AUTO_CANDIDATES, folds=None,
            seed: int = 0, fallback: str = AUTO_FALLBACK, K_init=None, **opts):
    """:func:`select_model`'s work on checked views; returns ``(selection, calibration)``, the
    calibration being the chosen candidate's solve (nothing is solved twice)."""
    for m in candidates:
        check_choice(m, "candidates", tuple(MODELS))
    check_choice(fallback, "fallback", tuple(MODELS))
    if folds is not None and int(folds) < 2:
        raise InputError(f"folds: expected at least 2 (or None: leave-one-out), got {folds}")
    min_views = int(opts.get("min_views", 3))
    fa = opts.get("fix_aspect_ratio")
    start = zhang_start(P, Q, size, usable, fix_aspect_ratio=fa, K_init=K_init)
    Vu = int(usable.sum())
    if Vu < min_views + 1:
        c = fit_model(P, Q, size, usable, fallback, start, rejected=reasons, **opts)
        sel = {"model": fallback, "best": None, "folds": 0, "scores": {}, "rejected": {},
               "reason": f"{Vu} views: too few to hold any out with {min_views} left to solve; "
                         f"the fallback model {fallback}"}
        return sel, c
    n_cor = np.array([p.shape[0] for p in P])
    fits, mse, scores = {}, {}, {}
    for m in candidates:
        try:
            c = fit_model(P, Q, size, usable, m, start, rejected=reasons,
                          max_iter=AUTO_MAX_ITER, **opts)
        except (InputError, cv2.error, np.linalg.LinAlgError) as exc:
            scores[m] = {"held_out_rms_px": None, "error": str(exc),
                         "rejected": f"the solve failed: {exc}"}
            continue
        d8 = np.zeros(8)
        d8[: c.camera.dist.size] = c.camera.dist
        start = (c.camera.K, d8, c._poses_all)
        e = _held_out(c, folds, seed)
        ok = c.views_used & np.isfinite(e)
        if not ok.any():
            scores[m] = {"held_out_rms_px": None, "error": "no view could be held out",
                         "rejected": f"no held-out error: {c.n_views_used} views in its solve"}
            continue
        lens = lens_degeneracy(c.camera, r_data=_data_radius(c))
        fits[m], mse[m] = c, np.where(ok, e, np.nan)
        scores[m] = {
            "held_out_rms_px": float(np.sqrt(np.sum(e[ok] * n_cor[ok]) / np.sum(n_cor[ok]))),
            "rms_px": c.rms_px, "converged": c.converged,
            "dist": [float(x) for x in c.camera.dist],
            "cancellation": lens["cancellation"], "degenerate": lens["reason"]}
    if not fits:
        raise InputError("select_model: every candidate model failed: " + "; ".join(
            f"{m}: {s.get('error')}" for m, s in scores.items()))
    best = min(fits, key=lambda m: scores[m]["held_out_rms_px"])
    chosen, rejected = None, {}
    for m in candidates:
        s = scores[m]
        if m not in fits:
            rejected[m] = s["rejected"]
            continue
        if s["degenerate"]:
            rejected[m] = s["rejected"] = f"degenerate lens: {s['degenerate']}"
            continue
        if chosen is None:
            chosen = m
            continue
        both = np.isfinite(mse[chosen]) & np.isfinite(mse[m])
        a, b = mse[chosen][both], mse[m][both]
        n = int(both.sum())
        gain = float(np.mean(a - b))
        se = float((a - b).std(ddof=1) / np.sqrt(n)) if n > 1 else 0.0
        noise = AUTO_GAIN_NOISE * se
        s.update({"compared_with": chosen, "gain_px2": gain, "gain_se_px2": se,
                  "noise_px2": noise})
        if gain > noise + AUTO_TIE_PX2:
            rejected[chosen] = scores[chosen]["rejected"] = (
                f"{m} gains {gain:.3g} ± {se:.3g} px² per view on held-out views over it")
            chosen = m
        else:
            rejected[m] = s["rejected"] = (
                f"held-out gain over {s['compared_with']} {gain:.3g} ± {se:.3g} px² per view "
                f"is below the noise ({AUTO_GAIN_NOISE:g} standard error over {n} views)")
    if chosen is None:
        raise InputError("select_model: every candidate is degenerate or failed: " + "; ".join(
            f"{m}: {why}" for m, why in rejected.items()))
    k = "leave-one-out" if folds is None else f"{int(folds)} folds"
    reason = (f"{chosen}: held-out RMS {scores[chosen]['held_out_rms_px']:.4g} px over "
              f"{fits[chosen].n_views_used} views ({k})")
    if rejected:
        reason += "; not taken: " + "; ".join(f"{m} ({why})" for m, why in rejected.items())
    log.info("select_model: %s", reason)
    sel = {"model": chosen, "best": best, "folds": Vu if folds is None else int(folds),
           "scores": scores, "rejected": rejected, "reason": reason}
    c = fits[chosen]
    if not c.converged:  # solved on from where the selection's iteration limit left it
        d8 = np.zeros(8)
        d8[: c.camera.dist.size] = c.camera.dist
        c = fit_model(P, Q, size, usable, chosen, (c.camera.K, d8, c._poses_all),
                      rejected=reasons, **opts)
    return sel, c


def select_model(object_points, image_points, image_size, *, candidates=AUTO_CANDIDATES,
                 folds: int | None = None, seed: int = 0, min_views: int = 3,
                 fallback: str = AUTO_FALLBACK, **kwargs) -> dict:
    """Choose a camera's distortion model: held-out error over its views, no degenerate lens.

    Parameters
    ----------
    object_points : sequence of (N_i, 3) float64, metres, board frame
    image_points : sequence of (N_i, 2) float64, pixels
        Per view, as for :func:`~._calib_solve.calibrate_camera`.
    image_size : (int, int)
        ``(width, height)``, pixels.
    candidates : sequence of str
        Models (keys of :data:`~._calib_solve.MODELS`), simplest first: the parsimony order
        (and the warm-start chain).
    folds : int or None
        None (default): leave one view out at a time; else k folds of views (shuffled,
        ``seed``).
    seed : int
        Shuffles the views of k folds.
    min_views : int
        Fewest views of a solve; with fewer than ``min_views + 1`` usable views nothing can be
        held out and ``fallback`` is the model.
    fallback : str
        The model when too few views can be held out (:data:`AUTO_FALLBACK`; a scan passes
        its rig file's model, :func:`~._calib_solve.model_of_dist` of the nominal camera).
    **kwargs
        Passed to every solve (``fix_aspect_ratio``, ``K_init``, ``loss``, ``reject_views`` …).

    Returns
    -------
    dict
        ``model`` (the choice), ``reason`` (one line, with why each other candidate was not
        taken), ``best`` (lowest held-out error, admissible or not), ``folds`` (number of
        folds: the views for leave-one-out), ``rejected`` (``{model: why}``), ``scores``:
        ``{model: {held_out_rms_px, rms_px, converged, dist, cancellation, degenerate,
        [compared_with, gain_px2, gain_se_px2, noise_px2,] [rejected]}}`` (``gain_px2``: mean
        per-view held-out gain over the model chosen before it, ``gain_se_px2`` its standard
        error; ``noise_px2``: the threshold it had to beat; a failed solve has
        ``held_out_rms_px`` None and ``error``).

    Raises
    ------
    InputError
        Unknown candidate, ``folds`` < 2, too few usable views, every candidate degenerate.
    """
    from facegeo.checks import as_array
    from facegeo.geometry._calib_detect import as_corner_lists

    P, Q = as_corner_lists(object_points, image_points)
    size = tuple(int(s) for s in as_array(image_size, "image_size", shape=(2,)))
    usable, reasons = _check_views(P, Q, size, min_views)
    sel, _ = _select(P, Q, size, usable, reasons, candidates=candidates, folds=folds,
                     seed=seed, fallback=fallback, min_views=min_views, **kwargs)
    return sel
