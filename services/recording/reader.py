"""A recording read ahead in another process, for a replay that has to keep time.

Decompressing and CRC-checking chunks is CPU work in Python. In the publishing process it
would hold the GIL, and on a busy machine the OS may preempt it while it holds the GIL, so
the publishing loop could wait tens of milliseconds past a message's due time. A child
process (`python -m robonav.services.recording.reader`, so it neither forks the parent's Zenoh
threads nor re-runs the caller's script) reads the file and streams the messages to its
stdout; a thread here only moves them from the pipe (the copy happens in `os.read`, without
the GIL) into a bounded queue.

Frames: u32 length, then `K` + key (a new key, numbered in order of appearance); `M` + loop
(u32), receive ns (i64), publish ns (i64), key number (u32) + payload; `E` + JSON
{offset, message} (a damaged file); `D` (done).
"""

from __future__ import annotations

import json
import os
import queue
import struct
import subprocess
import sys
import threading
from collections.abc import Sequence
from typing import Any, BinaryIO

from robonav.services.recording.files import RecordedMessage, Recording, RecordingError

_HEADER = struct.Struct("<IqqI")
_LENGTH = struct.Struct("<I")
_JOIN_TIMEOUT_S = 5.0


def stream(path: str, keys: Sequence[str], start_ns: int | None, end_ns: int | None, loop: bool,
           out: BinaryIO, recover: bool = False) -> None:
    """Write the recording's messages (over and over with `loop`) as frames to `out`."""

    def send(frame: bytes) -> None:
        out.write(_LENGTH.pack(len(frame)))
        out.write(frame)

    numbers: dict[str, int] = {}
    try:
        recording = Recording(path, recover=recover)
        pass_index = 0
        while True:
            count = 0
            for message in recording.messages(keys=keys, start_ns=start_ns, end_ns=end_ns):
                number = numbers.get(message.key)
                if number is None:
                    number = numbers[message.key] = len(numbers)
                    send(b"K" + message.key.encode())
                send(b"M" + _HEADER.pack(pass_index, message.receive_time_ns, message.source_time_ns, number)
                     + message.payload)
                count += 1
            if not loop or count == 0:
                break
            pass_index += 1
        send(b"D")
    except RecordingError as exc:
        send(b"E" + json.dumps({"offset": exc.offset, "message": exc.message}).encode())
    out.flush()


class ReadAhead:
    """(loop, message) items of a recording, read by a child process up to `max_items` ahead."""

    def __init__(self, recording: Recording, *, keys: Sequence[str], start_ns: int | None, end_ns: int | None,
                 loop: bool, max_items: int) -> None:
        self.path = recording.path
        self.items: queue.Queue[Any] = queue.Queue(maxsize=max_items)
        self._halt = threading.Event()
        request = json.dumps({"path": str(recording.path), "keys": list(keys), "start_ns": start_ns,
                              "end_ns": end_ns, "loop": loop, "recover": not recording.complete})
        self._process = subprocess.Popen([sys.executable, "-m", "robonav.services.recording.reader", request],
                                         stdout=subprocess.PIPE, bufsize=0)
        self._thread = threading.Thread(target=self._receive, name="replay-receive", daemon=True)
        self._thread.start()

    def _put(self, item: Any) -> bool:
        while not self._halt.is_set():
            try:
                self.items.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _read_exactly(self, n: int) -> bytes:
        assert self._process.stdout is not None
        fd = self._process.stdout.fileno()
        parts, remaining = [], n
        while remaining:
            part = os.read(fd, min(remaining, 1 << 20))
            if not part:
                raise EOFError
            parts.append(part)
            remaining -= len(part)
        return b"".join(parts)

    def _receive(self) -> None:
        keys: list[str] = []
        try:
            while not self._halt.is_set():
                (length,) = _LENGTH.unpack(self._read_exactly(_LENGTH.size))
                frame = self._read_exactly(length)
                kind = frame[:1]
                if kind == b"M":
                    loop, receive_ns, source_ns, number = _HEADER.unpack_from(frame, 1)
                    message = RecordedMessage(keys[number], frame[1 + _HEADER.size:], receive_ns, source_ns)
                    if not self._put((loop, message)):
                        return
                elif kind == b"K":
                    keys.append(frame[1:].decode())
                elif kind == b"E":
                    error = json.loads(frame[1:])
                    self._put(RecordingError(self.path, error["offset"], error["message"]))
                    return
                else:
                    self._put(None)
                    return
        except (EOFError, OSError, ValueError):
            if not self._halt.is_set():
                self._put(RecordingError(self.path, 0, f"the reader process ended unexpectedly "
                                                       f"(exit code {self._process.poll()})"))

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def get(self, timeout_s: float) -> tuple[int, RecordedMessage] | None:
        """The next item; None at the end. Raises RecordingError (damaged file) or queue.Empty."""
        item = self.items.get(timeout=timeout_s)
        if isinstance(item, RecordingError):
            raise item
        return item

    def close(self) -> None:
        self._halt.set()
        if self._process.poll() is None:
            self._process.terminate()  # it may be blocked writing to the pipe
        self._process.wait(_JOIN_TIMEOUT_S)
        if self._process.stdout is not None:
            self._process.stdout.close()
        self._thread.join(_JOIN_TIMEOUT_S)


if __name__ == "__main__":
    args = json.loads(sys.argv[1])
    try:
        stream(args["path"], args["keys"], args["start_ns"], args["end_ns"], args["loop"], sys.stdout.buffer,
               args.get("recover", False))
    except (BrokenPipeError, KeyboardInterrupt):
        pass  # the replay stopped reading
