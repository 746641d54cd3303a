"""The sim service alone over real Zenoh: render workers, labels, depth, noise, objects, contacts."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
import zenoh

from robonav.pipeline.perception.depth import points_from_depth
from robonav.pipeline.perception.self_filter import SelfFilter
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import look_at_quat_xyzw, transform_points
from robonav.pipeline.wire.messages import (
    Cameras,
    ContactEvent,
    DepthImage,
    ErrorReply,
    ExecutorStatus,
    JointState,
    ObjectMotionSpec,
    PointCloud,
    SceneObjectSpec,
    Setpoint,
    SimObjectsRequest,
    SimObjectsResponse,
    SimStatsRequest,
    SimStatsResponse,
)
from robonav.services.client import RobonavClient
from robonav.services.common import declare_latched_subscriber, open_session
from robonav.services.config import RobonavConfig, ZenohConfig, load_config
from robonav.services.stack.up import Stack

from ..conftest import free_port, write_config

EYE_M = [1.5, 0.3, 1.1]
LOOK = [float(v) for v in look_at_quat_xyzw(EYE_M, (0.3, 0.0, 0.4))]
CAMERA = {"width": 160, "height": 120, "vertical_fov_deg": 58.0, "near_m": 0.1, "far_m": 3.0,
          "position_m": EYE_M, "quat_xyzw": LOOK, "rate_hz": 10.0}
NOISY_LATENCY_S = 0.15
# Beside the arm, where joint 1 at +90 degrees swings the wrist into it.
WALL = {"name": "wall", "type": "box", "position_m": [0.0, 0.38, 0.5], "size_m": [0.4, 0.1, 0.6]}


@pytest.fixture(scope="module")
def sim_config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("sim")
    # The tests publish setpoints from a Python loop that shares its process with the recorder's
    # decoding: a generous setpoint timeout keeps a stall of that loop from braking the arm.
    path = write_config(directory, "sim.yaml", zenoh={"connect": [f"tcp/127.0.0.1:{free_port()}"]},
                        sim={"follow": "kinematic", "objects": [WALL], "setpoint_timeout_s": 1.0})
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    data["cameras"] = [{"camera_id": "clean", "output": "both", **CAMERA}, {"camera_id": "noisy", **CAMERA}]
    data["sim"]["camera_noise"] = {"noisy": {"enabled": True, "dropout_probability": 0.3, "latency_s": NOISY_LATENCY_S}}
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    load_config(path)
    return path


class Recorder:
    """Everything the sim publishes, kept with its arrival time."""

    def __init__(self, session: zenoh.Session, cfg: RobonavConfig) -> None:
        self.cond = threading.Condition()
        self.joint_states: list[JointState] = []
        self.clouds: dict[str, list[tuple[float, PointCloud]]] = {"clean": [], "noisy": []}
        self.depths: list[DepthImage] = []
        self.events: list[ContactEvent] = []
        root = f"robonav/{cfg.cell}"
        self._subs = [
            session.declare_subscriber(f"{root}/robot/joint_states", self._add(JointState, self.joint_states.append)),
            session.declare_subscriber(f"{root}/camera/*/cloud", self._add(
                PointCloud, lambda c: self.clouds[c.camera_id].append((time.time(), c)))),
            session.declare_subscriber(f"{root}/camera/*/depth", self._add(DepthImage, self.depths.append)),
            session.declare_subscriber(f"{root}/sim/contacts/events", self._add(ContactEvent, self.events.append)),
        ]

    def _add(self, cls, store: Callable) -> Callable[[zenoh.Sample], None]:  # noqa: ANN001 - a message class
        def callback(sample: zenoh.Sample) -> None:
            with self.cond:
                store(cls.from_wire(sample.payload.to_bytes()))
                self.cond.notify_all()
        return callback

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float = 20.0) -> bool:
        with self.cond:
            return self.cond.wait_for(predicate, timeout=timeout_s)


@pytest.fixture(scope="module")
def sim(sim_config: Path) -> Iterator[tuple[RobonavClient, Recorder, RobonavConfig]]:
    cfg = load_config(sim_config)
    stack = Stack(cfg, str(sim_config), services=("sim",), log_level="WARNING")
    try:
        session = open_session(ZenohConfig(mode="client", connect=cfg.zenoh.connect))
        client = RobonavClient(session, cfg.cell)
        recorder = Recorder(session, cfg)
        assert not client.wait_for_services(["sim"], 60.0)
        assert recorder.wait_for(lambda: all(len(c) >= 2 for c in recorder.clouds.values()), 60.0), "no clouds"
        yield client, recorder, cfg
        client.close()
        session.close()
    finally:
        codes = stack.close()
    assert codes == {"sim": 0, "router": 0}


def objects_query(client: RobonavClient, request: SimObjectsRequest) -> SimObjectsResponse | ErrorReply:
    return client.query(client.keys.root + "/sim/objects", request, SimObjectsResponse, 10.0)


def stream_setpoints(client: RobonavClient, cfg: RobonavConfig, q_of_t: Callable[[float], np.ndarray],
                     duration_s: float) -> None:
    """Publish setpoints at 100 Hz along q_of_t(t), like an executor would: with their velocity,
    so the sim's driver sees them continue one another however late the next one comes. Each
    setpoint's position is the one of its stamp: a sender preempted between reading two clocks
    would stamp a position tens of milliseconds old, which the driver rightly takes for a jump."""
    key = client.keys.setpoint
    start = time.time()
    while (t := (stamp := time.time()) - start) < duration_s:
        q = q_of_t(t)
        qd = (q_of_t(t + 1e-3) - q_of_t(max(t - 1e-3, 0.0))) / (t + 1e-3 - max(t - 1e-3, 0.0))
        client.session.put(key, Setpoint(stamp=stamp, trajectory_id="test", names=cfg.robot.joint_names,
                                         position=q, velocity=qd, acceleration=np.zeros(7)).to_wire())
        time.sleep(0.01)


def smooth_step(x: float) -> float:
    """0 to 1 with zero velocity at both ends (a half cosine): setpoints the driver's limits allow."""
    return 0.5 * (1.0 - math.cos(math.pi * min(max(x, 0.0), 1.0)))


