"""`robonav record -o run.mcap [KEYEXPR ...]`: Zenoh traffic into an MCAP recording.

The Zenoh callback only copies the payload and the receive time into a queue; a thread
hands them to a writer process that compresses and writes (`record_writer.py`,
`recording.py`), so neither a slow disk nor the GIL stalls Zenoh. The queue
is bounded in bytes (`--max-buffer-mb`): a sample that does not fit is dropped, counted per
key and reported, never lost silently. Clouds whose `seq` jumps are counted as lost upstream.
SIGINT/SIGTERM (or `--duration`) stops the subscriber, drains the queue and finishes the
file, so Ctrl-C leaves a valid recording. A SIGKILL of this process leaves the writer to
finish the file, counting the samples lost with the queue (`writer.py`). An existing output
file is kept unless `--force`. Exit code 0: every received sample written; 1: samples were
dropped; 2: bad config or output, or no router to connect to.
"""

from __future__ import annotations

import argparse
import collections
import datetime
import json
import logging
import os
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh
import zenoh.ext

from robonav.pipeline.config import ConfigError
from robonav.services.common import add_logging_arguments, load_cli_config, open_session, setup_logging
from robonav.services.keys import Keys
from robonav.services.recording.writer import CHECKPOINT_S, CountersFile, frame_finish, frame_message
from robonav.services.signals import stop_on_signals

log = logging.getLogger("robonav.record")

DEFAULT_MAX_BUFFER_MB = 1024.0
_DROP_LOG_EVERY = 100
_EPOCH = datetime.datetime(1970, 1, 1, tzinfo=datetime.timezone.utc)


@dataclass
class RecorderStats:
    received: collections.Counter[str] = field(default_factory=collections.Counter)
    dropped: collections.Counter[str] = field(default_factory=collections.Counter)
    """Samples that did not fit in the write buffer, per key."""
    missed: int = 0
    """Samples zenoh-ext reported missing (publishers with sample-miss detection only)."""
    ignored_deletes: int = 0
    max_buffered_bytes: int = 0


def source_time_ns(sample: zenoh.Sample, receive_time_ns: int) -> int:
    """The publisher's timestamp (Zenoh HLC time) in Unix ns, else the receive time."""
    if sample.timestamp is None:
        return receive_time_ns
    delta = sample.timestamp.get_time() - _EPOCH
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1_000


