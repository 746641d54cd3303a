"""The supervisor on real (small) processes: restarts with a doubling wait, counts, the wait falls
back after a healthy run, the time away ends with the liveliness token, stop codes."""

from __future__ import annotations

import logging
import os
import re
import signal
import sys
import time

import pytest

from robonav.services.config import StackConfig
from robonav.services.stack.supervisor import Supervisor, describe_exit

from ..conftest import wait_for

SLEEPER = [sys.executable, "-c", "import time; time.sleep(60)"]
FAILER = [sys.executable, "-c", "import sys; sys.exit(3)"]


def _row(supervisor: Supervisor, name: str):  # noqa: ANN202
    return next(r for r in supervisor.status() if r.name == name)


def test_a_killed_process_is_restarted_counted_and_back_when_its_token_returns() -> None:
    supervisor = Supervisor(StackConfig(restart_backoff_initial_s=0.2), restart=True)
    supervisor.add("worker", lambda: SLEEPER)
    supervisor.run_in_background()
    try:
        supervisor.token("worker", True)
        first = supervisor.pid("worker")
        assert _row(supervisor, "worker").alive and _row(supervisor, "worker").state == "running"
        os.kill(first, signal.SIGKILL)
        supervisor.token("worker", False)  # as Zenoh reports the dead session's token
        assert wait_for(lambda: _row(supervisor, "worker").state == "restarting")
        row = _row(supervisor, "worker")
        assert not row.alive and row.last_exit_code == -signal.SIGKILL and row.restart_in_s is not None
        assert supervisor.dead() == {"worker": -signal.SIGKILL}
        assert wait_for(lambda: supervisor.pid("worker") not in (None, first))
        row = _row(supervisor, "worker")
        assert row.restarts == 1 and row.state == "running" and not row.alive and row.last_back_s is None
        time.sleep(0.3)
        supervisor.token("worker", True)  # the restarted service serves
        row = _row(supervisor, "worker")
        assert row.alive and row.last_back_s is not None and 0.5 <= row.last_back_s < 5.0
        assert supervisor.dead() == {}
    finally:
        codes = supervisor.stop([["worker"]], grace_s=5.0)
    assert codes == {"worker": -signal.SIGINT}  # a bare sleeper dies of the SIGINT


def test_the_wait_doubles_for_exits_in_a_row_up_to_the_bound_and_falls_back_after_a_healthy_run(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.ERROR, logger="robonav.up")
    supervisor = Supervisor(StackConfig(restart_backoff_initial_s=0.1, restart_backoff_max_s=0.4), restart=True)
    supervisor.add("crashy", lambda: FAILER, has_token=False)
    supervisor.run_in_background()
    assert wait_for(lambda: _row(supervisor, "crashy").restarts >= 4, timeout_s=30.0)
    supervisor.stop([["crashy"]], grace_s=5.0)
    waits = [float(m.group(1)) for r in caplog.records if (m := re.search(r"restarting in ([0-9.]+) s", r.getMessage()))]
    assert waits[:4] == [0.1, 0.2, 0.4, 0.4], waits
    assert _row(supervisor, "crashy").last_exit_code == 3

    caplog.clear()
    policy = StackConfig(restart_backoff_initial_s=0.1, restart_backoff_max_s=0.4, restart_backoff_reset_s=1.0)
    healthy = Supervisor(policy, restart=True)
    healthy.add("steady", lambda: [sys.executable, "-c", "import time; time.sleep(1.2)"], has_token=False)
    healthy._children["steady"].backoff_s = 0.4  # as after several quick exits
    assert wait_for(lambda: (healthy.poll(), _row(healthy, "steady").restarts >= 1)[1], timeout_s=20.0)
    healthy.stop([["steady"]], grace_s=5.0)
    waits = [float(m.group(1)) for r in caplog.records if (m := re.search(r"restarting in ([0-9.]+) s", r.getMessage()))]
    assert waits[0] == 0.1, waits  # it ran longer than restart_backoff_reset_s


def test_without_restarts_an_exit_is_final_and_reported() -> None:
    supervisor = Supervisor(StackConfig(), restart=False)
    supervisor.add("once", lambda: FAILER)
    supervisor.add("view", lambda: SLEEPER, has_token=False)
    assert wait_for(lambda: "once" in supervisor.dead())
    time.sleep(0.3)
    supervisor.poll()
    once, view = _row(supervisor, "once"), _row(supervisor, "view")
    assert (once.state, once.restarts, once.last_exit_code, once.alive) == ("stopped", 0, 3, False)
    assert view.alive and view.state == "running" and view.pid is not None  # no token: running is alive
    codes = supervisor.stop([["once", "view"]], grace_s=5.0)
    assert codes == {"once": 3, "view": -signal.SIGINT}


def test_exit_descriptions() -> None:
    assert describe_exit(0) == "exit code 0"
    assert describe_exit(-9) == "killed by SIGKILL"
    assert describe_exit(-200) == "killed by signal 200"
