"""`--robot FILE`: the stack's config for another robot, its cell placed for the robot's reach,
goals drawn for it; a robot with a continuous and prismatic joints end to end through `robonav demo`."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.config import ConfigError
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.sim.cell import robot_reach
from robonav.pipeline.sim.scenes import clutter_scene
from robonav.services.config import load_config
from robonav.services.stack.robot_cell import demo_goals, read_robot, with_robot, write_config

from ...conftest import REPO_ROOT
from ..conftest import TURN_LIFT_REACH_ROBOT_FILE as ROBOT_FILE
from ..conftest import free_port, write_turn_lift_reach
from ..conftest import write_config as write_test_config

pytestmark = pytest.mark.e2e


@pytest.fixture()
def robot_file(tmp_path: Path) -> Path:
    return write_turn_lift_reach(tmp_path)


def test_read_robot_takes_a_robot_file_or_the_robot_of_a_config(robot_file: Path, tmp_path: Path) -> None:
    robot = read_robot(robot_file)
    assert robot.joint_names == ("turn", "lift", "reach") and Path(robot.urdf).is_absolute()
    assert read_robot(REPO_ROOT / "configs" / "iiwa.yaml") == load_config(REPO_ROOT / "configs" / "iiwa.yaml").robot
    broken = tmp_path / "broken.yaml"
    broken.write_text(ROBOT_FILE.replace("end_effector_link: tool", "end_effector_link: claw"), encoding="utf-8")
    with pytest.raises(ConfigError, match="claw"):
        read_robot(broken)
    with pytest.raises(ConfigError, match="cannot read"):
        read_robot(tmp_path / "missing.yaml")


def test_the_configs_own_robot_keeps_its_cell_and_goals() -> None:
    cfg = load_config()
    assert with_robot(cfg, cfg.robot) is cfg


def test_another_robot_gets_the_cell_placed_for_its_reach(robot_file: Path, tmp_path: Path) -> None:
    base = load_config()
    robot = read_robot(robot_file)
    cfg = with_robot(base, robot)
    assert cfg.robot == robot and cfg.demo.goals_rad == ()
    panda, other = robot_reach(RobotModel.from_config(base.robot)), robot_reach(RobotModel.from_config(robot))
    np.testing.assert_allclose(other.shoulder_m, [0.0, 0.0, 0.25 + 0.2])  # the lift joint's frame at home
    scale = other.reach_m / panda.reach_m

    def relative(point: tuple[float, ...], reach: object) -> np.ndarray:
        return (np.asarray(point) - np.asarray(reach.shoulder_m)) / reach.reach_m  # type: ignore[attr-defined]

    # Every object, camera and the workspace keep their place relative to the shoulder, in reaches.
    for before, after in zip(base.sim.objects, cfg.sim.objects):
        np.testing.assert_allclose(relative(after.position_m, other), relative(before.position_m, panda), atol=1e-3)
        if before.size_m is not None:
            np.testing.assert_allclose(after.size_m, np.asarray(before.size_m) * scale, atol=1e-3)
    for before, after in zip(base.cameras, cfg.cameras):
        np.testing.assert_allclose(relative(after.position_m, other), relative(before.position_m, panda), atol=1e-3)
        assert after.quat_xyzw == before.quat_xyzw
    np.testing.assert_allclose(relative(cfg.perception.workspace_min_m, other),
                               relative(base.perception.workspace_min_m, panda), atol=1e-3)
    # The campaign's clutter stands within the robot's reach, clear of its base.
    for seed in range(5):
        for obj in clutter_scene(cfg.sim.clutter, np.random.default_rng(seed)).objects:
            assert np.linalg.norm(np.subtract(obj.position_m, other.shoulder_m)) < 1.5 * other.reach_m, obj.name
    assert write_config(cfg, tmp_path / "placed.yaml") and load_config(tmp_path / "placed.yaml") == cfg


def test_demo_goals_are_free_reachable_and_seeded(robot_file: Path) -> None:
    cfg = with_robot(load_config(), read_robot(robot_file))
    goals = demo_goals(cfg, seed=4)
    assert len(goals) == 3 and goals == demo_goals(cfg, seed=4)
    robot = RobotModel.from_config(cfg.robot)
    truth = CollisionWorld(robot, padding_m=0.0)
    truth.set_objects(cfg.sim.objects)
    table = next(o for o in cfg.sim.objects if o.name == "table")
    top_z = table.position_m[2] + table.size_m[2] / 2.0  # type: ignore[index]
    margin = cfg.robot.padding_m + cfg.perception.inflation_m + math.sqrt(3.0) * cfg.perception.resolution_m
    for goal in goals:
        q = np.asarray(goal)
        assert not np.any(robot.check_joint_limits(q))
        assert truth.clearance_m(q) >= margin - 1e-6
        assert robot.frame_pose(q, "tool")[2, 3] >= top_z + 0.05
    assert max(abs(g[0]) for g in goals) > 0.0 and demo_goals(cfg, seed=5) != goals


def test_demo_runs_a_continuous_and_prismatic_robot_end_to_end(robot_file: Path, tmp_path: Path) -> None:
    """sim (pybullet loads the URDF), perception's self filter, planner and executor limits:
    the drawn goals are reached, nothing touched."""
    config = write_test_config(tmp_path, "stack.yaml", zenoh={"connect": [f"tcp/127.0.0.1:{free_port()}"]})
    out = tmp_path / "demo.json"
    run = subprocess.run([sys.executable, "-m", "robonav.services.cli", "demo", "--robot", str(robot_file),
                          "--config", str(config), "--seed", "2", "--json", str(out)],
                         capture_output=True, text=True, timeout=400)
    assert run.returncode == 0, run.stderr[-3000:]
    summary = json.loads(out.read_text())
    assert summary["goal_count"] == 3 and summary["reached"] == 3 and summary["contacts"] == 0
    drawn = yaml.safe_load(robot_file.read_text())["joint_names"]
    assert len(summary["goals"][0]["goal_rad"]) == len(drawn)
