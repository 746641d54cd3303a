"""`robonav bench wire`: what encoding and decoding a message costs, for the ones sent most often.

Setpoints go out at the executor rate (1 kHz) and every subscriber decodes each one (the sim,
`robonav campaign`'s limit monitor, a recorder); joint states and executor statuses at 100 Hz;
clouds at camera rate. Each message is encoded (`to_wire`) and decoded (`from_wire`, with all
of its checks) `--calls` times per batch, for `--batches` batches; the report gives the median
and the slowest batch's time per call, in microseconds of this process's wall clock.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from robonav.pipeline.wire.codec import Message
from robonav.pipeline.wire.messages import ExecutionState, ExecutorStatus, JointState, PointCloud, Setpoint


def add_parser(kinds: Any) -> None:  # noqa: ANN401 - argparse's private subparsers type
    """Register `wire` on `robonav bench`'s sub-commands."""
    parser = kinds.add_parser("wire", help="encode and decode time of the most frequent messages",
                              description=__doc__.split("\n\n")[0])
    parser.add_argument("--joints", type=int, default=7, help="joints of the setpoints and joint states")
    parser.add_argument("--points", type=int, default=20_000, help="points of the cloud")
    parser.add_argument("--calls", type=int, default=1000, help="calls per batch (clouds: a tenth)")
    parser.add_argument("--batches", type=int, default=7, help="batches per message and direction")
    parser.add_argument("--seed", type=int, default=0, help="seeds the values")
    parser.add_argument("--json", type=Path, default=None, help="write the summary as JSON to this file")


def sample_messages(*, joints: int, points: int, seed: int) -> dict[str, Message]:
    """One message of each measured kind, with values drawn from `seed`."""
    rng = np.random.default_rng(seed)
    names = tuple(f"joint{i + 1}" for i in range(joints))
    return {
        "Setpoint": Setpoint(stamp=time.time(), trajectory_id="bench-0", names=names,
                             position=rng.uniform(-2, 2, joints), velocity=rng.uniform(-1, 1, joints),
                             acceleration=rng.uniform(-5, 5, joints)),
        "JointState": JointState(stamp=time.time(), names=names, position=rng.uniform(-2, 2, joints),
                                 velocity=rng.uniform(-1, 1, joints)),
        "ExecutorStatus": ExecutorStatus(stamp=time.time(), state=ExecutionState.EXECUTING, trajectory_id="bench-0",
                                         progress=0.5, time_from_start_s=1.0, duration_s=2.0),
        "PointCloud": PointCloud(stamp=time.time(), camera_id="cam0",
                                 points=rng.uniform(-1, 1, (points, 3)).astype(np.float32)),
    }


def per_call_us(call: Callable[[], object], *, calls: int, batches: int) -> list[float]:
    """Wall time per call of each batch [µs]."""
    times = []
    for _ in range(batches):
        start = time.perf_counter()
        for _ in range(calls):
            call()
        times.append((time.perf_counter() - start) / calls * 1e6)
    return times


def measure(messages: dict[str, Message], *, calls: int, batches: int) -> list[dict[str, Any]]:
    """Per message: its size, and the median and slowest batch's encode and decode time per call."""
    rows = []
    for name, message in messages.items():
        n = max(1, calls // 10) if isinstance(message, PointCloud) else calls
        payload = message.to_wire()
        cls = type(message)
        row: dict[str, Any] = {"message": name, "bytes": len(payload), "calls": n}
        for direction, call in (("encode", message.to_wire), ("decode", lambda cls=cls: cls.from_wire(payload))):
            times = per_call_us(call, calls=n, batches=batches)
            row[f"{direction}_us_median"] = round(statistics.median(times), 2)
            row[f"{direction}_us_max"] = round(max(times), 2)
        rows.append(row)
    return rows


def format_table(rows: list[dict[str, Any]]) -> str:
    header = f"{'message':<16}{'bytes':>10}{'encode us':>12}{'(max)':>10}{'decode us':>12}{'(max)':>10}"
    lines = [header, "-" * len(header)]
    lines += [f"{r['message']:<16}{r['bytes']:>10}{r['encode_us_median']:>12.1f}{r['encode_us_max']:>10.1f}"
              f"{r['decode_us_median']:>12.1f}{r['decode_us_max']:>10.1f}" for r in rows]
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    bad = [f"--{name} must be > 0, got {value}" for name, value in
           (("joints", args.joints), ("points", args.points), ("calls", args.calls), ("batches", args.batches)) if value <= 0]
    if bad:
        print(f"robonav bench wire: {'; '.join(bad)}", file=sys.stderr)
        return 2
    messages = sample_messages(joints=args.joints, points=args.points, seed=args.seed)
    rows = measure(messages, calls=args.calls, batches=args.batches)
    print(format_table(rows))
    if args.json is not None:
        report = {"config": {"joints": args.joints, "points": args.points, "calls": args.calls,
                             "batches": args.batches, "seed": args.seed}, "messages": rows}
        args.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return 0

