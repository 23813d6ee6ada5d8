"""``facegeo reconstruct``: every stage the scan has input for, cached under ``SCAN/out/<stage>/``.

The chain (Debevec et al. 2000 from capture to novel views)::

    calibrate ─► (rig, residuals)                      if the scan has [calib]
    decode ─► mesh                                     if it has [structured_light]
    atlas ─► project ─► relight, fit ─► render         if it has [olat] (atlas needs a mesh)
    fit (image space)                                  [olat] of one camera and no geometry
    evaluate                                           last: every product against the
                                                       scan's references (facegeo.evaluate)

Each stage is a :class:`facegeo.pipeline.cache.StageSpec`: it reruns only when the content of
the files it reads, its settings, an earlier stage's key, the facegeo version or facegeo's code
(:func:`facegeo.pipeline.cache.code_fingerprint`) changed (:mod:`facegeo.pipeline.cache`; the
line ``facegeo reconstruct`` prints for a stage that ran says why), and every stage's metrics
are gathered in
``SCAN/out/metrics.json``. A stage is left out when the scan has nothing for it (a calibration-
only scan runs ``calibrate``; a structured-light-only scan runs ``decode → mesh``).

Which mesh and which rig the stages use — the chain is the default (issue 37):

* ``mesh="auto"`` (the default): the reconstructed mesh of the ``mesh`` stage whenever the scan
  has structured light, synthetic or not; a synthetic scan without structured light takes the
  generator's mesh (there is no other). ``"ground_truth"``, ``"reconstructed"`` or a mesh file
  (metres) choose explicitly.
* ``rig="auto"`` (the default): the ``calibrate`` stage's rig (``out/calibrate/rig.json``)
  whenever the scan has board views, synthetic or not, so a synthetic scan's figures are the
  whole chain's, end to end; without board views the scan's ``rig.json`` (a synthetic scan:
  the generator's true rig, ``ground_truth/rig.json``). When the calibration fails (the tiny
  preset's 80 × 120 px board views show no marker) ``auto`` falls back to that same rig, the
  run logs a warning and records why (``"rig_note"`` in the run record, below).
  ``"ground_truth"``, ``"calibrated"`` or ``"scan"`` choose explicitly. A calibrated rig's
  world frame is its own gauge: the evaluation reports the mesh also after the best rigid
  alignment, and moves the novel views' cameras into the generator's frame by that alignment.
  When ``rig`` is the true rig for a chain that meshes structured light while ``rig.json``'s
  projector is uncalibrated, the true projector is information a real scan would not have: the
  run logs one warning saying so (``"scan"`` meshes camera against camera instead).
* With the reconstructed mesh the atlas — and so the projection, fit and renders — is built on
  the mesh stage's *filled* surface (``mesh_filled.ply``: closed over what the structured light
  did not reach, its inferred faces left unmeasured and inferred in the renders; issue 37,
  :mod:`facegeo.pipeline.project`), the atlas setting ``surface`` (:data:`SURFACES`;
  ``"trimmed"``: ``mesh.ply``). ``mesh.ply`` stays the measured product the mesh figures are
  taken on.
* The stage-alone figures are a diagnostic: ``--rig ground_truth --mesh ground_truth`` feeds the
  same stages the generator's rig and mesh, so their errors are the surface methods' own.
  :func:`run_diagnostic` runs that pass into ``out/diagnostic/`` (its own cached pipeline,
  :data:`DIAGNOSTIC_DIR`); ``facegeo demo`` runs both and the report shows the two side by side.

A single-view OLAT scan without geometry (one camera, no structured light, no ground-truth mesh,
``mesh="auto"``: Yale B, DiLiGenT) has no atlas to build: its chain is the ``fit`` stage alone,
in image space (:func:`facegeo.pipeline.fit.fit_image_products`; every masked pixel a texel).
Give ``--mesh PATH`` to fit it on a mesh instead.

The last stage, ``evaluate`` (:mod:`facegeo.evaluate`), compares every earlier stage's products
with the scan's references (the generator's truth, ``[reference]`` answers): the stages
themselves never read the truth. Every run records what it used — ``{"rig", "mesh", "world"}``
(:func:`run_choices`) — in ``out/run/run.json`` and ``out/metrics.json`` → ``"run"``.

A calibration that fails (no board found in a camera's views, say) ends the run with the error
when the rig it should produce is used downstream; otherwise ``calibrate`` records the failure
in its metrics (``"error"``) and the other stages go on.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from facegeo.checks import fmt_value
from facegeo.errors import FacegeoError, InputError
from facegeo.pipeline.cache import Pipeline, StageContext, StageResult, StageSpec
from facegeo.render._cameras import FRONT, NOVEL_ORBITS

log = logging.getLogger(__name__)

__all__ = ["STAGES", "DIAGNOSTIC_DIR", "MESH_CHOICES", "RIG_CHOICES", "SURFACES",
           "SURFACE_DEFAULT", "reconstruct_pipeline", "reconstructed_surface",
           "record_run", "run_choices", "run_diagnostic", "run_reconstruct"]

#: Every stage ``facegeo reconstruct`` knows, in pipeline order.
STAGES = ("calibrate", "decode", "mesh", "atlas", "project", "relight", "fit", "render",
          "evaluate")
#: Values of ``mesh`` besides a mesh file.
MESH_CHOICES = ("auto", "ground_truth", "reconstructed")
#: Values of ``rig``.
RIG_CHOICES = ("auto", "ground_truth", "calibrated", "scan")

#: The render stage's default views: the rig's frontal camera (:func:`facegeo.render.front_camera`,
#: the source cameras' mean view of the head) orbited by these angles (degrees) — views no
#: source camera saw (on the two-camera presets, 15° and 45° beyond the outermost camera).
RENDER_ORBITS = NOVEL_ORBITS
#: Rays per pixel (s × s, a box filter over the pixel) of the render stage's views and of the
#: generator's references they are compared with: a camera's pixel integrates its footprint,
#: and at 1 (pixel centres) the hard shadow edges' point samples are an error floor every
#: method shares (docs/render.md, "The pixel footprint"). The fit stage fits the texels the
#: views' supersampled rays tap.
RENDER_SUPERSAMPLE = 3


#: Which of the ``mesh`` stage's surfaces the atlas (and so the projection, fit and renders) is
#: built on when the mesh is the reconstructed one — the atlas setting ``surface``:
#: ``"filled"`` (``mesh_filled.ply``: closed over what the structured light did not reach, its
#: inferred faces marked, issue 37) or ``"trimmed"`` (``mesh.ply``, the measured surface alone).
SURFACES = ("filled", "trimmed")
SURFACE_DEFAULT = "filled"


def reconstructed_surface(mesh_dir, surface: str = SURFACE_DEFAULT) -> Path:
    """The ``mesh`` stage's surface file for the atlas setting ``surface`` (:data:`SURFACES`):
    ``mesh_filled.ply`` or ``mesh.ply``; ``"filled"`` falls back to ``mesh.ply`` (with a log
    line) when the stage wrote no filled surface (the grid method, ``fill_distance_mm=None``).
    """
    from facegeo.pipeline.mesh import FILLED_MESH

    if surface not in SURFACES:
        raise InputError(f"atlas surface: expected one of {', '.join(SURFACES)}, got "
                         f"{fmt_value(surface)}")
    mesh_dir = Path(mesh_dir)
    if surface == "filled":
        if (mesh_dir / FILLED_MESH).is_file():
            return mesh_dir / FILLED_MESH
        log.info("atlas: %s has no %s (no filled surface made); the trimmed mesh.ply is used",
                 mesh_dir, FILLED_MESH)
    return mesh_dir / "mesh.ply"


def _atlas_surface(atlas_dir) -> str:
    """The ``surface`` setting the atlas in ``atlas_dir`` was built with (its ``stage.json``;
    ``"trimmed"`` for an atlas without one, from before the setting)."""
    try:
        doc = json.loads((Path(atlas_dir) / "stage.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return "trimmed"
    return doc.get("settings", {}).get("surface", "trimmed")


def _common_inputs(scan) -> list[Path]:
    files = [scan.manifest_path, scan.root / scan.manifest["scan"]["rig"]]
    # ground truth feeds the accuracy metrics (and, on synthetic scans, the true rig)
    files += [scan.ground_truth_path(k) for k in sorted(scan.ground_truth_keys)
              if scan.ground_truth_path(k).is_file()]
    return files


def _group_inputs(scan, group: str) -> list[Path]:
    files = _common_inputs(scan)
    for cam in scan.camera_names:
        files += [p for _, p in scan.expected_files(group, cam)]
    return files


def _resolve_mesh(scan, mesh: str) -> str:
    if mesh == "auto":  # the chain's own mesh whenever it makes one (module docstring)
        if scan.has("structured_light"):
            return "reconstructed"
        if "mesh" in scan.ground_truth_keys:
            return "ground_truth"
        raise InputError(f"scan {scan.root}: no structured light to build a mesh from and no "
                         "ground-truth mesh; give --mesh PATH (a mesh in metres)")
    if mesh == "ground_truth" and "mesh" not in scan.ground_truth_keys:
        raise InputError(f"mesh: scan {scan.root} has no ground-truth mesh (use 'reconstructed' "
                         "or a mesh file)")
    if mesh == "reconstructed" and not scan.has("structured_light"):
        raise InputError(f"mesh: scan {scan.root} has no structured-light frames to reconstruct "
                         "a mesh from")
    if mesh not in MESH_CHOICES and not Path(mesh).is_file():
        raise InputError(f"mesh: expected one of {', '.join(MESH_CHOICES)} or a mesh file, got "
                         f"{mesh!r}")
    return mesh


def _applicable(scan, mesh: str) -> list[str]:
    from facegeo.pipeline._fit_image import image_space_scan

    stages = []
    if scan.has("calib"):
        stages.append("calibrate")
    if scan.has("structured_light"):
        stages += ["decode", "mesh"]
    if image_space_scan(scan, mesh):
        stages.append("fit")  # in image space: no geometry to build an atlas on
    elif scan.has("olat") and scan.camera_names:
        stages += ["atlas", "project", "relight", "fit", "render"]
    return stages


#: What a stage reads from the scan, for the message when the scan lacks it.
_STAGE_NEEDS = {
    "calibrate": "no board views to calibrate (no [calib] group)",
    "decode": "no structured-light frames to decode (no [structured_light] group)",
    "mesh": "no structured light to mesh (no [structured_light] group)",
}


def _check_stage_has_input(scan, stage: str | None, flag: str | None) -> None:
    """Raise :class:`InputError` naming what the scan lacks when ``stage`` is a stage of the
    chain that this scan has no input for (``facegeo mesh`` on a calibration-only scan);
    ``flag`` (``"--only"``, ``"--from"``) prefixes the message."""
    if stage is None or stage not in STAGES or stage == "evaluate" \
            or stage in _applicable(scan, "auto"):
        return
    lacks = _STAGE_NEEDS.get(stage, f"no OLAT frames for the {stage!r} stage (no [olat] group)")
    have = ", ".join(f"[{g}]" for g in ("calib", "structured_light", "olat") if scan.has(g))
    raise InputError(f"{flag + ' ' + repr(stage) + ': ' if flag else ''}scan {scan.root} has "
                     f"{lacks}; it has {have or 'no frame groups'}")


def _resolve_rig(scan, rig: str, stages: list[str], calibration_error: str | None = None) -> str:
    """The rig the chain's stages use (module docstring); ``stages`` are the chain's.

    ``"auto"`` is the calibrated rig whenever the chain calibrates, unless
    ``calibration_error`` says the calibration failed: then, as without board views, the scan's
    ``rig.json`` — a synthetic scan's true rig (:func:`_warn_true_rig` says so where that stands
    in for an uncalibrated projector).
    """
    if rig not in RIG_CHOICES:
        raise InputError(f"rig: expected one of {', '.join(RIG_CHOICES)}, got {fmt_value(rig)}")
    has_gt = scan.synthetic and "rig" in scan.ground_truth_keys
    if rig == "auto":
        if "calibrate" in stages and calibration_error is None:
            return "calibrated"
        return "ground_truth" if has_gt else "scan"
    if rig == "ground_truth" and not has_gt:
        raise InputError(f"rig 'ground_truth': scan {scan.root} has no ground-truth rig")
    if rig == "calibrated" and "calibrate" not in stages:
        raise InputError(f"rig 'calibrated': scan {scan.root} has no [calib] board views to "
                         "calibrate from")
    return rig


def _warn_true_rig(scan, rig: str, use_rig: str, runs: list[str], stages: list[str]) -> None:
    """Log once (the pipeline is built once per run) that ``--rig auto`` took the generator's
    true rig for a ``mesh`` stage this run may run while ``rig.json``'s projector is uncalibrated:
    the true projector is what a real scan would not have. ``runs``: the stages the run may run
    (``Pipeline.stages_run``); ``stages``: all of the chain's."""
    if rig == "auto" and use_rig == "ground_truth" and "mesh" in runs \
            and not scan.rig.projector_calibrated:
        log.warning("rig auto: using the generator's true rig; rig.json's projector is "
                    "uncalibrated (give --rig scan to mesh camera against camera%s)",
                    ", or --rig calibrated after facegeo calibrate"
                    if "calibrate" in stages else "")


