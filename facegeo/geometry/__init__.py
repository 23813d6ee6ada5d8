"""Geometry: cameras and rigs (:mod:`.camera`, :mod:`.rig`), calibration boards (:mod:`.board`)
and structured-light patterns and decoding (:mod:`.structured_light`).

Geometry stages take arrays, never scans: :mod:`facegeo.capture` reads frames and hands them in.
"""
