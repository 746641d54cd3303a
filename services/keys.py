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

    @property
    def joint_states(self) -> str:
        return f"{self.root}/robot/joint_states"

    @property
    def occupancy(self) -> str:
        return f"{self.root}/perception/occupancy"

    @property
    def plan(self) -> str:
        return f"{self.root}/planner/plan"

    @property
    def scene(self) -> str:
        return f"{self.root}/planner/scene"

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
    def contacts(self) -> str:
        return f"{self.root}/sim/contacts"

    def alive(self, service: str) -> str:
        return f"{self.root}/alive/{service}"

    @property
    def all_alive(self) -> str:
        return f"{self.root}/alive/*"
