"""One campaign scene on a running stack: swap the scene in, reach goals, judge what happened.

The stack keeps running between scenes: the sim swaps its obstacles (`sim/objects set`),
perception forgets its map (`perception/clear`), and the arm goes home first so the new scene
never appears around it.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.planning.motion_planner import MotionPlanner, PlanOutcome, PlanProblem
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.robot.turns import joint_distance_rad
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.goals import Intruder, perceivable_objects, sample_goal
from robonav.pipeline.sim.scenes import Scene
from robonav.pipeline.trajectory.path_guard import PathGuard
from robonav.pipeline.wire.codes import ErrorCode, ExecutionState
from robonav.pipeline.wire.messages import (
    ErrorReply,
    ExecuteResponse,
    ObjectMotionSpec,
    Occupancy,
    PlanResponse,
    SimObjectsRequest,
    SimObjectsResponse,
)
from robonav.services.campaign.intruder import INTRUDER_SLIDE_S, IntruderPlacer
from robonav.services.campaign.jog import jog
from robonav.services.campaign.maps import CampaignMaps
from robonav.services.campaign.stops import judge_guard_stop, true_objects
from robonav.services.client import QueryFailed, RobonavClient, trajectory_outcome
from robonav.services.config import RobonavConfig
from robonav.services.planner.scene_specs import object_spec

log = logging.getLogger("robonav.campaign")

MAX_ATTEMPTS = 4
"""Plans per goal: the first and up to three replans."""
RETRYABLE = {"NO_SOLUTION", "START_IN_COLLISION", "GOAL_IN_COLLISION", "OCCUPANCY_STALE", "OCCUPANCY_MISSING",
             "OCCUPANCY_INCOMPLETE", "NO_JOINT_STATE", "INVALID_REQUEST", "PATH_IN_COLLISION", "BUSY"}
"""Plan or execute errors worth another try on a fresher map or state (INVALID_REQUEST: a path
that no longer starts at the measured state; PATH_IN_COLLISION: the executor's newer map holds a
voxel on the planned path; BUSY: every worker was busy)."""
HOME_TOLERANCE_RAD = 0.05
MAP_SETTLE_FRAMES = 3
"""Frames of the slowest camera integrated after a scene swap before planning in it."""
MOVING_GOAL_DRAWS = 20
"""Goals drawn in a moving scene until one leaves room for an intruder."""
MOVING_PLANS = 5
"""Plans asked for a moving scene's goal until one leaves room for an intruder."""
MOVING_SPEED_FACTOR = 0.5
"""A moving scene's goal is driven at this share of the campaign's speed by default: at full speed most
paths take under 3 s, and few leave a place where the box can rest 1.7 s in (slide and lead)
that the arm reaches later and that is not beside the goal."""


@dataclass
class GoalRecord:
    scene: int
    index: int
    goal_rad: list[float]
    feasible: bool
    detour: bool
    moving: bool = False
    intruder: bool = False
    """A box was slid onto this goal's path."""
    intruder_lead_s: float | None = None
    """Planned time from the box resting until a link would first come within 10 cm of it [s]."""
    guard_delay_s: float | None = None
    """From the intruder resting to the guard's stop request [s]."""
    guard_map_age_s: float | None = None
    """Age of the map (newest frame in it) when the guard stopped the arm [s]."""
    guard_check_ms: list[float] = field(default_factory=list)
    executor_stops: int = 0
    """Times the executor's own path monitor stopped this goal's motion (PATH_BLOCKED)."""
    executor_stop_after_frame_s: list[float] = field(default_factory=list)
    """For each: from the newest camera frame in the map that blocked the path to the stop [s]."""
    executor_stop_after_rest_s: float | None = None
    """Intruder goals: from the box coming to rest to the executor's stop command [s] (at most
    one frame period more than from the first frame that shows it at rest)."""
    executor_faults: list[str] = field(default_factory=list)
    """Error codes of the motions the executor's watchdog stopped (TRACKING_ERROR: the arm fell
    behind its setpoints; JOINT_STATE_STALE), one per stopped motion."""
    reached: bool = False
    result: str = ""
    replans: int = 0
    start_escapes: int = 0
    """Plans that first left the padding around the map at the start (PlanResponse.start_escaped)."""
    guard_stops: int = 0
    guard_stop_voxels: list[dict[str, Any]] = field(default_factory=list)
    """For each guard stop, its blocking voxels judged against the truth (`stops.judge_guard_stop`)."""
    planning_ms: list[float] = field(default_factory=list)
    plan_min_clearance_m: float | None = None
    """Smallest clearance the planner reported (robot to its map) [m]."""
    plan_true_clearance_m: float | None = None
    """Smallest distance from the unpadded robot along the planned paths to the TRUE obstacles [m]."""
    errors: list[str] = field(default_factory=list)
    final_error_rad: float | None = None
    plans_through_box: list[dict[str, float]] = field(default_factory=list)
    """Plans made after the intruder was sent whose path meets the TRUE box at rest: for each, the
    start's distance from it [m], how many voxels of the newest map lie inside it, the time
    since it came to rest [s] (negative: still sliding when planned), the newest frame of that
    map against the rest time [s], the true box's distance from its rest pose [m] and the
    pixels of the resting box a camera shows with the arm at the path's start."""


