"""Executor service: `executor/execute` and `executor/stop` queries, setpoints at the configured rate.

An execute while moving preempts (blends from the commanded state); the streaming loop also
runs the watchdog (stale joint states, tracking error) on every cycle.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid

import numpy as np
import zenoh

from robonav.pipeline.joint_order import reorder_to_robot
from robonav.pipeline.messages import (ExecuteRequest, ExecuteResponse, ExecutorPath, ExecutorStatus, JointState,
                                       Setpoint, StopRequest, StopResponse)
from robonav.pipeline.robot import RobotModel
from robonav.pipeline.trajectory.execution import ExecutionStateMachine, Limits, WatchdogConfig
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.pipeline.wire import ErrorCode, ProtocolError
from robonav.services.common import (Node, declare_latched_publisher, guarded_queryable, guarded_subscriber,
                                     decode_request, reply_ok, run_service)
from robonav.services.config import RobonavConfig
from robonav.services.keys import Keys

log = logging.getLogger("robonav.executor")


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
        # Setpoints and status must not be dropped under load (Zenoh's default for puts): a
        # lost final setpoint leaves the arm short of the goal while the status says done.
        self._setpoint_pub = session.declare_publisher(keys.setpoint, congestion_control=zenoh.CongestionControl.BLOCK,
                                                       priority=zenoh.Priority.REAL_TIME, express=True)
        self._status_pub = session.declare_publisher(keys.status, congestion_control=zenoh.CongestionControl.BLOCK)
        # Latched, so a viewer that starts late still sees the last path (plan replies go only to the asker).
        self._path_pub = declare_latched_publisher(session, keys.executor_path)
        self._sub = session.declare_subscriber(keys.joint_states, guarded_subscriber(self.on_joint_state, "executor"))
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
        trajectory = time_parameterize(
            path, max_velocity=self.robot.velocity_limits, max_acceleration=self.robot.acceleration_limits,
            max_jerk=self.robot.jerk_limits,
            velocity_scaling=request.max_velocity_scaling_factor or self.cfg.executor.velocity_scaling,
            acceleration_scaling=request.max_acceleration_scaling_factor or self.cfg.executor.acceleration_scaling,
            max_path_deviation_rad=self.cfg.executor.max_path_deviation_rad,
        )
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
        log.info("executing %s: %d waypoints, %.2f s%s", trajectory_id, len(path), duration_s,
                 " (preempted the running trajectory)" if preempted else "")
        self._path_pub.put(ExecutorPath(stamp=time.time(), trajectory_id=trajectory_id,
                                        joint_names=self.robot.joint_names, path=path, duration_s=duration_s).to_wire())
        reply_ok(query, ExecuteResponse(trajectory_id=trajectory_id, duration_s=duration_s, waypoint_count=len(path)))

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
                # A state change is published at once, not at the next status period.
                due = now >= next_status or self.machine.state != published_state
                status = self.machine.status(now) if due else None
            if sample is not None:
                self._setpoint_pub.put(Setpoint(
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
                self._status_pub.put(ExecutorStatus(stamp=time.time(), **status.__dict__).to_wire())
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
        for q in self._queryables:
            q.undeclare()
        self._sub.undeclare()
        self._setpoint_pub.undeclare()
        self._status_pub.undeclare()
        self._path_pub.undeclare()


def main(argv: list[str] | None = None) -> int:
    return run_service("executor", argv, ExecutorNode)
