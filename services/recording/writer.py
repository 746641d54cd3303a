"""The recorder's writing half, in its own process: frames on stdin, an MCAP file out.

`robonav record` receives samples in one process and writes them in this one, so the
Zenoh receive path never waits for the GIL behind compression, the Foxglove conversion or a
slow disk. (A lower priority for this process was tried: on a busy machine it then fell
behind for good and the buffer overflowed.)

Frames (u32 length, then): `M` + receive ns (i64), source ns (i64), key length (u16), key,
payload; `F` + JSON of the receiver's counters, which ends the file. On `F` this process
writes the `robonav.record_stats` metadata and the MCAP summary, prints the merged summary
as JSON on stdout and exits 0. Without `F` (stdin closed) it still finishes the file.
"""

from __future__ import annotations

import json
import struct
import sys
from typing import Any, BinaryIO

from robonav.services.recording.files import RecordingWriter

LENGTH = struct.Struct("<I")
MESSAGE_HEADER = struct.Struct("<qqH")


def frame_message(key: str, payload: bytes, receive_ns: int, source_ns: int) -> list[bytes]:
    """The parts of one `M` frame (written in turn, so the payload is never copied into a new buffer)."""
    key_bytes = key.encode()
    head = b"M" + MESSAGE_HEADER.pack(receive_ns, source_ns, len(key_bytes)) + key_bytes
    return [LENGTH.pack(len(head) + len(payload)), head, payload]


def frame_finish(counters: dict[str, Any]) -> bytes:
    body = b"F" + json.dumps(counters).encode()
    return LENGTH.pack(len(body)) + body


def merged_summary(writer: RecordingWriter, counters: dict[str, Any]) -> dict[str, Any]:
    """The receiver's counters (received, dropped per key) with what was written."""
    received: dict[str, int] = counters.get("received", {})
    dropped: dict[str, int] = counters.get("dropped", {})
    per_key = {}
    for key in sorted(set(received) | set(writer.stats)):
        stats = writer.stats.get(key)
        per_key[key] = {
            "received": received.get(key, 0), "dropped": dropped.get(key, 0),
            "written": stats.written if stats else 0, "bytes": stats.bytes if stats else 0,
            "foxglove_written": stats.foxglove_written if stats else 0,
            "publisher_seq_gaps": stats.seq_gaps if stats else 0,
        }
    return {
        "received": sum(received.values()),
        "written": sum(v["written"] for v in per_key.values()),
        "dropped": sum(dropped.values()),
        "missed_upstream": counters.get("missed", 0) + sum(v["publisher_seq_gaps"] for v in per_key.values()),
        "max_buffered_mb": counters.get("max_buffered_mb", 0.0),
        "write_error": None,
        "keys": per_key,
    }


def _read_exactly(stream: BinaryIO, n: int) -> bytes | None:
    data = stream.read(n)
    return data if len(data) == n else None


def run(output: str, foxglove: bool, metadata: dict[str, str], stream: BinaryIO) -> dict[str, Any]:
    writer = RecordingWriter(output, foxglove_clouds=foxglove, metadata=metadata)
    counters: dict[str, Any] = {}
    while (head := _read_exactly(stream, LENGTH.size)) is not None:
        (length,) = LENGTH.unpack(head)
        frame = _read_exactly(stream, length)
        if frame is None:
            break
        if frame[:1] == b"F":
            counters = json.loads(frame[1:])
            break
        receive_ns, source_ns, key_length = MESSAGE_HEADER.unpack_from(frame, 1)
        start = 1 + MESSAGE_HEADER.size
        key = frame[start:start + key_length].decode()
        writer.write(key, frame[start + key_length:], receive_time_ns=receive_ns, source_time_ns=source_ns)
    summary = merged_summary(writer, counters)
    writer.finish(summary)
    return summary


if __name__ == "__main__":
    args = json.loads(sys.argv[1])
    print(json.dumps(run(args["output"], args["foxglove"], args["metadata"], sys.stdin.buffer)), flush=True)
