"""`robonav up`: a Zenoh router and every service, each its own supervised process.

Each service gets its own process so the 1 kHz executor loop does not share a GIL with
rendering, ray casting or planning. The router is a process too (`robonav router`), so it can
die and come back like the others: services and clients reconnect on their own. `Stack` restarts
whatever exits (`supervisor.py`) and answers `stack/status` with each process's state, restart
count and uptime (`robonav status`). Each process runs in a session of its own, so a Ctrl-C in
the terminal reaches only the command that started them: it stops the arm and waits for rest
(`robonav demo`, `robonav campaign`) before `close` stops the services in turn.
"""

from __future__ import annotations

import argparse
import logging
import os
import secrets
import shutil
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import zenoh

from robonav.pipeline.wire.messages import StackStatusRequest, StackStatusResponse
from robonav.services.common import (
    decode_request,
    guarded_queryable,
    open_session,
    parse_args_and_config,
    reply_ok,
)
from robonav.services.config import RobonavConfig, ZenohConfig
from robonav.services.keys import SERVICES, Keys
from robonav.services.signals import stop_on_signals
from robonav.services.stack.supervisor import Supervisor

log = logging.getLogger("robonav.up")

SHUTDOWN_GRACE_S = 10.0
ROUTER = "router"
SCENE_FILE_NAME = "planning_scene.msgpack"


