"""A bare periodic loop beside the setpoint stream: what the machine itself allows a 1 kHz loop.

`robonav bench executor --reference-loop` runs it in its own process, at the stream's rate and
scheduling priority, for as long as the stream is measured. It does nothing but sleep to the
next tick and note the time (as cyclictest does, from rt-tests), so a period it misses was lost
to the machine: a stalled virtual CPU, an interrupt storm, a higher-priority task. A stream
period that is long while the reference's overlapping period is long too is counted as shared;
only the rest can be blamed on the stream's own work.
"""

from __future__ import annotations

import gc
import math
import time
from typing import Any

import numpy as np

from robonav.services.executor.setpoint_stream import pin_thread, set_real_time_priority


def run_reference_loop(period_s: float, priority: int, stop: Any, conn: Any,  # noqa: ANN401 - multiprocessing objects
                       cpus: tuple[int, ...] = ()) -> None:
    """Process body: send "ready", tick every `period_s` on the monotonic clock until `stop` is
    set, then send the (N,) wake-up times [s] through `conn`. On `cpus` when given (the stream's:
    then both loops live through the same CPU's stalls)."""
    set_real_time_priority(priority)
    pin_thread(cpus)
    conn.send("ready")
    capacity = 1 << 20
    times = np.zeros(capacity)
    gc.disable()  # nothing here makes cycles; a collection would be a stall of our own
    tick = math.ceil(time.monotonic() / period_s) * period_s
    count = 0
    while count < capacity and not stop.is_set():
        tick += period_s
        now = time.monotonic()
        if tick < now - period_s:  # as the stream does: skip whole ticks, keep the grid
            tick += math.ceil((now - tick) / period_s) * period_s
        if tick > now:
            time.sleep(tick - now)
        times[count] = time.monotonic()
        count += 1
    conn.send(times[:count])


def shared_misses(stream_times_s: np.ndarray, reference_times_s: np.ndarray, nominal_s: float) -> dict[str, Any]:
    """Misses (periods over twice `nominal_s`) of each loop, and how many stream misses overlap a
    reference miss in time. Only the part of the stream inside the reference's span counts."""
    low, high = reference_times_s[0], reference_times_s[-1]
    stream = stream_times_s[(stream_times_s >= low) & (stream_times_s <= high)]
    stream_gaps = _long_periods(stream, nominal_s)
    reference_gaps = _long_periods(reference_times_s, nominal_s)
    shared = sum(1 for a, b in stream_gaps if any(a < d and c < b for c, d in reference_gaps))
    reference_periods = np.diff(reference_times_s)
    return {"stream_missed": len(stream_gaps), "reference_missed": len(reference_gaps), "shared": shared,
            "stream_only": len(stream_gaps) - shared,
            "reference_period_error_ms": {
                "p50": float(np.percentile(np.abs(reference_periods - nominal_s), 50) * 1e3),
                "p99": float(np.percentile(np.abs(reference_periods - nominal_s), 99) * 1e3),
                "max": float(np.max(np.abs(reference_periods - nominal_s)) * 1e3)},
            "reference_long_periods_ms": [round((b - a) * 1e3, 2) for a, b in reference_gaps][:50]}


def _long_periods(times_s: np.ndarray, nominal_s: float) -> list[tuple[float, float]]:
    periods = np.diff(times_s)
    return [(float(times_s[k]), float(times_s[k + 1])) for k in np.flatnonzero(periods > 2 * nominal_s)]
