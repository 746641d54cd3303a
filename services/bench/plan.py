"""`robonav bench plan`: the planner on MotionBenchMaker problems, every path re-checked on the meshes.

`robonav bench plan` runs the planner on MotionBenchMaker problems (`mbm-primitives/1` files,
see the shared benchmarks' FORMAT.md) and counts a problem as solved only when the planner
succeeded AND its path starts at the start, ends at the goal and passes a fine re-check:
every segment interpolated at <= 0.01 rad and every state checked with FCL against the
robot's collision MESHES (`pipeline/mesh_check.py`), not the hulls the planner plans with.

Timing is wall-clock around `MotionPlanner.plan` only (search, simplification and the
planner's own re-validation); building the collision world or the occupancy map is setup.
The planning thread's CPU time is reported beside it (`median_cpu_ms`): on a shared machine
the wall time also holds the time the planner waited for a CPU.

This file reads the problem files, runs the pure core and prints; no algorithm lives here.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TextIO

import numpy as np

from robonav.pipeline.collision.world import CollisionWorld
from robonav.pipeline.evaluation.mbm import MbmProblem, MbmProblemSet, mbm_robot_config, parse_mbm
from robonav.pipeline.evaluation.mesh_check import FINE_STEP_RAD, MeshCollisionChecker
from robonav.pipeline.perception.config import PerceptionConfig
from robonav.pipeline.planning.config import PlannerConfig
from robonav.pipeline.planning.metrics import path_length_rad
from robonav.pipeline.planning.motion_planner import MotionPlanner, PlanProblem
from robonav.pipeline.planning.ompl_planners import seed_ompl_once
from robonav.pipeline.planning.result import PlanStatus
from robonav.pipeline.robot.config import RobotConfig
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.scene import SceneObject
from robonav.services.bench.plan_maps import CAMERA_FRAMES, CLOUD_SPACING_M, CameraSetup, camera_map, cloud_map
from robonav.services.campaign.run import EXTRA_CAMERAS_NAME, campaign_config
from robonav.services.config import ConfigError, default_config_path, load_config, load_robot_file

BENCH_EDGE_RESOLUTION_RAD = 0.02
"""Joint step of the planner's edge checks while it searches and shortcuts [rad]."""
BENCH_PATH_CHECK_RESOLUTION_RAD = FINE_STEP_RAD
"""The planner re-checks the path it returns as finely as the benchmark's re-check, so a good
planner loses no paths to it."""
SUMMARY_KEYS = ("problems", "solved", "solved_pct", "median_ms", "p95_ms", "median_length", "invalid_paths",
                "median_cpu_ms", "solved_by_search")
PROGRESS_WIDTH = 30

SceneKind = Literal["primitives", "cloud", "camera"]


@dataclass(frozen=True)
class ProblemRecord:
    """The outcome of one benchmark problem.

    Attributes:
        family: Problem family.
        index: Problem number within the family.
        status: The planner's status value ('success', 'timeout', 'goal_invalid', ...).
        wall_ms: Wall-clock time of the `plan` call [ms].
        returned_path: The planner returned a path.
        path_valid: That path passed the fine mesh re-check (False when there is no path).
        length_rad: Joint-space length of the returned path, or None [rad].
        detail: The planner's detail, or the re-check's reason for rejecting the path.
        cpu_ms: CPU time of the calling thread during the `plan` call [ms]; beside the wall
            time it tells planning work from waiting on a busy machine (a `race` runs in
            child processes, whose CPU time is not in it).
    """

    family: str
    index: int
    status: str
    wall_ms: float
    returned_path: bool
    path_valid: bool
    length_rad: float | None
    detail: str
    cpu_ms: float | None = None
    search: str = ""
    """Which search found the path (`PlanOutcome.search`): on a map, "surface" means no path
    that keeps the map's clearance was found in time."""

    @property
    def solved(self) -> bool:
        return self.returned_path and self.path_valid


