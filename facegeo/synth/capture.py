"""Synthetic light-stage capture: writes a scan directory exactly as a real rig would.

``generate_scan(out, preset="small")`` builds (or loads) a head, a ground-truth skin field and a
rig, then renders and writes, per camera:

* ChArUco board views seen by every camera at once (stereo) and close, image-filling views of
  each camera (intrinsics; :func:`facegeo.synth.boards.rig_calibration_views`), 8-bit sRGB PNG
  (on request a plain chessboard or a circle grid instead: ``calib_board``);
* the board under every structured-light pattern at a few poses (projector calibration);
* structured-light frames of the head (white/black, Gray code with inverse frames, phase
  shift), with projector shadows and camera occlusion traced by Embree, 8-bit sRGB PNG — on
  request Gray code only, a projector the cameras out-resolve, frames a camera lost
  (:mod:`facegeo.synth.sl_conditions`);
* one OLAT frame per light of the light stage in light-index order (the paper's capture order:
  θ fastest), linear EXR;
* ``ground_truth/``: mesh, rig, skin field (re-evaluable anywhere), per-vertex parameters,
  per-camera geometry, reference renders including novel viewpoints.

Frames are rendered and written one at a time, so memory stays bounded at any preset.
"""

from __future__ import annotations

import contextlib
import json
import logging
import numbers
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from facegeo import fsutil
from facegeo.errors import InputError
from facegeo.frames import look_at
from facegeo.checks import fmt_value
from facegeo.synth.boards import (
    BOARD_KINDS,
    board_for_cameras,
    calibration_board_poses,
    rig_calibration_views,
)
from facegeo.synth.rigs import (  # noqa: F401  (re-exported: capture's public names)
    LIGHT_PERTURBATION,
    PROJECTOR_VIEW_MAX_ANGLE_DEG,
    RIG_PERTURBATION,
    RING_BAND,
    WITNESS_ANGLE_DEG,
    WITNESS_ENV,
    WITNESS_ENV_HEIGHT,
    WITNESS_NAME,
    WITNESS_SUPERSAMPLE,
    _with_witness,
    perturbed_lights,
    perturbed_rig,
    projector_view_cameras,
    ring_cameras,
    witness_camera,
    witness_weights,
)
from facegeo.synth.sl_conditions import (
    camera_px_per_projector_px,
    check_projector_scale,
    check_sl_phase_steps,
    projector_coordinates,
    projector_size_for_scale,
    resolve_lost_frames,
    shared_code_fraction,
)

log = logging.getLogger(__name__)

__all__ = ["Preset", "PRESETS", "RING_BAND", "generate_scan", "SynthSummary", "build_rig",
           "build_head", "frame_rig", "face_fill", "ring_cameras", "perturbed_lights",
           "witness_camera"]


@dataclass(frozen=True)
class Preset:
    """Size of a synthetic capture.

    Attributes
    ----------
    name : str
    camera_scale : float
        Camera images relative to the default rig's 480 × 720.
    n_theta, n_phi : int
        Light-stage grid.
    head_subdivisions : int
        Procedural head resolution (icosphere subdivisions).
    projector_size : (int, int)
        Projector (width, height) in pixels.
    calib_views, projector_views : int
        Board poses for camera calibration / seen under the patterns for projector calibration.
    phase_steps : int
        Phase-shift frames per axis (0: none).
    olat_half : bool
        Store OLAT frames as float16 EXR (float32 otherwise).
    sl_supersample : int
        Structured-light frames integrate s × s rays per pixel (a box-filtered pixel, so
        stripes finer than a pixel blur as they would on a sensor); OLAT frames and the
        reference renders sample the pixel centre exactly.
    projector_tilt_deg : (float, float)
        Range of the board's tilt in the projector-calibration views, degrees from the
        targeted camera's axis.
    projector_views_shared : bool
        Every projector-calibration view is seen whole by every camera and the projector,
        where the cameras' axes meet (default). False: view k is placed for camera ``k mod
        C`` alone and the projector — pushed toward that camera's image corners and at the
        distance where it fills ``projector_fill`` of its image — so the views cover more of
        the projector's image and a range of depths (what pins a projector's focal length and
        principal point; the other cameras may see part of the board or none).
    projector_fill : (float, float)
        Fraction of the targeted camera's image the board spans in unshared projector views.
    n_cameras : int
        Capture cameras. 0 (default): the default rig's two cameras
        (:func:`facegeo.geometry.rig.default_rig`), so the presets' draws are unchanged; N > 0:
        N cameras on a band around the head (:func:`ring_cameras`), every one aimed at the head
        centre and seeing the face or the side of the head (a modern multi-camera stage,
        issue 38).
    corner_views : int
        Corner calibration views per camera (:func:`facegeo.synth.boards.rig_calibration_views`
        ``corner_per_camera``; :data:`facegeo.synth.boards.CORNER_VIEWS`): boards pushed into
        each image corner in turn, after the shared and close views, whose draws they leave
        unchanged. 0 (default): none.
    """

    name: str
    camera_scale: float
    n_theta: int
    n_phi: int
    head_subdivisions: int
    projector_size: tuple[int, int]
    calib_views: int
    projector_views: int
    phase_steps: int = 3
    olat_half: bool = True
    sl_supersample: int = 3
    projector_tilt_deg: tuple[float, float] = (20.0, 40.0)
    projector_views_shared: bool = True
    projector_fill: tuple[float, float] = (0.6, 0.85)
    n_cameras: int = 0
    corner_views: int = 0


PRESETS: dict[str, Preset] = {
    "tiny": Preset("tiny", 1 / 6, 16, 8, 4, (256, 192), 3, 1, 3, olat_half=False),
    "small": Preset("small", 1 / 2, 32, 16, 5, (512, 384), 30, 4, 3),
    "paper": Preset("paper", 1.0, 64, 32, 6, (1024, 768), 30, 6, 3, sl_supersample=2),
    # A modern multi-camera stage (issue 38): 16 cameras x 512 lights (16 x 32) at 80 x 120 px,
    # so its 8,192 OLAT frames stay small (16 x 512 x 80 x 120 x RGB float16: 0.47 GB in
    # memory as one field; docs/synth.md, Presets).
    "modern": Preset("modern", 1 / 6, 16, 32, 4, (256, 192), 6, 1, 3, n_cameras=16),
    # The same 16-camera band with 8 x 4 lights and one shared calibration view: the test size.
    "modern_tiny": Preset("modern_tiny", 1 / 6, 8, 4, 4, (256, 192), 1, 1, 3, olat_half=False,
                          sl_supersample=1, n_cameras=16),
}

#: Bounding-box diagonal a head mesh must have once converted to metres (a real head is
#: ≈ 0.3–0.45 m; a face-only mesh ≈ 0.2 m). Outside this the --units are almost surely wrong.
HEAD_DIAGONAL_RANGE_M = (0.1, 1.0)

#: Exposure of 16-bit PNG OLAT frames (pixel = radiance × exposure before the sRGB curve): a
#: white Lambertian surface facing a light (radiance 1/π) encodes at ≈ 0.64 of full scale.
OLAT_PNG_EXPOSURE = 2.0

#: Brightest linear value of a projector-calibration view's white frame: a view that would
#: exceed it at the capture's exposure is exposed less (clipped whites bias the fringes' phase
#: and the board's corners; the default, shared views at the head's distance stay below it).
PROJECTOR_VIEW_PEAK = 0.9


