"""From a dataset to a calibration: detect, PnP, every OpenCV method, refine, compare.

The steps, each refusing what it cannot use with a `CalibrationError` that says what to do:

1. Detect the ChArUco board in every image; a view with fewer than `MIN_CORNERS` corners is
   left out (and listed). No view at all: the board parameters are probably wrong.
2. Board pose per view (`cv2.solvePnP` with IPPE, then Levenberg-Marquardt refinement).
3. Refuse degenerate motion (`hand_eye.check_motion`).
4. Every OpenCV method (`hand_eye.solve_all`); the one with the lowest reprojection error
   seeds the joint refinement (`refine.py`), which is the result.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from robonav.calibration.board import Detection, board_corners_m, detect_board
from robonav.calibration.dataset import Dataset, IntrinsicsSpec
from robonav.calibration.hand_eye import (
    CalibrationError,
    HandEyeEstimate,
    MotionStats,
    check_motion,
    invert,
    pose_residuals,
    solve_all,
    transform_error,
)
from robonav.calibration.refine import RefineResult, refine, reprojection_residuals
from robonav.pipeline.types import FloatArray

MIN_CORNERS = 6
"""Fewest corners for a view to count: PnP on a plane needs 4, and a few more make it stable."""


@dataclass(frozen=True)
class MethodResult:
    method: str
    x: FloatArray
    y: FloatArray
    reprojection_rms_px: float
    rotation_residual_deg: float
    """RMS angle between predicted and PnP board poses."""
    translation_residual_mm: float
    error_vs_truth: tuple[float, float] | None = None
    """(translation [mm], rotation [deg]) against the dataset's ground truth X."""


@dataclass(frozen=True)
class Solution:
    setup: str
    x: FloatArray
    """world_from_camera (eye_to_hand) or ee_from_camera (eye_in_hand)."""
    y: FloatArray
    refinement: RefineResult
    methods: tuple[MethodResult, ...]
    """Every OpenCV method, then `refined`."""
    seed_method: str
    used_views: tuple[int, ...]
    skipped_views: dict[int, str] = field(default_factory=dict)
    motion: MotionStats | None = None


def detect_all(dataset: Dataset, folder: Path, load_image: Callable[[Path], np.ndarray]) -> list[Detection]:
    detections = []
    for i, view in enumerate(dataset.views):
        image_path = folder / view.image
        image = load_image(image_path)
        if image is None:
            raise CalibrationError(f"views[{i}]: cannot read image {image_path}")
        if image.shape[:2] != (dataset.intrinsics.height, dataset.intrinsics.width):
            raise CalibrationError(f"views[{i}]: image {image_path} is {image.shape[1]}x{image.shape[0]}, the "
                                   f"intrinsics say {dataset.intrinsics.width}x{dataset.intrinsics.height}")
        detections.append(detect_board(dataset.board, image))
    return detections


def board_pose(detection: Detection, corners_board_m: FloatArray, intrinsics: IntrinsicsSpec) -> FloatArray | None:
    """camera_from_board (4, 4) from one view's corners, or None if PnP fails."""
    object_points = corners_board_m[detection.ids]
    k, dist = intrinsics.camera_matrix, intrinsics.dist_coeffs
    ok, rvec, tvec = cv2.solvePnP(object_points, detection.corners_px, k, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(object_points, detection.corners_px, k, dist, rvec, tvec)
    out = np.eye(4)
    out[:3, :3], _ = cv2.Rodrigues(rvec)
    out[:3, 3] = tvec.reshape(3)
    return out if np.all(np.isfinite(out)) and out[2, 3] > 0 else None


def solve(dataset: Dataset, detections: list[Detection], base_from_ee: list[FloatArray]) -> Solution:
    """Calibrate from detections and the end-effector pose of every view.

    Raises:
        CalibrationError: the board is never (or too rarely) seen, or the motion is degenerate.
    """
    corners = board_corners_m(dataset.board)
    skipped: dict[int, str] = {}
    used, a, poses, dets = [], [], [], []
    for i, (det, pose) in enumerate(zip(detections, base_from_ee)):
        if det.ids.size < MIN_CORNERS:
            skipped[i] = f"board not found ({det.ids.size} corners, need {MIN_CORNERS})"
            continue
        camera_from_board = board_pose(det, corners, dataset.intrinsics)
        if camera_from_board is None:
            skipped[i] = "PnP failed"
            continue
        used.append(i)
        a.append(pose if dataset.setup == "eye_to_hand" else invert(pose))
        poses.append(camera_from_board)
        dets.append(det)
    if not used:
        b = dataset.board
        raise CalibrationError(f"board not found in any of the {len(detections)} images: check the board parameters "
                               f"({b.squares_x}x{b.squares_y} squares, {b.dictionary}) against the printed board, and "
                               "that the images show it whole, in focus and well lit")
    motion = check_motion(a)
    estimates = solve_all(a, poses)
    if not estimates:
        raise CalibrationError("every OpenCV hand-eye method failed on these views; collect views with larger, "
                               "more varied rotations")
    truth = ground_truth_x(dataset)
    methods = [_method_result(e, a, poses, dets, corners, dataset.intrinsics, truth) for e in estimates]
    seed = min(methods, key=lambda m: m.reprojection_rms_px)
    refined = refine(seed.x, seed.y, a, dets, corners, dataset.intrinsics)
    methods.append(_method_result(HandEyeEstimate("refined", refined.x, refined.y), a, poses, dets, corners,
                                  dataset.intrinsics, truth))
    return Solution(dataset.setup, refined.x, refined.y, refined, tuple(methods), seed.method, tuple(used),
                    skipped, motion)


def ground_truth_x(dataset: Dataset) -> FloatArray | None:
    gt = dataset.ground_truth
    if gt is None:
        return None
    pose = gt.world_from_camera if dataset.setup == "eye_to_hand" else gt.ee_from_camera
    return None if pose is None else pose.matrix


def _method_result(estimate: HandEyeEstimate, a: list[FloatArray], poses: list[FloatArray], dets: list[Detection],
                   corners: FloatArray, intrinsics: IntrinsicsSpec, truth: FloatArray | None) -> MethodResult:
    residuals = reprojection_residuals(estimate.x, estimate.y, a, dets, corners, intrinsics)
    rotation_deg, translation_mm = pose_residuals(estimate.x, estimate.y, a, poses)
    return MethodResult(estimate.method, estimate.x, estimate.y, float(np.sqrt(np.mean(residuals**2))),
                        rotation_deg, translation_mm, None if truth is None else transform_error(estimate.x, truth))
