"""Obstacle clusters from occupied voxels: voxel connected components, or DBSCAN on centers.

Connected components (scipy.ndimage.label, 26-connectivity) is the default: it works on the
grid the map already has, so it costs one labelling pass. DBSCAN (open3d) is kept to compare
against (`robonav bench perception` measures both); with `eps` just above one voxel diagonal
the two give the same groups.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt
import open3d as o3d
import scipy.ndimage as ndi

from robonav.pipeline.types import FloatArray, IntArray


@dataclass(frozen=True)
class ClusterSet:
    """K clusters; arrays are indexed by cluster."""

    centroids_m: FloatArray
    """(K, 3) mean voxel center [m]."""
    bbox_min_m: FloatArray
    """(K, 3) lower corner over the voxels' faces [m]."""
    bbox_max_m: FloatArray
    """(K, 3) upper corner [m]."""
    voxel_counts: IntArray
    """(K,) voxels per cluster."""
    label_ids: IntArray
    """(K,) most frequent non-negative voxel label, -1 when none."""
    members: IntArray
    """(N,) cluster index of each input voxel, -1 for voxels in clusters below `min_voxels`."""

    @property
    def count(self) -> int:
        return int(self.voxel_counts.size)


def cluster_voxels(
    ijk: IntArray,
    centers_m: FloatArray,
    resolution_m: float,
    *,
    labels: npt.ArrayLike | None = None,
    method: Literal["components", "dbscan"] = "components",
    min_voxels: int = 3,
    support_min_voxels: int = 200,
) -> ClusterSet:
    """Group occupied voxels into clusters.

    Args:
        ijk: (N, 3) integer voxel coordinates (any common origin).
        centers_m: (N, 3) the same voxels' centers [m].
        resolution_m: Voxel edge [m].
        labels: Optional (N,) integer label per voxel (-1 for none).
        method: "components" (26-connected voxels) or "dbscan" (open3d, eps = 1.01 x the
            voxel diagonal, which links exactly the 26-neighbours).
        min_voxels: Smaller clusters are dropped (their members are -1).
        support_min_voxels: A horizontal voxel layer with at least this many voxels (and the
            most of any layer) is a supporting surface, a table top or the floor: objects resting
            on it touch it, so it is split off as its own cluster together with what lies under
            it, and the objects are grouped without it. 0 turns this off.
    """
    ijk = np.asarray(ijk, dtype=np.int64)
    centers = np.asarray(centers_m, dtype=np.float64)
    n = ijk.shape[0]
    voxel_labels = np.full(n, -1, dtype=np.int64) if labels is None else np.asarray(labels, dtype=np.int64)
    if n == 0:
        empty3 = np.empty((0, 3))
        return ClusterSet(empty3, empty3, empty3, np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.int64))
    if method not in ("components", "dbscan"):
        raise ValueError(f"method must be 'components' or 'dbscan', got {method!r}")
    support = _support(ijk, support_min_voxels)
    raw = np.empty(n, dtype=np.int64)
    offset = 0
    for part in (np.flatnonzero(support), np.flatnonzero(~support)):
        if part.size == 0:
            continue
        if method == "components":
            local = ijk[part] - ijk[part].min(axis=0)
            grid = np.zeros(tuple(local.max(axis=0) + 1), dtype=bool)
            grid[local[:, 0], local[:, 1], local[:, 2]] = True
            component, _ = ndi.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
            ids = component[local[:, 0], local[:, 1], local[:, 2]].astype(np.int64) - 1
        else:
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centers[part]))
            ids = np.asarray(cloud.cluster_dbscan(eps=1.01 * np.sqrt(3.0) * resolution_m, min_points=1), dtype=np.int64)
        raw[part] = ids + offset
        offset += int(ids.max()) + 1
    sizes = np.bincount(raw, minlength=int(raw.max()) + 1)
    kept = np.flatnonzero(sizes >= min_voxels)
    remap = np.full(sizes.size, -1, dtype=np.int64)
    remap[kept] = np.arange(kept.size)
    members = remap[raw]
    k = kept.size
    inside = members >= 0
    m, c = members[inside], centers[inside]
    counts = np.bincount(m, minlength=k)
    centroids = np.column_stack([np.bincount(m, weights=c[:, a], minlength=k) for a in range(3)]) / counts[:, None]
    half = 0.5 * resolution_m
    bbox_min = np.full((k, 3), np.inf)
    bbox_max = np.full((k, 3), -np.inf)
    np.minimum.at(bbox_min, m, c - half)
    np.maximum.at(bbox_max, m, c + half)
    label_ids = np.full(k, -1, dtype=np.int64)
    lab = voxel_labels[inside]
    has = lab >= 0
    if has.any():
        # Most frequent label per cluster: count (cluster, label) pairs.
        span = int(lab[has].max()) + 1
        packed, pair_counts = np.unique(m[has] * span + lab[has], return_counts=True)
        cluster, label = packed // span, packed % span
        order = np.lexsort((-pair_counts, cluster))
        first = order[np.r_[True, cluster[order][1:] != cluster[order][:-1]]]
        label_ids[cluster[first]] = label[first]
    return ClusterSet(centroids, bbox_min, bbox_max, counts.astype(np.int64), label_ids, members)


def support_layer(ijk: IntArray, min_voxels: int) -> tuple[int, IntArray, IntArray] | None:
    """The supporting surface's layer: where most columns end.

    The layer holding the most column tops (voxels with nothing occupied above them) is the
    top of a table or the floor, if it has at least `min_voxels` of them.

    Returns:
        (layer k, (C, 2) the (i, j) of the columns whose top is in it, (N,) for each voxel
        whether its column reaches the layer), or None when no layer has enough tops.
    """
    if min_voxels <= 0 or ijk.shape[0] == 0:
        return None
    # One int per (i, j) column: np.unique on rows (axis=0) is several times slower.
    origin = ijk[:, :2].min(axis=0)
    ij = ijk[:, :2] - origin
    width = int(ij[:, 1].max()) + 1
    columns, column_of = np.unique(ij[:, 0] * width + ij[:, 1], return_inverse=True)
    column_of = column_of.ravel()
    top = np.full(columns.shape[0], np.iinfo(np.int64).min)
    np.maximum.at(top, column_of, ijk[:, 2])
    layers, counts = np.unique(top, return_counts=True)
    best = int(np.argmax(counts))
    if counts[best] < min_voxels:
        return None
    layer = int(layers[best])
    topped = columns[top == layer]
    reaches = np.zeros(columns.shape[0], dtype=bool)
    reaches[column_of[ijk[:, 2] == layer]] = True
    return layer, np.column_stack([topped // width, topped % width]) + origin, reaches[column_of]


def _support(ijk: IntArray, min_voxels: int) -> npt.NDArray[np.bool_]:
    """The supporting surface: every voxel at or below the support layer, in a column that reaches it."""
    found = support_layer(ijk, min_voxels)
    if found is None:
        return np.zeros(ijk.shape[0], dtype=bool)
    layer, _, reaches = found
    return reaches & (ijk[:, 2] <= layer)
