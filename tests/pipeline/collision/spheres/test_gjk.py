"""GJK proves a polytope apart from a primitive only where FCL finds them apart, and almost
wherever it does; the broad phase uses it without changing any answer."""

from __future__ import annotations

import json

import fcl
import numpy as np
import pytest
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from robonav.pipeline.collision.spheres.gjk import polytope_keeps_off
from robonav.pipeline.collision.spheres.kernels import BOX, CAPSULE, CYLINDER, SPHERE
from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.evaluation.mbm import mbm_robot_config, parse_mbm
from robonav.pipeline.robot.model import RobotModel
from robonav.services.config import load_robot_file

from ....conftest import REPO_ROOT

KINDS = (BOX, SPHERE, CYLINDER, CAPSULE)
SHARED = REPO_ROOT.parent / "shared"


def _fcl_distance(vertices: np.ndarray, rotation: np.ndarray, translation: np.ndarray, kind: int, params: np.ndarray,
                  obj_rotation: np.ndarray, obj_center: np.ndarray) -> float:
    """FCL's distance between the polytope and the primitive, -1 when they touch."""
    hull = ConvexHull(vertices)
    faces = np.hstack([np.full((len(hull.simplices), 1), 3), hull.simplices]).ravel()
    polytope = fcl.CollisionObject(fcl.Convex(vertices, len(hull.simplices), faces), fcl.Transform(rotation, translation))
    geometry = {BOX: lambda: fcl.Box(*(2 * params)), SPHERE: lambda: fcl.Sphere(params[0]),
                CYLINDER: lambda: fcl.Cylinder(params[0], 2 * params[1]),
                CAPSULE: lambda: fcl.Capsule(params[0], 2 * params[1])}[kind]()
    other = fcl.CollisionObject(geometry, fcl.Transform(obj_rotation, obj_center))
    if fcl.collide(polytope, other, fcl.CollisionRequest(), fcl.CollisionResult()):
        return -1.0
    return float(fcl.distance(polytope, other, fcl.DistanceRequest(), fcl.DistanceResult()))


@pytest.mark.parametrize("margin_m", [0.0, 0.01])
def test_apart_only_where_fcl_finds_them_apart_and_wherever_it_does(margin_m: float) -> None:
    rng = np.random.default_rng(7)
    proven = apart = 0
    for case in range(600):
        points = rng.normal(size=(int(rng.integers(4, 40)), 3)) * rng.uniform(0.02, 0.1, size=3)
        vertices = np.ascontiguousarray(points[ConvexHull(points).vertices])
        rotation = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        obj_rotation = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        translation, obj_center = rng.uniform(-0.15, 0.15, 3), rng.uniform(-0.15, 0.15, 3)
        kind, params = KINDS[case % 4], rng.uniform(0.01, 0.1, 3)
        keeps_off = polytope_keeps_off(rotation, translation, vertices, 0, len(vertices), kind, obj_rotation, obj_center,
                                       params[0], params[1], params[2], margin_m)
        distance = _fcl_distance(vertices, rotation, translation, kind, params, obj_rotation, obj_center)
        assert not keeps_off or distance > margin_m, f"case {case}: proven apart at distance {distance}"
        if distance > margin_m + 1e-4:
            apart += 1
            proven += keeps_off
    assert apart > 250
    assert proven == apart, f"{apart - proven} of {apart} pairs apart by more than 0.1 mm not proven"


def test_an_empty_or_enclosing_polytope_is_never_apart() -> None:
    cube = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * 0.05
    eye, zero = np.eye(3), np.zeros(3)
    assert not polytope_keeps_off(eye, zero, cube, 0, 0, BOX, eye, np.ones(3), 0.1, 0.1, 0.1, 0.0)
    assert not polytope_keeps_off(eye, zero, cube, 0, 8, SPHERE, eye, zero, 0.01, 0.0, 0.0, 0.0)  # inside
    assert not polytope_keeps_off(eye, zero, cube, 0, 8, BOX, eye, np.array([0.06, 0, 0]), 0.01, 0.01, 0.01, 0.0)
    assert polytope_keeps_off(eye, zero, cube, 0, 8, BOX, eye, np.array([0.07, 0, 0]), 0.01, 0.01, 0.01, 0.0)
    # The margin grows the primitive: 1 cm apart is not apart by 2 cm.
    assert not polytope_keeps_off(eye, zero, cube, 0, 8, BOX, eye, np.array([0.07, 0, 0]), 0.01, 0.01, 0.01, 0.02)


def test_near_cage_bars_few_free_states_stay_flagged_and_cleared_ones_are_free() -> None:
    # MotionBenchMaker's UR5 cages: the hand passes bars at an angle, where no face of a bar has
    # the whole link polytope beyond it. Before GJK, 239 of the 681 states flagged here were free.
    try:
        problems = parse_mbm(json.loads((SHARED / "benchmarks" / "mbm-ur5" / "cage.json").read_text(encoding="utf-8")))
        base = load_robot_file(REPO_ROOT / "configs" / "ur5.yaml")
    except (OSError, ValueError) as exc:
        pytest.skip(f"UR5 problems not available: {exc}")
    robot = RobotModel.from_config(mbm_robot_config(problems, base=base,
                                                    known_links=RobotModel.from_config(base).link_names))
    rng = np.random.default_rng(11)
    flagged = free_flagged = 0
    for problem in problems.problems[:3]:
        world = CollisionWorld(robot)
        world.set_objects(problem.obstacles)
        goal = np.array(problem.goals_rad)[0]
        states = np.clip(goal + rng.normal(scale=0.2, size=(300, robot.dof)), robot.lower_limits_rad,
                         robot.upper_limits_rad)
        suspect = [bool(world._broad_phase.state_suspect(q)) for q in states]
        assert not any(world.collisions(q) for q, s in zip(states, suspect) if not s)  # cleared: FCL-free
        flagged += sum(suspect)
        free_flagged += sum(1 for q, s in zip(states, suspect) if s and not world.collisions(q))
    assert flagged > 300
    assert free_flagged <= 0.25 * flagged, f"{free_flagged} of {flagged} flagged states are free"
