"""Surface clouds of primitives: every point on the surface, no large gaps, reproducible with a seed."""

from __future__ import annotations

import numpy as np
import pytest

from robonav.pipeline.evaluation.surface_sampling import sample_object_surfaces
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.transforms import transform_points

QUAT_XYZW = (0.1, -0.2, 0.3, 0.9273618)  # a generic rotation (unit norm)
SPACING_M = 0.01


def _local(obj: SceneObject, points_world: np.ndarray) -> np.ndarray:
    return transform_points(np.linalg.inv(obj.world_from_object), points_world)


def test_box_points_lie_on_its_faces_and_cover_them() -> None:
    box = SceneObject("b", "box", (0.4, -0.1, 0.3), QUAT_XYZW, size_m=(0.3, 0.2, 0.1))
    local = _local(box, sample_object_surfaces([box], spacing_m=SPACING_M, rng=np.random.default_rng(0)))
    half = 0.5 * np.array(box.size_m)
    assert np.all(np.abs(local) <= half + 1e-9)
    on_face = np.isclose(np.abs(local), half, atol=1e-9).any(axis=1)
    assert on_face.all()
    # Coverage: every point of a fine grid on the top face has a sample within 2 spacings.
    u, v = np.meshgrid(np.linspace(-half[0], half[0], 31), np.linspace(-half[1], half[1], 21))
    grid = np.column_stack([u.ravel(), v.ravel(), np.full(u.size, half[2])])
    top = local[np.isclose(local[:, 2], half[2])]
    nearest = np.min(np.linalg.norm(grid[:, None, :] - top[None, :, :], axis=2), axis=1)
    assert nearest.max() < 2 * SPACING_M


@pytest.mark.parametrize("kind", ["cylinder", "capsule"])
def test_cylinder_and_capsule_points_lie_on_their_surface(kind: str) -> None:
    obj = SceneObject("c", kind, (0.0, 0.5, 0.2), QUAT_XYZW, radius_m=0.04, length_m=0.2)  # type: ignore[arg-type]
    local = _local(obj, sample_object_surfaces([obj], spacing_m=SPACING_M, rng=np.random.default_rng(1)))
    radial = np.linalg.norm(local[:, :2], axis=1)
    if kind == "cylinder":
        on_side = np.isclose(radial, 0.04, atol=1e-9) & (np.abs(local[:, 2]) <= 0.1 + 1e-9)
        on_cap = np.isclose(np.abs(local[:, 2]), 0.1, atol=1e-9) & (radial <= 0.04 + 1e-9)
        assert (on_side | on_cap).all() and on_cap.any() and on_side.any()
    else:
        beyond = np.maximum(np.abs(local[:, 2]) - 0.1, 0.0)  # distance past the segment's ends along z
        assert np.allclose(np.hypot(radial, beyond), 0.04, atol=1e-9)


def test_sphere_points_and_seeding() -> None:
    ball = SceneObject("s", "sphere", (0.1, 0.2, 0.3), radius_m=0.05)
    first = sample_object_surfaces([ball], spacing_m=SPACING_M, rng=np.random.default_rng(3))
    again = sample_object_surfaces([ball], spacing_m=SPACING_M, rng=np.random.default_rng(3))
    np.testing.assert_array_equal(first, again)
    assert np.allclose(np.linalg.norm(first - [0.1, 0.2, 0.3], axis=1), 0.05)
    assert sample_object_surfaces([], spacing_m=SPACING_M, rng=np.random.default_rng(0)).shape == (0, 3)
    with pytest.raises(ValueError, match="spacing_m must be finite and > 0"):
        sample_object_surfaces([ball], spacing_m=0.0, rng=np.random.default_rng(0))
