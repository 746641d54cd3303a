"""Every wire message, schema version 1 (codec in `wire.py`, spec in `docs/protocol.md`).

Field docstrings give units and shapes. `n` is the number of joints named in the message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np

from robonav.pipeline.camera import CameraIntrinsics
from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire.codec import Message, ProtocolError, array_field, unpack
from robonav.pipeline.wire.codes import ErrorCode, ExecutionResult, ExecutionState


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
    labels: np.ndarray | None = array_field("<i4", (None,), optional=True)
    """(N,) object label of each point (a key of `label_names`), -1 for none; absent: unlabelled."""
    label_names: dict[int, str] | None = None
    """Label -> object name ('robot' for the arm). On the wire a map with decimal-string keys."""

    def __post_init__(self) -> None:
        _check_labels("PointCloud", self, self.points.shape[:1])

    def _fields_to_dict(self) -> dict[str, Any]:
        return _string_label_keys(super()._fields_to_dict())


@dataclass(frozen=True)
class DepthImage(Message):
    """`camera/<cam>/depth` (pub): a depth image in the camera's optical frame, with its camera model."""

    stamp: float
    camera_id: str
    intrinsics: CameraIntrinsics
    depth_m: np.ndarray = array_field("<f4", (None, None), finite=False)
    """(H, W) depth along the optical axis (z, not ray length) [m]; inf or NaN: no return."""
    seq: int = 0
    labels: np.ndarray | None = array_field("<i4", (None, None), optional=True)
    """(H, W) object label per pixel (a key of `label_names`), -1 for none; absent: unlabelled."""
    label_names: dict[int, str] | None = None
    """Label -> object name ('robot' for the arm). On the wire a map with decimal-string keys."""

    def __post_init__(self) -> None:
        if self.depth_m.shape != (self.intrinsics.height, self.intrinsics.width):
            raise ValueError(f"DepthImage: depth_m has shape {list(self.depth_m.shape)}, the intrinsics say "
                             f"[{self.intrinsics.height}, {self.intrinsics.width}]")
        _check_labels("DepthImage", self, self.depth_m.shape)

    def _fields_to_dict(self) -> dict[str, Any]:
        return _string_label_keys(super()._fields_to_dict())


def _check_labels(owner: str, message: Any, shape: tuple[int, ...]) -> None:
    """Labels match the points/pixels; label_names keys become ints (msgpack keys travel as strings)."""
    if message.labels is not None and message.labels.shape != shape:
        raise ValueError(f"{owner}: labels has shape {list(message.labels.shape)}, expected {list(shape)}")
    if message.label_names is None:
        return
    names: dict[int, str] = {}
    for key, name in message.label_names.items():
        if isinstance(key, bool) or not isinstance(name, str) or not (
                isinstance(key, int) or (isinstance(key, str) and key.lstrip("-").isdigit())):
            raise ValueError(f"{owner}: label_names must map integer labels to names, got {key!r}: {name!r}")
        names[int(key)] = name
    object.__setattr__(message, "label_names", names)


def _string_label_keys(out: dict[str, Any]) -> dict[str, Any]:
    if "label_names" in out:
        out["label_names"] = {str(k): v for k, v in out["label_names"].items()}
    return out


@dataclass(frozen=True)
class Occupancy(Message):
    """`perception/occupancy` (pub): the (inflated) occupancy map in the world frame."""

    stamp: float
    """Stamp of the newest cloud in the map [s]."""
    resolution_m: float
    octomap_binary: bytes
    """OctoMap `.bt` file contents (header + data) of the inflated occupied voxels."""
    occupied_centers_m: np.ndarray = array_field("<f4", (None, 3))
    """(N, 3) centers of occupied voxels before inflation [m]."""
    seq: int = 0
    frame_id: str = "world"
    camera_frames: dict[str, int] | None = None
    """Camera id -> frames integrated since the last clear or perception start, for every
    configured camera (0 for one not heard from); absent from older producers."""
    inflation_m: float | None = None
    """How far `octomap_binary` grows the voxels of `occupied_centers_m` [m]: with it, a planner
    may keep that clearance off the seen voxels on the way and release it near a query's start
    and goal (docs/architecture.md); absent from older producers (the octree is then the map)."""

    ADDED_KEYS: ClassVar[tuple[str, ...]] = ("inflation_m",)

    def __post_init__(self) -> None:
        if self.camera_frames is not None and any(n < 0 for n in self.camera_frames.values()):
            raise ValueError(f"Occupancy: camera_frames must be >= 0, got {self.camera_frames}")
        if self.inflation_m is not None and not (math.isfinite(self.inflation_m) and self.inflation_m >= 0):
            raise ValueError(f"Occupancy: inflation_m must be finite and >= 0, got {self.inflation_m}")


