"""The texture relight's task machinery (Debevec et al. 2000 §3.3, Eq. 4 on a camera's field,
rows at a time), split out of :mod:`facegeo.pipeline.relight`, which re-exports the public
names (``relight_rows_task``, ``relight_working_set``).

:func:`facegeo.pipeline.relight.relight_texture` plans the tasks and blends their rows; here
are the steps it calls: the stage folders it reads (:func:`_texture_dirs`,
:func:`_project_cameras`), one task's memory (:func:`relight_working_set`) and work
(:func:`relight_rows_task`), and the relit rows the tasks write and the client reads back
(:func:`_relit_rows_target`, :func:`_read_relit_rows`). The tunable task sizes
(``RELIGHT_TASK_TEXELS``, ``RELIGHT_MAPS_PER_TASK``) stay in :mod:`facegeo.pipeline.relight`
with the functions that read them.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from facegeo.errors import InputError


def _project_cameras(project_dir: Path, texels_path: Path) -> list[Path]:
    """The camera folders of ``project_dir`` that hold a projected field, sorted."""
    from facegeo.surface.reflectance import field_folders

    cams = field_folders(project_dir)  # R.npy or R.zarr
    if not cams or not texels_path.is_file():
        raise InputError(f"{project_dir.parent}: relighting in texture space needs the texture "
                         f"atlas ({texels_path}) and the surface reflectance field "
                         f"({project_dir}/<camera>/R.npy); run 'facegeo project SCAN' first")
    from facegeo.pipeline.project import check_projection_atlas

    check_projection_atlas(project_dir, texels_path)
    return cams


#: Bytes a relight task needs per sample (texel × light × channel) of its rows: the rows read
#: (float16 from a Zarr store, or the memory map's pages, resident once read: 2 B; 4 B for a
#: float32 field).
RELIGHT_BYTES_PER_SAMPLE = 2
#: ... and once: :func:`facegeo.lighting.relight.relight_field`'s chunk buffers (its
#: ``FUSED_CHUNK_BYTES`` = 16 MiB of float16, or ``CHUNK_BYTES`` of float32, per thread: one
#: thread on a worker) and the relit rows (12 B a texel, counted per texel below).
RELIGHT_BYTES_FIXED = 32 << 20
RELIGHT_BYTES_PER_TEXEL = 3 * 4 + 3 * 8


def relight_working_set(n_texels: int, n_lights: int, itemsize: int = 2,
                        n_maps: int = 1) -> int:
    """Memory (bytes) one relight task needs for ``n_texels`` rows of a field of ``n_lights``
    lights relit under ``n_maps`` environment maps at once::

        n × L × 3 × itemsize  +  n × B × 36 B  +  32 MiB

    the rows (:data:`RELIGHT_BYTES_PER_SAMPLE` × ``itemsize`` / 2 a sample, read once for the
    B maps), the relit rows of each map and their float64 blend
    (:data:`RELIGHT_BYTES_PER_TEXEL` a texel and map), the relighting's chunk buffers
    (:data:`RELIGHT_BYTES_FIXED`)."""
    n, L, B = int(n_texels), int(n_lights), max(1, int(n_maps))
    return (n * L * 3 * RELIGHT_BYTES_PER_SAMPLE * int(itemsize) // 2
            + n * B * RELIGHT_BYTES_PER_TEXEL + RELIGHT_BYTES_FIXED)


def relight_rows_task(field: tuple[str, str], relit: str, s0: int, s1: int, weights,
                      light_color=None) -> dict:
    """One relight task: rows ``s0:s1`` of a camera's field relit (Eq. 4,
    :func:`facegeo.lighting.relight.relight_field`) into rows ``s0:s1`` of ``relit``.

    ``field`` is ``(kind, location)`` (:func:`facegeo.surface.reflectance.find_field`: an
    ``R.npy`` path, or a Zarr store — a folder or an fsspec URL); ``weights`` ``(L, 3)`` (one
    map) or ``(B, L, 3)`` (a batch of B maps: the rows are read once, one GEMM a chunk);
    ``relit`` the float32 rows the stage created, ``(T_c, 3)`` for ``(L, 3)`` weights and
    ``(B, T_c, 3)`` for a batch: a ``.npy`` file, or a Zarr array (a path ending in ``.zarr``
    or a URL: workers that share no disk). Tasks write disjoint rows (whole chunks of a Zarr
    array). Reads only its rows (a memory map, or the Zarr chunks they fall in)."""
    from facegeo.lighting.relight import relight_field
    from facegeo.surface._zarr_field import open_zarr_field

    from facegeo.pipeline.fit import _drop_projection_inputs

    t0 = time.perf_counter()
    _drop_projection_inputs()
    kind, loc = field
    R = np.load(loc, mmap_mode="r") if kind == "npy" else open_zarr_field(loc)
    rows = R[s0:s1]  # a view of the memory map, or the Zarr chunks read
    out = relight_field(rows, weights, light_color=light_color, workers=1)
    sel = (slice(s0, s1),) if out.ndim == 2 else (slice(None), slice(s0, s1))
    if _is_zarr_target(relit):
        import zarr

        zarr.open_array(relit, mode="r+")[sel] = out
    else:
        dst = np.load(relit, mmap_mode="r+")
        dst[sel] = out
        dst.flush()
        del dst
    return {"texels": int(s1 - s0), "maps": 1 if out.ndim == 2 else int(out.shape[0]),
            "seconds": time.perf_counter() - t0}


def _is_zarr_target(location: str) -> bool:
    return "://" in str(location) or str(location).endswith(".zarr")


def _relit_rows_target(parts, name: str, n: int, step: int, n_maps: int) -> str:
    """Create the ``(n_maps, n, 3)`` float32 relit rows ``name`` (a camera and a batch of
    maps) in ``parts`` (a folder: a ``.npy``; an fsspec URL: a Zarr array chunked by ``step``
    rows and the batch's maps, one chunk a task)."""
    shape = (int(n_maps), int(n), 3)
    if isinstance(parts, str) and "://" in parts and not parts.startswith("file://"):
        import zarr

        loc = f"{parts.rstrip('/')}/{name}.zarr"
        zarr.create_array(store=loc, shape=shape, chunks=(shape[0], max(min(step, n), 1), 3),
                          dtype="float32", fill_value=np.nan, overwrite=True)
        return loc
    folder = Path(parts[len("file://"):] if isinstance(parts, str)
                  and parts.startswith("file://") else parts)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.npy"
    np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=shape).flush()
    return str(path)


def _read_relit_rows(location: str, j: int) -> np.ndarray:
    """Map ``j``'s ``(n, 3)`` relit rows of a ``(B, n, 3)`` target."""
    if _is_zarr_target(location):
        import zarr

        return np.asarray(zarr.open_array(location, mode="r")[j])
    return np.array(np.load(location, mmap_mode="r")[j])


def _texture_dirs(field_dir, project_dir, atlas_dir) -> tuple[Path, Path]:
    """``(project folder, texels.npz path)`` from ``field_dir`` or the explicit folders."""
    if field_dir is None and (project_dir is None or atlas_dir is None):
        raise InputError("relight_texture: give field_dir, or both project_dir and atlas_dir")
    proj = Path(project_dir) if project_dir is not None else Path(field_dir) / "project"
    atlas = Path(atlas_dir) if atlas_dir is not None else Path(field_dir) / "atlas"
    return proj, atlas / "texels.npz"
