"""The campaign's view of the occupancy map: forgetting it, waiting for a fresh, complete or settled one."""

from __future__ import annotations

import logging
import time

from robonav.pipeline.perception.map_readiness import map_complete
from robonav.pipeline.trajectory.path_guard import map_settled
from robonav.pipeline.wire.messages import ErrorReply, PerceptionClearRequest, PerceptionClearResponse
from robonav.services.client import QueryFailed, RobonavClient
from robonav.services.config import RobonavConfig

log = logging.getLogger("robonav.campaign")


class CampaignMaps:
    """`perception/clear` and the waits for maps taken after a moment, on one client."""

    def __init__(self, cfg: RobonavConfig, client: RobonavClient) -> None:
        self.cfg = cfg
        self.client = client
        self.frame_period_s = max(1.0 / c.rate_hz for c in cfg.cameras)
        self._cameras = [c.camera_id for c in cfg.cameras]

    def clear(self) -> None:
        try:
            reply = self.client.query(self.client.keys.perception_clear, PerceptionClearRequest(),
                                      PerceptionClearResponse, 5.0)
        except QueryFailed:
            reply = None
        if reply is None or isinstance(reply, ErrorReply):
            log.warning("perception/clear failed (%s); old voxels fade as the camera sees through them", reply)

    def wait_fresh(self, after: float, frames: int = 1) -> bool:
        """Wait for a map built from frames newer than `after` (+ frames - 1 frame periods) that
        is complete (every camera's frames since a clear, as the planner requires): an emptied
        map is not free space, and the planner would refuse it (OCCUPANCY_INCOMPLETE)."""
        threshold = after + (frames - 1) * self.frame_period_s
        needed = self.cfg.planner.occupancy_min_frames

        def fresh() -> bool:
            occupancy = self.client.occupancy
            return occupancy is not None and occupancy.stamp > threshold and \
                map_complete(occupancy.camera_frames, self._cameras, needed)
        return self.client.wait_for(fresh, 10.0 + max(frames, needed) * self.frame_period_s)

    def wait_settled(self, after: float) -> None:
        """A map of frames newer than `after`, then newer maps until one adds (almost) nothing to
        the one before, as the executor does before its own replans (`executor.replan_settle_s`)."""
        if not self.wait_fresh(after):
            return
        previous = self.client.occupancy
        assert previous is not None
        deadline = time.monotonic() + self.cfg.executor.replan_settle_s
        while time.monotonic() < deadline:
            seq = previous.seq
            if not self.client.wait_for(lambda: self.client.occupancy is not None and self.client.occupancy.seq != seq,
                                        max(0.0, deadline - time.monotonic())):
                return
            current = self.client.occupancy
            assert current is not None
            if map_settled(previous.occupied_centers_m, current.occupied_centers_m, current.resolution_m):
                return
            previous = current