@dataclass
class SynthSummary:
    """What :func:`generate_scan` wrote, with timings."""

    root: Path
    preset: str
    n_cameras: int
    n_lights: int
    image_size: tuple[int, int]
    n_faces: int
    frames_written: int = 0
    seconds: dict = field(default_factory=dict)
    #: Files of the replaced scan that facegeo had not written, carried into the new one
    #: (relative paths; ``PATH.keep`` where the new scan writes the same path).
    kept: list = field(default_factory=list)
    #: The projector's (width, height), pixels (the preset's unless ``projector_scale``).
    projector_size: tuple | None = None
    #: Camera → structured-light frames left unwritten and declared missing (``sl_missing``).
    sl_missing: dict = field(default_factory=dict)

    @property
    def frames_per_second(self) -> float:
        t = sum(self.seconds.values())
        return self.frames_written / t if t > 0 else float("nan")


# ---------------------------------------------------------------------------- building blocks


def build_head(head: str = "procedural", *, units: str = "cm", subdivisions: int = 5, seed: int = 0):
    """The ground-truth head mesh: ``"procedural"`` or a path to a mesh file (OBJ/PLY/GLB).

    A mesh file whose facial landmarks are known (:func:`facegeo.synth.head.real_face_landmarks`)
    is moved so the rig frames its face (:func:`facegeo.synth.head.frame_face`);
    ``metadata["face_landmarks"]`` then holds the landmarks in the final frame. Every mesh
    gets ``metadata["part_labels"]`` (per face, :data:`facegeo.synth.head.PART_NAMES`).
    """
    from facegeo.synth.head import (frame_face, load_head_mesh, part_labels, procedural_head,
                                    real_face_landmarks)

    if head == "procedural":
        mesh = procedural_head(subdivisions, seed=seed)
        mesh.metadata["part_labels"] = part_labels(mesh)
        return mesh
    p = Path(head)
    if not p.exists():
        raise InputError(f"--head: no such mesh file {p} (use 'procedural' or a path)")
    mesh = load_head_mesh(p, units=units)
    diag = float(np.linalg.norm(np.ptp(np.asarray(mesh.vertices), axis=0)))
    lo, hi = HEAD_DIAGONAL_RANGE_M
    if not lo <= diag <= hi:
        raise InputError(
            f"--head {p}: with --units {units} the mesh's bounding-box diagonal is {diag:.3g} m, "
            f"outside the {lo}–{hi} m of a head; check --units (cm, mm or m)"
        )
    mesh.metadata["part_labels"] = part_labels(mesh)
    landmarks = real_face_landmarks(mesh)
    if landmarks is None:
        log.warning("%s: no facial landmarks (no %s beside it, not an ICT FaceKit or MediaPipe "
                    "face): skin regions fall back to bounding-box placement", p,
                    p.with_name(p.stem + ".landmarks.json").name)
    else:
        frame_face(mesh, landmarks)
        mesh.metadata["face_landmarks"] = landmarks
    return mesh


def build_rig(preset: Preset):
    """The nominal default rig (paper-shaped) resized to the preset; with
    ``preset.n_cameras`` > 0 its two cameras replaced by :func:`ring_cameras`."""
    from facegeo.geometry.rig import Rig, default_rig

    rig = default_rig()
    if preset.n_cameras:
        rig = Rig(cameras=ring_cameras(preset.n_cameras), projector=rig.projector,
                  lights=rig.lights)
    if preset.camera_scale != 1.0:
        rig = rig.scaled(preset.camera_scale)
    proj = rig.projector
    if proj is not None and (proj.width, proj.height) != tuple(preset.projector_size):
        s = preset.projector_size[0] / proj.width
        if abs(proj.height * s - preset.projector_size[1]) > 1e-9:
            raise InputError("projector_size must keep the default projector's aspect ratio")
        proj = proj.scaled(s)
    lights = replace(rig.lights, n_theta=preset.n_theta, n_phi=preset.n_phi)
    return Rig(cameras=list(rig.cameras), projector=proj, lights=lights)


def _build_rigs(preset: Preset, mesh, seed: int):
    """The nominal rig (:func:`build_rig`, framed on a real face) and the true one
    (:func:`perturbed_rig`), with which every frame is rendered."""
    nominal_rig = build_rig(preset)
    if mesh.metadata.get("face_landmarks") is not None:  # a real face: fill the frame with it
        nominal_rig = frame_rig(nominal_rig, mesh.metadata["face_landmarks"])
    return nominal_rig, perturbed_rig(nominal_rig, seed)


def _rescale_projector(preset: Preset, projector_scale: float, renderer, mesh, seed: int):
    """The preset, nominal and true rigs with a projector whose pixel spans ``projector_scale``
    camera pixels on the head, and what was measured.

    The ratio of the preset's projector is measured on the true rig's cameras
    (:func:`facegeo.synth.sl_conditions.camera_px_per_projector_px`, averaged over cameras),
    the projector resized (:func:`facegeo.synth.sl_conditions.projector_size_for_scale`) and
    the rigs rebuilt: the cameras, and the seeded errors' draws, are the same. Returns
    ``(preset, nominal_rig, rig, info)``, ``info`` the ``scan.metadata.projector_scale`` entry.
    """
    def measure(rig):
        qs = {c.name: projector_coordinates(renderer.surface_view(c), rig.projector)
              for c in rig.cameras}
        return qs, {n: camera_px_per_projector_px(q) for n, q in qs.items()}

    _, rig = _build_rigs(preset, mesh, seed)
    _, ratio = measure(rig)
    size = projector_size_for_scale(preset.projector_size, float(np.mean(list(ratio.values()))),
                                    projector_scale)
    preset = replace(preset, projector_size=size)
    nominal_rig, rig = _build_rigs(preset, mesh, seed)
    qs, ratio = measure(rig)
    info = {"requested": projector_scale, "projector_size": list(size),
            "camera_px_per_projector_px": ratio,
            "shared_code_fraction": {n: shared_code_fraction(q) for n, q in qs.items()}}
    log.info("projector_scale %s: a %d x %d projector, %s camera px per projector px, codes "
             "shared by %s", projector_scale, *size,
             ", ".join(f"{v:.2f}" for v in ratio.values()),
             ", ".join(f"{v:.3f}" for v in info["shared_code_fraction"].values()))
    return preset, nominal_rig, rig, info


def _board_for_rig(rig, kind: str = "charuco"):
    """A ChArUco board whose 5 squares span ~60 % of the narrowest camera view at the head, as
    tall as that image allows, or a chessboard or circle grid on its sheet
    (:func:`facegeo.synth.boards.board_for_cameras`)."""
    return board_for_cameras(rig.cameras, kind=kind)


def _novel_cameras(rig) -> list:
    """Viewpoints the light stage's cameras never saw, for novel-view ground truth."""
    from facegeo.geometry.camera import Camera

    ref = rig.cameras[0]
    out = []
    for name, eye in (("novel_front", (0.0, 0.03, 1.1)), ("novel_three_quarter", (-0.75, 0.12, 0.8)),
                      ("novel_low", (0.25, -0.45, 1.0))):
        T = look_at(np.array(eye), np.zeros(3))
        out.append(Camera(name=name, width=ref.width, height=ref.height, K=ref.K.copy(),
                          dist=np.zeros(5), T_cam_world=T))
    return out


# ---------------------------------------------------------------------------- main entry


