"""`robonav view` without a browser: its helpers, and a view in process fed over real Zenoh on
loopback (what arrives is drawn, clouds are thinned, bad samples are counted, not fatal), plus
the executor's latched `executor/path` that the view draws."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import msgpack
import numpy as np
import pytest
import zenoh

pytest.importorskip("viser", reason="the `view` extra (viser) is not installed")

from robonav.pipeline.camera import CameraConfig  # noqa: E402
from robonav.pipeline.perception.depth import points_from_depth  # noqa: E402
from robonav.pipeline.robot.model import RobotModel  # noqa: E402
from robonav.pipeline.wire.codec import ProtocolError  # noqa: E402
from robonav.pipeline.wire.messages import (  # noqa: E402
    ErrorReply,
    ExecuteResponse,
    ExecutorPath,
    ExecutorStatus,
    JointState,
    Occupancy,
    PointCloud,
)
from robonav.services.client import RobonavClient  # noqa: E402
from robonav.services.common import declare_latched_publisher, declare_latched_subscriber, open_session  # noqa: E402
from robonav.services.config import ZenohConfig, load_config  # noqa: E402
from robonav.services.executor.node import ExecutorNode  # noqa: E402
from robonav.services.keys import Keys  # noqa: E402
from robonav.services.stack.robot_cell import read_robot, with_robot  # noqa: E402
from robonav.services.view.app import (  # noqa: E402
    CAMERA_LOOK_AT_M,
    CAMERA_POSITION_M,
    ViewNode,
    ViewOptions,
    initial_camera_m,
    main,
    parse_args,
    view_config,
)
from robonav.services.view.clusters import decode_clusters  # noqa: E402
from robonav.services.view.scene import cameras_of, decimate, height_colors, interpolate_path, wxyz_of  # noqa: E402

from ...conftest import REPO_ROOT  # noqa: E402
from ..conftest import free_port, write_turn_lift_reach  # noqa: E402
from .conftest import project  # noqa: E402

CONFIG = load_config()
HOME = np.array(CONFIG.robot.home_position_rad)
NAMES = tuple(CONFIG.robot.joint_names)
GOALS = np.array(CONFIG.demo.goals_rad)


def test_cameras_of_reads_a_list_or_a_single_camera() -> None:
    a, b = CameraConfig(camera_id="a"), CameraConfig(camera_id="b")
    assert cameras_of(SimpleNamespace(cameras=(a, b))) == (a, b)
    assert cameras_of(SimpleNamespace(camera=a)) == (a,)
    assert cameras_of(SimpleNamespace()) == ()
    assert len(cameras_of(CONFIG)) >= 1


@pytest.mark.parametrize("message, expected", [
    ({"v": 1, "clusters": [{"label": "crate", "center_m": [0.4, 0.3, 0.3], "size_m": [0.2, 0.2, 0.2], "point_count": 9}]},
     [("crate (9 pts)", [0.4, 0.3, 0.3], [0.2, 0.2, 0.2])]),
    ({"v": 1, "clusters": [{"id": 3, "min_m": [0.0, 0.0, 0.0], "max_m": [0.2, 0.4, 0.6]}, {"id": 4}, "junk"]},
     [("3", [0.1, 0.2, 0.3], [0.2, 0.4, 0.6])]),
    ({"v": 1, "centers_m": {"dtype": "<f4", "shape": [2, 3], "data": np.array([[0, 0, 1], [1, 1, 1]], "<f4").tobytes()},
      "sizes_m": [[0.1, 0.1, 0.1], [0.2, 0.2, 0.2]], "labels": ["a", "b"]},
     [("a", [0, 0, 1], [0.1] * 3), ("b", [1, 1, 1], [0.2] * 3)]),
    ([{"centroid_m": [1, 2, 3], "extent_m": [1, 1, 1]}], [("cluster 0", [1, 2, 3], [1, 1, 1])]),
    ({"v": 1, "clusters": [{"center_m": [float("nan"), 0, 0], "size_m": [1, 1, 1]}]}, []),
    ({"v": 1, "clusters": [{"center_m": [0, 0, 0], "size_m": [-1, 1, 1]}]}, []),
    ({"v": 1, "stamp": 1.0}, []),
    ("not a map", []),
])
def test_decode_clusters_reads_likely_forms_and_skips_the_rest(message: object, expected: list) -> None:
    boxes = decode_clusters(msgpack.packb(message, use_bin_type=True))
    assert [b.label for b in boxes] == [label for label, _, _ in expected]
    for box, (_, center, size) in zip(boxes, expected):
        assert np.allclose(box.center_m, center) and np.allclose(box.size_m, size)
    for box in boxes:
        assert box.quat_xyzw.tolist() == [0.0, 0.0, 0.0, 1.0]


def test_decode_clusters_reads_the_perception_message() -> None:
    from robonav.pipeline.wire import messages

    if not hasattr(messages, "Clusters"):
        pytest.skip("this version has no Clusters message")
    wire = messages.Clusters(
        stamp=1.0, ids=np.array([4, 7]), centroids_m=np.array([[0.5, 0.0, 0.4], [0.45, 0.38, 0.3]], np.float32),
        bbox_min_m=np.array([[0.44, -0.06, 0.2], [0.36, 0.29, 0.2]], np.float32),
        bbox_max_m=np.array([[0.56, 0.06, 0.7], [0.54, 0.47, 0.4]], np.float32),
        voxel_counts=np.array([300, 120]), labels=("pillar", "")).to_wire()
    boxes = decode_clusters(wire)
    assert [b.label for b in boxes] == ["pillar (300 voxels)", "cluster 7 (120 voxels)"]
    assert np.allclose(boxes[0].center_m, [0.5, 0.0, 0.45]) and np.allclose(boxes[0].size_m, [0.12, 0.12, 0.5])


def test_decode_clusters_never_raises_on_garbage() -> None:
    assert decode_clusters(b"\xc1\xff garbage") == ()
    assert decode_clusters(b"") == ()


def test_decimate_keeps_finite_rows_under_the_cap() -> None:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(307200, 3)).astype(np.float32)
    points[::7] = np.nan
    out = decimate(points, 20000)
    assert 10000 < len(out) <= 20000 and np.isfinite(out).all()
    finite = points[np.isfinite(points).all(axis=1)]
    assert np.array_equal(out, finite[:: int(np.ceil(len(finite) / 20000))])
    small = points[:100]
    assert np.array_equal(decimate(small, 20000), small[np.isfinite(small).all(axis=1)])


def test_height_colors_span_the_colormap_and_clip() -> None:
    colors = height_colors(np.array([-1.0, 0.0, 0.5, 1.0, 9.0]), 0.0, 1.0)
    assert colors.dtype == np.uint8 and colors.shape == (5, 3)
    assert np.array_equal(colors[0], colors[1]) and np.array_equal(colors[3], colors[4])
    assert not np.array_equal(colors[1], colors[3])


def test_interpolate_path_keeps_waypoints_and_bounds_the_step() -> None:
    path = np.vstack([HOME, GOALS[0], GOALS[1]])
    dense = interpolate_path(path, 0.05)
    assert np.allclose(dense[0], path[0]) and np.allclose(dense[-1], path[-1])
    assert all(np.min(np.abs(dense - waypoint).max(axis=1)) < 1e-12 for waypoint in path)
    assert np.abs(np.diff(dense, axis=0)).max() <= 0.05 + 1e-12


def test_executor_path_round_trip_and_checks() -> None:
    message = ExecutorPath(stamp=1.0, trajectory_id="t", joint_names=NAMES, path=np.vstack([HOME, GOALS[0]]), duration_s=2.0)
    back = ExecutorPath.from_wire(message.to_wire())
    assert back.trajectory_id == "t" and back.joint_names == NAMES and np.array_equal(back.path, message.path)
    wire = message.to_dict() | {"joint_names": list(NAMES[:6])}
    with pytest.raises(ProtocolError):
        ExecutorPath.from_dict(wire)
    with pytest.raises(ValueError):
        ExecutorPath(stamp=1.0, trajectory_id="t", joint_names=NAMES[:6], path=np.zeros((2, 7)))


@pytest.fixture
def endpoint() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    yield endpoint
    router.close()


def synthetic_cloud(camera: CameraConfig) -> np.ndarray:
    """A full 640x480 frame of a tilted plane seen by `camera` (optical frame, float32)."""
    intrinsics = camera.intrinsics
    rows = np.arange(intrinsics.height, dtype=np.float64)[:, None]
    depth_m = np.broadcast_to(1.2 + 0.001 * rows, (intrinsics.height, intrinsics.width))
    return points_from_depth(depth_m, intrinsics).astype(np.float32)


def test_view_draws_what_arrives_thins_clouds_and_survives_bad_samples(endpoint: str) -> None:
    cfg = dataclasses.replace(CONFIG, zenoh=ZenohConfig(connect=(endpoint,)))
    keys = Keys(cfg.cell)
    camera = cameras_of(cfg)[0]
    publisher = open_session(cfg.zenoh)
    # Published before the view exists: latched, so the view must still get it.
    path_pub = declare_latched_publisher(publisher, keys.executor_path)
    path_pub.put(ExecutorPath(stamp=time.time(), trajectory_id="t1", joint_names=NAMES,
                              path=np.vstack([HOME, GOALS[0], GOALS[1]]), duration_s=3.0).to_wire())
    view_session = open_session(cfg.zenoh)
    node = ViewNode(cfg, view_session, ViewOptions(port=0, cloud_rate_hz=4.0, max_cloud_points=5000))
    node.start()
    stop = threading.Event()

    def joint_states() -> None:
        while not stop.wait(0.01):
            publisher.put(keys.joint_states, JointState(stamp=time.time(), names=NAMES, position=GOALS[1],
                                                        velocity=np.zeros(7)).to_wire())

    thread = threading.Thread(target=joint_states, daemon=True)
    thread.start()
    try:
        centers = np.array([[0.5, 0.0, 0.3], [0.5, 0.0, 0.32]], np.float32)
        declare_latched_publisher(publisher, keys.occupancy).put(Occupancy(
            stamp=time.time(), resolution_m=0.02, octomap_binary=b"", occupied_centers_m=centers).to_wire())
        status = ExecutorStatus(stamp=time.time(), state="executing", trajectory_id="t1", progress=0.25,
                                duration_s=3.0).to_wire()
        clusters = msgpack.packb({"v": 1, "clusters": [{"label": "pillar", "center_m": [0.5, 0, 0.45],
                                                        "size_m": [0.1, 0.1, 0.5]}]})
        publisher.put(keys.status, status)
        publisher.put(f"{keys.root}/perception/clusters", clusters)
        points = synthetic_cloud(camera)
        cloud_key = keys.camera_cloud(camera.camera_id)
        # A 30 Hz camera for one second: the view redraws at most 4 per second.
        started = time.monotonic()
        for seq in range(30):
            publisher.put(cloud_key, PointCloud(stamp=time.time(), camera_id=camera.camera_id, points=points,
                                                seq=seq).to_wire())
            time.sleep(max(0.0, started + (seq + 1) / 30.0 - time.monotonic()))
        elapsed = time.monotonic() - started
        # Status and clusters are not latched: put once, they can pass the router before it knows
        # the view's subscribers (seen on a loaded host). Put again until they are drawn.
        deadline = time.monotonic() + 10.0
        while not (node.stats.clusters_drawn and node.client.status is not None) and time.monotonic() < deadline:
            publisher.put(keys.status, status)
            publisher.put(f"{keys.root}/perception/clusters", clusters)
            time.sleep(0.2)
        assert node.wait_until(lambda: (node.stats.paths_drawn and node.stats.maps_drawn and node.stats.clusters_drawn
                                        and node.stats.robot_updates and node.stats.clouds_drawn), 10.0), node.stats
        assert node.stats.clouds_drawn <= 4.0 * elapsed + 2, node.stats
        assert node.stats.cloud_points_sent <= 5000 * node.stats.clouds_drawn
        assert node.layers.roots["ghost"].visible
        assert node.client.status is not None and node.controls.progress.value == pytest.approx(25.0)
        assert node.layers.clusters[0].label == "pillar"
        # A resting arm at 100 Hz is drawn once, not a hundred times a second.
        assert node.stats.robot_updates == 1, node.stats
        # Garbage and an unknown camera are counted; the next good cloud is drawn.
        drawn = node.stats.clouds_drawn
        publisher.put(cloud_key, b"\x00garbage")
        time.sleep(0.3)
        publisher.put(keys.camera_cloud("nobody"), PointCloud(stamp=time.time(), camera_id="nobody", points=points[:10]).to_wire())
        path_pub.put(b"not a path")
        time.sleep(0.3)
        publisher.put(cloud_key, PointCloud(stamp=time.time(), camera_id=camera.camera_id, points=points[:100]).to_wire())
        assert node.wait_until(lambda: node.stats.clouds_drawn > drawn and node.stats.errors.get("cloud", 0) >= 2
                               and node.stats.errors.get("executor path", 0) >= 1, 5.0), node.stats
    finally:
        stop.set()
        thread.join()
        node.close()
        view_session.close()
        publisher.close()


def test_executor_publishes_the_accepted_path_latched(endpoint: str) -> None:
    # No planner and no camera here: the execute is checked against nothing but the robot itself.
    cfg = dataclasses.replace(CONFIG, zenoh=ZenohConfig(connect=(endpoint,)),
                              executor=dataclasses.replace(CONFIG.executor, require_scene=False),
                              planner=dataclasses.replace(CONFIG.planner, require_occupancy=False))
    node_session = open_session(cfg.zenoh)
    node = ExecutorNode(cfg, node_session)
    client_session = open_session(cfg.zenoh)
    client = RobonavClient(client_session)
    keys = Keys(cfg.cell)
    try:
        client_session.put(keys.joint_states, JointState(stamp=time.time(), names=NAMES, position=HOME,
                                                         velocity=np.zeros(7)).to_wire())
        deadline = time.monotonic() + 5.0
        while node._measured_q is None and time.monotonic() < deadline:
            time.sleep(0.01)
        # Joint names in another order: the published path is in the robot's order.
        order = list(reversed(range(7)))
        path = np.vstack([HOME, HOME + 0.1])
        reply = client.execute(path[:, order], joint_names=tuple(NAMES[i] for i in order), trajectory_id="late")
        assert isinstance(reply, ExecuteResponse), reply
        received: list[ExecutorPath] = []
        got = threading.Event()

        def on_path(sample: zenoh.Sample) -> None:
            received.append(ExecutorPath.from_wire(sample.payload.to_bytes()))
            got.set()

        subscriber = declare_latched_subscriber(client_session, keys.executor_path, on_path)  # after the put
        assert got.wait(5.0), "the latched path never reached a late subscriber"
        subscriber.undeclare()
        assert received[0].trajectory_id == "late" and received[0].joint_names == NAMES
        assert np.allclose(received[0].path, path) and received[0].duration_s == pytest.approx(reply.duration_s)
    finally:
        client.close()
        node.close()
        client_session.close()
        node_session.close()


def test_robot_option_takes_a_robot_file_or_a_configs_robot_as_the_demo_does(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        parse_args(["--help"])
    assert "--robot FILE" in capsys.readouterr().out
    robot_file = write_turn_lift_reach(tmp_path)
    cfg = view_config(parse_args(["--robot", str(robot_file)]))
    # The demo's and the campaign's reading: the robot, and the cell (cameras) placed for it.
    assert cfg == with_robot(CONFIG, read_robot(robot_file)) and cfg.robot.name == "turn_lift_reach"
    assert [c.position_m for c in cfg.cameras] != [c.position_m for c in CONFIG.cameras]
    iiwa = REPO_ROOT / "configs" / "iiwa.yaml"
    assert view_config(parse_args(["--robot", str(iiwa)])).robot == load_config(iiwa).robot
    assert view_config(parse_args([])) == CONFIG


def test_robot_option_refuses_a_bad_robot_file(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: nothing\nurdf: missing.urdf\n", encoding="utf-8")
    assert main(["--robot", str(bad), "--port", "0"]) == 2
    assert str(bad) in caplog.text


@pytest.mark.parametrize("robot_file", [None, "ur5.yaml", "iiwa.yaml"])
def test_the_browser_camera_starts_on_the_whole_robot_at_home(robot_file: str | None) -> None:
    """The Panda's starting camera is the view's constant; another robot's is placed for its
    shoulder and reach, so every link at home is in the picture (the browser test's 476 x 480
    canvas, 10 px in)."""
    robot = RobotModel.from_config(CONFIG.robot if robot_file is None else read_robot(REPO_ROOT / "configs" / robot_file))
    points_m = np.array([pose[:3, 3] for pose in robot.link_poses(robot.home_position_rad).values()])
    eye_m, target_m = initial_camera_m(robot)

    def in_picture(eye: tuple[float, ...], target: tuple[float, ...]) -> bool:
        px = project(points_m, 476, 480, eye, target)
        return bool(np.all((px >= 10) & (px <= (466, 470))))

    assert in_picture(eye_m, target_m)
    if robot_file is None:
        assert (eye_m, target_m) == (CAMERA_POSITION_M, CAMERA_LOOK_AT_M)
    if robot_file == "ur5.yaml":  # its shoulder is 1 m up: the Panda's camera cuts off its upper links
        assert not in_picture(CAMERA_POSITION_M, CAMERA_LOOK_AT_M)


def test_the_view_of_a_robot_file_draws_its_collision_spheres(endpoint: str, tmp_path: Path) -> None:
    """`robonav view --robot FILE --spheres`: the planner's spheres of that robot, not the config's."""
    args = parse_args(["--robot", str(write_turn_lift_reach(tmp_path)), "--spheres"])
    cfg = dataclasses.replace(view_config(args), zenoh=ZenohConfig(connect=(endpoint,)))
    session = open_session(cfg.zenoh)
    node = ViewNode(cfg, session, ViewOptions(port=0, spheres=args.spheres))
    try:
        spheres = node.layers.spheres
        assert node.layers.robot.config == cfg.robot and spheres.root.visible and spheres.model is not None
        assert set(spheres.model.link_names) == {"foot", "column", "carriage", "boom", "tool"}
        assert len(spheres.sphere_nodes) == spheres.model.sphere_count > 0
    finally:
        node.close()
        session.close()


def test_gui_plans_executes_and_stops_on_the_live_stack(client: RobonavClient, stack_config: Path) -> None:
    """The goal gizmo's buttons against the real services; the executed path comes back on `executor/path`."""
    cfg = load_config(stack_config)
    session = open_session(cfg.zenoh)
    node = ViewNode(cfg, session, ViewOptions(port=0))
    node.start()
    try:
        assert node.wait_until(lambda: node.stats.robot_updates > 0 and node.stats.maps_drawn > 0, 30.0), node.stats
        ee = cfg.robot.end_effector_link
        robot = RobotModel.from_config(cfg.robot)  # the view's model is the view's: it is not thread-safe
        goal = robot.frame_pose(GOALS[0], ee)
        node.controls.gizmo.position = goal[:3, 3]
        node.controls.gizmo.wxyz = wxyz_of(goal[:3, :3])
        assert node.controls.execute() == "plan first"
        text = node.controls.plan()
        assert text.startswith("planned"), text
        assert not node.controls.execute_button.disabled
        paths = node.stats.paths_drawn
        text = node.controls.execute()
        assert text.startswith("executing"), text
        trajectory_id = text.split("`")[1]
        assert client.wait_for_trajectory(trajectory_id, 30.0) == "succeeded"
        assert node.wait_until(lambda: node.stats.paths_drawn > paths, 5.0), "the executed path was not drawn"
        assert client.wait_for(lambda: np.linalg.norm(robot.frame_pose(client.joint_state.position, ee)[:3, 3]
                                                      - goal[:3, 3]) < 0.01, 5.0)
        assert node.controls.stop().startswith("stop: executor")
    finally:
        node.close()
        session.close()
    # Leave the arm at home for whatever test runs next on the shared stack.
    back = client.plan(HOME)
    assert not isinstance(back, ErrorReply), back
    done = client.execute(back.path, joint_names=back.joint_names)
    assert isinstance(done, ExecuteResponse) and client.wait_for_trajectory(done.trajectory_id, 30.0) == "succeeded"
