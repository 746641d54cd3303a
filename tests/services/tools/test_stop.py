"""Stopping is one keystroke: Ctrl-C in `robonav plan --execute` and in the example client stops
the arm and waits for rest; `robonav stop` stops a moving arm. Real services (`robonav up`, the
kinematic sim), real commands as subprocesses, real signals."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from robonav.pipeline.wire.codes import ExecutionState
from robonav.pipeline.wire.messages import ExecuteResponse, PlanResponse
from robonav.services.client import RobonavClient
from robonav.services.config import load_config
from robonav.services.tools.stop import EXIT_INTERRUPTED, REST_VELOCITY_RAD_S

from ...conftest import REPO_ROOT
from ..conftest import free_port, write_config

GOALS = [np.array(g) for g in load_config().demo.goals_rad]
SLOW = 0.1
"""Velocity and acceleration scaling of the motions stopped here: seconds long, easy to catch moving."""


def farthest_goal(client: RobonavClient) -> np.ndarray:
    assert client.joint_state is not None
    return max(GOALS, key=lambda g: float(np.max(np.abs(g - client.joint_state.position))))


def wait_moving(client: RobonavClient, timeout_s: float = 90.0) -> str:
    """Wait until the executor streams a trajectory and the arm moves; returns the trajectory id."""
    assert client.wait_for(lambda: client.status is not None and client.status.state is ExecutionState.EXECUTING
                           and 0.05 < client.status.progress < 0.5 and client.joint_state is not None
                           and float(np.max(np.abs(client.joint_state.velocity))) > 0.01, timeout_s), client.status
    assert client.status is not None
    return client.status.trajectory_id


def assert_at_rest(client: RobonavClient, trajectory_id: str) -> None:
    assert client.status is not None and client.status.trajectory_id == trajectory_id
    assert client.status.state is ExecutionState.STOPPED, client.status
    time.sleep(0.2)  # the joint states of the next 20 samples, not one that happened to be slow
    assert client.joint_state is not None
    assert float(np.max(np.abs(client.joint_state.velocity))) <= REST_VELOCITY_RAD_S


def robonav(*args: str) -> list[str]:
    return [sys.executable, "-m", "robonav.services.cli", *args]


def test_ctrl_c_in_plan_execute_stops_the_arm_and_waits_for_rest(client: RobonavClient, stack_config: Path) -> None:
    goal = farthest_goal(client)
    proc = subprocess.Popen(robonav("plan", "--config", str(stack_config), "--goal", *map(str, goal), "--execute",
                                    "--velocity-scaling", str(SLOW)),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        trajectory_id = wait_moving(client)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == EXIT_INTERRUPTED, out + err
    record = json.loads(out)
    assert record["interrupted"] and record["trajectory_id"] == trajectory_id
    # The command only exited once the executor had stopped and the arm was still.
    assert record["stop"]["at_rest"] and record["stop"]["executor_state"] == "stopped", record
    assert record["stop"]["max_velocity_rad_s"] <= REST_VELOCITY_RAD_S
    assert record["result"] == "stopped"
    assert_at_rest(client, trajectory_id)
    assert float(np.max(np.abs(client.joint_state.position - goal))) > 0.05  # it stopped on the way


def test_robonav_stop_stops_a_moving_arm(client: RobonavClient, stack_config: Path) -> None:
    goal = farthest_goal(client)
    plan = client.plan(goal, allowed_planning_time=5.0, seed=3)
    assert isinstance(plan, PlanResponse), plan
    execution = client.execute(plan.path, joint_names=plan.joint_names, max_velocity_scaling_factor=SLOW,
                               max_acceleration_scaling_factor=SLOW)
    assert isinstance(execution, ExecuteResponse), execution
    wait_moving(client)
    done = subprocess.run(robonav("stop", "--config", str(stack_config)), capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    record = json.loads(done.stdout)
    assert record["at_rest"] and record["executor_state"] == "stopped" and not record["emergency"]
    assert_at_rest(client, execution.trajectory_id)
    # At rest already: a stop answers at once and exits 0 too.
    done = subprocess.run(robonav("stop", "--config", str(stack_config), "--emergency"), capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0 and json.loads(done.stdout)["emergency"], done.stdout + done.stderr


def test_robonav_stop_without_an_executor_says_nothing_answered(tmp_path: Path) -> None:
    from robonav.services.common import open_session
    from robonav.services.config import ZenohConfig

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = write_config(tmp_path, "alone.yaml", zenoh={"connect": [endpoint]})
    with open_session(ZenohConfig(mode="router", listen=(endpoint,))):
        done = subprocess.run(robonav("stop", "--config", str(config)), capture_output=True, text=True, timeout=60)
    assert done.returncode == 3 and "robonav/arm0/executor/stop: no reply" in done.stdout, done.stdout


def test_ctrl_c_in_the_example_client_stops_the_arm(client: RobonavClient, stack_config: Path) -> None:
    goal = farthest_goal(client)
    router = load_config(stack_config).zenoh.connect[0]
    proc = subprocess.Popen([sys.executable, str(REPO_ROOT / "examples" / "plan_client.py"), "--router", router,
                             "--goal", *map(str, goal), "--execute", "--velocity-scaling", str(SLOW)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=dict(os.environ))
    try:
        trajectory_id = wait_moving(client)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, out + err
    assert json.loads(out.splitlines()[-1]) == {"trajectory_id": trajectory_id, "result": "interrupted", "at_rest": True}
    assert_at_rest(client, trajectory_id)
