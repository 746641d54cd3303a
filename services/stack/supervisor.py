"""Process supervision for `robonav up`: start each process, restart it with backoff when it
exits, count the restarts and time how long each was away.

A process that exits or is killed is started again after a wait that doubles with every exit in
a row (`stack.restart_backoff_initial_s` up to `stack.restart_backoff_max_s`), as systemd's
`Restart=always` with `RestartSec` steps would, and that falls back to the initial wait once the
process has run `stack.restart_backoff_reset_s`. A service is back when its Zenoh liveliness
token `alive/<name>` is declared again (`token`), which a service does once it serves; a process
without a token (`view`) is back when it runs.

No Zenoh here: `up.py` feeds the liveliness events in and serves `status()` on `stack/status`.
"""

from __future__ import annotations

import logging
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from robonav.pipeline.wire.messages import ServiceProcessStatus
from robonav.services.config import StackConfig

log = logging.getLogger("robonav.up")

POLL_PERIOD_S = 0.1
"""How often exits are looked for [s]: a killed service is noticed within this."""


def describe_exit(code: int) -> str:
    """'exit code 1' or 'killed by SIGKILL' (Popen reports a signal as its negative number)."""
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


@dataclass
class Child:
    """One supervised process and its history."""

    name: str
    command: Callable[[], list[str]]
    """Builds the command line for each start."""
    has_token: bool
    """It declares `alive/<name>` once it serves; otherwise running counts as alive."""
    backoff_s: float
    proc: subprocess.Popen[bytes] | None = None
    started_at: float = 0.0
    """time.monotonic() of the running process's start."""
    restarts: int = 0
    restart_due: float | None = None
    """time.monotonic() when the pending restart is due; None when none is pending."""
    last_exit_code: int | None = None
    last_exit_stamp: float | None = None
    away_since: float | None = None
    """time.monotonic() of the first exit of the current outage; cleared when it is back."""
    alive_since: float | None = None
    """time.monotonic() since which it holds its token (or, without one, runs)."""
    last_back_s: float | None = None


