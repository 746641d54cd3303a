import numpy as np
import pytest

from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.trajectory.blending import blend_from_state, polyline_deviation
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.pipeline.trajectory.trajectory import JointTrajectory

ROBOT = RobotConfig()
V_MAX = np.array(ROBOT.max_velocity_rad_s)
A_MAX = np.array(ROBOT.max_acceleration_rad_s2)
J_MAX = np.array(ROBOT.max_jerk_rad_s3)
LIMITS = {"max_velocity": V_MAX, "max_acceleration": A_MAX, "max_jerk": J_MAX}
DT_S = 1e-3


def _panda_path(seed: int, n_waypoints: int = 6) -> np.ndarray:
    rng = np.random.default_rng(seed)
    steps = rng.uniform(-0.6, 0.6, (n_waypoints - 1, 7))
    # Some segments move a single joint, some move all of them by very different amounts.
    steps[0, 1:] = 0.0
    steps[1] *= np.array([1.0, 0.01, 1.0, 0.05, 1.0, 0.001, 1.0])
    home = np.array(ROBOT.home_position_rad)
    return np.vstack([home, home + np.cumsum(steps, axis=0)])


@pytest.mark.parametrize(("seed", "v_scale", "a_scale"), [(0, 1.0, 1.0), (1, 0.5, 0.3), (2, 0.1, 1.0)])
def test_limits_hold_over_the_whole_run(seed: int, v_scale: float, a_scale: float) -> None:
    path = _panda_path(seed)
    trajectory = time_parameterize(path, **LIMITS, velocity_scaling=v_scale, acceleration_scaling=a_scale)
    t, q, qd, qdd = trajectory.sample_uniform(DT_S)
    assert t[0] == 0.0 and t[-1] == trajectory.duration_s
    assert np.all(np.diff(t) > 0) and np.all(np.diff(t) <= DT_S + 1e-12)
    assert np.all(np.abs(qd) <= V_MAX * v_scale + 1e-6)
    assert np.all(np.abs(qdd) <= A_MAX * a_scale + 1e-6)
    # Finite-difference jerk: exact inside constant-jerk phases; a sample interval that
    # straddles a phase switch averages two jerks, so it can only be smaller in magnitude.
    jerk = np.diff(qdd, axis=0) / np.diff(t)[:, None]
    assert np.all(np.abs(jerk) <= J_MAX * a_scale * (1 + 1e-6) + 1e-6)
    # Some joint actually reaches each limit (the profile is time-optimal, not timid).
    assert np.isclose(np.abs(qd).max(axis=0) / (V_MAX * v_scale), 1.0, atol=1e-6).any()
    assert np.isclose(np.abs(qdd).max(axis=0) / (A_MAX * a_scale), 1.0, atol=1e-6).any()


def _segment_times(trajectory: JointTrajectory, path: np.ndarray) -> np.ndarray:
    """Times at which a rest-to-rest trajectory is at each waypoint."""
    return np.append(trajectory.segment_start_times_s, trajectory.duration_s)[: path.shape[0]]


def test_rest_to_rest_passes_every_waypoint_at_rest_with_exact_endpoints() -> None:
    path = _panda_path(3)
    trajectory = time_parameterize(path, **LIMITS, max_path_deviation_rad=0.0)
    assert trajectory.dof == 7
    for t_s, waypoint in zip(_segment_times(trajectory, path), path):
        q, qd, qdd = trajectory.sample(t_s)
        np.testing.assert_allclose(q, waypoint, atol=1e-12)
        np.testing.assert_allclose(qd, 0.0, atol=1e-9)
        np.testing.assert_allclose(qdd, 0.0, atol=1e-9)
    q0, _, _ = trajectory.sample(0.0)
    q_end, qd_end, qdd_end = trajectory.sample(trajectory.duration_s)
    np.testing.assert_array_equal(q0, path[0])
    np.testing.assert_array_equal(q_end, path[-1])
    np.testing.assert_array_equal(qd_end, 0.0)
    np.testing.assert_array_equal(qdd_end, 0.0)
    # Sampling outside [0, duration] clamps.
    np.testing.assert_array_equal(trajectory.sample(-1.0)[0], path[0])
    np.testing.assert_array_equal(trajectory.sample(trajectory.duration_s + 5.0)[0], path[-1])


