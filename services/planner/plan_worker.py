"""One planning worker's own world: a collision world and a motion planner used by one thread.

`MotionPlanner` and `CollisionWorld` are not thread-safe (scratch buffers, posed FCL objects,
kept roadmaps), so each worker thread of the planner plans in a world of its own. Before each
plan, and only then, the worker brings its world up to date: the scene (objects and attached
objects, from a `SceneSnapshot` when its revision changed) and the newest occupancy map, with
its inflation as the clearance released near each query's start and goal when the map carries
it (`pipeline/collision/surface_allowance.py`). A plan
in flight therefore keeps the scene and the map it started with; scene changes and new maps
never wait for it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.planning.motion_planner import MotionPlanner
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.wire.messages import Occupancy
from robonav.services.planner.scene import SceneSnapshot, copy_scene_into

log = logging.getLogger("robonav.planner")


@dataclass
class PlanWorker:
    world: CollisionWorld
    planner: MotionPlanner
    scene_revision: int = -1
    """Revision of the scene copied into `world` (-1: none yet)."""
    occupancy: Occupancy | None = None
    """The map last put into `world` (or found unusable)."""
    map_stamp: float = 0.0
    """Stamp of the map in `world` (0: none)."""

    @classmethod
    def create(cls, robot: RobotModel, padding_m: float, config: PlannerConfig) -> PlanWorker:
        world = CollisionWorld(robot, padding_m=padding_m)
        return cls(world, MotionPlanner(robot, world, config))

    def sync(self, scene: SceneSnapshot, newest_map: Occupancy | None) -> None:
        """Between plans: copy the scene if it changed, and take the newest map if it is new."""
        if scene.revision != self.scene_revision:
            copy_scene_into(self.world, scene)
            self.scene_revision = scene.revision
        if newest_map is not None and newest_map is not self.occupancy:
            self.occupancy = newest_map  # a map the world refuses is not tried again
            self.world.set_octree(newest_map.octomap_binary, newest_map.resolution_m, newest_map.occupied_centers_m,
                                  clearance_m=self.planner.config.map_clearance_m(newest_map.inflation_m))
            self.map_stamp = newest_map.stamp

    def forget(self) -> None:
        """Empty the world (after a warm-up): the next `sync` copies the scene and the map again."""
        for attached in self.world.attached_objects:
            self.world.detach_object(attached.name)
        self.world.clear_objects()
        self.world.clear_octree()
        self.scene_revision, self.occupancy, self.map_stamp = -1, None, 0.0
