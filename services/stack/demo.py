"""`robonav demo`: bring the stack up, plan and execute the configured goals, print a JSON summary.

With `--robot FILE` (a robot file from `robonav robot init`, or a config whose `robot` section
is taken) the stack runs that robot: for a robot other than the config's own, the cell is
placed for its reach and goals are drawn for it (seeded by `--seed`) instead of the config's.

Exit code 0 only if every goal was reached within tolerance with zero robot–obstacle contacts.
Ctrl-C stops the arm and waits until it rests, then stops the services and reports the goals
done so far (exit code 130).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import signal
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.config import ConfigError
from robonav.pipeline.perception.map_readiness import map_complete
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.robot.turns import joint_distance_rad
from robonav.pipeline.wire.codes import ExecutionState
from robonav.pipeline.wire.messages import ErrorReply, ExecuteResponse, PlanResponse
from robonav.services.client import QueryFailed, RobonavClient
from robonav.services.common import add_logging_arguments, open_session, setup_logging
from robonav.services.config import RobonavConfig, default_config_path, load_config
from robonav.services.keys import SERVICES
from robonav.services.signals import stop_on_signals
from robonav.services.stack.robot_cell import DEMO_GOAL_COUNT, demo_goals, read_robot, with_robot, write_config
from robonav.services.stack.up import Stack
from robonav.services.tools.stop import EXIT_INTERRUPTED, Interrupt, stop_after_interrupt, wait_or_interrupt
from robonav.services.view.snapshot import snapshot_view

log = logging.getLogger("robonav.demo")

SERVICE_START_TIMEOUT_S = 300.0
"""Longest wait for every service's liveliness token [s]. Services compile and warm up before
they declare it: seconds with a filled compile cache (`robonav precompile`), minutes without."""
PLAN_ATTEMPTS = 3
"""Plans (and executes) per goal when one is refused for a reason a fresher map can remove."""
RETRYABLE = {"OCCUPANCY_INCOMPLETE", "OCCUPANCY_STALE", "OCCUPANCY_MISSING", "PATH_IN_COLLISION"}
SETTLE_TIMEOUT_S = 2.0
"""Longest wait after a trajectory ends for the arm to come within tolerance of the goal [s]."""
MOTION_ATTEMPTS = 3
"""Motions per goal when one ends in a fault (the arm braked mid-way)."""
"""Longest wait after a trajectory ends for the arm to come within tolerance of the goal [s]."""


def write_seeded_config(source: Path, seed: int, directory: Path) -> Path:
    """A copy of `source` with `planner.seed` set, so the planner process samples reproducibly."""
    data = yaml.safe_load(source.read_text(encoding="utf-8")) or {}
    data.setdefault("planner", {})["seed"] = seed
    out = directory / "demo-config.yaml"
    out.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return out


def robot_config(source: Path, robot_file: Path, seed: int, directory: Path) -> Path:
    """The config of `source` running the robot of `robot_file` (see `with_robot`), seeded, with
    goals drawn for the robot when the config's are another robot's."""
    cfg = with_robot(load_config(source), read_robot(robot_file))
    cfg = dataclasses.replace(cfg, planner=dataclasses.replace(cfg.planner, seed=seed))
    if not cfg.demo.goals_rad:
        log.warning("drawing %d goals for robot '%s' (seed %d)", DEMO_GOAL_COUNT, cfg.robot.name, seed)
        cfg = dataclasses.replace(cfg, demo=dataclasses.replace(cfg.demo, goals_rad=demo_goals(cfg, seed)))
    return write_config(cfg, directory / "demo-config.yaml")


def map_is_complete(client: RobonavClient, cfg: RobonavConfig) -> bool:
    """Whether the newest map holds the frames the planner needs from every camera."""
    occupancy = client.occupancy
    return occupancy is not None and map_complete(occupancy.camera_frames, [c.camera_id for c in cfg.cameras],
                                                  cfg.planner.occupancy_min_frames)


def true_scene(cfg: RobonavConfig) -> CollisionWorld:
    """The sim's obstacles as the planner's collision world, unpadded: ground truth for the report."""
    world = CollisionWorld(RobotModel.from_config(cfg.robot), padding_m=0.0)
    world.set_objects(cfg.sim.objects)
    return world


def run_goal(client: RobonavClient, truth: CollisionWorld, cfg: RobonavConfig, index: int, goal: np.ndarray,
             seed: int, interrupt: Interrupt) -> dict[str, Any]:
    """Plan and move to `goal`; a motion that ended in a fault (the arm braked: a watchdog, a
    setpoint the robot side refused) is planned again from where the arm came to rest, up to
    `MOTION_ATTEMPTS` motions, each fault kept in the record's `faults`."""
    faults: list[dict[str, Any]] = []
    blocked: bool | None = None
    for motion in range(MOTION_ATTEMPTS):
        record = move_to_goal(client, truth, cfg, index, goal, seed + 1000 * motion, interrupt)
        blocked = record["straight_line_blocked"] if blocked is None else blocked
        if record.get("result") != ExecutionState.ERROR.value or interrupt.is_set() or motion == MOTION_ATTEMPTS - 1:
            break
        status = client.status
        faults.append({"result": record["result"], "error_code": status.error_code if status else None,
                       "message": status.error_message if status else None,
                       "final_error_rad": record["final_error_rad"]})
        log.warning("goal %d: the motion ended in a fault (%s): planning again from where the arm rests",
                    index, faults[-1]["message"])
        client.wait_for(lambda: client.joint_state is not None and float(np.max(np.abs(client.joint_state.velocity))) < 1e-3,
                        SETTLE_TIMEOUT_S)
    record.update(straight_line_blocked=blocked, faults=faults)
    return record


