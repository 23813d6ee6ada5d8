"""Relit camera views against the generator's render under the same weights (synthetic scans).

Reads the camera views ``facegeo relight SCAN --view CAMERA`` wrote (``out/relit/<stem>.json``
with its ``.exr``; the ``relight`` stage of ``reconstruct`` relights the texture atlas, which
has no reference image): the environment, its projection, rotation and δA rule give back the
Eq. (4) weights the stage used, and the generator renders the camera under them
(:meth:`facegeo.synth.render.ReferenceRenderer.render_lights`). Figures per view
(:func:`relit_error`): ``relative_rmse`` = ‖img − ref‖ / ‖ref‖ and ``max_abs_over_max`` =
max |img − ref| / max ref over the pixels where both are finite — the ``reference`` figures the
relight stage reported until issue 37 moved the comparison here (equal on the tiny scan).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["evaluate_relit", "relit_error"]


def relit_error(scan, view: str, w: np.ndarray, img: np.ndarray, *, renderer=None) -> dict:
    """A relit camera image against the generator's render under the same Eq. (4) weights.

    The relight stage normalises the frames by the light colour (``normalize_color=True``);
    the generator's OLAT shading includes it, so the reference is ``render_lights(w / colour)``
    (:func:`facegeo.lighting.envmap.field_weights`). Figures over pixels where both are finite:
    ``relative_rmse`` ‖img − ref‖ / ‖ref‖ and ``max_abs_over_max`` max |img − ref| / max ref,
    with ``pixels`` compared and ``computed``; ``{"computed": False, "reason": …}`` without the
    generator's truth or without a finite pixel.

    Parameters
    ----------
    scan : facegeo.capture.scan.Scan
    view : str — the camera relit
    w : (L, 3) float — the Eq. (4) weights the image was relit with
    img : (H, W, 3) float — the relit image
    renderer : ReferenceRenderer, optional — the generator's (loaded when not given)
    """
    if not (scan.synthetic and "skin" in scan.ground_truth_keys
            and "mesh" in scan.ground_truth_keys):
        return {"computed": False, "reason": "no generator ground truth in this scan"}
    from facegeo.lighting.envmap import field_weights

    if renderer is None:
        from facegeo.synth.render import load_ground_truth

        renderer = load_ground_truth(scan)
    wn = field_weights(w, scan.rig.lights)
    ref = renderer.render_lights(renderer.rig.camera(view), scan.rig.lights,
                                 wn).astype(np.float64)
    got = np.asarray(img, np.float64)
    ok = np.isfinite(got).all(axis=-1) & np.isfinite(ref).all(axis=-1)
    if not ok.any():
        return {"computed": False, "reason": "no finite pixels to compare"}
    d = got[ok] - ref[ok]
    return {"computed": True, "pixels": int(ok.sum()),
            "relative_rmse": float(np.linalg.norm(d) / max(np.linalg.norm(ref[ok]), 1e-300)),
            "max_abs_over_max": float(np.abs(d).max() / max(np.abs(ref[ok]).max(), 1e-300))}


def evaluate_relit(scan, out) -> dict:
    """Every camera view in ``out/relit/`` against the generator's render (module docstring);
    ``{}`` when there is none or the scan has no generator truth."""
    from facegeo.capture import imageio
    from facegeo.lighting import envmap as E
    from facegeo.pipeline.relight import resolve_env

    folder = Path(out) / "relit"
    if not (folder.is_dir() and scan.synthetic and {"skin", "mesh"} <= set(
            scan.ground_truth_keys)):
        return {}
    views = {}
    renderer = None
    for doc_path in sorted(folder.glob("*.json")):
        try:
            m = json.loads(doc_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if not isinstance(m, dict) or m.get("view") not in scan.camera_names \
                or m.get("model", "measured") != "measured":
            continue  # the texture view and a fitted model's have no reference; nor foreign files
        exr = Path(m["files"]["exr"])
        exr = exr if exr.is_file() else folder / exr.name
        env_map = resolve_env(m["env"], m.get("projection", "latlong"),
                              rotate_deg=float(m.get("rotate_deg", 0.0)),
                              convention=m.get("envmap_convention", "facegeo"))
        w = E.light_weights(env_map, scan.rig.lights, solid_angle=m.get("solid_angle", "paper"))
        if renderer is None:
            from facegeo.synth.render import load_ground_truth

            renderer = load_ground_truth(scan)
        views[doc_path.stem] = relit_error(scan, m["view"], w, imageio.read_image(exr),
                                           renderer=renderer)
    return {"views": views} if views else {}
