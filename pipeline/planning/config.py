"""Planner settings."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from robonav.pipeline.config import require


@dataclass(frozen=True)
class PlannerConfig:
    planner_id: Literal["rrtconnect", "rrt", "rrtstar", "prm", "prmstar", "bitstar", "aorrtc",
                        "astar", "dijkstra", "potential_field", "auto"] = "rrtconnect"
    """Default planner when a request names none."""
    allowed_planning_time_s: float = 2.0
    """Default planning budget per request [s]."""
    range_rad: float = 0.7
    """Longest tree extension of RRT-Connect, RRT and RRT* in joint space [rad]; 0 lets OMPL
    choose (a fifth of the joint space's extent: about 3 rad on the UR5). MotionBenchMaker, 1 s:
    the UR5's 350 problems 92.9 % solved with OMPL's choice, 97.7-98.3 % with 1.0 and 99.4 % with
    0.7 (its cages need short steps); the Panda's 100 % with 0.7 and 1.0, in 6.0 and 5.6 ms."""
    focus_margin_of_range: float = 0.25
    """RRT-Connect and RRT sample first in the box around the start and goals grown by this
    share of each joint's range, for half the search's time, then everywhere (`OmplSpace`);
    0: everywhere from the start. MotionBenchMaker, 1 s: 0.2 left two of the UR5's cages
    unsolved, 0.25 none; 1.5 rad on every joint was as fast on the UR5 (a quarter of its 2 pi)
    and a tenth slower on the Panda's maps."""
    edge_resolution_rad: float = 0.02
    """Largest joint-space step between collision checks along an edge [rad]."""
    path_check_resolution_rad: float = 0.0
    """Largest joint-space step of the exact re-check of the returned path [rad]; 0: the edge
    resolution. Finer than the edges, the search checks fewer states and the one path it returns
    is still held to the finer step (a path that fails it is not returned)."""
    simplify: bool = True
    """Shortcut the raw path (every result is re-validated)."""
    shortcut_iterations: int = 40
    shortcut_patience: int = 10
    """Stop shortcutting after this many attempts in a row that shortened nothing (0: never)."""
    sphere_first_share: float = 0.5
    """Share of the budget for the sphere-first search (0: exact search only; 1: sphere-first only)."""
    sphere_first_exact_radius_rad: float = 0.5
    """Within this joint-space distance of the start or a goal, the sphere-first search still asks
    FCL about states the spheres flag [rad]."""
    surface_allowance_rad: float = 1.0
    """Within this joint-space distance (Euclidean) of the start or a goal, a map's clearance is
    released: the padded links need only keep off what the cameras saw, so a goal near a surface
    (a grasp in a shelf) is reachable [rad]. Only against maps that come with their seen voxels
    and inflation (`CollisionWorld.set_octree(clearance_m=...)`; in the services, a map whose
    `Occupancy.inflation_m` says it, see `map_clearance_m`); 0: the inflated map everywhere."""
    release_map_clearance: bool = True
    """When no path keeps a map's clearance (shrunk near the start and goals) within the
    sphere-first share of the budget, search the rest of it for a path that keeps the padded
    links off what the cameras saw, without the clearance (`search` = "surface"). False: the
    exact search with the clearance takes the rest of the budget."""
    map_clearance_share: float = 0.3
    """With `release_map_clearance`, the share of the budget for the search that keeps the clearance."""
    start_escape_rad: float = 0.1
    """A start inside the padding around the occupancy map may be left through states that keep
    off what the cameras saw, to a valid state within this distance in every joint [rad]
    (MoveIt's FixStartStateCollision; see `start_escape`). 0: such a start is START_IN_COLLISION."""
    start_escape_samples: int = 100
    """Candidate states drawn around such a start (MoveIt's max_sampling_attempts)."""
    seed: int = 0
    """Seeds OMPL's sampler once per planner process and the shortcutting per request."""
    occupancy_max_age_s: float = 10.0
    """A plan request fails with OCCUPANCY_STALE when the newest map's stamp (its newest frame)
    is further than this from the planner's clock [s]."""
    require_occupancy: bool = True
    """Refuse to plan (OCCUPANCY_MISSING) until a first occupancy map arrived."""
    occupancy_min_frames: int = 3
    """Refuse to plan (OCCUPANCY_INCOMPLETE) until every configured camera has integrated this
    many frames into the map since the last `perception/clear` or perception start; 0: off."""
    ik_restarts: int = 20
    """Random restarts of inverse kinematics for a pose goal."""
    ik_solutions: int = 4
    """Distinct IK solutions collected into a pose goal's goal set."""
    lattice_resolution_rad: float = 0.1
    """Joint step of the A*/Dijkstra lattice [rad]."""
    report_clearance: bool = True
    """Measure the path's minimum clearance for the reply (FCL distances at 12 states)."""
    first_map_wait_s: float = 2.0
    """How long a plan request waits for the first occupancy map before OCCUPANCY_MISSING [s]."""
    workers: int = 2
    """Plans the planner service runs at once, each in a collision world of its own: a long
    request holds one worker while the others answer."""
    scene_file: str | None = None
    """The planner service saves its planning scene (`planner/scene`) here after every change and
    loads it at start, so a restarted planner keeps its objects; relative to the working directory.
    None: not saved (`robonav up` then gives each stack's planner a file of its own, and
    `robonav serve planner --scene-file FILE` overrides this)."""

    def map_clearance_m(self, inflation_m: float | None) -> float | None:
        """The clearance a map grown by `inflation_m` is planned with (`CollisionWorld.set_octree(
        clearance_m=)`): its inflation, when the map says what that is (`Occupancy.inflation_m`)
        and the planner releases it near a query's ends (`surface_allowance_rad` > 0); None: the
        inflated map is the map, everywhere."""
        if inflation_m is None or self.surface_allowance_rad <= 0:
            return None
        return float(inflation_m)

    def __post_init__(self) -> None:
        require(self.allowed_planning_time_s > 0, f"planner.allowed_planning_time_s must be > 0, got {self.allowed_planning_time_s}")
        require(self.range_rad >= 0, f"planner.range_rad must be >= 0, got {self.range_rad}")
        require(self.focus_margin_of_range >= 0,
                f"planner.focus_margin_of_range must be >= 0, got {self.focus_margin_of_range}")
        require(self.edge_resolution_rad > 0, f"planner.edge_resolution_rad must be > 0, got {self.edge_resolution_rad}")
        require(0 <= self.path_check_resolution_rad <= self.edge_resolution_rad,
                f"planner.path_check_resolution_rad must be in [0, edge_resolution_rad], got {self.path_check_resolution_rad}")
        require(self.shortcut_iterations >= 0, f"planner.shortcut_iterations must be >= 0, got {self.shortcut_iterations}")
        require(self.shortcut_patience >= 0, f"planner.shortcut_patience must be >= 0, got {self.shortcut_patience}")
        require(0 <= self.sphere_first_share <= 1,
                f"planner.sphere_first_share must be in [0, 1], got {self.sphere_first_share}")
        require(self.sphere_first_exact_radius_rad >= 0,
                f"planner.sphere_first_exact_radius_rad must be >= 0, got {self.sphere_first_exact_radius_rad}")
        require(self.workers >= 1, f"planner.workers must be >= 1, got {self.workers}")
        require(self.surface_allowance_rad >= 0,
                f"planner.surface_allowance_rad must be >= 0, got {self.surface_allowance_rad}")
        require(0 < self.map_clearance_share <= 1,
                f"planner.map_clearance_share must be in (0, 1], got {self.map_clearance_share}")
        require(self.start_escape_rad >= 0, f"planner.start_escape_rad must be >= 0, got {self.start_escape_rad}")
        require(self.start_escape_samples >= 0,
                f"planner.start_escape_samples must be >= 0, got {self.start_escape_samples}")
        require(self.ik_restarts >= 0, f"planner.ik_restarts must be >= 0, got {self.ik_restarts}")
        require(self.ik_solutions >= 1, f"planner.ik_solutions must be >= 1, got {self.ik_solutions}")
        require(self.lattice_resolution_rad > 0,
                f"planner.lattice_resolution_rad must be > 0, got {self.lattice_resolution_rad}")
        require(self.first_map_wait_s >= 0, f"planner.first_map_wait_s must be >= 0, got {self.first_map_wait_s}")
        require(self.occupancy_max_age_s > 0, f"planner.occupancy_max_age_s must be > 0, got {self.occupancy_max_age_s}")
        require(self.occupancy_min_frames >= 0, f"planner.occupancy_min_frames must be >= 0, got {self.occupancy_min_frames}")
