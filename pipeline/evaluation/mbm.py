"""MotionBenchMaker problems in the `mbm-primitives/1` JSON format, and the robot model they need.

The format (one document per problem family) is described in the shared benchmarks'
`mbm/FORMAT.md`. This module turns an already-parsed document (a mapping, as `json.load`
returns it) into frozen dataclasses; reading the file is the caller's job. Obstacles become
`SceneObject`s in the world frame, which for these files is the robot's base frame (the URDF's
root link for the UR5 set).

Parsing is strict: a wrong format string, a missing key or a value of the wrong shape raises
`ValueError` naming the problem (position in the list and its `index`) and the key.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.transforms import PoseSpec
from robonav.pipeline.types import FloatArray

MBM_FORMAT = "mbm-primitives/1"
"""The only `format` string this parser accepts."""

MBM_PANDA_POSITION_LIMITS_RAD: dict[str, tuple[float, float]] = {
    "panda_joint1": (-2.9671, 2.9671),
    "panda_joint2": (-1.8326, 1.8326),
    "panda_joint3": (-2.9671, 2.9671),
    "panda_joint4": (-3.1416, 0.0873),
    "panda_joint5": (-2.9671, 2.9671),
    "panda_joint6": (-0.0873, 3.8223),
    "panda_joint7": (-2.9671, 2.9671),
}
"""Joint limits of the MBM Panda (robowflex_resources' URDF "hard" limits) [rad].

pybullet_data's panda.urdf agrees except for panda_joint4's upper limit (0.0 there); one MBM
goal has q4 = 0.0166, so the benchmark model must use these (FORMAT.md, "Robot model")."""

_QUAT_NORM_TOLERANCE = 1e-6
"""The files carry re-normalised quaternions; anything further off is a misread value."""
_HALF_EXTENT_TOLERANCE_M = 1e-9


@dataclass(frozen=True)
class MbmProblem:
    """One planning problem: a start, its goal(s) and the obstacles, in the robot base frame.

    Attributes:
        index: The problem's number within its family (NN of MBM's scene00NN.yaml), from 1.
        start_rad: (n,) start configuration in `MbmProblemSet.joint_names` order [rad].
        goals_rad: One or more (n,) goal configurations [rad]; MBM gives exactly one.
        obstacles: Primitive obstacles posed in the world (= robot base) frame.
    """

    index: int
    start_rad: tuple[float, ...]
    goals_rad: tuple[tuple[float, ...], ...]
    obstacles: tuple[SceneObject, ...]

    @property
    def start(self) -> FloatArray:
        """(n,) start configuration as an array [rad]."""
        return np.array(self.start_rad, dtype=np.float64)

    @property
    def goal(self) -> FloatArray:
        """(n,) first goal configuration as an array [rad]."""
        return np.array(self.goals_rad[0], dtype=np.float64)


@dataclass(frozen=True)
class MbmProblemSet:
    """One `mbm-primitives/1` document: a family of problems sharing a robot description.

    Attributes:
        family: Family name (e.g. 'box', 'cage').
        robot: Robot name (e.g. 'panda').
        joint_names: Planning joints, the order of every configuration.
        fixed_joint_positions: Non-planning joint -> its constant position [rad or m].
        allowed_collision_pairs: Sorted link pairs never checked for self-collision.
        problems: The problems, in document order.
    """

    family: str
    robot: str
    joint_names: tuple[str, ...]
    fixed_joint_positions: Mapping[str, float]
    allowed_collision_pairs: tuple[tuple[str, str], ...]
    problems: tuple[MbmProblem, ...]


def parse_mbm(document: Mapping[str, Any]) -> MbmProblemSet:
    """Parse an `mbm-primitives/1` document.

    Args:
        document: The parsed JSON object of one family file.

    Returns:
        The problem set; every start and goal has one value per joint, every obstacle a
        unit quaternion and positive dimensions.

    Raises:
        ValueError: wrong format string, a missing key, or a value of the wrong type or
            shape; the message names the problem (`problems[i] (index N)`) and the key.
    """
    where = "mbm document"
    if not isinstance(document, Mapping):
        raise ValueError(f"{where}: expected a JSON object, got {type(document).__name__}")
    fmt = _get(document, "format", where)
    if fmt != MBM_FORMAT:
        raise ValueError(f"{where}: key 'format': expected {MBM_FORMAT!r}, got {fmt!r}")
    family = _string(_get(document, "family", where), where, "family")
    where = f"mbm '{family}'"
    robot = _string(_get(document, "robot", where), where, "robot")
    joint_names = tuple(_string(v, where, f"joint_names[{i}]")
                        for i, v in enumerate(_list(_get(document, "joint_names", where), where, "joint_names")))
    if not joint_names or len(set(joint_names)) != len(joint_names):
        raise ValueError(f"{where}: key 'joint_names': expected distinct names, got {list(joint_names)}")
    fixed_raw = _get(document, "fixed_joint_positions", where)
    if not isinstance(fixed_raw, Mapping):
        raise ValueError(f"{where}: key 'fixed_joint_positions': expected an object, got {type(fixed_raw).__name__}")
    fixed = {str(k): _number(v, where, f"fixed_joint_positions.{k}") for k, v in fixed_raw.items()}
    _check_units_and_base(document, where)
    self_collision = _get(document, "self_collision", where)
    if not isinstance(self_collision, Mapping):
        raise ValueError(f"{where}: key 'self_collision': expected an object, got {type(self_collision).__name__}")
    pairs = []
    for i, pair in enumerate(_list(_get(self_collision, "allowed_pairs", where, "self_collision."),
                                   where, "self_collision.allowed_pairs")):
        key = f"self_collision.allowed_pairs[{i}]"
        items = _list(pair, where, key)
        if len(items) != 2:
            raise ValueError(f"{where}: key '{key}': expected 2 link names, got {len(items)}")
        a, b = (_string(v, where, key) for v in items)
        pairs.append((a, b) if a <= b else (b, a))
    problems_raw = _list(_get(document, "problems", where), where, "problems")
    count = _get(document, "count", where)
    if isinstance(count, bool) or not isinstance(count, int) or count != len(problems_raw):
        raise ValueError(f"{where}: key 'count': expected the number of problems ({len(problems_raw)}), got {count!r}")
    problems = tuple(_problem(p, i, len(joint_names), where) for i, p in enumerate(problems_raw))
    return MbmProblemSet(family, robot, joint_names, dict(fixed), tuple(pairs), problems)


def mbm_robot_config(problems: MbmProblemSet, *, padding_m: float = 0.0,
                     base: RobotConfig | None = None, known_links: frozenset[str] | None = None) -> RobotConfig:
    """The robot config that reproduces MBM's collision model for a problem set.

    Takes the fixed (finger) positions, the allowed-collision pairs and the base pose (the
    identity, the only one the parser accepts) from the document, everything else (URDF,
    limits, ...) from `base`, the default Panda config when None. For
    the Panda the MBM joint limits (`MBM_PANDA_POSITION_LIMITS_RAD`) replace the URDF's.

    Args:
        problems: A parsed document whose joints are the base config's planning joints.
        padding_m: Robot-vs-world padding when planning [m]; MBM's own checks use none.
        base: Config to start from (the robot file the user gave).
        known_links: Links of the base robot's URDF; allowed pairs naming any other link (the
            UR5 set's MoveIt matrix names `box_link`, an object of the original scene) are
            dropped. None keeps every pair.

    Raises:
        ValueError: the document's joints differ from the base config's.
    """
    cfg = base if base is not None else RobotConfig()
    if problems.joint_names != cfg.joint_names:
        hint = "" if base is not None else " (pass the robot's file: --robot FILE)"
        raise ValueError(f"mbm '{problems.family}': robot '{problems.robot}' joint_names {list(problems.joint_names)} "
                         f"differ from robot '{cfg.name}' config's {list(cfg.joint_names)}{hint}")
    pairs = problems.allowed_collision_pairs
    if known_links is not None:
        pairs = tuple(p for p in pairs if p[0] in known_links and p[1] in known_links)
    limits = dict(cfg.position_limits_rad)
    if problems.robot == "panda" and set(MBM_PANDA_POSITION_LIMITS_RAD) == set(cfg.joint_names):
        limits = dict(MBM_PANDA_POSITION_LIMITS_RAD)
    return dataclasses.replace(
        cfg,
        fixed_joint_positions={**cfg.fixed_joint_positions, **problems.fixed_joint_positions},
        position_limits_rad=limits,
        allowed_collision_pairs=pairs,
        padding_m=padding_m,
        # The obstacles are in the robot base frame, wherever the robot file puts the robot.
        world_from_base=PoseSpec((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
    )


def _problem(raw: Any, position: int, dof: int, family_where: str) -> MbmProblem:
    where = f"{family_where} problems[{position}]"
    if not isinstance(raw, Mapping):
        raise ValueError(f"{where}: expected an object, got {type(raw).__name__}")
    index = _get(raw, "index", where)
    if isinstance(index, bool) or not isinstance(index, int) or index < 1:
        raise ValueError(f"{where}: key 'index': expected an int >= 1, got {index!r}")
    where = f"{family_where} problems[{position}] (index {index})"
    start = _vector(_get(raw, "start", where), dof, where, "start")
    goals_raw = _list(_get(raw, "goals", where), where, "goals")
    if not goals_raw:
        raise ValueError(f"{where}: key 'goals': expected at least one goal configuration, got none")
    goals = tuple(_vector(g, dof, where, f"goals[{k}]") for k, g in enumerate(goals_raw))
    obstacles_raw = _list(_get(raw, "obstacles", where), where, "obstacles")
    obstacles = tuple(_obstacle(o, k, where) for k, o in enumerate(obstacles_raw))
    names = [o.name for o in obstacles]
    for k, name in enumerate(names):
        if name in names[:k]:
            raise ValueError(f"{where}: key 'obstacles[{k}].name': duplicate name {name!r}")
    return MbmProblem(index, start, goals, obstacles)


def _obstacle(raw: Any, k: int, where: str) -> SceneObject:
    prefix = f"obstacles[{k}]"
    if not isinstance(raw, Mapping):
        raise ValueError(f"{where}: key '{prefix}': expected an object, got {type(raw).__name__}")
    name = _string(_get(raw, "name", where, f"{prefix}."), where, f"{prefix}.name")
    kind = _get(raw, "type", where, f"{prefix}.")
    if kind not in ("box", "cylinder", "sphere", "capsule"):
        raise ValueError(f"{where}: key '{prefix}.type': expected box, cylinder, sphere or capsule, got {kind!r}")
    position = _vector(_get(raw, "position", where, f"{prefix}."), 3, where, f"{prefix}.position")
    quat = _vector(_get(raw, "orientation_xyzw", where, f"{prefix}."), 4, where, f"{prefix}.orientation_xyzw")
    if abs(math.sqrt(sum(v * v for v in quat)) - 1.0) > _QUAT_NORM_TOLERANCE:
        raise ValueError(f"{where}: key '{prefix}.orientation_xyzw': expected a unit quaternion, got {list(quat)}")
    size = radius = length = None
    if kind == "box":
        size = _vector(_get(raw, "size", where, f"{prefix}."), 3, where, f"{prefix}.size")
        if "half_extents" in raw:
            half = _vector(raw["half_extents"], 3, where, f"{prefix}.half_extents")
            if any(abs(2 * h - s) > _HALF_EXTENT_TOLERANCE_M for h, s in zip(half, size)):
                raise ValueError(f"{where}: key '{prefix}.half_extents': {list(half)} is not half of size {list(size)}")
    else:
        radius = _number(_get(raw, "radius", where, f"{prefix}."), where, f"{prefix}.radius")
    if kind in ("cylinder", "capsule"):
        length = _number(_get(raw, "length", where, f"{prefix}."), where, f"{prefix}.length")
    try:
        return SceneObject(name, kind, position, quat, size_m=size, radius_m=radius, length_m=length)  # type: ignore[arg-type]
    except ValueError as exc:
        raise ValueError(f"{where}: key '{prefix}': {exc}") from exc


def _check_units_and_base(document: Mapping[str, Any], where: str) -> None:
    """The parser assumes metres, radians and world frame = robot base frame; reject anything else."""
    units = _get(document, "units", where)
    if not isinstance(units, Mapping) or units.get("length") != "m" or units.get("angle") != "rad":
        raise ValueError(f"{where}: key 'units': expected {{'length': 'm', 'angle': 'rad'}}, got {units!r}")
    base = _get(document, "base_pose", where)
    if not isinstance(base, Mapping):
        raise ValueError(f"{where}: key 'base_pose': expected an object, got {type(base).__name__}")
    position = _vector(_get(base, "position", where, "base_pose."), 3, where, "base_pose.position")
    quat = _vector(_get(base, "orientation_xyzw", where, "base_pose."), 4, where, "base_pose.orientation_xyzw")
    if any(abs(v) > 1e-12 for v in position) or any(abs(v - e) > 1e-12 for v, e in zip(quat, (0, 0, 0, 1))):
        raise ValueError(f"{where}: key 'base_pose': only the identity is supported (obstacles are taken to be in "
                         f"the robot base frame), got position {list(position)}, orientation_xyzw {list(quat)}")


def _get(mapping: Mapping[str, Any], key: str, where: str, prefix: str = "") -> Any:
    if key not in mapping:
        raise ValueError(f"{where}: key '{prefix}{key}' is missing")
    return mapping[key]


def _list(value: Any, where: str, key: str) -> Sequence[Any]:
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"{where}: key '{key}': expected a list, got {type(value).__name__}")
    return value


def _string(value: Any, where: str, key: str) -> str:
    if not isinstance(value, str) or not value:
        raise ValueError(f"{where}: key '{key}': expected a non-empty string, got {value!r}")
    return value


def _number(value: Any, where: str, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{where}: key '{key}': expected a finite number, got {value!r}")
    return float(value)


def _vector(value: Any, n: int, where: str, key: str) -> tuple[float, ...]:
    items = _list(value, where, key)
    if len(items) != n:
        raise ValueError(f"{where}: key '{key}': expected {n} numbers, got {len(items)}")
    return tuple(_number(v, where, f"{key}[{i}]") for i, v in enumerate(items))
