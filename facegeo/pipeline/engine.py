"""Where a stage's tasks run: in this process, on a Dask ``LocalCluster`` or on an existing cluster.

A stage that splits its work into independent tasks (``decode``, ``project``: one task per
camera, and on a cluster the projection's blend per chunk of texels; ``fit``: whole fit chunks
of a camera's functions; the texture ``relight``: whole relighting chunks of a camera's
texels; ``render``: one task per view) hands them to an :class:`Engine` and gets back one small dict per task (metrics,
counts). Three modes behind one interface (issue 38):

* :class:`InProcessEngine` — the default: the tasks run one after another in this process, in
  the order given. Dask is not imported on this path (``make demo`` and the tests need no
  cluster), and a stage run through it writes exactly what it wrote before engines existed.
* ``DaskEngine.local(n_workers, memory_limit)`` — ``facegeo … --workers N``: a
  ``distributed.LocalCluster`` of ``N`` worker processes with one thread each and the stated
  memory limit per worker.
* ``DaskEngine.connect(address)`` — ``facegeo … --scheduler ADDRESS``: a ``distributed.Client``
  of a running scheduler (any deployment Dask supports: ``dask scheduler`` / ``dask worker``
  by hand, SSH, Kubernetes, Slurm through dask-jobqueue; docs/scale.md).

The two Dask modes are one class and one code path; only how the client is made differs.

What a task is
--------------
A :class:`Task` is a module-level function (pickled by reference: workers import facegeo
themselves), small arguments (paths, names, chunk bounds, settings — never large arrays) and
its **working set** in bytes, computed by the stage from the chunk it handles. Before anything
is submitted every task's working set is checked against a worker's memory
(:meth:`Engine.check_fits`): a task that cannot fit raises :class:`InputError` naming the task,
its working set and the limit, and nothing runs. A task's return value must be a dict (or
None) whose pickle is at most :data:`MAX_RESULT_BYTES`: products go to files the task writes
itself (the stage's staging folder on a disk the workers share, or a Zarr store), never
through the client. The check runs on the worker, so a large result never travels.

Memory
------
A worker runs one task at a time (one thread). Its resident memory is the interpreter with
facegeo's imports (:data:`WORKER_BASE_BYTES`, measured) plus the running task's working set;
that sum must stay under the fraction :data:`MEMORY_FRACTION` of the worker's limit, Dask's
``distributed.worker.memory.pause`` threshold (0.8 by default: above it a worker takes no new
task; at 0.95 the nanny restarts it). A task's results are small, so nothing is spilled.

Progress and failure
--------------------
``progress(stage, done, total)`` — the callback every stage takes (:class:`StageContext`) — is
called on the client as tasks finish. The dashboard's address is logged when the engine
starts (Dask serves it when ``bokeh`` is installed). When a task fails, its own exception is
raised on the client — in process at once, on a cluster after the other tasks (already
running side by side) have finished, so that no finished work is thrown away: what they wrote
stays (``decode`` keeps each finished camera in its ``.partial`` folder, and the next run takes
them from there). An interrupt (Ctrl-C) cancels the unfinished tasks.
"""

from __future__ import annotations

import logging
import os
import pickle
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from facegeo.checks import fmt_value
from facegeo.errors import FacegeoError, InputError

log = logging.getLogger(__name__)

__all__ = [
    "ENGINE_KINDS",
    "MAX_RESULT_BYTES",
    "MEMORY_FRACTION",
    "STALL_RESTARTS",
    "STALL_RESTART_SECONDS",
    "STALL_SECONDS",
    "WORKER_BASE_BYTES",
    "WORKER_ENV",
    "DaskEngine",
    "Engine",
    "InProcessEngine",
    "StalledError",
    "Task",
    "TaskRecord",
    "make_engine",
    "parse_memory",
]

