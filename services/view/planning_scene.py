"""What the planner knows, drawn in the view: its collision objects, those attached to the arm,
and, after a plan refused with START_IN_COLLISION or GOAL_IN_COLLISION, what collides where.

World objects come from the latched `planner/scene_state`; attached objects are posed in their
link's frame and follow the arm on every joint state. A refused plan's `details` name the
colliding pairs (`"link|object"`) and the state (`positions`): the links named are drawn as
red hulls at that state, the objects named turn red, and the ghost robot shows a goal state.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh
import viser

from robonav.pipeline.markers import Primitive, object_primitives
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.transforms import quat_xyzw_from_rotation
from robonav.pipeline.wire.joint_order import positions_by_name
from robonav.pipeline.wire.messages import PlanningSceneState, SceneObjectSpec

OBJECT_RGB = (110, 140, 180)
ATTACHED_RGB = (80, 200, 90)
COLLIDING_RGB = (230, 30, 30)
"""Links and objects a refused plan names (the browser test looks for this red)."""
OBJECT_OPACITY = 0.75
OCCUPANCY = "occupancy"


@dataclass(frozen=True)
class Collision:
    """What a START_IN_COLLISION / GOAL_IN_COLLISION reply's details say collides."""

    which: str
    """`start` or `goal` ("" when the reply does not say)."""
    links: tuple[str, ...]
    """Robot links in a colliding pair."""
    objects: tuple[str, ...]
    """Planner objects (world or attached) in a colliding pair."""
    occupancy: bool
    """Whether the occupancy map is in a colliding pair."""
    positions: np.ndarray | None
    """The colliding state in the robot's joint order [rad], when the reply carries it."""


def collision_from_details(details: Mapping[str, Any], robot_links: frozenset[str], dof: int) -> Collision:
    """Sorts the names of `details["pairs"]` into robot links, objects and the map; tolerant of
    replies from older planners (no positions) and of malformed entries (skipped)."""
    links: list[str] = []
    objects: list[str] = []
    occupancy = False
    pairs = details.get("pairs")
    for pair in pairs if isinstance(pairs, list) else []:
        if not isinstance(pair, str) or "|" not in pair:
            continue
        for name in pair.split("|", 1):
            if name == OCCUPANCY:
                occupancy = True
            elif name in robot_links:
                if name not in links:
                    links.append(name)
            elif name not in objects:
                objects.append(name)
    positions = None
    raw = details.get("positions")
    if isinstance(raw, list) and len(raw) == dof:
        try:
            candidate = np.array(raw, dtype=np.float64)
        except (TypeError, ValueError):
            candidate = None
        if candidate is not None and np.isfinite(candidate).all():
            positions = candidate
    which = details.get("which")
    return Collision(which if isinstance(which, str) else "", tuple(links), tuple(objects), occupancy, positions)


