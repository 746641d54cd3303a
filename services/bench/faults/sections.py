"""The sections of `robonav bench faults`: each drives a live stack into one kind of fault and
measures how it comes out of it. Every function returns a JSON-ready dict."""

from __future__ import annotations

import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

import robonav.configs
from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.codes import ErrorCode
from robonav.pipeline.wire.messages import ErrorReply, PlanRequest, PlanResponse, PointCloud, Setpoint
from robonav.services.bench.faults.fuzz import run_fuzz, seed_messages
from robonav.services.bench.faults.stack import LiveStack, free_port, plan_and_execute, wait_at_rest, write_campaign_config
from robonav.services.client import QueryFailed, RobonavClient
from robonav.services.keys import SERVICES
from robonav.services.stack.roles import forged_delivered, logins, probe_roles
from robonav.services.table_cache import TABLE_CACHE_ENV

ALIVE_TIMEOUT_S = 120.0
READY_TIMEOUT_S = 90.0
"""Longest wait for a plan that the planner answers (a complete, fresh map) after a start or restart [s]."""
RETRYABLE = {ErrorCode.OCCUPANCY_MISSING.value, ErrorCode.OCCUPANCY_STALE.value, ErrorCode.NO_JOINT_STATE.value,
             "OCCUPANCY_INCOMPLETE", "BUSY"}
"""Errors a freshly (re)started stack answers until its map and joint states are in."""


def first_plan(client: RobonavClient, goal_rad: np.ndarray, *, seed: int, timeout_s: float) -> tuple[bool, float | None, str]:
    """Plan until the planner answers with a path or a non-retryable error.

    Returns (ok, seconds from the call to the first path, last detail)."""
    started = time.monotonic()
    detail = ""
    while time.monotonic() - started < timeout_s:
        try:
            reply = client.plan(goal_rad, seed=seed, timeout_s=min(30.0, timeout_s))
        except (QueryFailed, ProtocolError) as exc:  # no reply, or one that is not a message
            detail = f"{type(exc).__name__}: {exc}"
            time.sleep(0.5)
            continue
        if isinstance(reply, PlanResponse):
            return True, round(time.monotonic() - started, 3), "ok"
        detail = f"{reply.code}: {reply.message}"
        if reply.code not in RETRYABLE:
            return False, None, detail
        time.sleep(0.3)
    return False, None, detail


def cold_start(config_path: Path, goal_rad: np.ndarray, *, seed: int, log_dir: Path) -> dict[str, Any]:
    """`robonav up` with empty caches (compiled kernels, per-robot tables): when are all services
    alive, and the first plan?"""
    with tempfile.TemporaryDirectory(prefix="robonav-cold-cache-") as cache:
        stack = LiveStack(config_path, env={"NUMBA_CACHE_DIR": cache, TABLE_CACHE_ENV: str(Path(cache) / "tables")},
                          log_path=log_dir / "cold_start.log")
        try:
            with stack.connect() as session:
                client = RobonavClient(session, stack.cfg.cell)
                try:
                    missing = client.wait_for_services(SERVICES, ALIVE_TIMEOUT_S)
                    alive_s = round(time.monotonic() - stack.started_at, 2)
                    ok, plan_s, detail = (False, None, f"not alive: {sorted(missing)}") if missing else \
                        first_plan(client, goal_rad, seed=seed, timeout_s=READY_TIMEOUT_S)
                finally:
                    client.close()
        finally:
            stack.close()
    return {"alive_s": alive_s if not missing else None, "first_plan_ok": ok, "first_plan_s": plan_s,
            "detail": detail}


def long_request(client: RobonavClient, goal_rad: np.ndarray, other_goal_rad: np.ndarray, *, seed: int,
                 planning_time_s: float, hold_s: float = 10.0) -> dict[str, Any]:
    """A plan answered while one RRT* request with a very long budget runs (its caller gives up after
    `hold_s`, and the planner must not keep a worker on it forever)."""
    outcome: dict[str, Any] = {}

    def ask_long() -> None:
        request = PlanRequest(goal_positions=other_goal_rad, planner_id="rrtstar", allowed_planning_time=planning_time_s,
                              seed=seed)
        try:
            reply = client.plan_request(request, timeout_s=hold_s)
            outcome["long"] = "path" if isinstance(reply, PlanResponse) else f"{reply.code}"
        except (QueryFailed, ProtocolError):
            outcome["long"] = "caller_timeout"

    thread = threading.Thread(target=ask_long, daemon=True)
    thread.start()
    time.sleep(1.0)  # the long request is planning now
    started = time.monotonic()
    try:
        reply = client.plan(goal_rad, seed=seed + 1, timeout_s=30.0)
        second = "ok" if isinstance(reply, PlanResponse) else f"{reply.code}: {reply.message}"
    except (QueryFailed, ProtocolError) as exc:
        second = f"no reply: {exc}"
    second_s = round(time.monotonic() - started, 3)
    thread.join(timeout=hold_s + 5.0)
    # After the long request's caller gave up, a plan must still be answered promptly.
    started = time.monotonic()
    ok_after, _, _ = first_plan(client, goal_rad, seed=seed + 2, timeout_s=30.0)
    return {"planning_time_s": planning_time_s, "second_plan_s": second_s, "second_plan": second,
            "long_request": outcome.get("long", "running"), "plan_after_s": round(time.monotonic() - started, 3),
            "plan_after_ok": ok_after}


