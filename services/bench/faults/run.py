"""`robonav bench faults`: the live stack under faults, and whether it comes out of them.

Sections (run in this order; `--sections` picks some):

- `cold_start`: `robonav up` with empty caches (compiled kernels, per-robot tables): when all
  services are alive, and the first plan;
- `long_request`: a plan while an RRT* request with a very long budget runs;
- `overload`: clouds at twice the camera rate: memory growth per service, maps still published;
- `kill`: SIGKILL each service (and the router) while the arm moves: back within how long, the
  arm at rest within how long, contacts, and the next goal reached;
- `safety`: a path through an obstacle sent straight to `executor/execute`, and setpoints
  beyond the limits published on the bus;
- `fuzz`: mutated payloads over every query and subscribed key (last: it leaves the scene
  and the map in whatever state the payloads asked for).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.wire.messages import ErrorReply
from robonav.services.bench.faults import sections
from robonav.services.bench.faults.stack import LiveStack, write_campaign_config
from robonav.services.client import QueryFailed, RobonavClient
from robonav.services.config import load_config
from robonav.services.keys import SERVICES

SECTIONS = ("cold_start", "long_request", "overload", "kill", "safety", "fuzz")
KILLABLE = (*SERVICES, "router")


def add_parser(kinds: Any) -> None:  # noqa: ANN401 - argparse's private subparsers type
    faults = kinds.add_parser("faults", help="the live stack under faults: cold start, fuzzing, kills, overload",
                              description=__doc__.split("\n\n")[0])
    faults.add_argument("--seed", type=int, default=0, help="seeds the payload mutations and the planner")
    faults.add_argument("--fuzz", type=int, default=10_000, help="mutated payloads to send (default %(default)s)")
    faults.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated subset of {','.join(SECTIONS)}")
    faults.add_argument("--kill", default=",".join(KILLABLE), help="services to kill, in order (default: all and the router)")
    faults.add_argument("--overload-s", type=float, default=60.0, help="seconds of double-rate clouds (default 60)")
    faults.add_argument("--long-request-s", type=float, default=3600.0, help="budget of the long RRT* request [s]")
    faults.add_argument("--config", type=Path, default=None, help="YAML config (default: the packaged default)")
    faults.add_argument("--json", type=Path, default=None, help="write the report as JSON to this file")
    faults.add_argument("--logs", type=Path, default=None, help="keep the stack's logs in this folder")


def main(args: argparse.Namespace) -> int:
    chosen = [s.strip() for s in args.sections.split(",") if s.strip()]
    unknown = sorted(set(chosen) - set(SECTIONS))
    victims = [s.strip() for s in args.kill.split(",") if s.strip()]
    if unknown or set(victims) - set(KILLABLE) or args.fuzz < 0:
        print(f"robonav bench faults: unknown sections {unknown} or services {sorted(set(victims) - set(KILLABLE))}, "
              f"or a negative --fuzz", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="robonav-faults-") as tmp:
        workdir = Path(tmp)
        logs = args.logs or workdir
        logs.mkdir(parents=True, exist_ok=True)
        config_path = write_campaign_config(args.config, workdir, seed=args.seed)
        report = run(config_path, chosen, victims, args, logs)
    text = json.dumps(report, indent=2)
    print(text)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n", encoding="utf-8")
    return 0 if report["targets_met"] else 1


def run(config_path: Path, chosen: list[str], victims: list[str], args: argparse.Namespace, logs: Path) -> dict[str, Any]:
    started = time.monotonic()
    report: dict[str, Any] = {"seed": args.seed, "sections": chosen}
    goals = [np.asarray(g, dtype=np.float64) for g in load_config(config_path).demo.goals_rad]
    if len(goals) < 2:
        raise SystemExit("robonav bench faults needs a config with at least two demo.goals_rad")
    if "cold_start" in chosen:
        report["cold_start"] = _guarded(lambda: sections.cold_start(config_path, goals[0], seed=args.seed, log_dir=logs))
    rest = [s for s in chosen if s != "cold_start"]
    if rest:
        stack = LiveStack(config_path, log_path=logs / "stack.log")
        try:
            with stack.connect() as session:
                client = RobonavClient(session, stack.cfg.cell)
                try:
                    missing = client.wait_for_services(SERVICES, sections.ALIVE_TIMEOUT_S)
                    if missing:
                        report["error"] = f"services not alive: {sorted(missing)}"
                    else:
                        sections.first_plan(client, goals[0], seed=args.seed, timeout_s=sections.READY_TIMEOUT_S)
                        _run_sections(stack, client, rest, victims, goals, args, report, logs)
                finally:
                    client.close()
        finally:
            report["up_exit_code"] = stack.close()
    report["wall_s"] = round(time.monotonic() - started, 1)
    report["targets"] = targets(report)
    report["targets_met"] = all(report["targets"].values()) and "error" not in report
    return report


def _run_sections(stack: LiveStack, client: RobonavClient, chosen: list[str], victims: list[str],
                  goals: list[np.ndarray], args: argparse.Namespace, report: dict[str, Any], logs: Path) -> None:
    seed = args.seed
    steps: dict[str, Any] = {
        "long_request": lambda: sections.long_request(client, goals[0], goals[1], seed=seed,
                                                      planning_time_s=args.long_request_s),
        "overload": lambda: sections.overload(stack, client, seconds=args.overload_s),
        "kill": lambda: {name: _guarded(lambda name=name, k=k: sections.kill(
            stack, client, name, goals, seed=seed + 10 * k))
            for k, name in enumerate(victims)},
        "safety": lambda: safety(stack, client, goals, seed=seed, logs=logs),
        "fuzz": lambda: sections.fuzz(stack, client, args.fuzz, seed=seed),
    }
    for name in SECTIONS:
        if name in chosen and name in steps:
            report[name] = _guarded(steps[name])


def _guarded(section: Any) -> dict[str, Any]:  # noqa: ANN401 - a zero-argument callable
    """A section's report, or what went wrong in it: one failing section must not end the campaign."""
    try:
        return section()
    except Exception as exc:  # reported, and the campaign goes on with the next section
        return {"error": f"{type(exc).__name__}: {exc}"}


