"""Stages whose products are cached under ``out/<stage>/`` by a key of their inputs.

The reconstruction pipeline (calibrate → decode → mesh → atlas → project → fit → render) is a
chain of stages, each reading some files of the scan and the products of earlier stages and writing its
own products into one folder. As Meshroom and COLMAP users expect, a stage reruns only when
something it depends on changed:

* its **key** is a SHA-256 over the stage name, the facegeo version, the fingerprint of
  facegeo's code (:func:`code_fingerprint`: every ``.py`` file of the installed package, so a
  code change without a version bump — a developer's edit, a fix pulled into a checkout —
  reruns the stages instead of reusing products made by the old code), the stage's settings,
  the content hashes of the scan files it reads and the keys of the stages it reads from — so
  changing one setting reruns that stage and every stage after it, and nothing before;
* its products are written into a temporary sibling folder and swapped in only when the stage
  has finished (the manifest ``stage.json`` is the last file written), so an interrupted run
  leaves the previous products — of this stage and of every earlier one — intact, and the next
  run resumes from the first stage whose products are missing or stale;
* every stage's metrics are gathered into ``out/metrics.json`` (one entry per stage);
* the manifest records what went into the key (version, code fingerprint, settings, input
  hashes, upstream keys), so a stage that reruns says why (:attr:`StageResult.reason`, e.g.
  ``"facegeo code changed"``, ``"settings changed: depth"``); products written before the code
  fingerprint was recorded are simply recomputed once.

Content hashes of large input files are memoised by (size, modification time) in
``out/.facegeo-hashes.json``, so a warm run does not reread the frames.

A stage's own command can make its products as the stage (``facegeo calibrate`` into
``out/calibrate``: :meth:`Pipeline.run` with ``settings_by``): the manifest records the
command, and its settings are the user's. A later pipeline run (``facegeo reconstruct``,
``facegeo mesh``) keeps them — it reuses those products, or reruns the stage with those settings
when code or inputs changed — instead of replacing them with a stage made with its default
settings; a run that asks for other settings of that stage explicitly is refused with the
differing settings named (:func:`_command_settings`).
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import facegeo
from facegeo import __version__
from facegeo.errors import InputError
from facegeo.fsutil import atomic_write_text, clean_stale_siblings, file_sha256, staged_directory
from facegeo.checks import fmt_value

log = logging.getLogger(__name__)

__all__ = ["StageSpec", "StageContext", "StageResult", "Pipeline", "MANIFEST_NAME", "code_fingerprint",
           "forget_missing_stages", "record_metrics", "stale_stages"]

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


def _relocated(value, tmp: Path, final: Path):
    """``value`` (a stage's metrics: dicts, lists, strings) with every string path inside the
    staging folder ``tmp`` rewritten into ``final``, where the folder is swapped in (a stage
    records the files it wrote where it wrote them; ``metrics.json`` pointed into a deleted
    staging folder)."""
    if isinstance(value, dict):
        return {k: _relocated(v, tmp, final) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_relocated(v, tmp, final) for v in value)
    if isinstance(value, Path):
        value = str(value)
    if isinstance(value, str):
        t = str(tmp)
        if value == t or value.startswith(t + os.sep):
            return str(final) + value[len(t):]
    return value


@dataclass
class StageResult:
    """The outcome of one stage in one run: ``ran`` is False when its cached products were used;
    ``reason`` says why a stage ran (``"facegeo code changed"``, ``"no products yet"``,
    ``"settings changed: depth"``, ``"forced by --from decode"``; several joined by ``"; "``),
    None when it was cached."""

    name: str
    key: str
    ran: bool
    seconds: float
    metrics: dict
    out_dir: Path
    reason: str | None = None


#: Package files that run in no stage, left out of :func:`code_fingerprint` (relative paths;
#: a trailing ``/``: a folder): the command line (its choices reach a stage as settings, which
#: are in the key), the registered benchmarks and the report page (written after the stages,
#: from their products). An edit there reruns nothing. (``rss.py`` is stage code: the stages
#: measure their peak memory with its ``peak_rss_mb``.)
NOT_STAGE_CODE = ("cli.py", "__main__.py", "pipeline/report.py", "bench/")
#: Set to ``ignore`` to leave facegeo's code out of the stage keys (a developer editing code
#: that does not change the products, at their own risk: products of other code are reused).
CODE_KEY_ENV = "FACEGEO_STAGE_KEY_CODE"


def _is_source_file(rel: Path) -> bool:
    """Whether ``rel`` (relative to the package folder) is a source file of the fingerprint:
    a ``.py`` file outside ``__pycache__`` and hidden folders (numba's and Python's caches,
    editors' lock files such as ``.#x.py``) and not in :data:`NOT_STAGE_CODE`."""
    posix = rel.as_posix()
    return rel.suffix == ".py" and not any(part == "__pycache__" or part.startswith(".")
                                           for part in rel.parts) and not any(
        posix.startswith(x) if x.endswith("/") else posix == x for x in NOT_STAGE_CODE)


def code_fingerprint() -> str:
    """SHA-256 of facegeo's source code as it is installed: every ``facegeo/**/*.py`` file
    (relative path and bytes, in sorted path order) of the package this process imported —
    ``Path(facegeo.__file__).parent``, so an editable checkout and an installed wheel are both
    hashed where they are. ``__pycache__`` folders and hidden files are left out (byte-code
    and numba's caches change without the code changing), and so are the files of
    :data:`NOT_STAGE_CODE`, which run in no stage. With the environment variable
    :data:`CODE_KEY_ENV` set to ``ignore`` the fingerprint is ``"ignored"`` (code left out of
    the keys).

    Computed once per process and memoised (measured on the 2-core development VM: 4–5 ms for
    112 files, 2.1 MB, with the files in the page cache; ≈ 11 ms after evicting them; 0.05 ms
    memoised) and part of every stage's cache key, so a code change without a version bump
    reruns the stages. Every stage depends on the whole package: a
    per-stage set of modules would miss a change in a helper a stage reaches through a lazy
    import. A package that is not a folder of files (a zip import) has no sources to read:
    its fingerprint is ``"unavailable"`` and the version alone tells code apart.

    Returns
    -------
    str
        64 hexadecimal digits, ``"unavailable"`` or ``"ignored"``.
    """
    if os.environ.get(CODE_KEY_ENV, "").strip().lower() == "ignore":
        return "ignored"
    return _source_fingerprint(Path(facegeo.__file__).resolve().parent)


@functools.lru_cache(maxsize=4)
def _source_fingerprint(root: Path) -> str:
    """:func:`code_fingerprint` of the package folder ``root`` (memoised per folder)."""
    files = sorted((p.relative_to(root) for p in root.rglob("*.py")),
                   key=lambda rel: rel.as_posix())
    h = hashlib.sha256()
    n = 0
    for rel in files:
        if not _is_source_file(rel):
            continue
        try:
            data = (root / rel).read_bytes()
        except OSError:  # removed while listing, a dangling link: not part of the code
            continue
        name = rel.as_posix().encode()
        # length-prefixed: no two different trees give the same byte stream
        h.update(b"%d:%s%d:" % (len(name), name, len(data)))
        h.update(data)
        n += 1
    if n == 0:
        log.debug("no facegeo source files under %s: code fingerprint unavailable", root)
        return "unavailable"
    return h.hexdigest()


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


def _has_products(folder: Path) -> bool:
    """Whether ``folder`` is a directory with something in it."""
    try:
        return folder.is_dir() and any(folder.iterdir())
    except OSError:
        return False


def forget_missing_stages(out_dir: str | os.PathLike) -> list[str]:
    """Drop from ``out_dir/metrics.json`` every entry whose products are gone; return their
    names (sorted).

    An entry ``name`` describes the products in ``out_dir/name/`` (a stage of the pipeline, or
    ``views`` of ``facegeo render``): when that folder was deleted by hand, or emptied, the
    entry no longer describes anything on disk and is dropped, so ``metrics.json`` and the
    report (:func:`facegeo.pipeline.report.write_report` calls this) do not show figures of
    products that no longer exist until the stage runs again. Kept: entries with
    ``last_run_failed`` (they record the last run's failure, which has no products by nature).
    The file is rewritten (atomically) only when an entry is dropped; a missing or unreadable
    file is left as it is.
    """
    out_dir = Path(out_dir)
    path = out_dir / "metrics.json"
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    if not isinstance(doc, dict):
        return []
    gone = sorted(
        name for name, m in doc.items()
        if not (isinstance(m, dict) and "last_run_failed" in m)
        and not (isinstance(name, str) and name and "/" not in name and name not in (".", "..")
                 and _has_products(out_dir / name))
    )
    if gone:
        for name in gone:
            del doc[name]
        log.info("%s: dropped the entries of %s: their products are gone (deleted by hand?); "
                 "'facegeo reconstruct' rebuilds them", path, ", ".join(gone))
        atomic_write_text(path, json.dumps(doc, indent=2, sort_keys=True, allow_nan=False))
    return gone


def stale_stages(out_dir: str | os.PathLike) -> dict[str, list[str]]:
    """The stages under ``out_dir`` whose products were made from upstream products that have
    since been replaced: ``{stage: [the upstream stages that ran again since]}``.

    A stage's manifest records the keys of the stages it read (``upstream``); when one of those
    stages has run again since, or is itself stale (``facegeo mesh`` alone after a full
    ``reconstruct``: the atlas, projection, relight, fit and render on disk were all made from
    the previous mesh), the stage is stale — here ``{"atlas": ["mesh"], ..., "render":
    ["mesh"]}`` — until it runs again. Read from the stage folders' manifests each time (not
    stored): the report and the printed summary show it."""
    out_dir = Path(out_dir)
    keys: dict[str, str | None] = {}

    def key_of(name: str) -> str | None:
        if name not in keys:
            m = _read_manifest(out_dir / name)
            keys[name] = m.get("key") if m is not None else None
        return keys[name]

    upstream_of: dict[str, dict] = {}
    try:
        folders = [p.name for p in out_dir.iterdir() if p.is_dir()]
    except OSError:
        return {}
    for name in folders:
        m = _read_manifest(out_dir / name)
        if m is not None and isinstance(m.get("upstream"), dict):
            upstream_of[name] = m["upstream"]
    roots: dict[str, set] = {}  # stage -> the upstream stages that ran again since

    def roots_of(name: str, seen: tuple = ()) -> set:
        # direct: an upstream stage whose key moved; indirect: an upstream stage that is
        # itself stale (its products, and so this stage's, come from replaced ones)
        if name not in roots:
            found: set = set()
            for a, k in upstream_of.get(name, {}).items():
                if key_of(a) != k:
                    found.add(a)
                elif a not in seen:
                    found |= roots_of(a, seen + (name,))
            roots[name] = found
        return roots[name]

    return {name: sorted(r) for name in sorted(upstream_of) if (r := roots_of(name))}


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


def _command_settings(name: str, final: Path, previous: dict | None, given, settings: dict
                      ) -> tuple[dict, str | None]:
    """The settings stage ``name`` runs with, and the command they belong to.

    When the products on disk (``previous``: their manifest) were made by the stage's own
    command (``settings_by``, e.g. ``"facegeo calibrate"``), their settings are the user's and
    are kept: with no explicit settings for the stage in this run (``given`` None or empty),
    this run's ``settings`` (the stage's defaults) give way to them; explicit settings that
    agree with them are fine; explicit settings that differ are refused — running would replace
    the user's products with ones made otherwise. Otherwise ``settings`` as they are.

    Raises
    ------
    InputError
        ``given`` differs from the command's settings; the message names each differing
        setting with both values and says how to proceed.
    """
    by = (previous or {}).get("settings_by")
    kept = (previous or {}).get("settings")
    if not by or "key" not in previous or not isinstance(kept, dict):
        return settings, None
    differ = sorted(k for k in (given or {}) if kept.get(k, ...) != given[k])
    if differ:
        both = "; ".join(f"{k}: {fmt_value(kept.get(k))} there, {fmt_value(given[k])} asked"
                         for k in differ)
        raise InputError(f"stage {name!r}: {final} was made by '{by}' with other settings "
                         f"({both}); this run would replace it. Run '{by}' again with the "
                         f"settings wanted, or remove {final} to let this run make its own")
    if kept != settings:
        log.info("stage %s: keeping the settings of '%s' that made %s (%s)", name, by, final,
                 ", ".join(f"{k}={fmt_value(v)}" for k, v in sorted(kept.items())))
    return dict(kept), by


def _rerun_reason(previous: dict | None, doc: dict) -> str:
    """Why a stage whose products are not current runs: what differs between the manifest of
    the products on disk (``previous``, None when there is none) and the key document ``doc``
    of this run (:meth:`Pipeline._key`); several reasons are joined by ``"; "``."""
    if previous is None:
        return "no finished products yet"
    doc = json.loads(json.dumps(doc))  # as the manifest holds it (tuples as lists)
    if "key" not in previous:
        return "products written outside the stage cache"
    why = []
    if previous.get("facegeo_version") != doc["facegeo_version"]:
        why.append(f"facegeo version changed ({previous.get('facegeo_version')} → "
                   f"{doc['facegeo_version']})")
    if "facegeo_code" not in previous:
        why.append("facegeo code changed (the products predate code fingerprints)")
    elif previous["facegeo_code"] != doc["facegeo_code"]:
        why.append("facegeo code changed")
    old_s, new_s = previous.get("settings"), doc["settings"]
    if old_s != new_s:
        old_s = old_s if isinstance(old_s, dict) else {}
        names = sorted(k for k in set(old_s) | set(new_s) if old_s.get(k, ...) != new_s.get(k, ...))
        why.append("settings changed: " + ", ".join(map(str, names)))
    old_i, new_i = previous.get("inputs"), doc["inputs"]
    if old_i != new_i:
        old_i = old_i if isinstance(old_i, dict) else {}
        changed = sorted(k for k in set(old_i) | set(new_i) if old_i.get(k) != new_i.get(k))
        shown = ", ".join(changed[:3]) + (f" and {len(changed) - 3} more" if len(changed) > 3
                                           else "")
        why.append(f"input files changed: {shown}")
    old_u = previous.get("upstream")
    old_u = old_u if isinstance(old_u, dict) else {}
    redone = [a for a, k in doc["upstream"].items() if old_u.get(a) != k]
    if redone:
        why.append(f"upstream stage{'s' if len(redone) > 1 else ''} {', '.join(redone)} changed")
    return "; ".join(why) or "cache key format changed"


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
        settings_by: str | None = None,
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
        settings_by : str, optional
            The command whose settings ``settings`` are (``"facegeo calibrate"``: a stage's own
            command run as the stage): they may name settings the stage's defaults do not, the
            manifest records the command, and later runs keep its settings
            (:func:`_command_settings`). Without it, a stage whose products were made by its
            command keeps that command's settings.
        """
        scan_dir = Path(scan_dir)
        if not scan_dir.is_dir():
            raise InputError(f"scan directory {scan_dir} does not exist")
        self._check_stage(from_stage, "--from")
        self._check_stage(only, "--only")
        self._check_stage(until, "until")
        wanted = None if until is None else self._upstream_closure(until) | {until}
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
            bad = (sorted(set(given) - set(spec.settings))
                   if spec.settings and settings_by is None else [])
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
                final = out / spec.name
                previous = _read_manifest(final)
                by = settings_by
                if settings_by is None:  # products of the stage's own command keep its settings
                    stage_settings, by = _command_settings(
                        spec.name, final, previous, settings.get(spec.name), stage_settings)
                key, doc = self._key(spec, scan_dir, stage_settings, keys, memo)
                keys[spec.name] = key
                cached = previous if previous is not None and previous.get("key") == key else None
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
                    self._warn_if_standalone(final, previous)
                    if cached is not None:
                        reason = (f"forced by --from {from_stage}" if from_stage is not None
                                  else f"forced by --only {only}")
                    else:
                        reason = _rerun_reason(previous, doc)
                    log.info("stage %s: running (%s)", spec.name, reason)
                    try:
                        result = self._run_stage(spec, scan_dir, out, key, doc, progress,
                                                 reason, settings_by=by)
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

    def stages_run(self, *, only: str | None = None, until: str | None = None) -> list[str]:
        """The stages :meth:`run` may run with these arguments, in order: ``only`` alone (the
        others' products are only checked), else ``until`` and the stages it reads from, else
        every stage (cached ones are not run again)."""
        self._check_stage(only, "--only")
        self._check_stage(until, "until")
        wanted = None if until is None else self._upstream_closure(until) | {until}
        return [n for n in self.names if (wanted is None or n in wanted)
                and (only is None or n == only)]

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
            "facegeo_code": code_fingerprint(),
            "settings": stage_settings,
            "inputs": inputs,
            "upstream": {a: keys[a] for a in spec.after},
        }
        blob = _canonical_json(doc, f"stage {spec.name!r} settings")
        return hashlib.sha256(blob.encode()).hexdigest(), doc

    @staticmethod
    def _warn_if_standalone(final: Path, m: dict | None) -> None:
        """Say so when the products about to be replaced were written by a stage's own
        command (``facegeo atlas``, ``facegeo project``: a manifest without a key), whose
        settings the cache cannot know: they are rebuilt with the pipeline's settings (``m``:
        their manifest, or None)."""
        if m is not None and "key" not in m:
            log.warning("%s was written by 'facegeo %s' outside the stage cache (settings %s); "
                        "rebuilding it with the pipeline's settings", final, final.name,
                        m.get("settings", {}))

    def _run_stage(self, spec, scan_dir, out, key, doc, progress, reason, settings_by=None):
        """Run one stage into a staging folder swapped in as ``out/<stage>`` when it finishes;
        paths into the staging folder in its metrics are recorded as their final place."""
        final = out / spec.name
        log.debug("stage %s: key %s", spec.name, key[:12])
        t0 = time.perf_counter()
        with staged_directory(final) as tmp:
            ctx = StageContext(scan_dir, tmp, dict(doc["settings"]),
                               {a: out / a for a in spec.after}, progress)
            metrics = spec.run(ctx)
            if metrics is None:
                metrics = {}
            if not isinstance(metrics, dict):
                raise InputError(f"stage {fmt_value(spec.name)} returned {type(metrics).__name__}, "
                                 "expected a dict of metrics")
            seconds = time.perf_counter() - t0
            metrics = _relocated(metrics, tmp, final)
            if isinstance(metrics.get("seconds"), dict):  # a stage's own breakdown (relight)
                metrics["seconds_parts"] = metrics["seconds"]
            metrics = {**metrics, "seconds": round(seconds, 4)}  # the stage's wall time
            # what went into the key (facegeo_code: the code fingerprint), so a later run can
            # say why it reran the stage
            manifest = {
                **doc,
                "key": key,
                "metrics": metrics,
                "reason": reason,
                "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            }
            if settings_by:  # not in the key: the products are the same whoever asked
                manifest["settings_by"] = settings_by
            # the manifest is written last: a folder without it is never taken as finished
            atomic_write_text(tmp / MANIFEST_NAME,
                              json.dumps(manifest, indent=2, sort_keys=True, allow_nan=False))
        return StageResult(spec.name, key, True, seconds, metrics, final, reason)
