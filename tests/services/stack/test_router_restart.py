"""What Zenoh does when the router of client-mode sessions dies and comes back on the same port.

A real `robonav router` process, two client sessions opened as every service and client opens
them (`open_session`, so with robonav's reconnect settings): one serves a query, a liveliness
token, a plain and a latched publisher; the other asks, subscribes and watches. The router is
killed (SIGKILL), a latched sample is published while it is away, and a new router is started on
the same port. Within 10 s of its start the query is answered again, publications flow, the
token is seen again and the latched sample published during the outage arrives: the sessions
reconnect and declare everything again on their own (Zenoh 1.x); robonav only shortens the retry
period (`RECONNECT_RETRY`, Zenoh's default backs off to 4 s).

The same with the real services under `robonav up` is in test_restart.py.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from robonav.services.common import (
    RECONNECT_RETRY,
    declare_latched_publisher,
    declare_latched_subscriber,
    open_session,
    open_session_waiting,
    to_zenoh_config,
)
from robonav.services.config import ZenohConfig

from ..conftest import free_port

pytestmark = pytest.mark.e2e

RECOVERY_LIMIT_S = 10.0
ROUTER_START_TIMEOUT_S = 30.0


class Router:
    """`robonav router` on a fixed endpoint; `kill` and `start` as often as needed."""

    def __init__(self, endpoint: str, config: Path) -> None:
        self.endpoint = endpoint
        self.config = config
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> float:
        """Start it and wait until it accepts a session; returns time.monotonic() of that moment."""
        self.proc = subprocess.Popen([sys.executable, "-m", "robonav.services.cli", "router", "--config", str(self.config),
                                      "--listen", self.endpoint, "--log-level", "WARNING"])
        deadline = time.monotonic() + ROUTER_START_TIMEOUT_S
        while True:
            try:
                open_session(ZenohConfig(connect=(self.endpoint,))).close()
                return time.monotonic()
            except zenoh.ZError:
                assert self.proc.poll() is None, f"the router exited with {self.proc.returncode}"
                assert time.monotonic() < deadline, "the router never listened"
                time.sleep(0.05)

    def kill(self) -> None:
        assert self.proc is not None
        self.proc.kill()
        self.proc.wait(timeout=10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=15)


@pytest.fixture
def router(tmp_path: Path) -> Iterator[Router]:
    from ..conftest import write_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    r = Router(endpoint, write_config(tmp_path, "router.yaml", zenoh={"connect": [endpoint]}))
    r.start()
    yield r
    r.stop()


def _within(limit_s: float, check: Callable[[], bool], period_s: float = 0.05) -> float | None:
    """Seconds until `check()` held, or None if it did not within `limit_s`."""
    started = time.monotonic()
    while time.monotonic() - started < limit_s:
        if check():
            return time.monotonic() - started
        time.sleep(period_s)
    return None


def test_client_sessions_resume_queries_publications_tokens_and_latched_samples(router: Router) -> None:
    cfg = ZenohConfig(connect=(router.endpoint,))
    server, client = open_session(cfg), open_session(cfg)
    received: list[bytes] = []
    latched: list[bytes] = []
    lock = threading.Lock()

    def keep(into: list[bytes]) -> Callable[[zenoh.Sample], None]:
        def callback(sample: zenoh.Sample) -> None:
            with lock:
                into.append(sample.payload.to_bytes())
        return callback

    try:
        queryable = server.declare_queryable("robonav/t/q", lambda q: q.reply("robonav/t/q", b"pong"))
        token = server.liveliness().declare_token("robonav/t/alive/server")
        publisher = server.declare_publisher("robonav/t/pub")
        latched_pub = declare_latched_publisher(server, "robonav/t/latched")
        subscriber = client.declare_subscriber("robonav/t/pub", keep(received))
        latched_sub = declare_latched_subscriber(client, "robonav/t/latched", keep(latched))

        def answered() -> bool:
            return any(r.ok is not None for r in client.get("robonav/t/q", timeout=0.5))

        def token_seen() -> bool:
            return any(r.ok is not None for r in client.liveliness().get("robonav/t/alive/*", timeout=0.5))

        def publication_arrives() -> bool:
            with lock:
                before = len(received)
            publisher.put(b"x")
            time.sleep(0.05)
            with lock:
                return len(received) > before

        latched_pub.put(b"before")
        assert _within(5.0, lambda: latched == [b"before"]) is not None, latched
        # Declarations reach the router asynchronously: each holds within a few seconds, not at once.
        before = {name: _within(5.0, check) for name, check in [
            ("query", answered), ("publication", publication_arrives), ("token", token_seen)]}
        assert all(t is not None for t in before.values()), before

        router.kill()
        time.sleep(1.0)
        latched_pub.put(b"during")  # nobody receives it now: the cache must hand it over later
        time.sleep(1.0)
        assert not answered()
        started = router.start()

        recovered = {name: _within(RECOVERY_LIMIT_S - (time.monotonic() - started), check) for name, check in [
            ("query", answered), ("publication", publication_arrives), ("token", token_seen),
            ("latched", lambda: b"during" in latched)]}
        print(f"recovered after the router restart [s]: {recovered}")
        assert all(t is not None for t in recovered.values()), recovered
        assert time.monotonic() - started <= RECOVERY_LIMIT_S
        assert latched == [b"before", b"during"], latched  # once each, nothing replayed twice
        for entity in (queryable, token, publisher, latched_pub, subscriber, latched_sub):
            entity.undeclare()
    finally:
        client.close()
        server.close()


def test_reconnect_retry_is_ours_unless_a_zenoh_config_file_sets_it(tmp_path: Path) -> None:
    default = to_zenoh_config(ZenohConfig())
    assert '"period_max_ms":1000' in default.get_json("connect/retry").replace(" ", "")
    assert RECONNECT_RETRY["period_max_ms"] <= 1000
    own = tmp_path / "zenoh.json5"
    own.write_text("{connect: {retry: {period_init_ms: 2000, period_max_ms: 8000, period_increase_factor: 2}}}",
                   encoding="utf-8")
    assert '"period_max_ms":8000' in to_zenoh_config(ZenohConfig(config_file=str(own))).get_json("connect/retry")


def test_a_service_session_waits_for_its_router_and_gives_up_on_stop(router: Router) -> None:
    router.kill()
    cfg = ZenohConfig(connect=(router.endpoint,))
    with pytest.raises(zenoh.ZError):
        open_session(cfg)  # a client fails at once
    stop = threading.Event()
    opened: list[zenoh.Session | None] = []
    waiter = threading.Thread(target=lambda: opened.append(open_session_waiting(cfg, stop, "test")))
    waiter.start()
    time.sleep(1.5)
    assert waiter.is_alive() and not opened  # still waiting
    started = router.start()
    waiter.join(timeout=10.0)
    assert opened and opened[0] is not None, "the waiting session did not connect"
    print(f"connected {time.monotonic() - started:.2f} s after the router listened")
    opened[0].close()

    router.kill()
    opened.clear()
    waiter = threading.Thread(target=lambda: opened.append(open_session_waiting(cfg, stop, "test")))
    waiter.start()
    time.sleep(0.5)
    stop.set()
    waiter.join(timeout=5.0)
    assert not waiter.is_alive() and opened == [None]
