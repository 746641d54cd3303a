"""Perception service: camera clouds → occupancy map → `perception/occupancy` and `perception/clusters`.

Frames are latest-only per camera: a slow cycle drops stale frames instead of queueing them.
Every camera updates the same map. The robot's own points are removed at the joint state
nearest the cloud stamp. Bad frames (undecodable, unknown camera, out of order, no joint
state, no returns) and joint states (incomplete, out of order) are counted by reason
(`perception/status`) and logged once per reason. Stamps are judged by `stamps.py`: one in the
future or a source whose clock went back never wedges a camera or the joint history.
"""

from __future__ import annotations

import bisect
import collections
import logging
import threading
import time

import numpy as np
import zenoh

from robonav.pipeline.perception.clusters import cluster_voxels
from robonav.pipeline.perception.maps.factory import make_occupancy_map
from robonav.pipeline.perception.maps.protocol import FrameRejected
from robonav.pipeline.perception.self_filter import perception_filters
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.joint_order import missing_joints, positions_by_name
from robonav.pipeline.wire.messages import (
    Clusters,
    DepthImage,
    JointState,
    Occupancy,
    PerceptionClearRequest,
    PerceptionClearResponse,
    PerceptionStatusRequest,
    PerceptionStatusResponse,
    PointCloud,
)
from robonav.services.common import (
    Node,
    check_publication_size,
    declare_latched_publisher,
    decode_request,
    guarded_queryable,
    guarded_subscriber,
    reply_ok,
    run_service,
)
from robonav.services.config import RobonavConfig, perceived_world_from_camera
from robonav.services.keys import Keys
from robonav.services.perception.frames import camera_frame
from robonav.services.perception.stamps import OK, RESTART, StampOrder
from robonav.services.perception.warm_up import warm_up_perception

log = logging.getLogger("robonav.perception")

JOINT_HISTORY = 256
"""Joint states kept for matching cloud stamps (2.5 s at 100 Hz)."""
MAX_JOINT_STATE_GAP_S = 0.25
"""A cloud is used only if a joint state lies within this of its stamp [s]."""


class JointHistory:
    """Recent joint states by stamp, to pose the robot as it was when a cloud was taken."""

    def __init__(self, joint_names: tuple[str, ...], *, future_tolerance_s: float = 1.0,
                 jump_back_s: float = 1.0) -> None:
        self.joint_names = joint_names
        self._stamps: collections.deque[float] = collections.deque(maxlen=JOINT_HISTORY)
        self._positions: collections.deque[np.ndarray] = collections.deque(maxlen=JOINT_HISTORY)
        self._order = StampOrder(future_tolerance_s, jump_back_s, allow_equal=True)
        self._lock = threading.Lock()

    def add(self, state: JointState, now_s: float | None = None) -> str:
        """Keep `state` if it fits the history (`stamps.py`). Returns `OK`, `RESTART` (the source's
        stamps started over: the older history was dropped), or why it was dropped:
        `incomplete` (it lacks a planning joint), `future_stamp`, `out_of_order`, `jumped_back`."""
        q = positions_by_name(state.names, state.position, self.joint_names)
        if q is None:
            return "incomplete"
        with self._lock:
            verdict = self._order.judge(state.stamp, time.time() if now_s is None else now_s)
            if verdict == RESTART:
                self._stamps.clear()
                self._positions.clear()
            elif verdict != OK:
                return verdict
            self._stamps.append(state.stamp)
            self._positions.append(q)
            return verdict

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


