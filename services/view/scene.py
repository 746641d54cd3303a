"""What `robonav view` draws: viser scene nodes for the robot, clouds, map, clusters, path and cameras.

Everything here takes decoded arrays in the world frame and turns them
into viser nodes; Zenoh stays in `view.py`. Each layer lives under its own parent frame, so a
GUI toggle hides a whole layer by that frame's visibility.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import trimesh
import viser
import yourdfpy
from matplotlib import colormaps
from viser.extras import ViserUrdf

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.robot.link_geometry import collada_unit_m, resolve_mesh_path
from robonav.pipeline.robot.model import RobotModel, resolve_urdf_path
from robonav.pipeline.transforms import quat_xyzw_from_rotation, rotation_from_quat_xyzw
from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire.joint_order import positions_by_name
from robonav.services.config import perceived_world_from_camera
from robonav.services.view.clusters import ClusterBox
from robonav.services.view.planning_scene import PlanningSceneLayer
from robonav.services.view.spheres import SphereLayer

LAYERS: tuple[str, ...] = ("robot", "ghost", "path", "cloud", "voxels", "clusters", "objects", "cameras", "spheres")
"""Toggleable layers; each is the scene node `/<name>`. All show at start but `spheres` (the
planner's collision spheres, `spheres.py`), which shows only when asked for."""

PATH_RGB = (255, 0, 200)
"""Executed path trace: a magenta that neither the robot's greys nor the height colormap use
(the browser test looks for it)."""
PLANNED_RGB = (255, 150, 0)
"""A path planned from the GUI that has not been executed yet."""
GHOST_RGBA = (0.25, 0.55, 1.0, 0.35)
FRUSTUM_RGB = (40, 40, 40)
CLUSTER_PALETTE = colormaps["tab10"]
HEIGHT_LUT = (np.asarray(colormaps["viridis"](np.linspace(0.0, 1.0, 256)))[:, :3] * 255).astype(np.uint8)
"""Height colormap as a 256-entry table: indexing is far cheaper than calling the colormap per point."""


def cameras_of(cfg: Any) -> tuple[CameraConfig, ...]:
    """The configured cameras, whether the config has a `cameras:` list or an older single `camera:`."""
    cameras = getattr(cfg, "cameras", None)
    if cameras is None:
        cameras = getattr(cfg, "camera", None)
    if cameras is None:
        return ()
    if isinstance(cameras, CameraConfig):
        return (cameras,)
    return tuple(cameras)


def decimate(points: npt.NDArray[np.floating], max_points: int) -> npt.NDArray[np.floating]:
    """Finite rows of `points` (N, 3), thinned by a constant stride to at most `max_points`.

    A stride keeps a depth image's row-major order evenly covered and is deterministic;
    voxel downsampling would cost tens of milliseconds per 640x480 frame.
    """
    # Column by column and by index: masking the whole (N, 3) array costs ten times more.
    rows = np.flatnonzero(np.isfinite(points[:, 0]) & np.isfinite(points[:, 1]) & np.isfinite(points[:, 2]))
    if len(rows) > max_points:
        rows = rows[::math.ceil(len(rows) / max_points)]
    return points[rows]


def height_colors(z_m: npt.NDArray[np.floating], z_min_m: float, z_max_m: float) -> npt.NDArray[np.uint8]:
    """(N, 3) uint8 viridis colours of heights `z_m` (N,) between `z_min_m` and `z_max_m`."""
    span = max(z_max_m - z_min_m, 1e-6)
    index = np.clip((np.asarray(z_m, dtype=np.float64) - z_min_m) / span * 255.0, 0, 255).astype(np.intp)
    return HEIGHT_LUT[index]


def cluster_rgb(index: int) -> tuple[int, int, int]:
    r, g, b, _ = CLUSTER_PALETTE(index % 10)
    return int(r * 255), int(g * 255), int(b * 255)


def cluster_colors(points_m: FloatArray, boxes: Sequence[ClusterBox],
                   base: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """`base` (N, 3) with the points inside each cluster box painted in that cluster's colour."""
    out = base.copy()
    for i, box in enumerate(boxes):
        local = (points_m - box.center_m) @ rotation_from_quat_xyzw(box.quat_xyzw)
        inside = np.all(np.abs(local) <= box.size_m / 2.0, axis=1)
        out[inside] = cluster_rgb(i)
    return out


def interpolate_path(path_rad: FloatArray, max_step_rad: float) -> FloatArray:
    """(M, n) joint path with every straight joint-space segment of `path_rad` (K, n) cut into
    steps of at most `max_step_rad` on any joint, so its end-effector trace shows the real curve."""
    path = np.asarray(path_rad, dtype=np.float64)
    rows = [path[:1]]
    for a, b in zip(path[:-1], path[1:]):
        steps = max(1, math.ceil(float(np.max(np.abs(b - a))) / max_step_rad))
        t = np.linspace(0.0, 1.0, steps + 1)[1:, None]
        rows.append(a + t * (b - a))
    return np.vstack(rows)


def wxyz_of(rotation: FloatArray) -> npt.NDArray[np.float64]:
    """viser's scalar-first quaternion of a 3x3 rotation."""
    x, y, z, w = quat_xyzw_from_rotation(rotation)
    return np.array([w, x, y, z])


def load_urdf(robot: RobotModel) -> yourdfpy.URDF:
    """The robot's URDF with visual meshes (see `load_visual_urdf`)."""
    return load_visual_urdf(resolve_urdf_path(robot.config.urdf, robot.config.package_paths), robot.config.package_paths)


def load_visual_urdf(urdf_path: Path, package_paths: Sequence[str | Path] = ()) -> yourdfpy.URDF:
    """A URDF with its visual meshes in metres, mesh references resolved like the collision model's.

    A COLLADA mesh in other units (`<unit meter="0.001">`) gets that scale on its `<mesh>`:
    trimesh keeps a COLLADA file's coordinates in the file's unit (`collada_unit_m`).
    """
    def resolve(fname: str) -> str:
        return str(resolve_mesh_path(fname, urdf_path, package_paths))

    description = yourdfpy.URDF.load(urdf_path, build_scene_graph=False, load_meshes=False,
                                     build_collision_scene_graph=False, load_collision_meshes=False,
                                     filename_handler=resolve).robot
    for link in description.links:
        for visual in link.visuals:
            mesh = visual.geometry.mesh if visual.geometry is not None else None
            if mesh is None or not mesh.filename.lower().endswith(".dae"):
                continue
            unit_m = collada_unit_m(Path(resolve(mesh.filename)))
            if unit_m != 1.0:  # yourdfpy scales the loaded scene, node transforms included
                mesh.scale = unit_m if mesh.scale is None else unit_m * mesh.scale
    return yourdfpy.URDF(robot=description, build_scene_graph=True, load_meshes=True, build_collision_scene_graph=False,
                         load_collision_meshes=False, filename_handler=resolve)


class UrdfPose:
    """A URDF drawn under one scene node, posed from joint values by name."""

    def __init__(self, server: viser.ViserServer, robot: RobotModel, node: str,
                 color_rgba: tuple[float, float, float, float] | None = None) -> None:
        urdf = load_urdf(robot)
        # The URDF root's pose in the world, from the model the planner uses: it holds
        # `robot.world_from_base` and a base link other than the root.
        world_from_root = robot.frame_pose(robot.home_position_rad, urdf.base_link)
        self.frame = server.scene.add_frame(node, show_axes=False, wxyz=wxyz_of(world_from_root[:3, :3]),
                                            position=world_from_root[:3, 3])
        self._urdf = ViserUrdf(server, urdf, root_node_name=node, mesh_color_override=color_rgba)
        self._names = self._urdf.get_actuated_joint_names()
        fixed = robot.config.fixed_joint_positions
        self._values = np.array([fixed.get(name, 0.0) for name in self._names], dtype=np.float64)
        self._index = {name: i for i, name in enumerate(self._names)}

    def set_joints(self, names: Sequence[str], positions: Sequence[float]) -> None:
        """Pose the URDF; joints not named keep their last (or fixed) value."""
        for name, value in zip(names, positions):
            i = self._index.get(name)
            if i is not None and math.isfinite(value):
                self._values[i] = value
        self._urdf.update_cfg(self._values.copy())


class SceneLayers:
    """The viser scene of one robot cell; every method is safe to call from any thread."""

    def __init__(self, server: viser.ViserServer, robot: RobotModel, cameras: Sequence[CameraConfig], *,
                 workspace_z_m: tuple[float, float] = (0.0, 1.2), path_step_rad: float = 0.05,
                 show_spheres: bool = False) -> None:
        self.server = server
        self.robot = robot
        self.z_range_m = workspace_z_m
        self.path_step_rad = path_step_rad
        self._lock = threading.RLock()
        scene = server.scene
        scene.set_up_direction("+z")
        scene.add_grid("/grid", width=2.0, height=2.0, cell_size=0.1, plane="xy", position=(0.5, 0.0, 0.0))
        self.roots = {name: scene.add_frame(f"/{name}", show_axes=False) for name in LAYERS
                      if name not in ("robot", "ghost", "spheres")}
        self.robot_pose = UrdfPose(server, robot, "/robot")
        self.ghost_pose = UrdfPose(server, robot, "/ghost", color_rgba=GHOST_RGBA)
        self.roots["robot"] = self.robot_pose.frame
        self.roots["ghost"] = self.ghost_pose.frame
        self.roots["ghost"].visible = False
        self._ghost_wanted = True
        self._dense_path: FloatArray | None = None
        self._path_names: tuple[str, ...] = ()
        self._voxel_centers: npt.NDArray[np.float32] | None = None
        self._cluster_nodes: list[Any] = []
        self.clusters: tuple[ClusterBox, ...] = ()
        for camera in cameras:
            self._add_frustum(camera)
        self.planning = PlanningSceneLayer(server, robot, self._lock)
        self.spheres = SphereLayer(server, robot, self._lock)
        self.roots["spheres"] = self.spheres.root
        self.spheres.show(show_spheres)

    def _add_frustum(self, camera: CameraConfig) -> None:
        world_from_camera = perceived_world_from_camera(camera)
        # viser frustums use the optical convention too (z forward, x right, y down).
        self.server.scene.add_camera_frustum(
            f"/cameras/{camera.camera_id}", fov=math.radians(camera.vertical_fov_deg), aspect=camera.width / camera.height,
            scale=0.12, thickness=3.0, thickness_units="screen", color=FRUSTUM_RGB,
            wxyz=wxyz_of(world_from_camera[:3, :3]), position=world_from_camera[:3, 3])
        self.server.scene.add_label(f"/cameras/{camera.camera_id}/label", camera.camera_id, position=(0.0, 0.0, 0.0))

    def set_visible(self, layer: str, visible: bool) -> None:
        if layer == "spheres":  # built on first show, outside the lock (`SphereLayer.show`)
            self.spheres.show(visible)
            return
        with self._lock:
            if layer == "ghost":
                self._ghost_wanted = visible
                visible = visible and self._dense_path is not None
            self.roots[layer].visible = visible

    def set_robot_joints(self, names: Sequence[str], positions: Sequence[float]) -> None:
        with self._lock:
            self.robot_pose.set_joints(names, positions)
            self.spheres.follow(names, positions)

    def show_cloud(self, camera_id: str, points_m: FloatArray, colors: npt.NDArray[np.uint8]) -> None:
        """Replace one camera's cloud: (N, 3) world points [m], (N, 3) uint8 colours."""
        with self._lock:
            self.server.scene.add_point_cloud(f"/cloud/{camera_id}", np.asarray(points_m, dtype=np.float32), colors,
                                              point_size=0.008, point_shape="square", point_shading="flat")

    def color_cloud(self, points_m: FloatArray, by_cluster: bool) -> npt.NDArray[np.uint8]:
        colors = height_colors(points_m[:, 2], *self.z_range_m)
        with self._lock:
            boxes = self.clusters
        return cluster_colors(points_m, boxes, colors) if by_cluster and boxes else colors

    def show_voxels(self, centers_m: npt.NDArray[np.floating], resolution_m: float) -> bool:
        """Draw occupied voxel centers (N, 3) as boxes of side `resolution_m`; False if unchanged."""
        centers = np.asarray(centers_m, dtype=np.float32)
        with self._lock:
            if self._voxel_centers is not None and np.array_equal(self._voxel_centers, centers):
                return False
            self._voxel_centers = centers
            box = trimesh.creation.box(extents=(resolution_m,) * 3)
            count = len(centers)
            self.server.scene.add_batched_meshes_simple(
                "/voxels/boxes", np.asarray(box.vertices, np.float32), np.asarray(box.faces, np.uint32),
                batched_wxyzs=np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (count, 1)),
                batched_positions=centers, batched_colors=height_colors(centers[:, 2], *self.z_range_m),
                lod="off", flat_shading=True, cast_shadow=False, receive_shadow=False)
            return True

    def show_clusters(self, boxes: Sequence[ClusterBox]) -> None:
        with self._lock:
            for node in self._cluster_nodes:
                node.remove()
            self._cluster_nodes = []
            self.clusters = tuple(boxes)
            for i, box in enumerate(boxes):
                wxyz = wxyz_of(rotation_from_quat_xyzw(box.quat_xyzw))
                self._cluster_nodes.append(self.server.scene.add_box(
                    f"/clusters/{i}", color=cluster_rgb(i), dimensions=tuple(box.size_m), wireframe=True,
                    wxyz=wxyz, position=box.center_m))
                top = box.center_m + np.array([0.0, 0.0, box.size_m[2] / 2.0 + 0.03])
                self._cluster_nodes.append(self.server.scene.add_label(f"/clusters/{i}_label", box.label, position=top))

    def show_path(self, joint_names: Sequence[str], path_rad: FloatArray, *, executed: bool) -> None:
        """Draw a joint path (K, n) as its end-effector trace, waypoints, and a ghost at the goal."""
        dense = interpolate_path(path_rad, self.path_step_rad)
        order = [list(joint_names).index(name) for name in self.robot.joint_names]
        ee = self.robot.config.end_effector_link
        color = PATH_RGB if executed else PLANNED_RGB
        with self._lock:  # also for the forward kinematics: RobotModel reuses one buffer
            trace = np.array([self.robot.frame_pose(q[order], ee)[:3, 3] for q in dense])
            waypoints = np.array([self.robot.frame_pose(np.asarray(q)[order], ee)[:3, 3] for q in path_rad])
            if len(trace) > 1:
                segments = np.stack([trace[:-1], trace[1:]], axis=1).astype(np.float32)
                self.server.scene.add_line_segments("/path/trace", segments, color, thickness=4.0,
                                                    thickness_units="screen")
            self.server.scene.add_point_cloud("/path/waypoints", waypoints.astype(np.float32), color,
                                              point_size=0.025, point_shape="circle", point_shading="flat")
            self._dense_path = dense
            self._path_names = tuple(joint_names)
            self.set_ghost_fraction(1.0)
            self.roots["ghost"].visible = self._ghost_wanted

    def show_ghost(self, positions_rad: FloatArray) -> None:
        """Pose the ghost robot at a state (robot joint order), e.g. a goal that collides."""
        with self._lock:
            self.ghost_pose.set_joints(self.robot.joint_names, np.asarray(positions_rad, dtype=np.float64).tolist())
            self.roots["ghost"].visible = self._ghost_wanted

    def set_ghost_fraction(self, fraction: float) -> None:
        """Pose the ghost robot `fraction` (0..1) of the way along the last path's waypoints."""
        with self._lock:
            if self._dense_path is None:
                return
            i = round(min(max(fraction, 0.0), 1.0) * (len(self._dense_path) - 1))
            self.ghost_pose.set_joints(self._path_names, self._dense_path[i])

    def end_effector_pose(self, names: Sequence[str], positions: Sequence[float]) -> FloatArray | None:
        """world_from_end_effector (4, 4) at a joint state, or None if it lacks a planning joint."""
        q = positions_by_name(names, positions, self.robot.joint_names)
        if q is None:
            return None
        with self._lock:
            return self.robot.frame_pose(q, self.robot.config.end_effector_link)