@dataclass(frozen=True)
class Clusters(Message):
    """`perception/clusters` (pub): obstacles as connected groups of occupied voxels, world frame."""

    stamp: float
    """Stamp of the newest frame in the map [s]."""
    ids: np.ndarray = array_field("<i4", (None,))
    """(K,) cluster ids, unique within one message (not tracked across messages)."""
    centroids_m: np.ndarray = array_field("<f4", (None, 3))
    """(K, 3) mean of each cluster's voxel centers [m]."""
    bbox_min_m: np.ndarray = array_field("<f4", (None, 3))
    """(K, 3) lower corner of each cluster's axis-aligned box (voxel faces) [m]."""
    bbox_max_m: np.ndarray = array_field("<f4", (None, 3))
    """(K, 3) upper corner [m]."""
    voxel_counts: np.ndarray = array_field("<i4", (None,))
    """(K,) occupied voxels in each cluster."""
    labels: tuple[str, ...] = ()
    """K names: the most frequent label the cameras saw in the cluster (e.g. the simulator's
    object name), or "" when the cameras carry no labels."""
    seq: int = 0
    frame_id: str = "world"


@dataclass(frozen=True)
class PerceptionClearRequest(Message):
    """`perception/clear` (query) request: forget the whole occupancy map."""


@dataclass(frozen=True)
class PerceptionClearResponse(Message):
    cleared_voxels: int
    """Occupied voxels that were forgotten."""
    ok: bool = True


@dataclass(frozen=True)
class PerceptionStatusRequest(Message):
    """`perception/status` (query) request: counters and timings of the perception service."""


@dataclass(frozen=True)
class PerceptionStatusResponse(Message):
    frames: int
    """Frames integrated into the map."""
    published: int
    """Occupancy maps published."""
    dropped: dict[str, int]
    """Frames not integrated, by reason: bad_message, too_large, unknown_camera, no_joint_state,
    future_stamp, out_of_order, jumped_back, no_intrinsics, before_clear, empty, unsupported,
    stale (replaced by a newer frame before it was processed), internal_error; joint states not
    kept: joint_state_incomplete, joint_state_future_stamp, joint_state_out_of_order,
    joint_state_jumped_back."""
    occupied_voxels: int
    stage_ms: dict[str, float]
    """Wall time per stage of the last frame [ms]."""
    ok: bool = True
    camera_frames: dict[str, int] | None = None
    """Camera id -> frames integrated since the last clear or start (as in `Occupancy`)."""


@dataclass(frozen=True)
class PlanRequest(Message):
    """`planner/plan` (query) request. Exactly one goal form: `goal_positions`, `goal_set` or
    `goal_position_m` (a Cartesian goal for `goal_link`)."""

    goal_positions: FloatArray | None = array_field("<f8", (None,), optional=True)
    """(n,) goal configuration [rad], in `joint_names` order."""
    joint_names: tuple[str, ...] | None = None
    """Order of the joint vectors; default: the robot's planning joints."""
    start_positions: FloatArray | None = array_field("<f8", (None,), optional=True)
    """(n,) start configuration [rad]; default: the latest joint state."""
    goal_set: FloatArray | None = array_field("<f8", (None, None), optional=True)
    """(G, n) several joint goals [rad]; the path ends at whichever it reaches."""
    goal_link: str | None = None
    """Link of a Cartesian goal; default: the robot's end-effector link."""
    goal_position_m: FloatArray | None = array_field("<f8", (3,), optional=True)
    """(3,) target position of `goal_link` in the world frame [m]."""
    goal_quat_xyzw: FloatArray | None = array_field("<f8", (4,), optional=True)
    """(4,) target orientation of `goal_link`; absent: any orientation."""
    position_tolerance_m: float | None = None
    """Cartesian goal position tolerance [m]; default 0.001."""
    orientation_tolerance_rad: float | None = None
    """Cartesian goal rotation-angle tolerance [rad]; default 0.01."""
    goal_tolerance_rad: float | None = None
    """Joint goal tolerance per joint [rad]; default 0 (exact)."""
    planner_id: str | None = None
    allowed_planning_time: float | None = None
    """[s]"""
    num_planning_attempts: int | None = None
    seed: int | None = None
    """Seeds IK restarts, goal sampling and path simplification; OMPL's sampler is seeded once
    per planner process."""
    simplify: bool | None = None
    workspace_min_m: FloatArray | None = array_field("<f8", (3,), optional=True)
    """(3,) lower corner of a world-frame box the end-effector link must stay in [m]."""
    workspace_max_m: FloatArray | None = array_field("<f8", (3,), optional=True)
    max_velocity_scaling_factor: float | None = None
    max_acceleration_scaling_factor: float | None = None
    request_id: str | None = None

    def __post_init__(self) -> None:
        forms = [k for k in ("goal_positions", "goal_set", "goal_position_m") if getattr(self, k) is not None]
        if len(forms) != 1:
            raise ValueError(f"PlanRequest: give exactly one of goal_positions, goal_set, goal_position_m "
                             f"(got {', '.join(forms) or 'none'})")
        if self.goal_position_m is None:
            for key in ("goal_link", "goal_quat_xyzw", "position_tolerance_m", "orientation_tolerance_rad"):
                if getattr(self, key) is not None:
                    raise ValueError(f"PlanRequest: '{key}' belongs to a Cartesian goal (goal_position_m)")
        if self.goal_set is not None and self.goal_set.shape[0] == 0:
            raise ValueError("PlanRequest: goal_set must hold at least one goal")
        joint_vectors = {"goal_positions": self.goal_positions, "goal_set": self.goal_set,
                         "start_positions": self.start_positions}
        if self.joint_names is not None:
            _check_same_length("PlanRequest", self.joint_names, **joint_vectors)
        else:
            lengths = {k: v.shape[-1] for k, v in joint_vectors.items() if v is not None}
            if len(set(lengths.values())) > 1:
                raise ValueError(f"PlanRequest: joint vectors differ in length: {lengths}")
        if self.goal_quat_xyzw is not None and not 0.5 < float(np.linalg.norm(self.goal_quat_xyzw)) < 2.0:
            raise ValueError(f"PlanRequest: goal_quat_xyzw must be a unit quaternion, got {self.goal_quat_xyzw.tolist()}")
        for key in ("position_tolerance_m", "orientation_tolerance_rad", "goal_tolerance_rad"):
            value = getattr(self, key)
            if value is not None and not value >= 0:
                raise ValueError(f"PlanRequest: {key} must be >= 0, got {value}")
        if (self.workspace_min_m is None) != (self.workspace_max_m is None):
            raise ValueError("PlanRequest: give both workspace_min_m and workspace_max_m, or neither")
        if self.workspace_min_m is not None and not np.all(self.workspace_min_m < self.workspace_max_m):
            raise ValueError("PlanRequest: workspace_min_m must be below workspace_max_m in x, y and z")
        if self.num_planning_attempts is not None and self.num_planning_attempts < 1:
            raise ValueError(f"PlanRequest: num_planning_attempts must be >= 1, got {self.num_planning_attempts}")
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
    """The planner that found the path (for `auto`: the one it chose or that won the race;
    `direct` when the straight segment was free)."""
    goal_index: int = 0
    """Index into `goal_set` (or into the IK solutions of a Cartesian goal) of the goal reached."""
    goal_positions: FloatArray | None = array_field("<f8", (None,), optional=True)
    """(n,) the goal the path ends at [rad] (= the last waypoint)."""
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
    start_escaped: bool = False
    """The start was inside the robot's padding around the occupancy map (bare links clear): the
    first segment leaves the padding through states where the bare links stay clear of the map."""
    scene_revision: int | None = None
    """Revision of the planner scene the path was planned in; pass it on as
    `ExecuteRequest.scene_revision` so the executor checks the path against that scene or a newer one."""
    ok: bool = True

    ADDED_KEYS: ClassVar[tuple[str, ...]] = ("scene_revision",)


