"""The planner service in process, over real Zenoh sessions on loopback, fed crafted maps.

Covers the error codes that need a particular world state: no map yet, no joint state, a
stale map, no solution in time.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import octomap
import pytest
import zenoh

from robonav.pipeline.planning.ik import pose_error
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import make_transform
from robonav.pipeline.wire.messages import (
    ErrorReply,
    JointState,
    Occupancy,
    PlanningSceneState,
    PlanRequest,
    PlanResponse,
    RobotDescription,
    SceneObjectSpec,
    SceneRequest,
    SceneResponse,
)
from robonav.services.client import RobonavClient
from robonav.services.common import declare_latched_publisher, declare_latched_subscriber, open_session
from robonav.services.config import ZenohConfig, load_config
from robonav.services.keys import Keys
from robonav.services.planner.node import PlannerNode

CONFIG = load_config()
CONFIG_ROBOT = RobotModel.from_config(CONFIG.robot)
HOME = np.array(CONFIG.robot.home_position_rad)
GOAL = np.array(CONFIG.demo.goals_rad[0])


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wall_map(x_m: float, stamp: float) -> Occupancy:
    """A 2 cm octree of a wall across the workspace at x = x_m, from z 0 to 1 m."""
    tree = octomap.OcTree(0.02)
    ys, zs = np.meshgrid(np.arange(-0.8, 0.8, 0.01), np.arange(0.0, 1.0, 0.01))
    points = np.column_stack([np.full(ys.size, x_m), ys.ravel(), zs.ravel()])
    tree.insertPointCloud(points, np.array([2.0, 0.0, 0.5]), maxrange=-1.0)
    occupied, _ = tree.extractPointCloud()
    return Occupancy(stamp=stamp, resolution_m=0.02, octomap_binary=tree.writeBinary(),
                     occupied_centers_m=np.asarray(occupied, dtype=np.float32))


@pytest.fixture
def planner(tmp_path: Path) -> Iterator[tuple[PlannerNode, zenoh.Session, RobonavClient]]:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    # A map stays fresh for 10 s here: on a loaded host a test's steps can take seconds, and the
    # map's age is what only the tests that change `occupancy_max_age_s` are about.
    cfg = dataclasses.replace(CONFIG, planner=dataclasses.replace(CONFIG.planner, occupancy_max_age_s=10.0,
                                                                   first_map_wait_s=0.3))
    node_session = open_session(ZenohConfig(connect=(endpoint,)))
    node = PlannerNode(cfg, node_session)
    client_session = open_session(ZenohConfig(connect=(endpoint,)))
    client = RobonavClient(client_session)
    yield node, client_session, client
    client.close()
    node.close()
    for s in (client_session, node_session, router):
        s.close()


def _publish_until(session: zenoh.Session, key: str, payload: bytes, predicate, timeout_s: float = 5.0) -> None:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, f"{key} never arrived"
        session.put(key, payload)
        time.sleep(0.05)


def _on_a_fresh_map(node: PlannerNode, session: zenoh.Session, key: str, ask):  # noqa: ANN001, ANN202
    """`ask()` (a request to the planner) right after a fresh wall map has arrived, again when it
    still found the map stale: on a loaded machine a test can outlast `occupancy_max_age_s` (10 s
    here), and the map's age is not what the tests that use this are about."""
    for _ in range(3):
        fresh = _wall_map(-0.9, time.time())
        _publish_until(session, key, fresh.to_wire(),
                       lambda: node._newest_map is not None and node._newest_map.stamp == fresh.stamp)
        reply = ask()
        if not (isinstance(reply, ErrorReply) and reply.code == "OCCUPANCY_STALE"):
            break
    return reply