class Stack:
    """The router and the service processes, supervised; `close` stops them by their PIDs.

    Args:
        restart: restart processes that exit (`robonav up` passes `stack.restart`); off, an
            exited process stays dead and `dead()` names it.

    Raises:
        RuntimeError: the router did not start listening within `stack.router_start_timeout_s`.
    """

    def __init__(self, cfg: RobonavConfig, config_path: str | None, *, services: Sequence[str] = SERVICES,
                 log_level: str = "INFO", view_port: int | None = None, restart: bool = False) -> None:
        self.cfg = cfg
        self.keys = Keys(cfg.cell)
        self.supervisor = Supervisor(cfg.stack, restart=restart)
        self._config_args = ["--config", str(Path(config_path).resolve())] if config_path is not None else []
        self._log_level = log_level
        # Lives as long as the stack: a planner restarted within it reloads its scene from here; a new
        # stack starts with an empty scene, as a new move_group does.
        self.run_dir = Path(tempfile.mkdtemp(prefix="robonav-up-"))
        self.session: zenoh.Session | None = None
        self._entities: list = []
        self._router_zid = ""
        try:
            self.supervisor.add(ROUTER, self._router_command)
            self.session = self._connect_to_router()
            self._entities = [
                self.session.liveliness().declare_subscriber(self.keys.all_alive, self._on_token, history=True),
                self.session.declare_queryable(self.keys.stack_status, guarded_queryable(self._handle_status, "up")),
            ]
            for name in services:
                self.supervisor.add(name, self._service_command(name))
            if view_port is not None:  # `robonav view`, in its own process like a service
                self.supervisor.add("view", lambda: [sys.executable, "-m", "robonav.services.cli", "view", "--port",
                                                     str(view_port), "--log-level", log_level, *self._config_args],
                                    has_token=False)
        except BaseException:
            self.close()
            raise
        self.supervisor.run_in_background()

    # --- commands ------------------------------------------------------------------------------

    def _router_command(self) -> list[str]:
        # A fresh Zenoh id on every start, like any router; the first one tells us we reached ours.
        self._router_zid = format(secrets.randbits(120) | 1 << 120, "x")  # Zenoh ids have no leading zeros
        return [sys.executable, "-m", "robonav.services.cli", "router", "--listen", self.cfg.zenoh.connect[0],
                "--id", self._router_zid, "--log-level", self._log_level, *self._config_args]

    def _service_command(self, name: str):  # noqa: ANN202 - a command factory
        def command() -> list[str]:
            cmd = [sys.executable, "-m", "robonav.services.cli", "serve", name, "--log-level", self._log_level,
                   *self._config_args]
            if name == "planner" and self.cfg.planner.scene_file is None:
                cmd += ["--scene-file", str(self.run_dir / SCENE_FILE_NAME)]
            return cmd

        return command

    def _connect_to_router(self) -> zenoh.Session:
        """Our own client session, once our router listens (not some other router on the port)."""
        deadline = time.monotonic() + self.cfg.stack.router_start_timeout_s
        zcfg = ZenohConfig(mode="client", connect=self.cfg.zenoh.connect[:1], config_file=self.cfg.zenoh.config_file)
        while True:
            dead = self.supervisor.dead()
            if ROUTER in dead:
                raise RuntimeError(f"the router exited ({dead[ROUTER]}) before it listened on {zcfg.connect[0]}: "
                                   "is the port taken? (see its log above)")
            try:
                session = open_session(zcfg)
            except zenoh.ZError:
                session = None
            if session is not None:
                if self._router_zid in {str(z) for z in session.info.routers_zid()}:
                    return session
                session.close()  # another router holds the port; ours will fail and exit
            if time.monotonic() > deadline:
                raise RuntimeError(f"the router did not listen on {zcfg.connect[0]} within "
                                   f"{self.cfg.stack.router_start_timeout_s:.0f} s")
            time.sleep(0.1)

    # --- Zenoh ----------------------------------------------------------------------------------

    def _on_token(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        self.supervisor.token(name, sample.kind == zenoh.SampleKind.PUT)

    def _handle_status(self, query: zenoh.Query) -> None:
        decode_request(query, StackStatusRequest)
        reply_ok(query, self.status())

    # --- API ------------------------------------------------------------------------------------

    def status(self) -> StackStatusResponse:
        """What `stack/status` answers: every process's state, restarts, uptime."""
        return StackStatusResponse(stamp=time.time(), started_stamp=self.supervisor.started_stamp,
                                   supervisor_pid=os.getpid(), restart=self.supervisor.restart,
                                   services=tuple(self.supervisor.status()))

    def pid(self, name: str) -> int | None:
        """The running process of `name` (e.g. to kill it in a test), if any."""
        return self.supervisor.pid(name)

    def dead(self) -> dict[str, int]:
        """Processes not running now, with their exit codes (with restarts on, until they are restarted)."""
        return self.supervisor.dead()

    def close(self) -> dict[str, int]:
        """SIGINT every service, then the router, wait, SIGKILL stragglers; returns exit codes."""
        others = [name for name in self.supervisor.names if name != ROUTER]
        codes = self.supervisor.stop([others], SHUTDOWN_GRACE_S)
        for entity in self._entities:
            entity.undeclare()
        self._entities = []
        if self.session is not None:
            self.session.close()
            self.session = None
        codes.update(self.supervisor.stop([[ROUTER]], SHUTDOWN_GRACE_S))
        shutil.rmtree(self.run_dir, ignore_errors=True)
        return codes


def main(argv: list[str] | None = None) -> int:
    view_parser = argparse.ArgumentParser(add_help=False)
    view_parser.add_argument("--view", action="store_true", help="also run `robonav view` (the live 3D view in the browser)")
    view_parser.add_argument("--view-port", type=int, default=8080, help="port of --view (default %(default)s)")
    view_args, argv = view_parser.parse_known_args(argv)
    loaded = parse_args_and_config("robonav up", "Run a Zenoh router and every service until Ctrl-C, restarting "
                                   "any that exits.", argv, parents=(view_parser,))
    if loaded is None:
        return 2
    args, cfg = loaded
    stop = stop_on_signals(signal.SIGINT, signal.SIGTERM)
    try:
        stack = Stack(cfg, args.config, log_level=args.log_level, restart=cfg.stack.restart,
                      view_port=view_args.view_port if view_args.view else None)
    except RuntimeError as exc:
        log.error("%s", exc)
        return 1
    if not cfg.stack.restart:
        _stop_when_one_exits(stack, stop)
    stop.wait()
    codes = stack.close()
    log.info("stopped: %s", codes)
    return 1 if any(code != 0 for code in codes.values()) else 0


def _stop_when_one_exits(stack: Stack, stop: threading.Event) -> None:
    """Without restarts, one exited process stops the stack (so a supervisor above sees it)."""

    def watch() -> None:
        while not stop.wait(0.5):
            dead = stack.dead()
            if dead:
                log.error("exited: %s; stopping the stack", dead)
                stop.set()

    threading.Thread(target=watch, daemon=True).start()
