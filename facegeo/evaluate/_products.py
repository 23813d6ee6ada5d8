"""Reading what a stage wrote in ``out/<stage>/``: its manifest, its settings, its rig.

The evaluation reads products, never a stage's memory: everything it compares is a file a
stage wrote (docs/evaluate.md lists which).
"""

from __future__ import annotations

import json
from pathlib import Path

from facegeo.errors import InputError

__all__ = ["has_stage", "stage_manifest", "stage_rig_product"]


def has_stage(out: Path, stage: str) -> bool:
    """Whether ``out/<stage>/`` holds a finished stage (its ``stage.json``)."""
    return (Path(out) / stage / "stage.json").is_file()


def stage_manifest(out: Path, stage: str) -> dict:
    """``out/<stage>/stage.json`` as a dict (``settings``, ``metrics``, …).

    Raises
    ------
    InputError
        The folder has no manifest (the stage did not run or did not finish) or it does not
        read as a JSON object; the message names the file and the command that writes it.
    """
    path = Path(out) / stage / "stage.json"
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"evaluate: {path} is missing; run 'facegeo reconstruct SCAN' (or "
                         f"'facegeo {stage} SCAN') first") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"evaluate: cannot read {path} ({exc}); rerun the {stage!r} stage") \
            from None
    if not isinstance(doc, dict):
        raise InputError(f"evaluate: {path} is not a JSON object; rerun the {stage!r} stage")
    return doc


def stage_rig_product(out: Path, stage: str):
    """The rig a stage worked with, as it wrote it (``out/<stage>/rig.json``), and its name
    (``settings["rig"]``: ``"ground_truth"``, ``"scan"``, ``"calibrated"`` or a file).

    Raises
    ------
    InputError
        No ``rig.json`` in the stage's folder (products written before the stages recorded
        their rig): rerun the stage.
    """
    from facegeo.geometry.rig import Rig

    path = Path(out) / stage / "rig.json"
    if not path.is_file():
        raise InputError(f"evaluate: {path} is missing (the {stage!r} products predate the "
                         f"rig they record); rerun 'facegeo {stage} SCAN' or 'facegeo "
                         f"reconstruct SCAN'")
    used = stage_manifest(out, stage).get("settings", {}).get("rig")
    return Rig.load(path), str(used)
