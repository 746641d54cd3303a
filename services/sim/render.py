"""Render workers: one process per simulated camera, so physics never waits on a render.

pybullet holds the GIL while it renders (50-300 ms for 640x480 with the tiny renderer on a
loaded machine), so a render in the physics process stalls stepping, joint states and the
setpoint subscriber. Each worker owns a pybullet DIRECT client that only mirrors the arm's
joint positions and the obstacles' poses, as captured by the physics loop in a `RenderJob`;
it renders, labels, adds noise and publishes `camera/<cam>/cloud` and/or `camera/<cam>/depth`
on its own Zenoh session. The stamp is the moment the pose was captured, not the end of the
render, so perception poses the robot as it was in the image.

The physics loop hands a worker a job only when the worker said it is idle: frames are
latest-only and a slow render lowers the frame rate instead of queueing stale poses.
"""

from __future__ import annotations

import heapq
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import time
from dataclasses import dataclass

import numpy as np

from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.config import SimConfig
from robonav.pipeline.sim.sensor import labelled_cloud, sensor_frame
from robonav.pipeline.sim.world import SimWorld
from robonav.pipeline.wire.messages import DepthImage, PointCloud
from robonav.services.common import open_session, setup_logging
from robonav.services.config import RobonavConfig
from robonav.services.keys import Keys

log = logging.getLogger("robonav.sim.render")

ROBOT_LABEL = 0
"""Label of the arm in every frame; obstacles get labels from 1 by name (see `LabelRegistry`)."""
STOP_TIMEOUT_S = 3.0
"""A worker that has not stopped by then (starved at its low priority on a busy machine) is terminated."""
RENDER_NICENESS = 10
"""Render processes run at this lower CPU priority than the physics process."""


@dataclass(frozen=True)
class RenderJob:
    """The scene at one moment, as the physics loop captured it."""

    stamp: float
    """Wall time of the captured pose [s]; becomes the frame's stamp."""
    seq: int
    """Frame number of this camera, from 1."""
    q: np.ndarray
    """(n,) arm joint positions [rad]."""
    poses: dict[str, tuple[tuple[float, ...], tuple[float, ...]]]
    """Object name -> (position_m, quat_xyzw) at the captured moment."""
    scene: tuple[tuple[int, SceneObject], ...] | None = None
    """(label, object) of every obstacle, sent when the set of objects changed since the last job."""


class LabelRegistry:
    """Stable labels by object name: the same name keeps its label for the sim's lifetime."""

    def __init__(self) -> None:
        self._labels: dict[str, int] = {"robot": ROBOT_LABEL}

    def label(self, name: str) -> int:
        if name not in self._labels:
            self._labels[name] = len(self._labels)
        return self._labels[name]


class RenderWorker:
    """The physics process's handle on one camera's render process."""

    def __init__(self, cfg: RobonavConfig, camera_index: int) -> None:
        self.camera = cfg.cameras[camera_index]
        self._cfg = cfg
        self._index = camera_index
        self.idle = False
        """The worker waits for a job (it reported ready and has not been sent one since)."""
        self.structure_sent = -1
        """Structure revision of the scene the worker has."""
        self.seq = 0
        self.render_ms: list[float] = []
        self.restarts = 0
        self._start()

    def _start(self) -> None:
        # spawn: a fork would copy the physics process's pybullet client and Zenoh session threads.
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self.process = ctx.Process(target=worker_main, args=(self._cfg, self._index, child),
                                   name=f"robonav-render-{self.camera.camera_id}", daemon=True)
        self.process.start()
        child.close()
        self.idle = False
        self.structure_sent = -1

    def poll(self) -> None:
        """Collect the worker's reports without blocking; restart it if it died."""
        try:
            while self._conn.poll():
                kind, value = self._conn.recv()
                self.idle = True
                if kind == "done":
                    self.render_ms.append(float(value))
        except (EOFError, OSError):
            pass
        if not self.process.is_alive():
            self.restarts += 1
            log.error("render worker of %s exited with %s; restarting it (restart %d)",
                      self.camera.camera_id, self.process.exitcode, self.restarts)
            self._start()

    def submit(self, job: RenderJob) -> None:
        self.idle = False
        try:
            self._conn.send(job)
        except (BrokenPipeError, OSError):
            pass  # poll() notices the dead worker and restarts it

    def request_stop(self) -> None:
        """Ask the worker to finish (frames it already rendered still go out)."""
        try:
            self._conn.send(None)
        except (BrokenPipeError, OSError):
            pass

    def close(self) -> None:
        """Stop the worker (see `request_stop`), terminating it if it does not finish in time."""
        self.request_stop()
        self.process.join(STOP_TIMEOUT_S)
        if self.process.is_alive():
            log.warning("render worker of %s did not stop within %.0f s; terminating pid %s", self.camera.camera_id,
                        STOP_TIMEOUT_S, self.process.pid)
            self.process.terminate()
            self.process.join(STOP_TIMEOUT_S)
        self._conn.close()


