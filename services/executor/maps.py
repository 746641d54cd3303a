"""The occupancy maps the executor receives: the newest for checking an execute, the last two for settling."""

from __future__ import annotations

import threading

import zenoh

from robonav.pipeline.wire.messages import Occupancy


class MapFeed:
    """Decodes every `perception/occupancy` sample once and keeps the two newest."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._maps: list[Occupancy] = []
        """The two newest maps, oldest first."""
        self._arrived = threading.Condition(self._lock)
        self.wake = threading.Event()
        """Set on every new map, for the path monitor's thread (it clears it)."""

    def on_occupancy(self, sample: zenoh.Sample) -> None:
        """Subscriber callback; wrap it in `guarded_subscriber` (a bad map raises and is counted)."""
        occupancy = Occupancy.from_wire(sample.payload.to_bytes())
        with self._arrived:
            self._maps = [*self._maps[-1:], occupancy]
            self._arrived.notify_all()
        self.wake.set()

    def newest(self) -> Occupancy | None:
        with self._lock:
            return self._maps[-1] if self._maps else None

    def two_newest(self) -> list[Occupancy]:
        """The newest map and the one before it (oldest first), as far as received."""
        with self._lock:
            return list(self._maps)

    def wait_newer(self, than: Occupancy | None, timeout_s: float) -> Occupancy | None:
        """The newest map once it is not `than`, or the newest at the timeout."""
        with self._arrived:
            self._arrived.wait_for(lambda: bool(self._maps) and self._maps[-1] is not than, timeout=timeout_s)
            return self._maps[-1] if self._maps else None
