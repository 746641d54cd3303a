"""A live stack for the fault campaign: `robonav up` in its own process group, on a free port.

The campaign kills services by PID, so it finds them as `up`'s child processes (their command
lines name the service), and it reads every process's resident memory from /proc.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.messages import ErrorReply, ExecuteResponse, PlanResponse
from robonav.services.client import QueryFailed, RobonavClient
from robonav.services.common import open_session
from robonav.services.config import RobonavConfig, ZenohConfig, default_config_path, load_config
from robonav.services.keys import SERVICES

SHUTDOWN_TIMEOUT_S = 30.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def write_campaign_config(source: Path | None, directory: Path, *, seed: int) -> Path:
    """The config with its own Zenoh port and the planner seeded, as `robonav up` will read it."""
    data = yaml.safe_load((source or default_config_path()).read_text(encoding="utf-8")) or {}
    data["zenoh"] = {**data.get("zenoh", {}), "connect": [f"tcp/127.0.0.1:{free_port()}"]}
    data.setdefault("planner", {})["seed"] = seed
    path = directory / "faults.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    load_config(path)
    return path


class LiveStack:
    """`robonav up --config PATH` as a child process group; `close` ends it with SIGTERM."""

    def __init__(self, config_path: Path, *, env: dict[str, str] | None = None, log_path: Path | None = None) -> None:
        self.config_path = config_path
        self.cfg: RobonavConfig = load_config(config_path)
        self._log = open(log_path, "ab") if log_path is not None else subprocess.DEVNULL  # noqa: SIM115 - closed in close
        self.started_at = time.monotonic()
        self.process = subprocess.Popen(
            [sys.executable, "-m", "robonav.services.cli", "up", "--config", str(config_path), "--log-level", "WARNING"],
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}, stdout=self._log, stderr=self._log,
            start_new_session=True)

    def connect(self, timeout_s: float = 30.0) -> Any:  # noqa: ANN401 - a zenoh.Session
        """A client session on the stack's router (retried while the router starts)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return open_session(ZenohConfig(mode="client", connect=self.cfg.zenoh.connect))
            except Exception:
                if time.monotonic() > deadline or self.process.poll() is not None:
                    raise
                time.sleep(0.2)

    def service_pids(self) -> dict[str, int]:
        """PID of each service process `up` runs now (by the `serve NAME` of its command line)."""
        found: dict[str, int] = {}
        for pid, ppid, cmdline in _processes():
            if ppid != self.process.pid:
                continue
            if "serve" in cmdline:
                name = cmdline[cmdline.index("serve") + 1] if cmdline.index("serve") + 1 < len(cmdline) else ""
                if name in SERVICES:
                    found[name] = pid
            elif "router" in cmdline:
                found["router"] = pid
        return found

    def rss_bytes(self) -> dict[str, int]:
        """Resident memory of every service process (and of `up` itself) [bytes]."""
        pids = {**self.service_pids(), "up": self.process.pid}
        return {name: _rss_bytes(pid) for name, pid in pids.items()}

    def kill(self, name: str) -> int:
        """SIGKILL the service `name` ("router": the router process, else `up` itself when it hosts
        the router); returns the PID killed."""
        pid = self.service_pids().get(name)
        if pid is None and name == "router":
            raise RuntimeError("the router runs inside `robonav up`, not as a process of its own: cannot kill it alone")
        if pid is None:
            raise RuntimeError(f"no process for service {name!r} (running: {sorted(self.service_pids())})")
        os.kill(pid, signal.SIGKILL)
        return pid

    def close(self) -> int | None:
        """SIGTERM `up` (which stops its services), SIGKILL the group if it hangs; returns `up`'s exit code."""
        code = self.process.poll()
        if code is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                code = self.process.wait(timeout=SHUTDOWN_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                code = self.process.wait()
        if self._log is not subprocess.DEVNULL:
            self._log.close()
        return code


def plan_and_execute(client: RobonavClient, goal_rad: np.ndarray, *, seed: int, timeout_s: float = 60.0,
                     wait: bool = True) -> dict[str, Any]:
    """Plan to `goal_rad` and execute the path (replanning on a block); waits for the end when `wait`.

    Returns a record with `ok`, `stage` (where it failed) and `detail`, never raises on a failed
    or silent service.
    """
    try:
        plan = client.plan(goal_rad, seed=seed, timeout_s=timeout_s)
        if not isinstance(plan, PlanResponse):
            return {"ok": False, "stage": "plan", "detail": f"{plan.code}: {plan.message}"}
        execution = client.execute(plan.path, joint_names=plan.joint_names, replan=True,
                                   occupancy_stamp=plan.occupancy_stamp, scene_revision=plan.scene_revision,
                                   timeout_s=timeout_s)
        if isinstance(execution, ErrorReply):
            return {"ok": False, "stage": "execute", "detail": f"{execution.code}: {execution.message}"}
        assert isinstance(execution, ExecuteResponse)
        if not wait:
            return {"ok": True, "stage": "started", "trajectory_id": execution.trajectory_id,
                    "duration_s": execution.duration_s}
        result = client.wait_for_trajectory(execution.trajectory_id, execution.duration_s + timeout_s)
        return {"ok": result == "succeeded", "stage": "done", "detail": result, "trajectory_id": execution.trajectory_id}
    except (QueryFailed, ProtocolError) as exc:  # no reply, or one that is not a message
        return {"ok": False, "stage": "query", "detail": f"{type(exc).__name__}: {exc}"}


def wait_at_rest(client: RobonavClient, *, timeout_s: float, speed_rad_s: float = 1e-3) -> float | None:
    """Seconds until the measured joint velocities are all below `speed_rad_s`, or None."""
    started = time.monotonic()
    at_rest = client.wait_for(
        lambda: client.joint_state is not None and float(np.max(np.abs(client.joint_state.velocity))) < speed_rad_s,
        timeout_s)
    return round(time.monotonic() - started, 3) if at_rest else None


def _processes() -> list[tuple[int, int, list[str]]]:
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().decode(errors="replace").split("\0")
        except OSError:
            continue  # gone meanwhile
        # The command name in field 2 may hold spaces and parentheses: split after the last ')'.
        ppid = int(stat[stat.rindex(")") + 2:].split()[1])
        out.append((int(entry.name), ppid, [c for c in cmdline if c]))
    return out


def _rss_bytes(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0
