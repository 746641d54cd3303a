"""Every motion the executor streams is checked first, like a plan (MoveIt's plan-execution validity check).

A client may send `executor/execute` any path, and a plan's map may be older than the newest:
before streaming, the executor times the path and checks the whole timed motion
(`pipeline/trajectory/motion_check.py`) against its newest occupancy map and the planner's
scene objects, with the planner's padding, resolution and start escape. A colliding motion is
refused with PATH_IN_COLLISION naming the first colliding sample and the pairs.

Where the executor gets the planner's objects: every planner publishes its whole scene latched on
`planner/scene_state` when it starts and after every change, and the executor keeps the last
one it received (with several planners, whose scenes clients keep equal, the last to change).
A planner that dies leaves its last scene in force (what the cell last agreed on); a restarted
planner publishes its (empty) scene again and that replaces it. Before any scene arrived (no
planner has run, or it has not answered yet) an execute waits `executor.scene_wait_s` and is
then refused with SCENE_MISSING, unless `executor.require_scene` is off (a cell without a
planner), when motions are checked against the map alone. An execute that names a scene
revision (its plan's, or that of a change the client just made) waits as long for that
revision, since the planner answers a change before its scene reaches the executor. The map
obeys the planner's rules: missing, stale (by its stamp) or incomplete maps refuse the execute
as they refuse a plan.

A map that says its inflation is planned with that clearance kept on the way and released
near each query's start and goal, down to keeping the padded links off the seen voxels, and a
path that keeps the clearance may not be found in time, then one that keeps off the seen voxels
is returned (`pipeline/collision/surface_allowance.py`, `PlannerConfig.release_map_clearance`).
Every path the planner returns keeps that much, and only that much holds for all of them, so
the executor checks a motion on such a map against the seen voxels: a plan is never refused
for the clearance it was allowed to give up, and a motion into anything seen still is.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import octomap
import zenoh

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.perception.map_readiness import occupancy_problem
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.trajectory.motion_check import MotionViolation, checked_timing
from robonav.pipeline.trajectory.trajectory import JointTrajectory
from robonav.pipeline.types import FloatArray, StateValidFn
from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.messages import Occupancy, PlanningSceneState
from robonav.services.common import declare_latched_subscriber, guarded_subscriber
from robonav.services.config import RobonavConfig
from robonav.services.executor.maps import MapFeed
from robonav.services.keys import Keys
from robonav.services.planner.scene_specs import scene_object

log = logging.getLogger("robonav.executor")

Timing = Callable[[StateValidFn | None], JointTrajectory]
"""Times the path being checked; the argument checks corner blends (None: blend freely)."""


@dataclass(frozen=True)
class CheckedMotion:
    trajectory: JointTrajectory
    """The motion to stream, checked."""
    occupancy: Occupancy | None
    """The map it was checked against (None: none was needed and none had arrived)."""
    scene_revision: int | None
    """Revision of the planner scene it was checked against (None: checked without one)."""
    check_ms: float
    """Timing and checking, waits for a map or a scene included [ms]."""
    samples: int
    """Samples of the motion checked."""


@dataclass(frozen=True)
class _Scene:
    state: PlanningSceneState
    objects: list[SceneObject]
    attached: list[tuple[SceneObject, str, tuple[str, ...]]]


class ExecuteCheck:
    """The executor's copy of the planner's world and the check of a motion against it."""

    def __init__(self, cfg: RobonavConfig, robot: RobotModel, session: zenoh.Session, maps: MapFeed) -> None:
        self._cfg = cfg
        # FCL alone: a map swap costs a parse (0.3 ms on the demo's map), where the sphere broad
        # phase would expand every leaf of the octree first (about 55 ms, and maps change at up
        # to 30 Hz); the motion's few hundred states then take tens of milliseconds (46 ms median
        # on the demo's motions, timing included, on a loaded 2-core machine).
        self._world = CollisionWorld(robot, padding_m=cfg.robot.padding_m, broad_phase=False)
        self._world_lock = threading.Lock()
        self._maps = maps
        self._applied_map: Occupancy | None = None
        self._applied_scene: _Scene | None = None
        self._scene: _Scene | None = None
        self._scene_arrived = threading.Condition()
        self._warm_up(robot)
        self._sub = declare_latched_subscriber(session, Keys(cfg.cell).scene_state,
                                               guarded_subscriber(self.on_scene_state, "executor"))

    def _warm_up(self, robot: RobotModel) -> None:
        """FCL's first octree query in a process takes about half a second, and each exact link mesh
        tens of milliseconds: pay them now, not in an execute."""
        self._world.build_exact_shapes()
        tree = octomap.OcTree(0.02)
        tree.updateNode(robot.frame_pose(robot.home_position_rad, robot.config.end_effector_link)[:3, 3], True)
        self._world.set_octree(tree.writeBinary(), 0.02)
        self._world.collisions(robot.home_position_rad)
        self._world.clear_octree()

    def on_scene_state(self, sample: zenoh.Sample) -> None:
        """Subscriber callback: a scene that does not decode or build is dropped (and counted)."""
        state = PlanningSceneState.from_wire(sample.payload.to_bytes())
        objects = [scene_object(spec, f"objects[{i}]") for i, spec in enumerate(state.objects)]
        attached = [(scene_object(a.object, f"attached[{i}].object"), a.link, a.touch_links)
                    for i, a in enumerate(state.attached)]
        with self._scene_arrived:
            self._scene = _Scene(state, objects, attached)
            self._scene_arrived.notify_all()
        log.info("planner scene revision %d: %d objects, %d attached", state.revision, len(objects), len(attached))

    @property
    def scene_revision(self) -> int | None:
        with self._scene_arrived:
            return None if self._scene is None else self._scene.state.revision

    def check(self, path: FloatArray, timing: Timing, min_scene_revision: int | None = None) -> CheckedMotion:
        """Time `path` (K, n) with `timing` and check the motion against the newest map and the
        planner's scene (at least `min_scene_revision` when given).

        Raises:
            ProtocolError: SCENE_MISSING, OCCUPANCY_MISSING / _STALE / _INCOMPLETE (the planner's
                map rules), PATH_IN_COLLISION or OUT_OF_JOINT_LIMITS (the first bad sample).
        """
        started = time.perf_counter()
        scene = self._wait_for_scene(min_scene_revision)
        occupancy = self._wait_for_map()
        with self._world_lock:
            self._apply(scene, occupancy)
            # The planner's own resolution for a returned path: its states are the ones checked on the lines.
            resolution = self._cfg.planner.path_check_resolution_rad or self._cfg.planner.edge_resolution_rad
            with self._rule(path):
                checked = checked_timing(self._world, timing, resolution_rad=resolution,
                                         escape_radius_rad=self._cfg.planner.start_escape_rad, path_rad=path)
        revision = None if scene is None else scene.state.revision
        if checked.violation is not None:
            raise _refusal(checked.violation, occupancy, revision)
        return CheckedMotion(checked.trajectory, occupancy, revision, (time.perf_counter() - started) * 1e3, checked.samples)

    def _rule(self, path: FloatArray) -> contextlib.AbstractContextManager[None]:
        """On a map planned with its clearance released near the ends (`PlannerConfig.map_clearance_m`),
        the rule every path the planner returns keeps: padded links off the seen voxels (the
        clearance released everywhere); otherwise the inflated map, as it is."""
        if not self._world.has_surface_allowance:
            return contextlib.nullcontext()
        return self._world.anchored(path[:1], math.inf)

    def _wait_for_scene(self, min_revision: int | None) -> _Scene | None:
        """The last scene received; with `min_revision`, waits for one at least that new (the
        planner's reply to a change comes a moment before its scene reaches here)."""
        wait_s, key = self._cfg.executor.scene_wait_s, Keys(self._cfg.cell).scene_state

        def arrived() -> bool:
            return self._scene is not None and (min_revision is None or self._scene.state.revision >= min_revision)

        with self._scene_arrived:
            # Without the need (and no revision asked for), a scene counts when there is one.
            if self._cfg.executor.require_scene or min_revision is not None:
                self._scene_arrived.wait_for(arrived, timeout=wait_s)
            scene = self._scene
        if min_revision is not None and (scene is None or scene.state.revision < min_revision):
            have = None if scene is None else scene.state.revision
            raise ProtocolError(ErrorCode.SCENE_MISSING,
                                f"the execute asks for planner scene revision {min_revision} or newer and the executor "
                                f"has {'none' if have is None else f'revision {have}'} after {wait_s} s on {key} "
                                "(a planner restarted without its scene file starts again at revision 0)",
                                {"scene_revision": have, "required_scene_revision": min_revision})
        if scene is None and self._cfg.executor.require_scene:
            raise ProtocolError(ErrorCode.SCENE_MISSING,
                                f"no planner scene on {key} within {wait_s} s: the executor checks every motion "
                                "against the planner's objects and has none (is a planner running?)")
        return scene

    def _wait_for_map(self) -> Occupancy | None:
        """The newest map once it passes the planner's rules (waiting up to `planner.first_map_wait_s`
        for a first or complete one), or None when maps are not required and none arrived."""
        planner = self._cfg.planner
        cameras = [c.camera_id for c in self._cfg.cameras]
        deadline = time.monotonic() + planner.first_map_wait_s
        occupancy = self._maps.newest()
        while True:
            if not planner.require_occupancy:
                return occupancy
            problem = occupancy_problem(None if occupancy is None else occupancy.stamp,
                                        None if occupancy is None else occupancy.camera_frames, now_s=time.time(),
                                        max_age_s=planner.occupancy_max_age_s, cameras=cameras,
                                        min_frames=planner.occupancy_min_frames)
            left_s = deadline - time.monotonic()
            if problem is None:
                return occupancy
            if problem.code is ErrorCode.OCCUPANCY_STALE or left_s <= 0:
                # A fresh exception: raising `problem` itself would tie it to this frame in a cycle
                # (exception, traceback, frame, local), keeping the query alive until the garbage
                # collector runs, and Zenoh ends a query only when it is dropped: the client would
                # wait for its timeout after the error reply.
                raise ProtocolError(problem.code, problem.message, problem.details)
            occupancy = self._maps.wait_newer(occupancy, left_s)

    def _apply(self, scene: _Scene | None, occupancy: Occupancy | None) -> None:
        """Bring the world to `scene` and `occupancy` (under the world lock)."""
        if scene is not self._applied_scene:
            self._applied_scene = None
            try:
                for name in [a.name for a in self._world.attached_objects]:
                    self._world.detach_object(name)
                self._world.set_objects([] if scene is None else scene.objects)
                for obj, link, touch_links in ([] if scene is None else scene.attached):
                    self._world.attach_object(obj, link, touch_links, world_from_link=np.eye(4))
            except ValueError as exc:
                raise ProtocolError(ErrorCode.SCENE_MISSING, f"the planner's scene revision "
                                    f"{scene.state.revision if scene else '?'} cannot be rebuilt here: {exc}") from exc
            self._applied_scene = scene
        if occupancy is not self._applied_map:
            self._applied_map = None
            if occupancy is None:
                self._world.clear_octree()
            else:
                try:
                    self._world.set_octree(occupancy.octomap_binary, occupancy.resolution_m, occupancy.occupied_centers_m,
                                           clearance_m=self._cfg.planner.map_clearance_m(occupancy.inflation_m))
                except ValueError as exc:
                    raise ProtocolError(ErrorCode.OCCUPANCY_MISSING,
                                        f"the newest occupancy map (seq {occupancy.seq}) is unusable: {exc}") from exc
            self._applied_map = occupancy

    def close(self) -> None:
        self._sub.undeclare()


def _refusal(violation: MotionViolation, occupancy: Occupancy | None, scene_revision: int | None) -> ProtocolError:
    where = f"sample {violation.index} ({violation.time_from_start_s:.3f} s from the start)"
    details: dict[str, object] = {
        "index": violation.index, "time_from_start_s": violation.time_from_start_s,
        "positions": violation.positions_rad.tolist(), "samples": violation.samples,
        "occupancy_stamp": None if occupancy is None else occupancy.stamp, "scene_revision": scene_revision}
    if violation.limit_violations:
        return ProtocolError(ErrorCode.OUT_OF_JOINT_LIMITS,
                             f"the timed motion leaves the joint limits at {where}: {'; '.join(violation.limit_violations)}",
                             details | {"violations": list(violation.limit_violations)})
    return ProtocolError(ErrorCode.PATH_IN_COLLISION,
                         f"the motion collides at {where}: {', '.join(violation.pairs)}; refusing to execute it",
                         details | {"pairs": list(violation.pairs)})

