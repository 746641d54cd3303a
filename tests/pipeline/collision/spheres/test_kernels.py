"""The sphere kernels' exact cell tests: a sphere against occupied voxels, and against the occupied
cells of a finer grid nested in them (the seen surface of a map, `surface_allowance.py`)."""

from __future__ import annotations

import numpy as np
import pytest

from robonav.pipeline.collision.spheres.kernels import touches_cells, touches_voxels

VOXEL_M = 0.02
CELL_M = 0.005


def _grids(fine_index: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One occupied 2 cm voxel, [0.02, 0.04] in every axis, and one occupied 5 mm cell inside it."""
    occupied = np.zeros((3, 3, 3), dtype=np.bool_)
    occupied[1, 1, 1] = True
    fine = np.zeros((12, 12, 12), dtype=np.bool_)
    fine[fine_index] = True
    # A grid's origin is the center of its cell (0, 0, 0).
    return occupied, np.full(3, 0.5 * VOXEL_M), fine, np.full(3, 0.5 * CELL_M)


@pytest.mark.parametrize(("radius_m", "by_voxel", "by_cell"), [
    (0.009, False, False),  # short of the voxel's top face (1 cm away)
    (0.011, True, False),  # into the voxel, not near its bottom corner cell
    (0.025, True, False),  # the cell's nearest corner: 2.5 cm below the center, 0.5 cm aside in x and y: 2.6 cm
    (0.026, True, True),
])
def test_fine_cells_are_touched_only_where_the_sphere_reaches_them(radius_m: float, by_voxel: bool,
                                                                  by_cell: bool) -> None:
    occupied, origin, fine, fine_origin = _grids((4, 4, 4))  # the cell [0.02, 0.025] in every axis
    x, y, z = 0.03, 0.03, 0.05  # 1 cm above the voxel's center column
    assert touches_voxels(x, y, z, radius_m, occupied, origin, VOXEL_M) is by_voxel
    assert touches_cells(x, y, z, radius_m, occupied, origin, VOXEL_M, fine, fine_origin, CELL_M) is by_cell


def test_fine_cells_outside_every_occupied_voxel_are_not_looked_at() -> None:
    """The cells are checked inside the voxels the sphere touches only (they must lie in occupied voxels)."""
    occupied, origin, fine, fine_origin = _grids((4, 4, 4))
    occupied[1, 1, 1] = False
    assert not touches_cells(0.03, 0.03, 0.05, 0.05, occupied, origin, VOXEL_M, fine, fine_origin, CELL_M)


def test_cells_as_large_as_the_voxels_are_the_voxels() -> None:
    occupied, origin, _, _ = _grids((0, 0, 0))
    for radius_m in (0.009, 0.011):
        assert touches_cells(0.03, 0.03, 0.05, radius_m, occupied, origin, VOXEL_M, occupied, origin, VOXEL_M) \
            is touches_voxels(0.03, 0.03, 0.05, radius_m, occupied, origin, VOXEL_M)