def generate_scan(
    out: str | Path,
    preset: str | Preset = "small",
    *,
    head: str = "procedural",
    units: str = "cm",
    seed: int = 0,
    noise: float = 0.0,
    skin: str = "regional",
    olat_format: str = "exr",
    overwrite: bool = False,
    progress: Callable[[str, int, int], None] | None = None,
    sl_effects=None,
    sl_codes=("gray",),
    sl_phase_steps: int | None = None,
    projector_scale: float | None = None,
    sl_missing: dict[str, list[str] | str] | None = None,
    calib_board: str = "charuco",
    witness: bool = False,
    light_error_deg: float = 0.0,
    backdrop: float = 0.0,
) -> SynthSummary:
    """Synthesise a light-stage capture into the scan directory ``out``.

    Parameters
    ----------
    out : path
        Scan directory to create: a new path, an empty directory, or (with ``overwrite``) a
        synthetic scan to replace. A symlink to a directory is followed (the scan is written
        where it points).
    preset : {"tiny", "small", "paper"} or Preset
        Capture size (see :data:`PRESETS`).
    head : str
        ``"procedural"`` or a mesh path (OBJ/PLY/GLB, +Y up, facing +Z).
    units : {"cm", "mm", "m"}
        Units of a mesh file.
    seed : int
        Seeds the head details, skin field, board poses and noise.
    skin : str
        Diffuse colour model of the ground-truth skin field: ``"regional"`` (a parametric
        linear-sRGB skin colour with regional variation) or ``"spectral"`` /
        ``"spectral:<type>"`` (Donner & Jensen 2006 albedo from smooth maps of melanin and
        haemoglobin, ``<type>`` one of ``facegeo.appearance.spectral.SKIN_TYPES``, default medium).
    olat_format : {"exr", "png16"}
        OLAT frames as linear EXR (float16 or float32 per preset) or as 16-bit PNG through the
        sRGB response with exposure :data:`OLAT_PNG_EXPOSURE` (highlights above the white level
        clip and are masked on load, as on a real sensor).
    noise : float
        Sensor noise σ as a fraction of the frame's white level (0: noise-free): read noise
        σ·white plus photon noise σ·√(white·signal), i.e. σ·white·√(1 + signal/white).
    overwrite : bool
        Replace an existing **synthetic** scan at ``out`` (see *Data safety*).
    progress : callable(stage, done, total), optional
        Called as work proceeds, with stages ``"calib"``, ``"calib.projector"``,
        ``"structured_light"``, ``"olat"``, ``"ground_truth"`` and, with ``witness``,
        ``"reference"`` (the CLI draws one progress bar per stage).
    sl_effects : facegeo.synth.sl_effects.SkinEffects or dict, optional
        Subsurface blur and interreflection in the structured-light frames (default: sharp,
        direct-only frames); recorded in ``scan.metadata.sl_effects``.
    sl_codes : sequence of {"gray", "xor02", "xor04", "minsw"}
        Code families the projector shows, each a full set of bit planes (Gupta et al. 2013's
        ensemble of codes; :class:`facegeo.geometry.structured_light.PatternSpec`); recorded in
        the scan's ``[structured_light.patterns]`` and decoded with a consistency vote.
    sl_phase_steps : int, optional
        Phase-shift frames per axis, overriding the preset's ``phase_steps`` (3): 0 projects
        Gray code only (with inverse frames, white and black), as real Gray-code scanners do.
    projector_scale : float, optional
        Resize the projector so one projector pixel spans about ``projector_scale`` camera
        pixels on the face, linear (the median over each camera's head pixels, averaged over the
        cameras; :mod:`facegeo.synth.sl_conditions`): 4 makes cameras that out-resolve the
        projector, many camera pixels sharing one code (issue 34). Default: the preset's
        ``projector_size`` (at ``tiny`` ≈ 0.75 camera pixels per projector pixel). The size
        chosen and the measured ratio and code sharing are recorded in
        ``scan.metadata.projector_scale``.
    sl_missing : dict of str to (list of str or str), optional
        Structured-light frames a camera lost: camera name → frame names, or the name of a
        set in :data:`facegeo.synth.sl_conditions.LOST_FRAME_PATTERNS` (``"issue34"``: the last
        column bit's pattern frame, both frames of the second-to-last row bit and the last row
        bit's inverse). Those frames are not written and are declared in
        ``[structured_light.cameras.<camera>] missing``; every other frame is the one the full
        scan has (noise is drawn for the lost frames too).
    calib_board : {"charuco", "chessboard", "circles"}
        The calibration board of the camera and projector views (the scan has one
        ``calib.board``): a ChArUco board (default), a plain chessboard or an asymmetric circle
        grid printed on the same sheet (:func:`facegeo.synth.boards.board_for_cameras`). The
        plain boards are the common projector–camera set-up: found in each projector view's
        white frame, under the projector's full light.
    witness : bool
        Add a calibration-only camera :data:`WITNESS_NAME` (``"witness"``) at a viewpoint the
        capture cameras do not share (:func:`witness_camera`: 40° from each, above the face),
        in ``rig.json`` (nominal) and ``ground_truth/rig.json`` (with its own seeded errors,
        like the others). It sees the camera-calibration board views (``[calib]``, so the
        calibrated rig places it) and declares every projector-view, structured-light and
        OLAT frame missing (``[<group>.cameras.witness] missing``). Its reference image — the
        true head under :data:`WITNESS_ENV` through the true witness camera, Eq. (4) with the
        render stage's weights (:func:`witness_weights`), :data:`WITNESS_SUPERSAMPLE`² rays per
        pixel, linear float32 EXR — is written to ``reference/witness_axis_lobes.exr`` and
        declared as ``[reference] images.witness.axis_lobes``. The capture cameras' frames
        differ from the scan without it (the shared board views must also be seen whole by
        the witness), not their rig.
    light_error_deg : float
        Light-stage calibration error (1 σ, degrees per tangent axis) in the scan's nominal
        light list (:func:`perturbed_lights`; :data:`LIGHT_PERTURBATION` suggests 0.5° with
        5 mm of distance): ``rig.json``'s lights become that list, ``ground_truth/rig.json``
        keeps the exact grid every frame is rendered with (the frames do not change). 0
        (default): ``rig.json`` has the exact grid, as before.
    backdrop : float
        Albedo of a matte backdrop behind the head, facing each camera, in the OLAT frames: a
        pixel that sees no head records ``backdrop / π · color · max(0, ω_l · v)`` under light
        ``l`` (``ω_l`` the light's direction from the stage centre, ``v`` the camera's; before
        the noise), where a light stage's dark cloth or a real capture's floor and walls glow
        faintly (DiLiGenT's objects stand on a background at 5–10 % of their own level:
        ``0.04`` is like it). 0 (default): a black background. The structured-light and board
        frames keep theirs (the projector's patterns fall on the head alone); the ground
        truth's uniform-environment renders are the head's alone. Recorded in
        ``scan.metadata.backdrop``.

    Returns
    -------
    SynthSummary

    Raises
    ------
    InputError
        An invalid argument (an unknown camera or frame in ``sl_missing`` lists the valid
        ones); ``out`` is a file, not writable, a non-empty directory without a
        manifest, a real capture (its ``scan.toml`` lacks ``scan.synthetic = true``), or a
        scan and ``overwrite`` is false. Raised before anything is written.

    Notes
    -----
    Data safety. Every argument is validated, and the head, rig and skin field are built,
    before anything touches the disk. The scan is written into a sibling directory
    ``.OUT.facegeo-tmp-PID-XXXX`` with a record of every file written
    (:data:`facegeo.fsutil.WRITTEN_RECORD`, ``OUT/.facegeo-written``). Only when it is complete
    are the files of the old scan that facegeo did not write (per the old record; for a scan
    from before the record, per its manifest) hard-linked into it, the old directory renamed
    aside, the new one renamed to ``OUT`` and the old tree deleted, never following a symlink.
    An exception or Ctrl-C at any point removes the temporary directory (and any parent
    directories this call created) and leaves the old scan as it was; leftovers of a killed
    run are cleaned up (or an old scan restored) by the next run on the same ``OUT``.
    """
    from facegeo.geometry.structured_light import PatternSpec, pattern_names
    from facegeo.synth.render import ReferenceRenderer
    from facegeo.synth.skin import SkinField

    # 1. Validate every argument and the destination; nothing on disk is touched yet.
    preset, skin_kwargs, root = _validate_arguments(
        out, preset, head=head, units=units, seed=seed, noise=noise, skin=skin,
        olat_format=olat_format, progress=progress)
    if calib_board not in BOARD_KINDS:
        raise InputError(f"calib_board: unknown {fmt_value(calib_board)}; expected one of "
                         f"{', '.join(BOARD_KINDS)}")
    if sl_effects is not None:
        from facegeo.synth.sl_effects import SkinEffects

        if not isinstance(sl_effects, SkinEffects):
            if not isinstance(sl_effects, dict):
                raise InputError(f"sl_effects: expected a SkinEffects or a dict, got "
                                 f"{type(sl_effects).__name__}")
            sl_effects = SkinEffects.from_dict(sl_effects)
    if not isinstance(witness, bool):
        raise InputError(f"witness: expected True or False, got {fmt_value(witness)}")
    if light_error_deg:  # validated here, before anything is built
        perturbed_lights(build_rig(preset).lights, seed, light_error_deg)
    if (isinstance(backdrop, bool) or not isinstance(backdrop, numbers.Real)
            or not 0.0 <= float(backdrop) <= 1.0):
        raise InputError(f"backdrop: expected an albedo in [0, 1], got {fmt_value(backdrop)}")
    backdrop = float(backdrop)
    projector_scale = check_projector_scale(projector_scale)
    sl_phase_steps = check_sl_phase_steps(sl_phase_steps)
    if sl_phase_steps is not None:
        preset = replace(preset, phase_steps=sl_phase_steps)
    _replaceable_files(root, overwrite=overwrite)  # read-only: refuse a real capture at once
    tick = progress or (lambda stage, done, total: None)
    seconds: dict[str, float] = {}

    # 2. Everything that can fail on bad input and needs no disk: the head (a bad mesh or wrong
    #    --units fails here), rig, skin field, renderer, board.
    t0 = time.perf_counter()
    mesh = build_head(head, units=units, subdivisions=preset.head_subdivisions, seed=seed)
    # Ground truth is stored as PLY with float32 vertices: render exactly that geometry, so the
    # mesh in ground_truth/ reproduces every frame bit for bit.
    mesh.vertices = np.asarray(mesh.vertices, np.float32).astype(np.float64)
    nominal_rig, rig = _build_rigs(preset, mesh, seed)
    landmarks = mesh.metadata.get("face_landmarks")
    if landmarks is not None:  # a real face: regions on its landmarks
        skin_field = SkinField.for_landmarks(landmarks, seed=seed, **skin_kwargs)
    else:
        skin_field = SkinField.for_mesh(mesh, seed=seed, **skin_kwargs)
    renderer = ReferenceRenderer.from_mesh(mesh, skin_field, parts=mesh.metadata["part_labels"])
    metadata = {}
    if backdrop > 0:
        metadata["backdrop"] = backdrop
    if projector_scale is not None:  # cameras that out-resolve the projector (issue 34)
        preset, nominal_rig, rig, metadata["projector_scale"] = _rescale_projector(
            preset, projector_scale, renderer, mesh, seed)
    board = _board_for_rig(rig, calib_board)
    calibration_only: tuple[str, ...] = ()
    if witness:  # a calibration-only camera (issue 37): after the board, sized on the others
        nominal_rig, rig = _with_witness(nominal_rig, rig, seed)
        calibration_only = (WITNESS_NAME,)
    if light_error_deg:  # the owner's light list, off by a calibration error (issue 37)
        from facegeo.geometry.rig import Rig

        nominal_rig = Rig(cameras=nominal_rig.cameras, projector=nominal_rig.projector,
                          lights=perturbed_lights(rig.lights, seed, light_error_deg))
    spec = PatternSpec(width=rig.projector.width, height=rig.projector.height,
                       phase_steps=preset.phase_steps, codes=sl_codes)
    sl_names = pattern_names(spec)
    lost = resolve_lost_frames(sl_missing, [c.name for c in rig.cameras
                                            if c.name not in calibration_only], sl_names, spec)
    seconds["setup"] = time.perf_counter() - t0

    # 3. Tidy leftovers of a killed run, then decide what the old directory holds (refusing a
    #    real capture) — still without modifying anything of it.
    fsutil.clean_stale_siblings(root)
    ours = _replaceable_files(root, overwrite=overwrite)

    # 4. Write the new scan into a sibling directory; swap it in only when complete.
    created_parents = _make_parents(root.parent)
    tmp = None
    try:
        tmp = fsutil.staging_dir(root, "tmp")
        frames = _write_scan(
            tmp, name=root.name, preset=preset, head=head, skin=skin, seed=seed, noise=noise,
            olat_format=olat_format, mesh=mesh, nominal_rig=nominal_rig, rig=rig,
            skin_field=skin_field, renderer=renderer, board=board, spec=spec,
            sl_names=sl_names, tick=tick, seconds=seconds, sl_effects=sl_effects, lost=lost,
            metadata=metadata, calibration_only=calibration_only, backdrop=backdrop)
        fsutil.write_written_record(tmp, fsutil.list_files(tmp))
        carried: list[str] = []
        if ours is not None:
            carried = fsutil.carry_over(root, tmp, ours)
        fsutil.swap_in_dir(tmp, root)
        tmp = None
    except BaseException:
        if tmp is not None:
            fsutil.remove_tree(tmp)
        for d in created_parents:  # deepest first; only if still empty
            with contextlib.suppress(OSError):
                d.rmdir()
        raise
    if carried:
        log.info("kept %d file(s) facegeo did not write: %s", len(carried),
                 ", ".join(carried[:10]) + (" ..." if len(carried) > 10 else ""))
    return SynthSummary(root=root, preset=preset.name, n_cameras=len(rig.cameras),
                        n_lights=rig.lights.n_lights, image_size=(rig.cameras[0].width,
                                                                  rig.cameras[0].height),
                        n_faces=len(mesh.faces), frames_written=frames, seconds=seconds,
                        kept=carried, projector_size=(rig.projector.width, rig.projector.height),
                        sl_missing=lost)


