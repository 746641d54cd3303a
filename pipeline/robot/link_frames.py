"""Where every link of a URDF is, from joint positions by name: the robot as a viewer draws it.

`RobotModel` holds the planning joints only and needs the URDF's files (meshes for collision
geometry). A recording or a remote viewer has the URDF text of `robot/description` and joint
states that name their joints, and wants every link, fingers included. This builds Pinocchio's
kinematic model from the text alone (no mesh is read) and places each link in the base frame
placed at `world_from_base` in `world`: joints the state does not name sit at
`fixed_joint_positions`, a `<mimic>` joint follows its leader, any other at 0.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence

import numpy as np
import pinocchio as pin

from robonav.pipeline.types import FloatArray


class LinkFrames:
    """world_from_link of every link of a URDF whose `base_frame` stands at `world_from_base`
    (4, 4) in the world (None: the identity, the base frame is the world).

    Not thread-safe: forward kinematics reuses one Pinocchio data buffer.

    Raises:
        ValueError: the text is not a URDF Pinocchio can build, or `base_frame` is not one of its links.
    """

    def __init__(self, urdf: str, base_frame: str, fixed_joint_positions: Mapping[str, float] | None = None,
                 world_from_base: FloatArray | None = None) -> None:
        try:
            root = ET.fromstring(urdf)
            self._model = pin.buildModelFromXML(urdf)
        except (ET.ParseError, ValueError, RuntimeError) as exc:
            raise ValueError(f"the robot description's URDF cannot be read: {exc}") from exc
        self.link_names: tuple[str, ...] = tuple(link.attrib["name"] for link in root.findall("link"))
        if base_frame not in self.link_names:
            raise ValueError(f"base frame '{base_frame}' is not a link of the URDF (links: {list(self.link_names)})")
        self.base_frame = base_frame
        self._world_from_base = np.eye(4) if world_from_base is None else np.asarray(world_from_base, dtype=np.float64)
        if self._world_from_base.shape != (4, 4) or not np.isfinite(self._world_from_base).all():
            raise ValueError(f"world_from_base must be a finite (4, 4) transform, got shape {self._world_from_base.shape}")
        # (parent link, child link) of every joint, in URDF order: the tree a viewer's transforms follow.
        edges = []
        for joint in root.findall("joint"):
            parent, child = joint.find("parent"), joint.find("child")
            if parent is None or child is None or parent.get("link") is None or child.get("link") is None:
                raise ValueError(f"URDF joint '{joint.get('name')}' lacks a parent or child link")
            edges.append((str(parent.get("link")), str(child.get("link"))))
        self.edges: tuple[tuple[str, str], ...] = tuple(edges)
        children = {child for _, child in self.edges}
        self.root_link = next(name for name in self.link_names if name not in children)
        self._data = self._model.createData()
        self._frame_ids = {name: self._model.getFrameId(name, pin.BODY) for name in self.link_names}
        self._base_id = self._frame_ids[base_frame]
        self._fixed = {k: float(v) for k, v in (fixed_joint_positions or {}).items()}
        self._mimic: dict[str, tuple[str, float, float]] = {}
        for joint in root.findall("joint"):
            mimic = joint.find("mimic")
            if mimic is not None:
                self._mimic[joint.attrib["name"]] = (mimic.attrib["joint"], float(mimic.attrib.get("multiplier", 1.0)),
                                                     float(mimic.attrib.get("offset", 0.0)))
        # 1-DoF joints by name: (index in q, nq); a continuous joint is (cos, sin) in Pinocchio.
        self._joints = {self._model.names[j]: (self._model.joints[j].idx_q, self._model.joints[j].nq)
                        for j in range(1, self._model.njoints) if self._model.joints[j].nv == 1}

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The URDF's moving (1-DoF) joints."""
        return tuple(self._joints)

    def _q(self, positions: Mapping[str, float]) -> FloatArray:
        values = {**self._fixed, **{k: float(v) for k, v in positions.items()}}
        for name, (leader, multiplier, offset) in self._mimic.items():
            if name not in positions and leader in values:
                values[name] = multiplier * values[leader] + offset
        q = pin.neutral(self._model)
        for name, (index, nq) in self._joints.items():
            value = values.get(name, 0.0)
            if nq == 2:
                q[index], q[index + 1] = math.cos(value), math.sin(value)
            else:
                q[index] = value
        return q

    def world_from_links(self, positions: Mapping[str, float]) -> dict[str, FloatArray]:
        """world_from_link (4, 4) of every link, for joint positions by name [rad, or m].

        Raises:
            ValueError: a position is not finite.
        """
        bad = [name for name, value in positions.items() if not math.isfinite(value)]
        if bad:
            raise ValueError(f"joint positions must be finite: {bad} are not")
        pin.framesForwardKinematics(self._model, self._data, self._q(positions))
        world_from_root = self._world_from_base @ np.linalg.inv(self._data.oMf[self._base_id].homogeneous)
        return {name: world_from_root @ self._data.oMf[fid].homogeneous for name, fid in self._frame_ids.items()}

    def tree_transforms(self, positions: Mapping[str, float],
                        world_frame: str = "world") -> list[tuple[str, str, FloatArray]]:
        """(parent, child, parent_from_child (4, 4)) of the URDF root in `world_frame`, then of each
        joint's child link in its parent link: the tree ROS's robot_state_publisher sends, so a
        viewer that also reads the URDF (and its joint origins) finds the same parents.

        Raises:
            ValueError: a position is not finite.
        """
        poses = self.world_from_links(positions)
        out = [(world_frame, self.root_link, poses[self.root_link])]
        for parent, child in self.edges:
            out.append((parent, child, np.linalg.inv(poses[parent]) @ poses[child]))
        return out

    def link_positions(self, joint_names: Sequence[str], path: FloatArray, link: str) -> FloatArray:
        """(N, 3) origin of `link` in world at each row of `path` (N, len(joint_names)) [m].

        Raises:
            ValueError: `link` is not a link of the URDF, the shapes disagree, or a value is not finite.
        """
        if link not in self._frame_ids:
            raise ValueError(f"link '{link}' is not a link of the URDF")
        rows = np.asarray(path, dtype=np.float64)
        if rows.ndim != 2 or rows.shape[1] != len(joint_names):
            raise ValueError(f"path must have shape (N, {len(joint_names)}), got {rows.shape}")
        out = np.empty((rows.shape[0], 3))
        for k, row in enumerate(rows):
            out[k] = self.world_from_links(dict(zip(joint_names, row.tolist(), strict=True)))[link][:3, 3]
        return out
