"""What one request may ask for (config `limits`), checked right after decoding.

A well-formed request can still ask for an hour of planning, a million waypoints or a scene of a
million meshes; each costs the service time or memory that other clients wait for. Beyond a
limit the request is refused before any work with INVALID_REQUEST naming the key, the value and
the limit (`details`: key, value, limit).
"""

from __future__ import annotations

from collections.abc import Sequence

from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.messages import ExecuteRequest, PlanRequest, SceneObjectSpec
from robonav.services.config import LimitsConfig


def check_limit(key: str, value: float, limit: float, config_key: str) -> None:
    """Raises INVALID_REQUEST when `value` of request key `key` is above `limit` (config `limits.<config_key>`)."""
    if value > limit:
        raise ProtocolError(ErrorCode.INVALID_REQUEST,
                            f"{key} is {value:g}, above the limit of {limit:g} (config limits.{config_key})",
                            {"key": key, "value": value, "limit": limit})


def check_plan_request(request: PlanRequest, limits: LimitsConfig) -> None:
    """Planning time, attempts and the goal set against the limits."""
    if request.allowed_planning_time is not None:
        check_limit("allowed_planning_time", request.allowed_planning_time, limits.max_planning_time_s,
                    "max_planning_time_s")
    if request.num_planning_attempts is not None:
        check_limit("num_planning_attempts", request.num_planning_attempts, limits.max_planning_attempts,
                    "max_planning_attempts")
    if request.goal_set is not None:
        check_limit("goal_set", len(request.goal_set), limits.max_goals, "max_goals")


def check_execute_request(request: ExecuteRequest, limits: LimitsConfig) -> None:
    """Waypoints and replan attempts against the limits."""
    check_limit("path", len(request.path), limits.max_waypoints, "max_waypoints")
    if request.replan_attempts is not None:
        check_limit("replan_attempts", request.replan_attempts, limits.max_replan_attempts, "max_replan_attempts")


def check_scene_request(objects: Sequence[SceneObjectSpec], names: Sequence[str], limits: LimitsConfig,
                        *, motions: int = 0) -> None:
    """Objects, names (and scripted motions) of a `planner/scene` or `sim/objects` request, and
    the size of every mesh in it."""
    check_limit("objects", len(objects), limits.max_scene_objects, "max_scene_objects")
    check_limit("names", len(names), limits.max_scene_objects, "max_scene_objects")
    check_limit("motions", motions, limits.max_scene_objects, "max_scene_objects")
    for i, spec in enumerate(objects):
        if spec.vertices_m is not None:
            check_limit(f"objects[{i}].vertices_m", len(spec.vertices_m), limits.max_mesh_size, "max_mesh_size")
        if spec.triangles is not None:
            check_limit(f"objects[{i}].triangles", len(spec.triangles), limits.max_mesh_size, "max_mesh_size")
