"""Several planners on one key: best matching asks one, a race takes the first valid plan,
and a planner that dies (between or during requests) costs the client at most its timeout.

Real Zenoh on loopback: an in-process router and two real planner processes. One plans
without a map (`fast`); the other insists on an occupancy map that never comes (`refusing`),
so it answers every plan request at once with OCCUPANCY_MISSING. The tests that kill planners
come last in this file.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zenoh

from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.messages import (
    ErrorReply,
    PlanRequest,
    PlanResponse,
    SceneObjectSpec,
    SceneRequest,
    SceneResponse,
)
from robonav.services import health
from robonav.services.client import QueryFailed, RobonavClient, reply_message
from robonav.services.common import open_session
from robonav.services.config import ZenohConfig
from robonav.services.tools import plan as plan_cli

from ..conftest import free_port, write_config

pytestmark = pytest.mark.e2e

START_TIMEOUT_S = 90.0
HOME = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]
GOAL = [0.487, -0.233, -0.041, -2.359, -0.011, 2.127, -0.332]
# Hand down left of the default scene's pillar, then right of it (the demo's first two goals).
BESIDE_PILLAR = ([0.487, -0.233, -0.041, -2.359, -0.011, 2.127, -0.332],
                 [0.357, -0.324, -0.759, -2.352, -0.256, 2.099, -1.03])


@dataclass
class Planners:
    client: RobonavClient
    config: Path
    processes: dict[str, subprocess.Popen[bytes]]
    zids: dict[str, str]
    """Planner role → Zenoh id of its session, as replies carry it."""


def repliers(session: zenoh.Session, key: str, request: PlanRequest, target: zenoh.QueryTarget,
             timeout_s: float = 10.0) -> dict[str, object]:
    """Every reply to one query, by replier id: the decoded code ('ok' for a plan)."""
    out: dict[str, object] = {}
    started = time.monotonic()
    for reply in session.get(key, payload=request.to_wire(), target=target,
                             consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s):
        replier = str(reply.replier_id.zid) if reply.replier_id is not None else "zenoh"
        try:
            message = reply_message(reply, key, PlanResponse, timeout_s, started)
        except QueryFailed as exc:
            out[replier] = f"failed: {exc.reason}"
            continue
        out[replier] = message.code if isinstance(message, ErrorReply) else "ok"
    return out


def probe() -> PlanRequest:
    return PlanRequest(start_positions=np.array(HOME), goal_positions=np.array(GOAL), seed=0)


@pytest.fixture(scope="module")
def planners(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Planners]:
    directory = tmp_path_factory.mktemp("scale_out")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    fast = write_config(directory, "fast.yaml", zenoh={"connect": [endpoint]},
                        planner={"require_occupancy": False, "planner_id": "rrtconnect"})
    refusing = write_config(directory, "refusing.yaml", zenoh={"connect": [endpoint]},
                            planner={"require_occupancy": True, "first_map_wait_s": 0.0})
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    processes = {role: subprocess.Popen([sys.executable, "-m", "robonav.services.cli", "serve", "planner",
                                         "--config", str(path), "--log-level", "WARNING"])
                 for role, path in (("fast", fast), ("refusing", refusing))}
    session = open_session(ZenohConfig(connect=(endpoint,)))
    client = RobonavClient(session)
    try:
        # Ready when both answer: the fast one with a plan, the refusing one with its error.
        deadline = time.monotonic() + START_TIMEOUT_S
        codes: dict[str, object] = {}
        while len(codes) < 2 and time.monotonic() < deadline:
            assert all(p.poll() is None for p in processes.values()), "a planner exited"
            codes = repliers(session, client.keys.plan, probe(), zenoh.QueryTarget.ALL)
            if len(codes) < 2:
                time.sleep(0.3)
        assert sorted(codes.values()) == sorted(["ok", ErrorCode.OCCUPANCY_MISSING.value]), codes
        zids = {("fast" if code == "ok" else "refusing"): zid for zid, code in codes.items()}
        yield Planners(client, fast, processes, zids)
    finally:
        client.close()
        session.close()
        for proc in processes.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in processes.values():
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        router.close()


def assert_valid_plan(answer: object) -> PlanResponse:
    assert isinstance(answer, PlanResponse), answer
    np.testing.assert_allclose(answer.path[0], HOME, atol=1e-9)
    np.testing.assert_allclose(answer.path[-1], GOAL, atol=1e-9)
    return answer


def test_a_race_returns_the_first_valid_plan(planners: Planners) -> None:
    client = planners.client
    for seed in range(3):  # the refusing planner's error arrives first every time
        answer = client.plan(np.array(GOAL), start_positions=np.array(HOME), seed=seed, race=True, timeout_s=20.0)
        assert_valid_plan(answer)
        assert client.last_replier == planners.zids["fast"]


def test_best_matching_asks_exactly_one_planner(planners: Planners) -> None:
    session, key = planners.client.session, planners.client.keys.plan
    assert len(repliers(session, key, probe(), zenoh.QueryTarget.BEST_MATCHING)) == 1
    assert len(repliers(session, key, probe(), zenoh.QueryTarget.ALL)) == 2
    answer = planners.client.plan(np.array(GOAL), start_positions=np.array(HOME), timeout_s=20.0)
    if planners.client.last_replier == planners.zids["fast"]:
        assert_valid_plan(answer)
    else:
        assert isinstance(answer, ErrorReply) and answer.code == ErrorCode.OCCUPANCY_MISSING.value


def test_a_race_without_a_valid_plan_returns_an_error(planners: Planners) -> None:
    beyond_limits = np.array(GOAL) + np.array([0.0, 0.0, 0.0, 5.0, 0.0, 0.0, 0.0])
    answer = planners.client.plan(beyond_limits, start_positions=np.array(HOME), race=True, timeout_s=20.0)
    assert isinstance(answer, ErrorReply)
    assert answer.code in (ErrorCode.OUT_OF_JOINT_LIMITS.value, ErrorCode.OCCUPANCY_MISSING.value)


def test_robonav_plan_races_from_the_command_line(planners: Planners, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "plan.json"
    code = plan_cli.main(["--goal", *map(str, GOAL), "--start", *map(str, HOME), "--race", "--timeout", "20",
                          "--config", str(planners.config), "--json", str(out)])
    printed = json.loads(capsys.readouterr().out)
    assert code == plan_cli.EXIT_OK, printed
    assert printed == json.loads(out.read_text(encoding="utf-8"))
    assert printed["ok"] and printed["race"] and printed["replier"] == planners.zids["fast"]
    np.testing.assert_allclose(printed["goal_positions"], GOAL, atol=1e-4)


def test_the_health_check_sees_each_service_by_its_own_token(planners: Planners) -> None:
    argv = ["--config", str(planners.config), "--timeout", "2"]
    assert health.main(["planner", *argv]) == 0
    assert health.main(["executor", *argv]) == 1  # not running here
    assert health.main(["planner", "--instance", "another-container", *argv]) == 1
    assert health.service_from_cmdline(["/opt/robonav/bin/python", "/opt/robonav/bin/robonav", "serve", "planner",
                                        "--config", "/etc/robonav/a.yaml"]) == ("planner", ["--config", "/etc/robonav/a.yaml"])
    assert health.service_from_cmdline(["robonav", "router", "--listen", "tcp/0.0.0.0:7447"]) == \
        ("router", ["--listen", "tcp/0.0.0.0:7447"])
    assert health.service_from_cmdline(["/bin/sh"]) is None


def _kill(planners: Planners, role: str) -> None:
    proc = planners.processes[role]
    if proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)


def test_killing_one_planner_leaves_the_other_serving(planners: Planners) -> None:
    _kill(planners, "refusing")
    session, key = planners.client.session, planners.client.keys.plan
    deadline = time.monotonic() + 10.0  # the router drops the dead session's queryable when its link closes
    while len(repliers(session, key, probe(), zenoh.QueryTarget.ALL)) > 1 and time.monotonic() < deadline:
        time.sleep(0.1)
    for race in (False, True):
        answer = planners.client.plan(np.array(GOAL), start_positions=np.array(HOME), race=race, timeout_s=20.0)
        assert_valid_plan(answer)
        assert planners.client.last_replier == planners.zids["fast"]


def test_a_planner_dying_mid_request_does_not_hang_the_client(planners: Planners) -> None:
    _kill(planners, "refusing")
    timeout_s = 15.0
    # The pillar blocks the straight motion between these goals, and RRT* optimises for all of
    # its 60 s: the planner is surely still working when it is killed.
    pillar = SceneObjectSpec(name="pillar", type="box", position_m=(0.5, 0.0, 0.45), size_m=(0.1, 0.1, 0.5))
    assert isinstance(planners.client.scene(SceneRequest(operation="add", objects=(pillar,))), SceneResponse)
    request = PlanRequest(start_positions=np.array(BESIDE_PILLAR[0]), goal_positions=np.array(BESIDE_PILLAR[1]),
                          planner_id="rrtstar", allowed_planning_time=60.0)
    killer = threading.Timer(1.0, _kill, args=(planners, "fast"))
    killer.start()
    started = time.monotonic()
    try:
        with pytest.raises(QueryFailed, match="died while handling the request"):
            planners.client.plan_request(request, timeout_s=timeout_s, race=True)
    finally:
        killer.join()
    assert time.monotonic() - started < timeout_s
    with pytest.raises(QueryFailed):  # and with nobody left, best matching fails at once
        planners.client.plan_request(probe(), timeout_s=timeout_s)
