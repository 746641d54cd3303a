"""`robonav replay run.mcap`: publish a recording's raw payloads back on their keys.

Messages go out in file (= receive) order, each at its recorded receive time scaled by
`--rate` (or as fast as possible with `--rate max`), byte for byte as recorded, so
perception and the planner run on recorded clouds exactly as live. A child process reads
and decompresses ahead (`replay_reader.py`), so the publishing loop only waits on the clock:
it sleeps until `SPIN_S` before a message is due, then spins. Publishers block rather than drop under
congestion: a replay loses nothing. A corrupt file is an error naming the byte offset (exit
code 2); a truncated one (its writer was killed) is read up to its last complete record, with a
warning; `--check` reads the whole file without publishing.

A replay must not move or mislead a live cell: robot state and commands (`robot/**`,
`executor/**`: joint states, setpoints, executor status and path) are published only with
`--robot-keys`, and `--cell NAME` moves every key into another cell. Payloads go out as
recorded, so a replayed map or cloud carries its recorded `stamp`: a planner that judges a
map's age by its stamp takes it as old.
"""

from __future__ import annotations

import argparse
import json
import logging
import queue
import signal
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from robonav.pipeline.config import ConfigError
from robonav.services.common import add_logging_arguments, load_cli_config, open_session, setup_logging
from robonav.services.recording.files import Recording, RecordingError
from robonav.services.recording.reader import ReadAhead
from robonav.services.signals import stop_on_signals

log = logging.getLogger("robonav.replay")

SPIN_S = 0.002
"""The publishing loop spins (instead of sleeping) this long before a message is due [s]."""
READ_AHEAD_BYTES = 256 * 2**20
READ_AHEAD_MAX_ITEMS = 4096
PREFILL_TIMEOUT_S = 2.0
ROBOT_KEYS = ("robonav/*/robot/**", "robonav/*/executor/**")
"""Robot state and commands: a live cell's arm or its clients would take them as real."""


def is_robot_key(key: str) -> bool:
    return any(zenoh.KeyExpr(pattern).intersects(zenoh.KeyExpr(key)) for pattern in ROBOT_KEYS)


def in_cell(key: str, cell: str | None) -> str:
    """`key` moved into `cell` (`robonav/<cell>/...`); keys outside `robonav/` and `cell=None` stay."""
    parts = key.split("/")
    if cell is None or len(parts) < 3 or parts[0] != "robonav":
        return key
    return "/".join(["robonav", cell, *parts[2:]])


@dataclass(frozen=True)
class ReplayOptions:
    rate: float | None = 1.0
    """Speed factor on the recorded timing; None publishes as fast as possible."""
    loop: bool = False
    keys: tuple[str, ...] = ()
    """Key expressions to replay (wildcards allowed); empty replays every recorded key."""
    start_s: float | None = None
    """Skip messages received earlier than this after the recording's first message [s]."""
    end_s: float | None = None
    """Stop at messages received later than this after the recording's first message [s]."""
    robot_keys: bool = False
    """Also publish robot state and commands (ROBOT_KEYS); without it they are skipped."""
    cell: str | None = None
    """Publish under `robonav/<cell>/` instead of the recorded cell."""

    def __post_init__(self) -> None:
        if self.cell is not None and (not self.cell or "/" in self.cell or "*" in self.cell or "$" in self.cell):
            raise ValueError(f"cell must be a non-empty name without '/', '*' or '$', got {self.cell!r}")
        if self.rate is not None and not self.rate > 0:
            raise ValueError(f"rate must be > 0 (or 'max'), got {self.rate}")
        for name in ("start_s", "end_s"):
            value = getattr(self, name)
            if value is not None and not value >= 0:
                raise ValueError(f"{name} must be >= 0 seconds from the recording's start, got {value}")
        if self.start_s is not None and self.end_s is not None and self.end_s < self.start_s:
            raise ValueError(f"end ({self.end_s} s) is before start ({self.start_s} s)")


