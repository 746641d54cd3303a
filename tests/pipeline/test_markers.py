"""Scene objects, boxes and heights as the primitives viewers draw (full extents, triangle lists)."""

from __future__ import annotations

import numpy as np
import pytest

from robonav.pipeline.markers import box_centers_and_sizes, height_rgba, object_primitives
from robonav.pipeline.transforms import quat_xyzw_from_rotation
from robonav.pipeline.wire.messages import SceneObjectSpec


def test_primitives_use_full_extents() -> None:
    (box,) = object_primitives(SceneObjectSpec("b", "box", (1.0, 2.0, 3.0), size_m=(0.1, 0.2, 0.3)))
    assert (box.kind, box.frame_id, box.position_m, box.quat_xyzw, box.size_m) == (
        "cube", "world", (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), (0.1, 0.2, 0.3))
    (sphere,) = object_primitives(SceneObjectSpec("s", "sphere", (0.0, 0.0, 0.0), radius_m=0.05))
    assert sphere.size_m == pytest.approx((0.1, 0.1, 0.1))
    (cylinder,) = object_primitives(SceneObjectSpec("c", "cylinder", (0.0, 0.0, 0.0), radius_m=0.05, length_m=0.4),
                                    frame_id="panda_hand")
    assert (cylinder.kind, cylinder.frame_id, cylinder.size_m) == ("cylinder", "panda_hand", pytest.approx((0.1, 0.1, 0.4)))


def test_a_capsule_is_a_cylinder_with_spheres_on_its_axis() -> None:
    # Lying along world x: local z turned onto x by a quarter turn about y.
    quat = tuple(quat_xyzw_from_rotation(np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])).tolist())
    shapes = object_primitives(SceneObjectSpec("cap", "capsule", (1.0, 0.0, 0.5), quat, radius_m=0.1, length_m=0.6))
    assert [s.kind for s in shapes] == ["cylinder", "sphere", "sphere"]
    ends = sorted(s.position_m for s in shapes[1:])
    np.testing.assert_allclose(ends, [[0.7, 0.0, 0.5], [1.3, 0.0, 0.5]], atol=1e-12)
    assert shapes[1].size_m == pytest.approx((0.2, 0.2, 0.2))


def test_a_mesh_becomes_its_triangle_corners() -> None:
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    (mesh,) = object_primitives(SceneObjectSpec("m", "mesh", (0.0, 0.0, 1.0), vertices_m=vertices,
                                                triangles=np.array([[0, 1, 2], [0, 2, 3]])))
    assert mesh.kind == "triangles" and mesh.points_m is not None
    np.testing.assert_array_equal(mesh.points_m, vertices[[0, 1, 2, 0, 2, 3]])


@pytest.mark.parametrize(("spec", "message"), [
    (SceneObjectSpec("b", "box", (0.0, 0.0, 0.0)), "size_m"),
    (SceneObjectSpec("c", "cylinder", (0.0, 0.0, 0.0), radius_m=0.1), "length_m"),
    (SceneObjectSpec("m", "mesh", (0.0, 0.0, 0.0), vertices_m=np.zeros((3, 3)), triangles=np.array([[0, 1, 3]])),
     "outside"),
    (SceneObjectSpec("x", None, (0.0, 0.0, 0.0)), "no drawable type"),
])
def test_incomplete_objects_fail_clearly(spec: SceneObjectSpec, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        object_primitives(spec)


def test_boxes_from_corners_keep_flat_ones_visible() -> None:
    centers, sizes = box_centers_and_sizes(np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]),
                                           np.array([[2.0, 4.0, 6.0], [1.0, 2.0, 3.0]]))
    np.testing.assert_allclose(centers, [[1.0, 2.0, 3.0], [1.0, 1.5, 2.0]])
    np.testing.assert_allclose(sizes, [[2.0, 4.0, 6.0], [1e-3, 1.0, 2.0]])


def test_height_colors_run_low_to_high() -> None:
    colors = height_rgba(np.array([0.0, 0.5, 1.0]), alpha=0.5)
    assert colors.shape == (3, 4) and np.all(colors[:, 3] == 0.5)
    assert colors[0, 2] > colors[0, 1] and colors[2, 0] > 0.9 and colors[2, 1] > 0.8  # blue-violet .. yellow
    assert height_rgba(np.zeros(0)).shape == (0, 4)
    level = height_rgba(np.full(4, 2.0))
    assert np.allclose(level, level[0])
