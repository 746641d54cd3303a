"""Stamp rules for perception's inputs: one `StampOrder` per camera and one for the joint states.

Perception keeps each source's samples in stamp order (a frame must be newer than its camera's
last one; the joint history must stay sorted to be searched). Left at that, one odd stamp wedges
a source: a joint state stamped in the future made every later one "out of order", and a camera
whose clock was reset (or a replay that loops) was dropped until its clock caught up again. The
rules, judged against the receiver's clock:

- a stamp more than `future_stamp_tolerance_s` ahead of the receiver's clock is dropped
  (`future_stamp`), so it never becomes the reference;
- a stamp not newer than the source's last, by at most `stamp_jump_back_s`, is out of order
  (`out_of_order`);
- a stamp further back is either a stray (dropped, `jumped_back`) or a restarted source: after
  `STAMP_RESTART_SAMPLES` such stamps in a row, each newer than the one before, the source counts
  as restarted and its stamps start over from there (`restart`). Strays interleaved with a good
  stream never reach that count, so they cannot reset it.

Stamps long ago are fine in themselves (a replayed recording): only their order counts.
"""

from __future__ import annotations

import math

STAMP_RESTART_SAMPLES = 3
"""Consecutive samples jumped back, in order among themselves, that show a source restarted."""

OK = "ok"
RESTART = "restart"


class StampOrder:
    """The order rules for one source; not thread-safe (the caller holds its own lock)."""

    def __init__(self, future_tolerance_s: float, jump_back_s: float, *, allow_equal: bool = False) -> None:
        """Args: allow_equal: a stamp equal to the last one is in order (joint states published twice
        at one moment); for camera frames it is a repeat, out of order."""
        self.future_tolerance_s = future_tolerance_s
        self.jump_back_s = jump_back_s
        self.allow_equal = allow_equal
        self.last: float | None = None
        """The newest accepted stamp [s]."""
        self._behind: list[float] = []
        """Stamps in a row that jumped back, each newer than the one before."""

    def judge(self, stamp: float, now_s: float) -> str:
        """`OK` (in order; it becomes the last), `RESTART` (the source restarted: it is the new last,
        older history no longer applies), or the reason to drop it: `bad_stamp`, `future_stamp`,
        `out_of_order`, `jumped_back`."""
        if not math.isfinite(stamp):
            return "bad_stamp"
        if stamp > now_s + self.future_tolerance_s:
            return "future_stamp"
        if self.last is None or stamp > self.last or (self.allow_equal and stamp == self.last):
            self.last = stamp
            self._behind.clear()
            return OK
        if self.last - stamp <= self.jump_back_s:
            self._behind.clear()
            return "out_of_order"
        if self._behind and stamp <= self._behind[-1]:
            self._behind.clear()
        self._behind.append(stamp)
        if len(self._behind) < STAMP_RESTART_SAMPLES:
            return "jumped_back"
        self.last = stamp
        self._behind.clear()
        return RESTART

    def reset(self) -> None:
        self.last = None
        self._behind.clear()
