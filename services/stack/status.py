"""`robonav status`: which services are alive, and (under `robonav up`) their restarts and uptimes.

    robonav status [--config FILE] [--zenoh-config FILE] [--json] [--timeout S]

Also the newest map's age and completeness (`perception/occupancy`, latched) and the executor's
state and last error (`executor/status`). Liveliness tokens say who serves now (`alive/<service>` and `alive/<service>/<instance>`, declared
once a service is warm). When a `robonav up` supervises the cell, its `stack/status` query adds
each process's state, restart count, uptime and last exit. Exit codes: 0 every expected service
is alive (the supervisor's processes, else the router and the four services); 1 one is not;
2 a bad config; 3 the router did not answer.

`collect_status` is the same report as a dict, for programs (`--json` prints it).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import time
from typing import Any

import zenoh

from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.messages import (
    ErrorReply,
    ExecutorStatus,
    Occupancy,
    StackStatusRequest,
    StackStatusResponse,
)
from robonav.services.client import QueryFailed, query_one
from robonav.services.common import declare_latched_subscriber, open_session, parse_args_and_config
from robonav.services.keys import SERVICES, Keys
from robonav.services.stack.supervisor import describe_exit

log = logging.getLogger("robonav.status")

ROUTER = "router"


def alive_tokens(session: zenoh.Session, keys: Keys, timeout_s: float) -> dict[str, list[str]]:
    """Service name → instances holding a token (`""` for the plain `alive/<service>` token)."""
    prefix = keys.alive("")
    found: dict[str, list[str]] = {}
    for reply in session.liveliness().get(f"{keys.root}/alive/**", timeout=timeout_s):
        if reply.ok is None:
            continue
        rest = str(reply.ok.key_expr)[len(prefix):]
        name, _, instance = rest.partition("/")
        found.setdefault(name, []).append(instance)
    return found


def supervisor_status(session: zenoh.Session, keys: Keys, timeout_s: float) -> StackStatusResponse | None:
    """The supervising `robonav up`'s report, or None when none answers (e.g. a compose stack)."""
    try:
        reply, _ = query_one(session, keys.stack_status, StackStatusRequest(), StackStatusResponse, timeout_s)
    except (QueryFailed, ProtocolError, zenoh.ZError):
        return None
    return None if isinstance(reply, ErrorReply) else reply


class _Latest:
    """The last occupancy map (latched: its cache answers at once) and executor status (20 Hz) to arrive."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self.occupancy: Occupancy | None = None
        self.status: ExecutorStatus | None = None
        self._both = threading.Event()
        self._subs = [declare_latched_subscriber(session, keys.occupancy, self._on(Occupancy, "occupancy")),
                      session.declare_subscriber(keys.status, self._on(ExecutorStatus, "status"))]

    def _on(self, cls: type[Occupancy] | type[ExecutorStatus], attr: str):  # noqa: ANN202 - a zenoh callback
        def callback(sample: zenoh.Sample) -> None:
            try:
                setattr(self, attr, cls.from_wire(sample.payload.to_bytes()))
            except ProtocolError:
                return  # a peer of another version: reported as unknown, never a crash
            if self.occupancy is not None and self.status is not None:
                self._both.set()
        return callback

    def wait(self, timeout_s: float) -> None:
        self._both.wait(max(0.0, timeout_s))

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()


def map_report(occupancy: Occupancy | None, min_frames: int, now: float) -> dict[str, Any] | None:
    """Age and completeness of the newest map (None: none received): `complete` as the planner
    judges it (every camera `min_frames` frames since the last clear; a map without counts is complete)."""
    if occupancy is None:
        return None
    frames = occupancy.camera_frames
    missing = sorted(c for c, n in (frames or {}).items() if n < min_frames)
    return {"stamp": occupancy.stamp, "age_s": round(now - occupancy.stamp, 3), "seq": occupancy.seq,
            "occupied_voxels": int(occupancy.occupied_centers_m.shape[0]), "camera_frames": frames,
            "required_frames": min_frames, "complete": not missing, "incomplete_cameras": missing}


def executor_report(status: ExecutorStatus | None) -> dict[str, Any] | None:
    """The executor's state and its last error (None: no status received)."""
    if status is None:
        return None
    return {"state": status.state.value, "trajectory_id": status.trajectory_id, "progress": round(status.progress, 4),
            "last_result": status.last_result.value, "error_code": status.error_code, "error_message": status.error_message,
            "age_s": round(time.time() - status.stamp, 3)}


