"""`robonav up`: an in-process Zenoh router plus every service as its own process.

Each service gets its own process so the 1 kHz executor loop does not share a GIL with
rendering, ray casting or planning. Each runs in a session of its own, so a Ctrl-C in the
terminal reaches only the command that started them: it stops the arm and waits for rest
(`robonav demo`, `robonav campaign`) before `close` stops the services in turn.
"""

from __future__ import annotations

import argparse
import logging
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import zenoh

from robonav.services.common import parse_args_and_config, stop_on_signals, to_zenoh_config
from robonav.services.config import RobonavConfig, ZenohConfig
from robonav.services.keys import SERVICES

log = logging.getLogger("robonav.up")

SHUTDOWN_GRACE_S = 10.0


class Stack:
    """The router session and the service processes; `close` stops them by their PIDs."""

    def __init__(self, cfg: RobonavConfig, config_path: str | None, *, services: Sequence[str] = SERVICES,
                 log_level: str = "INFO", view_port: int | None = None) -> None:
        self.cfg = cfg
        router_cfg = ZenohConfig(mode="router", listen=cfg.zenoh.connect[:1], multicast_scouting=False)
        self.router = zenoh.open(to_zenoh_config(router_cfg))
        self.processes: dict[str, subprocess.Popen[bytes]] = {}
        for name in services:
            cmd = [sys.executable, "-m", "robonav.services.cli", "serve", name, "--log-level", log_level]
            if config_path is not None:
                cmd += ["--config", str(Path(config_path).resolve())]
            self.processes[name] = subprocess.Popen(cmd, start_new_session=True)
            log.info("started %s (pid %d)", name, self.processes[name].pid)
        if view_port is not None:  # `robonav view`, in its own process like a service
            cmd = [sys.executable, "-m", "robonav.services.cli", "view", "--port", str(view_port), "--log-level", log_level]
            if config_path is not None:
                cmd += ["--config", str(Path(config_path).resolve())]
            self.processes["view"] = subprocess.Popen(cmd, start_new_session=True)
            log.info("started view on port %d (pid %d)", view_port, self.processes["view"].pid)

    def dead(self) -> dict[str, int]:
        """Services that exited, with their exit codes."""
        return {name: proc.returncode for name, proc in self.processes.items() if proc.poll() is not None}

    def close(self) -> dict[str, int]:
        """SIGINT every service, wait, SIGKILL stragglers; returns exit codes."""
        for proc in self.processes.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + SHUTDOWN_GRACE_S
        codes: dict[str, int] = {}
        for name, proc in self.processes.items():
            try:
                codes[name] = proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.error("%s did not stop within %.0f s; killing pid %d", name, SHUTDOWN_GRACE_S, proc.pid)
                proc.kill()
                codes[name] = proc.wait()
        self.router.close()
        return codes


def main(argv: list[str] | None = None) -> int:
    view_parser = argparse.ArgumentParser(add_help=False)
    view_parser.add_argument("--view", action="store_true")
    view_parser.add_argument("--view-port", type=int, default=8080)
    view_args, argv = view_parser.parse_known_args(argv)
    loaded = parse_args_and_config("robonav up", "Run a Zenoh router and every service until Ctrl-C "
                                   "(--view: also `robonav view` on --view-port, default 8080).", argv)
    if loaded is None:
        return 2
    args, cfg = loaded
    stop = stop_on_signals(signal.SIGINT, signal.SIGTERM)
    stack = Stack(cfg, args.config, log_level=args.log_level, view_port=view_args.view_port if view_args.view else None)
    failed: dict[str, int] = {}
    watcher = threading.Thread(target=lambda: _watch(stack, stop, failed), daemon=True)
    watcher.start()
    stop.wait()
    codes = stack.close()
    log.info("stopped: %s", codes)
    return 1 if failed or any(code != 0 for code in codes.values()) else 0


def _watch(stack: Stack, stop: threading.Event, failed: dict[str, int]) -> None:
    while not stop.wait(0.5):
        dead = stack.dead()
        if dead:
            failed.update(dead)
            log.error("service exited unexpectedly: %s; stopping the stack", dead)
            stop.set()
