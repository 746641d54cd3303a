"""What a 3D viewer draws for the planner's scene, the occupancy map and clusters: posed primitives.

Viewers (Foxglove's SceneUpdate, viser) draw cubes, spheres and cylinders by their full extents
along local x, y, z and meshes as triangle lists. The collision shapes of `pipeline/scene.py`
follow other conventions (box full sides, radius, full length along z, capsules, indexed
meshes); this module turns one into the other, so every viewer draws the same shapes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from robonav.pipeline.transforms import rotation_from_quat_xyzw
from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire.messages import SceneObjectSpec

PrimitiveKind = Literal["cube", "sphere", "cylinder", "triangles"]
IDENTITY_QUAT_XYZW = (0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class Primitive:
    """One shape to draw, posed in `frame_id` (`world`, or the robot link an object is attached to)."""

    kind: PrimitiveKind
    frame_id: str
    position_m: tuple[float, float, float]
    """Center of the shape (cube, sphere, cylinder) or origin of the mesh frame [m]."""
    quat_xyzw: tuple[float, float, float, float]
    size_m: tuple[float, float, float]
    """Full extents along local x, y, z [m] (a cylinder's axis is local z); (1, 1, 1) for triangles."""
    points_m: FloatArray | None = None
    """Triangles only: (3K, 3) corners of K triangles in the shape's frame [m]."""


def object_primitives(obj: SceneObjectSpec, frame_id: str = "world") -> list[Primitive]:
    """The primitives that draw one collision object; a capsule is a cylinder and two spheres.

    Raises:
        ValueError: the object lacks what its type needs (a size, a radius, a mesh), or has no type.
    """
    x, y, z = (float(v) for v in (obj.position_m or (0.0, 0.0, 0.0)))
    qx, qy, qz, qw = (float(v) for v in (obj.quat_xyzw or IDENTITY_QUAT_XYZW))
    position, quat = (x, y, z), (qx, qy, qz, qw)
    frame = obj.frame_id or frame_id

    def missing(what: str) -> ValueError:
        return ValueError(f"scene object '{obj.name}' ({obj.type}) has no {what}")

    if obj.type == "box":
        if obj.size_m is None:
            raise missing("size_m")
        sx, sy, sz = (float(v) for v in obj.size_m)
        return [Primitive("cube", frame, position, quat, (sx, sy, sz))]
    if obj.type in ("sphere", "cylinder", "capsule"):
        if obj.radius_m is None:
            raise missing("radius_m")
        d = 2.0 * float(obj.radius_m)
        if obj.type == "sphere":
            return [Primitive("sphere", frame, position, quat, (d, d, d))]
        if obj.length_m is None:
            raise missing("length_m")
        length = float(obj.length_m)
        out = [Primitive("cylinder", frame, position, quat, (d, d, length))]
        if obj.type == "capsule":
            half_axis = rotation_from_quat_xyzw(quat)[:, 2] * (length / 2.0)
            for end in (np.asarray(position) + half_axis, np.asarray(position) - half_axis):
                ex, ey, ez = (float(v) for v in end)
                out.append(Primitive("sphere", frame, (ex, ey, ez), quat, (d, d, d)))
        return out
    if obj.type == "mesh":
        if obj.vertices_m is None or obj.triangles is None:
            raise missing("vertices_m and triangles")
        vertices, indices = np.asarray(obj.vertices_m, dtype=np.float64), np.asarray(obj.triangles).reshape(-1)
        if indices.size and (indices.min() < 0 or indices.max() >= len(vertices)):
            raise ValueError(f"scene object '{obj.name}': triangle indices outside its {len(vertices)} vertices")
        corners = vertices[indices]
        return [Primitive("triangles", frame, position, quat, (1.0, 1.0, 1.0), corners)]
    raise ValueError(f"scene object '{obj.name}' has no drawable type ({obj.type!r})")


def box_centers_and_sizes(bbox_min_m: FloatArray, bbox_max_m: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(N, 3) centers and (N, 3) full sizes of axis-aligned boxes given by their corners [m];
    a degenerate (flat) box keeps a sliver of 1 mm so it stays visible."""
    low = np.asarray(bbox_min_m, dtype=np.float64).reshape(-1, 3)
    high = np.asarray(bbox_max_m, dtype=np.float64).reshape(-1, 3)
    return (low + high) / 2.0, np.maximum(high - low, 1e-3)


def height_rgba(z_m: FloatArray, alpha: float = 1.0) -> FloatArray:
    """(N, 4) colors in 0..1 running from blue (lowest) through green to yellow (highest) over the
    span of `z_m` (N,), as the map is drawn in `robonav view`; one color when all are level."""
    z = np.asarray(z_m, dtype=np.float64).reshape(-1)
    span = float(z.max() - z.min()) if z.size else 0.0
    t = (z - z.min()) / span if span > 0 else np.full(z.shape, 0.5)
    # Three stops of viridis (its 0, 0.5 and 1 colors), interpolated linearly: no colormap
    # library in the pure core for a gradient this simple.
    stops = np.array([[0.267, 0.005, 0.329], [0.128, 0.567, 0.551], [0.993, 0.906, 0.144]])
    rgb = np.stack([np.interp(t, [0.0, 0.5, 1.0], stops[:, c]) for c in range(3)], axis=1)
    return np.hstack([rgb, np.full((z.size, 1), float(alpha))])
