"""One occupancy-map protocol: integrate a camera frame, free where something else is, export.

Two backends implement it: `projection.ProjectionOccupancyMap` (the default: a dense log-odds
grid cleared by projecting occupied voxels into each depth image) and `octree.OccupancyMap`
(an OctoMap tree cleared by ray casting, `perception.clearing: raycast`). The perception
service and its benchmark hold a map through this protocol only (`factory.make_occupancy_map`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Protocol

from robonav.pipeline.camera import CameraIntrinsics
from robonav.pipeline.perception.self_filter import SelfFilter
from robonav.pipeline.types import BoolArray, FloatArray, IntArray


@dataclass(frozen=True)
class CameraFrame:
    """One camera frame and where everything was when it was taken.

    Exactly one of `depth_m` and `points_camera_m` is given.
    """

    intrinsics: CameraIntrinsics
    world_from_camera: FloatArray
    """(4, 4) pose of the optical frame in the world frame."""
    world_from_link: Mapping[str, FloatArray]
    """(4, 4) pose of every robot link at the frame's stamp (for the self filter)."""
    depth_m: FloatArray | None = None
    """(H, W) depth along the optical axis [m]: +inf = nothing within range, NaN or <= 0 = no return."""
    points_camera_m: FloatArray | None = None
    """(N, 3) points in the optical frame [m]; NaN rows = no return."""
    labels: IntArray | None = None
    """(H, W) label per pixel of `depth_m` (a simulator's segmentation), or None."""

    def __post_init__(self) -> None:
        if (self.depth_m is None) == (self.points_camera_m is None):
            raise ValueError("a CameraFrame holds exactly one of depth_m and points_camera_m")


class FrameRejected(ValueError):
    """A frame this map cannot use; `reason` is the short name the service counts it under."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class OccupiedVoxels:
    """The occupied voxels of a map, for clustering."""

    ijk: IntArray
    """(N, 3) integer grid coordinates (any fixed origin)."""
    centers_m: FloatArray
    """(N, 3) voxel centers in the world frame [m]."""
    labels: IntArray | None
    """(N,) last label seen in each voxel (-1: none), or None when the map keeps no labels."""


class OccupancyBackend(Protocol):
    """What perception needs of an occupancy map."""

    @property
    def resolution_m(self) -> float:
        """Voxel edge length [m]."""
        ...

    @property
    def voxel_count(self) -> int:
        """Occupied voxels."""
        ...

    def clear(self) -> None:
        """Forget everything: every voxel becomes unknown."""
        ...

    def integrate(self, frame: CameraFrame, *, self_filter: SelfFilter, clear_filter: SelfFilter) -> dict[str, float]:
        """Fuse one frame: its returns mark voxels occupied, what it sees through turns free, and
        voxels inside `clear_filter`'s padded links are freed (only the arm can be there).

        Args:
            frame: The frame and the robot's link poses when it was taken.
            self_filter: Drops returns on the robot.
            clear_filter: Frees occupied voxels on the robot.

        Returns:
            Wall time per stage of this frame [ms].

        Raises:
            FrameRejected: a frame this map cannot use (no return at all, an unsupported kind).
            ValueError: a malformed frame.
        """
        ...

    def free_where(self, inside: Callable[[FloatArray], BoolArray]) -> int:
        """Free every occupied voxel whose center `inside` flags ((N, 3) centers [m] → (N,) mask);
        returns how many."""
        ...

    def occupied_centers_m(self) -> FloatArray:
        """(N, 3) centers of the occupied voxels in the world frame [m]."""
        ...

    def occupied_voxels(self) -> OccupiedVoxels:
        """The occupied voxels with their grid coordinates (and labels where kept)."""
        ...

    def planning_binary(self) -> bytes:
        """The occupied voxels dilated by `inflation_m`, as an OctoMap binary `.bt` file."""
        ...

