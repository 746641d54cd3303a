"""`robonav plot trajectory`: position, velocity, acceleration and jerk per joint over time, with the scaled limits.

The path (waypoints and joint names, e.g. a saved `PlanResponse`) is timed with the
executor's own `time_parameterize` and sampled every millisecond; jerk is the finite
difference of the sampled acceleration. Rendering uses matplotlib's Agg backend (no display).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from robonav.pipeline.robot import RobotModel
from robonav.pipeline.trajectory.timing import time_parameterize
from robonav.services.config import load_config

SAMPLE_PERIOD_S = 1e-3


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="robonav plot", description="Plots.")
    kinds = parser.add_subparsers(dest="kind", required=True)
    trajectory = kinds.add_parser("trajectory", help="p, v, a, jerk per joint of a timed path, with limits")
    source = trajectory.add_mutually_exclusive_group(required=True)
    source.add_argument("--json", type=Path, help="JSON file with 'path' ([[q]]) and optionally 'joint_names'")
    source.add_argument("--path-json", help="the same JSON inline")
    trajectory.add_argument("-o", "--output", type=Path, required=True, help="PNG file to write")
    trajectory.add_argument("--velocity-scaling", type=float, default=None)
    trajectory.add_argument("--acceleration-scaling", type=float, default=None)
    trajectory.add_argument("--config", default=None, help="YAML config (robot limits, executor defaults)")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """Entry point of `robonav plot`; returns the exit code (2 on bad input)."""
    args = parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        data: dict[str, Any] = json.loads(args.json.read_text(encoding="utf-8") if args.json else args.path_json)
        cfg = load_config(args.config)
        robot = RobotModel.from_config(cfg.robot)
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
    except (OSError, ValueError, KeyError, TypeError) as exc:
        print(f"robonav plot trajectory: {exc}", file=sys.stderr)
        return 2
    t, q, qd, qdd = trajectory.sample_uniform(SAMPLE_PERIOD_S)
    jerk = np.diff(qdd, axis=0) / np.diff(t)[:, None]
    limits = trajectory.limits
    assert limits is not None

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 1, figsize=(11, 12), sharex=True)
    rows = [("position [rad]", t, q, None), ("velocity [rad/s]", t, qd, limits.velocity),
            ("acceleration [rad/s²]", t, qdd, limits.acceleration), ("jerk [rad/s³]", t[1:], jerk, limits.jerk)]
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, (label, times, values, limit) in zip(axes, rows):
        for j, name in enumerate(robot.joint_names):
            color = colors[j % len(colors)]
            ax.plot(times, values[:, j], color=color, lw=1.0, label=name)
            if limit is not None:
                ax.axhline(limit[j], color=color, lw=0.7, ls="--")
                ax.axhline(-limit[j], color=color, lw=0.7, ls="--")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    if trajectory.waypoint_times_s is not None:
        for w_t in trajectory.waypoint_times_s:
            axes[0].axvline(w_t, color="grey", lw=0.5, ls=":")
    axes[0].legend(loc="upper right", fontsize=7, ncol=4)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"{path.shape[0]} waypoints, {trajectory.duration_s:.3f} s, velocity x{v_scale}, accel/jerk x{a_scale}, "
                 f"max deviation {trajectory.max_path_deviation_rad:.4f} rad (dashed: scaled limits)")
    fig.tight_layout()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, dpi=110)
    plt.close(fig)
    print(f"wrote {args.output}")
    return 0
