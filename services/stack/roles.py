"""Who may send what: the roles of `configs/security/router-acl.json5`, and a probe that checks a router enforces them.

The table here is the one the router config, `docs/operations.md` and `docs/protocol.md`
state: each service identity publishes only its own outputs and serves only its own requests;
the operator asks the planner and the executor; the viewer sends nothing. `probe_roles` logs in
once per role on a router with that config and tries every publication, request, service
impersonation (a queryable on another service's key) and liveliness token of every role in a
cell of its own, then counts what got through. Zenoh's access control drops a denied message
without telling the sender, so the probe judges by what the receiving end saw: a forbidden put
must reach no subscriber, a forbidden query get no answer. Used by the role tests and by
benchmarks that report `forged_delivered`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from robonav.services.common import to_zenoh_config
from robonav.services.config import ZenohConfig

ROLES: tuple[str, ...] = ("sim", "perception", "planner", "executor", "operator", "viewer")

PUBLISHES: dict[str, tuple[str, ...]] = {
    "sim": ("robot/joint_states", "camera/cam0/cloud", "camera/cam0/depth", "sim/contacts/events", "cameras"),
    "perception": ("perception/occupancy", "perception/clusters"),
    "planner": ("planner/scene_state", "robot/description"),
    "executor": ("executor/setpoint", "executor/status", "executor/path"),
}
"""Keys (under `robonav/<cell>/`) each role may publish; nobody else may."""

SERVES: dict[str, tuple[str, ...]] = {
    "sim": ("sim/contacts", "sim/objects", "sim/stats"),
    "perception": ("perception/clear", "perception/status"),
    "planner": ("planner/plan", "planner/scene"),
    "executor": ("executor/execute", "executor/stop"),
}
"""Request keys each role may answer (declare a queryable on, reply to); nobody else may."""

ASKS: dict[str, tuple[str, ...]] = {
    "executor": ("planner/plan",),
    "operator": ("planner/plan", "planner/scene", "executor/execute", "executor/stop", "perception/clear",
                 "perception/status"),
}
"""Request keys each role may send a query to; nobody else may (sim/* requests: no role)."""

ALIVE: dict[str, str] = {"sim": "sim", "perception": "perception", "planner": "planner", "executor": "executor"}
"""The liveliness token (`alive/<service>`) each service role may declare."""

DEFAULT_CELL = "acl-probe"
QUERY_TIMEOUT_S = 1.5
SETTLE_TIMEOUT_S = 15.0
GRACE_S = 0.5


def all_published() -> tuple[str, ...]:
    return tuple(key for keys in PUBLISHES.values() for key in keys)


def all_served() -> tuple[str, ...]:
    return tuple(key for keys in SERVES.values() for key in keys)


@dataclass
class RoleProbe:
    """What one role tried and what got through."""

    role: str
    puts_tried: int = 0
    puts_forbidden: int = 0
    forbidden_puts_delivered: int = 0
    allowed_puts_missing: int = 0
    queries_tried: int = 0
    queries_forbidden: int = 0
    forbidden_queries_answered: int = 0
    allowed_queries_unanswered: int = 0
    impersonations_tried: int = 0
    impersonations_answered: int = 0
    """Queryables declared on another service's request key that answered a query."""
    tokens_forged: int = 0
    forged_tokens_seen: int = 0
    leaks: list[str] = field(default_factory=list)
    """Every forbidden message that got through, e.g. `put robot/joint_states`."""

    @property
    def forged_delivered(self) -> int:
        return (self.forbidden_puts_delivered + self.forbidden_queries_answered + self.impersonations_answered
                + self.forged_tokens_seen)

    def summary(self) -> dict[str, object]:
        return {"puts_tried": self.puts_tried, "puts_forbidden": self.puts_forbidden,
                "forbidden_puts_delivered": self.forbidden_puts_delivered,
                "allowed_puts_missing": self.allowed_puts_missing,
                "queries_tried": self.queries_tried, "queries_forbidden": self.queries_forbidden,
                "forbidden_queries_answered": self.forbidden_queries_answered,
                "allowed_queries_unanswered": self.allowed_queries_unanswered,
                "impersonations_tried": self.impersonations_tried,
                "impersonations_answered": self.impersonations_answered,
                "tokens_forged": self.tokens_forged, "forged_tokens_seen": self.forged_tokens_seen,
                "forged_delivered": self.forged_delivered, "leaks": list(self.leaks)}


class _Inbox:
    """Payloads seen by the probe's subscriber and queryables (Zenoh callbacks append)."""

    def __init__(self) -> None:
        self.items: set[bytes] = set()

    def add(self, payload: bytes) -> None:
        self.items.add(payload)

    def has(self, payload: bytes) -> bool:
        return payload in self.items


def _wait(condition: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def _answered(replies: zenoh.Handler, marker: bytes) -> bool:
    """Whether any reply (ok or error) carries `marker`; drains the replies until the query ends."""
    seen = False
    for reply in replies:
        sample = reply.ok if reply.ok is not None else reply.err
        if sample is not None and sample.payload.to_bytes() == marker:
            seen = True
    return seen


@contextmanager
def _sessions(open_role: Callable[[str], zenoh.Session], logins: list[tuple[str, str]]) -> Iterator[dict[str, zenoh.Session]]:
    """One session per (name, role) login, closed at the end."""
    with ExitStack() as stack:
        sessions = {}
        for name, role in logins:
            sessions[name] = open_role(role)
            stack.callback(sessions[name].close)
        yield sessions


def probe_roles(open_role: Callable[[str], zenoh.Session], *, cell: str = DEFAULT_CELL,
                roles: tuple[str, ...] = ROLES) -> dict[str, RoleProbe]:
    """Try every forbidden and allowed message of every role on a router enforcing the roles.

    Args:
        open_role: opens a client session logged in as the given role (e.g. with
            `client-<role>.json5`); every role of `roles` and `viewer` must be openable.
        cell: the cell the probe sends in; keep it apart from a live cell (no service of a
            live cell sees the probe's messages there).

    Returns: per role, what it tried and what got through (`forged_delivered` must be 0,
    `allowed_*` 0 too, or the router denies more than the roles allow).

    Raises:
        TimeoutError: the allowed traffic did not get through within SETTLE_TIMEOUT_S (a
            router without these roles, or one that denies more).
    """
    root = f"robonav/{cell}"
    results = {role: RoleProbe(role) for role in roles}
    inbox = _Inbox()
    # The probing sessions, and apart from them (a session delivers its own messages to itself,
    # without the router) an observer and the real owners of the request keys.
    logins = [(role, role) for role in roles] + [("observer", "viewer")] + [(f"owner:{o}", o) for o in SERVES]
    with _sessions(open_role, logins) as sessions, ExitStack() as declared:
        observer = sessions["observer"]
        declared.callback(observer.declare_subscriber(f"{root}/**", lambda s: inbox.add(s.payload.to_bytes())).undeclare)
        # The real owner of every request key answers with a marker of the key.
        for owner, keys in SERVES.items():
            for key in keys:
                answer = f"answer:{key}".encode()
                queryable = sessions[f"owner:{owner}"].declare_queryable(
                    f"{root}/{key}", lambda q, answer=answer: q.reply(q.key_expr, answer))
                declared.callback(queryable.undeclare)
        # Impersonations: every role serves every request key it does not own, and holds the
        # liveliness tokens of the services it is not.
        for role in roles:
            for key in all_served():
                if key not in SERVES.get(role, ()):
                    forged = f"forged:{role}:{key}".encode()
                    queryable = sessions[role].declare_queryable(
                        f"{root}/{key}", lambda q, forged=forged: q.reply(q.key_expr, forged))
                    declared.callback(queryable.undeclare)
                    results[role].impersonations_tried += 1
            for service in ALIVE.values():
                token_key = f"{root}/alive/{service}/forged-by-{role}"
                if ALIVE.get(role) != service:
                    declared.callback(sessions[role].liveliness().declare_token(token_key).undeclare)
                    results[role].tokens_forged += 1
                else:
                    declared.callback(sessions[role].liveliness().declare_token(token_key).undeclare)
        _settle(sessions, root, inbox)

        # Puts: each role publishes on every key; a fence put after them (roles that may publish)
        # arrives after anything sent before it.
        for role in roles:
            for key in all_published():
                sessions[role].put(f"{root}/{key}", f"put:{role}:{key}".encode())
                results[role].puts_tried += 1
                results[role].puts_forbidden += key not in PUBLISHES.get(role, ())
            if role in PUBLISHES:
                sessions[role].put(f"{root}/{PUBLISHES[role][0]}", f"fence:{role}".encode())
        # Queries: all at once, each ends with its answer or at the timeout.
        pending = []
        for role in roles:
            for key in all_served():
                marker = f"ask:{role}:{key}".encode()
                pending.append((role, key, sessions[role].get(f"{root}/{key}", payload=marker, timeout=QUERY_TIMEOUT_S,
                                                             target=zenoh.QueryTarget.ALL,
                                                             consolidation=zenoh.ConsolidationMode.NONE)))
        impersonation_replies: set[bytes] = set()
        for role, key, replies in pending:
            probe = results[role]
            probe.queries_tried += 1
            allowed = key in ASKS.get(role, ())
            probe.queries_forbidden += not allowed
            answer = f"answer:{key}".encode()
            answered = False
            for reply in replies:
                sample = reply.ok if reply.ok is not None else reply.err
                payload = sample.payload.to_bytes() if sample is not None else b""
                answered |= payload == answer
                if payload.startswith(b"forged:") and not payload.startswith(f"forged:{role}:".encode()):
                    impersonation_replies.add(payload)  # (a session's own queryable answers it locally)
            if answered and not allowed:
                probe.forbidden_queries_answered += 1
                probe.leaks.append(f"query {key}")
            if allowed and not answered:
                probe.allowed_queries_unanswered += 1
        _wait(lambda: all(inbox.has(f"fence:{role}".encode()) for role in roles if role in PUBLISHES), SETTLE_TIMEOUT_S)
        time.sleep(GRACE_S)
        for role in roles:
            probe = results[role]
            for key in all_published():
                delivered = inbox.has(f"put:{role}:{key}".encode())
                if key in PUBLISHES.get(role, ()):
                    probe.allowed_puts_missing += not delivered
                elif delivered:
                    probe.forbidden_puts_delivered += 1
                    probe.leaks.append(f"put {key}")
            for payload in impersonation_replies:
                _, forger, key = payload.decode().split(":", 2)
                if forger == role:
                    probe.impersonations_answered += 1
                    probe.leaks.append(f"serve {key}")
        seen_tokens = {str(r.ok.key_expr) for r in observer.liveliness().get(f"{root}/alive/**", timeout=QUERY_TIMEOUT_S)
                       if r.ok is not None}
        for role in roles:
            for service in ALIVE.values():
                if ALIVE.get(role) != service and f"{root}/alive/{service}/forged-by-{role}" in seen_tokens:
                    results[role].forged_tokens_seen += 1
                    results[role].leaks.append(f"token alive/{service}")
    return results


def _settle(sessions: dict[str, zenoh.Session], root: str, inbox: _Inbox) -> None:
    """Wait until declarations reached the router: the owners' puts and the operator's asks get through."""
    deadline = time.monotonic() + SETTLE_TIMEOUT_S
    for role, keys in PUBLISHES.items():
        if role not in sessions:
            continue
        marker = f"settle:{role}".encode()
        while not inbox.has(marker):
            if time.monotonic() > deadline:
                raise TimeoutError(f"{role}'s puts on {root}/{keys[0]} reach no subscriber: the router denies more "
                                   "than the roles allow, or the probe's subscriber was not declared")
            sessions[role].put(f"{root}/{keys[0]}", marker)
            time.sleep(0.05)
    asker = "operator" if "operator" in sessions else None
    if asker is None:
        return
    for key in ASKS["operator"]:
        owner = next(role for role, keys in SERVES.items() if key in keys)
        while not _answered(sessions[asker].get(f"{root}/{key}", timeout=0.5), f"answer:{key}".encode()):
            if time.monotonic() > deadline:
                raise TimeoutError(f"the operator's query on {root}/{key} gets no answer from {owner}")


def logins(security_dir: str | Path, endpoint: str) -> Callable[[str], zenoh.Session]:
    """`open_role` for `probe_roles`: sessions to `endpoint` with `client-<role>.json5` of
    `security_dir`, either a cell from `setup_cell.sh` (`<role>/client-<role>.json5`) or one
    directory holding every client file (a copy of configs/security with `certs/`).

    Example, against a router running router-acl.json5:
        results = probe_roles(logins("cell/security", "tls/localhost:7447"))
        assert forged_delivered(results) == 0
    """
    root = Path(security_dir)

    def open_role(role: str) -> zenoh.Session:
        directory = root / role if (root / role / f"client-{role}.json5").is_file() else root
        with contextlib.chdir(directory):  # the client files name their certificates relatively
            return zenoh.open(to_zenoh_config(ZenohConfig(connect=(endpoint,), config_file=f"client-{role}.json5")))

    return open_role


def forged_delivered(results: dict[str, RoleProbe]) -> int:
    """Forbidden messages of every role that got through (0 on a router enforcing the roles)."""
    return sum(probe.forged_delivered for probe in results.values())