def test_error_codes_that_depend_on_world_state(planner: tuple[PlannerNode, zenoh.Session, RobonavClient]) -> None:
    node, session, client = planner
    keys = client.keys

    reply = client.plan(GOAL)
    assert isinstance(reply, ErrorReply) and reply.code == "NO_JOINT_STATE"

    state = JointState(stamp=time.time(), names=CONFIG.robot.joint_names, position=HOME, velocity=np.zeros(7))
    _publish_until(session, keys.joint_states, state.to_wire(), lambda: node._joint_state is not None)
    reply = client.plan(GOAL)
    assert isinstance(reply, ErrorReply) and reply.code == "OCCUPANCY_MISSING"

    # A wall far behind the robot: planning works.
    far_wall = _wall_map(-0.9, time.time())
    _publish_until(session, keys.occupancy, far_wall.to_wire(), lambda: node._map_received_monotonic is not None)
    reply = client.plan(GOAL, seed=3)
    assert isinstance(reply, PlanResponse), reply
    assert reply.min_clearance_m is not None and reply.min_clearance_m > 0.3

    # A wall through the arm: the start collides with the occupancy map.
    node._map_received_monotonic = None
    near_wall = _wall_map(0.3, time.time())
    _publish_until(session, keys.occupancy, near_wall.to_wire(), lambda: node._map_received_monotonic is not None)
    reply = client.plan(GOAL)
    assert isinstance(reply, ErrorReply) and reply.code == "START_IN_COLLISION"
    assert any(p.endswith("|occupancy") for p in reply.details["pairs"])
    assert reply.details["which"] == "start" and len(reply.details["positions"]) == 7

    # No map for longer than occupancy_max_age_s: stale.
    node.cfg = dataclasses.replace(node.cfg, planner=dataclasses.replace(node.cfg.planner, occupancy_max_age_s=1.5))
    time.sleep(1.6)
    reply = client.plan(GOAL)
    assert isinstance(reply, ErrorReply) and reply.code == "OCCUPANCY_STALE"
    assert reply.details["age_s"] > 1.5


def _box_map(center: np.ndarray, size: np.ndarray, stamp: float) -> Occupancy:
    """A 2 cm octree of a solid box's points."""
    tree = octomap.OcTree(0.02)
    axes = [np.arange(c - h, c + h + 1e-9, 0.01) for c, h in zip(center, size / 2)]
    points = np.stack(np.meshgrid(*axes), axis=-1).reshape(-1, 3)
    for p in points:
        tree.updateNode(p, True)
    occupied, _ = tree.extractPointCloud()
    return Occupancy(stamp=stamp, resolution_m=0.02, octomap_binary=tree.writeBinary(),
                     occupied_centers_m=np.asarray(occupied, dtype=np.float32))


def test_no_solution_within_the_allowed_time(planner: tuple[PlannerNode, zenoh.Session, RobonavClient]) -> None:
    node, session, client = planner
    pillar = next(o for o in CONFIG.sim.objects if o.name == "pillar")
    occupancy = _box_map(np.array(pillar.position_m), np.array(pillar.size_m), time.time())
    _publish_until(session, client.keys.occupancy, occupancy.to_wire(), lambda: node._map_received_monotonic is not None)
    left, right = (np.array(g) for g in CONFIG.demo.goals_rad[:2])
    # The pillar stands between the two goals: a detour is needed and cannot be found in 0.1 ms.
    reply = client.plan(right, start_positions=left, allowed_planning_time=1e-4)
    assert isinstance(reply, ErrorReply) and reply.code == "NO_SOLUTION", reply
    reply = client.plan(right, start_positions=left, allowed_planning_time=5.0, seed=2)
    assert isinstance(reply, PlanResponse), reply
    assert reply.waypoint_count > 2


def test_a_request_racing_the_first_map_waits_for_it(planner: tuple[PlannerNode, zenoh.Session, RobonavClient]) -> None:
    node, session, client = planner
    node.cfg = dataclasses.replace(node.cfg, planner=dataclasses.replace(node.cfg.planner, first_map_wait_s=10.0))
    replies: list = []
    asking = threading.Thread(target=lambda: replies.append(client.plan(GOAL, start_positions=HOME, seed=1)))
    asking.start()
    time.sleep(0.5)
    assert not replies, "the planner answered before any map existed"
    session.put(client.keys.occupancy, _wall_map(-0.9, time.time()).to_wire())
    asking.join(timeout=20.0)
    assert replies and isinstance(replies[0], PlanResponse), replies