def collect_status(session: zenoh.Session, cell: str, timeout_s: float = 2.0, min_frames: int = 3) -> dict[str, Any]:
    """The whole report as plain data: `ok` (every expected service alive), `supervisor` (None
    without a `robonav up`), per service `alive`, `instances` and, from the supervisor,
    `state`, `restarts`, `pid`, `uptime_s`, `alive_for_s`, `last_exit_code`, `last_exit_stamp`,
    `last_back_s`, `restart_in_s` (None when unknown); `map` (`map_report`) and `executor`
    (`executor_report`), None when nothing arrived within the time left of `timeout_s`."""
    started = time.monotonic()
    keys = Keys(cell)
    latest = _Latest(session, keys)
    try:
        tokens = alive_tokens(session, keys, timeout_s)
        # One budget for the whole report: a silent peer delays it by at most `timeout_s` in all.
        supervised = supervisor_status(session, keys, max(0.1, timeout_s - (time.monotonic() - started)))
        # A running executor publishes at 20 Hz and the map's cache answers at once; a dead one
        # costs at most what is left of the budget.
        latest.wait(min(timeout_s - (time.monotonic() - started), 0.5))
    finally:
        latest.close()
    rows: dict[str, dict[str, Any]] = {}
    names = [s.name for s in supervised.services] if supervised is not None else [ROUTER, *SERVICES]
    for name in names:
        instances = sorted(i for i in tokens.get(name, []) if i)
        # We reached the router, so it serves; an upstream zenohd holds no token.
        alive = name in tokens or name == ROUTER
        rows[name] = {"name": name, "alive": alive, "instances": instances, "state": None, "restarts": None,
                      "pid": None, "uptime_s": None, "alive_for_s": None, "last_exit_code": None,
                      "last_exit_stamp": None, "last_back_s": None, "restart_in_s": None}
    if supervised is not None:
        for process in supervised.services:
            row = rows[process.name]
            row.update(state=process.state, restarts=process.restarts, pid=process.pid, uptime_s=process.uptime_s,
                       alive_for_s=process.alive_for_s, last_exit_code=process.last_exit_code,
                       last_exit_stamp=process.last_exit_stamp, last_back_s=process.last_back_s,
                       restart_in_s=process.restart_in_s)
            if process.name not in (ROUTER, *SERVICES):  # holds no token (view): the supervisor knows
                row["alive"] = process.alive
    for name in sorted(set(tokens) - set(rows)):  # tokens of processes nobody expects here
        rows[name] = {"name": name, "alive": True, "instances": sorted(i for i in tokens[name] if i)}
    return {
        "ok": all(rows[name]["alive"] for name in names),
        "cell": cell,
        "supervisor": None if supervised is None else {
            "pid": supervised.supervisor_pid, "started_stamp": supervised.started_stamp,
            "uptime_s": round(supervised.stamp - supervised.started_stamp, 3), "restart": supervised.restart},
        "services": list(rows.values()),
        "map": map_report(latest.occupancy, min_frames, time.time()),
        "executor": executor_report(latest.status),
    }


def _duration(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    if seconds < 120:
        return f"{seconds:.1f} s"
    minutes, secs = divmod(int(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}"


def format_table(report: dict[str, Any]) -> str:
    supervisor = report["supervisor"]
    lines = [f"robonav/{report['cell']}: " + (
        f"supervised by robonav up (pid {supervisor['pid']}, up {_duration(supervisor['uptime_s'])}, "
        f"restarts {'on' if supervisor['restart'] else 'off'})" if supervisor else
        "no robonav up answered stack/status: liveliness only")]
    lines.append(f"{'service':<11} {'alive':<6} {'state':<11} {'restarts':>8}  {'uptime':>9}  {'pid':>7}  last exit")
    for row in report["services"]:
        last = "-"
        if row.get("last_exit_code") is not None:
            last = describe_exit(row["last_exit_code"])
            if row.get("last_back_s") is not None and row.get("state") == "running":
                last += f", back after {row['last_back_s']:.1f} s"
            elif row.get("restart_in_s") is not None:
                last += f", restart in {row['restart_in_s']:.1f} s"
        restarts = "-" if row.get("restarts") is None else str(row["restarts"])
        pid = "-" if row.get("pid") is None else str(row["pid"])
        instances = f" [{', '.join(row['instances'])}]" if len(row.get("instances", [])) > 1 else ""
        lines.append(f"{row['name'] + instances:<11} {'yes' if row['alive'] else 'NO':<6} {row.get('state') or '-':<11} "
                     f"{restarts:>8}  {_duration(row.get('uptime_s')):>9}  {pid:>7}  {last}")
    lines.append(_map_line(report.get("map")))
    lines.append(_executor_line(report.get("executor")))
    return "\n".join(lines)


def _map_line(occupancy: dict[str, Any] | None) -> str:
    if occupancy is None:
        return "map: none received"
    done = "complete" if occupancy["complete"] else f"INCOMPLETE (cameras below {occupancy['required_frames']} frames: " \
        f"{', '.join(occupancy['incomplete_cameras'])})"
    return f"map: seq {occupancy['seq']}, age {_duration(occupancy['age_s'])}, {occupancy['occupied_voxels']} voxels, {done}"


def _executor_line(executor: dict[str, Any] | None) -> str:
    if executor is None:
        return "executor: no status received"
    error = f", error {executor['error_code']}: {executor['error_message']}" if executor["error_code"] else ""
    return f"executor: {executor['state']}, last result {executor['last_result']}" + \
        (f", trajectory {executor['trajectory_id']}" if executor["trajectory_id"] else "") + error


def main(argv: list[str] | None = None) -> int:
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--json", action="store_true", help="print the report as JSON")
    pre.add_argument("--timeout", type=float, default=2.0, help="longest wait for each answer [s] (default %(default)s)")
    known, rest = pre.parse_known_args(argv)
    loaded = parse_args_and_config("robonav status", "Which services are alive, with restart counts and uptimes "
                                   "under robonav up.", rest, parents=(pre,))
    if loaded is None:
        return 2
    _, cfg = loaded
    try:
        session = open_session(cfg.zenoh)
    except zenoh.ZError as exc:
        print(f"cannot reach the router at {', '.join(cfg.zenoh.connect)}: {str(exc).split(' at ')[0]}", file=sys.stderr)
        return 3
    with session:
        report = collect_status(session, cfg.cell, known.timeout, cfg.planner.occupancy_min_frames)
    print(json.dumps(report, indent=2) if known.json else format_table(report))
    return 0 if report["ok"] else 1