def safety(stack: LiveStack, client: RobonavClient, goals: list[np.ndarray], *, seed: int, logs: Path) -> dict[str, Any]:
    """A straight path through an obstacle sent to the executor (with and without the map stamp),
    and setpoints beyond the limits on the bus."""
    cfg = stack.cfg
    robot = RobotModel.from_config(cfg.robot)
    truth = CollisionWorld(robot, padding_m=0.0)
    truth.set_objects(cfg.sim.objects)
    contacts_before = sections._contacts(client)
    refused = attempts = 0
    assert client.joint_state is not None
    start = client.joint_state.position.copy()
    through = [g for g in goals if not truth.motion_valid(start, g, 0.01)]
    for goal in through[:1]:
        for stamp in (None, client.occupancy.stamp if client.occupancy is not None else None):
            attempts += 1
            try:
                reply = client.execute(np.vstack([start, goal]), occupancy_stamp=stamp, timeout_s=30.0)
            except QueryFailed:
                continue
            if isinstance(reply, ErrorReply):
                refused += 1
                continue
            # Accepted: stop it before it reaches the obstacle, and count what happened anyway.
            client.stop()
            sections.wait_at_rest(client, timeout_s=10.0)
            sections.plan_and_execute(client, start, seed=seed)
    contacts_after = sections._contacts(client)
    setpoints = sections.bad_setpoints(client, tuple(cfg.robot.joint_names), robot.upper_limits_rad)
    roles = sections.forged(logs)
    return {"unsafe_execute_tried": attempts, "unsafe_execute_refused": refused,
            "contacts": None if contacts_before is None or contacts_after is None else contacts_after - contacts_before,
            "bad_setpoints_injected": setpoints["injected"], "bad_setpoints_followed": setpoints["followed"],
            "forged_tried": roles.get("forged_tried"), "forged_delivered": roles.get("forged_delivered"), "roles": roles}


def targets(report: dict[str, Any]) -> dict[str, bool]:
    """The issue's targets, per section that ran (a section that failed misses its target)."""
    out: dict[str, bool] = {}
    c = report.get("cold_start")
    if c is not None:
        out["cold_start"] = bool(c.get("first_plan_ok")) and c.get("alive_s") is not None and c["alive_s"] <= 60.0
    f = report.get("fuzz")
    if f is not None:
        out["fuzz"] = "error" not in f and f["crashes"] == 0 and f["unstructured"] == 0 and f["no_reply"] == 0 \
            and f["alive_after"]
    for name, k in report.get("kill", {}).items():
        if name == "error":
            out["kill"] = False
            continue
        out[f"kill_{name}"] = (k.get("restarted_s") is not None and k["restarted_s"] <= 10.0 and k.get("contacts") == 0
                               and k.get("next_goal_reached") is True
                               and (name != "executor" or (k.get("arm_at_rest_s") is not None and k["arm_at_rest_s"] <= 1.0)))
    o = report.get("overload")
    if o is not None:
        out["overload"] = "error" not in o and o["maps_published"] > 0 and all(v <= 10.0 for v in o["rss_growth_pct"].values())
    r = report.get("long_request")
    if r is not None:
        out["long_request"] = "error" not in r and r["second_plan"] == "ok" and r["second_plan_s"] <= 2.0
    s = report.get("safety")
    if s is not None:
        out["safety"] = ("error" not in s and s["unsafe_execute_refused"] == s["unsafe_execute_tried"] > 0
                         and s["contacts"] == 0 and s["bad_setpoints_followed"] == 0
                         and s.get("forged_delivered") in (0, None))
    return out
