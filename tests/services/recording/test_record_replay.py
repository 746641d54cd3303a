"""`robonav record` and `robonav replay` over real Zenoh sessions on loopback.

A router session listens on a free port; the test's publisher, the recorder and the replayer
are client sessions. The recorder and replayer run in process (their classes), except where
the command's own behaviour is the point (Ctrl-C, exit codes).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud as FoxglovePointCloud
from mcap.reader import make_reader

from robonav.pipeline.camera import CameraIntrinsics
from robonav.pipeline.wire.messages import JointState, PointCloud
from robonav.services.recording import replay
from robonav.services.recording.files import Recording, RecordingError, RecordingWriter
from robonav.services.recording.record import Recorder
from robonav.services.recording.replay import Replayer, ReplayOptions

from ..conftest import wait_for, write_config

CELL = "rt"
CLOUD_KEY = f"robonav/{CELL}/camera/cam0/cloud"
JOINT_KEY = f"robonav/{CELL}/robot/joint_states"
OTHER_KEY = f"robonav/{CELL}/custom/blob"


def traffic(seed: int = 0) -> list[tuple[str, bytes]]:
    """Clouds (one empty, some with NaN rows), joint states and a payload that is not msgpack."""
    rng = np.random.default_rng(seed)
    intrinsics = CameraIntrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
    out: list[tuple[str, bytes]] = []
    for i in range(12):
        points = rng.normal(0.0, 1.0, (int(rng.integers(0, 3000)) if i else 0, 3)).astype(np.float32)
        if points.shape[0]:
            points[rng.integers(0, points.shape[0], 5)] = np.nan
        out.append((CLOUD_KEY, PointCloud(stamp=1000.0 + i / 30, camera_id="cam0", points=points, seq=i + 1,
                                          intrinsics=intrinsics).to_wire()))
        for j in range(3):
            out.append((JOINT_KEY, JointState(stamp=1000.0 + i / 30 + j / 100, names=("a", "b"),
                                              position=rng.normal(size=2), velocity=rng.normal(size=2)).to_wire()))
        if i % 4 == 0:
            out.append((OTHER_KEY, bytes(rng.integers(0, 256, int(rng.integers(0, 64)), dtype=np.uint8))))
    return out


def publish(session: zenoh.Session, messages: list[tuple[str, bytes]]) -> None:
    publishers = {k: session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
                  for k in dict.fromkeys(k for k, _ in messages)}
    assert wait_for(lambda: all(p.matching_status.matching for p in publishers.values())), "no subscriber matched"
    for key, payload in messages:
        publishers[key].put(payload)
    for p in publishers.values():
        p.undeclare()


def record(sessions: Callable[[], zenoh.Session], path: Path, messages: list[tuple[str, bytes]]) -> dict:
    recorder = Recorder(sessions(), path, [f"robonav/{CELL}/**"])
    publish(sessions(), messages)
    assert wait_for(lambda: sum(recorder.stats.received.values()) == len(messages)), recorder.summary()
    return recorder.close()


def collect_replay(sessions: Callable[[], zenoh.Session], path: Path, options: ReplayOptions,
                   expected: int) -> list[tuple[str, bytes]]:
    received: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            received.append((str(sample.key_expr), sample.payload.to_bytes()))

    sub = sessions().declare_subscriber(f"robonav/{CELL}/**", on_sample)
    replayer = Replayer(sessions(), Recording(path), options)
    assert replayer.wait_for_subscribers(10.0)
    result = replayer.run(threading.Event())
    assert sum(result.published.values()) == expected
    assert wait_for(lambda: len(received) >= expected)
    replayer.close()
    sub.undeclare()
    return received


def by_key(messages: list[tuple[str, bytes]]) -> dict[str, list[bytes]]:
    out: dict[str, list[bytes]] = defaultdict(list)
    for key, payload in messages:
        out[key].append(payload)
    return dict(out)


def test_record_then_replay_is_byte_exact(sessions: Callable[[], zenoh.Session], tmp_path: Path) -> None:
    sent = traffic()
    path = tmp_path / "run.mcap"
    summary = record(sessions, path, sent)
    assert summary["received"] == summary["written"] == len(sent) and summary["dropped"] == 0
    assert summary["missed_upstream"] == 0

    recording = Recording(path)
    recorded = [(m.key, m.payload) for m in recording.messages()]
    assert by_key(recorded) == by_key(sent)
    assert recording.info.message_counts == {k: len(v) for k, v in by_key(sent).items()}

    replayed = collect_replay(sessions, path, ReplayOptions(rate=None, robot_keys=True), len(sent))
    assert by_key(replayed) == by_key(sent)


def test_file_layout_opens_in_foxglove(sessions: Callable[[], zenoh.Session], tmp_path: Path) -> None:
    sent = traffic(1)
    path = tmp_path / "run.mcap"
    record(sessions, path, sent)
    clouds = [PointCloud.from_wire(p) for k, p in sent if k == CLOUD_KEY]
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        topics = {c.topic: (c.message_encoding, summary.schemas[c.schema_id]) for c in summary.channels.values()}
        # Joint states get a JSON copy; their link transforms need a robot description, not sent here.
        assert set(topics) == {CLOUD_KEY, JOINT_KEY, OTHER_KEY, CLOUD_KEY + "/foxglove", JOINT_KEY + "/json"}
        for key in (CLOUD_KEY, JOINT_KEY, OTHER_KEY):
            encoding, schema = topics[key]
            assert encoding == "msgpack" and schema.encoding == "jsonschema"
            json.loads(schema.data)
        cloud_schema = json.loads(topics[CLOUD_KEY][1].data)
        assert cloud_schema["title"] == "robonav.PointCloud"
        assert {"stamp", "camera_id", "points"} <= set(cloud_schema["required"])
        assert topics[CLOUD_KEY + "/foxglove"][1].name == "foxglove.PointCloud"

        foxglove = []
        for _schema, channel, message in reader.iter_messages():
            # Receive time comes after the publisher's time (one clock on loopback).
            assert message.log_time >= message.publish_time - 1_000_000
            if channel.topic == CLOUD_KEY + "/foxglove":
                foxglove.append(FoxglovePointCloud.FromString(message.data))
    assert len(foxglove) == len(clouds)
    for fox, cloud in zip(foxglove, clouds):
        assert fox.frame_id == "cam0" and fox.point_stride == 12 and [f.name for f in fox.fields] == ["x", "y", "z"]
        np.testing.assert_array_equal(np.frombuffer(fox.data, "<f4").reshape(-1, 3), cloud.points)
        assert abs(fox.timestamp.seconds + fox.timestamp.nanos * 1e-9 - cloud.stamp) < 1e-6


def test_replay_filters_keys_and_time(sessions: Callable[[], zenoh.Session], tmp_path: Path) -> None:
    sent = traffic(2)
    path = tmp_path / "run.mcap"
    record(sessions, path, sent)
    joint_states = [p for k, p in sent if k == JOINT_KEY]
    replayed = collect_replay(sessions, path, ReplayOptions(rate=None, keys=("**/joint_states",), robot_keys=True), len(joint_states))
    assert by_key(replayed) == {JOINT_KEY: joint_states}

    recording = Recording(path)
    all_messages = list(recording.messages())
    middle = all_messages[len(all_messages) // 2].receive_time_ns
    later = list(recording.messages(start_ns=middle))
    assert 0 < len(later) < len(all_messages)
    assert all(m.receive_time_ns >= middle for m in later)
    assert [m.payload for m in later] == [m.payload for m in all_messages if m.receive_time_ns >= middle]


def test_damaged_files_fail_naming_the_offset(sessions: Callable[[], zenoh.Session], tmp_path: Path,
                                              caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "run.mcap"
    record(sessions, path, traffic(3))
    data = path.read_bytes()

    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(RecordingError, match="truncated") as info:
        Recording(truncated)
    assert 0 < info.value.offset < len(data) * 2 // 3
    assert f"byte offset {info.value.offset}" in str(info.value)

    # Flip one byte inside the first chunk's compressed data: its CRC (or zstd) catches it.
    first_chunk = _chunk_offsets(path)[0]
    corrupt = tmp_path / "corrupt.mcap"
    flipped = bytearray(data)
    flipped[first_chunk + 200] ^= 0xFF
    corrupt.write_bytes(bytes(flipped))
    with pytest.raises(RecordingError, match=f"byte offset {first_chunk}: the chunk starting here"):
        list(Recording(corrupt).messages())

    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not a recording at all")
    with pytest.raises(RecordingError, match="byte offset 0: not an MCAP file"):
        Recording(garbage)

    # The command says the same and exits with 2, publishing nothing; a truncated file is read
    # up to its last complete record (exit 1: readable, but not all there).
    caplog.clear()
    assert replay.main([str(corrupt), "--check"]) == 2
    assert "byte offset" in caplog.text
    caplog.clear()
    assert replay.main([str(truncated), "--check"]) == 1
    assert f"up to byte {info.value.offset}" in caplog.text


def _chunk_offsets(path: Path) -> list[int]:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return sorted(c.chunk_start_offset for c in summary.chunk_indexes)


def test_dropped_samples_are_counted_not_lost_silently(sessions: Callable[[], zenoh.Session], tmp_path: Path) -> None:
    """A stalled writer process fills the buffer: every sample that did not fit is counted per key."""
    sent = traffic(4)
    recorder = Recorder(sessions(), tmp_path / "run.mcap", [f"robonav/{CELL}/**"], max_buffer_bytes=1)
    os.kill(recorder.writer.pid, signal.SIGSTOP)  # a disk that stopped answering
    try:
        publish(sessions(), sent)
        assert wait_for(lambda: sum(recorder.stats.received.values()) == len(sent))
    finally:
        os.kill(recorder.writer.pid, signal.SIGCONT)
    summary = recorder.close()
    assert summary["received"] == len(sent) and summary["dropped"] > 0
    assert summary["written"] + summary["dropped"] == len(sent)
    assert sum(k["dropped"] + k["written"] for k in summary["keys"].values()) == len(sent)
    stats = json.loads(Recording(tmp_path / "run.mcap").info.metadata["robonav.record_stats"]["json"])
    assert stats["dropped"] == summary["dropped"]
    assert len(list(Recording(tmp_path / "run.mcap").messages())) == summary["written"]


def test_cloud_seq_gaps_count_as_missed_upstream(tmp_path: Path) -> None:
    writer = RecordingWriter(tmp_path / "gaps.mcap")
    for seq in (1, 2, 5, 6, 9):
        cloud = PointCloud(stamp=float(seq), camera_id="cam0", points=np.zeros((2, 3), np.float32), seq=seq)
        writer.write(CLOUD_KEY, cloud.to_wire(), receive_time_ns=seq, source_time_ns=seq)
    writer.write(CLOUD_KEY, msgpack.packb({"v": 1, "not": "a cloud"}), receive_time_ns=10, source_time_ns=10)
    writer.finish()
    stats = writer.stats[CLOUD_KEY]
    assert stats.seq_gaps == 4 and stats.written == 6 and stats.foxglove_written == 5 and stats.foxglove_skipped == 1
    assert [m.receive_time_ns for m in Recording(tmp_path / "gaps.mcap").messages()] == [1, 2, 5, 6, 9, 10]


def test_ctrl_c_leaves_a_valid_file(endpoint: str, sessions: Callable[[], zenoh.Session], tmp_path: Path) -> None:
    config = write_config(tmp_path, "rec.yaml", zenoh={"mode": "client", "connect": [endpoint]})
    path = tmp_path / "run.mcap"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "robonav.services.cli", "record", "-o", str(path), "--config",
                             str(config), "--log-level", "WARNING", f"robonav/{CELL}/**"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        sent = traffic(5)
        publish(sessions(), sent)
        time.sleep(0.5)  # the samples are in flight to another process: give them a moment to land
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err.decode()
    summary = json.loads(out)
    assert summary["written"] == len(sent) and summary["dropped"] == 0
    assert by_key([(m.key, m.payload) for m in Recording(path).messages()]) == by_key(sent)


def test_replay_loops_until_stopped(sessions: Callable[[], zenoh.Session], tmp_path: Path) -> None:
    sent = [(k, p) for k, p in traffic(6) if k == JOINT_KEY][:10]
    path = tmp_path / "run.mcap"
    record(sessions, path, sent)
    received: list[bytes] = []
    stop = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        received.append(sample.payload.to_bytes())
        if len(received) >= 2 * len(sent) + 3:
            stop.set()

    sub = sessions().declare_subscriber(JOINT_KEY, on_sample)
    replayer = Replayer(sessions(), Recording(path), ReplayOptions(rate=None, loop=True, robot_keys=True))
    assert replayer.wait_for_subscribers(10.0)
    result = replayer.run(stop)
    replayer.close()
    sub.undeclare()
    assert result.loops >= 3
    payloads = [p for _, p in sent]
    assert received[: 2 * len(sent) + 3] == (payloads * 3)[: 2 * len(sent) + 3]
