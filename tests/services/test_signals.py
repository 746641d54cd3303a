"""A stop signal sets the stop event whatever the main thread is doing and whichever thread takes it.

Each case runs in a child interpreter, as signal handlers and the wakeup fd are process-wide."""

from __future__ import annotations

import subprocess
import sys
import textwrap

SETUP = """
import logging, os, signal, sys, threading, time
logging.basicConfig(level=logging.INFO, stream=sys.stderr)
from robonav.services.signals import stop_on_signals
stop = stop_on_signals(signal.SIGINT, signal.SIGTERM)
"""


def _run(body: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", SETUP + textwrap.dedent(body)], capture_output=True, text=True, timeout=20)


def test_a_signal_taken_while_the_main_thread_holds_the_stop_events_lock_still_sets_it() -> None:
    # The race of CPython issue #126434 made certain: the signal lands while the main thread is
    # inside the event's own lock, where a 5 ms `stop.wait` loop spends part of its time. Setting
    # the event in the Python handler deadlocked here for good.
    done = _run("""
        with stop._cond:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.2)
        print("stopped" if stop.wait(5.0) else "not stopped")
    """)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "stopped"
    assert "signal SIGTERM: stopping" in done.stderr


def test_a_signal_another_thread_takes_wakes_a_main_thread_asleep_on_the_stop_event() -> None:
    # Zenoh's threads do not block signals, so the kernel may give SIGINT to one of them; a main
    # thread asleep in `stop.wait()` (the router, `robonav up`) used to sleep on.
    done = _run("""
        sleeper = threading.Thread(target=time.sleep, args=(30,), daemon=True)
        sleeper.start()
        threading.Timer(0.2, lambda: signal.pthread_kill(sleeper.ident, signal.SIGINT)).start()
        print("stopped" if stop.wait(10.0) else "not stopped")
    """)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "stopped"


def test_the_latest_event_asked_for_a_signal_is_the_one_it_sets() -> None:
    done = _run("""
        later = stop_on_signals(signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)
        print(later.wait(5.0), stop.is_set())
        os.kill(os.getpid(), signal.SIGTERM)
        print(stop.wait(5.0))
    """)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["True", "False", "True"]
