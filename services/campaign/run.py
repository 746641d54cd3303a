"""`robonav campaign`: the live services end to end on many random scenes, with noise on.

    robonav campaign --scenes N --seed S [--json FILE] [--goals-per-scene G] [--moving M]
                     [--source clutter|mbm|yaml] [--scene-dir DIR] [--no-noise] [--config FILE]
                     [--extra-cameras FILE|none] [--robot FILE]

One stack runs the whole campaign; scenes are swapped in at run time (`sim/objects set`,
`perception/clear`). Each scene gets goals drawn so that a camera-built map can allow them
(some only by a detour): every link at the goal keeps padding + inflation + a voxel diagonal
from the true objects, the most the map can add around a surface. A reference planner on the
truth with that margin decides which goals are feasible. In `M` scenes a box slides onto the
path as the arm starts: it rests early enough to be avoided, where a camera sees it, and never
within that margin of the goal. Those goals are driven at `--moving-speed` (0.5) of the
campaign's speed, and goals and plans are drawn again until the path leaves room for such a
box. A goal the box makes unreachable for the reference planner counts as unreachable, not as
a failure. With `--robot FILE` the campaign runs that robot: the cell (cameras, clutter table,
workspace) is placed for its reach and goals are drawn for it. Reports contacts (pybullet ground
truth), setpoint limit violations, the smallest true clearance, planning time, perception
latency and replans. Exit code 0 when nothing touched and no setpoint broke a limit.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml
import zenoh
from tqdm import tqdm

from robonav.pipeline.config import ConfigError
from robonav.pipeline.evaluation.mbm import parse_mbm
from robonav.pipeline.perception.map_readiness import map_complete
from robonav.pipeline.planning.ompl_planners import seed_ompl_once
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.sim.scenes import Scene, clutter_scene, mbm_scenes, scene_from_mapping
from robonav.pipeline.wire.messages import ErrorReply, SimStatsRequest, SimStatsResponse
from robonav.services.campaign.monitors import Monitors
from robonav.services.campaign.scene import MOVING_SPEED_FACTOR, SceneRunner
from robonav.services.campaign.stops import stopped_by_fill_below, stopped_for_nothing
from robonav.services.client import QueryFailed, RobonavClient
from robonav.services.common import add_logging_arguments, open_session, setup_logging
from robonav.services.config import RobonavConfig, default_config_path, load_config
from robonav.services.keys import SERVICES
from robonav.services.stack.robot_cell import read_robot, with_robot, write_config
from robonav.services.stack.up import Stack
from robonav.services.tools.stop import Interrupt, stop_after_interrupt

log = logging.getLogger("robonav.campaign")

SERVICE_START_TIMEOUT_S = 90.0
EXTRA_CAMERAS_NAME = "campaign_cameras.yaml"
MAX_FAILED_SCENES_IN_A_ROW = 3
BOX_AT_REST_M = 0.01
"""A slid box this close to its resting place had arrived when a plan was checked against it."""


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="robonav campaign", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, required=True, help="number of scenes")
    parser.add_argument("--seed", type=int, default=0, help="seeds scenes, goals, noise and planning")
    parser.add_argument("--json", dest="json_path", help="write the full report to this file")
    parser.add_argument("--config", help="YAML config (default: the packaged default.yaml)")
    parser.add_argument("--robot", metavar="FILE",
                        help="run this robot (a robot file, or a config whose robot section is taken), the cell "
                             "placed for its reach")
    parser.add_argument("--goals-per-scene", type=int, default=2)
    parser.add_argument("--first-scene", type=int, default=0,
                        help="start at this scene number (the same scenes and goals as in a full run)")
    parser.add_argument("--moving", type=int, default=None,
                        help="scenes with a box sliding onto the path (default: a tenth of the scenes)")
    parser.add_argument("--source", choices=("clutter", "mbm", "yaml"), default="clutter",
                        help="procedural clutter (sim.clutter), MotionBenchMaker files or YAML scene files")
    parser.add_argument("--scene-dir", help="directory of mbm-primitives/1 JSON or YAML scene files")
    parser.add_argument("--no-noise", action="store_true", help="cameras without the noise model")
    parser.add_argument("--extra-cameras", default=str(default_config_path().with_name(EXTRA_CAMERAS_NAME)),
                        help="YAML file whose `cameras` list is added to the config's (default: the packaged "
                             f"{EXTRA_CAMERAS_NAME}, a second camera behind the robot); 'none' adds none")
    parser.add_argument("--no-guard", action="store_true",
                        help="do not stop and replan when a new map blocks the rest of the path")
    parser.add_argument("--velocity-scaling", type=float, help="scaling of velocity and acceleration limits")
    parser.add_argument("--moving-speed", type=float, default=MOVING_SPEED_FACTOR,
                        help="a moving scene's goal is driven at this share of the campaign's speed "
                             f"(default {MOVING_SPEED_FACTOR}: at full speed few paths leave room for the box)")
    add_logging_arguments(parser, "WARNING")
    args = parser.parse_args(argv)
    if args.scenes < 1 or args.goals_per_scene < 1:
        parser.error("--scenes and --goals-per-scene must be >= 1")
    if not 0 < args.moving_speed <= 1:
        parser.error("--moving-speed must be in (0, 1]")
    if args.source != "clutter" and not args.scene_dir:
        parser.error(f"--source {args.source} needs --scene-dir")
    return args


def campaign_config(source: Path, directory: Path, *, noise: bool, seed: int, extra_cameras: Path | None = None) -> Path:
    """The config for the campaign's stack: noise switched, no obstacles or scripts at start,
    the cameras of `extra_cameras` added, depth images when perception integrates them (no
    cloud to build and re-project)."""
    data = yaml.safe_load(source.read_text(encoding="utf-8")) or {}
    base = load_config(source)
    if extra_cameras is not None:
        extra = yaml.safe_load(extra_cameras.read_text(encoding="utf-8")) or {}
        if not isinstance(extra, dict) or set(extra) != {"cameras"} or not isinstance(extra["cameras"], list):
            raise ConfigError(str(extra_cameras), "<root>", "expected one key, `cameras`, holding a list")
        data["cameras"] = [*data.get("cameras", []), *extra["cameras"]]
    sim = data.setdefault("sim", {})
    sim["objects"] = []
    sim["motions"] = []
    sim["noise"] = {**(sim.get("noise") or {}), "enabled": noise, "seed": seed}
    data.setdefault("planner", {})["seed"] = seed
    if base.perception.clearing == "projection":
        data["cameras"] = [{**camera, "output": "depth"} for camera in data.get("cameras", [{}])]
    path = directory / "campaign-config.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    load_config(path)
    return path


def load_scenes(args: argparse.Namespace, cfg: RobonavConfig) -> list[Scene]:
    """The scenes in campaign order (seeded)."""
    rng = np.random.default_rng((args.seed, 1))
    if args.source == "clutter":
        return [clutter_scene(cfg.sim.clutter, np.random.default_rng((args.seed, i)), name=f"clutter-{i}")
                for i in range(args.first_scene, args.first_scene + args.scenes)]
    directory = Path(args.scene_dir)
    pool: list[Scene] = []
    if args.source == "mbm":
        for path in sorted(directory.glob("*.json")):
            pool += mbm_scenes(parse_mbm(json.loads(path.read_text(encoding="utf-8"))))
    else:
        for path in sorted(directory.glob("*.yaml")):
            pool.append(scene_from_mapping(yaml.safe_load(path.read_text(encoding="utf-8")), source=str(path)))
    if not pool:
        raise ValueError(f"no {args.source} scenes in {directory}")
    order = rng.permutation(len(pool))
    return [pool[order[i % len(pool)]] for i in range(args.first_scene, args.first_scene + args.scenes)]


def moving_scene_indices(scenes: int, moving: int) -> set[int]:
    """`moving` scene indices spread evenly over the campaign."""
    if moving <= 0:
        return set()
    return {int(i) for i in np.linspace(0, scenes - 1, min(moving, scenes)).round()}


def failed_scene(client: RobonavClient, index: int, scene: Scene, moving: bool, error: str) -> dict[str, Any]:
    """The record of a scene that could not be run to the end (its contacts still count)."""
    try:
        contacts = client.contacts(reset=True)
    except QueryFailed:
        contacts = None
    ok = contacts is not None and not isinstance(contacts, ErrorReply)
    return {"index": index, "scene": scene.name, "objects": len(scene.objects), "moving": moving,
            "contacts": contacts.contact_count if ok else 0, "contact_pairs": list(contacts.pairs) if ok else [],
            "min_distance_m": contacts.min_distance_m if ok else None,
            "min_distance_pair": contacts.min_distance_pair if ok else None, "goals": [], "error": error}


def _percentiles(values: list[float], digits: int = 2) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p95": None, "max": None}
    p50, p95, top = np.percentile(values, [50, 95, 100])
    return {"p50": round(float(p50), digits), "p95": round(float(p95), digits), "max": round(float(top), digits)}


def summarize(scenes: list[dict[str, Any]], monitors: Monitors, cfg: RobonavConfig, args: argparse.Namespace,
              wall_s: float, sim_stats: SimStatsResponse | None) -> dict[str, Any]:
    goals = [g for s in scenes for g in s["goals"]]
    # Goals with a box sliding onto their path test safety; reachability is judged on the others.
    still = [g for g in goals if not g["moving"]]
    feasible = [g for g in still if g["feasible"]]
    planned_clearances = [g["plan_true_clearance_m"] for g in goals if g["plan_true_clearance_m"] is not None]
    moving = [s for s in scenes if s["moving"]]
    distances = [s["min_distance_m"] for s in scenes if s["min_distance_m"] is not None]
    padding = cfg.robot.padding_m
    box_arrived = [_box_arrived(p) for g in goals for p in g.get("plans_through_box", [])]
    stops = [stop for g in goals for stop in g.get("guard_stop_voxels", [])]
    summary: dict[str, Any] = {
        "robot": cfg.robot.name, "joint_names": list(cfg.robot.joint_names),
        "scenes": len(scenes), "seed": args.seed, "source": args.source, "noise": not args.no_noise,
        "guard": not args.no_guard, "goals": len(goals), "goals_feasible": len(feasible),
        "goals_reached": sum(g["reached"] for g in goals),
        "goals_reached_feasible": sum(g["reached"] for g in feasible),
        "goals_unreachable": len(still) - len(feasible),
        "goals_failed": sum(not g["reached"] for g in feasible),
        "reached_of_feasible": round(sum(g["reached"] for g in feasible) / len(feasible), 4) if feasible else None,
        "goals_with_detour": sum(g["detour"] for g in goals),
        "contacts": sum(s["contacts"] for s in scenes), "contact_scenes": sum(s["contacts"] > 0 for s in scenes),
        "contact_events": monitors.contact_begins, "contact_examples": monitors.contact_examples,
        "moving_scenes": len(moving), "moving_contacts": sum(s["contacts"] for s in moving),
        "moving_goals": sum(g["moving"] for g in goals), "intruders": sum(g.get("intruder", False) for g in goals),
        "moving_goals_reached": sum(g["reached"] for g in goals if g["moving"]),
        "moving_speed_factor": args.moving_speed,
        "start_escapes": sum(g.get("start_escapes", 0) for g in goals),
        "plans_through_box": sum(box_arrived), "plans_through_box_not_arrived": len(box_arrived) - sum(box_arrived),
        "limit_violations": monitors.limit_violations, "setpoints_checked": monitors.setpoints,
        "limit_violation_examples": monitors.violation_examples,
        "min_clearance_m": round(min(distances), 4) if distances else None,
        "padding_m": padding, "scenes_below_padding": sum(d < padding for d in distances),
        "closest_pairs": _count([s["min_distance_pair"] for s in scenes if s["min_distance_m"] is not None
                                 and s["min_distance_m"] < padding]),
        "planned_true_clearance_m": _percentiles(planned_clearances, 4) | {
            "min": round(min(planned_clearances), 4) if planned_clearances else None},
        "planned_paths_below_padding": sum(c < padding for c in planned_clearances),
        "planning_ms": _percentiles([ms for g in goals for ms in g["planning_ms"]]),
        "perception_latency_ms": _percentiles([s * 1e3 for s in monitors.perception_latency_s], 1),
        "replans": sum(g["replans"] for g in goals), "guard_stops": sum(g["guard_stops"] for g in goals),
        "guard_stops_for_nothing": sum(stopped_for_nothing(stop) for stop in stops),
        "guard_stops_fill_below": sum(stopped_by_fill_below(stop) for stop in stops),
        "executor_stops": sum(g.get("executor_stops", 0) for g in goals),
        "executor_faults": _count([code for g in goals for code in g.get("executor_faults", [])]),
        "executor_stop_after_frame_ms": _percentiles([s * 1e3 for g in goals for s in g.get("executor_stop_after_frame_s", [])], 1),
        "intruder_rest_to_executor_stop_ms": _percentiles(
            [g["executor_stop_after_rest_s"] * 1e3 for g in goals if g.get("executor_stop_after_rest_s") is not None], 1),
        "intruder_rest_to_guard_stop_ms": _percentiles(
            [g["guard_delay_s"] * 1e3 for g in goals if g.get("guard_delay_s") is not None], 1),
        "plan_errors": _count([e for g in goals for e in g["errors"]]),
        "wall_time_s": round(wall_s, 1), "scenes_per_hour": round(3600.0 * len(scenes) / max(wall_s, 1e-9), 1),
    }
    if sim_stats is not None:
        summary["sim"] = {"real_time_factor": round(sim_stats.real_time_factor, 4),
                          "step_lateness_ms": {"p50": round(sim_stats.step_lateness_ms_p50, 3),
                                               "p99": round(sim_stats.step_lateness_ms_p99, 3),
                                               "max": round(sim_stats.step_lateness_ms_max, 3)},
                          "dropped_time_s": round(sim_stats.dropped_time_s, 3),
                          "joint_state_period_ms_max": round(sim_stats.joint_state_period_ms_max, 2),
                          "render_ms_p50": {c.camera_id: round(c.render_ms_p50, 1) for c in sim_stats.cameras},
                          # The arm's own rules (`pipeline/sim/driver.py`), counted since the sim started (a
                          # stats reset leaves them); None from a sim that does not report them.
                          "setpoints_followed": sim_stats.setpoints_followed,
                          "setpoints_rejected": sim_stats.setpoints_rejected,
                          "setpoint_timeouts": sim_stats.setpoint_timeouts, "brakes": sim_stats.brakes}
    summary["per_scene"] = scenes
    return summary


def _box_arrived(through: dict[str, Any]) -> bool:
    """Whether a plan through the resting box (`GoalRecord.plans_through_box`) met the box: else
    the box was still away from its resting place (it had not slid there, or not yet), and the
    path crossed only the place it was sent to."""
    from_rest_m = through.get("box_from_rest_m")
    return from_rest_m is None or from_rest_m <= BOX_AT_REST_M


def _count(items: list[str]) -> dict[str, int]:
    out: dict[str, int] = {}
    for item in items:
        out[item] = out.get(item, 0) + 1
    return dict(sorted(out.items()))


def table(summary: dict[str, Any]) -> str:
    rows = [
        ("robot (joints)", f"{summary.get('robot')} ({len(summary.get('joint_names', []))})"),
        ("scenes (moving obstacle / box slid in)",
         f"{summary['scenes']} ({summary['moving_scenes']} / {summary.get('intruders', 0)})"),
        ("goals: feasible / unreachable", f"{summary['goals']}: {summary['goals_feasible']} / {summary['goals_unreachable']}"),
        ("reached (of feasible)", f"{summary['goals_reached_feasible']} / {summary['goals_feasible']}"
                                  f" ({100 * (summary['reached_of_feasible'] or 0):.1f} %)"),
        ("robot-obstacle contacts (moving scenes)", f"{summary['contacts']} ({summary['moving_contacts']})"),
        ("plans through the resting box (box not arrived)",
         f"{summary.get('plans_through_box', 0)} ({summary.get('plans_through_box_not_arrived', 0)})"),
        ("setpoint limit violations", f"{summary['limit_violations']} of {summary['setpoints_checked']}"),
        ("min true clearance / padding", f"{summary['min_clearance_m']} m / {summary['padding_m']} m"
                                         f" ({summary['scenes_below_padding']} scenes below)"),
        ("planning ms p50 / p95", f"{summary['planning_ms']['p50']} / {summary['planning_ms']['p95']}"),
        ("perception latency ms p50 / p95", f"{summary['perception_latency_ms']['p50']} / {summary['perception_latency_ms']['p95']}"),
        ("replans (guard stops, executor stops)",
         f"{summary['replans']} ({summary['guard_stops']}, {summary.get('executor_stops', 0)})"),
        ("guard stops on voxels no object explains (below one)",
         f"{summary.get('guard_stops_for_nothing', 0)} ({summary.get('guard_stops_fill_below', 0)})"),
        ("executor stop after frame ms p50 / p95", f"{summary.get('executor_stop_after_frame_ms', {}).get('p50')} / "
                                                   f"{summary.get('executor_stop_after_frame_ms', {}).get('p95')}"),
        ("executor watchdog stops", ", ".join(f"{code} {n}" for code, n in summary.get("executor_faults", {}).items())
                                    or "0"),
        ("arm: rejected setpoints / timeouts / brakes", _driver_row(summary.get("sim", {}))),
        ("sim: dropped s / step late max ms / joint-state gap max ms", _sim_loop_row(summary.get("sim", {}))),
        ("wall time", f"{summary['wall_time_s']} s ({summary['scenes_per_hour']} scenes/h)"),
        ("scenes failed / arm resets", f"{summary.get('scenes_failed', 0)} / {summary.get('resets', 0)}"),
    ]
    width = max(len(name) for name, _ in rows)
    return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)


def _driver_row(sim: dict[str, Any]) -> str:
    rejected = sim.get("setpoints_rejected")
    if rejected is None:
        return "not reported"
    reasons = ", ".join(f"{reason} {n}" for reason, n in rejected.items() if n)
    return f"{sum(rejected.values())}{f' ({reasons})' if reasons else ''} / {sim.get('setpoint_timeouts')} / {sim.get('brakes')}"


def _sim_loop_row(sim: dict[str, Any]) -> str:
    late_ms = sim.get("step_lateness_ms", {}).get("max")
    return f"{sim.get('dropped_time_s')} / {late_ms} / {sim.get('joint_state_period_ms_max')}"


def run_campaign(args: argparse.Namespace, cfg: RobonavConfig, config_path: Path, scenes: list[Scene]) -> dict[str, Any]:
    total = args.first_scene + args.scenes
    moving = moving_scene_indices(total, total // 10 if args.moving is None else args.moving)
    started = time.monotonic()
    # The campaign's own reference plans decide which goals are feasible: seed OMPL's sampler
    # (once per process, before any planner exists) so a campaign is reproducible.
    seed_ompl_once(args.seed)
    stack = Stack(cfg, str(config_path), log_level=args.log_level)
    records: list[dict[str, Any]] = []
    try:
        with open_session(cfg.zenoh) as session:
            client = RobonavClient(session, cfg.cell)
            monitors = Monitors(session, cfg, RobotModel.from_config(cfg.robot))
            missing = client.wait_for_services(SERVICES, SERVICE_START_TIMEOUT_S)
            if missing:
                raise RuntimeError(f"services not up: {sorted(missing)}; exited: {stack.dead()}")
            if not client.wait_for(lambda: client.joint_state is not None and client.occupancy is not None and map_complete(
                    client.occupancy.camera_frames, [c.camera_id for c in cfg.cameras], cfg.planner.occupancy_min_frames),
                    SERVICE_START_TIMEOUT_S):
                raise RuntimeError("no complete occupancy map or no joint state")
            runner = SceneRunner(cfg, client, goals_per_scene=args.goals_per_scene, guard=not args.no_guard,
                                 velocity_scaling=args.velocity_scaling, seed=args.seed,
                                 moving_speed_factor=args.moving_speed)
            _sim_stats(client, reset=True)
            progress = tqdm(total=len(scenes), desc="campaign", unit="scene", file=sys.stderr, mininterval=1.0)
            interrupted, aborted = False, ""
            try:
                failures_in_a_row = 0
                for index, scene in enumerate(scenes, start=args.first_scene):
                    if stack.dead():
                        aborted = f"a service exited: {stack.dead()}"
                        break
                    try:
                        records.append(runner.run(index, scene, moving=index in moving,
                                                  rng=np.random.default_rng((args.seed, index, 2))))
                        failures_in_a_row = 0
                    except (RuntimeError, QueryFailed) as exc:  # one scene's failure; the campaign goes on
                        log.error("scene %d (%s) failed: %s", index, scene.name, exc)
                        records.append(failed_scene(client, index, scene, index in moving, str(exc)))
                        failures_in_a_row += 1
                        if failures_in_a_row >= MAX_FAILED_SCENES_IN_A_ROW:
                            aborted = f"{failures_in_a_row} scenes in a row failed; last: {exc}"
                            break
                    progress.update(1)
                    progress.set_postfix(reached=sum(g["reached"] for r in records for g in r["goals"]),
                                         contacts=sum(r["contacts"] for r in records))
            except KeyboardInterrupt:  # Ctrl-C or SIGTERM: stop the arm, report the scenes that finished
                interrupted = True
                log.warning("interrupted after %d scenes: stopping the arm", len(records))
                with Interrupt() as again:  # a second Ctrl-C while braking: an emergency stop
                    again.count = 1
                    log.warning("stop: %s", stop_after_interrupt(client, again))
            finally:
                runner.close()
            progress.close()
            summary = summarize(records, monitors, cfg, args, time.monotonic() - started, _sim_stats(client))
            summary.update(interrupted=interrupted, aborted=aborted or None, resets=runner.resets,
                           scenes_failed=sum(1 for r in records if r.get("error")))
            monitors.close()
            client.close()
    finally:
        codes = stack.close()
    summary["service_exit_codes"] = codes
    return summary


def _sim_stats(client: RobonavClient, *, reset: bool = False) -> SimStatsResponse | None:
    """The sim's real-time statistics, or None (logged) when the query failed: they are not worth the campaign."""
    try:
        stats = client.query(client.keys.sim_stats, SimStatsRequest(reset=reset), SimStatsResponse, 10.0)
    except QueryFailed as exc:
        log.warning("sim/stats: %s", exc)
        return None
    if isinstance(stats, ErrorReply):
        log.warning("sim/stats: %s: %s", stats.code, stats.message)
        return None
    return stats