def _backdrop_glow(renderer, cam, lights, backdrop: float):
    """``(background mask (H, W), per-light RGB level (L, 3) float32)`` of a matte backdrop of
    albedo ``backdrop`` facing camera ``cam`` (:func:`generate_scan` ``backdrop``), or None."""
    if backdrop <= 0:
        return None
    bg = ~renderer.surface_view(cam).mask
    v = np.asarray(cam.center_world, float) - np.asarray(lights.center, float)
    v /= np.linalg.norm(v)
    d = np.asarray(lights.directions, float)
    cos = np.clip((d / np.linalg.norm(d, axis=1, keepdims=True)) @ v, 0.0, None)
    level = backdrop / np.pi * cos[:, None] * np.asarray(lights.color, float)[None, :]
    return bg, level.astype(np.float32)


def _write_scan(root: Path, *, name, preset, head, skin, seed, noise, olat_format, mesh,
                nominal_rig, rig, skin_field, renderer, board, spec, sl_names, tick,
                seconds, sl_effects=None, lost=None, metadata=None,
                calibration_only=(), backdrop: float = 0.0) -> int:
    """Render and write a whole scan into the (empty, staging) directory ``root``; the manifest
    goes last. Returns the number of frames written.

    ``lost``: camera → structured-light frames not written (declared missing); ``metadata``:
    entries for ``scan.metadata``; ``calibration_only``: names of cameras that see only the
    camera-calibration views (every other group's frames declared missing) and get reference
    images (:data:`WITNESS_ENV`); ``backdrop``: the OLAT frames' background albedo
    (:func:`generate_scan`)."""
    from facegeo.capture import imageio, scan as scanmod
    from facegeo.geometry.board import render_board, save_board
    from facegeo.geometry.structured_light import pattern_value_at
    from facegeo.synth.render import _ordered_map

    rng = np.random.default_rng(seed)
    frames = 0

    manifest = scanmod.new_manifest(name, synthetic=True)
    manifest["scan"]["description"] = (
        f"facegeo synthetic capture, preset {preset.name}, head {head}, skin {skin}, seed {seed}, "
        f"noise {noise}"
    )
    if metadata:
        manifest["scan"].setdefault("metadata", {}).update(metadata)
    nominal_rig.save(root / manifest["scan"]["rig"])
    lost = lost or {}
    noise_rng = np.random.default_rng([seed, 1])

    def _noisy(img, white):
        # read noise σ = noise·white plus photon noise σ = noise·√(white·signal) (equal to the
        # read noise at the white level): σ_total = noise·white·√(1 + signal/white)
        if noise <= 0:
            return img
        sigma = noise * white * np.sqrt(1.0 + np.clip(img / white, 0, None))
        return img + (sigma * noise_rng.standard_normal(img.shape)).astype(np.float32)

    def _write_srgb(path, img, stage):
        # one 8-bit sRGB frame with the capture noise (drawn in frame order), counted for the
        # progress of ``stage``
        nonlocal frames, done
        imageio.write_image(path, imageio.encode(_noisy(img, 1.0), "srgb", np.uint8))
        frames += 1
        done += 1
        tick(stage, done, n_total)

    # ---- calibration: board views seen by all cameras at once, then close views of each
    #      camera (boards.rig_calibration_views) ----
    t0 = time.perf_counter()
    board_path = root / "calib" / "board.json"
    save_board(board, board_path)
    poses = rig_calibration_views(board, rig.cameras, preset.calib_views, rng,
                                  corner_per_camera=preset.corner_views)
    calib_files = scanmod.DEFAULT_FILES["calib"]
    exposure = 3.0  # maps a white board under unit irradiance (0.85/π) to ≈ 0.81
    n_total = len(poses) * len(rig.cameras)
    done = 0

    def calib_frame(item):  # noise-free linear frame of one (view, camera), on a worker thread
        _, T_world_board, cam = item
        bv = render_board(board, cam, cam.T_cam_world @ T_world_board)
        img = exposure * (bv.reflectance / np.pi + 0.01)
        return np.repeat(img[..., None], 3, axis=2).astype(np.float32)

    # Board renders run ahead on two worker threads (up to four in flight) (numpy and OpenCV release the GIL); noise, encoding
    # and writing stay here, in frame order, so the noise stream is the same.
    views = [(vi, T, cam) for vi, T in enumerate(poses) for cam in rig.cameras]
    for (vi, _, cam), img in _ordered_map(calib_frame, views, workers=2):
        _write_srgb(scanmod.frame_path(root, calib_files, camera=cam.name, view=vi), img, "calib")
    manifest["calib"] = {"board": "calib/board.json", "response": "srgb", "views": len(poses),
                         "files": calib_files}

    # ---- projector calibration: the board under every pattern ----
    proj = rig.projector
    # the cameras that see the projector views: those near the projector's axis (all of the
    # default rig's; the middle of a ring; never a calibration-only camera)
    proj_cams = projector_view_cameras(rig, exclude=calibration_only)
    if preset.projector_views_shared:
        proj_poses = calibration_board_poses(board, proj_cams + [proj],
                                             preset.projector_views, rng, shared_every=1,
                                             tilt_deg=tuple(preset.projector_tilt_deg))
    else:  # one camera and the projector: more of the projector's image, more depths
        proj_poses = calibration_board_poses(board, proj_cams, preset.projector_views,
                                             rng, shared_every=0,
                                             tilt_deg=tuple(preset.projector_tilt_deg),
                                             fill=tuple(preset.projector_fill),
                                             also_seen_by=[proj])
    proj_files = scanmod.DEFAULT_FILES["calib.projector"]
    n_total = len(proj_poses) * len(proj_cams) * len(sl_names)
    done = 0
    def projector_view(item):  # the board seen by one camera, lit by the projector (a worker)
        _, T_world_board, cam = item
        n_board = T_world_board.R[:, 2] * -1.0  # printed side faces -z_board
        bv = render_board(board, cam, cam.T_cam_world @ T_world_board)
        p = bv.p_world[bv.mask]
        e_proj, q_proj = _projector_irradiance(proj, p, np.broadcast_to(n_board, p.shape))
        base = bv.reflectance[bv.mask] / np.pi
        return bv.mask, base, e_proj, q_proj

    views = [(vi, T, cam) for vi, T in enumerate(proj_poses) for cam in proj_cams]
    for (vi, _, cam), (mask, base, e_proj, q_proj) in _ordered_map(projector_view, views,
                                                                   workers=2):
        # a camera exposes a pose so that its white frame does not clip: a board nearer the
        # projector than the head is lit several times more (unshared views come to 0.5 m)
        peak = float((base * (e_proj + 0.02)).max()) if base.size else 0.0
        gain = exposure if exposure * peak <= PROJECTOR_VIEW_PEAK else PROJECTOR_VIEW_PEAK / peak
        for name in sl_names:
            pat = pattern_value_at(spec, name, q_proj)
            val = np.zeros(mask.shape, np.float32)
            val[mask] = gain * base * (e_proj * pat + 0.02)
            _write_srgb(scanmod.frame_path(root, proj_files, camera=cam.name, view=vi, frame=name),
                        np.repeat(val[..., None], 3, axis=2), "calib.projector")
    manifest["calib"]["projector"] = {"views": len(proj_poses), "files": proj_files}
    unseen = [c.name for c in rig.cameras if all(c is not p for p in proj_cams)]
    if unseen:  # cameras without projector views declare every view missing
        manifest["calib"]["projector"]["cameras"] = {
            c: {"missing": list(range(len(proj_poses)))} for c in unseen}
    seconds["calib"] = time.perf_counter() - t0

    # ---- structured light on the head ----
    t0 = time.perf_counter()
    sl_files = scanmod.DEFAULT_FILES["structured_light"]
    capture = [c for c in rig.cameras if c.name not in calibration_only]
    n_total = len(capture) * len(sl_names) - sum(len(v) for v in lost.values())
    done = 0
    from facegeo.synth.sl_effects import render_sl_frames

    for cam in capture:
        # the skin BRDF under the projector as a point light with Embree shadows, the pattern
        # modulating it per projector pixel (and, with sl_effects, blurred by subsurface
        # scattering and lifted by interreflection; synth.sl_effects)
        for name, img in render_sl_frames(renderer, spec, cam, projector=proj,
                                          supersample=preset.sl_supersample, exposure=exposure,
                                          ambient=0.02, effects=sl_effects):
            if name in lost.get(cam.name, ()):
                _noisy(img, 1.0)  # a lost frame: its noise is drawn, so the others are unchanged
                continue
            _write_srgb(scanmod.frame_path(root, sl_files, camera=cam.name, frame=name), img,
                        "structured_light")
    manifest["structured_light"] = {"response": "srgb", "projector": proj.name, "frames": sl_names,
                                    "files": sl_files, "patterns": spec.to_dict()}
    sl_gone = {c: list(f) for c, f in lost.items()}
    sl_gone.update({c: list(sl_names) for c in calibration_only})
    if sl_gone:
        manifest["structured_light"]["cameras"] = {c: {"missing": f} for c, f in sl_gone.items()}
    if sl_effects is not None:
        manifest["scan"].setdefault("metadata", {})["sl_effects"] = sl_effects.to_dict()
    seconds["structured_light"] = time.perf_counter() - t0

    # ---- OLAT ----
    t0 = time.perf_counter()
    olat_files = scanmod.DEFAULT_FILES["olat"]
    if olat_format == "png16":
        olat_files = olat_files.rsplit(".", 1)[0] + ".png"
    n_total = len(capture) * rig.lights.n_lights
    done = 0
    uniform_renders = {}
    solid = rig.lights.solid_angles
    for cam in capture:
        acc = np.zeros((cam.height, cam.width, 3), np.float64)
        glow = _backdrop_glow(renderer, cam, rig.lights, backdrop)
        for l, img in renderer.olat_images(cam, rig.lights):
            acc += solid[l] * img  # the uniform-environment reference (Eq. 4), noise-free
            if glow is not None:
                bg, level = glow
                img[bg] += level[l]
            img = _noisy(img, 0.5)
            path = scanmod.frame_path(root, olat_files, camera=cam.name, light=l)
            if olat_format == "png16":
                imageio.write_image(path, imageio.encode(np.clip(img * OLAT_PNG_EXPOSURE, 0, 1),
                                                         "srgb", np.uint16))
            else:
                imageio.write_image(path, img, half=preset.olat_half)
            frames += 1
            done += 1
            tick("olat", done, n_total)
        uniform_renders[cam.name] = acc.astype(np.float32)
    manifest["olat"] = {"response": "linear" if olat_format == "exr" else "srgb",
                        "exposure": 1.0 if olat_format == "exr" else OLAT_PNG_EXPOSURE,
                        "n_lights": rig.lights.n_lights, "light_order": "theta-fastest",
                        "files": olat_files}
    if calibration_only:
        manifest["olat"]["cameras"] = {c: {"missing": list(range(rig.lights.n_lights))}
                                       for c in calibration_only}
    seconds["olat"] = time.perf_counter() - t0

    # ---- ground truth ----
    t0 = time.perf_counter()
    gt = _write_ground_truth(root, mesh, rig, skin_field, renderer, uniform_renders,
                             tick=tick)
    manifest["ground_truth"] = gt
    seconds["ground_truth"] = time.perf_counter() - t0
    if calibration_only:
        t0 = time.perf_counter()
        manifest["reference"] = _write_witness_references(root, rig, renderer,
                                                          calibration_only, tick=tick)
        seconds["reference"] = time.perf_counter() - t0

    scanmod.write_manifest(root, manifest)
    return frames



