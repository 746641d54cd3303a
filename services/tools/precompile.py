"""`robonav precompile`: compile every numba kernel into the compile cache, as the services would.

    robonav precompile [--config FILE] [--json FILE]

Runs each service's warm-up in this process, without Zenoh: the planner's plans (the sphere
broad phase, shortcutting), perception's synthetic frames (the projection map's voxel kernels)
and the executor's path guard (lane kinematics). A service started afterwards loads
its kernels from the cache instead of compiling them, which on a small machine takes minutes.
The cache is `NUMBA_CACHE_DIR`, by default `$XDG_CACHE_HOME/robonav/numba` or
`~/.cache/robonav/numba`, in a folder named after the kernel sources (see `services/cli.py`). `make setup` and the Docker image build run
this. Prints a JSON summary: the kernel signatures compiled now (0 when the cache was full)
and loaded from the cache; exit code 2 for a bad config.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

from robonav.pipeline.config import ConfigError
from robonav.services.cli import use_numba_cache_dir
from robonav.services.common import add_logging_arguments, setup_logging
from robonav.services.config import load_config

log = logging.getLogger("robonav.precompile")


def numba_kernels() -> dict[str, tuple[int, int]]:
    """Every numba kernel of the loaded robonav modules that compiles on its own (`module.name`),
    with how many signatures it compiled (not found in the cache) and loaded from the cache in
    this process. Kernels inlined into others (`inline="always"`) never compile on their own and
    are left out; a kernel called only from other kernels is compiled into them, and shows (0, 0)
    when they came from the cache."""
    from numba.core.registry import CPUDispatcher

    kernels: dict[str, tuple[int, int]] = {}
    for module_name, module in list(sys.modules.items()):
        if not module_name.startswith("robonav.") or module is None:
            continue
        for name, value in vars(module).items():
            if (isinstance(value, CPUDispatcher) and value.py_func.__module__ == module_name
                    and value.targetoptions.get("inline") != "always"):
                stats = value.stats
                kernels[f"{module_name}.{name}"] = (sum(stats.cache_misses.values()), sum(stats.cache_hits.values()))
    return kernels


def precompile(config_path: str | None) -> dict[str, Any]:
    """Warm every service's compiled code up in this process; returns the summary."""
    cache = use_numba_cache_dir()
    started = time.perf_counter()
    cfg = load_config(config_path)
    # Imported here: numba must see the cache directory first.
    from robonav.pipeline.perception.self_filter import perception_filters
    from robonav.pipeline.robot.model import RobotModel
    from robonav.pipeline.trajectory.path_guard import PathGuard
    from robonav.services.perception.warm_up import warm_up_perception
    from robonav.services.planner.plan_worker import PlanWorker
    from robonav.services.planner.warm_up import warm_up_worker

    robot = RobotModel.from_config(cfg.robot)
    warm_up_worker(PlanWorker.create(robot, cfg.robot.padding_m, cfg.planner), seed=cfg.planner.seed)
    # The projection map's kernels, whatever the config's map: the ray-casting one compiles nothing.
    perception = dataclasses.replace(cfg.perception, clearing="projection")
    filters = perception_filters(robot.link_hull_vertices, robot.static_link_names, perception, cfg.robot.padding_m)
    warm_up_perception(dataclasses.replace(cfg, perception=perception), robot, *filters)
    PathGuard(robot, padding_m=cfg.robot.padding_m, inflation_m=cfg.perception.inflation_m,
              edge_resolution_rad=cfg.planner.edge_resolution_rad).warm_up(robot.home_position_rad)
    kernels = numba_kernels()
    return {"cache_dir": str(cache), "seconds": round(time.perf_counter() - started, 1), "kernels": len(kernels),
            "compiled": sum(c for c, _ in kernels.values()), "loaded": sum(h for _, h in kernels.values()),
            "cache_files": sum(1 for _ in Path(cache).rglob("*.nbc")) if Path(cache).is_dir() else 0}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="robonav precompile", description=__doc__.splitlines()[0])
    parser.add_argument("--config", help="YAML config (default: the packaged default): its robot, cameras and maps")
    parser.add_argument("--json", help="also write the summary to this file")
    add_logging_arguments(parser, "WARNING")
    args = parser.parse_args(argv)
    setup_logging(args.log_level, args.log_format)
    try:
        summary = precompile(args.config)
    except ConfigError as exc:
        log.error("%s", exc)
        return 2
    text = json.dumps(summary, indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n", encoding="utf-8")
    return 0
