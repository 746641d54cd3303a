"""`robonav view bench`: how the view holds up under a 30 Hz 640x480 cloud stream.

Runs a Zenoh router, a view and a publisher in this process and the page in headless
Chromium, drags the camera around the whole time (so the browser renders continuously, as
when someone looks around), and measures two phases: joint states only, then joint states
plus the cloud stream. Per phase: frames the browser rendered per second, the page's
animation-frame rate, websocket messages and bytes per second to the browser, clouds
published and drawn per second, and the view's time per drawn cloud.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import multiprocessing
import socket
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from robonav.pipeline.camera import CameraConfig
from robonav.pipeline.perception.depth import points_from_depth
from robonav.pipeline.wire.messages import JointState, PointCloud
from robonav.services.common import add_logging_arguments, open_session, setup_logging
from robonav.services.config import ZenohConfig, load_config
from robonav.services.keys import Keys
from robonav.services.view.app import ViewNode, ViewOptions
from robonav.services.view.browser import open_page, page_url
from robonav.services.view.scene import cameras_of

log = logging.getLogger("robonav.view.bench")

COUNTERS_JS = """() => {
  const counters = {raf: 0, renders: 0, lastFrame: -1};
  window.__robonavCounters = counters;
  (function tick() { counters.raf++; requestAnimationFrame(tick); })();
  // three.js clears the canvas once per rendered frame: a frame with a clear was rendered.
  for (const proto of [WebGL2RenderingContext.prototype, WebGLRenderingContext.prototype]) {
    const clear = proto.clear;
    proto.clear = function (mask) {
      if (counters.lastFrame !== counters.raf) { counters.lastFrame = counters.raf; counters.renders++; }
      return clear.call(this, mask);
    };
  }
}"""


def synthetic_frame(camera: CameraConfig) -> np.ndarray:
    """A full 640x480 depth frame as points (every pixel valid): a floor with a box on it."""
    intrinsics = camera.intrinsics
    rows, cols = np.mgrid[0:intrinsics.height, 0:intrinsics.width].astype(np.float64)
    depth_m = 1.0 + 0.002 * rows
    box = (np.abs(cols - intrinsics.width / 2) < 80) & (np.abs(rows - intrinsics.height / 2) < 60)
    depth_m[box] -= 0.3
    return points_from_depth(depth_m, intrinsics).astype(np.float32)


def _publish(endpoint: str, cell: str, names: tuple[str, ...], home: np.ndarray, camera: CameraConfig,
             cloud_hz: float, clouds_on: Any, stop: Any, published: Any) -> None:
    """The publisher process: joint states at 100 Hz (a slowly turning first joint) and, while
    `clouds_on` is set, full frames at `cloud_hz` on an absolute schedule."""
    keys = Keys(cell)
    points = synthetic_frame(camera)
    with open_session(ZenohConfig(connect=(endpoint,))) as session:
        def joint_states() -> None:
            publisher = session.declare_publisher(keys.joint_states)
            started = time.monotonic()
            while not stop.wait(0.01):
                q = home.copy()
                q[0] += 0.5 * math.sin(0.5 * (time.monotonic() - started))
                publisher.put(JointState(stamp=time.time(), names=names, position=q, velocity=np.zeros_like(q)).to_wire())

        thread = threading.Thread(target=joint_states, daemon=True)
        thread.start()
        publisher = session.declare_publisher(keys.camera_cloud(camera.camera_id))
        next_s = time.monotonic()
        while not stop.is_set():
            if not clouds_on.wait(0.1):
                next_s = time.monotonic()
                continue
            with published.get_lock():
                published.value += 1
            publisher.put(PointCloud(stamp=time.time(), camera_id=camera.camera_id, points=points,
                                     seq=published.value).to_wire())
            next_s += 1.0 / cloud_hz
            stop.wait(max(0.0, next_s - time.monotonic()))
        thread.join()


class Publisher:
    """`_publish` in its own process, so encoding 3.7 MB frames does not take the view's GIL."""

    def __init__(self, endpoint: str, cell: str, names: tuple[str, ...], home: np.ndarray, camera: CameraConfig,
                 cloud_hz: float) -> None:
        context = multiprocessing.get_context("spawn")
        self.clouds_on = context.Event()
        self._stop = context.Event()
        self._published = context.Value("i", 0)
        self._process = context.Process(target=_publish, daemon=True, args=(
            endpoint, cell, names, home, camera, cloud_hz, self.clouds_on, self._stop, self._published))
        self._process.start()

    @property
    def clouds_published(self) -> int:
        return int(self._published.value)

    def close(self) -> None:
        self._stop.set()
        self._process.join(timeout=10.0)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()


