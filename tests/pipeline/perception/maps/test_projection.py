"""Projection-cleared occupancy map on real pybullet renders: mapping, clearing, self filter, fusion, clusters."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.perception.clusters import cluster_voxels
from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.perception.depth import depth_from_points, points_from_depth
from robonav.pipeline.perception.maps.projection import ProjectionOccupancyMap
from robonav.pipeline.perception.self_filter import SelfFilter
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.config import SimConfig
from robonav.pipeline.sim.world import SimWorld
from robonav.pipeline.transforms import look_at_quat_xyzw

ROBOT = RobotConfig()
HOME = np.array(ROBOT.home_position_rad)
RES = 0.02
CONFIG = PerceptionConfig(resolution_m=RES, fill_below_surfaces=False)
TABLE = SceneObject("table", "box", (0.55, 0.0, 0.1), size_m=(0.5, 1.2, 0.2))
BOX = SceneObject("box", "box", (0.55, 0.25, 0.3), size_m=(0.16, 0.16, 0.2))
MOVED = dataclasses.replace(BOX, position_m=(0.55, 0.35, 0.3))
CAN = SceneObject("can", "cylinder", (0.55, -0.3, 0.32), radius_m=0.05, length_m=0.24)


def camera(eye: tuple[float, float, float], camera_id: str = "cam0") -> CameraConfig:
    return CameraConfig(camera_id=camera_id, width=320, height=240, position_m=eye,
                        quat_xyzw=tuple(look_at_quat_xyzw(eye, (0.55, 0.0, 0.25))))


FRONT = camera((1.45, 0.55, 1.05))
BACK = camera((-0.2, -0.9, 1.0), "cam1")


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.from_config(ROBOT)


@pytest.fixture(scope="module")
def self_filter(robot: RobotModel) -> SelfFilter:
    return SelfFilter(robot.link_hull_vertices, 0.04)


def render(*objects: SceneObject, cam: CameraConfig = FRONT, q: np.ndarray = HOME):
    with SimWorld(ROBOT, cam, SimConfig(objects=objects, follow="kinematic", gravity=False)) as world:
        world.set_joint_target(q)
        world.step()
        return world.render_depth()


def integrate(m: ProjectionOccupancyMap, frame, robot: RobotModel, self_filter: SelfFilter, q: np.ndarray = HOME):
    return m.integrate_depth(frame.depth_m, frame.intrinsics, frame.world_from_camera, self_filter=self_filter,
                             world_from_link=robot.link_poses(q), labels=frame.segmentation)


def voxels_inside(m: ProjectionOccupancyMap, obj: SceneObject, shrink_m: float = 0.0) -> int:
    centers = m.occupied_centers_m()
    lo = np.asarray(obj.position_m) - np.asarray(obj.size_m) / 2 + shrink_m
    hi = np.asarray(obj.position_m) + np.asarray(obj.size_m) / 2 - shrink_m
    return int(np.all((centers >= lo) & (centers <= hi), axis=1).sum())


def near_box(m: ProjectionOccupancyMap, obj: SceneObject, margin_m: float) -> int:
    """Occupied voxels in the box grown by `margin_m`, above the table top's own voxel layer."""
    centers = m.occupied_centers_m()
    lo = np.asarray(obj.position_m) - np.asarray(obj.size_m) / 2 - margin_m
    hi = np.asarray(obj.position_m) + np.asarray(obj.size_m) / 2 + margin_m
    above_table = centers[:, 2] > TABLE.position_m[2] + TABLE.size_m[2] / 2 + RES
    return int((np.all((centers >= lo) & (centers <= hi), axis=1) & above_table).sum())


def test_a_box_is_mapped_on_its_visible_faces(robot: RobotModel, self_filter: SelfFilter) -> None:
    m = ProjectionOccupancyMap(CONFIG)
    update = integrate(m, render(TABLE, BOX), robot, self_filter)
    assert update.hit_voxels > 0 and update.newly_occupied == m.voxel_count
    # Every occupied voxel is on the table or the box, not in the air around them.
    centers = m.occupied_centers_m()
    on_something = np.zeros(len(centers), dtype=bool)
    for obj in (TABLE, BOX):
        lo = np.asarray(obj.position_m) - np.asarray(obj.size_m) / 2 - RES
        hi = np.asarray(obj.position_m) + np.asarray(obj.size_m) / 2 + RES
        on_something |= np.all((centers >= lo) & (centers <= hi), axis=1)
    assert on_something.all(), centers[~on_something][:5]
    # The top face of the box (0.16 m square at 2 cm) is fully there.
    top = centers[(np.abs(centers[:, 2] - 0.40) < 0.0201) & (np.abs(centers[:, 0] - 0.55) < 0.07)
                  & (np.abs(centers[:, 1] - 0.25) < 0.07)]
    assert len(top) >= 36


