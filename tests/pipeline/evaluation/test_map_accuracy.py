"""Map accuracy figures on hand-made maps: coverage, spurious voxels, voxels on the robot."""

from __future__ import annotations

import numpy as np

from robonav.pipeline.evaluation.map_accuracy import below_objects, map_accuracy, spurious_voxels
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.transforms import make_transform

RES = 0.02
ROBOT = RobotModel.from_config(RobotConfig())
LINKS = ROBOT.link_poses(np.array(RobotConfig().home_position_rad))
BOX = SceneObject("box", "box", (0.6, 0.0, 0.31), size_m=(0.2, 0.2, 0.2))


def top_face_points() -> np.ndarray:
    """What a camera straight above sees of the box: its top face."""
    u = np.linspace(0.501, 0.699, 40)
    xx, yy = np.meshgrid(u, u - 0.6)
    return np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, 0.409)])


def voxel_centers(points: np.ndarray) -> np.ndarray:
    return np.unique((np.floor(points / RES) + 0.5) * RES, axis=0)


def accuracy(centers: np.ndarray):
    return map_accuracy(centers, RES, visible_surface_m=top_face_points(), objects=[BOX],
                        robot_hulls=ROBOT.link_hull_vertices, world_from_link=LINKS)


def test_a_map_of_exactly_the_seen_face_is_fully_covered_and_clean() -> None:
    found = accuracy(voxel_centers(top_face_points()))
    assert found.surface_voxels == 100 and found.surface_covered == 1.0 and found.surface_covered_within_one_voxel == 1.0
    assert (found.spurious, found.on_robot) == (0, 0)


def test_missing_voxels_count_against_coverage_and_shifted_ones_only_strictly() -> None:
    face = voxel_centers(top_face_points())
    assert accuracy(face[10:]).surface_covered == 0.9
    shifted = accuracy(face + [0.0, 0.0, RES])  # one layer up: noise put every return above the face
    assert shifted.surface_covered == 0.0 and shifted.surface_covered_within_one_voxel == 1.0
    assert shifted.spurious == 0  # still within one voxel of the box


def test_voxels_inside_the_box_are_not_spurious_but_far_ones_and_ones_on_the_arm_are() -> None:
    inside = np.array([[0.61, 0.01, 0.31]])  # filled below the seen face
    far = np.array([[0.61, 0.01, 0.61], [-0.5, 0.5, 0.5]])
    hand = ROBOT.frame_pose(np.array(RobotConfig().home_position_rad), "panda_link5")[:3, 3][None]
    found = accuracy(np.vstack([voxel_centers(top_face_points()), inside, far, hand]))
    assert found.occupied == 104 and found.spurious == 3 and found.on_robot == 1
    assert found.spurious_fraction == 3 / 104


def test_spurious_voxels_are_those_no_object_explains_and_columns_below_an_object_are_told_apart() -> None:
    floating = SceneObject("floating", "box", (0.2, 0.3, 1.0), size_m=(0.1, 0.1, 0.1))
    on_top, beside = [0.21, 0.31, 1.05], [0.33, 0.3, 1.0]  # on its surface; 8 cm off its side
    column = [[0.19, 0.29, z] for z in (0.89, 0.71, 0.41)]  # straight below it, where fill_below puts voxels
    points = np.array([on_top, beside, *column, [0.6, 0.0, 0.31]])
    spurious = spurious_voxels(points, RES, [floating, BOX])
    assert spurious.tolist() == [False, True, True, True, True, False]
    # Within one voxel of a face counts as the object (noise), two voxels off does not.
    assert not spurious_voxels(np.array([[0.27, 0.3, 1.0]]), RES, [floating])[0]
    assert spurious_voxels(np.array([[0.31, 0.3, 1.0]]), RES, [floating])[0]
    assert below_objects(points, [floating]).tolist() == [False, False, True, True, True, False]
    # A turned object's footprint is that of its world-frame box; nothing is below an empty scene.
    turned = floating.with_pose(make_transform((0.2, 0.3, 1.0), (0.0, 0.0, np.sin(np.pi / 8), np.cos(np.pi / 8))))
    assert below_objects(np.array([[0.265, 0.3, 0.5]]), [turned])[0] and not below_objects(np.array([[0.265, 0.3, 0.5]]), [floating])[0]
    assert below_objects(np.array([[0.27, 0.3, 0.5]]), [floating], margin_m=0.03)[0]  # grown footprint
    assert not below_objects(np.array([[0.27, 0.3, 0.5]]), [floating])[0]
    assert below_objects(points, []).tolist() == [False] * 6 and spurious_voxels(points, RES, []).all()
