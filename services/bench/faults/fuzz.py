"""Mutated payloads for every key a service answers or listens on, and what came back.

Each target starts from a valid message of its key (`seed_messages`); a mutation damages it
the way a buggy or hostile peer would: bit flips, truncation, random bytes, wrong types, NaN
and inf, huge or negative array shapes, unknown or missing keys, a `v` of the wrong type, and
nesting deep enough to exhaust a naive decoder. Queries must each get a reply that is either
the key's response or a structured error map; publications get no reply, and the harness
checks that every service is still alive and serving afterwards.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np
import zenoh

from robonav.pipeline.camera import CameraIntrinsics
from robonav.pipeline.types import FloatArray
from robonav.pipeline.wire.messages import (
    ContactsRequest,
    DepthImage,
    ExecuteRequest,
    ExecutorStatus,
    JointState,
    Occupancy,
    PerceptionClearRequest,
    PerceptionStatusRequest,
    PlanRequest,
    PointCloud,
    SceneRequest,
    Setpoint,
    SimObjectsRequest,
    SimStatsRequest,
    StopRequest,
)
from robonav.services.keys import Keys

MUTATIONS: tuple[str, ...] = ("bit_flip", "truncate", "random_bytes", "wrong_type", "non_finite", "huge_shape",
                              "negative_shape", "unknown_key", "missing_key", "version_type", "depth_bomb")
DEPTH_BOMB_LEVELS = 100_000
"""Nested arrays in a depth bomb: far past any sane message, within a few hundred kB."""


@dataclass(frozen=True)
class Target:
    """One key to fuzz and a valid payload to start from."""

    key: str
    seed: dict[str, Any]
    """The valid message as a msgpack map."""
    query: bool
    """A queryable (a reply is due) rather than a subscriber."""


@dataclass
class FuzzCounts:
    """What the mutated payloads got."""

    sent: int = 0
    queries: int = 0
    structured: int = 0
    """Query replies that are the key's response or a structured error map."""
    unstructured: int = 0
    """Query replies that are neither (not msgpack, not a map, no `code`)."""
    no_reply: int = 0
    """Queries that got no reply within the timeout."""
    published: int = 0
    by_mutation: dict[str, int] = field(default_factory=dict)
    unstructured_examples: list[str] = field(default_factory=list)
    no_reply_examples: list[str] = field(default_factory=list)


def seed_messages(keys: Keys, joint_names: Sequence[str], home_rad: FloatArray, camera_id: str) -> list[Target]:
    """A valid message for every query key and every subscribed key of the four services."""
    n = len(joint_names)
    names = tuple(joint_names)
    zeros = np.zeros(n)
    intrinsics = CameraIntrinsics(width=8, height=6, fx=6.0, fy=6.0, cx=3.5, cy=2.5)
    points = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.2]], dtype=np.float32)
    now = time.time()
    queries = [
        (keys.plan, PlanRequest(goal_positions=home_rad + 0.05, allowed_planning_time=0.5)),
        (keys.scene, SceneRequest(operation="list")),
        (keys.execute, ExecuteRequest(path=np.vstack([home_rad, home_rad]))),
        (keys.stop, StopRequest()),
        (keys.perception_clear, PerceptionClearRequest()),
        (keys.perception_status, PerceptionStatusRequest()),
        (keys.contacts, ContactsRequest()),
        (keys.sim_objects, SimObjectsRequest(operation="list")),
        (keys.sim_stats, SimStatsRequest()),
    ]
    publications = [
        (keys.joint_states, JointState(stamp=now, names=names, position=home_rad, velocity=zeros)),
        (keys.camera_cloud(camera_id), PointCloud(stamp=now, camera_id=camera_id, points=points, intrinsics=intrinsics)),
        (keys.camera_depth(camera_id), DepthImage(stamp=now, camera_id=camera_id, intrinsics=intrinsics,
                                                  depth_m=np.full((6, 8), 1.5, dtype=np.float32))),
        (keys.setpoint, Setpoint(stamp=now, trajectory_id="fuzz", names=names, position=home_rad, velocity=zeros,
                                 acceleration=zeros)),
        (keys.occupancy, Occupancy(stamp=now, resolution_m=0.02, octomap_binary=b"",
                                   occupied_centers_m=np.zeros((0, 3), dtype=np.float32))),
        (keys.status, ExecutorStatus(stamp=now, state="executing", trajectory_id="fuzz", progress=0.5)),
    ]
    return ([Target(key, message.to_dict(), True) for key, message in queries]
            + [Target(key, message.to_dict(), False) for key, message in publications])


