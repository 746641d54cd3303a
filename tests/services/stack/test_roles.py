"""Roles: each identity of `configs/security/router-acl.json5` sends only what its role allows.

A real `robonav router` with the committed ACL config and real client sessions, one login per
role (`client-<role>.json5`): every role tries every publication, every request, serving every
other service's requests and holding every other service's liveliness token
(`robonav.services.stack.roles.probe_roles`); a forbidden message must reach no one, an allowed
one must get through. Then the four services run under their own identities and an operator
plans and executes through them while a viewer watches and may not.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from robonav.pipeline.wire.messages import JointState, Occupancy
from robonav.services.common import declare_latched_subscriber
from robonav.services.config import load_config
from robonav.services.stack.roles import (
    ASKS,
    PUBLISHES,
    ROLES,
    SERVES,
    all_published,
    all_served,
    logins,
    probe_roles,
)

from ..conftest import write_config
from .secure_cell import DEV_ENV, make_cell_dir, router, running, session

pytestmark = [pytest.mark.e2e, pytest.mark.skipif(shutil.which("openssl") is None, reason="gen_certs.sh needs the openssl command")]


@pytest.fixture(scope="module")
def cell_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_cell_dir(tmp_path_factory.mktemp("roles"))


def test_every_role_sends_only_what_it_may(cell_dir: Path) -> None:
    with router(cell_dir, "router-acl.json5") as port:
        results = probe_roles(logins(cell_dir, f"tls/localhost:{port}"))
    print(json.dumps({role: {k: v for k, v in r.summary().items() if k != "leaks"} for role, r in results.items()}))
    assert set(results) == set(ROLES)
    for role, probe in results.items():
        assert probe.leaks == [], f"{role}: forbidden messages got through: {probe.leaks}"
        assert probe.forged_delivered == 0
        # Everything the role may do got through, so the zeros above are the router's doing.
        assert probe.allowed_puts_missing == 0 and probe.allowed_queries_unanswered == 0, probe.summary()
        # It tried every key, and the forbidden ones are exactly those outside its role.
        assert probe.puts_tried == len(all_published()) and probe.queries_tried == len(all_served())
        assert probe.puts_forbidden == len(all_published()) - len(PUBLISHES.get(role, ()))
        assert probe.queries_forbidden == len(all_served()) - len(ASKS.get(role, ()))
        assert probe.impersonations_tried == len(all_served()) - len(SERVES.get(role, ()))
    assert results["viewer"].puts_forbidden == len(all_published())
    assert results["viewer"].queries_forbidden == len(all_served())


@pytest.fixture(scope="module")
def secured_stack(cell_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path]]:
    """The router and the four services, each logged in as itself; yields the endpoint and the YAML config."""
    with router(cell_dir, "router-acl.json5") as port:
        endpoint = f"tls/localhost:{port}"
        config = write_config(cell_dir, "stack.yaml", zenoh={"connect": [endpoint]}, sim={"follow": "kinematic"},
                              cameras={"width": 160, "height": 120},
                              # A loaded machine delays maps; this tests access, not freshness.
                              planner={"occupancy_max_age_s": 60.0})
        services = ("sim", "perception", "planner", "executor")
        with running(["serve", "sim", "--config", str(config), "--zenoh-config", "client-sim.json5"], cell_dir), \
                running(["serve", "perception", "--config", str(config), "--zenoh-config", "client-perception.json5"],
                        cell_dir), \
                running(["serve", "planner", "--config", str(config), "--zenoh-config", "client-planner.json5"],
                        cell_dir), \
                running(["serve", "executor", "--config", str(config), "--zenoh-config", "client-executor.json5"],
                        cell_dir):
            with session(cell_dir, endpoint, "client-viewer.json5") as watcher:
                alive = _wait_alive(watcher, services, 120.0)
                assert alive >= set(services), f"services alive: {alive}"
            yield endpoint, config


def _wait_alive(s: zenoh.Session, services: tuple[str, ...], timeout_s: float) -> set[str]:
    deadline = time.monotonic() + timeout_s
    alive: set[str] = set()
    while time.monotonic() < deadline and not alive >= set(services):
        alive = {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in s.liveliness().get("robonav/arm0/alive/*", timeout=1.0)
                 if r.ok is not None}
        time.sleep(0.2)
    return alive


def plan_command(config: Path, zenoh_config: str, goal: list[float], *extra: str) -> list[str]:
    return [sys.executable, "-m", "robonav.services.cli", "plan", "--config", str(config), "--zenoh-config",
            zenoh_config, "--timeout", "60", "--goal", *map(str, goal), *extra]


def test_the_services_run_under_their_own_identities(cell_dir: Path, secured_stack: tuple[str, Path]) -> None:
    endpoint, config = secured_stack
    cfg = load_config(config)
    goal = list(cfg.demo.goals_rad[0])
    env = {**os.environ, **DEV_ENV}
    # The viewer sees the robot and the latched map (through the map cache's history query) ...
    with session(cell_dir, endpoint, "client-viewer.json5") as viewer:
        seen: dict[str, object] = {}
        sub = viewer.declare_subscriber("robonav/arm0/robot/joint_states",
                                        lambda s: seen.setdefault("joint_state", JointState.from_wire(s.payload.to_bytes())))
        maps = declare_latched_subscriber(viewer, "robonav/arm0/perception/occupancy",
                                          lambda s: seen.setdefault("map", Occupancy.from_wire(s.payload.to_bytes())))
        deadline = time.monotonic() + 120.0
        while len(seen) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        sub.undeclare()
        maps.undeclare()
    assert set(seen) == {"joint_state", "map"}, seen
    # ... but may not plan: its query is dropped and `robonav plan` says nothing answered.
    done = subprocess.run(plan_command(config, "client-viewer.json5", goal, "--timeout", "3"), cwd=cell_dir, env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 3, done.stdout + done.stderr
    # The operator plans and executes through the planner and the executor, which run as themselves.
    for _ in range(20):  # the planner refuses to plan until perception's first map reached it
        done = subprocess.run(plan_command(config, "client-operator.json5", goal, "--execute"), cwd=cell_dir, env=env,
                              capture_output=True, text=True, timeout=180)
        record = json.loads(done.stdout)
        if record.get("stage") != "plan" or record.get("code") not in ("OCCUPANCY_MISSING", "OCCUPANCY_STALE"):
            break
    assert done.returncode == 0, done.stdout + done.stderr
    assert record["result"] == "succeeded" and np.allclose(record["goal_positions"], goal, atol=1e-3)
