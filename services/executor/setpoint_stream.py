"""The setpoint loop in a process of its own: publishes pre-sampled trajectories on a fixed time grid.

Why a process: in the executor's own process the loop shares one GIL with the query handlers,
the path monitor, time parameterisation and Zenoh callbacks, and each of them holds it for
milliseconds at a time (measured with perception at 30 Hz: p99 period error 4 ms, one period in
eight over 2 ms). Here nothing else runs Python. The loop is deliberately simple: the executor
samples every trajectory its state machine starts at the loop's period, on the loop's time grid
(`next_tick`), and sends the table; the loop publishes, at each tick, the row for that tick. A
table takes over at its first row's time, so the executor hands over a new trajectory (a
preemption, a stop) a little ahead (`executor.command_lead_s`) and the switch is exact. Long
trajectories go over in two parts: a head of `HEAD_S` first (fast to sample and send, so it is
on time), then the whole table, which replaces the head where it plays. A stream that runs out
of a head before the rest arrives brakes the arm from there, as when the executor is gone.

A table that reaches the loop after its start takes over at the current tick, its earlier rows
skipped: right for a preemption, which must switch when the executor's blend says. A motion
from rest (nothing playing, the table's first row at rest) is instead played from its first
row at once: skipped rows would make the arm's first setpoint one already in motion, which a
driver refuses (Franka's FCI, the sim's) while the arm stays put, until the executor's tracking
watchdog stops the motion. The loop then plays that table, and every table the executor sent
before it knew, that much later: it adds the delay to a counter it shares with the executor
(`delay_ticks`), each table goes over with the counter's value the executor had taken up when
it computed it, and the executor moves its state machine's clock by each increase.

If the executor's process goes away (the pipe closes) or the stream is closed while a table is
playing, the loop brakes the arm from its last row as fast as the robot's limits allow, plays
that to rest, and exits.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import math
import multiprocessing
import os
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from robonav.pipeline.trajectory.setpoint_table import SetpointTable, sample_table
from robonav.pipeline.trajectory.trajectory import JointTrajectory, TrajectoryLimits
from robonav.pipeline.types import FloatArray
from robonav.services.common import LOG_FORMAT_ENV, LOG_FORMATS, setup_logging
from robonav.services.config import ZenohConfig

log = logging.getLogger("robonav.executor.stream")

REALTIME_SWITCH_INTERVAL_S = 2e-4
"""Python's thread switch interval in the streaming process [s]: the loop gets the GIL back
from the pipe reader within this."""
DROP_WAIT_US = 50
"""Longest wait for room in Zenoh's transmit queue before a setpoint in motion is dropped [µs]."""
HEAD_S = 1.0
"""Trajectories longer than this go over as a head of this length, then the whole [s]. The
executor samples and sends the whole at normal priority: with a quarter second of head, a busy
2-core machine made it late about once a scene (a UR5 campaign), and the stream braked the arm."""
AT_REST = 1e-9
"""A table whose first row's velocity [rad/s] and acceleration [rad/s^2] are below this starts at rest."""
START_TIMEOUT_S = 60.0
"""The streaming process must have its Zenoh session up within this [s]."""
WALL_REFRESH_S = 1.0
"""The loop measures the wall clock's offset from the monotonic one this often [s]."""


@dataclass(frozen=True)
class StreamStats:
    published: int
    """Setpoints put since start."""
    late_s: tuple[float, ...]
    """For each table that arrived after its first row was due (the switch then skipped rows):
    how late [s]."""
    delayed_s: tuple[float, ...]
    """For each motion from rest that arrived after its first row was due (it played from its
    first row that much later, and so did what the executor sent before it knew): how late [s]."""
    starved: int
    """Heads played to their end before the rest of their trajectory arrived (the arm was braked)."""
    publish_times_s: FloatArray
    """time.monotonic() right after each put, when the stream was asked to keep them (else empty)."""


@dataclass(frozen=True)
class _StreamSpec:
    zenoh: ZenohConfig
    key: str
    joint_names: tuple[str, ...]
    period_s: float
    origin_s: float
    busy_wait_s: float
    realtime_priority: int
    cpu_affinity: tuple[int, ...]
    limits: TrajectoryLimits
    """Full limits for braking when orphaned."""
    keep_times: int
    log_level: int