def overload(stack: LiveStack, client: RobonavClient, *, seconds: float, factor: float = 2.0,
             settle_s: float = 10.0) -> dict[str, Any]:
    """Clouds at `factor` times the camera rate (the sim's own plus copies of them): memory growth per
    service over `seconds`, measured from `settle_s` after the extra clouds started (the buffers a
    doubled rate needs are allocated then; what grows after that is what a long overload would
    exhaust), and whether maps kept coming."""
    camera = stack.cfg.cameras[0]
    latest: dict[str, PointCloud] = {}
    maps = {"count": 0}

    def on_cloud(sample: Any) -> None:  # noqa: ANN401 - a zenoh sample
        try:
            latest["cloud"] = PointCloud.from_wire(sample.payload.to_bytes())
        except ValueError:
            pass

    cloud_sub = client.session.declare_subscriber(client.keys.camera_cloud(camera.camera_id), on_cloud)
    map_sub = client.session.declare_subscriber(client.keys.occupancy, lambda _s: maps.__setitem__("count", maps["count"] + 1))
    time.sleep(2.0)
    at_start = stack.rss_bytes()
    period_s = 1.0 / (camera.rate_hz * (factor - 1.0))
    sent = 0
    started = time.monotonic()
    before: dict[str, int] | None = None
    maps_at_start = 0
    while time.monotonic() - started < settle_s + seconds:
        if before is None and time.monotonic() - started >= settle_s:
            before, maps_at_start = stack.rss_bytes(), maps["count"]
        cloud = latest.get("cloud")
        if cloud is not None:
            copy = PointCloud(stamp=time.time(), camera_id=cloud.camera_id, points=cloud.points, seq=10_000_000 + sent,
                              intrinsics=cloud.intrinsics)
            client.session.put(client.keys.camera_cloud(camera.camera_id), copy.to_wire())
            sent += 1
        time.sleep(period_s)
    maps_during = maps["count"] - maps_at_start
    after = stack.rss_bytes()
    cloud_sub.undeclare()
    map_sub.undeclare()
    before = before or at_start

    def growth(base: dict[str, int]) -> dict[str, float]:
        return {name: round(100.0 * (after.get(name, 0) - rss) / rss, 1) for name, rss in base.items() if rss > 0}

    return {"seconds": seconds, "settle_s": settle_s, "extra_clouds": sent, "maps_published": maps_during,
            "rss_growth_pct": growth(before), "rss_growth_from_idle_pct": growth(at_start),
            "rss_mb_after": {name: round(v / 2**20, 1) for name, v in after.items()}}


def kill(stack: LiveStack, client: RobonavClient, name: str, goals: list[np.ndarray], *, seed: int) -> dict[str, Any]:
    """SIGKILL service `name` while the arm moves; time the restart and the arm coming to rest,
    count contacts, then plan and execute to the next goal."""
    contacts_before = _contacts(client)
    # The goal farthest from where the arm is, so it surely moves when the service dies.
    here = client.joint_state.position if client.joint_state is not None else goals[0]
    order = sorted(goals, key=lambda g: -float(np.max(np.abs(g - here))))
    goal, next_goal = order[0], order[1]
    motion = plan_and_execute(client, goal, seed=seed, wait=False)
    moving = motion["ok"] and client.wait_for(
        lambda: client.joint_state is not None and float(np.max(np.abs(client.joint_state.velocity))) > 0.05, 5.0)
    time.sleep(0.2)
    old_pids = stack.service_pids()
    try:
        stack.kill(name)
    except RuntimeError as exc:
        return {"killed_mid_motion": False, "error": str(exc)}
    killed_at = time.monotonic()
    at_rest_s = wait_at_rest(client, timeout_s=10.0)
    restarted_s = None
    while time.monotonic() - killed_at < 60.0:
        pids = stack.service_pids()
        if name in pids and pids[name] != old_pids.get(name) and name in (client.alive_services() | {"router"}):
            restarted_s = round(time.monotonic() - killed_at, 2)
            break
        time.sleep(0.2)
    missing = client.wait_for_services(SERVICES, 60.0)
    ok, _, detail = first_plan(client, next_goal, seed=seed + 1, timeout_s=READY_TIMEOUT_S)
    reached = ok and plan_and_execute(client, next_goal, seed=seed + 1)["ok"]
    contacts_after = _contacts(client)
    return {"killed_mid_motion": bool(moving), "restarted_s": restarted_s, "arm_at_rest_s": at_rest_s,
            "contacts": None if contacts_before is None or contacts_after is None else
            max(contacts_after - contacts_before, 0) if name != "sim" else contacts_after,
            "next_goal_reached": bool(reached), "not_alive": sorted(missing), "detail": detail}


