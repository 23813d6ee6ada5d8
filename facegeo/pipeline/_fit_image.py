"""The ``fit`` stage on a single-view scan without geometry: the image is the surface.

A photometric-stereo capture (Yale B, DiLiGenT: one camera, a light list, no structured light,
no mesh) has no atlas to project onto. Every pixel of the camera inside the mask is a texel;
:func:`facegeo.appearance.photometric.held_out_photometric` fits the per-pixel models on the
fitted lights (``hold_out``), predicts the held-out ones, and scores them beside the
Lambertian least squares on the same lights, pixels and samples. Products (``out/fit/``):

    photometric.npz      the fitted models (:func:`facegeo.appearance.photometric.load_photometric`)
                         + ``rows`` (pixel index r·W + c of each model row), ``image_size``,
                         ``light_names`` (the fitted lights), ``held_light_names``
    normal.exr/.png      normals, the lights' (world) frame, (n + 1)/2 in the PNG
    albedo.exr/.png      |b_c| of the chosen model (the frames' units per unit light intensity)
    specular.exr/.png    ρ_s of the lobe (0 without one); roughness.exr its Beckmann m (0: none)
    model.png            the model chosen per pixel: black none, grey Lambertian, blue + shadow
                         map, orange + lobe, red + lobe + shadow map
    fitted.png           255 where a pixel has a fit

Metrics: ``heldout_rel_mae``, ``heldout_rel_rmse`` and their ``…_lambertian`` baseline, the
``model_fraction_<model>`` shares, with reference normals (``[reference] normals``, camera
frame) ``normal_mean_error_deg`` / ``normal_median_error_deg`` and their ``…_lambertian``,
light and pixel counts, and the times of both fits.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError

log = logging.getLogger(__name__)

#: Default settings of the image-space ``fit`` stage (its cache key).
IMAGE_FIT_SETTINGS: dict[str, Any] = {
    "hold_out": "every_other", "light_cone_deg": None, "channels": "auto", "mask": "auto",
    "folds": 8, "eta": 1.4, "light_weights": "uniform", "light_gains": "auto", "models": "all",
    "criterion": "sse", "max_pixels": None,
}
#: Colours of ``model.png`` per model index (sRGB).
MODEL_COLOURS = np.array([[150, 150, 150], [60, 110, 230], [240, 150, 40], [220, 40, 40]],
                         np.uint8)


def image_space_scan(scan, mesh: str = "auto") -> bool:
    """Whether the fit stage works in image space on this scan: OLAT frames of one camera and
    no geometry to build an atlas on (no structured light, no ground-truth mesh, no mesh
    given)."""
    return (scan.has("olat") and len(scan.camera_names) == 1 and mesh == "auto"
            and not scan.has("structured_light") and "mesh" not in scan.ground_truth_keys)


def split_hold_out(hold_out, candidates: np.ndarray, names: list[str]):
    """The fitted and held-out light indices of a ``hold_out`` setting.

    ``"every_other"``: positions 0, 2, … of ``candidates`` fitted, the others held out
    (:func:`facegeo.appearance.lambertian.split_lights`); ``{"every": k, "offset": o}``: one in
    k fitted from position o; ``"none"``: every candidate fitted, none held out; a list of light
    names: those held out, the other candidates fitted.
    """
    from facegeo.appearance.lambertian import split_lights

    if hold_out == "none":
        return candidates, candidates[:0]
    if hold_out == "every_other":
        return split_lights(candidates)
    if isinstance(hold_out, dict):
        extra = set(hold_out) - {"every", "offset"}
        if extra:
            raise InputError(f"hold_out: unknown keys {sorted(extra)}; expected 'every' and "
                             "'offset'")
        return split_lights(candidates, every=hold_out.get("every", 2),
                            offset=hold_out.get("offset", 0))
    if isinstance(hold_out, (list, tuple)) and all(isinstance(n, str) for n in hold_out):
        where = {n: i for i, n in enumerate(names)}
        bad = [n for n in hold_out if n not in where]
        if bad:
            raise InputError(f"hold_out: no light named {bad[0]!r} in the rig (lights: "
                             f"{', '.join(names[:6])}{', …' if len(names) > 6 else ''})")
        held = np.array(sorted(where[n] for n in hold_out), np.int64)
        outside = np.setdiff1d(held, candidates)
        if outside.size:
            raise InputError(f"hold_out: light {names[int(outside[0])]!r} is outside the lights "
                             "the fit uses (light_cone_deg)")
        return np.setdiff1d(candidates, held), held
    raise InputError(f"hold_out: expected 'every_other', 'none', {{'every': k, 'offset': o}} or "
                     f"a list of light names, got {fmt_value(hold_out)}")


def _check(*, hold_out, light_cone_deg, channels, mask, folds, eta, light_weights, light_gains,
           models, criterion, max_pixels) -> None:
    from facegeo.appearance.photometric import CRITERIA, MODEL_NAMES

    if light_cone_deg is not None and not (isinstance(light_cone_deg, (int, float))
                                           and 0 < light_cone_deg <= 180):
        raise InputError(f"light_cone_deg: expected an angle in (0, 180] degrees or None, got "
                         f"{fmt_value(light_cone_deg)}")
    for key, val, choices in (("channels", channels, ("auto", "each", "grey")),
                              ("mask", mask, ("auto", "all", "reference")),
                              ("light_weights", light_weights, ("uniform", "cells")),
                              ("light_gains", light_gains, ("auto", "given", "fit")),
                              ("criterion", criterion, CRITERIA)):
        if val not in choices:
            raise InputError(f"{key}: expected one of {', '.join(choices)}, got {fmt_value(val)}")
    if max_pixels is not None and not (isinstance(max_pixels, int) and max_pixels > 0):
        raise InputError(f"max_pixels: expected a positive count or None, got "
                         f"{fmt_value(max_pixels)}")
    if models != "all" and (not isinstance(models, (list, tuple))
                            or any(m not in MODEL_NAMES for m in models)):
        raise InputError(f"models: expected 'all' or a list of {', '.join(MODEL_NAMES)}, got "
                         f"{fmt_value(models)}")


def _read_frames(scan, cam: str, lights: np.ndarray):
    """``(H·W, L, 3)`` float32 frames of ``lights``, their ``(H·W, L)`` validity (saturated
    samples untrusted, zeros measured dark), ambient subtracted when the scan has it."""
    ambient = scan.ambient_path(cam) is not None
    H, W = scan.rig.camera(cam).height, scan.rig.camera(cam).width
    R = np.empty((H * W, lights.size, 3), np.float32)
    V = np.empty((H * W, lights.size), bool)
    for j, (_, f, v) in enumerate(scan.iter_olat(cam, [int(x) for x in lights],
                                                 return_mask=True, subtract_ambient=ambient,
                                                 black_clipped="dark", read_ahead=2)):
        R[:, j] = f.reshape(-1, 3)
        V[:, j] = v.reshape(-1)
    return R, V, ambient


def _toward_camera(camera) -> np.ndarray:
    c = np.asarray(camera.center_world, np.float64)
    n = np.linalg.norm(c)
    if n == 0:
        raise InputError(f"camera {camera.name!r} sits at the world origin; the light cone "
                         "about it is undefined")
    return c / n


def fit_image_products(scan, dest, *, hold_out="every_other", light_cone_deg=None,
                       channels="auto", mask="auto", folds=8, eta=1.4,
                       light_weights="uniform", light_gains="auto", models="all",
                       criterion="sse", max_pixels=None, progress=None,
                       threads=None) -> tuple[dict, dict]:
    """Fit the per-pixel photometric models of a single-view scan in image space; write the
    products (module docstring) into ``dest``.

    Parameters
    ----------
    scan : Scan — one camera with OLAT frames under a light list or grid
    dest : path — the folder to write into (the stage cache's temporary folder)
    hold_out : "every_other" (default), "none", {"every": k, "offset": o} or a list of light
        names — which lights are held out of the fit and predicted (:func:`split_hold_out`)
    light_cone_deg : float, optional — only lights strictly within this angle of the camera's
        direction from the origin (fitted and held out); default every light
    channels : {"auto", "each", "grey"} — "auto": grey when every frame's channels are equal
    mask : {"auto", "all", "reference"} — the pixels fitted: "auto" is the scan's
        ``[reference] mask`` when it has one, else every pixel
    folds, eta, criterion — as :func:`facegeo.appearance.photometric.fit_photometric`
    light_weights : {"uniform", "cells"} — least-squares weight per light: 1, or the light
        list's Voronoi solid angle
    light_gains : {"auto", "given", "fit"} — the lights' intensities as the rig gives them, or
        each fitted light's gain fitted as well (``fit_photometric(light_gains="fit")``);
        "auto" fits them when every light of the rig has the same intensity (nominal: no
        photometric calibration, as Yale B's flashes), else takes them as given
    models : "all" or a list of model names
    max_pixels : int, optional — at most this many pixels of the mask, an even subsample
    progress : callable(stage, done, total), optional
    threads : int, optional — worker threads of the fit (not a setting: the results do not
        depend on it); default both cores when numba has them (``facegeo bench photometric``
        sets it to compare at equal threads)

    Returns
    -------
    (metrics, settings)
    """
    import numba

    from facegeo.appearance.lambertian import angular_error_deg, lights_within
    from facegeo.appearance.photometric import MODEL_NAMES, fit_photometric, held_out_photometric

    settings = {"hold_out": hold_out, "light_cone_deg": light_cone_deg, "channels": channels,
                "mask": mask, "folds": int(folds), "eta": float(eta),
                "light_weights": light_weights, "light_gains": light_gains, "models": models,
                "criterion": criterion, "max_pixels": max_pixels}
    _check(**settings)
    t_start = time.perf_counter()
    dest = Path(dest)
    cam = scan.camera_names[0]
    camera = scan.rig.camera(cam)
    lights = scan.rig.lights
    D_all = np.asarray(lights.directions, np.float64)
    names = list(getattr(lights, "names", None) or [str(i) for i in range(D_all.shape[0])])
    cand = (np.arange(D_all.shape[0]) if light_cone_deg is None
            else lights_within(D_all, _toward_camera(camera), float(light_cone_deg)))
    if cand.size < 4:
        raise InputError(f"light_cone_deg: {cand.size} lights lie within "
                         f"{fmt_value(light_cone_deg)}° of camera {cam!r}; the fit needs at "
                         "least 3 fitted lights and one to hold out")
    fit_l, held_l = split_hold_out(hold_out, cand, names)
    if fit_l.size < 3:
        raise InputError(f"hold_out: {fit_l.size} lights left to fit; at least 3 are needed")
    t0 = time.perf_counter()
    R, V, ambient = _read_frames(scan, cam, cand)
    t_read = time.perf_counter() - t0
    pos = {int(l): j for j, l in enumerate(cand)}
    fpos = np.array([pos[int(l)] for l in fit_l], np.int64)
    hpos = np.array([pos[int(l)] for l in held_l], np.int64)
    D = D_all[cand]
    E = None if getattr(lights, "intensities", None) is None else \
        np.asarray(lights.intensities, np.float64)[cand]
    ch = channels
    if ch == "auto":
        ch = "grey" if (np.array_equal(R[..., 0], R[..., 1])
                        and np.array_equal(R[..., 1], R[..., 2])) else "each"
    H, W = camera.height, camera.width
    rows = _mask(scan, mask, H, W)
    if max_pixels is not None and rows.sum() > max_pixels:
        from facegeo.render.novel import even_subset

        keep = np.flatnonzero(rows)[even_subset(int(rows.sum()), int(max_pixels))]
        rows = np.zeros_like(rows)
        rows[keep] = True
    view = -camera.pixel_rays()[1].reshape(-1, 3)
    ref = None
    if "normals" in scan.reference_keys:
        n_cam = np.load(scan.reference_path("normals")).reshape(-1, 3)
        ref = n_cam @ camera.T_cam_world.R  # camera frame -> world (the lights' frame)
    lw = None
    if light_weights == "cells":
        lw = np.asarray(lights.solid_angles, np.float64)[fit_l]
    gains = light_gains
    if gains == "auto":
        I = np.asarray(lights.intensities if getattr(lights, "intensities", None) is not None
                       else np.ones((D_all.shape[0], 3)), np.float64)
        gains = "fit" if np.ptp(I, axis=0).max() == 0 else "given"
    threads = (max(1, min(2, int(numba.config.NUMBA_NUM_THREADS))) if threads is None
               else max(1, int(threads)))
    kw = {"folds": int(folds), "eta": float(eta), "criterion": criterion, "threads": threads,
          "light_weights": lw, "light_gains": "fit" if gains == "fit" else None}
    if models != "all":
        kw["models"] = list(models)
    metrics: dict[str, Any] = {"space": "image", "camera": cam, "channels": ch,
                               "light_gains": gains,
                               "ambient_subtracted": bool(ambient),
                               "lights": int(cand.size), "lights_fitted": int(fit_l.size),
                               "lights_held_out": int(held_l.size),
                               "pixels": int(rows.sum()), "seconds_read": round(t_read, 4)}
    if progress:
        progress("fit", 0, int(rows.sum()))
    if held_l.size:
        score = held_out_photometric(R[:, np.r_[fpos, hpos]], D[np.r_[fpos, hpos]], view=view,
                                     fit=np.arange(fpos.size),
                                     held=np.arange(fpos.size, fpos.size + hpos.size),
                                     intensities=None if E is None else E[np.r_[fpos, hpos]],
                                     mask=rows, normal_ref=ref, channels=ch,
                                     valid=V[:, np.r_[fpos, hpos]], **kw)
        model = score.fit
        lam = score.lambertian
        metrics.update({
            "heldout_rel_mae": _r(score.rel_mae), "heldout_rel_rmse": _r(score.rel_rmse),
            "heldout_rel_mae_lambertian": _r(lam.rel_mae),
            "heldout_rel_rmse_lambertian": _r(lam.rel_rmse),
            "heldout_samples": score.samples, "heldout_untrusted": score.untrusted,
            "seconds_fit": round(score.seconds, 4),
            "seconds_lambertian": round(lam.seconds, 4)})
        if ref is not None:
            metrics.update({
                "normal_mean_error_deg": _r(score.normal_mean_error_deg, 4),
                "normal_median_error_deg": _r(score.normal_median_error_deg, 4),
                "normal_mean_error_deg_lambertian": _r(lam.normal_mean_error_deg, 4),
                "normal_median_error_deg_lambertian": _r(lam.normal_median_error_deg, 4),
                "normals_compared": score.normals_compared})
    else:
        t1 = time.perf_counter()
        model = fit_photometric(R[:, fpos], D[fpos], view=view,
                                intensities=None if E is None else E[fpos], channels=ch,
                                valid=V[:, fpos], rows=rows, **kw)
        metrics["seconds_fit"] = round(time.perf_counter() - t1, 4)
        if ref is not None:
            err = angular_error_deg(model.normal[rows], ref[rows])
            err = err[np.isfinite(err)]
            if err.size:
                metrics["normal_mean_error_deg"] = _r(float(err.mean()), 4)
                metrics["normal_median_error_deg"] = _r(float(np.median(err)), 4)
    fitted = rows & model.valid
    metrics["pixels_fitted"] = int(fitted.sum())
    if gains == "fit":
        metrics["light_gain_range"] = [round(float(model.light_gains.min()), 4),
                                       round(float(model.light_gains.max()), 4)]
    for name, share in model.model_fractions(rows).items():
        metrics[f"model_fraction_{name.replace('+', '_')}"] = share
    files = _write_products(dest, model, rows, fitted, H, W, [names[i] for i in fit_l],
                            [names[i] for i in held_l])
    metrics["files"] = files
    metrics["models"] = list(MODEL_NAMES)
    metrics["seconds"] = round(time.perf_counter() - t_start, 4)
    if progress:
        progress("fit", int(rows.sum()), int(rows.sum()))
    return metrics, settings


def _r(x, digits: int = 6):
    return None if x is None or not np.isfinite(x) else round(float(x), digits)


def _mask(scan, mask: str, H: int, W: int) -> np.ndarray:
    """``(H·W,)`` bool: the pixels to fit."""
    from facegeo.capture.imageio import read_image

    has = "mask" in scan.reference_keys
    if mask == "reference" and not has:
        raise InputError(f"mask 'reference': scan {scan.root} has no [reference] mask")
    if mask == "all" or not has:
        return np.ones(H * W, bool)
    path = scan.reference_path("mask")
    m = np.asarray(read_image(path))
    m = (m > 0).any(axis=-1) if m.ndim == 3 else m > 0
    if m.shape != (H, W):
        raise InputError(f"{path}: mask is {m.shape[1]}×{m.shape[0]} px but camera is {W}×{H}")
    return m.reshape(-1)


def _write_products(dest: Path, model, rows, fitted, H: int, W: int, fit_names, held_names):
    from facegeo.capture import imageio
    from facegeo.capture.response import encode

    model.subset(rows).save(dest / "photometric.npz", rows=np.flatnonzero(rows),
                            image_size=np.array([W, H]), light_names=np.array(fit_names),
                            held_light_names=np.array(held_names, dtype=str))

    def image(values, fill=0.0):
        a = np.asarray(values, np.float32)
        img = np.full((H * W,) + a.shape[1:], fill, np.float32)
        img[fitted] = a[fitted]
        return img.reshape((H, W) + a.shape[1:])

    files = {}
    n = image(np.nan_to_num(model.normal))
    files["normal"] = imageio.write_image(dest / "normal.exr", n).name
    imageio.write_image(dest / "normal.png", np.where(
        fitted.reshape(H, W)[..., None], np.clip((n + 1.0) * 127.5 + 0.5, 0, 255),
        0).astype(np.uint8))
    alb = model.albedo
    alb = np.repeat(alb, 3, axis=1) if alb.shape[1] == 1 else alb
    a = image(np.nan_to_num(alb))
    files["albedo"] = imageio.write_image(dest / "albedo.exr", a).name
    top = float(np.percentile(a[fitted.reshape(H, W)], 99)) if fitted.any() else 1.0
    imageio.write_image(dest / "albedo.png",
                        encode(np.clip(a / max(top, 1e-12), 0, 1), "srgb", np.uint8))
    rho = np.where(model.uses_lobe, model.rho_s, 0.0)
    s = image(rho)
    files["specular"] = imageio.write_image(dest / "specular.exr", s).name
    top = float(np.percentile(s[s > 0], 99)) if (s > 0).any() else 1.0
    imageio.write_image(dest / "specular.png",
                        encode(np.clip(s / max(top, 1e-12), 0, 1), "srgb", np.uint8))
    files["roughness"] = imageio.write_image(
        dest / "roughness.exr", image(np.where(model.uses_lobe, np.nan_to_num(model.roughness),
                                               0.0))).name
    choice = np.zeros((H * W, 3), np.uint8)
    ok = fitted & (model.model >= 0)
    choice[ok] = MODEL_COLOURS[model.model[ok]]
    files["model"] = imageio.write_image(dest / "model.png", choice.reshape(H, W, 3)).name
    files["fitted"] = imageio.write_image(
        dest / "fitted.png", (fitted.reshape(H, W) * 255).astype(np.uint8)).name
    files["photometric"] = "photometric.npz"
    return files
