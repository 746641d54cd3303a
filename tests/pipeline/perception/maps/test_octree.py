import fcl
import numpy as np
import octomap
import pytest

from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.perception.maps.octree import OccupancyMap

RES = 0.02
ORIGIN = np.array([0.0, 0.0, 0.5])


def _wall(x_m: float, half_width_m: float, n: int, seed: int) -> np.ndarray:
    """Points on the plane x = x_m, |y| and |z - 0.5| <= half_width_m."""
    rng = np.random.default_rng(seed)
    yz = rng.uniform(-half_width_m, half_width_m, (n, 2))
    return np.column_stack([np.full(n, x_m), yz[:, 0], yz[:, 1] + 0.5])


def _keys(centers: np.ndarray) -> set[tuple[int, int, int]]:
    return set(map(tuple, np.floor(centers / RES).astype(np.int64).tolist()))


def _leaf_keys_of_tree(tree: octomap.OcTree) -> set[tuple[int, int, int]]:
    """Occupied leaf-resolution keys of an octomap tree, expanding pruned nodes."""
    keys: set[tuple[int, int, int]] = set()
    for leaf in tree.begin_leafs():
        if not tree.isNodeOccupied(leaf):
            continue
        width = int(round(leaf.getSize() / RES))
        corner = np.round((leaf.getCoordinate() - 0.5 * leaf.getSize()) / RES).astype(np.int64)
        for i in range(width):
            for j in range(width):
                for k in range(width):
                    keys.add((int(corner[0] + i), int(corner[1] + j), int(corner[2] + k)))
    return keys


def test_wall_becomes_occupied_voxels_at_the_wall() -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES))
    assert occupancy.voxel_count == 0
    for frame in range(3):
        occupancy.insert(_wall(1.0, 0.2, 20_000, seed=frame), ORIGIN)
    centers = occupancy.occupied_centers_m()
    assert centers.shape[1] == 3 and centers.dtype == np.float64
    # The wall plane x = 1.0 is a voxel boundary; points sit in the voxel [1.00, 1.02).
    np.testing.assert_allclose(centers[:, 0], 1.0 + RES / 2, atol=1e-6)
    assert np.abs(centers[:, 1]).max() <= 0.2 + RES
    # 0.4 m x 0.4 m wall at 2 cm: 20 x 20 voxels (+ a boundary row if the edge straddles one).
    assert 400 <= occupancy.voxel_count <= 21 * 21
    assert occupancy.voxel_count == centers.shape[0]


def test_free_space_clearing_removes_a_vanished_wall() -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES, prob_hit=0.7, prob_miss=0.4))
    for frame in range(3):
        occupancy.insert(_wall(1.0, 0.2, 20_000, seed=frame), ORIGIN)
    near_before = (occupancy.occupied_centers_m()[:, 0] < 1.5).sum()
    assert near_before >= 400

    # The near wall is gone; the camera now sees a far wall through where it stood. The far
    # wall is wide enough that its rays cross every voxel of the old one.
    counts = []
    for frame in range(10):
        occupancy.insert(_wall(2.0, 0.6, 40_000, seed=100 + frame), ORIGIN)
        centers = occupancy.occupied_centers_m()
        counts.append(int((centers[:, 0] < 1.5).sum()))
    # Occupancy is evidence, not a single frame's view: the old wall survives one frame.
    assert counts[0] == near_before
    assert counts[-1] == 0
    assert (occupancy.occupied_centers_m()[:, 0] > 1.9).sum() >= 55 * 55


def test_pruned_blocks_are_expanded_to_leaf_voxels() -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES))
    steps = np.arange(8)
    grid = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)
    # An 8 x 8 x 8 block aligned to the octree, so octomap prunes it into one coarse node.
    block = (grid + 0.5) * RES + np.array([0.32, 0.0, 0.32])
    for _ in range(3):
        occupancy.insert(block, np.array([-1.0, 0.5, 0.5]))
    assert occupancy.voxel_count == 512
    assert _keys(occupancy.occupied_centers_m()) == _keys(block)