def test_an_empty_map_after_a_clear_is_not_free_space(planner: tuple[PlannerNode, zenoh.Session, RobonavClient]) -> None:
    """A map says how many frames each camera integrated since the last clear: until every
    configured camera has the configured number, plans are OCCUPANCY_INCOMPLETE; and a map
    is as old as its stamp says, whenever it arrives."""
    node, session, client = planner
    (camera,) = [c.camera_id for c in CONFIG.cameras]
    needed = CONFIG.planner.occupancy_min_frames
    assert needed >= 2

    published = [0]
    wall = _wall_map(-0.9, 0.0)

    def publish(age_s: float, frames: int | None) -> None:
        published[0] += 1
        seq = published[0]
        occupancy = dataclasses.replace(wall, stamp=time.time() - age_s, seq=seq,
                                        camera_frames=None if frames is None else {camera: frames})
        _publish_until(session, client.keys.occupancy, occupancy.to_wire(),
                       lambda: node._newest_map is not None and node._newest_map.seq == seq)

    publish(0.0, 0)  # what perception sends right after perception/clear
    reply = client.plan(GOAL, start_positions=HOME, seed=1)
    assert isinstance(reply, ErrorReply) and reply.code == "OCCUPANCY_INCOMPLETE", reply
    assert reply.details["camera_frames"] == {camera: 0} and reply.details["required_frames"] == needed
    assert reply.details["missing"] == [camera]
    publish(0.0, needed - 1)
    reply = client.plan(GOAL, start_positions=HOME, seed=1)
    assert isinstance(reply, ErrorReply) and reply.code == "OCCUPANCY_INCOMPLETE", reply

    # A plan that arrives while the map is rebuilt waits for it (up to first_map_wait_s).
    node.cfg = dataclasses.replace(node.cfg, planner=dataclasses.replace(node.cfg.planner, first_map_wait_s=10.0))
    replies: list = []
    asking = threading.Thread(target=lambda: replies.append(client.plan(GOAL, start_positions=HOME, seed=1)))
    asking.start()
    time.sleep(0.5)
    assert not replies, "the planner planned on an incomplete map"
    publish(0.0, needed)
    asking.join(timeout=20.0)
    assert replies and isinstance(replies[0], PlanResponse), replies

    # Arriving now does not make a map fresh: its stamp (newest frame) is what counts.
    publish(15.0, needed)
    reply = client.plan(GOAL, start_positions=HOME, seed=1)
    assert isinstance(reply, ErrorReply) and reply.code == "OCCUPANCY_STALE" and reply.details["age_s"] > 14.0, reply
    # A map from a producer older than the frame counts is taken as it is.
    publish(0.0, None)
    assert isinstance(client.plan(GOAL, start_positions=HOME, seed=1), PlanResponse)


def test_a_late_planner_gets_the_last_published_map(tmp_path: Path) -> None:
    """Perception publishes the map latched: a planner started after it still gets the last one."""
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    sessions = [open_session(ZenohConfig(mode="router", listen=(endpoint,)))]
    try:
        sessions.append(open_session(ZenohConfig(connect=(endpoint,))))
        publisher = declare_latched_publisher(sessions[-1], Keys(CONFIG.cell).occupancy)
        publisher.put(_wall_map(-0.9, time.time()).to_wire())
        time.sleep(0.3)
        sessions.append(open_session(ZenohConfig(connect=(endpoint,))))
        node = PlannerNode(CONFIG, sessions[-1])
        deadline = time.monotonic() + 10.0
        while node._map_received_monotonic is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert node._map_received_monotonic is not None, "the latched map never reached the late planner"
        node.close()
        publisher.undeclare()
    finally:
        for s in reversed(sessions):
            s.close()


