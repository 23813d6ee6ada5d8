"""``out/report.html``: every stage's metrics and images on one page, and a speed-against-error
summary for the terminal.

The report is built only from what the stages left in ``SCAN/out/``: ``metrics.json`` (one entry
per stage, written by :mod:`facegeo.pipeline.cache`) and the PNG images in each stage's folder.
It references the images by relative path (nothing is copied), so the page opens from the
``out/`` folder in any browser, and it is rewritten atomically after every run. A stage that has
not run yet is simply absent; the page says which of the pipeline's stages it shows. A stage whose
folder was deleted (or emptied) by hand is absent too: writing the report drops its entry from
``metrics.json`` (:func:`facegeo.pipeline.cache.forget_missing_stages`) and the page names it
once, as deleted, instead of showing figures of products that are gone.

The figures against references are the ``evaluate`` stage's (:mod:`facegeo.evaluate`, entry
``"evaluate"`` of ``metrics.json``, one sub-entry per compared stage): the speed-against-error
summary shows each beside the time of the stage whose products it measures (the ``project``
row's ``projection_rel_rmse``, the ``render`` row's ``psnr_db_min``), and the ``evaluate`` row
the headline figures of compared stages that have no row of their own (a ``facegeo evaluate``
of products made elsewhere).

When ``out/diagnostic/`` holds the stage-alone pass (:func:`facegeo.pipeline.reconstruct.
run_diagnostic`: the same stages fed the generator's rig and mesh; ``facegeo demo`` runs it),
the report shows the chain's evaluated figures and the stage-alone ones side by side
(:func:`chain_and_stage_alone`): how much of each error the chain's own calibration and mesh
add to the surface stages' own.
"""

from __future__ import annotations

import html
import json
import math
import time
from pathlib import Path
from typing import Any

from facegeo import __version__
from facegeo.errors import InputError
from facegeo.fsutil import atomic_write_text
from facegeo.pipeline.cache import forget_missing_stages, stale_stages
from facegeo.pipeline.reconstruct import DIAGNOSTIC_DIR, RUN_RECORD, STAGES

__all__ = ["PIPELINE_ORDER", "REPORT_NAME", "chain_and_stage_alone",
           "chain_and_stage_alone_table", "write_report", "summary_rows", "summary_table"]

#: Stage order of the whole pipeline (the order ``facegeo reconstruct`` runs them); stages not
#: listed come after these, alphabetically.
PIPELINE_ORDER = STAGES
REPORT_NAME = "report.html"
#: At most this many images per stage (the first ones in path order).
MAX_IMAGES_PER_STAGE = 24
#: Metric names that describe an error or a score (shown in the speed-against-error summary).
_ERROR_WORDS = ("error", "rmse", "rms_", "psnr", "agreement", "exact", "residual")


def _load_metrics(out_dir: Path) -> dict:
    path = out_dir / "metrics.json"
    if not path.is_file():
        raise InputError(f"{path}: no stage metrics yet; run `facegeo reconstruct` on the scan "
                         "first")
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: not readable JSON ({e})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object of stage entries")
    return data


def _ordered(stages) -> list[str]:
    known = [s for s in PIPELINE_ORDER if s in stages]
    return known + sorted(s for s in stages if s not in PIPELINE_ORDER)


def _flatten(d: Any, prefix: str = "") -> list[tuple[str, Any]]:
    rows: list[tuple[str, Any]] = []
    if isinstance(d, dict):
        for k in sorted(d, key=str):
            rows += _flatten(d[k], f"{prefix}.{k}" if prefix else str(k))
    else:
        rows.append((prefix, d))
    return rows


def _fmt(v: Any) -> str:
    if isinstance(v, bool) or v is None:
        return str(v).lower() if isinstance(v, bool) else "—"
    if isinstance(v, int):
        return f"{v:,}"
    if isinstance(v, float):
        if not math.isfinite(v):
            return str(v)
        if v != 0 and (abs(v) < 1e-3 or abs(v) >= 1e6):
            return f"{v:.3e}"
        return f"{v:.4g}"
    if isinstance(v, list):
        if len(v) <= 6 and all(isinstance(x, (int, float)) for x in v):
            return "[" + ", ".join(_fmt(x) for x in v) + "]"
        return f"[{len(v)} items]"
    return str(v)


