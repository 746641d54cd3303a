"""Hand-eye calibration with every OpenCV method, in one formulation for both setups.

Both setups share one chain, per view i:

    camera_from_board_i = inv(X) @ A_i @ Y

| setup | X (the answer) | A_i (known, from the robot) | Y (a by-product) |
| --- | --- | --- | --- |
| eye_to_hand | world_from_camera | base_from_ee_i | ee_from_board |
| eye_in_hand | ee_from_camera | ee_from_base_i = inv(base_from_ee_i) | world_from_board |

`cv2.calibrateHandEye` solves AX = XB from motions: it takes inv(A_i) as "gripper2base" and
camera_from_board_i as "target2cam" and returns X as "cam2gripper" (for eye_to_hand that is
OpenCV's documented trick of passing base2gripper). `cv2.calibrateRobotWorldHandEye` solves
AX = ZB for both unknowns at once: "world2cam" = camera_from_board_i, "base2gripper" = A_i,
and it returns inv(Y) ("base2world") and inv(X) ("gripper2cam").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from robonav.pipeline.types import FloatArray

HAND_EYE_METHODS: dict[str, int] = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}
ROBOT_WORLD_METHODS: dict[str, int] = {
    "shah": cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH,
    "li": cv2.CALIB_ROBOT_WORLD_HAND_EYE_LI,
}
MIN_VIEWS = 3
"""Hand-eye needs two motions with non-parallel rotation axes: three views at the very least."""
RECOMMENDED_VIEWS = 10
MIN_ROTATION_DEG = 5.0
"""Below this largest rotation between two views, the rotation (and so X) is not observable."""
MIN_AXIS_SPREAD = 0.02
"""Second over first eigenvalue of the angle-weighted rotation axes' scatter below this means
all motions turn about (nearly) one axis, which leaves X's translation along it unobservable."""


class CalibrationError(ValueError):
    """The data cannot give a calibration; the message says why and what to do."""


@dataclass(frozen=True)
class HandEyeEstimate:
    method: str
    x: FloatArray
    """(4, 4) X: world_from_camera (eye_to_hand) or ee_from_camera (eye_in_hand)."""
    y: FloatArray
    """(4, 4) Y: ee_from_board (eye_to_hand) or world_from_board (eye_in_hand)."""


@dataclass(frozen=True)
class MotionStats:
    max_rotation_deg: float
    """Largest rotation between any two views' A_i."""
    axis_spread: float
    """Second over first eigenvalue of the angle-weighted rotation axis scatter, 0..1."""


def invert(transform: FloatArray) -> FloatArray:
    out = np.eye(4)
    out[:3, :3] = transform[:3, :3].T
    out[:3, 3] = -transform[:3, :3].T @ transform[:3, 3]
    return out


def check_motion(a: Sequence[FloatArray]) -> MotionStats:
    """Refuse motions that cannot determine X.

    Raises:
        CalibrationError: fewer than MIN_VIEWS views, no rotation, or rotation about one axis only.
    """
    if len(a) < MIN_VIEWS:
        raise CalibrationError(f"too few usable views: {len(a)} (need at least {MIN_VIEWS}, and "
                               f"{RECOMMENDED_VIEWS} or more for a good result); collect more views "
                               "in which the whole board is visible")
    rotations = Rotation.from_matrix(np.array([t[:3, :3] for t in a]))
    scatter = np.zeros((3, 3))
    max_angle = 0.0
    for i in range(len(a)):
        relative = rotations[i].inv() * rotations[i + 1:]
        if len(relative) == 0:
            continue
        rotvecs = np.atleast_2d(relative.as_rotvec())
        angles = np.linalg.norm(rotvecs, axis=1)
        max_angle = max(max_angle, float(angles.max()))
        for rotvec, angle in zip(rotvecs, angles):
            if angle > 1e-9:
                axis = rotvec / angle
                scatter += angle * np.outer(axis, axis)
    eigenvalues = np.sort(np.linalg.eigvalsh(scatter))[::-1]
    spread = float(eigenvalues[1] / eigenvalues[0]) if eigenvalues[0] > 0 else 0.0
    stats = MotionStats(float(np.degrees(max_angle)), spread)
    if stats.max_rotation_deg < MIN_ROTATION_DEG:
        raise CalibrationError(f"degenerate motion: the end effector rotates at most {stats.max_rotation_deg:.2f} deg "
                               f"between views (need > {MIN_ROTATION_DEG:g}); hand-eye calibration cannot "
                               "work from translations alone: tilt the end effector by 20-40 deg about "
                               "different axes between views")
    if stats.axis_spread < MIN_AXIS_SPREAD:
        raise CalibrationError(f"degenerate motion: every rotation between views is about nearly the same axis "
                               f"(axis spread {stats.axis_spread:.4f} < {MIN_AXIS_SPREAD}); add views tilted "
                               "about other axes")
    return stats


