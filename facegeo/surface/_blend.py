"""The weighted blend of the per-camera reflectance fields (``out/project/blended/``).

Private module behind :mod:`facegeo.surface.reflectance` (which re-exports every public name):
Σ_c w_c R_c / Σ_c w_c per texel over the cameras that see it (:func:`blend_fields`), in one
loop on the client or, on a cluster, in tasks of texel chunks (:func:`blend_rows_task`, driven
by :func:`facegeo.pipeline.project.blend_on_engine`) that give the same bits. The field readers
it shares with :mod:`facegeo.surface.reflectance` are :mod:`facegeo.surface._field_io`'s.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError, ShapeError
from facegeo.surface._field_io import _chunk_rows, _open_found, _release_rows, open_field
from facegeo.surface._zarr_field import write_field_chunk

log = logging.getLogger("facegeo.surface.reflectance")

#: Blend float16 fields with the compiled kernels (False: the numpy reference path).
BLEND_KERNELS = True


#: File name of the blended field in its folder. Not ``R.npy``: consumers find the per-camera
#: fields as the folders of ``out/project/`` holding an ``R.npy``, and the blend is not a camera.
BLENDED_FILE = "R_blend.npy"


@dataclass
class BlendedField:
    """The weighted blend of the per-camera fields, as written by :func:`blend_fields`.

    Attributes
    ----------
    directory : pathlib.Path
        Holds ``R_blend.npy`` ``(U, L, 3)`` (float16 or float32, C order: chunked along
        texels) — or, blended by an engine's tasks from Zarr fields, the Zarr store
        ``R_blend.zarr`` or a link to it in a store (``R_blend.zarr.url``; found as
        :func:`find_field` finds a camera's field) — ``texel_index.npy`` ``(U,)`` int64,
        ``weight.npy`` ``(U,)`` float32 and ``n_cameras.npy`` ``(U,)`` int16.
    texel_index : (U,) int64
        Texels some camera weights (> 0), ascending.
    weight : (U,) float32
        ``Σ_c w_c`` over the cameras that weight the texel.
    n_cameras : (U,) int16
        How many cameras weight the texel.
    n_lights : int
    """

    directory: Path
    texel_index: np.ndarray
    weight: np.ndarray
    n_cameras: np.ndarray
    n_lights: int

    def field(self) -> np.ndarray:
        """The blended ``R`` ``(U, L, 3)``, read-only: memory-mapped, or the Zarr array
        (:func:`open_field`, either format)."""
        return open_field(self.directory, name=BLENDED_FILE)


def _camera_field(item) -> tuple[str, np.ndarray, np.ndarray, np.ndarray]:
    """(name, R memmap, texel_index, weight) of a ProjectedField or a camera folder."""
    # a ProjectedField (reflectance's, not imported here: it imports this module) has .directory
    d = Path(getattr(item, "directory", item))
    R = open_field(d)
    try:
        idx = np.load(d / "texel_index.npy")
        w = np.load(d / "weight.npy")
    except FileNotFoundError as exc:
        raise InputError(f"{d}: texel_index.npy and weight.npy must sit beside R.npy "
                         f"(a folder written by project_camera)") from exc
    if idx.shape != (R.shape[0],) or w.shape != (R.shape[0],):
        raise ShapeError(f"{d}: R.npy {R.shape}, texel_index.npy {idx.shape} and weight.npy "
                         f"{w.shape} disagree (expected {R.shape[0]} texels each)")
    if idx.size > 1 and not np.all(np.diff(idx) > 0):
        raise InputError(f"{d}: texel_index.npy must be strictly ascending")
    return d.name, R, idx.astype(np.int64), w.astype(np.float32)


def blend_sources(fields: Iterable) -> tuple[list, np.ndarray]:
    """The cameras a blend reads, checked, and the texels it covers.

    Returns ``(cams, U)``: per camera, in the order given, ``(name, R, texel_index, weight)``
    (``R`` opened read-only by :func:`open_field`, either format or a link; ``texel_index``
    ``(T_c,)`` int64 strictly ascending; ``weight`` ``(T_c,)`` float32) and ``U`` ``(U,)``
    int64, the ascending union of their texels: the blend's rows.

    Raises
    ------
    InputError
        No fields, different light counts, malformed folders.
    """
    cams = [_camera_field(f) for f in fields]
    if not cams:
        raise InputError("fields: expected at least one projected camera field")
    L = cams[0][1].shape[1]
    for name, R, _, _ in cams:
        if R.shape[1:] != (L, 3):
            raise ShapeError(f"fields: camera {fmt_value(name)} has R of shape {R.shape}, "
                             f"expected (T_c, {L}, 3) like {fmt_value(cams[0][0])}")
    U = np.unique(np.concatenate([idx for _, _, idx, _ in cams]))
    return cams, U.astype(np.int64)


def blend_weights(cams, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(weight, n_cameras)`` of the blend's rows ``U`` (:func:`blend_sources`): ``Σ_c w_c``
    ``(U,)`` float32, summed in camera order (the bits :func:`blend_fields` writes), and how
    many cameras weight each texel ``(U,)`` int16."""
    wsum = np.zeros(U.size, np.float32)
    ncam = np.zeros(U.size, np.int16)
    for _, _, idx, w in cams:
        pos = np.searchsorted(U, idx)  # every texel of a camera is in U, once
        wsum[pos] += w
        ncam[pos] += 1
    return wsum, ncam


def save_blend_index(directory, U: np.ndarray, weight: np.ndarray,
                     n_cameras: np.ndarray) -> None:
    """The blend's ``texel_index.npy``, ``weight.npy`` and ``n_cameras.npy`` into
    ``directory`` (beside its field; :class:`BlendedField`)."""
    directory = Path(directory)
    np.save(directory / "texel_index.npy", U.astype(np.int64))
    np.save(directory / "weight.npy", weight)
    np.save(directory / "n_cameras.npy", n_cameras)


def blend_compiled(cams, dtype: str) -> bool:
    """Whether a blend of ``cams`` (:func:`blend_sources`) into ``dtype`` runs the compiled
    float16 kernels (:data:`BLEND_KERNELS`; every field and the blend float16) — the same bits
    as the numpy path, decided once for every chunk of a blend."""
    return bool(BLEND_KERNELS and np.dtype(dtype) == np.float16
                and all(R.dtype == np.float16 for _, R, _, _ in cams))


def blend_block(parts, out_rows: np.ndarray, compiled: bool) -> None:
    """Rows of the blend ``R_b = Σ_c w_c R_c / Σ_c w_c`` (:func:`blend_fields`) into
    ``out_rows``, from each camera's rows that fall in them.

    Parameters
    ----------
    parts : list of (R, a, b, pos, w)
        Per camera, in camera order (the sums' order: the same bits whatever the chunking):
        its field ``R`` (an ``.npy`` memory map or a Zarr array), the rows ``a:b`` of it that
        fall in the block, their rows ``pos`` ``(b - a,)`` int in the block (ascending) and
        weights ``w`` ``(b - a,)`` float32.
    out_rows : (n, L, 3) ndarray, float16 or float32, writable
        The block of the blend (a memory map's rows, or an array written to a Zarr store
        after); every element written (NaN where no camera has a finite sample).
    compiled : bool
        :func:`blend_compiled`.
    """
    n, L = out_rows.shape[:2]
    num = np.zeros((n, L, 3), np.float32)
    den = np.zeros((n, L, 3), np.float32)
    if compiled:
        # float16 in and out: the compiled blend on the bits (_blend_kernels: the same float32
        # steps and roundings, bit for bit; ≈ 7× faster at the paper preset)
        from facegeo.surface._blend_kernels import accumulate_rows, quotient_rows
        from facegeo.surface._half import host_has_f16c

        f16c = host_has_f16c()
    for R, a, b, pos, w in parts:
        if compiled:
            bits = np.asarray(R[a:b]).view(np.uint16).reshape(b - a, L * 3)
            accumulate_rows(bits, np.asarray(pos, np.int64), w, num.reshape(n, L * 3),
                            den.reshape(n, L * 3), f16c)
            _release_rows(R, a, b, write=False)
        else:
            rows = np.array(R[a:b], dtype=np.float32)
            _release_rows(R, a, b, write=False)
            ok = np.isfinite(rows)
            wc = np.broadcast_to(w[:, None, None], rows.shape)
            with np.errstate(invalid="ignore"):  # 0 · inf of a masked sample, left out
                num[pos] += np.where(ok, wc * rows, 0.0)
            den[pos] += np.where(ok, wc, 0.0)
    if compiled:
        quotient_rows(num.reshape(n, L * 3), den.reshape(n, L * 3),
                      np.asarray(out_rows).view(np.uint16).reshape(n, L * 3), f16c)
    else:
        with np.errstate(invalid="ignore", divide="ignore"):
            out_rows[...] = np.where(den > 0, num / den, np.nan)


def blend_rows_task(sources: list, out_location: str, s: int, n: int, L: int, dtype: str,
                    compiled: bool) -> dict:
    """One task of a blend run by an engine: rows ``s:s+n`` of the blend, computed as
    :func:`blend_fields` computes them (:func:`blend_block`: the same bits), written into the
    blend at ``out_location``.

    Reads only those rows' samples of each camera field. ``out_location`` is the blend's
    ``.npy`` (created whole by the client; opened ``r+``, the task writes its disjoint rows:
    workers that share the disk) or its Zarr store (``….zarr``, a folder or an fsspec URL:
    ``s:s+n`` covers whole chunks of it, so tasks never share a chunk and need no lock).

    Parameters
    ----------
    sources : list of (kind, location, a, b, pos, w)
        Per camera with rows in the block, in camera order: its field as :func:`find_field`
        found it, and the ``(R, a, b, pos, w)`` of :func:`blend_block`.
    out_location : str
    s, n : int — the block's first row and row count
    L : int — lights
    dtype : {"float16", "float32"} — the blend's
    compiled : bool — :func:`blend_compiled`, decided once for the whole blend

    Returns
    -------
    dict
        ``{"rows": n}``.
    """
    from facegeo.surface._zarr_field import ZARR_SUFFIX

    parts = [(_open_found(kind, loc), int(a), int(b), np.asarray(pos, np.int64),
              np.asarray(w, np.float32)) for kind, loc, a, b, pos, w in sources]
    s, n = int(s), int(n)
    if str(out_location).rstrip("/").endswith(ZARR_SUFFIX):
        block = np.empty((n, int(L), 3), np.dtype(dtype))
        blend_block(parts, block, compiled)
        write_field_chunk(out_location, s, 0, block)
    else:
        out = np.load(out_location, mmap_mode="r+")
        if out.shape[1:] != (int(L), 3) or out.dtype != np.dtype(dtype) or s + n > len(out):
            raise ShapeError(f"{out_location}: {out.shape} {out.dtype}, a blend task writes "
                             f"rows {s}:{s + n} of (U, {L}, 3) {dtype}")
        blend_block(parts, out[s:s + n], compiled)
        out.flush()
        _release_rows(out, s, s + n, write=True)
        del out
    return {"rows": n}


def blend_fields(fields: Iterable, directory, *, dtype: str = "float16",
                 chunk_texels: int | None = None) -> BlendedField:
    """Blend per-camera fields into one field for fixed-viewpoint uses, streamed along texels.

    ``R_b[t, l] = Σ_c w_c(t) R_c[t, l] / Σ_c w_c(t)`` over the cameras ``c`` that weight texel
    ``t`` — the issue's "blended field" beside the per-camera fields ``R_c`` of Debevec et al.
    2000 Eq. (2) taken onto the surface (§2.1). The weights are light-independent
    (:func:`camera_visibility`), so the blend is linear in the frames and relighting it
    (Eq. 4) equals blending the relit cameras. A masked sample (NaN in ``R_c``) is left out of
    its texel's blend for that light and channel and the other cameras are renormalised; with
    no finite sample left the result is NaN (never a fake value). The blend discards the view
    dependence (``v_c``): it suits a viewpoint near the cameras, not novel views.

    Parameters
    ----------
    fields : iterable of ProjectedField or path-like
        Camera folders written by :func:`project_camera` (same number of lights).
    directory : path-like
        Created; receives the files listed in :class:`BlendedField`.
    dtype : {"float16", "float32"}
        On-disk type (computation is float32).
    chunk_texels : int, optional
        Texels of the blend computed per step (resident memory ≈ ``chunk × L × 3 × 24`` B);
        default: as many as make a 32 MB float32 chunk (1,365 texels at 2048 lights).

    Returns
    -------
    BlendedField

    Raises
    ------
    InputError
        No fields, fields with different light counts, unknown ``dtype``, malformed folders.
    """
    if dtype not in ("float16", "float32"):
        raise InputError(f"dtype: expected 'float16' or 'float32', got {fmt_value(dtype)}")
    cams, U = blend_sources(fields)
    L = cams[0][1].shape[1]
    chunk_texels = _chunk_rows(cams[0][1], chunk_texels)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    out = np.lib.format.open_memmap(directory / BLENDED_FILE, mode="w+", dtype=dtype,
                                    shape=(U.size, L, 3))
    wsum = np.zeros(U.size, np.float32)
    ncam = np.zeros(U.size, np.int16)
    step = int(chunk_texels)
    compiled = blend_compiled(cams, dtype)
    for s in range(0, U.size, step):
        u = U[s:s + step]
        parts = []
        for _, R, idx, w in cams:
            a, b = np.searchsorted(idx, [u[0], u[-1] + 1])
            if b <= a:
                continue
            pos = np.searchsorted(u, idx[a:b])  # unique within one camera
            parts.append((R, int(a), int(b), pos, w[a:b]))
            wsum[s + pos] += w[a:b]
            ncam[s + pos] += 1
        blend_block(parts, out[s:s + u.size], compiled)
        _release_rows(out, s, s + u.size, write=True)
    del out
    save_blend_index(directory, U, wsum, ncam)
    log.info("blend: %d cameras -> %d texels × %d lights", len(cams), U.size, L)
    return BlendedField(directory, U.astype(np.int64), wsum, ncam, int(L))


def open_blended(directory) -> BlendedField:
    """Read the blended field written by :func:`blend_fields` (``R`` stays memory-mapped:
    :meth:`BlendedField.field`, or ``iter_field_chunks(directory, name=BLENDED_FILE)``)."""
    d = Path(directory)
    R = open_field(d, name=BLENDED_FILE)
    try:
        idx, w, n = (np.load(d / f) for f in ("texel_index.npy", "weight.npy",
                                               "n_cameras.npy"))
    except FileNotFoundError as exc:
        raise InputError(f"{d}: texel_index.npy, weight.npy and n_cameras.npy must sit beside "
                         f"{BLENDED_FILE} (a folder written by blend_fields)") from exc
    if not (idx.shape == w.shape == n.shape == (R.shape[0],)):
        raise ShapeError(f"{d}: {BLENDED_FILE} {R.shape}, texel_index.npy {idx.shape}, "
                         f"weight.npy {w.shape}, n_cameras.npy {n.shape} disagree")
    return BlendedField(d, idx.astype(np.int64), w, n, int(R.shape[1]))
