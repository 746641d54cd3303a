"""Synthetic point clouds: the surfaces of primitive scene objects, sampled at a given spacing.

Stands in for a depth camera that sees every side of every object, so the perception path
(occupancy map, inflation, octree planning) can be benchmarked on scenes that only exist as
primitives. Sampling is stratified: each surface is cut into cells no larger than the spacing
and each cell gets one uniformly drawn point, so no gap exceeds twice the spacing while the
points do not line up with the occupancy grid.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from robonav.pipeline.scene import SceneObject
from robonav.pipeline.types import FloatArray


def sample_object_surfaces(objects: Sequence[SceneObject], *, spacing_m: float,
                           rng: np.random.Generator) -> FloatArray:
    """Points on the surfaces of primitive objects.

    Args:
        objects: Boxes, cylinders, spheres or capsules posed in the world frame.
        spacing_m: Largest side of the cell each point is drawn from [m].
        rng: Source of the in-cell positions (seed it for a reproducible cloud).

    Returns:
        (N, 3) points in the world frame [m], objects in the given order.

    Raises:
        ValueError: non-positive spacing, or an object type without a sampler (mesh).
    """
    if not (math.isfinite(spacing_m) and spacing_m > 0):
        raise ValueError(f"spacing_m must be finite and > 0, got {spacing_m}")
    parts = [np.zeros((0, 3))]
    for obj in objects:
        if obj.type == "box":
            local = _box_surface(np.asarray(obj.size_m, dtype=np.float64), spacing_m, rng)
        elif obj.type == "cylinder":
            local = _cylinder_surface(float(obj.radius_m), float(obj.length_m), spacing_m, rng, caps="flat")  # type: ignore[arg-type]
        elif obj.type == "capsule":
            local = _cylinder_surface(float(obj.radius_m), float(obj.length_m), spacing_m, rng, caps="round")  # type: ignore[arg-type]
        elif obj.type == "sphere":
            local = _sphere_surface(float(obj.radius_m), spacing_m, rng)  # type: ignore[arg-type]
        else:
            raise ValueError(f"object '{obj.name}': cannot sample the surface of type '{obj.type}'")
        pose = obj.world_from_object
        parts.append(local @ pose[:3, :3].T + pose[:3, 3])
    return np.vstack(parts)


def _stratified(extent_u: float, extent_v: float, spacing_m: float, rng: np.random.Generator) -> FloatArray:
    """(N, 2) points in [0, extent_u] x [0, extent_v], one per grid cell of side <= spacing."""
    nu, nv = max(1, math.ceil(extent_u / spacing_m)), max(1, math.ceil(extent_v / spacing_m))
    iu, iv = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    jitter = rng.random((nu * nv, 2))
    return np.column_stack([(iu.ravel() + jitter[:, 0]) * (extent_u / nu), (iv.ravel() + jitter[:, 1]) * (extent_v / nv)])


def _box_surface(size_m: FloatArray, spacing_m: float, rng: np.random.Generator) -> FloatArray:
    half = 0.5 * size_m
    faces = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        for sign in (-1.0, 1.0):
            uv = _stratified(size_m[u], size_m[v], spacing_m, rng)
            face = np.empty((uv.shape[0], 3))
            face[:, axis] = sign * half[axis]
            face[:, u] = uv[:, 0] - half[u]
            face[:, v] = uv[:, 1] - half[v]
            faces.append(face)
    return np.vstack(faces)


def _disk(radius_m: float, spacing_m: float, rng: np.random.Generator) -> FloatArray:
    """(N, 2) points in the disk of `radius_m`: the stratified square, cut to the disk, plus its rim."""
    square = _stratified(2 * radius_m, 2 * radius_m, spacing_m, rng) - radius_m
    inside = square[np.einsum("ij,ij->i", square, square) <= radius_m * radius_m]
    angles = _stratified(2 * math.pi * radius_m, 0.0, spacing_m, rng)[:, 0] / radius_m
    return np.vstack([inside, radius_m * np.column_stack([np.cos(angles), np.sin(angles)])])


def _cylinder_surface(radius_m: float, length_m: float, spacing_m: float, rng: np.random.Generator,
                      *, caps: str) -> FloatArray:
    arc_z = _stratified(2 * math.pi * radius_m, length_m, spacing_m, rng)
    angles = arc_z[:, 0] / radius_m
    side = np.column_stack([radius_m * np.cos(angles), radius_m * np.sin(angles), arc_z[:, 1] - 0.5 * length_m])
    ends = []
    for sign in (-1.0, 1.0):
        if caps == "flat":
            disk = _disk(radius_m, spacing_m, rng)
            ends.append(np.column_stack([disk, np.full(disk.shape[0], sign * 0.5 * length_m)]))
        else:
            ball = _sphere_surface(radius_m, spacing_m, rng)
            ball = ball[sign * ball[:, 2] >= 0]  # the outward hemisphere
            ends.append(ball + [0.0, 0.0, sign * 0.5 * length_m])
    return np.vstack([side, *ends])


def _sphere_surface(radius_m: float, spacing_m: float, rng: np.random.Generator) -> FloatArray:
    # Uniform directions with one point per spacing^2 of area: spacing-level coverage on average.
    count = max(4, math.ceil(4 * math.pi * radius_m * radius_m / (spacing_m * spacing_m)))
    directions = rng.normal(size=(count, 3))
    return radius_m * directions / np.linalg.norm(directions, axis=1, keepdims=True)
