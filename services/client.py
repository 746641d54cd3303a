"""A small Python client for the protocol: plan, execute, wait, read state.

Any language can do the same with Zenoh and msgpack alone (see `examples/plan_client.py`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from typing import Any, TypeVar

import numpy as np
import zenoh

from robonav.pipeline.wire.codec import Message, ProtocolError, unpack
from robonav.pipeline.wire.codes import ErrorCode, ExecutionState
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
)
from robonav.services.common import declare_latched_subscriber
from robonav.services.keys import Keys

log = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)


def _replier(reply: zenoh.Reply) -> str | None:
    return str(reply.replier_id.zid) if reply.replier_id is not None else None


class QueryFailed(RuntimeError):
    """A query got no reply of the protocol: nobody answered before the timeout, or Zenoh ended
    it with an error of its own (its text, e.g. "Timeout"), or the reply was not a message.

    Attributes: key, timeout_s, reason (what happened, with Zenoh's text when it sent one).
    """

    def __init__(self, key: str, timeout_s: float, reason: str) -> None:
        super().__init__(f"{key}: {reason} (query timeout {timeout_s:g} s)")
        self.key = key
        self.timeout_s = timeout_s
        self.reason = reason


KNOWN_CODES = frozenset(code.value for code in ErrorCode)


def error_reply(payload: bytes) -> ErrorReply | None:
    """The payload as a structured error (a msgpack map with `ok: false` and a string `code`),
    or None when it is not one.

    Read leniently, so that a peer of another version still gets its error across: a code this
    version does not know becomes INTERNAL_ERROR (docs/protocol.md), its own code kept at the
    front of the message and in `details.code`; keys beyond code, message and details are ignored.
    """
    try:
        obj = unpack(payload)
    except ProtocolError:
        return None
    if not isinstance(obj, dict) or obj.get("ok") is not False or not isinstance(obj.get("code"), str):
        return None
    message = obj.get("message") if isinstance(obj.get("message"), str) else ""
    details: dict[str, Any] = dict(obj["details"]) if isinstance(obj.get("details"), dict) else {}
    code = obj["code"]
    if code not in KNOWN_CODES:
        return ErrorReply(code=ErrorCode.INTERNAL_ERROR.value, message=f"{code}: {message}",
                          details={**details, "code": code})
    return ErrorReply(code=code, message=message, details=details)


def _zenoh_text(payload: bytes, limit: int = 200) -> str:
    text = payload.decode("utf-8", errors="replace")
    return repr(text if len(text) <= limit else text[:limit] + "...")


def reply_message(reply: zenoh.Reply, key: str, expected: type[M], timeout_s: float, started: float) -> M | ErrorReply:
    """The one rule for a reply to a protocol query (every caller of this package uses it).

    A structured error map, whether it came as `reply.err` or as an ordinary reply, is an
    `ErrorReply`; an ordinary reply is decoded as `expected`. Anything else is `QueryFailed`:
    Zenoh's own errors (their payload is Zenoh's text, such as "Timeout" when the query's
    timeout passed without a reply) and payloads that are not messages.

    Raises:
        QueryFailed: naming the key, the timeout and what came back.
    """
    sample = reply.ok if reply.ok is not None else reply.err
    payload = sample.payload.to_bytes()
    error = error_reply(payload)
    if error is not None:
        return error
    elapsed_s = time.monotonic() - started
    if reply.ok is None:
        raise QueryFailed(key, timeout_s, f"Zenoh ended the query with its own error after {elapsed_s:.1f} s: "
                                          f"{_zenoh_text(payload)}")
    try:
        return expected.from_wire(payload)
    except ProtocolError as exc:
        raise QueryFailed(key, timeout_s, f"the reply is not a {expected.__name__}: {exc.message}") from exc


def _no_reply(key: str, timeout_s: float, started: float) -> QueryFailed:
    # Zenoh drops a query that access control denies without telling the sender, so silence
    # is all a refused client sees: say so, rather than leave it to guess.
    return QueryFailed(
        key, timeout_s,
        f"no reply after {time.monotonic() - started:.1f} s: no service answered. "
        "It is not running or not reachable, died while handling the request, or the router's access "
        "control denied this client (Zenoh drops denied messages without an error)")


def query_one(session: zenoh.Session, key: str, request: Message, expected: type[M],
              timeout_s: float) -> tuple[M | ErrorReply, str | None]:
    """Ask the best-matching service on `key` for one reply; returns it and the replier's Zenoh id.

    Consolidation NONE hands the reply over the moment it arrives; Zenoh's default holds it
    until the query ends, and a query the service does not end in time (see
    `services.common.answer_query`) then ends in Zenoh's "Timeout" error with the reply
    arriving after it.

    Raises:
        QueryFailed: nothing answered within `timeout_s`, or the reply was not of the protocol.
    """
    started = time.monotonic()
    for reply in session.get(key, payload=request.to_wire(), timeout=timeout_s,
                             consolidation=zenoh.ConsolidationMode.NONE):
        return reply_message(reply, key, expected, timeout_s, started), _replier(reply)
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
        self.dropped: dict[str, int] = {}
        """Malformed publications dropped, per attribute (`joint_state`, `occupancy`, ...)."""
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
            try:
                message = cls.from_wire(sample.payload.to_bytes())
            except ProtocolError as exc:
                # Someone else's malformed publication: the last good message stays, and the
                # client's user sees one warning per topic, not a traceback per sample.
                with self._cond:
                    self.dropped[attr] = self.dropped.get(attr, 0) + 1
                    first = self.dropped[attr] == 1
                if first:
                    log.warning("dropped a malformed %s on %s (%s: %s); further ones are counted in "
                                "RobonavClient.dropped", cls.__name__, sample.key_expr, exc.code.value, exc.message)
                return
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
        one is dropped by the router) or the timeout passed; `QueryFailed` if no replier sent a
        reply of the protocol.
        """
        started = time.monotonic()
        first_error: ErrorReply | None = None
        error_replier: str | None = None
        # Consolidation NONE hands over each reply as it arrives; the default waits for all of them.
        replies = self.session.get(key, payload=request.to_wire(), target=zenoh.QueryTarget.ALL,
                                   consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s)
        failure: QueryFailed | None = None
        for reply in replies:
            try:
                message = reply_message(reply, key, expected, timeout_s, started)
            except QueryFailed as exc:
                failure = failure or exc  # not a valid reply; others may still come
                continue
            if not isinstance(message, ErrorReply):
                self.last_replier = _replier(reply)
                return message  # type: ignore[return-value]
            if first_error is None:
                first_error, error_replier = message, _replier(reply)
        if first_error is None:
            raise failure or _no_reply(key, timeout_s, started)
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