#: Environment of a ``LocalCluster``'s worker processes, over Dask's own
#: (``distributed.nanny.pre-spawn-environ``: ``OMP_NUM_THREADS``, ``MKL_NUM_THREADS``,
#: ``OPENBLAS_NUM_THREADS`` = 1). One thread a worker means one thread in numba's parallel
#: loops too. ``MALLOC_TRIM_THRESHOLD_`` (Dask sets 65536 so that workers hand freed memory
#: back at once) is left unset (None): setting it turns off glibc's adaptive mmap threshold,
#: so every frame-sized temporary is a fresh mapping whose pages fault in again — measured
#: 1.6–1.8× slower decoding (in process, 480 × 720 frames: 1.73–2.14 s against 3.08–3.46 s
#: with the variable). Workers of an existing scheduler are started by their owner:
#: ``NUMBA_NUM_THREADS=1 dask worker --nthreads 1 …`` (docs/scale.md).
WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "MALLOC_TRIM_THRESHOLD_": None}
#: The engine modes (:attr:`Engine.kind`).
ENGINE_KINDS = ("in-process", "local-cluster", "scheduler")
#: Largest pickled result a task may return (bytes): metrics, not products.
MAX_RESULT_BYTES = 1 << 20
#: Fraction of a worker's memory limit the interpreter and one task's working set may fill
#: together: Dask's default ``distributed.worker.memory.pause`` (a :class:`DaskEngine` reads
#: the cluster's configured value instead).
MEMORY_FRACTION = 0.8
#: Seconds a cluster stage waits for a task at a time before it looks at the workers
#: (:class:`_Quiet`).
STALL_POLL_SECONDS = 5.0
#: Seconds every worker may stay paused with no task running (or the cluster without
#: workers) before a stage stops with :class:`StalledError`: twice Dask's default
#: ``distributed.comm.timeouts.connect`` (30 s), room for a nanny to restart a worker that
#: passed the ``terminate`` threshold.
STALL_SECONDS = 60.0
#: Seconds every worker of a ``LocalCluster`` the engine started may stay paused with no task
#: running before the engine restarts them (:class:`_Quiet`): two looks, so that a worker
#: between two tasks is not taken for a stuck one.
STALL_RESTART_SECONDS = 10.0
#: Restarts of paused, idle workers a stage may make before it stops with
#: :class:`StalledError` instead (memory that a fresh worker fills again is not a leftover).
STALL_RESTARTS = 2
#: Seconds between the two looks that find a restarted cluster settled
#: (:meth:`DaskEngine.restart`), and the longest it waits for that.
SETTLE_SECONDS = 1.0
SETTLE_TIMEOUT_SECONDS = 60.0
#: Resident memory of a worker process before its first task's data: Python, numpy, OpenCV,
#: numba and ``distributed`` itself (measured: 234–246 MiB for a decode worker after a task
#: on the tiny preset's 80 × 120 cameras, whose data is negligible; rounded up).
WORKER_BASE_BYTES = 300 << 20


def parse_memory(value, what: str = "memory_limit") -> int | None:
    """Bytes from ``value``: an int (bytes), a string with a unit (``"2GiB"``, ``"1.5 GB"``,
    ``"512MB"``) or None (no limit).

    Raises
    ------
    InputError
        Anything else, or a size that is not positive.
    """
    if value is None:
        return None
    if isinstance(value, bool):
        raise InputError(f"{what}: expected bytes or a size like '2GiB', got {fmt_value(value)}")
    if isinstance(value, (int, float)):
        n = int(value)
    elif isinstance(value, str):
        import re

        units = {"": 1, "b": 1, "k": 1e3, "kb": 1e3, "m": 1e6, "mb": 1e6, "g": 1e9, "gb": 1e9,
                 "t": 1e12, "tb": 1e12, "kib": 2 ** 10, "mib": 2 ** 20, "gib": 2 ** 30,
                 "tib": 2 ** 40}
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:e[0-9]+)?)\s*([a-zA-Z]*)\s*", value)
        if m is None or m.group(2).lower() not in units:
            raise InputError(f"{what}: expected bytes or a size like '2GiB' or '1.5GB', got "
                             f"{fmt_value(value)}")
        n = int(float(m.group(1)) * units[m.group(2).lower()])
    else:
        raise InputError(f"{what}: expected bytes or a size like '2GiB', got {fmt_value(value)}")
    if n <= 0:
        raise InputError(f"{what}: expected a positive size, got {fmt_value(value)}")
    return n