def test_goal_forms_and_the_planning_scene_over_zenoh(planner: tuple[PlannerNode, zenoh.Session, RobonavClient]) -> None:
    node, session, client = planner

    def fresh(ask):  # noqa: ANN001, ANN202
        return _on_a_fresh_map(node, session, client.keys.occupancy, ask)

    # A Cartesian goal: the hand where it is at GOAL, reached within the default 1 mm / 0.01 rad.
    target = node.robot.frame_pose(GOAL, "panda_hand")
    quat_xyzw = _quat_xyzw(target[:3, :3])
    reply = fresh(lambda: client.plan_to_pose(target[:3, 3], quat_xyzw, start_positions=HOME, seed=1))
    assert isinstance(reply, PlanResponse), reply
    position_error_m, angle_error_rad = pose_error(node.robot, reply.path[-1], target, "panda_hand")
    assert position_error_m <= 1e-3 and angle_error_rad <= 0.01
    np.testing.assert_array_equal(reply.goal_positions, reply.path[-1])

    reply = fresh(lambda: client.plan_to_pose([3.0, 0.0, 0.5], start_positions=HOME))
    assert isinstance(reply, ErrorReply) and reply.code == "GOAL_UNREACHABLE", reply
    reply = client.plan_to_pose([0.4, 0.0, 0.5], goal_link="no_such_link", start_positions=HOME)
    assert isinstance(reply, ErrorReply) and reply.code == "INVALID_REQUEST" and "no_such_link" in reply.message

    # A goal set: the reply names the goal it reached.
    reply = fresh(lambda: client.plan_request(PlanRequest(goal_set=np.array([GOAL, HOME + 0.1]), start_positions=HOME,
                                                           seed=2)))
    assert isinstance(reply, PlanResponse), reply
    np.testing.assert_array_equal(reply.path[-1], [GOAL, HOME + 0.1][reply.goal_index])

    # A box added through planner/scene is planned around, and a start inside it is refused.
    hand = node.robot.frame_pose(HOME, "panda_hand")[:3, 3]
    scene = client.scene(SceneRequest(operation="add", objects=(
        SceneObjectSpec("crate", "box", tuple(hand), (0.0, 0.0, 0.0, 1.0), size_m=(0.1, 0.1, 0.1)),)))
    assert isinstance(scene, SceneResponse) and [o.name for o in scene.objects] == ["crate"]
    reply = fresh(lambda: client.plan(GOAL, start_positions=HOME))
    assert isinstance(reply, ErrorReply) and reply.code == "START_IN_COLLISION", reply
    assert any("crate" in pair for pair in reply.details["pairs"]), reply.details
    scene = client.scene(SceneRequest(operation="remove", names=("crate",)))
    assert isinstance(scene, SceneResponse) and scene.objects == ()
    reply = fresh(lambda: client.plan(GOAL, start_positions=HOME, seed=3))
    assert isinstance(reply, PlanResponse) and reply.scene_revision == scene.revision == 2, reply


def test_the_planner_publishes_its_whole_scene_latched_on_every_change(
        planner: tuple[PlannerNode, zenoh.Session, RobonavClient]) -> None:
    """What the executor checks executes against: complete objects (meshes too), attached ones in their link's frame."""
    _, session, client = planner
    states: list[PlanningSceneState] = []
    arrived = threading.Condition()

    def on_state(sample: zenoh.Sample) -> None:
        with arrived:
            states.append(PlanningSceneState.from_wire(sample.payload.to_bytes()))
            arrived.notify_all()

    subscriber = declare_latched_subscriber(session, client.keys.scene_state, on_state)  # after the planner started
    try:
        with arrived:
            assert arrived.wait_for(lambda: states, 5.0), "a late subscriber got no scene"
        assert states[-1].revision == 0 and states[-1].objects == () and states[-1].attached == ()
        vertices = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]])
        triangles = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        reply = client.scene(SceneRequest(operation="add", objects=(
            SceneObjectSpec("tetra", "mesh", (0.6, 0.3, 0.4), vertices_m=vertices, triangles=triangles),
            SceneObjectSpec("cup", "cylinder", (0.5, -0.3, 0.3), radius_m=0.04, length_m=0.1))))
        assert isinstance(reply, SceneResponse)
        with arrived:
            assert arrived.wait_for(lambda: states[-1].revision == 1, 5.0)
        tetra = next(o for o in states[-1].objects if o.name == "tetra")
        np.testing.assert_array_equal(tetra.vertices_m, vertices)
        np.testing.assert_array_equal(tetra.triangles, triangles)
        reply = client.scene(SceneRequest(operation="attach", names=("cup",), link="panda_hand",
                                          touch_links=("panda_leftfinger",), joint_positions=HOME))
        assert isinstance(reply, SceneResponse)
        with arrived:
            assert arrived.wait_for(lambda: states[-1].revision == 2, 5.0)
        (held,) = states[-1].attached
        assert held.link == "panda_hand" and held.touch_links == ("panda_leftfinger",)
        assert held.object.frame_id == "panda_hand" and [o.name for o in states[-1].objects] == ["tetra"]
        # Posed in the hand's frame: where the hand holds it at HOME is where it was added.
        world_from_cup = CONFIG_ROBOT.frame_pose(HOME, "panda_hand") @ make_transform(held.object.position_m,
                                                                                      held.object.quat_xyzw)
        np.testing.assert_allclose(world_from_cup[:3, 3], [0.5, -0.3, 0.3], atol=1e-9)
    finally:
        subscriber.undeclare()


