"""The planner's planning scene: collision objects added, moved, attached over `planner/scene`.

`PlanningScene` is owned by the planner node. It keeps the world objects by name, mirrors them
into a `CollisionWorld` of its own (`set_objects`, `attach_object`, `detach_object`: the robot's
kinematics for attach and detach, FCL for the shapes) and answers every request with the whole
scene and a revision counter. A request either applies completely or not at all, under the
scene's own lock: it never waits for a plan. Plans run in the worlds of the planner's workers,
which take a `snapshot` of the scene (immutable objects) and `copy_scene_into` their world
between plans: a plan in flight keeps the scene it started with, the next one sees the change.
With a `SceneFile`, every change is saved and the scene (and its revision) is loaded back at
start: a restarted planner has the objects it had.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import zenoh

from robonav.pipeline.collision.attached import AttachedObject
from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.joint_order import reorder_to_robot
from robonav.pipeline.wire.messages import (
    AttachedObjectSpec,
    PlanningSceneState,
    SceneObjectSpec,
    SceneRequest,
    SceneResponse,
)
from robonav.services.common import decode_request, reply_ok
from robonav.services.config import LimitsConfig
from robonav.services.limits import check_limit, check_scene_request
from robonav.services.planner.scene_file import SceneFile, scene_requests
from robonav.services.planner.scene_specs import checked, invalid_request, object_spec, object_state, scene_object

log = logging.getLogger("robonav.planner.scene")

WORLD_FRAME = "world"


@dataclass(frozen=True)
class SceneSnapshot:
    """The scene at one revision: what a planning worker copies into its own world."""

    revision: int
    objects: tuple[SceneObject, ...]
    """World objects, posed in the world frame."""
    attached: tuple[AttachedObject, ...]
    """Attached objects, each posed in its link's frame."""


def copy_scene_into(world: CollisionWorld, snapshot: SceneSnapshot) -> None:
    """Make `world`'s objects and attached objects those of `snapshot` (the octree is left alone)."""
    for attached in world.attached_objects:
        world.detach_object(attached.name)
    world.set_objects(snapshot.objects)
    for attached in snapshot.attached:  # the object is posed in the link frame: link_from_object
        world.attach_object(attached.object, attached.link, attached.touch_links, world_from_link=np.eye(4))