def _write_witness_references(root: Path, rig, renderer, names, *, tick) -> dict:
    """The reference images of the calibration-only cameras ``names``: the true head through
    the true camera under :data:`WITNESS_ENV`, Eq. (4) (Debevec et al. 2000) over the true
    light stage with :func:`witness_weights`, :data:`WITNESS_SUPERSAMPLE`² rays per pixel,
    linear float32 EXR. Returns the ``[reference]`` table (``images.<camera>.<env>``, the key
    ``facegeo.evaluate.views.reference_image_key`` reads)."""
    from facegeo.capture import imageio

    w = witness_weights(rig.lights)
    images: dict = {}
    for k, name in enumerate(names):
        tick("reference", k, len(names))
        cam = rig.camera(name)
        img = renderer.render_lights(cam, rig.lights, w, supersample=WITNESS_SUPERSAMPLE)
        rel = f"reference/{name}_{WITNESS_ENV}.exr"
        imageio.write_image(root / rel, img.astype(np.float32), half=False)
        images[name] = {WITNESS_ENV: rel}
    tick("reference", len(names), len(names))
    return {"images": images}


# ---------------------------------------------------------------------------- data safety

#: How the generator marks the scans it may replace: ``scan.synthetic = true`` in the manifest.
SYNTHETIC_KEY = ("scan", "synthetic")