def _mb(n: int | float | None) -> str:
    return "no limit" if n is None else f"{n / 2 ** 20:,.0f} MiB"


class StalledError(FacegeoError, RuntimeError):
    """A cluster stage whose remaining tasks cannot run: every worker paused at its memory
    limit with no task running (after :data:`STALL_RESTARTS` restarts, on a ``LocalCluster``
    the engine started), or no worker left (:class:`_Quiet`)."""


@dataclass(frozen=True)
class Task:
    """One unit of a stage's work.

    Attributes
    ----------
    name : str
        Unique within the stage (``"cam_left"``, ``"texels 0:4096"``): names the task in errors,
        logs and the dashboard.
    fn : callable
        A module-level function (workers import it by name); returns a dict or None.
    args : tuple
        Small arguments: paths, names, chunk bounds, settings.
    kwargs : dict
    working_set : int, bytes
        Memory the task needs while it runs, from its chunk size (0: negligible).
    size : int
        Units of work it does, for progress (1: a task is the unit; a fit task: its
        functions): ``progress(stage, done, total)`` counts these.
    """

    name: str
    fn: Callable[..., dict | None]
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)
    working_set: int = 0
    size: int = 1


@dataclass
class TaskRecord:
    """Where and how a task ran: ``worker`` (an address, or ``"in-process"``), ``seconds``,
    ``peak_rss_mb`` (the worker process's peak resident memory while the task ran; in-process:
    this process's peak since it started or was last reset, which includes earlier work)."""

    stage: str
    task: str
    worker: str
    seconds: float
    peak_rss_mb: float | None


def _checked_result(task: str, result) -> dict | None:
    if result is not None and not isinstance(result, dict):
        raise InputError(f"task {task!r}: returned {type(result).__name__}; a task returns a "
                         "dict of metrics (or None) and writes its products itself")
    size = len(pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL))
    if size > MAX_RESULT_BYTES:
        raise InputError(f"task {task!r}: its result pickles to {size:,} bytes, over the "
                         f"{MAX_RESULT_BYTES:,} allowed: write arrays to the products, return "
                         "metrics")
    return result


def _run_on_worker(task: str, fn, args, kwargs) -> tuple[dict | None, dict]:
    """Run one task in a worker process: its peak memory measured from a reset (one thread per
    worker: the peak is this task's), its result checked before it leaves the worker."""
    from facegeo.rss import peak_rss_mb, reset_peak_rss

    reset = reset_peak_rss()
    t0 = time.perf_counter()
    result = _checked_result(task, fn(*args, **kwargs))
    info = {"seconds": time.perf_counter() - t0,
            "peak_rss_mb": peak_rss_mb() if reset else None}
    try:
        from distributed import get_worker

        info["worker"] = get_worker().address
    except (ImportError, ValueError):
        info["worker"] = f"pid {os.getpid()}"
    return result, info


