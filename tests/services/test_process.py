"""Services as processes: clean exit on SIGINT/SIGTERM, exit code 2 on a bad config."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from robonav.services.client import RobonavClient
from robonav.services.common import open_session
from robonav.services.config import ZenohConfig

HERE = Path(__file__).resolve().parent


def _load_conftest_helpers():  # noqa: ANN202 - importlib mode: conftest is not importable by name
    import importlib.util

    spec = importlib.util.spec_from_file_location("services_conftest", HERE / "conftest.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_planner_process_stops_cleanly_on_signal(tmp_path: Path, signum: int) -> None:
    helpers = _load_conftest_helpers()
    endpoint = f"tcp/127.0.0.1:{helpers.free_port()}"
    # The service is a peer listening on its own port, so no router is needed.
    config = helpers.write_config(tmp_path, "peer.yaml", zenoh={"mode": "peer", "listen": [endpoint], "connect": []})
    proc = subprocess.Popen([sys.executable, "-m", "robonav.services.cli", "serve", "planner", "--config", str(config)])
    try:
        deadline = time.monotonic() + 30.0
        while True:
            try:
                session = open_session(ZenohConfig(mode="client", connect=(endpoint,)))
                break
            except Exception:
                assert time.monotonic() < deadline and proc.poll() is None, "planner never listened"
                time.sleep(0.2)
        with session:
            client = RobonavClient(session)
            assert not client.wait_for_services(["planner"], 30.0)
            client.close()
        proc.send_signal(signum)
        assert proc.wait(timeout=15) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_bad_config_exits_with_code_2_and_names_the_key(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("planner:\n  seed: many\n", encoding="utf-8")
    run = subprocess.run([sys.executable, "-m", "robonav.services.cli", "serve", "executor", "--config", str(bad)],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    assert "planner.seed" in run.stderr and "expected int" in run.stderr