def _rt(transforms: Sequence[FloatArray]) -> tuple[list[FloatArray], list[FloatArray]]:
    return [t[:3, :3] for t in transforms], [t[:3, 3].reshape(3, 1) for t in transforms]


def _transform(rotation: FloatArray, translation: FloatArray) -> FloatArray:
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = np.asarray(translation).reshape(3)
    return out


def mean_transform(transforms: Sequence[FloatArray]) -> FloatArray:
    """Chordal mean of the rotations, arithmetic mean of the translations."""
    rotation = Rotation.from_matrix(np.array([t[:3, :3] for t in transforms])).mean().as_matrix()
    return _transform(rotation, np.mean([t[:3, 3] for t in transforms], axis=0))


def y_from_x(x: FloatArray, a: Sequence[FloatArray], camera_from_board: Sequence[FloatArray]) -> FloatArray:
    """The Y that best fits a given X: the mean of inv(A_i) @ X @ camera_from_board_i."""
    return mean_transform([invert(ai) @ x @ ci for ai, ci in zip(a, camera_from_board)])


def solve_all(a: Sequence[FloatArray], camera_from_board: Sequence[FloatArray]) -> list[HandEyeEstimate]:
    """Every OpenCV hand-eye and robot-world method on the same views (skipping any that fail)."""
    estimates = []
    r_carrier, t_carrier = _rt([invert(ai) for ai in a])
    r_target, t_target = _rt(camera_from_board)
    for name, flag in HAND_EYE_METHODS.items():
        try:
            r_x, t_x = cv2.calibrateHandEye(r_carrier, t_carrier, r_target, t_target, method=flag)
        except cv2.error:
            continue
        x = _transform(r_x, t_x)
        if np.all(np.isfinite(x)):
            estimates.append(HandEyeEstimate(name, x, y_from_x(x, a, camera_from_board)))
    r_a, t_a = _rt(a)
    for name, flag in ROBOT_WORLD_METHODS.items():
        try:
            r_yinv, t_yinv, r_xinv, t_xinv = cv2.calibrateRobotWorldHandEye(r_target, t_target, r_a, t_a, method=flag)
        except cv2.error:
            continue
        x, y = invert(_transform(r_xinv, t_xinv)), invert(_transform(r_yinv, t_yinv))
        if np.all(np.isfinite(x)) and np.all(np.isfinite(y)):
            estimates.append(HandEyeEstimate(name, x, y))
    return estimates


def pose_residuals(x: FloatArray, y: FloatArray, a: Sequence[FloatArray],
                   camera_from_board: Sequence[FloatArray]) -> tuple[float, float]:
    """RMS rotation [deg] and translation [mm] between predicted and measured board poses."""
    angles, distances = [], []
    x_inv = invert(x)
    for ai, ci in zip(a, camera_from_board):
        predicted = x_inv @ ai @ y
        angles.append(rotation_angle_deg(predicted[:3, :3].T @ ci[:3, :3]))
        distances.append(np.linalg.norm(predicted[:3, 3] - ci[:3, 3]) * 1e3)
    return float(np.sqrt(np.mean(np.square(angles)))), float(np.sqrt(np.mean(np.square(distances))))


def rotation_angle_deg(rotation: FloatArray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))


def transform_error(estimate: FloatArray, truth: FloatArray) -> tuple[float, float]:
    """(translation error [mm], rotation error [deg]) of an estimated transform."""
    return (float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]) * 1e3),
            rotation_angle_deg(truth[:3, :3].T @ estimate[:3, :3]))