def test_frames_show_the_arm_at_the_joint_state_of_their_stamp(sim: tuple[RobonavClient, Recorder, RobonavConfig]) -> None:
    client, recorder, cfg = sim
    home = np.array(cfg.robot.home_position_rad)

    def sweep(t: float) -> np.ndarray:  # joint 1 swings at up to 1.2 rad/s, away from the wall
        return home + np.array([-0.6 * (1 - math.cos(2.0 * t)), 0, 0, 0, 0, 0, 0])

    since = time.time()
    stream_setpoints(client, cfg, sweep, 3.0)
    stream_setpoints(client, cfg, lambda t: home, 0.3)
    robot = RobotModel.from_config(cfg.robot)
    self_filter = SelfFilter(robot.link_hull_vertices, 0.02)
    by_stamp = {js.stamp: js.position for js in recorder.joint_states}
    stamps = np.array(sorted(by_stamp))
    now_fractions, before_fractions = [], []
    for _, cloud in [c for c in recorder.clouds["clean"] if c[1].stamp > since + 0.5]:
        assert cloud.stamp in by_stamp, "every frame's stamp is a published joint state's stamp"
        q = by_stamp[cloud.stamp]
        other = by_stamp[stamps[np.argmin(np.abs(stamps - (cloud.stamp - 0.25)))]]
        if np.abs(q - other).max() < 0.2:
            continue  # the arm barely moved in between: nothing to tell apart
        assert cloud.labels is not None and cloud.label_names is not None
        robot_label = next(label for label, name in cloud.label_names.items() if name == "robot")
        points = transform_points(cfg.cameras[0].world_from_camera, cloud.points[cloud.labels == robot_label])
        inside_now = 1.0 - self_filter.outside_mask(points, robot.link_poses(q)).mean()
        inside_before = 1.0 - self_filter.outside_mask(points, robot.link_poses(other)).mean()
        now_fractions.append(inside_now)
        before_fractions.append(inside_before)
    # The arm's points sit inside the arm posed at the frame's stamp, not at a pose 0.25 s older.
    assert len(now_fractions) >= 3 and min(now_fractions) > 0.97, now_fractions
    assert np.mean(before_fractions) < np.mean(now_fractions) - 0.05, (before_fractions, now_fractions)


