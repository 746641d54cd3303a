"""Zenoh key expressions, all under `robonav/<cell>/`."""

from __future__ import annotations

from dataclasses import dataclass

SERVICES: tuple[str, ...] = ("sim", "perception", "planner", "executor")


@dataclass(frozen=True)
class Keys:
    cell: str = "arm0"

    @property
    def root(self) -> str:
        return f"robonav/{self.cell}"

    def camera_cloud(self, camera_id: str) -> str:
        return f"{self.root}/camera/{camera_id}/cloud"

    @property
    def all_camera_clouds(self) -> str:
        return f"{self.root}/camera/*/cloud"

    def camera_depth(self, camera_id: str) -> str:
        return f"{self.root}/camera/{camera_id}/depth"

    @property
    def all_camera_depths(self) -> str:
        return f"{self.root}/camera/*/depth"

    @property
    def joint_states(self) -> str:
        return f"{self.root}/robot/joint_states"

    @property
    def occupancy(self) -> str:
        return f"{self.root}/perception/occupancy"

    @property
    def clusters(self) -> str:
        return f"{self.root}/perception/clusters"

    @property
    def perception_clear(self) -> str:
        return f"{self.root}/perception/clear"

    @property
    def perception_status(self) -> str:
        return f"{self.root}/perception/status"

    @property
    def plan(self) -> str:
        return f"{self.root}/planner/plan"

    @property
    def scene(self) -> str:
        return f"{self.root}/planner/scene"

    @property
    def scene_state(self) -> str:
        """The planner's whole scene, latched, on every change (the executor checks executes against it)."""
        return f"{self.root}/planner/scene_state"

    @property
    def robot_description(self) -> str:
        """The robot the planner plans for (URDF, planning joints, limits), latched (discovery)."""
        return f"{self.root}/robot/description"

    @property
    def cameras(self) -> str:
        """Every camera of the cell (intrinsics, world_from_camera, output), latched by the sim (discovery)."""
        return f"{self.root}/cameras"

    @property
    def execute(self) -> str:
        return f"{self.root}/executor/execute"

    @property
    def stop(self) -> str:
        return f"{self.root}/executor/stop"

    @property
    def setpoint(self) -> str:
        return f"{self.root}/executor/setpoint"

    @property
    def status(self) -> str:
        return f"{self.root}/executor/status"

    @property
    def executor_path(self) -> str:
        return f"{self.root}/executor/path"

    @property
    def contacts(self) -> str:
        return f"{self.root}/sim/contacts"

    @property
    def contact_events(self) -> str:
        return f"{self.root}/sim/contacts/events"

    @property
    def sim_objects(self) -> str:
        return f"{self.root}/sim/objects"

    @property
    def sim_stats(self) -> str:
        return f"{self.root}/sim/stats"

    @property
    def stack_status(self) -> str:
        return f"{self.root}/stack/status"

    def alive(self, service: str) -> str:
        return f"{self.root}/alive/{service}"

    def alive_instance(self, service: str, instance: str) -> str:
        """One replica's token (`alive/<service>/<instance>`); `alive/*` does not match it."""
        return f"{self.root}/alive/{service}/{instance}"

    @property
    def all_alive(self) -> str:
        return f"{self.root}/alive/*"
