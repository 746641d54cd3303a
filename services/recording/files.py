"""A recording: an MCAP file of raw Zenoh payloads, written by `robonav record`, read by `robonav replay`.

Layout (the `mcap` library does the format; this module only decides what goes where):

- one channel per key expression, topic = the key, message encoding `msgpack`, the payload
  exactly as received, schema = a JSON Schema of the map (`recording_schema.py`);
- every message carries `log_time` = receive time and `publish_time` = source time (the
  publisher's Zenoh timestamp; the receive time when the sample has none), Unix ns;
- camera clouds are also written on `<key>/foxglove` as `foxglove.PointCloud`, right after
  the raw message, so zstd finds the shared point bytes in the same chunk; frame transforms,
  scene updates and JSON copies of other keys likewise (`foxglove.py`), and the robot's URDF
  as an attachment;
- zstd-compressed chunks; a `robonav.recording` metadata record with what was recorded and,
  at the end, a `robonav.record_stats` one with the per-key counts.

Reading checks what the library leaves to the caller: a file without its footer (a recorder
that was killed) or with a damaged record fails with `RecordingError` naming the byte offset.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import zenoh
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Footer, Message, Metadata
from mcap.stream_reader import MAGIC_SIZE, StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from robonav.services.recording.foxglove import Derived, FoxgloveConverter
from robonav.services.recording.schema import (
    FOXGLOVE_SUFFIX,
    JSONSCHEMA_ENCODING,
    MSGPACK_ENCODING,
    foxglove_point_cloud,
    foxglove_point_cloud_schema,
    is_cloud_key,
    json_schema_for_key,
)

MCAP_MAGIC = b"\x89MCAP0\r\n"
STATS_METADATA = "robonav.record_stats"
CHECKPOINT_METADATA = "robonav.record_checkpoint"
CHUNK_SIZE_BYTES = 4 * 1024 * 1024
"""Chunks this large hold a cloud and its Foxglove copy together (zstd then shares their bytes)."""
_FOOTER_RECORD_BYTES = 1 + 8 + 8 + 8 + 4
"""opcode, length, summary_start, summary_offset_start, summary_crc."""


class RecordingError(Exception):
    """A recording cannot be read: not MCAP, truncated or corrupt, at byte `offset`."""

    def __init__(self, path: str | Path, offset: int, message: str) -> None:
        self.path = str(path)
        self.offset = offset
        self.message = message
        super().__init__(f"{path}: byte offset {offset}: {message}")


@dataclass
class KeyStats:
    """Counts for one key expression of a recording."""

    written: int = 0
    bytes: int = 0
    foxglove_written: int = 0
    foxglove_skipped: int = 0
    """Messages recorded raw without their Foxglove copy: a payload that did not decode as the
    key's message, a value no viewer draws (NaN), or a path whose robot description never came."""
    foxglove_error: str | None = None
    """Why the last one was skipped."""
    seq_gaps: int = 0
    """Clouds missing between consecutive `seq` values: lost before they reached the recorder."""
    last_seq: int | None = None


