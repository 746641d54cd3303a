"""`robonav bench perception`: per-stage cost of the perception core, and frame → published map
latency and sustained rate of the live perception service over Zenoh.

Frames are rendered once in pybullet (the configured scene and first camera, the arm at
seeded random poses), then replayed: in-process through the core (stage timings, both
clearing methods and both clustering methods), and published at `--rate` to a perception
service process (latency from the frame stamp to the arrival of the map carrying that stamp).

Accuracy (`--accuracy-frames N`, default 10): for the arm at home and reaching over the table, a
fresh map takes N renders with the sim's depth-noise model on (seeded), and is compared with
pybullet's ground truth (`pipeline/perception/accuracy.py`): coverage of the obstacles'
visible surface voxels, spurious voxels, voxels on the robot.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from robonav.pipeline.evaluation.map_accuracy import map_accuracy
from robonav.pipeline.perception.clusters import cluster_voxels
from robonav.pipeline.perception.depth import points_from_depth
from robonav.pipeline.perception.maps.factory import make_occupancy_map
from robonav.pipeline.perception.maps.protocol import CameraFrame
from robonav.pipeline.perception.self_filter import perception_filters
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.sim.noise import apply_depth_noise
from robonav.pipeline.sim.world import SimWorld
from robonav.pipeline.wire.messages import JointState, Occupancy, PointCloud
from robonav.services.common import open_session
from robonav.services.config import RobonavConfig, ZenohConfig, default_config_path, load_config
from robonav.services.keys import Keys


def add_parser(kinds: Any) -> None:
    bench = kinds.add_parser("perception", help="perception stage costs, frame→map latency and sustained rate")
    bench.add_argument("--config", type=Path, default=None, help="robonav YAML config (default: packaged)")
    bench.add_argument("--frames", type=int, default=300, help="frames fed through the core and the service")
    bench.add_argument("--distinct", type=int, default=10, help="distinct rendered frames (cycled)")
    bench.add_argument("--rate", type=float, default=30.0, help="publish rate of the live run [Hz]")
    bench.add_argument("--seed", type=int, default=0)
    bench.add_argument("--no-live", action="store_true", help="skip the live service run")
    bench.add_argument("--accuracy-frames", type=int, default=10,
                       help="noisy frames per arm pose for the ground-truth comparison (0: skip it)")
    bench.add_argument("--json", type=Path, default=None, help="write the summary as JSON to this file")


def _stats(values_ms: list[float]) -> dict[str, float]:
    a = np.asarray(values_ms, dtype=float)
    return {"p50": round(float(np.percentile(a, 50)), 3), "p95": round(float(np.percentile(a, 95)), 3),
            "max": round(float(a.max()), 3)}


def render_frames(cfg: RobonavConfig, distinct: int, seed: int) -> list[tuple[np.ndarray, np.ndarray, Any]]:
    """(points_camera float32, q, intrinsics) of `distinct` renders, the arm at random poses near home."""
    rng = np.random.default_rng(seed)
    camera = cfg.cameras[0]
    home = np.array(cfg.robot.home_position_rad)
    frames = []
    sim = dataclasses.replace(cfg.sim, follow="kinematic", gravity=False)
    with SimWorld(cfg.robot, camera, sim) as world:
        for _ in range(distinct):
            q = home + rng.uniform(-0.4, 0.4, home.size)
            world.set_joint_target(q)
            world.step()
            frame = world.render_depth()
            points = points_from_depth(frame.depth_m, frame.intrinsics, max_depth_m=camera.far_m).astype(np.float32)
            frames.append((points, world.joint_state()[0], frame.intrinsics))
    return frames


def accuracy_run(cfg: RobonavConfig, frames_per_pose: int, seed: int) -> dict[str, Any]:
    """Map accuracy against pybullet's ground truth with the depth-noise model on (see the module docstring)."""
    rng = np.random.default_rng((seed, 7))
    camera = cfg.cameras[0]
    robot = RobotModel.from_config(cfg.robot)
    self_filter, clear_filter = perception_filters(robot.link_hull_vertices, robot.static_link_names, cfg.perception,
                                                   cfg.robot.padding_m)
    noise = dataclasses.replace(cfg.sim.noise, enabled=True)
    home = np.array(cfg.robot.home_position_rad)
    # Home, and the hand out over the table on either side of the pillar, between the camera
    # and the objects: the self filter must take the arm out and what it hides stays unknown.
    poses = [home] + [np.array([yaw, 0.3, 0.0, -1.5, 0.0, 1.9, 0.785]) for yaw in (0.5, -0.5)]
    objects = list(cfg.sim.objects)
    results = []
    with SimWorld(cfg.robot, camera, dataclasses.replace(cfg.sim, follow="kinematic", gravity=False)) as world:
        obstacle_ids = [label for label, name in world.body_labels().items() if name != "robot"]
        for q in poses:
            world.set_joint_target(q)
            world.step()
            frame = world.render_depth()
            links = robot.link_poses(world.joint_state()[0])
            seen = np.isin(frame.segmentation, obstacle_ids) & np.isfinite(frame.depth_m)
            clean = np.where(seen, frame.depth_m, np.inf).astype(np.float32)
            pose = frame.world_from_camera
            visible = points_from_depth(clean, frame.intrinsics).astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
            grid = make_occupancy_map(dataclasses.replace(cfg.perception, clearing="projection"))
            for _ in range(frames_per_pose):
                depth, _ = apply_depth_noise(frame.depth_m, frame.segmentation, frame.intrinsics, noise, rng)
                grid.integrate(CameraFrame(frame.intrinsics, pose, links, depth_m=depth), self_filter=self_filter,
                               clear_filter=clear_filter)
            found = map_accuracy(grid.occupied_centers_m(), grid.resolution_m, visible_surface_m=visible,
                                 objects=objects, robot_hulls=robot.link_hull_vertices, world_from_link=links)
            results.append({"q_rad": np.round(q, 3).tolist(), **dataclasses.asdict(found)})
    return {"frames_per_pose": frames_per_pose, "poses": results,
            "surface_covered_min": min(r["surface_covered"] for r in results),
            "surface_covered_within_one_voxel_min": min(r["surface_covered_within_one_voxel"] for r in results),
            "spurious_fraction_max": max(r["spurious_fraction"] for r in results),
            "on_robot_total": sum(r["on_robot"] for r in results)}