def _is_error_metric(name: str) -> bool:
    low = name.lower()
    return any(w in low for w in _ERROR_WORDS)


def summary_rows(metrics: dict, stale: dict | None = None) -> list[dict]:
    """One row per stage: its time and its top-level error metrics (speed against error).

    Returns
    -------
    list of dict
        ``{"stage", "seconds", "errors": {name: value}, "stale": [stage, …]}`` in pipeline
        order; ``seconds`` is None when the stage did not record it; ``stale`` lists the upstream
        stages that ran again since this stage's products were made (from ``stale``, the
        ``{stage: [...]}`` of :func:`facegeo.pipeline.cache.stale_stages`; empty without it). A stage run on a rig other than the true one (a
        calibration's: its world frame is its own) shows its ``after_rigid_alignment`` figures
        as ``<name>_aligned`` in place of the same figures in the generator's frame (the gauge
        dominates those: 2–4 mm against a 0.08 mm shape error on the small preset).
    """
    from facegeo.evaluate.evaluation import summary_rows as evaluation_headlines

    evaluated = metrics.get("evaluate") if isinstance(metrics.get("evaluate"), dict) else {}
    rows = []
    for stage in _ordered(metrics):
        m = metrics[stage]
        if not isinstance(m, dict) or stage == RUN_RECORD:  # the run's choices: no stage
            continue
        sec = m.get("seconds")
        if isinstance(sec, dict):
            sec = sec.get("total")
        if stage == "evaluate":  # figures of compared stages without a row of their own
            errors = {f"{s}.{k}": v for s, k, v in evaluation_headlines(m)
                      if not isinstance(metrics.get(s), dict)
                      and isinstance(v, (int, float)) and not isinstance(v, bool)}
        else:  # the stage's own figures and the evaluation's of its products
            errors = _errors_of(m) | _errors_of(evaluated.get(stage) or {})
        # the stage's own (older metrics) or, since issue 37, the evaluation's of its products
        aligned = m.get("after_rigid_alignment") or (evaluated.get(stage) or {}).get(
            "after_rigid_alignment")
        if isinstance(aligned, dict) and _errors_of(aligned):
            # a rig other than the true one has its own world frame: the figures in the
            # generator's frame are mostly that gauge (millimetres); the shape's own error is
            # the one after the rigid alignment, shown in their place
            errors = {f"{k}_aligned": v for k, v in _errors_of(aligned).items()} | {
                k: v for k, v in errors.items() if k not in _errors_of(aligned)}
        rows.append({"stage": stage, "seconds": sec if isinstance(sec, (int, float)) else None,
                     "errors": errors, "stale": list((stale or {}).get(stage, []))})
    return rows


def _errors_of(m: dict) -> dict:
    """The top-level numeric error metrics of a metrics dict."""
    return {k: v for k, v in m.items()
            if _is_error_metric(k) and isinstance(v, (int, float)) and not isinstance(v, bool)}


def summary_table(metrics: dict, stale: dict | None = None) -> str:
    """The speed-against-error summary as plain text, for the terminal (``stale``: see
    :func:`summary_rows`)."""
    rows = summary_rows(metrics, stale)
    if not rows:
        return "no stage metrics"
    lines = [f"{'stage':<10} {'seconds':>9}  error metrics"]
    for r in rows:
        sec = f"{r['seconds']:.2f}" if r["seconds"] is not None else "—"
        errs = ", ".join(f"{k} {_fmt(v)}" for k, v in r["errors"].items()) or "—"
        if r.get("stale"):
            errs = f"[stale: made from an older {', '.join(r['stale'])}] " + errs
        lines.append(f"{r['stage']:<10} {sec:>9}  {errs}")
    return "\n".join(lines)


