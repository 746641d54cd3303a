"""Rigid transforms as 4x4 homogeneous matrices named `<to>_from_<from>`, composed with `@`.

Quaternions are scalar-last (`quat_xyzw`), the order used by pybullet, ROS and the MBM files.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from robonav.pipeline.config import require
from robonav.pipeline.types import FloatArray


def rotation_from_quat_xyzw(quat_xyzw: Sequence[float] | FloatArray) -> FloatArray:
    """3x3 rotation matrix of a quaternion given as (x, y, z, w); normalises it first.

    Raises:
        ValueError: the quaternion has zero norm or is not finite.
    """
    q = np.asarray(quat_xyzw, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if q.shape != (4,) or not np.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"quat_xyzw must be 4 finite numbers with non-zero norm, got {q.tolist()}")
    x, y, z, w = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_xyzw_from_rotation(rotation: FloatArray) -> FloatArray:
    """Unit quaternion (x, y, z, w) with w >= 0 of a 3x3 rotation matrix."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s])
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = np.array([0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s])
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = np.array([(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = np.array([(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def make_transform(position: Sequence[float] | FloatArray, quat_xyzw: Sequence[float] | FloatArray) -> FloatArray:
    """4x4 transform from a translation (metres) and a scalar-last quaternion."""
    out = np.eye(4)
    out[:3, :3] = rotation_from_quat_xyzw(quat_xyzw)
    out[:3, 3] = np.asarray(position, dtype=np.float64)
    return out


def transform_points(to_from_from: FloatArray, points: FloatArray) -> FloatArray:
    """Apply a 4x4 transform to (N, 3) points; returns (N, 3) float64."""
    pts = np.asarray(points, dtype=np.float64)
    return pts @ to_from_from[:3, :3].T + to_from_from[:3, 3]


def look_at_quat_xyzw(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)) -> FloatArray:
    """Orientation of an optical camera frame (z forward, x right, y down) at `eye` looking at `target`."""
    z = np.asarray(target, dtype=np.float64) - np.asarray(eye, dtype=np.float64)
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: view direction is parallel to 'up'")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return quat_xyzw_from_rotation(np.column_stack([x, y, z]))


@dataclass(frozen=True)
class PoseSpec:
    """A rigid transform as written in files: translation [m] and scalar-last unit quaternion."""

    position_m: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]

    def __post_init__(self) -> None:
        require(all(math.isfinite(v) for v in (*self.position_m, *self.quat_xyzw)),
                f"position_m and quat_xyzw must be finite, got {list(self.position_m)}, {list(self.quat_xyzw)}")
        norm = math.sqrt(sum(v * v for v in self.quat_xyzw))
        require(abs(norm - 1.0) < 1e-3, f"quat_xyzw must be a unit quaternion, got {list(self.quat_xyzw)} (norm {norm})")

    @property
    def matrix(self) -> FloatArray:
        return make_transform(self.position_m, self.quat_xyzw)

    @classmethod
    def from_matrix(cls, transform: FloatArray) -> PoseSpec:
        t = np.asarray(transform, dtype=np.float64)
        q = quat_xyzw_from_rotation(t[:3, :3])
        return cls(tuple(float(v) for v in t[:3, 3]), tuple(float(v) for v in q))  # type: ignore[arg-type]
