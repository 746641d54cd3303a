"""`robonav bench perception`: a short run writes the figures the issue asks for."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e


def test_bench_perception_writes_stage_latency_and_rate_figures(tmp_path: Path) -> None:
    out = tmp_path / "perception.json"
    run = subprocess.run([sys.executable, "-m", "robonav.services.cli", "bench", "perception", "--frames", "12",
                          "--distinct", "2", "--rate", "10", "--accuracy-frames", "3", "--json", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    report = json.loads(out.read_text())
    assert report["frames"] == 12
    assert report["latency_ms"]["p50"] > 0 and report["latency_ms"]["p95"] >= report["latency_ms"]["p50"]
    assert 0 < report["sustained_hz"] <= 12
    for stage in ("to_depth", "hits", "self_filter", "clearing", "publish_encode"):
        assert report["stages"][stage]["p50"] >= 0
    assert report["core"]["raycast"]["stages"]["raycast"]["p50"] > 0
    assert set(report["core"]["projection"]["clustering_ms"]) == {"components", "dbscan"}
    assert "frame→map latency" in run.stdout
    accuracy = report["accuracy"]
    assert accuracy["frames_per_pose"] == 3 and len(accuracy["poses"]) == 3
    assert all(pose["surface_voxels"] > 1000 for pose in accuracy["poses"])  # the default scene's visible faces
    assert accuracy["surface_covered_within_one_voxel_min"] > 0.9 and accuracy["on_robot_total"] == 0


def test_bench_perception_refuses_bad_arguments() -> None:
    run = subprocess.run([sys.executable, "-m", "robonav.services.cli", "bench", "perception", "--frames", "1"],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "--frames >= 2" in run.stderr
