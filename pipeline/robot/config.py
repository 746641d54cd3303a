"""Robot description config: which URDF, which joints plan, their limits, collision settings."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from robonav.pipeline.config import require


@dataclass(frozen=True)
class RobotConfig:
    """A robot arm as the planner, executor and sim see it.

    Joint position limits come from the URDF unless `position_limits_rad` overrides them;
    velocity, acceleration and jerk limits are here because URDFs carry no acceleration or
    jerk limits.
    """

    name: str = "panda"
    urdf: str = "pybullet_data:franka_panda/panda.urdf"
    """URDF path; the prefix `pybullet_data:` resolves inside the pybullet_data package."""
    base_link: str = "panda_link0"
    """Link whose frame is the world frame (the robot base frame)."""
    end_effector_link: str = "panda_hand"
    joint_names: tuple[str, ...] = (
        "panda_joint1", "panda_joint2", "panda_joint3", "panda_joint4",
        "panda_joint5", "panda_joint6", "panda_joint7",
    )
    """Planning joints, in the order of every configuration vector."""
    fixed_joint_positions: dict[str, float] = field(default_factory=dict)
    """Joints outside the planning group held at a constant position [rad or m]."""
    position_limits_rad: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Planning joint name -> (lower, upper) position limits replacing the URDF's [rad, or m for
    prismatic joints]; joints not named keep their URDF limits. For models whose URDF limits
    differ from the robot a dataset was made with (MotionBenchMaker's Panda allows q4 <= 0.0873,
    pybullet_data's URDF says 0.0)."""
    max_velocity_rad_s: tuple[float, ...] = (2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61)
    max_acceleration_rad_s2: tuple[float, ...] = (15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0)
    max_jerk_rad_s3: tuple[float, ...] = (7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0)
    home_position_rad: tuple[float, ...] = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)
    collision_links: tuple[str, ...] = ()
    """Links with collision geometry that are checked; empty means every link with geometry."""
    allowed_collision_pairs: tuple[tuple[str, str], ...] = ()
    """Link pairs never checked for self-collision (MoveIt's allowed-collision matrix)."""
    padding_m: float = 0.01
    """Robot-vs-world padding added to link shapes when planning [m]; self-collision is unpadded."""

    def __post_init__(self) -> None:
        n = len(self.joint_names)
        require(n > 0, "robot.joint_names must name at least one joint")
        require(len(set(self.joint_names)) == n, f"robot.joint_names has duplicates: {list(self.joint_names)}")
        for label, values in (
            ("max_velocity_rad_s", self.max_velocity_rad_s),
            ("max_acceleration_rad_s2", self.max_acceleration_rad_s2),
            ("max_jerk_rad_s3", self.max_jerk_rad_s3),
            ("home_position_rad", self.home_position_rad),
        ):
            require(len(values) == n, f"robot.{label} has {len(values)} values, expected {n} (one per joint)")
        for label, values in (
            ("max_velocity_rad_s", self.max_velocity_rad_s),
            ("max_acceleration_rad_s2", self.max_acceleration_rad_s2),
            ("max_jerk_rad_s3", self.max_jerk_rad_s3),
        ):
            for i, v in enumerate(values):
                require(v > 0, f"robot.{label}[{i}] ({self.joint_names[i]}) must be > 0, got {v}")
        require(self.padding_m >= 0, f"robot.padding_m must be >= 0, got {self.padding_m}")
        for name, limits in self.position_limits_rad.items():
            require(name in self.joint_names,
                    f"robot.position_limits_rad names '{name}', which is not a planning joint "
                    f"(robot.joint_names: {list(self.joint_names)})")
            require(len(limits) == 2, f"robot.position_limits_rad.{name} must be (lower, upper), got {limits}")
            lower, upper = limits
            require(math.isfinite(lower) and math.isfinite(upper),
                    f"robot.position_limits_rad.{name} must be finite, got ({lower}, {upper})")
            require(lower < upper, f"robot.position_limits_rad.{name}: lower {lower} must be < upper {upper}")