def move_to_goal(client: RobonavClient, truth: CollisionWorld, cfg: RobonavConfig, index: int, goal: np.ndarray,
                 seed: int, interrupt: Interrupt) -> dict[str, Any]:
    """One motion to `goal`: plan (again while refused for a reason a fresher map can remove),
    execute, wait, judge."""
    assert client.joint_state is not None
    start = client.joint_state.position.copy()
    # Blocked means the goal needs a detour around a real obstacle, on the turn the planner takes.
    planned_goal = truth.robot.nearest_turn_rad(goal, start)
    record: dict[str, Any] = {"index": index, "goal_rad": goal.round(4).tolist(),
                              "straight_line_blocked": not truth.motion_valid(start, planned_goal, 0.01)}
    refusals: list[str] = []
    for attempt in range(PLAN_ATTEMPTS):
        asked = time.monotonic()
        plan = client.plan(goal, seed=seed + index + 100 * attempt, request_id=f"demo-{index}-{attempt}")
        record["plan_wall_s"] = round(time.monotonic() - asked, 3)
        if isinstance(plan, ErrorReply):
            record.update(reached=False, error=f"plan: {plan.code}: {plan.message}")
            if plan.code in RETRYABLE:
                refusals.append(f"plan: {plan.code}")
                continue
            return record
        assert isinstance(plan, PlanResponse)
        record.update(planning_ms=round(plan.planning_time_s * 1e3, 2), path_length_rad=round(plan.path_length_rad, 4),
                      waypoints=plan.waypoint_count,
                      min_clearance_m=None if plan.min_clearance_m is None else round(plan.min_clearance_m, 4))
        if interrupt.is_set():  # Ctrl-C while planning: do not start the motion
            record.update(reached=False, interrupted=True)
            return record
        started = time.monotonic()
        # A map that changes under the moving arm (noise, a newly seen surface) should cost a
        # replan, not the goal.
        execution = client.execute(plan.path, joint_names=plan.joint_names, replan=True,
                                   occupancy_stamp=plan.occupancy_stamp, scene_revision=plan.scene_revision)
        if isinstance(execution, ErrorReply):
            # The executor checks the path against its own, newer map: a voxel that came in since
            # the plan refuses it (PATH_IN_COLLISION), and a new plan sees that voxel too.
            record.update(reached=False, error=f"execute: {execution.code}: {execution.message}")
            if execution.code in RETRYABLE:
                refusals.append(f"execute: {execution.code}: {execution.message}")
                continue
            return record
        break
    else:
        return record
    assert isinstance(execution, ExecuteResponse)
    record.pop("error", None)
    record.update(plan_attempts=attempt + 1, refusals=refusals, execute_check_ms=execution.check_ms,
                  execute_checked_samples=execution.checked_samples)
    trajectory_id = execution.trajectory_id
    wait_or_interrupt(client, lambda: client.trajectory_finished(trajectory_id),
                      execution.duration_s + cfg.demo.goal_timeout_s, interrupt)
    if interrupt.is_set() and not client.trajectory_finished(trajectory_id):
        record.update(reached=False, interrupted=True, stop=stop_after_interrupt(client, interrupt))
        return record
    result = client.wait_for_trajectory(trajectory_id, 0.0)
    # The arm lags the last setpoint a little (and more on a loaded machine): let it settle
    # well inside the tolerance, or give up after a while and judge where it is.
    # A continuous joint ends on the goal's turn nearest its start (the planner's shortest turn).
    turning = truth.robot.continuous_mask

    def error_rad() -> float:
        return float(np.max(joint_distance_rad(client.joint_state.position, goal, turning)))

    client.wait_for(lambda: error_rad() <= 0.1 * cfg.demo.goal_tolerance_rad, SETTLE_TIMEOUT_S)
    error = error_rad()
    record.update(execution_s=round(time.monotonic() - started, 3), trajectory_duration_s=round(execution.duration_s, 3),
                  result=result, final_error_rad=round(error, 5),
                  reached=bool(result == "succeeded" and error <= cfg.demo.goal_tolerance_rad))
    return record