@dataclass
class ReplayResult:
    published: Counter[str]
    bytes: int
    loops: int
    wall_s: float
    timing_error_s: list[float]
    """Publish time minus due time of every message but each loop's first (rate set only)."""

    def summary(self) -> dict[str, Any]:
        errors_ms = np.abs(np.asarray(self.timing_error_s)) * 1e3
        timing = ({"p50_ms": float(np.percentile(errors_ms, 50)), "p99_ms": float(np.percentile(errors_ms, 99)),
                   "max_ms": float(errors_ms.max()), "samples": int(errors_ms.size)} if errors_ms.size else None)
        return {"published": sum(self.published.values()), "per_key": dict(sorted(self.published.items())),
                "mb": round(self.bytes / 2**20, 1), "loops": self.loops, "wall_s": round(self.wall_s, 3),
                "timing_error": timing}


class Replayer:
    """Publishes a recording's messages on a session with their recorded timing."""

    def __init__(self, session: zenoh.Session, recording: Recording, options: ReplayOptions) -> None:
        self.recording = recording
        self.options = options
        self._session = session
        start = recording.info.start_ns
        self._start_ns = None if options.start_s is None else start + int(options.start_s * 1e9)
        self._end_ns = None if options.end_s is None else start + int(options.end_s * 1e9)
        selectors = [zenoh.KeyExpr(k) for k in options.keys]
        keys = [k for k in recording.info.message_counts
                if not selectors or any(s.intersects(zenoh.KeyExpr(k)) for s in selectors)]
        self.skipped = {k: recording.info.message_counts[k] for k in keys
                        if is_robot_key(k) and not options.robot_keys}
        """Recorded robot-state and command keys left out (no `robot_keys`), with their message counts."""
        self.publishers = {k: session.declare_publisher(in_cell(k, options.cell),
                                                        congestion_control=zenoh.CongestionControl.BLOCK)
                           for k in keys if k not in self.skipped}

    def wait_for_subscribers(self, timeout_s: float) -> bool:
        """Wait until some recorded key has a subscriber (or the timeout passes)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if any(p.matching_status.matching for p in self.publishers.values()):
                return True
            time.sleep(0.01)
        return any(p.matching_status.matching for p in self.publishers.values())

    def run(self, stop: threading.Event) -> ReplayResult:
        """Publish until the recording (or the last loop) ends or `stop` is set.

        Raises:
            RecordingError: the file is damaged; messages before the damage were published.
        """
        if not self.publishers:
            return ReplayResult(Counter(), 0, 0, 0.0, [])
        typical = max(1, self.recording.size // max(1, sum(self.recording.info.message_counts.values())))
        max_items = min(READ_AHEAD_MAX_ITEMS, max(16, READ_AHEAD_BYTES // typical))
        # Exactly the keys published (recorded keys, no wildcards): skipped ones are not even read.
        reader = ReadAhead(self.recording, keys=tuple(self.publishers), start_ns=self._start_ns, end_ns=self._end_ns,
                           loop=self.options.loop, max_items=max_items)
        try:
            # Start the clock with a filled read-ahead queue: the first chunks decompress meanwhile.
            deadline = time.monotonic() + PREFILL_TIMEOUT_S
            while reader.alive and reader.items.qsize() < max_items // 2 and time.monotonic() < deadline:
                stop.wait(0.01)
            result = ReplayResult(Counter(), 0, 0, 0.0, [])
            t_start = time.perf_counter()
            try:
                self._publish_loop(reader, stop, result)
            finally:
                result.wall_s = time.perf_counter() - t_start
        finally:
            reader.close()
        return result

    def _publish_loop(self, reader: ReadAhead, stop: threading.Event, result: ReplayResult) -> None:
        rate = self.options.rate
        loop_base_s = time.perf_counter()
        current_loop, first_ns, last_ns, gaps_ns = -1, 0, 0, 0.0
        while not stop.is_set():
            try:
                item = reader.get(timeout_s=0.1)
            except queue.Empty:
                continue
            if item is None:
                return
            loop, message = item
            first_of_loop = loop != current_loop
            if first_of_loop:
                if current_loop >= 0 and rate is not None:
                    # The next pass starts one typical message gap after the last one.
                    loop_base_s += ((last_ns - first_ns) + gaps_ns) / 1e9 / rate
                elif rate is not None:
                    loop_base_s = time.perf_counter()
                current_loop, first_ns = loop, message.receive_time_ns
                result.loops = loop + 1
            if rate is not None:
                due_s = loop_base_s + (message.receive_time_ns - first_ns) / 1e9 / rate
                _sleep_until(due_s, stop)
                sent_s = time.perf_counter()
                if not first_of_loop:
                    result.timing_error_s.append(sent_s - due_s)
            elif stop.is_set():
                return
            self.publishers[message.key].put(message.payload)
            result.published[message.key] += 1
            result.bytes += len(message.payload)
            if loop == 0 and not first_of_loop:
                count = sum(result.published.values())
                gaps_ns = (message.receive_time_ns - first_ns) / max(1, count - 1)
            last_ns = message.receive_time_ns

    def close(self) -> None:
        for pub in self.publishers.values():
            pub.undeclare()


def _sleep_until(due_s: float, stop: threading.Event) -> None:
    while (remaining := due_s - time.perf_counter()) > 0 and not stop.is_set():
        if remaining > SPIN_S:
            time.sleep(remaining - SPIN_S)
        else:
            time.sleep(0)  # lets the receiving thread take the GIL while spinning


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="robonav replay", description=__doc__.split("\n\n")[0])
    parser.add_argument("file", help="MCAP recording written by `robonav record`")
    parser.add_argument("--rate", default="1", help="speed factor on the recorded timing, or 'max' (default 1)")
    parser.add_argument("--loop", action="store_true", help="start over at the end, until Ctrl-C")
    parser.add_argument("--keys", nargs="+", default=[], metavar="KEYEXPR", help="replay only these key expressions")
    parser.add_argument("--start", type=float, help="skip the first START seconds of the recording")
    parser.add_argument("--end", type=float, help="stop END seconds after the recording's start")
    parser.add_argument("--check", action="store_true",
                        help="read and verify the whole file, publish nothing; exit 0 complete, 1 truncated "
                             "(read up to its last complete record), 2 corrupt")
    parser.add_argument("--robot-keys", action="store_true",
                        help="also publish robot state and commands (robonav/*/robot/**, robonav/*/executor/**: "
                             "joint states, setpoints, executor status); a live cell's arm and clients take them as real")
    parser.add_argument("--cell", help="publish under robonav/CELL/ instead of the recorded cell")
    parser.add_argument("--wait-subscribers", type=float, default=2.0, metavar="S",
                        help="wait up to S seconds for a subscriber before publishing (default 2)")
    parser.add_argument("--config", help="YAML config (Zenoh connection)")
    parser.add_argument("--zenoh-config", metavar="FILE",
                        help="Zenoh JSON5 config (TLS, login, e.g. client-viewer.json5); overrides zenoh.config_file")
    parser.add_argument("--json", help="write the summary (counts, timing error) to this file")
    add_logging_arguments(parser)
    return parser.parse_args(argv)


def check(recording: Recording) -> dict[str, Any]:
    """Read every message (decompressing and checking every chunk's CRC); counts per key, and
    what the recorder counted (written, dropped, missed upstream, lost when it was killed)."""
    counts: Counter[str] = Counter()
    for message in recording.messages():
        counts[message.key] += 1
    expected = recording.info.message_counts
    if dict(counts) != {k: v for k, v in expected.items() if v}:
        raise RecordingError(recording.path, 0, f"message counts {dict(counts)} differ from the summary's {expected}")
    summary: dict[str, Any] = {"file": str(recording.path), "complete": recording.complete,
                               "messages": sum(counts.values()), "per_key": dict(sorted(counts.items())),
                               "duration_s": round(recording.info.duration_s, 3)}
    if not recording.complete:
        assert recording.truncated_at is not None
        summary.update(truncated_at=recording.truncated_at, lost_bytes=recording.size - recording.truncated_at)
    stats = recording.stats()
    if stats is not None:
        summary["recorder"] = {key: stats.get(key) for key in ("received", "written", "dropped", "missed_upstream",
                                                                  "recorder_finished", "lost_at_recorder_exit")}
    return summary


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    setup_logging(args.log_level, args.log_format)
    try:
        options = ReplayOptions(rate=None if args.rate == "max" else float(args.rate), loop=args.loop,
                                keys=tuple(args.keys), start_s=args.start, end_s=args.end, robot_keys=args.robot_keys,
                                cell=args.cell)
        for key in options.keys:
            zenoh.KeyExpr(key)
        cfg = load_cli_config(args.config, args.zenoh_config)
        recording = Recording(args.file, recover=True)
        if not recording.complete:
            log.warning("%s is truncated (its writer was killed): reading its %d bytes up to byte %d, its last "
                        "complete record; %d bytes after it are lost", args.file, recording.size,
                        recording.truncated_at, recording.size - (recording.truncated_at or 0))
        if args.check:
            summary = check(recording)
            _report(summary, args.json)
            return 0 if recording.complete else 1
    except (ValueError, ConfigError, zenoh.ZError, RecordingError) as exc:
        log.error("%s", exc)
        return 2
    stop = stop_on_signals(signal.SIGINT, signal.SIGTERM)
    with open_session(cfg.zenoh) as session:
        replayer = Replayer(session, recording, options)
        if replayer.skipped:
            log.warning("not replaying robot state and commands (%s: %d messages); --robot-keys publishes them",
                        ", ".join(sorted(replayer.skipped)), sum(replayer.skipped.values()))
        elif options.robot_keys:
            warn_live(session, recording, options)
        if not replayer.publishers:
            log.error("no recorded key to replay matches %s (recorded: %s)", list(options.keys) or "**",
                      sorted(recording.info.message_counts))
            return 2
        if not replayer.wait_for_subscribers(args.wait_subscribers):
            log.warning("no subscriber for any recorded key after %.1f s; publishing anyway", args.wait_subscribers)
        log.info("replaying %s (%.1f s, %d messages) at rate %s", args.file, recording.info.duration_s,
                 sum(recording.info.message_counts.values()), args.rate)
        try:
            result = replayer.run(stop)
        except RecordingError as exc:
            log.error("%s", exc)
            return 2
        finally:
            replayer.close()
    _report({**result.summary(), "skipped": dict(sorted(replayer.skipped.items())), "cell": options.cell,
             "complete": recording.complete}, args.json)
    return 0


def warn_live(session: zenoh.Session, recording: Recording, options: ReplayOptions) -> None:
    """Say so when robot state and commands go into a cell whose services are running."""
    cells = {in_cell(k, options.cell).split("/")[1] for k in recording.info.message_counts
             if is_robot_key(k) and k.startswith("robonav/")}
    for cell in sorted(cells):
        alive = {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in session.liveliness().get(f"robonav/{cell}/alive/*",
                                                                                          timeout=1.0)
                 if r.ok is not None} - {"router"}
        if alive:
            log.warning("replaying robot state and commands into cell %s, where %s are running: they take them as "
                        "real (--cell NAME replays into another cell)", cell, ", ".join(sorted(alive)))


def _report(summary: dict[str, Any], json_path: str | None) -> None:
    text = json.dumps(summary, indent=2)
    print(text, flush=True)
    if json_path:
        Path(json_path).write_text(text + "\n", encoding="utf-8")