#: Figures of the side-by-side table besides the evaluation's headlines
#: (:data:`facegeo.evaluate.evaluation.HEADLINES`), per compared stage.
SIDE_BY_SIDE_EXTRA: dict[str, tuple[str, ...]] = {
    "render": ("psnr_db_mean", "naive_psnr_db_mean", "paper_psnr_db_mean"),
}


def _evaluated(out_dir: Path) -> dict:
    """``out_dir/metrics.json`` → ``"evaluate"`` ({} when absent or unreadable)."""
    try:
        m = json.loads((out_dir / "metrics.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    ev = m.get("evaluate") if isinstance(m, dict) else None
    return ev if isinstance(ev, dict) else {}


def chain_and_stage_alone(out_dir) -> list[dict]:
    """The chain's evaluated figures beside the stage-alone pass's (``out/diagnostic/``).

    A figure of a compared stage that has an ``after_rigid_alignment`` form (the mesh on a
    calibrated rig: its world frame is its own gauge) is shown in that form, marked
    ``aligned``, in both columns where each has it; a figure of such a stage without that form
    is marked ``gauge`` (it holds the calibrated frame's offset from the generator's: 0.20° /
    3.56 mm on the small preset, millimetres against a 0.03 mm shape error). The calibration
    has no upstream stage: its stage-alone figures are the chain's.

    Returns
    -------
    list of dict
        ``{"stage", "figure", "chain", "stage_alone", "aligned", "gauge"}`` in pipeline order,
        a value None where that pass lacks the figure; [] without a diagnostic pass.
    """
    from facegeo.evaluate.evaluation import HEADLINES

    out_dir = Path(out_dir)
    alone = _evaluated(out_dir / DIAGNOSTIC_DIR)
    if not alone:
        return []
    chain = _evaluated(out_dir)

    def value(m: dict, key: str) -> tuple[Any, bool]:
        aligned = m.get("after_rigid_alignment")
        if isinstance(aligned, dict) and _is_number(aligned.get(key)):
            return aligned[key], True
        return (m.get(key), False) if _is_number(m.get(key)) else (None, False)

    rows = []
    for stage, keys in HEADLINES.items():
        c, a = chain.get(stage), alone.get(stage)
        if not isinstance(c, dict) and not isinstance(a, dict):
            continue
        for key in keys + SIDE_BY_SIDE_EXTRA.get(stage, ()):
            cv, ca = value(c if isinstance(c, dict) else {}, key)
            av, aa = value(a if isinstance(a, dict) else {}, key)
            if stage == "calibrate" and not isinstance(a, dict):
                av, aa = cv, ca  # no upstream: the calibration alone is the chain's
            if cv is None and av is None:
                continue
            gauge = (not ca and cv is not None and isinstance(c, dict)
                     and isinstance(c.get("after_rigid_alignment"), dict))
            rows.append({"stage": stage, "figure": key, "chain": cv, "stage_alone": av,
                         "aligned": ca or aa, "gauge": gauge})
    return rows


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def chain_and_stage_alone_table(out_dir) -> str:
    """:func:`chain_and_stage_alone` as plain text for the terminal."""
    rows = chain_and_stage_alone(out_dir)
    if not rows:
        return "no stage-alone pass (out/diagnostic/) to compare with"
    lines = [f"{'stage':<10} {'figure':<44} {'chain':>12} {'stage alone':>12}"]
    for r in rows:
        lines.append(f"{r['stage']:<10} {_side_name(r):<44} {_fmt(r['chain']):>12} "
                     f"{_fmt(r['stage_alone']):>12}")
    if any(r["gauge"] for r in rows):
        lines.append("(aligned: after the best rigid alignment with the truth; gauge: the "
                     "chain's figure includes its calibrated frame's offset)")
    return "\n".join(lines)


def _side_name(r: dict) -> str:
    return r["figure"] + (" (aligned)" if r["aligned"] else " (gauge)" if r["gauge"] else "")


def _images(stage_dir: Path, out_dir: Path) -> list[str]:
    if not stage_dir.is_dir():
        return []
    found = sorted(p for p in stage_dir.rglob("*.png") if p.is_file())
    return [p.relative_to(out_dir).as_posix() for p in found[:MAX_IMAGES_PER_STAGE]]


def _bar_chart(rows: list[dict]) -> str:
    """An inline SVG bar chart of seconds per stage (no plotting dependency)."""
    timed = [r for r in rows if r["seconds"] is not None]
    if not timed:
        return ""
    width, bar_h, gap, label_w = 520, 18, 6, 90
    top = max(r["seconds"] for r in timed) or 1.0
    h = len(timed) * (bar_h + gap) + gap
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width + label_w + 80}" '
             f'height="{h}" role="img" aria-label="seconds per stage">']
    for i, r in enumerate(timed):
        y = gap + i * (bar_h + gap)
        w = max(1.0, width * r["seconds"] / top)
        parts.append(f'<text x="{label_w - 6}" y="{y + bar_h - 5}" text-anchor="end">'
                     f'{html.escape(r["stage"])}</text>')
        parts.append(f'<rect x="{label_w}" y="{y}" width="{w:.1f}" height="{bar_h}" '
                     'fill="#4a7fb5"/>')
        parts.append(f'<text x="{label_w + w + 4:.1f}" y="{y + bar_h - 5}">'
                     f'{r["seconds"]:.2f} s</text>')
    parts.append("</svg>")
    return "\n".join(parts)