class SetpointStream:
    """The parent's handle on the streaming process."""

    def __init__(self, zenoh: ZenohConfig, key: str, joint_names: tuple[str, ...], *, rate_hz: float,
                 busy_wait_s: float, realtime_priority: int, limits: TrajectoryLimits, keep_times: int = 0,
                 cpu_affinity: tuple[int, ...] = ()) -> None:
        """Start the process and wait until its session is up.

        Args:
            zenoh: The executor's Zenoh section; the process connects where the executor does
                (or to its listen endpoints) and listens nowhere.
            key: The setpoint key expression.
            joint_names: Names carried by every setpoint, robot order.
            rate_hz: Setpoint rate [Hz].
            busy_wait_s: Poll the clock this long before each tick instead of sleeping [s].
            realtime_priority: SCHED_FIFO priority for the loop (0: normal).
            cpu_affinity: CPUs the loop (and its pipe reader) may run on; empty: any.
            limits: The robot's full limits (braking when orphaned).
            keep_times: Keep up to this many publish times for `stats` (benchmarks).

        Raises:
            RuntimeError: the process did not come up.
        """
        self.period_s = 1.0 / rate_hz
        self.origin_s = time.monotonic()
        connect = zenoh.connect or zenoh.listen
        spec = _StreamSpec(dataclasses.replace(zenoh, mode="client" if zenoh.mode == "router" else zenoh.mode,
                                               connect=connect, listen=()),
                           key, tuple(joint_names), self.period_s, self.origin_s, busy_wait_s, realtime_priority,
                           tuple(cpu_affinity), limits, keep_times, logging.getLogger("robonav").getEffectiveLevel())
        context = multiprocessing.get_context("spawn")  # never fork a process with Zenoh's threads
        self._conn, child = context.Pipe()
        self._send_lock = threading.Lock()
        # Written by the loop alone; a 64-bit integer is read whole.
        self._delay_ticks = context.RawValue("q", 0)
        self._process = context.Process(target=_run, args=(spec, child, self._delay_ticks),
                                        name="robonav-setpoint-stream", daemon=True)
        self._process.start()
        child.close()
        try:
            answer = self._conn.recv() if self._conn.poll(START_TIMEOUT_S) else f"no answer within {START_TIMEOUT_S} s"
        except EOFError:
            answer = "it exited"
        if answer != "ready":
            self._process.terminate()
            raise RuntimeError(f"the setpoint stream process did not start: {answer}")

    @property
    def pid(self) -> int | None:
        """The streaming process's id."""
        return self._process.pid

    def next_tick(self, t_s: float) -> float:
        """The first tick of the stream's grid at or after time.monotonic() `t_s` [s]."""
        return self.origin_s + math.ceil((t_s - self.origin_s) / self.period_s - 1e-9) * self.period_s

    @property
    def delay_ticks(self) -> int:
        """Periods by which the loop has put off motions from rest that reached it late, in all
        (see the module's docstring); only ever grows."""
        return int(self._delay_ticks.value)

    def send(self, table: SetpointTable, known_delay_ticks: int = 0) -> None:
        """Play `table` from its start time on (replacing whatever plays then).

        Args:
            table: The table; its start is on the stream's grid.
            known_delay_ticks: `delay_ticks` as the sender knew it when it computed the table:
                the loop plays it `delay_ticks - known_delay_ticks` periods after its start.
        """
        with self._send_lock:
            self._conn.send(("table", (table, int(known_delay_ticks))))

    def play(self, trajectory: JointTrajectory, trajectory_id: str, start_s: float, known_delay_ticks: int = 0) -> None:
        """Sample `trajectory` from `start_s` (on the grid) and send it: its head first when long."""
        head = sample_table(trajectory, trajectory_id, start_s, self.period_s, max_rows=int(HEAD_S / self.period_s))
        self.send(head, known_delay_ticks)
        if not head.complete:
            self.send(sample_table(trajectory, trajectory_id, start_s, self.period_s), known_delay_ticks)

    def stats(self, timeout_s: float = 10.0) -> StreamStats:
        with self._send_lock:
            self._conn.send(("stats", None))
            if not self._conn.poll(timeout_s):
                raise RuntimeError("the setpoint stream process did not answer")
            return self._conn.recv()

    @property
    def alive(self) -> bool:
        return self._process.is_alive()

    def close(self, timeout_s: float = 5.0) -> None:
        """Ask the process to stop (braking first if a table is playing), then wait for it."""
        try:
            with self._send_lock:
                self._conn.send(("close", None))
        except (BrokenPipeError, OSError):
            pass
        self._process.join(timeout_s)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(1.0)
        self._conn.close()


