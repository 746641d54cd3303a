"""Replay and record cannot hurt a live cell, and a killed recorder still leaves a readable file.

Real Zenoh sessions on loopback (a router session, client sessions), the replayer in process,
`robonav record` and `robonav replay --check` as commands where their own behaviour is the
point: an existing file kept, a SIGKILL, exit codes.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh

from robonav.pipeline.wire.messages import ExecutorStatus, JointState, Occupancy
from robonav.services.recording.files import Recording, RecordingError
from robonav.services.recording.record import Recorder
from robonav.services.recording.replay import Replayer, ReplayOptions, in_cell, is_robot_key
from robonav.services.recording.writer import FLUSH_INTERVAL_S

from ..conftest import free_port, wait_for, write_config

CELL = "rs"
BLOB_KEY = f"robonav/{CELL}/custom/blob"


def cell_traffic() -> list[tuple[str, bytes]]:
    """What a cell publishes: robot state and commands, a map with an old stamp, and a blob."""
    root = f"robonav/{CELL}"
    q = np.zeros(7)
    status = ExecutorStatus(stamp=50.0, state="executing", trajectory_id="t", progress=0.5, time_from_start_s=1.0,
                            duration_s=2.0, last_result="none", error_code="", error_message="", replans=0,
                            blocked_after_frame_s=None, blocked_stamp=None)
    occupancy = Occupancy(stamp=1000.25, resolution_m=0.02, octomap_binary=b"", occupied_centers_m=np.zeros((3, 3), "<f4"),
                          seq=7, frame_id="world")
    return [(f"{root}/robot/joint_states", JointState(stamp=50.0, names=tuple(f"j{i}" for i in range(7)), position=q,
                                                      velocity=q).to_wire()),
            (f"{root}/executor/setpoint", msgpack.packb({"v": 1, "what": "a setpoint"})),
            (f"{root}/executor/status", status.to_wire()),
            (f"{root}/perception/occupancy", occupancy.to_wire()),
            (BLOB_KEY, b"\x00\x01 a blob")]


def record_traffic(sessions: Callable[[], zenoh.Session], path: Path, sent: list[tuple[str, bytes]]) -> None:
    recorder = Recorder(sessions(), path, [f"robonav/{CELL}/**"])
    session = sessions()
    publishers = {k: session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK) for k, _ in sent}
    assert wait_for(lambda: all(p.matching_status.matching for p in publishers.values()))
    for key, payload in sent:
        publishers[key].put(payload)
    assert wait_for(lambda: sum(recorder.stats.received.values()) == len(sent))
    recorder.close()


def replay_into(sessions: Callable[[], zenoh.Session], path: Path, options: ReplayOptions, watch: str,
                expected: int) -> tuple[Replayer, list[tuple[str, bytes]]]:
    received: list[tuple[str, bytes]] = []
    sub = sessions().declare_subscriber(watch, lambda s: received.append((str(s.key_expr), s.payload.to_bytes())))
    replayer = Replayer(sessions(), Recording(path, recover=True), options)
    assert replayer.wait_for_subscribers(10.0)
    replayer.run(threading.Event())
    wait_for(lambda: len(received) >= expected, 5.0)
    time.sleep(0.3)  # anything that should not arrive has had its chance
    replayer.close()
    sub.undeclare()
    return replayer, received


def test_robot_keys_are_those_that_move_or_report_the_arm() -> None:
    assert is_robot_key("robonav/arm0/robot/joint_states") and is_robot_key("robonav/arm0/executor/setpoint")
    assert is_robot_key("robonav/x/executor/status") and is_robot_key("robonav/x/executor/path")
    assert not is_robot_key("robonav/arm0/camera/cam0/cloud") and not is_robot_key("robonav/arm0/perception/occupancy")
    assert in_cell("robonav/arm0/camera/cam0/cloud", "bench") == "robonav/bench/camera/cam0/cloud"
    assert in_cell("robonav/arm0/camera/cam0/cloud", None) == "robonav/arm0/camera/cam0/cloud"
    assert in_cell("other/arm0/x", "bench") == "other/arm0/x"
    with pytest.raises(ValueError, match="cell"):
        ReplayOptions(cell="a/b")


def test_replay_publishes_robot_state_and_commands_only_when_asked(sessions: Callable[[], zenoh.Session],
                                                                   tmp_path: Path) -> None:
    sent = cell_traffic()
    path = tmp_path / "cell.mcap"
    record_traffic(sessions, path, sent)
    robot = {k for k, _ in sent if is_robot_key(k)}
    assert len(robot) == 3

    replayer, received = replay_into(sessions, path, ReplayOptions(rate=None), f"robonav/{CELL}/**", len(sent) - 3)
    assert sorted(k for k, _ in received) == sorted(k for k, _ in sent if k not in robot)
    assert replayer.skipped == dict.fromkeys(robot, 1)

    replayer, received = replay_into(sessions, path, ReplayOptions(rate=None, robot_keys=True), f"robonav/{CELL}/**",
                                     len(sent))
    assert sorted(received) == sorted(sent) and replayer.skipped == {}


def test_replay_into_another_cell_keeps_payloads_and_stamps(sessions: Callable[[], zenoh.Session], tmp_path: Path) -> None:
    sent = cell_traffic()
    path = tmp_path / "cell.mcap"
    record_traffic(sessions, path, sent)
    live: list[str] = []
    live_sub = sessions().declare_subscriber(f"robonav/{CELL}/**", lambda s: live.append(str(s.key_expr)))
    _, received = replay_into(sessions, path, ReplayOptions(rate=None, robot_keys=True, cell="offline"),
                              "robonav/offline/**", len(sent))
    live_sub.undeclare()
    assert live == []  # nothing reached the recorded (live) cell
    assert sorted(received) == sorted((in_cell(k, "offline"), p) for k, p in sent)
    # A replayed map is the recorded one byte for byte: its stamp is the recorded stamp, not now.
    maps = [Occupancy.from_wire(p) for k, p in received if k.endswith("perception/occupancy")]
    assert [m.stamp for m in maps] == [1000.25]


def test_record_keeps_an_existing_file_unless_forced(endpoint: str, tmp_path: Path) -> None:
    config = write_config(tmp_path, "rec.yaml", zenoh={"mode": "client", "connect": [endpoint]})
    path = tmp_path / "run.mcap"
    path.write_bytes(b"an earlier recording")
    command = [sys.executable, "-m", "robonav.services.cli", "record", "-o", str(path), "--config", str(config),
               "--duration", "0.5", "--log-level", "WARNING", f"robonav/{CELL}/**"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "--force" in done.stderr
    assert path.read_bytes() == b"an earlier recording"
    done = subprocess.run([*command, "--force"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert Recording(path).complete


def test_record_without_a_router_fails_clearly_and_leaves_no_file(tmp_path: Path) -> None:
    config = write_config(tmp_path, "rec.yaml", zenoh={"mode": "client", "connect": [f"tcp/127.0.0.1:{free_port()}"]})
    path = tmp_path / "run.mcap"
    done = subprocess.run([sys.executable, "-m", "robonav.services.cli", "record", "-o", str(path), "--config",
                           str(config), "--duration", "0.5"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "cannot reach the router" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr and not path.exists()


def _writer_of(recorder_pid: int) -> int:
    """The writer process `robonav record` started (its child)."""
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
                cmdline = (entry / "cmdline").read_bytes()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == recorder_pid and b"recording.writer" in cmdline:
                return int(entry.name)
    raise AssertionError(f"no writer process under {recorder_pid}")


class Counting:
    """Publishes numbered blobs (`seq` from 1) at a steady rate from a thread until stopped."""

    def __init__(self, session: zenoh.Session, rate_hz: float, size: int = 4096) -> None:
        self.publisher = session.declare_publisher(BLOB_KEY, congestion_control=zenoh.CongestionControl.BLOCK)
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(1.0 / rate_hz, size), daemon=True)

    def start(self) -> None:
        assert wait_for(lambda: self.publisher.matching_status.matching, 20.0), "the recorder never subscribed"
        self._thread.start()

    def _run(self, period_s: float, size: int) -> None:
        while not self._stop.wait(period_s):
            self.sent += 1
            self.publisher.put(msgpack.packb({"seq": self.sent, "pad": bytes(size)}))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        self.publisher.undeclare()


def start_recorder(endpoint: str, tmp_path: Path, path: Path) -> subprocess.Popen[bytes]:
    config = write_config(tmp_path, "rec.yaml", zenoh={"mode": "client", "connect": [endpoint]})
    return subprocess.Popen([sys.executable, "-m", "robonav.services.cli", "record", "-o", str(path), "--config",
                             str(config), "--log-level", "WARNING", BLOB_KEY],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def check(path: Path) -> tuple[int, dict]:
    done = subprocess.run([sys.executable, "-m", "robonav.services.cli", "replay", str(path), "--check", "--log-level",
                           "WARNING"], capture_output=True, text=True, timeout=120)
    return done.returncode, json.loads(done.stdout) if done.stdout else {}


def seqs_in(recording: Recording) -> list[int]:
    return [msgpack.unpackb(m.payload)["seq"] for m in recording.messages()]


def test_a_killed_recorder_leaves_a_finished_file_with_its_losses_counted(
        endpoint: str, sessions: Callable[[], zenoh.Session], tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    recorder = start_recorder(endpoint, tmp_path, path)
    publisher = Counting(sessions(), rate_hz=200.0)
    try:
        publisher.start()
        time.sleep(1.0)
        writer = _writer_of(recorder.pid)
        os.kill(writer, signal.SIGSTOP)  # a slow disk: samples pile up in the recorder's queue
        time.sleep(1.5)
        recorder.kill()  # SIGKILL: the queue dies with it
        recorder.wait(timeout=10)
        os.kill(writer, signal.SIGCONT)
        assert wait_for(lambda: not Path(f"/proc/{writer}").exists() or
                        Path(f"/proc/{writer}/stat").read_text().split()[2] == "Z", 30.0), "the writer did not finish"
    finally:
        publisher.stop()
        if recorder.poll() is None:
            recorder.kill()
    code, summary = check(path)
    assert code == 0 and summary["complete"], summary
    recorder_stats = summary["recorder"]
    assert recorder_stats["recorder_finished"] is False and recorder_stats["dropped"] == 0
    # The loss is counted exactly: of the samples the recorder's last checkpoint had received
    # (numbered 1..R in publication order on loopback), those missing from the file.
    stats = Recording(path).stats()
    assert stats is not None
    received_by_checkpoint = stats["keys"][BLOB_KEY]["received"]
    recorded = seqs_in(Recording(path))
    missing = received_by_checkpoint - sum(1 for s in recorded if s <= received_by_checkpoint)
    assert recorded == sorted(recorded) and len(set(recorded)) == len(recorded)
    assert recorder_stats["lost_at_recorder_exit"] == missing > 0, (recorder_stats, received_by_checkpoint, len(recorded))
    print(json.dumps({"published": publisher.sent, "written": len(recorded), "lost_counted": missing,
                      "received_by_last_checkpoint": received_by_checkpoint}))


def test_a_killed_writer_leaves_a_file_replay_check_reads(endpoint: str, sessions: Callable[[], zenoh.Session],
                                                          tmp_path: Path) -> None:
    path = tmp_path / "torn.mcap"
    recorder = start_recorder(endpoint, tmp_path, path)
    publisher = Counting(sessions(), rate_hz=100.0, size=256)
    try:
        publisher.start()
        time.sleep(2.0 + 2 * FLUSH_INTERVAL_S)
        sent_before = publisher.sent
        writer = _writer_of(recorder.pid)
        os.kill(writer, signal.SIGKILL)  # both processes die, as in a crash of the machine's container
        recorder.kill()
        recorder.wait(timeout=10)
    finally:
        publisher.stop()
        if recorder.poll() is None:
            recorder.kill()
    with pytest.raises(RecordingError, match="truncated"):
        Recording(path)
    recovered = Recording(path, recover=True)
    assert not recovered.complete and recovered.truncated_at is not None and recovered.truncated_at <= recovered.size
    seqs = seqs_in(recovered)
    # Every chunk older than the flush interval is on disk: at least what was published well before.
    assert seqs == list(range(1, len(seqs) + 1)) and len(seqs) >= sent_before // 2, (len(seqs), sent_before)
    assert recovered.stats() is not None  # the last checkpoint's counts
    code, summary = check(path)
    assert code == 1 and summary["complete"] is False and summary["messages"] == len(seqs), summary
    # And it replays: the recovered messages go out.
    replayer, received = replay_into(sessions, path, ReplayOptions(rate=None), BLOB_KEY, len(seqs))
    assert [msgpack.unpackb(p)["seq"] for _, p in received] == seqs
