"""`robonav view`: a live 3D view in the browser (viser) of what the pipeline sees, plans and does.

Subscribes to joint states, camera clouds, the occupancy map, clusters, the planner's scene
(objects, attached ones following the arm), the executor's path and status; draws them on a viser page. Zenoh callbacks only keep the latest sample: a redraw loop
decodes and draws at its own rates, so a 30 Hz 640x480 camera is thinned (fewer frames, fewer
points) before anything reaches the browser. `--snapshot out.png` renders the page once in
headless Chromium and writes it as a PNG.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from robonav.pipeline.config import ConfigError, require
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.sim.cell import CellPlacement, robot_reach
from robonav.pipeline.transforms import transform_points
from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire.messages import ExecutorPath, PlanningSceneState, PointCloud
from robonav.services.client import RobonavClient
from robonav.services.common import (
    add_logging_arguments,
    declare_latched_subscriber,
    load_cli_config,
    open_session,
    setup_logging,
)
from robonav.services.config import RobonavConfig, load_config, perceived_world_from_camera
from robonav.services.keys import Keys
from robonav.services.signals import stop_on_signals
from robonav.services.view.gate import TOKEN_ENV, TokenGate, is_loopback, new_token

log = logging.getLogger("robonav.view")

DEFAULT_PORT = 8080
CAMERA_POSITION_M = (1.9, -1.35, 1.35)
"""Where the browser's camera starts, world frame [m]: front right of the robot, above the table."""
CAMERA_LOOK_AT_M = (0.35, 0.0, 0.35)
CAMERA_FOV_RAD = 0.87
"""Vertical field of view of the browser's camera [rad] (50 degrees)."""


def initial_camera_m(robot: RobotModel) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Where the browser's camera starts and the point it looks at, world frame [m].

    `CAMERA_POSITION_M` and `CAMERA_LOOK_AT_M` frame the packaged config's Panda; another robot's
    are placed as its cell is (`pipeline/sim/cell.py`): the same place relative to its shoulder,
    in reaches. The UR5's shoulder is 1 m up: the Panda's camera would see its base only.
    """
    packaged = load_config().robot
    if robot.config == packaged:
        return CAMERA_POSITION_M, CAMERA_LOOK_AT_M
    placement = CellPlacement(robot_reach(RobotModel.from_config(packaged)), robot_reach(robot))
    return (tuple(float(v) for v in placement.point(CAMERA_POSITION_M)),
            tuple(float(v) for v in placement.point(CAMERA_LOOK_AT_M)))


@dataclass(frozen=True)
class ViewOptions:
    host: str = "127.0.0.1"
    """Address the page is served on; 0.0.0.0 makes it reachable from other machines, and then
    only with `token` (`gate.py`): the page commands the robot."""
    port: int = DEFAULT_PORT
    """HTTP and websocket port; 0 picks a free one, a busy one moves to the next free port."""
    rate_hz: float = 30.0
    """Redraw rate of the robot and the executor status [Hz]."""
    cloud_rate_hz: float = 5.0
    """Most cloud redraws per camera and second [Hz]; faster cameras are thinned to this."""
    max_cloud_points: int = 20000
    """Points per camera sent to the browser; denser clouds are decimated."""
    map_rate_hz: float = 2.0
    """Most occupancy redraws per second [Hz]; unchanged maps are not resent at all."""
    path_step_rad: float = 0.05
    """Joint step between samples of the end-effector trace [rad]."""
    spheres: bool = False
    """Show the planner's collision spheres at start (the "Collision spheres" toggle otherwise)."""
    token: str | None = None
    """Required on any address but loopback: the page and its websocket are served only to a
    browser that opened `...?token=<token>` (then a cookie)."""

    def __post_init__(self) -> None:
        require(0 <= self.port < 65536, f"view port must be in [0, 65535], got {self.port}")
        require(is_loopback(self.host) or bool(self.token),
                f"the view on {self.host} would serve Plan/Execute/Stop to anyone who reaches it: give it a token "
                f"({TOKEN_ENV} or --token-file), or serve it on 127.0.0.1")
        for key in ("rate_hz", "cloud_rate_hz", "map_rate_hz", "path_step_rad"):
            require(getattr(self, key) > 0, f"view {key} must be > 0, got {getattr(self, key)}")
        require(self.max_cloud_points > 0, f"view max_cloud_points must be > 0, got {self.max_cloud_points}")