def _interrupt(signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    setup_logging(args.log_level, args.log_format)
    signal.signal(signal.SIGTERM, _interrupt)
    source = Path(args.config) if args.config else default_config_path()
    with tempfile.TemporaryDirectory(prefix="robonav-campaign-") as tmp:
        try:
            extra = None if args.extra_cameras == "none" else Path(args.extra_cameras)
            config_path = campaign_config(source, Path(tmp), noise=not args.no_noise, seed=args.seed, extra_cameras=extra)
            if args.robot:
                write_config(with_robot(load_config(config_path), read_robot(args.robot)), config_path)
            cfg = load_config(config_path)
            scenes = load_scenes(args, cfg)
        except (ConfigError, OSError, ValueError, yaml.YAMLError) as exc:
            log.error("%s", exc)
            return 2
        try:
            summary = run_campaign(args, cfg, config_path, scenes)
        except zenoh.ZError as exc:  # e.g. another stack already listens on the config's endpoint
            log.error("could not start the stack's router on %s: %s", cfg.zenoh.connect[0], exc)
            return 1
        except RuntimeError as exc:
            log.error("campaign failed: %s", exc)
            return 1
    print(table(summary))
    if args.json_path:
        Path(args.json_path).write_text(json.dumps(summary, indent=1) + "\n", encoding="utf-8")
    return 0 if summary["contacts"] == 0 and summary["limit_violations"] == 0 and not summary["aborted"] else 1