def mutate(seed: dict[str, Any], kind: str, rng: np.random.Generator) -> bytes:
    """One damaged payload of the `kind` in MUTATIONS, made from the valid map `seed`."""
    if kind == "random_bytes":
        return rng.bytes(int(rng.integers(0, 2048)))
    if kind == "depth_bomb":
        return b"\x91" * DEPTH_BOMB_LEVELS + b"\xc0"  # fixarray of one element, nested, ending in nil
    valid = msgpack.packb(seed, use_bin_type=True)
    if kind == "bit_flip":
        data = bytearray(valid)
        for _ in range(int(rng.integers(1, 9))):
            bit = int(rng.integers(0, 8 * len(data)))
            data[bit // 8] ^= 1 << (bit % 8)
        return bytes(data)
    if kind == "truncate":
        return valid[:int(rng.integers(0, len(valid)))]
    obj = _copy(seed)
    if kind == "version_type":
        obj["v"] = [True, 1.0, "1", 2, -1, None, [1], 2**64 - 1][int(rng.integers(0, 8))]
    elif kind == "unknown_key":
        obj[f"unknown_{int(rng.integers(0, 1000))}"] = 1
    elif kind == "missing_key":
        fields = [k for k in obj if k != "v"]
        if fields:
            del obj[fields[int(rng.integers(0, len(fields)))]]
    elif kind == "wrong_type":
        fields = [k for k in obj if k != "v"] or ["v"]
        obj[fields[int(rng.integers(0, len(fields)))]] = _other_value(rng)
    elif kind == "non_finite":
        _set_non_finite(obj, rng)
    elif kind in ("huge_shape", "negative_shape"):
        arrays = [k for k, v in obj.items() if isinstance(v, dict) and set(v) == {"dtype", "shape", "data"}]
        if arrays:
            name = arrays[int(rng.integers(0, len(arrays)))]
            array = dict(obj[name])
            rank = max(len(array["shape"]), 1)
            array["shape"] = ([2**40] * rank if kind == "huge_shape" else [-1] * rank)
            obj[name] = array
        else:
            obj["shape"] = [2**40] if kind == "huge_shape" else [-1]
    return msgpack.packb(obj, use_bin_type=True)


def run_fuzz(session: zenoh.Session, targets: Sequence[Target], count: int, rng: np.random.Generator, *,
             timeout_s: float, pause_s: float = 0.002, alive: Callable[[], bool] | None = None) -> FuzzCounts:
    """Send `count` mutated payloads round-robin over `targets` (mutation kinds drawn from `rng`).

    Args:
        session: An open Zenoh session of the stack's cell.
        targets: From `seed_messages`.
        count: Payloads to send.
        rng: Seeded generator: the same seed sends the same payloads.
        timeout_s: Wait for each query's reply at most this long [s].
        pause_s: Pause after each publication [s], so subscribers see them rather than the
            transport dropping them.
        alive: Polled every 200 payloads; the run stops early when it returns False.
    """
    counts = FuzzCounts()
    for i in range(count):
        target = targets[i % len(targets)]
        kind = MUTATIONS[int(rng.integers(0, len(MUTATIONS)))]
        payload = mutate(target.seed, kind, rng)
        counts.sent += 1
        counts.by_mutation[kind] = counts.by_mutation.get(kind, 0) + 1
        if target.query:
            counts.queries += 1
            outcome = _ask(session, target.key, payload, timeout_s)
            if outcome == "structured":
                counts.structured += 1
            elif outcome == "no_reply":
                counts.no_reply += 1
                if len(counts.no_reply_examples) < 10:
                    counts.no_reply_examples.append(f"{target.key} {kind}")
            else:
                counts.unstructured += 1
                if len(counts.unstructured_examples) < 10:
                    counts.unstructured_examples.append(f"{target.key} {kind}: {outcome}")
        else:
            session.put(target.key, payload)
            counts.published += 1
            time.sleep(pause_s)
        if alive is not None and i % 200 == 199 and not alive():
            break
    return counts


def _ask(session: zenoh.Session, key: str, payload: bytes, timeout_s: float) -> str:
    """"structured", "no_reply", or why the reply is neither a response nor an error map."""
    for reply in session.get(key, payload=payload, timeout=timeout_s):
        sample = reply.ok if reply.ok is not None else reply.err
        raw = sample.payload.to_bytes()
        try:
            body = msgpack.unpackb(raw, raw=False)
        except Exception as exc:  # a reply that is not msgpack
            # Zenoh answers a query nobody replied to in time with its own error, as text.
            if reply.ok is None and b"timeout" in raw.lower():
                return "no_reply"
            return f"not msgpack ({exc})"
        if not isinstance(body, dict) or "v" not in body:
            return f"not a versioned map: {str(body)[:80]}"
        if reply.ok is None and not isinstance(body.get("code"), str):
            return f"error without a code: {str(body)[:80]}"
        return "structured"
    return "no_reply"


def _copy(value: Any) -> Any:  # noqa: ANN401 - any msgpack value
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_copy(v) for v in value]
    return value


def _other_value(rng: np.random.Generator) -> Any:  # noqa: ANN401 - any msgpack value
    return ["text", [1, 2, 3], {"a": 1}, True, None, -(2**63), 1.5, b"\x00\x01", 2**64 - 1][int(rng.integers(0, 9))]


def _set_non_finite(obj: dict[str, Any], rng: np.random.Generator) -> None:
    value = [math.nan, math.inf, -math.inf][int(rng.integers(0, 3))]
    floats = [k for k, v in obj.items() if isinstance(v, float)]
    arrays = [k for k, v in obj.items() if isinstance(v, dict) and v.get("dtype") in ("<f4", "<f8")]
    if arrays and (not floats or rng.random() < 0.5):
        name = arrays[int(rng.integers(0, len(arrays)))]
        array = dict(obj[name])
        data = np.frombuffer(array["data"], dtype=np.dtype(array["dtype"])).copy()
        if data.size:
            data[int(rng.integers(0, data.size))] = value
            array["data"] = data.tobytes()
        obj[name] = array
    elif floats:
        obj[floats[int(rng.integers(0, len(floats)))]] = value
    else:
        obj["stamp"] = value
