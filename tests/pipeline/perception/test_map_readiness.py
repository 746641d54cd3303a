"""When a map may be planned on: present, fresh by its stamp, complete after a clear."""

from __future__ import annotations

from robonav.pipeline.perception.map_readiness import map_complete, missing_frames, occupancy_problem
from robonav.pipeline.wire.codes import ErrorCode

CAMERAS = ("front", "back")


def _problem(stamp: float | None, frames: dict[str, int] | None, now_s: float = 100.0):  # noqa: ANN202
    return occupancy_problem(stamp, frames, now_s=now_s, max_age_s=2.0, cameras=CAMERAS, min_frames=3)


def test_no_map_is_missing() -> None:
    problem = _problem(None, None)
    assert problem is not None and problem.code is ErrorCode.OCCUPANCY_MISSING


def test_age_is_the_stamp_against_the_clock_either_way() -> None:
    old = _problem(97.5, {"front": 3, "back": 3})
    assert old is not None and old.code is ErrorCode.OCCUPANCY_STALE and old.details["age_s"] == 2.5
    future = _problem(102.5, {"front": 3, "back": 3})
    assert future is not None and future.code is ErrorCode.OCCUPANCY_STALE and "future" in future.message
    assert _problem(98.5, {"front": 3, "back": 3}) is None


def test_every_configured_camera_must_have_its_frames() -> None:
    problem = _problem(100.0, {"front": 5, "back": 1})
    assert problem is not None and problem.code is ErrorCode.OCCUPANCY_INCOMPLETE
    assert problem.details == {"camera_frames": {"front": 5, "back": 1}, "required_frames": 3, "missing": ["back"]}
    assert missing_frames({"front": 5}, CAMERAS, 3) == {"back": 3}  # a camera the map does not list owes all
    assert not map_complete({"front": 3, "back": 2, "other": 9}, CAMERAS, 3)
    assert map_complete({"front": 3, "back": 3}, CAMERAS, 3)
    assert map_complete({"front": 0, "back": 0}, CAMERAS, 0)


def test_a_map_from_an_older_producer_is_taken_as_complete() -> None:
    assert map_complete(None, CAMERAS, 3) and _problem(100.0, None) is None
