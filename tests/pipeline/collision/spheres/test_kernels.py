"""The sphere kernels' exact cell tests: a sphere against occupied voxels, and against the occupied
cells of a finer grid nested in them (the seen surface of a map, `surface_allowance.py`)."""

from __future__ import annotations

import numpy as np
import pytest

from robonav.pipeline.collision.spheres.grid_layers import column_ranges
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


def _boxes(occupied: np.ndarray, fine: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The voxels' rows of cell boxes and the boxes (`touches_cells`), by a loop over the voxels."""
    ratio = round(VOXEL_M / CELL_M)
    slot = np.full(occupied.shape, -1, dtype=np.int32)
    boxes = []
    for voxel in np.argwhere(occupied):
        block = fine[tuple(slice(v * ratio, (v + 1) * ratio) for v in voxel)]
        cells = np.argwhere(block) + voxel * ratio
        if len(cells):
            slot[tuple(voxel)] = len(boxes)
            boxes.append(np.concatenate([cells.min(axis=0), cells.max(axis=0)]))
    return slot, np.array(boxes, dtype=np.int64).reshape(-1, 6)


def _touches_cells(x: float, y: float, z: float, radius_m: float, occupied: np.ndarray, origin: np.ndarray,
                   fine: np.ndarray, fine_origin: np.ndarray) -> bool:
    slot, boxes = _boxes(occupied, fine)
    return touches_cells(x, y, z, radius_m, occupied, origin, VOXEL_M, fine, fine_origin, CELL_M, slot, boxes,
                         column_ranges(slot >= 0))


def _touches_voxels(x: float, y: float, z: float, radius_m: float, occupied: np.ndarray, origin: np.ndarray) -> bool:
    return touches_voxels(x, y, z, radius_m, occupied, origin, VOXEL_M, column_ranges(occupied))


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
    assert _touches_voxels(x, y, z, radius_m, occupied, origin) is by_voxel
    assert _touches_cells(x, y, z, radius_m, occupied, origin, fine, fine_origin) is by_cell


def test_fine_cells_outside_every_occupied_voxel_are_not_looked_at() -> None:
    """The cells are checked inside the voxels the sphere touches only (they must lie in occupied voxels)."""
    occupied, origin, fine, fine_origin = _grids((4, 4, 4))
    occupied[1, 1, 1] = False
    assert not _touches_cells(0.03, 0.03, 0.05, 0.05, occupied, origin, fine, fine_origin)


def test_cells_as_large_as_the_voxels_are_the_voxels() -> None:
    occupied, origin, _, _ = _grids((0, 0, 0))
    for radius_m in (0.009, 0.011):
        assert touches_cells(0.03, 0.03, 0.05, radius_m, occupied, origin, VOXEL_M, occupied, origin, VOXEL_M,
                             np.full((1, 1, 1), -1, dtype=np.int32), np.zeros((0, 6), dtype=np.int64),
                             column_ranges(occupied)) is _touches_voxels(0.03, 0.03, 0.05, radius_m, occupied, origin)


def test_cell_boxes_give_the_answers_of_every_cell() -> None:
    """Random surface slabs in random voxels, random spheres: a sphere touches the cells (box
    first, then the cells in it) exactly when one cell is within its radius, cube by cube."""
    rng = np.random.default_rng(7)
    ratio = round(VOXEL_M / CELL_M)
    occupied = rng.random((6, 6, 6)) < 0.3
    fine = np.zeros((6 * ratio,) * 3, dtype=np.bool_)
    for voxel in np.argwhere(occupied):
        # A slab one cell thick across the voxel, along a random axis (a seen surface), sometimes a lone cell.
        block = np.zeros((ratio,) * 3, dtype=np.bool_)
        if rng.random() < 0.8:
            axis, layer = int(rng.integers(3)), int(rng.integers(ratio))
            np.moveaxis(block, axis, 0)[layer] = True
        else:
            block[tuple(rng.integers(ratio, size=3))] = True
        fine[tuple(slice(v * ratio, (v + 1) * ratio) for v in voxel)] = block
    origin, fine_origin = np.full(3, 0.5 * VOXEL_M), np.full(3, 0.5 * CELL_M)
    lows = np.argwhere(fine) * CELL_M
    slot, boxes = _boxes(occupied, fine)
    column = column_ranges(slot >= 0)
    touching = 0
    for x, y, z, radius_m in np.column_stack([rng.uniform(-0.02, 0.14, size=(2000, 3)), rng.uniform(0.0, 0.05, 2000)]):
        gap = np.maximum(np.maximum(lows - (x, y, z), (x, y, z) - (lows + CELL_M)), 0.0)
        distance = float(np.sqrt((gap ** 2).sum(axis=1)).min())
        if abs(distance - radius_m) < 1e-9:
            continue  # touching within rounding: either answer is right
        exact = bool(distance <= radius_m)
        touching += exact
        assert touches_cells(x, y, z, radius_m, occupied, origin, VOXEL_M, fine, fine_origin, CELL_M, slot, boxes,
                             column) is exact
    assert 200 < touching < 1800


def test_voxels_give_the_answers_of_every_cube() -> None:
    """Random voxels in columns of random extent (some empty, some with gaps), random spheres: a
    sphere touches the voxels exactly when one cube is within its radius."""
    rng = np.random.default_rng(8)
    occupied = np.zeros((8, 8, 10), dtype=np.bool_)
    for i, j in np.ndindex(8, 8):
        if rng.random() < 0.6:
            low = int(rng.integers(10))
            occupied[i, j, low:low + int(rng.integers(1, 5))] = True
            occupied[i, j, int(rng.integers(10))] = rng.random() < 0.3
    origin = np.full(3, 0.5 * VOXEL_M)
    lows = np.argwhere(occupied) * VOXEL_M
    column = column_ranges(occupied)
    touching = 0
    for x, y, z, radius_m in np.column_stack([rng.uniform(-0.03, 0.2, size=(2000, 3)), rng.uniform(0.0, 0.05, 2000)]):
        gap = np.maximum(np.maximum(lows - (x, y, z), (x, y, z) - (lows + VOXEL_M)), 0.0)
        distance = float(np.sqrt((gap ** 2).sum(axis=1)).min())
        if abs(distance - radius_m) < 1e-9:
            continue
        exact = bool(distance <= radius_m)
        touching += exact
        assert touches_voxels(x, y, z, radius_m, occupied, origin, VOXEL_M, column) is exact
    assert 200 < touching < 1800


def test_column_ranges_hold_every_occupied_voxel() -> None:
    held = np.zeros((2, 3, 5), dtype=np.bool_)
    held[0, 0, [1, 3]] = True
    held[1, 2, 4] = True
    column = column_ranges(held)
    assert column[0, 0].tolist() == [1, 3] and column[1, 2].tolist() == [4, 4]
    assert column[0, 1].tolist() == [5, -1]  # none: an empty range