def test_depth_images_match_the_cloud_and_carry_the_same_labels(sim: tuple[RobonavClient, Recorder, RobonavConfig]) -> None:
    _, recorder, cfg = sim
    assert recorder.wait_for(lambda: len(recorder.depths) >= 2)
    depth = recorder.depths[-1]
    assert recorder.wait_for(lambda: any(c.seq == depth.seq for _, c in recorder.clouds["clean"]))
    cloud = next(c for _, c in recorder.clouds["clean"] if c.seq == depth.seq)
    assert depth.stamp == cloud.stamp and depth.depth_m.shape == (120, 160) and depth.intrinsics == cloud.intrinsics
    np.testing.assert_array_equal(points_from_depth(depth.depth_m, depth.intrinsics, max_depth_m=3.0), cloud.points)
    assert depth.labels is not None and cloud.labels is not None and depth.label_names == cloud.label_names
    np.testing.assert_array_equal(np.sort(np.unique(depth.labels[np.isfinite(depth.depth_m)])), np.unique(cloud.labels))
    assert set(depth.label_names.values()) == {"robot", "wall"}  # type: ignore[union-attr]
    assert not any(d.camera_id == "noisy" for d in recorder.depths)  # output: cloud only


def test_the_noisy_camera_drops_points_and_publishes_late(sim: tuple[RobonavClient, Recorder, RobonavConfig]) -> None:
    _, recorder, _ = sim
    assert recorder.wait_for(lambda: len(recorder.clouds["noisy"]) >= 3)
    clean = np.median([c.points.shape[0] for _, c in recorder.clouds["clean"][-5:]])
    noisy = [(arrival, c) for arrival, c in recorder.clouds["noisy"][-3:]]
    for arrival, cloud in noisy:
        assert 0.6 * clean < cloud.points.shape[0] < 0.8 * clean  # dropout 0.3, same view
        assert arrival - cloud.stamp >= NOISY_LATENCY_S  # the stamp stays the captured moment
    assert len({c.points.shape[0] for _, c in noisy}) > 1  # frames differ: the noise is per frame


def test_objects_can_be_listed_added_moved_and_removed(sim: tuple[RobonavClient, Recorder, RobonavConfig]) -> None:
    client, recorder, _ = sim
    listed = objects_query(client, SimObjectsRequest(operation="list"))
    assert isinstance(listed, SimObjectsResponse) and [o.name for o in listed.objects] == ["wall"]
    crate = SceneObjectSpec("crate", "box", (0.6, -0.3, 0.2), size_m=(0.2, 0.2, 0.2))
    added = objects_query(client, SimObjectsRequest(operation="add", objects=(crate,)))
    assert isinstance(added, SimObjectsResponse) and added.revision == listed.revision + 1
    moved = objects_query(client, SimObjectsRequest(operation="move", objects=(
        SceneObjectSpec("crate", position_m=(0.6, -0.4, 0.25)),)))
    assert isinstance(moved, SimObjectsResponse)
    assert next(o for o in moved.objects if o.name == "crate").position_m == pytest.approx((0.6, -0.4, 0.25))
    after = time.time()
    assert recorder.wait_for(lambda: any(c.stamp > after and "crate" in (c.label_names or {}).values()
                                         for _, c in recorder.clouds["clean"]))
    bad = objects_query(client, SimObjectsRequest(operation="remove", names=("crate", "nothing")))
    assert isinstance(bad, ErrorReply) and bad.code == "INVALID_REQUEST" and bad.details["key"] == "names[1]"
    removed = objects_query(client, SimObjectsRequest(operation="remove", names=("crate",)))
    assert isinstance(removed, SimObjectsResponse) and [o.name for o in removed.objects] == ["wall"]
    replies = list(client.session.get(client.keys.root + "/sim/objects", payload=b"\x00garbage", timeout=5.0))
    assert len(replies) == 1 and replies[0].err is not None


