"""The executor's path monitor: the rest of the executing path against every new occupancy map,
and a replan when a new obstacle blocks it.

A thread of the executor's process checks the rest of the path on every map and at
`executor.path_check_rate_hz`: a new obstacle on it stops the arm smoothly, then either ends the
execution with PATH_BLOCKED or, when the request asked to replan, asks the planner for a new
path from the rest state to the same goal and continues under the same trajectory id. A map
older than `executor.max_map_age_s` stops the arm the same way (OCCUPANCY_STALE without a
replan): the guard cannot see what moved in since its frames. It works on the node's state
machine under the node's lock (`ExecutorNode` owns both).

Every voxel the rest of the path touches is watched. The execute check (`execute_check.py`)
verified the whole motion against one map before it started, the baseline here: its voxels are
known to keep off the whole path, so off its rest too, and only the voxels each new map holds
beyond them need a check. That is the fast path, and it pays: on the demo's map (17,515 voxels)
and its three planned paths, a check against every voxel took 20 ms (median, KD-tree and
spheres over all voxels, then FCL), against the voxels new since the baseline 6 ms, at up to
30 maps a second in the process that also runs the state machine (2-core machine, loaded). The
baseline is the map the motion was checked against, never one the client names: a voxel that a
plan's map held, that a later map dropped and that then came back would otherwise go unwatched.
A motion checked without a map (maps not required) has no baseline: every voxel counts.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
import zlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from robonav.pipeline.trajectory.path_guard import PathGuard, map_settled
from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.codes import ErrorCode, ExecutionState
from robonav.pipeline.wire.joint_order import reorder_to_robot
from robonav.pipeline.wire.messages import ErrorReply, ExecutorPath, Occupancy, PlanRequest, PlanResponse
from robonav.services.client import QueryFailed, query_one

if TYPE_CHECKING:
    from robonav.services.executor.node import ExecutorNode

log = logging.getLogger("robonav.executor")


@dataclass(frozen=True)
class Execution:
    """What the path monitor needs to know about the execution in progress."""

    trajectory_id: str
    path: np.ndarray
    """(K, n) the path being followed, robot joint order [rad]; the last row is the goal."""
    replan: bool
    replans_left: int
    velocity_scaling: float | None
    acceleration_scaling: float | None
    generation: int
    """Bumped by every accepted request and replan: the monitor takes a new baseline map."""
    baseline_map: Occupancy | None
    """The map the execute check verified the whole motion against: only voxels beyond it need
    watching. None: the motion was checked without a map, every voxel counts."""


class PathMonitor:
    """Holds the path guard; runs the monitor thread of one `ExecutorNode`."""

    def __init__(self, node: ExecutorNode) -> None:
        self._node = node
        cfg = node.cfg
        self._guard = PathGuard(node.robot, padding_m=cfg.robot.padding_m, inflation_m=cfg.perception.inflation_m,
                                edge_resolution_rad=cfg.planner.edge_resolution_rad)
        # Now, not on the first map: compiling would stall the setpoint loop.
        self._guard.warm_up(node.robot.home_position_rad)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="executor-path-monitor", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def close(self, timeout_s: float) -> None:
        self._stop.set()
        self._node.maps.wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout_s)

    def _loop(self) -> None:
        period_s = 1.0 / self._node.cfg.executor.path_check_rate_hz
        maps = self._node.maps
        occupancy: Occupancy | None = None
        baseline_generation = -1
        while not self._stop.is_set():
            maps.wake.wait(period_s)
            maps.wake.clear()
            newest = maps.newest()
            if newest is not occupancy:
                occupancy = newest
                if baseline_generation >= 0 and occupancy is not None:
                    self._guard.update_map(occupancy.occupied_centers_m, occupancy.resolution_m)
            with self._node._lock:
                execution, state = self._node._execution, self._node.machine.state
                commanded = self._node.machine.commanded_state(time.monotonic())
            if execution is None:
                continue
            try:
                if state is ExecutionState.REPLANNING:
                    self._replan(execution)
                elif state is ExecutionState.EXECUTING and commanded is not None:
                    if baseline_generation != execution.generation:
                        baseline = execution.baseline_map
                        self._guard.start(None if baseline is None else baseline.occupied_centers_m,
                                          0.0 if baseline is None else baseline.resolution_m)
                        baseline_generation = execution.generation
                        if occupancy is not None:
                            self._guard.update_map(occupancy.occupied_centers_m, occupancy.resolution_m)
                    if occupancy is not None:
                        self._check_rest_of_path(execution, commanded[0], occupancy)
                        self._check_map_age(execution, occupancy)
            except Exception:  # noqa: BLE001 - the monitor must outlive any one bad check
                log.exception("path monitor: check failed")

    def _check_rest_of_path(self, execution: Execution, q_commanded: np.ndarray, occupancy: Occupancy) -> None:
        # On a map planned with its inflation released near the ends, the guard releases it alike.
        planner = self._node.cfg.planner
        allowance_rad = planner.surface_allowance_rad if planner.map_clearance_m(occupancy.inflation_m) is not None else 0.0
        blocked_at = self._guard.blocked_state(execution.path, q_commanded, allowance_radius_rad=allowance_rad)
        if blocked_at is None:
            return
        blocked_stamp = time.time()
        delay_s = blocked_stamp - occupancy.stamp
        outcome = self._halt(execution, ErrorCode.PATH_BLOCKED,
                             f"a new obstacle blocks the rest of '{execution.trajectory_id}' (map {occupancy.seq})",
                             blocked_stamp=blocked_stamp, delay_s=delay_s)
        if outcome is not None:
            log.warning("%s: the rest of the path is blocked in map %d, %.0f ms after its newest frame: %s",
                        execution.trajectory_id, occupancy.seq, delay_s * 1e3, outcome)

    def _check_map_age(self, execution: Execution, occupancy: Occupancy) -> None:
        """Stop a motion the guard watches on maps older than `executor.max_map_age_s`: whatever
        moved in since their frames is unseen (perception lags behind a busy machine, or is gone)."""
        cfg = self._node.cfg
        limit_s = cfg.executor.max_map_age_s
        age_s = time.time() - occupancy.stamp
        if limit_s <= 0 or not cfg.planner.require_occupancy or age_s <= limit_s:
            return
        outcome = self._halt(execution, ErrorCode.OCCUPANCY_STALE,
                             f"the newest map (map {occupancy.seq}) is {age_s:.2f} s old, more than "
                             f"executor.max_map_age_s ({limit_s:g} s), while '{execution.trajectory_id}' moves")
        if outcome is not None:
            log.warning("%s: the newest map (map %d) is %.0f ms old, more than executor.max_map_age_s: %s",
                        execution.trajectory_id, occupancy.seq, age_s * 1e3, outcome)

    def _halt(self, execution: Execution, code: ErrorCode, message: str, *, blocked_stamp: float | None = None,
              delay_s: float | None = None) -> str | None:
        """Brake `execution` like a normal stop, to replan when it may, else to a fault with
        `code`; what was done, or None when it was preempted or stopped meanwhile."""
        with self._node._lock:
            if self._node._execution is not execution or self._node.machine.state is not ExecutionState.EXECUTING:
                return None
            if blocked_stamp is not None:
                self._node._blocked_stamp, self._node._blocked_after_frame_s = blocked_stamp, delay_s
            if execution.replan and execution.replans_left > 0:
                self._node.machine.stop(self._node._switch_time(), scaling=self._node.cfg.executor.acceleration_scaling, replan=True)
                outcome = "stopping to replan"
            else:
                self._node.machine.fault(self._node._switch_time(), code,
                                         f"{message}{'; no replans left' if execution.replan else ''}")
                outcome = "stopping (replan not requested)" if not execution.replan else "stopping (no replans left)"
            self._node._stream_latest()
        return outcome

    def _replan(self, execution: Execution) -> None:
        """At rest after a block: plan from here to the goal and stream the new path, or give up.

        Ends within `replans_left` x `executor.replan_timeout_s` in every case: each attempt is
        one plan request, whatever becomes of it (a plan, a structured error, no reply, a reply
        that is not a plan, a path the executor's own check refuses or cannot time) uses one
        attempt up, and waiting for a settled map or between attempts comes out of the same
        budget. Then PATH_BLOCKED."""
        with self._node._lock:
            last = self._node.machine.last_setpoint
        if last is None:
            return
        timeout_s = self._node.cfg.executor.replan_timeout_s
        deadline = time.monotonic() + execution.replans_left * timeout_s
        errors: list[str] = []
        try:
            self._replan_attempts(execution, last.position, deadline, errors)
        except Exception as exc:  # noqa: BLE001 - whatever went wrong, replanning ends here, not in a loop
            log.exception("%s: replanning failed", execution.trajectory_id)
            errors.append(f"{type(exc).__name__}: {exc}")
        finally:
            with self._node._lock:  # still replanning this execution: every attempt failed
                if self._node._execution is execution and self._node.machine.state is ExecutionState.REPLANNING:
                    self._node.machine.fault(time.monotonic(), ErrorCode.PATH_BLOCKED,
                                             f"a new obstacle blocks '{execution.trajectory_id}' and replanning failed: "
                                             + "; ".join(errors[-3:] or [f"no plan within {execution.replans_left} x {timeout_s} s"]))

    def _replan_attempts(self, execution: Execution, start: np.ndarray, deadline: float, errors: list[str]) -> None:
        """Plan requests until one is streamed, the attempts or the time run out, or the execution changed."""
        timeout_s = self._node.cfg.executor.replan_timeout_s
        self.wait_settled_map(time.time(), deadline)
        left = execution.replans_left
        while left > 0 and time.monotonic() < deadline:
            left -= 1
            attempt = execution.replans_left - left
            request = PlanRequest(goal_positions=execution.path[-1], joint_names=self._node.robot.joint_names,
                                  start_positions=start,
                                  seed=zlib.crc32(execution.trajectory_id.encode()) + self._node.machine.replans * 10 + attempt,
                                  request_id=f"{execution.trajectory_id}-replan-{self._node.machine.replans + 1}")
            try:
                reply, _ = query_one(self._node._session, self._node._keys.plan, request, PlanResponse,
                                     max(0.1, min(timeout_s, deadline - time.monotonic())))
                if isinstance(reply, PlanResponse) and self._start_replanned(execution, reply, left):
                    return
                errors.append(f"{reply.code}: {reply.message}" if isinstance(reply, ErrorReply) else "the plan was not taken")
            except QueryFailed as exc:
                errors.append(f"no plan: {exc}")
            except ProtocolError as exc:  # the executor's own check refused the new path
                errors.append(f"{exc.code.value}: {exc.message}")
            except Exception as exc:  # noqa: BLE001 - e.g. a path that cannot be timed: this attempt failed
                log.exception("%s: replan %d", execution.trajectory_id, attempt)
                errors.append(f"{type(exc).__name__}: {exc}")
            log.warning("%s: replan %d failed: %s", execution.trajectory_id, attempt, errors[-1])
            with self._node._lock:
                if self._node._execution is not execution or self._node.machine.state is not ExecutionState.REPLANNING:
                    return  # a new request or a stop came in meanwhile
            pause_s = min(self._node.cfg.executor.replan_delay_s, deadline - time.monotonic())
            if left > 0 and pause_s > 0 and self._stop.wait(pause_s):
                return

    def wait_settled_map(self, rested_at: float, deadline: float = float("inf")) -> None:
        """Hold the replan until the two newest maps, both stamped after `rested_at`, agree
        (`map_settled`), or `executor.replan_settle_s` passes (or the monotonic `deadline`)."""
        deadline = min(deadline, time.monotonic() + self._node.cfg.executor.replan_settle_s)
        judged: Occupancy | None = None  # the newest map already compared with the one before
        while time.monotonic() < deadline:
            maps = self._node.maps.two_newest()
            if len(maps) == 2 and maps[1] is not judged:
                judged = maps[1]
                before, now = maps
                if before.stamp > rested_at and map_settled(before.occupied_centers_m, now.occupied_centers_m,
                                                            now.resolution_m):
                    return
            if self._stop.wait(0.02):
                return

    def _start_replanned(self, execution: Execution, plan: PlanResponse, replans_left: int) -> bool:
        """Check the new path like any execute and stream it; False when a request or a stop came
        in while planning.

        Raises:
            ProtocolError: the execute check refused it (PATH_IN_COLLISION, a map or scene problem).
        """
        path = reorder_to_robot(plan.path, plan.joint_names, self._node.robot.joint_names, "path")
        checked = self._node.check.check(path, lambda valid: self._node._time_parameterize(
            path, execution.velocity_scaling, execution.acceleration_scaling, valid), plan.scene_revision)
        trajectory = checked.trajectory
        with self._node._lock:
            if self._node._execution is not execution or self._node.machine.state is not ExecutionState.REPLANNING:
                return False  # a new request or a stop came in while planning
            self._node.machine.start(trajectory, execution.trajectory_id, self._node._switch_time(), replanned=True,
                                     start_dwell_s=self._node.cfg.executor.start_dwell_s)
            self._node._stream_latest()
            self._node._generation += 1
            self._node._execution = dataclasses.replace(execution, path=path, replans_left=replans_left,
                                                        generation=self._node._generation, baseline_map=checked.occupancy)
            duration_s = self._node.machine.trajectory.duration_s  # type: ignore[union-attr]  # with its dwell
        log.info("%s: replanned (%d waypoints, %.2f s)", execution.trajectory_id, len(path), duration_s)
        self._node._path_pub.put(ExecutorPath(stamp=time.time(), trajectory_id=execution.trajectory_id,
                                        joint_names=self._node.robot.joint_names, path=path, duration_s=duration_s).to_wire())
        return True
