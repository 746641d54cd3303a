"""Every wire message, schema version 1 (codec in `wire.py`, spec in `docs/protocol.md`).

Field docstrings give units and shapes. `n` is the number of joints named in the message.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from robonav.pipeline.camera import CameraIntrinsics
from robonav.pipeline.wire import ErrorCode, FloatArray, Message, ProtocolError, array_field, unpack

ExecutorState = Literal["idle", "executing", "stopping", "stopped", "error"]
EXECUTOR_STATES: tuple[str, ...] = ("idle", "executing", "stopping", "stopped", "error")


def _check_same_length(owner: str, names: tuple[str, ...], **arrays: np.ndarray | None) -> None:
    for key, array in arrays.items():
        if array is not None and array.shape[-1] != len(names):
            raise ValueError(f"{owner}: '{key}' has {array.shape[-1]} joint values but {len(names)} joint names")


def _check_scaling_factors(owner: str, velocity: float | None, acceleration: float | None) -> None:
    for key, value in (("max_velocity_scaling_factor", velocity), ("max_acceleration_scaling_factor", acceleration)):
        if value is not None and not 0.0 < value <= 1.0:
            raise ValueError(f"{owner}: {key} must be in (0, 1], got {value}")


@dataclass(frozen=True)
class JointState(Message):
    """`robot/joint_states` (pub): the measured joint state."""

    stamp: float
    names: tuple[str, ...]
    position: FloatArray = array_field("<f8", (None,))
    """(n,) [rad]"""
    velocity: FloatArray = array_field("<f8", (None,))
    """(n,) [rad/s]"""

    def __post_init__(self) -> None:
        _check_same_length("JointState", self.names, position=self.position, velocity=self.velocity)


@dataclass(frozen=True)
class PointCloud(Message):
    """`camera/<cam>/cloud` (pub): points in the camera's optical frame (z forward, x right, y down)."""

    stamp: float
    camera_id: str
    points: np.ndarray = array_field("<f4", (None, 3), finite=False)
    """(N, 3) [m]; NaN/inf rows are allowed and dropped by perception."""
    seq: int = 0
    intrinsics: CameraIntrinsics | None = None


@dataclass(frozen=True)
class Occupancy(Message):
    """`perception/occupancy` (pub): the (inflated) occupancy map in the world frame."""

    stamp: float
    """Stamp of the newest cloud in the map [s]."""
    resolution_m: float
    octomap_binary: bytes
    """OctoMap `.bt` file contents (header + data) of the inflated occupied voxels."""
    occupied_centers_m: np.ndarray = array_field("<f4", (None, 3))
    """(N, 3) centres of occupied voxels before inflation [m]."""
    seq: int = 0
    frame_id: str = "world"


@dataclass(frozen=True)
class PlanRequest(Message):
    """`planner/plan` (query) request: a joint-space goal."""

    goal_positions: FloatArray = array_field("<f8", (None,))
    """(n,) goal configuration [rad], in `joint_names` order."""
    joint_names: tuple[str, ...] | None = None
    """Order of the joint vectors; default: the robot's planning joints."""
    start_positions: FloatArray | None = array_field("<f8", (None,), optional=True)
    """(n,) start configuration [rad]; default: the latest joint state."""
    planner_id: str | None = None
    allowed_planning_time: float | None = None
    """[s]"""
    seed: int | None = None
    """Seeds path simplification; OMPL's sampler is seeded once per planner process."""
    simplify: bool | None = None
    max_velocity_scaling_factor: float | None = None
    max_acceleration_scaling_factor: float | None = None
    request_id: str | None = None

    def __post_init__(self) -> None:
        if self.joint_names is not None:
            _check_same_length("PlanRequest", self.joint_names, goal_positions=self.goal_positions,
                               start_positions=self.start_positions)
        elif self.start_positions is not None and self.start_positions.shape != self.goal_positions.shape:
            raise ValueError(f"PlanRequest: start_positions has {self.start_positions.shape[0]} values, "
                             f"goal_positions {self.goal_positions.shape[0]}")
        _check_scaling_factors("PlanRequest", self.max_velocity_scaling_factor, self.max_acceleration_scaling_factor)
        if self.allowed_planning_time is not None and self.allowed_planning_time <= 0:
            raise ValueError(f"PlanRequest: allowed_planning_time must be > 0, got {self.allowed_planning_time}")


@dataclass(frozen=True)
class PlanResponse(Message):
    """`planner/plan` (query) success reply."""

    joint_names: tuple[str, ...]
    path: FloatArray = array_field("<f8", (None, None))
    """(K, n) waypoints [rad], first = start, last = goal."""
    planner_id: str = "rrtconnect"
    planning_time_s: float = 0.0
    simplification_time_s: float = 0.0
    path_length_rad: float = 0.0
    max_joint_step_rad: float = 0.0
    min_clearance_m: float | None = None
    """Smallest robot–world distance along the path [m]; absent when the world is empty."""
    waypoint_count: int = 0
    occupancy_stamp: float = 0.0
    max_velocity_scaling_factor: float | None = None
    max_acceleration_scaling_factor: float | None = None
    request_id: str | None = None
    ok: bool = True