class Engine:
    """Runs a stage's tasks (module docstring). Use as a context manager, or call :meth:`close`.

    Attributes
    ----------
    kind : str
        One of :data:`ENGINE_KINDS`.
    n_workers : int
        Tasks that can run at once.
    memory_limit : int or None, bytes
        Per worker (None: not limited, no check).
    memory_fraction : float
        Fraction of ``memory_limit`` the interpreter and one task may fill together.
    dashboard : str or None
        The Dask dashboard's address.
    records : list of TaskRecord
        Every task run through the engine, in the order they finished.
    """

    kind = "in-process"

    def __init__(self, n_workers: int = 1, memory_limit: int | None = None,
                 memory_fraction: float = MEMORY_FRACTION):
        self.n_workers = int(n_workers)
        self.memory_limit = memory_limit
        self.memory_fraction = float(memory_fraction)
        self.dashboard: str | None = None
        self.records: list[TaskRecord] = []

    # ------------------------------------------------------------------ the interface
    def describe(self) -> dict:
        """Small JSON-able summary for a stage's metrics."""
        return {"kind": self.kind, "workers": self.n_workers,
                "memory_limit_mb": None if self.memory_limit is None
                else round(self.memory_limit / 2 ** 20, 1),
                "dashboard": self.dashboard}

    def stage_metrics(self, stage: str, names: Sequence[str]) -> dict:
        """:meth:`describe` and, per task of ``stage`` named in ``names``, the worker, seconds
        and peak memory it ran with (the ``engine`` entry of a stage's metrics on a cluster)."""
        recs = {r.task: r for r in self.records if r.stage == stage and r.task in names}
        out = self.describe()
        out["tasks"] = {n: {"worker": recs[n].worker, "seconds": round(recs[n].seconds, 4),
                            "peak_rss_mb": None if recs[n].peak_rss_mb is None
                            else round(recs[n].peak_rss_mb, 1)}
                        for n in names if n in recs}
        return out

    def task_budget(self) -> int | None:
        """Bytes a task's working set may take on one worker (None: not limited)."""
        if self.memory_limit is None:
            return None
        return int(self.memory_limit * self.memory_fraction) - WORKER_BASE_BYTES

    def check_fits(self, stage: str, tasks: Sequence[Task]) -> None:
        """Raise :class:`InputError` naming the first task whose working set does not fit a
        worker (module docstring, *Memory*); nothing has run yet when it does."""
        budget = self.task_budget()
        if budget is None:
            return
        for t in tasks:
            if t.working_set > budget:
                raise InputError(
                    f"{stage}: task {t.name!r} needs {_mb(t.working_set)} of memory, over what "
                    f"one worker holds: {self.memory_fraction:g} × its limit "
                    f"{_mb(self.memory_limit)} minus {_mb(WORKER_BASE_BYTES)} for the "
                    f"interpreter = {_mb(max(budget, 0))}; give the workers more memory "
                    "(--memory-limit) or make the task's chunk smaller")

    def map(self, stage: str, tasks: Sequence[Task],
            progress: Callable[[str, int, int], None] | None = None) -> list[dict | None]:
        """Run ``tasks``; returns their results in the order of ``tasks``.

        Every task's working set is checked first (:meth:`check_fits`); ``progress(stage,
        done, total)`` is called as tasks finish, counting their :attr:`Task.size`. A task's exception is raised here: in
        process at once (the later tasks do not run), on a cluster once the other tasks have
        finished (tasks run concurrently, and what each finished task wrote is kept for the
        next run; an interrupt cancels them instead).
        """
        tasks = list(tasks)
        names = [t.name for t in tasks]
        if len(set(names)) != len(names):
            raise InputError(f"{stage}: task names must be unique, got {names}")
        self.check_fits(stage, tasks)
        total = sum(int(t.size) for t in tasks)
        if progress:
            progress(stage, 0, total)
        if not tasks:
            return []
        if progress:  # tasks finish → units done
            sizes, done, report = {t.name: int(t.size) for t in tasks}, [0], progress

            def progress(stage, _k, _n, name=None):
                done[0] += sizes[name]
                report(stage, done[0], total)
        return self._map(stage, tasks, progress)

    def _map(self, stage, tasks, progress):
        from facegeo.rss import peak_rss_mb

        out = []
        for i, t in enumerate(tasks):
            t0 = time.perf_counter()
            out.append(_checked_result(t.name, t.fn(*t.args, **t.kwargs)))
            self.records.append(TaskRecord(stage, t.name, "in-process",
                                           time.perf_counter() - t0, peak_rss_mb()))
            if progress:
                progress(stage, i + 1, len(tasks), name=t.name)
        return out

    def close(self) -> None:
        """Release the engine's resources (nothing in process)."""

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(kind={self.kind!r}, workers={self.n_workers}, "
                f"memory_limit={_mb(self.memory_limit)})")


