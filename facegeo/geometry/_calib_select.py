"""Distortion model per camera, chosen by cross-validation over views (``model="auto"``).

A narrow camera (the synthetic rig's ≈ 12° field) does not constrain OpenCV's 5-term model:
k2, k3 and the tangential terms trade against the principal point (σ(k3) ≈ 10⁵, corr(c, k3) up
to 0.7), and the solve fits the noise with them. A wide real lens needs them. The choice is
therefore measured, per camera, on the camera's own views:

1. the views are split into ``folds`` groups (shuffled, ``seed``);
2. for every candidate model and fold, the camera is calibrated on the other folds' views
   (:func:`~._calib_solve.calibrate_camera`), then each held-out view's board pose alone is
   solved with those intrinsics fixed (``solvePnP``, IPPE start, Levenberg–Marquardt refine) and
   its corner residuals are the model's held-out error on that view;
3. the score of a model is the held-out RMS over all views, ``sqrt(Σ‖r‖² / N_corners)``;
4. parsimony (the "one-standard-error rule" of cross-validation, Hastie, Tibshirani & Friedman,
   *Elements of Statistical Learning* §7.10): the chosen model is the simplest one whose mean
   held-out squared error per view exceeds the best model's by at most one standard error of
   the per-view differences (paired over the same views), i.e. within the noise of the best.

The held-out view's pose is refitted (six parameters per view of ≥ 12 corners), so a model is
judged on what the pose cannot absorb: the shape of its projection over the image. This is
mrcal's reason for cross-validation (two solves on disjoint halves, :func:`~._calib_rig.
cross_validate`), made into a score per model with k folds so every view is held out once.
The flip side: what a pose can absorb is not scored. On a wide lens with 0.2 px corner noise
and 12 views the rule may drop tangential terms of ≈ 1e-3 (their effect is mostly a tilt of the
held-out board) and move the principal point by ≈ 2 σ; with 0.05 px it keeps them
(``docs/calibration.md``).
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from facegeo.checks import check_choice
from facegeo.errors import InputError

log = logging.getLogger(__name__)

__all__ = ["AUTO_CANDIDATES", "AUTO_FOLDS", "select_model"]

#: Candidate models of ``model="auto"``, simplest first (the parsimony order).
AUTO_CANDIDATES = ("pinhole", "k1", "k1k2", "opencv5", "rational8")

#: Default number of folds over the views.
AUTO_FOLDS = 5

#: Differences of mean squared held-out error below this (px²) are ties (noise-free data, where
#: a model and its superset both fit to rounding and the standard error is rounding too).
AUTO_TIE_PX2 = 1e-12

#: Model used when there are too few views to hold any out (OpenCV's default model).
AUTO_FALLBACK = "opencv5"


def _held_out_residuals(cam, p, q) -> np.ndarray:
    """Corner residuals (N, 2) of one view at its best pose with ``cam``'s intrinsics fixed."""
    ok, rv, tv = cv2.solvePnP(p, q, cam.K, cam.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rv, tv = cv2.solvePnP(p, q, cam.K, cam.dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return np.full(q.shape, np.nan)
    rv, tv = cv2.solvePnPRefineLM(p, q, cam.K, cam.dist, rv, tv)
    q_pred, _ = cv2.projectPoints(p, rv, tv, cam.K, cam.dist)
    return q_pred.reshape(-1, 2) - q


def select_model(object_points, image_points, image_size, *, solve, models,
                 candidates=AUTO_CANDIDATES, folds: int = AUTO_FOLDS, seed: int = 0,
                 min_views: int = 3, fallback: str = AUTO_FALLBACK, **kwargs) -> dict:
    """Choose a camera's distortion model by k-fold cross-validation over its views.

    ``solve`` and ``models`` are :func:`~._calib_solve.calibrate_camera` and
    :data:`~._calib_solve.MODELS`, passed in by that module (which calls this one for
    ``model="auto"``) so that neither module imports the other back; the public
    :func:`facegeo.geometry.calibration.select_model` binds them.

    Parameters
    ----------
    object_points : sequence of (N_i, 3) float64, metres, board frame
    image_points : sequence of (N_i, 2) float64, pixels
        Per view, as for :func:`~._calib_solve.calibrate_camera` (usable views only: views that
        fail its checks make every fold fail).
    image_size : (int, int)
        ``(width, height)``, pixels.
    candidates : sequence of str
        Models (keys of :data:`~._calib_solve.MODELS`), simplest first: ties go to the earlier.
    folds : int
        Number of folds (at most the number of views; each fold's training set keeps at least
        ``min_views`` views).
    seed : int
        Shuffles the views before the split.
    min_views : int
        Fewest training views of a fold's solve.
    fallback : str
        The model when too few views can be held out (:data:`AUTO_FALLBACK`; a scan passes
        its rig file's model, :func:`~._calib_solve.model_of_dist` of the nominal camera).
    **kwargs
        Passed to every :func:`~._calib_solve.calibrate_camera` (``fix_aspect_ratio``, ``loss``,
        ``reject_views`` …).

    Returns
    -------
    dict
        ``model`` (the choice), ``reason`` (one line), ``best`` (the lowest-scoring model),
        ``folds``, ``scores``: ``{model: {"held_out_rms_px", "delta_ms_px2", "delta_se_px2"}}``
        (held-out RMS over every corner; mean per-view difference of the mean squared error
        from the best model's and its standard error; ``None`` for a model whose solve failed,
        with ``error``). With fewer than ``min_views + 1`` views nothing can be held out:
        ``model`` is ``fallback`` and ``reason`` says so.

    Raises
    ------
    InputError
        Unknown candidate, ``folds`` < 2.
    """
    from facegeo.geometry._calib_detect import as_corner_lists

    MODELS, calibrate_camera = models, solve
    P, Q = as_corner_lists(object_points, image_points)
    for m in candidates:
        check_choice(m, "candidates", tuple(MODELS))
    check_choice(fallback, "fallback", tuple(MODELS))
    if int(folds) < 2:
        raise InputError(f"folds: expected at least 2, got {folds}")
    V = len(P)
    k = min(int(folds), V)
    # every training set keeps ≥ min_views views: the largest fold has ceil(V / k) views
    while k >= 2 and V - -(-V // k) < min_views:
        k -= 1
    if k < 2:
        return {"model": fallback, "best": None, "folds": 0, "scores": {},
                "reason": f"{V} views: too few to hold any out with {min_views} left to solve; "
                          f"the fallback model {fallback}"}
    perm = np.random.default_rng(seed).permutation(V)
    fold_of = np.empty(V, int)
    fold_of[perm] = np.arange(V) % k
    kwargs = {**kwargs, "min_views": min_views}
    sq = {}  # model → (V,) held-out mean squared residual per view (px²)
    ssum, ncor = {}, {}
    scores: dict = {}
    for m in candidates:
        per_view = np.full(V, np.nan)
        tot, n = 0.0, 0
        try:
            for f in range(k):
                tr = np.flatnonzero(fold_of != f)
                te = np.flatnonzero(fold_of == f)
                cal = calibrate_camera([P[i] for i in tr], [Q[i] for i in tr], image_size,
                                       model=m, **kwargs)
                for i in te:
                    r = _held_out_residuals(cal.camera, P[i], Q[i])
                    e = (r**2).sum(-1)
                    per_view[i] = float(e.mean())
                    tot += float(e.sum())
                    n += e.size
        except (InputError, cv2.error, np.linalg.LinAlgError) as exc:
            scores[m] = {"held_out_rms_px": None, "error": str(exc)}
            continue
        if not np.all(np.isfinite(per_view)):
            scores[m] = {"held_out_rms_px": None, "error": "a held-out view has no pose"}
            continue
        sq[m] = per_view
        ssum[m], ncor[m] = tot, n
        scores[m] = {"held_out_rms_px": float(np.sqrt(tot / n))}
    if not sq:
        raise InputError("select_model: every candidate model failed: " + "; ".join(
            f"{m}: {s.get('error')}" for m, s in scores.items()))
    best = min(sq, key=lambda m: ssum[m] / ncor[m])
    chosen = None
    for m in candidates:
        if m not in sq:
            continue
        d = sq[m] - sq[best]
        mean = float(d.mean())
        se = float(d.std(ddof=1) / np.sqrt(V)) if V > 1 else 0.0
        scores[m].update({"delta_ms_px2": mean, "delta_se_px2": se})
        if chosen is None and mean <= se + AUTO_TIE_PX2:
            chosen = m
    s_b, s_c = scores[best]["held_out_rms_px"], scores[chosen]["held_out_rms_px"]
    reason = (f"{chosen}: held-out RMS {s_c:.4g} px over {V} views in {k} folds"
              + ("" if chosen == best else
                 f", within one standard error of the best ({best}, {s_b:.4g} px)"))
    log.info("select_model: %s", reason)
    return {"model": chosen, "best": best, "folds": k, "scores": scores, "reason": reason}
