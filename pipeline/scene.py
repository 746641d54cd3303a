"""Collision objects of a scene: primitives with a pose in the world frame."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from robonav.pipeline.config import require
from robonav.pipeline.transforms import FloatArray, make_transform


@dataclass(frozen=True)
class SceneObject:
    """One primitive obstacle, posed in the world frame.

    Shapes follow the `mbm-primitives/1` conventions: a box has full side lengths `size_m`;
    a cylinder or capsule has `radius_m` and full `length_m` along its local z axis,
    centred at `position_m`; a sphere has `radius_m`.
    """

    name: str
    type: Literal["box", "cylinder", "sphere", "capsule"]
    position_m: tuple[float, float, float]
    """Centre of the primitive in the world frame [m]."""
    quat_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    """Orientation in the world frame, scalar last."""
    size_m: tuple[float, float, float] | None = None
    """Box only: full side lengths along local x, y, z [m]."""
    radius_m: float | None = None
    """Cylinder, capsule, sphere: radius [m]."""
    length_m: float | None = None
    """Cylinder, capsule: full length along local z [m]."""

    def __post_init__(self) -> None:
        require(bool(self.name), "scene object name must not be empty")
        if self.type == "box":
            require(self.size_m is not None and all(s > 0 for s in self.size_m),
                    f"box '{self.name}' needs size_m with three positive full side lengths, got {self.size_m}")
        else:
            require(self.radius_m is not None and self.radius_m > 0,
                    f"{self.type} '{self.name}' needs a positive radius_m, got {self.radius_m}")
        if self.type in ("cylinder", "capsule"):
            require(self.length_m is not None and self.length_m > 0,
                    f"{self.type} '{self.name}' needs a positive length_m, got {self.length_m}")
        require(float(np.linalg.norm(self.quat_xyzw)) > 1e-9, f"object '{self.name}': quat_xyzw has zero norm")

    @property
    def world_from_object(self) -> FloatArray:
        """4x4 pose of the object in the world frame."""
        return make_transform(self.position_m, self.quat_xyzw)
