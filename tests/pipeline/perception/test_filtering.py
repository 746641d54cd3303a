import numpy as np
import pytest

from robonav.pipeline.perception.filtering import (
    crop_box_mask,
    finite_points,
    range_mask,
    validate_transform,
    voxel_downsample,
)


def test_finite_points_drops_and_counts_nan_and_inf_rows() -> None:
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (100, 3))
    points[[3, 17, 50], 1] = np.nan
    points[60, 2] = np.inf
    points[61, 0] = -np.inf
    kept, n_dropped = finite_points(points)
    assert n_dropped == 5
    assert kept.shape == (95, 3)
    assert np.isfinite(kept).all()
    # Order is preserved.
    expected = np.delete(points, [3, 17, 50, 60, 61], axis=0)
    np.testing.assert_array_equal(kept, expected)


def test_finite_points_empty_and_all_finite() -> None:
    kept, n_dropped = finite_points(np.empty((0, 3)))
    assert kept.shape == (0, 3) and n_dropped == 0
    points = np.arange(12, dtype=float).reshape(4, 3)
    kept, n_dropped = finite_points(points)
    assert n_dropped == 0
    np.testing.assert_array_equal(kept, points)


@pytest.mark.parametrize("shape", [(5,), (5, 2), (5, 4), (2, 3, 3)])
def test_wrong_shape_raises_naming_the_quantity(shape: tuple[int, ...]) -> None:
    with pytest.raises(ValueError, match="points"):
        finite_points(np.zeros(shape))
    with pytest.raises(ValueError, match="points_camera"):
        range_mask(np.zeros(shape), 1.0)
    with pytest.raises(ValueError, match="points_world"):
        crop_box_mask(np.zeros(shape), (0, 0, 0), (1, 1, 1))
    with pytest.raises(ValueError, match="points"):
        voxel_downsample(np.zeros(shape), 0.1)


def test_masks_reject_nan_points() -> None:
    points = np.array([[0.0, 0.0, 1.0], [np.nan, 0.0, 1.0]])
    with pytest.raises(ValueError, match="NaN"):
        range_mask(points, 2.0)
    with pytest.raises(ValueError, match="NaN"):
        crop_box_mask(points, (0, 0, 0), (1, 1, 1))
    with pytest.raises(ValueError, match="NaN"):
        voxel_downsample(points, 0.1)


def test_range_mask_keeps_points_within_range() -> None:
    points = np.array([[0.0, 0.0, 1.0], [0.0, 3.0, 0.0], [2.0, 2.0, 2.0], [0.0, 0.0, 3.0001]])
    np.testing.assert_array_equal(range_mask(points, 3.0), [True, True, False, False])
    assert range_mask(np.empty((0, 3)), 1.0).shape == (0,)
    for bad in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="max_range_m"):
            range_mask(points, bad)


def test_crop_box_mask_is_closed_box() -> None:
    points = np.array(
        [
            [0.5, 0.5, 0.5],  # inside
            [0.0, 1.0, 0.5],  # on faces
            [1.01, 0.5, 0.5],  # outside x
            [0.5, -0.01, 0.5],  # outside y
            [0.5, 0.5, 2.0],  # outside z
        ]
    )
    np.testing.assert_array_equal(crop_box_mask(points, (0, 0, 0), (1, 1, 1)), [True, True, False, False, False])
    with pytest.raises(ValueError, match="min_m"):
        crop_box_mask(points, (0, 0, 2), (1, 1, 1))
    with pytest.raises(ValueError, match="corners"):
        crop_box_mask(points, (0, 0), (1, 1, 1))


def test_voxel_downsample_thins_a_dense_plane_and_keeps_its_extent() -> None:
    rng = np.random.default_rng(1)
    plane = np.column_stack([rng.uniform(0, 1, 200_000), rng.uniform(0, 1, 200_000), np.zeros(200_000)])
    voxel_m = 0.02
    out = voxel_downsample(plane, voxel_m)
    # One centroid per occupied voxel of a 1 m x 1 m plane (grid may straddle a boundary).
    assert 50 * 50 <= out.shape[0] <= 51 * 51
    assert out.dtype == np.float64
    np.testing.assert_allclose(out[:, 2], 0.0)
    assert out[:, :2].min() < voxel_m and out[:, :2].max() > 1.0 - voxel_m
    assert out[:, :2].min() >= 0.0 and out[:, :2].max() <= 1.0
    # No two centroids share a voxel; open3d anchors its grid half a voxel below the
    # cloud's minimum corner, not at the frame origin.
    anchor = plane.min(axis=0) - voxel_m / 2
    keys = np.floor((out - anchor) / voxel_m).astype(np.int64)
    assert np.unique(keys, axis=0).shape[0] == out.shape[0]


def test_voxel_downsample_empty_and_bad_voxel() -> None:
    assert voxel_downsample(np.empty((0, 3)), 0.05).shape == (0, 3)
    with pytest.raises(ValueError, match="voxel_m"):
        voxel_downsample(np.zeros((3, 3)), 0.0)


def test_validate_transform() -> None:
    np.testing.assert_array_equal(validate_transform(np.eye(4), "world_from_camera"), np.eye(4))
    with pytest.raises(ValueError, match="world_from_camera"):
        validate_transform(np.eye(3), "world_from_camera")
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="world_from_camera"):
        validate_transform(bad, "world_from_camera")
