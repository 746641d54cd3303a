"""The setpoint stream process over real Zenoh on loopback: tables play row by row on the grid,
a new table takes over at its start time, and closing mid-motion brakes to rest."""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from robonav.pipeline.trajectory.blending import blend_from_state
from robonav.pipeline.trajectory.setpoint_table import SetpointTable, sample_table
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.pipeline.trajectory.trajectory import TrajectoryLimits
from robonav.pipeline.wire.messages import Setpoint
from robonav.services.common import open_session
from robonav.services.config import ZenohConfig, load_config
from robonav.services.executor.setpoint_stream import SetpointStream, wall_from_monotonic

from ..conftest import free_port, wait_for

CONFIG = load_config()
HOME = np.array(CONFIG.robot.home_position_rad)
NAMES = tuple(CONFIG.robot.joint_names)
LIMITS = TrajectoryLimits(np.array(CONFIG.robot.max_velocity_rad_s), np.array(CONFIG.robot.max_acceleration_rad_s2),
                          np.array(CONFIG.robot.max_jerk_rad_s3))
KEY = "robonav/test/executor/setpoint"


class Received:
    def __init__(self, session: zenoh.Session) -> None:
        self.setpoints: list[Setpoint] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(KEY, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.setpoints.append(Setpoint.from_wire(sample.payload.to_bytes()))

    def wait_for_rest(self, trajectory_id: str, timeout_s: float) -> list[Setpoint]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                last = self.setpoints[-1] if self.setpoints else None
            if last is not None and last.trajectory_id == trajectory_id and np.abs(last.velocity).max() < 1e-9:
                time.sleep(0.05)  # nothing may follow the rest state
                with self._lock:
                    return list(self.setpoints)
            time.sleep(0.01)
        raise AssertionError(f"'{trajectory_id}' did not come to rest within {timeout_s} s")


@pytest.fixture
def stream() -> Iterator[tuple[SetpointStream, Received]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    session = open_session(ZenohConfig(connect=(endpoint,)))
    received = Received(session)
    handle = SetpointStream(ZenohConfig(connect=(endpoint,)), KEY, NAMES, rate_hz=1000.0, busy_wait_s=0.0,
                            realtime_priority=0, limits=LIMITS, keep_times=20_000)
    yield handle, received
    handle.close()
    session.close()
    router.close()


def _rows_at_stamps(table: SetpointTable, setpoints: list[Setpoint], period_s: float) -> np.ndarray:
    """The row of `table` each setpoint's stamp falls on, checking the setpoint is that row.

    Stamps are grid times: row k of a table is stamped k periods after its start (the rest
    state may come later than its time when the loop was late past the end)."""
    wall_from_monotonic_s = wall_from_monotonic()
    ticks = (np.array([s.stamp for s in setpoints]) - wall_from_monotonic_s - table.start_s) / period_s
    np.testing.assert_allclose(ticks, np.round(ticks), atol=0.05)
    rows = np.minimum(np.round(ticks).astype(int), len(table.position) - 1)
    assert np.all(rows >= 0)
    np.testing.assert_array_equal(table.position[rows], [s.position for s in setpoints])
    return rows


def _parameterize(path: np.ndarray):  # noqa: ANN202
    return time_parameterize(path, max_velocity=LIMITS.velocity, max_acceleration=LIMITS.acceleration,
                             max_jerk=LIMITS.jerk, velocity_scaling=0.5, acceleration_scaling=0.5)


def test_tables_play_row_by_row_and_hand_over_at_their_start(stream: tuple[SetpointStream, Received]) -> None:
    handle, received = stream
    period = handle.period_s
    first = _parameterize(np.array([HOME, HOME + 0.4, HOME + [0.6, 0, 0.2, 0, 0.3, 0, 0]]))
    start = handle.next_tick(time.monotonic() + 0.05)
    assert abs((start - handle.origin_s) / period - round((start - handle.origin_s) / period)) < 1e-6
    table_one = sample_table(first, "one", start, period)
    handle.send(table_one)
    time.sleep(0.3)
    # Preempt from the state the first table commands at the switch: no jump in p, v or a. The
    # lead covers parameterizing, sampling and sending the second table on a loaded machine (CI
    # once took 128 ms; a table that arrives after its start takes over late).
    switch = handle.next_tick(time.monotonic() + 0.3)
    q, qd, qdd = first.sample(switch - start)
    second = blend_from_state(_parameterize(np.array([q, q - 0.3])), q, qd, qdd)
    table_two = sample_table(second, "two", switch, period)
    handle.send(table_two)
    setpoints = received.wait_for_rest("two", 10.0)

    ids = [s.trajectory_id for s in setpoints]
    handover = ids.index("two")
    assert set(ids[:handover]) == {"one"} and set(ids[handover:]) == {"two"}
    rows_one = _rows_at_stamps(table_one, setpoints[:handover], period)
    rows_two = _rows_at_stamps(table_two, setpoints[handover:], period)
    # The handover is exact in time: every "one" setpoint is for a tick before the switch, every
    # "two" setpoint for the switch or later (whatever was dropped or skipped under load).
    assert rows_one[-1] < round((switch - start) / period)
    assert rows_two[-1] == len(table_two.position) - 1
    assert np.all(np.diff(rows_one) >= 1) and np.all(np.diff(rows_two) >= 1)
    np.testing.assert_array_equal(setpoints[-1].position, q - 0.3)
    stats = handle.stats()
    assert stats.published >= len(setpoints)
    times = stats.publish_times_s
    assert len(times) == stats.published and np.all(np.diff(times) > 0)

def test_a_motion_from_rest_that_arrives_late_plays_from_its_first_row_and_later_tables_follow(
        stream: tuple[SetpointStream, Received]) -> None:
    handle, received = stream
    period = handle.period_s
    first = _parameterize(np.array([HOME, HOME + [0.5, 0, 0.3, 0, 0.4, 0, 0]]))
    # Due 50 periods ago when it arrives: a hand-over on a machine too busy to make its lead.
    start = handle.next_tick(time.monotonic()) - 50 * period
    table_one = sample_table(first, "late", start, period)
    handle.send(table_one)
    deadline = time.monotonic() + 5.0
    while handle.delay_ticks == 0 and time.monotonic() < deadline:
        time.sleep(0.005)
    delay = handle.delay_ticks
    assert delay >= 50
    # A preemption computed on the sender's clock before it took the delay up: the stream plays
    # it `delay` periods later too, so it continues the first table exactly.
    switch = handle.next_tick(time.monotonic() + 0.2)
    q, qd, qdd = first.sample(switch - start)
    second = blend_from_state(_parameterize(np.array([q, q - 0.3])), q, qd, qdd)
    table_two = sample_table(second, "two", switch, period)
    handle.send(table_two, known_delay_ticks=0)
    setpoints = received.wait_for_rest("two", 10.0)

    ids = [s.trajectory_id for s in setpoints]
    handover = ids.index("two")
    assert set(ids[:handover]) == {"late"}
    shift_s = delay * period
    rows_one = _rows_at_stamps(dataclasses.replace(table_one, start_s=start + shift_s), setpoints[:handover], period)
    rows_two = _rows_at_stamps(dataclasses.replace(table_two, start_s=switch + shift_s), setpoints[handover:], period)
    assert rows_one[0] == 0, "the motion from rest did not start at its first row"
    np.testing.assert_array_equal(setpoints[0].velocity, np.zeros(7))
    assert rows_one[-1] < round((switch - start) / period) and rows_two[-1] == len(table_two.position) - 1
    # (A loaded machine may stall the loop past the second's start: it then takes over a row or
    # two in, counted late; it is not a motion from rest and delays nothing.)
    stats = handle.stats()
    assert len(stats.delayed_s) == 1 and stats.delayed_s[0] >= 50 * period - 1e-9
    assert handle.delay_ticks == delay


def test_a_late_preemption_takes_over_rows_in_and_delays_nothing(stream: tuple[SetpointStream, Received]) -> None:
    handle, received = stream
    period = handle.period_s
    first = _parameterize(np.array([HOME, HOME + [0.8, 0, 0.5, 0, 0.6, 0, 0]]))
    start = handle.next_tick(time.monotonic() + 0.05)
    handle.send(sample_table(first, "one", start, period))
    assert wait_for(lambda: len(received.setpoints) > 100, 5.0)
    # (A loop stalled past the first one's start delays it a little: follow that, as the executor does.)
    delay = handle.delay_ticks
    played_from = start + delay * period
    # Due 30 periods ago when it arrives; the arm is moving, so it must switch where the blend says.
    switch = handle.next_tick(time.monotonic()) - 30 * period
    q, qd, qdd = first.sample(switch - played_from)
    assert np.abs(qd).max() > 0.05
    table_two = sample_table(blend_from_state(_parameterize(np.array([q, q - 0.3])), q, qd, qdd), "two", switch, period)
    handle.send(table_two, known_delay_ticks=delay)
    setpoints = received.wait_for_rest("two", 10.0)
    handover = [s.trajectory_id for s in setpoints].index("two")
    rows_two = _rows_at_stamps(table_two, setpoints[handover:], period)
    assert rows_two[0] >= 30
    stats = handle.stats()
    assert max(stats.late_s) >= 30 * period - 1e-9
    assert handle.delay_ticks == delay


def test_closing_mid_motion_brakes_to_rest_within_the_limits(stream: tuple[SetpointStream, Received]) -> None:
    handle, received = stream
    long = _parameterize(np.array([HOME, HOME + [1.2, 0.4, 0.8, 0.5, 1.0, 0.5, 1.0]]))
    handle.send(sample_table(long, "long", handle.next_tick(time.monotonic() + 0.02), handle.period_s))
    time.sleep(0.4)
    assert received.setpoints and np.abs(received.setpoints[-1].velocity).max() > 0.1
    handle.close()
    setpoints = received.wait_for_rest("long", 5.0)
    assert not np.allclose(setpoints[-1].position, HOME + [1.2, 0.4, 0.8, 0.5, 1.0, 0.5, 1.0])  # braked short
    velocity = np.array([s.velocity for s in setpoints])
    acceleration = np.array([s.acceleration for s in setpoints])
    assert np.all(np.abs(velocity) <= LIMITS.velocity + 1e-9)
    assert np.all(np.abs(acceleration) <= LIMITS.acceleration + 1e-9)
    # Continuous in velocity: between setpoints no more change than the full acceleration allows
    # in the time between them (setpoints in motion may be dropped or skipped under load; stamps
    # are their grid times, up to the microseconds of converting the clock).
    dt = np.diff([s.stamp for s in setpoints])
    assert np.all(dt >= handle.period_s - 1e-4)
    assert np.all(np.abs(np.diff(velocity, axis=0)) <= LIMITS.acceleration * (dt[:, None] + 1e-4))


def test_the_loop_runs_on_the_cpus_it_is_pinned_to() -> None:
    cpu = (os.cpu_count() or 1) - 1
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    handle = SetpointStream(ZenohConfig(connect=(endpoint,)), KEY, NAMES, rate_hz=1000.0, busy_wait_s=0.0,
                            realtime_priority=0, limits=LIMITS, cpu_affinity=(cpu,))
    try:
        assert handle.pid is not None and os.sched_getaffinity(handle.pid) == {cpu}
    finally:
        handle.close()
        router.close()


def _real_time_allowed() -> bool:
    """Whether this host lets a thread of ours run under SCHED_FIFO (CAP_SYS_NICE or RLIMIT_RTPRIO)."""
    allowed: list[bool] = []

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            allowed.append(True)
        except (PermissionError, OSError):
            allowed.append(False)

    thread = threading.Thread(target=probe)  # a thread of its own: the scheduling class ends with it
    thread.start()
    thread.join()
    return allowed[0]


def test_zenohs_threads_in_the_stream_run_real_time_as_its_loop_does() -> None:
    if not hasattr(os, "sched_setscheduler") or not _real_time_allowed():
        pytest.skip("this host does not allow SCHED_FIFO")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    handle = SetpointStream(ZenohConfig(connect=(endpoint,)), KEY, NAMES, rate_hz=1000.0, busy_wait_s=0.0,
                            realtime_priority=1, limits=LIMITS)
    try:
        assert handle.pid is not None
        names = {int(tid): Path(f"/proc/{handle.pid}/task/{tid}/comm").read_text().strip()
                 for tid in os.listdir(f"/proc/{handle.pid}/task")}
        # Zenoh's runtime threads (app-N, net-N, tx-N, rx-N) put each setpoint on the wire.
        transport = [tid for tid, name in names.items() if name.split("-")[0] in ("app", "net", "tx", "rx")]
        assert any(names[tid].startswith("tx-") for tid in transport), names
        assert {tid: os.sched_getscheduler(tid) for tid in transport} == dict.fromkeys(transport, os.SCHED_FIFO)
        assert os.sched_getscheduler(handle.pid) == os.SCHED_FIFO  # the loop
    finally:
        handle.close()
        router.close()
