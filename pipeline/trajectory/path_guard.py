"""A path guard: does the rest of an executing path run into voxels that appeared after it was planned?

The executor stops (and replans) when the guard says the remaining path is blocked, e.g. an
obstacle slid into it. Rebuilding FCL's octree from every map costs 0.1-1.7 s on a loaded
2-core machine, far too slow to react, so the check has two stages. First the robot's covering
spheres (`robot_sphere_model`, which contain the link hulls) against new voxel centers in a
KD-tree: a state is suspect when a sphere comes within robot padding + inflation + half a voxel
diagonal of a voxel center. Spheres are fatter than the links, so a suspect state is then
confirmed with FCL: the padded link hulls against the suspect voxels as boxes grown by the
inflation (a superset of the planner's inflated voxels), which is at least as cautious as the
planner's hull-vs-inflated-octree check and not more. Only voxels new since `start` count: the
planner already accepted the others.

On a map the planner plans with its inflation released near a query's ends
(`PlannerConfig.map_clearance_m`), the guard releases it the same way near the path's start and
goal (`allowance_radius_rad`): the inflation shrinks in the planner's tiers toward them, to
none within the innermost, where the padded links must only keep off the new voxels. A path
that ends a centimetre from a shelf is then not stopped by a voxel of that shelf's noise, and
anything that lands on the path still stops it.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from robonav.pipeline.collision.spheres.sphere_model import robot_sphere_model
from robonav.pipeline.collision.surface_allowance import clearance_fractions
from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.lane_kinematics import LinkKinematics
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.types import FloatArray


class PathGuard:
    """Remaining-path checks against a stream of occupancy maps (voxel centers)."""

    def __init__(self, robot: RobotModel, *, padding_m: float, inflation_m: float, edge_resolution_rad: float) -> None:
        self._spheres = robot_sphere_model(robot)
        self._kinematics = LinkKinematics.from_robot(robot)
        self._padding_m = padding_m
        self._inflation_m = inflation_m
        self._confirm = CollisionWorld(robot, padding_m=padding_m, broad_phase=False)  # only its links are used
        self._resolution_rad = edge_resolution_rad
        self._baseline = np.zeros(0, dtype=np.int64)
        self._tree: cKDTree | None = None
        self._new_centers = np.zeros((0, 3))
        self._voxel_m = 0.0
        self.blocking_centers_m: FloatArray = np.zeros((0, 3))
        """The new voxels (K, 3) [m] near the state where the last confirmed `blocked_state` found
        the path blocked, at least one within the padded links' reach; empty when it found the
        path clear. What stopped a motion, for reports."""

    def warm_up(self, q: npt.ArrayLike) -> None:
        """Compile the kernels and run both stages once at `q` (n,), then forget it all: the
        first real check then costs what every later one does (compiling takes a few hundred
        milliseconds, holding the GIL). A voxel at the arm makes the FCL stage run too."""
        state = np.asarray(q, dtype=np.float64)
        hand = self._kinematics.link_poses_batch(state[None])[0, self._spheres.link_index[-1], :3, 3]
        self.start(None)
        self.update_map(hand[None], 0.02)
        self.blocked_state(np.array([state, state]), state)
        self.start(None)

    def start(self, centers_m: npt.ArrayLike | None, voxel_m: float = 0.0) -> None:
        """A path starts executing, planned on (about) this map: only voxels new since then count.

        Args:
            centers_m: (N, 3) occupied voxel centers of the map the path was planned on [m]; None: none.
            voxel_m: Voxel size of that map [m].
        """
        self._baseline = np.zeros(0, dtype=np.int64) if centers_m is None or voxel_m <= 0 else \
            np.unique(_voxel_keys(np.asarray(centers_m, dtype=np.float64), voxel_m))
        self._tree = None

    def update_map(self, centers_m: npt.ArrayLike, voxel_m: float) -> int:
        """Take a new map; returns how many of its voxels are new since `start`."""
        centers = np.asarray(centers_m, dtype=np.float64).reshape(-1, 3)
        # The baseline is sorted (np.unique): a binary search per key is ~10x faster than np.isin.
        keys = _voxel_keys(centers, voxel_m)
        at = np.minimum(np.searchsorted(self._baseline, keys), max(len(self._baseline) - 1, 0))
        new = np.ones(len(keys), dtype=bool) if len(self._baseline) == 0 else self._baseline[at] != keys
        self._new_centers = centers[new]
        self._tree = cKDTree(self._new_centers) if np.any(new) else None
        self._voxel_m = voxel_m
        return int(new.sum())

    def states_ahead(self, path: npt.ArrayLike, q_now: npt.ArrayLike, skip_rad: float = 0.05) -> FloatArray:
        """(M, n) states from a little ahead of `q_now` (on the segment it is closest to) to the path's end."""
        path_arr, q = np.asarray(path, dtype=np.float64), np.asarray(q_now, dtype=np.float64)
        if len(path_arr) < 2:
            return path_arr[-1:].copy()
        offsets = []
        for a, b in zip(path_arr[:-1], path_arr[1:]):
            d = b - a
            t = float(np.clip(np.dot(q - a, d) / max(np.dot(d, d), 1e-12), 0.0, 1.0))
            offsets.append((float(np.max(np.abs(a + t * d - q))), t))
        i = int(np.argmin([o for o, _ in offsets]))
        a, b = path_arr[i], path_arr[i + 1]
        # Start a little ahead of the arm: a stop cannot avoid what is right at the arm anyway.
        t_ahead = min(1.0, offsets[i][1] + skip_rad / max(float(np.max(np.abs(b - a))), 1e-9))
        corners = np.vstack([(a + t_ahead * (b - a))[None], path_arr[i + 1:]])
        states = [corners[0][None]]
        for c0, c1 in zip(corners[:-1], corners[1:]):
            steps = max(1, int(np.ceil(np.max(np.abs(c1 - c0)) / self._resolution_rad)))
            states.append(c0 + np.outer(np.arange(1, steps + 1) / steps, c1 - c0))
        return np.vstack(states)

    def remaining_blocked(self, path: npt.ArrayLike, q_now: npt.ArrayLike, *, allowance_radius_rad: float = 0.0) -> bool:
        """True when the path from near `q_now` to its end comes within the margin of a new voxel."""
        return self.blocked_state(path, q_now, allowance_radius_rad=allowance_radius_rad) is not None

    def blocked_state(self, path: npt.ArrayLike, q_now: npt.ArrayLike, *, confirm: bool = True,
                      allowance_radius_rad: float = 0.0) -> FloatArray | None:
        """A state from near `q_now` to the path's end whose padded links reach a new (inflated)
        voxel, or None when the rest of the path is clear. Without `confirm`, a state whose
        covering spheres come near one (the fast, more cautious stage only). With
        `allowance_radius_rad` (the planner's `surface_allowance_rad`), the inflation shrinks
        toward the path's start and goal as the planner's clearance does (module docstring).

        Suspects are confirmed deepest first (the sphere furthest inside a voxel's reach): when an
        obstacle really lands on the path that state almost always collides, so the stop is
        decided by one FCL check instead of one per grazing state before it."""
        self.blocking_centers_m = np.zeros((0, 3))
        if self._tree is None:
            return None
        states = self.states_ahead(path, q_now)
        path_arr = np.asarray(path, dtype=np.float64)
        inflation = np.full(len(states), self._inflation_m)
        if allowance_radius_rad > 0:
            ends = path_arr[[0, -1]]
            to_end = np.min(np.linalg.norm(states[:, None, :] - ends[None], axis=2), axis=1)
            inflation *= clearance_fractions(to_end, allowance_radius_rad)
        poses = self._kinematics.link_poses_batch(states)[:, self._spheres.link_index]  # (M, S, 4, 4)
        centers = np.einsum("msij,sj->msi", poses[..., :3, :3], self._spheres.centers_link_m) + poses[..., :3, 3]
        # A voxel is a cube around its center: half its diagonal more covers every point of it.
        reach = (self._spheres.radii_m[None] + self._padding_m + inflation[:, None]
                 + 0.5 * np.sqrt(3.0) * self._voxel_m)  # (M, S)
        distances, voxels = self._tree.query(centers.reshape(-1, 3), distance_upper_bound=float(reach.max()))
        gap = distances.reshape(len(states), -1) - reach
        near = gap < 0.0
        suspects = np.nonzero(np.any(near, axis=1))[0]
        if len(suspects) == 0:
            return None
        suspects = suspects[np.argsort(gap[suspects].min(axis=1), kind="stable")]
        if not confirm:
            return states[suspects[0]]
        # State by state: the voxels within reach of that state's suspect
        # spheres, as inflated boxes, against the padded links. Few voxels per state, so the
        # work stays small however many voxels are new.
        for m in suspects:
            balls = self._tree.query_ball_point(centers[m][near[m]], r=reach[m][near[m]])
            indices = np.unique(np.fromiter((i for ball in balls for i in ball), dtype=np.int64))
            if self._confirm.touches_cubes(states[m], self._new_centers[indices], self._voxel_m + 2.0 * inflation[m]):
                self.blocking_centers_m = self._new_centers[indices]
                return states[m]
        return None


