"""The robot as the view serves it: the scene the browser receives (viser's own serialization of
it) holds every visual link of another robot's URDF, read from COLLADA and STL through
`package://` and relative paths, with its triangles where the planner's model puts that link;
a COLLADA file in millimetres is drawn in metres."""

from __future__ import annotations

import dataclasses
import io
import math
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

pytest.importorskip("viser", reason="the `view` extra (viser) is not installed")

import trimesh  # noqa: E402
import viser  # noqa: E402
import zstandard  # noqa: E402

from robonav.pipeline.robot.config import RobotConfig  # noqa: E402
from robonav.pipeline.robot.model import RobotModel, resolve_urdf_path  # noqa: E402
from robonav.pipeline.transforms import PoseSpec, rotation_from_quat_xyzw  # noqa: E402
from robonav.services.stack.robot_cell import read_robot  # noqa: E402
from robonav.services.view.scene import SceneLayers, load_visual_urdf  # noqa: E402

from ...conftest import REPO_ROOT  # noqa: E402

UR5_FILE = REPO_ROOT / "configs" / "ur5.yaml"
UR5_DIR = REPO_ROOT.parent / "shared" / "robots" / "ur5"
UR5_STATE_RAD = (0.3, -1.2, 0.8, -1.0, 0.5, 0.2)
BOUNDS_TOLERANCE_M = 0.002
"""The UR5's COLLADA visual meshes and its STL collision meshes are the same shapes (their bounds
agree to 0.3 mm; the gripper's links use one STL for both): a link drawn in another place,
turned, or at another scale (a COLLADA file in millimetres read as metres) misses by centimetres."""


@pytest.fixture(scope="module")
def ur5() -> RobotModel:
    return RobotModel.from_config(read_robot(UR5_FILE))


@pytest.fixture
def server() -> Iterator[viser.ViserServer]:
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield server
    server.stop()


def served_scene(server: viser.ViserServer) -> dict[str, dict[str, Any]]:
    """The scene a browser connecting now receives, by node name: each node's message type and
    props, and its pose in its parent node (viser's recording of the scene: zstd-compressed,
    an 8-byte length, msgpack messages in the order they were sent)."""
    data = server.get_scene_serializer().serialize()
    inner = zstandard.ZstdDecompressor().decompress(data[8:], max_output_size=int.from_bytes(data[:8], "little"))
    size = int.from_bytes(inner[:8], "little")
    nodes: dict[str, dict[str, Any]] = {}
    for _, message in msgpack.unpackb(inner[8:8 + size])["messages"]:
        name, kind = message.get("name"), message["type"]
        if not name:  # the scene's root: viser's own world-to-browser turn
            continue
        node = nodes.setdefault(name, {"position": (0.0, 0.0, 0.0), "wxyz": (1.0, 0.0, 0.0, 0.0)})
        if kind == "SetPositionMessage":
            node["position"] = message["position"]
        elif kind == "SetOrientationMessage":
            node["wxyz"] = message["wxyz"]
        elif kind == "RemoveSceneNodeMessage":
            del nodes[name]
        elif "props" in message:
            node["type"], node["props"] = kind, message["props"]
    return nodes


def world_from_node(nodes: dict[str, dict[str, Any]], name: str) -> np.ndarray:
    """(4, 4) pose of node `name` in the world: its ancestors' poses composed, as the browser does."""
    world_from = np.eye(4)
    parts = name.split("/")
    for depth in range(2, len(parts) + 1):
        node = nodes.get("/".join(parts[:depth]))
        if node is None:
            continue
        w, x, y, z = node["wxyz"]
        parent_from_node = np.eye(4)
        parent_from_node[:3, :3] = rotation_from_quat_xyzw((x, y, z, w))
        parent_from_node[:3, 3] = node["position"]
        world_from = world_from @ parent_from_node
    return world_from


def drawn_links(nodes: dict[str, dict[str, Any]], root: str) -> dict[str, tuple[np.ndarray, int]]:
    """Per link under `root`: world vertices (V, 3) [m] and triangle count of its GLB meshes."""
    out: dict[str, tuple[np.ndarray, int]] = {}
    for name, node in nodes.items():
        if not name.startswith(f"{root}/") or node.get("type") != "GlbMessage":
            continue
        mesh = trimesh.load(io.BytesIO(node["props"]["glb_data"]), file_type="glb", force="mesh")
        world_from = world_from_node(nodes, name)
        vertices = np.asarray(mesh.vertices) @ world_from[:3, :3].T + world_from[:3, 3]
        link = name.split("/")[-2]  # viser names a mesh <link path>/<mesh name>
        before, faces = out.get(link, (np.zeros((0, 3)), 0))
        out[link] = (np.vstack([before, vertices]), faces + len(mesh.faces))
    return out


def visual_links(robot: RobotModel) -> set[str]:
    urdf = ET.parse(resolve_urdf_path(robot.config.urdf, robot.config.package_paths)).getroot()
    return {link.get("name", "") for link in urdf.iter("link") if link.find("visual") is not None}