class Drops:
    """Frames (and joint states, `joint_state_*`) not used, counted by reason; each reason is logged once."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}
        self._lock = threading.Lock()

    def add(self, reason: str, detail: str) -> None:
        with self._lock:
            self.counts[reason] = self.counts.get(reason, 0) + 1
            first = self.counts[reason] == 1
        if first:
            what = "a joint state" if reason.startswith("joint_state_") else "a frame"
            log.warning("dropping %s (%s: %s); further ones of this kind are counted silently", what, reason, detail)


class PerceptionNode(Node):
    def __init__(self, cfg: RobonavConfig, session: zenoh.Session) -> None:
        self.cfg = cfg
        self.robot = RobotModel.from_config(cfg.robot)
        self.self_filter, self.clear_filter = perception_filters(
            self.robot.link_hull_vertices, self.robot.static_link_names, cfg.perception, cfg.robot.padding_m)
        self.map = make_occupancy_map(cfg.perception)
        self.history = JointHistory(self.robot.joint_names, future_tolerance_s=cfg.perception.future_stamp_tolerance_s,
                                    jump_back_s=cfg.perception.stamp_jump_back_s)
        self.cameras = {cam.camera_id: cam for cam in cfg.cameras}
        self.world_from_camera = {cam.camera_id: perceived_world_from_camera(cam) for cam in cfg.cameras}
        self.frames = 0
        self.camera_frames = {cam.camera_id: 0 for cam in cfg.cameras}
        """Frames integrated per camera since the last clear or the start: an empty map is not free space."""
        self.published = 0
        self.drops = Drops()
        self.last_stage_ms: dict[str, float] = {}
        self._order = {cam.camera_id: StampOrder(cfg.perception.future_stamp_tolerance_s, cfg.perception.stamp_jump_back_s)
                       for cam in cfg.cameras}
        """Each camera's stamp order (`stamps.py`)."""
        self._last_stamp: dict[str, float] = {}
        """Each camera's newest integrated frame stamp [s]."""
        self._clock_offset_s: dict[str, float] = {}
        """Each camera's receive time minus frame stamp at its last integrated frame [s]: its latency,
        plus how far its clock is behind ours (a replay: hours)."""
        self._cleared_at = -np.inf
        """Wall time of the last perception/clear: frames taken before it are dropped."""
        self._clear_cutoff: dict[str, float] = {}
        """Per camera, the last clear in that camera's clock (for one whose clock is far from ours)."""
        self._newest_stamp = 0.0
        self._label_names: dict[int, str] = {}
        # Before any frame arrives, and before the service is alive: the first frame costs what any other does.
        warm_up_perception(cfg, self.robot, self.self_filter, self.clear_filter)
        self._pending: dict[str, zenoh.Sample] = {}  # latest unprocessed frame per key
        self._pending_lock = threading.Lock()
        self._wake = threading.Event()
        self._map_lock = threading.Lock()
        self._last_clusters = 0.0
        keys = Keys(cfg.cell)
        self._pub = declare_latched_publisher(session, keys.occupancy)
        self._clusters_pub = session.declare_publisher(keys.clusters)
        self._joint_sub = session.declare_subscriber(keys.joint_states, guarded_subscriber(self.on_joint_state, "perception"))
        self._cloud_sub = session.declare_subscriber(keys.all_camera_clouds, self.on_frame)
        self._depth_sub = session.declare_subscriber(keys.all_camera_depths, self.on_frame)
        self._queryables = [
            session.declare_queryable(keys.perception_clear, guarded_queryable(self.handle_clear, "perception")),
            session.declare_queryable(keys.perception_status, guarded_queryable(self.handle_status, "perception")),
        ]

    def on_joint_state(self, sample: zenoh.Sample) -> None:
        state = JointState.from_wire(sample.payload.to_bytes())
        verdict = self.history.add(state)
        if verdict == RESTART:
            log.warning("joint state stamps went back to %.3f: the source restarted; the joint history starts over",
                        state.stamp)
        elif verdict != OK:
            detail = (f"lacks joints {missing_joints(state.names, self.robot.joint_names)}" if verdict == "incomplete"
                      else f"stamp {state.stamp:.3f}, clock {time.time():.3f}")
            self.drops.add(f"joint_state_{verdict}", detail)

    def on_frame(self, sample: zenoh.Sample) -> None:
        """Keep only the newest frame of each camera: a slow cycle skips frames, never queues them."""
        key = str(sample.key_expr)
        try:
            check_publication_size(sample)
        except ProtocolError as exc:
            self.drops.add("too_large", exc.message)
            return
        with self._pending_lock:
            if key in self._pending:
                self.drops.add("stale", f"a newer frame replaced an unprocessed one on {key}")
            self._pending[key] = sample
        self._wake.set()

    def handle_clear(self, query: zenoh.Query) -> None:
        decode_request(query, PerceptionClearRequest)
        with self._map_lock:
            cleared = self.map.voxel_count
            self.map.clear()
            self.camera_frames = dict.fromkeys(self.camera_frames, 0)
            # A frame taken before now (pending, or on its way) shows the world as it was: after
            # a scene change it would put the old objects back into the emptied map. A camera whose
            # clock is far from ours (a replay) gets the moment in its own clock.
            self._cleared_at = time.time()
            tolerance_s = self.cfg.perception.stamp_jump_back_s
            self._clear_cutoff = {camera: self._cleared_at - offset for camera, offset in self._clock_offset_s.items()
                                  if abs(offset) > tolerance_s}
        reply_ok(query, PerceptionClearResponse(cleared_voxels=cleared))
        self._publish()

    def handle_status(self, query: zenoh.Query) -> None:
        decode_request(query, PerceptionStatusRequest)
        with self._map_lock:
            voxels = self.map.voxel_count
            camera_frames = dict(self.camera_frames)
        reply_ok(query, PerceptionStatusResponse(frames=self.frames, published=self.published,
                                                 dropped=dict(self.drops.counts), occupied_voxels=voxels,
                                                 stage_ms=dict(self.last_stage_ms), camera_frames=camera_frames))

    def _taken_before_clear(self, cloud: PointCloud | DepthImage) -> bool:
        """Whether the frame predates the last perception/clear (then counted as dropped)."""
        if cloud.stamp > self._clear_cutoff.get(cloud.camera_id, self._cleared_at):
            return False
        self.drops.add("before_clear", f"camera {cloud.camera_id!r} frame taken before the last perception/clear")
        return True

    def process(self, sample: zenoh.Sample) -> bool:
        """Integrate one frame; False (and counted) when it was dropped."""
        is_depth = str(sample.key_expr).endswith("/depth")
        try:
            cloud = (DepthImage if is_depth else PointCloud).from_wire(sample.payload.to_bytes())
        except Exception as exc:
            self.drops.add("bad_message", f"{sample.key_expr}: {exc}")
            return False
        camera = self.cameras.get(cloud.camera_id)
        if camera is None:
            self.drops.add("unknown_camera", f"{cloud.camera_id!r} (configured: {sorted(self.cameras)})")
            return False
        if not self._in_order(cloud) or self._taken_before_clear(cloud):
            return False
        q = self.history.nearest(cloud.stamp, max_gap_s=MAX_JOINT_STATE_GAP_S)
        if q is None:
            # Without the arm's pose the robot cannot be filtered out and would enter the map
            # as an obstacle around itself: better no update than that.
            self.drops.add("no_joint_state", f"no joint state within {MAX_JOINT_STATE_GAP_S} s of the cloud stamp")
            return False
        self._last_stamp[cloud.camera_id] = cloud.stamp
        self._clock_offset_s[cloud.camera_id] = time.time() - cloud.stamp
        if cloud.label_names:
            self._label_names.update(cloud.label_names)
        frame = camera_frame(cloud, camera, self.world_from_camera[cloud.camera_id], self.robot, q)
        with self._map_lock:
            if self._taken_before_clear(cloud):  # cleared while this frame was being prepared
                return False
            try:
                self.last_stage_ms = self.map.integrate(frame, self_filter=self.self_filter,
                                                        clear_filter=self.clear_filter)
            except FrameRejected as exc:
                self.drops.add(exc.reason, f"camera {cloud.camera_id!r}: {exc}")
                return False
            self.camera_frames[cloud.camera_id] += 1
        # The newest frame of any camera (not of all time: a camera whose clock went back moves it back).
        self._newest_stamp = max(self._last_stamp.values())
        self.frames += 1
        return True

    def _in_order(self, cloud: PointCloud | DepthImage) -> bool:
        """The camera's stamp rules (`stamps.py`); a dropped frame is counted."""
        order = self._order[cloud.camera_id]
        last = order.last
        verdict = order.judge(cloud.stamp, time.time())
        if verdict == OK:
            return True
        if verdict == RESTART:
            # A restarted camera's frames are new, whatever its clock says about the last clear.
            log.warning("camera %r: stamps went back from %.3f to %.3f; taking it as restarted", cloud.camera_id,
                        last, cloud.stamp)
            self._clear_cutoff[cloud.camera_id] = -np.inf
            return True
        if verdict in ("out_of_order", "jumped_back") and self._taken_before_clear(cloud):
            return False  # counted as before_clear: what it shows was cleared
        why = {"future_stamp": f"{cloud.stamp - time.time():.3f} s ahead of this host's clock",
               "jumped_back": f"{(last or 0.0) - cloud.stamp:.3f} s before the camera's newest frame",
               "out_of_order": f"not newer than the camera's newest frame {last}"}.get(verdict, "")
        self.drops.add(verdict, f"camera {cloud.camera_id!r} stamp {cloud.stamp:.3f}: {why}")
        return False

    def _publish(self) -> None:
        t0 = time.perf_counter()
        with self._map_lock:
            binary = self.map.planning_binary()
            centers = self.map.occupied_centers_m().astype(np.float32)
            clusters = self._clusters() if self._clusters_due() else None
            camera_frames = dict(self.camera_frames)
        self.published += 1
        self._pub.put(Occupancy(stamp=self._newest_stamp, resolution_m=self.cfg.perception.resolution_m,
                                octomap_binary=binary, occupied_centers_m=centers, seq=self.published,
                                camera_frames=camera_frames, inflation_m=self.cfg.perception.inflation_m).to_wire())
        if clusters is not None:
            self._clusters_pub.put(clusters.to_wire())
        self.last_stage_ms["publish"] = (time.perf_counter() - t0) * 1e3
        if self.published == 1:
            log.info("first occupancy map: %d voxels", centers.shape[0])

    def _clusters_due(self) -> bool:
        now = time.monotonic()
        if now - self._last_clusters < 1.0 / self.cfg.perception.clusters_rate_hz:
            return False
        self._last_clusters = now
        return True

    def _clusters(self) -> Clusters:
        voxels = self.map.occupied_voxels()
        found = cluster_voxels(voxels.ijk, voxels.centers_m, self.cfg.perception.resolution_m, labels=voxels.labels,
                               method=self.cfg.perception.clustering, min_voxels=self.cfg.perception.cluster_min_voxels)
        names = tuple(self._label_names.get(int(i), "") for i in found.label_ids)
        return Clusters(stamp=self._newest_stamp, ids=np.arange(found.count, dtype=np.int32),
                        centroids_m=found.centroids_m.astype(np.float32), bbox_min_m=found.bbox_min_m.astype(np.float32),
                        bbox_max_m=found.bbox_max_m.astype(np.float32), voxel_counts=found.voxel_counts.astype(np.int32),
                        labels=names, seq=self.published)

    def _take_pending(self) -> zenoh.Sample | None:
        with self._pending_lock:
            if not self._pending:
                return None
            key = next(iter(self._pending))  # insertion order: the camera waiting longest
            return self._pending.pop(key)

    def spin(self, stop: threading.Event) -> None:
        min_period_s = 1.0 / self.cfg.perception.max_update_rate_hz
        last = 0.0
        while not stop.is_set():
            sample = self._take_pending()
            if sample is None:
                self._wake.wait(0.05)
                self._wake.clear()
                continue
            wait_s = last + min_period_s - time.monotonic()
            if wait_s > 0:
                stop.wait(wait_s)  # rate limit; a newer frame may replace this one meanwhile
                with self._pending_lock:
                    sample = self._pending.pop(str(sample.key_expr), sample)
            last = time.monotonic()
            try:
                if self.process(sample):
                    self._publish()
            except Exception:  # a service never dies on input
                log.exception("perception: frame failed")
                self.drops.add("internal_error", "see the log")

    def close(self) -> None:
        for q in self._queryables:
            q.undeclare()
        self._cloud_sub.undeclare()
        self._depth_sub.undeclare()
        self._joint_sub.undeclare()
        self._clusters_pub.undeclare()
        self._pub.undeclare()


def main(argv: list[str] | None = None) -> int:
    return run_service("perception", argv, PerceptionNode)
