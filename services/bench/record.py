"""`robonav bench record`: does `robonav record` keep up, and does `robonav replay` keep time?

1. Renders `--frames` depth frames of the default sim scene at `--width`x`--height` (pybullet,
   the camera nudged a little per frame so no two clouds are alike) and turns them into clouds.
2. Starts `robonav record` as its own process, connected to a Zenoh router in this process.
3. Publishes those clouds at `--rate-hz` (seq 1, 2, ...) and joint states at 100 Hz for
   `--seconds`, like the sim (default congestion control), remembering each cloud's CRC.
4. Stops the recorder with SIGINT and reads the file: a cloud counts as recorded when a
   message with its seq and the same bytes is there. Lost = published - recorded.
5. Replays the first `--replay-seconds` with `robonav replay` (its own process) at 1x and
   reports its publish timing error (publish time - due time) and, from a subscriber here,
   the error of each cloud's inter-arrival time against the recorded one.

The recording is deleted at the end unless `--keep`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import yaml
import zenoh

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.perception.depth import points_from_depth
from robonav.pipeline.wire.messages import JointState, PointCloud
from robonav.services.common import open_session, setup_logging
from robonav.services.config import RobonavConfig, ZenohConfig, default_config_path, load_config
from robonav.services.recording.files import Recording

log = logging.getLogger("robonav.bench.record")

CELL = "bench"
JOINT_RATE_HZ = 100.0


def add_parser(kinds: Any) -> None:  # noqa: ANN401 - argparse's private subparsers type
    """Register `record` on `robonav bench`'s sub-commands."""
    parser = kinds.add_parser("record", help="record clouds at camera rate: messages lost; replay timing error",
                              description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="how long to publish [s]")
    parser.add_argument("--rate-hz", type=float, default=30.0, help="cloud rate [Hz]")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--frames", type=int, default=30, help="distinct rendered frames, published in turn")
    parser.add_argument("--replay-seconds", type=float, default=60.0, help="how much of the recording to replay at 1x")
    parser.add_argument("--out", type=Path, default=None, help="recording path (default: a temporary file)")
    parser.add_argument("--keep", action="store_true", help="keep the recording")
    parser.add_argument("--config", default=None, help="YAML config for the scene and camera (default: packaged)")
    parser.add_argument("--json", type=Path, default=None, help="write the summary as JSON to this file")


def render_clouds(cfg: RobonavConfig, camera: CameraConfig, frames: int) -> list[np.ndarray]:
    """(N_i, 3) float32 clouds of the sim scene from slightly different camera positions."""
    from robonav.pipeline.sim.world import SimWorld  # pybullet loads only for this benchmark

    world = SimWorld(cfg.robot, camera, cfg.sim)
    try:
        clouds = []
        for i in range(frames):
            nudge = 0.01 * np.array([np.sin(i), np.cos(1.3 * i), np.sin(0.7 * i)])
            posed = dataclasses.replace(camera, position_m=tuple(float(v) for v in np.add(camera.position_m, nudge)))
            frame = world.render_depth(posed)
            clouds.append(points_from_depth(frame.depth_m, frame.intrinsics, max_depth_m=camera.far_m))
        return clouds
    finally:
        world.close()


def _subprocess_config(directory: Path, endpoint: str) -> Path:
    data = yaml.safe_load(default_config_path().read_text(encoding="utf-8"))
    data["cell"] = CELL
    data["zenoh"] = {"mode": "client", "connect": [endpoint]}
    path = directory / "bench-record.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def _robonav(*args: str) -> list[str]:
    return [sys.executable, "-m", "robonav.services.cli", *args, "--log-level", "WARNING"]


