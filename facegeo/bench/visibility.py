"""Benchmarks of :mod:`facegeo.surface.visibility` against raw embreex and ``trimesh.ray``.

``visibility.closest_hit``: camera-coherent rays (a pinhole grid) against a displaced sphere of
~1.3 M triangles (quick: ~20 k), head-sized (radius 0.1 m) and seen from 0.5 m.
``visibility.occluded``: incoherent shadow rays from random surface points toward random
directions (the worst case for memory locality; :class:`~facegeo.surface.visibility.RayScene` sorts such
batches in Z-order on large meshes, and a row shows raw embreex on pre-sorted rays).

Ratios are taken **at equal thread counts**: facegeo on 1 thread against raw embreex on 1
thread (one ``EmbreeScene.run`` call on the same float32 arrays and the same BVH, so only
facegeo's overhead differs), and facegeo on 2 threads against raw embreex on 2 threads (the
same ``run`` calls on ray chunks of facegeo's chunk size, mapped over a 2-worker
``ThreadPoolExecutor``). The calls being compared are **interleaved** (each round runs every
case once, the previous result released first) so machine load and the allocator's state hit
them alike; speeds are the best wall time of the rounds, and every facegeo row also gives the
ratio of median CPU times (``time.process_time``, all of the process's threads), which machine
load does not inflate the way it inflates wall time.

``closest_hit`` returns more than raw embreex: ``run(output=1)`` gives float32 ``tfar``, ``u``,
``v`` and int32 ``primID``/``geomID`` (20 bytes per ray); the default :class:`Hits` holds
``hit``, float64 ``t``, ``bary``, ``point``, ``normal`` and int64 ``face`` (89 bytes per ray).
Both are measured: the default, and ``fields=("t", "face", "bary")`` — the information raw
embreex returns, float64-refined (41 bytes per ray). Writing fresh result memory is a large
part of the difference on the development VM (a first touch of a fresh 4 kB page costs
microseconds there). Whether embreex releases the GIL is measured, not assumed: the raw
2-thread row reports its speed-up over the 1-thread call, and how far a pure-Python loop in
the main thread progresses while ``run`` executes in a worker, beside the same figure for
``time.sleep`` (releases the GIL) and for one long C call that holds it (``sum(range(n))``),
measured in the same run (≈ 0.85–1 and ≈ 0.02 on the loaded 2-core machine). trimesh's
``mesh.ray`` (a single-threaded wrapper) is reported beside them. Timings on the shared 2-core
machines are noisy: compare ratios, not absolute speeds, and rerun when another job was using
the second core.

Before/after in one run: with ``FACEGEO_BENCH_PREVIOUS=/path/to/other/checkout`` (for example
the main worktree while a branch is being measured), ``visibility.closest_hit`` also loads that
checkout's ``facegeo/surface/visibility.py`` and its two private modules (copied into a package
of their own, so both versions share nothing but numpy, numba and embreex), builds the same scene
with it and interleaves its calls with the others; its rows state whether its results are
bit-identical to this version's. The copy is a cache, one folder per checkout under facegeo's
cache folder (``$FACEGEO_CACHE_DIR``, else ``$XDG_CACHE_HOME/facegeo``, else
``~/.cache/facegeo``; ``prev-vis/<hash of the checkout's path>``), refreshed from the checkout on
every run and reused: numba caches the compiled kernels (``cache=True``) beside the copied
sources, so a second run does not compile them again, and no run leaves a folder behind in
``/tmp``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facegeo.bench import BenchRow, best_of, register, repeats

_THREADS = (1, 2)


def _raw_chunked(run_chunk, n: int, chunk: int, threads: int):
    """Call ``run_chunk(slice)`` over ``n`` rays in chunks on ``threads`` Python threads."""
    from concurrent.futures import ThreadPoolExecutor

    slices = [slice(s, min(s + chunk, n)) for s in range(0, n, chunk)]
    with ThreadPoolExecutor(max_workers=threads) as ex:
        return list(ex.map(run_chunk, slices))


def _gil_free_fraction(call, min_seconds: float = 0.3) -> float:
    """How far Python runs while ``call()`` runs in another thread (≈1: GIL released, ≈0: held).

    A pure-Python counting loop runs in this thread while ``call`` runs in a worker; its rate is
    compared with its rate alone over the same wall time. Core contention lowers both, so this
    separates "released" from "held", not fine shades.
    """
    import threading
    import time

    def count(ev) -> int:
        k = 0
        while not ev.is_set():
            k += 1
        return k

    def run_then_set(ev) -> None:
        try:  # repeat short calls so thread start-up and switch intervals (5 ms) do not dominate
            end = time.perf_counter() + min_seconds
            call()
            while time.perf_counter() < end:
                call()
        finally:
            ev.set()

    busy_ev = threading.Event()
    t0 = time.perf_counter()
    threading.Thread(target=run_then_set, args=(busy_ev,)).start()
    busy = count(busy_ev)
    elapsed = time.perf_counter() - t0
    alone_ev = threading.Event()
    threading.Timer(elapsed, alone_ev.set).start()  # the same loop, same wall time, no work
    alone = count(alone_ev)
    return float(min(1.0, busy / max(alone, 1)))


def _gil_calibration(seconds: float) -> dict:
    """:func:`_gil_free_fraction` of a call known to release the GIL (``time.sleep``) and of one
    C call known to hold it for its whole length (``sum(range(n))``), each about ``seconds``
    long: under machine load the embreex figure reads against these two, not against 1 and 0."""
    import time

    t0 = time.perf_counter()
    sum(range(1_000_000))
    n = int(1_000_000 * seconds / max(time.perf_counter() - t0, 1e-6))
    return {"released (time.sleep)": _gil_free_fraction(lambda: time.sleep(seconds)),
            "held (one C call, sum(range(n)))": _gil_free_fraction(lambda: sum(range(n)))}


def _interleaved(cases: dict, repeat: int) -> tuple[dict, dict]:
    """Time ``cases`` (key → call) in ``repeat`` interleaved rounds.

    Each round calls every case once, in order; each result is released before the next call.
    Returns the best wall seconds and the median process CPU seconds per case.
    """
    import statistics
    import time

    wall: dict = {k: [] for k in cases}
    cpu: dict = {k: [] for k in cases}
    for _ in range(repeats(repeat)):
        for k, call in cases.items():
            c0, t0 = time.process_time(), time.perf_counter()
            out = call()
            wall[k].append(time.perf_counter() - t0)
            cpu[k].append(time.process_time() - c0)
            del out
    return ({k: min(v) for k, v in wall.items()},
            {k: statistics.median(v) for k, v in cpu.items()})


def _thread_rows(name: str, label: str, ours: dict, raw: dict, n: int, baseline: str,
                 cpu: dict | None = None) -> list[BenchRow]:
    """facegeo rows at each thread count with the ratio to the raw-embreex case ``baseline``
    at the same thread count (``ours``/``raw``: thread count → best wall seconds; ``cpu``:
    thread count → ratio of median process CPU times, raw over ours, reported beside)."""
    rows = []
    for th in _THREADS:
        t = f"{th} thread{'s' if th > 1 else ''}"
        key = f"vs {baseline}, {t}"
        ratios = {key: raw[th] / ours[th]}
        if cpu is not None:
            ratios[f"{key}, median CPU time"] = cpu[th]
        rows.append(BenchRow(name, f"{label} ({t})", n / ours[th] / 1e6, "Mrays/s",
                             ratios=ratios, threads=th,
                             baseline_threads={k: th for k in ratios}))
    return rows


def _previous_package_dir(root) -> Path:
    """The cache folder of the copy of checkout ``root`` (one per checkout, reused by every
    run): ``<facegeo cache>/prev-vis/<first 16 hex digits of SHA-256 of root's resolved path>``."""
    import hashlib

    from facegeo.appearance.spectral import default_cache_dir

    digest = hashlib.sha256(str(Path(root).resolve()).encode()).hexdigest()[:16]
    return default_cache_dir() / "prev-vis" / digest


