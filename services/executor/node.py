"""Executor service: `executor/execute` and `executor/stop` queries, setpoints at the configured rate.

The state machine lives here; the setpoints stream from a process of their own
(`setpoint_stream`), which plays each trajectory the machine starts, sampled on its time grid.
An execute while moving preempts (blends from the commanded state). The service's loop runs
the watchdog (stale joint states, tracking error) and publishes status. A second thread keeps
the rest of the executing path checked against the newest occupancy map (on every map and
at `path_check_rate_hz`): a new obstacle on it stops the arm smoothly, then either ends the
execution with PATH_BLOCKED or, when the request asked to replan, asks the planner for a new
path from the rest state to the same goal and continues under the same trajectory id.
"""

from __future__ import annotations

import collections
import dataclasses
import gc
import logging
import queue
import sys
import threading
import time
import uuid
import zlib
from dataclasses import dataclass

import numpy as np
import zenoh

from robonav.pipeline.wire.joint_order import positions_by_name, reorder_to_robot
from robonav.pipeline.wire.messages import (ErrorReply, ExecuteRequest, ExecuteResponse, ExecutorPath, ExecutorStatus,
                                       JointState, Occupancy, PlanRequest, PlanResponse, StopRequest,
                                       StopResponse)
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.trajectory.execution import ExecutionStateMachine, Limits
from robonav.pipeline.trajectory.path_guard import PathGuard, map_settled
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.pipeline.trajectory.trajectory import JointTrajectory
from robonav.pipeline.wire.codec import ProtocolError, unpack
from robonav.pipeline.wire.codes import ErrorCode, ExecutionState
from robonav.services.client import QueryFailed, query_one
from robonav.services.common import (Node, declare_latched_publisher, declare_latched_subscriber, guarded_queryable,
                                     guarded_subscriber, decode_request, reply_ok, run_service)
from robonav.services.config import RobonavConfig
from robonav.services.keys import Keys
from robonav.services.executor.setpoint_stream import SetpointStream, StreamStats

log = logging.getLogger("robonav.executor")

SWITCH_INTERVAL_S = 5e-4
"""Python's thread switch interval in the executor's process [s]."""
SUPERVISE_PERIOD_S = 0.005
"""The service loop (watchdog, state changes, status) runs every this [s]; setpoints do not wait on it."""
RECENT_MAPS = 64
"""Occupancy messages kept to find the one a path was planned on (about 2 s at 30 maps/s)."""
EVERY_VOXEL = b""
"""A path's baseline when the map it was planned on is no longer held: no voxel is known to the plan."""


@dataclass(frozen=True)
class _Execution:
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
    baseline_map: bytes | None
    """The occupancy message the path was planned on (undecoded), or None: only voxels new since
    count. Found by the plan's map stamp (`_baseline_map`) when the path starts, not when the
    monitor next runs, which may be after an obstacle that appeared meanwhile is already in a
    newer map."""


