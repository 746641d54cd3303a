"""Simulation settings: physics rate, how the arm follows setpoints, obstacles, camera noise, scripts."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from robonav.pipeline.config import require
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.motion import ObjectMotion
from robonav.pipeline.sim.noise import DepthNoiseConfig
from robonav.pipeline.sim.scenes import ClutterConfig


@dataclass(frozen=True)
class SimConfig:
    """One pybullet world: its rates, the joint-following model and its obstacles.

    `follow` chooses how the simulated arm tracks the executor's setpoints:

    * ``"dynamic"``: position-controlled joint motors track the setpoint position and
      velocity through a physics step. The arm has mass, is torque-limited and is stopped
      by obstacles, so tracking lag, overshoot and contact forces are realistic-ish; the
      state lags the setpoint by a few physics steps.
    * ``"kinematic"``: every step writes the setpoint straight into the joint state (no
      dynamics, no gravity effect) and only runs collision detection. Tracking is exact
      and deterministic, which suits planner/executor tests, but the arm passes through
      obstacles (contacts are still reported) and infeasible setpoints go unnoticed.
    """

    physics_rate_hz: float = 240.0
    """Physics steps per simulated second; one `SimWorld.step()` advances 1/physics_rate_hz [s]."""
    joint_state_rate_hz: float = 100.0
    """Rate at which the sim service publishes joint states [Hz]."""
    realtime: bool = True
    """The sim service paces steps to wall time; the world itself never sleeps."""
    follow: Literal["dynamic", "kinematic"] = "dynamic"
    """How the arm follows setpoints (see the class docstring)."""
    objects: tuple[SceneObject, ...] = ()
    """Static obstacles (mass 0) placed in the world."""
    gravity: bool = True
    """Apply -9.81 m/s^2 along world z (only matters in "dynamic" mode)."""
    noise: DepthNoiseConfig = field(default_factory=DepthNoiseConfig)
    """Depth noise of every simulated camera (see `DepthNoiseConfig`)."""
    camera_noise: dict[str, DepthNoiseConfig] = field(default_factory=dict)
    """Camera id -> its own noise model, replacing `noise` for that camera."""
    labels: bool = True
    """Publish per-point (and per-pixel) object labels with every frame."""
    motions: tuple[ObjectMotion, ...] = ()
    """Scripted obstacle motions, armed when the sim starts (see `ObjectMotion`)."""
    clutter: ClutterConfig = field(default_factory=ClutterConfig)
    """Procedural scenes (`robonav campaign`): the table and what is put on it."""
    setpoint_timeout_s: float = 0.2
    """Setpoint watchdog (Franka's communication watchdog, a UR's RTDE watchdog): after this long
    without a followed setpoint while the commanded motion moves, the arm brakes to rest on its
    own [s]. Until then the joints keep the last setpoint's velocity (a first-order hold)."""
    setpoint_slack_s: float = 0.02
    """Timing slack of the setpoint acceptance rule (`pipeline/sim/driver.py`): a setpoint may
    differ from the continuation of the last one by what the arm's limits allow in this much
    time [s]."""

    def __post_init__(self) -> None:
        require(math.isfinite(self.physics_rate_hz) and self.physics_rate_hz > 0,
                f"sim.physics_rate_hz must be a finite value > 0, got {self.physics_rate_hz}")
        require(math.isfinite(self.joint_state_rate_hz) and self.joint_state_rate_hz > 0,
                f"sim.joint_state_rate_hz must be a finite value > 0, got {self.joint_state_rate_hz}")
        require(self.joint_state_rate_hz <= self.physics_rate_hz,
                f"sim.joint_state_rate_hz ({self.joint_state_rate_hz}) must not exceed "
                f"sim.physics_rate_hz ({self.physics_rate_hz}): states only change once per physics step")
        require(math.isfinite(self.setpoint_timeout_s) and self.setpoint_timeout_s > 0,
                f"sim.setpoint_timeout_s must be a finite value > 0, got {self.setpoint_timeout_s}")
        require(math.isfinite(self.setpoint_slack_s) and self.setpoint_slack_s >= 0,
                f"sim.setpoint_slack_s must be a finite value >= 0, got {self.setpoint_slack_s}")
        require(self.follow in ("dynamic", "kinematic"),
                f"sim.follow must be 'dynamic' or 'kinematic', got {self.follow!r}")
        names = [obj.name for obj in self.objects]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        require(not duplicates, f"sim.objects has duplicate names: {duplicates}")
        require("robot" not in names, "sim.objects must not contain an object named 'robot' (reserved label)")
