"""Perception keeps mapping after odd but well-formed input: joint states and frames stamped in
the future or long ago, joint states lacking joints, a camera (and robot) whose clock jumps back.

The perception service in process over real Zenoh on loopback; this test plays the robot and
the camera. Each odd input is dropped and counted (`perception/status`), and the next normal
frame is integrated. Before these rules, one joint state stamped in the future made every
later joint state "out of order", and every cloud after it was dropped for want of a pose.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh

from robonav.pipeline.wire.messages import (
    JointState,
    Occupancy,
    PerceptionClearRequest,
    PerceptionClearResponse,
    PerceptionStatusRequest,
    PerceptionStatusResponse,
    PointCloud,
)
from robonav.services.client import query_one
from robonav.services.common import declare_latched_subscriber, open_session
from robonav.services.config import ZenohConfig, load_config
from robonav.services.keys import Keys
from robonav.services.perception.node import PerceptionNode
from robonav.services.perception.stamps import STAMP_RESTART_SAMPLES

from ..conftest import free_port

CONFIG = load_config()
NAMES = tuple(CONFIG.robot.joint_names)
HOME = np.array(CONFIG.robot.home_position_rad)
KEYS = Keys(CONFIG.cell)
HOUR_S = 3600.0
FIRST_FRAME_TIMEOUT_S = 60.0
"""The first frame may compile the map kernels."""


def _patch_cloud(stamp: float) -> PointCloud:
    """A 10 cm square of points facing the camera 1.25 m along its axis (above the table, away from the arm)."""
    u, v = np.meshgrid(np.linspace(-0.05, 0.05, 21), np.linspace(-0.05, 0.05, 21))
    points = np.column_stack([u.ravel(), v.ravel(), np.full(u.size, 1.25)]).astype(np.float32)
    return PointCloud(stamp=stamp, camera_id=CONFIG.cameras[0].camera_id, points=points)


class Feeder:
    """Plays the robot and the camera; reads perception/status."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.maps: list[Occupancy] = []
        self._sub = declare_latched_subscriber(session, KEYS.occupancy,
                                               lambda s: self.maps.append(Occupancy.from_wire(s.payload.to_bytes())))

    def status(self) -> PerceptionStatusResponse:
        reply, _ = query_one(self.session, KEYS.perception_status, PerceptionStatusRequest(), PerceptionStatusResponse, 10.0)
        assert isinstance(reply, PerceptionStatusResponse), reply
        return reply

    def joint_state(self, stamp: float, names: tuple[str, ...] = NAMES, position: np.ndarray = HOME) -> None:
        self.session.put(KEYS.joint_states, JointState(stamp=stamp, names=names, position=position,
                                                       velocity=np.zeros(len(names))).to_wire())

    def joint_states_around(self, stamp: float) -> None:
        """Joint states up to `stamp`, as a 100 Hz driver would have sent them."""
        for k in range(4, -1, -1):
            self.joint_state(stamp - 0.01 * k)
        time.sleep(0.05)

    def frame(self, stamp: float, timeout_s: float = 10.0) -> str:
        """Send one frame and wait for its fate: 'integrated' or the drop reason it was counted under."""
        before = self.status()
        self.session.put(KEYS.camera_cloud(CONFIG.cameras[0].camera_id), _patch_cloud(stamp).to_wire())
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            now = self.status()
            if now.frames > before.frames:
                return "integrated"
            grew = [r for r, n in now.dropped.items() if n > before.dropped.get(r, 0) and not r.startswith("joint_state_")]
            if grew:
                return grew[0]
            time.sleep(0.05)
        raise AssertionError(f"perception did nothing with a frame stamped {stamp} in {timeout_s} s")

    def map_stamped(self, stamp: float, timeout_s: float = 10.0) -> Occupancy:
        """The map built from the frame stamped `stamp` (it is published after the frame counts)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.maps and self.maps[-1].stamp == pytest.approx(stamp, abs=1e-6):
                return self.maps[-1]
            time.sleep(0.02)
        raise AssertionError(f"no map stamped {stamp} in {timeout_s} s; the last: {[m.stamp for m in self.maps[-3:]]}")

    def normal_frame(self) -> str:
        now = time.time()
        self.joint_states_around(now)
        return self.frame(now)

    def close(self) -> None:
        self._sub.undeclare()


@pytest.fixture
def feeder() -> Iterator[Feeder]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    cfg = dataclasses.replace(CONFIG, zenoh=ZenohConfig(connect=(endpoint,)))
    node_session = open_session(cfg.zenoh)
    node = PerceptionNode(cfg, node_session)
    stop = threading.Event()
    spinner = threading.Thread(target=node.spin, args=(stop,), daemon=True)
    spinner.start()
    session = open_session(cfg.zenoh)
    feeder = Feeder(session)
    now = time.time()
    feeder.joint_states_around(now)
    assert feeder.frame(now, timeout_s=FIRST_FRAME_TIMEOUT_S) == "integrated"
    yield feeder
    feeder.close()
    stop.set()
    spinner.join(timeout=10.0)
    node.close()
    for s in (session, node_session, router):
        s.close()


def _dropped(feeder: Feeder, reason: str) -> int:
    return feeder.status().dropped.get(reason, 0)


def test_a_joint_state_from_the_future_is_dropped_and_mapping_goes_on(feeder: Feeder) -> None:
    for ahead_s in (1e6, 30.0):
        feeder.joint_state(time.time() + ahead_s)
    time.sleep(0.2)
    assert _dropped(feeder, "joint_state_future_stamp") == 2
    assert feeder.normal_frame() == "integrated"
    assert feeder.normal_frame() == "integrated"


def test_joint_states_lacking_joints_are_dropped_and_the_last_complete_one_still_poses_the_arm(feeder: Feeder) -> None:
    feeder.joint_state(time.time(), names=NAMES[:-1], position=HOME[:-1])
    feeder.joint_state(time.time(), names=tuple(f"other_{n}" for n in NAMES), position=HOME)
    time.sleep(0.2)
    assert _dropped(feeder, "joint_state_incomplete") == 2
    # Extra joints (fingers) are fine: the planning joints are all there.
    now = time.time()
    for k in range(5):
        feeder.joint_state(now - 0.01 * k, names=(*NAMES, "panda_finger_joint1"), position=np.append(HOME, 0.04))
    time.sleep(0.05)
    assert feeder.frame(now) == "integrated"


def test_a_frame_and_pose_from_the_future_are_dropped_and_the_camera_is_not_wedged(feeder: Feeder) -> None:
    later = time.time() + HOUR_S
    feeder.joint_states_around(later)
    assert feeder.frame(later) == "future_stamp"
    assert _dropped(feeder, "joint_state_future_stamp") >= 5
    assert feeder.normal_frame() == "integrated"


def test_a_camera_and_robot_whose_clocks_jump_back_are_taken_as_restarted(feeder: Feeder) -> None:
    # Both clocks go back an hour (a driver restarted with a wrong clock, a replay looping).
    start = time.time() - HOUR_S
    for k in range(20):
        feeder.joint_state(start + 0.01 * k)
    time.sleep(0.1)
    assert _dropped(feeder, "joint_state_jumped_back") == STAMP_RESTART_SAMPLES - 1  # then the history started over
    fates = []
    for k in range(STAMP_RESTART_SAMPLES):
        stamp = start + 0.2 + 0.1 * k
        feeder.joint_states_around(stamp)
        fates.append(feeder.frame(stamp))
    assert fates == ["jumped_back"] * (STAMP_RESTART_SAMPLES - 1) + ["integrated"]
    feeder.map_stamped(start + 0.2 + 0.1 * (STAMP_RESTART_SAMPLES - 1))
    # A single step back within the tolerance is still out of order, not a restart.
    feeder.joint_states_around(start + 0.3)
    assert feeder.frame(start + 0.3) == "out_of_order"
    # And back to the present: a jump forward is just newer.
    assert feeder.normal_frame() == "integrated"


def test_a_stray_stamp_from_long_ago_does_not_reset_the_joint_history(feeder: Feeder) -> None:
    now = time.time()
    for k in range(10):  # strays interleaved with a good 100 Hz stream never count as a restart
        feeder.joint_state(now - 0.1 + 0.01 * k)
        feeder.joint_state(1.0 + k)
    time.sleep(0.2)
    assert _dropped(feeder, "joint_state_jumped_back") == 10
    assert feeder.frame(now - 0.03) == "integrated"


def test_a_clear_applies_in_the_clock_of_a_camera_that_runs_an_hour_behind(feeder: Feeder) -> None:
    offset_s = HOUR_S
    fates = []
    for k in range(STAMP_RESTART_SAMPLES):  # the camera and robot restart an hour behind
        stamp = time.time() - offset_s
        feeder.joint_states_around(stamp)
        fates.append(feeder.frame(stamp))
    assert fates[-1] == "integrated", fates
    reply, _ = query_one(feeder.session, KEYS.perception_clear, PerceptionClearRequest(), PerceptionClearResponse, 10.0)
    assert isinstance(reply, PerceptionClearResponse) and reply.cleared_voxels > 0
    # A frame taken before the clear, in the camera's own clock, is still dropped...
    stale = time.time() - offset_s - 0.5
    feeder.joint_states_around(stale)
    assert feeder.frame(stale) == "before_clear"
    # ...and one taken after it is mapped: every stamp is an hour before our clear, yet not "before" it.
    fresh = time.time() - offset_s
    feeder.joint_states_around(fresh)
    assert feeder.frame(fresh) == "integrated"
    assert feeder.status().occupied_voxels > 0
