"""`mbm-primitives/1` parsing on the real MotionBenchMaker files, the MBM Panda model, malformed documents."""

from __future__ import annotations

import copy
import dataclasses
import json
from typing import Any

import numpy as np
import pytest

from robonav.pipeline.evaluation.mbm import MBM_PANDA_POSITION_LIMITS_RAD, MbmProblemSet, mbm_robot_config, parse_mbm
from robonav.pipeline.evaluation.mesh_check import MeshCollisionChecker
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import PoseSpec

from ...conftest import MBM_DIR

"""The shared benchmark data (../shared/benchmarks/mbm next to the repository)."""
OBSTACLES_PER_PROBLEM = {  # FORMAT.md's table
    "bookshelf_small": 7, "bookshelf_tall": 15, "bookshelf_thin": 21, "box": 7,
    "cage": 8, "table_pick": 12, "table_under_pick": 12,
}

pytestmark = pytest.mark.skipif(not MBM_DIR.is_dir(), reason=f"MBM problems not found at {MBM_DIR}")


@pytest.fixture(scope="module")
def documents() -> dict[str, dict[str, Any]]:
    return {path.stem: json.loads(path.read_text(encoding="utf-8")) for path in sorted(MBM_DIR.glob("*.json"))}


@pytest.fixture(scope="module")
def problem_sets(documents: dict[str, dict[str, Any]]) -> dict[str, MbmProblemSet]:
    return {name: parse_mbm(doc) for name, doc in documents.items()}


@pytest.fixture(scope="module")
def mbm_panda(problem_sets: dict[str, MbmProblemSet]) -> RobotModel:
    return RobotModel.from_config(mbm_robot_config(problem_sets["box"]))


def test_real_files_parse_to_350_problems(problem_sets: dict[str, MbmProblemSet]) -> None:
    assert sorted(problem_sets) == sorted(OBSTACLES_PER_PROBLEM)
    assert sum(len(s.problems) for s in problem_sets.values()) == 350
    for name, problem_set in problem_sets.items():
        assert problem_set.family == name and problem_set.robot == "panda"
        assert problem_set.joint_names == tuple(f"panda_joint{i}" for i in range(1, 8))
        assert dict(problem_set.fixed_joint_positions) == {"panda_finger_joint1": 0.065, "panda_finger_joint2": 0.065}
        assert len(problem_set.allowed_collision_pairs) == 34
        assert [p.index for p in problem_set.problems] == list(range(1, 51))
        for problem in problem_set.problems:
            assert problem.start.shape == (7,) and problem.goal.shape == (7,) and len(problem.goals_rad) == 1
            assert len(problem.obstacles) == OBSTACLES_PER_PROBLEM[name]
            assert {o.type for o in problem.obstacles} <= {"box", "cylinder"}
            for obstacle in problem.obstacles:
                assert np.linalg.norm(obstacle.quat_xyzw) == pytest.approx(1.0, abs=1e-9)
    # Spot-check the conventions on box #1: its base plate is 0.7 x 0.7 x 0.04 full sides, the can 0.14 m tall.
    box = {o.name: o for o in problem_sets["box"].problems[0].obstacles}
    assert box["base"].size_m == (0.7, 0.7, 0.04)
    assert (box["Can1"].type, box["Can1"].radius_m, box["Can1"].length_m) == ("cylinder", 0.03, 0.14)


def test_mbm_robot_config_applies_limits_fingers_and_pairs(
    problem_sets: dict[str, MbmProblemSet], mbm_panda: RobotModel
) -> None:
    cfg = mbm_panda.config
    assert cfg.padding_m == 0.0
    assert cfg.allowed_collision_pairs == problem_sets["box"].allowed_collision_pairs
    expected = np.array([MBM_PANDA_POSITION_LIMITS_RAD[n] for n in mbm_panda.joint_names])
    np.testing.assert_allclose(mbm_panda.lower_limits_rad, expected[:, 0])
    np.testing.assert_allclose(mbm_panda.upper_limits_rad, expected[:, 1])
    assert mbm_panda.upper_limits_rad[3] == pytest.approx(0.0873)  # the URDF says 0.0
    poses = mbm_panda.link_poses(mbm_panda.home_position_rad)
    gap = np.linalg.norm(poses["panda_leftfinger"][:3, 3] - poses["panda_rightfinger"][:3, 3])
    assert gap == pytest.approx(0.13)  # 0.065 m each, beyond the URDF's 0.04 m limit
    assert mbm_robot_config(problem_sets["cage"], padding_m=0.01).padding_m == 0.01
    # The obstacles are in the base frame: a robot file placing the robot elsewhere does not move it here.
    placed = dataclasses.replace(RobotConfig(), world_from_base=PoseSpec((1.0, 2.0, 0.5), (0.0, 0.0, 0.6, 0.8)))
    np.testing.assert_array_equal(mbm_robot_config(problem_sets["box"], base=placed).world_from_base.matrix, np.eye(4))


