"""What a campaign watches on the wire: setpoint limits, contact events and perception latency."""

from __future__ import annotations

import threading
import time

import numpy as np
import zenoh

from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.wire.messages import ContactEvent, Occupancy, Setpoint
from robonav.services.config import RobonavConfig
from robonav.services.keys import Keys

LIMIT_TOLERANCE = 1e-6
"""Relative slack on velocity/acceleration limits and absolute slack on positions [rad]."""


class Monitors:
    """Subscribers that count what the campaign reports; thread-safe counters."""

    def __init__(self, session: zenoh.Session, cfg: RobonavConfig, robot: RobotModel) -> None:
        self._lock = threading.Lock()
        self._names = cfg.robot.joint_names
        self._lower, self._upper = robot.lower_limits_rad, robot.upper_limits_rad
        self._max_velocity = np.asarray(cfg.robot.max_velocity_rad_s, dtype=np.float64)
        self._max_acceleration = np.asarray(cfg.robot.max_acceleration_rad_s2, dtype=np.float64)
        self.setpoints = 0
        self.limit_violations = 0
        self.violation_examples: list[str] = []
        self.contact_begins = 0
        self.contact_examples: list[str] = []
        self.perception_latency_s: list[float] = []
        self._trajectory_id = ""
        """Of the newest setpoint: which motion a contact happened in."""
        keys = Keys(cfg.cell)
        self._subs = [
            session.declare_subscriber(keys.setpoint, self._on_setpoint),
            session.declare_subscriber(keys.contact_events, self._on_contact),
            session.declare_subscriber(keys.occupancy, self._on_occupancy),
        ]

    def _on_setpoint(self, sample: zenoh.Sample) -> None:
        try:
            sp = Setpoint.from_wire(sample.payload.to_bytes())
        except ValueError:
            return
        order = [sp.names.index(n) for n in self._names] if sp.names != self._names else slice(None)
        q, qd, qdd = sp.position[order], sp.velocity[order], sp.acceleration[order]
        bad = []
        if np.any(q < self._lower - LIMIT_TOLERANCE) or np.any(q > self._upper + LIMIT_TOLERANCE):
            bad.append(f"position {np.round(q, 4).tolist()}")
        if np.any(np.abs(qd) > self._max_velocity * (1 + LIMIT_TOLERANCE)):
            bad.append(f"velocity {np.round(qd, 4).tolist()}")
        if np.any(np.abs(qdd) > self._max_acceleration * (1 + LIMIT_TOLERANCE)):
            bad.append(f"acceleration {np.round(qdd, 3).tolist()}")
        with self._lock:
            self.setpoints += 1
            self._trajectory_id = sp.trajectory_id
            if bad:
                self.limit_violations += 1
                if len(self.violation_examples) < 5:
                    self.violation_examples.append(f"{sp.trajectory_id}: {'; '.join(bad)}")

    def _on_contact(self, sample: zenoh.Sample) -> None:
        event = ContactEvent.from_wire(sample.payload.to_bytes())
        if event.event == "begin":
            with self._lock:
                self.contact_begins += 1
                if len(self.contact_examples) < 20:
                    self.contact_examples.append(f"{event.link}|{event.object} {event.distance_m:.4f} m "
                                                 f"in {self._trajectory_id or 'no trajectory'}")

    def _on_occupancy(self, sample: zenoh.Sample) -> None:
        arrived = time.time()
        stamp = Occupancy.from_wire(sample.payload.to_bytes()).stamp
        with self._lock:
            self.perception_latency_s.append(arrived - stamp)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
