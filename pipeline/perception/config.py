"""Perception settings: crop, self-filter, voxel filter and occupancy map."""

from __future__ import annotations

from dataclasses import dataclass

from robonav.pipeline.config import require


@dataclass(frozen=True)
class PerceptionConfig:
    resolution_m: float = 0.02
    """Occupancy octree leaf size [m]."""
    workspace_min_m: tuple[float, float, float] = (-1.0, -1.0, 0.005)
    """Lower corner of the crop box in the world frame [m]; points outside are dropped."""
    workspace_max_m: tuple[float, float, float] = (1.5, 1.0, 1.5)
    """Upper corner of the crop box in the world frame [m]."""
    max_range_m: float = 3.0
    """Points farther than this from the camera are dropped; rays are clipped to it [m]."""
    self_filter_padding_m: float = 0.04
    """Robot link shapes grow by this much before removing the robot's own points [m]."""
    inflation_m: float = 0.02
    """Occupied voxels are dilated by this distance in the published map [m]."""
    fill_below_surfaces: bool = False
    """Count every voxel below a seen surface, down to `workspace_min_m[2]`, as a hit.

    One camera never sees an object's far side, and OctoMap leaves that space unknown, which
    the planner treats as free. Assuming what is seen rests on solid matter (true for objects
    on a table or floor; conservative under overhangs) fills objects' unseen interiors and
    back halves. Rays that later pass through the filled space clear it as usual."""
    max_update_rate_hz: float = 10.0
    """Clouds arriving faster than this are dropped (latest-only)."""
    prob_hit: float = 0.7
    prob_miss: float = 0.4

    def __post_init__(self) -> None:
        require(self.resolution_m > 0, f"perception.resolution_m must be > 0, got {self.resolution_m}")
        for i in range(3):
            require(self.workspace_min_m[i] < self.workspace_max_m[i],
                    f"perception.workspace_min_m[{i}]={self.workspace_min_m[i]} must be < workspace_max_m[{i}]={self.workspace_max_m[i]}")
        require(self.max_range_m > 0, f"perception.max_range_m must be > 0, got {self.max_range_m}")
        require(self.self_filter_padding_m >= 0, f"perception.self_filter_padding_m must be >= 0, got {self.self_filter_padding_m}")
        require(self.inflation_m >= 0, f"perception.inflation_m must be >= 0, got {self.inflation_m}")
        require(self.max_update_rate_hz > 0, f"perception.max_update_rate_hz must be > 0, got {self.max_update_rate_hz}")
        require(0.5 < self.prob_hit < 1.0, f"perception.prob_hit must be in (0.5, 1), got {self.prob_hit}")
        require(0.0 < self.prob_miss < 0.5, f"perception.prob_miss must be in (0, 0.5), got {self.prob_miss}")
