"""Several OMPL planners on one query at once, each in a forked process; the first exact
solution wins (the `auto` planner's race, `MotionPlanner._auto`)."""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import time
from collections.abc import Sequence
from typing import Any

from robonav.pipeline.planning.ompl_planners import OmplSpace
from robonav.pipeline.planning.result import PlanResult, PlanStatus
from robonav.pipeline.types import FloatArray


def race(
    space: OmplSpace,
    planner_ids: Sequence[str],
    start_rad: FloatArray,
    goals_rad: FloatArray,
    *,
    time_limit_s: float,
) -> tuple[str, PlanResult]:
    """Run several planners at once on the same query, one forked process each; the first
    exact solution wins and the other processes are killed.

    Processes, not threads: OMPL's Python bindings hold the GIL for the whole `solve`, so
    threads would take turns rather than run side by side (and a second thread starting
    while the first is inside `solve` was seen to deadlock). A forked child shares the
    parent's collision world copy-on-write and costs a few milliseconds to start. Where
    `fork` is unavailable the planners run one after another.

    Returns:
        The winning planner id and its result; when every planner failed, the first id and
        its TIMEOUT result.
    """
    if not planner_ids:
        raise ValueError("race needs at least one planner_id")
    t0 = time.perf_counter()
    if "fork" not in multiprocessing.get_all_start_methods():
        for planner_id in planner_ids:
            result = space.solve(planner_id, start_rad, goals_rad, time_limit_s=time_limit_s)
            if result.success:
                return planner_id, result
        return planner_ids[0], PlanResult(PlanStatus.TIMEOUT, None, "race: no planner solved it", time.perf_counter() - t0)
    context = multiprocessing.get_context("fork")
    children: dict[Any, tuple[str, Any]] = {}
    for planner_id in planner_ids:
        receiver, sender = context.Pipe(duplex=False)
        process = context.Process(target=_race_child, args=(space, planner_id, start_rad, goals_rad, time_limit_s, sender),
                                  daemon=True, name=f"plan-{planner_id}")
        process.start()
        sender.close()
        children[receiver] = (planner_id, process)
    results: dict[str, PlanResult] = {}
    winner: str | None = None
    deadline = time.monotonic() + time_limit_s + 5.0  # a child that hangs past its budget is abandoned
    pending = set(children)
    while pending and winner is None:
        ready = multiprocessing.connection.wait(list(pending), timeout=max(deadline - time.monotonic(), 0.0))
        if not ready:
            break
        for receiver in ready:
            pending.discard(receiver)
            planner_id = children[receiver][0]
            try:
                status, path, detail = receiver.recv()
            except (EOFError, OSError):
                status, path, detail = PlanStatus.TIMEOUT.value, None, f"{planner_id}: the planning process died"
            results[planner_id] = PlanResult(PlanStatus(status), path, detail, time.perf_counter() - t0)
            if results[planner_id].success and winner is None:
                winner = planner_id
    for receiver, (_, process) in children.items():
        if process.is_alive():
            process.kill()
        process.join(timeout=1.0)
        receiver.close()
    elapsed = time.perf_counter() - t0
    if winner is not None:
        result = results[winner]
        return winner, PlanResult(result.status, result.path, result.detail, elapsed)
    first = results.get(planner_ids[0])
    detail = "; ".join(r.detail for r in results.values()) or "race: no planner answered"
    return planner_ids[0], PlanResult(first.status if first else PlanStatus.TIMEOUT, None, detail, elapsed)


def _race_child(space: OmplSpace, planner_id: str, start_rad: FloatArray, goals_rad: FloatArray,
                time_limit_s: float, sender: Any) -> None:
    try:
        result = space.solve(planner_id, start_rad, goals_rad, time_limit_s=time_limit_s)
        sender.send((result.status.value, result.path, result.detail))
    except Exception as exc:  # reported to the parent as this planner's failure
        sender.send((PlanStatus.TIMEOUT.value, None, f"{planner_id}: {type(exc).__name__}: {exc}"))
    finally:
        sender.close()