@dataclass(frozen=True)
class ExecuteRequest(Message):
    """`executor/execute` (query) request: follow a joint path (usually a planner's)."""

    path: FloatArray = array_field("<f8", (None, None))
    """(K, n) waypoints [rad]; the first should be the current state."""
    joint_names: tuple[str, ...] | None = None
    max_velocity_scaling_factor: float | None = None
    max_acceleration_scaling_factor: float | None = None
    trajectory_id: str | None = None
    replan: bool = False
    """When a new obstacle blocks the rest of the path: stop, plan again from the rest state to
    the path's last waypoint, continue (MoveIt's `replan`). Without it the arm stops with
    error PATH_BLOCKED."""
    replan_attempts: int | None = None
    """Plans tried per block before giving up; default executor.replan_attempts."""
    occupancy_stamp: float | None = None
    """`PlanResponse.occupancy_stamp` of the plan this path came from. Accepted for compatibility,
    no longer used: the executor checks the motion against its own newest map and watches every
    voxel not in that map, whatever map the plan saw."""
    scene_revision: int | None = None
    """The planner scene revision the path must be checked against, or a newer one
    (`PlanResponse.scene_revision`, or `SceneResponse.revision` of a change just made): the
    executor waits up to `executor.scene_wait_s` for it to arrive on `planner/scene_state`, then
    refuses with SCENE_MISSING. Without it the executor checks against the last scene it received."""

    def __post_init__(self) -> None:
        if self.path.shape[0] < 1:
            raise ValueError("ExecuteRequest: path has no waypoints")
        if self.scene_revision is not None and self.scene_revision < 0:
            raise ValueError(f"ExecuteRequest: scene_revision must be >= 0, got {self.scene_revision}")
        if self.replan_attempts is not None and self.replan_attempts < 1:
            raise ValueError(f"ExecuteRequest: replan_attempts must be >= 1, got {self.replan_attempts}")
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
    check_ms: float | None = None
    """Time the executor took to time-parameterize and check the motion [ms]."""
    checked_samples: int | None = None
    """States of the motion checked against the map and the scene."""


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
    state: ExecutionState
    trajectory_id: str = ""
    progress: float = 0.0
    """Fraction of the current trajectory's duration done, 0..1."""
    time_from_start_s: float = 0.0
    duration_s: float = 0.0
    last_result: ExecutionResult = ExecutionResult.NONE
    """Outcome of the last trajectory: none, succeeded, stopped, aborted."""
    error_code: str = ""
    """An `ErrorCode` value in state `error` (JOINT_STATE_STALE, TRACKING_ERROR, PATH_BLOCKED,
    OCCUPANCY_STALE), else ""."""
    error_message: str = ""
    replans: int = 0
    """New paths planned for this trajectory id after its path was blocked."""
    blocked_after_frame_s: float | None = None
    """At the last block: from the stamp of the newest camera frame in the map that showed it to
    the stop command [s]."""
    blocked_stamp: float | None = None
    """Wall-clock time of that stop command [s]."""

    def __post_init__(self) -> None:
        # Plain strings are accepted and checked here, so a bad state fails where it is made.
        object.__setattr__(self, "state", ExecutionState(self.state))
        object.__setattr__(self, "last_result", ExecutionResult(self.last_result))


