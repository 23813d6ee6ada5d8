"""Synthetic light-stage capture: procedural or real heads, solid-texture skin, a reference
renderer, and a writer that produces scans in exactly the format a real rig writes.

Public entry points (imported lazily so ``import facegeo.synth`` stays cheap):

* :func:`facegeo.synth.capture.generate_scan` — write a scan directory (``facegeo synth``).
* :data:`facegeo.synth.capture.PRESETS` — ``tiny``, ``small``, ``paper``, and the 16-camera
  ``modern`` and ``modern_tiny`` (issue 38).
* :mod:`facegeo.synth.rigs` — the rigs a scan is built with: a multi-camera band, the true
  rig's seeded errors (and the lights' calibration error), the calibration-only witness camera.
* :class:`facegeo.synth.render.ReferenceRenderer` — exact images from any camera under any
  weighted set of lights (ground truth for novel views and relighting).
"""

from __future__ import annotations

__all__ = ["generate_scan", "PRESETS", "ReferenceRenderer"]


def __getattr__(name):
    if name in ("generate_scan", "PRESETS"):
        from facegeo.synth import capture

        return getattr(capture, name)
    if name == "ReferenceRenderer":
        from facegeo.synth.render import ReferenceRenderer

        return ReferenceRenderer
    raise AttributeError(name)