def test_a_scripted_obstacle_slides_in_when_the_executor_reports_progress(
        sim: tuple[RobonavClient, Recorder, RobonavConfig]) -> None:
    client, _, cfg = sim
    objects_query(client, SimObjectsRequest(operation="add", objects=(
        SceneObjectSpec("slider", "box", (0.6, -0.6, 0.3), size_m=(0.1, 0.1, 0.1)),)))
    armed = objects_query(client, SimObjectsRequest(operation="script", motions=(
        ObjectMotionSpec("slider", position_m=(0.6, -0.2, 0.3), duration_s=0.4, at_progress=0.5, trajectory_id="tr"),)))
    assert isinstance(armed, SimObjectsResponse) and armed.pending_motions == 1

    def status(progress: float, trajectory_id: str = "tr") -> None:
        client.session.put(client.keys.status, ExecutorStatus(stamp=time.time(), state="executing",
                                                              trajectory_id=trajectory_id, progress=progress).to_wire())

    def slider_y() -> float:
        reply = objects_query(client, SimObjectsRequest(operation="list"))
        assert isinstance(reply, SimObjectsResponse)
        return next(o for o in reply.objects if o.name == "slider").position_m[1]

    status(0.3)
    status(0.9, "another")
    time.sleep(0.3)
    assert slider_y() == pytest.approx(-0.6)
    status(0.6)
    deadline = time.monotonic() + 10.0
    while slider_y() != pytest.approx(-0.2) and time.monotonic() < deadline:
        time.sleep(0.1)
    final = objects_query(client, SimObjectsRequest(operation="remove", names=("slider",)))
    assert isinstance(final, SimObjectsResponse) and final.pending_motions == 0 and final.fired_motions >= 1
    assert time.monotonic() < deadline, "the slider never reached its target"


def test_driving_the_arm_into_a_box_is_a_contact_event(sim: tuple[RobonavClient, Recorder, RobonavConfig]) -> None:
    client, recorder, cfg = sim
    client.contacts(reset=True)
    home = np.array(cfg.robot.home_position_rad)
    into_wall = home + np.array([math.pi / 2, 0, 0, 0, 0, 0, 0])
    stream_setpoints(client, cfg, lambda t: home + (into_wall - home) * smooth_step(t / 1.5), 2.0)
    assert recorder.wait_for(lambda: any(e.event == "begin" and e.object == "wall" for e in recorder.events))
    contacts = client.contacts()
    assert not isinstance(contacts, ErrorReply) and contacts.contact_count >= 1
    assert all(pair.endswith("|wall") for pair in contacts.pairs)
    begin = next(e for e in recorder.events if e.event == "begin")
    assert begin.distance_m <= 0.0 and begin.link.startswith("panda_") and begin.contact_count >= 1
    stream_setpoints(client, cfg, lambda t: into_wall + (home - into_wall) * smooth_step(t / 1.5), 2.0)
    assert recorder.wait_for(lambda: any(e.event == "end" for e in recorder.events))


