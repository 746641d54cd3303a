"""Executor service: `executor/execute` and `executor/stop` queries, setpoints at the configured rate."""

from __future__ import annotations

import logging
import threading
import time
import uuid

import numpy as np
import zenoh

from robonav.pipeline.joint_order import reorder_to_robot
from robonav.pipeline.messages import (ExecuteRequest, ExecuteResponse, ExecutorStatus, JointState, Setpoint,
                                       StopRequest, StopResponse)
from robonav.pipeline.robot import RobotModel
from robonav.pipeline.trajectory.execution import ExecutionStateMachine, Limits
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.pipeline.wire import ErrorCode, ProtocolError
from robonav.services.common import Node, guarded_queryable, guarded_subscriber, decode_request, reply_ok, run_service
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
        keys = Keys(cfg.cell)
        # Setpoints and status must not be dropped under load (Zenoh's default for puts): a
        # lost final setpoint leaves the arm short of the goal while the status says done.
        self._setpoint_pub = session.declare_publisher(keys.setpoint, congestion_control=zenoh.CongestionControl.BLOCK,
                                                       priority=zenoh.Priority.REAL_TIME, express=True)
        self._status_pub = session.declare_publisher(keys.status, congestion_control=zenoh.CongestionControl.BLOCK)
        self._sub = session.declare_subscriber(keys.joint_states, guarded_subscriber(self.on_joint_state, "executor"))
        self._queryables = [
            session.declare_queryable(keys.execute, guarded_queryable(self.handle_execute, "executor")),
            session.declare_queryable(keys.stop, guarded_queryable(self.handle_stop, "executor")),
        ]

    def on_joint_state(self, sample: zenoh.Sample) -> None:
        state = JointState.from_wire(sample.payload.to_bytes())
        with self._lock:
            self._joint_state = state

    def _measured_position(self) -> np.ndarray | None:
        with self._lock:
            state = self._joint_state
        if state is None:
            return None
        by_name = dict(zip(state.names, state.position.tolist()))
        if any(n not in by_name for n in self.robot.joint_names):
            return None
        return np.array([by_name[n] for n in self.robot.joint_names])

    def handle_execute(self, query: zenoh.Query) -> None:
        request = decode_request(query, ExecuteRequest)
        path = reorder_to_robot(request.path, request.joint_names, self.robot.joint_names, "path")
        for i, q in enumerate(path):
            violations = self.robot.check_joint_limits(q)
            if violations:
                raise ProtocolError(ErrorCode.OUT_OF_JOINT_LIMITS, f"path waypoint {i} is outside the joint limits: {'; '.join(violations)}",
                                    {"waypoint": i, "violations": violations})
        measured = self._measured_position()
        if measured is not None:
            offset = float(np.max(np.abs(path[0] - measured)))
            if offset > self.cfg.executor.start_tolerance_rad:
                raise ProtocolError(ErrorCode.INVALID_REQUEST,
                                    f"path starts {offset:.3f} rad from the measured joint state (tolerance {self.cfg.executor.start_tolerance_rad} rad)",
                                    {"offset_rad": offset})
        trajectory = time_parameterize(
            path, max_velocity=self.robot.velocity_limits, max_acceleration=self.robot.acceleration_limits,
            max_jerk=self.robot.jerk_limits,
            velocity_scaling=request.max_velocity_scaling_factor or self.cfg.executor.velocity_scaling,
            acceleration_scaling=request.max_acceleration_scaling_factor or self.cfg.executor.acceleration_scaling,
        )
        trajectory_id = request.trajectory_id or uuid.uuid4().hex[:12]
        with self._lock:
            if self.machine.busy:
                raise ProtocolError(ErrorCode.EXECUTOR_BUSY, f"trajectory '{self.machine.trajectory_id}' is {self.machine.state}",
                                    {"trajectory_id": self.machine.trajectory_id, "state": self.machine.state})
            self.machine.start(trajectory, trajectory_id, time.monotonic())
        log.info("executing %s: %d waypoints, %.2f s", trajectory_id, len(path), trajectory.duration_s)
        reply_ok(query, ExecuteResponse(trajectory_id=trajectory_id, duration_s=trajectory.duration_s, waypoint_count=len(path)))

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
                sample = self.machine.tick(now)
                # A state change is published at once, not at the next status period.
                due = now >= next_status or self.machine.state != published_state
                status = self.machine.status(now) if due else None
            if sample is not None:
                self._setpoint_pub.put(Setpoint(
                    stamp=time.time(), trajectory_id=sample.trajectory_id, names=names,
                    position=sample.position, velocity=sample.velocity, acceleration=sample.acceleration,
                ).to_wire())
            if status is not None:
                next_status = now + status_period_s
                published_state = status.state
                self._status_pub.put(ExecutorStatus(stamp=time.time(), **status.__dict__).to_wire())
            next_tick += period_s
            if next_tick < now - period_s:  # fell behind (e.g. the machine stalled): resync, do not burst
                next_tick = now
            delay = next_tick - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        with self._lock:
            self.machine.stop(time.monotonic(), emergency=True)

    def close(self) -> None:
        for q in self._queryables:
            q.undeclare()
        self._sub.undeclare()
        self._setpoint_pub.undeclare()
        self._status_pub.undeclare()


def main(argv: list[str] | None = None) -> int:
    return run_service("executor", argv, ExecutorNode)
