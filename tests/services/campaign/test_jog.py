"""The campaign's last-resort jog home: it goes on from where a stop left the arm.

The client here stands in for the bus (a unit test of the jog's retries); the live services'
side of the same motions is covered by the campaign runs in `test_run.py` and the executor's
own tests."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from robonav.pipeline.wire.messages import ErrorReply, ExecuteResponse
from robonav.services.campaign.jog import jog
from robonav.services.campaign.scene import HOME_TOLERANCE_RAD, RETRYABLE

HOME = np.zeros(3)
NOT_CONTINUOUS = np.zeros(3, dtype=bool)


@dataclass
class State:
    position: np.ndarray


@dataclass
class Arm:
    """Executes each jog to the share of the way `reach` says (1.0: all of it), or refuses with
    `refusals` first; records what it was asked."""

    reach: list[float]
    refusals: list[str] = field(default_factory=list)
    joint_state: State = field(default_factory=lambda: State(np.array([1.0, -0.5, 0.25])))
    paths: list[np.ndarray] = field(default_factory=list)
    ids: list[str] = field(default_factory=list)
    outcome: str = ""

    def execute(self, path: np.ndarray, *, trajectory_id: str) -> ExecuteResponse | ErrorReply:
        self.paths.append(path)
        self.ids.append(trajectory_id)
        if self.refusals:
            return ErrorReply(code=self.refusals.pop(0), message="refused")
        share = self.reach.pop(0)
        self.joint_state = State(path[0] + share * (path[-1] - path[0]))
        self.outcome = "succeeded" if share == 1.0 else "error"
        return ExecuteResponse(trajectory_id=trajectory_id, duration_s=1.0, waypoint_count=len(path))

    def wait_for_trajectory(self, trajectory_id: str, timeout_s: float) -> str:
        return self.outcome

    def wait_for(self, predicate, timeout_s: float) -> bool:  # noqa: ANN001 - any zero-arg callable
        return bool(predicate())


def run(arm: Arm, attempts: int = 4) -> tuple[bool, int]:
    settles = []
    reached = jog(arm, HOME, NOT_CONTINUOUS, trajectory_id="reset-1", timeout_s=1.0,
                  settle=lambda: settles.append(1), tolerance_rad=HOME_TOLERANCE_RAD,
                  retryable=RETRYABLE, attempts=attempts)
    return reached, len(settles)


def test_a_jog_stopped_short_goes_on_from_where_the_arm_stopped() -> None:
    arm = Arm(reach=[0.4, 1.0])  # the first motion stops on a stale map, 40 % of the way
    reached, settles = run(arm)
    assert reached and settles == 1
    assert len(arm.paths) == 2 and arm.ids == ["reset-1-0", "reset-1-1"]
    np.testing.assert_allclose(arm.paths[1][0], 0.6 * np.array([1.0, -0.5, 0.25]))  # from where it stopped
    np.testing.assert_allclose(arm.paths[1][-1], HOME)
    assert np.max(np.abs(arm.joint_state.position - HOME)) <= HOME_TOLERANCE_RAD


def test_a_jog_refused_for_a_stale_map_tries_again_and_one_refused_for_good_does_not() -> None:
    reached, settles = run(Arm(reach=[1.0], refusals=["OCCUPANCY_STALE"]))
    assert reached and settles == 1
    arm = Arm(reach=[1.0], refusals=["OUT_OF_JOINT_LIMITS"])
    assert run(arm) == (False, 0) and len(arm.paths) == 1


def test_a_jog_that_never_arrives_gives_up_after_its_attempts() -> None:
    arm = Arm(reach=[0.5, 0.5, 0.5])
    assert run(arm, attempts=3) == (False, 2)
    assert len(arm.paths) == 3


def test_an_arm_already_home_is_not_moved() -> None:
    arm = Arm(reach=[], joint_state=State(HOME + 0.01))
    assert run(arm) == (True, 0) and arm.paths == []
