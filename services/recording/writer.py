"""The recorder's writing half, in its own process: frames on stdin, an MCAP file out.

`robonav record` receives samples in one process and writes them in this one, so the
Zenoh receive path never waits for the GIL behind compression, the Foxglove conversion or a
slow disk. (A lower priority for this process was tried: on a busy machine it then fell
behind for good and the buffer overflowed.)

Frames (u32 length, then): `M` + receive ns (i64), source ns (i64), receive index (u64: the
sample's number among those the recorder received on its key, dropped ones included), key
length (u16), key, payload; `F` + JSON of the receiver's final counters, which ends the file.
On `F` this process writes the `robonav.record_stats` metadata and the MCAP summary, prints the
merged summary as JSON on stdout and exits 0.

A killed recorder: stdin closes without `F`. This process still finishes the file, and counts
as lost at the recorder's exit every sample the recorder had received (and not dropped) that
never reached it: those were still in its queue. It knows how many the recorder received from
a counters file the recorder rewrites every CHECKPOINT_S from a thread of its own (so a full
pipe does not hold it back); samples received after the last rewrite and lost with the
recorder cannot be counted (at most CHECKPOINT_S of traffic). If this process dies too, the
file has no footer; every chunk is flushed within FLUSH_INTERVAL_S (with a
`robonav.record_checkpoint` metadata record of the counts so far), and
`Recording(path, recover=True)` reads the complete chunks back.
"""

from __future__ import annotations

import array
import bisect
import json
import os
import struct
import sys
import time
from pathlib import Path
from typing import Any, BinaryIO

from robonav.services.recording.files import RecordingWriter

LENGTH = struct.Struct("<I")
MESSAGE_HEADER = struct.Struct("<qqQH")
CHECKPOINT_S = 0.25
"""The recorder rewrites its counters file this often while it runs [s]."""
FLUSH_INTERVAL_S = 1.0
"""Every message is in a finished, flushed chunk within this long of arriving here [s]."""


def frame_message(key: str, payload: bytes, receive_ns: int, source_ns: int, index: int) -> list[bytes]:
    """The parts of one `M` frame (written in turn, so the payload is never copied into a new buffer)."""
    key_bytes = key.encode()
    head = b"M" + MESSAGE_HEADER.pack(receive_ns, source_ns, index, len(key_bytes)) + key_bytes
    return [LENGTH.pack(len(head) + len(payload)), head, payload]


def frame_finish(counters: dict[str, Any]) -> bytes:
    body = b"F" + json.dumps(counters).encode()
    return LENGTH.pack(len(body)) + body