def test_the_view_serves_every_ur5_visual_link_where_the_model_puts_it(ur5: RobotModel,
                                                                        server: viser.ViserServer) -> None:
    urdf_text = resolve_urdf_path(ur5.config.urdf, ur5.config.package_paths).read_text(encoding="utf-8")
    assert ".dae" in urdf_text and "package://" in urdf_text, "the check needs COLLADA meshes behind package:// URIs"
    expected = visual_links(ur5)
    layers = SceneLayers(server, ur5, [])
    for q in (ur5.home_position_rad, np.array(UR5_STATE_RAD)):
        layers.set_robot_joints(ur5.joint_names, q.tolist())
        links = drawn_links(served_scene(server), "/robot")
        assert set(links) == expected
        poses = ur5.link_poses(q)
        for link, (vertices, faces) in links.items():
            assert faces > 0, link
            world_from_link = poses[link]
            hull = ur5.link_hull_vertices[link] @ world_from_link[:3, :3].T + world_from_link[:3, 3]
            np.testing.assert_allclose(vertices.min(axis=0), hull.min(axis=0), atol=BOUNDS_TOLERANCE_M, err_msg=link)
            np.testing.assert_allclose(vertices.max(axis=0), hull.max(axis=0), atol=BOUNDS_TOLERANCE_M, err_msg=link)


def test_a_collada_mesh_in_millimetres_with_a_node_transform_is_drawn_in_metres(tmp_path: Path) -> None:
    """The UR5's wrist COLLADA rewritten as a CAD export in millimetres would be: `<unit
    meter="0.001">`, its node scaled by 1000 and moved 50 mm along x. trimesh applies the node
    transform but keeps the unit's coordinates; the view's URDF scales them to metres."""
    source = UR5_DIR / "meshes" / "ur5" / "visual" / "wrist3.dae"
    text = source.read_text(encoding="utf-8")
    identity = '<matrix sid="transform">1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1</matrix>'
    assert text.count(identity) == 1 and text.count('<unit name="meter" meter="1"/>') == 1
    (tmp_path / "wrist3_mm.dae").write_text(
        text.replace('<unit name="meter" meter="1"/>', '<unit name="millimeter" meter="0.001"/>')
        .replace(identity, '<matrix sid="transform">1000 0 0 50 0 1000 0 0 0 0 1000 0 0 0 0 1</matrix>'),
        encoding="utf-8")
    urdf_path = tmp_path / "part.urdf"
    urdf_path.write_text(f"""<robot name="part">
  <link name="metres"><visual><geometry><mesh filename="file://{source}"/></geometry></visual></link>
  <link name="millimetres"><visual><geometry><mesh filename="wrist3_mm.dae"/></geometry></visual></link>
  <joint name="weld" type="fixed"><parent link="metres"/><child link="millimetres"/></joint>
</robot>""", encoding="utf-8")
    scene = load_visual_urdf(urdf_path).scene
    bounds = {}
    for node in scene.graph.nodes_geometry:
        world_from_node, geometry = scene.graph.get(node)
        link = scene.graph.transforms.parents[node]
        vertices = trimesh.transform_points(scene.geometry[geometry].vertices, world_from_node)
        low, high = bounds.get(link, (np.full(3, np.inf), np.full(3, -np.inf)))
        bounds[link] = (np.minimum(low, vertices.min(axis=0)), np.maximum(high, vertices.max(axis=0)))
    np.testing.assert_allclose(bounds["millimetres"][0], bounds["metres"][0] + [0.05, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(bounds["millimetres"][1], bounds["metres"][1] + [0.05, 0.0, 0.0], atol=1e-6)


def test_a_robot_standing_elsewhere_is_drawn_where_the_model_puts_it(server: viser.ViserServer) -> None:
    # Moved and turned about a tilted axis by robot.world_from_base: every link frame the browser
    # composes is the planner model's.
    pose = PoseSpec((0.8, -0.6, 0.3), (0.1, -0.2, math.sin(0.4), math.sqrt(1.0 - 0.05 - math.sin(0.4) ** 2)))
    robot = RobotModel.from_config(dataclasses.replace(RobotConfig(), world_from_base=pose))
    layers = SceneLayers(server, robot, [])
    q = np.array([0.4, -0.5, 0.3, -2.0, 0.2, 1.8, -0.6])
    layers.set_robot_joints(robot.joint_names, q.tolist())
    nodes = served_scene(server)
    checked = 0
    for name in nodes:
        link = name.split("/")[-1]
        if name.startswith("/robot/") and link in robot.link_names:
            np.testing.assert_allclose(world_from_node(nodes, name), robot.frame_pose(q, link), atol=1e-6, err_msg=name)
            checked += 1
    assert checked >= len(robot.collision_link_names), sorted(nodes)
    np.testing.assert_allclose(world_from_node(nodes, "/robot"), pose.matrix, atol=1e-6)