def _validate_arguments(out, preset, *, head, units, seed, noise, skin, olat_format, progress):
    """Check every argument of :func:`generate_scan` and the destination, touching nothing.

    Returns ``(preset, skin_kwargs, root)`` with ``root`` the absolute destination (a symlinked
    destination is resolved to its directory, so the scan stays where the link points).
    """
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise InputError(f"preset: unknown {fmt_value(preset)}; expected one of {', '.join(PRESETS)}")
        preset = PRESETS[preset]
    elif not isinstance(preset, Preset):
        raise InputError(f"preset: expected a preset name ({', '.join(PRESETS)}) or a Preset, "
                         f"got {type(preset).__name__}")
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise InputError(f"seed: expected an integer >= 0, got {fmt_value(seed)}")
    if (isinstance(noise, bool) or not isinstance(noise, numbers.Real)
            or not np.isfinite(float(noise)) or float(noise) < 0):
        raise InputError(f"noise: expected a finite number >= 0, got {fmt_value(noise)}")
    skin_kwargs = _skin_model(skin)
    if olat_format not in ("exr", "png16"):
        raise InputError(f"olat_format: unknown {fmt_value(olat_format)}; expected 'exr' or 'png16'")
    if units not in ("cm", "mm", "m"):
        raise InputError(f"units: unknown {fmt_value(units)}; expected one of 'cm', 'mm', 'm'")
    if not isinstance(head, (str, os.PathLike)):
        raise InputError(f"head: expected 'procedural' or a mesh path, got {type(head).__name__}")
    if head != "procedural":
        hp = Path(head)
        if not hp.exists():
            raise InputError(f"--head: no such mesh file {hp} (use 'procedural' or a path)")
        if not hp.is_file():
            raise InputError(f"--head: {hp} is not a file (expected a mesh: OBJ, PLY or GLB)")
        if not os.access(hp, os.R_OK):
            raise InputError(f"--head: cannot read {hp} (permission denied)")
    if progress is not None and not callable(progress):
        raise InputError("progress: expected a callable(stage, done, total) or None")
    if not isinstance(out, (str, os.PathLike)) or not os.fspath(out):
        raise InputError(f"out: expected a directory path, got {fmt_value(out)}")
    given = Path(os.path.abspath(out))
    if given.is_symlink():
        if not given.is_dir():
            raise InputError(f"{given}: a symlink that does not point to a directory; expected "
                             "a scan directory to create or replace")
        root = Path(os.path.realpath(given))
    else:
        root = given
    if root.parent == root:
        raise InputError(f"{root}: cannot write a scan at the file-system root")
    if root.exists() and not root.is_dir():
        raise InputError(f"{root}: exists and is not a directory; expected a scan directory "
                         "to create (or, with --overwrite, a synthetic scan to replace)")
    anc = root.parent
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise InputError(f"{anc}: is not a directory, so {root} cannot be created in it")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise InputError(f"{anc}: not writable; cannot create the scan {root} "
                         "(facegeo writes the new scan beside it, then swaps it in)")
    return preset, skin_kwargs, root