def _quat_xyzw(rotation: np.ndarray) -> np.ndarray:
    import pinocchio as pin

    q = pin.Quaternion(rotation)
    return np.array([q.x, q.y, q.z, q.w])


def test_odd_joint_states_never_hold_back_the_default_start(planner: tuple[PlannerNode, zenoh.Session, RobonavClient]) -> None:
    """The default start is the latest complete joint state to arrive, whatever its stamp."""
    node, session, client = planner
    keys = client.keys
    _publish_until(session, keys.occupancy, _wall_map(-0.9, time.time()).to_wire(),
                   lambda: node._map_received_monotonic is not None)
    names = CONFIG.robot.joint_names

    def state(stamp: float, q: np.ndarray, joint_names: tuple[str, ...] = names) -> bytes:
        return JointState(stamp=stamp, names=joint_names, position=q, velocity=np.zeros(len(q))).to_wire()

    def start_of_plan() -> np.ndarray:
        reply = _on_a_fresh_map(node, session, keys.occupancy, lambda: client.plan(GOAL, allowed_planning_time=2.0, seed=1))
        assert isinstance(reply, PlanResponse), reply
        return reply.path[0]

    _publish_until(session, keys.joint_states, state(time.time(), HOME), lambda: node._joint_state is not None)
    # Incomplete ones (a joint missing, or other names) are dropped: the complete one stays the start.
    session.put(keys.joint_states, state(time.time(), HOME[:-1] + 0.1, names[:-1]))
    session.put(keys.joint_states, state(time.time(), HOME + 0.1, tuple(f"x_{n}" for n in names)))
    time.sleep(0.3)
    np.testing.assert_allclose(start_of_plan(), HOME)
    # One stamped far in the future, then an ordinary one: the ordinary one (the latest) is the start.
    moved = HOME + np.array([0.2, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0])
    session.put(keys.joint_states, state(time.time() + 1e6, moved))
    time.sleep(0.2)
    np.testing.assert_allclose(start_of_plan(), moved)
    session.put(keys.joint_states, state(time.time(), HOME))
    time.sleep(0.2)
    np.testing.assert_allclose(start_of_plan(), HOME)
    session.put(keys.joint_states, state(1.0, moved))  # stamped in 1970
    time.sleep(0.2)
    np.testing.assert_allclose(start_of_plan(), moved)


def test_the_robot_description_is_published_latched_for_discovery(
        planner: tuple[PlannerNode, zenoh.Session, RobonavClient]) -> None:
    node, session, _ = planner
    received: list[RobotDescription] = []
    sub = declare_latched_subscriber(session, Keys(CONFIG.cell).robot_description,
                                     lambda s: received.append(RobotDescription.from_wire(s.payload.to_bytes())))
    try:
        deadline = time.monotonic() + 10.0
        while not received and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        sub.undeclare()
    assert received, "no robot/description publication"
    description = received[0]
    assert description.joint_names == CONFIG.robot.joint_names and description.base_frame == CONFIG.robot.base_link
    assert description.end_effector_link == CONFIG.robot.end_effector_link and "<robot" in description.urdf
    np.testing.assert_array_equal(description.lower_limits, node.robot.lower_limits_rad)
    np.testing.assert_array_equal(description.upper_limits, node.robot.upper_limits_rad)
    np.testing.assert_array_equal(description.max_velocity, CONFIG.robot.max_velocity_rad_s)
    assert len(description.allowed_collision_pairs) == len(CONFIG.robot.allowed_collision_pairs)
