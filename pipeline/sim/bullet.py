"""pybullet, imported without the build banner its C module writes to stderr.

Every process that loads pybullet (the sim, each render worker, benchmarks, calibration) would
start with "pybullet build time: ..." on the console, which tells a user nothing. The banner is
written by the extension's initialisation, so the only way to keep it off the console is to
point file descriptor 2 elsewhere while the module loads (for a few milliseconds, once per
process; another thread's stderr output in that window would be lost too).
"""

from __future__ import annotations

import os
import sys
from types import ModuleType


def _import_quietly() -> ModuleType:
    if "pybullet" in sys.modules:
        return sys.modules["pybullet"]
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        import pybullet
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)
    return pybullet


pybullet = _import_quietly()
