"""Collision geometry of URDF links: the `<collision>` shapes of each link and their convex hulls.

Every shape keeps a convex hull expressed in its LINK frame, so a consumer (the FCL world, the
perception self-filter) can place it with `world_from_link` alone. Hulls of curved primitives are
circumscribed polytopes: they contain the true shape, never cut into it.
"""

from __future__ import annotations

import math
import os
import re
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import open3d as o3d

from robonav.pipeline.transforms import transform_points
from robonav.pipeline.types import FloatArray, IntArray

ShapeKind = Literal["mesh", "box", "cylinder", "sphere"]

_CYLINDER_SIDES = 24
_MIN_NORMAL_COS = 0.3
"""A grown hull's vertex moves at most padding / 0.3 along its normal."""
_SPHERE_SAMPLES = 96


@dataclass(frozen=True, eq=False)
class LinkShape:
    """One `<collision>` element of a URDF link.

    Attributes:
        link: Name of the link the shape belongs to.
        kind: 'mesh', 'box', 'cylinder' (axis = shape z) or 'sphere'.
        link_from_shape: (4, 4) pose of the shape frame in the link frame (the `<origin>`).
        hull_vertices: (H, 3) convex hull vertices in the LINK frame [m].
        hull_triangles: (F, 3) indices into `hull_vertices`, counter-clockwise seen from outside.
        vertices: (V, 3) mesh vertices in the SHAPE frame, scale applied [m]; meshes only.
        triangles: (T, 3) mesh triangle indices into `vertices`; meshes only.
        size_m: Box full side lengths along shape x, y, z [m]; boxes only.
        radius_m: Cylinder or sphere radius [m].
        length_m: Cylinder full length along shape z [m].
        source: Resolved mesh file path; '' for primitives.
    """

    link: str
    kind: ShapeKind
    link_from_shape: FloatArray
    hull_vertices: FloatArray
    hull_triangles: IntArray
    vertices: FloatArray | None = None
    triangles: IntArray | None = None
    size_m: tuple[float, float, float] | None = None
    radius_m: float | None = None
    length_m: float | None = None
    source: str = ""


def convex_hull(points_m: FloatArray) -> tuple[FloatArray, IntArray]:
    """Convex hull of a point set with outward-facing triangles.

    Args:
        points_m: (N, 3) points, N >= 4, not all coplanar.

    Returns:
        (H, 3) hull vertices and (F, 3) triangle indices into them, counter-clockwise seen
        from outside (normals point away from the hull's interior).
    """
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    if pts.shape[0] < 4 or not np.all(np.isfinite(pts)):
        raise ValueError(f"convex hull needs at least 4 finite points, got {pts.shape[0]}")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        hull, _ = cloud.compute_convex_hull()
    vertices = np.asarray(hull.vertices, dtype=np.float64).copy()
    triangles = np.asarray(hull.triangles, dtype=np.int64).copy()
    if triangles.shape[0] < 4:
        raise ValueError(f"convex hull of {pts.shape[0]} points is degenerate (points are coplanar)")
    # qhull's facet orientation is not guaranteed; the hull's vertex mean is interior, so flip
    # any triangle whose normal points towards it.
    interior = vertices.mean(axis=0)
    a, b, c = vertices[triangles[:, 0]], vertices[triangles[:, 1]], vertices[triangles[:, 2]]
    normals = np.cross(b - a, c - a)
    inward = np.einsum("ij,ij->i", normals, a - interior) < 0
    triangles[inward] = triangles[inward][:, ::-1]
    return vertices, triangles


def grow_hull(vertices: FloatArray, triangles: IntArray, padding_m: float) -> tuple[FloatArray, IntArray]:
    """A convex hull, vertices (H, 3) and outward triangles (F, 3), grown outwards by `padding_m` [m].

    Each vertex moves along its (angle-weighted) normal by padding / min(cos) over its faces,
    so every face plane moves out by at
    least `padding_m` and the grown hull contains the Minkowski sum of the hull and a sphere of
    radius `padding_m` (conservative at vertices and edges too). On the Panda links the grown
    hull's support function exceeds the original by 1.0-1.8x `padding_m`. The factor is capped
    at 1 / _MIN_NORMAL_COS so needle-sharp vertices cannot spike (there the guarantee lapses).
    """
    corners = [vertices[triangles[:, k]] for k in range(3)]
    face_normals = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    face_normals /= np.linalg.norm(face_normals, axis=1, keepdims=True)
    vertex_normals = np.zeros_like(vertices)
    for k in range(3):
        # Weighting by the face's angle at the vertex makes the normal independent of how a
        # flat facet was split into triangles (a fan of cap triangles would otherwise dominate).
        e1, e2 = corners[(k + 1) % 3] - corners[k], corners[(k + 2) % 3] - corners[k]
        cos_angle = np.einsum("ij,ij->i", e1, e2) / (np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1))
        angle = np.arccos(np.clip(cos_angle, -1.0, 1.0))
        np.add.at(vertex_normals, triangles[:, k], face_normals * angle[:, None])
    vertex_normals /= np.linalg.norm(vertex_normals, axis=1, keepdims=True)
    min_cos = np.ones(len(vertices))
    for k in range(3):
        np.minimum.at(min_cos, triangles[:, k], np.einsum("ij,ij->i", vertex_normals[triangles[:, k]], face_normals))
    scale = padding_m / np.maximum(min_cos, _MIN_NORMAL_COS)
    return convex_hull(vertices + vertex_normals * scale[:, None])


