"""`robonav bench executor`: setpoint timing of the streaming loop, and trajectory durations vs TOPP-RA.

(a) Period error. A Zenoh router and a fake robot (echoes the last setpoint as the joint state
at 100 Hz, so the watchdog is satisfied) run in this process, the executor in its own (as
`robonav serve executor` runs it, with its setpoint stream in a third), for `--seconds`. Paths between seeded random configurations
are executed back to back, each preempting the last before it ends, so setpoints stream
without a pause. The stream keeps `time.monotonic()` right after each setpoint `put`
returns; the period error is |t[i+1] - t[i] - 1/rate|. This measures the executor's own
schedule (sleep wake-up jitter, GIL stalls, the cost of `put`), not the delivery latency to
a subscriber. A missed cycle is a period longer than twice the nominal one. With
`--perception-hz R` the real perception service runs in its own process on the same router,
fed R depth images per second (a pybullet render of the default scene, published by a third
process), and its maps reach the executor's path monitor, which checks every executing path
against them: the executor then works as it does next to a live camera.

(b) Duration ratio. Seeded random Panda paths of 3-8 waypoints within the joint limits
(no collision model) are timed by `time_parameterize` (jerk-limited, corners blended within
`executor.max_path_deviation_rad`) and by TOPP-RA (time-optimal for velocity and
acceleration limits only, on a cubic spline through the same waypoints, same scaled limits).
The ratio is ours / TOPP-RA's duration. TOPP-RA's spline may stray far from the polyline;
ours stays within the bound, so a ratio near 1 is not expected at sharp corners.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.pipeline.sim.goals import intruder_for_trajectory
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.messages import JointState, Setpoint
from robonav.services.bench.reference_loop import run_reference_loop, shared_misses
from robonav.services.config import RobonavConfig, ZenohConfig, default_config_path, load_config


def add_parser(kinds: Any) -> None:  # noqa: ANN401 - argparse's private subparsers type
    """Register `executor` on `robonav bench`'s sub-commands."""
    parser = kinds.add_parser("executor", help="setpoint period error at the stream rate; durations vs TOPP-RA",
                              description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="streaming time for the period measurement [s]")
    parser.add_argument("--rate", type=float, default=None, help="setpoint rate [Hz] (default: executor.rate_hz)")
    parser.add_argument("--paths", type=int, default=20, help="random paths for the duration comparison")
    parser.add_argument("--busy-wait", type=float, default=None, help="executor.busy_wait_s override [s]")
    parser.add_argument("--realtime-priority", type=int, default=None,
                        help="executor.realtime_priority override (SCHED_FIFO 1-99; needs CAP_SYS_NICE)")
    parser.add_argument("--cpu", type=int, default=None,
                        help="executor.cpu_affinity override: pin the setpoint loop (and the reference loop) to this CPU")
    parser.add_argument("--perception-hz", type=float, default=0.0,
                        help="run the perception service in another process, fed depth images at this rate (0: off)")
    parser.add_argument("--drops", type=int, default=0,
                        help="with --perception-hz: then drop a box on a moving arm's path this many times and time "
                             "the stop from the first frame that shows it")
    parser.add_argument("--reference-loop", action="store_true",
                        help="run a bare loop at the same rate and priority beside the stream, to tell the "
                             "machine's own stalls from the stream's")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--config", default=None, help="YAML config (default: the packaged one)")
    parser.add_argument("--json", type=Path, default=None, help="write the summary as JSON to this file")


def random_paths(robot: RobotModel, count: int, seed: int) -> list[np.ndarray]:
    """`count` paths of 3-8 waypoints, steps of up to 0.8 rad per joint, inside the joint limits."""
    rng = np.random.default_rng(seed)
    lower, upper = robot.lower_limits_rad + 0.05, robot.upper_limits_rad - 0.05
    paths = []
    for _ in range(count):
        q = np.clip(robot.home_position_rad + rng.uniform(-0.5, 0.5, robot.dof), lower, upper)
        waypoints = [q]
        for _ in range(int(rng.integers(3, 9)) - 1):
            waypoints.append(np.clip(waypoints[-1] + rng.uniform(-0.8, 0.8, robot.dof), lower, upper))
        paths.append(np.array(waypoints))
    return paths


