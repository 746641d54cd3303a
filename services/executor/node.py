"""Executor service: `executor/execute` and `executor/stop` queries, setpoints at the configured rate.

The state machine lives here; the setpoints stream from a process of their own
(`setpoint_stream`), which plays each trajectory the machine starts, sampled on its time grid.
An execute while moving preempts (blends from the commanded state). The service's loop runs
the watchdog (stale joint states, tracking error) and publishes status. A second thread keeps
the rest of the executing path checked against the newest occupancy map (on every map and
at `path_check_rate_hz`, `path_monitor.py`): a new obstacle on it stops the arm smoothly, then either ends the
execution with PATH_BLOCKED or, when the request asked to replan, asks the planner for a new
path from the rest state to the same goal and continues under the same trajectory id.
"""

from __future__ import annotations

import gc
import logging
import queue
import sys
import threading
import time
import uuid

import numpy as np
import zenoh

from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.trajectory.execution import ExecutionStateMachine, Limits
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.pipeline.trajectory.trajectory import JointTrajectory
from robonav.pipeline.types import StateValidFn
from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.joint_order import missing_joints, positions_by_name, reorder_to_robot
from robonav.pipeline.wire.messages import (
    ExecuteRequest,
    ExecuteResponse,
    ExecutorPath,
    ExecutorStatus,
    JointState,
    StopRequest,
    StopResponse,
)
from robonav.services.common import (
    Node,
    declare_latched_publisher,
    declare_latched_subscriber,
    decode_request,
    guarded_queryable,
    guarded_subscriber,
    reply_ok,
    run_service,
)
from robonav.services.config import RobonavConfig
from robonav.services.executor.execute_check import ExecuteCheck
from robonav.services.executor.maps import MapFeed
from robonav.services.executor.path_monitor import Execution, PathMonitor
from robonav.services.executor.setpoint_stream import SetpointStream, StreamStats
from robonav.services.keys import Keys
from robonav.services.limits import check_execute_request
from robonav.services.workers import RequestWorkers

log = logging.getLogger("robonav.executor")