def test_removed_box_clears_within_three_frames(robot: RobotModel, self_filter: SelfFilter) -> None:
    m = ProjectionOccupancyMap(CONFIG)
    with_box, without = render(TABLE, BOX), render(TABLE)
    for _ in range(10):  # saturate: the worst case for clearing
        integrate(m, with_box, robot, self_filter)
    assert near_box(m, BOX, 0.0) > 50
    for frame in range(3):
        integrate(m, without, robot, self_filter)
    assert near_box(m, BOX, 0.0) == 0
    assert m.voxel_count > 0  # the table stays


def test_box_moved_10_cm_leaves_nothing_at_its_old_place(robot: RobotModel, self_filter: SelfFilter) -> None:
    m = ProjectionOccupancyMap(CONFIG)
    before, after = render(TABLE, BOX), render(TABLE, MOVED)
    for _ in range(10):
        integrate(m, before, robot, self_filter)
    for _ in range(3):
        integrate(m, after, robot, self_filter)
    centers = m.occupied_centers_m()
    lo_new = np.asarray(MOVED.position_m) - np.asarray(MOVED.size_m) / 2 - RES
    hi_new = np.asarray(MOVED.position_m) + np.asarray(MOVED.size_m) / 2 + RES
    lo_old = np.asarray(BOX.position_m) - np.asarray(BOX.size_m) / 2
    hi_old = np.asarray(BOX.position_m) + np.asarray(BOX.size_m) / 2
    in_old = np.all((centers >= lo_old) & (centers <= hi_old), axis=1) & (centers[:, 2] > 0.2 + RES)
    in_new = np.all((centers >= lo_new) & (centers <= hi_new), axis=1)
    assert not (in_old & ~in_new).any(), centers[in_old & ~in_new][:5]
    assert in_new.sum() > 50


def test_arm_moving_through_the_view_leaves_no_voxels(robot: RobotModel, self_filter: SelfFilter) -> None:
    m = ProjectionOccupancyMap(CONFIG)
    poses = [HOME + np.array([a, 0.3 * s, 0.0, 0.4 * s, 0.0, 0.2, 0.0]) for a, s in
             ((-0.8, 1), (-0.4, -1), (0.0, 1), (0.4, -1), (0.8, 1))]
    for q in poses:
        integrate(m, render(TABLE, q=q), robot, self_filter, q)
    # Only the table is left: nothing above its top face (0.2 m) plus a voxel.
    centers = m.occupied_centers_m()
    assert m.voxel_count > 100
    assert (centers[:, 2] <= 0.2 + RES).all(), centers[centers[:, 2] > 0.2 + RES][:5]


def test_two_cameras_fuse_into_one_map(robot: RobotModel, self_filter: SelfFilter) -> None:
    front, both = ProjectionOccupancyMap(CONFIG), ProjectionOccupancyMap(CONFIG)
    a, b = render(TABLE, BOX), render(TABLE, BOX, cam=BACK)
    integrate(front, a, robot, self_filter)
    integrate(both, a, robot, self_filter)
    integrate(both, b, robot, self_filter)
    # The back camera sees the faces of the box that face it (-x and -y sides).
    def far_side(m: ProjectionOccupancyMap) -> int:
        centers = m.occupied_centers_m()
        lo = np.asarray(BOX.position_m) - np.asarray(BOX.size_m) / 2
        return int(((np.abs(centers[:, 0] - (lo[0] + RES / 2)) < RES) & (centers[:, 2] > 0.22)
                    & (np.abs(centers[:, 1] - BOX.position_m[1]) < 0.07)).sum())
    assert far_side(both) > far_side(front) + 10
    # Neither camera clears what the other one sees.
    assert both.voxel_count >= front.voxel_count


