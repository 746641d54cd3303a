"""Joint vectors named by a client or a joint state, mapped onto the robot's joint order."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.codes import ErrorCode


def reorder_to_robot(values: np.ndarray, names: tuple[str, ...] | None, robot_names: tuple[str, ...], key: str) -> np.ndarray:
    """Return `values` (..., n) with its last axis in `robot_names` order.

    Args:
        values: joint values, last axis in `names` order (or robot order when `names` is None).
        names: the client's joint names, a permutation of `robot_names`, or None.
        robot_names: the robot's planning joints.
        key: the message key of `values`, for the error.

    Raises:
        ProtocolError(INVALID_REQUEST): wrong joint count or names.
    """
    n = len(robot_names)
    if names is None:
        if values.shape[-1] != n:
            raise ProtocolError(ErrorCode.INVALID_REQUEST,
                                f"'{key}' has {values.shape[-1]} joint values, the robot has {n} joints {list(robot_names)}",
                                {"key": key, "expected": n, "got": int(values.shape[-1])})
        return values
    if sorted(names) != sorted(robot_names):
        raise ProtocolError(ErrorCode.INVALID_REQUEST,
                            f"joint_names {list(names)} must name exactly the planning joints {list(robot_names)}",
                            {"key": "joint_names", "expected": list(robot_names), "got": list(names)})
    return values[..., [names.index(name) for name in robot_names]]


def positions_by_name(names: Sequence[str], positions: Sequence[float] | np.ndarray,
                      wanted: Sequence[str]) -> FloatArray | None:
    """The values of the `wanted` joints, in that order, from a vector named by `names`.

    A joint state may name more joints than the robot plans with (fingers) and in any order.

    Returns:
        (len(wanted),) float64, or None when `names` lacks any wanted joint.
    """
    index = {name: i for i, name in enumerate(names)}
    try:
        rows = [index[name] for name in wanted]
    except KeyError:
        return None
    return np.asarray(positions, dtype=np.float64)[rows]


def missing_joints(names: Sequence[str], wanted: Sequence[str]) -> list[str]:
    """The `wanted` joints `names` lacks, in `wanted` order."""
    have = set(names)
    return [name for name in wanted if name not in have]
