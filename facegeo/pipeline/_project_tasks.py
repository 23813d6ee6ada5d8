"""The ``project`` stage's inputs and per-camera steps, split out of
:mod:`facegeo.pipeline.project`, which re-exports every name (``load_mesh``,
``load_inferred_faces``, ``INFERRED_TEXELS``, ``stage_rig``, ``STAGE_RIGS``,
``project_working_set`` and the private steps).

The stage's inputs: the rig (:func:`stage_rig`), the mesh (:func:`load_mesh`,
:func:`load_inferred_faces`), the texels and ray scenes a worker keeps for its next camera
(:func:`_camera_inputs`); a camera task's memory (:func:`project_working_set`); and the steps of
a camera's projection: its visibility (:func:`_visible_texels`), shadow-consistent taps
(:func:`_camera_taps`), the saved occlusion decision (:func:`_save_visibility`) and the whole
camera's work (:func:`_project_camera`). The engine's task functions that call them
(``project_camera_task``, ``light_visibility_task``, ``light_block_task``) stay in
:mod:`facegeo.pipeline.project`, which a worker running them imports (and which tests patch).
"Module docstring" in the docstrings below means :mod:`facegeo.pipeline.project`'s (inferred
faces and texels, rigs, shadow taps, ``visibility.npz``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError
# the visibility file the evaluation reads (issue 37)
from facegeo.evaluate.projection import VISIBILITY_FILE
from facegeo.fsutil import READ_AHEAD_WORKERS
from facegeo.geometry.mesh import inferred_faces_path


def _scan(scan_dir):
    from facegeo.capture.scan import Scan, load_scan

    return scan_dir if isinstance(scan_dir, Scan) else load_scan(scan_dir)


def load_mesh(scan, mesh: str = "ground_truth") -> tuple[np.ndarray, np.ndarray, str]:
    """Vertices ``(V, 3)`` float64 (metres, world frame), faces ``(F, 3)`` and a description.

    ``mesh`` is ``"ground_truth"`` (a synthetic scan's ``ground_truth/mesh.ply``) or a path to a
    mesh file in metres (PLY/OBJ/GLB, loaded with ``process=False``).
    """
    import trimesh

    if mesh == "ground_truth":
        if "mesh" not in scan.ground_truth_keys:
            raise InputError(
                f"scan {scan.root}: no ground-truth mesh; pass mesh=<path to a mesh file in "
                f"metres> (facegeo reconstruct --mesh reconstructed builds one from the "
                f"structured light)")
        path = scan.ground_truth_path("mesh")
        import trimesh.exchange.ply

        with open(path, "rb") as fh:
            data = trimesh.exchange.ply.load_ply(fh)
        return (np.asarray(data["vertices"], np.float64), np.asarray(data["faces"], np.int64),
                f"ground truth ({path.name})")
    path = Path(mesh)
    if not path.is_file():
        raise InputError(f"mesh: {path} is not a file")
    try:
        m = trimesh.load(path, process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for unknown or unreadable files
        raise InputError(f"mesh: cannot read {path} as a mesh (PLY, OBJ, GLB, STL, OFF): "
                         f"{type(exc).__name__}: {exc}") from exc
    if len(getattr(m, "faces", ())) == 0:  # a point cloud, a scene without triangles
        raise InputError(f"mesh: {path} holds no triangles (read a {type(m).__name__} with "
                         f"{len(getattr(m, 'vertices', ()))} vertices)")
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64), str(path)


#: Texels of the atlas on inferred faces (module docstring), in the ``atlas`` folder.
INFERRED_TEXELS = "inferred_texels.npy"


def load_inferred_faces(scan, mesh: str, n_faces: int) -> np.ndarray | None:
    """``(F,)`` bool: the faces of the stage's mesh marked inferred (module docstring), or None
    when nothing marks them (the generator's mesh; a file without ``<stem>_inferred.npy``).

    Raises
    ------
    InputError
        The flags are not one boolean per face of the mesh.
    """
    if mesh == "ground_truth":
        return None
    path = inferred_faces_path(mesh)
    if not path.is_file():
        return None
    flags = np.load(path)
    if flags.shape != (n_faces,) or flags.dtype != bool:
        raise InputError(f"{path}: expected ({n_faces},) bool, one flag per face of {mesh}, got "
                         f"{flags.shape} {flags.dtype}; rebuild it with the mesh (facegeo mesh)")
    return flags


#: Rig choices of the stages after calibration (``rig=``); a rig file's path is accepted too.
STAGE_RIGS = ("ground_truth", "scan", "calibrated")


def stage_rig(scan, rig: str | None):
    """The rig a stage works with, and its name for the metrics.

    ``"ground_truth"`` — a synthetic scan's true rig (the default when there is one);
    ``"scan"`` — the scan's own ``rig.json`` (the nominal rig; the default otherwise);
    ``"calibrated"`` — ``out/calibrate/rig.json`` written by ``facegeo calibrate``;
    any other string — a rig file (``facegeo-rig`` JSON), e.g. another calibration's.
    """
    from facegeo.geometry.rig import Rig

    has_gt = scan.synthetic and "rig" in scan.ground_truth_keys
    if rig is None:
        rig = "ground_truth" if has_gt else "scan"
    if rig == "ground_truth":
        if not has_gt:
            raise InputError(f"rig: scan {scan.root} has no ground-truth rig; use rig='scan' or "
                             "'calibrated'")
        return Rig.load(scan.ground_truth_path("rig")), rig
    if rig == "scan":
        return scan.rig, rig
    path = scan.out_dir / "calibrate" / "rig.json" if rig == "calibrated" else Path(rig)
    if not path.is_file():
        if rig == "calibrated":
            raise InputError(f"rig 'calibrated': {path} does not exist; run `facegeo calibrate "
                             f"{scan.root}` first")
        raise InputError(f"rig: expected one of {', '.join(STAGE_RIGS)} or a rig file, got "
                         f"{fmt_value(rig)} (no such file)")
    the_rig = Rig.load(path)
    missing = [n for n in scan.camera_names if n not in the_rig.camera_names]
    if missing:
        raise InputError(f"rig {path}: lacks the scan's camera(s) {', '.join(missing)}")
    return the_rig, rig


#: Bytes a projection task needs per texel of the atlas, whatever the camera sees:
#: :func:`facegeo.surface.reflectance.camera_visibility`'s arrays over every texel (q, weight,
#: v_world, the masks, the camera-frame points and normals and their temporaries) and the texel
#: table itself (positions, normals, faces, barycentrics) ≈ 400 B; the sampler's remap maps,
#: the shadow taps and a sampled frame per projected texel ≈ 200 B more (bounded by T).
PROJECT_BYTES_PER_TEXEL = 600
#: ... per texel and light of a light block: the float32 RGB block buffer (12 B).
PROJECT_BYTES_PER_TEXEL_LIGHT = 12
#: ... per camera pixel: the frames in flight (the one sampled and ``READ_AHEAD_WORKERS`` read
#: ahead, float32 RGB, 12 B/px each) with their masks, the decoded 16-bit or 8-bit image, the
#: depth image and z-buffer of the visibility (float64) ≈ 40 B/px.
PROJECT_BYTES_PER_PIXEL = 12 * (READ_AHEAD_WORKERS + 1) + 40
#: ... per mesh triangle: Embree's BVH and the mesh arrays, for the visibility's scene and (with
#: shadow taps) the atlas mesh's shadow-ray scene ≈ 250 B each.
PROJECT_BYTES_PER_FACE = 250


def project_working_set(camera, n_texels: int, n_faces: int, block_lights: int,
                        shadow_taps: bool = True) -> int:
    """Memory (bytes) one camera's projection task needs (an upper bound: every texel of the
    atlas counted as projected): :data:`PROJECT_BYTES_PER_TEXEL` × texels +
    :data:`PROJECT_BYTES_PER_TEXEL_LIGHT` × texels × ``block_lights`` +
    :data:`PROJECT_BYTES_PER_PIXEL` × the camera's pixels + :data:`PROJECT_BYTES_PER_FACE` ×
    triangles (twice with shadow taps: the atlas mesh's own scene)."""
    T = int(n_texels)
    return (T * (PROJECT_BYTES_PER_TEXEL + PROJECT_BYTES_PER_TEXEL_LIGHT * int(block_lights))
            + int(camera.width) * int(camera.height) * PROJECT_BYTES_PER_PIXEL
            + int(n_faces) * PROJECT_BYTES_PER_FACE * (2 if shadow_taps else 1))


def _mesh_faces(scan, mesh: str) -> int:
    """Triangles of the stage's mesh, from the file's header where it has one (PLY), else by
    loading it."""
    if mesh == "ground_truth" and "mesh" not in scan.ground_truth_keys:
        return len(load_mesh(scan, mesh)[1])  # raises, naming what to give instead
    path = scan.ground_truth_path("mesh") if mesh == "ground_truth" else Path(mesh)
    if path.suffix.lower() == ".ply" and path.is_file():
        with open(path, "rb") as fh:
            for _ in range(64):
                line = fh.readline()
                if line.startswith(b"element face"):
                    return int(line.split()[2])
                if not line or line.startswith(b"end_header"):
                    break
    return len(load_mesh(scan, mesh)[1])


_INPUTS_CACHE: dict[tuple, tuple] = {}


def _camera_inputs(scan, atlas_dir: Path, mesh: str, shadow_taps: bool):
    """``(texels, scene, shadow_rays, inferred)`` of a projection task (``inferred``: the
    atlas's :data:`INFERRED_TEXELS`, or None), loaded once per process for the same files
    (keyed by their size and mtime; one entry kept): every camera of a run shares them, in
    process as on a worker."""
    from facegeo.fsutil import file_state
    from facegeo.surface.atlas import Atlas, Texels
    from facegeo.surface.visibility import RayScene

    mesh_path = scan.ground_truth_path("mesh") if mesh == "ground_truth" else Path(mesh)
    key = tuple((str(f), file_state(f)) for f in (
        atlas_dir / "atlas.npz", atlas_dir / "texels.npz", atlas_dir / INFERRED_TEXELS,
        mesh_path, inferred_faces_path(mesh_path)))
    key += (bool(shadow_taps),)
    if key not in _INPUTS_CACHE:
        _INPUTS_CACHE.clear()
        texels = Texels.load(atlas_dir / "texels.npz")
        inferred = atlas_dir / INFERRED_TEXELS
        inferred = np.load(inferred) if inferred.is_file() else None
        V, F, _ = load_mesh(scan, mesh)
        flags = load_inferred_faces(scan, mesh, len(F))
        # the visibility of the measured surface: inferred faces neither occlude nor end it
        # (module docstring)
        scene = RayScene(V, F if flags is None else F[~flags])
        shadow_rays = None
        if shadow_taps:
            from facegeo.surface.shadows import ShadowRays

            atlas = Atlas.load(atlas_dir / "atlas.npz")
            # the atlas's own mesh and shading normals: the texels' faces index it
            shadow_rays = ShadowRays(RayScene(atlas.vertices, atlas.faces), atlas.normals)
        _INPUTS_CACHE[key] = (texels, scene, shadow_rays, inferred)
    return _INPUTS_CACHE[key]


def _visible_texels(scan, atlas_dir, name: str, the_rig, mesh: str, vis_kw: dict,
                    shadow_taps: bool):
    """One camera's visibility over the atlas, its inferred texels left unmeasured (module
    docstring): ``(texels, shadow_rays, camera, vis, inferred_seen, seconds)``
    (``inferred_seen``: the inferred texels the camera saw, None when the atlas marks none).
    The first step of a whole camera's task and of a light-block projection's visibility
    task (:mod:`facegeo.pipeline._project_blocks`): the same code, the same bits."""
    from facegeo.surface import reflectance as rf

    texels, scene, shadow_rays, inferred = _camera_inputs(scan, Path(atlas_dir), mesh,
                                                          shadow_taps)
    camera = the_rig.camera(name)
    t0 = time.perf_counter()
    vis = rf.camera_visibility(texels, camera, scene, **vis_kw)
    inferred_seen = None
    if inferred is not None:  # surface no point supported: not measured (module docstring)
        inferred_seen = int(np.count_nonzero(vis.weight[inferred] > 0))
        vis.weight[inferred] = 0.0
    return texels, shadow_rays, camera, vis, inferred_seen, time.perf_counter() - t0


def _camera_taps(shadow_rays, camera, q, texels, sel: np.ndarray, lights):
    """The shadow-consistent taps of a camera's projected texels ``sel`` read at pixels ``q``
    (:func:`facegeo.surface.shadows.shadow_taps`), or None without ``shadow_rays``."""
    if shadow_rays is None:
        return None
    from facegeo.surface.shadows import shadow_taps as make_taps

    return make_taps(shadow_rays, camera, q, texels.face[sel], texels.bary[sel], lights)


def _save_visibility(d: Path, vis, vis_kw: dict) -> None:
    """The camera's occlusion decision, for the evaluation's comparison with other
    visibility (``visibility.npz``, module docstring)."""
    from facegeo.surface import reflectance as rf

    jump = vis_kw.get("depth_jump", rf.DEFAULT_DEPTH_JUMP)
    np.savez_compressed(d / VISIBILITY_FILE, in_image=vis.in_image, facing=vis.facing,
                        unoccluded=vis.unoccluded, depth_jump=np.float64(jump))


def _project_camera(scan, atlas_dir: str, d: Path, name: str, the_rig, mesh: str,
                    vis_kw: dict, dtype: str, block_lights: int, shadow_taps: bool,
                    field_format: str, field_store) -> dict:
    """:func:`project_camera_task`'s work, into the camera folder ``d``."""
    from facegeo.surface import reflectance as rf

    scan = _scan(scan)
    texels, shadow_rays, camera, vis, inferred_seen, t_vis = _visible_texels(
        scan, atlas_dir, name, the_rig, mesh, vis_kw, shadow_taps)
    t1 = time.perf_counter()
    # built and applied within seconds_projection
    sel = np.flatnonzero(vis.weight > 0)
    taps = _camera_taps(shadow_rays, camera, vis.q[sel], texels, sel, the_rig.lights)
    field = rf.project_camera(
        # black-clipped pixels are the dark samples a one-light frame is mostly made of:
        # measured (below one code value), not masked — masking them left 59 % of a 16-bit
        # PNG scan's samples NaN and every function incomplete; saturated ones stay masked
        scan.iter_olat(name, return_mask=True, read_ahead=READ_AHEAD_WORKERS,
                       black_clipped="dark"),
        vis, (camera.width, camera.height), scan.n_lights, d, dtype=dtype,
        block_lights=block_lights, shadows=taps, field_format=field_format,
        field_store=field_store)
    t2 = time.perf_counter()
    entry = {
        "visible_fraction": round(vis.visible_fraction, 6),
        "weighted_texels": int(field.texel_index.size),
        "seconds_visibility": round(t_vis, 4),
        "seconds_projection": round(t2 - t1, 4),
        "texels_per_second": round(field.texel_index.size * scan.n_lights
                                   / max(t2 - t1, 1e-9), 1),
        "masked_samples": field.n_masked,
        "float16_overflow": field.n_overflow,
        "shadow_taps": taps is not None,
    }
    if inferred_seen is not None:  # inferred texels this camera saw, left unmeasured
        entry["inferred_texels_unmeasured"] = inferred_seen
    if taps is not None:
        entry["shadow_edge_samples"] = round(taps.changed / max(taps.samples, 1), 6)
        entry["seconds_shadow_taps"] = round(taps.seconds, 4)
    _save_visibility(d, vis, vis_kw)
    return {"metrics": entry}
