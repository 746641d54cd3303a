"""`robonav bench executor`: the report's fields, with the perception service feeding the path monitor
and a box dropped on a moving arm's path."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e


def test_the_executor_bench_reports_periods_ratios_and_the_perception_load(tmp_path: Path) -> None:
    out = tmp_path / "executor.json"
    run = subprocess.run([sys.executable, "-m", "robonav.services.cli", "bench", "executor", "--seconds", "4",
                          "--paths", "2", "--perception-hz", "10", "--drops", "1", "--reference-loop", "--json", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    report = json.loads(out.read_text(encoding="utf-8"))
    assert report["rate_hz"] == 1000.0 and report["setpoints"] > 1000
    assert set(report["period_error_ms"]) == {"p50", "p99", "max"} and report["missed"] >= 0
    assert {"median", "max"} <= set(report["duration_ratio_vs_toppra"])
    assert report["perception_hz"] == 10.0 and report["perception_maps_hz"] > 0  # maps reached the executor
    assert run.stderr.count("is blocked") == 1  # the static map stopped nothing; the dropped box did
    reference = report["reference_loop"]  # a bare loop ran beside the stream for the whole measurement
    assert reference["reference_missed"] >= 0 and 0 <= reference["shared"] <= reference["stream_missed"]
    assert reference["reference_period_error_ms"]["p50"] < 1.0
    drop = report["drop_stop"]
    assert (drop["drops"], drop["stopped"]) == (1, 1) and drop["p50"] > 0
