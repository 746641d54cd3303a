"""Plan (and optionally execute) a motion with nothing but Zenoh and msgpack.

This file deliberately imports nothing from robonav: it is what a client in any language
does, following docs/protocol.md. Run the stack first (`robonav up`), then:

    python examples/plan_client.py --goal 0.4 -0.3 0.0 -2.2 0.0 1.9 0.8 [--execute]

Exit code 0 when the plan (and execution) succeeded, 1 on a structured error, 2 on no reply,
130 after Ctrl-C: while the arm moves, Ctrl-C sends `executor/stop` and waits until the
executor reports a resting state and the joint states show every joint still.
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


def query(session: zenoh.Session, key: str, request: dict, timeout_s: float) -> dict | None:
    for reply in session.get(key, payload=msgpack.packb(request, use_bin_type=True), timeout=timeout_s):
        sample = reply.ok if reply.ok is not None else reply.err
        return msgpack.unpackb(sample.payload.to_bytes(), raw=False)
    return None


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
    if reply is None or not reply.get("ok", False):
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
        plan = query(session, f"{root}/planner/plan", {
            "v": 1, "goal_positions": f8_array(args.goal), "allowed_planning_time": args.planning_time,
            "request_id": "example",
        }, args.timeout)
        if plan is None:
            print("no reply from the planner", file=sys.stderr)
            return 2
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
        if execute is None or not execute.get("ok", False):
            print(f"execute failed: {execute}", file=sys.stderr)
            return 1 if execute else 2
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