def _choices(scan, mesh: str, rig: str, calibration_error: str | None = None
             ) -> tuple[list[str], str | None, str]:
    """The chain's stages, the mesh of its surface stages (None without them) and its rig."""
    names = _applicable(scan, mesh)
    use_mesh = _resolve_mesh(scan, mesh) if "atlas" in names else None
    return names, use_mesh, _resolve_rig(scan, rig, names, calibration_error)


#: The diagnostic pass's products folder inside ``out/`` (:func:`run_diagnostic`).
DIAGNOSTIC_DIR = "diagnostic"
#: Where ``run_reconstruct`` records the run's choices (``RUN_RECORD/run.json``, and
#: ``out/metrics.json`` → ``"run"``).
RUN_RECORD = "run"


def run_choices(scan, *, mesh: str = "auto", rig: str = "auto",
                calibration_error: str | None = None) -> dict:
    """What a run of the chain uses: ``{"rig", "mesh", "world"}`` (and ``"rig_note"`` when
    ``rig="auto"`` fell back from a calibration that failed with ``calibration_error``).

    ``rig`` and ``mesh`` are the chain's resolved choices (``"ground_truth"``, ``"calibrated"``,
    ``"scan"``; ``"ground_truth"``, ``"reconstructed"`` or a file — ``"reconstructed"`` too when
    the chain meshes structured light and has no surface stages —, None when it makes or uses
    no mesh); ``world`` says whose world frame the products are in: the
    generator's (the true rig), the calibration's (its own description, ``out/calibrate``'s
    ``world`` when it ran) or the scan's ``rig.json``.
    """
    names, use_mesh, use_rig = _choices(scan, mesh, rig, calibration_error)
    if use_mesh is None and "mesh" in names:  # no surface stages: the chain's mesh is its own
        use_mesh = "reconstructed"
    if use_rig == "ground_truth":
        world = "the generator's (ground_truth/rig.json)"
    elif use_rig == "calibrated":
        world = "the calibration's"
        try:
            doc = json.loads((scan.out_dir / "calibrate" / "stage.json").read_text("utf-8"))
            if isinstance(doc.get("metrics", {}).get("world"), str):
                world = f"the calibration's: {doc['metrics']['world']}"
        except (OSError, ValueError, AttributeError):
            pass
    else:
        world = f"the scan's {scan.manifest['scan']['rig']} (nominal)"
    choices = {"rig": use_rig, "mesh": use_mesh, "world": world}
    if rig == "auto" and calibration_error is not None and "calibrate" in names:
        choices["rig_note"] = _fallback_note(calibration_error)
    return choices


