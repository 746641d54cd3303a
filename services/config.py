"""The whole product's config: one YAML file loaded strictly into frozen dataclasses."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Literal

import yaml

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.config import ConfigError, from_mapping, require
from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.sim.config import SimConfig
from robonav.pipeline.transforms import FloatArray

DEFAULT_CONFIG_NAME = "default.yaml"


@dataclass(frozen=True)
class ZenohConfig:
    mode: Literal["peer", "client", "router"] = "client"
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    """Endpoints to connect to; `robonav up` runs a router listening on the first one."""
    listen: tuple[str, ...] = ()
    multicast_scouting: bool = False
    """Off by default: a robot cell should not discover peers it was not told about."""
    config_file: str | None = None
    """A native Zenoh JSON5 config (TLS, user/password, access control; `configs/security/`) read
    first; the keys above are applied over it. Relative paths in it are relative to the working
    directory. `--zenoh-config FILE` on a service's command line overrides it for that process."""


@dataclass(frozen=True)
class LimitsConfig:
    max_request_bytes: int = 16 * 1024 * 1024
    """Query payloads larger than this are refused with PAYLOAD_TOO_LARGE [bytes]."""

    def __post_init__(self) -> None:
        require(self.max_request_bytes > 0, f"limits.max_request_bytes must be > 0, got {self.max_request_bytes}")


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
    """Watchdog: how far back setpoints count for the tracking error (the loop's latency) [s]."""
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
    monitor_path: bool = True
    """Re-check the rest of an executing path against every new occupancy map; a new obstacle on
    it stops the arm (and replans when the request asks for it)."""
    path_check_rate_hz: float = 10.0
    """The rest of the path is re-checked at least this often (and on every new map) [Hz]."""
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
        require(self.path_check_rate_hz > 0, f"executor.path_check_rate_hz must be > 0, got {self.path_check_rate_hz}")
        require(self.replan_attempts >= 1, f"executor.replan_attempts must be >= 1, got {self.replan_attempts}")
        require(self.replan_timeout_s > 0, f"executor.replan_timeout_s must be > 0, got {self.replan_timeout_s}")
        require(self.replan_delay_s >= 0, f"executor.replan_delay_s must be >= 0, got {self.replan_delay_s}")
        require(self.replan_settle_s >= 0, f"executor.replan_settle_s must be >= 0, got {self.replan_settle_s}")


@dataclass(frozen=True)
class DemoConfig:
    goals_rad: tuple[tuple[float, ...], ...] = ()
    """Joint goals visited in order by `robonav demo`."""
    goal_tolerance_rad: float = 0.02
    """A goal counts as reached when every joint is within this of it [rad]."""
    first_map_timeout_s: float = 60.0
    goal_timeout_s: float = 40.0

    def __post_init__(self) -> None:
        require(self.goal_tolerance_rad > 0, f"demo.goal_tolerance_rad must be > 0, got {self.goal_tolerance_rad}")


@dataclass(frozen=True)
class RobonavConfig:
    cell: str = "arm0"
    """Names one arm and its cameras; every key expression lives under robonav/<cell>/."""
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    robot: RobotConfig = field(default_factory=RobotConfig)
    cameras: tuple[CameraConfig, ...] = (CameraConfig(),)
    """Every depth camera of the cell; perception fuses them into one map."""
    sim: SimConfig = field(default_factory=SimConfig)
    perception: PerceptionConfig = field(default_factory=PerceptionConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    executor: ExecutorConfig = field(default_factory=ExecutorConfig)
    demo: DemoConfig = field(default_factory=DemoConfig)
    limits: LimitsConfig = field(default_factory=LimitsConfig)

    def __post_init__(self) -> None:
        require(bool(self.cell) and "/" not in self.cell and "*" not in self.cell,
                f"cell must be a non-empty name without '/' or '*', got {self.cell!r}")
        require(len(self.cameras) > 0, "cameras must list at least one camera")
        ids = [c.camera_id for c in self.cameras]
        require(len(set(ids)) == len(ids), f"cameras have duplicate camera_id values: {ids}")
        unknown = sorted(set(self.sim.camera_noise) - set(ids))
        require(not unknown, f"sim.camera_noise names cameras that are not in cameras: {unknown} (cameras: {ids})")
        n = len(self.robot.joint_names)
        for i, goal in enumerate(self.demo.goals_rad):
            require(len(goal) == n, f"demo.goals_rad[{i}] has {len(goal)} values, expected {n}")


def default_config_path() -> Path:
    return Path(str(resources.files("robonav.configs") / DEFAULT_CONFIG_NAME))


def load_config(path: str | Path | None = None) -> RobonavConfig:
    """Read a YAML config file strictly; `None` reads the packaged default.

    Raises:
        ConfigError: unreadable file, bad YAML, unknown key or wrong type (names file and key).
    """
    file = Path(path) if path is not None else default_config_path()
    try:
        text = file.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(file), "<file>", f"cannot read: {exc.strerror or exc}") from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(str(file), "<file>", f"invalid YAML: {exc}") from exc
    return _with_extrinsics(from_mapping(RobonavConfig, data, source=str(file)), file)


def _with_extrinsics(cfg: RobonavConfig, file: Path) -> RobonavConfig:
    """Resolve and check every camera's `extrinsics_file` now, so a bad one fails at load."""
    from robonav.calibration.extrinsics import read_extrinsics  # calibration's CLI imports this module

    cameras = []
    for i, camera in enumerate(cfg.cameras):
        if camera.extrinsics_file is None:
            cameras.append(camera)
            continue
        key = f"cameras[{i}].extrinsics_file"
        path = Path(camera.extrinsics_file)
        path = path if path.is_absolute() else file.parent / path
        if not path.is_file():
            raise ConfigError(str(file), key, f"{path} does not exist (run `robonav calibrate solve` to write it)")
        extrinsics = read_extrinsics(path)
        if extrinsics.camera_id != camera.camera_id:
            raise ConfigError(str(file), key, f"{path} calibrates camera {extrinsics.camera_id!r}, not {camera.camera_id!r}")
        if extrinsics.parent_frame != "world":
            raise ConfigError(str(file), key, f"{path} is an eye-in-hand result (parent_frame {extrinsics.parent_frame!r}); "
                                              "perception takes fixed cameras only (parent_frame: world)")
        cameras.append(dataclasses.replace(camera, extrinsics_file=str(path)))
    return dataclasses.replace(cfg, cameras=tuple(cameras))


def perceived_world_from_camera(camera: CameraConfig) -> FloatArray:
    """(4, 4) the camera pose perception uses: the calibrated one when the camera names an
    extrinsics file (resolved by `load_config`), else its configured pose."""
    if camera.extrinsics_file is None:
        return camera.world_from_camera
    from robonav.calibration.extrinsics import read_extrinsics

    return read_extrinsics(camera.extrinsics_file).parent_from_camera
