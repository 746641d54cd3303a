"""Executor service: `executor/execute` and `executor/stop` queries, setpoints at the configured rate.

An execute while moving preempts (blends from the commanded state); the streaming loop also
runs the watchdog (stale joint states, tracking error) on every cycle. A second thread keeps
the rest of the executing path checked against the newest occupancy map (on every map and
at `path_check_rate_hz`): a new obstacle on it stops the arm smoothly, then either ends the
execution with PATH_BLOCKED or, when the request asked to replan, asks the planner for a new
path from the rest state to the same goal and continues under the same trajectory id.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
import threading
import time
import uuid
import zlib
from dataclasses import dataclass

import numpy as np
import zenoh

from robonav.pipeline.joint_order import reorder_to_robot
from robonav.pipeline.messages import (ErrorReply, ExecuteRequest, ExecuteResponse, ExecutorPath, ExecutorStatus,
                                       JointState, Occupancy, PlanRequest, PlanResponse, Setpoint, StopRequest,
                                       StopResponse)
from robonav.pipeline.robot import RobotModel
from robonav.pipeline.trajectory.execution import PATH_BLOCKED, ExecutionStateMachine, Limits, WatchdogConfig
from robonav.pipeline.trajectory.path_guard import PathGuard
from robonav.pipeline.trajectory.timing import JointTrajectory, time_parameterize
from robonav.pipeline.wire import ErrorCode, ProtocolError
from robonav.services.client import QueryFailed, query_one
from robonav.services.common import (Node, declare_latched_publisher, declare_latched_subscriber, guarded_queryable,
                                     guarded_subscriber, decode_request, reply_ok, run_service)
from robonav.services.config import RobonavConfig
from robonav.services.keys import Keys

log = logging.getLogger("robonav.executor")

REALTIME_SWITCH_INTERVAL_S = 2e-4
"""Python's thread switch interval in a real-time executor process [s]."""


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