class PlanningSceneLayer:
    """The planner's objects under `/objects`, collision highlights under `/collision`; built by
    `SceneLayers`, whose lock it shares."""

    def __init__(self, server: viser.ViserServer, robot: RobotModel, lock: threading.RLock) -> None:
        self.server = server
        self.robot = robot
        self._lock = lock  # the scene layers' lock: it also guards the robot model's FK buffer
        # `/objects` is a layer root of `SceneLayers` (its toggle hides them); highlights always show.
        self.collision_root = server.scene.add_frame("/collision", show_axes=False)
        self._nodes: dict[str, list[Any]] = {}
        self._attached: dict[str, tuple[str, Any]] = {}
        """Attached object name -> (its link, the frame node that follows the link)."""
        self._specs: dict[str, tuple[SceneObjectSpec, str | None]] = {}
        self._collision_nodes: list[Any] = []
        self._highlighted: list[str] = []
        self._last_q: np.ndarray | None = None
        self.state: PlanningSceneState | None = None
        self.collision: Collision | None = None

    @property
    def object_names(self) -> tuple[str, ...]:
        with self._lock:
            return tuple(self._specs)

    def show(self, state: PlanningSceneState) -> None:
        """Replace the drawn objects by those of `state`; a bad object is skipped, not fatal."""
        with self._lock:
            for nodes in self._nodes.values():
                for node in reversed(nodes):  # children before their frame
                    node.remove()
            self._nodes, self._attached, self._specs = {}, {}, {}
            self.state = state
            for obj in state.objects:
                self._specs[obj.name] = (obj, None)
            for attached in state.attached:
                self._specs[attached.object.name] = (attached.object, attached.link)
            for name in self._specs:
                self._draw_object(name)

    def _draw_object(self, name: str) -> None:
        obj, link = self._specs[name]
        colliding = self.collision is not None and name in self.collision.objects
        color = COLLIDING_RGB if colliding else (ATTACHED_RGB if link is not None else OBJECT_RGB)
        safe = name.replace("/", "_")
        nodes: list[Any] = []
        parent = f"/objects/{safe}"
        if link is not None:  # posed in the link's frame: a frame node follows the link
            frame = self.server.scene.add_frame(parent, show_axes=False)
            self._attached[name] = (link, frame)
            nodes.append(frame)
            if self._last_q is not None and link in self.robot.link_names:
                world_from_link = self.robot.frame_pose(self._last_q, link)
                frame.wxyz, frame.position = _wxyz(world_from_link), world_from_link[:3, 3]
        try:
            primitives = object_primitives(obj)
        except ValueError:
            primitives = []
        for i, primitive in enumerate(primitives):
            nodes.append(self._add_primitive(f"{parent}/{i}", primitive, color))
        self._nodes[name] = nodes

    def _add_primitive(self, node: str, primitive: Primitive, color: tuple[int, int, int]) -> Any:
        x, y, z, w = primitive.quat_xyzw
        pose = {"wxyz": (w, x, y, z), "position": primitive.position_m}
        scene = self.server.scene
        if primitive.kind == "cube":
            return scene.add_box(node, color=color, dimensions=primitive.size_m, opacity=OBJECT_OPACITY, **pose)
        if primitive.kind == "sphere":
            return scene.add_icosphere(node, radius=primitive.size_m[0] / 2.0, color=color, opacity=OBJECT_OPACITY,
                                       **pose)
        if primitive.kind == "cylinder":
            return scene.add_cylinder(node, radius=primitive.size_m[0] / 2.0, height=primitive.size_m[2], color=color,
                                      opacity=OBJECT_OPACITY, **pose)
        assert primitive.points_m is not None
        faces = np.arange(len(primitive.points_m), dtype=np.uint32).reshape(-1, 3)
        return scene.add_mesh_simple(node, primitive.points_m.astype(np.float32), faces, color=color,
                                     opacity=OBJECT_OPACITY, side="double", **pose)

    def follow(self, names: Sequence[str], positions: Sequence[float]) -> None:
        """Move attached objects with their links to a joint state."""
        q = positions_by_name(names, positions, self.robot.joint_names)
        with self._lock:
            if q is None:
                return
            self._last_q = np.asarray(q, dtype=np.float64)
            for link, frame in self._attached.values():
                try:
                    world_from_link = self.robot.frame_pose(q, link)
                except ValueError:  # a link of another robot, or a state out of limits
                    continue
                frame.wxyz, frame.position = _wxyz(world_from_link), world_from_link[:3, 3]

    def show_collision(self, collision: Collision, current: np.ndarray | None) -> None:
        """Mark what collides: the named links as red hulls at the colliding state (`positions`,
        else `current`), the named objects in red."""
        with self._lock:
            self.clear_collision()
            self.collision = collision
            q = collision.positions if collision.positions is not None else current
            hulls = self.robot.link_hull_vertices
            if q is not None:
                for link in collision.links:
                    if link not in hulls:
                        continue
                    mesh = trimesh.convex.convex_hull(hulls[link])
                    world_from_link = self.robot.frame_pose(q, link)
                    self._collision_nodes.append(self.server.scene.add_mesh_simple(
                        f"/collision/{link}", np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32),
                        color=COLLIDING_RGB, opacity=0.6, wxyz=_wxyz(world_from_link), position=world_from_link[:3, 3]))
                    self._highlighted.append(link)
            for name in collision.objects:
                if name in self._specs:
                    self._redraw(name)

    def clear_collision(self) -> None:
        with self._lock:
            for node in self._collision_nodes:
                node.remove()
            self._collision_nodes, self._highlighted = [], []
            named = self.collision.objects if self.collision is not None else ()
            self.collision = None
            for name in named:
                if name in self._specs:
                    self._redraw(name)

    def _redraw(self, name: str) -> None:
        for node in reversed(self._nodes.pop(name, [])):
            node.remove()
        self._attached.pop(name, None)
        self._draw_object(name)

    @property
    def highlighted_links(self) -> tuple[str, ...]:
        """Links drawn as colliding hulls."""
        with self._lock:
            return tuple(self._highlighted)

    def object_color(self, name: str) -> tuple[int, int, int] | None:
        """The colour an object is drawn in (None: not drawn)."""
        with self._lock:
            nodes = [n for n in self._nodes.get(name, []) if hasattr(n, "color")]
            return tuple(int(c) for c in nodes[0].color) if nodes else None  # type: ignore[return-value]


def _wxyz(world_from_frame: np.ndarray) -> tuple[float, float, float, float]:
    """viser's scalar-first quaternion of a pose's rotation."""
    x, y, z, w = (float(v) for v in quat_xyzw_from_rotation(world_from_frame[:3, :3]))
    return w, x, y, z