def rpy_transform(xyz: tuple[float, float, float], rpy: tuple[float, float, float]) -> FloatArray:
    """4x4 transform of a URDF `<origin>`: fixed-axis roll, pitch, yaw, R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    out = np.eye(4)
    out[:3, :3] = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    out[:3, 3] = xyz
    return out


def parse_collision_shapes(urdf_path: Path, package_paths: Sequence[str | Path] = ()) -> dict[str, list[LinkShape]]:
    """Collision shapes of every link of a URDF that has any, in document order.

    Args:
        urdf_path: URDF file; mesh file names resolve as `resolve_mesh_path` says.
        package_paths: Folders holding ROS packages, searched for `package://NAME/...` first.

    Returns:
        Link name -> its shapes; links without `<collision>` are absent.

    Raises:
        ValueError: a mesh cannot be found or holds no triangles, or a geometry is unsupported.
    """
    root = ET.parse(urdf_path).getroot()
    shapes: dict[str, list[LinkShape]] = {}
    for link in root.findall("link"):
        name = link.attrib["name"]
        for index, collision in enumerate(link.findall("collision")):
            where = f"{urdf_path.name}: link '{name}' collision #{index}"
            origin = collision.find("origin")
            link_from_shape = rpy_transform(
                _floats(origin.attrib.get("xyz", "0 0 0") if origin is not None else "0 0 0", 3, where),
                _floats(origin.attrib.get("rpy", "0 0 0") if origin is not None else "0 0 0", 3, where),
            )
            geometry = collision.find("geometry")
            element = geometry[0] if geometry is not None and len(geometry) else None
            if element is None:
                raise ValueError(f"{where}: <geometry> is empty")
            try:
                shape = _shape(name, element, link_from_shape, urdf_path, where, package_paths)
            except KeyError as exc:
                raise ValueError(f"{where}: <{element.tag}> lacks the attribute {exc}") from exc
            shapes.setdefault(name, []).append(shape)
    return shapes


def _shape(link: str, element: ET.Element, link_from_shape: FloatArray, urdf_path: Path, where: str,
           package_paths: Sequence[str | Path]) -> LinkShape:
    tag = element.tag
    if tag == "mesh":
        path = resolve_mesh_path(element.attrib["filename"], urdf_path, package_paths)
        scale = np.array(_floats(element.attrib.get("scale", "1 1 1"), 3, where))
        vertices, triangles = load_mesh(path)
        vertices = vertices * scale
        hull_v, hull_t = convex_hull(transform_points(link_from_shape, vertices))
        return LinkShape(link, "mesh", link_from_shape, hull_v, hull_t, vertices, triangles, source=str(path))
    if tag == "box":
        size = _floats(element.attrib["size"], 3, where)
        corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)]) * size
        hull_v, hull_t = convex_hull(transform_points(link_from_shape, corners))
        return LinkShape(link, "box", link_from_shape, hull_v, hull_t, size_m=size)
    if tag == "cylinder":
        radius, length = float(element.attrib["radius"]), float(element.attrib["length"])
        # A regular polygon with apothem `radius` circumscribes the circle.
        angles = np.arange(_CYLINDER_SIDES) * (2 * math.pi / _CYLINDER_SIDES)
        rim = radius / math.cos(math.pi / _CYLINDER_SIDES)
        ring = np.column_stack([rim * np.cos(angles), rim * np.sin(angles)])
        pts = np.vstack([np.column_stack([ring, np.full(len(ring), z)]) for z in (-length / 2, length / 2)])
        hull_v, hull_t = convex_hull(transform_points(link_from_shape, pts))
        return LinkShape(link, "cylinder", link_from_shape, hull_v, hull_t, radius_m=radius, length_m=length)
    if tag == "sphere":
        radius = float(element.attrib["radius"])
        hull_v, hull_t = convex_hull(transform_points(link_from_shape, circumscribed_sphere_points(radius)))
        return LinkShape(link, "sphere", link_from_shape, hull_v, hull_t, radius_m=radius)
    raise ValueError(f"{where}: unsupported collision geometry <{tag}> (expected mesh, box, cylinder, sphere)")


def circumscribed_sphere_points(radius_m: float) -> FloatArray:
    """(N, 3) points around the origin whose convex hull contains the sphere of `radius_m`."""
    i = np.arange(_SPHERE_SAMPLES) + 0.5
    polar = np.arccos(1 - 2 * i / _SPHERE_SAMPLES)
    azimuth = math.pi * (1 + 5**0.5) * i
    unit = np.column_stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])
    vertices, triangles = convex_hull(unit)
    # The sampled hull's faces dip inside the unit sphere; scale so the closest face plane
    # touches the sphere of `radius_m`.
    a, b, c = vertices[triangles[:, 0]], vertices[triangles[:, 1]], vertices[triangles[:, 2]]
    normals = np.cross(b - a, c - a)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    inradius = float(np.min(np.einsum("ij,ij->i", normals, a)))
    return vertices * (radius_m / inradius)


ROS_PACKAGE_PATH_VARIABLE = "ROS_PACKAGE_PATH"


def package_search_paths(package_paths: Sequence[str | Path] = (), urdf_path: Path | None = None,
                         environ: Mapping[str, str] | None = None) -> list[Path]:
    """Folders searched for ROS packages, in order: the configured ones, then `ROS_PACKAGE_PATH`
    (os.pathsep-separated, as ROS reads it), then the URDF's own folder (a description shipped
    as one folder, like MotionBenchMaker's, holds its `package://` roots beside the URDF)."""
    env = os.environ if environ is None else environ
    out = [Path(p) for p in package_paths]
    out += [Path(p) for p in env.get(ROS_PACKAGE_PATH_VARIABLE, "").split(os.pathsep) if p]
    if urdf_path is not None:
        out.append(urdf_path.parent)
    return out