class _Renderer:
    """The worker's side: a pose-mirroring world, the publishers, frames waiting out their latency."""

    def __init__(self, cfg: RobonavConfig, camera_index: int) -> None:
        self.camera = cfg.cameras[camera_index]
        self.index = camera_index
        self.noise = cfg.sim.camera_noise.get(self.camera.camera_id, cfg.sim.noise)
        self.with_labels = cfg.sim.labels
        # Kinematic and without gravity: this world is never stepped, only posed.
        self.world = SimWorld(cfg.robot, self.camera, SimConfig(follow="kinematic", gravity=False))
        self.session = open_session(cfg.zenoh)
        keys = Keys(cfg.cell)
        output = self.camera.output
        self.cloud_pub = self.session.declare_publisher(keys.camera_cloud(self.camera.camera_id)) \
            if output in ("cloud", "both") else None
        self.depth_pub = self.session.declare_publisher(keys.camera_depth(self.camera.camera_id)) \
            if output in ("depth", "both") else None
        self.label_of_body: dict[int, int] = {}
        self.label_names: dict[int, str] = {ROBOT_LABEL: "robot"}
        self._robot_body = next(b for b, name in self.world.body_labels().items() if name == "robot")
        self._latency_rng = np.random.default_rng((self.noise.seed, camera_index, 1 << 20))
        self.waiting: list[tuple[float, int, list[tuple[object, bytes]]]] = []

    def apply(self, job: RenderJob) -> None:
        if job.scene is not None:
            self.world.set_objects([obj for _, obj in job.scene])
            body_of = {name: body for body, name in self.world.body_labels().items()}
            self.label_of_body = {self._robot_body: ROBOT_LABEL, **{body_of[obj.name]: label for label, obj in job.scene}}
            self.label_names = {ROBOT_LABEL: "robot", **{label: obj.name for label, obj in job.scene}}
        current = {obj.name: obj for obj in self.world.objects}
        for name, (position, quat) in job.poses.items():
            obj = current.get(name)
            if obj is not None and (obj.position_m != position or obj.quat_xyzw != quat):
                self.world.set_object_pose(name, position, quat)
        self.world.set_joint_positions(job.q)

    def render(self, job: RenderJob) -> None:
        """Render the job's scene and queue its messages until their latency has passed."""
        frame = sensor_frame(self.world.render_depth(), self.label_of_body, self.noise,
                             self.noise.frame_rng(self.index, job.seq))
        names = self.label_names if self.with_labels else None
        outgoing: list[tuple[object, bytes]] = []
        if self.cloud_pub is not None:
            points, labels = labelled_cloud(frame, max_depth_m=self.camera.far_m)
            outgoing.append((self.cloud_pub, PointCloud(
                stamp=job.stamp, camera_id=self.camera.camera_id, points=points, seq=job.seq,
                intrinsics=frame.intrinsics, labels=labels if self.with_labels else None, label_names=names).to_wire()))
        if self.depth_pub is not None:
            outgoing.append((self.depth_pub, DepthImage(
                stamp=job.stamp, camera_id=self.camera.camera_id, intrinsics=frame.intrinsics, depth_m=frame.depth_m,
                seq=job.seq, labels=frame.labels if self.with_labels else None, label_names=names).to_wire()))
        latency_s = self.noise.latency_s + self.noise.latency_jitter_s * float(self._latency_rng.random()) \
            if self.noise.enabled else 0.0
        heapq.heappush(self.waiting, (job.stamp + latency_s, job.seq, outgoing))

    def publish_due(self) -> float | None:
        """Publish frames whose latency has passed; returns seconds until the next one (None: none)."""
        while self.waiting and self.waiting[0][0] <= time.time():
            _, _, outgoing = heapq.heappop(self.waiting)
            for publisher, payload in outgoing:
                publisher.put(payload)  # type: ignore[attr-defined]
        return max(0.0, self.waiting[0][0] - time.time()) if self.waiting else None

    def close(self) -> None:
        for publisher in (self.cloud_pub, self.depth_pub):
            if publisher is not None:
                publisher.undeclare()
        self.session.close()
        self.world.close()


def worker_main(cfg: RobonavConfig, camera_index: int, conn: multiprocessing.connection.Connection) -> None:
    """Entry point of a render process: serve jobs until told to stop or the sim goes away."""
    # The sim process decides when to stop (SIGINT from a terminal reaches the whole group).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # On a busy machine the physics process must win the CPU: a late frame is harmless, a late
    # physics step or joint state trips the executor's watchdog.
    os.nice(RENDER_NICENESS)
    setup_logging("WARNING")
    renderer = _Renderer(cfg, camera_index)
    try:
        conn.send(("ready", None))
        while True:
            wait_s = renderer.publish_due()
            try:
                if not conn.poll(wait_s):
                    continue
                job = conn.recv()
            except (EOFError, OSError):
                break  # the sim process is gone
            if job is None:
                break
            started = time.perf_counter()
            renderer.apply(job)
            renderer.render(job)
            try:
                conn.send(("done", (time.perf_counter() - started) * 1e3))
            except OSError:  # BrokenPipeError: the sim process is gone (killed mid-frame)
                break
        while renderer.waiting:  # frames already captured still go out
            time.sleep(renderer.publish_due() or 0.0)
    finally:
        renderer.close()


def snapshot_scene(objects: tuple[SceneObject, ...], registry: LabelRegistry) -> tuple[tuple[int, SceneObject], ...]:
    """(label, object) for a job's `scene`."""
    return tuple((registry.label(obj.name), obj) for obj in objects)
