"""The ``project`` stage's cameras split into tasks by blocks of lights (issue 38).

A rig of few cameras and many lights (the paper's: 1–2 cameras × 2,048 lights) cannot keep more
workers busy than it has cameras when each camera is one task
(:func:`facegeo.pipeline.project.project_camera_task`). With light blocks a camera's projection
is two kinds of tasks of the same engine, run in two rounds:

1. its **visibility task** (:func:`facegeo.pipeline.project.light_visibility_task`): the
   camera's visibility over the atlas — the very code of a whole camera's task
   (:func:`facegeo.pipeline._project_tasks._visible_texels`) — written as the camera's
   ``texel_index.npy``, ``weight.npy``, ``v_world.npy`` and ``visibility.npz``; the camera's
   whole field created empty (``R.npy`` ``(T_c, L, 3)``, or the Zarr store ``R.zarr`` with the
   chunks a whole camera's field has); and the projected texels' pixel positions saved for the
   blocks (a scratch file, removed when the stage's tasks are done;
   :func:`prepare_split_camera`);
2. its **light-block tasks** (:func:`facegeo.pipeline.project.light_block_task`), one per block
   of ``lights_per_task`` lights — whole multiples of the field's light chunking
   (``min(block_lights, L)``): each reads only its lights' OLAT frames, samples them at the
   saved positions (with the camera's shadow-consistent taps, rebuilt per task) and writes its
   lights' columns of the field (:func:`project_light_block`).

The field holds the same bytes as a whole camera's task writes: the same samples, converted to
the disk type the same way, flushed in the same blocks of ``block_lights`` (a block task starts
on a whole chunk). A Zarr field's tasks write disjoint whole chunks (no lock). An ``.npy``
field's tasks write their light columns in place through a memory map of the one ``R.npy``:
every texel row holds all lights, so two tasks write disjoint bytes of the same pages. That is
safe where the writers share one page cache — processes on one machine (a ``LocalCluster``,
in process): ``MAP_SHARED`` mappings of a file are the same physical pages, a store to some
bytes never rewrites the others, and ``madvise(MADV_DONTNEED)`` (``_release_rows``) only unmaps
a page whose dirty data stays in the page cache. It is not safe across machines (each keeps its
own copy of a page and writes the whole page back): light blocks of an ``.npy`` field need every
worker on one host (:func:`npy_blocks_safe`), otherwise use ``field_format="zarr"``. The
alternative, a part file per block assembled by the client, would copy every field once more
on the client (a paper camera's 2.1 GB).

Why a visibility round rather than each block computing the visibility itself: the field must
exist, at its final size ``T_c`` (known only once the visibility is), before any block writes
into it; one task per camera computes it once and the blocks start from its result. Its cost is
one visibility per camera before the blocks run (the small preset's visibility task: 0.13–0.15
s against 5–9 s a block of 256 lights); the blocks repeat only the loading of the atlas and
scenes (once per worker process) and the shadow taps' construction.

Automatic rule (:func:`auto_lights_per_task`, ``lights_per_task=None`` on a Dask engine): split
when the scan has fewer cameras than 2 × the engine's workers — unless the cameras are a whole
multiple of the workers (as many cameras on every worker: nothing to balance; measured on the
small preset, 2 cameras on 2 workers took 21.9 s in blocks against 17.9 s whole) — into as many
blocks per camera as make at least 2 × workers tasks in all, each block at least
:data:`AUTO_MIN_LIGHTS` lights (rounded up to whole chunks): a task's fixed cost — the atlas
and scenes once per worker, the shadow taps' construction, the frame reader's start — is paid
per block. One camera of the small preset (512 lights) on 2 workers: 8.5–10.1 s in two blocks
against 11.2–12.6 s whole (2 cores shared with other jobs; docs/scale.md §1). In process (one
task at a time) the default stays one task per camera.
"""

from __future__ import annotations

import logging
import math
import shutil
from pathlib import Path
from urllib.parse import urlparse

import numpy as np

from facegeo.checks import check_positive_int, fmt_value
from facegeo.errors import InputError, ShapeError

log = logging.getLogger(__name__)

