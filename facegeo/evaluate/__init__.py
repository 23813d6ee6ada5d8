"""Comparisons of stage products with references of any origin (docs/evaluate.md).

The stages make products and never read the truth; this part reads their products (the files
in ``out/<stage>/``) and compares them with what the scan holds as references: the generator's
ground truth (``ground_truth/``), a scanner's reference cloud or mesh, published intrinsics, a
reference normal map, reference images of a camera. One module per kind of reference:

* :mod:`facegeo.evaluate.intrinsics` — a calibrated rig against reference cameras;
* :mod:`facegeo.evaluate.cloud` — a mesh against a reference point cloud or mesh;
* :mod:`facegeo.evaluate.projection` — projected fields against the generator's shading;
* :mod:`facegeo.evaluate.normals` — fitted normals against a reference normal map;
* :mod:`facegeo.evaluate.skin_fit` — the skin-model fits against the generator's skin;
* :mod:`facegeo.evaluate.views` — rendered views against reference images of their camera;
* :mod:`facegeo.evaluate.relit` — relit camera views against the generator's render;
* :mod:`facegeo.evaluate.gauge` — the rigid gauge alignment and texel areas they share;
* :mod:`facegeo.evaluate.evaluation` — all of them over a scan (``facegeo evaluate``).
"""

from __future__ import annotations

from facegeo.evaluate.evaluation import (
    EVALUATE_SETTINGS,
    evaluate_products,
    evaluation_inputs,
    run_evaluate,
    summary_rows,
)

__all__ = ["EVALUATE_SETTINGS", "evaluate_products", "evaluation_inputs", "run_evaluate",
           "summary_rows"]
