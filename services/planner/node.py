"""Planner service: answers `planner/plan` with collision-free joint paths.

Keeps the latest occupancy map and the latest joint state (the default start), and hands each
request to a worker thread (`planner.workers`), which plans with `MotionPlanner` in a world of
its own (`plan_worker.py`): a long request holds one worker, and the others go on answering.
Scene changes (`planner/scene`) apply to the scene at once; each worker copies them, and the
newest map, into its world before its next plan. Before the service declares itself alive,
every worker has planned once (`warm_up.py`), so the first request costs what any other does.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time

import numpy as np
import zenoh

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.perception.map_readiness import occupancy_problem
from robonav.pipeline.planning.motion_planner import PLANNERS, PlanProblem, PoseGoal
from robonav.pipeline.planning.ompl_planners import seed_ompl_once
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import make_transform
from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.joint_order import missing_joints, positions_by_name, reorder_to_robot
from robonav.pipeline.wire.messages import JointState, Occupancy, PlanRequest, PlanResponse
from robonav.services.common import (
    Node,
    declare_latched_publisher,
    declare_latched_subscriber,
    decode_request,
    guarded_queryable,
    guarded_subscriber,
    reply_error,
    reply_ok,
    run_service,
)
from robonav.services.config import RobonavConfig
from robonav.services.keys import Keys
from robonav.services.limits import check_plan_request
from robonav.services.planner.description import robot_description
from robonav.services.planner.plan_worker import PlanWorker
from robonav.services.planner.scene import PlanningScene
from robonav.services.planner.scene_file import SceneFile
from robonav.services.planner.warm_up import warm_up_worker
from robonav.services.workers import RequestWorkers

log = logging.getLogger("robonav.planner")

STATUS_CODES = {
    PlanStatus.START_INVALID: ErrorCode.START_IN_COLLISION,
    PlanStatus.GOAL_INVALID: ErrorCode.GOAL_IN_COLLISION,
    PlanStatus.GOAL_UNREACHABLE: ErrorCode.GOAL_UNREACHABLE,
    PlanStatus.OUT_OF_BOUNDS: ErrorCode.OUT_OF_JOINT_LIMITS,
    PlanStatus.TIMEOUT: ErrorCode.NO_SOLUTION,
}


class PlannerNode(Node):
    def __init__(self, cfg: RobonavConfig, session: zenoh.Session, *, scene_file: str | None = None) -> None:
        """Args: scene_file: where the planning scene is kept across restarts (default `planner.scene_file`)."""
        self.cfg = cfg
        self.robot = RobotModel.from_config(cfg.robot)
        # Before any planner exists: building an OMPL space already draws random numbers, and a
        # seed set after that has no effect (OMPL logs "Random number generation already started").
        seed_ompl_once(cfg.planner.seed)
        self._state_lock = threading.Lock()
        self._joint_state: JointState | None = None
        self._newest_map: Occupancy | None = None
        self._map_received_monotonic: float | None = None
        self._map_arrived = threading.Condition(self._state_lock)
        """Notified with every map: a plan waits on it for a first (or complete) map."""
        self._stopping = threading.Event()
        """Set when the service stops: running plans end early (their OMPL search polls it)."""
        keys = Keys(cfg.cell)
        # Latched: the executor checks every execute against this scene, also when it starts later.
        self._scene_pub = declare_latched_publisher(session, keys.scene_state)
        # Discovery: the robot this planner plans for, latched, so a client needs no config file.
        self._description_pub = declare_latched_publisher(session, keys.robot_description)
        self._description_pub.put(robot_description(self.robot).to_wire())
        # The scene's world only keeps the objects (no plan runs in it, so no broad phase).
        scene_file = scene_file or cfg.planner.scene_file
        self.scene = PlanningScene(CollisionWorld(self.robot, padding_m=cfg.robot.padding_m, broad_phase=False),
                                   threading.Lock(), current_q=self._start_from_joint_state, limits=cfg.limits,
                                   scene_file=SceneFile(scene_file) if scene_file else None,
                                   on_change=lambda state: self._scene_pub.put(state.to_wire()))
        self.plan_workers = [PlanWorker.create(self.robot, cfg.robot.padding_m, cfg.planner)
                             for _ in range(cfg.planner.workers)]
        for worker in self.plan_workers:
            warm_up_worker(worker, seed=cfg.planner.seed)
        self._subs = [
            session.declare_subscriber(keys.joint_states, guarded_subscriber(self.on_joint_state, "planner")),
            declare_latched_subscriber(session, keys.occupancy, guarded_subscriber(self.on_occupancy, "planner")),
        ]
        # Plans run on worker threads: a long one must not hold Zenoh's callback thread.
        self._workers = RequestWorkers("planner", self.handle_plan, workers=len(self.plan_workers),
                                       queue_size=cfg.limits.max_queued_requests)
        # complete: any one planner can answer a plan request, so a best-matching query reaches
        # exactly one of several replicas (a client races them all with target ALL).
        self._queryable = session.declare_queryable(keys.plan, self._workers.callback, complete=True)
        self._scene_queryable = session.declare_queryable(keys.scene, guarded_queryable(self.scene.handle_scene, "planner"))

    def on_joint_state(self, sample: zenoh.Sample) -> None:
        """The default start is the latest joint state to arrive (its stamp does not matter: one
        stamped in the future or long ago cannot hold later ones back). One lacking a planning
        joint is dropped and counted, and the last complete one stays the default start."""
        state = JointState.from_wire(sample.payload.to_bytes())
        if positions_by_name(state.names, state.position, self.robot.joint_names) is None:
            raise ValueError(f"joint state lacks joints {missing_joints(state.names, self.robot.joint_names)}")
        with self._state_lock:
            self._joint_state = state

    def on_occupancy(self, sample: zenoh.Sample) -> None:
        occupancy = Occupancy.from_wire(sample.payload.to_bytes())
        with self._state_lock:
            self._newest_map = occupancy
            self._map_received_monotonic = time.monotonic()
            self._map_arrived.notify_all()

    def _start_from_joint_state(self) -> np.ndarray:
        with self._state_lock:
            state = self._joint_state
        if state is None:
            raise ProtocolError(ErrorCode.NO_JOINT_STATE, "no start_positions given and no joint state received yet")
        q = positions_by_name(state.names, state.position, self.robot.joint_names)
        if q is None:
            raise ProtocolError(ErrorCode.NO_JOINT_STATE, "the latest joint state lacks joints "
                                f"{missing_joints(state.names, self.robot.joint_names)}")
        return q

    def _check_map(self) -> None:
        """Refuse to plan blind (`map_readiness.occupancy_problem`). A request that races the first
        map (services just started) or a map being rebuilt (a clear) waits for it briefly."""
        if not self.cfg.planner.require_occupancy:
            return
        deadline = time.monotonic() + self.cfg.planner.first_map_wait_s
        cameras = [camera.camera_id for camera in self.cfg.cameras]
        with self._state_lock:
            while True:
                occupancy = self._newest_map
                problem = occupancy_problem(
                    None if occupancy is None else occupancy.stamp, None if occupancy is None else occupancy.camera_frames,
                    now_s=time.time(), max_age_s=self.cfg.planner.occupancy_max_age_s, cameras=cameras,
                    min_frames=self.cfg.planner.occupancy_min_frames)
                left_s = deadline - time.monotonic()
                if problem is None:
                    return
                if problem.code is ErrorCode.OCCUPANCY_STALE or left_s <= 0:
                    # A fresh exception: raising `problem` itself would tie it to this frame in a cycle
                    # (exception, traceback, frame, local), keeping the query alive until the garbage
                    # collector runs, and Zenoh ends a query only when it is dropped: the client would
                    # wait for its timeout after the error reply.
                    raise ProtocolError(problem.code, problem.message, problem.details)
                self._map_arrived.wait(left_s)

    def handle_plan(self, query: zenoh.Query, worker: int) -> None:
        request = decode_request(query, PlanRequest)
        check_plan_request(request, self.cfg.limits)
        names = self.robot.joint_names
        if request.start_positions is not None:
            start = reorder_to_robot(request.start_positions, request.joint_names, names, "start_positions")
        else:
            start = self._start_from_joint_state()
        planner_id = request.planner_id or self.cfg.planner.planner_id
        if planner_id not in PLANNERS:
            raise ProtocolError(ErrorCode.UNKNOWN_PLANNER, f"unknown planner_id {planner_id!r}", {"known": list(PLANNERS)})
        self._check_map()
        problem = PlanProblem(
            start_rad=start, goals_rad=self._joint_goals(request), pose_goal=self._pose_goal(request),
            planner_id=planner_id,
            allowed_planning_time_s=request.allowed_planning_time or self.cfg.planner.allowed_planning_time_s,
            num_planning_attempts=request.num_planning_attempts or 1,
            seed=request.seed if request.seed is not None else self.cfg.planner.seed,
            simplify=self.cfg.planner.simplify if request.simplify is None else request.simplify,
            goal_tolerance_rad=request.goal_tolerance_rad or 0.0,
            workspace_min_m=request.workspace_min_m, workspace_max_m=request.workspace_max_m,
            stop=self._stopping.is_set,
        )
        plan_worker = self.plan_workers[worker]
        with self._state_lock:
            newest_map = self._newest_map
        # Between plans of this worker: what changed since its last one (a plan in flight on
        # another worker keeps the scene and map it started with).
        plan_worker.sync(self.scene.snapshot(), newest_map)
        try:
            outcome = plan_worker.planner.plan(problem)
        except ValueError as exc:  # shapes and values the decoder cannot know about
            raise ProtocolError(ErrorCode.INVALID_REQUEST, str(exc)) from exc
        map_stamp, scene_revision = plan_worker.map_stamp, plan_worker.scene_revision
        if outcome.status is not PlanStatus.SUCCESS or outcome.path is None:
            reply_error(query, STATUS_CODES[outcome.status], outcome.detail, outcome.details)
            return
        log.info("planned with %s: %d waypoints, %.1f ms, length %.2f rad%s", outcome.planner_id, len(outcome.path),
                 outcome.planning_time_s * 1e3, outcome.path_length_rad,
                 "; first left the start's padding" if outcome.start_escape is not None else "")
        reply_ok(query, PlanResponse(
            joint_names=names, path=outcome.path, planner_id=outcome.planner_id, goal_index=outcome.goal_index,
            goal_positions=outcome.path[-1],
            planning_time_s=outcome.planning_time_s, simplification_time_s=outcome.simplification_time_s,
            path_length_rad=outcome.path_length_rad, max_joint_step_rad=outcome.max_joint_step_rad,
            min_clearance_m=outcome.min_clearance_m if np.isfinite(outcome.min_clearance_m) else None,
            waypoint_count=len(outcome.path), occupancy_stamp=map_stamp,
            max_velocity_scaling_factor=request.max_velocity_scaling_factor,
            max_acceleration_scaling_factor=request.max_acceleration_scaling_factor,
            request_id=request.request_id, start_escaped=outcome.start_escape is not None,
            scene_revision=scene_revision,
        ))

    def _joint_goals(self, request: PlanRequest) -> np.ndarray | None:
        names = self.robot.joint_names
        if request.goal_positions is not None:
            return reorder_to_robot(request.goal_positions, request.joint_names, names, "goal_positions")
        if request.goal_set is not None:
            return np.array([reorder_to_robot(g, request.joint_names, names, f"goal_set[{k}]")
                             for k, g in enumerate(request.goal_set)])
        return None

    def _pose_goal(self, request: PlanRequest) -> PoseGoal | None:
        if request.goal_position_m is None:
            return None
        link = request.goal_link or self.robot.config.end_effector_link  # an unknown link fails in IK: INVALID_REQUEST
        quat = request.goal_quat_xyzw if request.goal_quat_xyzw is not None else np.array([0.0, 0.0, 0.0, 1.0])
        return PoseGoal(
            link=link, world_from_target=make_transform(request.goal_position_m, quat / np.linalg.norm(quat)),
            position_tolerance_m=request.position_tolerance_m if request.position_tolerance_m is not None else 1e-3,
            orientation_tolerance_rad=(None if request.goal_quat_xyzw is None else
                                       request.orientation_tolerance_rad if request.orientation_tolerance_rad is not None
                                       else 0.01),
        )

    def stop_planning(self) -> None:
        """End the running plans early (their searches poll this) and every later one at once:
        the service is stopping. Each gets its answer: an optimizing planner's best path so far,
        or NO_SOLUTION."""
        self._stopping.set()

    def close(self) -> None:
        self.stop_planning()
        self._queryable.undeclare()
        self._scene_queryable.undeclare()
        self._workers.close()
        self._scene_pub.undeclare()
        self._description_pub.undeclare()
        for sub in self._subs:
            sub.undeclare()


def main(argv: list[str] | None = None) -> int:
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--scene-file", help="keep the planning scene in this file across restarts (planner.scene_file)")
    known, rest = pre.parse_known_args(argv)
    return run_service("planner", rest, lambda cfg, session: PlannerNode(cfg, session, scene_file=known.scene_file),
                       parents=(pre,))
