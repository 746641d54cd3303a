"""The whole product's config: one YAML file loaded strictly into frozen dataclasses."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml

from robonav.pipeline.camera import CameraConfig, CameraExtrinsics
from robonav.pipeline.config import ConfigError, collect_errors, from_mapping, require
from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.robot.config import RobotConfig, missing_described_fields
from robonav.pipeline.sim.config import SimConfig
from robonav.pipeline.trajectory.config import ExecutorConfig
from robonav.pipeline.types import FloatArray

DEFAULT_CONFIG_NAME = "default.yaml"
DEFAULT_EXTRINSICS_DIRECTORY = Path("configs") / "calibration"
"""Where `robonav calibrate solve` writes `<camera_id>.yaml` unless told otherwise."""


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
    max_queued_requests: int = 8
    """Requests that may wait for a busy worker (planner/plan, executor/execute); more: BUSY."""
    max_planning_time_s: float = 3600.0
    """Largest `allowed_planning_time` of a plan request [s]."""
    max_planning_attempts: int = 100
    """Largest `num_planning_attempts` of a plan request."""
    max_goals: int = 256
    """Most rows of a plan request's `goal_set`."""
    max_waypoints: int = 10_000
    """Most rows of an execute request's `path`."""
    max_replan_attempts: int = 20
    """Largest `replan_attempts` of an execute request."""
    max_scene_objects: int = 1000
    """Most `objects` (and `names`, `motions`) in one planner/scene or sim/objects request, and
    most objects (world and attached) in the planner's scene."""
    max_mesh_size: int = 100_000
    """Most vertices, and most triangles, of one mesh object."""
    max_publication_bytes: int = 64 * 1024 * 1024
    """Published samples larger than this are dropped (and counted) by every subscribing
    service before decoding [bytes]; a 1280x720 cloud is about 11 MB."""

    def __post_init__(self) -> None:
        for name in ("max_request_bytes", "max_queued_requests", "max_planning_attempts", "max_goals", "max_waypoints",
                     "max_replan_attempts", "max_scene_objects", "max_mesh_size", "max_publication_bytes"):
            value = getattr(self, name)
            require(value > 0, f"limits.{name} must be > 0, got {value}")
        require(self.max_planning_time_s > 0, f"limits.max_planning_time_s must be > 0, got {self.max_planning_time_s}")


@dataclass(frozen=True)
class StackConfig:
    """How `robonav up` supervises its processes (the router and every service)."""

    restart: bool = True
    """Restart a process that exits or is killed (systemd's `Restart=always`); false: leave it dead."""
    restart_backoff_initial_s: float = 0.5
    """Wait before the first restart after a healthy period [s]."""
    restart_backoff_max_s: float = 8.0
    """The wait doubles with every exit in a row, up to this [s]."""
    restart_backoff_reset_s: float = 30.0
    """A process that ran this long counts as healthy: its next restart waits the initial time again [s]."""
    router_start_timeout_s: float = 30.0
    """How long `robonav up` waits for its router to listen before giving up [s]."""

    def __post_init__(self) -> None:
        require(self.restart_backoff_initial_s > 0,
                f"stack.restart_backoff_initial_s must be > 0, got {self.restart_backoff_initial_s}")
        require(self.restart_backoff_max_s >= self.restart_backoff_initial_s,
                f"stack.restart_backoff_max_s must be >= restart_backoff_initial_s, got {self.restart_backoff_max_s}")
        require(self.restart_backoff_reset_s > 0,
                f"stack.restart_backoff_reset_s must be > 0, got {self.restart_backoff_reset_s}")
        require(self.router_start_timeout_s > 0,
                f"stack.router_start_timeout_s must be > 0, got {self.router_start_timeout_s}")


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
    stack: StackConfig = field(default_factory=StackConfig)

    def __post_init__(self) -> None:
        require(bool(self.cell) and "/" not in self.cell and "*" not in self.cell,
                f"cell must be a non-empty name without '/' or '*', got {self.cell!r}")
        require(len(self.cameras) > 0, "cameras must list at least one camera")
        ids = [c.camera_id for c in self.cameras]
        require(len(set(ids)) == len(ids), f"cameras have duplicate camera_id values: {ids}")
        unknown = sorted(set(self.sim.camera_noise) - set(ids))
        require(not unknown, f"sim.camera_noise names cameras that are not in cameras: {unknown} (cameras: {ids})")
        require(self.planner.allowed_planning_time_s <= self.limits.max_planning_time_s,
                f"planner.allowed_planning_time_s ({self.planner.allowed_planning_time_s}) is above "
                f"limits.max_planning_time_s ({self.limits.max_planning_time_s})")
        require(self.executor.replan_attempts <= self.limits.max_replan_attempts,
                f"executor.replan_attempts ({self.executor.replan_attempts}) is above "
                f"limits.max_replan_attempts ({self.limits.max_replan_attempts})")
        n = len(self.robot.joint_names)
        for i, goal in enumerate(self.demo.goals_rad):
            require(len(goal) == n, f"demo.goals_rad[{i}] has {len(goal)} values, expected {n}")


