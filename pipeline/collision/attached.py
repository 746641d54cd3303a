"""Objects fixed to robot links: what is attached where, and where it is for a robot state.

`CollisionWorld` holds one `Attachments` and checks each attached object like a link
(`AttachedChecks`): padded against the world, bare against the other links, never against `link`
and its `touch_links`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import fcl
import numpy as np

from robonav.pipeline.collision.fcl_shapes import OCCUPANCY, object_geometry, world_aabb
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.types import BoolArray, FloatArray

if TYPE_CHECKING:  # the world these methods run on
    from robonav.pipeline.collision.world import CollisionWorld


@dataclass(frozen=True, eq=False)
class AttachedObject:
    """An object fixed to a robot link."""

    object: SceneObject
    """The object, posed in the LINK frame (its `world_from_object` is link_from_object)."""
    link: str
    """The robot frame it moves with."""
    touch_links: tuple[str, ...]
    """Robot links it may touch besides `link`."""
    link_from_object: FloatArray
    """(4, 4) pose of the object in the link frame."""

    @property
    def name(self) -> str:
        return self.object.name


@dataclass(frozen=True, eq=False)
class Attachment:
    info: AttachedObject
    obj: fcl.CollisionObject
    padded_obj: fcl.CollisionObject
    local_bounds: tuple[FloatArray, FloatArray]
    shape_index: int
    """A robot shape of `info.link` (its pose is the link's), or -1 for a link without geometry."""
    checked_shapes: BoolArray
    """(S,) robot shapes the object is checked against (not on `link` or `touch_links`)."""



class Attachments:
    """The attached objects of one world, by name, in attach order."""

    def __init__(self, robot: RobotModel, shape_links: Sequence[str], padding_m: float) -> None:
        """Args:
            robot: Kinematics, to pose links without collision geometry.
            shape_links: The link of each robot collision shape, in the world's shape order.
            padding_m: Robot-vs-world padding; attached primitives are padded like the links.
        """
        self._robot = robot
        self._shape_links = list(shape_links)
        self._padding_m = padding_m
        self._by_name: dict[str, Attachment] = {}

    def __bool__(self) -> bool:
        return bool(self._by_name)

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    @property
    def infos(self) -> tuple[AttachedObject, ...]:
        """The attached objects, in attach order."""
        return tuple(a.info for a in self._by_name.values())

    def attach(self, obj: SceneObject, link: str, touch_links: Sequence[str] = (), *, q: FloatArray | None = None,
               world_from_link: FloatArray | None = None) -> AttachedObject:
        """Fix `obj` to the robot frame `link` (see `CollisionWorld.attach_object`); names are the caller's to check."""
        if (q is None) == (world_from_link is None):
            raise ValueError("attach_object needs exactly one of q and world_from_link")
        home = self._robot.home_position_rad
        for i, name in enumerate((link, *touch_links)):
            try:
                self._robot.frame_pose(home, name)  # raises for names that are not frames of the robot
            except ValueError as exc:
                raise ValueError(f"{'link' if i == 0 else f'touch_links[{i - 1}]'}: {exc}") from exc
        if world_from_link is None:
            world_from_link = self._robot.frame_pose(self._robot.validate_q(q, "q"), link)
        pose = np.asarray(world_from_link, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ValueError(f"world_from_link must be a finite (4, 4) transform, got shape {pose.shape}")
        link_from_object = np.linalg.inv(pose) @ obj.world_from_object
        link_from_object.setflags(write=False)
        info = AttachedObject(obj.with_pose(link_from_object), link, tuple(touch_links), link_from_object)
        allowed = {link, *touch_links}
        self._by_name.pop(obj.name, None)
        self._by_name[obj.name] = Attachment(
            info=info,
            obj=fcl.CollisionObject(object_geometry(obj), fcl.Transform()),
            padded_obj=fcl.CollisionObject(object_geometry(obj, self._padding_m), fcl.Transform()),
            local_bounds=obj.local_bounds_m,
            shape_index=self._shape_links.index(link) if link in self._shape_links else -1,
            checked_shapes=np.array([lk not in allowed for lk in self._shape_links], dtype=bool),
        )
        return info

    def detach(self, name: str, *, q: FloatArray | None = None) -> SceneObject | None:
        """Unfix `name`; with `q`, the object posed in the world where the robot at `q` leaves it."""
        if name not in self._by_name:
            raise ValueError(f"no attached object named '{name}' (attached: {sorted(self._by_name)})")
        world_pose = None if q is None else self.world_from_object(name, q)
        info = self._by_name.pop(name).info
        return None if world_pose is None else info.object.with_pose(world_pose)

    def world_from_object(self, name: str, q: FloatArray) -> FloatArray:
        """(4, 4) world pose of the attached object `name` with the robot at `q` (dof,)."""
        if name not in self._by_name:
            raise ValueError(f"no attached object named '{name}' (attached: {sorted(self._by_name)})")
        info = self._by_name[name].info
        return self._robot.frame_pose(q, info.link) @ info.link_from_object

    def pose(self, q: FloatArray, world_from_shape_link: FloatArray) -> list[tuple[Attachment, FloatArray, FloatArray]]:
        """Pose every attached object for the robot at `q`, whose shapes' links are at
        `world_from_shape_link` (S, 4, 4); returns (attachment, world AABB center (3,), half extents (3,))."""
        out = []
        for attached in self._by_name.values():
            s = attached.shape_index
            world_from_link = world_from_shape_link[s] if s >= 0 else self._robot.frame_pose(q, attached.info.link)
            world_from_object = world_from_link @ attached.info.link_from_object
            for obj in (attached.obj, attached.padded_obj):
                obj.setRotation(world_from_object[:3, :3])
                obj.setTranslation(world_from_object[:3, 3])
            center, half = world_aabb(attached.info.object, world_from_object)
            out.append((attached, center, half))
        return out


class AttachedChecks:
    """The attached objects' collision checks of `CollisionWorld`."""

    def _check_attached(self: CollisionWorld, q: FloatArray, centers: FloatArray, hits: list[tuple[str, str]], *, first_only: bool) -> None:
        """Appends (attached object, link / object / 'occupancy') pairs that touch; needs `_pose(q)` first."""
        posed = self._attached.pose(q, self._world_from_shape_link)
        for attached, center, half in posed:
            name = attached.info.name
            candidates: list[tuple[str, fcl.CollisionObject, fcl.CollisionObject]] = []
            if self._object_names:
                near = np.all(np.abs(self._object_center - center) <= self._object_half + half + self._padding_m, axis=1)
                candidates += [(self._object_names[k], attached.padded_obj, self._object_fcl[k]) for k in np.flatnonzero(near)]
            if self._octree is not None:
                candidates.append((OCCUPANCY, attached.padded_obj, self._octree))
            offsets = centers - center
            radius = float(np.linalg.norm(half))
            near_shapes = (np.einsum("si,si->s", offsets, offsets) <= (self._radii + radius) ** 2) & attached.checked_shapes
            candidates += [(self._links[s], attached.obj, self._posed_obj(int(s), padded=False)) for s in np.flatnonzero(near_shapes)]
            for other, a, b in candidates:
                if (name, other) not in hits and self._collide(a, b):
                    hits.append((name, other))
                    if first_only:
                        return
        for i, (first, center_a, half_a) in enumerate(posed):
            for second, center_b, half_b in posed[i + 1:]:
                # Two objects on one link keep their relative pose: like adjacent links, never checked.
                if first.info.link == second.info.link or np.any(np.abs(center_a - center_b) > half_a + half_b):
                    continue
                if self._collide(first.obj, second.obj):
                    hits.append((first.info.name, second.info.name))
                    if first_only:
                        return