def test_odd_setpoints_are_ignored_and_stamps_never_hold_the_arm_back(sim: tuple[RobonavClient, Recorder, RobonavConfig]) -> None:
    """Setpoints naming other joints, or too few, are dropped; the latest good one is followed
    whatever its stamp (the sim does not order setpoints by stamp)."""
    client, recorder, cfg = sim
    home = np.array(cfg.robot.home_position_rad)
    away = home + np.array([-0.3, 0.0, 0.0, 0.2, 0.0, 0.0, 0.0])
    names = tuple(cfg.robot.joint_names)

    def stream(q_of_t: Callable[[float], np.ndarray], duration_s: float, *, stamp_offset_s: float = 0.0,
               joint_names: tuple[str, ...] = names, stamp: float | None = None) -> None:
        start = time.monotonic()
        while (t := time.monotonic() - start) < duration_s:
            q = q_of_t(t)[:len(joint_names)]
            client.session.put(client.keys.setpoint, Setpoint(
                stamp=time.time() + stamp_offset_s if stamp is None else stamp, trajectory_id="odd", names=joint_names,
                position=q, velocity=np.zeros(len(q)), acceleration=np.zeros(len(q))).to_wire())
            time.sleep(0.01)

    def arm_at(q: np.ndarray) -> bool:
        return recorder.wait_for(lambda: bool(recorder.joint_states)
                                 and np.max(np.abs(recorder.joint_states[-1].position - q)) < 1e-3, 5.0)

    stream(lambda t: home, 0.3)
    assert arm_at(home)
    towards_away = lambda t: home + (away - home) * min(t / 0.5, 1.0)  # noqa: E731
    stream(towards_away, 0.7, joint_names=tuple(f"other_{n}" for n in names))
    stream(towards_away, 0.7, joint_names=names[:-1])
    time.sleep(0.2)
    assert arm_at(home), "the sim followed setpoints for joints it does not have"
    stream(towards_away, 0.7, stamp_offset_s=1e6)  # stamped far in the future
    assert arm_at(away)
    stream(lambda t: away + (home - away) * min(t / 0.5, 1.0), 0.7)  # then ordinary stamps
    assert arm_at(home)
    stream(towards_away, 0.7, stamp=1.0)  # stamped in 1970
    assert arm_at(away)
    stream(lambda t: away + (home - away) * min(t / 0.5, 1.0), 0.7)
    assert arm_at(home)


def test_stats_report_physics_timing_and_frames(sim: tuple[RobonavClient, Recorder, RobonavConfig]) -> None:
    client, _, _ = sim
    stats = client.query(client.keys.root + "/sim/stats", SimStatsRequest(reset=True), SimStatsResponse, 10.0)
    assert isinstance(stats, SimStatsResponse)
    assert stats.steps > 0 and stats.sim_time_s > 0 and stats.real_time_factor > 0
    assert {c.camera_id for c in stats.cameras} == {"clean", "noisy"}
    assert all(c.frames > 0 and c.render_ms_p50 > 0 for c in stats.cameras)
    fresh = client.query(client.keys.root + "/sim/stats", SimStatsRequest(), SimStatsResponse, 10.0)
    assert isinstance(fresh, SimStatsResponse) and fresh.steps < stats.steps  # a new window


def test_the_cameras_are_published_latched_for_discovery(sim: tuple[RobonavClient, Recorder, RobonavConfig]) -> None:
    client, _, cfg = sim
    received: list[Cameras] = []
    # Subscribed long after the sim started: the latched cache answers.
    sub = declare_latched_subscriber(client.session, f"robonav/{cfg.cell}/cameras",
                                     lambda s: received.append(Cameras.from_wire(s.payload.to_bytes())))
    try:
        deadline = time.monotonic() + 10.0
        while not received and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        sub.undeclare()
    assert received, "no cameras publication"
    cameras = {c.camera_id: c for c in received[0].cameras}
    assert set(cameras) == {"clean", "noisy"}
    for camera in cfg.cameras:
        described = cameras[camera.camera_id]
        assert described.intrinsics == camera.intrinsics and described.output == camera.output
        np.testing.assert_allclose(described.world_from_camera, camera.world_from_camera, atol=1e-12)
