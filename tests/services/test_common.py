"""Guarded subscribers over real Zenoh: oversized samples are dropped before decoding and counted."""

from __future__ import annotations

import threading
import time

import zenoh

from robonav.services import common
from robonav.services.common import guarded_subscriber, open_session
from robonav.services.config import LimitsConfig, ZenohConfig

from .conftest import free_port


def test_a_sample_above_the_publication_limit_never_reaches_the_handler() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    session = open_session(ZenohConfig(connect=(endpoint,)))
    received: list[int] = []
    arrived = threading.Event()

    def handler(sample: zenoh.Sample) -> None:
        received.append(len(sample.payload))
        arrived.set()

    callback = guarded_subscriber(handler, "test")
    common.set_max_publication_bytes(1000)
    try:
        subscriber = session.declare_subscriber("robonav/test/big", callback)
        time.sleep(0.2)
        session.put("robonav/test/big", b"x" * 1001)
        session.put("robonav/test/big", b"x" * 1000)
        assert arrived.wait(5.0)
        time.sleep(0.2)
        assert received == [1000]
        assert callback.dropped == {"PAYLOAD_TOO_LARGE": 1}  # type: ignore[attr-defined]
        subscriber.undeclare()
    finally:
        common.set_max_publication_bytes(LimitsConfig().max_publication_bytes)
        session.close()
        router.close()