@dataclass(frozen=True)
class ExecutorPath(Message):
    """`executor/path` (latched pub): the path of every trajectory the executor accepted."""

    stamp: float
    trajectory_id: str
    joint_names: tuple[str, ...]
    path: FloatArray = array_field("<f8", (None, None))
    """(K, n) waypoints as requested [rad]; row 0 is the start."""
    duration_s: float = 0.0
    """Trajectory duration [s]."""

    def __post_init__(self) -> None:
        _check_same_length("ExecutorPath", self.joint_names, path=self.path)


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
    min_distance_pair: str | None = None
    """'link|object' of that smallest distance."""
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


SceneOperation = Literal["add", "move", "remove", "attach", "detach", "clear", "list"]
SCENE_OPERATIONS: tuple[str, ...] = ("add", "move", "remove", "attach", "detach", "clear", "list")
SCENE_OBJECT_TYPES: tuple[str, ...] = ("box", "cylinder", "sphere", "capsule", "mesh")
_SHAPE_KEYS: tuple[str, ...] = ("type", "size_m", "radius_m", "length_m", "vertices_m", "triangles")


def _invalid(message: str, key: str) -> ProtocolError:
    return ProtocolError(ErrorCode.INVALID_REQUEST, message, {"key": key})


@dataclass(frozen=True, eq=False)
class SceneObjectSpec(Message):
    """One collision object in a `planner/scene` request; travels nested, without `v`.

    Shapes follow `SceneObject`: box `size_m` (full sides), sphere `radius_m`, cylinder and
    capsule `radius_m` + `length_m` along local z (a capsule's between its cap centers), mesh
    `vertices_m` + `triangles` in the object frame.
    """

    name: str
    type: str | None = None
    """box, cylinder, sphere, capsule or mesh; required to add (or attach) a new object."""
    position_m: tuple[float, ...] | None = None
    """(3,) origin of the object in `frame_id` [m]."""
    quat_xyzw: tuple[float, ...] | None = None
    """(4,) orientation in `frame_id`, scalar last; default identity (move: unchanged)."""
    size_m: tuple[float, ...] | None = None
    """(3,) box full side lengths [m]."""
    radius_m: float | None = None
    length_m: float | None = None
    vertices_m: FloatArray | None = array_field("<f8", (None, 3), optional=True)
    """(N, 3) mesh vertices in the object frame [m]."""
    triangles: np.ndarray | None = array_field("<i8", (None, 3), optional=True)
    """(M, 3) mesh vertex indices, int."""
    frame_id: str | None = None
    """Frame of the pose: "world" (default) or, for attach, the attach link."""

    def __post_init__(self) -> None:
        for key, length in (("position_m", 3), ("quat_xyzw", 4), ("size_m", 3)):
            value = getattr(self, key)
            if value is not None and len(value) != length:
                raise _invalid(f"SceneObjectSpec '{self.name}': {key} needs {length} values, got {len(value)}", key)
        if self.type is not None and self.type not in SCENE_OBJECT_TYPES:
            raise _invalid(f"SceneObjectSpec '{self.name}': type must be one of {list(SCENE_OBJECT_TYPES)}, got {self.type!r}",
                           "type")

    def _key(self) -> tuple[Any, ...]:
        return tuple((v.shape, v.tobytes()) if isinstance(v, np.ndarray) else v
                     for v in (getattr(self, f) for f in self.__dataclass_fields__))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, SceneObjectSpec) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())


