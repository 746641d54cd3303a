"""The planner's collision spheres in the view: the sphere cover of every checked link, posed with
the arm (`robonav view --spheres`, or the "Collision spheres" toggle).

The spheres are the broad phase's (`pipeline/collision/spheres/sphere_model.py`, the default
cover the planner and the path guard build): each contains its link's collision hull, unpadded.
They are drawn in their link's frame under one frame node per link, so a new joint state moves
a dozen frames, not a hundred spheres. The cover is built on first show (seconds for a robot
whose meshes are not yet covered in this process: 6 s for the iiwa, 19 s for the UR5 on a busy
2-core machine), never when the layer stays off.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any

import numpy as np
import viser

from robonav.pipeline.collision.spheres.sphere_model import RobotSphereModel, robot_sphere_model
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import quat_xyzw_from_rotation
from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire.joint_order import positions_by_name

SPHERE_RGB = (255, 200, 40)
"""An amber that neither the robot's greys, the objects' blues nor the red of a collision use."""
SPHERE_OPACITY = 0.35
"""Translucent: the link meshes stay visible inside their spheres."""
SPHERE_SUBDIVISIONS = 2
"""Icosphere detail: 320 triangles a sphere, enough at a sphere's few centimetres."""


def world_spheres(robot: RobotModel, model: RobotSphereModel, q_rad: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Centers (S, 3) in the world frame [m] and radii (S,) [m] of the sphere model at joint
    state `q_rad` (robot joint order): each center moved by its link's pose."""
    poses = robot.link_poses(np.asarray(q_rad, dtype=np.float64))
    world_from_link = np.stack([poses[link] for link in model.link_names])[model.link_index]  # (S, 4, 4)
    centers = np.einsum("sij,sj->si", world_from_link[:, :3, :3], model.centers_link_m) + world_from_link[:, :3, 3]
    return centers, np.array(model.radii_m)


class SphereLayer:
    """The spheres under `/spheres` (a `SceneLayers` root, hidden unless asked for); shares the
    scene layers' lock, which also guards the robot model's forward-kinematics buffer."""

    def __init__(self, server: viser.ViserServer, robot: RobotModel, lock: threading.RLock) -> None:
        self.server = server
        self.robot = robot
        self._lock = lock
        self.root = server.scene.add_frame("/spheres", show_axes=False, visible=False)
        self.model: RobotSphereModel | None = None
        self.link_frames: dict[str, Any] = {}
        self.sphere_nodes: list[Any] = []
        self._q: np.ndarray | None = None

    def show(self, visible: bool) -> None:
        """Show or hide the spheres; the first show builds them, posed at the last joint state."""
        # The cover is computed outside the lock: for a robot new to this process it takes
        # seconds, while the arm keeps being redrawn.
        model = robot_sphere_model(self.robot) if visible and self.model is None else None
        with self._lock:
            if model is not None and self.model is None:
                self._build(model)
            self.root.visible = visible
            if visible and self._q is not None:
                self._pose(self._q)

    def follow(self, names: Sequence[str], positions: Sequence[float]) -> None:
        """Move the spheres with the arm; while hidden, only remember the state."""
        q = positions_by_name(names, positions, self.robot.joint_names)
        if q is None:
            return
        with self._lock:
            self._q = np.asarray(q, dtype=np.float64)
            if self.model is not None and self.root.visible:
                self._pose(self._q)

    def _build(self, model: RobotSphereModel) -> None:
        self.model = model
        scene = self.server.scene
        for li, link in enumerate(model.link_names):
            frame = scene.add_frame(f"/spheres/{link}", show_axes=False)
            self.link_frames[link] = frame
            for s in np.flatnonzero(model.link_index == li):
                self.sphere_nodes.append(scene.add_icosphere(
                    f"/spheres/{link}/{s}", radius=float(model.radii_m[s]), color=SPHERE_RGB, opacity=SPHERE_OPACITY,
                    subdivisions=SPHERE_SUBDIVISIONS, position=tuple(float(v) for v in model.centers_link_m[s]),
                    cast_shadow=False, receive_shadow=False))
        self._pose(self._q if self._q is not None else self.robot.home_position_rad)

    def _pose(self, q: np.ndarray) -> None:
        for link, world_from_link in self.robot.link_poses(q).items():
            frame = self.link_frames.get(link)
            if frame is not None:
                x, y, z, w = (float(v) for v in quat_xyzw_from_rotation(world_from_link[:3, :3]))
                frame.wxyz, frame.position = (w, x, y, z), world_from_link[:3, 3]