def _load_previous(root: str):
    """``RayScene`` of another facegeo checkout ``root`` (its ``facegeo/surface/visibility.py``,
    ``_vis_kernels.py`` and ``_vis_util.py``, copied into a package whose imports of each other
    are redirected to it), for before/after timings in one process. One previous checkout per
    process: later calls return the first one loaded.

    The copy lives in :func:`_previous_package_dir` (a cache, one per checkout; not a new
    temporary folder per run): a file is rewritten only when the checkout's version differs,
    so numba's on-disk cache of the compiled kernels beside it stays valid between runs."""
    import importlib
    import re
    import sys

    from facegeo.errors import InputError
    from facegeo.fsutil import atomic_write_text

    src = Path(root) / "facegeo" / "surface"
    pkg = "_facegeo_previous_vis"
    if pkg not in sys.modules:
        if not (src / "visibility.py").is_file():
            raise InputError(f"FACEGEO_BENCH_PREVIOUS={root}: not a facegeo checkout (no "
                             f"{src / 'visibility.py'})")
        base = _previous_package_dir(root)
        (base / pkg).mkdir(parents=True, exist_ok=True)
        for mod in ("__init__", "visibility", "_vis_kernels", "_vis_util"):
            text = "" if mod == "__init__" else (src / f"{mod}.py").read_text()
            text = re.sub(r"facegeo\.surface\.(_vis_\w+)", pkg + r".\1", text)
            text = text.replace("from facegeo.surface import _vis", f"from {pkg} import _vis")
            dest = base / pkg / f"{mod}.py"
            try:
                same = dest.read_text() == text
            except OSError:
                same = False
            if not same:  # unchanged files keep their mtime: numba's cache index stays valid
                atomic_write_text(dest, text)
        sys.path.insert(0, str(base))
    return importlib.import_module(f"{pkg}.visibility").RayScene


