"""Robot description config: which URDF, which joints plan, their limits, collision settings."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from robonav.pipeline.transforms import PoseSpec

PANDA_URDF = "pybullet_data:franka_panda/panda.urdf"

DESCRIBED_FIELDS: tuple[str, ...] = (
    "urdf", "base_link", "end_effector_link", "joint_names", "max_velocity_rad_s", "max_acceleration_rad_s2",
    "max_jerk_rad_s3", "home_position_rad",
)
"""Fields a robot's URDF/SRDF decides. Their defaults are the Panda's (the default robot), so a
config file describing any other URDF must state every one (`robonav robot init` writes them)."""

CONTINUOUS_JOINT_RANGE_RAD = (-2.0 * math.pi, 2.0 * math.pi)
"""Position range planned over for a `continuous` URDF joint unless `position_limits_rad` names
it: two turns each way, so from a start within half a turn of 0 every goal angle has an equivalent
inside at most half a turn away, which the planner goes to (`turns.py`)."""


@dataclass(frozen=True)
class RobotConfig:
    """A robot arm as the planner, executor and sim see it.

    Joint position limits come from the URDF unless `position_limits_rad` overrides them;
    velocity, acceleration and jerk limits are here because URDFs carry no acceleration or
    jerk limits.
    """

    name: str = "panda"
    urdf: str = PANDA_URDF
    """URDF path; the prefix `pybullet_data:` resolves inside the pybullet_data package."""
    base_link: str = "panda_link0"
    """The link whose frame is the robot's base frame, which `world_from_base` places in the world
    (`robonav robot init` names the URDF's root link; the sim requires the root)."""
    world_from_base: PoseSpec = PoseSpec((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    """Where `base_link` stands in the world: translation [m] and scalar-last unit quaternion
    (norm within 1e-3 of 1, normalised when used). The identity (the default) makes the base
    frame the world frame. Every link pose in the world (planning, collision, IK, the sim,
    perception's self filter, the view, recordings) follows it; a base link that moves with a
    planning joint takes only the identity."""
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
    package_paths: tuple[str, ...] = ()
    """Folders holding the ROS packages `package://NAME/...` mesh URIs name (each holds NAME/ or is
    NAME/), searched before `ROS_PACKAGE_PATH` and the URDF's own folder."""

    def __post_init__(self) -> None:
        # Every problem at once: a user fixing a new robot's file should not meet them one by one.
        errors: list[str] = []

        def require(condition: bool, message: str) -> None:
            if not condition:
                errors.append(message)

        n = len(self.joint_names)
        require(n > 0, "robot.joint_names must name at least one joint")
        require(len(set(self.joint_names)) == n, f"robot.joint_names has duplicates: {list(self.joint_names)}")
        require(bool(self.urdf), "robot.urdf must name a URDF file")
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
                if i >= n:
                    break
                require(v > 0, f"robot.{label}[{i}] ({self.joint_names[i]}) must be > 0, got {v}")
        require(self.padding_m >= 0, f"robot.padding_m must be >= 0, got {self.padding_m}")
        for name, limits in self.position_limits_rad.items():
            require(name in self.joint_names,
                    f"robot.position_limits_rad names '{name}', which is not a planning joint "
                    f"(robot.joint_names: {list(self.joint_names)})")
            if len(limits) != 2:
                require(False, f"robot.position_limits_rad.{name} must be (lower, upper), got {limits}")
                continue
            lower, upper = limits
            require(math.isfinite(lower) and math.isfinite(upper),
                    f"robot.position_limits_rad.{name} must be finite, got ({lower}, {upper})")
            require(lower < upper, f"robot.position_limits_rad.{name}: lower {lower} must be < upper {upper}")
        for i, pair in enumerate(self.allowed_collision_pairs):
            require(len(pair) == 2, f"robot.allowed_collision_pairs[{i}] must be two link names, got {list(pair)}")
        if errors:
            raise ValueError("; ".join(errors) if len(errors) == 1 else
                             f"{len(errors)} problems: " + "; ".join(errors))


def missing_described_fields(data: object) -> list[str]:
    """Fields of `DESCRIBED_FIELDS` a robot mapping (as read from YAML) leaves out although it names
    a URDF other than the Panda's; empty for the Panda or a mapping that states them all."""
    if not isinstance(data, dict) or data.get("urdf", PANDA_URDF) == PANDA_URDF:
        return []
    return [name for name in DESCRIBED_FIELDS if name not in data]
