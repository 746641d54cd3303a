"""The planner's `robot/description` publication: the robot it plans for, read from its own model."""

from __future__ import annotations

import time

from robonav.pipeline.robot.model import RobotModel, resolve_urdf_path
from robonav.pipeline.wire.messages import RobotDescription


def robot_description(robot: RobotModel, stamp: float | None = None) -> RobotDescription:
    """What a client needs to know of the robot: the URDF text, the planning joints and the limits
    the planner enforces (the URDF's position limits, or the config's overrides)."""
    cfg = robot.config
    return RobotDescription(
        stamp=time.time() if stamp is None else stamp, name=cfg.name,
        urdf=resolve_urdf_path(cfg.urdf).read_text(encoding="utf-8"), base_frame=cfg.base_link,
        end_effector_link=cfg.end_effector_link, joint_names=tuple(cfg.joint_names),
        lower_limits=robot.lower_limits_rad, upper_limits=robot.upper_limits_rad, max_velocity=robot.velocity_limits,
        max_acceleration=robot.acceleration_limits, max_jerk=robot.jerk_limits, home_position=robot.home_position_rad,
        fixed_joint_positions={k: float(v) for k, v in cfg.fixed_joint_positions.items()},
        allowed_collision_pairs=tuple(f"{a}|{b}" for a, b in cfg.allowed_collision_pairs), padding_m=cfg.padding_m,
        world_from_base=cfg.world_from_base.matrix)