@dataclass
class ViewStats:
    """Counters of what the view received and drew (read by `robonav view bench` and tests)."""

    clouds_pulled: int = 0
    """Cloud samples taken from the latest-only channel (older ones Zenoh already dropped)."""
    clouds_drawn: int = 0
    cloud_draw_s: float = 0.0
    """Time spent decoding, decimating, colouring and sending clouds [s]."""
    cloud_points_sent: int = 0
    maps_drawn: int = 0
    paths_drawn: int = 0
    clusters_drawn: int = 0
    scenes_drawn: int = 0
    """Planner scenes (`planner/scene_state`) drawn."""
    robot_updates: int = 0
    errors: dict[str, int] = field(default_factory=dict)


class ViewNode:
    """A viser server fed from Zenoh; `spin` redraws until stopped, `close` undeclares everything."""

    def __init__(self, cfg: RobonavConfig, session: zenoh.Session, options: ViewOptions = ViewOptions()) -> None:
        import viser  # imported here so the rest of the package works without the `view` extra

        from robonav.services.view.gui import ViewControls
        from robonav.services.view.scene import SceneLayers, cameras_of

        self.cfg = cfg
        self.options = options
        self.stats = ViewStats()
        self.cameras = {camera.camera_id: camera for camera in cameras_of(cfg)}
        # Clouds are drawn where perception puts them: at the calibrated pose when there is one.
        self._world_from_camera = {cam_id: perceived_world_from_camera(camera) for cam_id, camera in self.cameras.items()}
        self.gate: TokenGate | None = None
        if is_loopback(options.host):
            self.server = viser.ViserServer(host=options.host, port=options.port, verbose=False)
        else:  # viser stays on loopback; the gate serves the address asked for, to token holders only
            self.server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
            assert options.token is not None
            try:
                self.gate = TokenGate(options.host, options.port, int(self.server.get_port()), options.token)
            except OSError:
                self.server.stop()
                raise
        self.server.gui.configure_theme(show_share_button=False)
        self.server.gui.main_panel.dock_right()  # beside the 3D view, not over it
        # Shadow maps cost more than the whole scene when WebGL renders in software, and a
        # robot cell's view gains little from them.
        self.server.scene.configure_default_lights(cast_shadow=False)
        robot = RobotModel.from_config(cfg.robot)
        self.server.initial_camera.position, self.server.initial_camera.look_at = initial_camera_m(robot)
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        self.server.initial_camera.fov = CAMERA_FOV_RAD
        z_range = (float(cfg.perception.workspace_min_m[2]), float(cfg.perception.workspace_max_m[2]) * 0.8)
        self.layers = SceneLayers(self.server, robot, list(self.cameras.values()),
                                  workspace_z_m=z_range, path_step_rad=options.path_step_rad,
                                  show_spheres=options.spheres)
        self.client = RobonavClient(session, cfg.cell)
        self.controls = ViewControls(self.server, self.layers, self.client)
        keys = Keys(cfg.cell)
        self._lock = threading.Lock()
        self._path: ExecutorPath | None = None
        self._clusters: tuple | None = None
        self._planning_scene: PlanningSceneState | None = None
        # A wildcard over every camera: room for a few samples per camera so one fast camera
        # does not push another's only frame out before the loop drains the channel.
        self._cloud_sub = session.declare_subscriber(keys.all_camera_clouds,
                                                     zenoh.handlers.RingChannel(2 * max(1, len(self.cameras))))
        self._path_sub = declare_latched_subscriber(session, keys.executor_path, self._on_path)
        clusters_key = getattr(keys, "clusters", f"{keys.root}/perception/clusters")
        self._clusters_sub = session.declare_subscriber(clusters_key, self._on_clusters)
        self._scene_sub = declare_latched_subscriber(session, keys.scene_state, self._on_planning_scene)
        self._pending_clouds: dict[str, zenoh.Sample] = {}
        self._next_cloud_s: dict[str, float] = {}
        self._next_map_s = 0.0
        self._drawn: dict[str, object] = {}
        self.drawn_cameras: set[str] = set()
        self.paused = threading.Event()
        """While set, nothing is redrawn (a snapshot waits for a still picture)."""
        if self.gate is None:
            log.info("view: %s", self.url)

    @property
    def port(self) -> int:
        return self.gate.port if self.gate is not None else int(self.server.get_port())

    @property
    def url(self) -> str:
        """The page's address (with the token when gated: the first visit trades it for a cookie)."""
        host = "127.0.0.1" if self.options.host in ("0.0.0.0", "::", "") else self.options.host
        host = f"[{host}]" if ":" in host else host
        token = f"?token={self.options.token}" if self.gate is not None else ""
        return f"http://{host}:{self.port}/{token}"

    def _count_error(self, kind: str, exc: Exception) -> None:
        self.stats.errors[kind] = self.stats.errors.get(kind, 0) + 1
        if self.stats.errors[kind] == 1:
            log.warning("view: dropped %s (%s: %s); further ones are counted silently", kind, type(exc).__name__, exc)

    def _on_path(self, sample: zenoh.Sample) -> None:
        try:
            path = ExecutorPath.from_wire(sample.payload.to_bytes())
        except Exception as exc:  # a bad sample is dropped, never raised into Zenoh
            self._count_error("executor path", exc)
            return
        with self._lock:
            self._path = path

    def _on_planning_scene(self, sample: zenoh.Sample) -> None:
        try:
            state = PlanningSceneState.from_wire(sample.payload.to_bytes())
        except Exception as exc:  # a bad sample is dropped, never raised into Zenoh
            self._count_error("planning scene", exc)
            return
        with self._lock:
            self._planning_scene = state

    def _on_clusters(self, sample: zenoh.Sample) -> None:
        from robonav.services.view.clusters import decode_clusters

        boxes = decode_clusters(sample.payload.to_bytes())
        with self._lock:
            self._clusters = boxes

    def tick(self, now_s: float) -> None:
        """Draw whatever changed since the last tick (each layer at most at its own rate)."""
        if self.paused.is_set():
            return
        for name, step in (("joint state", self._draw_robot), ("status", self._draw_status),
                           ("occupancy", lambda: self._draw_map(now_s)), ("path", self._draw_path),
                           ("clusters", self._draw_clusters), ("planning scene", self._draw_planning_scene),
                           ("cloud", lambda: self._draw_clouds(now_s))):
            try:
                step()
            except Exception as exc:  # one bad message must not stop the other layers
                self._count_error(name, exc)

    def _changed(self, name: str, value: object) -> bool:
        if value is None or self._drawn.get(name) is value:
            return False
        self._drawn[name] = value
        return True

    def _draw_robot(self) -> None:
        state = self.client.joint_state
        if not self._changed("joint_state", state):
            return
        assert state is not None
        # A resting arm still publishes at 100 Hz: resend the pose only when it moved.
        key = (tuple(state.names), np.round(state.position, 5).tobytes())
        if key == self._drawn.get("joint_positions"):
            return
        self._drawn["joint_positions"] = key
        self.layers.set_robot_joints(state.names, state.position.tolist())
        self.layers.planning.follow(state.names, state.position.tolist())
        self.stats.robot_updates += 1
        if self.stats.robot_updates == 1:
            self.controls.move_gizmo_to_hand()

    def _draw_status(self) -> None:
        status = self.client.status
        if self._changed("status", status):
            assert status is not None
            self.controls.show_status(status)

    def _draw_map(self, now_s: float) -> None:
        occupancy = self.client.occupancy
        if now_s < self._next_map_s or self._drawn.get("occupancy") is occupancy or occupancy is None:
            return
        self._drawn["occupancy"] = occupancy
        self._next_map_s = now_s + 1.0 / self.options.map_rate_hz
        if self.layers.show_voxels(occupancy.occupied_centers_m, occupancy.resolution_m):
            self.stats.maps_drawn += 1

    def _draw_path(self) -> None:
        with self._lock:
            path = self._path
        if self._changed("path", path):
            assert path is not None
            self.layers.show_path(path.joint_names, path.path, executed=True)
            self.stats.paths_drawn += 1

    def _draw_clusters(self) -> None:
        with self._lock:
            clusters = self._clusters
        if self._changed("clusters", clusters):
            assert clusters is not None
            self.layers.show_clusters(clusters)
            self.stats.clusters_drawn += 1

    def _draw_planning_scene(self) -> None:
        with self._lock:
            state = self._planning_scene
        if self._changed("planning_scene", state):
            assert state is not None
            self.layers.planning.show(state)
            self.stats.scenes_drawn += 1

    def _draw_clouds(self, now_s: float) -> None:
        while (sample := self._cloud_sub.try_recv()) is not None:
            self._pending_clouds[str(sample.key_expr)] = sample
            self.stats.clouds_pulled += 1
        for key, sample in list(self._pending_clouds.items()):
            if now_s < self._next_cloud_s.get(key, 0.0):
                continue
            del self._pending_clouds[key]
            self._next_cloud_s[key] = now_s + 1.0 / self.options.cloud_rate_hz
            try:
                self._draw_cloud(sample)
            except Exception as exc:
                self._count_error("cloud", exc)

    def _draw_cloud(self, sample: zenoh.Sample) -> None:
        from robonav.services.view.scene import decimate

        started = time.perf_counter()
        cloud = PointCloud.from_wire(sample.payload.to_bytes())
        world_from_camera = self._world_from_camera.get(cloud.camera_id)
        if world_from_camera is None:
            raise ValueError(f"cloud from unknown camera {cloud.camera_id!r} (configured: {sorted(self.cameras)})")
        points: FloatArray = transform_points(world_from_camera, decimate(cloud.points, self.options.max_cloud_points))
        colors = self.layers.color_cloud(points, by_cluster=self.controls.cloud_coloring == "cluster")
        self.layers.show_cloud(cloud.camera_id, points, colors)
        self.drawn_cameras.add(cloud.camera_id)
        self.stats.clouds_drawn += 1
        self.stats.cloud_points_sent += len(points)
        self.stats.cloud_draw_s += time.perf_counter() - started

    def spin(self, stop: threading.Event) -> None:
        period_s = 1.0 / self.options.rate_hz
        next_tick = time.monotonic()
        while not stop.is_set():
            self.tick(time.monotonic())
            next_tick += period_s
            now = time.monotonic()
            if next_tick < now:  # fell behind: skip ticks rather than burst
                next_tick = now
            stop.wait(next_tick - now)

    def start(self) -> threading.Event:
        """Run `spin` in a daemon thread; set the returned event to stop it."""
        stop = threading.Event()
        self._thread = threading.Thread(target=self.spin, args=(stop,), name="robonav-view", daemon=True)
        self._thread.start()
        self._stop = stop
        return stop

    def wait_until(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > deadline:
                return False
            time.sleep(0.05)
        return True

    def close(self) -> None:
        if getattr(self, "_stop", None) is not None:
            self._stop.set()
            self._thread.join(timeout=5.0)
        for sub in (self._cloud_sub, self._path_sub, self._clusters_sub, self._scene_sub):
            sub.undeclare()
        self.client.close()
        if self.gate is not None:
            self.gate.close()
        self.server.stop()


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="robonav view", description=__doc__.split("\n\n")[0] + " `robonav view bench --help` measures it.")
    parser.add_argument("--config", help="YAML config file (default: the packaged configs/default.yaml)")
    parser.add_argument("--robot", metavar="FILE",
                        help="view this robot (a robot file, or a config whose robot section is taken), in the cell "
                             "placed for it as `robonav demo --robot FILE` and `robonav campaign --robot FILE` place "
                             "it; default: the robot of --config")
    parser.add_argument("--zenoh-config", metavar="FILE",
                        help="Zenoh JSON5 config (TLS, login: client-viewer.json5, or client-operator.json5 for the "
                             "controls); overrides zenoh.config_file")
    parser.add_argument("--host", default=ViewOptions.host,
                        help="address to serve the page on (default %(default)s); any other than loopback needs "
                             f"a token: --token-file, else {TOKEN_ENV}, else a new one is printed at start")
    parser.add_argument("--token-file", metavar="FILE", help="file holding the token for a non-loopback --host")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help="port of the page; 0 = any free one (default %(default)s)")
    parser.add_argument("--max-cloud-points", type=int, default=ViewOptions.max_cloud_points,
                        help="points per camera sent to the browser (default %(default)s)")
    parser.add_argument("--cloud-rate-hz", type=float, default=ViewOptions.cloud_rate_hz,
                        help="most cloud redraws per camera and second (default %(default)s)")
    parser.add_argument("--spheres", action="store_true",
                        help="show the planner's collision spheres on the robot from the start (a layer toggle "
                             "otherwise)")
    parser.add_argument("--snapshot", metavar="OUT.png", help="render the scene once in headless Chromium, write a PNG, exit")
    parser.add_argument("--wait-s", type=float, default=20.0, help="--snapshot: longest wait for data (default %(default)s)")
    parser.add_argument("--size", default="1280x800", help="--snapshot: picture size in pixels, WIDTHxHEIGHT (default %(default)s)")
    add_logging_arguments(parser)
    return parser.parse_args(argv)