def _publish(session: zenoh.Session, clouds: list[bytes], camera: CameraConfig, cfg: RobonavConfig,
             seconds: float, rate_hz: float) -> tuple[dict[int, int], int]:
    """Clouds at rate_hz and joint states at 100 Hz on an absolute schedule; (seq -> crc32, joint states)."""
    cloud_key = f"robonav/{CELL}/camera/{camera.camera_id}/cloud"
    cloud_pub = session.declare_publisher(cloud_key)
    joint_pub = session.declare_publisher(f"robonav/{CELL}/robot/joint_states")
    deadline = time.monotonic() + 30.0
    while not (cloud_pub.matching_status.matching and joint_pub.matching_status.matching):
        if time.monotonic() > deadline:
            raise RuntimeError("the recorder did not subscribe within 30 s")
        time.sleep(0.05)
    q = np.array(cfg.robot.home_position_rad)
    crcs: dict[int, int] = {}
    n_clouds, n_joints = int(seconds * rate_hz), int(seconds * JOINT_RATE_HZ)
    i_cloud = i_joint = 0
    t0 = time.perf_counter()
    next_report = 60.0
    while i_cloud < n_clouds or i_joint < n_joints:
        due_cloud = i_cloud / rate_hz if i_cloud < n_clouds else float("inf")
        due_joint = i_joint / JOINT_RATE_HZ if i_joint < n_joints else float("inf")
        due = min(due_cloud, due_joint)
        delay = t0 + due - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        if due_cloud <= due_joint:
            seq = i_cloud + 1
            payload = PointCloud(stamp=time.time(), camera_id=camera.camera_id, points=clouds[i_cloud % len(clouds)],
                                 seq=seq, intrinsics=camera.intrinsics).to_wire()
            crcs[seq] = zlib.crc32(payload)
            cloud_pub.put(payload)
            i_cloud += 1
        else:
            joint_pub.put(JointState(stamp=time.time(), names=cfg.robot.joint_names, position=q,
                                     velocity=np.zeros(q.size)).to_wire())
            i_joint += 1
        if due >= next_report:
            log.info("published %d clouds, %d joint states (%.0f s)", i_cloud, i_joint, due)
            next_report += 60.0
    cloud_pub.undeclare()
    joint_pub.undeclare()
    return crcs, i_joint


def _verify(path: Path, crcs: dict[int, int], cloud_key: str) -> tuple[int, int, list[tuple[int, int]]]:
    """(clouds recorded intact, joint states recorded, [(seq, receive ns)] in file order)."""
    intact: set[int] = set()
    joints = 0
    arrivals = []
    for message in Recording(path).messages():
        if message.key != cloud_key:
            joints += 1
            continue
        seq = PointCloud.from_wire(message.payload).seq
        if crcs.get(seq) == zlib.crc32(message.payload):
            intact.add(seq)
        arrivals.append((seq, message.receive_time_ns))
    return len(intact), joints, arrivals


def _percentiles(values_ms: np.ndarray) -> dict[str, float] | None:
    if values_ms.size == 0:
        return None
    return {"p50_ms": round(float(np.percentile(values_ms, 50)), 3), "p99_ms": round(float(np.percentile(values_ms, 99)), 3),
            "max_ms": round(float(values_ms.max()), 3), "samples": int(values_ms.size)}


