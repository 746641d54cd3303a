"""The sim as a driver, with real processes: setpoints beyond the arm's limits injected on the bus
are not followed, and when a real executor is killed mid-motion (its whole process group, setpoint
stream included) the arm brakes to rest on its own within a second."""

from __future__ import annotations

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
from robonav.pipeline.wire.messages import ExecuteResponse, JointState, Setpoint, SimStatsRequest, SimStatsResponse
from robonav.services.client import RobonavClient
from robonav.services.common import open_session
from robonav.services.config import RobonavConfig, ZenohConfig, load_config
from robonav.services.stack.up import Stack

from ..conftest import free_port, write_config

AT_REST_RAD_S = 0.01
"""Every joint slower than this: at rest."""


class JointLog:
    """Every joint state with its arrival time (time.monotonic())."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.lock = threading.Lock()
        self.states: list[tuple[float, JointState]] = []
        self._sub = session.declare_subscriber(key, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        state = JointState.from_wire(sample.payload.to_bytes())
        with self.lock:
            self.states.append((time.monotonic(), state))

    def since(self, t_s: float) -> list[tuple[float, JointState]]:
        with self.lock:
            return [(t, s) for t, s in self.states if t >= t_s]

    def close(self) -> None:
        self._sub.undeclare()


@pytest.fixture(scope="module")
def driver_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[RobonavClient, JointLog, RobonavConfig, Path]]:
    """The sim alone (dynamic following, as in the demo), with a router; tests start executors themselves."""
    directory = tmp_path_factory.mktemp("driver")
    path = write_config(directory, "driver.yaml", zenoh={"connect": [f"tcp/127.0.0.1:{free_port()}"]},
                        sim={"follow": "dynamic"}, cameras={"width": 160, "height": 120},
                        # No planner and no perception here: executes are checked against the robot alone.
                        executor={"require_scene": False}, planner={"require_occupancy": False})
    cfg = load_config(path)
    stack = Stack(cfg, str(path), services=("sim",), log_level="WARNING")
    try:
        session = open_session(ZenohConfig(mode="client", connect=cfg.zenoh.connect))
        client = RobonavClient(session, cfg.cell)
        joints = JointLog(session, client.keys.joint_states)
        assert not client.wait_for_services(["sim"], 60.0)
        assert client.wait_for(lambda: client.joint_state is not None, 30.0)
        yield client, joints, cfg, path
        joints.close()
        client.close()
        session.close()
    finally:
        codes = stack.close()
    assert codes == {"sim": 0, "router": 0}


def _stats(client: RobonavClient) -> SimStatsResponse:
    stats = client.query(client.keys.sim_stats, SimStatsRequest(), SimStatsResponse, 10.0)
    assert isinstance(stats, SimStatsResponse), stats
    return stats


def _wait_rejected(client: RobonavClient, count: int, timeout_s: float = 5.0) -> int:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        total = sum(_stats(client).setpoints_rejected.values())
        if total >= count:
            return total
        time.sleep(0.02)
    raise AssertionError(f"the sim judged fewer than {count} setpoints in {timeout_s} s")


def _wait_at_rest(client: RobonavClient, joints: JointLog, timeout_s: float = 10.0) -> np.ndarray:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        recent = joints.since(time.monotonic() - 0.3)
        if len(recent) > 10 and all(np.abs(s.velocity).max() < AT_REST_RAD_S for _, s in recent):
            return recent[-1][1].position.copy()
        time.sleep(0.05)
    raise AssertionError("the arm never came to rest")


def test_setpoints_beyond_the_arms_limits_are_not_followed(driver_stack: tuple[RobonavClient, JointLog, RobonavConfig, Path]) -> None:
    client, joints, cfg, _ = driver_stack
    q0 = _wait_at_rest(client, joints)
    names = cfg.robot.joint_names
    zero = np.zeros(7)
    upper = RobotModel.from_config(cfg.robot).upper_limits_rad

    def setpoint(q: np.ndarray, qd: np.ndarray = zero, qdd: np.ndarray = zero, joint_names: tuple[str, ...] = names) -> bytes:
        return Setpoint(stamp=time.time(), trajectory_id="forged", names=joint_names, position=q, velocity=qd,
                        acceleration=qdd).to_wire()

    one = np.eye(7)
    bad = {
        "jump": [setpoint(q0 + 0.5 * one[0]), setpoint(q0 - 0.1 * one[5])],
        "joint_limits": [setpoint(np.where(np.arange(7) == 3, upper[3] + 0.2, q0))],
        "velocity": [setpoint(q0, qd=5.0 * one[0])],
        "acceleration": [setpoint(q0, qdd=80.0 * one[1])],
        "bad_message": [setpoint(q0, joint_names=tuple(reversed(names))[:6] + ("elbow",)), b"\x00garbage"],
    }
    before = _stats(client)
    started = time.monotonic()
    seen = sum(before.setpoints_rejected.values())
    for payloads in bad.values():
        for payload in payloads:
            client.session.put(client.keys.setpoint, payload)
            # The sim takes the newest setpoint per physics step: wait for this one to be judged
            # before the next, so a slow step on a loaded machine does not merge two.
            seen = _wait_rejected(client, seen + 1)
    after = _stats(client)
    assert after.setpoints_followed == before.setpoints_followed, "a setpoint beyond the limits was followed"
    for reason, payloads in bad.items():
        grew = after.setpoints_rejected[reason] - before.setpoints_rejected[reason]
        assert grew == len(payloads), (reason, before.setpoints_rejected, after.setpoints_rejected)
    assert after.driver_state == "holding" and after.last_rejection
    moved = max(np.abs(s.position - q0).max() for _, s in joints.since(started))
    assert moved < 2e-3, f"the arm moved {moved:.4f} rad"


def test_the_arm_is_at_rest_within_a_second_after_the_executor_is_killed(
        driver_stack: tuple[RobonavClient, JointLog, RobonavConfig, Path]) -> None:
    client, joints, cfg, path = driver_stack
    # Its own session, so SIGKILL takes the executor and its setpoint stream (a child) and nothing else.
    executor = subprocess.Popen([sys.executable, "-m", "robonav.services.cli", "serve", "executor", "--config", str(path),
                                 "--log-level", "WARNING"], start_new_session=True)
    try:
        assert not client.wait_for_services(["executor"], 90.0), "the executor did not start"
        q0 = _wait_at_rest(client, joints)
        goal = q0 + np.array([2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        before = _stats(client)
        reply = client.execute(np.vstack([q0, goal]), trajectory_id="doomed")
        assert isinstance(reply, ExecuteResponse), reply
        assert client.wait_for(lambda: client.joint_state is not None and np.abs(client.joint_state.velocity).max() > 0.5,
                               10.0), "the arm never got going"
        os.killpg(executor.pid, signal.SIGKILL)
        killed_at = time.monotonic()
        executor.wait(timeout=10.0)
        time.sleep(1.5)
        after_kill = joints.since(killed_at)
        moving = [t for t, s in after_kill if np.abs(s.velocity).max() >= AT_REST_RAD_S]
        at_rest_s = (moving[-1] - killed_at) if moving else 0.0
        assert at_rest_s <= 1.0, f"the arm was still moving {at_rest_s:.2f} s after the executor died"
        assert np.abs(after_kill[-1][1].position - goal).max() > 0.3, "the arm went on to the goal"
        after = _stats(client)
        assert after.setpoint_timeouts == before.setpoint_timeouts + 1 and after.driver_state == "holding", after
        print(f"arm at rest {at_rest_s:.3f} s after SIGKILL of the executor's process group")
    finally:
        if executor.poll() is None:
            os.killpg(executor.pid, signal.SIGKILL)
            executor.wait()
