"""Service fixtures: real Zenoh on 127.0.0.1 (multicast scouting off), real service processes."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
import zenoh

from robonav.pipeline.wire.messages import ExecuteResponse, PlanResponse
from robonav.services.client import RobonavClient
from robonav.services.common import open_session
from robonav.services.config import ZenohConfig, default_config_path, load_config
from robonav.services.keys import SERVICES

STACK_START_TIMEOUT_S = 90.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def write_config(directory: Path, name: str, **sections: dict) -> Path:
    """The packaged default with some sections' keys replaced, written as a YAML file."""
    data = yaml.safe_load(default_config_path().read_text(encoding="utf-8"))
    for section, values in sections.items():
        if isinstance(data.get(section), list):  # e.g. cameras: the same keys for every item
            data[section] = [{**item, **values} for item in data[section]]
        else:
            data.setdefault(section, {}).update(values)
    path = directory / name
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    load_config(path)  # fail here, not in a service, if the test wrote a bad config
    return path


# A cylindrical robot for the `--robot FILE` tests: a column turning without end (continuous), a carriage sliding up it and
# a boom sliding out of the carriage (prismatic). Primitives only, so pybullet and the planner
# load it without meshes.
TURN_LIFT_REACH_URDF = """<?xml version="1.0"?>
<robot name="turn_lift_reach">
  <link name="foot"><collision><origin xyz="0 0 0.05"/><geometry><box size="0.2 0.2 0.1"/></geometry></collision>
    <inertial><mass value="5"/><inertia ixx="0.02" iyy="0.02" izz="0.02" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="column"><collision><origin xyz="0 0 0.4"/><geometry><cylinder radius="0.04" length="0.8"/></geometry></collision>
    <inertial><mass value="2"/><inertia ixx="0.06" iyy="0.06" izz="0.002" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="carriage"><collision><geometry><box size="0.12 0.12 0.08"/></geometry></collision>
    <inertial><mass value="1"/><inertia ixx="0.002" iyy="0.002" izz="0.002" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="boom"><collision><origin xyz="-0.2 0 0"/><geometry><box size="0.4 0.04 0.04"/></geometry></collision>
    <inertial><mass value="0.5"/><inertia ixx="0.0001" iyy="0.007" izz="0.007" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="tool"><collision><geometry><sphere radius="0.03"/></geometry></collision>
    <inertial><mass value="0.1"/><inertia ixx="0.0001" iyy="0.0001" izz="0.0001" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="turn" type="continuous"><parent link="foot"/><child link="column"/><origin xyz="0 0 0.1"/>
    <axis xyz="0 0 1"/><limit effort="50" velocity="1.5"/></joint>
  <joint name="lift" type="prismatic"><parent link="column"/><child link="carriage"/><origin xyz="0 0 0.15"/>
    <axis xyz="0 0 1"/><limit lower="0.0" upper="0.6" effort="100" velocity="0.5"/></joint>
  <joint name="reach" type="prismatic"><parent link="carriage"/><child link="boom"/><origin xyz="0 0 0"/>
    <axis xyz="1 0 0"/><limit lower="0.15" upper="0.45" effort="50" velocity="0.5"/></joint>
  <joint name="tool_joint" type="fixed"><parent link="boom"/><child link="tool"/><origin xyz="0.03 0 0"/></joint>
</robot>
"""

TURN_LIFT_REACH_ROBOT_FILE = """name: turn_lift_reach
urdf: robot.urdf
base_link: foot
end_effector_link: tool
joint_names: [turn, lift, reach]
max_velocity_rad_s: [1.5, 0.5, 0.5]
max_acceleration_rad_s2: [6.0, 2.0, 2.0]
max_jerk_rad_s3: [3000.0, 1000.0, 1000.0]
home_position_rad: [0.0, 0.2, 0.15]
padding_m: 0.01
allowed_collision_pairs:
  - [foot, column]
  - [column, carriage]
  - [carriage, boom]
  - [column, boom]   # the boom slides through a slot in the column
  - [boom, tool]
"""


def write_turn_lift_reach(directory: Path) -> Path:
    """Write the cylindrical test robot's URDF and robot file into `directory`; the robot file's path."""
    (directory / "robot.urdf").write_text(TURN_LIFT_REACH_URDF, encoding="utf-8")
    path = directory / "turn_lift_reach.yaml"
    path.write_text(TURN_LIFT_REACH_ROBOT_FILE, encoding="utf-8")
    return path


