"""The map's grids for the sphere broad phase: per voxel, the box of its surface cells."""

from __future__ import annotations

import numpy as np

from robonav.pipeline.collision.spheres.grid_layers import cell_boxes, cell_layer, voxel_layer

VOXEL_M, CELL_M = 0.02, 0.005


def test_each_voxels_box_holds_exactly_its_cells() -> None:
    rng = np.random.default_rng(3)
    ratio = round(VOXEL_M / CELL_M)
    voxels = np.unique(rng.integers(-4, 5, size=(40, 3)), axis=0)
    cells = [v * ratio + rng.integers(0, ratio, size=(int(rng.integers(1, 6)), 3)) for v in voxels[:-5]]
    keys = np.vstack(cells)  # the last five voxels hold no cell
    coarse = voxel_layer(voxels, VOXEL_M, 2, np.full(3, 0.5 * VOXEL_M))
    fine = cell_layer(keys, CELL_M)
    slot, boxes = cell_boxes(fine, coarse)
    low_cell = np.round((fine.origin - 0.5 * CELL_M) / CELL_M).astype(np.int64)  # fine index 0 as a grid key
    for i, voxel in enumerate(voxels):
        row = slot[tuple(np.round((voxel * VOXEL_M + 0.5 * VOXEL_M - coarse.origin) / VOXEL_M).astype(int))]
        if i >= len(voxels) - 5:
            assert row == -1
            continue
        mine = np.unique(cells[i], axis=0)
        np.testing.assert_array_equal(boxes[row, :3] + low_cell, mine.min(axis=0))
        np.testing.assert_array_equal(boxes[row, 3:] + low_cell, mine.max(axis=0))
    assert np.count_nonzero(slot >= 0) == len(voxels) - 5
