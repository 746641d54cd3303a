"""A work cell placed for a robot: the cell laid out for one arm, moved and scaled to another's reach.

The default cell (table, obstacles, cameras, perception workspace, clutter table) is laid out
for the Panda. Another arm stands elsewhere in its own root frame (the UR5's shoulder is 1 m
above its root link) and reaches further or less far. `CellPlacement` maps every point of the
cell so that it keeps its place relative to the arm's shoulder, scaled by the ratio of the two
reaches: a table 13 cm below the Panda's shoulder and in front of it is, for the UR5, the same
fraction of its reach below and in front of the UR5's shoulder. Directions (camera
orientations, "in front" = world +x) are kept: every arm here turns its first joint about the
vertical, so the cell's front is as good as any.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.types import FloatArray

REACH_SAMPLES = 2000
"""Random configurations the reach is measured over (seeded, so the cell is reproducible)."""


@dataclass(frozen=True)
class RobotReach:
    """Where an arm's shoulder is and how far its end effector gets from it."""

    shoulder_m: tuple[float, float, float]
    """At home, the horizontal position of the first planning joint (the axis the arm turns
    about) at the height of the second (the first joint that lifts the arm, whose height
    decides what the arm reaches down to) [m]."""
    reach_m: float
    """Largest shoulder-to-end-effector distance over `REACH_SAMPLES` configurations within the
    joint limits [m]."""

    def __post_init__(self) -> None:
        if not np.all(np.isfinite(self.shoulder_m)) or not (np.isfinite(self.reach_m) and self.reach_m > 0):
            raise ValueError(f"robot reach needs a finite shoulder and a reach > 0, got {self.shoulder_m}, {self.reach_m}")


def robot_reach(robot: RobotModel, seed: int = 0) -> RobotReach:
    """The shoulder and reach of `robot` (see `RobotReach`); seeded sampling of its joint limits."""
    home = robot.home_position_rad
    joints = robot.joint_names
    # Pinocchio keeps a frame per joint under the joint's name: its origin is on the joint's axis.
    axis = robot.frame_pose(home, joints[0])[:3, 3]
    lift = robot.frame_pose(home, joints[1] if len(joints) > 1 else joints[0])[:3, 3]
    shoulder = np.array([axis[0], axis[1], lift[2]])
    rng = np.random.default_rng(seed)
    samples = rng.uniform(robot.lower_limits_rad, robot.upper_limits_rad, size=(REACH_SAMPLES, robot.dof))
    link = robot.config.end_effector_link
    reach = max(float(np.linalg.norm(robot.frame_pose(q, link)[:3, 3] - shoulder)) for q in samples)
    return RobotReach(tuple(float(v) for v in shoulder), reach)  # type: ignore[arg-type]


@dataclass(frozen=True)
class CellPlacement:
    """Maps a cell laid out for the arm `source` to one for the arm `target`."""

    source: RobotReach
    target: RobotReach

    @property
    def scale(self) -> float:
        """Lengths in the target cell per length in the source cell."""
        return self.target.reach_m / self.source.reach_m

    def point(self, point_m: npt.ArrayLike) -> FloatArray:
        """(3,) or (N, 3) world points of the source cell, placed in the target cell [m]."""
        arr = np.asarray(point_m, dtype=np.float64)
        return np.asarray(self.target.shoulder_m) + (arr - np.asarray(self.source.shoulder_m)) * self.scale

    def length(self, length_m: float) -> float:
        """A length (size, radius, distance) of the source cell in the target cell [m]."""
        return float(length_m) * self.scale

    def xy(self, point_xy_m: npt.ArrayLike) -> FloatArray:
        """(2,) a horizontal position of the source cell, placed in the target cell [m]."""
        arr = np.asarray(point_xy_m, dtype=np.float64)
        return np.asarray(self.target.shoulder_m[:2]) + (arr - np.asarray(self.source.shoulder_m[:2])) * self.scale
