"""`robonav stop`: stop the arm and wait until it rests; and Ctrl-C in any command that moved it.

    robonav stop [--emergency] [--timeout S] [--config FILE] [--zenoh-config FILE] [--json FILE]

A stop is an `executor/stop` query: the executor brakes along the path at its acceleration
limits (`--emergency`: at the full limits). The arm is at rest once, after the stop, the
executor reports a resting state (`stopped`, `idle` or `error`) and a joint state measured
after the stop has every velocity within REST_VELOCITY_RAD_S. Prints one JSON object. Exit
code 0 once at rest; 1 when the executor refused or the arm was not at rest within
`--timeout`; 2 on a bad config; 3 when nothing answered (no executor, or access control
dropped the stop: only the `operator` role may send it).

Commands that start a motion (`robonav plan --execute`, the demo, the campaign) take Ctrl-C
through `Interrupt`: the first SIGINT (or SIGTERM) sends a stop and waits for rest before the
command exits, a second one makes it an emergency stop.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import signal
import sys
import threading
import time
from collections.abc import Callable
from types import FrameType
from typing import Any

import numpy as np
import zenoh

from robonav.pipeline.config import ConfigError
from robonav.pipeline.wire.messages import ErrorReply
from robonav.services.client import QueryFailed, RobonavClient
from robonav.services.common import load_cli_config, open_session

REST_VELOCITY_RAD_S = 0.01
"""Every joint slower than this counts as at rest [rad/s]."""
DEFAULT_REST_TIMEOUT_S = 10.0
STOP_QUERY_TIMEOUT_S = 5.0
EXIT_OK, EXIT_FAILED, EXIT_CONFIG, EXIT_NO_REPLY = 0, 1, 2, 3
EXIT_INTERRUPTED = 130
"""A command that Ctrl-C stopped (128 + SIGINT, the shell's convention)."""


@dataclasses.dataclass
class StopOutcome:
    at_rest: bool
    executor_state: str | None
    """The executor's state in the last status received."""
    max_velocity_rad_s: float | None
    """Largest joint speed in the last joint state received [rad/s]."""
    wait_s: float
    emergency: bool
    error: str | None = None

    def record(self) -> dict[str, Any]:
        record = dataclasses.asdict(self)
        if self.max_velocity_rad_s is not None:
            record["max_velocity_rad_s"] = round(self.max_velocity_rad_s, 5)
        record["wait_s"] = round(self.wait_s, 3)
        return record


def _max_speed(client: RobonavClient) -> float | None:
    state = client.joint_state
    return None if state is None else float(np.max(np.abs(state.velocity), initial=0.0))


def stop_and_wait(client: RobonavClient, *, emergency: bool = False,
                  timeout_s: float = DEFAULT_REST_TIMEOUT_S) -> StopOutcome:
    """Send `executor/stop` and wait until the executor rests and the arm's joints are still.

    Freshness is judged by arrival, not by stamps (the executor's and the driver's clocks may
    differ): a status and a joint state that arrived after the stop's reply must say so.

    Raises:
        QueryFailed: the stop got no reply (no executor, or access control dropped it).
    """
    started = time.monotonic()
    reply = client.stop(emergency=emergency, timeout_s=STOP_QUERY_TIMEOUT_S)
    if isinstance(reply, ErrorReply):
        return StopOutcome(False, None, _max_speed(client), time.monotonic() - started, emergency,
                           f"{reply.code}: {reply.message}")
    status_at_reply, joint_state_at_reply = client.status, client.joint_state

    def resting() -> bool:
        status, state = client.status, client.joint_state
        return (status is not None and status is not status_at_reply and status.state.finished
                and state is not None and state is not joint_state_at_reply
                and float(np.max(np.abs(state.velocity), initial=0.0)) <= REST_VELOCITY_RAD_S)

    at_rest = client.wait_for(resting, timeout_s)
    status = client.status
    return StopOutcome(at_rest, None if status is None else status.state.value, _max_speed(client),
                       time.monotonic() - started, emergency,
                       None if at_rest else f"not at rest within {timeout_s:.1f} s of the stop")


class Interrupt:
    """While entered, SIGINT and SIGTERM set `event` (and count) instead of ending the program."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.count = 0
        self._previous: dict[int, Any] = {}

    def _handle(self, _signum: int, _frame: FrameType | None) -> None:
        self.count += 1
        self.event.set()

    def __enter__(self) -> Interrupt:
        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *_exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)

    def is_set(self) -> bool:
        return self.event.is_set()


def wait_or_interrupt(client: RobonavClient, done: Callable[[], bool], timeout_s: float, interrupt: Interrupt) -> bool:
    """Wait until `done()` or an interrupt (checked at least every 0.1 s); returns `done()`."""
    deadline = time.monotonic() + timeout_s
    while not interrupt.is_set() and time.monotonic() < deadline:
        if client.wait_for(lambda: done() or interrupt.is_set(), min(0.1, max(0.0, deadline - time.monotonic()))):
            break
    return done()


def stop_after_interrupt(client: RobonavClient, interrupt: Interrupt) -> dict[str, Any]:
    """The stop a Ctrl-C asks for; a second Ctrl-C while braking makes it an emergency stop."""
    try:
        outcome = stop_and_wait(client, emergency=interrupt.count > 1)
        if not outcome.at_rest and interrupt.count > 1 and not outcome.emergency:
            outcome = stop_and_wait(client, emergency=True)
        return outcome.record()
    except QueryFailed as exc:
        return {"at_rest": False, "error": str(exc)}


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="robonav stop", description=__doc__.splitlines()[0])
    parser.add_argument("--emergency", action="store_true", help="brake at the full acceleration limits")
    parser.add_argument("--timeout", type=float, default=DEFAULT_REST_TIMEOUT_S,
                        help="longest wait for the arm to rest [s] (default %(default)s)")
    parser.add_argument("--config", help="YAML config (default: the packaged default); its zenoh and cell keys are used")
    parser.add_argument("--zenoh-config", help="Zenoh JSON5 config (TLS, login: client-operator.json5)")
    parser.add_argument("--json", help="also write the result to this file")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        cfg = load_cli_config(args.config, args.zenoh_config)
        zcfg = cfg.zenoh
    except (ConfigError, ValueError) as exc:
        print(f"robonav stop: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    try:
        session = open_session(zcfg)
    except zenoh.ZError as exc:
        print(f"robonav stop: cannot reach the router at {', '.join(zcfg.connect)}: {exc}", file=sys.stderr)
        return EXIT_NO_REPLY
    with session:
        client = RobonavClient(session, cfg.cell)
        try:
            # Wait for the executor's first status and a joint state so "moving" can be told from "at rest".
            client.wait_for(lambda: client.status is not None and client.joint_state is not None, 2.0)
            outcome = stop_and_wait(client, emergency=args.emergency, timeout_s=args.timeout)
            code, record = (EXIT_OK if outcome.at_rest else EXIT_FAILED), {"ok": outcome.at_rest, **outcome.record()}
        except QueryFailed as exc:
            code, record = EXIT_NO_REPLY, {"ok": False, "at_rest": False, "error": str(exc)}
        finally:
            client.close()
    text = json.dumps(record, indent=2)
    print(text)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as out:
            out.write(text + "\n")
    return code