def add_parser(kinds: Any) -> None:  # noqa: ANN401 - argparse's private subparsers type
    """`robonav bench plan` and its options."""
    plan = kinds.add_parser(
        "plan", help="plan MotionBenchMaker problems and re-check every path on the link meshes",
        description="Plan every problem of mbm-primitives/1 files; a problem is solved only when the "
                    "returned path passes a 0.01 rad re-check against the robot's collision meshes.")
    plan.add_argument("--problems", type=Path, required=True,
                      help="an mbm-primitives/1 JSON file, or a folder of them (every *.json)")
    plan.add_argument("--planner", default="rrtconnect", help="planner id (default: rrtconnect)")
    plan.add_argument("--time-limit", type=_positive_float, default=1.0, help="planning budget per problem [s]")
    plan.add_argument("--seed", type=int, default=0, help="seeds OMPL (once per process), shortcutting, clouds")
    plan.add_argument("--padding", type=_non_negative_float, default=0.0,
                      help="robot-vs-world padding for planning [m] (the re-check never pads)")
    plan.add_argument("--limit", type=_positive_int, default=None, help="first N problems of each family")
    plan.add_argument("--families", default=None, help="comma-separated family names (default: all)")
    plan.add_argument("--json", type=Path, default=None, help="write the summary as JSON to this file")
    plan.add_argument("--scene", choices=("primitives", "cloud", "camera"), default="primitives",
                      help="plan against the exact primitives, an occupancy map built from a sampled cloud, or "
                           "one built from the configured cameras' noisy depth images (the arm at the start)")
    plan.add_argument("--cloud-inflation", type=_non_negative_float, default=PerceptionConfig().inflation_m,
                      help="--scene cloud/camera: occupancy inflation [m] (default: the perception default)")
    plan.add_argument("--config", type=Path, default=None,
                      help="--scene camera: robonav YAML config whose cameras, sim noise and perception are used "
                           "(default: packaged)")
    plan.add_argument("--extra-cameras", default=str(default_config_path().with_name(EXTRA_CAMERAS_NAME)),
                      help="--scene camera: a YAML file whose `cameras` join the config's, as `robonav campaign` "
                           "adds them (default: the campaign's; 'none': the config's cameras alone)")
    plan.add_argument("--surface-allowance", type=_non_negative_float, default=PlannerConfig().surface_allowance_rad,
                      help="--scene cloud/camera: joint-space radius around the start and goal inside which the "
                           "map's inflation is released to the seen surface [rad] (0: inflation everywhere)")
    plan.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    plan.add_argument("--robot", type=Path, default=None,
                      help="robot file (`robonav robot init` writes one) whose joints the problems use; default: the Panda")


