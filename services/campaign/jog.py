"""The campaign's last-resort jog: the arm driven straight home in joint space, unplanned."""

from __future__ import annotations

import logging
from collections.abc import Callable, Collection

import numpy as np

from robonav.pipeline.robot.turns import joint_distance_rad
from robonav.pipeline.wire.messages import ErrorReply
from robonav.services.client import RobonavClient

log = logging.getLogger("robonav.campaign")


def jog(client: RobonavClient, goal_rad: np.ndarray, continuous_mask: np.ndarray, *, trajectory_id: str,
        timeout_s: float, settle: Callable[[], object], tolerance_rad: float, retryable: Collection[str],
        attempts: int) -> bool:
    """Drive the arm straight to `goal_rad` in joint space, unplanned; whether it got there.

    The executor still watches the motion, so a stop (a stale map, a voxel of noise) ends it short
    of the goal: the jog goes on from where the arm stopped, after `settle` (a fresh map), as
    does an execute refused for a reason a fresher map or state can clear (`retryable`)."""
    def error_rad() -> float:
        assert client.joint_state is not None
        return float(np.max(joint_distance_rad(client.joint_state.position, goal_rad, continuous_mask)))

    for attempt in range(attempts):
        if error_rad() <= tolerance_rad:
            return True
        if attempt > 0:
            settle()
        assert client.joint_state is not None
        execution = client.execute(np.vstack([client.joint_state.position, goal_rad]),
                                   trajectory_id=f"{trajectory_id}-{attempt}")
        if isinstance(execution, ErrorReply):
            log.warning("jog %s: execute refused: %s: %s", trajectory_id, execution.code, execution.message)
            if execution.code not in retryable:
                return False
            continue
        outcome = client.wait_for_trajectory(execution.trajectory_id, execution.duration_s + timeout_s)
        if outcome == "succeeded":
            client.wait_for(lambda: error_rad() <= tolerance_rad, 2.0)  # the joint state catches up
        else:
            log.warning("jog %s: attempt %d ended %s", trajectory_id, attempt, outcome)
    return error_rad() <= tolerance_rad