@dataclass(frozen=True)
class ExecuteRequest(Message):
    """`executor/execute` (query) request: follow a joint path (usually a planner's)."""

    path: FloatArray = array_field("<f8", (None, None))
    """(K, n) waypoints [rad]; the first should be the current state."""
    joint_names: tuple[str, ...] | None = None
    max_velocity_scaling_factor: float | None = None
    max_acceleration_scaling_factor: float | None = None
    trajectory_id: str | None = None

    def __post_init__(self) -> None:
        if self.path.shape[0] < 1:
            raise ValueError("ExecuteRequest: path has no waypoints")
        if self.joint_names is not None:
            _check_same_length("ExecuteRequest", self.joint_names, path=self.path)
        _check_scaling_factors("ExecuteRequest", self.max_velocity_scaling_factor,
                               self.max_acceleration_scaling_factor)


@dataclass(frozen=True)
class ExecuteResponse(Message):
    """`executor/execute` reply: the trajectory was accepted and is being streamed."""

    trajectory_id: str
    duration_s: float
    waypoint_count: int
    ok: bool = True


@dataclass(frozen=True)
class StopRequest(Message):
    """`executor/stop` (query) request."""

    emergency: bool = False


@dataclass(frozen=True)
class StopResponse(Message):
    state: str
    ok: bool = True


@dataclass(frozen=True)
class Setpoint(Message):
    """`executor/setpoint` (pub), at the executor rate."""

    stamp: float
    trajectory_id: str
    names: tuple[str, ...]
    position: FloatArray = array_field("<f8", (None,))
    velocity: FloatArray = array_field("<f8", (None,))
    acceleration: FloatArray = array_field("<f8", (None,))

    def __post_init__(self) -> None:
        _check_same_length("Setpoint", self.names, position=self.position, velocity=self.velocity,
                           acceleration=self.acceleration)


@dataclass(frozen=True)
class ExecutorStatus(Message):
    """`executor/status` (pub)."""

    stamp: float
    state: str
    trajectory_id: str = ""
    progress: float = 0.0
    """Fraction of the current trajectory's duration done, 0..1."""
    time_from_start_s: float = 0.0
    duration_s: float = 0.0
    last_result: str = "none"
    """Outcome of the last trajectory: none, succeeded, stopped, aborted."""
    error_code: str = ""
    error_message: str = ""

    def __post_init__(self) -> None:
        if self.state not in EXECUTOR_STATES:
            raise ValueError(f"ExecutorStatus: state must be one of {EXECUTOR_STATES}, got {self.state!r}")


@dataclass(frozen=True)
class ContactsRequest(Message):
    """`sim/contacts` (query) request: ground-truth robot–obstacle contacts so far."""

    reset: bool = False


@dataclass(frozen=True)
class ContactsResponse(Message):
    contact_count: int
    """Number of robot–obstacle contact onsets (a touching pair counts once until it separates)."""
    pairs: tuple[str, ...] = ()
    """'link|object' for every pair that ever touched."""
    min_distance_m: float | None = None
    """Smallest robot–obstacle distance seen [m]; absent when nothing came within the sim's query range."""
    ok: bool = True


@dataclass(frozen=True)
class ErrorReply(Message):
    """Any query's structured error reply (sent with Zenoh `reply_err`)."""

    code: str
    message: str
    details: dict[str, Any] = field(default_factory=dict)
    ok: bool = False

    def __post_init__(self) -> None:
        if self.code not in {c.value for c in ErrorCode}:
            raise ValueError(f"ErrorReply: unknown error code {self.code!r}")

    @classmethod
    def from_error(cls, error: ProtocolError) -> ErrorReply:
        return cls(code=error.code.value, message=error.message, details=_plain(error.details))


def _plain(value: Any) -> Any:
    """Details must survive msgpack: numpy scalars/arrays become plain numbers/lists."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def decode_reply(payload: bytes, expected: type[Message]) -> Message:
    """Decode a query reply that is either `expected` or an `ErrorReply` (by its `ok` key)."""
    obj = unpack(payload)
    if isinstance(obj, dict) and obj.get("ok") is False:
        return ErrorReply.from_dict(obj)
    return expected.from_dict(obj)


ALL_MESSAGES: tuple[type[Message], ...] = (
    JointState, PointCloud, Occupancy, PlanRequest, PlanResponse, ExecuteRequest, ExecuteResponse,
    StopRequest, StopResponse, Setpoint, ExecutorStatus, ContactsRequest, ContactsResponse, ErrorReply,
)
