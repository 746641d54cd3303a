"""Where a campaign's moving scene puts its box: on the arm's way, early enough to be avoided,
away from the goal, and where a camera sees it."""

from __future__ import annotations

import numpy as np

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.config import SimConfig
from robonav.pipeline.sim.goals import Intruder, intruder_for_trajectory
from robonav.pipeline.sim.world import SimWorld
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.pipeline.trajectory.trajectory import with_start_dwell
from robonav.services.config import RobonavConfig

INTRUDER_SLIDE_S = 0.5
INTRUDER_LEAD_S = 1.2
"""The box rests on the path at least this long before any link would come within 10 cm of it:
time for a frame, a map, the guard's check and a stop (a box hitting an arm that cannot get
away in time tests nothing)."""
INTRUDER_MIN_PIXELS = 100
"""Pixels of the resting box at least one camera must show, with the whole box inside its
view (a 10 cm box 1.2 m from a 320x240 camera fills about 500). A count alone let a box through
that stood above a camera's image, three rows of it in the top edge: the map held a sliver of
its underside and a plan went through the rest."""


class IntruderPlacer:
    """Finds a resting place for the box on a planned path, in the campaign's own noiseless copy
    of the scene (the cameras' view: a box in a blind spot tests the camera layout, not the
    pipeline)."""

    def __init__(self, cfg: RobonavConfig, robot: RobotModel, *, goal_margin_m: float) -> None:
        self.cfg = cfg
        self.robot = robot
        self.link = cfg.robot.end_effector_link
        self._goal_check = CollisionWorld(robot, padding_m=goal_margin_m, broad_phase=False)
        self._eyes = SimWorld(cfg.robot, cfg.cameras[0], SimConfig(follow="kinematic", gravity=False))

    def close(self) -> None:
        self._eyes.close()

    def set_scene(self, objects: tuple[SceneObject, ...]) -> None:
        self._eyes.set_objects(objects)

    def place(self, path: np.ndarray, velocity_scaling: float, acceleration_scaling: float) -> Intruder | None:
        """Where a box can slide onto `path` as the arm starts (timed with the executor's own
        parameterization at these scalings, its dwell at the start included), resting on the way,
        not within the goal margin of the arm at the goal, early enough to avoid, and where a
        camera sees it (`INTRUDER_MIN_PIXELS`) past the scene and the arm as it comes to rest."""
        trajectory = with_start_dwell(time_parameterize(
            path, max_velocity=self.robot.velocity_limits, max_acceleration=self.robot.acceleration_limits,
            max_jerk=self.robot.jerk_limits, velocity_scaling=velocity_scaling,
            acceleration_scaling=acceleration_scaling,
            max_path_deviation_rad=self.cfg.executor.max_path_deviation_rad), self.cfg.executor.start_dwell_s)
        times, q, _, _ = trajectory.sample_uniform(0.05)
        at_rest = q[min(int(np.searchsorted(times, INTRUDER_SLIDE_S)), len(q) - 1)]

        def unfit(box: SceneObject) -> bool:
            # The box blocks the way, not the goal: resting on or beside the goal, it would make
            # the goal unreachable rather than test a stop and a detour.
            self._goal_check.set_objects([box])
            return self._goal_check.in_collision(path[-1]) or self.pixels_seen(box, at_rest) < INTRUDER_MIN_PIXELS

        return intruder_for_trajectory(self.robot, times, q, link=self.link, slide_s=INTRUDER_SLIDE_S,
                                       min_lead_s=INTRUDER_LEAD_S, reject=unfit)

    def pixels_seen(self, box: SceneObject, q: np.ndarray) -> int:
        """The most pixels of `box` a camera shows that holds all of it in its view (0 if none
        does), the arm at `q` and the scene in front of it."""
        corners = box.bounds_corners_m
        cameras = [camera for camera in self.cfg.cameras if camera.holds(corners)]
        if not cameras:
            return 0
        self._eyes.set_joint_positions(q)
        self._eyes.add_object(box)
        try:
            return max(self._eyes.pixels_of(box.name, cameras))
        finally:
            self._eyes.remove_object(box.name)
