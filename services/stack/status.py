"""`robonav status`: which services are alive, and (under `robonav up`) their restarts and uptimes.

    robonav status [--config FILE] [--zenoh-config FILE] [--json] [--timeout S]

Liveliness tokens say who serves now (`alive/<service>` and `alive/<service>/<instance>`, declared
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
from typing import Any

import zenoh

from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.messages import ErrorReply, StackStatusRequest, StackStatusResponse
from robonav.services.client import QueryFailed, query_one
from robonav.services.common import open_session, parse_args_and_config
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


def collect_status(session: zenoh.Session, cell: str, timeout_s: float = 2.0) -> dict[str, Any]:
    """The whole report as plain data: `ok` (every expected service alive), `supervisor` (None
    without a `robonav up`), and per service `alive`, `instances` and, from the supervisor,
    `state`, `restarts`, `pid`, `uptime_s`, `alive_for_s`, `last_exit_code`, `last_exit_stamp`,
    `last_back_s`, `restart_in_s` (None when unknown)."""
    keys = Keys(cell)
    tokens = alive_tokens(session, keys, timeout_s)
    supervised = supervisor_status(session, keys, timeout_s)
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
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--json", action="store_true")
    pre.add_argument("--timeout", type=float, default=2.0)
    known, rest = pre.parse_known_args(argv)
    loaded = parse_args_and_config("robonav status", "Which services are alive, with restart counts and uptimes "
                                   "under robonav up. Also: --json, --timeout S (default 2).", rest)
    if loaded is None:
        return 2
    _, cfg = loaded
    try:
        session = open_session(cfg.zenoh)
    except zenoh.ZError as exc:
        print(f"cannot reach the router at {', '.join(cfg.zenoh.connect)}: {str(exc).split(' at ')[0]}", file=sys.stderr)
        return 3
    with session:
        report = collect_status(session, cfg.cell, known.timeout)
    print(json.dumps(report, indent=2) if known.json else format_table(report))
    return 0 if report["ok"] else 1