def _replaceable_files(root: Path, *, overwrite: bool) -> set[str] | None:
    """What the existing directory ``root`` may lose when a new scan replaces it.

    Returns None when ``root`` does not exist, an empty set for an empty directory, and for a
    synthetic scan (``overwrite`` only) the relative paths facegeo wrote there: its written
    record (:data:`facegeo.fsutil.WRITTEN_RECORD`) or, for a scan written before the record
    existed, the files its manifest describes. Everything else is carried over.

    Raises
    ------
    InputError
        ``root`` holds a scan and ``overwrite`` is false; it holds a real capture (manifest
        without ``scan.synthetic = true``) or files but no manifest; or its manifest cannot be
        read. Nothing is modified.
    """
    import tomllib

    if not root.exists():
        return None
    toml = root / "scan.toml"
    if not os.path.lexists(toml):
        with os.scandir(root) as it:
            if next(it, None) is None:
                return set()
        raise InputError(
            f"{root}: exists and holds files but no scan.toml (a capture in progress?); "
            "facegeo synth writes only a new or empty directory or replaces a synthetic scan")
    try:
        manifest = tomllib.loads(toml.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputError(f"{toml}: cannot read the manifest ({exc}), so it cannot be confirmed "
                         "synthetic; refusing to modify this scan") from exc
    section = manifest.get("scan")
    synthetic = section.get("synthetic") if isinstance(section, dict) else None
    if synthetic is not True:
        said = "scan.synthetic = false" if synthetic is False else "no scan.synthetic = true"
        raise InputError(
            f"{toml}: a real capture ({said}); facegeo synth never modifies a scan it did not "
            "synthesise; choose another output directory")
    if not overwrite:
        raise InputError(f"{root} already holds a scan (scan.toml); pass overwrite=True "
                         "(--overwrite) to replace it")
    try:
        ours = fsutil.read_written_record(root)
    except OSError as exc:
        raise InputError(f"{root / fsutil.WRITTEN_RECORD}: cannot read the record of the files "
                         f"facegeo wrote ({exc}); refusing to replace the scan") from exc
    if ours is None:
        ours = _files_in_manifest(root)
    return ours | {"scan.toml", fsutil.WRITTEN_RECORD}


def _files_in_manifest(root: Path) -> set[str]:
    """The relative paths a synthetic scan's manifest describes (rig, board, every frame,
    ground truth): what facegeo wrote in a scan from before the written record."""
    from facegeo.capture._scan_files import _format_template
    from facegeo.capture.scan import GROUPS, Scan, _read_manifest
    from facegeo.errors import FacegeoError

    try:
        scan = Scan(root, _read_manifest(root / "scan.toml"))
        m = scan.manifest
        rel = {m["scan"]["rig"]}
        if "calib" in m:
            rel.add(m["calib"]["board"])
        cams = scan.camera_names
        for group in GROUPS:
            if not scan.has(group):
                continue
            for cam in cams:
                rel.update(_expected_rel(scan, group, cam, _format_template))
        for key in scan.ground_truth_keys:
            flat = scan._gt[key]
            rel.add(flat)
            gdir = root / flat
            if gdir.is_dir() and not gdir.is_symlink():
                rel.update(f"{flat.rstrip('/')}/{f}" for f in fsutil.list_files(gdir))
    except (FacegeoError, OSError, KeyError, TypeError, ValueError) as exc:
        raise InputError(
            f"{root}: has no record of the files facegeo wrote ({fsutil.WRITTEN_RECORD}) and its "
            f"manifest cannot tell them apart from yours ({exc}); refusing to replace it: move "
            "your own files out and delete the scan by hand") from exc
    return {str(Path(r).as_posix()) for r in rel}


def _expected_rel(scan, group, camera, format_template):
    """``Scan.expected_files`` as relative POSIX strings, without resolving symlinks (a frame
    folder symlinked out of the scan must not make the old scan unreplaceable)."""
    sect = scan._section(group)
    t = sect["files"]
    if group == "calib":
        fields = [{"view": v} for v in range(sect["views"])]
    elif group == "calib.projector":
        fields = [{"view": v, "frame": f} for v in range(sect["views"]) for f in scan.sl_frames]
    elif group == "structured_light":
        fields = [{"frame": f} for f in scan.sl_frames]
    else:
        fields = [{"light": scan._olat_file_number(l)} for l in range(sect["n_lights"])]
    return [format_template(t, {"camera": camera, **f}) for f in fields]


def _make_parents(d: Path) -> list[Path]:
    """``mkdir -p d``; returns the directories it created, deepest first (to undo it)."""
    missing = []
    while not d.exists():
        missing.append(d)
        d = d.parent
    for m in reversed(missing):
        try:
            m.mkdir()
        except OSError as exc:
            raise InputError(f"{m}: cannot create the directory ({exc.strerror})") from exc
    return missing


def _skin_model(spec: str) -> dict:
    """``SkinField`` keyword arguments for a ``--skin`` value."""
    name, _, kind = str(spec).partition(":")
    if name == "regional" and not kind:
        return {"albedo_model": "regional"}
    if name == "spectral":
        from facegeo.appearance.spectral import SKIN_TYPES

        kind = kind or "medium"
        if kind not in SKIN_TYPES:
            raise InputError(f"skin: unknown spectral skin type {fmt_value(kind)}; expected one of "
                             f"{', '.join(SKIN_TYPES)}")
        return {"albedo_model": "spectral", "albedo_params": {"params": kind}}
    raise InputError(f"skin: unknown model {fmt_value(spec)}; expected 'regional' or 'spectral[:type]'")


def _projector_irradiance(proj, p_world, n_world):
    """Irradiance factor of the projector at points (unit at the projector's distance to the
    origin, inverse-square falloff, cosine) and the projector pixel each point sees."""
    c = proj.center_world
    to_p = c[None, :] - p_world
    d = np.linalg.norm(to_p, axis=1)
    l = to_p / d[:, None]
    cos = np.clip(np.einsum("pc,pc->p", l, n_world), 0, None)
    e = cos * (np.linalg.norm(c) / d) ** 2
    q, front = proj.project(p_world)
    q = np.where(front[:, None], q, -1e9)
    return e.astype(np.float32), q


def face_fill(camera, landmarks) -> dict:
    """How much of a camera's image the face box (:func:`facegeo.synth.head.face_box`) spans.

    Returns ``{"height": h, "width": w, "inside": bool}``: the projected box's extent as
    fractions of the image height and width, and whether all its corners are in the image.
    """
    from facegeo.synth.head import face_box

    lo, hi = face_box(landmarks)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    q, front = camera.project(corners)
    inside = bool(front.all() and (q[:, 0] >= 0).all() and (q[:, 0] <= camera.width - 1).all()
                  and (q[:, 1] >= 0).all() and (q[:, 1] <= camera.height - 1).all())
    return {"height": float(np.ptp(q[:, 1]) / camera.height),
            "width": float(np.ptp(q[:, 0]) / camera.width), "inside": inside}


#: Fraction of the image a real face's box (:func:`facegeo.synth.head.face_box`) spans along
#: its limiting axis once :func:`frame_rig` has moved the cameras.
FACE_FILL_TARGET = 0.8


def frame_rig(rig, landmarks, fill: float = FACE_FILL_TARGET):
    """The rig with every capture camera aimed at a real face and moved so the face fills it.

    Each camera keeps its direction from the face box's centre (:func:`facegeo.synth.head.face_box`)
    — its yaw and height angle — but looks at that centre (the default rig aims at the head
    centre, ≈ 11 cm behind the face, which shifts the face sideways in yawed cameras) from the
    distance at which the face box spans ``fill`` of the image height or width, whichever is
    reached first (three fixed-point steps: perspective makes the span only nearly
    ∝ 1/distance). Projector and light stage are unchanged.
    """
    from facegeo.geometry.rig import Rig
    from facegeo.synth.head import face_box

    lo, hi = face_box(landmarks)
    target = 0.5 * (lo + hi)
    cams = []
    for cam in rig.cameras:
        off = cam.center_world - target
        dist = float(np.linalg.norm(off))
        off = off / dist
        for _ in range(3):
            cam = cam.replace(T_cam_world=look_at(target + dist * off, target))
            f = face_fill(cam, landmarks)
            dist *= max(f["height"], f["width"]) / fill
        cams.append(cam.replace(T_cam_world=look_at(target + dist * off, target)))
    return Rig(cameras=cams, projector=rig.projector, lights=rig.lights)


def _write_head_truth(gt: Path, mesh, rig, skin, renderer) -> dict:
    """``parts.npz``, ``landmarks.json`` and, for a mesh file, ``head_transform.json`` and
    ``vertex_map.npz``; returns their manifest entries."""
    from facegeo.fsutil import atomic_path, atomic_write_text
    from facegeo.synth.head import head_landmarks
    from facegeo.synth.skin import PART_MATERIALS, region_landmark_distances

    out = {}
    names = list(renderer.part_names)
    labels = (renderer.parts if renderer.parts is not None
              else np.zeros(len(renderer.faces), np.int64))
    mats = [PART_MATERIALS.get(n) for n in names]
    with atomic_path(gt / "parts.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh, labels=labels.astype(np.int64), names=np.array(names),
                albedo=np.array([m.albedo if m else (np.nan,) * 3 for m in mats], np.float32),
                rho_s=np.array([m.rho_s if m else np.nan for m in mats], np.float32),
                roughness=np.array([m.roughness if m else np.nan for m in mats], np.float32))
    out["parts"] = "ground_truth/parts.npz"
    meta = mesh.metadata
    landmarks = meta.get("face_landmarks")
    if landmarks is None and "facegeo_head" in meta:
        landmarks = head_landmarks(mesh)
    doc: dict = {"landmarks": {}, "regions": {}}
    if landmarks is not None:
        doc["landmarks"] = {k: np.asarray(v, float).tolist() for k, v in landmarks.items()}
        doc["regions"] = region_landmark_distances(skin, mesh.vertices, mesh.faces, landmarks,
                                                   face_mask=labels == 0)
        doc["landmark_source"] = meta.get("landmark_source", "procedural head parameters")
        if "menton" in landmarks:
            doc["framing"] = {c.name: face_fill(c, landmarks) for c in rig.cameras}
    else:
        doc["note"] = "no facial landmarks known for this mesh: regions in bounding-box placement"
    atomic_write_text(gt / "landmarks.json", json.dumps(doc, indent=2))
    out["landmarks"] = "ground_truth/landmarks.json"
    if "source_vertex_index" in meta:
        scale = float(meta["scale_to_m"])
        t = np.asarray(meta["translation_m"], float)
        T = np.eye(4)
        T[:3, :3] *= scale
        T[:3, 3] = t
        atomic_write_text(gt / "head_transform.json", json.dumps({
            "source_path": meta.get("source_path"), "units": meta.get("units"),
            "scale_to_m": scale, "translation_m": t.tolist(),
            "world_from_file": T.tolist(),
            "note": "world = scale_to_m * file + translation_m (no rotation); mesh.ply vertices "
                    "are these, rounded to float32",
        }, indent=2))
        out["head_transform"] = "ground_truth/head_transform.json"
        src = np.asarray(meta["source_vertex_index"], np.int64)
        of_src = np.full(int(meta.get("n_source_vertices", src.max() + 1)), -1, np.int64)
        of_src[src[::-1]] = np.arange(len(src))[::-1]  # first output vertex of each file vertex
        with atomic_path(gt / "vertex_map.npz") as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, source_vertex_index=src, output_vertex_of_source=of_src)
        out["vertex_map"] = "ground_truth/vertex_map.npz"
    return out


