"""Stages whose products are cached under ``out/<stage>/`` by a key of their inputs.

The reconstruction pipeline (calibrate → decode → mesh → atlas → project → fit → render) is a
chain of stages, each reading some files of the scan and the products of earlier stages and writing its
own products into one folder. As Meshroom and COLMAP users expect, a stage reruns only when
something it depends on changed:

* its **key** is a SHA-256 over the stage name, the facegeo version, the stage's settings, the
  content hashes of the scan files it reads and the keys of the stages it reads from — so
  changing one setting reruns that stage and every stage after it, and nothing before;
* its products are written into a temporary sibling folder and swapped in only when the stage
  has finished (the manifest ``stage.json`` is the last file written), so an interrupted run
  leaves the previous products — of this stage and of every earlier one — intact, and the next
  run resumes from the first stage whose products are missing or stale;
* every stage's metrics are gathered into ``out/metrics.json`` (one entry per stage).

Content hashes of large input files are memoised by (size, modification time) in
``out/.facegeo-hashes.json``, so a warm run does not reread the frames.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from facegeo import __version__
from facegeo.errors import InputError
from facegeo.fsutil import atomic_write_text, clean_stale_siblings, file_sha256, staged_directory
from facegeo.checks import fmt_value

log = logging.getLogger(__name__)

__all__ = ["StageSpec", "StageContext", "StageResult", "Pipeline", "MANIFEST_NAME", "record_metrics"]

#: The manifest written last into every finished stage folder.
MANIFEST_NAME = "stage.json"
_HASH_MEMO = ".facegeo-hashes.json"


@dataclass(frozen=True)
class StageSpec:
    """One stage of a pipeline.

    Attributes
    ----------
    name : str
        Folder name under ``out/`` and the name used by ``--from`` / ``--only``.
    run : callable(StageContext) -> dict
        Does the work, writes its products into ``ctx.out_dir`` and returns the stage's
        metrics (JSON-serialisable).
    inputs : callable(Path) -> list of Path
        The scan files the stage reads (given the scan directory); their content is part of
        the key. Default: none.
    after : tuple of str
        Earlier stages whose products this stage reads (their keys are part of its key).
    settings : mapping
        Default settings (JSON-serialisable); overridable per run.
    """

    name: str
    run: Callable[[StageContext], dict]
    inputs: Callable[[Path], Sequence[Path]] = lambda scan_dir: ()
    after: tuple[str, ...] = ()
    settings: Mapping[str, Any] = field(default_factory=dict)


@dataclass
class StageContext:
    """What a running stage sees.

    Attributes
    ----------
    scan_dir : Path
        The scan directory (read only).
    out_dir : Path
        The (temporary) folder to write the stage's products into.
    settings : dict
        The stage's settings for this run.
    upstream : dict of str -> Path
        Product folder of each stage named in ``after``.
    progress : callable(stage, done, total) or None
    """

    scan_dir: Path
    out_dir: Path
    settings: dict
    upstream: dict[str, Path]
    progress: Callable[[str, int, int], None] | None = None


@dataclass
class StageResult:
    """The outcome of one stage in one run: ``ran`` is False when its cached products were used."""

    name: str
    key: str
    ran: bool
    seconds: float
    metrics: dict
    out_dir: Path


def _canonical_json(obj: Any, what: str) -> str:
    try:
        return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what}: expected JSON-serialisable values ({exc})") from exc


class _HashMemo:
    """SHA-256 of files, memoised by (size, mtime_ns) in a small JSON file."""

    def __init__(self, path: Path):
        self.path = path
        self.changed = False
        try:
            self.memo = json.loads(path.read_text(encoding="utf-8"))
            if not isinstance(self.memo, dict):
                self.memo = {}
        except (OSError, ValueError):
            self.memo = {}

    def digest(self, p: Path) -> str:
        try:
            st = p.stat()
        except FileNotFoundError:
            raise InputError(f"stage input {p} does not exist") from None
        k = str(p.resolve())
        hit = self.memo.get(k)
        if hit and hit[0] == st.st_size and hit[1] == st.st_mtime_ns:
            return hit[2]
        h = file_sha256(p)
        self.memo[k] = [st.st_size, st.st_mtime_ns, h]
        self.changed = True
        return h

    def save(self) -> None:
        if self.changed:
            atomic_write_text(self.path, json.dumps(self.memo))
            self.changed = False


def record_metrics(out_dir: str | os.PathLike, name: str, metrics: dict) -> None:
    """Set ``out_dir/metrics.json[name] = metrics`` (other entries kept; atomic write). A file
    that cannot be read as a JSON object is started afresh with a warning (a pipeline run puts
    every cached stage's metrics back from its manifest)."""
    path = Path(out_dir) / "metrics.json"
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(doc, dict):
            raise ValueError("not a JSON object")
    except FileNotFoundError:
        doc = {}
    except (OSError, ValueError) as exc:
        log.warning("%s: unreadable (%s); starting it afresh — 'facegeo reconstruct' puts "
                    "every cached stage's metrics back", path, exc)
        doc = {}
    doc[name] = metrics
    atomic_write_text(path, json.dumps(doc, indent=2, sort_keys=True, allow_nan=False))


def _read_manifest(final: Path) -> dict | None:
    """The ``stage.json`` of stage folder ``final`` as a dict, or None (absent, unreadable)."""
    try:
        m = json.loads((final / MANIFEST_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return m if isinstance(m, dict) else None


def _record_failure(out: Path, name: str, final: Path, exc: BaseException) -> None:
    """Mark stage ``name``'s entry in ``out/metrics.json``: ``last_run_failed`` (one line),
    beside the metrics of the products still on disk (the previous run's manifest's, or none).
    A later successful run replaces the whole entry."""
    old = (_read_manifest(final) or {}).get("metrics", {})
    if not isinstance(old, dict):
        old = {}
    text = " ".join(str(exc).split()) or type(exc).__name__
    try:
        record_metrics(out, name, {**old, "last_run_failed": f"{type(exc).__name__}: {text}"})
    except (OSError, ValueError) as err:  # never hide the stage's own error behind this one
        log.warning("%s: could not record the failure of stage %s (%s)", out, name, err)


class Pipeline:
    """An ordered chain of :class:`StageSpec` run against one scan directory.

    Parameters
    ----------
    stages : sequence of StageSpec
        In run order; every name in a stage's ``after`` must come earlier.
    out_name : str
        Name of the products folder inside the scan directory (default ``"out"``).
    """

    def __init__(self, stages: Sequence[StageSpec], *, out_name: str = "out"):
        seen: set[str] = set()
        for s in stages:
            if not s.name or "/" in s.name or s.name.startswith("."):
                raise InputError(f"stage name {fmt_value(s.name)}: expected a plain folder name")
            if s.name in seen:
                raise InputError(f"stage {fmt_value(s.name)} is listed twice")
            missing = [a for a in s.after if a not in seen]
            if missing:
                raise InputError(
                    f"stage {fmt_value(s.name)} reads {missing}, which do not come before it"
                )
            seen.add(s.name)
        self.stages = list(stages)
        self.out_name = out_name

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.stages]

    def _check_stage(self, name: str | None, flag: str) -> None:
        if name is not None and name not in self.names:
            raise InputError(f"{flag} {fmt_value(name)}: unknown stage; stages are {', '.join(self.names)}")

    def run(
        self,
        scan_dir: str | os.PathLike,
        *,
        settings: Mapping[str, Mapping[str, Any]] | None = None,
        from_stage: str | None = None,
        only: str | None = None,
        until: str | None = None,
        progress: Callable[[str, int, int], None] | None = None,
        on_stage: Callable[[StageResult], None] | None = None,
    ) -> list[StageResult]:
        """Run every stage whose products are missing or stale; return one result per stage.

        Parameters
        ----------
        scan_dir : path-like
        settings : mapping of stage name -> mapping, optional
            Overrides of each stage's default settings.
        from_stage : str, optional
            Rerun this stage and every later one even if cached (``--from``).
        only : str, optional
            Run only this stage, even if cached (``--only``); the stages it reads from must
            be cached and current, else :class:`~facegeo.errors.InputError` names the missing one.
        until : str, optional
            Stop after this stage: run it and the stages it reads from (directly or not), as
            usual (cached ones are not rerun), and none of the others (``facegeo decode``,
            ``facegeo fit``: one stage and what it needs).
        progress : callable(stage, done, total), optional
            Passed to the stages.
        on_stage : callable(StageResult), optional
            Called after each stage (ran or cached), e.g. to print a line.
        """
        scan_dir = Path(scan_dir)
        if not scan_dir.is_dir():
            raise InputError(f"scan directory {scan_dir} does not exist")
        self._check_stage(from_stage, "--from")
        self._check_stage(only, "--only")
        self._check_stage(until, "until")
        wanted = None if until is None else set(self._upstream_closure(until)) | {until}
        settings = dict(settings or {})
        unknown = set(settings) - set(self.names)
        if unknown:
            raise InputError(f"settings for unknown stages {sorted(unknown)}; stages are "
                             f"{', '.join(self.names)}")
        for spec in self.stages:  # before any stage runs: a typo would surface stages later
            given = settings.get(spec.name)
            if given is None:
                continue
            if not isinstance(given, Mapping):
                raise InputError(f"settings[{spec.name!r}]: expected a mapping of setting names "
                                 f"to values, got {fmt_value(given)}")
            bad = sorted(set(given) - set(spec.settings)) if spec.settings else []
            if bad:
                raise InputError(f"settings[{spec.name!r}]: unknown {bad}; the stage's settings "
                                 f"are {', '.join(sorted(spec.settings))}")
        out = scan_dir / self.out_name
        out.mkdir(parents=True, exist_ok=True)
        for name in self.names:  # leftovers of killed runs (only folders this code names)
            clean_stale_siblings(out / name)
        memo = _HashMemo(out / _HASH_MEMO)
        keys: dict[str, str] = {}
        results: list[StageResult] = []
        forced = False
        try:
            for spec in self.stages:
                if wanted is not None and spec.name not in wanted:
                    continue
                forced = forced or spec.name in (from_stage, only)
                stage_settings = {**spec.settings, **settings.get(spec.name, {})}
                key, inputs = self._key(spec, scan_dir, stage_settings, keys, memo)
                keys[spec.name] = key
                final = out / spec.name
                cached = self._cached_manifest(final, key)
                if only is not None and spec.name != only:
                    if cached is None and spec.name in self._upstream_closure(only):
                        raise InputError(
                            f"--only {only}: its input stage {fmt_value(spec.name)} has no current "
                            f"products in {final}; run it first (facegeo reconstruct --from "
                            f"{spec.name})"
                        )
                    continue
                if cached is not None and not forced:
                    result = StageResult(spec.name, key, False, 0.0, cached.get("metrics", {}),
                                         final)
                    # the manifest's metrics back into metrics.json: a lost or rewritten file
                    # is whole again after any run, not only after the stages that reran
                    record_metrics(out, spec.name, result.metrics)
                else:
                    self._warn_if_standalone(final)
                    try:
                        result = self._run_stage(spec, scan_dir, out, key, stage_settings,
                                                 inputs, keys, progress)
                    except Exception as exc:
                        # the products on disk are the previous run's (or none): their metrics
                        # stay, with the failure beside them, so the report does not read as
                        # if this run had not failed
                        _record_failure(out, spec.name, final, exc)
                        raise
                    record_metrics(out, spec.name, result.metrics)
                results.append(result)
                if on_stage is not None:
                    on_stage(result)
        finally:
            memo.save()
        return results

    # ------------------------------------------------------------------ internals

    def _upstream_closure(self, name: str) -> set[str]:
        by_name = {s.name: s for s in self.stages}
        todo, seen = list(by_name[name].after), set()
        while todo:
            n = todo.pop()
            if n not in seen:
                seen.add(n)
                todo.extend(by_name[n].after)
        return seen

    def _key(self, spec, scan_dir, stage_settings, keys, memo):
        inputs = {}
        for p in spec.inputs(scan_dir):
            p = Path(p)
            rel = os.path.relpath(p, scan_dir)
            inputs[rel] = memo.digest(p)
        doc = {
            "stage": spec.name,
            "facegeo_version": __version__,
            "settings": stage_settings,
            "inputs": inputs,
            "upstream": {a: keys[a] for a in spec.after},
        }
        blob = _canonical_json(doc, f"stage {spec.name!r} settings")
        return hashlib.sha256(blob.encode()).hexdigest(), inputs

    @staticmethod
    def _warn_if_standalone(final: Path) -> None:
        """Say so when the products about to be replaced were written by a stage's own
        command (``facegeo atlas``, ``facegeo project``: a manifest without a key), whose
        settings the cache cannot know: they are rebuilt with the pipeline's settings."""
        m = _read_manifest(final)
        if m is not None and "key" not in m:
            log.warning("%s was written by 'facegeo %s' outside the stage cache (settings %s); "
                        "rebuilding it with the pipeline's settings", final, final.name,
                        m.get("settings", {}))

    @staticmethod
    def _cached_manifest(final: Path, key: str) -> dict | None:
        m = _read_manifest(final)
        return m if m is not None and m.get("key") == key else None

    def _run_stage(self, spec, scan_dir, out, key, stage_settings, inputs, keys, progress):
        final = out / spec.name
        log.info("stage %s: running (key %s)", spec.name, key[:12])
        t0 = time.perf_counter()
        with staged_directory(final) as tmp:
            ctx = StageContext(scan_dir, tmp, dict(stage_settings),
                               {a: out / a for a in spec.after}, progress)
            metrics = spec.run(ctx)
            if metrics is None:
                metrics = {}
            if not isinstance(metrics, dict):
                raise InputError(f"stage {fmt_value(spec.name)} returned {type(metrics).__name__}, "
                                 "expected a dict of metrics")
            seconds = time.perf_counter() - t0
            metrics = {**metrics, "seconds": round(seconds, 4)}
            manifest = {
                "stage": spec.name,
                "key": key,
                "facegeo_version": __version__,
                "settings": stage_settings,
                "inputs": inputs,
                "upstream": {a: keys[a] for a in spec.after},
                "metrics": metrics,
                "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            }
            # the manifest is written last: a folder without it is never taken as finished
            atomic_write_text(tmp / MANIFEST_NAME,
                              json.dumps(manifest, indent=2, sort_keys=True, allow_nan=False))
        return StageResult(spec.name, key, True, seconds, metrics, final)