@dataclass(frozen=True)
class SceneRequest(Message):
    """`planner/scene` (query) request: change or list the planning scene's collision objects.

    `add` adds `objects` to the world, replacing same-named ones; `move` sets only the pose of
    world `objects`; `remove` drops `names` (world or attached); `attach` fixes `objects` (new,
    posed in `frame_id`) or `names` (world objects, where they are) to `link`; `detach` turns
    attached `names` back into world objects where the robot holds them; `clear` drops all;
    `list` changes nothing. Every operation answers with the whole scene.
    """

    operation: str
    objects: tuple[SceneObjectSpec, ...] = ()
    names: tuple[str, ...] = ()
    link: str | None = None
    """attach: the robot link the objects move with."""
    touch_links: tuple[str, ...] | None = None
    """attach: robot links the objects may touch besides `link` (e.g. the fingers)."""
    joint_names: tuple[str, ...] | None = None
    """Order of `joint_positions`; default the robot's planning joints."""
    joint_positions: FloatArray | None = array_field("<f8", (None,), optional=True)
    """(n,) robot state for attach/detach with world poses [rad]; default the latest joint state."""
    request_id: str | None = None

    def __post_init__(self) -> None:
        op = self.operation
        if op not in SCENE_OPERATIONS:
            raise _invalid(f"SceneRequest: operation must be one of {list(SCENE_OPERATIONS)}, got {op!r}", "operation")
        wants = {"add": "objects", "move": "objects", "remove": "names", "detach": "names"}.get(op)
        if wants == "objects" and (not self.objects or self.names):
            raise _invalid(f"SceneRequest: {op} needs 'objects' (and no 'names')", "objects")
        if wants == "names" and (not self.names or self.objects):
            raise _invalid(f"SceneRequest: {op} needs 'names' (and no 'objects')", "names")
        if op == "attach" and (not self.link or not (self.objects or self.names)):
            raise _invalid("SceneRequest: attach needs 'link' and 'objects' or 'names'", "link" if not self.link else "objects")
        if op in ("clear", "list") and (self.objects or self.names):
            raise _invalid(f"SceneRequest: {op} takes no 'objects' or 'names'", "objects" if self.objects else "names")
        every = [o.name for o in self.objects] + list(self.names)
        for i, name in enumerate(every):
            if not name or name in every[:i]:
                key = f"objects[{i}].name" if i < len(self.objects) else f"names[{i - len(self.objects)}]"
                raise _invalid(f"SceneRequest: object name {name!r} is empty or given twice", key)
        for i, obj in enumerate(self.objects):
            if op == "add" or (op == "attach" and obj.type is not None):
                for key in ("type", "position_m"):
                    if getattr(obj, key) is None:
                        raise _invalid(f"SceneRequest: {op} of '{obj.name}' needs {key}", f"objects[{i}].{key}")
            if op == "move":
                shape_keys = [k for k in _SHAPE_KEYS if getattr(obj, k) is not None]
                if shape_keys:
                    raise _invalid(f"SceneRequest: move changes only the pose; objects[{i}] has {shape_keys[0]}",
                                   f"objects[{i}].{shape_keys[0]}")
                if obj.position_m is None and obj.quat_xyzw is None:
                    raise _invalid(f"SceneRequest: move of '{obj.name}' needs position_m or quat_xyzw", f"objects[{i}].position_m")
        if self.joint_names is not None and self.joint_positions is not None:
            _check_same_length("SceneRequest", self.joint_names, joint_positions=self.joint_positions)


@dataclass(frozen=True)
class SceneObjectState(Message):
    """One object of the planning scene in a `planner/scene` reply; travels nested, without `v`."""

    name: str
    type: str
    position_m: tuple[float, ...]
    """(3,) origin in `frame_id` [m]."""
    quat_xyzw: tuple[float, ...]
    """(4,) orientation in `frame_id`, scalar last."""
    frame_id: str = "world"
    """"world", or the link of an attached object (the pose is then link_from_object)."""
    attached_link: str | None = None
    """The link the object is attached to; absent for world objects."""
    touch_links: tuple[str, ...] = ()
    size_m: tuple[float, ...] | None = None
    radius_m: float | None = None
    length_m: float | None = None
    vertex_count: int | None = None
    """Mesh only: number of vertices (the arrays are not echoed)."""


@dataclass(frozen=True)
class SceneResponse(Message):
    """`planner/scene` (query) success reply: the whole scene after the operation."""

    revision: int
    """Scene revision: +1 for every request that changed the scene."""
    objects: tuple[SceneObjectState, ...] = ()
    """World objects, then attached ones, each by name."""
    request_id: str | None = None
    ok: bool = True


@dataclass(frozen=True)
class AttachedObjectSpec(Message):
    """One object fixed to a robot link in a `planner/scene_state` publication; travels nested, without `v`."""

    link: str
    """The robot link it moves with."""
    object: SceneObjectSpec
    """The object posed in `link`'s frame (link_from_object; `frame_id` is the link)."""
    touch_links: tuple[str, ...] = ()
    """Robot links it may touch besides `link`."""


@dataclass(frozen=True)
class PlanningSceneState(Message):
    """`planner/scene_state` (latched pub): the planner's whole collision scene, sent when the
    planner starts and after every change; what the executor checks an execute against."""

    stamp: float
    """When the scene took this form [s]."""
    revision: int
    """As in `SceneResponse`: +1 for every request that changed the scene (0 for a fresh planner)."""
    objects: tuple[SceneObjectSpec, ...] = ()
    """World objects, complete (mesh arrays included), posed in the world frame."""
    attached: tuple[AttachedObjectSpec, ...] = ()
    """Objects fixed to robot links."""


@dataclass(frozen=True)
class ContactEvent(Message):
    """`sim/contacts/events` (pub): a robot link started or stopped touching an obstacle (ground truth)."""

    stamp: float
    link: str
    object: str
    event: str
    """'begin' or 'end'."""
    distance_m: float = 0.0
    """Deepest signed distance of the pair at this step [m] (<= 0 at 'begin'; 0 at 'end')."""
    contact_count: int = 0
    """Contact onsets counted so far (as `sim/contacts` reports them)."""

    def __post_init__(self) -> None:
        if self.event not in ("begin", "end"):
            raise ValueError(f"ContactEvent: event must be 'begin' or 'end', got {self.event!r}")