__all__ = ["AUTO_MIN_LIGHTS", "AUTO_TASKS_PER_WORKER", "SCRATCH_DIR", "auto_lights_per_task",
           "light_blocks", "whole_chunks", "npy_blocks_safe", "plan_lights_per_task",
           "prepare_split_camera", "load_selection", "project_light_block",
           "camera_block_metrics", "run_rounds", "remove_scratch"]

#: Fewest lights of an automatic light block (the fixed cost of a task amortised over enough
#: frames: module docstring).
AUTO_MIN_LIGHTS = 256
#: The automatic rule splits when the scan has fewer cameras than this many tasks per worker.
AUTO_TASKS_PER_WORKER = 2
#: Folder of the stage folder holding the blocks' scratch files while the tasks run.
SCRATCH_DIR = "_light_blocks"


def whole_chunks(lights: int, chunk: int) -> int:
    """``lights`` rounded up to a whole multiple of ``chunk`` (the field's lights per chunk)."""
    return -(-int(lights) // int(chunk)) * int(chunk)


def auto_lights_per_task(n_cameras: int, n_lights: int, chunk: int, engine) -> int | None:
    """The automatic ``lights_per_task`` (module docstring): None (one task per camera) in
    process, when ``n_cameras >= AUTO_TASKS_PER_WORKER × workers``, or when the cameras are a
    whole multiple of the workers (each worker has as many cameras: nothing to balance); else
    the lights of a block such that every camera makes ``ceil(2 × workers / n_cameras)``
    blocks, in whole ``chunk``s and at least :data:`AUTO_MIN_LIGHTS`; None again when that is
    the whole camera.
    """
    if engine.kind == "in-process":
        return None
    workers = int(engine.n_workers)
    target = AUTO_TASKS_PER_WORKER * workers
    if n_cameras <= 0 or n_cameras >= target or n_cameras % workers == 0:
        return None
    per_camera = -(-target // int(n_cameras))
    lights = max(whole_chunks(math.ceil(n_lights / per_camera), chunk),
                 whole_chunks(AUTO_MIN_LIGHTS, chunk))
    return lights if lights < n_lights else None


def light_blocks(n_lights: int, lights_per_task: int) -> list[tuple[int, int]]:
    """``[(l0, l1), ...]``: the lights ``0 … n_lights−1`` cut into blocks of
    ``lights_per_task`` (the last one shorter)."""
    return [(l0, min(l0 + lights_per_task, n_lights))
            for l0 in range(0, n_lights, lights_per_task)]


def npy_blocks_safe(engine) -> bool:
    """Whether light blocks may write an ``.npy`` field in place: every task runs on one
    machine (in process, a ``LocalCluster``, or a scheduler whose workers share one host; module
    docstring)."""
    client = getattr(engine, "client", None)
    if engine.kind in ("in-process", "local-cluster") or client is None:
        return True
    hosts = {urlparse(a).hostname for a in client.scheduler_info().get("workers", {})}
    return len(hosts) <= 1


def check_lights_per_task(value) -> int | None:
    """``lights_per_task`` validated: None or an integer >= 1 (InputError otherwise)."""
    if value is None:
        return None
    return check_positive_int(value, "lights_per_task")


def _scratch_q(scratch: Path, name: str) -> Path:
    return Path(scratch) / f"{name}.q.npy"


def prepare_split_camera(d: Path, vis, n_lights: int, dtype: str, chunk: int,
                         field_format: str, scratch, name: str) -> dict:
    """Round 1 of a camera split into light blocks, once its visibility ``vis`` is known
    (module docstring; :func:`facegeo.pipeline.project.light_visibility_task`): its small files
    and empty field in the camera folder ``d``, the projected texels' pixel positions
    ``(T_c, 2)`` float64 in ``scratch``. Returns ``visible_fraction`` and ``weighted_texels``."""
    from facegeo.surface import reflectance as rf

    d = Path(d)
    d.mkdir(parents=True, exist_ok=True)
    sel = np.flatnonzero(vis.weight > 0)
    # the field a whole camera's task creates (rf.project_camera): the same header or chunks
    R = rf._new_field(d, field_format, dtype, (sel.size, int(n_lights), 3), int(chunk))
    del R
    np.save(d / "texel_index.npy", sel.astype(np.int64))
    np.save(d / "weight.npy", vis.weight[sel])
    np.save(d / "v_world.npy", vis.v_world[sel])
    Path(scratch).mkdir(parents=True, exist_ok=True)
    np.save(_scratch_q(scratch, name), vis.q[sel])
    return {"visible_fraction": round(vis.visible_fraction, 6), "weighted_texels": int(sel.size)}


def load_selection(d: Path, scratch, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(texel_index (T_c,) int64, q (T_c, 2) float64)``: what a camera's visibility task
    left for its light blocks."""
    return np.load(Path(d) / "texel_index.npy"), np.load(_scratch_q(scratch, name))


def _open_for_block(d: Path, field_format: str):
    from facegeo.surface import reflectance as rf

    if field_format == "npy":
        return np.lib.format.open_memmap(d / "R.npy", mode="r+")
    return rf.open_zarr_field(rf.field_location(d), mode="r+")


def project_light_block(frames, d: Path, q: np.ndarray, size: tuple[int, int], name: str,
                        lights: tuple[int, int], chunk: int, dtype: str, taps,
                        field_format: str) -> dict:
    """Round 2 of a camera split into light blocks (module docstring;
    :func:`facegeo.pipeline.project.light_block_task`): the OLAT ``frames`` of ``lights = (l0,
    l1)`` (``(light, frame, valid)`` in light order) sampled at the camera's projected texels'
    pixels ``q`` (with the shadow ``taps``, or None) and written into columns ``l0:l1`` of the
    field in the camera folder ``d``, in blocks of ``chunk`` lights — Debevec et al. 2000
    Eq. (2), ``R_c[t, l] = L_l(q_c(t))``, exactly as
    :func:`facegeo.surface.reflectance.project_camera` computes it for the whole camera.

    Returns ``masked_samples``, ``float16_overflow`` and with taps ``shadow_changed``,
    ``shadow_samples``, ``seconds_shadow_taps`` (summed over a camera's blocks by
    :func:`camera_block_metrics`).

    Raises
    ------
    InputError
        A frame out of order or missing; ``l0`` not on a whole chunk.
    ShapeError
        A frame or mask of the wrong size; a field of another size than the visibility's.
    """
    from facegeo.surface import reflectance as rf

    l0, l1 = (int(v) for v in lights)
    B = int(chunk)
    if l0 % B or not 0 <= l0 < l1:
        raise InputError(f"camera {fmt_value(name)}: light block {l0}:{l1} does not start on a "
                         f"whole chunk of {B} lights")
    W, H = (int(v) for v in size)
    n = len(q)
    sampler = rf.frame_sampler(q, W, H)
    if taps is not None and len(taps.index) != n:
        raise ShapeError(f"camera {fmt_value(name)}: shadows holds {len(taps.index)} samples, "
                         f"the camera projects {n} texels")
    R = _open_for_block(Path(d), field_format)
    if R.shape[0] != n or R.shape[1] < l1:
        raise ShapeError(f"camera {fmt_value(name)}: field {R.shape}, expected {n} texels and "
                         f"at least {l1} lights (its visibility task's)")
    n_masked, n_overflow = rf.fill_light_columns(R, frames, sampler, taps, (l0, l1), B, dtype,
                                                 name, (W, H))
    del R
    out = {"masked_samples": n_masked, "float16_overflow": n_overflow}
    if taps is not None:
        out.update(shadow_changed=int(taps.changed), shadow_samples=int(taps.samples),
                   seconds_shadow_taps=round(taps.seconds, 4))
    return out


def camera_block_metrics(vis: dict, blocks: list[dict], n_lights: int) -> dict:
    """A camera's metrics from its visibility task's and its light blocks' (the keys of a whole
    camera's task, :func:`facegeo.pipeline._project_tasks._project_camera`): counts summed, the shadow
    taps' fraction from the summed counts (the same figure), ``seconds_projection`` the blocks'
    seconds summed (task time, not wall time)."""
    seconds = sum(b["seconds_projection"] for b in blocks)
    T_c = vis["weighted_texels"]
    entry = {
        "visible_fraction": vis["visible_fraction"],
        "weighted_texels": T_c,
        "seconds_visibility": vis["seconds_visibility"],
        "seconds_projection": round(seconds, 4),
        "texels_per_second": round(T_c * n_lights / max(seconds, 1e-9), 1),
        "masked_samples": sum(b["masked_samples"] for b in blocks),
        "float16_overflow": sum(b["float16_overflow"] for b in blocks),
        "shadow_taps": "shadow_samples" in blocks[0],
    }
    if "inferred_texels_unmeasured" in vis:
        entry["inferred_texels_unmeasured"] = vis["inferred_texels_unmeasured"]
    if entry["shadow_taps"]:
        changed = sum(b["shadow_changed"] for b in blocks)
        samples = sum(b["shadow_samples"] for b in blocks)
        entry["shadow_edge_samples"] = round(changed / max(samples, 1), 6)
        entry["seconds_shadow_taps"] = round(sum(b["seconds_shadow_taps"] for b in blocks), 4)
    return entry


def remove_scratch(dest: Path) -> None:
    """Remove the blocks' scratch folder from the stage folder ``dest`` (not a product)."""
    shutil.rmtree(Path(dest) / SCRATCH_DIR, ignore_errors=True)


def plan_lights_per_task(lights_per_task, *, engine, n_cameras: int, n_lights: int,
                         chunk: int, field_format: str, in_store: bool) -> int | None:
    """The lights of each block task, or None (one task per camera): ``lights_per_task``
    rounded up to whole ``chunk``s (the field's lights per chunk), or the automatic rule's
    (:func:`auto_lights_per_task`) when None; None too when a block would be the whole camera.

    Raises
    ------
    InputError
        ``lights_per_task`` not an integer >= 1; given with a ``store`` (not supported: each
        camera's task writes its field through the store whole), or with ``.npy`` fields on
        workers of several machines (:func:`npy_blocks_safe`).
    """
    lpt = check_lights_per_task(lights_per_task)
    npy_unsafe = field_format == "npy" and not npy_blocks_safe(engine)
    if lpt is None:
        if in_store or npy_unsafe:
            return None
        return auto_lights_per_task(n_cameras, n_lights, chunk, engine)
    if in_store:
        raise InputError("lights_per_task: not available with store= (--store): a camera's "
                         "task writes its field into the store whole; leave it unset")
    if npy_unsafe:
        raise InputError("lights_per_task: the workers are on several machines and .npy "
                         "fields are written in place through a memory map, which is safe only "
                         "on one machine; use field_format='zarr' or leave lights_per_task "
                         "unset")
    used = whole_chunks(lpt, chunk)
    if used != lpt:
        log.info("project: lights_per_task %d rounded up to %d (whole chunks of %d lights)",
                 lpt, used, chunk)
    return used if used < n_lights else None


def run_rounds(engine, whole: list, visibility: list, blocks: list, progress=None) -> dict:
    """Run the projection's tasks: round 1 the ``whole`` cameras' tasks and the split cameras'
    ``visibility`` tasks, round 2 the light ``blocks`` (their working sets all checked before
    anything runs). Returns ``{task name: result}``. ``progress(stage, done, total)`` counts
    cameras when nothing is split (as before), else lights projected (each task's
    :attr:`~facegeo.pipeline.engine.Task.size`)."""
    if not blocks:
        tasks = whole + visibility
        return {t.name: r for t, r in zip(tasks, engine.map("project", tasks,
                                                                progress=progress))}
    engine.check_fits("project", whole + visibility + blocks)
    total = sum(t.size for t in whole + visibility + blocks)
    out = {}
    offset = 0
    for tasks in (whole + visibility, blocks):
        prog = None
        if progress is not None:
            def prog(stage, done, _n, _offset=offset):
                progress(stage, _offset + done, total)
        out.update({t.name: r for t, r in zip(tasks, engine.map("project", tasks,
                                                                    progress=prog))})
        offset += sum(t.size for t in tasks)
    return out
