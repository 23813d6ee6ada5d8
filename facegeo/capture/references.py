"""Reference answers of a real scan (``[reference]`` in ``scan.toml``), read for the metrics.

Real data sets publish some answers — intrinsics from the authors' own calibration, a scanned
point cloud — that a stage's products can be compared with, as synthetic scans are compared
with their ``ground_truth/``. This module reads them into arrays for
:mod:`facegeo.evaluate` (:mod:`facegeo.evaluate.intrinsics`; ``pipeline/calibrate.py`` still
reads them too until its comparison moves there, issue 37).

Reference intrinsics (``[reference] intrinsics = "reference/intrinsics.json"``), JSON, one of:

* ``{"cameras": {NAME: {"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "dist": [...]}, ...}}``
  (what ``facegeo import --dataset`` writes; extra top-level keys are kept for people);
* ``{NAME: {"K": ...}, ...}``;
* ``{NAME: {"fx": ..., "fy": ..., "cx": ..., "cy": ...}, ...}``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from facegeo.errors import ScanFormatError

__all__ = ["read_reference_intrinsics", "reference_intrinsics"]


def _camera_K(name: str, entry, path: Path) -> np.ndarray:
    if isinstance(entry, dict) and "K" in entry:
        K = np.asarray(entry["K"], dtype=np.float64)
    elif isinstance(entry, dict) and {"fx", "fy", "cx", "cy"} <= set(entry):
        K = np.array([[entry["fx"], 0.0, entry["cx"]], [0.0, entry["fy"], entry["cy"]],
                      [0.0, 0.0, 1.0]], dtype=np.float64)
    else:
        raise ScanFormatError(f"camera {name!r}: expected {{'K': 3x3}} or fx, fy, cx, cy",
                              path=path, key="reference.intrinsics")
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ScanFormatError(f"camera {name!r}: K must be a finite 3x3 matrix with fx, fy > 0",
                              path=path, key="reference.intrinsics")
    return K


def read_reference_intrinsics(path) -> dict[str, np.ndarray]:
    """``{camera name: K (3, 3) float64}`` from a reference intrinsics file (module docstring).

    Raises
    ------
    ScanFormatError
        Unreadable or invalid JSON, or an entry that is not a camera matrix (naming the file).
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise ScanFormatError(f"cannot read reference intrinsics ({e})", path=path,
                              key="reference.intrinsics") from None
    if not isinstance(doc, dict):
        raise ScanFormatError("expected a JSON object of cameras", path=path,
                              key="reference.intrinsics")
    cams = doc["cameras"] if isinstance(doc.get("cameras"), dict) else {
        k: v for k, v in doc.items() if isinstance(v, dict)}
    return {name: _camera_K(name, entry, path) for name, entry in cams.items()}


def reference_intrinsics(scan) -> dict[str, np.ndarray]:
    """The scan's reference intrinsics (``{}`` when it has none)."""
    if "intrinsics" not in scan.reference_keys:
        return {}
    return read_reference_intrinsics(scan.reference_path("intrinsics"))
