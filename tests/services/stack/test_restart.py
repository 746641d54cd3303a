"""Services come back: `Stack(restart=True)` (what `robonav up` runs) with the real router and
services; each test kills one process with SIGKILL and checks that it is restarted, counted, back
and serving, and that it came back in the state a client expects:

- the planner with the objects its clients added (the planning scene file of the stack);
- the executor idle (no trajectory, no setpoints), ready for the next execute;
- perception with a new map built from new frames, which the planner plans on;
- the sim publishing joint states again;
- the router: every service reconnects on its own and the stack plans and executes again.

`robonav status` reads it all from another process. How long each process was away is printed
(`pytest -s`); on a busy 2-core machine most of it is the new process importing and loading.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.wire.messages import (
    ErrorReply,
    ExecuteResponse,
    ExecutorStatus,
    PlanResponse,
    SceneObjectSpec,
    SceneRequest,
    SceneResponse,
)
from robonav.services.client import RobonavClient
from robonav.services.common import open_session
from robonav.services.config import load_config
from robonav.services.keys import SERVICES
from robonav.services.stack.status import collect_status
from robonav.services.stack.up import Stack

from ..conftest import free_port, plan_and_execute, write_config

pytestmark = pytest.mark.e2e

START_TIMEOUT_S = 120.0
BACK_TIMEOUT_S = 60.0
"""Generous for a loaded machine; the measured times are printed."""
DEFAULT = load_config()
GOALS = [np.array(g) for g in DEFAULT.demo.goals_rad]
HOME = np.array(DEFAULT.robot.home_position_rad)


class Running:
    def __init__(self, stack: Stack, client: RobonavClient, config: Path) -> None:
        self.stack, self.client, self.config = stack, client, config

    def process(self, name: str):  # noqa: ANN201
        return next(p for p in self.stack.status().services if p.name == name)

    def kill(self, name: str) -> tuple[int, int]:
        """SIGKILL `name`; returns (its pid, its restart count before)."""
        pid, restarts = self.stack.pid(name), self.process(name).restarts
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        return pid, restarts

    def wait_back(self, name: str, restarts_before: int) -> float:
        """Wait until `name` was restarted and serves again; returns how long it was away [s]."""
        deadline = time.monotonic() + BACK_TIMEOUT_S
        while time.monotonic() < deadline:
            p = self.process(name)
            if p.restarts > restarts_before and p.alive and p.last_back_s is not None:
                print(f"{name}: back and serving {p.last_back_s:.1f} s after SIGKILL")
                return p.last_back_s
            time.sleep(0.05)
        raise AssertionError(f"{name} not back within {BACK_TIMEOUT_S} s: {self.process(name)}")

    def fresh_map(self, timeout_s: float = 30.0) -> None:
        since = time.time()
        assert self.client.wait_for(lambda: self.client.occupancy is not None and self.client.occupancy.stamp > since,
                                    timeout_s), "no new occupancy map"


@pytest.fixture(scope="module")
def running(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    config = write_config(tmp_path_factory.mktemp("restart"), "restart.yaml",
                          zenoh={"connect": [f"tcp/127.0.0.1:{free_port()}"]}, sim={"follow": "kinematic"},
                          cameras={"width": 320, "height": 240},
                          planner={"occupancy_max_age_s": 60.0}, stack={"restart_backoff_initial_s": 0.2})
    cfg = load_config(config)
    stack = Stack(cfg, str(config), log_level="WARNING", restart=True)
    session = open_session(cfg.zenoh)
    client = RobonavClient(session, cfg.cell)
    try:
        assert not client.wait_for_services(SERVICES, START_TIMEOUT_S), stack.status()
        assert client.wait_for(lambda: client.occupancy is not None and client.joint_state is not None, START_TIMEOUT_S)
        yield Running(stack, client, config)
    finally:
        client.close()
        session.close()
        codes = stack.close()
    assert all(code == 0 for code in codes.values()), codes


def _plan_and_execute(client: RobonavClient, goal: np.ndarray) -> str:
    return plan_and_execute(client, goal, seed=1)


def test_status_lists_every_process_alive_from_another_process(running: Running) -> None:
    run = subprocess.run([sys.executable, "-m", "robonav.services.cli", "status", "--config", str(running.config),
                          "--json"], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stdout + run.stderr
    report = json.loads(run.stdout)
    assert report["ok"] and report["supervisor"]["restart"] is True
    assert [s["name"] for s in report["services"]] == ["router", *SERVICES]
    assert all(s["alive"] and s["state"] == "running" and s["pid"] for s in report["services"]), report
    assert report["map"] is not None and report["map"]["complete"], report["map"]
    assert report["map"]["camera_frames"] and report["map"]["age_s"] < 60.0, report["map"]
    assert report["executor"] is not None and report["executor"]["state"] == "idle", report["executor"]
    assert report["executor"]["error_code"] == "", report["executor"]
    started = time.monotonic()
    collect_status(running.client.session, "arm0", timeout_s=2.0)
    print(f"status report in {time.monotonic() - started:.2f} s (budget 2 s)")
    table = subprocess.run([sys.executable, "-m", "robonav.services.cli", "status", "--config", str(running.config)],
                           capture_output=True, text=True, timeout=60)
    assert table.returncode == 0 and "supervised by robonav up" in table.stdout, table.stdout + table.stderr
    assert "map: seq" in table.stdout and "executor: idle" in table.stdout, table.stdout


def test_a_killed_planner_comes_back_with_its_planning_scene(running: Running) -> None:
    client = running.client
    # A small box where the first demo goal puts the hand: planning there is GOAL_IN_COLLISION while it exists.
    hand_m = RobotModel.from_config(DEFAULT.robot).frame_pose(GOALS[0], "panda_hand")[:3, 3]
    box = SceneObjectSpec(name="fixture", type="box", position_m=tuple(hand_m), size_m=(0.05, 0.05, 0.05))
    try:
        added = client.scene(SceneRequest(operation="add", objects=(box,)))
        assert isinstance(added, SceneResponse), added
        refused = client.plan(GOALS[0], start_positions=HOME, allowed_planning_time=2.0, timeout_s=60.0)
        assert isinstance(refused, ErrorReply) and refused.code == "GOAL_IN_COLLISION", refused

        _, restarts = running.kill("planner")
        time.sleep(0.3)
        report = collect_status(client.session, "arm0", timeout_s=2.0)
        assert not report["ok"]  # the planner's token went with it
        running.wait_back("planner", restarts)

        listed = client.scene(SceneRequest(operation="list"))
        assert isinstance(listed, SceneResponse), listed
        assert [o.name for o in listed.objects] == ["fixture"] and listed.revision == added.revision
        again = client.plan(GOALS[0], start_positions=HOME, allowed_planning_time=2.0, timeout_s=60.0)
        assert isinstance(again, ErrorReply) and again.code == "GOAL_IN_COLLISION", again
        assert any("fixture" in pair for pair in again.details.get("pairs", [])), again.details
    finally:
        assert isinstance(client.scene(SceneRequest(operation="clear"), timeout_s=60.0), SceneResponse)


def test_a_killed_executor_comes_back_idle_and_executes_again(running: Running) -> None:
    client = running.client
    plan = client.plan(GOALS[1], allowed_planning_time=5.0, seed=2, timeout_s=60.0)
    assert isinstance(plan, PlanResponse), plan
    execution = client.execute(plan.path, joint_names=plan.joint_names, max_velocity_scaling_factor=0.2,
                               max_acceleration_scaling_factor=0.2)
    assert isinstance(execution, ExecuteResponse), execution
    assert client.wait_for(lambda: client.status is not None and client.status.state.value == "executing"
                           and client.status.progress > 0.05, 20.0)
    _, restarts = running.kill("executor")
    killed_at = time.time()

    statuses: list[ExecutorStatus] = []
    setpoints: list[float] = []
    keys = client.keys

    def on_status(sample: zenoh.Sample) -> None:
        # A status the killed process sent just before SIGKILL can still be on its way on a loaded
        # host: only what the new process says counts.
        status = ExecutorStatus.from_wire(sample.payload.to_bytes())
        if status.stamp > killed_at:
            statuses.append(status)

    subs = [client.session.declare_subscriber(keys.status, on_status),
            client.session.declare_subscriber(keys.setpoint, lambda s: setpoints.append(time.monotonic()))]
    try:
        running.wait_back("executor", restarts)
        deadline = time.monotonic() + 10.0
        while not statuses and time.monotonic() < deadline:
            time.sleep(0.05)
        assert statuses, "the restarted executor publishes no status"
        first = statuses[0]
        assert (first.state.value, first.trajectory_id, first.last_result.value) == ("idle", "", "none"), first
        quiet_from = time.monotonic()
        time.sleep(1.0)
        assert not [t for t in setpoints if t > quiet_from], "an idle executor streams setpoints"
    finally:
        for sub in subs:
            sub.undeclare()
    state = client.joint_state
    assert state is not None and np.max(np.abs(state.velocity)) < 0.05, "the arm is not at rest"
    assert _plan_and_execute(client, GOALS[0]) == "succeeded"


def test_a_killed_perception_comes_back_with_a_map_from_new_frames(running: Running) -> None:
    client = running.client
    running.fresh_map()
    _, restarts = running.kill("perception")
    killed_at = time.time()
    running.wait_back("perception", restarts)
    # The new process counts its maps from 1 and builds them from frames taken after it started.
    assert client.wait_for(lambda: client.occupancy is not None and client.occupancy.stamp > killed_at
                           and len(client.occupancy.occupied_centers_m) > 0, 30.0)
    assert client.occupancy is not None and client.occupancy.seq < 1000
    deadline = time.monotonic() + 20.0
    while True:  # the planner gets that map a moment after this client did
        plan = client.plan(GOALS[2], allowed_planning_time=5.0, seed=3, timeout_s=60.0)
        assert isinstance(plan, PlanResponse), plan
        if plan.occupancy_stamp > killed_at or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert plan.occupancy_stamp > killed_at


def test_a_killed_sim_comes_back_publishing_joint_states(running: Running) -> None:
    client = running.client
    _, restarts = running.kill("sim")
    killed_at = time.time()
    running.wait_back("sim", restarts)
    assert client.wait_for(lambda: client.joint_state is not None and client.joint_state.stamp > killed_at, 10.0)
    running.fresh_map()
    # A new sim starts the arm at home, wherever the last motion left it: the next motion starts there.
    assert _plan_and_execute(client, GOALS[1]) == "succeeded"


def test_a_killed_router_comes_back_and_every_service_reconnects(running: Running) -> None:
    client = running.client
    service_restarts = {p.name: p.restarts for p in running.stack.status().services if p.name in SERVICES}
    _, restarts = running.kill("router")
    killed = time.monotonic()
    # The supervisor's own session lost the router too: it sees every token go (and come back).
    deadline = time.monotonic() + 10.0
    while any(p.alive for p in running.stack.status().services if p.name in SERVICES) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not any(p.alive for p in running.stack.status().services if p.name in SERVICES), running.stack.status()
    router_back_s = running.wait_back("router", restarts)
    # Every service's token again (declared anew over the new router), then a whole motion.
    missing = set(SERVICES)
    while missing and time.monotonic() - killed < BACK_TIMEOUT_S:
        missing -= {p.name for p in running.stack.status().services if p.alive}
        time.sleep(0.05)
    assert not missing, running.stack.status()
    all_back_s = time.monotonic() - killed
    running.fresh_map()
    done = threading.Event()
    result: list[str] = []
    threading.Thread(target=lambda: (result.append(_plan_and_execute(client, HOME)), done.set()), daemon=True).start()
    assert done.wait(90.0) and result == ["succeeded"], result
    print(f"router back {router_back_s:.1f} s after SIGKILL; every service alive again after {all_back_s:.1f} s; "
          f"a new map and a motion after {time.monotonic() - killed:.1f} s")
    assert running.process("router").restarts == restarts + 1
    # The services rode it out: reconnected, not restarted.
    assert {p.name: p.restarts for p in running.stack.status().services if p.name in SERVICES} == service_restarts