def _fallback_note(calibration_error: str) -> str:
    """Why ``rig="auto"`` did not take the calibrated rig (the run record's ``rig_note``)."""
    first = " ".join(calibration_error.split())
    return (f"rig auto: the calibration failed ({first[:120]}{'…' if len(first) > 120 else ''})"
            "; the chain fell back to the rig the scan has without boards")


def record_run(scan, choices: dict) -> None:
    """Write ``choices`` (:func:`run_choices`) to ``out/run/run.json`` and ``out/metrics.json``
    → ``"run"`` (atomic writes; the folder keeps the entry when the report drops the entries of
    deleted products)."""
    from facegeo.fsutil import atomic_write_text
    from facegeo.pipeline.cache import record_metrics

    folder = scan.out_dir / RUN_RECORD
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder / "run.json", json.dumps(choices, indent=2) + "\n")
    record_metrics(scan.out_dir, RUN_RECORD, choices)


def reconstruct_pipeline(scan, *, mesh: str = "auto", rig: str = "auto",
                         only: str | None = None, until: str | None = None,
                         engine=None, calibration_error: str | None = None,
                         diagnostic: bool = False, views: list | None = None,
                         store=None, lights_per_task: int | None = None) -> Pipeline:
    """The :class:`~facegeo.pipeline.cache.Pipeline` of ``facegeo reconstruct`` for one scan.

    Parameters
    ----------
    scan : facegeo.capture.scan.Scan
        The loaded scan (loaded and validated once; every stage reads it from here).
    mesh : str
        ``"auto"``, ``"ground_truth"``, ``"reconstructed"`` or a mesh file in metres (module
        docstring).
    rig : str
        ``"auto"``, ``"ground_truth"``, ``"calibrated"`` or ``"scan"`` (module docstring).
    only, until : str, optional
        The run's ``--only`` / ``until`` (:meth:`Pipeline.run`), when known: the warning about
        ``--rig auto`` is given only when the run may mesh.
    engine : facegeo.pipeline.engine.Engine, optional
        Where the stages that split into tasks run them (``decode``, ``project``: one task per
        camera; ``fit``, ``relight``: chunks; ``render``: one task per view); default in
        process. Not part of any stage's key: the products are the same bytes.
    store : str, optional
        The ``decode`` stage's tasks write through this store, the texture ``relight``'s tasks
        put their relit rows into it, and the ``render`` stage's view tasks read their inputs
        from it and write their views into it (:func:`run_reconstruct`).
    lights_per_task : int, optional
        The ``project`` stage's tasks split a camera into blocks of this many lights
        (:func:`facegeo.pipeline.project.project_products`; default: its automatic rule on a
        Dask engine). Not a setting: the products are the same bytes.
    calibration_error : str, optional
        The ``calibrate`` stage's recorded failure, when it failed: ``rig="auto"`` then falls
        back (module docstring; :func:`run_reconstruct` runs the calibration first to know).
    diagnostic : bool
        The stage-alone pass (:func:`run_diagnostic`): the stages after the calibration, fed
        the generator's rig and mesh (``mesh`` and ``rig`` must be ``"ground_truth"``), into
        ``out/diagnostic/`` (:data:`DIAGNOSTIC_DIR`); no ``calibrate`` stage (it has no
        upstream: its figures are the chain's).
    views : list of camera specs, optional
        The novel views the ``fit`` and ``render`` stages work for (default: orbits of the
        rig's frontal camera by :data:`RENDER_ORBITS`; the diagnostic pass: the chain's views
        in the generator's frame, camera dicts).
    """
    from facegeo.pipeline.fit import FIT_SETTINGS
    from facegeo.pipeline.render import RENDER_DEFAULT_ENV, SHRINKAGE_DEFAULT
    from facegeo.surface.atlas import DEFAULT_SPLIT_FACES

    names, use_mesh, use_rig = _choices(scan, mesh, rig, calibration_error)
    if diagnostic:
        if (mesh, rig) != ("ground_truth", "ground_truth"):
            raise InputError(f"the diagnostic pass feeds the stages the generator's rig and mesh:"
                             f" got mesh={mesh!r}, rig={rig!r}")
        names = [n for n in names if n != "calibrate"]
    # the stages that work in the rig's frame wait for the calibration when they use its rig
    rig_after = ("calibrate",) if use_rig == "calibrated" else ()
    specs: list[StageSpec] = []

    if "calibrate" in names:
        def run_calibrate(ctx: StageContext) -> dict:
            from facegeo.pipeline.calibrate import calibrate_products

            try:
                metrics, _ = calibrate_products(scan, ctx.out_dir, **ctx.settings)
            except FacegeoError as e:
                # the later stages need its rig when chosen explicitly; "auto" falls back
                # (run_reconstruct reads the recorded failure)
                if use_rig == "calibrated" and rig != "auto":
                    raise
                return {"error": str(e)}
            return metrics

        from facegeo.pipeline.calibrate import CALIBRATE_DEFAULTS, calibrate_inputs

        # the same inputs and settings as `facegeo calibrate`: its products are this stage's
        specs.append(StageSpec("calibrate", run_calibrate,
                               inputs=lambda d: calibrate_inputs(scan),
                               settings=dict(CALIBRATE_DEFAULTS)))

    if "decode" in names:
        def run_decode(ctx: StageContext) -> dict:
            from facegeo.pipeline.decode import PARTIAL_DIR, decode_products

            # finished cameras wait in out/decode/.partial until the stage completes
            # with a store the tasks write through it (not a setting: the products are the
            # same bytes wherever the tasks wrote them on their way)
            metrics, _ = decode_products(scan, ctx.out_dir, **ctx.settings,
                                         partial_dir=ctx.out_dir.parent / "decode" / PARTIAL_DIR,
                                         engine=engine, progress=ctx.progress, store=store)
            return metrics

        specs.append(StageSpec("decode", run_decode,
                               inputs=lambda d: _group_inputs(scan, "structured_light")))

        def run_mesh(ctx: StageContext) -> dict:
            from facegeo.pipeline.mesh import mesh_products

            metrics, _ = mesh_products(scan, ctx.upstream["decode"], ctx.out_dir, **ctx.settings)
            return metrics

        # the OLAT frames give the cameras' silhouettes (the mesh stage's ``silhouettes``),
        # which shape the filled surface: not when the surface stages take another mesh (the
        # stage-alone pass), where the stage's figures are its points' and trimmed mesh's
        sil = "auto" if use_mesh in (None, "reconstructed") else "off"
        specs.append(StageSpec("mesh", run_mesh, after=("decode",) + rig_after,
                               inputs=lambda d: _group_inputs(scan, "olat")
                               if scan.has("olat") and sil != "off" else _common_inputs(scan),
                               settings={"rig": use_rig, "method": "poisson", "depth": "auto",
                                         "point_weight": 4.0,
                                         "trim_quantile": 0.02, "fill_distance_mm": "auto",
                                         "fill_scale": None, "silhouettes": sil}))

    if "fit" in names and "atlas" not in names:  # a single-view scan, fitted in image space
        from facegeo.pipeline._fit_image import IMAGE_FIT_SETTINGS

        def run_fit_image(ctx: StageContext) -> dict:
            from facegeo.pipeline._fit_image import fit_image_products

            metrics, _ = fit_image_products(scan, ctx.out_dir, progress=ctx.progress,
                                            **ctx.settings)
            return metrics

        def image_inputs(d) -> list[Path]:
            # the frames, the ambient frame, the mask and reference normals (scored against)
            extra = [scan.ambient_path(c) for c in scan.camera_names]
            extra += [scan.reference_path(k) for k in sorted(scan.reference_keys)]
            return _group_inputs(scan, "olat") + [p for p in extra
                                                  if p is not None and p.is_file()]

        # the scan's own rig.json: the lights' directions and the camera are all it reads
        specs.append(StageSpec("fit", run_fit_image, inputs=image_inputs,
                               settings=dict(IMAGE_FIT_SETTINGS)))

    if "atlas" in names:
        from facegeo.pipeline.project import atlas_products, project_products

        mesh_after = ("mesh",) if use_mesh == "reconstructed" else ()

        def mesh_of(ctx: StageContext) -> str:
            if use_mesh != "reconstructed":
                return use_mesh
            # the atlas's setting; the project stage takes the surface its atlas was built on
            surface = (ctx.settings.get("surface") if "surface" in ctx.settings
                       else _atlas_surface(ctx.upstream["atlas"]))
            return str(reconstructed_surface(ctx.upstream["mesh"], surface))

        def mesh_inputs() -> list[Path]:
            if use_mesh == "ground_truth":
                return [scan.ground_truth_path("mesh")]
            return [] if use_mesh == "reconstructed" else [Path(use_mesh)]

        def without_mesh(ctx: StageContext) -> dict:
            return {k: v for k, v in ctx.settings.items() if k not in ("mesh", "surface")}

        def run_atlas(ctx: StageContext) -> dict:
            return atlas_products(scan, ctx.out_dir, mesh=mesh_of(ctx), **without_mesh(ctx))

        def run_project(ctx: StageContext) -> dict:
            metrics, _ = project_products(scan, ctx.upstream["atlas"], ctx.out_dir,
                                          mesh=mesh_of(ctx), **without_mesh(ctx),
                                          engine=engine, progress=ctx.progress,
                                          lights_per_task=lights_per_task)
            return metrics

        def run_relight(ctx: StageContext) -> dict:
            from facegeo.pipeline.relight import relight_products

            # with a store the tasks' relit rows go through it (not a setting: the same bytes)
            metrics, _ = relight_products(scan, ctx.upstream["project"], ctx.out_dir,
                                          atlas_dir=ctx.upstream["atlas"], engine=engine,
                                          store=store, **ctx.settings)
            return metrics

        def env_inputs(env: str) -> list[Path]:
            # a map file's content is part of the key; shipped maps are covered by the version
            return [Path(env)] if Path(env).is_file() else []

        def run_fit(ctx: StageContext) -> dict:
            from facegeo.pipeline.fit import fit_products

            metrics, _ = fit_products(scan, ctx.upstream["project"], ctx.out_dir,
                                      atlas_dir=ctx.upstream["atlas"], progress=ctx.progress,
                                      engine=engine, **ctx.settings)
            return metrics

        def run_render(ctx: StageContext) -> dict:
            from facegeo.pipeline.render import render_products

            return render_products(scan, ctx.upstream["atlas"].parent, ctx.out_dir,
                                   progress=ctx.progress, engine=engine, store=store,
                                   **ctx.settings)

        if views is None:
            views = [f"orbit:{FRONT}:{d:g}" for d in RENDER_ORBITS]
        fit_settings = dict(FIT_SETTINGS, texels="views", views=views, rig=use_rig,
                            supersample=RENDER_SUPERSAMPLE)
        specs += [
            StageSpec("atlas", run_atlas, after=mesh_after, inputs=lambda d: mesh_inputs(),
                      settings={"mesh": use_mesh, "texels_per_mm": 1.0, "size": None, "padding": 2,
                                "split_faces": DEFAULT_SPLIT_FACES, "repair": False,
                                **({"surface": SURFACE_DEFAULT}
                                   if use_mesh == "reconstructed" else {})}),
            StageSpec("project", run_project, after=("atlas",) + mesh_after + rig_after,
                      inputs=lambda d: _group_inputs(scan, "olat") + mesh_inputs(),
                      settings={"mesh": use_mesh, "rig": use_rig, "dtype": "float16",
                                "shadow_taps": True, "field_format": "npy",
                                "store": None}),
            StageSpec("relight", run_relight, after=("atlas", "project"),
                      inputs=lambda d: _common_inputs(scan) + env_inputs(RENDER_DEFAULT_ENV),
                      settings={"env": RENDER_DEFAULT_ENV, "rotate": 0.0, "view": "texture",
                                "projection": "latlong", "solid_angle": "paper"}),
            StageSpec("fit", run_fit, after=("atlas", "project") + rig_after,
                      inputs=lambda d: _common_inputs(scan), settings=fit_settings),
            StageSpec("render", run_render, after=("atlas", "project", "fit") + rig_after,
                      inputs=lambda d: _common_inputs(scan) + env_inputs(RENDER_DEFAULT_ENV),
                      settings={"views": views, "env": RENDER_DEFAULT_ENV, "rig": use_rig,
                                "shrinkage": SHRINKAGE_DEFAULT, "shadow_taps": True,
                                "image_detail": True, "supersample": RENDER_SUPERSAMPLE}),
        ]
    if not specs:
        raise InputError(f"scan {scan.root}: nothing to reconstruct (no [calib], "
                         "[structured_light] or [olat] frames)")
    specs.append(_evaluate_spec(scan, [s.name for s in specs]))
    pipeline = Pipeline(specs, out_name=f"out/{DIAGNOSTIC_DIR}" if diagnostic else "out")
    _warn_true_rig(scan, rig, use_rig, pipeline.stages_run(only=only, until=until), names)
    return pipeline