def toppra_duration_s(path: np.ndarray, v_max: np.ndarray, a_max: np.ndarray) -> float:
    import toppra
    import toppra.algorithm
    import toppra.constraint

    toppra.setup_logging("WARNING")
    lengths = np.linalg.norm(np.diff(path, axis=0), axis=1)
    ss = np.concatenate([[0.0], np.cumsum(lengths)]) / lengths.sum()
    spline = toppra.SplineInterpolator(ss, path)
    constraints = [toppra.constraint.JointVelocityConstraint(np.column_stack([-v_max, v_max])),
                   toppra.constraint.JointAccelerationConstraint(np.column_stack([-a_max, a_max]))]
    instance = toppra.algorithm.TOPPRA(constraints, spline, gridpoints=np.linspace(0, 1, 1001),
                                       parametrizer="ParametrizeConstAccel")
    trajectory = instance.compute_trajectory(0, 0)
    if trajectory is None:
        raise RuntimeError("TOPP-RA found no parameterisation")
    return float(trajectory.duration)


def duration_ratios(cfg: RobonavConfig, robot: RobotModel, count: int, seed: int) -> dict[str, Any]:
    scale_v, scale_a = cfg.executor.velocity_scaling, cfg.executor.acceleration_scaling
    ours, theirs, deviations = [], [], []
    for path in random_paths(robot, count, seed):
        trajectory = time_parameterize(path, max_velocity=robot.velocity_limits, max_acceleration=robot.acceleration_limits,
                                       max_jerk=robot.jerk_limits, velocity_scaling=scale_v, acceleration_scaling=scale_a,
                                       max_path_deviation_rad=cfg.executor.max_path_deviation_rad)
        ours.append(trajectory.duration_s)
        deviations.append(trajectory.max_path_deviation_rad)
        theirs.append(toppra_duration_s(path, robot.velocity_limits * scale_v, robot.acceleration_limits * scale_a))
    ratio = np.array(ours) / np.array(theirs)
    return {"paths": count, "median": float(np.median(ratio)), "max": float(ratio.max()), "min": float(ratio.min()),
            "ours_s_total": float(np.sum(ours)), "toppra_s_total": float(np.sum(theirs)),
            "max_path_deviation_rad": float(np.max(deviations))}


def publish_depth_frames(endpoint: str, config_path: str | None, rate_hz: float, stop: Any,  # noqa: ANN401 - multiprocessing objects
                         box_m: tuple[float, float, float] | None = None, box_on: Any = None,  # noqa: ANN401
                         box_since: Any = None) -> None:  # noqa: ANN401
    """Process body: render the default scene's first camera once, publish it at `rate_hz` until `stop`.

    With `box_m`, a second frame with a 10 cm box centered there is rendered too and published
    instead while `box_on` is set; `box_since` gets the wall time of its first publication.
    """
    from robonav.pipeline.sim.world import SimWorld
    from robonav.pipeline.wire.messages import DepthImage
    from robonav.services.common import open_session
    from robonav.services.keys import Keys

    cfg = load_config(config_path)
    camera = cfg.cameras[0]
    scenes = [cfg.sim.objects]
    if box_m is not None:
        scenes.append((*cfg.sim.objects, SceneObject("dropped", "box", box_m, size_m=(0.1, 0.1, 0.1))))
    depths = []
    for objects in scenes:
        sim = dataclasses.replace(cfg.sim, follow="kinematic", gravity=False, objects=objects)
        with SimWorld(cfg.robot, camera, sim) as world:
            world.set_joint_target(cfg.robot.home_position_rad)
            world.step()
            frame = world.render_depth()
            robot_label = next(label for label, name in world.body_labels().items() if name == "robot")
        # The arm moves and this frame does not: its pixels would turn into obstacles where the
        # arm no longer is. Without them the map is static, and the monitor checks every path
        # against it without ever stopping one, so the stream never pauses.
        depths.append(np.where(frame.segmentation == robot_label, np.inf, frame.depth_m).astype(np.float32))
    session = open_session(ZenohConfig(connect=(endpoint,)))
    key = f"{Keys(cfg.cell).root}/camera/{camera.camera_id}/depth"
    seq, next_at, showing_box = 0, time.monotonic(), False
    while not stop.is_set():
        seq += 1
        with_box = box_on is not None and box_on.is_set()
        stamp = time.time()
        session.put(key, DepthImage(stamp=stamp, camera_id=camera.camera_id, intrinsics=frame.intrinsics,
                                    depth_m=depths[1 if with_box else 0], seq=seq).to_wire())
        if with_box and not showing_box:
            box_since.value = stamp
        showing_box = with_box
        next_at += 1.0 / rate_hz
        time.sleep(max(0.0, next_at - time.monotonic()))
    session.close()


