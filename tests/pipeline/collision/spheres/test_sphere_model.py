"""Sphere covers contain every link hull (surface and interior samples) and stay reasonably tight."""

from __future__ import annotations

import numpy as np

from robonav.pipeline.collision.spheres.sphere_model import (
    box_points,
    cover_convex_points,
    cylinder_points,
    radii_covering,
    robot_sphere_model,
)
from robonav.pipeline.robot.link_geometry import convex_hull
from robonav.pipeline.robot.model import RobotModel


def _hull_samples(vertices: np.ndarray, rng: np.random.Generator, count: int = 4000) -> np.ndarray:
    """Points on the hull's surface (random triangle points) and inside it (convex combinations)."""
    v, t = convex_hull(vertices)
    tri = v[t[rng.integers(0, len(t), count)]]
    w = rng.dirichlet(np.ones(3), count)
    surface = np.einsum("nk,nkj->nj", w, tri)
    inner = rng.dirichlet(np.full(len(v), 0.3), count) @ v
    return np.vstack([surface, inner, v])


def _uncovered_m(points: np.ndarray, centers: np.ndarray, radii: np.ndarray) -> float:
    return float(np.max(np.min(np.linalg.norm(points[:, None] - centers[None], axis=2) - radii[None], axis=1)))


def test_panda_links_are_covered_by_a_reasonable_number_of_spheres(panda: RobotModel) -> None:
    model = robot_sphere_model(panda)
    rng = np.random.default_rng(0)
    for li, link in enumerate(model.link_names):
        mine = model.link_index == li
        for shape in panda.link_collision_shapes[link]:
            samples = _hull_samples(shape.hull_vertices, rng)
            assert _uncovered_m(samples, model.centers_link_m[mine], model.radii_m[mine]) <= 0.0, link
    assert 40 <= model.sphere_count <= 120
    assert model.union_volume_m3 < 2.5 * model.hull_volume_m3


def test_cover_of_box_and_cylinder_points() -> None:
    rng = np.random.default_rng(1)
    for points in (box_points((0.3, 0.1, 0.05)), cylinder_points(0.04, 0.2)):
        cover = cover_convex_points(points)
        assert _uncovered_m(_hull_samples(points, rng), cover.centers_m, cover.radii_m) <= 0.0
        assert cover.union_volume_m3 >= cover.hull_volume_m3 * 0.99


def test_cover_is_deterministic(panda: RobotModel) -> None:
    points = panda.link_collision_shapes["panda_hand"][0].hull_vertices
    a = cover_convex_points(points, max_protrusion_m=0.012)
    b = cover_convex_points(points.copy(), max_protrusion_m=0.012)
    np.testing.assert_array_equal(a.centers_m, b.centers_m)
    np.testing.assert_array_equal(a.radii_m, b.radii_m)


def test_radii_covering_a_grown_box_grow_only_where_needed() -> None:
    """Spheres of a box's cover refitted to the box grown by 2 cm: every sample of the grown box
    is covered, and the balls grow by at least the padding but not all by the corner's 3.5 cm."""
    cover = cover_convex_points(box_points((0.3, 0.1, 0.05)))
    grown = box_points((0.34, 0.14, 0.09))
    radii = radii_covering(grown, cover.centers_m, cover.radii_m + 0.02)
    assert _uncovered_m(_hull_samples(grown, np.random.default_rng(2)), cover.centers_m, radii) <= 0.0
    assert np.all(radii >= cover.radii_m + 0.02)
    assert np.min(radii - cover.radii_m) < 0.02 * 3**0.5