_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em; max-width: 1200px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 2px 8px; text-align: left; vertical-align: top; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
figure { display: inline-block; margin: 0 1em 1em 0; vertical-align: top; }
figure img { max-width: 360px; max-height: 360px; border: 1px solid #ddd;
             image-rendering: pixelated; }
figcaption { font-size: 0.8em; color: #555; max-width: 360px; word-break: break-all; }
details { margin-bottom: 1em; }
svg text { font-size: 12px; }
"""


def write_report(out_dir, *, title: str | None = None, stale: dict | None = None) -> Path:
    """Write ``OUT/report.html`` from ``OUT/metrics.json`` and the stages' PNG images.

    An entry of ``metrics.json`` whose products are gone (its folder ``OUT/<stage>/`` deleted
    or emptied by hand since the stage ran) is **dropped**, from ``metrics.json`` as well
    (:func:`facegeo.pipeline.cache.forget_missing_stages`; entries that record a failed run,
    ``last_run_failed``, are kept): the page shows only products that exist, and names the
    dropped stages once (rerunning ``facegeo reconstruct`` rebuilds them).

    Parameters
    ----------
    out_dir : path-like
        A scan's ``out/`` folder (``facegeo reconstruct`` writes it).
    title : str, optional
        Page title (default: the scan folder's name).
    stale : dict of str -> list of str, optional
        :func:`facegeo.pipeline.cache.stale_stages` of ``out_dir`` when the caller has it
        already (the CLI prints it in its summary too); read from the manifests when None.

    Returns
    -------
    Path
        The report, written atomically.

    Raises
    ------
    InputError
        ``metrics.json`` is missing or not a JSON object.
    """
    out_dir = Path(out_dir)
    dropped = forget_missing_stages(out_dir)
    metrics = _load_metrics(out_dir)
    stages = _ordered(metrics)
    title = title or f"facegeo report: {out_dir.resolve().parent.name}"
    rows = summary_rows(metrics, stale_stages(out_dir) if stale is None else stale)
    esc = html.escape
    body = [f"<h1>{esc(title)}</h1>",
            f"<p>facegeo {esc(__version__)}, written {esc(time.strftime('%Y-%m-%d %H:%M:%S'))}."
            f" Stages shown: {esc(', '.join(stages)) or 'none'}; pipeline: "
            f"{esc(' → '.join(PIPELINE_ORDER))}.</p>"]
    run = metrics.get(RUN_RECORD)
    if isinstance(run, dict):
        body.append(f"<p>Made with rig <code>{esc(str(run.get('rig')))}</code>, mesh "
                    f"<code>{esc(str(run.get('mesh')))}</code>, world frame "
                    f"{esc(str(run.get('world')))}.</p>")
    if dropped:
        body.append(f'<p class="dropped">Products deleted since they were made, so not shown '
                    f'(and dropped from metrics.json): {esc(", ".join(dropped))}; '
                    "<code>facegeo reconstruct</code> rebuilds them.</p>")
    body += ["<h2>Speed against error</h2>", "<table><tr><th>stage</th><th>seconds</th>"
             "<th>error metrics</th></tr>"]
    for r in rows:
        sec = f"{r['seconds']:.2f}" if r["seconds"] is not None else "—"
        errs = "<br>".join(f"{esc(k)} = {esc(_fmt(v))}" for k, v in r["errors"].items()) or "—"
        if r.get("stale"):
            errs = (f'<em class="stale">stale: made from an older {esc(", ".join(r["stale"]))}'
                    " (run <code>facegeo reconstruct</code>)</em><br>" + errs)
        body.append(f'<tr><td><a href="#{esc(r["stage"])}">{esc(r["stage"])}</a></td>'
                    f'<td class="num">{sec}</td><td>{errs}</td></tr>')
    body.append("</table>")
    body.append(_bar_chart(rows))
    side = chain_and_stage_alone(out_dir)
    if side:
        body += ['<h2 id="chain-and-stage-alone">The chain and the stages alone</h2>',
                 "<p>The chain: the calibrated rig and the reconstructed mesh (this page). "
                 "Stage alone: the same stages fed the generator's true rig and mesh (a "
                 f"diagnostic, <code>{esc(DIAGNOSTIC_DIR)}/</code>, "
                 f'<a href="{esc(DIAGNOSTIC_DIR)}/{REPORT_NAME}">its report</a>). '
                 "<em>aligned</em>: after the best rigid alignment with the truth (a "
                 "calibrated rig's world frame is its own gauge); <em>gauge</em>: the chain's "
                 "figure in its own frame, offset included.</p>",
                 "<table><tr><th>stage</th><th>figure</th><th>chain</th><th>stage alone</th>"
                 "</tr>"]
        for r in side:
            body.append(f"<tr><td>{esc(r['stage'])}</td><td>{esc(_side_name(r))}</td>"
                        f'<td class="num">{esc(_fmt(r["chain"]))}</td>'
                        f'<td class="num">{esc(_fmt(r["stage_alone"]))}</td></tr>')
        body.append("</table>")
    for stage in stages:
        m = metrics[stage]
        body.append(f'<h2 id="{esc(stage)}">{esc(stage)}</h2>')
        flat = _flatten(m) if isinstance(m, dict) else [("value", m)]
        top = [(k, v) for k, v in flat if k.count(".") == 0]
        nested = [(k, v) for k, v in flat if k.count(".") > 0]
        body.append("<table>" + "".join(
            f'<tr><td>{esc(k)}</td><td class="num">{esc(_fmt(v))}</td></tr>' for k, v in top)
            + "</table>")
        if nested:
            body.append(f"<details><summary>{len(nested)} more values</summary><table>"
                        + "".join(f'<tr><td>{esc(k)}</td><td class="num">{esc(_fmt(v))}</td></tr>'
                                  for k, v in nested) + "</table></details>")
        for rel in _images(out_dir / stage, out_dir):
            body.append(f'<figure><a href="{esc(rel)}"><img src="{esc(rel)}" alt="{esc(rel)}" '
                        f'loading="lazy"></a><figcaption>{esc(rel)}</figcaption></figure>')
    page = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{esc(title)}</title><style>{_CSS}</style></head><body>\n"
            + "\n".join(body) + "\n</body></html>\n")
    path = out_dir / REPORT_NAME
    atomic_write_text(path, page)
    return path