SWING_FROM = np.array([-1.3, 0.0, 0.0, -1.2, 0.0, 1.9, 0.785])
SWING_TO = np.array([1.3, 0.0, 0.0, -1.2, 0.0, 1.9, 0.785])
"""The drop trials swing the base with the hand high and out, clear of the default scene."""
DROP_SCALING = 0.3


def drop_target_m(cfg: RobonavConfig, robot: RobotModel) -> tuple[float, float, float]:
    """Where the hand passes on the swing at least 1.5 s after it starts (the box's center)."""
    trajectory = time_parameterize(np.array([SWING_FROM, SWING_TO]), max_velocity=robot.velocity_limits,
                                   max_acceleration=robot.acceleration_limits, max_jerk=robot.jerk_limits,
                                   velocity_scaling=DROP_SCALING, acceleration_scaling=DROP_SCALING,
                                   max_path_deviation_rad=cfg.executor.max_path_deviation_rad)
    times, q, _, _ = trajectory.sample_uniform(0.05)
    intruder = intruder_for_trajectory(robot, times, q, link=cfg.robot.end_effector_link, slide_s=0.0, min_lead_s=1.5)
    if intruder is None:
        raise RuntimeError("no place on the swing to drop a box on")
    return intruder.target_m


def _executor_process(cfg: RobonavConfig, keep_times: int, conn: Any) -> None:  # noqa: ANN401 - a Connection
    """Process body: the executor node as its service runs it; "stats" → its stream's stats, "stop" → exit."""
    from robonav.services.common import open_session
    from robonav.services.executor.node import ExecutorNode

    with open_session(cfg.zenoh) as session:
        node = ExecutorNode(cfg, session, keep_stream_times=keep_times)
        stop = threading.Event()
        spinner = threading.Thread(target=node.spin, args=(stop,), daemon=True)
        spinner.start()
        conn.send("ready")
        while conn.recv() == "stats":
            conn.send(node.stream_stats())
        stop.set()
        spinner.join(timeout=5.0)
        node.close()


