"""Parameter maps on disk: 16-bit PNG with a documented scale (or .npy), written atomically.

Layout of a map directory::

    C_m.png  beta_m.png  C_h.png  [rho_s.png]       16-bit greyscale, value = code/65535 · scale
    [residual.png]                                  16-bit, linear-RGB residual, scale 0.1
    [flags.png]                                     8-bit, the FLAG_* bitmask of the fit
    parameter_maps.json                             format, shape, and every file's scale

Scales (:data:`PNG_SCALES`): C_m 0.5, β_m 1, C_h 0.32, ρ_s 1, residual 0.1 — the upper ends of
:data:`facegeo.appearance.spectral.PARAMETER_RANGES`, so a code step is 7.6e-6 in C_m (0.8 % of the
smallest C_m, 0.001) and 4.9e-6 in C_h. Values are rounded to the nearest code; the
residual saturates at 0.1. With ``fmt="npy"`` the arrays are stored exactly as float64.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from facegeo.errors import InputError, ScanFormatError
from facegeo.fsutil import atomic_path, atomic_write_text
from facegeo.appearance.spectral._inverse import AlbedoFit
from facegeo.appearance.spectral._model import SkinParameters
from facegeo.checks import fmt_value

__all__ = ["PNG_SCALES", "save_parameter_maps", "load_parameter_maps"]

FORMAT = "facegeo.appearance.spectral.parameter_maps/1"
#: Physical value of PNG code 65535, per map.
PNG_SCALES: dict[str, float] = {
    "C_m": 0.5,
    "beta_m": 1.0,
    "C_h": 0.32,
    "rho_s": 1.0,
    "residual": 0.1,
}


def _cv2():
    import cv2

    return cv2


def _write_png(path: Path, img: np.ndarray) -> None:
    cv2 = _cv2()
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise OSError(f"{path}: OpenCV could not write the PNG")


def save_parameter_maps(
    maps: SkinParameters | AlbedoFit, directory: str | os.PathLike, *, fmt: str = "png"
) -> Path:
    """Write parameter maps (and a fit's residual and flags) into ``directory``.

    Parameters
    ----------
    maps : SkinParameters or AlbedoFit
        Maps of shape (H, W) for PNG; any shape for .npy.
    directory : path
        Created if needed; files inside are replaced atomically.
    fmt : {"png", "npy"}

    Returns
    -------
    Path of ``parameter_maps.json``.
    """
    if fmt not in ("png", "npy"):
        raise InputError(f"fmt: unknown value {fmt_value(fmt)}; expected 'png' or 'npy'")
    params = maps.parameters if isinstance(maps, AlbedoFit) else maps
    arrays: dict[str, np.ndarray] = {k: np.asarray(v, float) for k, v in params.as_dict().items()}
    if isinstance(maps, AlbedoFit):
        arrays["residual"] = np.asarray(maps.residual, float)
        arrays["flags"] = np.asarray(maps.flags, np.uint8)
    shape = np.shape(arrays["C_m"])
    for k, a in arrays.items():
        if a.shape != shape:
            raise InputError(f"{k}: shape {a.shape} differs from C_m's {shape}")
        if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise InputError(f"{k}: non-finite values cannot be stored")
    if fmt == "png" and len(shape) != 2:
        raise InputError(f"maps: PNG needs 2-D (H, W) maps, got shape {shape}; use fmt='npy'")
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    files = {}
    for k, a in arrays.items():
        if fmt == "npy":
            name = f"{k}.npy"
            with atomic_path(out / name) as tmp:
                with open(tmp, "wb") as fh:
                    np.save(fh, a)
            files[k] = {"file": name}
        elif k == "flags":
            name = "flags.png"
            _write_png(out / name, a.astype(np.uint8))
            files[k] = {"file": name, "dtype": "uint8", "meaning": "bitmask of FLAG_*"}
        else:
            scale = PNG_SCALES[k]
            if k != "residual" and (a.min() < 0 or a.max() > scale):
                raise InputError(f"{k}: values outside [0, {scale:g}] do not fit the PNG scale")
            code = np.round(np.clip(a / scale, 0.0, 1.0) * 65535.0).astype(np.uint16)
            name = f"{k}.png"
            _write_png(out / name, code)
            files[k] = {"file": name, "dtype": "uint16", "scale": scale,
                        "value": "code / 65535 * scale"}
    meta = {"format": FORMAT, "shape": list(shape), "files": files}
    meta_path = out / "parameter_maps.json"
    atomic_write_text(meta_path, json.dumps(meta, indent=2) + "\n")
    return meta_path


def load_parameter_maps(directory: str | os.PathLike) -> SkinParameters:
    """Read maps written by :func:`save_parameter_maps` (PNG codes → physical values)."""
    folder = Path(directory)
    meta_path = folder / "parameter_maps.json"
    if not meta_path.is_file():
        raise ScanFormatError("missing parameter_maps.json", path=folder)
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ScanFormatError(f"invalid JSON: {exc}", path=meta_path) from exc
    if meta.get("format") != FORMAT:
        raise ScanFormatError(
            f"format {fmt_value(meta.get('format'))}, expected {fmt_value(FORMAT)}", path=meta_path, key="format"
        )
    shape = tuple(meta.get("shape", ()))
    out = {}
    for k in ("C_m", "beta_m", "C_h", "rho_s"):
        entry = meta.get("files", {}).get(k)
        if entry is None:
            if k == "rho_s":
                continue
            raise ScanFormatError(f"no entry for {k}", path=meta_path, key=f"files.{k}")
        p = folder / entry["file"]
        if not p.is_file():
            raise ScanFormatError("missing map file", path=p)
        if p.suffix == ".npy":
            a = np.load(p)
        else:
            img = _cv2().imread(str(p), -1)  # IMREAD_UNCHANGED keeps 16 bits
            if img is None or img.dtype != np.uint16:
                raise ScanFormatError("expected a 16-bit greyscale PNG", path=p)
            a = img.astype(np.float64) / 65535.0 * float(entry["scale"])
        if a.shape != shape:
            raise ScanFormatError(f"shape {a.shape}, expected {shape}", path=p)
        out[k] = a
    return SkinParameters(**out)