class RecordingWriter:
    """Writes received payloads into an MCAP file; `finish` must be called for a valid file."""

    def __init__(self, output: str | Path | BinaryIO, *, foxglove_clouds: bool = True,
                 metadata: dict[str, str] | None = None, chunk_size_bytes: int = CHUNK_SIZE_BYTES) -> None:
        self._file: BinaryIO | None = open(output, "wb") if isinstance(output, (str, Path)) else None
        stream = self._file if self._file is not None else output
        self._stream = stream
        self._writer = Writer(stream, chunk_size=chunk_size_bytes, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="robonav-arm record")
        self._writer.add_metadata("robonav.recording", dict(metadata or {}))
        self._foxglove = foxglove_clouds
        self._channels: dict[str, int] = {}
        self._foxglove_channels: dict[str, int] = {}
        self._foxglove_schema: int | None = None
        self._derived_channels: dict[str, int] = {}
        self._derived_schemas: dict[tuple[str, str], int] = {}
        self._converter = FoxgloveConverter()
        self.stats: dict[str, KeyStats] = {}
        self._finished = False

    def write(self, key: str, payload: bytes, *, receive_time_ns: int, source_time_ns: int) -> None:
        """Append one sample: the raw payload on its key's channel (and a Foxglove copy of a cloud)."""
        channel = self._channels.get(key)
        if channel is None:
            channel = self._channels[key] = self._register(key)
            self.stats[key] = KeyStats()
        stats = self.stats[key]
        stats.written += 1
        stats.bytes += len(payload)
        self._writer.add_message(channel, log_time=receive_time_ns, data=payload, publish_time=source_time_ns,
                                 sequence=stats.written)
        if not is_cloud_key(key):
            if self._foxglove:
                self._write_derived(key, payload, stats, receive_time_ns, source_time_ns)
            return
        try:
            foxglove, seq = foxglove_point_cloud(payload)
        except ValueError:  # not a PointCloud after all: the raw message is what counts
            stats.foxglove_skipped += 1
            return
        if stats.last_seq is not None and seq > stats.last_seq + 1:
            stats.seq_gaps += seq - stats.last_seq - 1
        stats.last_seq = seq
        if self._foxglove:
            self._writer.add_message(self._foxglove_channel(key), log_time=receive_time_ns, data=foxglove,
                                     publish_time=source_time_ns, sequence=stats.written)
            stats.foxglove_written += 1

    def _write_derived(self, key: str, payload: bytes, stats: KeyStats, receive_time_ns: int,
                       source_time_ns: int) -> None:
        try:
            derived, attachments = self._converter.convert(key, payload)
        except Exception as exc:  # any error: a copy for viewers must never cost the recording its raw data
            stats.foxglove_skipped += 1
            stats.foxglove_error = f"{type(exc).__name__}: {exc}"
            return
        for message in derived:
            self._writer.add_message(self._derived_channel(key, message), log_time=receive_time_ns, data=message.data,
                                     publish_time=source_time_ns, sequence=stats.written)
            stats.foxglove_written += 1
        for attachment in attachments:
            self._writer.add_attachment(create_time=source_time_ns, log_time=receive_time_ns, name=attachment.name,
                                        media_type=attachment.media_type, data=attachment.data)

    def settle_conversions(self) -> None:
        """Count as skipped what waited for a robot description that never came (call before the summary)."""
        for key, reason in self._converter.undrawn().items():
            self.stats[key].foxglove_skipped += 1
            self.stats[key].foxglove_error = reason

    def _derived_channel(self, key: str, message: Derived) -> int:
        channel = self._derived_channels.get(message.topic)
        if channel is None:
            schema_key = (message.schema_name, message.schema_encoding)
            if schema_key not in self._derived_schemas:
                self._derived_schemas[schema_key] = self._writer.register_schema(
                    name=message.schema_name, encoding=message.schema_encoding, data=message.schema)
            channel = self._derived_channels[message.topic] = self._writer.register_channel(
                topic=message.topic, message_encoding=message.message_encoding,
                schema_id=self._derived_schemas[schema_key], metadata={"source_key": key})
        return channel

    def _register(self, key: str) -> int:
        name, schema = json_schema_for_key(key)
        schema_id = self._writer.register_schema(name=name, encoding=JSONSCHEMA_ENCODING, data=schema)
        return self._writer.register_channel(topic=key, message_encoding=MSGPACK_ENCODING, schema_id=schema_id,
                                             metadata={"zenoh_key": key})

    def _foxglove_channel(self, key: str) -> int:
        if key not in self._foxglove_channels:
            if self._foxglove_schema is None:
                name, data = foxglove_point_cloud_schema()
                self._foxglove_schema = self._writer.register_schema(name=name, encoding="protobuf", data=data)
            self._foxglove_channels[key] = self._writer.register_channel(
                topic=key + FOXGLOVE_SUFFIX, message_encoding="protobuf", schema_id=self._foxglove_schema,
                metadata={"source_key": key})
        return self._foxglove_channels[key]

    def flush(self, checkpoint: dict[str, object] | None = None) -> None:
        """End the chunk in progress and hand everything to the OS, so a killed writer loses
        nothing written so far; `checkpoint` (the counts so far) goes into a
        `robonav.record_checkpoint` metadata record after it."""
        if self._finished:
            return
        self._writer.flush()
        if checkpoint is not None:
            self._writer.add_metadata(CHECKPOINT_METADATA, {"json": json.dumps(checkpoint, sort_keys=True)})
        self._stream.flush()

    def finish(self, stats: dict[str, object] | None = None) -> None:
        """Write the stats metadata, the index and the footer; close a file opened by path."""
        if self._finished:
            return
        self._finished = True
        if stats is not None:
            self._writer.add_metadata(STATS_METADATA, {"json": json.dumps(stats, sort_keys=True)})
        self._writer.finish()
        if self._file is not None:
            self._file.close()


