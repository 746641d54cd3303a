"""Commands print only what their user needs: on stderr nothing but this project's log records.

Native libraries wrote banners ("pybullet build time: ..."), OMPL wrote a bare "Error:" about
seeding, and nanobind listed OMPL objects "leaked" at exit: a user reads each as a crash.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ..conftest import MBM_DIR
from .conftest import free_port, write_config

LOG_RECORD = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} (DEBUG|INFO|WARNING|ERROR|CRITICAL) robonav(\.[\w.]+)?: ")
ROBONAV = [sys.executable, "-m", "robonav.services.cli"]


def _foreign_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.strip() and not LOG_RECORD.match(line)]


def _run(args: list[str], timeout_s: float = 120.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*ROBONAV, *args], capture_output=True, text=True, timeout=timeout_s,
                          env=dict(os.environ, PYTHONUNBUFFERED="1"))


@pytest.mark.skipif(not MBM_DIR.is_dir(), reason=f"MBM problems not found at {MBM_DIR}")
def test_bench_plan_on_one_problem_prints_its_table_and_nothing_else(tmp_path: Path) -> None:
    problems = json.loads((MBM_DIR / "box.json").read_text(encoding="utf-8"))
    problems["problems"], problems["count"] = problems["problems"][:1], 1
    one = tmp_path / "box.json"
    one.write_text(json.dumps(problems), encoding="utf-8")
    done = _run(["bench", "plan", "--problems", str(one), "--no-progress", "--seed", "1"])
    assert done.returncode == 0, done.stderr
    assert "overall" in done.stdout
    assert _foreign_lines(done.stderr) == [], done.stderr


def test_help_prints_no_banner() -> None:
    for args in (["demo", "--help"], ["bench", "--help"]):
        done = _run(args)
        assert done.returncode == 0, done.stderr
        assert _foreign_lines(done.stderr) == [], (args, done.stderr)


@pytest.mark.e2e
def test_a_stack_start_and_stop_logs_only_records_of_its_own(tmp_path: Path) -> None:
    config = write_config(tmp_path, "quiet.yaml", zenoh={"connect": [f"tcp/127.0.0.1:{free_port()}"]},
                          sim={"follow": "kinematic"}, cameras={"width": 160, "height": 120})
    log = tmp_path / "up.stderr"
    with log.open("w") as stderr:
        up = subprocess.Popen([*ROBONAV, "up", "--config", str(config), "--log-level", "INFO"], stdout=subprocess.DEVNULL,
                              stderr=stderr, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        try:
            deadline = time.monotonic() + 90.0
            while time.monotonic() < deadline and log.read_text().count(": serving under robonav/") < 4:
                time.sleep(0.2)
            assert log.read_text().count(": serving under robonav/") >= 4, log.read_text()
        finally:
            up.send_signal(signal.SIGTERM)
            up.wait(timeout=60)
    assert up.returncode == 0, log.read_text()
    assert _foreign_lines(log.read_text()) == [], log.read_text()
