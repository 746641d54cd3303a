"""Ready means ready: `robonav precompile` fills the compile cache (outside the source tree), and
after the services' warm-ups a first real request compiles nothing.

Each check runs in a fresh interpreter: in this one, other tests have long compiled everything."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from ...conftest import NUMBA_CACHE_DIR, REPO_ROOT

FIRST_REQUESTS = r'''
import json
from robonav.services.cli import use_numba_cache_dir
use_numba_cache_dir()
import numpy as np
from robonav.pipeline.perception.self_filter import perception_filters
from robonav.pipeline.planning.motion_planner import PlanProblem
from robonav.pipeline.robot.model import RobotModel
from robonav.pipeline.sim.world import SimWorld
from robonav.pipeline.perception.maps.factory import make_occupancy_map
from robonav.pipeline.trajectory.path_guard import PathGuard
from robonav.pipeline.wire.messages import DepthImage, Occupancy, PointCloud
from robonav.pipeline.perception.depth import points_from_depth
from robonav.services.config import load_config, perceived_world_from_camera
from robonav.services.perception.frames import camera_frame
from robonav.services.perception.warm_up import warm_up_perception
from robonav.services.planner.plan_worker import PlanWorker
from robonav.services.planner.scene import SceneSnapshot
from robonav.services.planner.warm_up import warm_up_worker
from robonav.services.tools.precompile import numba_kernels
from numba.core.registry import CPUDispatcher
import sys

def signatures():
    out = {}
    for module_name, module in list(sys.modules.items()):
        if module_name.startswith("robonav.") and module is not None:
            for name, value in vars(module).items():
                if isinstance(value, CPUDispatcher):
                    out[f"{module_name}.{name}"] = {str(s) for s in value.signatures}
    return out

cfg = load_config()
robot = RobotModel.from_config(cfg.robot)
# What the services run before they declare themselves alive.
worker = PlanWorker.create(robot, cfg.robot.padding_m, cfg.planner)
warm_up_worker(worker, seed=cfg.planner.seed)
filters = perception_filters(robot.link_hull_vertices, robot.static_link_names, cfg.perception, cfg.robot.padding_m)
warm_up_perception(cfg, robot, *filters)
guard = PathGuard(robot, padding_m=cfg.robot.padding_m, inflation_m=cfg.perception.inflation_m,
                  edge_resolution_rad=cfg.planner.edge_resolution_rad)
guard.warm_up(robot.home_position_rad)
compiled_by_warm_up = sum(c for c, _ in numba_kernels().values())
before = signatures()

# The first real requests: the demo scene rendered by the sim, as a depth image and as a cloud...
camera = cfg.cameras[0]
sim = SimWorld(cfg.robot, camera, cfg.sim)
sim.set_joint_positions(robot.home_position_rad)
frame = sim.render_depth()
labels = np.zeros(frame.depth_m.shape, dtype=np.int32)
home = robot.home_position_rad
occupancy_map = make_occupancy_map(cfg.perception)
for message in (DepthImage(stamp=1.0, camera_id=camera.camera_id, intrinsics=frame.intrinsics, depth_m=frame.depth_m,
                           labels=labels, label_names={0: "robot"}),
                PointCloud(stamp=2.0, camera_id=camera.camera_id, intrinsics=frame.intrinsics,
                           points=points_from_depth(frame.depth_m, frame.intrinsics).astype(np.float32))):
    decoded = type(message).from_wire(message.to_wire())
    occupancy_map.integrate(camera_frame(decoded, camera, perceived_world_from_camera(camera), robot, home),
                            self_filter=filters[0], clear_filter=filters[1])
occupancy = Occupancy.from_wire(Occupancy(stamp=2.0, resolution_m=cfg.perception.resolution_m,
                                          octomap_binary=occupancy_map.planning_binary(),
                                          occupied_centers_m=occupancy_map.occupied_centers_m().astype(np.float32)).to_wire())
# ...planned on, with the scene's objects too, to the demo's goals...
goals = [np.asarray(g, float) for g in cfg.demo.goals_rad]
worker.sync(SceneSnapshot(1, tuple(cfg.sim.objects), ()), occupancy)
outcomes = [worker.planner.plan(PlanProblem(start_rad=a, goals_rad=b, seed=1)).status.name
            for a, b in zip([home, *goals[:-1]], goals)]
worker.sync(SceneSnapshot(2, (), ()), None)
outcomes.append(worker.planner.plan(PlanProblem(start_rad=goals[0], goals_rad=goals[1], seed=1)).status.name)
# ...and watched by the executor's path guard.
guard.start(occupancy.occupied_centers_m[:10], occupancy.resolution_m)
guard.update_map(occupancy.occupied_centers_m, occupancy.resolution_m)
guard.blocked_state(np.array([home, goals[0]]), home)
after = signatures()
print(json.dumps({"compiled_by_warm_up": compiled_by_warm_up, "outcomes": outcomes,
                  "new": {k: sorted(after[k] - before.get(k, set())) for k in after if after[k] - before.get(k, set())}}))
'''


def test_precompile_fills_the_cache_outside_the_source_tree() -> None:
    run = subprocess.run([sys.executable, "-m", "robonav.services.cli", "precompile"], capture_output=True, text=True,
                         timeout=1800, env=dict(os.environ))
    assert run.returncode == 0, run.stderr[-2000:]
    summary = json.loads(run.stdout)
    assert summary["cache_dir"] == str(NUMBA_CACHE_DIR) and summary["kernels"] >= 15 and summary["cache_files"] > 0
    in_tree = [p for folder in ("pipeline", "services") for p in (REPO_ROOT / folder).rglob("*.nb[ic]")]
    assert not in_tree, f"compiled kernels in the source tree: {in_tree[:3]}"


def test_after_the_warm_ups_a_first_request_compiles_nothing() -> None:
    test_precompile_fills_the_cache_outside_the_source_tree()  # the services start after `make setup` precompiled
    run = subprocess.run([sys.executable, "-c", FIRST_REQUESTS], capture_output=True, text=True, timeout=600,
                         env=dict(os.environ))
    assert run.returncode == 0, run.stderr[-3000:]
    report = json.loads(run.stdout.strip().splitlines()[-1])
    assert report["compiled_by_warm_up"] == 0, report  # everything came from the cache precompile filled
    assert report["new"] == {}, f"compiled during the first requests, not in a warm-up: {report['new']}"
    assert report["outcomes"][:3].count("SUCCESS") >= 2, report["outcomes"]