def _write_ground_truth(root: Path, mesh, rig, skin, renderer, uniform_renders: dict, *,
                        tick=None) -> dict:
    """Write ``ground_truth/`` and return its manifest table.

    Reports progress as stage ``"ground_truth"``: one step for the mesh and skin files, then,
    per capture and novel camera, one for its geometry and one per reference render (the
    renders not already accumulated during the OLAT pass are the slow part: a full Eq. (4)
    sum over the lights each).

    ``uniform_renders`` holds the capture cameras' uniform-environment renders, accumulated
    during the OLAT pass (the same Eq. (4) sum :meth:`ReferenceRenderer.render_lights` computes),
    so they are not shaded twice.
    """
    from facegeo.capture import imageio
    from facegeo.fsutil import atomic_path, atomic_write_text

    gt = root / "ground_truth"
    gt.mkdir(parents=True, exist_ok=True)
    out: dict[str, str] = {}
    tick = tick or (lambda stage, done, total: None)
    cams = list(rig.cameras) + _novel_cameras(rig)
    n_total = 1 + 3 * len(cams)
    done = 0
    tick("ground_truth", done, n_total)
    import trimesh

    with atomic_path(gt / "mesh.ply") as tmp:
        # geometry only: UVs and materials would make loaders try to load textures
        trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), process=False).export(tmp)
    out["mesh"] = "ground_truth/mesh.ply"
    rig.save(gt / "rig.json")
    out["rig"] = "ground_truth/rig.json"
    atomic_write_text(gt / "skin.json", json.dumps(skin.to_dict(), indent=2))
    out["skin"] = "ground_truth/skin.json"
    s = skin.evaluate(np.asarray(mesh.vertices))
    if renderer.parts is not None:  # eyes, teeth, mouth: their own materials
        from facegeo.synth.skin import apply_part_materials

        s = apply_part_materials(s, renderer.vertex_parts(), renderer.part_names)
    with atomic_path(gt / "vertex_params.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, alpha_0=s.alpha_0, alpha_1=s.alpha_1, rho_s=s.rho_s,
                                roughness=s.roughness, normals=renderer.vertex_normals)
    out["vertex_params"] = "ground_truth/vertex_params.npz"
    out.update(_write_head_truth(gt, mesh, rig, skin, renderer))
    novel = _novel_cameras(rig)
    atomic_write_text(gt / "novel_cameras.json", json.dumps([c.to_dict() for c in novel], indent=2))
    out["novel_cameras"] = "ground_truth/novel_cameras.json"
    done += 1
    tick("ground_truth", done, n_total)
    # Per-camera geometry and reference renders: every capture camera and the novel ones.
    lights = rig.lights
    # A uniform white environment of radiance 1 (Eq. 4 weights L·δA) and a single key light.
    uniform = np.repeat(lights.solid_angles[:, None], 3, axis=1)
    key = np.zeros((lights.n_lights, 3))
    from facegeo.frames import nearest_light_index

    key_l = int(nearest_light_index(np.array([0.5, 0.45, 0.74]), lights.n_theta, lights.n_phi))
    key[key_l] = 1.0
    for cam in list(rig.cameras) + novel:
        view = renderer.surface_view(cam)
        with atomic_path(gt / f"geometry_{cam.name}.npz") as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, mask=view.mask, p_world=view.to_image(view.p_world, np.nan),
                                    n_world=view.to_image(view.n_world, np.nan),
                                    face=view.to_image(view.face, -1))
        out[f"geometry_{cam.name}"] = f"ground_truth/geometry_{cam.name}.npz"
        done += 1
        tick("ground_truth", done, n_total)
        for tag, w in (("uniform", uniform), ("key", key)):
            if tag == "uniform" and cam.name in uniform_renders:
                img = uniform_renders[cam.name]
            else:
                img = renderer.render_lights(cam, lights, w)
            rel = f"ground_truth/renders/{cam.name}_{tag}.exr"
            imageio.write_image(root / rel, img)
            out[f"render_{cam.name}_{tag}"] = rel
            done += 1
            tick("ground_truth", done, n_total)
    atomic_write_text(gt / "renders.json", json.dumps({
        "uniform": "uniform white environment of radiance 1: weights[l] = δA_l (Eq. 4)",
        "key": f"the single light-stage light {key_l} at full weight (an OLAT frame)",
        "key_light": key_l,
        "cameras": [c.name for c in rig.cameras] + [c.name for c in novel],
    }, indent=2))
    out["renders"] = "ground_truth/renders.json"
    return out
