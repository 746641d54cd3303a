"""Perception service: camera clouds → filtered world points → occupancy octree → `perception/occupancy`.

Clouds are latest-only (a ring channel of one): a slow cycle drops stale frames instead of
queueing them. The robot's own points are removed at the joint state nearest the cloud stamp.
"""

from __future__ import annotations

import bisect
import collections
import logging
import threading
import time

import numpy as np
import zenoh

from robonav.pipeline.messages import JointState, Occupancy, PointCloud
from robonav.pipeline.perception.cloud_pipeline import process_cloud_with_clearing
from robonav.pipeline.perception.occupancy import OccupancyMap
from robonav.pipeline.perception.self_filter import SelfFilter
from robonav.pipeline.robot import RobotModel
from robonav.services.common import Node, declare_latched_publisher, guarded_subscriber, run_service
from robonav.services.config import RobonavConfig
from robonav.services.keys import Keys

log = logging.getLogger("robonav.perception")

JOINT_HISTORY = 256
"""Joint states kept for matching cloud stamps (2.5 s at 100 Hz)."""
MAX_JOINT_STATE_GAP_S = 0.25
"""A cloud is used only if a joint state lies within this of its stamp [s]."""


class JointHistory:
    """Recent joint states by stamp, to pose the robot as it was when a cloud was taken."""

    def __init__(self, joint_names: tuple[str, ...]) -> None:
        self.joint_names = joint_names
        self._stamps: collections.deque[float] = collections.deque(maxlen=JOINT_HISTORY)
        self._positions: collections.deque[np.ndarray] = collections.deque(maxlen=JOINT_HISTORY)
        self._lock = threading.Lock()

    def add(self, state: JointState) -> None:
        by_name = dict(zip(state.names, state.position.tolist()))
        q = np.array([by_name[n] for n in self.joint_names])  # KeyError → dropped sample, counted
        with self._lock:
            if self._stamps and state.stamp < self._stamps[-1]:
                return  # out of order; the history must stay sorted
            self._stamps.append(state.stamp)
            self._positions.append(q)

    def nearest(self, stamp: float, *, max_gap_s: float) -> np.ndarray | None:
        """The joint positions whose stamp is nearest `stamp`, if within `max_gap_s`."""
        with self._lock:
            if not self._stamps:
                return None
            stamps = list(self._stamps)
            i = bisect.bisect_left(stamps, stamp)
            candidates = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
            best = min(candidates, key=lambda j: abs(stamps[j] - stamp))
            return self._positions[best] if abs(stamps[best] - stamp) <= max_gap_s else None


class PerceptionNode(Node):
    def __init__(self, cfg: RobonavConfig, session: zenoh.Session) -> None:
        self.cfg = cfg
        self.robot = RobotModel.from_config(cfg.robot)
        self.self_filter = SelfFilter(self.robot.link_hull_vertices, cfg.perception.self_filter_padding_m)
        self.map = OccupancyMap(cfg.perception)
        self.history = JointHistory(self.robot.joint_names)
        self.world_from_camera = {cam.camera_id: cam.world_from_camera for cam in cfg.cameras}
        self.published = 0
        self.dropped_unknown_camera = 0
        self.dropped_no_joint_state = 0
        keys = Keys(cfg.cell)
        self._pub = declare_latched_publisher(session, keys.occupancy)
        self._joint_sub = session.declare_subscriber(keys.joint_states, guarded_subscriber(self.on_joint_state, "perception"))
        self._cloud_sub = session.declare_subscriber(keys.all_camera_clouds, zenoh.handlers.RingChannel(1))
        self._cloud_errors = guarded_subscriber(self.on_cloud, "perception")

    def on_joint_state(self, sample: zenoh.Sample) -> None:
        self.history.add(JointState.from_wire(sample.payload.to_bytes()))

    def on_cloud(self, sample: zenoh.Sample) -> None:
        cloud = PointCloud.from_wire(sample.payload.to_bytes())
        world_from_camera = self.world_from_camera.get(cloud.camera_id)
        if world_from_camera is None:
            self.dropped_unknown_camera += 1
            if self.dropped_unknown_camera == 1:
                log.warning("dropping clouds from unknown camera %r (configured: %s)", cloud.camera_id,
                            list(self.world_from_camera))
            return
        q = self.history.nearest(cloud.stamp, max_gap_s=MAX_JOINT_STATE_GAP_S)
        if q is None:
            # Without the arm's pose the robot cannot be filtered out and would enter the map
            # as an obstacle around itself: better no update than that.
            self.dropped_no_joint_state += 1
            if self.dropped_no_joint_state == 1:
                log.warning("dropping clouds: no joint state within %.2f s of the cloud stamp", MAX_JOINT_STATE_GAP_S)
            return
        world_from_link = self.robot.link_poses(q)
        # Points dropped by the crop or the self-filter still clear the space their rays crossed,
        # so a moved arm or object leaves no ghost where nothing is seen behind it.
        points_world, clear_only_world, stats = process_cloud_with_clearing(
            cloud.points, world_from_camera=world_from_camera, config=self.cfg.perception,
            self_filter=self.self_filter, world_from_link=world_from_link,
        )
        self.map.insert(points_world, world_from_camera[:3, 3], clear_only_world=clear_only_world)
        # Voxels inside the robot are traces of the arm that its body now hides from every ray.
        self.map.free_voxels_where(lambda centres: ~self.self_filter.outside_mask(centres, world_from_link))
        self.published += 1
        self._pub.put(Occupancy(
            stamp=cloud.stamp, resolution_m=self.cfg.perception.resolution_m,
            octomap_binary=self.map.planning_binary(),
            occupied_centers_m=self.map.occupied_centers_m().astype(np.float32), seq=self.published,
        ).to_wire())
        if self.published == 1:
            log.info("first occupancy map: %d points kept of %d, %d voxels", stats.kept, stats.received, self.map.voxel_count)

    def spin(self, stop: threading.Event) -> None:
        min_period_s = 1.0 / self.cfg.perception.max_update_rate_hz
        last = 0.0
        while not stop.is_set():
            sample = self._cloud_sub.try_recv()
            if sample is None:
                stop.wait(0.005)
                continue
            wait_s = last + min_period_s - time.monotonic()
            if wait_s > 0:
                # Rate limit, then take whatever is newest by then (latest-only).
                stop.wait(wait_s)
                sample = self._cloud_sub.try_recv() or sample
            last = time.monotonic()
            self._cloud_errors(sample)

    def close(self) -> None:
        self._cloud_sub.undeclare()
        self._joint_sub.undeclare()
        self._pub.undeclare()


def main(argv: list[str] | None = None) -> int:
    return run_service("perception", argv, PerceptionNode)
