import numpy as np
import pytest

from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.perception.self_filter import SelfFilter, perception_filters
from robonav.pipeline.transforms import make_transform

UNIT_CUBE = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])


def _cube_with_interior(seed: int) -> np.ndarray:
    # Interior vertices must not change the hull.
    rng = np.random.default_rng(seed)
    return np.vstack([UNIT_CUBE, rng.uniform(0.1, 0.9, (50, 3))])


def test_points_inside_unit_cube_removed_outside_kept() -> None:
    sf = SelfFilter({"box": _cube_with_interior(0)}, padding_m=0.0)
    points = np.array(
        [
            [0.5, 0.5, 0.5],
            [0.01, 0.99, 0.5],
            [0.999, 0.001, 0.999],
            [1.5, 0.5, 0.5],
            [-0.1, 0.5, 0.5],
            [0.5, 0.5, 1.05],
            [3.0, 3.0, 3.0],
        ]
    )
    mask = sf.outside_mask(points, {"box": np.eye(4)})
    np.testing.assert_array_equal(mask, [False, False, False, True, True, True, True])


def test_random_points_match_the_analytic_cube() -> None:
    sf = SelfFilter({"box": _cube_with_interior(1)}, padding_m=0.0)
    rng = np.random.default_rng(2)
    points = rng.uniform(-1.0, 2.0, (20_000, 3))
    inside = ((points > 0.0) & (points < 1.0)).all(axis=1)
    np.testing.assert_array_equal(sf.outside_mask(points, {"box": np.eye(4)}), ~inside)


def test_padding_enlarges_the_hull() -> None:
    near = np.array([[1.05, 0.5, 0.5], [0.5, -0.08, 0.5], [1.05, 1.05, 0.5]])
    far = np.array([[1.15, 0.5, 0.5], [0.5, 0.5, -0.2]])
    points = np.vstack([near, far])
    unpadded = SelfFilter({"box": UNIT_CUBE}, padding_m=0.0).outside_mask(points, {"box": np.eye(4)})
    padded = SelfFilter({"box": UNIT_CUBE}, padding_m=0.1).outside_mask(points, {"box": np.eye(4)})
    np.testing.assert_array_equal(unpadded, [True] * 5)
    np.testing.assert_array_equal(padded, [False, False, False, True, True])


def test_padded_hull_contains_every_point_within_padding() -> None:
    padding_m = 0.05
    sf = SelfFilter({"box": UNIT_CUBE}, padding_m=padding_m)
    rng = np.random.default_rng(3)
    points = rng.uniform(-0.2, 1.2, (20_000, 3))
    distance_to_cube = np.linalg.norm(points - np.clip(points, 0.0, 1.0), axis=1)
    mask = sf.outside_mask(points, {"box": np.eye(4)})
    assert not mask[distance_to_cube < padding_m - 1e-9].any()
    # Overshoot is bounded: the padded polytope is at most padding * sqrt(3) out at corners.
    assert mask[distance_to_cube > padding_m * np.sqrt(3) + 1e-9].all()


def test_link_pose_is_respected() -> None:
    sf = SelfFilter({"box": UNIT_CUBE}, padding_m=0.0)
    # Rotate 90 deg about z and shift by +2 in x: the cube occupies x in [1, 2], y in [0, 1].
    world_from_box = make_transform([2.0, 0.0, 0.0], [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)])
    points = np.array([[1.5, 0.5, 0.5], [2.5, 0.5, 0.5], [0.5, 0.5, 0.5], [1.9, 0.9, 0.9]])
    np.testing.assert_array_equal(sf.outside_mask(points, {"box": world_from_box}), [False, True, True, False])


def test_multiple_links_and_missing_links_are_skipped() -> None:
    sf = SelfFilter({"a": UNIT_CUBE, "b": UNIT_CUBE * 0.5}, padding_m=0.0)
    assert sf.link_names == ("a", "b")
    points = np.array([[0.5, 0.5, 0.5], [5.25, 0.25, 0.25], [9.0, 9.0, 9.0]])
    poses = {"a": np.eye(4), "b": make_transform([5.0, 0.0, 0.0], [0, 0, 0, 1]), "unknown": np.eye(4)}
    np.testing.assert_array_equal(sf.outside_mask(points, poses), [False, False, True])
    np.testing.assert_array_equal(sf.outside_mask(points, {"b": poses["b"]}), [True, False, True])
    np.testing.assert_array_equal(sf.outside_mask(points, {}), [True, True, True])


