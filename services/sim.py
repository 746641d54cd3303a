"""Sim service: a pybullet world paced to wall time that follows setpoints and streams sensors.

Publishes `robot/joint_states` and `camera/<cam>/cloud`; follows `executor/setpoint`;
answers `sim/contacts` with ground-truth robot–obstacle contacts.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import zenoh

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.joint_order import reorder_to_robot
from robonav.pipeline.messages import ContactsRequest, ContactsResponse, JointState, PointCloud, Setpoint
from robonav.pipeline.perception.depth import points_from_depth
from robonav.pipeline.sim.world import SimWorld
from robonav.services.common import Node, guarded_queryable, guarded_subscriber, decode_request, reply_ok, run_service
from robonav.services.config import RobonavConfig
from robonav.services.keys import Keys

log = logging.getLogger("robonav.sim")

CLEARANCE_QUERY_RANGE_M = 0.3
"""Ground-truth clearance is tracked up to this distance; beyond it is reported as absent."""
MAX_CATCH_UP_STEPS = 24
"""After a stall (a slow render), at most this many physics steps run back to back."""


class ContactTracker:
    """Counts contact onsets: a touching (link, object) pair counts once until it separates."""

    def __init__(self) -> None:
        self.count = 0
        self.pairs: set[str] = set()
        self.min_distance_m = float("inf")
        self._touching: set[str] = set()

    def update(self, touching: set[str]) -> set[str]:
        new = touching - self._touching
        self.count += len(new)
        self.pairs |= touching
        self._touching = touching
        return new

    def reset(self) -> None:
        """Zero the counters; pairs still touching are not counted again until they separate."""
        self.count = 0
        self.pairs = set(self._touching)
        self.min_distance_m = float("inf")


class SimNode(Node):
    def __init__(self, cfg: RobonavConfig, session: zenoh.Session) -> None:
        self.cfg = cfg
        self.world = SimWorld(cfg.robot, cfg.cameras[0], cfg.sim)
        self.names = cfg.robot.joint_names
        self.contacts = ContactTracker()
        self._lock = threading.Lock()
        self._setpoint: Setpoint | None = None
        keys = Keys(cfg.cell)
        self._joint_pub = session.declare_publisher(keys.joint_states)
        self._cloud_pubs = {cam.camera_id: session.declare_publisher(keys.camera_cloud(cam.camera_id))
                            for cam in cfg.cameras}
        self._sub = session.declare_subscriber(keys.setpoint, guarded_subscriber(self.on_setpoint, "sim"))
        self._queryable = session.declare_queryable(keys.contacts, guarded_queryable(self.handle_contacts, "sim"))
        self._cloud_seq = dict.fromkeys(self._cloud_pubs, 0)

    def on_setpoint(self, sample: zenoh.Sample) -> None:
        setpoint = Setpoint.from_wire(sample.payload.to_bytes())
        with self._lock:
            self._setpoint = setpoint

    def handle_contacts(self, query: zenoh.Query) -> None:
        request = decode_request(query, ContactsRequest)
        with self._lock:
            distance = self.contacts.min_distance_m
            response = ContactsResponse(contact_count=self.contacts.count, pairs=tuple(sorted(self.contacts.pairs)),
                                        min_distance_m=distance if np.isfinite(distance) else None)
            if request.reset:
                self.contacts.reset()
        reply_ok(query, response)

    def _apply_setpoint(self) -> None:
        with self._lock:
            setpoint, self._setpoint = self._setpoint, None
        if setpoint is not None:
            q = reorder_to_robot(setpoint.position, setpoint.names, self.names, "position")
            qd = reorder_to_robot(setpoint.velocity, setpoint.names, self.names, "velocity")
            self.world.set_joint_target(q, qd)

    def _step(self) -> None:
        self._apply_setpoint()
        self.world.step()
        touching = {f"{c.link}|{c.object}" for c in self.world.robot_obstacle_contacts()}
        with self._lock:
            new = self.contacts.update(touching)
        if new:
            log.warning("robot-obstacle contact: %s", ", ".join(sorted(new)))

    def _publish_joint_state(self) -> None:
        q, qd = self.world.joint_state()
        self._joint_pub.put(JointState(stamp=time.time(), names=self.names, position=q, velocity=qd).to_wire())
        distance = self.world.min_robot_obstacle_distance_m(CLEARANCE_QUERY_RANGE_M)
        with self._lock:
            self.contacts.min_distance_m = min(self.contacts.min_distance_m, distance)

    def _publish_cloud(self, camera: CameraConfig) -> None:
        # Stamp the moment the scene is captured, not when the (slow) render ends, so the
        # joint state nearest the stamp is the pose that was rendered.
        stamp = time.time()
        frame = self.world.render_depth(camera)
        points = points_from_depth(frame.depth_m, frame.intrinsics, max_depth_m=camera.far_m)
        self._cloud_seq[camera.camera_id] += 1
        self._cloud_pubs[camera.camera_id].put(PointCloud(
            stamp=stamp, camera_id=camera.camera_id, points=np.asarray(points, dtype=np.float32),
            seq=self._cloud_seq[camera.camera_id], intrinsics=frame.intrinsics).to_wire())

    def spin(self, stop: threading.Event) -> None:
        dt = self.world.dt_s
        joint_period = 1.0 / self.cfg.sim.joint_state_rate_hz
        next_joint = 0.0
        next_camera = [0.0] * len(self.cfg.cameras)
        wall_start = time.monotonic()
        steps = 0
        while not stop.is_set():
            due_steps = int((time.monotonic() - wall_start) / dt) if self.cfg.sim.realtime else steps + 1
            for _ in range(min(due_steps - steps, MAX_CATCH_UP_STEPS)):
                self._step()
                steps += 1
            if due_steps - steps > MAX_CATCH_UP_STEPS:  # drop time we cannot catch up with
                wall_start += (due_steps - steps) * dt
            sim_t = self.world.sim_time_s
            if sim_t >= next_joint or sim_t >= min(next_camera):
                # Also right before a render, so a joint state exists for the captured pose.
                self._publish_joint_state()
                next_joint = sim_t + joint_period
            for i, camera in enumerate(self.cfg.cameras):
                if sim_t >= next_camera[i]:
                    self._publish_cloud(camera)
                    next_camera[i] = sim_t + 1.0 / camera.rate_hz
            if self.cfg.sim.realtime:
                delay = wall_start + (steps + 1) * dt - time.monotonic()
                if delay > 0:
                    time.sleep(delay)

    def close(self) -> None:
        self._queryable.undeclare()
        self._sub.undeclare()
        self._joint_pub.undeclare()
        for pub in self._cloud_pubs.values():
            pub.undeclare()
        self.world.close()


def main(argv: list[str] | None = None) -> int:
    return run_service("sim", argv, SimNode)