def core_run(cfg: RobonavConfig, frames: list, count: int, clearing: str) -> dict[str, Any]:
    """Stage timings of the core for `count` frames with one clearing method."""
    pcfg = dataclasses.replace(cfg.perception, clearing=clearing)
    robot = RobotModel.from_config(cfg.robot)
    self_filter, clear_filter = perception_filters(robot.link_hull_vertices, robot.static_link_names, pcfg,
                                                   cfg.robot.padding_m)
    camera = cfg.cameras[0]
    pose = camera.world_from_camera
    stages: dict[str, list[float]] = {}
    totals: list[float] = []
    occupancy = make_occupancy_map(pcfg)
    for n in range(count):
        points, q, intrinsics = frames[n % len(frames)]
        t0 = time.perf_counter()
        frame = CameraFrame(intrinsics, pose, robot.link_poses(q), points_camera_m=points)
        lap = {k: v for k, v in occupancy.integrate(frame, self_filter=self_filter, clear_filter=clear_filter).items()
               if k != "total"}
        t1 = time.perf_counter()
        binary, centers = occupancy.planning_binary(), occupancy.occupied_centers_m()
        lap["publish_encode"] = (time.perf_counter() - t1) * 1e3
        Occupancy(stamp=0.0, resolution_m=pcfg.resolution_m, octomap_binary=binary,
                  occupied_centers_m=centers.astype(np.float32)).to_wire()
        totals.append((time.perf_counter() - t0) * 1e3)
        for key, value in lap.items():
            stages.setdefault(key, []).append(value)
    result: dict[str, Any] = {"frames": count, "total_ms": _stats(totals[1:] or totals),
                              "stages": {k: _stats(v[1:] or v) for k, v in stages.items()}}
    if clearing == "projection":  # the service's default map: how long clustering it takes
        voxels = occupancy.occupied_voxels()
        cluster_ms: dict[str, Any] = {}
        for method in ("components", "dbscan"):
            times = []
            for _ in range(5):
                t0 = time.perf_counter()
                found = cluster_voxels(voxels.ijk, voxels.centers_m, pcfg.resolution_m, method=method)
                times.append((time.perf_counter() - t0) * 1e3)
            cluster_ms[method] = {**_stats(times), "clusters": found.count}
        result["clustering_ms"] = cluster_ms
        result["occupied_voxels"] = int(voxels.centers_m.shape[0])
    return result