def test_clusters_match_the_sim_objects(robot: RobotModel, self_filter: SelfFilter) -> None:
    m = ProjectionOccupancyMap(CONFIG)
    with SimWorld(ROBOT, FRONT, SimConfig(objects=(TABLE, BOX, CAN), follow="kinematic", gravity=False)) as world:
        frame = world.render_depth()
        names = world.body_labels()
    integrate(m, frame, robot, self_filter)
    occupied = m.occupied_indices()
    found = cluster_voxels(m.ijk(occupied), m.centers_m(occupied), RES, labels=m.labels_of(occupied))
    by_label = {names.get(int(i), "?"): k for k, i in enumerate(found.label_ids)}
    assert {"table", "box", "can"} <= set(by_label), by_label
    for obj in (BOX, CAN):
        k = by_label[obj.name]
        assert np.all(found.bbox_min_m[k][:2] <= np.asarray(obj.position_m[:2]) + 0.01)
        assert np.all(found.bbox_max_m[k][:2] >= np.asarray(obj.position_m[:2]) - 0.01)
    dbscan = cluster_voxels(m.ijk(occupied), m.centers_m(occupied), RES, labels=m.labels_of(occupied), method="dbscan")
    assert dbscan.count == found.count


def test_a_cloud_rendered_back_to_depth_maps_like_the_depth_image(robot: RobotModel, self_filter: SelfFilter) -> None:
    frame = render(TABLE, BOX)
    points = points_from_depth(frame.depth_m, frame.intrinsics).astype(np.float32)
    depth, dropped = depth_from_points(points, frame.intrinsics)
    assert dropped == 0
    direct, via_cloud = ProjectionOccupancyMap(CONFIG), ProjectionOccupancyMap(CONFIG)
    integrate(direct, frame, robot, self_filter)
    via_cloud.integrate_depth(depth, frame.intrinsics, frame.world_from_camera, self_filter=self_filter,
                              world_from_link=robot.link_poses(HOME))
    np.testing.assert_array_equal(direct.occupied_indices(), via_cloud.occupied_indices())


def test_planning_binary_holds_the_inflated_voxels(robot: RobotModel, self_filter: SelfFilter) -> None:
    import octomap

    m = ProjectionOccupancyMap(CONFIG)
    integrate(m, render(TABLE, BOX), robot, self_filter)
    integrate(m, render(TABLE), robot, self_filter)  # some voxels flip back: the mirror follows
    tree = octomap.OcTree(RES)
    assert tree.readBinary(m.planning_binary())
    inflated = m.inflated_centers_m()
    assert len(inflated) > m.voxel_count
    def occupied(point: np.ndarray) -> bool:
        try:
            return bool(tree.isNodeOccupied(tree.search(point)))
        except octomap.NullPointerException:  # no node there: unknown
            return False

    assert all(occupied(c) for c in inflated)
    assert not occupied(np.array([-0.5, -0.5, 1.0]))


def test_the_arm_passing_close_to_an_obstacle_does_not_erase_it(robot: RobotModel) -> None:
    """A box 2.1 cm from the hand puts voxel centers between the clearing radius (2 cm) and the
    return filter's (4 cm): it must stay in the map while the arm is beside it. (A planned
    motion keeps voxel centers about 4 cm away: robot padding + inflation + half a voxel.)"""
    returns = SelfFilter(robot.link_hull_vertices, 0.04)
    box = SceneObject("box", "box", (0.307, 0.155, 0.59), size_m=(0.1, 0.06, 0.1))  # 2.1 cm from the hand at home
    away = HOME + np.array([-1.2, 0, 0, 0, 0, 0, 0])
    kept = {}
    for clear_padding in (0.02, 0.04):
        clearing = SelfFilter(robot.link_hull_vertices, clear_padding)
        m = ProjectionOccupancyMap(dataclasses.replace(CONFIG, fill_below_surfaces=True))  # fills the near side
        for q in (away, away, HOME, HOME):
            m.integrate_depth(*_frame_args(render(TABLE, box, q=q)), self_filter=returns, world_from_link=robot.link_poses(q),
                              clear_filter=clearing)
            if q is away:
                before = voxels_inside(m, box)
        kept[clear_padding] = voxels_inside(m, box) / before
    assert kept[0.02] == 1.0
    assert kept[0.04] < 0.95  # the old radius erased the near side: the test can tell


def _frame_args(frame) -> tuple:  # noqa: ANN001
    return frame.depth_m, frame.intrinsics, frame.world_from_camera


