"""Where a stage's surface meets the generator's: the rigid gauge alignment and texel areas.

A calibrated rig's world frame is its own gauge choice: before a product in that frame is
compared with the generator's truth, the atlas mesh is brought onto the true surface by the
best rigid transform (:func:`truth_gauge`), fitted on the measured surface only: vertices the
mesh stage inferred (hole filling, :func:`inferred_atlas_vertices`) are skipped.
:func:`texel_areas` weights per-texel statistics by the surface each texel stands for, so a
figure is a mean over the surface, not over however the atlas samples it.
:func:`chain_views_in_truth` gives the chain's rendered views' cameras in the generator's
frame: the cameras its references are rendered from, and the views the stage-alone pass
(``out/diagnostic/``) renders.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["chain_views_in_truth", "inferred_atlas_vertices", "texel_areas",
           "truth_gauge"]

#: truth_gauge's alignments of this process, by the meshes' contents (a few at most).
_GAUGES: dict[str, Any] = {}
#: truth_gauge aligns on every vertex when fewer measured ones than this remain.
GAUGE_MIN_VERTICES = 100


def inferred_atlas_vertices(out, atlas) -> np.ndarray | None:
    """``(V',)`` bool: the atlas vertices that lie only on faces the mesh stage marked as
    inferred — surface it filled where no camera measured (``<stem>_inferred.npy`` beside the
    atlas's input mesh, named by :func:`facegeo.geometry.mesh.inferred_faces_path`, read
    through ``atlas.face_map``). A vertex shared with a measured face is measured. None when
    the atlas's mesh has no such flags (the generator's mesh, the trimmed surface, an atlas
    written before the atlas stage recorded its mesh).

    Parameters
    ----------
    out : path-like
        The products folder holding ``atlas/stage.json`` (whose ``metrics.mesh`` names the mesh
        file; a moved products folder is looked up under ``out/mesh/`` by its name).
    atlas : facegeo.surface.atlas.Atlas

    Raises
    ------
    InputError
        The flags are not one boolean per face of the mesh the atlas was cut from.
    """
    from pathlib import Path

    from facegeo.errors import InputError
    from facegeo.evaluate._products import has_stage, stage_manifest
    from facegeo.geometry.mesh import inferred_faces_path

    out = Path(out)
    if not has_stage(out, "atlas"):
        return None
    mesh = stage_manifest(out, "atlas").get("metrics", {}).get("mesh")
    if not isinstance(mesh, str) or mesh == "ground_truth":
        return None
    path = inferred_faces_path(mesh)
    if not path.is_file():
        path = inferred_faces_path(out / "mesh" / Path(mesh).name)
        if not path.is_file():
            return None
    flags = np.load(path)
    face_map = np.asarray(atlas.face_map, np.int64)
    if flags.dtype != bool or flags.ndim != 1 or (face_map.size and
                                                   int(face_map.max()) >= flags.size):
        raise InputError(f"{path}: expected one bool per face of {mesh} (the atlas uses faces "
                         f"up to {int(face_map.max()) if face_map.size else -1}), got "
                         f"{flags.shape} {flags.dtype}; rerun the mesh and atlas stages")
    measured = np.zeros(len(atlas.vertices), bool)
    measured[atlas.faces[~flags[face_map]].ravel()] = True
    return ~measured


def truth_gauge(renderer, atlas, rig_used: str, *, skip=None) -> tuple[Any, dict]:
    """Where a stage's texels meet the generator's truth: ``(T_true_world, metrics)``.

    With the true rig (``rig_used == "ground_truth"``) the stage's world frame is the
    generator's: ``(None, {})``. With any other rig (a calibration's, the nominal
    ``rig.json``, a rig file) the world frame is that rig's gauge choice, so the atlas mesh is
    first brought onto the true surface by the best rigid transform
    (:meth:`facegeo.synth.render.ReferenceRenderer.gauge_alignment`, geometry only) — the
    ``mesh`` stage's ``after_rigid_alignment`` figures do the same — and the metrics say how
    far that was (``gauge_rotation_deg``, ``gauge_translation_mm``). Shared by the
    projection's, the fit's and the views' comparisons with the generator. Without it a
    calibrated rig's 0.2° / 3.5 mm frame offset (small preset, seed 0) read as a
    ``projection_rel_rmse`` of 12.0 % where the aligned figure is 3.0 % (true rig: 3.1 %; both
    plain bilinear, before the shadow-consistent taps).
    The alignment (≈ 1.6 s on the small preset's reconstruction) is kept for the process,
    keyed by the two meshes' contents and ``skip``, so the comparisons of one run compute it
    once.

    The alignment is fitted on the measured surface only: the vertices ``skip`` marks (the
    surface the mesh stage inferred, :func:`inferred_atlas_vertices`) are left out, since a
    hole filling that bulges or sags would otherwise pull the frame toward its own error; the
    metrics say how many (``gauge_inferred_vertices_skipped``, with ``skip`` given). With
    fewer than :data:`GAUGE_MIN_VERTICES` measured vertices every vertex is used.

    Parameters
    ----------
    renderer : facegeo.synth.render.ReferenceRenderer
        The generator's truth (its mesh, rig and materials).
    atlas : facegeo.surface.atlas.Atlas
        The stage's atlas (vertices in metres, the stage's world frame).
    rig_used : str
        The rig the stage used (``"ground_truth"``, ``"scan"``, ``"calibrated"`` or a file).
    skip : (V',) bool, optional
        Atlas vertices left out of the alignment (:func:`inferred_atlas_vertices`).
    """
    if rig_used == "ground_truth":
        return None, {}
    import hashlib

    from facegeo.errors import InputError

    vertices = np.asarray(atlas.vertices, np.float64)
    extra: dict[str, int] = {}
    if skip is not None:
        skip = np.asarray(skip)
        if skip.shape != (len(vertices),) or skip.dtype != bool:
            raise InputError(f"skip: expected ({len(vertices)},) bool, one flag per atlas "
                             f"vertex, got {skip.shape} {skip.dtype}")
        if int((~skip).sum()) < GAUGE_MIN_VERTICES:
            skip = np.zeros(len(vertices), bool)
        extra["gauge_inferred_vertices_skipped"] = int(skip.sum())
        vertices = vertices[~skip]
    key = hashlib.sha1(b"".join(np.ascontiguousarray(a).tobytes() for a in (
        vertices, atlas.faces, renderer.vertices, renderer.faces))).hexdigest()
    T = _GAUGES.get(key)
    if T is None:
        T = renderer.gauge_alignment(vertices)
        if len(_GAUGES) >= 8:
            _GAUGES.pop(next(iter(_GAUGES)))
        _GAUGES[key] = T
    return T, {"gauge_rotation_deg": round(float(np.degrees(np.linalg.norm(T.rvec))), 6),
               "gauge_translation_mm": round(float(np.linalg.norm(T.t)) * 1e3, 4), **extra}


def texel_areas(atlas, texels) -> np.ndarray:
    """Surface area each texel stands for, ``(T,)`` float64, m².

    A texel is one unit square of the atlas; the affine UV map of its face scales area by
    ``area_3d / area_uv`` (``area_uv`` in texel units), so a texel on a stretched chart stands
    for more surface. Weighting a per-texel statistic by this makes it a mean over the surface,
    independent of how the atlas samples it (docs/surface.md, "Atlas").

    Parameters
    ----------
    atlas : facegeo.surface.atlas.Atlas
    texels : facegeo.surface.atlas.Texels
        The texel table of ``atlas``.

    Returns
    -------
    (T,) float64, m²
        Summed over the texels it gives the charted surface's area up to the chart-boundary
        texels (a texel whose face has no UV area — none by construction — gets 0).
    """
    tri = atlas.vertices[atlas.faces]
    a3 = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    uv = atlas.uv[atlas.faces] * np.array([atlas.width, atlas.height], float)
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    auv = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        per_face = np.where(auv > 0, a3 / auv, 0.0)
    return per_face[texels.face]


def chain_views_in_truth(scan, out) -> list[dict] | None:
    """The cameras of the views the ``render`` stage rendered into ``out/render/``, moved into
    the generator's world frame: the cameras the evaluation renders their references from
    (:func:`facegeo.evaluate.views.evaluate_view`: the same :func:`truth_gauge` of the stage's
    atlas; unmoved when the stage used the true rig).

    The stage-alone pass (:func:`facegeo.pipeline.reconstruct.run_diagnostic`) renders these
    views with the true rig and mesh, so both passes are compared with the very same reference
    images (rendered once: :data:`facegeo.evaluate.evaluation.REFERENCE_CACHE`), and the
    figures side by side differ only by what the chain's calibration and mesh did.

    Parameters
    ----------
    scan : facegeo.capture.scan.Scan
        A synthetic scan (the generator's truth).
    out : path-like
        The chain's products folder (``SCAN/out``).

    Returns
    -------
    list of dict or None
        Camera dicts (:meth:`facegeo.geometry.camera.Camera.to_dict`, named as the stage named
        them), in the stage's view order; None when ``out`` holds no finished render stage.
    """
    import dataclasses
    import json
    from pathlib import Path

    from facegeo.evaluate._products import has_stage, stage_manifest
    from facegeo.geometry.camera import Camera
    from facegeo.surface.atlas import Atlas
    from facegeo.synth.render import load_ground_truth

    out = Path(out)
    if not (has_stage(out, "render") and has_stage(out, "atlas")):
        return None
    views = stage_manifest(out, "render").get("metrics", {}).get("views") or {}
    cams: list[dict] = []
    renderer = atlas = None
    for stem in views:
        cam_path = out / "render" / f"{stem}_camera.json"
        meta_path = out / "render" / f"{stem}.json"
        if not (cam_path.is_file() and meta_path.is_file()):
            return None
        camera = Camera.from_dict(json.loads(cam_path.read_text(encoding="utf-8")),
                                  where=str(cam_path))
        rig_used = json.loads(meta_path.read_text(encoding="utf-8")).get("rig")
        if rig_used != "ground_truth":
            if renderer is None:
                renderer = load_ground_truth(scan)
                atlas = Atlas.load(out / "atlas" / "atlas.npz")
            T_true, _ = truth_gauge(renderer, atlas, rig_used,
                                    skip=inferred_atlas_vertices(out, atlas))
            camera = dataclasses.replace(camera, T_cam_world=camera.T_cam_world @ T_true.inverse())
        cams.append(camera.to_dict())
    return cams or None
