"""Perception settings: crop, self-filter, voxel filter and occupancy map."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

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
    self_clear_padding_m: float = 0.02
    """Occupied voxels whose center lies inside the robot's links grown by this much are freed
    every frame (the robot is there now; no ray can clear what its body hides) [m]. Kept below
    the planner's robot padding + inflation: a planned motion never comes this close to a
    mapped obstacle, so passing one does not erase it (as a larger radius would, leaving a
    hole the next plan runs through). Links no planning joint moves (the base) free more: as
    far as the planner's padded check reaches from them (see `self_filter.perception_filters`)."""
    inflation_m: float = 0.02
    """Occupied voxels are dilated by this distance in the published map [m]."""
    fill_below_surfaces: bool = False
    """Count every voxel below a seen surface, down to `workspace_min_m[2]`, as a hit.

    One camera never sees an object's far side, and OctoMap leaves that space unknown, which
    the planner treats as free. Assuming what is seen rests on solid matter (true for objects
    on a table or floor; conservative under overhangs) fills objects' unseen interiors and
    back halves. Space the frame itself sees through (under a shelf board, seen through its
    opening) is not filled, and rays of later frames that pass through filled space clear it."""
    depth_edge_jump_m: float = 0.02
    """Flying pixel filter: a pixel whose depth differs from every 4-neighbour's by more than
    this (or than 4 pixel footprints, for surfaces at grazing angles) lies between surfaces,
    where cameras put "flying pixels" at depth edges, and is dropped [m]; 0 turns it off."""
    complete_support: bool = True
    """Complete the supporting surface (table top or floor) where nothing has been seen of it.

    Objects on a table and the arm itself cast shadows on it, which OctoMap leaves unknown and
    the planner treats as free: a path may then dip into the table behind the objects. The
    support layer (where most columns of the map end, `support_min_columns` of them at least)
    is taken to be flat and whole across the smallest rectangle that holds what was seen of
    it: its unknown cells there become occupied, except inside the robot. A cell a camera
    later sees through is cleared as usual and stays clear (e.g. a real gap between tables).
    The floor (the workspace's two bottom voxel layers) is never completed: the robot stands
    on it."""
    support_min_columns: int = 200
    """A horizontal layer is a supporting surface when at least this many columns end in it."""
    max_update_rate_hz: float = 30.0
    """Frames arriving faster than this are dropped (latest-only)."""
    clustering: Literal["components", "dbscan"] = "components"
    """How occupied voxels are grouped into `perception/clusters`: 26-connected components on
    the voxel grid, or open3d's DBSCAN on voxel centers."""
    cluster_min_voxels: int = 3
    """Clusters with fewer voxels are not published."""
    clusters_rate_hz: float = 5.0
    """`perception/clusters` is published at most this often."""
    prob_hit: float = 0.7
    """Occupancy probability of a voxel with a return in it; one hit makes an unknown voxel occupied."""
    prob_miss: float = 0.2
    """Occupancy probability of a voxel seen through. 0.2 frees a voxel saturated at octomap's
    clamp (0.971) after three misses: a removed object leaves the map within three frames."""
    clearing: Literal["projection", "raycast"] = "projection"
    """How free space is found: project occupied voxels into the depth image (needs clouds
    with intrinsics or depth images; cost grows with the occupied voxels), or cast every ray
    through an octomap tree (any cloud; cost grows with points x range)."""
    pixel_stride: int = 2
    """Projection: every n-th pixel in both directions becomes a return (at 2, a 640x480 frame
    gives 76,800 returns, a 4 mm spacing at 1.5 m: still several per 2 cm voxel)."""
    outlier_min_neighbors: int = 2
    """Projection: a hit voxel needs this many hit voxels among its 26 neighbours in the same
    frame, or it is dropped as an outlier (0 turns the filter off)."""
    near_m: float = 0.05
    """Projection: voxels closer to the camera than this get no free-space evidence [m]."""
    clearing_margin_m: float = 0.015
    """Projection: a voxel is seen through only if the depth behind it exceeds its own depth by
    this much: about half a voxel, plus the depth noise of the camera (a real camera needs more) [m]."""
    clearing_max_footprint_px: int = 6
    """Projection: at most this many pixels around a voxel's center are checked for a return
    in front of it (its footprint is half a voxel wide, up to this)."""
    future_stamp_tolerance_s: float = 1.0
    """A frame or joint state stamped more than this ahead of the perception service's clock is
    dropped (`future_stamp`): accepting it would make every later sample look out of order [s]."""
    stamp_jump_back_s: float = 1.0
    """A camera or joint state source whose stamps go back by more than this, for
    `STAMP_RESTART_SAMPLES` samples in a row, is taken as restarted (a driver's clock reset, a
    replay looping) and its stamps start over; a smaller step back is out of order [s]."""

    def __post_init__(self) -> None:
        require(self.resolution_m > 0, f"perception.resolution_m must be > 0, got {self.resolution_m}")
        for i in range(3):
            require(self.workspace_min_m[i] < self.workspace_max_m[i],
                    f"perception.workspace_min_m[{i}]={self.workspace_min_m[i]} must be < workspace_max_m[{i}]={self.workspace_max_m[i]}")
        require(self.max_range_m > 0, f"perception.max_range_m must be > 0, got {self.max_range_m}")
        require(self.self_filter_padding_m >= 0, f"perception.self_filter_padding_m must be >= 0, got {self.self_filter_padding_m}")
        require(0 <= self.self_clear_padding_m <= self.self_filter_padding_m,
                f"perception.self_clear_padding_m must be in [0, self_filter_padding_m], got {self.self_clear_padding_m}")
        require(self.inflation_m >= 0, f"perception.inflation_m must be >= 0, got {self.inflation_m}")
        require(self.max_update_rate_hz > 0, f"perception.max_update_rate_hz must be > 0, got {self.max_update_rate_hz}")
        require(0.5 < self.prob_hit < 1.0, f"perception.prob_hit must be in (0.5, 1), got {self.prob_hit}")
        require(0.0 < self.prob_miss < 0.5, f"perception.prob_miss must be in (0, 0.5), got {self.prob_miss}")
        require(self.clustering in ("components", "dbscan"),
                f"perception.clustering must be 'components' or 'dbscan', got {self.clustering!r}")
        require(self.depth_edge_jump_m >= 0, f"perception.depth_edge_jump_m must be >= 0, got {self.depth_edge_jump_m}")
        require(self.support_min_columns >= 1,
                f"perception.support_min_columns must be >= 1, got {self.support_min_columns}")
        require(self.cluster_min_voxels >= 1, f"perception.cluster_min_voxels must be >= 1, got {self.cluster_min_voxels}")
        require(self.clusters_rate_hz > 0, f"perception.clusters_rate_hz must be > 0, got {self.clusters_rate_hz}")
        require(self.clearing in ("projection", "raycast"),
                f"perception.clearing must be 'projection' or 'raycast', got {self.clearing!r}")
        require(self.pixel_stride >= 1, f"perception.pixel_stride must be >= 1, got {self.pixel_stride}")
        require(0 <= self.outlier_min_neighbors <= 26,
                f"perception.outlier_min_neighbors must be in [0, 26], got {self.outlier_min_neighbors}")
        require(self.near_m >= 0, f"perception.near_m must be >= 0, got {self.near_m}")
        require(self.clearing_margin_m >= 0, f"perception.clearing_margin_m must be >= 0, got {self.clearing_margin_m}")
        require(self.future_stamp_tolerance_s >= 0,
                f"perception.future_stamp_tolerance_s must be >= 0, got {self.future_stamp_tolerance_s}")
        require(self.stamp_jump_back_s > 0, f"perception.stamp_jump_back_s must be > 0, got {self.stamp_jump_back_s}")
        require(self.clearing_max_footprint_px >= 0,
                f"perception.clearing_max_footprint_px must be >= 0, got {self.clearing_max_footprint_px}")
