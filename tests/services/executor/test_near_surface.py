"""A goal a centimetre above a perceived shelf, through the real planner and executor services.

The map is what the perception core builds and the service publishes: a 2 cm octree inflated
by 2 cm, its seen voxels and (the field this is about) `inflation_m`. Planned against the
inflated map as it is, the goal is GOAL_IN_COLLISION; told the inflation, the planner releases
it near the goal and plans, and the executor runs the path to the goal. A goal that really
touches the shelf, and a motion through it, are still refused. A fake robot echoes setpoints
as joint states.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh

from robonav.pipeline.perception.maps.octree import OccupancyMap
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.wire.messages import ErrorReply, ExecuteResponse, Occupancy, PlanResponse
from robonav.services.client import RobonavClient
from robonav.services.common import declare_latched_publisher, open_session
from robonav.services.config import ZenohConfig, load_config
from robonav.services.executor.node import ExecutorNode
from robonav.services.planner.node import PlannerNode

from ..conftest import free_port, wait_until_served
from .test_node import FakeRobot

CONFIG = load_config()
ROBOT = RobotModel.from_config(CONFIG.robot)
HOME = np.array(CONFIG.robot.home_position_rad)
NAMES = tuple(CONFIG.robot.joint_names)
VOXEL_M = CONFIG.perception.resolution_m
HAND_LINKS = ("panda_hand", "panda_leftfinger", "panda_rightfinger")


def _hand_lowest_z(q: np.ndarray) -> float:
    poses = ROBOT.link_poses(q)
    return min(float(((vertices @ poses[link][:3, :3].T) + poses[link][:3, 3])[:, 2].min())
               for link, vertices in ROBOT.link_hull_vertices.items() if link in HAND_LINKS)


def _shelf_and_goal(bare_gap_m: float) -> tuple[float, np.ndarray]:
    """A shelf height with its voxel's top face 2 mm above it, and a goal (the demo's first,
    shoulder lowered) whose bare fingers are `bare_gap_m` above the shelf."""
    goal = np.array(CONFIG.demo.goals_rad[0])
    layer = math.floor((_hand_lowest_z(goal) - bare_gap_m - 0.9 * VOXEL_M) / VOXEL_M)
    shelf_z = layer * VOXEL_M + 0.9 * VOXEL_M
    low, high = 0.0, 0.4  # lowering the shoulder lowers the hand
    for _ in range(40):
        middle = 0.5 * (low + high)
        q = goal.copy()
        q[1] += middle
        low, high = (middle, high) if _hand_lowest_z(q) - shelf_z > bare_gap_m else (low, middle)
    goal[1] += low
    return shelf_z, goal


def _shelf_map(shelf_z: float, goal: np.ndarray, *, inflation_on_wire: bool) -> Occupancy:
    """The perception core's map of a 30 cm square shelf under the goal's hand, seen from above."""
    hand = ROBOT.frame_pose(goal, CONFIG.robot.end_effector_link)[:3, 3]
    xs, ys = np.meshgrid(np.arange(hand[0] - 0.15, hand[0] + 0.15, 0.005), np.arange(hand[1] - 0.15, hand[1] + 0.15, 0.005))
    points = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, shelf_z)])
    occupancy = OccupancyMap(CONFIG.perception)
    occupancy.insert(points, np.array([hand[0], hand[1], shelf_z + 1.0]))
    return Occupancy(stamp=time.time(), resolution_m=VOXEL_M, octomap_binary=occupancy.planning_binary(),
                     occupied_centers_m=occupancy.occupied_centers_m().astype(np.float32),
                     inflation_m=CONFIG.perception.inflation_m if inflation_on_wire else None)


@pytest.fixture
def cell() -> Iterator[tuple[PlannerNode, ExecutorNode, zenoh.Session, RobonavClient, FakeRobot]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    cfg = dataclasses.replace(CONFIG, zenoh=ZenohConfig(connect=(endpoint,)),
                              planner=dataclasses.replace(CONFIG.planner, workers=1, first_map_wait_s=0.5))
    planner_session, executor_session, client_session = (open_session(cfg.zenoh) for _ in range(3))
    planner = PlannerNode(cfg, planner_session)
    executor = ExecutorNode(cfg, executor_session)
    stop = threading.Event()
    spinner = threading.Thread(target=executor.spin, args=(stop,), daemon=True)
    spinner.start()
    client = RobonavClient(client_session)
    robot = FakeRobot(client_session, client)
    for key in (client.keys.plan, client.keys.execute):
        wait_until_served(client_session, key)
    assert client.wait_for(lambda: executor._measured_q is not None, 5.0), "joint states never reached the executor"
    yield planner, executor, client_session, client, robot
    robot.close()
    stop.set()
    spinner.join(timeout=5.0)
    client.close()
    executor.close()
    planner.close()
    for s in (client_session, executor_session, planner_session, router):
        s.close()


def _publish_map(session: zenoh.Session, client: RobonavClient, publisher, occupancy: Occupancy,  # noqa: ANN001
                 nodes: tuple[PlannerNode, ExecutorNode]) -> None:
    publisher.put(occupancy.to_wire())
    planner, executor = nodes
    assert client.wait_for(lambda: planner._newest_map is not None and planner._newest_map.seq == occupancy.seq
                           and executor.maps.newest() is not None and executor.maps.newest().seq == occupancy.seq, 5.0)


def test_a_goal_a_centimetre_above_a_seen_shelf_is_planned_and_executed(cell) -> None:  # noqa: ANN001
    planner, executor, session, client, robot = cell
    shelf_z, goal = _shelf_and_goal(bare_gap_m=CONFIG.robot.padding_m + 0.01)
    assert abs(_hand_lowest_z(goal) - shelf_z - 0.02) < 1e-6  # the padded fingers 1 cm above the shelf
    publisher = declare_latched_publisher(session, client.keys.occupancy)
    try:
        # The inflated map alone (a producer that does not say its inflation) swallows the goal.
        _publish_map(session, client, publisher, dataclasses.replace(_shelf_map(shelf_z, goal, inflation_on_wire=False),
                                                                     seq=1), (planner, executor))
        refused = client.plan(goal, seed=1)
        assert isinstance(refused, ErrorReply) and refused.code == "GOAL_IN_COLLISION", refused
        assert any(p.endswith("|occupancy") for p in refused.details["pairs"])

        told = dataclasses.replace(_shelf_map(shelf_z, goal, inflation_on_wire=True), seq=2)
        _publish_map(session, client, publisher, told, (planner, executor))
        plan = client.plan(goal, seed=1)
        assert isinstance(plan, PlanResponse), plan
        assert np.allclose(plan.path[-1], goal) and np.allclose(plan.path[0], HOME, atol=1e-6)

        # The executor's check and its path monitor accept the plan: the arm reaches the goal.
        started = client.execute(plan.path, trajectory_id="to-shelf")
        assert isinstance(started, ExecuteResponse), started
        for _ in range(3):  # live maps while it moves: the same shelf, seen again
            publisher.put(dataclasses.replace(told, stamp=time.time()).to_wire())
            time.sleep(0.1)
        assert client.wait_for_trajectory("to-shelf", 30.0) == "succeeded"
        assert np.allclose(robot.position, goal, atol=1e-4)

        # A motion into the shelf is refused by the executor: 2 cm further down than the goal.
        into = goal.copy()
        into[1] += 0.1
        assert _hand_lowest_z(into) < shelf_z
        refused = client.execute(np.array([robot.position, into]))
        assert isinstance(refused, ErrorReply) and refused.code == "PATH_IN_COLLISION", refused
        assert any(p.endswith("|occupancy") for p in refused.details["pairs"])

        # A goal whose padded fingers reach into what was seen is still GOAL_IN_COLLISION.
        near_z, touching = _shelf_and_goal(bare_gap_m=0.5 * CONFIG.robot.padding_m)
        _publish_map(session, client, publisher, dataclasses.replace(_shelf_map(near_z, touching, inflation_on_wire=True),
                                                                     seq=3), (planner, executor))
        refused = client.plan(touching, start_positions=HOME, joint_names=NAMES, seed=1)
        assert isinstance(refused, ErrorReply) and refused.code == "GOAL_IN_COLLISION", refused
        assert any(p.split("|")[0] in HAND_LINKS and p.endswith("|occupancy") for p in refused.details["pairs"])
    finally:
        publisher.undeclare()