def measure_phase(page: Any, node: ViewNode, publisher: Publisher, ws: dict[str, float], seconds: float) -> dict[str, Any]:
    """Drag the camera for `seconds` and return rates over that time."""
    box = page.locator("canvas").first.bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    read = "() => ({...window.__robonavCounters, now_ms: performance.now()})"
    before = page.evaluate(read)
    stats0, ws0, published0 = dataclasses.replace(node.stats), dict(ws), publisher.clouds_published
    started = time.monotonic()
    page.mouse.move(cx, cy)
    page.mouse.down()
    step = 0
    while (elapsed := time.monotonic() - started) < seconds:
        step += 1
        page.mouse.move(cx + 120 * math.sin(step / 20), cy + 30 * math.sin(step / 33))
        page.wait_for_timeout(15)
    stats, ws1, published1 = dataclasses.replace(node.stats), dict(ws), publisher.clouds_published
    after = page.evaluate(read)
    page.mouse.up()
    browser_s = (after["now_ms"] - before["now_ms"]) / 1e3
    drawn = stats.clouds_drawn - stats0.clouds_drawn
    return {
        "seconds": round(elapsed, 2),
        "browser_rendered_fps": round((after["renders"] - before["renders"]) / browser_s, 1),
        "browser_animation_frames_per_s": round((after["raf"] - before["raf"]) / browser_s, 1),
        "websocket_messages_per_s": round((ws1["messages"] - ws0["messages"]) / elapsed, 1),
        "websocket_mb_per_s": round((ws1["bytes"] - ws0["bytes"]) / elapsed / 1e6, 3),
        "clouds_published_per_s": round((published1 - published0) / elapsed, 1),
        "clouds_drawn_per_s": round(drawn / elapsed, 2),
        "points_sent_per_cloud": round((stats.cloud_points_sent - stats0.cloud_points_sent) / drawn) if drawn else 0,
        "view_ms_per_cloud": round((stats.cloud_draw_s - stats0.cloud_draw_s) / drawn * 1e3, 2) if drawn else None,
        "robot_updates_per_s": round((stats.robot_updates - stats0.robot_updates) / elapsed, 1),
    }


def run(seconds: float, cloud_hz: float, options: ViewOptions, width: int, height: int) -> dict[str, Any]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    base = load_config()
    cfg = dataclasses.replace(base, zenoh=ZenohConfig(connect=(endpoint,)))
    camera = cameras_of(cfg)[0]
    ws = {"messages": 0.0, "bytes": 0.0}

    def count_frame(payload: Any) -> None:
        ws["messages"] += 1
        ws["bytes"] += len(payload)

    def listen(page: Any) -> None:
        page.on("websocket", lambda socket_: socket_.on("framereceived", count_frame))

    frame = synthetic_frame(camera)
    with open_session(ZenohConfig(mode="router", listen=(endpoint,))), open_session(cfg.zenoh) as view_session:
        node = ViewNode(cfg, view_session, options)
        node.start()
        publisher = Publisher(endpoint, cfg.cell, tuple(cfg.robot.joint_names), np.array(cfg.robot.home_position_rad),
                              camera, cloud_hz)
        try:
            with open_page(page_url(node.url), width=width, height=height, before_load=listen) as page:
                page.evaluate(COUNTERS_JS)
                page.wait_for_timeout(3000)  # the scene arrives and shaders compile
                idle = measure_phase(page, node, publisher, ws, seconds / 2)
                publisher.clouds_on.set()
                page.wait_for_timeout(1000)
                streaming = measure_phase(page, node, publisher, ws, seconds)
        finally:
            publisher.close()
            node.close()
    return {"cloud_hz": cloud_hz, "cloud_points_published": int(len(frame)), "cloud_mb_published": round(frame.nbytes / 1e6, 2),
            "view": {"cloud_rate_hz": options.cloud_rate_hz, "max_cloud_points": options.max_cloud_points},
            "page_px": [width, height], "joint_states_only": idle, "with_clouds": streaming}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="robonav view bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="length of the cloud phase (default %(default)s)")
    parser.add_argument("--cloud-hz", type=float, default=30.0, help="camera rate (default %(default)s)")
    parser.add_argument("--cloud-rate-hz", type=float, default=ViewOptions.cloud_rate_hz,
                        help="the view's cloud redraw limit (default %(default)s)")
    parser.add_argument("--max-cloud-points", type=int, default=ViewOptions.max_cloud_points,
                        help="the view's points per cloud (default %(default)s)")
    parser.add_argument("--size", default="1280x800", help="page size WIDTHxHEIGHT (default %(default)s)")
    parser.add_argument("--json", dest="json_path", help="also write the result to this file")
    add_logging_arguments(parser, "WARNING")
    args = parser.parse_args(argv)
    setup_logging(args.log_level, args.log_format)
    width, height = (int(v) for v in args.size.lower().split("x"))
    options = ViewOptions(port=0, cloud_rate_hz=args.cloud_rate_hz, max_cloud_points=args.max_cloud_points)
    result = run(args.seconds, args.cloud_hz, options, width, height)
    text = json.dumps(result, indent=2)
    print(text)
    if args.json_path:
        Path(args.json_path).write_text(text + "\n", encoding="utf-8")
    return 0
