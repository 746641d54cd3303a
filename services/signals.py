"""SIGINT/SIGTERM as a `threading.Event`, set from a thread of its own.

A Python signal handler runs in the main thread between two bytecodes, wherever that thread is.
Setting the stop event there deadlocks when the main thread was interrupted inside that same
event's `wait` while holding the event's lock (CPython issue #126434): `robonav up` had to kill
an executor hung so (its loop waits 5 ms at a time), and a loop waiting 0.5 ms at a time hung in
1 of 200 stops.
And the kernel may hand a process signal to any thread, one of Zenoh's too: the handler then
runs only when the main thread next executes Python, so a main thread asleep in `stop.wait()`
(the router, `robonav up`) slept through it. `signal.set_wakeup_fd` has the interpreter's C
handler write the signal number to a pipe from whichever thread took the signal; a watcher
thread reads it and sets the event, so the stop arrives at once and no lock is taken in a
handler.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from typing import Any

log = logging.getLogger("robonav")

_lock = threading.Lock()
_events: dict[int, threading.Event] = {}
"""The event each watched signal sets: the latest `stop_on_signals` call for it wins, as with `signal.signal`."""
_wakeup_write_fd: int | None = None


def _watch(read_fd: int) -> None:
    while True:
        for signum in os.read(read_fd, 64):
            with _lock:
                event = _events.get(signum)
            if event is not None:
                log.info("signal %s: stopping", signal.Signals(signum).name)
                event.set()


def _keep_default_action_away(_signum: int, _frame: Any) -> None:
    """The Python-level handler: the watcher acts on the signal, this only replaces the default
    (KeyboardInterrupt, or termination) and must take no lock."""


def stop_on_signals(*signums: int) -> threading.Event:
    """An event set soon after SIGINT or SIGTERM (docker stop sends SIGTERM) arrives. Main thread only."""
    global _wakeup_write_fd
    stop = threading.Event()
    with _lock:
        if _wakeup_write_fd is None:
            read_fd, _wakeup_write_fd = os.pipe()
            os.set_blocking(_wakeup_write_fd, False)  # the C handler must never block on a full pipe
            threading.Thread(target=_watch, args=(read_fd,), name="robonav-signals", daemon=True).start()
        for signum in signums or (signal.SIGINT, signal.SIGTERM):
            _events[int(signum)] = stop
    # Set on every call: other code (an asyncio loop in the main thread) may have replaced it.
    signal.set_wakeup_fd(_wakeup_write_fd, warn_on_full_buffer=False)
    for signum in signums or (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _keep_default_action_away)
    return stop
