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
* Headers (:func:`read_image_info`: size, channels, sample type, and whether the file holds all
  its data) are read without decoding pixels: PNG, JPEG and TIFF through Pillow, OpenEXR by
  parsing its documented header and chunk offset table (the bindings expose neither pixel types
  nor the chunk table without decoding), Radiance HDR from its resolution line.
* What OpenEXR and OpenCV print on their own while failing on a corrupt file is hidden (logged
  at DEBUG level); the :class:`ImageReadError` raised names the file and the problem. Only
  those lines: whatever else is printed while an image is read, by any thread, reaches the
  terminal (see :func:`_quiet_native_output`).

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
from dataclasses import dataclass
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
from facegeo.checks import fmt_value
from facegeo.capture._native_output import _quiet_native_output, console_stream  # re-exported

__all__ = [
    "ImageReadError",
    "ImageInfo",
    "READ_SUFFIXES",
    "WRITE_SUFFIXES",
    "RESPONSE_KINDS",
    "read_image",
    "console_stream",
    "read_image_size",
    "read_image_info",
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

READ_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm", ".hdr", ".pic",
                 ".exr")
#: Suffixes whose header Pillow reads, and the format Pillow must find behind each.
_PIL_FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".tif": "TIFF", ".tiff": "TIFF",
                ".bmp": "BMP", ".pgm": "PPM", ".ppm": "PPM"}
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
            f"unsupported image format {fmt_value(path.suffix)}; readable: {', '.join(READ_SUFFIXES)}",
            path=path,
        )


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image file as stored.

    Parameters
    ----------
    path : path-like
        ``.png``, ``.jpg``/``.jpeg``, ``.tif``/``.tiff``, ``.bmp``, ``.pgm``/``.ppm`` (binary
        Netpbm, 8 or 16 bit), ``.hdr``/``.pic`` or ``.exr``.

    Returns
    -------
    (H, W, C) or (H, W) ndarray
        Channels in RGB(A) order; a single-channel file gives ``(H, W)``. The dtype is the
        stored one: uint8 or uint16 (PNG/JPEG/TIFF/BMP/PGM/PPM), float32 (``.hdr``, float EXR), float16
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
    with _quiet_native_output():  # OpenCV warns on stderr about truncated files
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


#: The first four bytes of every OpenEXR file.
EXR_MAGIC = b"\x76\x2f\x31\x01"

def _exr_open(path: Path, *, header_only: bool):
    import OpenEXR  # deferred

    _exr_structure(path)  # magic, header and chunk table, without OpenEXR's stderr noise
    try:
        with _quiet_native_output():
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
    with _quiet_native_output():
        return _read_exr_pixels(path)