def bad_setpoints(client: RobonavClient, joint_names: tuple[str, ...], upper_rad: np.ndarray, *,
                  count: int = 50) -> dict[str, Any]:
    """Setpoints the robot side must refuse (beyond the joint limits, and jumps far beyond one
    period of motion), published while the arm rests: how many did it follow?"""
    assert client.joint_state is not None
    rest = client.joint_state.position.copy()
    zeros = np.zeros_like(rest)
    followed = 0
    for k in range(count):
        target = upper_rad + 0.5 if k % 2 == 0 else rest + 1.0  # out of limits / a 1 rad jump in one period
        client.session.put(client.keys.setpoint, Setpoint(stamp=time.time(), trajectory_id=f"forged-{k}", names=joint_names,
                                                          position=target, velocity=zeros, acceleration=zeros).to_wire())
        time.sleep(0.01)
        if client.joint_state is not None and float(np.max(np.abs(client.joint_state.position - rest))) > 0.05:
            followed += 1
    time.sleep(0.5)
    moved = client.joint_state is not None and float(np.max(np.abs(client.joint_state.position - rest))) > 0.05
    return {"injected": count, "followed": followed + (1 if moved and followed == 0 else 0)}


def fuzz(stack: LiveStack, client: RobonavClient, count: int, *, seed: int) -> dict[str, Any]:
    """`count` mutated payloads over every query and subscribed key; crashes are service processes
    that died meanwhile (new PIDs), `alive_after` whether every service serves afterwards."""
    targets = seed_messages(client.keys, stack.cfg.robot.joint_names, np.array(stack.cfg.robot.home_position_rad),
                            stack.cfg.cameras[0].camera_id)
    pids_before = stack.service_pids()
    counts = run_fuzz(client.session, targets, count, np.random.default_rng(seed), timeout_s=10.0,
                      alive=lambda: stack.process.poll() is None)
    pids_after = stack.service_pids()
    crashes = sum(1 for name, pid in pids_before.items() if pids_after.get(name) != pid)
    missing = client.wait_for_services(SERVICES, 30.0)
    return {"sent": counts.sent, "queries": counts.queries, "published": counts.published,
            "structured": counts.structured, "unstructured": counts.unstructured, "no_reply": counts.no_reply,
            "crashes": crashes + (1 if stack.process.poll() is not None else 0), "alive_after": not missing,
            "by_mutation": counts.by_mutation, "unstructured_examples": counts.unstructured_examples,
            "no_reply_examples": counts.no_reply_examples}


def _contacts(client: RobonavClient) -> int | None:
    try:
        reply = client.contacts(timeout_s=10.0)
    except (QueryFailed, ProtocolError):
        return None
    return None if isinstance(reply, ErrorReply) else reply.contact_count


def forged(log_dir: Path) -> dict[str, Any]:
    """Every role of a secured cell (fresh passwords and certificates from `setup_cell.sh`, the
    router's access control from `router-acl.json5`) tries every publication, request,
    impersonation and liveliness token outside its role: how many got through?"""
    scripts = Path(robonav.configs.__file__).parent / "security"
    if not (scripts / "setup_cell.sh").is_file() or shutil.which("openssl") is None:
        return {"skipped": "needs configs/security/setup_cell.sh and openssl"}
    with tempfile.TemporaryDirectory(prefix="robonav-cell-") as cell:
        subprocess.run(["bash", str(scripts / "setup_cell.sh"), cell], check=True, capture_output=True)
        port = free_port()
        router_dir = Path(cell) / "router"
        config = write_campaign_config(None, router_dir, seed=0)
        with (log_dir / "forged_router.log").open("ab") as log:
            router = subprocess.Popen([sys.executable, "-m", "robonav.services.cli", "router", "--config", str(config),
                                       "--zenoh-config", "router-acl.json5", "--listen", f"tls/127.0.0.1:{port}",
                                       "--log-level", "WARNING"], cwd=router_dir, stdout=log, stderr=log)
            try:
                deadline = time.monotonic() + 30.0
                while time.monotonic() < deadline and router.poll() is None:
                    with socket.socket() as s:
                        if s.connect_ex(("127.0.0.1", port)) == 0:
                            break
                    time.sleep(0.1)
                results = probe_roles(logins(cell, f"tls/localhost:{port}"))
            finally:
                router.terminate()
                router.wait(timeout=15)
    tried = sum(r.puts_forbidden + r.queries_forbidden + r.impersonations_tried + r.tokens_forged for r in results.values())
    return {"forged_tried": tried, "forged_delivered": forged_delivered(results),
            "leaks": [leak for r in results.values() for leak in r.leaks][:10]}
