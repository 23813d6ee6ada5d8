"""Converters for public data sets: their folders become version-2 scans.

Each converter reads a data set as its authors ship it, writes the rig and the manifest that
describe it (``docs/scan-format.md``) and hard-links (or copies, across file systems) its frames
into the scan layout, so every facegeo stage reads it like any other capture. The source folder
is never modified; the scan is built in a sibling staging folder and appears at ``dest`` only
when it is complete and validated.

=====================  =====================================================================
``opencv-stereo``      OpenCV's stereo chessboard samples (``left01.jpg`` … ``right14.jpg``,
                       9 × 6 inner corners, 25 mm): calibration only, published intrinsics
                       kept under ``reference/``.
``yale-b``             One subject and pose of the Extended Yale Face Database B
                       (``yaleB01_P00A+035E+15.pgm`` …): 64 flashes named by azimuth and
                       elevation, 8-bit frames, an ambient frame to subtract; a light list.
``graycode-mannequin`` An 18-frame Gray-code capture (``1.jpg`` … ``18.jpg``) without
                       inverse or white/black frames: row and column bits interleaved.
``three-phase``        A three-step phase-shift capture of a face (``phase1.png`` …):
                       horizontal fringes, phase along the rows (axis ``y``), no Gray code.
=====================  =====================================================================

What none of these data sets publish is written as a *nominal* value and said so in the
manifest's description and ``[scan.metadata]``: the cameras' intrinsics before calibration
(focal length = image width, principal point at the centre, no distortion), the distance of the
Yale camera, and the resolution of the projectors (the pattern space).
"""

from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from facegeo.capture.importer import _carry, check_destination
from facegeo.capture.scan import MANIFEST_NAME, Scan, load_scan, new_manifest, write_manifest
from facegeo.checks import check_choice
from facegeo.errors import InputError
from facegeo.fsutil import atomic_write_text, clean_stale_siblings, staging_dir, swap_in_dir, \
    remove_tree

__all__ = ["DATASETS", "import_dataset", "yale_light_direction"]

log = logging.getLogger(__name__)


def _nominal_camera(name: str, width: int, height: int, eye=(0.0, 0.0, 1.0)):
    """A pinhole camera with f = width, centred principal point, looking at the origin."""
    from facegeo.frames import look_at
    from facegeo.geometry.camera import Camera

    f = float(width)
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return Camera(name, int(width), int(height), K, np.zeros(5), look_at(eye, (0.0, 0.0, 0.0)))


def _image_size(path: Path) -> tuple[int, int]:
    from facegeo.capture.imageio import read_image_size

    return read_image_size(path)


def _need(src: Path, names) -> list[Path]:
    paths = [src / n for n in names]
    missing = [p.name for p in paths if not p.is_file()]
    if missing:
        raise InputError(f"{src}: not the expected data set; missing "
                         f"{', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}")
    return paths


# ---------------------------------------------------------------- OpenCV stereo chessboards
_OPENCV_VIEWS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14)


def _read_cv_yaml(path: Path, keys: tuple[str, ...]) -> dict:
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        if not fs.isOpened():
            raise InputError(f"{path}: cannot read this OpenCV YAML file")
        out = {}
        for k in keys:
            node = fs.getNode(k)
            if node.empty():
                raise InputError(f"{path}: no {k!r} entry")
            out[k] = np.asarray(node.mat(), float)
        return out
    finally:
        fs.release()


