"""Recording tests' bus: a router on a free port and client sessions through it."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest
import zenoh

from robonav.services.common import open_session
from robonav.services.config import ZenohConfig

from ..conftest import free_port


@pytest.fixture
def endpoint() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohConfig(mode="router", listen=(endpoint,)))
    yield endpoint
    router.close()


@pytest.fixture
def sessions(endpoint: str) -> Iterator[Callable[[], zenoh.Session]]:
    opened: list[zenoh.Session] = []

    def new_session() -> zenoh.Session:
        opened.append(open_session(ZenohConfig(mode="client", connect=(endpoint,))))
        return opened[-1]

    yield new_session
    for s in opened:
        s.close()