@dataclass(frozen=True)
class RecordedMessage:
    key: str
    payload: bytes
    receive_time_ns: int
    """When the recorder received it (MCAP log_time), Unix ns."""
    source_time_ns: int
    """When it was published (MCAP publish_time), Unix ns."""


@dataclass(frozen=True)
class RecordingInfo:
    """What a recording's summary says (read without touching the data)."""

    start_ns: int
    end_ns: int
    message_counts: dict[str, int] = field(default_factory=dict)
    """Raw (msgpack) messages per key expression."""
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9


class Recording:
    """A recording opened for reading; its structure (magic, footer, summary) is checked on open.

    `recover`: a file without its footer (its writer was killed) is read up to its last complete
    record instead: `complete` is then False and `truncated_at` the byte where the readable part
    ends; channels and counts come from reading every chunk (there is no summary to read).

    Raises:
        RecordingError: not MCAP, truncated (no footer, and not `recover`), or a damaged summary.
    """

    def __init__(self, path: str | Path, *, recover: bool = False) -> None:
        self.path = Path(path)
        self.complete = True
        self.truncated_at: int | None = None
        """Where the readable part of a truncated file ends (its last complete record) [byte]."""
        try:
            self.size = self.path.stat().st_size
        except OSError as exc:
            raise RecordingError(path, 0, f"cannot open: {exc.strerror or exc}") from exc
        with open(self.path, "rb") as f:
            if f.read(MAGIC_SIZE) != MCAP_MAGIC:
                raise RecordingError(path, 0, "not an MCAP file (wrong magic bytes)")
            f.seek(max(0, self.size - MAGIC_SIZE - _FOOTER_RECORD_BYTES))
            tail = f.read()
        footer_ok = (len(tail) == MAGIC_SIZE + _FOOTER_RECORD_BYTES and tail.endswith(MCAP_MAGIC)
                     and tail[0] == 0x02)
        if not footer_ok:
            end = self._last_complete_record_end()
            if recover:
                self.complete, self.truncated_at = False, end
                self.channels, self.info = self._scan()
                return
            raise RecordingError(path, end, f"truncated: the file ({self.size} bytes) has no MCAP footer and its "
                                 f"last complete record ends at byte {end}; the recorder was stopped "
                                 "without finishing the file (killed, or the disk filled up)")
        summary_start, _, _ = struct.unpack_from("<QQI", tail, 9)
        self.channels, self.info = self._read_summary(summary_start)

    def _records(self, f: BinaryIO) -> Iterator[tuple[int, object]]:
        """(offset, record) of every top-level record, chunks left compressed."""
        reader = StreamReader(f, skip_magic=True, emit_chunks=True, record_size_limit=self.size)
        offset = f.tell()
        # A recovered file is read up to its last complete record, never into the torn one.
        stop = self.truncated_at if self.truncated_at is not None else self.size + 1
        if offset >= stop:
            return
        try:
            for record in reader.records:
                yield offset, record
                offset = f.tell()
                if isinstance(record, Footer) or offset >= stop:
                    return
        except (McapError, struct.error, UnicodeDecodeError, ValueError, KeyError) as exc:
            kind = "ends inside the" if f.tell() >= self.size else "has a damaged"
            raise RecordingError(self.path, offset, f"the file {kind} record starting here "
                                 f"({type(exc).__name__}: {exc})") from exc

    def _last_complete_record_end(self) -> int:
        end = MAGIC_SIZE
        with open(self.path, "rb") as f:
            f.seek(MAGIC_SIZE)
            try:
                for _offset, _record in self._records(f):
                    end = f.tell()
            except RecordingError as exc:
                end = exc.offset
        return end

    def _scan(self) -> tuple[dict[int, Channel], RecordingInfo]:
        """Channels, counts and metadata of a recovered file, from its data section."""
        channels: dict[int, Channel] = {}
        counts: dict[str, int] = {}
        metadata: dict[str, dict[str, str]] = {}
        times: list[int] = []

        def on(record: object) -> None:
            if isinstance(record, Channel):
                channels[record.id] = record
                if record.message_encoding == MSGPACK_ENCODING:
                    counts.setdefault(record.topic, 0)
            elif isinstance(record, Message) and record.channel_id in channels:
                channel = channels[record.channel_id]
                if channel.message_encoding == MSGPACK_ENCODING:
                    counts[channel.topic] += 1
                    times.append(record.log_time)

        with open(self.path, "rb") as f:
            f.seek(MAGIC_SIZE)
            for offset, record in self._records(f):
                if isinstance(record, Chunk):
                    for inner in self._chunk_records(record, offset):
                        on(inner)
                elif isinstance(record, Metadata):
                    metadata[record.name] = dict(record.metadata)
                else:
                    on(record)
        return channels, RecordingInfo(min(times, default=0), max(times, default=0), counts, metadata)

    def stats(self) -> dict[str, object] | None:
        """What the recorder counted: its final stats, else (a recovered file) its last checkpoint's."""
        for name in (STATS_METADATA, CHECKPOINT_METADATA):
            if name in self.info.metadata:
                return json.loads(self.info.metadata[name]["json"])
        return None

    def _read_summary(self, summary_start: int) -> tuple[dict[int, Channel], RecordingInfo]:
        """Channels and counts from the summary section, through the library's seeking reader."""
        with open(self.path, "rb") as f:
            try:
                reader = SeekingReader(f, record_size_limit=self.size)
                summary = reader.get_summary()
                metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            except (McapError, struct.error, UnicodeDecodeError, ValueError, KeyError) as exc:
                raise RecordingError(self.path, summary_start, f"the summary section starting here is damaged "
                                     f"({type(exc).__name__}: {exc})") from exc
        if summary is None or summary.statistics is None:
            raise RecordingError(self.path, summary_start, "the file has no summary statistics")
        stats = summary.statistics
        counts = {c.topic: stats.channel_message_counts.get(cid, 0) for cid, c in summary.channels.items()
                  if c.message_encoding == MSGPACK_ENCODING}
        return dict(summary.channels), RecordingInfo(stats.message_start_time, stats.message_end_time, counts, metadata)

    def messages(self, *, keys: Sequence[str] = (), start_ns: int | None = None,
                 end_ns: int | None = None) -> Iterator[RecordedMessage]:
        """Raw messages in file order (= receive order), optionally filtered.

        Args:
            keys: Key expressions (wildcards allowed); a message is kept when its key
                intersects one of them. Empty keeps every key.
            start_ns, end_ns: Keep messages received in [start_ns, end_ns] (Unix ns).

        Raises:
            RecordingError: a damaged record or a chunk failing its CRC, naming its offset.
        """
        selectors = [zenoh.KeyExpr(k) for k in keys]
        channels: dict[int, str] = {}
        lo = start_ns if start_ns is not None else -1
        hi = end_ns if end_ns is not None else 2**64

        def wanted(record: Message) -> bool:
            return record.channel_id in channels and lo <= record.log_time <= hi

        def on_channel(record: Channel) -> None:
            if record.message_encoding == MSGPACK_ENCODING and (
                    not selectors or any(s.intersects(zenoh.KeyExpr(record.topic)) for s in selectors)):
                channels[record.id] = record.topic

        for channel in self.channels.values():
            on_channel(channel)
        with open(self.path, "rb") as f:
            f.seek(MAGIC_SIZE)
            for offset, record in self._records(f):
                if isinstance(record, Channel):
                    on_channel(record)
                elif isinstance(record, Message) and wanted(record):
                    yield RecordedMessage(channels[record.channel_id], record.data, record.log_time, record.publish_time)
                elif isinstance(record, Chunk) and record.message_end_time >= lo and record.message_start_time <= hi:
                    for inner in self._chunk_records(record, offset):
                        if isinstance(inner, Channel):
                            on_channel(inner)
                        elif isinstance(inner, Message) and wanted(inner):
                            yield RecordedMessage(channels[inner.channel_id], inner.data, inner.log_time,
                                                  inner.publish_time)

    def _chunk_records(self, chunk: Chunk, offset: int) -> list[object]:
        try:
            return list(breakup_chunk(chunk, validate_crc=True))
        except (McapError, struct.error, UnicodeDecodeError, ValueError, zlib.error) as exc:
            raise RecordingError(self.path, offset, f"the chunk starting here is corrupt "
                                 f"({type(exc).__name__}: {exc})") from exc
        except Exception as exc:  # zstandard.ZstdError and friends: name the chunk, whatever the codec says
            raise RecordingError(self.path, offset, f"the chunk starting here does not decompress "
                                 f"({type(exc).__name__}: {exc})") from exc
