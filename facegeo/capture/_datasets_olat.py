"""Converters of the one-light-at-a-time data sets (:mod:`facegeo.capture.datasets`):
Extended Yale Face Database B (``yale-b``) and DiLiGenT (``diligent``). Public names are
re-exported by :mod:`facegeo.capture.datasets`."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from facegeo.capture._datasets_common import (
    _carry,
    _frame_bits,
    _image_size,
    _need,
    _nominal_camera,
    _note_source,
)
from facegeo.capture.scan import new_manifest
from facegeo.errors import InputError

log = logging.getLogger(__name__)


# ---------------------------------------------------------------- Yale face database B
_YALE_NAME = re.compile(r"^(?P<subject>yaleB\d+)_P(?P<pose>\d+)A(?P<az>[+-]\d{3})E(?P<el>[+-]\d{2})\.pgm$")


def yale_light_direction(azimuth_deg, elevation_deg) -> np.ndarray:
    """World direction toward a Yale B flash from its azimuth and elevation (degrees).

    The Yale convention, checked on the frames themselves (``A+070E+00`` lights the left half
    of the image, ``E+90`` the top): positive azimuth puts the light on the image's left, which
    for a camera on +z looking at the origin with +y up (``docs/conventions.md``) is world −x;
    positive elevation is +y. ``A+000E+00`` is the camera's direction, +z.

    Returns
    -------
    (..., 3) float64, unit (:func:`facegeo.geometry.lights.directions_from_azimuth_elevation`
    with the azimuth negated)
    """
    from facegeo.geometry.lights import directions_from_azimuth_elevation

    d = directions_from_azimuth_elevation(np.negative(azimuth_deg), elevation_deg)
    return d.reshape(np.broadcast(np.asarray(azimuth_deg), np.asarray(elevation_deg)).shape + (3,))


def _yale_ambient(ambient: Path, size: tuple[int, int]) -> dict | None:
    """Whether the ambient frame can go into the scan: None if it has the flashes' ``size``,
    else why it is dropped (logged as a warning naming the file).

    In the cropped Extended Yale B most subjects' ``_Ambient.pgm`` is the uncropped 640 × 480
    camera frame; the crop that made the 168 × 192 flashes is not published, so the ambient
    frame cannot be brought to them and the scan goes without one."""
    a = _image_size(ambient)
    if a == tuple(size):
        return None
    why = (f"{a[0]} x {a[1]} px, the flashes {size[0]} x {size[1]} px (an uncropped frame; the "
           "crop that made the flashes is not published)")
    log.warning("%s: ambient frame dropped: %s; the scan has no ambient frame to subtract",
                ambient, why)
    return {"file": ambient.name, "size": list(a), "dropped": why}


def _yale_b(src: Path, root: Path, mode: str) -> dict:
    from facegeo.geometry.lights import LightList
    from facegeo.geometry.rig import Rig

    lights = []
    for p in sorted(src.glob("*.pgm")):
        m = _YALE_NAME.match(p.name)
        if m:
            lights.append((p, m))
    if not lights:
        raise InputError(f"{src}: no Yale B frames (yaleBNN_PNNA+xxxE+yy.pgm)")
    keys = {(m["subject"], m["pose"]) for _, m in lights}
    if len(keys) != 1:
        raise InputError(f"{src}: frames of several subjects/poses {sorted(keys)}; convert one "
                         "subject and pose per scan")
    subject, pose = keys.pop()
    ambient = src / f"{subject}_P{pose}_Ambient.pgm"
    w, h = _image_size(lights[0][0])
    dropped = _yale_ambient(ambient, (w, h)) if ambient.is_file() else None
    has_ambient = ambient.is_file() and dropped is None
    names = [f"A{m['az']}E{m['el']}" for _, m in lights]
    dirs = yale_light_direction([int(m["az"]) for _, m in lights], [int(m["el"]) for _, m in lights])
    cam = _nominal_camera("cam", w, h, eye=(0.0, 0.0, 1.5))
    Rig(cameras=[cam], projector=None,
        lights=LightList(directions=dirs, names=names)).save(root / "rig.json")
    for (p, _), name in zip(lights, names):
        _carry(p, root / "olat" / "cam" / f"{name}.pgm", mode)
    manifest = new_manifest(
        f"{subject}_P{pose}", synthetic=False,
        description=f"Extended Yale Face Database B, subject {subject}, pose {pose}: "
                    f"{len(lights)} flashes named by azimuth/elevation, 8-bit frames"
                    + (", an ambient frame" if has_ambient else "")
                    + (f" (the ambient frame {ambient.name} was dropped: {dropped['dropped']})"
                       if dropped else "")
                    + ". Camera intrinsics and distance are nominal; the frames' response is not "
                      "published (read as linear); solid angles are spherical Voronoi cells of "
                      "the flash directions over the whole sphere.")
    manifest["scan"]["metadata"] = {"dataset": "yale-b", "nominal": ["cameras", "response"]}
    if dropped:
        manifest["scan"]["metadata"]["ambient"] = dropped
    manifest["olat"] = {"response": "linear", "n_lights": len(lights),
                        "files": "olat/{camera}/{light_name}.pgm"}
    if has_ambient:
        _carry(ambient, root / "olat" / "cam" / "ambient.pgm", mode)
        manifest["olat"]["ambient"] = "olat/{camera}/ambient.pgm"
    return manifest


# ---------------------------------------------------------------- DiLiGenT
#: Nominal focal length of the DiLiGenT camera in pixels of its frames: a 50 mm lens on the
#: 2448 x 2048 sensor of 3.45 um pixels, the data set's 612 x 512 frames being that sensor
#: reduced by 4 (13.8 um per frame pixel): 50 / 0.0138 = 3623 px. Our assumption, not
#: published with the frames; at that focal length a 300 px crop spans 4.7 deg, so the camera is
#: nearly orthographic and nothing per pixel depends on it.
DILIGENT_FOCAL_PX = 50e-3 / (4 * 3.45e-6)
#: Nominal distance of the DiLiGenT camera from the object (metres, on world +z).
DILIGENT_DISTANCE_M = 1.5
_DILIGENT_FILES = ("filenames.txt", "light_directions.txt", "light_intensities.txt", "mask.png")


def _read_table(path: Path, columns: int, what: str) -> np.ndarray:
    """A whitespace-separated text table of ``columns`` finite numbers per line, ``(n, columns)``
    float64; errors name the file and the line."""
    rows = []
    for k, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        try:
            v = [float(x) for x in line.split()]
        except ValueError:
            v = []
        if len(v) != columns or not np.isfinite(v).all():
            raise InputError(f"{path}, line {k}: expected {columns} numbers ({what}), got "
                             f"{line.strip()!r}")
        rows.append(v)
    if not rows:
        raise InputError(f"{path}: empty; expected one line of {what} per light")
    return np.array(rows, np.float64)


def _diligent_normals(mat: Path, size: tuple[int, int], R_cam_world: np.ndarray) -> np.ndarray:
    """``Normal_gt.mat`` (key ``Normal_gt``, H x W x 3, DiLiGenT's axes = the world frame here)
    as ``(H, W, 3)`` float64 unit normals in the camera frame, NaN where the file has none
    (its zero vectors, outside the mask)."""
    import scipy.io

    try:
        m = scipy.io.loadmat(mat)
    except (NotImplementedError, ValueError, OSError) as exc:  # v7.3 (HDF5), not MATLAB
        raise InputError(f"{mat}: cannot read it as a MATLAB v5 file ({exc})") from None
    if "Normal_gt" not in m:
        raise InputError(f"{mat}: no variable 'Normal_gt' (has "
                         f"{', '.join(k for k in m if not k.startswith('__')) or 'none'})")
    n_world = np.asarray(m["Normal_gt"], np.float64)
    w, h = size
    if n_world.shape != (h, w, 3):
        raise InputError(f"{mat} [Normal_gt]: shape {n_world.shape}, expected ({h}, {w}, 3) "
                         "(the frames' height x width x 3)")
    norm = np.linalg.norm(n_world, axis=-1)
    none = ~(norm > 0.5) | ~np.isfinite(norm)  # zero vectors outside the object
    n_cam = n_world @ R_cam_world.T
    n_cam /= np.where(none, 1.0, norm)[..., None]
    n_cam[none] = np.nan
    return n_cam


def _diligent(src: Path, root: Path, mode: str) -> dict:
    from facegeo.geometry.lights import LightList
    from facegeo.geometry.rig import Rig

    names_txt, dirs_txt, inten_txt, mask_png = _need(src, _DILIGENT_FILES)
    files = [ln.strip() for ln in names_txt.read_text(encoding="utf-8").splitlines() if ln.strip()]
    frames = _need(src, files)
    dirs = _read_table(dirs_txt, 3, "a light direction x y z")
    inten = _read_table(inten_txt, 3, "a light's R G B intensity")
    for what, table, path in (("directions", dirs, dirs_txt), ("intensities", inten, inten_txt)):
        if len(table) != len(files):
            raise InputError(f"{path}: {len(table)} {what}, but {names_txt.name} names "
                             f"{len(files)} frames; expected one line per frame")
    if (inten <= 0).any():
        k = int(np.flatnonzero((inten <= 0).any(axis=1))[0])
        raise InputError(f"{inten_txt}, line {k + 1}: intensities must be > 0, got {inten[k]}")
    suffixes = {p.suffix.lower() for p in frames}
    if len(suffixes) != 1:
        raise InputError(f"{names_txt}: frames of several kinds ({', '.join(sorted(suffixes))}); "
                         "expected one image format")
    suffix = suffixes.pop()
    w, h = _image_size(frames[0])
    if _image_size(mask_png) != (w, h):
        mw, mh = _image_size(mask_png)
        raise InputError(f"{mask_png}: {mw} x {mh} px, the frames {w} x {h} px")
    names = [p.stem for p in frames]

    f = DILIGENT_FOCAL_PX
    from facegeo.frames import look_at
    from facegeo.geometry.camera import Camera

    K = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    cam = Camera("cam", int(w), int(h), K, np.zeros(5),
                 look_at((0.0, 0.0, DILIGENT_DISTANCE_M), (0.0, 0.0, 0.0)))
    # DiLiGenT's axes (x right, y up, z toward the camera) are the world frame of a camera on
    # +z looking at the origin with +y up: its lights go in as they are
    Rig(cameras=[cam], projector=None,
        lights=LightList(directions=dirs, intensities=inten, names=names,
                         horizon_axis=(0.0, 0.0, 1.0))).save(root / "rig.json")
    for p, name in zip(frames, names):
        _carry(p, root / "olat" / "cam" / f"{name}{suffix}", mode)
    _carry(mask_png, root / "reference" / "mask.png", mode)
    reference = {"mask": "reference/mask.png"}
    mat = src / "Normal_gt.mat"
    if mat.is_file():
        R_cam_world = np.asarray(cam.T_cam_world.R, np.float64)
        n_cam = _diligent_normals(mat, (w, h), R_cam_world)
        out = root / "reference" / "normals.npy"
        _note_source(out, mat)
        np.save(out, n_cam)
        reference["normals"] = "reference/normals.npy"

    obj = re.sub(r"PNG$", "", src.name) or src.name
    depth = "16-bit" if _frame_bits(frames[0]) == 16 else "8-bit"
    manifest = new_manifest(
        f"diligent_{obj}", synthetic=False,
        description=f"DiLiGenT photometric-stereo object {obj!r} (Shi et al. 2016): "
                    f"{len(frames)} frames ({depth} {suffix[1:].upper()}, linear), one per "
                    "calibrated distant light (directions and RGB intensities from "
                    "light_directions.txt and light_intensities.txt: divide each frame by its "
                    "light's intensity before fitting). Camera intrinsics and distance are "
                    f"nominal (f = {f:.0f} px: a 50 mm lens, 13.8 um frame pixels; principal "
                    f"point at the frame centre; {DILIGENT_DISTANCE_M} m on +z): nearly "
                    "orthographic. reference/mask.png: the object; reference/normals.npy: the "
                    "ground-truth normals in the camera frame (x right, y down, z away from the "
                    "camera), NaN outside the object. Solid angles: spherical Voronoi cells "
                    "clipped at the plane facing the camera (the lights' hemisphere).")
    manifest["scan"]["metadata"] = {
        "dataset": "diligent", "object": obj, "nominal": ["cameras"],
        "camera": {"focal_px": f, "why": "50 mm lens / (4 x 3.45 um): the 2448 x 2048 sensor "
                   "reduced by 4 to 612 x 512 (assumed); crop offset unknown, principal point "
                   "at the frame centre", "distance_m": DILIGENT_DISTANCE_M},
        "frames": f"{depth}, linear response; hard links (or copies) of the source files",
        "source_frames": {n: p.name for n, p in zip(names, frames)},
        "normals": ("reference/normals.npy: (H, W, 3) float64, unit, camera frame (x right, y "
                    "down, z forward) = DiLiGenT's (x right, y up, z toward the camera) with y "
                    "and z negated; NaN outside the mask; a normal facing the camera is (0, 0, -1)")
        if "normals" in reference else "none (no Normal_gt.mat)",
    }
    manifest["olat"] = {"response": "linear", "n_lights": len(frames),
                        "files": "olat/{camera}/{light_name}" + suffix}
    manifest["reference"] = reference
    return manifest