def period_errors(cfg: RobonavConfig, robot: RobotModel, seconds: float, seed: int, *,
                  perception_hz: float = 0.0, config_path: str | None = None, drops: int = 0,
                  reference_loop: bool = False) -> dict[str, Any]:
    import socket

    from robonav.services.client import RobonavClient
    from robonav.services.common import open_session
    from robonav.services.keys import Keys

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    # No planner runs here: every execute is checked against the map alone (and needs none without perception).
    cfg = dataclasses.replace(cfg, zenoh=ZenohConfig(connect=(endpoint,)),
                              executor=dataclasses.replace(cfg.executor, require_scene=False),
                              planner=dataclasses.replace(cfg.planner, require_occupancy=perception_hz > 0))
    spawn = multiprocessing.get_context("spawn")
    executor_conn, child_conn = spawn.Pipe()
    # Not a daemon: the executor starts its setpoint stream as a child process.
    executor = spawn.Process(target=_executor_process,
                             args=(cfg, int(seconds * cfg.executor.rate_hz * 1.5) + 10_000, child_conn))
    client_session = open_session(ZenohConfig(connect=(endpoint,)))
    client = RobonavClient(client_session, cfg.cell)
    keys = Keys(cfg.cell)
    position = [robot.home_position_rad.copy()]
    sub = client_session.declare_subscriber(
        keys.setpoint, lambda sample: position.__setitem__(0, Setpoint.from_wire(sample.payload.to_bytes()).position))
    robot_stop = threading.Event()

    def fake_robot() -> None:
        while not robot_stop.wait(0.01):
            client_session.put(keys.joint_states, JointState(stamp=time.time(), names=robot.joint_names,
                                                             position=position[0], velocity=np.zeros(robot.dof)).to_wire())

    robot_thread = threading.Thread(target=fake_robot, daemon=True)
    robot_thread.start()
    helpers: list[Any] = []
    frames_stop, box_on, box_since = spawn.Event(), spawn.Event(), spawn.Value("d", 0.0)
    reference_stop = spawn.Event()
    reference_times: np.ndarray | None = None
    drop_delays_s: list[float] = []
    maps_before = 0
    if perception_hz > 0:
        with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as handle:
            data = yaml.safe_load((Path(config_path) if config_path else default_config_path()).read_text(encoding="utf-8"))
            data.setdefault("zenoh", {}).update(mode="client", connect=[endpoint], listen=[])
            data.setdefault("perception", {})["max_update_rate_hz"] = max(perception_hz, 1.0)
            yaml.safe_dump(data, handle)
        helpers.append(subprocess.Popen([sys.executable, "-m", "robonav.services.cli", "serve", "perception",
                                         "--config", handle.name, "--log-level", "WARNING"]))
        box_m = drop_target_m(cfg, robot) if drops > 0 else None
        frames = spawn.Process(target=publish_depth_frames,
                               args=(endpoint, handle.name, perception_hz, frames_stop, box_m, box_on, box_since),
                               daemon=True)
        frames.start()
        helpers.append(frames)
        if not client.wait_for(lambda: client.occupancy is not None, 60.0):
            raise RuntimeError("the perception service published no map within 60 s")
        maps_before = client.occupancy.seq if client.occupancy is not None else 0
    executor.start()
    if not executor_conn.poll(120.0) or executor_conn.recv() != "ready":
        raise RuntimeError("the executor process did not start")
    rng = np.random.default_rng(seed)
    lower, upper = robot.lower_limits_rad + 0.1, robot.upper_limits_rad - 0.1
    preemptions = 0
    try:
        client.wait_for(lambda: client.status is not None, 10.0)
        time.sleep(0.5)  # the fake robot's joint states reach the executor
        # With perception on, the path monitor checks every path against the scene's map: paths
        # through the table would be stopped (rightly), pausing the stream, so draw clear ones.
        scene = CollisionWorld(robot, padding_m=0.08) if perception_hz > 0 else None
        if scene is not None:
            scene.set_objects(list(cfg.sim.objects))
        if reference_loop:
            reference_conn, reference_child = spawn.Pipe()
            reference = spawn.Process(target=run_reference_loop, daemon=True, args=(
                1.0 / cfg.executor.rate_hz, cfg.executor.realtime_priority, reference_stop, reference_child,
                cfg.executor.cpu_affinity))
            reference.start()
            helpers.append(reference)
            if not reference_conn.poll(60.0) or reference_conn.recv() != "ready":
                raise RuntimeError("the reference loop did not start")
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            start = position[0].copy()
            for _ in range(100):
                goal = np.clip(start + rng.uniform(-0.6, 0.6, robot.dof), lower, upper)
                middle = np.clip((start + goal) / 2 + rng.uniform(-0.2, 0.2, robot.dof), lower, upper)
                if scene is None or scene.path_valid(np.array([start, middle, goal]), 0.05):
                    break
            reply = client.execute(np.array([start, middle, goal]))
            duration_s = getattr(reply, "duration_s", 0.5)
            preemptions += 1
            # Preempt 0.3 s before the end so the stream never pauses.
            time.sleep(max(min(duration_s - 0.3, end - time.monotonic()), 0.05))
        executor_conn.send("stats")
        if not executor_conn.poll(60.0):
            raise RuntimeError("the executor process did not report its stream")
        stream = executor_conn.recv()
        times = stream.publish_times_s
        if reference_loop:
            reference_stop.set()
            if not reference_conn.poll(30.0):
                raise RuntimeError("the reference loop did not report")
            reference_times = reference_conn.recv()
        maps = (client.occupancy.seq - maps_before) if perception_hz > 0 and client.occupancy is not None else 0
        for trial in range(drops if perception_hz > 0 else 0):
            delay = _drop_trial(client, position, box_on, box_since, trial)
            if delay is not None:
                drop_delays_s.append(delay)
    finally:
        frames_stop.set()
        reference_stop.set()
        for helper in helpers:
            if isinstance(helper, subprocess.Popen):
                helper.terminate()
                helper.wait(timeout=30)
            else:
                helper.join(timeout=10)
        if executor.is_alive():
            executor_conn.send("stop")
            executor.join(timeout=10.0)
        if executor.is_alive():
            executor.terminate()
        robot_stop.set()
        robot_thread.join()
        sub.undeclare()
        client.close()
        for session in (client_session, router):
            session.close()
    nominal_s = 1.0 / cfg.executor.rate_hz
    periods = np.diff(times)
    error_ms = np.abs(periods - nominal_s) * 1e3
    shared = None if reference_times is None else shared_misses(times, reference_times, nominal_s)
    return {"reference_loop": shared, "drops": drops, "stopped": len(drop_delays_s), "stop_after_frame_ms": [round(d * 1e3, 1) for d in drop_delays_s],
            "setpoints": int(times.size), "executes": preemptions, "perception_maps": maps,
            "perception_maps_hz": maps / seconds,
            "p50": float(np.percentile(error_ms, 50)), "p99": float(np.percentile(error_ms, 99)),
            "max": float(error_ms.max()), "missed": int(np.sum(periods > 2 * nominal_s)),
            "max_at_s": float(times[int(np.argmax(error_ms))] - times[0]),
            "late_tables": len(stream.late_s), "late_ms": [round(x * 1e3, 1) for x in stream.late_s],
            "delayed_starts": len(stream.delayed_s), "delayed_ms": [round(x * 1e3, 1) for x in stream.delayed_s],
            "starved": stream.starved,
            "mean_period_ms": float(periods.mean() * 1e3)}


