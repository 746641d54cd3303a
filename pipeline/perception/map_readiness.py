"""When an occupancy map may be planned or executed on: present, fresh by its own stamp, complete.

An empty map is not free space. Right after `perception/clear` or a perception (re)start the map
holds nothing, and a planner that took it at its word would plan through every obstacle. So a
map says how many frames each camera has integrated since the last clear or start
(`Occupancy.camera_frames`), and a map counts as complete once every configured camera has
contributed `min_frames`. Freshness is the map's stamp (its newest frame) against the checking
side's clock, not the moment it arrived: a map re-sent or replayed late is still old.

The planner and the executor apply the same rule (`occupancy_problem`); clients that clear the
map wait with `map_complete` before they plan.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from robonav.pipeline.wire.codec import ProtocolError
from robonav.pipeline.wire.codes import ErrorCode


def missing_frames(camera_frames: Mapping[str, int] | None, cameras: Sequence[str], min_frames: int) -> dict[str, int]:
    """Camera id -> frames it still owes, for every camera of `cameras` with fewer than `min_frames`.

    A map without `camera_frames` (a producer older than the field) owes nothing: it cannot
    say, and it was accepted before the field existed.
    """
    if camera_frames is None:
        return {}
    return {camera: min_frames - camera_frames.get(camera, 0) for camera in cameras
            if camera_frames.get(camera, 0) < min_frames}


def map_complete(camera_frames: Mapping[str, int] | None, cameras: Sequence[str], min_frames: int) -> bool:
    """Whether every camera of `cameras` has integrated at least `min_frames` frames into the map."""
    return not missing_frames(camera_frames, cameras, min_frames)


def occupancy_problem(stamp: float | None, camera_frames: Mapping[str, int] | None, *, now_s: float,
                      max_age_s: float, cameras: Sequence[str], min_frames: int) -> ProtocolError | None:
    """Why a map must not be planned or executed on, or None.

    Args:
        stamp: The map's stamp (its newest frame) [s, Unix], or None when no map arrived.
        camera_frames: Frames per camera since the last clear or start (`Occupancy.camera_frames`).
        now_s: The checking side's wall clock [s, Unix].
        max_age_s: Oldest acceptable map, either way from `now_s` [s]: a map stamped further in
            the future comes from a clock that cannot be compared.
        cameras: Every configured camera id.
        min_frames: Frames each camera must have contributed; 0 checks nothing.

    Returns:
        OCCUPANCY_MISSING, OCCUPANCY_STALE (`details.age_s`) or OCCUPANCY_INCOMPLETE
        (`details.camera_frames`, `details.required_frames`, `details.missing`), or None.
    """
    if stamp is None:
        return ProtocolError(ErrorCode.OCCUPANCY_MISSING, "no occupancy map received yet")
    age_s = now_s - stamp
    if abs(age_s) > max_age_s:
        when = f"{age_s:.1f} s old" if age_s > 0 else f"stamped {-age_s:.1f} s in the future"
        return ProtocolError(ErrorCode.OCCUPANCY_STALE,
                             f"newest occupancy map is {when} (limit {max_age_s} s): perception is not mapping, "
                             "or the clocks disagree", {"age_s": age_s})
    missing = missing_frames(camera_frames, cameras, min_frames)
    if missing:
        have = dict(camera_frames or {})
        return ProtocolError(ErrorCode.OCCUPANCY_INCOMPLETE,
                             f"the occupancy map is still being built after a clear or a perception start: cameras "
                             f"{sorted(missing)} have integrated {[have.get(c, 0) for c in sorted(missing)]} of "
                             f"{min_frames} frames; retry shortly",
                             {"camera_frames": have, "required_frames": min_frames, "missing": sorted(missing)})
    return None
