"""`--robot FILE` of `robonav demo` and `robonav campaign`: the stack's config for another robot.

The robot comes from a robot file (`robonav robot init`) or the `robot` section of a whole
config (e.g. configs/iiwa.yaml). The config's cell (cameras, obstacles, clutter table,
perception workspace) is laid out for the config's own robot; for another robot it is moved
and scaled to that robot's shoulder and reach (`pipeline/sim/cell.py`), and the config's demo
goals, which are joint vectors of its own robot, are dropped: the demo draws goals for the
robot instead (`demo_goals`).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import yaml

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.config import ConfigError
from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.planning.motion_planner import MotionPlanner
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.cell import CellPlacement, robot_reach
from robonav.pipeline.sim.config import SimConfig
from robonav.pipeline.sim.goals import draw_goal_sequence, goal_region, perceivable_objects
from robonav.services.config import RobonavConfig, config_to_mapping, load_config, load_robot_file

DEMO_GOAL_COUNT = 3
"""Goals the demo visits with a robot whose goals it draws (as many as the Panda's hand-picked ones)."""


def read_robot(path: str | Path) -> RobotConfig:
    """The robot of a robot file, or the `robot` section of a whole config; relative paths in
    either resolve against that file's folder.

    Raises:
        ConfigError: unreadable file, bad YAML, unknown keys or a robot that does not load.
    """
    file = Path(path).absolute()  # the config it goes into is written elsewhere: no path may stay relative
    try:
        data = yaml.safe_load(file.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(str(file), "<file>", f"cannot read: {exc.strerror or exc}") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(str(file), "<file>", f"invalid YAML: {exc}") from exc
    robot = load_config(file).robot if isinstance(data, dict) and "robot" in data else load_robot_file(file)
    try:
        RobotModel.from_config(robot)
    except ValueError as exc:
        raise ConfigError(str(file), "robot", str(exc)) from exc
    return robot


def with_robot(cfg: RobonavConfig, robot: RobotConfig) -> RobonavConfig:
    """`cfg` running `robot`: unchanged when it is the config's own robot; else with the cell
    placed for `robot` and no demo goals (see the module docstring)."""
    if robot == cfg.robot:
        return cfg
    for camera in cfg.cameras:
        if camera.extrinsics_file is not None:
            raise ConfigError("--robot", f"cameras[{camera.camera_id}].extrinsics_file",
                              "a calibrated camera cannot be moved for another robot: give a config without "
                              "extrinsics files, or one whose robot is this robot")
    placement = CellPlacement(robot_reach(RobotModel.from_config(cfg.robot)), robot_reach(RobotModel.from_config(robot)))
    return dataclasses.replace(
        cfg, robot=robot, cameras=tuple(_camera(c, placement) for c in cfg.cameras), sim=_sim(cfg.sim, placement),
        perception=_perception(cfg.perception, placement), demo=dataclasses.replace(cfg.demo, goals_rad=()))


def write_config(cfg: RobonavConfig, path: Path) -> Path:
    """Write `cfg` as a whole config file (every key) and check that it reads back."""
    path.write_text(yaml.safe_dump(config_to_mapping(cfg), sort_keys=False), encoding="utf-8")
    load_config(path)
    return path


def demo_goals(cfg: RobonavConfig, seed: int, count: int = DEMO_GOAL_COUNT) -> tuple[tuple[float, ...], ...]:
    """`count` goals for `cfg.robot` in `cfg.sim.objects`, visited in turn from home: each
    with the end effector over the table and inside the perception workspace, clear of the
    objects by what a camera-built map can add around them (padding + inflation + a voxel
    diagonal, as the campaign's goals), preferring ones the straight way to is blocked, and
    each reached from the one before by a planner on that view of the truth. Seeded.

    Raises:
        ValueError: no reachable goal was found for some step.
    """
    robot = RobotModel.from_config(cfg.robot)
    margin_m = cfg.robot.padding_m + cfg.perception.inflation_m + math.sqrt(3.0) * cfg.perception.resolution_m
    view = CollisionWorld(robot, padding_m=margin_m)
    view.set_objects(perceivable_objects(cfg.sim.objects, cfg.perception.workspace_min_m[2]))
    region_min, region_max = goal_region(cfg.sim.objects, cfg.perception.workspace_min_m, cfg.perception.workspace_max_m)
    goals = draw_goal_sequence(view, MotionPlanner(robot, view, cfg.planner), np.random.default_rng((seed, 23)),
                               robot.home_position_rad, count=count, link=cfg.robot.end_effector_link,
                               region_min_m=region_min, region_max_m=region_max, min_clearance_m=margin_m, seed=seed)
    return tuple(tuple(round(float(v), 4) for v in goal) for goal in goals)


def _point(placement: CellPlacement, point_m: tuple[float, ...]) -> tuple[float, float, float]:
    x, y, z = placement.point(point_m)
    return (round(float(x), 4), round(float(y), 4), round(float(z), 4))


def _camera(camera: CameraConfig, placement: CellPlacement) -> CameraConfig:
    return dataclasses.replace(camera, position_m=_point(placement, camera.position_m))


def _object(obj: SceneObject, placement: CellPlacement) -> SceneObject:
    def scaled(value: float | None) -> float | None:
        return None if value is None else round(placement.length(value), 4)

    return dataclasses.replace(
        obj, position_m=_point(placement, obj.position_m), radius_m=scaled(obj.radius_m), length_m=scaled(obj.length_m),
        size_m=None if obj.size_m is None else tuple(scaled(v) for v in obj.size_m),
        vertices_m=None if obj.vertices_m is None else np.asarray(obj.vertices_m) * placement.scale)


def _sim(sim: SimConfig, placement: CellPlacement) -> SimConfig:
    clutter = sim.clutter
    base_x, base_y = placement.xy(clutter.base_xy_m)
    clutter = dataclasses.replace(
        clutter, table_center_m=_point(placement, clutter.table_center_m),
        table_size_m=tuple(round(placement.length(v), 4) for v in clutter.table_size_m),
        keep_clear_radius_m=round(placement.length(clutter.keep_clear_radius_m), 4),
        base_xy_m=(round(float(base_x), 4), round(float(base_y), 4)))
    motions = tuple(m if m.position_m is None else dataclasses.replace(m, position_m=_point(placement, m.position_m))
                    for m in sim.motions)
    return dataclasses.replace(sim, objects=tuple(_object(o, placement) for o in sim.objects), clutter=clutter,
                               motions=motions)


def _perception(perception: PerceptionConfig, placement: CellPlacement) -> PerceptionConfig:
    return dataclasses.replace(perception, workspace_min_m=_point(placement, perception.workspace_min_m),
                               workspace_max_m=_point(placement, perception.workspace_max_m))
