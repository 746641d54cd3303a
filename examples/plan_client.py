"""Plan (and optionally execute) a motion with nothing but Zenoh and msgpack.

This file deliberately imports nothing from robonav: it is what a client in any language
does, following docs/protocol.md. Run the stack first (`robonav up`), then:

    python examples/plan_client.py --goal 0.4 -0.3 0.0 -2.2 0.0 1.9 0.8 [--execute]

Exit code 0 when the plan (and execution) succeeded, 1 on a structured error, 2 when a query
got no reply of the protocol (nothing answered, or Zenoh's own error such as "Timeout"), 130
after Ctrl-C: while the arm moves, Ctrl-C sends `executor/stop` and waits until the executor
reports a resting state and the joint states show every joint still.
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
import threading

import msgpack
import zenoh


def f8_array(values: list[float]) -> dict:
    """A 1-D float64 array map: little-endian bytes, shape, dtype."""
    return {"dtype": "<f8", "shape": [len(values)], "data": struct.pack(f"<{len(values)}d", *values)}


def decode_array(obj: dict) -> list:
    """An array map back into nested lists (float32 or float64, any shape)."""
    code = {"<f8": "d", "<f4": "f"}[obj["dtype"]]
    count = 1
    for n in obj["shape"]:
        count *= n
    flat = list(struct.unpack(f"<{count}{code}", obj["data"]))
    for n in reversed(obj["shape"][1:]):
        flat = [flat[i:i + n] for i in range(0, len(flat), n)]
    return flat


# The closed list of error codes this client knows (docs/protocol.md, Errors).
KNOWN_CODES = {"MALFORMED_MESSAGE", "UNSUPPORTED_VERSION", "INVALID_REQUEST", "OUT_OF_JOINT_LIMITS", "START_IN_COLLISION",
               "GOAL_IN_COLLISION", "GOAL_UNREACHABLE", "NO_SOLUTION", "UNKNOWN_PLANNER", "NO_JOINT_STATE",
               "OCCUPANCY_MISSING", "OCCUPANCY_STALE", "OCCUPANCY_INCOMPLETE", "EXECUTOR_BUSY", "INTERNAL_ERROR",
               "PAYLOAD_TOO_LARGE", "BUSY", "PATH_IN_COLLISION", "SCENE_MISSING"}


class NoReply(Exception):
    """The query got no reply of the protocol."""


def query(session: zenoh.Session, key: str, request: dict, timeout_s: float) -> dict:
    """One reply, read by the rule of docs/protocol.md: a map with `ok: false` and a `code` is an
    error (a code this client does not know counts as INTERNAL_ERROR); any other error payload
    is Zenoh's own (e.g. "Timeout"); an ordinary reply is the response map.

    Raises:
        NoReply: naming the key, the timeout and what came back.
    """
    # Consolidation NONE: take the reply when it arrives, not when the query ends.
    for reply in session.get(key, payload=msgpack.packb(request, use_bin_type=True), timeout=timeout_s,
                             consolidation=zenoh.ConsolidationMode.NONE):
        raw = (reply.ok if reply.ok is not None else reply.err).payload.to_bytes()
        try:
            message = msgpack.unpackb(raw, raw=False)
        except Exception:  # not msgpack: Zenoh's text, or garbage
            message = None
        if isinstance(message, dict) and message.get("ok") is False and isinstance(message.get("code"), str):
            if message["code"] not in KNOWN_CODES:
                message = {**message, "code": "INTERNAL_ERROR", "message": f"{message['code']}: {message.get('message')}"}
            return message
        if reply.ok is None or not isinstance(message, dict):
            raise NoReply(f"{key}: no reply of the protocol (timeout {timeout_s} s): {raw[:200].decode(errors='replace')!r}")
        return message
    raise NoReply(f"{key}: no reply within {timeout_s} s: is the service running?")


REST_VELOCITY_RAD_S = 0.01


def stop_and_wait(session: zenoh.Session, root: str, timeout_s: float) -> bool:
    """Send executor/stop; wait for a resting status and joint states with every velocity ~0."""
    rest = {"status": threading.Event(), "still": threading.Event()}

    def on_status(sample: zenoh.Sample) -> None:
        if msgpack.unpackb(sample.payload.to_bytes(), raw=False)["state"] in ("idle", "stopped", "error"):
            rest["status"].set()

    def on_joints(sample: zenoh.Sample) -> None:
        velocity = decode_array(msgpack.unpackb(sample.payload.to_bytes(), raw=False)["velocity"])
        if max((abs(v) for v in velocity), default=0.0) <= REST_VELOCITY_RAD_S:
            rest["still"].set()
        else:
            rest["still"].clear()

    reply = query(session, f"{root}/executor/stop", {"v": 1}, 5.0)
    if not reply.get("ok", False):
        print(f"stop failed: {reply}", file=sys.stderr)
        return False
    subscribers = [session.declare_subscriber(f"{root}/executor/status", on_status),
                   session.declare_subscriber(f"{root}/robot/joint_states", on_joints)]
    at_rest = rest["status"].wait(timeout_s) and rest["still"].wait(timeout_s)
    for subscriber in subscribers:
        subscriber.undeclare()
    return at_rest


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--router", default="tcp/127.0.0.1:7447")
    parser.add_argument("--cell", default="arm0")
    parser.add_argument("--goal", type=float, nargs="+", required=True, help="joint goal [rad], robot joint order")
    parser.add_argument("--planning-time", type=float, default=2.0)
    parser.add_argument("--execute", action="store_true", help="also execute the path and wait for the result")
    parser.add_argument("--velocity-scaling", type=float, help="scale the velocity and acceleration limits, (0, 1]")
    parser.add_argument("--timeout", type=float, default=30.0)
    args = parser.parse_args()

    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([args.router]))
    config.insert_json5("scouting/multicast/enabled", "false")
    root = f"robonav/{args.cell}"

    with zenoh.open(config) as session:
        try:
            return plan_and_execute(session, root, args)
        except NoReply as exc:
            print(exc, file=sys.stderr)
            return 2


def plan_and_execute(session: zenoh.Session, root: str, args: argparse.Namespace) -> int:
    """Plan, print the path; with --execute, execute it and wait for the outcome."""
    plan = query(session, f"{root}/planner/plan", {
        "v": 1, "goal_positions": f8_array(args.goal), "allowed_planning_time": args.planning_time,
        "request_id": "example",
    }, args.timeout)
    if not plan.get("ok", False):
        print(f"plan failed: {plan['code']}: {plan['message']}", file=sys.stderr)
        return 1
    path = decode_array(plan["path"])
    print(json.dumps({"waypoints": len(path), "planning_time_s": plan["planning_time_s"],
                      "path_length_rad": plan["path_length_rad"], "joint_names": plan["joint_names"]}))
    if not args.execute:
        return 0

    done = threading.Event()
    outcome: dict = {}

    def on_status(sample: zenoh.Sample) -> None:
        status = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
        if status["trajectory_id"] == outcome.get("trajectory_id") and status["state"] in ("idle", "stopped", "error"):
            outcome["result"] = status["last_result"] if status["state"] == "idle" else status["state"]
            done.set()

    subscriber = session.declare_subscriber(f"{root}/executor/status", on_status)
    flat = [v for row in path for v in row]
    execute = query(session, f"{root}/executor/execute", {
        "v": 1, "joint_names": plan["joint_names"],
        "path": {"dtype": "<f8", "shape": [len(path), len(path[0])], "data": struct.pack(f"<{len(flat)}d", *flat)},
        "max_velocity_scaling_factor": args.velocity_scaling, "max_acceleration_scaling_factor": args.velocity_scaling,
    }, args.timeout)
    if not execute.get("ok", False):
        print(f"execute failed: {execute['code']}: {execute['message']}", file=sys.stderr)
        return 1
    outcome["trajectory_id"] = execute["trajectory_id"]
    try:
        finished = done.wait(execute["duration_s"] + args.timeout)
    except KeyboardInterrupt:  # Ctrl-C while the arm moves: stop it, and wait until it rests
        subscriber.undeclare()
        at_rest = stop_and_wait(session, root, 10.0)
        print(json.dumps({"trajectory_id": execute["trajectory_id"], "result": "interrupted", "at_rest": at_rest}))
        return 130
    subscriber.undeclare()
    print(json.dumps({"trajectory_id": execute["trajectory_id"], "result": outcome.get("result", "timeout")}))
    return 0 if finished and outcome.get("result") == "succeeded" else 1


if __name__ == "__main__":
    sys.exit(main())
