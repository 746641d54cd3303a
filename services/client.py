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

from robonav.pipeline.wire.codec import Message, ProtocolError
from robonav.pipeline.wire.codes import ExecutionState
from robonav.pipeline.wire.messages import (
    ContactsRequest,
    ContactsResponse,
    ErrorReply,
    ExecuteRequest,
    ExecuteResponse,
    ExecutorStatus,
    JointState,
    Occupancy,
    PlanRequest,
    PlanResponse,
    SceneRequest,
    SceneResponse,
    StopRequest,
    StopResponse,
    decode_reply,
)
from robonav.services.common import declare_latched_subscriber
from robonav.services.keys import Keys

M = TypeVar("M", bound=Message)


def _replier(reply: zenoh.Reply) -> str | None:
    return str(reply.replier_id.zid) if reply.replier_id is not None else None


class QueryFailed(RuntimeError):
    """No reply arrived (nobody answered the key, or the timeout passed)."""


def _no_reply(key: str, timeout_s: float, started: float) -> QueryFailed:
    # Zenoh drops a query that access control denies without telling the sender, so silence
    # is all a refused client sees: say so, rather than leave it to guess.
    return QueryFailed(
        f"no reply on {key} after {time.monotonic() - started:.1f} s (timeout {timeout_s} s): no service answered. "
        "It is not running or not reachable, died while handling the request, or the router's access "
        "control denied this client (Zenoh drops denied messages without an error)")


def query_one(session: zenoh.Session, key: str, request: Message, expected: type[M],
              timeout_s: float) -> tuple[M | ErrorReply, str | None]:
    """Ask the best-matching service on `key` for one reply; returns it and the replier's Zenoh id.

    Raises:
        QueryFailed: nothing answered within `timeout_s`.
    """
    started = time.monotonic()
    for reply in session.get(key, payload=request.to_wire(), timeout=timeout_s):
        sample = reply.ok if reply.ok is not None else reply.err
        return decode_reply(sample.payload.to_bytes(), expected), _replier(reply)  # type: ignore[return-value]
    raise _no_reply(key, timeout_s, started)


def trajectory_outcome(status: ExecutorStatus) -> str:
    """A finished trajectory's outcome: its last_result when idle ('succeeded'), else the state ('stopped', 'error')."""
    return (status.last_result if status.state is ExecutionState.IDLE else status.state).value


class RobonavClient:
    """Subscribes to joint states, occupancy and executor status; sends queries."""

    def __init__(self, session: zenoh.Session, cell: str = "arm0") -> None:
        self.session = session
        self.keys = Keys(cell)
        self.last_replier: str | None = None
        """Zenoh id of the session that sent the reply the last query or race returned."""
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
        """Ask the best-matching service on `key` (one of several planner replicas) for one reply."""
        message, self.last_replier = query_one(self.session, key, request, expected, timeout_s)
        return message

    def race(self, key: str, request: Message, expected: type[M], timeout_s: float) -> M | ErrorReply:
        """Send to every service on `key` at once; return the first success as soon as it arrives.

        Without a success, the first error reply once every service answered or died (a dead
        one is dropped by the router) or the timeout passed; `QueryFailed` if nothing answered.
        """
        started = time.monotonic()
        first_error: ErrorReply | None = None
        error_replier: str | None = None
        # Consolidation NONE hands over each reply as it arrives; the default waits for all of them.
        replies = self.session.get(key, payload=request.to_wire(), target=zenoh.QueryTarget.ALL,
                                   consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s)
        for reply in replies:
            sample = reply.ok if reply.ok is not None else reply.err
            try:
                message = decode_reply(sample.payload.to_bytes(), expected)
            except ProtocolError:
                continue  # a malformed reply is not a valid one; others may still come
            if not isinstance(message, ErrorReply):
                self.last_replier = _replier(reply)
                return message  # type: ignore[return-value]
            if first_error is None:
                first_error, error_replier = message, _replier(reply)
        if first_error is None:
            raise _no_reply(key, timeout_s, started)
        self.last_replier = error_replier
        return first_error

    def plan(self, goal_rad: np.ndarray, *, timeout_s: float = 30.0, race: bool = False,
             **fields) -> PlanResponse | ErrorReply:  # noqa: ANN003
        """Plan to a joint goal; `race` asks every planner and takes the first valid plan."""
        return self.plan_request(PlanRequest(goal_positions=np.asarray(goal_rad, float), **fields),
                                 timeout_s=timeout_s, race=race)

    def plan_request(self, request: PlanRequest, *, timeout_s: float = 30.0, race: bool = False,
                     ) -> PlanResponse | ErrorReply:
        """Any plan request: a goal set, a Cartesian goal, workspace bounds, ...

        One planner (Zenoh's best match) answers, or with `race` all of them and the first
        valid plan wins. Either way a planner that dies mid-request costs at most `timeout_s`.
        """
        ask = self.race if race else self.query
        return ask(self.keys.plan, request, PlanResponse, timeout_s)

    def plan_to_pose(self, position_m: Sequence[float], quat_xyzw: Sequence[float] | None = None, *,
                     timeout_s: float = 30.0, race: bool = False, **fields) -> PlanResponse | ErrorReply:  # noqa: ANN003
        """Plan to a Cartesian goal for `goal_link` (default: the end-effector); no quaternion = any orientation."""
        request = PlanRequest(goal_position_m=np.asarray(position_m, float),
                              goal_quat_xyzw=None if quat_xyzw is None else np.asarray(quat_xyzw, float), **fields)
        return self.plan_request(request, timeout_s=timeout_s, race=race)

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

    def trajectory_finished(self, trajectory_id: str) -> bool:
        """Whether the latest status reports `trajectory_id` done, stopped or failed."""
        s = self.status
        return s is not None and s.trajectory_id == trajectory_id and s.state.finished

    def wait_for_trajectory(self, trajectory_id: str, timeout_s: float) -> str:
        """Wait until the executor reports `trajectory_id` finished; returns `trajectory_outcome` ('timeout' if not)."""
        if not self.wait_for(lambda: self.trajectory_finished(trajectory_id), timeout_s):
            return "timeout"
        assert self.status is not None
        return trajectory_outcome(self.status)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
