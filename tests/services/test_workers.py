"""Queries answered off Zenoh's callback thread: a bounded queue, BUSY when full, and every
query ended when its handler returns (real Zenoh sessions through a router)."""

from __future__ import annotations

import gc
import sys
import threading
import time

import pytest
import zenoh

from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.messages import ErrorReply, StopRequest, StopResponse
from robonav.services.client import QueryFailed, query_one, reply_message
from robonav.services.common import guarded_queryable
from robonav.services.workers import RequestWorkers

from .conftest import wait_until_served

KEY = "robonav/arm0/executor/stop"
OTHER = "robonav/arm0/executor/execute"


def _ask(client: zenoh.Session, key: str = KEY, timeout_s: float = 10.0) -> StopResponse | ErrorReply:
    return query_one(client, key, StopRequest(), StopResponse, timeout_s)[0]  # type: ignore[return-value]


def _reply(query: zenoh.Query, state: str = "idle") -> None:
    query.reply(query.key_expr, StopResponse(state=state).to_wire())


def test_a_query_ends_when_its_handler_returns_even_if_a_cycle_still_holds_it(
        bus: tuple[zenoh.Session, zenoh.Session]) -> None:
    """Numba's first compile left the handler's frame, and so the query, in a reference cycle:
    the query never ended, and a client with Zenoh's default consolidation got "Timeout"."""
    service, client = bus
    cycles: list[object] = []

    def handler(query: zenoh.Query) -> None:
        _reply(query)
        try:
            raise ValueError("kept")
        except ValueError as exc:
            cycles.append(exc)  # its traceback holds this frame, which holds `query`
        assert sys.getrefcount(query) > 2

    gc.disable()
    try:
        queryable = service.declare_queryable(KEY, guarded_queryable(handler, "test"))
        wait_until_served(client, KEY)
        replies = list(client.get(KEY, payload=StopRequest().to_wire(), timeout=5.0))  # default consolidation
        assert [r.ok is not None for r in replies] == [True], [r.err.payload.to_bytes() for r in replies if r.err]
    finally:
        gc.enable()
    queryable.undeclare()


def test_long_work_runs_off_the_callback_thread_and_a_full_queue_answers_busy(
        bus: tuple[zenoh.Session, zenoh.Session]) -> None:
    service, client = bus
    release = threading.Event()
    started: list[int] = []

    def slow(query: zenoh.Query, worker: int) -> None:
        started.append(worker)
        release.wait(20.0)
        _reply(query, "stopped")

    workers = RequestWorkers("slowpoke", slow, workers=1, queue_size=1)
    queryables = [service.declare_queryable(KEY, workers.callback),
                  service.declare_queryable(OTHER, guarded_queryable(_reply, "quick"))]
    wait_until_served(client, KEY)
    wait_until_served(client, OTHER)
    results: list[StopResponse | ErrorReply] = []
    askers = [threading.Thread(target=lambda: results.append(_ask(client))) for _ in range(2)]
    for asker in askers:  # one runs, one waits in the queue
        asker.start()
        time.sleep(0.3)
    assert started == [0]
    # The callback thread is free: another key of the same session answers at once.
    assert isinstance(_ask(client, OTHER), StopResponse)
    busy = _ask(client)  # the queue is full
    assert isinstance(busy, ErrorReply) and busy.code == ErrorCode.BUSY.value, busy
    assert busy.details == {"workers": 1, "queue_size": 1} and "slowpoke" in busy.message
    assert workers.refused == 1
    release.set()
    for asker in askers:
        asker.join(15.0)
    assert [r.state for r in results if isinstance(r, StopResponse)] == ["stopped", "stopped"], results
    workers.close()
    for q in queryables:
        q.undeclare()


def test_worker_exceptions_become_structured_errors(bus: tuple[zenoh.Session, zenoh.Session]) -> None:
    service, client = bus

    def failing(query: zenoh.Query, worker: int) -> None:
        if query.payload is not None and len(query.payload) > 0:
            raise ProtocolError(ErrorCode.INVALID_REQUEST, "bad", {"key": "emergency"})
        raise RuntimeError("a bug")

    workers = RequestWorkers("failing", failing, workers=2, queue_size=4)
    queryable = service.declare_queryable(KEY, workers.callback)
    wait_until_served(client, KEY)
    invalid = _ask(client)
    assert isinstance(invalid, ErrorReply) and invalid.code == "INVALID_REQUEST" and invalid.details == {"key": "emergency"}
    started = time.monotonic()
    replies = list(client.get(KEY, timeout=5.0))  # an empty payload: the handler's bug
    bug = reply_message(replies[0], KEY, StopResponse, 5.0, started)
    assert isinstance(bug, ErrorReply) and bug.code == "INTERNAL_ERROR" and "a bug" in bug.message
    workers.close()
    queryable.undeclare()


def test_closing_answers_the_waiting_queries_busy(bus: tuple[zenoh.Session, zenoh.Session]) -> None:
    service, client = bus
    release = threading.Event()
    workers = RequestWorkers("closing", lambda q, w: (release.wait(20.0), _reply(q)), workers=1, queue_size=4)
    queryable = service.declare_queryable(KEY, workers.callback)
    wait_until_served(client, KEY)
    results: list[object] = []
    askers = [threading.Thread(target=lambda: results.append(_ask(client))) for _ in range(3)]
    for asker in askers:
        asker.start()
    time.sleep(0.5)
    closer = threading.Thread(target=workers.close)
    closer.start()
    time.sleep(0.3)
    release.set()
    closer.join(10.0)
    for asker in askers:
        asker.join(10.0)
    codes = sorted(r.code if isinstance(r, ErrorReply) else "ok" for r in results)
    assert codes == ["BUSY", "BUSY", "ok"], results
    queryable.undeclare()


def test_closing_waits_once_for_all_running_handlers_not_once_each(bus: tuple[zenoh.Session, zenoh.Session]) -> None:
    service, client = bus
    release = threading.Event()
    started = threading.Semaphore(0)
    workers = RequestWorkers("stuck", lambda q, w: (started.release(), release.wait(30.0), _reply(q)),
                             workers=3, queue_size=4)
    queryable = service.declare_queryable(KEY, workers.callback)
    wait_until_served(client, KEY)
    answers: list[object] = []

    def ask() -> None:
        try:
            answers.append(_ask(client, KEY, 10.0))
        except QueryFailed as exc:
            answers.append(exc)

    askers = [threading.Thread(target=ask, daemon=True) for _ in range(3)]
    for asker in askers:
        asker.start()
    assert all(started.acquire(timeout=10.0) for _ in askers), "the handlers did not start"
    began = time.monotonic()
    workers.close(timeout_s=1.0)
    # Three stuck handlers: one budget of 1 s in all (a budget per thread would take 3 s).
    assert time.monotonic() - began < 2.5
    release.set()  # the abandoned handlers still answer when they end
    for asker in askers:
        asker.join(15.0)
    assert len(answers) == 3 and all(isinstance(a, StopResponse) for a in answers), answers
    queryable.undeclare()


def test_no_queue_is_not_allowed() -> None:
    with pytest.raises(ValueError, match="queue_size"):
        RequestWorkers("x", lambda q, w: None, workers=1, queue_size=0)