def find_package(name: str, search_paths: Sequence[Path]) -> Path | None:
    """Folder of ROS package `name`: `DIR/NAME`, or DIR itself when named NAME, or a folder up to
    two levels below DIR whose package.xml declares `<name>NAME</name>` (how catkin/colcon find
    packages whose folder is named otherwise); None when no search path holds it."""
    for base in search_paths:
        if (base / name).is_dir():
            return base / name
        if base.name == name and base.is_dir():
            return base
    for base in search_paths:
        for manifest in [*base.glob("*/package.xml"), *base.glob("*/*/package.xml")]:
            try:
                declared = ET.parse(manifest).getroot().findtext("name")
            except (ET.ParseError, OSError):
                continue
            if declared is not None and declared.strip() == name:
                return manifest.parent
    return None


def resolve_mesh_path(filename: str, urdf_path: Path, package_paths: Sequence[str | Path] = ()) -> Path:
    """File of a URDF mesh reference, resolved as ROS does.

    `package://NAME/rest` is `rest` inside package NAME, found through `package_search_paths`
    (configured folders, `ROS_PACKAGE_PATH`, the URDF's folder); `file://` is an absolute path;
    anything else is relative to the URDF's folder.

    Raises:
        ValueError: the file does not exist (the message lists where it was looked for).
    """
    if filename.startswith("file://"):
        candidate = Path(filename[len("file://"):])
        tried = [str(candidate)]
    elif filename.startswith("package://"):
        rest = filename[len("package://"):]
        name, _, tail = rest.partition("/")
        searched = package_search_paths(package_paths, urdf_path)
        package = find_package(name, searched)
        if package is None:
            raise ValueError(f"{urdf_path.name}: mesh '{filename}': package '{name}' not found in the package paths "
                             f"{[str(p) for p in searched]} (set robot.package_paths or {ROS_PACKAGE_PATH_VARIABLE})")
        candidate = package / tail
        tried = [str(candidate)]
    else:
        candidate = urdf_path.parent / filename
        tried = [str(candidate)]
    if candidate.is_file():
        return candidate
    raise ValueError(f"{urdf_path.name}: mesh '{filename}' not found (looked for {tried[0]})")


