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
                       elevation, 8-bit frames, an ambient frame to subtract (dropped with a
                       warning when it is the uncropped 640 × 480 frame); a light list.
``diligent``           One DiLiGenT photometric-stereo object (``ballPNG/``: ``001.png`` …,
                       ``light_directions.txt``, ``light_intensities.txt``, ``mask.png``,
                       ``Normal_gt.mat``): 96 distant lights with RGB intensities, linear
                       frames, the mask and the ground-truth normals (camera frame) under
                       ``reference/``.
``graycode-mannequin`` An 18-frame Gray-code capture (``1.jpg`` … ``18.jpg``) without
                       inverse or white/black frames: row and column bits interleaved.
``three-phase``        A three-step phase-shift capture of a face (``phase1.png`` …):
                       horizontal fringes, phase along the rows (axis ``y``), no Gray code.
``3dunderworld``       A 3DUNDERWORLD-SLS capture (``{leftCam,rightCam}/dataset1/0000.png``
                       …, ``calib/output/calib.xml``): two calibrated cameras, an
                       uncalibrated 1024 × 768 projector, 42 Gray-code frames with
                       inverses (frames a camera lacks declared missing), the scanner's
                       reconstruction as ``reference/points.ply``; ``scale`` 1, 0.5, 0.25.
=====================  =====================================================================

The 3DUNDERWORLD cameras are the scanner's own calibration (an OpenCV FileStorage
``calib.xml`` in millimetres and full-resolution pixels, read by
:mod:`facegeo.capture.opencv_storage`), scaled to the frames with the pixel-centre rule
``f' = f·s``, ``c' = (c + ½)·s − ½``.

What none of the other data sets publish is written as a *nominal* value and said so in the
manifest's description and ``[scan.metadata]``: the cameras' intrinsics before calibration
(focal length = image width, principal point at the centre, no distortion; DiLiGenT's from its
50 mm lens, :data:`DILIGENT_FOCAL_PX`), the distance of the Yale and DiLiGenT cameras, and the
resolution of the projectors (the pattern space).

The one-light-at-a-time converters (``yale-b``, ``diligent``) live in
:mod:`facegeo.capture._datasets_olat`, the helpers every converter shares in
:mod:`facegeo.capture._datasets_common`; this module keeps the others, the registry and
:func:`import_dataset`, and re-exports the public names.