def main(args: argparse.Namespace) -> int:
    """`robonav bench plan`: run, print the table (and unsolved problems), write the JSON."""
    try:
        sets = select(load_problem_sets(args.problems), families=args.families, limit=args.limit)
        robot_base = load_robot_file(args.robot) if args.robot is not None else None
        if robot_base is not None and args.scene == "camera":
            raise ValueError("--scene camera renders the configured cell's cameras and robot; use it without --robot")
    except (OSError, ValueError) as exc:
        print(f"robonav bench plan: {exc}", file=sys.stderr)
        return 2
    progress = None if args.no_progress else sys.stderr
    try:
        # OMPL takes one seed per process, before its first sampler (see seed_ompl_once).
        seed_ompl_once(args.seed)
        perception = dataclasses.replace(PerceptionConfig(), inflation_m=args.cloud_inflation)
        cameras = None
        if args.scene == "camera":
            cfg = load_config(args.config or default_config_path())
            if args.extra_cameras != "none":
                with tempfile.TemporaryDirectory() as tmp:
                    cfg = load_config(campaign_config(args.config or default_config_path(), Path(tmp), noise=True,
                                                      seed=args.seed, extra_cameras=Path(args.extra_cameras)))
            perception = dataclasses.replace(cfg.perception, inflation_m=args.cloud_inflation)
            cameras = CameraSetup(cfg.cameras, dataclasses.replace(cfg.sim.noise, enabled=True))
        records = run_plan_benchmark(sets, planner_id=args.planner, time_limit_s=args.time_limit, seed=args.seed,
                                     padding_m=args.padding, scene=args.scene, progress=progress, robot=robot_base,
                                     surface_allowance_rad=args.surface_allowance, perception=perception,
                                     cameras=cameras)
    except (ValueError, ConfigError) as exc:
        print(f"robonav bench plan: {exc}", file=sys.stderr)
        return 2
    report = build_report(records, config={
        "problems_path": str(args.problems), "families": [s.family for s in sets], "limit": args.limit,
        "robot": robot_base.name if robot_base is not None else "panda",
        "robot_file": str(args.robot) if args.robot is not None else None,
        "planner": args.planner, "time_limit_s": args.time_limit, "seed": args.seed, "padding_m": args.padding,
        "scene": args.scene, "surface_allowance_rad": args.surface_allowance, "range_rad": PlannerConfig().range_rad, "edge_resolution_rad": BENCH_EDGE_RESOLUTION_RAD,
        "path_check_resolution_rad": BENCH_PATH_CHECK_RESOLUTION_RAD,
        "fine_check_step_rad": FINE_STEP_RAD, "fine_check_model": "link collision meshes (FCL BVH), unpadded",
        **({"cloud_spacing_m": CLOUD_SPACING_M, "occupancy_resolution_m": PerceptionConfig().resolution_m,
            "occupancy_inflation_m": args.cloud_inflation} if args.scene == "cloud" else {}),
        **({"cameras": [c.camera_id for c in cameras.cameras], "camera_frames": CAMERA_FRAMES,
            "extra_cameras": args.extra_cameras,
            "occupancy_resolution_m": perception.resolution_m, "occupancy_inflation_m": args.cloud_inflation}
           if cameras is not None else {}),
    })
    print(format_table(report))
    by_search = report["overall"]["solved_by_search"]
    if set(by_search) - {"", "sphere_first", "exact"}:
        print("solved by search: " + ", ".join(f"{mode or 'none'} {count}" for mode, count in by_search.items()))
    unsolved = [r for r in records if not r.solved]
    if unsolved:
        print("\nunsolved:")
        for r in unsolved:
            reason = f"path failed the mesh re-check ({r.search} search)" if r.returned_path else r.status
            print(f"  {r.family} #{r.index}: {reason} ({r.wall_ms:.0f} ms): {r.detail}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return 0


def load_problem_sets(path: Path) -> list[MbmProblemSet]:
    """Parse one `mbm-primitives/1` file, or every `*.json` in a folder (sorted by name).

    Raises:
        ValueError: no JSON file, invalid JSON, or a malformed document (names the file).
        OSError: a file cannot be read.
    """
    files = sorted(path.glob("*.json")) if path.is_dir() else [path]
    if not files:
        raise ValueError(f"no *.json problem files in {path}")
    sets = []
    for file in files:
        try:
            document = json.loads(file.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{file}: invalid JSON: {exc}") from exc
        try:
            sets.append(parse_mbm(document))
        except ValueError as exc:
            raise ValueError(f"{file}: {exc}") from exc
    return sets


def select(sets: list[MbmProblemSet], *, families: str | None, limit: int | None) -> list[MbmProblemSet]:
    """The sets of the named families (comma-separated; None = all), each cut to its first `limit` problems.

    Raises:
        ValueError: a named family is not among the loaded sets.
    """
    known = [s.family for s in sets]
    if families is not None:
        wanted = [f.strip() for f in families.split(",") if f.strip()]
        unknown = [f for f in wanted if f not in known]
        if unknown or not wanted:
            raise ValueError(f"--families: unknown family {unknown or families!r} (known: {', '.join(known)})")
        sets = [s for s in sets if s.family in wanted]
    if limit is not None:
        sets = [dataclasses.replace(s, problems=s.problems[:limit]) for s in sets]
    return sets


def run_plan_benchmark(
    sets: Sequence[MbmProblemSet],
    *,
    planner_id: str,
    time_limit_s: float,
    seed: int,
    padding_m: float,
    scene: SceneKind = "primitives",
    progress: TextIO | None = None,
    perception: PerceptionConfig | None = None,
    robot: RobotConfig | None = None,
    surface_allowance_rad: float | None = None,
    cameras: CameraSetup | None = None,
) -> list[ProblemRecord]:
    """Plan every problem, time each `plan` call and re-check every returned path on the meshes.

    Args:
        sets: Parsed problem families.
        planner_id: Planner the requests name.
        time_limit_s: Planning budget per problem [s].
        seed: Seeds the shortcutting and the synthetic clouds (OMPL is seeded by the caller).
        padding_m: Robot-vs-world padding of the planning world [m].
        scene: 'primitives' plans against the obstacles themselves; 'cloud' against an occupancy
            map of their sampled surfaces. The re-check always uses the primitives.
        progress: Stream for the progress bar, or None.
        perception: Occupancy map settings for `scene='cloud'`; None takes the defaults.
        robot: The robot the problems are for (their joint names must match); None is the Panda.
        surface_allowance_rad: The planner's `surface_allowance_rad`; None: its default.
        cameras: The cameras and their noise for `scene='camera'` (required then).

    Returns:
        One record per problem, in family and problem order.
    """
    total = sum(len(s.problems) for s in sets)
    planner_config = PlannerConfig(allowed_planning_time_s=time_limit_s,
                                   edge_resolution_rad=BENCH_EDGE_RESOLUTION_RAD,
                                   path_check_resolution_rad=BENCH_PATH_CHECK_RESOLUTION_RAD, seed=seed)
    if surface_allowance_rad is not None:
        planner_config = dataclasses.replace(planner_config, surface_allowance_rad=surface_allowance_rad)
    robots: dict[tuple[Any, ...], RobotModel] = {}
    records: list[ProblemRecord] = []
    # The file's own model first: its errors are the user's, and it names the URDF's links.
    base_config = robot
    known_links = RobotModel.from_config(base_config).link_names if base_config is not None else None
    for problem_set in sets:
        robot_config = mbm_robot_config(problem_set, padding_m=padding_m, base=base_config, known_links=known_links)
        key = (robot_config.joint_names, tuple(sorted(robot_config.fixed_joint_positions.items())),
               robot_config.allowed_collision_pairs)
        if key not in robots:
            robots[key] = RobotModel.from_config(robot_config)
            # The link meshes contacts are confirmed on (tens of ms a mesh) are built before any
            # plan is timed, as the planner service's warm-up builds them; every world shares them.
            CollisionWorld(robots[key], padding_m=padding_m).build_exact_shapes()
        robot = robots[key]
        checker = MeshCollisionChecker(robot)
        for problem in problem_set.problems:
            if progress is not None:
                _draw_progress(progress, len(records), total, f"{problem_set.family} #{problem.index}")
            records.append(_run_one(problem_set.family, problem, robot, checker, planner_config,
                                    planner_id=planner_id, seed=seed, padding_m=padding_m, scene=scene,
                                    perception=perception, cameras=cameras))
    if progress is not None:
        _draw_progress(progress, len(records), total, "done")
        progress.write("\n")
        progress.flush()
    return records


def _run_one(family: str, problem: MbmProblem, robot: RobotModel, checker: MeshCollisionChecker,
             planner_config: PlannerConfig, *, planner_id: str, seed: int, padding_m: float,
             scene: SceneKind, perception: PerceptionConfig | None, cameras: CameraSetup | None) -> ProblemRecord:
    world = CollisionWorld(robot, padding_m=padding_m)
    if scene == "cloud":
        cloud_map(problem.obstacles, seed=seed + problem.index, config=perception).apply(world)
    elif scene == "camera":
        if cameras is None:
            raise ValueError("scene 'camera' needs the cameras")
        camera_map(problem.obstacles, robot, cameras.cameras, cameras.noise, problem.start, seed=seed + problem.index,
                   config=perception).apply(world)
    else:
        world.set_objects(problem.obstacles)
    planner = MotionPlanner(robot, world, planner_config)
    goals = np.array(problem.goals_rad, dtype=np.float64)  # (G, n); MBM always has G = 1
    request = PlanProblem(start_rad=problem.start, goals_rad=goals[0] if len(goals) == 1 else goals,
                          planner_id=planner_id, allowed_planning_time_s=planner_config.allowed_planning_time_s,
                          seed=seed, simplify=True)
    t0, cpu0 = time.perf_counter(), time.thread_time()
    outcome = planner.plan(request)
    wall_ms = 1000.0 * (time.perf_counter() - t0)
    cpu_ms = 1000.0 * (time.thread_time() - cpu0)
    status = outcome.status.value if isinstance(outcome.status, PlanStatus) else str(outcome.status)
    if outcome.path is None:
        return ProblemRecord(family, problem.index, status, wall_ms, False, False, None, outcome.detail, cpu_ms)
    checker.set_objects(problem.obstacles)
    # A path may end at any goal of the set: hold it to the one it ends nearest to.
    reached = goals[int(np.argmin(np.max(np.abs(goals - outcome.path[-1]), axis=1)))]
    check = checker.check_path(outcome.path, start_rad=problem.start, goal_rad=reached)
    return ProblemRecord(family, problem.index, status, wall_ms, True, check.valid,
                         path_length_rad(outcome.path), outcome.detail if check.valid else check.detail, cpu_ms,
                         outcome.search)


def occupancy_of_objects(objects: Sequence[SceneObject], *, seed: int,
                         config: PerceptionConfig | None = None) -> tuple[bytes, float]:
    """The planning octree (inflated, octomap binary) of the objects' sampled surfaces and its
    resolution [m] (`plan_maps.cloud_map`)."""
    planning_map = cloud_map(objects, seed=seed, config=config)
    return planning_map.octomap_binary, planning_map.resolution_m


def summarize(records: Sequence[ProblemRecord]) -> dict[str, Any]:
    """The summary of some records, keyed by `SUMMARY_KEYS`.

    Times are over all problems (an unsolved one counts at its wall time); the length median
    is over solved problems only (None when there are none). `invalid_paths` counts returned
    paths that failed the fine re-check.
    """
    n = len(records)
    solved = [r for r in records if r.solved]
    wall = np.array([r.wall_ms for r in records], dtype=np.float64)
    lengths = [r.length_rad for r in solved if r.length_rad is not None]
    cpu = [r.cpu_ms for r in records if r.cpu_ms is not None]
    return {
        "problems": n,
        "solved": len(solved),
        "solved_pct": round(100.0 * len(solved) / n, 2) if n else 0.0,
        "median_ms": _rounded(float(np.median(wall))) if n else None,
        "p95_ms": _rounded(float(np.percentile(wall, 95))) if n else None,
        "median_length": _rounded(float(np.median(lengths)), 4) if lengths else None,
        "invalid_paths": sum(1 for r in records if r.returned_path and not r.path_valid),
        "median_cpu_ms": _rounded(float(np.median(cpu))) if cpu and len(cpu) == n else None,
        "solved_by_search": {mode: sum(1 for r in solved if r.search == mode)
                             for mode in sorted({r.search for r in solved})},
    }


def build_report(records: Sequence[ProblemRecord], *, config: dict[str, Any]) -> dict[str, Any]:
    """`{"overall": summary, "families": {name: summary}, "config": config}`, families in record order."""
    families: dict[str, list[ProblemRecord]] = {}
    for r in records:
        families.setdefault(r.family, []).append(r)
    return {"overall": summarize(records),
            "families": {name: summarize(rs) for name, rs in families.items()},
            "config": config}


def format_table(report: dict[str, Any]) -> str:
    """The report's summaries as a fixed-width text table, one row per family and one overall."""
    header = f"{'family':<18} {'problems':>8} {'solved':>6} {'solved %':>8} {'median ms':>10} {'p95 ms':>9} " \
             f"{'median len':>10} {'invalid':>7} {'median cpu ms':>13}"
    rows = [header, "-" * len(header)]
    items = [*report["families"].items(), ("overall", report["overall"])]
    for i, (name, s) in enumerate(items):
        if i == len(items) - 1:
            rows.append("-" * len(header))
        rows.append(f"{name:<18} {s['problems']:>8} {s['solved']:>6} {s['solved_pct']:>8.1f} "
                    f"{_cell(s['median_ms'], 1):>10} {_cell(s['p95_ms'], 1):>9} {_cell(s['median_length'], 3):>10} "
                    f"{s['invalid_paths']:>7} {_cell(s.get('median_cpu_ms'), 1):>13}")
    return "\n".join(rows)


def _draw_progress(stream: TextIO, done: int, total: int, label: str) -> None:
    filled = PROGRESS_WIDTH * done // total if total else PROGRESS_WIDTH
    # Pad with spaces so a shorter label overwrites the end of a longer one.
    stream.write(f"\r[{'#' * filled}{'.' * (PROGRESS_WIDTH - filled)}] {done}/{total} {label:<24}")
    stream.flush()


def _cell(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _rounded(value: float, digits: int = 2) -> float:
    return round(value, digits) if math.isfinite(value) else value


def _positive_float(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def _non_negative_float(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be an integer > 0, got {text}")
    return value


if __name__ == "__main__":
    sys.exit(main())