def _evaluate_spec(scan, names: list[str]) -> StageSpec:
    """The last stage: every earlier stage's products against the scan's references
    (:func:`facegeo.evaluate.evaluate_products`), rerun when a product, a reference or a
    setting changed."""
    from facegeo.evaluate import EVALUATE_SETTINGS, evaluation_inputs

    def run_evaluate(ctx: StageContext) -> dict:
        from facegeo.evaluate import evaluate_products

        return evaluate_products(scan, ctx.out_dir.parent, ctx.out_dir, stages=names,
                                 progress=ctx.progress, **ctx.settings)

    return StageSpec("evaluate", run_evaluate, after=tuple(names),
                     inputs=lambda d: evaluation_inputs(scan), settings=dict(EVALUATE_SETTINGS))


def run_reconstruct(scan_dir, *, mesh: str = "auto", rig: str = "auto",
                    settings: Mapping[str, Mapping[str, Any]] | None = None,
                    from_stage: str | None = None, only: str | None = None,
                    until: str | None = None,
                    progress: Callable[[str, int, int], None] | None = None,
                    on_stage: Callable[[StageResult], None] | None = None,
                    engine=None, store: str | None = None,
                    lights_per_task: int | None = None) -> list[StageResult]:
    """Run every stage of ``facegeo reconstruct`` whose products are missing or stale.

    Parameters
    ----------
    scan_dir : path-like or facegeo.capture.scan.Scan
        The scan directory, or the scan already loaded (``facegeo render`` loads it once for
        its own checks and passes it on: not validated a second time).
    mesh, rig : str
        See :func:`reconstruct_pipeline`.
    settings : mapping of stage -> mapping, optional
        Overrides of a stage's settings (``{"atlas": {"texels_per_mm": 2.0}}``); a changed
        setting reruns that stage and the ones after it.
    from_stage, only : str, optional
        ``--from STAGE`` reruns that stage and every later one; ``--only STAGE`` runs one stage
        (its inputs must be current).
    until : str, optional
        Run that stage and what it needs, nothing after it (``facegeo decode SCAN``, ...).
    progress, on_stage : callable, optional
        See :meth:`facegeo.pipeline.cache.Pipeline.run`.
    engine : facegeo.pipeline.engine.Engine, optional
        See :func:`reconstruct_pipeline` (the caller creates and closes it:
        ``with make_engine(workers, scheduler, memory_limit) as engine: ...``).
    store : str, optional
        ``--store URL`` (a folder or an fsspec URL): the ``store`` setting of the stages that
        take one — ``project`` (the fields stay in the store, linked) and ``fit`` (its tasks'
        D and parameters go through it) — where the scan has them, and the ``decode`` stage's
        tasks (they write through the store and, when it holds the scan — ``facegeo push`` —
        read their frames from it; :func:`facegeo.pipeline.decode.decode_products`; not a
        setting: the products are the same) (docs/scale.md §3).
    lights_per_task : int, optional
        See :func:`reconstruct_pipeline`.
    """
    from facegeo.capture.scan import Scan, load_scan

    if isinstance(scan_dir, Scan):
        scan, scan_dir = scan_dir, scan_dir.root
    else:
        scan_dir = Path(scan_dir)
        scan = load_scan(scan_dir)  # validated once, before any stage starts
    if settings:
        json.dumps(settings)  # fail early on values that cannot enter a cache key
        for stage, given in settings.items():  # the chain's own choices, not a stage's
            clash = sorted({"mesh", "rig"} & set(given)) if isinstance(given, Mapping) else []
            if clash:
                raise InputError(f"settings[{stage!r}]: {', '.join(clash)} is chosen for the whole "
                                 f"chain: pass mesh= / rig= (--mesh / --rig), not a stage setting")
        # the fit fits the texels the render's rays tap: a render supersample given alone
        # carries over to the fit (a fit traced at other sub-pixel offsets leaves texels the
        # render taps unfitted)
        render_given = settings.get("render")
        if isinstance(render_given, Mapping) and "supersample" in render_given:
            fit_given = dict(settings.get("fit") or {})
            fit_given.setdefault("supersample", render_given["supersample"])
            settings = {**settings, "fit": fit_given}
    for name, flag in ((until, None), (only, "--only"), (from_stage, "--from")):
        _check_stage_has_input(scan, name, flag)
    calibration_error: str | None = None
    done: list[StageResult] = []
    try:
        if rig == "auto" and "calibrate" in _applicable(scan, mesh):
            # "auto" is the calibrated rig if the calibration succeeds: run it first (cached
            # like any stage) and fall back when it recorded a failure (module docstring)
            done, calibration_error = _calibrate_first(scan, scan_dir, mesh, settings,
                                                       from_stage, only, until, progress,
                                                       on_stage)
            if calibration_error is not None:
                log.warning("%s", _fallback_note(calibration_error))
            if "calibrate" in (only, until):
                return done
            if from_stage == "calibrate":  # it ran: the rest reruns, not the calibration again
                from_stage = next(s for s in STAGES[1:] if s in _applicable(scan, mesh)
                                  or s == "evaluate")
        pipeline = reconstruct_pipeline(scan, mesh=mesh, rig=rig, only=only, until=until,
                                        engine=engine, calibration_error=calibration_error,
                                        store=store, lights_per_task=lights_per_task)
        if store is not None:  # the stages with a store setting, where the scan has them
            settings = dict(settings or {})
            for spec in pipeline.stages:
                if "store" in (spec.settings or {}):
                    settings[spec.name] = {**(settings.get(spec.name) or {}), "store": store}

        def report(result: StageResult) -> None:
            if on_stage is not None and not (done and result.name == "calibrate"):
                on_stage(result)

        results = pipeline.run(scan_dir, settings=settings, from_stage=from_stage, only=only,
                               until=until, progress=progress, on_stage=report)
        return done + [r for r in results if not (done and r.name == "calibrate")]
    finally:  # what the products on disk were made with, failed run or not
        if (Path(scan_dir) / "out").is_dir():
            record_run(scan, run_choices(scan, mesh=mesh, rig=rig,
                                         calibration_error=calibration_error))


