"""`robonav plot trajectory`: position, velocity, acceleration and jerk per joint over time, with the scaled limits.

From a path (`--json`/`--path-json`: waypoints and joint names, e.g. a saved `PlanResponse`),
timed with the executor's own `time_parameterize` and sampled every millisecond; or from what
the executor streamed (`--recording run.mcap`, made by `robonav record`): the setpoints of one
trajectory, placed at their stamps (each setpoint's grid time). Jerk is the finite difference
of the acceleration. Rendering uses matplotlib's Agg backend (no display).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.pipeline.trajectory.trajectory import TrajectoryLimits
from robonav.pipeline.wire.joint_order import reorder_to_robot
from robonav.pipeline.wire.messages import Setpoint
from robonav.services.config import RobonavConfig, load_config
from robonav.services.recording.files import Recording, RecordingError

SAMPLE_PERIOD_S = 1e-3
SETPOINT_KEYS = "**/executor/setpoint"
"""Setpoints of any cell in a recording."""


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="robonav plot", description="Plots.")
    kinds = parser.add_subparsers(dest="kind", required=True)
    trajectory = kinds.add_parser("trajectory", help="p, v, a, jerk per joint of a timed path, with limits")
    source = trajectory.add_mutually_exclusive_group(required=True)
    source.add_argument("--json", type=Path, help="JSON file with 'path' ([[q]]) and optionally 'joint_names'")
    source.add_argument("--path-json", help="the same JSON inline")
    source.add_argument("--recording", type=Path, help="MCAP recording holding executor/setpoint (robonav record)")
    trajectory.add_argument("--trajectory-id", default=None,
                            help="with --recording: the trajectory to plot (default: the last one streamed)")
    trajectory.add_argument("-o", "--output", type=Path, required=True, help="PNG file to write")
    trajectory.add_argument("--velocity-scaling", type=float, default=None)
    trajectory.add_argument("--acceleration-scaling", type=float, default=None)
    trajectory.add_argument("--config", default=None, help="YAML config (robot limits, executor defaults)")
    return parser.parse_args(argv)


@dataclass(frozen=True)
class _Series:
    title: str
    joint_names: tuple[str, ...]
    t_s: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    limits: TrajectoryLimits
    marks_s: tuple[float, ...] = ()


def main(argv: list[str] | None = None) -> int:
    """Entry point of `robonav plot`; returns the exit code (2 on bad input)."""
    args = parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        cfg = load_config(args.config)
        robot = RobotModel.from_config(cfg.robot)
        series = _from_recording(args, cfg, robot) if args.recording else _from_path(args, cfg, robot)
    except (OSError, ValueError, KeyError, TypeError, RecordingError) as exc:
        print(f"robonav plot trajectory: {exc}", file=sys.stderr)
        return 2
    _draw(series, args.output)
    print(f"wrote {args.output}")
    return 0


def _from_path(args: argparse.Namespace, cfg: RobonavConfig, robot: RobotModel) -> _Series:
    data: dict[str, Any] = json.loads(args.json.read_text(encoding="utf-8") if args.json else args.path_json)
    path = np.asarray(data["path"], dtype=float)
    names = data.get("joint_names") or list(robot.joint_names)
    if path.ndim != 2 or path.shape[1] != len(robot.joint_names):
        raise ValueError(f"'path' must be (K, {len(robot.joint_names)}), got {path.shape}")
    if sorted(names) != sorted(robot.joint_names):
        raise ValueError(f"joint_names {names} must name the robot's joints {list(robot.joint_names)}")
    path = path[:, [names.index(n) for n in robot.joint_names]]
    v_scale = args.velocity_scaling or data.get("max_velocity_scaling_factor") or cfg.executor.velocity_scaling
    a_scale = args.acceleration_scaling or data.get("max_acceleration_scaling_factor") or cfg.executor.acceleration_scaling
    trajectory = time_parameterize(path, max_velocity=robot.velocity_limits, max_acceleration=robot.acceleration_limits,
                                   max_jerk=robot.jerk_limits, velocity_scaling=v_scale, acceleration_scaling=a_scale,
                                   max_path_deviation_rad=cfg.executor.max_path_deviation_rad)
    t, q, qd, qdd = trajectory.sample_uniform(SAMPLE_PERIOD_S)
    limits = trajectory.limits
    assert limits is not None
    title = (f"{path.shape[0]} waypoints, {trajectory.duration_s:.3f} s, velocity x{v_scale}, accel/jerk x{a_scale}, "
             f"max deviation {trajectory.max_path_deviation_rad:.4f} rad (dashed: scaled limits)")
    marks = tuple(trajectory.waypoint_times_s) if trajectory.waypoint_times_s is not None else ()
    return _Series(title, tuple(robot.joint_names), t, q, qd, qdd, limits, marks)


def _from_recording(args: argparse.Namespace, cfg: RobonavConfig, robot: RobotModel) -> _Series:
    """The setpoints of one trajectory from a recording, in robot joint order, by stamp."""
    setpoints: list[Setpoint] = []
    for message in Recording(args.recording).messages(keys=(SETPOINT_KEYS,)):
        try:
            setpoints.append(Setpoint.from_wire(message.payload))
        except ValueError:
            continue  # a malformed message on the key says nothing about the trajectory
    if not setpoints:
        raise ValueError(f"{args.recording} holds no setpoints (record '{SETPOINT_KEYS}' while the executor moves)")
    wanted = args.trajectory_id if args.trajectory_id is not None else setpoints[-1].trajectory_id
    chosen = sorted((s for s in setpoints if s.trajectory_id == wanted), key=lambda s: s.stamp)
    if not chosen:
        known = sorted({s.trajectory_id for s in setpoints})
        raise ValueError(f"no setpoints of trajectory '{wanted}' in {args.recording}; it holds: {', '.join(known)}")
    names = tuple(robot.joint_names)
    sent = tuple(chosen[0].names)

    def in_robot_order(values: list[np.ndarray], key: str) -> np.ndarray:
        return reorder_to_robot(np.array(values), sent, names, key)

    stamps = np.array([s.stamp for s in chosen])
    v_scale = args.velocity_scaling or 1.0
    a_scale = args.acceleration_scaling or 1.0
    limits = TrajectoryLimits(robot.velocity_limits * v_scale, robot.acceleration_limits * a_scale,
                              robot.jerk_limits * a_scale)
    title = (f"'{wanted}': {len(chosen)} setpoints over {stamps[-1] - stamps[0]:.3f} s from {args.recording.name} "
             f"(dashed: limits x{v_scale} velocity, x{a_scale} accel/jerk)")
    return _Series(title, names, stamps - stamps[0], in_robot_order([s.position for s in chosen], "position"),
                   in_robot_order([s.velocity for s in chosen], "velocity"),
                   in_robot_order([s.acceleration for s in chosen], "acceleration"), limits)


def _draw(series: _Series, output: Path) -> None:
    t, qdd = series.t_s, series.qdd
    dt = np.diff(t)
    jerk = np.diff(qdd, axis=0) / np.where(dt > 0, dt, np.inf)[:, None]
    limits = series.limits

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 1, figsize=(11, 12), sharex=True)
    rows = [("position [rad]", t, series.q, None), ("velocity [rad/s]", t, series.qd, limits.velocity),
            ("acceleration [rad/s²]", t, qdd, limits.acceleration), ("jerk [rad/s³]", t[1:], jerk, limits.jerk)]
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, (label, times, values, limit) in zip(axes, rows):
        for j, name in enumerate(series.joint_names):
            color = colors[j % len(colors)]
            ax.plot(times, values[:, j], color=color, lw=1.0, label=name)
            if limit is not None:
                ax.axhline(limit[j], color=color, lw=0.7, ls="--")
                ax.axhline(-limit[j], color=color, lw=0.7, ls="--")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    for mark in series.marks_s:
        axes[0].axvline(mark, color="grey", lw=0.5, ls=":")
    axes[0].legend(loc="upper right", fontsize=7, ncol=4)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(series.title)
    fig.tight_layout()
    output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(output, dpi=110)
    plt.close(fig)