def test_inflation_is_a_superset_and_reaches_the_inflation_distance() -> None:
    inflation_m = 0.05  # 2.5 voxels -> 3
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES, inflation_m=inflation_m))
    for frame in range(2):
        occupancy.insert(_wall(1.0, 0.1, 5_000, seed=frame), ORIGIN)
    occupied = occupancy.occupied_centers_m()
    inflated = occupancy.inflated_centers_m()
    inflated_keys = _keys(inflated)
    assert _keys(occupied) <= inflated_keys
    assert len(inflated_keys) == inflated.shape[0]

    # Every point within inflation_m of an occupied voxel's cube lies in an inflated voxel.
    rng = np.random.default_rng(7)
    n = 50_000
    in_cube = occupied[rng.integers(occupied.shape[0], size=n)] + rng.uniform(-RES / 2, RES / 2, (n, 3))
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    probes = in_cube + direction * rng.uniform(0, inflation_m * 0.999, (n, 1))
    assert _keys(probes) <= inflated_keys

    # And it does not grow much further: within r = 3 voxels (Chebyshev) of an occupied one.
    occupied_keys = np.floor(occupied / RES).astype(np.int64)
    for key in np.floor(inflated / RES).astype(np.int64)[::25]:
        assert np.abs(occupied_keys - key).max(axis=1).min() <= 3


@pytest.mark.parametrize(("inflation_m", "expected"), [(0.0, 1), (0.02, 27), (0.03, 125), (0.04, 125)])
def test_inflation_of_a_single_voxel(inflation_m: float, expected: int) -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES, inflation_m=inflation_m))
    for _ in range(2):
        occupancy.insert(np.array([[1.005, 0.005, 0.505]]), ORIGIN)
    assert occupancy.voxel_count == 1
    assert occupancy.inflated_centers_m().shape == (expected, 3)


def test_planning_binary_round_trips_to_the_inflated_voxels() -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES, inflation_m=0.04))
    for frame in range(2):
        occupancy.insert(_wall(1.0, 0.15, 10_000, seed=frame), ORIGIN)
    data = occupancy.planning_binary()
    assert data.startswith(b"# Octomap OcTree binary file")

    tree = octomap.OcTree(RES)
    assert tree.readBinary(data)
    assert tree.getResolution() == pytest.approx(RES)
    assert _leaf_keys_of_tree(tree) == _keys(occupancy.inflated_centers_m())
    # Only occupied voxels are stored.
    assert all(tree.isNodeOccupied(leaf) for leaf in tree.begin_leafs())


def test_planning_binary_loads_into_fcl() -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES, inflation_m=0.02))
    for frame in range(2):
        occupancy.insert(_wall(1.0, 0.15, 10_000, seed=frame), ORIGIN)
    data = occupancy.planning_binary()
    # fcl.OcTree reads only the data after the header, as signed chars.
    section = data[data.index(b"\ndata\n") + len(b"\ndata\n"):]
    octree = fcl.CollisionObject(fcl.OcTree(RES, np.frombuffer(section, dtype=np.int8).tolist()), fcl.Transform())

    def hits(x_m: float) -> bool:
        box = fcl.CollisionObject(fcl.Box(0.01, 0.01, 0.01), fcl.Transform(np.array([x_m, 0.0, 0.5])))
        return fcl.collide(octree, box, fcl.CollisionRequest(), fcl.CollisionResult()) > 0

    assert hits(1.01)
    assert hits(0.985)  # inside the one-voxel inflation in front of the wall
    assert not hits(0.9)
    assert not hits(1.2)


def test_empty_map_and_clear() -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES))
    assert occupancy.occupied_centers_m().shape == (0, 3)
    assert occupancy.inflated_centers_m().shape == (0, 3)
    empty_tree = octomap.OcTree(RES)
    assert empty_tree.readBinary(occupancy.planning_binary())
    assert empty_tree.getNumLeafNodes() == 0

    occupancy.insert(np.empty((0, 3)), ORIGIN)
    occupancy.insert(_wall(1.0, 0.1, 1000, seed=0), ORIGIN)
    assert occupancy.voxel_count > 0
    occupancy.clear()
    assert occupancy.voxel_count == 0


def test_insert_rejects_bad_input() -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES))
    with pytest.raises(ValueError, match="points_world"):
        occupancy.insert(np.array([[1.0, np.nan, 0.0]]), ORIGIN)
    with pytest.raises(ValueError, match="points_world"):
        occupancy.insert(np.zeros((4, 2)), ORIGIN)
    with pytest.raises(ValueError, match="sensor_origin_world"):
        occupancy.insert(np.zeros((4, 3)), np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="sensor_origin_world"):
        occupancy.insert(np.zeros((4, 3)), np.zeros(2))


def test_rays_beyond_max_range_only_clear() -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES, max_range_m=1.0))
    occupancy.insert(_wall(2.0, 0.1, 2000, seed=0), ORIGIN)
    assert occupancy.voxel_count == 0