SIM_OBJECT_OPERATIONS: tuple[str, ...] = ("list", "add", "move", "remove", "set", "script", "cancel")
OBJECT_MOTION_ACTIONS: tuple[str, ...] = ("move", "remove", "add")


@dataclass(frozen=True)
class ObjectMotionSpec(Message):
    """One scripted change of a sim object in a `sim/objects` script request; travels nested, without `v`.

    Fires once, when its trigger holds: `at_s` seconds (sim time) after the request, or when
    `executor/status` reports `at_progress` of a trajectory (`trajectory_id`, or any trajectory
    that is executing), or at once when neither is given. `move` slides the object in a
    straight line (and a slerp) to the target pose over `duration_s`; `remove` removes it; `add`
    adds `object` (its pose is the pose it appears at).
    """

    name: str
    action: str = "move"
    object: SceneObjectSpec | None = None
    """add: the new object (type, shape, pose; `name` must match)."""
    position_m: tuple[float, ...] | None = None
    """move: (3,) target position in the world frame [m]; absent keeps the position."""
    quat_xyzw: tuple[float, ...] | None = None
    """move: (4,) target orientation; absent keeps the orientation."""
    duration_s: float = 0.0
    """move: time to slide to the target (sim time) [s]; 0 jumps."""
    at_s: float | None = None
    """Trigger: sim seconds after the request."""
    at_progress: float | None = None
    """Trigger: executor progress in [0, 1]."""
    trajectory_id: str | None = None
    """With at_progress: only this trajectory's progress counts."""

    def __post_init__(self) -> None:
        if self.action not in OBJECT_MOTION_ACTIONS:
            raise _invalid(f"ObjectMotionSpec '{self.name}': action must be one of {list(OBJECT_MOTION_ACTIONS)}, "
                           f"got {self.action!r}", "action")
        if self.at_s is not None and self.at_progress is not None:
            raise _invalid(f"ObjectMotionSpec '{self.name}': give at_s or at_progress, not both", "at_progress")
        if self.at_progress is not None and not 0.0 <= self.at_progress <= 1.0:
            raise _invalid(f"ObjectMotionSpec '{self.name}': at_progress must be in [0, 1], got {self.at_progress}",
                           "at_progress")
        if self.at_s is not None and self.at_s < 0:
            raise _invalid(f"ObjectMotionSpec '{self.name}': at_s must be >= 0, got {self.at_s}", "at_s")
        if self.duration_s < 0:
            raise _invalid(f"ObjectMotionSpec '{self.name}': duration_s must be >= 0, got {self.duration_s}", "duration_s")
        if self.action == "add" and (self.object is None or self.object.name != self.name):
            raise _invalid(f"ObjectMotionSpec '{self.name}': add needs 'object' with the same name", "object")
        if self.action == "move" and self.position_m is None and self.quat_xyzw is None:
            raise _invalid(f"ObjectMotionSpec '{self.name}': move needs position_m or quat_xyzw", "position_m")
        for key, length in (("position_m", 3), ("quat_xyzw", 4)):
            value = getattr(self, key)
            if value is not None and len(value) != length:
                raise _invalid(f"ObjectMotionSpec '{self.name}': {key} needs {length} values, got {len(value)}", key)


@dataclass(frozen=True)
class SimObjectsRequest(Message):
    """`sim/objects` (query) request: list, change or script the simulated obstacles (ground truth).

    `list` changes nothing; `add` adds `objects` (replacing same-named ones); `move` sets the
    pose of existing `objects`; `remove` drops `names`; `set` replaces the whole scene with
    `objects` (none: an empty scene); `script` arms `motions`; `cancel` drops pending motions.
    """

    operation: str
    objects: tuple[SceneObjectSpec, ...] = ()
    names: tuple[str, ...] = ()
    motions: tuple[ObjectMotionSpec, ...] = ()
    request_id: str | None = None

    def __post_init__(self) -> None:
        op = self.operation
        if op not in SIM_OBJECT_OPERATIONS:
            raise _invalid(f"SimObjectsRequest: operation must be one of {list(SIM_OBJECT_OPERATIONS)}, got {op!r}",
                           "operation")
        if op in ("add", "move") and not self.objects:
            raise _invalid(f"SimObjectsRequest: {op} needs 'objects'", "objects")
        if op == "remove" and not self.names:
            raise _invalid("SimObjectsRequest: remove needs 'names'", "names")
        if op == "script" and not self.motions:
            raise _invalid("SimObjectsRequest: script needs 'motions'", "motions")
        for key in ("objects", "names", "motions"):
            allowed = {"objects": ("add", "move", "set"), "names": ("remove",), "motions": ("script",)}[key]
            if getattr(self, key) and op not in allowed:
                raise _invalid(f"SimObjectsRequest: {op} takes no '{key}'", key)
        names = [o.name for o in self.objects]
        for i, name in enumerate(names):
            if not name or name in names[:i]:
                raise _invalid(f"SimObjectsRequest: object name {name!r} is empty or given twice", f"objects[{i}].name")
            if name == "robot":
                raise _invalid("SimObjectsRequest: 'robot' is reserved for the arm", f"objects[{i}].name")
        for i, obj in enumerate(self.objects):
            if op in ("add", "set"):
                for key in ("type", "position_m"):
                    if getattr(obj, key) is None:
                        raise _invalid(f"SimObjectsRequest: {op} of '{obj.name}' needs {key}", f"objects[{i}].{key}")
            if op == "move":
                shape_keys = [k for k in _SHAPE_KEYS if getattr(obj, k) is not None]
                if shape_keys:
                    raise _invalid(f"SimObjectsRequest: move changes only the pose; objects[{i}] has {shape_keys[0]}",
                                   f"objects[{i}].{shape_keys[0]}")
                if obj.position_m is None and obj.quat_xyzw is None:
                    raise _invalid(f"SimObjectsRequest: move of '{obj.name}' needs position_m or quat_xyzw",
                                   f"objects[{i}].position_m")
            if obj.frame_id not in (None, "world"):
                raise _invalid(f"SimObjectsRequest: sim objects are posed in 'world', got {obj.frame_id!r}",
                               f"objects[{i}].frame_id")


