"""Collect a hand-eye dataset in the sim: choose joint poses, render the board, save the folder.

Poses: candidate board (eye-to-hand) or camera (eye-in-hand) poses are drawn around where
the camera can see the board, each tilted by up to `max_tilt_deg` about a random axis and
rolled about the view axis; inverse kinematics (Pinocchio) turns each into joint positions
without self-collision (FCL). From the reachable ones, views are picked greedily for
diversity: each next one is the candidate farthest (rotation angle plus position) from those
already picked, since hand-eye accuracy grows with large rotations about varied axes. A
picked view whose render shows too little of the board is replaced by the next candidate.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from robonav.calibration.board import BoardSpec, board_corners_m, detect_board
from robonav.calibration.dataset import (
    DATASET_FORMAT,
    Dataset,
    GroundTruth,
    IntrinsicsSpec,
    PoseSpec,
    Setup,
    ViewSpec,
    save_dataset,
)
from robonav.calibration.hand_eye import CalibrationError, invert
from robonav.calibration.sim_scene import CalibrationScene, camera_intrinsics
from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.config import require
from robonav.pipeline.planning.ik import solve_ik
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.types import FloatArray

MIN_VISIBLE_FRACTION = 0.75
"""A render counts as a view when at least this share of the board's corners is detected."""


@dataclass(frozen=True)
class CollectOptions:
    views: int = 20
    width: int = 1280
    height: int = 960
    seed: int = 0
    setup: Setup = "eye_to_hand"
    supersample: int = 3
    """Render this many times larger in each direction and average down (pixel-area integration)."""
    noise_std: float = 1.0
    """Gaussian sensor noise on the 0-255 grey levels."""
    board: BoardSpec = field(default_factory=BoardSpec)
    max_tilt_deg: float = 40.0
    """Largest tilt of the board (or camera) away from facing the camera (or board) straight."""
    board_distance_m: tuple[float, float] = (0.8, 1.3)
    """eye_to_hand: range of camera-to-board distances to try [m]."""
    camera_distance_m: tuple[float, float] = (0.35, 0.6)
    """eye_in_hand: range of camera-to-board distances to try [m]."""
    candidates_per_view: int = 10

    def __post_init__(self) -> None:
        require(self.views >= 1, f"views must be >= 1, got {self.views}")
        require(self.width >= 64 and self.height >= 48, f"image must be at least 64x48, got {self.width}x{self.height}")
        require(1 <= self.supersample <= 4, f"supersample must be 1..4, got {self.supersample}")
        require(self.noise_std >= 0, f"noise_std must be >= 0, got {self.noise_std}")
        require(0 < self.max_tilt_deg < 80, f"max_tilt_deg must be in (0, 80), got {self.max_tilt_deg}")


def ee_from_board_mount(board: BoardSpec, offset_m: float = 0.12) -> FloatArray:
    """The board centered on the end effector's z axis, `offset_m` beyond it, printed face outwards."""
    width, height = board.size_m
    mount = np.eye(4)
    # x_board = y_ee, y_board = x_ee, z_board = -z_ee: the face (seen along +z_board) looks along +z_ee.
    mount[:3, :3] = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    mount[:3, 3] = np.array([0.0, 0.0, offset_m]) - mount[:3, :3] @ np.array([width / 2, height / 2, 0.0])
    return mount


def ee_from_camera_mount() -> FloatArray:
    """A wrist camera beside the fingers, looking along the end effector's z, tilted 15 deg outwards."""
    mount = np.eye(4)
    mount[:3, :3] = Rotation.from_euler("x", -15.0, degrees=True).as_matrix()
    mount[:3, 3] = [0.0, 0.09, 0.03]
    return mount


def world_from_board_fixed(board: BoardSpec) -> FloatArray:
    """A board lying face up on the floor in front of the robot, centered at (0.5, 0, 0)."""
    width, height = board.size_m
    pose = np.eye(4)
    pose[:3, :3] = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    pose[:3, 3] = np.array([0.5, 0.0, 0.001]) - pose[:3, :3] @ np.array([width / 2, height / 2, 0.0])
    return pose