def table_columns_missing(m: ProjectionOccupancyMap, table: SceneObject = TABLE) -> int:
    """Columns over the table top with no occupied voxel at or above its top layer."""
    centers = m.occupied_centers_m()
    top = table.position_m[2] + table.size_m[2] / 2
    seen = set(map(tuple, np.floor(centers[centers[:, 2] > top - RES][:, :2] / RES).astype(int)))
    lo = np.round((np.asarray(table.position_m[:2]) - np.asarray(table.size_m[:2]) / 2) / RES).astype(int)
    hi = np.round((np.asarray(table.position_m[:2]) + np.asarray(table.size_m[:2]) / 2) / RES).astype(int)
    return sum((i, j) not in seen for i in range(lo[0], hi[0]) for j in range(lo[1], hi[1]))


def test_the_table_is_whole_in_the_shadow_of_a_tall_object(robot: RobotModel, self_filter: SelfFilter) -> None:
    """A shelf-high box hides a stretch of table from the camera; completion fills it, and only it."""
    tower = SceneObject("tower", "box", (0.7, 0.1, 0.4), size_m=(0.1, 0.3, 0.4))
    frame = render(TABLE, tower)
    plain = ProjectionOccupancyMap(dataclasses.replace(CONFIG, complete_support=False))
    completed = ProjectionOccupancyMap(CONFIG)
    for _ in range(2):
        integrate(plain, frame, robot, self_filter)
        integrate(completed, frame, robot, self_filter)
    assert table_columns_missing(plain) > 50  # the shadow (and the arm's)
    assert table_columns_missing(completed) == 0
    centers = completed.occupied_centers_m()
    top = TABLE.position_m[2] + TABLE.size_m[2] / 2
    layer = centers[np.abs(centers[:, 2] - (top + RES / 2)) < RES / 2]
    half = np.asarray(TABLE.size_m[:2]) / 2 + RES
    assert np.all(np.abs(layer[:, :2] - TABLE.position_m[:2]) <= half)  # nothing beyond the table's edges
    assert np.all(self_filter.outside_mask(centers, robot.link_poses(HOME)))  # nor inside the arm


def test_a_stray_column_at_table_height_does_not_stretch_the_support_over_the_robot(
        robot: RobotModel, self_filter: SelfFilter) -> None:
    """A flying pixel or a small object top at the table's height, far from the table (here a
    post beside the robot's base), must not pull the completed rectangle across the robot."""
    post = SceneObject("post", "box", (-0.3, -0.3, 0.1075), size_m=(0.04, 0.04, 0.215))  # top in the table top layer
    frame = render(TABLE, post)
    m = ProjectionOccupancyMap(CONFIG)
    for _ in range(2):
        integrate(m, frame, robot, self_filter)
    centers = m.occupied_centers_m()
    top = TABLE.position_m[2] + TABLE.size_m[2] / 2
    layer = centers[np.abs(centers[:, 2] - (top + RES / 2)) < RES / 2]
    off_table = layer[np.any(np.abs(layer[:, :2] - TABLE.position_m[:2]) > np.asarray(TABLE.size_m[:2]) / 2 + RES, axis=1)]
    assert len(off_table) <= 4, off_table  # the post's own top, nothing between it and the table


def test_flying_pixels_at_depth_edges_leave_no_voxels_in_free_space(robot: RobotModel, self_filter: SelfFilter) -> None:
    """The sim's flying pixels (at every depth edge, the arm's silhouette included) land
    between surfaces; the jump edge filter must keep them out of the map."""
    from robonav.pipeline.evaluation.map_accuracy import map_accuracy
    from robonav.pipeline.sim.noise import DepthNoiseConfig, apply_depth_noise

    frame = render(TABLE, BOX, CAN)
    noise = DepthNoiseConfig(enabled=True, axial_sigma_m=0.0, axial_sigma_per_m2=0.0, dropout_probability=0.0,
                             flying_pixel_probability=1.0)
    spurious = {}
    for jump_m in (0.0, 0.02):
        m = ProjectionOccupancyMap(dataclasses.replace(CONFIG, depth_edge_jump_m=jump_m))
        rng = np.random.default_rng(0)
        for _ in range(3):
            depth, labels = apply_depth_noise(frame.depth_m, frame.segmentation, frame.intrinsics, noise, rng)
            m.integrate_depth(depth, frame.intrinsics, frame.world_from_camera, self_filter=self_filter,
                              world_from_link=robot.link_poses(HOME), labels=labels)
        found = map_accuracy(m.occupied_centers_m(), RES, visible_surface_m=np.zeros((0, 3)), objects=[TABLE, BOX, CAN],
                             robot_hulls=robot.link_hull_vertices, world_from_link=robot.link_poses(HOME))
        spurious[jump_m] = found.spurious
    assert spurious[0.0] > 3, spurious  # without the filter the flying pixels do land in free space...
    assert spurious[0.02] == 0, spurious  # ...with it, none