@dataclass(frozen=True)
class SimObjectsResponse(Message):
    """`sim/objects` (query) success reply: every sim obstacle at its true pose after the request."""

    stamp: float
    """Wall time of the snapshot [s]."""
    sim_time_s: float
    """Simulated time since the sim started [s]."""
    revision: int
    """+1 for every request or motion that changed the scene."""
    objects: tuple[SceneObjectState, ...] = ()
    pending_motions: int = 0
    """Scripted motions armed but not finished."""
    fired_motions: int = 0
    """Scripted motions triggered since the sim started."""
    request_id: str | None = None
    ok: bool = True


@dataclass(frozen=True)
class SimStatsRequest(Message):
    """`sim/stats` (query) request: how well the sim keeps real time."""

    reset: bool = False
    """Start a new measurement window after answering."""


@dataclass(frozen=True)
class CameraStats(Message):
    """Frames of one camera in a `sim/stats` reply; travels nested, without `v`."""

    camera_id: str
    frames: int = 0
    render_ms_p50: float = 0.0
    render_ms_max: float = 0.0
    frame_period_ms_max: float = 0.0
    """Longest gap between two frames' stamps [ms]."""


@dataclass(frozen=True)
class SimStatsResponse(Message):
    """`sim/stats` (query) success reply: the physics loop's timing over the measurement window."""

    wall_time_s: float
    sim_time_s: float
    """Simulated time advanced in the window [s]."""
    real_time_factor: float
    """sim_time_s / wall_time_s; 1.0 keeps real time."""
    steps: int
    step_lateness_ms_p50: float
    """How late physics steps ran against their wall-clock schedule: median [ms]."""
    step_lateness_ms_p99: float
    step_lateness_ms_max: float
    dropped_time_s: float = 0.0
    """Simulated time skipped because the loop fell too far behind [s]."""
    joint_state_period_ms_max: float = 0.0
    """Longest gap between two published joint states [ms]."""
    cameras: tuple[CameraStats, ...] = ()
    ok: bool = True
    driver_state: str | None = None
    """How the arm takes setpoints now: following, braking (on its own) or holding."""
    setpoints_followed: int | None = None
    """Setpoints followed since the sim started (not reset with the window)."""
    setpoints_rejected: dict[str, int] | None = None
    """Setpoints not followed since the sim started, by reason: joint_limits, velocity,
    acceleration, jump, out_of_order, bad_message (`pipeline/sim/driver.py`)."""
    setpoint_timeouts: int | None = None
    """Times setpoints stopped arriving mid-motion and the arm braked on its own."""
    brakes: int | None = None
    """Times the arm braked on its own, for any reason."""
    last_rejection: str | None = None
    """The last setpoint rejection in words (reason: detail)."""


SERVICE_PROCESS_STATES: tuple[str, ...] = ("running", "restarting", "stopped")


@dataclass(frozen=True)
class StackStatusRequest(Message):
    """`stack/status` (query) request: the processes `robonav up` supervises."""


@dataclass(frozen=True)
class ServiceProcessStatus(Message):
    """One supervised process in a `stack/status` reply; travels nested, without `v`."""

    name: str
    """`router`, `sim`, `perception`, `planner`, `executor` or `view`."""
    state: str
    """'running'; 'restarting': exited, a restart is due in `restart_in_s`; 'stopped': exited, not restarted."""
    alive: bool
    """It holds its liveliness token `alive/<name>` (warm and serving); a process without a token
    (`view`): it runs."""
    restarts: int
    """Restarts since `robonav up` started."""
    pid: int | None = None
    """Of the running process."""
    uptime_s: float = 0.0
    """Since the running process started [s]; 0 when none runs."""
    alive_for_s: float = 0.0
    """Since its liveliness token appeared [s]; 0 when not alive."""
    last_exit_code: int | None = None
    """Of the last process that exited: its exit status, or minus the signal that killed it (-9: SIGKILL)."""
    last_exit_stamp: float | None = None
    """When that exit was seen [s]."""
    last_back_s: float | None = None
    """From that exit to the restarted process's liveliness token: how long it was away [s]."""
    restart_in_s: float | None = None
    """'restarting': the restart is due in this long [s]."""

    def __post_init__(self) -> None:
        if self.state not in SERVICE_PROCESS_STATES:
            raise ValueError(f"ServiceProcessStatus: state must be one of {SERVICE_PROCESS_STATES}, got {self.state!r}")


