"""Shared test fixtures: a Panda robot model and a 2-D point robot among axis-aligned walls."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from robonav.services.cli import use_numba_cache_dir

# As the `robonav` command does, before anything imports numba: compiled kernels go to the user's
# compile cache (or NUMBA_CACHE_DIR), never into the source tree; service processes inherit it.
NUMBA_CACHE_DIR = use_numba_cache_dir()

import numpy as np
import pytest

from robonav.pipeline.collision.spheres.table_store import use_table_store
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.services.table_cache import DirectoryTableStore

REPO_ROOT = Path(__file__).resolve().parents[1]
"""The repository's top folder."""
MBM_DIR = Path(os.environ.get("ROBONAV_MBM_DIR") or REPO_ROOT.parent / "shared" / "benchmarks" / "mbm")
"""The shared MotionBenchMaker Panda problems next to the repository (or where ROBONAV_MBM_DIR points)."""

PANDA_TEST_CONFIG = RobotConfig(
    # Open fingers (the URDF's 0.04 m limit): closed fingers touch each other.
    fixed_joint_positions={"panda_finger_joint1": 0.04, "panda_finger_joint2": 0.04},
)


@pytest.fixture(scope="session", autouse=True)
def _shared_tables(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Per-robot tables kept in one folder for the whole run, as `robonav` keeps them for its
    processes: a robot model built again (every UR5 fixture) reads what the first one built."""
    previous = use_table_store(DirectoryTableStore(tmp_path_factory.mktemp("tables")))
    yield
    use_table_store(previous)


@pytest.fixture(scope="session")
def panda() -> RobotModel:
    """pybullet_data's Panda, fingers open, every link with geometry checked, no allowed pairs."""
    return RobotModel.from_config(PANDA_TEST_CONFIG)


@dataclass(frozen=True)
class PointRobot2D:
    """A point in the unit square; `walls` are axis-aligned boxes (xmin, ymin, xmax, ymax), closed."""

    walls: tuple[tuple[float, float, float, float], ...]
    lower: np.ndarray = field(default_factory=lambda: np.zeros(2))
    upper: np.ndarray = field(default_factory=lambda: np.ones(2))

    def is_valid(self, q: np.ndarray) -> bool:
        return all(not (x0 <= q[0] <= x1 and y0 <= q[1] <= y1) for x0, y0, x1, y1 in self.walls)

    def motion_valid(self, a: np.ndarray, b: np.ndarray) -> bool:
        """Exact segment-vs-box test (slab clipping), so every sub-segment of a valid segment is valid."""
        d = b - a
        for x0, y0, x1, y1 in self.walls:
            t_in, t_out = 0.0, 1.0
            for lo, hi, p, v in ((x0, x1, a[0], d[0]), (y0, y1, a[1], d[1])):
                if abs(v) < 1e-15:
                    if p < lo or p > hi:
                        t_in, t_out = 1.0, 0.0
                    continue
                t0, t1 = sorted(((lo - p) / v, (hi - p) / v))
                t_in, t_out = max(t_in, t0), min(t_out, t1)
            if t_in <= t_out:
                return False
        return True


@pytest.fixture
def make_point_robot() -> Callable[[Sequence[tuple[float, float, float, float]]], PointRobot2D]:
    """Factory for `PointRobot2D` (test modules cannot import conftest under importlib mode)."""
    return lambda walls: PointRobot2D(tuple(tuple(w) for w in walls))