class Recorder:
    """Subscribes to key expressions; a writer process (`record_writer.py`) writes the MCAP file."""

    def __init__(self, session: zenoh.Session, output: str | Path, key_exprs: list[str], *,
                 foxglove_clouds: bool = True, metadata: dict[str, str] | None = None,
                 max_buffer_bytes: int = int(DEFAULT_MAX_BUFFER_MB * 2**20)) -> None:
        self.stats = RecorderStats()
        self._max_buffer_bytes = max_buffer_bytes
        self._buffered_bytes = 0
        self._lock = threading.Lock()
        self._queue: queue.SimpleQueue[tuple[str, bytes, int, int, int] | None] = queue.SimpleQueue()
        # What it received so far, for the writer should this process be killed (`writer.py`).
        self._counters_file = CountersFile(Path(tempfile.mkdtemp(prefix="robonav-record-")) / "counters.json")
        self._counters_file.write(self.counters())
        request = json.dumps({"output": str(output), "foxglove": foxglove_clouds, "metadata": metadata or {},
                              "counters_file": str(self._counters_file.path)})
        self.writer = subprocess.Popen([sys.executable, "-m", "robonav.services.recording.writer", request],
                                       stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0,
                                       start_new_session=True)  # Ctrl-C reaches us, not the writer
        self._write_error: str | None = None
        self._thread = threading.Thread(target=self._send_loop, name="record-send", daemon=True)
        self._thread.start()
        self._closing = threading.Event()
        self._checkpoints = threading.Thread(target=self._checkpoint_loop, name="record-checkpoint", daemon=True)
        self._checkpoints.start()
        # Advanced subscribers also fetch the cached last sample of latched publishers (the
        # occupancy map) and report samples lost by publishers that enable miss detection.
        self._subscribers = [
            zenoh.ext.declare_advanced_subscriber(
                session, key, self._on_sample, history=zenoh.ext.HistoryConfig(detect_late_publishers=True))
            for key in key_exprs]
        self._miss_listeners = [s.sample_miss_listener(self._on_miss) for s in self._subscribers]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        received_ns = time.time_ns()
        key = str(sample.key_expr)
        if sample.kind != zenoh.SampleKind.PUT:
            self.stats.ignored_deletes += 1
            return
        payload = sample.payload.to_bytes()
        with self._lock:
            self.stats.received[key] += 1
            index = self.stats.received[key]  # its number on this key, dropped ones included
            # An empty queue always takes one sample, however large, so progress never stops.
            if self._buffered_bytes and self._buffered_bytes + len(payload) > self._max_buffer_bytes:
                self.stats.dropped[key] += 1
                dropped = sum(self.stats.dropped.values())
                if dropped == 1 or dropped % _DROP_LOG_EVERY == 0:
                    log.error("write buffer full (%.0f MB): dropped %d samples so far (latest on %s); "
                              "the disk or compression cannot keep up", self._buffered_bytes / 2**20, dropped, key)
                return
            self._buffered_bytes += len(payload)
            self.stats.max_buffered_bytes = max(self.stats.max_buffered_bytes, self._buffered_bytes)
        self._queue.put((key, payload, received_ns, source_time_ns(sample, received_ns), index))

    def _on_miss(self, miss: zenoh.ext.Miss) -> None:
        self.stats.missed += miss.nb
        log.error("zenoh reports %d samples missed from publisher %s", miss.nb, miss.source)

    def _send_loop(self) -> None:
        assert self.writer.stdin is not None
        fd = self.writer.stdin.fileno()
        while (item := self._queue.get()) is not None:
            key, payload, received_ns, source_ns, index = item
            if self._write_error is None:
                try:
                    for part in frame_message(key, payload, received_ns, source_ns, index):
                        _write_all(fd, part)
                except OSError as exc:  # the writer died (e.g. disk full): keep counting, report at the end
                    self._write_error = f"the writer process failed: {exc}"
                    log.error("%s", self._write_error)
            with self._lock:
                self._buffered_bytes -= len(payload)

    def _checkpoint_loop(self) -> None:
        """Rewrites the counters file every CHECKPOINT_S, whether or not the writer keeps up."""
        while not self._closing.wait(CHECKPOINT_S):
            try:
                self._counters_file.write(self.counters())
            except OSError as exc:  # a full /tmp: the loss count of a kill would be stale, nothing else
                log.warning("cannot update %s: %s", self._counters_file.path, exc)

    @property
    def buffered_bytes(self) -> int:
        with self._lock:
            return self._buffered_bytes

    def counters(self) -> dict[str, object]:
        with self._lock:
            return {"received": dict(self.stats.received), "dropped": dict(self.stats.dropped),
                    "missed": self.stats.missed, "max_buffered_mb": round(self.stats.max_buffered_bytes / 2**20, 1)}

    def close(self) -> dict[str, Any]:
        """Stop subscribing, hand over what is queued, let the writer finish the file; returns the summary."""
        for listener in self._miss_listeners:
            listener.undeclare()
        for sub in self._subscribers:
            sub.undeclare()
        self._closing.set()
        self._checkpoints.join()
        self._queue.put(None)
        self._thread.join()
        assert self.writer.stdin is not None and self.writer.stdout is not None
        try:
            _write_all(self.writer.stdin.fileno(), frame_finish(self.counters()))
            self.writer.stdin.close()
        except OSError as exc:
            self._write_error = self._write_error or f"the writer process failed: {exc}"
        output = self.writer.stdout.read()
        code = self.writer.wait()
        self._counters_file.remove()
        if code == 0 and output:
            summary: dict[str, Any] = json.loads(output)
        else:
            summary = {**self.counters(), "written": None, "keys": {}}
            summary["received"] = sum(self.stats.received.values())
            summary["dropped"] = sum(self.stats.dropped.values())
            self._write_error = self._write_error or f"the writer process exited with code {code}"
        summary["write_error"] = self._write_error
        return summary


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="robonav record", description=__doc__.split("\n\n")[0])
    parser.add_argument("key_exprs", nargs="*", metavar="KEYEXPR",
                        help="key expressions to record (default: robonav/<cell>/**)")
    parser.add_argument("-o", "--output", required=True, help="MCAP file to write (an existing one is kept unless --force)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing output file")
    parser.add_argument("--config", help="YAML config (Zenoh connection, cell)")
    parser.add_argument("--zenoh-config", metavar="FILE",
                        help="Zenoh JSON5 config (TLS, login, e.g. client-viewer.json5); overrides zenoh.config_file")
    parser.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    parser.add_argument("--no-foxglove", action="store_true", help="write only the raw channels (no Foxglove point clouds, transforms, scene updates, JSON copies)")
    parser.add_argument("--max-buffer-mb", type=float, default=DEFAULT_MAX_BUFFER_MB,
                        help="memory for samples waiting to be written; beyond it samples are dropped and counted")
    parser.add_argument("--json", help="write the summary (counts per key) to this file")
    add_logging_arguments(parser)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    setup_logging(args.log_level, args.log_format)
    try:
        cfg = load_cli_config(args.config, args.zenoh_config)
    except ConfigError as exc:
        log.error("%s", exc)
        return 2
    key_exprs = args.key_exprs or [f"{Keys(cfg.cell).root}/**"]
    try:
        for key in key_exprs:
            zenoh.KeyExpr(key)
    except zenoh.ZError as exc:
        log.error("bad key expression: %s", exc)
        return 2
    stop = stop_on_signals(signal.SIGINT, signal.SIGTERM)
    metadata = {"key_exprs": json.dumps(key_exprs), "cell": cfg.cell,
                "started_at": datetime.datetime.now(datetime.timezone.utc).isoformat()}
    try:
        Path(args.output).open("wb" if args.force else "xb").close()
    except FileExistsError:
        log.error("%s exists: choose another name, or --force to overwrite it", args.output)
        return 2
    except OSError as exc:
        log.error("cannot write %s: %s", args.output, exc.strerror or exc)
        return 2
    try:
        session = open_session(cfg.zenoh)
    except zenoh.ZError as exc:
        Path(args.output).unlink(missing_ok=True)  # the empty file made above, not a recording
        log.error("cannot reach the router at %s: %s", ", ".join(cfg.zenoh.connect), exc)
        return 2
    with session:
        recorder = Recorder(session, args.output, key_exprs, foxglove_clouds=not args.no_foxglove, metadata=metadata,
                            max_buffer_bytes=int(args.max_buffer_mb * 2**20))
        log.info("recording %s into %s", " ".join(key_exprs), args.output)
        stop.wait(args.duration)
        log.info("stopping: writing %.1f MB still buffered", recorder.buffered_bytes / 2**20)
        summary = recorder.close()
    summary["file"] = str(args.output)
    summary["file_mb"] = round(Path(args.output).stat().st_size / 2**20, 1)
    text = json.dumps(summary, indent=2)
    print(text, file=sys.stdout, flush=True)
    if args.json:
        Path(args.json).write_text(text + "\n", encoding="utf-8")
    if summary["write_error"]:
        log.error("the recording is incomplete: %s", summary["write_error"])
        return 2
    if summary["dropped"]:
        log.error("%d samples were dropped (see 'dropped' per key)", summary["dropped"])
        return 1
    return 0