def _look_rotation(z_axis: FloatArray, x_hint: FloatArray) -> FloatArray:
    z = z_axis / np.linalg.norm(z_axis)
    x = x_hint - z * (x_hint @ z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _tilted(rotation: FloatArray, rng: np.random.Generator, max_tilt_deg: float) -> FloatArray:
    """`rotation` turned about a random axis across its z by up to max_tilt_deg, and rolled about z."""
    z = rotation[:, 2]
    axis = np.cross(z, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    tilt = Rotation.from_rotvec(axis * math.radians(rng.uniform(0.0, max_tilt_deg)))
    roll = Rotation.from_rotvec(np.array([0.0, 0.0, 1.0]) * math.radians(rng.uniform(-60.0, 60.0)))
    return (tilt * Rotation.from_matrix(rotation) * roll).as_matrix()


def _candidates(options: CollectOptions, world_from_camera: FloatArray, intrinsics: IntrinsicsSpec,
                rng: np.random.Generator) -> list[tuple[FloatArray, FloatArray]]:
    """(world_from_board, world_from_camera) pairs, one per candidate view."""
    out = []
    board_center = np.array([*np.divide(options.board.size_m, 2.0), 0.0, 1.0])
    for _ in range(options.views * options.candidates_per_view):
        if options.setup == "eye_to_hand":
            distance = rng.uniform(*options.board_distance_m)
            # Within the middle 60 % of the image, so the tilted board stays in view.
            u = rng.uniform(-0.3, 0.3) * intrinsics.width / intrinsics.fx
            v = rng.uniform(-0.3, 0.3) * intrinsics.height / intrinsics.fy
            center = world_from_camera @ np.array([u * distance, v * distance, distance, 1.0])
            facing = _look_rotation(center[:3] - world_from_camera[:3, 3], world_from_camera[:3, 0])
            world_from_board = np.eye(4)
            world_from_board[:3, :3] = _tilted(facing, rng, options.max_tilt_deg)
            world_from_board[:3, 3] = center[:3] - world_from_board[:3, :3] @ board_center[:3]
            out.append((world_from_board, world_from_camera))
        else:
            world_from_board = world_from_board_fixed(options.board)
            center = (world_from_board @ board_center)[:3]
            looking_down = np.diag([1.0, -1.0, -1.0])
            direction = _tilted(looking_down, rng, options.max_tilt_deg)[:, 2]
            eye = center - direction * rng.uniform(*options.camera_distance_m)
            camera = np.eye(4)
            camera[:3, :3] = _tilted(_look_rotation(center - eye, world_from_board[:3, 0]), rng, 5.0)
            camera[:3, 3] = eye
            out.append((world_from_board, camera))
    return out


def _diverse_order(poses: list[FloatArray]) -> list[int]:
    """Greedy farthest-point order over (rotation angle [deg] + 100 * distance [m]), from the first pose."""
    if not poses:
        return []
    rotations = Rotation.from_matrix(np.array([t[:3, :3] for t in poses]))
    positions = np.array([t[:3, 3] for t in poses])
    order = [0]
    nearest = np.full(len(poses), np.inf)
    while len(order) < len(poses):
        last = order[-1]
        angle = np.degrees((rotations[last].inv() * rotations).magnitude())
        nearest = np.minimum(nearest, angle + 100.0 * np.linalg.norm(positions - positions[last], axis=1))
        nearest[order] = -np.inf
        order.append(int(np.argmax(nearest)))
    return order


def _in_view(world_from_board: FloatArray, world_from_camera: FloatArray, corners: FloatArray,
             intrinsics: IntrinsicsSpec) -> bool:
    camera_from_board = invert(world_from_camera) @ world_from_board
    points = corners @ camera_from_board[:3, :3].T + camera_from_board[:3, 3]
    if np.any(points[:, 2] < 0.1) or camera_from_board[2, 2] < math.cos(math.radians(70.0)):
        return False
    u = intrinsics.fx * points[:, 0] / points[:, 2] + intrinsics.cx
    v = intrinsics.fy * points[:, 1] / points[:, 2] + intrinsics.cy
    margin = 0.03 * intrinsics.width
    return bool(np.all((u > margin) & (u < intrinsics.width - margin) & (v > margin) & (v < intrinsics.height - margin)))


def collect(robot_cfg: RobotConfig, camera: CameraConfig, options: CollectOptions, out_dir: str | Path, *,
            progress: Callable[[str], None] | None = None) -> Dataset:
    """Render `options.views` views into `out_dir` (images/ and dataset.yaml) and return the dataset.

    Raises:
        CalibrationError: not enough reachable, collision-free poses that show the board.
    """
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(options.seed)
    robot = RobotModel.from_config(robot_cfg)
    collision = CollisionWorld(robot)
    intrinsics = camera_intrinsics(camera, options.width, options.height)
    ee = robot_cfg.end_effector_link
    eye_to_hand = options.setup == "eye_to_hand"
    mount = ee_from_board_mount(options.board) if eye_to_hand else ee_from_camera_mount()
    corners = board_corners_m(options.board)

    reachable: list[tuple[FloatArray, FloatArray, FloatArray, FloatArray]] = []
    for world_from_board, world_from_camera in _candidates(options, camera.world_from_camera, intrinsics, rng):
        if not _in_view(world_from_board, world_from_camera, corners, intrinsics):
            continue
        target = world_from_board @ invert(mount) if eye_to_hand else world_from_camera @ invert(mount)
        result = solve_ik(robot, target, ee, rng=rng, seed_q=robot.home_position_rad, max_restarts=8,
                          position_tolerance_m=1e-4, orientation_tolerance_rad=1e-4,
                          is_valid=lambda q: not collision.in_collision(q))
        if result.success:
            q = result.solutions[0]
            reachable.append((q, robot.frame_pose(q, ee), world_from_board, world_from_camera))
    if progress:
        progress(f"{len(reachable)} of {options.views * options.candidates_per_view} candidate poses are reachable "
                 "and in view")

    views: list[ViewSpec] = []
    with CalibrationScene(robot_cfg, options.board) as scene:
        for index in _diverse_order([r[1] for r in reachable]):
            if len(views) == options.views:
                break
            q, base_from_ee, world_from_board, world_from_camera = reachable[index]
            scene.set_joint_positions(q)
            scene.set_board_pose(world_from_board)
            image = scene.render_rgb(world_from_camera, intrinsics, supersample=options.supersample,
                                     noise_std=options.noise_std, rng=rng)
            if detect_board(options.board, image).ids.size < MIN_VISIBLE_FRACTION * options.board.corner_count:
                continue  # the arm hides part of the board, or it is too oblique
            name = f"images/view_{len(views):03d}.png"
            cv2.imwrite(str(out / name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            views.append(ViewSpec(name, tuple(float(v) for v in q), PoseSpec.from_matrix(base_from_ee)))
            if progress:
                progress(f"view {len(views)}/{options.views}")
    if len(views) < options.views:
        raise CalibrationError(f"only {len(views)} of {options.views} views could be collected: too few reachable poses "
                               "show the whole board; lower --views or raise the tilt/distance ranges")
    if eye_to_hand:
        truth = GroundTruth(world_from_camera=PoseSpec.from_matrix(camera.world_from_camera),
                            ee_from_board=PoseSpec.from_matrix(mount))
    else:
        truth = GroundTruth(ee_from_camera=PoseSpec.from_matrix(mount),
                            world_from_board=PoseSpec.from_matrix(world_from_board_fixed(options.board)))
    dataset = Dataset(format=DATASET_FORMAT, setup=options.setup, camera_id=camera.camera_id, intrinsics=intrinsics,
                      board=options.board, views=tuple(views), end_effector_link=ee,
                      joint_names=robot_cfg.joint_names, ground_truth=truth,
                      source={"kind": "sim", "renderer": "pybullet TinyRenderer", "seed": options.seed,
                              "supersample": options.supersample, "noise_std": options.noise_std})
    save_dataset(out, dataset)
    return dataset