def test_rest_to_rest_stays_on_the_polyline() -> None:
    path = _panda_path(4)
    trajectory = time_parameterize(path, **LIMITS, max_path_deviation_rad=0.0)
    t, q, qd, _ = trajectory.sample_uniform(DT_S)
    boundaries = _segment_times(trajectory, path)
    segment = np.clip(np.searchsorted(boundaries, t, side="right") - 1, 0, path.shape[0] - 2)
    start, end = path[segment], path[segment + 1]
    delta = end - start
    s = np.einsum("ij,ij->i", q - start, delta) / np.einsum("ij,ij->i", delta, delta)
    deviation = np.linalg.norm(q - (start + s[:, None] * delta), axis=1)
    assert deviation.max() < 1e-9
    assert s.min() > -1e-9 and s.max() < 1 + 1e-9
    # Velocity always points along the segment, never backwards.
    assert (np.einsum("ij,ij->i", qd, delta) >= -1e-9).all()
    assert trajectory.max_path_deviation_rad == 0.0


@pytest.mark.parametrize(("seed", "bound_rad"), [(10, 0.02), (11, 0.005), (12, 0.05)])
def test_blending_stays_within_the_deviation_bound_and_is_faster(seed: int, bound_rad: float) -> None:
    path = _panda_path(seed, n_waypoints=7)
    blended = time_parameterize(path, **LIMITS, velocity_scaling=0.5, acceleration_scaling=0.5,
                                max_path_deviation_rad=bound_rad)
    rest = time_parameterize(path, **LIMITS, velocity_scaling=0.5, acceleration_scaling=0.5, max_path_deviation_rad=0.0)
    assert blended.duration_s < rest.duration_s
    t, q, qd, qdd = blended.sample_uniform(DT_S)
    # Measured independently of the parameteriser's own figure (which samples each blend at 2 ms).
    assert polyline_deviation(q, path).max() <= bound_rad + 1e-6
    assert 0.0 < blended.max_path_deviation_rad <= bound_rad
    for waypoint in path:  # every waypoint is passed within the bound
        assert np.linalg.norm(q - waypoint, axis=1).min() <= bound_rad + 1e-3
    times = blended.waypoint_times_s
    assert times is not None and times.shape == (path.shape[0],) and np.all(np.diff(times) > 0)
    # Exactly at the goal, at rest; limits hold throughout.
    q_end, qd_end, qdd_end = blended.sample(blended.duration_s)
    np.testing.assert_array_equal(q_end, path[-1])
    np.testing.assert_array_equal(qd_end, 0.0)
    np.testing.assert_array_equal(qdd_end, 0.0)
    np.testing.assert_array_equal(blended.sample(0.0)[0], path[0])
    assert np.all(np.abs(qd) <= V_MAX * 0.5 + 1e-6)
    assert np.all(np.abs(qdd) <= A_MAX * 0.5 + 1e-6)
    jerk = np.diff(qdd, axis=0) / np.diff(t)[:, None]
    assert np.all(np.abs(jerk) <= J_MAX * 0.5 * (1 + 1e-6) + 1e-6)
    # Continuous between 1 ms samples (no jumps at piece boundaries).
    assert np.all(np.abs(np.diff(q, axis=0)) <= V_MAX * 0.5 * DT_S + 1e-9)
    assert np.all(np.abs(np.diff(qd, axis=0)) <= A_MAX * 0.5 * DT_S + 1e-9)


def test_sharp_corners_and_reversals_stop_at_the_waypoint() -> None:
    q = np.array(ROBOT.home_position_rad)
    step = np.array([0.4, 0.2, 0.0, 0.1, 0.0, 0.0, 0.0])
    path = np.vstack([q, q + step, q])  # straight back: a 180 degree corner
    trajectory = time_parameterize(path, **LIMITS)
    assert trajectory.max_path_deviation_rad == 0.0
    times = trajectory.waypoint_times_s
    assert times is not None
    q_mid, qd_mid, _ = trajectory.sample(float(times[1]))
    np.testing.assert_allclose(q_mid, path[1], atol=1e-12)
    np.testing.assert_allclose(qd_mid, 0.0, atol=1e-9)


def test_state_valid_hook_falls_back_to_rest_to_rest_where_a_blend_is_invalid() -> None:
    path = _panda_path(13, n_waypoints=5)
    free = time_parameterize(path, **LIMITS)
    assert free.max_path_deviation_rad > 0
    calls: list[np.ndarray] = []

    def off_polyline_is_invalid(q: np.ndarray) -> bool:
        calls.append(q)
        return bool(polyline_deviation(q[None, :], path)[0] < 1e-6)

    checked = time_parameterize(path, **LIMITS, state_valid=off_polyline_is_invalid)
    assert calls, "the hook was never called"
    # Samples are at most check_step_rad apart in every joint.
    _, q, _, _ = checked.sample_uniform(DT_S)
    assert polyline_deviation(q, path).max() < 1e-9
    assert checked.max_path_deviation_rad == 0.0
    assert checked.duration_s > free.duration_s

    def always_valid(q: np.ndarray) -> bool:
        return True

    same = time_parameterize(path, **LIMITS, state_valid=always_valid)
    assert same.duration_s == pytest.approx(free.duration_s, rel=1e-12)


