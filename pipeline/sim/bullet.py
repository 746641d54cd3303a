"""pybullet, imported without the build banner its C module writes to stderr, and a way to keep
its C code's other chatter off the console.

Every process that loads pybullet (the sim, each render worker, benchmarks, calibration) would
start with "pybullet build time: ..." on the console, which tells a user nothing. The banner is
written by the extension's initialisation, so the only way to keep it off the console is to
point file descriptor 2 elsewhere while the module loads (for a few milliseconds, once per
process; another thread's stderr output in that window would be lost too).
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from types import ModuleType


@contextlib.contextmanager
def quiet_native_output(fds: tuple[int, ...] = (1, 2)) -> Iterator[None]:
    """Point the file descriptors `fds` at /dev/null while the block runs: what pybullet's C
    code prints there (the build banner, URDF importer warnings such as "No inertial data for
    link", which the sim answers with a unit mass) tells a user nothing. Another thread's output
    to them in that window is lost too, so keep the block short."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(fd) for fd in fds]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in fds:
            os.dup2(devnull, fd)
        yield
    finally:
        for fd, old in zip(fds, saved):
            os.dup2(old, fd)
            os.close(old)
        os.close(devnull)


def _import_quietly() -> ModuleType:
    if "pybullet" in sys.modules:
        return sys.modules["pybullet"]
    with quiet_native_output((2,)):
        import pybullet
    return pybullet


pybullet = _import_quietly()
