"""Scenes: seeded clutter is reproducible and well-formed, YAML scenes load strictly, MBM scenes
collide in the sim exactly where the benchmark's own mesh check says they do."""

from __future__ import annotations

import json
import math

import numpy as np
import pybullet as p
import pytest
import yaml

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.config import ConfigError
from robonav.pipeline.evaluation.mbm import mbm_robot_config, parse_mbm
from robonav.pipeline.evaluation.mesh_check import MeshCollisionChecker
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.config import SimConfig
from robonav.pipeline.sim.scenes import ClutterConfig, clutter_scene, mbm_scenes, scene_bounds_m, scene_from_mapping
from robonav.pipeline.sim.world import SimWorld

from ...conftest import MBM_DIR

"""The shared benchmark data (../shared/benchmarks/mbm next to the repository)."""
CONFIG = ClutterConfig()


def test_clutter_is_reproducible_from_the_seed() -> None:
    first = [clutter_scene(CONFIG, np.random.default_rng((42, i))) for i in range(12)]
    again = [clutter_scene(CONFIG, np.random.default_rng((42, i))) for i in range(12)]
    assert first == again
    other = [clutter_scene(CONFIG, np.random.default_rng((43, i))) for i in range(12)]
    assert first != other
    assert {s.name.rsplit("-", 1)[1] for s in first} == {"table", "shelf", "bin"}  # every layout occurs


@pytest.mark.parametrize("index", range(20))
def test_clutter_sits_on_the_table_and_keeps_clear_of_the_robot(index: int) -> None:
    scene = clutter_scene(CONFIG, np.random.default_rng((7, index)))
    table = scene.objects[0]
    assert table.name == "table" and len({o.name for o in scene.objects}) == len(scene.objects)
    low, high = scene_bounds_m(scene)
    top_z = CONFIG.table_center_m[2] + CONFIG.table_size_m[2] / 2.0
    table_low = np.subtract(CONFIG.table_center_m, np.divide(CONFIG.table_size_m, 2.0))
    table_high = np.add(CONFIG.table_center_m, np.divide(CONFIG.table_size_m, 2.0))
    assert np.all(low >= table_low - 1e-9) and np.all(high[:2] <= table_high[:2] + 1e-9)
    loose = [o for o in scene.objects if o.name.startswith("item_")]
    assert CONFIG.objects_min - 2 <= len(loose) <= CONFIG.objects_max  # a crowded table may refuse a few
    for obj in scene.objects[1:]:
        center, half = obj.local_bounds_m
        bottom = obj.position_m[2] - (half[2] if obj.type != "box" or obj.quat_xyzw[:2] == (0.0, 0.0) else np.max(half))
        assert bottom >= top_z - 1e-9, f"{obj.name} sinks into the table"
        assert math.hypot(*obj.position_m[:2]) >= CONFIG.keep_clear_radius_m
    def footprint_radius(obj: SceneObject) -> float:
        return math.hypot(*obj.local_bounds_m[1][:2]) if obj.type == "box" else float(obj.radius_m)  # type: ignore[arg-type]

    for i, a in enumerate(loose):  # footprints keep their gap
        for b in loose[i + 1:]:
            gap = math.dist(a.position_m[:2], b.position_m[:2]) - footprint_radius(a) - footprint_radius(b)
            assert gap >= CONFIG.gap_m - 1e-9, (a.name, b.name)


def test_clutter_config_is_validated() -> None:
    with pytest.raises(ValueError, match="layouts"):
        ClutterConfig(layouts=("garden",))
    with pytest.raises(ValueError, match="objects_min"):
        ClutterConfig(objects_min=5, objects_max=2)
    only_tables = ClutterConfig(layouts=("table",), objects_min=0, objects_max=0)
    assert [o.name for o in clutter_scene(only_tables, np.random.default_rng(0)).objects] == ["table"]


def test_yaml_scenes_load_strictly() -> None:
    text = """
name: two boxes
objects:
  - {name: a, type: box, position_m: [0.5, 0.0, 0.2], size_m: [0.1, 0.1, 0.1]}
  - {name: b, type: sphere, position_m: [0.5, 0.3, 0.2], radius_m: 0.05}
start_rad: [0, 0, 0, -2, 0, 2, 0.7]
goals_rad: [[0.5, 0, 0, -2, 0, 2, 0.7]]
"""
    scene = scene_from_mapping(yaml.safe_load(text), source="two.yaml")
    assert scene.name == "two boxes" and [o.name for o in scene.objects] == ["a", "b"]
    assert scene.goals_rad == ((0.5, 0.0, 0.0, -2.0, 0.0, 2.0, 0.7),)
    with pytest.raises(ConfigError, match=r"two.yaml: key 'objects\[0\].colour'"):
        scene_from_mapping({"objects": [{"name": "a", "type": "box", "position_m": [0, 0, 0], "size_m": [1, 1, 1],
                                         "colour": "red"}]}, source="two.yaml")
    with pytest.raises(ConfigError, match="duplicate"):
        scene_from_mapping({"objects": [{"name": "a", "type": "sphere", "position_m": [0, 0, 0], "radius_m": 1}] * 2})
    with pytest.raises(ConfigError, match="differ in length"):
        scene_from_mapping({"objects": [], "start_rad": [0, 0], "goals_rad": [[0, 0, 0]]})


@pytest.mark.skipif(not MBM_DIR.is_dir(), reason=f"MBM problems not found at {MBM_DIR}")
@pytest.mark.parametrize("family", ["box", "cage", "bookshelf_thin", "table_under_pick"])
def test_mbm_scenes_collide_in_the_sim_where_the_benchmark_check_says(family: str) -> None:
    problems = parse_mbm(json.loads((MBM_DIR / f"{family}.json").read_text(encoding="utf-8")))
    robot_config = mbm_robot_config(problems)
    mesh = MeshCollisionChecker(RobotModel.from_config(robot_config))
    scenes = mbm_scenes(problems)[:6]
    colliding = 0
    with SimWorld(robot_config, CameraConfig(), SimConfig(follow="kinematic", gravity=False)) as world:
        for scene in scenes:
            world.set_objects(scene.objects)
            mesh.set_objects(scene.objects)
            names = {o.name for o in scene.objects}
            assert scene.start_rad is not None and len(scene.goals_rad) == 1
            start, goal = np.array(scene.start_rad), np.array(scene.goals_rad[0])
            # Start and goal (free in MBM) and the straight line between them (often blocked).
            for t in np.linspace(0.0, 1.0, 9):
                q = start + t * (goal - start)
                world.set_joint_positions(q)
                p.performCollisionDetection(physicsClientId=world._client)
                sim_contacts = world.robot_obstacle_contacts()
                mesh_hits = [pair for pair in mesh.collisions(q) if pair[1] in names]
                if t in (0.0, 1.0):
                    assert not sim_contacts and not mesh_hits, (scene.name, t)
                # The sim's link shapes are the meshes' convex hulls: slightly larger, never smaller.
                if mesh_hits:
                    assert sim_contacts, (scene.name, t, mesh_hits)
                    colliding += 1
                if sim_contacts and not mesh_hits:
                    assert min(c.distance_m for c in sim_contacts) > -0.001, (scene.name, t, sim_contacts)
    assert colliding > 0  # the straight lines do cross obstacles, so the comparison means something
