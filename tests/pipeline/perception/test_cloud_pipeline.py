import numpy as np
import pytest

from robonav.pipeline.perception.cloud_pipeline import CloudStats, process_cloud, process_cloud_with_clearing
from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.perception.self_filter import SelfFilter
from robonav.pipeline.transforms import look_at_quat_xyzw, make_transform, transform_points

CONFIG = PerceptionConfig(
    resolution_m=0.02,
    workspace_min_m=(-1.0, -1.0, 0.005),
    workspace_max_m=(1.5, 1.0, 1.5),
    max_range_m=3.0,
)
WORLD_FROM_CAMERA = make_transform([1.6, 0.0, 1.0], look_at_quat_xyzw([1.6, 0.0, 1.0], [0.0, 0.0, 0.3]))
LINK_BOX = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.1, 0.1) for z in (0.0, 0.6)])
WORLD_FROM_LINK = {"link0": make_transform([0.3, 0.0, 0.0], [0, 0, 0, 1])}


def _scene_camera(seed: int) -> tuple[np.ndarray, dict[str, int]]:
    """A camera-frame cloud with known numbers of NaN, far, out-of-box and on-robot points."""
    rng = np.random.default_rng(seed)
    table = np.column_stack([rng.uniform(-0.5, 0.5, 30_000), rng.uniform(-0.5, 0.5, 30_000), np.full(30_000, 0.2)])
    robot = np.column_stack([rng.uniform(0.22, 0.38, 5_000), rng.uniform(-0.08, 0.08, 5_000), rng.uniform(0.25, 0.55, 5_000)])
    floor = np.column_stack([rng.uniform(-0.5, 0.5, 8_000), rng.uniform(-0.5, 0.5, 8_000), np.full(8_000, -0.3)])
    far = np.column_stack([rng.uniform(-3.0, -2.5, 2_000), rng.uniform(-0.5, 0.5, 2_000), rng.uniform(0.0, 1.0, 2_000)])
    points_camera = transform_points(np.linalg.inv(WORLD_FROM_CAMERA), np.vstack([table, robot, floor, far]))
    nan_rows = rng.choice(points_camera.shape[0], 1_000, replace=False)
    points_camera[nan_rows, rng.integers(0, 3, 1_000)] = np.nan
    return rng.permutation(points_camera), {"n": points_camera.shape[0]}


def _total(stats: CloudStats) -> int:
    return stats.non_finite + stats.out_of_range + stats.cropped + stats.voxel_merged + stats.self_filtered + stats.kept


def test_stats_add_up_and_every_stage_runs() -> None:
    points_camera, info = _scene_camera(0)
    self_filter = SelfFilter({"link0": LINK_BOX}, padding_m=0.04)
    points_world, stats = process_cloud(
        points_camera,
        world_from_camera=WORLD_FROM_CAMERA,
        config=CONFIG,
        self_filter=self_filter,
        world_from_link=WORLD_FROM_LINK,
    )
    assert stats.received == info["n"]
    assert _total(stats) == stats.received
    assert stats.kept == points_world.shape[0]
    assert stats.non_finite == 1_000
    assert stats.out_of_range > 0 and stats.cropped > 0 and stats.voxel_merged > 0 and stats.self_filtered > 0
    assert set(stats.stage_ms) == {"finite", "range", "transform", "crop", "voxel", "self_filter", "total"}
    assert all(ms >= 0 for ms in stats.stage_ms.values())

    # Output invariants: in the box, not on the robot, at most one point per half-voxel.
    lo, hi = np.array(CONFIG.workspace_min_m), np.array(CONFIG.workspace_max_m)
    assert ((points_world >= lo) & (points_world <= hi)).all()
    assert self_filter.outside_mask(points_world, WORLD_FROM_LINK).all()
    assert np.abs(points_world[:, 2] - 0.2).max() < 1e-6  # only the table survives


def test_without_self_filter() -> None:
    points_camera, _ = _scene_camera(1)
    points_world, stats = process_cloud(
        points_camera, world_from_camera=WORLD_FROM_CAMERA, config=CONFIG, self_filter=None, world_from_link=None
    )
    assert stats.self_filtered == 0
    assert _total(stats) == stats.received
    assert (points_world[:, 2] > 0.24).any()  # the robot's points are still there


def test_empty_and_all_nan_clouds() -> None:
    for cloud in (np.empty((0, 3)), np.full((10, 3), np.nan)):
        points_world, stats = process_cloud(
            cloud, world_from_camera=WORLD_FROM_CAMERA, config=CONFIG, self_filter=None, world_from_link=None
        )
        assert points_world.shape == (0, 3)
        assert stats.kept == 0 and _total(stats) == stats.received == cloud.shape[0]


def test_bad_inputs_raise() -> None:
    self_filter = SelfFilter({"link0": LINK_BOX}, padding_m=0.0)
    with pytest.raises(ValueError, match="world_from_link"):
        process_cloud(np.zeros((3, 3)), world_from_camera=np.eye(4), config=CONFIG, self_filter=self_filter, world_from_link=None)
    with pytest.raises(ValueError, match="world_from_camera"):
        process_cloud(np.zeros((3, 3)), world_from_camera=np.eye(3), config=CONFIG, self_filter=None, world_from_link=None)
    with pytest.raises(ValueError, match="points"):
        process_cloud(np.zeros((3, 2)), world_from_camera=np.eye(4), config=CONFIG, self_filter=None, world_from_link=None)


def test_with_clearing_returns_the_dropped_points_for_free_space_rays() -> None:
    points_camera, _ = _scene_camera(2)
    self_filter = SelfFilter({"link0": LINK_BOX}, padding_m=0.04)
    kwargs = dict(world_from_camera=WORLD_FROM_CAMERA, config=CONFIG, self_filter=self_filter, world_from_link=WORLD_FROM_LINK)
    points_world, stats = process_cloud(points_camera, **kwargs)
    points_world_2, clear_only_world, stats_2 = process_cloud_with_clearing(points_camera, **kwargs)
    np.testing.assert_array_equal(points_world, points_world_2)
    assert stats.clear_only == 0
    assert _total(stats_2) == stats_2.received
    assert stats_2.clear_only == clear_only_world.shape[0]
    assert "clearing" in stats_2.stage_ms

    # Every clearing point was dropped for a reason other than NaN: outside the box, beyond
    # range, or on the robot -- and each kind is there.
    lo, hi = np.array(CONFIG.workspace_min_m), np.array(CONFIG.workspace_max_m)
    outside_box = ~((clear_only_world >= lo) & (clear_only_world <= hi)).all(axis=1)
    # Out-of-range points come back pulled in to max range along their ray.
    beyond_range = np.linalg.norm(clear_only_world - WORLD_FROM_CAMERA[:3, 3], axis=1) > CONFIG.max_range_m - 0.02
    on_robot = ~self_filter.outside_mask(clear_only_world, WORLD_FROM_LINK)
    assert (outside_box | beyond_range | on_robot).all()
    assert np.isclose(clear_only_world[:, 2], -0.3).sum() > 0  # floor
    assert beyond_range.sum() > 0 and on_robot.sum() > 0
    # Cropped and far points are thinned, robot points are the self filter's.
    assert on_robot.sum() == stats_2.self_filtered
    assert (~on_robot).sum() < stats_2.cropped + stats_2.out_of_range
