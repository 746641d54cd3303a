"""A small Python client for the protocol: plan, execute, wait, read state.

Any language can do the same with Zenoh and msgpack alone (see `examples/plan_client.py`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from typing import TypeVar

import numpy as np
import zenoh

from robonav.pipeline.messages import (ContactsRequest, ContactsResponse, ErrorReply, ExecuteRequest, ExecuteResponse,
                                       ExecutorStatus, JointState, Occupancy, PlanRequest, PlanResponse, SceneRequest,
                                       SceneResponse, StopRequest, StopResponse, decode_reply)
from robonav.pipeline.wire import Message
from robonav.services.common import declare_latched_subscriber
from robonav.services.keys import Keys

M = TypeVar("M", bound=Message)


class QueryFailed(RuntimeError):
    """No reply arrived (nobody answered the key, or the timeout passed)."""


class RobonavClient:
    """Subscribes to joint states, occupancy and executor status; sends queries."""

    def __init__(self, session: zenoh.Session, cell: str = "arm0") -> None:
        self.session = session
        self.keys = Keys(cell)
        self._cond = threading.Condition()
        self.joint_state: JointState | None = None
        self.occupancy: Occupancy | None = None
        self.status: ExecutorStatus | None = None
        self._subs = [
            session.declare_subscriber(self.keys.joint_states, self._on(JointState, "joint_state")),
            declare_latched_subscriber(session, self.keys.occupancy, self._on(Occupancy, "occupancy")),
            session.declare_subscriber(self.keys.status, self._on(ExecutorStatus, "status")),
        ]

    def _on(self, cls: type[Message], attr: str):  # noqa: ANN202 - a zenoh callback
        def callback(sample: zenoh.Sample) -> None:
            message = cls.from_wire(sample.payload.to_bytes())
            with self._cond:
                setattr(self, attr, message)
                self._cond.notify_all()

        return callback

    def wait_for(self, predicate, timeout_s: float) -> bool:  # noqa: ANN001 - any zero-arg callable
        with self._cond:
            return self._cond.wait_for(predicate, timeout=timeout_s)

    def alive_services(self, timeout_s: float = 1.0) -> set[str]:
        names = set()
        for reply in self.session.liveliness().get(self.keys.all_alive, timeout=timeout_s):
            if reply.ok is not None:
                names.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        return names

    def wait_for_services(self, services: Sequence[str], timeout_s: float) -> set[str]:
        """Poll liveliness tokens until every service is up; returns the missing ones."""
        deadline = time.monotonic() + timeout_s
        missing = set(services)
        while missing and time.monotonic() < deadline:
            missing -= self.alive_services()
            if missing:
                time.sleep(0.2)
        return missing

    def query(self, key: str, request: Message, expected: type[M], timeout_s: float) -> M | ErrorReply:
        for reply in self.session.get(key, payload=request.to_wire(), timeout=timeout_s):
            if reply.ok is not None:
                return decode_reply(reply.ok.payload.to_bytes(), expected)  # type: ignore[return-value]
            return decode_reply(reply.err.payload.to_bytes(), expected)  # type: ignore[return-value]
        raise QueryFailed(f"no reply on {key} within {timeout_s} s")

    def plan(self, goal_rad: np.ndarray, *, timeout_s: float = 30.0, **fields) -> PlanResponse | ErrorReply:  # noqa: ANN003
        return self.query(self.keys.plan, PlanRequest(goal_positions=np.asarray(goal_rad, float), **fields),
                          PlanResponse, timeout_s)

    def plan_request(self, request: PlanRequest, *, timeout_s: float = 30.0) -> PlanResponse | ErrorReply:
        """Any plan request: a goal set, a Cartesian goal, workspace bounds, ..."""
        return self.query(self.keys.plan, request, PlanResponse, timeout_s)

    def plan_to_pose(self, position_m: Sequence[float], quat_xyzw: Sequence[float] | None = None, *,
                     timeout_s: float = 30.0, **fields) -> PlanResponse | ErrorReply:  # noqa: ANN003
        """Plan to a Cartesian goal for `goal_link` (default: the end-effector); no quaternion = any orientation."""
        request = PlanRequest(goal_position_m=np.asarray(position_m, float),
                              goal_quat_xyzw=None if quat_xyzw is None else np.asarray(quat_xyzw, float), **fields)
        return self.plan_request(request, timeout_s=timeout_s)

    def scene(self, request: SceneRequest, *, timeout_s: float = 10.0) -> SceneResponse | ErrorReply:
        """Change or list the planner's collision objects (`planner/scene`)."""
        return self.query(self.keys.scene, request, SceneResponse, timeout_s)

    def execute(self, path: np.ndarray, *, timeout_s: float = 10.0, **fields) -> ExecuteResponse | ErrorReply:  # noqa: ANN003
        return self.query(self.keys.execute, ExecuteRequest(path=np.asarray(path, float), **fields),
                          ExecuteResponse, timeout_s)

    def stop(self, *, emergency: bool = False, timeout_s: float = 5.0) -> StopResponse | ErrorReply:
        return self.query(self.keys.stop, StopRequest(emergency=emergency), StopResponse, timeout_s)

    def contacts(self, *, reset: bool = False, timeout_s: float = 5.0) -> ContactsResponse | ErrorReply:
        return self.query(self.keys.contacts, ContactsRequest(reset=reset), ContactsResponse, timeout_s)

    def wait_for_trajectory(self, trajectory_id: str, timeout_s: float) -> str:
        """Wait until the executor reports `trajectory_id` finished; returns its last_result ('timeout' if not)."""

        def finished() -> bool:
            s = self.status
            return s is not None and s.trajectory_id == trajectory_id and s.state in ("idle", "stopped", "error")

        if not self.wait_for(finished, timeout_s):
            return "timeout"
        assert self.status is not None
        return self.status.last_result if self.status.state == "idle" else self.status.state

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
