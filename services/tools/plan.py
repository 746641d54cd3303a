"""`robonav plan`: ask the running planners for a path (and optionally execute it) from a shell.

    robonav plan --goal q1 ... qn [--race] [--execute] [--config FILE] [--zenoh-config FILE]
    robonav plan --pose x y z [--quat x y z w] ...

One planner answers (Zenoh's best match) unless `--race`, which asks every planner and takes
the first valid plan. Prints one JSON object; exit code 0 when the plan (and the execution)
succeeded, 1 on a structured error (any code, BUSY included) or a failed execution, 2 on a bad
config or request, 3 when a query got no reply of the protocol: nothing answered within
`--timeout` (no service, a dead planner, access control refused us), Zenoh ended it with its
own error (its "Timeout"), or the reply was not a message; 130 after Ctrl-C. Ctrl-C (SIGINT, or SIGTERM) while the arm moves sends `executor/stop` and waits
until it rests before exiting (a second Ctrl-C: an emergency stop); before the execute was
sent, nothing moves.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import numpy as np
import zenoh

from robonav.pipeline.config import ConfigError
from robonav.pipeline.wire.messages import ErrorReply, ExecuteResponse, PlanRequest, PlanResponse
from robonav.services.client import QueryFailed, RobonavClient
from robonav.services.common import load_cli_config, open_session
from robonav.services.tools.stop import (
    EXIT_CONFIG,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_NO_REPLY,
    EXIT_OK,
    Interrupt,
    stop_after_interrupt,
    wait_or_interrupt,
)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="robonav plan", description=__doc__.splitlines()[0])
    goal = parser.add_mutually_exclusive_group(required=True)
    goal.add_argument("--goal", type=float, nargs="+", metavar="Q", help="joint goal [rad] in the robot's joint order")
    goal.add_argument("--pose", type=float, nargs=3, metavar=("X", "Y", "Z"),
                      help="Cartesian goal of the end effector in the world frame [m]")
    parser.add_argument("--quat", type=float, nargs=4, metavar=("X", "Y", "Z", "W"),
                        help="goal orientation quat_xyzw for --pose (default: any orientation)")
    parser.add_argument("--start", type=float, nargs="+", metavar="Q", help="start [rad] (default: the robot's joint state)")
    parser.add_argument("--planner-id", help="planner (default: each planner's configured one)")
    parser.add_argument("--planning-time", type=float, help="allowed planning time [s]")
    parser.add_argument("--seed", type=int)
    parser.add_argument("--race", action="store_true", help="ask every planner, take the first valid plan")
    parser.add_argument("--execute", action="store_true", help="execute the path and wait until it finishes")
    parser.add_argument("--velocity-scaling", type=float, metavar="F",
                        help="with --execute: scale the velocity and acceleration limits by F in (0, 1] "
                             "(MoveIt's max_velocity_scaling_factor; default: the executor's)")
    parser.add_argument("--replan", action="store_true",
                        help="with --execute: when a new obstacle blocks the path, stop and plan again (else stop with PATH_BLOCKED)")
    parser.add_argument("--timeout", type=float, default=30.0, help="per query [s]")
    parser.add_argument("--config", help="YAML config (default: the packaged default); its zenoh and cell keys are used")
    parser.add_argument("--zenoh-config", help="Zenoh JSON5 config (TLS, credentials); overrides zenoh.config_file")
    parser.add_argument("--json", help="also write the result to this file")
    return parser.parse_args(argv)


def plan_request(args: argparse.Namespace) -> PlanRequest:
    """Raises ValueError for a request the message refuses (e.g. joint vectors of different lengths)."""
    return PlanRequest(
        goal_positions=None if args.goal is None else np.asarray(args.goal, float),
        goal_position_m=None if args.pose is None else np.asarray(args.pose, float),
        goal_quat_xyzw=None if args.quat is None else np.asarray(args.quat, float),
        start_positions=None if args.start is None else np.asarray(args.start, float),
        planner_id=args.planner_id, allowed_planning_time=args.planning_time, seed=args.seed,
    )


def plan_and_execute(client: RobonavClient, args: argparse.Namespace, request: PlanRequest,
                     interrupt: Interrupt) -> tuple[int, dict[str, Any]]:
    """Raises QueryFailed when a query got no reply of the protocol."""
    started = time.monotonic()
    plan = client.plan_request(request, timeout_s=args.timeout, race=args.race)
    record: dict[str, Any] = {"race": args.race, "replier": client.last_replier,
                              "plan_wall_s": round(time.monotonic() - started, 3)}
    if isinstance(plan, ErrorReply):
        record.update(ok=False, stage="plan", code=plan.code, message=plan.message, details=plan.details)
        return EXIT_FAILED, record
    assert isinstance(plan, PlanResponse)
    record.update(ok=True, planner_id=plan.planner_id, planning_time_s=round(plan.planning_time_s, 4),
                  path_length_rad=round(plan.path_length_rad, 4), waypoint_count=plan.waypoint_count,
                  goal_positions=np.round(plan.path[-1], 5).tolist())
    if not args.execute:
        return EXIT_OK, record
    if interrupt.is_set():  # Ctrl-C while planning: nothing has moved, nothing will
        record.update(ok=False, stage="interrupted", interrupted=True)
        return EXIT_INTERRUPTED, record
    scaling = args.velocity_scaling
    execution = client.execute(plan.path, joint_names=plan.joint_names, timeout_s=args.timeout, replan=args.replan,
                               occupancy_stamp=plan.occupancy_stamp, scene_revision=plan.scene_revision,
                               max_velocity_scaling_factor=scaling,
                               max_acceleration_scaling_factor=scaling)
    if isinstance(execution, ErrorReply):
        record.update(ok=False, stage="execute", code=execution.code, message=execution.message, details=execution.details)
        return EXIT_FAILED, record
    assert isinstance(execution, ExecuteResponse)
    record.update(trajectory_id=execution.trajectory_id, duration_s=round(execution.duration_s, 3))
    trajectory_id = execution.trajectory_id
    wait_or_interrupt(client, lambda: client.trajectory_finished(trajectory_id), execution.duration_s + args.timeout,
                      interrupt)
    if interrupt.is_set() and not client.trajectory_finished(trajectory_id):
        record.update(ok=False, stage="interrupted", interrupted=True, stop=stop_after_interrupt(client, interrupt),
                      result=client.wait_for_trajectory(trajectory_id, 0.0))
        return EXIT_INTERRUPTED, record
    result = client.wait_for_trajectory(trajectory_id, 0.0)
    record.update(result=result, ok=result == "succeeded")
    return (EXIT_OK if result == "succeeded" else EXIT_FAILED), record


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.quat is not None and args.pose is None:
        print("robonav plan: --quat needs --pose", file=sys.stderr)
        return EXIT_CONFIG
    if args.velocity_scaling is not None and not 0 < args.velocity_scaling <= 1:
        print(f"robonav plan: --velocity-scaling must be in (0, 1], got {args.velocity_scaling}", file=sys.stderr)
        return EXIT_CONFIG
    try:
        cfg = load_cli_config(args.config, args.zenoh_config)
        zcfg = cfg.zenoh
    except (ConfigError, ValueError) as exc:
        print(f"robonav plan: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    try:
        request = plan_request(args)
    except ValueError as exc:
        print(f"robonav plan: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    try:
        session = open_session(zcfg)
    except zenoh.ZError as exc:
        print(f"robonav plan: cannot reach the router at {', '.join(zcfg.connect)}: {exc}", file=sys.stderr)
        return EXIT_NO_REPLY
    with session, Interrupt() as interrupt:
        client = RobonavClient(session, cfg.cell)
        try:
            code, record = plan_and_execute(client, args, request, interrupt)
        except QueryFailed as exc:
            code, record = EXIT_NO_REPLY, {"ok": False, "stage": "no_reply", "key": exc.key, "timeout_s": exc.timeout_s,
                                           "message": str(exc)}
        finally:
            client.close()
    text = json.dumps(record, indent=2)
    print(text)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as out:
            out.write(text + "\n")
    return code
