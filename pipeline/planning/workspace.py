"""A request's workspace box: the end-effector link must stay inside it along the whole path."""

from __future__ import annotations

import numpy as np

from robonav.pipeline.planning.metrics import interpolate_path
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.types import FloatArray, MotionValidFn, StateValidFn


def workspace_validity(robot: RobotModel, workspace_min_m: FloatArray | None, workspace_max_m: FloatArray | None,
                       is_valid: StateValidFn, motion_valid: MotionValidFn,
                       resolution_rad: float) -> tuple[StateValidFn, MotionValidFn]:
    """`is_valid` and `motion_valid` that also keep `robot`'s end-effector link inside the
    world-frame box [`workspace_min_m`, `workspace_max_m`]; unchanged without a box.

    Raises:
        ValueError: one bound without the other, bounds not finite (3,) vectors, or min not below max.
    """
    if workspace_min_m is None and workspace_max_m is None:
        return is_valid, motion_valid
    if workspace_min_m is None or workspace_max_m is None:
        raise ValueError("workspace bounds need both workspace_min_m and workspace_max_m")
    low = np.asarray(workspace_min_m, dtype=np.float64)
    high = np.asarray(workspace_max_m, dtype=np.float64)
    if low.shape != (3,) or high.shape != (3,) or not np.all(np.isfinite(low)) or not np.all(np.isfinite(high)):
        raise ValueError("workspace_min_m and workspace_max_m must be finite (3,) vectors")
    if not np.all(low < high):
        raise ValueError(f"workspace_min_m {low.tolist()} must be below workspace_max_m {high.tolist()} in x, y, z")
    link = robot.config.end_effector_link

    def inside(q: FloatArray) -> bool:
        p = robot.frame_pose(q, link)[:3, 3]
        return bool(np.all(p >= low) and np.all(p <= high))

    def bounded_is_valid(q: FloatArray) -> bool:
        return inside(q) and is_valid(q)

    def bounded_motion_valid(a: FloatArray, b: FloatArray) -> bool:
        return motion_valid(a, b) and all(inside(q) for q in interpolate_path(np.vstack([a, b]), resolution_rad))

    return bounded_is_valid, bounded_motion_valid