def main(args: argparse.Namespace) -> int:
    setup_logging("INFO")
    cfg = load_config(args.config)
    camera = dataclasses.replace(cfg.cameras[0], width=args.width, height=args.height)
    log.info("rendering %d frames at %dx%d", args.frames, args.width, args.height)
    clouds = render_clouds(cfg, camera, args.frames)
    cloud_key = f"robonav/{CELL}/camera/{camera.camera_id}/cloud"
    mean_points = float(np.mean([c.shape[0] for c in clouds]))

    with tempfile.TemporaryDirectory(prefix="robonav-bench-record-") as tmp:
        tmp_dir = Path(tmp)
        out = args.out or tmp_dir / "bench.mcap"
        endpoint = f"tcp/127.0.0.1:{_free_port()}"
        router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
        config = _subprocess_config(tmp_dir, endpoint)
        stats_path = tmp_dir / "record.json"
        recorder = subprocess.Popen(_robonav("record", "-o", str(out), "--config", str(config), "--json",
                                             str(stats_path), f"robonav/{CELL}/**"), stdout=subprocess.DEVNULL)
        try:
            log.info("publishing %.0f s of %.0f Hz clouds (%.0f points, %.2f MB each) and 100 Hz joint states",
                     args.seconds, args.rate_hz, mean_points, mean_points * 12 / 2**20)
            crcs, joints_sent = _publish(router, clouds, camera, cfg, args.seconds, args.rate_hz)
            time.sleep(1.0)  # the last samples are in flight to the recorder process
        finally:
            recorder.send_signal(signal.SIGINT)
            record_code = recorder.wait(timeout=600)
        record_stats = json.loads(stats_path.read_text(encoding="utf-8"))
        intact, joints_recorded, arrivals = _verify(out, crcs, cloud_key)
        summary: dict[str, Any] = {
            "clouds_published": len(crcs), "clouds_recorded_intact": intact, "clouds_lost": len(crcs) - intact,
            "joint_states_published": joints_sent, "joint_states_recorded": joints_recorded,
            "record_exit_code": record_code, "recorder_dropped": record_stats["dropped"],
            "recorder_max_buffered_mb": record_stats["max_buffered_mb"], "file_mb": record_stats["file_mb"],
            "raw_mb": round(sum(k["bytes"] for k in record_stats["keys"].values()) / 2**20, 1),
            "seconds": args.seconds, "rate_hz": args.rate_hz, "width": args.width, "height": args.height,
            "points_per_cloud": round(mean_points),
            "load_average_after_recording": [round(v, 2) for v in os.getloadavg()],
        }
        summary["replay"] = _replay_timing(router, out, config, tmp_dir, cloud_key, arrivals, args.replay_seconds)
        router.close()
        if args.keep and args.out is None:
            kept = Path.cwd() / "bench-record.mcap"
            os.replace(out, kept)
            summary["recording"] = str(kept)
        elif not args.keep:
            Path(out).unlink(missing_ok=True)
    text = json.dumps(summary, indent=2)
    print(text, flush=True)
    if args.json:
        args.json.write_text(text + "\n", encoding="utf-8")
    return 0 if summary["clouds_lost"] == 0 and record_code == 0 else 1


def _replay_timing(session: zenoh.Session, path: Path, config: Path, tmp_dir: Path, cloud_key: str,
                   recorded: list[tuple[int, int]], seconds: float) -> dict[str, Any]:
    arrivals: list[tuple[int, int]] = []
    lock = threading.Lock()

    def on_cloud(sample: zenoh.Sample) -> None:
        now = time.perf_counter_ns()
        seq = PointCloud.from_wire(sample.payload.to_bytes()).seq
        with lock:
            arrivals.append((seq, now))

    sub = session.declare_subscriber(cloud_key, on_cloud)
    stats_path = tmp_dir / "replay.json"
    # The joint states too (--robot-keys): the benchmark's own cell, and the replay's full load.
    code = subprocess.run(_robonav("replay", str(path), "--config", str(config), "--end", str(seconds), "--json",
                                   str(stats_path), "--wait-subscribers", "30", "--robot-keys"),
                          stdout=subprocess.DEVNULL).returncode
    time.sleep(0.5)
    sub.undeclare()
    replay_stats = json.loads(stats_path.read_text(encoding="utf-8")) if stats_path.exists() else {}
    recorded_ns = dict(recorded)
    with lock:
        got = [(seq, t) for seq, t in arrivals if seq in recorded_ns]
    # Inter-arrival time here vs the recorded one, for consecutive clouds.
    errors = [abs((t1 - t0) - (recorded_ns[s1] - recorded_ns[s0])) / 1e6
              for (s0, t0), (s1, t1) in zip(got, got[1:])]
    return {"exit_code": code, "seconds": seconds, "load_average_after": [round(v, 2) for v in os.getloadavg()],
            "published": replay_stats.get("published"),
            "clouds_received": len(got), "publish_timing_error": replay_stats.get("timing_error"),
            "cloud_interarrival_error": _percentiles(np.asarray(errors))}


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