def test_check_hook_samples_are_dense_enough() -> None:
    path = _panda_path(14, n_waypoints=4)
    seen: list[np.ndarray] = []
    time_parameterize(path, **LIMITS, state_valid=lambda q: seen.append(q) or True, check_step_rad=0.01)
    samples = np.array(seen)
    # Consecutive samples of one blend differ by at most the step (boundaries between blends may jump).
    steps = np.abs(np.diff(samples, axis=0)).max(axis=1)
    assert np.median(steps) <= 0.01 + 1e-9


@pytest.mark.parametrize("seed", [20, 21, 22])
def test_blend_from_a_moving_state_is_continuous_and_within_limits(seed: int) -> None:
    rng = np.random.default_rng(seed)
    old = time_parameterize(_panda_path(seed), **LIMITS, velocity_scaling=0.5, acceleration_scaling=0.5)
    q, qd, qdd = old.sample(old.duration_s * rng.uniform(0.2, 0.8))
    assert np.abs(qd).max() > 0.05
    new_path = np.vstack([q, q + rng.uniform(-0.5, 0.5, 7), q + rng.uniform(-0.5, 0.5, 7)])
    new = time_parameterize(new_path, **LIMITS, velocity_scaling=0.5, acceleration_scaling=0.5)
    spliced = blend_from_state(new, q, qd, qdd)
    q0, qd0, qdd0 = spliced.sample(0.0)
    np.testing.assert_allclose(q0, q, atol=1e-12)
    np.testing.assert_allclose(qd0, qd, atol=1e-12)
    np.testing.assert_allclose(qdd0, qdd, atol=1e-12)
    t, qs, qds, qdds = spliced.sample_uniform(DT_S)
    assert np.all(np.abs(qds) <= V_MAX * 0.5 + 1e-6)
    assert np.all(np.abs(qdds) <= A_MAX * 0.5 + 1e-6)
    assert np.all(np.abs(np.diff(qdds, axis=0) / np.diff(t)[:, None]) <= J_MAX * 0.5 * (1 + 1e-6) + 1e-6)
    np.testing.assert_array_equal(qs[-1], new_path[-1])
    np.testing.assert_array_equal(qds[-1], 0.0)


def test_scaling_lengthens_the_trajectory() -> None:
    path = _panda_path(5)
    full = time_parameterize(path, **LIMITS)
    half = time_parameterize(path, **LIMITS, velocity_scaling=0.5, acceleration_scaling=0.5)
    slow = time_parameterize(path, **LIMITS, velocity_scaling=0.1)
    assert full.duration_s < half.duration_s < slow.duration_s


def test_duplicate_waypoints_are_skipped() -> None:
    path = _panda_path(6, n_waypoints=3)
    with_duplicates = np.vstack([path[0], path[0], path[1], path[1] + 1e-12, path[2], path[2]])
    plain = time_parameterize(path, **LIMITS)
    deduplicated = time_parameterize(with_duplicates, **LIMITS)
    assert deduplicated.duration_s == pytest.approx(plain.duration_s, rel=1e-9)
    np.testing.assert_array_equal(deduplicated.sample(deduplicated.duration_s)[0], path[2])


def test_single_waypoint_and_all_equal_waypoints_hold_still() -> None:
    q = np.array(ROBOT.home_position_rad)
    for path in (q[None, :], np.vstack([q, q, q])):
        trajectory = time_parameterize(path, **LIMITS)
        assert trajectory.duration_s == 0.0
        t, qs, qd, qdd = trajectory.sample_uniform(DT_S)
        assert t.tolist() == [0.0]
        np.testing.assert_array_equal(qs[0], q)
        np.testing.assert_array_equal(qd, 0.0)


@pytest.mark.parametrize("travel", [1e-8, 1e-12, 1e-300])
def test_tiny_moves_are_timed_without_overflow(travel: float) -> None:
    q = np.array(ROBOT.home_position_rad)
    path = np.vstack([q, q + travel * np.linspace(0.0, 1.0, 7), q + 0.3])
    trajectory = time_parameterize(path, **LIMITS)
    t, qs, qd, qdd = trajectory.sample_uniform(DT_S)
    assert np.isfinite(qs).all() and np.isfinite(qd).all() and np.isfinite(qdd).all()
    assert np.all(np.abs(qd) <= V_MAX + 1e-6)
    np.testing.assert_array_equal(qs[-1], path[-1])


