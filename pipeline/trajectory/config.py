"""Executor settings: setpoint rate, scaling defaults, tolerances, the watchdog, path monitoring."""

from __future__ import annotations

import os
from dataclasses import dataclass

from robonav.pipeline.config import require


@dataclass(frozen=True)
class ExecutorConfig:
    rate_hz: float = 1000.0
    """Setpoint stream rate [Hz]."""
    status_rate_hz: float = 20.0
    velocity_scaling: float = 0.5
    """Default max_velocity_scaling_factor when a request gives none."""
    acceleration_scaling: float = 0.5
    """Default max_acceleration_scaling_factor when a request gives none."""
    start_tolerance_rad: float = 0.05
    """An execute path must start within this of the measured joint state [rad]."""
    preempt_tolerance_rad: float = 0.2
    """While moving, an execute path must start within this of the commanded state [rad]."""
    max_path_deviation_rad: float = 0.02
    """Blended corners stay within this of the path's polyline and waypoints [rad]; 0 = rest at every waypoint."""
    joint_state_timeout_s: float = 0.5
    """Watchdog: no joint state for longer than this while moving stops the arm (state error) [s]."""
    max_tracking_error_rad: float = 0.2
    """Watchdog: a joint further than this from every setpoint of the last `tracking_latency_s`
    while moving stops the arm [rad]."""
    tracking_latency_s: float = 0.3
    """Watchdog: how far back setpoints count for the tracking error. The measured state lags
    the commanded one by the loop's latency (executor → robot → joint state → executor), which
    under load reaches a few tens of milliseconds, so a measurement is compared with every
    setpoint of this window before its arrival, and since, and the closest one counts [s]."""
    busy_wait_s: float = 0.0
    """The streaming loop polls the clock for this long before each tick instead of sleeping [s]."""
    realtime_priority: int = 50
    """SCHED_FIFO priority (1-99) of the setpoint stream's loop; 0 leaves it at normal priority.
    Needs CAP_SYS_NICE or an RLIMIT_RTPRIO that allows it (`ulimit -r`, compose `ulimits:
    rtprio`); without either the stream logs a warning and runs at normal priority."""
    cpu_affinity: tuple[int, ...] = ()
    """CPUs the setpoint stream's loop may run on (ros2_control's `cpu_affinity`); empty: any.
    Its Zenoh threads stay free to run elsewhere."""
    command_lead_s: float = 0.01
    """A new trajectory (execute, stop, replan) takes over this long after the command: the time
    to sample it and hand it to the setpoint stream's process, so the switch is exact [s]."""
    start_dwell_s: float = 0.1
    """A motion from rest first streams its start, at rest, this long [s]. A driver in hold
    takes a first setpoint only if a motion from where it holds could have reached it since it
    last looked (Franka's FCI, the sim's driver): setpoints that reach it late and bunched (a
    busy host, a router) would otherwise show it one already 30-40 ms into the motion, which it
    refuses while the arm stays put until the tracking watchdog stops the motion. Once it
    follows the setpoints at rest, their stamps tell it how much time passed."""
    require_scene: bool = True
    """Refuse an execute (SCENE_MISSING) while no planner's scene (`planner/scene_state`) has
    arrived: the executor checks every motion against the planner's objects, and without them
    it cannot. False checks against the occupancy map alone (a cell without a planner)."""
    scene_wait_s: float = 1.0
    """How long an execute waits for a first planner scene (a planner that just started) [s]."""
    monitor_path: bool = True
    """Re-check the rest of an executing path against every new occupancy map; a new obstacle on
    it stops the arm (and replans when the request asks for it)."""
    path_check_rate_hz: float = 10.0
    """The rest of the path is re-checked at least this often (and on every new map) [Hz]."""
    max_map_age_s: float = 2.0
    """While a monitored path executes and maps are required (`planner.require_occupancy`), the
    newest map's frames may be at most this old [s]. Older, the path guard cannot see what came
    since (perception lags or is gone), and the arm stops as for a block: it replans when the
    request asks for it, else OCCUPANCY_STALE. 0: no limit."""
    replan_attempts: int = 3
    """Default plans per execute request after blocks (ExecuteRequest.replan_attempts)."""
    replan_timeout_s: float = 10.0
    """Wait for a planner's reply to a replan at most this long [s]."""
    replan_delay_s: float = 0.5
    """Pause after a failed replan before the next, so the map can change (MoveIt's replan_delay) [s]."""
    replan_settle_s: float = 1.0
    """Before a replan, wait up to this long for two maps taken after the stop, the second adding
    (almost) no voxel to the first: the obstacle that stopped the arm may still be moving, and a
    path around where it was runs into where it stops [s]; 0: plan at once."""

    def __post_init__(self) -> None:
        require(0 < self.rate_hz <= 2000, f"executor.rate_hz must be in (0, 2000], got {self.rate_hz}")
        require(self.status_rate_hz > 0, f"executor.status_rate_hz must be > 0, got {self.status_rate_hz}")
        for key in ("velocity_scaling", "acceleration_scaling"):
            value = getattr(self, key)
            require(0 < value <= 1, f"executor.{key} must be in (0, 1], got {value}")
        require(self.start_tolerance_rad > 0, f"executor.start_tolerance_rad must be > 0, got {self.start_tolerance_rad}")
        for key in ("preempt_tolerance_rad", "joint_state_timeout_s", "max_tracking_error_rad", "tracking_latency_s"):
            value = getattr(self, key)
            require(value > 0, f"executor.{key} must be > 0, got {value}")
        require(0 <= self.busy_wait_s < 1.0 / self.rate_hz,
                f"executor.busy_wait_s must be in [0, 1 / rate_hz), got {self.busy_wait_s}")
        require(self.max_path_deviation_rad >= 0,
                f"executor.max_path_deviation_rad must be >= 0, got {self.max_path_deviation_rad}")
        require(0 <= self.realtime_priority <= 99, f"executor.realtime_priority must be in [0, 99], got {self.realtime_priority}")
        cpus = os.cpu_count() or 1
        require(all(isinstance(c, int) and 0 <= c < cpus for c in self.cpu_affinity),
                f"executor.cpu_affinity must list CPUs in [0, {cpus - 1}], got {list(self.cpu_affinity)}")
        require(0 < self.command_lead_s <= 0.5, f"executor.command_lead_s must be in (0, 0.5], got {self.command_lead_s}")
        require(0 <= self.start_dwell_s <= 1.0, f"executor.start_dwell_s must be in [0, 1], got {self.start_dwell_s}")
        require(self.path_check_rate_hz > 0, f"executor.path_check_rate_hz must be > 0, got {self.path_check_rate_hz}")
        require(self.max_map_age_s >= 0, f"executor.max_map_age_s must be >= 0, got {self.max_map_age_s}")
        require(self.replan_attempts >= 1, f"executor.replan_attempts must be >= 1, got {self.replan_attempts}")
        require(self.replan_timeout_s > 0, f"executor.replan_timeout_s must be > 0, got {self.replan_timeout_s}")
        require(self.replan_delay_s >= 0, f"executor.replan_delay_s must be >= 0, got {self.replan_delay_s}")
        require(self.replan_settle_s >= 0, f"executor.replan_settle_s must be >= 0, got {self.replan_settle_s}")
        require(self.scene_wait_s >= 0, f"executor.scene_wait_s must be >= 0, got {self.scene_wait_s}")
