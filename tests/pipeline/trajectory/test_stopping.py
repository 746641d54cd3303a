import numpy as np
import pytest

from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.trajectory.stopping import stop_trajectory
from robonav.pipeline.trajectory.trajectory import JointTrajectory

ROBOT = RobotConfig()
V_MAX = np.array(ROBOT.max_velocity_rad_s)
A_MAX = np.array(ROBOT.max_acceleration_rad_s2)
J_MAX = np.array(ROBOT.max_jerk_rad_s3)
LIMITS = {"max_velocity": V_MAX, "max_acceleration": A_MAX, "max_jerk": J_MAX}
DT_S = 1e-3


def _moving_state(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A state inside the limits with every joint moving and accelerating."""
    rng = np.random.default_rng(seed)
    q = np.array(ROBOT.home_position_rad) + rng.uniform(-0.5, 0.5, 7)
    qd = rng.uniform(-0.9, 0.9, 7) * V_MAX
    qdd = rng.uniform(-0.9, 0.9, 7) * A_MAX
    return q, qd, qdd


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stop_ends_at_rest_within_limits_and_continues_the_state(seed: int) -> None:
    q, qd, qdd = _moving_state(seed)
    assert np.abs(qd).max() > 0.1 and np.abs(qdd).max() > 1.0
    stop = stop_trajectory(q, qd, qdd, **LIMITS)
    assert isinstance(stop, JointTrajectory) and stop.dof == 7
    assert stop.duration_s > 0

    q0, qd0, qdd0 = stop.sample(0.0)
    np.testing.assert_allclose(q0, q, atol=1e-12)
    np.testing.assert_allclose(qd0, qd, atol=1e-12)
    np.testing.assert_allclose(qdd0, qdd, atol=1e-12)
    _, qd_end, qdd_end = stop.sample(stop.duration_s)
    np.testing.assert_allclose(qd_end, 0.0, atol=1e-9)
    np.testing.assert_allclose(qdd_end, 0.0, atol=1e-9)

    t, qs, qds, qdds = stop.sample_uniform(DT_S)
    assert np.all(np.abs(qds) <= V_MAX + 1e-6)
    assert np.all(np.abs(qdds) <= A_MAX + 1e-6)
    jerk = np.diff(qdds, axis=0) / np.diff(t)[:, None]
    assert np.all(np.abs(jerk) <= J_MAX * (1 + 1e-6) + 1e-6)
    # Continuous: no jumps between 1 ms samples beyond what the limits allow.
    assert np.all(np.abs(np.diff(qs, axis=0)) <= V_MAX * DT_S + 1e-9)
    # Each joint keeps moving the way it was going until it stops (no reversal).
    moving = np.abs(qd) > 1e-6
    assert np.all(np.sign(qs[-1] - q)[moving] * np.sign(qd)[moving] >= 0)


def test_stop_from_above_the_velocity_limit_brakes_back() -> None:
    q = np.zeros(2)
    qd = np.array([3.0, -0.5])
    stop = stop_trajectory(q, qd, np.zeros(2), max_velocity=[1.0, 1.0], max_acceleration=[5.0, 5.0], max_jerk=[100.0, 100.0])
    _, qd_end, _ = stop.sample(stop.duration_s)
    np.testing.assert_allclose(qd_end, 0.0, atol=1e-9)
    _, qds, qdds = stop.sample_uniform(DT_S)[1:]
    assert np.all(np.abs(qdds) <= 5.0 + 1e-6)
    assert np.all(np.diff(np.abs(qds[:, 0])) <= 1e-9)  # speed only decreases


def test_stop_at_rest_is_instant() -> None:
    q = np.array(ROBOT.home_position_rad)
    stop = stop_trajectory(q, np.zeros(7), np.zeros(7), **LIMITS)
    assert stop.duration_s == 0.0
    np.testing.assert_array_equal(stop.sample(0.0)[0], q)


@pytest.mark.parametrize(
    ("state", "limits", "match"),
    [
        ((np.full(7, np.nan), np.zeros(7), np.zeros(7)), {}, "q"),
        ((np.zeros(7), np.zeros(6), np.zeros(7)), {}, "qd"),
        ((np.zeros(7), np.zeros(7), np.full(7, np.inf)), {}, "qdd"),
        ((np.zeros((7, 1)), np.zeros(7), np.zeros(7)), {}, "q"),
        ((np.zeros(7), np.zeros(7), np.zeros(7)), {"max_jerk": np.zeros(7)}, "max_jerk"),
        ((np.zeros(7), np.zeros(7), np.zeros(7)), {"max_velocity": V_MAX[:3]}, "max_velocity"),
    ],
)
def test_bad_inputs_raise(state: tuple[np.ndarray, ...], limits: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        stop_trajectory(*state, **{**LIMITS, **limits})
