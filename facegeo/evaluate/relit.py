"""Relit camera views against the generator's render under the same weights (synthetic scans).

Reads the camera views ``facegeo relight SCAN --view CAMERA`` wrote (``out/relit/<stem>.json``
with its ``.exr``; the ``relight`` stage of ``reconstruct`` relights the texture atlas, which
has no reference image): the environment, its projection, rotation and δA rule give back the
Eq. (4) weights the stage used, and the generator renders the camera under them
(:meth:`facegeo.synth.render.ReferenceRenderer.render_lights`). Figures per view:
``relative_rmse`` = ‖img − ref‖ / ‖ref‖ and ``max_abs_over_max`` = max |img − ref| / max ref
over the pixels where both are finite — the ``reference`` figures the stage reports today.

The comparison itself is still ``facegeo.pipeline.relight._reference_error`` (called here from
the products, not copied); it moves here when that stage module drops it (issue 37).
"""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["evaluate_relit"]


def evaluate_relit(scan, out) -> dict:
    """Every camera view in ``out/relit/`` against the generator's render (module docstring);
    ``{}`` when there is none or the scan has no generator truth."""
    from facegeo.capture import imageio
    from facegeo.lighting import envmap as E
    from facegeo.pipeline.relight import _reference_error, resolve_env

    folder = Path(out) / "relit"
    if not (folder.is_dir() and scan.synthetic and {"skin", "mesh"} <= set(
            scan.ground_truth_keys)):
        return {}
    views = {}
    for doc_path in sorted(folder.glob("*.json")):
        try:
            m = json.loads(doc_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if not isinstance(m, dict) or m.get("view") not in scan.camera_names:
            continue  # the texture view has no reference image; foreign files are not views
        exr = Path(m["files"]["exr"])
        exr = exr if exr.is_file() else folder / exr.name
        env_map = resolve_env(m["env"], m.get("projection", "latlong"),
                              rotate_deg=float(m.get("rotate_deg", 0.0)))
        w = E.light_weights(env_map, scan.rig.lights, solid_angle=m.get("solid_angle", "paper"))
        views[doc_path.stem] = _reference_error(scan, m["view"], w, imageio.read_image(exr))
    return {"views": views} if views else {}