def default_config_path() -> Path:
    return Path(str(resources.files("robonav.configs") / DEFAULT_CONFIG_NAME))


def _read_yaml(file: Path) -> Any:
    """The YAML data of `file`; ConfigError when it cannot be read or parsed."""
    try:
        return yaml.safe_load(file.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(str(file), "<file>", f"cannot read: {exc.strerror or exc}") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(str(file), "<file>", f"invalid YAML: {exc}") from exc


def load_config(path: str | Path | None = None) -> RobonavConfig:
    """Read a YAML config file strictly; `None` reads the packaged default.

    Raises:
        ConfigError: unreadable file, bad YAML, unknown key or wrong type (names file and key).
    """
    file = Path(path) if path is not None else default_config_path()
    data = _read_yaml(file)
    if isinstance(data, dict) and isinstance(data.get("robot"), dict):
        data = {**data, "robot": _robot_paths_resolved(data["robot"], file, "robot")}
    return _with_extrinsics(from_mapping(RobonavConfig, data, source=str(file)), file)


@dataclass(frozen=True)
class ConfigIssue:
    """One error of a config file, where it is: `file:line: key 'k': message` (line 0: no line)."""

    file: str
    line: int
    key: str
    message: str

    def __str__(self) -> str:
        return f"{self.file}:{self.line}: key '{self.key}': {self.message}" if self.line else \
            f"{self.file}: key '{self.key}': {self.message}"


def check_config(path: str | Path) -> tuple[RobonavConfig | None, list[ConfigIssue]]:
    """Read a config file and report every error at once, each with its line.

    A robot file is checked as the `robot` section. Every key is checked, also after a bad one; a section with a bad key skips its cross-key
    checks (they would repeat the fault). Duplicate keys, which YAML loaders silently let the
    last one win, are errors here. Returns (the config, []) or (None, the errors in line order).
    """
    file = Path(path)
    try:
        text = file.read_text(encoding="utf-8")
    except OSError as exc:
        return None, [ConfigIssue(str(file), 0, "<file>", f"cannot read: {exc.strerror or exc}")]
    try:
        # The node tree keeps where every key and value starts (PyYAML's marks, 0-based).
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        return None, [ConfigIssue(str(file), mark.line + 1 if mark else 0, "<file>", f"invalid YAML: {exc.problem}")]
    except yaml.YAMLError as exc:
        return None, [ConfigIssue(str(file), 0, "<file>", f"invalid YAML: {exc}")]
    # A robot file (`robonav robot init`) holds RobotConfig's keys at its top: checked as the
    # `robot` section of a config that keeps every other default.
    robot_file = isinstance(data, dict) and "urdf" in data and not data.keys() & _SECTIONS
    if robot_file:
        data = {"robot": data}
    lines: dict[str, int] = {}
    issues = [ConfigIssue(str(file), line, key, "duplicate key (YAML would keep only the last)")
              for key, line in _key_lines(root, "robot" if robot_file else "", lines)]
    if isinstance(data, dict) and isinstance(data.get("robot"), dict):
        try:
            data = {**data, "robot": _robot_paths_resolved(data["robot"], file, "robot")}
        except ConfigError as exc:
            issues.append(ConfigIssue(str(file), _line_of(exc.key, lines), exc.key, exc.detail))
    cfg, errors = collect_errors(RobonavConfig, data, source=str(file))
    issues += [ConfigIssue(str(file), _line_of(e.key, lines), e.key, e.detail) for e in errors]
    if cfg is not None and not issues:
        try:
            cfg = _with_extrinsics(cfg, file)
        except ConfigError as exc:
            issues.append(ConfigIssue(str(file), _line_of(exc.key, lines), exc.key, exc.detail))
    issues.sort(key=lambda issue: issue.line)
    return (cfg if not issues else None), issues


_SECTIONS = frozenset(f.name for f in dataclasses.fields(RobonavConfig))


def _key_lines(node: yaml.Node | None, prefix: str, lines: dict[str, int]) -> list[tuple[str, int]]:
    """Fill `lines` with dotted key path -> 1-based line (`a.b`, `a[0].b`); returns duplicate keys."""
    duplicates: list[tuple[str, int]] = []
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:
            path = f"{prefix}.{key_node.value}" if prefix else str(key_node.value)
            if path in lines:
                duplicates.append((path, key_node.start_mark.line + 1))
            lines[path] = key_node.start_mark.line + 1
            duplicates += _key_lines(value_node, path, lines)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            path = f"{prefix}[{i}]"
            lines[path] = item.start_mark.line + 1
            duplicates += _key_lines(item, path, lines)
    return duplicates


def _line_of(key: str, lines: dict[str, int]) -> int:
    """Line of `key`, else of the nearest enclosing key that is in the file (a missing key: its section)."""
    while key:
        if key in lines:
            return lines[key]
        cut = max(key.rfind("."), key.rfind("["))
        key = key[:cut] if cut > 0 else ""
    return 1 if lines else 0


def config_to_mapping(cfg: Any) -> Any:
    """A config (or any of its sections) as plain YAML data: every key, defaults included;
    `load_config` reads it back into an equal config."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        return {f.name: config_to_mapping(getattr(cfg, f.name)) for f in dataclasses.fields(cfg) if f.init}
    if isinstance(cfg, (tuple, list)):
        return [config_to_mapping(v) for v in cfg]
    if isinstance(cfg, dict):
        return {k: config_to_mapping(v) for k, v in cfg.items()}
    if isinstance(cfg, np.ndarray):
        return cfg.tolist()
    if isinstance(cfg, np.generic):
        return cfg.item()
    return cfg
def load_robot_file(path: str | Path) -> RobotConfig:
    """Read a robot file (what `robonav robot init` writes): a YAML mapping of `RobotConfig` keys.

    Relative `urdf` and `package_paths` entries resolve against the file's folder and `$VAR`s
    expand, so a file can point at a description kept outside the repository.

    Raises:
        ConfigError: unreadable file, bad YAML, an unknown key or wrong type, or keys a non-Panda
            URDF must state left out (all of those named at once).
    """
    file = Path(path)
    data = _read_yaml(file)
    if not isinstance(data, dict):
        raise ConfigError(str(file), "<root>", f"expected a mapping of robot keys, got {type(data).__name__}")
    return from_mapping(RobotConfig, _robot_paths_resolved(data, file, ""), source=str(file))


def _robot_paths_resolved(data: dict[str, Any], file: Path, key: str) -> dict[str, Any]:
    """`data` with its URDF-described keys checked and its file paths made absolute (relative to `file`)."""
    missing = missing_described_fields(data)
    if missing:
        raise ConfigError(str(file), key or "<root>",
                          f"the robot names its own URDF ({data.get('urdf')}), so these keys must be given too (the "
                          f"defaults are the Panda's): {', '.join(missing)}; `robonav robot init` writes them all")
    out = dict(data)

    def resolved(value: Any) -> Any:
        if not isinstance(value, str) or value.startswith(("pybullet_data:", "package://")):
            return value
        expanded = Path(os.path.expanduser(os.path.expandvars(value)))
        return str(expanded if expanded.is_absolute() else (file.parent / expanded))

    if "urdf" in out:
        out["urdf"] = resolved(out["urdf"])
    if isinstance(out.get("package_paths"), list):
        out["package_paths"] = [resolved(v) for v in out["package_paths"]]
    return out


def _with_extrinsics(cfg: RobonavConfig, file: Path) -> RobonavConfig:
    """Resolve and check every camera's `extrinsics_file` now, so a bad one fails at load."""
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
    return read_extrinsics(camera.extrinsics_file).parent_from_camera


def default_extrinsics_path(camera_id: str) -> Path:
    return DEFAULT_EXTRINSICS_DIRECTORY / f"{camera_id}.yaml"


def write_extrinsics(path: str | Path, extrinsics: CameraExtrinsics) -> Path:
    """Write a camera extrinsics file (see `read_extrinsics` for the layout)."""
    file = Path(path)
    file.parent.mkdir(parents=True, exist_ok=True)
    data: dict[str, Any] = {
        "camera_id": extrinsics.camera_id, "parent_frame": extrinsics.parent_frame,
        "position_m": [float(v) for v in extrinsics.position_m], "quat_xyzw": [float(v) for v in extrinsics.quat_xyzw],
        "method": extrinsics.method, "calibrated_at": extrinsics.calibrated_at,
    }
    if extrinsics.reprojection_rms_px is not None:
        data["reprojection_rms_px"] = float(extrinsics.reprojection_rms_px)
    file.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return file


def read_extrinsics(path: str | Path) -> CameraExtrinsics:
    """Read a camera extrinsics file strictly (unknown keys and wrong types raise ConfigError).

    The file hand-eye calibration writes and perception reads, `configs/calibration/<camera_id>.yaml`:

    ```yaml
    camera_id: cam0
    parent_frame: world          # eye-to-hand: the world frame; eye-in-hand: the
                                 # end-effector link the camera rides on, e.g. panda_hand
    position_m: [1.45, 0.55, 1.05]            # camera optical frame origin in parent_frame [m]
    quat_xyzw: [-0.444, -0.751, 0.420, 0.249] # optical frame orientation in parent_frame
    # informative, ignored when read:
    method: refined
    reprojection_rms_px: 0.08
    ```

    The optical frame is OpenCV's (z forward, x right, y down), the same as the `cameras[]`
    entries of the robonav config, so for a fixed camera `position_m`/`quat_xyzw` are exactly
    what `cameras[].position_m`/`cameras[].quat_xyzw` hold: world_from_camera.
    """
    file = Path(path)
    data = _read_yaml(file)
    return from_mapping(CameraExtrinsics, data, source=str(file))