class InProcessEngine(Engine):
    """The default engine: tasks run one after another in this process, in the order given
    (no Dask import, no check unless a ``memory_limit`` is given)."""


class DaskEngine(Engine):
    """Tasks on a ``distributed.Client``: a ``LocalCluster`` (:meth:`local`) or an existing
    scheduler (:meth:`connect`) — the same code from there on.

    Parameters
    ----------
    client : distributed.Client
    kind : {"local-cluster", "scheduler"}
    cluster : distributed.LocalCluster, optional
        Closed with the engine (an existing scheduler's cluster is left running).
    """

    def __init__(self, client, kind: str, cluster=None):
        import dask

        info = client.scheduler_info()
        workers = info.get("workers", {})
        limits = [int(w.get("memory_limit") or 0) for w in workers.values()]
        limit = min(limits) if limits and min(limits) > 0 else None
        pause = dask.config.get("distributed.worker.memory.pause", MEMORY_FRACTION)
        fraction = float(pause) if pause else 0.95
        super().__init__(max(len(workers), 1), limit, fraction)
        self.restarts = 0  # workers restarted before a stage (_resident_check) or in one (_Quiet)
        self.kind = kind
        self.client = client
        self.cluster = cluster
        self.dashboard = getattr(client, "dashboard_link", None)
        try:
            import bokeh  # noqa: F401  (Dask serves the dashboard with it)

            log.info("dask %s: %d workers, %s each; dashboard %s", kind, self.n_workers,
                     _mb(self.memory_limit), self.dashboard)
        except ImportError:
            log.info("dask %s: %d workers, %s each; dashboard not served (pip install "
                     "'bokeh>=3.1' to see it at %s)", kind, self.n_workers,
                     _mb(self.memory_limit), self.dashboard)

    @classmethod
    def local(cls, n_workers: int, memory_limit=None, **cluster_kwargs) -> DaskEngine:
        """A ``LocalCluster`` of ``n_workers`` processes × 1 thread, ``memory_limit`` each (bytes
        or a size string; default Dask's ``"auto"``: the machine's memory / ``n_workers``)."""
        if isinstance(n_workers, bool) or not isinstance(n_workers, int) or n_workers < 1:
            raise InputError(f"workers: expected an integer >= 1, got {fmt_value(n_workers)}")
        limit = parse_memory(memory_limit) if memory_limit is not None else "auto"
        import dask
        from distributed import Client, LocalCluster

        key = "distributed.nanny.pre-spawn-environ"
        spawn_env = {**dask.config.get(key, {}), **WORKER_ENV}
        environ = dict(os.environ)  # the nannies run here and set their env in os.environ
        kw = {"dashboard_address": ":0", **cluster_kwargs}
        try:
            with dask.config.set({key: spawn_env}):
                cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1,
                                       memory_limit=limit, processes=True, **kw)
        finally:
            _restore_environ(environ)
        try:
            client = Client(cluster)
            eng = cls(client, "local-cluster", cluster)
        except BaseException:
            cluster.close()
            raise
        eng._environ = environ  # put back after every restart (:meth:`_put_environ_back`)
        return eng

    @classmethod
    def connect(cls, address: str, timeout: str | float = "30s") -> DaskEngine:
        """A client of the scheduler at ``address`` (``tcp://host:8786``, a scheduler file
        ``*.json``); its workers must see the scan and ``out/`` at the same paths."""
        if not isinstance(address, str) or not address.strip():
            raise InputError(f"scheduler: expected an address like tcp://host:8786 or a "
                             f"scheduler file, got {fmt_value(address)}")
        from distributed import Client

        try:
            if address.endswith(".json"):
                client = Client(scheduler_file=address, timeout=timeout)
            else:
                client = Client(address, timeout=timeout)
        except (OSError, TimeoutError) as exc:
            raise InputError(f"scheduler {address}: cannot connect ({exc}); is a scheduler "
                             "running there (dask scheduler) with workers (dask worker)?") from exc
        try:
            if not client.scheduler_info().get("workers"):
                client.wait_for_workers(1, timeout=timeout)
            return cls(client, "scheduler")
        except BaseException:
            client.close()
            raise

    def restart(self) -> None:
        """Restart every worker (``Client.restart``) and wait until the cluster has settled:
        the same workers, all running, on two looks :data:`SETTLE_SECONDS` apart. Each nanny
        also restarts the worker it saw exit, after the scheduler has counted the workers
        back; a second restart in that time closed both nannies (seen here: a stage's restart
        3 s after another), so the next restart waits for this one to end."""
        try:
            self.client.restart(wait_for_workers=True)
            seen = None
            deadline = time.monotonic() + SETTLE_TIMEOUT_SECONDS
            while time.monotonic() < deadline:
                workers = self.client.scheduler_info().get("workers", {})
                now = (frozenset(workers), all(w.get("status") == "running"
                                               for w in workers.values()))
                if now == seen and now[1] and len(now[0]) >= self.n_workers:
                    return
                seen = now
                time.sleep(SETTLE_SECONDS)
            log.warning("workers restarted but not settled after %.0f s: %s",
                        SETTLE_TIMEOUT_SECONDS, sorted(seen[0]) if seen else "none")
        finally:
            self._put_environ_back()  # the nannies set the workers' variables here again

    def _resident_check(self, stage: str, tasks) -> None:
        """Restart the workers (of a ``LocalCluster``; a running scheduler's are only warned
        about) when one of them holds so much memory already (left by an earlier stage: freed
        arrays the allocator keeps, per-process caches) that its resident memory plus this
        stage's largest task would pass the pause threshold: the stated working sets count
        from a fresh worker (:data:`WORKER_BASE_BYTES`). Measured: workers
        at 463–470 MiB after the ``modern`` preset's projection reached 600–608 MiB of 640 MiB
        in the fit, and the nanny restarted them mid-stage."""
        if self.memory_limit is None:
            return
        need = max((int(t.working_set) for t in tasks), default=0)
        try:
            rss = self.client.run(_resident_bytes)
        except Exception:  # noqa: BLE001 - a check only: the stage runs without it
            return
        limit = self.memory_fraction * self.memory_limit
        over = {w: r for w, r in rss.items() if r + need > limit}
        if over and self.kind != "local-cluster":  # not ours to restart: say so
            log.warning("%s: workers %s hold %s already; with a task of %s they may pass the "
                        "pause threshold %s (restart them between stages, or give them more "
                        "memory)", stage, sorted(over), [_mb(r) for r in over.values()],
                        _mb(need), _mb(limit))
        elif over:
            log.info("%s: workers %s hold %s already, + a task of %s > %s: restarting them",
                     stage, sorted(over), [_mb(r) for r in over.values()], _mb(need),
                     _mb(limit))
            self.restart()
            self.restarts += 1

    def _map(self, stage, tasks, progress):
        from distributed import wait

        self._resident_check(stage, tasks)
        by_name = {t.name: t for t in tasks}

        def submit(names) -> dict:
            out = {}
            for n in names:
                t = by_name[n]
                f = self.client.submit(_run_on_worker, t.name, t.fn, t.args, t.kwargs,
                                       key=f"{stage}-{t.name}-{os.urandom(4).hex()}",
                                       pure=False)
                out[f] = t.name
            return out

        # future -> task name; a finished one is dropped as soon as it is read
        pending = submit(t.name for t in tasks)
        results: dict[str, Any] = {}
        done = 0
        failed: tuple[str, BaseException] | None = None
        quiet = _Quiet(self, stage)
        try:
            while pending:
                try:  # a bounded wait, so that a cluster that cannot go on is noticed
                    finished = wait(list(pending), timeout=STALL_POLL_SECONDS,
                                    return_when="FIRST_COMPLETED").done
                except TimeoutError:
                    if quiet.check(len(pending)):  # every worker paused and idle: restart
                        left = sorted(pending.values())
                        self.client.cancel(list(pending))
                        pending = {}
                        try:
                            self.restart()
                        except (TimeoutError, OSError) as exc:
                            raise StalledError(
                                f"{stage}: {len(left)} task(s) left; every worker was paused "
                                f"at its memory limit with no task running, and restarting "
                                f"them failed ({exc}); give the workers more memory "
                                "(--memory-limit) or run in one process") from exc
                        self.restarts += 1
                        pending = submit(left)  # a task writes whole files: run again
                    continue
                quiet.reset()
                for f in sorted(finished, key=lambda f: pending[f]):
                    name = pending.pop(f)
                    try:
                        result, info = f.result()  # a task's exception is raised here
                    except Exception as exc:  # the others finish: their products are kept
                        if failed is None:
                            failed = (name, exc)
                            log.error("%s: task %r failed (%s); waiting for the %d other "
                                      "tasks still running so that their work is kept", stage,
                                      name, exc, len(pending))
                        continue
                    results[name] = result
                    self.records.append(TaskRecord(stage, name, info["worker"],
                                                   info["seconds"], info["peak_rss_mb"]))
                    done += 1
                    if progress:
                        progress(stage, done, len(tasks), name=name)
                del finished
        except BaseException:  # Ctrl-C, or the client lost: stop everything
            self.client.cancel(list(pending))
            raise
        finally:  # a nanny that restarted a worker on its own set the workers' variables here
            self._put_environ_back()
        if failed is not None:
            raise failed[1]
        return [results[t.name] for t in tasks]

    def close(self) -> None:
        """Close the client, and the ``LocalCluster`` this engine started."""
        try:
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()
            self._put_environ_back()

    def _put_environ_back(self) -> None:
        """Put this process's environment back as it was before the ``LocalCluster`` started:
        its nannies run in this process and set the workers' variables
        (:data:`WORKER_ENV`: ``NUMBA_NUM_THREADS=1``) in ``os.environ`` each time they spawn
        a worker — at a restart too — and this process's numba then refused to run with its
        own thread count (``Cannot set NUMBA_NUM_THREADS to a different value``, seen in the
        tests after a restart)."""
        environ = getattr(self, "_environ", None)
        if environ is not None:
            _restore_environ(environ)


