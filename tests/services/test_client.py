"""The client's one rule for replies, against real Zenoh queryables that answer late, never,
with Zenoh's own error text, with garbage, or with an error code this version does not know."""

from __future__ import annotations

import threading
import time

import msgpack
import numpy as np
import pytest
import zenoh

from robonav.pipeline.wire.messages import ErrorReply, JointState, StopRequest, StopResponse
from robonav.services.client import QueryFailed, RobonavClient, error_reply, query_one

from .conftest import StandInPeer

KEY = "robonav/arm0/executor/stop"


def _serve(bus: tuple[zenoh.Session, zenoh.Session], answer) -> StandInPeer:  # noqa: ANN001
    """A stand-in service on KEY calling `answer(query)`, once the client side sees it."""
    return StandInPeer(bus[0], KEY, answer, observer=bus[1])


def _ask(client: zenoh.Session, timeout_s: float) -> StopResponse | ErrorReply:
    reply, _ = query_one(client, KEY, StopRequest(), StopResponse, timeout_s)
    return reply  # type: ignore[return-value]


def _error_map(code: str, message: str = "why", **extra: object) -> bytes:
    return msgpack.packb({"v": 1, "ok": False, "code": code, "message": message, "details": {"key": "x"}, **extra})


def test_a_reply_arrives_although_the_peer_never_ends_the_query(bus: tuple[zenoh.Session, zenoh.Session]) -> None:
    # A peer that replies but holds on to the query (as a reference cycle once did): Zenoh's
    # default consolidation would hold the reply until the timeout and deliver "Timeout" first.
    _, client = bus
    peer = _serve(bus, lambda q: q.reply(q.key_expr, StopResponse(state="idle").to_wire()))
    started = time.monotonic()
    reply = _ask(client, timeout_s=10.0)
    assert isinstance(reply, StopResponse) and reply.state == "idle"
    assert time.monotonic() - started < 9.0, "the reply waited for the query to end"
    peer.close()


def test_a_late_reply_within_the_timeout_is_taken(bus: tuple[zenoh.Session, zenoh.Session]) -> None:
    _, client = bus

    repliers: list[threading.Thread] = []

    def later(query: zenoh.Query) -> None:
        def run() -> None:
            time.sleep(1.0)
            query.reply(query.key_expr, StopResponse(state="stopped").to_wire())
        repliers.append(threading.Thread(target=run, daemon=True))
        repliers[-1].start()

    peer = _serve(bus, later)
    reply = _ask(client, timeout_s=10.0)
    assert isinstance(reply, StopResponse) and reply.state == "stopped"
    for replier in repliers:
        replier.join(5.0)
    peer.close()


@pytest.mark.parametrize("timeout_s", [0.5])
def test_a_silent_or_too_slow_peer_is_query_failed_naming_key_timeout_and_zenohs_text(
        bus: tuple[zenoh.Session, zenoh.Session], timeout_s: float) -> None:
    _, client = bus
    peer = _serve(bus, lambda q: None)
    with pytest.raises(QueryFailed) as failed:
        _ask(client, timeout_s=timeout_s)
    text = str(failed.value)
    assert KEY in text and f"{timeout_s:g} s" in text and "'Timeout'" in text, text
    assert failed.value.key == KEY and failed.value.timeout_s == timeout_s
    peer.close()


def test_nobody_serving_the_key_is_query_failed(bus: tuple[zenoh.Session, zenoh.Session]) -> None:
    _, client = bus
    with pytest.raises(QueryFailed, match="no service answered"):
        _ask(client, timeout_s=0.5)


@pytest.mark.parametrize("payload", [b"Timeout", b"\x00\xff garbage", b"", msgpack.packb([1, 2, 3]),
                                     msgpack.packb({"ok": False, "message": "no code"})])
def test_an_error_reply_that_is_not_an_error_map_is_query_failed(
        bus: tuple[zenoh.Session, zenoh.Session], payload: bytes) -> None:
    _, client = bus
    peer = _serve(bus, lambda q: q.reply_err(payload))
    with pytest.raises(QueryFailed, match="its own error") as failed:
        _ask(client, timeout_s=5.0)
    assert KEY in str(failed.value)
    peer.close()


def test_an_ordinary_reply_that_is_not_the_message_is_query_failed(bus: tuple[zenoh.Session, zenoh.Session]) -> None:
    _, client = bus
    peer = _serve(bus, lambda q: q.reply(q.key_expr, b"\x92\x01"))
    with pytest.raises(QueryFailed, match="not a StopResponse"):
        _ask(client, timeout_s=5.0)
    peer.close()


@pytest.mark.parametrize("as_error", [True, False])
def test_an_error_map_is_an_error_reply_as_an_error_or_as_an_ordinary_reply(
        bus: tuple[zenoh.Session, zenoh.Session], as_error: bool) -> None:
    _, client = bus
    payload = _error_map("NO_JOINT_STATE")
    peer = _serve(bus, (lambda q: q.reply_err(payload)) if as_error else (lambda q: q.reply(q.key_expr, payload)))
    reply = _ask(client, timeout_s=5.0)
    assert isinstance(reply, ErrorReply) and reply.code == "NO_JOINT_STATE" and reply.details == {"key": "x"}
    peer.close()


def test_an_unknown_code_is_internal_error_keeping_the_code(bus: tuple[zenoh.Session, zenoh.Session]) -> None:
    # A peer of a newer version: an unknown code, and a key this version does not know.
    _, client = bus
    peer = _serve(bus, lambda q: q.reply_err(_error_map("ARM_ON_FIRE", "too hot", hint="later")))
    reply = _ask(client, timeout_s=5.0)
    assert isinstance(reply, ErrorReply) and reply.code == "INTERNAL_ERROR"
    assert reply.message == "ARM_ON_FIRE: too hot" and reply.details == {"key": "x", "code": "ARM_ON_FIRE"}
    peer.close()


def test_error_reply_reads_only_error_maps() -> None:
    assert error_reply(_error_map("BUSY")) == ErrorReply(code="BUSY", message="why", details={"key": "x"})
    assert error_reply(StopResponse(state="idle").to_wire()) is None
    assert error_reply(b"Timeout") is None


def test_a_race_with_only_unusable_replies_is_query_failed(bus: tuple[zenoh.Session, zenoh.Session]) -> None:
    _, client = bus
    peer = _serve(bus, lambda q: q.reply_err(b"Timeout"))
    robonav = RobonavClient(client)
    with pytest.raises(QueryFailed, match="'Timeout'"):
        robonav.race(KEY, StopRequest(), StopResponse, 5.0)
    robonav.close()
    peer.close()


def test_malformed_publications_are_dropped_and_counted_keeping_the_last_good_one(
        bus: tuple[zenoh.Session, zenoh.Session]) -> None:
    publisher, session = bus
    client = RobonavClient(session)
    try:
        good = JointState(stamp=1.0, names=("a", "b"), position=np.array([0.1, 0.2]), velocity=np.zeros(2))
        for payload in (b"\xc1 not msgpack", msgpack.packb({"v": 1, "stamp": "soon"}), good.to_wire(),
                        msgpack.packb([1, 2, 3])):
            publisher.put(client.keys.joint_states, payload)
        assert client.wait_for(lambda: client.dropped.get("joint_state", 0) == 3 and client.joint_state is not None,
                               5.0), client.dropped
        np.testing.assert_array_equal(client.joint_state.position, good.position)
    finally:
        client.close()