class Supervisor:
    """Starts, watches and restarts processes; thread-safe. `run_in_background` starts the watch loop."""

    def __init__(self, policy: StackConfig, *, restart: bool) -> None:
        self.policy = policy
        self.restart = restart
        self.started_stamp = time.time()
        self._children: dict[str, Child] = {}
        self._lock = threading.RLock()
        self._stopping = threading.Event()
        """Set by `stop`: exits are final from then on."""
        self._thread: threading.Thread | None = None

    @property
    def names(self) -> list[str]:
        with self._lock:
            return list(self._children)

    def add(self, name: str, command: Callable[[], list[str]], *, has_token: bool = True) -> Child:
        """Start `name` now and watch it from then on."""
        child = Child(name, command, has_token, backoff_s=self.policy.restart_backoff_initial_s)
        with self._lock:
            self._children[name] = child
            self._spawn(child)
        return child

    def pid(self, name: str) -> int | None:
        with self._lock:
            proc = self._children[name].proc
            return proc.pid if proc is not None else None

    def _spawn(self, child: Child) -> None:
        # A session of its own: a Ctrl-C in the terminal reaches only the command that started the
        # stack, which stops the arm first and then the processes in turn.
        child.proc = subprocess.Popen(child.command(), start_new_session=True)
        child.started_at = time.monotonic()
        log.info("started %s (pid %d)%s", child.name, child.proc.pid,
                 f", restart {child.restarts}" if child.restarts else "")

    def poll(self) -> None:
        """One pass: notice exits, schedule and run restarts."""
        with self._lock:
            now = time.monotonic()
            for child in self._children.values():
                if child.proc is not None and child.proc.poll() is not None:
                    self._exited(child, child.proc.returncode, now)
                if (child.proc is None and child.restart_due is not None and now >= child.restart_due
                        and not self._stopping.is_set()):
                    child.restart_due = None
                    child.restarts += 1
                    try:
                        self._spawn(child)
                    except OSError as exc:  # e.g. out of processes: try again after the next wait
                        log.error("could not restart %s: %s", child.name, exc)
                        self._schedule_restart(child, now)
                if not child.has_token and child.proc is not None:
                    self._mark_alive(child, True, now)

    def _exited(self, child: Child, code: int, now: float) -> None:
        ran_s = now - child.started_at
        child.proc = None
        child.last_exit_code = code
        child.last_exit_stamp = time.time()
        if child.away_since is None:
            child.away_since = now
        if not child.has_token:
            child.alive_since = None
        if self._stopping.is_set():
            return
        if not self.restart:
            log.error("%s %s after %.1f s; not restarted (stack.restart is off)", child.name, describe_exit(code), ran_s)
            return
        if ran_s >= self.policy.restart_backoff_reset_s:
            child.backoff_s = self.policy.restart_backoff_initial_s
        delay_s = self._schedule_restart(child, now)
        log.error("%s %s after %.1f s; restarting in %.1f s (restarts so far: %d)", child.name, describe_exit(code),
                  ran_s, delay_s, child.restarts)

    def _schedule_restart(self, child: Child, now: float) -> float:
        delay_s = child.backoff_s
        child.restart_due = now + delay_s
        child.backoff_s = min(delay_s * 2.0, self.policy.restart_backoff_max_s)
        return delay_s

    def token(self, name: str, alive: bool) -> None:
        """A liveliness event: `alive/<name>` was declared (True) or went away (False)."""
        with self._lock:
            child = self._children.get(name)
            if child is not None and child.has_token:
                self._mark_alive(child, alive, time.monotonic())

    def _mark_alive(self, child: Child, alive: bool, now: float) -> None:
        if not alive:
            child.alive_since = None
            return
        if child.alive_since is not None:
            return
        child.alive_since = now
        if child.away_since is not None:
            child.last_back_s = now - child.away_since
            child.away_since = None
            log.warning("%s is back and serving, %.1f s after it exited (restarts: %d)", child.name,
                        child.last_back_s, child.restarts)

    def dead(self) -> dict[str, int]:
        """Processes not running now (exited; a restart may be pending), with their last exit codes."""
        with self._lock:
            self.poll()
            return {c.name: c.last_exit_code for c in self._children.values()
                    if c.proc is None and c.last_exit_code is not None}

    def status(self) -> list[ServiceProcessStatus]:
        """Every process in start order, as `stack/status` reports it."""
        with self._lock:
            now = time.monotonic()
            rows = []
            for c in self._children.values():
                if c.proc is not None:
                    state = "running"
                elif c.restart_due is not None and not self._stopping.is_set():
                    state = "restarting"
                else:
                    state = "stopped"
                rows.append(ServiceProcessStatus(
                    name=c.name, state=state, alive=c.alive_since is not None and c.proc is not None,
                    restarts=c.restarts, pid=c.proc.pid if c.proc is not None else None,
                    uptime_s=round(now - c.started_at, 3) if c.proc is not None else 0.0,
                    alive_for_s=round(now - c.alive_since, 3) if c.alive_since is not None and c.proc is not None else 0.0,
                    last_exit_code=c.last_exit_code, last_exit_stamp=c.last_exit_stamp,
                    last_back_s=None if c.last_back_s is None else round(c.last_back_s, 3),
                    restart_in_s=round(max(0.0, c.restart_due - now), 3) if state == "restarting" else None))
            return rows

    def run_in_background(self) -> None:
        def loop() -> None:
            while not self._stopping.wait(POLL_PERIOD_S):
                try:
                    self.poll()
                except Exception:  # noqa: BLE001 - the watch must outlive any one failure
                    log.exception("supervisor: poll failed")

        self._thread = threading.Thread(target=loop, name="robonav-supervisor", daemon=True)
        self._thread.start()

    def stop(self, order: Sequence[Sequence[str]], grace_s: float) -> dict[str, int]:
        """Stop restarting, then SIGINT each group of processes in `order` (each group together),
        wait up to `grace_s`, SIGKILL stragglers; returns every process's exit code (for one that
        was not running, its last)."""
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        codes: dict[str, int] = {}
        for group in order:
            with self._lock:
                children = [self._children[name] for name in group if name in self._children]
            for child in children:
                if child.proc is not None and child.proc.poll() is None:
                    child.proc.send_signal(signal.SIGINT)
            deadline = time.monotonic() + grace_s
            for child in children:
                if child.proc is None:
                    if child.last_exit_code is not None:
                        codes[child.name] = child.last_exit_code
                    continue
                try:
                    codes[child.name] = child.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    log.error("%s did not stop within %.0f s; killing pid %d", child.name, grace_s, child.proc.pid)
                    child.proc.kill()
                    codes[child.name] = child.proc.wait()
        return codes