def _voxel_keys(centers_m: FloatArray, voxel_m: float) -> npt.NDArray[np.int64]:
    """One int64 per voxel (21 bits per axis: +-10 km at 1 cm)."""
    ijk = np.floor(centers_m / voxel_m).astype(np.int64) + (1 << 20)
    return (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]


SETTLED_MAX_NEW_VOXELS = 2
"""A map adding at most this many voxels to the one before shows a scene at rest: depth noise
adds 0-2 per frame with the arm still; an object still moving adds its leading faces."""


def new_voxel_count(previous_centers_m: npt.ArrayLike, centers_m: npt.ArrayLike, voxel_m: float) -> int:
    """How many voxels of `centers_m` (N, 3) are not in `previous_centers_m` (M, 3), both maps
    of `voxel_m` voxels: 0 (up to sensor noise) when nothing moved in between."""
    if voxel_m <= 0:
        raise ValueError(f"voxel_m must be > 0, got {voxel_m}")
    before = _voxel_keys(np.asarray(previous_centers_m, dtype=np.float64).reshape(-1, 3), voxel_m)
    now = _voxel_keys(np.asarray(centers_m, dtype=np.float64).reshape(-1, 3), voxel_m)
    return int(np.count_nonzero(~np.isin(now, before)))


def map_settled(previous_centers_m: npt.ArrayLike, centers_m: npt.ArrayLike, voxel_m: float) -> bool:
    """Whether a map adds at most `SETTLED_MAX_NEW_VOXELS` to the one before it."""
    return new_voxel_count(previous_centers_m, centers_m, voxel_m) <= SETTLED_MAX_NEW_VOXELS