# --- the streaming process ------------------------------------------------------------------


class _Loop:
    def __init__(self, spec: _StreamSpec, conn: Any, delay_ticks: Any) -> None:  # noqa: ANN401 - a Connection, a RawValue
        self.spec = spec
        self.conn = conn
        self.delay_ticks = delay_ticks
        self.lock = threading.Lock()
        self.pending: list[tuple[SetpointTable, int]] = []
        """Tables not yet played, in the order sent, each with the delay its sender knew."""
        self.closing = threading.Event()
        self.stats_asked = threading.Event()
        self.times = np.zeros(spec.keep_times)
        self.published = 0
        self.late_s: list[float] = []
        self.delayed_s: list[float] = []
        self.starved = 0

    def receive(self) -> None:
        """Reader thread: tables in, stats out; a closed pipe means the executor is gone."""
        while True:
            try:
                kind, body = self.conn.recv()
            except (EOFError, OSError):
                log.warning("setpoint stream: the executor process is gone; braking and stopping")
                self.closing.set()
                return
            if kind == "table":
                with self.lock:
                    self.pending.append(body)
            elif kind == "stats":
                self.stats_asked.set()
            elif kind == "close":
                self.closing.set()
                return

    def take(self, tick_s: float, active: SetpointTable | None) -> SetpointTable | None:
        """The table that plays at `tick_s`: the newest pending one already due (the last sent
        of those with the latest start), else `active`. Starts are as played: moved by the delay
        the sender did not know of yet."""
        period = self.spec.period_s
        with self.lock:
            delay = int(self.delay_ticks.value)
            pending = [(dataclasses.replace(table, start_s=table.start_s + (delay - known) * period)
                        if known != delay else table) for table, known in self.pending]
            due = [i for i, table in enumerate(pending) if table.start_s <= tick_s + 1e-6]
            if not due:
                return active
            self.pending = [entry for i, entry in enumerate(self.pending) if i not in due]
        table = pending[due[0]]
        for candidate in (pending[i] for i in due[1:]):
            if candidate.start_s >= table.start_s - 1e-9:
                table = candidate
        if active is not None and table.start_s < active.start_s - 1e-9:
            return active  # overtaken (e.g. by a brake): never go back to an older start
        rest_of_active = (active is not None and not active.complete and abs(table.start_s - active.start_s) < 1e-9
                          and table.trajectory_id == active.trajectory_id)
        late_s = tick_s - table.start_s
        if late_s <= 0.5 * period or rest_of_active:
            return table
        if active is None and max(np.abs(table.velocity[0]).max(), np.abs(table.acceleration[0]).max()) < AT_REST:
            ticks = int(round(late_s / period))
            self.delay_ticks.value = delay + ticks
            self.delayed_s.append(late_s)
            log.warning("setpoint stream: '%s', a motion from rest, arrived %.1f ms after its start: it starts now, "
                        "from its first row", table.trajectory_id, late_s * 1e3)
            return dataclasses.replace(table, start_s=table.start_s + ticks * period)
        self.late_s.append(late_s)
        log.warning("setpoint stream: '%s' arrived %.1f ms after its start: it takes over %d rows in",
                    table.trajectory_id, late_s * 1e3, int(round(late_s / period)))
        return table

    def answer_stats(self) -> None:
        self.stats_asked.clear()
        kept = min(self.published, len(self.times))
        self.conn.send(StreamStats(self.published, tuple(self.late_s), tuple(self.delayed_s), self.starved,
                                   self.times[:kept].copy()))

    def run(self) -> None:
        import zenoh

        from robonav.pipeline.wire.messages import Setpoint
        from robonav.services.common import to_zenoh_config

        spec = self.spec
        # The threads started from here on run in the loop's scheduling class, set before the
        # session opens so that Zenoh's own threads, which write each setpoint to the socket,
        # inherit it: at normal priority a busy machine held them off for 100-300 ms at a time
        # while the loop kept handing them setpoints, and the arm's driver braked for want of any.
        # The reader inherits it too: at normal priority it could be preempted while holding the
        # GIL, and the real-time loop would wait for it.
        set_real_time_priority(spec.realtime_priority)
        try:
            zcfg = to_zenoh_config(spec.zenoh)
            # A setpoint in motion that cannot be queued at once is dropped at once: waiting for
            # room (Zenoh's default, up to 1 ms) only delays the loop, and the next setpoint
            # supersedes it a period later anyway.
            zcfg.insert_json5("transport/link/tx/queue/congestion_control/drop/wait_before_drop",
                              str(DROP_WAIT_US))
            session = zenoh.open(zcfg)
        except zenoh.ZError as exc:
            self.conn.send(f"no Zenoh session ({exc})")
            return
        # A setpoint in motion is superseded a period later: under congestion it is dropped
        # rather than blocking the loop on a slow subscriber (a blocking put stalled it for up
        # to 5 ms). The last setpoint of a motion (at rest) must arrive: a lost one leaves the
        # arm short of the goal.
        moving = session.declare_publisher(spec.key, congestion_control=zenoh.CongestionControl.DROP,
                                           priority=zenoh.Priority.REAL_TIME, express=True)
        final = session.declare_publisher(spec.key, congestion_control=zenoh.CongestionControl.BLOCK,
                                          priority=zenoh.Priority.REAL_TIME, express=True)
        pin_thread(spec.cpu_affinity)
        reader = threading.Thread(target=self.receive, name="setpoint-stream-reader", daemon=True)
        reader.start()
        # What the loop allocates (setpoints, their bytes) holds no cycles: a collection pass
        # would only stall a tick.
        gc.freeze()
        gc.disable()
        self.conn.send("ready")
        period = spec.period_s
        tick = spec.origin_s + math.ceil((time.monotonic() - spec.origin_s) / period) * period
        wall_from_monotonic_s, refresh_at = wall_from_monotonic(), tick + WALL_REFRESH_S
        active: SetpointTable | None = None
        braking = False
        try:
            while True:
                if self.closing.is_set() and not braking:
                    braking = True
                    active = self._brake(active, tick)
                    if active is None:
                        break
                active = active if braking else self.take(tick, active)
                if active is not None:
                    rows = len(active.position)
                    row = min(max(int(round((tick - active.start_s) / period)), 0), rows - 1)
                    if row == rows - 1 and not active.complete:
                        # The rest of the trajectory is overdue: never hold a moving arm still.
                        log.error("setpoint stream: the rest of '%s' did not arrive in time; braking",
                                  active.trajectory_id)
                        self.starved += 1
                        active = self._brake(active, tick)
                        rows, row = len(active.position), 0
                    last = row == rows - 1
                    # The stamp is the moment the setpoint is for (its tick, as Unix time), not
                    # when it was put: a consumer can place it in time even when it left late.
                    (final if last else moving).put(Setpoint(
                        stamp=tick + wall_from_monotonic_s, trajectory_id=active.trajectory_id, names=spec.joint_names,
                        position=active.position[row], velocity=active.velocity[row],
                        acceleration=active.acceleration[row]).to_wire())
                    if self.published < len(self.times):
                        self.times[self.published] = time.monotonic()
                    self.published += 1
                    if last:
                        active = None
                        if braking:
                            break
                if self.stats_asked.is_set():
                    self.answer_stats()
                if tick >= refresh_at:  # follows NTP slewing the wall clock
                    wall_from_monotonic_s, refresh_at = wall_from_monotonic(), tick + WALL_REFRESH_S
                tick += period
                now = time.monotonic()
                if tick < now - period:  # fell behind (the machine stalled): skip whole ticks, keep the grid
                    tick += math.ceil((now - tick) / period) * period
                # Sleep wakes up late by 0.05-1 ms; the last `busy_wait_s` before a tick is spent
                # polling the clock instead, trading CPU for period accuracy.
                delay = tick - now - spec.busy_wait_s
                if delay > 0:
                    time.sleep(delay)
                while time.monotonic() < tick:
                    time.sleep(0)
        finally:
            moving.undeclare()
            final.undeclare()
            session.close()

    def _brake(self, active: SetpointTable | None, tick_s: float) -> SetpointTable | None:
        """A table braking from the row due at `tick_s` to rest at full limits, or None when at rest."""
        if active is None:
            return None
        from robonav.pipeline.trajectory.stopping import stop_trajectory

        period = self.spec.period_s
        row = min(max(int(round((tick_s - active.start_s) / period)), 0), len(active.position) - 1)
        if row == len(active.position) - 1 and active.complete:
            return dataclasses.replace(active, start_s=tick_s, position=active.position[row:],
                                       velocity=active.velocity[row:], acceleration=active.acceleration[row:])
        limits = self.spec.limits
        stop = stop_trajectory(active.position[row], active.velocity[row], active.acceleration[row],
                               max_velocity=limits.velocity, max_acceleration=limits.acceleration, max_jerk=limits.jerk)
        return sample_table(stop, active.trajectory_id, tick_s, period)