class CountersFile:
    """The recorder's counters, rewritten whole (write, then rename) so a reader never sees half of them."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def write(self, counters: dict[str, Any]) -> None:
        partial = self.path.with_suffix(".partial")
        partial.write_text(json.dumps(counters), encoding="utf-8")
        os.replace(partial, self.path)

    def read(self) -> dict[str, Any]:
        try:
            return json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {}

    def remove(self) -> None:
        """Delete it and its directory (the recorder's private temporary one)."""
        for path in (self.path, self.path.with_suffix(".partial")):
            path.unlink(missing_ok=True)
        try:
            self.path.parent.rmdir()
        except OSError:
            pass


class LossAccount:
    """Which receive indexes reached the file, per key, to count what a killed recorder lost."""

    def __init__(self) -> None:
        self.indexes: dict[str, array.array] = {}

    def on_message(self, key: str, index: int) -> None:
        self.indexes.setdefault(key, array.array("Q")).append(index)

    def lost(self, counters: dict[str, Any]) -> dict[str, int]:
        """Per key: received by the time of `counters`, not dropped, and never written."""
        received: dict[str, int] = counters.get("received", {})
        dropped: dict[str, int] = counters.get("dropped", {})
        lost = {}
        for key, n in received.items():
            # Indexes arrive in order: those up to n are the written ones it had received by then.
            written = bisect.bisect_right(self.indexes.get(key, array.array("Q")), n)
            if n - dropped.get(key, 0) - written > 0:
                lost[key] = n - dropped.get(key, 0) - written
        return lost


def merged_summary(writer: RecordingWriter, counters: dict[str, Any], *, finished: bool = True,
                   lost: dict[str, int] | None = None) -> dict[str, Any]:
    """The receiver's counters (received, dropped per key) with what was written.

    `finished`: the recorder sent its final counters; else they are its last checkpoint's and
    `lost` counts per key what it received by then that never arrived here.
    """
    received: dict[str, int] = counters.get("received", {})
    dropped: dict[str, int] = counters.get("dropped", {})
    lost = lost or {}
    per_key = {}
    for key in sorted(set(received) | set(writer.stats)):
        stats = writer.stats.get(key)
        per_key[key] = {
            "received": received.get(key, 0), "dropped": dropped.get(key, 0),
            "written": stats.written if stats else 0, "bytes": stats.bytes if stats else 0,
            "foxglove_written": stats.foxglove_written if stats else 0,
            "foxglove_skipped": stats.foxglove_skipped if stats else 0,
            "publisher_seq_gaps": stats.seq_gaps if stats else 0,
            "lost_at_recorder_exit": lost.get(key, 0),
        }
        if stats is not None and stats.foxglove_error is not None:
            per_key[key]["foxglove_error"] = stats.foxglove_error
    return {
        "received": sum(received.values()),
        "written": sum(v["written"] for v in per_key.values()),
        "dropped": sum(dropped.values()),
        "missed_upstream": counters.get("missed", 0) + sum(v["publisher_seq_gaps"] for v in per_key.values()),
        "recorder_finished": finished,
        "lost_at_recorder_exit": sum(lost.values()),
        "max_buffered_mb": counters.get("max_buffered_mb", 0.0),
        "write_error": None,
        "keys": per_key,
    }


def _read_exactly(stream: BinaryIO, n: int) -> bytes | None:
    data = stream.read(n)
    return data if len(data) == n else None


def run(output: str, foxglove: bool, metadata: dict[str, str], stream: BinaryIO,
        counters_file: CountersFile | None = None) -> dict[str, Any]:
    writer = RecordingWriter(output, foxglove_clouds=foxglove, metadata=metadata)
    account = LossAccount()
    counters: dict[str, Any] = {}
    finished = False
    next_flush = time.monotonic() + FLUSH_INTERVAL_S
    while (head := _read_exactly(stream, LENGTH.size)) is not None:
        (length,) = LENGTH.unpack(head)
        frame = _read_exactly(stream, length)
        if frame is None:
            break
        if frame[:1] == b"F":
            counters, finished = json.loads(frame[1:]), True
            break
        receive_ns, source_ns, index, key_length = MESSAGE_HEADER.unpack_from(frame, 1)
        start = 1 + MESSAGE_HEADER.size
        key = frame[start:start + key_length].decode()
        writer.write(key, frame[start + key_length:], receive_time_ns=receive_ns, source_time_ns=source_ns)
        account.on_message(key, index)
        if time.monotonic() >= next_flush:  # a kill of this process loses at most the last second
            checkpoint = counters_file.read() if counters_file is not None else {}
            writer.flush(merged_summary(writer, checkpoint, finished=False))
            next_flush = time.monotonic() + FLUSH_INTERVAL_S
    writer.settle_conversions()
    if finished:
        summary = merged_summary(writer, counters)
    else:  # the recorder died: its last counters are all there is
        counters = counters_file.read() if counters_file is not None else {}
        summary = merged_summary(writer, counters, finished=False, lost=account.lost(counters))
    writer.finish(summary)
    return summary


if __name__ == "__main__":
    args = json.loads(sys.argv[1])
    counters_path = args.get("counters_file")
    counters_file = CountersFile(counters_path) if counters_path else None
    summary = run(args["output"], args["foxglove"], args["metadata"], sys.stdin.buffer, counters_file)
    if counters_file is not None:
        counters_file.remove()
    try:
        print(json.dumps(summary), flush=True)
    except BrokenPipeError:  # the recorder was killed: the file is finished, nobody reads the summary
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
