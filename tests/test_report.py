"""``out/report.html``: parses, references only files that exist, escapes what it shows."""

from __future__ import annotations

import json
from html.parser import HTMLParser

import numpy as np
import pytest

from facegeo.capture.imageio import write_image
from facegeo.errors import InputError
from facegeo.pipeline.report import summary_rows, summary_table, write_report


class _Collect(HTMLParser):
    def __init__(self):
        super().__init__()
        self.srcs, self.ids, self.text, self.stack = [], set(), [], []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.srcs.append(a["src"])
        if "id" in a:
            self.ids.add(a["id"])
        if tag not in ("img", "meta", "br"):
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):  # <rect .../>: opens and closes
        if tag == "img":
            self.srcs.append(dict(attrs)["src"])

    def handle_endtag(self, tag):
        assert self.stack and self.stack[-1] == tag, f"unbalanced </{tag}>"
        self.stack.pop()

    def handle_data(self, data):
        self.text.append(data)


def _out(tmp_path):
    out = tmp_path / "out"
    metrics = {
        "project": {"seconds": 9.07, "projection_rel_rmse": 0.049, "texels": 107707,
                    "cameras": {"cam_left": {"visible_fraction": 0.39}}},
        "atlas": {"seconds": 2.03, "mesh": "ground truth <mesh.ply> & more", "charts": 9},
        "custom": {"seconds": {"total": 1.5}, "phase_rms_error_proj_px": 0.04},
    }
    for stage in metrics:  # every entry's products are on disk (a manifest, at least)
        (out / stage).mkdir(parents=True)
        (out / stage / "stage.json").write_text("{}")
    (out / "project" / "cam_left").mkdir(parents=True)
    (out / "metrics.json").write_text(json.dumps(metrics))
    write_image(out / "project" / "preview.png", np.zeros((4, 4, 3), np.uint8))
    write_image(out / "project" / "cam_left" / "x.png", np.zeros((4, 4), np.uint8))
    return out, metrics


def test_report_parses_and_every_image_exists(tmp_path):
    out, _ = _out(tmp_path)
    path = write_report(out)
    assert path == out / "report.html"
    p = _Collect()
    p.feed(path.read_text())
    p.close()
    assert p.stack == []  # every element closed
    assert sorted(p.srcs) == ["project/cam_left/x.png", "project/preview.png"]
    for src in p.srcs:
        assert (out / src).is_file(), src
    # pipeline order first (atlas before project), unknown stages after
    assert p.ids >= {"atlas", "project", "custom"}
    text = "".join(p.text)
    assert text.index("atlas") < text.index("project")
    # values are escaped, not markup
    assert "ground truth <mesh.ply> & more" in text
    assert "<mesh.ply>" not in path.read_text()


def test_summary_is_speed_against_error(tmp_path):
    _, metrics = _out(tmp_path)
    rows = summary_rows(metrics)
    assert [r["stage"] for r in rows] == ["atlas", "project", "custom"]
    assert rows[1]["seconds"] == 9.07 and rows[1]["errors"] == {"projection_rel_rmse": 0.049}
    assert rows[2]["seconds"] == 1.5 and "phase_rms_error_proj_px" in rows[2]["errors"]
    assert "projection_rel_rmse 0.049" in summary_table(metrics)


def test_summary_shows_a_calibrated_rigs_aligned_shape_error():
    """A mesh made with a rig other than the true one (its own world frame) is summarised by
    its error after the rigid alignment (the shape), not by the gauge-dominated figures in the
    generator's frame; a true-rig mesh keeps its figures as they are."""
    shape = {"points_rms_error_mm": 0.081, "mesh_p95_error_mm": 0.215,
             "normal_median_error_deg": 1.34, "alignment_translation_mm": 4.08}
    calibrated = {"seconds": 3.5, "points_rms_error_mm": 2.816, "mesh_p95_error_mm": 3.771,
                  "normal_median_error_deg": 1.5, "after_rigid_alignment": shape}
    row = summary_rows({"mesh": calibrated})[0]
    assert row["errors"] == {"points_rms_error_mm_aligned": 0.081,
                             "mesh_p95_error_mm_aligned": 0.215,
                             "normal_median_error_deg_aligned": 1.34}
    assert "mesh_p95_error_mm_aligned 0.215" in summary_table({"mesh": calibrated})
    true_rig = {k: v for k, v in calibrated.items() if k != "after_rigid_alignment"}
    assert summary_rows({"mesh": true_rig})[0]["errors"]["mesh_p95_error_mm"] == 3.771


def test_missing_metrics_is_a_clear_error(tmp_path):
    with pytest.raises(InputError, match="metrics.json.*facegeo reconstruct"):
        write_report(tmp_path)
    (tmp_path / "metrics.json").write_text("[1, 2]")
    with pytest.raises(InputError, match="JSON object"):
        write_report(tmp_path)


def test_a_stage_folder_deleted_by_hand_is_dropped_from_report_and_metrics(tmp_path):
    """An entry whose products were deleted (folder gone, or emptied) since its stage ran is
    dropped from metrics.json and not shown, and the page names it once; an entry recording
    a failed run (no products by nature) is kept."""
    import shutil

    out, metrics = _out(tmp_path)
    write_report(out)
    assert set(json.loads((out / "metrics.json").read_text())) == set(metrics)  # all there
    shutil.rmtree(out / "project")
    (out / "atlas" / "stage.json").unlink()  # emptied
    doc = json.loads((out / "metrics.json").read_text())
    doc["mesh"] = {"last_run_failed": "RuntimeError: boom"}  # failed before any products
    (out / "metrics.json").write_text(json.dumps(doc))
    page = write_report(out).read_text()
    assert set(json.loads((out / "metrics.json").read_text())) == {"custom", "mesh"}
    p = _Collect()
    p.feed(page)
    p.close()
    assert "project" not in p.ids and "atlas" not in p.ids and p.srcs == []
    assert {"custom", "mesh"} <= p.ids
    text = " ".join("".join(p.text).split())
    assert "(and dropped from metrics.json): atlas, project;" in text
    assert "projection_rel_rmse" not in text
    # named once: the next report has nothing left to drop
    assert "dropped" not in write_report(out).read_text()