Errors name the data set's files: a converter builds the scan in a staging folder, and an
error about a file there (the validation of a frame's size, say) is reported against the
source file it was carried from, with its place in the scan added (:func:`import_dataset`).
"""

from __future__ import annotations

import inspect
import json
import logging
import os
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from facegeo.capture._datasets_common import (
    _SOURCES,
    _carry,
    _image_size,
    _need,
    _nominal_camera,
    _note_source,
)
from facegeo.capture._datasets_olat import (
    DILIGENT_DISTANCE_M,
    DILIGENT_FOCAL_PX,
    _diligent,
    _yale_b,
    yale_light_direction,
)
from facegeo.capture.importer import check_destination
from facegeo.capture.opencv_storage import read_matrices
from facegeo.capture.scan import MANIFEST_NAME, Scan, load_scan, new_manifest, write_manifest
from facegeo.checks import check_choice
from facegeo.errors import FacegeoError, InputError, ScanFormatError
from facegeo.fsutil import atomic_write_text, clean_stale_siblings, staging_dir, swap_in_dir, \
    remove_tree

__all__ = ["DATASETS", "DILIGENT_FOCAL_PX", "import_dataset", "yale_light_direction"]

log = logging.getLogger(__name__)


# ---------------------------------------------------------------- OpenCV stereo chessboards
_OPENCV_VIEWS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14)


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
    # the data has no single-camera calibration of the right images (only left_intrinsics.yml):
    # the right reference is stereo_calib's M2, a joint fit (fixed aspect, k3 and tangential
    # terms at 0, shared focal). OpenCV's own single-camera calibration of the 13 right views
    # with the calibration sample's flags (fix aspect ratio; the same procedure gives the left
    # camera within 0.09 px of left_intrinsics.yml) lands 8.8 px from M2's principal point and
    # 1.3 % from its focal; facegeo's 10.8 px, 0.38 % (2026-12-02)
    ref = {"source": "OpenCV samples/data (left: the calibration sample's output "
                     "left_intrinsics.yml; right: stereo_calib's output intrinsics.yml, its "
                     "left under stereo_calib)",
           "note": "right: no single-camera reference ships with the data; M2 is the stereo "
                   "calibration's joint fit, 8.8 px (principal point) and 1.3 % (focal) from "
                   "OpenCV's single-camera calibration of the right views",
           "cameras": {}}
    if (src / "intrinsics.yml").is_file():
        m = read_matrices(src / "intrinsics.yml", ("M1", "D1", "M2", "D2"))
        ref["cameras"] = {"left": {"K": m["M1"].tolist(), "dist": m["D1"].ravel().tolist()},
                          "right": {"K": m["M2"].tolist(), "dist": m["D2"].ravel().tolist()}}
    if (src / "left_intrinsics.yml").is_file():
        m = read_matrices(src / "left_intrinsics.yml",
                          ("camera_matrix", "distortion_coefficients"))
        ref["left_single_camera"] = {"K": m["camera_matrix"].tolist(),
                                     "dist": m["distortion_coefficients"].ravel().tolist()}
        # the left camera's reference is OpenCV's own single-camera calibration of these
        # images; stereo_calib's M1 (cx 335.7 against 342.3) is a joint stereo fit, kept apart
        if "left" in ref["cameras"]:
            ref["stereo_calib"] = {"left": ref["cameras"]["left"]}
        ref["cameras"]["left"] = ref["left_single_camera"]
    manifest = new_manifest(
        "opencv_stereo_chessboards", synthetic=False,
        description="OpenCV's stereo calibration samples: 13 chessboard views per camera "
                    "(9 x 6 inner corners, 25 mm squares). Camera intrinsics in rig.json are "
                    "nominal (f = image width); the published ones are under reference/: "
                    "left, OpenCV's single-camera calibration (left_intrinsics.yml); right, "
                    "the stereo calibration's M2 (intrinsics.yml; no single-camera one is "
                    "published), 8.8 px in principal point and 1.3 % in focal from OpenCV's "
                    "own single-camera calibration of the right views.")
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


# ---------------------------------------------------------------- 3DUNDERWORLD-SLS
#: Scan camera name -> the data set's camera folder.
_UNDERWORLD_CAMERAS = {"left": "leftCam", "right": "rightCam"}
#: The scanner's patterns: white, black, 10 column then 10 row Gray bits, MSB first, each
#: followed by its inverse, over a 1024 x 768 projector (frames 0000 ... 0041).
_UNDERWORLD_PATTERNS = {"width": 1024, "height": 768, "n_bits_x": 10, "n_bits_y": 10,
                        "inverse": True, "white_black": True}
_UNDERWORLD_FRAME = re.compile(r"^(\d{4})\.(png|jpe?g|bmp|tiff?|pgm)$", re.IGNORECASE)
#: ``scale`` -> the side of the box the frames are reduced by.
_UNDERWORLD_SCALES = {1: 1, 0.5: 2, 0.25: 4}
#: Why the scanner's chessboard views are not declared under ``[calib]``.
_UNDERWORLD_NO_CALIB = (
    "not declared under [calib]: with board views `facegeo reconstruct` (rig auto) meshes with "
    "its own calibration (out/calibrate/rig.json, brought to rig.json's frame only by an "
    "averaged rigid transform) instead of the scanner's calib.xml, the frame of the reference "
    "cloud; and the scanner's corner lists use a different sub-grid of the board in each view "
    "(5 x 6 to 8 x 7 inner corners), so no one board size describes them")


def _underworld_reduction(scale) -> int:
    """The box side ``n`` of a ``scale`` (1, 0.5, 0.25 -> 1, 2, 4); else InputError."""
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) \
            or scale not in _UNDERWORLD_SCALES:
        raise InputError(f"scale: expected 1, 0.5 or 0.25 (the source frames reduced by an exact "
                         f"1/2 or 1/4 box mean), got {scale!r}")
    return _UNDERWORLD_SCALES[scale]


def _underworld_frames(folder: Path, names: list[str]) -> dict[str, Path]:
    """``{frame name: file}`` of the ``NNNN.<image suffix>`` files in ``folder`` (frame number
    k is ``names[k]``); frames absent from the folder are absent from the result."""
    if not folder.is_dir():
        raise InputError(f"{folder}: not found; a 3DUNDERWORLD data set has leftCam/dataset1/ and "
                         "rightCam/dataset1/ with the frames 0000.png ...")
    found: dict[str, Path] = {}
    for q in sorted(folder.iterdir()):
        m = _UNDERWORLD_FRAME.match(q.name)
        if not m or not q.is_file():
            continue
        k = int(m.group(1))
        if k >= len(names):
            raise InputError(f"{q}: frame {k}, but the scanner's patterns have {len(names)} "
                             f"(0000 ... {len(names) - 1:04d}: white, black, 10 column and 10 "
                             "row Gray bits with inverses)")
        if names[k] in found:
            raise InputError(f"{q}: frame {k} twice ({found[names[k]].name} and {q.name})")
        found[names[k]] = q
    if not found:
        raise InputError(f"{folder}: no frames (0000.png ... {len(names) - 1:04d}.png)")
    return found


def _read_obj_points(path: Path) -> np.ndarray:
    """The ``v`` lines of an OBJ file, ``(N, 3)`` float64, in the file's units."""
    rows = [ln.split()[1:4] for ln in path.read_text(encoding="utf-8", errors="replace")
            .splitlines() if ln.startswith("v ")]
    try:
        p = np.array(rows, dtype=np.float64)
    except ValueError:
        raise InputError(f"{path}: a 'v' line without three numbers") from None
    if p.ndim != 2 or p.shape[0] == 0 or p.shape[1] != 3:
        raise InputError(f"{path}: no vertices ('v x y z' lines)")
    if not np.isfinite(p).all():
        raise InputError(f"{path}: non-finite vertex coordinates")
    return p


#: Decode settings written into an imported 3DUNDERWORLD scan (``[structured_light.decode]``).
#: The bust's pattern / inverse margins are small against its direct light (plaster under a
#: dim projector): the generator's relative margin 0.15 leaves holes the meshes cannot close
#: (reference points within 1 mm of the mesh, with the hole fill: 97.3 %); 0.05 reaches
#: 99.5 % with points as accurate (0.161 against 0.167 mm median to the scanner's cloud).
UNDERWORLD_DECODE = {"rel_contrast": 0.05}


def _write_points_ply(path: Path, p_world: np.ndarray, comment: str) -> None:
    """Binary little-endian PLY of ``(N, 3)`` float64 points (``double x, y, z``), atomically."""
    from facegeo.fsutil import atomic_path

    head = ["ply", "format binary_little_endian 1.0", f"comment {comment}",
            f"element vertex {len(p_world)}", "property double x", "property double y",
            "property double z", "end_header", ""]
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write("\n".join(head).encode("ascii"))
        fh.write(np.ascontiguousarray(p_world, dtype="<f8").tobytes())


def _reduce_frame(src: Path, dst: Path, n: int, size: tuple[int, int]) -> None:
    """Write ``src`` reduced by the mean of its ``n x n`` blocks to ``size`` as PNG ``dst``
    (``cv2.resize`` INTER_AREA: on exact multiples the block mean, rounded)."""
    import cv2

    from facegeo.capture.imageio import read_image, write_image

    _note_source(dst, src)
    img = read_image(src)
    h, w = img.shape[:2]
    if (w, h) != (size[0] * n, size[1] * n):
        raise InputError(f"{src}: {w} x {h} pixels, but this camera's frames are "
                         f"{size[0] * n} x {size[1] * n} (the first frame's size)")
    write_image(dst, cv2.resize(img, size, interpolation=cv2.INTER_AREA))


def _underworld_cameras(xmls: dict[str, Path], frames: dict[str, dict[str, Path]], n: int):
    """Each camera's ``calib.xml`` (millimetres, calibrated-size pixels) rescaled to its frames
    reduced by ``n``: ``(cameras in metres, {name: the camera as calibrated})``."""
    from facegeo.capture.opencv_storage import read_opencv_camera, rescale_camera

    cams, calibrated = [], {}
    for cam, xml in xmls.items():
        first = next(iter(frames[cam].values()))
        w, h = _image_size(first)
        if w % n or h % n:
            raise InputError(f"{first}: {w} x {h} pixels do not divide by {n} (scale 1/{n}); "
                             "choose a scale whose reduction divides the frames")
        calibrated[cam] = full = read_opencv_camera(xml, cam, units=1e-3)
        try:
            cams.append(rescale_camera(full, w // n, h // n))
        except InputError as exc:
            raise InputError(f"{xml}: calibrated at {full.width} x {full.height}, frames "
                             f"{first} are {w} x {h}: {exc}") from None
    return cams, calibrated


def _underworld_carry(frames: dict[str, dict[str, Path]], root: Path, mode: str, rig,
                      n: int) -> str:
    """Carry (``n`` = 1: link or copy) or reduce by ``n`` (write PNG) every frame into the
    scan; returns the suffix of the ``files`` template."""
    if n > 1:
        for cam, found in frames.items():
            for frame, p in found.items():
                _reduce_frame(p, root / "structured_light" / cam / f"{frame}.png", n,
                              rig.camera(cam).size)
        return ".png"
    for cam, found in frames.items():
        for frame, p in found.items():
            _carry(p, root / "structured_light" / cam / f"{frame}{p.suffix.lower()}", mode)
    suffixes = {p.suffix.lower() for found in frames.values() for p in found.values()}
    return suffixes.pop() if len(suffixes) == 1 else ".*"


def _underworld_reference(src: Path, root: Path) -> dict | None:
    """The scanner's reconstruction (one ``*.obj`` of SRC, millimetres) as
    ``reference/points.ply`` in metres; its metadata, or None without one."""
    objs = sorted(q for q in src.glob("*.obj") if q.is_file())
    if len(objs) > 1:
        raise InputError(f"{src}: several reference clouds ({', '.join(q.name for q in objs)}); "
                         "expected at most one .obj (the scanner's reconstruction)")
    if not objs:
        return None
    p_world = _read_obj_points(objs[0]) * 1e-3  # millimetres -> metres
    _write_points_ply(root / "reference" / "points.ply", p_world,
                      f"facegeo import --dataset 3dunderworld: {objs[0].name}, metres, world "
                      "frame (the extr board view)")
    return {"point_cloud": objs[0].name, "points": len(p_world),
            "converted": "millimetres -> metres, world frame of the calibration (extr)"}


def _underworld_description(rig, calibrated: dict, missing: dict, n: int,
                            reference: dict | None) -> str:
    s_text = ", ".join(f"{c.name} {calibrated[c.name].width} x {calibrated[c.name].height} px "
                       f"-> s = {c.width / calibrated[c.name].width:g}" for c in rig.cameras)
    lost = "; ".join(f"{c} lacks {', '.join(m)}" for c, m in missing.items() if m)
    return ("3DUNDERWORLD-SLS structured-light capture: two cameras (left, right), an "
            "uncalibrated 1024 x 768 projector, white/black and 10 column + 10 row Gray bits "
            "with inverses (42 frames)"
            + (f"; {lost} (not in the data set)" if lost else "")
            + f". Cameras from the scanner's calib.xml (millimetres; {s_text}: f' = f s, "
            "c' = (c + 1/2) s - 1/2), world frame = the extr board view"
            + (f"; frames reduced by {n} x {n} box means" if n > 1 else "")
            + (f". reference/points.ply: the scanner's own reconstruction "
               f"({reference['points']} points, metres), a baseline, not ground truth"
               if reference else "")
            + ". The chessboard views are not declared under [calib], so that `facegeo "
              "reconstruct` meshes with the scanner's calibration (scan.metadata.board_views "
              "says why).")


def _underworld(src: Path, root: Path, mode: str, *, scale=1) -> dict:
    from facegeo.geometry.rig import Projector, Rig
    from facegeo.geometry.structured_light import PatternSpec, pattern_names

    n = _underworld_reduction(scale)
    spec = PatternSpec(**_UNDERWORLD_PATTERNS)
    names = pattern_names(spec)
    xmls = {cam: _need(src / folder / "calib" / "output", ["calib.xml"])[0]
            for cam, folder in _UNDERWORLD_CAMERAS.items()}
    frames = {cam: _underworld_frames(src / folder / "dataset1", names)
              for cam, folder in _UNDERWORLD_CAMERAS.items()}
    cams, calibrated = _underworld_cameras(xmls, frames, n)
    rig = Rig(cameras=cams, projector=Projector("projector", spec.width, spec.height),
              lights=None)
    rig.save(root / "rig.json")
    suffix = _underworld_carry(frames, root, mode, rig, n)
    missing = {cam: [f for f in names if f not in found] for cam, found in frames.items()}
    reference = _underworld_reference(src, root)

    manifest = new_manifest(src.name, synthetic=False, description=_underworld_description(
        rig, calibrated, missing, n, reference))
    manifest["scan"]["metadata"] = {
        "dataset": "3dunderworld",
        "source_folder": src.name,
        "nominal": [],
        "units": {"rig": "metres, pixels of the scan's frames",
                  "calibration_files": "millimetres, pixels of the calibrated image size"},
        "calibration": {c.name: {"file": xmls[c.name].relative_to(src).as_posix(),
                                 "calibrated_size": list(calibrated[c.name].size),
                                 "scale": c.width / calibrated[c.name].width}
                        for c in cams},
        "pixel_mapping": "c' = (c + 1/2) s - 1/2, f' = f s (pixel centres at integers)",
        "frames_scale": float(scale),
        "frames": ("hard links (or copies) of the source files" if n == 1 else
                   f"the source frames reduced by the exact mean of {n} x {n} blocks "
                   "(cv2.resize INTER_AREA), written as PNG"),
        "source_frames": {c: {f: p.relative_to(src).as_posix() for f, p in found.items()}
                          for c, found in frames.items()},
        "board_views": {"files": [f"{folder}/calib/{q.name}"
                                  for folder in _UNDERWORLD_CAMERAS.values()
                                  for q in sorted((src / folder / "calib").glob("*.png"))],
                        "declared": False, "why": _UNDERWORLD_NO_CALIB},
    }
    if reference:
        manifest["scan"]["metadata"]["reference"] = reference
        manifest["reference"] = {"point_cloud": "reference/points.ply"}
    manifest["structured_light"] = {"response": "srgb", "projector": "projector",
                                    "frames": names,
                                    "files": "structured_light/{camera}/{frame}" + suffix,
                                    "patterns": spec.to_dict(),
                                    "decode": dict(UNDERWORLD_DECODE)}
    if any(missing.values()):
        manifest["structured_light"]["cameras"] = {c: {"missing": m}
                                                   for c, m in missing.items() if m}
    return manifest


#: Data set name -> converter ``(src, staging_root, mode) -> manifest``; a converter that
#: takes a keyword ``scale`` can reduce the frames (:func:`import_dataset`).
DATASETS: dict[str, Callable[..., dict]] = {
    "opencv-stereo": _opencv_stereo,
    "yale-b": _yale_b,
    "graycode-mannequin": _graycode_mannequin,
    "three-phase": _three_phase,
    "3dunderworld": _underworld,
    "diligent": _diligent,
}


def import_dataset(kind: str, src: str | os.PathLike, dest: str | os.PathLike, *,
                   mode: str = "link", scale: float | None = None) -> Scan:
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
    scale : {1, 0.5, 0.25}, optional
        The scan's frames relative to the source frames (``3dunderworld`` only): 1 carries the
        files as they are; 0.5 and 0.25 write each frame reduced by the exact mean of its
        2 × 2 or 4 × 4 blocks (PNG) and scale the intrinsics with the pixel-centre rule
        (:func:`facegeo.capture.opencv_storage.rescale_camera`). None or 1 for every other
        data set.

    Returns
    -------
    Scan
        The new scan, loaded with the quick check.

    Raises
    ------
    InputError
        Unknown ``kind``; ``src`` is not that data set (the message names the missing files);
        ``dest`` is a file or a non-empty directory; a ``scale`` the data set's converter does
        not take, or that does not divide its frames.
    ScanFormatError
        The converted scan does not validate (a frame of the wrong size, a truncated file): the
        message and ``path`` name the source file, ``(in the scan: <relative path>)`` added —
        never the staging folder.
    """
    check_choice(kind, "dataset", tuple(DATASETS))
    check_choice(mode, "mode", ("link", "copy"))
    convert = DATASETS[kind]
    options = {}
    if scale is not None:
        if "scale" in inspect.signature(convert).parameters:
            options["scale"] = scale
        elif not (isinstance(scale, (int, float)) and not isinstance(scale, bool)
                  and scale == 1):
            takes = [k for k, f in DATASETS.items() if "scale" in inspect.signature(f).parameters]
            raise InputError(f"scale: the {kind} converter carries the frames at their own size "
                             f"(scale 1), got {scale!r}; only {', '.join(takes)} can reduce them")
    src, dest = Path(src), Path(dest)
    if not src.is_dir():
        raise InputError(f"{src}: source folder not found")
    check_destination(src, dest)  # new or empty, never inside the source
    dest.parent.mkdir(parents=True, exist_ok=True)
    clean_stale_siblings(dest)
    tmp = staging_dir(dest, "tmp")
    sources: dict[Path, Path] = {}
    token = _SOURCES.set(sources)
    try:
        manifest = convert(src, tmp, mode, **options)
        write_manifest(tmp, manifest)
        swap_in_dir(tmp, dest)
    except FacegeoError as exc:
        remove_tree(tmp)
        named = _named_by_source(exc, tmp, dest, sources)
        if named is exc:
            raise
        raise named.with_traceback(exc.__traceback__) from None
    except BaseException:
        remove_tree(tmp)
        raise
    finally:
        _SOURCES.reset(token)
    log.info("converted %s data set %s into %s", kind, src, dest)
    return load_scan(dest / MANIFEST_NAME)


def _named_by_source(exc: FacegeoError, tmp: Path, dest: Path,
                     sources: dict[Path, Path]) -> FacegeoError:
    """``exc`` with every path into the staging folder ``tmp`` replaced by what the user knows:
    the source file a scan file was carried (or reduced) from, ``(in the scan: <rel>)`` added,
    or else the file's place under ``dest`` (a file the converter wrote: the rig, a reference).
    The same exception type, the same ``key``; ``exc`` itself when it names no staging path.
    """
    roots = {str(tmp), os.path.realpath(tmp)}
    text = str(exc)
    if not any(r in text for r in roots):
        return exc

    def rel_of(q: Path) -> Path | None:
        text_q = str(q)
        for r in roots:
            if text_q.startswith(r + os.sep):
                return Path(text_q[len(r) + 1:])
        return None

    # staged file -> its source, longest paths first (a file's path before its folder's)
    swaps = sorted(((os.path.join(r, q.relative_to(tmp)), str(original))
                    for q, original in sources.items() for r in roots),
                   key=lambda t: -len(t[0]))

    def rewrite(message: str) -> str:
        for staged, original in swaps:
            message = message.replace(staged, original)
        for r in roots:
            message = message.replace(r, str(dest))
        return message

    if isinstance(exc, ScanFormatError):
        where = ([str(exc.path)] if exc.path is not None else []) + (
            [f"[{exc.key}]"] if exc.key is not None else [])
        prefix = (" ".join(where) + ": ") if where else ""
        body = text[len(prefix):] if text.startswith(prefix) else text
        path = exc.path
        rel = rel_of(path) if path is not None else None
        if rel is not None:
            original = sources.get(tmp / rel)
            if original is not None:
                path = original
                body = f"{rewrite(body)} (in the scan: {rel.as_posix()})"
            else:
                path = dest / rel
                body = rewrite(body)
        else:
            body = rewrite(body)
            if path is not None and str(path) in roots:  # the staging folder itself
                path = dest
        return ScanFormatError(body, path=path, key=exc.key)
    try:
        return type(exc)(rewrite(text))
    except TypeError:  # an error type with another constructor: leave it as it is
        return exc
