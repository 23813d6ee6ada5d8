"""Capture: the scan directory on disk — manifest, schema and file lists (:mod:`.scan`), image
I/O (:mod:`.imageio`) and camera response curves (:mod:`.response`).

Only this part (with :mod:`facegeo.pipeline` and the CLI) touches the file-system layout of a
scan; the stages below it take arrays.
"""
