"""A reader of `perception/clusters` for the view: strict first, tolerant after.

A payload is decoded with the `Clusters` message when this version has one. Anything else (an
older or newer perception, another producer) goes to a tolerant reader that picks boxes out of
the forms a cluster message is likely to use — per-cluster maps with a center and size or with
min/max corners, or parallel arrays — and skips what it cannot read. A wrong guess costs a
missing box, never a dead view.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire import messages
from robonav.pipeline.wire.codec import ProtocolError, unpack

CENTER_KEYS = ("center_m", "center_m", "centroid_m", "position_m", "center", "centroid", "position")
SIZE_KEYS = ("size_m", "extent_m", "extents_m", "dimensions_m", "size", "extent", "extents", "dimensions")
MIN_KEYS = ("min_m", "aabb_min_m", "bbox_min_m", "min_corner_m", "lower_m", "min")
MAX_KEYS = ("max_m", "aabb_max_m", "bbox_max_m", "max_corner_m", "upper_m", "max")
QUAT_KEYS = ("quat_xyzw", "orientation_xyzw")
LABEL_KEYS = ("label", "name", "class_name", "class", "id", "cluster_id")
COUNT_KEYS = ("point_count", "num_points", "points_count", "count")
LIST_KEYS = ("clusters", "boxes", "objects", "items")


@dataclass(frozen=True)
class ClusterBox:
    """One perceived cluster as a box in the world frame."""

    label: str
    center_m: FloatArray
    """(3,) box center [m]."""
    size_m: FloatArray
    """(3,) full side lengths along the box axes [m]."""
    quat_xyzw: FloatArray
    """(4,) box orientation, scalar last."""


def as_rows(value: Any, columns: int) -> FloatArray | None:
    """A wire value (an array map `{dtype, shape, data}` or nested lists) as finite float64
    rows (N, columns), or None when it is not one."""
    if isinstance(value, Mapping):
        if not {"dtype", "shape", "data"} <= set(value):
            return None
        try:
            arr = np.frombuffer(value["data"], dtype=np.dtype(str(value["dtype"]))).reshape(value["shape"])
        except (TypeError, ValueError):
            return None
    else:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            return None
    if arr.size == 0 or arr.ndim == 0 or arr.shape[-1] != columns:
        return None
    rows = arr.reshape(-1, columns).astype(np.float64)
    return rows if np.isfinite(rows).all() else None


def _first(item: Mapping[str, Any], keys: Sequence[str], columns: int) -> FloatArray | None:
    for key in keys:
        if key in item:
            rows = as_rows(item[key], columns)
            if rows is not None:
                return rows
    return None


def _label(item: Mapping[str, Any], index: int) -> str:
    label = next((str(item[k]) for k in LABEL_KEYS if isinstance(item.get(k), (str, int))), f"cluster {index}")
    count = next((item[k] for k in COUNT_KEYS if isinstance(item.get(k), int) and not isinstance(item.get(k), bool)), None)
    return f"{label} ({count} pts)" if count is not None else label


def _box(center: FloatArray, size: FloatArray, quat: FloatArray | None, label: str) -> ClusterBox | None:
    if np.any(size < 0):
        return None
    identity = np.array([0.0, 0.0, 0.0, 1.0])
    q = identity if quat is None or np.linalg.norm(quat) < 1e-9 else quat / np.linalg.norm(quat)
    return ClusterBox(label=label, center_m=center, size_m=size, quat_xyzw=q)


def _from_item(item: Mapping[str, Any], index: int) -> ClusterBox | None:
    quat = _first(item, QUAT_KEYS, 4)
    center, size = _first(item, CENTER_KEYS, 3), _first(item, SIZE_KEYS, 3)
    if center is not None and size is not None and len(center) == len(size) == 1:
        return _box(center[0], size[0], None if quat is None else quat[0], _label(item, index))
    low, high = _first(item, MIN_KEYS, 3), _first(item, MAX_KEYS, 3)
    if low is not None and high is not None and len(low) == len(high) == 1:
        return _box((low[0] + high[0]) / 2.0, high[0] - low[0], None, _label(item, index))
    return None


def _from_arrays(message: Mapping[str, Any]) -> list[ClusterBox]:
    """Parallel arrays: `centers_m` + `sizes_m` (N, 3), or `min_m` + `max_m` (N, 3), and `labels`."""
    def rows(*keys: str) -> FloatArray | None:
        return _first(message, keys, 3)

    centers, sizes = rows("centers_m", "centroids_m", "positions_m"), rows("sizes_m", "extents_m", "dimensions_m")
    if centers is None or sizes is None or len(centers) != len(sizes):
        low, high = (rows("bbox_min_m", "mins_m", "min_m", "aabb_min_m"),
                     rows("bbox_max_m", "maxs_m", "max_m", "aabb_max_m"))
        if low is None or high is None or len(low) != len(high):
            return []
        centers, sizes = (low + high) / 2.0, high - low
    labels = message.get("labels")
    names = [str(x) for x in labels] if isinstance(labels, list) and len(labels) == len(centers) else None
    boxes = [_box(c, s, None, (names[i] if names and names[i] else f"cluster {i}"))
             for i, (c, s) in enumerate(zip(centers, sizes))]
    return [b for b in boxes if b is not None]


def _strict(payload: bytes) -> tuple[ClusterBox, ...] | None:
    """Boxes of a payload the `Clusters` message decodes, or None (no such message, or not one)."""
    cls = getattr(messages, "Clusters", None)
    if cls is None:
        return None
    try:
        clusters = cls.from_wire(payload)
        low, high = np.asarray(clusters.bbox_min_m, float), np.asarray(clusters.bbox_max_m, float)
        ids, counts, labels = list(clusters.ids), list(clusters.voxel_counts), list(clusters.labels)
    except (ProtocolError, AttributeError, TypeError, ValueError):
        return None
    boxes = []
    for i in range(len(low)):
        name = labels[i] if i < len(labels) and labels[i] else f"cluster {ids[i] if i < len(ids) else i}"
        label = f"{name} ({counts[i]} voxels)" if i < len(counts) else name
        box = _box((low[i] + high[i]) / 2.0, high[i] - low[i], None, label)
        if box is not None:
            boxes.append(box)
    return tuple(boxes)


def decode_clusters(payload: bytes) -> tuple[ClusterBox, ...]:
    """Every box found in a clusters payload; an unreadable payload gives none (never raises)."""
    strict = _strict(payload)
    if strict is not None:
        return strict
    try:
        message = unpack(payload)
    except ValueError:
        return ()
    items: Any = message
    if isinstance(message, Mapping):
        items = next((message[k] for k in LIST_KEYS if isinstance(message.get(k), list)), None)
        if items is None:
            return tuple(_from_arrays(message))
    if not isinstance(items, list):
        return ()
    boxes = [_from_item(item, i) if isinstance(item, Mapping) else None for i, item in enumerate(items)]
    return tuple(b for b in boxes if b is not None)
