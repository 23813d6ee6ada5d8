"""The benchmark registry and its reports (correctness only: no timing asserts)."""

from __future__ import annotations

import json

import pytest

from facegeo.pipeline.bench import BenchRow, register, registered, run_benchmarks, write_reports
from facegeo.errors import InputError


def test_every_stage_registers_benchmarks():
    names = registered()
    for expected in ("visibility.closest_hit", "visibility.occluded", "synth.generate",
                     "structured_light.decode_gray"):
        assert expected in names


def test_unknown_benchmark_lists_available():
    with pytest.raises(InputError, match="available: .*visibility.closest_hit"):
        run_benchmarks(["no.such.bench"])


def test_reports_written_and_escaped(tmp_path):
    @register("test.dummy")
    def _dummy(quick):
        return [BenchRow("test.dummy", "a|b", 2.0, "x/s", error=0.5, error_unit="max |e|",
                         ratios={"vs ref": 1.5}, extra={"n": 3})]

    rows = run_benchmarks(["test.dummy"], quick=True)
    j, m = write_reports(rows, tmp_path)
    data = json.loads(j.read_text())
    assert data["rows"][0]["ratios"] == {"vs ref": 1.5}
    line = m.read_text().splitlines()[2]
    assert line.count(" | ") == 5  # six cells: pipes inside cells are escaped
    assert "a\\|b" in line and "max \\|e\\|" in line
