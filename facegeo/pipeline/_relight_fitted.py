"""``facegeo relight --model fitted``: a camera image under an environment predicted by an
image-space fit's per-pixel models (Debevec et al. 2000 Eq. 4 with fitted reflectance
functions), split out of :mod:`facegeo.pipeline.relight`, which re-exports
:func:`relight_fitted` and writes its products (``_relight_fitted_products``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError

#: ``model="fitted"``: the environment is sampled on this (n_θ, n_φ) grid of directions (exact
#: cell solid angles, every direction of the sphere) and the fitted model evaluated at each.
FITTED_GRID = (64, 32)


def _fitted_model_path(scan, view: str, fit_dir) -> Path:
    """``fit_dir/photometric.npz`` of an image-space fit of ``view``, or a clear error."""
    if view == "texture" or view not in scan.camera_names:
        raise InputError(f"view: --model fitted relights a camera of a single-view scan fitted "
                         f"in image space; got {fmt_value(view)} (cameras: "
                         f"{', '.join(scan.camera_names)})")
    path = (Path(fit_dir) if fit_dir is not None else scan.out_dir / "fit") / "photometric.npz"
    if not path.is_file():
        raise InputError(f"{path} is missing: --model fitted needs the image-space fit of a "
                         f"single-view scan; run 'facegeo fit {scan.root}' first (a scan with a "
                         "mesh is fitted per texel: relight it with --model measured or render "
                         "it with 'facegeo render')")
    return path


def relight_fitted(path, env_map, *, grid=FITTED_GRID) -> tuple[np.ndarray, np.ndarray]:
    """The camera image under an environment predicted by an image-space fit's models.

    Eq. 4 of Debevec et al. 2000 with the fitted per-pixel models in place of measured
    reflectance functions: ``Σ_k L̄_k δA_k ⊙ f(ω_k)``, ω_k every cell centre of a
    ``grid = (n_θ, n_φ)`` lat-long grid over the sphere (exact cell solid angles, so
    ``Σ w = ∫ L``), f the pixel's model evaluated at ω_k
    (:func:`facegeo.appearance.photometric.predict_environment`: Lambertian, shadow map, and
    the Torrance–Sparrow lobe from its fitted parameters). A grey fit is relit channel by
    channel (its albedo times each channel's light).

    Parameters
    ----------
    path : path — ``photometric.npz`` with ``rows`` and ``image_size`` (the fit stage's)
    env_map : EnvironmentMap
    grid : (int, int)

    Returns
    -------
    image : (H, W, 3) float32 — 0 where no pixel was fitted
    weights : (n_θ n_φ, 3) float64 — the Eq. 4 weights used (δA included)
    """
    from facegeo.appearance.photometric import load_photometric, predict_environment
    from facegeo.appearance.skin import LightSet
    from facegeo.lighting import envmap as E

    model = load_photometric(path)
    with np.load(path) as z:
        if "rows" not in z.files or "image_size" not in z.files:
            raise InputError(f"{path}: no 'rows' / 'image_size' arrays (not written by the fit "
                             "stage; re-run 'facegeo fit')")
        rows = z["rows"].astype(np.int64)
        W, H = (int(x) for x in z["image_size"])
    nt, npf = (int(g) for g in grid)
    w = E.light_stage_weights(env_map, nt, npf, solid_angle="exact")
    dirs = LightSet.from_grid(nt, npf).directions
    lit = np.any(w != 0, axis=1)
    if model.b_lambert.shape[1] == 3:
        vals = predict_environment(model, dirs[lit], w[lit])
    else:
        vals = np.concatenate([predict_environment(model, dirs[lit], w[lit, c])
                               for c in range(3)], axis=1)
    img = np.zeros((H * W, 3), np.float32)
    img[rows] = np.nan_to_num(vals, nan=0.0)
    return img.reshape(H, W, 3), w
