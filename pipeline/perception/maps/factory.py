"""The occupancy map a perception config asks for."""

from __future__ import annotations

from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.perception.maps.octree import OccupancyMap
from robonav.pipeline.perception.maps.projection import ProjectionOccupancyMap
from robonav.pipeline.perception.maps.protocol import OccupancyBackend


def make_occupancy_map(config: PerceptionConfig) -> OccupancyBackend:
    """The backend `config.clearing` names: `projection` (the default) or `raycast`."""
    return ProjectionOccupancyMap(config) if config.clearing == "projection" else OccupancyMap(config)