class ExecutorNode(Node):
    def __init__(self, cfg: RobonavConfig, session: zenoh.Session, *, keep_stream_times: int = 0) -> None:
        """Args: keep_stream_times: the setpoint stream keeps this many publish times for
        `stream_stats` (benchmarks)."""
        self.cfg = cfg
        self.robot = RobotModel.from_config(cfg.robot)
        limits = Limits(
            velocity=np.asarray(self.robot.velocity_limits, dtype=float),
            acceleration=np.asarray(self.robot.acceleration_limits, dtype=float),
            jerk=np.asarray(self.robot.jerk_limits, dtype=float),
        )
        self.machine = ExecutionStateMachine(limits)
        self._lock = threading.Lock()
        self._joint_state: JointState | None = None
        self._measured_q: np.ndarray | None = None
        """(n,) latest measured position in robot order [rad]."""
        self._measured_at_s = -np.inf
        """time.monotonic() when it arrived [s]."""
        keys = Keys(cfg.cell)
        self._stream = SetpointStream(cfg.zenoh, keys.setpoint, tuple(self.robot.joint_names), rate_hz=cfg.executor.rate_hz,
                                      busy_wait_s=cfg.executor.busy_wait_s,
                                      realtime_priority=cfg.executor.realtime_priority, limits=limits,
                                      keep_times=keep_stream_times, cpu_affinity=cfg.executor.cpu_affinity)
        self._streamed_revision = 0
        self._to_stream: queue.SimpleQueue[tuple[JointTrajectory | None, float, str] | None] = queue.SimpleQueue()
        self._feeder = threading.Thread(target=self._feed_stream, name="executor-stream-feeder", daemon=True)
        self._feeder.start()
        # Status must arrive: a lost one could leave a client waiting for a state it missed.
        self._status_pub = session.declare_publisher(keys.status, congestion_control=zenoh.CongestionControl.BLOCK)
        # Latched, so a viewer that starts late still sees the last path (plan replies go only to the asker).
        self._path_pub = declare_latched_publisher(session, keys.executor_path)
        self._sub = session.declare_subscriber(keys.joint_states, guarded_subscriber(self.on_joint_state, "executor"))
        self._session = session
        self._keys = keys
        self._execution: _Execution | None = None
        self._generation = 0
        self._blocked_after_frame_s: float | None = None
        self._blocked_stamp: float | None = None
        self._map_lock = threading.Lock()
        self._map_wire: bytes | None = None
        """The newest occupancy message the monitor has not taken yet, undecoded: it decodes only what it uses."""
        self._recent_map_wires: collections.deque[bytes] = collections.deque(maxlen=RECENT_MAPS)
        """The newest occupancy messages, oldest first: a new path's baseline is among them."""
        self._map_arrived = threading.Event()
        self._guard = PathGuard(self.robot, padding_m=cfg.robot.padding_m, inflation_m=cfg.perception.inflation_m,
                                edge_resolution_rad=cfg.planner.edge_resolution_rad)
        if cfg.executor.monitor_path:
            # Now, not on the first map: compiling would stall the setpoint loop.
            self._guard.warm_up(self.robot.home_position_rad)
        self._map_sub = (declare_latched_subscriber(session, keys.occupancy, self.on_occupancy)
                         if cfg.executor.monitor_path else None)
        self._monitor_stop = threading.Event()
        self._monitor = threading.Thread(target=self._monitor_loop, name="executor-path-monitor", daemon=True)
        if cfg.executor.monitor_path:
            self._monitor.start()
        # Hand-overs to the stream must happen within `command_lead_s`: a shorter switch interval
        # gets the feeder the GIL sooner, and frozen start-up objects (robot model, meshes, FCL)
        # keep the cyclic collector's full passes short.
        sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL_S))
        gc.freeze()
        self._queryables = [
            session.declare_queryable(keys.execute, guarded_queryable(self.handle_execute, "executor")),
            session.declare_queryable(keys.stop, guarded_queryable(self.handle_stop, "executor")),
        ]

    def on_joint_state(self, sample: zenoh.Sample) -> None:
        state = JointState.from_wire(sample.payload.to_bytes())
        measured = positions_by_name(state.names, state.position, self.robot.joint_names)
        with self._lock:
            self._joint_state = state
            if measured is not None and np.isfinite(measured).all():
                self._measured_q = measured
                self._measured_at_s = time.monotonic()

    def on_occupancy(self, sample: zenoh.Sample) -> None:
        with self._map_lock:
            self._map_wire = sample.payload.to_bytes()
            self._recent_map_wires.append(self._map_wire)
        self._map_arrived.set()

    def handle_execute(self, query: zenoh.Query) -> None:
        request = decode_request(query, ExecuteRequest)
        path = reorder_to_robot(request.path, request.joint_names, self.robot.joint_names, "path")
        for i, q in enumerate(path):
            violations = self.robot.check_joint_limits(q)
            if violations:
                raise ProtocolError(ErrorCode.OUT_OF_JOINT_LIMITS, f"path waypoint {i} is outside the joint limits: {'; '.join(violations)}",
                                    {"waypoint": i, "violations": violations})
        self._check_start(path[0])
        # The expensive part (corner blends) runs outside the lock, so streaming goes on meanwhile.
        trajectory = self._time_parameterize(path, request.max_velocity_scaling_factor,
                                             request.max_acceleration_scaling_factor)
        trajectory_id = request.trajectory_id or uuid.uuid4().hex[:12]
        baseline_map = self._baseline_map(request.occupancy_stamp)
        with self._lock:
            switch_s = self._switch_time()
            commanded = self.machine.commanded_state(switch_s)
            if commanded is not None:
                offset = float(np.max(np.abs(path[0] - commanded[0])))
                if offset > self.cfg.executor.preempt_tolerance_rad:
                    raise ProtocolError(ErrorCode.INVALID_REQUEST,
                                        f"path starts {offset:.3f} rad from the commanded state of the moving arm "
                                        f"(tolerance {self.cfg.executor.preempt_tolerance_rad} rad)", {"offset_rad": offset})
            # One ruckig blend from the commanded state (tens of microseconds) under the lock.
            preempted = self.machine.start(trajectory, trajectory_id, switch_s)
            self._stream_latest()
            duration_s = self.machine.status(switch_s).duration_s
            self._generation += 1
            self._execution = _Execution(
                trajectory_id, path, request.replan,
                request.replan_attempts or self.cfg.executor.replan_attempts,
                request.max_velocity_scaling_factor, request.max_acceleration_scaling_factor, self._generation,
                baseline_map)
            self._blocked_after_frame_s = self._blocked_stamp = None
        log.info("executing %s: %d waypoints, %.2f s%s", trajectory_id, len(path), duration_s,
                 " (preempted the running trajectory)" if preempted else "")
        self._path_pub.put(ExecutorPath(stamp=time.time(), trajectory_id=trajectory_id,
                                        joint_names=self.robot.joint_names, path=path, duration_s=duration_s).to_wire())
        reply_ok(query, ExecuteResponse(trajectory_id=trajectory_id, duration_s=duration_s, waypoint_count=len(path)))

    def _time_parameterize(self, path: np.ndarray, velocity_scaling: float | None,
                           acceleration_scaling: float | None) -> JointTrajectory:
        return time_parameterize(
            path, max_velocity=self.robot.velocity_limits, max_acceleration=self.robot.acceleration_limits,
            max_jerk=self.robot.jerk_limits,
            velocity_scaling=velocity_scaling or self.cfg.executor.velocity_scaling,
            acceleration_scaling=acceleration_scaling or self.cfg.executor.acceleration_scaling,
            max_path_deviation_rad=self.cfg.executor.max_path_deviation_rad,
        )

    # --- the path monitor (its own thread) --------------------------------------------------

    def _monitor_loop(self) -> None:
        period_s = 1.0 / self.cfg.executor.path_check_rate_hz
        occupancy: Occupancy | None = None
        baseline_generation = -1
        while not self._monitor_stop.is_set():
            self._map_arrived.wait(period_s)
            self._map_arrived.clear()
            with self._map_lock:
                wire, self._map_wire = self._map_wire, None
            if wire is not None:
                try:
                    occupancy = Occupancy.from_wire(wire)
                    if baseline_generation >= 0:
                        self._guard.update_map(occupancy.occupied_centers_m, occupancy.resolution_m)
                except ValueError as exc:  # a bad map must not end the monitor
                    log.warning("path monitor: ignoring a malformed occupancy map: %s", exc)
            with self._lock:
                execution, state = self._execution, self.machine.state
                commanded = self.machine.commanded_state(time.monotonic())
            if execution is None:
                continue
            try:
                if state is ExecutionState.REPLANNING:
                    self._replan(execution)
                elif state is ExecutionState.EXECUTING and commanded is not None:
                    if baseline_generation != execution.generation:
                        # Only voxels new since the map the path was planned on count. Without
                        # any map then, the first one is the baseline.
                        every_voxel = execution.baseline_map == EVERY_VOXEL
                        baseline = None if every_voxel else self._decoded(execution.baseline_map) or occupancy
                        if every_voxel or baseline is not None:
                            self._guard.start(None if baseline is None else baseline.occupied_centers_m,
                                              0.0 if baseline is None else baseline.resolution_m)
                            baseline_generation = execution.generation
                            if occupancy is not None and occupancy is not baseline:
                                self._guard.update_map(occupancy.occupied_centers_m, occupancy.resolution_m)
                    if baseline_generation == execution.generation and occupancy is not None:
                        self._check_rest_of_path(execution, commanded[0], occupancy)
            except Exception:  # noqa: BLE001 - the monitor must outlive any one bad check
                log.exception("path monitor: check failed")

    @staticmethod
    def _decoded(wire: bytes | None) -> Occupancy | None:
        try:
            return Occupancy.from_wire(wire) if wire else None
        except ValueError:
            return None  # already reported when it arrived

    def _baseline_map(self, planned_on_stamp: float | None) -> bytes | None:
        """The held occupancy message a path was planned on: the newest one stamped no later than
        `planned_on_stamp` (an older one only makes more voxels count as new).

        A plan's map is often not the newest: maps keep arriving while the planner works, and a
        box that came to rest meanwhile would be in the baseline, unwatched, though the plan never
        saw it. None (the client gave no stamp) takes the newest map, as MoveIt's monitor would
        take the current scene. When no held map is that old (the plan saw none, stamp 0, or it
        is no longer held), EVERY_VOXEL: all voxels count.
        """
        with self._map_lock:
            wires = list(self._recent_map_wires)
        if planned_on_stamp is None:
            return wires[-1] if wires else None
        if planned_on_stamp <= 0:
            return EVERY_VOXEL
        for wire in reversed(wires):
            try:
                fields = unpack(wire)
            except ProtocolError:
                continue  # already reported when it arrived
            stamp = fields.get("stamp") if isinstance(fields, dict) else None
            if isinstance(stamp, (int, float)) and stamp <= planned_on_stamp:
                return wire
        if wires:
            log.warning("the map a path was planned on (stamp %.3f) is older than the %d held: every voxel counts",
                        planned_on_stamp, len(wires))
        return EVERY_VOXEL

    def _check_rest_of_path(self, execution: _Execution, q_commanded: np.ndarray, occupancy: Occupancy) -> None:
        blocked_at = self._guard.blocked_state(execution.path, q_commanded)
        if blocked_at is None:
            return
        with self._lock:
            if self._execution is not execution or self.machine.state is not ExecutionState.EXECUTING:
                return  # preempted or stopped meanwhile
            self._blocked_stamp = time.time()
            delay_s = self._blocked_stamp - occupancy.stamp
            self._blocked_after_frame_s = delay_s
            if execution.replan and execution.replans_left > 0:
                self.machine.stop(self._switch_time(), scaling=self.cfg.executor.acceleration_scaling, replan=True)
                outcome = "stopping to replan"
            else:
                self.machine.fault(self._switch_time(), ErrorCode.PATH_BLOCKED,
                                   f"a new obstacle blocks the rest of '{execution.trajectory_id}' "
                                   f"(map {occupancy.seq}){'; no replans left' if execution.replan else ''}")
                outcome = "stopping (replan not requested)" if not execution.replan else "stopping (no replans left)"
            self._stream_latest()
        log.warning("%s: the rest of the path is blocked in map %d, %.0f ms after its newest frame: %s",
                    execution.trajectory_id, occupancy.seq, delay_s * 1e3, outcome)

    def _replan(self, execution: _Execution) -> None:
        """At rest after a block: plan from here to the goal and stream the new path, or give up."""
        with self._lock:
            last = self.machine.last_setpoint
        if last is None:
            return
        self._wait_settled_map(time.time())
        errors: list[str] = []
        left = execution.replans_left
        while left > 0:
            left -= 1
            attempt = execution.replans_left - left
            request = PlanRequest(goal_positions=execution.path[-1], joint_names=self.robot.joint_names,
                                  start_positions=last.position,
                                  seed=zlib.crc32(execution.trajectory_id.encode()) + self.machine.replans * 10 + attempt,
                                  request_id=f"{execution.trajectory_id}-replan-{self.machine.replans + 1}")
            try:
                reply, _ = query_one(self._session, self._keys.plan, request, PlanResponse,
                                     self.cfg.executor.replan_timeout_s)
            except QueryFailed as exc:
                reply = ErrorReply(code="INTERNAL_ERROR", message=str(exc))
            if isinstance(reply, PlanResponse):
                self._start_replanned(execution, reply, left)
                return
            errors.append(f"{reply.code}: {reply.message}")
            log.warning("%s: replan %d failed: %s", execution.trajectory_id, attempt, errors[-1])
            if left > 0 and self._monitor_stop.wait(self.cfg.executor.replan_delay_s):
                return
            with self._lock:
                if self._execution is not execution or self.machine.state is not ExecutionState.REPLANNING:
                    return
        with self._lock:
            if self._execution is execution and self.machine.state is ExecutionState.REPLANNING:
                self.machine.fault(time.monotonic(), ErrorCode.PATH_BLOCKED,
                                   f"a new obstacle blocks '{execution.trajectory_id}' and replanning failed: "
                                   + "; ".join(errors[-3:]))

    def _wait_settled_map(self, rested_at: float) -> None:
        """Hold the replan until the two newest held maps, both stamped after `rested_at`, agree
        (`map_settled`), or `executor.replan_settle_s` passes."""
        deadline = time.monotonic() + self.cfg.executor.replan_settle_s
        judged: bytes | None = None  # the newest map already compared with the one before
        while time.monotonic() < deadline:
            with self._map_lock:
                wires = list(self._recent_map_wires)[-2:]
            if len(wires) == 2 and wires[1] is not judged:
                judged = wires[1]
                before, now = self._decoded(wires[0]), self._decoded(wires[1])
                if before is not None and now is not None and before.stamp > rested_at and \
                        map_settled(before.occupied_centers_m, now.occupied_centers_m, now.resolution_m):
                    return
            if self._monitor_stop.wait(0.02):
                return

    def _start_replanned(self, execution: _Execution, plan: PlanResponse, replans_left: int) -> None:
        path = reorder_to_robot(plan.path, plan.joint_names, self.robot.joint_names, "path")
        trajectory = self._time_parameterize(path, execution.velocity_scaling, execution.acceleration_scaling)
        baseline_map = self._baseline_map(plan.occupancy_stamp)
        with self._lock:
            if self._execution is not execution or self.machine.state is not ExecutionState.REPLANNING:
                return  # a new request or a stop came in while planning
            self.machine.start(trajectory, execution.trajectory_id, self._switch_time(), replanned=True)
            self._stream_latest()
            self._generation += 1
            self._execution = dataclasses.replace(execution, path=path, replans_left=replans_left,
                                                  generation=self._generation, baseline_map=baseline_map)
            duration_s = trajectory.duration_s
        log.info("%s: replanned (%d waypoints, %.2f s)", execution.trajectory_id, len(path), duration_s)
        self._path_pub.put(ExecutorPath(stamp=time.time(), trajectory_id=execution.trajectory_id,
                                        joint_names=self.robot.joint_names, path=path, duration_s=duration_s).to_wire())

    def _check_start(self, start: np.ndarray) -> None:
        """An idle arm must be where the path starts, and the watchdog must have a fresh joint state."""
        with self._lock:
            measured, age_s, busy = self._measured_q, time.monotonic() - self._measured_at_s, self.machine.busy
        if measured is None or age_s > self.cfg.executor.joint_state_timeout_s:
            detail = "none received" if measured is None else f"the last is {age_s:.3f} s old"
            raise ProtocolError(ErrorCode.NO_JOINT_STATE,
                                f"no fresh joint state on robot/joint_states ({detail}; timeout "
                                f"{self.cfg.executor.joint_state_timeout_s} s): refusing to move blind")
        if not busy:
            offset = float(np.max(np.abs(start - measured)))
            if offset > self.cfg.executor.start_tolerance_rad:
                raise ProtocolError(ErrorCode.INVALID_REQUEST,
                                    f"path starts {offset:.3f} rad from the measured joint state (tolerance {self.cfg.executor.start_tolerance_rad} rad)",
                                    {"offset_rad": offset})

    def handle_stop(self, query: zenoh.Query) -> None:
        request = decode_request(query, StopRequest)
        with self._lock:
            self.machine.stop(self._switch_time(), emergency=request.emergency,
                              scaling=self.cfg.executor.acceleration_scaling)
            self._stream_latest()
            state = self.machine.state
        reply_ok(query, StopResponse(state=state))

    # --- handing trajectories to the setpoint stream ----------------------------------------

    def _switch_time(self) -> float:
        """When a trajectory started now takes over: the stream's first tick after the lead that
        sampling it and handing it over needs."""
        return self._stream.next_tick(time.monotonic() + self.cfg.executor.command_lead_s)

    def _stream_latest(self) -> None:
        """Under `_lock`, after any call that may have replaced the machine's trajectory."""
        if self.machine.revision != self._streamed_revision:
            self._streamed_revision = self.machine.revision
            self._to_stream.put((self.machine.trajectory, self.machine.started_at_s, self.machine.trajectory_id))

    def _feed_stream(self) -> None:
        """Sample each new trajectory on the stream's grid and send it, in order.

        None of them is skipped, not even the older of two quick ones: the newer was computed from the older's
        commanded state, so the stream must play the older until the newer takes over."""
        while (item := self._to_stream.get()) is not None:
            trajectory, start_s, trajectory_id = item
            if trajectory is not None:
                self._stream.play(trajectory, trajectory_id, start_s)

    def stream_stats(self) -> StreamStats:
        """The setpoint stream's counters (and publish times when kept)."""
        return self._stream.stats()

    def spin(self, stop: threading.Event) -> None:
        """Watchdog, state changes and status every SUPERVISE_PERIOD_S; setpoints stream elsewhere."""
        status_period_s = 1.0 / self.cfg.executor.status_rate_hz
        next_status = time.monotonic()
        published_state = ""
        while not stop.wait(SUPERVISE_PERIOD_S):
            now = time.monotonic()
            with self._lock:
                tripped = self.machine.check_watchdog(self._switch_time(), self._measured_q, now - self._measured_at_s,
                                                      self.cfg.executor)
                self._stream_latest()
                self.machine.tick(now)
                # A state change is published at once, not at the next status period.
                due = now >= next_status or self.machine.state != published_state
                status = self.machine.status(now) if due else None
            if tripped is not None:
                log.error("watchdog: %s", self.machine.error_message)
            if status is not None:
                next_status = now + status_period_s
                published_state = status.state
                self._status_pub.put(ExecutorStatus(
                    stamp=time.time(), state=status.state, trajectory_id=status.trajectory_id, progress=status.progress,
                    time_from_start_s=status.time_from_start_s, duration_s=status.duration_s,
                    last_result=status.last_result, error_code=status.error_code.value if status.error_code else "",
                    error_message=status.error_message, replans=status.replans,
                    blocked_after_frame_s=self._blocked_after_frame_s, blocked_stamp=self._blocked_stamp).to_wire())
            if not self._stream.alive:
                log.error("the setpoint stream process died: stopping the executor")
                return

    def close(self) -> None:
        self._monitor_stop.set()
        self._map_arrived.set()
        if self._monitor.is_alive():
            self._monitor.join(timeout=self.cfg.executor.replan_timeout_s + 1.0)
        for q in self._queryables:
            q.undeclare()
        if self._map_sub is not None:
            self._map_sub.undeclare()
        self._sub.undeclare()
        self._to_stream.put(None)
        self._feeder.join(timeout=5.0)
        self._stream.close()  # it brakes a moving arm to rest first
        self._status_pub.undeclare()
        self._path_pub.undeclare()


def main(argv: list[str] | None = None) -> int:
    return run_service("executor", argv, ExecutorNode)