def urdf_with_resolved_meshes(urdf_path: Path, package_paths: Sequence[str | Path] = ()) -> str:
    """The URDF's text with every `<mesh filename>` replaced by its absolute path, resolved as
    `resolve_mesh_path` does, for loaders that know no ROS packages (pybullet, which only strips
    `package://` and looks beside the URDF).

    Raises:
        ValueError: unreadable XML, or a mesh that cannot be found.
    """
    try:
        tree = ET.parse(urdf_path)
    except (ET.ParseError, OSError) as exc:
        raise ValueError(f"{urdf_path}: cannot read the URDF: {exc}") from exc
    for mesh in tree.getroot().iter("mesh"):
        if "filename" in mesh.attrib:
            mesh.set("filename", str(resolve_mesh_path(mesh.attrib["filename"], urdf_path, package_paths).absolute()))
    return ET.tostring(tree.getroot(), encoding="unicode")


def load_mesh(path: Path) -> tuple[FloatArray, IntArray]:
    """Vertices (V, 3) and triangles (T, 3) of an OBJ, STL or COLLADA (.dae) mesh file, in metres.

    COLLADA goes through trimesh (with pycollada), which applies the file's node transforms, and
    is scaled by its `<unit>` here (`collada_unit_m`); OBJ and STL through open3d, which the rest
    of the geometry code uses.
    """
    if path.suffix.lower() == ".dae":
        return _load_collada(path)
    # open3d logs skipped records and missing .mtl textures at warning level; the pure core stays quiet.
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(path))
    if mesh.has_triangles():
        # OBJ readers split vertices per texture coordinate; merge them for smaller hull input.
        mesh.remove_duplicated_vertices()
        vertices = np.asarray(mesh.vertices, dtype=np.float64).copy()
        triangles = np.asarray(mesh.triangles, dtype=np.int64).copy()
    elif path.suffix.lower() == ".obj":
        # Some OBJ exports (pybullet_data's panda link6.obj) carry `l` polyline records that
        # strict loaders reject outright; keep only vertex and face records, in memory.
        vertices, triangles = _parse_obj_faces(path.read_text(errors="replace"))
    else:
        vertices, triangles = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    if triangles.shape[0] == 0:
        raise ValueError(f"mesh '{path}' holds no triangles")
    return vertices, triangles


def collada_unit_m(path: Path) -> float:
    """Metres per coordinate unit of a COLLADA file: its `<asset><unit meter=...>`, 1 without one.

    trimesh reads the unit into its `units` metadata but leaves the coordinates as they are, so
    a file in millimetres would load 1000 times too large.

    Raises:
        ValueError: unreadable XML, or a unit that is not a positive number.
    """
    try:
        # The asset block comes first: stop at the first element after it, never parse the meshes.
        for _, element in ET.iterparse(path, events=("start",)):
            tag = element.tag.rsplit("}", 1)[-1]
            if tag == "unit":
                text = element.get("meter", "1")
                try:
                    unit_m = float(text)
                except ValueError:
                    unit_m = math.nan
                if not (math.isfinite(unit_m) and unit_m > 0):
                    raise ValueError(f"mesh '{path}': <unit meter=\"{text}\"> is not a positive number")
                return unit_m
            if tag.startswith("library_") or tag == "scene":
                return 1.0
    except (ET.ParseError, OSError) as exc:
        raise ValueError(f"mesh '{path}' cannot be read as COLLADA: {exc}") from exc
    return 1.0


def _load_collada(path: Path) -> tuple[FloatArray, IntArray]:
    import trimesh  # imported lazily: only COLLADA meshes need it

    try:
        loaded = trimesh.load(str(path), force="mesh")
    except Exception as exc:  # trimesh/pycollada raise many types for a bad file
        raise ValueError(f"mesh '{path}' cannot be read as COLLADA: {exc}") from exc
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    vertices = vertices * collada_unit_m(path)  # node transforms are applied: one scale covers them too
    triangles = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3).copy()
    if triangles.shape[0] == 0:
        raise ValueError(f"mesh '{path}' holds no triangles")
    return vertices, triangles


def _parse_obj_faces(text: str) -> tuple[FloatArray, IntArray]:
    vertices: list[list[float]] = []
    triangles: list[list[int]] = []
    for line in text.splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            vertices.append([float(v) for v in parts[1:4]])
        elif parts[0] == "f":
            # Face corners are `v`, `v/vt`, `v//vn` or `v/vt/vn`; 1-based, negative = from the end.
            idx = [int(p.split("/")[0]) for p in parts[1:]]
            idx = [i - 1 if i > 0 else len(vertices) + i for i in idx]
            triangles.extend([idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1))
    return np.array(vertices, dtype=np.float64).reshape(-1, 3), np.array(triangles, dtype=np.int64).reshape(-1, 3)


def _floats(text: str, count: int, where: str) -> tuple[float, ...]:
    values = tuple(float(v) for v in re.split(r"[\s,]+", text.strip()) if v)
    if len(values) != count:
        raise ValueError(f"{where}: expected {count} numbers, got '{text}'")
    return values