class _Quiet:
    """Whether a cluster that finishes no task can go on. A stage whose workers are all paused
    (resident memory past Dask's ``pause`` threshold) with no task running — memory an
    earlier task left: freed arrays the allocator keeps, per-process caches — or whose
    cluster has no worker would otherwise wait for ever: Dask has no task timeout, and a
    paused worker's memory does not come back by itself. A paused worker that is still
    running a task is not stuck (the task's own memory paused it; it ends).

    On a ``LocalCluster`` the engine started, workers stuck for :data:`STALL_RESTART_SECONDS`
    are restarted — :meth:`check` says so and the stage cancels its tasks left, restarts every
    worker (``Client.restart``; per-worker ``Client.restart_workers`` once left both nannies
    closed on a loaded machine, each restarting its exited worker beside the scheduler's
    restart) and submits those tasks again (a task writes
    whole files, so one run twice writes the same products) — at most :data:`STALL_RESTARTS`
    times a stage. Otherwise, after
    :data:`STALL_SECONDS`, the stage stops with :class:`StalledError` naming what each
    worker holds. Measured (CI, ``scale.reconstruct`` quick, 512 MiB workers): a fit worker
    paused at 411 MiB between two tasks."""

    def __init__(self, engine: DaskEngine, stage: str):
        self.engine, self.stage = engine, stage
        self.restarts = 0
        self.reset()

    def reset(self) -> None:
        self.since: float | None = None  # when every worker was first seen stuck

    def check(self, n_left: int) -> bool:
        """True when the caller should restart the workers (see the class); raises
        :class:`StalledError` when the stage cannot go on."""
        try:
            workers = self.engine.client.scheduler_info().get("workers", {})
        except Exception:  # noqa: BLE001 - the client's own errors surface on the next wait
            return False
        stuck = not workers or all(
            w.get("status") == "paused"
            and not ((w.get("metrics") or {}).get("task_counts") or {}).get("executing")
            for w in workers.values())
        if not stuck:
            self.since = None
            return False
        now = time.monotonic()
        if self.since is None:
            self.since = now
            return False
        held = {a: _mb(int((w.get("metrics") or {}).get("memory") or 0))
                for a, w in workers.items()}
        if (workers and self.engine.kind == "local-cluster" and self.restarts < STALL_RESTARTS
                and now - self.since >= STALL_RESTART_SECONDS):
            log.warning("%s: every worker is paused at its memory limit with no task running "
                        "(%s, limit %s each; %d task(s) left): restarting them", self.stage,
                        held, _mb(self.engine.memory_limit), n_left)
            self.restarts += 1
            self.since = None
            return True
        if now - self.since < STALL_SECONDS:
            return False
        what = (f"every worker is paused at its memory limit with no task running ({held}, "
                f"limit {_mb(self.engine.memory_limit)} each"
                + (f"; restarted {self.restarts} time(s) in this stage" if self.restarts
                   else "") + ")" if workers else "the cluster has no workers")
        raise StalledError(
            f"{self.stage}: {n_left} task(s) cannot run for {now - self.since:.0f} s: {what}; "
            "give the workers more memory (--memory-limit), restart them between stages, or "
            "run in one process")