def wait_for(condition: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    """Poll `condition` until it holds (True) or `timeout_s` passed (its last value)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


def wait_until_served(session: zenoh.Session, key: str, timeout_s: float = 10.0) -> None:
    """Wait until `session` sees a queryable on `key`: a query sent right after another session
    declared one may reach the router before the declaration does, and get no reply at all."""
    querier = session.declare_querier(key)
    try:
        assert wait_for(lambda: querier.matching_status.matching, timeout_s), f"no queryable on {key} after {timeout_s} s"
    finally:
        querier.undeclare()


class StandInPeer:
    """A bare queryable on `key` standing in for a service: `answer(query)` runs for each query,
    which is kept (a silent or slow peer holds its queries) and dropped by `close`, never while
    its callback still runs (the callback holds it: dropping it then raises "Already borrowed").
    With `observer`, waits until that session sees the queryable. `close` does not wait until it
    no longer does: a querier's matching status has been seen to keep an undeclared queryable
    for over 10 s, so each test serves one stand-in per key and bus."""

    def __init__(self, session: zenoh.Session, key: str, answer: Callable[[zenoh.Query], object], *,
                 observer: zenoh.Session | None = None) -> None:
        self.queries: list[zenoh.Query] = []
        self._lock = threading.Lock()

        def callback(query: zenoh.Query) -> None:
            with self._lock:
                self.queries.append(query)
                answer(query)

        self._queryable = session.declare_queryable(key, callback, complete=True)
        if observer is not None:
            wait_until_served(observer, key)

    def close(self) -> None:
        with self._lock:
            for query in self.queries:
                query.drop()
            self._queryable.undeclare()


@pytest.fixture
def bus() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """A router on a free port and two client sessions through it: (service side, client side)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    service = open_session(ZenohConfig(connect=(endpoint,)))
    client = open_session(ZenohConfig(connect=(endpoint,)))
    yield service, client
    for s in (client, service, router):
        s.close()


@pytest.fixture(scope="session")
def stack_config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # Kinematic following makes the arm track setpoints exactly, so results do not depend on
    # how busy the machine is; the demo uses the dynamic model.
    return write_config(tmp_path_factory.mktemp("stack"), "stack.yaml",
                        zenoh={"connect": [f"tcp/127.0.0.1:{free_port()}"]}, sim={"follow": "kinematic"},
                        # A quarter of the pixels: the sim renders in its physics loop, and a
                        # 640x480 render on a loaded 2-core machine stalls joint states long
                        # enough to trip the executor's watchdog.
                        cameras={"width": 320, "height": 240})


@pytest.fixture(scope="session")
def stack(stack_config: Path) -> Iterator[subprocess.Popen[bytes]]:
    """`robonav up` as a process; torn down with SIGTERM, which must end it with exit code 0."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "robonav.services.cli", "up", "--config", str(stack_config),
                             "--log-level", "WARNING"], env=env)
    yield proc
    proc.send_signal(signal.SIGTERM)
    code = proc.wait(timeout=30)
    assert code == 0, f"robonav up exited with {code} after SIGTERM"


@pytest.fixture(scope="session")
def session(stack: subprocess.Popen[bytes], stack_config: Path) -> Iterator[zenoh.Session]:
    cfg = load_config(stack_config)
    deadline = time.monotonic() + 20.0
    while True:  # the router may need a moment to listen
        try:
            s = open_session(ZenohConfig(mode="client", connect=cfg.zenoh.connect))
            break
        except zenoh.ZError:
            if time.monotonic() > deadline or stack.poll() is not None:
                raise
            time.sleep(0.2)
    yield s
    s.close()


@pytest.fixture(scope="session")
def client(session: zenoh.Session, stack: subprocess.Popen[bytes]) -> Iterator[RobonavClient]:
    c = RobonavClient(session, "arm0")
    missing = c.wait_for_services(SERVICES, STACK_START_TIMEOUT_S)
    assert not missing, f"services not alive: {missing}"
    # A map published after every service was up, so the planner has one too.
    alive_at = time.time()
    assert c.wait_for(lambda: c.occupancy is not None and c.occupancy.stamp > alive_at and c.joint_state is not None,
                      STACK_START_TIMEOUT_S), "no occupancy map or joint state"
    yield c
    c.close()


LOAD_FAULTS = ("JOINT_STATE_STALE", "TRACKING_ERROR")
"""What the executor's watchdog rightly trips when a loaded host starves the sim or the executor of CPU."""


def plan_and_execute(client: RobonavClient, goal: np.ndarray, *, seed: int) -> str:
    """Plan from the measured state and execute; the outcome, with the executor's error when it is not 'succeeded'.

    A watchdog trip of `LOAD_FAULTS` gets one more try from where the arm stopped: the tests that use this move the
    arm to set a scene up or to check that a stack serves, and the watchdog doing its job on a starved host is
    tested elsewhere (tests/pipeline/trajectory/test_execution.py, tests/services/executor/test_node.py).
    """
    for attempt in range(2):
        plan = client.plan(goal, allowed_planning_time=5.0, seed=seed, timeout_s=60.0)
        assert isinstance(plan, PlanResponse), plan
        execution = client.execute(plan.path, joint_names=plan.joint_names, max_velocity_scaling_factor=1.0,
                                   max_acceleration_scaling_factor=1.0)
        assert isinstance(execution, ExecuteResponse), execution
        outcome = client.wait_for_trajectory(execution.trajectory_id, execution.duration_s + 20.0)
        status = client.status
        if outcome == "succeeded" or status is None:
            return outcome
        print(f"execution {attempt + 1}: {outcome} {status.error_code}: {status.error_message}")
        if status.error_code not in LOAD_FAULTS or attempt == 1:
            return f"{outcome} {status.error_code}: {status.error_message}"
        assert client.wait_for(lambda: client.joint_state is not None
                               and float(np.max(np.abs(client.joint_state.velocity))) < 0.05, 10.0)
    raise AssertionError("unreachable")