# --- free-space-only rays (points that must not be marked occupied) -------------------

CAMERA = np.array([2.2, 0.0, 1.2])  # outside the default box (x <= 1.5)


def _patch_x(x_m: float, y_half_m: float, z_range_m: tuple[float, float], step_m: float) -> np.ndarray:
    """Grid of points on the plane x = x_m, offset half a step so none lies on a voxel face."""
    ys = np.arange(-y_half_m, y_half_m, step_m) + step_m / 2
    zs = np.arange(z_range_m[0], z_range_m[1], step_m) + step_m / 2
    y, z = np.meshgrid(ys, zs)
    return np.column_stack([np.full(y.size, x_m), y.ravel(), z.ravel()])


def _floor(x_range_m: tuple[float, float], y_half_m: float, step_m: float) -> np.ndarray:
    xs = np.arange(x_range_m[0], x_range_m[1] + 1e-9, step_m)
    ys = np.arange(-y_half_m, y_half_m + 1e-9, step_m)
    x, y = np.meshgrid(xs, ys)
    return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])


def _count_near_x(occupancy: OccupancyMap, x_m: float) -> int:
    return int((np.abs(occupancy.occupied_centers_m()[:, 0] - x_m) < 0.03).sum())


# Points on the floor (cropped: the box starts at z = 0.005) seen past the obstacle's place.
OBSTACLE = _patch_x(0.605, 0.1, (0.05, 0.25), 0.005)
FLOOR_BEHIND = _floor((0.1, 0.6), 0.2, 0.005)


@pytest.mark.parametrize("use_clear_only", [False, True])
def test_floor_outside_the_box_clears_a_vanished_object_only_with_clear_only_rays(use_clear_only: bool) -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES))
    for _ in range(3):
        occupancy.insert(OBSTACLE, CAMERA)
    assert _count_near_x(occupancy, 0.61) >= 100

    # The obstacle is gone: the camera now sees the floor behind where it stood.
    counts = []
    for _ in range(10):
        occupancy.insert(np.empty((0, 3)), CAMERA, clear_only_world=FLOOR_BEHIND if use_clear_only else None)
        counts.append(_count_near_x(occupancy, 0.61))
    if use_clear_only:
        assert counts[0] > 0  # evidence accumulates: one frame is not enough
        assert counts[-1] == 0
    else:
        assert counts[-1] >= 100
    assert occupancy.voxel_count == counts[-1]  # the floor itself is never marked occupied


def test_clear_only_rays_do_not_erase_what_this_frame_sees() -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES))
    # The obstacle is still there and seen every frame; clear-only rays that graze or
    # (inconsistently) pass through it must not outvote this frame's hits.
    for _ in range(10):
        occupancy.insert(OBSTACLE, CAMERA, clear_only_world=FLOOR_BEHIND)
    assert _count_near_x(occupancy, 0.61) >= 100


def test_clear_only_segments_stop_at_their_point() -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES))
    wall = _patch_x(1.005, 0.1, (0.5, 0.7), 0.005)
    for _ in range(3):
        occupancy.insert(wall, CAMERA)
    before = occupancy.voxel_count
    # Something outside the box (x > 1.5) between the camera and the wall, and something
    # inside the box in front of it (say the robot): their segments end before the wall.
    occluder = CAMERA + (wall - CAMERA) * 0.4
    assert (occluder[:, 0] > 1.5).all()
    in_front = CAMERA + (wall - CAMERA) * 0.9
    # Points in the wall's voxels, reached straight on: a ray never clears its own voxel.
    head_on = np.array([[1.015, 0.0, 0.61]])
    for _ in range(10):
        occupancy.insert(np.empty((0, 3)), np.array([2.2, 0.0, 0.61]), clear_only_world=head_on)
        occupancy.insert(np.empty((0, 3)), CAMERA, clear_only_world=np.vstack([occluder, in_front]))
    assert occupancy.voxel_count == before


