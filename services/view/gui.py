"""The view's control panel: layer toggles, executor status, and a goal gizmo to plan, execute, stop."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Literal

import numpy as np
import viser

from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire.joint_order import positions_by_name
from robonav.pipeline.wire.messages import ErrorReply, ExecuteResponse, ExecutorStatus, PlanResponse
from robonav.services.client import QueryFailed, RobonavClient
from robonav.services.view.planning_scene import collision_from_details
from robonav.services.view.scene import LAYERS, SceneLayers, wxyz_of

log = logging.getLogger("robonav.view")

CloudColoring = Literal["height", "cluster"]
LAYER_LABELS = {"robot": "Robot", "ghost": "Ghost at goal", "path": "Path", "cloud": "Cloud", "voxels": "Occupied voxels",
                "clusters": "Clusters", "objects": "Planner objects", "cameras": "Camera frustums",
                "spheres": "Collision spheres"}
IN_COLLISION_CODES = ("START_IN_COLLISION", "GOAL_IN_COLLISION")
PLAN_TIMEOUT_S = 30.0
"""Longest wait for the planner's reply to a GUI plan [s]."""


class ViewControls:
    """GUI widgets bound to the scene layers and to the services' queries."""

    def __init__(self, server: viser.ViserServer, layers: SceneLayers, client: RobonavClient) -> None:
        self.layers = layers
        self.client = client
        self.cloud_coloring: CloudColoring = "height"
        self._planned: tuple[tuple[str, ...], FloatArray] | None = None
        self._busy = threading.Lock()
        gui = server.gui
        with gui.add_folder("Layers"):
            self.toggles = {name: gui.add_checkbox(LAYER_LABELS[name],
                                                   initial_value=name != "spheres" or layers.roots[name].visible)
                            for name in LAYERS}
            for name, box in self.toggles.items():
                box.on_update(lambda _event, name=name: self.layers.set_visible(name, self.toggles[name].value))
            self.coloring = gui.add_dropdown("Cloud colours", ("height", "cluster"), initial_value="height")
            self.coloring.on_update(lambda _event: setattr(self, "cloud_coloring", self.coloring.value))
            self.ghost_slider = gui.add_slider("Ghost along path", min=0.0, max=1.0, step=0.01, initial_value=1.0)
            self.ghost_slider.on_update(lambda _event: self.layers.set_ghost_fraction(self.ghost_slider.value))
        with gui.add_folder("Executor"):
            self.status_text = gui.add_markdown("no status yet")
            self.progress = gui.add_progress_bar(0.0)
        with gui.add_folder("Goal"):
            self.gizmo = server.scene.add_transform_controls("/goal", scale=0.15, visible=False)
            self.show_gizmo = gui.add_checkbox("Show goal gizmo", initial_value=False)
            self.show_gizmo.on_update(lambda _event: setattr(self.gizmo, "visible", self.show_gizmo.value))
            self.keep_orientation = gui.add_checkbox("Goal orientation", initial_value=True,
                                                     hint="off: plan to the position only, any orientation")
            self.to_hand = gui.add_button("Gizmo to the hand")
            self.plan_button = gui.add_button("Plan")
            self.execute_button = gui.add_button("Execute", disabled=True)
            self.stop_button = gui.add_button("Stop", color="red")
            self.result_text = gui.add_markdown("")
        self.to_hand.on_click(lambda _event: self.move_gizmo_to_hand())
        self.plan_button.on_click(lambda _event: self._guarded(self.plan))
        self.execute_button.on_click(lambda _event: self._guarded(self.execute))
        self.stop_button.on_click(lambda _event: self._guarded(self.stop))

    def show_status(self, status: ExecutorStatus) -> None:
        self.progress.value = float(np.clip(status.progress, 0.0, 1.0) * 100.0)
        lines = [f"**{status.state}** `{status.trajectory_id or '-'}` "
                 f"{status.time_from_start_s:.1f} / {status.duration_s:.1f} s, last result: {status.last_result}"]
        if status.error_code:
            lines.append(f"error `{status.error_code}`: {status.error_message}")
        text = "\n\n".join(lines)
        if self.status_text.content != text:
            self.status_text.content = text

    def move_gizmo_to_hand(self) -> bool:
        state = self.client.joint_state
        pose = None if state is None else self.layers.end_effector_pose(state.names, state.position.tolist())
        if pose is None:
            return False
        self.gizmo.position = pose[:3, 3]
        self.gizmo.wxyz = wxyz_of(pose[:3, :3])
        return True

    def _guarded(self, action: Callable[[], str]) -> None:
        """Run one query at a time from the GUI; a failure is shown, never raised into viser."""
        if not self._busy.acquire(blocking=False):
            self.result_text.content = "busy: the last request has not finished"
            return
        try:
            self.result_text.content = action()
        except QueryFailed as exc:
            self.result_text.content = f"no reply: {exc}"
        except Exception as exc:  # the GUI stays usable whatever a request does
            log.exception("view: GUI action failed")
            self.result_text.content = f"failed: {type(exc).__name__}: {exc}"
        finally:
            self._busy.release()

    def plan(self) -> str:
        w, x, y, z = (float(v) for v in self.gizmo.wxyz)
        quat_xyzw = (x, y, z, w) if self.keep_orientation.value else None
        self.result_text.content = "planning..."
        reply = self.client.plan_to_pose(tuple(float(v) for v in self.gizmo.position), quat_xyzw,
                                         timeout_s=PLAN_TIMEOUT_S, request_id="view")
        if isinstance(reply, ErrorReply):
            if reply.code in IN_COLLISION_CODES:
                return self._show_collision(reply)
            return f"plan failed: `{reply.code}` {reply.message}"
        assert isinstance(reply, PlanResponse)
        self.layers.planning.clear_collision()
        self._planned = (tuple(reply.joint_names), reply.path)
        self.layers.show_path(reply.joint_names, reply.path, executed=False)
        self.execute_button.disabled = False
        return (f"planned with {reply.planner_id}: {reply.waypoint_count} waypoints, "
                f"{reply.path_length_rad:.2f} rad, {reply.planning_time_s * 1e3:.0f} ms")

    def _show_collision(self, reply: ErrorReply) -> str:
        """Mark what the planner says collides; the text names it too."""
        robot = self.layers.robot
        collision = collision_from_details(reply.details, robot.link_names, robot.dof)
        state = self.client.joint_state
        current = None if state is None else positions_by_name(state.names, state.position.tolist(), robot.joint_names)
        self.layers.planning.show_collision(collision, None if current is None else np.asarray(current))
        if collision.which == "goal" and collision.positions is not None:
            self.layers.show_ghost(collision.positions)
        named = [*collision.links, *collision.objects, *(["occupancy"] if collision.occupancy else [])]
        where = f"; colliding (in red): {', '.join(named)}" if named else ""
        return f"plan failed: `{reply.code}` {reply.message}{where}"

    def execute(self) -> str:
        if self._planned is None:
            return "plan first"
        names, path = self._planned
        reply = self.client.execute(path, joint_names=names)
        if isinstance(reply, ErrorReply):
            return f"execute failed: `{reply.code}` {reply.message}"
        assert isinstance(reply, ExecuteResponse)
        self._planned = None
        self.execute_button.disabled = True
        return f"executing `{reply.trajectory_id}` ({reply.duration_s:.1f} s)"

    def stop(self) -> str:
        reply = self.client.stop()
        if isinstance(reply, ErrorReply):
            return f"stop failed: `{reply.code}` {reply.message}"
        return f"stop: executor {reply.state}"