class ExecutorNode(Node):
    def __init__(self, cfg: RobonavConfig, session: zenoh.Session) -> None:
        self.cfg = cfg
        self.robot = RobotModel.from_config(cfg.robot)
        self.machine = ExecutionStateMachine(Limits(
            velocity=np.asarray(self.robot.velocity_limits, dtype=float),
            acceleration=np.asarray(self.robot.acceleration_limits, dtype=float),
            jerk=np.asarray(self.robot.jerk_limits, dtype=float),
        ))
        self._lock = threading.Lock()
        self._joint_state: JointState | None = None
        self._measured_q: np.ndarray | None = None
        """(n,) latest measured position in robot order [rad]."""
        self._measured_at_s = -np.inf
        """time.monotonic() when it arrived [s]."""
        self._watchdog = WatchdogConfig(cfg.executor.joint_state_timeout_s, cfg.executor.max_tracking_error_rad,
                                        cfg.executor.tracking_latency_s)
        self.publish_times_s: list[float] | None = None
        """When a list, spin appends time.monotonic() after each setpoint put (for `robonav bench executor`)."""
        keys = Keys(cfg.cell)
        # A setpoint in motion is superseded a period later: under congestion it is dropped
        # rather than blocking the 1 kHz loop on a slow subscriber (a blocking put stalled the
        # loop for up to 5 ms). The last setpoint of a motion (at rest) and status must arrive:
        # a lost one leaves the arm short of the goal while the status says done.
        self._setpoint_pub = session.declare_publisher(keys.setpoint, congestion_control=zenoh.CongestionControl.DROP,
                                                       priority=zenoh.Priority.REAL_TIME, express=True)
        self._final_setpoint_pub = session.declare_publisher(keys.setpoint, congestion_control=zenoh.CongestionControl.BLOCK,
                                                             priority=zenoh.Priority.REAL_TIME, express=True)
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
        """The newest occupancy message, undecoded: the monitor decodes only what it uses."""
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
        self._queryables = [
            session.declare_queryable(keys.execute, guarded_queryable(self.handle_execute, "executor")),
            session.declare_queryable(keys.stop, guarded_queryable(self.handle_stop, "executor")),
        ]

    def on_joint_state(self, sample: zenoh.Sample) -> None:
        state = JointState.from_wire(sample.payload.to_bytes())
        by_name = dict(zip(state.names, state.position.tolist()))
        measured = (np.array([by_name[n] for n in self.robot.joint_names])
                    if all(n in by_name for n in self.robot.joint_names) else None)
        with self._lock:
            self._joint_state = state
            if measured is not None and np.isfinite(measured).all():
                self._measured_q = measured
                self._measured_at_s = time.monotonic()

    def on_occupancy(self, sample: zenoh.Sample) -> None:
        with self._map_lock:
            self._map_wire = sample.payload.to_bytes()
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
        with self._lock:
            commanded = self.machine.commanded_state(time.monotonic())
            if commanded is not None:
                offset = float(np.max(np.abs(path[0] - commanded[0])))
                if offset > self.cfg.executor.preempt_tolerance_rad:
                    raise ProtocolError(ErrorCode.INVALID_REQUEST,
                                        f"path starts {offset:.3f} rad from the commanded state of the moving arm "
                                        f"(tolerance {self.cfg.executor.preempt_tolerance_rad} rad)", {"offset_rad": offset})
            # One ruckig blend from the commanded state (tens of microseconds) under the lock.
            preempted = self.machine.start(trajectory, trajectory_id, time.monotonic())
            duration_s = self.machine.status(time.monotonic()).duration_s
            self._generation += 1
            self._execution = _Execution(
                trajectory_id, path, request.replan,
                request.replan_attempts or self.cfg.executor.replan_attempts,
                request.max_velocity_scaling_factor, request.max_acceleration_scaling_factor, self._generation)
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
                if state == "replanning":
                    self._replan(execution)
                elif state == "executing" and commanded is not None:
                    if baseline_generation != execution.generation:
                        # The path was planned on (about) the newest map: only voxels new since
                        # count. Without a map yet, the first one is the baseline.
                        if occupancy is not None:
                            self._guard.start(occupancy.occupied_centers_m, occupancy.resolution_m)
                            baseline_generation = execution.generation
                    else:
                        self._check_rest_of_path(execution, commanded[0], occupancy)
            except Exception:  # noqa: BLE001 - the monitor must outlive any one bad check
                log.exception("path monitor: check failed")

    def _check_rest_of_path(self, execution: _Execution, q_commanded: np.ndarray, occupancy: Occupancy) -> None:
        blocked_at = self._guard.blocked_state(execution.path, q_commanded)
        if blocked_at is None:
            return
        with self._lock:
            if self._execution is not execution or self.machine.state != "executing":
                return  # preempted or stopped meanwhile
            self._blocked_stamp = time.time()
            delay_s = self._blocked_stamp - occupancy.stamp
            self._blocked_after_frame_s = delay_s
            if execution.replan and execution.replans_left > 0:
                self.machine.stop(time.monotonic(), scaling=self.cfg.executor.acceleration_scaling, replan=True)
                outcome = "stopping to replan"
            else:
                self.machine.fault(time.monotonic(), PATH_BLOCKED,
                                   f"a new obstacle blocks the rest of '{execution.trajectory_id}' "
                                   f"(map {occupancy.seq}){'; no replans left' if execution.replan else ''}")
                outcome = "stopping (replan not requested)" if not execution.replan else "stopping (no replans left)"
        log.warning("%s: the rest of the path is blocked in map %d, %.0f ms after its newest frame: %s",
                    execution.trajectory_id, occupancy.seq, delay_s * 1e3, outcome)

    def _replan(self, execution: _Execution) -> None:
        """At rest after a block: plan from here to the goal and stream the new path, or give up."""
        with self._lock:
            last = self.machine.last_setpoint
        if last is None:
            return
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
                if self._execution is not execution or self.machine.state != "replanning":
                    return
        with self._lock:
            if self._execution is execution and self.machine.state == "replanning":
                self.machine.fault(time.monotonic(), PATH_BLOCKED,
                                   f"a new obstacle blocks '{execution.trajectory_id}' and replanning failed: "
                                   + "; ".join(errors[-3:]))

    def _start_replanned(self, execution: _Execution, plan: PlanResponse, replans_left: int) -> None:
        path = reorder_to_robot(plan.path, plan.joint_names, self.robot.joint_names, "path")
        trajectory = self._time_parameterize(path, execution.velocity_scaling, execution.acceleration_scaling)
        with self._lock:
            if self._execution is not execution or self.machine.state != "replanning":
                return  # a new request or a stop came in while planning
            self.machine.start(trajectory, execution.trajectory_id, time.monotonic(), replanned=True)
            self._generation += 1
            self._execution = dataclasses.replace(execution, path=path, replans_left=replans_left,
                                                  generation=self._generation)
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
            self.machine.stop(time.monotonic(), emergency=request.emergency,
                              scaling=self.cfg.executor.acceleration_scaling)
            state = self.machine.state
        reply_ok(query, StopResponse(state=state))

    def spin(self, stop: threading.Event) -> None:
        """Stream setpoints on an absolute schedule so periods do not drift."""
        _real_time_priority(self.cfg.executor.realtime_priority)
        period_s = 1.0 / self.cfg.executor.rate_hz
        status_period_s = 1.0 / self.cfg.executor.status_rate_hz
        names = self.robot.joint_names
        next_tick = time.monotonic()
        next_status = next_tick
        published_state = ""
        while not stop.is_set():
            now = time.monotonic()
            with self._lock:
                tripped = self.machine.check_watchdog(now, self._measured_q, now - self._measured_at_s, self._watchdog)
                sample = self.machine.tick(now)
                final = not self.machine.busy  # this sample ended a motion: it is the rest state
                # A state change is published at once, not at the next status period.
                due = now >= next_status or self.machine.state != published_state
                status = self.machine.status(now) if due else None
            if sample is not None:
                (self._final_setpoint_pub if final else self._setpoint_pub).put(Setpoint(
                    stamp=time.time(), trajectory_id=sample.trajectory_id, names=names,
                    position=sample.position, velocity=sample.velocity, acceleration=sample.acceleration,
                ).to_wire())
                if self.publish_times_s is not None:
                    self.publish_times_s.append(time.monotonic())
            if tripped is not None:
                log.error("watchdog: %s", self.machine.error_message)
            if status is not None:
                next_status = now + status_period_s
                published_state = status.state
                self._status_pub.put(ExecutorStatus(stamp=time.time(), blocked_after_frame_s=self._blocked_after_frame_s,
                                                    blocked_stamp=self._blocked_stamp,
                                                    **status.__dict__).to_wire())
            next_tick += period_s
            if next_tick < now - period_s:  # fell behind (e.g. the machine stalled): resync, do not burst
                next_tick = now
            # Sleep wakes up late by 0.05-1 ms; the last `busy_wait_s` before a tick is spent
            # polling the clock instead (yielding the GIL), trading CPU for period accuracy.
            delay = next_tick - time.monotonic() - self.cfg.executor.busy_wait_s
            if delay > 0:
                time.sleep(delay)
            while time.monotonic() < next_tick:
                time.sleep(0)
        with self._lock:
            self.machine.stop(time.monotonic(), emergency=True)

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
        self._setpoint_pub.undeclare()
        self._final_setpoint_pub.undeclare()
        self._status_pub.undeclare()
        self._path_pub.undeclare()


def _real_time_priority(priority: int) -> None:
    """Run the calling thread (the streaming loop) under SCHED_FIFO at `priority` (0: leave it).

    What robot control loops do (ros2_control, Franka's libfranka): the scheduler then never
    makes the loop wait for ordinary threads and processes, which on a busy 2-core machine
    otherwise costs it whole milliseconds. It needs CAP_SYS_NICE (root, or
    `docker run --cap-add SYS_NICE`); without it the loop runs at normal priority.
    """
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))  # 0: this thread on Linux
        # The loop also needs the GIL back quickly: other threads (queries, the path monitor)
        # otherwise keep it for up to Python's default 5 ms switch interval.
        sys.setswitchinterval(min(sys.getswitchinterval(), REALTIME_SWITCH_INTERVAL_S))
        log.info("setpoint loop runs under SCHED_FIFO priority %d", priority)
    except (PermissionError, OSError) as exc:
        log.warning("setpoint loop stays at normal priority: SCHED_FIFO refused (%s); "
                    "grant CAP_SYS_NICE or set executor.realtime_priority: 0", exc)


def main(argv: list[str] | None = None) -> int:
    return run_service("executor", argv, ExecutorNode)