def test_round_link_from_sphere_vertices() -> None:
    rng = np.random.default_rng(4)
    directions = rng.normal(size=(400, 3))
    sphere = 0.5 * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    sf = SelfFilter({"ball": sphere}, padding_m=0.02)
    points = rng.uniform(-1.0, 1.0, (20_000, 3))
    radius = np.linalg.norm(points, axis=1)
    mask = sf.outside_mask(points, {"ball": np.eye(4)})
    assert not mask[radius < 0.45].any()
    assert mask[radius > 0.53].all()


def test_flat_link_is_joggled_and_padded() -> None:
    plate = np.array([[x, y, 0.0] for x in (0.0, 1.0) for y in (0.0, 1.0)] + [[0.5, 0.5, 0.0]])
    sf = SelfFilter({"plate": plate}, padding_m=0.02)
    points = np.array([[0.5, 0.5, 0.01], [0.5, 0.5, -0.01], [0.5, 0.5, 0.1]])
    np.testing.assert_array_equal(sf.outside_mask(points, {"plate": np.eye(4)}), [False, False, True])


def test_a_link_can_have_its_own_padding() -> None:
    points = np.array([[1.05, 0.5, 0.5], [3.05, 0.5, 0.5]])
    poses = {"a": np.eye(4), "b": make_transform([2.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])}
    sf = SelfFilter({"a": UNIT_CUBE, "b": UNIT_CUBE}, padding_m=0.0, link_padding_m={"b": 0.1})
    np.testing.assert_array_equal(sf.outside_mask(points, poses), [True, False])
    with pytest.raises(ValueError, match="without a hull"):
        SelfFilter({"a": UNIT_CUBE}, padding_m=0.0, link_padding_m={"c": 0.1})
    with pytest.raises(ValueError, match="padding of a"):
        SelfFilter({"a": UNIT_CUBE}, padding_m=0.0, link_padding_m={"a": float("nan")})


def test_the_base_is_filtered_as_far_as_the_planner_checks(panda) -> None:  # noqa: ANN001 - session fixture
    config = PerceptionConfig(resolution_m=0.02, inflation_m=0.02, self_filter_padding_m=0.04,
                              self_clear_padding_m=0.02)
    self_filter, clear_filter = perception_filters(panda.link_hull_vertices, panda.static_link_names, config,
                                                   robot_padding_m=0.01)
    q = panda.home_position_rad
    poses = panda.link_poses(q)
    # Points straight out from the base's and the hand's hull, beyond the moving links' paddings
    # but within the planner's reach (padding + inflated voxel half diagonal = 0.062 m).
    base_hull = panda.link_hull_vertices["panda_link0"]
    base_side = np.array([base_hull[:, 0].max() + 0.05, 0.0, 0.05])
    hand_hull = panda.link_hull_vertices["panda_hand"]
    hand_side = poses["panda_hand"] @ np.array([0.0, hand_hull[:, 1].max() + 0.05, 0.0, 1.0])
    points = np.vstack([base_side, hand_side[:3]])
    for sf in (self_filter, clear_filter):
        outside = sf.outside_mask(points, poses)
        assert not outside[0] and outside[1]


def test_empty_cloud() -> None:
    sf = SelfFilter({"box": UNIT_CUBE}, padding_m=0.0)
    assert sf.outside_mask(np.empty((0, 3)), {"box": np.eye(4)}).shape == (0,)


def test_bad_inputs_raise() -> None:
    with pytest.raises(ValueError, match="padding_m"):
        SelfFilter({"box": UNIT_CUBE}, padding_m=-0.1)
    with pytest.raises(ValueError, match="'tiny'"):
        SelfFilter({"tiny": UNIT_CUBE[:3]}, padding_m=0.0)
    with pytest.raises(ValueError, match="'box'"):
        SelfFilter({"box": UNIT_CUBE[:, :2]}, padding_m=0.0)
    sf = SelfFilter({"box": UNIT_CUBE}, padding_m=0.0)
    with pytest.raises(ValueError, match="points_world"):
        sf.outside_mask(np.array([[np.nan, 0.0, 0.0]]), {"box": np.eye(4)})
    with pytest.raises(ValueError, match="world_from_link"):
        sf.outside_mask(np.zeros((1, 3)), {"box": np.eye(3)})


def test_accepts_the_robot_models_read_only_hulls(panda) -> None:  # noqa: ANN001 - session fixture
    hulls = panda.link_hull_vertices
    assert not next(iter(hulls.values())).flags.writeable
    self_filter = SelfFilter(hulls, 0.02)
    hand = panda.link_poses(panda.home_position_rad)["panda_hand"]
    inside = hand[:3, 3][None, :]
    assert not self_filter.outside_mask(inside, panda.link_poses(panda.home_position_rad))[0]