def test_clear_only_rays_stop_at_max_range() -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES, max_range_m=1.0))
    near = _patch_x(1.605, 0.1, (0.9, 1.1), 0.005)  # ~0.6 m from CAMERA
    far = _patch_x(0.805, 0.1, (0.5, 0.7), 0.005)  # ~1.5 m from CAMERA
    for _ in range(3):
        occupancy.insert(near, CAMERA)
        occupancy.insert(far, np.array([1.3, 0.0, 0.6]))  # seen from close by
    near_before, far_before = _count_near_x(occupancy, 1.61), _count_near_x(occupancy, 0.81)
    assert near_before > 0 and far_before > 0
    # Points 3 m out, on rays through both patches: the rays clear within max range only.
    through_both = CAMERA + (far - CAMERA) * 2.0
    through_near = CAMERA + (near - CAMERA) * 5.0
    for _ in range(10):
        occupancy.insert(np.empty((0, 3)), CAMERA, clear_only_world=np.vstack([through_both, through_near]))
    assert _count_near_x(occupancy, 1.61) == 0
    assert _count_near_x(occupancy, 0.81) == far_before


def test_clear_only_rejects_bad_input() -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=RES))
    with pytest.raises(ValueError, match="clear_only_world"):
        occupancy.insert(np.empty((0, 3)), CAMERA, clear_only_world=np.array([[np.nan, 0.0, 0.0]]))


def test_free_where_frees_only_flagged_voxels() -> None:
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=0.02))
    xs, ys = np.meshgrid(np.arange(-0.3, 0.3, 0.01), np.arange(-0.3, 0.3, 0.01))
    wall = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.5)])
    for _ in range(5):
        occupancy.insert(wall, np.array([0.0, 0.0, 1.5]))
    before = occupancy.occupied_centers_m().copy()
    freed = occupancy.free_where(lambda c: c[:, 0] > 0.0)
    after = occupancy.occupied_centers_m()
    assert freed == int(np.sum(before[:, 0] > 0.0)) > 0
    assert np.all(after[:, 0] <= 0.0)
    assert after.shape[0] == before.shape[0] - freed


def _box_surface_seen_from_front() -> np.ndarray:
    """Points on the +x face and the top of a 10 cm cube standing on z = 0 at x, y = 0.5, 0."""
    s = np.arange(-0.05, 0.05, 0.005)
    a, b = np.meshgrid(s, s)
    plus_x = np.column_stack([np.full(a.size, 0.55), a.ravel(), 0.05 + b.ravel()])
    top = np.column_stack([0.5 + a.ravel(), b.ravel(), np.full(a.size, 0.1)])
    return np.vstack([plus_x, top])


@pytest.mark.parametrize("fill", [False, True])
def test_fill_below_surfaces_covers_the_unseen_back_of_an_object(fill: bool) -> None:
    origin = np.array([1.5, 0.0, 0.8])
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=0.02, workspace_min_m=(-1.0, -1.0, 0.0),
                                              fill_below_surfaces=fill))
    for _ in range(3):
        occupancy.insert(_box_surface_seen_from_front(), origin)
    centers = occupancy.occupied_centers_m()
    # The voxel just inside the unseen -x face, mid-height.
    has_back = bool(np.any(np.all(np.abs(centers - np.array([0.45 + 0.01, 0.01, 0.05])) < 0.011, axis=1)))
    assert has_back is fill
    # Nothing is filled outside the cube's footprint (no sideways growth), nor below the floor.
    assert np.all(np.abs(centers[:, 0] - 0.5) <= 0.07) and np.all(np.abs(centers[:, 1]) <= 0.07)
    assert centers[:, 2].min() >= 0.0


def test_fill_below_a_board_leaves_the_space_the_scan_sees_through() -> None:
    """Rays under a shelf board to the wall behind it: the fill from the board stops at them."""
    res = 0.02
    grid = np.arange(0.0, 0.3, 0.005)
    x, y = np.meshgrid(0.45 + grid, -0.15 + grid, indexing="ij")
    board = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 0.451)])
    # Points on a wall beyond the board, hit by rays that pass under it at z = 0.31.
    xs = 0.45 + grid
    wall = np.column_stack([xs, np.full(xs.size, -0.6), np.full(xs.size, 0.31)])
    occupancy = OccupancyMap(PerceptionConfig(resolution_m=res, workspace_min_m=(-1.0, -1.0, 0.0),
                                              fill_below_surfaces=True))
    occupancy.insert(np.vstack([board, wall]), np.array([0.6, 0.8, 0.31]))
    centers = occupancy.occupied_centers_m()
    under = centers[(np.abs(centers[:, 0] - 0.6) < 0.05) & (np.abs(centers[:, 1]) < 0.1)]  # inside the rays' fan
    at_ray = np.abs(under[:, 2] - 0.31) < 0.011
    assert not np.any(at_ray)  # seen through
    assert np.sum(np.abs(under[:, 2] - 0.39) < 0.011) >= 40  # unseen: filled