def wait_for_services(client: RobonavClient, stack: Stack) -> set[str]:
    """Wait until every service is alive; returns the missing ones (at once when one exited)."""
    deadline = time.monotonic() + SERVICE_START_TIMEOUT_S
    missing = set(SERVICES)
    while missing and time.monotonic() < deadline and not stack.dead():
        missing = client.wait_for_services(missing, min(5.0, deadline - time.monotonic()))
    return missing


def run_demo(cfg: RobonavConfig, config_path: Path, seed: int, *, view_port: int | None = None,
             snapshot: Path | None = None) -> dict[str, Any]:
    """`view_port`: also run `robonav view` there and keep everything up after the goals until
    Ctrl-C; `snapshot`: write a PNG of the final scene (see `robonav view --snapshot`)."""
    started = time.monotonic()
    truth = true_scene(cfg)
    stack = Stack(cfg, str(config_path), view_port=view_port)
    summary: dict[str, Any] = {"seed": seed, "goals": [], "goal_count": len(cfg.demo.goals_rad)}
    try:
        with open_session(cfg.zenoh) as session:
            client = RobonavClient(session, cfg.cell)
            missing = wait_for_services(client, stack)
            if missing:
                raise RuntimeError(f"services not up after {SERVICE_START_TIMEOUT_S:.0f} s: {sorted(missing)}; exited: {stack.dead()}")
            summary["services_alive_s"] = round(time.monotonic() - started, 2)
            # A complete map, not just a first one: the planner refuses one that is still being
            # built (OCCUPANCY_INCOMPLETE), and so would the first plan.
            if not client.wait_for(lambda: client.joint_state is not None and map_is_complete(client, cfg),
                                   cfg.demo.first_map_timeout_s):
                raise RuntimeError(f"no complete occupancy map within {cfg.demo.first_map_timeout_s:.0f} s")
            summary["first_map_s"] = round(time.monotonic() - started, 2)
            with Interrupt() as interrupt:
                for index, goal in enumerate(cfg.demo.goals_rad):
                    # Plan on a map taken with the arm at rest, so no trace of its motion remains.
                    at_rest = time.time()
                    client.wait_for(lambda: client.occupancy is not None and client.occupancy.stamp > at_rest, 5.0)
                    if interrupt.is_set():
                        break
                    try:
                        record = run_goal(client, truth, cfg, index, np.asarray(goal, float), seed, interrupt)
                    except QueryFailed as exc:
                        record = {"index": index, "reached": False, "error": str(exc)}
                    log.info("goal %d: %s", index, record)
                    summary["goals"].append(record)
                    if interrupt.is_set():
                        break
            summary["interrupted"] = interrupt.is_set()
            contacts = client.contacts()
            if isinstance(contacts, ErrorReply):
                raise RuntimeError(f"contacts query failed: {contacts.code}: {contacts.message}")
            checks = [g["execute_check_ms"] for g in summary["goals"] if g.get("execute_check_ms") is not None]
            summary["execute_check_ms_median"] = round(float(np.median(checks)), 2) if checks else None
            summary.update(contacts=contacts.contact_count, contact_pairs=list(contacts.pairs),
                           min_obstacle_distance_m=None if contacts.min_distance_m is None else round(contacts.min_distance_m, 4))
            if snapshot is not None:
                summary.update(snapshot_view(cfg, snapshot))
            if view_port is not None and not summary["interrupted"]:
                log.warning("demo done; the view stays on http://127.0.0.1:%d until Ctrl-C", view_port)
                stop_on_signals(signal.SIGINT, signal.SIGTERM).wait()
            client.close()
    finally:
        summary["service_exit_codes"] = stack.close()
    summary["reached"] = sum(1 for g in summary["goals"] if g.get("reached"))
    summary["wall_time_s"] = round(time.monotonic() - started, 2)
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="robonav demo", description=__doc__)
    parser.add_argument("--config", help="YAML config file (default: the packaged configs/default.yaml)")
    parser.add_argument("--robot", metavar="FILE",
                        help="run this robot (a robot file, or a config whose robot section is taken): the cell is "
                             "placed for its reach and goals are drawn for it")
    parser.add_argument("--seed", type=int, default=0,
                        help="seeds the planner's sampler and shortcutting (and the goals drawn with --robot)")
    parser.add_argument("--json", dest="json_path", help="also write the summary to this file")
    parser.add_argument("--view", action="store_true", help="also serve the live 3D view; stay up until Ctrl-C")
    parser.add_argument("--view-port", type=int, default=8080, help="port of the view (default %(default)s)")
    parser.add_argument("--snapshot", metavar="OUT.png", help="write a picture of the final scene (needs chromium)")
    add_logging_arguments(parser, "WARNING")
    args = parser.parse_args(argv)
    setup_logging(args.log_level, args.log_format)
    source = Path(args.config) if args.config else default_config_path()
    with tempfile.TemporaryDirectory(prefix="robonav-demo-") as tmp:
        try:
            if args.robot:
                config_path = robot_config(source, Path(args.robot), args.seed, Path(tmp))
            else:
                config_path = write_seeded_config(source, args.seed, Path(tmp))
            cfg = load_config(config_path)
        except (ConfigError, OSError, ValueError, yaml.YAMLError) as exc:
            log.error("%s", exc)
            return 2
        if len(cfg.demo.goals_rad) == 0:
            log.error("%s: demo.goals_rad is empty", source)
            return 2
        try:
            summary = run_demo(cfg, config_path, args.seed, view_port=args.view_port if args.view else None,
                               snapshot=Path(args.snapshot) if args.snapshot else None)
        except RuntimeError as exc:
            log.error("demo failed: %s", exc)
            return 1
    text = json.dumps(summary, indent=2)
    print(text)
    if args.json_path:
        Path(args.json_path).write_text(text + "\n", encoding="utf-8")
    if summary.get("interrupted"):
        return EXIT_INTERRUPTED
    ok = summary["reached"] == summary["goal_count"] and summary["contacts"] == 0 and "snapshot_error" not in summary
    return 0 if ok else 1