@dataclass(frozen=True)
class StackStatusResponse(Message):
    """`stack/status` (query) success reply."""

    stamp: float
    started_stamp: float
    """When `robonav up` started [s]."""
    supervisor_pid: int
    restart: bool
    """Whether exited processes are restarted (`stack.restart`)."""
    services: tuple[ServiceProcessStatus, ...] = ()
    ok: bool = True


@dataclass(frozen=True)
class RobotDescription(Message):
    """`robot/description` (latched pub, planner): the robot the planner plans for, so a client
    needs nothing but the router's address (MoveIt's `robot_description`)."""

    stamp: float
    """When the planner started [s]."""
    name: str
    urdf: str
    """The URDF text the planner loaded; mesh file names in it are as the URDF gives them."""
    base_frame: str
    """The robot's base link, which stands at `world_from_base` in the `world` frame of every message."""
    end_effector_link: str
    """The default link of Cartesian goals."""
    joint_names: tuple[str, ...]
    """The planning joints, in the order of every joint vector."""
    lower_limits: FloatArray = array_field("<f8", (None,))
    """(n,) position limits the planner enforces (the URDF's, or the config's) [rad, or m for prismatic]."""
    upper_limits: FloatArray = array_field("<f8", (None,))
    max_velocity: FloatArray = array_field("<f8", (None,))
    """(n,) [rad/s]"""
    max_acceleration: FloatArray = array_field("<f8", (None,))
    """(n,) [rad/s^2]"""
    max_jerk: FloatArray = array_field("<f8", (None,))
    """(n,) [rad/s^3]"""
    home_position: FloatArray | None = array_field("<f8", (None,), optional=True)
    """(n,) the configured home state [rad]."""
    fixed_joint_positions: dict[str, float] = field(default_factory=dict)
    """Non-planning joints held at these positions (e.g. the fingers) [rad or m]."""
    allowed_collision_pairs: tuple[str, ...] = ()
    """'link|link' pairs never checked against each other (the SRDF's disable_collisions)."""
    padding_m: float = 0.0
    """Padding the planner adds around every link [m]."""
    srdf: str | None = None
    """An SRDF, when the robot has one (none yet: `allowed_collision_pairs` carries its content)."""
    world_from_base: FloatArray | None = array_field("<f8", (4, 4), optional=True)
    """(4, 4) pose of `base_frame` in the world [m]; absent: the identity (the base frame is the world)."""

    def __post_init__(self) -> None:
        _check_same_length("RobotDescription", self.joint_names, lower_limits=self.lower_limits,
                           upper_limits=self.upper_limits, max_velocity=self.max_velocity,
                           max_acceleration=self.max_acceleration, max_jerk=self.max_jerk,
                           home_position=self.home_position)


CAMERA_OUTPUTS: tuple[str, ...] = ("cloud", "depth", "both")


@dataclass(frozen=True, eq=False)
class CameraDescription(Message):
    """One camera in a `cameras` publication; travels nested, without `v`."""

    camera_id: str
    intrinsics: CameraIntrinsics
    world_from_camera: FloatArray = array_field("<f8", (4, 4))
    """(4, 4) pose of the optical frame (z forward, x right, y down) in `world`: the calibrated
    one when the camera has an extrinsics file (what perception uses), else the configured one."""
    output: str = "cloud"
    """What it publishes: `cloud` (camera/<id>/cloud), `depth` (camera/<id>/depth) or `both`."""
    near_m: float = 0.0
    far_m: float = 0.0
    """Depth range [m]."""
    rate_hz: float = 0.0
    """Frames per second."""

    def __post_init__(self) -> None:
        if self.output not in CAMERA_OUTPUTS:
            raise ValueError(f"CameraDescription: output must be one of {list(CAMERA_OUTPUTS)}, got {self.output!r}")

    def _key(self) -> tuple[Any, ...]:
        return tuple((v.shape, v.tobytes()) if isinstance(v, np.ndarray) else v
                     for v in (getattr(self, f) for f in self.__dataclass_fields__))

    def __eq__(self, other: object) -> bool:  # the pose is an array: compared by value, as SceneObjectSpec
        return isinstance(other, CameraDescription) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())


@dataclass(frozen=True)
class Cameras(Message):
    """`cameras` (latched pub, sim or the camera drivers): every camera of the cell."""

    stamp: float
    cameras: tuple[CameraDescription, ...] = ()


ALL_MESSAGES: tuple[type[Message], ...] = (
    JointState, PointCloud, Occupancy, PlanRequest, PlanResponse, ExecuteRequest, ExecuteResponse,
    StopRequest, StopResponse, Setpoint, ExecutorStatus, ContactsRequest, ContactsResponse, ErrorReply,
    SceneRequest, SceneResponse, DepthImage, ContactEvent, SimObjectsRequest, SimObjectsResponse, SimStatsRequest,
    SimStatsResponse, PlanningSceneState, StackStatusRequest, StackStatusResponse, RobotDescription, Cameras,
)
