"""Image files in and out; the camera responses that make their pixels linear are re-exported.

This is the only module that touches image files. Everything it returns is indexed
``[row, col, channel]`` with channels in **RGB** order (OpenCV's BGR is swapped here, at the
edge, and nowhere else).

Formats
-------
* PNG, JPEG, TIFF and Radiance ``.hdr`` go through OpenCV (``IMREAD_UNCHANGED``, so 16-bit
  PNGs stay ``uint16`` and ``.hdr`` is ``float32``).
* OpenEXR goes through the ``OpenEXR`` Python bindings: the OpenCV 5.0 wheels are built without
  OpenEXR (verified: ``cv2.haveImageReader("x.exr")`` is False, ``cv2.imread`` returns None and
  ``cv2.imwrite`` raises "could not find a writer for the specified extension").

Radiometry (``docs/conventions.md``): every pixel value inside the library is linear float32.
8/16-bit frames are linearised by a declared :class:`Response` (``"linear"``, ``"srgb"``, a
gamma, or a tabulated Debevec–Malik curve); saturated and black-clipped samples are flagged by
:func:`saturated_mask` and :func:`clipped_mask` and must never be trusted. These live in
:mod:`facegeo.capture.response` and are re-exported here under the same names (``Response``,
``parse_response``, ``load_response_table``, ``linearize``, ``encode``, ``srgb_to_linear``,
``linear_to_srgb``, ``saturated_mask``, ``clipped_mask``, ``RESPONSE_KINDS``), so
``from facegeo.capture.imageio import linearize`` keeps working.
"""

from __future__ import annotations

import logging
import os
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from facegeo.errors import InputError, ScanFormatError
from facegeo.fsutil import atomic_path
from facegeo.capture.response import (  # re-exported: part of this module's public API
    _INT_DTYPES,
    RESPONSE_KINDS,
    Response,
    clipped_mask,
    encode,
    linear_to_srgb,
    linearize,
    load_response_table,
    parse_response,
    saturated_mask,
    srgb_to_linear,
)

__all__ = [
    "ImageReadError",
    "READ_SUFFIXES",
    "WRITE_SUFFIXES",
    "RESPONSE_KINDS",
    "read_image",
    "read_image_size",
    "write_image",
    "Response",
    "parse_response",
    "load_response_table",
    "linearize",
    "encode",
    "saturated_mask",
    "clipped_mask",
    "srgb_to_linear",
    "linear_to_srgb",
]

log = logging.getLogger(__name__)

READ_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".hdr", ".pic", ".exr")
WRITE_SUFFIXES = (".png", ".exr", ".hdr")

_HALF_MAX = float(np.finfo(np.float16).max)


class ImageReadError(ScanFormatError):
    """An image file is missing, unreadable, corrupt or not in a supported format."""


# --------------------------------------------------------------------------- reading


def _cv2():
    import cv2  # deferred: keeps ``import facegeo`` fast

    return cv2


