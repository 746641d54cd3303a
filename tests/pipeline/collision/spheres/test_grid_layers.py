"""The map's grids for the sphere broad phase: per voxel, the box of its surface cells; the distance
field raised to those boxes."""

from __future__ import annotations

import numpy as np

from robonav.pipeline.collision.spheres.grid_layers import cell_boxes, cell_layer, field_to_cell_boxes, voxel_layer
from robonav.pipeline.collision.spheres.kernels import voxel_distance

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


def test_the_field_raised_to_the_cell_boxes_still_bounds_the_distance_to_the_cells() -> None:
    """Slabs of cells across random voxels (a seen surface): at random points the raised field's
    lookup never exceeds the distance to the nearest cell cube, and is tighter than the voxels'."""
    rng = np.random.default_rng(5)
    ratio = round(VOXEL_M / CELL_M)
    voxels = np.unique(rng.integers(-5, 6, size=(60, 3)), axis=0)
    cells = []
    for v in voxels:
        slab = np.argwhere(np.ones((ratio, ratio), dtype=bool))
        cells.append(v * ratio + np.insert(slab, int(rng.integers(3)), int(rng.integers(ratio)), axis=1))
    keys = np.vstack(cells)
    coarse = voxel_layer(voxels, VOXEL_M, 8, np.full(3, 0.5 * VOXEL_M))
    fine = cell_layer(keys, CELL_M)
    slot, boxes = cell_boxes(fine, coarse)
    reach = 0.08
    raised = field_to_cell_boxes(coarse, fine, slot, boxes, reach)
    assert np.all(raised.field >= coarse.field)
    lows = keys * CELL_M
    gained = []
    for p in rng.uniform(-0.2, 0.2, size=(3000, 3)):
        gap = np.maximum(np.maximum(lows - p, p - (lows + CELL_M)), 0.0)
        distance = float(np.sqrt((gap ** 2).sum(axis=1)).min())
        before = voxel_distance(*p, coarse.field, coarse.origin, VOXEL_M, coarse.box)
        after = voxel_distance(*p, raised.field, raised.origin, VOXEL_M, raised.box)
        assert after <= distance + 1e-12
        if distance < reach:
            gained.append(after - before)
    assert len(gained) > 500 and np.median(gained) > 0.25 * VOXEL_M
