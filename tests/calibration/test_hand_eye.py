"""Hand-eye math on synthetic data: every OpenCV method, the motion checks, the refinement."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from robonav.calibration.board import BoardSpec, Detection, board_corners_m
from robonav.calibration.dataset import IntrinsicsSpec
from robonav.calibration.hand_eye import (
    HAND_EYE_METHODS,
    ROBOT_WORLD_METHODS,
    CalibrationError,
    check_motion,
    invert,
    solve_all,
    transform_error,
)
from robonav.calibration.refine import refine, reprojection_residuals

INTRINSICS = IntrinsicsSpec(640, 480, 500.0, 500.0, 319.5, 239.5)
BOARD = BoardSpec()


def _transform(rotvec: np.ndarray, translation: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    out[:3, 3] = translation
    return out


def _scene(seed: int, views: int = 12) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """X, Y, A_i and camera_from_board_i of an eye-to-hand-like rig, without noise."""
    rng = np.random.default_rng(seed)
    x = _transform(rng.normal(0, 1.0, 3), rng.normal(0, 0.5, 3))
    y = _transform(rng.normal(0, 1.0, 3), rng.normal(0, 0.1, 3))
    a, c = [], []
    for _ in range(views):
        # A board ~1 m in front of the camera, facing it, turned by up to ~35 deg.
        camera_from_board = _transform(np.array([np.pi, 0, 0]) + rng.normal(0, 0.35, 3),
                                       np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.1, 3))
        ai = x @ camera_from_board @ invert(y)
        a.append(ai)
        c.append(camera_from_board)
    return x, y, a, c


@pytest.mark.parametrize("seed", [0, 1])
def test_every_method_recovers_x_and_y_from_exact_data(seed: int) -> None:
    x, y, a, c = _scene(seed)
    estimates = solve_all(a, c)
    assert {e.method for e in estimates} == set(HAND_EYE_METHODS) | set(ROBOT_WORLD_METHODS)
    for estimate in estimates:
        t_mm, r_deg = transform_error(estimate.x, x)
        assert t_mm < 1e-3 and r_deg < 1e-4, estimate.method
        t_mm, r_deg = transform_error(estimate.y, y)
        assert t_mm < 1e-3 and r_deg < 1e-4, estimate.method


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=6, max_size=6))
def test_invert_is_the_inverse(values: list[float]) -> None:
    t = _transform(np.array(values[:3]), np.array(values[3:]))
    np.testing.assert_allclose(invert(t) @ t, np.eye(4), atol=1e-12)
    assert transform_error(t, t) == pytest.approx((0.0, 0.0), abs=1e-5)


def test_motion_checks_refuse_degenerate_views() -> None:
    _, _, a, _ = _scene(2)
    stats = check_motion(a)
    assert stats.max_rotation_deg > 20 and stats.axis_spread > 0.1
    with pytest.raises(CalibrationError, match="too few usable views: 2"):
        check_motion(a[:2])
    translated_only = [_transform(np.zeros(3), np.array([0.1 * i, 0.05 * i, 0.0])) for i in range(6)]
    with pytest.raises(CalibrationError, match="degenerate motion: the end effector rotates at most 0.00 deg"):
        check_motion(translated_only)
    one_axis = [_transform(np.array([0.0, 0.0, 0.3 * i]), np.array([0.1 * i, 0.0, 0.0])) for i in range(6)]
    with pytest.raises(CalibrationError, match="about nearly the same axis"):
        check_motion(one_axis)


def test_refinement_fits_pixels_better_than_any_method() -> None:
    """With corner noise, the joint refinement's reprojection error is the smallest, and close to truth."""
    rng = np.random.default_rng(3)
    x, y, a, c = _scene(3, views=15)
    corners = board_corners_m(BOARD)
    detections = []
    for ai in a:
        ids = np.arange(corners.shape[0])
        exact = reprojection_residuals(x, y, [ai], [Detection(ids, np.zeros((ids.size, 2)))], corners, INTRINSICS)
        detections.append(Detection(ids, exact.reshape(-1, 2) + rng.normal(0, 0.2, (ids.size, 2))))
    # Board poses from noisy pixels, as PnP would give them: here the exact poses, slightly disturbed.
    noisy_c = [ci @ _transform(rng.normal(0, 0.003, 3), rng.normal(0, 0.002, 3)) for ci in c]
    estimates = solve_all(a, noisy_c)
    rms = {e.method: float(np.sqrt(np.mean(reprojection_residuals(e.x, e.y, a, detections, corners, INTRINSICS) ** 2)))
           for e in estimates}
    best = min(estimates, key=lambda e: rms[e.method])
    result = refine(best.x, best.y, a, detections, corners, INTRINSICS)
    assert result.rms_px <= min(rms.values())
    assert result.rms_px == pytest.approx(0.2, rel=0.2)  # down to the pixel noise
    t_mm, r_deg = transform_error(result.x, x)
    assert t_mm < 3 * result.x_translation_sigma_mm + 0.1 and r_deg < 3 * result.x_rotation_sigma_deg + 0.01
    assert t_mm < transform_error(best.x, x)[0]