def _check_readable(path: Path) -> None:
    if not path.exists():
        raise ImageReadError("image file not found", path=path)
    if not path.is_file():
        raise ImageReadError("expected an image file, found a directory or special file", path=path)
    if path.suffix.lower() not in READ_SUFFIXES:
        raise ImageReadError(
            f"unsupported image format {path.suffix!r}; readable: {', '.join(READ_SUFFIXES)}",
            path=path,
        )


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image file as stored.

    Parameters
    ----------
    path : path-like
        ``.png``, ``.jpg``/``.jpeg``, ``.tif``/``.tiff``, ``.hdr``/``.pic`` or ``.exr``.

    Returns
    -------
    (H, W, C) or (H, W) ndarray
        Channels in RGB(A) order; a single-channel file gives ``(H, W)``. The dtype is the
        stored one: uint8 or uint16 (PNG/JPEG/TIFF), float32 (``.hdr``, float EXR), float16
        (half EXR). Values are *not* linearised (see :func:`linearize`).

    Raises
    ------
    ImageReadError
        The file is missing, not a supported format, truncated or corrupt; the message names
        the file and what is wrong.
    """
    path = Path(path)
    _check_readable(path)
    if path.suffix.lower() == ".exr":
        return _read_exr(path)
    cv2 = _cv2()
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise ImageReadError(f"cannot read file ({exc.strerror or exc})", path=path) from exc
    if data.size == 0:
        raise ImageReadError("file is empty", path=path)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ImageReadError(
            f"cannot decode {path.suffix} image (truncated, corrupt, or not really "
            f"{path.suffix.lstrip('.').upper()})",
            path=path,
        )
    if img.ndim == 3:
        if img.shape[2] == 3:
            img = img[..., ::-1]
        elif img.shape[2] == 4:
            img = img[..., [2, 1, 0, 3]]
        elif img.shape[2] == 1:
            img = img[..., 0]
    return np.ascontiguousarray(img)


def _exr_open(path: Path, *, header_only: bool):
    import OpenEXR  # deferred

    try:
        ok = OpenEXR.isOpenExrFile(str(path))
    except Exception:  # pragma: no cover - binding quirk
        ok = False
    if not ok:
        raise ImageReadError("not an OpenEXR file (bad magic number)", path=path)
    try:
        return OpenEXR.File(str(path), separate_channels=True, header_only=header_only)
    except Exception as exc:  # the bindings raise RuntimeError or ValueError on corrupt files
        what = "header" if header_only else "pixel data"
        raise ImageReadError(
            f"cannot read OpenEXR {what} (truncated or corrupt file: {exc})", path=path
        ) from exc


def _exr_size(header: Mapping[str, Any], path: Path) -> tuple[int, int]:
    try:
        (x0, y0), (x1, y1) = header["dataWindow"]
    except Exception as exc:
        raise ImageReadError("OpenEXR header has no valid dataWindow", path=path) from exc
    return int(x1) - int(x0) + 1, int(y1) - int(y0) + 1


def _read_exr(path: Path) -> np.ndarray:
    f = _exr_open(path, header_only=False)
    try:
        channels = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
        width, height = _exr_size(f.header(), path)
    except ImageReadError:
        raise
    except Exception as exc:
        raise ImageReadError(f"cannot read OpenEXR pixel data ({exc})", path=path) from exc
    if not channels:
        raise ImageReadError("OpenEXR file has no channels (truncated or corrupt?)", path=path)
    for name, px in channels.items():
        if px.shape != (height, width):
            raise ImageReadError(
                f"OpenEXR channel {name!r} has shape {px.shape}, expected {(height, width)} "
                "from the data window (subsampled channels are not supported)",
                path=path,
            )
    names = set(channels)
    if {"R", "G", "B"} <= names:
        order = ["R", "G", "B"] + (["A"] if "A" in names else [])
    elif len(names) == 1:
        order = list(names)
    else:
        raise ImageReadError(
            f"OpenEXR channels {sorted(names)} are neither R,G,B[,A] nor a single channel",
            path=path,
        )
    dtypes = {channels[n].dtype for n in order}
    dtype = dtypes.pop() if len(dtypes) == 1 else np.dtype(np.float32)
    if len(order) == 1:
        return np.ascontiguousarray(channels[order[0]], dtype=dtype)
    return np.stack([channels[n].astype(dtype, copy=False) for n in order], axis=-1)


# --------------------------------------------------------------------------- header sizes


def _png_size(path: Path) -> tuple[int, int]:
    with open(path, "rb") as fh:
        head = fh.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise ImageReadError("not a PNG file (bad signature or missing IHDR chunk)", path=path)
    width, height = struct.unpack(">II", head[16:24])
    return int(width), int(height)


def _jpeg_size(path: Path) -> tuple[int, int] | None:
    sof = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
    with open(path, "rb") as fh:
        if fh.read(2) != b"\xff\xd8":
            raise ImageReadError("not a JPEG file (missing SOI marker)", path=path)
        while True:
            b = fh.read(1)
            while b and b != b"\xff":
                b = fh.read(1)
            while b == b"\xff":
                b = fh.read(1)
            if not b:
                return None
            marker = b[0]
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                continue
            seg = fh.read(2)
            if len(seg) < 2:
                return None
            (length,) = struct.unpack(">H", seg)
            if marker in sof:
                body = fh.read(5)
                if len(body) < 5:
                    return None
                height, width = struct.unpack(">HH", body[1:5])
                return int(width), int(height)
            fh.seek(length - 2, os.SEEK_CUR)


def _hdr_size(path: Path) -> tuple[int, int] | None:
    with open(path, "rb") as fh:
        first = fh.readline(256)
        if not first.startswith(b"#?"):
            raise ImageReadError("not a Radiance HDR file (missing '#?' header)", path=path)
        for _ in range(256):
            line = fh.readline(256)
            if not line:
                return None
            if line.strip() == b"":
                res = fh.readline(256).split()
                if len(res) == 4 and res[0] in (b"-Y", b"+Y") and res[2] in (b"+X", b"-X"):
                    return int(res[3]), int(res[1])
                return None
    return None


def read_image_size(path: str | os.PathLike) -> tuple[int, int]:
    """Width and height of an image file, from its header when the format allows.

    PNG (IHDR chunk), JPEG (SOF marker), Radiance HDR (resolution line) and OpenEXR (data
    window) are read without decoding pixels; other formats are decoded.

    Returns
    -------
    (width, height) : tuple of int, pixels

    Raises
    ------
    ImageReadError
        Missing file, unsupported format, or a header that cannot be parsed.
    """
    path = Path(path)
    _check_readable(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".png":
            return _png_size(path)
        if suffix == ".exr":
            return _exr_size(_exr_open(path, header_only=True).header(), path)
        if suffix in (".jpg", ".jpeg"):
            size = _jpeg_size(path)
        elif suffix in (".hdr", ".pic"):
            size = _hdr_size(path)
        else:
            size = None
    except (OSError, struct.error) as exc:
        raise ImageReadError(f"cannot read image header ({exc})", path=path) from exc
    if size is None:
        img = read_image(path)
        size = (int(img.shape[1]), int(img.shape[0]))
    return size


# --------------------------------------------------------------------------- writing


def write_image(path: str | os.PathLike, img: Any, *, half: bool = False) -> Path:
    """Write an image atomically (temporary file beside ``path``, then rename).

    Parameters
    ----------
    path : path-like
        Destination; the suffix picks the format:

        * ``.png``: uint8 or uint16, ``(H, W)``, ``(H, W, 3)`` RGB or ``(H, W, 4)`` RGBA;
        * ``.exr``: float32 (or float16 input), ``(H, W)`` stored as channel ``Y``,
          ``(H, W, 3)`` as ``R, G, B``, ``(H, W, 4)`` as ``R, G, B, A``; ZIP compression;
          stored as 32-bit float, or as half when ``half=True``;
        * ``.hdr``: Radiance RGBE, float32 ``(H, W, 3)``, finite and >= 0 (lossy: about 1 %
          relative precision).
    img : ndarray
        Pixels, RGB order, indexed ``[row, col, channel]``.
    half : bool
        EXR only: store 16-bit half floats. Finite values beyond ±65504 are refused rather than
        silently turned into inf.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    InputError
        A dtype or shape the format cannot hold (for example float to PNG, or integer to EXR),
        an unsupported suffix, or ``half`` with a non-EXR suffix.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in WRITE_SUFFIXES:
        raise InputError(
            f"write_image: cannot write {suffix or 'a file without suffix'!r} ({path}); "
            f"writable formats: {', '.join(WRITE_SUFFIXES)}"
        )
    if half and suffix != ".exr":
        raise InputError(f"write_image: half=True only applies to .exr, not {suffix} ({path})")
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (3, 4))):
        raise InputError(
            f"write_image: expected an image of shape (H, W), (H, W, 3) or (H, W, 4), "
            f"got {a.shape} ({path})"
        )
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise InputError(f"write_image: empty image of shape {a.shape} ({path})")
    if suffix == ".png":
        _write_png(path, a)
    elif suffix == ".exr":
        _write_exr(path, a, half=half)
    else:
        _write_hdr(path, a)
    log.debug("wrote %s (%s %s%s)", path, a.dtype, a.shape, ", half" if half else "")
    return path