class SceneRunner:
    """Runs scenes one after another on one stack."""

    def __init__(self, cfg: RobonavConfig, client: RobonavClient, *, goals_per_scene: int, guard: bool,
                 velocity_scaling: float | None, seed: int, moving_speed_factor: float = MOVING_SPEED_FACTOR) -> None:
        self.cfg = cfg
        self.client = client
        self.robot = RobotModel.from_config(cfg.robot)
        self.goals_per_scene = goals_per_scene
        self.guard = PathGuard(self.robot, padding_m=cfg.robot.padding_m, inflation_m=cfg.perception.inflation_m,
                               edge_resolution_rad=cfg.planner.edge_resolution_rad) if guard else None
        self.scaling = velocity_scaling
        self.moving_speed_factor = moving_speed_factor
        self.seed = seed
        self.home = np.asarray(cfg.robot.home_position_rad, dtype=np.float64)
        # What the map can allow: padding, inflation and a voxel of quantization on top of the
        # truth. A voxel holding a surface point reaches up to its diagonal beyond that point.
        self.margin_m = cfg.robot.padding_m + cfg.perception.inflation_m + math.sqrt(3.0) * cfg.perception.resolution_m
        self.view = CollisionWorld(self.robot, padding_m=self.margin_m)
        self.truth = CollisionWorld(self.robot, padding_m=0.0)
        self.reference = MotionPlanner(self.robot, self.view, cfg.planner)
        self._view_objects: tuple[SceneObject, ...] = ()
        self._intruder_at_rest: SceneObject | None = None
        self._box_truth = CollisionWorld(self.robot, padding_m=0.0, broad_phase=False)
        self._placer = IntruderPlacer(cfg, self.robot, goal_margin_m=self.margin_m)
        self.maps = CampaignMaps(cfg, client)
        self.link = cfg.robot.end_effector_link
        self.plan_seq = 0
        self.resets = 0
        """Times the arm was jogged home without the planner (in an emptied world)."""
        self._intruder_rest_at = 0.0
        if self.guard is not None:  # compile its kinematics now, not while the arm moves
            self.guard.warm_up(self.home)

    def close(self) -> None:
        self._placer.close()

    # --- queries --------------------------------------------------------------------------

    def _objects(self, request: SimObjectsRequest) -> SimObjectsResponse:
        reply = self.client.query(self.client.keys.sim_objects, request, SimObjectsResponse, 10.0)
        if isinstance(reply, ErrorReply):
            raise RuntimeError(f"sim/objects {request.operation}: {reply.code}: {reply.message}")
        return reply

    def _q(self) -> np.ndarray:
        assert self.client.joint_state is not None
        return self.client.joint_state.position.copy()

    def _error_rad(self, goal: np.ndarray) -> float:
        """Largest joint distance from `goal`, a continuous joint's modulo a turn (the planner
        ends it on the goal's turn nearest its start)."""
        return float(np.max(joint_distance_rad(self._q(), goal, self.robot.continuous_mask)))

    # --- scene ----------------------------------------------------------------------------

    def swap_in(self, scene: Scene) -> None:
        """Home the arm (or take it to the scene's start through an emptied world), replace the
        sim's obstacles, forget the map, wait for a fresh one."""
        self.go_home()
        if scene.start_rad is not None:
            self._objects(SimObjectsRequest(operation="set"))
            emptied = time.time()
            self.maps.clear()
            self.maps.wait_fresh(emptied, MAP_SETTLE_FRAMES)
            if not self._move(np.asarray(scene.start_rad, float), GoalRecord(-1, -1, [], True, False)):
                raise RuntimeError(f"scene {scene.name}: could not reach its start")
        self._objects(SimObjectsRequest(operation="set", objects=tuple(object_spec(o) for o in scene.objects)))
        swapped = time.time()
        self.maps.clear()
        if not self.maps.wait_fresh(swapped, MAP_SETTLE_FRAMES):
            raise RuntimeError("no occupancy map after the scene swap")

    def go_home(self) -> None:
        if self._error_rad(self.home) <= HOME_TOLERANCE_RAD:
            return
        for _ in range(2):
            if self._move(self.home, GoalRecord(-1, -1, [], True, False)):
                return
        # Stuck (e.g. boxed in by a noisy map): empty the world, then the way home is free.
        log.warning("going home through an emptied scene")
        self._objects(SimObjectsRequest(operation="set"))
        emptied = time.time()
        self.maps.clear()
        self.maps.wait_fresh(emptied, MAP_SETTLE_FRAMES)
        if self._move(self.home, GoalRecord(-1, -1, [], True, False)):
            return
        # The world is empty in truth, so a straight joint-space move is safe whatever the map
        # says (an operator jogging the arm in an empty cell). Counted: it bypasses the planner.
        self.resets += 1
        log.warning("jogging the arm home in the empty world (reset %d)", self.resets)
        if not jog(self.client, self.home, self.robot.continuous_mask, trajectory_id=f"campaign-reset-{self.resets}",
                   timeout_s=self.cfg.demo.goal_timeout_s, settle=lambda: self.maps.wait_settled(time.time()),
                   tolerance_rad=HOME_TOLERANCE_RAD, retryable=RETRYABLE, attempts=MAX_ATTEMPTS):
            raise RuntimeError("could not bring the arm home")

    def run(self, index: int, scene: Scene, *, moving: bool, rng: np.random.Generator) -> dict[str, Any]:
        started = time.monotonic()
        self.swap_in(scene)
        self._view_objects = perceivable_objects(scene.objects, self.cfg.perception.workspace_min_m[2])
        self.view.set_objects(self._view_objects)
        truth = self.truth
        truth.set_objects(scene.objects)
        if moving:  # only moving scenes place a box
            self._placer.set_scene(scene.objects)
        top_z = max((o.position_m[2] + o.local_bounds_m[1][2] for o in scene.objects if o.name == "table"), default=0.0)
        region_min = np.array(self.cfg.perception.workspace_min_m, dtype=np.float64)
        region_max = np.array(self.cfg.perception.workspace_max_m, dtype=np.float64)
        region_min[2] = max(region_min[2], top_z + 0.05)
        records: list[GoalRecord] = []
        goals = [np.asarray(g, float) for g in scene.goals_rad][: self.goals_per_scene]
        for g in range(self.goals_per_scene if not goals else len(goals)):
            start = self._q()
            seed = self.seed + index * 100 + g
            if goals:
                goal = self.robot.nearest_turn_rad(goals[g], start)  # the turn the planner ends on
                detour = not truth.motion_valid(start, goal, 0.01)
                reference = self.reference.plan(PlanProblem(start_rad=start, goals_rad=goal, allowed_planning_time_s=2.0,
                                                            seed=seed))
            else:
                # A moving scene's goal must leave room for the box: one whose way is too short
                # for it to rest ahead of the arm would test nothing, so another is drawn.
                drawn = self._draw_goal(index, g, start, rng, region_min, region_max, seed,
                                        draws=MOVING_GOAL_DRAWS if moving and g == 0 else 1)
                if drawn is None:
                    log.warning("scene %d: no goal found", index)
                    continue
                goal, reference = drawn
                detour = not truth.motion_valid(start, goal, 0.01)
            record = GoalRecord(index, g, np.round(goal, 4).tolist(), reference.status is PlanStatus.SUCCESS, detour,
                                moving=moving and g == 0)
            self._intruder_at_rest = None
            try:
                self._move(goal, record)
            except QueryFailed as exc:  # a slow or lost reply fails this goal, not the scene or the campaign
                record.errors.append(f"no_reply: {exc.reason}")
            if record.feasible and self._intruder_at_rest is not None:
                record.feasible = self._reachable_with(self._intruder_at_rest, start, goal, record)
            records.append(record)
            if record.moving:
                self._objects(SimObjectsRequest(operation="cancel"))
                names = {o.name for o in self._objects(SimObjectsRequest(operation="list")).objects}
                if "intruder" in names:
                    self._objects(SimObjectsRequest(operation="remove", names=("intruder",)))
                self._intruder_at_rest = None  # gone: the way home is not checked against it
        # Reset here, not at the swap: contacts while going home count for the scene that follows.
        contacts = self.client.contacts(reset=True)
        if isinstance(contacts, ErrorReply):
            raise RuntimeError(f"sim/contacts: {contacts.code}: {contacts.message}")
        return {"index": index, "scene": scene.name, "objects": len(scene.objects), "moving": moving,
                "contacts": contacts.contact_count, "contact_pairs": list(contacts.pairs),
                "min_distance_m": contacts.min_distance_m, "min_distance_pair": contacts.min_distance_pair, "goals": [r.__dict__ for r in records],
                "wall_s": round(time.monotonic() - started, 2)}

    def _draw_goal(self, index: int, g: int, start: np.ndarray, rng: np.random.Generator, region_min: np.ndarray,
                   region_max: np.ndarray, seed: int, draws: int) -> tuple[np.ndarray, PlanOutcome] | None:
        """A random goal (every other one needing a detour) and the reference plan to it. With
        `draws` > 1, goals are drawn until the reference path has room for an intruder; the
        last one drawn is kept when none has."""
        drawn: tuple[np.ndarray, PlanOutcome] | None = None
        for _ in range(draws):
            sample = sample_goal(self.view, rng, start, link=self.link, region_min_m=region_min,
                                 region_max_m=region_max, min_clearance_m=self.margin_m,
                                 want_blocked=(g % 2 == 0) or None)
            if sample is None:
                sample = sample_goal(self.view, rng, start, link=self.link, region_min_m=region_min,
                                     region_max_m=region_max, min_clearance_m=self.margin_m)
            if sample is None:
                continue
            reference = self.reference.plan(PlanProblem(start_rad=start, goals_rad=sample.q, allowed_planning_time_s=2.0,
                                                        seed=seed))
            drawn = (sample.q, reference)
            if draws == 1 or (reference.path is not None and self._intruder_for(reference.path) is not None):
                return drawn
        if draws > 1:
            log.warning("scene %d: no goal in %d draws leaves room for an intruder", index, draws)
        return drawn

    def _intruder_for(self, path: np.ndarray) -> Intruder | None:
        return self._placer.place(path, *self._scaling(moving=True))

    def _scaling(self, *, moving: bool) -> tuple[float, float]:
        """Velocity and acceleration scaling for a goal's motions (MoveIt's factors)."""
        velocity = self.scaling or self.cfg.executor.velocity_scaling
        acceleration = self.scaling or self.cfg.executor.acceleration_scaling
        factor = self.moving_speed_factor if moving else 1.0
        return velocity * factor, acceleration * factor

    def _reachable_with(self, box: SceneObject, start: np.ndarray, goal: np.ndarray, record: GoalRecord) -> bool:
        """Whether the reference planner still reaches `goal` from `start` with `box` added: a goal
        the intruder made unreachable is reported as such, not as a failure."""
        self.view.set_objects((*self._view_objects, box))
        try:
            return self.reference.plan(PlanProblem(start_rad=start, goals_rad=goal, allowed_planning_time_s=2.0,
                                                   seed=self.seed + record.scene * 100 + record.index)).status \
                is PlanStatus.SUCCESS
        finally:
            self.view.set_objects(self._view_objects)

    # --- one goal -------------------------------------------------------------------------

    def _move(self, goal: np.ndarray, record: GoalRecord) -> bool:
        """Plan, execute and replan until `goal` is reached or attempts run out."""
        armed = False
        for attempt in range(MAX_ATTEMPTS):
            if attempt > 0:
                record.replans += 1
                self.maps.wait_settled(time.time())
            self.plan_seq += 1
            # The guard's baseline: the planner plans on this map or a newer one, and a voxel it
            # never saw must not hide in a baseline taken after the plan came back.
            planned_on = self.client.occupancy
            plan = self.client.plan(goal, seed=self.seed + self.plan_seq, request_id=f"campaign-{self.plan_seq}")
            if isinstance(plan, ErrorReply):
                record.errors.append(f"plan:{plan.code}")
                if plan.code not in RETRYABLE:
                    break
                continue
            assert isinstance(plan, PlanResponse)
            intruder = None
            if record.moving and not armed:
                # Worked out before the arm starts: the box slides as the arm does.
                plan, intruder = self._plan_with_room(goal, plan)
            record.planning_ms.append(round(plan.planning_time_s * 1e3, 2))
            record.start_escapes += plan.start_escaped
            if plan.min_clearance_m is not None:
                record.plan_min_clearance_m = round(min(plan.min_clearance_m, record.plan_min_clearance_m or np.inf), 4)
            true_clearance = self.truth.path_clearance_m(plan.path, self.cfg.planner.edge_resolution_rad)
            if np.isfinite(true_clearance):
                record.plan_true_clearance_m = round(min(true_clearance, record.plan_true_clearance_m or np.inf), 4)
            if self._intruder_at_rest is not None:
                self._check_against_box(plan.path, record)
            trajectory_id = f"campaign-{record.scene}-{record.index}-{attempt}-{self.plan_seq}"
            fields: dict[str, Any] = {"joint_names": plan.joint_names, "trajectory_id": trajectory_id,
                                      "occupancy_stamp": plan.occupancy_stamp, "scene_revision": plan.scene_revision}
            velocity_scaling, acceleration_scaling = self._scaling(moving=record.moving)
            fields.update(max_velocity_scaling_factor=velocity_scaling, max_acceleration_scaling_factor=acceleration_scaling)
            execution = self.client.execute(plan.path, **fields)
            if isinstance(execution, ErrorReply):
                record.errors.append(f"execute:{execution.code}")
                if execution.code not in RETRYABLE:
                    break
                continue
            assert isinstance(execution, ExecuteResponse)
            if record.moving and not armed:
                self._intruder_rest_at = time.time() + INTRUDER_SLIDE_S
                record.intruder = self._arm_intruder(intruder, trajectory_id, record)
                armed = True
            record.result = self._follow(trajectory_id, plan.path, execution.duration_s, record, planned_on)
            if record.result == "succeeded":
                self.client.wait_for(lambda: self._error_rad(goal) <= 0.1 * self.cfg.demo.goal_tolerance_rad, 2.0)
                record.final_error_rad = round(self._error_rad(goal), 5)
                record.reached = record.final_error_rad <= self.cfg.demo.goal_tolerance_rad
                if record.reached:
                    return True
        return False

    def _check_against_box(self, path: np.ndarray, record: GoalRecord) -> None:
        """Record a plan whose path meets the resting intruder: the map the planner saw lacked it."""
        box = self._intruder_at_rest
        assert box is not None
        self._box_truth.set_objects([box])
        if self._box_truth.path_valid(path, self.cfg.planner.edge_resolution_rad):
            return
        occupancy = self.client.occupancy
        voxels = 0
        if occupancy is not None and len(occupancy.occupied_centers_m):
            _, half = box.local_bounds_m
            inside = np.all(np.abs(occupancy.occupied_centers_m - np.asarray(box.position_m)) <= half, axis=1)
            voxels = int(np.count_nonzero(inside))
        start_clearance_m = self._box_truth.clearance_m(path[0])
        # Why the map lacked it: still sliding, hidden from the cameras, or not yet in a frame.
        true_box = [o for o in self._objects(SimObjectsRequest(operation="list")).objects if o.name == box.name]
        from_rest_m = float(np.linalg.norm(np.subtract(true_box[0].position_m, box.position_m))) if true_box else None
        record.plans_through_box.append({
            "start_clearance_m": round(float(start_clearance_m), 4), "box_voxels_in_map": voxels,
            "since_rest_s": round(time.time() - self._intruder_rest_at, 3),
            "map_frame_after_rest_s": None if occupancy is None else round(occupancy.stamp - self._intruder_rest_at, 3),
            "box_from_rest_m": None if from_rest_m is None else round(from_rest_m, 4),
            "box_pixels_seen_from_start": self._placer.pixels_seen(box, path[0])})
        log.warning("scene %d: a plan passes through the resting box (start %.3f m from it, %d map voxels inside it, "
                    "the box %s m from its resting place)", record.scene, start_clearance_m, voxels,
                    "?" if from_rest_m is None else f"{from_rest_m:.3f}")

    def _plan_with_room(self, goal: np.ndarray, plan: PlanResponse) -> tuple[PlanResponse, Intruder | None]:
        """`plan`, or another plan to `goal` (the planner is randomized) that leaves room for an
        intruder, and the intruder; up to `MOVING_PLANS` plans."""
        intruder = self._intruder_for(plan.path)
        for _ in range(MOVING_PLANS - 1):
            if intruder is not None:
                break
            self.plan_seq += 1
            again = self.client.plan(goal, seed=self.seed + self.plan_seq, request_id=f"campaign-{self.plan_seq}")
            if not isinstance(again, PlanResponse):
                break
            plan, intruder = again, self._intruder_for(again.path)
        return plan, intruder

    def _follow(self, trajectory_id: str, path: np.ndarray, duration_s: float, record: GoalRecord,
                planned_on: Occupancy | None) -> str:
        """Wait for the trajectory to end; with the guard on, stop it when a map newer than
        `planned_on` blocks the rest (the newest map is checked at once)."""
        deadline = time.monotonic() + duration_s + self.cfg.demo.goal_timeout_s
        seen_seq = planned_on.seq if planned_on is not None else -1
        if self.guard is not None:
            self.guard.start(None if planned_on is None else planned_on.occupied_centers_m,
                             0.0 if planned_on is None else planned_on.resolution_m)

        def finished() -> bool:
            return self.client.trajectory_finished(trajectory_id)

        def woken() -> bool:
            return finished() or (self.client.occupancy is not None and self.client.occupancy.seq != seen_seq)

        while time.monotonic() < deadline:
            self.client.wait_for(woken, max(0.0, deadline - time.monotonic()))
            if finished():
                status = self.client.status
                assert status is not None
                if status.state is ExecutionState.ERROR and status.error_code == ErrorCode.PATH_BLOCKED:
                    record.executor_stops += 1
                    if status.blocked_after_frame_s is not None:
                        record.executor_stop_after_frame_s.append(round(status.blocked_after_frame_s, 3))
                    if record.intruder and record.executor_stop_after_rest_s is None and status.blocked_stamp:
                        record.executor_stop_after_rest_s = round(status.blocked_stamp - self._intruder_rest_at, 3)
                elif status.state is ExecutionState.ERROR and status.error_code:
                    record.executor_faults.append(status.error_code)
                return trajectory_outcome(status)
            occupancy = self.client.occupancy
            if occupancy is None or occupancy.seq == seen_seq:
                continue
            seen_seq = occupancy.seq
            if self.guard is None:
                continue
            check_started = time.perf_counter()
            self.guard.update_map(occupancy.occupied_centers_m, occupancy.resolution_m)
            # As the executor's monitor does: the inflation released near the path's ends on a map planned so.
            planner = self.cfg.planner
            allowance_rad = planner.surface_allowance_rad if planner.map_clearance_m(occupancy.inflation_m) is not None else 0.0
            blocked = self.guard.remaining_blocked(path, self._q(), allowance_radius_rad=allowance_rad)
            record.guard_check_ms.append(round((time.perf_counter() - check_started) * 1e3, 1))
            if blocked:
                record.guard_stops += 1
                if record.intruder and record.guard_delay_s is None:
                    record.guard_delay_s = round(time.time() - self._intruder_rest_at, 3)
                    record.guard_map_age_s = round(time.time() - occupancy.stamp, 3)
                log.info("%s: the rest of the path is blocked in map %d: stopping to replan", trajectory_id, seen_seq)
                self.client.stop()
                record.guard_stop_voxels.append(self._judge_stop(occupancy.resolution_m))
                self.client.wait_for(finished, 10.0)
                return "guard_stop"
        return "timeout"

    def _judge_stop(self, voxel_m: float) -> dict[str, Any]:
        """The guard's blocking voxels against the true objects, the box where the sim has it now."""
        assert self.guard is not None
        try:
            listed = self._objects(SimObjectsRequest(operation="list")).objects
        except (RuntimeError, QueryFailed) as exc:  # a report, not worth the goal
            return {"error": str(exc)}
        sliding = self._intruder_at_rest is not None and time.time() < self._intruder_rest_at
        objects = true_objects(self._view_objects, listed, self._intruder_at_rest)
        return judge_guard_stop(self.guard.blocking_centers_m, voxel_m, objects, box_sliding=sliding)

    def _arm_intruder(self, intruder: Intruder | None, trajectory_id: str, record: GoalRecord) -> bool:
        """Slide `intruder` onto the path as the arm starts (see `IntruderPlacer.place`)."""
        if intruder is None:
            log.warning("%s: no room for an avoidable intruder on the planned path", trajectory_id)
            return False
        record.intruder_lead_s = round(intruder.lead_s, 2)
        self._objects(SimObjectsRequest(operation="add", objects=(object_spec(intruder.start),)))
        self._objects(SimObjectsRequest(operation="script", motions=(ObjectMotionSpec(
            "intruder", position_m=intruder.target_m, duration_s=INTRUDER_SLIDE_S, at_progress=0.0,
            trajectory_id=trajectory_id),)))
        resting = np.eye(4)
        resting[:3, 3] = intruder.target_m
        self._intruder_at_rest = intruder.start.with_pose(resting)
        return True
