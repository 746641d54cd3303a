"""`sim/objects`: list, change and script the simulated obstacles while the sim runs.

The handler only translates wire specs to core objects; `apply_objects_request` runs on the
physics thread (the sim hands it over), so the world is never touched from two threads.
"""

from __future__ import annotations

import time

import numpy as np

from robonav.pipeline.sim.motion import MotionScript, ObjectMotion, Pose
from robonav.pipeline.sim.world import SimWorld
from robonav.pipeline.wire.messages import ObjectMotionSpec, SimObjectsRequest, SimObjectsResponse
from robonav.services.planner.scene_specs import checked, invalid_request, object_spec, object_state, scene_object


def object_motion(spec: ObjectMotionSpec, key: str) -> ObjectMotion:
    obj = None if spec.object is None else scene_object(spec.object, f"{key}.object")
    return checked(lambda: ObjectMotion(
        name=spec.name, action=spec.action, object=obj, position_m=spec.position_m,  # type: ignore[arg-type]
        quat_xyzw=spec.quat_xyzw, duration_s=spec.duration_s, at_s=spec.at_s,  # type: ignore[arg-type]
        at_progress=spec.at_progress, trajectory_id=spec.trajectory_id), key)


def motion_spec(motion: ObjectMotion) -> ObjectMotionSpec:
    """The wire form of a core motion."""
    return ObjectMotionSpec(name=motion.name, action=motion.action,
                            object=None if motion.object is None else object_spec(motion.object),
                            position_m=motion.position_m, quat_xyzw=motion.quat_xyzw, duration_s=motion.duration_s,
                            at_s=motion.at_s, at_progress=motion.at_progress, trajectory_id=motion.trajectory_id)


class SimObjects:
    """The sim's obstacles as the query sees them: the world, the motion script, the revisions."""

    def __init__(self, world: SimWorld, script: MotionScript) -> None:
        self.world = world
        self.script = script
        self.revision = 0
        """+1 for every change (request or motion)."""
        self.structure_revision = 0
        """+1 when objects are added or removed (render workers then rebuild their bodies)."""

    def apply(self, request: SimObjectsRequest) -> SimObjectsResponse:
        """Apply a request completely or not at all (specs are converted before anything changes)."""
        op = request.operation
        existing = {obj.name for obj in self.world.objects}
        if op in ("add", "set"):
            objects = [scene_object(spec, f"objects[{i}]") for i, spec in enumerate(request.objects)]
            if op == "set":
                self.world.set_objects(objects)
            else:
                for obj in objects:
                    self.world.add_object(obj)
            self._changed(structure=True)
        elif op == "move":
            for i, spec in enumerate(request.objects):
                if spec.name not in existing:
                    raise invalid_request(f"no sim object named {spec.name!r} (objects: {sorted(existing)})", f"objects[{i}].name")
                if spec.quat_xyzw is not None and float(np.linalg.norm(spec.quat_xyzw)) < 1e-9:
                    raise invalid_request(f"object '{spec.name}': quat_xyzw has zero norm", f"objects[{i}].quat_xyzw")
            current = {obj.name: obj for obj in self.world.objects}
            for spec in request.objects:
                self.world.set_object_pose(spec.name, spec.position_m or current[spec.name].position_m, spec.quat_xyzw)
            self._changed(structure=False)
        elif op == "remove":
            for i, name in enumerate(request.names):
                if name not in existing:
                    raise invalid_request(f"no sim object named {name!r} (objects: {sorted(existing)})", f"names[{i}]")
            for name in request.names:
                self.world.remove_object(name)
            self._changed(structure=True)
        elif op == "script":
            motions = [object_motion(spec, f"motions[{i}]") for i, spec in enumerate(request.motions)]
            self.script.arm(motions, self.world.sim_time_s)
        elif op == "cancel":
            self.script.cancel()
        return self.describe(request.request_id)

    def _changed(self, *, structure: bool) -> None:
        self.revision += 1
        if structure:
            self.structure_revision += 1

    def step_motions(self) -> None:
        """Apply the script's changes due now (physics thread, every step)."""
        if not self.script.pending:
            return
        poses = {obj.name: (obj.position_m, obj.quat_xyzw) for obj in self.world.objects}

        def pose_of(name: str) -> Pose | None:
            pose = poses.get(name)
            return None if pose is None else (np.asarray(pose[0], float), np.asarray(pose[1], float))

        for step in self.script.advance(self.world.sim_time_s, pose_of):
            if step.kind == "add":
                assert step.object is not None
                self.world.add_object(step.object)
                self._changed(structure=True)
            elif step.kind == "remove":
                self.world.remove_object(step.name)
                self._changed(structure=True)
            elif step.name in poses:
                self.world.set_object_pose(step.name, step.position_m, step.quat_xyzw)  # type: ignore[arg-type]
                self._changed(structure=False)

    def describe(self, request_id: str | None = None) -> SimObjectsResponse:
        return SimObjectsResponse(stamp=time.time(), sim_time_s=self.world.sim_time_s, revision=self.revision,
                                  objects=tuple(object_state(obj) for obj in self.world.objects),
                                  pending_motions=self.script.pending, fired_motions=self.script.fired,
                                  request_id=request_id)
