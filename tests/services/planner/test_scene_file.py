"""The planning scene saved to a file and loaded back by a new scene, as a restarted planner does.

The process-level check (a planner killed and restarted by `robonav up`) is in
tests/services/stack/test_restart.py; here the file itself: what it keeps, and that a bad file
or an unwritable place never stops the scene from serving.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.wire.messages import SceneObjectSpec, SceneRequest, SceneResponse
from robonav.services.planner.scene import PlanningScene
from robonav.services.planner.scene_file import SceneFile

HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
TETRA_VERTICES = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]])
TETRA_TRIANGLES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int64)


def _scene(panda: RobotModel, path: Path | None) -> tuple[PlanningScene, CollisionWorld]:
    world = CollisionWorld(panda)
    return PlanningScene(world, threading.Lock(), current_q=lambda: HOME,
                         scene_file=None if path is None else SceneFile(path)), world


def _build(scene: PlanningScene) -> SceneResponse:
    scene.apply(SceneRequest(operation="add", objects=(
        SceneObjectSpec("shelf", "box", (0.6, 0.0, 0.4), (0.0, 0.0, 0.3826834, 0.9238795), size_m=(0.3, 0.6, 0.02)),
        SceneObjectSpec("tetra", "mesh", (0.4, -0.3, 0.2), vertices_m=TETRA_VERTICES, triangles=TETRA_TRIANGLES),
        SceneObjectSpec("can", "cylinder", (0.5, 0.3, 0.1), radius_m=0.04, length_m=0.12),
    )))
    # One object taken from the world at the robot's state, one new in the link's frame.
    scene.apply(SceneRequest(operation="attach", names=("can",), link="panda_hand", touch_links=("panda_leftfinger",)))
    scene.apply(SceneRequest(operation="attach", link="panda_hand", objects=(
        SceneObjectSpec("tool", "capsule", (0.0, 0.0, 0.1), radius_m=0.01, length_m=0.05, frame_id="panda_hand"),)))
    return scene.apply(SceneRequest(operation="move", objects=(SceneObjectSpec("shelf", position_m=(0.65, 0.0, 0.4)),)))


def test_a_new_scene_on_the_same_file_has_every_object_pose_and_the_revision(panda: RobotModel, tmp_path: Path) -> None:
    path = tmp_path / "state" / "scene.msgpack"  # the folder is made on the first save
    first, _ = _scene(panda, path)
    before = _build(first)
    assert path.is_file() and before.revision == 4

    second, world = _scene(panda, path)
    after = second.apply(SceneRequest(operation="list"))
    assert after.revision == before.revision
    assert [o.name for o in after.objects] == ["shelf", "tetra", "can", "tool"]
    for a, b in zip(before.objects, after.objects, strict=True):
        assert (a.name, a.type, a.frame_id, a.attached_link, a.touch_links, a.vertex_count) == \
            (b.name, b.type, b.frame_id, b.attached_link, b.touch_links, b.vertex_count)
        np.testing.assert_allclose(a.position_m, b.position_m, atol=1e-12)
        np.testing.assert_allclose(a.quat_xyzw, b.quat_xyzw, atol=1e-12)
    # The restored objects are in the collision world, not only in the reply: every state collides
    # with the same things as in a world built by the requests themselves.
    assert {a.name for a in world.attached_objects} == {"can", "tool"}
    reference = _world_without_file(panda)
    rng = np.random.default_rng(3)
    states = rng.uniform(panda.lower_limits_rad, panda.upper_limits_rad, size=(60, panda.dof))
    pairs = [sorted(world.collisions(q)) for q in states]
    assert pairs == [sorted(reference.collisions(q)) for q in states]
    assert any(p.endswith(("|shelf", "|tetra")) or p.startswith("can|") for q_pairs in pairs for p in map("|".join, q_pairs))

    second.apply(SceneRequest(operation="clear"))
    third, world = _scene(panda, path)
    listed = third.apply(SceneRequest(operation="list"))
    assert listed.objects == () and listed.revision == before.revision + 1 and world.attached_objects == ()


def _world_without_file(panda: RobotModel) -> CollisionWorld:
    scene, world = _scene(panda, None)
    _build(scene)
    return world


def test_an_unreadable_file_is_moved_aside_and_the_scene_starts_empty(panda: RobotModel, tmp_path: Path) -> None:
    path = tmp_path / "scene.msgpack"
    path.write_bytes(b"\x92\x01garbage that is not a scene")
    scene, _ = _scene(panda, path)
    listed = scene.apply(SceneRequest(operation="list"))
    assert listed.objects == () and listed.revision == 0
    assert (tmp_path / "scene.msgpack.unreadable").is_file() and not path.exists()
    scene.apply(SceneRequest(operation="add", objects=(SceneObjectSpec("b", "box", (0.5, 0, 0.5), size_m=(0.1, 0.1, 0.1)),)))
    assert path.is_file()  # and it saves again


def test_a_scene_that_cannot_be_saved_still_serves(panda: RobotModel, tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the folder should be", encoding="utf-8")
    scene, world = _scene(panda, blocker / "scene.msgpack")
    reply = scene.apply(SceneRequest(operation="add", objects=(SceneObjectSpec("b", "box", (0.5, 0, 0.5), size_m=(0.1, 0.1, 0.1)),)))
    assert reply.revision == 1 and [o.name for o in reply.objects] == ["b"]
    assert world.object_names == ("b",)


@pytest.mark.parametrize("missing", [True, False], ids=["no-file", "empty-scene"])
def test_no_saved_scene_is_an_empty_scene(panda: RobotModel, tmp_path: Path, missing: bool) -> None:
    path = tmp_path / "scene.msgpack"
    if not missing:
        _scene(panda, path)[0].apply(SceneRequest(operation="clear"))
    listed = _scene(panda, path)[0].apply(SceneRequest(operation="list"))
    assert listed.objects == () and listed.revision == (0 if missing else 1)