def view_token(args: argparse.Namespace) -> str | None:
    """The token for a non-loopback host: from --token-file, else the environment, else a new one."""
    if is_loopback(args.host):
        return None
    if args.token_file:
        try:
            token = Path(args.token_file).read_text(encoding="utf-8").strip()
        except OSError as exc:
            raise ValueError(f"--token-file {args.token_file}: {exc.strerror or exc}") from exc
        require(bool(token), f"--token-file {args.token_file} is empty")
        return token
    return os.environ.get(TOKEN_ENV) or new_token()


def view_config(args: argparse.Namespace) -> RobonavConfig:
    """The config of `--config` (and `--zenoh-config`), running the robot of `--robot` when given.

    Raises:
        ConfigError: a bad config, Zenoh config or robot file.
    """
    cfg = load_cli_config(args.config, args.zenoh_config)
    if not args.robot:
        return cfg
    # The demo's and the campaign's own reading: the same robot file gives the same robot and
    # cell, so the view draws clouds and cameras where a stack run with that file has them.
    # Imported here: it brings in the planner, which the view needs for nothing else.
    from robonav.services.stack.robot_cell import read_robot, with_robot

    return with_robot(cfg, read_robot(args.robot))


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["bench"]:
        from robonav.services.bench.view import main as bench_main

        return bench_main(argv[1:])
    args = parse_args(argv)
    setup_logging(args.log_level, args.log_format)
    try:
        cfg = view_config(args)
        options = ViewOptions(host=args.host, port=args.port, max_cloud_points=args.max_cloud_points,
                              cloud_rate_hz=args.cloud_rate_hz, spheres=args.spheres, token=view_token(args))
        width, height = (int(v) for v in args.size.lower().split("x"))
        require(width > 0 and height > 0, f"--size must be WIDTHxHEIGHT in pixels, got {args.size!r}")
    except (ConfigError, ValueError) as exc:
        log.error("%s", exc)
        return 2
    stop = stop_on_signals(signal.SIGINT, signal.SIGTERM)
    try:
        session = open_session(cfg.zenoh)
    except zenoh.ZError as exc:
        log.error("cannot reach the Zenoh router at %s (%s): start the stack with `robonav up`", list(cfg.zenoh.connect), exc)
        return 1
    with session:
        try:
            node = ViewNode(cfg, session, options)
        except ImportError as exc:
            log.error("robonav view needs the `view` extra (pip install 'robonav-arm[view]'): %s", exc)
            return 2
        except OSError as exc:
            log.error("view: cannot serve on %s:%d: %s", options.host, options.port, exc)
            return 1
        if node.gate is not None:  # the address with the token, for whoever started the view
            print(f"view: {node.url}", flush=True)
        try:
            if args.snapshot:
                node.start()
                from robonav.services.view.snapshot import run_snapshot

                return run_snapshot(node, Path(args.snapshot), args.wait_s, width, height)
            node.spin(stop)
        finally:
            node.close()
    return 0