def _opencv_stereo(src: Path, root: Path, mode: str) -> dict:
    from facegeo.geometry.rig import Rig

    files = {cam: _need(src, [f"{cam}{v:02d}.jpg" for v in _OPENCV_VIEWS])
             for cam in ("left", "right")}
    w, h = _image_size(files["left"][0])
    # nominal cameras a hand-span apart; calibration finds the real ones
    cams = [_nominal_camera("left", w, h, eye=(-0.03, 0.0, 0.5)),
            _nominal_camera("right", w, h, eye=(0.03, 0.0, 0.5))]
    Rig(cameras=cams, projector=None, lights=None).save(root / "rig.json")
    for cam, paths in files.items():
        for view, p in enumerate(paths):
            _carry(p, root / "calib" / cam / f"view_{view:03d}.jpg", mode)
    ref = {"source": "OpenCV samples/data (stereo_calib output intrinsics.yml; calibration "
                     "sample output left_intrinsics.yml)", "cameras": {}}
    if (src / "intrinsics.yml").is_file():
        m = _read_cv_yaml(src / "intrinsics.yml", ("M1", "D1", "M2", "D2"))
        ref["cameras"] = {"left": {"K": m["M1"].tolist(), "dist": m["D1"].ravel().tolist()},
                          "right": {"K": m["M2"].tolist(), "dist": m["D2"].ravel().tolist()}}
    if (src / "left_intrinsics.yml").is_file():
        m = _read_cv_yaml(src / "left_intrinsics.yml",
                          ("camera_matrix", "distortion_coefficients"))
        ref["left_single_camera"] = {"K": m["camera_matrix"].tolist(),
                                     "dist": m["distortion_coefficients"].ravel().tolist()}
    manifest = new_manifest(
        "opencv_stereo_chessboards", synthetic=False,
        description="OpenCV's stereo calibration samples: 13 chessboard views per camera "
                    "(9 x 6 inner corners, 25 mm squares). Camera intrinsics in rig.json are "
                    "nominal (f = image width); the published ones are under reference/.")
    manifest["scan"]["metadata"] = {"dataset": "opencv-stereo", "source_views": list(_OPENCV_VIEWS),
                                    "nominal": ["cameras"]}
    manifest["calib"] = {"board": {"kind": "chessboard", "cols": 9, "rows": 6,
                                   "square_size": 0.025},
                         "response": "srgb", "views": len(_OPENCV_VIEWS),
                         "files": "calib/{camera}/view_{view:03d}.jpg"}
    if ref["cameras"] or "left_single_camera" in ref:
        atomic_write_text(root / "reference" / "intrinsics.json", json.dumps(ref, indent=2))
        manifest["reference"] = {"intrinsics": "reference/intrinsics.json"}
    return manifest


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
                    + (", an ambient frame" if ambient.is_file() else "")
                    + ". Camera intrinsics and distance are nominal; the frames' response is not "
                      "published (read as linear); solid angles are spherical Voronoi cells of "
                      "the flash directions over the whole sphere.")
    manifest["scan"]["metadata"] = {"dataset": "yale-b", "nominal": ["cameras", "response"]}
    manifest["olat"] = {"response": "linear", "n_lights": len(lights),
                        "files": "olat/{camera}/{light_name}.pgm"}
    if ambient.is_file():
        _carry(ambient, root / "olat" / "cam" / "ambient.pgm", mode)
        manifest["olat"]["ambient"] = "olat/{camera}/ambient.pgm"
    return manifest


# ---------------------------------------------------------------- structured light
def _sl_scan(root: Path, mode: str, *, name: str, description: str, metadata: dict,
             paths: list[Path], frames: list[str], spec, suffix: str) -> dict:
    """A one-camera structured-light scan with an uncalibrated projector of ``spec``'s size:
    writes the rig, carries the frames (``paths[k]`` becomes frame ``frames[k]``), returns the
    manifest."""
    from facegeo.geometry.rig import Projector, Rig

    w, h = _image_size(paths[0])
    Rig(cameras=[_nominal_camera("cam", w, h)],
        projector=Projector("projector", spec.width, spec.height),
        lights=None).save(root / "rig.json")
    for p, frame in zip(paths, frames):
        _carry(p, root / "structured_light" / "cam" / f"{frame}{suffix}", mode)
    manifest = new_manifest(name, synthetic=False, description=description)
    manifest["scan"]["metadata"] = metadata
    manifest["structured_light"] = {"response": "srgb", "projector": "projector",
                                    "frames": frames,
                                    "files": "structured_light/{camera}/{frame}" + suffix,
                                    "patterns": spec.to_dict()}
    return manifest