def _drop_summary(periods: dict[str, Any]) -> dict[str, Any]:
    delays = periods["stop_after_frame_ms"]
    p50, p95, top = (np.percentile(delays, [50, 95, 100]).round(1).tolist() if delays else (None, None, None))
    return {"drops": periods["drops"], "stopped": periods["stopped"], "p50": p50, "p95": p95, "max": top,
            "stop_after_frame_ms": delays}


def _drop_trial(client: Any, position: list[np.ndarray], box_on: Any, box_since: Any, trial: int) -> float | None:  # noqa: ANN401
    """Swing, show the box 0.3 s in; returns stop command time - first frame with the box [s]
    (None when the executor did not stop the swing for it)."""
    def move(path: np.ndarray, trajectory_id: str, **fields: Any) -> Any:  # noqa: ANN401
        reply = client.execute(path, trajectory_id=trajectory_id, **fields)
        if not hasattr(reply, "duration_s"):
            raise RuntimeError(f"drop trial {trial}: execute refused: {reply}")
        return reply

    box_on.clear()
    # The timing run preempts each motion before its end, so its last one may still be moving
    # (on a loaded host, long after the run): a path from the measured position would start
    # away from the commanded state, which the executor rightly refuses.
    if not client.wait_for(lambda: client.status is not None and client.status.state.value in ("idle", "stopped", "error"),
                           60.0):
        raise RuntimeError(f"drop trial {trial}: the arm is still moving after 60 s: {client.status}")
    time.sleep(0.5)  # perception sees the box gone (it clears within 3 frames); the measured state settles
    back = move(np.array([position[0].copy(), SWING_FROM]), f"drop-back-{trial}")
    client.wait_for_trajectory(back.trajectory_id, back.duration_s + 5.0)
    time.sleep(0.3)
    swing = move(np.array([position[0].copy(), SWING_TO]), f"drop-{trial}", max_velocity_scaling_factor=DROP_SCALING,
                 max_acceleration_scaling_factor=DROP_SCALING)
    time.sleep(0.3)
    box_since.value = 0.0
    box_on.set()
    client.wait_for_trajectory(swing.trajectory_id, swing.duration_s + 5.0)
    status = client.status
    box_on.clear()
    if status is None or status.error_code != ErrorCode.PATH_BLOCKED or status.blocked_stamp is None or box_since.value <= 0:
        return None
    return float(status.blocked_stamp - box_since.value)