def _resident_bytes() -> int:
    """This process's resident memory (bytes): run on every worker by the resident check."""
    import psutil

    return int(psutil.Process().memory_info().rss)


def _restore_environ(environ: dict) -> None:
    """Put this process's environment back as it was (a ``LocalCluster``'s nannies update
    ``os.environ`` with the workers' variables before spawning them)."""
    for k in set(os.environ) - set(environ):
        del os.environ[k]
    for k, v in environ.items():
        if os.environ.get(k) != v:
            os.environ[k] = v


def make_engine(workers: int | None = None, scheduler: str | None = None,
                memory_limit=None) -> Engine:
    """The engine of ``--workers N`` / ``--scheduler ADDRESS`` (neither: in process).

    Parameters
    ----------
    workers : int, optional
        Start a ``LocalCluster`` of this many worker processes (1 thread each).
    scheduler : str, optional
        Address of a running scheduler (or a scheduler file).
    memory_limit : int or str, optional
        Per worker: of the ``LocalCluster`` (default: the machine's memory / ``workers``), or,
        in process, the budget tasks are checked against (default: none). With a scheduler the
        workers' own limits hold; giving one is an error.

    Raises
    ------
    InputError
        Both ``workers`` and ``scheduler``; a bad value.
    """
    if workers is not None and scheduler is not None:
        raise InputError("--workers and --scheduler: give one (--workers N starts a local "
                         "cluster, --scheduler ADDRESS uses a running one)")
    if scheduler is not None:
        if memory_limit is not None:
            raise InputError("--memory-limit: a running scheduler's workers keep their own "
                             "limits (dask worker --memory-limit); leave it out with --scheduler")
        return DaskEngine.connect(scheduler)
    if workers is not None:
        return DaskEngine.local(workers, memory_limit)
    return InProcessEngine(1, parse_memory(memory_limit))