def _same_hits(a, b) -> bool:
    """Whether two :class:`Hits` are bit-identical (NaN equal to NaN, None to None)."""
    for f in ("hit", "t", "face", "bary", "point", "normal"):
        x, y = getattr(a, f), getattr(b, f)
        if (x is None) != (y is None) or (x is not None
                                          and not np.array_equal(x, y, equal_nan=True)):
            return False
    return True

_RADIUS = 0.1  # metres, a head
_CAMERA_DISTANCE = 0.5  # metres


def _mesh(quick: bool):
    """A displaced icosphere (concavities, so some rays meet several layers of surface)."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=5 if quick else 8)
    v = np.asarray(sphere.vertices)
    bump = 1.0 + 0.2 * np.sin(9 * v[:, 0]) * np.sin(7 * v[:, 1] + 1.0) * np.sin(8 * v[:, 2] + 0.5)
    v = _RADIUS * v * bump[:, None]
    return trimesh.Trimesh(v, np.asarray(sphere.faces), process=False)


def _pinhole_rays(n_side: int):
    """Origins (3,) and unit directions (n_side², 3) of a pinhole camera on +Z looking at 0."""
    c = np.array([0.013, -0.007, _CAMERA_DISTANCE])
    half = 1.15 * _RADIUS / _CAMERA_DISTANCE  # tan of the half field of view
    x, y = np.meshgrid(np.linspace(-half, half, n_side), np.linspace(-half, half, n_side))
    d = np.stack([x, -y, -np.ones_like(x)], axis=-1).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return c, d


def _trimesh_closest(mesh, o, d):
    """trimesh.ray closest hits as (face, t) arrays, -1 / NaN on miss."""
    tri, ray, loc = mesh.ray.intersects_id(o, d, multiple_hits=False, return_locations=True)
    face = np.full(len(o), -1, dtype=np.int64)
    t = np.full(len(o), np.nan)
    face[ray] = tri
    t[ray] = np.linalg.norm(loc - o[ray], axis=1)
    return face, t


@register("visibility.closest_hit")
def bench_closest_hit(quick: bool) -> list[BenchRow]:
    from facegeo.surface.visibility import RayScene

    import os

    mesh = _mesh(quick)
    n_side = 256 if quick else 1000
    repeat = 15 if quick else 5
    scene = RayScene.from_trimesh(mesh)
    t_build, _ = best_of(scene.build, repeat=1)
    c, d = _pinhole_rays(n_side)
    n = len(d)
    o = np.broadcast_to(c, d.shape)
    # Outside the timing: the float64 face table (built on the first query, like the BVH) and
    # the compiled kernels (loaded from numba's cache on first use).
    scene.closest_hit(o[:16], d[:16])

    # Raw embreex on the same BVH and float32 arrays: one call (1 thread), and the same calls
    # on facegeo's chunks over a 2-worker thread pool (2 threads).
    emb, prim_to_face = scene._scene()
    o32 = np.ascontiguousarray(o - scene._centre, dtype=np.float32)
    d32 = np.ascontiguousarray(d, dtype=np.float32)
    raw_fields = ("t", "face", "bary")

    def ours(th, **kw):
        scene.n_threads = th
        return scene.closest_hit(o, d, **kw)

    cases = {("all", 1): lambda: ours(1), ("raw fields", 1): lambda: ours(1, fields=raw_fields),
             ("raw", 1): lambda: emb.run(o32, d32, output=1)}
    previous_root = os.environ.get("FACEGEO_BENCH_PREVIOUS")
    if previous_root:
        prev = _load_previous(previous_root).from_trimesh(mesh, n_threads=1).build()
        prev.closest_hit(o[:16], d[:16])
        cases[("previous all", 1)] = lambda: prev.closest_hit(o, d)
        cases[("previous raw fields", 1)] = lambda: prev.closest_hit(o, d, fields=raw_fields)
    for th in _THREADS[1:]:
        cases[("all", th)] = lambda th=th: ours(th)
        cases[("raw fields", th)] = lambda th=th: ours(th, fields=raw_fields)
        scene.n_threads = th
        chunk = scene._chunk_rays()  # facegeo's chunks at this thread count
        cases[("raw", th)] = lambda th=th, chunk=chunk: _raw_chunked(
            lambda sl: emb.run(o32[sl], d32[sl], output=1), n, chunk, th)
    # The timed cases' results are released between rounds; the ones compared are recomputed.
    t_wall, t_cpu = _interleaved(cases, repeat)
    hits = ours(1)
    raw = emb.run(o32, d32, output=1)
    t_raw = {th: t_wall[("raw", th)] for th in _THREADS}
    raw_hit = raw["primID"] >= 0
    raw_prim = np.maximum(raw["primID"], 0).astype(np.int64)
    raw_face = np.where(raw_hit, raw_prim if prim_to_face is None else prim_to_face[raw_prim], -1)
    raw_t = np.where(raw_hit, raw["tfar"].astype(np.float64), np.nan)
    both = hits.hit & raw_hit
    err_t = float(np.max(np.abs(hits.t[both] - raw_t[both]) / raw_t[both])) if both.any() else 0.0
    diff_face = float(np.mean(hits.face != raw_face))

    # trimesh's mesh.ray (embreex-backed when embreex is installed), on a subset.
    n_tm = min(n, 200_000)
    sub = np.linspace(0, n - 1, n_tm).astype(np.int64)
    o_tm, d_tm = np.ascontiguousarray(o[sub]), np.ascontiguousarray(d[sub])
    _trimesh_closest(mesh, o_tm[:10], d_tm[:10])  # build trimesh's scene outside the timing
    t_tm, (tm_face, tm_t) = best_of(lambda: _trimesh_closest(mesh, o_tm, d_tm), repeat)
    ours_1 = t_wall[("all", 1)]
    ok = hits.hit[sub] & (tm_face >= 0)
    t_sub = hits.t[sub]
    err_tm = float(np.max(np.abs(tm_t[ok] - t_sub[ok]) / t_sub[ok])) if ok.any() else 0.0
    diff_tm = float(np.mean(tm_face != hits.face[sub]))

    tm_speed = n_tm / t_tm / 1e6
    sizes = {"faces": scene.n_faces, "rays": n, "hit fraction": float(hits.hit.mean())}
    name = "visibility.closest_hit"
    baseline = "raw embreex EmbreeScene.run(output=1) on the same float32 rays and BVH"
    cpu = {k: {th: t_cpu[("raw", th)] / t_cpu[(k, th)] for th in _THREADS}
           for k in ("all", "raw fields")}
    rows = _thread_rows(name, "RayScene.closest_hit, all fields (hit, t, face, bary, point, "
                        "normal; 89 B/ray)", {th: t_wall[("all", th)] for th in _THREADS}, t_raw,
                        n, baseline, cpu["all"])
    rows[0].error, rows[0].error_unit = err_t, "max |Δt|/t vs raw embreex"
    rows[0].extra.update({**sizes, "face ids differing vs embreex": diff_face,
                          "BVH build s": t_build})
    rows += _thread_rows(name, "RayScene.closest_hit(fields=('t', 'face', 'bary')), raw "
                         "embreex's information in float64 (41 B/ray)",
                         {th: t_wall[("raw fields", th)] for th in _THREADS}, t_raw, n, baseline,
                         cpu["raw fields"])
    if previous_root:
        for k, fl, label in (("previous all", None, "all fields"),
                             ("previous raw fields", raw_fields, "fields=('t', 'face', 'bary')")):
            key = f"vs {baseline}, 1 thread"
            rows.append(BenchRow(
                name, f"previous RayScene.closest_hit ({previous_root}), {label} (1 thread)",
                n / t_wall[(k, 1)] / 1e6, "Mrays/s",
                ratios={key: t_raw[1] / t_wall[(k, 1)],
                        f"{key}, median CPU time": t_cpu[("raw", 1)] / t_cpu[(k, 1)]},
                extra={"results bit-identical to this version's": _same_hits(
                    prev.closest_hit(o, d, fields=fl), ours(1, fields=fl))},
                threads=1, baseline_threads={key: 1, f"{key}, median CPU time": 1}))
    gil_free = _gil_free_fraction(lambda: emb.run(o32, d32, output=1))
    rows += _raw_rows(name, "raw embreex run(output=1)", t_raw, n, chunk, sizes, gil_free)
    rows.append(BenchRow(name, "trimesh mesh.ray.intersects_id (single-threaded wrapper)",
                         tm_speed, "Mrays/s", err_tm, "max |Δt|/t vs RayScene",
                         {"RayScene 1 thread vs this": (n / ours_1 / 1e6) / tm_speed},
                         {"rays": n_tm, "face ids differing vs RayScene": diff_tm},
                         threads=1, baseline_threads={"RayScene 1 thread vs this": 1}))
    return rows


def _raw_rows(name: str, label: str, t_raw: dict, n: int, chunk: int, sizes: dict,
              gil_free: float):
    rows = [BenchRow(name, f"{label}, 1 call, 1 thread, robust BVH", n / t_raw[1] / 1e6,
                     "Mrays/s", extra=sizes, threads=1)]
    for th in _THREADS[1:]:
        speedup = t_raw[1] / t_raw[th]
        rows.append(BenchRow(
            name, f"{label}, {chunk}-ray chunks on a {th}-worker ThreadPoolExecutor",
            n / t_raw[th] / 1e6, "Mrays/s",
            extra={"speed-up over 1 thread": speedup,
                   "Python progress during run()": gil_free,
                   **{f"Python progress, {k}": v
                      for k, v in _gil_calibration(0.3).items()}},
            threads=th))
    return rows


def _surface_points(mesh, n: int, rng: np.random.Generator):
    """Uniform random points on the mesh and their face normals."""
    area = np.asarray(mesh.area_faces)
    f = rng.choice(len(area), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)[f]]
    p = np.einsum("ni,nij->nj", w, tri)
    return p, np.asarray(mesh.face_normals)[f]


@register("visibility.occluded")
def bench_occluded(quick: bool) -> list[BenchRow]:
    from facegeo.surface.visibility import RayScene

    rng = np.random.default_rng(20000)
    mesh = _mesh(quick)
    n = 65_536 if quick else 1_000_000
    repeat = 2 if quick else 3
    scene = RayScene.from_trimesh(mesh).build()
    p, nrm = _surface_points(mesh, n, rng)
    scene.occluded(p[:16], nrm[:16], np.inf)  # kernels loaded outside the timing
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # Shadow rays toward the hemisphere above the surface, as toward lights that can reach it.
    d *= np.where(np.einsum("ni,ni->n", d, nrm) < 0, -1.0, 1.0)[:, None]

    emb, _ = scene._scene()
    o32 = np.ascontiguousarray(p + scene.eps * d - scene._centre, dtype=np.float32)
    d32 = np.ascontiguousarray(d, dtype=np.float32)
    far = np.full(n, np.finfo(np.float32).max, dtype=np.float32)

    def ours(th):
        scene.n_threads = th
        return scene.occluded(p, d, np.inf)

    cases = {("ours", 1): lambda: ours(1),
             ("raw", 1): lambda: emb.run(o32, d32, query="OCCLUDED", dists=far)}
    for th in _THREADS[1:]:
        cases[("ours", th)] = lambda th=th: ours(th)
        scene.n_threads = th
        chunk = scene._chunk_rays()  # facegeo's chunks at this thread count
        cases[("raw", th)] = lambda th=th, chunk=chunk: _raw_chunked(
            lambda sl: emb.run(o32[sl], d32[sl], query="OCCLUDED", dists=far[sl]), n, chunk,
            th)
    t_wall, t_cpu = _interleaved(cases, repeat)
    occ = ours(1)
    raw = emb.run(o32, d32, query="OCCLUDED", dists=far)
    t_raw = {th: t_wall[("raw", th)] for th in _THREADS}
    diff_raw = float(np.mean(occ != (raw == 0)))
    # The ceiling for incoherent rays: raw embreex on the same rays in Z-order (sort untimed).
    from facegeo.surface.visibility import _morton_order

    z = _morton_order(p, scene.bounds[0], scene.bounds[1])
    o32z, d32z = np.ascontiguousarray(o32[z]), np.ascontiguousarray(d32[z])
    t_rawz, _ = best_of(lambda: emb.run(o32z, d32z, query="OCCLUDED", dists=far), repeat)
    sorted_auto = scene._ray_order(p, d, None) is not None

    # Consistency with closest_hit on a subset (occluded iff a hit exists).
    sub = np.linspace(0, n - 1, min(n, 100_000)).astype(np.int64)
    diff_closest = float(np.mean(scene.closest_hit(p[sub], d[sub]).hit != occ[sub]))

    n_tm = min(n, 200_000)
    o_tm = np.ascontiguousarray(p[:n_tm] + scene.eps * d[:n_tm])
    d_tm = np.ascontiguousarray(d[:n_tm])
    mesh.ray.intersects_any(o_tm[:10], d_tm[:10])
    t_tm, tm_any = best_of(lambda: mesh.ray.intersects_any(o_tm, d_tm), repeat)
    diff_tm = float(np.mean(np.asarray(tm_any) != occ[:n_tm]))

    tm_speed = n_tm / t_tm / 1e6
    sizes = {"faces": scene.n_faces, "rays": n, "occluded fraction": float(occ.mean())}
    name = "visibility.occluded"
    ours_t = {th: t_wall[("ours", th)] for th in _THREADS}
    rows = _thread_rows(name, "RayScene.occluded", ours_t, t_raw, n,
                        "raw embreex EmbreeScene.run(query='OCCLUDED') on the same float32 "
                        "rays and BVH",
                        {th: t_cpu[("raw", th)] / t_cpu[("ours", th)] for th in _THREADS})
    rows[0].error, rows[0].error_unit = diff_raw, "fraction differing vs raw embreex"
    rows[0].extra.update({**sizes, "differing vs closest_hit": diff_closest,
                          "Z-order sorting (auto)": sorted_auto})
    gil_free = _gil_free_fraction(lambda: emb.run(o32, d32, query="OCCLUDED", dists=far))
    rows += _raw_rows(name, "raw embreex run(query='OCCLUDED')", t_raw, n, chunk, sizes,
                      gil_free)
    key = "RayScene 1 thread vs this"
    rows.append(BenchRow(name, "raw embreex, same rays pre-sorted in Z-order (sort untimed), "
                         "1 call, 1 thread", n / t_rawz / 1e6, "Mrays/s",
                         ratios={key: t_rawz / ours_t[1]}, threads=1, baseline_threads={key: 1}))
    rows.append(BenchRow(name, "trimesh mesh.ray.intersects_any (origin moved eps), "
                         "single-threaded wrapper", tm_speed, "Mrays/s", diff_tm,
                         "fraction differing vs RayScene", {key: (n / ours_t[1] / 1e6) / tm_speed},
                         {"rays": n_tm}, threads=1, baseline_threads={key: 1}))
    return rows