def _calibrate_first(scan, scan_dir, mesh, settings, from_stage, only, until, progress,
                     on_stage) -> tuple[list[StageResult], str | None]:
    """Run (or find cached) the ``calibrate`` stage of a ``rig="auto"`` run; return its
    results and its recorded failure (None when it succeeded or is not run now).

    A run with ``--only`` another stage, or one that stops before any stage that needs the
    rig (``until="decode"``), does not calibrate: the failure is read from the calibration's
    products on disk, if any.
    """
    needs = "calibrate" in reconstruct_pipeline(scan, mesh=mesh, rig="auto").stages_run(
        until=until)
    if (only is not None and only != "calibrate") or (only is None and not needs):
        try:
            doc = json.loads((scan.out_dir / "calibrate" / "stage.json").read_text("utf-8"))
            error = doc.get("metrics", {}).get("error")
        except (OSError, ValueError, AttributeError):
            error = None
        return [], error if isinstance(error, str) else None
    first = reconstruct_pipeline(scan, mesh=mesh, rig="auto", until="calibrate")
    given = {k: v for k, v in (settings or {}).items() if k == "calibrate"}
    done = first.run(scan_dir, settings=given, until="calibrate", progress=progress,
                     on_stage=on_stage, from_stage="calibrate" if from_stage == "calibrate"
                     else None, only=only)
    error = next((r.metrics.get("error") for r in done if r.name == "calibrate"), None)
    return done, error if isinstance(error, str) else None