def test_single_joint_path() -> None:
    trajectory = time_parameterize([[0.0], [1.0], [0.5]], max_velocity=[1.0], max_acceleration=[2.0], max_jerk=[10.0])
    assert trajectory.dof == 1
    np.testing.assert_allclose(trajectory.sample(trajectory.duration_s)[0], [0.5])


def test_trajectory_is_read_only() -> None:
    trajectory = time_parameterize(_panda_path(7), **LIMITS)
    with pytest.raises(AttributeError):
        trajectory.duration_s = 1.0  # type: ignore[misc]
    with pytest.raises(AttributeError):
        trajectory.extra = 1  # type: ignore[attr-defined]
    q, _, _ = trajectory.sample(0.3)
    q[:] = 100.0  # samples are fresh arrays: mutating one does not leak into the trajectory
    assert np.all(trajectory.sample(0.3)[0] < 100.0)


@pytest.mark.parametrize(
    ("path", "kwargs", "match"),
    [
        (np.full((3, 7), np.nan), {}, "path"),
        (np.zeros(7), {}, "path"),
        (np.zeros((0, 7)), {}, "path"),
        (np.zeros((3, 6)), {}, "max_velocity"),
        (np.zeros((3, 7)), {"velocity_scaling": 0.0}, "velocity_scaling"),
        (np.zeros((3, 7)), {"velocity_scaling": 1.5}, "velocity_scaling"),
        (np.zeros((3, 7)), {"acceleration_scaling": 0.0}, "acceleration_scaling"),
        (np.zeros((3, 7)), {"acceleration_scaling": 1.5}, "acceleration_scaling"),
        (np.zeros((3, 7)), {"acceleration_scaling": float("nan")}, "acceleration_scaling"),
        (np.zeros((3, 7)), {"max_jerk": -J_MAX}, "max_jerk"),
        (np.zeros((3, 7)), {"max_acceleration": np.full(7, np.inf)}, "max_acceleration"),
        (np.zeros((3, 7)), {"max_path_deviation_rad": -0.1}, "max_path_deviation_rad"),
        (np.zeros((3, 7)), {"max_path_deviation_rad": float("nan")}, "max_path_deviation_rad"),
        (np.zeros((3, 7)), {"check_step_rad": 0.0}, "check_step_rad"),
    ],
)
def test_bad_inputs_raise(path: np.ndarray, kwargs: dict, match: str) -> None:
    arguments = {**LIMITS, **kwargs}
    with pytest.raises(ValueError, match=match):
        time_parameterize(path, **arguments)


def test_bad_sample_arguments_raise() -> None:
    trajectory = time_parameterize(_panda_path(8), **LIMITS)
    with pytest.raises(ValueError, match="dt_s"):
        trajectory.sample_uniform(0.0)
    with pytest.raises(ValueError, match="t_s"):
        trajectory.sample(float("nan"))
    with pytest.raises(ValueError, match="finite"):
        trajectory.sample_many([0.0, float("inf")])


def test_sample_many_is_sample_at_every_time() -> None:
    """Every kind of piece: straight lines, corner blends, a preemption blend, a stop, a hold."""
    from robonav.pipeline.trajectory.stopping import stop_trajectory

    blended = time_parameterize(_panda_path(30), **LIMITS, velocity_scaling=0.5, acceleration_scaling=0.5)
    q, qd, qdd = blended.sample(0.4 * blended.duration_s)
    trajectories = [
        time_parameterize(_panda_path(31), **LIMITS, max_path_deviation_rad=0.0),
        blended,
        blend_from_state(time_parameterize(_panda_path(32), **LIMITS), q, qd, qdd),
        stop_trajectory(q, qd, qdd, **LIMITS, synchronize=True),
        time_parameterize(np.zeros((2, 7)), **LIMITS),
    ]
    for trajectory in trajectories:
        times = np.concatenate([np.linspace(-0.5, trajectory.duration_s + 0.5, 997),
                                trajectory.segment_start_times_s, [trajectory.duration_s]])
        many = trajectory.sample_many(times)
        one = [trajectory.sample(float(t)) for t in times]
        for k in range(3):
            np.testing.assert_array_equal(many[k], np.array([s[k] for s in one]))
