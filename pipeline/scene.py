"""Collision objects of a scene: primitives and triangle meshes with a pose in the world frame."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from robonav.pipeline.config import require
from robonav.pipeline.transforms import make_transform, quat_xyzw_from_rotation
from robonav.pipeline.types import FloatArray

_CORNER_SIGNS = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64)

ObjectType = Literal["box", "cylinder", "sphere", "capsule", "mesh"]
OBJECT_TYPES: tuple[str, ...] = ("box", "cylinder", "sphere", "capsule", "mesh")


@dataclass(frozen=True, eq=False)
class SceneObject:
    """One obstacle (a primitive or a triangle mesh), posed in the world frame.

    Shapes follow the `mbm-primitives/1` conventions: a box has full side lengths `size_m`;
    a cylinder or capsule has `radius_m` and full `length_m` along its local z axis,
    centered at `position_m`; a sphere has `radius_m`. A mesh has `vertices_m` in its own
    (object) frame and `triangles` indexing them; `position_m`/`quat_xyzw` place that frame.

    Equality and hashing compare every field, mesh arrays by value (the arrays are stored
    read-only, so an object cannot change after it was hashed).
    """

    name: str
    type: ObjectType
    position_m: tuple[float, float, float]
    """Center of the primitive in the world frame [m]."""
    quat_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    """Orientation in the world frame, scalar last."""
    size_m: tuple[float, float, float] | None = None
    """Box only: full side lengths along local x, y, z [m]."""
    radius_m: float | None = None
    """Cylinder, capsule, sphere: radius [m]."""
    length_m: float | None = None
    """Cylinder, capsule: full length along local z [m]."""
    vertices_m: npt.NDArray[np.float64] | None = None
    """Mesh only: (N, 3) vertices in the object frame [m], N >= 3; stored as read-only float64."""
    triangles: npt.NDArray[np.int64] | None = None
    """Mesh only: (M, 3) vertex indices of the triangles, M >= 1; stored as read-only int64."""

    def __post_init__(self) -> None:
        require(bool(self.name), "scene object name must not be empty")
        require(self.type in OBJECT_TYPES, f"object '{self.name}': type must be one of {list(OBJECT_TYPES)}, got {self.type!r}")
        if self.type != "mesh":
            require(self.vertices_m is None and self.triangles is None,
                    f"{self.type} '{self.name}': vertices_m/triangles are for type 'mesh' only")
        if self.type == "mesh":
            self._check_mesh()
        elif self.type == "box":
            require(self.size_m is not None and all(s > 0 for s in self.size_m),
                    f"box '{self.name}' needs size_m with three positive full side lengths, got {self.size_m}")
        else:  # sphere, cylinder, capsule
            require(self.radius_m is not None and self.radius_m > 0,
                    f"{self.type} '{self.name}' needs a positive radius_m, got {self.radius_m}")
        if self.type in ("cylinder", "capsule"):
            require(self.length_m is not None and self.length_m > 0,
                    f"{self.type} '{self.name}' needs a positive length_m, got {self.length_m}")
        require(float(np.linalg.norm(self.quat_xyzw)) > 1e-9, f"object '{self.name}': quat_xyzw has zero norm")

    def _check_mesh(self) -> None:
        require(self.vertices_m is not None and self.triangles is not None,
                f"mesh '{self.name}' needs vertices_m (N, 3) and triangles (M, 3)")
        vertices = np.array(self.vertices_m, dtype=np.float64)
        raw_triangles = np.asarray(self.triangles)
        require(vertices.ndim == 2 and vertices.shape[1] == 3 and vertices.shape[0] >= 3,
                f"mesh '{self.name}': vertices_m must have shape (N >= 3, 3), got {vertices.shape}")
        bad = np.argwhere(~np.isfinite(vertices))
        require(bad.size == 0, f"mesh '{self.name}': vertices_m{bad[0].tolist() if bad.size else ''} is not finite")
        require(raw_triangles.ndim == 2 and raw_triangles.shape[1] == 3 and raw_triangles.shape[0] >= 1,
                f"mesh '{self.name}': triangles must have shape (M >= 1, 3), got {raw_triangles.shape}")
        require(raw_triangles.dtype.kind in "iu",
                f"mesh '{self.name}': triangles must be integers, got dtype {raw_triangles.dtype}")
        triangles = raw_triangles.astype(np.int64)
        out_of_range = np.argwhere((triangles < 0) | (triangles >= vertices.shape[0]))
        require(out_of_range.size == 0,
                f"mesh '{self.name}': triangles{out_of_range[0].tolist() if out_of_range.size else ''} = "
                f"{triangles[tuple(out_of_range[0])] if out_of_range.size else ''} is outside [0, {vertices.shape[0] - 1}]")
        vertices.setflags(write=False)
        triangles.setflags(write=False)
        # Frozen dataclass: normalise the arrays once so FCL, equality and hashing see one form.
        object.__setattr__(self, "vertices_m", vertices)
        object.__setattr__(self, "triangles", triangles)

    def _key(self) -> tuple[Any, ...]:
        values = []
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            values.append((value.shape, value.tobytes()) if isinstance(value, np.ndarray) else value)
        return tuple(values)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SceneObject):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    @property
    def local_bounds_m(self) -> tuple[FloatArray, FloatArray]:
        """Center (3,) and half extents (3,) of the object's axis-aligned box in its own frame [m].

        A capsule's box includes its caps; a mesh's box is that of its vertices.
        """
        if self.type == "mesh":
            assert self.vertices_m is not None  # validated in __post_init__
            low, high = self.vertices_m.min(axis=0), self.vertices_m.max(axis=0)
            return 0.5 * (low + high), 0.5 * (high - low)
        if self.type == "box":
            assert self.size_m is not None
            return np.zeros(3), 0.5 * np.array(self.size_m, dtype=np.float64)
        assert self.radius_m is not None
        if self.type == "sphere":
            return np.zeros(3), np.full(3, self.radius_m)
        assert self.length_m is not None
        cap = self.radius_m if self.type == "capsule" else 0.0
        return np.zeros(3), np.array([self.radius_m, self.radius_m, 0.5 * self.length_m + cap])

    @property
    def bounds_corners_m(self) -> FloatArray:
        """(8, 3) corners of `local_bounds_m`'s box, posed in the world frame [m]."""
        center, half = self.local_bounds_m
        pose = self.world_from_object
        return (center + half * _CORNER_SIGNS) @ pose[:3, :3].T + pose[:3, 3]

    def with_pose(self, world_from_object: FloatArray) -> SceneObject:
        """A copy of this object placed at `world_from_object` (4, 4); shape and name unchanged."""
        pose = np.asarray(world_from_object, dtype=np.float64)
        return dataclasses.replace(self, position_m=tuple(float(v) for v in pose[:3, 3]),
                                   quat_xyzw=tuple(float(v) for v in quat_xyzw_from_rotation(pose[:3, :3])))

    @property
    def world_from_object(self) -> FloatArray:
        """4x4 pose of the object in the world frame."""
        return make_transform(self.position_m, self.quat_xyzw)
