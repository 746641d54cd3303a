"""`robonav robot init`: a UR5 URDF + SRDF from a MoveIt configuration in, a robot file that plans out."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from robonav.pipeline.evaluation.mbm import parse_mbm
from robonav.pipeline.planning.ompl_planners import seed_ompl_once
from robonav.pipeline.robot.model import RobotModel
from robonav.services.bench.cli import main as bench_main
from robonav.services.bench.plan import run_plan_benchmark
from robonav.services.config import ConfigError, load_robot_file
from robonav.services.tools.robot import main

from ...conftest import REPO_ROOT

UR5_DIR = REPO_ROOT.parent / "shared" / "robots" / "ur5"
MBM_UR5_DIR = REPO_ROOT.parent / "shared" / "benchmarks" / "mbm-ur5"
UR5_JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
              "wrist_3_joint")


@pytest.fixture(scope="module")
def ur5_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("robots") / "ur5.yaml"
    code = main(["init", "--urdf", str(UR5_DIR / "ur5.urdf"), "--srdf", str(UR5_DIR / "ur5.srdf"), "--out", str(out)])
    assert code == 0
    return out


def test_init_writes_what_the_srdf_and_urdf_say(ur5_file: Path) -> None:
    text = ur5_file.read_text()
    data = yaml.safe_load(text)
    assert data["joint_names"] == list(UR5_JOINTS)
    assert data["base_link"] == "offset_link" and data["end_effector_link"] == "ee_link"
    assert data["home_position_rad"] == [0.0, -1.57, 0.0, -1.57, 0.0, 0.0]  # the SRDF's state 'home'
    assert data["max_velocity_rad_s"] == [0.5] * 6  # the URDF's <limit velocity>
    assert data["max_acceleration_rad_s2"] == [2.0] * 6 and data["max_jerk_rad_s3"] == [1000.0] * 6
    assert len(data["allowed_collision_pairs"]) == 88  # every <disable_collisions> of the SRDF
    assert ["base_link", "shoulder_link"] in data["allowed_collision_pairs"]
    assert not Path(data["urdf"]).is_absolute()  # relative to the file: it moves with its description
    assert "# CHECK" in text and "derived, 4/s x velocity" in text


def test_the_written_file_loads_and_plans_an_mbm_problem(ur5_file: Path) -> None:
    cfg = load_robot_file(ur5_file)
    robot = RobotModel.from_config(cfg)
    assert robot.joint_names == UR5_JOINTS and robot.static_link_names == ("base_link",)
    # The arm's base stands 0.9144 m above the root link, the world frame.
    assert robot.link_poses(robot.home_position_rad)["base_link"][2, 3] == pytest.approx(0.9144)
    problems = parse_mbm(json.loads((MBM_UR5_DIR / "box.json").read_text()))
    one = type(problems)(**{**problems.__dict__, "problems": problems.problems[1:2]})
    seed_ompl_once(1)
    record, = run_plan_benchmark([one], planner_id="rrtconnect", time_limit_s=5.0, seed=1, padding_m=0.0, robot=cfg)
    assert record.solved, record.detail
    assert record.path_valid and record.returned_path


def test_missing_keys_of_another_robot_are_named_together(tmp_path: Path) -> None:
    file = tmp_path / "partial.yaml"
    file.write_text(f"name: ur5\nurdf: {UR5_DIR / 'ur5.urdf'}\njoint_names: [{', '.join(UR5_JOINTS)}]\n")
    with pytest.raises(ConfigError) as info:
        load_robot_file(file)
    for key in ("base_link", "end_effector_link", "max_velocity_rad_s", "max_acceleration_rad_s2",
                "max_jerk_rad_s3", "home_position_rad"):
        assert key in str(info.value)


def test_init_without_srdf_samples_the_collision_matrix(tmp_path: Path) -> None:
    out = tmp_path / "ur5_bare.yaml"
    code = main(["init", "--urdf", str(UR5_DIR / "ur5.urdf"), "--tip", "ee_link", "--acm-samples", "200",
                 "--out", str(out)])
    assert code == 0
    data = yaml.safe_load(out.read_text())
    assert data["joint_names"] == list(UR5_JOINTS)
    pairs = {tuple(p) for p in data["allowed_collision_pairs"]}
    assert ("base_link", "shoulder_link") in pairs  # adjacent
    assert "adjacent" in out.read_text() and "never" in out.read_text()
    assert data["home_position_rad"] == [0.0] * 6
    assert np.all(np.isfinite(data["max_velocity_rad_s"]))


def test_bad_input_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["init", "--urdf", str(UR5_DIR / "ur5.urdf"), "--srdf", str(UR5_DIR / "ur5.srdf"),
                 "--group", "arm", "--out", str(tmp_path / "x.yaml")])
    assert code == 2
    assert "SRDF has no group 'arm'" in capsys.readouterr().err


def test_the_shipped_ur5_file_is_what_init_writes(ur5_file: Path) -> None:
    """configs/ur5.yaml is `robonav robot init` output for ../shared/robots/ur5 (regenerate it if this fails)."""
    shipped, fresh = load_robot_file(REPO_ROOT / "configs" / "ur5.yaml"), load_robot_file(ur5_file)
    assert Path(shipped.urdf).resolve() == Path(fresh.urdf).resolve()
    assert dataclasses.replace(shipped, urdf=fresh.urdf) == fresh


def test_bench_plan_takes_the_robot_file(ur5_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bench.json"
    args = ["plan", "--problems", str(MBM_UR5_DIR), "--families", "box", "--limit", "1", "--time-limit", "1",
            "--robot", str(ur5_file), "--no-progress", "--json", str(out)]
    assert bench_main(args) == 0
    report = json.loads(out.read_text())
    assert report["config"]["robot"] == "ur5_robotiq85" and report["overall"]["problems"] == 1
    assert report["overall"]["invalid_paths"] == 0
    # Problems of another robot are refused by name, before any planning.
    panda_problems = REPO_ROOT.parent / "shared" / "benchmarks" / "mbm"
    assert bench_main(["plan", "--problems", str(panda_problems), "--families", "box", "--limit", "1",
                       "--robot", str(ur5_file), "--no-progress"]) == 2
    assert "differ from robot 'ur5_robotiq85' config's" in capsys.readouterr().err
