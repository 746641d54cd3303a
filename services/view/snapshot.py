"""`robonav view --snapshot` and `robonav demo --snapshot`: a picture of the view for people without a browser."""

from __future__ import annotations

import logging
import time
from pathlib import Path

from robonav.services.common import open_session
from robonav.services.config import RobonavConfig
from robonav.services.keys import Keys
from robonav.services.view.app import ViewNode, ViewOptions
from robonav.services.view.browser import BrowserUnavailable, capture_page

log = logging.getLogger("robonav.view")


class NoJointState(RuntimeError):
    """A snapshot found no robot to draw."""


def write_snapshot(node: ViewNode, out_path: Path, *, wait_s: float, width: int = 1280, height: int = 800) -> list[str]:
    """Wait up to `wait_s` for data, then render the page headless and write a PNG.

    Returns the layers that had no data yet (the picture is taken anyway).

    Raises:
        NoJointState: no joint state arrived within `wait_s`.
        BrowserUnavailable: Chromium or Playwright is missing.
    """
    if not node.wait_until(lambda: node.stats.robot_updates > 0, wait_s):
        raise NoJointState(f"no joint state on {Keys(node.cfg.cell).joint_states} within {wait_s:.0f} s: is the stack up?")
    node.wait_until(lambda: node.stats.maps_drawn > 0 and node.drawn_cameras >= set(node.cameras), wait_s)
    missing = ([] if node.stats.maps_drawn else ["occupancy"]) + sorted(set(node.cameras) - node.drawn_cameras)
    if node.stats.paths_drawn == 0:
        missing.append("path")
    # Freeze the scene: a live cloud redrawn five times a second would never give two equal pictures.
    time.sleep(2.0 / node.options.rate_hz)
    node.paused.set()
    try:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_bytes(capture_page(node.url, width=width, height=height))
    finally:
        node.paused.clear()
    return missing


def snapshot_view(cfg: RobonavConfig, out_path: Path, *, wait_s: float = 20.0) -> dict[str, object]:
    """Start a view on a free port, write a PNG of it to `out_path`, stop it (for `robonav demo --snapshot`).

    Returns summary entries: `snapshot` (the path) and `snapshot_missing` (layers without data),
    or `snapshot_error` when no picture could be written.
    """
    try:
        with open_session(cfg.zenoh) as session:
            node = ViewNode(cfg, session, ViewOptions(port=0))
            try:
                node.start()
                missing = write_snapshot(node, out_path, wait_s=wait_s)
            finally:
                node.close()
    except Exception as exc:  # a missing picture is reported in the summary; the demo's own result stands
        kind = "" if isinstance(exc, (BrowserUnavailable, NoJointState)) else f"{type(exc).__name__}: "
        log.error("snapshot: %s%s", kind, exc)
        return {"snapshot_error": f"{kind}{exc}"}
    return {"snapshot": str(out_path), "snapshot_missing": missing}


def run_snapshot(node: ViewNode, out_path: Path, wait_s: float, width: int, height: int) -> int:
    """`robonav view --snapshot`: write the picture; exit code 0, or 1 with the reason logged."""
    try:
        missing = write_snapshot(node, out_path, wait_s=wait_s, width=width, height=height)
    except (NoJointState, BrowserUnavailable) as exc:
        log.error("snapshot: %s", exc)
        return 1
    except Exception as exc:  # e.g. the browser timed out: say so and fail, do not crash with a trace
        log.error("snapshot: %s: %s", type(exc).__name__, exc)
        return 1
    if missing:
        log.warning("snapshot: nothing received yet for %s", ", ".join(missing))
    log.info("snapshot: wrote %s", out_path)
    return 0