def _write_png(path: Path, a: np.ndarray) -> None:
    if a.dtype not in _INT_DTYPES:
        hint = " (encode it first: facegeo.capture.imageio.encode)" if a.dtype.kind == "f" else ""
        raise InputError(
            f"write_image: PNG holds uint8 or uint16, got {a.dtype}{hint} ({path})"
        )
    cv2 = _cv2()
    if a.ndim == 3:
        a = a[..., [2, 1, 0]] if a.shape[2] == 3 else a[..., [2, 1, 0, 3]]
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(a)):
            raise OSError(f"OpenCV failed to write PNG {path}")


def _write_exr(path: Path, a: np.ndarray, *, half: bool) -> None:
    if a.dtype.kind != "f" or a.dtype not in (np.dtype(np.float16), np.dtype(np.float32)):
        raise InputError(
            f"write_image: EXR holds float32 or float16, got {a.dtype}"
            f"{' (linearise it first: facegeo.capture.imageio.linearize)' if a.dtype.kind in 'ui' else ''}"
            f" ({path})"
        )
    if half:
        finite = np.isfinite(a)
        big = finite & (np.abs(a) > _HALF_MAX)
        if big.any():
            raise InputError(
                f"write_image: {int(big.sum())} value(s) exceed the half-float range ±65504 "
                f"(max |value| {float(np.abs(a[finite]).max()):.6g}); write float32 instead "
                f"({path})"
            )
        a = a.astype(np.float16, copy=False)
    else:
        a = a.astype(np.float32, copy=False)
    import OpenEXR  # deferred

    if a.ndim == 2:
        channels = {"Y": np.ascontiguousarray(a)}
    else:
        names = "RGBA"[: a.shape[2]]
        channels = {n: np.ascontiguousarray(a[..., i]) for i, n in enumerate(names)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        OpenEXR.File(header, channels).write(str(tmp))


def _write_hdr(path: Path, a: np.ndarray) -> None:
    if a.dtype.kind != "f":
        raise InputError(f"write_image: Radiance .hdr holds float RGB, got {a.dtype} ({path})")
    if a.ndim != 3 or a.shape[2] != 3:
        raise InputError(
            f"write_image: Radiance .hdr holds RGB only, got shape {a.shape}; write .exr for "
            f"grey or RGBA ({path})"
        )
    a = a.astype(np.float32, copy=False)
    if not np.isfinite(a).all() or (a < 0).any():
        raise InputError(
            f"write_image: Radiance .hdr holds finite values >= 0 only; write .exr instead ({path})"
        )
    cv2 = _cv2()
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(a[..., ::-1])):
            raise OSError(f"OpenCV failed to write Radiance HDR {path}")
