"""The bare reference loop and how stream misses are matched to its own."""

from __future__ import annotations

import multiprocessing
import time

import numpy as np

from robonav.services.bench.reference_loop import run_reference_loop, shared_misses

NOMINAL_S = 1e-3


def _grid(start_s: float, count: int, gaps_at: dict[int, float]) -> np.ndarray:
    """Ticks every millisecond from `start_s`, with period k lengthened by gaps_at[k] seconds."""
    periods = np.full(count - 1, NOMINAL_S)
    for k, extra in gaps_at.items():
        periods[k] += extra
    return start_s + np.concatenate([[0.0], np.cumsum(periods)])


def test_stream_misses_are_shared_only_when_they_overlap_a_reference_miss() -> None:
    reference = _grid(0.0, 2000, {500: 0.004})  # the machine stalled 4 ms after 0.5 s
    stream = _grid(0.0003, 2000, {500: 0.004, 1500: 0.003})  # the same stall, then one of its own
    result = shared_misses(stream, reference, NOMINAL_S)
    assert (result["stream_missed"], result["reference_missed"], result["shared"], result["stream_only"]) == (2, 1, 1, 1)
    assert result["reference_long_periods_ms"] == [5.0]
    assert abs(result["reference_period_error_ms"]["max"] - 4.0) < 1e-6


def test_stream_ticks_outside_the_reference_span_do_not_count() -> None:
    reference = _grid(1.0, 1000, {})
    stream = _grid(0.0, 3000, {100: 0.01, 1500: 0.002})  # the first miss is before the reference started
    result = shared_misses(stream, reference, NOMINAL_S)
    assert (result["stream_missed"], result["reference_missed"], result["shared"]) == (1, 0, 0)


def test_the_reference_loop_ticks_at_its_period_until_stopped() -> None:
    spawn = multiprocessing.get_context("spawn")
    stop = spawn.Event()
    parent, child = spawn.Pipe()
    loop = spawn.Process(target=run_reference_loop, args=(NOMINAL_S, 0, stop, child), daemon=True)
    loop.start()
    assert parent.poll(60.0) and parent.recv() == "ready"
    time.sleep(0.5)
    stop.set()
    assert parent.poll(30.0)
    times = parent.recv()
    loop.join(timeout=10.0)
    assert len(times) > 200  # about 500 unless the machine is very busy
    assert abs(float(np.median(np.diff(times))) - NOMINAL_S) < 2e-4
