"""The protocol's closed lists: error codes, and the executor's states and results.

Each is a `str` enum whose values are what travels on the wire (`docs/protocol.md`).
"""

from __future__ import annotations

import enum


class ErrorCode(str, enum.Enum):
    """The closed list of error codes a query can answer with."""

    MALFORMED_MESSAGE = "MALFORMED_MESSAGE"
    """Not msgpack, not a map, a missing/unknown key or a value of the wrong type."""
    UNSUPPORTED_VERSION = "UNSUPPORTED_VERSION"
    INVALID_REQUEST = "INVALID_REQUEST"
    """Well-formed but meaningless: NaN, wrong joint count or names, bad scaling factors."""
    OUT_OF_JOINT_LIMITS = "OUT_OF_JOINT_LIMITS"
    START_IN_COLLISION = "START_IN_COLLISION"
    GOAL_IN_COLLISION = "GOAL_IN_COLLISION"
    GOAL_UNREACHABLE = "GOAL_UNREACHABLE"
    """Inverse kinematics found no configuration within a Cartesian goal's tolerances."""
    NO_SOLUTION = "NO_SOLUTION"
    """The planner found no path within the allowed planning time."""
    UNKNOWN_PLANNER = "UNKNOWN_PLANNER"
    NO_JOINT_STATE = "NO_JOINT_STATE"
    """No start given and no joint state received yet."""
    OCCUPANCY_MISSING = "OCCUPANCY_MISSING"
    OCCUPANCY_STALE = "OCCUPANCY_STALE"
    OCCUPANCY_INCOMPLETE = "OCCUPANCY_INCOMPLETE"
    """The map is being rebuilt after a clear or a perception start: a camera has not yet
    contributed the configured number of frames."""
    EXECUTOR_BUSY = "EXECUTOR_BUSY"
    """An execute request arrived while a trajectory is streaming or stopping."""
    INTERNAL_ERROR = "INTERNAL_ERROR"
    PAYLOAD_TOO_LARGE = "PAYLOAD_TOO_LARGE"
    """The request payload is larger than the service's `limits.max_request_bytes`."""
    BUSY = "BUSY"
    """Every worker of the service is busy and its queue of waiting requests is full."""
    PATH_IN_COLLISION = "PATH_IN_COLLISION"
    """An execute's timed motion leaves the joint limits or collides with the map, the planner's
    scene objects or itself (MoveIt's plan-execution validity check)."""
    SCENE_MISSING = "SCENE_MISSING"
    """The executor holds no planning scene from a planner (`planner/scene_state`) to check an execute against."""
    # The executor reports these in `executor/status` (`error_code`) when it stopped a motion.
    JOINT_STATE_STALE = "JOINT_STATE_STALE"
    """No joint state for longer than the watchdog timeout while moving."""
    TRACKING_ERROR = "TRACKING_ERROR"
    """The measured position is too far from the commanded one while moving."""
    PATH_BLOCKED = "PATH_BLOCKED"
    """A new obstacle blocks the rest of the path (and no replan reached the goal)."""


class ExecutionState(str, enum.Enum):
    """The executor's state (`executor/status` `state`); transitions in `trajectory/execution.py`."""

    IDLE = "idle"
    EXECUTING = "executing"
    STOPPING = "stopping"
    """Braking to rest: a stop request, a fault, or a blocked path."""
    STOPPED = "stopped"
    REPLANNING = "replanning"
    """At rest after a blocked path, waiting for a new plan to the same goal."""
    ERROR = "error"
    """A fault stopped the arm; `error_code` says which, until the next execute."""

    @property
    def busy(self) -> bool:
        """A trajectory is streaming (moving or braking)."""
        return self in (ExecutionState.EXECUTING, ExecutionState.STOPPING)

    @property
    def finished(self) -> bool:
        """The last trajectory ended: done, stopped or failed."""
        return self in (ExecutionState.IDLE, ExecutionState.STOPPED, ExecutionState.ERROR)


class ExecutionResult(str, enum.Enum):
    """How the last trajectory ended (`executor/status` `last_result`)."""

    NONE = "none"
    SUCCEEDED = "succeeded"
    STOPPED = "stopped"
    ABORTED = "aborted"