def _read_exr_pixels(path: Path) -> np.ndarray:
    f = _exr_open(path, header_only=False)
    try:
        channels = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
        width, height = _exr_size(f.header(), path)
    except ImageReadError:
        raise
    except Exception as exc:
        raise ImageReadError(
            f"corrupt OpenEXR file: the OpenEXR library cannot decode its pixel data ({exc})",
            path=path,
        ) from exc
    if not channels:
        raise ImageReadError("OpenEXR file has no channels (truncated or corrupt?)", path=path)
    for name, px in channels.items():
        if px.shape != (height, width):
            raise ImageReadError(
                f"OpenEXR channel {fmt_value(name)} has shape {px.shape}, expected {(height, width)} "
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


# --------------------------------------------------------------------------- headers


@dataclass(frozen=True)
class ImageInfo:
    """What an image file's header says, as :func:`read_image` would return it.

    Attributes
    ----------
    width, height : int, pixels
    channels : int
        1 (grey), 3 (RGB) or 4 (RGBA); the last axis :func:`read_image` returns, or 1 for
        ``(H, W)``.
    dtype : numpy.dtype
        The stored sample type (uint8, uint16, float16, float32).
    verified : bool
        True when the file's structure was checked to hold all its data (PNG chunks and CRCs,
        the OpenEXR chunk table, the JPEG end marker); False when only the header was read.
    """

    width: int
    height: int
    channels: int
    dtype: np.dtype
    verified: bool = False

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)``."""
        return self.width, self.height


# OpenEXR scan lines per chunk by compression (OpenEXR file layout, "Scan Line Blocks").
_EXR_LINES_PER_CHUNK = {0: 1, 1: 1, 2: 1, 3: 16, 4: 32, 5: 16, 6: 32, 7: 32, 8: 32, 9: 256}
_EXR_PIXEL_DTYPES = {0: np.dtype(np.uint32), 1: np.dtype(np.float16), 2: np.dtype(np.float32)}


def _exr_structure(path: Path, *, check_chunks: bool = True) -> dict:
    """Parse an OpenEXR header and check that its chunk table fits the file.

    The Python bindings give neither channel pixel types nor the chunk table without decoding
    the pixels, and on a truncated file they fail with "file has 0 parts" plus native noise on
    stderr; this reads the documented single-part layout directly: magic number, version
    flags, attributes up to the empty name, then the offset table of ``ceil(height /
    lines_per_chunk)`` uint64 offsets. The chunk at the largest offset must end inside the file
    and every offset must point inside it (a writer that died leaves zeros or a short file).
    Tiled, multi-part and deep files get the header check only.

    Returns
    -------
    dict
        ``width``, ``height``, ``channels`` (list of ``(name, dtype)``), ``compression`` (int),
        ``verified`` (bool: the chunk table was checked).

    Raises
    ------
    ImageReadError
        Not an OpenEXR file (bad magic number), a header that cannot be parsed, or a file
        shorter than its chunk table says (truncated).
    """
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            if fh.read(4) != EXR_MAGIC:
                raise ImageReadError(
                    "not an OpenEXR file (bad magic number; an EXR starts with bytes 76 2f 31 01)",
                    path=path,
                )
            (version,) = struct.unpack("<I", fh.read(4))
            attrs: dict[str, tuple[str, bytes]] = {}
            for _ in range(10_000):
                name = _read_cstring(fh, path)
                if name == "":
                    break
                type_name = _read_cstring(fh, path)
                raw = fh.read(4)
                if len(raw) < 4:
                    raise ImageReadError("OpenEXR header is truncated", path=path)
                (n,) = struct.unpack("<i", raw)
                if n < 0 or n > size:
                    raise ImageReadError(f"OpenEXR attribute {fmt_value(name)} has a bad size {n}",
                                         path=path)
                value = fh.read(n)
                if len(value) < n:
                    raise ImageReadError("OpenEXR header is truncated", path=path)
                attrs[name] = (type_name, value)
            else:
                raise ImageReadError("OpenEXR header has no end", path=path)
            table_start = fh.tell()
            if "dataWindow" not in attrs or "channels" not in attrs:
                raise ImageReadError("OpenEXR header lacks dataWindow or channels", path=path)
            x0, y0, x1, y1 = struct.unpack("<4i", attrs["dataWindow"][1][:16])
            width, height = x1 - x0 + 1, y1 - y0 + 1
            if width <= 0 or height <= 0:
                raise ImageReadError(f"OpenEXR dataWindow is empty ({width}×{height})", path=path)
            channels = _exr_channels(attrs["channels"][1], path)
            compression = attrs["compression"][1][0] if "compression" in attrs else 0
            single_scanline = not version & (0x200 | 0x800 | 0x1000)
            lpc = _EXR_LINES_PER_CHUNK.get(compression)
            verified = False
            if check_chunks and single_scanline and lpc is not None:
                n_chunks = -(-height // lpc)
                table = fh.read(8 * n_chunks)
                if len(table) < 8 * n_chunks:
                    raise ImageReadError(
                        f"truncated OpenEXR file: {size} bytes end inside the chunk offset table "
                        f"({n_chunks} chunks from byte {table_start})",
                        path=path,
                    )
                offsets = np.frombuffer(table, dtype="<u8")
                data_start = table_start + 8 * n_chunks
                bad = (offsets < data_start) | (offsets >= size)
                if bad.any():
                    raise ImageReadError(
                        f"truncated or incomplete OpenEXR file: {int(bad.sum())} of {n_chunks} "
                        f"chunk offsets point outside the file's {size} bytes",
                        path=path,
                    )
                last = int(offsets.max())
                fh.seek(last)
                leader = fh.read(8)
                end = last + 8 + (struct.unpack("<ii", leader)[1] if len(leader) == 8 else 0)
                if len(leader) < 8 or end > size:
                    raise ImageReadError(
                        f"truncated OpenEXR file: its last chunk ends at byte {end} but the file "
                        f"has {size} bytes",
                        path=path,
                    )
                verified = True
    except OSError as exc:
        raise ImageReadError(f"cannot read file ({exc.strerror or exc})", path=path) from exc
    except struct.error as exc:
        raise ImageReadError(f"OpenEXR header is truncated or corrupt ({exc})", path=path) from exc
    return {"width": width, "height": height, "channels": channels,
            "compression": compression, "verified": verified}


def _read_cstring(fh, path: Path, limit: int = 256) -> str:
    out = bytearray()
    while len(out) <= limit:
        c = fh.read(1)
        if not c:
            raise ImageReadError("OpenEXR header is truncated", path=path)
        if c == b"\0":
            return out.decode("latin-1")
        out += c
    raise ImageReadError("OpenEXR header has an over-long name", path=path)


def _exr_channels(raw: bytes, path: Path) -> list[tuple[str, np.dtype]]:
    out, i = [], 0
    while i < len(raw) and raw[i] != 0:
        j = raw.index(b"\0", i)
        name = raw[i:j].decode("latin-1")
        (ptype,) = struct.unpack("<i", raw[j + 1:j + 5])
        if ptype not in _EXR_PIXEL_DTYPES:
            raise ImageReadError(f"OpenEXR channel {fmt_value(name)} has unknown pixel type {ptype}",
                                 path=path)
        out.append((name, _EXR_PIXEL_DTYPES[ptype]))
        i = j + 1 + 16
    if not out:
        raise ImageReadError("OpenEXR file has no channels", path=path)
    return out


def _exr_info(path: Path, verify: bool) -> ImageInfo:
    h = _exr_structure(path, check_chunks=verify)
    names = {n for n, _ in h["channels"]}
    if {"R", "G", "B"} <= names:
        used = ["R", "G", "B"] + (["A"] if "A" in names else [])
    elif len(names) == 1:
        used = list(names)
    else:
        raise ImageReadError(
            f"OpenEXR channels {sorted(names)} are neither R,G,B[,A] nor a single channel",
            path=path,
        )
    dtypes = {d for n, d in h["channels"] if n in used}
    dtype = dtypes.pop() if len(dtypes) == 1 else np.dtype(np.float32)
    return ImageInfo(h["width"], h["height"], len(used), dtype, h["verified"])


# Pillow mode -> channels as read_image returns them (cv2 IMREAD_UNCHANGED), 8-bit unless the
# tile's raw mode says 16.
_PIL_CHANNELS = {"L": 1, "1": 1, "I;16": 1, "I;16B": 1, "I;16L": 1, "RGB": 3, "RGBA": 4,
                 "LA": 4, "P": None}


def _pillow_info(path: Path, verify: bool) -> ImageInfo | None:
    """PNG / JPEG / TIFF / BMP / PGM / PPM header through Pillow (reads the header only;
    ``verify`` walks PNG chunks and CRCs, checks the JPEG end marker, or the file size of an
    uncompressed BMP / Netpbm raster). None when the mode needs a decode to know
    what :func:`read_image` returns (palettes, CMYK, ...)."""
    from PIL import Image, UnidentifiedImageError  # deferred

    suffix = path.suffix.lower()
    try:
        with Image.open(path) as im:
            fmt = im.format
            width, height = im.size
            mode = im.mode
            raw = str(im.tile[0].args[0] if isinstance(im.tile[0].args, tuple)
                      else im.tile[0].args) if im.tile else mode
            tile = im.tile[0] if im.tile and im.tile[0].codec_name == "raw" else None
            offset = tile.offset if tile is not None else None
            stride = (tile.args[1] if tile is not None and isinstance(tile.args, tuple)
                      and len(tile.args) > 1 and isinstance(tile.args[1], int) else None)
            if verify and fmt == "PNG":
                im.verify()
    except UnidentifiedImageError as exc:
        kind = suffix.lstrip(".").upper()
        raise ImageReadError(f"not a {kind} file (unrecognised header)", path=path) from exc
    except (OSError, SyntaxError, ValueError, struct.error) as exc:
        raise ImageReadError(
            f"truncated or corrupt {suffix.lstrip('.').upper()} file ({exc})", path=path
        ) from exc
    if fmt != _PIL_FORMATS.get(suffix):
        raise ImageReadError(f"file suffix is {suffix} but the file is {fmt}", path=path)
    verified = verify and fmt == "PNG"
    if verify and fmt in ("BMP", "PPM") and offset is not None:
        # Uncompressed rasters: the file must hold offset + rows × stride bytes.
        need = offset + _raster_bytes(mode, raw, int(width), int(height), stride)
        size = path.stat().st_size
        if size < need:
            raise ImageReadError(
                f"truncated {fmt} file ({size} bytes; its header promises {need})", path=path)
        verified = True
    if verify and fmt == "JPEG":
        with open(path, "rb") as fh:
            fh.seek(-2, os.SEEK_END)
            if fh.read(2) != b"\xff\xd9":
                raise ImageReadError("truncated JPEG file (no end-of-image marker)", path=path)
        verified = True
    channels = _PIL_CHANNELS.get(mode)
    if channels is None:
        return None
    dtype = np.dtype(np.uint16) if (";16" in raw or mode.startswith("I;16")) else np.dtype(np.uint8)
    return ImageInfo(int(width), int(height), channels, dtype, verified)


def _raster_bytes(mode: str, raw: str, width: int, height: int, stride: int | None) -> int:
    """Bytes of an uncompressed BMP / binary Netpbm raster (``stride``: bytes per row when the
    decoder states it, as for BMP's 4-byte padded rows)."""
    if stride:
        return abs(stride) * height
    channels = 3 if mode == "RGB" else 1
    sample = 2 if (";16" in raw or mode.startswith("I")) else 1
    return width * height * channels * sample


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


def read_image_info(path: str | os.PathLike, *, verify: bool = True) -> ImageInfo:
    """Size, channel count and sample type of an image file, from its header.

    Cheap: no pixels are decoded for PNG, JPEG, TIFF (Pillow reads the header), OpenEXR (the
    header and chunk table, see :func:`_exr_structure`) and Radiance HDR (its resolution line;
    always RGB float32). Other cases fall back to :func:`read_image`.

    Parameters
    ----------
    path : path-like
    verify : bool
        Also check that the file holds all its data, still without decoding: PNG chunk lengths
        and CRCs (Pillow's ``verify``), the OpenEXR chunk table against the file size, the
        JPEG end-of-image marker. Radiance HDR is not verified (run-length encoded rows have
        no index). ``ImageInfo.verified`` says whether it was done.

    Returns
    -------
    ImageInfo
        Equal to what :func:`read_image` returns: ``(height, width[, channels])`` and dtype.

    Raises
    ------
    ImageReadError
        Missing file, unsupported format, a header that cannot be parsed, or (``verify``) a
        truncated file; the message names the file.
    """
    path = Path(path)
    _check_readable(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        return _exr_info(path, verify)
    info = None
    if suffix in _PIL_FORMATS:
        info = _pillow_info(path, verify)
    elif suffix in (".hdr", ".pic"):
        try:
            size = _hdr_size(path)
        except (OSError, ValueError) as exc:
            raise ImageReadError(f"cannot read image header ({exc})", path=path) from exc
        if size is not None:
            info = ImageInfo(size[0], size[1], 3, np.dtype(np.float32), False)
    if info is None:
        img = read_image(path)
        info = ImageInfo(int(img.shape[1]), int(img.shape[0]),
                         1 if img.ndim == 2 else int(img.shape[2]), img.dtype, True)
    return info


def read_image_size(path: str | os.PathLike) -> tuple[int, int]:
    """Width and height of an image file, from its header (see :func:`read_image_info`).

    Returns
    -------
    (width, height) : tuple of int, pixels

    Raises
    ------
    ImageReadError
        Missing file, unsupported format, or a header that cannot be parsed.
    """
    return read_image_info(path, verify=False).size


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
            f"write_image: cannot write {fmt_value(suffix or 'a file without suffix')} ({path}); "
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
        # a NaN-ignoring range check first (two passes, no temporaries); count only if it fails
        if not (np.fmax.reduce(a, axis=None) <= _HALF_MAX
                and np.fmin.reduce(a, axis=None) >= -_HALF_MAX):
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
    else:  # the bindings split an interleaved "RGB"/"RGBA" array into R, G, B(, A) channels
        channels = {"RGBA"[: a.shape[2]]: np.ascontiguousarray(a)}
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
