"""Scripted obstacle motion: triggers by time and by executor progress, slides, adds, removals."""

from __future__ import annotations

import numpy as np
import pytest

from robonav.pipeline.config import ConfigError, from_mapping
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.motion import MotionScript, ObjectMotion, Pose

BOX = SceneObject("box", "box", (0.5, 0.6, 0.3), size_m=(0.1, 0.1, 0.1))


class Poses:
    """A stand-in world: object poses by name, changed by the script's steps."""

    def __init__(self, *objects: SceneObject) -> None:
        self.poses: dict[str, Pose] = {o.name: (np.array(o.position_m), np.array(o.quat_xyzw)) for o in objects}

    def get(self, name: str) -> Pose | None:
        return self.poses.get(name)

    def run(self, script: MotionScript, now_s: float) -> list[str]:
        kinds = []
        for step in script.advance(now_s, self.get):
            kinds.append(step.kind)
            if step.kind == "pose":
                self.poses[step.name] = (step.position_m, step.quat_xyzw)
            elif step.kind == "remove":
                del self.poses[step.name]
            else:
                assert step.object is not None
                self.poses[step.name] = (np.array(step.object.position_m), np.array(step.object.quat_xyzw))
        return kinds


def test_a_timed_slide_moves_at_constant_speed_and_ends_on_the_target() -> None:
    world, script = Poses(BOX), MotionScript()
    turn = (0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4))
    script.arm([ObjectMotion("box", position_m=(0.5, 0.0, 0.3), quat_xyzw=turn, duration_s=2.0, at_s=1.0)], now_s=10.0)
    assert world.run(script, 10.5) == [] and script.pending == 1 and script.fired == 0
    world.run(script, 11.0)  # fires: starts from where the box is
    np.testing.assert_allclose(world.poses["box"][0], BOX.position_m)
    world.run(script, 12.0)
    np.testing.assert_allclose(world.poses["box"][0], (0.5, 0.3, 0.3))
    angle = 2 * np.arccos(world.poses["box"][1][3])
    assert angle == pytest.approx(np.pi / 4)  # halfway through a quarter turn
    world.run(script, 13.5)
    np.testing.assert_allclose(world.poses["box"][0], (0.5, 0.0, 0.3))
    np.testing.assert_allclose(world.poses["box"][1], turn, atol=1e-12)
    assert script.pending == 0 and script.fired == 1


def test_progress_triggers_need_an_executing_trajectory_past_the_fraction() -> None:
    world, script = Poses(BOX), MotionScript()
    script.arm([ObjectMotion("box", position_m=(0.5, 0.0, 0.3), at_progress=0.4, trajectory_id="t2")], now_s=0.0)
    script.on_progress("t1", "executing", 0.9)  # another trajectory
    script.on_progress("t2", "idle", 1.0)  # not executing
    script.on_progress("t2", "executing", 0.3)  # not far enough
    assert world.run(script, 1.0) == []
    script.on_progress("t2", "executing", 0.45)
    assert world.run(script, 1.1) == ["pose"]
    np.testing.assert_allclose(world.poses["box"][0], (0.5, 0.0, 0.3))  # duration 0 jumps
    any_trajectory = MotionScript()
    any_trajectory.arm([ObjectMotion("box", action="remove", at_progress=0.1)], now_s=0.0)
    any_trajectory.on_progress("whatever", "executing", 0.2)
    assert world.run(any_trajectory, 1.2) == ["remove"] and "box" not in world.poses


def test_add_then_remove_and_missing_objects_are_skipped() -> None:
    world, script = Poses(), MotionScript()
    script.arm([ObjectMotion("box", action="add", object=BOX),
                ObjectMotion("ghost", position_m=(0.0, 0.0, 1.0)),
                ObjectMotion("box", action="remove", at_s=0.5)], now_s=0.0)
    assert world.run(script, 0.0) == ["add"]
    assert "box" in world.poses and script.skipped and "ghost" in script.skipped[0]
    assert world.run(script, 0.5) == ["remove"] and not world.poses
    assert script.fired == 3 and script.pending == 0
    script.arm([ObjectMotion("box", action="remove", at_s=5.0)], now_s=1.0)
    assert script.cancel() == 1 and script.pending == 0


def test_motions_are_validated_and_load_from_config() -> None:
    loaded = from_mapping(ObjectMotion, {
        "name": "crate", "action": "add", "at_progress": 0.3,
        "object": {"name": "crate", "type": "box", "position_m": [0.5, 0.0, 0.5], "size_m": [0.1, 0.1, 0.1]}},
        key="sim.motions[0]")
    assert loaded.object is not None and loaded.object.type == "box"
    with pytest.raises(ValueError, match="not both"):
        ObjectMotion("box", position_m=(0, 0, 0), at_s=1.0, at_progress=0.5)
    with pytest.raises(ValueError, match="needs position_m or quat_xyzw"):
        ObjectMotion("box")
    with pytest.raises(ValueError, match="add needs"):
        ObjectMotion("box", action="add")
    with pytest.raises(ValueError, match="at_progress"):
        ObjectMotion("box", action="remove", at_progress=1.5)
    with pytest.raises(ConfigError, match="sim.motions\\[0\\].speed"):
        from_mapping(ObjectMotion, {"name": "box", "speed": 1}, key="sim.motions[0]")
