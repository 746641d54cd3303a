"""Scenes for the sim: seeded procedural clutter, MotionBenchMaker problems and YAML scene files.

A `Scene` is obstacles in the world (robot base) frame, optionally with a start and goals.
Reading files is the caller's job; this module turns parsed documents and seeds into scenes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from robonav.pipeline.config import ConfigError, from_mapping, require
from robonav.pipeline.evaluation.mbm import MbmProblem, MbmProblemSet
from robonav.pipeline.scene import SceneObject

LAYOUTS: tuple[str, ...] = ("table", "shelf", "bin")


@dataclass(frozen=True)
class Scene:
    """Obstacles of one world, and a start and goals when the source has them."""

    name: str
    objects: tuple[SceneObject, ...]
    start_rad: tuple[float, ...] | None = None
    """(n,) start configuration [rad]."""
    goals_rad: tuple[tuple[float, ...], ...] = ()
    """Goal configurations [rad]."""

    def __post_init__(self) -> None:
        names = [o.name for o in self.objects]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        require(not duplicates, f"scene '{self.name}': duplicate object names {duplicates}")
        require("robot" not in names, f"scene '{self.name}': 'robot' is reserved for the arm")
        lengths = {len(g) for g in self.goals_rad} | ({len(self.start_rad)} if self.start_rad is not None else set())
        require(len(lengths) <= 1, f"scene '{self.name}': start_rad and goals_rad differ in length")


@dataclass(frozen=True)
class ClutterConfig:
    """Procedural clutter on a table in front of the robot; sizes in metres, world frame."""

    table_center_m: tuple[float, float, float] = (0.55, 0.0, 0.1)
    """Center of the table box [m]."""
    table_size_m: tuple[float, float, float] = (0.5, 1.2, 0.2)
    """Full side lengths of the table box [m]; its top is the support plane."""
    layouts: tuple[str, ...] = LAYOUTS
    """Layouts drawn from, uniformly: table (loose objects), shelf (a shelf unit on the table),
    bin (an open bin holding objects)."""
    objects_min: int = 3
    objects_max: int = 7
    """Loose objects per scene, drawn uniformly in [objects_min, objects_max]."""
    size_min_m: float = 0.04
    size_max_m: float = 0.18
    """Range of object widths (box sides, cylinder and sphere diameters) [m]."""
    height_max_m: float = 0.3
    """Tallest loose object [m]."""
    gap_m: float = 0.03
    """Smallest horizontal gap between the footprints of two objects [m]."""
    keep_clear_radius_m: float = 0.35
    """No object within this horizontal distance of the robot base axis [m]."""
    base_xy_m: tuple[float, float] = (0.0, 0.0)
    """Where the robot base axis stands, world frame [m] (a cell placed for another arm moves it)."""

    def __post_init__(self) -> None:
        require(all(s > 0 for s in self.table_size_m), f"clutter.table_size_m must be positive, got {self.table_size_m}")
        require(bool(self.layouts) and set(self.layouts) <= set(LAYOUTS),
                f"clutter.layouts must be a non-empty subset of {list(LAYOUTS)}, got {list(self.layouts)}")
        require(0 <= self.objects_min <= self.objects_max,
                f"clutter needs 0 <= objects_min <= objects_max, got {self.objects_min}, {self.objects_max}")
        require(0 < self.size_min_m <= self.size_max_m,
                f"clutter needs 0 < size_min_m <= size_max_m, got {self.size_min_m}, {self.size_max_m}")
        require(self.height_max_m >= self.size_min_m, f"clutter.height_max_m must be >= size_min_m, got {self.height_max_m}")
        require(self.gap_m >= 0 and self.keep_clear_radius_m >= 0, "clutter.gap_m and keep_clear_radius_m must be >= 0")


@dataclass(frozen=True)
class SceneFile:
    """The YAML scene format: `name`, `objects` (as in `sim.objects`), optional `start_rad`, `goals_rad`."""

    objects: tuple[SceneObject, ...]
    name: str = "scene"
    start_rad: tuple[float, ...] | None = None
    goals_rad: tuple[tuple[float, ...], ...] = field(default=())


def scene_from_mapping(data: Any, *, source: str = "<scene>") -> Scene:
    """A scene from a parsed YAML document; unknown keys and wrong types raise `ConfigError`."""
    parsed = from_mapping(SceneFile, data, source=source)
    try:
        return Scene(parsed.name, parsed.objects, parsed.start_rad, parsed.goals_rad)
    except ValueError as exc:
        raise ConfigError(source, "<root>", str(exc)) from exc


def mbm_scenes(problems: MbmProblemSet) -> list[Scene]:
    """One scene per MotionBenchMaker problem (`parse_mbm` output), with its start and goal."""
    return [mbm_scene(problems.family, problem) for problem in problems.problems]


def mbm_scene(family: str, problem: MbmProblem) -> Scene:
    return Scene(f"mbm-{family}-{problem.index:03d}", problem.obstacles, problem.start_rad, problem.goals_rad)


def clutter_scene(config: ClutterConfig, rng: np.random.Generator, *, name: str = "clutter") -> Scene:
    """A random table scene: the table, a layout (loose objects, a shelf or a bin) and loose objects.

    Args:
        config: Table geometry, layouts and object ranges.
        rng: Source of randomness; the same generator state gives the same scene.
        name: Name of the scene.
    """
    layout = config.layouts[int(rng.integers(len(config.layouts)))]
    table = SceneObject("table", "box", config.table_center_m, size_m=config.table_size_m)
    top_z = config.table_center_m[2] + config.table_size_m[2] / 2.0
    placer = _Placer(config, rng)
    objects = [table]
    if layout == "shelf":
        objects += _shelf(config, rng, placer, top_z)
    elif layout == "bin":
        objects += _bin(config, rng, placer, top_z)
    for i in range(int(rng.integers(config.objects_min, config.objects_max + 1))):
        obj = _loose_object(f"item_{i}", config, rng, placer, top_z)
        if obj is not None:
            objects.append(obj)
    return Scene(f"{name}-{layout}", tuple(objects))


class _Placer:
    """Rejection sampling of footprints (discs) on the table top that keep a gap to each other."""

    def __init__(self, config: ClutterConfig, rng: np.random.Generator) -> None:
        self.config = config
        self.rng = rng
        self.discs: list[tuple[float, float, float]] = []

    def place(self, radius_m: float, attempts: int = 30) -> tuple[float, float] | None:
        cx, cy, _ = self.config.table_center_m
        half_x, half_y = self.config.table_size_m[0] / 2.0 - radius_m, self.config.table_size_m[1] / 2.0 - radius_m
        if half_x <= 0 or half_y <= 0:
            return None
        for _ in range(attempts):
            x, y = cx + self.rng.uniform(-half_x, half_x), cy + self.rng.uniform(-half_y, half_y)
            base_x, base_y = self.config.base_xy_m
            if math.hypot(x - base_x, y - base_y) < self.config.keep_clear_radius_m + radius_m:
                continue
            if all(math.hypot(x - ox, y - oy) >= radius_m + r + self.config.gap_m for ox, oy, r in self.discs):
                self.discs.append((x, y, radius_m))
                return x, y
        return None


def _yaw_quat(yaw_rad: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw_rad / 2.0), math.cos(yaw_rad / 2.0))


def _loose_object(name: str, config: ClutterConfig, rng: np.random.Generator, placer: _Placer,
                  base_z: float) -> SceneObject | None:
    kind = ("box", "cylinder", "sphere")[int(rng.integers(3))]
    width = float(rng.uniform(config.size_min_m, config.size_max_m))
    if kind == "sphere":
        xy = placer.place(width / 2.0)
        return None if xy is None else SceneObject(name, "sphere", (xy[0], xy[1], base_z + width / 2.0), radius_m=width / 2.0)
    height = float(rng.uniform(config.size_min_m, config.height_max_m))
    if kind == "cylinder":
        xy = placer.place(width / 2.0)
        return None if xy is None else SceneObject(name, "cylinder", (xy[0], xy[1], base_z + height / 2.0),
                                                   radius_m=width / 2.0, length_m=height)
    depth = float(rng.uniform(config.size_min_m, config.size_max_m))
    xy = placer.place(math.hypot(width, depth) / 2.0)
    return None if xy is None else SceneObject(name, "box", (xy[0], xy[1], base_z + height / 2.0),
                                               quat_xyzw=_yaw_quat(float(rng.uniform(-math.pi, math.pi))),
                                               size_m=(width, depth, height))


def _shelf(config: ClutterConfig, rng: np.random.Generator, placer: _Placer, top_z: float) -> list[SceneObject]:
    """An open-fronted shelf unit facing the robot, with one board and objects on it."""
    depth, width, height, wall = 0.25, float(rng.uniform(0.4, 0.6)), float(rng.uniform(0.4, 0.55)), 0.02
    cx = config.table_center_m[0] + config.table_size_m[0] / 2.0 - depth / 2.0
    xy = None
    for _ in range(30):
        cy = config.table_center_m[1] + float(rng.uniform(-1, 1)) * (config.table_size_m[1] - width) / 2.0
        if math.hypot(cx - config.base_xy_m[0], cy - config.base_xy_m[1]) >= \
                config.keep_clear_radius_m + math.hypot(depth, width) / 2.0:
            xy = (cx, cy)
            break
    if xy is None:
        return []
    placer.discs.append((xy[0], xy[1], math.hypot(depth, width) / 2.0))
    board_z = top_z + float(rng.uniform(0.45, 0.6)) * height
    parts = [
        SceneObject("shelf_left", "box", (xy[0], xy[1] - width / 2.0 + wall / 2.0, top_z + height / 2.0), size_m=(depth, wall, height)),
        SceneObject("shelf_right", "box", (xy[0], xy[1] + width / 2.0 - wall / 2.0, top_z + height / 2.0), size_m=(depth, wall, height)),
        SceneObject("shelf_back", "box", (xy[0] + depth / 2.0 - wall / 2.0, xy[1], top_z + height / 2.0), size_m=(wall, width, height)),
        SceneObject("shelf_top", "box", (xy[0], xy[1], top_z + height - wall / 2.0), size_m=(depth, width, wall)),
        SceneObject("shelf_board", "box", (xy[0], xy[1], board_z), size_m=(depth, width, wall)),
    ]
    for i in range(int(rng.integers(1, 3))):
        size = float(rng.uniform(config.size_min_m, min(config.size_max_m, 0.1)))
        y = xy[1] + (i - 0.5) * width / 2.5
        parts.append(SceneObject(f"shelf_item_{i}", "box", (xy[0], y, board_z + wall / 2.0 + size / 2.0),
                                 size_m=(size, size, size)))
    return parts


def _bin(config: ClutterConfig, rng: np.random.Generator, placer: _Placer, top_z: float) -> list[SceneObject]:
    """An open bin (floor and four walls) with small objects inside."""
    length, width, height, wall = float(rng.uniform(0.2, 0.3)), float(rng.uniform(0.25, 0.4)), float(rng.uniform(0.08, 0.15)), 0.015
    xy = placer.place(math.hypot(length, width) / 2.0)
    if xy is None:
        return []
    x, y = xy
    z = top_z + height / 2.0
    parts = [
        SceneObject("bin_floor", "box", (x, y, top_z + wall / 2.0), size_m=(length, width, wall)),
        SceneObject("bin_near", "box", (x - length / 2.0 + wall / 2.0, y, z), size_m=(wall, width, height)),
        SceneObject("bin_far", "box", (x + length / 2.0 - wall / 2.0, y, z), size_m=(wall, width, height)),
        SceneObject("bin_left", "box", (x, y - width / 2.0 + wall / 2.0, z), size_m=(length, wall, height)),
        SceneObject("bin_right", "box", (x, y + width / 2.0 - wall / 2.0, z), size_m=(length, wall, height)),
    ]
    for i in range(int(rng.integers(1, 4))):
        radius = float(rng.uniform(0.02, 0.04))
        px = x + float(rng.uniform(-1, 1)) * (length / 2.0 - wall - radius)
        py = y + float(rng.uniform(-1, 1)) * (width / 2.0 - wall - radius)
        parts.append(SceneObject(f"bin_item_{i}", "sphere", (px, py, top_z + wall + radius), radius_m=radius))
    return parts


def scene_bounds_m(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """World-frame axis-aligned bounds (min (3,), max (3,)) of every object's bounding box [m]."""
    corners = []
    for obj in scene.objects:
        center, half = obj.local_bounds_m
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
        local = center + signs * half
        pose = obj.world_from_object
        corners.append(local @ pose[:3, :3].T + pose[:3, 3])
    stacked = np.concatenate(corners) if corners else np.zeros((1, 3))
    return stacked.min(axis=0), stacked.max(axis=0)

