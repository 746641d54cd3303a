"""How well the sim keeps real time: physics step lateness, joint-state gaps, camera frames."""

from __future__ import annotations

import collections
import time

import numpy as np

from robonav.pipeline.wire.messages import CameraStats, SimStatsResponse

MAX_SAMPLES = 240 * 600
"""Step lateness samples kept (10 minutes at 240 Hz); older ones fall out of the window."""


class LoopStats:
    """A measurement window over the physics loop; `reset` starts a new one."""

    def __init__(self, camera_ids: tuple[str, ...]) -> None:
        self._camera_ids = camera_ids
        self.reset(0.0)

    def reset(self, sim_time_s: float) -> None:
        self._wall_start = time.monotonic()
        self._sim_start = sim_time_s
        self._lateness_s: collections.deque[float] = collections.deque(maxlen=MAX_SAMPLES)
        self._dropped_s = 0.0
        self._steps = 0
        self._last_joint_state: float | None = None
        self._joint_gap_max_s = 0.0
        self._frames = dict.fromkeys(self._camera_ids, 0)
        self._last_stamp: dict[str, float] = {}
        self._period_max_s = dict.fromkeys(self._camera_ids, 0.0)
        self._render_ms: dict[str, list[float]] = {c: [] for c in self._camera_ids}

    def step(self, lateness_s: float) -> None:
        self._lateness_s.append(lateness_s)
        self._steps += 1

    def dropped(self, seconds: float) -> None:
        self._dropped_s += seconds

    def joint_state(self, now_s: float) -> None:
        if self._last_joint_state is not None:
            self._joint_gap_max_s = max(self._joint_gap_max_s, now_s - self._last_joint_state)
        self._last_joint_state = now_s

    def frame(self, camera_id: str, stamp: float) -> None:
        self._frames[camera_id] += 1
        last = self._last_stamp.get(camera_id)
        if last is not None:
            self._period_max_s[camera_id] = max(self._period_max_s[camera_id], stamp - last)
        self._last_stamp[camera_id] = stamp

    def render(self, camera_id: str, render_ms: float) -> None:
        self._render_ms[camera_id].append(render_ms)

    def report(self, sim_time_s: float) -> SimStatsResponse:
        wall_s = max(time.monotonic() - self._wall_start, 1e-9)
        lateness_ms = np.asarray(self._lateness_s, dtype=np.float64) * 1e3
        p50, p99, top = (np.percentile(lateness_ms, [50, 99, 100]).tolist() if lateness_ms.size else (0.0, 0.0, 0.0))
        cameras = tuple(CameraStats(
            camera_id=c, frames=self._frames[c],
            render_ms_p50=float(np.median(self._render_ms[c])) if self._render_ms[c] else 0.0,
            render_ms_max=max(self._render_ms[c], default=0.0),
            frame_period_ms_max=self._period_max_s[c] * 1e3) for c in self._camera_ids)
        return SimStatsResponse(
            wall_time_s=wall_s, sim_time_s=sim_time_s - self._sim_start,
            real_time_factor=(sim_time_s - self._sim_start) / wall_s, steps=self._steps,
            step_lateness_ms_p50=float(p50), step_lateness_ms_p99=float(p99), step_lateness_ms_max=float(top),
            dropped_time_s=self._dropped_s, joint_state_period_ms_max=self._joint_gap_max_s * 1e3, cameras=cameras)
