"""Refine X and Y together on the reprojection error of every detected corner in every view.

Per-view board poses (PnP) weigh every view alike and throw away how well each corner was
seen; the hand-eye methods then fit poses, not pixels. Here the unknowns are X and Y of
`hand_eye.py` (6 + 6 parameters), the data are the detected corners, and the model is

    pixel = project(K, dist, inv(X) @ A_i @ Y @ corner_board)

solved with scipy's `least_squares` (trust region, Huber loss so a bad corner cannot pull
the answer). The 1-sigma uncertainty of X comes from the Jacobian at the solution.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from robonav.calibration.board import Detection
from robonav.calibration.dataset import IntrinsicsSpec
from robonav.calibration.hand_eye import invert
from robonav.pipeline.types import FloatArray

HUBER_SCALE_PX = 1.0
"""Residuals beyond this count linearly, not quadratically [px]."""


@dataclass(frozen=True)
class RefineResult:
    x: FloatArray
    y: FloatArray
    rms_px: float
    """RMS reprojection error over all corners [px]."""
    initial_rms_px: float
    x_translation_sigma_mm: float
    """1-sigma uncertainty of X's translation (norm of the per-axis sigmas) [mm]."""
    x_rotation_sigma_deg: float
    """1-sigma uncertainty of X's rotation (norm of the per-axis sigmas) [deg]."""
    corners: int
    evaluations: int


def _to_params(x: FloatArray, y: FloatArray) -> FloatArray:
    return np.concatenate([Rotation.from_matrix(x[:3, :3]).as_rotvec(), x[:3, 3],
                           Rotation.from_matrix(y[:3, :3]).as_rotvec(), y[:3, 3]])


def _from_params(params: FloatArray) -> tuple[FloatArray, FloatArray]:
    out = []
    for offset in (0, 6):
        t = np.eye(4)
        t[:3, :3] = Rotation.from_rotvec(params[offset:offset + 3]).as_matrix()
        t[:3, 3] = params[offset + 3:offset + 6]
        out.append(t)
    return out[0], out[1]


def reprojection_residuals(x: FloatArray, y: FloatArray, a: Sequence[FloatArray], detections: Sequence[Detection],
                           corners_board_m: FloatArray, intrinsics: IntrinsicsSpec) -> FloatArray:
    """(sum K_i * 2,) predicted minus detected corner positions [px], view after view."""
    x_inv = invert(x)
    k, dist = intrinsics.camera_matrix, intrinsics.dist_coeffs
    parts = []
    for ai, det in zip(a, detections):
        camera_from_board = x_inv @ ai @ y
        rvec = Rotation.from_matrix(camera_from_board[:3, :3]).as_rotvec()
        projected, _ = cv2.projectPoints(corners_board_m[det.ids], rvec, camera_from_board[:3, 3], k, dist)
        parts.append((projected.reshape(-1, 2) - det.corners_px).ravel())
    return np.concatenate(parts)


def refine(x0: FloatArray, y0: FloatArray, a: Sequence[FloatArray], detections: Sequence[Detection],
           corners_board_m: FloatArray, intrinsics: IntrinsicsSpec) -> RefineResult:
    """Least-squares X and Y from a starting estimate (the best OpenCV method's)."""

    def residuals(params: FloatArray) -> FloatArray:
        x, y = _from_params(params)
        return reprojection_residuals(x, y, a, detections, corners_board_m, intrinsics)

    p0 = _to_params(x0, y0)
    initial = residuals(p0)
    # x_scale: 1 mrad ~ 1 mm at the scale of a cell, so both kinds of parameter move alike.
    solution = least_squares(residuals, p0, method="trf", loss="huber", f_scale=HUBER_SCALE_PX,
                             x_scale=np.full(12, 1e-3), xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
    x, y = _from_params(solution.x)
    final = residuals(solution.x)
    sigma_t, sigma_r = _x_sigmas(solution.jac, final, solution.x.size)
    return RefineResult(x=x, y=y, rms_px=float(np.sqrt(np.mean(final**2))),
                        initial_rms_px=float(np.sqrt(np.mean(initial**2))),
                        x_translation_sigma_mm=sigma_t, x_rotation_sigma_deg=sigma_r,
                        corners=final.size // 2, evaluations=int(solution.nfev))


def _x_sigmas(jacobian: FloatArray, residuals: FloatArray, n_params: int) -> tuple[float, float]:
    dof = max(1, residuals.size - n_params)
    variance = float(residuals @ residuals) / dof
    try:
        covariance = np.linalg.inv(jacobian.T @ jacobian) * variance
    except np.linalg.LinAlgError:
        return float("inf"), float("inf")
    sigmas = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    return float(np.linalg.norm(sigmas[3:6]) * 1e3), float(np.degrees(np.linalg.norm(sigmas[0:3])))