def live_run(cfg: RobonavConfig, frames: list, count: int, rate_hz: float, config_path: Path | None) -> dict[str, Any]:
    """Publish frames at `rate_hz` to a perception service process; latency and sustained rate."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    data = yaml.safe_load((config_path or default_config_path()).read_text(encoding="utf-8"))
    data["zenoh"] = {**data.get("zenoh", {}), "mode": "peer", "connect": [f"tcp/127.0.0.1:{port}"], "listen": []}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.yaml"
        path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
        session = open_session(ZenohConfig(mode="peer", connect=(), listen=(f"tcp/127.0.0.1:{port}",)))
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = subprocess.Popen([sys.executable, "-m", "robonav.services.cli", "serve", "perception", "--config",
                                 str(path), "--log-level", "WARNING"], env=env)
        keys = Keys(cfg.cell)
        arrivals: dict[float, float] = {}
        lock = threading.Lock()

        def on_map(sample: Any) -> None:
            now = time.time()
            occupancy = Occupancy.from_wire(sample.payload.to_bytes())
            with lock:
                arrivals.setdefault(occupancy.stamp, now)

        sub = session.declare_subscriber(keys.occupancy, on_map)
        joint_pub = session.declare_publisher(keys.joint_states)
        camera = cfg.cameras[0]
        cloud_pub = session.declare_publisher(keys.camera_cloud(camera.camera_id))
        names = cfg.robot.joint_names
        current_q = [frames[0][1]]
        stop = threading.Event()

        def publish_joint_states() -> None:  # 100 Hz, like a robot driver
            while not stop.wait(0.01):
                q = current_q[0]
                joint_pub.put(JointState(stamp=time.time(), names=names, position=q, velocity=np.zeros_like(q)).to_wire())

        joints = threading.Thread(target=publish_joint_states, daemon=True)
        joints.start()
        try:
            # Wait for the service: it answers once it publishes a map for a frame.
            deadline = time.monotonic() + 60.0
            points, q, intrinsics = frames[0]
            while not arrivals and time.monotonic() < deadline and proc.poll() is None:
                stamp = time.time()
                joint_pub.put(JointState(stamp=stamp, names=names, position=q, velocity=np.zeros_like(q)).to_wire())
                cloud_pub.put(PointCloud(stamp=stamp, camera_id=camera.camera_id, points=points,
                                         intrinsics=intrinsics).to_wire())
                time.sleep(0.2)
            if not arrivals:
                raise RuntimeError("the perception service published no map within 60 s")
            time.sleep(0.5)
            with lock:
                arrivals.clear()
            sent: list[float] = []
            period = 1.0 / rate_hz
            start = time.monotonic()
            for n in range(count):
                points, q, intrinsics = frames[n % len(frames)]
                current_q[0] = q
                due = start + n * period
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                stamp = time.time()
                joint_pub.put(JointState(stamp=stamp, names=names, position=q, velocity=np.zeros_like(q)).to_wire())
                cloud_pub.put(PointCloud(stamp=stamp, camera_id=camera.camera_id, points=points, seq=n + 1,
                                         intrinsics=intrinsics).to_wire())
                sent.append(stamp)
            duration_s = time.monotonic() - start
            time.sleep(1.0)
        finally:
            stop.set()
            joints.join()
            sub.undeclare()
            proc.terminate()
            proc.wait(timeout=30)
            session.close()
    with lock:
        latencies = [(arrivals[s] - s) * 1e3 for s in sent if s in arrivals]
    if not latencies:
        raise RuntimeError("no map carried the stamp of a benchmark frame")
    return {"frames_sent": len(sent), "maps_for_frames": len(latencies), "publish_rate_hz": rate_hz,
            "sustained_hz": round(len(latencies) / duration_s, 2), "latency_ms": _stats(latencies)}


def main(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    if args.frames < 2 or args.distinct < 1 or args.rate <= 0:
        print("robonav bench perception: --frames >= 2, --distinct >= 1 and --rate > 0 are required", file=sys.stderr)
        return 2
    frames = render_frames(cfg, args.distinct, args.seed)
    camera = cfg.cameras[0]
    report: dict[str, Any] = {"resolution": [camera.width, camera.height], "points_per_frame": int(frames[0][0].shape[0]),
                              "frames": args.frames}
    projection = core_run(cfg, frames, args.frames, "projection")
    raycast = core_run(cfg, frames, max(10, args.frames // 10), "raycast")
    report["core"] = {"projection": projection, "raycast": raycast}
    report["stages"] = projection["stages"]
    print(f"{camera.width}x{camera.height} frames, {report['points_per_frame']} points each")
    for name, run in (("projection", projection), ("raycast", raycast)):
        print(f"core, {name} clearing ({run['frames']} frames): total p50 {run['total_ms']['p50']:.2f} ms "
              f"p95 {run['total_ms']['p95']:.2f} ms")
        for stage, s in run["stages"].items():
            print(f"    {stage:<16} p50 {s['p50']:8.3f}  p95 {s['p95']:8.3f} ms")
    for method, s in projection["clustering_ms"].items():
        print(f"clustering {method:<10} p50 {s['p50']:.2f} ms ({s['clusters']} clusters)")
    if args.accuracy_frames > 0:
        accuracy = accuracy_run(cfg, args.accuracy_frames, args.seed)
        report["accuracy"] = accuracy
        print(f"accuracy vs ground truth, noise on, {args.accuracy_frames} frames per pose, {len(accuracy['poses'])} poses:")
        for r in accuracy["poses"]:
            print(f"    surface voxels {r['surface_voxels']:5d}: covered {100 * r['surface_covered']:.1f} % "
                  f"(within one voxel {100 * r['surface_covered_within_one_voxel']:.1f} %); occupied {r['occupied']}, "
                  f"spurious {r['spurious']} ({100 * r['spurious_fraction']:.2f} %); on the robot {r['on_robot']}")
    if not args.no_live:
        live = live_run(cfg, frames, args.frames, args.rate, args.config)
        report.update({"latency_ms": live["latency_ms"], "sustained_hz": live["sustained_hz"], "live": live})
        print(f"live service at {args.rate:.0f} Hz: {live['maps_for_frames']}/{live['frames_sent']} frames mapped, "
              f"sustained {live['sustained_hz']:.1f} Hz, frame→map latency p50 {live['latency_ms']['p50']:.1f} ms "
              f"p95 {live['latency_ms']['p95']:.1f} ms")
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return 0
