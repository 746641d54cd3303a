"""Replaying a recording into the perception core twice gives identical occupancy maps.

Clouds of a box on a table (seen by the default camera, with seeded noise) and joint states
are recorded over real Zenoh, replayed twice as fast as possible into a subscriber, and each
replay is run through the pure perception core (`process_cloud_with_clearing` with the
robot's self filter, then `OccupancyMap`), as the perception service does per cloud.
"""

from __future__ import annotations

import bisect
import importlib.util
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from robonav.pipeline.perception.maps.octree import OccupancyMap
from robonav.pipeline.perception.maps.protocol import CameraFrame
from robonav.pipeline.perception.self_filter import SelfFilter
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import transform_points
from robonav.pipeline.wire.messages import JointState, PointCloud
from robonav.services.common import open_session
from robonav.services.config import ZenohConfig, load_config
from robonav.services.recording.files import Recording
from robonav.services.recording.record import Recorder
from robonav.services.recording.replay import Replayer, ReplayOptions

CONFIG = load_config()
CAMERA = CONFIG.cameras[0]
CLOUD_KEY = f"robonav/pr/camera/{CAMERA.camera_id}/cloud"
JOINT_KEY = "robonav/pr/robot/joint_states"


def _free_port() -> int:
    spec = importlib.util.spec_from_file_location("services_conftest", Path(__file__).resolve().parents[1] / "conftest.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return int(module.free_port())


@pytest.fixture
def new_session() -> Iterator:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    opened: list[zenoh.Session] = []

    def make() -> zenoh.Session:
        opened.append(open_session(ZenohConfig(mode="client", connect=(endpoint,))))
        return opened[-1]

    yield make
    for s in opened:
        s.close()
    router.close()


def _traffic(frames: int = 6) -> list[tuple[str, bytes]]:
    rng = np.random.default_rng(7)
    camera_from_world = np.linalg.inv(CAMERA.world_from_camera)
    q_home = np.array(CONFIG.robot.home_position_rad)
    out: list[tuple[str, bytes]] = []
    for i in range(frames):
        stamp = 2000.0 + i * 0.2
        table = np.column_stack([rng.uniform(0.2, 0.9, 6000), rng.uniform(-0.5, 0.5, 6000), np.full(6000, 0.3)])
        box_x = 0.55 + 0.02 * i  # the box moves: later frames must clear where it was
        box = np.column_stack([rng.uniform(box_x, box_x + 0.1, 2000), rng.uniform(0.1, 0.2, 2000),
                               rng.uniform(0.3, 0.45, 2000)])
        points = transform_points(camera_from_world, np.vstack([table, box]))
        points += rng.normal(0.0, 0.002, points.shape)
        out.append((JOINT_KEY, JointState(stamp=stamp, names=CONFIG.robot.joint_names, position=q_home,
                                          velocity=np.zeros(q_home.size)).to_wire()))
        out.append((CLOUD_KEY, PointCloud(stamp=stamp, camera_id=CAMERA.camera_id,
                                          points=points.astype(np.float32), seq=i + 1).to_wire()))
    return out


def _occupancy(messages: list[tuple[str, bytes]], robot: RobotModel) -> bytes:
    """What perception does with each cloud, on the pure core; returns the map's planning octree."""
    self_filter = SelfFilter(robot.link_hull_vertices, CONFIG.perception.self_filter_padding_m)
    occupancy = OccupancyMap(CONFIG.perception)
    stamps: list[float] = []
    positions: list[np.ndarray] = []
    world_from_camera = CAMERA.world_from_camera
    for key, payload in messages:
        if key == JOINT_KEY:
            state = JointState.from_wire(payload)
            stamps.append(state.stamp)
            positions.append(state.position)
            continue
        cloud = PointCloud.from_wire(payload)
        nearest = min(max(bisect.bisect_left(stamps, cloud.stamp), 0), len(stamps) - 1)
        world_from_link = robot.link_poses(positions[nearest])
        occupancy.integrate(CameraFrame(CAMERA.intrinsics, world_from_camera, world_from_link, points_camera_m=cloud.points),
                            self_filter=self_filter, clear_filter=self_filter)
    return occupancy.planning_binary()


def _wait_for(condition, timeout_s: float = 10.0) -> bool:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not condition():
        time.sleep(0.01)
    return condition()


def test_two_replays_build_identical_maps(new_session, tmp_path: Path) -> None:  # noqa: ANN001
    sent = _traffic()
    path = tmp_path / "clouds.mcap"
    recorder = Recorder(new_session(), path, ["robonav/pr/**"])
    publisher_session = new_session()
    publishers = {k: publisher_session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
                  for k in (JOINT_KEY, CLOUD_KEY)}
    assert _wait_for(lambda: all(p.matching_status.matching for p in publishers.values()))
    for key, payload in sent:
        publishers[key].put(payload)
    assert _wait_for(lambda: sum(recorder.stats.received.values()) == len(sent))
    assert recorder.close()["dropped"] == 0

    replays = []
    for _ in range(2):
        received: list[tuple[str, bytes]] = []
        lock = threading.Lock()

        def on_sample(sample: zenoh.Sample, received=received, lock=lock) -> None:  # noqa: ANN001
            with lock:
                received.append((str(sample.key_expr), sample.payload.to_bytes()))

        sub = new_session().declare_subscriber("robonav/pr/**", on_sample)
        replayer = Replayer(new_session(), Recording(path), ReplayOptions(rate=None, robot_keys=True))
        assert replayer.wait_for_subscribers(10.0)
        replayer.run(threading.Event())
        assert _wait_for(lambda received=received: len(received) == len(sent))
        replayer.close()
        sub.undeclare()
        replays.append(received)

    robot = RobotModel.from_config(CONFIG.robot)
    maps = [_occupancy(replay, robot) for replay in replays]
    live = _occupancy(sent, robot)
    assert len(live) > 1000  # a real map: the table and the box
    assert maps[0] == maps[1] == live