def test_a_gap_between_tables_that_a_camera_sees_through_stays_free(robot: RobotModel, self_filter: SelfFilter) -> None:
    near = SceneObject("near", "box", (0.4, 0.0, 0.1), size_m=(0.2, 1.2, 0.2))
    far = SceneObject("far", "box", (0.7, 0.0, 0.1), size_m=(0.2, 1.2, 0.2))
    frame = render(near, far)
    m = ProjectionOccupancyMap(CONFIG)

    def in_gap() -> np.ndarray:
        centers = m.occupied_centers_m()
        return centers[(centers[:, 0] > 0.52) & (centers[:, 0] < 0.58) & (np.abs(centers[:, 1]) < 0.4)
                       & (centers[:, 2] > 0.15)]

    integrate(m, frame, robot, self_filter)
    assert len(in_gap()) > 0  # the first frame completes the two tops into one...
    for _ in range(3):
        integrate(m, frame, robot, self_filter)
    assert len(in_gap()) == 0, in_gap()[:10]  # ...the next ones see through the gap and keep it clear


def test_bad_input_is_refused_with_a_clear_error() -> None:
    m = ProjectionOccupancyMap(CONFIG)
    k = FRONT.intrinsics
    with pytest.raises(ValueError, match="depth_m must be"):
        m.integrate_depth(np.zeros((10, 10), np.float32), k, FRONT.world_from_camera)
    with pytest.raises(ValueError, match="floats"):
        m.integrate_depth(np.zeros((k.height, k.width), np.int32), k, FRONT.world_from_camera)
    with pytest.raises(ValueError, match="world_from_link"):
        m.integrate_depth(np.ones((k.height, k.width), np.float32), k, FRONT.world_from_camera,
                          self_filter=SelfFilter({"l": np.eye(4)[:, :3] * 0.1 + 0.01}, 0.0))
    # NaN and inf depths are "no return", not errors.
    depth = np.full((k.height, k.width), np.nan, np.float32)
    depth[::2] = np.inf
    update = m.integrate_depth(depth, k, FRONT.world_from_camera)
    assert update.hit_voxels == 0 and update.no_return == update.sampled


def test_filling_below_a_surface_stops_at_the_robot(robot: RobotModel, self_filter: SelfFilter) -> None:
    # A plate over the hand: the columns under it run down through the arm to the floor.
    hand = robot.link_poses(HOME)["panda_hand"][:3, 3]
    plate = SceneObject("plate", "box", (hand[0], hand[1], hand[2] + 0.25), size_m=(0.2, 0.2, 0.02))
    m = ProjectionOccupancyMap(dataclasses.replace(CONFIG, fill_below_surfaces=True))
    integrate(m, render(TABLE, plate), robot, self_filter)
    centers = m.occupied_centers_m()
    below = centers[(np.abs(centers[:, 0] - hand[0]) < 0.08) & (np.abs(centers[:, 1] - hand[1]) < 0.08)
                    & (centers[:, 2] < hand[2] + 0.2)]
    assert len(below) > 10  # the plate's shadow is filled, around the arm
    assert np.all(self_filter.outside_mask(centers, robot.link_poses(HOME)))  # but never on it


def test_the_fill_below_a_board_stops_where_the_camera_sees_under_it(robot: RobotModel, self_filter: SelfFilter) -> None:
    """A shelf board on a post: the camera sees the table under its near edge, not under its far side."""
    board = SceneObject("board", "box", (0.6, 0.1, 0.45), size_m=(0.3, 0.3, 0.02))
    post = SceneObject("post", "box", (0.6, -0.02, 0.325), size_m=(0.04, 0.04, 0.23))
    gap = SceneObject("gap", "box", (0.6, 0.1, 0.325), size_m=(0.3, 0.3, 0.19))  # between table and board
    m = ProjectionOccupancyMap(dataclasses.replace(CONFIG, fill_below_surfaces=True))
    for _ in range(3):
        integrate(m, render(TABLE, board, post), robot, self_filter)
    under_board = voxels_inside(m, gap, shrink_m=0.03)
    full = np.prod(np.floor((np.asarray(gap.size_m) - 0.06) / RES))
    assert 0.2 * full < under_board < 0.8 * full, (under_board, full)  # the hidden part filled, the seen part not