class PlanningScene:
    """World and attached collision objects of one planner, served on `planner/scene`."""

    def __init__(
        self,
        world: CollisionWorld,
        lock: threading.Lock,
        *,
        current_q: Callable[[], FloatArray] | None = None,
        initial_objects: Sequence[SceneObject] = (),
        limits: LimitsConfig | None = None,
        scene_file: SceneFile | None = None,
        on_change: Callable[[PlanningSceneState], None] | None = None,
    ) -> None:
        """Take over the world's primitive objects.

        Args:
            world: The scene's collision world (no plan runs in it; `broad_phase=False` will do);
                its objects are replaced by this scene's.
            lock: Held for every change and snapshot; never held while planning.
            current_q: Returns the robot's latest (dof,) joint positions [rad] (or raises
                `ProtocolError(NO_JOINT_STATE)`); used by attach/detach of world-posed objects
                when the request carries no `joint_positions`.
            initial_objects: World objects the scene starts with (e.g. from the config).
            limits: Request and scene size limits (default: the config's defaults).
            scene_file: Where the scene is saved after every change; what it holds is loaded
                now, over `initial_objects`.
            on_change: Called with the whole scene now and after every change, under the lock,
                so calls come in revision order (the planner publishes it on `planner/scene_state`).
        """
        self._world = world
        self._lock = lock
        self._current_q = current_q
        self._limits = limits or LimitsConfig()
        self._objects: dict[str, SceneObject] = {o.name: o for o in initial_objects}
        self._revision = 0
        self._file = scene_file
        self._on_change = on_change
        with self._lock:
            world.set_objects(list(self._objects.values()))
            if scene_file is not None:
                self._restore(scene_file)
            self._changed()

    def _restore(self, scene_file: SceneFile) -> None:
        saved = scene_file.load()
        if saved is None:
            return
        revision, requests = saved
        for request in requests:
            try:
                getattr(self, f"_{request.operation}")(request)
            except ValueError as exc:  # ProtocolError is one: e.g. a link this robot config lacks
                log.error("planning scene %s: cannot restore a saved %s (%s); left out", scene_file.path,
                          request.operation, exc)
        self._revision = revision
        log.info("planning scene restored from %s: revision %d, %d world and %d attached objects", scene_file.path,
                 revision, len(self._objects), len(self._world.attached_objects))

    @property
    def revision(self) -> int:
        return self._revision

    def snapshot(self) -> SceneSnapshot:
        """The scene as it is now (a request in progress is not half in it)."""
        with self._lock:
            return SceneSnapshot(self._revision, tuple(self._objects.values()), self._world.attached_objects)

    def handle_scene(self, query: zenoh.Query) -> None:
        """`planner/scene` handler; wrap it in `guarded_queryable` so errors become error replies."""
        request = decode_request(query, SceneRequest)
        check_scene_request(request.objects, request.names, self._limits)
        response = self.apply(request)
        log.info("scene %s: revision %d, %d objects", request.operation, response.revision, len(response.objects))
        reply_ok(query, response)

    def apply(self, request: SceneRequest) -> SceneResponse:
        """Apply one request and describe the resulting scene.

        Raises:
            ProtocolError: INVALID_REQUEST (unknown object or link, name clash, bad shape or
                frame) or NO_JOINT_STATE (a world pose needs the robot state and none is known).
        """
        with self._lock:
            changed = getattr(self, f"_{request.operation}")(request)
            if changed:
                self._revision += 1
                if self._file is not None:
                    self._file.save(self._revision, scene_requests(list(self._objects.values()),
                                                                   self._world.attached_objects))
                self._changed()
            return self._describe(request.request_id)

    def state(self) -> PlanningSceneState:
        """The whole scene as `planner/scene_state` carries it: complete objects, attached ones in their link's frame."""
        attached = tuple(AttachedObjectSpec(link=a.link, touch_links=a.touch_links,
                                            object=dataclasses.replace(object_spec(a.object), frame_id=a.link))
                         for a in self._world.attached_objects)
        return PlanningSceneState(stamp=time.time(), revision=self._revision,
                                  objects=tuple(object_spec(o) for o in self._objects.values()), attached=attached)

    def _changed(self) -> None:
        if self._on_change is not None:
            self._on_change(self.state())

    # Each operation validates everything before it touches the world, so a rejected request changes nothing.

    def _add(self, request: SceneRequest) -> bool:
        attached = {a.name for a in self._world.attached_objects}
        objects = dict(self._objects)
        for i, spec in enumerate(request.objects):
            if spec.name in attached:
                raise invalid_request(f"'{spec.name}' is attached to a link; detach or remove it first", f"objects[{i}].name")
            self._require_world_frame(spec, i)
            objects[spec.name] = scene_object(spec, f"objects[{i}]")
        self._set_world_objects(objects)
        return True

    def _move(self, request: SceneRequest) -> bool:
        objects = dict(self._objects)
        for i, spec in enumerate(request.objects):
            current = self._world_object(spec.name, f"objects[{i}].name")
            self._require_world_frame(spec, i)
            objects[spec.name] = checked(lambda: dataclasses.replace(
                current,
                position_m=current.position_m if spec.position_m is None else spec.position_m,
                quat_xyzw=current.quat_xyzw if spec.quat_xyzw is None else spec.quat_xyzw,
            ), f"objects[{i}]")
        self._set_world_objects(objects)
        return True

    def _remove(self, request: SceneRequest) -> bool:
        attached = {a.name for a in self._world.attached_objects}
        for i, name in enumerate(request.names):
            if name not in self._objects and name not in attached:
                raise self._unknown(name, f"names[{i}]")
        for name in request.names:
            if name in attached:
                self._world.detach_object(name)
        self._set_world_objects({k: v for k, v in self._objects.items() if k not in request.names})
        return True

    def _attach(self, request: SceneRequest) -> bool:
        assert request.link is not None  # SceneRequest requires it for attach
        link, touch_links = request.link, tuple(request.touch_links or ())
        self._require_robot_frames(link, touch_links)
        attached = {a.name for a in self._world.attached_objects}
        needs_q = bool(request.names) or any((s.frame_id or WORLD_FRAME) == WORLD_FRAME for s in request.objects)
        q = self._robot_q(request) if needs_q else None
        plan: list[tuple[SceneObject, FloatArray | None]] = []  # (object, world_from_link or None for "at q")
        for i, name in enumerate(request.names):
            if name in self._objects:
                plan.append((self._objects[name], None))
            elif name in attached:  # re-attach: take it from where the robot holds it now
                pose = self._world.attached_world_from_object(name, q)
                plan.append((next(a.object for a in self._world.attached_objects if a.name == name).with_pose(pose), None))
            else:
                raise self._unknown(name, f"names[{i}]")
        for i, spec in enumerate(request.objects):
            if spec.type is None:
                raise invalid_request(f"attach of a new object '{spec.name}' needs type and position_m; "
                               "attach existing world objects by 'names'", f"objects[{i}].type")
            if spec.name in self._objects:
                raise invalid_request(f"'{spec.name}' is a world object; attach it by 'names' or remove it first", f"objects[{i}].name")
            frame = spec.frame_id or WORLD_FRAME
            if frame not in (WORLD_FRAME, link):
                raise invalid_request(f"objects[{i}].frame_id must be '{WORLD_FRAME}' or the attach link '{link}', got '{frame}'",
                               f"objects[{i}].frame_id")
            plan.append((scene_object(spec, f"objects[{i}]"), None if frame == WORLD_FRAME else np.eye(4)))
        taken = {obj.name for obj, _ in plan}
        self._set_world_objects({k: v for k, v in self._objects.items() if k not in taken})
        for obj, world_from_link in plan:
            if world_from_link is None:
                self._world.attach_object(obj, link, touch_links, q=q)
            else:
                self._world.attach_object(obj, link, touch_links, world_from_link=world_from_link)
        return True

    def _detach(self, request: SceneRequest) -> bool:
        attached = {a.name for a in self._world.attached_objects}
        for i, name in enumerate(request.names):
            if name not in attached:
                raise invalid_request(f"no attached object named '{name}' (attached: {sorted(attached)})", f"names[{i}]", name=name)
        q = self._robot_q(request)
        objects = dict(self._objects)
        for name in request.names:
            released = self._world.detach_object(name, q=q)
            assert released is not None  # q was given
            objects[name] = released
        self._set_world_objects(objects)
        return True

    def _clear(self, request: SceneRequest) -> bool:
        for attached in self._world.attached_objects:
            self._world.detach_object(attached.name)
        self._set_world_objects({})
        return True

    def _list(self, request: SceneRequest) -> bool:
        return False

    def _set_world_objects(self, objects: dict[str, SceneObject]) -> None:
        attached = {a.name for a in self._world.attached_objects}
        check_limit("objects", len(objects.keys() | attached), self._limits.max_scene_objects, "max_scene_objects")
        try:
            self._world.set_objects(list(objects.values()))
        except ValueError as exc:
            raise ProtocolError(ErrorCode.INVALID_REQUEST, str(exc), {"key": "objects"}) from exc
        self._objects = objects

    def _world_object(self, name: str, key: str) -> SceneObject:
        if name not in self._objects:
            raise self._unknown(name, key)
        return self._objects[name]

    def _unknown(self, name: str, key: str) -> ProtocolError:
        known = sorted([*self._objects, *(a.name for a in self._world.attached_objects)])
        return invalid_request(f"no object named '{name}' in the scene (objects: {known})", key, name=name)

    def _require_world_frame(self, spec: SceneObjectSpec, index: int) -> None:
        if (spec.frame_id or WORLD_FRAME) != WORLD_FRAME:
            raise invalid_request(f"objects[{index}].frame_id must be '{WORLD_FRAME}' for world objects, got '{spec.frame_id}'",
                           f"objects[{index}].frame_id")

    def _require_robot_frames(self, link: str, touch_links: tuple[str, ...]) -> None:
        robot = self._world.robot
        for key, name in (("link", link), *((f"touch_links[{i}]", n) for i, n in enumerate(touch_links))):
            try:
                robot.frame_pose(robot.home_position_rad, name)
            except ValueError as exc:
                raise invalid_request(f"{key}: '{name}' is not a link of robot '{robot.config.name}'", key, name=name) from exc

    def _robot_q(self, request: SceneRequest) -> FloatArray:
        robot = self._world.robot
        if request.joint_positions is not None:
            q = reorder_to_robot(request.joint_positions, request.joint_names, robot.joint_names, "joint_positions")
            return checked(lambda: robot.validate_q(q, "joint_positions"), "joint_positions")
        if self._current_q is None:
            raise ProtocolError(ErrorCode.NO_JOINT_STATE, "a world-frame pose needs joint_positions (this scene has no joint state)")
        return self._current_q()

    def _describe(self, request_id: str | None) -> SceneResponse:
        states = [object_state(obj) for obj in self._objects.values()]
        for attached in self._world.attached_objects:
            states.append(dataclasses.replace(object_state(attached.object), frame_id=attached.link, attached_link=attached.link,
                                              touch_links=attached.touch_links))
        return SceneResponse(revision=self._revision, objects=tuple(states), request_id=request_id)