SWITCH_INTERVAL_S = 5e-4
"""Python's thread switch interval in the executor's process [s]."""
SUPERVISE_PERIOD_S = 0.005
CLOSE_WAIT_S = 1.5
"""At close, the longest wait for the path monitor, the request workers and the stream feeder each [s]."""
CLOSE_BRAKE_S = 4.0
"""At close, the longest wait for the stream to brake the arm to rest and end [s]."""
CLOSE_BUDGET_S = 3 * CLOSE_WAIT_S + CLOSE_BRAKE_S
"""The service loop (watchdog, state changes, status) runs every this [s]; setpoints do not wait on it."""


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
        self._stream_delay_ticks = 0
        """The stream's `delay_ticks` as the machine's clock has taken it up."""
        self._to_stream: queue.SimpleQueue[tuple[JointTrajectory | None, float, str, int] | None] = queue.SimpleQueue()
        self._feeder = threading.Thread(target=self._feed_stream, name="executor-stream-feeder", daemon=True)
        self._feeder.start()
        # Status must arrive: a lost one could leave a client waiting for a state it missed.
        self._status_pub = session.declare_publisher(keys.status, congestion_control=zenoh.CongestionControl.BLOCK)
        # Latched, so a viewer that starts late still sees the last path (plan replies go only to the asker).
        self._path_pub = declare_latched_publisher(session, keys.executor_path)
        self._sub = session.declare_subscriber(keys.joint_states, guarded_subscriber(self.on_joint_state, "executor"))
        self._session = session
        self._keys = keys
        self._execution: Execution | None = None
        self._generation = 0
        self._blocked_after_frame_s: float | None = None
        self._blocked_stamp: float | None = None
        # Before the service is alive: the first execute costs what later ones do (the path
        # monitor warms its guard's compiled kernels too).
        home = self.robot.home_position_rad
        self._time_parameterize(np.vstack([home, home + 0.05, home + np.linspace(0.0, 0.1, len(home))]), None, None)
        self.maps = MapFeed()
        self._map_sub = declare_latched_subscriber(session, keys.occupancy, guarded_subscriber(self.maps.on_occupancy,
                                                                                               "executor"))
        self.check = ExecuteCheck(cfg, self.robot, session, self.maps)
        self.monitor = PathMonitor(self) if cfg.executor.monitor_path else None
        if self.monitor is not None:
            self.monitor.start()
        # Hand-overs to the stream must happen within `command_lead_s`: a shorter switch interval
        # gets the feeder the GIL sooner, and frozen start-up objects (robot model, meshes, FCL)
        # keep the cyclic collector's full passes short.
        sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL_S))
        # Collect first: what is frozen is never collected, and garbage frozen now (reference
        # cycles holding ruckig or OMPL objects) would outlive the interpreter.
        gc.collect()
        gc.freeze()
        # An execute (time parameterisation: corner blends) runs on a worker thread, one at a time in
        # arrival order; a stop is short and is answered on Zenoh's callback thread, never behind one.
        self._workers = RequestWorkers("executor", lambda query, _worker: self.handle_execute(query), workers=1,
                                       queue_size=cfg.limits.max_queued_requests)
        self._queryables = [
            session.declare_queryable(keys.execute, self._workers.callback),
            session.declare_queryable(keys.stop, guarded_queryable(self.handle_stop, "executor")),
        ]

    def on_joint_state(self, sample: zenoh.Sample) -> None:
        """The latest joint state to arrive is the measurement, whatever its stamp (staleness is
        judged by arrival, so a stamp from the future or long ago holds nothing back). One
        lacking a planning joint is no measurement: it is counted and the watchdog goes on
        waiting for a complete one."""
        state = JointState.from_wire(sample.payload.to_bytes())
        measured = positions_by_name(state.names, state.position, self.robot.joint_names)
        if measured is None:
            raise ValueError(f"joint state lacks joints {missing_joints(state.names, self.robot.joint_names)}")
        with self._lock:
            self._joint_state = state
            self._measured_q = measured
            self._measured_at_s = time.monotonic()

    def handle_execute(self, query: zenoh.Query) -> None:
        request = decode_request(query, ExecuteRequest)
        check_execute_request(request, self.cfg.limits)
        path = reorder_to_robot(request.path, request.joint_names, self.robot.joint_names, "path")
        for i, q in enumerate(path):
            violations = self.robot.check_joint_limits(q)
            if violations:
                raise ProtocolError(ErrorCode.OUT_OF_JOINT_LIMITS, f"path waypoint {i} is outside the joint limits: {'; '.join(violations)}",
                                    {"waypoint": i, "violations": violations})
        measured, busy = self._check_start(path[0])
        if not busy:
            # An idle arm starts where it is, not where row 0 says (within start_tolerance_rad of
            # it): a driver refuses a first setpoint away from its current state.
            path = np.vstack([measured[None], path[1:]])
        # The expensive part (timing, corner blends, the check) runs outside the lock, so
        # streaming goes on meanwhile. `occupancy_stamp` is no longer needed: the motion is
        # checked against the newest map, and the monitor watches every voxel not in that one.
        checked = self.check.check(path, lambda valid: self._time_parameterize(
            path, request.max_velocity_scaling_factor, request.max_acceleration_scaling_factor, valid),
            request.scene_revision)
        trajectory = checked.trajectory
        trajectory_id = request.trajectory_id or uuid.uuid4().hex[:12]
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
            preempted = self.machine.start(trajectory, trajectory_id, switch_s,
                                           start_dwell_s=self.cfg.executor.start_dwell_s)
            self._stream_latest()
            duration_s = self.machine.status(switch_s).duration_s
            self._generation += 1
            self._execution = Execution(
                trajectory_id, path, request.replan,
                request.replan_attempts or self.cfg.executor.replan_attempts,
                request.max_velocity_scaling_factor, request.max_acceleration_scaling_factor, self._generation,
                checked.occupancy)
            self._blocked_after_frame_s = self._blocked_stamp = None
        log.info("executing %s: %d waypoints, %.2f s, %d states checked in %.1f ms%s", trajectory_id, len(path),
                 duration_s, checked.samples, checked.check_ms, " (preempted the running trajectory)" if preempted else "")
        self._path_pub.put(ExecutorPath(stamp=time.time(), trajectory_id=trajectory_id,
                                        joint_names=self.robot.joint_names, path=path, duration_s=duration_s).to_wire())
        reply_ok(query, ExecuteResponse(trajectory_id=trajectory_id, duration_s=duration_s, waypoint_count=len(path),
                                        check_ms=round(checked.check_ms, 3), checked_samples=checked.samples))

    def _time_parameterize(self, path: np.ndarray, velocity_scaling: float | None, acceleration_scaling: float | None,
                           state_valid: StateValidFn | None = None) -> JointTrajectory:
        return time_parameterize(
            path, max_velocity=self.robot.velocity_limits, max_acceleration=self.robot.acceleration_limits,
            max_jerk=self.robot.jerk_limits,
            velocity_scaling=velocity_scaling or self.cfg.executor.velocity_scaling,
            acceleration_scaling=acceleration_scaling or self.cfg.executor.acceleration_scaling,
            max_path_deviation_rad=self.cfg.executor.max_path_deviation_rad, state_valid=state_valid,
            check_step_rad=self.cfg.planner.edge_resolution_rad,
        )

    def _check_start(self, start: np.ndarray) -> tuple[np.ndarray, bool]:
        """An idle arm must be where the path starts, and the watchdog must have a fresh joint state.
        Returns the measured position (n,) and whether a trajectory is streaming."""
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
        return measured.copy(), busy

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
        """Under `_lock`: when a trajectory started now takes over, the stream's first tick after
        the lead that sampling it and handing it over needs.

        It first takes up a delay the stream added (a motion from rest that reached it late
        plays from its first row, later): the machine's clock moves with it, so every blend,
        stop and status after this one starts from what the stream really plays."""
        delay_ticks = self._stream.delay_ticks
        if delay_ticks != self._stream_delay_ticks:
            delay_s = (delay_ticks - self._stream_delay_ticks) * self._stream.period_s
            self.machine.delay(delay_s)
            self._stream_delay_ticks = delay_ticks
            log.info("'%s' reached the setpoint stream late and plays %.1f ms later than planned",
                     self.machine.trajectory_id, delay_s * 1e3)
        return self._stream.next_tick(time.monotonic() + self.cfg.executor.command_lead_s)

    def _stream_latest(self) -> None:
        """Under `_lock`, after any call that may have replaced the machine's trajectory."""
        if self.machine.revision != self._streamed_revision:
            self._streamed_revision = self.machine.revision
            self._to_stream.put((self.machine.trajectory, self.machine.started_at_s, self.machine.trajectory_id,
                                 self._stream_delay_ticks))

    def _feed_stream(self) -> None:
        """Sample each new trajectory on the stream's grid and send it, in order.

        None of them is skipped, not even the older of two quick ones: the newer was computed from the older's
        commanded state, so the stream must play the older until the newer takes over."""
        while (item := self._to_stream.get()) is not None:
            trajectory, start_s, trajectory_id, known_delay_ticks = item
            if trajectory is not None:
                self._stream.play(trajectory, trajectory_id, start_s, known_delay_ticks)

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
        """Stop within CLOSE_BUDGET_S, which `robonav up` waits for before it kills: a replan or an
        execute still running by then is abandoned (their threads are daemons), never the brake."""
        if self.monitor is not None:
            self.monitor.close(timeout_s=CLOSE_WAIT_S)
        for q in self._queryables:
            q.undeclare()
        self._workers.close(timeout_s=CLOSE_WAIT_S)
        self._map_sub.undeclare()
        self.check.close()
        self._sub.undeclare()
        self._to_stream.put(None)
        self._feeder.join(timeout=CLOSE_WAIT_S)
        self._stream.close(timeout_s=CLOSE_BRAKE_S)  # it brakes a moving arm to rest first
        self._status_pub.undeclare()
        self._path_pub.undeclare()
        # Frozen objects are never collected: give them back, so this node's cycles are freed
        # before the interpreter ends and the bindings find nothing of theirs left over.
        gc.unfreeze()


def main(argv: list[str] | None = None) -> int:
    return run_service("executor", argv, ExecutorNode)
