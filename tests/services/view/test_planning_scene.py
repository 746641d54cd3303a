"""The view shows what the planner knows: its objects (attached ones following the arm) from the
latched `planner/scene_state`, and after a plan refused with START/GOAL_IN_COLLISION the links
and objects the reply names, in red; over real Zenoh, and against the live planner."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("viser", reason="the `view` extra (viser) is not installed")

from robonav.pipeline.robot.model import RobotModel  # noqa: E402
from robonav.pipeline.wire.messages import (  # noqa: E402
    AttachedObjectSpec,
    ErrorReply,
    JointState,
    PlanningSceneState,
    SceneObjectSpec,
    SceneRequest,
    SceneResponse,
)
from robonav.services.client import RobonavClient  # noqa: E402
from robonav.services.common import declare_latched_publisher, open_session  # noqa: E402
from robonav.services.config import ZenohConfig, load_config  # noqa: E402
from robonav.services.keys import Keys  # noqa: E402
from robonav.services.view.app import ViewNode, ViewOptions  # noqa: E402
from robonav.services.view.planning_scene import (  # noqa: E402
    ATTACHED_RGB,
    COLLIDING_RGB,
    OBJECT_RGB,
    collision_from_details,
)
from robonav.services.view.scene import wxyz_of  # noqa: E402

from ..conftest import free_port  # noqa: E402

CONFIG = load_config()
NAMES = tuple(CONFIG.robot.joint_names)
GOALS = np.array(CONFIG.demo.goals_rad)
ROBOT = RobotModel.from_config(CONFIG.robot)
LINKS = ROBOT.link_names


@pytest.fixture
def endpoint() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    yield endpoint
    router.close()


def test_collision_details_sort_links_objects_and_the_map() -> None:
    collision = collision_from_details({"pairs": ["panda_hand|crate", "panda_link7|occupancy", "tool|panda_link5",
                                                  "panda_hand|crate", 7, "no bar"],
                                        "which": "goal", "positions": GOALS[0].tolist()}, LINKS, 7)
    assert collision.links == ("panda_hand", "panda_link7", "panda_link5")
    assert collision.objects == ("crate", "tool") and collision.occupancy and collision.which == "goal"
    np.testing.assert_array_equal(collision.positions, GOALS[0])
    # An older planner's reply (no positions) or a malformed one: names only, nothing raised.
    for details in ({"pairs": ["panda_hand|crate"]}, {"pairs": "x", "positions": [1, 2]},
                    {"positions": [float("nan")] * 7}, {"positions": ["a"] * 7}):
        assert collision_from_details(details, LINKS, 7).positions is None


def test_the_view_draws_planner_objects_and_marks_what_collides(endpoint: str) -> None:
    cfg = dataclasses.replace(CONFIG, zenoh=ZenohConfig(connect=(endpoint,)))
    keys = Keys(cfg.cell)
    publisher = open_session(cfg.zenoh)
    tool = SceneObjectSpec("tool", "sphere", (0.0, 0.0, 0.12), radius_m=0.02, frame_id="panda_hand")
    scene = PlanningSceneState(stamp=time.time(), revision=3, objects=(
        SceneObjectSpec("crate", "box", (0.5, 0.3, 0.1), size_m=(0.2, 0.2, 0.2)),
        SceneObjectSpec("rod", "capsule", (0.5, -0.3, 0.2), radius_m=0.03, length_m=0.3),
        SceneObjectSpec("plate", "mesh", (0.0, 0.6, 0.0), vertices_m=np.array([[0, 0, 0], [0.2, 0, 0], [0, 0.2, 0.0]]),
                        triangles=np.array([[0, 1, 2]])),
    ), attached=(AttachedObjectSpec("panda_hand", tool),))
    # Published before the view exists: latched, so the view must still get it.
    scene_pub = declare_latched_publisher(publisher, keys.scene_state)
    scene_pub.put(scene.to_wire())
    view_session = open_session(cfg.zenoh)
    node = ViewNode(cfg, view_session, ViewOptions(port=0))
    node.start()
    stop = threading.Event()

    def joint_states() -> None:
        while not stop.wait(0.01):
            publisher.put(keys.joint_states, JointState(stamp=time.time(), names=NAMES, position=GOALS[1],
                                                        velocity=np.zeros(7)).to_wire())

    thread = threading.Thread(target=joint_states, daemon=True)
    thread.start()
    planning = node.layers.planning
    try:
        assert node.wait_until(lambda: node.stats.scenes_drawn and node.stats.robot_updates, 10.0), node.stats
        assert set(planning.object_names) == {"crate", "rod", "plate", "tool"}
        assert planning.object_color("crate") == OBJECT_RGB and planning.object_color("tool") == ATTACHED_RGB
        assert len(planning._nodes["rod"]) == 3  # a capsule: a cylinder and two spheres
        # The attached tool sits in the hand's frame, wherever the arm is.
        link, frame = planning._attached["tool"]
        hand = ROBOT.frame_pose(GOALS[1], "panda_hand")
        assert link == "panda_hand"
        np.testing.assert_allclose(frame.position, hand[:3, 3], atol=1e-6)
        np.testing.assert_allclose(np.abs(frame.wxyz), np.abs(wxyz_of(hand[:3, :3])), atol=1e-6)

        # A goal the planner refused: the named links are drawn red at the goal, the crate turns
        # red, the ghost shows the goal; the text names them.
        reply = ErrorReply(code="GOAL_IN_COLLISION", message="goal is in collision: panda_hand|crate", details={
            "pairs": ["panda_hand|crate", "panda_leftfinger|crate"], "which": "goal", "positions": GOALS[0].tolist()})
        text = node.controls._show_collision(reply)
        assert "panda_hand" in text and "crate" in text
        assert planning.highlighted_links == ("panda_hand", "panda_leftfinger")
        assert planning.object_color("crate") == COLLIDING_RGB and planning.object_color("rod") == OBJECT_RGB
        assert node.layers.roots["ghost"].visible
        # A newer scene keeps the mark on objects still named; clearing restores the colours.
        scene_pub.put(dataclasses.replace(scene, revision=4).to_wire())
        assert node.wait_until(lambda: node.stats.scenes_drawn >= 2, 5.0), node.stats
        assert planning.object_color("crate") == COLLIDING_RGB
        planning.clear_collision()
        assert planning.highlighted_links == () and planning.object_color("crate") == OBJECT_RGB
        # A bad scene sample is counted, not fatal; an empty scene removes every object.
        scene_pub.put(b"\x00not a scene")
        scene_pub.put(PlanningSceneState(stamp=time.time(), revision=5).to_wire())
        assert node.wait_until(lambda: node.stats.errors.get("planning scene", 0) >= 1
                               and not planning.object_names, 5.0), node.stats
    finally:
        stop.set()
        thread.join()
        node.close()
        view_session.close()
        publisher.close()


def test_a_gui_plan_into_an_object_marks_the_links_and_the_object(client: RobonavClient, stack_config: Path) -> None:
    """The live planner refuses a Cartesian goal inside a planner object with GOAL_IN_COLLISION;
    the view draws the links its nearest IK solution puts there, and the object, in red."""
    cfg = load_config(stack_config)
    session = open_session(cfg.zenoh)
    node = ViewNode(cfg, session, ViewOptions(port=0))
    node.start()
    ee = cfg.robot.end_effector_link
    # The stack is shared: the arm may stand at any demo goal. Block the one farthest from it,
    # so the refusal is the goal's and not the start's.
    assert client.wait_for(lambda: client.joint_state is not None, 10.0)
    now = client.joint_state.position
    goal = ROBOT.frame_pose(max(GOALS, key=lambda q: float(np.abs(q - now).max())), ee)
    added = client.scene(SceneRequest(operation="add", objects=(
        SceneObjectSpec("view_block", "box", tuple(goal[:3, 3]), size_m=(0.12, 0.12, 0.12)),)))
    assert isinstance(added, SceneResponse), added
    try:
        planning = node.layers.planning
        assert node.wait_until(lambda: "view_block" in planning.object_names and node.stats.robot_updates > 0,
                               30.0), node.stats
        node.controls.gizmo.position = goal[:3, 3]
        node.controls.gizmo.wxyz = wxyz_of(goal[:3, :3])
        text = node.controls.plan()
        assert text.startswith("plan failed: `GOAL_IN_COLLISION`") and "view_block" in text, text
        assert planning.object_color("view_block") == COLLIDING_RGB
        assert planning.highlighted_links and set(planning.highlighted_links) <= LINKS, planning.highlighted_links
        assert ee in planning.highlighted_links or any("finger" in link for link in planning.highlighted_links)
        assert node.layers.roots["ghost"].visible
        removed = client.scene(SceneRequest(operation="remove", names=("view_block",)))
        assert isinstance(removed, SceneResponse), removed
        assert node.wait_until(lambda: "view_block" not in planning.object_names, 10.0)
        text = node.controls.plan()
        assert text.startswith("planned"), text
        assert planning.highlighted_links == () and planning.collision is None
    finally:
        client.scene(SceneRequest(operation="remove", names=("view_block",)))
        node.close()
        session.close()