def main(args: argparse.Namespace) -> int:
    """`robonav bench executor`: print the summary, write the JSON."""
    cfg = load_config(args.config)
    if args.rate is not None:
        cfg = dataclasses.replace(cfg, executor=dataclasses.replace(cfg.executor, rate_hz=args.rate))
    if args.busy_wait is not None:
        cfg = dataclasses.replace(cfg, executor=dataclasses.replace(cfg.executor, busy_wait_s=args.busy_wait))
    if args.cpu is not None:
        cfg = dataclasses.replace(cfg, executor=dataclasses.replace(cfg.executor, cpu_affinity=(args.cpu,)))
    if args.realtime_priority is not None:
        cfg = dataclasses.replace(cfg, executor=dataclasses.replace(cfg.executor, realtime_priority=args.realtime_priority))
    robot = RobotModel.from_config(cfg.robot)
    ratios = duration_ratios(cfg, robot, args.paths, args.seed)
    periods = period_errors(cfg, robot, args.seconds, args.seed, perception_hz=args.perception_hz, config_path=args.config,
                            drops=args.drops, reference_loop=args.reference_loop)
    report = {"rate_hz": cfg.executor.rate_hz, "seconds": args.seconds, "busy_wait_s": cfg.executor.busy_wait_s,
              "realtime_priority": cfg.executor.realtime_priority, "cpu_affinity": list(cfg.executor.cpu_affinity),
              "period_error_ms": {k: periods[k] for k in ("p50", "p99", "max")}, "missed": periods["missed"],
              "setpoints": periods["setpoints"], "executes": periods["executes"], "max_at_s": periods["max_at_s"],
              "mean_period_ms": periods["mean_period_ms"],
              "late_tables": periods["late_tables"], "late_ms": periods["late_ms"], "starved": periods["starved"],
              "delayed_starts": periods["delayed_starts"], "delayed_ms": periods["delayed_ms"],
              "perception_hz": args.perception_hz, "perception_maps_hz": periods["perception_maps_hz"],
              "drop_stop": _drop_summary(periods), "reference_loop": periods["reference_loop"],
              "duration_ratio_vs_toppra": ratios,
              "method": "period: time.monotonic() after each setpoint put in the executor's setpoint stream process; "
                        "ratio: time_parameterize duration / TOPP-RA (vel+acc, cubic spline) duration"}
    print(f"rate {report['rate_hz']:.0f} Hz for {args.seconds:.0f} s: {periods['setpoints']} setpoints, "
          f"{periods['executes']} executes (each preempting the last)")
    if args.perception_hz > 0:
        print(f"perception in another process: fed {args.perception_hz:.0f} Hz, published "
              f"{periods['perception_maps_hz']:.1f} maps/s to the executor's path monitor")
    if args.drops > 0 and args.perception_hz > 0:
        drop = report["drop_stop"]
        print(f"box dropped on the path {drop['drops']} times: stopped {drop['stopped']}; stop command after the first "
              f"frame showing it [ms]: p50 {drop['p50']}  p95 {drop['p95']}  max {drop['max']}")
    print(f"period error [ms]: p50 {periods['p50']:.3f}  p99 {periods['p99']:.3f}  max {periods['max']:.3f}  "
          f"missed (> 2x period) {periods['missed']}")
    shared = periods["reference_loop"]
    if shared is not None:
        print(f"bare reference loop beside it: missed {shared['reference_missed']}, period error p99 "
              f"{shared['reference_period_error_ms']['p99']:.3f} max {shared['reference_period_error_ms']['max']:.3f} ms; "
              f"stream misses while the reference missed too: {shared['shared']} of {shared['stream_missed']}")
    print(f"trajectories handed to the stream after their start time: {periods['late_tables']} "
          f"(late by [ms]: {periods['late_ms'][:20]}); braked for want of the rest of one: {periods['starved']}; "
          f"motions from rest started late, from their first row: {periods['delayed_starts']} "
          f"(by [ms]: {periods['delayed_ms'][:20]})")
    print(f"duration vs TOPP-RA over {ratios['paths']} paths: median {ratios['median']:.3f}  max {ratios['max']:.3f}  "
          f"min {ratios['min']:.3f}  (our max deviation {ratios['max_path_deviation_rad']:.4f} rad)")
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="robonav bench")
    add_parser(parser.add_subparsers(dest="kind", required=True))
    sys.exit(main(parser.parse_args()))