def wall_from_monotonic(tries: int = 5) -> float:
    """time.time() - time.monotonic() [s], from the tightest of `tries` bracketed reads.

    One pair of reads is off by however long the process was preempted between them (50 µs
    seen on a busy machine), which would put a setpoint's stamp off its tick."""
    best_spread, best = math.inf, 0.0
    for _ in range(tries):
        before = time.monotonic()
        wall = time.time()
        after = time.monotonic()
        if after - before < best_spread:
            best_spread, best = after - before, wall - 0.5 * (before + after)
    return best


def _run(spec: _StreamSpec, conn: Any, delay_ticks: Any) -> None:  # noqa: ANN401 - a Connection, a RawValue
    """Process body."""
    log_format = os.environ.get(LOG_FORMAT_ENV, "text")  # the parent's --log-format (setup_logging set it)
    setup_logging(logging.getLevelName(spec.log_level), log_format if log_format in LOG_FORMATS else "text")
    sys.setswitchinterval(REALTIME_SWITCH_INTERVAL_S)
    _Loop(spec, conn, delay_ticks).run()


def pin_thread(cpus: tuple[int, ...]) -> None:
    """Let the calling thread (and threads it starts later) run only on `cpus` (empty: leave it).

    With the loop on a CPU of its own (best with `isolcpus`), other work cannot delay it, and a
    reference loop on the same CPU (`robonav bench executor --reference-loop`) shares exactly
    the stalls the machine gives it."""
    if not cpus or not hasattr(os, "sched_setaffinity"):
        return
    try:
        os.sched_setaffinity(0, set(cpus))  # 0: this thread on Linux
        log.info("setpoint loop pinned to CPUs %s", sorted(cpus))
    except OSError as exc:
        log.warning("setpoint loop not pinned to CPUs %s: %s", sorted(cpus), exc)


def set_real_time_priority(priority: int) -> None:
    """Run the calling thread (the streaming loop) under SCHED_FIFO at `priority` (0: leave it).

    What robot control loops do (ros2_control, Franka's libfranka): the scheduler then never
    makes the loop wait for ordinary threads and processes, which on a busy 2-core machine
    otherwise costs it whole milliseconds (measured with perception at 30 Hz beside it: p99
    period error 2.1 ms at normal priority, 0.09 ms under SCHED_FIFO). It needs CAP_SYS_NICE or
    an RLIMIT_RTPRIO of at least `priority` (`ulimit -r`; compose `ulimits: rtprio`); without
    either the loop runs at normal priority.
    """
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))  # 0: this thread on Linux
        log.info("setpoint loop runs under SCHED_FIFO priority %d", priority)
    except (PermissionError, OSError) as exc:
        log.warning("setpoint loop stays at normal priority: SCHED_FIFO refused (%s); "
                    "grant CAP_SYS_NICE or an rtprio limit (ulimit -r), or set executor.realtime_priority: 0", exc)