def _graycode_mannequin(src: Path, root: Path, mode: str) -> dict:
    from facegeo.geometry.structured_light import PatternSpec

    paths = _need(src, [f"{k}.jpg" for k in range(1, 19)])
    # GrayDecoder.pde: level k (frame k + 1) is a row bit for even k, a column bit for odd k,
    # most significant first; 9 bits each over a 1024 x 1024 pattern space.
    frames = [f"gray_{'y' if k % 2 == 0 else 'x'}_{k // 2:02d}" for k in range(18)]
    spec = PatternSpec(width=1024, height=1024, gray=True, n_bits_x=9, n_bits_y=9,
                       inverse=False, white_black=False)
    return _sl_scan(
        root, mode, name="graycode_mannequin", paths=paths, frames=frames, spec=spec,
        suffix=".jpg",
        description="Gray-code structured light of a mannequin: 9 column and 9 row bits, no "
                    "inverse or white/black frames (threshold from the data). The projector's "
                    "pattern space is 1024 x 1024 (shown squeezed into 1024 x 768); camera and "
                    "projector are uncalibrated.",
        metadata={"dataset": "graycode-mannequin", "nominal": ["cameras", "projector resolution"],
                  "source_frames": {name: f"{k + 1}.jpg" for k, name in enumerate(frames)}})


def _three_phase(src: Path, root: Path, mode: str) -> dict:
    from facegeo.geometry.structured_light import PatternSpec

    paths = _need(src, [f"phase{k}.png" for k in (1, 2, 3)])
    w, h = _image_size(paths[0])
    # The fringes are horizontal bands: the wrapped phase advances down the image (median
    # |dphi/drow| 0.10 rad per pixel against 0.03 per column), so the phase codes projector
    # rows, axis "y" (test_three_phase_declares_the_axis_its_fringes_vary_along).
    spec = PatternSpec(width=w, height=h, gray=False, inverse=False, white_black=False,
                       phase_steps=3, phase_axes=("y",))
    return _sl_scan(
        root, mode, name="face_threephase", paths=paths,
        frames=[f"phase_y_{k}" for k in range(3)], spec=spec, suffix=".png",
        description="Three-step phase shift of a face, horizontal fringes (the phase varies "
                    "down the image rows: projector axis y), no Gray code (wrapped phase only). "
                    "Projector resolution and fringe period are not published: the pattern "
                    "space is nominally the camera's size.",
        metadata={"dataset": "three-phase",
                  "nominal": ["cameras", "projector resolution", "phase period"]})


#: Data set name -> converter ``(src, staging_root, mode) -> manifest``.
DATASETS: dict[str, Callable[[Path, Path], dict]] = {
    "opencv-stereo": _opencv_stereo,
    "yale-b": _yale_b,
    "graycode-mannequin": _graycode_mannequin,
    "three-phase": _three_phase,
}


def import_dataset(kind: str, src: str | os.PathLike, dest: str | os.PathLike, *,
                   mode: str = "link") -> Scan:
    """Convert a public data set folder into a scan at ``dest``.

    Parameters
    ----------
    kind : str
        One of :data:`DATASETS`.
    src : path-like
        The data set's folder, as shipped (read only).
    dest : path-like
        The new scan directory; must not exist or be empty (nothing is ever overwritten).
    mode : {"link", "copy"}
        Hard-link the frames (copies across file systems), or always copy them.

    Returns
    -------
    Scan
        The new scan, loaded with the quick check.

    Raises
    ------
    InputError
        Unknown ``kind``; ``src`` is not that data set (the message names the missing files);
        ``dest`` is a file or a non-empty directory.
    ScanFormatError
        The converted scan does not validate (a frame of the wrong size, a truncated file: the
        message names the file).
    """
    check_choice(kind, "dataset", tuple(DATASETS))
    check_choice(mode, "mode", ("link", "copy"))
    src, dest = Path(src), Path(dest)
    if not src.is_dir():
        raise InputError(f"{src}: source folder not found")
    check_destination(src, dest)  # new or empty, never inside the source
    dest.parent.mkdir(parents=True, exist_ok=True)
    clean_stale_siblings(dest)
    tmp = staging_dir(dest, "tmp")
    try:
        manifest = DATASETS[kind](src, tmp, mode)
        write_manifest(tmp, manifest)
        swap_in_dir(tmp, dest)
    except BaseException:
        remove_tree(tmp)
        raise
    log.info("converted %s data set %s into %s", kind, src, dest)
    return load_scan(dest / MANIFEST_NAME)