def run_diagnostic(scan_dir, *, progress: Callable[[str, int, int], None] | None = None,
                   on_stage: Callable[[StageResult], None] | None = None,
                   engine=None) -> list[StageResult]:
    """The stage-alone pass: the chain's stages after the calibration fed the generator's
    true rig and mesh (``rig="ground_truth"``, ``mesh="ground_truth"``), cached in
    ``out/diagnostic/`` (:data:`DIAGNOSTIC_DIR`, its own ``metrics.json``) beside the chain's
    ``out/``; the report shows its figures beside the chain's.

    Its novel views are the chain's (``out/render/``), moved into the generator's frame by the
    evaluation's gauge alignment (:func:`facegeo.evaluate.gauge.chain_views_in_truth`): the
    two passes are compared with the same reference images, which the evaluation renders once
    (:data:`facegeo.evaluate.evaluation.REFERENCE_CACHE`) — run it after the chain.

    Parameters
    ----------
    scan_dir : path-like or facegeo.capture.scan.Scan
        A synthetic scan (one with a ground-truth rig and mesh).
    progress, on_stage, engine
        As for :func:`run_reconstruct`.

    Raises
    ------
    InputError
        The scan has no ground-truth rig or mesh (a real capture: no diagnostic pass).
    """
    from facegeo.capture.scan import Scan, load_scan

    scan = scan_dir if isinstance(scan_dir, Scan) else load_scan(scan_dir)
    if "mesh" not in scan.ground_truth_keys:
        raise InputError(f"diagnostic pass: scan {scan.root} has no ground-truth mesh")
    from facegeo.evaluate.gauge import chain_views_in_truth

    # the chain's own views, in the generator's frame: both passes then meet the same
    # reference images (rendered once); before the chain rendered, the default orbits
    views = chain_views_in_truth(scan, scan.out_dir)
    pipeline = reconstruct_pipeline(scan, mesh="ground_truth", rig="ground_truth",
                                    engine=engine, diagnostic=True, views=views)
    results = pipeline.run(scan.root, progress=progress, on_stage=on_stage)
    from facegeo.fsutil import atomic_write_text
    from facegeo.pipeline.cache import record_metrics

    out = scan.root / pipeline.out_name
    choices = {"rig": "ground_truth", "mesh": "ground_truth",
               "world": "the generator's (ground_truth/rig.json)"}
    (out / RUN_RECORD).mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / RUN_RECORD / "run.json", json.dumps(choices, indent=2) + "\n")
    record_metrics(out, RUN_RECORD, choices)
    return results