def test_starts_and_goals_are_free_on_the_meshes_and_within_limits(
    problem_sets: dict[str, MbmProblemSet], mbm_panda: RobotModel
) -> None:
    checker = MeshCollisionChecker(mbm_panda)
    for problem_set in problem_sets.values():
        for problem in problem_set.problems[:2]:
            checker.set_objects(problem.obstacles)
            for label, q in (("start", problem.start), ("goal", problem.goal)):
                where = f"{problem_set.family} #{problem.index} {label}"
                assert mbm_panda.check_joint_limits(q) == [], where
                assert checker.collisions(q) == [], where


def test_the_goal_above_the_urdf_q4_limit_is_within_the_mbm_limit(
    problem_sets: dict[str, MbmProblemSet], mbm_panda: RobotModel
) -> None:
    q4 = [(s.family, p.index, p.goal[3]) for s in problem_sets.values() for p in s.problems if p.goal[3] > 0.0]
    assert q4, "FORMAT.md: one MBM goal has q4 = 0.0166 > the URDF's 0.0"
    for family, index, value in q4:
        assert value <= mbm_panda.upper_limits_rad[3], (family, index)


def _malformed(documents: dict[str, dict[str, Any]]) -> dict[str, Any]:
    doc = copy.deepcopy(documents["box"])
    doc["problems"] = doc["problems"][:3]
    doc["count"] = 3
    return doc


@pytest.mark.parametrize(("edit", "message"), [
    (lambda d: d.update(format="mbm-primitives/2"), r"key 'format': expected 'mbm-primitives/1', got 'mbm-primitives/2'"),
    (lambda d: d.pop("joint_names"), r"mbm 'box': key 'joint_names' is missing"),
    (lambda d: d.update(count=50), r"key 'count': expected the number of problems \(3\), got 50"),
    (lambda d: d["problems"][1].pop("start"), r"problems\[1\] \(index 2\): key 'start' is missing"),
    (lambda d: d["problems"][2]["goals"][0].pop(), r"problems\[2\] \(index 3\): key 'goals\[0\]': expected 7 numbers, got 6"),
    (lambda d: d["problems"][0]["start"].__setitem__(3, "x"), r"problems\[0\] \(index 1\): key 'start\[3\]': expected a finite number"),
    (lambda d: d["problems"][1].update(goals=[]), r"problems\[1\] \(index 2\): key 'goals': expected at least one"),
    (lambda d: d["problems"][0]["obstacles"][1].pop("size"), r"problems\[0\] \(index 1\): key 'obstacles\[1\].size' is missing"),
    (lambda d: d["problems"][0]["obstacles"][1].update(size=[0.7, 0.7]), r"key 'obstacles\[1\].size': expected 3 numbers, got 2"),
    (lambda d: d["problems"][0]["obstacles"][2].update(orientation_xyzw=[0, 0, 0, 2]),
     r"problems\[0\] \(index 1\): key 'obstacles\[2\].orientation_xyzw': expected a unit quaternion"),
    (lambda d: d["problems"][0]["obstacles"][0].update(type="cone"), r"key 'obstacles\[0\].type': expected box, cylinder"),
    (lambda d: d["problems"][0]["obstacles"][0].update(radius=-0.03), r"key 'obstacles\[0\]': cylinder 'Can1' needs a positive radius_m"),
    (lambda d: d["problems"][0]["obstacles"][1].update(half_extents=[0.7, 0.7, 0.04]), r"'obstacles\[1\].half_extents': .* is not half of size"),
    (lambda d: d["problems"][2].update(index=0), r"problems\[2\]: key 'index': expected an int >= 1, got 0"),
    (lambda d: d.update(base_pose={"position": [0, 0, 0.1], "orientation_xyzw": [0, 0, 0, 1]}), r"key 'base_pose': only the identity"),
])
def test_malformed_documents_name_problem_and_key(documents: dict[str, dict[str, Any]], edit: Any, message: str) -> None:
    doc = _malformed(documents)
    edit(doc)
    with pytest.raises(ValueError, match=message):
        parse_mbm(doc)


def test_the_unedited_cut_document_parses(documents: dict[str, dict[str, Any]]) -> None:
    assert len(parse_mbm(_malformed(documents)).problems) == 3


def test_a_non_object_document_is_rejected() -> None:
    with pytest.raises(ValueError, match="expected a JSON object, got list"):
        parse_mbm([])  # type: ignore[arg-type]
